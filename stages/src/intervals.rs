//! The sampling plan's intervals (the `ray_intervals` table, written by the `intersect` kind):
//! for every pixel of every selected image, the intervals of the first `k` primitive intervals its ray crosses (sorted by entry),
//! and a sky interval beyond the farthest one when fewer than `k` are kept. Empty space is never
//! sampled; rays that meet nothing are marked (`hits = 0`) so later stages render them as sky
//! without evaluating a network. Output: `ray_intervals` (see `data_schema/ray_intervals.json`).

use arrow::{
    datatypes::{Float32Type, UInt32Type, UInt8Type},
    record_batch::RecordBatch,
};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::{
    geometry::{Bvh, Camera, CameraRow, Hit, Primitive},
    labels, tables, Result, StageError,
};

/// Parameters of the `intersect` stage.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct IntersectParams {
    /// Maximum number of primitive intervals kept per ray (the paper's 10); 1..=255.
    pub k: u32,
    /// Length in metres of the sky interval appended beyond the last kept interval.
    pub sky_interval: f64,
    /// Maximum ray length in metres considered; intervals are clipped to it.
    pub far: f64,
    /// Camera ids to process (0 = left, 1 = right).
    pub cameras: Vec<u8>,
}

impl Default for IntersectParams {
    fn default() -> Self {
        Self {
            k: 10,
            sky_interval: 50.0,
            far: 200.0,
            cameras: vec![0, 1],
        }
    }
}

/// The per-pixel plan of one image, before it becomes a table row.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct ImagePlan {
    pub hits: Vec<u8>,
    pub t_in: Vec<f32>,
    pub t_out: Vec<f32>,
    pub prim: Vec<u32>,
    pub sky_t0: Vec<f32>,
    pub sky_t1: Vec<f32>,
    pub first_label: Vec<u8>,
    pub first_instance: Vec<u32>,
}

impl ImagePlan {
    fn append(&mut self, o: ImagePlan) {
        self.hits.extend(o.hits);
        self.t_in.extend(o.t_in);
        self.t_out.extend(o.t_out);
        self.prim.extend(o.prim);
        self.sky_t0.extend(o.sky_t0);
        self.sky_t1.extend(o.sky_t1);
        self.first_label.extend(o.first_label);
        self.first_instance.extend(o.first_instance);
    }

    /// Adds one pixel from its sorted hits (all of them within `[0, far]`).
    fn push_pixel(&mut self, prims: &[Primitive], hits: &[Hit], p: &IntersectParams) {
        let kept = &hits[..hits.len().min(p.k as usize)];
        self.hits.push(kept.len() as u8);
        let mut t_far = 0f64;
        for h in kept {
            self.t_in.push(h.t_in as f32);
            self.t_out.push(h.t_out as f32);
            self.prim.push(h.prim);
            t_far = t_far.max(h.t_out);
        }
        let sky = if !kept.is_empty() && kept.len() < p.k as usize {
            p.sky_interval
        } else {
            0.0
        };
        self.sky_t0.push(t_far as f32);
        self.sky_t1.push((t_far + sky) as f32);
        match kept.first() {
            Some(h) => {
                let pr = &prims[h.prim as usize];
                self.first_label.push(pr.label);
                self.first_instance.push(pr.instance);
            }
            None => {
                self.first_label.push(labels::SKY);
                self.first_instance.push(0);
            }
        }
    }
}

/// The plan of one image: rows of pixels in parallel (rayon), one hit buffer per row.
pub fn plan_image(prims: &[Primitive], bvh: &Bvh, cam: &Camera, p: &IntersectParams) -> ImagePlan {
    let rows: Vec<ImagePlan> = (0..cam.height)
        .into_par_iter()
        .map_init(Vec::new, |hits, y| {
            let mut row = ImagePlan::default();
            for x in 0..cam.width {
                let ray = cam.pixel_ray(x, y);
                bvh.intersect_all(prims, &ray, 0.0, p.far, hits);
                row.push_pixel(prims, hits, p);
            }
            row
        })
        .collect();
    let mut plan = ImagePlan::default();
    for r in rows {
        plan.append(r);
    }
    plan
}

/// Builds the `ray_intervals` table from `(camera row, plan)` pairs.
pub fn plans_to_table(k: u32, images: &[(&CameraRow, ImagePlan)]) -> Result<RecordBatch> {
    let col = |f: fn(&ImagePlan) -> Vec<f32>| {
        tables::list::<Float32Type>(images.iter().map(|(_, p)| f(p)))
    };
    tables::build(
        "ray_intervals",
        vec![
            tables::prim::<UInt32Type>(images.iter().map(|(r, _)| r.frame)),
            tables::prim::<UInt8Type>(images.iter().map(|(r, _)| r.camera)),
            tables::prim::<UInt32Type>(images.iter().map(|(r, _)| r.cam.width)),
            tables::prim::<UInt32Type>(images.iter().map(|(r, _)| r.cam.height)),
            tables::prim::<UInt32Type>(images.iter().map(|_| k)),
            tables::list::<UInt8Type>(images.iter().map(|(_, p)| p.hits.clone())),
            col(|p| p.t_in.clone()),
            col(|p| p.t_out.clone()),
            tables::list::<UInt32Type>(images.iter().map(|(_, p)| p.prim.clone())),
            col(|p| p.sky_t0.clone()),
            col(|p| p.sky_t1.clone()),
            tables::list::<UInt8Type>(images.iter().map(|(_, p)| p.first_label.clone())),
            tables::list::<UInt32Type>(images.iter().map(|(_, p)| p.first_instance.clone())),
        ],
    )
}

/// Stage kind `intersect`.
/// A "first primitive hit" picture of one image.
pub struct FirstHitImage {
    pub frame: u32,
    pub camera: u8,
    pub image: image::RgbImage,
}

/// Colours each pixel by the class of its first primitive (`labels::color`), brightened or
/// darkened per instance so neighbouring things separate, and darkened with distance (up to
/// `far`); sky where nothing is hit.
pub fn first_hit_images(table: &RecordBatch, far: f64) -> Result<Vec<FirstHitImage>> {
    const T: &str = "ray_intervals";
    let frame = tables::get_prim::<UInt32Type>(table, T, "frame")?;
    let camera = tables::get_prim::<UInt8Type>(table, T, "camera")?;
    let width = tables::get_prim::<UInt32Type>(table, T, "width")?;
    let height = tables::get_prim::<UInt32Type>(table, T, "height")?;
    let hits = tables::get_list::<UInt8Type>(table, T, "hits")?;
    let t_in = tables::get_list::<Float32Type>(table, T, "t_in")?;
    let label = tables::get_list::<UInt8Type>(table, T, "first_label")?;
    let inst = tables::get_list::<UInt32Type>(table, T, "first_instance")?;
    (0..table.num_rows())
        .map(|r| {
            let (w, h) = (width[r], height[r]);
            let (hits, t_in, label, inst) = (hits.row(r), t_in.row(r), label.row(r), inst.row(r));
            if hits.len() != (w * h) as usize {
                return Err(StageError::Input(format!(
                    "table `{T}` row {r}: {} pixels in `hits`, expected {w}x{h}",
                    hits.len()
                )));
            }
            let mut px = Vec::with_capacity(hits.len() * 3);
            let mut off = 0usize;
            for i in 0..hits.len() {
                let c = labels::color(label[i]);
                let shade = if hits[i] == 0 {
                    1.0
                } else {
                    let inst_shade = if inst[i] == 0 {
                        1.0
                    } else {
                        0.6 + 0.4 * ((inst[i] as f64 * 0.618_034).fract())
                    };
                    let dist = (t_in[off] as f64 / far).clamp(0.0, 1.0);
                    inst_shade * (1.0 - 0.5 * dist.sqrt())
                };
                off += hits[i] as usize;
                // Keep dark classes visible: shade towards black from a lifted base.
                px.extend(c.map(|v| ((v as f64 * 0.85 + 38.0) * shade).round().min(255.0) as u8));
            }
            let image = image::RgbImage::from_raw(w, h, px).expect("size checked");
            Ok(FirstHitImage {
                frame: frame[r],
                camera: camera[r],
                image,
            })
        })
        .collect()
}
