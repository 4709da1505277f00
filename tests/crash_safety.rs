//! Crash safety of the cache under SIGKILL: the default tiny pipeline is killed at many
//! pseudo-random moments across all its stages; after every kill each published entry must
//! verify (no partial or corrupt entry), and the run that finally completes must produce the
//! same metrics as an uninterrupted run.

mod common;

use std::{
    fs, thread,
    time::{Duration, Instant},
};

use common::Workspace;

fn metrics_bytes(ws: &Workspace) -> Vec<u8> {
    let out = ws.dir().join("metrics-export");
    let _ = fs::remove_dir_all(&out);
    let (code, o, e) = ws.cmd("export", &["evaluate", "--to", out.to_str().unwrap()]);
    assert_eq!(code, 0, "{o}{e}");
    fs::read(out.join("metrics.json")).unwrap()
}

#[test]
fn sigkill_at_random_moments_never_corrupts_the_cache() {
    // Reference: one uninterrupted run.
    let reference = Workspace::new(common::TINY_PIPELINE);
    let t0 = Instant::now();
    reference.run_ok(&[]);
    let full = t0.elapsed();
    let want = metrics_bytes(&reference);

    let ws = Workspace::new(common::TINY_PIPELINE);
    let mut rng = stages::rng::SplitMix64::new(20261122);
    let mut kills = 0;
    let mut attempts = 0;
    while kills < 24 && attempts < 200 {
        attempts += 1;
        // Kill somewhere in the remaining work: spread over the whole uninterrupted duration.
        let delay = Duration::from_secs_f64(full.as_secs_f64() * rng.unit() as f64 * 0.9);
        let mut child = ws.spawn(&[]);
        thread::sleep(delay);
        if child.try_wait().unwrap().is_some() {
            // It finished first: force everything to be recomputed again for the next try.
            fs::remove_dir_all(ws.cache().join("objects")).unwrap();
            continue;
        }
        child.kill().unwrap();
        child.wait().unwrap();
        kills += 1;
        ws.assert_every_entry_verifies(&format!("kill {kills} at {delay:?}"));
        // Now and then start over so that kills land in early stages too.
        if kills % 6 == 0 {
            fs::remove_dir_all(ws.cache().join("objects")).unwrap();
        }
    }
    assert!(
        kills >= 20,
        "only {kills} kills landed in {attempts} attempts"
    );
    ws.run_ok(&[]);
    ws.assert_every_entry_verifies("the final run");
    assert!(
        fs::read_dir(ws.cache().join("tmp"))
            .unwrap()
            .next()
            .is_none(),
        "tmp/ not cleaned"
    );
    assert_eq!(
        metrics_bytes(&ws),
        want,
        "metrics differ from an uninterrupted run"
    );
}
