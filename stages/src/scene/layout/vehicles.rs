//! Parked vehicles: cars, caravans and trailers along the parking strips.

use crate::geometry::{DMat3, DVec3};
use crate::labels::{CAR, CARAVAN, TRAILER};
use crate::scene::rng::Rng;

use super::builder::{BoundShape, Builder};
use super::parts::{mat, Pattern};

const CAR_COLOURS: &[[f64; 3]] = &[
    [0.7, 0.1, 0.1],
    [0.12, 0.2, 0.55],
    [0.85, 0.85, 0.86],
    [0.15, 0.15, 0.16],
    [0.45, 0.47, 0.5],
    [0.2, 0.45, 0.3],
    [0.9, 0.75, 0.2],
];

/// Parked vehicles along one side's parking strip.
pub(super) fn parking_side(b: &mut Builder, side: f64, x0: f64, x1: f64) {
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

/// A car: body, cabin, four wheels; returns its instance number.
pub(super) fn vehicle_car(b: &mut Builder, pos: DVec3, len: f64, yaw: f64) -> u32 {
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
    inst
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
