//! The synthetic urban street with ground truth, generated
//! deterministically from its params, standing in for a KITTI-360 sequence (which cannot be
//! downloaded here nor shipped).
//!
//! One run builds the street ([`layout`]), places a forward-moving stereo rig ([`rig`];
//! [`params`] are its parameters), renders every
//! image exactly ([`tracer`]), derives noisy pseudo labels ([`noise`]), weak stereo depth and
//! LiDAR depth ([`depth`]), and writes the tables of `data_schema/`: `scene_info`, `cameras`,
//! `primitives`, `dynamic_boxes` (the moving objects' boxes), `images`, `pseudo_labels`,
//! `stereo_depth`, `lidar_depth`, `gt_semantic`, `gt_instance`, `gt_depth`, an image at a time as each is rendered ([`write_tables`]: the
//! full-size street with fisheye cameras takes 0.2 GB where holding its maps took 4.2 GB).
//! `export` writes the KITTI-360 layout ([`kitti360_export`]) and
//! colour previews ([`preview`]).
//!
//! Frames: the street's layout is `street_length_m` long with a frame every
//! `frame_spacing_m` (frame number k at x = k * spacing, like KITTI-360's frame numbers);
//! `first_frame` and `frames` choose the window that is rendered. The default window (16
//! frames x 2 cameras at 176x47) keeps the default pipeline trainable on 2 CPU cores.
//!
//! Cost (2 cores, dev profile with optimised dependencies): the default scene takes 0.35-0.9 s;
//! full KITTI-360 size (`scale` 1, 1408x376) about 0.7 s per image.

use arrow::array::ArrayRef;
use arrow::datatypes::{Float32Type, Float64Type, UInt16Type, UInt32Type, UInt8Type};
use arrow::record_batch::RecordBatch;
use rayon::prelude::*;

use crate::geometry::{
    cameras_to_table, dynamic_boxes_to_table, primitives_to_table, Bvh, CameraRow, DVec3,
    DynamicBox,
};
use crate::labels::{self, SKY};
use crate::stage::Inputs;
use crate::stream::TableWriter;
use crate::{tables, Progress, Result, StageError, Tables};

use super::layout::Layout;
use super::{depth, layout, noise, tracer};

/// Everything generated for one scene, before it becomes tables.
pub struct Generated {
    pub layout: Layout,
    pub cameras: Vec<CameraRow>,
    /// Per camera row: the rendering.
    pub images: Vec<tracer::Rendered>,
    /// The camera rows with pseudo labels (the left ones, and the fisheye ones when asked),
    /// and their pseudo labels.
    pub labelled: Vec<usize>,
    pub pseudo: Vec<Vec<u8>>,
    /// Per left camera row (frame order): stereo depth.
    pub stereo: Vec<Vec<f32>>,
    /// Per eval frame: LiDAR depth (left camera).
    pub lidar: Vec<(u32, Vec<f32>)>,
}

/// The street, its BVH and every camera row of the window, before anything is rendered.
struct Street {
    layout: Layout,
    bvh: Bvh,
    cameras: Vec<CameraRow>,
}

impl Street {
    fn build(p: &SceneParams) -> Result<Self> {
        let layout = layout::build(&p.layout_params()?);
        let bvh = Bvh::build(&layout.parts);
        let cameras: Vec<CameraRow> = p
            .frame_numbers()
            .flat_map(|f| {
                let eval = p.is_eval(f);
                rig(p, f)
                    .into_iter()
                    .chain(fisheye_rig(p, f))
                    .enumerate()
                    .filter(|(c, _)| p.cameras.contains(&(*c as u8)))
                    .map(move |(c, cam)| CameraRow {
                        frame: f,
                        camera: c as u8,
                        eval,
                        cam,
                    })
            })
            .collect();
        Ok(Self {
            layout,
            bvh,
            cameras,
        })
    }
}

/// What one camera row gives: its exact rendering and, where the row has them, pseudo labels
/// (left camera; fisheye cameras when asked), stereo depth (left) and LiDAR depth (left, eval
/// frames). Each from seeds of its own row, so any order of rows gives the same maps.
struct RowMaps {
    render: tracer::Rendered,
    pseudo: Option<Vec<u8>>,
    stereo: Option<Vec<f32>>,
    lidar: Option<Vec<f32>>,
}

fn has_pseudo_labels(p: &SceneParams, row: &CameraRow) -> bool {
    row.camera == 0 || (row.camera >= 2 && p.fisheye_pseudo_labels)
}

/// Stereo depth: the left camera's images.
fn has_stereo(row: &CameraRow) -> bool {
    row.camera == 0
}

/// LiDAR depth: the left camera's images of eval frames.
fn has_lidar(row: &CameraRow) -> bool {
    row.camera == 0 && row.eval
}

/// What the pseudo-label noise model needs of `row`'s rendering `img`.
fn noise_input<'a>(row: &CameraRow, img: &'a tracer::Rendered) -> noise::NoiseInput<'a> {
    noise::NoiseInput {
        width: row.cam.width as usize,
        height: row.cam.height as usize,
        labels: &img.labels,
        instances: &img.instances,
        overexposed: &img.overexposed,
    }
}

fn row_maps(p: &SceneParams, s: &Street, row: &CameraRow) -> RowMaps {
    let look = tracer::Look::of(p.seed, row.frame, row.camera, row.cam.width, row.cam.height);
    let world = tracer::World::at(&s.layout, &s.bvh, row.frame);
    let img = tracer::render(&world, &row.cam, &look, p.supersample);
    let pseudo = has_pseudo_labels(p, row).then(|| {
        let inp = noise_input(row, &img);
        // The left camera's noise as before; each fisheye camera its own.
        let seed = p.seed ^ ((row.camera as u64) << 40);
        let mut pl = noise::pseudo_labels(&inp, p.noise, seed, row.frame);
        noise::far_region_errors(
            &inp,
            &img.depth,
            &mut pl,
            p.noise_far_regions,
            p.noise,
            seed,
            row.frame,
        );
        for (l, &gt) in pl.iter_mut().zip(&img.labels) {
            if gt == labels::UNLABELED {
                *l = labels::UNLABELED; // outside a fisheye's lens
            }
        }
        pl
    });
    let stereo = has_stereo(row).then(|| {
        let (w, h) = (row.cam.width as usize, row.cam.height as usize);
        let model = depth::StereoModel {
            max_depth: p.stereo_max_depth_m,
            fb: row.cam.fx * p.baseline_m,
            width: w,
            height: h,
        };
        depth::stereo_depth(&model, &img.depth, &img.overexposed, p.seed, row.frame)
    });
    let lidar = has_lidar(row).then(|| {
        let cam = &row.cam;
        let r = cam.cam_to_world.matrix3;
        let origin = cam
            .cam_to_world
            .transform_point3(DVec3::new(0.3, -0.2, -0.3));
        let basis = [r * DVec3::Z, r * -DVec3::X, r * -DVec3::Y];
        let cast = |o: DVec3, d: DVec3| {
            let ray = crate::geometry::Ray { origin: o, dir: d };
            world.first_hit(&ray, 0.0, 1.0e4).map(|(h, ..)| h.t_in)
        };
        depth::lidar_depth(
            &depth::LidarModel::default(),
            origin,
            basis,
            cam.width,
            cam.height,
            cast,
            |q| cam.project(q),
            p.seed,
            row.frame,
        )
    });
    RowMaps {
        render: img,
        pseudo,
        stereo,
        lidar,
    }
}

/// Generates the whole scene in memory (tests; the stage streams it, [`write_tables`]).
pub fn generate(p: &SceneParams, progress: &dyn Progress) -> Result<Generated> {
    let s = Street::build(p)?;
    let total = s.cameras.len() as u64;
    let done = std::sync::atomic::AtomicU64::new(0);
    let maps: Vec<RowMaps> = s
        .cameras
        .par_iter()
        .map(|row| {
            let m = row_maps(p, &s, row);
            let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress.update(d, total, "rendering");
            m
        })
        .collect();
    let mut g = Generated {
        layout: s.layout,
        cameras: s.cameras,
        images: Vec::with_capacity(maps.len()),
        labelled: Vec::new(),
        pseudo: Vec::new(),
        stereo: Vec::new(),
        lidar: Vec::new(),
    };
    for (i, m) in maps.into_iter().enumerate() {
        g.images.push(m.render);
        if let Some(pl) = m.pseudo {
            g.labelled.push(i);
            g.pseudo.push(pl);
        }
        g.stereo.extend(m.stereo);
        g.lidar.extend(m.lidar.map(|l| (g.cameras[i].frame, l)));
    }
    Ok(g)
}

/// The per-image tables, written a camera row at a time (see [`crate::stream::TableWriter`]).
struct ImageTables {
    images: TableWriter,
    gt_semantic: TableWriter,
    gt_instance: TableWriter,
    gt_depth: TableWriter,
    pseudo_labels: TableWriter,
    stereo_depth: TableWriter,
    lidar_depth: TableWriter,
    /// Classes seen in any GT image so far (for `scene_info`).
    seen: [bool; 256],
}

impl ImageTables {
    fn open(inputs: &Inputs) -> Result<Self> {
        Ok(Self {
            images: inputs.writer("images")?,
            gt_semantic: inputs.writer("gt_semantic")?,
            gt_instance: inputs.writer("gt_instance")?,
            gt_depth: inputs.writer("gt_depth")?,
            pseudo_labels: inputs.writer("pseudo_labels")?,
            stereo_depth: inputs.writer("stereo_depth")?,
            lidar_depth: inputs.writer("lidar_depth")?,
            seen: [false; 256],
        })
    }

    /// Writes `row`'s maps to every table that has a row for it; each map is freed once its
    /// table holds it.
    fn push(&mut self, row: &CameraRow, m: RowMaps) -> Result<()> {
        let RowMaps {
            render,
            pseudo,
            stereo,
            lidar,
        } = m;
        for &l in &render.labels {
            self.seen[l as usize] = true;
        }
        let one = |name: &str, values| image_row(name, row, values);
        self.images
            .write(one("images", tables::binary([&render.rgb]))?)?;
        self.gt_semantic.write(one(
            "gt_semantic",
            tables::list::<UInt8Type>([render.labels]),
        )?)?;
        self.gt_instance.write(one(
            "gt_instance",
            tables::list::<UInt16Type>([render.instances]),
        )?)?;
        self.gt_depth.write(one(
            "gt_depth",
            tables::list::<Float32Type>([render.depth]),
        )?)?;
        if let Some(pl) = pseudo {
            self.pseudo_labels
                .write(one("pseudo_labels", tables::list::<UInt8Type>([pl]))?)?;
        }
        if let Some(d) = stereo {
            self.stereo_depth
                .write(one("stereo_depth", tables::list::<Float32Type>([d]))?)?;
        }
        if let Some(d) = lidar {
            self.lidar_depth
                .write(one("lidar_depth", tables::list::<Float32Type>([d]))?)?;
        }
        Ok(())
    }

    /// Ends every table and adds `scene_info`, `cameras` and `primitives` (small, whole).
    fn finish(
        self,
        p: &SceneParams,
        cameras: &[CameraRow],
        layout: &Layout,
        t: &mut Tables,
    ) -> Result<()> {
        annotation_tables(p, layout, self.seen, t)?;
        t.insert("cameras".into(), cameras_to_table(cameras)?);
        for w in [
            self.images,
            self.gt_semantic,
            self.gt_instance,
            self.gt_depth,
            self.pseudo_labels,
            self.stereo_depth,
            self.lidar_depth,
        ] {
            w.finish_into(t)?;
        }
        Ok(())
    }
}

/// `primitives` (the layout's boxes with `p.edits` applied), `dynamic_boxes` (the movers') and
/// `scene_info`, whose classes are those `seen` in any GT image, of any primitive, and sky.
pub fn annotation_tables(
    p: &SceneParams,
    layout: &Layout,
    mut seen: [bool; 256],
    t: &mut Tables,
) -> Result<()> {
    let prims = super::edits::apply(&layout.bounds, &p.edits)?;
    seen[SKY as usize] = true;
    for b in &prims {
        seen[b.label as usize] = true;
    }
    let classes: Vec<u8> = (0..=255u8).filter(|&c| seen[c as usize]).collect();
    t.insert(
        "scene_info".into(),
        tables::build(
            "scene_info",
            vec![
                tables::strings([p.name.as_str()]),
                tables::strings([p.sequence.as_str()]),
                tables::fixed_list::<Float64Type>(3, p.origin.to_vec()),
                tables::list::<UInt8Type>([classes]),
                tables::prim::<Float64Type>([p.baseline_m]),
            ],
        )?,
    );
    t.insert("primitives".into(), primitives_to_table(&prims)?);
    t.insert(
        "dynamic_boxes".into(),
        dynamic_boxes_to_table(&dynamic_boxes(p, layout))?,
    );
    Ok(())
}

/// The movers' boxes at every rendered frame they are in, sorted by (object, frame).
pub fn dynamic_boxes(p: &SceneParams, layout: &Layout) -> Vec<DynamicBox> {
    let mut boxes: Vec<DynamicBox> = layout
        .movers
        .iter()
        .flat_map(|m| {
            p.frame_numbers().filter_map(move |frame| {
                m.bound_at(frame).map(|primitive| DynamicBox {
                    object: m.object(),
                    frame,
                    primitive,
                })
            })
        })
        .collect();
    boxes.sort_by_key(|b| (b.object, b.frame));
    boxes
}

/// One row of a per-image table: `row`'s (frame, camera, width, height) and a value column.
fn image_row(name: &str, row: &CameraRow, values: ArrayRef) -> Result<RecordBatch> {
    tables::build(
        name,
        vec![
            tables::prim::<UInt32Type>([row.frame]),
            tables::prim::<UInt8Type>([row.camera]),
            tables::prim::<UInt32Type>([row.cam.width]),
            tables::prim::<UInt32Type>([row.cam.height]),
            values,
        ],
    )
}

/// Generates the scene and writes its tables through `inputs`' writers as each image is done
/// (the body of `run`): images are rendered in parallel in camera-row order and written in that
/// order, so memory holds a few images' maps, not the scene's (at full size with fisheye
/// cameras the maps take gigabytes). The tables equal [`to_tables`] of [`generate`].
pub fn write_tables(p: &SceneParams, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables> {
    let s = Street::build(p)?;
    let total = s.cameras.len() as u64;
    let mut out = ImageTables::open(inputs)?;
    // Rows are handed to the workers in order (`par_bridge`), so the writer below waits on few
    // of them; the bounded channel stops the workers when the writer falls behind.
    let (tx, rx) = std::sync::mpsc::sync_channel::<(usize, RowMaps)>(2);
    let street = &s;
    let written = std::thread::scope(|scope| -> Result<ImageTables> {
        let writer = scope.spawn(move || -> Result<ImageTables> {
            let mut waiting = std::collections::BTreeMap::new();
            let mut next = 0;
            for (i, m) in rx {
                waiting.insert(i, m);
                while let Some(m) = waiting.remove(&next) {
                    out.push(&street.cameras[next], m)?;
                    next += 1;
                    progress.update(next as u64, total, "rendering");
                }
            }
            if next != street.cameras.len() {
                return Err(StageError::Failed(format!(
                    "the synthetic scene wrote {next} of {} images",
                    street.cameras.len()
                )));
            }
            Ok(out)
        });
        // A send fails only when the writer stopped on an error, which `join` gives back.
        let _ = s
            .cameras
            .iter()
            .enumerate()
            .par_bridge()
            .try_for_each(|(i, row)| tx.send((i, row_maps(p, street, row))).map_err(|_| ()));
        drop(tx);
        writer
            .join()
            .map_err(|_| StageError::Failed("the synthetic scene's writer panicked".into()))?
    })?;
    let mut t = Tables::new();
    written.finish(p, &s.cameras, &s.layout, &mut t)?;
    Ok(t)
}

pub mod in_memory;
mod params;
mod rig;
pub use params::SceneParams;
pub use rig::{fisheye_rig, rig};
#[cfg(test)]
mod tests;
