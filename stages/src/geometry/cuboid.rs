//! The unit cube `[-0.5, 0.5]^3` in local space: slab test and point test. The fast special case
//! for the most common primitive (KITTI-360 cuboids arrive as 8-vertex meshes; the scene loader
//! may recognise them).

use glam::DVec3;

use super::ray::LocalInterval;

/// The interval of the whole line `o + t d` inside the cube (`None` if it misses or only touches
/// an edge). A line parallel to a face and lying in its plane counts as inside (closed cube).
#[inline]
pub(crate) fn intersect(o: DVec3, d: DVec3) -> Option<LocalInterval> {
    let mut lo = f64::NEG_INFINITY;
    let mut hi = f64::INFINITY;
    let mut axis = 0;
    for k in 0..3 {
        if d[k] == 0.0 {
            if o[k].abs() > 0.5 {
                return None;
            }
            continue;
        }
        let inv = 1.0 / d[k];
        let t1 = (-0.5 - o[k]) * inv;
        let t2 = (0.5 - o[k]) * inv;
        let (near, far) = if t1 < t2 { (t1, t2) } else { (t2, t1) };
        if near > lo {
            lo = near;
            axis = k;
        }
        hi = hi.min(far);
    }
    if lo >= hi {
        return None;
    }
    let mut n = DVec3::ZERO;
    n[axis] = 1.0;
    Some(LocalInterval {
        t_in: lo,
        t_out: hi,
        n_in: n,
    })
}

/// Whether the local point is in the closed cube.
#[inline]
pub(crate) fn contains(q: DVec3) -> bool {
    q.abs().max_element() <= 0.5
}
