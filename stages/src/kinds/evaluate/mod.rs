//! The `evaluate` stage kind: semantic, panoptic, multi-view-consistency and depth metrics of
//! the rendered labels on the evaluation frames, next to the same metrics for the baselines
//! (the pseudo labels themselves, the class of the first primitive each ray hits, and the
//! argmax of the fixed-field rendering), all against the scene's ground truth.

use std::{
    collections::{BTreeMap, HashMap},
    path::{Path, PathBuf},
    sync::Arc,
};

use arrow::{
    array::{Array, ArrayRef, Float64Array},
    datatypes::{UInt16Type, UInt32Type, UInt64Type, UInt8Type},
    record_batch::RecordBatch,
};
use rayon::prelude::*;

use crate::metrics::scores::{self, METHODS, SCORES};
use crate::{
    geometry::{self, Bvh, CameraRow, Primitive},
    labels,
    metrics::{
        cross_view_consistency, multiview_consistency, BinResult, Consistency, DepthBins,
        LabelledView, Pinhole,
    },
    tables, InputSlot, Inputs, Progress, Result, ScoreSpec, StageError, Table, TableSet, Tables,
    TypedStage,
};

mod depth_bins;
mod images;
mod json;
mod motion;
mod params;
mod review;
mod sums;
#[cfg(test)]
pub(crate) mod testing;

use depth_bins::{depth_bin_keys, BinKey};
use images::{check_size, map_f32, map_u16, map_u8, one_image};
pub use json::{camera_metrics_json, depth_breakdown_json, metrics_json, motion_metrics_json};
pub use motion::PARTS as MOTION_PARTS;
use motion::{MotionGroups, MovingObjects, PartGt, PARTS};
pub use params::{EvaluateParams, PANOPTICAPI_SUFFIX, PQ_CONVENTIONS};
use sums::{ClassRows, FrameMaps, Group, GtRows, MetricRows};

pub struct Evaluate;

/// Label and panoptic maps of "the first primitive each ray hits" (sky where none is hit):
/// the static `prims` and the moving objects' boxes at the image's frame (`moving`); and per
/// pixel whether its ray meets a moving box at all (in front of or behind the first hit).
pub fn first_primitive_maps(
    cam: &geometry::Camera,
    prims: &[Primitive],
    bvh: &Bvh,
    moving: (&[Primitive], &Bvh),
) -> (Vec<u8>, Vec<u16>, Vec<bool>) {
    let n = (cam.width * cam.height) as usize;
    let mut sem = vec![labels::SKY; n];
    let mut inst = vec![labels::SKY as u16 * labels::INSTANCE_FACTOR as u16; n];
    let mut meets_moving = vec![false; n];
    sem.par_iter_mut()
        .zip(inst.par_iter_mut())
        .zip(meets_moving.par_iter_mut())
        .enumerate()
        .for_each(|(i, ((s, ins), meets))| {
            let (x, y) = ((i as u32) % cam.width, (i as u32) / cam.width);
            let Some(ray) = cam.pixel_ray(x, y) else {
                *s = labels::UNLABELED;
                *ins = 0;
                return;
            };
            // Each set's first hit along the whole ray (the moving one says whether the ray
            // meets a moving box at all); the nearer wins, a tie the static primitive, as in
            // `Bvh::first_hit_of_two`.
            let on_static = bvh.first_hit(prims, &ray, 0.0, f64::INFINITY);
            let on_moving = moving.1.first_hit(moving.0, &ray, 0.0, f64::INFINITY);
            *meets = on_moving.is_some();
            let first = match (on_static, on_moving) {
                (Some(s), Some(m)) if m.t_in < s.t_in => Some(&moving.0[m.prim as usize]),
                (Some(s), _) => Some(&prims[s.prim as usize]),
                (None, Some(m)) => Some(&moving.0[m.prim as usize]),
                (None, None) => None,
            };
            if let Some(p) = first {
                *s = p.label;
                *ins = (p.label as u32 * labels::INSTANCE_FACTOR + p.instance.min(999)) as u16;
            }
        });
    (sem, inst, meets_moving)
}

fn view<'a>(c: &CameraRow, labels: &'a [u8], depth: &'a [f32]) -> LabelledView<'a> {
    LabelledView {
        width: c.cam.width as usize,
        height: c.cam.height as usize,
        labels,
        depth,
        intrinsics: Pinhole {
            fx: c.cam.fx,
            fy: c.cam.fy,
            cx: c.cam.cx,
            cy: c.cam.cy,
        },
        cam_to_world: geometry::io::affine_to_row_major(&c.cam.cam_to_world),
    }
}

/// The per-image tables evaluation reads, indexed by (frame, camera), each read one evaluated
/// image at a time: at full size the ground truth, LiDAR and exact depth of the evaluation
/// images alone take gigabytes.
struct Sources<'a> {
    gt_sem: RowIndex<'a>,
    gt_inst: RowIndex<'a>,
    lidar: RowIndex<'a>,
    /// The scene's exact depth (synthetic scenes; none from KITTI-360).
    exact: RowIndex<'a>,
    pseudo: RowIndex<'a>,
    maps: RowIndex<'a>,
}

/// The rows of a per-image table that is read an image at a time.
struct RowIndex<'a> {
    table: &'a Table,
    rows: HashMap<(u32, u8), usize>,
}

impl<'a> RowIndex<'a> {
    fn new(table: &'a Table) -> Result<Self> {
        let keys = table.columns(&["frame", "camera"])?;
        Ok(Self {
            rows: tables::frame_camera_index(&keys, table.name())?,
            table,
        })
    }

    /// The row of image `key` (a one-row batch), if the table has one.
    fn get(&self, key: (u32, u8)) -> Result<Option<RecordBatch>> {
        self.rows.get(&key).map(|&r| self.table.row(r)).transpose()
    }

    /// Like [`RowIndex::get`], an error naming the table when it has no such row.
    fn need(&self, key: (u32, u8)) -> Result<RecordBatch> {
        self.get(key)?.ok_or_else(|| {
            StageError::Input(format!(
                "no `{}` row for frame {} camera {}",
                self.table.name(),
                key.0,
                key.1
            ))
        })
    }
}

impl<'a> Sources<'a> {
    fn new(inputs: &Inputs<'a>) -> Result<Self> {
        let index = |slot: &str, table: &str| RowIndex::new(inputs.stored(slot, table)?);
        Ok(Self {
            gt_sem: index("scene", "gt_semantic")?,
            gt_inst: index("scene", "gt_instance")?,
            lidar: index("scene", "lidar_depth")?,
            exact: index("scene", "gt_depth")?,
            pseudo: index("scene", "pseudo_labels")?,
            maps: index("render", "label_maps")?,
        })
    }

    /// The LiDAR depth of image `key`, checked against the image's size.
    fn lidar_depth(&self, key: (u32, u8)) -> Result<Option<Vec<f32>>> {
        let Some(row) = self.lidar.get(key)? else {
            return Ok(None);
        };
        Ok(Some(
            map_f32(&one_image(&row, "lidar_depth")?, "lidar_depth", "depth")?.to_vec(),
        ))
    }
}

/// The camera model of an evaluated image, as the `camera_metrics` table names it.
fn camera_model(c: &CameraRow) -> &'static str {
    match c.cam.lens {
        geometry::Lens::Pinhole => "perspective",
        geometry::Lens::Mei(_) => "fisheye",
    }
}

/// Scores of labels from perspective views carried into fisheye views (cross-view MC).
const ACROSS_MODELS: &str = "perspective_fisheye";

/// The accumulators over all evaluated images and per camera model, and what the per-frame
/// pass keeps for later.
struct Evaluation {
    all: Group,
    /// Per camera model, where the evaluated images have more than one; with one, its group is
    /// `all` (scored once).
    by_model: BTreeMap<&'static str, Group>,
    only_model: Option<&'static str>,
    /// Cross-view consistency per method, perspective LiDAR points carried into fisheye views.
    across: BTreeMap<&'static str, Consistency>,
    /// Label maps per method per evaluated image, kept for multi-view consistency.
    labels_of: BTreeMap<(&'static str, u32, u8), Vec<u8>>,
    gt: GtRows,
    /// Where the rendered depth's error comes from (ours; LiDAR pixels).
    depth_bins: DepthBins<BinKey>,
    /// The scene's moving objects, and their pixels and the rest scored apart (where it has
    /// any).
    moving: MovingObjects,
    by_motion: Option<MotionGroups>,
}

impl Evaluation {
    fn new(p: &EvaluateParams, models: &[&'static str], moving: MovingObjects) -> Result<Self> {
        Ok(Self {
            by_motion: (!moving.is_empty())
                .then(|| MotionGroups::new(p))
                .transpose()?,
            moving,
            depth_bins: DepthBins::new(p.max_depth)?,
            all: Group::new(p)?,
            by_model: match models {
                [_] => BTreeMap::new(),
                _ => models
                    .iter()
                    .map(|&m| Ok((m, Group::new(p)?)))
                    .collect::<Result<_>>()?,
            },
            only_model: match models {
                [m] => Some(*m),
                _ => None,
            },
            across: BTreeMap::new(),
            labels_of: BTreeMap::new(),
            gt: GtRows::default(),
        })
    }

    /// Scores every method on the evaluation image `c`.
    fn add_frame(
        &mut self,
        src: &Sources,
        c: &CameraRow,
        prims: &[Primitive],
        bvh: &Bvh,
    ) -> Result<()> {
        let key = (c.frame, c.camera);
        let g_row = src.gt_sem.need(key)?;
        let g = &one_image(&g_row, "gt_semantic")?;
        let gi_row = src.gt_inst.need(key)?;
        let gi = &one_image(&gi_row, "gt_instance")?;
        let m_row = src.maps.need(key)?;
        let m = &one_image(&m_row, "label_maps")?;
        let lidar = src.lidar_depth(key)?;
        let exact_row = src.exact.get(key)?;
        if (g.width, g.height) != (c.cam.width as usize, c.cam.height as usize)
            || (m.width, m.height) != (g.width, g.height)
        {
            return Err(StageError::Input(format!(
                "frame {} camera {}: image sizes differ between cameras, gt_semantic and label_maps",
                c.frame, c.camera
            )));
        }
        let ps_row = src.pseudo.get(key)?;
        let pseudo = ps_row
            .as_ref()
            .map(|r| map_u8(&one_image(r, "pseudo_labels")?, "pseudo_labels", "labels"))
            .transpose()?;
        let (fp_sem, fp_inst, moving) =
            first_primitive_maps(&c.cam, prims, bvh, self.moving.at(c.frame));
        let gsem = map_u8(g, "gt_semantic", "labels")?;
        let boundary = labels::label_edges(gsem, g.width);
        let f = FrameMaps {
            boundary: &boundary,
            gsem,
            ginst: map_u16(gi, "gt_instance", "instances")?,
            ours: map_u8(m, "label_maps", "semantic")?,
            ours_inst: map_u16(m, "label_maps", "instance")?,
            fixed: map_u8(m, "label_maps", "fixed_semantic")?,
            depth: map_f32(m, "label_maps", "depth")?,
            fp_sem: &fp_sem,
            fp_inst: &fp_inst,
            pseudo,
            lidar: lidar.as_deref(),
            exact: exact_row
                .as_ref()
                .map(|e| {
                    let d = map_f32(&one_image(e, "gt_depth")?, "gt_depth", "depth")?;
                    check_size(d.len(), g, "gt_depth", "depth")?;
                    Ok::<_, StageError>(d)
                })
                .transpose()?,
        };
        self.gt.push(c, g, f.gsem, f.ginst);
        if let Some(lidar) = f.lidar {
            check_size(lidar.len(), g, "lidar_depth", "depth")?;
            let mut inside = Vec::new();
            for (i, (&l, &d)) in lidar.iter().zip(f.depth).enumerate() {
                if l > 0.0 && l.is_finite() {
                    let b = f.boundary[i];
                    let ps = f.pseudo.map(|m| m[i]);
                    let keys = depth_bin_keys(c, i, l, d, f.gsem, b, ps, prims, bvh, &mut inside);
                    self.depth_bins.add(&keys, d, l);
                }
            }
        }
        // Every group this image counts in, scored in parallel: the whole, its camera model's,
        // and (with moving objects) the static and the moving part, each part's GT made in
        // its own task.
        let mut jobs: Vec<(&mut Group, Option<bool>)> = vec![(&mut self.all, None)];
        if let Some(g) = self.by_model.get_mut(camera_model(c)) {
            jobs.push((g, None));
        }
        if let Some(groups) = &mut self.by_motion {
            for (group, in_moving) in groups.parts.iter_mut().zip([false, true]) {
                jobs.push((group, Some(in_moving)));
            }
        }
        jobs.into_par_iter().try_for_each(|(g, part)| match part {
            Some(in_moving) => g.add(&PartGt::of(&f, &moving, in_moving).maps(&f)),
            None => g.add(&f),
        })?;
        for (method, labels) in [
            ("panoptic_nerf", Some(f.ours)),
            ("fixed_field", Some(f.fixed)),
            ("first_primitive", Some(f.fp_sem)),
            ("pseudo_labels", f.pseudo),
        ] {
            if let Some(l) = labels {
                self.labels_of
                    .insert((method, c.frame, c.camera), l.to_vec());
            }
        }
        Ok(())
    }

    /// The label maps `method` gave images `a` and `b`, when it labelled both.
    fn label_pair(
        &self,
        method: &'static str,
        a: &CameraRow,
        b: &CameraRow,
    ) -> Option<(&[u8], &[u8])> {
        let get = |c: &CameraRow| {
            self.labels_of
                .get(&(method, c.frame, c.camera))
                .map(Vec::as_slice)
        };
        Some((get(a)?, get(b)?))
    }

    /// Multi-view consistency over consecutive evaluation frames of each camera, and across
    /// camera models: each frame's perspective LiDAR points carried into its fisheye views.
    fn add_consistency(&mut self, src: &Sources, eval: &[&CameraRow], distance: f64) -> Result<()> {
        for w in eval.windows(2) {
            let (a, b) = (w[0], w[1]);
            if a.camera != b.camera {
                continue;
            }
            let (Some(da), Some(db)) = (
                src.lidar_depth((a.frame, a.camera))?,
                src.lidar_depth((b.frame, b.camera))?,
            ) else {
                continue;
            };
            for &method in METHODS {
                let Some((ma, mb)) = self.label_pair(method, a, b) else {
                    continue;
                };
                let c = multiview_consistency(&view(a, ma, &da), &view(b, mb, &db), distance)?;
                self.all.add_mc(method, &c);
                if let Some(g) = self.by_model.get_mut(camera_model(a)) {
                    g.add_mc(method, &c);
                }
            }
        }
        for a in eval.iter().filter(|c| camera_model(c) == "perspective") {
            let Some(da) = src.lidar_depth((a.frame, a.camera))? else {
                continue;
            };
            for b in eval
                .iter()
                .filter(|b| b.frame == a.frame && camera_model(b) == "fisheye")
            {
                for &method in METHODS {
                    let Some((ma, mb)) = self.label_pair(method, a, b) else {
                        continue;
                    };
                    let size = (b.cam.width as usize, b.cam.height as usize);
                    let project = |p: [f64; 3]| {
                        b.cam
                            .project(geometry::DVec3::from_array(p))
                            .map(|(u, v, _)| (u, v))
                    };
                    let c = cross_view_consistency(
                        &view(a, ma, &da),
                        mb,
                        size,
                        labels::UNLABELED,
                        project,
                    )?;
                    self.across.entry(method).or_default().merge(&c);
                }
            }
        }
        Ok(())
    }

    /// The `depth_breakdown` table.
    fn depth_table(&self) -> Result<RecordBatch> {
        let rows = self.depth_bins.results();
        let f = |get: fn(&BinResult) -> Option<f64>| {
            Arc::new(Float64Array::from(
                rows.iter()
                    .map(|(_, r)| get(r).filter(|v| v.is_finite()))
                    .collect::<Vec<_>>(),
            )) as ArrayRef
        };
        tables::build(
            "depth_breakdown",
            vec![
                tables::strings(rows.iter().map(|(k, _)| k.2).collect::<Vec<_>>()),
                tables::strings(rows.iter().map(|(k, _)| k.3).collect::<Vec<_>>()),
                tables::prim::<UInt64Type>(rows.iter().map(|(_, r)| r.pixels).collect::<Vec<_>>()),
                f(|r| r.rmse),
                f(|r| r.mean_error),
                f(|r| r.delta_1_25),
                f(|r| r.share_sq_error),
            ],
        )
    }

    /// The `metrics`, `class_iou`, `camera_metrics`, `camera_class_iou` and `motion_metrics`
    /// tables. `review`: the review's figures, rows of `panoptic_nerf` in `metrics`.
    fn score_tables(&self, review: &[(String, Option<f64>)]) -> Result<[RecordBatch; 5]> {
        let mut rows = MetricRows::default();
        let mut ciou = ClassRows::default();
        self.all.scores(
            |m, k, v| rows.push(None, m, k, v),
            |m, c| ciou.push(None, m, c),
        );
        for (k, v) in review {
            rows.push(None, "panoptic_nerf", k, *v);
        }
        let mut by_model = MetricRows::default();
        let mut model_ciou = ClassRows::default();
        let groups = self.only_model.map(|m| (m, &self.all)).into_iter();
        for (model, group) in groups.chain(self.by_model.iter().map(|(&m, g)| (m, g))) {
            group.scores(
                |m, k, v| by_model.push(Some(model), m, k, v),
                |m, c| model_ciou.push(Some(model), m, c),
            );
        }
        if !self.across.is_empty() {
            for &method in METHODS {
                let v = self.across.get(method).and_then(|c| c.value());
                by_model.push(Some(ACROSS_MODELS), method, "mc", v);
            }
        }
        let mut by_motion = MetricRows::default();
        for (part, group) in PARTS
            .iter()
            .zip(self.by_motion.iter().flat_map(|m| &m.parts))
        {
            group.scores(|m, k, v| by_motion.push(Some(part), m, k, v), |_, _| {});
        }
        Ok([
            rows.table("metrics")?,
            ciou.table("class_iou")?,
            by_model.table("camera_metrics")?,
            model_ciou.table("camera_class_iou")?,
            by_motion.table("motion_metrics")?,
        ])
    }
}

impl TypedStage for Evaluate {
    type Params = EvaluateParams;
    const KIND: &'static str = "evaluate";
    // 10: with a `review` input, the review's figures against GT in `metrics`.
    // 11: `motion_metrics` (static and moving pixels apart); the first-primitive baseline
    // includes the moving objects' boxes.
    // 12: the parts' `motion_metrics` without the panopticapi and off-boundary depth rows.
    const VERSION: u32 = 12;
    const DESCRIPTION: &'static str =
        "semantic (mIoU, Acc), panoptic (PQ/SQ/RQ, PQ-dagger), multi-view consistency and depth metrics against GT, for the rendered labels and the baselines";
    const INPUTS: &'static [InputSlot] = &[
        InputSlot {
            name: "scene",
            tables: &[
                "scene_info",
                "cameras",
                "primitives",
                "dynamic_boxes",
                "gt_semantic",
                "gt_instance",
                "pseudo_labels",
                "lidar_depth",
            ],
            optional: false,
            doc: "the scene with its ground truth",
        },
        InputSlot {
            name: "render",
            tables: &["label_maps"],
            optional: false,
            doc: "rendered labels",
        },
        InputSlot {
            name: "review",
            tables: &["review_maps", "review_regions"],
            optional: true,
            doc: "the review: how well its score finds the wrong labels (review_* metrics)",
        },
    ];
    const SCORES: Option<&'static ScoreSpec> = Some(&SCORES);
    const OUTPUTS: &'static [&'static str] = &[
        "metrics",
        "class_iou",
        "eval_gt",
        "camera_metrics",
        "camera_class_iou",
        "depth_breakdown",
        "motion_metrics",
    ];

    fn validate(p: &EvaluateParams) -> Result<()> {
        if p.cameras.iter().any(|&c| c > 3) {
            return Err(StageError::Params(
                "`cameras` must list KITTI-360 cameras 0 .. 3 (2, 3: the fisheye cameras)".into(),
            ));
        }
        if p.classes.is_empty() {
            return Err(StageError::Params("`classes` is empty".into()));
        }
        for &c in p.classes.iter().chain(&p.things) {
            if c == 0 || labels::by_id(c).is_none() {
                return Err(StageError::Params(format!(
                    "`classes`: unknown label id {c}"
                )));
            }
        }
        if let Some(t) = p.things.iter().find(|t| !p.classes.contains(t)) {
            return Err(StageError::Params(format!(
                "`things`: {t} is not in `classes`"
            )));
        }
        if !(p.mc_distance > 0.0 && p.max_depth > 0.0) {
            return Err(StageError::Params(
                "`mc_distance` and `max_depth` must be positive".into(),
            ));
        }
        Ok(())
    }

    fn run(&self, p: &EvaluateParams, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        let cameras = geometry::cameras_from_table(inputs.table("scene", "cameras")?)?;
        let prims = geometry::primitives_from_table(inputs.table("scene", "primitives")?)?;
        let bvh = Bvh::build(&prims);
        let maps = Sources::new(inputs)?;
        for &f in &p.frames {
            if !cameras.iter().any(|c| c.eval && c.frame == f) {
                let mut marked: Vec<u32> =
                    cameras.iter().filter(|c| c.eval).map(|c| c.frame).collect();
                marked.dedup();
                return Err(StageError::Params(format!(
                    "`frames`: frame {f} is not an evaluation frame of the scene (those: {marked:?})"
                )));
            }
        }
        let mut eval: Vec<&CameraRow> = cameras
            .iter()
            .filter(|c| c.eval && p.scores(c.camera))
            .filter(|c| p.frames.is_empty() || p.frames.contains(&c.frame))
            .collect();
        eval.sort_by_key(|c| (c.camera, c.frame));
        // No evaluation image (a sequence without 2D GT, the usual case): the tables say so
        // (`frames` 0, every score null) and the report and `metrics.json` say why.
        let mut models: Vec<&'static str> = eval.iter().map(|c| camera_model(c)).collect();
        models.sort_unstable();
        models.dedup();
        let moving = geometry::dynamic_boxes_from_table(inputs.table("scene", "dynamic_boxes")?)?;
        let mut run = Evaluation::new(p, &models, MovingObjects::new(moving))?;
        for (n, c) in eval.iter().enumerate() {
            progress.update(n as u64, eval.len() as u64, "evaluating");
            run.add_frame(&maps, c, &prims, &bvh)?;
        }
        run.add_consistency(&maps, &eval, p.mc_distance)?;
        let review = review::review_figures(inputs, |c| p.scores(c), progress)?;
        let [metrics, class_iou, camera_metrics, camera_class_iou, motion_metrics] =
            run.score_tables(&review)?;
        let depth_breakdown = run.depth_table()?;
        let info = inputs.table("scene", "scene_info")?;
        let sequence = tables::get_strings(info, "scene_info", "sequence")?;
        if sequence.is_empty() {
            return Err(StageError::Input("table `scene_info` is empty".into()));
        }
        let eval_gt = run.gt.table(sequence.value(0))?;
        Ok(Tables::from([
            ("metrics".to_string(), metrics),
            ("class_iou".to_string(), class_iou),
            ("eval_gt".to_string(), eval_gt),
            ("camera_metrics".to_string(), camera_metrics),
            ("camera_class_iou".to_string(), camera_class_iou),
            ("depth_breakdown".to_string(), depth_breakdown),
            ("motion_metrics".to_string(), motion_metrics),
        ]))
    }

    fn export(&self, _: &EvaluateParams, t: &TableSet, dir: &Path) -> Result<Vec<PathBuf>> {
        let mut json = metrics_json(&t.whole_tables()?)?;
        if t.table("eval_gt")?.num_rows() == 0 {
            json["not_evaluated"] = serde_json::json!(scores::NOT_EVALUATED);
        }
        let conventions: serde_json::Map<String, serde_json::Value> = PQ_CONVENTIONS
            .iter()
            .map(|(k, v)| (k.to_string(), serde_json::json!(v)))
            .collect();
        json["pq_conventions"] = serde_json::Value::Object(conventions);
        json["by_camera_model"] =
            camera_metrics_json(t.table("camera_metrics")?, t.table("camera_class_iou")?)?;
        json["depth_breakdown"] = depth_breakdown_json(t.table("depth_breakdown")?)?;
        json["by_motion"] = motion_metrics_json(t.table("motion_metrics")?)?;
        let path = dir.join("metrics.json");
        std::fs::write(&path, serde_json::to_vec_pretty(&json).unwrap_or_default())
            .map_err(|e| StageError::Failed(format!("writing {}: {e}", path.display())))?;
        let mut files = vec![path];
        let gt = t.table("eval_gt")?;
        let seq = tables::get_strings(gt, "eval_gt", "sequence")?;
        let frames = tables::get_prim::<UInt32Type>(gt, "eval_gt", "frame")?;
        let cams = tables::get_prim::<UInt8Type>(gt, "eval_gt", "camera")?;
        let w = tables::get_prim::<UInt32Type>(gt, "eval_gt", "width")?;
        let h = tables::get_prim::<UInt32Type>(gt, "eval_gt", "height")?;
        let sem = tables::get_list::<UInt8Type>(gt, "eval_gt", "semantic")?;
        let inst = tables::get_list::<UInt16Type>(gt, "eval_gt", "instance")?;
        for r in 0..gt.num_rows() {
            let name = crate::pngio::label_file_name(seq.value(r), frames[r], cams[r]);
            let s = dir.join("gt/semantic").join(&name);
            crate::pngio::write_gray8(&s, w[r], h[r], sem.row(r))?;
            let i = dir.join("gt/instance").join(&name);
            crate::pngio::write_gray16(&i, w[r], h[r], inst.row(r))?;
            files.extend([s, i]);
        }
        Ok(files)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A stored-style per-image table of two images, the second with one value too few.
    fn gt_semantic() -> Table {
        let batch = tables::build(
            "gt_semantic",
            vec![
                tables::prim::<UInt32Type>([3, 4]),
                tables::prim::<UInt8Type>([0, 2]),
                tables::prim::<UInt32Type>([2, 2]),
                tables::prim::<UInt32Type>([1, 1]),
                tables::list::<UInt8Type>([vec![7, 8], vec![9]]),
            ],
        )
        .unwrap();
        Table::memory("gt_semantic", batch)
    }

    #[test]
    fn images_are_read_one_row_at_a_time_and_checked() {
        let table = gt_semantic();
        let index = RowIndex::new(&table).unwrap();
        let row = index.need((3, 0)).unwrap();
        assert_eq!(row.num_rows(), 1);
        let img = one_image(&row, "gt_semantic").unwrap();
        assert_eq!((img.width, img.height), (2, 1));
        assert_eq!(map_u8(&img, "gt_semantic", "labels").unwrap(), &[7, 8]);

        let e = index.need((3, 2)).unwrap_err().to_string();
        assert!(
            e.contains("no `gt_semantic` row for frame 3 camera 2"),
            "{e}"
        );
        assert!(index.get((3, 2)).unwrap().is_none());

        let short = index.need((4, 2)).unwrap();
        let e = map_u8(
            &one_image(&short, "gt_semantic").unwrap(),
            "gt_semantic",
            "labels",
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("gt_semantic") && e.contains("labels") && e.contains("2x1"),
            "{e}"
        );
        let e = one_image(&table.whole().unwrap().clone(), "gt_semantic")
            .map(|_| ())
            .unwrap_err()
            .to_string();
        assert!(e.contains("one image's row, got 2"), "{e}");
    }
}
