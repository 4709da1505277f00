//! The fused CPU path of the grid field: forward, volume rendering, the five losses, their
//! backward pass and Adam in plain Rust over flat buffers, with a small-matrix product
//! ([`mlp::gemm`]) for the dense layers and rayon across ray partitions.
//!
//! Why: burn's CPU backends keep about one core busy and spend most of a step on small-tensor
//! overhead; this engine computes the same function (the parameter layout and initialisation of
//! [`crate::model::params`], the losses of [`crate::model::burn::loss`]) several times faster.
//! The burn engine stays the reference definition, and the tests hold this engine's losses,
//! gradients, training steps and rendered maps to it.
//!
//! Files: [`FusedField`] (layout, inference) here; the per-partition buffers and the field's
//! forward pass in `work`; rendering, losses and the backward pass of one step in `step`; the
//! trainer (partitions, gradient reduction, clipping, Adam) in `train`; dense layers in [`mlp`];
//! the same kernels compiled for AVX2 and chosen at run time in `simd`.
//!
//! Determinism: rays are split into a fixed number of partitions ([`PARTITIONS`], independent
//! of the thread count); each partition accumulates its own gradients and they are summed in
//! partition order, so a seed gives the same bytes on any machine with the same float
//! semantics.

// The kernels index several parallel per-sample arrays with one index; iterator chains over
// four zipped slices read worse than the formulas they implement.
#![allow(clippy::needless_range_loop)]

mod field;
mod gemm;
mod infer;
pub mod mlp;
mod simd;
mod step;
#[cfg(test)]
mod tests;
mod train;
mod work;

pub use field::{supports, FusedField, PARTITIONS};
pub(crate) use simd::dispatch;
pub use simd::{avx2, baseline_only};
pub use train::{FusedTrainer, EXPOSURE};
