//! Buildings: one instance per lot, in one of three facade styles.

use crate::geometry::DVec3;
use crate::labels::BUILDING;

use super::builder::{BoundShape, Builder};
use super::parts::{mat, Pattern};

const FACADE_COLOURS: &[[f64; 3]] = &[
    [0.78, 0.72, 0.62],
    [0.93, 0.92, 0.88],
    [0.62, 0.6, 0.58],
    [0.62, 0.36, 0.3],
    [0.82, 0.66, 0.42],
    [0.72, 0.76, 0.78],
];

/// A building on the lot from `x` over `w` metres: main block with pilasters, balconies or a
/// recessed ground floor, and a cornice; one instance, one coarse bounding box.
pub(super) fn build_building(b: &mut Builder, side: f64, x: f64, w: f64) {
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
