//! A cache shared by people and pipelines: a read-only cache still serves a fully cached run,
//! `pipe gc` keeps what any pipeline that ran in the cache reaches, and a run survives the
//! layout being removed under it or a lock holder being killed.

mod common;

use std::{
    fs,
    os::unix::fs::PermissionsExt,
    path::Path,
    process::Command,
    time::{Duration, Instant},
};

use common::{wait_with_timeout, Workspace};

const PIPELINE: &str = "
stages:
  small:
    uses: test_source
  big:
    uses: test_source
    params: {rows: 2000, value: 7}
  map:
    uses: test_map
    inputs: {src: big}
";

const OTHER: &str = "
stages:
  other:
    uses: test_source
    params: {value: 3}
  tail:
    uses: test_map
    inputs: {src: other}
";

/// Sets the mode of everything under `dir` (directories `dirs`, files `files`).
fn chmod_tree(dir: &Path, dirs: u32, files: u32) {
    for e in fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            chmod_tree(&p, dirs, files);
        } else {
            fs::set_permissions(&p, fs::Permissions::from_mode(files)).unwrap();
        }
    }
    fs::set_permissions(dir, fs::Permissions::from_mode(dirs)).unwrap();
}

/// Whether a private mount namespace can mount `dir` read-only (as root).
fn read_only_mounts_work(dir: &Path) -> bool {
    Command::new("unshare")
        .args(["-m", "sh", "-c"])
        .arg(
            r#"mount --bind "$1" "$1" && mount -o remount,bind,ro "$1" "$1" && ! touch "$1/probe""#,
        )
        .args(["sh", &dir.display().to_string()])
        .output()
        .is_ok_and(|o| o.status.success())
}

/// `pipe ARGS` with the workspace's cache read-only: a read-only bind mount in a private mount
/// namespace (as root, where modes do not stop writes), or write permission removed (otherwise).
/// `None` (the test is skipped, but not under CI) where neither can be arranged.
fn on_read_only_cache(ws: &Workspace, args: &[&str]) -> Option<(i32, String, String)> {
    let cache = ws.cache();
    let probe = tempfile::tempdir_in(ws.dir()).unwrap();
    fs::set_permissions(probe.path(), fs::Permissions::from_mode(0o555)).unwrap();
    let modes_hold = fs::write(probe.path().join("x"), b"x").is_err();
    fs::set_permissions(probe.path(), fs::Permissions::from_mode(0o755)).unwrap();
    let out = if modes_hold {
        chmod_tree(&cache, 0o555, 0o444);
        let out = Command::new(common::PIPE)
            .args(args)
            .current_dir(ws.dir())
            .output();
        chmod_tree(&cache, 0o755, 0o644);
        out.unwrap()
    } else if read_only_mounts_work(&cache) {
        Command::new("unshare")
            .args(["-m", "sh", "-c"])
            .arg(r#"mount --bind "$1" "$1" && mount -o remount,bind,ro "$1" "$1" && shift && exec "$@""#)
            .args(["sh", &cache.display().to_string(), common::PIPE])
            .args(args)
            .current_dir(ws.dir())
            .output()
            .unwrap()
    } else {
        assert!(
            std::env::var("CI").as_deref() != Ok("true"),
            "CI must be able to make a read-only cache (unshare -m as root, or a non-root user)"
        );
        eprintln!("skipped: neither file modes nor a read-only bind mount can be arranged here");
        return None;
    };
    Some((
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    ))
}

#[test]
fn a_fully_cached_run_works_on_a_read_only_cache_and_a_stale_stage_says_so() {
    let ws = Workspace::new(PIPELINE);
    ws.run_ok(&[]);
    let entries = ws.entries();
    let Some((code, out, err)) = on_read_only_cache(&ws, &["run"]) else {
        return;
    };
    assert_eq!(code, 0, "{out}\n{err}");
    let results: Vec<&str> = out
        .lines()
        .filter(|l| ["small", "big", "map"].iter().any(|s| l.starts_with(s)))
        .collect();
    assert_eq!(results.len(), 3, "{out}");
    assert!(results.iter().all(|l| l.contains("cached")), "{out}");

    let (code, out, err) = on_read_only_cache(&ws, &["run", "--set", "big.value=9"]).unwrap();
    assert_eq!(code, 1, "{out}\n{err}");
    assert!(!err.contains("panicked"), "{err}");
    for part in ["stage `big` would have to run", "is read-only", "--cache"] {
        assert!(err.contains(part), "`{part}` missing:\n{err}");
    }
    assert_eq!(ws.entries(), entries);
    ws.assert_every_entry_verifies("runs on a read-only cache");
    ws.run_ok(&[]);
}

fn gc(ws: &Workspace, args: &[&str]) -> String {
    let (code, out, err) = ws.cmd("gc", args);
    assert_eq!(code, 0, "{out}\n{err}");
    out
}

#[test]
fn gc_keeps_what_every_pipeline_that_ran_in_the_cache_reaches() {
    let ws = Workspace::new(PIPELINE);
    ws.run_ok(&[]);
    let other = ws.dir().join("other.yaml");
    fs::write(&other, OTHER).unwrap();
    ws.run_ok(&["-f", "other.yaml"]);
    assert_eq!(ws.entries().len(), 5);

    // Another pipeline's gc: everything is someone's current work.
    let out = gc(&ws, &["-f", "other.yaml"]);
    assert!(out.contains("removed 0 entries"), "{out}");
    assert!(out.contains("pipeline.yaml: reaches 3 entries"), "{out}");
    assert_eq!(ws.entries().len(), 5);

    // other.yaml changes: its old entries are what nobody reaches, listed before removal.
    fs::write(&other, OTHER.replace("value: 3", "value: 4")).unwrap();
    ws.run_ok(&["-f", "other.yaml"]);
    assert_eq!(ws.entries().len(), 7);
    let out = gc(&ws, &["--dry-run"]);
    assert!(out.contains("would remove 2 entries"), "{out}");
    assert!(
        out.contains("stage `other` (test_source v") && out.contains("stage `tail` (test_map v"),
        "{out}"
    );
    assert_eq!(ws.entries().len(), 7, "a dry run removed something");
    let out = gc(&ws, &[]);
    assert!(out.contains("removed 2 entries"), "{out}");
    assert_eq!(ws.entries().len(), 5);

    // A pipeline file that cannot be read here (a colleague's, moved away): its last run's
    // entries stay.
    fs::rename(&other, ws.dir().join("moved.yaml")).unwrap();
    let out = gc(&ws, &[]);
    assert!(out.contains("cannot be read or resolved here"), "{out}");
    assert!(out.contains("keeping the 2 entries its last run"), "{out}");
    assert_eq!(ws.entries().len(), 5);

    // Only when told: everything the -f pipeline does not reach goes.
    let out = gc(&ws, &["--only-this-pipeline"]);
    assert!(out.contains("removed 2 entries"), "{out}");
    assert_eq!(ws.entries().len(), 3);
    ws.run_ok(&[]);
    assert!(ws
        .last_run()
        .iter()
        .all(|(_, o)| *o == common::Outcome::Cached));
}

#[test]
fn a_run_goes_on_when_the_objects_directory_is_removed_under_it() {
    let ws =
        Workspace::new("stages:\n  slow:\n    uses: test_source\n    params: {sleep_ms: 1500}\n");
    ws.run_ok(&["--set", "slow.sleep_ms=0"]);
    let child = ws.spawn_until(&[], "running `slow`");
    fs::remove_dir_all(ws.cache().join("objects")).unwrap();
    let out = wait_with_timeout(child, Duration::from_secs(120)).expect("the run hung");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(ws.stage_is_fresh("slow"));
    ws.assert_every_entry_verifies("objects/ removed during a run");
}

#[test]
fn a_run_that_takes_over_a_killed_holders_lock_removes_its_temporary_entry() {
    let ws =
        Workspace::new("stages:\n  slow:\n    uses: test_source\n    params: {sleep_ms: 4000}\n");
    let mut holder = ws.spawn_until(&[], "running `slow`");
    let tmp = ws.cache().join("tmp");
    let names = |dir: &Path| -> Vec<String> {
        fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect()
    };
    // The holder creates its entry under tmp/ just after saying it runs.
    let t0 = Instant::now();
    while names(&tmp).is_empty() && t0.elapsed() < Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(20));
    }
    let holders: Vec<String> = names(&tmp);
    assert!(
        !holders.is_empty(),
        "the holder writes its entry under tmp/"
    );
    let waiter = ws.spawn_until(&[], "waiting for process");
    holder.kill().unwrap();
    holder.wait().unwrap();
    let t0 = Instant::now();
    let out = wait_with_timeout(waiter, Duration::from_secs(120)).expect("the waiter hung");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        t0.elapsed() < Duration::from_secs(60),
        "the lock was not broken at once"
    );
    let left: Vec<String> = names(&tmp)
        .into_iter()
        .filter(|n| holders.contains(n))
        .collect();
    assert!(
        left.is_empty(),
        "the killed holder's {left:?} survive in tmp/"
    );
    assert!(ws.stage_is_fresh("slow"));
}

#[test]
fn gc_keeps_the_last_run_of_a_pipeline_whose_data_is_not_here() {
    let ws = Workspace::new(PIPELINE);
    ws.run_ok(&[]);
    let data = ws.dir().join("data");
    fs::create_dir_all(&data).unwrap();
    fs::write(data.join("numbers.txt"), "1\n2\n").unwrap();
    fs::write(
        data.join("theirs.yaml"),
        "cache: ../.pipe\nstages:\n  f:\n    uses: test_file\n    params: {path: data/numbers.txt}\n",
    )
    .unwrap();
    ws.run_ok(&["-f", "data/theirs.yaml"]);
    assert_eq!(ws.entries().len(), 4);
    // Their data is on another machine now: their pipeline cannot be resolved here.
    fs::remove_file(data.join("numbers.txt")).unwrap();
    let out = gc(&ws, &[]);
    assert!(
        out.contains("theirs.yaml: cannot be read or resolved here"),
        "{out}"
    );
    assert!(out.contains("keeping the 1 entries its last run"), "{out}");
    assert_eq!(ws.entries().len(), 4);
}
