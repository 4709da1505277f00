//! Tests of the sampling plan on toy ray sets: sample placement, fixed fields, batches.

use super::*;
use crate::intervals::{ImagePlan, IntersectParams};
use crate::labels;

/// One ray crossing a car box [5, 7] inside a road slab [4, 10], sky [10, 60].
fn toy() -> RaySet {
    RaySet {
        prims: PrimInfo {
            classes: vec![labels::ROAD, labels::CAR, labels::SKY],
            things: vec![(labels::CAR, 1)],
            prim_class: vec![0, 1],
            prim_thing: vec![u32::MAX, 0],
            ..Default::default()
        },
        origin: vec![[0.0; 3]],
        dir: vec![[0.0, 0.0, 1.0]],
        z_scale: vec![1.0],
        offsets: vec![0, 2],
        t_in: vec![4.0, 5.0],
        t_out: vec![10.0, 7.0],
        prim: vec![0, 1],
        sky: vec![[10.0, 60.0]],
        rgb: vec![[0.5; 3]],
        label: vec![1],
        u_mask: vec![true],
        depth: vec![0.0],
    }
}

/// The toy ray 300 times, each with its own interval ends, label and depth.
fn many() -> RaySet {
    let mut set = toy();
    let one = toy();
    set.offsets = vec![0];
    for v in [&mut set.origin, &mut set.dir] {
        v.clear();
    }
    set.t_in.clear();
    set.t_out.clear();
    set.prim.clear();
    set.sky.clear();
    set.rgb.clear();
    set.label.clear();
    set.u_mask.clear();
    set.depth.clear();
    set.z_scale.clear();
    for k in 0..300 {
        let x = k as f32 * 0.01;
        set.origin.push(one.origin[0]);
        set.dir.push(one.dir[0]);
        set.z_scale.push(1.0);
        set.t_in.extend([4.0 + x, 5.0 + x]);
        set.t_out.extend([10.0 + x, 7.0]);
        set.prim.extend([0, 1]);
        set.offsets.push(set.t_in.len() as u32);
        set.sky.push([10.0 + x, 60.0]);
        set.rgb.push([x, 0.5, 1.0 - x]);
        set.label.push((k % 3) as u16);
        set.u_mask.push(k % 2 == 0);
        set.depth.push(x);
    }
    set
}

#[test]
fn parallel_batches_equal_the_serial_ones() {
    let set = many();
    let p = SamplingParams::default();
    let ids: Vec<u32> = (0..300).rev().chain(5..40).collect();
    for seed in [Some(11), None] {
        let par = sample_batch(&set, &ids, &p, seed).unwrap();
        let ser = sample_rays(&set, &ids, &p, seed).unwrap();
        assert_eq!(format!("{par:?}"), format!("{ser:?}"), "seed {seed:?}");
        assert_eq!(par.rays, ids.len());
    }
}

#[test]
fn fixed_fields_follow_the_intervals() {
    let set = toy();
    let (prims, iv) = (&set.prims, set.intervals(0));
    let mut out = [0.0; 3];
    assert!(fixed_semantic_at(prims, &iv, 4.5, &mut out));
    assert_eq!(out, [1.0, 0.0, 0.0]);
    assert!(
        !fixed_semantic_at(prims, &iv, 6.0, &mut out),
        "road and car overlap"
    );
    assert_eq!(out, [0.5, 0.5, 0.0]);
    assert!(fixed_semantic_at(prims, &iv, 30.0, &mut out));
    assert_eq!(out, [0.0, 0.0, 1.0], "sky interval");
    assert!(!fixed_semantic_at(prims, &iv, 2.0, &mut out));
    assert_eq!(out, [0.0; 3], "outside everything");
    let mut inst = [0.0];
    assert!(fixed_instance_at(prims, &iv, 6.0, &mut inst));
    assert_eq!(inst, [1.0]);
    assert!(!fixed_instance_at(prims, &iv, 8.0, &mut inst));
}

/// The sparse members are exactly the non-zero entries of the dense distributions, with the
/// same equal share, at every sample of many random plans.
#[test]
fn fixed_members_are_the_non_zero_entries_of_the_fixed_fields() {
    let set = many();
    let prims = &set.prims;
    let (mut cls, mut th) = (Vec::new(), Vec::new());
    let mut dense = vec![0f32; prims.classes.len()];
    let mut dense_inst = vec![0f32; prims.things.len()];
    let mut checked = 0;
    for r in 0..set.len() {
        let iv = set.intervals(r);
        for k in 0..200 {
            let t = k as f32 * 0.37;
            fixed_semantic_at(prims, &iv, t, &mut dense);
            fixed_instance_at(prims, &iv, t, &mut dense_inst);
            fixed_members_at(prims, &iv, t, &mut cls, &mut th);
            for (members, d) in [(&cls, &dense), (&th, &dense_inst)] {
                let share = if members.len() > 1 {
                    1.0 / members.len() as f32
                } else {
                    1.0
                };
                for (i, &v) in d.iter().enumerate() {
                    let want = if members.contains(&i) { share } else { 0.0 };
                    assert_eq!(v.to_bits(), want.to_bits(), "ray {r} t {t} entry {i}");
                }
            }
            checked += cls.len() + th.len();
        }
    }
    assert!(
        checked > 1000,
        "the plans cross primitives and things: {checked}"
    );
}

#[test]
fn samples_stay_inside_primitives_and_strata_tile_them() {
    let set = toy();
    let p = SamplingParams {
        samples: 6,
        sky_samples: 2,
        ..Default::default()
    };
    let mut rng = SplitMix64::new(7);
    let (mut t, mut d) = (vec![0.0; 8], vec![0.0; 8]);
    place_samples(&set.intervals(0), &p, Some(&mut rng), &mut t, &mut d);
    // Union [4, 10] gets 6 strata of width 1; sky [10, 60] two of width 25.
    for i in 0..6 {
        assert!(t[i] >= 4.0 + i as f32 && t[i] <= 5.0 + i as f32, "{t:?}");
        assert!((d[i] - 1.0).abs() < 1e-6);
    }
    assert!(t[6] >= 10.0 && t[7] <= 60.0 && (d[6] - 25.0).abs() < 1e-5);
    let total: f32 = d.iter().sum();
    assert!(
        (total - 56.0).abs() < 1e-4,
        "strata cover exactly the sampled length"
    );
    // A ray with no hits gets only padding (zero width).
    let mut empty = toy();
    empty.offsets = vec![0, 0];
    empty.sky = vec![[0.0, 0.0]];
    place_samples(&empty.intervals(0), &p, None, &mut t, &mut d);
    assert!(d.iter().all(|&x| x == 0.0));
}

#[test]
fn batches_are_deterministic_for_a_seed() {
    let set = toy();
    let p = SamplingParams::default();
    let a = sample_batch(&set, &[0], &p, Some(3)).unwrap();
    let b = sample_batch(&set, &[0], &p, Some(3)).unwrap();
    let c = sample_batch(&set, &[0], &p, Some(4)).unwrap();
    assert_eq!(a.t, b.t);
    assert_ne!(a.t, c.t);
    assert_eq!(a.label, vec![1]);
    assert_eq!(a.positions.len(), p.per_ray() * 3);
}

/// A 2-frame synthetic street at 1/20 scale.
fn small_street() -> crate::Tables {
    use crate::scene::synthetic::{generate, to_tables, SceneParams};
    let sp = SceneParams {
        frames: 2,
        scale: 0.05,
        ..SceneParams::default()
    };
    to_tables(&sp, &generate(&sp, &crate::NoProgress).unwrap()).unwrap()
}

/// `scene` with the plan the `intersect` stage would store for it (default parameters), as
/// training's inputs; also the plan and the number of cameras.
fn planned(scene: crate::Tables) -> (crate::MemoryInputs, arrow::record_batch::RecordBatch, usize) {
    use crate::geometry::{cameras_from_table, primitives_from_table, Bvh};
    use crate::intervals::{plan_image, plan_row};
    let cams = cameras_from_table(&scene["cameras"]).unwrap();
    let prims = primitives_from_table(&scene["primitives"]).unwrap();
    let (bvh, ip) = (Bvh::build(&prims), IntersectParams::default());
    let rows: Vec<_> = cams
        .iter()
        .map(|c| plan_row(c, plan_image(&prims, &bvh, &c.cam, &ip), &ip).unwrap())
        .collect();
    let plan = arrow::compute::concat_batches(&rows[0].schema(), &rows).unwrap();
    let mem = crate::MemoryInputs::new([
        ("scene", scene),
        (
            "rays",
            crate::Tables::from([("ray_intervals".to_string(), plan.clone())]),
        ),
    ]);
    (mem, plan, cams.len())
}

/// Training traces each ray again when it is drawn; rendering reads the plan the `intersect`
/// stage stored. Both must give every ray the same origin, direction and intervals.
#[test]
fn training_traces_exactly_the_plan_the_intersect_stage_stores() {
    use crate::geometry::primitives_from_table;
    let scene = small_street();
    let prims = primitives_from_table(&scene["primitives"]).unwrap();
    let (mem, plan, cams) = planned(scene);
    let traced = train_rays(&mem.inputs()).unwrap();
    assert_eq!(traced.images.len(), cams);
    let (mut a, mut b) = (RayPlan::default(), RayPlan::default());
    let mut crossing = 0;
    for (r, im) in traced.images.iter().enumerate() {
        let n = (im.cam.width * im.cam.height) as usize;
        let image_plan = ImagePlan::from_row(&plan, r, n, prims.len()).unwrap();
        let planned = PlannedImage::new(&traced.prims, &im.cam, &image_plan).unwrap();
        for p in 0..n as u32 {
            let t = traced.ray(im.first_ray + p, &mut a).unwrap();
            let s = planned.ray(p, &mut b).unwrap();
            assert_eq!(
                (t.origin, t.dir, t.z_scale),
                (s.origin, s.dir, s.z_scale),
                "image {r} pixel {p}"
            );
            let (ti, si) = (t.intervals, s.intervals);
            assert_eq!(
                (ti.t_in, ti.t_out, ti.prim, ti.sky),
                (si.t_in, si.t_out, si.prim, si.sky),
                "image {r} pixel {p}"
            );
            crossing += usize::from(ti.hits_anything());
        }
    }
    assert!(crossing > 100, "{crossing} rays cross a primitive");
    // A plan made over other primitives is caught when a ray is traced.
    let mut wrong = traced.images[0].hits.clone();
    let p = wrong.iter().position(|&h| h > 0).unwrap();
    wrong[p] += 1;
    let mut bad = train_rays(&mem.inputs()).unwrap();
    bad.images[0].hits = wrong;
    let e = bad.ray(p as u32, &mut a).unwrap_err().to_string();
    assert!(e.contains("ray_intervals does not match the scene"), "{e}");
}

/// A pseudo label of sky on a ray below the horizon cannot be honoured (the ray has no sky
/// interval): training drops it; every other pseudo label is kept as it is.
#[test]
fn sky_pseudo_labels_below_the_horizon_are_dropped() {
    use crate::intervals::may_see_sky;
    let mut scene = small_street();
    // Pseudo labels all sky, so both sides of the horizon are covered.
    let pl = scene["pseudo_labels"].clone();
    let col = pl.schema().index_of("labels").unwrap();
    let lists =
        crate::tables::get_list::<arrow::datatypes::UInt8Type>(&pl, "pseudo_labels", "labels")
            .unwrap();
    let sky: Vec<Vec<u8>> = (0..pl.num_rows())
        .map(|r| vec![labels::SKY; lists.row(r).len()])
        .collect();
    let mut columns = pl.columns().to_vec();
    columns[col] = crate::tables::list::<arrow::datatypes::UInt8Type>(sky);
    scene.insert(
        "pseudo_labels".into(),
        arrow::record_batch::RecordBatch::try_new(pl.schema(), columns).unwrap(),
    );
    let (mem, _, _) = planned(scene);
    let traced = train_rays(&mem.inputs()).unwrap();
    let sky = traced.prims.sky_class() as u16;
    let (mut buf, mut kept, mut dropped) = (RayPlan::default(), 0, 0);
    for r in 0..traced.len() as u32 {
        // Only the left images have pseudo labels.
        if traced.locate(r).0.targets.labels.is_none() {
            continue;
        }
        let ray = traced.ray(r, &mut buf).unwrap();
        let d = ray.dir.map(f64::from);
        let dir = glam::DVec3::from(d).normalize();
        // f32 directions: skip the rays within rounding of the limit.
        if (dir.z + crate::intervals::SKY_MAX_DEPRESSION_DEG.to_radians().sin()).abs() < 1e-5 {
            continue;
        }
        if may_see_sky(dir) {
            assert_eq!(
                ray.targets.label, sky,
                "ray {r} looks up: keeps its sky label"
            );
            kept += 1;
        } else {
            assert_eq!(ray.targets.label, NONE, "ray {r} looks down: no sky label");
            assert!(!ray.targets.u_mask);
            dropped += 1;
        }
    }
    assert!(
        kept > 100 && dropped > 100,
        "{kept} kept, {dropped} dropped"
    );
}

/// `restrict_depth_to` keeps the stereo depth exactly on the rays that cross a primitive of a
/// listed class (checked ray by ray against the traced intervals); other rays lose it, and an
/// empty list keeps every ray's depth.
#[test]
fn depth_is_kept_only_on_rays_crossing_a_listed_class() {
    use crate::geometry::primitives_from_table;
    let scene = small_street();
    let prims = primitives_from_table(&scene["primitives"]).unwrap();
    let (mem, _, _) = planned(scene);
    let all = train_rays(&mem.inputs()).unwrap();
    let mut some = train_rays(&mem.inputs()).unwrap();
    let listed = [labels::BUILDING, labels::CAR];
    some.restrict_depth_to(&listed);
    let mut unchanged = train_rays(&mem.inputs()).unwrap();
    unchanged.restrict_depth_to(&[]);
    let (mut a, mut b, mut c) = (RayPlan::default(), RayPlan::default(), RayPlan::default());
    let (mut kept, mut dropped) = (0, 0);
    for r in 0..all.len() as u32 {
        let full = all.ray(r, &mut a).unwrap();
        let restricted = some.ray(r, &mut b).unwrap();
        assert_eq!(
            unchanged.ray(r, &mut c).unwrap().targets.depth,
            full.targets.depth
        );
        if full.targets.depth <= 0.0 {
            assert_eq!(restricted.targets.depth, 0.0);
            continue;
        }
        let crosses = full
            .intervals
            .prim
            .iter()
            .any(|&p| listed.contains(&prims[p as usize].label));
        if crosses {
            assert_eq!(restricted.targets.depth, full.targets.depth, "ray {r}");
            kept += 1;
        } else {
            assert_eq!(restricted.targets.depth, 0.0, "ray {r}");
            dropped += 1;
        }
        // Everything else about the ray is untouched.
        assert_eq!(restricted.targets.label, full.targets.label);
        assert_eq!(restricted.targets.u_mask, full.targets.u_mask);
    }
    assert!(kept > 20 && dropped > 20, "{kept} kept, {dropped} dropped");
}

/// A `depth_classes` list none of whose classes the scene's primitives have would switch L_depth
/// off without a word: training refuses it, naming the parameter and the scene's classes.
#[test]
fn training_refuses_depth_classes_the_scene_lacks() {
    use crate::kinds::train::{Train, TrainParams};
    use crate::TypedStage;
    let (mem, _, _) = planned(small_street());
    let p = TrainParams {
        depth_classes: vec!["rail track".into()],
        ..TrainParams::default()
    };
    Train::validate(&p).unwrap();
    let e = Train
        .run(&p, &mem.inputs(), &crate::NoProgress)
        .err()
        .expect("refused")
        .to_string();
    assert!(
        e.contains("depth_classes") && e.contains("rail track") && e.contains("road"),
        "{e}"
    );
}
