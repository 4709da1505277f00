//! Every stage kind, by name. The runner knows stages only through this.

use super::{
    aggregate, evaluate, intersect, kitti360_scene, motion_stereo, render, report, stereo_depth,
    synthetic_scene, testing, train,
};
use crate::stage::Stage;

/// Every stage kind, by name.
pub fn registry() -> Vec<Box<dyn Stage>> {
    let mut all: Vec<Box<dyn Stage>> = vec![
        Box::new(synthetic_scene::SyntheticScene),
        Box::new(kitti360_scene::Kitti360Scene),
        Box::new(stereo_depth::StereoDepth),
        Box::new(motion_stereo::MotionStereo),
        Box::new(intersect::Intersect),
        Box::new(train::Train),
        Box::new(render::Render),
        Box::new(evaluate::Evaluate),
        Box::new(report::Report),
        Box::new(aggregate::Aggregate),
    ];
    all.extend(testing::kinds());
    all
}

/// Looks up one kind by name.
pub fn find(kind: &str) -> Option<Box<dyn Stage>> {
    registry().into_iter().find(|s| s.kind() == kind)
}
