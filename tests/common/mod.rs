//! Shared helpers for integration tests: a temporary directory with a pipeline file, and ways to
//! run the real `pipe` binary in it and inspect its cache.
#![allow(dead_code)]

use std::{
    collections::BTreeMap,
    fs,
    io::{BufRead, BufReader},
    path::{Path, PathBuf},
    process::{Child, Command, Stdio},
};

pub use pipe::runner::Outcome;

pub const PIPE: &str = env!("CARGO_BIN_EXE_pipe");

/// The whole pipeline on a scene small enough for tests (6 frames of 88x23, 40 iterations).
pub const TINY_PIPELINE: &str = "
stages:
  scene:
    uses: synthetic_scene
    params: {frames: 6, eval_every: 2, scale: 0.0625}
  rays:
    uses: intersect
    inputs: {scene: scene}
  train:
    uses: train
    inputs: {scene: scene, rays: rays}
    params:
      train: {iterations: 40, rays_per_batch: 256}
  render:
    uses: render
    inputs: {scene: scene, rays: rays, train: train}
  evaluate:
    uses: evaluate
    inputs: {scene: scene, render: render}
  report:
    uses: report
    inputs: {scene: scene, evaluate: evaluate, render: render, train: train}
";

pub struct Workspace {
    dir: tempfile::TempDir,
}

impl Workspace {
    pub fn new(pipeline: &str) -> Workspace {
        let ws = Workspace {
            dir: tempfile::tempdir().unwrap(),
        };
        ws.write_pipeline(pipeline);
        ws
    }

    pub fn dir(&self) -> &Path {
        self.dir.path()
    }

    pub fn cache(&self) -> PathBuf {
        self.dir().join(".pipe")
    }

    pub fn write_pipeline(&self, text: &str) {
        fs::write(self.dir().join("pipeline.yaml"), text).unwrap();
    }

    /// Runs `pipe run ARGS`; returns (exit code, stdout, stderr).
    pub fn run(&self, args: &[&str]) -> (i32, String, String) {
        self.cmd("run", args)
    }

    pub fn cmd(&self, command: &str, args: &[&str]) -> (i32, String, String) {
        let out = Command::new(PIPE)
            .arg(command)
            .args(args)
            .current_dir(self.dir())
            .output()
            .unwrap();
        (
            out.status.code().unwrap_or(-1),
            String::from_utf8_lossy(&out.stdout).into_owned(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    }

    pub fn run_ok(&self, args: &[&str]) -> String {
        let (code, out, err) = self.run(args);
        assert_eq!(code, 0, "pipe run {args:?} failed:\n{out}\n{err}");
        out
    }

    pub fn spawn(&self, args: &[&str]) -> Child {
        Command::new(PIPE)
            .arg("run")
            .args(args)
            .current_dir(self.dir())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    }

    /// Spawns `pipe run ARGS` and returns once its stderr contains `needle`.
    pub fn spawn_until(&self, args: &[&str], needle: &str) -> Child {
        let mut child = self.spawn(args);
        let stderr = child.stderr.take().unwrap();
        let mut reader = BufReader::new(stderr);
        let mut line = String::new();
        loop {
            line.clear();
            if reader.read_line(&mut line).unwrap() == 0 {
                panic!("pipe ended before printing {needle:?}");
            }
            if line.contains(needle) {
                break;
            }
        }
        // Keep draining so the child never blocks on a full pipe.
        std::thread::spawn(move || {
            let mut sink = String::new();
            while reader.read_line(&mut sink).unwrap_or(0) > 0 {
                sink.clear();
            }
        });
        child
    }

    pub fn status(&self, args: &[&str]) -> String {
        let (code, out, err) = self.cmd("status", args);
        assert_eq!(code, 0, "{err}");
        out
    }

    pub fn status_line<'a>(&self, status: &'a str, stage: &str) -> &'a str {
        status
            .lines()
            .find(|l| l.split_whitespace().next() == Some(stage))
            .unwrap_or_else(|| panic!("no status line for {stage}:\n{status}"))
    }

    /// (stage, outcome) of the last run, in run order.
    pub fn last_run(&self) -> Vec<(String, Outcome)> {
        let rep: pipe::runner::RunReport =
            serde_json::from_slice(&fs::read(self.cache().join("runs/last-run.json")).unwrap())
                .unwrap();
        rep.stages
            .into_iter()
            .map(|s| (s.stage, s.outcome))
            .collect()
    }

    pub fn last_run_map(&self) -> BTreeMap<String, Outcome> {
        self.last_run().into_iter().collect()
    }

    pub fn run_record_exists(&self, stage: &str) -> bool {
        self.cache()
            .join("runs")
            .join(format!("{stage}.json"))
            .exists()
    }

    /// The key of the last successful run of `stage`.
    pub fn stage_key(&self, stage: &str) -> String {
        let rec: serde_json::Value = serde_json::from_slice(
            &fs::read(self.cache().join(format!("runs/{stage}.json"))).unwrap(),
        )
        .unwrap();
        rec["key"].as_str().unwrap().to_string()
    }

    pub fn stage_is_fresh(&self, stage: &str) -> bool {
        let st = self.status(&[]);
        self.status_line(&st, stage).contains("fresh")
    }

    pub fn entries(&self) -> Vec<String> {
        let mut v: Vec<String> = fs::read_dir(self.cache().join("objects"))
            .map(|rd| {
                rd.map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                    .collect()
            })
            .unwrap_or_default();
        v.sort();
        v
    }

    /// Applies `damage` to the first table file of `stage`'s entry.
    pub fn corrupt_file(&self, stage: &str, damage: impl FnOnce(&mut Vec<u8>)) {
        let dir = self.cache().join("objects").join(self.stage_key(stage));
        let file = fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .find(|p| p.extension().is_some_and(|e| e == "parquet"))
            .unwrap();
        let mut bytes = fs::read(&file).unwrap();
        damage(&mut bytes);
        fs::write(&file, bytes).unwrap();
    }

    /// The numbers the last run of a test stage wrote, read from its cache entry.
    pub fn numbers(&self, stage: &str) -> Vec<i64> {
        let store = pipe::store::Store::open_existing(&self.cache());
        let key = self.stage_key(stage);
        let pipe::store::Entry::Valid(m) = store.check(&key, true) else {
            panic!("entry of {stage} not valid")
        };
        let t = store.load(&m).unwrap();
        let b = &t["test_numbers"];
        stages::tables::get_prim::<arrow::datatypes::Int64Type>(b, "test_numbers", "value")
            .unwrap()
            .to_vec()
    }
}
