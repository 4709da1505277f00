//! The edits suite file (`benches/suites/edits.yaml`): scenes, seeds and edits of the boxes,
//! each run before, as an update and from scratch. Parsed strictly; errors name the file and
//! the key.

use std::path::{Path, PathBuf};

use serde::Deserialize;
use serde_yaml::{Mapping, Value as Yaml};

use crate::config::{ConfigError, Loc};

/// The built-in edits suites: (name, file it was built from, text).
pub const BUILT_IN: &[(&str, &str, &str)] = &[(
    "edits",
    "benches/suites/edits.yaml",
    include_str!("../../../benches/suites/edits.yaml"),
)];

/// An edits suite.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EditsSuite {
    pub name: String,
    /// The base pipeline (used unless `-f` names another).
    #[serde(default)]
    pub pipeline: Option<PathBuf>,
    /// The last stage each run computes (labels: `render`).
    pub until: String,
    /// `STAGE.PARAM` that takes the list of edits.
    pub edits_param: String,
    #[serde(default)]
    pub seeds: Option<Seeds>,
    pub scenes: Vec<Scene>,
    pub edits: Vec<EditCase>,
}

/// Every run once per value of `param`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Seeds {
    pub param: String,
    pub values: Vec<Yaml>,
}

/// A scene: the base pipeline (or its own) with these `STAGE.PARAM: value` settings.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    pub name: String,
    /// Its own pipeline file (e.g. `pipelines/kitti360.yaml` over an exported street).
    #[serde(default)]
    pub pipeline: Option<PathBuf>,
    #[serde(default)]
    pub set: Mapping,
}

/// One edit of the boxes: the scene before it (`before`, edits of the unedited scene) and after
/// it (`edits`), and the primitive (row of the unedited scene) whose pixels are scored.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EditCase {
    pub name: String,
    #[serde(default)]
    pub label: String,
    pub object: u32,
    #[serde(default = "empty_list")]
    pub before: Yaml,
    pub edits: Yaml,
}

fn empty_list() -> Yaml {
    Yaml::Sequence(Vec::new())
}

fn error(file: &Path, key: Option<String>, message: String) -> ConfigError {
    ConfigError {
        file: file.to_path_buf(),
        loc: Loc::Unknown,
        stage: None,
        key,
        message,
    }
}

/// The edits suite `spec` names (a built-in name or a .yaml file with an `edits:` list);
/// `None` when it is none (another kind of suite, or an unknown name).
pub fn load(spec: &str) -> Result<Option<EditsSuite>, ConfigError> {
    let (file, text) = match BUILT_IN.iter().find(|(n, ..)| *n == spec) {
        Some((_, file, text)) => (
            PathBuf::from(format!("{file} (built in)")),
            text.to_string(),
        ),
        None => {
            let file = PathBuf::from(spec);
            if !(spec.ends_with(".yaml") || spec.ends_with(".yml")) || !file.is_file() {
                return Ok(None);
            }
            let text = crate::config::read_text(&file, "suite file")?;
            (file, text)
        }
    };
    // Only a document with an `edits:` list is an edits suite; any other (or invalid YAML) is
    // left to the other suites' parser, which locates its errors.
    let Some(doc) = serde_yaml::from_str::<Yaml>(&text)
        .ok()
        .filter(|d| d.get("edits").is_some())
    else {
        return Ok(None);
    };
    let suite: EditsSuite = serde_yaml::from_value(doc)
        .map_err(|e| error(&file, None, format!("not an edits suite: {e}")))?;
    check(&file, &suite)?;
    Ok(Some(suite))
}

fn check(file: &Path, s: &EditsSuite) -> Result<(), ConfigError> {
    let dotted = |key: &str, v: &str| {
        if v.split_once('.')
            .is_some_and(|(a, b)| !a.is_empty() && !b.is_empty())
        {
            Ok(())
        } else {
            Err(error(
                file,
                Some(key.into()),
                format!("`{v}`: expected STAGE.PARAM"),
            ))
        }
    };
    dotted("edits_param", &s.edits_param)?;
    if let Some(seeds) = &s.seeds {
        dotted("seeds.param", &seeds.param)?;
        if seeds.values.is_empty() {
            return Err(error(file, Some("seeds.values".into()), "no value".into()));
        }
    }
    if s.scenes.is_empty() || s.edits.is_empty() {
        return Err(error(
            file,
            None,
            "an edits suite needs at least one scene and one edit".into(),
        ));
    }
    for (i, e) in s.edits.iter().enumerate() {
        for (what, v) in [("before", &e.before), ("edits", &e.edits)] {
            if !v.is_sequence() {
                return Err(error(
                    file,
                    Some(format!("edits[{i}].{what}")),
                    "expected a list of edits".into(),
                ));
            }
        }
    }
    for (i, sc) in s.scenes.iter().enumerate() {
        for k in sc.set.keys() {
            let k = k.as_str().unwrap_or_default();
            dotted(&format!("scenes[{i}].set"), k)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_built_in_suite_parses_and_other_suites_are_not_edits_suites() {
        let s = load("edits").unwrap().unwrap();
        assert_eq!(s.until, "render");
        assert_eq!(s.edits.len(), 4);
        assert!(load("quick").unwrap().is_none());
        assert!(load("nope").unwrap().is_none());
        let dir = std::env::temp_dir().join(format!("edits-suite-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let bad = dir.join("bad.yaml");
        std::fs::write(
            &bad,
            "name: x\nuntil: render\nedits_param: scene\nscenes: [{name: a}]\n\
             edits: [{name: e, object: 1, edits: []}]\n",
        )
        .unwrap();
        let e = load(bad.to_str().unwrap()).unwrap_err().to_string();
        assert!(
            e.contains("edits_param") && e.contains("STAGE.PARAM"),
            "{e}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// The suite files shipped beside the built-in one parse, with the edits of the built-in's.
    #[test]
    fn the_shipped_kitti360_suite_parses() {
        let file = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/benches/suites/edits-kitti360.yaml"
        );
        let s = load(file).unwrap().expect("an edits suite");
        let built_in = load("edits").unwrap().unwrap();
        assert_eq!(
            s.pipeline.as_deref(),
            Some(Path::new("pipelines/kitti360.yaml"))
        );
        let names = |s: &EditsSuite| s.edits.iter().map(|e| e.name.clone()).collect::<Vec<_>>();
        assert_eq!(names(&s), names(&built_in));
    }
}
