//! The `train` stage kind: fits the radiance field with dual semantic fields to one scene.
//! Rays come from the `intersect` stage's sampling plan (samples only inside primitives plus the
//! sky interval, re-jittered every iteration); targets from the scene (RGB, pseudo labels,
//! stereo depth). Writes the weights as `(name, shape, values)` rows readable by pyarrow, the
//! model description needed to rebuild the field, and the training log.

use std::sync::Arc;

use arrow::{
    array::{Array, ArrayRef, Float32Array},
    datatypes::{Float64Type, UInt32Type, UInt8Type},
};
use serde::{Deserialize, Serialize};

use crate::{
    field::{weights::NamedWeight, Backend, FieldSpec, RadianceField},
    fused::{FusedField, FusedTrainer},
    sampling::{self, RaySet, SampleBatch, SamplingParams, SplitMix},
    tables,
    train::{BatchOrder, LossTerm, RayBatch, RaySamples, RayTargets, TrainConfig, Trainer},
    InputSlot, Inputs, Progress, Result, StageError, Tables, TypedStage,
};

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainParams {
    /// Optimiser, losses and field architecture.
    pub train: TrainConfig,
    /// Where samples go along each ray.
    pub sampling: SamplingParams,
    /// Cameras whose rays are trained on (0 = left, 1 = right).
    pub cameras: Vec<u8>,
    /// `fused` (default: the hand-written CPU path of the grid field, see `stages::fused`), or a
    /// burn backend: flex, ndarray, wgpu or cuda (the latter need their cargo feature).
    pub backend: String,
}

impl Default for TrainParams {
    fn default() -> Self {
        Self {
            train: TrainConfig::default(),
            sampling: SamplingParams::default(),
            cameras: vec![0, 1],
            backend: FUSED.to_string(),
        }
    }
}

/// The `backend` value of the fused CPU path.
pub const FUSED: &str = "fused";

/// The model description stored beside the weights.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ModelInfo {
    pub spec: FieldSpec,
    pub sampling: SamplingParams,
    /// Label ids of the semantic head's classes (sky last).
    pub classes: Vec<u8>,
}

pub struct Train;

/// Converts a sample batch to the trainer's host batch. Stereo depth is a camera z-depth; the
/// trainer compares it with distances along the ray, so divide by the ray's z scale.
pub fn to_ray_batch(b: &SampleBatch) -> RayBatch {
    let depth_valid: Vec<bool> = b.depth.iter().map(|&d| d > 0.0).collect();
    RayBatch {
        samples: RaySamples {
            rays: b.rays,
            samples: b.samples,
            classes: b.classes,
            positions: b.positions.clone(),
            deltas: b.deltas.clone(),
            t_mid: b.t.clone(),
            directions: b.dirs.clone(),
            fixed_semantics: b.fixed_semantic.clone(),
        },
        targets: RayTargets {
            labels: b.label.iter().map(|&l| l as i32).collect(),
            ray_mask: b.u_mask.clone(),
            depth: b
                .depth
                .iter()
                .zip(&b.z_scale)
                .map(|(&d, &z)| if d > 0.0 && z > 0.0 { d / z } else { 0.0 })
                .collect(),
            depth_valid,
            rgb: b.target_rgb.clone(),
        },
    }
}

/// The field spec of a ray set: its classes and the bounds of its primitives.
pub fn spec_for(set: &RaySet, config: &TrainConfig) -> FieldSpec {
    let pad = 1.0;
    FieldSpec {
        config: config.field.clone(),
        num_classes: set.classes.len(),
        aabb_min: set.bounds_min.map(|v| v - pad),
        aabb_max: set.bounds_max.map(|v| v + pad),
        seed: config.seed,
    }
}

fn backend(name: &str) -> Result<Backend> {
    Backend::from_name(name).ok_or_else(|| {
        StageError::Params(format!(
            "`backend`: `{name}` is not compiled in (available: {})",
            Backend::available()
                .iter()
                .map(|b| b.name())
                .collect::<Vec<_>>()
                .join(", ")
        ))
    })
}

impl TypedStage for Train {
    type Params = TrainParams;
    const KIND: &'static str = "train";
    const VERSION: u32 = 4;
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
    const BUDGET_PARAM: Option<&'static str> = Some("train.iterations");

    fn validate(p: &TrainParams) -> Result<()> {
        p.train.validate().map_err(StageError::Params)?;
        p.sampling.validate()?;
        if p.cameras.is_empty() || p.cameras.iter().any(|&c| c > 1) {
            return Err(StageError::Params("`cameras` must list 0 and/or 1".into()));
        }
        if p.backend == FUSED {
            if p.train.field.encoding != crate::field::EncodingKind::Grid {
                return Err(StageError::Params(
                    "`backend: fused` supports `train.field.encoding: grid` only; use backend flex \
                     for pe"
                        .into(),
                ));
            }
        } else {
            backend(&p.backend)?;
        }
        Ok(())
    }

    fn run(&self, p: &TrainParams, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        let set = RaySet::from_inputs(inputs)?;
        let candidates: Vec<u32> = set
            .images
            .iter()
            .filter(|im| p.cameras.contains(&im.camera))
            .flat_map(|im| {
                let n = (im.width * im.height) as usize;
                (im.first_ray..im.first_ray + n)
                    .filter(|&r| set.hits_anything(r))
                    .map(|r| r as u32)
            })
            .collect();
        if candidates.is_empty() {
            return Err(StageError::Input(
                "no ray of the selected cameras crosses a primitive".into(),
            ));
        }
        let spec = spec_for(&set, &p.train);
        let mut trainer = if p.backend == FUSED {
            let init = spec.init(&Backend::default().device());
            let field = FusedField::from_field(&init).map_err(StageError::Params)?;
            AnyTrainer::Fused(Box::new(FusedTrainer::new(p.train.clone(), field)?))
        } else {
            AnyTrainer::Burn(Box::new(Trainer::new(
                p.train.clone(),
                spec.clone(),
                backend(&p.backend)?,
            )?))
        };
        let iters = p.train.iterations;
        let batch = p.train.rays_per_batch.min(candidates.len());
        let start = std::time::Instant::now();
        let mut log = LogColumns::default();
        let mut order = BatchOrder::new(p.train.seed, candidates.len(), batch);
        for it in 0..iters {
            // Epoch-wise shuffles: every ray is visited once per epoch. (Drawing each batch from
            // a SplitMix stream seeded with `seed ^ it * GOLDEN` made consecutive batches share
            // all but one ray: training saw only ~iterations + batch distinct rays.)
            let ids: Vec<u32> = order.indices(it).iter().map(|&i| candidates[i]).collect();
            let jitter =
                SplitMix(p.train.seed ^ (it as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)).next_u64();
            let samples = sampling::sample_batch(&set, &ids, &p.sampling, Some(jitter));
            let losses = trainer.step(&to_ray_batch(&samples))?;
            let secs = start.elapsed().as_secs_f64();
            log.push(it as u32, secs, &losses);
            if it % 10 == 0 || it + 1 == iters {
                let rays_s = (it + 1) as f64 * batch as f64 / secs.max(1e-9);
                progress.update(
                    it as u64 + 1,
                    iters as u64,
                    &format!("loss {:.4} ({:.0} rays/s)", losses.total, rays_s),
                );
            }
        }
        let (weights, spec) = match trainer {
            AnyTrainer::Fused(t) => {
                let f = t.into_field();
                (f.weights, f.spec)
            }
            AnyTrainer::Burn(t) => {
                let f: RadianceField = t.into_field();
                (f.weights(), f.spec)
            }
        };
        let info = ModelInfo {
            spec,
            sampling: p.sampling.clone(),
            classes: set.classes.clone(),
        };
        Ok(Tables::from([
            ("weights".to_string(), weights_table(&weights)?),
            (
                "model".to_string(),
                tables::build(
                    "model",
                    vec![
                        tables::strings([serde_json::to_string(&info)
                            .map_err(|e| StageError::Failed(e.to_string()))?]),
                        tables::list::<UInt8Type>([set.classes.clone()]),
                        tables::strings([p.backend.clone()]),
                    ],
                )?,
            ),
            ("train_log".to_string(), log.table()?),
        ]))
    }
}

fn weights_table(w: &[NamedWeight]) -> Result<arrow::record_batch::RecordBatch> {
    tables::build(
        "weights",
        vec![
            tables::strings(w.iter().map(|x| x.name.as_str())),
            tables::list::<UInt32Type>(
                w.iter()
                    .map(|x| x.shape.iter().map(|&s| s as u32).collect()),
            ),
            tables::list::<arrow::datatypes::Float32Type>(w.iter().map(|x| x.values.clone())),
        ],
    )
}

/// Reads a trained field back from the `train` stage's tables.
pub fn load_field(
    weights: &arrow::record_batch::RecordBatch,
    model: &arrow::record_batch::RecordBatch,
    backend_name: Option<&str>,
) -> Result<(RadianceField, ModelInfo)> {
    let info_col = tables::get_strings(model, "model", "info")?;
    if info_col.is_empty() {
        return Err(StageError::Input("table `model` is empty".into()));
    }
    let info: ModelInfo = serde_json::from_str(info_col.value(0))
        .map_err(|e| StageError::Input(format!("table `model` column `info`: {e}")))?;
    let names = tables::get_strings(weights, "weights", "name")?;
    let shapes = tables::get_list::<UInt32Type>(weights, "weights", "shape")?;
    let values = tables::get_list::<arrow::datatypes::Float32Type>(weights, "weights", "values")?;
    let rows: Vec<NamedWeight> = (0..weights.num_rows())
        .map(|i| NamedWeight {
            name: names.value(i).to_string(),
            shape: shapes.row(i).iter().map(|&s| s as usize).collect(),
            values: values.row(i).to_vec(),
        })
        .collect();
    let b = backend(backend_name.unwrap_or(Backend::default().name()))?;
    let field = info
        .spec
        .init(&b.device())
        .load_weights(&rows)
        .map_err(|e| StageError::Input(format!("table `weights`: {e}")))?;
    Ok((field, info))
}

/// The burn trainer or the fused CPU one.
enum AnyTrainer {
    Burn(Box<Trainer>),
    Fused(Box<FusedTrainer>),
}

impl AnyTrainer {
    fn step(
        &mut self,
        batch: &RayBatch,
    ) -> std::result::Result<crate::train::LossTerms, crate::train::TrainError> {
        match self {
            AnyTrainer::Burn(t) => t.step(batch),
            AnyTrainer::Fused(t) => t.step(batch),
        }
    }
}

/// Columns of the train log.
#[derive(Default)]
struct LogColumns {
    iteration: Vec<u32>,
    seconds: Vec<f64>,
    lr: Vec<f64>,
    total: Vec<f32>,
    grad_norm: Vec<f32>,
    terms: [Vec<Option<f32>>; 5],
}

impl LogColumns {
    fn push(&mut self, it: u32, secs: f64, l: &crate::train::LossTerms) {
        self.iteration.push(it);
        self.seconds.push(secs);
        self.lr.push(l.lr);
        self.total.push(l.total);
        self.grad_norm.push(l.grad_norm);
        for (k, term) in LossTerm::ALL.into_iter().enumerate() {
            self.terms[k].push(l.get(term));
        }
    }

    fn table(self) -> Result<arrow::record_batch::RecordBatch> {
        let mut cols: Vec<ArrayRef> = vec![
            tables::prim::<UInt32Type>(self.iteration),
            tables::prim::<Float64Type>(self.seconds),
            tables::prim::<Float64Type>(self.lr),
            tables::prim::<arrow::datatypes::Float32Type>(self.total),
            tables::prim::<arrow::datatypes::Float32Type>(self.grad_norm),
        ];
        for t in self.terms {
            cols.push(Arc::new(Float32Array::from(t)));
        }
        tables::build("train_log", cols)
    }
}
