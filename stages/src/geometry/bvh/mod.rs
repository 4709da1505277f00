//! A bounding volume hierarchy over primitive bounds: rays and points traverse it instead of
//! testing every primitive.
//!
//! Why our own and not a crate: `parry3d` answers first-hit queries only, and the sampling plan
//! needs *every* entry/exit interval along a ray; `bvh` (0.13) would do but pulls `nalgebra`
//! (minutes of compile time on the project's 2-core machine) for ~200 lines of code. This one is
//! a flat array of nodes built by binned SAH, traversed with a fixed-size stack (no allocation
//! per ray). Like parry's, it knows only leaf indices and calls back into [`Primitive`] for the
//! exact test. Build, traversal and invariant checking live in separate files.

mod build;
mod traverse;
mod validate;

use super::Aabb;

/// Maximum primitives in a leaf the builder aims for (SAH may stop earlier).
const LEAF_TARGET: usize = 4;
/// Depth bound; the traversal stack holds this many entries.
const MAX_DEPTH: usize = 60;

/// One node: a leaf holds `order[first .. first + count]`; an interior node (`count == 0`) has
/// its children at `nodes[first]` and `nodes[first + 1]`.
#[derive(Clone, Copy, Debug)]
struct Node {
    aabb: Aabb,
    first: u32,
    count: u32,
}

/// The hierarchy over one primitive slice; queries take the same slice again.
#[derive(Clone, Debug, Default)]
pub struct Bvh {
    nodes: Vec<Node>,
    /// Primitive indices, grouped by leaf.
    order: Vec<u32>,
    /// `boxes[k]` = bounds of primitive `order[k]`: leaves test these (contiguous, cheap)
    /// before calling the exact primitive test.
    boxes: Vec<Aabb>,
}

impl Bvh {
    /// Number of nodes (0 for an empty scene).
    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// Depth of the deepest leaf (root = 1; 0 for an empty scene).
    pub fn depth(&self) -> usize {
        fn go(b: &Bvh, i: usize) -> usize {
            let n = &b.nodes[i];
            if n.count > 0 {
                1
            } else {
                1 + go(b, n.first as usize).max(go(b, n.first as usize + 1))
            }
        }
        if self.nodes.is_empty() {
            0
        } else {
            go(self, 0)
        }
    }
}
