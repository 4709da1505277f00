//! The synthetic street: its true geometry (what the cameras see, composed of exact geometry
//! primitives with a class, instance and material) and its coarse 3D bounding primitives (what
//! a human annotator would draw: inflated, slightly misaligned, overlapping boxes, ellipsoids
//! and extruded polygons).
//!
//! Scene frame: x along the street (the rig drives towards +x), y to the left, z up; the road
//! surface is z = 0. Cross-section (|y|, both sides): road [0, 4], parking strip [4, 6.2],
//! planted verge [6.2, 7.2] (terrain, street trees), raised sidewalk [7.2, 9] (kerb 0.12 m), gardens (terrain) from 9 with hedges, walls,
//! fences and gates along |y| = 9.3, then buildings with facades at |y| = 12.5..15 and gaps
//! with trees; beyond |y| = 45 and past the street's ends, open terrain.

use std::collections::BTreeMap;

use crate::geometry::{DAffine3, DMat3, DVec3, Primitive, Shape};
use crate::labels::{
    BOX, BUILDING, CAR, CARAVAN, FENCE, GATE, PARKING, ROAD, SIDEWALK, TERRAIN, TRAILER,
    VEGETATION, WALL,
};

use super::rng::{Purpose, Rng};

/// Surface patterns of the procedural textures (see `render.rs`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Pattern {
    /// Asphalt with lane markings.
    Asphalt,
    /// Paving stones (parking strips).
    Paving,
    /// Sidewalk slabs.
    Slabs,
    Grass,
    /// Building facade with a window grid; windows start at `x0` along the facade.
    Facade {
        x0: f64,
        bay: f64,
        floor: f64,
    },
    Foliage,
    Bark,
    Paint,
    Glass,
    Tyre,
    Concrete,
    Brick,
    /// Vertical slats (fences, gates).
    Slats,
    Metal,
}

/// A part's look: pattern and base colour (display values in [0, 1]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Material {
    pub pattern: Pattern,
    pub color: [f64; 3],
}

const fn mat(pattern: Pattern, color: [f64; 3]) -> Material {
    Material { pattern, color }
}

/// The whole scene.
pub struct Layout {
    /// True geometry, rendered exactly.
    pub parts: Vec<Primitive>,
    /// `materials[i]` is the look of `parts[i]`.
    pub materials: Vec<Material>,
    /// Coarse bounding primitives (the `primitives` table).
    pub bounds: Vec<Primitive>,
    /// Street extent along x (the stuff strips span it).
    pub x_range: (f64, f64),
}

/// What the layout depends on.
#[derive(Debug, Clone)]
pub struct LayoutParams {
    pub seed: u64,
    /// Length of the driven street segment; the street is built 30 m before and 70 m after it.
    pub street_length: f64,
    /// Classes that may appear (label ids); road, terrain are always present.
    pub classes: Vec<u8>,
}

/// Half-widths of the cross-section strips (|y| boundaries), metres.
pub const ROAD_HALF: f64 = 4.0;
pub const PARKING_OUTER: f64 = 6.2;
/// A planted verge (terrain, street trees) between the parking strip and the sidewalk.
pub const VERGE_OUTER: f64 = 7.2;
pub const SIDEWALK_OUTER: f64 = 9.0;
pub const KERB: f64 = 0.12;
pub const GARDEN_TOP: f64 = 0.1;
pub const GARDEN_OUTER: f64 = 45.0;
/// Lateral position of the left camera (the rig drives in the right lane).
pub const RIG_Y: f64 = -2.0;

/// A local -> world transform: yaw about z, then scale `size`, centred at `centre`.
pub fn box_tf(centre: DVec3, size: DVec3, yaw: f64) -> DAffine3 {
    DAffine3::from_mat3_translation(
        DMat3::from_rotation_z(yaw) * DMat3::from_diagonal(size),
        centre,
    )
}

/// A regular `n`-gon of radius 0.5 (a cylinder cross-section for extruded primitives).
fn ngon(n: usize) -> Vec<[f64; 2]> {
    (0..n)
        .map(|k| {
            let a = std::f64::consts::TAU * k as f64 / n as f64;
            [0.5 * a.cos(), 0.5 * a.sin()]
        })
        .collect()
}

/// Points whose convex hull contains the primitive (exact vertices for cuboids and extruded
/// polygons; a dense surface sample for ellipsoids, whose parts here are axis-aligned so the
/// axis extremes are exact).
pub fn hull_points(p: &Primitive) -> Vec<DVec3> {
    let local: Vec<DVec3> = match &p.shape {
        Shape::Cuboid => (0..8)
            .map(|k| {
                DVec3::new(
                    if k & 1 == 0 { -0.5 } else { 0.5 },
                    if k & 2 == 0 { -0.5 } else { 0.5 },
                    if k & 4 == 0 { -0.5 } else { 0.5 },
                )
            })
            .collect(),
        Shape::Ellipsoid => {
            let mut v = Vec::new();
            for i in 0..=8 {
                let th = std::f64::consts::PI * i as f64 / 8.0;
                for j in 0..16 {
                    let ph = std::f64::consts::TAU * j as f64 / 16.0;
                    v.push(0.5 * DVec3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()));
                }
            }
            v
        }
        Shape::Extruded { polygon } => polygon
            .iter()
            .flat_map(|q| [DVec3::new(q[0], q[1], -0.5), DVec3::new(q[0], q[1], 0.5)])
            .collect(),
        Shape::Mesh { vertices, .. } => vertices.clone(),
    };
    local
        .into_iter()
        .map(|v| p.to_world.transform_point3(v))
        .collect()
}

/// Which convex shape a bounding primitive takes.
#[derive(Clone, Copy, PartialEq)]
enum BoundShape {
    Box,
    Ellipsoid,
}

struct Builder {
    parts: Vec<Primitive>,
    materials: Vec<Material>,
    bounds: Vec<Primitive>,
    instances: BTreeMap<u8, u32>,
    classes: Vec<u8>,
    rng: Rng,
    brng: Rng,
}

impl Builder {
    fn has(&self, class: u8) -> bool {
        self.classes.contains(&class)
    }

    fn new_instance(&mut self, class: u8) -> u32 {
        let n = self.instances.entry(class).or_insert(0);
        *n += 1;
        *n
    }

    fn part(&mut self, shape: Shape, tf: DAffine3, label: u8, instance: u32, m: Material) {
        let p = Primitive::new(shape, tf, label, instance)
            .unwrap_or_else(|e| panic!("synthetic part of class {label} is invalid: {e}"));
        self.parts.push(p);
        self.materials.push(m);
    }

    fn cuboid(&mut self, centre: DVec3, size: DVec3, yaw: f64, label: u8, inst: u32, m: Material) {
        self.part(Shape::Cuboid, box_tf(centre, size, yaw), label, inst, m);
    }

    /// A cylinder with its axis along the local y of `yaw` (wheels).
    fn wheel(&mut self, centre: DVec3, radius: f64, width: f64, yaw: f64, label: u8, inst: u32) {
        // Local z (extrusion) -> world y: rotate +90 degrees about x, then yaw.
        let r = DMat3::from_rotation_z(yaw) * DMat3::from_rotation_x(-std::f64::consts::FRAC_PI_2);
        let tf = DAffine3::from_mat3_translation(
            r * DMat3::from_diagonal(DVec3::new(2.0 * radius, 2.0 * radius, width)),
            centre,
        );
        let m = mat(Pattern::Tyre, [0.09, 0.09, 0.1]);
        self.part(Shape::Extruded { polygon: ngon(12) }, tf, label, inst, m);
    }

    /// An upright cylinder standing on `base` (tree trunks).
    fn pillar(&mut self, base: DVec3, radius: f64, height: f64, label: u8, m: Material) {
        let tf = DAffine3::from_mat3_translation(
            DMat3::from_diagonal(DVec3::new(2.0 * radius, 2.0 * radius, height)),
            base + DVec3::Z * (height / 2.0),
        );
        self.part(Shape::Extruded { polygon: ngon(8) }, tf, label, 0, m);
    }

    /// A bounding primitive around parts `from..` (plus `extra` points), in a frame of heading
    /// `yaw`: inflated by `inflate` (relative) plus `margin` metres, jittered (yaw, offset) like
    /// a hand annotation, then grown until it really contains every part.
    #[allow(clippy::too_many_arguments)]
    fn bound(
        &mut self,
        from: usize,
        extra: &[DVec3],
        yaw: f64,
        inflate: f64,
        margin: f64,
        shape: BoundShape,
        label: u8,
        instance: u32,
    ) {
        let mut pts: Vec<DVec3> = self.parts[from..].iter().flat_map(hull_points).collect();
        pts.extend_from_slice(extra);
        let rot = DMat3::from_rotation_z(-yaw);
        let local: Vec<DVec3> = pts.iter().map(|&p| rot * p).collect();
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for p in &local {
            lo = lo.min(*p);
            hi = hi.max(*p);
        }
        let b = &mut self.brng;
        let jitter_yaw = yaw + b.normal() * 0.012;
        let centre = DMat3::from_rotation_z(yaw) * ((lo + hi) / 2.0)
            + DVec3::new(b.normal(), b.normal(), 0.3 * b.normal()) * 0.35 * margin;
        let mut size = (hi - lo) * (1.0 + inflate * b.range(0.6, 1.4)) + DVec3::splat(2.0 * margin);
        if shape == BoundShape::Ellipsoid {
            size *= 1.15;
        }
        let kind = match shape {
            BoundShape::Box => Shape::Cuboid,
            BoundShape::Ellipsoid => Shape::Ellipsoid,
        };
        for _ in 0..100 {
            let p = Primitive::new(
                kind.clone(),
                box_tf(centre, size, jitter_yaw),
                label,
                instance,
            )
            .expect("bounding primitive is valid");
            if pts.iter().all(|&q| p.contains(q)) {
                self.bounds.push(p);
                return;
            }
            size *= 1.04;
        }
        panic!("bounding primitive of class {label} never contained its parts");
    }

    /// A stuff bound as a polygon in world xy extruded over [z0, z1].
    fn slab_bound(&mut self, polygon: Vec<[f64; 2]>, z0: f64, z1: f64, label: u8) {
        let tf = DAffine3::from_mat3_translation(
            DMat3::from_diagonal(DVec3::new(1.0, 1.0, z1 - z0)),
            DVec3::new(0.0, 0.0, (z0 + z1) / 2.0),
        );
        let p = Primitive::new(Shape::Extruded { polygon }, tf, label, 0)
            .expect("stuff polygon is valid");
        self.bounds.push(p);
    }

    fn box_bound(&mut self, lo: DVec3, hi: DVec3, label: u8) {
        let p = Primitive::new(
            Shape::Cuboid,
            box_tf((lo + hi) / 2.0, hi - lo, 0.0),
            label,
            0,
        )
        .expect("stuff box is valid");
        self.bounds.push(p);
    }
}

/// A strip polygon along x from `x0` to `x1` between lateral edges near `y_in` and `y_out`
/// (each wobbling outward by up to `wobble` every 8 m, like a hand-drawn outline).
fn strip(rng: &mut Rng, x0: f64, x1: f64, y_in: f64, y_out: f64, wobble: f64) -> Vec<[f64; 2]> {
    let n = ((x1 - x0) / 8.0).ceil().max(1.0) as usize;
    let xs: Vec<f64> = (0..=n)
        .map(|k| x0 + (x1 - x0) * k as f64 / n as f64)
        .collect();
    let s = (y_out - y_in).signum();
    let mut poly: Vec<[f64; 2]> = xs
        .iter()
        .map(|&x| [x, y_in - s * wobble * rng.f64()])
        .collect();
    poly.extend(
        xs.iter()
            .rev()
            .map(|&x| [x, y_out + s * wobble * rng.f64()]),
    );
    poly
}

const FACADE_COLOURS: &[[f64; 3]] = &[
    [0.78, 0.72, 0.62],
    [0.93, 0.92, 0.88],
    [0.62, 0.6, 0.58],
    [0.62, 0.36, 0.3],
    [0.82, 0.66, 0.42],
    [0.72, 0.76, 0.78],
];
const CAR_COLOURS: &[[f64; 3]] = &[
    [0.7, 0.1, 0.1],
    [0.12, 0.2, 0.55],
    [0.85, 0.85, 0.86],
    [0.15, 0.15, 0.16],
    [0.45, 0.47, 0.5],
    [0.2, 0.45, 0.3],
    [0.9, 0.75, 0.2],
];

/// Builds the scene. Deterministic in `p`.
pub fn build(p: &LayoutParams) -> Layout {
    let x0 = -30.0;
    let x1 = p.street_length + 70.0;
    let mut b = Builder {
        parts: Vec::new(),
        materials: Vec::new(),
        bounds: Vec::new(),
        instances: BTreeMap::new(),
        classes: p.classes.clone(),
        rng: Rng::new(p.seed, Purpose::Layout, &[]),
        brng: Rng::new(p.seed, Purpose::Bounds, &[]),
    };
    let parking = if b.has(PARKING) { PARKING } else { ROAD };
    let sidewalk = if b.has(SIDEWALK) { SIDEWALK } else { TERRAIN };

    // Ground: the road, parking strips, raised sidewalks, gardens, and far terrain below all.
    let len = x1 - x0;
    let xc = (x0 + x1) / 2.0;
    let asphalt = mat(Pattern::Asphalt, [0.33, 0.33, 0.34]);
    b.cuboid(
        DVec3::new(xc, 0.0, -0.15),
        DVec3::new(len, 2.0 * ROAD_HALF, 0.3),
        0.0,
        ROAD,
        0,
        asphalt,
    );
    for side in [1.0, -1.0] {
        let m = if parking == PARKING {
            mat(Pattern::Paving, [0.5, 0.47, 0.44])
        } else {
            asphalt
        };
        let w = PARKING_OUTER - ROAD_HALF;
        b.cuboid(
            DVec3::new(xc, side * (ROAD_HALF + w / 2.0), -0.15),
            DVec3::new(len, w, 0.3),
            0.0,
            parking,
            0,
            m,
        );
        let w = VERGE_OUTER - PARKING_OUTER;
        b.cuboid(
            DVec3::new(xc, side * (PARKING_OUTER + w / 2.0), (KERB - 0.3) / 2.0),
            DVec3::new(len, w, KERB + 0.3),
            0.0,
            TERRAIN,
            0,
            mat(Pattern::Grass, [0.4, 0.5, 0.22]),
        );
        let w = SIDEWALK_OUTER - VERGE_OUTER;
        let m = if sidewalk == SIDEWALK {
            mat(Pattern::Slabs, [0.66, 0.64, 0.62])
        } else {
            mat(Pattern::Grass, [0.35, 0.5, 0.2])
        };
        b.cuboid(
            DVec3::new(xc, side * (VERGE_OUTER + w / 2.0), (KERB - 0.3) / 2.0),
            DVec3::new(len, w, KERB + 0.3),
            0.0,
            sidewalk,
            0,
            m,
        );
        let w = GARDEN_OUTER - SIDEWALK_OUTER;
        b.cuboid(
            DVec3::new(
                xc,
                side * (SIDEWALK_OUTER + w / 2.0),
                (GARDEN_TOP - 0.3) / 2.0,
            ),
            DVec3::new(len, w, GARDEN_TOP + 0.3),
            0.0,
            TERRAIN,
            0,
            mat(Pattern::Grass, [0.36, 0.52, 0.2]),
        );
    }
    b.cuboid(
        DVec3::new(50.0, 0.0, -0.27),
        DVec3::new(900.0, 800.0, 0.5),
        0.0,
        TERRAIN,
        0,
        mat(Pattern::Grass, [0.45, 0.55, 0.25]),
    );

    // Stuff bounds: a road slab reaching into the parking strips, parking strips reaching
    // into the road and sidewalks, hand-drawn sidewalk and garden outlines, far terrain.
    let mut srng = Rng::new(p.seed, Purpose::Bounds, &[1]);
    b.box_bound(
        DVec3::new(x0 - 0.5, -ROAD_HALF - 0.35, -0.45),
        DVec3::new(x1 + 0.5, ROAD_HALF + 0.35, 0.3),
        ROAD,
    );
    for side in [1.0f64, -1.0] {
        let (ya, yb) = (side * (ROAD_HALF - 0.2), side * (PARKING_OUTER + 0.2));
        b.box_bound(
            DVec3::new(x0 - 0.5, ya.min(yb), -0.45),
            DVec3::new(x1 + 0.5, ya.max(yb), 0.35),
            parking,
        );
        let poly = strip(
            &mut srng,
            x0,
            x1,
            side * (PARKING_OUTER - 0.12),
            side * (VERGE_OUTER + 0.12),
            0.15,
        );
        b.slab_bound(poly, -0.45, 0.45, TERRAIN);
        let poly = strip(
            &mut srng,
            x0,
            x1,
            side * (VERGE_OUTER - 0.1),
            side * (SIDEWALK_OUTER + 0.1),
            0.2,
        );
        b.slab_bound(poly, -0.45, 0.45, sidewalk);
        let poly = strip(
            &mut srng,
            x0,
            x1,
            side * (SIDEWALK_OUTER - 0.12),
            side * (GARDEN_OUTER + 0.5),
            0.3,
        );
        b.slab_bound(poly, -0.45, 0.45, TERRAIN);
    }
    let far = 450.0;
    b.box_bound(
        DVec3::new(x1 - 1.0, -far, -0.6),
        DVec3::new(far + 50.0, far, 0.3),
        TERRAIN,
    );
    b.box_bound(
        DVec3::new(-far, -far, -0.6),
        DVec3::new(x0 + 1.0, far, 0.3),
        TERRAIN,
    );
    b.box_bound(
        DVec3::new(x0, GARDEN_OUTER - 1.0, -0.6),
        DVec3::new(x1, far, 0.3),
        TERRAIN,
    );
    b.box_bound(
        DVec3::new(x0, -far, -0.6),
        DVec3::new(x1, -GARDEN_OUTER + 1.0, 0.3),
        TERRAIN,
    );

    for (k, side) in [1.0f64, -1.0].into_iter().enumerate() {
        b.rng = Rng::new(p.seed, Purpose::Layout, &[10 + k as u64]);
        frontage_side(&mut b, side, x0, x1);
        b.rng = Rng::new(p.seed, Purpose::Layout, &[20 + k as u64]);
        parking_side(&mut b, side, x0, x1);
    }

    Layout {
        parts: b.parts,
        materials: b.materials,
        bounds: b.bounds,
        x_range: (x0, x1),
    }
}

/// What stands at the front of a lot, along |y| = 9.3.
#[derive(Clone, Copy)]
enum Front {
    Hedge,
    Wall,
    Fence,
    WallGate,
    FenceGate,
    Open,
}

/// Lots along one side: buildings or open gardens with trees, a frontage, street trees and
/// boxes on the sidewalk.
fn frontage_side(b: &mut Builder, side: f64, x0: f64, x1: f64) {
    let fronts = [
        Front::Hedge,
        Front::Wall,
        Front::Fence,
        Front::WallGate,
        Front::Hedge,
        Front::Wall,
        Front::FenceGate,
        Front::Open,
    ];
    let mut k = b.rng.below(fronts.len() as u64) as usize;
    let mut x = x0 + 2.0;
    while x < x1 - 6.0 {
        let w = b.rng.range(9.0, 16.0).min(x1 - x);
        let building = b.rng.chance(0.8) && b.has(BUILDING);
        frontage(b, side, x, w, fronts[k % fronts.len()]);
        k += 1;
        // A fence between neighbouring gardens, from the frontage back to the facades.
        if b.rng.chance(0.5) && b.has(FENCE) {
            let (ya, yb) = (9.45, 12.3);
            let from = b.parts.len();
            let m = mat(Pattern::Slats, [0.5, 0.42, 0.32]);
            let centre = DVec3::new(x + 0.1, side * (ya + yb) / 2.0, 0.65);
            b.cuboid(centre, DVec3::new(0.05, yb - ya, 1.3), 0.0, FENCE, 0, m);
            b.bound(from, &[], 0.0, 0.03, 0.13, BoundShape::Box, FENCE, 0);
        }
        if building {
            let gap_a = b.rng.range(0.0, 1.2);
            let gap_b = b.rng.range(0.0, 1.2);
            build_building(b, side, x + gap_a, w - gap_a - gap_b);
            // A garden tree in front of some buildings (canopy reaching the facade).
            if b.rng.chance(0.35) {
                let tx = x + b.rng.range(2.0, w - 2.0);
                let ty = side * b.rng.range(10.6, 11.6);
                tree(b, DVec3::new(tx, ty, GARDEN_TOP), 1.0);
            }
        } else {
            let n = 1 + b.rng.below(3);
            for _ in 0..n {
                let tx = x + b.rng.range(1.5, (w - 1.5).max(1.6));
                let ty = side * b.rng.range(11.0, 20.0);
                tree(b, DVec3::new(tx, ty, GARDEN_TOP), 1.2);
            }
        }
        // Street trees in the sidewalk, boxes by the garden edge.
        if b.rng.chance(0.6) {
            let tx = x + b.rng.range(1.0, w - 1.0);
            tree(
                b,
                DVec3::new(tx, side * (PARKING_OUTER + VERGE_OUTER) / 2.0, KERB),
                0.8,
            );
        }
        if b.rng.chance(0.45) && b.has(BOX) {
            let bx = x + b.rng.range(1.0, w - 1.0);
            let size = DVec3::new(
                b.rng.range(0.5, 0.9),
                b.rng.range(0.4, 0.6),
                b.rng.range(0.9, 1.3),
            );
            let centre = DVec3::new(
                bx,
                side * (SIDEWALK_OUTER - 0.2 - size.y / 2.0),
                KERB + size.z / 2.0,
            );
            let inst = b.new_instance(BOX);
            let from = b.parts.len();
            let colour =
                [[0.55, 0.57, 0.5], [0.3, 0.35, 0.45], [0.7, 0.55, 0.3]][b.rng.below(3) as usize];
            b.cuboid(centre, size, 0.0, BOX, inst, mat(Pattern::Metal, colour));
            b.bound(from, &[], 0.0, 0.1, 0.08, BoundShape::Box, BOX, inst);
        }
        x += w;
    }
}

/// The frontage of one lot along |y| = 9.3 from `x` over `w` metres.
fn frontage(b: &mut Builder, side: f64, x: f64, w: f64, front: Front) {
    let y = side * 9.3;
    let (wall, fence, gate, hedge) = (b.has(WALL), b.has(FENCE), b.has(GATE), b.has(VEGETATION));
    let run = |b: &mut Builder, xa: f64, xb: f64, kind: u8| {
        if xb - xa < 0.3 {
            return;
        }
        let from = b.parts.len();
        let xm = (xa + xb) / 2.0;
        match kind {
            WALL => {
                let h = 1.25;
                let m = mat(Pattern::Brick, [0.6, 0.42, 0.36]);
                b.cuboid(
                    DVec3::new(xm, y, h / 2.0),
                    DVec3::new(xb - xa, 0.3, h),
                    0.0,
                    WALL,
                    0,
                    m,
                );
                b.bound(from, &[], 0.0, 0.03, 0.12, BoundShape::Box, WALL, 0);
            }
            FENCE => {
                let h = 1.3;
                let m = mat(Pattern::Slats, [0.55, 0.45, 0.33]);
                b.cuboid(
                    DVec3::new(xm, y, h / 2.0),
                    DVec3::new(xb - xa, 0.05, h),
                    0.0,
                    FENCE,
                    0,
                    m,
                );
                b.bound(from, &[], 0.0, 0.03, 0.13, BoundShape::Box, FENCE, 0);
            }
            VEGETATION => {
                let h = 1.2;
                let m = mat(Pattern::Foliage, [0.2, 0.38, 0.14]);
                b.cuboid(
                    DVec3::new(xm, y + side * 0.35, h / 2.0),
                    DVec3::new(xb - xa, 0.9, h),
                    0.0,
                    VEGETATION,
                    0,
                    m,
                );
                b.bound(from, &[], 0.0, 0.06, 0.12, BoundShape::Box, VEGETATION, 0);
            }
            _ => {
                let h = 1.5;
                let m = mat(Pattern::Slats, [0.25, 0.27, 0.3]);
                b.cuboid(
                    DVec3::new(xm, y, h / 2.0),
                    DVec3::new(xb - xa, 0.06, h),
                    0.0,
                    GATE,
                    0,
                    m,
                );
                b.bound(from, &[], 0.0, 0.03, 0.12, BoundShape::Box, GATE, 0);
            }
        }
    };
    let (a, z) = (x + 0.3, x + w - 0.3);
    match front {
        Front::Hedge if hedge => run(b, a, z, VEGETATION),
        Front::Wall if wall => run(b, a, z, WALL),
        Front::Fence if fence => run(b, a, z, FENCE),
        Front::WallGate | Front::FenceGate => {
            let kind = if matches!(front, Front::WallGate) {
                WALL
            } else {
                FENCE
            };
            let gm = a + (z - a) * b.rng.range(0.35, 0.65);
            let have = if kind == WALL { wall } else { fence };
            if have {
                run(b, a, gm - 1.25, kind);
                run(b, gm + 1.25, z, kind);
            }
            if gate {
                run(b, gm - 1.2, gm + 1.2, GATE);
            }
        }
        _ => {}
    }
}

/// A building on the lot from `x` over `w` metres: main block with pilasters, balconies or a
/// recessed ground floor, and a cornice; one instance, one coarse bounding box.
fn build_building(b: &mut Builder, side: f64, x: f64, w: f64) {
    let inst = b.new_instance(BUILDING);
    let r = &mut b.rng;
    let face = r.range(12.5, 15.0); // |y| of the facade plane
    let depth = r.range(9.0, 14.0);
    let floors = 2 + r.below(4) as usize;
    let floor = r.range(2.9, 3.3);
    let height = floors as f64 * floor + r.range(0.2, 0.8);
    let bay = r.range(2.4, 3.4);
    let colour = FACADE_COLOURS[r.below(FACADE_COLOURS.len() as u64) as usize];
    let style = r.below(3);
    let facade = mat(Pattern::Facade { x0: x, bay, floor }, colour);
    let plain = mat(
        Pattern::Concrete,
        [colour[0] * 0.85, colour[1] * 0.85, colour[2] * 0.85],
    );
    let from = b.parts.len();
    let xm = x + w / 2.0;
    // |y| -> world y on this side for a block spanning [ya, yb] in |y|.
    let yc = |ya: f64, yb: f64| side * (ya + yb) / 2.0;
    match style {
        // Recessed ground floor: the upper floors overhang the entrance zone.
        0 => {
            let g = floor;
            b.cuboid(
                DVec3::new(xm, yc(face + 1.8, face + depth), g / 2.0),
                DVec3::new(w, depth - 1.8, g),
                0.0,
                BUILDING,
                inst,
                facade,
            );
            b.cuboid(
                DVec3::new(xm, yc(face, face + depth), (g + height) / 2.0),
                DVec3::new(w, depth, height - g),
                0.0,
                BUILDING,
                inst,
                facade,
            );
        }
        // Pilasters: the wall between them is inset by 0.25 m.
        1 => {
            b.cuboid(
                DVec3::new(xm, yc(face + 0.25, face + depth), height / 2.0),
                DVec3::new(w, depth - 0.25, height),
                0.0,
                BUILDING,
                inst,
                facade,
            );
            let n = (w / bay).floor() as usize;
            for k in 0..=n {
                let px = (x + 0.25 + k as f64 * (w - 0.5) / n.max(1) as f64)
                    .clamp(x + 0.25, x + w - 0.25);
                b.cuboid(
                    DVec3::new(px, yc(face, face + 0.3), height / 2.0),
                    DVec3::new(0.5, 0.3, height),
                    0.0,
                    BUILDING,
                    inst,
                    plain,
                );
            }
        }
        // Balconies on the upper floors.
        _ => {
            b.cuboid(
                DVec3::new(xm, yc(face, face + depth), height / 2.0),
                DVec3::new(w, depth, height),
                0.0,
                BUILDING,
                inst,
                facade,
            );
            let n = (w / bay).floor() as usize;
            for f in 1..floors {
                for k in (0..n).step_by(2) {
                    let bx = x + (k as f64 + 1.0) * bay;
                    if bx + 1.2 > x + w {
                        continue;
                    }
                    let z = f as f64 * floor;
                    b.cuboid(
                        DVec3::new(bx, yc(face - 1.2, face), z),
                        DVec3::new(2.2, 1.2, 0.15),
                        0.0,
                        BUILDING,
                        inst,
                        plain,
                    );
                    b.cuboid(
                        DVec3::new(bx, yc(face - 1.2, face - 1.12), z + 0.5),
                        DVec3::new(2.2, 0.08, 0.9),
                        0.0,
                        BUILDING,
                        inst,
                        mat(Pattern::Metal, [0.25, 0.25, 0.27]),
                    );
                }
            }
        }
    }
    // Cornice.
    b.cuboid(
        DVec3::new(xm, yc(face - 0.3, face + 0.5), height + 0.2),
        DVec3::new(w + 0.2, 0.8, 0.4),
        0.0,
        BUILDING,
        inst,
        plain,
    );
    let inflate = b.brng.range(0.05, 0.15);
    b.bound(
        from,
        &[DVec3::new(xm, side * (face + 1.0), -0.2)],
        0.0,
        inflate,
        0.15,
        BoundShape::Box,
        BUILDING,
        inst,
    );
}

/// A tree: an upright trunk and an irregular canopy of 3-4 ellipsoids. Bounds: a box around
/// the trunk and an ellipsoid or box around the canopy.
fn tree(b: &mut Builder, base: DVec3, size: f64) {
    if !b.has(VEGETATION) {
        return;
    }
    let r = &mut b.rng;
    let trunk_h = r.range(2.0, 3.2) * size;
    let radius = r.range(1.4, 2.2) * size;
    let n = 3 + r.below(2);
    let mut blobs = Vec::new();
    for _ in 0..n {
        let off = DVec3::new(r.range(-0.6, 0.6), r.range(-0.6, 0.6), r.range(0.0, 0.9)) * radius;
        let s = DVec3::new(r.range(1.2, 1.8), r.range(1.2, 1.8), r.range(1.0, 1.5)) * radius;
        blobs.push((base + DVec3::Z * (trunk_h + radius * 0.6) + off, s));
    }
    let use_ellipsoid = r.chance(0.6);
    let from = b.parts.len();
    b.pillar(
        base - DVec3::Z * 0.1,
        0.14 * size.max(0.8),
        trunk_h + radius * 0.5,
        VEGETATION,
        mat(Pattern::Bark, [0.35, 0.26, 0.18]),
    );
    b.bound(from, &[], 0.0, 0.05, 0.12, BoundShape::Box, VEGETATION, 0);
    let from = b.parts.len();
    for (c, s) in blobs {
        let tf = DAffine3::from_mat3_translation(DMat3::from_diagonal(s), c);
        b.part(
            Shape::Ellipsoid,
            tf,
            VEGETATION,
            0,
            mat(Pattern::Foliage, [0.22, 0.4, 0.13]),
        );
    }
    let shape = if use_ellipsoid {
        BoundShape::Ellipsoid
    } else {
        BoundShape::Box
    };
    b.bound(from, &[], 0.0, 0.06, 0.1, shape, VEGETATION, 0);
}

/// Parked vehicles along one side's parking strip.
fn parking_side(b: &mut Builder, side: f64, x0: f64, x1: f64) {
    // A deck per ~45 m guarantees every vehicle class shows up regularly.
    let mut deck: Vec<u8> = Vec::new();
    let mut x = x0 + 3.0;
    while x < x1 - 8.0 {
        if deck.is_empty() {
            deck = vec![CAR, CAR, CAR, CARAVAN, 0, TRAILER, 0, CAR, 0, 0];
            for i in (1..deck.len()).rev() {
                let j = b.rng.below(i as u64 + 1) as usize;
                deck.swap(i, j);
            }
        }
        let kind = deck.pop().unwrap_or(0);
        let yaw = if b.rng.chance(0.5) {
            0.0
        } else {
            std::f64::consts::PI
        } + b.rng.normal() * 0.04;
        let y = side * b.rng.range(4.95, 5.25);
        let gap = b.rng.range(0.8, 2.5);
        let len = match kind {
            CAR if b.has(CAR) => {
                let l = b.rng.range(3.9, 4.7);
                vehicle_car(b, DVec3::new(x + l / 2.0, y, 0.0), l, yaw);
                l
            }
            CARAVAN if b.has(CARAVAN) => {
                let l = b.rng.range(5.5, 6.5);
                vehicle_box(
                    b,
                    CARAVAN,
                    DVec3::new(x + l / 2.0, y, 0.0),
                    l,
                    2.3,
                    2.6,
                    yaw,
                );
                l
            }
            TRAILER if b.has(TRAILER) => {
                let l = b.rng.range(2.8, 3.6);
                vehicle_box(
                    b,
                    TRAILER,
                    DVec3::new(x + l / 2.0, y, 0.0),
                    l,
                    1.7,
                    1.3,
                    yaw,
                );
                l
            }
            _ => b.rng.range(4.0, 9.0),
        };
        x += len + gap;
    }
}

fn car_colour(r: &mut Rng) -> [f64; 3] {
    CAR_COLOURS[r.below(CAR_COLOURS.len() as u64) as usize]
}

/// A car: body, cabin, four wheels.
fn vehicle_car(b: &mut Builder, pos: DVec3, len: f64, yaw: f64) {
    let inst = b.new_instance(CAR);
    let colour = car_colour(&mut b.rng);
    let width = b.rng.range(1.7, 1.9);
    let rot = DMat3::from_rotation_z(yaw);
    let at = |v: DVec3| pos + rot * v;
    let from = b.parts.len();
    let paint = mat(Pattern::Paint, colour);
    b.cuboid(
        at(DVec3::new(0.0, 0.0, 0.68)),
        DVec3::new(len, width, 0.66),
        yaw,
        CAR,
        inst,
        paint,
    );
    let cabin_len = len * b.rng.range(0.45, 0.55);
    b.cuboid(
        at(DVec3::new(-0.1 * len, 0.0, 1.22)),
        DVec3::new(cabin_len, width * 0.9, 0.46),
        yaw,
        CAR,
        inst,
        mat(Pattern::Glass, colour),
    );
    for (sx, sy) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
        let c = at(DVec3::new(
            sx * (len / 2.0 - 0.75),
            sy * (width / 2.0 - 0.08),
            0.33,
        ));
        b.wheel(c, 0.33, 0.22, yaw, CAR, inst);
    }
    let below = at(DVec3::new(0.0, 0.0, -0.12));
    b.bound(from, &[below], yaw, 0.08, 0.1, BoundShape::Box, CAR, inst);
}

/// A caravan or trailer: a box body on two wheels with a drawbar.
fn vehicle_box(
    b: &mut Builder,
    class: u8,
    pos: DVec3,
    len: f64,
    width: f64,
    height: f64,
    yaw: f64,
) {
    let inst = b.new_instance(class);
    let rot = DMat3::from_rotation_z(yaw);
    let at = |v: DVec3| pos + rot * v;
    let from = b.parts.len();
    let (colour, pattern) = if class == CARAVAN {
        ([0.9, 0.9, 0.86], Pattern::Paint)
    } else {
        ([0.45, 0.47, 0.5], Pattern::Metal)
    };
    let body_len = len - 0.9;
    let z0 = 0.45;
    b.cuboid(
        at(DVec3::new(0.45, 0.0, z0 + height / 2.0)),
        DVec3::new(body_len, width, height),
        yaw,
        class,
        inst,
        mat(pattern, colour),
    );
    b.cuboid(
        at(DVec3::new(-len / 2.0 + 0.5, 0.0, 0.45)),
        DVec3::new(1.0, 0.12, 0.1),
        yaw,
        class,
        inst,
        mat(Pattern::Metal, [0.2, 0.2, 0.2]),
    );
    for sy in [1.0, -1.0] {
        let c = at(DVec3::new(0.45, sy * (width / 2.0 - 0.12), 0.3));
        b.wheel(c, 0.3, 0.2, yaw, class, inst);
    }
    let below = at(DVec3::new(0.0, 0.0, -0.1));
    b.bound(from, &[below], yaw, 0.08, 0.1, BoundShape::Box, class, inst);
}
