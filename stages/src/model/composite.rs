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
use crate::sampling::{fixed_instance_at, fixed_semantic_at, Intervals, PrimInfo};

/// Transmittance below which the rest of a ray is skipped.
pub const EARLY_STOP_T: f32 = 1e-4;

/// One sample (of width `delta` > 0) of the front-to-back march, given the log transmittance
/// before it: `None` once the transmittance is below [`EARLY_STOP_T`] (the rest of the ray is
/// skipped), else that transmittance and the sample's optical depth, with `log_t` advanced.
/// The compositor and rendering's marching evaluation share it, so they stop at the same sample.
#[inline]
pub fn march_step(log_t: &mut f32, sigma: f32, delta: f32) -> Option<(f32, f32)> {
    let tr = log_t.exp();
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
    /// Index of the argmax class of the learned rendering S, and its probability.
    pub class: usize,
    pub confidence: f32,
    /// Argmax class of the fixed rendering S_hat.
    pub fixed_class: usize,
    /// Argmax thing instance (index into `PrimInfo::things`) of the class, if any.
    pub thing: Option<usize>,
}

/// Scratch buffers reused across rays (no allocation per ray).
pub struct Scratch {
    s: Vec<f32>,
    s_hat: Vec<f32>,
    inst: Vec<f32>,
    fixed: Vec<f32>,
    fixed_inst: Vec<f32>,
    prob: Vec<f32>,
}

impl Scratch {
    pub fn new(classes: usize, things: usize) -> Self {
        Self {
            s: vec![0.0; classes],
            s_hat: vec![0.0; classes],
            inst: vec![0.0; things],
            fixed: vec![0.0; classes],
            fixed_inst: vec![0.0; things],
            prob: vec![0.0; classes],
        }
    }
}

/// Softmax of `logits` into `out` (max-shifted).
pub fn softmax_into(logits: &[f32], out: &mut [f32]) {
    let m = logits.iter().cloned().fold(f32::NEG_INFINITY, f32::max);
    let mut z = 0.0;
    for (o, &l) in out.iter_mut().zip(logits) {
        *o = (l - m).exp();
        z += *o;
    }
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

/// Composites a ray with intervals `iv` from its samples (`t`, `delta`) and the field's outputs
/// at them (`sigma` [S], `rgb` [S, 3], `logits` [S, C]).
#[allow(clippy::too_many_arguments)]
pub fn composite_ray(
    prims: &PrimInfo,
    iv: &Intervals,
    t: &[f32],
    delta: &[f32],
    sigma: &[f32],
    rgb: &[f32],
    logits: &[f32],
    scratch: &mut Scratch,
) -> Composite {
    let c_n = prims.classes.len();
    let sky = prims.sky_class();
    let Scratch {
        s,
        s_hat,
        inst,
        fixed,
        fixed_inst,
        prob,
    } = scratch;
    s.iter_mut().for_each(|v| *v = 0.0);
    s_hat.iter_mut().for_each(|v| *v = 0.0);
    inst.iter_mut().for_each(|v| *v = 0.0);
    let (mut color, mut wt, mut wsum) = ([0.0f32; 3], 0.0f32, 0.0f32);
    let mut log_t = 0.0f32; // log transmittance: -sum sigma delta
    for i in 0..t.len() {
        if delta[i] <= 0.0 {
            continue;
        }
        let Some((tr, sd)) = march_step(&mut log_t, sigma[i], delta[i]) else {
            break;
        };
        let w = tr * (1.0 - (-sd).exp());
        if w <= 0.0 {
            continue;
        }
        for k in 0..3 {
            color[k] += w * rgb[i * 3 + k];
        }
        wt += w * t[i];
        wsum += w;
        softmax_into(&logits[i * c_n..(i + 1) * c_n], prob);
        fixed_semantic_at(prims, iv, t[i], fixed);
        fixed_instance_at(prims, iv, t[i], fixed_inst);
        for c in 0..c_n {
            s[c] += w * prob[c];
            s_hat[c] += w * fixed[c];
        }
        for (a, &b) in inst.iter_mut().zip(fixed_inst.iter()) {
            *a += w * b;
        }
    }
    let remainder = (1.0 - wsum).max(0.0);
    s[sky] += remainder;
    s_hat[sky] += remainder;
    let (class, confidence) = argmax(s);
    let (fixed_class, _) = argmax(s_hat);
    // Panoptic: instances whose class differs from the argmax class are zeroed.
    let label = prims.classes[class];
    let mut thing = None;
    if labels::by_id(label).is_some_and(|l| l.has_instances) {
        let mut best = 0.0;
        for (k, &(l, _)) in prims.things.iter().enumerate() {
            if l == label && inst[k] > best {
                best = inst[k];
                thing = Some(k);
            }
        }
    }
    Composite {
        rgb: color,
        t: if wsum > 0.0 { wt / wsum } else { 0.0 },
        opacity: wsum,
        class,
        confidence,
        fixed_class,
        thing,
    }
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
    fn constant_density_matches_the_analytic_opacity() {
        // sigma = 0.5 over [4, 8] in 4 samples of width 1: opacity = 1 - exp(-2).
        let set = one_ray();
        let t = [4.5, 5.5, 6.5, 7.5];
        let delta = [1.0; 4];
        let sigma = [0.5; 4];
        let rgb = [0.2, 0.4, 0.6].repeat(4);
        let logits = [0.0, 5.0, 0.0].repeat(4);
        let mut sc = Scratch::new(3, 1);
        let c = composite_ray(&set, &IV, &t, &delta, &sigma, &rgb, &logits, &mut sc);
        let op = 1.0 - (-2.0f32).exp();
        assert!((c.opacity - op).abs() < 1e-5);
        assert!((c.rgb[1] - 0.4 * op).abs() < 1e-5);
        // Expected t: sum w_i t_i / sum w_i with w_i = e^{-0.5 i}(1 - e^{-0.5}).
        let w: Vec<f32> = (0..4)
            .map(|i| (-0.5 * i as f32).exp() * (1.0 - (-0.5f32).exp()))
            .collect();
        let et = w.iter().zip(&t).map(|(a, b)| a * b).sum::<f32>() / w.iter().sum::<f32>();
        assert!((c.t - et).abs() < 1e-4);
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
        let mut sc = Scratch::new(3, 1);
        let c = composite_ray(
            &set,
            &IV,
            &[5.0],
            &[1.0],
            &[0.0],
            &[1.0; 3],
            &[9.0, 0.0, 0.0],
            &mut sc,
        );
        assert_eq!(set.classes[c.class], labels::SKY);
        assert_eq!(c.opacity, 0.0);
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
            &mut sc,
        );
        assert!((c.opacity - 1.0).abs() < 1e-6);
        assert_eq!(c.rgb, [1.0, 0.0, 0.0]);
        assert_eq!(set.classes[c.class], labels::ROAD);
        assert_eq!(c.t, 4.5);
    }
}
