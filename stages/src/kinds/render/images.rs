//! Rendering the images of a scene one at a time, each whole or, in an update, only where an
//! edit of the primitives can change it (the rest keeps the previous maps).

use std::collections::HashMap;

use arrow::array::Array;
use arrow::datatypes::{Float32Type, Float64Type, UInt16Type, UInt32Type, UInt8Type};
use arrow::record_batch::RecordBatch;

use glam::DQuat;

use super::moving::MovingLabels;
use super::params::{Colour, NovelView, RenderParams, NOVEL_CAMERA_BASE};
use super::writer::MapWriter;
use crate::geometry::{self, changes::pixels_meeting, changes::ChangeView, Camera, CameraRow};
use crate::geometry::{DAffine3, DVec3, Primitive};
use crate::intervals::{plan_image, ImagePlan, IntersectParams};
use crate::model::maps::{
    coarse_cells_of, lens_mask, render_image_again, sky_colour, Again, ImageMaps, Renderer,
    SkyColour,
};
use crate::model::{weights, Heads};
use crate::sampling::{PlannedImage, PrimInfo, SamplingParams};
use crate::stage::{Inputs, Progress, Result, StageError, Table, Tables};
use crate::tables;

/// What an update renders again: the previous `label_maps` (with its row of each image) and the
/// changed primitives (old and new extents); a pixel is rendered again when its ray can meet
/// one of them.
pub(super) struct Previously<'a> {
    pub maps: &'a Table,
    pub rows: HashMap<(u32, u8), usize>,
    pub changed: Vec<Primitive>,
    pub view: ChangeView,
}

/// How much was rendered: images and pixels, in all and rendered (again).
#[derive(Debug, Default)]
pub(super) struct Rendered {
    pub images: usize,
    pub images_rendered: usize,
    pub pixels: u64,
    pub pixels_rendered: u64,
}

/// What becomes of one image.
enum Part<'a> {
    /// Rendered whole.
    Whole,
    /// The previous row (of this table), as it was.
    Keep(&'a Table, usize),
    /// The previous maps with these pixels rendered again.
    Again(ImageMaps, Vec<bool>),
}

impl<'a> Previously<'a> {
    /// What an update does with image (`frame`, `camera`) of camera `cam` (rays no farther than
    /// `far`, pixels decided on a grid of spacing `stride`).
    fn part(&mut self, key: (u32, u8), cam: &Camera, far: f64, stride: u32) -> Result<Part<'a>> {
        let Some(&row) = self.rows.get(&key) else {
            return Ok(Part::Whole);
        };
        if !self.view.seen_by(cam, far) {
            return Ok(Part::Keep(self.maps, row));
        }
        let meeting = pixels_meeting(cam, &self.changed, far);
        if meeting.is_empty() {
            return Ok(Part::Keep(self.maps, row));
        }
        let pixels = coarse_cells_of(cam.width, cam.height, stride, &meeting);
        Ok(Part::Again(maps_from_row(&self.maps.row(row)?)?, pixels))
    }
}

/// The maps of a one-image `label_maps` batch.
pub(super) fn maps_from_row(b: &RecordBatch) -> Result<ImageMaps> {
    const T: &str = "label_maps";
    let one = |what: &str| StageError::Input(format!("{T}: {what}: expected one row"));
    let first = |v: &[u32]| v.first().copied().ok_or_else(|| one("no row"));
    Ok(ImageMaps {
        frame: first(tables::get_prim::<UInt32Type>(b, T, "frame")?)?,
        camera: *tables::get_prim::<UInt8Type>(b, T, "camera")?
            .first()
            .ok_or_else(|| one("camera"))?,
        width: first(tables::get_prim::<UInt32Type>(b, T, "width")?)?,
        height: first(tables::get_prim::<UInt32Type>(b, T, "height")?)?,
        semantic: tables::get_list::<UInt8Type>(b, T, "semantic")?
            .row(0)
            .to_vec(),
        fixed: tables::get_list::<UInt8Type>(b, T, "fixed_semantic")?
            .row(0)
            .to_vec(),
        instance: tables::get_list::<UInt16Type>(b, T, "instance")?
            .row(0)
            .to_vec(),
        depth: tables::get_list::<Float32Type>(b, T, "depth")?
            .row(0)
            .to_vec(),
        confidence: tables::get_list::<Float32Type>(b, T, "confidence")?
            .row(0)
            .to_vec(),
        rgb: tables::get_binary(b, T, "rgb")?.value(0).to_vec(),
    })
}

/// Renders every planned image (and novel view) into `label_maps`; with `previously`, only
/// what an edit of the primitives can change.
pub(super) fn render_all(
    p: &RenderParams,
    inputs: &Inputs,
    progress: &dyn Progress,
    previously: Option<Previously>,
) -> Result<(Tables, Rendered)> {
    let seq = sequence(inputs)?;
    let out = inputs.writer("label_maps")?;
    let (out, counts) = std::thread::scope(|s| {
        let mut writer = MapWriter::start(s, out, &seq);
        let counts = render_into(p, inputs, progress, previously, &mut writer);
        // A failed write reaches `render_into` as its error: the first error is the one told.
        let out = writer.finish();
        Ok::<_, StageError>((out, counts?))
    })?;
    let out = out?;
    let mut tables = Tables::new();
    out.finish_into(&mut tables)?;
    Ok((tables, counts))
}

/// [`render_all`]'s images, their rows sent to `out`.
fn render_into<'t>(
    p: &RenderParams,
    inputs: &Inputs,
    progress: &dyn Progress,
    mut previously: Option<Previously<'t>>,
    out: &mut MapWriter<'_, 't>,
) -> Result<Rendered> {
    let cams = geometry::cameras_from_table(inputs.table("scene", "cameras")?)?;
    let prims = geometry::primitives_from_table(inputs.table("scene", "primitives")?)?;
    let info = PrimInfo::of(&prims);
    let (model, rows) = weights::read(
        inputs.table("train", "weights")?,
        inputs.table("train", "model")?,
    )?;
    if model.classes != info.classes {
        return Err(StageError::Input(format!(
            "the field was trained for classes {:?} but this scene's primitives give {:?}",
            model.classes, info.classes
        )));
    }
    // Rendering runs where training ran when that was a GPU.
    let trained = weights::trained_engine(inputs.table("train", "model")?)?;
    let engine = p.backend.resolve(&model.spec.config, trained);
    let field = engine.field(model.spec.clone(), rows)?;
    // The samples per ray of the training, or the `samples` param.
    let samples = Some(p.samples).filter(|&n| n > 0);
    let sampling = SamplingParams {
        samples: samples.unwrap_or(model.sampling.samples),
        ..model.sampling.clone()
    };
    let renderer = |rgb: bool| Renderer {
        field: field.as_ref(),
        sampling: &sampling,
        chunk: p.chunk,
        heads: Heads {
            rgb,
            semantics: true,
        },
        coarse_stride: p.coarse_stride,
        depth: p.depth,
    };
    let r = renderer(p.colour == Colour::All);
    // One image at a time: its plan is read, it is rendered and its maps are stored before
    // the next; nothing grows with the number of images.
    let plan = inputs.stored("rays", "ray_intervals")?;
    let planned = planned_images(p, plan)?;
    let images = inputs.stored("scene", "images")?;
    let image_rows: HashMap<(u32, u8), usize> =
        tables::frame_camera_index(&images.columns(&["frame", "camera"])?, "images")?;
    let novel = novel_cameras(&cams, &p.novel_views)?;
    let camera_of = |key: (u32, u8)| {
        cams.iter()
            .find(|c| (c.frame, c.camera) == key)
            .ok_or_else(|| {
                StageError::Input(format!(
                    "ray_intervals: frame {} camera {} is not in `cameras`",
                    key.0, key.1
                ))
            })
    };
    let pixels = |c: &Camera| c.width as u64 * c.height as u64;
    let mut total = novel.iter().map(|(_, _, c)| pixels(c)).sum::<u64>();
    for &(_, key) in &planned {
        total += pixels(&camera_of(key)?.cam);
    }
    let moving = MovingLabels::new(inputs, &cams)?;
    // The lens mask of each camera, kept while its intrinsics stay the same.
    let mut masks: HashMap<u8, (Camera, Vec<bool>)> = HashMap::new();
    let (mut done, mut sky_sum) = (0u64, [0f32; 3]);
    let mut counts = Rendered::default();
    let ip = plan_params(plan)?;
    for &(row, (frame, camera)) in &planned {
        let cam = &camera_of((frame, camera))?.cam;
        let n = (cam.width * cam.height) as usize;
        let part = match previously.as_mut() {
            Some(prev) => prev.part((frame, camera), cam, ip.far, p.coarse_stride)?,
            None => Part::Whole,
        };
        // A kept image is copied as stored, unread (its sky colour only matters to novel views).
        if let (Part::Keep(maps, before), true) = (&part, novel.is_empty()) {
            out.copy(maps, *before)?;
            counts.images += 1;
            counts.pixels += n as u64;
            done += n as u64;
            progress.update(done, total, &format!("frame {frame} cam {camera}"));
            continue;
        }
        let image_plan = ImagePlan::from_row(&plan.row(row)?, 0, n, prims.len())?;
        let rays = PlannedImage::new(&info, cam, &image_plan)?;
        let input = image_rows.get(&(frame, camera)).ok_or_else(|| {
            StageError::Input(format!("no `images` row for frame {frame} camera {camera}"))
        })?;
        let input = images.row(*input)?;
        let rgb = tables::get_binary(&input, "images", "rgb")?.value(0);
        let mask = lens_mask_of(&mut masks, camera, cam);
        let sky_in = SkyColour::FromInput(rgb);
        let labels = moving.pseudo_labels(frame, camera, n)?;
        let sky = counts.render(&r, &rays, mask, (frame, camera), sky_in, part, out, |m| {
            moving.boxes.overlay(m, cam, labels.as_deref());
        })?;
        for (acc, v) in sky_sum.iter_mut().zip(sky) {
            *acc += v;
        }
        done += n as u64;
        progress.update(done, total, &format!("frame {frame} cam {camera}"));
    }
    if !novel.is_empty() {
        // Novel views: planned here as the `rays` stage planned the scene; their sky is the
        // mean sky colour of the scene's images.
        let bvh = geometry::Bvh::build(&prims);
        let scene_sky = sky_sum.map(|v| v / planned.len().max(1) as f32);
        for (frame, camera, cam) in &novel {
            let image_plan = plan_image(&prims, &bvh, cam, &ip);
            let rays = PlannedImage::new(&info, cam, &image_plan)?;
            let part = match previously.as_mut() {
                Some(prev) => prev.part((*frame, *camera), cam, ip.far, p.coarse_stride)?,
                None => Part::Whole,
            };
            counts.render(
                &renderer(p.colour != Colour::None),
                &rays,
                &lens_mask(cam),
                (*frame, *camera),
                SkyColour::Fixed(scene_sky),
                part,
                out,
                |m| {
                    moving.boxes.overlay(m, cam, None);
                },
            )?;
            done += pixels(cam);
            progress.update(done, total, &format!("novel view {camera}"));
        }
    }
    Ok(counts)
}

/// The lens mask of `cam` (camera `camera`), from `masks` while its intrinsics stay the same.
fn lens_mask_of<'m>(
    masks: &'m mut HashMap<u8, (Camera, Vec<bool>)>,
    camera: u8,
    cam: &Camera,
) -> &'m [bool] {
    if !masks.get(&camera).is_some_and(|(c, _)| c.same_pixels(cam)) {
        masks.insert(camera, (cam.clone(), lens_mask(cam)));
    }
    &masks[&camera].1
}

/// The images of the plan to render, (plan row, (frame, camera)), after the `frames` param.
fn planned_images(p: &RenderParams, plan: &Table) -> Result<Vec<(usize, (u32, u8))>> {
    let planned: Vec<(usize, (u32, u8))> = tables::frame_camera_index::<Vec<_>>(
        &plan.columns(&["frame", "camera"])?,
        "ray_intervals",
    )?
    .into_iter()
    .filter(|((frame, _), _)| p.frames.is_empty() || p.frames.contains(frame))
    .map(|(key, row)| (row, key))
    .collect();
    if let Some(f) = p
        .frames
        .iter()
        .find(|f| !planned.iter().any(|(_, (g, _))| g == *f))
    {
        return Err(StageError::Params(format!(
            "`frames`: frame {f} has no planned image (the `rays` stage planned frames {})",
            frame_list(plan)?
        )));
    }
    Ok(planned)
}

impl Rendered {
    /// Renders one image as `part` says into `out`, counting what it rendered; returns the
    /// image's sky colour.
    #[allow(clippy::too_many_arguments)]
    fn render<'t>(
        &mut self,
        r: &Renderer,
        rays: &PlannedImage,
        in_lens: &[bool],
        (frame, camera): (u32, u8),
        sky: SkyColour,
        part: Part<'t>,
        out: &mut MapWriter<'_, 't>,
        moving: impl FnOnce(&mut ImageMaps),
    ) -> Result<[f32; 3]> {
        let n = rays.cam.width as u64 * rays.cam.height as u64;
        self.images += 1;
        self.pixels += n;
        let (mut maps, sky) = match part {
            Part::Keep(maps, before) => {
                out.copy(maps, before)?;
                return sky_colour(rays, in_lens, sky).map_err(|e| {
                    StageError::Input(format!("images: frame {frame} camera {camera}: {e}"))
                });
            }
            Part::Whole => {
                self.images_rendered += 1;
                self.pixels_rendered += n;
                render_image_again(r, rays, in_lens, frame, camera, sky, None)?
            }
            Part::Again(previous, pixels) => {
                self.images_rendered += 1;
                self.pixels_rendered += pixels.iter().filter(|&&x| x).count() as u64;
                let again = Again {
                    previous: &previous,
                    pixels: &pixels,
                };
                render_image_again(r, rays, in_lens, frame, camera, sky, Some(again))?
            }
        };
        moving(&mut maps);
        out.maps(maps)?;
        Ok(sky)
    }
}

/// The sequence name of the scene (`scene` when it has none).
pub(super) fn sequence(inputs: &Inputs) -> Result<String> {
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
fn novel_cameras(cams: &[CameraRow], views: &[NovelView]) -> Result<Vec<(u32, u8, Camera)>> {
    views
        .iter()
        .enumerate()
        .map(|(k, v)| {
            let from = cams
                .iter()
                .find(|c| (c.frame, c.camera) == (v.frame, v.camera))
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

/// The frames of a plan, as `first..last` ranges.
fn frame_list(plan: &Table) -> Result<String> {
    let keys = plan.columns(&["frame"])?;
    let mut frames = tables::get_prim::<UInt32Type>(&keys, "ray_intervals", "frame")?.to_vec();
    frames.sort_unstable();
    frames.dedup();
    let mut out: Vec<String> = Vec::new();
    let mut i = 0;
    while i < frames.len() {
        let mut j = i;
        while j + 1 < frames.len() && frames[j + 1] == frames[j] + 1 {
            j += 1;
        }
        out.push(if i == j {
            frames[i].to_string()
        } else {
            format!("{}..{}", frames[i], frames[j])
        });
        i = j + 1;
    }
    Ok(out.join(", "))
}

/// The `intersect` parameters of the `rays` input's plan (novel views are planned with them).
pub(super) fn plan_params(plan: &Table) -> Result<IntersectParams> {
    const T: &str = "ray_intervals";
    let b = plan.rows(
        0..plan.num_rows().min(1),
        Some(&["k", "far", "sky_interval"]),
    )?;
    let (k, far, sky) = (
        tables::get_prim::<UInt32Type>(&b, T, "k")?,
        tables::get_prim::<Float64Type>(&b, T, "far")?,
        tables::get_prim::<Float64Type>(&b, T, "sky_interval")?,
    );
    match (k.first(), far.first(), sky.first()) {
        (Some(&k), Some(&far), Some(&sky_interval)) => Ok(IntersectParams {
            k,
            far,
            sky_interval,
            cameras: Vec::new(),
        }),
        _ => Ok(IntersectParams::default()),
    }
}
