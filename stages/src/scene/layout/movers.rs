//! Moving objects: cars driving along the street and across it, and a cyclist (a bicycle and
//! its rider, two objects as KITTI-360 annotates them). Each is built once in its own
//! frame (x forward, y left, z up, origin on the ground under its centre) with its parts and the
//! annotator's box, and placed at every frame of its span by a pose: a straight drive at
//! constant speed, as KITTI-360 annotates moving objects (one box per object and frame).

use std::ops::RangeInclusive;

use crate::geometry::{DAffine3, DMat3, DVec3, Primitive, Shape};
use crate::labels::{BICYCLE, CAR, INSTANCE_FACTOR, RIDER};
use crate::scene::rng::{Purpose, Rng};

use super::builder::{BoundShape, Builder};
use super::parts::{box_tf, mat, Material, Pattern};
use super::section::RIG_Y;

/// The most moving objects the street has: a car ahead in the rig's lane, an oncoming car, a
/// car crossing the road, a cyclist the rig overtakes (its bicycle and rider are two objects).
pub const MAX_MOVERS: u32 = 4;

/// Which frames the movers are placed for: the rendered window and the rig's speed.
#[derive(Debug, Clone, PartialEq)]
pub struct MoverParams {
    /// How many (0..=[`MAX_MOVERS`]), in the order above.
    pub count: u32,
    pub first_frame: u32,
    pub frames: u32,
    /// The rig's x advance per frame (frame k is at x = k * spacing).
    pub frame_spacing: f64,
}

/// One moving object.
pub struct Mover {
    pub label: u8,
    pub instance: u32,
    /// True geometry in the mover's own frame.
    pub parts: Vec<Primitive>,
    /// `materials[i]` is the look of `parts[i]`.
    pub materials: Vec<Material>,
    /// The annotator's box in the mover's own frame.
    pub bound: Primitive,
    /// Ground position at frame `*frames.start()`.
    start: DVec3,
    /// Heading (about z) and distance driven per frame along it.
    yaw: f64,
    step: f64,
    /// The frames it is in the scene.
    pub frames: RangeInclusive<u32>,
}

impl Mover {
    /// Its value in the instance maps (and `object` of `dynamic_boxes`).
    pub fn object(&self) -> u32 {
        self.label as u32 * INSTANCE_FACTOR + self.instance
    }

    /// Own frame -> scene frame at `frame` (`None` outside its span).
    pub fn pose(&self, frame: u32) -> Option<DAffine3> {
        if !self.frames.contains(&frame) {
            return None;
        }
        let rot = DMat3::from_rotation_z(self.yaw);
        let driven = self.step * (frame - self.frames.start()) as f64;
        Some(DAffine3::from_mat3_translation(
            rot,
            self.start + rot * DVec3::new(driven, 0.0, 0.0),
        ))
    }

    /// Its parts placed at `frame` (none outside its span).
    pub fn parts_at(&self, frame: u32) -> Vec<Primitive> {
        self.pose(frame)
            .map(|tf| self.parts.iter().map(|p| placed(p, &tf)).collect())
            .unwrap_or_default()
    }

    /// Its box placed at `frame`.
    pub fn bound_at(&self, frame: u32) -> Option<Primitive> {
        self.pose(frame).map(|tf| placed(&self.bound, &tf))
    }
}

/// Where a mover is at its first frame, its heading and its distance per frame.
struct Path {
    start: DVec3,
    yaw: f64,
    step: f64,
    frames: RangeInclusive<u32>,
}

/// A mover of class `label` along `path`: `build` adds its parts and box in its own frame and
/// returns its instance number.
fn built(
    b: &mut Builder,
    label: u8,
    path: &Path,
    build: impl FnOnce(&mut Builder) -> u32,
) -> Mover {
    let (from_part, from_bound) = (b.parts.len(), b.bounds.len());
    let instance = build(b);
    let bound = b
        .bounds
        .drain(from_bound..)
        .next()
        .expect("a mover has a box");
    Mover {
        label,
        instance,
        parts: b.parts.drain(from_part..).collect(),
        materials: b.materials.drain(from_part..).collect(),
        bound,
        start: path.start,
        yaw: path.yaw,
        step: path.step,
        frames: path.frames.clone(),
    }
}

/// A bicycle in its own frame: two wheels, a frame, a seat post and handlebars.
fn bicycle(b: &mut Builder) -> u32 {
    let inst = b.new_instance(BICYCLE);
    let from = b.parts.len();
    let paint = mat(Pattern::Paint, [0.1, 0.35, 0.6]);
    for x in [-0.52, 0.52] {
        b.wheel(DVec3::new(x, 0.0, 0.34), 0.34, 0.05, 0.0, BICYCLE, inst);
    }
    let bars = [
        (DVec3::new(0.0, 0.0, 0.62), DVec3::new(0.95, 0.05, 0.06)),
        (DVec3::new(-0.2, 0.0, 0.75), DVec3::new(0.04, 0.04, 0.35)),
        (DVec3::new(0.45, 0.0, 0.8), DVec3::new(0.05, 0.05, 0.42)),
        (DVec3::new(0.45, 0.0, 1.02), DVec3::new(0.05, 0.58, 0.04)),
    ];
    for (centre, size) in bars {
        b.cuboid(centre, size, 0.0, BICYCLE, inst, paint);
    }
    b.bound(from, &[], 0.0, 0.04, 0.06, BoundShape::Box, BICYCLE, inst);
    inst
}

/// Its rider in the bicycle's frame: legs from the saddle down, a torso, arms to the bars, a
/// head.
fn rider(b: &mut Builder) -> u32 {
    let inst = b.new_instance(RIDER);
    let from = b.parts.len();
    let shirt = [[0.75, 0.2, 0.15], [0.2, 0.5, 0.25], [0.9, 0.8, 0.3]][b.rng.below(3) as usize];
    let (cloth, trousers) = (
        mat(Pattern::Concrete, shirt),
        mat(Pattern::Concrete, [0.12, 0.12, 0.2]),
    );
    for y in [-0.11, 0.11] {
        b.cuboid(
            DVec3::new(-0.08, y, 0.62),
            DVec3::new(0.14, 0.12, 0.5),
            0.0,
            RIDER,
            inst,
            trousers,
        );
    }
    b.cuboid(
        DVec3::new(-0.05, 0.0, 1.2),
        DVec3::new(0.32, 0.38, 0.58),
        0.0,
        RIDER,
        inst,
        cloth,
    );
    for y in [-0.22, 0.22] {
        b.cuboid(
            DVec3::new(0.22, y, 1.18),
            DVec3::new(0.45, 0.08, 0.08),
            0.0,
            RIDER,
            inst,
            cloth,
        );
    }
    let head = box_tf(DVec3::new(0.0, 0.0, 1.63), DVec3::new(0.22, 0.2, 0.26), 0.0);
    b.part(
        Shape::Ellipsoid,
        head,
        RIDER,
        inst,
        mat(Pattern::Paint, [0.8, 0.62, 0.5]),
    );
    b.bound(from, &[], 0.0, 0.04, 0.06, BoundShape::Box, RIDER, inst);
    inst
}

/// `p` moved by `tf` (a rigid motion keeps every shape valid).
fn placed(p: &Primitive, tf: &DAffine3) -> Primitive {
    Primitive::new(p.shape.clone(), *tf * p.to_world, p.label, p.instance)
        .expect("a rigid motion of a valid primitive is valid")
}

/// The movers of `m`, built after the static street (their instance numbers follow its), each
/// from random streams of its own so the static street is the same with or without them.
pub(super) fn movers(b: &mut Builder, seed: u64, m: &MoverParams) -> Vec<Mover> {
    let n = m.frames.max(1);
    let last = m.first_frame + n - 1;
    let rig_x = |f: f64| f * m.frame_spacing;
    let at = |share: f64| m.first_frame as f64 + share * (n - 1) as f64;
    let mut out = Vec::new();
    for k in 0..m.count.min(MAX_MOVERS) {
        b.rng = Rng::new(seed, Purpose::Layout, &[30 + k as u64]);
        b.brng = Rng::new(seed, Purpose::Bounds, &[30 + k as u64]);
        let (start, yaw, step, frames) = match k {
            // Ahead in the rig's lane, a little faster than the rig.
            0 => {
                let x = rig_x(m.first_frame as f64) + b.rng.range(8.0, 11.0);
                let step = m.frame_spacing * b.rng.range(1.08, 1.2);
                (DVec3::new(x, RIG_Y, 0.0), 0.0, step, m.first_frame..=last)
            }
            // Oncoming in the other lane, passing the rig two thirds into the window.
            1 => {
                let step = b.rng.range(0.9, 1.2);
                let pass = at(2.0 / 3.0);
                let x = rig_x(pass) + step * (pass - m.first_frame as f64);
                let y = -RIG_Y + b.rng.range(-0.2, 0.2);
                let yaw = std::f64::consts::PI;
                (DVec3::new(x, y, 0.0), yaw, step, m.first_frame..=last)
            }
            // Crossing the road well ahead of the rig, on the road only (|y| <= 3 m).
            2 => {
                let step = b.rng.range(0.25, 0.35);
                let mid = at(1.0 / 3.0).round();
                let x = rig_x(mid) + b.rng.range(12.0, 15.0);
                let half = (3.0 / step).floor() as u32;
                let first = (mid as u32).saturating_sub(half).max(m.first_frame);
                let end = (mid as u32 + half).min(last);
                let y = -step * (mid - first as f64);
                let yaw = std::f64::consts::FRAC_PI_2;
                (DVec3::new(x, y, 0.0), yaw, step, first..=end)
            }
            // A cyclist near the kerb of the rig's side, a little ahead and slower than the
            // rig, which overtakes it 15 to 25 frames into the window.
            _ => {
                let step = m.frame_spacing * b.rng.range(0.45, 0.6);
                let x = rig_x(m.first_frame as f64) + b.rng.range(6.0, 8.0);
                let y = RIG_Y - b.rng.range(1.3, 1.5);
                (DVec3::new(x, y, 0.0), 0.0, step, m.first_frame..=last)
            }
        };
        let path = Path {
            start,
            yaw,
            step,
            frames,
        };
        if k < 3 {
            out.push(built(b, CAR, &path, |b| {
                let len = b.rng.range(3.9, 4.7);
                super::vehicles::vehicle_car(b, DVec3::ZERO, len, 0.0)
            }));
        } else {
            out.push(built(b, BICYCLE, &path, bicycle));
            out.push(built(b, RIDER, &path, rider));
        }
    }
    out
}
