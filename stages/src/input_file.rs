//! Files outside the cache that stages read: only regular files are read. A FIFO would block
//! the read (and the run) forever; a directory or device in a path parameter is a mistake, and
//! a directory would be hashed recursively (a whole data set root) before anything failed.

use std::{os::unix::fs::FileTypeExt, path::Path};

/// What `path` is when it exists and is not a regular file (`"a directory"`, `"a FIFO (named
/// pipe)"`, ...); `None` for a regular file, a link to one, or a missing path (reported by the
/// reader, which knows which input it is).
pub fn not_regular(path: &Path) -> Option<&'static str> {
    let t = std::fs::metadata(path).ok()?.file_type();
    Some(if t.is_file() {
        return None;
    } else if t.is_dir() {
        "a directory"
    } else if t.is_fifo() {
        "a FIFO (named pipe)"
    } else if t.is_socket() {
        "a socket"
    } else if t.is_block_device() || t.is_char_device() {
        "a device"
    } else {
        "not a regular file"
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_regular_files_pass() {
        let dir = tempfile_dir();
        let file = dir.join("f.txt");
        std::fs::write(&file, "x").unwrap();
        let fifo = dir.join("p.fifo");
        assert!(std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success());
        assert_eq!(not_regular(&file), None);
        assert_eq!(not_regular(&dir.join("missing")), None);
        assert_eq!(not_regular(&dir), Some("a directory"));
        assert_eq!(not_regular(&fifo), Some("a FIFO (named pipe)"));
        assert_eq!(not_regular(Path::new("/dev/null")), Some("a device"));
        std::fs::remove_dir_all(dir).unwrap();
    }

    fn tempfile_dir() -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("input-file-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }
}
