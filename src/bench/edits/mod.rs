//! `pipe bench --suite edits`: relabelling after an edit of the boxes. For every scene, seed
//! and edit of the suite it runs the base pipeline before the edit (the parent), with the edit
//! (an update: `pipe run`) and with the edit from scratch (`pipe run --cold`), each up to the
//! suite's `until` stage, one after another on one cache (an update starts from the stage's last
//! run, so the runs cannot be interleaved), and writes `REPORT.md` and `results.csv`: time and
//! peak memory of update and cold run, and the scores of [`measure`].

mod measure;
pub mod suite;

use std::{
    fmt::Write as _,
    path::{Path, PathBuf},
    time::Instant,
};

use serde_yaml::Value as Yaml;

pub use suite::{load, EditsSuite};

use crate::{
    bench::BenchError,
    config::{self, Override},
    error::IoContext,
    runner::{fmt_bytes, Outcome, RunReport},
    store::{Entry, Store},
};
use measure::{Entries, Measured};

/// What `pipe bench --suite edits` was asked to do.
pub struct EditsOptions {
    pub base_file: PathBuf,
    /// `--cache`, else the base pipeline's cache.
    pub cache: Option<PathBuf>,
    /// `--set` overrides applied to every run.
    pub set: Vec<Override>,
    pub suite: EditsSuite,
    pub out: PathBuf,
}

/// What a run computed (the stages that did not reuse an entry of the run before the edit).
#[derive(Debug, Clone, Default)]
pub struct Cost {
    pub wall_s: f64,
    pub cpu_s: f64,
    pub peak_rss: u64,
    /// Stages found cached, whose figures are the cache's records of when they were computed.
    pub recorded: usize,
    /// `stage: outcome (reason)` of each stage computed.
    pub stages: Vec<String>,
}

/// One edit on one scene and seed.
pub struct EditRow {
    pub scene: String,
    pub seed: String,
    pub edit: String,
    pub label: String,
    pub update: Cost,
    pub cold: Cost,
    pub scores: Measured,
}

fn override_of(key: &str, value: Yaml) -> Override {
    let (stage, param) = key.split_once('.').unwrap_or((key, ""));
    Override {
        stage: stage.into(),
        param: param.into(),
        arg: format!(
            "{key}={}",
            serde_yaml::to_string(&value).unwrap_or_default().trim()
        ),
        value,
    }
}

/// One run of the base pipeline with `extra` settings, up to `until`.
/// How a run of the bench computes what is stale.
#[derive(Clone, Copy, PartialEq)]
enum Mode {
    /// Updating wherever a stage can, every stage computed now (even where the update or the
    /// result from scratch is cached).
    Update,
    /// As `pipe run --cold`: the edit from scratch, and the run before it (cached entries as
    /// they are, never an update of the last run: the scene before an addition is a scene a
    /// user ran, not one derived from the previous case's).
    Cold,
}

/// One run of `file` with `extra` settings, up to `until`, as a user runs it: `pipe run` in a
/// process of its own (so its time and peak memory are the run's alone); its report is the
/// cache's `runs/last-run.json`.
fn run_once(
    opts: &EditsOptions,
    file: &Path,
    extra: Vec<Override>,
    until: &str,
    mode: Mode,
) -> Result<(RunReport, f64), BenchError> {
    let exe = std::env::current_exe().io_context(|| "finding the pipe executable".to_string())?;
    let mut cmd = std::process::Command::new(exe);
    cmd.arg("run").arg("-f").arg(file).args(["--until", until]);
    if let Some(c) = &opts.cache {
        cmd.arg("--cache").arg(c);
    }
    for o in opts.set.iter().chain(&extra) {
        cmd.arg("--set").arg(&o.arg);
    }
    match mode {
        Mode::Update => {
            // Computed now, as an update, even where an earlier bench left the entry cached:
            // the update's time is measured, never taken from a record.
            cmd.args(["--prefer-update", "--force-all"]);
        }
        Mode::Cold => {
            cmd.arg("--cold");
        }
    }
    let t0 = Instant::now();
    // Its progress and log lines go to the bench's stderr; its summary table is not needed.
    let status = cmd
        .stdout(std::process::Stdio::null())
        .status()
        .io_context(|| format!("running pipe run -f {}", file.display()))?;
    let wall = t0.elapsed().as_secs_f64();
    if !status.success() {
        return Err(BenchError::PipelineFailed(file.to_path_buf()));
    }
    let cache = match &opts.cache {
        Some(c) => c.clone(),
        None => config::load(file, &[])?.cache_dir,
    };
    let path = cache.join("runs").join("last-run.json");
    let bytes = std::fs::read(&path).io_context(|| format!("reading {}", path.display()))?;
    let report: RunReport = serde_json::from_slice(&bytes).map_err(|source| BenchError::Json {
        what: format!("reading {}", path.display()),
        source,
    })?;
    Ok((report, wall))
}

fn key_of(report: &RunReport, stage: &str) -> Result<String, BenchError> {
    report
        .stages
        .iter()
        .find(|s| s.stage == stage)
        .and_then(|s| s.key.clone())
        .ok_or_else(|| BenchError::Results(format!("the run has no entry of stage `{stage}`")))
}

/// What `report` computed that the run `before` had not: the stages it ran, timed now (`wall`
/// is the run's wall clock), and the ones it found cached, from the cache's records of when
/// they were computed.
fn cost(store: &Store, report: &RunReport, before: &RunReport, wall: f64) -> Cost {
    let computed = report
        .stages
        .iter()
        .any(|s| matches!(s.outcome, Outcome::Ran | Outcome::Updated));
    let mut c = Cost {
        wall_s: if computed { wall } else { 0.0 },
        ..Default::default()
    };
    for s in &report.stages {
        let old = before.stages.iter().find(|b| b.stage == s.stage);
        if s.key.is_none() || old.and_then(|b| b.key.as_ref()) == s.key.as_ref() {
            continue;
        }
        let Entry::Valid(m) = store.check(s.key.as_deref().unwrap_or_default(), false) else {
            continue;
        };
        if s.outcome == Outcome::Cached {
            c.recorded += 1;
            c.wall_s += m.wall_s;
            c.cpu_s += m.cpu_s;
            c.peak_rss = c.peak_rss.max(m.peak_rss_bytes);
        } else {
            c.cpu_s += s.cpu_s;
            c.peak_rss = c.peak_rss.max(s.peak_rss_bytes);
        }
        let how = match (&m.parent, &m.redone) {
            (Some(_), Some(r)) => format!("updated: {r}"),
            _ => "from scratch".into(),
        };
        let when = if s.outcome == Outcome::Cached {
            ", cached"
        } else {
            ""
        };
        c.stages.push(format!("{}: {how}{when}", s.stage));
    }
    c
}

/// Runs the suite and writes its report; returns the rows.
pub fn run(opts: &EditsOptions) -> Result<Vec<EditRow>, BenchError> {
    let s = &opts.suite;
    std::fs::create_dir_all(&opts.out).io_context(|| format!("creating {}", opts.out.display()))?;
    let scene_stage = s.edits_param.split_once('.').map_or("", |(a, _)| a);
    let seeds: Vec<Option<Yaml>> = match &s.seeds {
        Some(sd) => sd.values.iter().cloned().map(Some).collect(),
        None => vec![None],
    };
    let edits_set = |v: &Yaml| override_of(&s.edits_param, v.clone());
    let mut rows = Vec::new();
    for scene in &s.scenes {
        let file = scene.pipeline.as_deref().unwrap_or(&opts.base_file);
        let cache = config::load(file, &opts.set)?.cache_dir;
        let store = Store::open_existing(opts.cache.as_ref().unwrap_or(&cache));
        for seed in &seeds {
            let mut common: Vec<Override> = scene
                .set
                .iter()
                .map(|(k, v)| override_of(k.as_str().unwrap_or_default(), v.clone()))
                .collect();
            if let (Some(sd), Some(v)) = (&s.seeds, seed) {
                common.push(override_of(&sd.param, v.clone()));
            }
            let with = |edits: &Yaml| {
                let mut v = common.clone();
                v.push(edits_set(edits));
                v
            };
            let seed_name = seed.as_ref().map_or("-".into(), |v| {
                serde_yaml::to_string(v)
                    .unwrap_or_default()
                    .trim()
                    .to_string()
            });
            let (unedited, _) = run_once(
                opts,
                file,
                with(&Yaml::Sequence(vec![])),
                scene_stage,
                Mode::Cold,
            )?;
            for case in &s.edits {
                eprintln!(
                    "bench edits: {} seed {seed_name}: {}",
                    scene.name, case.name
                );
                let (before, _) = run_once(opts, file, with(&case.before), &s.until, Mode::Cold)?;
                let (update, wall_u) =
                    run_once(opts, file, with(&case.edits), &s.until, Mode::Update)?;
                let (cold, wall_c) = run_once(opts, file, with(&case.edits), &s.until, Mode::Cold)?;
                let entries = Entries {
                    unedited: key_of(&unedited, scene_stage)?,
                    before: key_of(&before, scene_stage)?,
                    after: key_of(&update, scene_stage)?,
                    maps_before: key_of(&before, &s.until)?,
                    maps_update: key_of(&update, &s.until)?,
                    maps_cold: key_of(&cold, &s.until)?,
                };
                let scores = measure::measure(&store, &entries, case.object, &case.edits)?;
                rows.push(EditRow {
                    scene: scene.name.clone(),
                    seed: seed_name.clone(),
                    edit: case.name.clone(),
                    label: case.label.clone(),
                    update: cost(&store, &update, &before, wall_u),
                    cold: cost(&store, &cold, &before, wall_c),
                    scores,
                });
            }
        }
    }
    write_report(opts, &rows)?;
    Ok(rows)
}

/// `mean ± sd` of `values` (the sample standard deviation; `-` without values).
fn spread(values: &[f64], digits: usize) -> String {
    if values.is_empty() {
        return "-".into();
    }
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    if values.len() == 1 {
        return format!("{mean:.digits$}");
    }
    let sd = (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    format!("{mean:.digits$} ± {sd:.digits$}")
}

/// The summary table over seeds, one line per scene and edit.
/// `car 91.2 / 90.8, road 97.0 / -`: each class of either run with its IoU in both (`-`: not
/// in that run's reach), the classes behind a reach mIoU.
fn class_ious(update: &[(u8, f64)], cold: &[(u8, f64)]) -> String {
    let classes: std::collections::BTreeSet<u8> =
        update.iter().chain(cold).map(|&(c, _)| c).collect();
    let of = |list: &[(u8, f64)], c: u8| {
        list.iter()
            .find(|x| x.0 == c)
            .map_or("-".to_string(), |x| format!("{:.1}", 100.0 * x.1))
    };
    classes
        .into_iter()
        .map(|c| {
            let name = stages::labels::by_id(c).map_or("?", |l| l.name);
            format!("{name} {} / {}", of(update, c), of(cold, c))
        })
        .collect::<Vec<_>>()
        .join(", ")
}

fn summary_table(rows: &[EditRow]) -> String {
    let mut out = String::from(
        "| scene | edit | time update / cold (s) | peak update / cold (MiB) | mIoU reach update / cold | \
         PQ reach update / cold | update vs cold mIoU | object update / cold (%) | elsewhere changed update / cold (%) |\n\
         |---|---|---|---|---|---|---|---|---|\n",
    );
    let mut keys: Vec<(&str, &str)> = Vec::new();
    for r in rows {
        if !keys.contains(&(r.scene.as_str(), r.edit.as_str())) {
            keys.push((r.scene.as_str(), r.edit.as_str()));
        }
    }
    for (scene, edit) in keys {
        let rs: Vec<&EditRow> = rows
            .iter()
            .filter(|r| r.scene == scene && r.edit == edit)
            .collect();
        let col = |f: &dyn Fn(&EditRow) -> Option<f64>, scale: f64, digits: usize| {
            let v: Vec<f64> = rs.iter().filter_map(|r| f(r)).map(|v| v * scale).collect();
            spread(&v, digits)
        };
        let mib = 1.0 / (1u64 << 20) as f64;
        let _ = writeln!(
            out,
            "| {scene} | {edit} | {} / {} | {} / {} | {} / {} | {} / {} | {} | {} / {} | {} / {} |",
            col(&|r| Some(r.update.wall_s), 1.0, 1),
            col(&|r| Some(r.cold.wall_s), 1.0, 1),
            col(&|r| Some(r.update.peak_rss as f64), mib, 0),
            col(&|r| Some(r.cold.peak_rss as f64), mib, 0),
            col(&|r| r.scores.update.miou, 100.0, 1),
            col(&|r| r.scores.cold.miou, 100.0, 1),
            col(&|r| r.scores.update.pq, 100.0, 1),
            col(&|r| r.scores.cold.pq, 100.0, 1),
            col(&|r| r.scores.update_vs_cold, 100.0, 1),
            col(&|r| r.scores.update.object, 100.0, 1),
            col(&|r| r.scores.cold.object, 100.0, 1),
            col(&|r| Some(r.scores.update.elsewhere_changed), 100.0, 2),
            col(&|r| Some(r.scores.cold.elsewhere_changed), 100.0, 2),
        );
    }
    out
}

fn write_report(opts: &EditsOptions, rows: &[EditRow]) -> Result<(), BenchError> {
    let s = &opts.suite;
    let mut md = format!(
        "# pipe bench: {}\n\nBase pipeline `{}`, every run up to `{}`; edits through `{}`. \
         Mean ± sd over {} seed(s).\n\n",
        s.name,
        opts.base_file.display(),
        s.until,
        s.edits_param,
        s.seeds.as_ref().map_or(1, |sd| sd.values.len()),
    );
    md.push_str(
        "*Reach*: the pixels whose ray meets a changed box (old or new extent), scored against \
         GT with the edit applied (a relabelled object's pixels take its new class). *Object*: \
         the edited object's GT pixels labelled with the class its box has after the edit (for \
         a deleted box: its old class). *Elsewhere changed*: the other pixels whose label \
         differs from the run before the edit. Time: wall clock of `pipe run` (update) and \
         `pipe run --cold` up to the last stage; the stages found cached (computed by an \
         earlier run: a scene or plan another seed shares) add the times the cache recorded.\n\n",
    );
    md.push_str(&summary_table(rows));
    md.push_str("\n## Every run\n\n");
    for r in rows {
        let _ = writeln!(
            md,
            "- **{} seed {} {}** ({}): update {:.1} s (peak {}), cold {:.1} s (peak {}); reach {:.1} % \
             of the pixels, class {}\n  - update: {}\n  - cold: {}",
            r.scene,
            r.seed,
            r.edit,
            r.label,
            r.update.wall_s,
            fmt_bytes(r.update.peak_rss),
            r.cold.wall_s,
            fmt_bytes(r.cold.peak_rss),
            100.0 * r.scores.reach,
            r.scores.class,
            r.update.stages.join("; "),
            r.cold.stages.join("; "),
        );
        let _ = writeln!(
            md,
            "  - reach IoU by class, update / cold: {}",
            class_ious(&r.scores.update.class_iou, &r.scores.cold.class_iou)
        );
    }
    let md_path = opts.out.join("REPORT.md");
    std::fs::write(&md_path, md).io_context(|| format!("writing {}", md_path.display()))?;
    let mut csv = String::from(
        "scene,seed,edit,run,wall_s,cpu_s,peak_rss_bytes,miou_reach,pq_reach,object,\
         elsewhere_changed,update_vs_cold_miou,reach,stages_recorded\n",
    );
    let num = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.6}"));
    for r in rows {
        for (run, c, sc) in [
            ("update", &r.update, &r.scores.update),
            ("cold", &r.cold, &r.scores.cold),
        ] {
            let _ = writeln!(
                csv,
                "{},{},{},{run},{:.3},{:.3},{},{},{},{},{:.6},{},{:.6},{}",
                r.scene,
                r.seed,
                r.edit,
                c.wall_s,
                c.cpu_s,
                c.peak_rss,
                num(sc.miou),
                num(sc.pq),
                num(sc.object),
                sc.elsewhere_changed,
                if run == "update" {
                    num(r.scores.update_vs_cold)
                } else {
                    String::new()
                },
                r.scores.reach,
                c.recorded,
            );
        }
    }
    let csv_path = opts.out.join("results.csv");
    std::fs::write(&csv_path, csv).io_context(|| format!("writing {}", csv_path.display()))?;
    Ok(())
}

/// The files the bench wrote under `out`.
pub fn files(out: &Path) -> Vec<PathBuf> {
    vec![out.join("REPORT.md"), out.join("results.csv")]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spread_is_mean_and_sample_sd() {
        assert_eq!(spread(&[1.0, 2.0, 3.0], 2), "2.00 ± 1.00");
        assert_eq!(spread(&[4.0], 1), "4.0");
        assert_eq!(spread(&[], 1), "-");
    }
}
