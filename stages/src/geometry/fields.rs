//! The fixed fields of Panoptic NeRF, read off the primitives (paper: s_beta and t_beta).
//!
//! - Fixed semantic field `s_beta(x)`: a probability vector over a class list. Inside one
//!   primitive: one-hot of its class. Inside several primitives: equal probability over their
//!   *distinct* classes (two overlapping cars give one-hot "car"; a car inside a building
//!   volume gives 0.5 / 0.5). Outside every primitive: the all-zero vector (no class; in
//!   particular *not* sky: sky only comes from the sky interval of the sampling plan).
//!   Enclosing primitives whose class is not in the list are ignored.
//! - Fixed instance field `t_beta(x)`: the same over the scene's things, each identified by
//!   (label, instance) with instance > 0; stuff primitives contribute nothing.

use std::cell::RefCell;

use super::{Bvh, Primitive};
use glam::DVec3;

thread_local! {
    static IDS: RefCell<Vec<u32>> = const { RefCell::new(Vec::new()) };
}

/// Writes `s_beta(p)` over `classes` (label ids, in the caller's class-index order) into `out`
/// (`out.len() == classes.len()`). All zeros = outside everything.
pub fn fixed_semantic(prims: &[Primitive], bvh: &Bvh, p: DVec3, classes: &[u8], out: &mut [f32]) {
    assert_eq!(out.len(), classes.len(), "one output per class");
    spread(prims, bvh, p, out, |pr| {
        classes.iter().position(|&c| c == pr.label)
    });
}

/// Writes `t_beta(p)` over `things` (`(label, instance)` pairs in the caller's order, e.g. from
/// [`scene_things`]) into `out`. All zeros = inside no thing.
pub fn fixed_instance(
    prims: &[Primitive],
    bvh: &Bvh,
    p: DVec3,
    things: &[(u8, u32)],
    out: &mut [f32],
) {
    assert_eq!(out.len(), things.len(), "one output per thing");
    spread(prims, bvh, p, out, |pr| {
        (pr.instance > 0)
            .then(|| things.iter().position(|&t| t == (pr.label, pr.instance)))
            .flatten()
    });
}

/// The scene's things, `(label, instance)` with instance > 0, sorted and unique.
pub fn scene_things(prims: &[Primitive]) -> Vec<(u8, u32)> {
    let mut t: Vec<(u8, u32)> = prims
        .iter()
        .filter(|p| p.instance > 0)
        .map(|p| (p.label, p.instance))
        .collect();
    t.sort_unstable();
    t.dedup();
    t
}

/// Equal probability over the distinct slots `slot_of` gives the primitives containing `p`.
fn spread(
    prims: &[Primitive],
    bvh: &Bvh,
    p: DVec3,
    out: &mut [f32],
    slot_of: impl Fn(&Primitive) -> Option<usize>,
) {
    out.fill(0.0);
    IDS.with(|ids| {
        let mut ids = ids.borrow_mut();
        bvh.containing(prims, p, &mut ids);
        let mut n = 0;
        for &i in ids.iter() {
            if let Some(s) = slot_of(&prims[i as usize]) {
                if out[s] == 0.0 {
                    out[s] = 1.0;
                    n += 1;
                }
            }
        }
        if n > 1 {
            let w = 1.0 / n as f32;
            out.iter_mut().filter(|v| **v > 0.0).for_each(|v| *v = w);
        }
    });
}
