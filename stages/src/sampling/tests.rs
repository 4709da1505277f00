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

/// `Intervals::in_sky` (what rendering tells the field) is where the fixed field is one-hot
/// sky (what training tells it, `SampleBatch::in_sky`), at the interval ends too.
#[test]
fn sky_samples_are_where_the_fixed_field_is_sky() {
    let set = many();
    let mut out = [0.0; 3];
    for r in (0..300).step_by(7) {
        let iv = set.intervals(r);
        for k in 0..=700 {
            let t = k as f32 * 0.1;
            fixed_semantic_at(&set.prims, &iv, t, &mut out);
            assert_eq!(iv.in_sky(t), out == [0.0, 0.0, 1.0], "ray {r}, t {t}");
        }
        for t in [iv.sky[0], iv.sky[1], iv.t_out[0]] {
            fixed_semantic_at(&set.prims, &iv, t, &mut out);
            assert_eq!(iv.in_sky(t), out == [0.0, 0.0, 1.0], "ray {r}, end {t}");
        }
    }
    let b = sample_batch(&set, &[0, 1, 2], &SamplingParams::default(), Some(1)).unwrap();
    let flags = b.in_sky();
    assert!(flags.contains(&true) && flags.contains(&false));
    for (i, &f) in flags.iter().enumerate() {
        let iv = set.intervals(b.ray_ids[i / b.samples] as usize);
        assert_eq!(f, iv.in_sky(b.t[i]) && b.deltas[i] > 0.0, "sample {i}");
    }
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
    // Road [4, 10] and car [5, 7] share 6 samples, 3 each, spread over each by length: the
    // pieces [4, 5], [5, 7], [7, 10] get 0.5, 1 + 3 and 1.5, rounded to 1, 4 and 1 (the tie of
    // remainders goes to the nearer piece); sky [10, 60] two strata of width 25.
    let strata = [
        (4.0, 1.0),
        (5.0, 0.5),
        (5.5, 0.5),
        (6.0, 0.5),
        (6.5, 0.5),
        (7.0, 3.0),
    ];
    for (i, &(t0, w)) in strata.iter().enumerate() {
        assert!(t[i] >= t0 && t[i] <= t0 + w, "{i}: {t:?}");
        assert!((d[i] - w).abs() < 1e-6, "{i}: {d:?}");
    }
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

/// Samples of one ray with the given primitive intervals at stratum centres.
fn centres(intervals: &[(f32, f32)], samples: usize) -> (Vec<f32>, Vec<f32>) {
    let (t_in, t_out): (Vec<f32>, Vec<f32>) = intervals.iter().copied().unzip();
    let prim: Vec<u32> = (0..intervals.len() as u32).collect();
    let iv = Intervals {
        t_in: &t_in,
        t_out: &t_out,
        prim: &prim,
        sky: [0.0, 0.0],
    };
    let p = SamplingParams {
        samples,
        sky_samples: 0,
        ..Default::default()
    };
    let (mut t, mut d) = (vec![0.0; samples], vec![0.0; samples]);
    place_samples(&iv, &p, None, &mut t, &mut d);
    (t, d)
}

#[test]
fn a_thin_primitive_in_front_of_a_deep_one_gets_its_own_share() {
    // A 0.2 m gate box overlapping the first 0.1 m of a 20 m garden box, as a side camera sees
    // a frontage: merged into one stretch, the gate got 28 * 0.2 / 20.1 = 0.3 samples; with a
    // share per interval it gets its 14 (7 + 7.07 over its two pieces).
    let (t, d) = centres(&[(9.9, 10.1), (10.0, 30.0)], 28);
    let in_gate = t.iter().filter(|&&x| (9.9..=10.1).contains(&x)).count();
    assert_eq!(in_gate, 14, "{t:?}");
    // No stratum straddles a face of either box.
    for (&x, &w) in t.iter().zip(&d) {
        let (a, b) = (x - w / 2.0, x + w / 2.0);
        for face in [10.0f32, 10.1] {
            assert!(
                !(a < face - 1e-4 && b > face + 1e-4),
                "[{a}, {b}] straddles {face}"
            );
        }
    }
    assert!((d.iter().sum::<f32>() - 20.1).abs() < 1e-3);
}

proptest::proptest! {
    /// For any intervals: samples ascend, strata lie inside the primitives and do not overlap,
    /// a lone interval gets its whole share, and with a sample per interval the strata tile the
    /// union exactly.
    #[test]
    fn strata_tile_the_union_of_any_intervals(
        raw in proptest::collection::vec((-2.0f32..60.0, 0.001f32..30.0), 1..14),
        samples in 1usize..80,
    ) {
        let mut intervals: Vec<(f32, f32)> = raw.iter().map(|&(a, l)| (a, a + l)).collect();
        intervals.sort_by(|a, b| a.0.total_cmp(&b.0));
        let (t, d) = centres(&intervals, samples);
        let placed = d.iter().take_while(|&&w| w > 0.0).count();
        proptest::prop_assert!(d[placed..].iter().all(|&w| w == 0.0));
        let covered = |x: f32| intervals.iter().any(|&(a, b)| x >= a.max(0.0) - 1e-3 && x <= b + 1e-3);
        let mut prev_end = f32::NEG_INFINITY;
        for i in 0..placed {
            let (a, b) = (t[i] - d[i] / 2.0, t[i] + d[i] / 2.0);
            proptest::prop_assert!(a >= prev_end - 1e-3, "strata overlap at {i}: {t:?} {d:?}");
            proptest::prop_assert!(covered(a) && covered(b) && covered(t[i]), "[{a}, {b}] outside");
            prev_end = b;
        }
        // The union's length, clipped at 0.
        let mut union = 0.0f64;
        let mut cur: Option<(f32, f32)> = None;
        for &(a, b) in &intervals {
            let a = a.max(0.0);
            if b <= a { continue; }
            match cur {
                Some((c0, c1)) if a <= c1 => cur = Some((c0, c1.max(b))),
                _ => {
                    if let Some((c0, c1)) = cur { union += f64::from(c1 - c0); }
                    cur = Some((a, b));
                }
            }
        }
        if let Some((c0, c1)) = cur { union += f64::from(c1 - c0); }
        let n = intervals.iter().filter(|&&(a, b)| b > a.max(0.0)).count();
        let total: f64 = d.iter().map(|&w| f64::from(w)).sum();
        if n == 0 {
            // Every interval lies behind the origin: there is nowhere to put a sample.
            proptest::prop_assert_eq!(placed, 0);
        } else if samples >= n {
            proptest::prop_assert_eq!(placed, samples);
            proptest::prop_assert!((total - union).abs() < 1e-3 * union.max(1.0), "{total} vs {union}");
        } else {
            proptest::prop_assert!(total <= union + 1e-3 * union.max(1.0));
        }
        // An interval meeting no other is a stretch of its own: it gets its share rounded down
        // or up.
        for (j, &(a, b)) in intervals.iter().enumerate() {
            let a = a.max(0.0);
            let alone = b > a && intervals.iter().enumerate().all(|(i, &(c, e))| {
                i == j || e < a || c.max(0.0) > b || e <= c.max(0.0)
            });
            if alone {
                let share = samples as f64 / n as f64;
                let got = t[..placed].iter().filter(|&&x| x > a && x < b).count() as f64;
                proptest::prop_assert!(got >= share.floor() && got <= share.ceil(),
                    "interval {j} got {got} of share {share}");
            }
        }
    }
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
    use crate::scene::synthetic::{generate, in_memory::to_tables, SceneParams};
    let sp = SceneParams {
        frames: 2,
        scale: 0.05,
        ..SceneParams::default()
    };
    to_tables(&sp, generate(&sp, &crate::NoProgress).unwrap()).unwrap()
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
    let mut p = TrainParams::default();
    p.losses.depth_classes = vec!["rail track".into()];
    Train::validate(&p).unwrap();
    let e = Train
        .run(&p, &mem.inputs(), &crate::NoProgress)
        .expect_err("refused")
        .to_string();
    assert!(
        e.contains("losses.depth_classes") && e.contains("rail track") && e.contains("road"),
        "{e}"
    );
}

/// A jittered ray goes through a point of its own pixel (projected back, to f32 rounding), is
/// traced anew there (its intervals are those of a trace through that point), keeps its
/// pixel's targets, and falls back to the pixel's centre ray where the point sees no
/// primitive; the offset (0.5, 0.5) is the centre ray itself, and the points depend on the seed.
#[test]
fn jittered_rays_pass_through_their_own_pixel() {
    use crate::geometry::{primitives_from_table, Bvh};
    let scene = small_street();
    let prims = primitives_from_table(&scene["primitives"]).unwrap();
    let bvh = Bvh::build(&prims);
    let (mem, _, _) = planned(scene);
    let traced = train_rays(&mem.inputs()).unwrap();
    let (a, b) = (
        JitteredRays {
            rays: &traced,
            seed: 7,
            width: 1.0,
            bilinear_labels: false,
        },
        JitteredRays {
            rays: &traced,
            seed: 8,
            width: 1.0,
            bilinear_labels: false,
        },
    );
    let (mut buf, mut centre_buf, mut own) =
        (RayPlan::default(), RayPlan::default(), RayPlan::default());
    let (mut moved, mut other_intervals, mut fell_back, mut seeds_differ) = (0, 0, 0, 0);
    for r in 0..traced.len() as u32 {
        let (im, p) = traced.locate(r);
        if im.hits[p] == 0 {
            continue;
        }
        let (x, y) = (p as u32 % im.cam.width, p as u32 / im.cam.width);
        let centre = traced.ray(r, &mut centre_buf).unwrap();
        let same = traced.ray_at(r, Some([0.5, 0.5]), &mut buf).unwrap();
        assert_eq!((same.origin, same.dir), (centre.origin, centre.dir));
        let off = a.offset(r);
        assert!(off.iter().all(|o| (0.0..1.0).contains(o)), "{off:?}");
        seeds_differ += usize::from(off != b.offset(r));
        let half = JitteredRays { width: 0.5, ..a }.offset(r);
        assert!(half.iter().all(|o| (0.25..0.75).contains(o)), "{half:?}");
        // A corner of the pixel every 7th ray: the most likely to leave the primitives.
        let off = if r % 7 == 0 { [0.0, 0.0] } else { off };
        let ray = traced.ray_at(r, Some(off), &mut buf).unwrap();
        assert_eq!(ray.targets.rgb, centre.targets.rgb, "ray {r}");
        assert_eq!(ray.targets.depth, centre.targets.depth, "ray {r}");
        assert!(ray.intervals.hits_anything(), "ray {r} crosses nothing");
        let through = im
            .cam
            .ray(x as f64 + off[0], y as f64 + off[1])
            .expect("pinhole");
        own.trace(&prims, &bvh, &through, &IntersectParams::default());
        if own.t_in.is_empty() {
            assert_eq!(
                (ray.origin, ray.dir),
                (centre.origin, centre.dir),
                "ray {r}"
            );
            fell_back += 1;
            continue;
        }
        assert_eq!(ray.intervals.t_in, &own.t_in[..], "ray {r}");
        assert_eq!(ray.intervals.prim, &own.prim[..], "ray {r}");
        let far = glam::DVec3::from(ray.origin.map(f64::from))
            + 20.0 * glam::DVec3::from(ray.dir.map(f64::from));
        let (u, v, _) = im.cam.project(far).unwrap();
        let tol = 1e-3;
        assert!(
            u > x as f64 - tol && u < (x + 1) as f64 + tol,
            "ray {r}: u {u}, pixel x {x}"
        );
        assert!(
            v > y as f64 - tol && v < (y + 1) as f64 + tol,
            "ray {r}: v {v}, pixel y {y}"
        );
        let (dc, dj) = (centre.dir, ray.dir);
        moved += usize::from(dc != dj);
        other_intervals += usize::from(ray.intervals.prim != centre.intervals.prim);
    }
    assert!(moved > 1000, "{moved} rays moved");
    assert!(
        other_intervals > 10,
        "{other_intervals} jittered rays cross other primitives than their centre ray"
    );
    assert!(fell_back > 0, "no jittered ray fell back to its centre");
    assert!(seeds_differ > 1000, "{seeds_differ}");
}

/// Bilinear jitter labels: a ray takes the neighbour on its point's side of each axis with
/// probability equal to the point's distance from the centre (the neighbour's bilinear
/// weight), its own pixel's label otherwise, and the draw is deterministic in the seed.
#[test]
fn bilinear_jitter_labels_draw_neighbours_with_their_bilinear_weight() {
    let scene = small_street();
    let (mem, _, _) = planned(scene);
    let traced = train_rays(&mem.inputs()).unwrap();
    let j = JitteredRays {
        rays: &traced,
        seed: 11,
        width: 1.0,
        bilinear_labels: true,
    };
    let plain = JitteredRays {
        bilinear_labels: false,
        ..j
    };
    // Per axis, bins of the distance |offset - 0.5|: draws and neighbour picks.
    const BINS: usize = 5;
    let mut draws = [0usize; BINS];
    let mut picked = [0usize; BINS];
    let (mut buf, mut relabelled) = (RayPlan::default(), 0);
    for r in 0..traced.len() as u32 {
        let (off, shift) = j.draw(r);
        assert_eq!(
            off,
            plain.offset(r),
            "the point does not depend on the labels' draw"
        );
        assert_eq!(plain.draw(r).1, [0, 0]);
        assert_eq!(j.draw(r), (off, shift), "deterministic");
        for a in 0..2 {
            let d = off[a] - 0.5;
            assert!(
                shift[a] == 0 || shift[a] == d.signum() as i32,
                "{off:?} {shift:?}"
            );
            let bin = ((d.abs() * 2.0 * BINS as f64) as usize).min(BINS - 1);
            draws[bin] += 1;
            picked[bin] += usize::from(shift[a] != 0);
        }
        // The ray's label is the shifted pixel's (clamped to the image), sky aside (a sky
        // label below the horizon is dropped).
        let (im, p) = traced.locate(r);
        let (w, h) = (im.cam.width as i64, im.cam.height as i64);
        let (x, y) = (p as i64 % w, p as i64 / w);
        let q = ((y + shift[1] as i64).clamp(0, h - 1) * w + (x + shift[0] as i64).clamp(0, w - 1))
            as usize;
        let Some(labels) = &im.targets.labels else {
            continue;
        };
        let want = traced.prims.label_class(labels[q]);
        let ray = traced
            .ray_labelled_by(r, Some(off), shift, &mut buf)
            .unwrap();
        let via_trait = j.ray(r, &mut RayPlan::default()).unwrap().targets.label;
        assert_eq!(ray.targets.label, via_trait, "ray {r}");
        let sky = want != NONE && traced.prims.classes[want as usize] == labels::SKY;
        if !sky && (ray.dir != traced.ray(r, &mut RayPlan::default()).unwrap().dir) {
            assert_eq!(ray.targets.label, want, "ray {r}, shift {shift:?}");
            relabelled += usize::from(q != p && labels[q] != labels[p]);
        }
    }
    for b in 0..BINS {
        // Bin b holds distances in [b, b + 1) / (2 BINS): expected pick rate its midpoint.
        let want = (b as f64 + 0.5) / (2 * BINS) as f64;
        let got = picked[b] as f64 / draws[b] as f64;
        let sd = (want * (1.0 - want) / draws[b] as f64).sqrt();
        assert!(draws[b] > 500, "bin {b}: {} draws", draws[b]);
        assert!(
            (got - want).abs() < 4.0 * sd + 0.01,
            "bin {b}: {got} vs {want}"
        );
    }
    assert!(
        relabelled > 20,
        "{relabelled} rays took another class from a neighbour"
    );
}

/// The sparse stereo depth gives back every finite, positive value of the dense map it came
/// from, and 0 at every other pixel (0, NaN, infinite, negative, past the end).
#[test]
fn sparse_depth_gives_back_the_dense_map() {
    let mut rng = crate::rng::SplitMix64::new(7);
    let dense: Vec<f32> = (0..5000)
        .map(|_| match rng.next_u64() % 6 {
            0 | 1 => 0.0,
            2 => f32::NAN,
            3 => f32::INFINITY,
            4 => -1.5,
            _ => 0.5 + (rng.next_u64() % 4000) as f32 / 100.0,
        })
        .collect();
    let sparse = SparseDepth::from_dense(&dense);
    let mut kept = 0;
    for (p, &d) in dense.iter().enumerate() {
        let want = if d.is_finite() && d > 0.0 { d } else { 0.0 };
        kept += (want > 0.0) as usize;
        assert_eq!(sparse.get(p), want, "pixel {p}: dense {d}");
    }
    assert!(kept > 500, "only {kept} values: no test");
    assert_eq!(sparse.get(dense.len()), 0.0);
    assert_eq!(sparse.get(usize::MAX >> 1), 0.0);
}
