//! The review finds wrong labels without GT: on a small synthetic scene where GT says which
//! labels are wrong, its score ranks them above the right ones better than the rendered
//! confidence alone, and what it exports (queue, regions, per-image figures, masks) agrees with
//! its tables.

mod common;

use std::fs;

use common::Workspace;

/// Every frame has GT (eval_every 1); the right camera has no pseudo labels.
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
  render:
    uses: render
    inputs: {scene: scene, rays: rays, train: train}
  review:
    uses: review
    inputs: {scene: scene, rays: rays, render: render}
  evaluate:
    uses: evaluate
    inputs: {scene: scene, render: render, review: review}
  report:
    uses: report
    inputs: {scene: scene, evaluate: evaluate, render: render, train: train, review: review}
";

fn csv(path: &std::path::Path) -> (Vec<String>, Vec<Vec<String>>) {
    let text = fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let header = lines.next().unwrap().split(',').map(String::from).collect();
    // No field of these tables holds a comma but `object`, which is quoted then.
    let rows = lines
        .map(|l| {
            let mut out = Vec::new();
            let mut cell = String::new();
            let mut quoted = false;
            for ch in l.chars() {
                match ch {
                    '"' => quoted = !quoted,
                    ',' if !quoted => out.push(std::mem::take(&mut cell)),
                    c => cell.push(c),
                }
            }
            out.push(cell);
            out
        })
        .collect();
    (header, rows)
}

#[test]
fn the_review_beats_the_confidence_and_exports_its_queue() {
    let ws = Workspace::new(PIPELINE);
    ws.run_ok(&[]);
    let (code, out, err) = ws.cmd("export", &["evaluate", "--to", "eval"]);
    assert_eq!(code, 0, "{out}{err}");
    let m: serde_json::Value =
        serde_json::from_slice(&fs::read(ws.dir().join("eval/metrics.json")).unwrap()).unwrap();
    let ours = &m["panoptic_nerf"];
    let get = |k: &str| {
        ours[k]
            .as_f64()
            .unwrap_or_else(|| panic!("metrics.json has no {k}: {ours}"))
    };
    // Every left image of the 6 frames (the right camera is not scored by default).
    assert_eq!(get("review_images"), 6.0);
    assert!(get("review_wrong_share") > 0.0);
    for k in ["auroc", "recall_5pct"] {
        let (r, c) = (get(&format!("review_{k}")), get(&format!("confidence_{k}")));
        assert!(
            r > c,
            "review {k} {r:.3} does not beat the confidence's {c:.3}"
        );
    }
    assert!(get("review_auroc") > 0.85, "{ours}");

    let (code, out, err) = ws.cmd("export", &["review", "--to", "review"]);
    assert_eq!(code, 0, "{out}{err}");
    let dir = ws.dir().join("review");
    let (header, frames) = csv(&dir.join("frames.csv"));
    assert_eq!(header[..4], ["sequence", "frame", "camera", "score"]);
    assert_eq!(frames.len(), 12, "one row per image, both cameras");
    let (header, regions) = csv(&dir.join("regions.csv"));
    let (header_q, queue) = csv(&dir.join("queue.csv"));
    assert!(!regions.is_empty() && !queue.is_empty());
    // The queue holds every listed region once, ranked by expected wrong pixels.
    let col = |h: &[String], name: &str| h.iter().position(|c| c == name).unwrap();
    let linked: usize = queue
        .iter()
        .map(|r| r[col(&header_q, "regions")].parse::<usize>().unwrap())
        .sum();
    assert_eq!(linked, regions.len());
    let expected: Vec<f64> = queue
        .iter()
        .map(|r| r[col(&header_q, "expected_wrong")].parse().unwrap())
        .collect();
    assert!(expected.windows(2).all(|w| w[0] >= w[1]), "{expected:?}");
    // A region's pixels in its image's mask are the region's size.
    let r0 = &regions[0];
    let name = format!(
        "{}_{:010}{}.png",
        r0[col(&header, "sequence")],
        r0[col(&header, "frame")].parse::<u32>().unwrap(),
        if r0[col(&header, "camera")] == "0" {
            ""
        } else {
            "_01"
        }
    );
    let mask = image::open(dir.join("regions").join(&name))
        .unwrap()
        .into_luma16();
    let index: u16 = r0[col(&header, "index")].parse().unwrap();
    let pixels = mask.pixels().filter(|p| p.0[0] == index).count();
    assert_eq!(pixels.to_string(), r0[col(&header, "pixels")]);
    for sub in ["score", "reason"] {
        assert!(dir.join(sub).join(&name).is_file(), "{sub}/{name}");
    }

    let (code, out, err) = ws.cmd("export", &["report", "--to", "report"]);
    assert_eq!(code, 0, "{out}{err}");
    let html = fs::read_to_string(ws.dir().join("report/report.html")).unwrap();
    for part in [
        "<h2>Review</h2>",
        "Review queue",
        "Top regions",
        "frame score",
    ] {
        assert!(html.contains(part), "the report lacks {part}");
    }
}
