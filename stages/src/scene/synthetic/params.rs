//! The synthetic street's parameters: their defaults and checks.

use serde::{Deserialize, Serialize};

use crate::labels::{self, PAPER_CLASSES, ROAD, SKY, TERRAIN};
use crate::scene::layout::{self, LayoutParams};
use crate::{Result, StageError};

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
    pub edits: Vec<crate::scene::edits::Edit>,
    /// Moving objects, 0..=4 (0: a static street, the default). In order: a car ahead in the
    /// rig's lane driving a little faster than the rig, an oncoming car in the other lane, a
    /// car crossing the road ahead, a cyclist the rig overtakes (a `bicycle` and its `rider`,
    /// two objects, whatever `classes` says: the static street has neither). Each has its own instance
    /// id for the whole sequence, exact GT in every frame, pseudo labels with the same noise,
    /// and one box per frame (the `dynamic_boxes` table).
    pub moving_objects: u32,
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
            moving_objects: 0,
        }
    }
}

/// KITTI-360's rectified perspective cameras at full size.
pub(super) const KITTI_WIDTH: f64 = 1408.0;
pub(super) const KITTI_HEIGHT: f64 = 376.0;
pub(super) const KITTI_F: f64 = 552.554261;
pub(super) const KITTI_CX: f64 = 682.049453;
pub(super) const KITTI_CY: f64 = 238.769549;

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
            movers: layout::MoverParams {
                count: self.moving_objects,
                first_frame: self.first_frame,
                frames: self.frames,
                frame_spacing: self.frame_spacing_m,
            },
        })
    }

    /// Checks ranges and consistency; errors name the parameter.
    pub fn validate(&self) -> Result<()> {
        let p = self;
        let bad = |m: String| Err(StageError::Params(m));
        if p.frames == 0 {
            return bad("`frames` must be at least 1".into());
        }
        crate::scene::edits::check(&p.edits, None)?;
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
        if p.moving_objects > layout::MAX_MOVERS {
            return bad(format!(
                "`moving_objects` must be 0..={}, got {}",
                layout::MAX_MOVERS,
                p.moving_objects
            ));
        }
        if p.moving_objects > 0 && !p.class_ids()?.contains(&labels::CAR) {
            return bad("`moving_objects` begin with cars: `classes` must include `car`".into());
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
