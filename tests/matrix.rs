//! Scene matrices: expansion into per-scene stage instances, scene selection, dataset stages
//! that gather every scene, the local executor's worker processes and retries, and many runs
//! on one cache at once (per-entry locks, stale-lock take-over). Test stage kinds keep it fast;
//! one test runs the real tiny pipeline with the `aggregate` kind.

mod common;

use common::{wait_with_timeout, Outcome, Workspace, TINY_PIPELINE};
use std::{fs, time::Duration};

const MATRIX: &str = "
scenes:
  matrix:
    a.value: [1, 2]
    b.factor: [3, 10]
stages:
  a:
    uses: test_source
  b:
    uses: test_map
    inputs: {src: a}
dataset:
  all:
    uses: test_map
    inputs: {src: b}
    params: {factor: 1}
";

/// Keys of the entries of every stage instance in a run's report.
fn ran(ws: &Workspace) -> Vec<String> {
    ws.last_run()
        .into_iter()
        .filter(|(_, o)| *o == Outcome::Ran)
        .map(|(s, _)| s)
        .collect()
}

#[test]
fn a_matrix_expands_to_one_chain_per_scene_and_the_dataset_stage_gathers_them() {
    let ws = Workspace::new(MATRIX);
    let st = ws.status(&[]);
    for sc in [
        "value1-factor3",
        "value1-factor10",
        "value2-factor3",
        "value2-factor10",
    ] {
        assert!(
            ws.status_line(&st, &format!("a@{sc}"))
                .contains("never run"),
            "{st}"
        );
        assert!(ws.status_line(&st, sc).contains("stale"), "{st}");
    }
    ws.run_ok(&[]);
    // Scene by scene in matrix order, the first key varying slowest; `all` gathers them.
    let all = ws.numbers("all");
    assert_eq!(all, vec![3, 6, 9, 10, 20, 30, 6, 9, 12, 20, 30, 40]);
    // Two scenes share a's parameters (value 1): one entry, computed once.
    assert_eq!(ws.last_run_map()["a@value1-factor10"], Outcome::Cached);
    ws.run_ok(&[]);
    assert!(ran(&ws).is_empty(), "{:?}", ws.last_run());

    // A template override reaches every scene; an instance override only its scene.
    ws.run_ok(&["--set", "b@value2-factor10.modulo=7"]);
    assert_eq!(ran(&ws), vec!["b@value2-factor10", "all"]);
    ws.run_ok(&["--set", "a.rows=1"]);
    assert_eq!(ws.numbers("all"), vec![3, 10, 6, 20]);
    let (code, _, err) = ws.run(&["--set", "b@nope.factor=1"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("no such stage"), "{err}");
}

#[test]
fn scenes_are_selected_by_name_and_the_dataset_stage_waits_for_all() {
    let ws = Workspace::new(
        "
scenes:
  - name: small
    set: {a.value: 1}
  - name: big.one
    set: {a.value: 100, b.factor: 3}
stages:
  a:
    uses: test_source
  b:
    uses: test_map
    inputs: {src: a}
dataset:
  all:
    uses: test_map
    inputs: {src: b}
",
    );
    ws.run_ok(&["--scene", "big.one"]);
    assert_eq!(
        ws.last_run_map().keys().cloned().collect::<Vec<_>>(),
        vec!["a@big.one", "b@big.one"]
    );
    assert_eq!(ws.numbers("b@big.one"), vec![300, 303, 306]);
    let st = ws.status(&["--scene", "small"]);
    assert!(ws.status_line(&st, "a@small").contains("never run"), "{st}");
    assert!(!st.contains("big.one"), "{st}");
    let st = ws.status(&[]);
    assert!(ws.status_line(&st, "big.one").contains("fresh"), "{st}");
    assert!(
        ws.status_line(&st, "all").contains("waits on stale input"),
        "{st}"
    );

    let (code, _, err) = ws.run(&["--scene", "nope"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("no scene named `nope`"), "{err}");
    // `--until TEMPLATE` with a scene means that scene's instance.
    ws.run_ok(&["--scenes", "small", "--until", "a"]);
    assert_eq!(
        ws.last_run_map().keys().cloned().collect::<Vec<_>>(),
        vec!["a@small"]
    );
    ws.run_ok(&["--scenes", "all"]);
    assert_eq!(ran(&ws), vec!["b@small", "all"]);
}

#[test]
fn local_workers_run_scenes_in_parallel_and_retry_a_failing_scene() {
    let ws = Workspace::new(
        "
scenes:
  matrix:
    a.value: [1, 2, 3]
stages:
  a:
    uses: test_source
    params: {sleep_ms: 600}
  b:
    uses: test_map
    inputs: {src: a}
dataset:
  all:
    uses: test_map
    inputs: {src: b}
",
    );
    let t0 = std::time::Instant::now();
    let out = ws.run_ok(&["--jobs", "3"]);
    assert!(out.contains("3 scenes (3 ran, 0 cached)"), "{out}");
    assert_eq!(ws.numbers("all").len(), 9);
    assert!(t0.elapsed() < Duration::from_secs(10));
    let (code, out, err) = ws.run(&["--jobs", "3"]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("nothing submitted"), "{err}");
    assert!(out.contains("3 scenes (0 ran, 3 cached)"), "{out}");

    // One scene fails every time: retried, its log named, the dataset stage not run.
    let (code, out, err) = ws.run(&[
        "--jobs",
        "2",
        "--retries",
        "1",
        "--set",
        "b@value2.fail=true",
    ]);
    assert_eq!(code, 1, "{out}{err}");
    assert!(
        err.contains("scene value2: try 1 failed (exit code 1)"),
        "{err}"
    );
    assert!(err.contains("scene value2: FAILED after 2 tries"), "{err}");
    let log = err
        .lines()
        .find(|l| l.contains("FAILED after"))
        .and_then(|l| l.split("; log ").nth(1))
        .expect("the log file is named");
    let text = fs::read_to_string(log.trim()).unwrap();
    assert!(text.contains("test stage asked to fail"), "{text}");
    assert!(err.contains("the dataset stages did not run"), "{err}");
}

#[test]
fn runs_of_different_scenes_on_one_cache_overlap() {
    let ws = Workspace::new(
        "
scenes:
  matrix:
    a.value: [1, 2]
stages:
  a:
    uses: test_source
    params: {sleep_ms: 1500}
",
    );
    let t0 = std::time::Instant::now();
    let kids: Vec<_> = ["value1", "value2"]
        .iter()
        .map(|sc| ws.spawn(&["--scene", sc, "--no-wait"]))
        .collect();
    for k in kids {
        let out = wait_with_timeout(k, Duration::from_secs(60)).expect("run hung");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    // Sequential runs would take 3 s or more.
    assert!(
        t0.elapsed() < Duration::from_millis(2900),
        "{:?}",
        t0.elapsed()
    );
    assert!(ws.stage_is_fresh("a@value1") && ws.stage_is_fresh("a@value2"));
}

#[test]
fn runs_of_one_scene_compute_each_entry_once_and_a_dead_runs_lock_is_taken_over() {
    let ws = Workspace::new(
        "
scenes:
  - name: s
stages:
  a:
    uses: test_source
    params: {sleep_ms: 1200}
",
    );
    let first = ws.spawn_until(&["--scene", "s"], "running `a@s`");
    let second = ws.spawn(&["--scene", "s"]);
    let out = wait_with_timeout(second, Duration::from_secs(60)).expect("second run hung");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("waiting for process"), "{err}");
    assert!(
        String::from_utf8_lossy(&out.stdout).contains("computed meanwhile by another run"),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
    assert!(wait_with_timeout(first, Duration::from_secs(60))
        .unwrap()
        .status
        .success());
    assert_eq!(ws.entries().len(), 1);

    // SIGKILL a run while it holds an entry's lock: the next run breaks the stale lock at
    // once (same host, dead pid) and leaves no lock or temporary file behind.
    let mut killed = ws.spawn_until(&["--scene", "s", "--set", "a.value=9"], "running `a@s`");
    let locks = || -> Vec<String> {
        fs::read_dir(ws.cache().join("locks"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect()
    };
    assert_eq!(locks().len(), 1, "{:?}", locks());
    killed.kill().unwrap();
    killed.wait().unwrap();
    let (code, _, err) = ws.run(&["--scene", "s", "--set", "a.value=9", "--no-wait"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(ws.last_run_map()["a@s"], Outcome::Ran);
    assert!(locks().is_empty(), "{:?}", locks());
    assert_eq!(fs::read_dir(ws.cache().join("tmp")).unwrap().count(), 0);
    ws.assert_every_entry_verifies("a killed run and its successor");
}

#[test]
fn the_tiny_pipeline_as_a_two_scene_matrix_aggregates_and_exports_a_summary() {
    let stages = TINY_PIPELINE.replace("stages:\n", "");
    let ws = Workspace::new(&format!(
        "scenes:\n  matrix:\n    scene.seed: [1, 2]\nstages:\n{stages}dataset:\n  summary:\n    uses: aggregate\n    inputs: {{evaluate: evaluate}}\n"
    ));
    ws.run_ok(&[]);
    let (code, out, err) = ws.cmd("export", &["summary", "--to", "out"]);
    assert_eq!(code, 0, "{out}{err}");
    let md = fs::read_to_string(ws.dir().join("out/summary.md")).unwrap();
    assert!(md.contains("2 scenes: seed1, seed2"), "{md}");
    assert!(
        md.contains("| seed1 |") && md.contains("| **mean** |"),
        "{md}"
    );
    let json: serde_json::Value =
        serde_json::from_slice(&fs::read(ws.dir().join("out/summary.json")).unwrap()).unwrap();
    let ours = &json["methods"]["panoptic_nerf"];
    let per = |s: &str| ours["per_scene"][s]["miou"].as_f64().unwrap();
    let mean = ours["mean"]["miou"].as_f64().unwrap();
    assert!(
        (mean - (per("seed1") + per("seed2")) / 2.0).abs() < 1e-9,
        "{json}"
    );
    assert_ne!(
        per("seed1"),
        per("seed2"),
        "the two seeds gave the same scene"
    );
}

#[test]
fn a_dry_run_of_a_matrix_lists_every_stage_of_every_scene_and_exits_0() {
    let ws = Workspace::new(MATRIX);
    for jobs in ["1", "2"] {
        let (code, out, err) = ws.run(&["--dry-run", "-j", jobs]);
        assert_eq!(code, 0, "-j {jobs}: {out}{err}");
        let would: Vec<&str> = out
            .lines()
            .filter(|l| l.contains("would run"))
            .map(|l| l.split_whitespace().next().unwrap())
            .collect();
        // Every scene's stages, each after its inputs, then the dataset stage.
        for stage in ["a@value1-factor3", "b@value2-factor10", "all"] {
            assert!(
                would.contains(&stage),
                "-j {jobs}: {stage} missing in\n{out}"
            );
        }
        let pos = |s: &str| would.iter().position(|w| *w == s).unwrap();
        assert!(pos("a@value2-factor3") < pos("b@value2-factor3"), "{out}");
        assert_eq!(pos("all"), would.len() - 1, "{out}");
        assert!(!out.contains("skipped") && !out.contains("failed"), "{out}");
    }
    assert!(ws.entries().is_empty(), "a dry run computes nothing");
}
