//! The synthetic urban street with ground truth, generated
//! deterministically from its params, standing in for a KITTI-360 sequence (which cannot be
//! downloaded here nor shipped).
//!
//! One run builds the street ([`layout`]), places a forward-moving stereo rig, renders every
//! image exactly ([`tracer`]), derives noisy pseudo labels ([`noise`]), weak stereo depth and
//! LiDAR depth ([`depth`]), and writes the tables of `data_schema/`: `scene_info`, `cameras`,
//! `primitives`, `images`, `pseudo_labels`, `stereo_depth`, `lidar_depth`, `gt_semantic`,
//! `gt_instance`, `gt_depth`, an image at a time as each is rendered ([`write_tables`]: the
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
use serde::{Deserialize, Serialize};

use crate::geometry::{
    cameras_to_table, primitives_to_table, Bvh, Camera, CameraRow, DAffine3, DMat3, DVec3, Lens,
    Mei,
};
use crate::labels::{self, PAPER_CLASSES, ROAD, SKY, TERRAIN};
use crate::stage::Inputs;
use crate::stream::TableWriter;
use crate::{tables, Progress, Result, StageError, Tables};

use super::layout::{Layout, LayoutParams, RIG_Y};
use super::{depth, layout, noise, rng, tracer};

/// Parameters of the synthetic scene. Every field has a default.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct SceneParams {
    /// Seed of every random choice (layout, annotation jitter, exposure, noise, sensors).
    pub seed: u64,
    /// Human-readable scene name.
    pub name: String,
    /// KITTI-360 style sequence name used by the export.
    pub sequence: String,
    /// World position of the scene frame's origin (KITTI-like thousands of metres).
    pub origin: [f64; 3],
    /// Length of the driven street segment, metres.
    pub street_length_m: f64,
    /// Distance between consecutive frames, metres.
    pub frame_spacing_m: f64,
    /// First rendered frame number (frame k is at x = k * frame_spacing_m).
    pub first_frame: u32,
    /// Number of rendered frames (each with a left and a right image).
    pub frames: u32,
    /// Every `eval_every`-th frame of the window (counting from `first_frame`) is an
    /// evaluation frame.
    pub eval_every: u32,
    /// Image size relative to KITTI-360's 1408x376.
    pub scale: f64,
    /// Stereo baseline, metres.
    pub baseline_m: f64,
    /// Camera height above the road, metres.
    pub camera_height_m: f64,
    /// Pseudo-label noise level (0 = ground truth; 1 calibrated to about 65-70 mIoU).
    pub noise: f64,
    /// Chance (at noise 1) that a far segment is labelled whole as a class it is confused with.
    /// Far: a mean depth beyond 30 m; networks fail so on distant regions
    /// ([`noise::far_region_errors`]). 0 = off, the default.
    pub noise_far_regions: f64,
    /// Amount of surface detail in the procedural textures: 1 = the default street, 0 = none.
    /// Detail is per-stone, per-slab and grain variation on road, walls, facades, grass and
    /// foliage; at 0 every surface is one flat colour between its joints, markings and windows
    /// (uniform asphalt and rendered walls, as on real streets). At 1/8 scale it barely changes
    /// the ablation (docs/experiments/stereo-reach.md).
    pub texture: f64,
    /// Rays per pixel side for the image colours, 1..=8: n x n rays averaged over the pixel.
    /// 1 is a point sample through the pixel centre; more integrate the pixel's footprint as a
    /// real sensor does. Labels and depth stay the centre ray's.
    pub supersample: u32,
    /// Farthest depth stereo matching reports, metres.
    pub stereo_max_depth_m: f64,
    /// Classes that appear (paper class names); road, terrain and sky are required.
    pub classes: Vec<String>,
    /// Cameras rendered: the stereo pair `image_00`, `image_01`, and the fisheye cameras listed.
    /// KITTI-360's side fisheye cameras are `image_02` (looking left) and `image_03` (looking
    /// right), with its MEI calibration's shape, 1400x1400 at `scale` 1; numbers 0 .. 3 are read
    /// too. Every image has ground truth.
    #[serde(deserialize_with = "crate::geometry::camera::camera_ids")]
    #[schemars(with = "Vec<crate::geometry::camera::CameraName>")]
    pub cameras: Vec<u8>,
    /// Pseudo labels for the fisheye images too; without them those images train colour only.
    /// A 2D network for fisheye images may not exist.
    pub fisheye_pseudo_labels: bool,
    /// Edits of the generated primitives (reclassify, move, turn, resize, delete), in order.
    /// The images and GT stay those of the street: the edits change the annotation only.
    pub edits: Vec<super::edits::Edit>,
}

impl Default for SceneParams {
    fn default() -> Self {
        Self {
            seed: 0,
            name: "synthetic street".into(),
            sequence: "2099_01_01_drive_0000_sync".into(),
            origin: [4213.25, 1307.5, 115.75],
            street_length_m: 50.0,
            frame_spacing_m: 0.8,
            first_frame: 20,
            frames: 16,
            eval_every: 5,
            scale: 0.125,
            baseline_m: 0.6,
            camera_height_m: 1.55,
            noise: 1.0,
            noise_far_regions: 0.0,
            texture: 1.0,
            supersample: 1,
            stereo_max_depth_m: 15.0,
            classes: PAPER_CLASSES
                .iter()
                .map(|&c| labels::by_id(c).expect("paper class").name.to_string())
                .collect(),
            cameras: vec![0, 1],
            fisheye_pseudo_labels: false,
            edits: Vec::new(),
        }
    }
}

/// KITTI-360's rectified perspective cameras at full size.
const KITTI_WIDTH: f64 = 1408.0;
const KITTI_HEIGHT: f64 = 376.0;
const KITTI_F: f64 = 552.554261;
const KITTI_CX: f64 = 682.049453;
const KITTI_CY: f64 = 238.769549;

/// KITTI-360's fisheye cameras (image_02, image_03) at full size: the shape of their MEI
/// calibration (rounded), and where they sit in the left camera's frame (x right, y down, z
/// forward), metres.
const FISHEYE_SIDE: f64 = 1400.0;
const FISHEYE_GAMMA: [f64; 2] = [1336.3, 1335.8];
const FISHEYE_CENTRE: [f64; 2] = [716.9, 705.8];
const FISHEYE_MEI: Mei = Mei {
    xi: 2.2134,
    k1: 0.01693,
    k2: 1.6798,
    p1: 4.2e-4,
    p2: 4.2e-4,
    max_half_angle_deg: crate::geometry::FISHEYE_HALF_ANGLE_DEG,
};
const FISHEYE_POSITION: [[f64; 3]; 2] = [[-0.7, -0.1, -0.8], [1.3, -0.1, -0.8]];

impl SceneParams {
    /// Label ids of the `classes` param (validated).
    pub fn class_ids(&self) -> Result<Vec<u8>> {
        let mut ids = Vec::new();
        for name in &self.classes {
            let l = labels::by_name(name)
                .filter(|l| PAPER_CLASSES.contains(&l.id))
                .ok_or_else(|| {
                    StageError::Params(format!(
                        "`classes`: unknown class `{name}` (known: {})",
                        PAPER_CLASSES
                            .iter()
                            .map(|&c| labels::by_id(c).unwrap().name)
                            .collect::<Vec<_>>()
                            .join(", ")
                    ))
                })?;
            ids.push(l.id);
        }
        for need in [ROAD, TERRAIN, SKY] {
            if !ids.contains(&need) {
                return Err(StageError::Params(format!(
                    "`classes` must include `{}` (the ground and the sky need it)",
                    labels::by_id(need).unwrap().name
                )));
            }
        }
        ids.sort_unstable();
        ids.dedup();
        Ok(ids)
    }

    /// Image size.
    pub fn image_size(&self) -> (u32, u32) {
        (
            (KITTI_WIDTH * self.scale).round() as u32,
            (KITTI_HEIGHT * self.scale).round() as u32,
        )
    }

    /// Number of frame positions along the street.
    pub fn street_frames(&self) -> u32 {
        (self.street_length_m / self.frame_spacing_m).floor() as u32 + 1
    }

    /// The rendered frame numbers.
    pub fn frame_numbers(&self) -> impl Iterator<Item = u32> {
        self.first_frame..self.first_frame + self.frames
    }

    pub fn is_eval(&self, frame: u32) -> bool {
        (frame - self.first_frame) % self.eval_every == 0
    }

    pub(crate) fn layout_params(&self) -> Result<LayoutParams> {
        Ok(LayoutParams {
            seed: self.seed,
            street_length: self.street_length_m,
            classes: self.class_ids()?,
            texture: self.texture,
        })
    }

    /// Checks ranges and consistency; errors name the parameter.
    pub fn validate(&self) -> Result<()> {
        let p = self;
        let bad = |m: String| Err(StageError::Params(m));
        if p.frames == 0 {
            return bad("`frames` must be at least 1".into());
        }
        super::edits::check(&p.edits, None)?;
        if !(p.scale.is_finite() && p.scale > 0.0) {
            return bad(format!("`scale` must be positive, got {}", p.scale));
        }
        if p.scale > 2.0 {
            return bad(format!(
                "`scale` must be at most 2 (2816x752), got {}",
                p.scale
            ));
        }
        let (w, h) = p.image_size();
        if w < 16 || h < 4 {
            return bad(format!(
                "`scale` {} gives {w}x{h} images; use at least {:.3} (16x4)",
                p.scale,
                16.0 / KITTI_WIDTH
            ));
        }
        if !(1..=8).contains(&p.supersample) {
            return bad(format!(
                "`supersample` must be 1..=8 rays per pixel side, got {}",
                p.supersample
            ));
        }
        if !(p.street_length_m.is_finite()
            && p.street_length_m > 0.0
            && p.street_length_m <= 2000.0)
        {
            return bad(format!(
                "`street_length_m` must be in (0, 2000], got {}",
                p.street_length_m
            ));
        }
        if !(p.frame_spacing_m.is_finite() && p.frame_spacing_m > 0.0) {
            return bad(format!(
                "`frame_spacing_m` must be positive, got {}",
                p.frame_spacing_m
            ));
        }
        let n = p.street_frames();
        if p.first_frame as u64 + p.frames as u64 > n as u64 {
            return bad(format!(
                "frames {}..{} run past the street: {} m at {} m spacing has frames 0..{}; \
                 lower `first_frame` or `frames`, or lengthen `street_length_m`",
                p.first_frame,
                p.first_frame as u64 + p.frames as u64 - 1,
                p.street_length_m,
                p.frame_spacing_m,
                n - 1
            ));
        }
        if p.eval_every == 0 {
            return bad("`eval_every` must be at least 1".into());
        }
        if !(p.cameras.contains(&0) && p.cameras.contains(&1)) || p.cameras.iter().any(|&c| c > 3) {
            return bad(format!(
                "`cameras` = {:?}: the synthetic street renders the stereo pair image_00, image_01 \
                 and any of the fisheye cameras image_02, image_03",
                p.cameras
            ));
        }
        if !(p.baseline_m.is_finite() && p.baseline_m > 0.0 && p.baseline_m < 5.0) {
            return bad(format!(
                "`baseline_m` must be in (0, 5), got {}",
                p.baseline_m
            ));
        }
        if !(p.camera_height_m.is_finite() && p.camera_height_m > 0.3 && p.camera_height_m < 5.0) {
            return bad(format!(
                "`camera_height_m` must be in (0.3, 5), got {}",
                p.camera_height_m
            ));
        }
        if !(p.noise.is_finite() && (0.0..=10.0).contains(&p.noise)) {
            return bad(format!("`noise` must be in [0, 10], got {}", p.noise));
        }
        if !(p.texture.is_finite() && (0.0..=1.0).contains(&p.texture)) {
            return bad(format!("`texture` must be in [0, 1], got {}", p.texture));
        }
        if !(p.noise_far_regions.is_finite() && (0.0..=1.0).contains(&p.noise_far_regions)) {
            return bad(format!(
                "`noise_far_regions` must be in [0, 1], got {}",
                p.noise_far_regions
            ));
        }
        if !(p.stereo_max_depth_m.is_finite() && p.stereo_max_depth_m > 0.0) {
            return bad(format!(
                "`stereo_max_depth_m` must be positive, got {}",
                p.stereo_max_depth_m
            ));
        }
        if p.origin.iter().any(|v| !v.is_finite()) {
            return bad("`origin` must be finite".into());
        }
        if p.sequence.is_empty() || p.sequence.contains(['/', '\\']) {
            return bad(format!(
                "`sequence` must be a plain directory name, got `{}`",
                p.sequence
            ));
        }
        p.class_ids().map(|_| ())
    }
}

/// The left (camera 0) and right (camera 1) cameras of `frame`.
pub fn rig(p: &SceneParams, frame: u32) -> [Camera; 2] {
    let (width, height) = p.image_size();
    let s = width as f64 / KITTI_WIDTH;
    let (rot, pos) = rig_pose(p, frame);
    let cam = |centre: DVec3| Camera {
        width,
        height,
        fx: KITTI_F * s,
        fy: KITTI_F * s,
        // KITTI's principal point is in OpenCV pixel coordinates (centres at integers); ours
        // has pixel (0, 0) spanning [0, 1), hence the half-pixel shift before scaling.
        cx: (KITTI_CX + 0.5) * s,
        cy: (KITTI_CY + 0.5) * (height as f64 / KITTI_HEIGHT),
        lens: Lens::Pinhole,
        cam_to_world: DAffine3::from_mat3_translation(rot, centre),
    };
    let right = pos + rot * DVec3::new(p.baseline_m, 0.0, 0.0);
    [cam(pos), cam(right)]
}

/// The side fisheye cameras of `frame` (cameras 2 and 3): left-looking, with its x axis
/// forward, and right-looking, with its x axis backward, both with the left camera's y (down).
pub fn fisheye_rig(p: &SceneParams, frame: u32) -> [Camera; 2] {
    let side = (FISHEYE_SIDE * p.scale).round().max(8.0) as u32;
    let s = side as f64 / FISHEYE_SIDE;
    let (rot, pos) = rig_pose(p, frame);
    let looking = [
        DMat3::from_cols(DVec3::Z, DVec3::Y, -DVec3::X),
        DMat3::from_cols(-DVec3::Z, DVec3::Y, DVec3::X),
    ];
    std::array::from_fn(|k| Camera {
        width: side,
        height: side,
        fx: FISHEYE_GAMMA[0] * s,
        fy: FISHEYE_GAMMA[1] * s,
        cx: (FISHEYE_CENTRE[0] + 0.5) * s,
        cy: (FISHEYE_CENTRE[1] + 0.5) * s,
        lens: Lens::Mei(FISHEYE_MEI),
        cam_to_world: DAffine3::from_mat3_translation(
            rot * looking[k],
            pos + rot * DVec3::from_array(FISHEYE_POSITION[k]),
        ),
    })
}

/// The left camera's axes and centre in the scene frame at `frame`.
fn rig_pose(p: &SceneParams, frame: u32) -> (DMat3, DVec3) {
    // A little deterministic wobble of heading and pitch, like a real drive.
    let mut r = rng::Rng::new(p.seed, rng::Purpose::Layout, &[0xCA, frame as u64]);
    let (yaw, pitch) = (r.normal() * 0.006, r.normal() * 0.004);
    // Camera axes (x right, y down, z forward) in the scene frame (x forward, y left, z up).
    let base = DMat3::from_cols(-DVec3::Y, -DVec3::Z, DVec3::X);
    let rot = DMat3::from_rotation_z(yaw) * DMat3::from_rotation_y(-pitch) * base;
    let pos = DVec3::new(
        frame as f64 * p.frame_spacing_m,
        RIG_Y + r.normal() * 0.05,
        p.camera_height_m,
    );
    (rot, pos)
}

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
    let img = tracer::render(&s.layout, &s.bvh, &row.cam, &look, p.supersample);
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
            s.bvh
                .first_hit(&s.layout.parts, &ray, 0.0, 1.0e4)
                .map(|h| h.t_in)
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

/// `primitives` (the layout's boxes with `p.edits` applied) and `scene_info`, whose classes are
/// those `seen` in any GT image, of any primitive, and sky.
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
    Ok(())
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
#[cfg(test)]
mod tests;
