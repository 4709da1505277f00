//! The sampling plan's intervals (the `ray_intervals` table, written by the `intersect` kind):
//! for every pixel of every selected image, the intervals of the first `k` primitive intervals its ray crosses (sorted by entry),
//! and a sky interval beyond the farthest one when fewer than `k` are kept. Empty space is never
//! sampled; rays that meet nothing are marked (`hits = 0`) so later stages render them as sky
//! without evaluating a network. Output: `ray_intervals` (see `data_schema/ray_intervals.json`).

use arrow::{
    datatypes::{Float32Type, Float64Type, UInt32Type, UInt8Type},
    record_batch::RecordBatch,
};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::{
    geometry::{Bvh, Camera, CameraRow, Hit, Primitive, Ray},
    labels, tables, Result, StageError,
};

/// Parameters of the `intersect` stage.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct IntersectParams {
    /// Maximum number of primitive intervals kept per ray (the paper's 10); 1..=255.
    pub k: u32,
    /// Length in metres of the sky interval appended beyond the last kept interval.
    pub sky_interval: f64,
    /// Maximum ray length in metres considered; intervals are clipped to it.
    pub far: f64,
    /// Cameras planned (`image_00` .. `image_03`, or 0 .. 3); empty: every camera of the scene.
    #[serde(deserialize_with = "crate::geometry::camera::camera_ids")]
    #[schemars(with = "Vec<crate::geometry::camera::CameraName>")]
    pub cameras: Vec<u8>,
}

impl Default for IntersectParams {
    fn default() -> Self {
        Self {
            k: 10,
            sky_interval: 50.0,
            far: 200.0,
            cameras: Vec::new(),
        }
    }
}

/// The sky lies above the horizon: a ray pointing further below it than this (in the world
/// frame, z up, as KITTI-360's) gets no sky interval. Beyond its last primitive such a ray is
/// underground or on unannotated ground, and a sky interval there let the photometric loss
/// explain ground colour by density below the ground, rendered as sky (blotches of sky on the
/// paving beside the car in the fisheye views). The margin allows for pitch in the poses.
pub const SKY_MAX_DEPRESSION_DEG: f64 = 1.0;

/// Whether a ray with unit direction `dir` can see the sky (see [`SKY_MAX_DEPRESSION_DEG`]).
pub fn may_see_sky(dir: glam::DVec3) -> bool {
    dir.z >= -SKY_MAX_DEPRESSION_DEG.to_radians().sin()
}

/// The kept hits of one ray (the first `k`) and its sky interval `[t0, t1]`, in f64: the one
/// rule behind every plan, whether written to the table or traced again during training.
fn keep<'h>(hits: &'h [Hit], ray: &Ray, p: &IntersectParams) -> (&'h [Hit], f64, f64) {
    let kept = &hits[..hits.len().min(p.k as usize)];
    let t_far = kept.iter().fold(0f64, |m, h| m.max(h.t_out));
    let sky = if !kept.is_empty() && kept.len() < p.k as usize && may_see_sky(ray.dir) {
        p.sky_interval
    } else {
        0.0
    };
    (kept, t_far, t_far + sky)
}

/// The plan of one ray as the sampler reads it (f32, `t_out >= t_in`, sky `t1 >= t0`), traced
/// into reusable buffers: training re-traces the rays of each batch instead of holding every
/// ray's intervals.
#[derive(Debug, Default, Clone)]
pub struct RayPlan {
    hits: Vec<Hit>,
    pub t_in: Vec<f32>,
    pub t_out: Vec<f32>,
    pub prim: Vec<u32>,
    pub sky: [f32; 2],
}

impl RayPlan {
    /// Traces `ray` through `bvh`, keeping what the `intersect` stage keeps for it.
    pub fn trace(&mut self, prims: &[Primitive], bvh: &Bvh, ray: &Ray, p: &IntersectParams) {
        bvh.intersect_all(prims, ray, 0.0, p.far, &mut self.hits);
        let (kept, t0, t1) = keep(&self.hits, ray, p);
        self.t_in.clear();
        self.t_out.clear();
        self.prim.clear();
        for h in kept {
            let (a, b) = (h.t_in as f32, h.t_out as f32);
            self.t_in.push(a);
            self.t_out.push(b.max(a));
            self.prim.push(h.prim);
        }
        let (s0, s1) = (t0 as f32, t1 as f32);
        self.sky = [s0, s1.max(s0)];
    }
}

/// The per-pixel plan of one image: a `ray_intervals` row.
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

    /// Adds one pixel from its ray's sorted hits (all of them within `[0, far]`; none for a
    /// pixel without a ray).
    fn push_pixel(
        &mut self,
        prims: &[Primitive],
        ray: Option<&Ray>,
        hits: &[Hit],
        p: &IntersectParams,
    ) {
        let (kept, t0, t1) = match ray {
            Some(ray) => keep(hits, ray, p),
            None => (&hits[..0], 0.0, 0.0),
        };
        self.hits.push(kept.len() as u8);
        for h in kept {
            self.t_in.push(h.t_in as f32);
            self.t_out.push(h.t_out as f32);
            self.prim.push(h.prim);
        }
        self.sky_t0.push(t0 as f32);
        self.sky_t1.push(t1 as f32);
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

    /// Pixels of the image.
    pub fn len(&self) -> usize {
        self.hits.len()
    }

    pub fn is_empty(&self) -> bool {
        self.hits.is_empty()
    }

    /// Row `r` of a `ray_intervals` batch, only the intervals (`hits`, `t_in`, `t_out`,
    /// `prim`; the sky and first-hit columns are left empty), checked as [`ImagePlan::from_row`]
    /// checks them.
    pub fn intervals_from_row(
        batch: &RecordBatch,
        r: usize,
        pixels: usize,
        prim_count: usize,
    ) -> Result<ImagePlan> {
        Self::read_row(batch, r, pixels, prim_count, Read::Intervals)
    }

    /// Row `r` of a `ray_intervals` batch (the per-pixel columns the sampler reads; the
    /// first-hit columns are left empty), every length checked against `pixels` and the ids
    /// against `prim_count`.
    pub fn from_row(
        batch: &RecordBatch,
        r: usize,
        pixels: usize,
        prim_count: usize,
    ) -> Result<ImagePlan> {
        Self::read_row(batch, r, pixels, prim_count, Read::Sampler)
    }

    /// Row `r` of a `ray_intervals` batch, every per-pixel column (checked as
    /// [`ImagePlan::from_row`] checks them).
    pub fn whole_from_row(
        batch: &RecordBatch,
        r: usize,
        pixels: usize,
        prim_count: usize,
    ) -> Result<ImagePlan> {
        Self::read_row(batch, r, pixels, prim_count, Read::All)
    }

    fn read_row(
        batch: &RecordBatch,
        r: usize,
        pixels: usize,
        prim_count: usize,
        what: Read,
    ) -> Result<ImagePlan> {
        const T: &str = "ray_intervals";
        let hits = tables::get_list::<UInt8Type>(batch, T, "hits")?.row(r);
        let (sky0, sky1): (&[f32], &[f32]) = if what != Read::Intervals {
            (
                tables::get_list::<Float32Type>(batch, T, "sky_t0")?.row(r),
                tables::get_list::<Float32Type>(batch, T, "sky_t1")?.row(r),
            )
        } else {
            (&[], &[])
        };
        let (first_label, first_instance): (&[u8], &[u32]) = if what == Read::All {
            (
                tables::get_list::<UInt8Type>(batch, T, "first_label")?.row(r),
                tables::get_list::<UInt32Type>(batch, T, "first_instance")?.row(r),
            )
        } else {
            (&[], &[])
        };
        let per_pixel = [
            sky0.len(),
            sky1.len(),
            first_label.len(),
            first_instance.len(),
        ];
        if hits.len() != pixels || per_pixel.iter().any(|&n| n != 0 && n != pixels) {
            return Err(StageError::Input(format!(
                "{T} row {r}: per-pixel arrays do not have {pixels} entries"
            )));
        }
        let total: usize = hits.iter().map(|&h| h as usize).sum();
        let (ti, to, pr) = (
            tables::get_list::<Float32Type>(batch, T, "t_in")?.row(r),
            tables::get_list::<Float32Type>(batch, T, "t_out")?.row(r),
            tables::get_list::<UInt32Type>(batch, T, "prim")?.row(r),
        );
        if ti.len() != total || to.len() != total || pr.len() != total {
            return Err(StageError::Input(format!(
                "{T} row {r}: {} intervals listed but hits sum to {total}",
                ti.len()
            )));
        }
        if let Some(&bad) = pr.iter().find(|&&p| p as usize >= prim_count) {
            return Err(StageError::Input(format!(
                "{T} row {r}: primitive id {bad} is not in `primitives` ({prim_count} rows)"
            )));
        }
        Ok(ImagePlan {
            hits: hits.to_vec(),
            t_in: ti.to_vec(),
            t_out: to.to_vec(),
            prim: pr.to_vec(),
            sky_t0: sky0.to_vec(),
            sky_t1: sky1.to_vec(),
            first_label: first_label.to_vec(),
            first_instance: first_instance.to_vec(),
        })
    }

    /// This image's plan after an edit of the primitives (`self`: its plan before, every
    /// column; `prims` and `bvh`: the primitives after): the pixels in `meeting` (ascending:
    /// those whose ray meets a changed primitive's old or new extent) are traced again, every
    /// other pixel keeps its intervals with the ids renumbered by `old_to_new`. A kept pixel
    /// whose renumbered ids would no longer be in the order a trace gives (equal entries, ids
    /// swapped by a reordering) is traced again too. `None` where a kept pixel names a
    /// primitive that changed: `meeting` missed it (the caller plans the image again).
    #[allow(clippy::too_many_arguments)]
    pub fn replanned(
        &self,
        meeting: &[u32],
        old_to_new: &[Option<u32>],
        prims: &[Primitive],
        bvh: &Bvh,
        cam: &Camera,
        p: &IntersectParams,
    ) -> Option<ImagePlan> {
        let n = self.hits.len();
        let mut out = ImagePlan {
            hits: Vec::with_capacity(n),
            t_in: Vec::with_capacity(self.t_in.len()),
            t_out: Vec::with_capacity(self.t_out.len()),
            prim: Vec::with_capacity(self.prim.len()),
            sky_t0: Vec::with_capacity(n),
            sky_t1: Vec::with_capacity(n),
            first_label: Vec::with_capacity(n),
            first_instance: Vec::with_capacity(n),
        };
        let (mut hits, mut ids) = (Vec::new(), Vec::new());
        let mut meeting = meeting.iter().copied().peekable();
        let mut off = 0usize;
        for i in 0..n {
            let count = self.hits[i] as usize;
            let range = off..off + count;
            off += count;
            let mut again = meeting.next_if_eq(&(i as u32)).is_some();
            if !again {
                ids.clear();
                for &o in &self.prim[range.clone()] {
                    ids.push(old_to_new.get(o as usize).copied().flatten()?);
                }
                let t = &self.t_in[range.clone()];
                again = (1..count).any(|j| t[j - 1] == t[j] && ids[j - 1] > ids[j]);
            }
            if again {
                let ray = cam.pixel_ray(i as u32 % cam.width, i as u32 / cam.width);
                match &ray {
                    Some(ray) => bvh.intersect_all(prims, ray, 0.0, p.far, &mut hits),
                    None => hits.clear(),
                }
                out.push_pixel(prims, ray.as_ref(), &hits, p);
                continue;
            }
            out.hits.push(self.hits[i]);
            out.t_in.extend_from_slice(&self.t_in[range.clone()]);
            out.t_out.extend_from_slice(&self.t_out[range]);
            out.prim.extend_from_slice(&ids);
            out.sky_t0.push(self.sky_t0[i]);
            out.sky_t1.push(self.sky_t1[i]);
            out.first_label.push(self.first_label[i]);
            out.first_instance.push(self.first_instance[i]);
        }
        Some(out)
    }
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Read {
    Intervals,
    Sampler,
    All,
}

/// The plan of one image: rows of pixels in parallel (rayon), one hit buffer per row.
pub fn plan_image(prims: &[Primitive], bvh: &Bvh, cam: &Camera, p: &IntersectParams) -> ImagePlan {
    let rows: Vec<ImagePlan> = (0..cam.height)
        .into_par_iter()
        .map_init(Vec::new, |hits, y| {
            let mut row = ImagePlan::default();
            for x in 0..cam.width {
                // A pixel outside a fisheye's lens crosses nothing.
                let ray = cam.pixel_ray(x, y);
                match &ray {
                    Some(ray) => bvh.intersect_all(prims, ray, 0.0, p.far, hits),
                    None => hits.clear(),
                }
                row.push_pixel(prims, ray.as_ref(), hits, p);
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

/// The `ray_intervals` row of one image planned with `p`.
pub fn plan_row(row: &CameraRow, plan: ImagePlan, p: &IntersectParams) -> Result<RecordBatch> {
    tables::build(
        "ray_intervals",
        vec![
            tables::prim::<UInt32Type>([row.frame]),
            tables::prim::<UInt8Type>([row.camera]),
            tables::prim::<UInt32Type>([row.cam.width]),
            tables::prim::<UInt32Type>([row.cam.height]),
            tables::prim::<UInt32Type>([p.k]),
            tables::prim::<Float64Type>([p.far]),
            tables::prim::<Float64Type>([p.sky_interval]),
            tables::list::<UInt8Type>([plan.hits]),
            tables::list::<Float32Type>([plan.t_in]),
            tables::list::<Float32Type>([plan.t_out]),
            tables::list::<UInt32Type>([plan.prim]),
            tables::list::<Float32Type>([plan.sky_t0]),
            tables::list::<Float32Type>([plan.sky_t1]),
            tables::list::<UInt8Type>([plan.first_label]),
            tables::list::<UInt32Type>([plan.first_instance]),
        ],
    )
}

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
