//! Why a run could not start or go on ([`RunError`]: bad selections are usage errors, the
//! rest failures), and why one stage failed ([`StageFailure`]: reported in the run's summary,
//! not returned).

use std::{collections::BTreeSet, path::PathBuf};

use crate::{config::ConfigError, error::Classify, store::StoreError};

#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The pipeline is invalid (a cycle).
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("--scene {scenes}: {} declares no scenes", .file.display())]
    NoScenes { scenes: String, file: PathBuf },
    #[error(
        "--scene {scene}: no scene named `{scene}` in {} (scenes: {})",
        .file.display(),
        .known.join(", ")
    )]
    NoSuchScene {
        scene: String,
        file: PathBuf,
        known: Vec<String>,
    },
    /// `flag` is `--until`, `--only` or `--force`.
    #[error("{flag} {name}: no stage named `{name}` in {}", .file.display())]
    NoSuchStage {
        flag: &'static str,
        name: String,
        file: PathBuf,
    },
    #[error("--until and --only cannot be combined")]
    UntilAndOnly,
    /// A stage outside the selection (`--only`, or the scenes before the dataset stages) is
    /// stale, so the selected stages cannot run.
    #[error("cannot run only the selected stages: {}", not_up_to_date(.only, .stage, .reason))]
    NotUpToDate {
        only: Option<String>,
        stage: String,
        reason: String,
    },
    /// The files outside the cache a stage reads could not be named.
    #[error("stage `{stage}`")]
    ExternalInputs {
        stage: String,
        #[source]
        source: stages::StageError,
    },
    /// A stage is stale and the cache cannot be written: only a fully cached run works on it.
    #[error(
        "stage `{stage}` would have to run ({reason}), but the cache at {} is read-only \
         ({why}): a run whose stages are all cached works on it; to compute, give a writable \
         cache (`--cache DIR`)",
        .cache.display()
    )]
    ReadOnly {
        cache: PathBuf,
        why: String,
        stage: String,
        reason: String,
    },
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("stage thread panicked: {0}")]
    Panicked(String),
    #[error("starting the async runtime")]
    Runtime(#[source] std::io::Error),
}

fn not_up_to_date(only: &Option<String>, stage: &str, reason: &str) -> String {
    match only {
        Some(o) => format!(
            "`{o}` needs stage `{stage}`, which is not up to date ({reason}); run `pipe run --until {o}` first"
        ),
        None => format!(
            "the dataset stages need stage `{stage}`, which is not up to date ({reason}); run its scene first"
        ),
    }
}

impl Classify for RunError {
    fn is_usage(&self) -> bool {
        match self {
            RunError::Config(_)
            | RunError::NoScenes { .. }
            | RunError::NoSuchScene { .. }
            | RunError::NoSuchStage { .. }
            | RunError::UntilAndOnly
            | RunError::NotUpToDate { .. } => true,
            RunError::ReadOnly { .. } => false,
            RunError::ExternalInputs { .. }
            | RunError::Store(_)
            | RunError::Panicked(_)
            | RunError::Runtime(_) => false,
        }
    }
}

/// Why one stage did not produce a verified entry.
#[derive(Debug, thiserror::Error)]
pub enum StageFailure {
    /// Its entry's lock could not be taken (`--no-wait`, or the cache is unwritable).
    #[error("stage `{stage}`")]
    Lock {
        stage: String,
        #[source]
        source: StoreError,
    },
    /// Reading its inputs or publishing its outputs.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// An input entry failed verification when read (bit rot the cheap check cannot see); it
    /// was moved to `trash/` (`moved`) and the run recomputes it.
    #[error("input `{stage}`: cache entry {key} is corrupt: {why}{}", .moved.as_ref().map_or(String::new(), |d| format!(" (moved to {})", d.display())))]
    InputCorrupt {
        stage: String,
        key: String,
        why: String,
        moved: Option<PathBuf>,
    },
    #[error("scene `{scene}` has no table `{table}`")]
    GatherMissing { scene: String, table: String },
    #[error("no scenes to gather table `{0}` from")]
    GatherEmpty(String),
    #[error(transparent)]
    Gather(#[from] arrow::error::ArrowError),
    /// The stage body returned an error.
    #[error("stage `{stage}` (kind `{kind}`) failed")]
    Body {
        stage: String,
        kind: String,
        #[source]
        source: stages::StageError,
    },
    #[error("stage `{stage}` (kind `{kind}`) wrote tables {written:?} but declares {declared:?}")]
    Outputs {
        stage: String,
        kind: String,
        written: BTreeSet<String>,
        declared: BTreeSet<String>,
    },
    /// An output table does not match its schema file.
    #[error("stage `{stage}` (kind `{kind}`): {message}")]
    Schema {
        stage: String,
        kind: String,
        message: String,
    },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn selections_are_usage_errors_and_failures_are_not() {
        assert_eq!(RunError::UntilAndOnly.exit_code(), 2);
        assert_eq!(RunError::Panicked("boom".into()).exit_code(), 1);
        let only = RunError::NotUpToDate {
            only: Some("d".into()),
            stage: "b".into(),
            reason: "never run".into(),
        };
        assert_eq!(
            only.to_string(),
            "cannot run only the selected stages: `d` needs stage `b`, which is not up to date (never run); run `pipe run --until d` first"
        );
        let dataset = RunError::NotUpToDate {
            only: None,
            stage: "b@s".into(),
            reason: "never run".into(),
        };
        assert_eq!(
            dataset.to_string(),
            "cannot run only the selected stages: the dataset stages need stage `b@s`, which is not up to date (never run); run its scene first"
        );
        assert!(dataset.is_usage());
    }
}
