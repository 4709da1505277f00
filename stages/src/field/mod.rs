//! The learned part of Panoptic NeRF as burn modules: position/direction encodings, the
//! radiance field with its learned semantic head, volume rendering, and weight export.
//!
//! One definition serves every burn backend: burn 0.22 tensors carry their backend in a runtime
//! `Device`, chosen in one place ([`backend`]). The pipeline is
//! `positions -> RadianceField::prepare (host) -> forward (burn) -> render_weights -> render_*`.

pub mod backend;
pub mod encoding;
#[cfg(test)]
pub(crate) mod gradcheck;
pub mod mlp;
pub mod radiance;
pub mod render;
pub mod weights;

pub use backend::Backend;
pub use encoding::{EncodingKind, GridConfig};
pub use radiance::{FieldConfig, FieldHead, FieldInput, FieldOutputs, FieldSpec, RadianceField};
pub use render::{render_depth, render_rgb, render_semantics, render_weights, RenderWeights};
pub use weights::NamedWeight;
