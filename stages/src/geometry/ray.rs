//! Rays and the intervals along them.

use glam::DVec3;

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

/// A local-frame interval of the whole line `o' + t d'`, `t` in R; `n_in` is the local entry
/// normal in any orientation and length.
#[derive(Clone, Copy, Debug)]
pub(crate) struct LocalInterval {
    pub t_in: f64,
    pub t_out: f64,
    pub n_in: DVec3,
}
