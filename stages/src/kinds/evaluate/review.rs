//! How well the review finds wrong labels, where GT says which are wrong: over every reviewed
//! image of a scored camera that has GT (not only the evaluation frames: the review is for the
//! labels of every frame), the review score against the rendered confidence alone.

use std::collections::HashMap;

use arrow::datatypes::{Float32Type, Float64Type, UInt16Type, UInt32Type, UInt8Type};

use crate::metrics::detection::{spearman, top_region_precision, ScoreHistogram, ScoredRegion};
use crate::review::regions::connected_regions;
use crate::stage::{Inputs, Progress, Result, StageError};
use crate::{labels, tables};

/// The share of pixels [`ReviewFigures`] looks at first, and the regions it judges.
pub const TOP_SHARE: f64 = 0.05;
pub const TOP_REGIONS: usize = 20;
/// Flag threshold and smallest region (share of the image) for the confidence's own regions,
/// the review's defaults.
const CONFIDENCE_FLAG: f32 = 0.5;
const MIN_REGION: f64 = 2e-5;

/// One detector's counts: pixels by score, regions, per-image score and error.
#[derive(Default)]
struct Detector {
    pixels: ScoreHistogram,
    regions: Vec<ScoredRegion>,
    image_score: Vec<f64>,
}

impl Detector {
    /// (metric suffix, value) of this detector.
    fn figures(&self, image_error: &[f64]) -> [(&'static str, Option<f64>); 4] {
        [
            ("auroc", self.pixels.auroc()),
            ("recall_5pct", self.pixels.recall_at(TOP_SHARE)),
            (
                "top20_precision",
                top_region_precision(&self.regions, TOP_REGIONS),
            ),
            ("frame_rank_corr", spearman(&self.image_score, image_error)),
        ]
    }
}

/// The figures of the review (`review_*`) and of the confidence alone (`confidence_*`) as
/// metric rows of `panoptic_nerf`, with `review_images` and `review_wrong_share`.
pub(super) fn review_figures(
    inputs: &Inputs,
    scores: impl Fn(u8) -> bool,
    progress: &dyn Progress,
) -> Result<Vec<(String, Option<f64>)>> {
    let (Some(maps), Some(regions)) = (
        inputs.optional_stored("review", "review_maps")?,
        inputs.optional_table("review", "review_regions")?,
    ) else {
        return Ok(Vec::new());
    };
    let gt = inputs.stored("scene", "gt_semantic")?;
    let rendered = inputs.stored("render", "label_maps")?;
    let (gt_rows, rendered_rows) = (gt.image_rows()?, rendered.image_rows()?);
    // Expected wrong pixels of each listed region, by (frame, camera, index).
    const R: &str = "review_regions";
    let (rf, rc, ri, re) = (
        tables::get_prim::<UInt32Type>(regions, R, "frame")?,
        tables::get_prim::<UInt8Type>(regions, R, "camera")?,
        tables::get_prim::<UInt16Type>(regions, R, "index")?,
        tables::get_prim::<Float64Type>(regions, R, "expected_wrong")?,
    );
    let mut listed: HashMap<(u32, u8), Vec<(u16, f64)>> = HashMap::new();
    for i in 0..regions.num_rows() {
        listed
            .entry((rf[i], rc[i]))
            .or_default()
            .push((ri[i], re[i]));
    }
    let mut keys: Vec<((u32, u8), usize)> = maps
        .image_rows()?
        .into_iter()
        .filter(|((_, c), _)| scores(*c))
        .filter(|(k, _)| gt_rows.contains_key(k) && rendered_rows.contains_key(k))
        .collect();
    keys.sort_unstable();
    let (mut review, mut confidence) = (Detector::default(), Detector::default());
    let mut image_error = Vec::new();
    let (mut judged, mut wrong) = (0u64, 0u64);
    for (k, &(key, row)) in keys.iter().enumerate() {
        progress.update(k as u64, keys.len() as u64, "judging the review");
        let m = maps.row(row)?;
        let g = gt.row(gt_rows[&key])?;
        let r = rendered_rows[&key];
        let l = rendered.rows(r..r + 1, Some(&["semantic", "confidence"]))?;
        let score = tables::get_list::<UInt16Type>(&m, "review_maps", "score")?.row(0);
        let region = tables::get_list::<UInt16Type>(&m, "review_maps", "region")?.row(0);
        let gsem = tables::get_list::<UInt8Type>(&g, "gt_semantic", "labels")?.row(0);
        let ours = tables::get_list::<UInt8Type>(&l, "label_maps", "semantic")?.row(0);
        let conf = tables::get_list::<Float32Type>(&l, "label_maps", "confidence")?.row(0);
        let w = tables::get_prim::<UInt32Type>(&m, "review_maps", "width")?[0] as usize;
        let h = tables::get_prim::<UInt32Type>(&m, "review_maps", "height")?[0] as usize;
        let n = ours.len();
        if [score.len(), region.len(), gsem.len(), conf.len(), w * h]
            .iter()
            .any(|&len| len != n)
        {
            return Err(StageError::Input(format!(
                "frame {} camera {}: review_maps ({w}x{h}), gt_semantic and label_maps differ in size",
                key.0, key.1
            )));
        }
        let valid = |p: usize| gsem[p] != labels::UNLABELED;
        let is_wrong = |p: usize| ours[p] != gsem[p];
        let u = |p: usize| {
            if conf[p].is_finite() {
                1.0 - conf[p]
            } else {
                1.0
            }
        };
        let (mut n_valid, mut n_wrong, mut sum_r, mut sum_c) = (0u64, 0u64, 0f64, 0f64);
        let mut per_region: HashMap<u16, (u64, u64)> = HashMap::new();
        for p in (0..n).filter(|&p| valid(p)) {
            let bad = is_wrong(p);
            review.pixels.add(score[p] as f32 / u16::MAX as f32, bad);
            confidence.pixels.add(u(p), bad);
            n_valid += 1;
            n_wrong += bad as u64;
            // Per image, the frame score of review_frames: the mean squared score.
            sum_r += (score[p] as f64 / u16::MAX as f64).powi(2);
            sum_c += (u(p) as f64).powi(2);
            if region[p] > 0 {
                let e = per_region.entry(region[p]).or_default();
                e.0 += 1;
                e.1 += bad as u64;
            }
        }
        if n_valid == 0 {
            continue;
        }
        for &(i, expected_wrong) in listed.get(&key).map(Vec::as_slice).unwrap_or(&[]) {
            let (j, bad) = per_region.get(&i).copied().unwrap_or((0, 0));
            review.regions.push(ScoredRegion {
                expected_wrong,
                judged: j,
                wrong: bad,
            });
        }
        // The confidence's own regions: pixels with 1 - confidence >= the review's flag, among
        // the rays (outside a fisheye's lens nothing is rendered: confidence 0, unlabeled).
        let mask: Vec<bool> = (0..n)
            .map(|p| u(p) >= CONFIDENCE_FLAG && ours[p] != labels::UNLABELED)
            .collect();
        let (ids, count) = connected_regions(&mask, w, h);
        let min_pixels = ((MIN_REGION * n as f64).ceil() as u64).max(1);
        let mut sums = vec![(0u64, 0f64, 0u64, 0u64); count as usize];
        for (p, &id) in ids.iter().enumerate().filter(|(_, &id)| id > 0) {
            let s = &mut sums[id as usize - 1];
            s.0 += 1;
            s.1 += u(p) as f64;
            if valid(p) {
                s.2 += 1;
                s.3 += is_wrong(p) as u64;
            }
        }
        confidence
            .regions
            .extend(
                sums.into_iter()
                    .filter(|s| s.0 >= min_pixels)
                    .map(|(_, e, j, bad)| ScoredRegion {
                        expected_wrong: e,
                        judged: j,
                        wrong: bad,
                    }),
            );
        review.image_score.push(sum_r / n_valid as f64);
        confidence.image_score.push(sum_c / n_valid as f64);
        image_error.push(n_wrong as f64 / n_valid as f64);
        judged += n_valid;
        wrong += n_wrong;
    }
    let mut out = Vec::new();
    for (prefix, d) in [("review", &review), ("confidence", &confidence)] {
        for (k, v) in d.figures(&image_error) {
            out.push((format!("{prefix}_{k}"), v));
        }
    }
    out.push(("review_images".into(), Some(image_error.len() as f64)));
    out.push((
        "review_wrong_share".into(),
        (judged > 0).then(|| wrong as f64 / judged as f64),
    ));
    Ok(out)
}
