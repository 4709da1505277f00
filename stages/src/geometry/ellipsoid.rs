//! The unit-diameter sphere (radius 0.5) in local space, which a transform makes an oriented,
//! scaled ellipsoid: a quadratic in `t`, solved in the cancellation-free form.

use glam::DVec3;

use super::ray::LocalInterval;

/// The chord of the whole line `o + t d` through the sphere `|x| <= 0.5` (`None` if it misses
/// or is tangent).
#[inline]
pub(crate) fn intersect(o: DVec3, d: DVec3) -> Option<LocalInterval> {
    let a = d.length_squared();
    // Solve about the point of the line nearest to the centre: stable for far-away origins.
    let t_mid = -o.dot(d) / a;
    let closest = o + t_mid * d;
    let h2 = 0.25 - closest.length_squared();
    if h2 <= 0.0 {
        return None;
    }
    let half = (h2 / a).sqrt();
    let t_in = t_mid - half;
    Some(LocalInterval {
        t_in,
        t_out: t_mid + half,
        n_in: o + t_in * d,
    })
}

/// Whether the local point is in the closed ball.
#[inline]
pub(crate) fn contains(q: DVec3) -> bool {
    q.length_squared() <= 0.25
}
