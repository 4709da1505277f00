//! Test helper: central finite differences against autodiff for a scalar function of one
//! tensor, in f32 with tolerances that still catch a wrong formula.

use burn::tensor::{Tensor, TensorData};

use super::Backend;

/// Deterministic pseudo-random coefficients in [-1, 1], to project outputs onto a scalar.
pub fn coefficients(n: usize, seed: u64) -> Vec<f32> {
    let mut rng = crate::rng::SplitMix64::new(seed);
    (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect()
}

/// Checks the autodiff gradient of `f` at `x` against central differences with step `h`:
/// every component must satisfy `|ad - fd| <= rtol * |fd| + atol`, with `atol = rtol * 0.05 *
/// max|fd|` (so a gradient that is wrong by a few percent anywhere fails). Returns the
/// autodiff gradient.
pub fn check<const D: usize>(
    what: &str,
    x: &[f32],
    shape: [usize; D],
    f: impl Fn(Tensor<D>) -> Tensor<1>,
    h: f32,
    rtol: f32,
) -> Vec<f32> {
    let ad_device = Backend::REFERENCE.train_device();
    let plain = Backend::REFERENCE.device();
    let leaf =
        Tensor::<D>::from_data(TensorData::new(x.to_vec(), shape), &ad_device).require_grad();
    let y = f(leaf.clone());
    let grads = y.backward();
    let ad = leaf
        .grad(&grads)
        .expect("gradient of the leaf")
        .into_data()
        .try_to_vec::<f32>()
        .unwrap();
    let eval = |v: Vec<f32>| -> f64 {
        f(Tensor::from_data(TensorData::new(v, shape), &plain))
            .into_data()
            .try_to_vec::<f32>()
            .unwrap()[0] as f64
    };
    let fd: Vec<f32> = (0..x.len())
        .map(|i| {
            let mut p = x.to_vec();
            let mut m = x.to_vec();
            p[i] += h;
            m[i] -= h;
            ((eval(p) - eval(m)) / (2.0 * h as f64)) as f32
        })
        .collect();
    let scale = fd.iter().fold(0f32, |a, v| a.max(v.abs()));
    assert!(
        scale > 0.0,
        "{what}: the gradient is zero everywhere, the check is vacuous"
    );
    let atol = rtol * 0.05 * scale;
    for i in 0..x.len() {
        assert!(
            (ad[i] - fd[i]).abs() <= rtol * fd[i].abs() + atol,
            "{what}: component {i}: autodiff {} vs finite differences {}\nad {ad:?}\nfd {fd:?}",
            ad[i],
            fd[i]
        );
    }
    ad
}
