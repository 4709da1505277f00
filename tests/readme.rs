//! The guide cannot rot: every `pipe` command in README.md's shell blocks runs, in the order the
//! README gives them, on the tiny scene (a workspace whose `pipeline.yaml` is the tiny pipeline,
//! with the repository's `pipelines/` beside it), and must succeed. Commands that need what a
//! test machine lacks are checked as far as they can be without it: a pipeline file of its own
//! (`-f pipelines/...`: KITTI-360 data, full-size scenes) or a Slurm run is validated with
//! `pipe dag` (every stage, input and parameter, with the same `--set`s); a `pipe bench` suite
//! must exist.

mod common;

use std::{fs, path::Path};

use common::{Workspace, TINY_PIPELINE};

/// The README's commands: the lines of its `sh` blocks that start with `pipe ` or
/// `cargo run --release -- ` (as `pipe ...`), comments dropped, split into arguments.
fn readme_commands(text: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let mut in_sh = false;
    for line in text.lines() {
        let t = line.trim();
        if t.starts_with("```") {
            in_sh = !in_sh && (t == "```sh" || t == "```bash");
            continue;
        }
        if !in_sh {
            continue;
        }
        let t = t.split(" #").next().unwrap_or("").trim();
        let rest = t
            .strip_prefix("pipe ")
            .or_else(|| t.strip_prefix("cargo run --release -- "));
        if let Some(rest) = rest {
            out.push(rest.split_whitespace().map(String::from).collect());
        }
    }
    out
}

/// The value after `flag` in `args`.
fn value_of<'a>(args: &'a [String], flag: &str) -> Option<&'a str> {
    args.iter()
        .position(|a| a == flag)
        .and_then(|i| args.get(i + 1))
        .map(String::as_str)
}

/// `pipe dag` with the pipeline file and the `--set`s of `args`.
fn as_dag(args: &[String]) -> Vec<String> {
    let mut dag = vec!["dag".to_string()];
    for flag in ["-f", "--set"] {
        for (i, a) in args.iter().enumerate() {
            if a == flag {
                dag.extend([a.clone(), args[i + 1].clone()]);
            }
        }
    }
    dag
}

fn copy_dir(from: &Path, to: &Path) {
    fs::create_dir_all(to).unwrap();
    for e in fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
}

#[test]
fn the_readme_s_commands_run_in_order_on_the_tiny_scene() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let readme = fs::read_to_string(root.join("README.md")).unwrap();
    let commands = readme_commands(&readme);
    let ws = Workspace::new(TINY_PIPELINE);
    copy_dir(&root.join("pipelines"), &ws.dir().join("pipelines"));
    let (mut ran, mut validated) = (0, 0);
    for args in &commands {
        let shown = format!("pipe {}", args.join(" "));
        if args.first().map(String::as_str) == Some("bench") {
            let suite = value_of(args, "--suite").unwrap_or("quick");
            let file = root.join("benches/suites").join(format!("{suite}.yaml"));
            assert!(file.exists(), "{shown}: no suite {}", file.display());
            continue;
        }
        let elsewhere = value_of(args, "-f").is_some_and(|f| f != "pipeline.yaml")
            || value_of(args, "--executor") == Some("slurm");
        let run: Vec<String> = if elsewhere {
            validated += 1;
            as_dag(args)
        } else {
            ran += 1;
            args.clone()
        };
        let refs: Vec<&str> = run[1..].iter().map(String::as_str).collect();
        let (code, out, err) = ws.cmd(&run[0], &refs);
        assert_eq!(
            code,
            0,
            "`{shown}` (run as `pipe {}`) failed:\n{out}\n{err}",
            run.join(" ")
        );
    }
    // The guide shows the whole loop on the default pipeline, and the recipes for real data.
    assert!(ran >= 8, "only {ran} README commands ran: {commands:?}");
    assert!(validated >= 2, "only {validated} pipeline files validated");
}

#[test]
fn commands_are_read_from_shell_blocks_only() {
    let text = "pipe run\n```sh\npipe run --until render   # stop early\ncargo run --release -- \
                status\ncargo test\n```\n```yaml\npipe: no\n```\n";
    assert_eq!(
        readme_commands(text),
        [vec!["run", "--until", "render"], vec!["status"],]
    );
    let args: Vec<String> = ["run", "-f", "p.yaml", "--set", "a.b=1", "--jobs", "2"]
        .map(String::from)
        .to_vec();
    assert_eq!(as_dag(&args), ["dag", "-f", "p.yaml", "--set", "a.b=1"]);
}
