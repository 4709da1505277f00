//! The inputs of `RaySet::build`: per-image tables indexed by (frame, camera),
//! the columns of `ray_intervals`, and one row of it read together with its camera and
//! targets, every length checked, so building the rays never indexes out of bounds.

use std::collections::HashMap;

use arrow::datatypes::{Float32Type, UInt32Type, UInt8Type};

use crate::geometry;
use crate::stage::{Result, StageError};
use crate::tables;

/// A per-image input table with its (frame, camera) -> row index.
pub(super) struct ImageRows<'a> {
    index: HashMap<(u32, u8), usize>,
    batch: &'a arrow::record_batch::RecordBatch,
    table: &'static str,
}

impl<'a> ImageRows<'a> {
    pub(super) fn new(
        batch: &'a arrow::record_batch::RecordBatch,
        table: &'static str,
    ) -> Result<Self> {
        Ok(Self {
            index: tables::frame_camera_index(batch, table)?,
            batch,
            table,
        })
    }
}

/// The columns of the `ray_intervals` table (one row per image).
pub(super) struct RayRows<'a> {
    frames: &'a [u32],
    cameras: &'a [u8],
    hits: tables::ListColumn<'a, u8>,
    t_in: tables::ListColumn<'a, f32>,
    t_out: tables::ListColumn<'a, f32>,
    prim: tables::ListColumn<'a, u32>,
    sky_t0: tables::ListColumn<'a, f32>,
    sky_t1: tables::ListColumn<'a, f32>,
}

impl<'a> RayRows<'a> {
    pub(super) fn of(rays_t: &'a arrow::record_batch::RecordBatch) -> Result<Self> {
        let t = "ray_intervals";
        Ok(Self {
            frames: tables::get_prim::<UInt32Type>(rays_t, t, "frame")?,
            cameras: tables::get_prim::<UInt8Type>(rays_t, t, "camera")?,
            hits: tables::get_list::<UInt8Type>(rays_t, t, "hits")?,
            t_in: tables::get_list::<Float32Type>(rays_t, t, "t_in")?,
            t_out: tables::get_list::<Float32Type>(rays_t, t, "t_out")?,
            prim: tables::get_list::<UInt32Type>(rays_t, t, "prim")?,
            sky_t0: tables::get_list::<Float32Type>(rays_t, t, "sky_t0")?,
            sky_t1: tables::get_list::<Float32Type>(rays_t, t, "sky_t1")?,
        })
    }
}

/// One `ray_intervals` row with its camera and targets, checked against each other: per-pixel
/// hits and sky intervals, the intervals the hits count, and per-pixel RGB (plus pseudo labels
/// and stereo depth where the image has them).
pub(super) struct ImageRays<'a> {
    pub(super) cam: &'a geometry::CameraRow,
    pub(super) hits: &'a [u8],
    pub(super) t_in: &'a [f32],
    pub(super) t_out: &'a [f32],
    pub(super) prim: &'a [u32],
    pub(super) sky_t0: &'a [f32],
    pub(super) sky_t1: &'a [f32],
    pub(super) targets: Targets<'a>,
}

/// The per-pixel targets of one image: RGB, and pseudo labels and stereo depth where it has
/// them.
pub(super) struct Targets<'a> {
    pub(super) rgb: &'a [u8],
    pub(super) labels: Option<&'a [u8]>,
    pub(super) depth: Option<&'a [f32]>,
}

impl<'a> ImageRays<'a> {
    /// Row `r` of `rows`; errors name the row, image or table that does not fit.
    pub(super) fn read(
        rows: &RayRows<'a>,
        r: usize,
        cams: &'a [geometry::CameraRow],
        prim_count: usize,
        images: &ImageRows<'a>,
        pseudo: &ImageRows<'a>,
        stereo: Option<&ImageRows<'a>>,
    ) -> Result<Self> {
        let (sky0, sky1) = (&rows.sky_t0, &rows.sky_t1);
        let key = (rows.frames[r], rows.cameras[r]);
        let cam = cams
            .iter()
            .find(|c| (c.frame, c.camera) == key)
            .ok_or_else(|| {
                StageError::Input(format!(
                    "ray_intervals row {r}: frame {} camera {} is not in `cameras`",
                    key.0, key.1
                ))
            })?;
        let (w, h) = (cam.cam.width, cam.cam.height);
        let n = (w * h) as usize;
        let hits = rows.hits.row(r);
        if hits.len() != n || sky0.row(r).len() != n || sky1.row(r).len() != n {
            return Err(StageError::Input(format!(
                "ray_intervals row {r}: per-pixel arrays do not have {w}x{h} entries"
            )));
        }
        let total: usize = hits.iter().map(|&h| h as usize).sum();
        let (ti, to, pr) = (rows.t_in.row(r), rows.t_out.row(r), rows.prim.row(r));
        if ti.len() != total || to.len() != total || pr.len() != total {
            return Err(StageError::Input(format!(
                "ray_intervals row {r}: {} intervals listed but hits sum to {total}",
                ti.len()
            )));
        }
        if let Some(&bad) = pr.iter().find(|&&p| p as usize >= prim_count) {
            return Err(StageError::Input(format!(
                "ray_intervals row {r}: primitive id {bad} is not in `primitives` ({prim_count} rows)"
            )));
        }
        let targets = image_targets(key, w, h, images, pseudo, stereo)?;
        Ok(Self {
            cam,
            hits,
            t_in: ti,
            t_out: to,
            prim: pr,
            sky_t0: sky0.row(r),
            sky_t1: sky1.row(r),
            targets,
        })
    }
}

/// Per-pixel RGB, pseudo labels and stereo depth of image `key` (`w` x `h`): RGB must exist,
/// the others may be absent; each must have one value per pixel.
fn image_targets<'a>(
    key: (u32, u8),
    w: u32,
    h: u32,
    images: &ImageRows<'a>,
    pseudo: &ImageRows<'a>,
    stereo: Option<&ImageRows<'a>>,
) -> Result<Targets<'a>> {
    let n = (w * h) as usize;
    let rgb = images
        .index
        .get(&key)
        .map(|&i| tables::get_binary(images.batch, images.table, "rgb").map(|b| b.value(i)))
        .transpose()?
        .ok_or_else(|| {
            StageError::Input(format!(
                "no `images` row for frame {} camera {}",
                key.0, key.1
            ))
        })?;
    if rgb.len() != n * 3 {
        return Err(StageError::Input(format!(
            "images: frame {} camera {} has {} bytes, expected {w}x{h}x3",
            key.0,
            key.1,
            rgb.len()
        )));
    }
    let labels_row = pseudo
        .index
        .get(&key)
        .map(|&i| {
            tables::get_list::<UInt8Type>(pseudo.batch, pseudo.table, "labels").map(|l| l.row(i))
        })
        .transpose()?;
    let depth_row = match stereo {
        Some(s) => s
            .index
            .get(&key)
            .map(|&i| tables::get_list::<Float32Type>(s.batch, s.table, "depth").map(|l| l.row(i)))
            .transpose()?,
        None => None,
    };
    for (what, len) in [
        ("pseudo_labels", labels_row.map(<[u8]>::len)),
        ("stereo_depth", depth_row.map(<[f32]>::len)),
    ] {
        if let Some(len) = len {
            if len != n {
                return Err(StageError::Input(format!(
                    "{what}: frame {} camera {} has {len} values, expected {w}x{h}",
                    key.0, key.1
                )));
            }
        }
    }
    Ok(Targets {
        rgb,
        labels: labels_row,
        depth: depth_row,
    })
}
