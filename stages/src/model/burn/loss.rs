//! The five losses of Panoptic NeRF, each a scalar tensor (`[1]`), each a pure function of
//! rendered quantities and targets so it can be gradient-checked on its own. This is their
//! definition; the fused engine's hand-written forward and backward are held to it by tests.
//!
//! Every cross-entropy is either `-log(p + PROB_EPS)` of a rendered probability (the two 2D
//! terms: S and S_hat are mixtures, not softmaxes, so no log-softmax applies) or uses
//! log-softmax of the logits (L_3D). Means are over the rays or points a mask keeps; an empty
//! mask gives 0 (denominators are at least 1).

use burn::tensor::activation::log_softmax;
use burn::tensor::Tensor;

/// Masked mean of `-log(probs[r, label_r] + eps)`: L_fixed2D (with S_hat and the mask of
/// rays that have a label) and L_learned2D (with S and that mask times u(r)); `eps` is the
/// training config's `label_eps` ([`crate::model::PROB_EPS`] for the paper's `-log p`).
///
/// # Shapes
/// `probs`, `label_one_hot`: `[rays, classes]`; `mask`: `[rays]` (0/1).
pub fn label_nll(
    probs: Tensor<2>,
    label_one_hot: Tensor<2>,
    mask: Tensor<1>,
    eps: f32,
) -> Tensor<1> {
    let rays = probs.dims()[0];
    let p = (probs * label_one_hot).sum_dim(1).reshape([rays]); // [rays]
    let nll = p.add_scalar(eps).log().neg();
    let count = mask.clone().sum().clamp_min(1.0);
    (nll * mask).sum() / count
}

/// L_3D: masked mean over points of `-sum_k fixed_k log_softmax(logits)_k`, the mask being
/// `unique_class * (density > sigma_threshold)` (density detached: the mask picks points, it is
/// not optimised).
///
/// # Shapes
/// `logits`, `fixed`: `[rays, samples, classes]`; `unique`, `density`: `[rays, samples]`.
pub fn point_ce(
    logits: Tensor<3>,
    fixed: Tensor<3>,
    unique: Tensor<2>,
    density: Tensor<2>,
    sigma_threshold: f32,
) -> Tensor<1> {
    let [rays, samples, _] = logits.dims();
    let log_p = log_softmax(logits, 2);
    let ce = (fixed * log_p).sum_dim(2).reshape([rays, samples]).neg(); // [rays, samples]
    let dense = density.detach().greater_elem(sigma_threshold).float();
    let mask = unique * dense;
    let count = mask.clone().sum().clamp_min(1.0);
    (ce * mask).sum() / count
}

/// L_rgb: mean over rays and channels of `(C - C*)^2`.
///
/// # Shapes
/// `rgb`, `target`: `[rays, 3]`.
pub fn rgb_mse(rgb: Tensor<2>, target: Tensor<2>) -> Tensor<1> {
    (rgb - target).square().mean()
}

/// L_depth: mean over rays with valid stereo depth of `(D - D*)^2`.
///
/// # Shapes
/// `depth`, `target`, `valid`: `[rays]`.
pub fn depth_mse(depth: Tensor<1>, target: Tensor<1>, valid: Tensor<1>) -> Tensor<1> {
    let count = valid.clone().sum().clamp_min(1.0);
    ((depth - target).square() * valid).sum() / count
}

/// L_sky: mean over rays of `unlabelled * g * (1 - S_hat(sky))`, with the gate `g = exp(-|C*
/// - C_sky|^2 / colour^2)` (0 for rays without sky samples) detached: it weighs rays, it is
/// not optimised. `C_sky` is the mean colour of the ray's sky samples.
///
/// # Shapes
/// `s_hat_sky`, `unlabelled`: `[rays]`; `rgb`: `[rays, samples, 3]`; `sky_mask`: `[rays,
/// samples, 1]` (0/1); `target`: `[rays, 3]`.
pub fn sky_prior(
    s_hat_sky: Tensor<1>,
    rgb: Tensor<3>,
    sky_mask: Tensor<3>,
    target: Tensor<2>,
    unlabelled: Tensor<1>,
    colour: f32,
) -> Tensor<1> {
    let rays = s_hat_sky.dims()[0];
    let count = sky_mask.clone().sum_dim(1).reshape([rays, 1]); // [rays, 1]
    let sky_rgb = (rgb * sky_mask).sum_dim(1).reshape([rays, 3]) / count.clone().clamp_min(1.0);
    let d2 = (sky_rgb - target).square().sum_dim(1).reshape([rays]);
    let has_sky = count.reshape([rays]).greater_elem(0.0).float();
    let gate = (d2.div_scalar(-colour * colour).exp() * has_sky * unlabelled).detach();
    (gate * s_hat_sky.neg().add_scalar(1.0)).sum() / rays.max(1) as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::burn::gradcheck::{check, coefficients};
    use crate::model::burn::volume::{render_depth, render_rgb, render_semantics, render_weights};
    use crate::model::burn::Backend;
    use crate::model::loss::LossTerm;
    use crate::model::loss::PROB_EPS;
    use burn::tensor::activation::softmax;
    use burn::tensor::{Device, TensorData};

    const R: usize = 3;
    const S: usize = 4;
    const C: usize = 3;

    fn t1(v: &[f32], d: &Device) -> Tensor<1> {
        Tensor::from_data(TensorData::new(v.to_vec(), [v.len()]), d)
    }
    fn t2(v: &[f32], shape: [usize; 2], d: &Device) -> Tensor<2> {
        Tensor::from_data(TensorData::new(v.to_vec(), shape), d)
    }
    fn t3(v: &[f32], shape: [usize; 3], d: &Device) -> Tensor<3> {
        Tensor::from_data(TensorData::new(v.to_vec(), shape), d)
    }
    fn scalar(t: Tensor<1>) -> f32 {
        t.into_data().try_to_vec::<f32>().unwrap()[0]
    }

    /// Labels [0, 2 (sky), 1]; the third ray is masked out of the learned term.
    const ONE_HOT: [f32; R * C] = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0];
    const SIGMA: [f32; R * S] = [0.3, 1.2, 0.05, 2.0, 0.8, 0.0, 1.5, 0.4, 0.1, 0.2, 0.9, 0.6];
    const DELTA: [f32; R * S] = [0.5, 0.3, 0.7, 0.2, 0.4, 0.6, 0.25, 0.5, 0.3, 0.3, 0.3, 0.3];
    /// Fixed distributions: one-hot, overlaps (uniform over two classes), sky samples.
    const FIXED: [f32; R * S * C] = [
        1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.0, 1.0, //
        0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, //
        0.5, 0.5, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0,
    ];

    #[test]
    fn label_nll_gradient_wrt_probabilities() {
        let probs: Vec<f32> = coefficients(R * C, 11)
            .iter()
            .map(|v| 0.4 + 0.3 * v)
            .collect();
        check(
            "label_nll/probs",
            &probs,
            [R, C],
            |p| {
                let d = p.device();
                label_nll(
                    p,
                    t2(&ONE_HOT, [R, C], &d),
                    t1(&[1.0, 1.0, 0.0], &d),
                    PROB_EPS,
                )
            },
            1e-3,
            1e-2,
        );
    }

    /// L_sky against density by finite differences (the gate is a constant), and its value by
    /// hand: ray 0 has one sky sample, ray 1 two, ray 2 none (gate 0).
    #[test]
    fn sky_prior_gradient_wrt_density_and_value() {
        let rgb: Vec<f32> = coefficients(R * S * 3, 21)
            .iter()
            .map(|v| 0.5 + 0.4 * v)
            .collect();
        let target = [0.5f32, 0.6, 0.7, 0.2, 0.4, 0.9, 0.1, 0.1, 0.1];
        let sky: Vec<f32> = FIXED.chunks(C).map(|row| row[C - 1]).collect();
        let prior = |sig: Tensor<2>| {
            let d = sig.device();
            let w = render_weights(sig, t2(&DELTA, [R, S], &d));
            let s_hat = render_semantics(&w, t3(&FIXED, [R, S, C], &d), C - 1);
            sky_prior(
                s_hat.narrow(1, C - 1, 1).reshape([R]),
                t3(&rgb, [R, S, 3], &d),
                t3(&sky, [R, S, 1], &d),
                t2(&target, [R, 3], &d),
                t1(&[1.0, 1.0, 1.0], &d),
                0.5,
            )
        };
        check("sky_prior/sigma", &SIGMA, [R, S], prior, 1e-2, 2e-2);

        // By hand: S_hat(sky) = weights of the sky samples + remainder.
        let d = Backend::REFERENCE.device();
        let got = scalar(prior(t2(&SIGMA, [R, S], &d)));
        let mut want = 0.0;
        for r in 0..R {
            let (mut log_t, mut s_sky, mut c_sky, mut n) = (0f32, 0f32, [0f32; 3], 0f32);
            for i in 0..S {
                let k = r * S + i;
                let w = log_t.exp() * (1.0 - (-SIGMA[k] * DELTA[k]).exp());
                log_t -= SIGMA[k] * DELTA[k];
                s_sky += w * sky[k];
                if sky[k] == 1.0 {
                    n += 1.0;
                    (0..3).for_each(|ch| c_sky[ch] += rgb[k * 3 + ch]);
                }
            }
            s_sky += log_t.exp();
            if n > 0.0 {
                let d2: f32 = (0..3)
                    .map(|ch| (c_sky[ch] / n - target[r * 3 + ch]).powi(2))
                    .sum();
                want += (-d2 / 0.25).exp() * (1.0 - s_sky) / R as f32;
            }
        }
        assert!(sky.iter().filter(|&&m| m == 1.0).count() == 3);
        assert!((got - want).abs() < 1e-5, "L_sky {got} vs by hand {want}");
    }

    #[test]
    fn fixed_2d_gradient_wrt_density() {
        check(
            "fixed_2d/sigma",
            &SIGMA,
            [R, S],
            |sig| {
                let d = sig.device();
                let w = render_weights(sig, t2(&DELTA, [R, S], &d));
                let s_hat = render_semantics(&w, t3(&FIXED, [R, S, C], &d), C - 1);
                label_nll(
                    s_hat,
                    t2(&ONE_HOT, [R, C], &d),
                    t1(&[1.0, 1.0, 1.0], &d),
                    PROB_EPS,
                )
            },
            1e-2,
            2e-2,
        );
    }

    #[test]
    fn learned_2d_gradient_wrt_logits_and_density() {
        let logits: Vec<f32> = coefficients(R * S * C, 12)
            .iter()
            .map(|v| 2.0 * v)
            .collect();
        let learned = |sig: Tensor<2>, l: Tensor<3>| {
            let d = sig.device();
            let w = render_weights(sig, t2(&DELTA, [R, S], &d));
            let s = render_semantics(&w, softmax(l, 2), C - 1);
            label_nll(
                s,
                t2(&ONE_HOT, [R, C], &d),
                t1(&[1.0, 1.0, 0.0], &d),
                PROB_EPS,
            )
        };
        check(
            "learned_2d/logits",
            &logits,
            [R, S, C],
            |l| learned(t2(&SIGMA, [R, S], &l.device()), l),
            1e-2,
            2e-2,
        );
        check(
            "learned_2d/sigma",
            &SIGMA,
            [R, S],
            |sig| {
                let l = t3(&logits, [R, S, C], &sig.device());
                learned(sig, l)
            },
            1e-2,
            2e-2,
        );
    }

    #[test]
    fn point_3d_gradient_wrt_logits() {
        let logits: Vec<f32> = coefficients(R * S * C, 13)
            .iter()
            .map(|v| 2.0 * v)
            .collect();
        let unique: Vec<f32> = FIXED
            .chunks(C)
            .map(|p| if p.contains(&1.0) { 1.0 } else { 0.0 })
            .collect();
        let ad = check(
            "point_3d/logits",
            &logits,
            [R, S, C],
            |l| {
                let d = l.device();
                point_ce(
                    l,
                    t3(&FIXED, [R, S, C], &d),
                    t2(&unique, [R, S], &d),
                    t2(&SIGMA, [R, S], &d),
                    0.1,
                )
            },
            1e-2,
            2e-2,
        );
        // masked points (overlap, or density <= 0.1) get no gradient
        for (i, (&u, &s)) in unique.iter().zip(&SIGMA).enumerate() {
            if u == 0.0 || s <= 0.1 {
                assert!(
                    ad[i * C..(i + 1) * C].iter().all(|&g| g == 0.0),
                    "point {i}"
                );
            }
        }
    }

    #[test]
    fn rgb_and_depth_gradients() {
        let rgb: Vec<f32> = coefficients(R * 3, 14)
            .iter()
            .map(|v| 0.5 + 0.3 * v)
            .collect();
        check(
            "rgb_mse/rgb",
            &rgb,
            [R, 3],
            |c| {
                let target = t2(
                    &[0.1, 0.9, 0.5, 0.2, 0.2, 0.2, 1.0, 0.0, 0.3],
                    [R, 3],
                    &c.device(),
                );
                rgb_mse(c, target)
            },
            1e-2,
            1e-2,
        );
        check(
            "rgb_mse/sigma",
            &SIGMA,
            [R, S],
            |sig| {
                let d = sig.device();
                let colours: Vec<f32> = (0..R * S * 3).map(|i| (i % 7) as f32 / 7.0).collect();
                let w = render_weights(sig, t2(&DELTA, [R, S], &d));
                let target = t2(&[0.1, 0.9, 0.5, 0.2, 0.2, 0.2, 1.0, 0.0, 0.3], [R, 3], &d);
                rgb_mse(render_rgb(&w, t3(&colours, [R, S, 3], &d)), target)
            },
            1e-2,
            2e-2,
        );
        check(
            "depth_mse/sigma",
            &SIGMA,
            [R, S],
            |sig| {
                let d = sig.device();
                let t: Vec<f32> = (0..R * S).map(|i| 1.0 + (i % S) as f32).collect();
                let w = render_weights(sig, t2(&DELTA, [R, S], &d));
                depth_mse(
                    render_depth(&w, t2(&t, [R, S], &d)),
                    t1(&[2.0, 1.5, 9.0], &d),
                    t1(&[1.0, 1.0, 0.0], &d),
                )
            },
            1e-2,
            2e-2,
        );
    }

    #[test]
    fn impossible_label_costs_minus_log_eps_and_stays_finite() {
        let d = Backend::REFERENCE.train_device();
        let p = t2(&[0.0, 1.0], [1, 2], &d).require_grad();
        let l = label_nll(
            p.clone(),
            t2(&[1.0, 0.0], [1, 2], &d),
            t1(&[1.0], &d),
            PROB_EPS,
        );
        let g = p
            .grad(&l.backward())
            .unwrap()
            .into_data()
            .try_to_vec::<f32>()
            .unwrap();
        let l = -(PROB_EPS.ln());
        assert!((l - 13.815_51).abs() < 1e-3);
        assert!(
            (g[0] + 1.0 / PROB_EPS).abs() / (1.0 / PROB_EPS) < 1e-3,
            "{g:?}"
        );
        assert_eq!(g[1], 0.0);
    }

    #[test]
    fn empty_masks_give_zero_not_nan() {
        let d = Backend::REFERENCE.device();
        let l = label_nll(
            t2(&[0.5, 0.5], [1, 2], &d),
            t2(&[1.0, 0.0], [1, 2], &d),
            t1(&[0.0], &d),
            PROB_EPS,
        );
        assert_eq!(scalar(l), 0.0);
        let l = depth_mse(t1(&[3.0], &d), t1(&[0.0], &d), t1(&[0.0], &d));
        assert_eq!(scalar(l), 0.0);
    }

    /// sigma up to 1e10, delta down to 1e-9, all-zero density, a sky-interval-only ray and
    /// logits of +-1e4: every loss and every gradient stays finite.
    #[test]
    fn extreme_inputs_give_finite_losses_and_gradients() {
        let d = Backend::REFERENCE.train_device();
        let (r, s, c) = (5, 4, 3);
        #[rustfmt::skip]
        let sigma = [
            1e10, 1e10, 1e10, 1e10, // opaque
            1.0, 5.0, 1e10, 0.5,    // tiny deltas
            0.0, 0.0, 0.0, 0.0,     // empty
            0.3, 0.3, 0.3, 0.3,     // sky interval only
            1e-3, 1e10, 0.0, 2.0,   // mixed
        ];
        #[rustfmt::skip]
        let delta = [
            1.0, 1.0, 1.0, 1.0,
            1e-9, 1e-9, 1e-9, 1e-9,
            1.0, 1.0, 1.0, 1.0,
            10.0, 10.0, 10.0, 10.0,
            1e-9, 1.0, 0.0, 1e3,
        ];
        let mut fixed = vec![0f32; r * s * c];
        for i in 0..r * s {
            let class = if (12..16).contains(&i) { 2 } else { i % 2 };
            fixed[i * c + class] = 1.0;
        }
        let logits: Vec<f32> = (0..r * s * c)
            .map(|i| {
                if i % 3 == 0 {
                    1e4
                } else if i % 3 == 1 {
                    -1e4
                } else {
                    0.0
                }
            })
            .collect();
        let sig = t2(&sigma, [r, s], &d).require_grad();
        let lg = t3(&logits, [r, s, c], &d).require_grad();
        let colours = t3(&vec![0.5; r * s * 3], [r, s, 3], &d).require_grad();
        let w = render_weights(sig.clone(), t2(&delta, [r, s], &d));
        let one_hot: Vec<f32> = (0..r)
            .flat_map(|i| {
                let mut v = vec![0f32; c];
                v[[1, 0, 0, 2, 1][i]] = 1.0;
                v
            })
            .collect();
        let mask = t1(&vec![1.0; r], &d);
        let t: Vec<f32> = (0..r * s).map(|i| 1.0 + i as f32).collect();
        let fixed_t = t3(&fixed, [r, s, c], &d);
        let terms = [
            label_nll(
                render_semantics(&w, fixed_t.clone(), c - 1),
                t2(&one_hot, [r, c], &d),
                mask.clone(),
                PROB_EPS,
            ),
            label_nll(
                render_semantics(&w, softmax(lg.clone(), 2), c - 1),
                t2(&one_hot, [r, c], &d),
                mask.clone(),
                PROB_EPS,
            ),
            point_ce(
                lg.clone(),
                fixed_t,
                t2(&vec![1.0; r * s], [r, s], &d),
                sig.clone(),
                0.1,
            ),
            rgb_mse(
                render_rgb(&w, colours.clone()),
                t2(&vec![0.2; r * 3], [r, 3], &d),
            ),
            depth_mse(
                render_depth(&w, t2(&t, [r, s], &d)),
                t1(&[1.0, 2.0, 3.0, 4.0, 5.0], &d),
                mask,
            ),
        ];
        let mut total = Tensor::<1>::zeros([1], &d);
        for (k, term) in terms.into_iter().enumerate() {
            let v = scalar(term.clone().detach());
            assert!(v.is_finite(), "loss {:?} = {v}", LossTerm::ALL[k]);
            total = total + term;
        }
        let grads = total.backward();
        for (name, g) in [
            ("sigma", sig.grad(&grads).unwrap().into_data()),
            ("logits", lg.grad(&grads).unwrap().into_data()),
            ("colours", colours.grad(&grads).unwrap().into_data()),
        ] {
            let g = g.try_to_vec::<f32>().unwrap();
            assert!(g.iter().all(|v| v.is_finite()), "{name} gradient: {g:?}");
        }
    }
}
