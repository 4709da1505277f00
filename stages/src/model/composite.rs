//! Per-ray volume compositing for inference (render stage), in plain Rust: weights from
//! densities, then colour, depth, learned and fixed semantic distributions and the fixed
//! instance distribution, with early ray termination. Every engine's inference goes through
//! this one compositor (engines only evaluate the field at the samples); the training path
//! computes the same quantities on tensors ([`crate::model::burn::volume`]) and the fused
//! engine by hand, and tests hold them to the same numbers.
//!
//! Conventions (REFERENCE.md section 1): alpha_i = 1 - exp(-sigma_i delta_i), T_i =
//! exp(-sum_{j<i} sigma_j delta_j), w_i = T_i alpha_i; the remainder 1 - sum w_i is the sky
//! probability in both semantic renderings.

use crate::labels;
use crate::sampling::{fixed_members_at, Intervals, PrimInfo};

/// Transmittance below which the rest of a ray is skipped.
pub const EARLY_STOP_T: f32 = 1e-4;

/// Transmittance below which a ray also stops once its labels are settled (see
/// [`Compositor::settled`]): the rest of the ray cannot change its semantic, fixed-field or
/// panoptic label, and changes its depth, colour and confidence by at most this much weight.
pub const LABEL_STOP_T: f32 = 1e-2;

/// e^x without a libm call, so loops over classes vectorise: range reduction to 2^n e^r with
/// |r| <= ln 2 / 2 and Cephes' degree-5 polynomial for e^r; within 2 ulp of `f32::exp`
/// (tested). Inputs below -87.3 give about 1e-38, above 88 about 1.7e38.
#[inline]
pub fn fast_exp(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    // ln 2 in two parts, so n * LN2_HI is exact.
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // 1.5 * 2^23: adding and subtracting it rounds to the nearest integer.
    const ROUND: f32 = 12_582_912.0;
    let x = x.clamp(-87.3, 88.0);
    let n = (x * LOG2E + ROUND) - ROUND;
    let r = x - n * LN2_HI - n * LN2_LO;
    let p = ((((1.987_569_2e-4 * r + 1.398_2e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2) * r
        + 1.666_666_5e-1)
        * r
        + 0.5;
    let e_r = p * r * r + r + 1.0;
    e_r * f32::from_bits(((n as i32 + 127) as u32) << 23)
}

/// One sample (of width `delta` > 0) of the front-to-back march, given the log transmittance
/// before it: `None` once the transmittance is below [`EARLY_STOP_T`] (the rest of the ray is
/// skipped), else that transmittance and the sample's optical depth, with `log_t` advanced.
#[inline]
pub fn march_step(log_t: &mut f32, sigma: f32, delta: f32) -> Option<(f32, f32)> {
    let tr = fast_exp(*log_t);
    if tr < EARLY_STOP_T {
        return None;
    }
    let sd = (sigma.max(0.0) * delta).min(1e4);
    *log_t -= sd;
    Some((tr, sd))
}

/// What one ray composites to.
#[derive(Debug, Clone, PartialEq)]
pub struct Composite {
    pub rgb: [f32; 3],
    /// Expected distance along the ray over the non-sky part (sum w t / sum w), 0 if no weight.
    pub t: f32,
    /// sum of weights (1 - remainder).
    pub opacity: f32,
    /// Median distance: the `t` of the sample at which the accumulated weight first reaches
    /// 0.5 (nerfstudio's "median" depth), 0 if it never does (opacity below 0.5).
    pub t_median: f32,
    /// Index of the argmax class of the learned rendering S, and its probability.
    pub class: usize,
    pub confidence: f32,
    /// Argmax class of the fixed rendering S_hat.
    pub fixed_class: usize,
    /// Argmax thing instance (index into `PrimInfo::things`) of the class, if any.
    pub thing: Option<usize>,
}

/// The running sums of one ray besides its per-class sums.
#[derive(Debug, Clone, Copy, Default)]
pub struct RaySums {
    pub color: [f32; 3],
    /// sum w t and sum w.
    pub wt: f32,
    pub wsum: f32,
    /// The `t` of the sample where `wsum` first reached 0.5, 0 before.
    pub t_median: f32,
    /// Log transmittance: -sum sigma delta.
    pub log_t: f32,
    /// The transmittance fell below [`EARLY_STOP_T`]: later samples are not added.
    pub saturated: bool,
}

/// Front-to-back compositing of rays over the primitives `prims`, a sample at a time. A ray's
/// per-class sums live in a slice of [`Compositor::width`] values: S `[C]`, S_hat `[C]`, the
/// instance distribution `[I]`. Holds scratch buffers only (no allocation per sample).
pub struct Compositor<'p> {
    prims: &'p PrimInfo,
    sky: usize,
    prob: Vec<f32>,
    /// The classes and thing instances of the fixed fields at the current sample.
    fixed: Vec<usize>,
    fixed_inst: Vec<usize>,
}

impl<'p> Compositor<'p> {
    pub fn new(prims: &'p PrimInfo) -> Self {
        Self {
            sky: prims.sky_class(),
            prob: vec![0.0; prims.classes.len()],
            fixed: Vec::new(),
            fixed_inst: Vec::new(),
            prims,
        }
    }

    /// Per-class sums per ray.
    pub fn width(&self) -> usize {
        2 * self.prims.classes.len() + self.prims.things.len()
    }

    /// Adds the sample at `t` (width `delta`, field outputs `sigma`, `rgb` (empty: no colour)
    /// and `logits`) of a ray with intervals `iv`; false once the ray is saturated (nothing is
    /// added from then on).
    #[allow(clippy::too_many_arguments)]
    pub fn add(
        &mut self,
        ray: &mut RaySums,
        sums: &mut [f32],
        iv: &Intervals,
        t: f32,
        delta: f32,
        sigma: f32,
        rgb: &[f32],
        logits: &[f32],
    ) -> bool {
        if ray.saturated {
            return false;
        }
        if delta <= 0.0 {
            return true;
        }
        let Some((tr, sd)) = march_step(&mut ray.log_t, sigma, delta) else {
            ray.saturated = true;
            return false;
        };
        let w = tr * (1.0 - fast_exp(-sd));
        if w <= 0.0 {
            return true;
        }
        for (k, &c) in rgb.iter().enumerate().take(3) {
            ray.color[k] += w * c;
        }
        ray.wt += w * t;
        if ray.wsum < 0.5 && ray.wsum + w >= 0.5 {
            ray.t_median = t;
        }
        ray.wsum += w;
        let c_n = self.prims.classes.len();
        softmax_fast(logits, &mut self.prob);
        let (s, rest) = sums.split_at_mut(c_n);
        let (s_hat, inst) = rest.split_at_mut(c_n);
        for (sc, &p) in s.iter_mut().zip(&self.prob) {
            *sc += w * p;
        }
        // The fixed fields are equal shares over a few classes and instances: add only those
        // (the zero entries of the dense distributions would add exactly 0).
        fixed_members_at(self.prims, iv, t, &mut self.fixed, &mut self.fixed_inst);
        for (members, out) in [(&self.fixed, s_hat), (&self.fixed_inst, inst)] {
            let share = match members.len() {
                0 => continue,
                1 => 1.0,
                n => 1.0 / n as f32,
            };
            for &m in members.iter() {
                out[m] += w * share;
            }
        }
        true
    }

    /// Whether the rest of the ray cannot change its labels: its transmittance T (the weight
    /// the rest of the ray and the sky remainder share) is below [`LABEL_STOP_T`], and the
    /// argmax of S, of S_hat and of the argmax class's instances each lead the runner-up by more
    /// than T, so no way of sharing T among the classes can overtake them.
    pub fn settled(&self, ray: &RaySums, sums: &[f32]) -> bool {
        let tr = fast_exp(ray.log_t);
        // Below EARLY_STOP_T the compositor adds nothing more.
        if ray.saturated || tr < EARLY_STOP_T {
            return true;
        }
        if tr >= LABEL_STOP_T {
            return false;
        }
        // Float sums of the full ray may differ from the ideal by rounding: a margin.
        let bound = tr * (1.0 + 1e-3) + 1e-6;
        let c_n = self.prims.classes.len();
        let (s, s_hat, inst) = (&sums[..c_n], &sums[c_n..2 * c_n], &sums[2 * c_n..]);
        let (Some((class, g1)), Some((_, g2))) = (lead(s), lead(s_hat)) else {
            return false;
        };
        if g1 <= bound || g2 <= bound {
            return false;
        }
        let label = self.prims.classes[class];
        if !labels::by_id(label).is_some_and(|l| l.has_instances) {
            return true;
        }
        let mut top = [0f32; 2];
        let mut any = false;
        for (k, &(l, _)) in self.prims.things.iter().enumerate() {
            if l == label {
                any = true;
                let v = inst[k];
                if v > top[0] {
                    top = [v, top[0]];
                } else if v > top[1] {
                    top[1] = v;
                }
            }
        }
        !any || top[0] - top[1] > bound
    }

    /// The ray's composite; the remainder 1 - sum w goes to sky in S and S_hat.
    pub fn finish(&self, ray: &RaySums, sums: &mut [f32]) -> Composite {
        let c_n = self.prims.classes.len();
        let (s, rest) = sums.split_at_mut(c_n);
        let (s_hat, inst) = rest.split_at_mut(c_n);
        let remainder = (1.0 - ray.wsum).max(0.0);
        s[self.sky] += remainder;
        s_hat[self.sky] += remainder;
        let (class, confidence) = argmax(s);
        let (fixed_class, _) = argmax(s_hat);
        // Panoptic: instances whose class differs from the argmax class are zeroed.
        let label = self.prims.classes[class];
        let mut thing = None;
        if labels::by_id(label).is_some_and(|l| l.has_instances) {
            let mut best = 0.0;
            for (k, &(l, _)) in self.prims.things.iter().enumerate() {
                if l == label && inst[k] > best {
                    best = inst[k];
                    thing = Some(k);
                }
            }
        }
        Composite {
            rgb: ray.color,
            t: if ray.wsum > 0.0 {
                ray.wt / ray.wsum
            } else {
                0.0
            },
            opacity: ray.wsum,
            t_median: ray.t_median,
            class,
            confidence,
            fixed_class,
            thing,
        }
    }
}

/// Softmax of `logits` into `out` (max-shifted).
#[inline(always)]
pub fn softmax_into(logits: &[f32], out: &mut [f32]) {
    let m = logits.iter().cloned().fold(f32::NEG_INFINITY, f32::max);
    let mut z = 0.0;
    for (o, &l) in out.iter_mut().zip(logits) {
        *o = (l - m).exp();
        z += *o;
    }
    out.iter_mut().for_each(|o| *o /= z);
}

/// [`softmax_into`] with [`fast_exp`] (rendering; training keeps the libm one).
fn softmax_fast(logits: &[f32], out: &mut [f32]) {
    let m = logits.iter().cloned().fold(f32::NEG_INFINITY, f32::max);
    for (o, &l) in out.iter_mut().zip(logits) {
        *o = fast_exp(l - m);
    }
    let z: f32 = out.iter().sum();
    out.iter_mut().for_each(|o| *o /= z);
}

fn argmax(v: &[f32]) -> (usize, f32) {
    v.iter()
        .enumerate()
        .fold((0, f32::NEG_INFINITY), |(bi, bv), (i, &x)| {
            if x > bv {
                (i, x)
            } else {
                (bi, bv)
            }
        })
}

/// The argmax of `v` and its lead over the runner-up (`None` for an empty `v`).
fn lead(v: &[f32]) -> Option<(usize, f32)> {
    let (i, top) = argmax(v);
    let second = v
        .iter()
        .enumerate()
        .filter(|&(j, _)| j != i)
        .fold(0f32, |m, (_, &x)| m.max(x));
    (!v.is_empty()).then_some((i, top - second))
}

/// Composites a ray with intervals `iv` from its samples (`t`, `delta`) and the field's outputs
/// at them (`sigma` [S], `rgb` [S, 3] or empty, `logits` [S, C]): every sample up to
/// saturation.
#[allow(clippy::too_many_arguments)]
pub fn composite_ray(
    prims: &PrimInfo,
    iv: &Intervals,
    t: &[f32],
    delta: &[f32],
    sigma: &[f32],
    rgb: &[f32],
    logits: &[f32],
) -> Composite {
    let c_n = prims.classes.len();
    let mut comp = Compositor::new(prims);
    let mut sums = vec![0f32; comp.width()];
    let mut ray = RaySums::default();
    for i in 0..t.len() {
        let col = if rgb.is_empty() {
            &[][..]
        } else {
            &rgb[i * 3..i * 3 + 3]
        };
        let l = &logits[i * c_n..(i + 1) * c_n];
        if !comp.add(&mut ray, &mut sums, iv, t[i], delta[i], sigma[i], col, l) {
            break;
        }
    }
    comp.finish(&ray, &mut sums)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one_ray() -> PrimInfo {
        PrimInfo {
            classes: vec![labels::ROAD, labels::CAR, labels::SKY],
            things: vec![(labels::CAR, 3)],
            prim_class: vec![1],
            prim_thing: vec![0],
            ..Default::default()
        }
    }

    /// The ray's one interval: the car box over [4, 8], then sky [8, 58].
    const IV: Intervals = Intervals {
        t_in: &[4.0],
        t_out: &[8.0],
        prim: &[0],
        sky: [8.0, 58.0],
    };

    #[test]
    fn fast_exp_is_within_two_ulp_of_exp() {
        let mut worst = 0f32;
        let mut x = -87.0f32;
        while x < 88.0 {
            let (a, b) = (fast_exp(x), x.exp());
            worst = worst.max((a - b).abs() / b);
            x += 0.0137;
        }
        assert!(worst < 2.5e-7, "relative error {worst}");
        assert_eq!(fast_exp(0.0), 1.0);
        assert!(fast_exp(-1e4) < 2e-38 && fast_exp(-1e4) >= 0.0);
        assert!(fast_exp(1e4).is_finite());
        assert!(fast_exp(f32::NAN).is_nan() || fast_exp(f32::NAN) >= 0.0);
    }

    #[test]
    fn constant_density_matches_the_analytic_opacity() {
        // sigma = 0.5 over [4, 8] in 4 samples of width 1: opacity = 1 - exp(-2).
        let set = one_ray();
        let t = [4.5, 5.5, 6.5, 7.5];
        let delta = [1.0; 4];
        let sigma = [0.5; 4];
        let rgb = [0.2, 0.4, 0.6].repeat(4);
        let logits = [0.0, 5.0, 0.0].repeat(4);
        let c = composite_ray(&set, &IV, &t, &delta, &sigma, &rgb, &logits);
        let op = 1.0 - (-2.0f32).exp();
        assert!((c.opacity - op).abs() < 1e-5);
        assert!((c.rgb[1] - 0.4 * op).abs() < 1e-5);
        // Expected t: sum w_i t_i / sum w_i with w_i = e^{-0.5 i}(1 - e^{-0.5}).
        let w: Vec<f32> = (0..4)
            .map(|i| (-0.5 * i as f32).exp() * (1.0 - (-0.5f32).exp()))
            .collect();
        let et = w.iter().zip(&t).map(|(a, b)| a * b).sum::<f32>() / w.iter().sum::<f32>();
        assert!((c.t - et).abs() < 1e-4);
        // Median: the first sample whose accumulated weight 1 - e^{-0.5 (i + 1)} reaches 0.5.
        let i = (0..4)
            .find(|&i| 1.0 - (-0.5 * (i + 1) as f32).exp() >= 0.5)
            .unwrap();
        assert_eq!(c.t_median, t[i]);
        assert_eq!(
            set.classes[c.class],
            labels::CAR,
            "car logits dominate the 86% opacity"
        );
        assert_eq!(set.classes[c.fixed_class], labels::CAR);
        assert_eq!(c.thing, Some(0));
    }

    #[test]
    fn transparent_rays_are_sky_and_opaque_rays_stop_early() {
        let set = one_ray();
        let c = composite_ray(
            &set,
            &IV,
            &[5.0],
            &[1.0],
            &[0.0],
            &[1.0; 3],
            &[9.0, 0.0, 0.0],
        );
        assert_eq!(set.classes[c.class], labels::SKY);
        assert_eq!(c.opacity, 0.0);
        assert_eq!(c.t_median, 0.0, "no median depth below 0.5 opacity");
        assert_eq!(c.thing, None);
        // A huge density in the first sample: the rest does not matter.
        let c = composite_ray(
            &set,
            &IV,
            &[4.5, 5.5],
            &[1.0, 1.0],
            &[1e10, f32::NAN],
            &[1.0, 0.0, 0.0, f32::NAN, f32::NAN, f32::NAN],
            &[5.0, 0.0, 0.0, f32::NAN, f32::NAN, f32::NAN],
        );
        assert!((c.opacity - 1.0).abs() < 1e-6);
        assert_eq!(c.rgb, [1.0, 0.0, 0.0]);
        assert_eq!(set.classes[c.class], labels::ROAD);
        assert_eq!(c.t, 4.5);
        assert_eq!(c.t_median, 4.5);
    }
}
