//! The evaluate stage's parameters and the PQ conventions it reports.

use serde::{Deserialize, Serialize};

use crate::labels;

/// Parameters of the `evaluate` stage.
#[derive(Debug, Clone, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct EvaluateParams {
    /// Cameras scored (`image_00` .. `image_03`, or 0 .. 3); empty: the scene's, but `image_01`.
    /// Only the scene's evaluation images are scored (those of its evaluation frames that have
    /// GT). The right perspective camera is left out by default, as the paper scores the left
    /// one: it sees the left camera's view a baseline away.
    #[serde(deserialize_with = "crate::geometry::camera::camera_ids")]
    #[schemars(with = "Vec<crate::geometry::camera::CameraName>")]
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
    /// Evaluation frames scored; empty: every one the scene marks.
    /// With `render.frames`, the frames rendered, e.g. those in the middle of a longer window.
    pub frames: Vec<u32>,
}

impl EvaluateParams {
    /// Whether images of `camera` are scored.
    pub fn scores(&self, camera: u8) -> bool {
        if self.cameras.is_empty() {
            camera != 1
        } else {
            self.cameras.contains(&camera)
        }
    }
}

impl Default for EvaluateParams {
    fn default() -> Self {
        Self {
            cameras: Vec::new(),
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
