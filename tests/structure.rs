//! The shape of the code, measured and held: no import circles between the files (nor between
//! the top-level modules) of either crate, no library module of `stages` importing a stage kind
//! (`stages::kinds`), and no file over 800 lines or function over 150 lines outside tests,
//! except the ones listed below with their reason.
//!
//! A small reader of Rust imports, not a compiler: comments, strings and `#[cfg(test)]` items
//! are blanked, `use` trees and `crate::`/`super::`/`self::` paths (and paths through names a
//! `use` bound or a child module) are resolved to the file that defines them, following `pub use`
//! re-exports, so importing through a facade counts as importing what it re-exports.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

const MAX_FILE_LINES: usize = 800;
const MAX_FN_LINES: usize = 150;

/// Functions allowed over the limit, with the reason.
const LONG_FUNCTIONS: &[(&str, &str, &str)] = &[];

type Module = Vec<String>;

struct Crate {
    files: BTreeMap<Module, PathBuf>,
    /// Source with comments, strings and test code blanked (line breaks kept).
    code: BTreeMap<Module, String>,
    /// Raw source lines, for the size limits.
    lines: BTreeMap<Module, usize>,
    edges: BTreeMap<Module, BTreeSet<Module>>,
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// Blanks comments, string and char literals (keeping line breaks and the quotes).
fn strip(src: &str) -> String {
    let b = src.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let blank = |out: &mut Vec<u8>, s: &[u8]| {
        out.extend(s.iter().map(|&c| if c == b'\n' { b'\n' } else { b' ' }))
    };
    let mut i = 0;
    while i < b.len() {
        let rest = &b[i..];
        if rest.starts_with(b"//") {
            let end = rest.iter().position(|&c| c == b'\n').unwrap_or(rest.len());
            blank(&mut out, &rest[..end]);
            i += end;
        } else if rest.starts_with(b"/*") {
            let (mut depth, mut j) = (1, 2);
            while j < rest.len() && depth > 0 {
                if rest[j..].starts_with(b"/*") {
                    depth += 1;
                    j += 2;
                } else if rest[j..].starts_with(b"*/") {
                    depth -= 1;
                    j += 2;
                } else {
                    j += 1;
                }
            }
            blank(&mut out, &rest[..j]);
            i += j;
        } else if rest[0] == b'r'
            && (i == 0 || !(b[i - 1].is_ascii_alphanumeric() || b[i - 1] == b'_'))
            && rest.len() > 1
            && (rest[1] == b'"' || rest[1] == b'#')
        {
            let hashes = rest[1..].iter().take_while(|&&c| c == b'#').count();
            if rest.get(1 + hashes) != Some(&b'"') {
                out.push(rest[0]);
                i += 1;
                continue;
            }
            let mut close = vec![b'"'];
            close.extend(std::iter::repeat_n(b'#', hashes));
            let start = 2 + hashes;
            let end = rest[start..]
                .windows(close.len())
                .position(|w| w == close.as_slice())
                .map_or(rest.len(), |p| start + p + close.len());
            blank(&mut out, &rest[..end]);
            i += end;
        } else if rest[0] == b'"' {
            let mut j = 1;
            while j < rest.len() && rest[j] != b'"' {
                j += if rest[j] == b'\\' { 2 } else { 1 };
            }
            out.push(b'"');
            blank(&mut out, &rest[1..j.min(rest.len())]);
            out.push(b'"');
            i += j + 1;
        } else if rest[0] == b'\'' {
            // A char literal ('x', '\n', '\u{..}'), not a lifetime.
            let len = if rest.get(1) == Some(&b'\\') {
                rest.iter().skip(2).position(|&c| c == b'\'').map(|p| p + 3)
            } else if rest.get(2) == Some(&b'\'') {
                Some(3)
            } else {
                None
            };
            match len {
                Some(n) if n <= 12 => {
                    blank(&mut out, &rest[..n]);
                    i += n;
                }
                _ => {
                    out.push(b'\'');
                    i += 1;
                }
            }
        } else {
            out.push(rest[0]);
            i += 1;
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// Index of the brace closing the one at `open`.
fn matching_brace(s: &[u8], open: usize) -> usize {
    let mut depth = 0;
    for (j, &c) in s.iter().enumerate().skip(open) {
        match c {
            b'{' => depth += 1,
            b'}' => {
                depth -= 1;
                if depth == 0 {
                    return j;
                }
            }
            _ => {}
        }
    }
    s.len() - 1
}

/// Child modules declared under `#[cfg(test)]` (`#[cfg(test)] mod name;`): test code.
fn test_modules(code: &str) -> Vec<String> {
    let mut out = Vec::new();
    for (i, _) in code.match_indices("#[cfg(test)]") {
        let rest = code[i + 12..].trim_start();
        let rest = rest
            .strip_prefix("pub(crate) ")
            .or_else(|| rest.strip_prefix("pub "))
            .unwrap_or(rest);
        if let Some(decl) = rest.strip_prefix("mod ") {
            let name: String = decl
                .chars()
                .take_while(|&c| c.is_alphanumeric() || c == '_')
                .collect();
            if decl[name.len()..].trim_start().starts_with(';') {
                out.push(name);
            }
        }
    }
    out
}

/// Blanks every `#[cfg(test)]` item.
fn remove_tests(code: &str) -> String {
    let mut s = code.as_bytes().to_vec();
    let pat = b"#[cfg(test)]";
    let mut from = 0;
    while let Some(p) = s[from..].windows(pat.len()).position(|w| w == pat) {
        let start = from + p;
        let mut k = start + pat.len();
        while k < s.len() && s[k] != b'{' && s[k] != b';' {
            k += 1;
        }
        let end = if k < s.len() && s[k] == b'{' {
            matching_brace(&s, k)
        } else {
            k.min(s.len() - 1)
        };
        for c in &mut s[start..=end] {
            if *c != b'\n' {
                *c = b' ';
            }
        }
        from = end;
    }
    String::from_utf8(s).expect("ascii blanks")
}

fn is_ident(c: u8) -> bool {
    c.is_ascii_alphanumeric() || c == b'_'
}

/// The paths of a use tree (`a::{b, c::d as e, f::*}`), each with the name it binds.
fn use_tree(tree: &str) -> Vec<(Vec<String>, Option<String>)> {
    fn walk(prefix: &[String], s: &str, out: &mut Vec<(Vec<String>, Option<String>)>) {
        let mut items = Vec::new();
        let (mut depth, mut cur) = (0, String::new());
        for c in s.chars() {
            match c {
                '{' => depth += 1,
                '}' => depth -= 1,
                _ => {}
            }
            if c == ',' && depth == 0 {
                items.push(std::mem::take(&mut cur));
            } else {
                cur.push(c);
            }
        }
        items.push(cur);
        for item in items.iter().map(|i| i.trim()).filter(|i| !i.is_empty()) {
            if let Some(b) = item.find('{') {
                let mut p = prefix.to_vec();
                p.extend(
                    item[..b]
                        .split("::")
                        .map(str::trim)
                        .filter(|x| !x.is_empty())
                        .map(String::from),
                );
                walk(&p, &item[b + 1..item.rfind('}').unwrap_or(item.len())], out);
            } else {
                let (path, alias) = match item.split_once(" as ") {
                    Some((p, a)) => (p, Some(a.trim().to_string())),
                    None => (item, None),
                };
                let mut p = prefix.to_vec();
                p.extend(path.split("::").map(str::trim).map(String::from));
                if p.last().is_some_and(|l| l == "self") {
                    p.pop();
                }
                let bound = alias.or_else(|| p.last().cloned());
                out.push((p, bound));
            }
        }
    }
    let mut out = Vec::new();
    walk(
        &[],
        &tree.split_whitespace().collect::<Vec<_>>().join(" "),
        &mut out,
    );
    out
}

/// `use` statements of a file: (path, bound name, public).
fn uses(code: &str) -> Vec<(Vec<String>, Option<String>, bool)> {
    let b = code.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while let Some(p) = code[i..].find("use ") {
        let at = i + p;
        i = at + 4;
        if at > 0 && is_ident(b[at - 1]) {
            continue;
        }
        // Only at the start of a statement, possibly after `pub`/`pub(crate)`.
        let before = code[..at].trim_end();
        let public = before.ends_with("pub");
        let restricted = before.ends_with(')') && before.contains("pub(");
        let line_start = before.rfind(['\n', ';', '{', '}']).map_or(0, |x| x + 1);
        let lead = before[line_start..].trim();
        if !(lead.is_empty() || lead == "pub" || (lead.starts_with("pub(") && restricted)) {
            continue;
        }
        let end = code[at..].find(';').map_or(code.len(), |e| at + e);
        for (path, bound) in use_tree(&code[at + 4..end]) {
            out.push((path, bound, public || restricted));
        }
        i = end;
    }
    out
}

/// Paths written in code: `crate::a::b`, `super::x`, `name::y` (any identifier head).
fn inline_paths(code: &str) -> Vec<Vec<String>> {
    let b = code.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < b.len() {
        if is_ident(b[i]) && (i == 0 || !(is_ident(b[i - 1]) || b[i - 1] == b':')) {
            let mut parts = Vec::new();
            let mut j = i;
            loop {
                let s = j;
                while j < b.len() && is_ident(b[j]) {
                    j += 1;
                }
                parts.push(code[s..j].to_string());
                if b[j..].starts_with(b"::") && b.get(j + 2).is_some_and(|&c| is_ident(c)) {
                    j += 2;
                } else {
                    break;
                }
            }
            if parts.len() > 1 {
                out.push(parts);
            }
            i = j.max(i + 1);
        } else {
            i += 1;
        }
    }
    out
}

fn module_of(rel: &Path) -> Option<Module> {
    let mut parts: Vec<String> = rel
        .with_extension("")
        .iter()
        .map(|c| c.to_string_lossy().into_owned())
        .collect();
    if parts.iter().any(|p| p == "tests") || parts == ["main"] {
        return None;
    }
    match parts.last().map(String::as_str) {
        Some("lib") if parts.len() == 1 => parts.clear(),
        Some("mod") => {
            parts.pop();
        }
        _ => {}
    }
    Some(parts)
}

fn load(dir: &str) -> Crate {
    let base = root().join(dir);
    let mut paths = Vec::new();
    rust_files(&base, &mut paths);
    let mut c = Crate {
        files: BTreeMap::new(),
        code: BTreeMap::new(),
        lines: BTreeMap::new(),
        edges: BTreeMap::new(),
    };
    let mut sources = BTreeMap::new();
    let mut test_only = BTreeSet::new();
    for p in paths {
        let Some(m) = module_of(p.strip_prefix(&base).unwrap()) else {
            continue;
        };
        let src = std::fs::read_to_string(&p).unwrap();
        test_only.extend(
            test_modules(&strip(&src))
                .into_iter()
                .map(|t| [m.clone(), vec![t]].concat()),
        );
        sources.insert(m, (p, src));
    }
    for (m, (p, src)) in sources {
        if test_only.contains(&m) {
            continue;
        }
        let code = remove_tests(&strip(&src));
        let non_test = code
            .lines()
            .zip(src.lines())
            .filter(|(c, s)| {
                !c.trim().is_empty() || s.trim().is_empty() || s.trim_start().starts_with("//")
            })
            .count();
        c.lines.insert(m.clone(), non_test);
        c.code.insert(m.clone(), code);
        c.files.insert(m, p);
    }
    resolve_edges(&mut c);
    c
}

fn absolute(c: &Crate, module: &[String], path: &[String]) -> Option<Vec<String>> {
    let head = path.first()?;
    match head.as_str() {
        "crate" => Some(path[1..].to_vec()),
        "self" => Some([module, &path[1..]].concat()),
        "super" => {
            let ups = path.iter().take_while(|p| *p == "super").count();
            let base = &module[..module.len().checked_sub(ups)?];
            Some([base, &path[ups..]].concat())
        }
        _ => {
            let child: Module = [module, &path[..1]].concat();
            c.files
                .contains_key(&child)
                .then(|| [module, path].concat())
        }
    }
}

/// The file that defines `path` (absolute), following `pub use` re-exports.
fn resolve(
    c: &Crate,
    reexports: &BTreeMap<Module, Vec<(Vec<String>, String)>>,
    path: &[String],
    depth: usize,
) -> Module {
    let mut k = path.len();
    while k > 0 && !c.files.contains_key(&path[..k]) {
        k -= 1;
    }
    let module = path[..k].to_vec();
    let rest = &path[k..];
    if let (Some(name), true) = (rest.first(), depth < 8) {
        for (target, bound) in reexports.get(&module).into_iter().flatten() {
            let glob = bound == "*";
            if bound == name || glob {
                let Some(t) = absolute(c, &module, target) else {
                    continue;
                };
                let full = if glob {
                    [&t, rest].concat()
                } else {
                    [&t, &rest[1..]].concat()
                };
                let r = resolve(c, reexports, &full, depth + 1);
                if !glob || r.len() > t.len() {
                    return r;
                }
            }
        }
    }
    module
}

fn resolve_edges(c: &mut Crate) {
    let mut reexports: BTreeMap<Module, Vec<(Vec<String>, String)>> = BTreeMap::new();
    let mut all_uses = BTreeMap::new();
    for (m, code) in &c.code {
        let u = uses(code);
        for (path, bound, public) in &u {
            if *public {
                let name = if path.last().is_some_and(|l| l == "*") {
                    "*".to_string()
                } else {
                    bound.clone().unwrap_or_default()
                };
                reexports
                    .entry(m.clone())
                    .or_default()
                    .push((path.clone(), name));
            }
        }
        all_uses.insert(m.clone(), u);
    }
    let mut edges: BTreeMap<Module, BTreeSet<Module>> = BTreeMap::new();
    for (m, code) in &c.code {
        let mut bound: BTreeMap<String, Vec<String>> = BTreeMap::new();
        let mut targets = Vec::new();
        for (path, name, _) in &all_uses[m] {
            if let Some(abs) = absolute(c, m, path) {
                if let Some(n) = name {
                    bound.insert(n.clone(), abs.clone());
                }
                targets.push(abs);
            }
        }
        for p in inline_paths(code) {
            if let Some(abs) = absolute(c, m, &p) {
                targets.push(abs);
            } else if let Some(b) = bound.get(&p[0]) {
                targets.push([b.as_slice(), &p[1..]].concat());
            }
        }
        let out = edges.entry(m.clone()).or_default();
        for t in targets {
            let file = resolve(c, &reexports, &t, 0);
            if &file != m {
                out.insert(file);
            }
        }
    }
    c.edges = edges;
}

/// Strongly connected components with more than one member (Tarjan).
fn cycles(
    nodes: &BTreeSet<Module>,
    edges: &BTreeMap<Module, BTreeSet<Module>>,
) -> Vec<Vec<Module>> {
    struct T<'a> {
        edges: &'a BTreeMap<Module, BTreeSet<Module>>,
        index: BTreeMap<Module, usize>,
        low: BTreeMap<Module, usize>,
        stack: Vec<Module>,
        on: BTreeSet<Module>,
        out: Vec<Vec<Module>>,
    }
    fn visit(t: &mut T, v: &Module) {
        let n = t.index.len();
        t.index.insert(v.clone(), n);
        t.low.insert(v.clone(), n);
        t.stack.push(v.clone());
        t.on.insert(v.clone());
        for w in t.edges.get(v).into_iter().flatten() {
            if !t.index.contains_key(w) {
                visit(t, w);
                let l = t.low[v].min(t.low[w]);
                t.low.insert(v.clone(), l);
            } else if t.on.contains(w) {
                let l = t.low[v].min(t.index[w]);
                t.low.insert(v.clone(), l);
            }
        }
        if t.low[v] == t.index[v] {
            let mut comp = Vec::new();
            loop {
                let w = t.stack.pop().unwrap();
                t.on.remove(&w);
                let done = &w == v;
                comp.push(w);
                if done {
                    break;
                }
            }
            if comp.len() > 1 {
                comp.sort();
                t.out.push(comp);
            }
        }
    }
    let mut t = T {
        edges,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on: BTreeSet::new(),
        out: Vec::new(),
    };
    for v in nodes {
        if !t.index.contains_key(v) {
            visit(&mut t, v);
        }
    }
    t.out
}

fn name(m: &Module) -> String {
    if m.is_empty() {
        "<crate root>".into()
    } else {
        m.join("::")
    }
}

/// (function name, first line, lines) of every function body.
fn functions(code: &str) -> Vec<(String, usize, usize)> {
    let b = code.as_bytes();
    let mut out = Vec::new();
    let mut from = 0;
    while let Some(p) = code[from..].find("fn ") {
        let at = from + p;
        from = at + 3;
        if at > 0 && is_ident(b[at - 1]) {
            continue;
        }
        let name: String = code[at + 3..]
            .chars()
            .take_while(|&c| c.is_alphanumeric() || c == '_')
            .collect();
        if name.is_empty() {
            continue;
        }
        let mut depth = 0i32;
        let mut k = at;
        let open = loop {
            match b.get(k) {
                None => break None,
                Some(b'(' | b'[' | b'<') => depth += 1,
                Some(b')' | b']') => depth -= 1,
                Some(b'>') if k > 0 && b[k - 1] != b'-' && b[k - 1] != b'=' => depth -= 1,
                Some(b';') if depth <= 0 => break None,
                Some(b'{') if depth <= 0 => break Some(k),
                _ => {}
            }
            k += 1;
        };
        let Some(open) = open else { continue };
        let close = matching_brace(b, open);
        let first = code[..at].matches('\n').count() + 1;
        let last = code[..close].matches('\n').count() + 1;
        out.push((name, first, last - first + 1));
    }
    out
}

fn crates() -> [(&'static str, Crate); 2] {
    [("src", load("src")), ("stages/src", load("stages/src"))]
}

#[test]
fn no_import_circles_between_files_or_top_level_modules() {
    let mut found = Vec::new();
    for (dir, c) in crates() {
        assert!(
            c.files.len() > 10,
            "{dir}: only {} files found",
            c.files.len()
        );
        let nodes: BTreeSet<Module> = c.files.keys().cloned().collect();
        for comp in cycles(&nodes, &c.edges) {
            found.push(format!(
                "{dir}: files {}",
                comp.iter().map(name).collect::<Vec<_>>().join(" -> ")
            ));
        }
        let top = |m: &Module| m.iter().take(1).cloned().collect::<Module>();
        let mut top_edges: BTreeMap<Module, BTreeSet<Module>> = BTreeMap::new();
        for (a, bs) in &c.edges {
            for b in bs {
                if top(a) != top(b) {
                    top_edges.entry(top(a)).or_default().insert(top(b));
                }
            }
        }
        let top_nodes: BTreeSet<Module> = nodes.iter().map(top).collect();
        for comp in cycles(&top_nodes, &top_edges) {
            found.push(format!(
                "{dir}: modules {}",
                comp.iter().map(name).collect::<Vec<_>>().join(" -> ")
            ));
        }
    }
    assert!(found.is_empty(), "import circles:\n{}", found.join("\n"));
}

#[test]
fn no_library_module_imports_a_stage_kind() {
    let c = load("stages/src");
    let kind = |m: &Module| m.first().is_some_and(|x| x == "kinds");
    assert!(
        c.files.keys().filter(|m| kind(m)).count() >= 10,
        "the kinds were not found"
    );
    let up: Vec<String> = c
        .edges
        .iter()
        .filter(|(a, _)| !kind(a))
        .flat_map(|(a, bs)| {
            bs.iter()
                .filter(|b| kind(b))
                .map(move |b| format!("{} -> {}", name(a), name(b)))
        })
        .collect();
    assert!(
        up.is_empty(),
        "library modules importing a kind:\n{}",
        up.join("\n")
    );
    // The reader does see imports: the train kind's params reach the model's engine.
    let train: Module = vec!["kinds".into(), "train".into(), "params".into()];
    let engine: Module = vec!["model".into(), "engine".into()];
    assert!(c.edges[&train].contains(&engine), "{:?}", c.edges[&train]);
}

#[test]
fn files_and_functions_stay_small() {
    let mut found = Vec::new();
    for (dir, c) in crates() {
        for (m, path) in &c.files {
            let rel = path.strip_prefix(root()).unwrap().display().to_string();
            if c.lines[m] > MAX_FILE_LINES {
                found.push(format!("{rel}: {} lines outside tests", c.lines[m]));
            }
            for (f, line, len) in functions(&c.code[m]) {
                let allowed = LONG_FUNCTIONS
                    .iter()
                    .any(|(p, n, _)| rel.ends_with(p) && *n == f);
                if len > MAX_FN_LINES && !allowed {
                    found.push(format!("{rel}:{line}: fn {f} has {len} lines"));
                }
            }
        }
        let _ = dir;
    }
    assert!(
        found.is_empty(),
        "over the limits ({MAX_FILE_LINES} lines a file, {MAX_FN_LINES} a function):\n{}",
        found.join("\n")
    );
}

#[test]
fn the_reader_resolves_imports_and_finds_circles() {
    let code = strip(
        "use crate::a::{b::C, d as e};\n// use crate::x;\nlet s = \"crate::y\"; f(super::z::W);",
    );
    let u = uses(&code);
    assert_eq!(u[0].0, ["crate", "a", "b", "C"]);
    assert_eq!(
        u[1],
        (
            vec!["crate".into(), "a".into(), "d".into()],
            Some("e".into()),
            false
        )
    );
    assert_eq!(u.len(), 2, "{u:?}");
    assert!(inline_paths(&code).contains(&vec!["super".into(), "z".into(), "W".into()]));
    assert!(!inline_paths(&code)
        .iter()
        .any(|p| p.contains(&"y".to_string())));
    let m = |s: &str| {
        s.split('/')
            .filter(|x| !x.is_empty())
            .map(String::from)
            .collect::<Module>()
    };
    let nodes: BTreeSet<Module> = ["a", "b", "c"].iter().map(|s| m(s)).collect();
    let mut edges = BTreeMap::new();
    edges.insert(m("a"), BTreeSet::from([m("b")]));
    edges.insert(m("b"), BTreeSet::from([m("c")]));
    assert!(cycles(&nodes, &edges).is_empty());
    edges.insert(m("c"), BTreeSet::from([m("a")]));
    assert_eq!(cycles(&nodes, &edges), vec![vec![m("a"), m("b"), m("c")]]);
    let f = functions(&strip(
        "fn short() -> Vec<u8> {\n    vec![]\n}\nfn decl();\n",
    ));
    assert_eq!(f, vec![("short".to_string(), 1, 3)]);
    assert_eq!(
        remove_tests("a\n#[cfg(test)]\nmod t {\n x\n}\nb"),
        "a\n            \n       \n  \n \nb"
    );
}
