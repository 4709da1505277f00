//! The method does what it is for: on a tiny synthetic scene, training lowers every loss and the
//! fused labels rendered for the training frames are more accurate than the noisy pseudo labels
//! they were trained from (multi-view fusion plus the primitives' geometry removes noise that a
//! single view cannot).

mod common;

use std::fs;

use common::Workspace;

/// Every frame is evaluated (eval_every 1), so the metrics are on the training frames.
const PIPELINE: &str = "
stages:
  scene:
    uses: synthetic_scene
    params: {frames: 6, eval_every: 1, scale: 0.0625, noise: 1.5}
  rays:
    uses: intersect
    inputs: {scene: scene}
  train:
    uses: train
    inputs: {scene: scene, rays: rays}
    params:
      schedule: {iterations: 300, rays_per_batch: 512}
      optimiser: {lr: 0.005, lr_final_factor: 0.1}
  render:
    uses: render
    inputs: {scene: scene, rays: rays, train: train}
  evaluate:
    uses: evaluate
    inputs: {scene: scene, render: render}
";

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

#[test]
fn training_lowers_the_losses_and_beats_the_pseudo_labels_on_the_training_frames() {
    let ws = Workspace::new(PIPELINE);
    ws.run_ok(&[]);

    // Losses fall: the mean of the last tenth of the log is below the first tenth, per term.
    let (code, out, err) = ws.cmd(
        "show",
        &["train", "--table", "train_log", "--head", "1000000"],
    );
    assert_eq!(code, 0, "{out}{err}");
    let lines: Vec<&str> = out
        .lines()
        .skip_while(|l| !l.starts_with("iteration "))
        .collect();
    let header: Vec<&str> = lines[0].split_whitespace().collect();
    let rows: Vec<Vec<f64>> = lines[1..]
        .iter()
        .map(|l| {
            l.split_whitespace()
                .map(|v| v.parse().unwrap_or(f64::NAN))
                .collect()
        })
        .filter(|r: &Vec<f64>| r.len() == header.len())
        .collect();
    assert_eq!(rows.len(), 300, "{out}");
    let tenth = rows.len() / 10;
    for term in [
        "loss_total",
        "loss_fixed_2d",
        "loss_learned_2d",
        "loss_point_3d",
        "loss_rgb",
        "loss_depth",
    ] {
        let k = header.iter().position(|h| *h == term).expect(term);
        let first: Vec<f64> = rows[..tenth].iter().map(|r| r[k]).collect();
        let last: Vec<f64> = rows[rows.len() - tenth..].iter().map(|r| r[k]).collect();
        assert!(
            last.iter().all(|v| v.is_finite()),
            "{term} is not finite: {last:?}"
        );
        assert!(
            mean(&last) < 0.9 * mean(&first),
            "{term} did not fall: {} -> {}",
            mean(&first),
            mean(&last)
        );
    }

    let (code, out, err) = ws.cmd("export", &["evaluate", "--to", "eval"]);
    assert_eq!(code, 0, "{out}{err}");
    let m: serde_json::Value =
        serde_json::from_slice(&fs::read(ws.dir().join("eval/metrics.json")).unwrap()).unwrap();
    let ours = m["panoptic_nerf"]["acc"].as_f64().unwrap();
    let pseudo = m["pseudo_labels"]["acc"].as_f64().unwrap();
    let frames = m["panoptic_nerf"]["frames"].as_f64().unwrap();
    assert_eq!(frames, 6.0, "every training frame is evaluated");
    assert!(
        ours > pseudo,
        "fused labels' pixel accuracy {ours:.4} does not beat the pseudo labels' {pseudo:.4}: {m}"
    );
}
