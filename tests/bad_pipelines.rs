//! The bad-pipeline corpus: every file under tests/bad_inputs/pipeline/ must make `pipe run`
//! exit with code 2 and print every `# expect:` line of the file (file, line:column, stage, key
//! and the problem), and nothing may run or be cached.

mod common;

use std::{fs, path::Path, process::Command};

#[test]
fn every_bad_pipeline_gives_its_clear_error() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/bad_inputs/pipeline");
    let mut files: Vec<_> = fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    assert!(files.len() >= 15, "corpus shrank");
    let tmp = tempfile::tempdir().unwrap();
    let mut failures = Vec::new();
    for f in &files {
        let name = f.file_name().unwrap().to_str().unwrap();
        let text = fs::read_to_string(f).unwrap();
        let expects: Vec<&str> = text
            .lines()
            .filter_map(|l| l.strip_prefix("# expect: "))
            .collect();
        assert!(!expects.is_empty(), "{name} has no `# expect:` line");
        let local = tmp.path().join(name);
        fs::write(&local, &text).unwrap();
        for cmd in ["run", "status"] {
            let out = Command::new(common::PIPE)
                .args([cmd, "-f", name])
                .current_dir(tmp.path())
                .output()
                .unwrap();
            let err = String::from_utf8_lossy(&out.stderr);
            if out.status.code() != Some(2) {
                failures.push(format!(
                    "{name} ({cmd}): exit {:?}, want 2\n{err}",
                    out.status.code()
                ));
            }
            for e in &expects {
                if !err.contains(e) {
                    failures.push(format!("{name} ({cmd}): stderr lacks {e:?}\n  got: {err}"));
                }
            }
            if err.contains("panicked") {
                failures.push(format!("{name} ({cmd}): panic\n{err}"));
            }
        }
    }
    assert!(
        !tmp.path().join(".pipe/objects").exists(),
        "an invalid pipeline created cache entries"
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn bad_command_lines_are_usage_errors() {
    let ws = common::Workspace::new("stages:\n  a:\n    uses: test_source\n");
    for args in [
        vec!["--set", "a"],
        vec!["--set", "zz.value=1"],
        vec!["--set", "a.nope=1"],
        vec!["--until", "zz"],
        vec!["--until", "a", "--only", "a"],
        vec!["--frobnicate"],
        vec!["-f", "missing.yaml"],
    ] {
        let (code, _, err) = ws.run(&args);
        assert_eq!(code, 2, "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{err}");
    }
    let (code, _, err) = ws.cmd("show", &["zz"]);
    assert_eq!(code, 2, "{err}");
}
