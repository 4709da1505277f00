//! `pipe bench` end to end on a micro suite (tests/fixtures/bench_micro.yaml: one tiny scene,
//! two budgets, two variants, a few iterations): the files it writes, the rows of
//! results.parquet, a second run that reuses every cache entry and gives identical error
//! figures, and the exit code 2 errors for a bad suite.

mod common;

use std::{collections::BTreeSet, fs, path::Path};

use arrow::array::{Array, Float64Array, StringArray, UInt64Array};
use common::{Workspace, EDIT_PIPELINE, TINY_PIPELINE};
use pipe::runner::{Outcome, RunReport};

fn fixture() -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/bench_micro.yaml")
        .display()
        .to_string()
}

fn read_results(path: &Path) -> arrow::record_batch::RecordBatch {
    pipe::store::read_parquet(fs::read(path).unwrap()).unwrap()
}

fn column<'a, T: 'static>(b: &'a arrow::record_batch::RecordBatch, name: &str) -> &'a T {
    b.column_by_name(name)
        .unwrap_or_else(|| panic!("results.parquet has no column `{name}`"))
        .as_any()
        .downcast_ref::<T>()
        .unwrap_or_else(|| panic!("column `{name}` has the wrong type"))
}

#[test]
fn micro_suite_writes_its_files_and_a_second_run_reuses_the_cache() {
    let ws = Workspace::new(TINY_PIPELINE);
    let suite = fixture();
    let (code, out, err) = ws.cmd("bench", &["--suite", &suite, "--out", "out"]);
    assert_eq!(code, 0, "stdout:\n{out}\nstderr:\n{err}");
    let dir = ws.dir().join("out");
    for f in [
        "REPORT.md",
        "report.html",
        "results.parquet",
        "time_vs_error_t0.png",
        "pipeline.yaml",
        "run-report.json",
    ] {
        let p = dir.join(f);
        assert!(
            p.metadata().is_ok_and(|m| m.len() > 0),
            "{} missing or empty",
            p.display()
        );
    }
    let md = fs::read_to_string(dir.join("REPORT.md")).unwrap();
    for needle in [
        "Error figures are reproducible",
        "Times vary",
        "## Ablation (budget 6)",
        "w/o L_depth",
        "Runner overhead",
    ] {
        assert!(md.contains(needle), "REPORT.md lacks {needle:?}:\n{md}");
    }
    let html = fs::read_to_string(dir.join("report.html")).unwrap();
    assert!(html.contains("data:image/png;base64,"), "plots not inline");

    let first = read_results(&dir.join("results.parquet"));
    let names: Vec<String> = first
        .schema()
        .fields()
        .iter()
        .map(|f| f.name().clone())
        .collect();
    assert_eq!(
        names,
        [
            "scene",
            "variant",
            "budget",
            "seed",
            "method",
            "metric",
            "value",
            "train_wall_s"
        ]
    );
    let variant = column::<StringArray>(&first, "variant");
    let budget = column::<UInt64Array>(&first, "budget");
    let method = column::<StringArray>(&first, "method");
    let metric = column::<StringArray>(&first, "metric");
    let runs: BTreeSet<(String, u64)> = (0..first.num_rows())
        .map(|i| (variant.value(i).to_string(), budget.value(i)))
        .collect();
    let expected: BTreeSet<(String, u64)> = [("complete", 3), ("complete", 6), ("no_depth", 6)]
        .iter()
        .map(|&(v, b)| (v.to_string(), b))
        .collect();
    assert_eq!(runs, expected);
    assert_eq!(first.num_rows() % runs.len(), 0, "runs have unequal rows");
    let methods: BTreeSet<&str> = (0..first.num_rows()).map(|i| method.value(i)).collect();
    for m in [
        "panoptic_nerf",
        "fixed_field",
        "pseudo_labels",
        "first_primitive",
        "stage:train",
        "stage:evaluate",
    ] {
        assert!(methods.contains(m), "no rows of method {m}: {methods:?}");
    }
    for (m, k) in [
        ("panoptic_nerf", "miou"),
        ("panoptic_nerf", "pq"),
        ("panoptic_nerf", "depth_rmse"),
        ("stage:train", "peak_rss_bytes"),
    ] {
        let n = (0..first.num_rows())
            .filter(|&i| method.value(i) == m && metric.value(i) == k)
            .count();
        assert_eq!(n, runs.len(), "{m}/{k}: one row per run");
    }

    // Again: everything comes from the cache and the figures are the same.
    let (code, out, err) = ws.cmd("bench", &["--suite", &suite, "--out", "out"]);
    assert_eq!(code, 0, "stdout:\n{out}\nstderr:\n{err}");
    let rep: RunReport =
        serde_json::from_slice(&fs::read(dir.join("run-report.json")).unwrap()).unwrap();
    assert!(!rep.stages.is_empty());
    for s in &rep.stages {
        assert_eq!(s.outcome, Outcome::Cached, "stage `{}` re-ran", s.stage);
    }
    let second = read_results(&dir.join("results.parquet"));
    assert_eq!(second.num_rows(), first.num_rows());
    let (a, b) = (
        column::<Float64Array>(&first, "value"),
        column::<Float64Array>(&second, "value"),
    );
    assert_eq!(a, b, "error figures differ between runs");
}

#[test]
fn bad_suites_are_usage_errors_naming_the_file_and_key() {
    let ws = Workspace::new(TINY_PIPELINE);
    let (code, _, err) = ws.cmd("bench", &["--suite", "nope"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("unknown suite `nope`"), "{err}");

    fs::write(ws.dir().join("bad.yaml"), "name: x\nscenes: [{name: a\n").unwrap();
    let (code, _, err) = ws.cmd("bench", &["--suite", "bad.yaml"]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("bad.yaml:") && err.contains("invalid suite"),
        "{err}"
    );

    fs::write(
        ws.dir().join("key.yaml"),
        "name: x\nscenes: [{name: a}]\nbudgets: [1]\nvariants:\n  - name: v\n    set: {train.losses.nope: 0}\n",
    )
    .unwrap();
    let (code, _, err) = ws.cmd("bench", &["--suite", "key.yaml"]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("key.yaml:6:11: `variants.0.set.train.losses.nope`")
            && err.contains("unknown parameter `losses.nope` of stage `train`"),
        "{err}"
    );
    assert!(
        !ws.dir().join("bench-results").exists(),
        "nothing is written for a bad suite"
    );
}

/// `pipe bench --suite` with an edits suite, on a tiny street: the run before the edit, the
/// update and the run from scratch, each a `pipe run` of its own; the report names what every
/// stage did. Run twice, the second bench computes the updates again (their time is measured,
/// never a record of the first bench's) while the runs from scratch are found cached.
#[test]
fn an_edits_suite_measures_every_update_afresh() {
    let ws = Workspace::new(EDIT_PIPELINE);
    fs::write(
        ws.dir().join("edits.yaml"),
        "name: edits
until: render
edits_param: scene.edits
scenes:
  - {name: street}
edits:
  - name: relabel
    label: car 93 becomes a caravan
    object: 93
    edits: [{primitive: 93, class: caravan}]
",
    )
    .unwrap();
    for round in 0..2 {
        let (code, out, err) = ws.cmd("bench", &["--suite", "edits.yaml", "--out", "out"]);
        assert_eq!(code, 0, "stdout:\n{out}\nstderr:\n{err}");
        let md = fs::read_to_string(ws.dir().join("out/REPORT.md")).unwrap();
        let line = md
            .lines()
            .find(|l| l.trim_start().starts_with("- update:"))
            .unwrap_or_else(|| panic!("no update line:\n{md}"));
        for stage in ["rays", "train", "render"] {
            assert!(
                line.contains(&format!("{stage}: updated: ")),
                "round {round}: {stage} was not updated now: {line}"
            );
        }
        assert!(!line.contains("cached"), "round {round}: {line}");
        let cold = md
            .lines()
            .find(|l| l.trim_start().starts_with("- cold:"))
            .unwrap();
        assert!(
            cold.contains("train: from scratch") && (round == 0) != cold.contains("cached"),
            "round {round}: {cold}"
        );
    }
}
