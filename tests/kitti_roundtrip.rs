//! The KITTI-360 round trip through the real `pipe` binary. The tiny synthetic scene runs
//! through intersect -> train -> render -> evaluate; `pipe export scene` writes it in the
//! KITTI-360 layout (images, poses, calibration, bounding primitives, pseudo labels, GT, stereo
//! depth as 16-bit PNGs, LiDAR as velodyne scans with `calib_cam_to_velo.txt`); a second
//! pipeline loads that directory with `kitti360_scene` and runs the same stages. The loaded
//! tables must equal the synthetic ones and the metrics must agree within [`tolerance`]. A third run drives the shipped `pipelines/kitti360.yaml` (SGM `stereo_depth` instead
//! of the exported depth) on the same directory.
//!
//! Why the metrics are close but not bit-equal: the export writes ellipsoids (tree crowns) as
//! closed 16 x 8 meshes, as KITTI-360 stores every non-cuboid primitive, so the sampling
//! intervals of rays that graze a crown differ; the stereo depth is rounded to 1/256 m by its
//! PNG format; extruded polygons also come back as meshes, whose intersections round
//! differently in the last bits; poses and transforms come back to about 1e-12 m. The
//! untrained methods (pseudo labels, first-primitive projection) agree closely; the trained
//! ones are chaotic after 40 iterations and only their mIoU, Acc, depth and MC are compared.

mod common;

use std::fs;
use std::path::Path;

use common::Workspace;
use stages::scene::kitti360_export::{self, LIDAR_DEPTH_TOLERANCE, STEREO_DEPTH_TOLERANCE_M};

/// Largest allowed |synthetic - loaded| of a metric (scores are fractions: 0.01 = 1 point;
/// depth RMSE is in metres), or `None` where it is not compared. Measured on this scene (see
/// the module doc): `pseudo_labels` equal; `first_primitive` within 0.5 point (per-class IoU
/// within 5.4 points, MC within 2 points: tie flips between coincident sidewalk and terrain
/// tops); the trained methods (`panoptic_nerf`, `fixed_field`) after 40 iterations within 3.2
/// points mIoU and 4.7 points Acc, but their PQ, SQ, RQ and per-class IoU move by up to 37
/// points: at 40 iterations the fields are barely trained and training amplifies the tiny
/// input differences, so those are not compared.
fn tolerance(method: &str, metric: &str) -> Option<f64> {
    let trained = matches!(method, "panoptic_nerf" | "fixed_field");
    match metric {
        "frames" | "pixels" => Some(0.0),
        _ if method == "pseudo_labels" => Some(0.0),
        "miou" | "acc" if trained => Some(0.1),
        "depth_rmse" => Some(0.5),
        "depth_delta_1_25" | "mc" => Some(0.05),
        _ if trained => None,
        m if m.starts_with("class_iou.") => Some(0.1),
        _ => Some(0.01),
    }
}

/// intersect -> train -> render -> evaluate on the stage `scene`.
const DOWNSTREAM: &str = "
  rays:
    uses: intersect
    inputs: {scene: scene}
  train:
    uses: train
    inputs: {scene: scene, rays: rays}
    params:
      schedule: {iterations: 40, rays_per_batch: 256}
  render:
    uses: render
    inputs: {scene: scene, rays: rays, train: train}
  evaluate:
    uses: evaluate
    inputs: {scene: scene, render: render}
";

const SEQUENCE: &str = "2099_01_01_drive_0000_sync";

fn synthetic_pipeline() -> String {
    format!(
        "stages:
  scene:
    uses: synthetic_scene
    params: {{frames: 6, eval_every: 2, scale: 0.0625}}
{DOWNSTREAM}"
    )
}

/// `kitti360_scene` reading everything the export wrote. `origin` is the synthetic scene's, so
/// the recentred coordinates (and the field's inputs) are the same; no primitive is culled.
fn kitti_pipeline(root: &Path, origin: [f64; 3]) -> String {
    format!(
        "stages:
  scene:
    uses: kitti360_scene
    params:
      root: '{}'
      sequence: {SEQUENCE}
      first_frame: 20
      last_frame: 25
      eval_every: 2
      origin: [{}, {}, {}]
      stereo_depth: '{}'
      lidar: '{}'
      max_distance_m: 1000
{DOWNSTREAM}",
        root.display(),
        origin[0],
        origin[1],
        origin[2],
        stages::scene::kitti360::STEREO_DEPTH_PATTERN,
        stages::scene::kitti360::LIDAR_PATTERN,
    )
}

/// The tables of `stage`'s last run, read from the cache.
fn tables(ws: &Workspace, stage: &str) -> stages::Tables {
    let store = pipe::store::Store::open_existing(&ws.cache());
    let pipe::store::Entry::Valid(m) = store.check(&ws.stage_key(stage), true) else {
        panic!("entry of {stage} not valid")
    };
    store.load(&m).unwrap()
}

/// `metrics.json` of the evaluate stage.
fn metrics(ws: &Workspace, stage: &str) -> serde_json::Value {
    let (code, out, err) = ws.cmd("export", &[stage, "--to", "eval"]);
    assert_eq!(code, 0, "{out}{err}");
    serde_json::from_slice(&fs::read(ws.dir().join("eval/metrics.json")).unwrap()).unwrap()
}

/// `metrics.json` less what only a scene with an exact depth has: the `exact_depth` rows and
/// the `*_exact` and `*_exact_interior` metrics, everywhere in the tree.
fn without_exact_depth(v: &mut serde_json::Value) {
    if let serde_json::Value::Object(m) = v {
        m.retain(|k, _| {
            k != "exact_depth" && !k.ends_with("_exact") && !k.ends_with("_exact_interior")
        });
        m.values_mut().for_each(without_exact_depth);
    }
}

/// Every number of two metrics.json trees, as (path, a, b); nulls must match.
fn pairs(
    path: &str,
    a: &serde_json::Value,
    b: &serde_json::Value,
    out: &mut Vec<(String, f64, f64)>,
) {
    use serde_json::Value::{Number, Object};
    match (a, b) {
        (Object(x), Object(y)) => {
            let keys: Vec<&std::string::String> = x.keys().collect();
            assert_eq!(keys, y.keys().collect::<Vec<_>>(), "{path}: keys differ");
            for k in keys {
                pairs(&format!("{path}.{k}"), &x[k], &y[k], out);
            }
        }
        (Number(x), Number(y)) => out.push((path.into(), x.as_f64().unwrap(), y.as_f64().unwrap())),
        // Rows (the depth breakdown's): keyed by their `group` and `bin`.
        (serde_json::Value::Array(x), serde_json::Value::Array(y)) => {
            let keyed = |v: &Vec<serde_json::Value>| -> serde_json::Value {
                v.iter()
                    .enumerate()
                    .map(|(i, r)| match (r["group"].as_str(), r["bin"].as_str()) {
                        (Some(g), Some(b)) => (format!("{g}/{b}"), r.clone()),
                        _ => (i.to_string(), r.clone()),
                    })
                    .collect::<serde_json::Map<_, _>>()
                    .into()
            };
            pairs(path, &keyed(x), &keyed(y), out);
        }
        (x, y) => assert_eq!(x, y, "{path}"),
    }
}

#[test]
fn the_exported_synthetic_scene_runs_through_the_pipeline_with_the_same_metrics() {
    let t0 = std::time::Instant::now();
    let synth = Workspace::new(&synthetic_pipeline());
    synth.run_ok(&[]);
    let root = synth.dir().join("k360");
    let (code, out, err) = synth.cmd("export", &["scene", "--to", root.to_str().unwrap()]);
    assert_eq!(code, 0, "{out}{err}");
    for f in [
        "calibration/calib_cam_to_velo.txt",
        "data_3d_raw/2099_01_01_drive_0000_sync/velodyne_points/data/0000000022.bin",
        "stereo_depth/2099_01_01_drive_0000_sync/image_00/0000000025.png",
        "data_2d_semantics/train/2099_01_01_drive_0000_sync/image_01/instance/0000000024.png",
    ] {
        assert!(root.join(f).exists(), "the export lacks {f}");
    }
    let a = tables(&synth, "scene");
    let origin = stages::scene::io::scene_info(&a).unwrap().origin.to_array();

    let kitti = Workspace::new(&kitti_pipeline(&root, origin));
    kitti.run_ok(&[]);
    let b = tables(&kitti, "scene");

    // The loaded scene: byte-equal images, labels, cameras' table shape; depth within the
    // export's tolerances (the unit tests in stages compare cameras and primitives closely).
    for name in ["images", "pseudo_labels", "gt_semantic", "gt_instance"] {
        assert_eq!(a[name], b[name], "table {name} differs");
    }
    assert_eq!(a["cameras"].num_rows(), b["cameras"].num_rows());
    assert_eq!(a["primitives"].num_rows(), b["primitives"].num_rows());
    let stereo = kitti360_export::depth_difference(&a, &b, "stereo_depth").unwrap();
    let lidar = kitti360_export::depth_difference(&a, &b, "lidar_depth").unwrap();
    eprintln!("stereo depth {stereo:?}\nLiDAR depth {lidar:?}");
    assert!(stereo.pixels > 0 && stereo.max_abs <= STEREO_DEPTH_TOLERANCE_M);
    assert!(lidar.pixels > 0 && lidar.max_rel <= LIDAR_DEPTH_TOLERANCE);

    // The metrics.
    let (mut ma, mut mb) = (metrics(&synth, "evaluate"), metrics(&kitti, "evaluate"));
    // The KITTI-360 layout carries no exact depth: the synthetic scene's scores against it are
    // its own (and null on the reloaded scene).
    assert!(ma["exact_depth"]["depth_rmse"].is_number(), "{ma}");
    assert!(mb["panoptic_nerf"]["depth_rmse_exact"].is_null(), "{mb}");
    without_exact_depth(&mut ma);
    without_exact_depth(&mut mb);
    let mut all = Vec::new();
    pairs("", &ma, &mb, &mut all);
    assert!(all.len() > 50, "{ma}");
    let mut failures = Vec::new();
    for (path, x, y) in &all {
        let (method, metric) = path[1..].split_once('.').unwrap();
        let d = (x - y).abs();
        let tol = match method {
            // Per camera model: the method's own tolerances.
            "by_camera_model" => {
                let (_, rest) = metric.split_once('.').unwrap();
                let (method, metric) = rest.split_once('.').unwrap();
                tolerance(method, metric)
            }
            // Ours' depth per bin: the LiDAR pixels in each bin agree to a pixel or two (a
            // point on a primitive's face may land either side after the export's 1e-7
            // rounding); the errors are those of a trained field (the `all` bin is
            // `depth_rmse`, compared above).
            "depth_breakdown" if metric.ends_with(".pixels") => Some(2.0),
            "depth_breakdown" => None,
            _ => tolerance(method, metric),
        };
        eprintln!("{path}: synthetic {x:.6} loaded {y:.6} (diff {d:.2e}, tolerance {tol:?})");
        if tol.is_some_and(|t| d > t) {
            failures.push(format!(
                "{path}: synthetic {x} vs loaded {y} (tolerance {tol:?})"
            ));
        }
    }
    // The pseudo labels and GT are byte-equal, so their scores are exactly equal (tolerance 0).
    assert!(failures.is_empty(), "{failures:#?}");
    eprintln!(
        "kitti round trip: {} metrics compared in {:.1} s",
        all.len(),
        t0.elapsed().as_secs_f64()
    );

    // The shipped pipelines/kitti360.yaml on the same directory: SGM depth, then to the report.
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("pipelines/kitti360.yaml");
    let sets = [
        format!("scene.root={}", root.display()),
        format!("scene.sequence={SEQUENCE}"),
        "scene.first_frame=20".into(),
        "scene.last_frame=25".into(),
        "scene.eval_every=2".into(),
        format!("scene.lidar={}", stages::scene::kitti360::LIDAR_PATTERN),
        "depth.max_disparity=48".into(),
        "train.schedule={iterations: 40, rays_per_batch: 256}".into(),
    ];
    let mut args = vec![
        "-f".to_string(),
        file.display().to_string(),
        "--cache".into(),
        kitti.dir().join("shipped").display().to_string(),
    ];
    for s in &sets {
        args.extend(["--set".into(), s.clone()]);
    }
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    kitti.run_ok(&args);
    let eval = kitti.dir().join("eval-shipped");
    let mut export = vec!["evaluate", "--to", eval.to_str().unwrap()];
    export.extend(&args);
    let (code, out, err) = kitti.cmd("export", &export);
    assert_eq!(code, 0, "{out}{err}");
    let mc: serde_json::Value =
        serde_json::from_slice(&fs::read(eval.join("metrics.json")).unwrap()).unwrap();
    let miou = |m: &serde_json::Value| m["panoptic_nerf"]["miou"].as_f64().unwrap();
    eprintln!(
        "shipped kitti360.yaml (SGM depth): mIoU {:.4} vs {:.4} with the synthetic stereo depth",
        miou(&mc),
        miou(&ma)
    );
    assert!(mc["panoptic_nerf"]["depth_rmse"].is_number(), "{mc}");

    // Most of KITTI-360 has no 2D GT: the same shipped file, the GT directory gone, runs to the
    // report, says plainly that nothing was evaluated, and exports the rendered labels of every
    // image in the KITTI-360 layout.
    fs::remove_dir_all(root.join("data_2d_semantics")).unwrap();
    kitti.run_ok(&args);
    let no_gt = kitti.dir().join("no-gt");
    for stage in ["evaluate", "render", "report"] {
        let dir = no_gt.join(stage);
        let mut export = vec![stage, "--to", dir.to_str().unwrap()];
        export.extend(&args);
        let (code, out, err) = kitti.cmd("export", &export);
        assert_eq!(code, 0, "export {stage}: {out}{err}");
    }
    let m: serde_json::Value =
        serde_json::from_slice(&fs::read(no_gt.join("evaluate/metrics.json")).unwrap()).unwrap();
    assert!(
        m["not_evaluated"]
            .as_str()
            .unwrap()
            .contains("no evaluation frame with GT"),
        "{m}"
    );
    assert_eq!(m["panoptic_nerf"]["frames"], 0.0, "{m}");
    assert!(m["panoptic_nerf"]["miou"].is_null(), "{m}");
    let report = fs::read_to_string(no_gt.join("report/REPORT.md")).unwrap();
    assert!(report.contains("## Not evaluated"), "{report}");
    let html = fs::read_to_string(no_gt.join("report/report.html")).unwrap();
    assert!(
        html.contains("Rendered frames (no GT)") && html.contains("<img"),
        "{html}"
    );
    let labels = no_gt.join(format!("render/data_2d_semantics/train/{SEQUENCE}"));
    for frame in 20..=25 {
        for cam in ["image_00", "image_01"] {
            for sub in ["semantic", "semantic_rgb", "instance"] {
                let f = labels.join(format!("{cam}/{sub}/{frame:010}.png"));
                assert!(f.exists(), "{} missing", f.display());
            }
        }
    }
    eprintln!("total {:.1} s", t0.elapsed().as_secs_f64());
}
