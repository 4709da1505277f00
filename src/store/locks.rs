//! Who may write the cache. Per entry, [`KeyLock`]: `locks/<key>.lock`, created by the
//! hard-link trick (atomic on NFS) and kept alive by a heartbeat, so many runs on many machines
//! compute each entry once; a lock whose holder died is broken by the next run. For the whole
//! cache, [`RunLock`]: an flock shared by every `pipe run` and exclusive for `pipe gc`.

use std::{
    fs::{self, File},
    io::{Read, Write},
    os::unix::fs::MetadataExt,
    path::{Path, PathBuf},
    sync::{
        atomic::{AtomicBool, Ordering},
        Arc,
    },
    time::{Duration, Instant, SystemTime},
};

use super::{
    error::StoreError,
    files::{host_name, is_leftover, owned_name, pid_alive, refused, STALE_LOCK_S},
    layout::Store,
};
use crate::error::{IoContext, IoError};

/// How often a held [`KeyLock`] refreshes its file's mtime.
const HEARTBEAT_S: u64 = 20;

/// The content of a lock file: `PID HOST NONCE START`, and its inode and age.
struct LockHolder {
    /// `None` when the file does not hold `PID HOST NONCE` (empty, truncated, garbage): a lock
    /// is linked into place only once its content is written and synced, so such a file was
    /// never a live lock.
    pid: Option<u32>,
    host: String,
    /// When the holder started ([`process_start`]): tells the holder from a later process that
    /// reuses its pid. `None` in a lock without it (written by an older `pipe`).
    start: Option<u64>,
    ino: u64,
    age_s: f64,
}

impl LockHolder {
    fn read(path: &Path) -> Option<LockHolder> {
        let meta = fs::metadata(path).ok()?;
        let text = fs::read_to_string(path).ok()?;
        let mut it = text.split_whitespace();
        let pid = it.next().and_then(|p| p.parse().ok()).filter(|&p| p > 0);
        let host = it.next().unwrap_or("?").to_string();
        let pid = pid.filter(|_| it.next().is_some());
        let start = it.next().and_then(|s| s.parse().ok());
        let age_s = meta
            .modified()
            .ok()
            .and_then(|t| t.elapsed().ok())
            .map_or(0.0, |d| d.as_secs_f64());
        Some(LockHolder {
            pid,
            host,
            start,
            ino: meta.ino(),
            age_s,
        })
    }

    fn is_stale(&self) -> bool {
        let Some(pid) = self.pid else {
            return true;
        };
        if self.age_s > STALE_LOCK_S {
            return true;
        }
        if self.host != host_name() {
            return false;
        }
        if !pid_alive(pid) {
            return true;
        }
        match self.start {
            // A live process by that pid that started at another time reuses the pid.
            Some(start) => process_start(pid).is_some_and(|now| now != start),
            // No start time to tell: a live holder refreshes the file every HEARTBEAT_S.
            None => self.age_s > 3.0 * HEARTBEAT_S as f64,
        }
    }

    fn describe(&self) -> String {
        match self.pid {
            Some(pid) => format!("process {pid} on {}", self.host),
            None => "an unreadable lock file".to_string(),
        }
    }
}

/// The lock of one cache entry while this process computes it: `locks/<key>.lock`, refreshed
/// by a heartbeat thread, removed on drop (if it is still ours).
pub struct KeyLock {
    path: PathBuf,
    nonce: String,
    stop: Arc<AtomicBool>,
    beat: Option<std::thread::JoinHandle<()>>,
}

impl KeyLock {
    fn start(path: PathBuf, nonce: String) -> KeyLock {
        let stop = Arc::new(AtomicBool::new(false));
        let (p, s) = (path.clone(), stop.clone());
        let beat = std::thread::spawn(move || {
            let mut last = Instant::now();
            while !s.load(Ordering::Relaxed) {
                std::thread::sleep(Duration::from_millis(100));
                if last.elapsed().as_secs() >= HEARTBEAT_S {
                    last = Instant::now();
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
        self.stop.store(true, Ordering::Relaxed);
        if let Some(b) = self.beat.take() {
            let _ = b.join();
        }
        if fs::read_to_string(&self.path).is_ok_and(|t| t.contains(&self.nonce)) {
            let _ = fs::remove_file(&self.path);
        }
    }
}

impl Store {
    /// Removes leftovers of interrupted runs: temporary entries and lock files of processes
    /// that are gone (on this host) or silent for [`STALE_LOCK_S`]. Other runs' live work is
    /// left alone, so this is safe while they run.
    pub fn clean_tmp(&self) -> usize {
        let mut n = self.remove_tmp_leftovers();
        if let Ok(rd) = fs::read_dir(self.dir("locks")) {
            for e in rd.filter_map(|e| e.ok()) {
                let name = e.file_name().to_string_lossy().into_owned();
                if name.starts_with('.') && is_leftover(&e.path()) {
                    let _ = fs::remove_file(e.path());
                } else if let Some(key) = name.strip_suffix(".lock") {
                    if self.break_stale_lock(key).is_some() {
                        n += 1;
                    }
                }
            }
        }
        n
    }

    /// Removes the temporary entries of processes that are gone: how many.
    fn remove_tmp_leftovers(&self) -> usize {
        let mut n = 0;
        if let Ok(rd) = fs::read_dir(self.dir("tmp")) {
            for e in rd.filter_map(|e| e.ok()) {
                let path = e.path();
                if !is_leftover(&path) {
                    continue;
                }
                let removed = if path.is_dir() {
                    fs::remove_dir_all(&path)
                } else {
                    fs::remove_file(&path)
                };
                n += usize::from(removed.is_ok());
            }
        }
        n
    }

    fn lock_path(&self, key: &str) -> PathBuf {
        self.dir("locks").join(format!("{key}.lock"))
    }

    /// If the lock of `key` is stale, breaks it and returns who held it; `None` when it is
    /// held by a live process or free.
    fn break_stale_lock(&self, key: &str) -> Option<String> {
        let path = self.lock_path(key);
        let holder = LockHolder::read(&path)?;
        if !holder.is_stale() {
            return None;
        }
        // Rename it away (only one breaker succeeds), then make sure we broke that lock and
        // not a fresh one taken meanwhile; a fresh one is put back.
        let aside = path.with_file_name(format!(".{}", owned_name(&format!("{key}.broken"))));
        if fs::rename(&path, &aside).is_err() {
            return None;
        }
        let moved_ino = fs::metadata(&aside).map(|m| m.ino()).unwrap_or(0);
        if moved_ino != holder.ino {
            let _ = fs::hard_link(&aside, &path);
            let _ = fs::remove_file(&aside);
            return None;
        }
        let _ = fs::remove_file(&aside);
        // What the dead holder was writing is of no use to anyone.
        self.remove_tmp_leftovers();
        Some(holder.describe())
    }

    /// Tries once to take the lock of entry `key`: the lock, or who holds it. A stale lock is
    /// broken and taken.
    pub fn try_lock_key(&self, key: &str) -> Result<Result<KeyLock, String>, StoreError> {
        let dir = self.dir("locks");
        fs::create_dir_all(&dir).io_context(|| format!("creating {}", dir.display()))?;
        let path = self.lock_path(key);
        let nonce = owned_name("lock");
        let uniq = dir.join(format!(".{key}.{nonce}"));
        let me = std::process::id();
        let start = process_start(me).unwrap_or(0);
        let content = format!("{me} {} {nonce} {start}\n", host_name());
        let written = File::create(&uniq)
            .and_then(|mut f| f.write_all(content.as_bytes()).and_then(|()| f.sync_all()))
            .io_context(|| format!("writing lock file {} (disk full?)", uniq.display()));
        if let Err(e) = written {
            let _ = fs::remove_file(&uniq);
            return Err(e.into());
        }
        let result = (|| {
            for _ in 0..5 {
                if link_lock(&uniq, &path, &content)? {
                    return Ok(Ok(KeyLock::start(path.clone(), nonce.clone())));
                }
                if self.break_stale_lock(key).is_some() {
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
    ) -> Result<KeyLock, StoreError> {
        let mut said = false;
        let mut pause = Duration::from_millis(50);
        loop {
            match self.try_lock_key(key)? {
                Ok(lock) => return Ok(lock),
                Err(holder) if no_wait => {
                    return Err(StoreError::Locked {
                        cache: self.root.clone(),
                        holder,
                        entry: Some(key.to_string()),
                    })
                }
                Err(holder) => {
                    if !said {
                        waiting(&holder);
                        said = true;
                    }
                    std::thread::sleep(pause);
                    pause = (pause * 2).min(Duration::from_secs(2));
                }
            }
        }
    }
}

/// When process `pid` started (clock ticks after boot, `/proc/PID/stat` field 22), or `None`
/// where that cannot be read.
fn process_start(pid: u32) -> Option<u64> {
    let stat = fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // The command name (field 2) may hold spaces and parentheses: count from its end.
    let after = &stat[stat.rfind(')')? + 1..];
    after.split_whitespace().nth(19)?.parse().ok()
}

/// Links our unique file `uniq` as the lock `path`: whether we got the lock.
fn link_lock(uniq: &Path, path: &Path, content: &str) -> Result<bool, StoreError> {
    // The hard-link trick: link(2) is atomic on NFS, and a lost reply is caught by the link
    // count of our own file.
    Ok(match fs::hard_link(uniq, path) {
        Ok(()) => true,
        Err(_) if fs::metadata(uniq).is_ok_and(|m| m.nlink() == 2) => true,
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => false,
        Err(_) => {
            // File systems without hard links: exclusive create.
            match fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(path)
            {
                Ok(mut f) => {
                    f.write_all(content.as_bytes())
                        .and_then(|()| f.sync_all())
                        .io_context(|| {
                            format!("writing lock file {} (disk full?)", path.display())
                        })?;
                    true
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => false,
                Err(source) => {
                    return Err(IoError {
                        what: format!("creating lock file {}", path.display()),
                        source,
                    }
                    .into())
                }
            }
        }
    })
}

/// A lock on the whole cache (flock on `.pipe/lock`): shared by every `pipe run`, exclusive for
/// `pipe gc`, which deletes entries. The kernel releases the lock of a process that died. Where
/// the file system has no flock (some NFS set-ups), it is skipped: the per-entry locks still
/// hold.
pub struct RunLock {
    _file: Option<File>,
}

impl RunLock {
    /// Takes the lock (`exclusive` for gc); if it is taken the other way, waits (printing who
    /// holds it) or, with `no_wait`, fails with a message naming the holder.
    pub fn acquire(root: &Path, no_wait: bool, exclusive: bool) -> Result<RunLock, StoreError> {
        use std::os::fd::AsRawFd;
        let path = root.join("lock");
        let opened = fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path);
        let mut file = match opened {
            Ok(f) => f,
            // A read-only cache: a shared lock through a read-only descriptor, so a gc by whoever
            // may write it still waits; without a lock file nobody can gc it either.
            Err(e) if !exclusive && refused(&e) => match File::open(&path) {
                Ok(f) => f,
                Err(_) => return Ok(RunLock { _file: None }),
            },
            opened => opened.io_context(|| format!("opening lock file {}", path.display()))?,
        };
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
                return Ok(RunLock { _file: Some(file) });
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
                return Err(StoreError::Locked {
                    cache: root.to_path_buf(),
                    holder: who,
                    entry: None,
                });
            }
            eprintln!("waiting for {who} on {} ...", root.display());
            // SAFETY: as above; blocks until the holder releases or dies.
            if unsafe { libc::flock(fd, mode) } != 0 {
                return Err(StoreError::Flock {
                    path,
                    source: std::io::Error::last_os_error(),
                });
            }
        }
        if exclusive {
            // Who holds the lock, for the message of a waiting run.
            use std::io::Seek;
            file.set_len(0)
                .and_then(|()| file.seek(std::io::SeekFrom::Start(0)))
                .and_then(|_| write!(file, "{} on {}", std::process::id(), host_name()))
                .and_then(|()| file.flush())
                .io_context(|| format!("writing lock file {} (disk full?)", path.display()))?;
        }
        Ok(RunLock { _file: Some(file) })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lock_file_without_a_holder_is_stale() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        fs::create_dir_all(store.dir("locks")).unwrap();
        for (key, content) in [
            ("empty", ""),
            ("garbage", "\u{0}\u{0}x"),
            ("pid_only", "123"),
        ] {
            fs::write(store.lock_path(key), content).unwrap();
            let lock = store.try_lock_key(key).unwrap();
            assert!(lock.is_ok(), "{key:?} lock file: {:?}", lock.err());
        }
        // A live holder (this process) still holds.
        let held = store.try_lock_key("live").unwrap().unwrap();
        assert!(store.try_lock_key("live").unwrap().is_err());
        drop(held);
        assert!(store.try_lock_key("live").unwrap().is_ok());
    }

    #[test]
    fn a_live_process_that_reuses_the_holders_pid_does_not_hold_the_lock() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        fs::create_dir_all(store.dir("locks")).unwrap();
        let me = std::process::id();
        let start = process_start(me).expect("/proc/self/stat");
        let host = host_name();
        let held = |content: String| {
            fs::write(store.lock_path("k"), content).unwrap();
            let got = store.try_lock_key("k").unwrap();
            let held = got.is_err();
            drop(got);
            let _ = fs::remove_file(store.lock_path("k"));
            held
        };
        assert!(
            held(format!("{me} {host} n {start}\n")),
            "the holder itself"
        );
        assert!(
            !held(format!("{me} {host} n {}\n", start + 1)),
            "a process that started at another time reuses the pid"
        );
        // Without a start time (an older lock): held while its heartbeat is fresh.
        assert!(held(format!("{me} {host} n\n")));
        fs::write(store.lock_path("k"), format!("{me} {host} n\n")).unwrap();
        let old = SystemTime::now() - Duration::from_secs(3 * HEARTBEAT_S + 5);
        File::options()
            .write(true)
            .open(store.lock_path("k"))
            .unwrap()
            .set_modified(old)
            .unwrap();
        assert!(store.try_lock_key("k").unwrap().is_ok(), "no heartbeat");
    }

    #[test]
    fn breaking_a_dead_holders_lock_removes_its_temporary_entries() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let dead = child.id();
        child.wait().unwrap();
        let host = host_name();
        fs::write(store.lock_path("k"), format!("{dead} {host} n 1\n")).unwrap();
        let theirs = store.dir("tmp").join(format!("entry.k~{dead}~{host}~1"));
        let ours = store.dir("tmp").join(owned_name("entry.j"));
        fs::create_dir_all(&theirs).unwrap();
        fs::create_dir_all(&ours).unwrap();
        assert!(store.try_lock_key("k").unwrap().is_ok());
        assert!(!theirs.exists(), "the dead holder's entry survives");
        assert!(ours.exists(), "a live process's entry was removed");
    }
}
