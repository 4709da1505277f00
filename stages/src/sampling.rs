//! The sampling plan: batches of samples placed *only inside the primitives a ray crosses* plus
//! its sky interval, with the fixed semantic and instance distributions at each sample, for the
//! rays of [`Rays`]: every ray of a scene's images with its targets (RGB, pseudo label, stereo
//! depth, ray mask u(r)) and its intervals traced again when training draws it ([`ImageRays`]),
//! or one image's rays with the plan the `intersect` stage stored ([`PlannedImage`], rendering).
//!
//! Samples of one ray: each primitive interval gets an equal share of the primitive sample
//! budget (the paper's "N per interval"), spread over it by length; the intervals' ends cut the
//! ray into pieces, each stratified with the shares of the intervals covering it, so a thin car
//! box gets as many samples as a long road slab even inside it, and no stratum straddles a
//! box's face. `delta` of a sample is the width of its stratum, so no delta spans empty space.
//! The `uniform` mode (ablation) samples [near, far] evenly and ignores the intervals for
//! placement (but not for the fixed fields).

mod images;
mod params;
mod rays;
mod train;

pub use images::{train_rays, ImageRays, JitteredRays, SparseDepth, Targets, TrainImage};
pub use params::{SamplingMode, SamplingParams};
use rayon::prelude::*;
pub use rays::{
    pixel_ray, Intervals, PlannedImage, PrimInfo, RaySet, RayTargets, Rays, SceneRay, StoredRays,
    NONE,
};
pub use train::{JitterLabels, LateJitter, TrainSampling};

use crate::intervals::RayPlan;
use crate::rng::SplitMix64;
use crate::stage::Result;

/// A batch of rays with their samples, flat row-major, ready for the fields.
///
/// # Shapes
/// `R` rays, `S` samples per ray, `C` classes, `I` thing instances. A rendering batch
/// ([`sample_for_render`]) leaves the fixed semantics and targets empty.
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

impl SampleBatch {
    /// Per sample: whether it lies in its ray's sky interval ([`in_sky_rows`]).
    pub fn in_sky(&self) -> Vec<bool> {
        in_sky_rows(&self.fixed_semantic, self.classes)
    }
}

/// Per row of fixed semantic distributions (`classes` values each, sky last): whether it is
/// one-hot sky, which is where a sample lies in its ray's sky interval (no primitive reaches
/// into the sky interval, and outside it no row has sky).
pub fn in_sky_rows(fixed: &[f32], classes: usize) -> Vec<bool> {
    fixed
        .chunks_exact(classes)
        .map(|row| row[classes - 1] == 1.0)
        .collect()
}

/// Places the samples of one ray with intervals `iv`: writes `t` and `delta` (`per_ray`
/// entries each, padding with delta 0 at the end). `jitter` = None puts samples at stratum
/// centres (rendering).
pub fn place_samples(
    iv: &Intervals,
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
            let ns = primitive_strata(iv, p.samples, &mut |t0, t1, count| {
                put(t0, t1, count, &mut jitter)
            });
            let [s0, s1] = iv.sky;
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

/// Interval ends one ray's strata are planned in without a heap buffer (16 intervals; `k` is
/// 10 by default, at most 255).
const INLINE_ENDS: usize = 32;

/// Splits the primitive sample budget `samples` of a ray among its intervals and calls `emit(t0,
/// t1, count)`, in order of distance, for each run of `count` equal strata over `[t0, t1]`;
/// returns how many non-empty intervals the ray has.
///
/// Each interval gets an equal share (the paper's "N per interval"), spread over it by length.
/// The intervals' ends cut the ray into pieces over which the set of enclosing primitives is
/// constant; a piece's quota is the sum of the shares of the intervals covering it, so a thin
/// gate box in front of a deep garden box gets its own share instead of a sliver of the merged
/// [gate, garden] stretch (the rule before train VERSION 11), and no stratum straddles the gate's
/// faces.
fn primitive_strata(
    iv: &Intervals,
    samples: usize,
    emit: &mut impl FnMut(f32, f32, usize),
) -> usize {
    let n = sampled_intervals(iv).count();
    if n == 0 || samples == 0 {
        return n;
    }
    if 2 * n <= INLINE_ENDS {
        let mut ends = [0f32; INLINE_ENDS];
        let mut quota = [0f64; INLINE_ENDS];
        plan_strata(iv, n, samples, &mut ends, &mut quota, emit);
    } else {
        // Only with `k` above 16: one buffer per ray.
        let (mut ends, mut quota) = (vec![0f32; 2 * n], vec![0f64; 2 * n]);
        plan_strata(iv, n, samples, &mut ends, &mut quota, emit);
    }
    n
}

/// The intervals of `iv` that samples go into: clipped to start at the camera, empty ones left out.
fn sampled_intervals<'a>(iv: &'a Intervals) -> impl Iterator<Item = (f32, f32)> + 'a {
    iv.t_in
        .iter()
        .zip(iv.t_out)
        .map(|(&t_in, &t1)| (t_in.max(0.0), t1))
        .filter(|(t0, t1)| t1 > t0)
}

/// [`primitive_strata`] for a ray with `n` non-empty intervals, in buffers of at least `2 n`.
///
/// Quotas become whole samples by rounding their running sums, first over the stretches
/// (maximal runs of covered pieces), then over the pieces of each stretch: every stretch and
/// every piece gets its quota rounded down or up, the counts add up exactly, and a stretch (whose
/// quota is at least one interval's share) keeps a sample whenever `samples >= n`. A piece
/// rounded to nothing joins the run before it (the first run of its stretch when none is), so
/// strata tile every stretch that has a sample.
fn plan_strata(
    iv: &Intervals,
    n: usize,
    samples: usize,
    ends: &mut [f32],
    quota: &mut [f64],
    emit: &mut impl FnMut(f32, f32, usize),
) {
    let mut ne = 0;
    for (t0, t1) in sampled_intervals(iv) {
        ends[ne] = t0;
        ends[ne + 1] = t1;
        ne += 2;
    }
    let ends = &mut ends[..ne];
    // Insertion sort: a handful of ends, nearly sorted already (intervals come by entry).
    for i in 1..ends.len() {
        let x = ends[i];
        let mut j = i;
        while j > 0 && ends[j - 1] > x {
            ends[j] = ends[j - 1];
            j -= 1;
        }
        ends[j] = x;
    }
    let mut m = 1;
    for i in 1..ends.len() {
        if ends[i] > ends[m - 1] {
            ends[m] = ends[i];
            m += 1;
        }
    }
    let (ends, pieces) = (&ends[..m], m - 1);
    // A piece's quota: the sum over the intervals covering it of share * piece / interval
    // (0 for a piece no interval covers: empty space).
    let share = samples as f64 / n as f64;
    quota[..pieces].fill(0.0);
    for (t0, t1) in sampled_intervals(iv) {
        let per_metre = share / f64::from(t1 - t0);
        let mut k = ends.iter().position(|&e| e >= t0).unwrap_or(m);
        while k < pieces && ends[k] < t1 {
            quota[k] += per_metre * f64::from(ends[k + 1] - ends[k]);
            k += 1;
        }
    }
    // Nearest whole number of a non-negative sum (`as` truncates: no libm call per piece).
    let round = |x: f64, cap: usize| ((x + 0.5) as usize).min(cap);
    let (mut cum_all, mut given_all) = (0.0, 0);
    let mut k = 0;
    while k < pieces {
        if quota[k] == 0.0 {
            k += 1;
            continue;
        }
        let first = k;
        let mut total = 0.0;
        while k < pieces && quota[k] > 0.0 {
            total += quota[k];
            k += 1;
        }
        let last = k - 1;
        cum_all += total;
        let upto = round(cum_all, samples).max(given_all);
        let whole = upto - given_all;
        given_all = upto;
        if whole == 0 {
            continue;
        }
        let scale = whole as f64 / total;
        let (mut cum, mut given) = (0.0, 0);
        let mut run: Option<(f32, usize)> = None;
        for j in first..=last {
            cum += quota[j] * scale;
            let upto = round(cum, whole).max(given);
            let c = upto - given;
            given = upto;
            if c > 0 {
                let start = match run {
                    Some((s, rc)) => {
                        emit(s, ends[j], rc);
                        ends[j]
                    }
                    None => ends[first],
                };
                run = Some((start, c));
            }
        }
        // Rounding can leave the last sample of a stretch unplaced: the last run takes it.
        if let Some((s, rc)) = run {
            emit(s, ends[last + 1], rc + (whole - given));
        }
    }
}

/// The fixed semantic distribution at distance `t` of a ray with intervals `iv` (equal over the
/// distinct classes of the intervals containing `t`; sky inside the sky interval; zeros outside
/// everything), and whether exactly one class encloses the point. `out` has one entry per class.
pub fn fixed_semantic_at(prims: &PrimInfo, iv: &Intervals, t: f32, out: &mut [f32]) -> bool {
    out.iter_mut().for_each(|v| *v = 0.0);
    let mut count = 0;
    for j in 0..iv.t_in.len() {
        if t >= iv.t_in[j] && t <= iv.t_out[j] {
            let c = prims.prim_class[iv.prim[j] as usize] as usize;
            if out[c] == 0.0 {
                out[c] = 1.0;
                count += 1;
            }
        }
    }
    if count == 0 {
        let [s0, s1] = iv.sky;
        if t >= s0 && t <= s1 && s1 > s0 {
            out[prims.sky_class()] = 1.0;
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

/// The fixed instance distribution at distance `t` of a ray with intervals `iv` over
/// `prims.things` (equal over the distinct thing instances whose intervals contain `t`).
/// Returns whether any thing contains it.
pub fn fixed_instance_at(prims: &PrimInfo, iv: &Intervals, t: f32, out: &mut [f32]) -> bool {
    out.iter_mut().for_each(|v| *v = 0.0);
    let mut count = 0;
    for j in 0..iv.t_in.len() {
        let th = prims.prim_thing[iv.prim[j] as usize];
        if th != u32::MAX && t >= iv.t_in[j] && t <= iv.t_out[j] && out[th as usize] == 0.0 {
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

/// The non-zero entries of [`fixed_semantic_at`] and [`fixed_instance_at`] at `t`, which share
/// their weight equally: the distinct class indices (the sky class alone inside the sky
/// interval when no interval contains `t`) and the distinct thing indices. At most one entry per
/// interval, where the dense distributions have one per class and per thing instance: what
/// rendering adds up per sample.
pub fn fixed_members_at(
    prims: &PrimInfo,
    iv: &Intervals,
    t: f32,
    classes: &mut Vec<usize>,
    things: &mut Vec<usize>,
) {
    classes.clear();
    things.clear();
    for j in 0..iv.t_in.len() {
        if t >= iv.t_in[j] && t <= iv.t_out[j] {
            let prim = iv.prim[j] as usize;
            let c = prims.prim_class[prim] as usize;
            if !classes.contains(&c) {
                classes.push(c);
            }
            let th = prims.prim_thing[prim];
            if th != u32::MAX && !things.contains(&(th as usize)) {
                things.push(th as usize);
            }
        }
    }
    let [s0, s1] = iv.sky;
    if classes.is_empty() && t >= s0 && t <= s1 && s1 > s0 {
        classes.push(prims.sky_class());
    }
}

/// Rays per parallel part of a batch.
const CHUNK: usize = 128;

/// Builds the batch of rays `ray_ids`. `seed` drives the stratified jitter (None: stratum
/// centres). Chunks of rays are built in parallel; each ray has its own generator, so the batch
/// does not depend on the thread count.
pub fn sample_batch(
    rays: &dyn Rays,
    ray_ids: &[u32],
    p: &SamplingParams,
    seed: Option<u64>,
) -> Result<SampleBatch> {
    if ray_ids.len() <= CHUNK {
        return sample_rays(rays, ray_ids, p, seed);
    }
    let parts: Vec<SampleBatch> = ray_ids
        .par_chunks(CHUNK)
        .map(|ids| sample_rays(rays, ids, p, seed))
        .collect::<Result<_>>()?;
    let mut b = SampleBatch {
        rays: ray_ids.len(),
        samples: p.per_ray(),
        classes: rays.prims().classes.len(),
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
    Ok(b)
}

/// The samples of rays `ray_ids` at their stratum centres, on one thread, without what only
/// training reads (fixed semantics, targets): rendering evaluates the fixed fields only at the
/// samples the compositor reaches.
pub fn sample_for_render(
    rays: &dyn Rays,
    ray_ids: &[u32],
    p: &SamplingParams,
) -> Result<SampleBatch> {
    sample_into(rays, ray_ids, p, None, false)
}

/// [`sample_batch`] on one thread.
fn sample_rays(
    rays: &dyn Rays,
    ray_ids: &[u32],
    p: &SamplingParams,
    seed: Option<u64>,
) -> Result<SampleBatch> {
    sample_into(rays, ray_ids, p, seed, true)
}

/// The samples of `ray_ids`; with `training`, also the fixed semantics at every sample and the
/// rays' targets.
fn sample_into(
    rays: &dyn Rays,
    ray_ids: &[u32],
    p: &SamplingParams,
    seed: Option<u64>,
    training: bool,
) -> Result<SampleBatch> {
    let prims = rays.prims();
    let (r_n, s_n) = (ray_ids.len(), p.per_ray());
    let c_n = prims.classes.len();
    let (f_n, t_n) = if training { (c_n, 1) } else { (0, 0) };
    let mut b = SampleBatch {
        rays: r_n,
        samples: s_n,
        classes: c_n,
        ray_ids: ray_ids.to_vec(),
        positions: vec![0.0; r_n * s_n * 3],
        dirs: vec![0.0; r_n * 3],
        deltas: vec![0.0; r_n * s_n],
        t: vec![0.0; r_n * s_n],
        fixed_semantic: vec![0.0; r_n * s_n * f_n],
        unique_class: vec![0.0; r_n * s_n * t_n],
        target_rgb: vec![0.0; r_n * 3 * t_n],
        label: vec![-1; r_n * t_n],
        u_mask: vec![0.0; r_n * t_n],
        depth: vec![0.0; r_n * t_n],
        z_scale: vec![0.0; r_n],
    };
    let mut buf = RayPlan::default();
    for (i, &rid) in ray_ids.iter().enumerate() {
        let ray = rays.ray(rid, &mut buf)?;
        let mut rng =
            seed.map(|s| SplitMix64::new(s ^ (rid as u64).wrapping_mul(0xA24B_AED4_963E_E407)));
        let ts = &mut b.t[i * s_n..(i + 1) * s_n];
        let ds = &mut b.deltas[i * s_n..(i + 1) * s_n];
        place_samples(&ray.intervals, p, rng.as_mut(), ts, ds);
        let (o, d) = (ray.origin, ray.dir);
        b.dirs[i * 3..i * 3 + 3].copy_from_slice(&d);
        b.z_scale[i] = ray.z_scale;
        for s in 0..s_n {
            let t = b.t[i * s_n + s];
            for k in 0..3 {
                b.positions[(i * s_n + s) * 3 + k] = o[k] + t * d[k];
            }
        }
        if !training {
            continue;
        }
        for s in 0..s_n {
            let t = b.t[i * s_n + s];
            let fs = &mut b.fixed_semantic[(i * s_n + s) * c_n..(i * s_n + s + 1) * c_n];
            let unique = fixed_semantic_at(prims, &ray.intervals, t, fs);
            b.unique_class[i * s_n + s] = if unique && b.deltas[i * s_n + s] > 0.0 {
                1.0
            } else {
                0.0
            };
        }
        let tg = ray.targets;
        b.target_rgb[i * 3..i * 3 + 3].copy_from_slice(&tg.rgb);
        b.label[i] = if tg.label == NONE {
            -1
        } else {
            tg.label as i64
        };
        b.u_mask[i] = if tg.u_mask { 1.0 } else { 0.0 };
        b.depth[i] = tg.depth;
    }
    Ok(b)
}

#[cfg(test)]
mod tests;
