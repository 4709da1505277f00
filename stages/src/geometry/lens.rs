//! Lens models: what lies between a camera-frame direction and the normalised image plane
//! (before the focal lengths and principal point of [`super::Camera`]). KITTI-360's perspective
//! cameras are rectified pinholes; its side fisheye cameras (image_02, image_03) follow MEI's
//! unified omnidirectional model: a point is projected onto the unit sphere, then from a centre
//! `xi` behind the sphere's centre onto the plane, then distorted radially and tangentially.
//!
//! The model folds back beyond the angle where `1 + xi cos(theta) = 0` (and where a strong
//! distortion stops growing with the radius), so projection and lifting are both defined only on
//! the invertible part; a pixel there is also "in the lens" only within
//! [`Mei::max_half_angle_deg`] of the optical axis.

use glam::{DMat2, DVec2, DVec3};

/// How a camera maps directions to the normalised image plane.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Lens {
    /// A rectified pinhole: the plane point is `(x/z, y/z)`.
    Pinhole,
    /// MEI's unified omnidirectional model (KITTI-360 fisheye cameras).
    Mei(Mei),
}

/// Parameters of MEI's model as KITTI-360's `image_02.yaml` names them (the projection
/// parameters gamma1, gamma2, u0, v0 are the camera's fx, fy, cx, cy).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Mei {
    /// Mirror parameter: distance of the projection centre behind the unit sphere's centre.
    pub xi: f64,
    pub k1: f64,
    pub k2: f64,
    pub p1: f64,
    pub p2: f64,
    /// Pixels whose ray is farther than this from the optical axis are outside the lens (a
    /// fisheye image is dark outside its lens circle).
    pub max_half_angle_deg: f64,
}

/// Half the field of view of a KITTI-360 fisheye lens (about 185 degrees), with a margin.
pub const FISHEYE_HALF_ANGLE_DEG: f64 = 95.0;

/// Plane points whose distortion is undone to within this are lifted (about 1e-9 px).
const UNDISTORT_TOLERANCE: f64 = 1e-12;
const UNDISTORT_ITERATIONS: usize = 50;

impl Lens {
    /// The normalised plane point of a camera-frame direction (any length); `None` where the
    /// lens does not image it.
    pub fn to_plane(&self, x: DVec3) -> Option<DVec2> {
        match self {
            Lens::Pinhole => (x.z > 0.0).then(|| DVec2::new(x.x / x.z, x.y / x.z)),
            Lens::Mei(m) => m.to_plane(x),
        }
    }

    /// The unit camera-frame direction through normalised plane point `p`; `None` outside the
    /// lens.
    pub fn from_plane(&self, p: DVec2) -> Option<DVec3> {
        match self {
            Lens::Pinhole => Some(DVec3::new(p.x, p.y, 1.0).normalize()),
            Lens::Mei(m) => m.from_plane(p),
        }
    }

    /// The model's name in the `cameras` table and in KITTI-360's calibration files.
    pub fn name(&self) -> &'static str {
        match self {
            Lens::Pinhole => "pinhole",
            Lens::Mei(_) => "MEI",
        }
    }
}

impl Mei {
    /// Checks the parameters: all finite, `xi > 0`, a positive half angle.
    pub fn validate(&self) -> Result<(), String> {
        let v = [self.xi, self.k1, self.k2, self.p1, self.p2];
        if !v.iter().all(|x| x.is_finite()) {
            return Err(format!("MEI parameters must be finite: {self:?}"));
        }
        if self.xi <= 0.0 {
            return Err(format!(
                "mirror parameter xi must be > 0, found {}",
                self.xi
            ));
        }
        if !(self.max_half_angle_deg > 0.0 && self.max_half_angle_deg <= 180.0) {
            return Err(format!(
                "max_half_angle_deg must be in (0, 180], found {}",
                self.max_half_angle_deg
            ));
        }
        Ok(())
    }

    /// Whether a unit direction `s` is inside the lens: within the half angle, and on the
    /// invertible part of the model.
    fn images(&self, s: DVec3) -> bool {
        s.z >= self.max_half_angle_deg.to_radians().cos()
            && s.z + self.xi > 0.0
            && 1.0 + self.xi * s.z > 0.0
    }

    /// The distorted plane point of camera-frame direction `x` (any length).
    pub fn to_plane(&self, x: DVec3) -> Option<DVec2> {
        let s = x.try_normalize()?;
        if !self.images(s) {
            return None;
        }
        let m = DVec2::new(s.x, s.y) / (s.z + self.xi);
        (self.jacobian(m).determinant() > 0.0).then(|| self.distort(m))
    }

    /// The unit direction whose distorted plane point is `d`.
    pub fn from_plane(&self, d: DVec2) -> Option<DVec3> {
        let m = self.undistort(d)?;
        let r2 = m.length_squared();
        let disc = 1.0 + (1.0 - self.xi * self.xi) * r2;
        if disc < 0.0 {
            return None;
        }
        let f = (self.xi + disc.sqrt()) / (r2 + 1.0);
        let s = DVec3::new(f * m.x, f * m.y, f - self.xi).try_normalize()?;
        self.images(s).then_some(s)
    }

    /// Radial-tangential distortion of an undistorted plane point.
    pub fn distort(&self, m: DVec2) -> DVec2 {
        let (x, y) = (m.x, m.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2;
        DVec2::new(
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// Jacobian of [`Mei::distort`] at `m`.
    fn jacobian(&self, m: DVec2) -> DMat2 {
        let (x, y) = (m.x, m.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2;
        // d(radial)/dx = (2 k1 + 4 k2 r2) x
        let dr = 2.0 * self.k1 + 4.0 * self.k2 * r2;
        let dxdx = radial + x * dr * x + 2.0 * self.p1 * y + 6.0 * self.p2 * x;
        let dxdy = x * dr * y + 2.0 * self.p1 * x + 2.0 * self.p2 * y;
        let dydx = y * dr * x + 2.0 * self.p1 * x + 2.0 * self.p2 * y;
        let dydy = radial + y * dr * y + 6.0 * self.p1 * y + 2.0 * self.p2 * x;
        DMat2::from_cols(DVec2::new(dxdx, dydx), DVec2::new(dxdy, dydy))
    }

    /// The undistorted plane point whose distortion is `d` (Newton's method from `d`); `None`
    /// where it does not converge or lands where the distortion folds over.
    pub fn undistort(&self, d: DVec2) -> Option<DVec2> {
        if !d.is_finite() {
            return None;
        }
        let mut m = d;
        for _ in 0..UNDISTORT_ITERATIONS {
            let e = self.distort(m) - d;
            let j = self.jacobian(m);
            if e.length() < UNDISTORT_TOLERANCE {
                return (j.determinant() > 0.0).then_some(m);
            }
            let det = j.determinant();
            if det.is_nan() || det <= 0.0 || !m.is_finite() {
                return None;
            }
            let step = j.inverse() * e;
            // Damped where a full step would more than double the radius (far outside the
            // lens the cubic and quintic terms overshoot).
            let limit = 0.5 * (m.length() + 1e-3);
            m -= if step.length() > limit {
                step * (limit / step.length())
            } else {
                step
            };
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use glam::DAffine3;
    use proptest::prelude::*;

    use super::*;
    use crate::geometry::Camera;

    /// The shape of KITTI-360's image_02 calibration.
    fn kitti_fisheye() -> Camera {
        Camera {
            width: 1400,
            height: 1400,
            fx: 1336.0,
            fy: 1337.0,
            cx: 716.9 + 0.5,
            cy: 705.8 + 0.5,
            lens: Lens::Mei(Mei {
                xi: 2.2134,
                k1: 0.01693,
                k2: 1.6798,
                p1: 4.2e-4,
                p2: 4.2e-4,
                max_half_angle_deg: FISHEYE_HALF_ANGLE_DEG,
            }),
            cam_to_world: DAffine3::IDENTITY,
        }
    }

    #[test]
    fn every_lens_pixel_projects_back_onto_itself() {
        let cam = kitti_fisheye();
        let (mut inside, mut total, mut worst) = (0usize, 0usize, 0f64);
        for y in (0..cam.height).step_by(3) {
            for x in (0..cam.width).step_by(3) {
                total += 1;
                let Some(ray) = cam.pixel_ray(x, y) else {
                    continue;
                };
                inside += 1;
                let (u, v, _) = cam.project(ray.at(7.0)).expect("a lifted ray projects");
                let e = (u - (x as f64 + 0.5)).hypot(v - (y as f64 + 0.5));
                worst = worst.max(e);
            }
        }
        assert!(worst < 1e-3, "worst round trip {worst} px");
        // The lens circle: the centre and the middle of each side are in, the corners out.
        for (x, y) in [(700, 700), (700, 40), (40, 700), (1360, 700), (700, 1360)] {
            assert!(cam.pixel_in_lens(x, y), "({x}, {y})");
        }
        for (x, y) in [(0, 0), (1399, 0), (0, 1399), (1399, 1399)] {
            assert!(!cam.pixel_in_lens(x, y), "({x}, {y})");
        }
        let share = inside as f64 / total as f64;
        assert!(
            (0.6..0.95).contains(&share),
            "{share} of the pixels in the lens"
        );
    }

    /// The direction of image point `(u, v)` by brute force: the best of a grid over the
    /// sphere, refined by smaller grids around the best; only `project` is used.
    fn lift_by_search(cam: &Camera, u: f64, v: f64) -> DVec3 {
        let dir = |theta: f64, phi: f64| {
            DVec3::new(
                theta.sin() * phi.cos(),
                theta.sin() * phi.sin(),
                theta.cos(),
            )
        };
        let err = |d: DVec3| {
            cam.project(d)
                .map_or(f64::INFINITY, |(pu, pv, _)| (pu - u).hypot(pv - v))
        };
        let (mut best, mut best_e) = ((0.0, 0.0), f64::INFINITY);
        let (mut span_t, mut span_p) = (std::f64::consts::PI, std::f64::consts::PI);
        let (mut centre_t, mut centre_p) = (span_t / 2.0, 0.0);
        for _ in 0..14 {
            for i in 0..=40 {
                for j in 0..=40 {
                    let t = centre_t + span_t * (i as f64 / 40.0 - 0.5);
                    let p = centre_p + span_p * 2.0 * (j as f64 / 40.0 - 0.5);
                    let e = err(dir(t, p));
                    if e < best_e {
                        (best, best_e) = ((t, p), e);
                    }
                }
            }
            (centre_t, centre_p) = best;
            span_t /= 8.0;
            span_p /= 8.0;
        }
        dir(best.0, best.1)
    }

    #[test]
    fn lifting_agrees_with_a_brute_force_search() {
        let cam = kitti_fisheye();
        for (u, v) in [
            (700.5, 700.5),
            (100.5, 700.5),
            (1150.5, 300.5),
            (650.25, 1350.75),
            (250.5, 300.5),
            (1000.5, 900.5),
        ] {
            let lifted = cam.dir_cam(u, v).expect("in the lens");
            let searched = lift_by_search(&cam, u, v);
            let angle = lifted.angle_between(searched);
            assert!(
                angle < 1e-6,
                "({u}, {v}): {lifted} vs {searched}: {angle} rad"
            );
        }
    }

    #[test]
    fn the_pinhole_lens_is_the_perspective_division() {
        let lens = Lens::Pinhole;
        let p = lens.to_plane(DVec3::new(2.0, -1.0, 4.0)).unwrap();
        assert_eq!(p, DVec2::new(0.5, -0.25));
        assert!(lens.to_plane(DVec3::new(0.0, 0.0, -1.0)).is_none());
        let d = lens.from_plane(p).unwrap();
        assert!((d - DVec3::new(2.0, -1.0, 4.0).normalize()).length() < 1e-15);
    }

    #[test]
    fn bad_points_and_parameters_are_refused_not_panicked_on() {
        let cam = kitti_fisheye();
        for (u, v) in [(f64::NAN, 3.0), (1e30, 0.0), (f64::INFINITY, 5.0)] {
            assert!(cam.dir_cam(u, v).is_none(), "({u}, {v})");
        }
        assert!(cam.project(cam.centre()).is_none(), "the centre itself");
        // Straight behind the camera: outside any fisheye lens.
        assert!(cam.project(DVec3::new(0.0, 0.0, -3.0)).is_none());
        let Lens::Mei(m) = cam.lens else {
            unreachable!()
        };
        let bad = [
            Mei { xi: 0.0, ..m },
            Mei { xi: -1.0, ..m },
            Mei { k1: f64::NAN, ..m },
            Mei {
                max_half_angle_deg: 0.0,
                ..m
            },
        ];
        for b in bad {
            assert!(b.validate().is_err(), "{b:?}");
        }
        assert!(m.validate().is_ok());
    }

    proptest! {
        /// Any direction inside the lens projects and lifts back to itself, for MEI parameters
        /// around KITTI-360's (mirror parameters below and above 1).
        #[test]
        fn directions_survive_projection_and_lifting(
            xi in 0.3f64..3.0,
            k1 in -0.05f64..0.1,
            k2 in 0.0f64..2.0,
            p1 in -1e-3f64..1e-3,
            p2 in -1e-3f64..1e-3,
            theta_deg in 0.0f64..95.0,
            phi in 0.0f64..std::f64::consts::TAU,
        ) {
            let m = Mei { xi, k1, k2, p1, p2, max_half_angle_deg: FISHEYE_HALF_ANGLE_DEG };
            let t = theta_deg.to_radians();
            let d = DVec3::new(t.sin() * phi.cos(), t.sin() * phi.sin(), t.cos());
            // Where the model folds (xi < 1 reaches 180 degrees, strong k1 < 0 folds early)
            // there is nothing to invert; otherwise the round trip is exact.
            if let Some(p) = m.to_plane(d) {
                let back = m.from_plane(p).expect("a projected point lifts");
                prop_assert!((back - d).length() < 1e-9, "{d} -> {p} -> {back}");
                // Relative: plane points reach 1e3 and more near 95 degrees with a small xi,
                // where one f64 ulp is already 1e-13.
                let again = m.to_plane(back * 5.0).unwrap();
                prop_assert!((again - p).length() < 1e-12 * p.length().max(1.0), "{again} vs {p}");
            } else {
                prop_assert!(xi < 1.0 || k1 < 0.0 || 1.0 + xi * d.z <= 1e-9,
                    "{d} does not project with {m:?}");
            }
        }
    }
}
