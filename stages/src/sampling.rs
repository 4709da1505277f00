//! The sampling plan: every training/rendering ray with its primitive intervals (from the
//! `intersect` stage), targets (RGB, pseudo label, stereo depth, ray mask u(r)), and batches of
//! samples placed *only inside the primitives a ray crosses* plus its sky interval, with the
//! fixed semantic and instance distributions at each sample.
//!
//! Samples of one ray: the union of its intervals is split into disjoint covered segments; each
//! segment gets an equal share of the primitive sample budget, stratified within the segment,
//! so a thin car box gets as many samples as a long road slab (as the paper's "N per
//! interval"). `delta` of a sample is the width of its stratum, so no delta spans empty space.
//! The `uniform` mode (ablation) samples [near, far] evenly and ignores the intervals for
//! placement (but not for the fixed fields).

mod inputs;

use rayon::prelude::*;

use serde::{Deserialize, Serialize};

use crate::geometry::{self, Primitive};
use crate::intervals::{plan_image, IntersectParams};
use crate::labels;
use crate::rng::SplitMix64;
use crate::stage::{Inputs, Result, StageError};
use inputs::{ImageRays, ImageRows, RayRows};

/// Index meaning "no class / no label".
pub const NONE: u16 = u16::MAX;

/// How samples are placed along a ray.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SamplingMode {
    /// Only inside the primitives a ray crosses, plus the sky interval (the method).
    Primitives,
    /// Evenly over [near, far] (ablation: "uniform sampling").
    Uniform,
}

/// Sampling parameters.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SamplingParams {
    pub mode: SamplingMode,
    /// Samples per ray inside primitives (shared equally by the ray's covered segments).
    pub samples: usize,
    /// Samples in the sky interval (when the ray has one).
    pub sky_samples: usize,
    /// Uniform mode: near and far distance, metres.
    pub near: f32,
    pub far: f32,
}

impl Default for SamplingParams {
    fn default() -> Self {
        Self {
            mode: SamplingMode::Primitives,
            samples: 28,
            sky_samples: 4,
            near: 0.5,
            far: 80.0,
        }
    }
}

impl SamplingParams {
    pub fn validate(&self) -> Result<()> {
        if self.samples == 0 || self.samples > 512 {
            return Err(StageError::Params("`samples` must be 1..=512".into()));
        }
        if self.sky_samples > 64 {
            return Err(StageError::Params(
                "`sky_samples` must be at most 64".into(),
            ));
        }
        if !(self.near >= 0.0 && self.far > self.near) {
            return Err(StageError::Params(
                "`near` and `far` need 0 <= near < far".into(),
            ));
        }
        Ok(())
    }

    /// Samples per ray in a batch.
    pub fn per_ray(&self) -> usize {
        match self.mode {
            SamplingMode::Primitives => self.samples + self.sky_samples,
            SamplingMode::Uniform => self.samples,
        }
    }
}

/// One image of the ray set.
#[derive(Debug, Clone)]
pub struct ImageInfo {
    pub frame: u32,
    pub camera: u8,
    pub width: u32,
    pub height: u32,
    /// First ray of this image in the set.
    pub first_ray: usize,
    pub cam: geometry::Camera,
}

/// Every ray of the selected images with its intervals and targets. Scene frame, f32.
#[derive(Debug, Clone, Default)]
pub struct RaySet {
    /// Label ids the fields predict: classes of the primitives ascending, then sky (last).
    pub classes: Vec<u8>,
    /// Thing instances (label, instance) of the primitives, sorted: the fixed instance field's
    /// entries.
    pub things: Vec<(u8, u32)>,
    pub images: Vec<ImageInfo>,
    // Per ray.
    pub origin: Vec<[f32; 3]>,
    pub dir: Vec<[f32; 3]>,
    /// Camera-frame z of the unit ray direction: z-depth = t * z_scale.
    pub z_scale: Vec<f32>,
    /// Ragged intervals: ray r has entries offsets[r]..offsets[r+1].
    pub offsets: Vec<u32>,
    pub t_in: Vec<f32>,
    pub t_out: Vec<f32>,
    pub prim: Vec<u32>,
    pub sky: Vec<[f32; 2]>,
    /// Target colour in [0, 1].
    pub rgb: Vec<[f32; 3]>,
    /// Pseudo label as a class index, or [`NONE`].
    pub label: Vec<u16>,
    /// The ray mask u(r): the pseudo label is the class of a primitive the ray hits, or sky.
    pub u_mask: Vec<bool>,
    /// Stereo z-depth target, 0 = none.
    pub depth: Vec<f32>,
    // Per primitive.
    pub prim_class: Vec<u16>,
    /// Index into `things`, or [`NONE`] (u32::MAX) for stuff.
    pub prim_thing: Vec<u32>,
    /// Scene bounds of everything sampled (primitive bounds), for the encoding.
    pub bounds_min: [f32; 3],
    pub bounds_max: [f32; 3],
}

impl RaySet {
    /// Builds the ray set of the images the `rays` input covers, from the `scene` and `rays`
    /// inputs. Images without pseudo labels (right camera) get [`NONE`] labels.
    pub fn from_inputs(inputs: &Inputs) -> Result<RaySet> {
        let cams = geometry::cameras_from_table(inputs.table("scene", "cameras")?)?;
        let prims = geometry::primitives_from_table(inputs.table("scene", "primitives")?)?;
        let images = ImageRows::new(inputs.table("scene", "images")?, "images")?;
        let pseudo = ImageRows::new(inputs.table("scene", "pseudo_labels")?, "pseudo_labels")?;
        // A connected `depth` stage (stereo matching) takes precedence over the scene's own.
        let depth_table = match inputs.optional_table("depth", "stereo_depth")? {
            Some(t) => Some(t),
            None => inputs.optional_table("scene", "stereo_depth")?,
        };
        let stereo = match depth_table {
            Some(t) => Some(ImageRows::new(t, "stereo_depth")?),
            None => None,
        };
        let rays_t = inputs.table("rays", "ray_intervals")?;
        Self::build(&cams, &prims, &images, &pseudo, stereo.as_ref(), rays_t)
    }

    /// The ray set of the `ray_intervals` rows: the per-primitive part, then each row's
    /// image, checked against its camera and targets, with one ray per pixel.
    fn build(
        cams: &[geometry::CameraRow],
        prims: &[Primitive],
        images: &ImageRows,
        pseudo: &ImageRows,
        stereo: Option<&ImageRows>,
        rays_t: &arrow::record_batch::RecordBatch,
    ) -> Result<RaySet> {
        let mut set = Self::over_primitives(prims);
        let rows = RayRows::of(rays_t)?;
        for r in 0..rays_t.num_rows() {
            let img = ImageRays::read(&rows, r, cams, prims.len(), images, pseudo, stereo)?;
            set.push_image(&img);
        }
        Ok(set)
    }

    /// An empty ray set over `prims`: the classes (primitive classes ascending, then sky last,
    /// the fields' convention), the thing instances, each primitive's class and thing, and the
    /// primitives' bounds.
    fn over_primitives(prims: &[Primitive]) -> RaySet {
        let mut classes: Vec<u8> = prims
            .iter()
            .map(|p| p.label)
            .filter(|&l| l != labels::SKY)
            .collect();
        classes.sort_unstable();
        classes.dedup();
        classes.push(labels::SKY);
        let mut things: Vec<(u8, u32)> = prims
            .iter()
            .filter(|p| p.instance > 0)
            .map(|p| (p.label, p.instance))
            .collect();
        things.sort_unstable();
        things.dedup();
        let mut set = RaySet {
            prim_class: prims
                .iter()
                .map(|p| class_index(&classes, p.label))
                .collect(),
            prim_thing: prims
                .iter()
                .map(|p| {
                    if p.instance == 0 {
                        u32::MAX
                    } else {
                        things
                            .binary_search(&(p.label, p.instance))
                            .map_or(u32::MAX, |i| i as u32)
                    }
                })
                .collect(),
            ..Default::default()
        };
        let (mut lo, mut hi) = ([f64::MAX; 3], [f64::MIN; 3]);
        for p in prims {
            let b = p.aabb();
            for k in 0..3 {
                lo[k] = lo[k].min(b.min[k]);
                hi[k] = hi[k].max(b.max[k]);
            }
        }
        set.classes = classes.clone();
        set.things = things.clone();
        set.bounds_min = lo.map(|v| v as f32);
        set.bounds_max = hi.map(|v| v as f32);
        set.offsets.push(0);
        set
    }

    /// Appends the image of `img` and its rays (one per pixel, row-major) with their intervals
    /// and targets.
    fn push_image(&mut self, img: &ImageRays) {
        let cam = img.cam;
        let (w, h) = (cam.cam.width, cam.cam.height);
        let n = (w * h) as usize;
        self.images.push(ImageInfo {
            frame: cam.frame,
            camera: cam.camera,
            width: w,
            height: h,
            first_ray: self.origin.len(),
            cam: cam.cam.clone(),
        });
        let (hits, ti, to, pr) = (img.hits, img.t_in, img.t_out, img.prim);
        let (sky0, sky1) = (img.sky_t0, img.sky_t1);
        let (rgb, labels_row, depth_row) = (img.targets.rgb, img.targets.labels, img.targets.depth);
        let origin = cam.cam.centre();
        let mut k = 0usize;
        for p in 0..n {
            let (x, y) = ((p as u32) % w, (p as u32) / w);
            let ray = cam.cam.pixel_ray(x, y);
            self.origin
                .push([origin.x as f32, origin.y as f32, origin.z as f32]);
            self.dir
                .push([ray.dir.x as f32, ray.dir.y as f32, ray.dir.z as f32]);
            self.z_scale
                .push(cam.cam.dir_cam(x as f64 + 0.5, y as f64 + 0.5).z as f32);
            let nh = hits[p] as usize;
            let mut hit_sky_or_label = false;
            let label = labels_row.map_or(NONE, |l| {
                if l[p] == 0 {
                    NONE
                } else {
                    class_index(&self.classes, l[p])
                }
            });
            for j in k..k + nh {
                self.t_in.push(ti[j]);
                self.t_out.push(to[j].max(ti[j]));
                self.prim.push(pr[j]);
                if label != NONE && self.prim_class[pr[j] as usize] == label {
                    hit_sky_or_label = true;
                }
            }
            k += nh;
            self.offsets.push(self.t_in.len() as u32);
            self.sky.push([sky0[p], sky1[p].max(sky0[p])]);
            self.rgb
                .push([0, 1, 2].map(|c| rgb[p * 3 + c] as f32 / 255.0));
            if label != NONE && self.classes[label as usize] == labels::SKY {
                hit_sky_or_label = true;
            }
            self.label.push(label);
            self.u_mask.push(hit_sky_or_label);
            self.depth.push(depth_row.map_or(0.0, |d| {
                if d[p].is_finite() && d[p] > 0.0 {
                    d[p]
                } else {
                    0.0
                }
            }));
        }
    }

    /// The rays of new cameras (`(frame, camera id, camera)`) over the primitives of `base`,
    /// intersected with `prims` with the `intersect` kind's defaults; they have no input colour,
    /// labels or depth.
    pub fn for_cameras(
        base: &RaySet,
        prims: &[Primitive],
        cams: &[(u32, u8, geometry::Camera)],
    ) -> RaySet {
        let bvh = geometry::Bvh::build(prims);
        let ip = IntersectParams::default();
        let mut set = RaySet {
            classes: base.classes.clone(),
            things: base.things.clone(),
            prim_class: base.prim_class.clone(),
            prim_thing: base.prim_thing.clone(),
            bounds_min: base.bounds_min,
            bounds_max: base.bounds_max,
            ..Default::default()
        };
        set.offsets.push(0);
        for (frame, camera, cam) in cams {
            let plan = plan_image(prims, &bvh, cam, &ip);
            set.images.push(ImageInfo {
                frame: *frame,
                camera: *camera,
                width: cam.width,
                height: cam.height,
                first_ray: set.origin.len(),
                cam: cam.clone(),
            });
            let origin = cam.centre();
            let mut j = 0usize;
            for y in 0..cam.height {
                for x in 0..cam.width {
                    let p = (y * cam.width + x) as usize;
                    let ray = cam.pixel_ray(x, y);
                    set.origin
                        .push([origin.x as f32, origin.y as f32, origin.z as f32]);
                    set.dir
                        .push([ray.dir.x as f32, ray.dir.y as f32, ray.dir.z as f32]);
                    set.z_scale
                        .push(cam.dir_cam(x as f64 + 0.5, y as f64 + 0.5).z as f32);
                    let nh = plan.hits[p] as usize;
                    for i in j..j + nh {
                        set.t_in.push(plan.t_in[i]);
                        set.t_out.push(plan.t_out[i].max(plan.t_in[i]));
                        set.prim.push(plan.prim[i]);
                    }
                    j += nh;
                    set.offsets.push(set.t_in.len() as u32);
                    set.sky
                        .push([plan.sky_t0[p], plan.sky_t1[p].max(plan.sky_t0[p])]);
                    set.rgb.push([0.0; 3]);
                    set.label.push(NONE);
                    set.u_mask.push(false);
                    set.depth.push(0.0);
                }
            }
        }
        set
    }

    pub fn len(&self) -> usize {
        self.origin.len()
    }

    pub fn is_empty(&self) -> bool {
        self.origin.is_empty()
    }

    /// Whether ray `r` crosses any primitive (otherwise it is pure sky: no network needed).
    pub fn hits_anything(&self, r: usize) -> bool {
        self.offsets[r + 1] > self.offsets[r]
    }

    pub fn sky_class(&self) -> usize {
        self.classes
            .iter()
            .position(|&c| c == labels::SKY)
            .expect("sky is always a class")
    }
}

/// Index of label `l` in `classes`, or [`NONE`].
fn class_index(classes: &[u8], l: u8) -> u16 {
    classes
        .iter()
        .position(|&c| c == l)
        .map_or(NONE, |i| i as u16)
}

/// A batch of rays with their samples, flat row-major, ready for the fields.
///
/// # Shapes
/// `R` rays, `S` samples per ray, `C` classes, `I` thing instances.
#[derive(Debug, Clone, Default)]
pub struct SampleBatch {
    pub rays: usize,
    pub samples: usize,
    pub classes: usize,
    /// Ray ids in the ray set. [R]
    pub ray_ids: Vec<u32>,
    /// [R, S, 3]
    pub positions: Vec<f32>,
    /// [R, 3] unit view directions.
    pub dirs: Vec<f32>,
    /// [R, S] stratum widths (0 for padding samples: they get zero weight).
    pub deltas: Vec<f32>,
    /// [R, S] distances along the ray.
    pub t: Vec<f32>,
    /// [R, S, C] fixed semantic distribution (all zero outside every primitive).
    pub fixed_semantic: Vec<f32>,
    /// [R, S] 1 where the sample is inside primitives of exactly one class.
    pub unique_class: Vec<f32>,
    /// [R, 3] target colour.
    pub target_rgb: Vec<f32>,
    /// [R] pseudo label class index, -1 = none.
    pub label: Vec<i64>,
    /// [R] u(r) as 0/1.
    pub u_mask: Vec<f32>,
    /// [R] stereo z-depth target (0 = none) and the ray's z scale (z = t * z_scale).
    pub depth: Vec<f32>,
    pub z_scale: Vec<f32>,
}

/// Places the samples of one ray: writes `t` and `delta` (`per_ray` entries each, padding with
/// delta 0 at the end). `jitter` = None puts samples at stratum centres (rendering).
pub fn place_samples(
    set: &RaySet,
    r: usize,
    p: &SamplingParams,
    mut jitter: Option<&mut SplitMix64>,
    t_out: &mut [f32],
    delta_out: &mut [f32],
) {
    let s_total = p.per_ray();
    debug_assert_eq!(t_out.len(), s_total);
    let mut n = 0;
    let mut put = |t0: f32, t1: f32, count: usize, jitter: &mut Option<&mut SplitMix64>| {
        if count == 0 || t1 <= t0 {
            return;
        }
        let w = (t1 - t0) / count as f32;
        for i in 0..count {
            if n >= s_total {
                return;
            }
            let u = jitter.as_mut().map_or(0.5, |g| g.unit());
            t_out[n] = t0 + (i as f32 + u) * w;
            delta_out[n] = w;
            n += 1;
        }
    };
    match p.mode {
        SamplingMode::Uniform => put(p.near, p.far, p.samples, &mut jitter),
        SamplingMode::Primitives => {
            // Union of the ray's intervals as disjoint segments (intervals are sorted by t_in).
            let (a, b) = (set.offsets[r] as usize, set.offsets[r + 1] as usize);
            let mut segs: [(f32, f32); 64] = [(0.0, 0.0); 64];
            let mut ns = 0;
            for j in a..b {
                let (t0, t1) = (set.t_in[j].max(0.0), set.t_out[j]);
                if ns > 0 && t0 <= segs[ns - 1].1 {
                    segs[ns - 1].1 = segs[ns - 1].1.max(t1);
                } else if ns < segs.len() {
                    segs[ns] = (t0, t1);
                    ns += 1;
                }
            }
            if let Some(base) = p.samples.checked_div(ns) {
                let extra = p.samples % ns;
                for (i, &(t0, t1)) in segs[..ns].iter().enumerate() {
                    put(t0, t1, base + usize::from(i < extra), &mut jitter);
                }
            }
            let [s0, s1] = set.sky[r];
            if ns > 0 {
                put(s0, s1, p.sky_samples, &mut jitter);
            }
        }
    }
    // Padding: zero-width samples at the last position contribute nothing.
    let last = if n > 0 { t_out[n - 1] } else { 0.0 };
    for i in n..s_total {
        t_out[i] = last;
        delta_out[i] = 0.0;
    }
}

/// The fixed semantic distribution at distance `t` of ray `r` (equal over the distinct classes
/// of the intervals containing `t`; sky inside the sky interval; zeros outside everything), and
/// whether exactly one class encloses the point. `out` has one entry per class.
pub fn fixed_semantic_at(set: &RaySet, r: usize, t: f32, out: &mut [f32]) -> bool {
    out.iter_mut().for_each(|v| *v = 0.0);
    let (a, b) = (set.offsets[r] as usize, set.offsets[r + 1] as usize);
    let mut count = 0;
    for j in a..b {
        if t >= set.t_in[j] && t <= set.t_out[j] {
            let c = set.prim_class[set.prim[j] as usize] as usize;
            if out[c] == 0.0 {
                out[c] = 1.0;
                count += 1;
            }
        }
    }
    if count == 0 {
        let [s0, s1] = set.sky[r];
        if t >= s0 && t <= s1 && s1 > s0 {
            out[set.sky_class()] = 1.0;
            return true;
        }
        return false;
    }
    if count > 1 {
        let w = 1.0 / count as f32;
        out.iter_mut().filter(|v| **v > 0.0).for_each(|v| *v = w);
    }
    count == 1
}

/// The fixed instance distribution at distance `t` of ray `r` over `set.things` (equal over the
/// distinct thing instances whose intervals contain `t`). Returns whether any thing contains it.
pub fn fixed_instance_at(set: &RaySet, r: usize, t: f32, out: &mut [f32]) -> bool {
    out.iter_mut().for_each(|v| *v = 0.0);
    let (a, b) = (set.offsets[r] as usize, set.offsets[r + 1] as usize);
    let mut count = 0;
    for j in a..b {
        let th = set.prim_thing[set.prim[j] as usize];
        if th != u32::MAX && t >= set.t_in[j] && t <= set.t_out[j] && out[th as usize] == 0.0 {
            out[th as usize] = 1.0;
            count += 1;
        }
    }
    if count > 1 {
        let w = 1.0 / count as f32;
        out.iter_mut().filter(|v| **v > 0.0).for_each(|v| *v = w);
    }
    count > 0
}

/// Builds the batch of rays `ray_ids`. `seed` drives the stratified jitter (None: stratum
/// centres, for rendering). Chunks of rays are built in parallel; each ray has its own
/// generator, so the batch does not depend on the thread count.
pub fn sample_batch(
    set: &RaySet,
    ray_ids: &[u32],
    p: &SamplingParams,
    seed: Option<u64>,
) -> SampleBatch {
    const CHUNK: usize = 128;
    if ray_ids.len() <= CHUNK {
        return sample_rays(set, ray_ids, p, seed);
    }
    let parts: Vec<SampleBatch> = ray_ids
        .par_chunks(CHUNK)
        .map(|ids| sample_rays(set, ids, p, seed))
        .collect();
    let mut b = SampleBatch {
        rays: ray_ids.len(),
        samples: p.per_ray(),
        classes: set.classes.len(),
        ..Default::default()
    };
    for part in parts {
        b.ray_ids.extend(part.ray_ids);
        b.positions.extend(part.positions);
        b.dirs.extend(part.dirs);
        b.deltas.extend(part.deltas);
        b.t.extend(part.t);
        b.fixed_semantic.extend(part.fixed_semantic);
        b.unique_class.extend(part.unique_class);
        b.target_rgb.extend(part.target_rgb);
        b.label.extend(part.label);
        b.u_mask.extend(part.u_mask);
        b.depth.extend(part.depth);
        b.z_scale.extend(part.z_scale);
    }
    b
}

/// [`sample_batch`] on one thread.
fn sample_rays(
    set: &RaySet,
    ray_ids: &[u32],
    p: &SamplingParams,
    seed: Option<u64>,
) -> SampleBatch {
    let (r_n, s_n, c_n) = (ray_ids.len(), p.per_ray(), set.classes.len());
    let mut b = SampleBatch {
        rays: r_n,
        samples: s_n,
        classes: c_n,
        ray_ids: ray_ids.to_vec(),
        positions: vec![0.0; r_n * s_n * 3],
        dirs: vec![0.0; r_n * 3],
        deltas: vec![0.0; r_n * s_n],
        t: vec![0.0; r_n * s_n],
        fixed_semantic: vec![0.0; r_n * s_n * c_n],
        unique_class: vec![0.0; r_n * s_n],
        target_rgb: vec![0.0; r_n * 3],
        label: vec![-1; r_n],
        u_mask: vec![0.0; r_n],
        depth: vec![0.0; r_n],
        z_scale: vec![0.0; r_n],
    };
    for (i, &rid) in ray_ids.iter().enumerate() {
        let r = rid as usize;
        let mut rng =
            seed.map(|s| SplitMix64::new(s ^ (rid as u64).wrapping_mul(0xA24B_AED4_963E_E407)));
        let ts = &mut b.t[i * s_n..(i + 1) * s_n];
        let ds = &mut b.deltas[i * s_n..(i + 1) * s_n];
        place_samples(set, r, p, rng.as_mut(), ts, ds);
        let (o, d) = (set.origin[r], set.dir[r]);
        for s in 0..s_n {
            let t = b.t[i * s_n + s];
            for k in 0..3 {
                b.positions[(i * s_n + s) * 3 + k] = o[k] + t * d[k];
            }
            let fs = &mut b.fixed_semantic[(i * s_n + s) * c_n..(i * s_n + s + 1) * c_n];
            let unique = fixed_semantic_at(set, r, t, fs);
            b.unique_class[i * s_n + s] = if unique && b.deltas[i * s_n + s] > 0.0 {
                1.0
            } else {
                0.0
            };
        }
        b.dirs[i * 3..i * 3 + 3].copy_from_slice(&d);
        b.target_rgb[i * 3..i * 3 + 3].copy_from_slice(&set.rgb[r]);
        b.label[i] = if set.label[r] == NONE {
            -1
        } else {
            set.label[r] as i64
        };
        b.u_mask[i] = if set.u_mask[r] { 1.0 } else { 0.0 };
        b.depth[i] = set.depth[r];
        b.z_scale[i] = set.z_scale[r];
    }
    b
}

#[cfg(test)]
mod tests;
