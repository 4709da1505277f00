//! The whole pipeline on a tiny synthetic scene: scene -> rays -> train -> render -> evaluate
//! -> report, then the exported files: metrics.json must agree with the PNGs it was computed
//! from (recomputed here from the files alone), and the report must exist.

mod common;

use std::{collections::BTreeMap, fs, path::Path};

use common::{Outcome, Workspace};

fn gray8(path: &Path) -> Vec<u8> {
    image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .into_luma8()
        .into_raw()
}

#[test]
fn tiny_pipeline_runs_and_its_metrics_match_its_files() {
    let ws = Workspace::new(common::TINY_PIPELINE);
    ws.run_ok(&[]);
    assert!(ws.last_run().iter().all(|(_, o)| *o == Outcome::Ran));

    let (code, out, err) = ws.cmd("export", &["evaluate", "--to", "eval"]);
    assert_eq!(code, 0, "{out}{err}");
    let (code, out, err) = ws.cmd("export", &["render", "--to", "render"]);
    assert_eq!(code, 0, "{out}{err}");
    let (code, out, err) = ws.cmd("export", &["report", "--to", "report"]);
    assert_eq!(code, 0, "{out}{err}");
    assert!(
        fs::metadata(ws.dir().join("report/report.html"))
            .unwrap()
            .len()
            > 10_000
    );
    assert!(fs::read_to_string(ws.dir().join("report/REPORT.md"))
        .unwrap()
        .contains("| Panoptic NeRF (ours) |"));

    let metrics: serde_json::Value =
        serde_json::from_slice(&fs::read(ws.dir().join("eval/metrics.json")).unwrap()).unwrap();
    for m in [
        "panoptic_nerf",
        "fixed_field",
        "pseudo_labels",
        "first_primitive",
    ] {
        assert!(metrics[m]["miou"].is_number(), "{m} has no mIoU: {metrics}");
        assert!(
            metrics[m]["class_iou"]["road"].is_number(),
            "{m}: {metrics}"
        );
    }

    // Recompute our mIoU from the exported PNGs alone.
    let gt_dir = ws.dir().join("eval/gt/semantic");
    let mut files: Vec<_> = fs::read_dir(&gt_dir)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    files.sort();
    assert!(!files.is_empty());
    let mut conf = stages::metrics::ConfusionMatrix::new(stages::labels::PAPER_CLASSES).unwrap();
    for f in &files {
        let gt = gray8(&gt_dir.join(f));
        let ours = gray8(&ws.dir().join("render/semantic").join(f));
        conf.add(&gt, &ours).unwrap();
        for sub in ["semantic_rgb", "instance", "panoptic_rgb", "depth"] {
            assert!(
                ws.dir().join("render").join(sub).join(f).exists(),
                "render/{sub}/{f:?}"
            );
        }
        // Colour is rendered for novel views only, by default.
        assert!(
            !ws.dir().join("render/rgb").join(f).exists(),
            "render/rgb/{f:?}"
        );
    }
    let from_files = conf.miou().unwrap();
    let reported = metrics["panoptic_nerf"]["miou"].as_f64().unwrap();
    assert!(
        (from_files - reported).abs() < 1e-9,
        "metrics.json says {reported}, the PNGs give {from_files}"
    );

    // Depth against the scene's exact depth (every pixel of the evaluated images with an exact
    // depth in (0, 100) m, no rendered depth counting as 0 m), and that exact depth against the
    // LiDAR, recomputed from the cached tables.
    let eval_keys = image_widths(&ws);
    let depth = frame_camera_rows(&ws, "render", "label_maps", Some("depth"));
    let exact = frame_camera_rows(&ws, "scene", "gt_depth", Some("depth"));
    let lidar = frame_camera_rows(&ws, "scene", "lidar_depth", Some("depth"));
    let gt_semantic = frame_camera_rows(&ws, "scene", "gt_semantic", Some("labels"));
    let pseudo = frame_camera_rows(&ws, "scene", "pseudo_labels", Some("labels"));
    let (mut ours_sq, mut ours_n, mut floor_sq, mut floor_n) = (0f64, 0u64, 0f64, 0u64);
    let (mut inside_sq, mut inside_n) = (0f64, 0u64);
    // The depth breakdown's LiDAR pixels on a class boundary whose pseudo label is wrong.
    let (mut wrong_sq, mut wrong_n) = (0f64, 0u64);
    for (key, &width) in &eval_keys {
        let e = &exact[key];
        // Off a class boundary: all 8 neighbours (inside the image) have the pixel's GT class.
        let sem = &gt_semantic[key];
        let (w, h) = (width as i64, (sem.len() / width) as i64);
        let inside = |i: usize| {
            let (x, y) = (i as i64 % w, i as i64 / w);
            (-1..=1).all(|dy| {
                (-1..=1).all(|dx| {
                    let (nx, ny) = (x + dx, y + dy);
                    !(0..w).contains(&nx)
                        || !(0..h).contains(&ny)
                        || sem[(ny * w + nx) as usize] == sem[i]
                })
            })
        };
        for (i, (&d, &g)) in depth[key].iter().zip(e).enumerate() {
            if g > 0.0 && g < 100.0 {
                ours_sq += (d as f64 - g as f64).powi(2);
                ours_n += 1;
                if inside(i) {
                    inside_sq += (d as f64 - g as f64).powi(2);
                    inside_n += 1;
                }
            }
        }
        for (i, (&g, &l)) in e
            .iter()
            .zip(lidar.get(key).into_iter().flatten())
            .enumerate()
        {
            if l > 0.0 && l < 100.0 {
                floor_sq += (g as f64 - l as f64).powi(2);
                floor_n += 1;
                let p = pseudo.get(key).map_or(0.0, |p| p[i]);
                if p != 0.0 && p != sem[i] && !inside(i) {
                    let d = depth[key][i];
                    let d = if d.is_finite() { d as f64 } else { 0.0 };
                    wrong_sq += (d - l as f64).powi(2);
                    wrong_n += 1;
                }
            }
        }
    }
    let wrong = metrics["depth_breakdown"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["group"] == "pseudo label" && r["bin"] == "wrong, on a class boundary")
        .expect("the breakdown has the wrong-pseudo-label boundary bin");
    assert!(wrong_n > 0);
    assert_eq!(wrong["pixels"].as_u64().unwrap(), wrong_n, "{wrong}");
    let rmse = (wrong_sq / wrong_n as f64).sqrt();
    assert!(
        (wrong["rmse"].as_f64().unwrap() - rmse).abs() < 1e-6,
        "{wrong} vs {rmse}"
    );
    assert!(ours_n > 0 && floor_n > 0 && inside_n > 0 && inside_n < ours_n);
    for (method, metric, expected) in [
        (
            "panoptic_nerf",
            "depth_rmse_exact",
            (ours_sq / ours_n as f64).sqrt(),
        ),
        (
            "panoptic_nerf",
            "depth_rmse_exact_interior",
            (inside_sq / inside_n as f64).sqrt(),
        ),
        (
            "exact_depth",
            "depth_rmse",
            (floor_sq / floor_n as f64).sqrt(),
        ),
    ] {
        let got = metrics[method][metric].as_f64().unwrap();
        assert!(
            (got - expected).abs() < 1e-6,
            "{method} {metric}: {got} vs {expected}"
        );
    }

    // A second run is all cache hits.
    ws.run_ok(&[]);
    assert!(ws.last_run().iter().all(|(_, o)| *o == Outcome::Cached));
    // Training again with the same seed and config writes the same bytes (no clock in its
    // tables), so nothing downstream of it re-runs.
    ws.run_ok(&["--force", "train"]);
    let r = ws.last_run_map();
    assert_eq!(r["train"], Outcome::Ran);
    for stage in ["render", "evaluate", "report"] {
        assert_eq!(
            r[stage],
            Outcome::Cached,
            "{stage} after a same-seed re-train"
        );
    }

    // The median depth: written where the expected depth is (opacity 0.5, up to rays at
    // exactly 0.5), one sample's distance where the weight is split.
    ws.run_ok(&["--until", "render", "--set", "render.depth=median"]);
    let median = frame_camera_rows(&ws, "render", "label_maps", Some("depth"));
    let (mut both, mut one, mut differ) = (0usize, 0usize, 0usize);
    for (key, m) in &median {
        for (&a, &b) in depth[key].iter().zip(m) {
            match (a > 0.0, b > 0.0) {
                (true, true) => {
                    both += 1;
                    differ += usize::from((a - b).abs() > 1e-3 * a);
                }
                (false, false) => {}
                _ => one += 1,
            }
        }
    }
    assert!(both > 0 && one * 1000 <= both, "{one} of {both} pixels");
    assert!(differ > 0, "median and expected depth agree everywhere");

    // Adaptive rendering (the default: a coarse grid first, the rest where it disagrees) gives
    // the labels of rendering every pixel, but for details finer than its cells.
    let every = "render.coarse_stride=1";
    ws.run_ok(&["--until", "render", "--set", every]);
    let (code, out, err) = ws.cmd("export", &["render", "--to", "every", "--set", every]);
    assert_eq!(code, 0, "{out}{err}");
    let (mut pixels, mut differ) = (0usize, 0usize);
    for f in fs::read_dir(ws.dir().join("every/instance")).unwrap() {
        let f = f.unwrap().file_name();
        let a = gray16(&ws.dir().join("render/instance").join(&f));
        let b = gray16(&ws.dir().join("every/instance").join(&f));
        assert_eq!(a.len(), b.len());
        pixels += a.len();
        differ += a.iter().zip(&b).filter(|(x, y)| x != y).count();
    }
    assert!(pixels > 0);
    let share = differ as f64 / pixels as f64;
    assert!(
        share < ADAPTIVE_DIFFERENCE,
        "{differ} of {pixels} panoptic labels differ"
    );
}

/// Rows of `stage`'s cached table `table` by (frame, camera): the float32 list column `column`,
/// or nothing.
fn frame_camera_rows(
    ws: &Workspace,
    stage: &str,
    table: &str,
    column: Option<&str>,
) -> BTreeMap<(u32, u8), Vec<f32>> {
    use arrow::array::AsArray;
    use arrow::datatypes::{Float32Type, UInt32Type, UInt8Type};
    let path = ws
        .cache()
        .join("objects")
        .join(ws.stage_key(stage))
        .join(format!("{table}.parquet"));
    let file = fs::File::open(&path).unwrap();
    let reader = parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(file)
        .unwrap()
        .build()
        .unwrap();
    let mut rows = BTreeMap::new();
    for batch in reader {
        let b = batch.unwrap();
        let frame = b
            .column_by_name("frame")
            .unwrap()
            .as_primitive::<UInt32Type>();
        let camera = b
            .column_by_name("camera")
            .unwrap()
            .as_primitive::<UInt8Type>();
        for i in 0..b.num_rows() {
            let values = column.map_or_else(Vec::new, |c| {
                let list = b.column_by_name(c).unwrap().as_list::<i32>().value(i);
                let list =
                    arrow::compute::cast(&list, &arrow::datatypes::DataType::Float32).unwrap();
                list.as_primitive::<Float32Type>().values().to_vec()
            });
            rows.insert((frame.value(i), camera.value(i)), values);
        }
    }
    rows
}

/// The width of every evaluated image, by (frame, camera), from the `eval_gt` table.
fn image_widths(ws: &Workspace) -> BTreeMap<(u32, u8), usize> {
    use arrow::array::AsArray;
    use arrow::datatypes::{UInt32Type, UInt8Type};
    let path = ws
        .cache()
        .join("objects")
        .join(ws.stage_key("evaluate"))
        .join("eval_gt.parquet");
    let reader = parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(
        fs::File::open(&path).unwrap(),
    )
    .unwrap()
    .build()
    .unwrap();
    let mut widths = BTreeMap::new();
    for batch in reader {
        let b = batch.unwrap();
        let col = |name: &str| b.column_by_name(name).unwrap().clone();
        let (frame, camera, width) = (col("frame"), col("camera"), col("width"));
        for i in 0..b.num_rows() {
            widths.insert(
                (
                    frame.as_primitive::<UInt32Type>().value(i),
                    camera.as_primitive::<UInt8Type>().value(i),
                ),
                width.as_primitive::<UInt32Type>().value(i) as usize,
            );
        }
    }
    widths
}

/// Largest share of panoptic labels in which adaptive rendering may differ from rendering every
/// pixel on the tiny scene (0.05-0.1 % at full size, where a cell is a smaller detail).
const ADAPTIVE_DIFFERENCE: f64 = 0.01;

fn gray16(path: &Path) -> Vec<u16> {
    image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .into_luma16()
        .into_raw()
}

/// A novel view (a scene camera moved and turned) is rendered beside the scene's images, and
/// its labels differ from the camera it came from but still show the street.
#[test]
fn novel_views_are_rendered_and_exported() {
    let ws = Workspace::new(common::TINY_PIPELINE);
    let view = "render.novel_views=[{frame: 20, camera: 0, translate: [1.0, 0, 2.0], yaw_deg: 8}]";
    ws.run_ok(&["--until", "render", "--set", view]);
    let (code, out, err) = ws.cmd("export", &["render", "--to", "render", "--set", view]);
    assert_eq!(code, 0, "{out}{err}");
    let dir = ws.dir().join("render/semantic");
    let seq = fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .find(|n| n.ends_with("_0000000020.png"))
        .expect("frame 20 of the scene")
        .trim_end_matches("_0000000020.png")
        .to_string();
    let novel = gray8(&dir.join(format!("{seq}_0000000020_10.png")));
    // The novel view is rendered in colour (the default `colour: novel_views`).
    let rgb = image::open(ws.dir().join(format!("render/rgb/{seq}_0000000020_10.png")))
        .unwrap()
        .to_rgb8();
    assert_eq!(rgb.len(), novel.len() * 3);
    assert!(
        rgb.pixels().any(|p| p.0 != rgb.get_pixel(0, 0).0),
        "the colour map is not one flat colour"
    );
    let original = gray8(&dir.join(format!("{seq}_0000000020.png")));
    assert_eq!(novel.len(), original.len());
    let differ = novel.iter().zip(&original).filter(|(a, b)| a != b).count();
    assert!(
        differ * 20 > novel.len(),
        "the moved camera sees the same labels"
    );
    let road = novel.iter().filter(|&&l| l == 7).count();
    let sky = novel.iter().filter(|&&l| l == 23).count();
    assert!(
        road * 20 > novel.len() && sky * 20 > novel.len(),
        "road {road}, sky {sky}"
    );
    // A view of a frame the scene does not have is a parameter error naming it.
    let (code, _, err) = ws.run(&[
        "--until",
        "render",
        "--set",
        "render.novel_views=[{frame: 999, camera: 0}]",
    ]);
    assert_ne!(code, 0);
    assert!(
        err.contains("novel_views[0]") && err.contains("frame 999"),
        "{err}"
    );
}

/// The GPU path through the whole pipeline (in CI on Mesa's llvmpipe, a Vulkan driver on the
/// CPU): the tiny scene trained with `backend: wgpu` and rendered (on wgpu too: rendering follows
/// a GPU training engine) gives the fused CPU engine's losses and labels. Tolerances: every
/// logged loss of the first 10 steps within 1e-3 relative (float sums in another order, and
/// llvmpipe flushes subnormals), and at least 97 % of the evaluated pixels with the same label
/// after 40 steps (training amplifies those differences a little every step).
#[cfg(feature = "wgpu")]
#[test]
fn the_wgpu_backend_trains_and_renders_like_the_cpu() {
    use stages::model::{burn::Backend, Engine};
    if !Engine::usable().contains(&Engine::Burn(Backend::Wgpu)) {
        return; // Engine::usable said why; under CI=true it panics instead
    }
    let runs: Vec<(Workspace, Vec<f32>, Vec<Vec<u8>>)> = ["fused", "wgpu"]
        .iter()
        .map(|engine| {
            let ws = Workspace::new(common::TINY_PIPELINE);
            let set = format!("train.backend={engine}");
            ws.run_ok(&["--until", "render", "--set", &set]);
            let (code, out, err) = ws.cmd(
                "show",
                &[
                    "train",
                    "--table",
                    "train_log",
                    "--head",
                    "10",
                    "--set",
                    &set,
                ],
            );
            assert_eq!(code, 0, "{out}{err}");
            let losses = losses_of(&out);
            let (code, out, err) = ws.cmd("export", &["render", "--to", "render", "--set", &set]);
            assert_eq!(code, 0, "{out}{err}");
            let dir = ws.dir().join("render/semantic");
            let mut files: Vec<_> = fs::read_dir(&dir)
                .unwrap()
                .map(|e| e.unwrap().path())
                .collect();
            files.sort();
            let maps = files.iter().map(|f| gray8(f)).collect();
            (ws, losses, maps)
        })
        .collect();
    let (cpu, gpu) = (&runs[0], &runs[1]);
    assert_eq!(cpu.1.len(), 10);
    for (i, (a, b)) in cpu.1.iter().zip(&gpu.1).enumerate() {
        assert!(
            (a - b).abs() <= 1e-3 * a.abs(),
            "step {i}: loss {a} (fused) vs {b} (wgpu)"
        );
    }
    let (mut same, mut all) = (0usize, 0usize);
    for (a, b) in cpu.2.iter().zip(&gpu.2) {
        assert_eq!(a.len(), b.len());
        same += a.iter().zip(b).filter(|(x, y)| x == y).count();
        all += a.len();
    }
    assert!(
        all > 0 && same * 100 >= all * 97,
        "{same} of {all} pixels agree"
    );
}

/// The `loss_total` column of `pipe show train --table train_log` output.
#[cfg(feature = "wgpu")]
fn losses_of(show: &str) -> Vec<f32> {
    let mut lines = show
        .lines()
        .skip_while(|l| !l.split_whitespace().any(|w| w == "iteration"));
    let header: Vec<&str> = lines.next().unwrap_or("").split_whitespace().collect();
    let col = header
        .iter()
        .position(|h| *h == "loss_total")
        .expect("a `loss_total` column");
    lines
        .filter_map(|l| l.split_whitespace().nth(col)?.parse().ok())
        .collect()
}

/// The side fisheye cameras through the pipeline: listed once, in the scene, they are planned,
/// trained on (colour and their pseudo labels), rendered (unlabelled and black outside the lens
/// circle) and evaluated; a stage may still narrow the cameras (here evaluate).
#[test]
fn fisheye_cameras_are_trained_rendered_and_evaluated() {
    let ws = Workspace::new(common::TINY_PIPELINE);
    let sets = [
        "scene.cameras=[image_00, image_01, image_02, image_03]",
        "scene.fisheye_pseudo_labels=true",
        "evaluate.cameras=[2, 3]",
    ];
    let args: Vec<&str> = sets.iter().flat_map(|s| ["--set", *s]).collect();
    ws.run_ok(&args);
    let mut export = vec!["render", "--to", "render"];
    export.extend(&args);
    let (code, out, err) = ws.cmd("export", &export);
    assert_eq!(code, 0, "{out}{err}");
    let seq = "2099_01_01_drive_0000_sync";
    let path = ws
        .dir()
        .join(format!("render/semantic/{seq}_0000000020_02.png"));
    let img = image::open(&path).unwrap().into_luma8();
    let (w, h) = img.dimensions();
    assert_eq!((w, h), (88, 88));
    for (x, y) in [(0, 0), (w - 1, 0), (0, h - 1), (w - 1, h - 1)] {
        assert_eq!(
            img.get_pixel(x, y)[0],
            0,
            "corner ({x}, {y}) is outside the lens"
        );
    }
    let inside = img.pixels().filter(|p| p[0] != 0).count();
    assert!(
        inside * 10 > (w * h) as usize * 7,
        "{inside} labelled pixels"
    );
    let mut ev = vec!["evaluate", "--to", "eval"];
    ev.extend(&args);
    let (code, out, err) = ws.cmd("export", &ev);
    assert_eq!(code, 0, "{out}{err}");
    let metrics: serde_json::Value =
        serde_json::from_slice(&fs::read(ws.dir().join("eval/metrics.json")).unwrap()).unwrap();
    let fisheye_only = metrics["panoptic_nerf"].clone();
    assert!(fisheye_only["miou"].as_f64().unwrap() > 0.0, "{metrics}");

    // One evaluation of both camera models, by default (the scene's evaluation images: every
    // camera but the right one): per-model scores equal separate evaluations, the pixels add up,
    // and labels agree across the models (cross-view MC).
    let both: Vec<&str> = args[..args.len() - 2].to_vec();
    ws.run_ok(&both);
    let mut ev = vec!["evaluate", "--to", "eval_both"];
    ev.extend(&both);
    let (code, out, err) = ws.cmd("export", &ev);
    assert_eq!(code, 0, "{out}{err}");
    let m: serde_json::Value =
        serde_json::from_slice(&fs::read(ws.dir().join("eval_both/metrics.json")).unwrap())
            .unwrap();
    let by = &m["by_camera_model"];
    for key in ["miou", "acc", "pq", "pixels", "frames", "class_iou"] {
        assert_eq!(
            by["fisheye"]["panoptic_nerf"][key], fisheye_only[key],
            "{key}: {by}"
        );
    }
    assert!(
        by["fisheye"]["panoptic_nerf"]["class_iou"]["road"].is_number(),
        "{by}"
    );
    let px = |v: &serde_json::Value| v["pixels"].as_f64().unwrap();
    assert_eq!(
        px(&by["fisheye"]["panoptic_nerf"]) + px(&by["perspective"]["panoptic_nerf"]),
        px(&m["panoptic_nerf"]),
        "{m}"
    );
    assert!(
        by["perspective"]["panoptic_nerf"]["frames"]
            .as_f64()
            .unwrap()
            > 0.0
    );
    for method in ["panoptic_nerf", "first_primitive"] {
        let mc = by["perspective_fisheye"][method]["mc"].as_f64().unwrap();
        assert!(mc > 0.5 && mc <= 1.0, "{method} cross-view MC {mc}");
    }

    // The depth breakdown: its `all` bin is the depth RMSE, every group covers the same LiDAR
    // pixels, and the shares of the squared error add up to 1 within each group.
    let rows = m["depth_breakdown"].as_array().unwrap();
    let all = rows.iter().find(|r| r["group"] == "all").unwrap();
    let rmse = m["panoptic_nerf"]["depth_rmse"].as_f64().unwrap();
    assert!(
        (all["rmse"].as_f64().unwrap() - rmse).abs() < 1e-9,
        "{all} vs {rmse}"
    );
    let n = all["pixels"].as_u64().unwrap();
    assert!(n > 0);
    for group in [
        "distance",
        "class",
        "boundary",
        "rendered",
        "fixed field",
        "pseudo label",
    ] {
        let bins: Vec<_> = rows.iter().filter(|r| r["group"] == group).collect();
        let px: u64 = bins.iter().map(|r| r["pixels"].as_u64().unwrap()).sum();
        let share: f64 = bins
            .iter()
            .map(|r| r["share_sq_error"].as_f64().unwrap())
            .sum();
        assert_eq!(px, n, "{group}");
        assert!((share - 1.0).abs() < 1e-9, "{group}: {share}");
    }
    let interior = m["panoptic_nerf"]["depth_rmse_interior"].as_f64().unwrap();
    let inside = rows.iter().find(|r| r["bin"] == "inside a region").unwrap();
    assert!((inside["rmse"].as_f64().unwrap() - interior).abs() < 1e-9);

    // The report shows the per-model table and pictures of fisheye frames.
    let mut rep = vec!["report", "--to", "report"];
    rep.extend(&both);
    let (code, out, err) = ws.cmd("export", &rep);
    assert_eq!(code, 0, "{out}{err}");
    let html = fs::read_to_string(ws.dir().join("report/report.html")).unwrap();
    assert!(html.contains("Per camera model"));
    assert!(html.contains("Per-class IoU per camera model") && html.contains("<th>fisheye: "));
    assert!(html.contains("Depth error breakdown") && html.contains("alt=\"depth error\""));
    assert!(html.contains("cam 2</td>") && html.contains("cam 3</td>"));
}

/// The shipped `pipelines/fisheye.yaml`, shrunk: the fisheye cameras get their depth from
/// motion stereo (the left camera keeps the scene's), training reads it, and `evaluate.frames`
/// scores only the frames asked for (a frame the scene does not evaluate is an error naming it).
#[test]
fn fisheye_pipeline_gets_motion_stereo_depth_and_evaluates_chosen_frames() {
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("pipelines/fisheye.yaml");
    let ws = Workspace::new(&fs::read_to_string(file).unwrap());
    let sets = [
        "scene.frames=6",
        "scene.eval_every=2",
        "scene.scale=0.0625",
        "train.schedule.iterations=40",
        "train.schedule.rays_per_batch=256",
    ];
    let mut args: Vec<&str> = sets.iter().flat_map(|s| ["--set", *s]).collect();
    ws.run_ok(&args);
    let mut show = vec!["fisheye_depth", "--head", "20"];
    show.extend(&args);
    let (code, out, err) = ws.cmd("show", &show);
    assert_eq!(code, 0, "{out}{err}");
    // 6 frames: 6 left rows kept and 12 fisheye rows added.
    assert!(out.contains("18 rows"), "{out}");
    let metrics = |ws: &Workspace, args: &[&str]| -> serde_json::Value {
        let mut ev = vec!["evaluate", "--to", "eval"];
        ev.extend(args);
        let (code, out, err) = ws.cmd("export", &ev);
        assert_eq!(code, 0, "{out}{err}");
        serde_json::from_slice(&fs::read(ws.dir().join("eval/metrics.json")).unwrap()).unwrap()
    };
    let frames = |m: &serde_json::Value| {
        m["by_camera_model"]["fisheye"]["panoptic_nerf"]["frames"]
            .as_f64()
            .unwrap()
    };
    // Evaluation frames 20, 22 and 24, two fisheye images each.
    assert_eq!(frames(&metrics(&ws, &args)), 6.0);
    args.extend(["--set", "evaluate.frames=[22]"]);
    ws.run_ok(&args);
    assert_eq!(frames(&metrics(&ws, &args)), 2.0);
    let n = args.len();
    args[n - 1] = "evaluate.frames=[21]";
    let (code, out, err) = ws.run(&args);
    assert_ne!(code, 0);
    assert!(
        err.contains("frame 21 is not an evaluation frame")
            || out.contains("frame 21 is not an evaluation frame"),
        "{out}{err}"
    );
}
