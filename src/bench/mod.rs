//! `pipe bench`: runs a suite of scenes x variants x training budgets through the normal cached
//! pipeline and writes the time-vs-error plots, the paper's ablation table, machine and runner
//! figures: `REPORT.md`, `report.html`, `results.parquet`, PNGs and the generated pipeline.
//!
//! The suite becomes one ordinary pipeline file (`plan`), run by the same runner on the same
//! cache as `pipe run`, so a repeated bench reuses every entry and only stale stages run.

pub mod doc;
pub mod machine;
pub mod plan;
pub mod plots;
pub mod results;
pub mod suite;

use std::{
    collections::BTreeMap,
    path::{Path, PathBuf},
    sync::Arc,
    time::Instant,
};

use anyhow::{Context, Result};

use crate::{
    config,
    runner::{self, Outcome, RunOptions, RunReport},
    store::Store,
};
use doc::Doc;
use results::{value, Row};
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

/// File names under the output directory.
pub const PIPELINE_FILE: &str = "pipeline.yaml";
pub const RUN_REPORT_FILE: &str = "run-report.json";
pub const RESULTS_FILE: &str = "results.parquet";

const BASELINES: [(&str, &str); 2] = [
    ("pseudo_labels", "pseudo labels"),
    ("first_primitive", "first primitive"),
];

/// The paper's ablation on one KITTI-360 scene (REFERENCE.md): depth RMSE, delta, mIoU.
const PAPER_ABLATION: [(&str, &str); 6] = [
    ("photometric", "10.71 / 78.4 / 67.2"),
    ("no_fixed_2d", "6.28 / 93.1 / 76.9"),
    ("no_depth", "6.15 / 94.0 / 79.1"),
    ("uniform", "6.28 / 91.1 / 73.5"),
    ("no_point_3d", "5.74 / 95.0 / 70.7"),
    ("complete", "5.23 / 95.1 / 81.4"),
];

fn abs(p: &Path) -> PathBuf {
    std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf())
}

/// Runs the bench: builds and runs the pipeline, then writes the report files.
pub fn run(opts: &BenchOptions) -> Result<BenchOutcome> {
    let t0 = Instant::now();
    let base = config::load(&opts.base_file, &opts.set)?;
    let cache_dir = abs(opts.cache.as_ref().unwrap_or(&base.cache_dir));
    let base_text = std::fs::read_to_string(&opts.base_file)
        .with_context(|| format!("reading {}", opts.base_file.display()))?;
    let extra: Vec<Setting> = opts
        .set
        .iter()
        .map(|o| Setting {
            key: format!("{}.{}", o.stage, o.param),
            value: o.value.clone(),
            loc: config::Loc::CommandLine(o.arg.clone()),
            path: o.arg.clone(),
        })
        .collect();
    let plan = plan::build(&opts.suite, &opts.base_file, &base_text, &extra, &cache_dir)?;
    std::fs::create_dir_all(&opts.out)
        .with_context(|| format!("creating {}", opts.out.display()))?;
    let pipeline_file = opts.out.join(PIPELINE_FILE);
    std::fs::write(&pipeline_file, &plan.yaml)
        .with_context(|| format!("writing {}", pipeline_file.display()))?;
    let p = Arc::new(config::load(&pipeline_file, &[])?);

    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    let ropts = RunOptions {
        jobs: opts.jobs.max(1),
        ..Default::default()
    };
    let report = rt.block_on(runner::run(p.clone(), &ropts))?;
    std::fs::write(
        opts.out.join(RUN_REPORT_FILE),
        serde_json::to_vec_pretty(&report)?,
    )?;
    if report.failed {
        eprint!("{}", runner::summary(&report));
        anyhow::bail!(
            "the bench pipeline failed (see above; {} is the pipeline it ran)",
            pipeline_file.display()
        );
    }
    let keys: BTreeMap<String, String> = report
        .stages
        .iter()
        .filter_map(|s| Some((s.stage.clone(), s.key.clone()?)))
        .collect();
    let store = Store::open_existing(&cache_dir);
    let manifests = results::manifests(&store, &keys)?;
    let rows = results::collect(&plan, &store, &manifests)?;
    let mut files = vec![pipeline_file.clone(), opts.out.join(RUN_REPORT_FILE)];
    let results_path = opts.out.join(RESULTS_FILE);
    std::fs::write(
        &results_path,
        crate::store::write_parquet(&results::to_batch(&rows)?)?,
    )?;
    files.push(results_path);

    // Runner overhead: no-op runs of this (now fresh) pipeline, one scene chain, and the base
    // pipeline when it is up to date.
    let reps = opts.suite.overhead_repeats;
    let chain_file = opts.out.join("pipeline-one-run.yaml");
    std::fs::write(&chain_file, one_run_yaml(&plan, &cache_dir)?)?;
    let mut timings = vec![
        machine::time_command(
            &format!("no-op `pipe run` ({} stages of one run)", plan.roles.len()),
            &["run", "--no-wait"],
            &chain_file,
            reps,
        ),
        machine::time_command(
            &format!("`pipe status` ({} stages of one run)", plan.roles.len()),
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
    let base_fresh = base_is_fresh(&base, &cache_dir);
    if base_fresh {
        timings.push(machine::time_command(
            &format!(
                "no-op `pipe run` ({}, {} stages)",
                opts.base_file.display(),
                base.stages.len()
            ),
            &["run", "--no-wait"],
            &opts.base_file,
            reps,
        ));
    }
    timings.push(machine::time_command(
        &format!(
            "`pipe status` ({}, {} stages)",
            opts.base_file.display(),
            base.stages.len()
        ),
        &["status"],
        &opts.base_file,
        reps,
    ));
    let _ = std::fs::remove_file(&chain_file);

    // Plots.
    let mut images = BTreeMap::new();
    let variants: Vec<(String, String, bool)> = opts
        .suite
        .variants
        .iter()
        .map(|v| (v.name.clone(), v.label.clone(), v.semantics))
        .collect();
    for sc in &opts.suite.scenes {
        let panels = plots::time_vs_error(&rows, &sc.name, &variants, &BASELINES);
        let png = plots::render_png(
            &format!("{}: error against training time", sc.name),
            &panels,
        )?;
        let name = format!("time_vs_error_{}.png", sc.name);
        std::fs::write(opts.out.join(&name), &png)?;
        files.push(opts.out.join(&name));
        images.insert(name, png);
    }

    let wall_s = t0.elapsed().as_secs_f64();
    let doc = report_doc(&ReportInput {
        opts,
        plan: &plan,
        rows: &rows,
        report: &report,
        manifests: &manifests,
        timings: &timings,
        base_fresh,
        base_text: &base_text,
        pipeline_yaml: &plan.yaml,
        wall_s,
    });
    let md = opts.out.join("REPORT.md");
    std::fs::write(&md, doc.markdown())?;
    let html = opts.out.join("report.html");
    std::fs::write(
        &html,
        doc.html(&format!("pipe bench: {}", opts.suite.name), &images),
    )?;
    files.push(md);
    files.push(html);
    Ok(BenchOutcome {
        report,
        rows,
        files,
        wall_s,
    })
}

/// The stages of the plan's first run alone, as a pipeline file on the same cache.
fn one_run_yaml(plan: &plan::Plan, cache: &Path) -> Result<String> {
    let full: serde_yaml::Value = serde_yaml::from_str(&plan.yaml)?;
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
    Ok(serde_yaml::to_string(&doc)?)
}

fn base_is_fresh(base: &config::Pipeline, cache: &Path) -> bool {
    let Ok(dag) = crate::dag::Dag::build(base) else {
        return false;
    };
    let store = Store::open_existing(cache);
    runner::resolve(base, &dag, &store, false).is_ok_and(|res| {
        res.iter()
            .all(|r| matches!(r.state, runner::State::Fresh(_)))
    })
}

struct ReportInput<'a> {
    opts: &'a BenchOptions,
    plan: &'a plan::Plan,
    rows: &'a [Row],
    report: &'a RunReport,
    manifests: &'a results::Manifests,
    timings: &'a [machine::Timing],
    base_fresh: bool,
    base_text: &'a str,
    pipeline_yaml: &'a str,
    wall_s: f64,
}

/// How many stages of a run ended with `outcome`.
pub fn count(report: &RunReport, outcome: Outcome) -> usize {
    report
        .stages
        .iter()
        .filter(|r| r.outcome == outcome)
        .count()
}

/// Ours' `metric` in `run`; none for a semantic metric of a variant without semantics.
fn ours(rows: &[Row], run: &plan::Run, semantics: bool, metric: &str) -> Option<f64> {
    if !semantics && !metric.starts_with("depth") {
        return None;
    }
    value(
        rows,
        &run.scene,
        &run.variant,
        run.budget,
        "panoptic_nerf",
        metric,
    )
}

/// Training time to come within 1 mIoU of the first variant's largest budget (the stand-in for
/// the converged value), on one scene; None when the variant ran at fewer than two budgets.
fn speed_to_goal(i: &ReportInput, scene: &str) -> Option<String> {
    let variant = &i.opts.suite.variants.first()?.name;
    let mut runs: Vec<&plan::Run> = i
        .plan
        .runs
        .iter()
        .filter(|r| r.scene == scene && &r.variant == variant)
        .collect();
    runs.sort_by_key(|r| r.budget);
    let last = *runs.last()?;
    if runs.len() < 2 {
        return None;
    }
    let miou = |r: &plan::Run| ours(i.rows, r, true, "miou");
    let reference = miou(last)?;
    let wall = |r: &plan::Run| i.manifests[&r.instances[&i.plan.train_role]].wall_s;
    let first = runs
        .iter()
        .find(|r| miou(r).is_some_and(|m| m >= reference - 0.01))?;
    Some(format!(
        "Speed to the goal: the largest budget ({} steps, {:.1} s of training) reaches {:.1} mIoU; the first budget within 1 mIoU of it is {} steps, {:.1} mIoU after {:.1} s of training ({} the goal of at most 60 s).",
        last.budget,
        wall(last),
        reference * 100.0,
        first.budget,
        miou(first).unwrap_or(f64::NAN) * 100.0,
        wall(first),
        if wall(first) <= 60.0 { "within" } else { "over" },
    ))
}

fn f(v: Option<f64>, scale: f64, digits: usize) -> String {
    v.map_or("—".into(), |v| format!("{:.*}", digits, v * scale))
}

fn hash(s: &str) -> String {
    blake3::hash(s.as_bytes()).to_hex()[..16].to_string()
}

/// Every `seed` parameter (at any depth) of a stage's params, as `path=value`.
fn seeds(prefix: &str, v: &serde_json::Value, out: &mut Vec<String>) {
    if let serde_json::Value::Object(o) = v {
        for (k, x) in o {
            let p = format!("{prefix}.{k}");
            if k == "seed" && !x.is_object() {
                out.push(format!("{p}={x}"));
            } else {
                seeds(&p, x, out);
            }
        }
    }
}

fn report_doc(i: &ReportInput) -> Doc {
    let s = &i.opts.suite;
    let m = machine::machine();
    let mut d = Doc::default();
    d.h(1, format!("pipe bench: suite `{}`", s.name));
    if !s.description.is_empty() {
        d.p(&s.description);
    }
    d.p("**Error figures are reproducible**: the same suite and build on the same machine give the same metrics (scenes and training are seeded, and stages are cached by content). **Times vary** from run to run and machine to machine; a stage reused from the cache reports the wall time of the run that computed it.");
    let (ran, cached) = (
        count(i.report, Outcome::Ran),
        count(i.report, Outcome::Cached),
    );
    d.p(format!(
        "This bench took {:.1} s: {ran} stages ran, {cached} came from the cache.",
        i.wall_s
    ));

    d.h(2, "Machine and build");
    let mut keys: Vec<(String, String)> = i
        .report
        .stages
        .iter()
        .filter_map(|r| Some((r.stage.clone(), r.key.clone()?)))
        .collect();
    keys.sort();
    let key_text: String = keys.iter().map(|(n, k)| format!("{n} {k}\n")).collect();
    let mut seed_list = Vec::new();
    for sc in &s.scenes {
        if let Some(run) = i.plan.runs.iter().find(|r| r.scene == sc.name) {
            let mut v = Vec::new();
            for r in &i.plan.roles {
                if let Some(mf) = i.manifests.get(&run.instances[r]) {
                    seeds(r, &mf.params, &mut v);
                }
            }
            seed_list.push(format!("{}: {}", sc.name, v.join(", ")));
        }
    }
    d.table(
        &["", ""],
        vec![
            vec!["CPU".into(), m.cpu],
            vec!["cores".into(), format!("{} logical ({} usable by this process)", m.cores, m.usable)],
            vec!["memory".into(), m.memory],
            vec!["system".into(), m.kernel],
            vec!["tool".into(), m.tool_version],
            vec!["suite".into(), format!("`{}` (blake3 {})", s.file.display(), hash(&s.text))],
            vec!["base pipeline".into(), format!("`{}` (blake3 {})", i.opts.base_file.display(), hash(i.base_text))],
            vec!["pipeline hash".into(), format!("{} (blake3 over every stage's cache key; the generated pipeline is `{PIPELINE_FILE}`, blake3 {})", hash(&key_text), hash(i.pipeline_yaml))],
            vec!["seeds".into(), seed_list.join("; ")],
        ],
    );

    let variant = |name: &str| s.variants.iter().find(|v| v.name == name);
    d.h(2, "Time against error");
    d.p("Ours (`panoptic_nerf`) per variant and training budget, against the training stage's wall time. The plots draw the variants run at several budgets; the 2D baselines (the pseudo labels given as input, and the class of the first primitive each ray hits) do not train and are flat lines. mIoU, Acc, PQ and delta<1.25 in %, depth RMSE in metres.");
    for sc in &s.scenes {
        d.h(3, format!("Scene `{}`", sc.name));
        d.image(
            format!("time_vs_error_{}.png", sc.name),
            format!("{}: mIoU, PQ and depth RMSE against training time", sc.name),
        );
        let mut rows = Vec::new();
        for run in i.plan.runs.iter().filter(|r| r.scene == sc.name) {
            let sem = variant(&run.variant).is_none_or(|v| v.semantics);
            let g = |metric: &str| ours(i.rows, run, sem, metric);
            let wall = i.manifests[&run.instances[&i.plan.train_role]].wall_s;
            rows.push(vec![
                variant(&run.variant).map_or(run.variant.clone(), |v| v.label.clone()),
                run.budget.to_string(),
                format!("{wall:.1}"),
                f(g("miou"), 100.0, 1),
                f(g("acc"), 100.0, 1),
                f(g("pq"), 100.0, 1),
                f(g("depth_rmse"), 1.0, 2),
                f(g("depth_delta_1_25"), 100.0, 1),
            ]);
        }
        d.table(
            &[
                "variant",
                "budget",
                "train wall s",
                "mIoU",
                "Acc",
                "PQ",
                "depth RMSE",
                "delta<1.25",
            ],
            rows,
        );
        if let Some(line) = speed_to_goal(i, &sc.name) {
            d.p(line);
        }
        let first = s.variants.first().map(|v| v.name.as_str());
        let longest = i
            .plan
            .runs
            .iter()
            .filter(|r| r.scene == sc.name && Some(r.variant.as_str()) == first)
            .max_by_key(|r| r.budget);
        if let Some(run) = longest.or_else(|| i.plan.runs.iter().find(|r| r.scene == sc.name)) {
            let rows = ["pseudo_labels", "first_primitive", "fixed_field"]
                .iter()
                .map(|&method| {
                    let g = |metric: &str| {
                        value(i.rows, &run.scene, &run.variant, run.budget, method, metric)
                    };
                    vec![
                        method.to_string(),
                        f(g("miou"), 100.0, 1),
                        f(g("acc"), 100.0, 1),
                        f(g("pq"), 100.0, 1),
                        f(g("mc"), 100.0, 1),
                    ]
                })
                .collect();
            d.p("Baselines (independent of training; `fixed_field` is the fixed-field rendering of the longest run of the first variant; it depends on the learned density):");
            d.table(&["method", "mIoU", "Acc", "PQ", "MC"], rows);
        }
    }

    d.h(2, format!("Ablation (budget {})", s.ablation_budget));
    d.p("In the paper's form: ours with one part of the method removed, at the same training budget. The photometric-only field has no semantic supervision, so only its depth is reported. The last column is the paper's figure on one KITTI-360 scene (depth RMSE m / delta<1.25 % / mIoU %), for the ordering, not the scale.");
    for sc in &s.scenes {
        let mut rows = Vec::new();
        for v in &s.variants {
            let Some(run) = i.plan.runs.iter().find(|r| {
                r.scene == sc.name && r.variant == v.name && r.budget == s.ablation_budget
            }) else {
                continue;
            };
            let g = |metric: &str| ours(i.rows, run, v.semantics, metric);
            rows.push(vec![
                v.label.clone(),
                f(g("depth_rmse"), 1.0, 2),
                f(g("depth_delta_1_25"), 100.0, 1),
                f(g("miou"), 100.0, 1),
                f(g("acc"), 100.0, 1),
                PAPER_ABLATION
                    .iter()
                    .find(|(n, _)| *n == v.name)
                    .map_or("".into(), |(_, p)| p.to_string()),
            ]);
        }
        if !rows.is_empty() {
            d.h(3, format!("Scene `{}`", sc.name));
            d.table(
                &[
                    "variant",
                    "depth RMSE (m)",
                    "delta<1.25 (%)",
                    "mIoU (%)",
                    "Acc (%)",
                    "paper",
                ],
                rows,
            );
        }
    }
    for (label, why) in &i.plan.skipped {
        d.p(format!(
            "Variant **{label}** was skipped: this build cannot express it ({why})."
        ));
    }

    d.h(2, "Stages: wall time and peak memory");
    d.p("Per stage instance: from its cache entry (the run that computed it), and what this bench did with it. `runner` is the runner's own time on the stage in this bench (key, look-up, loading inputs, hashing and writing outputs). Peak RSS is that of the `pipe` process while the stage ran, so it includes the tables the runner keeps for later stages.");
    let rows = i
        .report
        .stages
        .iter()
        .map(|r| {
            let mf = i.manifests.get(&r.stage);
            vec![
                r.stage.clone(),
                r.kind.clone(),
                format!("{:?}", r.outcome).to_lowercase(),
                mf.map_or("—".into(), |m| runner::fmt_secs(m.wall_s)),
                mf.map_or("—".into(), |m| runner::fmt_secs(m.cpu_s)),
                mf.map_or("—".into(), |m| runner::fmt_bytes(m.peak_rss_bytes)),
                runner::fmt_secs(r.overhead_s),
            ]
        })
        .collect();
    d.table(
        &[
            "stage",
            "kind",
            "this bench",
            "wall",
            "CPU",
            "peak RSS",
            "runner",
        ],
        rows,
    );

    d.h(2, "Runner overhead");
    d.p(format!("Each command spawned {} times after a warm-up, with everything cached (a no-op); times include process start.", s.overhead_repeats));
    let mut rows: Vec<Vec<String>> = i
        .timings
        .iter()
        .map(|t| {
            vec![
                t.what.clone(),
                format!("{:.1} ms", t.median_s * 1e3),
                format!("{:.1} ms", t.min_s * 1e3),
                if t.ok { "ok".into() } else { "FAILED".into() },
            ]
        })
        .collect();
    let ran: Vec<f64> = i
        .report
        .stages
        .iter()
        .filter(|r| r.outcome == Outcome::Ran)
        .map(|r| r.overhead_s)
        .collect();
    if !ran.is_empty() {
        let max = ran.iter().cloned().fold(0.0, f64::max);
        let mean = ran.iter().sum::<f64>() / ran.len() as f64;
        rows.push(vec![
            format!(
                "runner time per re-run stage beyond its own work ({} stages)",
                ran.len()
            ),
            format!("{:.1} ms (mean)", mean * 1e3),
            format!("{:.1} ms (max)", max * 1e3),
            "".into(),
        ]);
    }
    d.table(&["what", "median", "min / max", ""], rows);
    if !i.base_fresh {
        d.p(format!(
            "`{}` was not up to date, so no no-op `pipe run` of it was timed (run it once first).",
            i.opts.base_file.display()
        ));
    }

    d.h(2, "Files");
    d.p(format!("`{RESULTS_FILE}`: one row per scene x variant x budget x method x metric (columns scene, variant, budget, method, metric, value, train_wall_s); methods `panoptic_nerf`, `fixed_field`, `pseudo_labels`, `first_primitive` carry the evaluate stage's metrics, `stage:ROLE` rows carry wall_s, cpu_s and peak_rss_bytes of each stage. `{PIPELINE_FILE}`: the pipeline the bench ran (`pipe status -f` it). `{RUN_REPORT_FILE}`: the runner's report of this bench."));
    d.h(2, "Suite");
    d.code(s.text.trim_end());
    d
}
