//! The burn engine: the field as burn modules on any burn backend (flex, ndarray, wgpu, cuda),
//! trained with autodiff and burn's Adam. It is the reference definition of the losses
//! ([`loss`]) and of volume rendering on tensors ([`volume`]); the other engines are held to it.
//!
//! burn 0.22 tensors carry their backend in a runtime `Device`, chosen in one place
//! ([`backend`]). The pipeline is `positions -> RadianceField::prepare (host) -> forward (burn)
//! -> render_weights -> render_*`.

pub mod backend;
pub mod field;
#[cfg(test)]
pub(crate) mod gradcheck;
mod infer;
pub mod loss;
pub mod step;
pub mod volume;
pub mod weights;

pub use backend::Backend;
pub use field::{FieldHead, RadianceField};
pub use step::{reference_gradients, Trainer};
