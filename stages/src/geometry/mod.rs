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
pub mod changes;
pub mod cuboid;
pub mod demo;
pub mod ellipsoid;
pub mod error;
pub mod extruded;
pub mod fields;
pub mod io;
pub mod lens;
pub mod mesh;
pub mod primitive;
pub mod ray;

pub use aabb::Aabb;
pub use bvh::Bvh;
pub use camera::Camera;
pub use changes::PrimitiveChanges;
pub use error::GeometryError;
pub use fields::{fixed_instance, fixed_semantic, scene_things};
pub use glam::{DAffine3, DMat3, DVec3};
pub use io::{
    cameras_from_table, cameras_to_table, dynamic_boxes_from_table, dynamic_boxes_to_table,
    primitives_from_table, primitives_to_table, CameraRow, DynamicBox,
};
pub use lens::{Lens, Mei, FISHEYE_HALF_ANGLE_DEG};
pub use primitive::{Primitive, Shape};
pub use ray::{Hit, Interval, Ray};

#[cfg(test)]
mod tests;
