//! Cameras (OpenCV/KITTI-360 axes: x right, y down, z forward), rectified pinhole or fisheye
//! ([`Lens`]): pixel rays, projection, the pixels a lens images, and the conversion from ray
//! distance to camera-frame depth.

use glam::{DAffine3, DVec2, DVec3};

use super::lens::Lens;
use super::ray::Ray;

/// A camera. Pixel `(x, y)` spans `[x, x+1) x [y, y+1)`, so its centre is at image point
/// `(x + 0.5, y + 0.5)`. The image point of normalised plane point `p` (see [`Lens`]) is
/// `(fx p.x + cx, fy p.y + cy)`: for MEI's model, fx, fy, cx, cy are gamma1, gamma2, u0, v0.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub lens: Lens,
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

    /// Whether `other` maps pixels to the same camera-frame rays (poses aside).
    pub fn same_pixels(&self, other: &Camera) -> bool {
        (
            self.width,
            self.height,
            self.fx,
            self.fy,
            self.cx,
            self.cy,
            self.lens,
        ) == (
            other.width,
            other.height,
            other.fx,
            other.fy,
            other.cx,
            other.cy,
            other.lens,
        )
    }

    /// Unit direction, in the camera frame, through image point `(u, v)`; `None` outside the
    /// lens (never for a pinhole).
    pub fn dir_cam(&self, u: f64, v: f64) -> Option<DVec3> {
        self.lens
            .from_plane(DVec2::new((u - self.cx) / self.fx, (v - self.cy) / self.fy))
    }

    /// The world ray from the camera centre through image point `(u, v)`; `None` outside the
    /// lens.
    pub fn ray(&self, u: f64, v: f64) -> Option<Ray> {
        self.ray_and_dir_cam(u, v).map(|(ray, _)| ray)
    }

    /// [`Camera::ray`] and its camera-frame direction, from one lift (a Newton solve for a
    /// fisheye).
    pub fn ray_and_dir_cam(&self, u: f64, v: f64) -> Option<(Ray, DVec3)> {
        let d = self.dir_cam(u, v)?;
        let ray = Ray {
            origin: self.centre(),
            dir: self.cam_to_world.transform_vector3(d).normalize(),
        };
        Some((ray, d))
    }

    /// The ray through the centre of pixel `(x, y)`; `None` for a pixel outside the lens (which
    /// is not a ray: no label, no loss).
    pub fn pixel_ray(&self, x: u32, y: u32) -> Option<Ray> {
        self.ray(x as f64 + 0.5, y as f64 + 0.5)
    }

    /// Whether pixel `(x, y)` sees the scene through the lens (every pixel of a pinhole).
    pub fn pixel_in_lens(&self, x: u32, y: u32) -> bool {
        matches!(self.lens, Lens::Pinhole) || self.pixel_ray(x, y).is_some()
    }

    /// Image point `(u, v)` and camera-frame depth `z` of a world point; `None` where the lens
    /// does not image it (behind a pinhole, outside a fisheye's lens).
    pub fn project(&self, p: DVec3) -> Option<(f64, f64, f64)> {
        let q = self.world_to_cam().transform_point3(p);
        if self.lens == Lens::Pinhole {
            // The pinhole's own arithmetic (fx * x / z), as before lenses existed: the same
            // bytes in every table derived from a projection.
            return (q.z > 0.0).then(|| {
                (
                    self.fx * q.x / q.z + self.cx,
                    self.fy * q.y / q.z + self.cy,
                    q.z,
                )
            });
        }
        let m = self.lens.to_plane(q)?;
        Some((self.fx * m.x + self.cx, self.fy * m.y + self.cy, q.z))
    }

    /// Camera-frame `z` of the point at distance `t` along `ray` (KITTI depth maps hold `z`;
    /// rays use unit directions, so `z = t * dir_cam.z` for rays from the centre).
    pub fn z_depth(&self, ray: &Ray, t: f64) -> f64 {
        self.world_to_cam().transform_point3(ray.at(t)).z
    }

    /// The depth a depth map of this camera holds for the point at distance `t` along `ray`
    /// (from the centre): camera-frame `z` for a pinhole (KITTI's convention), the distance
    /// `t` itself for a fisheye (whose rays reach 90 degrees from the axis and beyond, where
    /// `z` is zero or negative).
    pub fn depth(&self, ray: &Ray, t: f64) -> f64 {
        match self.lens {
            Lens::Pinhole => self.z_depth(ray, t),
            Lens::Mei(_) => t,
        }
    }

    /// Depth per metre along the ray of unit camera-frame direction `d_cam` (see
    /// [`Camera::depth`]).
    pub fn depth_scale(&self, d_cam: DVec3) -> f64 {
        match self.lens {
            Lens::Pinhole => d_cam.z,
            Lens::Mei(_) => 1.0,
        }
    }
}

/// # camera
///
/// How a `cameras` parameter names one camera, for its documented type (`pipe kinds`): a
/// KITTI-360 name (its number, 0 .. 3, is read too; see [`camera_ids`]).
#[derive(schemars::JsonSchema)]
#[allow(dead_code, non_camel_case_types)]
pub enum CameraName {
    image_00,
    image_01,
    image_02,
    image_03,
}

/// A `cameras` parameter as camera numbers, from numbers (`0`) or KITTI-360 names
/// (`image_00`); for `#[serde(deserialize_with)]`.
pub fn camera_ids<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Vec<u8>, D::Error> {
    #[derive(serde::Deserialize)]
    #[serde(untagged)]
    enum Name {
        Number(u8),
        Text(String),
    }
    let names = <Vec<Name> as serde::Deserialize>::deserialize(d)?;
    names
        .into_iter()
        .map(|n| match n {
            Name::Number(c) => Ok(c),
            Name::Text(t) => t
                .strip_prefix("image_")
                .filter(|k| k.len() == 2)
                .and_then(|k| k.parse::<u8>().ok())
                .ok_or_else(|| {
                    serde::de::Error::custom(format!(
                        "camera `{t}`: name KITTI-360 cameras image_00 .. image_03 (or 0 .. 3)"
                    ))
                }),
        })
        .collect()
}
