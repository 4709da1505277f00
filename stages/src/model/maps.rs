//! Label maps of whole images from a trained field, whatever the engine: rays that cross no
//! primitive are sky without any network evaluation; the others are sampled as in training
//! (stratum centres), evaluated in chunks and composited per ray
//! ([`crate::model::composite`]). The field is evaluated front to back in rounds of a few
//! samples per ray, and a ray leaves once its transmittance is below the compositor's early-stop
//! threshold, so the samples the compositor would skip are never evaluated.

use rayon::prelude::*;

use super::composite::{composite_ray, march_step, Composite, Scratch, EARLY_STOP_T};
use super::field::{Field, FieldSamples, Heads};
use crate::intervals::RayPlan;
use crate::labels;
use crate::sampling::{self, PlannedImage, Rays, SamplingParams};
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

/// The colour of rays that cross no primitive.
#[derive(Debug, Clone, Copy)]
pub enum SkyColour<'a> {
    /// The mean input colour of those pixels (RGB bytes of the input image).
    FromInput(&'a [u8]),
    /// A given colour (novel views have no input).
    Fixed([f32; 3]),
}

/// Renders one image: its rays, with the plan of each pixel, and its frame and camera id.
/// Returns the maps and the sky colour used.
pub fn render_image(
    r: &Renderer,
    rays: &PlannedImage,
    frame: u32,
    camera: u8,
    sky: SkyColour,
) -> Result<(ImageMaps, [f32; 3])> {
    let (field, sampling, prims) = (r.field, r.sampling, rays.prims);
    let (c_n, t_n) = (prims.classes.len(), prims.things.len());
    let (width, height) = (rays.cam.width, rays.cam.height);
    let n = (width * height) as usize;
    let sky_label = labels::SKY;
    let mut semantic = vec![sky_label; n];
    let mut fixed = vec![sky_label; n];
    let mut instance = vec![sky_label as u16 * labels::INSTANCE_FACTOR as u16; n];
    let mut depth = vec![0f32; n];
    let mut confidence = vec![1f32; n];
    let mut rgb = vec![0u8; n * 3];
    let sky_ids: Vec<usize> = (0..n).filter(|&p| !rays.hits_anything(p)).collect();
    let sky_rgb = match sky {
        SkyColour::Fixed(c) => c,
        SkyColour::FromInput(input) => {
            if input.len() != n * 3 {
                return Err(StageError::Input(format!(
                    "images: frame {frame} camera {camera} has {} bytes, expected {width}x{height}x3",
                    input.len()
                )));
            }
            let mut c = [0f32; 3];
            for &p in &sky_ids {
                for (k, acc) in c.iter_mut().enumerate() {
                    *acc += (input[p * 3 + k] as f32 / 255.0) / sky_ids.len() as f32;
                }
            }
            c
        }
    };
    for &p in &sky_ids {
        for k in 0..3 {
            rgb[p * 3 + k] = (sky_rgb[k] * 255.0).round() as u8;
        }
    }
    let hit_ids: Vec<u32> = (0..n as u32)
        .filter(|&p| rays.hits_anything(p as usize))
        .collect();
    // Chunks in parallel (each samples, marches and composites its rays), so the serial
    // parts of one chunk overlap with the others' field evaluations.
    let chunks: Vec<&[u32]> = hit_ids.chunks(r.chunk).collect();
    let composited: Vec<Vec<(Composite, f32)>> = chunks
        .par_iter()
        .map(|chunk| composite_chunk(rays, sampling, field, chunk, c_n, t_n))
        .collect::<Result<_>>()?;
    for (chunk, results) in chunks.iter().zip(composited) {
        for (&px, (c, z_scale)) in chunk.iter().zip(results) {
            let px = px as usize;
            let label = prims.classes[c.class];
            semantic[px] = label;
            fixed[px] = prims.classes[c.fixed_class];
            let inst = c.thing.map_or(0, |k| prims.things[k].1.min(999));
            instance[px] = (label as u32 * labels::INSTANCE_FACTOR + inst) as u16;
            depth[px] = if c.opacity > 0.5 { c.t * z_scale } else { 0.0 };
            confidence[px] = c.confidence;
            let rem = (1.0 - c.opacity).max(0.0);
            for k in 0..3 {
                rgb[px * 3 + k] =
                    ((c.rgb[k] + rem * sky_rgb[k]).clamp(0.0, 1.0) * 255.0).round() as u8;
            }
        }
    }
    let maps = ImageMaps {
        frame,
        camera,
        width,
        height,
        semantic,
        fixed,
        instance,
        depth,
        confidence,
        rgb,
    };
    Ok((maps, sky_rgb))
}

/// Samples, evaluates and composites the rays `chunk` of `rays`; each with its z scale.
fn composite_chunk(
    rays: &PlannedImage,
    sampling: &SamplingParams,
    field: &dyn Field,
    chunk: &[u32],
    c_n: usize,
    t_n: usize,
) -> Result<Vec<(Composite, f32)>> {
    let b = sampling::sample_for_render(rays, chunk, sampling)?;
    let FieldSamples {
        sigma,
        rgb: col,
        logits,
    } = evaluate_marching(field, &b.positions, &b.dirs, &b.deltas, b.samples, c_n)?;
    let s_n = b.samples;
    let mut scratch = Scratch::new(c_n, t_n);
    let mut buf = RayPlan::default();
    chunk
        .iter()
        .enumerate()
        .map(|(i, &px)| {
            let ray = rays.ray(px, &mut buf)?;
            let rs = i * s_n..(i + 1) * s_n;
            let c = composite_ray(
                rays.prims,
                &ray.intervals,
                &b.t[rs.clone()],
                &b.deltas[rs.clone()],
                &sigma[rs.clone()],
                &col[rs.start * 3..rs.end * 3],
                &logits[rs.start * c_n..rs.end * c_n],
                &mut scratch,
            );
            Ok((c, b.z_scale[i]))
        })
        .collect()
}

/// Samples per ray evaluated per round of [`evaluate_marching`].
const MARCH_ROUND: usize = 8;

/// The field at the samples (`positions` `[R, S, 3]`, `deltas` `[R, S]`, `directions` `[R, 3]`)
/// that compositing reads: front to back in rounds of [`MARCH_ROUND`] samples per ray, dropping
/// a ray once its transmittance is below [`EARLY_STOP_T`] (the compositor stops there too, and
/// runs the same sums in the same order, so it never reads a sample left out; those stay 0).
/// The field's outputs at a sample do not depend on which other samples share the call.
pub fn evaluate_marching(
    field: &dyn Field,
    positions: &[f32],
    directions: &[f32],
    deltas: &[f32],
    samples: usize,
    classes: usize,
) -> Result<FieldSamples> {
    let rays = directions.len() / 3;
    let n = rays * samples;
    let mut out = FieldSamples {
        sigma: vec![0.0; n],
        rgb: vec![0.0; n * 3],
        logits: vec![0.0; n * classes],
    };
    let mut log_t = vec![0f32; rays];
    let mut alive: Vec<usize> = (0..rays).collect();
    let (mut pos, mut dirs) = (Vec::new(), Vec::new());
    let mut s0 = 0;
    while s0 < samples && !alive.is_empty() {
        let k = MARCH_ROUND.min(samples - s0);
        pos.clear();
        dirs.clear();
        for &r in &alive {
            pos.extend_from_slice(&positions[(r * samples + s0) * 3..(r * samples + s0 + k) * 3]);
            dirs.extend_from_slice(&directions[r * 3..r * 3 + 3]);
        }
        let got = field.evaluate(&pos, &dirs, k, Heads::ALL);
        let m = alive.len() * k;
        if got.sigma.len() != m || got.rgb.len() != m * 3 || got.logits.len() != m * classes {
            return Err(StageError::Failed(
                "the field returned outputs of unexpected size".into(),
            ));
        }
        for (a, &r) in alive.iter().enumerate() {
            let (src, dst) = (a * k, r * samples + s0);
            out.sigma[dst..dst + k].copy_from_slice(&got.sigma[src..src + k]);
            out.rgb[dst * 3..(dst + k) * 3].copy_from_slice(&got.rgb[src * 3..(src + k) * 3]);
            out.logits[dst * classes..(dst + k) * classes]
                .copy_from_slice(&got.logits[src * classes..(src + k) * classes]);
        }
        // Transmittance after this round, by the compositor's own step.
        alive.retain(|&r| {
            let lt = &mut log_t[r];
            let round = r * samples + s0..r * samples + s0 + k;
            for (&delta, &sigma) in deltas[round.clone()].iter().zip(&out.sigma[round]) {
                if delta <= 0.0 {
                    continue;
                }
                if march_step(lt, sigma, delta).is_none() {
                    return false;
                }
            }
            lt.exp() >= EARLY_STOP_T
        });
        s0 += k;
    }
    Ok(out)
}
