//! Tests of the KITTI-360 loader: the hand-written fixture (tests/fixtures/kitti360), every
//! malformed input of tests/bad_inputs/kitti360 plus generated ones (truncated PNG, missing
//! file, unknown label id, frame without pose), and the round trip synthetic scene -> `pipe
//! export` layout -> `kitti360_scene`.

use std::path::{Path, PathBuf};

use arrow::datatypes::{Float64Type, UInt32Type, UInt8Type};

use super::*;
use crate::geometry::{cameras_from_table, dynamic_boxes_from_table, primitives_from_table, Shape};
use crate::kinds::kitti360_scene::Kitti360Scene;
use crate::kinds::synthetic_scene::SyntheticScene;
use crate::labels;
use crate::scene::kitti360_export::{self, LIDAR_DEPTH_TOLERANCE, STEREO_DEPTH_TOLERANCE_M};
use crate::scene::synthetic::SceneParams;
use crate::Inputs;
use crate::{NoProgress, Stage};

mod dynamic;
mod fisheye;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let t = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &t);
        } else {
            std::fs::copy(e.path(), t).unwrap();
        }
    }
}

/// A fresh temporary directory for one test.
fn temp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("kitti360-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The RGB byte of frame `f`, camera `c`, pixel (x, y), channel `k` in the fixture.
fn fixture_rgb(f: u32, c: u8, x: u32, y: u32, k: u32) -> u8 {
    (f * 31 + c as u32 * 17 + x * 7 + y * 3 + k * 50) as u8
}

/// The fixture in a temporary directory, with its PNGs written (8x4, frames 3 and 7).
fn fixture(name: &str) -> (PathBuf, Kitti360Params) {
    let root = temp(name);
    copy_dir(&repo().join("tests/fixtures/kitti360"), &root);
    let p = Kitti360Params {
        root: root.display().to_string(),
        sequence: "seq_a".into(),
        first_frame: 0,
        last_frame: 10,
        eval_every: 1,
        ..Default::default()
    };
    for f in [3u32, 7, 12] {
        for c in [0u8, 1] {
            let rgb: Vec<u8> = (0..4)
                .flat_map(|y| {
                    (0..8).flat_map(move |x| (0..3).map(move |k| fixture_rgb(f, c, x, y, k)))
                })
                .collect();
            crate::pngio::write_rgb8(&p.path(&p.images, f, c), 8, 4, &rgb).unwrap();
            let sem: Vec<u8> = (0..32).map(|i| if i < 16 { 23 } else { 26 }).collect();
            let inst: Vec<u16> = sem
                .iter()
                .map(|&l| if l == 26 { 26001 } else { 23000 })
                .collect();
            let gs = p.gt_semantic.clone().unwrap();
            let gi = p.gt_instance.clone().unwrap();
            crate::pngio::write_gray8(&p.path(&gs, f, c), 8, 4, &sem).unwrap();
            crate::pngio::write_gray16(&p.path(&gi, f, c), 8, 4, &inst).unwrap();
        }
        let pl: Vec<u8> = (0..32).map(|i| if i < 20 { 23 } else { 7 }).collect();
        crate::pngio::write_gray8(&p.path(&p.pseudo_labels, f, 0), 8, 4, &pl).unwrap();
    }
    (root, p)
}

fn run(p: &Kitti360Params) -> Result<Tables> {
    let v = serde_json::to_value(p).unwrap();
    let s = Kitti360Scene;
    let v = Stage::canonical_params(&s, &v)?;
    Stage::run(&s, &v, &Inputs::new(Default::default()), &NoProgress)
}

#[test]
fn the_hand_written_fixture_loads() {
    let (root, p) = fixture("good");
    let t = run(&p).unwrap();
    let cams = cameras_from_table(&t["cameras"]).unwrap();
    // Frames 3 and 7 of [0, 10] have poses (12 is outside the range), two cameras each.
    let keys: Vec<(u32, u8)> = cams.iter().map(|r| (r.frame, r.camera)).collect();
    assert_eq!(keys, vec![(3, 0), (3, 1), (7, 0), (7, 1)]);
    // Origin: the first pose's centre rounded to metres (1000.5 rounds away from zero).
    let (o, _) =
        tables::get_fixed_list::<Float64Type>(&t["scene_info"], "scene_info", "origin").unwrap();
    assert_eq!(o, &[1001.0, 2000.0, 100.0]);
    let base = tables::get_prim::<Float64Type>(&t["scene_info"], "scene_info", "baseline").unwrap();
    assert_eq!(base, &[0.5]);
    let c0 = &cams[0].cam;
    assert_eq!((c0.width, c0.height, c0.fx, c0.fy), (8, 4, 4.0, 4.0));
    assert_eq!((c0.cx, c0.cy), (4.0, 2.0)); // OpenCV (3.5, 1.5) + half a pixel
    assert!((c0.centre() - DVec3::new(-0.5, 0.25, 0.0)).length() < 1e-12);
    assert!((cams[1].cam.centre() - DVec3::new(0.0, 0.25, 0.0)).length() < 1e-12);
    assert!((cams[2].cam.centre() - DVec3::new(-0.5, 0.25, 1.0)).length() < 1e-12);
    // Primitives: the car cuboid and the building mesh; the dynamic person and the far road
    // are dropped.
    let prims = primitives_from_table(&t["primitives"]).unwrap();
    assert_eq!(prims.len(), 2);
    assert_eq!(prims[0].shape, Shape::Cuboid);
    assert_eq!((prims[0].label, prims[0].instance), (labels::CAR, 1));
    assert!((prims[0].to_world.translation - DVec3::new(-0.5, 0.25, 10.0)).length() < 1e-12);
    assert_eq!(prims[0].to_world.matrix3.x_axis.x, 2.0);
    assert!(matches!(prims[1].shape, Shape::Mesh { .. }));
    assert_eq!((prims[1].label, prims[1].instance), (labels::BUILDING, 2));
    // World vertex = R v + T: the tetrahedron's apex (0, 0, 1) is at world (999, 1999, 123).
    assert!(prims[1].contains(DVec3::new(999.2 - 1001.0, 1999.2 - 2000.0, 120.2 - 100.0)));
    assert!(!prims[1].contains(DVec3::new(1001.9 - 1001.0, 1999.0 - 2000.0, 122.9 - 100.0)));
    // Images and labels.
    let rgb = tables::get_binary(&t["images"], "images", "rgb").unwrap();
    assert_eq!(arrow::array::Array::len(rgb), 4);
    assert_eq!(
        rgb.value(3)[3 * (8 * 2 + 5) + 1],
        fixture_rgb(7, 1, 5, 2, 1)
    );
    assert_eq!(t["pseudo_labels"].num_rows(), 2);
    assert_eq!(t["gt_semantic"].num_rows(), 4);
    assert_eq!(t["gt_instance"].num_rows(), 4);
    assert_eq!(t["stereo_depth"].num_rows(), 0);
    assert_eq!(t["lidar_depth"].num_rows(), 0);
    assert_eq!(t["gt_depth"].num_rows(), 0);
    let classes = tables::get_list::<UInt8Type>(&t["scene_info"], "scene_info", "classes").unwrap();
    assert_eq!(
        classes.row(0),
        &[labels::BUILDING, labels::SKY, labels::CAR]
    );
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn explicit_frames_eval_frames_and_culling_distance() {
    let (root, mut p) = fixture("frames");
    p.frames = vec![12, 3];
    p.cameras = vec![0];
    p.eval_frames = vec![12];
    p.max_distance_m = 7.0; // the car (6 m from frame 12's camera) stays, the building goes
    let t = run(&p).unwrap();
    let cams = cameras_from_table(&t["cameras"]).unwrap();
    let keys: Vec<(u32, u8, bool)> = cams.iter().map(|r| (r.frame, r.camera, r.eval)).collect();
    assert_eq!(keys, vec![(3, 0, false), (12, 0, true)]);
    let prims = primitives_from_table(&t["primitives"]).unwrap();
    assert_eq!(prims.len(), 1);
    assert_eq!(prims[0].label, labels::CAR);
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn input_files_lists_what_a_run_reads() {
    let (root, mut p) = fixture("inputs");
    p.stereo_depth = Some("stereo/{seq}/{frame}.png".into());
    let files = input_files(&p).unwrap();
    let rel: Vec<String> = files
        .iter()
        .map(|f| f.strip_prefix(&root).unwrap().display().to_string())
        .collect();
    assert_eq!(rel[0], "data_poses/seq_a/cam0_to_world.txt");
    assert_eq!(rel[1], "calibration/perspective.txt");
    assert_eq!(rel[2], "data_3d_bboxes/train/seq_a.xml");
    assert!(rel.contains(&"data_2d_raw/seq_a/image_01/data_rect/0000000007.png".to_string()));
    assert!(rel.contains(&"pseudo_labels/seq_a/image_00/0000000003.png".to_string()));
    assert!(rel.contains(&"stereo/seq_a/0000000007.png".to_string()));
    assert!(
        rel.contains(&"data_2d_semantics/train/seq_a/image_01/instance/0000000003.png".to_string())
    );
    assert!(!rel.iter().any(|r| r.contains("0000000012")), "{rel:?}");
    // Everything a run reads exists and is listed (the fixture has no stereo files: they are
    // listed so that adding them changes the key).
    assert_eq!(files.len(), 3 + 2 * (2 * 3) + 2 * 2);
    std::fs::remove_dir_all(root).unwrap();
}

/// A malformed input: the error names the file and the element and says what is wrong.
fn assert_error(p: &Kitti360Params, file: &str, needles: &[&str]) {
    let e = run(p).expect_err("malformed input must fail").to_string();
    assert!(e.starts_with("bad input: "), "{e}");
    assert!(e.contains(file), "error does not name {file}: {e}");
    for n in needles {
        assert!(e.contains(n), "error lacks `{n}`: {e}");
    }
}

#[test]
fn every_malformed_file_of_the_corpus_is_an_error_naming_file_and_element() {
    let cases: &[(&str, &str, &[&str])] = &[
        (
            "pose_nan.txt",
            "data_poses/seq_a/cam0_to_world.txt",
            &["line 2 (frame 7)", "non-finite"],
        ),
        (
            "pose_short_line.txt",
            "data_poses/seq_a/cam0_to_world.txt",
            &["line 1 (frame 3)", "found 15"],
        ),
        (
            "perspective_p01_11_values.txt",
            "calibration/perspective.txt",
            &["`P_rect_01`", "expected 12 numbers, found 11"],
        ),
        (
            "perspective_no_p01.txt",
            "calibration/perspective.txt",
            &["no `P_rect_01` line"],
        ),
        (
            "bboxes_vertices_size.xml",
            "data_3d_bboxes/train/seq_a.xml",
            &["<object2>/<vertices>", "needs 12 values, <data> has 11"],
        ),
        (
            "bboxes_nan.xml",
            "data_3d_bboxes/train/seq_a.xml",
            &["<object2>/<transform>", "non-finite"],
        ),
        (
            "bboxes_unknown_semantic.xml",
            "data_3d_bboxes/train/seq_a.xml",
            &["<object2>/<semanticId>", "99 is not a KITTI-360 kittiId"],
        ),
        (
            "bboxes_open_mesh.xml",
            "data_3d_bboxes/train/seq_a.xml",
            &["<object2> (building)", "not closed"],
        ),
        (
            "bboxes_face_index.xml",
            "data_3d_bboxes/train/seq_a.xml",
            &["<object2>/<faces>", "face 3 refers to vertex 4"],
        ),
        (
            "bboxes_truncated.xml",
            "data_3d_bboxes/train/seq_a.xml",
            &["not well-formed XML"],
        ),
        (
            "bboxes_transform_3x4.xml",
            "data_3d_bboxes/train/seq_a.xml",
            &[
                "<object2>/<transform>",
                "expected a 4 x 4 matrix, found 3 x 4",
            ],
        ),
        (
            "perspective_r_rect_reflection.txt",
            "calibration/perspective.txt",
            &["line 6 `R_rect_00`", "not a rotation"],
        ),
        (
            "velodyne_truncated.bin",
            "data_3d_raw/seq_a/velodyne_points/data/0000000007.bin",
            &["20 bytes", "not a whole number of points", "truncated"],
        ),
        (
            "velodyne_nan.bin",
            "data_3d_raw/seq_a/velodyne_points/data/0000000007.bin",
            &["point 1 (byte 16)", "non-finite coordinate (12, NaN, -0.3"],
        ),
        (
            "calib_cam_to_velo_11_values.txt",
            "calibration/calib_cam_to_velo.txt",
            &["camera -> velodyne", "expected 12 numbers, found 11"],
        ),
        (
            "calib_cam_to_velo_not_rigid.txt",
            "calibration/calib_cam_to_velo.txt",
            &["camera -> velodyne", "not a rotation"],
        ),
    ];
    let corpus = repo().join("tests/bad_inputs/kitti360");
    let n = std::fs::read_dir(&corpus).unwrap().count();
    assert_eq!(n, cases.len(), "every corpus file has a case");
    for (bad, target, needles) in cases {
        let (root, mut p) = fixture(&format!("bad-{bad}"));
        if target.contains("velo") {
            with_lidar(&mut p);
        }
        std::fs::copy(corpus.join(bad), root.join(target)).unwrap();
        assert_error(&p, target, needles);
        std::fs::remove_dir_all(root).unwrap();
    }
}

#[test]
fn broken_pngs_missing_files_and_frames_without_pose_are_errors() {
    // A truncated image.
    let (root, p) = fixture("png");
    let img = p.path(&p.images, 7, 1);
    let bytes = std::fs::read(&img).unwrap();
    std::fs::write(&img, &bytes[..bytes.len() / 2]).unwrap();
    assert_error(
        &p,
        "image_01/data_rect/0000000007.png",
        &["not a readable PNG"],
    );
    // A missing image.
    std::fs::remove_file(&img).unwrap();
    assert_error(&p, "image_01/data_rect/0000000007.png", &["cannot read"]);
    std::fs::remove_dir_all(root).unwrap();

    // A pseudo label that is not a label id, and one of the wrong size.
    let (root, p) = fixture("label");
    let pl = p.path(&p.pseudo_labels, 3, 0);
    let mut v = vec![7u8; 32];
    v[8 + 5] = 200;
    crate::pngio::write_gray8(&pl, 8, 4, &v).unwrap();
    assert_error(
        &p,
        "image_00/0000000003.png",
        &["pixel (5, 1)", "200 is not a KITTI-360 label id"],
    );
    crate::pngio::write_gray8(&pl, 4, 4, &[7; 16]).unwrap();
    assert_error(
        &p,
        "image_00/0000000003.png",
        &["image is 4x4, expected 8x4"],
    );
    crate::pngio::write_rgb8(&pl, 8, 4, &[7; 96]).unwrap();
    assert_error(
        &p,
        "image_00/0000000003.png",
        &["expected an 8-bit single-channel"],
    );
    std::fs::remove_dir_all(root).unwrap();

    // An explicitly requested frame without a pose; an empty range.
    let (root, mut p) = fixture("nopose");
    p.frames = vec![3, 5];
    assert_error(
        &p,
        "cam0_to_world.txt",
        &["frame 5 (listed in `frames`) has no pose"],
    );
    p.frames = vec![];
    p.first_frame = 20;
    p.last_frame = 30;
    assert_error(
        &p,
        "cam0_to_world.txt",
        &["no frame in [20, 30] has a pose"],
    );
    // A missing pose file.
    p.sequence = "seq_b".into();
    assert_error(&p, "data_poses/seq_b/cam0_to_world.txt", &["cannot read"]);
    std::fs::remove_dir_all(root).unwrap();

    // An evaluation frame without GT; a GT instance PNG of the wrong depth.
    let (root, p) = fixture("gt");
    let gi = p.path(p.gt_instance.as_ref().unwrap(), 7, 0);
    crate::pngio::write_gray8(&gi, 8, 4, &[0; 32]).unwrap();
    assert_error(
        &p,
        "image_00/instance/0000000007.png",
        &["expected a 16-bit single-channel instance PNG"],
    );
    std::fs::remove_file(&gi).unwrap();
    let auto = p.clone();
    let mut p = p;
    p.eval_gt = EvalGt::Required;
    assert_error(
        &p,
        "image_00/instance/0000000007.png",
        &["missing", "evaluation frame", "eval_gt: required"],
    );
    // `auto` (the default): that image is trained on, not evaluated; the others still are.
    let eval_of = |p: &Kitti360Params| -> Vec<(u32, u8, bool)> {
        let t = load(p, &NoProgress).unwrap();
        cameras_from_table(&t["cameras"])
            .unwrap()
            .iter()
            .map(|r| (r.frame, r.camera, r.eval))
            .collect()
    };
    let with_gt = {
        let gi_back = p.path(p.gt_instance.as_ref().unwrap(), 7, 0);
        crate::pngio::write_gray16(&gi_back, 8, 4, &[7000; 32]).unwrap();
        let e = eval_of(&auto);
        std::fs::remove_file(&gi_back).unwrap();
        e
    };
    let without = eval_of(&auto);
    assert!(with_gt.contains(&(7, 0, true)), "{with_gt:?}");
    assert_eq!(
        without,
        with_gt
            .iter()
            .map(|&(f, c, e)| (f, c, e && (f, c) != (7, 0)))
            .collect::<Vec<_>>()
    );
    assert!(without.iter().any(|r| r.2), "{without:?}");
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn bad_params_are_rejected() {
    let s = Kitti360Scene;
    for (json, needle) in [
        (serde_json::json!({"cameras": [2]}), "`cameras`"),
        (
            serde_json::json!({"first_frame": 9, "last_frame": 3}),
            "`first_frame`",
        ),
        (serde_json::json!({"sequence": "a/b"}), "`sequence`"),
        (
            serde_json::json!({"max_distance_m": 0.0}),
            "`max_distance_m`",
        ),
        (serde_json::json!({"rooot": "x"}), "rooot"),
        (serde_json::json!({"cameras": [1]}), "`cameras` [1] lacks 0"),
        (
            serde_json::json!({"eval_every": 0}),
            "`eval_every` 0 without `eval_frames`",
        ),
    ] {
        let e = Stage::canonical_params(&s, &json).unwrap_err().to_string();
        assert!(e.contains(needle), "{e}");
    }
    // Listed evaluation frames need no eval_every.
    let ok = serde_json::json!({"eval_every": 0, "eval_frames": [3]});
    assert!(Stage::canonical_params(&s, &ok).is_ok());
}

/// An evaluation frame the scene does not read is an error of the params, found when the
/// runner lists the input files (before any stage runs), naming the setting and the frame.
#[test]
fn evaluation_frames_outside_the_selection_are_refused_before_running() {
    let (root, mut p) = fixture("eval-frames");
    p.eval_frames = vec![7, 12]; // 12 has a pose but is outside [0, 10]
    let e = input_files(&p).unwrap_err().to_string();
    assert!(
        e.contains("`eval_frames`: frame 12 is not among the selected frames ([3, 7])"),
        "{e}"
    );
    p.eval_frames = vec![7];
    assert!(input_files(&p).is_ok());
    std::fs::remove_dir_all(root).unwrap();
}

/// Turns on `lidar` and writes a one-point scan for frames 3 and 7 (both evaluation frames):
/// 10 m ahead on the ray through the centre of pixel (4, 2).
fn with_lidar(p: &mut Kitti360Params) -> Vec<u8> {
    p.lidar = Some(LIDAR_PATTERN.into());
    // calib_cam_to_velo maps camera (x, y, z) to velodyne (z + 0.1, -x - 0.2, -y - 0.3);
    // pixel (4, 2)'s centre is image point (4.5, 2.5), 0.5 px right of and below (cx, cy) =
    // (4, 2), with fx = fy = 4.
    let cam_pt = DVec3::new(0.5 / 4.0 * 10.0, 0.5 / 4.0 * 10.0, 10.0);
    let velo = DVec3::new(cam_pt.z + 0.1, -cam_pt.x - 0.2, -cam_pt.y - 0.3);
    let mut bytes = Vec::new();
    for v in [velo.x, velo.y, velo.z, 0.5] {
        bytes.extend((v as f32).to_le_bytes());
    }
    for f in [3u32, 7] {
        let path = p.path(LIDAR_PATTERN, f, 0);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, &bytes).unwrap();
    }
    bytes
}

#[test]
fn lidar_scans_project_into_the_left_camera() {
    let (root, mut p) = fixture("lidar");
    let bytes = with_lidar(&mut p);
    let t = run(&p).unwrap();
    assert_eq!(t["lidar_depth"].num_rows(), 2);
    let d = tables::get_list::<arrow::datatypes::Float32Type>(
        &t["lidar_depth"],
        "lidar_depth",
        "depth",
    )
    .unwrap();
    assert!((d.row(0)[2 * 8 + 4] - 10.0).abs() < 1e-4, "{:?}", d.row(0));
    assert_eq!(d.row(0).iter().filter(|&&x| x > 0.0).count(), 1);
    // A truncated scan.
    let path = p.path(p.lidar.as_ref().unwrap(), 7, 0);
    std::fs::write(&path, &bytes[..10]).unwrap();
    assert_error(
        &p,
        "velodyne_points/data/0000000007.bin",
        &["10 bytes", "truncated"],
    );
    // A missing scan of an evaluation frame; a missing calibration.
    std::fs::remove_file(&path).unwrap();
    assert_error(&p, "velodyne_points/data/0000000007.bin", &["cannot read"]);
    std::fs::write(&path, &bytes).unwrap();
    std::fs::remove_file(root.join("calibration/calib_cam_to_velo.txt")).unwrap();
    assert_error(
        &p,
        "calibration/calib_cam_to_velo.txt",
        &["cannot read", "`lidar_calib`", "`lidar`"],
    );
    std::fs::remove_dir_all(root).unwrap();
}

/// Exports the default synthetic scene in the KITTI-360 layout and loads it back.
fn round_trip(tag: &str, max_distance_m: f64) -> (Tables, Tables) {
    // With its moving cars and cyclist: their boxes go through the XML as dynamic objects.
    let sp = SceneParams {
        moving_objects: 4,
        ..SceneParams::default()
    };
    let synth = crate::scene::synthetic::in_memory::to_tables(
        &sp,
        crate::scene::synthetic::generate(&sp, &NoProgress).unwrap(),
    )
    .unwrap();
    let root = temp(&format!("roundtrip-{tag}"));
    kitti360_export::write(&synth, &root).unwrap();
    let p = Kitti360Params {
        root: root.display().to_string(),
        sequence: sp.sequence.clone(),
        first_frame: sp.first_frame,
        last_frame: sp.first_frame + sp.frames - 1,
        eval_every: sp.eval_every,
        origin: Some(sp.origin),
        name: sp.name.clone(),
        max_distance_m,
        pseudo_labels: "pseudo_labels/{seq}/image_00/%010d.png".into(),
        stereo_depth: Some(STEREO_DEPTH_PATTERN.into()),
        lidar: Some(LIDAR_PATTERN.into()),
        ..Default::default()
    };
    let loaded = run(&p).unwrap();
    std::fs::remove_dir_all(root).unwrap();
    let _ = SyntheticScene;
    (synth, loaded)
}

#[test]
fn the_exported_synthetic_scene_loads_back_into_equal_tables() {
    // No culling: every primitive comes back.
    let (a, b) = round_trip("tables", 1.0e6);
    // Byte-equal tables.
    for name in ["images", "pseudo_labels", "gt_semantic", "gt_instance"] {
        assert_eq!(a[name], b[name], "table {name} differs");
    }
    let si = |t: &Tables| crate::scene::io::scene_info(t).unwrap();
    let (ia, ib) = (si(&a), si(&b));
    assert_eq!((ia.name, ia.sequence), (ib.name, ib.sequence));
    assert_eq!(ia.origin, ib.origin);
    assert!(
        (ia.baseline - ib.baseline).abs() < 1e-12,
        "{} {}",
        ia.baseline,
        ib.baseline
    );
    let cl = |t: &Tables| {
        tables::get_list::<UInt8Type>(&t["scene_info"], "scene_info", "classes")
            .unwrap()
            .row(0)
            .to_vec()
    };
    assert_eq!(cl(&a), cl(&b));

    // Depth: stereo to the 16-bit format's 1/256 m; LiDAR (exported as velodyne points through
    // calib_cam_to_velo and R_rect_00, re-projected) on the same pixels, to float32 rounding.
    let diff = |name: &str| kitti360_export::depth_difference(&a, &b, name).unwrap();
    let (stereo, lidar) = (diff("stereo_depth"), diff("lidar_depth"));
    eprintln!("round trip: stereo depth {stereo:?}, LiDAR depth {lidar:?}");
    assert!(stereo.pixels > 0 && lidar.pixels > 0);
    assert!(stereo.max_abs <= STEREO_DEPTH_TOLERANCE_M, "{stereo:?}");
    assert!(lidar.max_rel <= LIDAR_DEPTH_TOLERANCE, "{lidar:?}");

    // Cameras: same rows, intrinsics and poses within 1e-9 (pixels, metres).
    let (ca, cb) = (
        cameras_from_table(&a["cameras"]).unwrap(),
        cameras_from_table(&b["cameras"]).unwrap(),
    );
    assert_eq!(ca.len(), cb.len());
    let mut worst = 0f64;
    for (x, y) in ca.iter().zip(&cb) {
        assert_eq!((x.frame, x.camera, x.eval), (y.frame, y.camera, y.eval));
        assert_eq!((x.cam.width, x.cam.height), (y.cam.width, y.cam.height));
        for (u, v) in [
            (x.cam.fx, y.cam.fx),
            (x.cam.fy, y.cam.fy),
            (x.cam.cx, y.cam.cx),
            (x.cam.cy, y.cam.cy),
        ] {
            worst = worst.max((u - v).abs());
        }
        let (ma, mb) = (
            x.cam.cam_to_world.to_cols_array(),
            y.cam.cam_to_world.to_cols_array(),
        );
        for (u, v) in ma.iter().zip(mb) {
            worst = worst.max((u - v).abs());
        }
    }
    eprintln!("round trip: cameras differ by at most {worst:.2e}");
    assert!(worst < 1e-9, "{worst}");

    // Primitives: same count, labels, instances and transforms; cuboids stay cuboids, other
    // shapes come back as the exported closed mesh (ellipsoids tessellated 16 x 8).
    let (pa, pb) = (
        primitives_from_table(&a["primitives"]).unwrap(),
        primitives_from_table(&b["primitives"]).unwrap(),
    );
    assert_eq!(pa.len(), pb.len());
    let mut worst = 0f64;
    let mut rng = crate::scene::rng::Rng::new(7, crate::scene::rng::Purpose::Layout, &[1]);
    let (mut agree, mut total) = (0usize, 0usize);
    for (i, (x, y)) in pa.iter().zip(&pb).enumerate() {
        assert_eq!(
            (x.label, x.instance),
            (y.label, y.instance),
            "primitive {i}"
        );
        let (ma, mb) = (x.to_world.to_cols_array(), y.to_world.to_cols_array());
        for (u, v) in ma.iter().zip(mb) {
            worst = worst.max((u - v).abs());
        }
        match (&x.shape, &y.shape) {
            (Shape::Cuboid, Shape::Cuboid) => {}
            (s, Shape::Mesh { vertices, faces }) => {
                let (v, f) = kitti360_export::local_mesh(s);
                assert_eq!(&f, faces, "primitive {i}");
                assert!(v
                    .iter()
                    .zip(vertices)
                    .all(|(p, q)| (*p - *q).length() < 1e-12));
                if !matches!(s, Shape::Ellipsoid) {
                    // Extruded polygons and meshes are exact: same inside/outside everywhere.
                    let bb = x.aabb();
                    for _ in 0..500 {
                        let q = bb.min
                            + (bb.max - bb.min) * DVec3::new(rng.f64(), rng.f64(), rng.f64());
                        total += 1;
                        agree += (x.contains(q) == y.contains(q)) as usize;
                    }
                }
            }
            (s, t) => panic!("primitive {i}: {} came back as {}", s.kind(), t.kind()),
        }
    }
    eprintln!("round trip: primitive transforms differ by at most {worst:.2e}; contains() agrees on {agree}/{total} random points");
    assert!(worst < 1e-9, "{worst}");
    assert_eq!(agree, total);

    // The moving objects' boxes: the same (object, frame) rows and transforms, the cyclist's
    // two classes among them.
    let (da, db) = (
        dynamic_boxes_from_table(&a["dynamic_boxes"]).unwrap(),
        dynamic_boxes_from_table(&b["dynamic_boxes"]).unwrap(),
    );
    assert!(da.len() > 16, "{} moving boxes", da.len());
    for class in [labels::CAR, labels::RIDER, labels::BICYCLE] {
        assert!(
            db.iter().any(|b| b.primitive.label == class),
            "no {class} box"
        );
    }
    assert_eq!(da.len(), db.len());
    for (x, y) in da.iter().zip(&db) {
        assert_eq!((x.object, x.frame), (y.object, y.frame));
        let (ma, mb) = (
            x.primitive.to_world.to_cols_array(),
            y.primitive.to_world.to_cols_array(),
        );
        assert!(ma.iter().zip(mb).all(|(u, v)| (u - v).abs() < 1e-9));
    }
}

#[test]
fn the_intersect_stage_gives_the_same_first_primitive_labels_on_the_round_trip() {
    let (a, b) = round_trip("rays", 1.0e6);
    let rays = |t: &Tables| {
        let s = crate::kinds::intersect::Intersect;
        let v = Stage::canonical_params(&s, &serde_json::json!({})).unwrap();
        let mem = crate::MemoryInputs::new([("scene", t.clone())]);
        Stage::run(&s, &v, &mem.inputs(), &NoProgress).unwrap()
    };
    // The synthetic scene with its ellipsoids replaced by the 16 x 8 tessellation the export
    // writes: the loaded scene must match it exactly, pixel for pixel.
    let tessellated: Vec<Primitive> = primitives_from_table(&a["primitives"])
        .unwrap()
        .into_iter()
        .map(|q| match q.shape {
            Shape::Ellipsoid => {
                let (vertices, faces) = kitti360_export::local_mesh(&Shape::Ellipsoid);
                Primitive::new(
                    Shape::Mesh { vertices, faces },
                    q.to_world,
                    q.label,
                    q.instance,
                )
                .unwrap()
            }
            _ => q,
        })
        .collect();
    let mut a_mesh = a.clone();
    a_mesh.insert(
        "primitives".into(),
        primitives_to_table(&tessellated).unwrap(),
    );
    let (ra, rb, rm) = (rays(&a), rays(&b), rays(&a_mesh));
    let col = |t: &Tables| {
        tables::get_list::<UInt8Type>(&t["ray_intervals"], "ray_intervals", "first_label")
            .unwrap()
            .row(0)
            .len()
    };
    assert!(col(&ra) > 0);
    let fl = |t: &Tables| {
        let r = &t["ray_intervals"];
        let l = tables::get_list::<UInt8Type>(r, "ray_intervals", "first_label").unwrap();
        (0..r.num_rows())
            .flat_map(|i| l.row(i).to_vec())
            .collect::<Vec<u8>>()
    };
    let (la, lb, lm) = (fl(&ra), fl(&rb), fl(&rm));
    // Pixels whose first primitive differs must be ties: two primitives entered at the same
    // distance (the synthetic street has coincident sidewalk and terrain tops), where the
    // order is decided by rounding.
    let first_t = |t: &Tables| {
        let r = &t["ray_intervals"];
        let hits = tables::get_list::<UInt8Type>(r, "ray_intervals", "hits").unwrap();
        let t_in =
            tables::get_list::<arrow::datatypes::Float32Type>(r, "ray_intervals", "t_in").unwrap();
        let mut out = Vec::new();
        for i in 0..r.num_rows() {
            let mut off = 0usize;
            for &h in hits.row(i) {
                out.push(if h > 0 { t_in.row(i)[off] } else { -1.0 });
                off += h as usize;
            }
        }
        out
    };
    let (tm, tb) = (first_t(&rm), first_t(&rb));
    let mut exact = 0;
    for p in 0..lb.len() {
        if lm[p] == lb[p] {
            exact += 1;
        } else {
            assert!(
                tm[p] > 0.0 && (tm[p] - tb[p]).abs() < 1e-3,
                "pixel {p}: {} at {} vs {} at {}",
                lm[p],
                tm[p],
                lb[p],
                tb[p]
            );
        }
    }
    eprintln!(
        "round trip: first-primitive labels equal the tessellated synthetic scene's on {exact}/{} pixels; the rest are ties (equal entry distance)",
        lb.len()
    );
    let same = la.iter().zip(&lb).filter(|(x, y)| x == y).count();
    let frac = same as f64 / la.len() as f64;
    // First-primitive mIoU against GT (the evaluate stage's baseline), both ways.
    let gt = tables::get_list::<UInt8Type>(&a["gt_semantic"], "gt_semantic", "labels").unwrap();
    let gt: Vec<u8> = (0..a["gt_semantic"].num_rows())
        .flat_map(|i| gt.row(i).to_vec())
        .collect();
    let miou = |pred: &[u8]| {
        let mut c = crate::metrics::ConfusionMatrix::new(labels::PAPER_CLASSES).unwrap();
        c.add(&gt, pred).unwrap();
        100.0 * c.miou().unwrap()
    };
    let (ma, mb) = (miou(&la), miou(&lb));
    eprintln!(
        "round trip: first-primitive labels agree on {:.4}% of {} pixels; first-primitive mIoU {ma:.3} (synthetic) vs {mb:.3} (loaded)",
        100.0 * frac,
        la.len()
    );
    let _ = tables::get_prim::<UInt32Type>(&ra["ray_intervals"], "ray_intervals", "frame").unwrap();
    // Against the exact ellipsoids, only silhouettes of tree crowns differ.
    assert!(frac > 0.99, "{frac}");
    assert!((ma - mb).abs() < 1.0, "{ma} vs {mb}");
}

#[test]
fn text_files_with_a_byte_order_mark_read_as_without() {
    let (root, p) = fixture("bom");
    let plain = run(&p).unwrap();
    for file in [
        "calibration/perspective.txt",
        "data_poses/seq_a/cam0_to_world.txt",
    ] {
        let text = std::fs::read_to_string(root.join(file)).unwrap();
        std::fs::write(root.join(file), format!("\u{feff}{text}")).unwrap();
    }
    let with_bom = run(&p).unwrap();
    for (name, t) in &plain {
        assert_eq!(t, &with_bom[name], "table {name}");
    }
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn a_pose_far_from_the_rest_names_the_frame_wherever_it_is() {
    let step = |x: f64| format!("1 0 0 {x} 0 1 0 20 0 0 1 1 0 0 0 1");
    let path = Path::new("poses.txt");
    // The outlier first, in the middle and last; 1e30 m and 5 km (after 2 frames) away.
    for (xs, bad) in [
        ([1e30, 0.0, 1.0, 2.0], 3),
        ([0.0, 1.0, 5000.0, 2.0], 9),
        ([0.0, 1.0, 2.0, -1e30], 12),
    ] {
        let text: String = [3, 5, 9, 12]
            .iter()
            .zip(xs)
            .map(|(f, x)| format!("{f} {}\n", step(x)))
            .collect();
        let e = parse::poses(path, &text).unwrap_err().to_string();
        assert!(e.contains(&format!("(frame {bad})")), "{xs:?}: {e}");
        assert!(e.contains("at most 100 m per frame"), "{e}");
    }
    // 90 m per frame of gap is a fast car, but possible; 5 km over 100 frames too.
    let ok: String = [(0, 0.0), (1, 90.0), (101, 5090.0)]
        .iter()
        .map(|(f, x)| format!("{f} {}\n", step(*x)))
        .collect();
    assert_eq!(parse::poses(path, &ok).unwrap().len(), 3);
}

/// The exported XML read the way KITTI-360's devkit reads it (`Annotation3D`, written here
/// from its description rather than with our reader): every `<objectN>` keyed by `globalId =
/// semanticId * 1000 + instanceId`, one object per key and timestamp. Every primitive must
/// survive as its own object, and things keep their instance ids.
#[test]
fn the_exported_bboxes_keep_every_object_apart_for_the_devkit() {
    let sp = SceneParams::default();
    let synth = crate::scene::synthetic::in_memory::to_tables(
        &sp,
        crate::scene::synthetic::generate(&sp, &NoProgress).unwrap(),
    )
    .unwrap();
    let root = temp("devkit-ids");
    kitti360_export::write(&synth, &root).unwrap();
    let xml_path = root.join(format!("data_3d_bboxes/train/{}.xml", sp.sequence));
    let text = std::fs::read_to_string(&xml_path).unwrap();
    let doc = roxmltree::Document::parse(&text).unwrap();
    let field = |obj: roxmltree::Node, tag: &str| -> i64 {
        obj.children()
            .find(|c| c.has_tag_name(tag))
            .and_then(|c| c.text())
            .unwrap()
            .trim()
            .parse()
            .unwrap()
    };
    let mut objects = std::collections::BTreeMap::new();
    let mut listed = 0;
    for obj in doc
        .root_element()
        .children()
        .filter(|c| c.is_element() && c.tag_name().name().starts_with("object"))
    {
        listed += 1;
        let kitti_id = field(obj, "semanticId");
        let global = kitti_id * 1000 + field(obj, "instanceId");
        objects.insert((global, field(obj, "timestamp")), field(obj, "index"));
    }
    let prims = primitives_from_table(&synth["primitives"]).unwrap();
    assert!(prims.len() > 100, "the default street has many primitives");
    assert_eq!(listed, prims.len());
    assert_eq!(
        objects.len(),
        prims.len(),
        "objects sharing (semanticId, instanceId)"
    );
    // Things: the instance id of the primitive (as in the GT instance maps).
    for (i, p) in prims.iter().enumerate() {
        let l = labels::by_id(p.label).unwrap();
        if l.has_instances {
            let global = i64::from(l.kitti_id) * 1000 + i64::from(p.instance);
            assert_eq!(objects.get(&(global, -1)), Some(&(i as i64)), "thing {i}");
        }
    }
    std::fs::remove_dir_all(root).unwrap();
}

/// CRC-32 of a PNG chunk's type and data (to forge a header).
fn png_crc(bytes: &[u8]) -> u32 {
    let mut c = 0xFFFF_FFFFu32;
    for &b in bytes {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

/// An 8-bit palette PNG of `w` x `h` indices.
fn write_palette(path: &Path, w: u32, h: u32, indices: &[u8]) {
    let f = std::fs::File::create(path).unwrap();
    let mut e = png::Encoder::new(std::io::BufWriter::new(f), w, h);
    e.set_color(png::ColorType::Indexed);
    e.set_depth(png::BitDepth::Eight);
    e.set_palette(
        (0..=255u8)
            .flat_map(|i| [i, 255 - i, i / 2])
            .collect::<Vec<u8>>(),
    );
    e.write_header().unwrap().write_image_data(indices).unwrap();
}

#[test]
fn png_messages_say_what_is_wrong_and_palette_labels_read_as_ids() {
    // A palette pseudo label: its indices are the label ids.
    let (root, p) = fixture("palette");
    let pl = p.path(&p.pseudo_labels, 3, 0);
    let mut ids = vec![labels::ROAD; 32];
    ids[5] = labels::CAR;
    write_palette(&pl, 8, 4, &ids);
    let t = run(&p).unwrap();
    let rows = tables::get_prim::<UInt32Type>(&t["pseudo_labels"], "pseudo_labels", "frame")
        .unwrap()
        .to_vec();
    let row = rows.iter().position(|&f| f == 3).unwrap();
    let got =
        tables::get_list::<UInt8Type>(&t["pseudo_labels"], "pseudo_labels", "labels").unwrap();
    assert_eq!(got.row(row), &ids[..]);
    ids[9] = 200;
    write_palette(&pl, 8, 4, &ids);
    assert_error(
        &p,
        "image_00/0000000003.png",
        &["pixel (1, 1)", "200 is not"],
    );
    std::fs::remove_dir_all(root).unwrap();

    // A right-camera image of the wrong size names the right camera's calibration.
    let (root, p) = fixture("rightsize");
    crate::pngio::write_rgb8(&p.path(&p.images, 7, 1), 4, 4, &[9; 48]).unwrap();
    assert_error(
        &p,
        "image_01/data_rect/0000000007.png",
        &["image is 4x4, expected 8x4 (S_rect_01 in perspective.txt)"],
    );
    std::fs::remove_dir_all(root).unwrap();

    // A header claiming 20000 x 20000 pixels: refused as too large, with its size.
    let (root, p) = fixture("huge");
    let img = p.path(&p.images, 7, 0);
    let mut bytes = std::fs::read(&img).unwrap();
    bytes[16..20].copy_from_slice(&20000u32.to_be_bytes());
    bytes[20..24].copy_from_slice(&20000u32.to_be_bytes());
    let crc = png_crc(&bytes[12..29]);
    bytes[29..33].copy_from_slice(&crc.to_be_bytes());
    std::fs::write(&img, &bytes).unwrap();
    assert_error(
        &p,
        "image_00/data_rect/0000000007.png",
        &["too large to decode: 20000x20000 pixels"],
    );
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn a_directory_for_a_file_parameter_is_refused_naming_the_parameter() {
    let (_root, mut p) = fixture("dir_param");
    p.bboxes = ".".into();
    let e = input_files(&p).unwrap_err().to_string();
    assert!(
        e.contains("parameter `bboxes` (\".\")") && e.contains("is a directory"),
        "{e}"
    );
    let (_root, mut p) = fixture("dir_param_poses");
    p.poses = "data_poses".into();
    let e = input_files(&p).unwrap_err().to_string();
    assert!(e.contains("parameter `poses`"), "{e}");
}
