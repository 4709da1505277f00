//! Rectified pinhole cameras (OpenCV/KITTI-360 axes: x right, y down, z forward): pixel rays,
//! projection, and the conversion from ray distance to camera-frame depth.

use glam::{DAffine3, DVec3};

use super::ray::Ray;

/// A pinhole camera. Pixel `(x, y)` spans `[x, x+1) x [y, y+1)`, so its centre is at image
/// point `(x + 0.5, y + 0.5)`.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// Rigid camera -> world (scene frame) transform.
    pub cam_to_world: DAffine3,
}

impl Camera {
    /// World -> camera (the inverse of the rigid pose: transpose rotation).
    pub fn world_to_cam(&self) -> DAffine3 {
        self.cam_to_world.inverse()
    }

    /// Camera centre in world coordinates.
    pub fn centre(&self) -> DVec3 {
        self.cam_to_world.translation
    }

    /// Unit direction, in the camera frame, through image point `(u, v)`.
    pub fn dir_cam(&self, u: f64, v: f64) -> DVec3 {
        DVec3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0).normalize()
    }

    /// The world ray from the camera centre through image point `(u, v)`.
    pub fn ray(&self, u: f64, v: f64) -> Ray {
        Ray {
            origin: self.centre(),
            dir: self
                .cam_to_world
                .transform_vector3(self.dir_cam(u, v))
                .normalize(),
        }
    }

    /// The ray through the centre of pixel `(x, y)`.
    pub fn pixel_ray(&self, x: u32, y: u32) -> Ray {
        self.ray(x as f64 + 0.5, y as f64 + 0.5)
    }

    /// Image point `(u, v)` and camera-frame depth `z` of a world point; `None` if `z <= 0`.
    pub fn project(&self, p: DVec3) -> Option<(f64, f64, f64)> {
        let q = self.world_to_cam().transform_point3(p);
        (q.z > 0.0).then(|| {
            (
                self.fx * q.x / q.z + self.cx,
                self.fy * q.y / q.z + self.cy,
                q.z,
            )
        })
    }

    /// Camera-frame `z` of the point at distance `t` along `ray` (KITTI depth maps hold `z`;
    /// rays use unit directions, so `z = t * dir_cam.z` for rays from the centre).
    pub fn z_depth(&self, ray: &Ray, t: f64) -> f64 {
        self.world_to_cam().transform_point3(ray.at(t)).z
    }
}
