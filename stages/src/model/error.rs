//! Why the model could not be built, trained or loaded.

use super::loss::LossTerm;
use crate::stage::StageError;

/// A model that cannot be built as asked, or weights that do not fit it.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ModelError {
    /// A parameter is out of range (the message names it).
    #[error("{0}")]
    Param(String),
    /// No engine of that name is compiled into this build.
    #[error("`backend`: `{name}` is not compiled in (available: {available})")]
    UnknownEngine { name: String, available: String },
    /// The engine cannot run an option of the field.
    #[error("`backend: {engine}` {what}")]
    Unsupported { engine: &'static str, what: String },
    /// Weight rows that do not fit the field spec.
    #[error("{0}")]
    Weights(String),
    /// A GPU backend has no device here.
    #[error(
        "`backend: {engine}` has no device here: {why} (install its driver, or use \
         `backend: fused` on the CPU)"
    )]
    NoDevice { engine: &'static str, why: String },
}

impl From<ModelError> for StageError {
    fn from(e: ModelError) -> Self {
        match e {
            ModelError::Weights(m) => StageError::Input(format!("table `weights`: {m}")),
            e @ ModelError::NoDevice { .. } => StageError::Failed(e.to_string()),
            other => StageError::Params(other.to_string()),
        }
    }
}

/// Why training stopped.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TrainError {
    /// The config or field spec is invalid.
    #[error("invalid train config: {0}")]
    Config(String),
    /// A batch has wrong lengths or values.
    #[error("bad ray batch: {0}")]
    Batch(String),
    /// A loss term evaluated to NaN or infinity.
    #[error(
        "iteration {iteration}: loss `{term}` is {value}; check the inputs, lower lr or enable \
         grad_clip_norm"
    )]
    NonFiniteLoss {
        iteration: usize,
        term: LossTerm,
        value: f32,
    },
    /// A gradient has NaN or infinite entries (`term` is `total` when no single term does).
    #[error(
        "iteration {iteration}: the gradient of loss `{term}` is not finite in parameter \
         `{param}`; lower lr or enable grad_clip_norm"
    )]
    NonFiniteGradient {
        iteration: usize,
        term: String,
        param: String,
    },
}

impl From<ModelError> for TrainError {
    fn from(e: ModelError) -> Self {
        TrainError::Config(e.to_string())
    }
}

impl From<TrainError> for StageError {
    fn from(e: TrainError) -> Self {
        match e {
            TrainError::Config(m) => StageError::Params(m),
            TrainError::Batch(m) => StageError::Input(m),
            other => StageError::Failed(other.to_string()),
        }
    }
}
