//! Axis-aligned bounding boxes: union, transform, point test and the ray slab test the BVH
//! traverses with.

use glam::{DAffine3, DVec3};

/// An axis-aligned box `[min, max]` (empty when any `min > max`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    pub min: DVec3,
    pub max: DVec3,
}

impl Aabb {
    pub const EMPTY: Aabb = Aabb {
        min: DVec3::splat(f64::INFINITY),
        max: DVec3::splat(f64::NEG_INFINITY),
    };

    pub fn new(min: DVec3, max: DVec3) -> Self {
        Self { min, max }
    }

    /// The smallest box holding all `points` (EMPTY for none).
    pub fn from_points(points: impl IntoIterator<Item = DVec3>) -> Self {
        points.into_iter().fold(Self::EMPTY, |b, p| b.grow(p))
    }

    pub fn grow(self, p: DVec3) -> Self {
        Self::new(self.min.min(p), self.max.max(p))
    }

    pub fn union(self, o: Aabb) -> Self {
        Self::new(self.min.min(o.min), self.max.max(o.max))
    }

    pub fn is_empty(&self) -> bool {
        self.min.cmpgt(self.max).any()
    }

    pub fn centre(&self) -> DVec3 {
        0.5 * (self.min + self.max)
    }

    pub fn extent(&self) -> DVec3 {
        (self.max - self.min).max(DVec3::ZERO)
    }

    /// Half the surface area (the SAH cost only needs proportions); 0 for empty boxes.
    pub fn half_area(&self) -> f64 {
        if self.is_empty() {
            return 0.0;
        }
        let e = self.extent();
        e.x * e.y + e.y * e.z + e.z * e.x
    }

    pub fn contains(&self, p: DVec3) -> bool {
        p.cmpge(self.min).all() && p.cmple(self.max).all()
    }

    /// Whether `o` lies inside (or on) `self`.
    pub fn contains_box(&self, o: &Aabb) -> bool {
        o.is_empty() || (self.contains(o.min) && self.contains(o.max))
    }

    /// Bounds of the image of this box under `m` (the 8 corners).
    pub fn transformed(&self, m: &DAffine3) -> Self {
        let mut b = Self::EMPTY;
        for i in 0..8 {
            let c = DVec3::new(
                if i & 1 == 0 { self.min.x } else { self.max.x },
                if i & 2 == 0 { self.min.y } else { self.max.y },
                if i & 4 == 0 { self.min.z } else { self.max.z },
            );
            b = b.grow(m.transform_point3(c));
        }
        b
    }

    /// `1 / dir` with zero components mapped to `+inf` (never `-inf`, which [`Aabb::ray_overlap`]
    /// relies on for rays lying in a slab plane).
    #[inline]
    pub fn inv_dir(dir: DVec3) -> DVec3 {
        DVec3::ONE / (dir + DVec3::ZERO)
    }

    /// Slab test: the overlap of the ray (given `inv_dir` from [`Aabb::inv_dir`]) with the
    /// box, clipped to `[t_min, t_max]`; `None` if empty. Boundaries are inclusive, as the
    /// primitives' are. A ray parallel to a slab and starting exactly on one of its planes gives
    /// `0 * inf = NaN`, which fails both comparisons below and so (correctly) adds no
    /// constraint; the comparison form also compiles to plain `maxsd`/`minsd`.
    #[inline]
    pub fn ray_overlap(
        &self,
        origin: DVec3,
        inv_dir: DVec3,
        t_min: f64,
        t_max: f64,
    ) -> Option<(f64, f64)> {
        let mut lo = t_min;
        let mut hi = t_max;
        for k in 0..3 {
            let (a, b) = if inv_dir[k] >= 0.0 {
                (self.min[k], self.max[k])
            } else {
                (self.max[k], self.min[k])
            };
            let near = (a - origin[k]) * inv_dir[k];
            let far = (b - origin[k]) * inv_dir[k];
            if near > lo {
                lo = near;
            }
            if far < hi {
                hi = far;
            }
        }
        (lo <= hi).then_some((lo, hi))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slab_test_handles_parallel_rays_on_planes() {
        let b = Aabb::new(DVec3::ZERO, DVec3::ONE);
        let inv = |d: DVec3| Aabb::inv_dir(d);
        // Along x, on the y = 0 and z = 1 planes (boundary: inside).
        let o = DVec3::new(-1.0, 0.0, 1.0);
        assert_eq!(b.ray_overlap(o, inv(DVec3::X), 0.0, 10.0), Some((1.0, 2.0)));
        assert_eq!(
            b.ray_overlap(o, inv(DVec3::new(1.0, -0.0, 0.0)), 0.0, 10.0),
            Some((1.0, 2.0))
        );
        // Parallel, just outside.
        let o = DVec3::new(-1.0, -1e-12, 0.5);
        assert_eq!(b.ray_overlap(o, inv(DVec3::X), 0.0, 10.0), None);
        // Backwards direction, clipped range.
        let o = DVec3::new(3.0, 0.5, 0.5);
        assert_eq!(
            b.ray_overlap(o, inv(-DVec3::X), 0.0, 10.0),
            Some((2.0, 3.0))
        );
        assert_eq!(b.ray_overlap(o, inv(-DVec3::X), 0.0, 1.5), None);
        assert_eq!(Aabb::EMPTY.ray_overlap(o, inv(-DVec3::X), 0.0, 10.0), None);
    }
}
