//! What every error type of the library shares: how the command line classifies it (bad usage
//! or configuration, exit code 2, against a failure while working, exit code 1), a file error
//! that names what was being done, and the one-line rendering of an error and its causes.
//!
//! The convention: an error's `Display` says its own layer only ("writing .pipe/runs/a.json
//! (disk full?)"); what caused it is its `source()` ("File too large (os error 27)"); [`chain`]
//! joins the layers with `: `, as the user reads them.

use std::error::Error;

/// Whether an error is the user's to fix by changing the command line or a file (exit code 2)
/// or a failure while working (exit code 1). Every library error type says which it is by its
/// type or variant.
pub trait Classify {
    /// Bad usage or configuration (exit code 2).
    fn is_usage(&self) -> bool;

    /// The exit code of a command that ends with this error.
    fn exit_code(&self) -> i32 {
        if self.is_usage() {
            2
        } else {
            1
        }
    }
}

/// An error and every cause below it on one line: `outer: cause: root cause`.
pub fn chain(e: &(dyn Error + 'static)) -> String {
    let mut out = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        out.push_str(": ");
        out.push_str(&c.to_string());
        cause = c.source();
    }
    out
}

/// A file-system operation that failed: what was being done (naming the path) and the OS error.
#[derive(Debug, thiserror::Error)]
#[error("{what}")]
pub struct IoError {
    pub what: String,
    #[source]
    pub source: std::io::Error,
}

/// `.io_context(|| format!("writing {}", path.display()))` on an `io::Result`.
pub trait IoContext<T> {
    fn io_context(self, what: impl FnOnce() -> String) -> Result<T, IoError>;
}

impl<T> IoContext<T> for std::io::Result<T> {
    fn io_context(self, what: impl FnOnce() -> String) -> Result<T, IoError> {
        self.map_err(|source| IoError {
            what: what(),
            source,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_chain_joins_every_layer() {
        let e = std::io::Error::other("File too large (os error 27)");
        let e: Result<(), _> = Err(e);
        let e = e
            .io_context(|| "writing x (disk full?)".into())
            .unwrap_err();
        assert_eq!(
            chain(&e),
            "writing x (disk full?): File too large (os error 27)"
        );
    }
}
