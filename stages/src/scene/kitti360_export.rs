//! Writes a scene's tables in the KITTI-360 directory layout, so the KITTI-360 loader can be
//! tested on synthetic data (the real data set may not be shipped):
//!
//! ```text
//! data_2d_raw/<seq>/image_00|image_01/data_rect/%010d.png        RGB
//! data_poses/<seq>/cam0_to_world.txt                              frame + row-major 4x4
//! calibration/perspective.txt                                     P_rect_0x, R_rect_0x, S_rect_0x
//! data_3d_bboxes/train/<seq>.xml                                  OpenCV FileStorage XML
//! data_2d_semantics/train/<seq>/image_0x/semantic/%010d.png       8-bit label ids (GT)
//! data_2d_semantics/train/<seq>/image_0x/instance/%010d.png       16-bit id*1000+instance (GT)
//! pseudo_labels/<seq>/image_00/%010d.png                          8-bit label ids (noisy)
//! stereo_depth/<seq>/image_00/%010d.png                           16-bit metres*256 (weak depth)
//! data_3d_raw/<seq>/velodyne_points/data/%010d.bin                LiDAR, float32 N x 4 (eval frames)
//! calibration/calib_cam_to_velo.txt                               3x4 unrectified camera 0 -> velodyne
//! with fisheye cameras (2, 3):
//! data_2d_raw/<seq>/image_02|image_03/data_rgb/%010d.png          RGB (black outside the lens)
//! calibration/image_02.yaml, image_03.yaml                        MEI intrinsics, OpenCV YAML
//! calibration/calib_cam_to_pose.txt                               image_00 (= R_rect_00), image_02/03
//! data_poses/<seq>/poses.txt                                      frame + 3x4 pose -> world
//! pseudo_labels/<seq>/image_02|image_03/%010d.png                 their noisy labels, if any
//! ```
//!
//! Every path is the `kitti360_scene` loader's default pattern (its `lidar` and `stereo_depth`
//! are off by default: set them to [`kitti360::LIDAR_PATTERN`] and
//! [`kitti360::STEREO_DEPTH_PATTERN`] to read what this writes).
//!
//! LiDAR: the scene's per-pixel `lidar_depth` (z-depth in the left camera, 0 = none) becomes one
//! point per valid pixel, on the ray through the pixel centre at that depth, in the velodyne
//! frame ([`rect_to_velo`]: the synthetic scanner's mounting). `calib_cam_to_velo.txt` holds the
//! *unrectified* camera 0 -> velodyne transform and `perspective.txt` a small non-identity
//! `R_rect_00`, as in KITTI-360, so a loader must compose `R_rect_00 * inverse(cam_to_velo)` to
//! get back to the rectified camera. Re-projecting the points gives the same pixels and depths
//! up to float32 rounding of the coordinates (about 1e-6 relative); intensity is written as 0.
//! Stereo depth is quantised to 1/256 m by the 16-bit format (values above 255.99 m saturate).
//!
//! Poses and primitives are written in world coordinates (scene frame + `scene_info.origin`).
//! The principal point in `perspective.txt` follows KITTI/OpenCV (pixel centres at integer
//! coordinates): `cx_file = cx - 0.5`, where the `cameras` table's `cx` has pixel (0, 0)
//! spanning [0, 1). Numbers are written with Rust's shortest round-trip formatting.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use arrow::datatypes::{Float32Type, UInt16Type, UInt8Type};
use glam::{DAffine3, DMat3, DVec3};

use super::io::{image_keys, scene_info, table, write_bytes, write_png, write_text, SceneInfo};
use super::kitti360::{self, Kitti360Params};
use crate::geometry::{
    cameras_from_table, dynamic_boxes_from_table, io::affine_to_row_major, primitives_from_table,
    Camera, CameraRow, DynamicBox, Lens, Primitive, Shape,
};
use crate::{labels, pngio};
use crate::{tables, Result, StageError, Tables};

/// `R_rect_00` of the export: the unrectified -> rectified left camera rotation, a small
/// rotation (0.4 degrees) like KITTI-360's, so the LiDAR round trip exercises it.
pub fn r_rect_00() -> DMat3 {
    DMat3::from_axis_angle(DVec3::new(1.0, -2.0, 0.5).normalize(), 0.4f64.to_radians())
}

/// Rectified left camera -> velodyne: the synthetic scanner sits at camera (0.3, -0.2, -0.3)
/// with axes forward = camera z, left = camera -x, up = camera -y (see `scene::generate`).
pub fn rect_to_velo() -> DAffine3 {
    let velo_to_rect = DAffine3::from_mat3_translation(
        DMat3::from_cols(DVec3::Z, -DVec3::X, -DVec3::Y),
        DVec3::new(0.3, -0.2, -0.3),
    );
    velo_to_rect.inverse()
}

/// A velodyne `.bin` (float32 x, y, z, intensity, little-endian) of one left image's LiDAR
/// z-depth: a point per valid pixel on the ray through the pixel centre, at that depth.
pub fn lidar_points(depth: &[f32], cam: &Camera, rect_to_velo: &DAffine3) -> Vec<u8> {
    let w = cam.width as usize;
    let mut out = Vec::new();
    for (i, &z) in depth.iter().enumerate() {
        if !(z.is_finite() && z > 0.0) {
            continue;
        }
        let (x, y) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
        let z = z as f64;
        let p = DVec3::new((x - cam.cx) / cam.fx * z, (y - cam.cy) / cam.fy * z, z);
        let q = rect_to_velo.transform_point3(p);
        for v in [q.x as f32, q.y as f32, q.z as f32, 0.0] {
            out.extend(v.to_le_bytes());
        }
    }
    out
}

/// Writes the KITTI-360 layout into `dir`; returns the files written. One writer per file
/// kind, in a fixed order (poses, calibrations, bounding primitives, images, GT, left-camera
/// tables, LiDAR), so the list of files and the first error are always the same.
pub fn write(t: &Tables, dir: &Path) -> Result<Vec<PathBuf>> {
    let info = scene_info(t)?;
    let cams = cameras_from_table(table(t, "cameras")?)?;
    let prims = primitives_from_table(table(t, "primitives")?)?;
    // Moving objects: a scene kind without them has no such table.
    let moving = match t.get("dynamic_boxes") {
        Some(b) => dynamic_boxes_from_table(b)?,
        None => Vec::new(),
    };
    // The loader's default patterns, resolved in `dir`.
    let at = Kitti360Params {
        root: dir.display().to_string(),
        sequence: info.sequence.clone(),
        ..Default::default()
    };
    let mut files = Vec::new();
    write_poses(&at, &info, &cams, &mut files)?;
    write_perspective(&at, &info, &cams, &mut files)?;
    let rect_to_velo = rect_to_velo();
    write_lidar_calibration(&at, &rect_to_velo, &mut files)?;
    write_bboxes(&at, &info, &cams, (&prims, &moving), &mut files)?;
    write_fisheye_calibration(&at, &info, &cams, &mut files)?;
    write_images(&at, t, &mut files)?;
    write_gt(&at, t, &mut files)?;
    write_left_tables(&at, t, &mut files)?;
    write_lidar(&at, t, &cams, &rect_to_velo, &mut files)?;
    Ok(files)
}

/// `cam0_to_world.txt`: the poses of the left camera, world = scene + origin.
fn write_poses(
    at: &Kitti360Params,
    info: &SceneInfo,
    cams: &[CameraRow],
    files: &mut Vec<PathBuf>,
) -> Result<()> {
    let mut poses = String::new();
    for row in cams.iter().filter(|r| r.camera == 0) {
        let mut m = affine_to_row_major(&row.cam.cam_to_world);
        m[3] += info.origin.x;
        m[7] += info.origin.y;
        m[11] += info.origin.z;
        let _ = write!(poses, "{}", row.frame);
        for v in m {
            let _ = write!(poses, " {}", num(v));
        }
        poses.push('\n');
    }
    write_text(at.path(&at.poses, 0, 0), &poses, files)
}

/// `perspective.txt`: the rectified intrinsics (both cameras share them; the right one is
/// offset by the baseline).
fn write_perspective(
    at: &Kitti360Params,
    info: &SceneInfo,
    cams: &[CameraRow],
    files: &mut Vec<PathBuf>,
) -> Result<()> {
    let left = cams
        .iter()
        .find(|r| r.camera == 0)
        .ok_or_else(|| StageError::Input("table `cameras` has no left camera".into()))?;
    let c = &left.cam;
    let (cx, cy) = (c.cx - 0.5, c.cy - 0.5);
    let r_rect = r_rect_00().transpose().to_cols_array().map(num).join(" ");
    let mut calib = String::new();
    for (k, tx) in [(0, 0.0), (1, -c.fx * info.baseline)] {
        let _ = writeln!(
            calib,
            "P_rect_0{k}: {} 0 {cx} {tx} 0 {} {cy} 0 0 0 1 0",
            c.fx, c.fy
        );
        let r = if k == 0 {
            r_rect.as_str()
        } else {
            "1 0 0 0 1 0 0 0 1"
        };
        let _ = writeln!(calib, "R_rect_0{k}: {r}");
        let _ = writeln!(calib, "S_rect_0{k}: {} {}", c.width, c.height);
    }
    write_text(at.path(&at.calibration, 0, 0), &calib, files)
}

/// The fisheye cameras' calibration, when the scene has any: `image_0K.yaml` (MEI intrinsics),
/// `calib_cam_to_pose.txt` and `poses.txt`. The pose frame is the world-oriented frame of the
/// left camera's pose (`calib_cam_to_pose[image_00]` = `R_rect_00`, so `poses.txt` holds the
/// lines of `cam0_to_world.txt`); a fisheye camera's extrinsics are its pose relative to the
/// left camera, which must be the same in every frame (a rigid rig).
fn write_fisheye_calibration(
    at: &Kitti360Params,
    info: &SceneInfo,
    cams: &[CameraRow],
    files: &mut Vec<PathBuf>,
) -> Result<()> {
    let mut fisheyes: Vec<u8> = cams
        .iter()
        .filter(|r| kitti360::is_fisheye(r.camera))
        .map(|r| r.camera)
        .collect();
    fisheyes.sort_unstable();
    fisheyes.dedup();
    if fisheyes.is_empty() {
        return Ok(());
    }
    let left = |frame: u32| {
        cams.iter()
            .find(|r| (r.frame, r.camera) == (frame, 0))
            .map(|r| r.cam.cam_to_world)
            .ok_or_else(|| {
                StageError::Input(format!(
                    "table `cameras`: frame {frame} has fisheye images but no left camera (the \
                     KITTI-360 layout places fisheye cameras relative to it)"
                ))
            })
    };
    let row12 = |m: &DAffine3| {
        affine_to_row_major(m)[..12]
            .iter()
            .map(|&v| num(v))
            .collect::<Vec<_>>()
            .join(" ")
    };
    let mut extrinsics = format!("image_00: {}\n", row12(&DAffine3::from_mat3(r_rect_00())));
    for &k in &fisheyes {
        let rows: Vec<&CameraRow> = cams.iter().filter(|r| r.camera == k).collect();
        let rel = left(rows[0].frame)?.inverse() * rows[0].cam.cam_to_world;
        for r in &rows {
            let other = left(r.frame)?.inverse() * r.cam.cam_to_world;
            if !other.abs_diff_eq(rel, 1e-9) {
                return Err(StageError::Input(format!(
                    "table `cameras`: camera {k} moves relative to the left camera between frames \
                     {} and {}; the KITTI-360 layout needs a rigid rig",
                    rows[0].frame, r.frame
                )));
            }
        }
        let _ = writeln!(extrinsics, "image_{k:02}: {}", row12(&rel));
        let c = &rows[0].cam;
        let Lens::Mei(m) = c.lens else {
            return Err(StageError::Input(format!(
                "table `cameras`: camera {k} is a fisheye camera of KITTI-360 but has a {} lens",
                c.lens.name()
            )));
        };
        let yaml = format!(
            "%YAML:1.0\n---\nmodel_type: MEI\ncamera_name: image_{k:02}\nimage_width: {}\n\
             image_height: {}\nmirror_parameters:\n   xi: {}\ndistortion_parameters:\n   \
             k1: {}\n   k2: {}\n   p1: {}\n   p2: {}\nprojection_parameters:\n   gamma1: {}\n   \
             gamma2: {}\n   u0: {}\n   v0: {}\n",
            c.width,
            c.height,
            num(m.xi),
            num(m.k1),
            num(m.k2),
            num(m.p1),
            num(m.p2),
            num(c.fx),
            num(c.fy),
            num(c.cx - 0.5),
            num(c.cy - 0.5),
        );
        write_text(at.path(&at.fisheye_calibration, 0, k), &yaml, files)?;
    }
    write_text(at.file(&at.cam_to_pose), &extrinsics, files)?;
    let mut poses = String::new();
    for row in cams.iter().filter(|r| r.camera == 0) {
        let mut m = row.cam.cam_to_world;
        m.translation += info.origin;
        let _ = writeln!(poses, "{} {}", row.frame, row12(&m));
    }
    write_text(at.file(&at.imu_poses), &poses, files)
}

/// `calib_cam_to_velo.txt`: unrectified camera 0 -> velodyne = rectified -> velodyne after
/// unrectified -> rectified.
fn write_lidar_calibration(
    at: &Kitti360Params,
    rect_to_velo: &DAffine3,
    files: &mut Vec<PathBuf>,
) -> Result<()> {
    let cam_to_velo = *rect_to_velo * DAffine3::from_mat3(r_rect_00());
    let row_major = affine_to_row_major(&cam_to_velo);
    let line = row_major[..12].iter().map(|&v| num(v)).collect::<Vec<_>>();
    write_text(
        at.path(&at.lidar_calib, 0, 0),
        &(line.join(" ") + "\n"),
        files,
    )
}

/// The `data_3d_bboxes` XML of the 3D bounding primitives, valid over the cameras' frames.
fn write_bboxes(
    at: &Kitti360Params,
    info: &SceneInfo,
    cams: &[CameraRow],
    (prims, moving): (&[Primitive], &[DynamicBox]),
    files: &mut Vec<PathBuf>,
) -> Result<()> {
    let frames: Vec<u32> = cams.iter().map(|r| r.frame).collect();
    let (first, last) = (
        frames.iter().copied().min().unwrap_or(0),
        frames.iter().copied().max().unwrap_or(0),
    );
    let xml = bboxes_xml(prims, moving, info.origin, first, last)?;
    write_text(at.path(&at.bboxes, 0, 0), &xml, files)
}

/// The RGB images of both cameras.
fn write_images(at: &Kitti360Params, t: &Tables, files: &mut Vec<PathBuf>) -> Result<()> {
    let images = table(t, "images")?;
    let rgb = tables::get_binary(images, "images", "rgb")?;
    for (i, (f, cam, w, h)) in image_keys(images, "images")?.into_iter().enumerate() {
        let path = kitti360::image_path(at, &(f, cam, w, h));
        write_png(
            path,
            w,
            h,
            image::ExtendedColorType::Rgb8,
            rgb.value(i),
            files,
        )?;
    }
    Ok(())
}

/// The ground-truth semantic (8-bit ids) and instance (16-bit) PNGs.
fn write_gt(at: &Kitti360Params, t: &Tables, files: &mut Vec<PathBuf>) -> Result<()> {
    let sem = table(t, "gt_semantic")?;
    let labels_col = tables::get_list::<UInt8Type>(sem, "gt_semantic", "labels")?;
    let gt_semantic = at.gt_semantic.clone().unwrap_or_default();
    for (i, (f, cam, w, h)) in image_keys(sem, "gt_semantic")?.into_iter().enumerate() {
        write_png(
            at.path(&gt_semantic, f, cam),
            w,
            h,
            image::ExtendedColorType::L8,
            labels_col.row(i),
            files,
        )?;
    }
    let inst = table(t, "gt_instance")?;
    let inst_col = tables::get_list::<UInt16Type>(inst, "gt_instance", "instances")?;
    let gt_instance = at.gt_instance.clone().unwrap_or_default();
    for (i, (f, cam, w, h)) in image_keys(inst, "gt_instance")?.into_iter().enumerate() {
        let path = at.path(&gt_instance, f, cam);
        pngio::write_gray16(&path, w, h, inst_col.row(i))?;
        files.push(path);
    }
    Ok(())
}

/// Pseudo labels and stereo depth (left camera only).
fn write_left_tables(at: &Kitti360Params, t: &Tables, files: &mut Vec<PathBuf>) -> Result<()> {
    let pl = table(t, "pseudo_labels")?;
    let pl_col = tables::get_list::<UInt8Type>(pl, "pseudo_labels", "labels")?;
    for (i, (f, cam, w, h)) in image_keys(pl, "pseudo_labels")?.into_iter().enumerate() {
        let path = if kitti360::is_fisheye(cam) {
            at.path(kitti360::FISHEYE_PSEUDO_LABELS_PATTERN, f, cam)
        } else {
            left_only("pseudo_labels", f, cam)?;
            at.path(&at.pseudo_labels, f, 0)
        };
        write_png(
            path,
            w,
            h,
            image::ExtendedColorType::L8,
            pl_col.row(i),
            files,
        )?;
    }
    let sd = table(t, "stereo_depth")?;
    let sd_col = tables::get_list::<Float32Type>(sd, "stereo_depth", "depth")?;
    for (i, (f, cam, w, h)) in image_keys(sd, "stereo_depth")?.into_iter().enumerate() {
        left_only("stereo_depth", f, cam)?;
        let path = at.path(kitti360::STEREO_DEPTH_PATTERN, f, 0);
        pngio::write_gray16(&path, w, h, &pngio::depth_to_u16(sd_col.row(i)))?;
        files.push(path);
    }
    Ok(())
}

/// The LiDAR scans of the evaluation frames ([`lidar_points`] of each `lidar_depth` row).
fn write_lidar(
    at: &Kitti360Params,
    t: &Tables,
    cams: &[CameraRow],
    rect_to_velo: &DAffine3,
    files: &mut Vec<PathBuf>,
) -> Result<()> {
    let ld = table(t, "lidar_depth")?;
    let ld_col = tables::get_list::<Float32Type>(ld, "lidar_depth", "depth")?;
    for (i, (f, cam, w, h)) in image_keys(ld, "lidar_depth")?.into_iter().enumerate() {
        left_only("lidar_depth", f, cam)?;
        let row = cams
            .iter()
            .find(|r| (r.frame, r.camera) == (f, 0))
            .filter(|r| (r.cam.width, r.cam.height) == (w, h))
            .ok_or_else(|| {
                StageError::Input(format!(
                    "table `lidar_depth`: frame {f} ({w}x{h}) has no left camera of that size"
                ))
            })?;
        let bytes = lidar_points(ld_col.row(i), &row.cam, rect_to_velo);
        write_bytes(at.path(kitti360::LIDAR_PATTERN, f, 0), &bytes, files)?;
    }
    Ok(())
}

/// How far a loaded `stereo_depth` may be from the exported one: half of the 16-bit format's
/// 1/256 m step (plus float32 slack).
pub const STEREO_DEPTH_TOLERANCE_M: f64 = 0.5 / 256.0 + 1e-6;
/// How far (relative) a re-projected `lidar_depth` may be from the exported one: float32
/// rounding of the velodyne coordinates.
pub const LIDAR_DEPTH_TOLERANCE: f64 = 1e-6;

/// The difference between two per-pixel depth tables (0 = no depth), over pixels valid in both.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DepthDifference {
    /// Pixels with depth in both.
    pub pixels: usize,
    /// Largest |a - b|, metres.
    pub max_abs: f64,
    /// Largest |a - b| / a.
    pub max_rel: f64,
}

/// Compares table `name` (`stereo_depth`, `lidar_depth`, `gt_depth`) of two scenes: the rows
/// (frame, camera, size) and the set of pixels with depth must be equal, else an error saying
/// where they differ; returns how much the depths differ.
pub fn depth_difference(a: &Tables, b: &Tables, name: &str) -> Result<DepthDifference> {
    let (ta, tb) = (table(a, name)?, table(b, name)?);
    let (ka, kb) = (image_keys(ta, name)?, image_keys(tb, name)?);
    if ka != kb {
        return Err(StageError::Input(format!(
            "table `{name}`: rows (frame, camera, width, height) differ: {ka:?} vs {kb:?}"
        )));
    }
    let ca = tables::get_list::<Float32Type>(ta, name, "depth")?;
    let cb = tables::get_list::<Float32Type>(tb, name, "depth")?;
    let mut d = DepthDifference::default();
    for (i, k) in ka.iter().enumerate() {
        let (ra, rb) = (ca.row(i), cb.row(i));
        if ra.len() != rb.len() {
            return Err(StageError::Input(format!(
                "table `{name}`: frame {} camera {}: {} vs {} pixels",
                k.0,
                k.1,
                ra.len(),
                rb.len()
            )));
        }
        for (p, (&x, &y)) in ra.iter().zip(rb).enumerate() {
            if (x > 0.0) != (y > 0.0) {
                return Err(StageError::Input(format!(
                    "table `{name}`: frame {} camera {} pixel {p}: depth {x} vs {y}",
                    k.0, k.1
                )));
            }
            if x > 0.0 {
                let e = (x as f64 - y as f64).abs();
                d.pixels += 1;
                d.max_abs = d.max_abs.max(e);
                d.max_rel = d.max_rel.max(e / x as f64);
            }
        }
    }
    Ok(d)
}

/// KITTI-360 keeps pseudo labels, stereo depth and LiDAR for the left camera only.
fn left_only(table: &str, frame: u32, camera: u8) -> Result<()> {
    if camera != 0 {
        return Err(StageError::Input(format!(
            "table `{table}`: frame {frame} camera {camera}: only the left camera (0) can be \
             exported in the KITTI-360 layout"
        )));
    }
    Ok(())
}

/// A number in Rust's shortest round-trip form, without a negative zero.
fn num(v: f64) -> String {
    (v + 0.0).to_string()
}

/// KITTI-360's coarse category of a label.
fn category(label: u8) -> &'static str {
    use crate::labels::*;
    match label {
        ROAD | SIDEWALK | PARKING => "flat",
        BUILDING | WALL | FENCE | GATE => "construction",
        VEGETATION | TERRAIN => "nature",
        CAR | CARAVAN | TRAILER => "vehicle",
        SKY => "sky",
        _ => "object",
    }
}

/// A closed triangle mesh of a primitive in its local frame (vertices, faces), outward-wound.
pub fn local_mesh(shape: &Shape) -> (Vec<DVec3>, Vec<[u32; 3]>) {
    match shape {
        Shape::Cuboid => {
            let v: Vec<DVec3> = (0..8)
                .map(|k| {
                    DVec3::new(
                        if k & 1 == 0 { -0.5 } else { 0.5 },
                        if k & 2 == 0 { -0.5 } else { 0.5 },
                        if k & 4 == 0 { -0.5 } else { 0.5 },
                    )
                })
                .collect();
            let f = vec![
                [0, 2, 3],
                [0, 3, 1], // z-
                [4, 5, 7],
                [4, 7, 6], // z+
                [0, 1, 5],
                [0, 5, 4], // y-
                [2, 6, 7],
                [2, 7, 3], // y+
                [0, 4, 6],
                [0, 6, 2], // x-
                [1, 3, 7],
                [1, 7, 5], // x+
            ];
            (v, f)
        }
        Shape::Ellipsoid => {
            let (seg, rings) = (16u32, 8u32);
            let mut v = vec![DVec3::new(0.0, 0.0, 0.5)];
            for r in 1..rings {
                let th = std::f64::consts::PI * r as f64 / rings as f64;
                for s in 0..seg {
                    let ph = std::f64::consts::TAU * s as f64 / seg as f64;
                    v.push(0.5 * DVec3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()));
                }
            }
            v.push(DVec3::new(0.0, 0.0, -0.5));
            let south = v.len() as u32 - 1;
            let at = |r: u32, s: u32| 1 + (r - 1) * seg + s % seg;
            let mut f = Vec::new();
            for s in 0..seg {
                f.push([0, at(1, s), at(1, s + 1)]);
                f.push([south, at(rings - 1, s + 1), at(rings - 1, s)]);
            }
            for r in 1..rings - 1 {
                for s in 0..seg {
                    let (a, b, c, d) = (at(r, s), at(r, s + 1), at(r + 1, s), at(r + 1, s + 1));
                    f.push([a, c, d]);
                    f.push([a, d, b]);
                }
            }
            (v, f)
        }
        Shape::Extruded { polygon } => {
            let mut poly = polygon.clone();
            let area: f64 = (0..poly.len())
                .map(|i| {
                    let (a, b) = (poly[i], poly[(i + 1) % poly.len()]);
                    a[0] * b[1] - b[0] * a[1]
                })
                .sum();
            if area < 0.0 {
                poly.reverse();
            }
            let n = poly.len() as u32;
            let mut v: Vec<DVec3> = poly.iter().map(|q| DVec3::new(q[0], q[1], -0.5)).collect();
            v.extend(poly.iter().map(|q| DVec3::new(q[0], q[1], 0.5)));
            let mut f = Vec::new();
            for [a, b, c] in ear_clip(&poly) {
                f.push([a + n, b + n, c + n]); // top, counter-clockwise seen from +z
                f.push([a, c, b]); // bottom
            }
            for i in 0..n {
                let j = (i + 1) % n;
                f.push([i, j, j + n]);
                f.push([i, j + n, i + n]);
            }
            (v, f)
        }
        Shape::Mesh { vertices, faces } => (vertices.clone(), faces.clone()),
    }
}

/// Triangulates a simple counter-clockwise polygon (ear clipping).
fn ear_clip(poly: &[[f64; 2]]) -> Vec<[u32; 3]> {
    let cross = |o: [f64; 2], a: [f64; 2], b: [f64; 2]| {
        (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
    };
    let mut idx: Vec<usize> = (0..poly.len()).collect();
    let mut out = Vec::new();
    while idx.len() > 3 {
        let m = idx.len();
        let ear = (0..m).find(|&k| {
            let (a, b, c) = (
                poly[idx[(k + m - 1) % m]],
                poly[idx[k]],
                poly[idx[(k + 1) % m]],
            );
            if cross(a, b, c) <= 0.0 {
                return false;
            }
            idx.iter().all(|&q| {
                let p = poly[q];
                p == a
                    || p == b
                    || p == c
                    || !(cross(a, b, p) >= 0.0 && cross(b, c, p) >= 0.0 && cross(c, a, p) >= 0.0)
            })
        });
        // A valid simple polygon always has an ear; fall back to the first vertex regardless.
        let k = ear.unwrap_or(0);
        out.push([
            idx[(k + m - 1) % m] as u32,
            idx[k] as u32,
            idx[(k + 1) % m] as u32,
        ]);
        idx.remove(k);
    }
    out.push([idx[0] as u32, idx[1] as u32, idx[2] as u32]);
    out
}

fn matrix(out: &mut String, tag: &str, rows: usize, cols: usize, dt: &str, data: &[String]) {
    let _ = writeln!(out, "  <{tag} type_id=\"opencv-matrix\">");
    let _ = writeln!(
        out,
        "    <rows>{rows}</rows>\n    <cols>{cols}</cols>\n    <dt>{dt}</dt>"
    );
    let _ = write!(out, "    <data>");
    for (i, d) in data.iter().enumerate() {
        if i > 0 {
            // Rows wrap as " \n": a space on both sides of every value, so parsers that split
            // on single spaces (the devkit's parseOpencvMatrix) never glue two values together.
            out.push_str(if i % cols == 0 { " \n" } else { " " });
        }
        out.push_str(d);
    }
    let _ = writeln!(out, "</data></{tag}>");
}

/// The `instanceId` of every primitive in the XML: KITTI-360 gives every object its own
/// (semanticId, instanceId) pair, and its devkit keys objects by `semanticId * 1000 +
/// instanceId`. Things keep theirs (the instance ids of the GT maps); stuff, which the project
/// does not tell apart (reading sets it to 0), gets the free ids of its class from 1 up.
pub fn xml_instance_ids(prims: &[Primitive]) -> Result<Vec<u32>> {
    use std::collections::{BTreeMap, BTreeSet};
    let is_thing = |p: &Primitive| labels::by_id(p.label).is_some_and(|l| l.has_instances);
    let mut used: BTreeMap<u8, BTreeSet<u32>> = BTreeMap::new();
    for (i, p) in prims.iter().enumerate().filter(|(_, p)| is_thing(p)) {
        if !used.entry(p.label).or_default().insert(p.instance) {
            return Err(StageError::Input(format!(
                "primitive {i}: instance {} of class {} is used by another primitive; \
                 KITTI-360 needs every object's (semanticId, instanceId) to be unique",
                p.instance, p.label
            )));
        }
    }
    let mut next: BTreeMap<u8, u32> = BTreeMap::new();
    prims
        .iter()
        .map(|p| {
            if is_thing(p) {
                return Ok(p.instance);
            }
            let taken = used.entry(p.label).or_default();
            let n = next.entry(p.label).or_insert(1);
            while taken.contains(n) {
                *n += 1;
            }
            if *n >= labels::INSTANCE_FACTOR {
                return Err(StageError::Input(format!(
                    "more than {} objects of class {}: KITTI-360 instance ids are below {}",
                    labels::INSTANCE_FACTOR - 1,
                    p.label,
                    labels::INSTANCE_FACTOR
                )));
            }
            taken.insert(*n);
            Ok(*n)
        })
        .collect()
}

/// The `data_3d_bboxes` XML of the primitives, valid over frames `first..=last`, and of the
/// moving objects' boxes, one object element per box with its frame as `timestamp` and the
/// object's first and last frame as `start_frame` and `end_frame` (world frame = scene +
/// `origin`).
pub fn bboxes_xml(
    prims: &[Primitive],
    moving: &[DynamicBox],
    origin: DVec3,
    first: u32,
    last: u32,
) -> Result<String> {
    let mut s = String::from("<?xml version=\"1.0\"?>\n<opencv_storage>\n");
    let instance_ids = xml_instance_ids(prims)?;
    for (i, p) in prims.iter().enumerate() {
        let object = XmlBox {
            instance: instance_ids[i],
            span: (first, last),
            timestamp: -1,
        };
        write_object(&mut s, i, p, object, origin)
            .map_err(|e| StageError::Input(format!("primitive {i}: {e}")))?;
    }
    let mut span = std::collections::BTreeMap::new();
    for b in moving {
        let e = span.entry(b.object).or_insert((b.frame, b.frame));
        *e = (e.0.min(b.frame), e.1.max(b.frame));
    }
    for (k, b) in moving.iter().enumerate() {
        let object = XmlBox {
            instance: b.primitive.instance,
            span: span[&b.object],
            timestamp: i64::from(b.frame),
        };
        write_object(&mut s, prims.len() + k, &b.primitive, object, origin).map_err(|e| {
            StageError::Input(format!(
                "moving object {} at frame {}: {e}",
                b.object, b.frame
            ))
        })?;
    }
    s.push_str("</opencv_storage>\n");
    Ok(s)
}

/// What an object element says beyond its primitive: its instance id, the frames it is valid
/// over, and its timestamp (-1: static).
struct XmlBox {
    instance: u32,
    span: (u32, u32),
    timestamp: i64,
}

/// Appends `<object{index + 1}>` of primitive `p`.
fn write_object(
    s: &mut String,
    index: usize,
    p: &Primitive,
    o: XmlBox,
    origin: DVec3,
) -> std::result::Result<(), String> {
    let l = labels::by_id(p.label)
        .filter(|l| l.kitti_id >= 0)
        .ok_or_else(|| format!("label {} has no kittiId", p.label))?;
    let mut m = affine_to_row_major(&p.to_world);
    m[3] += origin.x;
    m[7] += origin.y;
    m[11] += origin.z;
    let (v, f) = local_mesh(&p.shape);
    let _ = writeln!(s, "<object{}>", index + 1);
    matrix(s, "transform", 4, 4, "f", &m.map(num));
    let vd: Vec<String> = v.iter().flat_map(|q| [q.x, q.y, q.z]).map(num).collect();
    matrix(s, "vertices", v.len(), 3, "f", &vd);
    let dt = if v.len() <= 256 { "u" } else { "i" };
    let fd: Vec<String> = f.iter().flatten().map(|x| x.to_string()).collect();
    matrix(s, "faces", f.len(), 3, dt, &fd);
    let _ = writeln!(s, "  <semanticId>{}</semanticId>", l.kitti_id);
    let _ = writeln!(s, "  <instanceId>{}</instanceId>", o.instance);
    let (first, last) = o.span;
    let _ = writeln!(
        s,
        "  <start_frame>{first}</start_frame>\n  <end_frame>{last}</end_frame>"
    );
    let _ = writeln!(
        s,
        "  <timestamp>{}</timestamp>\n  <index>{index}</index>",
        o.timestamp
    );
    let _ = writeln!(
        s,
        "  <label>{}</label>\n  <category>{}</category>",
        l.name,
        category(p.label)
    );
    let _ = writeln!(s, "</object{}>", index + 1);
    Ok(())
}
