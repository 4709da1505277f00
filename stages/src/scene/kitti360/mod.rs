//! The `kitti360_scene` stage kind: the tables of `synthetic_scene` (scene_info, cameras,
//! primitives, images, pseudo_labels, stereo_depth, lidar_depth, gt_semantic, gt_instance,
//! gt_depth) read from a directory in the KITTI-360 layout (REFERENCE.md section 2), so real
//! data (or data exported by `pipe export` of a synthetic scene) runs through the same pipeline;
//! and `dynamic_boxes`, the moving objects' per-frame boxes.
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
//! with cameras image_02 / image_03 (the side fisheye cameras):
//! calibration/image_{cam}.yaml                        MEI intrinsics (OpenCV YAML)
//! calibration/calib_cam_to_pose.txt                   camera -> pose frame, image_00..03
//! data_poses/{seq}/poses.txt                          pose frame -> world per frame
//! data_2d_raw/{seq}/image_{cam}/data_rgb/{frame}.png  fisheye images
//! param `fisheye_pseudo_labels` (optional)            their noisy labels
//! ```
//!
//! A fisheye camera -> world is `poses.txt[frame] * calib_cam_to_pose[cam]`; the perspective
//! cameras stay on `cam0_to_world.txt`, which must agree with
//! `poses.txt * calib_cam_to_pose[image_00] * R_rect_00^T` (to 1 cm and 1 mrad) in every selected
//! frame, or the fisheye cameras would not line up with them.
//!
//! Frames: `frames` if given (each must have a pose), else every frame in
//! `[first_frame, last_frame]` that has a pose (KITTI-360 poses are not contiguous; frames
//! without one are skipped). Primitives: the static objects (`timestamp` -1), kept when their
//! world bounds come within `max_distance_m` of a selected camera centre; the unit cube becomes
//! a `cuboid`, anything else a closed `mesh`. Moving objects (one box per frame, `timestamp` =
//! the frame) go to their own table, `dynamic_boxes`, at the selected frames and as near. Everything is recentred on `origin` in f64.
//! Tables with no source (no stereo-depth directory, no LiDAR, never GT depth) have no rows.
//!
//! Cache keying: [`input_files`] lists every file a run with given params reads, so the runner
//! can hash them into the stage key (see the module's report for the hook it needs).

mod fisheye;
mod params;
pub mod parse;
mod read;

pub use params::{is_fisheye, EvalGt, Kitti360Params};
pub use read::Key;

use std::path::PathBuf;

use arrow::array::ArrayRef;
use arrow::datatypes::{Float32Type, Float64Type, UInt16Type, UInt32Type, UInt8Type};
use arrow::record_batch::RecordBatch;
use glam::DVec3;

use crate::geometry::{
    cameras_to_table, dynamic_boxes_to_table, primitives_to_table, CameraRow, DynamicBox, Primitive,
};
use crate::labels::SKY;
use crate::{tables, Progress, Result, Tables};

use fisheye::Fisheye;
use read::{
    camera_rows, check_eval_gt, load_each, load_gt_instance, load_gt_semantic, load_lidar,
    load_primitives, load_stereo_depth,
};

/// The file of parameter `name` (`pattern` under `root`); one that exists but is not a regular
/// file (a directory, a FIFO) is refused naming the parameter.
fn named_file(p: &Kitti360Params, name: &str, pattern: &str) -> Result<PathBuf> {
    let path = p.file(pattern);
    match crate::input_file::not_regular(&path) {
        None => Ok(path),
        Some(what) => Err(crate::StageError::Input(format!(
            "parameter `{name}` ({pattern:?}): {}: is {what}, expected a regular file",
            path.display()
        ))),
    }
}

/// Where `pipe export scene` writes the LiDAR scans (KITTI-360's own layout); `lidar` is off
/// by default because the scans are a large, separate download.
pub const LIDAR_PATTERN: &str = "data_3d_raw/{seq}/velodyne_points/data/{frame}.bin";
/// Where `pipe export scene` writes the weak stereo depth (KITTI-360 has no such directory).
pub const STEREO_DEPTH_PATTERN: &str = "stereo_depth/{seq}/image_00/{frame}.png";

/// Every file a run with these params reads (existing or not), in a fixed order: the runner
/// hashes them into the stage's cache key. Reads the pose file to resolve the frame range.
pub fn input_files(p: &Kitti360Params) -> Result<Vec<PathBuf>> {
    let pose_path = named_file(p, "poses", &p.poses)?;
    let posed = parse::poses(&pose_path, &parse::read_text(&pose_path)?)?;
    let frames = p.select_frames(&posed)?;
    let mut out = vec![
        pose_path,
        named_file(p, "calibration", &p.calibration)?,
        named_file(p, "bboxes", &p.bboxes)?,
    ];
    let fisheyes = p.fisheye_cameras();
    if !fisheyes.is_empty() {
        out.extend([
            named_file(p, "cam_to_pose", &p.cam_to_pose)?,
            named_file(p, "imu_poses", &p.imu_poses)?,
        ]);
        out.extend(
            fisheyes
                .iter()
                .map(|&c| p.path(&p.fisheye_calibration, 0, c)),
        );
    }
    if p.lidar.is_some() {
        out.push(named_file(p, "lidar_calib", &p.lidar_calib)?);
    }
    for (k, &f) in frames.iter().enumerate() {
        for &c in &p.cameras {
            out.push(image_path(p, &(f, c, 0, 0)));
            if let Some(pat) = p.fisheye_pseudo_labels.as_ref().filter(|_| is_fisheye(c)) {
                out.push(p.path(pat, f, c));
            }
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

/// Where `pipe export scene` writes the fisheye cameras' pseudo labels (KITTI-360 has none).
pub const FISHEYE_PSEUDO_LABELS_PATTERN: &str = "pseudo_labels/{seq}/image_{cam}/{frame}.png";

/// The image file of `k`: rectified perspective, or fisheye.
pub fn image_path(p: &Kitti360Params, k: &Key) -> PathBuf {
    let pattern = if is_fisheye(k.1) {
        &p.fisheye_images
    } else {
        &p.images
    };
    p.path(pattern, k.0, k.1)
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

/// Reads the scene (the body of `run`): poses and calibration, the camera rows, the
/// primitives near them, the per-image files, the LiDAR scans, then the tables. Every reader
/// runs in this order, so the first error reported is always the same one.
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

    let fisheye = Fisheye::load(p, &frames, &posed, calib.r_rect)?;
    let mut cameras = camera_rows(p, &frames, &posed, &calib, fisheye.as_ref(), origin)?;
    let centres: Vec<DVec3> = cameras.iter().map(|r| r.cam.centre()).collect();

    // Primitives.
    let xml_path = p.file(&p.bboxes);
    let objects = parse::bboxes(&xml_path, &parse::read_text(&xml_path)?)?;
    let posed_span = match (posed.keys().next(), posed.keys().next_back()) {
        (Some(&a), Some(&b)) => (a, b),
        _ => (0, 0),
    };
    let (prims, dynamic) = load_primitives(
        &xml_path,
        objects,
        origin,
        (&centres, &frames),
        posed_span,
        p.max_distance_m,
    )?;
    let prims = crate::scene::edits::apply(&prims, &p.edits)?;
    progress.update(1, 4, "primitives");

    // Images and labels.
    let (w, h) = (calib.width, calib.height);
    let all: Vec<Key> = cameras
        .iter()
        .map(|r| (r.frame, r.camera, r.cam.width, r.cam.height))
        .collect();
    let left: Vec<Key> = all.iter().copied().filter(|k| k.1 == 0).collect();
    let rgb = load_each(
        &all,
        |k| image_path(p, k),
        |path, k| parse::rgb(path, (k.2, k.3, k.1)),
        true,
    )?;
    // Pseudo labels: every left image, and every fisheye image when the params name them.
    let labelled: Vec<Key> = all
        .iter()
        .copied()
        .filter(|k| k.1 == 0 || (is_fisheye(k.1) && p.fisheye_pseudo_labels.is_some()))
        .collect();
    let pseudo = load_each(
        &labelled,
        |k| match (&p.fisheye_pseudo_labels, is_fisheye(k.1)) {
            (Some(pat), true) => p.path(pat, k.0, k.1),
            _ => p.path(&p.pseudo_labels, k.0, 0),
        },
        |path, k| parse::labels(path, (k.2, k.3, k.1)),
        true,
    )?;
    progress.update(2, 4, "images");
    let gt_sem = load_gt_semantic(p, &all)?;
    let gt_inst = load_gt_instance(p, &all)?;
    check_eval_gt(p, &mut cameras, &gt_sem, &gt_inst)?;
    let stereo = load_stereo_depth(p, &left, w, h)?;
    progress.update(3, 4, "labels");

    let lidar = load_lidar(p, &cameras, &calib)?;

    let read = Read {
        cameras,
        prims,
        dynamic,
        all,
        left,
        labelled,
        rgb,
        pseudo,
        gt_sem,
        gt_inst,
        stereo,
        lidar,
    };
    let t = scene_tables(p, &frames, origin, calib.baseline, read)?;
    progress.update(4, 4, "tables");
    Ok(t)
}

/// Everything [`load`] read, before it becomes tables: the camera rows, the primitives, the
/// image keys (`all` images, `left` ones) and the per-image values in key order (`None`:
/// no file).
struct Read {
    cameras: Vec<CameraRow>,
    prims: Vec<Primitive>,
    dynamic: Vec<DynamicBox>,
    all: Vec<Key>,
    left: Vec<Key>,
    /// The images with pseudo labels.
    labelled: Vec<Key>,
    rgb: Vec<Option<Vec<u8>>>,
    pseudo: Vec<Option<Vec<u8>>>,
    gt_sem: Vec<Option<Vec<u8>>>,
    gt_inst: Vec<Option<Vec<u16>>>,
    /// Empty when the params have no stereo depth.
    stereo: Vec<Option<Vec<f32>>>,
    lidar: Vec<(Key, Vec<f32>)>,
}

/// The classes present in the scene: in any GT label image or any primitive, plus sky.
fn classes_present(gt_sem: &[Option<Vec<u8>>], prims: &[Primitive]) -> Vec<u8> {
    let mut seen = [false; 256];
    seen[SKY as usize] = true;
    for l in gt_sem.iter().flatten().flatten() {
        seen[*l as usize] = true;
    }
    for q in prims {
        seen[q.label as usize] = true;
    }
    (0..=255u8).filter(|&c| seen[c as usize]).collect()
}

/// The stage's tables of what was read (images without a file have no row).
fn scene_tables(
    p: &Kitti360Params,
    frames: &[u32],
    origin: DVec3,
    baseline: f64,
    r: Read,
) -> Result<Tables> {
    let Read {
        cameras,
        prims,
        dynamic,
        all,
        left,
        labelled,
        rgb,
        pseudo,
        gt_sem,
        gt_inst,
        stereo,
        lidar,
    } = r;
    let classes = classes_present(&gt_sem, &prims);
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
                tables::prim::<Float64Type>([baseline]),
            ],
        )?,
    );
    t.insert("cameras".into(), cameras_to_table(&cameras)?);
    t.insert("primitives".into(), primitives_to_table(&prims)?);
    t.insert("dynamic_boxes".into(), dynamic_boxes_to_table(&dynamic)?);
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
            &labelled,
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
    Ok(t)
}

#[cfg(test)]
mod tests;
