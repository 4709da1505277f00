//! KITTI-360's fisheye calibration (REFERENCE.md section 4): the MEI intrinsics of
//! `calibration/image_02.yaml` / `image_03.yaml` (OpenCV YAML), and the camera -> pose-frame
//! extrinsics of `calibration/calib_cam_to_pose.txt`, which with `data_poses/{seq}/poses.txt`
//! (pose frame -> world) place a fisheye camera in the world.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{DAffine3, DMat3};
use serde_yaml::Value;

use super::parse::{err, keyed, poses, read_text};
use super::Kitti360Params;
use crate::geometry::io::affine_from_row_major;
use crate::geometry::{Mei, FISHEYE_HALF_ANGLE_DEG};
use crate::{Result, StageError};

/// The intrinsics of one fisheye camera.
#[derive(Clone, Debug, PartialEq)]
pub struct MeiCalibration {
    pub width: u32,
    pub height: u32,
    /// gamma1, gamma2.
    pub fx: f64,
    pub fy: f64,
    /// u0, v0 in OpenCV pixel coordinates (pixel centres at integers).
    pub cx_file: f64,
    pub cy_file: f64,
    pub mei: Mei,
}

/// Parses `image_02.yaml` (or `image_03.yaml`): `model_type: MEI`, `image_width`,
/// `image_height`, `mirror_parameters.xi`, `distortion_parameters.{k1,k2,p1,p2}`,
/// `projection_parameters.{gamma1,gamma2,u0,v0}`. OpenCV writes a `%YAML:1.0` first line,
/// which YAML 1.2 parsers refuse; it is skipped.
pub fn mei_yaml(path: &Path, text: &str) -> Result<MeiCalibration> {
    let body: String = text
        .lines()
        .filter(|l| !l.trim_start().starts_with("%YAML"))
        .collect::<Vec<_>>()
        .join("\n");
    let doc: Value =
        serde_yaml::from_str(&body).map_err(|e| err(path, format!("not valid YAML: {e}")))?;
    let key = |section: Option<&str>, name: &str| -> Result<&Value> {
        let parent = match section {
            Some(s) => doc
                .get(s)
                .ok_or_else(|| err(path, format!("no `{s}` section")))?,
            None => &doc,
        };
        let full = section.map_or(name.to_string(), |s| format!("{s}.{name}"));
        parent
            .get(name)
            .ok_or_else(|| err(path, format!("no `{full}`")))
    };
    let number = |section: Option<&str>, name: &str| -> Result<f64> {
        let full = section.map_or(name.to_string(), |s| format!("{s}.{name}"));
        let v = key(section, name)?;
        let x = v
            .as_f64()
            .ok_or_else(|| err(path, format!("`{full}` is not a number: {v:?}")))?;
        if !x.is_finite() {
            return Err(err(path, format!("`{full}` is not finite: {x}")));
        }
        Ok(x)
    };
    let model = key(None, "model_type")?;
    if model.as_str() != Some("MEI") {
        return Err(err(
            path,
            format!("`model_type` is {model:?}; only MEI (KITTI-360's fisheye model) is supported"),
        ));
    }
    let side = |name: &str| -> Result<u32> {
        let v = number(None, name)?;
        if v < 1.0 || v > super::parse::MAX_IMAGE_SIDE as f64 || v.fract() != 0.0 {
            return Err(err(
                path,
                format!("`{name}` must be a whole number of pixels, found {v}"),
            ));
        }
        Ok(v as u32)
    };
    let (d, p) = (Some("distortion_parameters"), Some("projection_parameters"));
    let mei = Mei {
        xi: number(Some("mirror_parameters"), "xi")?,
        k1: number(d, "k1")?,
        k2: number(d, "k2")?,
        p1: number(d, "p1")?,
        p2: number(d, "p2")?,
        max_half_angle_deg: FISHEYE_HALF_ANGLE_DEG,
    };
    if mei.xi <= 0.0 {
        return Err(err(
            path,
            format!(
                "`mirror_parameters.xi` must be > 0, found {} (MEI's mirror parameter)",
                mei.xi
            ),
        ));
    }
    let out = MeiCalibration {
        width: side("image_width")?,
        height: side("image_height")?,
        fx: number(p, "gamma1")?,
        fy: number(p, "gamma2")?,
        cx_file: number(p, "u0")?,
        cy_file: number(p, "v0")?,
        mei,
    };
    for (name, v) in [("gamma1", out.fx), ("gamma2", out.fy)] {
        if v <= 0.0 {
            return Err(err(
                path,
                format!("`projection_parameters.{name}` must be > 0, found {v}"),
            ));
        }
    }
    Ok(out)
}

/// `calib_cam_to_pose.txt`: lines `image_0K: <12 numbers>` (3x4, camera -> pose frame), by
/// camera number.
pub fn cam_to_pose(path: &Path, text: &str) -> Result<BTreeMap<u8, DAffine3>> {
    let mut out = BTreeMap::new();
    for (key, (line, v)) in keyed(path, text)? {
        let Some(cam) = key
            .strip_prefix("image_")
            .and_then(|n| n.parse::<u8>().ok())
        else {
            continue;
        };
        if v.len() != 12 {
            return Err(err(
                path,
                format!(
                    "line {line} `{key}`: expected 12 numbers (a 3x4 matrix), found {}",
                    v.len()
                ),
            ));
        }
        let mut m = v;
        m.extend([0.0, 0.0, 0.0, 1.0]);
        let t = affine_from_row_major(&m).map_err(|e| err(path, format!("line {line}: {e}")))?;
        super::parse::check_rotation(path, &format!("line {line} `{key}`"), &t.matrix3)?;
        out.insert(cam, t);
    }
    Ok(out)
}

/// What places and models the fisheye cameras of a scene: their intrinsics, the pose-frame
/// trajectory and every camera's extrinsics.
pub struct Fisheye {
    pub intrinsics: BTreeMap<u8, MeiCalibration>,
    imu: BTreeMap<u32, DAffine3>,
    cam_to_pose: BTreeMap<u8, DAffine3>,
    imu_path: PathBuf,
}

/// The perspective chain and `cam0_to_world.txt` may differ by this much (the files are
/// printed to a few significant digits).
const CHAIN_TOLERANCE_M: f64 = 0.01;
const CHAIN_TOLERANCE_RAD: f64 = 1e-3;

impl Fisheye {
    /// Reads the fisheye calibration of `p.cameras` (None without a fisheye camera) and checks
    /// that `poses.txt * calib_cam_to_pose[image_00] * R_rect_00^T` gives the perspective
    /// camera of `cam0_to_world.txt` in every selected frame.
    pub fn load(
        p: &Kitti360Params,
        frames: &[u32],
        cam0: &BTreeMap<u32, DAffine3>,
        r_rect: DMat3,
    ) -> Result<Option<Fisheye>> {
        let fisheyes = p.fisheye_cameras();
        if fisheyes.is_empty() {
            return Ok(None);
        }
        let mut intrinsics = BTreeMap::new();
        for &c in &fisheyes {
            let path = p.path(&p.fisheye_calibration, 0, c);
            intrinsics.insert(c, mei_yaml(&path, &read_text(&path)?)?);
        }
        let c2p_path = p.file(&p.cam_to_pose);
        let cam_to_pose = cam_to_pose(&c2p_path, &read_text(&c2p_path)?)?;
        for c in fisheyes.iter().copied().chain([0]) {
            if !cam_to_pose.contains_key(&c) {
                return Err(err(&c2p_path, format!("no `image_{c:02}` line")));
            }
        }
        let imu_path = p.file(&p.imu_poses);
        let imu = poses(&imu_path, &read_text(&imu_path)?)?;
        let f = Fisheye {
            intrinsics,
            imu,
            cam_to_pose,
            imu_path,
        };
        let unrectify = DAffine3::from_mat3(r_rect.transpose());
        for &frame in frames {
            let chain = f.pose(frame)? * f.cam_to_pose[&0] * unrectify;
            let given = cam0[&frame];
            let dt = chain.translation.distance(given.translation);
            let rel = chain.matrix3.transpose() * given.matrix3;
            let da = ((rel.x_axis.x + rel.y_axis.y + rel.z_axis.z - 1.0) / 2.0)
                .clamp(-1.0, 1.0)
                .acos();
            if !(dt <= CHAIN_TOLERANCE_M && da <= CHAIN_TOLERANCE_RAD) {
                return Err(StageError::Input(format!(
                    "{}: frame {frame}: the perspective camera of this file and the one of {} * \
                     {} (image_00) * R_rect_00^T disagree by {dt:.3} m and {:.4} degrees (at \
                     most {CHAIN_TOLERANCE_M} m and {:.3} degrees); the fisheye cameras are \
                     placed by the second chain, so they would not line up with the others",
                    p.file(&p.poses).display(),
                    f.imu_path.display(),
                    c2p_path.display(),
                    da.to_degrees(),
                    CHAIN_TOLERANCE_RAD.to_degrees(),
                )));
            }
        }
        Ok(Some(f))
    }

    /// Pose frame -> world of `frame`.
    fn pose(&self, frame: u32) -> Result<DAffine3> {
        self.imu.get(&frame).copied().ok_or_else(|| {
            err(
                &self.imu_path,
                format!("frame {frame} has no pose (the fisheye cameras need one per frame)"),
            )
        })
    }

    /// Fisheye camera `c` -> world in `frame`.
    pub fn cam_to_world(&self, frame: u32, c: u8) -> Result<DAffine3> {
        Ok(self.pose(frame)? * self.cam_to_pose[&c])
    }
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use super::*;

    /// The shape of KITTI-360's `image_02.yaml` (values rounded; written here, not copied).
    pub const IMAGE_02: &str = "%YAML:1.0
---
model_type: MEI
camera_name: image_02
image_width: 1400
image_height: 1400
mirror_parameters:
   xi: 2.2134
distortion_parameters:
   k1: 1.6798e-02
   k2: 1.6548
   p1: 4.2223e-04
   p2: 4.2462e-04
projection_parameters:
   gamma1: 1.3363e+03
   gamma2: 1.3357e+03
   u0: 7.1694e+02
   v0: 7.0576e+02
";

    fn path() -> PathBuf {
        PathBuf::from("calibration/image_02.yaml")
    }

    #[test]
    fn reads_an_opencv_mei_file() {
        let c = mei_yaml(&path(), IMAGE_02).unwrap();
        assert_eq!((c.width, c.height), (1400, 1400));
        assert_eq!(
            (c.fx, c.fy, c.cx_file, c.cy_file),
            (1336.3, 1335.7, 716.94, 705.76)
        );
        assert_eq!(
            (c.mei.xi, c.mei.k1, c.mei.k2, c.mei.p1, c.mei.p2),
            (2.2134, 1.6798e-2, 1.6548, 4.2223e-4, 4.2462e-4)
        );
    }

    #[test]
    fn bad_files_name_the_file_and_key() {
        let cases = [
            (
                IMAGE_02.replace("model_type: MEI", "model_type: KANNALA_BRANDT"),
                "only MEI",
            ),
            (
                IMAGE_02.replace("   xi: 2.2134\n", ""),
                "`mirror_parameters.xi`",
            ),
            (
                IMAGE_02.replace("xi: 2.2134", "xi: -0.5"),
                "`mirror_parameters.xi` must be > 0",
            ),
            (IMAGE_02.replace("xi: 2.2134", "xi: 0"), "must be > 0"),
            (
                IMAGE_02.replace("   k2: 1.6548\n", ""),
                "no `distortion_parameters.k2`",
            ),
            (
                IMAGE_02.replace("gamma1: 1.3363e+03", "gamma1: abc"),
                "`projection_parameters.gamma1` is not a number",
            ),
            (
                IMAGE_02.replace("image_width: 1400", "image_width: 14.5"),
                "`image_width` must be a whole number",
            ),
            (
                IMAGE_02.replace("projection_parameters:", "projection_parameters: ["),
                "not valid YAML",
            ),
        ];
        for (text, want) in cases {
            let e = mei_yaml(&path(), &text).unwrap_err().to_string();
            assert!(
                e.contains("image_02.yaml") && e.contains(want),
                "{want}: {e}"
            );
        }
    }

    #[test]
    fn reads_camera_to_pose_lines() {
        let text = "image_00: 1 0 0 1.5 0 1 0 0.2 0 0 1 -0.3\n\
                    image_02: 0 0 1 0.5 -1 0 0 0.1 0 -1 0 0\n\
                    calib_time: 09-Jan-2012\n";
        let p = Path::new("calibration/calib_cam_to_pose.txt");
        let m = cam_to_pose(p, text).unwrap();
        assert_eq!(m.len(), 2);
        assert_eq!(m[&0].translation.x, 1.5);
        assert_eq!(m[&2].matrix3.x_axis.y, -1.0);
        let e = cam_to_pose(p, "image_03: 1 0 0 0 0 1 0 0 0 0 1\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("`image_03`: expected 12 numbers"), "{e}");
        let e = cam_to_pose(p, "image_03: 2 0 0 0 0 1 0 0 0 0 1 0\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("not a rotation"), "{e}");
    }
}
