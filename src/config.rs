//! `pipeline.yaml` -> a validated [`Pipeline`]: stage instances with their kind, canonical
//! parameters (defaults filled in) and named inputs. Every error names the file, the line and
//! column, the stage and the key; nothing runs when the file is invalid.
//!
//! ```yaml
//! cache: .pipe              # optional, relative to this file
//! stages:
//!   scene:
//!     uses: synthetic_scene # a kind from the registry (`pipe kinds`)
//!     params: {frames: 16}
//!   rays:
//!     uses: intersect
//!     inputs: {scene: scene}  # input slot -> stage instance
//! ```

use std::{
    collections::{BTreeMap, HashMap},
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
    /// Stage instances in file order.
    pub stages: Vec<StageDecl>,
}

impl Pipeline {
    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.stages.iter().position(|s| s.name == name)
    }
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

const TOP_KEYS: &[&str] = &["cache", "stages"];
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

    for o in overrides {
        if !stages_map.keys().any(|k| k.as_str() == Some(&o.stage)) {
            return Err(ConfigError {
                file: file.to_path_buf(),
                loc: Loc::CommandLine(o.arg.clone()),
                stage: Some(o.stage.clone()),
                key: None,
                message: "no such stage".into(),
            });
        }
    }

    let mut stages = Vec::new();
    for (k, v) in stages_map {
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
        let mine: Vec<&Override> = overrides.iter().filter(|o| o.stage == name).collect();
        stages.push(stage_decl(&cx, &name, v, &mine)?);
    }

    check_inputs(&cx, &stages)?;

    let cache_dir = match cache {
        Some(c) => file.parent().unwrap_or(Path::new(".")).join(c),
        None => file.parent().unwrap_or(Path::new(".")).join(".pipe"),
    };
    Ok(Pipeline {
        file: file.to_path_buf(),
        cache_dir,
        stages,
    })
}

fn valid_name(n: &str) -> bool {
    !n.is_empty()
        && n.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

fn stage_decl(
    cx: &Ctx,
    name: &str,
    v: &Yaml,
    overrides: &[&Override],
) -> Result<StageDecl, ConfigError> {
    let base = format!("stages.{name}");
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
    for o in overrides {
        given.retain(|(k, ..)| k != &o.param);
        given.push((
            o.param.clone(),
            o.value.clone(),
            Loc::CommandLine(o.arg.clone()),
        ));
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
        name: name.to_string(),
        kind,
        params,
        inputs,
        loc,
    })
}

/// Inputs name existing stages whose kind writes the tables the slot reads.
fn check_inputs(cx: &Ctx, stages: &[StageDecl]) -> Result<(), ConfigError> {
    for s in stages {
        for (slot, up) in &s.inputs {
            let kpath = format!("stages.{}.inputs.{slot}", s.name);
            let Some(u) = stages.iter().find(|x| &x.name == up) else {
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
}
