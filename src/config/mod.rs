//! `pipeline.yaml` -> a validated [`Pipeline`]: stage instances with their kind, canonical
//! parameters (defaults filled in) and named inputs. Every error names the file, the line and
//! column, the stage and the key; nothing runs when the file is invalid.
//!
//! ```yaml
//! cache: .pipe              # optional, relative to this file
//! scenes:                   # optional: a scene matrix (or a list, see below)
//!   matrix: {scene.seed: [1, 2], scene.noise: [0.5, 1.0]}
//! stages:
//!   scene:
//!     uses: synthetic_scene # a kind from the registry (`pipe kinds`)
//!     params: {frames: 16}
//!   rays:
//!     uses: intersect
//!     inputs: {scene: scene}  # input slot -> stage instance
//! dataset:                  # with `scenes:` only: stages run once over every scene
//!   summary:
//!     uses: aggregate
//!     inputs: {evaluate: evaluate}  # gathers `evaluate` of every scene
//! executor:                 # optional: resources of `pipe run --executor slurm`
//!   slurm: {partition: gpu, gpus: 1, time: "02:00:00"}
//! ```
//!
//! With `scenes:`, every stage under `stages:` is a template instantiated once per scene as
//! `STAGE@SCENE` (inputs renamed to the same scene), with the scene's parameter settings
//! applied. `scenes:` is either `matrix:` (every combination of the listed values; scene names
//! like `seed1-noise0.5`) or a list of `{name: NAME, set: {STAGE.PARAM[.FIELD...]: VALUE}}`.
//! A `dataset:` stage's input that names a template stage *gathers* it: the stage receives, for
//! each table the slot reads, the rows of every scene with a leading `scene` column.
//!
//! The parts: `yaml` (positions of keys, messages about values), `validate` (a stage
//! against the registry), `scenes` (matrix and expansion), `overrides` (`--set` and the
//! param setter), `slurm` (`executor.slurm`); this file reads the top-level sections and
//! puts them together.

mod error;
mod overrides;
mod pipeline;
mod scenes;
mod slurm;
mod validate;
mod yaml;

use std::path::{Path, PathBuf};

use serde_yaml::{Mapping, Value as Yaml};

pub use error::{ConfigError, Loc};
pub use overrides::{set_path, Override};
pub use pipeline::{Pipeline, StageDecl};
pub use slurm::SlurmConfig;
pub(crate) use yaml::Locations;
pub use yaml::{shorten, show_json};

use yaml::{yaml_type, Ctx};

const TOP_KEYS: &[&str] = &["cache", "scenes", "stages", "dataset", "executor"];

/// The largest pipeline or suite file read (a pipeline file is a few KiB).
pub const MAX_FILE_BYTES: u64 = 4 << 20;

/// The text of a pipeline or suite file (`what` names it in messages): only a regular file of at
/// most [`MAX_FILE_BYTES`] is read, so a FIFO, a device or a huge file is refused at once instead
/// of hanging or filling the memory.
pub fn read_text(file: &Path, what: &str) -> Result<String, ConfigError> {
    let err = |message: String| ConfigError {
        file: file.to_path_buf(),
        loc: Loc::Unknown,
        stage: None,
        key: None,
        message,
    };
    let meta = std::fs::metadata(file).map_err(|e| err(format!("cannot read the {what}: {e}")))?;
    if !meta.is_file() {
        let kind = if meta.is_dir() {
            "a directory"
        } else {
            "not a regular file (a FIFO, socket or device?)"
        };
        return Err(err(format!("the {what} is {kind}: expected a YAML file")));
    }
    if meta.len() > MAX_FILE_BYTES {
        return Err(err(format!(
            "the {what} is {:.1} MiB; more than {} MiB is refused (is it the right file?)",
            meta.len() as f64 / (1u64 << 20) as f64,
            MAX_FILE_BYTES >> 20
        )));
    }
    let mut text = String::new();
    std::io::Read::read_to_string(
        &mut std::io::Read::take(
            std::fs::File::open(file).map_err(|e| err(format!("cannot read the {what}: {e}")))?,
            MAX_FILE_BYTES + 1,
        ),
        &mut text,
    )
    .map_err(|e| err(format!("cannot read the {what}: {e}")))?;
    if text.len() as u64 > MAX_FILE_BYTES {
        return Err(err(format!(
            "the {what} grew past {} MiB while being read",
            MAX_FILE_BYTES >> 20
        )));
    }
    Ok(text)
}

/// Loads and validates a pipeline file, applying `--set` overrides.
pub fn load(file: &Path, overrides: &[Override]) -> Result<Pipeline, ConfigError> {
    let text = read_text(file, "pipeline file")?;
    parse(file, &text, overrides)
}

/// Validates pipeline text (`file` is used in messages and to resolve `cache`).
pub fn parse(file: &Path, text: &str, overrides: &[Override]) -> Result<Pipeline, ConfigError> {
    let cx = Ctx {
        file,
        locs: Locations::scan(text),
    };
    let doc: Yaml = serde_yaml::from_str(text).map_err(|e| {
        let (loc, msg) = cx.locs.serde_error(text, &e);
        cx.err(loc, None, None, format!("invalid YAML: {msg}"))
    })?;
    let top = Sections::read(&cx, &doc)?;
    let stages_map = stages_section(&cx, top.stages)?;
    let slurm = match top.executor {
        None => SlurmConfig::default(),
        Some(v) => slurm::executor_config(&cx, v)?,
    };
    let scenes = match top.scenes {
        None => Vec::new(),
        Some(v) => scenes::parse_scenes(&cx, v, stages_map)?,
    };
    let dataset_map = dataset_section(&cx, top.dataset, !scenes.is_empty())?;
    let names = addressable_names(&cx, stages_map, dataset_map, &scenes)?;
    let overrides = overrides
        .iter()
        .map(|o| overrides::resolve(file, o, &names))
        .collect::<Result<Vec<_>, _>>()?;

    // The stages as written (templates when there are scenes), validated once.
    let mut stages = declare(&cx, "stages", Some(stages_map), &overrides)?;
    let mut dataset = declare(&cx, "dataset", dataset_map, &overrides)?;
    validate::check_inputs(&cx, &stages, &[], "stages")?;
    validate::check_inputs(&cx, &dataset, &stages, "dataset")?;

    if !scenes.is_empty() {
        let templates: Vec<String> = stages.iter().map(|s| s.name.clone()).collect();
        stages = scenes::expand(&cx, stages_map, &scenes, &overrides)?;
        scenes::gather(&mut dataset, &templates, &scenes);
        stages.extend(dataset);
    }

    let dir = file.parent().unwrap_or(Path::new("."));
    Ok(Pipeline {
        file: file.to_path_buf(),
        cache_dir: dir.join(top.cache.unwrap_or_else(|| ".pipe".into())),
        stages,
        scenes: scenes.into_iter().map(|s| s.name).collect(),
        slurm,
    })
}

/// The top-level keys of a pipeline file, each checked for its shape.
struct Sections<'a> {
    cache: Option<PathBuf>,
    stages: Option<&'a Yaml>,
    scenes: Option<&'a Yaml>,
    dataset: Option<&'a Yaml>,
    executor: Option<&'a Yaml>,
}

impl<'a> Sections<'a> {
    fn read(cx: &Ctx, doc: &'a Yaml) -> Result<Sections<'a>, ConfigError> {
        let top = match doc {
            Yaml::Mapping(m) => m,
            Yaml::Null => {
                return Err(cx.err(
                    Loc::Unknown,
                    None,
                    None,
                    "the file is empty: expected a `stages:` mapping",
                ))
            }
            other => {
                return Err(cx.err(
                    cx.locs.value(""),
                    None,
                    None,
                    format!(
                        "expected a mapping with `stages:`, found {}",
                        yaml_type(other)
                    ),
                ))
            }
        };
        let mut s = Sections {
            cache: None,
            stages: None,
            scenes: None,
            dataset: None,
            executor: None,
        };
        for (k, v) in top {
            let key = k.as_str().unwrap_or("?");
            match key {
                "cache" => match v.as_str() {
                    Some(c) if !c.is_empty() => s.cache = Some(c.into()),
                    _ => {
                        return Err(cx.err(
                            cx.locs.value("cache"),
                            None,
                            Some("cache"),
                            "expected a directory path",
                        ))
                    }
                },
                "stages" => s.stages = Some(v),
                "scenes" => s.scenes = Some(v),
                "dataset" => s.dataset = Some(v),
                "executor" => s.executor = Some(v),
                other => {
                    return Err(cx.err(
                        cx.locs.key(other),
                        None,
                        Some(other),
                        format!("unknown key (expected one of: {})", TOP_KEYS.join(", ")),
                    ))
                }
            }
        }
        Ok(s)
    }
}

/// `stages:`: a non-empty mapping of stage name -> stage.
fn stages_section<'a>(cx: &Ctx, v: Option<&'a Yaml>) -> Result<&'a Mapping, ConfigError> {
    match v {
        Some(Yaml::Mapping(m)) if !m.is_empty() => Ok(m),
        Some(Yaml::Mapping(_)) | Some(Yaml::Null) => Err(cx.err(
            cx.locs.key("stages"),
            None,
            Some("stages"),
            "no stages declared",
        )),
        Some(other) => Err(cx.err(
            cx.locs.value("stages"),
            None,
            Some("stages"),
            format!(
                "expected a mapping of stage name -> stage, found {}",
                yaml_type(other)
            ),
        )),
        None => Err(cx.err(
            Loc::Unknown,
            None,
            Some("stages"),
            "missing `stages:` mapping",
        )),
    }
}

/// `dataset:`: stages that run once over every scene (only with `scenes:`).
fn dataset_section<'a>(
    cx: &Ctx,
    v: Option<&'a Yaml>,
    has_scenes: bool,
) -> Result<Option<&'a Mapping>, ConfigError> {
    match v {
        None | Some(Yaml::Null) => Ok(None),
        Some(_) if !has_scenes => Err(cx.err(
            cx.locs.key("dataset"),
            None,
            Some("dataset"),
            "dataset stages need a `scenes:` section (they run over every scene)",
        )),
        Some(Yaml::Mapping(m)) => Ok(Some(m)),
        Some(other) => Err(cx.err(
            cx.locs.value("dataset"),
            None,
            Some("dataset"),
            format!(
                "expected a mapping of stage name -> stage, found {}",
                yaml_type(other)
            ),
        )),
    }
}

/// Every name a `--set` may address: stages, dataset stages and stage instances. Checks the
/// stage names on the way.
fn addressable_names(
    cx: &Ctx,
    stages: &Mapping,
    dataset: Option<&Mapping>,
    scenes: &[scenes::SceneDecl],
) -> Result<Vec<String>, ConfigError> {
    let mut names: Vec<String> = Vec::new();
    for (k, _) in stages.iter().chain(dataset.into_iter().flatten()) {
        let name = match k.as_str() {
            Some(n) if validate::valid_name(n) => n.to_string(),
            _ => {
                return Err(cx.err(
                    cx.locs.value("stages"),
                    None,
                    None,
                    format!(
                        "bad stage name {:?}: use letters, digits, `_` and `-`",
                        serde_yaml::to_string(k).unwrap_or_default().trim()
                    ),
                ))
            }
        };
        if names.contains(&name) {
            return Err(cx.err(
                cx.locs.key(&format!("dataset.{name}")),
                Some(&name),
                None,
                "a dataset stage cannot have the name of a stage under `stages:`",
            ));
        }
        names.push(name);
    }
    for t in stages.keys().filter_map(|k| k.as_str()) {
        for sc in scenes {
            names.push(format!("{t}@{}", sc.name));
        }
    }
    Ok(names)
}

/// The stages of one section (`stages`, `dataset`) as written, with their `--set` overrides.
fn declare(
    cx: &Ctx,
    section: &str,
    m: Option<&Mapping>,
    overrides: &[Override],
) -> Result<Vec<StageDecl>, ConfigError> {
    m.into_iter()
        .flatten()
        .map(|(k, v)| {
            let name = k.as_str().expect("names checked");
            let settings: Vec<_> = overrides
                .iter()
                .filter(|o| o.stage == name)
                .map(Override::setting)
                .collect();
            validate::stage_decl(cx, name, &format!("{section}.{name}"), v, &settings)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse_str(text: &str) -> Result<Pipeline, ConfigError> {
        parse(Path::new("pipeline.yaml"), text, &[])
    }

    #[test]
    fn a_valid_pipeline_fills_defaults() {
        let p = parse_str(
            "stages:\n  a:\n    uses: test_source\n    params: {value: 5}\n  b:\n    uses: test_map\n    inputs: {src: a}\n",
        )
        .unwrap();
        assert_eq!(p.stages.len(), 2);
        assert_eq!(p.stages[0].params["value"], 5);
        assert_eq!(p.stages[0].params["rows"], 3);
        assert_eq!(p.stages[1].inputs["src"], "a");
        assert_eq!(p.cache_dir, Path::new(".pipe"));
    }

    #[test]
    fn locations_are_one_based() {
        let e = parse_str("stages:\n  a:\n    uses: test_source\n    bogus: 1\n")
            .err()
            .unwrap();
        assert_eq!(e.loc, Loc::File { line: 4, col: 5 }, "{e}");
        assert!(
            e.to_string()
                .starts_with("pipeline.yaml:4:5: stage `a`: `bogus`: unknown key"),
            "{e}"
        );
    }

    #[test]
    fn overrides_replace_params() {
        let o = Override::parse("a.value=7").unwrap();
        let p = parse(
            Path::new("p.yaml"),
            "stages:\n  a:\n    uses: test_source\n    params: {value: 5}\n",
            &[o],
        )
        .unwrap();
        assert_eq!(p.stages[0].params["value"], 7);
        let bad = Override::parse("a.value=abc").unwrap();
        let e = parse(
            Path::new("p.yaml"),
            "stages:\n  a:\n    uses: test_source\n",
            &[bad],
        )
        .err()
        .unwrap();
        assert!(e.to_string().contains("command line `a.value=abc`"), "{e}");
        assert!(Override::parse("novalue").is_err());
    }

    #[test]
    fn overrides_reach_inside_nested_params_and_keep_their_siblings() {
        let text =
            std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/pipeline.yaml")).unwrap();
        let sets = ["train.optimiser.lr=0.01", "train.sampling.samples=16"];
        let o: Vec<Override> = sets.iter().map(|s| Override::parse(s).unwrap()).collect();
        let plain = parse(Path::new("pipeline.yaml"), &text, &[]).unwrap();
        let plain = &plain.stages[plain.index_of("train").unwrap()].params;
        let p = parse(Path::new("pipeline.yaml"), &text, &o).unwrap();
        let train = &p.stages[p.index_of("train").unwrap()].params;
        assert_eq!(train["optimiser"]["lr"], 0.01);
        assert_ne!(plain["optimiser"]["lr"], 0.01);
        assert_eq!(
            train["optimiser"]["adam_beta1"], plain["optimiser"]["adam_beta1"],
            "sibling kept: {train}"
        );
        assert_eq!(train["sampling"]["samples"], 16);
        let bad = Override::parse("train.optimiser.no_such_field=1").unwrap();
        let e = parse(Path::new("pipeline.yaml"), &text, &[bad])
            .err()
            .unwrap();
        assert!(e.to_string().contains("no_such_field"), "{e}");
    }
}
