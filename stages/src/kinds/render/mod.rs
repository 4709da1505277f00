//! The `render` stage kind: renders every image of the scene with the trained field into label
//! maps: the learned semantic map (argmax S), the fixed-field map (argmax S_hat), the panoptic
//! map (fixed instance field rendered with the learned weights, masked by the argmax class),
//! depth, colour and confidence. Rays that cross no primitive are sky without any network
//! evaluation; compositing stops once transmittance is negligible. Moving objects are labelled
//! over the static field's maps from their per-frame boxes ([`moving`]). After an edit of the
//! primitives it renders again only the pixels whose ray can meet a changed primitive.

mod hull;
mod images;
mod moving;
mod params;
mod update;
mod writer;

use std::path::{Path, PathBuf};

use arrow::datatypes::{Float32Type, UInt16Type, UInt32Type, UInt8Type};
use arrow::record_batch::RecordBatch;

pub use params::{Colour, NovelView, RenderParams, NOVEL_CAMERA_BASE};

use crate::report::panoptic_colors;
use crate::stage::{
    Changed, InputSlot, Inputs, Lineage, Previous, Progress, Result, StageError, TableSet, Tables,
    TypedStage, Updated,
};
use crate::{pngio, tables};

pub struct Render;

impl TypedStage for Render {
    type Params = RenderParams;
    const KIND: &'static str = "render";
    // 11: moving objects labelled from their boxes (`dynamic_boxes`), trimmed by the pseudo
    // labels and the static depth; the same maps for a scene without moving objects.
    // 10: `adaptive: false` is `coarse_stride: 1` (one knob); the same maps.
    // 12: in images without pseudo labels, moving objects labelled from their hulls.
    // 13: with pseudo labels, a pixel takes the nearest box of its pseudo class, not the
    // nearest box (a rider's box overlaps its bicycle's); the same maps where boxes of
    // one class only meet.
    const VERSION: u32 = 14;
    const DESCRIPTION: &'static str =
        "renders semantic, fixed-field, panoptic, depth, colour and confidence maps for every image";
    const MOVED: &'static [(&'static str, &'static str)] =
        &[("adaptive", "coarse_stride (1 renders every pixel)")];
    const INPUTS: &'static [InputSlot] = &[
        InputSlot {
            name: "scene",
            tables: &[
                "scene_info",
                "cameras",
                "primitives",
                "dynamic_boxes",
                "images",
                "pseudo_labels",
            ],
            optional: false,
            doc: "the scene (the input images give the sky colour; moving objects are labelled \
                  from their boxes, trimmed by the pseudo labels)",
        },
        InputSlot {
            name: "rays",
            tables: &["ray_intervals"],
            optional: false,
            doc: "the sampling plan",
        },
        InputSlot {
            name: "train",
            tables: &["weights", "model"],
            optional: false,
            doc: "the trained field",
        },
    ];
    const OUTPUTS: &'static [&'static str] = &["label_maps"];
    const UPDATES: bool = true;
    const PARENT_INPUTS: &'static [(&'static str, &'static str)] = &[("scene", "primitives")];

    fn validate(p: &RenderParams) -> Result<()> {
        if p.chunk == 0 {
            return Err(StageError::Params("`chunk` must be at least 1".into()));
        }
        if !(p.coarse_stride.is_power_of_two() && p.coarse_stride <= 16) {
            return Err(StageError::Params(format!(
                "`coarse_stride` must be 1, 2, 4, 8 or 16, not {}",
                p.coarse_stride
            )));
        }
        if p.novel_views.len() > (u8::MAX - NOVEL_CAMERA_BASE) as usize {
            return Err(StageError::Params(format!(
                "`novel_views`: at most {} views",
                u8::MAX - NOVEL_CAMERA_BASE
            )));
        }
        for (i, v) in p.novel_views.iter().enumerate() {
            if !(v.translate.iter().all(|x| x.is_finite()) && v.yaw_deg.is_finite()) {
                return Err(StageError::Params(format!(
                    "`novel_views[{i}]`: translate and yaw_deg must be finite"
                )));
            }
        }
        Ok(())
    }

    fn run(&self, p: &RenderParams, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        Ok(images::render_all(p, inputs, progress, None)?.0)
    }

    fn can_update(
        &self,
        _: &RenderParams,
        changed: &Changed,
        lineage: &Lineage,
    ) -> std::result::Result<(), String> {
        update::can_update(changed, lineage)
    }

    fn update(
        &self,
        p: &RenderParams,
        inputs: &Inputs,
        previous: &Previous,
        progress: &dyn Progress,
    ) -> Result<Updated> {
        update::update(p, inputs, previous, progress)
    }

    fn export(&self, _: &RenderParams, t: &TableSet, dir: &Path) -> Result<Vec<PathBuf>> {
        let maps = t
            .get("label_maps")
            .ok_or_else(|| StageError::Input("missing table `label_maps`".into()))?;
        let mut files = Vec::new();
        for r in 0..maps.num_rows() {
            files.extend(export_label_maps(&maps.row(r)?, dir)?);
        }
        Ok(files)
    }
}

/// Writes KITTI-360-style PNGs of a `label_maps` table under `dir`: semantic/ (8-bit ids),
/// semantic_rgb/, instance/ (16-bit id*1000+instance), panoptic_rgb/, depth/ (16-bit,
/// metres*256), rgb/, named `{seq}_{frame}.png` as the KITTI-360 benchmark does (right-camera
/// files carry `_01`); and the labels of every scene camera again in the data set's own layout,
/// `data_2d_semantics/train/{seq}/image_{cam}/{semantic,semantic_rgb,instance}/{frame}.png`,
/// which `kitti360_scene` reads back as GT.
pub fn export_label_maps(t: &RecordBatch, dir: &Path) -> Result<Vec<PathBuf>> {
    let n = "label_maps";
    let seq = tables::get_strings(t, n, "sequence")?;
    let frames = tables::get_prim::<UInt32Type>(t, n, "frame")?;
    let cams = tables::get_prim::<UInt8Type>(t, n, "camera")?;
    let w = tables::get_prim::<UInt32Type>(t, n, "width")?;
    let h = tables::get_prim::<UInt32Type>(t, n, "height")?;
    let sem = tables::get_list::<UInt8Type>(t, n, "semantic")?;
    let inst = tables::get_list::<UInt16Type>(t, n, "instance")?;
    let depth = tables::get_list::<Float32Type>(t, n, "depth")?;
    let rgb = tables::get_binary(t, n, "rgb")?;
    let mut out = Vec::new();
    for r in 0..t.num_rows() {
        let name = pngio::label_file_name(seq.value(r), frames[r], cams[r]);
        let (w, h) = (w[r], h[r]);
        let files = [
            ("semantic", 0),
            ("semantic_rgb", 1),
            ("instance", 2),
            ("panoptic_rgb", 3),
            ("depth", 4),
            ("rgb", 5),
        ];
        for (sub, kind) in files {
            let path = dir.join(sub).join(&name);
            match kind {
                0 => pngio::write_gray8(&path, w, h, sem.row(r))?,
                1 => pngio::write_rgb8(&path, w, h, &pngio::colorize(sem.row(r)))?,
                2 => pngio::write_gray16(&path, w, h, inst.row(r))?,
                3 => pngio::write_rgb8(&path, w, h, &panoptic_colors(inst.row(r)))?,
                4 => pngio::write_gray16(&path, w, h, &pngio::depth_to_u16(depth.row(r)))?,
                _ if rgb.value(r).is_empty() => continue,
                _ => pngio::write_rgb8(&path, w, h, rgb.value(r))?,
            }
            out.push(path);
        }
        // Novel views (camera ids 10, 11, ...) are no KITTI-360 camera.
        if cams[r] < 10 {
            let base = dir
                .join("data_2d_semantics/train")
                .join(seq.value(r))
                .join(format!("image_{:02}", cams[r]));
            let file = format!("{:010}.png", frames[r]);
            let (sem_p, rgb_p, inst_p) = (
                base.join("semantic").join(&file),
                base.join("semantic_rgb").join(&file),
                base.join("instance").join(&file),
            );
            pngio::write_gray8(&sem_p, w, h, sem.row(r))?;
            pngio::write_rgb8(&rgb_p, w, h, &pngio::colorize(sem.row(r)))?;
            pngio::write_gray16(&inst_p, w, h, inst.row(r))?;
            out.extend([sem_p, rgb_p, inst_p]);
        }
    }
    Ok(out)
}
