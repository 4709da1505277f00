//! `pipe bench`: runs a suite of scenes x variants x training budgets through the normal cached
//! pipeline and writes the time-vs-error plots, the ablation table, machine and runner
//! figures: `REPORT.md`, `report.html`, `results.parquet`, PNGs and the generated pipeline.
//!
//! The suite becomes one ordinary pipeline file (`plan`), run by the same runner on the same
//! cache as `pipe run`, so a repeated bench reuses every entry and only stale stages run. The
//! bench knows the method only through the registry: the stage whose kind scores methods
//! (`Stage::scores`) says which table to read and how to show it, the stage whose kind has a
//! budget parameter (`Stage::budget_param`) is the one the budgets go to.

pub mod doc;
pub mod edits;
mod error;
pub mod machine;
pub mod plan;
pub mod plots;
mod report;
pub mod results;
pub mod suite;

use std::{
    collections::BTreeMap,
    path::{Path, PathBuf},
    sync::Arc,
    time::Instant,
};

pub use error::BenchError;
pub use report::{PIPELINE_FILE, RESULTS_FILE, RUN_REPORT_FILE};

use crate::{
    config::{self, Loc, Pipeline},
    dag::Dag,
    error::IoContext,
    runner::{self, RunOptions, RunReport, State},
    store::{write_parquet, Store},
};
use machine::Timing;
use plan::Plan;
use results::Row;
use suite::{Setting, Suite};

/// What `pipe bench` was asked to do.
pub struct BenchOptions {
    /// The base pipeline file (`-f`).
    pub base_file: PathBuf,
    /// `--cache`, else the base pipeline's cache.
    pub cache: Option<PathBuf>,
    /// `--set` overrides applied to every run.
    pub set: Vec<config::Override>,
    pub suite: Suite,
    pub out: PathBuf,
    pub jobs: usize,
}

/// What a bench produced.
pub struct BenchOutcome {
    pub report: RunReport,
    pub rows: Vec<Row>,
    pub files: Vec<PathBuf>,
    pub wall_s: f64,
}

fn abs(p: &Path) -> PathBuf {
    std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf())
}

fn write(path: &Path, bytes: &[u8]) -> Result<PathBuf, BenchError> {
    std::fs::write(path, bytes).io_context(|| format!("writing {}", path.display()))?;
    Ok(path.to_path_buf())
}

/// Runs the bench: builds and runs the pipeline, then writes the report files.
pub fn run(opts: &BenchOptions) -> Result<BenchOutcome, BenchError> {
    let t0 = Instant::now();
    let base = config::load(&opts.base_file, &opts.set)?;
    let cache_dir = abs(opts.cache.as_ref().unwrap_or(&base.cache_dir));
    let base_text = config::read_text(&opts.base_file, "pipeline file")?;
    let extra: Vec<Setting> = opts
        .set
        .iter()
        .map(|o| Setting {
            key: format!("{}.{}", o.stage, o.param),
            value: o.value.clone(),
            loc: Loc::CommandLine(o.arg.clone()),
            path: o.arg.clone(),
        })
        .collect();
    let plan = plan::build(&opts.suite, &opts.base_file, &base_text, &extra, &cache_dir)?;
    let (p, report) = run_plan(opts, &plan)?;
    let keys: BTreeMap<String, String> = report
        .stages
        .iter()
        .filter_map(|s| Some((s.stage.clone(), s.key.clone()?)))
        .collect();
    let store = Store::open_existing(&cache_dir);
    let manifests = results::manifests(&store, &keys)?;
    let rows = results::collect(&plan, &store, &manifests)?;
    let mut files = vec![opts.out.join(PIPELINE_FILE), opts.out.join(RUN_REPORT_FILE)];
    let results_path = opts.out.join(RESULTS_FILE);
    let batch = results::to_batch(&rows)?;
    let bytes = write_parquet(&batch).map_err(|source| BenchError::Codec {
        what: format!("encoding {}", results_path.display()),
        source,
    })?;
    files.push(write(&results_path, &bytes)?);

    let base_fresh = base_is_fresh(&base, &cache_dir);
    let timings = time_overhead(opts, &plan, &p, &base, base_fresh, &cache_dir)?;
    let images = plots(opts, &plan, &rows, &mut files)?;

    let wall_s = t0.elapsed().as_secs_f64();
    let doc = report::doc(&report::Input {
        suite: &opts.suite,
        base_file: &opts.base_file,
        base_text: &base_text,
        plan: &plan,
        rows: &rows,
        report: &report,
        manifests: &manifests,
        timings: &timings,
        base_fresh,
        wall_s,
    });
    files.push(write(
        &opts.out.join("REPORT.md"),
        doc.markdown().as_bytes(),
    )?);
    let html = doc.html(&format!("pipe bench: {}", opts.suite.name), &images);
    files.push(write(&opts.out.join("report.html"), html.as_bytes())?);
    Ok(BenchOutcome {
        report,
        rows,
        files,
        wall_s,
    })
}

/// Writes the generated pipeline under the output directory and runs it; the run report is
/// written beside it. A failed stage fails the bench.
fn run_plan(opts: &BenchOptions, plan: &Plan) -> Result<(Arc<Pipeline>, RunReport), BenchError> {
    std::fs::create_dir_all(&opts.out).io_context(|| format!("creating {}", opts.out.display()))?;
    let pipeline_file = write(&opts.out.join(PIPELINE_FILE), plan.yaml.as_bytes())?;
    let p = Arc::new(config::load(&pipeline_file, &[])?);
    let ropts = RunOptions {
        jobs: opts.jobs.max(1),
        ..Default::default()
    };
    let report = runner::run_blocking(p.clone(), &ropts)?;
    let json = serde_json::to_vec_pretty(&report).map_err(|source| BenchError::Json {
        what: format!("encoding {RUN_REPORT_FILE}"),
        source,
    })?;
    write(&opts.out.join(RUN_REPORT_FILE), &json)?;
    if report.failed {
        eprint!("{}", runner::summary(&report));
        return Err(BenchError::PipelineFailed(pipeline_file));
    }
    Ok((p, report))
}

/// Runner overhead: no-op runs of the (now fresh) bench pipeline, one scene chain, and the
/// base pipeline when it is up to date.
fn time_overhead(
    opts: &BenchOptions,
    plan: &Plan,
    p: &Pipeline,
    base: &Pipeline,
    base_fresh: bool,
    cache_dir: &Path,
) -> Result<Vec<Timing>, BenchError> {
    let reps = opts.suite.overhead_repeats;
    let pipeline_file = opts.out.join(PIPELINE_FILE);
    let chain_file = write(
        &opts.out.join("pipeline-one-run.yaml"),
        one_run_yaml(plan, cache_dir)?.as_bytes(),
    )?;
    let one_run = plan.roles.len();
    let mut timings = vec![
        machine::time_command(
            &format!("no-op `pipe run` ({one_run} stages of one run)"),
            &["run", "--no-wait"],
            &chain_file,
            reps,
        ),
        machine::time_command(
            &format!("`pipe status` ({one_run} stages of one run)"),
            &["status"],
            &chain_file,
            reps,
        ),
        machine::time_command(
            &format!("no-op `pipe run` (whole bench, {} stages)", p.stages.len()),
            &["run", "--no-wait"],
            &pipeline_file,
            reps,
        ),
    ];
    let base_file = opts.base_file.display();
    let n = base.stages.len();
    if base_fresh {
        timings.push(machine::time_command(
            &format!("no-op `pipe run` ({base_file}, {n} stages)"),
            &["run", "--no-wait"],
            &opts.base_file,
            reps,
        ));
    }
    timings.push(machine::time_command(
        &format!("`pipe status` ({base_file}, {n} stages)"),
        &["status"],
        &opts.base_file,
        reps,
    ));
    let _ = std::fs::remove_file(&chain_file);
    Ok(timings)
}

/// The time-vs-error PNG of every scene, written beside the report (and listed in `files`).
fn plots(
    opts: &BenchOptions,
    plan: &Plan,
    rows: &[Row],
    files: &mut Vec<PathBuf>,
) -> Result<BTreeMap<String, Vec<u8>>, BenchError> {
    let mut images = BTreeMap::new();
    let variants: Vec<(String, String, bool)> = opts
        .suite
        .variants
        .iter()
        .map(|v| (v.name.clone(), v.label.clone(), v.semantics))
        .collect();
    for sc in &opts.suite.scenes {
        let panels = plots::time_vs_error(rows, &sc.name, &variants, plan.spec);
        let png = plots::render_png(
            &format!("{}: error against training time", sc.name),
            &panels,
        )?;
        let name = format!("time_vs_error_{}.png", sc.name);
        files.push(write(&opts.out.join(&name), &png)?);
        images.insert(name, png);
    }
    Ok(images)
}

/// The stages of the plan's first run alone, as a pipeline file on the same cache.
fn one_run_yaml(plan: &Plan, cache: &Path) -> Result<String, BenchError> {
    let yaml_err = |source| BenchError::Yaml {
        what: "writing the pipeline of one run".into(),
        source,
    };
    let full: serde_yaml::Value = serde_yaml::from_str(&plan.yaml).map_err(yaml_err)?;
    let mut stages = serde_yaml::Mapping::new();
    if let Some(run) = plan.runs.first() {
        for r in &plan.roles {
            let name = &run.instances[r];
            if let Some(decl) = full.get("stages").and_then(|s| s.get(name.as_str())) {
                stages.insert(name.clone().into(), decl.clone());
            }
        }
    }
    let mut doc = serde_yaml::Mapping::new();
    doc.insert("cache".into(), cache.to_string_lossy().into_owned().into());
    doc.insert("stages".into(), serde_yaml::Value::Mapping(stages));
    serde_yaml::to_string(&doc).map_err(yaml_err)
}

fn base_is_fresh(base: &Pipeline, cache: &Path) -> bool {
    let Ok(dag) = Dag::build(base) else {
        return false;
    };
    let store = Store::open_existing(cache);
    runner::resolve(base, &dag, &store, false)
        .is_ok_and(|res| res.iter().all(|r| matches!(r.state, State::Fresh(_))))
}
