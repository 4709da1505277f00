//! The pseudo-label model: turns a ground-truth label map into the kind of noisy prediction a
//! 2D segmentation network makes, so the method has something realistic to correct.
//!
//! Four effects, applied in order, each driven by random fields that depend only on
//! (seed, frame) and each growing with the `noise` level `s` through thresholds (so the error
//! regions at a smaller `s` are, effect by effect, contained in those at a larger one):
//! 1. missed objects: small segments (distant or thin things, fences, gates) and a few random
//!    ones vanish, filled in from their surroundings;
//! 2. boundary errors: labels are read through a smooth random displacement field;
//! 3. confusions between similar classes (road/parking/sidewalk, vegetation/terrain,
//!    wall/fence/building/gate, caravan/trailer/car, box/building, rider/bicycle) in smooth
//!    blotches;
//! 4. blotches of wrong labels in over-exposed regions.
//!
//! `s = 0` gives the ground truth back; the default `s = 1` is calibrated to about 65-70 mIoU.
//! A fifth effect is off by default ([`far_region_errors`]): whole distant segments labelled as
//! a class theirs is confused with, as networks do where far regions lack the detail near ones
//! have.

use super::rng::{fbm2, hash, unit, value2};
use crate::labels::{
    BICYCLE, BOX, BUILDING, CAR, CARAVAN, FENCE, GATE, PARKING, RIDER, ROAD, SIDEWALK, SKY,
    TERRAIN, TRAILER, VEGETATION, WALL,
};

/// One image's ground truth, as the noise model sees it.
pub struct NoiseInput<'a> {
    pub width: usize,
    pub height: usize,
    /// Label ids, row-major.
    pub labels: &'a [u8],
    /// `id * 1000 + instance`, row-major (separates touching things of one class).
    pub instances: &'a [u16],
    /// Pixels whose colour clipped (any channel saturated).
    pub overexposed: &'a [bool],
}

/// (class, fraction of its area confused at noise 1, the classes it is confused with).
const CONFUSIONS: &[(u8, f64, &[u8])] = &[
    (ROAD, 0.06, &[PARKING, SIDEWALK]),
    (PARKING, 0.35, &[ROAD, SIDEWALK]),
    (SIDEWALK, 0.15, &[ROAD, PARKING, TERRAIN]),
    (VEGETATION, 0.08, &[TERRAIN]),
    (TERRAIN, 0.22, &[VEGETATION, SIDEWALK]),
    (BUILDING, 0.04, &[WALL]),
    (WALL, 0.3, &[BUILDING, FENCE]),
    (FENCE, 0.3, &[WALL, VEGETATION, BUILDING]),
    (GATE, 0.35, &[FENCE, WALL]),
    (CAR, 0.02, &[CARAVAN]),
    (CARAVAN, 0.3, &[CAR, TRAILER]),
    (TRAILER, 0.3, &[CAR, CARAVAN]),
    (BOX, 0.3, &[BUILDING, WALL]),
    (RIDER, 0.15, &[BICYCLE]),
    (BICYCLE, 0.3, &[RIDER]),
];

/// Classes whose segments can be missed: (class, chance per segment at noise 1).
const MISSABLE: &[(u8, f64)] = &[
    (CAR, 0.02),
    (CARAVAN, 0.05),
    (TRAILER, 0.08),
    (BOX, 0.15),
    (FENCE, 0.12),
    (GATE, 0.15),
    (WALL, 0.05),
    (BICYCLE, 0.1),
    (RIDER, 0.03),
];

/// Labels that blotches in over-exposed regions take.
const BLOTCH_LABELS: &[u8] = &[SKY, BUILDING, VEGETATION, WALL];

/// Segments smaller than this fraction of the image (times the noise level) are missed.
const MISS_AREA_FRACTION: f64 = 0.0006;
/// Boundary displacement amplitude at noise 1, in pixels of a 176-pixel-wide image.
const BOUNDARY_PX: f64 = 0.5;
/// The `noise` param is multiplied by this: calibrated so that noise 1 scores about 67 mIoU on
/// the default scene (the paper's 2D input scored 67.2).
const NOISE_CALIBRATION: f64 = 0.8;
/// Scales every class's confusion rate (calibration of the default noise level).
const CONFUSION_SCALE: f64 = 0.5;
/// Standard deviation of [`fbm2`] values (measured).
const FBM_SD: f64 = 0.13;
/// Fraction of over-exposed area that turns into blotches at noise 1.
const BLOTCH_FRACTION: f64 = 0.25;

/// The noisy labels of one image at noise level `noise` (0 = ground truth).
pub fn pseudo_labels(inp: &NoiseInput, noise: f64, seed: u64, frame: u32) -> Vec<u8> {
    let (w, h) = (inp.width, inp.height);
    let noise = noise * NOISE_CALIBRATION;
    if noise <= 0.0 {
        return inp.labels.to_vec();
    }
    let key = |purpose: u64| hash(&[seed, 0x5015E, frame as u64, purpose]);
    // Field coordinates in units of a 176-pixel-wide image, so the model is scale-free.
    let unit_px = w as f64 / 176.0;

    // 1. Missed segments.
    let missed = missed_mask(inp, noise, key(1));
    let mut base = inp.labels.to_vec();
    fill_from_neighbours(&mut base, &missed, w, h);

    // 2. Boundary errors: read labels through a smooth displacement field.
    let (kx, ky) = (key(2), key(3));
    let amp = noise * BOUNDARY_PX * unit_px;
    let cell = 5.0 * unit_px;
    let mut out = vec![0u8; w * h];
    for y in 0..h {
        for x in 0..w {
            let (fx, fy) = (x as f64 / cell, y as f64 / cell);
            let dx = (value2(kx, fx, fy) * 2.0 - 1.0) * amp * 1.6;
            let dy = (value2(ky, fx, fy) * 2.0 - 1.0) * amp * 1.6;
            let sx = (x as f64 + dx).round().clamp(0.0, (w - 1) as f64) as usize;
            let sy = (y as f64 + dy).round().clamp(0.0, (h - 1) as f64) as usize;
            out[y * w + x] = base[sy * w + sx];
        }
    }

    // 3. Confusions between similar classes, in smooth blotches.
    let blob = 9.0 * unit_px;
    for (i, l) in out.iter_mut().enumerate() {
        let Some(&(_, rate, targets)) = CONFUSIONS.iter().find(|c| c.0 == *l) else {
            continue;
        };
        let (x, y) = ((i % w) as f64 / blob, (i / w) as f64 / blob);
        let r = fbm2(key(100 + *l as u64), x, y);
        if quantile_above(r, CONFUSION_SCALE * rate * noise) {
            let pick = value2(key(200 + *l as u64), x * 0.5, y * 0.5);
            *l = targets[((pick * targets.len() as f64) as usize).min(targets.len() - 1)];
        }
    }

    // 4. Blotches in over-exposed regions.
    let kb = key(4);
    for (i, l) in out.iter_mut().enumerate() {
        if !inp.overexposed[i] {
            continue;
        }
        let (x, y) = ((i % w) as f64 / blob, (i / w) as f64 / blob);
        if quantile_above(fbm2(kb, x, y), BLOTCH_FRACTION * noise) {
            let pick = value2(kb ^ 0xB10, x * 0.7, y * 0.7);
            let b = BLOTCH_LABELS[((pick * 4.0) as usize).min(3)];
            *l = if b == inp.labels[i] {
                BLOTCH_LABELS[(((pick * 4.0) as usize) + 1) % 4]
            } else {
                b
            };
        }
    }
    out
}

/// Segments whose mean depth lies beyond this many metres count as far.
pub const FAR_REGION_M: f32 = 30.0;

/// Effect 5: each far segment (connected pixels of one GT class and instance, mean depth beyond
/// [`FAR_REGION_M`]) of a class with [`CONFUSIONS`] is, with chance `chance * noise` (clamped
/// to 1), labelled whole in `labels` as one class it is confused with, where `labels` still
/// has its GT class. `depth`: the GT z-depth per pixel (0 = sky). The coins depend only on
/// (seed, frame, segment), so a larger chance keeps the smaller one's errors.
pub fn far_region_errors(
    inp: &NoiseInput,
    depth: &[f32],
    labels: &mut [u8],
    chance: f64,
    noise: f64,
    seed: u64,
    frame: u32,
) {
    let p = (chance * noise).min(1.0);
    if p <= 0.0 {
        return;
    }
    let (w, h) = (inp.width, inp.height);
    let comp = components(inp.labels, inp.instances, w, h);
    let mut sum = vec![(0f64, 0u32); comp.count];
    for (&c, &d) in comp.ids.iter().zip(depth) {
        if d > 0.0 && d.is_finite() {
            let s = &mut sum[c as usize];
            *s = (s.0 + d as f64, s.1 + 1);
        }
    }
    let key = hash(&[seed, 0x5015E, frame as u64, 5]);
    let to: Vec<Option<u8>> = (0..comp.count)
        .map(|c| {
            let (total, n) = sum[c];
            let far = n > 0 && total / n as f64 > FAR_REGION_M as f64;
            let (_, _, targets) = CONFUSIONS.iter().find(|x| x.0 == comp.labels[c])?;
            let identity = [key, comp.instances[c] as u64, comp.first[c] as u64 / 7];
            (far && unit(&identity) < p).then(|| {
                let pick = unit(&[identity[0] ^ 0xFA2, identity[1], identity[2]]);
                targets[((pick * targets.len() as f64) as usize).min(targets.len() - 1)]
            })
        })
        .collect();
    for (i, l) in labels.iter_mut().enumerate() {
        if let Some(t) = to[comp.ids[i] as usize] {
            if *l == inp.labels[i] {
                *l = t;
            }
        }
    }
}

/// Whether a field value `r` (fbm, roughly bell-shaped on [0, 1)) lies in the top `fraction`
/// of its distribution. A monotone threshold keeps error regions nested as `fraction` grows.
fn quantile_above(r: f64, fraction: f64) -> bool {
    if fraction <= 0.0 {
        return false;
    }
    // The fbm of two value-noise octaves is roughly a bell on [0, 1) centred at 0.5 with
    // standard deviation ~0.13: threshold at its (1 - fraction) quantile, with the logistic
    // approximation of the normal quantile function.
    let f = fraction.clamp(1e-6, 1.0 - 1e-6);
    let threshold = 0.5 + FBM_SD * ((1.0 - f) / f).ln() / 1.7;
    r > threshold
}

/// Pixels of segments the network misses.
fn missed_mask(inp: &NoiseInput, noise: f64, key: u64) -> Vec<bool> {
    let (w, h) = (inp.width, inp.height);
    let comp = components(inp.labels, inp.instances, w, h);
    let mut area = vec![0usize; comp.count];
    for &c in &comp.ids {
        area[c as usize] += 1;
    }
    let min_area = noise * MISS_AREA_FRACTION * (w * h) as f64;
    let missed: Vec<bool> = (0..comp.count)
        .map(|c| {
            let label = comp.labels[c];
            let Some(&(_, chance)) = MISSABLE.iter().find(|m| m.0 == label) else {
                return false;
            };
            // A segment's identity for the coin: its label, instance and a stable pixel.
            let coin = unit(&[key, comp.instances[c] as u64, comp.first[c] as u64 / 7]);
            (area[c] as f64) < min_area || coin < chance * noise
        })
        .collect();
    comp.ids.iter().map(|&c| missed[c as usize]).collect()
}

/// Connected components (4-neighbour) of equal (label, instance).
struct Components {
    ids: Vec<u32>,
    count: usize,
    labels: Vec<u8>,
    instances: Vec<u16>,
    first: Vec<usize>,
}

fn components(labels: &[u8], instances: &[u16], w: usize, h: usize) -> Components {
    let mut ids = vec![u32::MAX; w * h];
    let (mut lab, mut ins, mut first) = (Vec::new(), Vec::new(), Vec::new());
    let mut stack = Vec::new();
    for start in 0..w * h {
        if ids[start] != u32::MAX {
            continue;
        }
        let c = lab.len() as u32;
        let key = (labels[start], instances[start]);
        lab.push(key.0);
        ins.push(key.1);
        first.push(start);
        ids[start] = c;
        stack.push(start);
        while let Some(i) = stack.pop() {
            let (x, y) = (i % w, i / w);
            let mut visit = |j: usize| {
                if ids[j] == u32::MAX && (labels[j], instances[j]) == key {
                    ids[j] = c;
                    stack.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < w {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - w);
            }
            if y + 1 < h {
                visit(i + w);
            }
        }
    }
    Components {
        ids,
        count: lab.len(),
        labels: lab,
        instances: ins,
        first,
    }
}

/// Replaces masked pixels by labels grown in from unmasked neighbours (repeated 4-neighbour
/// dilation, first neighbour in a fixed order wins; deterministic).
fn fill_from_neighbours(labels: &mut [u8], mask: &[bool], w: usize, h: usize) {
    let mut todo: Vec<bool> = mask.to_vec();
    let mut remaining = todo.iter().filter(|&&m| m).count();
    while remaining > 0 {
        let mut changed = Vec::new();
        for i in 0..w * h {
            if !todo[i] {
                continue;
            }
            let (x, y) = (i % w, i / w);
            let nbrs = [
                (y + 1 < h).then(|| i + w),
                (x > 0).then(|| i - 1),
                (x + 1 < w).then(|| i + 1),
                (y > 0).then(|| i - w),
            ];
            if let Some(j) = nbrs.into_iter().flatten().find(|&j| !todo[j]) {
                changed.push((i, labels[j]));
            }
        }
        if changed.is_empty() {
            break; // the whole image is masked: leave it as it is
        }
        for (i, l) in changed {
            labels[i] = l;
            todo[i] = false;
            remaining -= 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image() -> (Vec<u8>, Vec<u16>) {
        // Sky on top, a building block, road below with a small box.
        let (w, h) = (40, 20);
        let mut l = vec![SKY; w * h];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if y >= 12 {
                    l[i] = ROAD;
                } else if y >= 5 && x < 25 {
                    l[i] = BUILDING;
                }
                if y == 14 && (30..33).contains(&x) {
                    l[i] = BOX;
                }
            }
        }
        let inst = l
            .iter()
            .map(|&c| c as u16 * 1000 + u16::from(c == BOX || c == BUILDING))
            .collect();
        (l, inst)
    }

    #[test]
    fn zero_noise_is_ground_truth_and_noise_changes_labels() {
        let (l, inst) = image();
        let over = vec![false; l.len()];
        let inp = NoiseInput {
            width: 40,
            height: 20,
            labels: &l,
            instances: &inst,
            overexposed: &over,
        };
        assert_eq!(pseudo_labels(&inp, 0.0, 1, 0), l);
        let a = pseudo_labels(&inp, 1.0, 1, 0);
        assert_eq!(a, pseudo_labels(&inp, 1.0, 1, 0));
        let wrong = |p: &[u8]| p.iter().zip(&l).filter(|(a, b)| a != b).count();
        assert!(wrong(&a) > 0);
        assert!(wrong(&pseudo_labels(&inp, 3.0, 1, 0)) > wrong(&a));
        // The 3-pixel box is smaller than the missed-segment area at the largest noise
        // (0.0006 * 0.8 * 10 * 800 = 3.8 px).
        let p5 = pseudo_labels(&inp, 10.0, 1, 0);
        assert!(!p5.contains(&BOX));
    }

    #[test]
    fn far_region_errors_relabel_whole_far_segments_only() {
        // Two buildings of 20x20: instance 1 near (10 m), instance 2 far (60 m); sky above none.
        let (w, h) = (40, 20);
        let l = vec![BUILDING; w * h];
        let inst: Vec<u16> = (0..w * h)
            .map(|i| BUILDING as u16 * 1000 + 1 + u16::from(i % w >= 20))
            .collect();
        let depth: Vec<f32> = (0..w * h)
            .map(|i| if i % w >= 20 { 60.0 } else { 10.0 })
            .collect();
        let over = vec![false; w * h];
        let inp = NoiseInput {
            width: w,
            height: h,
            labels: &l,
            instances: &inst,
            overexposed: &over,
        };
        let run = |chance: f64| {
            let mut out = l.clone();
            far_region_errors(&inp, &depth, &mut out, chance, 1.0, 3, 0);
            out
        };
        assert_eq!(run(0.0), l);
        let all = run(10.0);
        for (i, &x) in all.iter().enumerate() {
            if i % w >= 20 {
                assert_eq!(
                    x, WALL,
                    "far pixel {i}: building is confused with wall only"
                );
            } else {
                assert_eq!(x, BUILDING, "near pixel {i}");
            }
        }
        // Pixels another effect already changed stay as they were.
        let mut pre = l.clone();
        pre[30] = SKY;
        far_region_errors(&inp, &depth, &mut pre, 10.0, 1.0, 3, 0);
        assert_eq!(pre[30], SKY);
        assert_eq!(pre[31], WALL);
    }

    #[test]
    fn fill_grows_labels_into_holes() {
        let mut l = vec![1u8, 1, 2, 2, 2, 2];
        let mask = vec![false, false, true, true, false, false];
        fill_from_neighbours(&mut l, &mask, 6, 1);
        assert_eq!(l, vec![1, 1, 1, 2, 2, 2]);
    }
}
