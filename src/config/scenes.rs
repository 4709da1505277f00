//! `scenes:`: a scene matrix or a list of named scenes, each a set of parameter settings, and
//! the expansion of the stages under `stages:` into one instance per scene (`STAGE@SCENE`),
//! with the dataset stages' inputs that name a template turned into gathers of every scene.

use std::collections::BTreeSet;

use serde_json::Value;
use serde_yaml::{Mapping, Value as Yaml};

use super::{
    error::{ConfigError, Loc},
    overrides::{Override, Setting},
    pipeline::StageDecl,
    validate::stage_decl,
    yaml::{describe, yaml_type, Ctx},
};

/// One parameter setting of a scene: `STAGE.PARAM[.FIELD...]: VALUE`.
struct SceneSet {
    stage: String,
    /// PARAM and the fields below it, the value, where it is written.
    setting: Setting,
}

/// A scene of the matrix or the list.
pub(super) struct SceneDecl {
    pub name: String,
    sets: Vec<SceneSet>,
}

fn valid_scene_name(n: &str) -> bool {
    !n.is_empty()
        && n.chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.'))
}

/// Parses `STAGE.PARAM[.FIELD...]` of a scene setting; the stage must be under `stages:`.
fn scene_set(
    cx: &Ctx,
    key: &str,
    value: &Yaml,
    loc: Loc,
    templates: &Mapping,
) -> Result<SceneSet, ConfigError> {
    let parts: Vec<&str> = key.split('.').collect();
    if parts.len() < 2 || parts.iter().any(|p| p.is_empty()) {
        return Err(cx.err(
            loc,
            None,
            Some(key),
            "expected STAGE.PARAM[.FIELD...] (a parameter of a stage under `stages:`)",
        ));
    }
    if !templates.keys().any(|k| k.as_str() == Some(parts[0])) {
        let known: Vec<&str> = templates.keys().filter_map(|k| k.as_str()).collect();
        return Err(cx.err(
            loc,
            None,
            Some(key),
            format!(
                "no stage `{}` under `stages:` (stages: {})",
                parts[0],
                known.join(", ")
            ),
        ));
    }
    Ok(SceneSet {
        stage: parts[0].to_string(),
        setting: Setting {
            path: parts[1..].iter().map(|p| p.to_string()).collect(),
            value: value.clone(),
            loc,
        },
    })
}

/// A matrix value as part of a scene name (`0.5`, `true`, `street_a`).
fn name_part(v: &Yaml) -> Option<String> {
    let s = match v {
        Yaml::Number(n) => n.to_string(),
        Yaml::String(s) => s.clone(),
        Yaml::Bool(b) => b.to_string(),
        _ => return None,
    };
    Some(
        s.chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.') {
                    c
                } else {
                    '_'
                }
            })
            .collect(),
    )
}

/// `scenes:`: a `matrix:` of values, or a list of named scenes with their settings.
pub(super) fn parse_scenes(
    cx: &Ctx,
    v: &Yaml,
    templates: &Mapping,
) -> Result<Vec<SceneDecl>, ConfigError> {
    let out = match v {
        Yaml::Mapping(m) => parse_matrix(cx, m, templates)?,
        Yaml::Sequence(list) if !list.is_empty() => list
            .iter()
            .enumerate()
            .map(|(i, item)| parse_listed(cx, i, item, templates))
            .collect::<Result<_, _>>()?,
        other => {
            return Err(cx.err(
                cx.locs.value("scenes"),
                None,
                Some("scenes"),
                format!(
                    "expected `matrix:` or a non-empty list of scenes, found {}",
                    yaml_type(other)
                ),
            ))
        }
    };
    let mut seen = BTreeSet::new();
    for s in &out {
        if !seen.insert(s.name.as_str()) {
            return Err(cx.err(
                cx.locs.key("scenes"),
                None,
                Some("scenes"),
                format!("two scenes are named `{}`", s.name),
            ));
        }
    }
    Ok(out)
}

/// One matrix key's values: (value, its scene-name part, where it is written).
type Axis = Vec<(Yaml, String, Loc)>;

/// `scenes: {matrix: {STAGE.PARAM: [values]}}`: every combination, the first key varying
/// slowest, named `PARAMvalue-PARAMvalue`.
fn parse_matrix(cx: &Ctx, m: &Mapping, templates: &Mapping) -> Result<Vec<SceneDecl>, ConfigError> {
    let bad = |loc: Loc, key: &str, msg: String| cx.err(loc, None, Some(key), msg);
    for k in m.keys() {
        let key = k.as_str().unwrap_or("?");
        if key != "matrix" {
            return Err(bad(
                cx.locs.key(&format!("scenes.{key}")),
                key,
                "unknown key (expected `matrix:`, or a list of `{name, set}` scenes)".into(),
            ));
        }
    }
    let Some(Yaml::Mapping(matrix)) = m.get("matrix") else {
        return Err(bad(
            cx.locs.value("scenes.matrix"),
            "matrix",
            "expected a mapping of STAGE.PARAM -> list of values".into(),
        ));
    };
    if matrix.is_empty() {
        return Err(bad(
            cx.locs.key("scenes.matrix"),
            "matrix",
            "the matrix is empty".into(),
        ));
    }
    let mut axes: Vec<(String, Axis)> = Vec::new();
    for (k, vals) in matrix {
        let key = k.as_str().unwrap_or("?").to_string();
        let kpath = format!("scenes.matrix.{key}");
        let Yaml::Sequence(list) = vals else {
            return Err(bad(
                cx.locs.value(&kpath),
                &key,
                format!("expected a list of values, found {}", yaml_type(vals)),
            ));
        };
        if list.is_empty() {
            return Err(bad(
                cx.locs.value(&kpath),
                &key,
                "expected at least one value".into(),
            ));
        }
        let mut axis = Vec::new();
        for (j, x) in list.iter().enumerate() {
            let loc = cx.locs.value(&format!("{kpath}.{j}"));
            let part = name_part(x).ok_or_else(|| {
                bad(
                    loc.clone(),
                    &key,
                    format!(
                        "matrix values must be numbers, strings or booleans, found {} (list the scenes instead for structured values)",
                        yaml_type(x)
                    ),
                )
            })?;
            axis.push((x.clone(), part, loc));
        }
        scene_set(cx, &key, &Yaml::Null, cx.locs.key(&kpath), templates)?;
        axes.push((key, axis));
    }
    let mut combos: Vec<Vec<usize>> = vec![vec![]];
    for (_, axis) in &axes {
        combos = combos
            .into_iter()
            .flat_map(|c| {
                (0..axis.len()).map(move |j| {
                    let mut c = c.clone();
                    c.push(j);
                    c
                })
            })
            .collect();
    }
    let mut out = Vec::new();
    for combo in combos {
        let mut parts = Vec::new();
        let mut sets = Vec::new();
        for ((key, axis), &j) in axes.iter().zip(&combo) {
            let (value, part, loc) = &axis[j];
            let last = key.rsplit('.').next().unwrap_or(key);
            parts.push(format!("{last}{part}"));
            sets.push(scene_set(cx, key, value, loc.clone(), templates)?);
        }
        out.push(SceneDecl {
            name: parts.join("-"),
            sets,
        });
    }
    Ok(out)
}

/// Item `i` of a scene list: `{name: NAME, set: {STAGE.PARAM: VALUE}}`.
fn parse_listed(
    cx: &Ctx,
    i: usize,
    item: &Yaml,
    templates: &Mapping,
) -> Result<SceneDecl, ConfigError> {
    let bad = |loc: Loc, key: Option<&str>, msg: String| cx.err(loc, None, key, msg);
    let base = format!("scenes.{i}");
    let Yaml::Mapping(im) = item else {
        return Err(bad(
            cx.locs.value(&base),
            None,
            format!(
                "expected a scene `{{name: NAME, set: {{STAGE.PARAM: VALUE}}}}`, found {}",
                yaml_type(item)
            ),
        ));
    };
    for k in im.keys() {
        let key = k.as_str().unwrap_or("?");
        if key != "name" && key != "set" {
            return Err(bad(
                cx.locs.key(&format!("{base}.{key}")),
                Some(key),
                "unknown key of a scene (expected one of: name, set)".into(),
            ));
        }
    }
    let name = match im.get("name") {
        Some(Yaml::String(n)) if valid_scene_name(n) => n.clone(),
        Some(other) => {
            return Err(bad(
                cx.locs.value(&format!("{base}.name")),
                Some("name"),
                format!(
                    "bad scene name {}: use letters, digits, `_`, `-` and `.`",
                    describe(&serde_json::to_value(other).unwrap_or(Value::Null))
                ),
            ))
        }
        None => {
            return Err(bad(
                cx.locs.value(&base),
                Some("name"),
                "missing: every scene of the list needs a `name:`".into(),
            ))
        }
    };
    let mut sets = Vec::new();
    match im.get("set") {
        None | Some(Yaml::Null) => {}
        Some(Yaml::Mapping(sm)) => {
            for (k, x) in sm {
                let key = k.as_str().unwrap_or("?");
                let loc = cx.locs.key(&format!("{base}.set.{key}"));
                sets.push(scene_set(cx, key, x, loc, templates)?);
            }
        }
        Some(other) => {
            return Err(bad(
                cx.locs.value(&format!("{base}.set")),
                Some("set"),
                format!(
                    "expected a mapping of STAGE.PARAM -> value, found {}",
                    yaml_type(other)
                ),
            ))
        }
    }
    Ok(SceneDecl { name, sets })
}

/// The stage instances of every scene: each stage under `stages:` once per scene, named
/// `STAGE@SCENE`, its inputs renamed to the same scene, the scene's settings and then the
/// overrides of the template or of the instance applied.
pub(super) fn expand(
    cx: &Ctx,
    templates: &Mapping,
    scenes: &[SceneDecl],
    overrides: &[Override],
) -> Result<Vec<StageDecl>, ConfigError> {
    let mut out = Vec::new();
    for sc in scenes {
        for (k, v) in templates {
            let tname = k.as_str().expect("checked");
            let name = format!("{tname}@{}", sc.name);
            let settings: Vec<Setting> = sc
                .sets
                .iter()
                .filter(|s| s.stage == tname)
                .map(|s| s.setting.clone())
                .chain(
                    overrides
                        .iter()
                        .filter(|o| o.stage == tname || o.stage == name)
                        .map(Override::setting),
                )
                .collect();
            let mut d = stage_decl(cx, &name, &format!("stages.{tname}"), v, &settings)?;
            d.template = tname.to_string();
            d.scene = Some(sc.name.clone());
            for up in d.inputs.values_mut() {
                *up = format!("{up}@{}", sc.name);
            }
            out.push(d);
        }
    }
    Ok(out)
}

/// Turns the inputs of dataset stages that name a template (`evaluate`) into gathers of that
/// template's instance in every scene, in scene order.
pub(super) fn gather(dataset: &mut [StageDecl], templates: &[String], scenes: &[SceneDecl]) {
    for d in dataset {
        let gathered: Vec<String> = d
            .inputs
            .iter()
            .filter(|(_, up)| templates.contains(up))
            .map(|(slot, _)| slot.clone())
            .collect();
        for slot in gathered {
            let up = d.inputs.remove(&slot).expect("listed");
            let all = scenes
                .iter()
                .map(|sc| (sc.name.clone(), format!("{up}@{}", sc.name)))
                .collect();
            d.gather.insert(slot, all);
        }
    }
}
