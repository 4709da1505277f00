//! The readers of [`load`](super::load), one per source: the camera rows from the poses and
//! calibration, the primitives of the bounding-box XML, the optional per-image files (GT
//! labels and instances, stereo depth) and the LiDAR scans of the evaluation frames.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{DAffine3, DVec3};
use rayon::prelude::*;

use crate::geometry::{Camera, CameraRow, DynamicBox, Lens, Primitive, Shape};
use crate::labels;
use crate::{Result, StageError};

use super::fisheye::Fisheye;
use super::params::is_fisheye;
use super::parse::{self, err};
use super::{EvalGt, Kitti360Params};

/// The objects of the bounding-box XML, recentred: the static ones (`timestamp` -1) that
/// matter for cameras at `centres` (scene frame), and the boxes of moving objects at the
/// `selected` frames near those cameras, sorted by (object, frame). A moving object's
/// `timestamp` must be a frame of the sequence (`poses`: its first and last posed frame), and an
/// object (`semanticId`, `instanceId`) has at most one box per frame.
pub(super) fn load_primitives(
    path: &Path,
    objects: Vec<parse::XmlObject>,
    origin: DVec3,
    cameras: (&[DVec3], &[u32]),
    poses: (u32, u32),
    max_distance: f64,
) -> Result<(Vec<Primitive>, Vec<DynamicBox>)> {
    let (centres, selected) = cameras;
    let near = |b: &crate::geometry::Aabb| {
        centres.iter().any(|c| {
            let q = c.clamp(b.min, b.max);
            q.distance(*c) <= max_distance
        })
    };
    let (total, mut dynamic) = (objects.len(), 0);
    let mut out = Vec::new();
    let mut moving = Vec::new();
    let mut boxes_at: BTreeMap<(i64, i64, i64), String> = BTreeMap::new();
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
        // A moving object keeps its id whatever its class: it is the object's name over the
        // sequence (`object` of `dynamic_boxes`).
        let instance = if label.has_instances || o.timestamp != -1 {
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
        let frame = if o.timestamp == -1 {
            None
        } else {
            dynamic += 1;
            let (lo, hi) = poses;
            let frame = u32::try_from(o.timestamp)
                .ok()
                .filter(|f| (lo..=hi).contains(f))
                .ok_or_else(|| {
                    err(
                        path,
                        format!(
                            "<{at}>/<timestamp>: {} is outside the sequence's frames \
                             {lo}..={hi} (-1 marks a static object)",
                            o.timestamp
                        ),
                    )
                })?;
            let key = (o.semantic_id, o.instance_id, o.timestamp);
            if let Some(first) = boxes_at.insert(key, at.clone()) {
                return Err(err(
                    path,
                    format!(
                        "<{first}> and <{at}> are both object (semanticId {}, instanceId {}) \
                         at frame {frame}: a moving object has one box per frame",
                        o.semantic_id, o.instance_id
                    ),
                ));
            }
            Some(frame)
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
        match frame {
            None if near(&p.aabb()) => out.push(p),
            Some(frame) if selected.contains(&frame) && near(&p.aabb()) => {
                moving.push(DynamicBox {
                    object: u32::from(label.id) * labels::INSTANCE_FACTOR + instance,
                    frame,
                    primitive: p,
                })
            }
            _ => {}
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
    moving.sort_by_key(|b| (b.object, b.frame));
    Ok((out, moving))
}

/// Whether a mesh is KITTI-360's unit cube: the 8 corners of `[-0.5, 0.5]^3` and 12 triangles.
pub(super) fn is_unit_cube(v: &[DVec3], f: &[[u32; 3]]) -> bool {
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

/// An image: (frame, camera, width, height).
pub type Key = (u32, u8, u32, u32);

/// Loads one optional per-image file for every key; `None` for keys whose file is absent.
pub(super) fn load_each<T: Send>(
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
pub(super) fn lidar_depth(points: &[DVec3], velo_to_rect: &DAffine3, cam: &Camera) -> Vec<f32> {
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

/// The camera rows of the selected frames (each camera of `p.cameras` per frame, the right
/// one offset by the baseline along the left camera's x, the fisheye ones placed by
/// `fisheye`), recentred on `origin` in f64.
pub(super) fn camera_rows(
    p: &Kitti360Params,
    frames: &[u32],
    posed: &BTreeMap<u32, DAffine3>,
    calib: &parse::Perspective,
    fisheye: Option<&Fisheye>,
    origin: DVec3,
) -> Result<Vec<CameraRow>> {
    let mut cameras = Vec::new();
    for (k, &f) in frames.iter().enumerate() {
        let mut pose = posed[&f];
        pose.translation -= origin;
        for &c in &p.cameras {
            // Intrinsics (width, height, fx, fy, OpenCV cx, cy), lens and pose.
            let (size, lens, cam_to_world) = match fisheye.filter(|_| is_fisheye(c)) {
                Some(fe) => {
                    let m = &fe.intrinsics[&c];
                    let mut to_world = fe.cam_to_world(f, c)?;
                    to_world.translation -= origin;
                    let size = (m.width, m.height, m.fx, m.fy, m.cx_file, m.cy_file);
                    (size, Lens::Mei(m.mei), to_world)
                }
                None => {
                    let mut to_world = pose;
                    if c == 1 {
                        to_world.translation += pose.matrix3 * DVec3::new(calib.baseline, 0.0, 0.0);
                    }
                    let k = calib;
                    let size = (k.width, k.height, k.fx, k.fy, k.cx_file, k.cy_file);
                    (size, Lens::Pinhole, to_world)
                }
            };
            let (width, height, fx, fy, cx_file, cy_file) = size;
            cameras.push(CameraRow {
                frame: f,
                camera: c,
                eval: p.is_eval(k, f),
                cam: Camera {
                    width,
                    height,
                    fx,
                    fy,
                    cx: cx_file + 0.5,
                    cy: cy_file + 0.5,
                    lens,
                    cam_to_world,
                },
            });
        }
    }
    Ok(cameras)
}

/// The optional GT semantic PNGs of every image (`None` where the file is absent, or for
/// every image when `gt_semantic` is null).
pub(super) fn load_gt_semantic(p: &Kitti360Params, all: &[Key]) -> Result<Vec<Option<Vec<u8>>>> {
    Ok(match p.gt_semantic.clone() {
        Some(pat) => load_each(
            all,
            |k| p.path(&pat, k.0, k.1),
            |path, k| parse::labels(path, (k.2, k.3, k.1)),
            false,
        )?,
        None => vec![None; all.len()],
    })
}

/// The optional GT instance PNGs of every image, checked to hold `id * 1000 + instance` of
/// KITTI-360 labels (`None` as for [`load_gt_semantic`]).
pub(super) fn load_gt_instance(p: &Kitti360Params, all: &[Key]) -> Result<Vec<Option<Vec<u16>>>> {
    Ok(match p.gt_instance.clone() {
        Some(pat) => load_each(
            all,
            |k| p.path(&pat, k.0, k.1),
            |path, &(_, c, w, h)| {
                let v = parse::gray16(path, (w, h, c), "instance")?;
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
    })
}

/// Every evaluation image needs its GT labels and instances where the params ask for them:
/// with `eval_gt: required` a missing file is an error; with `auto` the image stops being an
/// evaluation image (it is trained on like the others).
pub(super) fn check_eval_gt(
    p: &Kitti360Params,
    cameras: &mut [CameraRow],
    gt_sem: &[Option<Vec<u8>>],
    gt_inst: &[Option<Vec<u16>>],
) -> Result<()> {
    for (i, r) in cameras.iter_mut().enumerate() {
        let missing = [
            (&p.gt_semantic, gt_sem[i].is_none(), "labels"),
            (&p.gt_instance, gt_inst[i].is_none(), "instances"),
        ]
        .into_iter()
        .find(|(pat, absent, _)| pat.is_some() && *absent);
        let Some((pat, _, what)) = missing.filter(|_| r.eval) else {
            continue;
        };
        if p.eval_gt == EvalGt::Auto {
            r.eval = false;
            continue;
        }
        return Err(err(
            &p.path(pat.as_deref().unwrap_or(""), r.frame, r.camera),
            format!(
                "missing: frame {} camera {} is an evaluation frame and needs GT {what} \
                 (`eval_gt: required`; with `auto` it would be trained on, not evaluated)",
                r.frame, r.camera
            ),
        ));
    }
    Ok(())
}

/// The weak stereo depth of every left image, metres (16-bit PNGs of metres * 256); empty
/// when `stereo_depth` is null.
pub(super) fn load_stereo_depth(
    p: &Kitti360Params,
    left: &[Key],
    w: u32,
    h: u32,
) -> Result<Vec<Option<Vec<f32>>>> {
    Ok(match &p.stereo_depth {
        Some(pat) => load_each(
            left,
            |k| p.path(pat, k.0, 0),
            |path, _| {
                let v = parse::gray16(path, (w, h, 0), "depth (metres * 256)")?;
                Ok(v.iter().map(|&x| x as f32 / 256.0).collect::<Vec<f32>>())
            },
            true,
        )?,
        None => Vec::new(),
    })
}

/// LiDAR z-depth of the evaluation frames' left images, from the velodyne scans projected
/// through `lidar_calib` and `R_rect_00`; empty when `lidar` is null.
pub(super) fn load_lidar(
    p: &Kitti360Params,
    cameras: &[CameraRow],
    calib: &parse::Perspective,
) -> Result<Vec<(Key, Vec<f32>)>> {
    let (w, h) = (calib.width, calib.height);
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
                lens: crate::geometry::Lens::Pinhole,
                cam_to_world: DAffine3::IDENTITY,
                ..r.cam.clone()
            };
            lidar.push(((r.frame, 0, w, h), lidar_depth(&pts, &velo_to_rect, &cam)));
        }
    }
    Ok(lidar)
}
