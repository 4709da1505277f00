//! The `report` stage kind: a self-contained HTML page (pictures and plots embedded) and a
//! Markdown summary of one run: the metrics table in the paper's form (methods x metrics), the
//! per-class IoU, the training curves, and per evaluation frame a row of pictures:
//! RGB | pseudo labels | ours | GT | error map | panoptic | depth.

use std::{collections::BTreeMap, fmt::Write as _, path::Path, path::PathBuf};

use arrow::{
    array::{Array, Float64Array},
    datatypes::UInt8Type,
    record_batch::RecordBatch,
};
use serde::{Deserialize, Serialize};

use crate::metrics::scores::METHODS;
use crate::report::training_svg;
use crate::stage::{
    InputSlot, Inputs, Progress, Result, StageError, Table, TableSet, Tables, TypedStage,
};
use crate::{labels, tables};

mod motion;
mod pictures;
mod review;

#[derive(Debug, Clone, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct ReportParams {
    /// Title of the page.
    pub title: String,
    /// At most this many evaluation frames get a row of pictures.
    pub max_frames: usize,
    /// Pictures are scaled up by this integer factor (nearest neighbour) for readability.
    pub zoom: u32,
    /// Depth pictures map 0..depth_range metres onto the colour scale.
    pub depth_range: f32,
    /// The review section pictures the worst region of this many queue entries.
    pub review_regions: usize,
}

impl Default for ReportParams {
    fn default() -> Self {
        Self {
            title: "panoptic-pipe report".into(),
            max_frames: 8,
            zoom: 2,
            depth_range: 50.0,
            review_regions: 8,
        }
    }
}

pub struct Report;

/// (column label, metric key, scale, decimals) of the main table.
const COLUMNS: &[(&str, &str, f64, usize)] = &[
    ("mIoU", "miou", 100.0, 1),
    ("Acc", "acc", 100.0, 1),
    ("MC", "mc", 100.0, 1),
    ("PQ", "pq", 100.0, 1),
    ("SQ", "sq", 100.0, 1),
    ("RQ", "rq", 100.0, 1),
    ("PQ th", "pq_things", 100.0, 1),
    ("PQ st", "pq_stuff", 100.0, 1),
    ("PQ†", "pq_dagger", 100.0, 1),
    ("PQ api", "pq_panopticapi", 100.0, 1),
    ("depth RMSE (m)", "depth_rmse", 1.0, 2),
    ("δ<1.25", "depth_delta_1_25", 100.0, 1),
];

/// Ours' depth against the scene's exact depth, and what that exact depth scores against the
/// LiDAR (the LiDAR metric's floor), where evaluate had an exact depth (synthetic scenes).
fn exact_depth_note(metrics: &BTreeMap<String, BTreeMap<String, Option<f64>>>) -> Option<String> {
    let get = |m: &str, k: &str| metrics.get(m).and_then(|v| v.get(k).copied().flatten());
    let (rmse, delta) = (
        get("panoptic_nerf", "depth_rmse_exact")?,
        get("panoptic_nerf", "depth_delta_1_25_exact")?,
    );
    let floor = match (
        get("exact_depth", "depth_rmse"),
        get("exact_depth", "depth_delta_1_25"),
    ) {
        (Some(r), Some(d)) => format!(
            " The exact depth itself scores {r:.2} m / {:.1} % against the LiDAR: the floor of \
             the LiDAR metric on this scene, whose points and the pixel centres see different \
             surfaces at depth edges.",
            d * 100.0
        ),
        _ => String::new(),
    };
    Some(format!(
        "Ours' depth against the scene's exact depth at every pixel within the depth range \
         (not the LiDAR): RMSE {rmse:.2} m, δ<1.25 {:.1} %.{floor}",
        delta * 100.0
    ))
}

/// The header cells `labels` of a table's right-aligned columns in both documents, then the
/// Markdown separator (`lead_sep` for the columns before them) and the end of the HTML row.
fn numeric_header<'a>(
    md: &mut String,
    html: &mut String,
    labels: impl ExactSizeIterator<Item = &'a str>,
    lead_sep: &str,
) {
    let n = labels.len();
    for label in labels {
        let _ = write!(md, " {label} |");
        let _ = write!(html, "<th>{label}</th>");
    }
    md.push_str(&format!("\n{lead_sep}"));
    md.push_str(&"---:|".repeat(n));
    md.push('\n');
    html.push_str("</tr>");
}

fn method_label(m: &str) -> &str {
    match m {
        "panoptic_nerf" => "Panoptic NeRF (ours)",
        "fixed_field" => "fixed field S_hat",
        "pseudo_labels" => "pseudo labels (2D input)",
        "first_primitive" => "first-primitive projection",
        other => other,
    }
}

fn f64_col<'a>(b: &'a RecordBatch, table: &str, col: &str) -> Result<&'a Float64Array> {
    b.column_by_name(col)
        .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
        .ok_or_else(|| StageError::Input(format!("table `{table}` lacks float64 column `{col}`")))
}

/// method -> metric -> value.
fn metric_map(t: &RecordBatch) -> Result<BTreeMap<String, BTreeMap<String, Option<f64>>>> {
    let methods = tables::get_strings(t, "metrics", "method")?;
    let metrics = tables::get_strings(t, "metrics", "metric")?;
    let values = f64_col(t, "metrics", "value")?;
    let mut out: BTreeMap<String, BTreeMap<String, Option<f64>>> = BTreeMap::new();
    for i in 0..t.num_rows() {
        out.entry(methods.value(i).into()).or_default().insert(
            metrics.value(i).into(),
            (!values.is_null(i)).then(|| values.value(i)),
        );
    }
    Ok(out)
}

/// (group, method) -> metric -> value, of a metrics table whose first column is `key` (the
/// camera model of `camera_metrics`, the part of `motion_metrics`).
type GroupedMetrics = BTreeMap<(String, String), BTreeMap<String, Option<f64>>>;

fn grouped_metric_map(t: &RecordBatch, table: &str, key: &str) -> Result<GroupedMetrics> {
    let groups = tables::get_strings(t, table, key)?;
    let methods = tables::get_strings(t, table, "method")?;
    let metrics = tables::get_strings(t, table, "metric")?;
    let values = f64_col(t, table, "value")?;
    let mut by = GroupedMetrics::new();
    for i in 0..t.num_rows() {
        by.entry((groups.value(i).into(), methods.value(i).into()))
            .or_default()
            .insert(
                metrics.value(i).into(),
                (!values.is_null(i)).then(|| values.value(i)),
            );
    }
    Ok(by)
}

/// One method's row of a scores table, in Markdown and HTML: the `lead` cells, the method's
/// name (ours highlighted), then `cols` (label, metric key, scale, decimals) of `vals`.
fn method_row(
    md: &mut String,
    html: &mut String,
    lead: &[&str],
    method: &str,
    vals: &BTreeMap<String, Option<f64>>,
    cols: &[(&str, &str, f64, usize)],
) {
    let ours = if method == "panoptic_nerf" {
        " class=\"ours\""
    } else {
        ""
    };
    let _ = write!(html, "<tr{ours}>");
    md.push('|');
    for cell in lead.iter().copied().chain([method_label(method)]) {
        let _ = write!(md, " {cell} |");
        let _ = write!(html, "<td>{cell}</td>");
    }
    for &(_, key, scale, dec) in cols {
        let v = fmt_value(vals.get(key).copied().flatten(), scale, dec);
        let _ = write!(md, " {v} |");
        let _ = write!(html, "<td>{v}</td>");
    }
    md.push('\n');
    html.push_str("</tr>");
}

fn fmt_value(v: Option<f64>, scale: f64, decimals: usize) -> String {
    v.map_or("–".into(), |v| format!("{:.*}", decimals, v * scale))
}

/// The report page being written, as Markdown and HTML side by side.
struct Page {
    md: String,
    html: String,
}

impl Page {
    fn new(title: &str, scene_name: &str) -> Self {
        let md = format!("# {title}\n\nScene: `{scene_name}`\n\n");
        let mut html = String::new();
        let _ = write!(
        html,
        "<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>{}</title><style>\
         body{{font-family:sans-serif;margin:24px;color:#222;max-width:1500px}}\
         table{{border-collapse:collapse;margin:8px 0 20px}}td,th{{border:1px solid #ccc;padding:4px 8px;text-align:right}}\
         th{{background:#f3f3f3}}td:first-child,th:first-child{{text-align:left}}tr.ours td{{font-weight:bold;background:#eef6ee}}\
         .frames{{width:100%;table-layout:fixed}}.frames td{{border:none;padding:2px;text-align:center;vertical-align:top}}.frames td:first-child{{width:56px}}.frames img{{image-rendering:pixelated;display:block;width:100%;height:auto}}\
         .cap{{font-size:12px;color:#555}}.legend span{{display:inline-block;margin:2px 8px 2px 0;font-size:12px}}\
         .legend i{{display:inline-block;width:12px;height:12px;margin-right:4px;vertical-align:middle;border:1px solid #999}}\
         </style></head><body><h1>{}</h1><p>Scene <code>{scene_name}</code>. Metrics on the evaluation frames \
         (semantic metrics and PQ in %, depth RMSE in metres; – = not applicable).</p>",
        title, title
    );
        Page { md, html }
    }

    /// The main table: methods x metrics.
    fn metrics(&mut self, metrics: &BTreeMap<String, BTreeMap<String, Option<f64>>>) {
        let (md, html) = (&mut self.md, &mut self.html);
        // Main table.
        let mut head = "| method |".to_string();
        let mut sep = "|---|".to_string();
        html.push_str("<h2>Metrics</h2><table><tr><th>method</th>");
        for (label, ..) in COLUMNS {
            let _ = write!(head, " {label} |");
            sep.push_str("---:|");
            let _ = write!(html, "<th>{label}</th>");
        }
        html.push_str("</tr>");
        md.push_str(&format!("## Metrics\n\n{head}\n{sep}\n"));
        for &m in METHODS {
            let Some(vals) = metrics.get(m) else { continue };
            method_row(md, html, &[], m, vals, COLUMNS);
        }
        html.push_str("</table>");
        let note = "PQ, SQ, RQ, PQ th/st and PQ† follow the Panoptic NeRF paper (predicted \
                    segments under evaluate's min_segment_px, default 100 px, become sky before \
                    matching); PQ api scores the same maps against the same GT as panopticapi \
                    and the KITTI-360 scripts do (predicted segments as they are). Compare with \
                    other papers in the convention they state.";
        md.push_str(&format!("\n{note}\n\n"));
        let _ = write!(html, "<p class=\"cap\">{note}</p>");
        if let Some(note) = exact_depth_note(metrics) {
            md.push_str(&format!("{note}\n\n"));
            let _ = write!(html, "<p class=\"cap\">{note}</p>");
        }
    }

    /// Per-class IoU: classes x methods. Returns the label ids present, ascending.
    fn class_iou(&mut self, class_t: &RecordBatch) -> Result<Vec<u8>> {
        let cm = tables::get_strings(class_t, "class_iou", "method")?;
        let (per_class, _) = per_class_iou(class_t, "class_iou", |i| cm.value(i).to_string())?;
        let columns: Vec<(String, String)> = METHODS
            .iter()
            .map(|&m| (m.to_string(), method_label(m).to_string()))
            .collect();
        self.class_table("Per-class IoU (%)", &columns, &per_class);
        let mut present: Vec<u8> = per_class.keys().map(|(id, _)| *id).collect();
        present.dedup();
        Ok(present)
    }

    /// Per-class IoU per camera model, when the evaluation covered fisheye cameras: classes x
    /// (camera model, method), methods with no score on a model left out.
    fn camera_class_iou(&mut self, t: &RecordBatch) -> Result<()> {
        const T: &str = "camera_class_iou";
        let models = tables::get_strings(t, T, "camera_model")?;
        let cm = tables::get_strings(t, T, "method")?;
        let (per_class, scored) =
            per_class_iou(t, T, |i| format!("{}/{}", models.value(i), cm.value(i)))?;
        if !scored.iter().any(|k| k.starts_with("fisheye/")) {
            return Ok(());
        }
        let columns: Vec<(String, String)> = ["perspective", "fisheye"]
            .iter()
            .flat_map(|model| {
                METHODS.iter().map(move |&m| {
                    (
                        format!("{model}/{m}"),
                        format!("{model}: {}", method_label(m)),
                    )
                })
            })
            .filter(|(key, _)| scored.contains(key))
            .collect();
        self.class_table("Per-class IoU per camera model (%)", &columns, &per_class);
        Ok(())
    }

    /// A table of classes (rows) x `columns` (key, header) of IoU in percent.
    fn class_table(
        &mut self,
        title: &str,
        columns: &[(String, String)],
        per_class: &BTreeMap<(u8, String), BTreeMap<String, Option<f64>>>,
    ) {
        let (md, html) = (&mut self.md, &mut self.html);
        let _ = write!(md, "\n## {title}\n\n| class |");
        let _ = write!(html, "<h2>{title}</h2><table><tr><th>class</th>");
        for (_, header) in columns {
            let _ = write!(md, " {header} |");
            let _ = write!(html, "<th>{header}</th>");
        }
        md.push_str("\n|---|");
        md.push_str(&"---:|".repeat(columns.len()));
        md.push('\n');
        html.push_str("</tr>");
        for ((id, name), vals) in per_class {
            let c = labels::color(*id);
            let _ = write!(md, "| {name} |");
            let _ = write!(
            html,
            "<tr><td><i style=\"display:inline-block;width:10px;height:10px;background:rgb({},{},{});margin-right:6px\"></i>{name}</td>",
            c[0], c[1], c[2]
        );
            for (key, _) in columns {
                let v = fmt_value(vals.get(key).copied().flatten(), 100.0, 1);
                let _ = write!(md, " {v} |");
                let _ = write!(html, "<td>{v}</td>");
            }
            md.push('\n');
            html.push_str("</tr>");
        }
        html.push_str("</table>");
    }

    /// Where the depth error comes from: the `depth_breakdown` table.
    fn depth_breakdown(&mut self, t: &RecordBatch) -> Result<()> {
        if t.num_rows() == 0 {
            return Ok(());
        }
        let table = "depth_breakdown";
        let group = tables::get_strings(t, table, "group")?;
        let bin = tables::get_strings(t, table, "bin")?;
        let pixels = tables::get_prim::<arrow::datatypes::UInt64Type>(t, table, "pixels")?;
        let cols = [
            ("RMSE (m)", f64_col(t, table, "rmse")?, 1.0, 2),
            ("mean error (m)", f64_col(t, table, "mean_error")?, 1.0, 2),
            ("δ<1.25", f64_col(t, table, "delta_1_25")?, 100.0, 1),
            (
                "share of squared error",
                f64_col(t, table, "share_sq_error")?,
                100.0,
                1,
            ),
        ];
        let (md, html) = (&mut self.md, &mut self.html);
        md.push_str("\n## Depth error breakdown (ours, LiDAR pixels)\n\n| group | bin | pixels |");
        html.push_str(
            "<h2>Depth error breakdown</h2><p class=\"cap\">Ours at the LiDAR pixels of the evaluation frames, \
             by bins; the share column says where the RMSE comes from (it sums to 100 % within a group).</p>\
             <table><tr><th>group</th><th>bin</th><th>pixels</th>",
        );
        numeric_header(md, html, cols.iter().map(|c| c.0), "|---|---|---:|");
        for (i, &px) in pixels.iter().enumerate() {
            let _ = write!(md, "| {} | {} | {px} |", group.value(i), bin.value(i));
            let _ = write!(
                html,
                "<tr><td>{}</td><td>{}</td><td>{}</td>",
                group.value(i),
                bin.value(i),
                px
            );
            for (_, col, scale, dec) in &cols {
                let v = fmt_value((!col.is_null(i)).then(|| col.value(i)), *scale, *dec);
                let _ = write!(md, " {v} |");
                let _ = write!(html, "<td>{v}</td>");
            }
            md.push('\n');
            html.push_str("</tr>");
        }
        html.push_str("</table>");
        Ok(())
    }

    /// The scores per camera model, when the evaluation covered fisheye cameras: one row per
    /// (model, method), and cross-view consistency between the models.
    fn camera_models(&mut self, t: &RecordBatch) -> Result<()> {
        let by = grouped_metric_map(t, "camera_metrics", "camera_model")?;
        if !by.keys().any(|(m, _)| m == "fisheye") {
            return Ok(());
        }
        const COLS: &[(&str, &str, f64, usize)] = &[
            ("mIoU", "miou", 100.0, 1),
            ("Acc", "acc", 100.0, 1),
            ("MC", "mc", 100.0, 1),
            ("PQ", "pq", 100.0, 1),
            ("PQ api", "pq_panopticapi", 100.0, 1),
            ("frames", "frames", 1.0, 0),
        ];
        let (md, html) = (&mut self.md, &mut self.html);
        md.push_str("\n## Per camera model\n\n| cameras | method |");
        html.push_str("<h2>Per camera model</h2><table><tr><th>cameras</th><th>method</th>");
        numeric_header(md, html, COLS.iter().map(|c| c.0), "|---|---|");
        for model in ["perspective", "fisheye", "perspective_fisheye"] {
            for &m in METHODS {
                let Some(vals) = by.get(&(model.to_string(), m.to_string())) else {
                    continue;
                };
                let label = if model == "perspective_fisheye" {
                    "perspective → fisheye (cross-view MC)"
                } else {
                    model
                };
                method_row(md, html, &[label], m, vals, COLS);
            }
        }
        html.push_str("</table>");
        let note = "Cross-view MC: each LiDAR point of a perspective evaluation image is carried \
                    into the same frame's fisheye images; the share of points given the same \
                    label in both (no occlusion test: the first-primitive row shows the floor \
                    that occlusion and resolution set).";
        md.push_str(&format!("\n{note}\n\n"));
        let _ = write!(html, "<p class=\"cap\">{note}</p>");
        Ok(())
    }

    /// In place of the score tables when nothing was evaluated: why, in plain words.
    fn not_evaluated(&mut self) {
        let why = crate::metrics::scores::NOT_EVALUATED;
        self.md.push_str(&format!("## Not evaluated\n\n{why}.\n"));
        let _ = write!(self.html, "<h2>Not evaluated</h2><p>{why}.</p>");
    }
}

/// The label ids of the rendered semantic maps, ascending (the legend without scores); one
/// image read at a time.
fn classes_rendered(maps: &Table) -> Result<Vec<u8>> {
    let mut seen = [false; 256];
    for r in 0..maps.num_rows() {
        let row = maps.rows(r..r + 1, Some(&["semantic"]))?;
        for &l in tables::get_list::<UInt8Type>(&row, "label_maps", "semantic")?.row(0) {
            seen[l as usize] = true;
        }
    }
    Ok((0..=255u8).filter(|&l| seen[l as usize]).collect())
}

/// At most `n` of `keys`, evenly spread from the first to the last.
fn spread<T: Copy>(keys: &[T], n: usize) -> Vec<T> {
    if keys.len() <= n {
        return keys.to_vec();
    }
    if n <= 1 {
        return keys.iter().take(n).copied().collect();
    }
    (0..n)
        .map(|i| keys[i * (keys.len() - 1) / (n - 1)])
        .collect()
}

/// IoU per (label id, class name) per column key (`key_of(row)`) from a `class_iou`-shaped
/// table, and the keys with at least one score.
#[allow(clippy::type_complexity)]
fn per_class_iou(
    t: &RecordBatch,
    table: &str,
    key_of: impl Fn(usize) -> String,
) -> Result<(
    BTreeMap<(u8, String), BTreeMap<String, Option<f64>>>,
    std::collections::BTreeSet<String>,
)> {
    let cn = tables::get_strings(t, table, "name")?;
    let cl = tables::get_prim::<UInt8Type>(t, table, "label")?;
    let ci = f64_col(t, table, "iou")?;
    let mut per_class: BTreeMap<(u8, String), BTreeMap<String, Option<f64>>> = BTreeMap::new();
    let mut scored = std::collections::BTreeSet::new();
    for (i, &label) in cl.iter().enumerate() {
        let v = (!ci.is_null(i)).then(|| ci.value(i));
        let key = key_of(i);
        if v.is_some() {
            scored.insert(key.clone());
        }
        per_class
            .entry((label, cn.value(i).to_string()))
            .or_default()
            .insert(key, v);
    }
    Ok((per_class, scored))
}

impl TypedStage for Report {
    type Params = ReportParams;
    const KIND: &'static str = "report";
    // 8: the review section; loss curves on a symlog axis where a term is zero or negative.
    // 9: the "Static and moving pixels" table where the scene has moving objects.
    // 10: and the pictures of the evaluation image moving objects cover most.
    const VERSION: u32 = 10;
    const DESCRIPTION: &'static str =
        "self-contained HTML page and Markdown summary: metrics table, per-class IoU, training curves, pictures per evaluation frame";
    const INPUTS: &'static [InputSlot] = &[
        InputSlot {
            name: "scene",
            tables: &[
                "images",
                "pseudo_labels",
                "scene_info",
                "lidar_depth",
                "dynamic_boxes",
            ],
            optional: false,
            doc: "the scene (RGB and pseudo labels)",
        },
        InputSlot {
            name: "evaluate",
            tables: &[
                "metrics",
                "class_iou",
                "eval_gt",
                "camera_metrics",
                "camera_class_iou",
                "depth_breakdown",
                "motion_metrics",
            ],
            optional: false,
            doc: "metrics and the GT they were computed against",
        },
        InputSlot {
            name: "render",
            tables: &["label_maps"],
            optional: false,
            doc: "rendered labels",
        },
        InputSlot {
            name: "train",
            tables: &["train_log"],
            optional: true,
            doc: "training log for the loss curves",
        },
        InputSlot {
            name: "review",
            tables: &[
                "review_maps",
                "review_regions",
                "review_queue",
                "review_frames",
            ],
            optional: true,
            doc: "the review: its top regions as pictures, the per-frame score and coverage",
        },
    ];
    const OUTPUTS: &'static [&'static str] = &["report_files"];

    fn validate(p: &ReportParams) -> Result<()> {
        if p.zoom == 0 || p.zoom > 8 {
            return Err(StageError::Params("`zoom` must be 1..=8".into()));
        }
        if p.depth_range.is_nan() || p.depth_range <= 0.0 {
            return Err(StageError::Params("`depth_range` must be positive".into()));
        }
        Ok(())
    }

    fn run(&self, p: &ReportParams, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        let info = inputs.table("scene", "scene_info")?;
        let scene_name = tables::get_strings(info, "scene_info", "name")?;
        let scene_name = if scene_name.is_empty() {
            "?"
        } else {
            scene_name.value(0)
        };
        let mut page = Page::new(&p.title, scene_name);
        let present = if inputs.table("evaluate", "eval_gt")?.num_rows() > 0 {
            page.metrics(&metric_map(inputs.table("evaluate", "metrics")?)?);
            let present = page.class_iou(inputs.table("evaluate", "class_iou")?)?;
            page.camera_models(inputs.table("evaluate", "camera_metrics")?)?;
            let motion = inputs.table("evaluate", "motion_metrics")?;
            page.motion_parts(motion)?;
            if motion.num_rows() > 0 {
                page.moving_picture(inputs, p)?;
            }
            page.camera_class_iou(inputs.table("evaluate", "camera_class_iou")?)?;
            page.depth_breakdown(inputs.table("evaluate", "depth_breakdown")?)?;
            present
        } else {
            page.not_evaluated();
            classes_rendered(inputs.stored("render", "label_maps")?)?
        };
        if let Some(log) = inputs.optional_table("train", "train_log")? {
            if let Some(svg) = training_svg(log)? {
                page.html.push_str("<h2>Training</h2>");
                page.html.push_str(&svg);
            }
        }
        if let Some(section) = review::review_section(inputs, p.zoom, p.review_regions)? {
            page.html.push_str(&section.html);
            page.md.push_str(&section.md);
        }
        page.pictures(p, inputs, &present, progress)?;
        page.html.push_str("</table></body></html>\n");
        page.md
            .push_str("\nPictures and training curves: see report.html.\n");
        let names = vec!["report.html".to_string(), "REPORT.md".to_string()];
        let contents = vec![page.html.into_bytes(), page.md.into_bytes()];
        let t = tables::build(
            "report_files",
            vec![tables::strings(&names), tables::binary(&contents)],
        )?;
        Ok(Tables::from([("report_files".to_string(), t)]))
    }

    fn export(&self, _: &ReportParams, t: &TableSet, dir: &Path) -> Result<Vec<PathBuf>> {
        let files = t.table("report_files")?;
        let names = tables::get_strings(files, "report_files", "name")?;
        let contents = tables::get_binary(files, "report_files", "content")?;
        let mut out = Vec::new();
        for i in 0..files.num_rows() {
            let path = dir.join(names.value(i));
            std::fs::write(&path, contents.value(i))
                .map_err(|e| StageError::Failed(format!("writing {}: {e}", path.display())))?;
            out.push(path);
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::report::{error_colors, panoptic_colors};

    #[test]
    fn error_map_colours_void_correct_and_wrong() {
        assert_eq!(
            error_colors(&[7, 7, 8], &[0, 7, 7]),
            vec![0, 0, 0, 40, 160, 60, 220, 40, 40]
        );
    }

    #[test]
    fn panoptic_colours_keep_stuff_and_vary_things() {
        let c = panoptic_colors(&[7000, 26001, 26002]);
        assert_eq!(&c[0..3], &labels::color(7));
        assert_ne!(&c[3..6], &c[6..9]);
    }
}
