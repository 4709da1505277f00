//! The fisheye cameras of the KITTI-360 layout: MEI intrinsics from `image_02.yaml`, placed by
//! `poses.txt * calib_cam_to_pose.txt`, which must agree with `cam0_to_world.txt`.

use super::*;
use crate::geometry::{Lens, Mei};
use crate::scene::synthetic::SceneParams;

/// Camera 0 -> pose frame: half a metre behind the pose frame's origin along x.
const CAM0_TO_POSE: [f64; 12] = [1., 0., 0., 0.2, 0., 1., 0., 0., 0., 0., 1., 0.];
/// image_02 -> pose frame: looking along -x of camera 0 (left), its x along camera 0's z.
const CAM2_TO_POSE: [f64; 12] = [0., 0., -1., 0.1, 0., 1., 0., 0., 1., 0., 0., 0.5];

fn line(m: &[f64]) -> String {
    m.iter()
        .map(|v| format!("{v:e}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// The hand-written fixture plus image_02: its calibration, `poses.txt` consistent with
/// `cam0_to_world.txt`, and 12x12 fisheye images of frames 3, 7 and 12.
fn fisheye_fixture(name: &str) -> (PathBuf, Kitti360Params) {
    let (root, mut p) = fixture(name);
    p.cameras = vec![0, 2];
    std::fs::write(
        p.file(&p.cam_to_pose),
        format!(
            "image_00: {}\nimage_02: {}\n",
            line(&CAM0_TO_POSE),
            line(&CAM2_TO_POSE)
        ),
    )
    .unwrap();
    // pose = cam0_to_world * inverse(cam0_to_pose): the same x, 0.2 m less.
    let poses: String = [(3, 100.0), (7, 101.0), (12, 102.0)]
        .iter()
        .map(|(f, z)| format!("{f} 1 0 0 1000.3 0 1 0 2000.25 0 0 1 {z}\n"))
        .collect();
    std::fs::write(p.file(&p.imu_poses), poses).unwrap();
    std::fs::write(
        p.path(&p.fisheye_calibration, 0, 2),
        "%YAML:1.0\n---\nmodel_type: MEI\ncamera_name: image_02\nimage_width: 12\n\
         image_height: 12\nmirror_parameters:\n   xi: 2.2\ndistortion_parameters:\n   k1: 0.02\n\
         \x20  k2: 1.6\n   p1: 4.0e-04\n   p2: -3.0e-04\nprojection_parameters:\n   gamma1: 11.5\n\
         \x20  gamma2: 11.4\n   u0: 5.6\n   v0: 5.4\n",
    )
    .unwrap();
    for f in [3u32, 7, 12] {
        let rgb: Vec<u8> = (0..12 * 12 * 3).map(|i| (i as u32 * 7 + f) as u8).collect();
        crate::pngio::write_rgb8(&p.path(&p.fisheye_images, f, 2), 12, 12, &rgb).unwrap();
    }
    (root, p)
}

#[test]
fn fisheye_cameras_load_by_name_with_their_lens_and_pose() {
    let (root, mut p) = fisheye_fixture("fisheye");
    p = serde_json::from_value(serde_json::json!({
        "root": p.root, "sequence": "seq_a", "first_frame": 0, "last_frame": 10,
        "eval_every": 1, "cameras": ["image_00", "image_02"],
    }))
    .unwrap();
    let t = run(&p).unwrap();
    let cams = cameras_from_table(&t["cameras"]).unwrap();
    let keys: Vec<(u32, u8)> = cams.iter().map(|r| (r.frame, r.camera)).collect();
    assert_eq!(keys, vec![(3, 0), (3, 2), (7, 0), (7, 2)]);
    let fe = &cams[1].cam;
    assert_eq!((fe.width, fe.height, fe.fx, fe.fy), (12, 12, 11.5, 11.4));
    assert_eq!((fe.cx, fe.cy), (6.1, 5.9)); // OpenCV u0, v0 + half a pixel
    assert_eq!(
        fe.lens,
        Lens::Mei(Mei {
            xi: 2.2,
            k1: 0.02,
            k2: 1.6,
            p1: 4e-4,
            p2: -3e-4,
            max_half_angle_deg: crate::geometry::FISHEYE_HALF_ANGLE_DEG,
        })
    );
    // Camera -> world = pose * cam_to_pose, recentred on the origin (1001, 2000, 100):
    // (1000.3 + 0.1, 2000.25, 100 + 0.5) - origin.
    assert!((fe.centre() - DVec3::new(-0.6, 0.25, 0.5)).length() < 1e-9);
    let z = fe.cam_to_world.transform_vector3(DVec3::Z);
    assert!((z - DVec3::new(-1.0, 0.0, 0.0)).length() < 1e-12, "{z}");
    // The left camera is where cam0_to_world.txt puts it.
    assert!((cams[0].cam.centre() - DVec3::new(-0.5, 0.25, 0.0)).length() < 1e-12);
    // Images at the fisheye's size; pseudo labels only for the left camera (none given for
    // the fisheye), and no GT for it (KITTI-360 has none).
    let sizes = |table: &str| -> Vec<(u8, u32)> {
        let c = tables::get_prim::<UInt8Type>(&t[table], table, "camera").unwrap();
        let w = tables::get_prim::<UInt32Type>(&t[table], table, "width").unwrap();
        c.iter().copied().zip(w.iter().copied()).collect()
    };
    assert_eq!(sizes("images"), vec![(0, 8), (2, 12), (0, 8), (2, 12)]);
    assert_eq!(sizes("pseudo_labels"), vec![(0, 8), (0, 8)]);
    assert_eq!(sizes("gt_semantic"), vec![(0, 8), (0, 8)]);
    // Every file read is an input of the stage's key.
    let files = input_files(&p).unwrap();
    for f in [
        p.file(&p.cam_to_pose),
        p.file(&p.imu_poses),
        p.path(&p.fisheye_calibration, 0, 2),
        p.path(&p.fisheye_images, 7, 2),
    ] {
        assert!(files.contains(&f), "{}", f.display());
    }
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn fisheye_pseudo_labels_are_read_when_named() {
    let (root, mut p) = fisheye_fixture("fisheye-pseudo");
    p.fisheye_pseudo_labels = Some("pseudo_labels/{seq}/image_{cam}/{frame}.png".into());
    for f in [3u32, 7] {
        let pl = vec![7u8; 144];
        let path = p.path(p.fisheye_pseudo_labels.as_ref().unwrap(), f, 2);
        crate::pngio::write_gray8(&path, 12, 12, &pl).unwrap();
    }
    let t = run(&p).unwrap();
    let c = tables::get_prim::<UInt8Type>(&t["pseudo_labels"], "pseudo_labels", "camera").unwrap();
    assert_eq!(c, &[0, 2, 0, 2]);
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn bad_fisheye_inputs_name_the_file_and_what_is_wrong() {
    type Edit = fn(&Kitti360Params);
    let cases: [(&str, Edit, &[&str]); 5] = [
        (
            "chain",
            |p| {
                let path = p.file(&p.imu_poses);
                let text = std::fs::read_to_string(&path).unwrap();
                std::fs::write(&path, text.replace("1 101\n", "1 101.5\n")).unwrap();
            },
            &[
                "cam0_to_world.txt",
                "poses.txt",
                "frame 7",
                "disagree by 0.500 m",
            ],
        ),
        (
            "model",
            |p| {
                let path = p.path(&p.fisheye_calibration, 0, 2);
                let text = std::fs::read_to_string(&path).unwrap();
                std::fs::write(&path, text.replace("MEI", "PINHOLE")).unwrap();
            },
            &["image_02.yaml", "only MEI"],
        ),
        (
            "xi",
            |p| {
                let path = p.path(&p.fisheye_calibration, 0, 2);
                let text = std::fs::read_to_string(&path).unwrap();
                std::fs::write(&path, text.replace("xi: 2.2", "xi: -1")).unwrap();
            },
            &["image_02.yaml", "`mirror_parameters.xi` must be > 0"],
        ),
        (
            "size",
            |p| {
                let rgb = vec![0u8; 10 * 12 * 3];
                crate::pngio::write_rgb8(&p.path(&p.fisheye_images, 7, 2), 10, 12, &rgb).unwrap();
            },
            &["image_02/data_rgb/0000000007.png", "12x12"],
        ),
        (
            "extrinsics",
            |p| {
                std::fs::write(
                    p.file(&p.cam_to_pose),
                    format!("image_00: {}\n", line(&CAM0_TO_POSE)),
                )
                .unwrap();
            },
            &["calib_cam_to_pose.txt", "no `image_02` line"],
        ),
    ];
    for (name, edit, want) in cases {
        let (root, p) = fisheye_fixture(&format!("fisheye-bad-{name}"));
        edit(&p);
        let e = run(&p).unwrap_err().to_string();
        for w in want {
            assert!(e.contains(w), "{name}: `{w}` not in: {e}");
        }
        std::fs::remove_dir_all(root).unwrap();
    }
    // Cameras by a name KITTI-360 does not have.
    for bad in [r#"["image_05"]"#, r#"["cam0"]"#] {
        let v: serde_json::Value = serde_json::from_str(&format!(
            r#"{{"root": "r", "sequence": "s", "cameras": {bad}}}"#
        ))
        .unwrap();
        let e = Stage::canonical_params(&Kitti360Scene, &v)
            .unwrap_err()
            .to_string();
        assert!(e.contains("image_00 .. image_03"), "{bad}: {e}");
    }
}

/// A synthetic scene with fisheye cameras, exported in the KITTI-360 layout (fisheye images,
/// `image_0K.yaml`, `calib_cam_to_pose.txt`, `poses.txt`, their pseudo labels) and loaded back,
/// gives the synthetic tables: images, labels and GT byte for byte, cameras (lens included) to
/// 1e-9.
#[test]
fn the_exported_fisheye_scene_loads_back_into_equal_tables() {
    let sp = SceneParams {
        frames: 3,
        cameras: vec![0, 1, 2, 3],
        fisheye_pseudo_labels: true,
        ..Default::default()
    };
    let g = crate::scene::synthetic::generate(&sp, &NoProgress).unwrap();
    let synth = crate::scene::synthetic::in_memory::to_tables(&sp, g).unwrap();
    let root = temp("roundtrip-fisheye");
    kitti360_export::write(&synth, &root).unwrap();
    for f in [
        "calibration/image_02.yaml",
        "calibration/image_03.yaml",
        "calibration/calib_cam_to_pose.txt",
        "data_poses/2099_01_01_drive_0000_sync/poses.txt",
        "data_2d_raw/2099_01_01_drive_0000_sync/image_03/data_rgb/0000000021.png",
    ] {
        assert!(root.join(f).is_file(), "{f}");
    }
    let p: Kitti360Params = serde_json::from_value(serde_json::json!({
        "root": root.display().to_string(),
        "sequence": sp.sequence,
        "first_frame": sp.first_frame,
        "last_frame": sp.first_frame + sp.frames - 1,
        "eval_every": sp.eval_every,
        "origin": sp.origin,
        "name": sp.name,
        "max_distance_m": 1.0e6,
        "cameras": ["image_00", "image_01", "image_02", "image_03"],
        "fisheye_pseudo_labels": crate::scene::kitti360::FISHEYE_PSEUDO_LABELS_PATTERN,
    }))
    .unwrap();
    let loaded = run(&p).unwrap();
    for name in ["images", "pseudo_labels", "gt_semantic", "gt_instance"] {
        assert_eq!(synth[name], loaded[name], "table {name} differs");
    }
    let (a, b) = (
        cameras_from_table(&synth["cameras"]).unwrap(),
        cameras_from_table(&loaded["cameras"]).unwrap(),
    );
    assert_eq!(a.len(), 12);
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!((x.frame, x.camera, x.eval), (y.frame, y.camera, y.eval));
        assert_eq!(x.cam.lens, y.cam.lens);
        let (ia, ib) = (
            [x.cam.fx, x.cam.fy, x.cam.cx, x.cam.cy],
            [y.cam.fx, y.cam.fy, y.cam.cx, y.cam.cy],
        );
        assert!(
            ia.iter().zip(ib).all(|(u, v)| (u - v).abs() < 1e-9),
            "{ia:?} {ib:?}"
        );
        assert!(
            x.cam.cam_to_world.abs_diff_eq(y.cam.cam_to_world, 1e-9),
            "frame {} camera {}",
            x.frame,
            x.camera
        );
    }
    std::fs::remove_dir_all(root).unwrap();
}

/// The exported MEI calibration read by a separate implementation of the model, written here
/// from the formulas of KITTI-360's devkit (REFERENCE.md section 4) in its own pixel
/// convention: the same 3D point lands on the same pixel as through the pipeline's camera.
#[test]
fn an_independent_mei_projection_of_the_exported_calibration_agrees() {
    let sp = SceneParams {
        frames: 1,
        cameras: vec![0, 1, 2, 3],
        ..Default::default()
    };
    let g = crate::scene::synthetic::generate(&sp, &NoProgress).unwrap();
    let synth = crate::scene::synthetic::in_memory::to_tables(&sp, g).unwrap();
    let root = temp("independent-mei");
    kitti360_export::write(&synth, &root).unwrap();
    let text = std::fs::read_to_string(root.join("calibration/image_02.yaml")).unwrap();
    // A deliberately plain reader: `key: value` lines.
    let get = |key: &str| -> f64 {
        text.lines()
            .find_map(|l| l.trim().strip_prefix(&format!("{key}:")))
            .unwrap_or_else(|| panic!("{key}"))
            .trim()
            .parse()
            .unwrap()
    };
    let (xi, k1, k2, p1, p2) = (get("xi"), get("k1"), get("k2"), get("p1"), get("p2"));
    let (g1, g2, u0, v0) = (get("gamma1"), get("gamma2"), get("u0"), get("v0"));
    // The devkit's projection: OpenCV pixel coordinates (pixel centres at integers).
    let project = |x: f64, y: f64, z: f64| -> (f64, f64) {
        let n = (x * x + y * y + z * z).sqrt();
        let (x, y, z) = (x / n, y / n, z / n);
        let (mx, my) = (x / (z + xi), y / (z + xi));
        let r2 = mx * mx + my * my;
        let radial = 1.0 + k1 * r2 + k2 * r2 * r2;
        let dx = mx * radial + 2.0 * p1 * mx * my + p2 * (r2 + 2.0 * mx * mx);
        let dy = my * radial + p1 * (r2 + 2.0 * my * my) + 2.0 * p2 * mx * my;
        (g1 * dx + u0, g2 * dy + v0)
    };
    let cam = &cameras_from_table(&synth["cameras"]).unwrap()[2].cam;
    assert_eq!(cam.lens.name(), "MEI");
    let mut rng = crate::rng::SplitMix64::new(11);
    let mut checked = 0;
    for _ in 0..500 {
        let q = DVec3::new(
            rng.uniform(-20.0, 20.0) as f64,
            rng.uniform(-5.0, 5.0) as f64,
            rng.uniform(-20.0, 20.0) as f64,
        );
        let world = cam.cam_to_world.transform_point3(q);
        let Some((u, v, _)) = cam.project(world) else {
            continue;
        };
        let (ud, vd) = project(q.x, q.y, q.z);
        // Ours has pixel (0, 0) spanning [0, 1): half a pixel more than OpenCV's.
        assert!(
            (u - 0.5 - ud).abs() < 1e-6 && (v - 0.5 - vd).abs() < 1e-6,
            "{q}: ({u}, {v}) vs devkit ({ud}, {vd})"
        );
        checked += 1;
    }
    assert!(checked > 200, "{checked}");
    std::fs::remove_dir_all(root).unwrap();
}
