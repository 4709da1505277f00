//! The part-and-bound builder the layout's builders share: true-geometry parts with their
//! materials, and the coarse bounding primitives an annotator would draw around them.

use std::collections::BTreeMap;

use crate::geometry::{DAffine3, DMat3, DVec3, Primitive, Shape};
use crate::scene::rng::Rng;

use super::parts::{box_tf, hull_points, mat, ngon, Material, Pattern};

/// Which convex shape a bounding primitive takes.
#[derive(Clone, Copy, PartialEq)]
pub(super) enum BoundShape {
    Box,
    Ellipsoid,
}

/// The scene under construction (what becomes a [`super::Layout`]) with its random streams.
pub(super) struct Builder {
    pub(super) parts: Vec<Primitive>,
    /// `materials[i]` is the look of `parts[i]`.
    pub(super) materials: Vec<Material>,
    pub(super) bounds: Vec<Primitive>,
    /// The last instance number given out, per class.
    pub(super) instances: BTreeMap<u8, u32>,
    /// Classes that may appear (label ids).
    pub(super) classes: Vec<u8>,
    /// Layout choices; `build` gives each side's lots and parking strip their own stream.
    pub(super) rng: Rng,
    /// The annotation jitter of every bound, one stream for the whole street.
    pub(super) brng: Rng,
}

impl Builder {
    pub(super) fn has(&self, class: u8) -> bool {
        self.classes.contains(&class)
    }

    pub(super) fn new_instance(&mut self, class: u8) -> u32 {
        let n = self.instances.entry(class).or_insert(0);
        *n += 1;
        *n
    }

    pub(super) fn part(
        &mut self,
        shape: Shape,
        tf: DAffine3,
        label: u8,
        instance: u32,
        m: Material,
    ) {
        let p = Primitive::new(shape, tf, label, instance)
            .unwrap_or_else(|e| panic!("synthetic part of class {label} is invalid: {e}"));
        self.parts.push(p);
        self.materials.push(m);
    }

    pub(super) fn cuboid(
        &mut self,
        centre: DVec3,
        size: DVec3,
        yaw: f64,
        label: u8,
        inst: u32,
        m: Material,
    ) {
        self.part(Shape::Cuboid, box_tf(centre, size, yaw), label, inst, m);
    }

    /// A cylinder with its axis along the local y of `yaw` (wheels).
    pub(super) fn wheel(
        &mut self,
        centre: DVec3,
        radius: f64,
        width: f64,
        yaw: f64,
        label: u8,
        inst: u32,
    ) {
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
    pub(super) fn pillar(&mut self, base: DVec3, radius: f64, height: f64, label: u8, m: Material) {
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
    pub(super) fn bound(
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
    pub(super) fn slab_bound(&mut self, polygon: Vec<[f64; 2]>, z0: f64, z1: f64, label: u8) {
        let tf = DAffine3::from_mat3_translation(
            DMat3::from_diagonal(DVec3::new(1.0, 1.0, z1 - z0)),
            DVec3::new(0.0, 0.0, (z0 + z1) / 2.0),
        );
        let p = Primitive::new(Shape::Extruded { polygon }, tf, label, 0)
            .expect("stuff polygon is valid");
        self.bounds.push(p);
    }

    pub(super) fn box_bound(&mut self, lo: DVec3, hi: DVec3, label: u8) {
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
