//! Bounded, proptest-driven fuzzing of the two parsers that read user files: the pipeline YAML
//! (`pipe::config::parse` + the DAG check) and the KITTI-360 `data_3d_bboxes` XML (the whole
//! `kitti360_scene` loader on a fixture whose XML is mutated).
//!
//! Inputs are real files (pipeline.yaml, pipelines/, the bad-pipeline corpus, the fixture XML and
//! the bad-XML corpus) with random edits: deleted ranges, inserted syntax tokens and random
//! characters, duplicated and swapped lines, truncation, and numbers replaced by extreme ones.
//! Properties: nothing panics; the YAML gives a pipeline or an error that names the file and a
//! line and column inside it; the XML gives a scene or an input error naming the XML file.
//!
//! A few hundred cases each, seconds in CI; `PROPTEST_CASES=100000` soaks.

mod common;

use std::{
    fs,
    path::{Path, PathBuf},
};

use pipe::config::{self, Loc};
use proptest::prelude::*;
use stages::scene::kitti360::{self, Kitti360Params};

fn repo() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// `cases` by default; `PROPTEST_CASES=N` in the environment overrides it (for soak runs).
fn cfg(cases: u32) -> ProptestConfig {
    let cases = std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(cases);
    ProptestConfig {
        cases,
        // The corpus is the regression file: keep the source tree clean.
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

/// One random edit of a text.
#[derive(Debug, Clone)]
enum Edit {
    Delete { at: usize, len: usize },
    Insert { at: usize, text: String },
    DuplicateLine { line: usize },
    SwapLines { a: usize, b: usize },
    Truncate { at: usize },
    Number { nth: usize, value: &'static str },
}

/// Numbers that break careless parsers: overflow, NaN, negative sizes, huge dimensions.
const EXTREME_NUMBERS: &[&str] = &[
    "0",
    "-0",
    "-1",
    "1e999",
    "-1e999",
    "1e-400",
    "nan",
    "NaN",
    "inf",
    "-inf",
    ".nan",
    "4294967296",
    "18446744073709551616",
    "6148914691236517206",
    "99999999999999999999999999",
    "1.5",
    "0x10",
    "",
];

fn edit(tokens: &'static [&'static str]) -> impl Strategy<Value = Edit> {
    let text = prop_oneof![
        prop::sample::select(tokens).prop_map(str::to_string),
        "[ -~\n\t]{1,4}",
        "\\PC{1,3}",
    ];
    prop_oneof![
        (any::<usize>(), 1usize..12).prop_map(|(at, len)| Edit::Delete { at, len }),
        (any::<usize>(), text).prop_map(|(at, text)| Edit::Insert { at, text }),
        any::<usize>().prop_map(|line| Edit::DuplicateLine { line }),
        (any::<usize>(), any::<usize>()).prop_map(|(a, b)| Edit::SwapLines { a, b }),
        any::<usize>().prop_map(|at| Edit::Truncate { at }),
        (any::<usize>(), prop::sample::select(EXTREME_NUMBERS))
            .prop_map(|(nth, value)| Edit::Number { nth, value }),
    ]
}

/// Applies edits on characters (never splitting one), positions taken modulo the length.
fn apply(text: &str, edits: &[Edit]) -> String {
    let mut c: Vec<char> = text.chars().collect();
    for e in edits {
        let n = c.len().max(1);
        match e {
            Edit::Delete { at, len } => {
                let a = at % n;
                let b = (a + len).min(c.len());
                if a < b {
                    c.drain(a..b);
                }
            }
            Edit::Insert { at, text } => {
                let a = at % (c.len() + 1);
                c.splice(a..a, text.chars());
            }
            Edit::DuplicateLine { line } | Edit::SwapLines { a: line, .. } => {
                let s: String = c.iter().collect();
                let mut lines: Vec<&str> = s.split('\n').collect();
                let i = line % lines.len();
                match e {
                    Edit::SwapLines { b, .. } => {
                        let j = b % lines.len();
                        lines.swap(i, j);
                    }
                    _ => lines.insert(i, lines[i]),
                }
                c = lines.join("\n").chars().collect();
            }
            Edit::Truncate { at } => c.truncate(at % n),
            Edit::Number { nth, value } => {
                // Maximal runs of digits (with sign, dot and exponent) are the numbers.
                let is_num = |ch: char| ch.is_ascii_digit() || ".eE+-".contains(ch);
                let mut runs = Vec::new();
                let mut i = 0;
                while i < c.len() {
                    if c[i].is_ascii_digit() {
                        let mut a = i;
                        while a > 0 && is_num(c[a - 1]) {
                            a -= 1;
                        }
                        let mut b = i;
                        while b < c.len() && is_num(c[b]) {
                            b += 1;
                        }
                        runs.push((a, b));
                        i = b;
                    } else {
                        i += 1;
                    }
                }
                if !runs.is_empty() {
                    let (a, b) = runs[nth % runs.len()];
                    c.splice(a..b, value.chars());
                }
            }
        }
    }
    c.into_iter().collect()
}

fn read_all(paths: impl IntoIterator<Item = PathBuf>) -> Vec<String> {
    paths
        .into_iter()
        .map(|p| fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display())))
        .collect()
}

fn files_in(dir: &str, ext: &str) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = fs::read_dir(repo().join(dir))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == ext))
        .collect();
    v.sort();
    v
}

// ---- pipeline YAML ----

const YAML_TOKENS: &[&str] = &[
    ": ",
    "- ",
    "\n",
    "  ",
    "\t",
    "{",
    "}",
    "[",
    "]",
    ",",
    "&a ",
    "*a",
    "<<: *a\n",
    "!!str ",
    "!!binary ",
    "!custom ",
    "'",
    "\"",
    "#",
    "|\n",
    ">-\n",
    "? ",
    "~",
    "null",
    "---\n",
    "...\n",
    "%YAML 1.2\n",
    "stages:",
    "uses: ",
    "inputs: ",
    "params: ",
    "cache: ",
    "scene",
    "train",
    "synthetic_scene",
    "intersect",
    "test_source",
    "{scene: scene}",
    "é",
    "\u{202e}",
    "\u{0}",
    // Line breaks to libyaml only (it once placed errors past the file's last line).
    "\u{2028}",
    "\u{2029}",
    "\u{85}",
    "\r",
];

fn yaml_seeds() -> Vec<String> {
    let mut seeds = read_all(
        [
            repo().join("pipeline.yaml"),
            repo().join("pipelines/kitti360.yaml"),
        ]
        .into_iter()
        .chain(files_in("tests/bad_inputs/pipeline", "yaml")),
    );
    seeds.push(common::TINY_PIPELINE.to_string());
    seeds
}

/// Ok, or an error that names the file and (when located) a line and column inside the text.
fn check_pipeline(text: &str) -> Result<(), TestCaseError> {
    let file = Path::new("fuzz/pipeline.yaml");
    let result = config::parse(file, text, &[]).and_then(|p| {
        pipe::dag::Dag::build(&p)?;
        Ok(p)
    });
    match result {
        Ok(p) => prop_assert!(!p.stages.is_empty()),
        Err(e) => {
            let msg = e.to_string();
            prop_assert!(msg.starts_with("fuzz/pipeline.yaml"), "{msg}");
            prop_assert!(!e.message.trim().is_empty(), "empty message: {msg}");
            if let Loc::File { line, col } = e.loc {
                let lines = text.split('\n').count();
                prop_assert!(
                    (1..=lines + 1).contains(&line) && col >= 1,
                    "{msg}: location outside the {lines}-line text {text:?}"
                );
            }
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(cfg(400))]

    #[test]
    fn mutated_pipeline_files_never_panic_and_errors_are_located(
        seed in any::<prop::sample::Index>(),
        edits in prop::collection::vec(edit(YAML_TOKENS), 1..6),
    ) {
        let seeds = yaml_seeds();
        let text = apply(seeds[seed.index(seeds.len())].as_str(), &edits);
        check_pipeline(&text)?;
    }

    #[test]
    fn arbitrary_text_never_panics_the_pipeline_parser(text in "\\PC{0,120}|[ -~\n]{0,200}") {
        check_pipeline(&text)?;
    }

    #[test]
    fn arbitrary_set_overrides_never_panic(arg in "\\PC{0,40}|[a-z]{1,5}\\.[a-z_]{1,8}=[ -~]{0,20}") {
        if let Ok(o) = config::Override::parse(&arg) {
            let text = "stages:\n  a:\n    uses: test_source\n";
            let _ = config::parse(Path::new("p.yaml"), text, &[o]);
        }
    }
}

#[test]
fn the_mutation_engine_edits_characters_and_numbers() {
    // The fuzz tests are only as good as their edits: check the tricky ones do what they say.
    let t = "a: 12\nb: -3.5e2\né: x";
    assert_eq!(
        apply(
            t,
            &[Edit::Number {
                nth: 1,
                value: "nan"
            }]
        ),
        "a: 12\nb: nan\né: x"
    );
    assert_eq!(
        apply(t, &[Edit::SwapLines { a: 0, b: 2 }]),
        "é: x\nb: -3.5e2\na: 12"
    );
    assert_eq!(
        apply(t, &[Edit::Delete { at: 16, len: 9 }]),
        "a: 12\nb: -3.5e2\n"
    );
    assert_eq!(
        apply(
            t,
            &[
                Edit::Insert {
                    at: 0,
                    text: "é".into()
                },
                Edit::Truncate { at: 2 }
            ]
        ),
        "éa"
    );
    assert!(yaml_seeds().len() >= 20);
}

// ---- KITTI-360 bboxes XML ----

const XML_TOKENS: &[&str] = &[
    "<",
    ">",
    "</",
    "/>",
    "&amp;",
    "&#0;",
    "&#x110000;",
    "&bogus;",
    "<![CDATA[",
    "]]>",
    "<!--",
    "-->",
    "<?xml version=\"1.0\"?>",
    "<!DOCTYPE x [<!ENTITY e \"ee\">]>",
    "&e;",
    "\"",
    "=",
    " ",
    "\n",
    "<rows>",
    "</rows>",
    "<cols>",
    "</cols>",
    "<data>",
    "</data>",
    "<object9>",
    "</object9>",
    "<semanticId>",
    "</semanticId>",
    "<timestamp>-1</timestamp>",
    "é",
    "\u{0}",
];

fn xml_seeds() -> Vec<String> {
    read_all(
        std::iter::once(repo().join("tests/fixtures/kitti360/data_3d_bboxes/train/seq_a.xml"))
            .chain(files_in("tests/bad_inputs/kitti360", "xml")),
    )
}

struct Fixture {
    _dir: tempfile::TempDir,
    params: Kitti360Params,
    xml: PathBuf,
}

fn fixture() -> Fixture {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("k360");
    common::kitti360_fixture(&root);
    let params = Kitti360Params {
        root: root.display().to_string(),
        sequence: "seq_a".into(),
        first_frame: 0,
        last_frame: 10,
        eval_every: 1,
        ..Default::default()
    };
    let xml = root.join("data_3d_bboxes/train/seq_a.xml");
    Fixture {
        _dir: dir,
        params,
        xml,
    }
}

proptest! {
    #![proptest_config(cfg(300))]

    #[test]
    fn mutated_bboxes_xml_never_panics_the_loader(
        seed in any::<prop::sample::Index>(),
        edits in prop::collection::vec(edit(XML_TOKENS), 1..6),
    ) {
        thread_local! {
            static FIXTURE: Fixture = fixture();
        }
        let seeds = xml_seeds();
        let text = apply(seeds[seed.index(seeds.len())].as_str(), &edits);
        // The parser alone, then the whole loader (primitive validation, culling, tables).
        let _ = kitti360::parse::bboxes(Path::new("seq_a.xml"), &text);
        FIXTURE.with(|f| -> Result<(), TestCaseError> {
            fs::write(&f.xml, &text).unwrap();
            if let Err(e) = kitti360::load(&f.params, &stages::NoProgress) {
                let msg = e.to_string();
                let want = format!("bad input: {}: ", f.xml.display());
                prop_assert!(msg.starts_with(&want), "{msg}\nfor XML {text:?}");
            }
            Ok(())
        })?;
    }
}
