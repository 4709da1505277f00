//! Geometry of the Panoptic NeRF sampling plan: rays, pinhole cameras, the four kinds of 3D
//! bounding primitive (cuboid, ellipsoid, extruded polygon, closed triangle mesh), exact
//! ray-primitive intervals, point-in-primitive tests, a BVH over primitive bounds, the fixed
//! semantic and instance fields, and the Arrow codecs of the `cameras` and `primitives` tables.
//!
//! Everything here is `f64`: KITTI-360 coordinates are thousands of metres and poses must be
//! recentred before anything is converted to the `f32` the network sees.
//!
//! How a primitive is intersected: the world ray `o + t d` is mapped into the primitive's local
//! frame with the cached inverse transform, giving the (unnormalised) local ray `o' + t d'`. The
//! map is affine, so a local parameter `t` *is* the world distance `t`: no rescaling is needed.
//! Each shape file (`cuboid.rs`, `ellipsoid.rs`, `extruded.rs`, `mesh.rs`) answers one
//! local-space question, "which intervals of the whole line `o' + t d'` (t in R) lie inside?",
//! and [`Primitive::intersect`] keeps those with `t_out > 0` and turns the local entry normal into
//! a world one (inverse transpose, oriented against the ray).

pub mod aabb;
pub mod bvh;
pub mod camera;
pub mod cuboid;
pub mod demo;
pub mod ellipsoid;
pub mod extruded;
pub mod fields;
pub mod io;
pub mod mesh;

use std::fmt;

pub use aabb::Aabb;
pub use bvh::Bvh;
pub use camera::Camera;
pub use fields::{fixed_instance, fixed_semantic, scene_things};
pub use glam::{DAffine3, DMat3, DVec3};
pub use io::{
    cameras_from_table, cameras_to_table, primitives_from_table, primitives_to_table, CameraRow,
};

/// A ray `origin + t * dir`, `dir` of unit length, so `t` is a distance in metres.
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    pub origin: DVec3,
    /// Unit length.
    pub dir: DVec3,
}

impl Ray {
    /// A ray from `origin` towards `dir` (normalised here).
    pub fn new(origin: DVec3, dir: DVec3) -> Self {
        Self {
            origin,
            dir: dir.normalize(),
        }
    }

    /// The point at distance `t`.
    pub fn at(&self, t: f64) -> DVec3 {
        self.origin + t * self.dir
    }
}

/// One stretch of a ray inside one primitive.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Interval {
    pub t_in: f64,
    pub t_out: f64,
    /// World unit outward normal at entry (any unit vector if `t_in <= 0`).
    pub normal_in: DVec3,
}

/// An [`Interval`] of primitive `prim` (its index in the primitive slice / table row id).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub t_in: f64,
    pub t_out: f64,
    pub prim: u32,
    pub normal_in: DVec3,
}

/// The shape of a primitive in its local frame (conventions of `data_schema/primitives.json`).
#[derive(Clone, Debug, PartialEq)]
pub enum Shape {
    /// The unit cube `[-0.5, 0.5]^3`.
    Cuboid,
    /// The unit-diameter sphere (radius 0.5) at the origin.
    Ellipsoid,
    /// A simple polygon in local xy (either orientation, convex or not) extruded over
    /// `z in [-0.5, 0.5]`.
    Extruded { polygon: Vec<[f64; 2]> },
    /// A closed, consistently oriented triangle mesh (KITTI-360 XML style). Faces may wind
    /// either way as long as all agree; inward-wound meshes are flipped on construction.
    Mesh {
        vertices: Vec<DVec3>,
        faces: Vec<[u32; 3]>,
    },
}

impl Shape {
    /// The `kind` string of the primitives table.
    pub fn kind(&self) -> &'static str {
        match self {
            Shape::Cuboid => "cuboid",
            Shape::Ellipsoid => "ellipsoid",
            Shape::Extruded { .. } => "extruded",
            Shape::Mesh { .. } => "mesh",
        }
    }
}

/// Why a primitive is rejected. Messages name the problem and the offending element.
#[derive(Clone, Debug, PartialEq)]
pub enum GeometryError {
    /// A NaN or infinite number in the named part.
    NonFinite(&'static str),
    /// The transform collapses a local axis (`axis` is 'x', 'y' or 'z'), or its columns are
    /// linearly dependent (`axis` is '?').
    DegenerateTransform {
        axis: char,
    },
    PolygonTooFew {
        n: usize,
    },
    PolygonZeroArea,
    /// Two non-adjacent polygon edges (numbered by their first vertex) cross or touch.
    PolygonSelfIntersecting {
        a: usize,
        b: usize,
    },
    MeshNoFaces,
    MeshIndexOutOfRange {
        face: usize,
        index: u32,
        vertices: usize,
    },
    /// A face repeats a vertex or has zero area.
    MeshDegenerateFace {
        face: usize,
    },
    /// An edge used by a number of faces other than two.
    MeshOpen {
        a: u32,
        b: u32,
        faces: u32,
    },
    /// Two faces traverse an edge in the same direction (a flipped face).
    MeshFlippedFace {
        a: u32,
        b: u32,
    },
    MeshZeroVolume,
}

impl fmt::Display for GeometryError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        use GeometryError::*;
        match self {
            NonFinite(what) => write!(f, "non-finite value (NaN or infinity) in {what}"),
            DegenerateTransform { axis: '?' } => write!(
                f,
                "degenerate transform (local axes are linearly dependent: zero volume)"
            ),
            DegenerateTransform { axis } => {
                write!(f, "degenerate transform (zero extent along local {axis})")
            }
            PolygonTooFew { n } => write!(f, "polygon has fewer than 3 vertices (it has {n})"),
            PolygonZeroArea => write!(f, "polygon has zero area"),
            PolygonSelfIntersecting { a, b } => write!(
                f,
                "polygon is self-intersecting: edge {a} crosses edge {b} (edges numbered by their first vertex)"
            ),
            MeshNoFaces => write!(f, "mesh has no faces"),
            MeshIndexOutOfRange { face, index, vertices } => write!(
                f,
                "mesh face {face} refers to vertex {index}, but there are only {vertices} vertices"
            ),
            MeshDegenerateFace { face } => {
                write!(f, "mesh face {face} is degenerate (repeated vertex or zero area)")
            }
            MeshOpen { a, b, faces } => write!(
                f,
                "mesh is not closed: edge ({a},{b}) used by {faces} face{} (every edge needs exactly 2)",
                if *faces == 1 { "" } else { "s" }
            ),
            MeshFlippedFace { a, b } => write!(
                f,
                "mesh has a flipped face: edge ({a},{b}) is traversed in the same direction by both its faces"
            ),
            MeshZeroVolume => write!(f, "mesh encloses zero volume"),
        }
    }
}

impl std::error::Error for GeometryError {}

/// Local-frame data prepared once per primitive.
#[derive(Clone, Debug)]
enum Local {
    Cuboid,
    Ellipsoid,
    Extruded(extruded::Polygon),
    Mesh(mesh::Mesh),
}

/// One 3D bounding primitive: a shape, its local -> world transform, class and instance.
#[derive(Clone, Debug)]
pub struct Primitive {
    pub shape: Shape,
    pub to_world: DAffine3,
    /// KITTI-360 label id.
    pub label: u8,
    /// 1..999 for things, 0 for stuff.
    pub instance: u32,
    to_local: DAffine3,
    /// Inverse transpose of the linear part: local normal -> world normal.
    normal_world: DMat3,
    local: Local,
    aabb: Aabb,
}

/// A local-frame interval of the whole line `o' + t d'`, `t` in R; `n_in` is the local entry
/// normal in any orientation and length.
#[derive(Clone, Copy, Debug)]
pub(crate) struct LocalInterval {
    pub t_in: f64,
    pub t_out: f64,
    pub n_in: DVec3,
}

fn check_transform(m: &DAffine3) -> Result<(), GeometryError> {
    if !m.is_finite() {
        return Err(GeometryError::NonFinite("transform"));
    }
    let cols = [m.matrix3.x_axis, m.matrix3.y_axis, m.matrix3.z_axis];
    let norms = cols.map(|c| c.length());
    let scale = norms
        .iter()
        .cloned()
        .fold(0.0, f64::max)
        .max(f64::MIN_POSITIVE);
    for (axis, n) in ['x', 'y', 'z'].into_iter().zip(norms) {
        if n <= 1e-12 * scale || n < 1e-12 {
            return Err(GeometryError::DegenerateTransform { axis });
        }
    }
    if m.matrix3.determinant().abs() <= 1e-12 * norms[0] * norms[1] * norms[2] {
        return Err(GeometryError::DegenerateTransform { axis: '?' });
    }
    Ok(())
}

impl Primitive {
    /// Validates the shape and transform and caches the inverse transform and world bounds.
    pub fn new(
        shape: Shape,
        to_world: DAffine3,
        label: u8,
        instance: u32,
    ) -> Result<Self, GeometryError> {
        check_transform(&to_world)?;
        let (local, local_box) = match &shape {
            Shape::Cuboid => (
                Local::Cuboid,
                Aabb::new(DVec3::splat(-0.5), DVec3::splat(0.5)),
            ),
            Shape::Ellipsoid => (
                Local::Ellipsoid,
                Aabb::new(DVec3::splat(-0.5), DVec3::splat(0.5)),
            ),
            Shape::Extruded { polygon } => {
                let p = extruded::Polygon::new(polygon)?;
                let b = p.bounds();
                (Local::Extruded(p), b)
            }
            Shape::Mesh { vertices, faces } => {
                let m = mesh::Mesh::new(vertices, faces)?;
                let b = m.bounds();
                (Local::Mesh(m), b)
            }
        };
        let to_local = to_world.inverse();
        let normal_world = to_local.matrix3.transpose();
        let aabb = match &shape {
            // The exact bounds of a transformed sphere: centre +- the row norms.
            Shape::Ellipsoid => {
                let m = to_world.matrix3.transpose(); // rows of the linear part as columns
                let half =
                    0.5 * DVec3::new(m.x_axis.length(), m.y_axis.length(), m.z_axis.length());
                Aabb::new(to_world.translation - half, to_world.translation + half)
            }
            _ => local_box.transformed(&to_world),
        };
        Ok(Self {
            shape,
            to_world,
            label,
            instance,
            to_local,
            normal_world,
            local,
            aabb,
        })
    }

    /// World bounds (exact for cuboids, ellipsoids and meshes' vertex hulls).
    pub fn aabb(&self) -> Aabb {
        self.aabb
    }

    /// Local -> world is `to_world`; this is its cached inverse.
    pub fn to_local(&self) -> &DAffine3 {
        &self.to_local
    }

    /// Appends every interval where the ray is inside this primitive and `t_out > 0`, sorted
    /// by `t_in` (non-overlapping). `t_in` is negative when the origin is inside. Allocates
    /// nothing beyond `out` (extruded polygons and meshes use a thread-local scratch buffer).
    pub fn intersect(&self, ray: &Ray, out: &mut Vec<Interval>) {
        let o = self.to_local.transform_point3(ray.origin);
        let d = self.to_local.transform_vector3(ray.dir);
        let mut emit = |li: LocalInterval| {
            if li.t_out > 0.0 && li.t_in < li.t_out {
                let mut n = (self.normal_world * li.n_in).normalize_or(-ray.dir);
                if n.dot(ray.dir) > 0.0 {
                    n = -n;
                }
                out.push(Interval {
                    t_in: li.t_in,
                    t_out: li.t_out,
                    normal_in: n,
                });
            }
        };
        match &self.local {
            Local::Cuboid => {
                if let Some(li) = cuboid::intersect(o, d) {
                    emit(li)
                }
            }
            Local::Ellipsoid => {
                if let Some(li) = ellipsoid::intersect(o, d) {
                    emit(li)
                }
            }
            Local::Extruded(p) => p.intersect(o, d, &mut emit),
            Local::Mesh(m) => m.intersect(o, d, &mut emit),
        }
    }

    /// Whether `p` is inside or on the boundary (closed set; for meshes, generalised winding
    /// number >= 1/2, so points on a mesh face may go either way).
    pub fn contains(&self, p: DVec3) -> bool {
        if !self.aabb.contains(p) {
            return false;
        }
        let q = self.to_local.transform_point3(p);
        match &self.local {
            Local::Cuboid => cuboid::contains(q),
            Local::Ellipsoid => ellipsoid::contains(q),
            Local::Extruded(poly) => poly.contains(q),
            Local::Mesh(m) => m.contains(q),
        }
    }
}

#[cfg(test)]
mod tests;
