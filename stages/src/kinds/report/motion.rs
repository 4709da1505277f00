//! The report's "Static and moving pixels" table: every method's scores inside the moving
//! objects' box outlines and on the rest, where the scene has moving objects (`motion_metrics`).

use arrow::record_batch::RecordBatch;

use super::{grouped_metric_map, method_row, numeric_header, Page};
use crate::metrics::scores::METHODS;
use crate::stage::Result;

impl Page {
    /// The table, when `t` (`motion_metrics`) has rows.
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
}
