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
        vec!["-j", "0"],
    ] {
        let (code, _, err) = ws.run(&args);
        assert_eq!(code, 2, "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{err}");
    }
    let (code, _, err) = ws.cmd("show", &["zz"]);
    assert_eq!(code, 2, "{err}");
}

/// A bad value deep inside a param names its full key (`STAGE.PARAM.FIELD`) and where it was
/// given, and shows NaN as NaN.
#[test]
fn nested_param_errors_name_the_full_key_and_where_it_was_given() {
    let ws = common::Workspace::new(common::TINY_PIPELINE);
    for (set, needles) in [
        (
            "train.optimiser.lr=.nan",
            &[
                "command line `train.optimiser.lr=.nan`",
                "`train.optimiser.lr`",
                ".nan (NaN)",
            ][..],
        ),
        (
            "train.schedule.iterations=-1",
            &["`train.schedule.iterations`", "invalid value: integer `-1`"][..],
        ),
        ("scene.seed=.inf", &["`scene.seed`", "infinity"][..]),
        // Out of range: the full key, the command line and the range.
        (
            "train.optimiser.lr=-0.02",
            &[
                "command line `train.optimiser.lr=-0.02`",
                "`train.optimiser.lr`: -0.02 must be > 0",
            ][..],
        ),
        (
            "train.schedule.rays_per_batch=4000000000",
            &["`train.schedule.rays_per_batch`: 4000000000 must be in 1..="][..],
        ),
    ] {
        let (code, _, err) = ws.run(&["--set", set]);
        assert_eq!(code, 2, "{set}: {err}");
        for n in needles {
            assert!(err.contains(n), "{set}: lacks {n:?}: {err}");
        }
        assert!(!err.contains("null"), "{set}: {err}");
    }
    // In the file: the line of the nested key itself.
    let text = fs::read_to_string(ws.dir().join("pipeline.yaml")).unwrap();
    let bad = text.replacen("iterations: 40,", "iterations: -1,", 1);
    assert_ne!(bad, text, "the tiny pipeline sets train params inline");
    fs::write(ws.dir().join("bad.yaml"), &bad).unwrap();
    let line = bad
        .lines()
        .position(|l| l.contains("iterations: -1"))
        .unwrap()
        + 1;
    let (code, _, err) = ws.run(&["-f", "bad.yaml"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains(&format!("bad.yaml:{line}:")), "{err}");
    assert!(err.contains("`train.schedule.iterations`"), "{err}");
}

/// Every pipeline file the project ships parses and validates (`pipe dag` checks every stage,
/// input and parameter; `pipe status` keys each stage from them), so a renamed parameter cannot
/// leave one broken.
#[test]
fn shipped_pipelines_validate() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files = vec![root.join("pipeline.yaml")];
    for e in std::fs::read_dir(root.join("pipelines")).unwrap() {
        let path = e.unwrap().path();
        if path.extension().is_some_and(|x| x == "yaml") {
            files.push(path);
        }
    }
    assert!(files.len() >= 5, "{files:?}");
    let ws = common::Workspace::new("stages:\n  a:\n    uses: test_source\n");
    for f in &files {
        let (code, out, err) = ws.cmd("dag", &["-f", f.to_str().unwrap()]);
        assert_eq!(code, 0, "{}: {out}{err}", f.display());
        let (code, out, err) = ws.cmd(
            "status",
            &[
                "-f",
                f.to_str().unwrap(),
                "--cache",
                ws.cache().to_str().unwrap(),
            ],
        );
        // The KITTI-360 pipelines read a data set this machine does not have: their params
        // passed (above) and the only complaint is the missing data.
        let kitti = f
            .file_name()
            .is_some_and(|n| n.to_string_lossy().starts_with("kitti360"));
        let needs_data = kitti && err.contains("cannot read");
        assert!(code == 0 || needs_data, "{}: {out}{err}", f.display());
    }
}

/// A pipeline file that is no regular file (a FIFO, a device, a directory) or is too large is
/// refused before it is read, by every command that takes `-f`: nothing hangs or fills memory.
#[test]
fn pipeline_files_that_are_no_regular_file_or_too_large_are_refused_unread() {
    let tmp = tempfile::tempdir().unwrap();
    let fifo = tmp.path().join("fifo.yaml");
    let made = Command::new("mkfifo").arg(&fifo).status();
    let big = tmp.path().join("big.yaml");
    fs::write(&big, "#".repeat(5 << 20)).unwrap();
    let mut cases = vec![
        (big.clone(), "more than 4 MiB is refused"),
        (tmp.path().to_path_buf(), "is a directory"),
        (Path::new("/dev/zero").to_path_buf(), "not a regular file"),
    ];
    if made.is_ok_and(|s| s.success()) {
        cases.push((fifo, "not a regular file"));
    }
    for (file, want) in &cases {
        for cmd in ["run", "status", "dag"] {
            let mut child = Command::new(common::PIPE)
                .args([cmd, "-f"])
                .arg(file)
                .current_dir(tmp.path())
                .stdout(std::process::Stdio::null())
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap();
            // A hang is a failure, not a stuck test.
            let t0 = std::time::Instant::now();
            let status = loop {
                if let Some(s) = child.try_wait().unwrap() {
                    break s;
                }
                if t0.elapsed().as_secs() > 20 {
                    child.kill().unwrap();
                    panic!("pipe {cmd} -f {} hangs", file.display());
                }
                std::thread::sleep(std::time::Duration::from_millis(20));
            };
            let mut err = String::new();
            std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut err).unwrap();
            assert_eq!(status.code(), Some(2), "{cmd} {}: {err}", file.display());
            assert!(err.contains(want), "{cmd} {}: {err}", file.display());
        }
    }
}

/// A cache whose `objects` is a file is not taken for a cache: the message says what is wrong.
#[test]
fn a_cache_directory_that_is_a_file_is_named() {
    let ws = common::Workspace::new("stages:\n  a:\n    uses: test_source\n");
    fs::create_dir_all(ws.cache()).unwrap();
    fs::write(ws.cache().join("objects"), "not a directory").unwrap();
    let (code, _, err) = ws.run(&[]);
    assert_ne!(code, 0);
    assert!(
        err.contains("objects is a file, not a directory: this is not a cache"),
        "{err}"
    );
    assert!(
        !err.contains("File exists") && !err.contains("panicked"),
        "{err}"
    );
}
