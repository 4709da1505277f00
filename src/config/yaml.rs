//! The raw YAML side of configuration files: where every key and value stands (line and
//! column, from yaml-rust2's event stream, since serde_yaml keeps no positions), the errors
//! that point there, and how values are named in messages.

use std::{collections::HashMap, path::Path};

use serde_json::Value;
use serde_yaml::Value as Yaml;
use yaml_rust2::{parser::MarkedEventReceiver, parser::Parser, scanner::Marker, Event};

use super::error::{ConfigError, Loc};

/// Key paths (`stages.train.params.lr`) -> where the key stands in the file.
#[derive(Default)]
pub(crate) struct Locations {
    map: HashMap<String, Loc>,
    /// Byte offset where each `\n`-separated line starts.
    line_starts: Vec<usize>,
}

struct Recv {
    stack: Vec<Frame>,
    out: HashMap<String, Loc>,
}

enum Frame {
    Map { path: String, key: Option<String> },
    Seq { path: String, index: usize },
}

fn join(a: &str, b: &str) -> String {
    if a.is_empty() {
        b.to_string()
    } else {
        format!("{a}.{b}")
    }
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

impl Locations {
    pub(crate) fn scan(text: &str) -> Locations {
        let mut recv = Recv {
            stack: Vec::new(),
            out: HashMap::new(),
        };
        // Syntax errors are reported by serde_yaml; a failed scan only loses locations.
        let _ = Parser::new_from_str(text).load(&mut recv, false);
        let line_starts = std::iter::once(0)
            .chain(text.match_indices('\n').map(|(i, _)| i + 1))
            .collect();
        Locations {
            map: recv.out,
            line_starts,
        }
    }

    /// Line and column (1-based, columns in characters) of byte `index` of `text`.
    ///
    /// libyaml also breaks lines at U+0085, U+2028 and U+2029, which editors do not, so its
    /// own line numbers can point past the file.
    fn at_byte(&self, text: &str, index: usize) -> Loc {
        let mut index = index.min(text.len());
        while !text.is_char_boundary(index) {
            index -= 1;
        }
        let line = self.line_starts.partition_point(|&s| s <= index).max(1);
        let start = self.line_starts.get(line - 1).copied().unwrap_or(0);
        Loc::File {
            line,
            col: text[start..index].chars().count() + 1,
        }
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

    /// Where a serde_yaml error stands, and its message without serde_yaml's own " at line X
    /// column Y" (the location goes in front). A repeated key is pointed at itself rather than
    /// at its mapping.
    pub(crate) fn serde_error(&self, text: &str, e: &serde_yaml::Error) -> (Loc, String) {
        let loc = e
            .location()
            .map_or(Loc::Unknown, |l| self.at_byte(text, l.index()));
        let msg = e.to_string();
        let msg = msg.split(" at line ").next().unwrap_or(&msg).to_string();
        let loc = match msg.split_once(": duplicate entry with key \"") {
            Some((path, rest)) => {
                let key = rest.trim_end_matches('"');
                match self.key(&format!("{path}.{key}")) {
                    Loc::Unknown => loc,
                    l => l,
                }
            }
            None => loc,
        };
        (loc, msg)
    }
}

/// A file being validated: its name for messages and where its keys stand.
pub(crate) struct Ctx<'a> {
    pub file: &'a Path,
    pub locs: Locations,
}

impl Ctx<'_> {
    pub fn err(
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

pub(crate) fn yaml_type(v: &Yaml) -> &'static str {
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

pub(crate) fn json_type(v: &Value) -> &'static str {
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

pub(crate) fn describe(v: &Value) -> String {
    shorten(&show_json(v), 40)
}

/// `v` as compact JSON, except that a float that is exactly an f32 (the kinds' f32 params,
/// stored as f64) is written in the shortest form that parses back to that f32: `0.9`, not
/// `0.8999999761581421`.
pub fn show_json(v: &Value) -> String {
    let mut out = String::new();
    write_json(v, &mut out);
    out
}

fn write_json(v: &Value, out: &mut String) {
    match v {
        Value::Number(n) => out.push_str(&stages::params_doc::show_number(n)),
        Value::Array(items) => {
            out.push('[');
            for (i, item) in items.iter().enumerate() {
                if i > 0 {
                    out.push(',');
                }
                write_json(item, out);
            }
            out.push(']');
        }
        Value::Object(m) => {
            out.push('{');
            for (i, (k, item)) in m.iter().enumerate() {
                if i > 0 {
                    out.push(',');
                }
                out.push_str(&Value::String(k.clone()).to_string());
                out.push(':');
                write_json(item, out);
            }
            out.push('}');
        }
        other => out.push_str(&other.to_string()),
    }
}

/// `s` cut to at most `max` characters plus `...` (on a character boundary: values may hold
/// any UTF-8).
pub fn shorten(s: &str, max: usize) -> String {
    match s.char_indices().nth(max) {
        Some((end, _)) => format!("{}...", &s[..end]),
        None => s.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn f32_values_show_in_their_shortest_form() {
        let v = serde_json::json!({
            "momentum": f64::from(0.9f32),
            "lr": f64::from(5e-3f32),
            "tiny": f64::from(1e-10f32),
            "exact": 0.1f64,
            "n": [1, f64::from(0.3f32), "x"],
        });
        let shown = show_json(&v);
        assert_eq!(
            shown,
            r#"{"exact":0.1,"lr":0.005,"momentum":0.9,"n":[1,0.3,"x"],"tiny":1e-10}"#
        );
        // Every shown f32 parses back to the same f32.
        for (text, f) in [("0.9", 0.9f32), ("0.005", 5e-3), ("1e-10", 1e-10)] {
            assert_eq!(text.parse::<f32>().unwrap(), f);
        }
        // A true f64 that is not an f32 keeps its full form.
        assert_eq!(show_json(&serde_json::json!(0.3f64)), "0.3");
        assert_ne!(f64::from(0.3f32), 0.3f64);
    }

    /// Where serde_yaml fails, in the lines an editor shows (libyaml alone also breaks at
    /// U+2028), columns counted in characters.
    #[test]
    fn syntax_errors_are_located_in_newline_lines() {
        let locate = |text: &str| {
            let e = serde_yaml::from_str::<serde_yaml::Value>(text).unwrap_err();
            Locations::scan(text).serde_error(text, &e).0
        };
        // The fuzz case that libyaml placed on line 3 of a one-line text.
        assert!(matches!(locate("®:\u{2028}🌀"), Loc::File { line: 1, .. }));
        // An unclosed flow sequence fails at the end of the text: line 3, after 'é: x'.
        let text = "a: 1\nb: [1, 2\né: x";
        let Loc::File { line, col } = locate(text) else {
            panic!("no location")
        };
        assert_eq!(line, 3);
        assert!((1..=5).contains(&col), "column {col}");
        // A byte index past the text or inside a character is clamped, not a panic.
        let locs = Locations::scan("é\n");
        assert!(matches!(
            locs.at_byte("é\n", 1),
            Loc::File { line: 1, col: 1 }
        ));
        assert!(matches!(
            locs.at_byte("é\n", 99),
            Loc::File { line: 2, col: 1 }
        ));
    }
}
