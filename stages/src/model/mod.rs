//! THE model, once: the radiance field with dual semantic fields, its losses and volume
//! rendering, behind one engine seam.
//!
//! - [`config`]: the field and the losses as users set them, [`FieldSpec`], and what a trainer is
//!   given ([`TrainConfig`]: field, [`Losses`], [`optimiser::Optimiser`]).
//! - [`params`]: the parameter layout and seeded initialisation, as named rows every engine
//!   reads and writes; [`weights`]: those rows and the model description as tables.
//! - [`engine`]: [`Engine`] (`fused` or a burn backend), the [`Trainer`] and [`Field`] seams
//!   ([`train`], [`field`]) and the one training loop [`fit`].
//! - [`burn`]: the reference engine (burn modules, autodiff; the losses and tensor rendering
//!   are defined there); [`fused`]: hand-written CPU kernels of the same function.
//! - [`encoding`], [`batch`], [`composite`]: host parts shared by the engines: the
//!   parameter-free encodings, the batch layout, and per-ray compositing for inference.
//! - [`loss`], [`error`]: loss terms by name, per-step reports and errors.
//!
//! Data walk: sampling plan -> [`RayBatch`] -> `Trainer::step` (xN) -> weights rows -> the
//! `weights` table -> `Engine::field` -> `Field::evaluate` -> [`composite::composite_ray`] ->
//! label maps. No step converts one engine's weights into another's form: rows are the form.

pub mod batch;
pub mod burn;
pub mod composite;
pub mod config;
pub mod encoding;
pub mod engine;
pub mod error;
pub mod field;
pub mod fused;
pub mod loss;
pub mod maps;
pub mod optimiser;
pub mod params;
pub mod train;
pub mod weights;

#[cfg(test)]
mod parity;
#[cfg(test)]
pub(crate) mod testing;

pub use batch::{batch_indices, selection_sample, BatchOrder, RayBatch, RaySamples, RayTargets};
pub use config::{
    EncodingKind, FieldConfig, FieldSpec, GridConfig, Losses, SkyColourInput, TrainConfig,
};
pub use engine::{Engine, EngineChoice};
pub use error::{ModelError, TrainError};
pub use field::{Field, FieldSamples, Heads};
pub use loss::{LossTerm, LossTerms, PROB_EPS};
pub use optimiser::Optimiser;
pub use params::NamedWeight;
pub use train::{fit, Gradients, Schedule, Trainer};
pub use weights::ModelInfo;
