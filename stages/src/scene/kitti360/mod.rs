//! The `kitti360_scene` stage kind: the tables of `synthetic_scene` (scene_info, cameras,
//! primitives, images, pseudo_labels, stereo_depth, lidar_depth, gt_semantic, gt_instance,
//! gt_depth) read from a directory in the KITTI-360 layout (REFERENCE.md section 2), so real
//! data (or data exported by `pipe export` of a synthetic scene) runs through the same pipeline.
//!
//! What it reads, relative to `root` (`{seq}` = `sequence`, `{cam}` = `00`/`01`, `{frame}` or
//! `%010d` = the ten-digit frame number):
//!
//! ```text
//! data_poses/{seq}/cam0_to_world.txt                  poses (frames need not be contiguous)
//! calibration/perspective.txt                         P_rect_00/01, S_rect_00, R_rect_00
//! data_3d_bboxes/train/{seq}.xml                      primitives (param `bboxes`)
//! data_2d_raw/{seq}/image_{cam}/data_rect/{frame}.png images
//! pseudo_labels/{seq}/image_00/{frame}.png            noisy labels (param `pseudo_labels`)
//! param `stereo_depth` (optional)                     16-bit metres*256 PNGs, left camera
//! params `gt_semantic`, `gt_instance` (optional)      KITTI-360 semantic/instance PNGs
//! param `lidar` + `lidar_calib` (optional)            velodyne .bin for evaluation frames
//! ```
//!
//! Frames: `frames` if given (each must have a pose), else every frame in
//! `[first_frame, last_frame]` that has a pose (KITTI-360 poses are not contiguous; frames
//! without one are skipped). Primitives: static objects only (`timestamp` -1), kept when their
//! world bounds come within `max_distance_m` of a selected camera centre; the unit cube becomes
//! a `cuboid`, anything else a closed `mesh`. Everything is recentred on `origin` in f64.
//! Tables with no source (no stereo-depth directory, no LiDAR, never GT depth) have no rows.
//!
//! Cache keying: [`input_files`] lists every file a run with given params reads, so the runner
//! can hash them into the stage key (see the module's report for the hook it needs).

pub mod parse;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use arrow::array::ArrayRef;
use arrow::datatypes::{Float32Type, Float64Type, UInt16Type, UInt32Type, UInt8Type};
use arrow::record_batch::RecordBatch;
use glam::{DAffine3, DVec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::geometry::{cameras_to_table, primitives_to_table, Camera, CameraRow, Primitive, Shape};
use crate::labels::{self, SKY};
use crate::{tables, Progress, Result, StageError, Tables};

use parse::err;

/// Where `pipe export scene` writes the LiDAR scans (KITTI-360's own layout); `lidar` is off
/// by default because the scans are a large, separate download.
pub const LIDAR_PATTERN: &str = "data_3d_raw/{seq}/velodyne_points/data/{frame}.bin";
/// Where `pipe export scene` writes the weak stereo depth (KITTI-360 has no such directory).
pub const STEREO_DEPTH_PATTERN: &str = "stereo_depth/{seq}/image_00/{frame}.png";

/// Parameters of `kitti360_scene`. Paths are relative to `root` unless absolute.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Kitti360Params {
    /// The KITTI-360 root directory (holding data_2d_raw/, data_poses/, calibration/, ...).
    pub root: String,
    /// Sequence directory name, e.g. `2013_05_28_drive_0000_sync`.
    pub sequence: String,
    /// First frame of the range (inclusive); frames without a pose are skipped.
    pub first_frame: u32,
    /// Last frame of the range (inclusive).
    pub last_frame: u32,
    /// Explicit frame list; overrides the range when non-empty. Each must have a pose.
    pub frames: Vec<u32>,
    /// Cameras to load: 0 = left (image_00), 1 = right (image_01).
    pub cameras: Vec<u8>,
    /// Evaluation frames; when empty, every `eval_every`-th selected frame from the first.
    pub eval_frames: Vec<u32>,
    /// See `eval_frames` (0 = no evaluation frames unless listed).
    pub eval_every: u32,
    /// Pose file.
    pub poses: String,
    /// Rectified calibration file.
    pub calibration: String,
    /// The 3D bounding primitives XML.
    pub bboxes: String,
    /// Rectified images.
    pub images: String,
    /// Noisy 2D semantic labels of the left camera (8-bit label ids).
    pub pseudo_labels: String,
    /// Optional weak depth of the left camera (16-bit PNG, metres * 256, 0 = none); null when the
    /// pipeline computes it with the `stereo_depth` stage.
    pub stereo_depth: Option<String>,
    /// Optional GT semantic PNGs (8-bit ids); frames without a file have no GT row, but every
    /// evaluation frame needs one.
    pub gt_semantic: Option<String>,
    /// Optional GT instance PNGs (16-bit, id*1000 + instance); same rule as `gt_semantic`.
    pub gt_instance: Option<String>,
    /// Optional velodyne scans for evaluation depth (evaluation frames, left camera).
    pub lidar: Option<String>,
    /// Unrectified camera 0 -> velodyne (3x4), used with `lidar`.
    pub lidar_calib: String,
    /// Primitives farther than this from every selected camera centre are dropped, metres.
    pub max_distance_m: f64,
    /// World position of the scene frame's origin; null = the first left camera's centre
    /// rounded to whole metres.
    pub origin: Option<[f64; 3]>,
    /// Human-readable scene name; empty = "<sequence> frames <first>-<last>".
    pub name: String,
}

impl Default for Kitti360Params {
    fn default() -> Self {
        Self {
            root: "KITTI-360".into(),
            sequence: "2013_05_28_drive_0000_sync".into(),
            first_frame: 0,
            last_frame: 63,
            frames: Vec::new(),
            cameras: vec![0, 1],
            eval_frames: Vec::new(),
            eval_every: 5,
            poses: "data_poses/{seq}/cam0_to_world.txt".into(),
            calibration: "calibration/perspective.txt".into(),
            bboxes: "data_3d_bboxes/train/{seq}.xml".into(),
            images: "data_2d_raw/{seq}/image_{cam}/data_rect/{frame}.png".into(),
            pseudo_labels: "pseudo_labels/{seq}/image_00/%010d.png".into(),
            stereo_depth: None,
            gt_semantic: Some(
                "data_2d_semantics/train/{seq}/image_{cam}/semantic/{frame}.png".into(),
            ),
            gt_instance: Some(
                "data_2d_semantics/train/{seq}/image_{cam}/instance/{frame}.png".into(),
            ),
            lidar: None,
            lidar_calib: "calibration/calib_cam_to_velo.txt".into(),
            max_distance_m: 80.0,
            origin: None,
            name: String::new(),
        }
    }
}

impl Kitti360Params {
    /// A pattern resolved against `root` for one frame and camera.
    pub fn path(&self, pattern: &str, frame: u32, camera: u8) -> PathBuf {
        let s = pattern
            .replace("{seq}", &self.sequence)
            .replace("{cam}", &format!("{camera:02}"))
            .replace("{frame}", &format!("{frame:010}"))
            .replace("%010d", &format!("{frame:010}"));
        Path::new(&self.root).join(s)
    }

    fn file(&self, pattern: &str) -> PathBuf {
        self.path(pattern, 0, 0)
    }

    /// The selected frames, given the frames that have a pose.
    pub fn select_frames(&self, posed: &BTreeMap<u32, DAffine3>) -> Result<Vec<u32>> {
        let frames: Vec<u32> = if self.frames.is_empty() {
            posed
                .range(self.first_frame..=self.last_frame)
                .map(|(&f, _)| f)
                .collect()
        } else {
            let mut f = self.frames.clone();
            f.sort_unstable();
            f.dedup();
            if let Some(m) = f.iter().find(|f| !posed.contains_key(f)) {
                return Err(err(
                    &self.file(&self.poses),
                    format!("frame {m} (listed in `frames`) has no pose"),
                ));
            }
            f
        };
        if frames.is_empty() {
            return Err(err(
                &self.file(&self.poses),
                format!(
                    "no frame in [{}, {}] has a pose (posed frames: {}..={})",
                    self.first_frame,
                    self.last_frame,
                    posed.keys().next().unwrap_or(&0),
                    posed.keys().last().unwrap_or(&0)
                ),
            ));
        }
        Ok(frames)
    }

    /// Whether `frame` (the `k`-th selected frame) is an evaluation frame.
    fn is_eval(&self, k: usize, frame: u32) -> bool {
        if self.eval_frames.is_empty() {
            self.eval_every > 0 && k % self.eval_every as usize == 0
        } else {
            self.eval_frames.contains(&frame)
        }
    }

    /// Checks the parameters; errors name them.
    pub fn validate(&self) -> Result<()> {
        let p = self;
        let bad = |m: String| Err(StageError::Params(m));
        if p.root.is_empty() {
            return bad("`root` must name the KITTI-360 directory".into());
        }
        if p.sequence.is_empty() || p.sequence.contains(['/', '\\']) {
            return bad(format!(
                "`sequence` must be a plain directory name, got `{}`",
                p.sequence
            ));
        }
        if p.frames.is_empty() && p.first_frame > p.last_frame {
            return bad(format!(
                "`first_frame` {} is after `last_frame` {}",
                p.first_frame, p.last_frame
            ));
        }
        if p.cameras.is_empty() || p.cameras.iter().any(|&c| c > 1) {
            return bad("`cameras` must list 0 and/or 1".into());
        }
        let mut c = p.cameras.clone();
        c.sort_unstable();
        c.dedup();
        if c != p.cameras {
            return bad("`cameras` must be ascending without repeats, e.g. [0, 1]".into());
        }
        if !(p.max_distance_m.is_finite() && p.max_distance_m > 0.0) {
            return bad(format!(
                "`max_distance_m` must be positive, got {}",
                p.max_distance_m
            ));
        }
        if p.origin.is_some_and(|o| o.iter().any(|v| !v.is_finite())) {
            return bad("`origin` must be finite".into());
        }
        Ok(())
    }
}

/// Every file a run with these params reads (existing or not), in a fixed order: the runner
/// hashes them into the stage's cache key. Reads the pose file to resolve the frame range.
pub fn input_files(p: &Kitti360Params) -> Result<Vec<PathBuf>> {
    let pose_path = p.file(&p.poses);
    let posed = parse::poses(&pose_path, &parse::read_text(&pose_path)?)?;
    let frames = p.select_frames(&posed)?;
    let mut out = vec![pose_path, p.file(&p.calibration), p.file(&p.bboxes)];
    if p.lidar.is_some() {
        out.push(p.file(&p.lidar_calib));
    }
    for (k, &f) in frames.iter().enumerate() {
        for &c in &p.cameras {
            out.push(p.path(&p.images, f, c));
            for pat in [&p.gt_semantic, &p.gt_instance].into_iter().flatten() {
                out.push(p.path(pat, f, c));
            }
        }
        if p.cameras.contains(&0) {
            out.push(p.path(&p.pseudo_labels, f, 0));
            if let Some(s) = &p.stereo_depth {
                out.push(p.path(s, f, 0));
            }
            if let Some(l) = p.lidar.as_ref().filter(|_| p.is_eval(k, f)) {
                out.push(p.path(l, f, 0));
            }
        }
    }
    Ok(out)
}

/// The primitives of the XML that matter for cameras at `centres` (scene frame), recentred.
fn load_primitives(
    path: &Path,
    objects: Vec<parse::XmlObject>,
    origin: DVec3,
    centres: &[DVec3],
    max_distance: f64,
) -> Result<Vec<Primitive>> {
    let near = |b: &crate::geometry::Aabb| {
        centres.iter().any(|c| {
            let q = c.clamp(b.min, b.max);
            q.distance(*c) <= max_distance
        })
    };
    let (total, mut dynamic) = (objects.len(), 0);
    let mut out = Vec::new();
    for o in objects {
        let at = &o.element;
        let label = i16::try_from(o.semantic_id)
            .ok()
            .and_then(labels::by_kitti_id)
            .ok_or_else(|| {
                err(
                    path,
                    format!(
                        "<{at}>/<semanticId>: {} is not a KITTI-360 kittiId",
                        o.semantic_id
                    ),
                )
            })?;
        if o.timestamp != -1 {
            dynamic += 1;
            continue; // dynamic object: one box per timestamp, not a static primitive
        }
        let instance = if label.has_instances {
            u32::try_from(o.instance_id)
                .ok()
                .filter(|&i| i < labels::INSTANCE_FACTOR)
                .ok_or_else(|| {
                    err(
                        path,
                        format!(
                            "<{at}>/<instanceId>: {} is outside 0..999 for class {}",
                            o.instance_id, label.name
                        ),
                    )
                })?
        } else {
            0
        };
        let mut to_world = o.transform;
        to_world.translation -= origin;
        let shape = if is_unit_cube(&o.vertices, &o.faces) {
            Shape::Cuboid
        } else {
            Shape::Mesh {
                vertices: o.vertices,
                faces: o.faces,
            }
        };
        let p = Primitive::new(shape, to_world, label.id, instance)
            .map_err(|e| err(path, format!("<{at}> ({}): {e}", label.name)))?;
        if near(&p.aabb()) {
            out.push(p);
        }
    }
    if out.is_empty() {
        // Nothing to transfer labels from: every ray would be sky.
        return Err(err(
            path,
            format!(
                "no static object within {max_distance} m of the selected cameras (the file has \
                 {total} object(s): {dynamic} dynamic, {} farther away); at least one 3D \
                 primitive is needed",
                total - dynamic
            ),
        ));
    }
    Ok(out)
}

/// Whether a mesh is KITTI-360's unit cube: the 8 corners of `[-0.5, 0.5]^3` and 12 triangles.
fn is_unit_cube(v: &[DVec3], f: &[[u32; 3]]) -> bool {
    if v.len() != 8 || f.len() != 12 {
        return false;
    }
    let mut seen = [false; 8];
    for q in v {
        let bit = |x: f64| -> Option<usize> {
            if (x - 0.5).abs() < 1e-9 {
                Some(1)
            } else if (x + 0.5).abs() < 1e-9 {
                Some(0)
            } else {
                None
            }
        };
        match (bit(q.x), bit(q.y), bit(q.z)) {
            (Some(a), Some(b), Some(c)) => seen[a | b << 1 | c << 2] = true,
            _ => return false,
        }
    }
    seen.iter().all(|&s| s) && crate::geometry::mesh::Mesh::new(v, f).is_ok()
}

/// A per-image table from (frame, camera, width, height) keys and a value column.
fn image_table(name: &str, keys: &[(u32, u8, u32, u32)], values: ArrayRef) -> Result<RecordBatch> {
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

type Key = (u32, u8, u32, u32);

/// Loads one optional per-image file for every key; `None` for keys whose file is absent.
fn load_each<T: Send>(
    keys: &[Key],
    path_of: impl Fn(&Key) -> PathBuf + Sync,
    load: impl Fn(&Path, &Key) -> Result<T> + Sync,
    required: bool,
) -> Result<Vec<Option<T>>> {
    keys.par_iter()
        .map(|k| {
            let path = path_of(k);
            if !required && !path.exists() {
                return Ok(None);
            }
            load(&path, k).map(Some)
        })
        .collect()
}

/// LiDAR z-depth in the left rectified camera (nearest return per pixel, 0 < z <= 100 m, the
/// synthetic scanner's range).
fn lidar_depth(points: &[DVec3], velo_to_rect: &DAffine3, cam: &Camera) -> Vec<f32> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut d = vec![0f32; w * h];
    for p in points {
        let q = velo_to_rect.transform_point3(*p);
        if !(q.z > 0.0 && q.z <= 100.0) {
            continue;
        }
        let u = cam.fx * q.x / q.z + cam.cx;
        let v = cam.fy * q.y / q.z + cam.cy;
        if u < 0.0 || v < 0.0 || u >= w as f64 || v >= h as f64 {
            continue;
        }
        let i = v as usize * w + u as usize;
        if d[i] == 0.0 || (q.z as f32) < d[i] {
            d[i] = q.z as f32;
        }
    }
    d
}

/// Reads the scene (the body of `run`).
pub fn load(p: &Kitti360Params, progress: &dyn Progress) -> Result<Tables> {
    let pose_path = p.file(&p.poses);
    let posed = parse::poses(&pose_path, &parse::read_text(&pose_path)?)?;
    let frames = p.select_frames(&posed)?;
    let calib_path = p.file(&p.calibration);
    let calib = parse::perspective(&calib_path, &parse::read_text(&calib_path)?)?;
    let origin = match p.origin {
        Some(o) => DVec3::from_array(o),
        None => posed[&frames[0]].translation.round(),
    };
    progress.update(0, 4, "poses and calibration");

    // Cameras, recentred in f64.
    let mut cameras = Vec::new();
    for (k, &f) in frames.iter().enumerate() {
        let mut pose = posed[&f];
        pose.translation -= origin;
        for &c in &p.cameras {
            let mut cam_to_world = pose;
            if c == 1 {
                cam_to_world.translation += pose.matrix3 * DVec3::new(calib.baseline, 0.0, 0.0);
            }
            cameras.push(CameraRow {
                frame: f,
                camera: c,
                eval: p.is_eval(k, f),
                cam: Camera {
                    width: calib.width,
                    height: calib.height,
                    fx: calib.fx,
                    fy: calib.fy,
                    cx: calib.cx_file + 0.5,
                    cy: calib.cy_file + 0.5,
                    cam_to_world,
                },
            });
        }
    }
    let centres: Vec<DVec3> = cameras.iter().map(|r| r.cam.centre()).collect();

    // Primitives.
    let xml_path = p.file(&p.bboxes);
    let objects = parse::bboxes(&xml_path, &parse::read_text(&xml_path)?)?;
    let prims = load_primitives(&xml_path, objects, origin, &centres, p.max_distance_m)?;
    progress.update(1, 4, "primitives");

    // Images and labels.
    let (w, h) = (calib.width, calib.height);
    let all: Vec<Key> = cameras.iter().map(|r| (r.frame, r.camera, w, h)).collect();
    let left: Vec<Key> = all.iter().copied().filter(|k| k.1 == 0).collect();
    let rgb = load_each(
        &all,
        |k| p.path(&p.images, k.0, k.1),
        |path, _| parse::rgb(path, w, h),
        true,
    )?;
    let pseudo = load_each(
        &left,
        |k| p.path(&p.pseudo_labels, k.0, 0),
        |path, _| parse::labels(path, w, h),
        true,
    )?;
    progress.update(2, 4, "images");
    let optional = |pat: &Option<String>| pat.clone();
    let gt_sem = match optional(&p.gt_semantic) {
        Some(pat) => load_each(
            &all,
            |k| p.path(&pat, k.0, k.1),
            |path, _| parse::labels(path, w, h),
            false,
        )?,
        None => vec![None; all.len()],
    };
    let gt_inst = match optional(&p.gt_instance) {
        Some(pat) => load_each(
            &all,
            |k| p.path(&pat, k.0, k.1),
            |path, _| {
                let v = parse::gray16(path, w, h, "instance")?;
                if let Some(i) = v.iter().position(|&x| {
                    labels::by_id((x as u32 / labels::INSTANCE_FACTOR) as u8).is_none()
                        || x as u32 / labels::INSTANCE_FACTOR > 255
                }) {
                    return Err(err(
                        path,
                        format!(
                            "pixel ({}, {}): {} is not id*1000 + instance of a KITTI-360 label",
                            i % w as usize,
                            i / w as usize,
                            v[i]
                        ),
                    ));
                }
                Ok(v)
            },
            false,
        )?,
        None => vec![None; all.len()],
    };
    for (i, r) in cameras.iter().enumerate() {
        if r.eval && (p.gt_semantic.is_some() && gt_sem[i].is_none()) {
            return Err(err(
                &p.path(p.gt_semantic.as_deref().unwrap_or(""), r.frame, r.camera),
                format!(
                    "missing: frame {} camera {} is an evaluation frame and needs GT labels",
                    r.frame, r.camera
                ),
            ));
        }
        if r.eval && (p.gt_instance.is_some() && gt_inst[i].is_none()) {
            return Err(err(
                &p.path(p.gt_instance.as_deref().unwrap_or(""), r.frame, r.camera),
                format!(
                    "missing: frame {} camera {} is an evaluation frame and needs GT instances",
                    r.frame, r.camera
                ),
            ));
        }
    }
    let stereo = match &p.stereo_depth {
        Some(pat) => load_each(
            &left,
            |k| p.path(pat, k.0, 0),
            |path, _| {
                let v = parse::gray16(path, w, h, "depth (metres * 256)")?;
                Ok(v.iter().map(|&x| x as f32 / 256.0).collect::<Vec<f32>>())
            },
            true,
        )?,
        None => Vec::new(),
    };
    progress.update(3, 4, "labels");

    // LiDAR for evaluation frames.
    let mut lidar: Vec<(Key, Vec<f32>)> = Vec::new();
    if let Some(pat) = &p.lidar {
        let calib_path = p.file(&p.lidar_calib);
        let text = parse::read_text(&calib_path).map_err(|e| {
            StageError::Input(format!(
                "{e} (the camera -> velodyne calibration `lidar_calib`, needed to project the \
                 `lidar` scans)"
            ))
        })?;
        let cam_to_velo = parse::cam_to_velo(&calib_path, &text)?;
        let velo_to_rect = DAffine3::from_mat3(calib.r_rect) * cam_to_velo.inverse();
        for r in cameras.iter().filter(|r| r.camera == 0 && r.eval) {
            let pts = parse::velodyne(&p.path(pat, r.frame, 0))?;
            // The rectified camera frame is the scene pose's camera frame: depth is its z.
            let cam = Camera {
                cam_to_world: DAffine3::IDENTITY,
                ..r.cam.clone()
            };
            lidar.push(((r.frame, 0, w, h), lidar_depth(&pts, &velo_to_rect, &cam)));
        }
    }

    // Tables.
    let mut seen = [false; 256];
    seen[SKY as usize] = true;
    for l in gt_sem.iter().flatten().flatten() {
        seen[*l as usize] = true;
    }
    for q in &prims {
        seen[q.label as usize] = true;
    }
    let classes: Vec<u8> = (0..=255u8).filter(|&c| seen[c as usize]).collect();
    let name = if p.name.is_empty() {
        format!(
            "{} frames {}-{}",
            p.sequence,
            frames[0],
            frames[frames.len() - 1]
        )
    } else {
        p.name.clone()
    };
    let mut t = Tables::new();
    t.insert(
        "scene_info".into(),
        tables::build(
            "scene_info",
            vec![
                tables::strings([name.as_str()]),
                tables::strings([p.sequence.as_str()]),
                tables::fixed_list::<Float64Type>(3, origin.to_array().to_vec()),
                tables::list::<UInt8Type>([classes]),
                tables::prim::<Float64Type>([calib.baseline]),
            ],
        )?,
    );
    t.insert("cameras".into(), cameras_to_table(&cameras)?);
    t.insert("primitives".into(), primitives_to_table(&prims)?);
    t.insert(
        "images".into(),
        image_table("images", &all, tables::binary(rgb.iter().flatten()))?,
    );
    let present = |v: Vec<Option<Vec<u8>>>| -> (Vec<Key>, Vec<Vec<u8>>) {
        all.iter()
            .copied()
            .zip(v)
            .filter_map(|(k, x)| x.map(|x| (k, x)))
            .unzip()
    };
    let (sk, sv) = present(gt_sem);
    t.insert(
        "gt_semantic".into(),
        image_table("gt_semantic", &sk, tables::list::<UInt8Type>(sv))?,
    );
    let (ik, iv): (Vec<Key>, Vec<Vec<u16>>) = all
        .iter()
        .copied()
        .zip(gt_inst)
        .filter_map(|(k, x)| x.map(|x| (k, x)))
        .unzip();
    t.insert(
        "gt_instance".into(),
        image_table("gt_instance", &ik, tables::list::<UInt16Type>(iv))?,
    );
    t.insert(
        "gt_depth".into(),
        image_table("gt_depth", &[], tables::list::<Float32Type>(Vec::new()))?,
    );
    t.insert(
        "pseudo_labels".into(),
        image_table(
            "pseudo_labels",
            &left,
            tables::list::<UInt8Type>(pseudo.into_iter().flatten()),
        )?,
    );
    let stereo_keys: &[Key] = if stereo.is_empty() { &[] } else { &left };
    t.insert(
        "stereo_depth".into(),
        image_table(
            "stereo_depth",
            stereo_keys,
            tables::list::<Float32Type>(stereo.into_iter().flatten()),
        )?,
    );
    let (lk, lv): (Vec<Key>, Vec<Vec<f32>>) = lidar.into_iter().unzip();
    t.insert(
        "lidar_depth".into(),
        image_table("lidar_depth", &lk, tables::list::<Float32Type>(lv))?,
    );
    progress.update(4, 4, "tables");
    Ok(t)
}

#[cfg(test)]
mod tests;
