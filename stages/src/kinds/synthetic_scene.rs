//! The `synthetic_scene` kind: the built-in synthetic street ([`crate::scene::synthetic`]) as
//! scene tables, exported in the KITTI-360 layout with previews.

use std::path::{Path, PathBuf};

use crate::scene::{
    kitti360_export, preview,
    synthetic::{write_tables, SceneParams},
};
use crate::stage::{InputSlot, Inputs, Progress, Result, TableSet, Tables, TypedStage};

/// The synthetic street scene kind.
pub struct SyntheticScene;

impl TypedStage for SyntheticScene {
    type Params = SceneParams;
    const KIND: &'static str = "synthetic_scene";
    // 3: `cameras` lists the cameras rendered (was `fisheye: true`); the same tables.
    const VERSION: u32 = 3;
    const DESCRIPTION: &'static str =
        "synthetic urban street: stereo images, GT labels and depth, 3D bounding primitives, \
         noisy pseudo labels, stereo and LiDAR depth";
    const INPUTS: &'static [InputSlot] = &[];
    const MOVED: &'static [(&'static str, &'static str)] = &[(
        "fisheye",
        "cameras (list the fisheye cameras: [image_00, image_01, image_02, image_03])",
    )];
    const OUTPUTS: &'static [&'static str] = &[
        "scene_info",
        "cameras",
        "primitives",
        "images",
        "pseudo_labels",
        "stereo_depth",
        "lidar_depth",
        "gt_semantic",
        "gt_instance",
        "gt_depth",
    ];

    fn validate(p: &SceneParams) -> Result<()> {
        p.validate()
    }

    fn run(&self, p: &SceneParams, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        write_tables(p, inputs, progress)
    }

    fn export(&self, _: &SceneParams, t: &TableSet, dir: &Path) -> Result<Vec<PathBuf>> {
        let t = t.whole_tables()?;
        let mut files = kitti360_export::write(&t, dir)?;
        files.extend(preview::write(&t, &dir.join("previews"))?);
        Ok(files)
    }
}
