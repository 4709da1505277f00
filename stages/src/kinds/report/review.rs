//! The report's review section: how well the review finds wrong labels (where there is GT),
//! the per-frame score and coverage along the sequence, the queue's first entries, and the
//! top regions as cropped pictures (RGB, ours, pseudo label, fixed field, the review).

use std::collections::HashMap;
use std::fmt::Write as _;

use arrow::array::{Array, Float64Array};
use arrow::datatypes::{Float64Type, UInt16Type, UInt32Type, UInt64Type, UInt8Type};
use arrow::record_batch::RecordBatch;

use crate::report::{png_data_uri, review_svg};
use crate::review::REASONS;
use crate::stage::{Inputs, Result, StageError};
use crate::{labels, tables};

/// The section, as HTML and as Markdown.
pub struct Section {
    pub html: String,
    pub md: String,
}

/// Colour of each reason code ([`REASONS`]) in the review pictures.
const REASON_COLOURS: [[u8; 3]; 7] = [
    [0, 0, 0],
    [255, 220, 0],
    [255, 128, 0],
    [230, 0, 230],
    [0, 220, 230],
    [40, 90, 255],
    [255, 0, 0],
];

/// The figures of the review against GT, as `evaluate` wrote them.
const FIGURES: &[(&str, &str, f64, usize)] = &[
    ("auroc", "AUROC", 1.0, 3),
    (
        "recall_5pct",
        "wrong pixels in the top 5 % (recall)",
        100.0,
        1,
    ),
    (
        "top20_precision",
        "top-20 regions mostly wrong (precision)",
        100.0,
        1,
    ),
    (
        "frame_rank_corr",
        "per-frame score vs error (Spearman)",
        1.0,
        2,
    ),
];

/// Rows of the `metrics` table of `panoptic_nerf` as a map.
fn review_metrics(t: &RecordBatch) -> Result<HashMap<String, f64>> {
    let method = tables::get_strings(t, "metrics", "method")?;
    let metric = tables::get_strings(t, "metrics", "metric")?;
    let value = t
        .column_by_name("value")
        .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
        .ok_or_else(|| StageError::Input("metrics.value is not float64".into()))?;
    Ok((0..t.num_rows())
        .filter(|&i| method.value(i) == "panoptic_nerf" && !value.is_null(i))
        .map(|i| (metric.value(i).to_string(), value.value(i)))
        .collect())
}

/// `w` x `h` RGB crop `[x0, x1) x [y0, y1)` of a row-major image with `channels` per pixel,
/// mapped to RGB by `colour`.
fn crop<T: Copy>(
    src: &[T],
    w: usize,
    (x0, y0, x1, y1): (usize, usize, usize, usize),
    channels: usize,
    colour: impl Fn(&[T]) -> [u8; 3],
) -> Vec<u8> {
    let mut out = Vec::with_capacity((x1 - x0) * (y1 - y0) * 3);
    for y in y0..y1 {
        for x in x0..x1 {
            let p = (y * w + x) * channels;
            out.extend(colour(&src[p..p + channels]));
        }
    }
    out
}

/// The review section, or `None` when the report has no `review` input.
pub fn review_section(inputs: &Inputs, zoom: u32, top: usize) -> Result<Option<Section>> {
    let Some(frames) = inputs.optional_table("review", "review_frames")? else {
        return Ok(None);
    };
    let (regions, queue) = (
        inputs.table("review", "review_regions")?,
        inputs.table("review", "review_queue")?,
    );
    let mut html = String::from(
        "<h2>Review</h2><p class=\"cap\">Where the labels are likely wrong, from the run's own \
         signals (no ground truth): the review score of a pixel estimates the probability that \
         its label is wrong, from the learned field's confidence, its disagreement with the \
         pseudo label and with the fixed (primitive) field, nearness to a label boundary, depth \
         outside every primitive the ray crosses, and coverage gaps (no primitive on the ray, \
         yet not sky). <code>pipe export review</code> writes the maps and the queue.</p>",
    );
    let mut md = String::from("\n## Review\n\n");
    // How well it finds wrong labels, where there is GT.
    let m = review_metrics(inputs.table("evaluate", "metrics")?)?;
    if m.contains_key("review_auroc") {
        let images = m.get("review_images").copied().unwrap_or(0.0);
        let wrong = m.get("review_wrong_share").copied().unwrap_or(f64::NAN);
        let _ = write!(
            html,
            "<p>Against the ground truth of {images:.0} images ({:.1} % of their labels wrong):</p>\
             <table><tr><th></th><th>review score</th><th>confidence alone</th></tr>",
            wrong * 100.0
        );
        md.push_str("| against GT | review score | confidence alone |\n|---|---|---|\n");
        for &(k, label, scale, decimals) in FIGURES {
            let show = |v: Option<&f64>| {
                v.map_or("–".to_string(), |v| format!("{:.*}", decimals, v * scale))
            };
            let (r, c) = (
                show(m.get(&format!("review_{k}"))),
                show(m.get(&format!("confidence_{k}"))),
            );
            let _ = write!(html, "<tr><td>{label}</td><td>{r}</td><td>{c}</td></tr>");
            let _ = writeln!(md, "| {label} | {r} | {c} |");
        }
        html.push_str("</table>");
    }
    // Per frame along the sequence, and coverage.
    const F: &str = "review_frames";
    let (ff, fc, fs, fcov, fgap) = (
        tables::get_prim::<UInt32Type>(frames, F, "frame")?,
        tables::get_prim::<UInt8Type>(frames, F, "camera")?,
        tables::get_prim::<Float64Type>(frames, F, "score")?,
        tables::get_prim::<Float64Type>(frames, F, "coverage")?,
        tables::get_prim::<UInt64Type>(frames, F, "gap_pixels")?,
    );
    let rows: Vec<(u32, u8, f64, f64)> = (0..frames.num_rows())
        .map(|i| (ff[i], fc[i], fs[i], fcov[i]))
        .collect();
    if let Some(worst) = (0..rows.len()).min_by(|&a, &b| rows[a].3.total_cmp(&rows[b].3)) {
        let mean = rows.iter().map(|r| r.3).sum::<f64>() / rows.len() as f64;
        let gaps = tables::get_strings(regions, "review_regions", "kind")?;
        let gap_regions = (0..regions.num_rows())
            .filter(|&i| gaps.value(i) == "coverage_gap")
            .count();
        let line = format!(
            "The annotations cover {:.2} % of the pixels on average; least: frame {} camera {} \
             ({:.2} %). {} coverage-gap pixels in all, {gap_regions} coverage-gap regions \
             (pixels whose ray crosses no primitive, yet the pseudo label, or a ray below the \
             horizon, says they are not sky: their labels are guesses).",
            mean * 100.0,
            rows[worst].0,
            rows[worst].1,
            rows[worst].3 * 100.0,
            fgap.iter().sum::<u64>(),
        );
        let _ = write!(html, "<p>{line}</p>");
        let _ = writeln!(md, "\n{line}");
        if let Some(largest) = largest_gaps(regions, 5)? {
            let _ = write!(html, "<p>Largest coverage gaps: {largest}.</p>");
            let _ = writeln!(md, "\nLargest coverage gaps: {largest}.");
        }
    }
    if let Some(svg) = review_svg(&rows)? {
        html.push_str(&svg);
    }
    queue_table(queue, &mut html, &mut md)?;
    crops(inputs, queue, regions, zoom, top, &mut html)?;
    Ok(Some(Section { html, md }))
}

/// The `n` largest coverage-gap regions, in words (`None` without any).
fn largest_gaps(regions: &RecordBatch, n: usize) -> Result<Option<String>> {
    const R: &str = "review_regions";
    let kind = tables::get_strings(regions, R, "kind")?;
    let (frame, camera, class, pixels) = (
        tables::get_prim::<UInt32Type>(regions, R, "frame")?,
        tables::get_prim::<UInt8Type>(regions, R, "camera")?,
        tables::get_prim::<UInt8Type>(regions, R, "class")?,
        tables::get_prim::<UInt32Type>(regions, R, "pixels")?,
    );
    let mut gaps: Vec<usize> = (0..regions.num_rows())
        .filter(|&i| kind.value(i) == "coverage_gap")
        .collect();
    gaps.sort_by_key(|&i| (std::cmp::Reverse(pixels[i]), i));
    let words: Vec<String> = gaps
        .iter()
        .take(n)
        .map(|&i| {
            let what = labels::by_id(class[i]).map_or("unknown", |l| l.name);
            format!(
                "{} px in frame {} camera {} (pseudo label: {what})",
                pixels[i], frame[i], camera[i]
            )
        })
        .collect();
    Ok((!words.is_empty()).then(|| words.join("; ")))
}

/// The queue's first entries as a table.
fn queue_table(queue: &RecordBatch, html: &mut String, md: &mut String) -> Result<()> {
    const Q: &str = "review_queue";
    let object = tables::get_strings(queue, Q, "object")?;
    let (regions, images, first, last) = (
        tables::get_prim::<UInt32Type>(queue, Q, "regions")?,
        tables::get_prim::<UInt32Type>(queue, Q, "images")?,
        tables::get_prim::<UInt32Type>(queue, Q, "first_frame")?,
        tables::get_prim::<UInt32Type>(queue, Q, "last_frame")?,
    );
    let (pixels, expected) = (
        tables::get_prim::<UInt64Type>(queue, Q, "pixels")?,
        tables::get_prim::<Float64Type>(queue, Q, "expected_wrong")?,
    );
    html.push_str(
        "<h3>Review queue</h3><table><tr><th>rank</th><th>object</th><th>regions</th>\
         <th>images</th><th>frames</th><th>flagged px</th><th>expected wrong px</th></tr>",
    );
    md.push_str("\n| rank | object | regions | images | frames | flagged px | expected wrong px |\n|---|---|---|---|---|---|---|\n");
    for i in 0..queue.num_rows().min(10) {
        let cells = format!(
            "{}|{}|{}|{}|{}–{}|{}|{:.0}",
            i + 1,
            object.value(i),
            regions[i],
            images[i],
            first[i],
            last[i],
            pixels[i],
            expected[i]
        );
        let _ = write!(
            html,
            "<tr><td>{}</td></tr>",
            cells.split('|').collect::<Vec<_>>().join("</td><td>")
        );
        let _ = writeln!(
            md,
            "| {} |",
            cells.split('|').collect::<Vec<_>>().join(" | ")
        );
    }
    html.push_str("</table>");
    Ok(())
}

/// Pictures of the worst region of each of the first `top` queue entries.
fn crops(
    inputs: &Inputs,
    queue: &RecordBatch,
    regions: &RecordBatch,
    zoom: u32,
    top: usize,
    html: &mut String,
) -> Result<()> {
    const R: &str = "review_regions";
    let ids = tables::get_prim::<UInt32Type>(regions, R, "region")?;
    let by_id: HashMap<u32, usize> = ids.iter().enumerate().map(|(i, &id)| (id, i)).collect();
    let (rf, rc, ri) = (
        tables::get_prim::<UInt32Type>(regions, R, "frame")?,
        tables::get_prim::<UInt8Type>(regions, R, "camera")?,
        tables::get_prim::<UInt16Type>(regions, R, "index")?,
    );
    let bbox = [
        tables::get_prim::<UInt32Type>(regions, R, "x0")?,
        tables::get_prim::<UInt32Type>(regions, R, "y0")?,
        tables::get_prim::<UInt32Type>(regions, R, "x1")?,
        tables::get_prim::<UInt32Type>(regions, R, "y1")?,
    ];
    let reason = tables::get_strings(regions, R, "reason")?;
    let object = tables::get_strings(queue, "review_queue", "object")?;
    let worst = tables::get_prim::<UInt32Type>(queue, "review_queue", "worst_region")?;
    let images = inputs.stored("scene", "images")?;
    let pseudo = inputs.stored("scene", "pseudo_labels")?;
    let maps = inputs.stored("render", "label_maps")?;
    let review = inputs.stored("review", "review_maps")?;
    let (im_i, ps_i, m_i, rv_i) = (
        images.image_rows()?,
        pseudo.image_rows()?,
        maps.image_rows()?,
        review.image_rows()?,
    );
    html.push_str(
        "<h3>Top regions</h3><p class=\"cap\">The worst region of each of the first queue \
         entries: RGB · ours · pseudo label · fixed field (the primitives' classes) · review \
         (the region in its reason's colour, other flagged pixels dimmer). Reasons: ",
    );
    for (code, name) in REASONS.iter().enumerate().skip(1) {
        let c = REASON_COLOURS[code];
        let _ = write!(
            html,
            "<span><i style=\"display:inline-block;width:10px;height:10px;background:rgb({},{},{})\"></i> {name}</span> ",
            c[0], c[1], c[2]
        );
    }
    html.push_str("</p><table class=\"frames\">");
    for (q, worst_q) in worst.iter().enumerate().take(top) {
        let Some(&r) = by_id.get(worst_q) else {
            continue;
        };
        let key = (rf[r], rc[r]);
        let (Some(&mi), Some(&vi), Some(&ii)) = (m_i.get(&key), rv_i.get(&key), im_i.get(&key))
        else {
            continue;
        };
        let (m, v, img) = (maps.row(mi)?, review.row(vi)?, images.row(ii)?);
        let w = tables::get_prim::<UInt32Type>(&m, "label_maps", "width")?[0] as usize;
        let h = tables::get_prim::<UInt32Type>(&m, "label_maps", "height")?[0] as usize;
        // The region's box with a margin of half its size (at least 6 % of the image height).
        let [bx0, by0, bx1, by1] = bbox.map(|b| b[r] as usize);
        if !(bx0 <= bx1 && bx1 < w && by0 <= by1 && by1 < h) {
            continue;
        }
        let margin_x = (bx1 - bx0 + 1).div_ceil(2).max(h * 6 / 100).max(4);
        let margin_y = (by1 - by0 + 1).div_ceil(2).max(h * 6 / 100).max(4);
        let area = (
            bx0.saturating_sub(margin_x),
            by0.saturating_sub(margin_y),
            (bx1 + 1 + margin_x).min(w),
            (by1 + 1 + margin_y).min(h),
        );
        let (cw, ch) = ((area.2 - area.0) as u32, (area.3 - area.1) as u32);
        let z = zoom.max(96u32.div_ceil(ch.max(1))).min(8);
        let ours = tables::get_list::<UInt8Type>(&m, "label_maps", "semantic")?.row(0);
        let fixed = tables::get_list::<UInt8Type>(&m, "label_maps", "fixed_semantic")?.row(0);
        let rgb = tables::get_binary(&img, "images", "rgb")?.value(0);
        let why = tables::get_list::<UInt8Type>(&v, "review_maps", "reason")?.row(0);
        let region = tables::get_list::<UInt16Type>(&v, "review_maps", "region")?.row(0);
        if [ours.len(), fixed.len(), why.len(), region.len()]
            .iter()
            .any(|&n| n != w * h)
            || rgb.len() != w * h * 3
        {
            continue;
        }
        let label = |l: &[u8]| labels::color(l[0]);
        let mut cells: Vec<(&str, Option<Vec<u8>>)> = vec![
            ("RGB", Some(crop(rgb, w, area, 3, |p| [p[0], p[1], p[2]]))),
            ("ours", Some(crop(ours, w, area, 1, label))),
        ];
        let ps = ps_i.get(&key).map(|&i| pseudo.row(i)).transpose()?;
        let ps = ps
            .as_ref()
            .map(|b| tables::get_list::<UInt8Type>(b, "pseudo_labels", "labels").map(|l| l.row(0)))
            .transpose()?
            .filter(|l| l.len() == w * h);
        cells.push(("pseudo label", ps.map(|l| crop(l, w, area, 1, label))));
        cells.push(("fixed field", Some(crop(fixed, w, area, 1, label))));
        // The review: the region in its reason colour over a dimmed RGB.
        let index = ri[r];
        let overlay: Vec<u8> = (0..w * h)
            .flat_map(|p| {
                let c = REASON_COLOURS[(why[p] as usize).min(6)];
                let g = rgb[p * 3..p * 3 + 3].iter().map(|&v| v as u32).sum::<u32>() / 9;
                if region[p] == index {
                    c
                } else if why[p] > 0 {
                    [
                        (c[0] as u32 / 2 + g / 2) as u8,
                        (c[1] as u32 / 2 + g / 2) as u8,
                        (c[2] as u32 / 2 + g / 2) as u8,
                    ]
                } else {
                    [g as u8; 3]
                }
            })
            .collect();
        cells.push((
            "review",
            Some(crop(&overlay, w, area, 3, |p| [p[0], p[1], p[2]])),
        ));
        let _ = write!(
            html,
            "<tr><td class=\"cap\">#{} {}<br>frame {} camera {}<br>{}</td>",
            q + 1,
            object.value(q),
            key.0,
            key.1,
            reason.value(r)
        );
        for (cap, pic) in cells {
            match pic {
                Some(pic) => {
                    let uri = png_data_uri(cw, ch, &pic, z)?;
                    let _ = write!(html, "<td><img src=\"{uri}\" alt=\"{cap}\"><span class=\"cap\">{cap}</span></td>");
                }
                None => {
                    let _ = write!(html, "<td class=\"cap\">{cap}: n/a</td>");
                }
            }
        }
        html.push_str("</tr>");
    }
    html.push_str("</table>");
    Ok(())
}
