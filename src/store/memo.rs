//! Hash memos, so a no-op run does not re-hash gigabytes: `state/verified.json` holds the
//! (size, mtime, inode, ctime) of every entry file hashed since it last changed, `state/files.json`
//! the digests of files outside the cache that stages read. Both are best effort: losing one
//! only costs a re-hash.

use std::{
    collections::BTreeMap,
    fs::{self, Metadata},
    os::unix::fs::MetadataExt,
    path::{Path, PathBuf},
};

use super::{
    error::StoreError,
    files::{hash_bytes, write_atomic},
    layout::Store,
};
use crate::error::IoContext;

/// (size, mtime in ns, inode, ctime in ns): a file is re-hashed when any of them changed. The
/// ctime catches a write whose mtime was put back (`touch -d`, `cp -p` over it): no user call
/// can set it.
type Stamp = (u64, i64, u64, i64);

pub(super) fn stamp(meta: &Metadata) -> Stamp {
    (
        meta.len(),
        meta.mtime() * 1_000_000_000 + meta.mtime_nsec(),
        meta.ino(),
        meta.ctime() * 1_000_000_000 + meta.ctime_nsec(),
    )
}

fn read_json<T: serde::de::DeserializeOwned + Default>(path: &Path) -> T {
    fs::read(path)
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok())
        .unwrap_or_default()
}

/// `state/verified.json`: `KEY/FILE` -> the stamp of the file when it last verified.
pub(super) struct Verified {
    path: PathBuf,
    map: BTreeMap<String, Stamp>,
    changed: bool,
}

impl Verified {
    pub fn load(store: &Store) -> Verified {
        let path = store.dir("state").join("verified.json");
        Verified {
            map: read_json(&path),
            path,
            changed: false,
        }
    }

    /// Whether file `name` of entry `key` verified with this stamp.
    pub fn holds(&self, key: &str, name: &str, stamp: &Stamp) -> bool {
        self.map.get(&format!("{key}/{name}")) == Some(stamp)
    }

    pub fn record(&mut self, key: &str, name: &str, stamp: Stamp) {
        self.map.insert(format!("{key}/{name}"), stamp);
        self.changed = true;
    }

    /// Forgets one file that failed verification, at once.
    pub fn forget_file(&mut self, key: &str, name: &str) {
        self.map.remove(&format!("{key}/{name}"));
        self.save();
    }

    /// Forgets every file of an entry moved aside, at once.
    pub fn forget_entry(&mut self, key: &str) {
        self.map.retain(|k, _| !k.starts_with(key));
        self.save();
    }

    pub fn save_if_changed(&self) {
        if self.changed {
            self.save();
        }
    }

    fn save(&self) {
        // Best effort: losing the memo only costs a re-hash.
        let _ = write_atomic(
            &self.path,
            &serde_json::to_vec(&self.map).unwrap_or_default(),
        );
    }
}

/// `path` itself if it is not a directory, else every file below it, sorted.
impl Store {
    /// blake3 over the contents of the files `paths` (in order; a missing one enters as
    /// "missing" so the stage itself reports it; the caller has checked they are regular files).
    /// File hashes are memoised by path, size, mtime and inode in `state/files.json`.
    pub fn files_digest(&self, paths: &[PathBuf]) -> Result<String, StoreError> {
        type FileMemo = BTreeMap<String, (Stamp, String)>;
        let memo_path = self.dir("state").join("files.json");
        let mut memo: FileMemo = read_json(&memo_path);
        let mut changed = false;
        let mut h = blake3::Hasher::new();
        for f in paths {
            let name = f.to_string_lossy().into_owned();
            h.update(name.as_bytes());
            h.update(&[0]);
            let digest = match fs::metadata(f) {
                Err(_) => "missing".to_string(),
                Ok(meta) => {
                    let stamp = stamp(&meta);
                    match memo.get(&name) {
                        Some((s, d)) if *s == stamp => d.clone(),
                        _ => {
                            let bytes = fs::read(f)
                                .io_context(|| format!("reading input file {}", f.display()))?;
                            let d = hash_bytes(&bytes);
                            memo.insert(name.clone(), (stamp, d.clone()));
                            changed = true;
                            d
                        }
                    }
                }
            };
            h.update(digest.as_bytes());
            h.update(b"\n");
        }
        if changed && fs::create_dir_all(self.dir("state")).is_ok() {
            // Best effort, like the verified-files memo.
            let _ = write_atomic(&memo_path, &serde_json::to_vec(&memo).unwrap_or_default());
        }
        Ok(h.finalize().to_hex().to_string())
    }
}
