//! The vocabulary of the street's parts: surface patterns and materials, the box transform,
//! cylinder cross-sections, and the points a bounding primitive must contain.

use crate::geometry::{DAffine3, DMat3, DVec3, Primitive, Shape};

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

/// A material of `pattern` and `color`.
pub(super) const fn mat(pattern: Pattern, color: [f64; 3]) -> Material {
    Material { pattern, color }
}

/// A local -> world transform: yaw about z, then scale `size`, centred at `centre`.
pub fn box_tf(centre: DVec3, size: DVec3, yaw: f64) -> DAffine3 {
    DAffine3::from_mat3_translation(
        DMat3::from_rotation_z(yaw) * DMat3::from_diagonal(size),
        centre,
    )
}

/// A regular `n`-gon of radius 0.5 (a cylinder cross-section for extruded primitives).
pub(super) fn ngon(n: usize) -> Vec<[f64; 2]> {
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
