//! The runner's guarantees, exercised through the real `pipe` binary on small test stage kinds:
//! caching, selective re-runs, early cutoff, status explanations, failures, kills, corruption,
//! concurrency.

mod common;

use common::{Outcome, Workspace};
use std::{fs, process::Command, thread, time::Duration};

const CHAIN: &str = "
stages:
  a:
    uses: test_source
    params: {value: 5}
  b:
    uses: test_map
    inputs: {src: a}
  c:
    uses: test_source
    params: {value: 100}
  d:
    uses: test_map
    inputs: {src: c, extra: b}
";

#[test]
fn second_run_is_all_cache_hits() {
    let ws = Workspace::new(CHAIN);
    ws.run_ok(&[]);
    assert!(ws.last_run().iter().all(|(_, o)| *o == Outcome::Ran));
    let out = ws.run_ok(&[]);
    for (stage, o) in ws.last_run() {
        assert_eq!(o, Outcome::Cached, "stage {stage} re-ran:\n{out}");
    }
    assert!(out.contains("cached"), "{out}");
}

#[test]
fn one_param_change_reruns_exactly_that_stage_and_downstream() {
    let ws = Workspace::new(CHAIN);
    ws.run_ok(&[]);
    ws.run_ok(&["--set", "c.value=101"]);
    let r = ws.last_run_map();
    assert_eq!(r["a"], Outcome::Cached);
    assert_eq!(r["b"], Outcome::Cached);
    assert_eq!(r["c"], Outcome::Ran);
    assert_eq!(r["d"], Outcome::Ran);
    // The output reflects the change: d = c*2 + b = (101..)*2 + (5..)*2
    assert_eq!(ws.numbers("d"), vec![212, 216, 220]);
}

#[test]
fn unrelated_changes_rerun_nothing() {
    let ws = Workspace::new(CHAIN);
    ws.run_ok(&[]);
    // Reorder stages, add comments and a new independent stage, spell defaults out.
    ws.write_pipeline(
        "
# a comment
stages:
  c:
    uses: test_source
    params: {value: 100, rows: 3}   # rows is the default
  e:
    uses: test_source
  d:
    uses: test_map
    inputs: {extra: b, src: c}
  b:
    uses: test_map
    inputs: {src: a}
    params: {factor: 2, modulo: null}
  a:
    uses: test_source
    params: {value: 5}
",
    );
    ws.run_ok(&[]);
    let r = ws.last_run_map();
    assert_eq!(r["e"], Outcome::Ran);
    for s in ["a", "b", "c", "d"] {
        assert_eq!(r[s], Outcome::Cached, "stage {s}");
    }
}

#[test]
fn identical_upstream_outputs_cut_off_downstream() {
    let ws = Workspace::new(CHAIN);
    ws.run_ok(&[]);
    ws.run_ok(&["--set", "a.salt=new"]);
    let r = ws.last_run_map();
    assert_eq!(r["a"], Outcome::Ran, "a's key changed");
    assert_eq!(
        r["b"],
        Outcome::Cached,
        "a wrote identical bytes: b must not re-run"
    );
    assert_eq!(r["d"], Outcome::Cached);
}

#[test]
fn until_only_and_force_select_stages() {
    let ws = Workspace::new(CHAIN);
    ws.run_ok(&["--until", "b"]);
    let r = ws.last_run_map();
    assert_eq!(r.keys().cloned().collect::<Vec<_>>(), vec!["a", "b"]);
    assert!(!ws.stage_is_fresh("c"));

    // --only on a stage whose inputs are not up to date is a usage error.
    let (code, _, err) = ws.run(&["--only", "d"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("not up to date"), "{err}");

    ws.run_ok(&["--only", "c"]);
    assert_eq!(ws.last_run_map().len(), 1);
    ws.run_ok(&["--only", "d"]);
    assert_eq!(ws.last_run_map()["d"], Outcome::Ran);

    ws.run_ok(&["--force", "b"]);
    let r = ws.last_run_map();
    assert_eq!(r["b"], Outcome::Ran);
    assert_eq!(r["a"], Outcome::Cached);
    assert_eq!(r["d"], Outcome::Cached, "forced b wrote the same bytes");

    ws.run_ok(&["--force-all"]);
    assert!(ws.last_run().iter().all(|(_, o)| *o == Outcome::Ran));

    let (code, _, err) = ws.run(&["--until", "nope"]);
    assert_eq!(code, 2);
    assert!(err.contains("no stage named `nope`"), "{err}");
}

#[test]
fn status_explains_every_kind_of_staleness() {
    let ws = Workspace::new(CHAIN);
    let st = ws.status(&[]);
    assert!(ws.status_line(&st, "a").contains("never run"), "{st}");
    assert!(
        ws.status_line(&st, "b").contains("waits on stale input"),
        "{st}"
    );
    ws.run_ok(&[]);
    let st = ws.status(&[]);
    for s in ["a", "b", "c", "d"] {
        assert!(ws.status_line(&st, s).contains("fresh"), "{st}");
    }

    let st = ws.status(&["--set", "a.value=7"]);
    assert!(
        ws.status_line(&st, "a").contains("param `a.value` 5 -> 7"),
        "{st}"
    );
    ws.run_ok(&["--set", "a.value=7", "--until", "a"]);
    let st = ws.status(&["--set", "a.value=7"]);
    assert!(
        ws.status_line(&st, "b")
            .contains("input `src` changed (stage `a` wrote different outputs)"),
        "{st}"
    );

    // A record from an older code version.
    let c_key = ws.stage_key("c");
    let rec_path = ws.cache().join("runs/c.json");
    let mut rec: serde_json::Value = serde_json::from_slice(&fs::read(&rec_path).unwrap()).unwrap();
    rec["version"] = 0.into();
    rec["key"] = "0000".into();
    fs::write(&rec_path, serde_json::to_vec(&rec).unwrap()).unwrap();
    fs::remove_dir_all(ws.cache().join("objects").join(&c_key)).unwrap();
    let st = ws.status(&[]);
    assert!(
        ws.status_line(&st, "c")
            .contains("code version of kind `test_source` 0 -> 1"),
        "{st}"
    );

    // Corruption.
    ws.run_ok(&[]);
    ws.corrupt_file("d", |b| {
        let i = b.len() / 2;
        b[i] ^= 1;
    });
    let st = ws.status(&[]);
    assert!(ws.status_line(&st, "d").contains("CORRUPT"), "{st}");
    assert!(ws.status_line(&st, "d").contains("blake3"), "{st}");
}

#[test]
fn corrupt_entries_are_detected_moved_aside_and_recomputed() {
    type Damage = fn(&mut Vec<u8>);
    let cases: [(&str, Damage); 3] = [
        ("flipped byte", |b| {
            let i = b.len() / 3;
            b[i] ^= 0x10
        }),
        ("truncated", |b| b.truncate(b.len() - 5)),
        ("emptied", |b| b.clear()),
    ];
    for (what, damage) in cases {
        let ws = Workspace::new(CHAIN);
        ws.run_ok(&[]);
        let before = ws.numbers("b");
        ws.corrupt_file("b", damage);
        let st = ws.status(&[]);
        assert!(ws.status_line(&st, "b").contains("CORRUPT"), "{what}: {st}");
        let out = ws.run_ok(&[]);
        let r = ws.last_run_map();
        assert_eq!(r["b"], Outcome::Ran, "{what}: corrupt entry reused\n{out}");
        assert_eq!(ws.numbers("b"), before, "{what}");
        assert_eq!(
            fs::read_dir(ws.cache().join("trash")).unwrap().count(),
            1,
            "{what}"
        );
    }
    // A deleted file and a deleted manifest.
    let ws = Workspace::new(CHAIN);
    ws.run_ok(&[]);
    let dir = ws.cache().join("objects").join(ws.stage_key("a"));
    fs::remove_file(dir.join("test_numbers.parquet")).unwrap();
    ws.run_ok(&[]);
    assert_eq!(ws.last_run_map()["a"], Outcome::Ran);
    let dir = ws.cache().join("objects").join(ws.stage_key("a"));
    fs::remove_file(dir.join("manifest.json")).unwrap();
    ws.run_ok(&[]);
    assert_eq!(ws.last_run_map()["a"], Outcome::Ran);
}

/// Flips one byte of `file` in place (same inode, same size) and puts its mtime back.
fn flip_in_place(file: &std::path::Path) {
    use std::io::{Read, Seek, SeekFrom, Write};
    let mtime = fs::metadata(file).unwrap().modified().unwrap();
    let mut f = fs::File::options()
        .read(true)
        .write(true)
        .open(file)
        .unwrap();
    let at = f.metadata().unwrap().len() / 3;
    let mut byte = [0u8];
    f.seek(SeekFrom::Start(at)).unwrap();
    f.read_exact(&mut byte).unwrap();
    f.seek(SeekFrom::Start(at)).unwrap();
    f.write_all(&[byte[0] ^ 0x10]).unwrap();
    f.set_modified(mtime).unwrap();
}

#[test]
fn bit_rot_is_found_reported_and_repaired() {
    let ws = Workspace::new(CHAIN);
    ws.run_ok(&[]);
    let before = ws.numbers("b");
    let parquet = |stage: &str| {
        ws.cache()
            .join("objects")
            .join(ws.stage_key(stage))
            .join("test_numbers.parquet")
    };
    let trash = || fs::read_dir(ws.cache().join("trash")).map_or(0, |d| d.count());

    // A write whose mtime was put back: the cheap check sees the ctime change.
    flip_in_place(&parquet("b"));
    let st = ws.status(&[]);
    assert!(ws.status_line(&st, "b").contains("CORRUPT"), "{st}");
    ws.run_ok(&[]);
    assert_eq!(ws.last_run_map()["b"], Outcome::Ran);
    assert_eq!((ws.numbers("b"), trash()), (before.clone(), 1));

    // Rot no stamp shows (as on a failing disk; simulated by recording the damaged file's
    // stamp as verified): found by the first stage that reads the entry, which recomputes it
    // and then runs.
    let rot = |ws: &Workspace| {
        use std::os::unix::fs::MetadataExt;
        let file = parquet("b");
        flip_in_place(&file);
        let m = fs::metadata(&file).unwrap();
        let memo_path = ws.cache().join("state/verified.json");
        let mut memo: serde_json::Value =
            serde_json::from_slice(&fs::read(&memo_path).unwrap()).unwrap();
        let name = format!("{}/test_numbers.parquet", ws.stage_key("b"));
        memo[name] = serde_json::json!([
            m.len(),
            m.mtime() * 1_000_000_000 + m.mtime_nsec(),
            m.ino(),
            m.ctime() * 1_000_000_000 + m.ctime_nsec()
        ]);
        fs::write(&memo_path, serde_json::to_vec(&memo).unwrap()).unwrap();
    };
    rot(&ws);
    let st = ws.status(&[]);
    assert!(
        ws.status_line(&st, "b").contains("fresh"),
        "invisible to the cheap check: {st}"
    );
    let (code, out, err) = ws.run(&["--force", "d"]);
    assert_eq!(code, 0, "{out}{err}");
    assert!(
        err.contains("cache entry corrupt") && err.contains("stage `b`"),
        "{err}"
    );
    let r = ws.last_run_map();
    assert_eq!((r["b"], r["d"]), (Outcome::Ran, Outcome::Ran), "{out}");
    assert_eq!((ws.numbers("b"), trash()), (before.clone(), 2));
    ws.assert_every_entry_verifies("the repair");

    // `show` and `export` read it too: they move it aside and say what recomputes it.
    rot(&ws);
    let (code, _, err) = ws.cmd("show", &["b"]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("corrupt") && err.contains("pipe run --until b"),
        "{err}"
    );
    assert_eq!(trash(), 3);
    ws.run_ok(&[]);
    assert_eq!(ws.last_run_map()["b"], Outcome::Ran);
    assert_eq!(ws.numbers("b"), before);
}

#[test]
fn a_failing_stage_publishes_nothing_and_skips_dependents() {
    let ws = Workspace::new(CHAIN);
    let (code, out, err) = ws.run(&["--set", "b.fail=true"]);
    assert_eq!(code, 1, "{out}{err}");
    assert!(err.contains("stage `b` (kind `test_map`) failed"), "{err}");
    let r = ws.last_run_map();
    assert_eq!(r["a"], Outcome::Ran);
    assert_eq!(r["b"], Outcome::Failed);
    assert_eq!(r["d"], Outcome::Skipped);
    // Only a's entry exists (and c's if it ran before b failed).
    assert_eq!(
        ws.entries().len(),
        ws.last_run()
            .iter()
            .filter(|(_, o)| *o == Outcome::Ran)
            .count()
    );
    assert_eq!(fs::read_dir(ws.cache().join("tmp")).unwrap().count(), 0);

    // --keep-going still runs what does not depend on the failure.
    let (code, ..) = ws.run(&["--set", "b.fail=true", "--keep-going"]);
    assert_eq!(code, 1);
    let r = ws.last_run_map();
    assert_ne!(r["c"], Outcome::Skipped);
    assert_eq!(r["d"], Outcome::Skipped);
}

#[test]
fn sigkill_mid_stage_leaves_no_partial_entry_and_the_next_run_completes() {
    let ws = Workspace::new(CHAIN);
    ws.run_ok(&["--until", "a"]);
    let entries_before = ws.entries();
    let mut child = ws.spawn_until(&["--set", "b.sleep_ms=5000"], "running `b`");
    thread::sleep(Duration::from_millis(300));
    child.kill().unwrap();
    child.wait().unwrap();
    assert_eq!(
        ws.entries(),
        entries_before,
        "a killed run published something"
    );
    // The lock died with the process: the next run neither waits nor fails.
    let (code, out, err) = ws.run(&["--no-wait"]);
    assert_eq!(code, 0, "{out}{err}");
    assert_eq!(ws.numbers("d"), vec![210, 214, 218]);
    assert_eq!(fs::read_dir(ws.cache().join("tmp")).unwrap().count(), 0);
}

#[test]
fn concurrent_runs_serialise_and_do_not_corrupt_the_cache() {
    let ws = Workspace::new(CHAIN);
    let slow = ["--set", "a.sleep_ms=600"];
    let kids: Vec<_> = (0..4).map(|_| ws.spawn(&slow)).collect();
    for k in kids {
        let out = k.wait_with_output().unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    for key in ws.entries() {
        assert_eq!(
            pipe::cli::entry_state(&pipe::store::Store::open_existing(&ws.cache()), &key),
            "valid"
        );
    }
    assert_eq!(ws.numbers("d"), vec![210, 214, 218]);

    // --no-wait fails with a clear message while another run holds the lock of an entry it
    // needs. (`running` is printed after the lock is taken.)
    let busy = ["--force", "a", "--set", "a.sleep_ms=1500"];
    let holder = ws.spawn_until(&busy, "running `a`");
    let (code, _, err) = ws.run(&[&["--no-wait"][..], &busy].concat());
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("is locked by process"), "{err}");
    assert!(holder.wait_with_output().unwrap().status.success());
}

#[test]
fn export_writes_the_stage_files() {
    let ws = Workspace::new(CHAIN);
    let (code, _, err) = ws.cmd("export", &["b", "--to", "out"]);
    assert_eq!(code, 2, "exporting a stale stage is a usage error");
    assert!(err.contains("run `pipe run --until b` first"), "{err}");
    ws.run_ok(&[]);
    let (code, out, err) = ws.cmd("export", &["b", "--to", "out"]);
    assert_eq!(code, 0, "{out}{err}");
    assert_eq!(
        fs::read_to_string(ws.dir().join("out/numbers.txt")).unwrap(),
        "10\n12\n14\n"
    );
}

#[test]
fn jobs_run_independent_stages_at_once() {
    let ws = Workspace::new(
        "stages:\n  s1:\n    uses: test_source\n    params: {sleep_ms: 800}\n  s2:\n    uses: test_source\n    params: {value: 9, sleep_ms: 800}\n  m:\n    uses: test_map\n    inputs: {src: s1, extra: s2}\n",
    );
    ws.run_ok(&["--jobs", "2"]);
    assert_eq!(ws.numbers("m"), vec![11, 14, 17]);
    // The two sources' stage bodies overlapped in time (from their manifests).
    let span = |s: &str| {
        let m: serde_json::Value = serde_json::from_slice(
            &fs::read(
                ws.cache()
                    .join("objects")
                    .join(ws.stage_key(s))
                    .join("manifest.json"),
            )
            .unwrap(),
        )
        .unwrap();
        (
            m["started"].as_f64().unwrap(),
            m["finished"].as_f64().unwrap(),
        )
    };
    let (a0, a1) = span("s1");
    let (b0, b1) = span("s2");
    assert!(
        a0 < b1 && b0 < a1,
        "s1 {a0}..{a1} and s2 {b0}..{b1} did not overlap"
    );
}

#[test]
fn editing_an_external_input_file_reruns_exactly_what_depends_on_it() {
    let ws = Workspace::new(
        "stages:\n  f:\n    uses: test_file\n    params: {path: numbers.txt}\n  m:\n    uses: test_map\n    inputs: {src: f}\n  s:\n    uses: test_source\n",
    );
    let file = ws.dir().join("numbers.txt");
    fs::write(&file, "1\n2\n").unwrap();
    ws.run_ok(&[]);
    ws.run_ok(&[]);
    assert!(ws.last_run().iter().all(|(_, o)| *o == Outcome::Cached));
    // Same content, new mtime: re-hashed, still cached.
    thread::sleep(Duration::from_millis(20));
    fs::write(&file, "1\n2\n").unwrap();
    ws.run_ok(&[]);
    assert!(ws.last_run().iter().all(|(_, o)| *o == Outcome::Cached));
    fs::write(&file, "1\n3\n").unwrap();
    let st = ws.status(&[]);
    assert!(
        ws.status_line(&st, "f").contains("its input files changed"),
        "{st}"
    );
    ws.run_ok(&[]);
    let r = ws.last_run_map();
    assert_eq!(
        (r["f"], r["m"], r["s"]),
        (Outcome::Ran, Outcome::Ran, Outcome::Cached)
    );
    assert_eq!(ws.numbers("m"), vec![2, 6]);
}

#[test]
fn an_input_that_is_not_a_regular_file_is_an_error_at_once() {
    let ws =
        Workspace::new("stages:\n  f:\n    uses: test_file\n    params: {path: numbers.txt}\n");
    // A directory (think `--set scene.bboxes=.` on a data set root): never hashed.
    fs::create_dir_all(ws.dir().join("big/nested")).unwrap();
    fs::write(ws.dir().join("big/nested/x.bin"), "x").unwrap();
    // A FIFO: reading it would block forever.
    let fifo = ws.dir().join("pipe.fifo");
    let made = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap();
    assert!(made.success());
    for (value, what) in [("big", "is a directory"), ("pipe.fifo", "is a FIFO")] {
        let set = format!("f.path={value}");
        for command in ["run", "status"] {
            let child = ws.spawn_command(command, &["--set", &set]);
            let out = common::wait_with_timeout(child, Duration::from_secs(60))
                .unwrap_or_else(|| panic!("`pipe {command} --set {set}` hangs"));
            let err = String::from_utf8_lossy(&out.stderr);
            assert_eq!(out.status.code(), Some(1), "{command} {set}: {err}");
            assert!(
                err.contains(what) && err.contains(value) && err.contains("stage `f`"),
                "{command} {set}: {err}"
            );
        }
    }
    assert!(ws.entries().is_empty());
}

#[test]
fn a_dry_run_lists_every_stage_that_would_run_in_order() {
    let ws = Workspace::new(CHAIN);
    let (code, out, err) = ws.run(&["--dry-run"]);
    assert_eq!(code, 0, "{out}{err}");
    let lines: Vec<&str> = out.lines().filter(|l| l.contains("would run")).collect();
    let names: Vec<&str> = lines
        .iter()
        .map(|l| l.split_whitespace().next().unwrap())
        .collect();
    assert_eq!(names, ["a", "b", "c", "d"], "{out}");
    assert!(lines[0].contains("never run"), "{out}");
    assert!(lines[1].contains("upstream `a` would run first"), "{out}");
    assert!(!out.contains("skipped") && !out.contains("failed"), "{out}");
    assert!(ws.entries().is_empty(), "a dry run computes nothing");
    // After a real run, a param change: the changed stage and what is below it.
    ws.run_ok(&[]);
    let (code, out, _) = ws.run(&["--dry-run", "--set", "a.value=6"]);
    assert_eq!(code, 0, "{out}");
    assert!(
        out.lines()
            .any(|l| l.starts_with('a') && l.contains("param")),
        "{out}"
    );
    assert!(out.contains("upstream `a` would run first"), "{out}");
}

#[test]
fn an_unusable_cache_directory_is_a_clear_error() {
    let ws = Workspace::new("cache: not-a-dir/cache\nstages:\n  a:\n    uses: test_source\n");
    fs::write(ws.dir().join("not-a-dir"), "a file").unwrap();
    let (code, _, err) = ws.run(&[]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("cannot create cache directory") && err.contains("not-a-dir"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn gc_removes_unreachable_entries() {
    let ws = Workspace::new(CHAIN);
    ws.run_ok(&[]);
    ws.run_ok(&["--set", "a.value=9"]);
    let n = ws.entries().len();
    let out = Command::new(common::PIPE)
        .args(["gc", "--keep-all-runs"])
        .current_dir(ws.dir())
        .output()
        .unwrap();
    assert!(out.status.success());
    assert_eq!(ws.entries().len(), n);
    let out = Command::new(common::PIPE)
        .args(["gc"])
        .current_dir(ws.dir())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(
        ws.entries().len(),
        4,
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
    ws.run_ok(&[]);
    assert!(ws.last_run().iter().all(|(_, o)| *o == Outcome::Cached));
}

#[test]
fn schema_mismatch_between_code_and_data_schema_is_caught() {
    // Every table a real stage kind declares has a schema file, and every file parses.
    for kind in stages::kinds::registry() {
        for t in kind.outputs() {
            assert!(
                stages::schema::get(t).is_some(),
                "kind {} writes {t} without data_schema/{t}.json",
                kind.kind()
            );
        }
    }
    let bad = arrow::datatypes::Schema::new(vec![arrow::datatypes::Field::new(
        "value",
        arrow::datatypes::DataType::Int32,
        false,
    )]);
    let e = stages::schema::check("test_numbers", &bad).unwrap_err();
    assert!(
        e.contains("does not match data_schema/test_numbers.json"),
        "{e}"
    );
}

#[test]
fn a_long_stage_writes_progress_lines_when_stderr_is_not_a_terminal() {
    // `output()` pipes stderr, as Slurm, nohup and CI do: no bars, but lines with the step,
    // rate, elapsed time and ETA, and a closing line.
    let ws = Workspace::new("stages:\n  slow:\n    uses: test_source\n    params: {sleep_ms: 3000}\n  quick:\n    uses: test_source\n    params: {value: 2}\n");
    let (code, out, err) = ws.run(&[]);
    assert_eq!(code, 0, "{out}\n{err}");
    let lines: Vec<&str> = err
        .lines()
        .filter(|l| l.trim_start().starts_with("slow: "))
        .collect();
    assert!(
        lines.len() >= 2,
        "expected progress lines for `slow`:\n{err}"
    );
    let mid = lines[0];
    for part in ["/300 (", "/s, elapsed 0:0", ", ETA 0:0", "| sleeping"] {
        assert!(mid.contains(part), "`{part}` missing from `{mid}`:\n{err}");
    }
    let last = lines.last().unwrap();
    assert!(
        last.contains("300/300 (100%)") && last.contains("done"),
        "{err}"
    );
    assert!(
        !err.lines().any(|l| l.trim_start().starts_with("quick: ")),
        "a stage too quick for a line printed one:\n{err}"
    );
    assert!(!err.contains('\u{1b}'), "terminal escapes in a log:\n{err}");
}
