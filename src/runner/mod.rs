//! Executes a pipeline: for each selected stage in dependency order, reuse its verified cache
//! entry or run it (on a blocking thread, tokio driving the schedule) and publish the outputs.
//! Also answers "is this stage fresh, and if not, why?" for `pipe status` and `--dry-run`.
//!
//! The parts: [`plan`] (keys, freshness and why, the selection), `schedule` (which stage
//! next), `execute` (one stage on its thread), `progress` (bars), [`report`] (the run's
//! report and the printed summary), [`options`], and the errors [`RunError`] (the run could
//! not start or go on) and [`StageFailure`] (one stage failed; in the report).

mod error;
mod execute;
pub mod options;
pub mod parent;
pub mod plan;
mod progress;
pub mod report;
mod schedule;

use std::{sync::Arc, time::Instant};

use tokio::task::JoinSet;

pub use crate::fingerprint::FILES_SLOT;
pub use error::{RunError, StageFailure};
pub use execute::gather_tables;
pub use options::{RunOptions, Scenes};
pub use plan::{check_scenes, external_digests, resolve, selection, Resolved, State};
pub use report::{fmt_bytes, fmt_secs, summary, text_table, Outcome, RunReport, StageReport};

use crate::{
    config::Pipeline,
    dag::Dag,
    store::{write_atomic, RunLock, Store},
};
use schedule::Scheduler;

/// Runs the pipeline. Stage failures are reported in the result (`failed`), not as `Err`;
/// `Err` means the run could not start or the cache could not be written.
pub async fn run(p: Arc<Pipeline>, opts: &RunOptions) -> Result<RunReport, RunError> {
    let t0 = Instant::now();
    let dag = Dag::build(&p)?;
    let selected = selection(&p, &dag, opts)?;
    let store = Arc::new(Store::open(&p.cache_dir)?);
    let _lock = if opts.dry_run {
        None
    } else {
        Some(RunLock::acquire(store.root(), opts.no_wait, false)?)
    };
    let writes = !opts.dry_run && store.read_only().is_none();
    // The pipeline file is known to the cache from its first run on (gc keeps what it reaches).
    let known_as = writes
        .then(|| std::fs::canonicalize(&p.file).ok())
        .flatten();
    if writes {
        store.clean_tmp();
        if let Some(file) = &known_as {
            let _ = store.record_pipeline(file, None);
        }
    }
    let external = external_digests(&p, &store)?;
    let mut schedule = Scheduler::new(&p, &dag, &store, opts, selected, external);
    let mut running = JoinSet::new();
    loop {
        schedule.start_ready(&mut running)?;
        let Some(joined) = running.join_next().await else {
            break;
        };
        schedule.finish(joined.map_err(|e| RunError::Panicked(e.to_string()))?)?;
    }
    let rep = schedule.into_report(t0.elapsed().as_secs_f64());
    if writes {
        // Best effort (the summary is printed too), but never a half-written file.
        let path = store.root().join("runs").join("last-run.json");
        if let Ok(json) = serde_json::to_vec_pretty(&rep) {
            let _ = write_atomic(&path, &json);
        }
        if let Some(file) = &known_as {
            let reached = rep
                .stages
                .iter()
                .filter(|s| matches!(s.outcome, Outcome::Cached | Outcome::Ran | Outcome::Updated))
                .filter_map(|s| s.key.clone())
                .collect();
            let _ = store.record_pipeline(file, Some(reached));
        }
    }
    Ok(rep)
}

/// Runs the pipeline on a runtime of its own (for callers that are not async).
pub fn run_blocking(p: Arc<Pipeline>, opts: &RunOptions) -> Result<RunReport, RunError> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .map_err(RunError::Runtime)?;
    rt.block_on(run(p, opts))
}
