//! A bench suite file (`benches/suites/*.yaml`): which scenes, which training budgets and which
//! variants `pipe bench` runs, and published figures to show beside them. Parsed strictly
//! (unknown keys are errors); every error names the suite file, the line and column where
//! known, and the key.
//!
//! ```yaml
//! name: quick
//! set: {train.schedule.rays_per_batch: 256}      # applied to every run
//! scenes:
//!   - {name: tiny0, set: {scene.seed: 0, scene.frames: 6}}
//! budgets: [50, 150, 400]                     # values of `budget_param`
//! budget_param: train.schedule.iterations        # optional: the budget parameter of the stage
//!                                             # whose kind has one (`Stage::budget_param`)
//! paper:                                      # optional: what the variants' `paper:` are
//!   column: paper                             # the ablation table's column (default `paper`)
//!   note: The last column is the paper's figure (RMSE / delta / mIoU).
//! seeds:                                      # optional: every run once per value of `param`;
//!   param: train.seed                   # tables show the mean and the spread
//!   values: [0, 1, 2]
//! variants:
//!   - {name: complete, paper: "5.23 / 95.1 / 81.4"}
//!   - {name: no_depth, label: "w/o L_depth", set: {train.losses.depth: 0}, budgets: [400]}
//! ```
//!
//! A `set` key is `STAGE.PARAM[.FIELD...]` of the base pipeline (as `pipe run --set`, but it may
//! reach into nested parameters); the value is YAML.

use std::path::{Path, PathBuf};

use serde::Deserialize;
use serde_yaml::{Mapping, Value as Yaml};

use crate::config::{ConfigError, Loc, Locations};

/// The built-in suites, by name: (name, file it was built from, text).
pub const BUILT_IN: &[(&str, &str, &str)] = &[
    (
        "quick",
        "benches/suites/quick.yaml",
        include_str!("../../benches/suites/quick.yaml"),
    ),
    (
        "standard",
        "benches/suites/standard.yaml",
        include_str!("../../benches/suites/standard.yaml"),
    ),
    (
        "full",
        "benches/suites/full.yaml",
        include_str!("../../benches/suites/full.yaml"),
    ),
    (
        "seeds",
        "benches/suites/seeds.yaml",
        include_str!("../../benches/suites/seeds.yaml"),
    ),
    (
        "growth",
        "benches/suites/growth.yaml",
        include_str!("../../benches/suites/growth.yaml"),
    ),
    (
        "fisheye",
        "benches/suites/fisheye.yaml",
        include_str!("../../benches/suites/fisheye.yaml"),
    ),
];

fn yes() -> bool {
    true
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct SuiteFile {
    name: String,
    #[serde(default)]
    description: String,
    #[serde(default)]
    pipeline: Option<PathBuf>,
    #[serde(default)]
    set: Mapping,
    scenes: Vec<SceneFile>,
    budgets: Vec<u64>,
    #[serde(default)]
    budget_param: Option<String>,
    #[serde(default)]
    ablation_budget: Option<u64>,
    #[serde(default)]
    paper: Option<PaperFile>,
    variants: Vec<VariantFile>,
    #[serde(default)]
    overhead_repeats: Option<usize>,
    #[serde(default)]
    goal_train_s: Option<f64>,
    #[serde(default)]
    seeds: Option<SeedsFile>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct SeedsFile {
    param: String,
    values: Vec<u64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneFile {
    name: String,
    #[serde(default)]
    set: Mapping,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PaperFile {
    #[serde(default)]
    column: Option<String>,
    note: String,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct VariantFile {
    name: String,
    #[serde(default)]
    label: Option<String>,
    #[serde(default)]
    set: Mapping,
    #[serde(default)]
    budgets: Option<Vec<u64>>,
    #[serde(default)]
    scenes: Option<Vec<String>>,
    #[serde(default)]
    optional: bool,
    #[serde(default = "yes")]
    semantics: bool,
    #[serde(default)]
    paper: Option<String>,
}

/// One parameter override: `stage.param.field...` = value, and where it was written.
#[derive(Debug, Clone)]
pub struct Setting {
    /// `STAGE.PARAM[.FIELD...]` as written.
    pub key: String,
    pub value: Yaml,
    /// Where the key stands (for errors).
    pub loc: Loc,
    /// The key path inside the suite file (`variants.2.set.<key>`), for errors.
    pub path: String,
}

#[derive(Debug, Clone)]
pub struct Scene {
    pub name: String,
    pub set: Vec<Setting>,
}

#[derive(Debug, Clone)]
pub struct Variant {
    pub name: String,
    /// How tables and plots name it.
    pub label: String,
    pub set: Vec<Setting>,
    /// Budgets this variant runs at (a subset of, or equal to, the suite's).
    pub budgets: Vec<u64>,
    /// Scenes it runs on (default: all).
    pub scenes: Vec<String>,
    /// Skip (with a note) rather than fail when this build lacks one of its parameters.
    pub optional: bool,
    /// False when the semantic outputs are meaningless (photometric-only): tables show only
    /// the metrics that need no labels.
    pub semantics: bool,
    /// The published figures of this variant, shown beside the ablation (see [`Paper`]).
    pub paper: Option<String>,
}

/// What the variants' `paper:` figures are: the ablation table's column heading and a note
/// printed above the table.
#[derive(Debug, Clone)]
pub struct Paper {
    pub column: String,
    pub note: String,
}

/// `seeds:`: every run repeated once per value of a seed parameter, so that the tables can say
/// how much of a difference between two variants is the seed's.
#[derive(Debug, Clone)]
pub struct Seeds {
    /// The seed parameter (`STAGE.PARAM[.FIELD...]`); its `value` is unused.
    pub param: Setting,
    /// Distinct values, in the suite's order.
    pub values: Vec<u64>,
}

/// A validated suite.
#[derive(Debug, Clone)]
pub struct Suite {
    pub name: String,
    pub description: String,
    /// Where it came from (a path, or `benches/suites/quick.yaml (built in)`).
    pub file: PathBuf,
    /// The suite text, for the report's reproducibility section.
    pub text: String,
    /// `pipeline:`: the base pipeline the suite is written for (relative to the working
    /// directory), used unless `-f` names another.
    pub pipeline: Option<PathBuf>,
    pub set: Vec<Setting>,
    pub scenes: Vec<Scene>,
    pub budgets: Vec<u64>,
    /// `budget_param:`; `None`: the budget parameter of the base stage whose kind has one.
    pub budget_param: Option<Setting>,
    pub ablation_budget: u64,
    pub paper: Option<Paper>,
    pub variants: Vec<Variant>,
    pub overhead_repeats: usize,
    /// `goal_train_s:`: the training time the suite's scenes should come near their best
    /// within (the report says whether they did); none: no goal.
    pub goal_train_s: Option<f64>,
    pub seeds: Option<Seeds>,
}

/// Whether `--suite` names a file rather than a built-in suite.
fn looks_like_path(s: &str) -> bool {
    s.contains('/') || s.ends_with(".yaml") || s.ends_with(".yml")
}

/// Finds a suite by built-in name or path. `Ok(None)`: neither (the caller reports a usage error).
pub fn load(spec: &str) -> Result<Option<Suite>, ConfigError> {
    if let Some((_, file, text)) = BUILT_IN.iter().find(|(n, ..)| *n == spec) {
        return parse(Path::new(&format!("{file} (built in)")), text).map(Some);
    }
    if !looks_like_path(spec) {
        return Ok(None);
    }
    let file = Path::new(spec);
    let text = crate::config::read_text(file, "suite file")?;
    parse(file, &text).map(Some)
}

fn valid_name(n: &str) -> bool {
    !n.is_empty()
        && n.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

/// The suite file being parsed: its name and where its keys stand.
struct Cx<'a> {
    file: &'a Path,
    locs: Locations,
}

impl Cx<'_> {
    fn err(&self, loc: Loc, key: Option<&str>, msg: String) -> ConfigError {
        ConfigError {
            file: self.file.to_path_buf(),
            loc,
            stage: None,
            key: key.map(String::from),
            message: msg,
        }
    }

    /// The `set:` mapping at key path `base`, each key checked for its shape.
    fn settings(&self, m: &Mapping, base: &str) -> Result<Vec<Setting>, ConfigError> {
        m.iter()
            .map(|(k, v)| {
                let key = k.as_str().unwrap_or("?").to_string();
                let path = format!("{base}.{key}");
                let loc = self.locs.key(&path);
                let parts: Vec<&str> = key.split('.').collect();
                if parts.len() < 2 || parts.iter().any(|p| p.is_empty()) {
                    return Err(self.err(
                        loc,
                        Some(&path),
                        format!("`{key}`: expected STAGE.PARAM[.FIELD...]"),
                    ));
                }
                Ok(Setting {
                    key,
                    value: v.clone(),
                    loc,
                    path,
                })
            })
            .collect()
    }

    fn check_name(&self, what: &str, path: &str, n: &str) -> Result<(), ConfigError> {
        if valid_name(n) {
            Ok(())
        } else {
            Err(self.err(
                self.locs.value(path),
                Some(path),
                format!("bad {what} name {n:?}: use letters, digits, `_` and `-`"),
            ))
        }
    }

    /// A parameter named by its key (`budget_param`, `seeds.param`) at key path `path`.
    fn param(&self, key: &str, path: &str) -> Result<Setting, ConfigError> {
        let loc = self.locs.value(path);
        if key.split('.').count() < 2 || key.split('.').any(str::is_empty) {
            return Err(self.err(
                loc,
                Some(path),
                format!("`{key}`: expected STAGE.PARAM[.FIELD...]"),
            ));
        }
        Ok(Setting {
            key: key.to_string(),
            value: Yaml::Null,
            loc,
            path: path.to_string(),
        })
    }

    fn seeds(&self, raw: &SeedsFile) -> Result<Seeds, ConfigError> {
        let mut values = Vec::new();
        for &v in &raw.values {
            if values.contains(&v) {
                return Err(self.err(
                    self.locs.key("seeds.values"),
                    Some("seeds.values"),
                    format!("seed {v} is listed twice"),
                ));
            }
            values.push(v);
        }
        if values.is_empty() {
            return Err(self.err(
                self.locs.key("seeds.values"),
                Some("seeds.values"),
                "expected at least one seed".into(),
            ));
        }
        Ok(Seeds {
            param: self.param(&raw.param, "seeds.param")?,
            values,
        })
    }

    fn check_budgets(&self, budgets: &[u64], path: &str) -> Result<(), ConfigError> {
        if budgets.is_empty() || budgets.contains(&0) {
            return Err(self.err(
                self.locs.key(path),
                Some(path),
                "expected a list of budgets > 0".into(),
            ));
        }
        Ok(())
    }
}

/// Parses and validates suite text (`file` is used in messages).
pub fn parse(file: &Path, text: &str) -> Result<Suite, ConfigError> {
    let cx = Cx {
        file,
        locs: Locations::scan(text),
    };
    let raw: SuiteFile = serde_yaml::from_str(text).map_err(|e| {
        let (loc, msg) = cx.locs.serde_error(text, &e);
        cx.err(loc, None, format!("invalid suite: {msg}"))
    })?;
    if raw.scenes.is_empty() {
        return Err(cx.err(cx.locs.key("scenes"), Some("scenes"), "no scenes".into()));
    }
    if raw.variants.is_empty() {
        return Err(cx.err(
            cx.locs.key("variants"),
            Some("variants"),
            "no variants".into(),
        ));
    }
    cx.check_budgets(&raw.budgets, "budgets")?;
    let scenes = scenes(&cx, &raw.scenes)?;
    let variants = variants(&cx, &raw, &scenes)?;
    let paper = paper(&cx, &raw)?;
    let budget_param = raw
        .budget_param
        .as_ref()
        .map(|key| cx.param(key, "budget_param"))
        .transpose()?;
    let seeds = raw.seeds.as_ref().map(|s| cx.seeds(s)).transpose()?;
    Ok(Suite {
        ablation_budget: raw
            .ablation_budget
            .unwrap_or_else(|| ablation_default(&raw)),
        name: raw.name,
        description: raw.description,
        file: file.to_path_buf(),
        text: text.to_string(),
        pipeline: raw.pipeline,
        set: cx.settings(&raw.set, "set")?,
        scenes,
        budgets: raw.budgets,
        budget_param,
        paper,
        variants,
        overhead_repeats: raw.overhead_repeats.unwrap_or(5).max(1),
        goal_train_s: raw.goal_train_s.filter(|g| g.is_finite() && *g > 0.0),
        seeds,
    })
}

fn scenes(cx: &Cx, raw: &[SceneFile]) -> Result<Vec<Scene>, ConfigError> {
    let mut scenes = Vec::new();
    for (i, s) in raw.iter().enumerate() {
        let path = format!("scenes.{i}.name");
        cx.check_name("scene", &path, &s.name)?;
        if scenes.iter().any(|x: &Scene| x.name == s.name) {
            return Err(cx.err(
                cx.locs.value(&path),
                Some(&path),
                format!("scene `{}` is listed twice", s.name),
            ));
        }
        scenes.push(Scene {
            name: s.name.clone(),
            set: cx.settings(&s.set, &format!("scenes.{i}.set"))?,
        });
    }
    Ok(scenes)
}

fn variants(cx: &Cx, raw: &SuiteFile, scenes: &[Scene]) -> Result<Vec<Variant>, ConfigError> {
    let mut variants: Vec<Variant> = Vec::new();
    for (i, v) in raw.variants.iter().enumerate() {
        let path = format!("variants.{i}.name");
        cx.check_name("variant", &path, &v.name)?;
        if variants.iter().any(|x| x.name == v.name) {
            return Err(cx.err(
                cx.locs.value(&path),
                Some(&path),
                format!("variant `{}` is listed twice", v.name),
            ));
        }
        let budgets = v.budgets.clone().unwrap_or_else(|| raw.budgets.clone());
        cx.check_budgets(&budgets, &format!("variants.{i}.budgets"))?;
        let on = v
            .scenes
            .clone()
            .unwrap_or_else(|| scenes.iter().map(|s| s.name.clone()).collect());
        for (k, s) in on.iter().enumerate() {
            if !scenes.iter().any(|x| &x.name == s) {
                let p = format!("variants.{i}.scenes.{k}");
                return Err(cx.err(
                    cx.locs.value(&p),
                    Some(&p),
                    format!("no scene named `{s}` in this suite"),
                ));
            }
        }
        variants.push(Variant {
            name: v.name.clone(),
            label: v.label.clone().unwrap_or_else(|| v.name.clone()),
            set: cx.settings(&v.set, &format!("variants.{i}.set"))?,
            budgets,
            scenes: on,
            optional: v.optional,
            semantics: v.semantics,
            paper: v.paper.clone(),
        });
    }
    Ok(variants)
}

/// `paper:` of the suite, which must say what the variants' `paper:` figures are (and is
/// only given with figures).
fn paper(cx: &Cx, raw: &SuiteFile) -> Result<Option<Paper>, ConfigError> {
    let with_figures = raw.variants.iter().position(|v| v.paper.is_some());
    match (&raw.paper, with_figures) {
        (Some(p), Some(_)) => {
            if p.note.trim().is_empty() {
                return Err(cx.err(
                    cx.locs.value("paper.note"),
                    Some("paper.note"),
                    "expected a sentence saying what the variants' `paper:` figures are".into(),
                ));
            }
            Ok(Some(Paper {
                column: p.column.clone().unwrap_or_else(|| "paper".into()),
                note: p.note.trim().to_string(),
            }))
        }
        (None, Some(i)) => {
            let path = format!("variants.{i}.paper");
            Err(cx.err(
                cx.locs.key(&path),
                Some(&path),
                "figures without a suite-level `paper: {note: ...}` saying what they are".into(),
            ))
        }
        (Some(_), None) => Err(cx.err(
            cx.locs.key("paper"),
            Some("paper"),
            "no variant has `paper:` figures".into(),
        )),
        (None, None) => Ok(None),
    }
}

/// The default ablation budget: the largest budget every variant ran at (so the table has
/// every row), else the largest budget.
fn ablation_default(raw: &SuiteFile) -> u64 {
    let ran_at = |v: &VariantFile| v.budgets.clone().unwrap_or_else(|| raw.budgets.clone());
    raw.budgets
        .iter()
        .chain(raw.variants.iter().flat_map(|v| v.budgets.iter().flatten()))
        .filter(|b| raw.variants.iter().all(|v| ran_at(v).contains(b)))
        .max()
        .copied()
        .unwrap_or_else(|| *raw.budgets.iter().max().expect("budgets checked non-empty"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn built_in_suites_parse() {
        for (name, ..) in BUILT_IN {
            let s = load(name).unwrap().unwrap();
            assert_eq!(&s.name, name);
            assert!(s.variants.iter().any(|v| v.name == "complete"));
            if s.variants.iter().any(|v| v.name == "no_fixed_2d") {
                // The paper's ablation: its figures beside it.
                assert!(s.paper.is_some(), "{name}: the paper's ablation figures");
                let complete = s.variants.iter().find(|v| v.name == "complete").unwrap();
                assert_eq!(complete.paper.as_deref(), Some("5.23 / 95.1 / 81.4"));
            }
            if let Some(p) = &s.pipeline {
                let file = Path::new(env!("CARGO_MANIFEST_DIR")).join(p);
                assert!(file.is_file(), "{name}: its pipeline {}", file.display());
            }
        }
        assert_eq!(
            load("full").unwrap().unwrap().pipeline.as_deref(),
            Some(Path::new("pipelines/full.yaml"))
        );
    }

    #[test]
    fn the_ablation_defaults_to_the_largest_budget_every_variant_ran_at() {
        assert_eq!(load("quick").unwrap().unwrap().ablation_budget, 400);
        assert_eq!(load("standard").unwrap().unwrap().ablation_budget, 1700);
        let text = "name: x\nscenes: [{name: a}]\nbudgets: [1, 5, 9]\nvariants:\n  - {name: complete}\n  - {name: v, budgets: [1, 5]}\n";
        assert_eq!(parse(Path::new("s.yaml"), text).unwrap().ablation_budget, 5);
        let text = "name: x\nscenes: [{name: a}]\nbudgets: [1, 5, 9]\nvariants:\n  - {name: complete}\n  - {name: v, budgets: [7]}\n";
        assert_eq!(parse(Path::new("s.yaml"), text).unwrap().ablation_budget, 9);
    }

    #[test]
    fn unknown_keys_and_bad_names_are_located() {
        let e = parse(
            Path::new("s.yaml"),
            "name: x\nscenes: [{name: a}]\nbudgets: [1]\nvariants:\n  - {name: v, sett: {}}\n",
        )
        .unwrap_err();
        let msg = e.to_string();
        assert!(msg.starts_with("s.yaml:5:"), "{msg}");
        assert!(msg.contains("unknown field `sett`"), "{msg}");
        let e = parse(
            Path::new("s.yaml"),
            "name: x\nscenes: [{name: a}]\nbudgets: [1]\nvariants:\n  - name: v\n    set: {nodot: 1}\n",
        )
        .unwrap_err();
        assert!(
            e.to_string()
                .starts_with("s.yaml:6:11: `variants.0.set.nodot`"),
            "{e}"
        );
        assert!(load("no-such-suite").unwrap().is_none());
    }

    #[test]
    fn paper_figures_need_a_note_saying_what_they_are() {
        let base = "name: x\nscenes: [{name: a}]\nbudgets: [1]\n";
        let text = format!("{base}variants:\n  - name: v\n    paper: \"1 / 2\"\n");
        let e = parse(Path::new("s.yaml"), &text).unwrap_err();
        assert!(
            e.to_string()
                .starts_with("s.yaml:6:5: `variants.0.paper`: figures without"),
            "{e}"
        );
        let text = format!("{base}paper: {{note: what}}\nvariants:\n  - name: v\n");
        let e = parse(Path::new("s.yaml"), &text).unwrap_err();
        assert!(
            e.to_string()
                .starts_with("s.yaml:4:1: `paper`: no variant has `paper:` figures"),
            "{e}"
        );
        let text =
            format!("{base}paper: {{colum: p, note: n}}\nvariants:\n  - {{name: v, paper: a}}\n");
        let e = parse(Path::new("s.yaml"), &text).unwrap_err();
        assert!(
            e.to_string().starts_with("s.yaml:4:")
                && e.to_string().contains("unknown field `colum`"),
            "{e}"
        );
        let text = format!(
            "{base}paper: {{column: published, note: what they are}}\nvariants:\n  - {{name: v, paper: \"1 / 2\"}}\n  - {{name: w}}\n"
        );
        let s = parse(Path::new("s.yaml"), &text).unwrap();
        let p = s.paper.unwrap();
        assert_eq!(
            (p.column.as_str(), p.note.as_str()),
            ("published", "what they are")
        );
        assert_eq!(s.variants[0].paper.as_deref(), Some("1 / 2"));
        assert_eq!(s.variants[1].paper, None);
    }

    #[test]
    fn seeds_are_distinct_values_of_one_parameter() {
        let base = "name: x\nscenes: [{name: a}]\nbudgets: [1]\nvariants: [{name: v}]\n";
        let s = parse(
            Path::new("s.yaml"),
            &format!("{base}seeds: {{param: train.seed, values: [3, 1]}}\n"),
        )
        .unwrap();
        let seeds = s.seeds.unwrap();
        assert_eq!(seeds.param.key, "train.seed");
        assert_eq!(seeds.values, [3, 1]);
        assert!(parse(Path::new("s.yaml"), base).unwrap().seeds.is_none());
        for (seeds, want) in [
            ("{param: train.seed, values: [1, 1]}", "s.yaml:5:"),
            ("{param: train.seed, values: []}", "s.yaml:5:"),
            ("{param: seed, values: [1]}", "s.yaml:5:"),
            ("{param: train.seed, valeus: [1]}", "s.yaml:5:"),
        ] {
            let e = parse(Path::new("s.yaml"), &format!("{base}seeds: {seeds}\n")).unwrap_err();
            assert!(e.to_string().starts_with(want), "{seeds}: {e}");
        }
        let e = parse(
            Path::new("s.yaml"),
            &format!("{base}seeds: {{param: train.seed, values: [2, 2]}}\n"),
        )
        .unwrap_err();
        assert!(e.to_string().contains("seed 2 is listed twice"), "{e}");
    }
}
