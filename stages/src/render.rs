//! The `render` stage kind: renders every image of the scene with the trained field into label
//! maps: the learned semantic map (argmax S), the fixed-field map (argmax S_hat), the panoptic
//! map (fixed instance field rendered with the learned weights, masked by the argmax class),
//! depth, colour and confidence. Rays that cross no primitive are sky without any network
//! evaluation; compositing stops once transmittance is negligible.

use std::path::{Path, PathBuf};

use arrow::{
    array::Array,
    datatypes::{Float32Type, UInt16Type, UInt32Type, UInt8Type},
};
use burn::tensor::Tensor;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::{
    compose::{composite_ray, Scratch},
    field::{FieldHead, RadianceField},
    fused::{FusedField, Heads},
    geometry, labels, pngio,
    rays::{self, IntersectParams},
    sampling::{self, RaySet, SamplingParams},
    tables,
    train_stage::load_field,
    InputSlot, Inputs, Progress, Result, StageError, Tables, TypedStage,
};

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RenderParams {
    /// Rays evaluated per network call.
    pub chunk: usize,
    /// Samples inside primitives per ray; 0 = as in training.
    pub samples: usize,
    /// Inference backend: empty = the fused CPU path for grid fields (else the default burn
    /// backend); or a burn backend name (flex, ndarray, wgpu, cuda) or `fused`.
    pub backend: String,
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
            backend: String::new(),
            novel_views: Vec::new(),
        }
    }
}

pub struct Render;

/// Per-image output columns.
#[derive(Default)]
struct Maps {
    frame: Vec<u32>,
    camera: Vec<u8>,
    width: Vec<u32>,
    height: Vec<u32>,
    semantic: Vec<Vec<u8>>,
    fixed: Vec<Vec<u8>>,
    instance: Vec<Vec<u16>>,
    depth: Vec<Vec<f32>>,
    confidence: Vec<Vec<f32>>,
    rgb: Vec<Vec<u8>>,
}

fn read(t: Tensor<2>) -> Vec<f32> {
    t.into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .unwrap_or_default()
}

/// Field outputs for a batch of samples: (sigma [R*S], rgb [R*S*3], logits [R*S*C]).
fn evaluate_field(
    field: &RadianceField,
    fused: Option<&FusedField>,
    b: &sampling::SampleBatch,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    if let Some(f) = fused {
        let heads = Heads {
            rgb: true,
            semantics: true,
        };
        return f.evaluate(&b.positions, &b.dirs, b.samples, heads);
    }
    let input = field.prepare(&b.positions, Some(&b.dirs), b.samples);
    let o = field.forward(&input, &[FieldHead::Rgb, FieldHead::Semantics]);
    let sigma = o
        .density
        .into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .unwrap_or_default();
    let rgb = o.rgb.map(read).unwrap_or_default();
    let logits = o.logits.map(read).unwrap_or_default();
    (sigma, rgb, logits)
}

/// What rendering needs besides the rays.
struct Renderer<'a> {
    field: &'a RadianceField,
    fused: Option<&'a FusedField>,
    sampling: &'a SamplingParams,
    chunk: usize,
}

/// Renders every image of `set` into `maps`. The colour of rays that hit nothing is the mean
/// input colour of such pixels in the image, or `sky_override` (novel views have no input);
/// returns the mean of those sky colours over the images.
#[allow(clippy::too_many_arguments)]
fn render_images(
    r: &Renderer,
    set: &RaySet,
    sky_override: Option<[f32; 3]>,
    maps: &mut Maps,
    progress: &dyn Progress,
    done: &mut u64,
    total_rays: u64,
) -> Result<[f32; 3]> {
    let (field, fused, sampling) = (r.field, r.fused, r.sampling);
    let (c_n, t_n) = (set.classes.len(), set.things.len());
    let sky_label = labels::SKY;
    let mut sky_sum = [0f32; 3];
    for im in &set.images {
        let n = (im.width * im.height) as usize;
        let mut semantic = vec![sky_label; n];
        let mut fixed = vec![sky_label; n];
        let mut instance = vec![sky_label as u16 * labels::INSTANCE_FACTOR as u16; n];
        let mut depth = vec![0f32; n];
        let mut confidence = vec![1f32; n];
        let mut rgb = vec![0u8; n * 3];
        // Sky colour for rays without primitives: the mean colour of those pixels' input.
        let sky_ids: Vec<usize> = (0..n)
            .filter(|&p| !set.hits_anything(im.first_ray + p))
            .collect();
        let mut sky_rgb = [0f32; 3];
        for &p in &sky_ids {
            for (acc, v) in sky_rgb.iter_mut().zip(set.rgb[im.first_ray + p]) {
                *acc += v / sky_ids.len() as f32;
            }
        }
        if let Some(c) = sky_override {
            sky_rgb = c;
        }
        for (acc, v) in sky_sum.iter_mut().zip(sky_rgb) {
            *acc += v;
        }
        for &p in &sky_ids {
            for k in 0..3 {
                rgb[p * 3 + k] = (sky_rgb[k] * 255.0).round() as u8;
            }
        }
        let hit_ids: Vec<u32> = (0..n)
            .filter(|&p| set.hits_anything(im.first_ray + p))
            .map(|p| (im.first_ray + p) as u32)
            .collect();
        for chunk in hit_ids.chunks(r.chunk) {
            let b = sampling::sample_batch(set, chunk, sampling, None);
            let (sigma, col, logits) = evaluate_field(field, fused, &b);
            let s_n = b.samples;
            if sigma.len() != chunk.len() * s_n
                || col.len() != sigma.len() * 3
                || logits.len() != sigma.len() * c_n
            {
                return Err(StageError::Failed(
                    "the field returned outputs of unexpected size".into(),
                ));
            }
            let results: Vec<_> = chunk
                .par_iter()
                .enumerate()
                .map_init(
                    || Scratch::new(c_n, t_n),
                    |scratch, (i, &rid)| {
                        let rs = i * s_n..(i + 1) * s_n;
                        composite_ray(
                            set,
                            rid as usize,
                            &b.t[rs.clone()],
                            &b.deltas[rs.clone()],
                            &sigma[rs.clone()],
                            &col[rs.start * 3..rs.end * 3],
                            &logits[rs.start * c_n..rs.end * c_n],
                            scratch,
                        )
                    },
                )
                .collect();
            for (&rid, c) in chunk.iter().zip(results) {
                let px = rid as usize - im.first_ray;
                let label = set.classes[c.class];
                semantic[px] = label;
                fixed[px] = set.classes[c.fixed_class];
                let inst = c.thing.map_or(0, |k| set.things[k].1.min(999));
                instance[px] = (label as u32 * labels::INSTANCE_FACTOR + inst) as u16;
                depth[px] = if c.opacity > 0.5 {
                    c.t * set.z_scale[rid as usize]
                } else {
                    0.0
                };
                confidence[px] = c.confidence;
                let rem = (1.0 - c.opacity).max(0.0);
                for k in 0..3 {
                    rgb[px * 3 + k] =
                        ((c.rgb[k] + rem * sky_rgb[k]).clamp(0.0, 1.0) * 255.0).round() as u8;
                }
            }
            *done += chunk.len() as u64;
            progress.update(
                *done,
                total_rays,
                &format!("frame {} cam {}", im.frame, im.camera),
            );
        }
        *done += sky_ids.len() as u64;
        maps.frame.push(im.frame);
        maps.camera.push(im.camera);
        maps.width.push(im.width);
        maps.height.push(im.height);
        maps.semantic.push(semantic);
        maps.fixed.push(fixed);
        maps.instance.push(instance);
        maps.depth.push(depth);
        maps.confidence.push(confidence);
        maps.rgb.push(rgb);
    }
    let n = set.images.len().max(1) as f32;
    Ok(sky_sum.map(|v| v / n))
}

/// The rays of the novel views: each a scene camera moved in its own frame, intersected with
/// the primitives (the `intersect` kind's defaults); no input colour, labels or depth.
fn novel_set(base: &RaySet, prims: &[geometry::Primitive], views: &[NovelView]) -> Result<RaySet> {
    let bvh = geometry::Bvh::build(prims);
    let ip = IntersectParams::default();
    let mut set = RaySet {
        classes: base.classes.clone(),
        things: base.things.clone(),
        prim_class: base.prim_class.clone(),
        prim_thing: base.prim_thing.clone(),
        bounds_min: base.bounds_min,
        bounds_max: base.bounds_max,
        ..Default::default()
    };
    set.offsets.push(0);
    for (k, v) in views.iter().enumerate() {
        let from = base
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
        let local = geometry::DAffine3::from_rotation_translation(
            glam::DQuat::from_rotation_y(v.yaw_deg.to_radians()),
            geometry::DVec3::from(v.translate),
        );
        cam.cam_to_world *= local;
        let plan = rays::plan_image(prims, &bvh, &cam, &ip);
        set.images.push(sampling::ImageInfo {
            frame: v.frame,
            camera: NOVEL_CAMERA_BASE + k as u8,
            width: cam.width,
            height: cam.height,
            first_ray: set.origin.len(),
            cam: cam.clone(),
        });
        let origin = cam.centre();
        let mut j = 0usize;
        for y in 0..cam.height {
            for x in 0..cam.width {
                let p = (y * cam.width + x) as usize;
                let ray = cam.pixel_ray(x, y);
                set.origin
                    .push([origin.x as f32, origin.y as f32, origin.z as f32]);
                set.dir
                    .push([ray.dir.x as f32, ray.dir.y as f32, ray.dir.z as f32]);
                set.z_scale
                    .push(cam.dir_cam(x as f64 + 0.5, y as f64 + 0.5).z as f32);
                let nh = plan.hits[p] as usize;
                for i in j..j + nh {
                    set.t_in.push(plan.t_in[i]);
                    set.t_out.push(plan.t_out[i].max(plan.t_in[i]));
                    set.prim.push(plan.prim[i]);
                }
                j += nh;
                set.offsets.push(set.t_in.len() as u32);
                set.sky
                    .push([plan.sky_t0[p], plan.sky_t1[p].max(plan.sky_t0[p])]);
                set.rgb.push([0.0; 3]);
                set.label.push(sampling::NONE);
                set.u_mask.push(false);
                set.depth.push(0.0);
            }
        }
    }
    Ok(set)
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
        let burn_backend =
            (!p.backend.is_empty() && p.backend != "fused").then_some(p.backend.as_str());
        let (field, info) = load_field(
            inputs.table("train", "weights")?,
            inputs.table("train", "model")?,
            burn_backend,
        )?;
        let fused = match p.backend.as_str() {
            "" => FusedField::from_field(&field).ok(),
            "fused" => Some(FusedField::from_field(&field).map_err(StageError::Params)?),
            _ => None,
        };
        if info.classes != set.classes {
            return Err(StageError::Input(format!(
                "the field was trained for classes {:?} but this scene's primitives give {:?}",
                info.classes, set.classes
            )));
        }
        let sampling = SamplingParams {
            samples: if p.samples > 0 {
                p.samples
            } else {
                info.sampling.samples
            },
            ..info.sampling.clone()
        };
        let seq = tables::get_strings(
            inputs.table("scene", "scene_info")?,
            "scene_info",
            "sequence",
        )?;
        let sequence = if seq.is_empty() {
            "scene".to_string()
        } else {
            seq.value(0).to_string()
        };
        let mut maps = Maps::default();
        let r = Renderer {
            field: &field,
            fused: fused.as_ref(),
            sampling: &sampling,
            chunk: p.chunk,
        };
        let novel = if p.novel_views.is_empty() {
            None
        } else {
            let prims = geometry::io::primitives_from_table(inputs.table("scene", "primitives")?)?;
            Some(novel_set(&set, &prims, &p.novel_views)?)
        };
        let total_rays = (set.len() + novel.as_ref().map_or(0, RaySet::len)) as u64;
        let mut done = 0u64;
        let scene_sky = render_images(&r, &set, None, &mut maps, progress, &mut done, total_rays)?;
        if let Some(novel) = &novel {
            render_images(
                &r,
                novel,
                Some(scene_sky),
                &mut maps,
                progress,
                &mut done,
                total_rays,
            )?;
        }
        let rows = maps.frame.len();
        let t = tables::build(
            "label_maps",
            vec![
                tables::strings(vec![sequence; rows]),
                tables::prim::<UInt32Type>(maps.frame),
                tables::prim::<UInt8Type>(maps.camera),
                tables::prim::<UInt32Type>(maps.width),
                tables::prim::<UInt32Type>(maps.height),
                tables::list::<UInt8Type>(maps.semantic),
                tables::list::<UInt8Type>(maps.fixed),
                tables::list::<UInt16Type>(maps.instance),
                tables::list::<Float32Type>(maps.depth),
                tables::list::<Float32Type>(maps.confidence),
                tables::binary(&maps.rgb),
            ],
        )?;
        Ok(Tables::from([("label_maps".to_string(), t)]))
    }

    fn export(&self, _: &RenderParams, t: &Tables, dir: &Path) -> Result<Vec<PathBuf>> {
        export_label_maps(&t["label_maps"], dir)
    }
}

/// Writes KITTI-360-style PNGs of a `label_maps` table under `dir`: semantic/ (8-bit ids),
/// semantic_rgb/, instance/ (16-bit id*1000+instance), panoptic_rgb/, depth/ (16-bit,
/// metres*256), rgb/; right-camera files carry `_01`.
pub fn export_label_maps(t: &arrow::record_batch::RecordBatch, dir: &Path) -> Result<Vec<PathBuf>> {
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
                3 => pngio::write_rgb8(&path, w, h, &crate::report::panoptic_colors(inst.row(r)))?,
                4 => pngio::write_gray16(&path, w, h, &pngio::depth_to_u16(depth.row(r)))?,
                _ => pngio::write_rgb8(&path, w, h, rgb.value(r))?,
            }
            out.push(path);
        }
    }
    Ok(out)
}
