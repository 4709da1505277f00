//! A 3D bounding primitive: a shape, a transform, a class and an instance, with its exact
//! ray intervals and point test.

use glam::{DAffine3, DMat3, DVec3};

use super::aabb::Aabb;
use super::error::GeometryError;
use super::ray::{Interval, LocalInterval, Ray};
use super::{cuboid, ellipsoid, extruded, mesh};

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
