//! Trees: trunk and canopy parts with their bounds.

use crate::geometry::{DAffine3, DMat3, DVec3, Shape};
use crate::labels::VEGETATION;

use super::builder::{BoundShape, Builder};
use super::parts::{mat, Pattern};

/// A tree: an upright trunk and an irregular canopy of 3-4 ellipsoids. Bounds: a box around
/// the trunk and an ellipsoid or box around the canopy.
pub(super) fn tree(b: &mut Builder, base: DVec3, size: f64) {
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
