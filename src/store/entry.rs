//! Cache entries: `objects/<key>/` with one Parquet file per table and `manifest.json`.
//! Published atomically (written under `tmp/`, fsynced, renamed into `objects/`), verified on
//! every look-up (sizes always, hashes unless the file is unchanged since it last verified) and
//! on every read, moved to `trash/` when corrupt, removed by `gc`.

use std::{
    collections::{BTreeMap, BTreeSet},
    fs::{self, File},
    io::Write,
    path::{Path, PathBuf},
};

use arrow::record_batch::RecordBatch;
use serde::{Deserialize, Serialize};
use stages::{Table, TableSet, Tables};

use super::{
    codec::{HashingFile, StoredTable, TableEncoder},
    error::StoreError,
    files::{dir_size, fsync_dir, hash_file, owned_name, unix_now},
    layout::Store,
    memo::{stamp, Verified},
    pending::{FileInfo, PendingEntry},
};
use crate::{error::IoContext, fingerprint};

/// An input of a run: which stage fed the slot, the digest of what it wrote and, where known,
/// the key of that entry (what lets a later run find the inputs of this one).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct InputInfo {
    pub stage: String,
    pub digest: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub key: Option<String>,
}

/// `manifest.json` of a cache entry.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Manifest {
    pub key: String,
    pub kind: String,
    pub version: u32,
    /// The stage instance that first produced this entry (entries are shared by content).
    pub stage: String,
    pub params: serde_json::Value,
    pub inputs: BTreeMap<String, InputInfo>,
    /// File name -> size and blake3.
    pub files: BTreeMap<String, FileInfo>,
    /// Table name -> schema file name in data_schema/.
    pub schemas: BTreeMap<String, String>,
    /// blake3 over the files' digests: what downstream keys are computed from.
    pub output_digest: String,
    pub wall_s: f64,
    pub cpu_s: f64,
    pub peak_rss_bytes: u64,
    /// Unix seconds.
    pub started: f64,
    pub finished: f64,
    pub tool_version: String,
    /// The entry this one was updated from ([`stages::Stage::update`]); none when computed
    /// from scratch.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub parent: Option<String>,
    /// What that update computed again (`12 of 128 images`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub redone: Option<String>,
}

/// What a look-up of a key found.
pub enum Entry {
    Missing,
    Valid(Box<Manifest>),
    Corrupt(String),
}

fn files_digest(m: &Manifest) -> String {
    let digests = m
        .files
        .iter()
        .map(|(n, f)| (n.clone(), f.blake3.clone()))
        .collect();
    fingerprint::output_digest(&digests)
}

impl Store {
    fn read_manifest(&self, key: &str) -> Result<Manifest, String> {
        let path = self.entry_dir(key).join("manifest.json");
        let bytes = fs::read(&path).map_err(|e| format!("cannot read manifest.json: {e}"))?;
        let m: Manifest = serde_json::from_slice(&bytes)
            .map_err(|e| format!("manifest.json is malformed: {e}"))?;
        if m.key != key {
            return Err(format!(
                "manifest.json names key {} instead of {key}",
                m.key
            ));
        }
        if files_digest(&m) != m.output_digest {
            return Err("manifest.json output digest does not match its file list".into());
        }
        Ok(m)
    }

    /// Looks up `key`, verifying sizes always and hashes unless the file is unchanged since it
    /// was last hashed (`full` forces hashing).
    pub fn check(&self, key: &str, full: bool) -> Entry {
        let dir = self.entry_dir(key);
        if !dir.exists() {
            return Entry::Missing;
        }
        let m = match self.read_manifest(key) {
            Ok(m) => m,
            Err(e) => return Entry::Corrupt(e),
        };
        let mut memo = Verified::load(self);
        let mut extra: BTreeSet<String> = match fs::read_dir(&dir) {
            Ok(rd) => rd
                .filter_map(|e| e.ok())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect(),
            Err(e) => return Entry::Corrupt(format!("cannot list entry: {e}")),
        };
        extra.remove("manifest.json");
        for (name, info) in &m.files {
            extra.remove(name);
            let path = dir.join(name);
            let meta = match fs::metadata(&path) {
                Ok(meta) => meta,
                Err(_) => return Entry::Corrupt(format!("file {name} is missing")),
            };
            if meta.len() != info.size {
                return Entry::Corrupt(format!(
                    "file {name} has {} bytes, the manifest says {}",
                    meta.len(),
                    info.size
                ));
            }
            let stamp = stamp(&meta);
            if !full && memo.holds(key, name, &stamp) {
                continue;
            }
            let digest = match hash_file(&path) {
                Ok(d) => d,
                Err(e) => return Entry::Corrupt(format!("cannot read {name}: {e}")),
            };
            if digest != info.blake3 {
                memo.forget_file(key, name);
                return Entry::Corrupt(format!(
                    "file {name} does not match its blake3 in the manifest"
                ));
            }
            memo.record(key, name, stamp);
        }
        if let Some(x) = extra.into_iter().next() {
            return Entry::Corrupt(format!("unexpected file {x} in the entry"));
        }
        memo.save_if_changed();
        Entry::Valid(Box::new(m))
    }

    /// Moves a corrupt entry to `trash/` so it is kept for inspection but never used.
    pub fn quarantine(&self, key: &str) -> Result<PathBuf, StoreError> {
        let dest = self.dir("trash").join(format!(
            "{key}.{}.{}",
            std::process::id(),
            unix_now() as u64
        ));
        fs::rename(self.entry_dir(key), &dest)
            .io_context(|| format!("moving corrupt entry {key} to {}", dest.display()))?;
        Verified::load(self).forget_entry(key);
        Ok(dest)
    }

    /// An entry's tables, read on demand. Unless `trusted` (written or verified by this process
    /// moments ago), every file is hashed against the manifest first, in pieces.
    pub fn open_tables(&self, m: &Manifest, trusted: bool) -> Result<TableSet, StoreError> {
        self.open_some_tables(m, trusted, None)
    }

    /// [`Store::open_tables`] for the tables `only` names (all with `None`); the others are
    /// neither opened nor verified.
    pub fn open_some_tables(
        &self,
        m: &Manifest,
        trusted: bool,
        only: Option<&[&str]>,
    ) -> Result<TableSet, StoreError> {
        let dir = self.entry_dir(&m.key);
        let mut tables = TableSet::default();
        for (name, info) in &m.files {
            let table = name.strip_suffix(".parquet").unwrap_or(name);
            if only.is_some_and(|only| !only.contains(&table)) {
                continue;
            }
            let path = dir.join(name);
            if !trusted {
                let size = fs::metadata(&path)
                    .io_context(|| format!("reading {}", path.display()))?
                    .len();
                let digest =
                    hash_file(&path).io_context(|| format!("reading {}", path.display()))?;
                if size != info.size || digest != info.blake3 {
                    return Err(StoreError::Corrupt(format!(
                        "{} changed since it was verified (size or blake3 mismatch)",
                        path.display()
                    )));
                }
            }
            let stored = StoredTable::open(&path).map_err(|source| StoreError::Codec {
                what: format!("decoding {}", path.display()),
                source,
            })?;
            tables.insert(Table::stored(table, Box::new(stored)));
        }
        Ok(tables)
    }

    /// Reads an entry's tables whole, verifying every file against the manifest.
    pub fn load(&self, m: &Manifest) -> Result<Tables, StoreError> {
        self.open_tables(m, false)?
            .whole_tables()
            .map_err(|e| StoreError::Corrupt(e.to_string()))
    }

    /// A new entry for `key` being written under `tmp/`: its streamed tables go there as the
    /// stage produces them (see [`PendingEntry`]).
    pub fn begin(&self, key: &str) -> Result<PendingEntry, StoreError> {
        PendingEntry::create(self.dir("tmp").join(owned_name(key)))
    }

    /// Writes `tables` as a new entry and publishes it atomically. If another process
    /// published the same key meanwhile, its (verified) entry wins and ours is discarded.
    pub fn publish(&self, manifest: Manifest, tables: &Tables) -> Result<Manifest, StoreError> {
        let pending = self.begin(&manifest.key)?;
        self.publish_pending(pending, manifest, tables, false)
    }

    /// Publishes `pending` (its streamed tables) with `tables` as the entry of the manifest's
    /// key; `replacing` as [`Store::publish_replacing`]. The temporary directory is removed
    /// whatever happens.
    pub fn publish_pending(
        &self,
        pending: PendingEntry,
        mut manifest: Manifest,
        tables: &Tables,
        replacing: bool,
    ) -> Result<Manifest, StoreError> {
        let key = manifest.key.clone();
        let tmp = pending.dir().to_path_buf();
        let result = pending
            .finish()
            .and_then(|streamed| self.write_entry(&tmp, &mut manifest, tables, streamed))
            .and_then(|()| {
                if replacing {
                    let same = match self.check(&key, false) {
                        Entry::Valid(old) => old.output_digest == manifest.output_digest,
                        Entry::Missing | Entry::Corrupt(_) => false,
                    };
                    if !same && self.entry_dir(&key).exists() {
                        self.quarantine(&key)?;
                    }
                }
                self.rename_into_objects(&tmp, &key, &manifest)
            });
        if result.is_err() {
            let _ = fs::remove_dir_all(&tmp);
        }
        result
    }

    /// Publishes like [`Store::publish`], but a valid entry already under the key is moved to
    /// `trash/` first when its output differs (what `--force` asks: a re-run after a code change
    /// that forgot its VERSION bump must not leave the old bytes in place). The caller holds the
    /// key's lock, so no other writer races; a reader in between sees the entry missing and
    /// waits on the lock.
    pub fn publish_replacing(
        &self,
        manifest: Manifest,
        tables: &Tables,
    ) -> Result<Manifest, StoreError> {
        let pending = self.begin(&manifest.key)?;
        self.publish_pending(pending, manifest, tables, true)
    }

    /// Writes the tables and the manifest (completed with the files' sizes, hashes and output
    /// digest, the `streamed` tables' included) into directory `tmp`, fsynced.
    fn write_entry(
        &self,
        tmp: &Path,
        manifest: &mut Manifest,
        tables: &Tables,
        streamed: BTreeMap<String, FileInfo>,
    ) -> Result<(), StoreError> {
        fs::create_dir_all(tmp).io_context(|| format!("creating {}", tmp.display()))?;
        manifest.files.clear();
        manifest.schemas.clear();
        for (name, info) in streamed {
            if tables.contains_key(&name) {
                return Err(StoreError::Corrupt(format!(
                    "table `{name}` was both streamed and returned"
                )));
            }
            manifest.files.insert(format!("{name}.parquet"), info);
            manifest
                .schemas
                .insert(name.clone(), format!("data_schema/{name}.json"));
        }
        for (name, batch) in tables {
            let file = format!("{name}.parquet");
            let info = write_table(&tmp.join(&file), batch)?;
            manifest.files.insert(file, info);
            manifest
                .schemas
                .insert(name.clone(), format!("data_schema/{name}.json"));
        }
        manifest.output_digest = files_digest(manifest);
        let json = serde_json::to_vec_pretty(&*manifest).map_err(|source| StoreError::Json {
            what: "manifest.json".into(),
            source,
        })?;
        write_synced(&tmp.join("manifest.json"), &json)?;
        Ok(fsync_dir(tmp)?)
    }

    /// Publishes the complete entry in `tmp` as `objects/<key>`; the first writer wins.
    fn rename_into_objects(
        &self,
        tmp: &Path,
        key: &str,
        manifest: &Manifest,
    ) -> Result<Manifest, StoreError> {
        let dest = self.entry_dir(key);
        let objects = self.dir("objects");
        let mut renamed = fs::rename(tmp, &dest);
        if renamed.is_err() && !objects.is_dir() && tmp.is_dir() {
            // objects/ was removed while this run worked (a clean-up by hand): lay it out again.
            fs::create_dir_all(&objects)
                .io_context(|| format!("creating {}", objects.display()))?;
            renamed = fs::rename(tmp, &dest);
        }
        match renamed {
            Ok(()) => {
                fsync_dir(&self.dir("objects"))?;
                Ok(manifest.clone())
            }
            Err(_) if dest.exists() => {
                // First writer wins; ours is a duplicate.
                let _ = fs::remove_dir_all(tmp);
                match self.check(key, true) {
                    Entry::Valid(m) => Ok(*m),
                    _ => Err(StoreError::Corrupt(format!(
                        "entry {key} appeared concurrently but does not verify"
                    ))),
                }
            }
            Err(e) => Err(e)
                .io_context(|| format!("publishing {}", dest.display()))
                .map_err(StoreError::from),
        }
    }

    /// Keys of every entry in `objects/`.
    pub fn keys(&self) -> Vec<String> {
        let mut keys: Vec<String> = fs::read_dir(self.dir("objects"))
            .map(|rd| {
                rd.filter_map(|e| e.ok())
                    .map(|e| e.file_name().to_string_lossy().into_owned())
                    .collect()
            })
            .unwrap_or_default();
        keys.sort();
        keys
    }

    /// Removes every entry not in `keep` (with `dry_run`, none): each one's key and size.
    pub fn gc(
        &self,
        keep: &BTreeSet<String>,
        dry_run: bool,
    ) -> Result<Vec<(String, u64)>, StoreError> {
        let mut removed = Vec::new();
        for key in self.keys() {
            if keep.contains(&key) {
                continue;
            }
            let dir = self.entry_dir(&key);
            let bytes = dir_size(&dir);
            if !dry_run {
                // Rename first so a concurrent reader never sees a half-deleted entry.
                let doomed = self.dir("tmp").join(owned_name(&format!("gc.{key}")));
                fs::rename(&dir, &doomed).io_context(|| format!("removing {}", dir.display()))?;
                fs::remove_dir_all(&doomed)
                    .io_context(|| format!("removing {}", doomed.display()))?;
            }
            removed.push((key, bytes));
        }
        if !dry_run {
            let _ = fs::remove_dir_all(self.dir("trash"));
            let _ = fs::create_dir_all(self.dir("trash"));
        }
        Ok(removed)
    }

    /// The manifest of entry `key`, unverified (for listings), or `None`.
    pub fn manifest_of(&self, key: &str) -> Option<Manifest> {
        self.read_manifest(key).ok()
    }
}

/// Writes `batch` as the Parquet file `path`, synced to disk; its size and blake3.
fn write_table(path: &Path, batch: &RecordBatch) -> Result<FileInfo, StoreError> {
    let file = HashingFile::create(path).io_context(|| format!("creating {}", path.display()))?;
    let codec = |source| StoreError::Codec {
        what: format!("encoding {}", path.display()),
        source,
    };
    let mut enc = TableEncoder::new(file, batch.schema()).map_err(codec)?;
    enc.write_whole(batch).map_err(codec)?;
    let (size, blake3) = enc
        .finish()
        .map_err(codec)?
        .finish()
        .io_context(|| format!("writing {} (disk full?)", path.display()))?;
    Ok(FileInfo { size, blake3 })
}

/// Creates `path` with `bytes`, synced to disk.
fn write_synced(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    let mut f = File::create(path).io_context(|| format!("creating {}", path.display()))?;
    f.write_all(bytes)
        .and_then(|_| f.sync_all())
        .io_context(|| format!("writing {} (disk full?)", path.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use arrow::{array::Int64Array, datatypes::Schema, record_batch::RecordBatch};
    use std::sync::Arc;

    fn tables(v: i64) -> Tables {
        let schema = stages::schema::get("test_numbers").unwrap();
        let b =
            RecordBatch::try_new(schema, vec![Arc::new(Int64Array::from(vec![v, v + 1]))]).unwrap();
        Tables::from([("test_numbers".to_string(), b)])
    }

    fn manifest(key: &str) -> Manifest {
        Manifest {
            key: key.into(),
            kind: "test_source".into(),
            version: 1,
            stage: "a".into(),
            params: serde_json::json!({}),
            inputs: BTreeMap::new(),
            files: BTreeMap::new(),
            schemas: BTreeMap::new(),
            output_digest: String::new(),
            wall_s: 0.0,
            cpu_s: 0.0,
            peak_rss_bytes: 0,
            started: 0.0,
            finished: 0.0,
            tool_version: "test".into(),
            parent: None,
            redone: None,
        }
    }

    #[test]
    fn publish_then_load_round_trips_and_detects_corruption() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let m = store.publish(manifest("k1"), &tables(5)).unwrap();
        let Entry::Valid(m2) = store.check("k1", true) else {
            panic!("not valid")
        };
        assert_eq!(m2.output_digest, m.output_digest);
        let t = store.load(&m2).unwrap();
        assert_eq!(t["test_numbers"], tables(5)["test_numbers"]);
        assert_eq!(
            *t["test_numbers"].schema(),
            Schema::clone(&stages::schema::get("test_numbers").unwrap())
        );
        assert!(fs::read_dir(dir.path().join("tmp"))
            .unwrap()
            .next()
            .is_none());

        // Same content, same digest: the basis of early cutoff.
        let again = store.publish(manifest("k2"), &tables(5)).unwrap();
        assert_eq!(again.output_digest, m.output_digest);

        // Flip one byte in the middle of the parquet file.
        let f = dir.path().join("objects/k1/test_numbers.parquet");
        let mut bytes = fs::read(&f).unwrap();
        let mid = bytes.len() / 2;
        bytes[mid] ^= 0x40;
        fs::write(&f, &bytes).unwrap();
        match store.check("k1", false) {
            Entry::Corrupt(why) => assert!(why.contains("blake3"), "{why}"),
            _ => panic!("flipped byte not detected"),
        }
        store.quarantine("k1").unwrap();
        assert!(matches!(store.check("k1", false), Entry::Missing));
    }

    #[test]
    fn opening_some_tables_verifies_those_and_leaves_the_rest_unread() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let mut two = tables(5);
        two.insert("other".into(), tables(7)["test_numbers"].clone());
        let m = store.publish(manifest("k"), &two).unwrap();
        // Corrupt the table that is not asked for: opening the other one still works.
        let f = dir.path().join("objects/k/other.parquet");
        let mut bytes = fs::read(&f).unwrap();
        let mid = bytes.len() / 2;
        bytes[mid] ^= 0x40;
        fs::write(&f, &bytes).unwrap();
        let some = store
            .open_some_tables(&m, false, Some(&["test_numbers"]))
            .unwrap();
        assert!(some.contains("test_numbers") && !some.contains("other"));
        assert_eq!(
            *some.get("test_numbers").unwrap().whole().unwrap(),
            tables(5)["test_numbers"]
        );
        // Asked for, it is verified and refused.
        let err = store.open_some_tables(&m, false, Some(&["other"]));
        assert!(
            matches!(&err, Err(StoreError::Corrupt(w)) if w.contains("other.parquet")),
            "{:?}",
            err.err()
        );
        assert!(matches!(
            store.open_tables(&m, false),
            Err(StoreError::Corrupt(_))
        ));
    }

    #[test]
    fn a_forced_publish_replaces_different_bytes_and_a_plain_one_keeps_the_first() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let first = store.publish(manifest("k"), &tables(1)).unwrap();
        let kept = store.publish(manifest("k"), &tables(2)).unwrap();
        assert_eq!(kept.output_digest, first.output_digest, "first writer wins");
        let same = store.publish_replacing(manifest("k"), &tables(1)).unwrap();
        assert_eq!(same.output_digest, first.output_digest);
        assert!(fs::read_dir(dir.path().join("trash"))
            .unwrap()
            .next()
            .is_none());
        let new = store.publish_replacing(manifest("k"), &tables(2)).unwrap();
        assert_ne!(new.output_digest, first.output_digest);
        let Entry::Valid(m) = store.check("k", true) else {
            panic!("not valid")
        };
        assert_eq!(m.output_digest, new.output_digest);
        assert_eq!(
            store.load(&m).unwrap()["test_numbers"],
            tables(2)["test_numbers"]
        );
        assert_eq!(fs::read_dir(dir.path().join("trash")).unwrap().count(), 1);
        assert!(fs::read_dir(dir.path().join("tmp"))
            .unwrap()
            .next()
            .is_none());
    }

    #[test]
    fn truncation_and_deletion_are_detected() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        store.publish(manifest("k"), &tables(1)).unwrap();
        let f = dir.path().join("objects/k/test_numbers.parquet");
        let len = fs::metadata(&f).unwrap().len();
        fs::OpenOptions::new()
            .write(true)
            .open(&f)
            .unwrap()
            .set_len(len - 3)
            .unwrap();
        assert!(matches!(store.check("k", false), Entry::Corrupt(w) if w.contains("bytes")));
        fs::remove_file(&f).unwrap();
        assert!(matches!(store.check("k", false), Entry::Corrupt(w) if w.contains("missing")));
        fs::write(dir.path().join("objects/k/manifest.json"), b"{").unwrap();
        assert!(matches!(store.check("k", false), Entry::Corrupt(w) if w.contains("malformed")));
    }
}
