//! Test inputs of the evaluation: rendered maps made from a scene's GT.

use std::collections::HashSet;

use arrow::datatypes::{Float32Type, UInt16Type, UInt8Type};

use crate::{tables, Tables};

/// `label_maps` that copy the scene's GT, with `moving_as` (if any) on the pixels of the
/// moving `objects` (their values in the instance maps).
pub(crate) fn label_maps(scene: &Tables, objects: &HashSet<u16>, moving_as: Option<u8>) -> Tables {
    let gs = &scene["gt_semantic"];
    let gi = &scene["gt_instance"];
    let gd = &scene["gt_depth"];
    let sem = tables::get_list::<UInt8Type>(gs, "gt_semantic", "labels").unwrap();
    let inst = tables::get_list::<UInt16Type>(gi, "gt_instance", "instances").unwrap();
    let depth = tables::get_list::<Float32Type>(gd, "gt_depth", "depth").unwrap();
    let n = gs.num_rows();
    let mut semantic = Vec::new();
    for r in 0..n {
        let mut s = sem.row(r).to_vec();
        if let Some(l) = moving_as {
            for (v, i) in s.iter_mut().zip(inst.row(r)) {
                if objects.contains(i) {
                    *v = l;
                }
            }
        }
        semantic.push(s);
    }
    let col = |name: &str| gs.column_by_name(name).unwrap().clone();
    let batch = tables::build(
        "label_maps",
        vec![
            tables::strings(vec!["seq"; n]),
            col("frame"),
            col("camera"),
            col("width"),
            col("height"),
            tables::list::<UInt8Type>(semantic),
            tables::list::<UInt8Type>((0..n).map(|r| sem.row(r).to_vec())),
            tables::list::<UInt16Type>((0..n).map(|r| inst.row(r).to_vec())),
            tables::list::<Float32Type>((0..n).map(|r| depth.row(r).to_vec())),
            tables::list::<Float32Type>((0..n).map(|r| vec![1.0; sem.row(r).len()])),
            tables::binary((0..n).map(|_| Vec::<u8>::new())),
        ],
    )
    .unwrap();
    Tables::from([("label_maps".to_string(), batch)])
}
