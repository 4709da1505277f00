//! The bench report (`REPORT.md` and `report.html`): machine and build, time against error per
//! scene, the ablation, stage costs, runner overhead. Which metrics the tables show, with
//! which labels, units and decimals, comes from the scoring kind's [`ScoreSpec`]; published
//! figures beside the ablation come from the suite (`paper:`).

use std::path::Path;

use stages::{MetricInfo, ScoreSpec};

use super::{
    doc::Doc,
    machine::{self, Timing},
    plan::{Plan, Run},
    results::{spread, Manifests, Row, Spread},
    suite::{Suite, Variant},
};
use crate::runner::{fmt_bytes, fmt_secs, Outcome, RunReport};

/// File names under the output directory.
pub const PIPELINE_FILE: &str = "pipeline.yaml";
pub const RUN_REPORT_FILE: &str = "run-report.json";
pub const RESULTS_FILE: &str = "results.parquet";

/// Everything the report shows.
pub(super) struct Input<'a> {
    pub suite: &'a Suite,
    pub base_file: &'a Path,
    pub base_text: &'a str,
    pub plan: &'a Plan,
    pub rows: &'a [Row],
    pub report: &'a RunReport,
    pub manifests: &'a Manifests,
    pub timings: &'a [Timing],
    /// Whether the base pipeline was up to date (then its no-op run was timed).
    pub base_fresh: bool,
    pub wall_s: f64,
}

/// `a`, `a and b`, `a, b and c`.
pub(super) fn and_list(items: &[String]) -> String {
    match items {
        [] => String::new(),
        [one] => one.clone(),
        [rest @ .., last] => format!("{} and {last}", rest.join(", ")),
    }
}

/// The metrics of `names` the spec describes, in that order.
fn metrics(spec: &'static ScoreSpec, names: &[&str]) -> Vec<&'static MetricInfo> {
    names.iter().filter_map(|n| spec.metric(n)).collect()
}

/// A metric's value as the spec shows it (scaled, with its decimals); `—` when absent.
fn cell(v: Option<f64>, m: &MetricInfo) -> String {
    v.map_or("—".into(), |v| format!("{:.*}", m.decimals, v * m.scale))
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

impl Input<'_> {
    fn spec(&self) -> &'static ScoreSpec {
        self.plan.spec
    }

    fn variant(&self, name: &str) -> Option<&Variant> {
        self.suite.variants.iter().find(|v| v.name == name)
    }

    /// Ours' `metric` in `run`'s (scene, variant, budget) over its seeds; none for a semantic
    /// metric of a variant without semantics.
    fn ours_spread(&self, run: &Run, semantics: bool, metric: &MetricInfo) -> Option<Spread> {
        if !semantics && metric.semantic {
            return None;
        }
        spread(
            self.rows,
            &run.scene,
            &run.variant,
            run.budget,
            self.spec().method,
            metric.name,
        )
    }

    /// Ours' `metric` in `run`: the mean over its seeds.
    fn ours(&self, run: &Run, semantics: bool, metric: &MetricInfo) -> Option<f64> {
        self.ours_spread(run, semantics, metric).map(|s| s.mean)
    }

    /// [`Input::ours`] as a table shows it: with the seeds' standard deviation when there are
    /// several.
    fn ours_cell(&self, run: &Run, semantics: bool, metric: &MetricInfo) -> String {
        match self.ours_spread(run, semantics, metric) {
            Some(s) if s.n > 1 => format!(
                "{} ± {:.*}",
                cell(Some(s.mean), metric),
                metric.decimals,
                s.sd * metric.scale
            ),
            s => cell(s.map(|s| s.mean), metric),
        }
    }

    /// Wall time of the training stage of `run` (the mean over its seeds).
    fn train_wall(&self, run: &Run) -> f64 {
        let walls: Vec<f64> = self
            .plan
            .seeds_of(run)
            .map(|r| self.manifests[&r.instances[&self.plan.train_role]].wall_s)
            .collect();
        walls.iter().sum::<f64>() / walls.len().max(1) as f64
    }

    /// Training time to come within one unit of the headline metric (1 mIoU) of the first
    /// variant's largest budget (the stand-in for the converged value), on one scene; None
    /// when the variant ran at fewer than two budgets.
    fn speed_to_goal(&self, scene: &str) -> Option<String> {
        let headline = self.spec().metric(self.spec().headline)?;
        let variant = &self.suite.variants.first()?.name;
        let mut runs: Vec<&Run> = self
            .plan
            .cells()
            .filter(|r| r.scene == scene && &r.variant == variant)
            .collect();
        runs.sort_by_key(|r| r.budget);
        let last = *runs.last()?;
        if runs.len() < 2 {
            return None;
        }
        let score = |r: &Run| self.ours(r, true, headline);
        let reference = score(last)?;
        let first = runs
            .iter()
            .find(|r| score(r).is_some_and(|m| m >= reference - 1.0 / headline.scale))?;
        let label = headline.label;
        let goal = match self.suite.goal_train_s {
            Some(g) if self.train_wall(first) <= g => {
                format!(" (within the goal of at most {g} s)")
            }
            Some(g) => format!(" (over the goal of at most {g} s)"),
            None => String::new(),
        };
        Some(format!(
            "Speed to the goal: the largest budget ({} steps, {:.1} s of training) reaches {} {label}; the first budget within 1 {label} of it is {} steps, {} {label} after {:.1} s of training{goal}.",
            last.budget,
            self.train_wall(last),
            cell(Some(reference), headline),
            first.budget,
            cell(score(first), headline),
            self.train_wall(first),
        ))
    }
}

/// The whole report.
pub(super) fn doc(i: &Input) -> Doc {
    let mut d = Doc::default();
    header(&mut d, i);
    machine_and_build(&mut d, i);
    time_against_error(&mut d, i);
    ablation(&mut d, i);
    stage_costs(&mut d, i);
    runner_overhead(&mut d, i);
    files(&mut d, i);
    d.h(2, "Suite");
    d.code(i.suite.text.trim_end());
    d
}

fn header(d: &mut Doc, i: &Input) {
    let s = i.suite;
    d.h(1, format!("pipe bench: suite `{}`", s.name));
    if !s.description.is_empty() {
        d.p(&s.description);
    }
    d.p("**Error figures are reproducible**: the same suite and build on the same machine give the same metrics (scenes and training are seeded, and stages are cached by content). **Times vary** from run to run and machine to machine; a stage reused from the cache reports the wall time of the run that computed it.");
    let (ran, cached) = (
        i.report.count(Outcome::Ran) + i.report.count(Outcome::Updated),
        i.report.count(Outcome::Cached),
    );
    d.p(format!(
        "This bench took {:.1} s: {ran} stages ran, {cached} came from the cache.",
        i.wall_s
    ));
}

fn machine_and_build(d: &mut Doc, i: &Input) {
    let s = i.suite;
    let m = machine::machine();
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
    if let Some(seeds) = &s.seeds {
        let values: Vec<String> = seeds.values.iter().map(u64::to_string).collect();
        seed_list.push(format!(
            "every run once per `{}` in {} (tables: mean ± standard deviation over them)",
            seeds.param.key,
            values.join(", ")
        ));
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
            vec!["base pipeline".into(), format!("`{}` (blake3 {})", i.base_file.display(), hash(i.base_text))],
            vec!["pipeline hash".into(), format!("{} (blake3 over every stage's cache key; the generated pipeline is `{PIPELINE_FILE}`, blake3 {})", hash(&key_text), hash(&i.plan.yaml))],
            vec!["seeds".into(), seed_list.join("; ")],
        ],
    );
}

/// `mIoU, Acc and PQ in %, depth RMSE in m`: the metrics grouped by unit.
fn units(ms: &[&MetricInfo]) -> String {
    let mut by_unit: Vec<(&str, Vec<String>)> = Vec::new();
    for m in ms {
        match by_unit.iter_mut().find(|(u, _)| *u == m.unit) {
            Some((_, labels)) => labels.push(m.label.to_string()),
            None => by_unit.push((m.unit, vec![m.label.to_string()])),
        }
    }
    let parts: Vec<String> = by_unit
        .iter()
        .map(|(u, labels)| match *u {
            "" => format!("{} as plain numbers", and_list(labels)),
            u => format!("{} in {u}", and_list(labels)),
        })
        .collect();
    parts.join(", ")
}

fn time_against_error(d: &mut Doc, i: &Input) {
    let (s, spec) = (i.suite, i.spec());
    let per_run = metrics(spec, spec.per_run);
    let plotted: Vec<String> = metrics(spec, spec.plotted)
        .iter()
        .map(|m| m.label.to_string())
        .collect();
    let flat: Vec<String> = spec
        .baselines
        .iter()
        .filter(|b| !b.depends_on_budget)
        .map(|b| b.label.to_string())
        .collect();
    d.h(2, "Time against error");
    d.p(format!(
        "Ours (`{}`) per variant and training budget, against the training stage's wall time. The plots draw the variants run at several budgets; the baselines that do not depend on the training budget ({}) are flat lines. {}.",
        spec.method,
        and_list(&flat),
        units(&per_run)
    ));
    for note in spec.notes {
        d.p(format!("{note}."));
    }
    for sc in &s.scenes {
        d.h(3, format!("Scene `{}`", sc.name));
        d.image(
            format!("time_vs_error_{}.png", sc.name),
            format!("{}: {} against training time", sc.name, and_list(&plotted)),
        );
        let mut rows = Vec::new();
        for run in i.plan.cells().filter(|r| r.scene == sc.name) {
            let v = i.variant(&run.variant);
            let sem = v.is_none_or(|v| v.semantics);
            let mut row = vec![
                v.map_or(run.variant.clone(), |v| v.label.clone()),
                run.budget.to_string(),
                format!("{:.1}", i.train_wall(run)),
            ];
            row.extend(per_run.iter().map(|m| i.ours_cell(run, sem, m)));
            rows.push(row);
        }
        let mut header = vec!["variant", "budget", "train wall s"];
        header.extend(per_run.iter().map(|m| m.label));
        d.table(&header, rows);
        if let Some(line) = i.speed_to_goal(&sc.name) {
            d.p(line);
        }
        baselines(d, i, &sc.name);
    }
}

/// The baselines of one scene, from the longest run of the first variant.
fn baselines(d: &mut Doc, i: &Input, scene: &str) {
    let spec = i.spec();
    let first = i.suite.variants.first().map(|v| v.name.as_str());
    let longest = i
        .plan
        .cells()
        .filter(|r| r.scene == scene && Some(r.variant.as_str()) == first)
        .max_by_key(|r| r.budget);
    let Some(run) = longest.or_else(|| i.plan.cells().find(|r| r.scene == scene)) else {
        return;
    };
    let per_baseline = metrics(spec, spec.per_baseline);
    let rows = spec
        .baselines
        .iter()
        .map(|b| {
            let mut row = vec![b.name.to_string()];
            row.extend(per_baseline.iter().map(|m| {
                let v = spread(i.rows, &run.scene, &run.variant, run.budget, b.name, m.name);
                cell(v.map(|s| s.mean), m)
            }));
            row
        })
        .collect();
    let dependent: Vec<String> = spec
        .baselines
        .iter()
        .filter(|b| b.depends_on_budget)
        .map(|b| format!("`{}`", b.name))
        .collect();
    d.p(match dependent.len() {
        0 => "Baselines (they do not depend on the training budget):".to_string(),
        n => format!(
            "Baselines, from the longest run of the first variant ({} {} on the training budget; the others do not):",
            and_list(&dependent),
            if n == 1 { "depends" } else { "depend" }
        ),
    });
    let mut header = vec!["method"];
    header.extend(per_baseline.iter().map(|m| m.label));
    d.table(&header, rows);
}

fn ablation(d: &mut Doc, i: &Input) {
    let (s, spec) = (i.suite, i.spec());
    let ablated = metrics(spec, spec.ablation);
    d.h(2, format!("Ablation (budget {})", s.ablation_budget));
    let mut text = format!(
        "Ours (`{}`) per variant, at the same training budget.",
        spec.method
    );
    let unsupervised: Vec<String> = s
        .variants
        .iter()
        .filter(|v| !v.semantics)
        .map(|v| v.label.clone())
        .collect();
    if !unsupervised.is_empty() {
        let label_free: Vec<String> = ablated
            .iter()
            .filter(|m| !m.semantic)
            .map(|m| m.label.to_string())
            .collect();
        text.push_str(&format!(
            " Without semantic supervision ({}), only {} {} reported.",
            and_list(&unsupervised),
            and_list(&label_free),
            if label_free.len() == 1 { "is" } else { "are" },
        ));
    }
    if let Some(p) = &s.paper {
        text.push(' ');
        text.push_str(&p.note);
    }
    d.p(text);
    for sc in &s.scenes {
        let mut rows = Vec::new();
        for v in &s.variants {
            let Some(run) = i.plan.cells().find(|r| {
                r.scene == sc.name && r.variant == v.name && r.budget == s.ablation_budget
            }) else {
                continue;
            };
            let mut row = vec![v.label.clone()];
            row.extend(ablated.iter().map(|m| i.ours_cell(run, v.semantics, m)));
            if s.paper.is_some() {
                row.push(v.paper.clone().unwrap_or_default());
            }
            rows.push(row);
        }
        if !rows.is_empty() {
            d.h(3, format!("Scene `{}`", sc.name));
            let mut header: Vec<String> = vec!["variant".into()];
            header.extend(ablated.iter().map(|m| format!("{} ({})", m.label, m.unit)));
            header.extend(s.paper.iter().map(|p| p.column.clone()));
            let header: Vec<&str> = header.iter().map(String::as_str).collect();
            d.table(&header, rows);
        }
    }
    for (label, why) in &i.plan.skipped {
        d.p(format!(
            "Variant **{label}** was skipped: this build cannot express it ({why})."
        ));
    }
}

fn stage_costs(d: &mut Doc, i: &Input) {
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
                mf.map_or("—".into(), |m| fmt_secs(m.wall_s)),
                mf.map_or("—".into(), |m| fmt_secs(m.cpu_s)),
                mf.map_or("—".into(), |m| fmt_bytes(m.peak_rss_bytes)),
                fmt_secs(r.overhead_s),
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
}

fn runner_overhead(d: &mut Doc, i: &Input) {
    d.h(2, "Runner overhead");
    d.p(format!("Each command spawned {} times after a warm-up, with everything cached (a no-op); times include process start.", i.suite.overhead_repeats));
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
        .filter(|r| matches!(r.outcome, Outcome::Ran | Outcome::Updated))
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
            i.base_file.display()
        ));
    }
}

fn files(d: &mut Doc, i: &Input) {
    let spec = i.spec();
    let methods: Vec<String> = std::iter::once(spec.method)
        .chain(spec.baselines.iter().map(|b| b.name))
        .map(|m| format!("`{m}`"))
        .collect();
    d.h(2, "Files");
    d.p(format!("`{RESULTS_FILE}`: one row per scene x variant x budget x seed x method x metric (columns scene, variant, budget, seed (null without `seeds:`), method, metric, value, train_wall_s); methods {} carry the `{}` stage's `{}` table, `stage:ROLE` rows carry wall_s, cpu_s and peak_rss_bytes of each stage. `{PIPELINE_FILE}`: the pipeline the bench ran (`pipe status -f` it). `{RUN_REPORT_FILE}`: the runner's report of this bench.", methods.join(", "), i.plan.eval_role, spec.table));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lists_and_units_read_as_prose() {
        let s = |v: &[&str]| v.iter().map(|x| x.to_string()).collect::<Vec<_>>();
        assert_eq!(and_list(&s(&["a"])), "a");
        assert_eq!(and_list(&s(&["a", "b", "c"])), "a, b and c");
        let spec = stages::kinds::find("evaluate").unwrap().scores().unwrap();
        assert_eq!(
            units(&metrics(spec, spec.per_run)),
            "mIoU, Acc, PQ, PQ (panopticapi), delta<1.25, delta<1.25 vs exact depth, review recall@5% and review top-20 region precision in %, depth RMSE, depth RMSE inside regions, depth RMSE vs exact depth and depth RMSE vs exact depth inside regions in m, review AUROC and review per-frame rank corr. as plain numbers"
        );
    }
}
