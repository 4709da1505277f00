//! Tests of the `intersect` stage on a hand-made scene with exact answers, its schema, params
//! and export.

use crate::MemoryInputs;

use arrow::datatypes::{Float32Type, UInt32Type, UInt8Type};
use glam::{DAffine3, DMat3, DQuat, DVec3};

use arrow::record_batch::RecordBatch;

use super::*;
use crate::geometry::{cameras_to_table, primitives_to_table, Camera, CameraRow, Primitive, Shape};
use crate::{labels, schema, tables, NoProgress, Stage};

/// Camera at the origin looking along world +x (camera x = world -y, y = world -z), 3x3 pixels,
/// f = 5 so the side pixels look 0.2 rad off axis. A cuboid occupying x in [4, 6], y in
/// [-0.5, 0.5], z in [-5, 5] and a sphere of radius 1 centred at (10, 0, 0): the centre pixel
/// crosses both; the side columns miss everything; the centre column's top and bottom pixels
/// cross only the cuboid.
fn scene(camera: u8) -> Tables {
    let prims = vec![
        Primitive::new(
            Shape::Cuboid,
            DAffine3::from_scale_rotation_translation(
                DVec3::new(2.0, 1.0, 10.0),
                DQuat::IDENTITY,
                DVec3::new(5.0, 0.0, 0.0),
            ),
            labels::CAR,
            3,
        )
        .unwrap(),
        Primitive::new(
            Shape::Ellipsoid,
            DAffine3::from_scale_rotation_translation(
                DVec3::splat(2.0),
                DQuat::IDENTITY,
                DVec3::new(10.0, 0.0, 0.0),
            ),
            labels::VEGETATION,
            0,
        )
        .unwrap(),
    ];
    let cam = Camera {
        width: 3,
        height: 3,
        fx: 5.0,
        fy: 5.0,
        cx: 1.5,
        cy: 1.5,
        lens: crate::geometry::Lens::Pinhole,
        cam_to_world: DAffine3::from_mat3(DMat3::from_cols(-DVec3::Y, -DVec3::Z, DVec3::X)),
    };
    let rows = vec![CameraRow {
        frame: 7,
        camera,
        eval: true,
        cam,
    }];
    Tables::from([
        ("cameras".to_string(), cameras_to_table(&rows).unwrap()),
        (
            "primitives".to_string(),
            primitives_to_table(&prims).unwrap(),
        ),
    ])
}

fn run(params: &IntersectParams, scene: &Tables) -> Result<RecordBatch> {
    let mem = MemoryInputs::new([("scene", scene.clone())]);
    let mut out = TypedStage::run(&Intersect, params, &mem.inputs(), &NoProgress)?;
    Ok(out.remove("ray_intervals").unwrap())
}

fn close(a: &[f32], b: &[f64]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (*x as f64 - y).abs() < 1e-5)
}

#[test]
fn exact_intervals_on_a_tiny_scene() {
    let t = run(&IntersectParams::default(), &scene(0)).unwrap();
    assert_eq!(t.num_rows(), 1);
    let row = |c: &str| {
        tables::get_list::<Float32Type>(&t, "ray_intervals", c)
            .unwrap()
            .row(0)
    };
    let hits = tables::get_list::<UInt8Type>(&t, "ray_intervals", "hits").unwrap();
    let prim = tables::get_list::<UInt32Type>(&t, "ray_intervals", "prim").unwrap();
    // Side columns look 0.2 rad sideways and pass beside the 1 m wide cuboid.
    assert_eq!(hits.row(0), &[0, 1, 0, 0, 2, 0, 0, 1, 0]);
    // Top and bottom centre pixels: the cuboid's x-slab [4, 6] at t = x / dir.x.
    let e = (1.0f64 + 0.04).sqrt();
    assert!(
        close(row("t_in"), &[4.0 * e, 4.0, 9.0, 4.0 * e]),
        "{:?}",
        row("t_in")
    );
    assert!(
        close(row("t_out"), &[6.0 * e, 6.0, 11.0, 6.0 * e]),
        "{:?}",
        row("t_out")
    );
    assert_eq!(prim.row(0), &[0, 0, 1, 0]);
    // The sky interval follows the last exit, except on the bottom pixel, which looks 11 degrees
    // below the horizon: it cannot see the sky, its interval is empty.
    let sky0 = [0.0, 6.0 * e, 0.0, 0.0, 11.0, 0.0, 0.0, 6.0 * e, 0.0];
    let mut sky1 = sky0.map(|v| if v == 0.0 { 0.0 } else { v + 50.0 });
    sky1[7] = sky0[7];
    assert!(close(row("sky_t0"), &sky0), "{:?}", row("sky_t0"));
    assert!(close(row("sky_t1"), &sky1), "{:?}", row("sky_t1"));
    let first = tables::get_list::<UInt8Type>(&t, "ray_intervals", "first_label").unwrap();
    assert_eq!(first.row(0)[3], labels::SKY);
    assert_eq!(first.row(0)[4], labels::CAR);
    let inst = tables::get_list::<UInt32Type>(&t, "ray_intervals", "first_instance").unwrap();
    assert_eq!(inst.row(0)[4], 3);
}

#[test]
fn rays_below_the_horizon_get_no_sky_interval() {
    use crate::geometry::{Bvh, Ray};
    use crate::intervals::{may_see_sky, RayPlan, SKY_MAX_DEPRESSION_DEG};
    // A ground slab 2 m below the ray origin, 100 m long: rays at several depressions.
    let slab = Primitive::new(
        Shape::Cuboid,
        DAffine3::from_scale_rotation_translation(
            DVec3::new(100.0, 100.0, 1.0),
            DQuat::IDENTITY,
            DVec3::new(50.0, 0.0, -2.5),
        ),
        labels::ROAD,
        0,
    )
    .unwrap();
    let prims = vec![slab];
    let bvh = Bvh::build(&prims);
    let p = IntersectParams::default();
    let mut plan = RayPlan::default();
    let lim = SKY_MAX_DEPRESSION_DEG;
    for (deg, sees_sky) in [
        (-10.0, false),
        (-lim - 0.01, false),
        (-lim + 0.01, true),
        (0.0, true),
    ] {
        let a = f64::to_radians(deg);
        let dir = DVec3::new(a.cos(), 0.0, a.sin());
        assert_eq!(may_see_sky(dir), sees_sky, "{deg} degrees");
        // From inside the slab (top at z = -2) every ray crosses it.
        let ray = Ray::new(DVec3::new(0.0, 0.0, -2.1), dir);
        plan.trace(&prims, &bvh, &ray, &p);
        assert_eq!(plan.t_in.len(), 1, "{deg} degrees");
        let len = plan.sky[1] - plan.sky[0];
        let want = if sees_sky { p.sky_interval as f32 } else { 0.0 };
        assert!(
            (len - want).abs() < 1e-3,
            "{deg} degrees: sky interval {len}"
        );
    }
}

#[test]
fn k_and_far_limit_the_intervals() {
    // k = 1: the centre pixel keeps only the cuboid, and its sky interval is empty.
    let p = IntersectParams {
        k: 1,
        ..Default::default()
    };
    let t = run(&p, &scene(0)).unwrap();
    let hits = tables::get_list::<UInt8Type>(&t, "ray_intervals", "hits").unwrap();
    assert_eq!(hits.row(0)[4], 1);
    let s0 = tables::get_list::<Float32Type>(&t, "ray_intervals", "sky_t0").unwrap();
    let s1 = tables::get_list::<Float32Type>(&t, "ray_intervals", "sky_t1").unwrap();
    assert_eq!((s0.row(0)[4], s1.row(0)[4]), (6.0, 6.0));
    // far = 10: the sphere's interval is clipped to [9, 10].
    let p = IntersectParams {
        far: 10.0,
        ..Default::default()
    };
    let t = run(&p, &scene(0)).unwrap();
    let t_out = tables::get_list::<Float32Type>(&t, "ray_intervals", "t_out").unwrap();
    assert_eq!(t_out.row(0)[2], 10.0);
}

#[test]
fn camera_selection_and_bad_params() {
    let e = run(
        &IntersectParams {
            cameras: vec![0],
            ..Default::default()
        },
        &scene(1),
    )
    .unwrap_err();
    assert!(e.to_string().contains("camera id in [0]"), "{e}");
    // No camera named: every camera of the scene.
    let every = run(&IntersectParams::default(), &scene(1)).unwrap();
    assert_eq!(every.num_rows(), 1);
    let stage: &dyn Stage = &Intersect;
    for (bad, what) in [
        (serde_json::json!({"k": 0}), "`k`"),
        (serde_json::json!({"k": 300}), "`k`"),
        (serde_json::json!({"sky_interval": -1.0}), "`sky_interval`"),
        (serde_json::json!({"far": 0.0}), "`far`"),
        (serde_json::json!({"cameras": [4]}), "`cameras`"),
        (serde_json::json!({"kk": 3}), "unknown field"),
    ] {
        let e = stage.canonical_params(&bad).unwrap_err().to_string();
        assert!(e.contains(what), "{bad}: {e}");
    }
    assert_eq!(
        stage.canonical_params(&serde_json::json!({})).unwrap(),
        serde_json::to_value(IntersectParams::default()).unwrap()
    );
}

#[test]
fn output_matches_its_schema_file() {
    let t = run(&IntersectParams::default(), &scene(0)).unwrap();
    schema::check("ray_intervals", t.schema().as_ref()).unwrap();
    assert_eq!(t.schema(), schema::get("ray_intervals").unwrap());
    assert!(crate::kinds::find("intersect").is_some());
}

#[test]
fn ragged_intervals_agree_with_the_bvh_on_the_street_scene() {
    let (prims, cam) = geometry::demo::street_scene(48, 16);
    let p = IntersectParams::default();
    let bvh = Bvh::build(&prims);
    let plan = plan_image(&prims, &bvh, &cam, &p);
    assert_eq!(plan.hits.len(), 48 * 16);
    assert_eq!(
        plan.t_in.len(),
        plan.hits.iter().map(|&h| h as usize).sum::<usize>()
    );
    let mut off = 0;
    let mut hits = Vec::new();
    for y in 0..16 {
        for x in 0..48 {
            let i = (y * 48 + x) as usize;
            bvh.intersect_all(&prims, &cam.pixel_ray(x, y).unwrap(), 0.0, p.far, &mut hits);
            let n = hits.len().min(10);
            assert_eq!(plan.hits[i] as usize, n);
            for (j, h) in hits[..n].iter().enumerate() {
                assert_eq!(
                    (plan.prim[off + j], plan.t_in[off + j]),
                    (h.prim, h.t_in as f32)
                );
            }
            off += n;
        }
    }
    // Looking down the street, most pixels see something, and the top rows see sky.
    assert!(plan.hits.iter().filter(|&&h| h > 0).count() > 48 * 8);
    assert!(plan.hits[..48].contains(&0));
}

#[test]
fn export_writes_one_png_per_image() {
    let t = run(&IntersectParams::default(), &scene(0)).unwrap();
    let dir = std::env::temp_dir().join(format!("geom-export-{}", std::process::id()));
    let tables = Tables::from([("ray_intervals".to_string(), t)]);
    let files = TypedStage::export(
        &Intersect,
        &IntersectParams::default(),
        &tables.into(),
        &dir,
    )
    .unwrap();
    assert_eq!(files, vec![dir.join("first_hit/0000000007_0.png")]);
    let img = image::open(&files[0]).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (3, 3));
    // Middle row's side pixels are sky; the centre is the (shaded) car colour, bluish.
    let sky = labels::color(labels::SKY).map(|v| ((v as f64 * 0.85 + 38.0).round()) as u8);
    assert_eq!(img.get_pixel(0, 1).0, sky);
    let c = img.get_pixel(1, 1).0;
    assert!(c[2] > c[0] && c[2] > c[1], "{c:?}");
    std::fs::remove_dir_all(&dir).ok();
}

/// The demo street seen from x = -30, 0, 30, looking along +x and along -x: six images.
fn street_from_six_places() -> (Vec<Primitive>, Tables) {
    let (prims, cam) = geometry::demo::street_scene(40, 14);
    let rows: Vec<CameraRow> = (0..6)
        .map(|i| {
            let x = -30.0 + 30.0 * (i / 2) as f64;
            let turn = DAffine3::from_rotation_z(std::f64::consts::PI * (i % 2) as f64);
            let mut c = cam.clone();
            c.cam_to_world = DAffine3::from_translation(DVec3::new(x, 0.0, 1.6))
                * turn
                * DAffine3::from_mat3(cam.cam_to_world.matrix3);
            CameraRow {
                frame: i,
                camera: 0,
                eval: false,
                cam: c,
            }
        })
        .collect();
    let cameras = cameras_to_table(&rows).unwrap();
    (
        prims.clone(),
        Tables::from([
            ("cameras".to_string(), cameras),
            (
                "primitives".to_string(),
                primitives_to_table(&prims).unwrap(),
            ),
        ]),
    )
}

/// The update of `old_out` (planned from scene `before`) after an edit of the primitives that
/// gives scene `after`.
fn update(p: &IntersectParams, before: &Tables, old_out: &RecordBatch, after: Tables) -> Updated {
    use crate::stage::{Changed, Previous};
    let changed = Changed::from([("scene".to_string(), ["primitives".to_string()].into())]);
    let outputs = TableSet::from(Tables::from([(
        "ray_intervals".to_string(),
        old_out.clone(),
    )]));
    let inputs = TableSet::from(before.clone());
    let previous = Previous {
        outputs: &outputs,
        inputs: [("scene".to_string(), &inputs)].into(),
        changed: &changed,
        lineage: &Default::default(),
    };
    let mem = MemoryInputs::new([("scene", after)]);
    TypedStage::update(&Intersect, p, &mem.inputs(), &previous, &NoProgress).unwrap()
}

/// Brute force against the cold run: after each kind of edit (moved, relabelled, removed
/// with the ids after it shifting, added), the update writes the very rows a run from scratch
/// writes, and intersects again only the images that can see the edit.
#[test]
fn an_update_after_an_edit_equals_a_run_from_scratch() {
    let (prims, before) = street_from_six_places();
    let p = IntersectParams::default();
    let old_out = run(&p, &before).unwrap();
    // The thing farthest along +x (not the ground): the cameras looking along -x from x = 30
    // and x = 0 cannot see it.
    let far_end = (0..prims.len())
        .filter(|&i| prims[i].label != labels::ROAD && prims[i].label != labels::SIDEWALK)
        .max_by(|&a, &b| prims[a].aabb().min.x.total_cmp(&prims[b].aabb().min.x))
        .unwrap();
    let q = &prims[far_end];
    let moved = Primitive::new(
        q.shape.clone(),
        DAffine3::from_translation(DVec3::new(0.0, 1.0, 0.0)) * q.to_world,
        q.label,
        q.instance,
    )
    .unwrap();
    let relabelled =
        Primitive::new(q.shape.clone(), q.to_world, labels::CARAVAN, q.instance).unwrap();
    let edits: [(&str, Vec<Primitive>); 4] = [
        ("moved", {
            let mut v = prims.clone();
            v[far_end] = moved.clone();
            v
        }),
        ("relabelled", {
            let mut v = prims.clone();
            v[far_end] = relabelled;
            v
        }),
        ("removed", {
            let mut v = prims.clone();
            v.remove(far_end);
            v
        }),
        ("added", {
            let mut v = prims.clone();
            v.push(moved);
            v
        }),
    ];
    for (what, edited) in edits {
        let mut after = before.clone();
        after.insert("primitives".into(), primitives_to_table(&edited).unwrap());
        let cold = run(&p, &after).unwrap();
        let u = update(&p, &before, &old_out, after);
        assert_eq!(u.tables["ray_intervals"], cold, "{what}");
        let redone: usize = u.redone.split(' ').next().unwrap().parse().unwrap();
        assert!((1..6).contains(&redone), "{what}: {}", u.redone);
        assert!(u.redone.ends_with("(1 primitive changed)"), "{}", u.redone);
    }
}

/// Two boxes around the camera (every ray enters both at t = 0: tied entries, ordered by id)
/// and the tiny scene's two primitives; the table reordered (nothing else changed) and then one
/// box removed. The update must give the order a trace gives, not the previous order
/// renumbered, and must trace again exactly the pixels that need it.
#[test]
fn a_reordered_table_keeps_tied_entries_in_trace_order() {
    let before = scene(0);
    let mut prims = geometry::primitives_from_table(&before["primitives"]).unwrap();
    for (size, label) in [(3.0, labels::ROAD), (4.0, labels::BUILDING)] {
        prims.push(
            Primitive::new(
                Shape::Cuboid,
                DAffine3::from_scale(DVec3::splat(size)),
                label,
                0,
            )
            .unwrap(),
        );
    }
    let table = |v: &[Primitive]| {
        let mut t = before.clone();
        t.insert("primitives".into(), primitives_to_table(v).unwrap());
        t
    };
    let p = IntersectParams::default();
    let old_scene = table(&prims);
    let old_out = run(&p, &old_scene).unwrap();
    let reordered = vec![
        prims[3].clone(),
        prims[0].clone(),
        prims[2].clone(),
        prims[1].clone(),
    ];
    let removed = vec![prims[3].clone(), prims[0].clone(), prims[1].clone()];
    for (what, edited) in [
        ("reordered", reordered),
        ("reordered, one removed", removed),
    ] {
        let after = table(&edited);
        let cold = run(&p, &after).unwrap();
        let u = update(&p, &old_scene, &old_out, after);
        assert_eq!(u.tables["ray_intervals"], cold, "{what}");
        // The order changed: every pixel's ids differ from the previous ones.
        assert_ne!(u.tables["ray_intervals"], old_out, "{what}");
    }
}
