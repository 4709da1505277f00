//! Stage declarations checked against the registry: the kind exists, the inputs are slots of
//! the kind and name stages that write what the slot reads, and the params (with scene settings
//! and `--set` overrides applied) fit the kind's defaults and pass its own validation.

use std::collections::BTreeMap;

use serde_json::Value;
use serde_yaml::{Mapping, Value as Yaml};
use stages::Stage;

use super::{
    error::{ConfigError, Loc},
    overrides::{self, Setting},
    pipeline::StageDecl,
    yaml::{describe, json_type, yaml_type, Ctx},
};

const STAGE_KEYS: &[&str] = &["uses", "params", "inputs", "doc"];

pub(super) fn valid_name(n: &str) -> bool {
    !n.is_empty()
        && n.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

/// Whether a user value may replace a default of this JSON type (shallow check; the kind's own
/// deserialisation checks the rest).
fn type_fits(default: &Value, user: &Value) -> bool {
    match (default, user) {
        (Value::Null, _) => true,
        (Value::Number(d), Value::Number(u)) => d.is_f64() || !u.is_f64(),
        (Value::Bool(_), Value::Bool(_)) => true,
        (Value::String(_), Value::String(_)) => true,
        (Value::Array(_), Value::Array(_)) => true,
        (Value::Object(_), Value::Object(_)) => true,
        (Value::Object(_) | Value::Array(_) | Value::String(_), Value::Null) => false,
        _ => false,
    }
}

/// One stage being validated: its name, where it is written (`stages.train`) and its mapping.
struct Decl<'a> {
    cx: &'a Ctx<'a>,
    name: &'a str,
    base: &'a str,
    m: &'a Mapping,
}

impl Decl<'_> {
    fn err(&self, loc: Loc, key: Option<&str>, msg: impl Into<String>) -> ConfigError {
        self.cx.err(loc, Some(self.name), key, msg)
    }

    fn key(&self, sub: &str) -> Loc {
        self.cx.locs.key(&format!("{}.{sub}", self.base))
    }

    fn value(&self, sub: &str) -> Loc {
        self.cx.locs.value(&format!("{}.{sub}", self.base))
    }
}

/// Validates stage `name` written at key path `base` (`stages.train`), applying `settings`
/// (a scene's, then the command line's) to its params.
pub(super) fn stage_decl(
    cx: &Ctx,
    name: &str,
    base: &str,
    v: &Yaml,
    settings: &[Setting],
) -> Result<StageDecl, ConfigError> {
    let loc = cx.locs.key(base);
    let m = match v {
        Yaml::Mapping(m) => m,
        other => {
            return Err(cx.err(
                cx.locs.value(base),
                Some(name),
                None,
                format!(
                    "expected a mapping with `uses:`, found {}",
                    yaml_type(other)
                ),
            ))
        }
    };
    let d = Decl { cx, name, base, m };
    for k in m.keys() {
        let key = k.as_str().unwrap_or("?");
        if !STAGE_KEYS.contains(&key) {
            return Err(d.err(
                d.key(key),
                Some(key),
                format!("unknown key (expected one of: {})", STAGE_KEYS.join(", ")),
            ));
        }
    }
    let (kind_name, kind) = kind_of(&d, loc.clone())?;
    let inputs = inputs_of(&d, &kind_name, kind.as_ref())?;
    let params = params_of(&d, &kind_name, kind.as_ref(), settings)?;
    Ok(StageDecl {
        scene: None,
        template: name.to_string(),
        gather: BTreeMap::new(),
        name: name.to_string(),
        kind,
        params,
        inputs,
        loc,
    })
}

/// `uses:`: the kind, from the registry.
fn kind_of(d: &Decl, loc: Loc) -> Result<(String, Box<dyn Stage>), ConfigError> {
    let kind_name = match d.m.get("uses") {
        Some(Yaml::String(s)) => s.clone(),
        Some(other) => {
            return Err(d.err(
                d.value("uses"),
                Some("uses"),
                format!("expected a stage kind name, found {}", yaml_type(other)),
            ))
        }
        None => {
            return Err(d.err(
                loc,
                Some("uses"),
                "missing: which stage kind does this stage use?",
            ))
        }
    };
    let kind = stages::kinds::find(&kind_name).ok_or_else(|| {
        let known: Vec<_> = stages::kinds::registry()
            .iter()
            .map(|k| k.kind())
            .filter(|k| !k.starts_with("test_"))
            .collect();
        d.err(
            d.value("uses"),
            Some("uses"),
            format!(
                "unknown stage kind `{kind_name}` (known: {})",
                known.join(", ")
            ),
        )
    })?;
    Ok((kind_name, kind))
}

/// `inputs:`: slot -> upstream stage, every slot a slot of the kind, every required slot given.
fn inputs_of(
    d: &Decl,
    kind_name: &str,
    kind: &dyn Stage,
) -> Result<BTreeMap<String, String>, ConfigError> {
    let mut inputs = BTreeMap::new();
    match d.m.get("inputs") {
        None | Some(Yaml::Null) => {}
        Some(Yaml::Mapping(im)) => {
            for (k, v) in im {
                let slot = k.as_str().unwrap_or("?").to_string();
                let sub = format!("inputs.{slot}");
                if !kind.inputs().iter().any(|s| s.name == slot) {
                    let slots: Vec<_> = kind.inputs().iter().map(|s| s.name).collect();
                    return Err(d.err(
                        d.key(&sub),
                        Some(&sub),
                        format!(
                            "kind `{kind_name}` has no input slot `{slot}` (slots: {})",
                            if slots.is_empty() {
                                "none".to_string()
                            } else {
                                slots.join(", ")
                            }
                        ),
                    ));
                }
                let up = v.as_str().ok_or_else(|| {
                    d.err(
                        d.value(&sub),
                        Some(&sub),
                        format!("expected the name of a stage, found {}", yaml_type(v)),
                    )
                })?;
                inputs.insert(slot, up.to_string());
            }
        }
        Some(other) => {
            return Err(d.err(
                d.value("inputs"),
                Some("inputs"),
                format!(
                    "expected a mapping of input slot -> stage name, found {}",
                    yaml_type(other)
                ),
            ))
        }
    }
    for slot in kind.inputs() {
        if !slot.optional && !inputs.contains_key(slot.name) {
            return Err(d.err(
                d.cx.locs.key(d.base),
                Some(&format!("inputs.{}", slot.name)),
                format!(
                    "missing input: kind `{kind_name}` needs slot `{}` ({})",
                    slot.name, slot.doc
                ),
            ));
        }
    }
    Ok(inputs)
}

/// `params:` with `settings` applied: a shallow type check against the kind's defaults, then
/// the kind's own validation, which gives the canonical params.
fn params_of(
    d: &Decl,
    kind_name: &str,
    kind: &dyn Stage,
    settings: &[Setting],
) -> Result<Value, ConfigError> {
    let defaults = kind.default_params();
    let Value::Object(mut merged) = defaults.clone() else {
        unreachable!("stage params are a struct");
    };
    let mut given: Vec<(String, Yaml, Loc)> = Vec::new();
    match d.m.get("params") {
        None | Some(Yaml::Null) => {}
        Some(Yaml::Mapping(pm)) => {
            for (k, v) in pm {
                let key = k.as_str().unwrap_or("?").to_string();
                let l = d.key(&format!("params.{key}"));
                given.push((key, v.clone(), l));
            }
        }
        Some(other) => {
            return Err(d.err(
                d.value("params"),
                Some("params"),
                format!(
                    "expected a mapping of param -> value, found {}",
                    yaml_type(other)
                ),
            ))
        }
    }
    moved_params(d, kind_name, kind, &given, settings)?;
    overrides::apply(&mut given, settings);
    for (key, v, l) in &given {
        let pkey = format!("params.{key}");
        let Some(default) = defaults.get(key) else {
            let known: Vec<_> = defaults
                .as_object()
                .map(|o| o.keys().cloned().collect())
                .unwrap_or_default();
            return Err(d.err(
                l.clone(),
                Some(&pkey),
                format!(
                    "unknown param of kind `{kind_name}` (params: {})",
                    if known.is_empty() {
                        "none".to_string()
                    } else {
                        known.join(", ")
                    }
                ),
            ));
        };
        if let Some((path, x)) = non_finite(v, key) {
            // JSON has no NaN: it would reach the kind as `null` and be reported as such.
            return Err(d.err(
                nested_loc(d, l, &path),
                None,
                format!(
                    "`{}.{path}`: {} is not a finite number",
                    d.name,
                    show_float(x)
                ),
            ));
        }
        let user: Value = serde_json::to_value(v)
            .map_err(|e| d.err(l.clone(), Some(&pkey), format!("unsupported value: {e}")))?;
        if !type_fits(default, &user) {
            return Err(d.err(
                l.clone(),
                Some(&pkey),
                format!(
                    "expected {} (default {}), found {} {}",
                    json_type(default),
                    describe(default),
                    yaml_type(v),
                    describe(&user)
                ),
            ));
        }
        merged.insert(key.clone(), user);
    }
    kind.canonical_params(&Value::Object(merged)).map_err(|e| {
        let msg = match e {
            stages::StageError::Params(m) => m,
            other => other.to_string(),
        };
        // Point at the param the message names (`name`, or `name.field[0]` when the kind's
        // deserialisation failed inside it), if the user gave it.
        let named = msg.split('`').nth(1).unwrap_or_default().to_string();
        let top = named.split(['.', '[']).next().unwrap_or_default();
        match given.iter().find(|(k, ..)| k == top) {
            Some((k, _, l)) if named == *k => {
                let rest = msg.strip_prefix(&format!("`{k}`: ")).unwrap_or(&msg);
                d.err(l.clone(), Some(&format!("params.{k}")), rest)
            }
            Some((_, _, l)) => {
                let rest = msg
                    .strip_prefix(&format!("`{named}`: "))
                    .unwrap_or(&msg)
                    .to_string();
                let full = format!("`{}.{named}`: {rest}", d.name);
                d.err(nested_loc(d, l, &named), None, full)
            }
            None => d.err(d.key("params"), None, msg),
        }
    })
}

/// A parameter of an earlier layout (`train.train.lr`), in the file or in a setting, is an
/// error that names where it went (`train.optimiser.lr`): never a silent default.
fn moved_params(
    d: &Decl,
    kind_name: &str,
    kind: &dyn Stage,
    given: &[(String, Yaml, Loc)],
    settings: &[Setting],
) -> Result<(), ConfigError> {
    let check = |path: &str, loc: Loc| match kind.moved_param(path) {
        Some(to) => Err(d.err(
            loc,
            None,
            stages::params_doc::moved_message(d.name, kind_name, path, &to),
        )),
        None => Ok(()),
    };
    for (key, v, l) in given {
        for path in leaf_paths(key, v) {
            check(&path, nested_loc(d, l, &path))?;
        }
    }
    for s in settings {
        for path in leaf_paths(&s.path.join("."), &s.value) {
            check(&path, s.loc.clone())?;
        }
    }
    Ok(())
}

/// The dotted paths of the values inside `v` (`path` itself when it is not a mapping, or an
/// empty one).
fn leaf_paths(path: &str, v: &Yaml) -> Vec<String> {
    match v {
        Yaml::Mapping(m) if !m.is_empty() => m
            .iter()
            .flat_map(|(k, x)| leaf_paths(&format!("{path}.{}", k.as_str().unwrap_or("?")), x))
            .collect(),
        Yaml::Tagged(t) => leaf_paths(path, &t.value),
        _ => vec![path.to_string()],
    }
}

/// Where the field `path` (`optimiser.lr`, `origin[0]`) inside a param stands: the field's own key
/// when the value came from the file, else where the param was given (`--set`).
fn nested_loc(d: &Decl, given: &Loc, path: &str) -> Loc {
    match given {
        Loc::File { .. } => match d.key(&format!(
            "params.{}",
            path.replace('[', ".").replace(']', "")
        )) {
            Loc::Unknown => given.clone(),
            l => l,
        },
        other => other.clone(),
    }
}

/// The first NaN or infinity in a param's value, with its path (`optimiser.lr`, `origin[0]`).
fn non_finite(v: &Yaml, path: &str) -> Option<(String, f64)> {
    match v {
        Yaml::Number(n) => n
            .as_f64()
            .filter(|x| !x.is_finite())
            .map(|x| (path.to_string(), x)),
        Yaml::Sequence(items) => items
            .iter()
            .enumerate()
            .find_map(|(i, item)| non_finite(item, &format!("{path}[{i}]"))),
        Yaml::Mapping(m) => m.iter().find_map(|(k, item)| {
            let k = k.as_str().unwrap_or("?");
            non_finite(item, &format!("{path}.{k}"))
        }),
        Yaml::Tagged(t) => non_finite(&t.value, path),
        _ => None,
    }
}

/// NaN and infinities as YAML writes them.
fn show_float(x: f64) -> &'static str {
    if x.is_nan() {
        ".nan (NaN)"
    } else if x > 0.0 {
        ".inf (infinity)"
    } else {
        "-.inf (-infinity)"
    }
}

/// Inputs name existing stages (of `stages` itself or of `more`) whose kind writes the tables
/// the slot reads; `section` is where `stages` are written (`stages`, `dataset`).
pub(super) fn check_inputs(
    cx: &Ctx,
    stages: &[StageDecl],
    more: &[StageDecl],
    section: &str,
) -> Result<(), ConfigError> {
    for s in stages {
        for (slot, up) in &s.inputs {
            let kpath = format!("{section}.{}.inputs.{slot}", s.name);
            let Some(u) = stages.iter().chain(more).find(|x| &x.name == up) else {
                return Err(cx.err(
                    cx.locs.value(&kpath),
                    Some(&s.name),
                    Some(&format!("inputs.{slot}")),
                    format!("no stage named `{up}` in this pipeline"),
                ));
            };
            let spec = s
                .kind
                .inputs()
                .iter()
                .find(|x| x.name == slot)
                .expect("slot checked");
            for t in spec.tables {
                if !u.kind.outputs().contains(t) {
                    return Err(cx.err(
                        cx.locs.value(&kpath),
                        Some(&s.name),
                        Some(&format!("inputs.{slot}")),
                        format!(
                            "stage `{up}` (kind `{}`) does not write table `{t}` that slot `{slot}` reads (it writes: {})",
                            u.kind.kind(),
                            u.kind.outputs().join(", ")
                        ),
                    ));
                }
            }
        }
    }
    Ok(())
}
