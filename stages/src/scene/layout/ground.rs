//! The ground: the cross-section's slabs (road, parking strips, verges, raised sidewalks,
//! gardens, far terrain) and their stuff bounds.

use crate::geometry::DVec3;
use crate::labels::{PARKING, ROAD, SIDEWALK, TERRAIN};
use crate::scene::rng::{Purpose, Rng};

use super::builder::Builder;
use super::parts::{mat, Pattern};
use super::section::{
    GARDEN_OUTER, GARDEN_TOP, KERB, PARKING_OUTER, ROAD_HALF, SIDEWALK_OUTER, VERGE_OUTER,
};

/// The true ground along the street from `x0` to `x1`: the road, parking strips (`parking`:
/// their class, road where parking is not a class), planted verges, raised sidewalks
/// (`sidewalk`: their class, terrain where sidewalk is not one), gardens, and far terrain
/// below all.
pub(super) fn ground_parts(b: &mut Builder, x0: f64, x1: f64, parking: u8, sidewalk: u8) {
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
}

/// Stuff bounds of the ground: a road slab reaching into the parking strips, parking strips
/// reaching into the road and sidewalks, hand-drawn sidewalk and garden outlines (from their
/// own stream, so they do not shift the parts' draws), and far terrain.
pub(super) fn stuff_bounds(
    b: &mut Builder,
    seed: u64,
    x0: f64,
    x1: f64,
    parking: u8,
    sidewalk: u8,
) {
    let mut srng = Rng::new(seed, Purpose::Bounds, &[1]);
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
