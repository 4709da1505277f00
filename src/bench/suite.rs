//! A bench suite file (`benches/suites/*.yaml`): which scenes, which training budgets and which
//! variants `pipe bench` runs. Parsed strictly (unknown keys are errors); every error names the
//! suite file, the line and column where known, and the key.
//!
//! ```yaml
//! name: quick
//! set: {train.train.rays_per_batch: 256}      # applied to every run
//! scenes:
//!   - {name: tiny0, set: {scene.seed: 0, scene.frames: 6}}
//! budgets: [50, 150, 400]                     # values of `budget_param`
//! variants:
//!   - {name: complete}
//!   - {name: no_depth, label: "w/o L_depth", set: {train.train.losses.depth: 0}, budgets: [400]}
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
];

fn default_budget_param() -> String {
    "train.train.iterations".into()
}

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
    set: Mapping,
    scenes: Vec<SceneFile>,
    budgets: Vec<u64>,
    #[serde(default = "default_budget_param")]
    budget_param: String,
    #[serde(default)]
    ablation_budget: Option<u64>,
    variants: Vec<VariantFile>,
    #[serde(default)]
    overhead_repeats: Option<usize>,
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
    /// False when the semantic outputs are meaningless (photometric-only): tables show only depth.
    pub semantics: bool,
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
    pub set: Vec<Setting>,
    pub scenes: Vec<Scene>,
    pub budgets: Vec<u64>,
    pub budget_param: Setting,
    pub ablation_budget: u64,
    pub variants: Vec<Variant>,
    pub overhead_repeats: usize,
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
    let text = std::fs::read_to_string(file).map_err(|e| ConfigError {
        file: file.to_path_buf(),
        loc: Loc::Unknown,
        stage: None,
        key: None,
        message: format!("cannot read the suite file: {e}"),
    })?;
    parse(file, &text).map(Some)
}

fn valid_name(n: &str) -> bool {
    !n.is_empty()
        && n.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

/// Parses and validates suite text (`file` is used in messages).
pub fn parse(file: &Path, text: &str) -> Result<Suite, ConfigError> {
    let locs = Locations::scan(text);
    let err = |loc: Loc, key: Option<&str>, msg: String| ConfigError {
        file: file.to_path_buf(),
        loc,
        stage: None,
        key: key.map(String::from),
        message: msg,
    };
    let raw: SuiteFile = serde_yaml::from_str(text).map_err(|e| {
        let loc = e.location().map_or(Loc::Unknown, |l| Loc::File {
            line: l.line(),
            col: l.column(),
        });
        let msg = e.to_string();
        let msg = msg.split(" at line ").next().unwrap_or(&msg).to_string();
        err(loc, None, format!("invalid suite: {msg}"))
    })?;
    let settings = |m: &Mapping, base: &str| -> Result<Vec<Setting>, ConfigError> {
        m.iter()
            .map(|(k, v)| {
                let key = k.as_str().unwrap_or("?").to_string();
                let path = format!("{base}.{key}");
                let loc = locs.key(&path);
                let parts: Vec<&str> = key.split('.').collect();
                if parts.len() < 2 || parts.iter().any(|p| p.is_empty()) {
                    return Err(err(
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
    };
    let check_name = |what: &str, path: &str, n: &str| {
        if valid_name(n) {
            Ok(())
        } else {
            Err(err(
                locs.value(path),
                Some(path),
                format!("bad {what} name {n:?}: use letters, digits, `_` and `-`"),
            ))
        }
    };
    if raw.scenes.is_empty() {
        return Err(err(locs.key("scenes"), Some("scenes"), "no scenes".into()));
    }
    if raw.variants.is_empty() {
        return Err(err(
            locs.key("variants"),
            Some("variants"),
            "no variants".into(),
        ));
    }
    if raw.budgets.is_empty() || raw.budgets.contains(&0) {
        return Err(err(
            locs.key("budgets"),
            Some("budgets"),
            "expected a list of budgets > 0".into(),
        ));
    }
    let mut scenes = Vec::new();
    for (i, s) in raw.scenes.iter().enumerate() {
        let path = format!("scenes.{i}.name");
        check_name("scene", &path, &s.name)?;
        if scenes.iter().any(|x: &Scene| x.name == s.name) {
            return Err(err(
                locs.value(&path),
                Some(&path),
                format!("scene `{}` is listed twice", s.name),
            ));
        }
        scenes.push(Scene {
            name: s.name.clone(),
            set: settings(&s.set, &format!("scenes.{i}.set"))?,
        });
    }
    let mut variants: Vec<Variant> = Vec::new();
    for (i, v) in raw.variants.iter().enumerate() {
        let path = format!("variants.{i}.name");
        check_name("variant", &path, &v.name)?;
        if variants.iter().any(|x| x.name == v.name) {
            return Err(err(
                locs.value(&path),
                Some(&path),
                format!("variant `{}` is listed twice", v.name),
            ));
        }
        let budgets = v.budgets.clone().unwrap_or_else(|| raw.budgets.clone());
        if budgets.is_empty() || budgets.contains(&0) {
            let p = format!("variants.{i}.budgets");
            return Err(err(
                locs.key(&p),
                Some(&p),
                "expected a list of budgets > 0".into(),
            ));
        }
        let on = v
            .scenes
            .clone()
            .unwrap_or_else(|| scenes.iter().map(|s| s.name.clone()).collect());
        for (k, s) in on.iter().enumerate() {
            if !scenes.iter().any(|x| &x.name == s) {
                let p = format!("variants.{i}.scenes.{k}");
                return Err(err(
                    locs.value(&p),
                    Some(&p),
                    format!("no scene named `{s}` in this suite"),
                ));
            }
        }
        variants.push(Variant {
            name: v.name.clone(),
            label: v.label.clone().unwrap_or_else(|| v.name.clone()),
            set: settings(&v.set, &format!("variants.{i}.set"))?,
            budgets,
            scenes: on,
            optional: v.optional,
            semantics: v.semantics,
        });
    }
    let bp_loc = locs.value("budget_param");
    if raw.budget_param.split('.').count() < 2 {
        return Err(err(
            bp_loc,
            Some("budget_param"),
            format!("`{}`: expected STAGE.PARAM[.FIELD...]", raw.budget_param),
        ));
    }
    // Default: the largest budget every variant ran at (so the table has every row), else the
    // largest budget.
    let ablation_budget = raw.ablation_budget.unwrap_or_else(|| {
        let ran_at = |v: &VariantFile| v.budgets.clone().unwrap_or_else(|| raw.budgets.clone());
        raw.budgets
            .iter()
            .chain(raw.variants.iter().flat_map(|v| v.budgets.iter().flatten()))
            .filter(|b| raw.variants.iter().all(|v| ran_at(v).contains(b)))
            .max()
            .copied()
            .unwrap_or_else(|| *raw.budgets.iter().max().expect("budgets checked non-empty"))
    });
    Ok(Suite {
        name: raw.name,
        description: raw.description,
        file: file.to_path_buf(),
        text: text.to_string(),
        set: settings(&raw.set, "set")?,
        scenes,
        budgets: raw.budgets,
        budget_param: Setting {
            key: raw.budget_param,
            value: Yaml::Null,
            loc: bp_loc,
            path: "budget_param".into(),
        },
        ablation_budget,
        variants,
        overhead_repeats: raw.overhead_repeats.unwrap_or(5).max(1),
    })
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
        }
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
}
