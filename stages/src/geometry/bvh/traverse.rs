//! Queries: all intervals along a ray, the first hit (ordered, pruned traversal), and the
//! primitives containing a point. Fixed-size stacks and a thread-local interval buffer: no
//! allocation per query beyond the caller's `out`.

use std::cell::RefCell;

use super::{Bvh, MAX_DEPTH};
use crate::geometry::{Aabb, Hit, Interval, Primitive, Ray};

thread_local! {
    static SCRATCH: RefCell<Vec<Interval>> = const { RefCell::new(Vec::new()) };
}

/// Clips `iv` to `[t_min, t_max]`; `None` if nothing is left.
#[inline]
fn clip(iv: &Interval, prim: u32, t_min: f64, t_max: f64) -> Option<Hit> {
    let t_in = iv.t_in.max(t_min);
    let t_out = iv.t_out.min(t_max);
    (t_in < t_out).then_some(Hit {
        t_in,
        t_out,
        prim,
        normal_in: iv.normal_in,
    })
}

fn hit_order(a: &Hit, b: &Hit) -> std::cmp::Ordering {
    a.t_in.total_cmp(&b.t_in).then(a.prim.cmp(&b.prim))
}

impl Bvh {
    /// Every interval of every primitive overlapping `[t_min, t_max]`, clipped to it, sorted by
    /// `t_in` (ties by primitive id). `out` is cleared first. A primitive may contribute several
    /// intervals (non-convex shapes); intervals of different primitives may overlap.
    pub fn intersect_all(
        &self,
        prims: &[Primitive],
        ray: &Ray,
        t_min: f64,
        t_max: f64,
        out: &mut Vec<Hit>,
    ) {
        out.clear();
        if self.nodes.is_empty() {
            return;
        }
        let inv = Aabb::inv_dir(ray.dir);
        SCRATCH.with(|s| {
            let mut s = s.borrow_mut();
            let mut stack = [0u32; MAX_DEPTH + 2];
            let mut sp = 1;
            while sp > 0 {
                sp -= 1;
                let node = &self.nodes[stack[sp] as usize];
                if node
                    .aabb
                    .ray_overlap(ray.origin, inv, t_min, t_max)
                    .is_none()
                {
                    continue;
                }
                if node.count == 0 {
                    stack[sp] = node.first;
                    stack[sp + 1] = node.first + 1;
                    sp += 2;
                    continue;
                }
                for k in node.first as usize..(node.first + node.count) as usize {
                    if self.boxes[k]
                        .ray_overlap(ray.origin, inv, t_min, t_max)
                        .is_none()
                    {
                        continue;
                    }
                    let pi = self.order[k];
                    s.clear();
                    prims[pi as usize].intersect(ray, &mut s);
                    out.extend(s.iter().filter_map(|iv| clip(iv, pi, t_min, t_max)));
                }
            }
        });
        out.sort_unstable_by(hit_order);
    }

    /// [`Bvh::first_hit`] over two primitive sets at once (a static scene and the moving
    /// objects at one frame, each with its hierarchy): the nearer hit and whether it is the
    /// second set's (the first set's on a tie).
    pub fn first_hit_of_two(
        (a, a_prims): (&Bvh, &[Primitive]),
        (b, b_prims): (&Bvh, &[Primitive]),
        ray: &Ray,
        t_min: f64,
        t_max: f64,
    ) -> Option<(Hit, bool)> {
        let first = a.first_hit(a_prims, ray, t_min, t_max);
        let end = first.as_ref().map_or(t_max, |h| h.t_in.max(t_min));
        match b.first_hit(b_prims, ray, t_min, end) {
            Some(h)
                if first
                    .as_ref()
                    .is_none_or(|f| h.t_in.max(t_min) < f.t_in.max(t_min)) =>
            {
                Some((h, true))
            }
            _ => first.map(|h| (h, false)),
        }
    }

    /// The hit with the smallest clipped entry `max(t_in, t_min)` in `[t_min, t_max]` (ties by
    /// primitive id), i.e. the first element [`Bvh::intersect_all`] would return. Children are
    /// visited near-first and skipped when their box starts beyond the best hit so far.
    pub fn first_hit(&self, prims: &[Primitive], ray: &Ray, t_min: f64, t_max: f64) -> Option<Hit> {
        if self.nodes.is_empty() {
            return None;
        }
        let inv = Aabb::inv_dir(ray.dir);
        let mut best: Option<Hit> = None;
        SCRATCH.with(|s| {
            let mut s = s.borrow_mut();
            let mut stack = [(0u32, 0.0f64); MAX_DEPTH + 2];
            let Some((t0, _)) = self.nodes[0]
                .aabb
                .ray_overlap(ray.origin, inv, t_min, t_max)
            else {
                return;
            };
            stack[0] = (0, t0);
            let mut sp = 1;
            while sp > 0 {
                sp -= 1;
                let (ni, near) = stack[sp];
                if best.is_some_and(|b| near > b.t_in) {
                    continue;
                }
                let node = &self.nodes[ni as usize];
                if node.count == 0 {
                    let (a, b) = (node.first, node.first + 1);
                    let limit = best.map_or(t_max, |b| b.t_in);
                    let ha = self.nodes[a as usize]
                        .aabb
                        .ray_overlap(ray.origin, inv, t_min, limit);
                    let hb = self.nodes[b as usize]
                        .aabb
                        .ray_overlap(ray.origin, inv, t_min, limit);
                    match (ha, hb) {
                        (Some((ta, _)), Some((tb, _))) => {
                            // Push the farther first so the nearer is popped first.
                            let (f, n) = if ta <= tb {
                                ((b, tb), (a, ta))
                            } else {
                                ((a, ta), (b, tb))
                            };
                            stack[sp] = f;
                            stack[sp + 1] = n;
                            sp += 2;
                        }
                        (Some(x), None) => {
                            stack[sp] = (a, x.0);
                            sp += 1;
                        }
                        (None, Some(x)) => {
                            stack[sp] = (b, x.0);
                            sp += 1;
                        }
                        (None, None) => {}
                    }
                    continue;
                }
                for k in node.first as usize..(node.first + node.count) as usize {
                    let limit = best.map_or(t_max, |b| b.t_in);
                    if self.boxes[k]
                        .ray_overlap(ray.origin, inv, t_min, limit)
                        .is_none()
                    {
                        continue;
                    }
                    let pi = self.order[k];
                    s.clear();
                    prims[pi as usize].intersect(ray, &mut s);
                    for iv in s.iter() {
                        if let Some(h) = clip(iv, pi, t_min, t_max) {
                            if best.is_none_or(|b| hit_order(&h, &b).is_lt()) {
                                best = Some(h);
                            }
                            break; // a primitive's intervals are sorted: the first clipped one is its nearest
                        }
                    }
                }
            }
        });
        best
    }

    /// Ids of the primitives containing `p`, ascending. `out` is cleared first.
    pub fn containing(&self, prims: &[Primitive], p: glam::DVec3, out: &mut Vec<u32>) {
        out.clear();
        if self.nodes.is_empty() {
            return;
        }
        let mut stack = [0u32; MAX_DEPTH + 2];
        let mut sp = 1;
        while sp > 0 {
            sp -= 1;
            let node = &self.nodes[stack[sp] as usize];
            if !node.aabb.contains(p) {
                continue;
            }
            if node.count == 0 {
                stack[sp] = node.first;
                stack[sp + 1] = node.first + 1;
                sp += 2;
                continue;
            }
            for &pi in &self.order[node.first as usize..(node.first + node.count) as usize] {
                if prims[pi as usize].contains(p) {
                    out.push(pi);
                }
            }
        }
        out.sort_unstable();
    }
}
