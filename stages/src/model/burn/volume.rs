//! Volume rendering on `[rays, samples]` tensors: weights from density, then the rendered colour
//! C, depth D, learned semantics S and fixed semantics S_hat. Stateless: weights and values in,
//! result out.
//!
//! Numerics: transmittance is `exp(-exclusive_cumsum(sigma * delta))` (no product of
//! `1 - alpha`, which underflows and has poor gradients), the exclusive sum is built by shifting
//! (no `cumsum - x` cancellation), and the sky takes the remainder `1 - sum(w)` (clamped at 0)
//! in both semantic renderings. Padding samples with `delta = 0` contribute nothing.

use burn::tensor::Tensor;

/// Per-sample weights of a batch of rays.
///
/// # Shapes
/// `weights`: `[rays, samples]`; `opacity` (= sum of weights): `[rays]`.
#[derive(Debug, Clone)]
pub struct RenderWeights {
    pub weights: Tensor<2>,
    pub opacity: Tensor<1>,
}

/// `w_i = T_i (1 - exp(-sigma_i delta_i))`, `T_i = exp(-sum_{j<i} sigma_j delta_j)`.
///
/// # Shapes
/// `density`, `deltas`: `[rays, samples]`.
pub fn render_weights(density: Tensor<2>, deltas: Tensor<2>) -> RenderWeights {
    let [rays, samples] = density.dims();
    let optical = density * deltas; // [rays, samples]
    let exclusive = if samples > 1 {
        let inclusive = optical.clone().cumsum(1);
        Tensor::cat(
            vec![
                Tensor::zeros([rays, 1], &inclusive.device()),
                inclusive.narrow(1, 0, samples - 1),
            ],
            1,
        )
    } else {
        optical.zeros_like()
    };
    let transmittance = exclusive.neg().exp();
    let alpha = optical.neg().exp().neg().add_scalar(1.0);
    let weights = transmittance * alpha;
    let opacity = weights.clone().sum_dim(1).reshape([rays]);
    RenderWeights { weights, opacity }
}

/// `sum_i w_i v_i` for per-sample vectors.
///
/// # Shapes
/// `weights`: `[rays, samples]`; `values`: `[rays, samples, k]` -> `[rays, k]`.
pub fn render_vectors(weights: &Tensor<2>, values: Tensor<3>) -> Tensor<2> {
    let [rays, _, k] = values.dims();
    (weights.clone().unsqueeze_dim::<3>(2) * values)
        .sum_dim(1) // [rays, 1, k]
        .reshape([rays, k])
}

/// Rendered colour C (black where the ray is transparent).
///
/// # Shapes
/// `rgb`: `[rays, samples, 3]` -> `[rays, 3]`.
pub fn render_rgb(w: &RenderWeights, rgb: Tensor<3>) -> Tensor<2> {
    render_vectors(&w.weights, rgb)
}

/// Rendered (expected) depth D = sum w_i t_i.
///
/// # Shapes
/// `t`: `[rays, samples]` -> `[rays]`.
pub fn render_depth(w: &RenderWeights, t: Tensor<2>) -> Tensor<1> {
    let rays = t.dims()[0];
    (w.weights.clone() * t).sum_dim(1).reshape([rays])
}

/// Rendered class distribution `sum_i w_i p_i + (1 - sum_i w_i) e_sky`: used for the learned S
/// (p = softmax of the logits) and the fixed S_hat (p = the primitives' distribution).
///
/// # Shapes
/// `probs`: `[rays, samples, classes]` -> `[rays, classes]`.
pub fn render_semantics(w: &RenderWeights, probs: Tensor<3>, sky: usize) -> Tensor<2> {
    let [rays, _, classes] = probs.dims();
    assert!(sky < classes, "sky index {sky} >= classes {classes}");
    let device = probs.device();
    let mixed = render_vectors(&w.weights, probs); // [rays, classes]
    let remainder = w.opacity.clone().neg().add_scalar(1.0).clamp_min(0.0); // [rays]
    let mut one_hot = vec![0f32; classes];
    one_hot[sky] = 1.0;
    let sky_row = Tensor::<1>::from_floats(one_hot.as_slice(), &device).unsqueeze::<2>(); // [1, classes]
    mixed + remainder.reshape([rays, 1]) * sky_row
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::burn::Backend;
    use burn::tensor::{Device, TensorData};

    fn t2(v: &[f32], shape: [usize; 2], d: &Device) -> Tensor<2> {
        Tensor::from_data(TensorData::new(v.to_vec(), shape), d)
    }
    fn vec1(t: Tensor<1>) -> Vec<f32> {
        t.into_data().try_to_vec::<f32>().unwrap()
    }
    fn vec2(t: Tensor<2>) -> Vec<f32> {
        t.into_data().try_to_vec::<f32>().unwrap()
    }

    #[test]
    fn constant_density_over_one_interval_has_opacity_one_minus_exp() {
        let d = Backend::REFERENCE.device();
        // sigma = 0.7 over L = 2 split in 64 samples: sum w = 1 - exp(-1.4), any split.
        let s = 64;
        let w = render_weights(
            t2(&vec![0.7; s], [1, s], &d),
            t2(&vec![2.0 / s as f32; s], [1, s], &d),
        );
        let o = vec1(w.opacity)[0];
        assert!((o - (1.0 - (-1.4f32).exp())).abs() < 1e-5, "{o}");
    }

    #[test]
    fn two_samples_by_hand() {
        let d = Backend::REFERENCE.device();
        // sigma = [1, 2], delta = [0.5, 0.25], t = [1, 2], colours red then green.
        let w = render_weights(t2(&[1.0, 2.0], [1, 2], &d), t2(&[0.5, 0.25], [1, 2], &d));
        let a1 = 1.0 - (-0.5f32).exp();
        let a2 = 1.0 - (-0.5f32).exp();
        let (w1, w2) = (a1, (-0.5f32).exp() * a2);
        let got = vec2(w.weights.clone());
        assert!(
            (got[0] - w1).abs() < 1e-6 && (got[1] - w2).abs() < 1e-6,
            "{got:?}"
        );
        let rgb = Tensor::<3>::from_data(
            TensorData::new(vec![1.0f32, 0.0, 0.0, 0.0, 1.0, 0.0], [1, 2, 3]),
            &d,
        );
        let c = vec2(render_rgb(&w, rgb));
        assert!((c[0] - w1).abs() < 1e-6 && (c[1] - w2).abs() < 1e-6 && c[2].abs() < 1e-7);
        let depth = vec1(render_depth(&w, t2(&[1.0, 2.0], [1, 2], &d)))[0];
        assert!((depth - (w1 + 2.0 * w2)).abs() < 1e-6);
        // classes [a, b, sky]: sample 1 is a, sample 2 is half a half b.
        let probs = Tensor::<3>::from_data(
            TensorData::new(vec![1.0f32, 0.0, 0.0, 0.5, 0.5, 0.0], [1, 2, 3]),
            &d,
        );
        let s = vec2(render_semantics(&w, probs, 2));
        let expect = [w1 + 0.5 * w2, 0.5 * w2, 1.0 - w1 - w2];
        for k in 0..3 {
            assert!((s[k] - expect[k]).abs() < 1e-6, "{s:?} vs {expect:?}");
        }
    }

    #[test]
    fn opaque_first_sample_takes_everything_and_sky_gets_nothing() {
        let d = Backend::REFERENCE.device();
        let w = render_weights(t2(&[1e10, 1.0, 1.0], [1, 3], &d), t2(&[1.0; 3], [1, 3], &d));
        assert_eq!(vec2(w.weights.clone()), vec![1.0, 0.0, 0.0]);
        let probs = Tensor::<3>::from_data(
            TensorData::new(vec![0.0f32, 1.0, 0.0, 1.0, 0.0, 1.0], [1, 3, 2]),
            &d,
        );
        assert_eq!(vec2(render_semantics(&w, probs, 1)), vec![0.0, 1.0]);
    }

    #[test]
    fn empty_ray_is_all_sky_and_single_sample_rays_work() {
        let d = Backend::REFERENCE.device();
        let w = render_weights(t2(&[0.0, 0.0], [1, 2], &d), t2(&[1.0, 1.0], [1, 2], &d));
        let probs = Tensor::<3>::from_data(TensorData::new(vec![0.5f32; 4], [1, 2, 2]), &d);
        assert_eq!(vec2(render_semantics(&w, probs, 1)), vec![0.0, 1.0]);
        let w = render_weights(t2(&[2.0], [1, 1], &d), t2(&[1.0], [1, 1], &d));
        assert!((vec1(w.opacity)[0] - (1.0 - (-2.0f32).exp())).abs() < 1e-6);
    }

    // ---- gradient checks: finite differences vs autodiff ----

    use crate::model::burn::gradcheck::{check, coefficients};

    const R: usize = 2;
    const S: usize = 4;
    const C: usize = 3;
    const SIGMA: [f32; R * S] = [0.3, 1.2, 0.05, 2.0, 0.8, 0.0, 1.5, 0.4];
    const DELTA: [f32; R * S] = [0.5, 0.3, 0.7, 0.2, 0.4, 0.6, 0.25, 0.5];

    fn on(v: &[f32], like: &Tensor<2>) -> Tensor<2> {
        Tensor::from_data(TensorData::new(v.to_vec(), [R, S]), &like.device())
    }

    #[test]
    fn gradient_of_weights_wrt_density_and_deltas() {
        let proj = coefficients(R * S, 1);
        let project = move |w: Tensor<2>| (w.clone() * on(&proj, &w)).sum();
        let p2 = project.clone();
        check(
            "weights/sigma",
            &SIGMA,
            [R, S],
            |sig| {
                let d = on(&DELTA, &sig);
                p2(render_weights(sig, d).weights)
            },
            1e-2,
            2e-2,
        );
        check(
            "weights/delta",
            &DELTA,
            [R, S],
            |d| {
                let sig = on(&SIGMA, &d);
                project(render_weights(sig, d).weights)
            },
            1e-2,
            2e-2,
        );
    }

    #[test]
    fn gradient_of_colour_and_depth() {
        let colours = coefficients(R * S * 3, 2)
            .iter()
            .map(|v| 0.5 + 0.4 * v)
            .collect::<Vec<_>>();
        let proj = coefficients(R * 3, 3);
        let rgb_of = |sig: Tensor<2>, c: Tensor<3>| {
            let d = on(&DELTA, &sig);
            let out = render_rgb(&render_weights(sig, d), c);
            let p = Tensor::<2>::from_data(TensorData::new(proj.clone(), [R, 3]), &out.device());
            (out * p).sum()
        };
        check(
            "rgb/sigma",
            &SIGMA,
            [R, S],
            |sig| {
                let c =
                    Tensor::from_data(TensorData::new(colours.clone(), [R, S, 3]), &sig.device());
                rgb_of(sig, c)
            },
            1e-2,
            2e-2,
        );
        check(
            "rgb/colour",
            &colours,
            [R, S, 3],
            |c| {
                let sig = Tensor::from_data(TensorData::new(SIGMA.to_vec(), [R, S]), &c.device());
                rgb_of(sig, c)
            },
            1e-2,
            2e-2,
        );
        let t: Vec<f32> = (0..R * S).map(|i| 1.0 + 0.5 * (i % S) as f32).collect();
        check(
            "depth/sigma",
            &SIGMA,
            [R, S],
            |sig| {
                let d = on(&DELTA, &sig);
                let tt = on(&t, &sig);
                let coef = Tensor::<1>::from_floats([0.7, -1.3], &sig.device());
                let depth = render_depth(&render_weights(sig, d), tt);
                (depth * coef).sum()
            },
            1e-2,
            2e-2,
        );
    }

    #[test]
    fn gradient_of_semantics_with_the_sky_remainder() {
        // probabilities: a softmax of fixed logits, so rows are valid distributions
        let probs: Vec<f32> = coefficients(R * S * C, 4)
            .chunks(C)
            .flat_map(|l| {
                let e: Vec<f32> = l.iter().map(|v| (2.0 * v).exp()).collect();
                let z: f32 = e.iter().sum();
                e.into_iter().map(move |v| v / z)
            })
            .collect();
        let proj = coefficients(R * C, 5);
        let sem = |sig: Tensor<2>, p: Tensor<3>| {
            let d = on(&DELTA, &sig);
            let out = render_semantics(&render_weights(sig, d), p, C - 1);
            let pr = Tensor::<2>::from_data(TensorData::new(proj.clone(), [R, C]), &out.device());
            (out * pr).sum()
        };
        check(
            "semantics/sigma",
            &SIGMA,
            [R, S],
            |sig| {
                let p = Tensor::from_data(TensorData::new(probs.clone(), [R, S, C]), &sig.device());
                sem(sig, p)
            },
            1e-2,
            2e-2,
        );
        check(
            "semantics/probs",
            &probs,
            [R, S, C],
            |p| {
                let sig = Tensor::from_data(TensorData::new(SIGMA.to_vec(), [R, S]), &p.device());
                sem(sig, p)
            },
            1e-2,
            2e-2,
        );
    }
}
