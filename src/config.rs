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

use std::{
    collections::{BTreeMap, BTreeSet, HashMap},
    fmt,
    path::{Path, PathBuf},
};

use serde_json::Value;
use serde_yaml::Value as Yaml;
use stages::Stage;
use yaml_rust2::{parser::MarkedEventReceiver, parser::Parser, scanner::Marker, Event};

/// A place in the pipeline file (1-based line and column), or a command-line override.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Loc {
    File { line: usize, col: usize },
    CommandLine(String),
    Unknown,
}

/// A configuration error: exit code 2.
#[derive(Debug, Clone)]
pub struct ConfigError {
    pub file: PathBuf,
    pub loc: Loc,
    pub stage: Option<String>,
    pub key: Option<String>,
    pub message: String,
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file.display())?;
        match &self.loc {
            Loc::File { line, col } => write!(f, ":{line}:{col}")?,
            Loc::CommandLine(arg) => write!(f, " (command line `{arg}`)")?,
            Loc::Unknown => {}
        }
        write!(f, ": ")?;
        if let Some(s) = &self.stage {
            write!(f, "stage `{s}`: ")?;
        }
        if let Some(k) = &self.key {
            write!(f, "`{k}`: ")?;
        }
        write!(f, "{}", self.message)
    }
}

impl std::error::Error for ConfigError {}

/// One stage instance, validated.
pub struct StageDecl {
    /// The scene this instance belongs to (`None`: a plain or dataset-level stage).
    pub scene: Option<String>,
    /// The name of the stage in the file (`train` for the instance `train@seed1`).
    pub template: String,
    /// Gathered input slots of a dataset stage: slot -> (scene, stage instance) for every
    /// scene, in scene order.
    pub gather: BTreeMap<String, Vec<(String, String)>>,
    pub name: String,
    pub kind: Box<dyn Stage>,
    /// Canonical parameters: every param of the kind, defaults filled in, serialised by the
    /// kind's own type (so `lr: 1` and `lr: 1.0` are the same).
    pub params: Value,
    /// Input slot -> upstream stage instance name.
    pub inputs: BTreeMap<String, String>,
    pub loc: Loc,
}

/// A validated pipeline.
pub struct Pipeline {
    pub file: PathBuf,
    /// Cache directory (absolute or relative to the working directory).
    pub cache_dir: PathBuf,
    /// Stage instances in file order (scene by scene, then the dataset stages).
    pub stages: Vec<StageDecl>,
    /// Scene names in file order; empty when the file declares no `scenes:`.
    pub scenes: Vec<String>,
    /// `executor.slurm` of the file.
    pub slurm: SlurmConfig,
}

impl Pipeline {
    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.stages.iter().position(|s| s.name == name)
    }

    /// Indices of the stage instances of `scene`.
    pub fn scene_stages(&self, scene: &str) -> Vec<usize> {
        (0..self.stages.len())
            .filter(|&i| self.stages[i].scene.as_deref() == Some(scene))
            .collect()
    }

    /// Indices of the dataset-level stages (those of no scene, in a scene pipeline).
    pub fn dataset_stages(&self) -> Vec<usize> {
        if self.scenes.is_empty() {
            return Vec::new();
        }
        (0..self.stages.len())
            .filter(|&i| self.stages[i].scene.is_none())
            .collect()
    }

    /// Instances named `name`: the stage itself, or a template's instance in each of `scenes`.
    pub fn instances(&self, name: &str, scenes: &[String]) -> Vec<usize> {
        if let Some(i) = self.index_of(name) {
            return vec![i];
        }
        (0..self.stages.len())
            .filter(|&i| {
                let s = &self.stages[i];
                s.template == name && s.scene.as_ref().is_some_and(|sc| scenes.contains(sc))
            })
            .collect()
    }
}

impl StageDecl {
    /// Every upstream stage instance, plain and gathered.
    pub fn upstream_names(&self) -> impl Iterator<Item = &String> {
        self.inputs
            .values()
            .chain(self.gather.values().flatten().map(|(_, up)| up))
    }
}

/// `executor.slurm` of a pipeline file: what `pipe run --executor slurm` asks for per task.
#[derive(Debug, Clone, Default, serde::Deserialize, serde::Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct SlurmConfig {
    /// `--partition`.
    pub partition: Option<String>,
    /// `--cpus-per-task`.
    pub cpus_per_task: Option<u32>,
    /// GPUs per task (`--gres=gpu:N`).
    pub gpus: Option<u32>,
    /// `--mem` (e.g. `16G`).
    pub mem: Option<String>,
    /// `--time` (e.g. `02:00:00`).
    pub time: Option<String>,
    /// At most this many tasks of the array at once (`--array=...%N`).
    pub max_parallel: Option<u32>,
    /// `--job-name` (default `pipe`).
    pub job_name: Option<String>,
    /// More sbatch options, passed as they are (e.g. `--account=proj`, `--qos=normal`).
    pub sbatch_args: Vec<String>,
    /// Shell lines each task runs before `pipe` (e.g. `module load cuda`).
    pub setup: Option<String>,
    /// The `pipe` binary on the compute nodes (default: the coordinator's own binary).
    pub pipe: Option<String>,
    /// Seconds between two looks at the queue (default 5).
    pub poll_s: Option<f64>,
}

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
}

/// Key paths (`stages.train.params.lr`) -> where the key stands in the file.
#[derive(Default)]
pub(crate) struct Locations {
    map: HashMap<String, Loc>,
}

impl Locations {
    pub(crate) fn scan(text: &str) -> Locations {
        struct Recv {
            stack: Vec<Frame>,
            out: HashMap<String, Loc>,
        }
        enum Frame {
            Map { path: String, key: Option<String> },
            Seq { path: String, index: usize },
        }
        impl Recv {
            /// The path of the node that is starting now, and marks its key as consumed.
            fn child_path(&mut self, scalar: Option<&str>, mark: Marker) -> Option<String> {
                match self.stack.last_mut() {
                    None => Some(String::new()),
                    Some(Frame::Map { path, key }) => match key.take() {
                        Some(k) => Some(join(path, &k)),
                        None => {
                            // This scalar is a key.
                            let k = scalar.unwrap_or("?").to_string();
                            let p = join(path, &k);
                            self.out.insert(
                                p,
                                Loc::File {
                                    line: mark.line(),
                                    col: mark.col() + 1,
                                },
                            );
                            *key = Some(k);
                            None
                        }
                    },
                    Some(Frame::Seq { path, index }) => {
                        let p = join(path, &index.to_string());
                        *index += 1;
                        Some(p)
                    }
                }
            }
        }
        fn join(a: &str, b: &str) -> String {
            if a.is_empty() {
                b.to_string()
            } else {
                format!("{a}.{b}")
            }
        }
        impl MarkedEventReceiver for Recv {
            fn on_event(&mut self, ev: Event, mark: Marker) {
                let loc = Loc::File {
                    line: mark.line(),
                    col: mark.col() + 1,
                };
                match ev {
                    Event::Scalar(s, ..) => {
                        if let Some(p) = self.child_path(Some(&s), mark) {
                            self.out.entry(format!("{p}#value")).or_insert(loc);
                        }
                    }
                    Event::Alias(_) => {
                        self.child_path(None, mark);
                    }
                    Event::MappingStart(..) => {
                        let p = self.child_path(None, mark).unwrap_or_default();
                        self.out.entry(format!("{p}#value")).or_insert(loc);
                        self.stack.push(Frame::Map { path: p, key: None });
                    }
                    Event::SequenceStart(..) => {
                        let p = self.child_path(None, mark).unwrap_or_default();
                        self.out.entry(format!("{p}#value")).or_insert(loc);
                        self.stack.push(Frame::Seq { path: p, index: 0 });
                    }
                    Event::MappingEnd | Event::SequenceEnd => {
                        self.stack.pop();
                    }
                    _ => {}
                }
            }
        }
        let mut recv = Recv {
            stack: Vec::new(),
            out: HashMap::new(),
        };
        // Syntax errors are reported by serde_yaml; a failed scan only loses locations.
        let _ = Parser::new_from_str(text).load(&mut recv, false);
        Locations { map: recv.out }
    }

    /// Where key `path` stands (falling back to its parents).
    pub(crate) fn key(&self, path: &str) -> Loc {
        let mut p = path.to_string();
        loop {
            if let Some(l) = self.map.get(&p) {
                return l.clone();
            }
            match p.rfind('.') {
                Some(i) => p.truncate(i),
                None => return Loc::Unknown,
            }
        }
    }

    /// Where the value of key `path` starts.
    pub(crate) fn value(&self, path: &str) -> Loc {
        self.map
            .get(&format!("{path}#value"))
            .cloned()
            .unwrap_or_else(|| self.key(path))
    }
}

const TOP_KEYS: &[&str] = &["cache", "scenes", "stages", "dataset", "executor"];
const STAGE_KEYS: &[&str] = &["uses", "params", "inputs", "doc"];

struct Ctx<'a> {
    file: &'a Path,
    locs: Locations,
}

impl Ctx<'_> {
    fn err(
        &self,
        loc: Loc,
        stage: Option<&str>,
        key: Option<&str>,
        msg: impl Into<String>,
    ) -> ConfigError {
        ConfigError {
            file: self.file.to_path_buf(),
            loc,
            stage: stage.map(String::from),
            key: key.map(String::from),
            message: msg.into(),
        }
    }
}

fn yaml_type(v: &Yaml) -> &'static str {
    match v {
        Yaml::Null => "null",
        Yaml::Bool(_) => "a boolean",
        Yaml::Number(n) if n.is_f64() => "a float",
        Yaml::Number(_) => "an integer",
        Yaml::String(_) => "a string",
        Yaml::Sequence(_) => "a list",
        Yaml::Mapping(_) => "a mapping",
        Yaml::Tagged(_) => "a tagged value",
    }
}

fn json_type(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(n) if n.is_f64() => "a number",
        Value::Number(_) => "an integer",
        Value::String(_) => "a string",
        Value::Array(_) => "a list",
        Value::Object(_) => "a mapping",
    }
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

fn describe(v: &Value) -> String {
    shorten(&v.to_string(), 40)
}

/// `s` cut to at most `max` characters plus `...` (on a character boundary: values may hold
/// any UTF-8).
pub fn shorten(s: &str, max: usize) -> String {
    match s.char_indices().nth(max) {
        Some((end, _)) => format!("{}...", &s[..end]),
        None => s.to_string(),
    }
}

/// Loads and validates a pipeline file, applying `--set` overrides.
pub fn load(file: &Path, overrides: &[Override]) -> Result<Pipeline, ConfigError> {
    let text = std::fs::read_to_string(file).map_err(|e| ConfigError {
        file: file.to_path_buf(),
        loc: Loc::Unknown,
        stage: None,
        key: None,
        message: format!("cannot read the pipeline file: {e}"),
    })?;
    parse(file, &text, overrides)
}

/// Validates pipeline text (`file` is used in messages and to resolve `cache`).
pub fn parse(file: &Path, text: &str, overrides: &[Override]) -> Result<Pipeline, ConfigError> {
    let cx = Ctx {
        file,
        locs: Locations::scan(text),
    };
    let doc: Yaml = serde_yaml::from_str(text).map_err(|e| {
        let loc = e.location().map_or(Loc::Unknown, |l| Loc::File {
            line: l.line(),
            col: l.column(),
        });
        // serde_yaml appends " at line X column Y"; the location is already in front.
        let msg = e.to_string();
        let msg = msg.split(" at line ").next().unwrap_or(&msg).to_string();
        // serde_yaml points at the mapping; point at the repeated key instead.
        let loc = match (msg.split_once(": duplicate entry with key \""), &loc) {
            (Some((path, rest)), _) => {
                let key = rest.trim_end_matches('"');
                match cx.locs.key(&format!("{path}.{key}")) {
                    Loc::Unknown => loc,
                    l => l,
                }
            }
            _ => loc,
        };
        cx.err(loc, None, None, format!("invalid YAML: {msg}"))
    })?;
    let top = match &doc {
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
    let mut cache = None;
    let mut stages_yaml = None;
    let mut scenes_yaml = None;
    let mut dataset_yaml = None;
    let mut executor_yaml = None;
    for (k, v) in top {
        let key = k.as_str().unwrap_or("?");
        match key {
            "cache" => match v.as_str() {
                Some(s) if !s.is_empty() => cache = Some(s.to_string()),
                _ => {
                    return Err(cx.err(
                        cx.locs.value("cache"),
                        None,
                        Some("cache"),
                        "expected a directory path",
                    ))
                }
            },
            "stages" => stages_yaml = Some(v),
            "scenes" => scenes_yaml = Some(v),
            "dataset" => dataset_yaml = Some(v),
            "executor" => executor_yaml = Some(v),
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
    let stages_map = match stages_yaml {
        Some(Yaml::Mapping(m)) if !m.is_empty() => m,
        Some(Yaml::Mapping(_)) | Some(Yaml::Null) => {
            return Err(cx.err(
                cx.locs.key("stages"),
                None,
                Some("stages"),
                "no stages declared",
            ))
        }
        Some(other) => {
            return Err(cx.err(
                cx.locs.value("stages"),
                None,
                Some("stages"),
                format!(
                    "expected a mapping of stage name -> stage, found {}",
                    yaml_type(other)
                ),
            ))
        }
        None => {
            return Err(cx.err(
                Loc::Unknown,
                None,
                Some("stages"),
                "missing `stages:` mapping",
            ))
        }
    };

    let slurm = match executor_yaml {
        None => SlurmConfig::default(),
        Some(v) => executor_config(&cx, v)?,
    };
    let scenes = match scenes_yaml {
        None => Vec::new(),
        Some(v) => parse_scenes(&cx, v, stages_map)?,
    };
    let dataset_map = match dataset_yaml {
        None | Some(Yaml::Null) => None,
        Some(_) if scenes.is_empty() => {
            return Err(cx.err(
                cx.locs.key("dataset"),
                None,
                Some("dataset"),
                "dataset stages need a `scenes:` section (they run over every scene)",
            ))
        }
        Some(Yaml::Mapping(m)) => Some(m),
        Some(other) => {
            return Err(cx.err(
                cx.locs.value("dataset"),
                None,
                Some("dataset"),
                format!(
                    "expected a mapping of stage name -> stage, found {}",
                    yaml_type(other)
                ),
            ))
        }
    };

    // Every name a `--set` may address: stages, dataset stages and stage instances.
    let mut names: Vec<String> = Vec::new();
    for (k, _) in stages_map.iter().chain(dataset_map.into_iter().flatten()) {
        let name = match k.as_str() {
            Some(n) if valid_name(n) => n.to_string(),
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
    let templates: Vec<String> = stages_map
        .keys()
        .filter_map(|k| k.as_str().map(String::from))
        .collect();
    for t in &templates {
        for sc in &scenes {
            names.push(format!("{t}@{}", sc.name));
        }
    }
    let overrides = overrides
        .iter()
        .map(|o| resolve_override(file, o, &names))
        .collect::<Result<Vec<_>, _>>()?;

    // The stages as written (templates when there are scenes), validated once.
    let mut stages = Vec::new();
    for (k, v) in stages_map {
        let name = k.as_str().expect("checked above");
        let mine: Vec<&Override> = overrides.iter().filter(|o| o.stage == name).collect();
        stages.push(stage_decl(
            &cx,
            name,
            &format!("stages.{name}"),
            v,
            &[],
            &mine,
        )?);
    }
    let mut dataset = Vec::new();
    for (k, v) in dataset_map.into_iter().flatten() {
        let name = k.as_str().expect("checked above");
        let mine: Vec<&Override> = overrides.iter().filter(|o| o.stage == name).collect();
        dataset.push(stage_decl(
            &cx,
            name,
            &format!("dataset.{name}"),
            v,
            &[],
            &mine,
        )?);
    }
    check_inputs(&cx, &stages, &[], "stages")?;
    check_inputs(&cx, &dataset, &stages, "dataset")?;

    if !scenes.is_empty() {
        stages = expand_scenes(&cx, stages_map, &scenes, &overrides)?;
        for d in &mut dataset {
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
        stages.extend(dataset);
    }

    let cache_dir = match cache {
        Some(c) => file.parent().unwrap_or(Path::new(".")).join(c),
        None => file.parent().unwrap_or(Path::new(".")).join(".pipe"),
    };
    Ok(Pipeline {
        file: file.to_path_buf(),
        cache_dir,
        stages,
        scenes: scenes.into_iter().map(|s| s.name).collect(),
        slurm,
    })
}

/// An `--set` override with its stage resolved among `names` (a scene name may hold `.`, so
/// the longest stage name that prefixes `STAGE.PARAM` wins).
fn resolve_override(file: &Path, o: &Override, names: &[String]) -> Result<Override, ConfigError> {
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

/// One parameter setting of a scene: `STAGE.PARAM[.FIELD...]: VALUE`.
struct SceneSet {
    stage: String,
    /// PARAM and the fields below it.
    path: Vec<String>,
    value: Yaml,
    loc: Loc,
}

/// A scene of the matrix or the list.
struct SceneDecl {
    name: String,
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
    templates: &serde_yaml::Mapping,
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
        path: parts[1..].iter().map(|p| p.to_string()).collect(),
        value: value.clone(),
        loc,
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
fn parse_scenes(
    cx: &Ctx,
    v: &Yaml,
    templates: &serde_yaml::Mapping,
) -> Result<Vec<SceneDecl>, ConfigError> {
    let bad = |loc: Loc, key: Option<&str>, msg: String| cx.err(loc, None, key, msg);
    let mut out: Vec<SceneDecl> = Vec::new();
    match v {
        Yaml::Mapping(m) => {
            for k in m.keys() {
                let key = k.as_str().unwrap_or("?");
                if key != "matrix" {
                    return Err(bad(
                        cx.locs.key(&format!("scenes.{key}")),
                        Some(key),
                        "unknown key (expected `matrix:`, or a list of `{name, set}` scenes)"
                            .into(),
                    ));
                }
            }
            let Some(Yaml::Mapping(matrix)) = m.get("matrix") else {
                return Err(bad(
                    cx.locs.value("scenes.matrix"),
                    Some("matrix"),
                    "expected a mapping of STAGE.PARAM -> list of values".into(),
                ));
            };
            if matrix.is_empty() {
                return Err(bad(
                    cx.locs.key("scenes.matrix"),
                    Some("matrix"),
                    "the matrix is empty".into(),
                ));
            }
            // (key, values) with each value's scene-name part and location.
            /// One matrix key's values: (value, its scene-name part, where it is written).
            type Axis = Vec<(Yaml, String, Loc)>;
            let mut axes: Vec<(String, Axis)> = Vec::new();
            for (k, vals) in matrix {
                let key = k.as_str().unwrap_or("?").to_string();
                let kpath = format!("scenes.matrix.{key}");
                let Yaml::Sequence(list) = vals else {
                    return Err(bad(
                        cx.locs.value(&kpath),
                        Some(&key),
                        format!("expected a list of values, found {}", yaml_type(vals)),
                    ));
                };
                if list.is_empty() {
                    return Err(bad(
                        cx.locs.value(&kpath),
                        Some(&key),
                        "expected at least one value".into(),
                    ));
                }
                let mut axis = Vec::new();
                for (j, x) in list.iter().enumerate() {
                    let loc = cx.locs.value(&format!("{kpath}.{j}"));
                    let part = name_part(x).ok_or_else(|| {
                        bad(
                            loc.clone(),
                            Some(&key),
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
            // Every combination, the first key varying slowest.
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
        }
        Yaml::Sequence(list) if !list.is_empty() => {
            for (i, item) in list.iter().enumerate() {
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
                out.push(SceneDecl { name, sets });
            }
        }
        other => {
            return Err(bad(
                cx.locs.value("scenes"),
                Some("scenes"),
                format!(
                    "expected `matrix:` or a non-empty list of scenes, found {}",
                    yaml_type(other)
                ),
            ))
        }
    }
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

/// The stage instances of every scene: each stage under `stages:` once per scene, named
/// `STAGE@SCENE`, its inputs renamed to the same scene and the scene's settings applied.
fn expand_scenes(
    cx: &Ctx,
    templates: &serde_yaml::Mapping,
    scenes: &[SceneDecl],
    overrides: &[Override],
) -> Result<Vec<StageDecl>, ConfigError> {
    let mut out = Vec::new();
    for sc in scenes {
        for (k, v) in templates {
            let tname = k.as_str().expect("checked");
            let name = format!("{tname}@{}", sc.name);
            let sets: Vec<&SceneSet> = sc.sets.iter().filter(|s| s.stage == tname).collect();
            let mine: Vec<&Override> = overrides
                .iter()
                .filter(|o| o.stage == tname || o.stage == name)
                .collect();
            let mut d = stage_decl(cx, &name, &format!("stages.{tname}"), v, &sets, &mine)?;
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

/// `executor:` of the file: `slurm:` resources.
fn executor_config(cx: &Ctx, v: &Yaml) -> Result<SlurmConfig, ConfigError> {
    let m = match v {
        Yaml::Mapping(m) => m,
        Yaml::Null => return Ok(SlurmConfig::default()),
        other => {
            return Err(cx.err(
                cx.locs.value("executor"),
                None,
                Some("executor"),
                format!(
                    "expected a mapping with `slurm:`, found {}",
                    yaml_type(other)
                ),
            ))
        }
    };
    let mut slurm = SlurmConfig::default();
    for (k, x) in m {
        match k.as_str().unwrap_or("?") {
            "slurm" => {
                slurm = serde_yaml::from_value(x.clone()).map_err(|e| {
                    let msg = e.to_string();
                    let field = msg
                        .strip_prefix("unknown field `")
                        .and_then(|r| r.split('`').next())
                        .map(String::from);
                    let loc = match &field {
                        Some(f) => cx.locs.key(&format!("executor.slurm.{f}")),
                        None => cx.locs.value("executor.slurm"),
                    };
                    cx.err(loc, None, Some("executor.slurm"), msg)
                })?
            }
            other => {
                return Err(cx.err(
                    cx.locs.key(&format!("executor.{other}")),
                    None,
                    Some(other),
                    "unknown key (expected: slurm)",
                ))
            }
        }
    }
    Ok(slurm)
}

fn valid_name(n: &str) -> bool {
    !n.is_empty()
        && n.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

/// Validates stage `name` written at key path `base` (`stages.train`), applying a scene's
/// settings and then the command line's overrides to its params.
fn stage_decl(
    cx: &Ctx,
    name: &str,
    base: &str,
    v: &Yaml,
    sets: &[&SceneSet],
    overrides: &[&Override],
) -> Result<StageDecl, ConfigError> {
    let base = base.to_string();
    let loc = cx.locs.key(&base);
    let m = match v {
        Yaml::Mapping(m) => m,
        other => {
            return Err(cx.err(
                cx.locs.value(&base),
                Some(name),
                None,
                format!(
                    "expected a mapping with `uses:`, found {}",
                    yaml_type(other)
                ),
            ))
        }
    };
    for k in m.keys() {
        let key = k.as_str().unwrap_or("?");
        if !STAGE_KEYS.contains(&key) {
            return Err(cx.err(
                cx.locs.key(&format!("{base}.{key}")),
                Some(name),
                Some(key),
                format!("unknown key (expected one of: {})", STAGE_KEYS.join(", ")),
            ));
        }
    }
    let kind_name = match m.get("uses") {
        Some(Yaml::String(s)) => s.clone(),
        Some(other) => {
            return Err(cx.err(
                cx.locs.value(&format!("{base}.uses")),
                Some(name),
                Some("uses"),
                format!("expected a stage kind name, found {}", yaml_type(other)),
            ))
        }
        None => {
            return Err(cx.err(
                loc,
                Some(name),
                Some("uses"),
                "missing: which stage kind does this stage use?",
            ))
        }
    };
    let kind = stages::find(&kind_name).ok_or_else(|| {
        let known: Vec<_> = stages::registry()
            .iter()
            .map(|k| k.kind())
            .filter(|k| !k.starts_with("test_"))
            .collect();
        cx.err(
            cx.locs.value(&format!("{base}.uses")),
            Some(name),
            Some("uses"),
            format!(
                "unknown stage kind `{kind_name}` (known: {})",
                known.join(", ")
            ),
        )
    })?;

    // Inputs.
    let mut inputs = BTreeMap::new();
    match m.get("inputs") {
        None | Some(Yaml::Null) => {}
        Some(Yaml::Mapping(im)) => {
            for (k, v) in im {
                let slot = k.as_str().unwrap_or("?").to_string();
                let kpath = format!("{base}.inputs.{slot}");
                if !kind.inputs().iter().any(|s| s.name == slot) {
                    let slots: Vec<_> = kind.inputs().iter().map(|s| s.name).collect();
                    return Err(cx.err(
                        cx.locs.key(&kpath),
                        Some(name),
                        Some(&format!("inputs.{slot}")),
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
                    cx.err(
                        cx.locs.value(&kpath),
                        Some(name),
                        Some(&format!("inputs.{slot}")),
                        format!("expected the name of a stage, found {}", yaml_type(v)),
                    )
                })?;
                inputs.insert(slot, up.to_string());
            }
        }
        Some(other) => {
            return Err(cx.err(
                cx.locs.value(&format!("{base}.inputs")),
                Some(name),
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
            return Err(cx.err(
                cx.locs.key(&base),
                Some(name),
                Some(&format!("inputs.{}", slot.name)),
                format!(
                    "missing input: kind `{kind_name}` needs slot `{}` ({})",
                    slot.name, slot.doc
                ),
            ));
        }
    }

    // Params: shallow type check against the defaults, then the kind's own validation.
    let defaults = kind.default_params();
    let Value::Object(mut merged) = defaults.clone() else {
        unreachable!("stage params are a struct");
    };
    let mut given: Vec<(String, Yaml, Loc)> = Vec::new();
    match m.get("params") {
        None | Some(Yaml::Null) => {}
        Some(Yaml::Mapping(pm)) => {
            for (k, v) in pm {
                let key = k.as_str().unwrap_or("?").to_string();
                let l = cx.locs.key(&format!("{base}.params.{key}"));
                given.push((key, v.clone(), l));
            }
        }
        Some(other) => {
            return Err(cx.err(
                cx.locs.value(&format!("{base}.params")),
                Some(name),
                Some("params"),
                format!(
                    "expected a mapping of param -> value, found {}",
                    yaml_type(other)
                ),
            ))
        }
    }
    // Scene settings, then `--set` overrides (`--set train.train.lr=0.01` sets one field inside
    // the `train` param and keeps the rest): `[param, field...]`, the value, where it was given.
    let settings = sets
        .iter()
        .map(|s| {
            let path: Vec<&str> = s.path.iter().map(String::as_str).collect();
            (path, &s.value, s.loc.clone())
        })
        .chain(overrides.iter().map(|o| {
            let path: Vec<&str> = o.param.split('.').collect();
            (path, &o.value, Loc::CommandLine(o.arg.clone()))
        }));
    for (path, value, loc) in settings {
        let key = path[0].to_string();
        let value = if path.len() == 1 {
            value.clone()
        } else {
            let mut v = given
                .iter()
                .find(|(k, ..)| *k == key)
                .map_or(Yaml::Null, |(_, v, _)| v.clone());
            crate::bench::plan::set_path(&mut v, &path[1..], value);
            v
        };
        given.retain(|(k, ..)| *k != key);
        given.push((key, value, loc));
    }
    for (key, v, l) in &given {
        let Some(default) = defaults.get(key) else {
            let known: Vec<_> = defaults
                .as_object()
                .map(|o| o.keys().cloned().collect())
                .unwrap_or_default();
            return Err(cx.err(
                l.clone(),
                Some(name),
                Some(&format!("params.{key}")),
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
        let user: Value = serde_json::to_value(v).map_err(|e| {
            cx.err(
                l.clone(),
                Some(name),
                Some(&format!("params.{key}")),
                format!("unsupported value: {e}"),
            )
        })?;
        if !type_fits(default, &user) {
            return Err(cx.err(
                l.clone(),
                Some(name),
                Some(&format!("params.{key}")),
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
    let params = kind.canonical_params(&Value::Object(merged)).map_err(|e| {
        let msg = match e {
            stages::StageError::Params(m) => m,
            other => other.to_string(),
        };
        // Point at the param the message names (`name`), if the user gave it.
        let named = msg.split('`').nth(1).map(str::to_string);
        let (l, key) = match named.and_then(|n| given.iter().find(|(k, ..)| *k == n)) {
            Some((k, _, l)) => (l.clone(), Some(format!("params.{k}"))),
            None => (cx.locs.key(&format!("{base}.params")), None),
        };
        cx.err(l, Some(name), key.as_deref(), msg)
    })?;

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

/// Inputs name existing stages (of `stages` itself or of `more`) whose kind writes the tables
/// the slot reads; `section` is where `stages` are written (`stages`, `dataset`).
fn check_inputs(
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
        let sets = ["train.train.lr=0.01", "train.sampling.samples=16"];
        let o: Vec<Override> = sets.iter().map(|s| Override::parse(s).unwrap()).collect();
        let plain = parse(Path::new("pipeline.yaml"), &text, &[]).unwrap();
        let plain = &plain.stages[plain.index_of("train").unwrap()].params;
        let p = parse(Path::new("pipeline.yaml"), &text, &o).unwrap();
        let train = &p.stages[p.index_of("train").unwrap()].params;
        assert_eq!(train["train"]["lr"], 0.01);
        assert_ne!(plain["train"]["lr"], 0.01);
        assert_eq!(
            train["train"]["iterations"], plain["train"]["iterations"],
            "sibling kept: {train}"
        );
        assert_eq!(train["sampling"]["samples"], 16);
        let bad = Override::parse("train.train.no_such_field=1").unwrap();
        let e = parse(Path::new("pipeline.yaml"), &text, &[bad])
            .err()
            .unwrap();
        assert!(e.to_string().contains("no_such_field"), "{e}");
    }
}
