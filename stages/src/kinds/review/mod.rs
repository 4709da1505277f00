//! The `review` stage kind: where the rendered labels are likely wrong, without ground truth.
//! Per pixel a review score and its reason ([`crate::review`]); flagged pixels grouped into
//! regions, regions of one primitive linked across frames into a ranked queue; coverage gaps
//! (surfaces no primitive covers); per image its score and coverage. One image at a time.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use arrow::array::Array;
use arrow::datatypes::{Float32Type, UInt16Type, UInt8Type};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::geometry::{self, Camera, CameraRow, Primitive};
use crate::intervals::{may_see_sky, ImagePlan};
use crate::review::{
    regions::connected_regions, review_image, ImageSignals, Shape, Weights, GAP, NO_PRIMITIVE,
};
use crate::stage::{InputSlot, Inputs, Progress, Result, StageError, TableSet, Tables, TypedStage};
use crate::tables;

mod export;
mod queue;

use queue::{Region, RegionKind};

#[derive(Debug, Clone, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct ReviewParams {
    /// Pixels scoring at least this (an estimated probability of a wrong label) are flagged.
    pub flag: f32,
    /// Width of the boundary band, as a share of the image width (8 pixels at 1408).
    pub boundary_band: f32,
    /// Slack in metres when the rendered depth is tested against a primitive's interval.
    pub depth_slack_m: f32,
    /// Regions under this share of their image are not listed. Their pixels stay flagged in
    /// the maps.
    pub min_region: f64,
    /// The score's logistic weights (docs/experiments/review.md).
    pub weights: Weights,
}

impl Default for ReviewParams {
    fn default() -> Self {
        Self {
            flag: 0.5,
            boundary_band: 0.0057,
            depth_slack_m: 0.5,
            min_region: 2e-5,
            weights: Weights::default(),
        }
    }
}

pub struct Review;

/// The smallest `min_region`: an image then has at most 65535 regions.
const MIN_REGION_LOWEST: f64 = 1.0 / u16::MAX as f64;

/// The `label_maps` and `ray_intervals` columns the review reads.
const MAP_COLUMNS: &[&str] = &["semantic", "fixed_semantic", "depth", "confidence"];
const PLAN_COLUMNS: &[&str] = &["hits", "t_in", "t_out", "prim"];

/// Per pixel of a camera's image: the camera-frame ray direction (`None` outside the lens).
/// It depends on the intrinsics only, so it is computed once per camera model.
fn pixel_directions(cam: &Camera) -> Vec<Option<glam::DVec3>> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    (0..w * h)
        .into_par_iter()
        .map(|p| cam.dir_cam((p % w) as f64 + 0.5, (p / w) as f64 + 0.5))
        .collect()
}

/// Per pixel of `cam` (directions from [`pixel_directions`]): depth per metre along the ray
/// (0: no ray), and whether it may see sky.
fn ray_geometry(cam: &Camera, dirs: &[Option<glam::DVec3>]) -> (Vec<f32>, Vec<bool>) {
    let rot = cam.cam_to_world.matrix3;
    dirs.par_iter()
        .map(|d| match d {
            Some(d) => (
                cam.depth_scale(*d) as f32,
                may_see_sky((rot * *d).normalize()),
            ),
            None => (0.0, false),
        })
        .unzip()
}

/// What one reviewed image adds to the outputs.
struct Reviewed {
    maps_row: arrow::record_batch::RecordBatch,
    regions: Vec<Region>,
    frame_row: queue::FrameRow,
}

/// Counts of keys, the most frequent first-seen on ties.
#[derive(Default)]
struct Tally<K: Eq + std::hash::Hash + Copy>(Vec<(K, u32)>);

impl<K: Eq + std::hash::Hash + Copy> Tally<K> {
    fn add(&mut self, k: K) {
        match self.0.iter_mut().find(|(x, _)| *x == k) {
            Some((_, n)) => *n += 1,
            None => self.0.push((k, 1)),
        }
    }
    fn most(&self) -> Option<K> {
        let mut best: Option<(K, u32)> = None;
        for &(k, n) in &self.0 {
            if best.is_none_or(|(_, m)| n > m) {
                best = Some((k, n));
            }
        }
        best.map(|(k, _)| k)
    }
}

/// One region under construction.
struct Growing {
    pixels: u32,
    bbox: [u32; 4],
    class: Tally<u8>,
    reason: Tally<u8>,
    primitive: Tally<u32>,
    score: f64,
}

/// The regions of `mask` (labels `ids`, `count` of them), listed when at least `min_pixels`.
#[allow(clippy::too_many_arguments)]
fn grow(
    ids: &[u32],
    count: u32,
    width: usize,
    class: &[u8],
    reason: &[u8],
    primitive: &[u32],
    score: &[f32],
) -> Vec<Growing> {
    let mut out: Vec<Growing> = (0..count)
        .map(|_| Growing {
            pixels: 0,
            bbox: [u32::MAX, u32::MAX, 0, 0],
            class: Tally::default(),
            reason: Tally::default(),
            primitive: Tally::default(),
            score: 0.0,
        })
        .collect();
    for (p, &id) in ids.iter().enumerate() {
        if id == 0 {
            continue;
        }
        let g = &mut out[id as usize - 1];
        let (x, y) = ((p % width) as u32, (p / width) as u32);
        g.pixels += 1;
        g.bbox = [
            g.bbox[0].min(x),
            g.bbox[1].min(y),
            g.bbox[2].max(x),
            g.bbox[3].max(y),
        ];
        g.class.add(class[p]);
        g.reason.add(reason[p]);
        g.primitive.add(primitive[p]);
        g.score += score[p] as f64;
    }
    out
}

/// Reviews one image (its regions numbered from 1).
#[allow(clippy::too_many_arguments)]
fn review_one(
    p: &ReviewParams,
    seq: &str,
    c: &CameraRow,
    maps: &arrow::record_batch::RecordBatch,
    plan: &ImagePlan,
    pseudo: Option<&[u8]>,
    dirs: &[Option<glam::DVec3>],
) -> Result<Reviewed> {
    const M: &str = "label_maps";
    let (w, h) = (c.cam.width as usize, c.cam.height as usize);
    let n = w * h;
    let ours = tables::get_list::<UInt8Type>(maps, M, "semantic")?.row(0);
    let fixed = tables::get_list::<UInt8Type>(maps, M, "fixed_semantic")?.row(0);
    let confidence = tables::get_list::<Float32Type>(maps, M, "confidence")?.row(0);
    let depth = tables::get_list::<Float32Type>(maps, M, "depth")?.row(0);
    for (col, len) in [
        ("semantic", ours.len()),
        ("fixed_semantic", fixed.len()),
        ("confidence", confidence.len()),
        ("depth", depth.len()),
    ] {
        if len != n {
            return Err(StageError::Input(format!(
                "label_maps frame {} camera {}: `{col}` has {len} values, the camera {w}x{h}",
                c.frame, c.camera
            )));
        }
    }
    if let Some(ps) = pseudo.filter(|ps| ps.len() != n) {
        return Err(StageError::Input(format!(
            "pseudo_labels frame {} camera {}: {} values, the camera {w}x{h}",
            c.frame,
            c.camera,
            ps.len()
        )));
    }
    let (depth_scale, sky) = ray_geometry(&c.cam, dirs);
    let signals = ImageSignals {
        width: w,
        height: h,
        ours,
        fixed,
        confidence,
        depth,
        pseudo,
        plan,
        depth_scale: &depth_scale,
        may_see_sky: &sky,
    };
    let shape = Shape {
        band: (p.boundary_band * w as f32).max(1e-3),
        slack: p.depth_slack_m,
    };
    let r = review_image(&signals, &p.weights, shape);
    let flagged: Vec<bool> = r.score.iter().map(|&s| s >= p.flag).collect();
    let label_mask: Vec<bool> = flagged.iter().zip(&r.gap).map(|(&f, &g)| f && !g).collect();
    let min_pixels = ((p.min_region * n as f64).ceil() as u32).max(1);
    // Coverage gaps take the pseudo label as their class (0 without one).
    let no_pseudo = if pseudo.is_none() {
        vec![0u8; n]
    } else {
        Vec::new()
    };
    let mut region_map = vec![0u16; n];
    let mut regions = Vec::new();
    for (kind, mask, class) in [
        (RegionKind::Label, &label_mask, ours),
        (
            RegionKind::CoverageGap,
            &r.gap,
            pseudo.unwrap_or(&no_pseudo),
        ),
    ] {
        let (ids, count) = connected_regions(mask, w, h);
        let grown = grow(&ids, count, w, class, &r.reason, &r.primitive, &r.score);
        let mut number = vec![0u16; count as usize];
        for (k, g) in grown.into_iter().enumerate() {
            if g.pixels < min_pixels {
                continue;
            }
            let index = (regions.len() + 1).min(u16::MAX as usize) as u16;
            number[k] = index;
            let primitive = g.primitive.most().filter(|&q| q != NO_PRIMITIVE);
            regions.push(Region {
                id: regions.len() as u32 + 1,
                frame: c.frame,
                camera: c.camera,
                index,
                kind,
                class: g.class.most().unwrap_or(0),
                reason: g.reason.most().unwrap_or(GAP),
                primitive: if kind == RegionKind::CoverageGap {
                    None
                } else {
                    primitive
                },
                pixels: g.pixels,
                bbox: g.bbox,
                expected_wrong: g.score,
            });
        }
        for (m, &id) in region_map.iter_mut().zip(&ids) {
            if id > 0 && number[id as usize - 1] > 0 {
                *m = number[id as usize - 1];
            }
        }
    }
    let rays = depth_scale.iter().filter(|&&s| s > 0.0).count().max(1) as f64;
    let gap_pixels = r.gap.iter().filter(|&&g| g).count() as u64;
    let frame_row = queue::FrameRow {
        frame: c.frame,
        camera: c.camera,
        score: r.score.iter().map(|&s| (s as f64).powi(2)).sum::<f64>() / rays,
        flagged: flagged.iter().filter(|&&f| f).count() as f64 / rays,
        coverage: 1.0 - gap_pixels as f64 / rays,
        gap_pixels,
        regions: regions.len() as u32,
    };
    let reason: Vec<u8> = r
        .reason
        .iter()
        .zip(flagged.iter().zip(&r.gap))
        .map(|(&why, (&f, &g))| if f || g { why } else { 0 })
        .collect();
    let score: Vec<u16> = r
        .score
        .iter()
        .map(|&s| crate::metrics::detection::level(s) as u16)
        .collect();
    let maps_row = tables::build(
        "review_maps",
        vec![
            tables::strings([seq]),
            tables::prim::<arrow::datatypes::UInt32Type>([c.frame]),
            tables::prim::<UInt8Type>([c.camera]),
            tables::prim::<arrow::datatypes::UInt32Type>([w as u32]),
            tables::prim::<arrow::datatypes::UInt32Type>([h as u32]),
            tables::list::<UInt16Type>([score]),
            tables::list::<UInt8Type>([reason]),
            tables::list::<UInt16Type>([region_map]),
        ],
    )?;
    Ok(Reviewed {
        maps_row,
        regions,
        frame_row,
    })
}

impl TypedStage for Review {
    type Params = ReviewParams;
    const KIND: &'static str = "review";
    const VERSION: u32 = 1;
    const DESCRIPTION: &'static str =
        "where the labels are likely wrong, without GT: per-pixel review score and reason, regions, a ranked queue of objects, coverage gaps";
    const INPUTS: &'static [InputSlot] = &[
        InputSlot {
            name: "scene",
            tables: &["scene_info", "cameras", "primitives", "pseudo_labels"],
            optional: false,
            doc: "the scene: cameras, primitives and pseudo labels",
        },
        InputSlot {
            name: "rays",
            tables: &["ray_intervals"],
            optional: false,
            doc: "the primitive intervals of every pixel",
        },
        InputSlot {
            name: "render",
            tables: &["label_maps"],
            optional: false,
            doc: "the rendered labels, fixed field, confidence and depth",
        },
    ];
    const OUTPUTS: &'static [&'static str] = &[
        "review_maps",
        "review_regions",
        "review_queue",
        "review_frames",
    ];

    fn validate(p: &ReviewParams) -> Result<()> {
        if !(p.flag > 0.0 && p.flag <= 1.0) {
            return Err(StageError::Params(format!(
                "`flag`: {} must be in (0, 1]",
                p.flag
            )));
        }
        if !(p.boundary_band > 0.0 && p.boundary_band < 1.0) {
            return Err(StageError::Params(format!(
                "`boundary_band`: {} must be in (0, 1)",
                p.boundary_band
            )));
        }
        if !(p.depth_slack_m >= 0.0 && p.depth_slack_m.is_finite()) {
            return Err(StageError::Params(format!(
                "`depth_slack_m`: {} must be >= 0",
                p.depth_slack_m
            )));
        }
        // At most 1 / min_region regions an image: their numbers fit the 16-bit region maps.
        if !(MIN_REGION_LOWEST..1.0).contains(&p.min_region) {
            return Err(StageError::Params(format!(
                "`min_region`: {} must be in [1/65535, 1) (region numbers are 16-bit)",
                p.min_region
            )));
        }
        let w = &p.weights;
        for (k, v) in [
            ("bias", w.bias),
            ("confidence", w.confidence),
            ("pseudo", w.pseudo),
            ("fixed", w.fixed),
            ("boundary", w.boundary),
            ("near_boundary", w.near_boundary),
            ("outside", w.outside),
            ("gap", w.gap),
        ] {
            if !v.is_finite() {
                return Err(StageError::Params(format!(
                    "`weights.{k}`: {v} must be finite"
                )));
            }
        }
        Ok(())
    }

    fn run(&self, p: &ReviewParams, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        let cams = geometry::cameras_from_table(inputs.table("scene", "cameras")?)?;
        let prims: Vec<Primitive> =
            geometry::primitives_from_table(inputs.table("scene", "primitives")?)?;
        let seq = tables::get_strings(
            inputs.table("scene", "scene_info")?,
            "scene_info",
            "sequence",
        )?;
        let seq = if seq.is_empty() {
            "scene".to_string()
        } else {
            seq.value(0).to_string()
        };
        let maps = inputs.stored("render", "label_maps")?;
        let plan = inputs.stored("rays", "ray_intervals")?;
        let pseudo = inputs.stored("scene", "pseudo_labels")?;
        let (plan_rows, pseudo_rows) = (plan.image_rows()?, pseudo.image_rows()?);
        // Every rendered scene image with a plan (novel views have none).
        let by_key: HashMap<(u32, u8), &CameraRow> =
            cams.iter().map(|c| ((c.frame, c.camera), c)).collect();
        let mut images: Vec<(usize, &CameraRow, usize)> = maps
            .image_rows()?
            .into_iter()
            .filter_map(|(key, row)| {
                let c = *by_key.get(&key)?;
                Some((row, c, *plan_rows.get(&key)?))
            })
            .collect();
        images.sort_by_key(|(_, c, _)| (c.frame, c.camera));
        let mut out = inputs.writer("review_maps")?;
        let mut regions: Vec<Region> = Vec::new();
        let mut frames = Vec::new();
        // A few images at a time, reviewed in parallel and written in order: memory stays that
        // of a few images whatever their number.
        // The camera-frame ray directions of each camera model, once.
        let mut directions: Vec<(&Camera, Vec<Option<glam::DVec3>>)> = Vec::new();
        for (_, c, _) in &images {
            if !directions.iter().any(|(k, _)| k.same_pixels(&c.cam)) {
                directions.push((&c.cam, pixel_directions(&c.cam)));
            }
        }
        let directions_of = |cam: &Camera| {
            directions
                .iter()
                .find(|(k, _)| k.same_pixels(cam))
                .map(|(_, d)| d.as_slice())
                .expect("directions of every camera model")
        };
        // At most 8 images in flight (a full-size image takes some 50 MB here).
        let batch = (rayon::current_num_threads().max(1) * 2).min(8);
        for (k, chunk) in images.chunks(batch).enumerate() {
            progress.update((k * batch) as u64, images.len() as u64, "reviewing");
            let reviewed: Vec<Reviewed> = chunk
                .par_iter()
                .map(|&(row, c, plan_row)| -> Result<Reviewed> {
                    let at = |e: StageError| {
                        StageError::Input(format!("frame {} camera {}: {e}", c.frame, c.camera))
                    };
                    // Only the columns the review reads: a third of a full-size image's bytes.
                    let m = maps.rows(row..row + 1, Some(MAP_COLUMNS))?;
                    let n = (c.cam.width * c.cam.height) as usize;
                    let plan_row = plan.rows(plan_row..plan_row + 1, Some(PLAN_COLUMNS))?;
                    let image_plan =
                        ImagePlan::intervals_from_row(&plan_row, 0, n, prims.len()).map_err(at)?;
                    let ps_batch = pseudo_rows
                        .get(&(c.frame, c.camera))
                        .map(|&r| pseudo.row(r))
                        .transpose()
                        .map_err(at)?;
                    let ps = ps_batch
                        .as_ref()
                        .map(|b| {
                            tables::get_list::<UInt8Type>(b, "pseudo_labels", "labels")
                                .map(|l| l.row(0))
                        })
                        .transpose()
                        .map_err(at)?;
                    review_one(p, &seq, c, &m, &image_plan, ps, directions_of(&c.cam))
                })
                .collect::<Result<_>>()?;
            for mut r in reviewed {
                let base = regions.len() as u32;
                r.regions.iter_mut().for_each(|g| g.id += base);
                out.write(r.maps_row)?;
                regions.extend(r.regions);
                frames.push(r.frame_row);
            }
        }
        progress.update(images.len() as u64, images.len() as u64, "ranking");
        let mut tables = Tables::new();
        out.finish_into(&mut tables)?;
        tables.insert(
            "review_regions".into(),
            queue::regions_table(&seq, &regions)?,
        );
        tables.insert("review_queue".into(), queue::queue_table(&regions, &prims)?);
        tables.insert("review_frames".into(), queue::frames_table(&seq, &frames)?);
        Ok(tables)
    }

    fn export(&self, _: &ReviewParams, t: &TableSet, dir: &Path) -> Result<Vec<PathBuf>> {
        export::export(t, dir)
    }
}
