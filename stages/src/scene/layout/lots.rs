//! The lots along each side: a frontage (hedge, wall, fence, gates) along |y| = 9.3, fences
//! between gardens, a building or an open garden with trees, street trees and boxes.

use crate::geometry::DVec3;
use crate::labels::{BOX, BUILDING, FENCE, GATE, VEGETATION, WALL};

use super::builder::{BoundShape, Builder};
use super::buildings::build_building;
use super::parts::{mat, Pattern};
use super::section::{GARDEN_TOP, KERB, PARKING_OUTER, SIDEWALK_OUTER, VERGE_OUTER};
use super::vegetation::tree;

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
pub(super) fn frontage_side(b: &mut Builder, side: f64, x0: f64, x1: f64) {
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
