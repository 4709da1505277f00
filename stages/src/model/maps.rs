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
    render_image_again(r, rays, in_lens, frame, camera, sky, None)
}

/// The part of an image rendered again over a previous rendering of it: the pixels to decide
/// again (a union of whole closed cells of the coarse grid, see [`coarse_cells_of`]); the others
/// keep the previous maps (sky pixels take the current sky colour).
pub struct Again<'a> {
    pub previous: &'a ImageMaps,
    pub pixels: &'a [bool],
}

/// Every pixel of the closed cells of the grid of spacing `stride` that hold one of `pixels`,
/// row-major over `width` x `height`. The adaptive render decides a pixel from the corners of
/// the cells around it, which all lie in its closed coarse cell: rendering these cells again
/// gives, inside them, what rendering the whole image again gives.
pub fn coarse_cells_of(width: u32, height: u32, stride: u32, pixels: &[u32]) -> Vec<bool> {
    let s = stride.max(1);
    let (cw, ch) = (width.div_ceil(s), height.div_ceil(s));
    let mut cells = vec![false; (cw * ch) as usize];
    for &p in pixels {
        let (x, y) = (p % width, p / width);
        cells[((y / s) * cw + x / s) as usize] = true;
    }
    let mut out = vec![false; (width * height) as usize];
    for (c, _) in cells.iter().enumerate().filter(|(_, on)| **on) {
        let (cx, cy) = (c as u32 % cw * s, c as u32 / cw * s);
        for y in cy..=(cy + s).min(height - 1) {
            let row = (y * width) as usize;
            out[row + cx as usize..=row + (cx + s).min(width - 1) as usize].fill(true);
        }
    }
    out
}

/// The pixels that see through the lens and cross no primitive: sky, without a field.
fn sky_pixels(rays: &PlannedImage, in_lens: &[bool]) -> Vec<usize> {
    let n = (rays.cam.width * rays.cam.height) as usize;
    (0..n)
        .filter(|&p| !rays.hits_anything(p) && in_lens.get(p).copied().unwrap_or(true))
        .collect()
}

/// The colour an image's sky pixels get: the fixed one, or their mean input colour.
pub fn sky_colour(
    rays: &PlannedImage,
    in_lens: &[bool],
    sky: SkyColour,
) -> std::result::Result<[f32; 3], String> {
    let input = match sky {
        SkyColour::Fixed(c) => return Ok(c),
        SkyColour::FromInput(input) => input,
    };
    let (width, height) = (rays.cam.width, rays.cam.height);
    if input.len() != (width * height) as usize * 3 {
        return Err(format!(
            "{} bytes, expected {width}x{height}x3",
            input.len()
        ));
    }
    let sky_ids = sky_pixels(rays, in_lens);
    let mut c = [0f32; 3];
    for &p in &sky_ids {
        for (k, acc) in c.iter_mut().enumerate() {
            *acc += (input[p * 3 + k] as f32 / 255.0) / sky_ids.len() as f32;
        }
    }
    Ok(c)
}

/// [`render_image`], or with `again` only its pixels rendered again over a previous rendering.
pub fn render_image_again(
    r: &Renderer,
    rays: &PlannedImage,
    in_lens: &[bool],
    frame: u32,
    camera: u8,
    sky: SkyColour,
    again: Option<Again>,
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
    let sky_ids = sky_pixels(rays, in_lens);
    let sky_rgb = sky_colour(rays, in_lens, sky)
        .map_err(|e| StageError::Input(format!("images: frame {frame} camera {camera}: {e}")))?;
    for &p in &sky_ids {
        for (out, v) in maps.rgb[p * 3..p * 3 + 3].iter_mut().zip(sky_rgb) {
            *out = (v * 255.0).round() as u8;
        }
    }
    let decide = |p: usize| again.as_ref().is_none_or(|a| a.pixels[p]);
    if let Some(a) = &again {
        keep_previous(&mut maps, a, rays)?;
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
        .filter(|&p| rays.hits_anything(p as usize) && decide(p as usize))
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
                if (row_known && on_grid(x, width, s)) || !rays.hits_anything(p) || !decide(p) {
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

/// Copies the previous maps of the pixels `a` does not decide again and that cross a primitive
/// (sky pixels keep the current sky colour).
fn keep_previous(maps: &mut ImageMaps, a: &Again, rays: &PlannedImage) -> Result<()> {
    let prev = a.previous;
    let n = maps.semantic.len();
    let sizes = [
        prev.semantic.len(),
        prev.fixed.len(),
        prev.instance.len(),
        prev.depth.len(),
        prev.confidence.len(),
        a.pixels.len(),
    ];
    if (prev.width, prev.height) != (maps.width, maps.height) || sizes.iter().any(|&l| l != n) {
        return Err(StageError::Input(format!(
            "the previous maps of frame {} camera {} are not {}x{}",
            maps.frame, maps.camera, maps.width, maps.height
        )));
    }
    let prev_rgb = prev.rgb.len() == n * 3;
    for p in (0..n).filter(|&p| !a.pixels[p] && rays.hits_anything(p)) {
        maps.semantic[p] = prev.semantic[p];
        maps.fixed[p] = prev.fixed[p];
        maps.instance[p] = prev.instance[p];
        maps.depth[p] = prev.depth[p];
        maps.confidence[p] = prev.confidence[p];
        if prev_rgb {
            maps.rgb[p * 3..p * 3 + 3].copy_from_slice(&prev.rgb[p * 3..p * 3 + 3]);
        }
    }
    Ok(())
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

#[cfg(test)]
mod tests {
    use glam::{DAffine3, DMat3, DQuat, DVec3};

    use super::*;
    use crate::geometry::{changes::pixels_meeting, Bvh, Primitive, Shape};
    use crate::intervals::{plan_image, ImagePlan, IntersectParams};
    use crate::model::testing::{lively, toy_field, toy_sampling};
    use crate::model::{params, Engine, FieldSpec};
    use crate::sampling::PrimInfo;

    fn cuboid(centre: [f64; 3], size: [f64; 3], label: u8, instance: u32) -> Primitive {
        let t = DAffine3::from_scale_rotation_translation(
            DVec3::from(size),
            DQuat::IDENTITY,
            DVec3::from(centre),
        );
        Primitive::new(Shape::Cuboid, t, label, instance).unwrap()
    }

    /// A road, a building and a car (at `car_x`) in front of a camera at the origin looking
    /// along +x.
    fn street(car_x: f64) -> Vec<Primitive> {
        vec![
            cuboid([15.0, 0.0, -1.6], [30.0, 12.0, 0.2], labels::ROAD, 0),
            cuboid([20.0, 5.0, 2.0], [8.0, 3.0, 8.0], labels::BUILDING, 0),
            cuboid([car_x, -1.5, -0.8], [4.0, 1.8, 1.5], labels::CAR, 3),
        ]
    }

    fn camera() -> Camera {
        Camera {
            width: 61,
            height: 37,
            fx: 40.0,
            fy: 40.0,
            cx: 30.5,
            cy: 18.5,
            lens: Lens::Pinhole,
            cam_to_world: DAffine3::from_mat3(DMat3::from_cols(-DVec3::Y, -DVec3::Z, DVec3::X)),
        }
    }

    /// Every map of `a` and `b` at pixel `p` (labels, depth, confidence; colour when both have
    /// one).
    fn same_at(a: &ImageMaps, b: &ImageMaps, p: usize) -> bool {
        (a.semantic[p], a.fixed[p], a.instance[p]) == (b.semantic[p], b.fixed[p], b.instance[p])
            && a.depth[p].to_bits() == b.depth[p].to_bits()
            && a.confidence[p].to_bits() == b.confidence[p].to_bits()
    }

    /// The cells rendered again hold every pixel that meets the edit, and only closed coarse
    /// cells that hold one (brute force over the cells).
    #[test]
    fn coarse_cells_are_the_closed_cells_of_the_pixels() {
        let (w, h) = (23u32, 10u32);
        for stride in [1, 2, 4, 8, 16] {
            let pixels = [0u32, 5 * w + 7, 9 * w + 22, 4 * w + 8];
            let cells = coarse_cells_of(w, h, stride, &pixels);
            for y in 0..h {
                for x in 0..w {
                    // In a closed cell [x0, x0 + s] x [y0, y0 + s] of one of the pixels?
                    let expected = pixels.iter().any(|&q| {
                        let (qx, qy) = (q % w, q / w);
                        let (x0, y0) = (qx - qx % stride, qy - qy % stride);
                        (x0..=(x0 + stride).min(w - 1)).contains(&x)
                            && (y0..=(y0 + stride).min(h - 1)).contains(&y)
                    });
                    assert_eq!(
                        cells[(y * w + x) as usize],
                        expected,
                        "s {stride} ({x},{y})"
                    );
                }
            }
        }
    }

    /// Rendering again where the edit can change the image gives there exactly what rendering
    /// the whole image gives, and keeps the previous maps everywhere else.
    #[test]
    fn rendering_again_equals_a_whole_render_inside_and_the_previous_outside() {
        let cam = camera();
        let (before, after) = (street(12.0), street(13.0));
        let info = PrimInfo::of(&after);
        assert_eq!(info.classes, PrimInfo::of(&before).classes);
        let spec = FieldSpec {
            config: toy_field(),
            num_classes: info.classes.len(),
            aabb_min: [-5.0, -10.0, -5.0],
            aabb_max: [35.0, 10.0, 10.0],
            seed: 0,
        };
        let field = |seed| {
            Engine::Fused
                .field(spec.clone(), lively(params::initial(&spec), seed))
                .unwrap()
        };
        let (old_field, new_field) = (field(1), field(2));
        let sampling = toy_sampling();
        let ip = IntersectParams::default();
        let plan =
            |prims: &[Primitive]| -> ImagePlan { plan_image(prims, &Bvh::build(prims), &cam, &ip) };
        let (old_plan, new_plan) = (plan(&before), plan(&after));
        let old_info = PrimInfo::of(&before);
        let old_rays = PlannedImage::new(&old_info, &cam, &old_plan).unwrap();
        let new_rays = PlannedImage::new(&info, &cam, &new_plan).unwrap();
        let input = vec![90u8; (cam.width * cam.height * 3) as usize];
        for stride in [1, 4] {
            let render = |f: &dyn Field, rays: &PlannedImage, again: Option<Again>| {
                let r = Renderer {
                    field: f,
                    sampling: &sampling,
                    chunk: 64,
                    heads: Heads::ALL,
                    coarse_stride: stride,
                    depth: DepthKind::Expected,
                };
                let sky = SkyColour::FromInput(&input);
                render_image_again(&r, rays, &[], 0, 0, sky, again)
                    .unwrap()
                    .0
            };
            let previous = render(old_field.as_ref(), &old_rays, None);
            let whole = render(new_field.as_ref(), &new_rays, None);
            let meeting = pixels_meeting(&cam, &[before[2].clone(), after[2].clone()], ip.far);
            let pixels = coarse_cells_of(cam.width, cam.height, stride, &meeting);
            let again = Again {
                previous: &previous,
                pixels: &pixels,
            };
            let updated = render(new_field.as_ref(), &new_rays, Some(again));
            let (mut inside, mut outside, mut differ_outside) = (0, 0, 0);
            for (p, &in_cell) in pixels.iter().enumerate() {
                if in_cell {
                    inside += 1;
                    assert!(same_at(&updated, &whole, p), "stride {stride}: pixel {p}");
                    assert_eq!(updated.rgb[p * 3..p * 3 + 3], whole.rgb[p * 3..p * 3 + 3]);
                } else {
                    outside += 1;
                    assert!(
                        same_at(&updated, &previous, p),
                        "stride {stride}: pixel {p}"
                    );
                    differ_outside += usize::from(!same_at(&whole, &previous, p));
                }
            }
            // The test tells the two apart: the fields differ outside the edit too.
            assert!(inside > 50 && outside > 500, "{inside} / {outside}");
            assert!(differ_outside > 100, "{differ_outside}");
            // Every pixel rendered again: the whole render.
            let all = vec![true; pixels.len()];
            let again = Again {
                previous: &previous,
                pixels: &all,
            };
            assert_eq!(render(new_field.as_ref(), &new_rays, Some(again)), whole);
        }
    }
}
