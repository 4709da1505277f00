//! What `pipe kinds KIND` prints: every parameter of a kind with its dotted path, type, default
//! and doc, in the order its params struct declares them, and a commented YAML block of them.
//! Types and docs come from the params structs' own doc comments (schemars), defaults from their
//! `Default`: one home for each. Also the table of parameters that moved ([`moved`]).

use schemars::JsonSchema;
use serde::Serialize;
use serde_json::{Map, Value};

/// One parameter, or a group of them (a struct inside the params).
#[derive(Debug, Clone, PartialEq)]
pub struct ParamDoc {
    /// Dotted path inside the stage's `params:` (`schedule.iterations`).
    pub path: String,
    /// How deep it is: 0 at the top of `params:`.
    pub depth: usize,
    /// The type as a user writes it: `integer`, `number`, `boolean`, `string`, `grid | pe`,
    /// `list of string`, `[number, number] or null`; `group` for a struct of parameters.
    pub ty: String,
    /// The default (for a group: its members' defaults).
    pub default: Value,
    /// The doc comment, lines joined by spaces.
    pub doc: String,
    /// Whether it is a group of parameters (its members follow it).
    pub group: bool,
}

impl ParamDoc {
    /// The key alone (the last part of the path).
    pub fn key(&self) -> &str {
        self.path.rsplit('.').next().unwrap_or(&self.path)
    }

    /// The doc's first sentence.
    pub fn summary(&self) -> &str {
        first_sentence(&self.doc)
    }
}

/// The first sentence of `doc`: up to a full stop followed by a space and an upper-case letter,
/// a digit, a quote or an opening bracket (so `e.g. parking` does not end it), or the whole
/// first paragraph.
pub fn first_sentence(doc: &str) -> &str {
    let para = doc.split("\n\n").next().unwrap_or("").trim();
    let bytes = para.as_bytes();
    for (i, w) in bytes.windows(3).enumerate() {
        let starts = w[2].is_ascii_uppercase() || w[2].is_ascii_digit() || b"`(\"".contains(&w[2]);
        let ellipsis = i > 0 && bytes[i - 1] == b'.';
        if w[0] == b'.' && w[1] == b' ' && starts && !ellipsis {
            return &para[..=i];
        }
    }
    para
}

/// Every parameter of `P` (its default taken from `P::default()`), groups before their members.
pub fn docs<P: JsonSchema + Serialize + Default>() -> Vec<ParamDoc> {
    let schema = serde_json::to_value(schemars::schema_for!(P)).expect("a schema is JSON");
    let defaults = serde_json::to_value(P::default()).expect("params serialise to JSON");
    // Declaration order: serde_json's maps are sorted, serde_yaml's keep the struct's order.
    let ordered = serde_yaml::to_value(P::default()).expect("params serialise to YAML");
    let defs = schema
        .get("$defs")
        .and_then(Value::as_object)
        .cloned()
        .unwrap_or_default();
    let mut out = Vec::new();
    walk(&defs, &schema, &defaults, &ordered, "", 0, &mut out);
    out
}

fn walk(
    defs: &Map<String, Value>,
    schema: &Value,
    defaults: &Value,
    ordered: &serde_yaml::Value,
    prefix: &str,
    depth: usize,
    out: &mut Vec<ParamDoc>,
) {
    let props = resolve(defs, schema)
        .get("properties")
        .and_then(Value::as_object)
        .cloned()
        .unwrap_or_default();
    let Some(keys) = ordered.as_mapping() else {
        return;
    };
    for key in keys.keys().filter_map(serde_yaml::Value::as_str) {
        let prop = props.get(key).cloned().unwrap_or(Value::Null);
        let default = defaults.get(key).cloned().unwrap_or(Value::Null);
        let path = format!("{prefix}{key}");
        let inner = non_null(defs, &prop);
        let group = inner.get("properties").is_some() && default.is_object();
        out.push(ParamDoc {
            path: path.clone(),
            depth,
            ty: if inner.get("properties").is_some() {
                if nullable(defs, &prop) {
                    "group or null".into()
                } else {
                    "group".into()
                }
            } else {
                type_name(defs, &prop)
            },
            default: default.clone(),
            doc: description(defs, &prop),
            group,
        });
        if group {
            let sub = &ordered[key];
            walk(
                defs,
                &inner,
                &default,
                sub,
                &format!("{path}."),
                depth + 1,
                out,
            );
        }
    }
}

/// `schema` with a `$ref` followed.
fn resolve<'a>(defs: &'a Map<String, Value>, schema: &'a Value) -> &'a Value {
    match schema.get("$ref").and_then(Value::as_str) {
        Some(r) => defs
            .get(r.trim_start_matches("#/$defs/"))
            .map_or(schema, |d| resolve(defs, d)),
        None => schema,
    }
}

/// The alternatives of `anyOf` / `oneOf`, or `schema` alone.
fn alternatives(schema: &Value) -> Vec<&Value> {
    for k in ["anyOf", "oneOf"] {
        if let Some(a) = schema.get(k).and_then(Value::as_array) {
            return a.iter().collect();
        }
    }
    vec![schema]
}

fn is_null(schema: &Value) -> bool {
    schema.get("type").and_then(Value::as_str) == Some("null")
}

fn nullable(defs: &Map<String, Value>, schema: &Value) -> bool {
    let s = resolve(defs, schema);
    alternatives(s).iter().any(|a| is_null(a))
        || s.get("type")
            .and_then(Value::as_array)
            .is_some_and(|t| t.iter().any(|x| x == "null"))
}

/// The schema of the value when it is not null (`Option<T>` -> `T`), `$ref`s followed.
fn non_null(defs: &Map<String, Value>, schema: &Value) -> Value {
    let s = resolve(defs, schema);
    let alts: Vec<&Value> = alternatives(s)
        .into_iter()
        .filter(|a| !is_null(a))
        .collect();
    match alts.as_slice() {
        [one] if s.get("anyOf").is_some() => resolve(defs, one).clone(),
        _ => s.clone(),
    }
}

/// The doc of a property: its own, else its type's.
fn description(defs: &Map<String, Value>, schema: &Value) -> String {
    let own = schema.get("description").and_then(Value::as_str);
    let text = own
        .or_else(|| {
            resolve(defs, schema)
                .get("description")
                .and_then(Value::as_str)
        })
        .unwrap_or("");
    // Rustdoc links read as plain code: "[`Foo::Bar`]" -> "`Foo::Bar`".
    text.replace("[`", "`")
        .replace("`]", "`")
        .split("\n\n")
        .map(|p| p.split_whitespace().collect::<Vec<_>>().join(" "))
        .collect::<Vec<_>>()
        .join("\n\n")
}

fn type_name(defs: &Map<String, Value>, schema: &Value) -> String {
    let s = resolve(defs, schema);
    // A type that names itself (`# camera` heading its doc comment).
    if let Some(title) = s.get("title").and_then(Value::as_str) {
        return title.to_string();
    }
    if let Some(values) = s.get("enum").and_then(Value::as_array) {
        return values.iter().map(show).collect::<Vec<_>>().join(" | ");
    }
    if let Some(c) = s.get("const") {
        return show(c);
    }
    let alts = alternatives(s);
    if alts.len() > 1 {
        // Unit variants with docs come as `oneOf` of consts: show them as one enum.
        let mut names: Vec<String> = alts.iter().map(|a| type_name(defs, a)).collect();
        names.dedup();
        let all_consts = alts.iter().all(|a| {
            let a = resolve(defs, a);
            a.get("const").is_some() || a.get("enum").is_some()
        });
        return names.join(if all_consts { " | " } else { " or " });
    }
    match s.get("type") {
        Some(Value::Array(types)) => types
            .iter()
            .map(|t| {
                let mut one = s.clone();
                one["type"] = t.clone();
                type_name(defs, &one)
            })
            .collect::<Vec<_>>()
            .join(" or "),
        Some(Value::String(t)) => match t.as_str() {
            "array" => {
                if let Some(items) = s.get("prefixItems").and_then(Value::as_array) {
                    let parts: Vec<String> = items.iter().map(|i| type_name(defs, i)).collect();
                    format!("[{}]", parts.join(", "))
                } else {
                    let items = s.get("items").cloned().unwrap_or(Value::Null);
                    let n = s.get("maxItems").filter(|m| Some(*m) == s.get("minItems"));
                    match n.and_then(Value::as_u64) {
                        Some(n) => {
                            let item = type_name(defs, &items);
                            format!("[{}]", vec![item; n as usize].join(", "))
                        }
                        None => format!("list of {}", type_name(defs, &items)),
                    }
                }
            }
            "object" => "mapping".into(),
            other => other.into(),
        },
        _ => "any".into(),
    }
}

/// A JSON value as YAML flow text (`1700`, `[0, 1]`, `{a: 1}`, `null`, `''`).
pub fn show(v: &Value) -> String {
    match v {
        Value::Null => "null".into(),
        Value::String(s) => {
            let y = serde_yaml::to_string(s).unwrap_or_default();
            y.trim_end().to_string()
        }
        Value::Array(a) => format!("[{}]", a.iter().map(show).collect::<Vec<_>>().join(", ")),
        Value::Object(o) => format!(
            "{{{}}}",
            o.iter()
                .map(|(k, v)| format!("{k}: {}", show(v)))
                .collect::<Vec<_>>()
                .join(", ")
        ),
        Value::Number(n) => show_number(n),
        other => other.to_string(),
    }
}

/// A number as written: an f32 parameter reaches JSON as its f64 value (0.1 ->
/// 0.10000000149011612), so a float that is exactly an f32 shows as that f32 (`0.1`).
pub fn show_number(n: &serde_json::Number) -> String {
    match n.as_f64().filter(|_| n.is_f64()) {
        Some(x) if (x as f32).is_finite() && f64::from(x as f32) == x => format!("{:?}", x as f32),
        _ => n.to_string(),
    }
}

/// `docs` as a commented YAML mapping for a pipeline file's `params:`: every parameter at its
/// default with its doc above it, indented by `indent` spaces and wrapped at `width` columns.
pub fn yaml_params(docs: &[ParamDoc], indent: usize, width: usize) -> String {
    let mut out = String::new();
    for d in docs {
        let pad = " ".repeat(indent + 2 * d.depth);
        for line in wrap(&d.doc, width.saturating_sub(pad.len() + 2).max(40)) {
            out.push_str(format!("{pad}# {line}").trim_end());
            out.push('\n');
        }
        if d.group {
            out.push_str(&format!("{pad}{}:\n", d.key()));
        } else {
            out.push_str(&format!("{pad}{}: {}\n", d.key(), show(&d.default)));
        }
    }
    out
}

/// `text` broken into lines of at most `width` characters (a longer word stands alone).
fn wrap(text: &str, width: usize) -> Vec<String> {
    let mut lines = Vec::new();
    for para in text.split("\n\n") {
        if !lines.is_empty() {
            lines.push(String::new());
        }
        let mut line = String::new();
        for word in para.split_whitespace() {
            if !line.is_empty() && line.len() + 1 + word.len() > width {
                lines.push(std::mem::take(&mut line));
            }
            if !line.is_empty() {
                line.push(' ');
            }
            line.push_str(word);
        }
        if !line.is_empty() {
            lines.push(line);
        }
    }
    lines
}

/// Where `path` moved according to `table` (`(old path, new path [(note)])` or `(old path,
/// (note))`): the longest old path that is `path` or above it; a new path gets the rest of
/// `path` appended, before its note.
pub fn moved(table: &[(&str, &str)], path: &str) -> Option<String> {
    table
        .iter()
        .filter(|(old, _)| {
            path == *old || (path.starts_with(old) && path.as_bytes().get(old.len()) == Some(&b'.'))
        })
        .max_by_key(|(old, _)| old.len())
        .map(|(old, new)| {
            let rest = &path[old.len()..];
            if new.starts_with('(') {
                return new.to_string();
            }
            match new.split_once(' ') {
                Some((to, note)) => format!("{to}{rest} {note}"),
                None => format!("{new}{rest}"),
            }
        })
}

/// The error for an old parameter path of stage `stage` (kind `kind`) that `moved_to` (what
/// [`moved`] gives: a new path with an optional note, or a note alone) replaced.
pub fn moved_message(stage: &str, kind: &str, path: &str, moved_to: &str) -> String {
    let to = if moved_to.starts_with('(') {
        format!(" {moved_to}")
    } else {
        match moved_to.split_once(' ') {
            Some((to, note)) => format!(" to `{stage}.{to}` {note}"),
            None => format!(" to `{stage}.{moved_to}`"),
        }
    };
    format!("`{stage}.{path}` moved{to}; `pipe kinds {kind}` lists every parameter")
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    /// A group of settings.
    #[derive(Debug, Serialize, Deserialize, JsonSchema, PartialEq)]
    #[serde(default, deny_unknown_fields)]
    struct Inner {
        /// How many, e.g. three. Not more.
        count: u32,
        /// A pair.
        pair: Option<[f32; 2]>,
    }

    impl Default for Inner {
        fn default() -> Self {
            Self {
                count: 3,
                pair: None,
            }
        }
    }

    /// A mode.
    #[derive(Debug, Default, Serialize, Deserialize, JsonSchema, PartialEq)]
    #[serde(rename_all = "lowercase")]
    enum Mode {
        /// The first.
        #[default]
        Fast,
        /// The second.
        Slow,
    }

    #[derive(Debug, Default, Serialize, Deserialize, JsonSchema, PartialEq)]
    #[serde(default, deny_unknown_fields)]
    struct Params {
        /// Zeta comes first.
        zeta: bool,
        /// The mode.
        mode: Mode,
        /// Names.
        names: Vec<String>,
        /// The inner group.
        inner: Inner,
        /// Maybe a group.
        maybe: Option<Inner>,
        undocumented: f64,
    }

    #[test]
    fn parameters_come_in_declaration_order_with_types_defaults_and_docs() {
        let d = docs::<Params>();
        let rows: Vec<(&str, &str, String, &str)> = d
            .iter()
            .map(|p| {
                (
                    p.path.as_str(),
                    p.ty.as_str(),
                    show(&p.default),
                    p.summary(),
                )
            })
            .collect();
        assert_eq!(
            rows,
            [
                ("zeta", "boolean", "false".into(), "Zeta comes first."),
                ("mode", "fast | slow", "fast".into(), "The mode."),
                ("names", "list of string", "[]".into(), "Names."),
                (
                    "inner",
                    "group",
                    "{count: 3, pair: null}".into(),
                    "The inner group."
                ),
                (
                    "inner.count",
                    "integer",
                    "3".into(),
                    "How many, e.g. three."
                ),
                (
                    "inner.pair",
                    "[number, number] or null",
                    "null".into(),
                    "A pair."
                ),
                ("maybe", "group or null", "null".into(), "Maybe a group."),
                ("undocumented", "number", "0.0".into(), ""),
            ]
        );
        assert!(
            d[3].group && !d[4].group && !d[6].group,
            "a null group has no members"
        );
        assert_eq!(d[4].depth, 1);
    }

    #[test]
    fn the_yaml_block_parses_back_to_the_defaults() {
        let d = docs::<Params>();
        let text = format!("params:\n{}", yaml_params(&d, 2, 40));
        let v: serde_yaml::Value = serde_yaml::from_str(&text).unwrap();
        let params: Params = serde_yaml::from_value(v["params"].clone()).unwrap();
        assert_eq!(params, Params::default());
        assert!(
            text.contains("    # How many, e.g. three. Not more.\n    count: 3\n"),
            "{text}"
        );
        assert!(
            text.lines().all(|l| l.len() <= 40 || !l.contains('#')),
            "{text}"
        );
    }

    #[test]
    fn moved_keys_map_to_the_new_path_or_a_hint() {
        let table = [
            ("train", "(into groups)"),
            ("train.lr", "optimiser.lr"),
            ("train.field", "field (a note)"),
        ];
        assert_eq!(moved(&table, "train.lr").as_deref(), Some("optimiser.lr"));
        assert_eq!(
            moved(&table, "train.field.grid.levels").as_deref(),
            Some("field.grid.levels (a note)")
        );
        assert_eq!(
            moved(&table, "train.nope").as_deref(),
            Some("(into groups)")
        );
        assert_eq!(moved(&table, "training").as_deref(), None);
        assert_eq!(moved(&table, "train.lrx").as_deref(), Some("(into groups)"));
        assert_eq!(moved(&table, "field.grid").as_deref(), None);
        assert_eq!(
            moved_message("t", "train", "train.lr", "optimiser.lr"),
            "`t.train.lr` moved to `t.optimiser.lr`; `pipe kinds train` lists every parameter"
        );
        assert_eq!(
            moved_message("t", "train", "train.x", "(into groups)"),
            "`t.train.x` moved (into groups); `pipe kinds train` lists every parameter"
        );
        assert_eq!(
            moved_message("r", "render", "adaptive", "coarse_stride (1: every pixel)"),
            "`r.adaptive` moved to `r.coarse_stride` (1: every pixel); `pipe kinds render` lists \
             every parameter"
        );
    }

    #[test]
    fn first_sentences_skip_abbreviations() {
        assert_eq!(first_sentence("One. Two."), "One.");
        assert_eq!(
            first_sentence("Classes (e.g. parking, wall). More."),
            "Classes (e.g. parking, wall)."
        );
        assert_eq!(first_sentence("No stop"), "No stop");
        assert_eq!(first_sentence("From `a` .. `b`. Then."), "From `a` .. `b`.");
        assert_eq!(first_sentence("Para one\n\nPara two. Three."), "Para one");
    }
}
