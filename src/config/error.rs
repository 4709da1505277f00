//! A configuration error: the file, where in it (or which command-line argument), the stage and
//! the key it concerns, and the problem. Always bad usage (exit code 2).

use std::{fmt, path::PathBuf};

use crate::error::Classify;

/// A place in the pipeline file (1-based line and column), or a command-line override.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Loc {
    File { line: usize, col: usize },
    CommandLine(String),
    Unknown,
}

/// A configuration error: exit code 2.
#[derive(Debug, Clone)]
pub struct ConfigError {
    pub file: PathBuf,
    pub loc: Loc,
    pub stage: Option<String>,
    pub key: Option<String>,
    pub message: String,
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file.display())?;
        match &self.loc {
            Loc::File { line, col } => write!(f, ":{line}:{col}")?,
            Loc::CommandLine(arg) => write!(f, " (command line `{arg}`)")?,
            Loc::Unknown => {}
        }
        write!(f, ": ")?;
        if let Some(s) = &self.stage {
            write!(f, "stage `{s}`: ")?;
        }
        if let Some(k) = &self.key {
            write!(f, "`{k}`: ")?;
        }
        write!(f, "{}", self.message)
    }
}

impl std::error::Error for ConfigError {}

impl Classify for ConfigError {
    fn is_usage(&self) -> bool {
        true
    }
}
