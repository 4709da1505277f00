//! The `train` stage kind: fits the radiance field with dual semantic fields to one scene.
//! Rays come from the `intersect` stage's sampling plan (samples only inside primitives plus the
//! sky interval, re-jittered every iteration); targets from the scene (RGB, pseudo labels,
//! stereo depth). Writes the weights as `(name, shape, values)` rows readable by pyarrow, the
//! model description needed to rebuild the field, and the training log. The model itself is
//! [`crate::model`]'s; this is glue between tables, the sampler and the engine.

use std::sync::Arc;

use arrow::array::{ArrayRef, Float32Array};
use arrow::datatypes::{Float32Type, Float64Type, UInt32Type};
use arrow::record_batch::RecordBatch;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::geometry::DVec3;
use crate::model::NamedWeight;
use crate::model::TrainError;
use crate::model::{
    fit, weights, BatchOrder, Engine, FieldConfig, FieldSpec, LossTerm, LossTerms, Losses,
    ModelInfo, Optimiser, RayBatch, Schedule, TrainConfig,
};
use crate::rng::{mix, SplitMix64};
use crate::sampling::{
    self, ImageRays, JitterLabels, JitteredRays, PrimInfo, SamplingParams, TrainSampling,
};
use crate::stage::{
    Changed, InputSlot, Inputs, Previous, Progress, Result, StageError, Tables, TypedStage, Updated,
};

mod update;
use crate::{labels, tables};

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
    pub update: update::UpdateParams,
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
            update: update::UpdateParams::default(),
        }
    }
}

/// Where the parameters of the layout before December 2026 went (`train.lr` ->
/// `optimiser.lr`); the runner names the new key when an old one is given.
const MOVED: &[(&str, &str)] = &[
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

pub struct Train;

/// The field spec of a scene: its classes, and as its box the bounds of its primitives
/// (padded by 1 m) clipped to `config.field.margin` around the centres of `cameras`.
pub fn spec_for(prims: &PrimInfo, cameras: &[DVec3], config: &TrainConfig) -> FieldSpec {
    let pad = 1.0;
    let mut lo = prims.bounds_min.map(|v| v - pad);
    let mut hi = prims.bounds_max.map(|v| v + pad);
    if config.field.margin > 0.0 && !cameras.is_empty() {
        let m = f64::from(config.field.margin);
        for a in 0..3 {
            let c_lo = cameras.iter().map(|c| c[a]).fold(f64::INFINITY, f64::min) - m;
            let c_hi = cameras
                .iter()
                .map(|c| c[a])
                .fold(f64::NEG_INFINITY, f64::max)
                + m;
            let (l, h) = (lo[a].max(c_lo as f32), hi[a].min(c_hi as f32));
            // Primitives wholly beyond the margin on this axis: keep their own bounds.
            if l < h {
                (lo[a], hi[a]) = (l, h);
            }
        }
    }
    FieldSpec {
        config: config.field.clone(),
        num_classes: prims.classes.len(),
        aabb_min: lo,
        aabb_max: hi,
        seed: config.seed,
    }
}

/// Rays of the selected cameras (empty: every camera) that cross a primitive: the ones
/// training draws from.
fn candidates(rays: &ImageRays, cameras: &[u8]) -> Vec<u32> {
    rays.images
        .iter()
        .filter(|im| cameras.is_empty() || cameras.contains(&im.camera))
        .flat_map(|im| {
            im.hits
                .iter()
                .enumerate()
                .filter(|(_, &h)| h > 0)
                .map(|(p, _)| im.first_ray + p as u32)
        })
        .collect()
}

impl TypedStage for Train {
    type Params = TrainParams;
    const KIND: &'static str = "train";
    // 16: parameters grouped (schedule, field, sampling, losses, optimiser, experimental) and
    // `cameras` defaulting to the plan's; the same weights for the same settings.
    // 15: the train log has a `loss_sky_prior` column (null unless `losses.sky_prior` > 0).
    // 14: the train log has no wall-clock column (the same seed and config give the same bytes;
    // the runner times the stage); `late_jitter` (on by default) changes runs past 8 passes.
    const VERSION: u32 = 16;
    const DESCRIPTION: &'static str =
        "fits the radiance field with dual semantic fields (L_fixed2D, L_learned2D, L_3D, L_rgb, L_depth)";
    const INPUTS: &'static [InputSlot] = &[
        InputSlot {
            name: "scene",
            tables: &[
                "cameras",
                "primitives",
                "images",
                "pseudo_labels",
                "stereo_depth",
            ],
            optional: false,
            doc: "posed images, primitives, pseudo labels and stereo depth",
        },
        InputSlot {
            name: "rays",
            tables: &["ray_intervals"],
            optional: false,
            doc: "the sampling plan",
        },
        InputSlot {
            name: "depth",
            tables: &["stereo_depth"],
            optional: true,
            doc: "stereo depth for L_depth (default: the scene's own stereo_depth table)",
        },
    ];
    const OUTPUTS: &'static [&'static str] = &["weights", "model", "train_log"];
    const BUDGET_PARAM: Option<&'static str> = Some("schedule.iterations");
    const UPDATES: bool = true;
    const KEYLESS_DEFAULTS: &'static [&'static str] = &["update"];
    const MOVED: &'static [(&'static str, &'static str)] = MOVED;

    fn validate(p: &TrainParams) -> Result<()> {
        p.schedule.validate()?;
        p.update.validate()?;
        let config = p.model_config();
        config.validate()?;
        p.sampling.validate()?;
        p.sampling_params().validate()?;
        if p.cameras.iter().any(|&c| c > 3) {
            return Err(StageError::Params(
                "`cameras` must list KITTI-360 cameras 0 .. 3 (2, 3: the fisheye cameras)".into(),
            ));
        }
        p.backend.supports(&p.field)?;
        p.backend.supports_train(&config)?;
        p.depth_class_ids()?;
        Ok(())
    }

    fn run(&self, p: &TrainParams, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        let rays = training_rays(p, inputs)?;
        let candidates = candidates(&rays, &p.cameras);
        if candidates.is_empty() {
            return Err(StageError::Input(nothing_crossed(inputs, &p.cameras)?));
        }
        let config = p.model_config();
        let centres: Vec<DVec3> = rays.images.iter().map(|im| im.cam.centre()).collect();
        let spec = spec_for(&rays.prims, &centres, &config);
        let mut trainer = p.backend.trainer(&config, spec.clone())?;
        let batch = p.schedule.rays_per_batch.min(candidates.len());
        let training = candidates.len() as f64;
        let mut order = BatchOrder::over(p.seed, candidates, batch);
        // Epoch-wise shuffles: every ray is visited once per epoch. (Drawing each batch from a
        // SplitMix stream seeded with `seed ^ it * GOLDEN` made consecutive batches share all
        // but one ray: training saw only ~iterations + batch distinct rays.)
        let steps = Steps {
            iterations: p.schedule.iterations,
            batch,
            training_rays: training,
            first: 0,
        };
        let mut log = LogColumns::default();
        steps.train(
            p,
            &rays,
            trainer.as_mut(),
            |it| order.batch(it).to_vec(),
            &mut log,
            progress,
        )?;
        outputs(p, &rays, spec, trainer.weights(), log.table()?)
    }

    /// After an edit of the primitives alone, trains on from the previous weights.
    fn can_update(&self, _: &TrainParams, changed: &Changed) -> std::result::Result<(), String> {
        update::can_update(changed)
    }

    fn update(
        &self,
        p: &TrainParams,
        inputs: &Inputs,
        previous: &Previous,
        progress: &dyn Progress,
    ) -> Result<Updated> {
        update::update(self, p, inputs, previous, progress)
    }
}

/// The scene's training rays, with stereo depth kept where `losses.depth_classes` says.
fn training_rays(p: &TrainParams, inputs: &Inputs) -> Result<ImageRays> {
    let mut rays = sampling::train_rays(inputs)?;
    let depth_classes = p.depth_class_ids()?;
    if !depth_classes.is_empty() && !depth_classes.iter().any(|c| rays.prims.classes.contains(c)) {
        // L_depth would silently be off.
        return Err(StageError::Params(format!(
            "`losses.depth_classes`: no primitive of the scene has one of [{}] (its classes: {})",
            p.losses.depth_classes.join(", "),
            rays.prims
                .classes
                .iter()
                .filter_map(|&c| labels::by_id(c).map(|l| l.name))
                .collect::<Vec<_>>()
                .join(", ")
        )));
    }
    rays.restrict_depth_to(&depth_classes);
    Ok(rays)
}

/// The stage's tables: the weights, the model description and the log.
fn outputs(
    p: &TrainParams,
    rays: &ImageRays,
    spec: FieldSpec,
    weights: Vec<NamedWeight>,
    log: RecordBatch,
) -> Result<Tables> {
    let info = ModelInfo {
        spec,
        sampling: p.sampling_params(),
        classes: rays.prims.classes.clone(),
    };
    Ok(Tables::from([
        ("weights".to_string(), weights::weights_table(&weights)?),
        ("model".to_string(), weights::model_table(&info, p.backend)?),
        ("train_log".to_string(), log),
    ]))
}

/// A run of training steps: how many, the batch, the rays drawn from, and the number of the
/// first step (an update continues the previous run's count: its jitter and log go on).
struct Steps {
    iterations: usize,
    batch: usize,
    training_rays: f64,
    first: usize,
}

impl Steps {
    /// Trains `trainer` on the rays `ids_at(step)` names at each step, logging every step.
    fn train(
        &self,
        p: &TrainParams,
        rays: &ImageRays,
        trainer: &mut dyn crate::model::Trainer,
        mut ids_at: impl FnMut(usize) -> Vec<u32>,
        log: &mut LogColumns,
        progress: &dyn Progress,
    ) -> Result<()> {
        let plan = p.sampling_params();
        let (iters, batch, first) = (self.iterations, self.batch, self.first);
        let start = std::time::Instant::now();
        let next_batch = |step: usize| {
            let ids = ids_at(step);
            let it = first + step;
            let jitter = SplitMix64::new(p.seed ^ (it as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15))
                .next_u64();
            let (width, labels) = p
                .sampling
                .jitter_at(it as f64 * batch as f64 / self.training_rays);
            let batch = if width > 0.0 {
                let jittered = JitteredRays {
                    rays,
                    seed: mix(jitter),
                    width: width as f64,
                    bilinear_labels: labels == JitterLabels::Bilinear,
                };
                sampling::sample_batch(&jittered, &ids, &plan, Some(jitter))
            } else {
                sampling::sample_batch(rays, &ids, &plan, Some(jitter))
            };
            batch
                .map(|b| {
                    let mut batch = RayBatch::from_samples(&b);
                    if p.losses.exposure {
                        batch.targets.image = b
                            .ray_ids
                            .iter()
                            .map(|&r| rays.image_index(r) as u32)
                            .collect();
                    }
                    batch
                })
                .map_err(|e| TrainError::Batch(e.message().to_string()))
        };
        let mut step = 0usize;
        fit(trainer, iters, next_batch, |losses| {
            log.push((first + step) as u32, losses);
            if step % 10 == 0 || step + 1 == iters {
                let secs = start.elapsed().as_secs_f64();
                let rays_s = (step + 1) as f64 * batch as f64 / secs.max(1e-9);
                progress.update(
                    step as u64 + 1,
                    iters as u64,
                    &format!("loss {:.4} ({:.0} rays/s)", losses.total, rays_s),
                );
            }
            step += 1;
        })?;
        Ok(())
    }
}

/// Columns of the train log.
#[derive(Default)]
struct LogColumns {
    iteration: Vec<u32>,
    lr: Vec<f64>,
    total: Vec<f32>,
    grad_norm: Vec<f32>,
    terms: [Vec<Option<f32>>; LossTerm::ALL.len()],
}

impl LogColumns {
    fn push(&mut self, it: u32, l: &LossTerms) {
        self.iteration.push(it);
        self.lr.push(l.lr);
        self.total.push(l.total);
        self.grad_norm.push(l.grad_norm);
        for (k, term) in LossTerm::ALL.into_iter().enumerate() {
            self.terms[k].push(l.get(term));
        }
    }

    fn table(self) -> Result<RecordBatch> {
        let mut cols: Vec<ArrayRef> = vec![
            tables::prim::<UInt32Type>(self.iteration),
            tables::prim::<Float64Type>(self.lr),
            tables::prim::<Float32Type>(self.total),
            tables::prim::<Float32Type>(self.grad_norm),
        ];
        for t in self.terms {
            cols.push(Arc::new(Float32Array::from(t)));
        }
        tables::build("train_log", cols)
    }
}

/// Why no ray can be trained on, as far as the scene shows: which images were looked at and
/// how far the primitives are from their cameras.
fn nothing_crossed(inputs: &Inputs, cameras: &[u8]) -> Result<String> {
    let rows = crate::geometry::cameras_from_table(inputs.table("scene", "cameras")?)?;
    let prims = crate::geometry::primitives_from_table(inputs.table("scene", "primitives")?)?;
    let used: Vec<_> = rows
        .iter()
        .filter(|r| cameras.is_empty() || cameras.contains(&r.camera))
        .collect();
    let cameras: Vec<u8> = used
        .iter()
        .map(|r| r.camera)
        .collect::<std::collections::BTreeSet<u8>>()
        .into_iter()
        .collect();
    let frames: std::collections::BTreeSet<u32> = used.iter().map(|r| r.frame).collect();
    let nearest = used
        .iter()
        .flat_map(|r| {
            let at = r.cam.cam_to_world.translation;
            prims.iter().map(move |p| p.aabb().centre().distance(at))
        })
        .fold(f64::INFINITY, f64::min);
    let frames = match (frames.first(), frames.last()) {
        (Some(a), Some(b)) => format!("frames {a}..={b}"),
        _ => "no frame".to_string(),
    };
    Ok(format!(
        "no ray of the {} images of cameras {cameras:?} ({frames}) crosses any of the {} \
         primitives; the nearest primitive centre is {nearest:.1} m from a camera. Check that \
         the poses and the primitives (the scene stage's poses file and bboxes XML) are of \
         the same sequence and frames",
        used.len(),
        prims.len()
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn prims(lo: [f32; 3], hi: [f32; 3]) -> PrimInfo {
        PrimInfo {
            classes: vec![7, 23],
            bounds_min: lo,
            bounds_max: hi,
            ..PrimInfo::default()
        }
    }

    /// A street's far terrain reaches 450 m; cameras drive x in 0..20 at y = 0, z = 1.6.
    #[test]
    fn the_field_box_is_the_primitives_clipped_around_the_cameras() {
        let p = prims([-450.0, -450.0, -1.5], [500.0, 450.0, 18.5]);
        let cams = [DVec3::new(0.0, 0.0, 1.6), DVec3::new(20.0, 0.0, 1.6)];
        let config = TrainConfig::default();
        assert_eq!(config.field.margin, 50.0);
        let s = spec_for(&p, &cams, &config);
        assert_eq!(s.aabb_min, [-50.0, -50.0, -2.5]);
        assert_eq!(s.aabb_max, [70.0, 50.0, 19.5]);
        // 0 keeps the primitives' (padded) bounds, as do scenes with no camera.
        let mut whole = config.clone();
        whole.field.margin = 0.0;
        let s = spec_for(&p, &cams, &whole);
        assert_eq!(s.aabb_min, [-451.0, -451.0, -2.5]);
        assert_eq!(s.aabb_max, [501.0, 451.0, 19.5]);
        assert_eq!(spec_for(&p, &[], &config).aabb_max, [501.0, 451.0, 19.5]);
        // Primitives wholly beyond the margin on an axis keep their own extent there.
        let far = prims([200.0, -5.0, 0.0], [210.0, 5.0, 3.0]);
        let s = spec_for(&far, &cams, &config);
        assert_eq!((s.aabb_min[0], s.aabb_max[0]), (199.0, 211.0));
        assert_eq!((s.aabb_min[1], s.aabb_max[1]), (-6.0, 6.0));
        s.validate().unwrap();
    }

    /// The `update` group enters the canonical params (the cache key) only when it is not the
    /// default, so the key of every train stage cached before it existed stays the same.
    #[test]
    fn default_update_params_stay_out_of_the_key() {
        use crate::Stage;
        let canonical = |v: serde_json::Value| Train.canonical_params(&v).unwrap();
        let plain = canonical(serde_json::json!({}));
        assert!(plain.get("update").is_none(), "{plain}");
        assert!(plain.get("schedule").is_some());
        let set = canonical(serde_json::json!({"update": {"iterations": 50}}));
        assert_eq!(set["update"]["iterations"], 50);
        assert_eq!(
            canonical(plain.clone()),
            plain,
            "canonical params are a fixed point"
        );
        let bad = Train
            .canonical_params(&serde_json::json!({"update": {"edited_share": 1.5}}))
            .unwrap_err()
            .to_string();
        assert!(
            bad.contains("`update.edited_share`: 1.5 must be in 0..=1"),
            "{bad}"
        );
    }

    /// `depth_classes` resolves names and refuses unknown ones by name.
    #[test]
    fn depth_classes_are_named_and_checked() {
        let mut p = TrainParams::default();
        p.losses.depth_classes = vec!["parking".into(), "wall".into(), "gate".into()];
        assert_eq!(
            p.depth_class_ids().unwrap(),
            [labels::PARKING, labels::WALL, labels::GATE]
        );
        Train::validate(&p).unwrap();
        let json = serde_json::to_value(&p).unwrap();
        assert_eq!(json["losses"]["depth_classes"][2], "gate");
        for bad in ["parkng", "sky"] {
            let mut q = TrainParams::default();
            q.losses.depth_classes = vec![bad.into()];
            let e = Train::validate(&q).unwrap_err().to_string();
            assert!(e.contains("losses.depth_classes") && e.contains(bad), "{e}");
        }
    }
}
