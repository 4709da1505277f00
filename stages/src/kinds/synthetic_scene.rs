//! The `synthetic_scene` kind: the built-in synthetic street ([`crate::scene::synthetic`]) as
//! scene tables, exported in the KITTI-360 layout with previews.

use std::path::{Path, PathBuf};

use crate::scene::{
    kitti360_export, preview,
    synthetic::{annotation_tables, write_tables, SceneParams},
};
use crate::stage::{
    InputSlot, Inputs, Previous, Progress, Result, TableSet, Tables, TypedStage, Updated,
};
use crate::{tables, StageError};
use arrow::datatypes::UInt8Type;

/// The synthetic street scene kind.
pub struct SyntheticScene;

impl TypedStage for SyntheticScene {
    type Params = SceneParams;
    const KIND: &'static str = "synthetic_scene";
    // 3: `cameras` lists the cameras rendered (was `fisheye: true`); the same tables.
    // 4: the table `dynamic_boxes` (moving objects, `moving_objects`).
    const VERSION: u32 = 4;
    const DESCRIPTION: &'static str =
        "synthetic urban street: stereo images, GT labels and depth, 3D bounding primitives \
         (and moving objects' boxes), noisy pseudo labels, stereo and LiDAR depth";
    const INPUTS: &'static [InputSlot] = &[];
    const MOVED: &'static [(&'static str, &'static str)] = &[(
        "fisheye",
        "cameras (list the fisheye cameras: [image_00, image_01, image_02, image_03])",
    )];
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

    // An edit of the annotation (`edits`) rewrites the primitives and keeps the street's
    // images, labels and depth.
    const UPDATES: bool = true;
    const EDITABLE: &'static [&'static str] = &["edits"];

    fn validate(p: &SceneParams) -> Result<()> {
        p.validate()
    }

    fn update(
        &self,
        p: &SceneParams,
        _: &Inputs,
        previous: &Previous,
        _: &dyn Progress,
    ) -> Result<Updated> {
        Ok(Updated {
            tables: edited_tables(p, previous.outputs)?,
            redone: "the annotation edited: primitives and scene_info written again, the \
                     images, labels and depth kept"
                .into(),
        })
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

/// The tables an edit of the annotation changes (`primitives`, `scene_info`; `dynamic_boxes`
/// written again, the same), from `previous`,
/// the same street generated with other edits: the images, labels and depth stay the same (the
/// edits change the annotation only), so the classes of its GT images carry over.
fn edited_tables(p: &SceneParams, previous: &TableSet) -> Result<Tables> {
    let layout = crate::scene::layout::build(&p.layout_params()?);
    let gt = previous
        .get("gt_semantic")
        .ok_or_else(|| StageError::Failed("the previous scene has no gt_semantic".into()))?;
    let mut seen = [false; 256];
    for i in 0..gt.num_rows() {
        let row = gt.rows(i..i + 1, Some(&["labels"]))?;
        let labels = tables::get_list::<UInt8Type>(&row, "gt_semantic", "labels")?;
        for &l in labels.row(0) {
            seen[l as usize] = true;
        }
    }
    let mut t = Tables::new();
    annotation_tables(p, &layout, seen, &mut t)?;
    Ok(t)
}
