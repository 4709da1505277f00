//! The content-addressed cache.
//!
//! ```text
//! .pipe/
//!   objects/<key>/<table>.parquet   one file per output table
//!   objects/<key>/manifest.json     what made the entry, and each file's size + blake3
//!   tmp/                            entries being written (renamed into objects/ when complete)
//!   trash/                          corrupt entries moved aside for inspection
//!   runs/<stage>.json               the last successful run of each stage instance (for status)
//!   state/verified.json             (size, mtime, inode) of files already hashed, so a no-op
//!                                   run does not re-hash gigabytes
//!   locks/<key>.lock                who computes entry <key> right now (pid, host); see KeyLock
//!   lock                            flock: shared by every `pipe run`, exclusive for `pipe gc`
//! ```
//! An entry is published by writing it completely under `tmp/`, fsyncing it and renaming the
//! directory into `objects/`, so a crash leaves no partial entry. Reading verifies sizes and
//! hashes; a corrupt entry is moved to `trash/` and recomputed.
//!
//! Many `pipe run` processes, on many machines sharing the cache over NFS, may work on one
//! cache at once: before computing an entry a run takes the entry's lock file (created by the
//! hard-link trick, atomic on NFS), then looks again whether another run published the entry
//! meanwhile. The first writer wins; a duplicate is discarded. A lock whose holder died (same
//! host and the pid is gone, or no heartbeat for [`STALE_LOCK_S`]) is broken by the next run.

use std::{
    collections::{BTreeMap, BTreeSet},
    fs::{self, File},
    io::{Read, Write},
    os::unix::fs::MetadataExt,
    path::{Path, PathBuf},
    sync::Arc,
    time::SystemTime,
};

use anyhow::{anyhow, bail, Context, Result};
use arrow::{compute::concat_batches, record_batch::RecordBatch};
use parquet::{
    arrow::{arrow_reader::ParquetRecordBatchReaderBuilder, ArrowWriter},
    basic::Compression,
    file::properties::WriterProperties,
};
use serde::{Deserialize, Serialize};
use stages::Tables;

use crate::fingerprint;

/// Size and hash of one file of an entry.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct FileInfo {
    pub size: u64,
    pub blake3: String,
}

/// An input of a run: which stage fed the slot, and the digest of what it wrote.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct InputInfo {
    pub stage: String,
    pub digest: String,
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
}

/// The last successful run of a stage instance, kept for `pipe status` explanations.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunRecord {
    pub key: String,
    pub kind: String,
    pub version: u32,
    pub params: serde_json::Value,
    pub inputs: BTreeMap<String, InputInfo>,
    /// Every key this stage instance has had (for `gc --keep-all-runs`).
    #[serde(default)]
    pub history: Vec<String>,
}

/// What a look-up of a key found.
pub enum Entry {
    Missing,
    Valid(Box<Manifest>),
    Corrupt(String),
}

pub struct Store {
    root: PathBuf,
}

pub fn unix_now() -> f64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// This machine's host name (lock files and temporary names say who wrote them).
pub fn host_name() -> String {
    let h = fs::read_to_string("/proc/sys/kernel/hostname").unwrap_or_default();
    let h = h.trim();
    if h.is_empty() {
        "localhost".into()
    } else {
        h.to_string()
    }
}

/// Whether process `pid` exists on this machine.
fn pid_alive(pid: u32) -> bool {
    if pid == 0 || pid > i32::MAX as u32 {
        return false;
    }
    // SAFETY: kill with signal 0 only checks for existence.
    let r = unsafe { libc::kill(pid as i32, 0) };
    r == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
}

/// `NAME~PID~HOST~NANOS`: a temporary name that says who made it.
fn owned_name(name: &str) -> String {
    format!(
        "{name}~{}~{}~{}",
        std::process::id(),
        host_name(),
        SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0)
    )
}

/// Whether the temporary file or directory `path` (named by [`owned_name`]) is a leftover: its
/// process is gone (same host), or it has not changed for [`STALE_LOCK_S`].
fn is_leftover(path: &Path) -> bool {
    let name = path.file_name().unwrap_or_default().to_string_lossy();
    let parts: Vec<&str> = name.split('~').collect();
    if let [_, pid, host, _] = parts[..] {
        if host == host_name() {
            return !pid.parse().is_ok_and(pid_alive);
        }
    }
    fs::symlink_metadata(path)
        .and_then(|m| m.modified())
        .ok()
        .and_then(|t| t.elapsed().ok())
        .is_some_and(|age| age.as_secs_f64() > STALE_LOCK_S)
}

fn hash_bytes(bytes: &[u8]) -> String {
    let mut h = blake3::Hasher::new();
    if bytes.len() > 1 << 20 {
        h.update_rayon(bytes);
    } else {
        h.update(bytes);
    }
    h.finalize().to_hex().to_string()
}

/// Writes `bytes` to `path` through a temporary file beside it and a rename, so readers see the
/// old content or the new, never a part; on failure (disk full) no temporary file is left.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let name = path.file_name().unwrap_or_default().to_string_lossy();
    let tmp = path.with_file_name(format!(".{}", owned_name(&name)));
    let written = fs::write(&tmp, bytes)
        .with_context(|| format!("writing {} (disk full?)", tmp.display()))
        .and_then(|()| {
            fs::rename(&tmp, path).with_context(|| format!("publishing {}", path.display()))
        });
    if written.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    written
}

fn fsync_dir(dir: &Path) -> Result<()> {
    File::open(dir)
        .and_then(|f| f.sync_all())
        .with_context(|| format!("fsync {}", dir.display()))
}

type Memo = BTreeMap<String, (u64, i64, u64)>;

impl Store {
    /// Opens (creating if needed) the cache at `root`.
    pub fn open(root: &Path) -> Result<Store> {
        for d in ["objects", "tmp", "trash", "runs", "state", "locks"] {
            let p = root.join(d);
            fs::create_dir_all(&p).with_context(|| {
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

    fn memo_path(&self) -> PathBuf {
        self.root.join("state").join("verified.json")
    }

    fn load_memo(&self) -> Memo {
        fs::read(self.memo_path())
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok())
            .unwrap_or_default()
    }

    fn save_memo(&self, memo: &Memo) {
        // Best effort: losing the memo only costs a re-hash.
        let _ = write_atomic(
            &self.memo_path(),
            &serde_json::to_vec(memo).unwrap_or_default(),
        );
    }

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
        let digests = m
            .files
            .iter()
            .map(|(n, f)| (n.clone(), f.blake3.clone()))
            .collect();
        if fingerprint::output_digest(&digests) != m.output_digest {
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
        let mut memo = self.load_memo();
        let mut memo_changed = false;
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
            let stamp = (
                meta.len(),
                meta.mtime() * 1_000_000_000 + meta.mtime_nsec(),
                meta.ino(),
            );
            let memo_key = format!("{key}/{name}");
            if !full && memo.get(&memo_key) == Some(&stamp) {
                continue;
            }
            let digest = match fs::read(&path) {
                Ok(bytes) => hash_bytes(&bytes),
                Err(e) => return Entry::Corrupt(format!("cannot read {name}: {e}")),
            };
            if digest != info.blake3 {
                memo.remove(&memo_key);
                self.save_memo(&memo);
                return Entry::Corrupt(format!(
                    "file {name} does not match its blake3 in the manifest"
                ));
            }
            memo.insert(memo_key, stamp);
            memo_changed = true;
        }
        if let Some(x) = extra.into_iter().next() {
            return Entry::Corrupt(format!("unexpected file {x} in the entry"));
        }
        if memo_changed {
            self.save_memo(&memo);
        }
        Entry::Valid(Box::new(m))
    }

    /// blake3 over the contents of `paths` (directories recursively, in sorted order; a missing
    /// path enters as "missing" so the stage itself reports it). File hashes are memoised by
    /// path, size, mtime and inode in `state/files.json`.
    pub fn files_digest(&self, paths: &[PathBuf]) -> Result<String> {
        type FileMemo = BTreeMap<String, ((u64, i64, u64), String)>;
        let memo_path = self.root.join("state").join("files.json");
        let mut memo: FileMemo = fs::read(&memo_path)
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok())
            .unwrap_or_default();
        let mut changed = false;
        let mut files = Vec::new();
        for p in paths {
            collect_files(p, &mut files);
        }
        let mut h = blake3::Hasher::new();
        for f in files {
            let name = f.to_string_lossy().into_owned();
            h.update(name.as_bytes());
            h.update(&[0]);
            let digest = match fs::metadata(&f) {
                Err(_) => "missing".to_string(),
                Ok(meta) => {
                    let stamp = (
                        meta.len(),
                        meta.mtime() * 1_000_000_000 + meta.mtime_nsec(),
                        meta.ino(),
                    );
                    match memo.get(&name) {
                        Some((s, d)) if *s == stamp => d.clone(),
                        _ => {
                            let bytes = fs::read(&f)
                                .with_context(|| format!("reading input file {}", f.display()))?;
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
        if changed && fs::create_dir_all(self.root.join("state")).is_ok() {
            // Best effort, like the verified-files memo.
            let _ = write_atomic(&memo_path, &serde_json::to_vec(&memo).unwrap_or_default());
        }
        Ok(h.finalize().to_hex().to_string())
    }

    /// Moves a corrupt entry to `trash/` so it is kept for inspection but never used.
    pub fn quarantine(&self, key: &str) -> Result<PathBuf> {
        let dest = self.root.join("trash").join(format!(
            "{key}.{}.{}",
            std::process::id(),
            unix_now() as u64
        ));
        fs::rename(self.entry_dir(key), &dest)
            .with_context(|| format!("moving corrupt entry {key} to {}", dest.display()))?;
        let mut memo = self.load_memo();
        memo.retain(|k, _| !k.starts_with(key));
        self.save_memo(&memo);
        Ok(dest)
    }

    /// Reads an entry's tables, verifying every byte read against the manifest.
    pub fn load(&self, m: &Manifest) -> Result<Tables> {
        let dir = self.entry_dir(&m.key);
        let mut tables = Tables::new();
        for (name, info) in &m.files {
            let path = dir.join(name);
            let mut bytes = Vec::with_capacity(info.size as usize);
            File::open(&path)
                .and_then(|mut f| f.read_to_end(&mut bytes))
                .with_context(|| format!("reading {}", path.display()))?;
            if bytes.len() as u64 != info.size || hash_bytes(&bytes) != info.blake3 {
                bail!(
                    "{} changed since it was verified (size or blake3 mismatch)",
                    path.display()
                );
            }
            let table = name.strip_suffix(".parquet").unwrap_or(name).to_string();
            let batch =
                read_parquet(bytes).with_context(|| format!("decoding {}", path.display()))?;
            tables.insert(table, batch);
        }
        Ok(tables)
    }

    /// Writes `tables` as a new entry and publishes it atomically. If another process
    /// published the same key meanwhile, its (verified) entry wins and ours is discarded.
    pub fn publish(&self, mut manifest: Manifest, tables: &Tables) -> Result<Manifest> {
        let key = manifest.key.clone();
        let tmp = self.root.join("tmp").join(owned_name(&key));
        let result = (|| -> Result<Manifest> {
            fs::create_dir_all(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
            manifest.files.clear();
            manifest.schemas.clear();
            for (name, batch) in tables {
                let file = format!("{name}.parquet");
                let bytes =
                    write_parquet(batch).with_context(|| format!("encoding table {name}"))?;
                let path = tmp.join(&file);
                let mut f =
                    File::create(&path).with_context(|| format!("creating {}", path.display()))?;
                f.write_all(&bytes)
                    .and_then(|_| f.sync_all())
                    .with_context(|| format!("writing {} (disk full?)", path.display()))?;
                manifest.files.insert(
                    file,
                    FileInfo {
                        size: bytes.len() as u64,
                        blake3: hash_bytes(&bytes),
                    },
                );
                manifest
                    .schemas
                    .insert(name.clone(), format!("data_schema/{name}.json"));
            }
            let digests = manifest
                .files
                .iter()
                .map(|(n, f)| (n.clone(), f.blake3.clone()))
                .collect();
            manifest.output_digest = fingerprint::output_digest(&digests);
            let mpath = tmp.join("manifest.json");
            let mut f =
                File::create(&mpath).with_context(|| format!("creating {}", mpath.display()))?;
            f.write_all(&serde_json::to_vec_pretty(&manifest)?)
                .and_then(|_| f.sync_all())
                .with_context(|| format!("writing {} (disk full?)", mpath.display()))?;
            fsync_dir(&tmp)?;
            let dest = self.entry_dir(&key);
            match fs::rename(&tmp, &dest) {
                Ok(()) => {
                    fsync_dir(&self.root.join("objects"))?;
                    Ok(manifest.clone())
                }
                Err(_) if dest.exists() => {
                    // First writer wins; ours is a duplicate.
                    let _ = fs::remove_dir_all(&tmp);
                    match self.check(&key, true) {
                        Entry::Valid(m) => Ok(*m),
                        _ => bail!("entry {key} appeared concurrently but does not verify"),
                    }
                }
                Err(e) => Err(anyhow!(e)).with_context(|| format!("publishing {}", dest.display())),
            }
        })();
        if result.is_err() {
            let _ = fs::remove_dir_all(&tmp);
        }
        result
    }

    /// Removes leftovers of interrupted runs: temporary entries and lock files of processes
    /// that are gone (on this host) or silent for [`STALE_LOCK_S`]. Other runs' live work is
    /// left alone, so this is safe while they run.
    pub fn clean_tmp(&self) -> usize {
        let mut n = 0;
        if let Ok(rd) = fs::read_dir(self.root.join("tmp")) {
            for e in rd.filter_map(|e| e.ok()) {
                if is_leftover(&e.path()) && fs::remove_dir_all(e.path()).is_ok() {
                    n += 1;
                }
            }
        }
        if let Ok(rd) = fs::read_dir(self.root.join("locks")) {
            for e in rd.filter_map(|e| e.ok()) {
                let name = e.file_name().to_string_lossy().into_owned();
                if name.starts_with('.') && is_leftover(&e.path()) {
                    let _ = fs::remove_file(e.path());
                } else if let Some(key) = name.strip_suffix(".lock") {
                    if let Ok(Some(_)) = self.stale_lock(key) {
                        n += 1;
                    }
                }
            }
        }
        n
    }

    fn lock_path(&self, key: &str) -> PathBuf {
        self.root.join("locks").join(format!("{key}.lock"))
    }

    /// If the lock of `key` is stale, breaks it and returns who held it; `Ok(None)` when it is
    /// held by a live process or free.
    fn stale_lock(&self, key: &str) -> Result<Option<String>> {
        let path = self.lock_path(key);
        let Some(holder) = LockHolder::read(&path) else {
            return Ok(None);
        };
        if !holder.is_stale() {
            return Ok(None);
        }
        // Rename it away (only one breaker succeeds), then make sure we broke that lock and
        // not a fresh one taken meanwhile; a fresh one is put back.
        let aside = path.with_file_name(format!(".{}", owned_name(&format!("{key}.broken"))));
        if fs::rename(&path, &aside).is_err() {
            return Ok(None);
        }
        let moved_ino = fs::metadata(&aside).map(|m| m.ino()).unwrap_or(0);
        if moved_ino != holder.ino {
            let _ = fs::hard_link(&aside, &path);
            let _ = fs::remove_file(&aside);
            return Ok(None);
        }
        let _ = fs::remove_file(&aside);
        Ok(Some(holder.describe()))
    }

    /// Tries once to take the lock of entry `key`: the lock, or who holds it. A stale lock is
    /// broken and taken.
    pub fn try_lock_key(&self, key: &str) -> Result<Result<KeyLock, String>> {
        let dir = self.root.join("locks");
        fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        let path = self.lock_path(key);
        let nonce = owned_name("lock");
        let uniq = dir.join(format!(".{key}.{nonce}"));
        let content = format!("{} {} {nonce}\n", std::process::id(), host_name());
        let written = File::create(&uniq)
            .and_then(|mut f| f.write_all(content.as_bytes()).and_then(|()| f.sync_all()))
            .with_context(|| format!("writing lock file {} (disk full?)", uniq.display()));
        if let Err(e) = written {
            let _ = fs::remove_file(&uniq);
            return Err(e);
        }
        let result = (|| {
            for _ in 0..5 {
                // The hard-link trick: link(2) is atomic on NFS, and a lost reply is caught
                // by the link count of our own file.
                let linked = match fs::hard_link(&uniq, &path) {
                    Ok(()) => true,
                    Err(_) if fs::metadata(&uniq).is_ok_and(|m| m.nlink() == 2) => true,
                    Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => false,
                    Err(_) => {
                        // File systems without hard links: exclusive create.
                        match fs::OpenOptions::new()
                            .write(true)
                            .create_new(true)
                            .open(&path)
                        {
                            Ok(mut f) => {
                                f.write_all(content.as_bytes())
                                    .and_then(|()| f.sync_all())
                                    .with_context(|| {
                                        format!("writing lock file {} (disk full?)", path.display())
                                    })?;
                                true
                            }
                            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => false,
                            Err(e) => {
                                return Err(anyhow!(e)).with_context(|| {
                                    format!("creating lock file {}", path.display())
                                })
                            }
                        }
                    }
                };
                if linked {
                    return Ok(Ok(KeyLock::start(path.clone(), nonce.clone())));
                }
                if self.stale_lock(key)?.is_some() {
                    continue;
                }
                match LockHolder::read(&path) {
                    Some(h) => return Ok(Err(h.describe())),
                    None => continue, // released meanwhile
                }
            }
            Ok(Err(
                "another process (the lock keeps changing hands)".to_string()
            ))
        })();
        let _ = fs::remove_file(&uniq);
        result
    }

    /// Takes the lock of entry `key`, waiting while a live process holds it (`waiting` is
    /// called once with the holder); with `no_wait`, a held lock is an error naming the holder.
    pub fn lock_key(
        &self,
        key: &str,
        no_wait: bool,
        mut waiting: impl FnMut(&str),
    ) -> Result<KeyLock> {
        let mut said = false;
        let mut pause = std::time::Duration::from_millis(50);
        loop {
            match self.try_lock_key(key)? {
                Ok(lock) => return Ok(lock),
                Err(holder) if no_wait => bail!(
                    "the cache {} is locked by {holder} (another `pipe run` computes entry {key}); retry later or drop --no-wait",
                    self.root.display()
                ),
                Err(holder) => {
                    if !said {
                        waiting(&holder);
                        said = true;
                    }
                    std::thread::sleep(pause);
                    pause = (pause * 2).min(std::time::Duration::from_secs(2));
                }
            }
        }
    }

    pub fn run_record(&self, stage: &str) -> Option<RunRecord> {
        let bytes = fs::read(self.root.join("runs").join(format!("{stage}.json"))).ok()?;
        serde_json::from_slice(&bytes).ok()
    }

    pub fn save_run_record(&self, stage: &str, mut rec: RunRecord) -> Result<()> {
        let mut history = self
            .run_record(stage)
            .map(|r| r.history)
            .unwrap_or_default();
        if !history.contains(&rec.key) {
            history.push(rec.key.clone());
        }
        rec.history = history;
        let dest = self.root.join("runs").join(format!("{stage}.json"));
        write_atomic(&dest, &serde_json::to_vec_pretty(&rec)?)
    }

    /// All run records (stage name -> record).
    pub fn run_records(&self) -> BTreeMap<String, RunRecord> {
        let mut out = BTreeMap::new();
        if let Ok(rd) = fs::read_dir(self.root.join("runs")) {
            for e in rd.filter_map(|e| e.ok()) {
                let name = e.file_name().to_string_lossy().into_owned();
                if let Some(stage) = name.strip_suffix(".json").filter(|s| !s.starts_with('.')) {
                    if let Some(r) = self.run_record(stage) {
                        out.insert(stage.to_string(), r);
                    }
                }
            }
        }
        out
    }

    /// Keys of every entry in `objects/`.
    pub fn keys(&self) -> Vec<String> {
        let mut keys: Vec<String> = fs::read_dir(self.root.join("objects"))
            .map(|rd| {
                rd.filter_map(|e| e.ok())
                    .map(|e| e.file_name().to_string_lossy().into_owned())
                    .collect()
            })
            .unwrap_or_default();
        keys.sort();
        keys
    }

    /// Removes every entry not in `keep`; returns (entries removed, bytes freed).
    pub fn gc(&self, keep: &BTreeSet<String>, dry_run: bool) -> Result<(Vec<String>, u64)> {
        let mut removed = Vec::new();
        let mut bytes = 0;
        for key in self.keys() {
            if keep.contains(&key) {
                continue;
            }
            let dir = self.entry_dir(&key);
            bytes += dir_size(&dir);
            if !dry_run {
                // Rename first so a concurrent reader never sees a half-deleted entry.
                let doomed = self.root.join("tmp").join(owned_name(&format!("gc.{key}")));
                fs::rename(&dir, &doomed).with_context(|| format!("removing {}", dir.display()))?;
                fs::remove_dir_all(&doomed)
                    .with_context(|| format!("removing {}", doomed.display()))?;
            }
            removed.push(key);
        }
        if !dry_run {
            let _ = fs::remove_dir_all(self.root.join("trash"));
            let _ = fs::create_dir_all(self.root.join("trash"));
        }
        Ok((removed, bytes))
    }
}

/// `path` itself if it is not a directory, else every file below it, sorted.
fn collect_files(path: &Path, out: &mut Vec<PathBuf>) {
    if path.is_dir() {
        let mut entries: Vec<PathBuf> = fs::read_dir(path)
            .map(|rd| rd.filter_map(|e| e.ok()).map(|e| e.path()).collect())
            .unwrap_or_default();
        entries.sort();
        for e in entries {
            collect_files(&e, out);
        }
    } else {
        out.push(path.to_path_buf());
    }
}

fn dir_size(dir: &Path) -> u64 {
    fs::read_dir(dir)
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .filter_map(|e| e.metadata().ok())
                .map(|m| m.len())
                .sum()
        })
        .unwrap_or(0)
}

/// Encodes one table as Parquet (snappy), deterministically.
pub fn write_parquet(batch: &RecordBatch) -> Result<Vec<u8>> {
    let mut props = WriterProperties::builder()
        .set_compression(Compression::SNAPPY)
        .set_created_by(format!("panoptic-pipe {}", env!("CARGO_PKG_VERSION")));
    // Float columns (weights, positions, depths) barely repeat: a dictionary only costs time
    // (interning a million weights took ~0.4 s per train entry) and space.
    let parquet_schema = parquet::arrow::ArrowSchemaConverter::new().convert(&batch.schema())?;
    for col in parquet_schema.columns() {
        if matches!(
            col.physical_type(),
            parquet::basic::Type::FLOAT | parquet::basic::Type::DOUBLE
        ) {
            props = props.set_column_dictionary_enabled(col.path().clone(), false);
        }
    }
    let props = props.build();
    let mut buf = Vec::new();
    let mut w = ArrowWriter::try_new(&mut buf, batch.schema(), Some(props))?;
    w.write(batch)?;
    w.close()?;
    Ok(buf)
}

/// Decodes a Parquet file into one batch.
pub fn read_parquet(bytes: Vec<u8>) -> Result<RecordBatch> {
    let builder = ParquetRecordBatchReaderBuilder::try_new(bytes::Bytes::from(bytes))?;
    let schema = Arc::clone(builder.schema());
    let reader = builder.with_batch_size(1 << 16).build()?;
    let batches = reader.collect::<Result<Vec<_>, _>>()?;
    Ok(concat_batches(&schema, &batches)?)
}

/// Seconds without a heartbeat after which a lock (or a temporary file) of a process on another
/// host counts as abandoned. On the same host a lock is stale as soon as its process is gone.
pub const STALE_LOCK_S: f64 = 300.0;

/// How often a held [`KeyLock`] refreshes its file's mtime.
const HEARTBEAT_S: u64 = 20;

/// The content of a lock file: `PID HOST NONCE`, and its inode and age.
struct LockHolder {
    pid: u32,
    host: String,
    ino: u64,
    age_s: f64,
}

impl LockHolder {
    fn read(path: &Path) -> Option<LockHolder> {
        let meta = fs::metadata(path).ok()?;
        let text = fs::read_to_string(path).ok()?;
        let mut it = text.split_whitespace();
        let pid = it.next().and_then(|p| p.parse().ok()).unwrap_or(0);
        let host = it.next().unwrap_or("?").to_string();
        let age_s = meta
            .modified()
            .ok()
            .and_then(|t| t.elapsed().ok())
            .map_or(0.0, |d| d.as_secs_f64());
        Some(LockHolder {
            pid,
            host,
            ino: meta.ino(),
            age_s,
        })
    }

    fn is_stale(&self) -> bool {
        (self.host == host_name() && !pid_alive(self.pid)) || self.age_s > STALE_LOCK_S
    }

    fn describe(&self) -> String {
        format!("process {} on {}", self.pid, self.host)
    }
}

/// The lock of one cache entry while this process computes it: `locks/<key>.lock`, refreshed
/// by a heartbeat thread, removed on drop (if it is still ours).
pub struct KeyLock {
    path: PathBuf,
    nonce: String,
    stop: Arc<std::sync::atomic::AtomicBool>,
    beat: Option<std::thread::JoinHandle<()>>,
}

impl KeyLock {
    fn start(path: PathBuf, nonce: String) -> KeyLock {
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let (p, s) = (path.clone(), stop.clone());
        let beat = std::thread::spawn(move || {
            let mut last = std::time::Instant::now();
            while !s.load(std::sync::atomic::Ordering::Relaxed) {
                std::thread::sleep(std::time::Duration::from_millis(100));
                if last.elapsed().as_secs() >= HEARTBEAT_S {
                    last = std::time::Instant::now();
                    let _ = File::options()
                        .write(true)
                        .open(&p)
                        .and_then(|f| f.set_modified(SystemTime::now()));
                }
            }
        });
        KeyLock {
            path,
            nonce,
            stop,
            beat: Some(beat),
        }
    }
}

impl Drop for KeyLock {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        if let Some(b) = self.beat.take() {
            let _ = b.join();
        }
        if fs::read_to_string(&self.path).is_ok_and(|t| t.contains(&self.nonce)) {
            let _ = fs::remove_file(&self.path);
        }
    }
}

/// A lock on the whole cache (flock on `.pipe/lock`): shared by every `pipe run`, exclusive for
/// `pipe gc`, which deletes entries. The kernel releases the lock of a process that died. Where
/// the file system has no flock (some NFS set-ups), it is skipped: the per-entry locks still
/// hold.
pub struct RunLock {
    _file: File,
}

impl RunLock {
    /// Takes the lock (`exclusive` for gc); if it is taken the other way, waits (printing who
    /// holds it) or, with `no_wait`, fails with a message naming the holder.
    pub fn acquire(root: &Path, no_wait: bool, exclusive: bool) -> Result<RunLock> {
        use std::os::fd::AsRawFd;
        let path = root.join("lock");
        let mut file = fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .with_context(|| format!("opening lock file {}", path.display()))?;
        let fd = file.as_raw_fd();
        let mode = if exclusive {
            libc::LOCK_EX
        } else {
            libc::LOCK_SH
        };
        let unsupported = |e: &std::io::Error| {
            matches!(
                e.raw_os_error(),
                Some(libc::ENOLCK) | Some(libc::EOPNOTSUPP) | Some(libc::ENOSYS)
            )
        };
        // SAFETY: flock on a file descriptor we own.
        if unsafe { libc::flock(fd, mode | libc::LOCK_NB) } != 0 {
            let err = std::io::Error::last_os_error();
            if unsupported(&err) {
                return Ok(RunLock { _file: file });
            }
            let mut holder = String::new();
            let _ = file.read_to_string(&mut holder);
            let holder = holder.trim();
            let who = if exclusive || holder.is_empty() {
                "another process (`pipe run` or `pipe gc`)".to_string()
            } else {
                format!("process {holder} (`pipe gc`)")
            };
            if no_wait {
                bail!(
                    "the cache {} is locked by {who}; retry later or drop --no-wait",
                    root.display()
                );
            }
            eprintln!("waiting for {who} on {} ...", root.display());
            // SAFETY: as above; blocks until the holder releases or dies.
            if unsafe { libc::flock(fd, mode) } != 0 {
                bail!(
                    "locking {}: {}",
                    path.display(),
                    std::io::Error::last_os_error()
                );
            }
        }
        if exclusive {
            // Who holds the lock, for the message of a waiting run.
            use std::io::Seek;
            file.set_len(0)
                .and_then(|()| file.seek(std::io::SeekFrom::Start(0)))
                .and_then(|_| write!(file, "{} on {}", std::process::id(), host_name()))
                .and_then(|()| file.flush())
                .with_context(|| format!("writing lock file {} (disk full?)", path.display()))?;
        }
        Ok(RunLock { _file: file })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use arrow::{array::Int64Array, datatypes::Schema};

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
