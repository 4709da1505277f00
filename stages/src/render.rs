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
    labels, pngio,
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
}

impl Default for RenderParams {
    fn default() -> Self {
        Self {
            chunk: 4096,
            samples: 0,
            backend: String::new(),
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

impl TypedStage for Render {
    type Params = RenderParams;
    const KIND: &'static str = "render";
    const VERSION: u32 = 2;
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
        let (c_n, t_n) = (set.classes.len(), set.things.len());
        let sky_label = labels::SKY;
        let mut maps = Maps::default();
        let total_rays = set.len() as u64;
        let mut done = 0u64;
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
            for &p in &sky_ids {
                for k in 0..3 {
                    rgb[p * 3 + k] = (sky_rgb[k] * 255.0).round() as u8;
                }
            }
            let hit_ids: Vec<u32> = (0..n)
                .filter(|&p| set.hits_anything(im.first_ray + p))
                .map(|p| (im.first_ray + p) as u32)
                .collect();
            for chunk in hit_ids.chunks(p.chunk) {
                let b = sampling::sample_batch(&set, chunk, &sampling, None);
                let (sigma, col, logits) = evaluate_field(&field, fused.as_ref(), &b);
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
                                &set,
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
                done += chunk.len() as u64;
                progress.update(
                    done,
                    total_rays,
                    &format!("frame {} cam {}", im.frame, im.camera),
                );
            }
            done += sky_ids.len() as u64;
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
