//! Small deterministic scenes for tests, benchmarks and pictures: a street-like scene of every
//! primitive kind, random scenes of many primitives, and shape builders (a cube as a mesh, a
//! star-shaped non-convex mesh, a star polygon). The crate's SplitMix64 keeps this free of a
//! `rand` dependency.

use glam::{DAffine3, DQuat, DVec3};

use super::{Camera, Lens, Primitive, Shape};
use crate::labels;
use crate::rng::{SplitMix64, GOLDEN_GAMMA};

/// The crate's SplitMix64 with f64 draws and random directions, for test scenes.
#[derive(Clone, Debug)]
pub struct Rng(SplitMix64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(SplitMix64::new(seed ^ GOLDEN_GAMMA))
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0.next_u64()
    }
    /// Uniform in `[lo, hi)`.
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64)
    }
    pub fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }
    /// A uniformly random unit vector.
    pub fn unit(&mut self) -> DVec3 {
        loop {
            let v = DVec3::new(
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
            );
            let l = v.length_squared();
            if l > 1e-6 && l <= 1.0 {
                return v / l.sqrt();
            }
        }
    }
    pub fn rotation(&mut self) -> DQuat {
        DQuat::from_axis_angle(self.unit(), self.range(0.0, std::f64::consts::TAU))
    }
}

/// The unit cube `[-0.5, 0.5]^3` as an outward-wound 8-vertex, 12-triangle mesh (KITTI-360's
/// cuboid encoding).
pub fn cube_mesh() -> Shape {
    let vertices = (0..8)
        .map(|i| {
            DVec3::new(
                if i & 1 == 0 { -0.5 } else { 0.5 },
                if i & 2 == 0 { -0.5 } else { 0.5 },
                if i & 4 == 0 { -0.5 } else { 0.5 },
            )
        })
        .collect();
    // Quads wound counter-clockwise seen from outside.
    let quads: [[u32; 4]; 6] = [
        [0, 2, 3, 1], // z = -0.5
        [4, 5, 7, 6], // z = +0.5
        [0, 1, 5, 4], // y = -0.5
        [2, 6, 7, 3], // y = +0.5
        [0, 4, 6, 2], // x = -0.5
        [1, 3, 7, 5], // x = +0.5
    ];
    let faces = quads
        .iter()
        .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
        .collect();
    Shape::Mesh { vertices, faces }
}

/// A star-shaped (about the origin), generally non-convex closed mesh: `rings` latitude rings
/// of `sectors` vertices plus two poles, vertex radii from `radius` (called once per vertex).
pub fn star_mesh(rings: usize, sectors: usize, mut radius: impl FnMut() -> f64) -> Shape {
    use std::f64::consts::PI;
    let mut vertices = vec![DVec3::Z * radius()];
    for i in 1..=rings {
        let th = PI * i as f64 / (rings + 1) as f64;
        for j in 0..sectors {
            let ph = 2.0 * PI * j as f64 / sectors as f64;
            let dir = DVec3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos());
            vertices.push(dir * radius());
        }
    }
    vertices.push(-DVec3::Z * radius());
    let bottom = (vertices.len() - 1) as u32;
    let v = |i: usize, j: usize| (1 + (i - 1) * sectors + j % sectors) as u32;
    let mut faces = Vec::new();
    for j in 0..sectors {
        faces.push([0, v(1, j), v(1, j + 1)]);
        for i in 1..rings {
            faces.push([v(i, j), v(i + 1, j), v(i + 1, j + 1)]);
            faces.push([v(i, j), v(i + 1, j + 1), v(i, j + 1)]);
        }
        faces.push([v(rings, j), bottom, v(rings, j + 1)]);
    }
    Shape::Mesh { vertices, faces }
}

/// A star-shaped polygon of `n` vertices about the origin (non-convex in general), with radii
/// from `radius` and angular jitter from `jitter` (in `[0, 0.45]` of a sector).
pub fn star_polygon(
    n: usize,
    mut radius: impl FnMut() -> f64,
    mut jitter: impl FnMut() -> f64,
) -> Shape {
    let polygon = (0..n)
        .map(|j| {
            let a = std::f64::consts::TAU * (j as f64 + jitter()) / n as f64;
            let r = radius();
            [r * a.cos(), r * a.sin()]
        })
        .collect();
    Shape::Extruded { polygon }
}

/// A random shape of any kind.
pub fn random_shape(rng: &mut Rng) -> Shape {
    match rng.below(5) {
        0 => Shape::Cuboid,
        1 => Shape::Ellipsoid,
        2 => {
            let n = 3 + rng.below(8);
            let mut r2 = rng.clone();
            let s = star_polygon(n, || r2.range(0.25, 0.5), || 0.0);
            *rng = r2;
            s
        }
        3 => cube_mesh(),
        _ => {
            let (rings, sectors) = (1 + rng.below(3), 3 + rng.below(5));
            star_mesh(rings, sectors, || rng.range(0.25, 0.5))
        }
    }
}

/// `n` random primitives of every kind in a box of side `extent` metres, sizes 0.5..`size` m.
pub fn random_scene(n: usize, extent: f64, size: f64, seed: u64) -> Vec<Primitive> {
    let mut rng = Rng::new(seed);
    let classes = labels::PAPER_CLASSES;
    (0..n)
        .map(|i| {
            let shape = random_shape(&mut rng);
            let scale = DVec3::new(
                rng.range(0.5, size),
                rng.range(0.5, size),
                rng.range(0.5, size),
            );
            let t = DVec3::new(
                rng.range(-extent, extent) * 0.5,
                rng.range(-extent, extent) * 0.5,
                rng.range(-extent, extent) * 0.5,
            );
            let m = DAffine3::from_scale_rotation_translation(scale, rng.rotation(), t);
            let label = classes[rng.below(classes.len())];
            let inst = if labels::is_paper_thing(label) {
                i as u32 % 999 + 1
            } else {
                0
            };
            Primitive::new(shape, m, label, inst).expect("random primitives are valid")
        })
        .collect()
}

/// A street-like scene in the scene frame (x forward along the street, y left, z up): road,
/// sidewalks, buildings (one L-shaped extruded footprint, one mesh with a gable roof), cars,
/// trees (ellipsoid crowns), a fence, and a box. Returns the primitives and a left camera at
/// the start of the street looking along +x (OpenCV axes: z forward, x right, y down).
pub fn street_scene(width: u32, height: u32) -> (Vec<Primitive>, Camera) {
    let mut prims = Vec::new();
    street_ground(&mut prims);
    street_buildings(&mut prims);
    street_cars(&mut prims);
    street_furniture(&mut prims);
    // Camera 1.6 m above the road at x = 0.
    (
        prims,
        looking_along_x(width, height, DVec3::new(0.0, 0.0, 1.6)),
    )
}

/// Appends a primitive of `shape` scaled by `scale`, turned by `rot_z` about z and moved to `t`.
fn add_street(
    prims: &mut Vec<Primitive>,
    shape: Shape,
    scale: DVec3,
    rot_z: f64,
    t: DVec3,
    label: u8,
    inst: u32,
) {
    let m = DAffine3::from_scale_rotation_translation(scale, DQuat::from_rotation_z(rot_z), t);
    prims.push(Primitive::new(shape, m, label, inst).expect("street primitives are valid"));
}

/// The street's ground: the road, and a sidewalk and terrain on each side.
fn street_ground(prims: &mut Vec<Primitive>) {
    use labels::*;
    // Road: 8 m wide, 80 m long, 0.2 m thick, top at z = 0.
    add_street(
        prims,
        Shape::Cuboid,
        DVec3::new(80.0, 8.0, 0.2),
        0.0,
        DVec3::new(40.0, 0.0, -0.1),
        ROAD,
        0,
    );
    for side in [-1.0, 1.0] {
        add_street(
            prims,
            Shape::Cuboid,
            DVec3::new(80.0, 3.0, 0.35),
            0.0,
            DVec3::new(40.0, side * 5.5, -0.025),
            SIDEWALK,
            0,
        );
        add_street(
            prims,
            Shape::Cuboid,
            DVec3::new(80.0, 10.0, 0.2),
            0.0,
            DVec3::new(40.0, side * 12.0, -0.1),
            TERRAIN,
            0,
        );
    }
}

/// The street's buildings, instances 1 to 4: two boxes and an L-shaped extruded footprint on
/// the left (y > 0), a house with a gable roof on the right.
fn street_buildings(prims: &mut Vec<Primitive>) {
    use labels::*;
    let mut inst = 1;
    for (x0, len, h) in [(6.0, 10.0, 9.0), (30.0, 8.0, 14.0)] {
        add_street(
            prims,
            Shape::Cuboid,
            DVec3::new(len, 8.0, h),
            0.0,
            DVec3::new(x0 + len / 2.0, 12.0, h / 2.0),
            BUILDING,
            inst,
        );
        inst += 1;
    }
    let l_shape = Shape::Extruded {
        polygon: vec![
            [0.0, 0.0],
            [1.0, 0.0],
            [1.0, 0.4],
            [0.4, 0.4],
            [0.4, 1.0],
            [0.0, 1.0],
        ],
    };
    add_street(
        prims,
        l_shape,
        DVec3::new(12.0, 10.0, 11.0),
        0.0,
        DVec3::new(17.0, 7.5, 5.5),
        BUILDING,
        inst,
    );
    inst += 1;
    add_street(
        prims,
        gable_house(),
        DVec3::new(14.0, 9.0, 10.0),
        0.0,
        DVec3::new(20.0, -12.0, 5.0),
        BUILDING,
        inst,
    );
}

/// A house with a gable roof in the unit cube: a mesh (pentagonal prism along x).
fn gable_house() -> Shape {
    let prof = [
        [-0.5, -0.5],
        [0.5, -0.5],
        [0.5, 0.2],
        [0.0, 0.5],
        [-0.5, 0.2],
    ]; // (y, z)
    let mut vertices = Vec::new();
    for x in [-0.5, 0.5] {
        for p in prof {
            vertices.push(DVec3::new(x, p[0], p[1]));
        }
    }
    let mut faces = vec![
        [0, 2, 1],
        [0, 3, 2],
        [0, 4, 3],
        [5, 6, 7],
        [5, 7, 8],
        [5, 8, 9],
    ];
    for k in 0..5u32 {
        let n = (k + 1) % 5;
        faces.push([k, n, n + 5]);
        faces.push([k, n + 5, k + 5]);
    }
    Shape::Mesh { vertices, faces }
}

/// Four cars parked on both sides, instances 1 to 4.
fn street_cars(prims: &mut Vec<Primitive>) {
    for (k, (x, y, rot)) in [
        (9.0, 2.6, 0.0),
        (15.0, -2.7, 0.05),
        (24.0, 2.5, -0.04),
        (38.0, -2.6, 0.0),
    ]
    .into_iter()
    .enumerate()
    {
        add_street(
            prims,
            Shape::Cuboid,
            DVec3::new(4.3, 1.8, 1.5),
            rot,
            DVec3::new(x, y, 0.75),
            labels::CAR,
            k as u32 + 1,
        );
    }
}

/// Trees on the right sidewalk (trunk: a pole-like vegetation cuboid; crown: an ellipsoid), a
/// fence and a box.
fn street_furniture(prims: &mut Vec<Primitive>) {
    use labels::*;
    for x in [8.0, 26.0, 34.0] {
        add_street(
            prims,
            Shape::Cuboid,
            DVec3::new(0.3, 0.3, 3.0),
            0.0,
            DVec3::new(x, -5.5, 1.5),
            VEGETATION,
            0,
        );
        add_street(
            prims,
            Shape::Ellipsoid,
            DVec3::new(3.5, 3.5, 4.0),
            0.0,
            DVec3::new(x, -5.5, 4.5),
            VEGETATION,
            0,
        );
    }
    add_street(
        prims,
        Shape::Cuboid,
        DVec3::new(6.0, 0.1, 1.2),
        0.0,
        DVec3::new(48.0, 7.2, 0.6),
        FENCE,
        0,
    );
    add_street(
        prims,
        Shape::Cuboid,
        DVec3::new(1.0, 1.0, 1.0),
        0.4,
        DVec3::new(12.0, 5.0, 0.5),
        BOX,
        1,
    );
}

/// A camera at `centre` looking along +x with a 90 degree horizontal field of view: camera z =
/// world x, camera x = world -y, camera y = world -z.
fn looking_along_x(width: u32, height: u32, centre: DVec3) -> Camera {
    let r = glam::DMat3::from_cols(-DVec3::Y, -DVec3::Z, DVec3::X);
    let f = width as f64 * 0.5;
    Camera {
        width,
        height,
        fx: f,
        fy: f,
        cx: width as f64 / 2.0,
        cy: height as f64 / 2.0,
        lens: Lens::Pinhole,
        cam_to_world: DAffine3::from_mat3_translation(r, centre),
    }
}

/// A long synthetic street of `n` primitives of every kind (road slabs, buildings as cuboids,
/// L-shaped extrusions and non-convex meshes, cars, tree crowns, clutter meshes) over
/// x in [0, 400] m, and a camera at its start looking down +x with a 90 degree field of view.
/// Used by the `intersect` benchmark.
pub fn city_scene(n: usize, width: u32, height: u32, seed: u64) -> (Vec<Primitive>, Camera) {
    use labels::*;
    let mut rng = Rng::new(seed);
    let mut prims = Vec::with_capacity(n);
    let side = |rng: &mut Rng| if rng.below(2) == 0 { -1.0 } else { 1.0 };
    for i in 0..n {
        let x = rng.range(0.0, 400.0);
        let yaw = DQuat::from_rotation_z(rng.range(-0.1, 0.1));
        let (shape, scale, t, label, inst) = match rng.below(10) {
            0 => (
                Shape::Cuboid,
                DVec3::new(20.0, 8.0, 0.2),
                DVec3::new(x, 0.0, -0.1),
                ROAD,
                0,
            ),
            1..=3 => {
                let (l, w, h) = (
                    rng.range(8.0, 20.0),
                    rng.range(8.0, 15.0),
                    rng.range(6.0, 25.0),
                );
                let shape = match rng.below(3) {
                    0 => Shape::Cuboid,
                    1 => Shape::Extruded {
                        polygon: vec![
                            [-0.5, -0.5],
                            [0.5, -0.5],
                            [0.5, -0.1],
                            [-0.1, -0.1],
                            [-0.1, 0.5],
                            [-0.5, 0.5],
                        ],
                    },
                    _ => star_mesh(2, 6, || rng.range(0.35, 0.5)),
                };
                let y = side(&mut rng) * rng.range(12.0, 20.0);
                (
                    shape,
                    DVec3::new(l, w, h),
                    DVec3::new(x, y, h / 2.0),
                    BUILDING,
                    i as u32 % 999 + 1,
                )
            }
            4..=6 => {
                let y = side(&mut rng) * rng.range(2.0, 3.5);
                (
                    Shape::Cuboid,
                    DVec3::new(4.3, 1.8, 1.5),
                    DVec3::new(x, y, 0.75),
                    CAR,
                    i as u32 % 999 + 1,
                )
            }
            7 | 8 => {
                let y = side(&mut rng) * rng.range(5.0, 7.0);
                (
                    Shape::Ellipsoid,
                    DVec3::new(3.5, 3.5, 4.0),
                    DVec3::new(x, y, 4.5),
                    VEGETATION,
                    0,
                )
            }
            _ => {
                let y = side(&mut rng) * rng.range(4.5, 7.0);
                let s = rng.range(0.5, 2.0);
                let shape = star_mesh(1 + rng.below(2), 4 + rng.below(4), || rng.range(0.3, 0.5));
                (
                    shape,
                    DVec3::splat(s),
                    DVec3::new(x, y, s / 2.0),
                    BOX,
                    i as u32 % 999 + 1,
                )
            }
        };
        let m = DAffine3::from_scale_rotation_translation(scale, yaw, t);
        prims.push(Primitive::new(shape, m, label, inst).expect("city primitives are valid"));
    }
    (
        prims,
        looking_along_x(width, height, DVec3::new(-5.0, 0.0, 1.6)),
    )
}
