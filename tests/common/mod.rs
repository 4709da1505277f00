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

/// The tiny street up to `render`, trained briefly, with a short update after an edit.
pub const EDIT_PIPELINE: &str = "
stages:
  scene:
    uses: synthetic_scene
    params: {frames: 4, scale: 0.0625}
  rays:
    uses: intersect
    inputs: {scene: scene}
  train:
    uses: train
    inputs: {scene: scene, rays: rays}
    params:
      schedule: {iterations: 60, rays_per_batch: 256}
      update: {iterations: 20}
  render:
    uses: render
    inputs: {scene: scene, rays: rays, train: train}
";

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
      schedule: {iterations: 40, rays_per_batch: 256}
  render:
    uses: render
    inputs: {scene: scene, rays: rays, train: train}
  review:
    uses: review
    inputs: {scene: scene, rays: rays, render: render}
  evaluate:
    uses: evaluate
    inputs: {scene: scene, render: render, review: review}
  report:
    uses: report
    inputs: {scene: scene, evaluate: evaluate, render: render, train: train, review: review}
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
        self.spawn_command("run", args)
    }

    /// Spawns `pipe COMMAND ARGS` with piped stdout and stderr.
    pub fn spawn_command(&self, command: &str, args: &[&str]) -> Child {
        Command::new(PIPE)
            .arg(command)
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

    /// Every entry in `objects/` verifies (sizes and hashes): nothing partial or corrupt.
    pub fn assert_every_entry_verifies(&self, after: &str) {
        let store = pipe::store::Store::open_existing(&self.cache());
        for key in self.entries() {
            assert_eq!(
                pipe::cli::entry_state(&store, &key),
                "valid",
                "entry {key} is not valid after {after}"
            );
        }
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

/// The hand-written KITTI-360 sequence of tests/fixtures/kitti360 copied to `root`, with the
/// PNGs its README describes written (8x4 stereo pairs, pseudo labels and GT for frames 3, 7
/// and 12). Returns the `scene:` stage of a pipeline that loads it (frames 3 and 7).
pub fn kitti360_fixture(root: &Path) -> String {
    copy_dir(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/kitti360"),
        root,
    );
    let png = |rel: String| {
        let p = root.join(rel);
        fs::create_dir_all(p.parent().unwrap()).unwrap();
        p
    };
    for f in [3u32, 7, 12] {
        for c in [0u32, 1] {
            let rgb: Vec<u8> = (0..4 * 8 * 3)
                .map(|i| (f * 31 + c * 17 + i * 5) as u8)
                .collect();
            let img = png(format!(
                "data_2d_raw/seq_a/image_{c:02}/data_rect/{f:010}.png"
            ));
            stages::pngio::write_rgb8(&img, 8, 4, &rgb).unwrap();
            let gt = format!("data_2d_semantics/train/seq_a/image_{c:02}");
            let sem: Vec<u8> = (0..32).map(|i| if i < 16 { 23 } else { 26 }).collect();
            let inst: Vec<u16> = sem
                .iter()
                .map(|&l| if l == 26 { 26001 } else { 23000 })
                .collect();
            let sem_png = png(format!("{gt}/semantic/{f:010}.png"));
            stages::pngio::write_gray8(&sem_png, 8, 4, &sem).unwrap();
            let inst_png = png(format!("{gt}/instance/{f:010}.png"));
            stages::pngio::write_gray16(&inst_png, 8, 4, &inst).unwrap();
        }
        let pl: Vec<u8> = (0..32).map(|i| if i < 20 { 23 } else { 7 }).collect();
        let pl_png = png(format!("pseudo_labels/seq_a/image_00/{f:010}.png"));
        stages::pngio::write_gray8(&pl_png, 8, 4, &pl).unwrap();
    }
    format!(
        "  scene:
    uses: kitti360_scene
    params: {{root: '{}', sequence: seq_a, first_frame: 0, last_frame: 10, eval_every: 1}}
",
        root.display()
    )
}

/// Copies a directory tree (following symlinks).
pub fn copy_dir(from: &Path, to: &Path) {
    fs::create_dir_all(to).unwrap();
    for e in fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let t = to.join(e.file_name());
        if e.path().is_dir() {
            copy_dir(&e.path(), &t);
        } else {
            fs::copy(e.path(), t).unwrap();
        }
    }
}

/// Waits for `child` at most `limit`; kills it and returns `None` when it takes longer.
pub fn wait_with_timeout(
    mut child: Child,
    limit: std::time::Duration,
) -> Option<std::process::Output> {
    let start = std::time::Instant::now();
    // Drain the pipes on threads so a chatty child never blocks on a full pipe.
    let drain = |r: Option<Box<dyn std::io::Read + Send>>| {
        std::thread::spawn(move || {
            let mut v = Vec::new();
            if let Some(mut r) = r {
                let _ = r.read_to_end(&mut v);
            }
            v
        })
    };
    let out = drain(child.stdout.take().map(|s| Box::new(s) as _));
    let err = drain(child.stderr.take().map(|s| Box::new(s) as _));
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return Some(std::process::Output {
                status,
                stdout: out.join().unwrap(),
                stderr: err.join().unwrap(),
            });
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            return None;
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
}
