//! Accumulators of the evaluation: per method over a set of images (all evaluated images, or
//! one camera model's), the per-image maps they read, and the rows of the tables they fill.

use std::{collections::BTreeMap, sync::Arc};

use arrow::{
    array::{ArrayRef, Float64Array},
    datatypes::{UInt16Type, UInt32Type, UInt64Type, UInt8Type},
    record_batch::RecordBatch,
};

use super::images::Image;
use super::params::{EvaluateParams, PANOPTICAPI_SUFFIX};
use crate::metrics::scores::METHODS;
use crate::{
    geometry::CameraRow,
    labels,
    metrics::{
        ConfusionMatrix, Consistency, DepthAccumulator, DepthMetrics, PanopticAccumulator,
        PanopticConfig, PanopticResult, PqSummary,
    },
    tables, Result,
};

/// Columns of the `eval_gt` table.
#[derive(Default)]
pub(super) struct GtRows {
    pub(super) frame: Vec<u32>,
    pub(super) camera: Vec<u8>,
    pub(super) width: Vec<u32>,
    pub(super) height: Vec<u32>,
    pub(super) semantic: Vec<Vec<u8>>,
    pub(super) instance: Vec<Vec<u16>>,
}

impl GtRows {
    pub(super) fn push(&mut self, c: &CameraRow, g: &Image, semantic: &[u8], instance: &[u16]) {
        self.frame.push(c.frame);
        self.camera.push(c.camera);
        self.width.push(g.width as u32);
        self.height.push(g.height as u32);
        self.semantic.push(semantic.to_vec());
        self.instance.push(instance.to_vec());
    }

    /// The `eval_gt` table.
    pub(super) fn table(self, sequence: &str) -> Result<RecordBatch> {
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

/// Columns of the `class_iou` table, or of `camera_class_iou` (the same per camera model).
#[derive(Default)]
pub(super) struct ClassRows {
    pub(super) camera_model: Vec<String>,
    pub(super) method: Vec<String>,
    pub(super) label: Vec<u8>,
    pub(super) name: Vec<String>,
    pub(super) iou: Vec<Option<f64>>,
    pub(super) tp: Vec<u64>,
    pub(super) fp: Vec<u64>,
    pub(super) fn_: Vec<u64>,
}

impl ClassRows {
    /// Rows of `method`'s classes; `camera_model` is `None` for the `class_iou` table.
    pub(super) fn push(
        &mut self,
        camera_model: Option<&str>,
        method: &str,
        confusion: &ConfusionMatrix,
    ) {
        for row in confusion.table() {
            if let Some(model) = camera_model {
                self.camera_model.push(model.to_string());
            }
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

    /// `class_iou`, or `camera_class_iou` when the rows were pushed with a camera model.
    pub(super) fn table(self, name: &str) -> Result<RecordBatch> {
        let mut columns = Vec::with_capacity(8);
        if name == "camera_class_iou" {
            columns.push(tables::strings(&self.camera_model));
        }
        columns.extend([
            tables::strings(&self.method),
            tables::prim::<UInt8Type>(self.label),
            tables::strings(&self.name),
            Arc::new(Float64Array::from(self.iou)) as ArrayRef,
            tables::prim::<UInt64Type>(self.tp),
            tables::prim::<UInt64Type>(self.fp),
            tables::prim::<UInt64Type>(self.fn_),
        ]);
        tables::build(name, columns)
    }
}

/// The `metrics` rows of the scene's exact depth scored against the LiDAR (depth metrics only).
pub(super) const EXACT_DEPTH: &str = "exact_depth";

/// Accumulators of one method.
pub(super) struct MethodSums {
    pub(super) confusion: ConfusionMatrix,
    pub(super) panoptic: Option<PanopticAccumulator>,
    /// The same panoptic maps scored as panopticapi (and the KITTI-360 and Cityscapes scripts
    /// built on it) does: no small-segment rules.
    pub(super) panopticapi: Option<PanopticAccumulator>,
    pub(super) depth: Option<DepthAccumulator>,
    /// The same over LiDAR pixels inside GT regions (not on a class boundary).
    pub(super) depth_interior: Option<DepthAccumulator>,
    /// Against the scene's exact depth at every pixel centre (synthetic scenes).
    pub(super) depth_exact: Option<DepthAccumulator>,
    /// The same off GT class boundaries: the geometry where a pixel sees one surface.
    pub(super) depth_exact_interior: Option<DepthAccumulator>,
    pub(super) mc: Option<Consistency>,
}

impl MethodSums {
    /// One frame's panoptic maps, under both conventions.
    pub(super) fn add_panoptic(
        &mut self,
        gsem: &[u8],
        ginst: &[u16],
        sem: &[u8],
        inst: &[u16],
    ) -> Result<()> {
        self.panoptic
            .as_mut()
            .expect("a panoptic method")
            .add_frame(gsem, ginst, sem, inst)?;
        if let Some(api) = &mut self.panopticapi {
            api.add_frame(gsem, ginst, sem, inst)?;
        }
        Ok(())
    }
}

/// The accumulators of every method over one set of images (all evaluated images, or one
/// camera model's).
pub(super) struct Group {
    pub(super) sums: BTreeMap<&'static str, MethodSums>,
    /// The scene's exact depth scored against the LiDAR as ours is (whole image, inside
    /// regions): the floor the LiDAR metric sets on a perfect geometry.
    pub(super) exact_vs_lidar: [DepthAccumulator; 2],
    pub(super) frames: usize,
    pub(super) pseudo_frames: usize,
    /// A part of the images' pixels (static or moving): scored by the headline metrics only,
    /// without the panopticapi convention and the depth off class boundaries.
    part: bool,
}

impl Group {
    pub(super) fn new(p: &EvaluateParams) -> Result<Self> {
        Self::build(p, false)
    }

    /// The group of a part of the images' pixels.
    pub(super) fn for_part(p: &EvaluateParams) -> Result<Self> {
        Self::build(p, true)
    }

    fn build(p: &EvaluateParams, part: bool) -> Result<Self> {
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
            let depth_acc = || -> Result<Option<DepthAccumulator>> {
                Ok(depth
                    .then(|| DepthAccumulator::new(p.max_depth))
                    .transpose()?)
            };
            Ok(MethodSums {
                confusion: ConfusionMatrix::new(&p.classes)?,
                panoptic: acc(&pan_cfg)?,
                panopticapi: if part { None } else { acc(&api_cfg)? },
                depth: depth_acc()?,
                depth_interior: if part { None } else { depth_acc()? },
                depth_exact: depth_acc()?,
                depth_exact_interior: if part { None } else { depth_acc()? },
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
            exact_vs_lidar: [
                DepthAccumulator::new(p.max_depth)?,
                DepthAccumulator::new(p.max_depth)?,
            ],
            frames: 0,
            pseudo_frames: 0,
            part,
        })
    }

    /// One evaluated image's maps (`pseudo`: the pseudo labels, where the image has them).
    pub(super) fn add(&mut self, f: &FrameMaps) -> Result<()> {
        self.frames += 1;
        let s = self.sums.get_mut("panoptic_nerf").unwrap();
        s.confusion.add(f.gsem, f.ours)?;
        s.add_panoptic(f.gsem, f.ginst, f.ours, f.ours_inst)?;
        if let Some(l) = f.lidar {
            s.depth.as_mut().unwrap().add(f.depth, l)?;
            if let Some(d) = &mut s.depth_interior {
                let interior = off_boundary(l, f.boundary);
                d.add(f.depth, &interior)?;
                if let Some(exact) = f.exact {
                    self.exact_vs_lidar[0].add(exact, l)?;
                    self.exact_vs_lidar[1].add(exact, &interior)?;
                }
            }
        }
        if let Some(exact) = f.exact {
            s.depth_exact.as_mut().unwrap().add(f.depth, exact)?;
            if let Some(d) = &mut s.depth_exact_interior {
                d.add(f.depth, &off_boundary(exact, f.boundary))?;
            }
        }
        let s = self.sums.get_mut("fixed_field").unwrap();
        s.confusion.add(f.gsem, f.fixed)?;
        let s = self.sums.get_mut("first_primitive").unwrap();
        s.confusion.add(f.gsem, f.fp_sem)?;
        s.add_panoptic(f.gsem, f.ginst, f.fp_sem, f.fp_inst)?;
        if let Some(ps) = f.pseudo {
            let s = self.sums.get_mut("pseudo_labels").unwrap();
            s.confusion.add(f.gsem, ps)?;
            self.pseudo_frames += 1;
        }
        Ok(())
    }

    pub(super) fn add_mc(&mut self, method: &str, c: &Consistency) {
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
    pub(super) fn scores(
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
                if self.part && !suffix.is_empty() {
                    continue;
                }
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
            for (suffix, acc) in [
                ("", &s.depth),
                ("_interior", &s.depth_interior),
                ("_exact", &s.depth_exact),
                ("_exact_interior", &s.depth_exact_interior),
            ] {
                if self.part && suffix.ends_with("_interior") {
                    continue;
                }
                push_depth(&mut push, method, suffix, acc.as_ref().map(|d| d.result()));
            }
            ciou(method, &s.confusion);
        }
        let [whole, interior] = [0, 1].map(|k| self.exact_vs_lidar[k].result());
        if whole.pixels > 0 {
            push_depth(&mut push, EXACT_DEPTH, "", Some(whole));
            push_depth(&mut push, EXACT_DEPTH, "_interior", Some(interior));
        }
    }
}

/// A reference depth with the pixels on a GT class boundary set to 0 (no reference there).
fn off_boundary(depth: &[f32], boundary: &[bool]) -> Vec<f32> {
    depth
        .iter()
        .zip(boundary)
        .map(|(&d, &b)| if b { 0.0 } else { d })
        .collect()
}

/// `depth_rmse{suffix}` and `depth_delta_1_25{suffix}` of `method`.
fn push_depth(
    push: &mut impl FnMut(&str, &str, Option<f64>),
    method: &str,
    suffix: &str,
    d: Option<DepthMetrics>,
) {
    push(
        method,
        &format!("depth_rmse{suffix}"),
        d.and_then(|d| d.rmse),
    );
    push(
        method,
        &format!("depth_delta_1_25{suffix}"),
        d.and_then(|d| d.delta_1_25),
    );
}

/// One evaluated image's maps: GT, each method's labels, LiDAR where the image has it.
#[derive(Clone, Copy)]
pub(super) struct FrameMaps<'a> {
    pub(super) gsem: &'a [u8],
    pub(super) ginst: &'a [u16],
    pub(super) ours: &'a [u8],
    pub(super) ours_inst: &'a [u16],
    pub(super) fixed: &'a [u8],
    pub(super) depth: &'a [f32],
    pub(super) fp_sem: &'a [u8],
    pub(super) fp_inst: &'a [u16],
    pub(super) pseudo: Option<&'a [u8]>,
    pub(super) lidar: Option<&'a [f32]>,
    /// The scene's exact depth (z-depth as ours', 0 = none), where the scene has one.
    pub(super) exact: Option<&'a [f32]>,
    /// Per pixel: on a GT class boundary ([`crate::labels::label_edges`]).
    pub(super) boundary: &'a [bool],
}

/// Rows of the `metrics` table (no group), or of `camera_metrics` or `motion_metrics`.
#[derive(Default)]
pub(super) struct MetricRows {
    pub(super) model: Vec<String>,
    pub(super) method: Vec<String>,
    pub(super) metric: Vec<String>,
    pub(super) value: Vec<Option<f64>>,
}

impl MetricRows {
    pub(super) fn push(&mut self, model: Option<&str>, method: &str, metric: &str, v: Option<f64>) {
        if let Some(m) = model {
            self.model.push(m.to_string());
        }
        self.method.push(method.to_string());
        self.metric.push(metric.to_string());
        self.value.push(v.filter(|x| x.is_finite()));
    }

    pub(super) fn table(self, name: &str) -> Result<RecordBatch> {
        let mut cols = Vec::new();
        // `camera_metrics` and `motion_metrics` lead with their group (camera model, part).
        if name != "metrics" {
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
