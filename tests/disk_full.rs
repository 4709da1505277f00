//! A full disk or an unwritable cache directory: `pipe run` fails with exit code 1 and a message
//! naming the path and the OS error, publishes nothing partial, `pipe status` still works, and
//! the next normal run completes with the right results.
//!
//! "Disk full" without root: the child runs under `setrlimit(RLIMIT_FSIZE)` with SIGXFSZ ignored,
//! so a write past the limit fails with EFBIG ("File too large"), as a write to a full disk fails
//! with ENOSPC: same code paths. The limit is swept so the failure lands on each kind of file in
//! turn (lock, table, manifest, run record).

mod common;

use std::{fs, os::unix::fs::PermissionsExt, os::unix::process::CommandExt, process::Command};

use common::{Outcome, Workspace};

/// A small entry, a big one (about 160 kB of Parquet) and one downstream of the big one.
const PIPELINE: &str = "
stages:
  small:
    uses: test_source
  big:
    uses: test_source
    params: {rows: 20000, value: 7}
  map:
    uses: test_map
    inputs: {src: big}
";

/// `pipe run ARGS` with every file it writes limited to `max_file_bytes`.
fn run_limited(ws: &Workspace, max_file_bytes: u64, args: &[&str]) -> (i32, String) {
    let mut cmd = Command::new(common::PIPE);
    cmd.arg("run").args(args).current_dir(ws.dir());
    // SAFETY: signal() and setrlimit() are async-signal-safe; nothing else runs between fork
    // and exec.
    unsafe {
        cmd.pre_exec(move || {
            libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
            let lim = libc::rlimit {
                rlim_cur: max_file_bytes,
                rlim_max: max_file_bytes,
            };
            if libc::setrlimit(libc::RLIMIT_FSIZE, &lim) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let out = cmd.output().unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// No partial entry, no leftover temporary entry, and `pipe status` answers.
fn assert_cache_consistent(ws: &Workspace, after: &str) {
    ws.assert_every_entry_verifies(after);
    let tmp = ws.cache().join("tmp");
    let left: Vec<_> = fs::read_dir(&tmp)
        .map(|d| d.map(|e| e.unwrap().file_name()).collect())
        .unwrap_or_default();
    assert!(left.is_empty(), "{after}: tmp/ holds {left:?}");
    let runs: Vec<_> = fs::read_dir(ws.cache().join("runs"))
        .map(|d| d.map(|e| e.unwrap().file_name()).collect())
        .unwrap_or_default();
    assert!(
        runs.iter().all(|n| !n.to_string_lossy().starts_with('.')),
        "{after}: half-written run records {runs:?}"
    );
    let (code, _, err) = ws.cmd("status", &["--verify"]);
    assert_eq!(code, 0, "{after}: pipe status failed: {err}");
}

fn assert_clear_failure(code: i32, err: &str, os_error: &str, after: &str) {
    assert_eq!(code, 1, "{after}: {err}");
    assert!(!err.contains("panicked"), "{after}: {err}");
    assert!(
        err.contains(".pipe/") && err.contains(os_error),
        "{after}: the message must name the path and `{os_error}`:\n{err}"
    );
}

#[test]
fn a_full_disk_fails_clearly_publishes_nothing_partial_and_the_next_run_completes() {
    let reference = Workspace::new(PIPELINE);
    reference.run_ok(&[]);

    let ws = Workspace::new(PIPELINE);
    let mut failures = 0;
    let mut partial = false;
    // 0: even the lock file cannot be written; then a table, a manifest or a run record
    // crosses the limit; the last limits let everything through.
    for limit in [0, 16, 600, 1_500, 4_000, 50_000, 1 << 20] {
        let after = format!("a run limited to {limit}-byte files");
        let before = ws.entries();
        let (code, err) = run_limited(&ws, limit, &[]);
        if code != 0 {
            failures += 1;
            assert_clear_failure(code, &err, "File too large (os error 27)", &after);
            // Some stages may have finished before the failure; none is half there.
            partial |= !ws.entries().is_empty() && ws.entries().len() < 3;
        }
        assert!(
            before.iter().all(|k| ws.entries().contains(k)),
            "{after}: an entry disappeared"
        );
        assert_cache_consistent(&ws, &after);
    }
    assert!(failures >= 3, "only {failures} limits made the run fail");
    assert!(
        partial,
        "no limit let the small stage through but not the big one"
    );

    // A normal run completes, with the uninterrupted run's results.
    ws.run_ok(&[]);
    assert_cache_consistent(&ws, "the normal run");
    assert_eq!(ws.numbers("map"), reference.numbers("map"));
    assert_eq!(ws.entries(), reference.entries());
    ws.run_ok(&[]);
    assert!(ws.last_run().iter().all(|(_, o)| *o == Outcome::Cached));
}

/// Whether this process may write into a directory whatever its mode says (root, or
/// CAP_DAC_OVERRIDE), found by trying.
fn permissions_are_ignored(dir: &std::path::Path) -> bool {
    let probe = tempfile::tempdir_in(dir).unwrap();
    fs::set_permissions(probe.path(), fs::Permissions::from_mode(0o555)).unwrap();
    let writable = fs::write(probe.path().join("probe"), b"x").is_ok();
    fs::set_permissions(probe.path(), fs::Permissions::from_mode(0o755)).unwrap();
    writable
}

#[test]
fn an_unwritable_cache_directory_fails_clearly_and_publishes_nothing() {
    let ws = Workspace::new(PIPELINE);
    ws.run_ok(&["--until", "small"]);
    let entries = ws.entries();
    let dirs = [ws.cache().join("objects"), ws.cache().join("tmp")];
    let (code, err, os_error) = if permissions_are_ignored(ws.dir()) {
        // Running as root (as CI containers often do): modes do not stop us, so make every
        // write fail instead. Not skipped: the same guarantee is checked another way.
        let (code, err) = run_limited(&ws, 0, &[]);
        (code, err, "File too large (os error 27)")
    } else {
        for d in &dirs {
            fs::set_permissions(d, fs::Permissions::from_mode(0o555)).unwrap();
        }
        let (code, _, err) = ws.run(&[]);
        for d in &dirs {
            fs::set_permissions(d, fs::Permissions::from_mode(0o755)).unwrap();
        }
        (code, err, "Permission denied (os error 13)")
    };
    assert_clear_failure(code, &err, os_error, "a run on a read-only cache");
    assert_eq!(ws.entries(), entries, "the failed run changed objects/");
    assert_cache_consistent(&ws, "a run on a read-only cache");

    ws.run_ok(&[]);
    assert_cache_consistent(&ws, "the normal run");
    assert!(ws.stage_is_fresh("map"));
}
