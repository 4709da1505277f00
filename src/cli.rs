//! Command-line interface: argument parsing (clap) and one function per command. `main.rs`
//! only dispatches and maps errors to exit codes (0 ok, 1 a stage failed, 2 bad usage/config):
//! a [`CliError`] says which by its variant.

use std::{
    path::{Path, PathBuf},
    sync::Arc,
};

use anyhow::{anyhow, Context};
use arrow::util::display::{ArrayFormatter, FormatOptions};
use clap::{Args, Parser, Subcommand};

mod gc;
mod kinds;

use crate::{
    bench::{self, BenchError},
    config::{self, ConfigError, Override, Pipeline},
    dag::Dag,
    error::Classify,
    executor::{self, ExecOptions, ExecutorError, ExecutorKind},
    runner::{self, Outcome, RunError, RunOptions, State},
    store::{Entry, Manifest, Store, StoreError},
};

/// Why a command failed: bad usage or configuration (exit code 2) or a failure while working
/// (exit code 1), told by the variant (and, for the library's errors, by theirs).
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    /// A bad command line: exit code 2.
    #[error("{0}")]
    Usage(String),
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Run(#[from] RunError),
    /// (Boxed, as is `Bench`: they hold the others, and errors travel by value.)
    #[error(transparent)]
    Executor(Box<ExecutorError>),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    Bench(Box<BenchError>),
    /// Anything else that went wrong while working (exporting, formatting a table).
    #[error(transparent)]
    Other(#[from] anyhow::Error),
}

impl From<ExecutorError> for CliError {
    fn from(e: ExecutorError) -> CliError {
        CliError::Executor(Box::new(e))
    }
}

impl From<gc::GcError> for CliError {
    fn from(e: gc::GcError) -> CliError {
        match e {
            gc::GcError::Config(e) => CliError::Config(e),
            gc::GcError::Run(e) => CliError::Run(e),
            gc::GcError::Store(e) => CliError::Store(e),
            e @ (gc::GcError::ReadOnly { .. } | gc::GcError::NotHere { .. }) => {
                CliError::Other(e.into())
            }
        }
    }
}

impl From<BenchError> for CliError {
    fn from(e: BenchError) -> CliError {
        CliError::Bench(Box::new(e))
    }
}

impl Classify for CliError {
    fn is_usage(&self) -> bool {
        match self {
            CliError::Usage(_) => true,
            CliError::Config(e) => e.is_usage(),
            CliError::Run(e) => e.is_usage(),
            CliError::Executor(e) => e.is_usage(),
            CliError::Store(e) => e.is_usage(),
            CliError::Bench(e) => e.is_usage(),
            CliError::Other(_) => false,
        }
    }
}

type Result<T, E = CliError> = std::result::Result<T, E>;

fn usage(msg: impl Into<String>) -> CliError {
    CliError::Usage(msg.into())
}

#[derive(Parser, Debug)]
#[command(
    name = "pipe",
    version,
    about = "Panoptic NeRF label transfer as a content-hashed stage pipeline",
    long_about = "Runs the stages declared in pipeline.yaml (scene -> rays -> train -> render -> evaluate -> report), \
caching every stage's tables under a key made of its code version, parameters and inputs, so only \
what a change made stale is recomputed.\n\nExit codes: 0 ok, 1 a stage failed, 2 bad usage or configuration."
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

/// The pipeline file when `-f` is not given.
const DEFAULT_PIPELINE: &str = "pipeline.yaml";

#[derive(Args, Debug, Clone)]
pub struct PipelineArgs {
    /// The pipeline file.
    #[arg(
        short = 'f',
        long = "file",
        default_value = DEFAULT_PIPELINE,
        global = true
    )]
    pub file: PathBuf,
    /// Override a parameter: STAGE.PARAM=VALUE (VALUE is YAML). Repeatable.
    #[arg(long = "set", value_name = "STAGE.PARAM=VALUE", global = true)]
    pub set: Vec<String>,
    /// Cache directory (default: `cache:` of the pipeline file, else .pipe beside it).
    #[arg(long, global = true)]
    pub cache: Option<PathBuf>,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Bring stages up to date: reuse cached outputs, run what is stale.
    Run {
        /// Stop after this stage (runs it and what it depends on).
        #[arg(long, value_name = "STAGE")]
        until: Option<String>,
        /// Run only this stage; its inputs must already be up to date.
        #[arg(long, value_name = "STAGE")]
        only: Option<String>,
        /// Re-run this stage even if cached (an update again from its parent; with --cold from
        /// scratch). Repeatable.
        #[arg(long, value_name = "STAGE")]
        force: Vec<String>,
        /// Re-run every selected stage.
        #[arg(long)]
        force_all: bool,
        /// Show what would run and why, without running anything.
        #[arg(long)]
        dry_run: bool,
        /// Fail at once if another `pipe run` holds the cache instead of waiting.
        #[arg(long)]
        no_wait: bool,
        /// How many independent stages may run at once.
        #[arg(long, short = 'j', default_value_t = 1, value_parser = at_least_one)]
        jobs: usize,
        /// After a stage fails, still run the stages that do not depend on it.
        #[arg(long)]
        keep_going: bool,
        /// Hash every cached file, even those unchanged since they were last verified.
        #[arg(long)]
        verify: bool,
        /// Compute stale stages from scratch, never by updating their previous run (what an
        /// annotation edit otherwise does: see `pipe kinds` for the kinds that update).
        #[arg(long)]
        cold: bool,
        /// Update a stage that can even where its result from scratch is cached (for measuring
        /// updates: `pipe bench --suite edits`).
        #[arg(long, hide = true, conflicts_with = "cold")]
        prefer_update: bool,
        /// Run only this scene of a pipeline with `scenes:` (no dataset stages). Repeatable.
        #[arg(long = "scene", value_name = "NAME")]
        scene: Vec<String>,
        /// `all` (every scene, then the dataset stages: the default) or scenes A,B,...
        #[arg(long, value_name = "all|A,B,...")]
        scenes: Option<String>,
        /// Where the scenes run: `local` (this process, or --jobs N worker processes) or
        /// `slurm` (one job array; resources from `executor.slurm` of the pipeline file).
        #[arg(long, value_enum, default_value = "local")]
        executor: ExecutorKind,
        /// Further tries of a scene whose task failed (executors with worker processes).
        #[arg(long, default_value_t = 1)]
        retries: u32,
        #[command(flatten)]
        pipeline: PipelineArgs,
    },
    /// Every stage: fresh, or stale and why.
    Status {
        /// Hash every cached file, even those unchanged since they were last verified.
        #[arg(long)]
        verify: bool,
        /// Only the stages of this scene. Repeatable.
        #[arg(long = "scene", value_name = "NAME")]
        scene: Vec<String>,
        #[command(flatten)]
        pipeline: PipelineArgs,
    },
    /// The stage graph, as text or Graphviz (`--dot`).
    Dag {
        #[arg(long)]
        dot: bool,
        #[command(flatten)]
        pipeline: PipelineArgs,
    },
    /// A cached stage's tables: schema, row count and first rows.
    Show {
        stage: String,
        /// Only this table.
        #[arg(long)]
        table: Option<String>,
        /// Rows to print.
        #[arg(long, default_value_t = 5)]
        head: usize,
        #[command(flatten)]
        pipeline: PipelineArgs,
    },
    /// Write a cached stage's human-facing files (PNGs, reports) into a directory.
    Export {
        stage: String,
        #[arg(long, value_name = "DIR")]
        to: PathBuf,
        #[command(flatten)]
        pipeline: PipelineArgs,
    },
    /// Remove cache entries that no pipeline file which ran in the cache reaches (each is read
    /// as it stands now; one that cannot be read keeps what its last run reached).
    Gc {
        /// Also keep every entry any stage instance has ever produced.
        #[arg(long)]
        keep_all_runs: bool,
        /// Only list what would be removed.
        #[arg(long)]
        dry_run: bool,
        /// Keep only what the `-f` pipeline reaches: removes every other pipeline's entries.
        #[arg(long)]
        only_this_pipeline: bool,
        #[command(flatten)]
        pipeline: PipelineArgs,
    },
    /// Run a bench suite through the cached pipeline: time against error, the ablation table,
    /// machine and runner figures (REPORT.md, report.html, results.parquet, PNG plots).
    Bench {
        /// A built-in suite (quick, standard, full, seeds, growth, fisheye, edits) or a suite file.
        #[arg(long, default_value = "quick", value_name = "SUITE")]
        suite: String,
        /// Output directory (default: bench-results/SUITE).
        #[arg(long, value_name = "DIR")]
        out: Option<PathBuf>,
        /// How many independent stages may run at once.
        #[arg(long, short = 'j', default_value_t = 1, value_parser = at_least_one)]
        jobs: usize,
        #[command(flatten)]
        pipeline: PipelineArgs,
    },
    /// The stage kinds this build knows; with KIND, its inputs, outputs and every parameter
    /// (dotted path, type, default, what it does).
    Kinds {
        /// Only this kind, with every parameter.
        kind: Option<String>,
        /// Print the kind as a commented YAML stage to paste into a pipeline file.
        #[arg(long, requires = "kind")]
        yaml: bool,
    },
}

/// The `--set` arguments, parsed.
fn overrides(args: &PipelineArgs) -> Result<Vec<Override>> {
    args.set
        .iter()
        .map(|s| Override::parse(s).map_err(usage))
        .collect()
}

fn load(args: &PipelineArgs) -> Result<Pipeline> {
    let mut p = config::load(&args.file, &overrides(args)?)?;
    if let Some(c) = &args.cache {
        p.cache_dir = c.clone();
    }
    Ok(p)
}

/// A count that must be at least 1 (`-j 0` would run nothing, so it is refused).
fn at_least_one(s: &str) -> std::result::Result<usize, String> {
    match s.parse::<usize>() {
        Ok(0) => Err("0 would run nothing; at least 1".into()),
        Ok(n) => Ok(n),
        Err(e) => Err(format!("{e}")),
    }
}

pub fn dispatch(cli: Cli) -> Result<i32> {
    match cli.command {
        Command::Run {
            until,
            only,
            force,
            force_all,
            dry_run,
            no_wait,
            jobs,
            keep_going,
            verify,
            cold,
            prefer_update,
            scene,
            scenes,
            executor,
            retries,
            pipeline,
        } => {
            let p = Arc::new(load(&pipeline)?);
            let mut named = scene;
            match scenes.as_deref() {
                None | Some("all") => {}
                Some(list) => named.extend(list.split(',').map(str::to_string)),
            }
            let opts = RunOptions {
                scenes: if named.is_empty() {
                    runner::Scenes::All
                } else {
                    runner::Scenes::Named(named)
                },
                until,
                only,
                force,
                force_all,
                dry_run,
                no_wait,
                jobs,
                keep_going,
                verify,
                cold,
                prefer_update,
            };
            let several = match &opts.scenes {
                runner::Scenes::Named(list) => list.len() > 1,
                _ => p.scenes.len() > 1,
            };
            if executor == ExecutorKind::Slurm && p.scenes.is_empty() {
                return Err(ExecutorError::NoScenes(p.file.clone()).into());
            }
            let matrix =
                !p.scenes.is_empty() && (executor == ExecutorKind::Slurm || (jobs > 1 && several));
            // A dry run lists every stage of every scene in order, in process; on Slurm it
            // then shows the job array it would submit.
            let dry_listing = if opts.dry_run {
                Some(cmd_run(p.clone(), &opts)?)
            } else {
                None
            };
            if matrix && (dry_listing.is_none() || executor == ExecutorKind::Slurm) {
                let exec = ExecOptions {
                    kind: executor,
                    jobs,
                    retries,
                    run: opts,
                    set: pipeline.set.clone(),
                };
                let code = executor::run_scenes(p, &exec)?;
                return Ok(dry_listing.unwrap_or(code));
            }
            if let Some(code) = dry_listing {
                return Ok(code);
            }
            cmd_run(p, &opts)
        }
        Command::Status {
            verify,
            scene,
            pipeline,
        } => cmd_status(&load(&pipeline)?, verify, &scene),
        Command::Dag { dot, pipeline } => cmd_dag(&load(&pipeline)?, dot),
        Command::Show {
            stage,
            table,
            head,
            pipeline,
        } => cmd_show(&load(&pipeline)?, &stage, table.as_deref(), head),
        Command::Export {
            stage,
            to,
            pipeline,
        } => cmd_export(&load(&pipeline)?, &stage, &to),
        Command::Gc {
            keep_all_runs,
            dry_run,
            only_this_pipeline,
            pipeline,
        } => Ok(gc::run(
            &load(&pipeline)?,
            &gc::GcOptions {
                keep_all_runs,
                dry_run,
                only_this_pipeline,
            },
        )?),
        Command::Bench {
            suite,
            out,
            jobs,
            pipeline,
        } => cmd_bench(&suite, out, jobs, &pipeline),
        Command::Kinds { kind, yaml } => cmd_kinds(kind.as_deref(), yaml),
    }
}

fn cmd_run(p: Arc<Pipeline>, opts: &RunOptions) -> Result<i32> {
    let rep = runner::run_blocking(p, opts)?;
    print!("{}", runner::summary(&rep));
    Ok(if rep.failed { 1 } else { 0 })
}

fn cmd_status(p: &Pipeline, verify: bool, scenes: &[String]) -> Result<i32> {
    let dag = Dag::build(p)?;
    let store = Store::open_existing(&p.cache_dir);
    let res = runner::resolve(p, &dag, &store, verify)?;
    if !scenes.is_empty() {
        runner::check_scenes(p, scenes)?;
    }
    let shown = |i: usize| {
        scenes.is_empty()
            || p.stages[i]
                .scene
                .as_ref()
                .is_some_and(|sc| scenes.contains(sc))
    };
    let rows: Vec<Vec<String>> = dag
        .order
        .iter()
        .filter(|&&i| shown(i))
        .map(|&i| {
            let s = &p.stages[i];
            let (state, why) = match &res[i].state {
                State::Fresh(m) => (
                    "fresh",
                    match (&m.parent, &m.redone) {
                        (Some(parent), Some(redone)) => {
                            format!("updated from {}: {redone}", &parent[..parent.len().min(8)])
                        }
                        _ => String::new(),
                    },
                ),
                State::Stale(why) if res[i].corrupt => ("CORRUPT", why.clone()),
                State::Stale(why) => ("stale", why.clone()),
            };
            vec![
                s.name.clone(),
                s.kind.kind().to_string(),
                state.to_string(),
                why,
            ]
        })
        .collect();
    print!(
        "{}",
        runner::text_table(&["stage", "kind", "state", "why"], &rows)
    );
    if !p.scenes.is_empty() {
        // One line per scene: what a `pipe run --executor ...` would hand out.
        let rows: Vec<Vec<String>> = p
            .scenes
            .iter()
            .filter(|sc| scenes.is_empty() || scenes.contains(sc))
            .map(|sc| {
                let idx = p.scene_stages(sc);
                let stale: Vec<&str> = idx
                    .iter()
                    .filter(|&&i| !matches!(res[i].state, State::Fresh(_)))
                    .map(|&i| p.stages[i].template.as_str())
                    .collect();
                let state = if stale.is_empty() { "fresh" } else { "stale" };
                vec![
                    sc.clone(),
                    state.to_string(),
                    format!("{}/{}", idx.len() - stale.len(), idx.len()),
                    stale.join(", "),
                ]
            })
            .collect();
        println!();
        print!(
            "{}",
            runner::text_table(&["scene", "state", "fresh stages", "stale"], &rows)
        );
    }
    Ok(0)
}

fn cmd_dag(p: &Pipeline, dot: bool) -> Result<i32> {
    let dag = Dag::build(p)?;
    if dot {
        print!("{}", dag.dot(p));
        return Ok(0);
    }
    for &i in &dag.order {
        let s = &p.stages[i];
        let mut ins: Vec<String> = s
            .inputs
            .iter()
            .map(|(slot, up)| {
                if slot == up {
                    up.clone()
                } else {
                    format!("{slot}={up}")
                }
            })
            .collect();
        for (slot, ups) in &s.gather {
            let template = ups
                .first()
                .map_or("?", |(_, up)| up.split('@').next().unwrap_or(up));
            ins.push(format!("{slot}={template}@* ({} scenes)", ups.len()));
        }
        if ins.is_empty() {
            println!("{} ({})", s.name, s.kind.kind());
        } else {
            println!("{} ({}) <- {}", s.name, s.kind.kind(), ins.join(", "));
        }
    }
    Ok(0)
}

/// The verified manifest of a fresh stage, or a usage error saying how to make it fresh.
fn fresh_entry(p: &Pipeline, stage: &str) -> Result<(Store, Box<Manifest>)> {
    let i = p
        .index_of(stage)
        .ok_or_else(|| usage(format!("no stage named `{stage}` in {}", p.file.display())))?;
    let dag = Dag::build(p)?;
    let store = Store::open_existing(&p.cache_dir);
    let res = runner::resolve(p, &dag, &store, false)?;
    match &res[i].state {
        State::Fresh(m) => Ok((store, m.clone())),
        State::Stale(why) => Err(usage(format!(
            "stage `{stage}` is not up to date ({why}); run `pipe run --until {stage}` first"
        ))),
    }
}

/// The tables of stage `stage`'s up-to-date entry, verified against its manifest. An entry
/// that fails (bit rot the cheap check did not see) is an error saying how to repair it.
fn open_fresh(p: &Pipeline, stage: &str) -> Result<(Store, Box<Manifest>, stages::TableSet)> {
    let (store, m) = fresh_entry(p, stage)?;
    match store.open_tables(&m, false) {
        Ok(t) => Ok((store, m, t)),
        Err(StoreError::Corrupt(why)) => {
            let moved = match store.quarantine(&m.key) {
                Ok(d) => format!("moved to {}", d.display()),
                Err(e) => format!("could not be moved to trash/: {e}"),
            };
            Err(anyhow!(
                "stage `{stage}`: cache entry {} is corrupt: {why} ({moved}); \
                 `pipe run --until {stage}` recomputes it",
                m.key
            )
            .into())
        }
        Err(e) => Err(e.into()),
    }
}

fn cmd_show(p: &Pipeline, stage: &str, table: Option<&str>, head: usize) -> Result<i32> {
    let (store, m, tables) = open_fresh(p, stage)?;
    if let Some(t) = table {
        if !tables.contains(t) {
            return Err(usage(format!(
                "stage `{stage}` has no table `{t}` (tables: {})",
                tables.names().collect::<Vec<_>>().join(", ")
            )));
        }
    }
    println!(
        "stage `{stage}` (kind `{}`, version {}), key {}\nentry {}",
        m.kind,
        m.version,
        m.key,
        store.entry_dir(&m.key).display()
    );
    for stored in tables.iter() {
        let name = stored.name();
        if table.is_some_and(|t| t != name) {
            continue;
        }
        let file = format!("{name}.parquet");
        let size = m.files.get(&file).map_or(0, |f| f.size);
        println!(
            "\ntable `{name}`: {} rows, {} ({file})",
            stored.num_rows(),
            runner::fmt_bytes(size)
        );
        for f in stored.schema().fields() {
            println!(
                "  {}: {}",
                f.name(),
                stages::schema::format_type(f.data_type())
            );
        }
        let n = head.min(stored.num_rows());
        if n == 0 {
            continue;
        }
        // Only the rows shown are read.
        let batch = stored
            .rows(0..n, None)
            .map_err(|e| anyhow!("reading table `{name}` of stage `{stage}`: {e}"))?;
        // A null shows as `null`, so every row has a value in every column.
        let opts = FormatOptions::default().with_null("null");
        let fmts = batch
            .columns()
            .iter()
            .map(|c| ArrayFormatter::try_new(c.as_ref(), &opts))
            .collect::<Result<Vec<_>, _>>()
            .context("formatting the table")?;
        let header: Vec<&str> = batch
            .schema_ref()
            .fields()
            .iter()
            .map(|f| f.name().as_str())
            .collect();
        let rows: Vec<Vec<String>> = (0..n)
            .map(|r| {
                fmts.iter()
                    .map(|f| {
                        let s = f.value(r).to_string();
                        if s.chars().count() > 40 {
                            format!("{}...", s.chars().take(37).collect::<String>())
                        } else {
                            s
                        }
                    })
                    .collect()
            })
            .collect();
        println!();
        print!("{}", runner::text_table(&header, &rows));
    }
    Ok(0)
}

fn cmd_export(p: &Pipeline, stage: &str, to: &Path) -> Result<i32> {
    let (_, _, tables) = open_fresh(p, stage)?;
    let s = &p.stages[p.index_of(stage).unwrap()];
    std::fs::create_dir_all(to).with_context(|| format!("creating {}", to.display()))?;
    let files = s
        .kind
        .export(&s.params, &tables, to)
        .map_err(|e| anyhow!("exporting stage `{stage}`: {e}"))?;
    if files.is_empty() {
        println!(
            "stage `{stage}` (kind `{}`) has no files to export",
            s.kind.kind()
        );
    } else {
        println!("wrote {} files under {}", files.len(), to.display());
    }
    Ok(0)
}

fn cmd_bench(suite: &str, out: Option<PathBuf>, jobs: usize, args: &PipelineArgs) -> Result<i32> {
    if let Some(edits) = bench::edits::load(suite)? {
        return cmd_bench_edits(edits, out, args);
    }
    let suite = bench::suite::load(suite)?.ok_or_else(|| {
        usage(format!(
            "unknown suite `{suite}` (built in: {}; or give the path of a suite .yaml file)",
            bench::suite::BUILT_IN
                .iter()
                .chain(bench::edits::suite::BUILT_IN)
                .map(|(n, ..)| *n)
                .collect::<Vec<_>>()
                .join(", ")
        ))
    })?;
    let set = overrides(args)?;
    let out = out.unwrap_or_else(|| PathBuf::from("bench-results").join(&suite.name));
    // The suite's own base pipeline unless `-f` names another than the default.
    let base_file = match &suite.pipeline {
        Some(p) if args.file == Path::new(DEFAULT_PIPELINE) => p.clone(),
        _ => args.file.clone(),
    };
    let opts = bench::BenchOptions {
        base_file,
        cache: args.cache.clone(),
        set,
        suite,
        out,
        jobs,
    };
    let done = bench::run(&opts)?;
    let ran = done.report.count(Outcome::Ran) + done.report.count(Outcome::Updated);
    println!(
        "bench `{}`: {} stages ({ran} ran, {} cached), {} result rows, {}",
        opts.suite.name,
        done.report.stages.len(),
        done.report.stages.len() - ran,
        done.rows.len(),
        runner::fmt_secs(done.wall_s)
    );
    for f in &done.files {
        println!("  {}", f.display());
    }
    Ok(0)
}

/// `pipe bench --suite edits`: each edit before, updated and from scratch, one after another.
fn cmd_bench_edits(
    suite: bench::edits::EditsSuite,
    out: Option<PathBuf>,
    args: &PipelineArgs,
) -> Result<i32> {
    let out = out.unwrap_or_else(|| PathBuf::from("bench-results").join(&suite.name));
    let base_file = match &suite.pipeline {
        Some(p) if args.file == Path::new(DEFAULT_PIPELINE) => p.clone(),
        _ => args.file.clone(),
    };
    let opts = bench::edits::EditsOptions {
        base_file,
        cache: args.cache.clone(),
        set: overrides(args)?,
        suite,
        out,
    };
    let rows = bench::edits::run(&opts)?;
    println!("bench `{}`: {} edits scored", opts.suite.name, rows.len());
    for f in bench::edits::files(&opts.out) {
        println!("  {}", f.display());
    }
    Ok(0)
}

fn cmd_kinds(only: Option<&str>, yaml: bool) -> Result<i32> {
    let all = stages::kinds::registry();
    let Some(name) = only else {
        for k in all.iter().filter(|k| !k.kind().starts_with("test_")) {
            println!(
                "{} (version {}): {}",
                k.kind(),
                k.version(),
                k.description()
            );
            let top: Vec<String> = k
                .param_docs()
                .iter()
                .filter(|d| d.depth == 0)
                .map(|d| d.path.clone())
                .collect();
            println!("  params {}", top.join(", "));
        }
        println!("\n`pipe kinds KIND` lists a kind's parameters; `pipe kinds KIND --yaml` writes them as YAML.");
        return Ok(0);
    };
    let k = all
        .iter()
        .find(|k| k.kind() == name)
        .ok_or_else(|| usage(format!("no stage kind `{name}`")))?;
    if yaml {
        print!("{}", kinds::yaml(k.as_ref()));
    } else {
        print!("{}", kinds::text(k.as_ref()));
    }
    Ok(0)
}

/// Used by tests and callers that want the corrupt/fresh state of one entry.
pub fn entry_state(store: &Store, key: &str) -> &'static str {
    match store.check(key, true) {
        Entry::Missing => "missing",
        Entry::Valid(_) => "valid",
        Entry::Corrupt(_) => "corrupt",
    }
}

/// Whether a run report contains a stage that actually ran.
pub fn any_ran(rep: &runner::RunReport) -> bool {
    rep.stages
        .iter()
        .any(|r| matches!(r.outcome, Outcome::Ran | Outcome::Updated))
}
