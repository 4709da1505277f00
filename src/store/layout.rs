//! The cache directory and where each of its parts lies (see the module documentation of
//! [`crate::store`]).

use std::{
    fs,
    path::{Path, PathBuf},
};

use super::error::StoreError;
use crate::error::IoContext;

/// A cache directory. Its operations live beside what they work on: entries (`entry`), run
/// records (`records`), the hash memo (`memo`) and locks (`locks`).
pub struct Store {
    pub(super) root: PathBuf,
}

impl Store {
    /// Opens (creating if needed) the cache at `root`.
    pub fn open(root: &Path) -> Result<Store, StoreError> {
        for d in ["objects", "tmp", "trash", "runs", "state", "locks"] {
            let p = root.join(d);
            // Something else by that name: say so, not "File exists".
            if let Ok(m) = fs::metadata(&p) {
                if !m.is_dir() {
                    return Err(std::io::Error::other(format!(
                        "{} is a file, not a directory: this is not a cache (move the file, or \
                         give another --cache)",
                        p.display()
                    )))
                    .io_context(|| format!("opening the cache at {}", root.display()))
                    .map_err(StoreError::from);
                }
            }
            fs::create_dir_all(&p).io_context(|| {
                format!(
                    "cannot create cache directory {} (is it writable?)",
                    p.display()
                )
            })?;
        }
        Ok(Store {
            root: root.to_path_buf(),
        })
    }

    /// Opens an existing cache read-only (no directories are created).
    pub fn open_existing(root: &Path) -> Store {
        Store {
            root: root.to_path_buf(),
        }
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn entry_dir(&self, key: &str) -> PathBuf {
        self.root.join("objects").join(key)
    }

    pub(super) fn dir(&self, part: &str) -> PathBuf {
        self.root.join(part)
    }
}
