//! Why the scenes could not be handed out or followed.

use std::path::PathBuf;

use crate::{
    config::ConfigError,
    error::{Classify, IoError},
    runner::RunError,
    store::StoreError,
};

#[derive(Debug, thiserror::Error)]
pub enum ExecutorError {
    /// `--until` / `--only` with an executor that hands out whole scenes.
    #[error("--until and --only select stages inside a scene: use them with `--executor local` and --jobs 1 (or with --scene NAME)")]
    StageSelection,
    #[error(
        "--executor slurm runs the scenes of a scene matrix, and {} declares no `scenes:`",
        .0.display()
    )]
    NoScenes(PathBuf),
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Run(#[from] RunError),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    Io(#[from] IoError),
    /// A Slurm command ran and failed.
    #[error("`{command}` failed ({status}): {stderr}")]
    Slurm {
        command: String,
        status: String,
        stderr: String,
    },
    #[error("sbatch printed no job id: {0:?}")]
    NoJobId(String),
    #[error("squeue keeps failing; the tasks may still run")]
    SqueueFailing(#[source] Box<ExecutorError>),
}

impl Classify for ExecutorError {
    fn is_usage(&self) -> bool {
        match self {
            ExecutorError::StageSelection | ExecutorError::NoScenes(_) => true,
            ExecutorError::Config(e) => e.is_usage(),
            ExecutorError::Run(e) => e.is_usage(),
            ExecutorError::Store(_)
            | ExecutorError::Io(_)
            | ExecutorError::Slurm { .. }
            | ExecutorError::NoJobId(_)
            | ExecutorError::SqueueFailing(_) => false,
        }
    }
}
