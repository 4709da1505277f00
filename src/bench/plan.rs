//! Turns a suite and a base pipeline into one ordinary pipeline file: for every (scene,
//! variant, budget) the base stages up to the one whose kind scores methods
//! (`Stage::scores`, e.g. `evaluate`), with the suite's parameter overrides applied and the
//! budget set on the parameter the registry names (`Stage::budget_param`, e.g. training
//! iterations). Stage instances whose kind, parameters and inputs are equal across runs are
//! declared once (the scene and rays of a scene are shared by every variant and budget), so the
//! runner computes each once and the cache shares everything else.
//!
//! With `seeds:` every run is repeated once per seed value.
//!
//! Instances are named `ROLE-SCENE[-VARIANT][-bBUDGET][-sSEED]`, where ROLE is the base stage's
//! name and the variant, budget and seed parts appear only when that role depends on them.

use std::{
    collections::{BTreeMap, BTreeSet},
    path::Path,
};

use serde_json::Value;
use serde_yaml::{Mapping, Value as Yaml};
use stages::ScoreSpec;

use super::suite::{Setting, Suite, Variant};
use crate::config::{set_path, ConfigError, Loc};

/// One (scene, variant, budget, seed) combination and the stage instances that compute it.
#[derive(Debug, Clone)]
pub struct Run {
    pub scene: String,
    pub variant: String,
    pub budget: u64,
    /// The value of the suite's seed parameter (`None`: the suite has no `seeds:`).
    pub seed: Option<u64>,
    /// Base stage name (role) -> stage instance name in the generated pipeline.
    pub instances: BTreeMap<String, String>,
}

/// The generated pipeline and what it computes.
#[derive(Debug, Clone)]
pub struct Plan {
    /// The pipeline file text (`cache:` absolute).
    pub yaml: String,
    pub runs: Vec<Run>,
    /// The base stages kept (ancestors of `evaluate`, and it), in dependency order.
    pub roles: Vec<String>,
    /// The role whose wall time is the training time (the stage `budget_param` names).
    pub train_role: String,
    /// The role whose kind scores methods: it writes the score table.
    pub eval_role: String,
    /// How that score table reads.
    pub spec: &'static ScoreSpec,
    /// Variants left out, with the reason (optional ones this build cannot express).
    pub skipped: Vec<(String, String)>,
}

impl Plan {
    /// One run per (scene, variant, budget), its first seed's: the tables have a row for each
    /// (with figures over all its seeds).
    pub fn cells(&self) -> impl Iterator<Item = &Run> {
        self.runs
            .iter()
            .enumerate()
            .filter(|&(k, r)| !self.runs[..k].iter().any(|o| o.same_cell(r)))
            .map(|(_, r)| r)
    }

    /// The runs of `run`'s (scene, variant, budget), one per seed.
    pub fn seeds_of<'a>(&'a self, run: &'a Run) -> impl Iterator<Item = &'a Run> {
        self.runs.iter().filter(move |o| o.same_cell(run))
    }
}

impl Run {
    fn same_cell(&self, o: &Run) -> bool {
        (self.scene.as_str(), self.variant.as_str(), self.budget)
            == (o.scene.as_str(), o.variant.as_str(), o.budget)
    }
}

fn cfg_err(suite: &Suite, s: &Setting, msg: String) -> ConfigError {
    ConfigError {
        file: suite.file.clone(),
        loc: s.loc.clone(),
        stage: None,
        key: Some(s.path.clone()),
        message: msg,
    }
}

/// The base pipeline's stages: name -> (kind, params, inputs), in file order.
struct BaseStage {
    name: String,
    kind: String,
    params: Yaml,
    inputs: BTreeMap<String, String>,
}

fn base_stages(text: &str) -> Vec<BaseStage> {
    let doc: Yaml = serde_yaml::from_str(text).unwrap_or(Yaml::Null);
    let Some(Yaml::Mapping(stages)) = doc.get("stages") else {
        return Vec::new();
    };
    stages
        .iter()
        .map(|(k, v)| BaseStage {
            name: k.as_str().unwrap_or_default().to_string(),
            kind: v
                .get("uses")
                .and_then(Yaml::as_str)
                .unwrap_or_default()
                .to_string(),
            params: v.get("params").cloned().unwrap_or(Yaml::Null),
            inputs: match v.get("inputs") {
                Some(Yaml::Mapping(m)) => m
                    .iter()
                    .map(|(a, b)| {
                        (
                            a.as_str().unwrap_or_default().to_string(),
                            b.as_str().unwrap_or_default().to_string(),
                        )
                    })
                    .collect(),
                _ => BTreeMap::new(),
            },
        })
        .collect()
}

/// Checks that `key` (`stage.param.field...`) names a parameter of the base pipeline; the
/// error text says what is known at the level that failed.
fn check_key(base: &[BaseStage], base_file: &Path, key: &str) -> Result<(), String> {
    let mut parts = key.split('.');
    let stage = parts.next().unwrap_or_default();
    let Some(s) = base.iter().find(|s| s.name == stage) else {
        return Err(format!(
            "no stage `{stage}` in {} (stages: {})",
            base_file.display(),
            base.iter()
                .map(|s| s.name.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        ));
    };
    let kind = stages::kinds::find(&s.kind).ok_or_else(|| format!("unknown kind `{}`", s.kind))?;
    let path = key.split_once('.').map_or("", |(_, rest)| rest);
    let mut cur = kind.default_params();
    let mut walked = Vec::new();
    for p in parts {
        let next =
            match &cur {
                Value::Object(o) => {
                    o.get(p).cloned().ok_or_else(|| {
                        if let Some(to) = kind.moved_param(path) {
                            return stages::params_doc::moved_message(stage, &s.kind, path, &to);
                        }
                        format!(
                    "unknown parameter `{}` of stage `{stage}` (kind `{}`; known there: {})",
                    walked.iter().chain([&p]).cloned().collect::<Vec<_>>().join("."),
                    s.kind,
                    o.keys().cloned().collect::<Vec<_>>().join(", ")
                )
                    })?
                }
                _ => {
                    return Err(format!(
                        "parameter `{}` of stage `{stage}` is not a mapping",
                        walked.join(".")
                    ))
                }
            };
        walked.push(p);
        cur = next;
    }
    Ok(())
}

/// Base stages in dependency order, restricted to the scoring stage's ancestors and itself.
fn kept_roles(base: &[BaseStage], eval: &str) -> Vec<String> {
    let mut keep = BTreeSet::new();
    let mut todo = vec![eval.to_string()];
    while let Some(n) = todo.pop() {
        if keep.insert(n.clone()) {
            if let Some(s) = base.iter().find(|s| s.name == n) {
                todo.extend(s.inputs.values().cloned());
            }
        }
    }
    let mut order: Vec<String> = Vec::new();
    while order.len() < keep.len() {
        let before = order.len();
        for s in base {
            if keep.contains(&s.name)
                && !order.contains(&s.name)
                && s.inputs.values().all(|u| order.contains(u))
            {
                order.push(s.name.clone());
            }
        }
        if order.len() == before {
            break; // a cycle: config::load has already refused it
        }
    }
    order
}

fn base_err(base_file: &Path, message: String) -> ConfigError {
    ConfigError {
        file: base_file.to_path_buf(),
        loc: Loc::Unknown,
        stage: None,
        key: None,
        message,
    }
}

/// Names of the registry's kinds for which `has` holds (for messages).
fn kinds_with(has: impl Fn(&dyn stages::Stage) -> bool) -> String {
    let names: Vec<&str> = stages::kinds::registry()
        .iter()
        .filter(|k| has(k.as_ref()) && !k.kind().starts_with("test_"))
        .map(|k| k.kind())
        .collect();
    names.join(", ")
}

/// The base stage whose kind scores methods, and how its score table reads.
fn scoring_role(
    base: &[BaseStage],
    base_file: &Path,
) -> Result<(String, &'static ScoreSpec), ConfigError> {
    let scoring: Vec<(&BaseStage, &'static ScoreSpec)> = base
        .iter()
        .filter_map(|s| Some((s, stages::kinds::find(&s.kind)?.scores()?)))
        .collect();
    match scoring.as_slice() {
        [(one, spec)] => Ok((one.name.clone(), spec)),
        _ => Err(base_err(
            base_file,
            format!(
                "pipe bench needs a pipeline with exactly one stage whose kind scores methods (kinds: {}), found {}",
                kinds_with(|k| k.scores().is_some()),
                scoring.len()
            ),
        )),
    }
}

/// The setting the budget goes to: the suite's `budget_param`, else `ROLE.PARAM` of the one
/// kept stage whose kind names a budget parameter.
fn budget_setting(
    suite: &Suite,
    base: &[BaseStage],
    roles: &[String],
    base_file: &Path,
) -> Result<Setting, ConfigError> {
    if let Some(s) = &suite.budget_param {
        return Ok(s.clone());
    }
    let with_budget: Vec<String> = roles
        .iter()
        .filter_map(|r| {
            let s = base.iter().find(|s| &s.name == r)?;
            Some(format!(
                "{r}.{}",
                stages::kinds::find(&s.kind)?.budget_param()?
            ))
        })
        .collect();
    match with_budget.as_slice() {
        [one] => Ok(Setting {
            key: one.clone(),
            value: Yaml::Null,
            loc: Loc::Unknown,
            path: "budget_param".into(),
        }),
        _ => Err(ConfigError {
            file: suite.file.clone(),
            loc: Loc::Unknown,
            stage: None,
            key: Some("budget_param".into()),
            message: format!(
                "missing: {} stages of {} have a budget parameter (kinds with one: {}){}; name the one to vary as `budget_param: STAGE.PARAM`",
                with_budget.len(),
                base_file.display(),
                kinds_with(|k| k.budget_param().is_some()),
                if with_budget.is_empty() {
                    String::new()
                } else {
                    format!(": {}", with_budget.join(", "))
                }
            ),
        }),
    }
}

/// The variants this build can express, and those left out (optional ones naming a parameter
/// it lacks) with why.
#[allow(clippy::type_complexity)]
fn usable_variants<'a>(
    suite: &'a Suite,
    base: &[BaseStage],
    base_file: &Path,
) -> Result<(Vec<&'a Variant>, Vec<(String, String)>), ConfigError> {
    let mut skipped = Vec::new();
    let mut variants = Vec::new();
    for v in &suite.variants {
        let bad = v
            .set
            .iter()
            .find_map(|s| check_key(base, base_file, &s.key).err().map(|m| (s, m)));
        match bad {
            Some((s, m)) if v.optional => {
                skipped.push((v.label.clone(), format!("`{}`: {m}", s.key)));
            }
            Some((s, m)) => return Err(cfg_err(suite, s, m)),
            None => variants.push(v),
        }
    }
    Ok((variants, skipped))
}

/// One run's stages, with overrides applied; identity = kind + params + upstream identity.
struct Combo {
    scene: String,
    variant: String,
    budget: u64,
    seed: Option<u64>,
    params: BTreeMap<String, Yaml>,
    identity: BTreeMap<String, String>,
}

/// Every (scene, variant, budget, seed) of the suite, with its params and the identity of each
/// role.
fn combos(
    suite: &Suite,
    base: &[BaseStage],
    roles: &[String],
    variants: &[&Variant],
    extra: &[Setting],
    budget_param: &Setting,
) -> Vec<Combo> {
    let seeds: Vec<Option<u64>> = match &suite.seeds {
        Some(s) => s.values.iter().copied().map(Some).collect(),
        None => vec![None],
    };
    let mut combos = Vec::new();
    for sc in &suite.scenes {
        for v in variants.iter().filter(|v| v.scenes.contains(&sc.name)) {
            for (&b, &seed) in v
                .budgets
                .iter()
                .flat_map(|b| seeds.iter().map(move |s| (b, s)))
            {
                let mut params: BTreeMap<String, Yaml> = base
                    .iter()
                    .map(|s| (s.name.clone(), s.params.clone()))
                    .collect();
                let budget = Setting {
                    value: Yaml::Number(b.into()),
                    ..budget_param.clone()
                };
                let seed_setting = suite.seeds.as_ref().zip(seed).map(|(s, value)| Setting {
                    value: Yaml::Number(value.into()),
                    ..s.param.clone()
                });
                for s in suite
                    .set
                    .iter()
                    .chain(extra)
                    .chain(&sc.set)
                    .chain(&v.set)
                    .chain([&budget])
                    .chain(seed_setting.as_ref())
                {
                    let path: Vec<&str> = s.key.split('.').collect();
                    let p = params.get_mut(path[0]).expect("key checked");
                    set_path(p, &path[1..], &s.value);
                }
                let mut identity = BTreeMap::new();
                for r in roles {
                    let s = base.iter().find(|s| &s.name == r).expect("role");
                    let ups: BTreeMap<&String, &String> = s
                        .inputs
                        .iter()
                        .map(|(slot, up)| (slot, &identity[up]))
                        .collect();
                    let id = serde_json::to_string(&(
                        &s.kind,
                        serde_json::to_value(&params[r]).unwrap_or(Value::Null),
                        ups,
                    ))
                    .unwrap_or_default();
                    identity.insert(r.clone(), id);
                }
                combos.push(Combo {
                    scene: sc.name.clone(),
                    variant: v.name.clone(),
                    budget: b,
                    seed,
                    params,
                    identity,
                });
            }
        }
    }
    combos
}

/// What distinguishes the runs of one scene.
#[derive(Clone, Copy, PartialEq)]
enum Axis {
    Variant,
    Budget,
    Seed,
}

impl Axis {
    const ALL: [Axis; 3] = [Axis::Variant, Axis::Budget, Axis::Seed];

    fn same(self, a: &Combo, b: &Combo) -> bool {
        match self {
            Axis::Variant => a.variant == b.variant,
            Axis::Budget => a.budget == b.budget,
            Axis::Seed => a.seed == b.seed,
        }
    }
}

/// Whether a role depends on `axis`: two runs differing only along it differ there.
fn depends(combos: &[Combo], role: &str, axis: Axis) -> bool {
    combos.iter().any(|a| {
        combos.iter().any(|b| {
            a.scene == b.scene
                && !axis.same(a, b)
                && Axis::ALL
                    .iter()
                    .all(|&other| other == axis || other.same(a, b))
                && a.identity[role] != b.identity[role]
        })
    })
}

/// The stage declarations of the generated pipeline (each distinct instance once) and the runs
/// with their instance names.
fn instances(base: &[BaseStage], roles: &[String], combos: &[Combo]) -> (Mapping, Vec<Run>) {
    // A role's name carries the variant (budget, seed) where two runs differing only in it
    // differ there; and where two runs differing in several differ there while the names would
    // still meet (a variant with budgets of its own), all of them.
    let mut by: BTreeMap<&String, [bool; 3]> = roles
        .iter()
        .map(|r| (r, Axis::ALL.map(|axis| depends(combos, r, axis))))
        .collect();
    for r in roles {
        let named = by[r];
        let meet = |a: &Combo, b: &Combo| {
            a.scene == b.scene
                && Axis::ALL
                    .iter()
                    .zip(named)
                    .all(|(axis, n)| !n || axis.same(a, b))
                && a.identity[r] != b.identity[r]
        };
        if combos.iter().any(|a| combos.iter().any(|b| meet(a, b))) {
            by.insert(r, [true; 3]);
        }
    }
    let mut stages_out = Mapping::new();
    let mut runs = Vec::new();
    for c in combos {
        let mut names = BTreeMap::new();
        for r in roles {
            let mut n = format!("{r}-{}", c.scene);
            let [variant, budget, seed] = by[r];
            if variant {
                n.push_str(&format!("-{}", c.variant));
            }
            if budget {
                n.push_str(&format!("-b{}", c.budget));
            }
            if let (true, Some(s)) = (seed, c.seed) {
                n.push_str(&format!("-s{s}"));
            }
            names.insert(r.clone(), n.clone());
            let key = Yaml::String(n);
            if stages_out.contains_key(&key) {
                continue;
            }
            let s = base.iter().find(|s| &s.name == r).expect("role");
            let mut decl = Mapping::new();
            decl.insert("uses".into(), Yaml::String(s.kind.clone()));
            if !s.inputs.is_empty() {
                let ins: Mapping = s
                    .inputs
                    .iter()
                    .map(|(slot, up)| (Yaml::String(slot.clone()), Yaml::String(names[up].clone())))
                    .collect();
                decl.insert("inputs".into(), Yaml::Mapping(ins));
            }
            if !c.params[r].is_null() {
                decl.insert("params".into(), c.params[r].clone());
            }
            stages_out.insert(key, Yaml::Mapping(decl));
        }
        runs.push(Run {
            scene: c.scene.clone(),
            variant: c.variant.clone(),
            budget: c.budget,
            seed: c.seed,
            instances: names,
        });
    }
    (stages_out, runs)
}

/// Builds the bench pipeline for `suite` from the base pipeline text (`base_file` already
/// validated by `config::load`), writing entries to `cache_dir`.
pub fn build(
    suite: &Suite,
    base_file: &Path,
    base_text: &str,
    extra: &[Setting],
    cache_dir: &Path,
) -> Result<Plan, ConfigError> {
    let base = base_stages(base_text);
    let (eval_role, spec) = scoring_role(&base, base_file)?;
    let roles = kept_roles(&base, &eval_role);
    let budget_param = budget_setting(suite, &base, &roles, base_file)?;
    let train_role = budget_param
        .key
        .split('.')
        .next()
        .unwrap_or_default()
        .to_string();
    for s in suite
        .set
        .iter()
        .chain(extra)
        .chain(suite.scenes.iter().flat_map(|s| &s.set))
        .chain([&budget_param])
        .chain(suite.seeds.as_ref().map(|s| &s.param))
    {
        check_key(&base, base_file, &s.key).map_err(|m| cfg_err(suite, s, m))?;
    }
    if !roles.contains(&train_role) {
        return Err(cfg_err(
            suite,
            &budget_param,
            format!("stage `{train_role}` does not feed `{eval_role}`"),
        ));
    }
    let (variants, skipped) = usable_variants(suite, &base, base_file)?;
    let combos = combos(suite, &base, &roles, &variants, extra, &budget_param);
    let (stages_out, runs) = instances(&base, &roles, &combos);
    let mut doc = Mapping::new();
    doc.insert(
        "cache".into(),
        Yaml::String(cache_dir.to_string_lossy().into_owned()),
    );
    doc.insert("stages".into(), Yaml::Mapping(stages_out));
    let body = serde_yaml::to_string(&Yaml::Mapping(doc)).unwrap_or_default();
    let yaml = format!(
        "# Generated by `pipe bench --suite {}` from {}: one instance per distinct stage.\n\
         # `pipe status -f` this file shows what the bench computed; its entries live in `cache`.\n{body}",
        suite.name,
        base_file.display()
    );
    Ok(Plan {
        yaml,
        runs,
        roles,
        train_role,
        eval_role,
        spec,
        skipped,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const BASE: &str = "stages:\n  scene:\n    uses: synthetic_scene\n    params: {frames: 6}\n  rays:\n    uses: intersect\n    inputs: {scene: scene}\n  train:\n    uses: train\n    inputs: {scene: scene, rays: rays}\n    params:\n      schedule: {iterations: 40}\n  render:\n    uses: render\n    inputs: {scene: scene, rays: rays, train: train}\n  evaluate:\n    uses: evaluate\n    inputs: {scene: scene, render: render}\n  report:\n    uses: report\n    inputs: {scene: scene, evaluate: evaluate, render: render, train: train}\n";

    fn suite(variants: &str) -> Suite {
        super::super::suite::parse(
            Path::new("s.yaml"),
            &format!("name: t\nscenes: [{{name: a}}]\nbudgets: [5, 10]\nvariants:\n{variants}"),
        )
        .unwrap()
    }

    #[test]
    fn shares_stages_that_do_not_depend_on_variant_or_budget() {
        let s = suite(
            "  - {name: full}\n  - {name: nod, set: {train.losses.depth: 0}, budgets: [10]}\n",
        );
        let p = build(&s, Path::new("p.yaml"), BASE, &[], Path::new("/c")).unwrap();
        assert_eq!(p.roles, ["scene", "rays", "train", "render", "evaluate"]);
        assert_eq!(p.runs.len(), 3);
        assert_eq!(p.runs[0].instances["scene"], "scene-a");
        assert_eq!(p.runs[2].instances["train"], "train-a-nod-b10");
        let pipe = crate::config::parse(Path::new("gen.yaml"), &p.yaml, &[]).unwrap();
        // scene, rays + 3 x (train, render, evaluate).
        assert_eq!(pipe.stages.len(), 11);
        let t = &pipe.stages[pipe.index_of("train-a-nod-b10").unwrap()];
        assert_eq!(t.params["losses"]["depth"], 0.0);
        assert_eq!(t.params["schedule"]["iterations"], 10);
    }

    #[test]
    fn variants_with_budgets_of_their_own_get_stages_of_their_own() {
        // Same settings, different budgets: the runs differ in both variant and budget.
        let s = suite("  - {name: x, budgets: [5]}\n  - {name: y, budgets: [10]}\n");
        let p = build(&s, Path::new("p.yaml"), BASE, &[], Path::new("/c")).unwrap();
        let pipe = crate::config::parse(Path::new("gen.yaml"), &p.yaml, &[]).unwrap();
        let iterations: Vec<_> = p
            .runs
            .iter()
            .map(|r| {
                let t = &pipe.stages[pipe.index_of(&r.instances["train"]).unwrap()];
                t.params["schedule"]["iterations"].clone()
            })
            .collect();
        assert_eq!(iterations, [5, 10]);
        assert_eq!(p.runs[0].instances["scene"], p.runs[1].instances["scene"]);
    }

    #[test]
    fn the_scoring_stage_and_the_budget_come_from_the_registry() {
        let s = suite("  - {name: full}\n");
        assert!(s.budget_param.is_none());
        let p = build(&s, Path::new("p.yaml"), BASE, &[], Path::new("/c")).unwrap();
        assert_eq!(
            (p.eval_role.as_str(), p.train_role.as_str()),
            ("evaluate", "train")
        );
        assert_eq!(p.spec.table, "metrics");
        let pipe = crate::config::parse(Path::new("gen.yaml"), &p.yaml, &[]).unwrap();
        let t = &pipe.stages[pipe.index_of("train-a-b5").unwrap()];
        assert_eq!(t.params["schedule"]["iterations"], 5);
        let no_eval = BASE.split("  evaluate:").next().unwrap();
        let e = build(&s, Path::new("p.yaml"), no_eval, &[], Path::new("/c")).unwrap_err();
        assert!(
            e.to_string().starts_with("p.yaml: pipe bench needs a pipeline with exactly one stage whose kind scores methods (kinds: evaluate), found 0"),
            "{e}"
        );
    }

    #[test]
    fn unknown_override_keys_name_the_suite_and_key() {
        let s = suite("  - name: v\n    set: {train.losses.nope: 0}\n");
        let e = build(&s, Path::new("p.yaml"), BASE, &[], Path::new("/c")).unwrap_err();
        let msg = e.to_string();
        assert!(
            msg.starts_with("s.yaml:6:11: `variants.0.set.train.losses.nope`"),
            "{msg}"
        );
        assert!(
            msg.contains("unknown parameter `losses.nope` of stage `train`"),
            "{msg}"
        );
        // A key of the layout before December 2026 names its new place.
        let s = suite("  - name: v\n    set: {train.train.lr: 0.1}\n");
        let msg = build(&s, Path::new("p.yaml"), BASE, &[], Path::new("/c"))
            .unwrap_err()
            .to_string();
        assert!(
            msg.contains("`train.train.lr` moved to `train.optimiser.lr`"),
            "{msg}"
        );
        let s =
            suite("  - {name: v, optional: true, set: {train.schedule.nope: 0}}\n  - {name: w}\n");
        let p = build(&s, Path::new("p.yaml"), BASE, &[], Path::new("/c")).unwrap();
        assert_eq!(p.skipped.len(), 1);
        assert_eq!(p.runs.len(), 2);
    }

    #[test]
    fn seeds_repeat_every_run_and_name_only_the_stages_they_reach() {
        let s = super::super::suite::parse(
            Path::new("s.yaml"),
            "name: t\nscenes: [{name: a}]\nbudgets: [5, 10]\nseeds: {param: train.seed, values: [0, 7]}\nvariants:\n  - {name: full}\n",
        )
        .unwrap();
        let p = build(&s, Path::new("p.yaml"), BASE, &[], Path::new("/c")).unwrap();
        assert_eq!(p.runs.len(), 4);
        let pipe = crate::config::parse(Path::new("gen.yaml"), &p.yaml, &[]).unwrap();
        // scene, rays + 4 x (train, render, evaluate).
        assert_eq!(pipe.stages.len(), 14);
        for r in &p.runs {
            let seed = r.seed.unwrap();
            assert_eq!(r.instances["scene"], "scene-a");
            let train = format!("train-a-b{}-s{seed}", r.budget);
            assert_eq!(r.instances["train"], train);
            let t = &pipe.stages[pipe.index_of(&train).unwrap()];
            assert_eq!(t.params["seed"], seed);
            assert_eq!(t.params["schedule"]["iterations"], r.budget);
        }
        let cells: Vec<(u64, Option<u64>)> = p.cells().map(|r| (r.budget, r.seed)).collect();
        assert_eq!(cells, [(5, Some(0)), (10, Some(0))]);
        let first = p.cells().next().unwrap();
        let seeds: Vec<Option<u64>> = p.seeds_of(first).map(|r| r.seed).collect();
        assert_eq!(seeds, [Some(0), Some(7)]);
        let bad = super::super::suite::parse(
            Path::new("s.yaml"),
            "name: t\nscenes: [{name: a}]\nbudgets: [5]\nseeds: {param: train.sed, values: [0]}\nvariants:\n  - {name: full}\n",
        )
        .unwrap();
        let e = build(&bad, Path::new("p.yaml"), BASE, &[], Path::new("/c")).unwrap_err();
        assert!(e.to_string().contains("`sed` of stage `train`"), "{e}");
    }
}
