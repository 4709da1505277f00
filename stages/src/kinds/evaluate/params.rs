//! The evaluate stage's parameters and the PQ conventions it reports.

use serde::{Deserialize, Serialize};

use crate::labels;

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EvaluateParams {
    /// Cameras evaluated (0 = left, 1 = right, 2 and 3 the fisheye cameras); KITTI-360 has GT
    /// for the left camera only.
    #[serde(deserialize_with = "crate::geometry::camera::camera_ids")]
    pub cameras: Vec<u8>,
    /// Evaluated classes (label ids); default: the paper's 14 classes.
    pub classes: Vec<u8>,
    /// Thing classes for PQ; default: building, car, caravan, trailer, box.
    pub things: Vec<u8>,
    /// GT segments under this many pixels are void; predicted ones are relabelled sky.
    pub min_segment_px: usize,
    /// Matching distance of LiDAR points for multi-view consistency, metres.
    pub mc_distance: f64,
    /// Depth metrics use LiDAR pixels closer than this, metres.
    pub max_depth: f64,
    /// Evaluation frames scored (default, empty: every one the scene marks); with
    /// `render.frames`, the frames rendered, e.g. those in the middle of a longer window.
    pub frames: Vec<u32>,
}

impl Default for EvaluateParams {
    fn default() -> Self {
        Self {
            cameras: vec![0],
            classes: labels::PAPER_CLASSES.to_vec(),
            things: labels::PAPER_THINGS.to_vec(),
            min_segment_px: 100,
            mc_distance: 0.1,
            max_depth: 100.0,
            frames: Vec::new(),
        }
    }
}

/// Metric names ending in this (`pq_panopticapi`, `pq_things_panopticapi`, ...) score the
/// panoptic maps as panopticapi does: every predicted segment counts, however small. Without
/// it (`pq`, ...): the Panoptic NeRF paper's convention, where predicted segments under
/// `min_segment_px` become sky first. In both, GT segments under it are void (the exported GT).
pub const PANOPTICAPI_SUFFIX: &str = "_panopticapi";

/// What each PQ convention means, as `metrics.json` states it.
pub const PQ_CONVENTIONS: &[(&str, &str)] = &[
    (
        "pq",
        "Panoptic NeRF paper: predicted segments under min_segment_px (100) pixels are relabelled sky and GT segments under it are void, before matching",
    ),
    (
        "pq_panopticapi",
        "panopticapi (COCO; the Cityscapes and KITTI-360 scripts): predicted segments as they are, no relabelling; the same GT (segments under min_segment_px void, as exported)",
    ),
];
