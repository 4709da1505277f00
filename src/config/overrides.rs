//! Parameter settings from outside a stage's `params:`: `--set STAGE.PARAM[.FIELD...]=VALUE` on
//! the command line and a scene's `set:`. Both reach inside nested params and keep the other
//! fields; [`set_path`] is the setter (`pipe bench` builds its variants with it too).

use std::path::Path;

use serde_yaml::{Mapping, Value as Yaml};

use super::error::{ConfigError, Loc};

/// A `--set stage.param=value` override; the value is parsed as YAML.
#[derive(Debug, Clone)]
pub struct Override {
    pub stage: String,
    pub param: String,
    pub value: Yaml,
    pub arg: String,
}

impl Override {
    pub fn parse(arg: &str) -> Result<Override, String> {
        let (lhs, value) = arg
            .split_once('=')
            .ok_or_else(|| format!("`{arg}`: expected STAGE.PARAM=VALUE"))?;
        let (stage, param) = lhs
            .split_once('.')
            .ok_or_else(|| format!("`{arg}`: expected STAGE.PARAM=VALUE"))?;
        if stage.is_empty() || param.is_empty() {
            return Err(format!("`{arg}`: expected STAGE.PARAM=VALUE"));
        }
        let value: Yaml =
            serde_yaml::from_str(value).map_err(|e| format!("`{arg}`: bad value: {e}"))?;
        Ok(Override {
            stage: stage.into(),
            param: param.into(),
            value,
            arg: arg.into(),
        })
    }

    /// The override as a setting of its stage's params.
    pub(super) fn setting(&self) -> Setting {
        Setting {
            path: self.param.split('.').map(String::from).collect(),
            value: self.value.clone(),
            loc: Loc::CommandLine(self.arg.clone()),
        }
    }
}

/// An `--set` override with its stage resolved among `names` (a scene name may hold `.`, so
/// the longest stage name that prefixes `STAGE.PARAM` wins).
pub(super) fn resolve(
    file: &Path,
    o: &Override,
    names: &[String],
) -> Result<Override, ConfigError> {
    let full = format!("{}.{}", o.stage, o.param);
    let best = names
        .iter()
        .filter(|n| full.len() > n.len() + 1 && full.starts_with(n.as_str()))
        .filter(|n| full.as_bytes()[n.len()] == b'.')
        .max_by_key(|n| n.len());
    match best {
        Some(n) => Ok(Override {
            stage: n.clone(),
            param: full[n.len() + 1..].to_string(),
            ..o.clone()
        }),
        None => Err(ConfigError {
            file: file.to_path_buf(),
            loc: Loc::CommandLine(o.arg.clone()),
            stage: Some(o.stage.clone()),
            key: None,
            message: "no such stage".into(),
        }),
    }
}

/// One setting of a stage's params: `[PARAM, FIELD...]`, the value, and where it was given.
#[derive(Debug, Clone)]
pub(crate) struct Setting {
    pub path: Vec<String>,
    pub value: Yaml,
    pub loc: Loc,
}

/// Applies `settings` in order to the params given in the file (`(param, value, where)`): a
/// whole param is replaced; a field inside one is set and its siblings are kept.
pub(super) fn apply(given: &mut Vec<(String, Yaml, Loc)>, settings: &[Setting]) {
    for s in settings {
        let key = s.path[0].clone();
        let value = if s.path.len() == 1 {
            s.value.clone()
        } else {
            let mut v = given
                .iter()
                .find(|(k, ..)| *k == key)
                .map_or(Yaml::Null, |(_, v, _)| v.clone());
            let fields: Vec<&str> = s.path[1..].iter().map(String::as_str).collect();
            set_path(&mut v, &fields, &s.value);
            v
        };
        given.retain(|(k, ..)| *k != key);
        given.push((key, value, s.loc.clone()));
    }
}

/// Sets `path` inside a params mapping, creating mappings on the way.
pub fn set_path(params: &mut Yaml, path: &[&str], value: &Yaml) {
    if !matches!(params, Yaml::Mapping(_)) {
        *params = Yaml::Mapping(Mapping::new());
    }
    let Yaml::Mapping(m) = params else {
        unreachable!()
    };
    let key = Yaml::String(path[0].to_string());
    if path.len() == 1 {
        m.insert(key, value.clone());
    } else {
        let child = m.entry(key).or_insert(Yaml::Null);
        set_path(child, &path[1..], value);
    }
}
