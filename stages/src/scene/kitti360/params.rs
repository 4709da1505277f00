//! The parameters of `kitti360_scene`: where the files are, which frames and cameras to read,
//! and how they are checked and resolved against `root`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::DAffine3;
use serde::{Deserialize, Serialize};

use crate::{Result, StageError};

use super::parse::err;

/// Parameters of `kitti360_scene`. Paths are relative to `root` unless absolute.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
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
    /// Cameras to load: `image_00`, `image_01` (the stereo pair) and the fisheye cameras listed.
    /// `image_02` and `image_03` are the left and right side fisheye cameras; numbers 0 .. 3 are
    /// read too. Rays, training and evaluation take these cameras unless a stage narrows them.
    #[serde(deserialize_with = "crate::geometry::camera::camera_ids")]
    #[schemars(with = "Vec<crate::geometry::camera::CameraName>")]
    pub cameras: Vec<u8>,
    /// Evaluation frames; when empty, every `eval_every`-th selected frame from the first.
    pub eval_frames: Vec<u32>,
    /// See `eval_frames` (at least 1 unless `eval_frames` lists the frames).
    pub eval_every: u32,
    /// `auto`: evaluation images without GT are trained on instead; `required`: they are errors.
    /// GT is `gt_semantic`, and `gt_instance` when set; most of KITTI-360 has no 2D GT.
    pub eval_gt: EvalGt,
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
    /// Fisheye images (`{cam}` = 02, 03).
    pub fisheye_images: String,
    /// Fisheye intrinsics: MEI model, OpenCV YAML.
    pub fisheye_calibration: String,
    /// Camera -> pose-frame extrinsics of every camera (`image_0K:` lines, 3x4).
    pub cam_to_pose: String,
    /// Pose frame -> world per frame (3x4): with `cam_to_pose`, places the fisheye cameras.
    /// The perspective cameras stay on `poses`, checked to agree.
    pub imu_poses: String,
    /// Optional noisy 2D labels of the fisheye cameras. Without them the fisheye images train
    /// colour only (and still get labels rendered).
    pub fisheye_pseudo_labels: Option<String>,
    /// Optional weak depth of the left camera (16-bit PNG, metres * 256, 0 = none). Null when
    /// the pipeline computes it with the `stereo_depth` stage.
    pub stereo_depth: Option<String>,
    /// Optional GT semantic PNGs (8-bit ids). Frames without a file have no GT row, but every
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
    /// World position of the scene frame's origin. Null: the first left camera's centre,
    /// rounded to whole metres.
    pub origin: Option<[f64; 3]>,
    /// Edits of the primitives as read (reclassify, move, turn, resize, delete), in order. Ids
    /// are rows of the unedited `primitives` table; editing the XML file does the same by hand.
    pub edits: Vec<crate::scene::edits::Edit>,
    /// Human-readable scene name; empty = "<sequence> frames <first>-<last>".
    pub name: String,
}

/// Whether evaluation frames must have GT (see [`Kitti360Params::eval_gt`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum EvalGt {
    Auto,
    Required,
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
            eval_gt: EvalGt::Auto,
            poses: "data_poses/{seq}/cam0_to_world.txt".into(),
            calibration: "calibration/perspective.txt".into(),
            bboxes: "data_3d_bboxes/train/{seq}.xml".into(),
            images: "data_2d_raw/{seq}/image_{cam}/data_rect/{frame}.png".into(),
            pseudo_labels: "pseudo_labels/{seq}/image_00/%010d.png".into(),
            fisheye_images: "data_2d_raw/{seq}/image_{cam}/data_rgb/{frame}.png".into(),
            fisheye_calibration: "calibration/image_{cam}.yaml".into(),
            cam_to_pose: "calibration/calib_cam_to_pose.txt".into(),
            imu_poses: "data_poses/{seq}/poses.txt".into(),
            fisheye_pseudo_labels: None,
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
            edits: Vec::new(),
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

    pub(crate) fn file(&self, pattern: &str) -> PathBuf {
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
        if let Some(f) = self
            .eval_frames
            .iter()
            .find(|f| frames.binary_search(f).is_err())
        {
            return Err(StageError::Params(format!(
                "`eval_frames`: frame {f} is not among the selected frames ({}); evaluation \
                 frames must be frames the scene reads",
                describe_frames(&frames)
            )));
        }
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
    pub(super) fn is_eval(&self, k: usize, frame: u32) -> bool {
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
        crate::scene::edits::check(&p.edits, None)?;
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
        if p.cameras.is_empty() || p.cameras.iter().any(|&c| c > 3) {
            return bad(
                "`cameras` must list KITTI-360 cameras: image_00 .. image_03 (or 0 .. 3)".into(),
            );
        }
        if !p.cameras.contains(&0) {
            return bad(format!(
                "`cameras` {:?} lacks 0: the pseudo labels, the GT and the evaluation are those \
                 of the left camera (image_00)",
                p.cameras
            ));
        }
        if p.eval_frames.is_empty() && p.eval_every == 0 {
            return bad(
                "`eval_every` 0 without `eval_frames` selects no evaluation frame: give \
                 `eval_every` >= 1 or list `eval_frames`"
                    .into(),
            );
        }
        let mut c = p.cameras.clone();
        c.sort_unstable();
        c.dedup();
        if c != p.cameras {
            return bad(
                "`cameras` must be ascending without repeats, e.g. [image_00, image_01]".into(),
            );
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

impl Kitti360Params {
    /// The selected fisheye cameras.
    pub fn fisheye_cameras(&self) -> Vec<u8> {
        self.cameras
            .iter()
            .copied()
            .filter(|&c| is_fisheye(c))
            .collect()
    }
}

/// Whether camera `c` is one of KITTI-360's fisheye cameras.
pub fn is_fisheye(c: u8) -> bool {
    c >= 2
}

/// `a..=b (n frames)`, or the list when short, for messages.
fn describe_frames(frames: &[u32]) -> String {
    match frames {
        [] => "none".to_string(),
        [a, .., b] if frames.len() > 8 => format!("{a}..={b}, {} frames", frames.len()),
        _ => format!("{frames:?}"),
    }
}
