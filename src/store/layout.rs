//! The cache directory and where each of its parts lies (see the module documentation of
//! [`crate::store`]).

use std::{
    fs,
    path::{Path, PathBuf},
};

use super::{error::StoreError, files::refused};
use crate::error::IoContext;

/// A cache directory. Its operations live beside what they work on: entries (`entry`), run
/// records (`records`), the hash memo (`memo`) and locks (`locks`).
pub struct Store {
    pub(super) root: PathBuf,
    /// Why nothing can be written here (a read-only mount, a published cache without write
    /// permission): cached entries are still read, nothing is computed.
    read_only: Option<String>,
}

impl Store {
    /// Opens (creating if needed) the cache at `root`. A cache that exists but cannot be
    /// written opens read-only (see [`Store::read_only`]).
    pub fn open(root: &Path) -> Result<Store, StoreError> {
        let mut read_only = None;
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
            match fs::create_dir_all(&p) {
                Err(e) if refused(&e) && root.join("objects").is_dir() => {
                    read_only.get_or_insert(format!("creating {}: {e}", p.display()));
                }
                made => made.io_context(|| {
                    format!(
                        "cannot create cache directory {} (is it writable?)",
                        p.display()
                    )
                })?,
            }
        }
        if read_only.is_none() {
            read_only = write_probe(&root.join("tmp"));
        }
        Ok(Store {
            root: root.to_path_buf(),
            read_only,
        })
    }

    /// Opens an existing cache read-only (no directories are created).
    pub fn open_existing(root: &Path) -> Store {
        Store {
            root: root.to_path_buf(),
            read_only: None,
        }
    }

    /// Why this cache cannot be written (the path and the OS error), or `None`.
    pub fn read_only(&self) -> Option<&str> {
        self.read_only.as_deref()
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

/// Tries to create (and removes) an empty file in `dir`: why writing is refused, or `None`.
fn write_probe(dir: &Path) -> Option<String> {
    let probe = dir.join(format!(".{}", super::files::owned_name("probe")));
    match fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
    {
        Ok(_) => {
            let _ = fs::remove_file(&probe);
            None
        }
        Err(e) if refused(&e) => Some(format!("creating a file in {}: {e}", dir.display())),
        // Anything else (a full disk) shows where the run writes, with its own message.
        Err(_) => None,
    }
}
