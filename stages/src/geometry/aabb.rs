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

    /// Slab test: the overlap of the ray (given `inv_dir` from [`Aabb::inv_dir`]) with
    /// the box, clipped to `[t_min, t_max]`; `None` if empty. The NaN of `0 * inf` (origin on a
    /// slab plane, ray parallel to it) is read as "inside that slab": boundaries are inclusive,
    /// as the primitives' are.
    #[inline]
    pub fn ray_overlap(
        &self,
        origin: DVec3,
        inv_dir: DVec3,
        t_min: f64,
        t_max: f64,
    ) -> Option<(f64, f64)> {
        let t1 = (self.min - origin) * inv_dir;
        let t2 = (self.max - origin) * inv_dir;
        let mut lo = t_min;
        let mut hi = t_max;
        for k in 0..3 {
            let a = if t1[k].is_nan() {
                f64::NEG_INFINITY
            } else {
                t1[k]
            };
            let b = if t2[k].is_nan() { f64::INFINITY } else { t2[k] };
            lo = lo.max(a.min(b));
            hi = hi.min(a.max(b));
        }
        (lo <= hi).then_some((lo, hi))
    }
}
