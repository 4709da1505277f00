//! The `render` stage kind: renders every image of the scene with the trained field into label
//! maps: the learned semantic map (argmax S), the fixed-field map (argmax S_hat), the panoptic
//! map (fixed instance field rendered with the learned weights, masked by the argmax class),
//! depth, colour and confidence. Rays that cross no primitive are sky without any network
//! evaluation; compositing stops once transmittance is negligible.

use std::path::{Path, PathBuf};

use arrow::array::Array;
use arrow::datatypes::{Float32Type, UInt16Type, UInt32Type, UInt8Type};
use arrow::record_batch::RecordBatch;
use serde::{Deserialize, Serialize};

use glam::DQuat;

use crate::geometry::{self, Camera, DAffine3, DVec3};
use crate::model::maps::{render_images, ImageMaps, Renderer};
use crate::model::{weights, EngineChoice};
use crate::report::panoptic_colors;
use crate::sampling::{ImageInfo, RaySet, SamplingParams};
use crate::stage::{InputSlot, Inputs, Progress, Result, StageError, Tables, TypedStage};
use crate::{pngio, tables};

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RenderParams {
    /// Rays evaluated per network call.
    pub chunk: usize,
    /// Samples inside primitives per ray; 0 = as in training.
    pub samples: usize,
    /// Inference engine: empty = the fused CPU path for grid fields (else the default burn
    /// backend); or a burn backend name (flex, ndarray, wgpu, cuda) or `fused`.
    pub backend: EngineChoice,
    /// Poses that are not in the scene, rendered too: rows with camera id
    /// [`NOVEL_CAMERA_BASE`] + their index (files `<seq>_<frame>_10.png`, ...). Their rays are
    /// intersected with the primitives here, with the `intersect` kind's default params.
    pub novel_views: Vec<NovelView>,
}

/// Camera id of the first novel view in `label_maps`.
pub const NOVEL_CAMERA_BASE: u8 = 10;

/// An existing camera of the scene, moved in its own frame (x right, y down, z forward); its
/// intrinsics and image size are kept.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NovelView {
    /// Frame and camera id (0 left, 1 right) of the camera it starts from.
    pub frame: u32,
    pub camera: u8,
    /// Translation in that camera's frame, metres.
    #[serde(default)]
    pub translate: [f64; 3],
    /// Rotation about the camera's y axis, degrees (positive turns right).
    #[serde(default)]
    pub yaw_deg: f64,
}

impl Default for RenderParams {
    fn default() -> Self {
        Self {
            chunk: 4096,
            samples: 0,
            backend: EngineChoice::default(),
            novel_views: Vec::new(),
        }
    }
}

pub struct Render;

/// The sequence name of the scene (`scene` when it has none).
fn sequence(inputs: &Inputs) -> Result<String> {
    let seq = tables::get_strings(
        inputs.table("scene", "scene_info")?,
        "scene_info",
        "sequence",
    )?;
    Ok(if seq.is_empty() {
        "scene".to_string()
    } else {
        seq.value(0).to_string()
    })
}

/// The cameras of the novel views: each a scene camera moved in its own frame.
fn novel_cameras(set: &RaySet, views: &[NovelView]) -> Result<Vec<(u32, u8, Camera)>> {
    views
        .iter()
        .enumerate()
        .map(|(k, v)| {
            let from = set
                .images
                .iter()
                .find(|im| (im.frame, im.camera) == (v.frame, v.camera))
                .ok_or_else(|| {
                    StageError::Params(format!(
                        "`novel_views[{k}]`: the scene has no image of frame {} camera {}",
                        v.frame, v.camera
                    ))
                })?;
            let mut cam = from.cam.clone();
            cam.cam_to_world *= DAffine3::from_rotation_translation(
                DQuat::from_rotation_y(v.yaw_deg.to_radians()),
                DVec3::from(v.translate),
            );
            Ok((v.frame, NOVEL_CAMERA_BASE + k as u8, cam))
        })
        .collect()
}

/// The `label_maps` table of rendered images.
fn label_maps_table(sequence: &str, maps: Vec<ImageMaps>) -> Result<RecordBatch> {
    let rows = maps.len();
    let (frame, camera, width, height): (Vec<u32>, Vec<u8>, Vec<u32>, Vec<u32>) = (
        maps.iter().map(|m| m.frame).collect(),
        maps.iter().map(|m| m.camera).collect(),
        maps.iter().map(|m| m.width).collect(),
        maps.iter().map(|m| m.height).collect(),
    );
    let (mut semantic, mut fixed, mut instance) = (Vec::new(), Vec::new(), Vec::new());
    let (mut depth, mut confidence, mut rgb) = (Vec::new(), Vec::new(), Vec::new());
    for m in maps {
        semantic.push(m.semantic);
        fixed.push(m.fixed);
        instance.push(m.instance);
        depth.push(m.depth);
        confidence.push(m.confidence);
        rgb.push(m.rgb);
    }
    tables::build(
        "label_maps",
        vec![
            tables::strings(vec![sequence; rows]),
            tables::prim::<UInt32Type>(frame),
            tables::prim::<UInt8Type>(camera),
            tables::prim::<UInt32Type>(width),
            tables::prim::<UInt32Type>(height),
            tables::list::<UInt8Type>(semantic),
            tables::list::<UInt8Type>(fixed),
            tables::list::<UInt16Type>(instance),
            tables::list::<Float32Type>(depth),
            tables::list::<Float32Type>(confidence),
            tables::binary(&rgb),
        ],
    )
}

impl TypedStage for Render {
    type Params = RenderParams;
    const KIND: &'static str = "render";
    const VERSION: u32 = 3;
    const DESCRIPTION: &'static str =
        "renders semantic, fixed-field, panoptic, depth, colour and confidence maps for every image";
    const INPUTS: &'static [InputSlot] = &[
        InputSlot {
            name: "scene",
            tables: &[
                "scene_info",
                "cameras",
                "primitives",
                "images",
                "pseudo_labels",
            ],
            optional: false,
            doc: "the scene",
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

    fn validate(p: &RenderParams) -> Result<()> {
        if p.chunk == 0 {
            return Err(StageError::Params("`chunk` must be at least 1".into()));
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
        let set = RaySet::from_inputs(inputs)?;
        let (info, rows) = weights::read(
            inputs.table("train", "weights")?,
            inputs.table("train", "model")?,
        )?;
        if info.classes != set.classes {
            return Err(StageError::Input(format!(
                "the field was trained for classes {:?} but this scene's primitives give {:?}",
                info.classes, set.classes
            )));
        }
        let engine = p.backend.resolve(&info.spec.config);
        let field = engine.field(info.spec.clone(), rows)?;
        let sampling = SamplingParams {
            samples: if p.samples > 0 {
                p.samples
            } else {
                info.sampling.samples
            },
            ..info.sampling.clone()
        };
        let r = Renderer {
            field: field.as_ref(),
            sampling: &sampling,
            chunk: p.chunk,
        };
        let novel = if p.novel_views.is_empty() {
            None
        } else {
            let prims = geometry::primitives_from_table(inputs.table("scene", "primitives")?)?;
            Some(RaySet::for_cameras(
                &set,
                &prims,
                &novel_cameras(&set, &p.novel_views)?,
            ))
        };
        let total_rays = (set.len() + novel.as_ref().map_or(0, RaySet::len)) as u64;
        let mut done = 0u64;
        let mut report = |rays: u64, im: &ImageInfo| {
            done += rays;
            progress.update(
                done,
                total_rays,
                &format!("frame {} cam {}", im.frame, im.camera),
            );
        };
        let (mut maps, scene_sky) = render_images(&r, &set, None, &mut report)?;
        if let Some(novel) = &novel {
            maps.extend(render_images(&r, novel, Some(scene_sky), &mut report)?.0);
        }
        let t = label_maps_table(&sequence(inputs)?, maps)?;
        Ok(Tables::from([("label_maps".to_string(), t)]))
    }

    fn export(&self, _: &RenderParams, t: &Tables, dir: &Path) -> Result<Vec<PathBuf>> {
        export_label_maps(&t["label_maps"], dir)
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
