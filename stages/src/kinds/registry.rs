//! Every stage kind, by name. The runner knows stages only through this.

use crate::stage::Stage;

/// Every stage kind, by name.
pub fn registry() -> Vec<Box<dyn Stage>> {
    let mut all: Vec<Box<dyn Stage>> = vec![
        Box::new(crate::scene::SyntheticScene),
        Box::new(crate::scene::kitti360::Kitti360Scene),
        Box::new(crate::stereo::StereoDepth),
        Box::new(crate::rays::Intersect),
        Box::new(crate::train_stage::Train),
        Box::new(crate::render::Render),
        Box::new(crate::evaluate::Evaluate),
        Box::new(crate::report::Report),
        Box::new(crate::aggregate::Aggregate),
    ];
    all.extend(crate::testing::kinds());
    all
}

/// Looks up one kind by name.
pub fn find(kind: &str) -> Option<Box<dyn Stage>> {
    registry().into_iter().find(|s| s.kind() == kind)
}
