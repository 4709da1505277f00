//! Label maps of whole images from a trained field, whatever the engine: rays that cross no
//! primitive are sky without any network evaluation; the others are sampled as in training
//! (stratum centres), evaluated in chunks and composited per ray
//! ([`crate::model::composite`]), stopping once transmittance is negligible.

use rayon::prelude::*;

use super::composite::{composite_ray, Scratch};
use super::field::{Field, FieldSamples, Heads};
use crate::labels;
use crate::sampling::{self, ImageInfo, RaySet, SamplingParams};
use crate::stage::{Result, StageError};

/// What rendering needs besides the rays.
pub struct Renderer<'a> {
    pub field: &'a dyn Field,
    pub sampling: &'a SamplingParams,
    /// Rays evaluated per field call.
    pub chunk: usize,
}

/// The rendered maps of one image, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageMaps {
    pub frame: u32,
    pub camera: u8,
    pub width: u32,
    pub height: u32,
    /// Label ids of argmax S.
    pub semantic: Vec<u8>,
    /// Label ids of argmax S_hat.
    pub fixed: Vec<u8>,
    /// `label * 1000 + instance` (KITTI-360's instance PNG values).
    pub instance: Vec<u16>,
    /// Camera z-depth where the opacity exceeds 0.5, else 0.
    pub depth: Vec<f32>,
    /// Probability of the argmax class.
    pub confidence: Vec<f32>,
    /// Rendered colour, the remainder filled with the sky colour.
    pub rgb: Vec<u8>,
}

/// Renders every image of `set`. The colour of rays that hit nothing is the mean input colour
/// of such pixels in the image, or `sky_override` (novel views have no input); also returns the
/// mean of those sky colours over the images. `progress` sees the rays done of each image as
/// they complete.
pub fn render_images(
    r: &Renderer,
    set: &RaySet,
    sky_override: Option<[f32; 3]>,
    progress: &mut dyn FnMut(u64, &ImageInfo),
) -> Result<(Vec<ImageMaps>, [f32; 3])> {
    let (field, sampling) = (r.field, r.sampling);
    let mut maps = Vec::with_capacity(set.images.len());
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
            let FieldSamples {
                sigma,
                rgb: col,
                logits,
            } = field.evaluate(&b.positions, &b.dirs, b.samples, Heads::ALL);
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
            progress(chunk.len() as u64, im);
        }
        progress(sky_ids.len() as u64, im);
        maps.push(ImageMaps {
            frame: im.frame,
            camera: im.camera,
            width: im.width,
            height: im.height,
            semantic,
            fixed,
            instance,
            depth,
            confidence,
            rgb,
        });
    }
    let n = set.images.len().max(1) as f32;
    Ok((maps, sky_sum.map(|v| v / n)))
}
