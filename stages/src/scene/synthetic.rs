//! The synthetic urban street with ground truth, generated
//! deterministically from its params, standing in for a KITTI-360 sequence (which cannot be
//! downloaded here nor shipped).
//!
//! One run builds the street ([`layout`]), places a forward-moving stereo rig, renders every
//! image exactly ([`tracer`]), derives noisy pseudo labels ([`noise`]), weak stereo depth and
//! LiDAR depth ([`depth`]), and writes the tables of `data_schema/`: `scene_info`, `cameras`,
//! `primitives`, `images`, `pseudo_labels`, `stereo_depth`, `lidar_depth`, `gt_semantic`,
//! `gt_instance`, `gt_depth`. `export` writes the KITTI-360 layout ([`kitti360_export`]) and
//! colour previews ([`preview`]).
//!
//! Frames: the street's layout is `street_length_m` long with a frame every
//! `frame_spacing_m` (frame number k at x = k * spacing, like KITTI-360's frame numbers);
//! `first_frame` and `frames` choose the window that is rendered. The default window (16
//! frames x 2 cameras at 176x47) keeps the default pipeline trainable on 2 CPU cores.
//!
//! Cost (2 cores, dev profile with optimised dependencies): the default scene takes 0.35-0.9 s;
//! full KITTI-360 size (`scale` 1, 1408x376) about 0.7 s per image.

use arrow::datatypes::{Float32Type, Float64Type, UInt16Type, UInt32Type, UInt8Type};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::geometry::{
    cameras_to_table, primitives_to_table, Bvh, Camera, CameraRow, DAffine3, DMat3, DVec3, Lens,
    Mei,
};
use crate::labels::{self, PAPER_CLASSES, ROAD, SKY, TERRAIN};
use crate::{tables, Progress, Result, StageError, Tables};

use super::layout::{Layout, LayoutParams, RIG_Y};
use super::{depth, layout, noise, rng, tracer};

/// Parameters of the synthetic scene. Every field has a default.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
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
    /// Chance (at noise 1) that a far segment (mean depth beyond 30 m) is labelled whole as a
    /// class it is confused with, as networks fail on distant regions
    /// ([`noise::far_region_errors`]); 0 = off, the default.
    pub noise_far_regions: f64,
    /// Amount of surface detail in the procedural textures (per-stone, per-slab and grain
    /// variation on road, walls, facades, grass and foliage), 1 = the default street, 0 = every
    /// surface one flat colour between its joints, markings and windows (uniform asphalt
    /// and rendered walls, as on real streets). At 1/8 scale it barely changes the ablation:
    /// sensor noise, shading, joints and markings carry the matching (README, issue 19).
    pub texture: f64,
    /// Rays per pixel side for the image colours: 1 = one ray through the pixel centre (a
    /// point sample), n > 1 = the mean over n x n rays spread over the pixel, as a real sensor
    /// integrates its pixel's footprint. Labels and depth stay the centre ray's. At most 8.
    pub supersample: u32,
    /// Farthest depth stereo matching reports, metres.
    pub stereo_max_depth_m: f64,
    /// Classes that appear (paper class names); road, terrain and sky are required.
    pub classes: Vec<String>,
    /// Also render the two side fisheye cameras of KITTI-360 (camera 2, image_02, looking left;
    /// camera 3, image_03, looking right): its MEI calibration's shape, 1400x1400 at `scale` 1,
    /// about 190 degrees across the lens circle.
    pub fisheye: bool,
    /// Pseudo labels for the fisheye images too (a 2D network for fisheye images may not
    /// exist; without them those images train colour only).
    pub fisheye_pseudo_labels: bool,
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
            fisheye: false,
            fisheye_pseudo_labels: false,
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

    fn layout_params(&self) -> Result<LayoutParams> {
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

/// Generates the scene (the body of `run`, also used by tests).
pub fn generate(p: &SceneParams, progress: &dyn Progress) -> Result<Generated> {
    let layout = layout::build(&p.layout_params()?);
    let bvh = Bvh::build(&layout.parts);
    let cameras: Vec<CameraRow> = p
        .frame_numbers()
        .flat_map(|f| {
            let eval = p.is_eval(f);
            let fisheye = p.fisheye.then(|| fisheye_rig(p, f));
            rig(p, f)
                .into_iter()
                .chain(fisheye.into_iter().flatten())
                .enumerate()
                .map(move |(c, cam)| CameraRow {
                    frame: f,
                    camera: c as u8,
                    eval,
                    cam,
                })
        })
        .collect();
    let total = cameras.len() as u64;
    let done = std::sync::atomic::AtomicU64::new(0);
    let images: Vec<tracer::Rendered> = cameras
        .par_iter()
        .map(|row| {
            let look =
                tracer::Look::of(p.seed, row.frame, row.camera, row.cam.width, row.cam.height);
            let out = tracer::render(&layout, &bvh, &row.cam, &look, p.supersample);
            let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress.update(d, total, "rendering");
            out
        })
        .collect();
    let left: Vec<usize> = (0..cameras.len())
        .filter(|&i| cameras[i].camera == 0)
        .collect();
    let labelled: Vec<usize> = (0..cameras.len())
        .filter(|&i| cameras[i].camera == 0 || (cameras[i].camera >= 2 && p.fisheye_pseudo_labels))
        .collect();
    let pseudo: Vec<Vec<u8>> = labelled
        .par_iter()
        .map(|&i| {
            let (row, img) = (&cameras[i], &images[i]);
            let inp = noise::NoiseInput {
                width: row.cam.width as usize,
                height: row.cam.height as usize,
                labels: &img.labels,
                instances: &img.instances,
                overexposed: &img.overexposed,
            };
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
        })
        .collect();
    let stereo: Vec<Vec<f32>> = left
        .par_iter()
        .map(|&i| {
            let (row, img) = (&cameras[i], &images[i]);
            let (w, h) = (row.cam.width as usize, row.cam.height as usize);
            let model = depth::StereoModel {
                max_depth: p.stereo_max_depth_m,
                fb: row.cam.fx * p.baseline_m,
                width: w,
                height: h,
            };
            depth::stereo_depth(&model, &img.depth, &img.overexposed, p.seed, row.frame)
        })
        .collect();
    let lidar: Vec<(u32, Vec<f32>)> = left
        .par_iter()
        .filter(|&&i| cameras[i].eval)
        .map(|&i| {
            let cam = &cameras[i].cam;
            let r = cam.cam_to_world.matrix3;
            let origin = cam
                .cam_to_world
                .transform_point3(DVec3::new(0.3, -0.2, -0.3));
            let basis = [r * DVec3::Z, r * -DVec3::X, r * -DVec3::Y];
            let cast = |o: DVec3, d: DVec3| {
                let ray = crate::geometry::Ray { origin: o, dir: d };
                bvh.first_hit(&layout.parts, &ray, 0.0, 1.0e4)
                    .map(|h| h.t_in)
            };
            let d = depth::lidar_depth(
                &depth::LidarModel::default(),
                origin,
                basis,
                cam.width,
                cam.height,
                cast,
                |q| cam.project(q),
                p.seed,
                cameras[i].frame,
            );
            (cameras[i].frame, d)
        })
        .collect();
    Ok(Generated {
        layout,
        cameras,
        images,
        labelled,
        pseudo,
        stereo,
        lidar,
    })
}

/// The classes present in the scene: in any GT image or any primitive, plus sky.
fn classes_present(g: &Generated) -> Vec<u8> {
    let mut seen = [false; 256];
    seen[SKY as usize] = true;
    for img in &g.images {
        for &l in &img.labels {
            seen[l as usize] = true;
        }
    }
    for b in &g.layout.bounds {
        seen[b.label as usize] = true;
    }
    (0..=255u8).filter(|&c| seen[c as usize]).collect()
}

/// Builds one per-image table from (frame, camera, width, height) keys and a value column.
fn image_table(
    name: &str,
    keys: &[(u32, u8, u32, u32)],
    values: arrow::array::ArrayRef,
) -> Result<arrow::record_batch::RecordBatch> {
    tables::build(
        name,
        vec![
            tables::prim::<UInt32Type>(keys.iter().map(|k| k.0)),
            tables::prim::<UInt8Type>(keys.iter().map(|k| k.1)),
            tables::prim::<UInt32Type>(keys.iter().map(|k| k.2)),
            tables::prim::<UInt32Type>(keys.iter().map(|k| k.3)),
            values,
        ],
    )
}

/// Turns a generated scene into the stage's tables, freeing each image map as soon as its
/// column holds it (at full size the maps alone take gigabytes).
pub fn to_tables(p: &SceneParams, g: Generated) -> Result<Tables> {
    let key = |r: &CameraRow| (r.frame, r.camera, r.cam.width, r.cam.height);
    let all: Vec<_> = g.cameras.iter().map(key).collect();
    let left: Vec<_> = g
        .cameras
        .iter()
        .filter(|r| r.camera == 0)
        .map(key)
        .collect();
    let eval: Vec<_> = g
        .cameras
        .iter()
        .filter(|r| r.camera == 0 && r.eval)
        .map(key)
        .collect();
    let labelled: Vec<_> = g.labelled.iter().map(|&i| key(&g.cameras[i])).collect();
    let mut t = Tables::new();
    t.insert(
        "scene_info".into(),
        tables::build(
            "scene_info",
            vec![
                tables::strings([p.name.as_str()]),
                tables::strings([p.sequence.as_str()]),
                tables::fixed_list::<Float64Type>(3, p.origin.to_vec()),
                tables::list::<UInt8Type>([classes_present(&g)]),
                tables::prim::<Float64Type>([p.baseline_m]),
            ],
        )?,
    );
    t.insert("cameras".into(), cameras_to_table(&g.cameras)?);
    t.insert("primitives".into(), primitives_to_table(&g.layout.bounds)?);
    let Generated {
        mut images,
        pseudo,
        stereo,
        lidar,
        ..
    } = g;
    let mut put = |name: &str, keys: &[(u32, u8, u32, u32)], values| -> Result<()> {
        t.insert(name.into(), image_table(name, keys, values)?);
        Ok(())
    };
    put(
        "images",
        &all,
        tables::binary(images.iter().map(|i| &i.rgb)),
    )?;
    for i in &mut images {
        i.rgb = Vec::new();
        i.overexposed = Vec::new();
    }
    put(
        "gt_semantic",
        &all,
        tables::list::<UInt8Type>(images.iter_mut().map(|i| std::mem::take(&mut i.labels))),
    )?;
    put(
        "gt_instance",
        &all,
        tables::list::<UInt16Type>(images.iter_mut().map(|i| std::mem::take(&mut i.instances))),
    )?;
    put(
        "gt_depth",
        &all,
        tables::list::<Float32Type>(images.into_iter().map(|i| i.depth)),
    )?;
    put(
        "pseudo_labels",
        &labelled,
        tables::list::<UInt8Type>(pseudo),
    )?;
    put("stereo_depth", &left, tables::list::<Float32Type>(stereo))?;
    put(
        "lidar_depth",
        &eval,
        tables::list::<Float32Type>(lidar.into_iter().map(|l| l.1)),
    )?;
    Ok(t)
}

#[cfg(test)]
mod tests;
