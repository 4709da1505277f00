//! Label maps of whole images from a trained field, whatever the engine: rays that cross no
//! primitive are sky without any network evaluation; the others are sampled as in training
//! (stratum centres), evaluated in chunks and composited per ray
//! ([`crate::model::composite`]). The field is evaluated front to back in rounds of a few
//! samples per ray, and a ray leaves once its transmittance is below the compositor's early-stop
//! threshold, so the samples the compositor would skip are never evaluated.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::composite::{Composite, Compositor, RaySums};
use super::config::SkyColourInput;
use super::field::{Field, Heads};
use crate::geometry::{Camera, Lens};
use crate::labels;
use crate::sampling::{self, Intervals, PlannedImage, SamplingParams, StoredRays};
use crate::stage::{Result, StageError};

/// What rendering needs besides the rays.
pub struct Renderer<'a> {
    pub field: &'a dyn Field,
    pub sampling: &'a SamplingParams,
    /// Rays evaluated per field call.
    pub chunk: usize,
    /// The heads evaluated (without colour the colour map is the sky colour).
    pub heads: Heads,
    /// Render a coarse grid of pixels of this spacing first and the rest only where those
    /// disagree (see [`render_image`]); a power of two, 1 renders every pixel.
    pub coarse_stride: u32,
    /// Which depth a ray's depth map shows.
    pub depth: DepthKind,
}

/// The depth of a rendered ray, written only where the opacity reaches 0.5 (else 0: sky).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum DepthKind {
    /// Expected termination distance over the ray's non-sky weight, sum w t / sum w (the
    /// paper's code renders sum w t; over its opaque pixels the two are nearly equal).
    #[default]
    Expected,
    /// The sample where the accumulated weight reaches 0.5: one surface where the weight is
    /// split between two, never a depth between them.
    Median,
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
    /// Rendered colour, the remainder filled with the sky colour; empty without the colour
    /// head.
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

/// Which pixels of `cam` see through its lens, row-major; empty for a pinhole (all of them).
/// The same for every image of a camera: compute it once per camera.
pub fn lens_mask(cam: &Camera) -> Vec<bool> {
    match cam.lens {
        Lens::Pinhole => Vec::new(),
        Lens::Mei(_) => (0..cam.width * cam.height)
            .map(|p| cam.pixel_in_lens(p % cam.width, p / cam.width))
            .collect(),
    }
}

/// Renders one image: its rays, with the plan of each pixel, the lens mask of its camera
/// ([`lens_mask`]), and its frame and camera id. Returns the maps and the sky colour used.
///
/// Only the pixels of a grid of spacing [`Renderer::coarse_stride`] (and the last row and
/// column) are rendered first; then, halving
/// the spacing until it is 1, each pixel new on the finer grid is rendered too unless the four
/// pixels of the coarser grid around it have its panoptic and fixed-field labels and it crosses
/// the same primitives as they do, in which case it takes their labels and an interpolation of
/// their depth, confidence and colour. Labels change only inside a cell of four agreeing pixels
/// (a detail of the learned field finer than the cell, within one primitive).
pub fn render_image(
    r: &Renderer,
    rays: &PlannedImage,
    in_lens: &[bool],
    frame: u32,
    camera: u8,
    sky: SkyColour,
) -> Result<(ImageMaps, [f32; 3])> {
    let (width, height) = (rays.cam.width, rays.cam.height);
    let n = (width * height) as usize;
    let sky_label = labels::SKY;
    let mut maps = ImageMaps {
        frame,
        camera,
        width,
        height,
        semantic: vec![sky_label; n],
        fixed: vec![sky_label; n],
        instance: vec![sky_label as u16 * labels::INSTANCE_FACTOR as u16; n],
        depth: vec![0f32; n],
        confidence: vec![1f32; n],
        rgb: vec![0u8; n * 3],
    };
    // Pixels outside a fisheye's lens are no rays: unlabelled, no depth, black.
    if !in_lens.is_empty() && in_lens.len() != n {
        return Err(StageError::Failed(format!(
            "lens mask of {} pixels for a {width}x{height} image",
            in_lens.len()
        )));
    }
    for (p, _) in in_lens.iter().enumerate().filter(|(_, inside)| !**inside) {
        maps.semantic[p] = labels::UNLABELED;
        maps.fixed[p] = labels::UNLABELED;
        maps.instance[p] = 0;
        maps.confidence[p] = 0.0;
    }
    let sky_ids: Vec<usize> = (0..n)
        .filter(|&p| !rays.hits_anything(p) && in_lens.get(p).copied().unwrap_or(true))
        .collect();
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
        for (out, v) in maps.rgb[p * 3..p * 3 + 3].iter_mut().zip(sky_rgb) {
            *out = (v * 255.0).round() as u8;
        }
    }
    let coarse_stride = r.coarse_stride.max(1);
    let on_grid = |x: u32, n: u32, s: u32| x % s == 0 || x == n - 1;
    let first: Vec<u32> = (0..height)
        .filter(|&y| on_grid(y, height, coarse_stride))
        .flat_map(|y| {
            (0..width)
                .filter(move |&x| on_grid(x, width, coarse_stride))
                .map(move |x| y * width + x)
        })
        .filter(|&p| rays.hits_anything(p as usize))
        .collect();
    render_pixels(r, rays, &first, sky_rgb, &mut maps)?;
    // Halve the spacing until every pixel is decided: a pixel new on the finer grid is rendered
    // unless the four pixels of the coarser grid around it agree.
    let mut s = coarse_stride;
    while s > 1 {
        let h = s / 2;
        let mut rest = Vec::new();
        for y in (0..height).filter(|&y| on_grid(y, height, h)) {
            let (y0, y1) = cell(y, height, s);
            let row_known = on_grid(y, height, s);
            for x in (0..width).filter(|&x| on_grid(x, width, h)) {
                let p = (y * width + x) as usize;
                if (row_known && on_grid(x, width, s)) || !rays.hits_anything(p) {
                    continue;
                }
                let (x0, x1) = cell(x, width, s);
                let corners = [
                    (y0 * width + x0) as usize,
                    (y0 * width + x1) as usize,
                    (y1 * width + x0) as usize,
                    (y1 * width + x1) as usize,
                ];
                let same = corners.iter().all(|&c| {
                    maps.instance[c] == maps.instance[corners[0]]
                        && maps.fixed[c] == maps.fixed[corners[0]]
                        && rays.intervals(c as u32).prim == rays.intervals(p as u32).prim
                });
                if !same {
                    rest.push(p as u32);
                    continue;
                }
                let frac = |v: u32, v0: u32, v1: u32| {
                    if v1 > v0 {
                        (v - v0) as f32 / (v1 - v0) as f32
                    } else {
                        0.0
                    }
                };
                let (fx, fy) = (frac(x, x0, x1), frac(y, y0, y1));
                let w = [
                    (1.0 - fx) * (1.0 - fy),
                    fx * (1.0 - fy),
                    (1.0 - fx) * fy,
                    fx * fy,
                ];
                interpolate(&mut maps, p, &corners, &w);
            }
        }
        render_pixels(r, rays, &rest, sky_rgb, &mut maps)?;
        s = h;
    }
    if !r.heads.rgb {
        maps.rgb = Vec::new();
    }
    Ok((maps, sky_rgb))
}

/// The pixels of the grid of spacing `s` around `x` on a side of `n` pixels (the last pixel is
/// on every grid).
fn cell(x: u32, n: u32, s: u32) -> (u32, u32) {
    let x0 = x - x % s;
    let x1 = (x0 + s).min(n - 1);
    (x0, x1)
}

/// Pixel `p` from the rendered pixels `corners` (which share its labels) with bilinear weights
/// `w`: their labels, and the weighted depth (over the corners with a depth), confidence and
/// colour.
fn interpolate(maps: &mut ImageMaps, p: usize, corners: &[usize; 4], w: &[f32; 4]) {
    let c0 = corners[0];
    maps.semantic[p] = maps.semantic[c0];
    maps.fixed[p] = maps.fixed[c0];
    maps.instance[p] = maps.instance[c0];
    let (mut d, mut dw, mut conf) = (0f32, 0f32, 0f32);
    let mut rgb = [0f32; 3];
    for (&c, &wc) in corners.iter().zip(w) {
        if maps.depth[c] > 0.0 {
            d += wc * maps.depth[c];
            dw += wc;
        }
        conf += wc * maps.confidence[c];
        for (k, v) in rgb.iter_mut().enumerate() {
            *v += wc * maps.rgb[c * 3 + k] as f32;
        }
    }
    maps.depth[p] = if dw > 0.0 { d / dw } else { 0.0 };
    maps.confidence[p] = conf;
    for (k, v) in rgb.iter().enumerate() {
        maps.rgb[p * 3 + k] = v.round().clamp(0.0, 255.0) as u8;
    }
}

/// Renders pixels `ids` (which cross primitives) into `maps`: chunks of rays in parallel, each
/// sampled, marched and composited, so the serial parts of one chunk overlap with the others'
/// field evaluations.
fn render_pixels(
    r: &Renderer,
    rays: &PlannedImage,
    ids: &[u32],
    sky_rgb: [f32; 3],
    maps: &mut ImageMaps,
) -> Result<()> {
    let prims = rays.prims;
    let chunks: Vec<&[u32]> = ids.chunks(r.chunk).collect();
    let composited: Vec<Vec<(Composite, f32)>> = chunks
        .par_iter()
        .map(|chunk| composite_rays(r.field, r.sampling, r.heads, rays, chunk))
        .collect::<Result<_>>()?;
    for (chunk, results) in chunks.iter().zip(composited) {
        for (&px, (c, z_scale)) in chunk.iter().zip(results) {
            let px = px as usize;
            let label = prims.classes[c.class];
            maps.semantic[px] = label;
            maps.fixed[px] = prims.classes[c.fixed_class];
            let inst = c.thing.map_or(0, |k| prims.things[k].1.min(999));
            maps.instance[px] = (label as u32 * labels::INSTANCE_FACTOR + inst) as u16;
            maps.depth[px] = match r.depth {
                DepthKind::Expected if c.opacity > 0.5 => c.t * z_scale,
                DepthKind::Median => c.t_median * z_scale,
                DepthKind::Expected => 0.0,
            };
            maps.confidence[px] = c.confidence;
            let rem = (1.0 - c.opacity).max(0.0);
            for (k, out) in maps.rgb[px * 3..px * 3 + 3].iter_mut().enumerate() {
                *out = ((c.rgb[k] + rem * sky_rgb[k]).clamp(0.0, 1.0) * 255.0).round() as u8;
            }
        }
    }
    Ok(())
}

/// Samples, evaluates and composites the rays `chunk` of `rays` with `field`'s `heads`; each with
/// its z scale.
///
/// The field is evaluated front to back in rounds of a few samples per ray, each round
/// composited at once, and a ray leaves once the compositor says it is saturated or its labels
/// are settled ([`Compositor::settled`]): the samples the rest of a ray holds cannot change its
/// labels, so they are never evaluated.
pub fn composite_rays(
    field: &dyn Field,
    sampling: &SamplingParams,
    heads: Heads,
    rays: &dyn StoredRays,
    chunk: &[u32],
) -> Result<Vec<(Composite, f32)>> {
    let b = sampling::sample_for_render(rays, chunk, sampling)?;
    let prims = rays.prims();
    let (s_n, c_n) = (b.samples, prims.classes.len());
    let mut comp = Compositor::new(prims);
    let width = comp.width();
    let mut sums = vec![0f32; chunk.len() * width];
    let mut state = vec![RaySums::default(); chunk.len()];
    let intervals: Vec<Intervals> = chunk.iter().map(|&r| rays.intervals(r)).collect();
    let mut alive: Vec<usize> = (0..chunk.len()).collect();
    let (mut pos, mut dirs, mut in_sky) = (Vec::new(), Vec::new(), Vec::new());
    let direction_sky = field.spec().config.sky_colour == SkyColourInput::Direction;
    let mut s0 = 0;
    for &k in MARCH_ROUNDS.iter().chain(std::iter::repeat(&MARCH_ROUND)) {
        if s0 >= s_n || alive.is_empty() {
            break;
        }
        let k = k.min(s_n - s0);
        pos.clear();
        dirs.clear();
        in_sky.clear();
        for &r in &alive {
            pos.extend_from_slice(&b.positions[(r * s_n + s0) * 3..(r * s_n + s0 + k) * 3]);
            dirs.extend_from_slice(&b.dirs[r * 3..r * 3 + 3]);
            if direction_sky && heads.rgb {
                let ts = &b.t[r * s_n + s0..r * s_n + s0 + k];
                in_sky.extend(ts.iter().map(|&t| intervals[r].in_sky(t)));
            }
        }
        let got = field.evaluate(&pos, &dirs, k, &in_sky, heads);
        let m = alive.len() * k;
        if got.sigma.len() != m
            || got.logits.len() != m * c_n
            || (heads.rgb && got.rgb.len() != m * 3)
        {
            return Err(StageError::Failed(
                "the field returned outputs of unexpected size".into(),
            ));
        }
        for (a, &r) in alive.iter().enumerate() {
            let ray_sums = &mut sums[r * width..(r + 1) * width];
            for j in 0..k {
                let (i, g) = (r * s_n + s0 + j, a * k + j);
                let rgb = if heads.rgb {
                    &got.rgb[g * 3..g * 3 + 3]
                } else {
                    &[][..]
                };
                let logits = &got.logits[g * c_n..(g + 1) * c_n];
                let (t, d) = (b.t[i], b.deltas[i]);
                if !comp.add(
                    &mut state[r],
                    ray_sums,
                    &intervals[r],
                    t,
                    d,
                    got.sigma[g],
                    rgb,
                    logits,
                ) {
                    break;
                }
            }
        }
        alive.retain(|&r| !comp.settled(&state[r], &sums[r * width..(r + 1) * width]));
        s0 += k;
    }
    Ok((0..chunk.len())
        .map(|r| {
            let c = comp.finish(&state[r], &mut sums[r * width..(r + 1) * width]);
            (c, b.z_scale[r])
        })
        .collect())
}

/// Samples per ray of the first rounds of [`composite_rays`]: small, since most rays settle
/// within their first few samples; then [`MARCH_ROUND`] at a time.
const MARCH_ROUNDS: [usize; 2] = [4, 4];
const MARCH_ROUND: usize = 8;
