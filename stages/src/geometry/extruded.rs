//! A simple polygon in local xy (convex or not, either winding) extruded over `z in [-0.5, 0.5]`.
//!
//! Ray intersection: the line's `z` range inside the slab `|z| <= 0.5`, intersected with the
//! intervals where its xy projection is inside the polygon. The latter come from the crossings
//! of the projected line with the polygon's edges, paired in order along the line. A vertex
//! lying exactly on the line is classified with the half-open rule of the crossing-number test
//! (side `>= 0` vs `< 0`), so the crossings always pair up and no vertex is counted twice.

use std::cell::RefCell;

use glam::{DVec2, DVec3};

use super::aabb::Aabb;
use super::error::GeometryError;
use super::ray::LocalInterval;

thread_local! {
    /// Crossings of one ray: (t, 2D edge normal). Reused so intersecting allocates nothing.
    static CROSSINGS: RefCell<Vec<(f64, DVec2)>> = const { RefCell::new(Vec::new()) };
}

/// A validated polygon.
#[derive(Clone, Debug)]
pub struct Polygon {
    pts: Vec<DVec2>,
}

fn cross(a: DVec2, b: DVec2) -> f64 {
    a.x * b.y - a.y * b.x
}

/// Whether closed segments `ab` and `cd` share a point.
fn segments_meet(a: DVec2, b: DVec2, c: DVec2, d: DVec2) -> bool {
    let o1 = cross(b - a, c - a);
    let o2 = cross(b - a, d - a);
    let o3 = cross(d - c, a - c);
    let o4 = cross(d - c, b - c);
    if o1 == 0.0 && o2 == 0.0 {
        // Collinear: do the boxes overlap?
        let (lo1, hi1) = (a.min(b), a.max(b));
        let (lo2, hi2) = (c.min(d), c.max(d));
        return lo1.cmple(hi2).all() && lo2.cmple(hi1).all();
    }
    o1 * o2 <= 0.0 && o3 * o4 <= 0.0
}

impl Polygon {
    /// Checks the polygon: at least 3 finite vertices, non-zero area, no two non-adjacent edges
    /// meeting (O(n^2), fine for annotation polygons).
    pub fn new(points: &[[f64; 2]]) -> Result<Self, GeometryError> {
        if points.len() < 3 {
            return Err(GeometryError::PolygonTooFew { n: points.len() });
        }
        if points.iter().flatten().any(|v| !v.is_finite()) {
            return Err(GeometryError::NonFinite("polygon"));
        }
        let pts: Vec<DVec2> = points.iter().map(|&[x, y]| DVec2::new(x, y)).collect();
        let n = pts.len();
        let area: f64 = (0..n).map(|i| cross(pts[i], pts[(i + 1) % n])).sum::<f64>() * 0.5;
        let (lo, hi) = pts
            .iter()
            .fold((pts[0], pts[0]), |(lo, hi), &p| (lo.min(p), hi.max(p)));
        let ext = hi - lo;
        if area.abs() <= 1e-12 * ext.x.max(ext.y).powi(2) || area == 0.0 {
            return Err(GeometryError::PolygonZeroArea);
        }
        for i in 0..n {
            for j in i + 2..n {
                if i == 0 && j == n - 1 {
                    continue; // adjacent through the closing edge
                }
                if segments_meet(pts[i], pts[(i + 1) % n], pts[j], pts[(j + 1) % n]) {
                    return Err(GeometryError::PolygonSelfIntersecting { a: i, b: j });
                }
            }
        }
        Ok(Self { pts })
    }

    /// Local bounds of the prism.
    pub fn bounds(&self) -> Aabb {
        let b = Aabb::from_points(self.pts.iter().map(|p| p.extend(0.0)));
        Aabb::new(b.min.truncate().extend(-0.5), b.max.truncate().extend(0.5))
    }

    /// Even-odd point-in-polygon test in xy.
    pub fn contains_2d(&self, p: DVec2) -> bool {
        let n = self.pts.len();
        let mut inside = false;
        for i in 0..n {
            let (a, b) = (self.pts[i], self.pts[(i + 1) % n]);
            if (a.y > p.y) != (b.y > p.y) {
                let x = a.x + (p.y - a.y) / (b.y - a.y) * (b.x - a.x);
                if p.x < x {
                    inside = !inside;
                }
            }
        }
        inside
    }

    pub(crate) fn contains(&self, q: DVec3) -> bool {
        q.z.abs() <= 0.5 && self.contains_2d(q.truncate())
    }

    /// Calls `emit` with every interval of the whole line `o + t d` inside the prism, in order.
    pub(crate) fn intersect(&self, o: DVec3, d: DVec3, emit: &mut impl FnMut(LocalInterval)) {
        let (zlo, zhi) = if d.z == 0.0 {
            if o.z.abs() > 0.5 {
                return;
            }
            (f64::NEG_INFINITY, f64::INFINITY)
        } else {
            let t1 = (-0.5 - o.z) / d.z;
            let t2 = (0.5 - o.z) / d.z;
            (t1.min(t2), t1.max(t2))
        };
        let cap = DVec3::Z;
        let (o2, d2) = (o.truncate(), d.truncate());
        if d2 == DVec2::ZERO {
            if self.contains_2d(o2) {
                emit(LocalInterval {
                    t_in: zlo,
                    t_out: zhi,
                    n_in: cap,
                });
            }
            return;
        }
        CROSSINGS.with(|c| {
            let mut c = c.borrow_mut();
            c.clear();
            let n = self.pts.len();
            for i in 0..n {
                let (a, b) = (self.pts[i], self.pts[(i + 1) % n]);
                let sa = cross(d2, a - o2);
                let sb = cross(d2, b - o2);
                if (sa >= 0.0) != (sb >= 0.0) {
                    let e = b - a;
                    let t = cross(a - o2, e) / cross(d2, e);
                    c.push((t, DVec2::new(e.y, -e.x)));
                }
            }
            c.sort_unstable_by(|x, y| x.0.total_cmp(&y.0));
            for pair in c.chunks_exact(2) {
                let (ta, na) = pair[0];
                let tb = pair[1].0;
                let lo = ta.max(zlo);
                let hi = tb.min(zhi);
                if lo < hi {
                    let n_in = if ta >= zlo { na.extend(0.0) } else { cap };
                    emit(LocalInterval {
                        t_in: lo,
                        t_out: hi,
                        n_in,
                    });
                }
            }
        });
    }
}
