//! The `stereo_depth` kind: weak depth of the left images by semi-global matching
//! ([`crate::scene::stereo`]), for scenes that bring no depth of their own (KITTI-360).

use std::collections::BTreeMap;

use arrow::datatypes::{Float32Type, UInt32Type, UInt8Type};

use crate::geometry::cameras_from_table;
use crate::scene::io::{image_keys, scene_info};
use crate::scene::stereo::{depth_from_disparity, grey, Matcher, StereoParams};
use crate::stage::{
    Changed, InputSlot, Inputs, Lineage, Previous, Progress, Result, StageError, Tables,
    TypedStage, Updated,
};
use crate::tables;

/// The SGM stereo stage kind.
pub struct StereoDepth;

impl TypedStage for StereoDepth {
    type Params = StereoParams;
    const KIND: &'static str = "stereo_depth";
    const VERSION: u32 = 1;
    const DESCRIPTION: &'static str =
        "weak depth of the left images by semi-global matching on the rectified stereo pairs \
         (census cost, 8 paths, left-right check, sub-pixel), near range only";
    const INPUTS: &'static [InputSlot] = &[InputSlot {
        name: "scene",
        tables: &["scene_info", "cameras", "images"],
        optional: false,
        doc: "rectified stereo images, intrinsics and the baseline",
    }];
    const OUTPUTS: &'static [&'static str] = &["stereo_depth"];
    const UPDATES: bool = true;
    const PARENT_INPUTS: &'static [(&'static str, &'static str)] = &[("scene", "scene_info")];

    fn validate(p: &StereoParams) -> Result<()> {
        p.validate()
    }

    /// Depth depends on the images, the cameras and the baseline: an edit of the primitives
    /// (which may change the scene's list of classes) leaves it as it was.
    fn can_update(
        &self,
        _: &StereoParams,
        changed: &Changed,
        _: &Lineage,
    ) -> std::result::Result<(), String> {
        match changed.values().flatten().find(|t| *t != "scene_info") {
            None => Ok(()),
            Some(t) => Err(format!("the scene's `{t}` changed")),
        }
    }

    fn update(
        &self,
        p: &StereoParams,
        inputs: &Inputs,
        previous: &Previous,
        progress: &dyn Progress,
    ) -> Result<Updated> {
        let baseline = |t: &arrow::record_batch::RecordBatch| -> Result<f64> {
            Ok(scene_info(&Tables::from([("scene_info".to_string(), t.clone())]))?.baseline)
        };
        let before = previous.input("scene", "scene_info")?.whole()?;
        if baseline(before)? != baseline(inputs.table("scene", "scene_info")?)? {
            let tables = TypedStage::run(self, p, inputs, progress)?;
            return Ok(Updated {
                tables,
                redone: "every pair matched again (the baseline changed)".into(),
            });
        }
        let depth = previous.output("stereo_depth")?.whole()?.clone();
        Ok(Updated {
            redone: format!("0 of {} pairs matched again", depth.num_rows()),
            tables: Tables::from([("stereo_depth".to_string(), depth)]),
        })
    }

    fn run(&self, p: &StereoParams, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        let info = scene_info(&Tables::from([(
            "scene_info".to_string(),
            inputs.table("scene", "scene_info")?.clone(),
        )]))?;
        let cams = cameras_from_table(inputs.table("scene", "cameras")?)?;
        let images = inputs.table("scene", "images")?;
        let keys = image_keys(images, "images")?;
        let rgb = tables::get_binary(images, "images", "rgb")?;
        let index: BTreeMap<(u32, u8), usize> = keys
            .iter()
            .enumerate()
            .map(|(i, k)| ((k.0, k.1), i))
            .collect();
        let lefts: Vec<_> = cams.iter().filter(|c| c.camera == 0).collect();
        let mut rows = Vec::new();
        let mut matcher = Matcher::default();
        for (n, c) in lefts.iter().enumerate() {
            progress.update(n as u64, lefts.len() as u64, "matching");
            let (Some(&li), Some(&ri)) = (index.get(&(c.frame, 0)), index.get(&(c.frame, 1)))
            else {
                return Err(StageError::Input(format!(
                    "frame {}: the `images` table needs both the left and the right image",
                    c.frame
                )));
            };
            let (w, h) = (c.cam.width as usize, c.cam.height as usize);
            let (l, r) = (rgb.value(li), rgb.value(ri));
            if l.len() != w * h * 3 || r.len() != w * h * 3 {
                return Err(StageError::Input(format!(
                    "frame {}: images are not {w}x{h} RGB as the cameras table says",
                    c.frame
                )));
            }
            let disp = matcher.disparity(&grey(l), &grey(r), w, h, p);
            let depth = depth_from_disparity(&disp, c.cam.fx, info.baseline, p.max_depth_m);
            rows.push(((c.frame, 0u8, w as u32, h as u32), depth));
        }
        depth_tables(rows)
    }
}

/// One row of a `stereo_depth` table: (frame, camera, width, height) and the depth values.
pub type DepthRow = ((u32, u8, u32, u32), Vec<f32>);

/// The `stereo_depth` output of `rows`.
pub fn depth_tables(rows: Vec<DepthRow>) -> Result<Tables> {
    let t = tables::build(
        "stereo_depth",
        vec![
            tables::prim::<UInt32Type>(rows.iter().map(|r| r.0 .0)),
            tables::prim::<UInt8Type>(rows.iter().map(|r| r.0 .1)),
            tables::prim::<UInt32Type>(rows.iter().map(|r| r.0 .2)),
            tables::prim::<UInt32Type>(rows.iter().map(|r| r.0 .3)),
            tables::list::<Float32Type>(rows.into_iter().map(|r| r.1)),
        ],
    )?;
    Ok(Tables::from([("stereo_depth".to_string(), t)]))
}
