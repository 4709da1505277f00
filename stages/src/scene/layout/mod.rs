//! The synthetic street: its true geometry (what the cameras see, composed of exact geometry
//! primitives with a class, instance and material) and its coarse 3D bounding primitives (what
//! a human annotator would draw: inflated, slightly misaligned, overlapping boxes, ellipsoids
//! and extruded polygons).
//!
//! Scene frame: x along the street (the rig drives towards +x), y to the left, z up; the road
//! surface is z = 0. Cross-section (|y|, both sides): road [0, 4], parking strip [4, 6.2],
//! planted verge [6.2, 7.2] (terrain, street trees), raised sidewalk [7.2, 9] (kerb 0.12 m),
//! gardens (terrain) from 9 with hedges, walls, fences and gates along |y| = 9.3, then
//! buildings with facades at |y| = 12.5..15 and gaps with trees; beyond |y| = 45 and past the
//! street's ends, open terrain.
//!
//! The builders, by what they place: `ground` (the cross-section's slabs and their stuff
//! bounds), `lots` (frontages, garden fences, buildings or gardens, street trees and boxes along
//! each side), `buildings`, `vegetation` (trees), `vehicles` (parked cars, caravans,
//! trailers) and `movers` (cars driving along and across the street, placed per frame), all
//! over the part-and-bound `builder` and the shared `parts` (materials, transforms) and
//! `section` (the strips' boundaries). Each side's lots and parking strip draw
//! from their own random stream, set here, so the order of the builders fixes every draw.

mod builder;
mod buildings;
mod ground;
mod lots;
mod movers;
mod parts;
mod section;
mod vegetation;
mod vehicles;

pub use movers::{Mover, MoverParams, MAX_MOVERS};
pub use parts::{box_tf, hull_points, Material, Pattern};
pub use section::{
    GARDEN_OUTER, GARDEN_TOP, KERB, PARKING_OUTER, RIG_Y, ROAD_HALF, SIDEWALK_OUTER, VERGE_OUTER,
};

use std::collections::BTreeMap;

use crate::geometry::Primitive;
use crate::labels::{PARKING, ROAD, SIDEWALK, TERRAIN};

use super::rng::{Purpose, Rng};
use builder::Builder;

/// The whole scene.
pub struct Layout {
    /// True geometry, rendered exactly.
    pub parts: Vec<Primitive>,
    /// `materials[i]` is the look of `parts[i]`.
    pub materials: Vec<Material>,
    /// Coarse bounding primitives (the `primitives` table).
    pub bounds: Vec<Primitive>,
    /// Moving objects (their boxes are the `dynamic_boxes` table).
    pub movers: Vec<Mover>,
    /// Street extent along x (the stuff strips span it).
    pub x_range: (f64, f64),
    /// Amount of texture detail (`SceneParams::texture`).
    pub texture: f64,
}

/// What the layout depends on.
#[derive(Debug, Clone)]
pub struct LayoutParams {
    pub seed: u64,
    /// Length of the driven street segment; the street is built 30 m before and 70 m after it.
    pub street_length: f64,
    /// Classes that may appear (label ids); road, terrain are always present.
    pub classes: Vec<u8>,
    /// Amount of texture detail, 0..=1 (the rendering's, not the layout's: no random draw
    /// depends on it).
    pub texture: f64,
    /// The moving objects and the frames they are placed for.
    pub movers: MoverParams,
}

/// Builds the scene. Deterministic in `p`: the ground's parts, its stuff bounds, then each
/// side's lots and parked vehicles, always in this order (the bounds' order is the
/// `primitives` table's row order, and every bound draws from one jitter stream); the moving
/// objects last, from streams of their own.
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

    ground::ground_parts(&mut b, x0, x1, parking, sidewalk);
    ground::stuff_bounds(&mut b, p.seed, x0, x1, parking, sidewalk);

    // Each side: its lots, then its parked vehicles, each from its own stream.
    for (k, side) in [1.0f64, -1.0].into_iter().enumerate() {
        b.rng = Rng::new(p.seed, Purpose::Layout, &[10 + k as u64]);
        lots::frontage_side(&mut b, side, x0, x1);
        b.rng = Rng::new(p.seed, Purpose::Layout, &[20 + k as u64]);
        vehicles::parking_side(&mut b, side, x0, x1);
    }
    let movers = movers::movers(&mut b, p.seed, &p.movers);

    Layout {
        parts: b.parts,
        materials: b.materials,
        bounds: b.bounds,
        movers,
        x_range: (x0, x1),
        texture: p.texture,
    }
}
