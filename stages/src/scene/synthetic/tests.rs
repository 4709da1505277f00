//! Tests of the synthetic scene: pseudo-label quality and its response to `noise`, ground truth
//! inside the bounding primitives, intended overlaps, determinism, params, export.

use std::sync::OnceLock;
use std::time::Instant;

use glam::DVec3;

use super::in_memory::to_tables;
use super::*;
use crate::geometry::Primitive;
use crate::kinds::synthetic_scene::SyntheticScene;
use crate::labels::{
    BUILDING, CAR, PAPER_CLASSES, PARKING, ROAD, SIDEWALK, SKY, TERRAIN, VEGETATION,
};
use crate::{NoProgress, Stage};

/// The default scene, generated once for all tests (and timed).
fn default_scene() -> &'static (SceneParams, Generated) {
    static SCENE: OnceLock<(SceneParams, Generated)> = OnceLock::new();
    SCENE.get_or_init(|| {
        let p = SceneParams::default();
        let t0 = Instant::now();
        let g = generate(&p, &NoProgress).unwrap();
        eprintln!(
            "default scene: {} images {}x{}, {} parts, {} primitives, generated in {:.2?}",
            g.images.len(),
            p.image_size().0,
            p.image_size().1,
            g.layout.parts.len(),
            g.layout.bounds.len(),
            t0.elapsed()
        );
        (p, g)
    })
}

/// mIoU (percent) of predictions against GT over the paper's classes (the metrics module's
/// definition: classes present in GT or prediction, GT void ignored).
fn miou(pairs: &[(&[u8], &[u8])]) -> f64 {
    let mut conf = crate::metrics::ConfusionMatrix::new(labels::PAPER_CLASSES).unwrap();
    for (gt, pred) in pairs {
        conf.add(gt, pred).unwrap();
    }
    if std::env::var("SCENE_DEBUG").is_ok() {
        eprintln!("{conf}");
    }
    100.0 * conf.miou().unwrap()
}

fn pseudo_miou(p: &SceneParams, g: &Generated, level: f64) -> f64 {
    let left: Vec<usize> = (0..g.cameras.len())
        .filter(|&i| g.cameras[i].camera == 0)
        .collect();
    let preds: Vec<Vec<u8>> = left
        .iter()
        .map(|&i| {
            let row = &g.cameras[i];
            let inp = noise_input(row, &g.images[i]);
            noise::pseudo_labels(&inp, level, p.seed, row.frame)
        })
        .collect();
    let pairs: Vec<(&[u8], &[u8])> = left
        .iter()
        .zip(&preds)
        .map(|(&i, pr)| (g.images[i].labels.as_slice(), pr.as_slice()))
        .collect();
    miou(&pairs)
}

#[test]
fn pseudo_labels_score_about_67_miou_and_follow_the_noise_level() {
    let (p, g) = default_scene();
    let at_default = pseudo_miou(p, g, p.noise);
    // The stored table was made the same way.
    let left: Vec<usize> = (0..g.cameras.len())
        .filter(|&i| g.cameras[i].camera == 0)
        .collect();
    let stored: Vec<(&[u8], &[u8])> = left
        .iter()
        .zip(&g.pseudo)
        .map(|(&i, pr)| (g.images[i].labels.as_slice(), pr.as_slice()))
        .collect();
    assert_eq!(miou(&stored), at_default);
    let levels = [0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0];
    let scores: Vec<f64> = levels.iter().map(|&l| pseudo_miou(p, g, l)).collect();
    eprintln!(
        "pseudo-label mIoU by noise level: {:?}",
        levels.iter().zip(&scores).collect::<Vec<_>>()
    );
    assert!(
        (62.0..=72.0).contains(&at_default),
        "mIoU at default noise: {at_default:.1}"
    );
    assert_eq!(scores[0], 100.0);
    for k in 1..scores.len() {
        assert!(
            scores[k] < scores[k - 1],
            "mIoU not decreasing with noise: {scores:?}"
        );
    }
}

/// Scene-frame point seen at pixel (x, y) with z-depth `z`.
fn unproject(cam: &crate::geometry::Camera, x: u32, y: u32, z: f64) -> DVec3 {
    let d = cam.dir_cam(x as f64 + 0.5, y as f64 + 0.5).unwrap();
    cam.cam_to_world.transform_point3(d * (z / d.z))
}

#[test]
fn every_gt_pixel_lies_inside_a_primitive_of_its_class() {
    let (_, g) = default_scene();
    assert!(gt_points_inside_primitives(g) > 10_000);
}

#[test]
fn gt_lies_inside_primitives_for_other_seeds_and_windows() {
    for (seed, first_frame) in [(1, 0), (2, 30), (3, 58)] {
        let p = SceneParams {
            seed,
            first_frame,
            frames: 4,
            ..SceneParams::default()
        };
        gt_points_inside_primitives(&generate(&p, &NoProgress).unwrap());
    }
}

/// Asserts that every non-sky GT pixel's 3D point is inside a primitive of its class; returns
/// how many were checked.
fn gt_points_inside_primitives(g: &Generated) -> usize {
    let prims = &g.layout.bounds;
    let bvh = Bvh::build(prims);
    let mut inside = Vec::new();
    let mut checked = 0;
    for (row, img) in g.cameras.iter().zip(&g.images) {
        let w = row.cam.width;
        for (i, &label) in img.labels.iter().enumerate() {
            let z = img.depth[i] as f64;
            if label == SKY {
                assert_eq!(z, 0.0);
                continue;
            }
            let (x, y) = (i as u32 % w, i as u32 / w);
            let q = unproject(&row.cam, x, y, z);
            bvh.containing(prims, q, &mut inside);
            assert!(
                inside.iter().any(|&k| prims[k as usize].label == label),
                "frame {} camera {} pixel ({x}, {y}) of class {label} at {q} (depth {z}) is in \
                 no primitive of its class (in: {:?})",
                row.frame,
                row.camera,
                inside
                    .iter()
                    .map(|&k| prims[k as usize].label)
                    .collect::<Vec<_>>()
            );
            checked += 1;
        }
    }
    checked
}

fn overlap(a: &Primitive, b: &Primitive) -> bool {
    // Sample a's bounding box on a grid; any point in both?
    let bb = a.aabb();
    let n = 24;
    (0..n * n * n).any(|k| {
        let f =
            DVec3::new((k % n) as f64, ((k / n) % n) as f64, (k / n / n) as f64) / (n - 1) as f64;
        let q = bb.min + (bb.max - bb.min) * f;
        a.contains(q) && b.contains(q)
    })
}

#[test]
fn primitives_overlap_at_stuff_thing_boundaries_and_leave_air_between() {
    let (_, g) = default_scene();
    let b = &g.layout.bounds;
    let of = |l: u8| b.iter().filter(move |p| p.label == l);
    let ground: Vec<&Primitive> = b
        .iter()
        .filter(|p| [ROAD, PARKING].contains(&p.label))
        .collect();
    // Every car box reaches into the road or parking slab.
    for car in of(CAR) {
        assert!(
            ground.iter().any(|gp| overlap(car, gp)),
            "car {} floats",
            car.instance
        );
    }
    // Road into parking, parking into the verge, the verge into the sidewalk.
    let road = of(ROAD).next().unwrap();
    assert!(of(PARKING).all(|p| overlap(p, road)));
    assert!(
        of(PARKING).all(|p| of(TERRAIN).any(|v| overlap(p, v))),
        "parking into verge"
    );
    assert!(
        of(SIDEWALK).all(|s| of(TERRAIN).any(|v| overlap(s, v))),
        "sidewalk into verge"
    );
    // Some tree canopy reaches into a building's box.
    let canopy_into_building = of(VEGETATION).any(|v| of(BUILDING).any(|bd| overlap(v, bd)));
    assert!(canopy_into_building);
    // Air: above the road's centre line at 3 m, mostly inside nothing.
    let (x0, x1) = g.layout.x_range;
    let empty = (0..100)
        .map(|k| DVec3::new(x0 + (x1 - x0) * k as f64 / 100.0, 0.0, 3.0))
        .filter(|&q| !b.iter().any(|p| p.contains(q)))
        .count();
    assert!(empty > 80, "{empty} of 100 points above the road are empty");
}

#[test]
fn the_scene_has_every_paper_class_with_unique_thing_instances() {
    let (_, g) = default_scene();
    let mut seen = std::collections::BTreeSet::new();
    for img in g.images.iter().step_by(2) {
        seen.extend(img.labels.iter().copied());
    }
    for &c in PAPER_CLASSES {
        assert!(
            seen.contains(&c),
            "class {} never visible in the left images",
            labels::by_id(c).unwrap().name
        );
    }
    let mut things = std::collections::BTreeSet::new();
    for p in &g.layout.bounds {
        if labels::is_paper_thing(p.label) {
            assert!(p.instance >= 1 && p.instance <= 999);
            assert!(
                things.insert((p.label, p.instance)),
                "duplicate instance {} {}",
                p.label,
                p.instance
            );
        } else {
            assert_eq!(p.instance, 0);
        }
    }
}

#[test]
fn same_params_give_identical_tables_whatever_the_thread_count() {
    let p = SceneParams {
        frames: 3,
        first_frame: 40,
        eval_every: 2,
        ..SceneParams::default()
    };
    let a = to_tables(&p, generate(&p, &NoProgress).unwrap()).unwrap();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let b = pool.install(|| to_tables(&p, generate(&p, &NoProgress).unwrap()).unwrap());
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    for (k, t) in &a {
        assert_eq!(t, &b[k], "table {k} differs");
        crate::schema::check(k, &t.schema()).unwrap();
    }
    assert_eq!(a["cameras"].num_rows(), 6);
    assert_eq!(a["pseudo_labels"].num_rows(), 3);
    assert_eq!(a["lidar_depth"].num_rows(), 2); // frames 40 and 42
    let q = SceneParams {
        seed: 1,
        ..p.clone()
    };
    let c = to_tables(&q, generate(&q, &NoProgress).unwrap()).unwrap();
    assert_ne!(a["images"], c["images"], "the seed changes the scene");
}

/// The stage writes its tables an image at a time as the images are rendered, in parallel;
/// they must equal the tables of the scene generated whole, on any number of threads, with
/// every kind of row (fisheye images with pseudo labels, eval frames with LiDAR).
#[test]
fn streamed_tables_equal_the_scene_generated_whole() {
    let p = SceneParams {
        frames: 3,
        first_frame: 40,
        eval_every: 2,
        cameras: vec![0, 1, 2, 3],
        fisheye_pseudo_labels: true,
        ..SceneParams::default()
    };
    let whole = to_tables(&p, generate(&p, &NoProgress).unwrap()).unwrap();
    let no_slots = crate::stage::Inputs::new(Default::default());
    let streamed = write_tables(&p, &no_slots, &NoProgress).unwrap();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let one_thread = pool.install(|| write_tables(&p, &no_slots, &NoProgress).unwrap());
    assert_eq!(
        whole.keys().collect::<Vec<_>>(),
        streamed.keys().collect::<Vec<_>>()
    );
    for (k, t) in &whole {
        assert_eq!(t, &streamed[k], "table {k} differs");
        assert_eq!(t, &one_thread[k], "table {k} differs on one thread");
    }
    assert_eq!(whole["images"].num_rows(), 12);
    assert_eq!(whole["pseudo_labels"].num_rows(), 9);
    assert_eq!(whole["stereo_depth"].num_rows(), 3);
    assert_eq!(whole["lidar_depth"].num_rows(), 2);
}

#[test]
fn bad_params_are_rejected_with_clear_errors() {
    let kind = SyntheticScene;
    let err = |v: serde_json::Value| kind.canonical_params(&v).unwrap_err().to_string();
    assert!(err(serde_json::json!({"frames": 0})).contains("`frames` must be at least 1"));
    assert!(err(serde_json::json!({"scale": -0.5})).contains("`scale` must be positive"));
    let e = err(serde_json::json!({"classes": ["road", "terrain", "sky", "unicorn"]}));
    assert!(e.contains("unknown class `unicorn`"), "{e}");
    assert!(err(serde_json::json!({"classes": ["terrain", "sky"]})).contains("`road`"));
    assert!(err(serde_json::json!({"first_frame": 60})).contains("run past the street"));
    assert!(err(serde_json::json!({"noise": -1.0})).contains("`noise`"));
    assert!(err(serde_json::json!({"texture": 1.5})).contains("`texture` must be in [0, 1]"));
    assert!(err(serde_json::json!({"supersample": 0})).contains("`supersample` must be 1..=8"));
    assert!(err(serde_json::json!({"supersample": 9})).contains("`supersample` must be 1..=8"));
    assert!(err(serde_json::json!({"colour": 1})).contains("unknown field"));
    let ok = kind.canonical_params(&serde_json::json!({})).unwrap();
    assert_eq!(ok, kind.default_params());
}

#[test]
fn fewer_classes_leave_those_objects_out() {
    let p = SceneParams {
        frames: 2,
        classes: ["road", "terrain", "sky", "building"]
            .map(String::from)
            .to_vec(),
        ..SceneParams::default()
    };
    let g = generate(&p, &NoProgress).unwrap();
    let allowed = [ROAD, TERRAIN, SKY, BUILDING];
    assert!(g.layout.bounds.iter().all(|b| allowed.contains(&b.label)));
    assert!(g
        .images
        .iter()
        .all(|i| i.labels.iter().all(|l| allowed.contains(l))));
}

#[test]
fn stereo_and_lidar_depth_behave_like_their_sensors() {
    let (p, g) = default_scene();
    let left: Vec<usize> = (0..g.cameras.len())
        .filter(|&i| g.cameras[i].camera == 0)
        .collect();
    let (mut n, mut err, mut holes, mut near) = (0usize, 0.0, 0usize, 0usize);
    for (k, &i) in left.iter().enumerate() {
        for (j, &s) in g.stereo[k].iter().enumerate() {
            let z = g.images[i].depth[j];
            if z > 0.0 && (z as f64) < p.stereo_max_depth_m * 0.9 {
                near += 1;
                if s == 0.0 {
                    holes += 1;
                }
            }
            if s > 0.0 {
                assert!((s as f64) < p.stereo_max_depth_m);
                n += 1;
                err += (s - z).abs() as f64;
            }
        }
    }
    let mae = err / n as f64;
    eprintln!("stereo: {n} values, MAE {mae:.3} m, {holes} holes of {near} near pixels");
    assert!(mae > 0.02 && mae < 1.5, "{mae}");
    assert!(holes > near / 20 && holes < near / 2);
    assert_eq!(g.lidar.len(), 4);
    let (mut m, mut lerr) = (0usize, 0.0);
    for (f, d) in &g.lidar {
        let i = g
            .cameras
            .iter()
            .position(|r| r.frame == *f && r.camera == 0)
            .unwrap();
        for (j, &z) in d.iter().enumerate() {
            if z > 0.0 {
                assert!(z < 100.0);
                let gt = g.images[i].depth[j];
                // Projected points are not pixel centres: compare only on smooth surfaces.
                if gt > 0.0 && (z - gt).abs() < 1.0 {
                    m += 1;
                    lerr += (z - gt).abs() as f64;
                }
            }
        }
    }
    let total: usize = g.lidar.iter().map(|(_, d)| d.len()).sum();
    eprintln!(
        "lidar: {m} of {total} pixels, mean |z - gt| {:.3} m",
        lerr / m as f64
    );
    assert!(m > total / 20 && m < total);
}

#[test]
fn export_writes_the_kitti360_layout() {
    let p = SceneParams {
        frames: 2,
        ..SceneParams::default()
    };
    let t = to_tables(&p, generate(&p, &NoProgress).unwrap()).unwrap();
    let dir = std::env::temp_dir().join(format!("scene-export-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let files = Stage::export(
        &SyntheticScene,
        &serde_json::to_value(&p).unwrap(),
        &t.clone().into(),
        &dir,
    )
    .unwrap();
    let seq = &p.sequence;
    let f0 = format!("{:010}", p.first_frame);
    for rel in [
        format!("data_2d_raw/{seq}/image_00/data_rect/{f0}.png"),
        format!("data_2d_raw/{seq}/image_01/data_rect/{f0}.png"),
        format!("data_poses/{seq}/cam0_to_world.txt"),
        "calibration/perspective.txt".to_string(),
        format!("data_3d_bboxes/train/{seq}.xml"),
        format!("data_2d_semantics/train/{seq}/image_00/semantic/{f0}.png"),
        format!("data_2d_semantics/train/{seq}/image_00/instance/{f0}.png"),
        format!("pseudo_labels/{seq}/image_00/{f0}.png"),
        format!("previews/{f0}.png"),
    ] {
        assert!(files.contains(&dir.join(&rel)), "missing {rel}");
    }
    // Poses: frame + 16 numbers, world = scene + origin.
    let poses =
        std::fs::read_to_string(dir.join(format!("data_poses/{seq}/cam0_to_world.txt"))).unwrap();
    let first: Vec<f64> = poses
        .lines()
        .next()
        .unwrap()
        .split(' ')
        .map(|s| s.parse().unwrap())
        .collect();
    assert_eq!(first.len(), 17);
    assert_eq!(first[0], p.first_frame as f64);
    let cam = &rig(&p, p.first_frame)[0];
    assert_eq!(first[4], cam.cam_to_world.translation.x + p.origin[0]);
    // Calibration: P_rect_01[0,3] = -fx * baseline.
    let calib = std::fs::read_to_string(dir.join("calibration/perspective.txt")).unwrap();
    let p01: Vec<f64> = calib
        .lines()
        .find_map(|l| l.strip_prefix("P_rect_01: "))
        .unwrap()
        .split(' ')
        .map(|s| s.parse().unwrap())
        .collect();
    assert!((-p01[3] / p01[0] - p.baseline_m).abs() < 1e-12);
    assert_eq!(p01[2], cam.cx - 0.5);
    assert!(calib.contains(&format!("S_rect_00: {} {}", cam.width, cam.height)));
    // Bboxes: one object per primitive with the devkit's fields.
    let xml = std::fs::read_to_string(dir.join(format!("data_3d_bboxes/train/{seq}.xml"))).unwrap();
    let n = t["primitives"].num_rows();
    assert_eq!(
        xml.matches("<transform type_id=\"opencv-matrix\">").count(),
        n
    );
    for tag in [
        "<vertices",
        "<faces",
        "<semanticId>",
        "<instanceId>",
        "<timestamp>-1</timestamp>",
        "<index>",
        "<start_frame>",
        "<end_frame>",
    ] {
        assert_eq!(xml.matches(tag).count(), n, "{tag}");
    }
    // Every matrix has rows * cols values, also when split on single spaces like the devkit.
    for block in xml.split("type_id=\"opencv-matrix\">").skip(1) {
        let get = |tag: &str| {
            let a = block.find(&format!("<{tag}>")).unwrap() + tag.len() + 2;
            let b = block.find(&format!("</{tag}>")).unwrap();
            block[a..b].to_string()
        };
        let (rows, cols): (usize, usize) =
            (get("rows").parse().unwrap(), get("cols").parse().unwrap());
        let values: Vec<f64> = get("data")
            .split(' ')
            .map(|d| d.replace('\n', ""))
            .filter(|d| !d.is_empty())
            .map(|d| d.parse().unwrap())
            .collect();
        assert_eq!(values.len(), rows * cols);
    }
    // Instance PNG: 16-bit id*1000+instance.
    let inst = image::open(dir.join(format!(
        "data_2d_semantics/train/{seq}/image_00/instance/{f0}.png"
    )))
    .unwrap()
    .into_luma16();
    assert_eq!((inst.width(), inst.height()), (cam.width, cam.height));
    assert!(inst.pixels().any(|v| v.0[0] == SKY as u16 * 1000));
    assert!(inst
        .pixels()
        .any(|v| v.0[0] / 1000 == CAR as u16 && v.0[0] % 1000 > 0));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn local_meshes_are_closed_and_outward() {
    use crate::geometry::Shape;
    use crate::scene::kitti360_export::local_mesh;
    let shapes = [
        Shape::Cuboid,
        Shape::Ellipsoid,
        Shape::Extruded {
            polygon: vec![[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [1.0, 0.3], [0.0, 1.0]],
        },
    ];
    for s in shapes {
        let (v, f) = local_mesh(&s);
        // Divergence theorem: volume > 0 for outward faces; Primitive::new checks closure.
        let vol: f64 = f
            .iter()
            .map(|t| v[t[0] as usize].dot(v[t[1] as usize].cross(v[t[2] as usize])) / 6.0)
            .sum();
        assert!(vol > 0.0, "{s:?}: volume {vol}");
        Primitive::new(
            Shape::Mesh {
                vertices: v,
                faces: f,
            },
            glam::DAffine3::IDENTITY,
            7,
            0,
        )
        .unwrap();
    }
}

#[test]
fn pseudo_label_quality_is_similar_for_other_seeds() {
    for seed in 1..4 {
        let p = SceneParams {
            seed,
            ..SceneParams::default()
        };
        let g = generate(&p, &NoProgress).unwrap();
        let m = pseudo_miou(&p, &g, p.noise);
        eprintln!("seed {seed}: pseudo-label mIoU {m:.1}");
        assert!((50.0..=80.0).contains(&m), "seed {seed}: mIoU {m:.1}");
    }
}

#[test]
fn the_rig_is_a_rectified_stereo_pair_looking_down_the_street() {
    let p = SceneParams::default();
    let [l, r] = rig(&p, 30);
    // Right camera: shifted by the baseline along the left camera's x axis (to the right,
    // i.e. towards -y in the scene frame), same orientation.
    let shift = l.cam_to_world.matrix3.transpose() * (r.centre() - l.centre());
    assert!((shift - DVec3::new(p.baseline_m, 0.0, 0.0)).length() < 1e-12);
    assert!(r.centre().y < l.centre().y);
    assert_eq!(l.cam_to_world.matrix3, r.cam_to_world.matrix3);
    // A point 10 m ahead: disparity fx * b / z, the horizon near the image's middle row.
    let q = l.cam_to_world.transform_point3(DVec3::new(0.0, 0.0, 10.0));
    let (ul, vl, z) = l.project(q).unwrap();
    let (ur, vr, _) = r.project(q).unwrap();
    assert!((ul - ur - l.fx * p.baseline_m / z).abs() < 1e-9);
    assert!((vl - vr).abs() < 1e-9);
    assert!(q.x > l.centre().x + 9.9, "looks along +x");
    assert!((l.centre().z - p.camera_height_m).abs() < 1e-12);
    assert_eq!((l.width, l.height), (176, 47));
}

#[test]
fn exported_meshes_match_the_primitives() {
    use crate::geometry::Shape;
    use crate::scene::kitti360_export::local_mesh;
    let (_, g) = default_scene();
    let mut r = crate::scene::rng::Rng::new(9, crate::scene::rng::Purpose::Layout, &[]);
    for (i, p) in g.layout.bounds.iter().enumerate() {
        let (v, f) = local_mesh(&p.shape);
        let m = Primitive::new(
            Shape::Mesh {
                vertices: v,
                faces: f,
            },
            p.to_world,
            p.label,
            p.instance,
        )
        .unwrap_or_else(|e| panic!("primitive {i} ({}) exports a bad mesh: {e}", p.shape.kind()));
        if matches!(p.shape, Shape::Ellipsoid) {
            continue; // the tessellation is inscribed: slightly smaller
        }
        let bb = p.aabb();
        for _ in 0..200 {
            let q = bb.min + (bb.max - bb.min) * DVec3::new(r.f64(), r.f64(), r.f64());
            assert_eq!(
                m.contains(q),
                p.contains(q),
                "primitive {i} ({}) at {q}",
                p.shape.kind()
            );
        }
    }
}

#[test]
fn the_intersect_stage_accepts_the_scene() {
    let p = SceneParams {
        frames: 2,
        ..SceneParams::default()
    };
    let t = to_tables(&p, generate(&p, &NoProgress).unwrap()).unwrap();
    let kind = crate::kinds::find("intersect").expect("intersect kind registered");
    let mem = crate::MemoryInputs::new([("scene", t)]);
    let out = kind
        .run(&kind.default_params(), &mem.inputs(), &NoProgress)
        .unwrap();
    assert!(!out.is_empty());
}

/// The side fisheye cameras: rendered exactly through MEI's model (a GT depth pixel lifted to
/// 3D projects back onto itself and lies on the first surface its ray meets), black and
/// unlabelled outside the lens circle, looking at the street's sides, with pseudo labels only
/// when asked.
#[test]
fn fisheye_cameras_render_the_street_through_their_lens() {
    let p = SceneParams {
        frames: 2,
        cameras: vec![0, 1, 2, 3],
        fisheye_pseudo_labels: true,
        ..Default::default()
    };
    let g = generate(&p, &NoProgress).unwrap();
    let cams: Vec<(u32, u8)> = g.cameras.iter().map(|r| (r.frame, r.camera)).collect();
    assert_eq!(
        cams,
        vec![
            (20, 0),
            (20, 1),
            (20, 2),
            (20, 3),
            (21, 0),
            (21, 1),
            (21, 2),
            (21, 3)
        ]
    );
    assert_eq!(g.labelled, vec![0, 2, 3, 4, 6, 7]);
    let bvh = Bvh::build(&g.layout.parts);
    for (row, img) in g
        .cameras
        .iter()
        .zip(&g.images)
        .filter(|(r, _)| r.camera >= 2)
    {
        let cam = &row.cam;
        assert_eq!((cam.width, cam.height), (175, 175));
        let (mut outside, mut checked) = (0, 0);
        for y in 0..cam.height {
            for x in 0..cam.width {
                let i = (y * cam.width + x) as usize;
                let Some(ray) = cam.pixel_ray(x, y) else {
                    outside += 1;
                    assert_eq!(img.labels[i], labels::UNLABELED);
                    assert_eq!(&img.rgb[i * 3..i * 3 + 3], &[0, 0, 0]);
                    continue;
                };
                if img.depth[i] <= 0.0 || (x + y) % 7 != 0 {
                    continue;
                }
                // Fisheye depth maps hold the distance along the ray.
                let t = img.depth[i] as f64;
                let q = ray.at(t);
                let (u, v, _) = cam.project(q).expect("a lens pixel's point projects");
                assert!((u - x as f64 - 0.5).abs() < 1e-3 && (v - y as f64 - 0.5).abs() < 1e-3);
                let hit = bvh
                    .first_hit(&g.layout.parts, &ray, 0.0, 1e4)
                    .expect("a pixel with depth hits a part");
                assert!(
                    (hit.t_in - t).abs() < 1e-3 * t.max(1.0),
                    "{} vs {t}",
                    hit.t_in
                );
                checked += 1;
            }
        }
        let n = (cam.width * cam.height) as usize;
        assert!(checked > 500, "{checked}");
        // The lens circle leaves the corners dark: 10-30 % of the square.
        assert!(
            (n / 10..n * 3 / 10).contains(&outside),
            "{outside} of {n} outside"
        );
        let share = |l: u8| img.labels.iter().filter(|&&x| x == l).count() as f64 / n as f64;
        assert!(share(labels::ROAD) > 0.05 && share(SKY) > 0.05);
        // The street's side: buildings, vegetation, parked cars (7.6 %, 2.1 % and 1.2 % of
        // camera 2's first frame).
        assert!(share(BUILDING) + share(VEGETATION) + share(CAR) > 0.05);
    }
    // The left cameras' pseudo labels are those of a scene without fisheye cameras.
    let plain = generate(
        &SceneParams {
            frames: 2,
            ..Default::default()
        },
        &NoProgress,
    )
    .unwrap();
    assert_eq!(g.pseudo[0], plain.pseudo[0]);
    assert_eq!(g.pseudo[3], plain.pseudo[1]);
    let cameras = g.cameras.clone();
    let t = to_tables(&p, g).unwrap();
    assert_eq!(t["pseudo_labels"].num_rows(), 6);
    assert_eq!(t["images"].num_rows(), 8);
    let back = crate::geometry::cameras_from_table(&t["cameras"]).unwrap();
    assert_eq!(back, cameras);
}

#[test]
fn flat_textures_change_the_look_only_and_lower_the_road_contrast() {
    // Mean absolute difference of horizontally adjacent road pixels (green) in the first left
    // image. At 1/8 scale the sensor noise and shading dominate it (13.9 at texture 1, 12.7 at
    // 0): the asphalt's grain is a small part of what a pixel sees. The exact effect on the
    // albedo is held by the tracer's test; here, that the image follows it.
    let p = |texture| SceneParams {
        frames: 1,
        texture,
        ..SceneParams::default()
    };
    let road_contrast = |g: &Generated| {
        let img = &g.images[0];
        let w = g.cameras[0].cam.width as usize;
        let (mut sum, mut n) = (0.0, 0usize);
        for i in 0..img.labels.len() - 1 {
            if (i + 1) % w != 0 && img.labels[i] == ROAD && img.labels[i + 1] == ROAD {
                sum += (img.rgb[i * 3 + 1] as f64 - img.rgb[(i + 1) * 3 + 1] as f64).abs();
                n += 1;
            }
        }
        sum / n as f64
    };
    let rich = generate(&p(1.0), &NoProgress).unwrap();
    let flat = generate(&p(0.0), &NoProgress).unwrap();
    let (a, b) = (road_contrast(&rich), road_contrast(&flat));
    assert!(
        b < 0.95 * a,
        "road contrast {a:.2} at texture 1, {b:.2} at 0"
    );
    assert_ne!(rich.images[0].rgb, flat.images[0].rgb);
    // Same geometry, labels and depth: texture is the look only.
    assert_eq!(rich.images[0].labels, flat.images[0].labels);
    assert_eq!(rich.images[0].depth, flat.images[0].depth);
}

#[test]
fn supersampled_colour_is_the_mean_over_a_finer_grid_and_labels_stay_the_centre_rays() {
    // A pixel's 3 x 3 sub-pixel rays are the centre rays of the 3x finer camera's pixels, so
    // the supersampled radiance must equal the mean of that camera's nine pixels: an
    // independent route to the sub-pixel placement.
    let p = SceneParams {
        frames: 1,
        ..SceneParams::default()
    };
    let layout = layout::build(&p.layout_params().unwrap());
    let bvh = crate::geometry::Bvh::build(&layout.parts);
    let world = tracer::World::at(&layout, &bvh, p.first_frame);
    let cam = rig(&p, p.first_frame)[0].clone();
    let fine = crate::geometry::Camera {
        width: cam.width * 3,
        height: cam.height * 3,
        fx: cam.fx * 3.0,
        fy: cam.fy * 3.0,
        cx: cam.cx * 3.0,
        cy: cam.cy * 3.0,
        ..cam.clone()
    };
    let (mut mixed, mut moved, mut knife_edges) = (0, 0, 0);
    for y in 0..cam.height {
        for x in 0..cam.width {
            let centre = tracer::trace(&world, &cam.pixel_ray(x, y).unwrap());
            let got =
                tracer::pixel_radiance(&world, &cam, (x as usize, y as usize), 3, centre.radiance);
            let mut want = [0.0; 3];
            let mut classes = std::collections::BTreeSet::new();
            for j in 0..3 {
                for i in 0..3 {
                    let ray = fine.pixel_ray(3 * x + i, 3 * y + j).unwrap();
                    let (u, v) = (
                        x as f64 + (i as f64 + 0.5) / 3.0,
                        y as f64 + (j as f64 + 0.5) / 3.0,
                    );
                    assert!((cam.ray(u, v).unwrap().dir - ray.dir).length() < 1e-12);
                    let s = tracer::trace(&world, &ray);
                    classes.insert(s.label);
                    for (w, r) in want.iter_mut().zip(s.radiance) {
                        *w += r / 9.0;
                    }
                }
            }
            if (0..3).any(|k| (got[k] - want[k]).abs() > 1e-9) {
                knife_edges += 1;
            }
            if classes.len() > 1 {
                mixed += 1;
                moved += (0..3).any(|k| (got[k] - centre.radiance[k]).abs() > 1e-3) as usize;
            }
        }
    }
    // The two routes give rays equal to the last few bits (asserted above); a sub-ray that
    // grazes a texture edge or a shadow ray along a coplanar face can still flip on those bits
    // (12 of 8272 pixels here).
    assert!(
        knife_edges * 200 <= cam.width * cam.height,
        "{knife_edges} pixels differ from the finer camera's mean"
    );
    // Pixels straddling a class boundary are where the mean differs from the centre ray.
    assert!(
        mixed > 300 && moved * 10 > mixed * 9,
        "{moved} of {mixed} mixed pixels moved"
    );

    let g1 = generate(&p, &NoProgress).unwrap();
    let g3 = generate(
        &SceneParams {
            supersample: 3,
            ..p.clone()
        },
        &NoProgress,
    )
    .unwrap();
    for (a, b) in g1.images.iter().zip(&g3.images) {
        assert_eq!(a.labels, b.labels);
        assert_eq!(a.instances, b.instances);
        assert_eq!(a.depth, b.depth);
        assert_ne!(a.rgb, b.rgb);
    }
}

mod movers;
