//! File helpers of the cache: atomic writes, fsync, temporary names that say who made them and
//! whether such a leftover is abandoned, hashing.

use std::{
    fs::{self, File},
    path::Path,
    time::SystemTime,
};

use crate::error::{IoContext, IoError};

/// Seconds without a heartbeat after which a lock (or a temporary file) of a process on another
/// host counts as abandoned. On the same host a lock is stale as soon as its process is gone.
pub const STALE_LOCK_S: f64 = 300.0;

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
pub(super) fn pid_alive(pid: u32) -> bool {
    if pid == 0 || pid > i32::MAX as u32 {
        return false;
    }
    // SAFETY: kill with signal 0 only checks for existence.
    let r = unsafe { libc::kill(pid as i32, 0) };
    r == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
}

/// Whether `e` says writing is not allowed here (a read-only mount, no permission), as opposed
/// to a missing path or a full disk.
pub(super) fn refused(e: &std::io::Error) -> bool {
    matches!(
        e.raw_os_error(),
        Some(libc::EROFS) | Some(libc::EACCES) | Some(libc::EPERM)
    )
}

/// `NAME~PID~HOST~NANOS`: a temporary name that says who made it.
pub(super) fn owned_name(name: &str) -> String {
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
pub(super) fn is_leftover(path: &Path) -> bool {
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

/// The blake3 of the file at `path`, read in pieces (entry files may be gigabytes).
pub(super) fn hash_file(path: &Path) -> std::io::Result<String> {
    let mut h = blake3::Hasher::new();
    h.update_reader(File::open(path)?)?;
    Ok(h.finalize().to_hex().to_string())
}

pub(super) fn hash_bytes(bytes: &[u8]) -> String {
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
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), IoError> {
    let name = path.file_name().unwrap_or_default().to_string_lossy();
    let tmp = path.with_file_name(format!(".{}", owned_name(&name)));
    let written = fs::write(&tmp, bytes)
        .io_context(|| format!("writing {} (disk full?)", tmp.display()))
        .and_then(|()| {
            fs::rename(&tmp, path).io_context(|| format!("publishing {}", path.display()))
        });
    if written.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    written
}

pub(super) fn fsync_dir(dir: &Path) -> Result<(), IoError> {
    File::open(dir)
        .and_then(|f| f.sync_all())
        .io_context(|| format!("fsync {}", dir.display()))
}

/// The total size of the files directly in `dir`.
pub(super) fn dir_size(dir: &Path) -> u64 {
    fs::read_dir(dir)
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .filter_map(|e| e.metadata().ok())
                .map(|m| m.len())
                .sum()
        })
        .unwrap_or(0)
}
