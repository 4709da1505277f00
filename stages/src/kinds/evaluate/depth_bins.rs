//! The bins of the depth breakdown: which distance band, class, boundary, rendering and fixed
//! field case a LiDAR pixel belongs to.

use crate::{
    geometry::{Bvh, CameraRow, Primitive},
    labels,
};

/// A bin of the depth breakdown: (group order, bin order, group, bin).
pub(super) type BinKey = (u8, u16, &'static str, &'static str);

/// Distance bands of the depth breakdown: (lower bound of the LiDAR depth in metres, name);
/// the last one ends at `max_depth`.
pub(super) const DEPTH_BANDS: [(f64, &str); 4] = [
    (0.0, "0-10 m"),
    (10.0, "10-20 m"),
    (20.0, "20-40 m"),
    (40.0, ">= 40 m"),
];

/// The bins of LiDAR pixel `i` of image `c`: all pixels; its distance band; its GT class;
/// whether it lies on a GT class boundary (a different GT class among its 8 neighbours);
/// whether a depth was rendered (opacity > 0.5); how many classes the fixed field has at the
/// LiDAR point (the primitives containing it); whether the pixel's pseudo label (`pseudo`,
/// None: the image has none) is right or wrong, on a class boundary or inside a region.
#[allow(clippy::too_many_arguments)]
pub(super) fn depth_bin_keys(
    c: &CameraRow,
    i: usize,
    lidar: f32,
    rendered: f32,
    gsem: &[u8],
    boundary: bool,
    pseudo: Option<u8>,
    prims: &[Primitive],
    bvh: &Bvh,
    inside: &mut Vec<u32>,
) -> [BinKey; 7] {
    let w = c.cam.width as usize;
    let (x, y) = (i % w, i / w);
    let g = f64::from(lidar);
    let band = DEPTH_BANDS
        .iter()
        .rposition(|&(lo, _)| g >= lo)
        .unwrap_or(0);
    let class = gsem[i];
    let class_name = labels::by_id(class).map_or("?", |l| l.name);
    let fixed = match c.cam.ray_and_dir_cam(x as f64 + 0.5, y as f64 + 0.5) {
        Some((ray, d_cam)) => {
            bvh.containing(prims, ray.at(g / c.cam.depth_scale(d_cam)), inside);
            let mut labels_at = inside.iter().map(|&p| prims[p as usize].label);
            match labels_at.next() {
                None => (2, "in no primitive"),
                Some(first) if labels_at.all(|l| l == first) => (0, "one class"),
                Some(_) => (1, "several classes (overlapping primitives)"),
            }
        }
        None => (2, "in no primitive"),
    };
    let drawn = rendered > 0.0 && rendered.is_finite();
    [
        (0, 0, "all", "all"),
        (1, band as u16, "distance", DEPTH_BANDS[band].1),
        (2, u16::from(class), "class", class_name),
        (
            3,
            u16::from(boundary),
            "boundary",
            if boundary {
                "on a class boundary (GT, 8-neighbourhood)"
            } else {
                "inside a region"
            },
        ),
        (
            4,
            u16::from(!drawn),
            "rendered",
            if drawn {
                "depth rendered"
            } else {
                "no depth rendered (opacity <= 0.5: scored as 0 m)"
            },
        ),
        (5, fixed.0, "fixed field", fixed.1),
        match (pseudo.filter(|&l| l != labels::UNLABELED), boundary) {
            (None, _) => (6, 4, "pseudo label", "no pseudo label"),
            (Some(l), true) if l == class => (6, 0, "pseudo label", "right, on a class boundary"),
            (Some(_), true) => (6, 1, "pseudo label", "wrong, on a class boundary"),
            (Some(l), false) if l == class => (6, 2, "pseudo label", "right, inside a region"),
            (Some(_), false) => (6, 3, "pseudo label", "wrong, inside a region"),
        },
    ]
}
