//! Why a bench could not run or report.

use std::path::PathBuf;

use crate::{
    config::ConfigError,
    error::{Classify, IoError},
    runner::RunError,
    store::{CodecError, StoreError},
};

#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// The suite, the base pipeline or the generated pipeline is invalid.
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Run(#[from] RunError),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    Io(#[from] IoError),
    #[error(
        "the bench pipeline failed (see above; {} is the pipeline it ran)",
        .0.display()
    )]
    PipelineFailed(PathBuf),
    #[error("stage `{stage}`: cache entry {key} is missing")]
    MissingEntry { stage: String, key: String },
    #[error("stage `{stage}`: cache entry corrupt: {why}")]
    CorruptEntry { stage: String, why: String },
    #[error("loading {stage}")]
    Load {
        stage: String,
        #[source]
        source: StoreError,
    },
    /// The scoring stage did not write its score table, or wrote it in another shape.
    #[error("stage `{stage}` wrote no `{table}` table")]
    NoScoreTable { stage: String, table: String },
    #[error("{table} table: no {ty} column `{column}`")]
    ScoreColumn {
        table: String,
        ty: &'static str,
        column: String,
    },
    /// Writing `results.parquet`.
    #[error("{what}")]
    Codec {
        what: String,
        #[source]
        source: CodecError,
    },
    #[error("{what}")]
    Json {
        what: String,
        #[source]
        source: serde_json::Error,
    },
    #[error("{what}")]
    Yaml {
        what: String,
        #[source]
        source: serde_yaml::Error,
    },
    #[error(transparent)]
    Arrow(#[from] arrow::error::ArrowError),
    /// Scoring what a bench produced (the edits suite reads the cached maps).
    #[error("scoring the results: {0}")]
    Results(String),
    #[error("drawing a plot: {0}")]
    Plot(String),
    #[error("encoding a plot as PNG")]
    Png(#[source] image::ImageError),
}

impl Classify for BenchError {
    fn is_usage(&self) -> bool {
        match self {
            BenchError::Config(e) => e.is_usage(),
            BenchError::Run(e) => e.is_usage(),
            _ => false,
        }
    }
}
