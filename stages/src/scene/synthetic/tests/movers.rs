//! Moving objects of the synthetic street (`moving_objects`): the static street is the same
//! with or without them, their GT lies in their box at each frame, and `dynamic_boxes` holds
//! those boxes.

use super::*;
use crate::geometry::{dynamic_boxes_from_table, primitives_from_table};
use crate::scene::layout::hull_points;

/// A short window of the default street with `n` movers.
fn with_movers(n: u32) -> SceneParams {
    SceneParams {
        frames: 10,
        moving_objects: n,
        ..SceneParams::default()
    }
}

fn movers_scene() -> &'static (SceneParams, Generated) {
    static SCENE: OnceLock<(SceneParams, Generated)> = OnceLock::new();
    SCENE.get_or_init(|| {
        let p = with_movers(4);
        let g = generate(&p, &NoProgress).unwrap();
        (p, g)
    })
}

#[test]
fn movers_change_only_the_pixels_they_cover_and_no_static_primitive() {
    let (p, g) = movers_scene();
    let still = generate(&with_movers(0), &NoProgress).unwrap();
    assert_eq!(
        g.layout.movers.len(),
        5,
        "three cars, a bicycle and its rider"
    );
    assert!(still.layout.movers.is_empty());
    // The same static street: parts, bounds, instance numbers.
    assert_eq!(g.layout.parts.len(), still.layout.parts.len());
    let key = |b: &Primitive| (b.label, b.instance, b.to_world.to_cols_array());
    let (a, b): (Vec<_>, Vec<_>) = (
        g.layout.bounds.iter().map(key).collect(),
        still.layout.bounds.iter().map(key).collect(),
    );
    assert_eq!(a, b);
    let objects: Vec<u16> = g.layout.movers.iter().map(|m| m.object() as u16).collect();
    for m in &g.layout.movers {
        assert!(
            !still
                .layout
                .bounds
                .iter()
                .any(|b| (b.label, b.instance) == (m.label, m.instance)),
            "mover {} shares its instance with a parked car",
            m.object()
        );
    }
    // A label or depth differs only where a mover is seen, and every mover is seen.
    let mut seen = vec![0usize; objects.len()];
    for (i, (x, y)) in g.images.iter().zip(&still.images).enumerate() {
        for k in 0..x.labels.len() {
            if let Some(j) = objects.iter().position(|&o| o == x.instances[k]) {
                seen[j] += 1;
            } else {
                assert_eq!(
                    (x.labels[k], x.instances[k], x.depth[k]),
                    (y.labels[k], y.instances[k], y.depth[k]),
                    "image {i} pixel {k}: changed by no mover"
                );
            }
        }
    }
    let pixels = g.images.len() * g.images[0].labels.len();
    for (o, n) in objects.iter().zip(&seen) {
        assert!(
            *n * 1000 > pixels,
            "mover {o} seen in {n} of {pixels} pixels"
        );
    }
    assert!(p.validate().is_ok());
}

#[test]
fn a_movers_pixels_lie_in_its_box_at_their_frame_and_it_moves() {
    let (_, g) = movers_scene();
    let mut far = 0;
    for m in &g.layout.movers {
        let mut centres = Vec::new();
        for (row, img) in g.cameras.iter().zip(&g.images) {
            let cam = &row.cam;
            let mut sum = (DVec3::ZERO, 0usize);
            for (k, &inst) in img.instances.iter().enumerate() {
                if inst as u32 != m.object() {
                    continue;
                }
                let bound = m.bound_at(row.frame).expect("seen only in its span");
                let (x, y) = (
                    (k % cam.width as usize) as u32,
                    (k / cam.width as usize) as u32,
                );
                let ray = cam.pixel_ray(x, y).unwrap();
                // GT depth back along the ray: the surface point the label belongs to.
                let t = img.depth[k] as f64 / cam.depth(&ray, 1.0);
                let q = ray.at(t);
                assert!(
                    bound.contains(q) || bound_distance(&bound, q) < 1e-3,
                    "mover {} frame {} pixel ({x}, {y}): {q} outside its box",
                    m.object(),
                    row.frame
                );
                sum = (sum.0 + q, sum.1 + 1);
            }
            if sum.1 > 0 {
                centres.push((row.frame, sum.0 / sum.1 as f64));
            }
        }
        // It moves: where it was driven far enough, what it shows at its last frame lies
        // outside its box at its first.
        let (first, last) = (centres.first().unwrap(), centres.last().unwrap());
        let shift = m.pose(last.0).unwrap().translation - m.pose(first.0).unwrap().translation;
        let extent = m.bound.to_world.matrix3.x_axis.length();
        if shift.length() > extent + 0.5 {
            far += 1;
            let then = m.bound_at(first.0).unwrap();
            assert!(!then.contains(last.1), "mover {} did not move", m.object());
        }
    }
    // The car ahead drives about 8 m in the window; the oncoming one leaves the view as it
    // passes, the crossing one is slow.
    assert!(far >= 1, "{far} movers drove farther than their length");
}

/// How far `q` is outside `bound` (0 inside), in metres along the box's axes.
fn bound_distance(bound: &Primitive, q: DVec3) -> f64 {
    let local = bound.to_local().transform_point3(q);
    let out = (local.abs() - DVec3::splat(0.5)).max(DVec3::ZERO);
    (bound.to_world.matrix3 * out).length()
}

#[test]
fn dynamic_boxes_hold_each_movers_box_at_every_frame_it_is_in() {
    let (p, g) = movers_scene();
    let t = to_tables(p, generate(p, &NoProgress).unwrap()).unwrap();
    let boxes = dynamic_boxes_from_table(&t["dynamic_boxes"]).unwrap();
    let expected: usize = g
        .layout
        .movers
        .iter()
        .map(|m| p.frame_numbers().filter(|f| m.frames.contains(f)).count())
        .sum();
    assert_eq!(boxes.len(), expected);
    let keys: Vec<(u32, u32)> = boxes.iter().map(|b| (b.object, b.frame)).collect();
    let mut sorted = keys.clone();
    sorted.sort();
    sorted.dedup();
    assert_eq!(keys, sorted, "rows sorted by (object, frame), each once");
    for b in &boxes {
        let m = g
            .layout
            .movers
            .iter()
            .find(|m| m.object() == b.object)
            .unwrap();
        for part in m.parts_at(b.frame) {
            for q in hull_points(&part) {
                assert!(
                    b.primitive.contains(q),
                    "object {} frame {}",
                    b.object,
                    b.frame
                );
            }
        }
        assert_eq!(
            (b.primitive.label, b.primitive.instance),
            (m.label, m.instance)
        );
    }
    // The crossing car is in the scene only while on the road.
    let crossing = &g.layout.movers[2];
    assert!(crossing.frames.end() - crossing.frames.start() < 25);
    // Static primitives: none of the movers'.
    let prims = primitives_from_table(&t["primitives"]).unwrap();
    assert_eq!(prims.len(), g.layout.bounds.len());
    // A static street has the table, empty.
    let still = to_tables(&SceneParams::default(), default_scene_tables_source()).unwrap();
    assert_eq!(still["dynamic_boxes"].num_rows(), 0);
}

/// A one-frame default street (the empty `dynamic_boxes` case, cheap).
fn default_scene_tables_source() -> Generated {
    generate(
        &SceneParams {
            frames: 1,
            ..SceneParams::default()
        },
        &NoProgress,
    )
    .unwrap()
}

#[test]
fn moving_objects_are_checked() {
    let bad = |p: SceneParams, needle: &str| {
        let e = p.validate().unwrap_err().to_string();
        assert!(e.contains(needle), "{e}");
    };
    bad(with_movers(5), "`moving_objects` must be 0..=4");
    bad(
        SceneParams {
            classes: ["road", "terrain", "sky", "building"]
                .map(String::from)
                .to_vec(),
            ..with_movers(1)
        },
        "must include `car`",
    );
}
