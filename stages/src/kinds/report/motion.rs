//! The report's "Static and moving pixels" section, where the scene has moving objects: every
//! method's scores inside the moving objects' box outlines and on the rest (`motion_metrics`),
//! and the pictures of the evaluation image the moving objects cover most.

use std::collections::HashSet;
use std::fmt::Write as _;

use arrow::record_batch::RecordBatch;

use super::pictures::Pictured;
use super::{grouped_metric_map, method_row, numeric_header, Page, ReportParams};
use crate::metrics::scores::METHODS;
use crate::stage::{Inputs, Result};

/// The evaluation image whose GT has the most pixels of the scene's moving objects, and how
/// many; `None` where no GT pixel is one.
fn most_moving(inputs: &Inputs, pictured: &Pictured) -> Result<Option<((u32, u8), usize)>> {
    let boxes = crate::geometry::dynamic_boxes_from_table(inputs.table("scene", "dynamic_boxes")?)?;
    let objects: HashSet<u16> = boxes
        .iter()
        .filter_map(|b| u16::try_from(b.object).ok())
        .collect();
    let mut best = None;
    for &key in pictured.gt.index.keys() {
        let Some(row) = pictured.gt.get(key)? else {
            continue;
        };
        let n = row
            .u16("instance")?
            .iter()
            .filter(|i| objects.contains(i))
            .count();
        if n > best.map_or(0, |(_, m)| m) {
            best = Some((key, n));
        }
    }
    Ok(best)
}

impl Page {
    /// The section, when `t` (`motion_metrics`) has rows.
    pub(super) fn motion_parts(&mut self, t: &RecordBatch) -> Result<()> {
        if t.num_rows() == 0 {
            return Ok(());
        }
        let by = grouped_metric_map(t, "motion_metrics", "part")?;
        const COLS: &[(&str, &str, f64, usize)] = &[
            ("mIoU", "miou", 100.0, 1),
            ("Acc", "acc", 100.0, 1),
            ("PQ", "pq", 100.0, 1),
            ("depth RMSE (m)", "depth_rmse_exact", 1.0, 2),
            ("depth RMSE LiDAR (m)", "depth_rmse", 1.0, 2),
            ("pixels", "pixels", 1.0, 0),
        ];
        let (md, html) = (&mut self.md, &mut self.html);
        md.push_str("\n## Static and moving pixels\n\n| pixels | method |");
        html.push_str("<h2>Static and moving pixels</h2><table><tr><th>pixels</th><th>method</th>");
        numeric_header(md, html, COLS.iter().map(|c| c.0), "|---|---|");
        for part in crate::kinds::evaluate::MOTION_PARTS {
            for &m in METHODS {
                if let Some(vals) = by.get(&(part.to_string(), m.to_string())) {
                    method_row(md, html, &[part], m, vals, COLS);
                }
            }
        }
        html.push_str("</table>");
        let note = "Moving: the pixels whose ray meets a moving object's box at the image's \
                    frame (the object and what is seen around it through its coarse box); \
                    static: the rest. Each part is scored with the other's GT void. The \
                    first-primitive projection includes the moving objects' boxes.";
        md.push_str(&format!("\n{note}\n\n"));
        html.push_str(&format!("<p class=\"cap\">{note}</p>"));
        Ok(())
    }

    /// Under the table, the pictures of the evaluation image moving objects cover most.
    pub(super) fn moving_picture(&mut self, inputs: &Inputs, p: &ReportParams) -> Result<()> {
        let (md, html) = (&mut self.md, &mut self.html);
        let pictured = Pictured::new(inputs)?;
        if let Some((key, n)) = most_moving(inputs, &pictured)? {
            let what = format!(
                "Frame {} camera {}, the evaluation image moving objects cover most ({n} pixels)",
                key.0, key.1
            );
            md.push_str(&format!("{what}: pictured in report.html.\n\n"));
            let _ = write!(
                html,
                "<p class=\"cap\">{what}: {}.</p><table class=\"frames\">",
                Pictured::captions(true)
            );
            pictured.row(key, true, p, html)?;
            html.push_str("</table>");
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tables;

    fn table(rows: &[(&str, &str, &str, Option<f64>)]) -> RecordBatch {
        tables::build(
            "motion_metrics",
            vec![
                tables::strings(rows.iter().map(|r| r.0)),
                tables::strings(rows.iter().map(|r| r.1)),
                tables::strings(rows.iter().map(|r| r.2)),
                std::sync::Arc::new(arrow::array::Float64Array::from(
                    rows.iter().map(|r| r.3).collect::<Vec<_>>(),
                )),
            ],
        )
        .unwrap()
    }

    #[test]
    fn the_table_shows_each_part_and_method_and_is_absent_without_moving_objects() {
        let mut page = Page::new("t", "s");
        let before = page.md.len();
        page.motion_parts(&table(&[])).unwrap();
        assert_eq!(page.md.len(), before, "no moving objects, no section");
        page.motion_parts(&table(&[
            ("moving", "panoptic_nerf", "miou", Some(0.618)),
            ("moving", "first_primitive", "miou", Some(0.114)),
            ("static", "panoptic_nerf", "miou", Some(0.858)),
            ("static", "panoptic_nerf", "depth_rmse_exact", None),
        ]))
        .unwrap();
        let md = &page.md[before..];
        assert!(md.contains("## Static and moving pixels"), "{md}");
        let row = |lead: &str, method: &str| {
            md.lines()
                .find(|l| l.starts_with(&format!("| {lead} | {method}")))
                .unwrap_or_else(|| panic!("no row {lead} {method} in {md}"))
                .to_string()
        };
        assert!(row("moving", "Panoptic NeRF").contains("| 61.8 |"));
        assert!(row("moving", "first-primitive").contains("| 11.4 |"));
        assert!(row("static", "Panoptic NeRF").contains("| 85.8 |"));
        // The parts in the order of the evaluation's: static, then moving.
        assert!(md.find("| static |").unwrap() < md.find("| moving |").unwrap());
        assert!(page.html.contains("<h2>Static and moving pixels</h2>"));
    }

    #[test]
    fn the_section_pictures_the_image_moving_objects_cover_most() {
        use crate::kinds::{evaluate::testing::label_maps, evaluate::Evaluate, report::Report};
        use crate::scene::synthetic::{generate, in_memory::to_tables, SceneParams};
        use crate::{MemoryInputs, NoProgress, Stage};
        use arrow::datatypes::{UInt16Type, UInt32Type, UInt8Type};

        let sp = SceneParams {
            frames: 6,
            moving_objects: 3,
            ..SceneParams::default()
        };
        let scene = to_tables(&sp, generate(&sp, &NoProgress).unwrap()).unwrap();
        let boxes = crate::geometry::dynamic_boxes_from_table(&scene["dynamic_boxes"]).unwrap();
        let objects: HashSet<u16> = boxes.iter().map(|b| b.object as u16).collect();
        let render = label_maps(&scene, &objects, None);
        let run = |stage: &dyn Stage, inputs: MemoryInputs| {
            let v = stage.canonical_params(&serde_json::json!({})).unwrap();
            stage.run(&v, &inputs.inputs(), &NoProgress).unwrap()
        };
        let evaluate = run(
            &Evaluate,
            MemoryInputs::new([("scene", scene.clone()), ("render", render.clone())]),
        );
        let report = run(
            &Report,
            MemoryInputs::new([
                ("scene", scene.clone()),
                ("render", render),
                ("evaluate", evaluate.clone()),
            ]),
        );
        let md = tables::get_binary(&report["report_files"], "report_files", "content")
            .unwrap()
            .value(1)
            .to_vec();
        let md = String::from_utf8(md).unwrap();
        let line = md
            .lines()
            .find(|l| l.contains("the evaluation image moving objects cover most"))
            .unwrap_or_else(|| panic!("no picture named in {md}"));

        // The moving objects' GT pixels per evaluated image, counted from the scene's GT.
        let gt = &evaluate["eval_gt"];
        let frames = tables::get_prim::<UInt32Type>(gt, "eval_gt", "frame").unwrap();
        let cams = tables::get_prim::<UInt8Type>(gt, "eval_gt", "camera").unwrap();
        let gi = &scene["gt_instance"];
        let gi_frames = tables::get_prim::<UInt32Type>(gi, "gt_instance", "frame").unwrap();
        let gi_cams = tables::get_prim::<UInt8Type>(gi, "gt_instance", "camera").unwrap();
        let inst = tables::get_list::<UInt16Type>(gi, "gt_instance", "instances").unwrap();
        let counts: Vec<((u32, u8), usize)> = frames
            .iter()
            .zip(cams)
            .map(|(&f, &c)| {
                let r = (0..gi.num_rows())
                    .find(|&r| (gi_frames[r], gi_cams[r]) == (f, c))
                    .unwrap();
                let n = inst.row(r).iter().filter(|i| objects.contains(i)).count();
                ((f, c), n)
            })
            .collect();
        let &((f, c), n) = counts.iter().max_by_key(|(_, n)| *n).unwrap();
        assert!(n > 0 && counts.len() > 1, "{counts:?}");
        assert!(
            line.contains(&format!("Frame {f} camera {c},"))
                && line.contains(&format!("({n} pixels)")),
            "{line} against {counts:?}"
        );
        let html = tables::get_binary(&report["report_files"], "report_files", "content")
            .unwrap()
            .value(0);
        let html = String::from_utf8_lossy(html);
        let at = html.find("moving objects cover most").unwrap();
        let pictures = &html[at..html[at..].find("</table>").unwrap() + at];
        for cap in [
            "alt=\"RGB\"",
            "alt=\"pseudo labels\"",
            "alt=\"ours\"",
            "alt=\"ground truth\"",
        ] {
            assert!(pictures.contains(cap), "no {cap} picture");
        }
    }
}
