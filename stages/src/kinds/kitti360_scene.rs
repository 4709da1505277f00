//! The `kitti360_scene` kind: a KITTI-360 sequence (or data in its layout) read into scene
//! tables ([`crate::scene::kitti360`]); its files are declared inputs, hashed into the key.

use std::path::{Path, PathBuf};

use crate::scene::kitti360::{input_files, load, Kitti360Params};
use crate::scene::preview;
use crate::stage::{InputSlot, Inputs, Progress, Result, TableSet, Tables, TypedStage};

/// The KITTI-360 loader kind.
pub struct Kitti360Scene;

impl TypedStage for Kitti360Scene {
    type Params = Kitti360Params;
    const KIND: &'static str = "kitti360_scene";
    const VERSION: u32 = 3;
    const DESCRIPTION: &'static str =
        "a KITTI-360 sequence (or data in its layout): posed stereo images, 3D bounding \
         primitives near the chosen frames, pseudo labels, optional stereo depth, GT and LiDAR";
    const INPUTS: &'static [InputSlot] = &[];
    const OUTPUTS: &'static [&'static str] = &[
        "scene_info",
        "cameras",
        "primitives",
        "dynamic_boxes",
        "images",
        "pseudo_labels",
        "stereo_depth",
        "lidar_depth",
        "gt_semantic",
        "gt_instance",
        "gt_depth",
    ];

    fn validate(p: &Kitti360Params) -> Result<()> {
        p.validate()
    }

    fn run(&self, p: &Kitti360Params, _: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        load(p, progress)
    }

    fn external_inputs(&self, p: &Kitti360Params) -> Result<Vec<PathBuf>> {
        input_files(p)
    }

    fn export(&self, _: &Kitti360Params, t: &TableSet, dir: &Path) -> Result<Vec<PathBuf>> {
        preview::write(&t.whole_tables()?, &dir.join("previews"))
    }
}
