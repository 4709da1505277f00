//! The parameters of the `train` stage, grouped by what they configure, and where the
//! parameters of earlier layouts went.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::labels;
use crate::model::{Engine, FieldConfig, Losses, Optimiser, Schedule, TrainConfig};
use crate::sampling::{SamplingParams, TrainSampling};
use crate::stage::{Result, StageError};

/// Parameters of the `train` stage, grouped by what they configure.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct TrainParams {
    /// Cameras trained on (`image_00` .. `image_03`, or 0 .. 3); empty: every camera of `rays`.
    /// The `rays` stage plans the scene's cameras unless it narrows them. Images without pseudo
    /// labels train colour only.
    #[serde(deserialize_with = "crate::geometry::camera::camera_ids")]
    #[schemars(with = "Vec<crate::geometry::camera::CameraName>")]
    pub cameras: Vec<u8>,
    /// The engine: `fused` (CPU kernels of the grid field) or a burn backend.
    /// The burn backends are flex, ndarray, wgpu and cuda (the last three need their cargo
    /// feature). Some settings are one engine's alone; the others refuse them by name.
    pub backend: Engine,
    /// Seed of the initial weights, the ray order and the jitter.
    pub seed: u64,
    /// How long training runs.
    pub schedule: Schedule,
    /// The radiance field with its dual semantic heads.
    pub field: FieldConfig,
    /// What each training ray samples, and where in its pixel it goes.
    pub sampling: TrainSampling,
    /// The loss terms' weights and settings.
    pub losses: Losses,
    /// Adam and its learning rate.
    pub optimiser: Optimiser,
    /// Switches for research only (the paper's ablations): each makes the labels worse.
    pub experimental: Experimental,
    /// How an edit of the primitives trains on from the previous weights (`pipe run --cold`:
    /// from scratch). Absent from the cache key while at its defaults.
    pub update: UpdateParams,
}

/// Switches for research only: the paper's ablations (docs/experiments/ablation.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Experimental {
    /// Apply the ray mask u(r) to L_learned2D; false: every labelled ray counts (the ablation
    /// "w/o u(r)").
    pub ray_mask: bool,
    /// `[near, far]` metres to sample rays evenly over (the ablation); null: in the primitives.
    /// The ablation "uniform sampling" places samples without regard to the primitives.
    pub uniform_sampling: Option<[f32; 2]>,
}

impl Default for Experimental {
    fn default() -> Self {
        Self {
            ray_mask: true,
            uniform_sampling: None,
        }
    }
}

impl TrainParams {
    /// Label ids of `losses.depth_classes`; an unknown name is an error naming it.
    pub fn depth_class_ids(&self) -> Result<Vec<u8>> {
        self.losses
            .depth_classes
            .iter()
            .map(|name| {
                labels::by_name(name)
                    .filter(|l| l.id != labels::SKY)
                    .map(|l| l.id)
                    .ok_or_else(|| {
                        StageError::Params(format!(
                            "`losses.depth_classes`: `{name}` is not a KITTI-360 class name that \
                             primitives can have (e.g. road, parking, wall, gate, building)"
                        ))
                    })
            })
            .collect()
    }

    /// What the engine's trainer is given.
    pub fn model_config(&self) -> TrainConfig {
        TrainConfig {
            field: self.field.clone(),
            losses: self.losses.clone(),
            optimiser: self.optimiser.clone(),
            iterations: self.schedule.iterations,
            seed: self.seed,
            ray_mask: self.experimental.ray_mask,
        }
    }

    /// Where samples go along each ray, as stored beside the weights.
    pub fn sampling_params(&self) -> SamplingParams {
        self.sampling.params(self.experimental.uniform_sampling)
    }
}

impl Default for TrainParams {
    fn default() -> Self {
        Self {
            cameras: Vec::new(),
            backend: Engine::Fused,
            seed: 0,
            schedule: Schedule::default(),
            field: FieldConfig::default(),
            sampling: TrainSampling::default(),
            losses: Losses::default(),
            optimiser: Optimiser::default(),
            experimental: Experimental::default(),
            update: UpdateParams::default(),
        }
    }
}

/// Where the parameters of the layout before December 2026 went (`train.lr` ->
/// `optimiser.lr`); the runner names the new key when an old one is given.
pub(super) const MOVED: &[(&str, &str)] = &[
    ("train.iterations", "schedule.iterations"),
    ("train.rays_per_batch", "schedule.rays_per_batch"),
    ("train.seed", "seed"),
    ("train.field_margin", "field.margin"),
    ("train.field", "field"),
    ("train.losses", "losses"),
    ("train.label_eps", "losses.label_eps"),
    ("train.sigma_threshold", "losses.sigma_threshold"),
    ("train.sky_prior_colour", "losses.sky_prior_colour"),
    ("train.exposure", "losses.exposure"),
    ("train.ray_mask", "experimental.ray_mask"),
    ("train.lr", "optimiser.lr"),
    ("train.lr_final_factor", "optimiser.lr_final_factor"),
    ("train.grad_clip_norm", "optimiser.grad_clip_norm"),
    ("train.adam_beta1", "optimiser.adam_beta1"),
    ("train.adam_beta2", "optimiser.adam_beta2"),
    ("train.adam_epsilon", "optimiser.adam_epsilon"),
    ("train.pixel_jitter", "sampling.pixel_jitter"),
    ("train.jitter_labels", "sampling.jitter_labels"),
    ("train.late_jitter", "sampling.late_jitter"),
    (
        "train",
        "(into the groups schedule, field, sampling, losses, optimiser and experimental)",
    ),
    ("depth_classes", "losses.depth_classes"),
    (
        "sampling.mode",
        "experimental.uniform_sampling ([near, far] metres, or null for the primitives)",
    ),
    (
        "sampling.near",
        "experimental.uniform_sampling ([near, far] metres)",
    ),
    (
        "sampling.far",
        "experimental.uniform_sampling ([near, far] metres)",
    ),
];

/// How an edit of the primitives trains on from the previous weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct UpdateParams {
    /// Steps trained after an edit, from the previous weights; the learning rate decays over them.
    pub iterations: usize,
    /// Steps instead of `iterations` for an edit that only removes primitives. The fields need
    /// only stop seeing them; nothing new has to be learned.
    pub removal_iterations: usize,
    /// Share of each batch drawn from the rays the edit can change (0..=1); the rest from all.
    pub edited_share: f64,
    /// The update's first learning rate as a share of `optimiser.lr` (it decays as a run's does).
    pub lr_factor: f64,
}

impl Default for UpdateParams {
    fn default() -> Self {
        Self {
            iterations: 400,
            // 250: a deletion labelled as well as with 400, in 65 s (docs/experiments/edits.md).
            removal_iterations: 250,
            edited_share: 0.5,
            // 0.3: a moved box's geometry needs it at full size (docs/experiments/edits.md).
            lr_factor: 0.3,
        }
    }
}

impl UpdateParams {
    pub fn validate(&self) -> Result<()> {
        for (name, n) in [
            ("iterations", self.iterations),
            ("removal_iterations", self.removal_iterations),
        ] {
            if n == 0 {
                return Err(StageError::Params(format!(
                    "`update.{name}`: 0 must be at least 1"
                )));
            }
        }
        if !(self.lr_factor.is_finite() && self.lr_factor > 0.0) {
            return Err(StageError::Params(format!(
                "`update.lr_factor`: {} must be > 0",
                self.lr_factor
            )));
        }
        if !(0.0..=1.0).contains(&self.edited_share) {
            return Err(StageError::Params(format!(
                "`update.edited_share`: {} must be in 0..=1",
                self.edited_share
            )));
        }
        Ok(())
    }
}
