//! Runs the scenes of a scene pipeline (`scenes:` in pipeline.yaml) as separate
//! `pipe run --scene NAME` tasks on one shared cache, then the dataset stages in this process.
//!
//! The coordinator resolves every scene's cache keys and hands only the stale scenes to a
//! [`Backend`]: worker processes on this machine ([`local::Local`], `--executor local
//! --jobs N`) or one Slurm job array ([`slurm::Slurm`], `--executor slurm`). A task counts as
//! done when its scene is up to date in the cache afterwards (the cache, not an exit code, is
//! the truth); a task that failed is retried up to `--retries` times and, if it still fails,
//! its log file is named. Ctrl-C cancels every task. Tasks share the cache safely: each entry
//! is computed under its own lock file and published by an atomic rename (see `store`).

mod backend;
mod error;
pub mod local;
pub mod slurm;

use std::{
    collections::BTreeMap,
    path::{Path, PathBuf},
    sync::{
        atomic::{AtomicBool, Ordering},
        Arc,
    },
    time::{Duration, Instant},
};

pub use backend::{shell_quote, Backend, Task};
pub use error::ExecutorError;

use crate::{
    config::{shorten, Pipeline},
    dag::Dag,
    error::IoContext,
    runner::{self, RunOptions, Scenes, State},
    store::{unix_now, Store},
};

/// Where scene tasks run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ExecutorKind {
    /// This machine: in this process, or `--jobs N` worker processes.
    Local,
    /// A Slurm cluster: one job array (`sbatch --array`), resources from `executor.slurm`.
    Slurm,
}

/// What the coordinator needs beyond the pipeline.
#[derive(Debug, Clone)]
pub struct ExecOptions {
    pub kind: ExecutorKind,
    /// Worker processes of the local executor.
    pub jobs: usize,
    /// Further tries of a failed scene.
    pub retries: u32,
    /// The run's options (scenes, force, verify, dry run ...).
    pub run: RunOptions,
    /// `--set` arguments, forwarded to every task.
    pub set: Vec<String>,
}

static INTERRUPTED: AtomicBool = AtomicBool::new(false);

extern "C" fn on_signal(_: libc::c_int) {
    INTERRUPTED.store(true, Ordering::SeqCst);
}

/// Ctrl-C (and SIGTERM) set a flag the coordinator polls, so it can cancel its tasks.
fn catch_interrupts() {
    // SAFETY: the handler only stores to an atomic.
    unsafe {
        libc::signal(libc::SIGINT, on_signal as *const () as libc::sighandler_t);
        libc::signal(libc::SIGTERM, on_signal as *const () as libc::sighandler_t);
    }
}

/// The arguments of `pipe` that run one scene (the scene name appended by the backend).
pub fn task_args(p: &Pipeline, opts: &ExecOptions) -> Result<Vec<String>, ExecutorError> {
    let abs = |path: &Path| -> Result<PathBuf, ExecutorError> {
        Ok(std::path::absolute(path).io_context(|| format!("resolving {}", path.display()))?)
    };
    let mut args = vec![
        "run".to_string(),
        "-f".into(),
        abs(&p.file)?.to_string_lossy().into_owned(),
        "--cache".into(),
        abs(&p.cache_dir)?.to_string_lossy().into_owned(),
    ];
    for s in &opts.set {
        args.push("--set".into());
        args.push(s.clone());
    }
    for f in &opts.run.force {
        args.push("--force".into());
        args.push(f.clone());
    }
    if opts.run.force_all {
        args.push("--force-all".into());
    }
    if opts.run.verify {
        args.push("--verify".into());
    }
    if opts.run.cold {
        args.push("--cold".into());
    }
    if opts.run.keep_going {
        args.push("--keep-going".into());
    }
    args.push("--scene".into());
    Ok(args)
}

/// Whether every stage of `scene` is fresh.
fn scene_fresh(p: &Pipeline, res: &[runner::Resolved], scene: &str) -> bool {
    p.scene_stages(scene)
        .iter()
        .all(|&i| matches!(res[i].state, State::Fresh(_)))
}

/// How one scene ended in this run.
struct SceneEnd {
    result: &'static str,
    tries: u32,
    how: String,
    log: Option<PathBuf>,
}

/// Runs the selected scenes through the executor, then the dataset stages; returns the exit
/// code (0 all done, 1 a scene or a dataset stage failed, 130 interrupted).
pub fn run_scenes(p: Arc<Pipeline>, opts: &ExecOptions) -> Result<i32, ExecutorError> {
    let t0 = Instant::now();
    if opts.run.until.is_some() || opts.run.only.is_some() {
        return Err(ExecutorError::StageSelection);
    }
    let dag = Dag::build(&p)?;
    let store = Store::open(&p.cache_dir)?;
    let scenes: Vec<String> = match &opts.run.scenes {
        Scenes::Named(list) => {
            runner::selection(&p, &dag, &opts.run)?;
            list.clone()
        }
        _ => p.scenes.clone(),
    };
    let forced: Vec<usize> = opts
        .run
        .force
        .iter()
        .flat_map(|f| p.instances(f, &scenes))
        .collect();
    let res = runner::resolve(&p, &dag, &store, opts.run.verify)?;
    let stale: Vec<String> = scenes
        .iter()
        .filter(|sc| {
            opts.run.force_all
                || !scene_fresh(&p, &res, sc)
                || forced
                    .iter()
                    .any(|&i| p.stages[i].scene.as_deref() == Some(sc))
        })
        .cloned()
        .collect();
    let mut ends: BTreeMap<String, SceneEnd> = scenes
        .iter()
        .map(|sc| {
            let e = SceneEnd {
                result: "cached",
                tries: 0,
                how: "up to date".into(),
                log: None,
            };
            (sc.clone(), e)
        })
        .collect();
    eprintln!(
        "{} scenes: {} up to date, {} to run{}",
        scenes.len(),
        scenes.len() - stale.len(),
        stale.len(),
        if stale.is_empty() {
            " (nothing submitted)".to_string()
        } else {
            format!(": {}", shorten(&stale.join(", "), 200))
        }
    );

    let run_id = format!("{}-{}", unix_now() as u64, std::process::id());
    let logs = p.cache_dir.join("logs").join(&run_id);
    let log_dir =
        std::path::absolute(&logs).io_context(|| format!("resolving {}", logs.display()))?;
    let mut failed_scenes = 0;
    if !stale.is_empty() {
        let args = task_args(&p, opts)?;
        let mut backend: Box<dyn Backend> = match opts.kind {
            ExecutorKind::Local => Box::new(local::Local::new(args, opts.jobs)?),
            ExecutorKind::Slurm => Box::new(slurm::Slurm::new(
                &p.slurm,
                args,
                &stale,
                &log_dir,
                opts.run.dry_run,
            )?),
        };
        if opts.run.dry_run {
            // Local backends have nothing to show; Slurm printed its sbatch command.
            let _ = backend.submit(&first_tries(&stale, &log_dir));
            return Ok(0);
        }
        std::fs::create_dir_all(&log_dir)
            .io_context(|| format!("creating log directory {}", log_dir.display()))?;
        catch_interrupts();
        let code = follow(
            &p,
            &dag,
            &store,
            opts,
            backend.as_mut(),
            &stale,
            &log_dir,
            &mut ends,
        )?;
        if code != 0 {
            return Ok(code);
        }
        failed_scenes = ends.values().filter(|e| e.result == "FAILED").count();
    }

    print_scenes(&scenes, &ends);
    if failed_scenes > 0 {
        eprintln!(
            "error: {failed_scenes} of {} scenes failed; the dataset stages did not run",
            scenes.len()
        );
        return Ok(1);
    }
    let mut code = 0;
    if opts.run.scenes == Scenes::All && !p.dataset_stages().is_empty() {
        let run = RunOptions {
            scenes: Scenes::Dataset,
            jobs: 1,
            ..opts.run.clone()
        };
        let rep = runner::run_blocking(p.clone(), &run)?;
        print!("{}", runner::summary(&rep));
        code = i32::from(rep.failed);
    }
    println!(
        "{} scenes ({} ran, {} cached) in {}",
        scenes.len(),
        ends.values().filter(|e| e.result == "ran").count(),
        ends.values().filter(|e| e.result == "cached").count(),
        runner::fmt_secs(t0.elapsed().as_secs_f64())
    );
    Ok(code)
}

fn first_tries(stale: &[String], log_dir: &Path) -> Vec<Task> {
    stale
        .iter()
        .enumerate()
        .map(|(index, sc)| Task {
            index,
            scene: sc.clone(),
            attempt: 1,
            log: log_dir.join(format!("{sc}.try1.log")),
        })
        .collect()
}

/// Submits the stale scenes and follows them to the end, retrying failures. Returns 130 when
/// interrupted (after cancelling), else 0; failures are recorded in `ends`.
#[allow(clippy::too_many_arguments)]
fn follow(
    p: &Pipeline,
    dag: &Dag,
    store: &Store,
    opts: &ExecOptions,
    backend: &mut dyn Backend,
    stale: &[String],
    log_dir: &Path,
    ends: &mut BTreeMap<String, SceneEnd>,
) -> Result<i32, ExecutorError> {
    backend.submit(&first_tries(stale, log_dir))?;
    eprintln!(
        "{}: {} tasks submitted; logs in {}",
        backend.label(),
        stale.len(),
        log_dir.display()
    );
    let (mut done, mut failed) = (0usize, 0usize);
    let mut last_line = String::new();
    let mut last_shown = Instant::now();
    loop {
        if INTERRUPTED.load(Ordering::SeqCst) {
            let what = backend.cancel();
            eprintln!("interrupted: {what}");
            return Ok(130);
        }
        let ended = backend.poll()?;
        if !ended.is_empty() {
            let res = runner::resolve(p, dag, store, false)?;
            let mut again = Vec::new();
            for (task, how) in ended {
                let ok = scene_fresh(p, &res, &task.scene)
                    && (how == "exit code 0" || how == slurm::UNKNOWN_END);
                let end = ends.get_mut(&task.scene).expect("a scene of this run");
                end.tries = task.attempt;
                end.how = how.clone();
                end.log = Some(task.log.clone());
                if ok {
                    done += 1;
                    end.result = "ran";
                    eprintln!("scene {}: done (try {})", task.scene, task.attempt);
                } else if task.attempt <= opts.retries {
                    eprintln!(
                        "scene {}: try {} failed ({how}); log {}; retrying",
                        task.scene,
                        task.attempt,
                        task.log.display()
                    );
                    let attempt = task.attempt + 1;
                    again.push(Task {
                        log: log_dir.join(format!("{}.try{attempt}.log", task.scene)),
                        attempt,
                        ..task
                    });
                } else {
                    failed += 1;
                    end.result = "FAILED";
                    eprintln!(
                        "scene {}: FAILED after {} tries ({how}); log {}",
                        task.scene,
                        task.attempt,
                        task.log.display()
                    );
                }
            }
            if !again.is_empty() {
                backend.submit(&again)?;
            }
        }
        let (waiting, running) = backend.counts();
        let line = format!(
            "{}: {} scenes: {done} done, {running} running, {waiting} waiting, {failed} failed",
            backend.label(),
            stale.len()
        );
        if line != last_line || last_shown.elapsed() > Duration::from_secs(60) {
            eprintln!("{line}");
            last_line = line;
            last_shown = Instant::now();
        }
        if waiting + running == 0 {
            return Ok(0);
        }
        std::thread::sleep(backend.poll_interval());
    }
}

fn print_scenes(scenes: &[String], ends: &BTreeMap<String, SceneEnd>) {
    let rows: Vec<Vec<String>> = scenes
        .iter()
        .map(|sc| {
            let e = &ends[sc];
            vec![
                sc.clone(),
                e.result.to_string(),
                if e.tries == 0 {
                    "-".into()
                } else {
                    e.tries.to_string()
                },
                e.how.clone(),
                e.log
                    .as_ref()
                    .map_or(String::new(), |l| l.display().to_string()),
            ]
        })
        .collect();
    print!(
        "{}",
        runner::text_table(&["scene", "result", "tries", "how", "log"], &rows)
    );
}
