//! What a stage kind reports when it cannot produce its outputs ([`StageError`]), as the runner
//! classifies it.

/// Why a stage could not produce its outputs, as the runner classifies it: the library's own
/// errors (`ModelError`, `TrainError`, `GeometryError`, `MetricError`, ...) convert into one of
/// these at the kind boundary, keeping their message.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StageError {
    /// The parameters are invalid (the runner reports this as a configuration error, exit 2).
    #[error("invalid params: {0}")]
    Params(String),
    /// An input table or file is missing or malformed.
    #[error("bad input: {0}")]
    Input(String),
    /// The computation itself failed (e.g. training diverged).
    #[error("{0}")]
    Failed(String),
}

pub type Result<T, E = StageError> = std::result::Result<T, E>;

impl StageError {
    /// The message without the kind's prefix (for wrapping into another error).
    pub fn message(&self) -> &str {
        match self {
            StageError::Params(m) | StageError::Input(m) | StageError::Failed(m) => m,
        }
    }
}
