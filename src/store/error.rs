//! What can go wrong with the cache: a file operation (named, with the OS error), Parquet
//! encoding or decoding, an entry that does not verify, a lock another process holds. Never
//! bad usage: exit code 1.

use std::path::PathBuf;

use super::codec::CodecError;
use crate::error::{Classify, IoError};

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error(transparent)]
    Io(#[from] IoError),
    /// Encoding or decoding a table: what was being done (naming the table or file).
    #[error("{what}")]
    Codec {
        what: String,
        #[source]
        source: CodecError,
    },
    /// A JSON file of the cache could not be written.
    #[error("encoding {what}")]
    Json {
        what: String,
        #[source]
        source: serde_json::Error,
    },
    /// An entry's bytes are not what its manifest says.
    #[error("{0}")]
    Corrupt(String),
    /// Another process holds the cache (`entry`: the entry it computes) and `--no-wait` was
    /// given.
    #[error(
        "the cache {} is locked by {holder}{}; retry later or drop --no-wait",
        .cache.display(),
        .entry.as_ref().map_or(String::new(), |k| format!(" (another `pipe run` computes entry {k})"))
    )]
    Locked {
        cache: PathBuf,
        holder: String,
        entry: Option<String>,
    },
    /// flock failed for another reason than the lock being held.
    #[error("locking {}", .path.display())]
    Flock {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

impl Classify for StoreError {
    fn is_usage(&self) -> bool {
        false
    }
}
