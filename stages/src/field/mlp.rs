//! Small fully connected networks (ReLU between layers, linear output) and the seeded random
//! generator that initialises every parameter of the field.
//!
//! Parameters are initialised on the host from [`SplitMix64`] rather than with the backend's
//! random ops, so a seed gives the same initial weights on every backend (flex, ndarray, GPU).

use burn::module::{Module, Param};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor, TensorData};

/// SplitMix64: tiny, fast, seedable; good enough for initialisation and ray shuffling.
#[derive(Debug, Clone)]
pub struct SplitMix64 {
    state: u64,
}

impl SplitMix64 {
    pub fn new(seed: u64) -> Self {
        Self { state: seed }
    }

    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    pub fn unit(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform in `[lo, hi)`.
    pub fn uniform(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.unit()
    }

    /// Uniform integer in `0..n` (`n > 0`).
    pub fn below(&mut self, n: usize) -> usize {
        (((self.next_u64() >> 11) as u128 * n as u128) >> 53) as usize
    }
}

/// One affine layer `x W + b`.
#[derive(Module, Debug)]
pub struct Dense {
    /// `[inputs, outputs]`.
    pub weight: Param<Tensor<2>>,
    /// `[outputs]`.
    pub bias: Param<Tensor<1>>,
}

impl Dense {
    /// Kaiming-uniform weights (bound `sqrt(6 / inputs)`, suited to ReLU), zero bias.
    pub fn new(inputs: usize, outputs: usize, rng: &mut SplitMix64, device: &Device) -> Self {
        let bound = (6.0 / inputs as f32).sqrt();
        let w: Vec<f32> = (0..inputs * outputs)
            .map(|_| rng.uniform(-bound, bound))
            .collect();
        Self {
            weight: Param::from_tensor(Tensor::from_data(
                TensorData::new(w, [inputs, outputs]),
                device,
            )),
            bias: Param::from_tensor(Tensor::zeros([outputs], device)),
        }
    }

    /// # Shapes
    /// `x`: `[rows, inputs]` -> `[rows, outputs]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        x.matmul(self.weight.val()) + self.bias.val().unsqueeze::<2>()
    }
}

/// `inputs -> hidden (x depth) -> outputs`, ReLU after every layer but the last.
#[derive(Module, Debug)]
pub struct Mlp {
    pub layers: Vec<Dense>,
}

impl Mlp {
    /// `hidden_layers` hidden layers of width `hidden` (0 gives a single affine layer).
    pub fn new(
        inputs: usize,
        hidden: usize,
        hidden_layers: usize,
        outputs: usize,
        rng: &mut SplitMix64,
        device: &Device,
    ) -> Self {
        let mut widths = vec![inputs];
        widths.extend(std::iter::repeat_n(hidden, hidden_layers));
        widths.push(outputs);
        let layers = widths
            .windows(2)
            .map(|w| Dense::new(w[0], w[1], rng, device))
            .collect();
        Self { layers }
    }

    /// # Shapes
    /// `x`: `[rows, inputs]` -> `[rows, outputs]`.
    pub fn forward(&self, mut x: Tensor<2>) -> Tensor<2> {
        let last = self.layers.len() - 1;
        for (i, layer) in self.layers.iter().enumerate() {
            x = layer.forward(x);
            if i < last {
                x = relu(x);
            }
        }
        x
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splitmix_is_reproducible_and_in_range() {
        let mut a = SplitMix64::new(7);
        let mut b = SplitMix64::new(7);
        for _ in 0..1000 {
            let x = a.unit();
            assert_eq!(x, b.unit());
            assert!((0.0..1.0).contains(&x));
            assert!(a.below(10) < 10);
            b.below(10);
        }
    }

    #[test]
    fn mlp_shapes() {
        let device = crate::field::Backend::default().device();
        let mlp = Mlp::new(5, 8, 2, 3, &mut SplitMix64::new(0), &device);
        assert_eq!(mlp.layers.len(), 3);
        let y = mlp.forward(Tensor::ones([4, 5], &device));
        assert_eq!(y.dims(), [4, 3]);
    }
}
