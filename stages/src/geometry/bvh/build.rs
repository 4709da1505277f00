//! Binned SAH construction: split each node's primitives along the longest axis of their
//! centroid bounds at the best of 16 bin boundaries, or make a leaf when splitting does not pay.

use super::{Bvh, Node, LEAF_TARGET, MAX_DEPTH};
use crate::geometry::{Aabb, Primitive};

const BINS: usize = 16;
/// Cost of visiting a node relative to one primitive test.
const TRAVERSAL_COST: f64 = 1.0;

impl Bvh {
    /// Builds over `prims`.
    pub fn build(prims: &[Primitive]) -> Bvh {
        build(prims)
    }
}

fn build(prims: &[Primitive]) -> Bvh {
    let boxes: Vec<Aabb> = prims.iter().map(|p| p.aabb()).collect();
    let mut order: Vec<u32> = (0..prims.len() as u32).collect();
    let mut nodes = Vec::with_capacity(2 * prims.len().max(1));
    if !prims.is_empty() {
        nodes.push(Node {
            aabb: Aabb::EMPTY,
            first: 0,
            count: 0,
        });
        split(&boxes, &mut order, &mut nodes, 0, 0, prims.len(), 1);
    }
    let boxes = order.iter().map(|&i| boxes[i as usize]).collect();
    Bvh {
        nodes,
        order,
        boxes,
    }
}

fn split(
    boxes: &[Aabb],
    order: &mut [u32],
    nodes: &mut Vec<Node>,
    node: usize,
    start: usize,
    end: usize,
    depth: usize,
) {
    let items = &mut order[start..end];
    let bounds = items
        .iter()
        .fold(Aabb::EMPTY, |b, &i| b.union(boxes[i as usize]));
    let centroids = items
        .iter()
        .fold(Aabb::EMPTY, |b, &i| b.grow(boxes[i as usize].centre()));
    let n = items.len();
    let make_leaf = |nodes: &mut Vec<Node>| {
        nodes[node] = Node {
            aabb: bounds,
            first: start as u32,
            count: n as u32,
        };
    };
    if n <= 1 || depth >= MAX_DEPTH {
        return make_leaf(nodes);
    }
    let ext = centroids.extent();
    let axis = if ext.x >= ext.y && ext.x >= ext.z {
        0
    } else if ext.y >= ext.z {
        1
    } else {
        2
    };
    let mid = if ext[axis] <= 0.0 {
        // All centroids coincide: no plane separates them.
        if n <= LEAF_TARGET * 4 {
            return make_leaf(nodes);
        }
        n / 2
    } else {
        let lo = centroids.min[axis];
        let scale = BINS as f64 / ext[axis];
        let bin_of =
            |i: u32| (((boxes[i as usize].centre()[axis] - lo) * scale) as usize).min(BINS - 1);
        let mut bin_box = [Aabb::EMPTY; BINS];
        let mut bin_n = [0usize; BINS];
        for &i in items.iter() {
            let b = bin_of(i);
            bin_box[b] = bin_box[b].union(boxes[i as usize]);
            bin_n[b] += 1;
        }
        // Sweep from the right, then from the left, for the cost of each of BINS-1 planes.
        let mut right_cost = [0.0; BINS];
        let (mut acc, mut cnt) = (Aabb::EMPTY, 0);
        for b in (1..BINS).rev() {
            acc = acc.union(bin_box[b]);
            cnt += bin_n[b];
            right_cost[b] = acc.half_area() * cnt as f64;
        }
        let (mut acc, mut cnt) = (Aabb::EMPTY, 0);
        let mut best = (f64::INFINITY, 0);
        for b in 0..BINS - 1 {
            acc = acc.union(bin_box[b]);
            cnt += bin_n[b];
            let cost = acc.half_area() * cnt as f64 + right_cost[b + 1];
            if cnt > 0 && cnt < n && cost < best.0 {
                best = (cost, b + 1);
            }
        }
        let parent = bounds.half_area().max(f64::MIN_POSITIVE);
        let split_cost = TRAVERSAL_COST + best.0 / parent;
        if best.0.is_infinite() || (split_cost >= n as f64 && n <= LEAF_TARGET) {
            if n <= LEAF_TARGET * 4 {
                return make_leaf(nodes);
            }
            // Degenerate binning: fall back to a median split.
            items.sort_unstable_by(|&a, &b| {
                boxes[a as usize].centre()[axis].total_cmp(&boxes[b as usize].centre()[axis])
            });
            n / 2
        } else {
            let plane = best.1;
            // Partition in place: bins below `plane` to the left.
            let mut l = 0;
            for k in 0..n {
                if bin_of(items[k]) < plane {
                    items.swap(k, l);
                    l += 1;
                }
            }
            l
        }
    };
    let left = nodes.len();
    let child = Node {
        aabb: Aabb::EMPTY,
        first: 0,
        count: 0,
    };
    nodes.push(child);
    nodes.push(child);
    nodes[node] = Node {
        aabb: bounds,
        first: left as u32,
        count: 0,
    };
    split(boxes, order, nodes, left, start, start + mid, depth + 1);
    split(boxes, order, nodes, left + 1, start + mid, end, depth + 1);
}
