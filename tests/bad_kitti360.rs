//! The bad-input corpus of the `kitti360_scene` loader, run through the real `pipe` binary.
//!
//! Every directory under tests/bad_inputs/kitti360_scene/ is one case: its files are laid over
//! a fresh copy of the hand-written fixture (tests/fixtures/kitti360, same relative paths), and
//! its `expect` file says what else to do and what must happen:
//!
//! ```text
//! exit: 1                                  the exit code (1: a stage failed, 2: bad usage)
//! copy: ../../kitti360/pose_nan.txt -> data_poses/seq_a/cam0_to_world.txt
//! remove: calibration/perspective.txt      delete a fixture file
//! set: scene.max_distance_m=0.5            a `--set` override
//! stderr: data_poses/seq_a/cam0_to_world.txt   must appear in stderr (file, element, problem)
//! ```
//!
//! `pipe run` (scene -> rays) must exit with that code within the time limit (no hang), print
//! every `stderr:` line, never panic, and publish nothing.

mod common;

use std::{
    fs,
    path::{Path, PathBuf},
    process::{Command, Stdio},
    time::{Duration, Instant},
};

/// Far above the ~0.1 s a case takes; a case that reaches it is reported as a hang.
const LIMIT: Duration = Duration::from_secs(30);

fn corpus() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/bad_inputs/kitti360_scene")
}

/// Lays the case's files over `root` (every file of the case directory but `expect`).
fn overlay(case: &Path, dir: &Path, root: &Path) {
    for e in fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        let rel = p.strip_prefix(case).unwrap();
        if p.is_dir() {
            overlay(case, &p, root);
        } else if rel != Path::new("expect") {
            let dest = root.join(rel);
            fs::create_dir_all(dest.parent().unwrap()).unwrap();
            fs::copy(&p, dest).unwrap();
        }
    }
}

/// A fixture directory and a pipeline (scene -> rays) that loads it.
fn workspace(tmp: &Path) -> PathBuf {
    let root = tmp.join("kitti360");
    let scene = common::kitti360_fixture(&root);
    let pipeline = format!(
        "cache: .pipe\nstages:\n{scene}  rays:\n    uses: intersect\n    inputs: {{scene: scene}}\n"
    );
    fs::write(tmp.join("pipeline.yaml"), pipeline).unwrap();
    root
}

fn run_pipe(dir: &Path, args: &[String]) -> Result<(i32, String), String> {
    let t0 = Instant::now();
    let child = Command::new(common::PIPE)
        .arg("run")
        .args(args)
        .current_dir(dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let out = common::wait_with_timeout(child, LIMIT)
        .ok_or_else(|| format!("no exit after {:.0?} (hang?)", t0.elapsed()))?;
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    Ok((out.status.code().unwrap_or(-1), err))
}

/// Runs one case; returns what went wrong.
fn check_case(case: &Path) -> Vec<String> {
    let name = case.file_name().unwrap().to_string_lossy().into_owned();
    let spec = fs::read_to_string(case.join("expect"))
        .unwrap_or_else(|e| panic!("{name}: cannot read its `expect` file: {e}"));
    let tmp = tempfile::tempdir().unwrap();
    let root = workspace(tmp.path());
    overlay(case, case, &root);
    let (mut exit, mut args, mut needles) = (None, Vec::new(), Vec::new());
    for line in spec
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
    {
        let (key, value) = line
            .split_once(": ")
            .unwrap_or_else(|| panic!("{name}/expect: `{line}` is not `key: value`"));
        match key {
            "exit" => exit = Some(value.parse::<i32>().unwrap()),
            "stderr" => needles.push(value.to_string()),
            "set" => args.extend(["--set".to_string(), value.to_string()]),
            "remove" => fs::remove_file(root.join(value))
                .unwrap_or_else(|e| panic!("{name}/expect: remove {value}: {e}")),
            "copy" => {
                let (src, dest) = value.split_once(" -> ").unwrap();
                fs::copy(case.join(src), root.join(dest))
                    .unwrap_or_else(|e| panic!("{name}/expect: copy {src}: {e}"));
            }
            _ => panic!("{name}/expect: unknown key `{key}`"),
        }
    }
    let exit = exit.unwrap_or_else(|| panic!("{name}/expect has no `exit:` line"));
    assert!([1, 2].contains(&exit), "{name}: exit must be 1 or 2");
    assert!(!needles.is_empty(), "{name}/expect has no `stderr:` line");
    let (code, err) = match run_pipe(tmp.path(), &args) {
        Ok(r) => r,
        Err(why) => return vec![format!("{name}: {why}")],
    };
    let mut failures = Vec::new();
    if code != exit {
        failures.push(format!("{name}: exit {code}, want {exit}"));
    }
    if err.contains("panicked") {
        failures.push(format!("{name}: panic"));
    }
    for n in &needles {
        if !err.contains(n.as_str()) {
            failures.push(format!("{name}: stderr lacks {n:?}"));
        }
    }
    let objects = tmp.path().join(".pipe/objects");
    if fs::read_dir(&objects).is_ok_and(|mut d| d.next().is_some()) {
        failures.push(format!("{name}: a failed run published a cache entry"));
    }
    if !failures.is_empty() {
        failures.push(format!("  stderr of {name}:\n{err}"));
    }
    failures
}

#[test]
fn the_unmodified_fixture_loads_through_pipe() {
    // The control: every case differs from this run only by its own change.
    let tmp = tempfile::tempdir().unwrap();
    workspace(tmp.path());
    let (code, err) = run_pipe(tmp.path(), &[]).unwrap();
    assert_eq!(code, 0, "{err}");
}

#[test]
fn every_bad_kitti360_input_gives_a_clear_error_naming_file_and_element() {
    let mut cases: Vec<PathBuf> = fs::read_dir(corpus())
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    cases.sort();
    assert!(cases.len() >= 50, "corpus shrank to {}", cases.len());
    // Two workers: the cases are independent and each is a short `pipe run`.
    let (even, odd): (Vec<_>, Vec<_>) = cases.iter().enumerate().partition(|(i, _)| i % 2 == 0);
    let work = |part: Vec<(usize, &PathBuf)>| {
        part.into_iter()
            .flat_map(|(_, c)| check_case(c))
            .collect::<Vec<String>>()
    };
    let failures: Vec<String> = std::thread::scope(|s| {
        let a = s.spawn(|| work(even));
        let b = work(odd);
        let mut f = a.join().unwrap();
        f.extend(b);
        f
    });
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
