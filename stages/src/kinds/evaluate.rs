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
    datatypes::{Float32Type, UInt16Type, UInt32Type, UInt64Type, UInt8Type},
    record_batch::RecordBatch,
};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::metrics::scores::{self, METHODS, SCORES};
use crate::{
    geometry::{self, Bvh, CameraRow, Primitive},
    labels,
    metrics::{
        cross_view_consistency, multiview_consistency, BinResult, ConfusionMatrix, Consistency,
        DepthAccumulator, DepthBins, LabelledView, PanopticAccumulator, PanopticConfig,
        PanopticResult, Pinhole, PqSummary,
    },
    tables, InputSlot, Inputs, Progress, Result, ScoreSpec, StageError, Table, TableSet, Tables,
    TypedStage,
};

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EvaluateParams {
    /// Cameras evaluated (0 = left, 1 = right, 2 and 3 the fisheye cameras); KITTI-360 has GT
    /// for the left camera only.
    #[serde(deserialize_with = "crate::geometry::camera::camera_ids")]
    pub cameras: Vec<u8>,
    /// Evaluated classes (label ids); default: the paper's 14 classes.
    pub classes: Vec<u8>,
    /// Thing classes for PQ; default: building, car, caravan, trailer, box.
    pub things: Vec<u8>,
    /// GT segments under this many pixels are void; predicted ones are relabelled sky.
    pub min_segment_px: usize,
    /// Matching distance of LiDAR points for multi-view consistency, metres.
    pub mc_distance: f64,
    /// Depth metrics use LiDAR pixels closer than this, metres.
    pub max_depth: f64,
}

impl Default for EvaluateParams {
    fn default() -> Self {
        Self {
            cameras: vec![0],
            classes: labels::PAPER_CLASSES.to_vec(),
            things: labels::PAPER_THINGS.to_vec(),
            min_segment_px: 100,
            mc_distance: 0.1,
            max_depth: 100.0,
        }
    }
}

pub struct Evaluate;

/// One image's maps, keyed by (frame, camera).
struct Image<'a> {
    width: usize,
    height: usize,
    row: usize,
    batch: &'a RecordBatch,
}

fn index_images<'a>(batch: &'a RecordBatch, table: &str) -> Result<HashMap<(u32, u8), Image<'a>>> {
    let frames = tables::get_prim::<UInt32Type>(batch, table, "frame")?;
    let cams = tables::get_prim::<UInt8Type>(batch, table, "camera")?;
    let w = tables::get_prim::<UInt32Type>(batch, table, "width")?;
    let h = tables::get_prim::<UInt32Type>(batch, table, "height")?;
    Ok((0..batch.num_rows())
        .map(|r| {
            (
                (frames[r], cams[r]),
                Image {
                    width: w[r] as usize,
                    height: h[r] as usize,
                    row: r,
                    batch,
                },
            )
        })
        .collect())
}

fn map_u8<'a>(img: &Image<'a>, table: &str, col: &str) -> Result<&'a [u8]> {
    let v = tables::get_list::<UInt8Type>(img.batch, table, col)?.row(img.row);
    check_size(v.len(), img, table, col)?;
    Ok(v)
}

fn map_u16<'a>(img: &Image<'a>, table: &str, col: &str) -> Result<&'a [u16]> {
    let v = tables::get_list::<UInt16Type>(img.batch, table, col)?.row(img.row);
    check_size(v.len(), img, table, col)?;
    Ok(v)
}

fn map_f32<'a>(img: &Image<'a>, table: &str, col: &str) -> Result<&'a [f32]> {
    let v = tables::get_list::<Float32Type>(img.batch, table, col)?.row(img.row);
    check_size(v.len(), img, table, col)?;
    Ok(v)
}

fn check_size(len: usize, img: &Image, table: &str, col: &str) -> Result<()> {
    if len != img.width * img.height {
        return Err(StageError::Input(format!(
            "table `{table}` row {} column `{col}` has {len} values, expected {}x{}",
            img.row, img.width, img.height
        )));
    }
    Ok(())
}

/// Label and panoptic maps of "the first primitive each ray hits" (sky where none is hit).
pub fn first_primitive_maps(
    cam: &geometry::Camera,
    prims: &[Primitive],
    bvh: &Bvh,
) -> (Vec<u8>, Vec<u16>) {
    let n = (cam.width * cam.height) as usize;
    let mut sem = vec![labels::SKY; n];
    let mut inst = vec![labels::SKY as u16 * labels::INSTANCE_FACTOR as u16; n];
    sem.par_iter_mut()
        .zip(inst.par_iter_mut())
        .enumerate()
        .for_each(|(i, (s, ins))| {
            let (x, y) = ((i as u32) % cam.width, (i as u32) / cam.width);
            let Some(ray) = cam.pixel_ray(x, y) else {
                *s = labels::UNLABELED;
                *ins = 0;
                return;
            };
            if let Some(hit) = bvh.first_hit(prims, &ray, 0.0, f64::INFINITY) {
                let p = &prims[hit.prim as usize];
                *s = p.label;
                *ins = (p.label as u32 * labels::INSTANCE_FACTOR + p.instance.min(999)) as u16;
            }
        });
    (sem, inst)
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

/// Columns of the `eval_gt` table.
#[derive(Default)]
struct GtRows {
    frame: Vec<u32>,
    camera: Vec<u8>,
    width: Vec<u32>,
    height: Vec<u32>,
    semantic: Vec<Vec<u8>>,
    instance: Vec<Vec<u16>>,
}

impl GtRows {
    fn push(&mut self, c: &CameraRow, g: &Image, semantic: &[u8], instance: &[u16]) {
        self.frame.push(c.frame);
        self.camera.push(c.camera);
        self.width.push(g.width as u32);
        self.height.push(g.height as u32);
        self.semantic.push(semantic.to_vec());
        self.instance.push(instance.to_vec());
    }

    /// The `eval_gt` table.
    fn table(self, sequence: &str) -> Result<RecordBatch> {
        tables::build(
            "eval_gt",
            vec![
                tables::strings(vec![sequence; self.frame.len()]),
                tables::prim::<UInt32Type>(self.frame),
                tables::prim::<UInt8Type>(self.camera),
                tables::prim::<UInt32Type>(self.width),
                tables::prim::<UInt32Type>(self.height),
                tables::list::<UInt8Type>(self.semantic),
                tables::list::<UInt16Type>(self.instance),
            ],
        )
    }
}

/// Columns of the `class_iou` table.
#[derive(Default)]
struct ClassRows {
    method: Vec<String>,
    label: Vec<u8>,
    name: Vec<String>,
    iou: Vec<Option<f64>>,
    tp: Vec<u64>,
    fp: Vec<u64>,
    fn_: Vec<u64>,
}

impl ClassRows {
    fn push(&mut self, method: &str, confusion: &ConfusionMatrix) {
        for row in confusion.table() {
            self.method.push(method.to_string());
            self.label.push(row.class);
            self.name
                .push(labels::by_id(row.class).map_or("?", |l| l.name).to_string());
            self.iou.push(row.iou);
            self.tp.push(row.tp);
            self.fp.push(row.fp);
            self.fn_.push(row.fn_);
        }
    }

    fn table(self) -> Result<RecordBatch> {
        tables::build(
            "class_iou",
            vec![
                tables::strings(&self.method),
                tables::prim::<UInt8Type>(self.label),
                tables::strings(&self.name),
                Arc::new(Float64Array::from(self.iou)) as ArrayRef,
                tables::prim::<UInt64Type>(self.tp),
                tables::prim::<UInt64Type>(self.fp),
                tables::prim::<UInt64Type>(self.fn_),
            ],
        )
    }
}

/// Metric names ending in this (`pq_panopticapi`, `pq_things_panopticapi`, ...) score the
/// panoptic maps as panopticapi does: every predicted segment counts, however small. Without
/// it (`pq`, ...): the Panoptic NeRF paper's convention, where predicted segments under
/// `min_segment_px` become sky first. In both, GT segments under it are void (the exported GT).
pub const PANOPTICAPI_SUFFIX: &str = "_panopticapi";

/// What each PQ convention means, as `metrics.json` states it.
pub const PQ_CONVENTIONS: &[(&str, &str)] = &[
    (
        "pq",
        "Panoptic NeRF paper: predicted segments under min_segment_px (100) pixels are relabelled sky and GT segments under it are void, before matching",
    ),
    (
        "pq_panopticapi",
        "panopticapi (COCO; the Cityscapes and KITTI-360 scripts): predicted segments as they are, no relabelling; the same GT (segments under min_segment_px void, as exported)",
    ),
];

/// Accumulators of one method.
struct MethodSums {
    confusion: ConfusionMatrix,
    panoptic: Option<PanopticAccumulator>,
    /// The same panoptic maps scored as panopticapi (and the KITTI-360 and Cityscapes scripts
    /// built on it) does: no small-segment rules.
    panopticapi: Option<PanopticAccumulator>,
    depth: Option<DepthAccumulator>,
    /// The same over LiDAR pixels inside GT regions (not on a class boundary).
    depth_interior: Option<DepthAccumulator>,
    mc: Option<Consistency>,
}

impl MethodSums {
    /// One frame's panoptic maps, under both conventions.
    fn add_panoptic(&mut self, gsem: &[u8], ginst: &[u16], sem: &[u8], inst: &[u16]) -> Result<()> {
        for acc in [&mut self.panoptic, &mut self.panopticapi] {
            acc.as_mut()
                .expect("a panoptic method")
                .add_frame(gsem, ginst, sem, inst)?;
        }
        Ok(())
    }
}

/// The per-image tables evaluation reads, indexed by (frame, camera). The ground truth and
/// LiDAR exist for the evaluation images only and are read whole; pseudo labels and label maps
/// exist for every image and are read one evaluated image at a time.
struct Sources<'a> {
    gt_sem: HashMap<(u32, u8), Image<'a>>,
    gt_inst: HashMap<(u32, u8), Image<'a>>,
    lidar: HashMap<(u32, u8), Image<'a>>,
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
}

impl<'a> Sources<'a> {
    fn new(inputs: &Inputs<'a>) -> Result<Self> {
        let index = |slot: &str, table: &str| index_images(inputs.table(slot, table)?, table);
        Ok(Self {
            gt_sem: index("scene", "gt_semantic")?,
            gt_inst: index("scene", "gt_instance")?,
            lidar: index("scene", "lidar_depth")?,
            pseudo: RowIndex::new(inputs.stored("scene", "pseudo_labels")?)?,
            maps: RowIndex::new(inputs.stored("render", "label_maps")?)?,
        })
    }

    fn lidar_depth(&self, key: (u32, u8)) -> Result<Option<&'a [f32]>> {
        self.lidar
            .get(&key)
            .map(|l| map_f32(l, "lidar_depth", "depth"))
            .transpose()
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

/// The accumulators of every method over one set of images (all evaluated images, or one
/// camera model's).
struct Group {
    sums: BTreeMap<&'static str, MethodSums>,
    frames: usize,
    pseudo_frames: usize,
}

impl Group {
    fn new(p: &EvaluateParams) -> Result<Self> {
        let pan_cfg = PanopticConfig {
            classes: p.classes.clone(),
            things: p.things.clone(),
            min_gt_segment_px: p.min_segment_px,
            min_pred_segment_px: Some(p.min_segment_px),
            sky_id: labels::SKY,
        };
        let api_cfg = pan_cfg.clone().panopticapi();
        let new_sums = |panoptic: bool, depth: bool| -> Result<MethodSums> {
            let acc = |cfg: &PanopticConfig| -> Result<Option<PanopticAccumulator>> {
                Ok(if panoptic {
                    Some(PanopticAccumulator::new(cfg.clone())?)
                } else {
                    None
                })
            };
            Ok(MethodSums {
                confusion: ConfusionMatrix::new(&p.classes)?,
                panoptic: acc(&pan_cfg)?,
                panopticapi: acc(&api_cfg)?,
                depth: if depth {
                    Some(DepthAccumulator::new(p.max_depth)?)
                } else {
                    None
                },
                depth_interior: if depth {
                    Some(DepthAccumulator::new(p.max_depth)?)
                } else {
                    None
                },
                mc: Some(Consistency::default()),
            })
        };
        let mut sums: BTreeMap<&'static str, MethodSums> = BTreeMap::new();
        sums.insert("panoptic_nerf", new_sums(true, true)?);
        sums.insert("fixed_field", new_sums(false, false)?);
        sums.insert("pseudo_labels", new_sums(false, false)?);
        sums.insert("first_primitive", new_sums(true, false)?);
        Ok(Self {
            sums,
            frames: 0,
            pseudo_frames: 0,
        })
    }

    /// One evaluated image's maps (`pseudo`: the pseudo labels, where the image has them).
    fn add(&mut self, f: &FrameMaps) -> Result<()> {
        self.frames += 1;
        let s = self.sums.get_mut("panoptic_nerf").unwrap();
        s.confusion.add(f.gsem, f.ours)?;
        s.add_panoptic(f.gsem, f.ginst, f.ours, f.ours_inst)?;
        if let Some(l) = f.lidar {
            s.depth.as_mut().unwrap().add(f.depth, l)?;
            let interior: Vec<f32> = l
                .iter()
                .zip(&f.boundary)
                .map(|(&d, &b)| if b { 0.0 } else { d })
                .collect();
            s.depth_interior.as_mut().unwrap().add(f.depth, &interior)?;
        }
        let s = self.sums.get_mut("fixed_field").unwrap();
        s.confusion.add(f.gsem, f.fixed)?;
        let s = self.sums.get_mut("first_primitive").unwrap();
        s.confusion.add(f.gsem, &f.fp_sem)?;
        s.add_panoptic(f.gsem, f.ginst, &f.fp_sem, &f.fp_inst)?;
        if let Some(ps) = f.pseudo {
            let s = self.sums.get_mut("pseudo_labels").unwrap();
            s.confusion.add(f.gsem, ps)?;
            self.pseudo_frames += 1;
        }
        Ok(())
    }

    fn add_mc(&mut self, method: &str, c: &Consistency) {
        self.sums
            .get_mut(method)
            .unwrap()
            .mc
            .as_mut()
            .unwrap()
            .merge(c);
    }

    /// Every method's scores, as `push(method, metric, value)` calls; each method's confusion
    /// matrix goes to `ciou`.
    fn scores(
        &self,
        mut push: impl FnMut(&str, &str, Option<f64>),
        mut ciou: impl FnMut(&str, &ConfusionMatrix),
    ) {
        for &method in METHODS {
            let s = &self.sums[method];
            let frames = if method == "pseudo_labels" {
                self.pseudo_frames
            } else {
                self.frames
            };
            push(method, "frames", Some(frames as f64));
            push(method, "pixels", Some(s.confusion.total() as f64));
            push(method, "miou", s.confusion.miou());
            push(method, "acc", s.confusion.accuracy());
            let pan = s.panoptic.as_ref().map(|a| a.result());
            let api = s.panopticapi.as_ref().map(|a| a.result());
            for (suffix, res) in [("", &pan), (PANOPTICAPI_SUFFIX, &api)] {
                let part = |f: fn(&PanopticResult) -> Option<PqSummary>| res.as_ref().and_then(f);
                for (prefix, summary) in [
                    ("", part(|r| r.all)),
                    ("_things", part(|r| r.things)),
                    ("_stuff", part(|r| r.stuff)),
                ] {
                    push(
                        method,
                        &format!("pq{prefix}{suffix}"),
                        summary.map(|x| x.pq),
                    );
                    push(
                        method,
                        &format!("sq{prefix}{suffix}"),
                        summary.map(|x| x.sq),
                    );
                    push(
                        method,
                        &format!("rq{prefix}{suffix}"),
                        summary.map(|x| x.rq),
                    );
                }
            }
            push(method, "pq_dagger", pan.as_ref().and_then(|r| r.pq_dagger));
            push(method, "mc", s.mc.and_then(|c| c.value()));
            let d = s.depth.as_ref().map(|d| d.result());
            push(method, "depth_rmse", d.and_then(|d| d.rmse));
            push(method, "depth_delta_1_25", d.and_then(|d| d.delta_1_25));
            let d = s.depth_interior.as_ref().map(|d| d.result());
            push(method, "depth_rmse_interior", d.and_then(|d| d.rmse));
            push(
                method,
                "depth_delta_1_25_interior",
                d.and_then(|d| d.delta_1_25),
            );
            ciou(method, &s.confusion);
        }
    }
}

/// One evaluated image's maps: GT, each method's labels, LiDAR where the image has it.
struct FrameMaps<'a> {
    gsem: &'a [u8],
    ginst: &'a [u16],
    ours: &'a [u8],
    ours_inst: &'a [u16],
    fixed: &'a [u8],
    depth: &'a [f32],
    fp_sem: Vec<u8>,
    fp_inst: Vec<u16>,
    pseudo: Option<&'a [u8]>,
    lidar: Option<&'a [f32]>,
    /// Per pixel: on a GT class boundary ([`class_boundary`]).
    boundary: Vec<bool>,
}

/// The accumulators over all evaluated images and per camera model, and what the per-frame
/// pass keeps for later.
struct Evaluation {
    all: Group,
    by_model: BTreeMap<&'static str, Group>,
    /// Cross-view consistency per method, perspective LiDAR points carried into fisheye views.
    across: BTreeMap<&'static str, Consistency>,
    /// Label maps per method per evaluated image, kept for multi-view consistency.
    labels_of: BTreeMap<(&'static str, u32, u8), Vec<u8>>,
    gt: GtRows,
    /// Where the rendered depth's error comes from (ours; LiDAR pixels).
    depth_bins: DepthBins<BinKey>,
}

/// A bin of the depth breakdown: (group order, bin order, group, bin).
type BinKey = (u8, u16, &'static str, String);

/// Distance bands of the depth breakdown (LiDAR depth, metres; the last one ends at
/// `max_depth`).
const DEPTH_BANDS: [f64; 4] = [0.0, 10.0, 20.0, 40.0];

/// Per pixel of a `width`-wide GT label map: whether a different class is among its 8
/// neighbours (a class boundary, where LiDAR and camera, or foreground and background, meet).
fn class_boundary(gsem: &[u8], width: usize) -> Vec<bool> {
    let h = gsem.len() / width.max(1);
    (0..gsem.len())
        .map(|i| {
            let (x, y) = ((i % width) as i64, (i / width) as i64);
            (-1..=1).any(|dy| {
                (-1..=1).any(|dx| {
                    let (nx, ny) = (x + dx, y + dy);
                    nx >= 0
                        && ny >= 0
                        && (nx as usize) < width
                        && (ny as usize) < h
                        && gsem[ny as usize * width + nx as usize] != gsem[i]
                })
            })
        })
        .collect()
}

/// The bins of LiDAR pixel `i` of image `c`: all pixels; its distance band; its GT class;
/// whether it lies on a GT class boundary (a different GT class among its 8 neighbours);
/// whether a depth was rendered (opacity > 0.5); how many classes the fixed field has at the
/// LiDAR point (the primitives containing it).
#[allow(clippy::too_many_arguments)]
fn depth_bin_keys(
    c: &CameraRow,
    i: usize,
    lidar: f32,
    rendered: f32,
    gsem: &[u8],
    boundary: bool,
    prims: &[Primitive],
    bvh: &Bvh,
    inside: &mut Vec<u32>,
) -> Vec<BinKey> {
    let w = c.cam.width as usize;
    let (x, y) = (i % w, i / w);
    let g = f64::from(lidar);
    let band = DEPTH_BANDS.iter().rposition(|&lo| g >= lo).unwrap_or(0);
    let band_name = match DEPTH_BANDS.get(band + 1) {
        Some(hi) => format!("{:.0}-{:.0} m", DEPTH_BANDS[band], hi),
        None => format!(">= {:.0} m", DEPTH_BANDS[band]),
    };
    let class = gsem[i];
    let class_name = labels::by_id(class).map_or("?", |l| l.name).to_string();
    let fixed = match c.cam.ray_and_dir_cam(x as f64 + 0.5, y as f64 + 0.5) {
        Some((ray, d_cam)) => {
            bvh.containing(prims, ray.at(g / c.cam.depth_scale(d_cam)), inside);
            let mut classes: Vec<u8> = inside.iter().map(|&p| prims[p as usize].label).collect();
            classes.sort_unstable();
            classes.dedup();
            match classes.len() {
                0 => (2, "in no primitive"),
                1 => (0, "one class"),
                _ => (1, "several classes (overlapping primitives)"),
            }
        }
        None => (2, "in no primitive"),
    };
    vec![
        (0, 0, "all", "all".to_string()),
        (1, band as u16, "distance", band_name),
        (2, u16::from(class), "class", class_name),
        (
            3,
            u16::from(boundary),
            "boundary",
            if boundary {
                "on a class boundary (GT, 8-neighbourhood)"
            } else {
                "inside a region"
            }
            .to_string(),
        ),
        (
            4,
            u16::from(rendered <= 0.0 || !rendered.is_finite()),
            "rendered",
            if rendered > 0.0 && rendered.is_finite() {
                "depth rendered"
            } else {
                "no depth rendered (opacity <= 0.5: scored as 0 m)"
            }
            .to_string(),
        ),
        (5, fixed.0, "fixed field", fixed.1.to_string()),
    ]
}

impl Evaluation {
    fn new(p: &EvaluateParams, models: &[&'static str]) -> Result<Self> {
        Ok(Self {
            depth_bins: DepthBins::new(p.max_depth)?,
            all: Group::new(p)?,
            by_model: models
                .iter()
                .map(|&m| Ok((m, Group::new(p)?)))
                .collect::<Result<_>>()?,
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
        let missing = |what: &str| {
            StageError::Input(format!(
                "no `{what}` row for frame {} camera {}",
                c.frame, c.camera
            ))
        };
        let key = (c.frame, c.camera);
        let g = src.gt_sem.get(&key).ok_or_else(|| missing("gt_semantic"))?;
        let gi = src
            .gt_inst
            .get(&key)
            .ok_or_else(|| missing("gt_instance"))?;
        let m_row = src.maps.get(key)?.ok_or_else(|| missing("label_maps"))?;
        let m_index = index_images(&m_row, "label_maps")?;
        let m = &m_index[&key];
        if (g.width, g.height) != (c.cam.width as usize, c.cam.height as usize)
            || (m.width, m.height) != (g.width, g.height)
        {
            return Err(StageError::Input(format!(
                "frame {} camera {}: image sizes differ between cameras, gt_semantic and label_maps",
                c.frame, c.camera
            )));
        }
        let ps_row = src.pseudo.get(key)?;
        let ps_index = ps_row
            .as_ref()
            .map(|r| index_images(r, "pseudo_labels"))
            .transpose()?;
        let pseudo = ps_index
            .as_ref()
            .map(|i| map_u8(&i[&key], "pseudo_labels", "labels"))
            .transpose()?;
        let (fp_sem, fp_inst) = first_primitive_maps(&c.cam, prims, bvh);
        let gsem = map_u8(g, "gt_semantic", "labels")?;
        let f = FrameMaps {
            boundary: class_boundary(gsem, g.width),
            gsem,
            ginst: map_u16(gi, "gt_instance", "instances")?,
            ours: map_u8(m, "label_maps", "semantic")?,
            ours_inst: map_u16(m, "label_maps", "instance")?,
            fixed: map_u8(m, "label_maps", "fixed_semantic")?,
            depth: map_f32(m, "label_maps", "depth")?,
            fp_sem,
            fp_inst,
            pseudo,
            lidar: src.lidar_depth(key)?,
        };
        self.gt.push(c, g, f.gsem, f.ginst);
        if let Some(lidar) = f.lidar {
            check_size(lidar.len(), g, "lidar_depth", "depth")?;
            let mut inside = Vec::new();
            for (i, (&l, &d)) in lidar.iter().zip(f.depth).enumerate() {
                if l > 0.0 && l.is_finite() {
                    let b = f.boundary[i];
                    let keys = depth_bin_keys(c, i, l, d, f.gsem, b, prims, bvh, &mut inside);
                    self.depth_bins.add(&keys, d, l);
                }
            }
        }
        self.all.add(&f)?;
        self.by_model
            .get_mut(camera_model(c))
            .expect("a group per evaluated camera model")
            .add(&f)?;
        for (method, labels) in [
            ("panoptic_nerf", Some(f.ours)),
            ("fixed_field", Some(f.fixed)),
            ("first_primitive", Some(&f.fp_sem[..])),
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
                let c = multiview_consistency(&view(a, ma, da), &view(b, mb, db), distance)?;
                self.all.add_mc(method, &c);
                self.by_model
                    .get_mut(camera_model(a))
                    .expect("a group per evaluated camera model")
                    .add_mc(method, &c);
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
                        &view(a, ma, da),
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
                tables::strings(rows.iter().map(|(k, _)| k.3.as_str()).collect::<Vec<_>>()),
                tables::prim::<UInt64Type>(rows.iter().map(|(_, r)| r.pixels).collect::<Vec<_>>()),
                f(|r| r.rmse),
                f(|r| r.mean_error),
                f(|r| r.delta_1_25),
                f(|r| r.share_sq_error),
            ],
        )
    }

    /// The `metrics`, `class_iou` and `camera_metrics` tables.
    fn score_tables(&self) -> Result<(RecordBatch, RecordBatch, RecordBatch)> {
        let mut rows = MetricRows::default();
        let mut ciou = ClassRows::default();
        self.all
            .scores(|m, k, v| rows.push(None, m, k, v), |m, c| ciou.push(m, c));
        let mut by_model = MetricRows::default();
        for (&model, group) in &self.by_model {
            group.scores(|m, k, v| by_model.push(Some(model), m, k, v), |_, _| {});
        }
        if !self.across.is_empty() {
            for &method in METHODS {
                let v = self.across.get(method).and_then(|c| c.value());
                by_model.push(Some(ACROSS_MODELS), method, "mc", v);
            }
        }
        Ok((
            rows.table("metrics")?,
            ciou.table()?,
            by_model.table("camera_metrics")?,
        ))
    }
}

/// Rows of the `metrics` table (no camera model) or the `camera_metrics` table.
#[derive(Default)]
struct MetricRows {
    model: Vec<String>,
    method: Vec<String>,
    metric: Vec<String>,
    value: Vec<Option<f64>>,
}

impl MetricRows {
    fn push(&mut self, model: Option<&str>, method: &str, metric: &str, v: Option<f64>) {
        if let Some(m) = model {
            self.model.push(m.to_string());
        }
        self.method.push(method.to_string());
        self.metric.push(metric.to_string());
        self.value.push(v.filter(|x| x.is_finite()));
    }

    fn table(self, name: &str) -> Result<RecordBatch> {
        let mut cols = Vec::new();
        if name == "camera_metrics" {
            cols.push(tables::strings(&self.model));
        }
        cols.extend([
            tables::strings(&self.method),
            tables::strings(&self.metric),
            Arc::new(Float64Array::from(self.value)) as ArrayRef,
        ]);
        tables::build(name, cols)
    }
}

impl TypedStage for Evaluate {
    type Params = EvaluateParams;
    const KIND: &'static str = "evaluate";
    const VERSION: u32 = 4;
    const DESCRIPTION: &'static str =
        "semantic (mIoU, Acc), panoptic (PQ/SQ/RQ, PQ-dagger), multi-view consistency and depth metrics against GT, for the rendered labels and the baselines";
    const INPUTS: &'static [InputSlot] = &[
        InputSlot {
            name: "scene",
            tables: &[
                "scene_info",
                "cameras",
                "primitives",
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
    ];
    const SCORES: Option<&'static ScoreSpec> = Some(&SCORES);
    const OUTPUTS: &'static [&'static str] = &[
        "metrics",
        "class_iou",
        "eval_gt",
        "camera_metrics",
        "depth_breakdown",
    ];

    fn validate(p: &EvaluateParams) -> Result<()> {
        if p.cameras.is_empty() || p.cameras.iter().any(|&c| c > 3) {
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
        let mut eval: Vec<&CameraRow> = cameras
            .iter()
            .filter(|c| c.eval && p.cameras.contains(&c.camera))
            .collect();
        eval.sort_by_key(|c| (c.camera, c.frame));
        // No evaluation image (a sequence without 2D GT, the usual case): the tables say so
        // (`frames` 0, every score null) and the report and `metrics.json` say why.
        let mut models: Vec<&'static str> = eval.iter().map(|c| camera_model(c)).collect();
        models.sort_unstable();
        models.dedup();
        let mut run = Evaluation::new(p, &models)?;
        for (n, c) in eval.iter().enumerate() {
            progress.update(n as u64, eval.len() as u64, "evaluating");
            run.add_frame(&maps, c, &prims, &bvh)?;
        }
        run.add_consistency(&maps, &eval, p.mc_distance)?;
        let (metrics, class_iou, camera_metrics) = run.score_tables()?;
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
            ("depth_breakdown".to_string(), depth_breakdown),
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
        json["by_camera_model"] = camera_metrics_json(t.table("camera_metrics")?)?;
        json["depth_breakdown"] = depth_breakdown_json(t.table("depth_breakdown")?)?;
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

/// `[{group, bin, pixels, rmse, mean_error, delta_1_25, share_sq_error}]` from the
/// `depth_breakdown` table.
pub fn depth_breakdown_json(t: &RecordBatch) -> Result<serde_json::Value> {
    let table = "depth_breakdown";
    let group = tables::get_strings(t, table, "group")?;
    let bin = tables::get_strings(t, table, "bin")?;
    let pixels = tables::get_prim::<UInt64Type>(t, table, "pixels")?;
    let mut out = Vec::new();
    for (i, &px) in pixels.iter().enumerate() {
        let mut row = serde_json::json!({
            "group": group.value(i),
            "bin": bin.value(i),
            "pixels": px,
        });
        for col in ["rmse", "mean_error", "delta_1_25", "share_sq_error"] {
            let v = t
                .column_by_name(col)
                .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
                .ok_or_else(|| StageError::Input(format!("{table}.{col} is not float64")))?;
            row[col] = if v.is_null(i) {
                serde_json::Value::Null
            } else {
                serde_json::json!(v.value(i))
            };
        }
        out.push(row);
    }
    Ok(serde_json::Value::Array(out))
}

/// `{camera model: {method: {metric: value}}}` from the `camera_metrics` table.
pub fn camera_metrics_json(t: &RecordBatch) -> Result<serde_json::Value> {
    let models = tables::get_strings(t, "camera_metrics", "camera_model")?;
    let methods = tables::get_strings(t, "camera_metrics", "method")?;
    let metrics = tables::get_strings(t, "camera_metrics", "metric")?;
    let values = t
        .column_by_name("value")
        .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
        .ok_or_else(|| StageError::Input("camera_metrics.value is not float64".into()))?;
    let mut out = serde_json::json!({});
    for i in 0..t.num_rows() {
        let v = if values.is_null(i) {
            serde_json::Value::Null
        } else {
            serde_json::json!(values.value(i))
        };
        let model = out
            .as_object_mut()
            .expect("an object")
            .entry(models.value(i))
            .or_insert_with(|| serde_json::json!({}));
        let method = model
            .as_object_mut()
            .expect("an object")
            .entry(methods.value(i))
            .or_insert_with(|| serde_json::json!({}));
        method[metrics.value(i)] = v;
    }
    Ok(out)
}

/// `{method: {metric: value, ..., "class_iou": {class name: iou}}}` from the stage's tables.
pub fn metrics_json(t: &Tables) -> Result<serde_json::Value> {
    let get = |name: &str| {
        t.get(name)
            .ok_or_else(|| StageError::Input(format!("evaluate output lacks table `{name}`")))
    };
    let m = get("metrics")?;
    let methods = tables::get_strings(m, "metrics", "method")?;
    let metrics = tables::get_strings(m, "metrics", "metric")?;
    let values = m
        .column_by_name("value")
        .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
        .ok_or_else(|| StageError::Input("metrics.value is not float64".into()))?;
    let mut out = serde_json::Map::new();
    for i in 0..m.num_rows() {
        let entry = out
            .entry(methods.value(i).to_string())
            .or_insert_with(|| serde_json::json!({}));
        let v = if values.is_null(i) {
            serde_json::Value::Null
        } else {
            serde_json::json!(values.value(i))
        };
        entry[metrics.value(i)] = v;
    }
    let c = get("class_iou")?;
    let cm = tables::get_strings(c, "class_iou", "method")?;
    let cn = tables::get_strings(c, "class_iou", "name")?;
    let ci = c
        .column_by_name("iou")
        .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
        .ok_or_else(|| StageError::Input("class_iou.iou is not float64".into()))?;
    for i in 0..c.num_rows() {
        let entry = out
            .entry(cm.value(i).to_string())
            .or_insert_with(|| serde_json::json!({}));
        if entry.get("class_iou").is_none() {
            entry["class_iou"] = serde_json::json!({});
        }
        entry["class_iou"][cn.value(i)] = if ci.is_null(i) {
            serde_json::Value::Null
        } else {
            serde_json::json!(ci.value(i))
        };
    }
    Ok(serde_json::Value::Object(out))
}
