//! Numeric stress: volume rendering under extreme density and spacing, KITTI-360 coordinates
//! offset by 1e4 m, rays parallel to cuboid faces and along edges, rays that hit nothing,
//! single-class scenes, and training on pseudo labels that are all wrong. Everything must stay
//! finite and, where the answer is known, right.
//!
//! Every loss with sigma up to 1e10 and delta down to 1e-9 (fixed cases, losses and gradients)
//! is covered by `extreme_inputs_give_finite_losses_and_gradients` in
//! stages/src/train/loss.rs; here the renderer's invariants are checked on random mixtures of
//! such values, and the stages run end to end (loader -> intersect -> train -> render ->
//! evaluate) on small scenes written in the KITTI-360 layout.

mod common;

use std::{fs, path::PathBuf};

use arrow::{
    array::{Array, AsArray},
    datatypes::{DataType, Float32Type, Float64Type, UInt8Type},
    record_batch::RecordBatch,
};
use burn::tensor::{Tensor, TensorData};
use proptest::prelude::*;
use serde_json::{json, Value};
use stages::{
    geometry::{cameras_from_table, primitives_from_table, DAffine3, DMat3, DVec3, Primitive},
    geometry::{Interval, Ray, Shape},
    model::burn::loss::{depth_mse, label_nll},
    model::burn::volume::{render_depth, render_semantics, render_weights},
    model::burn::Backend,
    model::PROB_EPS,
    tables, MemoryInputs, NoProgress, Tables,
};

// ---- volume rendering ----

const SIGMAS: &[f32] = &[0.0, 1e-12, 1e-3, 1.0, 1e3, 1e6, 1e10];
const DELTAS: &[f32] = &[0.0, 1e-9, 1e-6, 1e-2, 1.0, 1e3];

fn values(t: Tensor<2>) -> Vec<f32> {
    t.into_data().try_to_vec::<f32>().unwrap()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, failure_persistence: None, ..Default::default() })]

    /// Weights in [0, 1] summing to at most 1, the semantic rendering a distribution, depth
    /// inside the samples' range, and finite gradients of two losses through all of them.
    #[test]
    fn volume_rendering_stays_a_distribution_under_extreme_sigma_and_delta(
        samples in 1usize..48,
        picks in prop::collection::vec((0..SIGMAS.len(), 0..DELTAS.len()), 8 * 48),
    ) {
        let (rays, classes) = (8, 3);
        let d = Backend::default().train_device();
        let n = rays * samples;
        let sigma: Vec<f32> = picks[..n].iter().map(|p| SIGMAS[p.0]).collect();
        let delta: Vec<f32> = picks[..n].iter().map(|p| DELTAS[p.1]).collect();
        let t: Vec<f32> = (0..n).map(|i| 1.0 + (i % samples) as f32).collect();
        let probs: Vec<f32> = (0..n * classes).map(|i| [0.7, 0.2, 0.1][i % 3]).collect();
        let sig = Tensor::<2>::from_data(TensorData::new(sigma.clone(), [rays, samples]), &d)
            .require_grad();
        let del = Tensor::<2>::from_data(TensorData::new(delta, [rays, samples]), &d);
        let w = render_weights(sig.clone(), del);
        let sem = render_semantics(
            &w,
            Tensor::from_data(TensorData::new(probs, [rays, samples, classes]), &d),
            classes - 1,
        );
        let depth = render_depth(&w, Tensor::from_data(TensorData::new(t, [rays, samples]), &d));

        let wv = values(w.weights.clone());
        prop_assert!(wv.iter().all(|x| x.is_finite() && (0.0..=1.0).contains(x)), "{wv:?}\n{sigma:?}");
        for r in 0..rays {
            let total: f32 = wv[r * samples..(r + 1) * samples].iter().sum();
            prop_assert!(total <= 1.0 + 1e-5, "ray {r}: weights sum to {total}");
        }
        let sv = values(sem.clone());
        for r in 0..rays {
            let row = &sv[r * classes..(r + 1) * classes];
            let total: f32 = row.iter().sum();
            prop_assert!(row.iter().all(|p| p.is_finite() && *p >= 0.0), "{row:?}");
            prop_assert!((total - 1.0).abs() < 1e-4, "ray {r}: semantics sum to {total}");
        }
        let dv = depth.clone().into_data().try_to_vec::<f32>().unwrap();
        prop_assert!(dv.iter().all(|x| x.is_finite() && *x >= 0.0 && *x <= samples as f32 + 1e-3), "{dv:?}");

        let one_hot: Vec<f32> = (0..rays * classes).map(|i| (i % classes == i / classes % classes) as u8 as f32).collect();
        let all = Tensor::<1>::ones([rays], &d);
        // The smallest eps allowed: the steepest the label term gets.
        let loss = label_nll(sem, Tensor::from_data(TensorData::new(one_hot, [rays, classes]), &d), all.clone(), PROB_EPS)
            + depth_mse(depth, all.clone().mul_scalar(3.0), all);
        let l = loss.clone().into_data().try_to_vec::<f32>().unwrap()[0];
        prop_assert!(l.is_finite(), "loss {l}");
        let g = values(sig.grad(&loss.backward()).unwrap());
        prop_assert!(g.iter().all(|x| x.is_finite()), "sigma gradient {g:?}");
    }
}

// ---- rays parallel to faces and along edges, far from the origin ----

/// A ray's intervals in a primitive.
fn intervals(p: &Primitive, r: &Ray) -> Vec<Interval> {
    let mut out = Vec::new();
    p.intersect(r, &mut out);
    out
}

#[test]
fn rays_parallel_to_faces_and_along_edges_agree_at_1e4_m_offsets() {
    // A rotated, non-uniformly scaled cuboid (and the same box as a mesh), at the origin and
    // 1e4 m away; rays built in its local frame: parallel to a face just inside, just outside
    // and exactly in its plane, and along an edge. Far away the answers must match the origin's
    // (in-plane and on-edge rays touch the closed box: empty or the same interval).
    let cube_mesh = {
        let v: Vec<DVec3> = (0..8)
            .map(|i| DVec3::new((i & 1) as f64, ((i >> 1) & 1) as f64, (i >> 2) as f64) - 0.5)
            .collect();
        let f = [
            [0, 2, 3],
            [0, 3, 1],
            [4, 5, 7],
            [4, 7, 6],
            [0, 1, 5],
            [0, 5, 4],
            [2, 6, 7],
            [2, 7, 3],
            [0, 4, 6],
            [0, 6, 2],
            [1, 3, 7],
            [1, 7, 5],
        ];
        Shape::Mesh {
            vertices: v,
            faces: f.to_vec(),
        }
    };
    let linear = DMat3::from_rotation_z(0.3) * DMat3::from_diagonal(DVec3::new(2.0, 1.0, 4.0));
    let mut checked = 0;
    for shape in [Shape::Cuboid, cube_mesh] {
        for offset in [
            DVec3::new(1e4, -2e4, 3e3),
            DVec3::new(12345.678, 9876.5, -4321.25),
        ] {
            let make = |t: DVec3| {
                Primitive::new(
                    shape.clone(),
                    DAffine3::from_mat3_translation(linear, t),
                    26,
                    1,
                )
                .unwrap()
            };
            let (near, far) = (make(DVec3::ZERO), make(offset));
            // (local origin, local direction, touches only the boundary)
            let cases = [
                (DVec3::new(-3.0, 0.0, 0.5 - 1e-6), DVec3::X, false), // inside, parallel to top
                (DVec3::new(-3.0, 0.0, 0.5 + 1e-6), DVec3::X, false), // outside, parallel to top
                (DVec3::new(-3.0, 0.2, 0.5), DVec3::X, true),         // in the top face's plane
                (DVec3::new(-3.0, 0.5, 0.5), DVec3::X, true),         // along an edge
                (DVec3::new(0.5, -3.0, -0.5), DVec3::Y, true),        // along another edge
                (DVec3::new(-1.0, -1.0, 0.5), DVec3::new(1.0, 1.0, 0.0), true), // across a corner
                (DVec3::new(0.1, 0.2, -3.0), DVec3::Z, false),        // straight through
            ];
            for (o, dir, boundary) in cases {
                let to_world = |p: &Primitive, x: DVec3| p.to_world.transform_point3(x);
                let ray = |p: &Primitive| {
                    let d = p.to_world.transform_vector3(dir);
                    Ray::new(to_world(p, o), d)
                };
                let (a, b) = (intervals(&near, &ray(&near)), intervals(&far, &ray(&far)));
                let what = format!(
                    "{} ray from local {o} along {dir}, offset {offset}",
                    shape.kind()
                );
                for i in a.iter().chain(&b) {
                    assert!(
                        i.t_in.is_finite() && i.t_out.is_finite() && i.t_in <= i.t_out,
                        "{what}: {i:?}"
                    );
                    assert!((i.normal_in.length() - 1.0).abs() < 1e-9, "{what}: {i:?}");
                }
                let same = a.len() == b.len()
                    && a.iter().zip(&b).all(|(x, y)| {
                        (x.t_in - y.t_in).abs() < 1e-6 && (x.t_out - y.t_out).abs() < 1e-6
                    });
                // A ray touching the closed box's boundary may be kept or dropped by rounding.
                let touch = |v: &[Interval]| v.iter().all(|i| i.t_out - i.t_in < 1e-6);
                let either = a.is_empty() || b.is_empty() || (touch(&a) && touch(&b));
                assert!(
                    same || (boundary && either),
                    "{what}: at the origin {a:?}, far away {b:?}"
                );
                if !boundary {
                    checked += 1;
                }
            }
        }
    }
    assert_eq!(checked, 2 * 2 * 3);
}

// ---- stages end to end on small KITTI-360-layout scenes ----

/// Runs one stage kind in process.
fn stage(kind: &str, params: Value, inputs: &[(&str, &Tables)]) -> Tables {
    let s = stages::kinds::find(kind).unwrap();
    let p = s.canonical_params(&params).unwrap();
    let mem = MemoryInputs::new(inputs.iter().map(|(k, t)| (*k, (*t).clone())));
    s.run(&p, &mem.inputs(), &NoProgress)
        .unwrap_or_else(|e| panic!("stage {kind}: {e}"))
}

/// The number of NaN or infinite values in an Arrow column (nulls are not counted).
fn non_finite(a: &dyn Array) -> usize {
    match a.data_type() {
        DataType::Float32 => a
            .as_primitive::<Float32Type>()
            .iter()
            .flatten()
            .filter(|v| !v.is_finite())
            .count(),
        DataType::Float64 => a
            .as_primitive::<Float64Type>()
            .iter()
            .flatten()
            .filter(|v| !v.is_finite())
            .count(),
        DataType::List(_) => non_finite(a.as_list::<i32>().values().as_ref()),
        DataType::LargeList(_) => non_finite(a.as_list::<i64>().values().as_ref()),
        DataType::FixedSizeList(..) => non_finite(a.as_fixed_size_list().values().as_ref()),
        DataType::Struct(_) => a
            .as_struct()
            .columns()
            .iter()
            .map(|c| non_finite(c.as_ref()))
            .sum(),
        _ => 0,
    }
}

fn assert_finite(t: &Tables, what: &str) {
    for (name, b) in t {
        for (f, c) in b.schema().fields().iter().zip(b.columns()) {
            let n = non_finite(c.as_ref());
            assert_eq!(n, 0, "{what}: {n} non-finite values in {name}.{}", f.name());
        }
    }
}

/// A KITTI-360 root with the fixture's poses, images and labels and the given objects: unit
/// cubes with a row-major local -> world transform, a kittiId and an instance id.
struct Scene {
    _dir: tempfile::TempDir,
    root: PathBuf,
}

impl Scene {
    fn new(objects: &[([f64; 16], i32, u32)]) -> Scene {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("k360");
        common::kitti360_fixture(&root);
        let scene = Scene { _dir: dir, root };
        scene.write_objects(objects);
        scene
    }

    fn write_objects(&self, objects: &[([f64; 16], i32, u32)]) {
        const CUBE: &str = "<vertices type_id=\"opencv-matrix\"><rows>8</rows><cols>3</cols><dt>f</dt>
<data>-0.5 -0.5 -0.5 0.5 -0.5 -0.5 -0.5 0.5 -0.5 0.5 0.5 -0.5 -0.5 -0.5 0.5 0.5 -0.5 0.5 -0.5 0.5 0.5 0.5 0.5 0.5</data></vertices>
<faces type_id=\"opencv-matrix\"><rows>12</rows><cols>3</cols><dt>u</dt>
<data>0 2 3 0 3 1 4 5 7 4 7 6 0 1 5 0 5 4 2 6 7 2 7 3 0 4 6 0 6 2 1 3 7 1 7 5</data></faces>";
        let mut xml = String::from("<?xml version=\"1.0\"?>\n<opencv_storage>\n");
        for (i, (m, semantic, instance)) in objects.iter().enumerate() {
            let data: Vec<String> = m.iter().map(|v| format!("{v:.17e}")).collect();
            xml += &format!(
                "<object{i}>\n<transform type_id=\"opencv-matrix\"><rows>4</rows><cols>4</cols><dt>f</dt>\n<data>{}</data></transform>\n{CUBE}\n<semanticId>{semantic}</semanticId>\n<instanceId>{instance}</instanceId>\n<timestamp>-1</timestamp>\n</object{i}>\n",
                data.join(" ")
            );
        }
        xml += "</opencv_storage>\n";
        fs::write(self.root.join("data_3d_bboxes/train/seq_a.xml"), xml).unwrap();
    }

    fn path(&self, rel: &str) -> PathBuf {
        self.root.join(rel)
    }

    /// Rewrites a text file of the scene.
    fn edit(&self, rel: &str, f: impl FnOnce(&str) -> String) {
        let p = self.path(rel);
        let s = fs::read_to_string(&p).unwrap();
        fs::write(&p, f(&s)).unwrap();
    }

    /// Every pseudo label (frames 3 and 7) set to `label`.
    fn pseudo_labels(&self, label: u8) {
        for f in [3, 7] {
            let p = self.path(&format!("pseudo_labels/seq_a/image_00/{f:010}.png"));
            stages::pngio::write_gray8(&p, 8, 4, &[label; 32]).unwrap();
        }
    }

    fn params(&self) -> Value {
        json!({"root": self.root.display().to_string(), "sequence": "seq_a",
               "first_frame": 0, "last_frame": 10, "eval_every": 1})
    }

    fn load(&self) -> Tables {
        self.load_with(json!({}))
    }

    fn load_with(&self, extra: Value) -> Tables {
        let mut p = self.params();
        p.as_object_mut()
            .unwrap()
            .extend(extra.as_object().unwrap().clone());
        stage("kitti360_scene", p, &[])
    }
}

/// Row-major 4x4 of `diag(scale)` then translation `t` (world metres, before recentring).
fn cuboid(scale: [f64; 3], t: [f64; 3]) -> [f64; 16] {
    [
        scale[0], 0.0, 0.0, t[0], 0.0, scale[1], 0.0, t[1], 0.0, 0.0, scale[2], t[2], 0.0, 0.0,
        0.0, 1.0,
    ]
}

const CAR: i32 = 13; // kittiId of car
const BUILDING: i32 = 11;

/// Trains a few iterations, renders, evaluates; every float anywhere must be finite.
fn train_render_evaluate(scene: &Tables, what: &str) -> (Tables, Tables) {
    let rays = stage("intersect", json!({}), &[("scene", scene)]);
    assert_finite(&rays, &format!("{what}: rays"));
    let train = stage(
        "train",
        json!({"schedule": {"iterations": 6, "rays_per_batch": 32}}),
        &[("scene", scene), ("rays", &rays)],
    );
    assert_finite(&train, &format!("{what}: train"));
    assert!(train["train_log"].num_rows() > 0, "{what}: empty train log");
    let render = stage(
        "render",
        json!({}),
        &[("scene", scene), ("rays", &rays), ("train", &train)],
    );
    assert_finite(&render, &format!("{what}: render"));
    let eval = stage(
        "evaluate",
        json!({}),
        &[("scene", scene), ("render", &render)],
    );
    assert_finite(&eval, &format!("{what}: evaluate"));
    (rays, train)
}

#[test]
fn training_on_all_wrong_pseudo_labels_stays_finite() {
    // The fixture's car and building; GT is sky above and car below, every pseudo label says
    // building: wrong everywhere.
    let s = Scene::new(&[
        (cuboid([2.0, 1.0, 4.0], [1000.5, 2000.25, 110.0]), CAR, 1),
        (cuboid([3.0, 3.0, 3.0], [999.0, 1999.0, 121.0]), BUILDING, 2),
    ]);
    s.pseudo_labels(11);
    train_render_evaluate(&s.load(), "all pseudo labels wrong");
}

#[test]
fn single_class_scene_trains_renders_and_evaluates() {
    // One car in front of the cameras, pseudo labels all car: one class besides the sky.
    let s = Scene::new(&[(cuboid([8.0, 4.0, 4.0], [1000.5, 2000.25, 110.0]), CAR, 1)]);
    s.pseudo_labels(26);
    let scene = s.load();
    let classes = tables::get_list::<UInt8Type>(&scene["scene_info"], "scene_info", "classes")
        .unwrap()
        .row(0)
        .to_vec();
    assert_eq!(classes, vec![23, 26], "sky and car only");
    train_render_evaluate(&scene, "single class");
}

#[test]
fn rays_that_hit_nothing_are_sky_and_a_scene_of_only_such_rays_is_a_clear_error() {
    // The only object is behind the cameras (they look along +z from z = 100, 101): every ray
    // is empty. The sampling plan is finite and all sky; training refuses with a clear error
    // instead of fitting nothing (rays with no hit inside a batch are trained on in the other
    // tests of this file).
    let s = Scene::new(&[(cuboid([2.0, 1.0, 4.0], [1000.5, 2000.25, 90.0]), CAR, 1)]);
    let scene = s.load();
    let rays = stage("intersect", json!({}), &[("scene", &scene)]);
    assert_finite(&rays, "empty rays");
    assert_eq!(
        hit_counts(&rays).iter().sum::<usize>(),
        0,
        "a ray hit the object behind"
    );
    let train = stages::kinds::find("train").unwrap();
    let p = train
        .canonical_params(&json!({"schedule": {"iterations": 2}}))
        .unwrap();
    let mem = MemoryInputs::new([("scene", scene.clone()), ("rays", rays.clone())]);
    let e = train
        .run(&p, &mem.inputs(), &NoProgress)
        .expect_err("training on rays that cross nothing must fail")
        .to_string();
    // The message says what was looked at and how far the primitives are.
    for needle in [
        "cameras [0, 1]",
        "crosses any of the 1 primitives",
        "the nearest primitive centre is",
        "poses file and bboxes XML",
    ] {
        assert!(e.contains(needle), "lacks {needle:?}: {e}");
    }
}

/// The number of primitive hits of each ray.
fn hit_counts(rays: &Tables) -> Vec<usize> {
    let r = &rays["ray_intervals"];
    let hits = tables::get_list::<UInt8Type>(r, "ray_intervals", "hits").unwrap();
    (0..r.num_rows())
        .flat_map(|i| hits.row(i).iter().map(|&h| h as usize).collect::<Vec<_>>())
        .collect()
}

#[test]
fn rays_in_the_planes_of_cuboid_faces_and_along_an_edge_train_finite() {
    // Principal point on a pixel centre (column 3, row 1): that column's rays lie in the plane
    // x = camera x, that row's in y = camera y. The car's faces x = -0.5 and y = 0.25 (scene
    // frame) are put in exactly those planes, so pixel (3, 1) looks along their common edge;
    // pixels to the right and below see the car, the others nothing.
    let s = Scene::new(&[(cuboid([8.0, 4.0, 4.0], [1004.5, 2002.25, 110.0]), CAR, 1)]);
    s.edit("calibration/perspective.txt", |t| {
        t.lines()
            .map(|l| {
                if l.starts_with("P_rect_0") {
                    l.replace("3.500000e+00", "3.000000e+00")
                        .replace("1.500000e+00", "1.000000e+00")
                } else {
                    l.to_string()
                }
            })
            .collect::<Vec<_>>()
            .join("\n")
    });
    let scene = s.load();
    let cams = cameras_from_table(&scene["cameras"]).unwrap();
    let prims = primitives_from_table(&scene["primitives"]).unwrap();
    let c = &cams[0].cam;
    let (centre, bb) = (c.centre(), prims[0].aabb());
    assert_eq!((c.cx, c.cy), (3.5, 1.5));
    assert_eq!(
        (bb.min.x, bb.min.y),
        (centre.x, centre.y),
        "faces not in the camera planes"
    );
    let (rays, _) = train_render_evaluate(&scene, "rays in face planes");
    let hits = hit_counts(&rays);
    assert!(
        hits.iter().any(|&h| h > 0) && hits.contains(&0),
        "want rays that hit the car and rays that hit nothing: {hits:?}"
    );
}

// ---- coordinates offset by 1e4 m ----

/// Adds `offset` to the translation of every pose line and every XML transform.
fn shift(s: &Scene, offset: [f64; 3]) {
    let shift_row_major = |v: &mut [f64]| {
        for (k, o) in offset.iter().enumerate() {
            v[4 * k + 3] += o;
        }
    };
    s.edit("data_poses/seq_a/cam0_to_world.txt", |t| {
        t.lines()
            .map(|l| {
                let mut tok = l.split_whitespace();
                let frame = tok.next().unwrap();
                let mut v: Vec<f64> = tok.map(|x| x.parse().unwrap()).collect();
                shift_row_major(&mut v);
                let v: Vec<String> = v.iter().map(|x| format!("{x:.17e}")).collect();
                format!("{frame} {}\n", v.join(" "))
            })
            .collect()
    });
    s.edit("data_3d_bboxes/train/seq_a.xml", |t| {
        let mut out = String::new();
        let mut rest = t;
        while let Some(i) = rest.find("<transform") {
            let a = i + rest[i..].find("<data>").unwrap() + "<data>".len();
            let b = a + rest[a..].find("</data>").unwrap();
            let mut v: Vec<f64> = rest[a..b]
                .split_whitespace()
                .map(|x| x.parse().unwrap())
                .collect();
            shift_row_major(&mut v);
            let v: Vec<String> = v.iter().map(|x| format!("{x:.17e}")).collect();
            out += &rest[..a];
            out += &v.join(" ");
            rest = &rest[b..];
        }
        out + rest
    });
}

fn assert_close(a: &[f64], b: &[f64], tol: f64, what: &str) {
    assert_eq!(a.len(), b.len(), "{what}");
    let worst = a
        .iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max);
    assert!(worst <= tol, "{what}: differs by {worst:e}");
}

fn f32_column(t: &RecordBatch, table: &str, col: &str) -> Vec<f64> {
    let l = tables::get_list::<Float32Type>(t, table, col).unwrap();
    (0..t.num_rows())
        .flat_map(|i| l.row(i).iter().map(|&x| x as f64).collect::<Vec<_>>())
        .collect()
}

#[test]
fn a_scene_offset_by_1e4_m_gives_the_same_tables() {
    let objects = [
        (cuboid([2.0, 1.0, 4.0], [1000.5, 2000.25, 110.0]), CAR, 1),
        (cuboid([3.0, 3.0, 3.0], [999.0, 1999.0, 121.0]), BUILDING, 2),
    ];
    let base = Scene::new(&objects);
    let a = base.load();
    let origin_a = tables::get_fixed_list::<Float64Type>(&a["scene_info"], "scene_info", "origin")
        .unwrap()
        .0
        .to_vec();
    // Whole metres (the default origin moves with the data) and fractions (explicit origin).
    for offset in [[1e4, -1e4, 1e4], [12345.678, -9876.543, 4321.5]] {
        let s = Scene::new(&objects);
        shift(&s, offset);
        let origin: Vec<f64> = origin_a.iter().zip(offset).map(|(o, d)| o + d).collect();
        let b = if offset.iter().all(|o| o.fract() == 0.0) {
            s.load()
        } else {
            s.load_with(json!({ "origin": origin }))
        };
        let what = format!("offset {offset:?}");
        let origin_b =
            tables::get_fixed_list::<Float64Type>(&b["scene_info"], "scene_info", "origin")
                .unwrap()
                .0
                .to_vec();
        assert_close(&origin_b, &origin, 1e-9, &format!("{what}: origin"));
        for name in ["images", "pseudo_labels", "gt_semantic", "gt_instance"] {
            assert_eq!(a[name], b[name], "{what}: table {name} differs");
        }
        let (ca, cb) = (
            cameras_from_table(&a["cameras"]).unwrap(),
            cameras_from_table(&b["cameras"]).unwrap(),
        );
        let flat = |c: &[stages::geometry::CameraRow]| -> Vec<f64> {
            c.iter()
                .flat_map(|r| r.cam.cam_to_world.to_cols_array())
                .collect()
        };
        assert_close(
            &flat(&ca),
            &flat(&cb),
            1e-9,
            &format!("{what}: camera poses"),
        );
        let (pa, pb) = (
            primitives_from_table(&a["primitives"]).unwrap(),
            primitives_from_table(&b["primitives"]).unwrap(),
        );
        let flat = |p: &[Primitive]| -> Vec<f64> {
            p.iter().flat_map(|q| q.to_world.to_cols_array()).collect()
        };
        assert_close(
            &flat(&pa),
            &flat(&pb),
            1e-9,
            &format!("{what}: primitive transforms"),
        );
        // The f32 sampling plan is the same too.
        let (ra, rb) = (
            stage("intersect", json!({}), &[("scene", &a)]),
            stage("intersect", json!({}), &[("scene", &b)]),
        );
        let (ia, ib) = (&ra["ray_intervals"], &rb["ray_intervals"]);
        let labels = |t: &RecordBatch| {
            let l = tables::get_list::<UInt8Type>(t, "ray_intervals", "first_label").unwrap();
            (0..l.len())
                .flat_map(|i| l.row(i).to_vec())
                .collect::<Vec<u8>>()
        };
        assert_eq!(labels(ia), labels(ib), "{what}: first labels");
        for col in ["t_in", "t_out"] {
            assert_close(
                &f32_column(ia, "ray_intervals", col),
                &f32_column(ib, "ray_intervals", col),
                1e-5,
                &format!("{what}: {col}"),
            );
        }
    }
}
