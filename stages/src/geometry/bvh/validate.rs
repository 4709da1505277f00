//! Invariants of a built hierarchy, checked by tests (and callable after deserialising one).

use super::Bvh;
use crate::geometry::Primitive;

impl Bvh {
    /// Checks: every primitive appears in exactly one leaf; every node's box holds its
    /// children's boxes (interior) or its primitives' boxes (leaf); child links are in range
    /// and each node but the root is some node's child exactly once. Returns the first violation.
    pub fn validate(&self, prims: &[Primitive]) -> Result<(), String> {
        if prims.is_empty() {
            return if self.nodes.is_empty() {
                Ok(())
            } else {
                Err("nodes for an empty scene".into())
            };
        }
        let mut seen = vec![0u32; prims.len()];
        let mut parent_count = vec![0u32; self.nodes.len()];
        for (i, n) in self.nodes.iter().enumerate() {
            if n.count == 0 {
                let (a, b) = (n.first as usize, n.first as usize + 1);
                if a <= i || b >= self.nodes.len() {
                    return Err(format!(
                        "node {i}: child index {a} out of range or not after it"
                    ));
                }
                for c in [a, b] {
                    parent_count[c] += 1;
                    if !n.aabb.contains_box(&self.nodes[c].aabb) {
                        return Err(format!("node {i}: box does not hold child {c}"));
                    }
                }
            } else {
                let r = n.first as usize..(n.first + n.count) as usize;
                if r.end > self.order.len() {
                    return Err(format!("leaf {i}: range {r:?} out of bounds"));
                }
                for &p in &self.order[r] {
                    seen[p as usize] += 1;
                    if !n.aabb.contains_box(&prims[p as usize].aabb()) {
                        return Err(format!("leaf {i}: box does not hold primitive {p}"));
                    }
                }
            }
        }
        if let Some(p) = seen.iter().position(|&c| c != 1) {
            return Err(format!("primitive {p} is in {} leaves", seen[p]));
        }
        if let Some(i) = (1..self.nodes.len()).find(|&i| parent_count[i] != 1) {
            return Err(format!("node {i} has {} parents", parent_count[i]));
        }
        Ok(())
    }
}
