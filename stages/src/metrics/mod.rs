//! The evaluation metrics of the project (REFERENCE.md section 3), as pure functions over
//! in-memory maps: no I/O, no tables. Stage kinds that evaluate a run read their inputs, call
//! these, and write the numbers out.
//!
//! - [`confusion`]: confusion matrix, per-class IoU, mIoU, pixel accuracy.
//! - [`panoptic`]: panoptic quality (PQ / SQ / RQ, Kirillov et al. 2019) and PQ-dagger
//!   (Porzi et al. 2019), accumulated over frames.
//! - [`consistency`]: multi-view consistency of labels through LiDAR points.
//! - [`depth`]: depth RMSE and delta < 1.25, accumulated over frames.
//!
//! Conventions shared by all of them:
//! - Maps are row-major, `width * height` values, pixel `(x, y)` at index `y * width + x`.
//! - Label maps hold KITTI-360 label ids (`u8`, [`crate::labels`]); id 0 is unlabeled (void).
//!   Pixels whose ground truth is void are ignored.
//! - Instance maps hold `id * 1000 + instance` ([`crate::labels::INSTANCE_FACTOR`]) as `u16`
//!   (KITTI-360's PNGs) or `u32`; a value below 1000 (KITTI-360 stores the bare label id for
//!   stuff) means instance 0, i.e. no instance.
//! - Everything that is summed over frames is accumulated as sums and counts (never a mean of
//!   per-frame means), and accumulators merge, so frames can be evaluated in parallel.

pub mod confusion;
pub mod consistency;
pub mod depth;
pub mod detection;
pub mod error;
pub mod panoptic;
pub mod scores;

pub use confusion::{ClassIou, ConfusionMatrix};
pub use consistency::{
    cross_view_consistency, multiview_consistency, Consistency, LabelledView, Pinhole,
};
pub use depth::{BinResult, DepthAccumulator, DepthBins, DepthMetrics};
pub use error::{instance_number, MetricError};
pub use panoptic::{
    relabel_small_segments, ClassPq, PanopticAccumulator, PanopticConfig, PanopticResult, PqSummary,
};
