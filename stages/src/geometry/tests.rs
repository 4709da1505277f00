//! Tests of the geometry core: every shape against a brute-force reference (dense marching with
//! the point test), rays from inside, grazing and parallel rays, degenerate primitives, the BVH
//! against brute force, the camera, the fixed fields and the table codecs. Randomised tests use
//! proptest (seeded per run, shrinking) and print the ray and primitive on failure.

use glam::{DAffine3, DQuat, DVec3};
use proptest::prelude::*;

use super::demo::{cube_mesh, random_scene, star_mesh, star_polygon, Rng};
use super::*;
use crate::labels;

fn intervals(p: &Primitive, r: &Ray) -> Vec<Interval> {
    let mut v = Vec::new();
    p.intersect(r, &mut v);
    v
}

/// Checks `intervals(p, r)` against dense marching with `p.contains` and basic invariants.
/// Returns a description of the first violation.
fn check_against_marching(p: &Primitive, r: &Ray) -> Result<(), String> {
    let ivs = intervals(p, r);
    let ctx = || format!("ray {r:?}\nprimitive {p:?}\nintervals {ivs:?}");
    for (k, iv) in ivs.iter().enumerate() {
        if !(iv.t_in < iv.t_out && iv.t_out > 0.0) {
            return Err(format!("bad interval {k}\n{}", ctx()));
        }
        if (iv.normal_in.length() - 1.0).abs() > 1e-9 {
            return Err(format!("normal of interval {k} not unit\n{}", ctx()));
        }
        if iv.t_in > 0.0 && iv.normal_in.dot(r.dir) > 1e-9 {
            return Err(format!(
                "entry normal of interval {k} faces along the ray\n{}",
                ctx()
            ));
        }
        if k > 0 && ivs[k - 1].t_out > iv.t_in {
            return Err(format!(
                "intervals {} and {k} overlap or are unsorted\n{}",
                k - 1,
                ctx()
            ));
        }
        let mid = 0.5 * (iv.t_in.max(0.0) + iv.t_out);
        if !p.contains(r.at(mid)) {
            return Err(format!(
                "midpoint {mid} of interval {k} is outside\n{}",
                ctx()
            ));
        }
    }
    // March far enough to leave the primitive's bounds.
    let b = p.aabb();
    let far = (b.max - r.origin)
        .abs()
        .max((b.min - r.origin).abs())
        .length()
        + 1.0;
    let steps = 3000;
    let tol = 1e-7 * (1.0 + far);
    for s in 1..=steps {
        let t = far * s as f64 / steps as f64;
        let by_iv = ivs.iter().any(|iv| iv.t_in <= t && t <= iv.t_out);
        if by_iv != p.contains(r.at(t)) {
            let near_end = ivs
                .iter()
                .any(|iv| (iv.t_in - t).abs() < tol || (iv.t_out - t).abs() < tol);
            if !near_end {
                return Err(format!(
                    "at t = {t}: intervals say inside = {by_iv}, contains says {}\n{}",
                    !by_iv,
                    ctx()
                ));
            }
        }
    }
    Ok(())
}

// ---- strategies ----

fn arb_vec(lo: f64, hi: f64) -> impl Strategy<Value = DVec3> {
    (lo..hi, lo..hi, lo..hi).prop_map(|(x, y, z)| DVec3::new(x, y, z))
}

fn arb_unit() -> impl Strategy<Value = DVec3> {
    arb_vec(-1.0, 1.0)
        .prop_filter("non-zero direction", |v| v.length() > 1e-3)
        .prop_map(|v| v.normalize())
}

fn arb_transform() -> impl Strategy<Value = DAffine3> {
    (
        arb_vec(0.2, 4.0),
        arb_unit(),
        0.0..std::f64::consts::TAU,
        arb_vec(-3.0, 3.0),
    )
        .prop_map(|(s, axis, angle, t)| {
            DAffine3::from_scale_rotation_translation(s, DQuat::from_axis_angle(axis, angle), t)
        })
}

/// Any shape kind, with random non-convex polygons and meshes.
fn arb_shape() -> impl Strategy<Value = Shape> {
    prop_oneof![
        Just(Shape::Cuboid),
        Just(Shape::Ellipsoid),
        (3usize..12, any::<u64>(), any::<bool>()).prop_map(|(n, seed, flip)| {
            let mut rng = Rng::new(seed);
            let mut r2 = Rng::new(seed.wrapping_add(1));
            let mut s = star_polygon(n, || rng.range(0.1, 0.5), || r2.range(0.0, 0.45));
            if let (Shape::Extruded { polygon }, true) = (&mut s, flip) {
                polygon.reverse();
            }
            s
        }),
        Just(cube_mesh()),
        (1usize..4, 3usize..8, any::<u64>()).prop_map(|(rings, sectors, seed)| {
            let mut rng = Rng::new(seed);
            star_mesh(rings, sectors, || rng.range(0.15, 0.5))
        }),
    ]
}

fn arb_primitive() -> impl Strategy<Value = Primitive> {
    (arb_shape(), arb_transform())
        .prop_map(|(s, m)| Primitive::new(s, m, labels::CAR, 1).expect("valid primitive"))
}

/// Rays from outside aimed near the primitive (so most hit).
fn arb_ray_at(p: &Primitive) -> impl Strategy<Value = Ray> {
    let c = p.to_world.translation;
    let size = p.aabb().extent().length();
    (arb_unit(), 1.0..3.0f64, arb_vec(-0.6, 0.6)).prop_map(move |(from, dist, off)| {
        let origin = c + from * size * dist;
        Ray::new(origin, c + off * size - origin)
    })
}

/// `cases` by default; `PROPTEST_CASES=N` in the environment overrides it (for soak runs).
fn cfg(cases: u32) -> ProptestConfig {
    if std::env::var_os("PROPTEST_CASES").is_some() {
        return ProptestConfig::default();
    }
    ProptestConfig {
        cases,
        ..ProptestConfig::default()
    }
}

proptest! {
    #![proptest_config(cfg(400))]

    #[test]
    fn intervals_match_dense_marching((p, r) in arb_primitive().prop_flat_map(|p| {
        let rays = arb_ray_at(&p);
        (Just(p), rays)
    })) {
        check_against_marching(&p, &r).map_err(TestCaseError::fail)?;
    }

    #[test]
    fn rays_starting_inside((p, r) in arb_primitive().prop_flat_map(|p| {
        let m = p.to_world;
        (Just(p), arb_vec(-0.08, 0.08), arb_unit()).prop_map(move |(p, off, d)| {
            let o = m.transform_point3(off);
            (p, Ray::new(o, d))
        })
    })) {
        prop_assume!(p.contains(r.origin));
        let ivs = intervals(&p, &r);
        prop_assert!(!ivs.is_empty() && ivs[0].t_in <= 0.0 && ivs[0].t_out > 0.0,
            "origin inside but first interval {:?}\nray {:?}\nprim {:?}", ivs.first(), r, p);
        check_against_marching(&p, &r).map_err(TestCaseError::fail)?;
    }

    /// Rays aimed exactly at an edge or vertex of the unit cube give the same interval as a
    /// cuboid, a 12-triangle mesh and an extruded square (intervals shorter than 1e-9 ignored:
    /// a ray that only touches an edge may or may not produce one).
    #[test]
    fn cube_kinds_agree_on_edges_and_vertices(
        m in arb_transform(),
        from in arb_unit(),
        axis in 0usize..3,
        s in prop_oneof![Just(-0.5), Just(0.5), -0.5..0.5f64],
        corner in (any::<bool>(), any::<bool>()),
    ) {
        let mut target = DVec3::splat(0.0);
        target[axis] = s;
        target[(axis + 1) % 3] = if corner.0 { 0.5 } else { -0.5 };
        target[(axis + 2) % 3] = if corner.1 { 0.5 } else { -0.5 };
        let origin = m.transform_point3(from * 3.0);
        let r = Ray::new(origin, m.transform_point3(target) - origin);
        let square = Shape::Extruded { polygon: vec![[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]] };
        let kinds = [Shape::Cuboid, cube_mesh(), square];
        let results: Vec<Vec<(f64, f64)>> = kinds
            .into_iter()
            .map(|k| {
                let p = Primitive::new(k, m, 1, 0).unwrap();
                intervals(&p, &r).iter().filter(|iv| iv.t_out - iv.t_in > 1e-9)
                    .map(|iv| (iv.t_in, iv.t_out)).collect()
            })
            .collect();
        for k in 1..3 {
            prop_assert_eq!(results[0].len(), results[k].len(), "kind {} differs: {:?}\nray {:?}", k, results, r);
            for (a, b) in results[0].iter().zip(&results[k]) {
                prop_assert!((a.0 - b.0).abs() < 1e-7 && (a.1 - b.1).abs() < 1e-7,
                    "kind {} differs: {:?}\nray {:?}", k, results, r);
            }
        }
    }

    #[test]
    fn camera_ray_and_project_round_trip(
        rot in arb_unit(), angle in 0.0..std::f64::consts::TAU, pos in arb_vec(-1000.0, 1000.0),
        u in 0.0..1408.0f64, v in 0.0..376.0f64, t in 0.5..150.0f64,
    ) {
        let cam = Camera { width: 1408, height: 376, fx: 552.5, fy: 552.5, cx: 682.0, cy: 238.8,
            lens: crate::geometry::Lens::Pinhole, cam_to_world: DAffine3::from_rotation_translation(DQuat::from_axis_angle(rot, angle), pos) };
        let r = cam.ray(u, v).expect("a pinhole has a ray through every point");
        prop_assert!((r.dir.length() - 1.0).abs() < 1e-12);
        let (pu, pv, z) = cam.project(r.at(t)).expect("in front");
        prop_assert!((pu - u).abs() < 1e-6 && (pv - v).abs() < 1e-6, "({pu},{pv}) vs ({u},{v})");
        prop_assert!((z - cam.z_depth(&r, t)).abs() < 1e-7);
        prop_assert!((z - t * cam.dir_cam(u, v).unwrap().z).abs() < 1e-7);
        prop_assert!(cam.project(r.at(-t)).is_none());
    }
}

// ---- BVH against brute force ----

fn brute_force(prims: &[Primitive], r: &Ray, t_min: f64, t_max: f64) -> Vec<Hit> {
    let mut out = Vec::new();
    for (i, p) in prims.iter().enumerate() {
        for iv in intervals(p, r) {
            let (a, b) = (iv.t_in.max(t_min), iv.t_out.min(t_max));
            if a < b {
                out.push(Hit {
                    t_in: a,
                    t_out: b,
                    prim: i as u32,
                    normal_in: iv.normal_in,
                });
            }
        }
    }
    out.sort_by(|a, b| a.t_in.total_cmp(&b.t_in).then(a.prim.cmp(&b.prim)));
    out
}

proptest! {
    #![proptest_config(cfg(24))]

    #[test]
    fn bvh_equals_brute_force(seed in any::<u64>(), n in 0usize..220, t_min in 0.0..5.0f64) {
        let prims = random_scene(n, 40.0, 6.0, seed);
        let bvh = Bvh::build(&prims);
        bvh.validate(&prims).map_err(TestCaseError::fail)?;
        let mut rng = Rng::new(seed ^ 77);
        let mut got = Vec::new();
        let mut ids = Vec::new();
        let mut total_hits = 0;
        for _ in 0..200 {
            let o = DVec3::new(rng.range(-30.0, 30.0), rng.range(-30.0, 30.0), rng.range(-30.0, 30.0));
            // Half the rays aim near a random primitive, half go anywhere.
            let dir = if n > 0 && rng.below(2) == 0 {
                let c = prims[rng.below(n)].aabb().centre();
                c + rng.unit() * rng.range(0.0, 2.0) - o
            } else {
                rng.unit()
            };
            let r = Ray::new(o, dir);
            let t_max = rng.range(10.0, 80.0);
            let want = brute_force(&prims, &r, t_min, t_max);
            bvh.intersect_all(&prims, &r, t_min, t_max, &mut got);
            prop_assert_eq!(&got, &want, "ray {:?}", r);
            total_hits += got.len();
            prop_assert_eq!(bvh.first_hit(&prims, &r, t_min, t_max), want.first().copied(), "ray {:?}", r);
            let want_ids: Vec<u32> = (0..prims.len() as u32).filter(|&i| prims[i as usize].contains(o)).collect();
            bvh.containing(&prims, o, &mut ids);
            prop_assert_eq!(&ids, &want_ids, "point {:?}", o);
        }
        // Not vacuous: rays aimed at primitives hit them.
        prop_assert!(n < 10 || total_hits > 20, "only {} hits", total_hits);
    }
}

/// Two sets at once (a static scene and the moving objects at a frame) give the first hit of
/// their union: its entry, and the set it belongs to.
#[test]
fn first_hit_of_two_sets_is_the_first_hit_of_their_union() {
    let (mut hits, mut second) = (0, 0);
    for seed in 0..8u64 {
        let a = random_scene(60, 30.0, 5.0, seed);
        let b = random_scene(6, 20.0, 4.0, seed ^ 0x5eed);
        let union: Vec<Primitive> = a.iter().chain(&b).cloned().collect();
        let (ba, bb, bu) = (Bvh::build(&a), Bvh::build(&b), Bvh::build(&union));
        let mut rng = Rng::new(seed);
        for _ in 0..300 {
            let o = DVec3::new(
                rng.range(-25.0, 25.0),
                rng.range(-25.0, 25.0),
                rng.range(-25.0, 25.0),
            );
            let target = union[rng.below(union.len())].aabb().centre();
            let r = Ray::new(o, target + rng.unit() * rng.range(0.0, 2.0) - o);
            let want = bu.first_hit(&union, &r, 0.0, 100.0);
            let got = Bvh::first_hit_of_two((&ba, &a), (&bb, &b), &r, 0.0, 100.0);
            match (want, got) {
                (None, None) => {}
                (Some(w), Some((g, in_b))) => {
                    hits += 1;
                    second += usize::from(in_b);
                    assert_eq!(w.t_in.max(0.0), g.t_in.max(0.0), "seed {seed} ray {r:?}");
                    let picked = if in_b {
                        &b[g.prim as usize]
                    } else {
                        &a[g.prim as usize]
                    };
                    let first = &union[w.prim as usize];
                    assert_eq!(picked.to_world, first.to_world, "seed {seed} ray {r:?}");
                }
                (w, g) => panic!("seed {seed} ray {r:?}: union {w:?}, two sets {g:?}"),
            }
        }
    }
    assert!(
        hits > 500 && second > 50,
        "{hits} hits, {second} in the second set"
    );
}

#[test]
fn bvh_of_many_coincident_primitives_is_valid() {
    let prims: Vec<Primitive> = (0..100)
        .map(|_| Primitive::new(Shape::Cuboid, DAffine3::IDENTITY, 7, 0).unwrap())
        .collect();
    let bvh = Bvh::build(&prims);
    bvh.validate(&prims).unwrap();
    let mut hits = Vec::new();
    bvh.intersect_all(
        &prims,
        &Ray::new(DVec3::new(-2.0, 0.1, 0.2), DVec3::X),
        0.0,
        10.0,
        &mut hits,
    );
    assert_eq!(hits.len(), 100);
    assert_eq!(Bvh::build(&[]).node_count(), 0);
}

// ---- exact and grazing cases ----

fn unit(shape: Shape) -> Primitive {
    Primitive::new(shape, DAffine3::IDENTITY, 7, 0).unwrap()
}

fn spans(p: &Primitive, r: &Ray) -> Vec<(f64, f64)> {
    intervals(p, r)
        .iter()
        .map(|iv| (iv.t_in, iv.t_out))
        .collect()
}

fn assert_spans(got: &[(f64, f64)], want: &[(f64, f64)]) {
    assert_eq!(got.len(), want.len(), "got {got:?}, want {want:?}");
    for (g, w) in got.iter().zip(want) {
        assert!(
            (g.0 - w.0).abs() < 1e-9 && (g.1 - w.1).abs() < 1e-9,
            "got {got:?}, want {want:?}"
        );
    }
}

#[test]
fn exact_intervals_of_each_kind() {
    let r = Ray::new(DVec3::new(-2.0, 0.0, 0.0), DVec3::X);
    assert_spans(&spans(&unit(Shape::Cuboid), &r), &[(1.5, 2.5)]);
    assert_spans(&spans(&unit(Shape::Ellipsoid), &r), &[(1.5, 2.5)]);
    assert_spans(&spans(&unit(cube_mesh()), &r), &[(1.5, 2.5)]);
    // A U-shaped (non-convex) prism: the ray along x at y = 0.4 crosses both arms.
    let u = Shape::Extruded {
        polygon: vec![
            [-0.5, -0.5],
            [0.5, -0.5],
            [0.5, 0.5],
            [0.2, 0.5],
            [0.2, 0.0],
            [-0.2, 0.0],
            [-0.2, 0.5],
            [-0.5, 0.5],
        ],
    };
    let r = Ray::new(DVec3::new(-2.0, 0.4, 0.0), DVec3::X);
    assert_spans(&spans(&unit(u.clone()), &r), &[(1.5, 1.8), (2.2, 2.5)]);
    // The same U through a vertex of the notch (y = 0.0 is the notch bottom edge: grazing).
    let r = Ray::new(DVec3::new(-2.0, -0.2, 0.0), DVec3::X);
    assert_spans(&spans(&unit(u), &r), &[(1.5, 2.5)]);
    // Scaled, rotated, translated ellipsoid: semi-axes 2, 1, 0.5 along world x, y, z.
    let m = DAffine3::from_scale_rotation_translation(
        DVec3::new(4.0, 2.0, 1.0),
        DQuat::IDENTITY,
        DVec3::new(10.0, 0.0, 0.0),
    );
    let e = Primitive::new(Shape::Ellipsoid, m, 1, 0).unwrap();
    assert_spans(&spans(&e, &Ray::new(DVec3::ZERO, DVec3::X)), &[(8.0, 12.0)]);
    let iv = intervals(&e, &Ray::new(DVec3::ZERO, DVec3::X))[0];
    assert!((iv.normal_in - -DVec3::X).length() < 1e-12);
    // A ray from inside: negative t_in.
    assert_spans(
        &spans(&e, &Ray::new(DVec3::new(11.0, 0.0, 0.0), DVec3::X)),
        &[(-3.0, 1.0)],
    );
    // Behind the origin: nothing.
    assert!(spans(&e, &Ray::new(DVec3::new(13.0, 0.0, 0.0), DVec3::X)).is_empty());
}

#[test]
fn non_convex_mesh_gives_several_intervals() {
    // An extruded U as a mesh must give the same two intervals as the extruded primitive.
    let poly = [
        [-0.5, -0.5],
        [0.5, -0.5],
        [0.5, 0.5],
        [0.2, 0.5],
        [0.2, 0.0],
        [-0.2, 0.0],
        [-0.2, 0.5],
        [-0.5, 0.5],
    ];
    let n = poly.len() as u32;
    let mut vertices = Vec::new();
    for z in [-0.5, 0.5] {
        vertices.extend(poly.iter().map(|p| DVec3::new(p[0], p[1], z)));
    }
    // Caps by a fan from vertex 1 (the U is star-shaped about no vertex, so triangulate by hand).
    let cap = [
        [0, 1, 5],
        [1, 4, 5],
        [1, 2, 4],
        [2, 3, 4],
        [0, 5, 6],
        [0, 6, 7],
    ];
    let mut faces: Vec<[u32; 3]> = cap.iter().map(|&[a, b, c]| [a, c, b]).collect(); // bottom faces down
    faces.extend(cap.iter().map(|&[a, b, c]| [a + n, b + n, c + n]));
    for k in 0..n {
        let j = (k + 1) % n;
        faces.push([k, j, j + n]);
        faces.push([k, j + n, k + n]);
    }
    let mesh = unit(Shape::Mesh { vertices, faces });
    let r = Ray::new(DVec3::new(-2.0, 0.4, 0.1), DVec3::X);
    assert_spans(&spans(&mesh, &r), &[(1.5, 1.8), (2.2, 2.5)]);
    check_against_marching(&mesh, &r).unwrap();
    assert!(mesh.contains(DVec3::new(0.0, -0.2, 0.0)));
    assert!(!mesh.contains(DVec3::new(0.0, 0.3, 0.0)));
}

#[test]
fn grazing_and_parallel_rays() {
    let cube = unit(Shape::Cuboid);
    let mesh = unit(cube_mesh());
    let sphere = unit(Shape::Ellipsoid);
    // Diagonally through a vertex and out through the opposite vertex.
    let r = Ray::new(DVec3::splat(-1.0), DVec3::ONE);
    let s3 = 3f64.sqrt();
    for p in [&cube, &mesh] {
        assert_spans(&spans(p, &r), &[(0.5 * s3, 1.5 * s3)]);
    }
    // Through an edge (x = -0.5, y = -0.5) into the interior.
    let r = Ray::new(DVec3::new(-1.0, -1.0, 0.3), DVec3::new(1.0, 1.0, 0.0));
    let s2 = 2f64.sqrt();
    for p in [&cube, &mesh] {
        assert_spans(&spans(p, &r), &[(0.5 * s2, 1.5 * s2)]);
    }
    // Through a triangle diagonal of the mesh face z = 0.5.
    let r = Ray::new(DVec3::new(0.1, 0.1, 2.0), -DVec3::Z);
    assert_spans(&spans(&mesh, &r), &[(1.5, 2.5)]);
    // Touching an edge from outside (silhouette): nothing, or nothing longer than zero.
    let r = Ray::new(DVec3::new(-1.5, 0.0, 0.5), DVec3::new(1.0, 0.0, 1.0));
    for p in [&cube, &mesh] {
        assert!(
            spans(p, &r).iter().all(|s| s.1 - s.0 < 1e-9),
            "{:?}",
            spans(p, &r)
        );
    }
    // Tangent to the sphere: nothing.
    assert!(spans(&sphere, &Ray::new(DVec3::new(-2.0, 0.5, 0.0), DVec3::X)).is_empty());
    // Parallel to faces, inside: the whole chord, t_in negative.
    for p in [&cube, &mesh] {
        assert_spans(
            &spans(p, &Ray::new(DVec3::new(0.0, 0.1, 0.2), DVec3::Y)),
            &[(-0.6, 0.4)],
        );
    }
    // Parallel to a face, outside: nothing.
    for p in [&cube, &mesh] {
        assert!(spans(p, &Ray::new(DVec3::new(-2.0, 0.7, 0.0), DVec3::X)).is_empty());
    }
    // In the plane of a face (closed cube: inside; mesh boundary: either, but well-formed).
    let r = Ray::new(DVec3::new(-2.0, 0.0, 0.5), DVec3::X);
    assert_spans(&spans(&cube, &r), &[(1.5, 2.5)]);
    let m = spans(&mesh, &r);
    assert!(
        m.is_empty() || (m.len() == 1 && (m[0].0 - 1.5).abs() < 1e-9),
        "{m:?}"
    );
    // Along the axis of an extruded prism (no xy motion).
    let tri = unit(Shape::Extruded {
        polygon: vec![[-0.4, -0.4], [0.4, -0.4], [0.0, 0.4]],
    });
    assert_spans(
        &spans(&tri, &Ray::new(DVec3::new(0.0, 0.0, -3.0), DVec3::Z)),
        &[(2.5, 3.5)],
    );
    assert!(spans(&tri, &Ray::new(DVec3::new(0.39, 0.3, -3.0), DVec3::Z)).is_empty());
}

#[test]
fn meshes_with_per_face_vertex_copies_are_welded() {
    let Shape::Mesh { vertices, faces } = cube_mesh() else {
        unreachable!()
    };
    let (mut vs, mut fs) = (Vec::new(), Vec::new());
    for f in &faces {
        let base = vs.len() as u32;
        vs.extend(f.iter().map(|&i| vertices[i as usize]));
        fs.push([base, base + 1, base + 2]);
    }
    let p = unit(Shape::Mesh {
        vertices: vs.clone(),
        faces: fs.clone(),
    });
    assert_spans(
        &spans(&p, &Ray::new(DVec3::new(-2.0, 0.1, 0.1), DVec3::X)),
        &[(1.5, 2.5)],
    );
    // Still open when a face is missing.
    let e = Primitive::new(
        Shape::Mesh {
            vertices: vs,
            faces: fs[1..].to_vec(),
        },
        DAffine3::IDENTITY,
        1,
        0,
    );
    assert!(e.unwrap_err().to_string().contains("not closed"));
}

#[test]
fn inward_wound_mesh_is_flipped() {
    let Shape::Mesh { vertices, faces } = cube_mesh() else {
        unreachable!()
    };
    let inward = Shape::Mesh {
        vertices,
        faces: faces.iter().map(|&[a, b, c]| [a, c, b]).collect(),
    };
    let p = unit(inward);
    assert!(p.contains(DVec3::ZERO) && !p.contains(DVec3::splat(0.6)));
    assert_spans(
        &spans(&p, &Ray::new(DVec3::new(-2.0, 0.1, 0.1), DVec3::X)),
        &[(1.5, 2.5)],
    );
}

#[test]
fn degenerate_primitives_are_rejected_with_clear_errors() {
    let err = |s: Shape, m: DAffine3| Primitive::new(s, m, 1, 0).unwrap_err().to_string();
    let flat = DAffine3::from_scale(DVec3::new(1.0, 2.0, 0.0));
    assert_eq!(
        err(Shape::Cuboid, flat),
        "degenerate transform (zero extent along local z)"
    );
    let collapsed = DAffine3::from_mat3(DMat3::from_cols(
        DVec3::X,
        DVec3::Y,
        DVec3::new(1.0, 1.0, 0.0),
    ));
    assert!(err(Shape::Ellipsoid, collapsed).contains("linearly dependent"));
    let mut nan = DAffine3::IDENTITY;
    nan.translation.x = f64::NAN;
    assert!(err(Shape::Cuboid, nan).contains("non-finite"));
    let id = DAffine3::IDENTITY;
    assert_eq!(
        err(
            Shape::Extruded {
                polygon: vec![[0.0, 0.0], [1.0, 0.0]]
            },
            id
        ),
        "polygon has fewer than 3 vertices (it has 2)"
    );
    assert_eq!(
        err(
            Shape::Extruded {
                polygon: vec![[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]
            },
            id
        ),
        "polygon has zero area"
    );
    let bowtie = vec![[0.0, 0.0], [2.0, 2.0], [2.0, 0.0], [0.0, 1.0]];
    assert!(err(Shape::Extruded { polygon: bowtie }, id).contains("self-intersecting"));
    let Shape::Mesh { vertices, faces } = cube_mesh() else {
        unreachable!()
    };
    let open = Shape::Mesh {
        vertices: vertices.clone(),
        faces: faces[..11].to_vec(),
    };
    let e = err(open, id);
    assert!(
        e.starts_with("mesh is not closed: edge (") && e.contains("used by 1 face"),
        "{e}"
    );
    let mut flipped = faces.clone();
    flipped[3] = [flipped[3][0], flipped[3][2], flipped[3][1]];
    let e = err(
        Shape::Mesh {
            vertices: vertices.clone(),
            faces: flipped,
        },
        id,
    );
    assert!(e.contains("flipped face"), "{e}");
    let mut bad = faces.clone();
    bad[0][1] = 99;
    assert_eq!(
        err(
            Shape::Mesh {
                vertices: vertices.clone(),
                faces: bad
            },
            id
        ),
        "mesh face 0 refers to vertex 99, but there are only 8 vertices"
    );
    let mut dup = faces.clone();
    dup[0] = [0, 0, 1];
    assert!(err(
        Shape::Mesh {
            vertices: vertices.clone(),
            faces: dup
        },
        id
    )
    .contains("degenerate"));
    assert_eq!(
        err(
            Shape::Mesh {
                vertices,
                faces: vec![]
            },
            id
        ),
        "mesh has no faces"
    );
    // Two copies of the same triangle, opposite windings: closed, consistent, zero volume.
    let sheet = Shape::Mesh {
        vertices: vec![DVec3::ZERO, DVec3::X, DVec3::Y],
        faces: vec![[0, 1, 2], [0, 2, 1]],
    };
    assert_eq!(err(sheet, id), "mesh encloses zero volume");
}

// ---- fixed fields ----

#[test]
fn fixed_semantic_and_instance_fields() {
    let at = |x: f64, label: u8, inst: u32| {
        Primitive::new(
            Shape::Cuboid,
            DAffine3::from_translation(DVec3::new(x, 0.0, 0.0)),
            label,
            inst,
        )
        .unwrap()
    };
    // Two cars overlapping on [0.1, 0.4]; a building overlapping the second car on [0.6, 0.9].
    let prims = vec![
        at(-0.1, labels::CAR, 1),
        at(0.5, labels::CAR, 2),
        at(1.4, labels::BUILDING, 1),
    ];
    let bvh = Bvh::build(&prims);
    let classes = [labels::ROAD, labels::BUILDING, labels::CAR];
    let mut s = [0f32; 3];
    let sem = |x: f64, s: &mut [f32; 3]| {
        fixed_semantic(&prims, &bvh, DVec3::new(x, 0.0, 0.0), &classes, s)
    };
    sem(-0.5, &mut s);
    assert_eq!(s, [0.0, 0.0, 1.0]);
    sem(0.2, &mut s); // same class overlap: one-hot
    assert_eq!(s, [0.0, 0.0, 1.0]);
    sem(0.95, &mut s); // car and building: equal
    assert_eq!(s, [0.0, 0.5, 0.5]);
    sem(5.0, &mut s); // outside: all zero
    assert_eq!(s, [0.0, 0.0, 0.0]);
    let things = scene_things(&prims);
    assert_eq!(
        things,
        vec![(labels::BUILDING, 1), (labels::CAR, 1), (labels::CAR, 2)]
    );
    let mut t = [0f32; 3];
    fixed_instance(&prims, &bvh, DVec3::new(0.2, 0.0, 0.0), &things, &mut t);
    assert_eq!(t, [0.0, 0.5, 0.5]);
    fixed_instance(&prims, &bvh, DVec3::new(1.5, 0.0, 0.0), &things, &mut t);
    assert_eq!(t, [1.0, 0.0, 0.0]);
}

// ---- table codecs ----

#[test]
fn primitives_and_cameras_round_trip_through_tables() {
    let (mut prims, cam) = demo::street_scene(64, 32);
    prims.extend(random_scene(20, 10.0, 2.0, 3));
    let t = primitives_to_table(&prims).unwrap();
    let back = primitives_from_table(&t).unwrap();
    assert_eq!(back.len(), prims.len());
    for (a, b) in prims.iter().zip(&back) {
        assert_eq!(
            (&a.shape, a.label, a.instance),
            (&b.shape, b.label, b.instance)
        );
        assert!(a.to_world.abs_diff_eq(b.to_world, 1e-12));
    }
    let rows = vec![
        CameraRow {
            frame: 250,
            camera: 0,
            eval: true,
            cam: cam.clone(),
        },
        CameraRow {
            frame: 252,
            camera: 1,
            eval: false,
            cam: cam.clone(),
        },
        CameraRow {
            frame: 252,
            camera: 2,
            eval: false,
            cam: Camera {
                lens: crate::geometry::Lens::Mei(crate::geometry::Mei {
                    xi: 2.2,
                    k1: 0.017,
                    k2: 1.65,
                    p1: 4e-4,
                    p2: -3e-4,
                    max_half_angle_deg: 95.0,
                }),
                ..cam
            },
        },
    ];
    let t = cameras_to_table(&rows).unwrap();
    assert_eq!(cameras_from_table(&t).unwrap(), rows);
    // A lens the code does not know, and an MEI lens with xi <= 0, name row and column.
    let mut cols: Vec<arrow::array::ArrayRef> = t.columns().to_vec();
    let lens_col = t.schema().index_of("lens").unwrap();
    cols[lens_col] = crate::tables::strings(["pinhole", "kannala_brandt", "MEI"]);
    let e = cameras_from_table(&crate::tables::build("cameras", cols).unwrap())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("row 1 column `lens`: unknown lens `kannala_brandt`"),
        "{e}"
    );
    let mut bad = rows.clone();
    if let crate::geometry::Lens::Mei(m) = &mut bad[2].cam.lens {
        m.xi = 0.0;
    }
    let e = cameras_from_table(&cameras_to_table(&bad).unwrap())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("row 2 column `lens_params`: mirror parameter xi"),
        "{e}"
    );
}

#[test]
fn bad_primitive_rows_name_row_and_column() {
    let prims = vec![
        Primitive::new(Shape::Cuboid, DAffine3::IDENTITY, 7, 0).unwrap(),
        Primitive::new(cube_mesh(), DAffine3::IDENTITY, 11, 1).unwrap(),
    ];
    let t = primitives_to_table(&prims).unwrap();
    // Drop the last face of row 1: an open mesh.
    use arrow::{array::ArrayRef, datatypes::UInt32Type};
    let faces = crate::tables::get_list::<UInt32Type>(&t, "primitives", "faces").unwrap();
    let rows: Vec<Vec<u32>> = (0..2).map(|i| faces.row(i).to_vec()).collect();
    let short = vec![rows[0].clone(), rows[1][..33].to_vec()];
    let mut cols: Vec<ArrayRef> = t.columns().to_vec();
    cols[7] = crate::tables::list::<UInt32Type>(short);
    let bad = crate::tables::build("primitives", cols).unwrap();
    let e = primitives_from_table(&bad).unwrap_err().to_string();
    assert!(
        e.contains("row 1 column `faces`: mesh is not closed"),
        "{e}"
    );
}
