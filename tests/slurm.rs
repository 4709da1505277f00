//! The Slurm executor against a real single-node Slurm cluster (Debian's slurm-wlm + munge,
//! started by `.ci/slurm-up.sh`, which this test runs first): a 3-scene tiny matrix goes out
//! as one job array, a task killed mid-way is retried and its partial output never lands, the
//! aggregate is computed, a second run submits nothing, and Ctrl-C cancels the array. If the
//! cluster cannot start, the test fails with the script's reason; it is never skipped.

mod common;

use common::{Workspace, TINY_PIPELINE};
use std::{
    fs,
    io::{BufRead, BufReader},
    path::Path,
    process::{Command, Stdio},
    time::{Duration, Instant},
};

/// Brings the cluster up (idempotent) or panics with why it could not.
fn cluster_up() {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join(".ci/slurm-up.sh");
    let out = Command::new("bash")
        .arg(&script)
        .output()
        .expect("running .ci/slurm-up.sh");
    assert!(
        out.status.success(),
        "the Slurm test cluster did not start ({}):\n{}{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The pid of the `pipe run --scene SCENE` process working on `cache`, if there is one.
fn task_pid(cache: &Path, scene: &str) -> Option<i32> {
    let cache = cache.to_string_lossy().into_owned();
    for e in fs::read_dir("/proc").ok()?.flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<i32>() else {
            continue;
        };
        let Ok(cmd) = fs::read(e.path().join("cmdline")) else {
            continue;
        };
        let args: Vec<String> = cmd
            .split(|b| *b == 0)
            .map(|a| String::from_utf8_lossy(a).into_owned())
            .collect();
        let scene_arg = args.windows(2).any(|w| w[0] == "--scene" && w[1] == scene);
        if scene_arg && args.iter().any(|a| a == &cache) {
            return Some(pid);
        }
    }
    None
}

/// The newest log directory of the executor.
fn log_dir(ws: &Workspace) -> Option<std::path::PathBuf> {
    let mut dirs: Vec<_> = fs::read_dir(ws.cache().join("logs"))
        .ok()?
        .map(|e| e.unwrap().path())
        .collect();
    dirs.sort();
    dirs.pop()
}

fn squeue_jobs() -> String {
    let out = Command::new("squeue")
        .args(["-h", "-o", "%i %j"])
        .output()
        .unwrap();
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
fn a_scene_matrix_runs_as_a_slurm_job_array_with_retries() {
    let t_all = Instant::now();
    cluster_up();
    let pipe = common::PIPE;

    // Ctrl-C cancels the array (test kinds: tasks that sleep).
    let ws = Workspace::new(
        "
scenes:
  matrix:
    a.value: [1, 2]
stages:
  a:
    uses: test_source
    params: {sleep_ms: 60000}
executor:
  slurm: {poll_s: 0.3, cpus_per_task: 1, job_name: pipe-interrupt-test}
",
    );
    // A dry run lists every stage it would run and submits nothing.
    let (code, out, err) = ws.run(&["--executor", "slurm", "--dry-run"]);
    assert_eq!(code, 0, "{out}{err}");
    for stage in ["a@value1", "a@value2"] {
        assert!(
            out.lines()
                .any(|l| l.starts_with(stage) && l.contains("would run")),
            "{stage}: {out}"
        );
    }
    assert!(
        !squeue_jobs().contains("pipe-interrupt-test"),
        "a dry run submitted a job"
    );
    let mut coord = Command::new(pipe)
        .args(["run", "--executor", "slurm"])
        .current_dir(ws.dir())
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(coord.stderr.take().unwrap()).lines();
    let job = loop {
        let l = lines
            .next()
            .expect("the coordinator ended before submitting")
            .unwrap();
        if let Some(rest) = l.strip_prefix("slurm: submitted job array ") {
            break rest.split_whitespace().next().unwrap().to_string();
        }
    };
    assert!(squeue_jobs().contains(&job), "{}", squeue_jobs());
    // SAFETY: signalling our own child.
    unsafe { libc::kill(coord.id() as i32, libc::SIGINT) };
    let rest: Vec<String> = lines.map_while(Result::ok).collect();
    let status = coord.wait().unwrap();
    assert_eq!(status.code(), Some(130), "{rest:?}");
    assert!(
        rest.iter()
            .any(|l| l.contains(&format!("cancelled slurm job(s) {job}"))),
        "{rest:?}"
    );
    let deadline = Instant::now() + Duration::from_secs(30);
    while squeue_jobs()
        .lines()
        .any(|l| l.starts_with(&format!("{job}_")))
    {
        assert!(
            Instant::now() < deadline,
            "job {job} still queued after scancel"
        );
        std::thread::sleep(Duration::from_millis(200));
    }

    // The tiny pipeline as a 3-scene matrix, with the aggregate.
    let stages = TINY_PIPELINE.replace("stages:\n", "");
    let ws = Workspace::new(&format!(
        "scenes:\n  matrix:\n    scene.seed: [1, 2, 3]\nstages:\n{stages}dataset:\n  summary:\n    uses: aggregate\n    inputs: {{evaluate: evaluate}}\nexecutor:\n  slurm: {{poll_s: 0.5, cpus_per_task: 1, time: '00:10:00', job_name: pipe-matrix-test}}\n"
    ));
    let t0 = Instant::now();
    let coord = Command::new(pipe)
        .args(["run", "--executor", "slurm", "--retries", "2"])
        .current_dir(ws.dir())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Kill scene seed2's task while it trains.
    let mut killed = false;
    while t0.elapsed() < Duration::from_secs(120) && !killed {
        let log = log_dir(&ws).map(|d| d.join("seed2.try1.log"));
        let training = log
            .as_ref()
            .and_then(|l| fs::read_to_string(l).ok())
            .is_some_and(|t| t.contains("running `train@seed2`"));
        if training {
            if let Some(pid) = task_pid(&ws.cache(), "seed2") {
                // SAFETY: a process this test's pipeline started.
                unsafe { libc::kill(pid, libc::SIGKILL) };
                killed = true;
            }
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(killed, "never saw scene seed2's task train");
    let out = common::wait_with_timeout(coord, Duration::from_secs(150))
        .expect("the coordinator did not finish within 150 s");
    let wall = t0.elapsed();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(
        stderr.contains("3 scenes: 0 up to date, 3 to run"),
        "{stderr}"
    );
    assert!(stderr.contains("scene seed2: try 1 failed"), "{stderr}");
    assert!(
        stderr.contains("submitted job array") && stderr.contains("try 2"),
        "{stderr}"
    );
    for sc in ["seed1", "seed2", "seed3"] {
        assert!(stderr.contains(&format!("scene {sc}: done")), "{stderr}");
    }
    assert!(
        stdout.contains("summary") && stdout.contains("ran"),
        "{stdout}"
    );
    // The killed try left nothing partial: every entry verifies, no temporary entry or lock.
    ws.assert_every_entry_verifies("a killed Slurm task and its retry");
    assert_eq!(fs::read_dir(ws.cache().join("tmp")).unwrap().count(), 0);
    let locks: Vec<_> = fs::read_dir(ws.cache().join("locks"))
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert!(locks.is_empty(), "{locks:?}");
    let dir = log_dir(&ws).unwrap();
    assert!(dir.join("seed2.try2.log").exists());
    let st = ws.status(&[]);
    for line in st
        .lines()
        .filter(|l| l.contains('@') || l.starts_with("summary"))
    {
        assert!(line.contains("fresh"), "{st}");
    }
    let (code, _, err) = ws.cmd("export", &["summary", "--to", "out"]);
    assert_eq!(code, 0, "{err}");
    let md = fs::read_to_string(ws.dir().join("out/summary.md")).unwrap();
    assert!(md.contains("3 scenes: seed1, seed2, seed3"), "{md}");

    // A second run submits nothing.
    let (code, out2, err2) = ws.cmd("run", &["--executor", "slurm"]);
    assert_eq!(code, 0, "{err2}");
    assert!(
        err2.contains("nothing submitted") && !err2.contains("submitted job array"),
        "{err2}"
    );
    assert!(out2.contains("3 scenes (0 ran, 3 cached)"), "{out2}");
    eprintln!(
        "3-scene tiny matrix through Slurm (one task killed and retried): {:.1}s; whole test {:.1}s",
        wall.as_secs_f64(),
        t_all.elapsed().as_secs_f64()
    );
}
