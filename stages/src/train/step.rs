//! One optimisation step (forward, losses, backward, global-norm clipping, Adam) and the
//! training loop.
//!
//! Non-finite values are caught at two points and reported as [`TrainError`]s naming the
//! iteration and the loss term: the loss values (read back every step anyway for the log), and
//! the global gradient norm (one extra scalar read-back). A non-finite gradient re-runs the
//! forward/backward per term, only on that failure path, to name the term responsible. Either
//! way the weights are left as they were before the failing step.

use std::time::Instant;

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::activation::softmax;
use burn::tensor::{Device, Tensor, TensorData};

use super::batch::{batch_indices, RayBatch};
use super::loss::{self, LossTerm};
use super::TrainConfig;
use crate::field::{
    render_depth, render_rgb, render_semantics, render_weights, Backend, FieldHead, FieldSpec,
    RadianceField,
};
use crate::StageError;

/// Why training stopped.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TrainError {
    /// The config or field spec is invalid.
    #[error("invalid train config: {0}")]
    Config(String),
    /// A batch has wrong lengths or values.
    #[error("bad ray batch: {0}")]
    Batch(String),
    /// A loss term evaluated to NaN or infinity.
    #[error(
        "iteration {iteration}: loss `{term}` is {value}; check the inputs, lower lr or enable \
         grad_clip_norm"
    )]
    NonFiniteLoss {
        iteration: usize,
        term: LossTerm,
        value: f32,
    },
    /// A gradient has NaN or infinite entries (`term` is `total` when no single term does).
    #[error(
        "iteration {iteration}: the gradient of loss `{term}` is not finite in parameter \
         `{param}`; lower lr or enable grad_clip_norm"
    )]
    NonFiniteGradient {
        iteration: usize,
        term: String,
        param: String,
    },
}

impl From<TrainError> for StageError {
    fn from(e: TrainError) -> Self {
        match e {
            TrainError::Config(m) => StageError::Params(m),
            TrainError::Batch(m) => StageError::Input(m),
            other => StageError::Failed(other.to_string()),
        }
    }
}

/// What one step reports.
#[derive(Debug, Clone, PartialEq)]
pub struct LossTerms {
    pub iteration: usize,
    pub lr: f64,
    /// Unweighted value of each enabled term.
    pub terms: Vec<(LossTerm, f32)>,
    /// Weighted sum, the optimised quantity.
    pub total: f32,
    /// Global gradient norm before clipping.
    pub grad_norm: f32,
}

impl LossTerms {
    /// Unweighted value of `term`, `None` when disabled.
    pub fn get(&self, term: LossTerm) -> Option<f32> {
        self.terms.iter().find(|(t, _)| *t == term).map(|(_, v)| *v)
    }
}

/// One row of the train log.
#[derive(Debug, Clone, PartialEq)]
pub struct LogRow {
    /// Seconds since training started, at the end of this step.
    pub seconds: f64,
    pub losses: LossTerms,
}

/// Device tensors of one batch.
struct BatchTensors {
    deltas: Tensor<2>,
    t_mid: Tensor<2>,
    fixed: Tensor<3>,
    unique: Tensor<2>,
    label_one_hot: Tensor<2>,
    labelled: Tensor<1>,
    learned_mask: Tensor<1>,
    depth: Tensor<1>,
    depth_valid: Tensor<1>,
    rgb: Tensor<2>,
}

impl BatchTensors {
    fn new(batch: &RayBatch, use_ray_mask: bool, device: &Device) -> Self {
        let s = &batch.samples;
        let t = &batch.targets;
        let (r, n, c) = (s.rays, s.samples, s.classes);
        let t2 = |v: Vec<f32>, shape: [usize; 2]| {
            Tensor::<2>::from_data(TensorData::new(v, shape), device)
        };
        let t1 = |v: Vec<f32>| Tensor::<1>::from_data(TensorData::new(v, [r]), device);
        let mut one_hot = vec![0f32; r * c];
        let mut labelled = vec![0f32; r];
        for (i, &l) in t.labels.iter().enumerate() {
            if l >= 0 {
                one_hot[i * c + l as usize] = 1.0;
                labelled[i] = 1.0;
            }
        }
        let learned: Vec<f32> = labelled
            .iter()
            .zip(&t.ray_mask)
            .map(|(a, b)| if use_ray_mask { a * b } else { *a })
            .collect();
        let valid: Vec<f32> = t.depth_valid.iter().map(|&v| v as u8 as f32).collect();
        let depth: Vec<f32> = t
            .depth
            .iter()
            .zip(&t.depth_valid)
            .map(|(&d, &v)| if v { d } else { 0.0 })
            .collect();
        Self {
            deltas: t2(s.deltas.clone(), [r, n]),
            t_mid: t2(s.t_mid.clone(), [r, n]),
            fixed: Tensor::from_data(
                TensorData::new(s.fixed_semantics.clone(), [r, n, c]),
                device,
            ),
            unique: t2(s.unique_class_mask(), [r, n]),
            label_one_hot: t2(one_hot, [r, c]),
            labelled: t1(labelled),
            learned_mask: t1(learned),
            depth: t1(depth),
            depth_valid: t1(valid),
            rgb: t2(t.rgb.clone(), [r, 3]),
        }
    }
}

/// Forward pass and the requested loss terms (unweighted, each `[1]`).
fn losses(
    field: &RadianceField,
    batch: &RayBatch,
    config: &TrainConfig,
    terms: &[LossTerm],
) -> Vec<(LossTerm, Tensor<1>)> {
    let device = field.trunk.layers[0].weight.device();
    let s = &batch.samples;
    let (r, n, c) = (s.rays, s.samples, s.classes);
    let bt = BatchTensors::new(batch, config.ray_mask, &device);
    let mut heads = vec![FieldHead::Density];
    if terms.contains(&LossTerm::Rgb) {
        heads.push(FieldHead::Rgb);
    }
    if terms.contains(&LossTerm::Learned2d) || terms.contains(&LossTerm::Point3d) {
        heads.push(FieldHead::Semantics);
    }
    let directions = heads
        .contains(&FieldHead::Rgb)
        .then_some(s.directions.as_slice());
    let input = field.prepare(&s.positions, directions, n);
    let out = field.forward(&input, &heads);
    let density = out.density.reshape([r, n]); // [rays, samples]
    let w = render_weights(density.clone(), bt.deltas);
    let logits = out.logits.map(|l| l.reshape([r, n, c])); // [rays, samples, classes]
    let sky = c - 1;
    terms
        .iter()
        .map(|&term| {
            let value = match term {
                LossTerm::Fixed2d => loss::label_nll(
                    render_semantics(&w, bt.fixed.clone(), sky),
                    bt.label_one_hot.clone(),
                    bt.labelled.clone(),
                ),
                LossTerm::Learned2d => loss::label_nll(
                    render_semantics(&w, softmax(logits.clone().expect("semantics head"), 2), sky),
                    bt.label_one_hot.clone(),
                    bt.learned_mask.clone(),
                ),
                LossTerm::Point3d => loss::point_ce(
                    logits.clone().expect("semantics head"),
                    bt.fixed.clone(),
                    bt.unique.clone(),
                    density.clone(),
                    config.sigma_threshold,
                ),
                LossTerm::Rgb => loss::rgb_mse(
                    render_rgb(&w, out.rgb.clone().expect("rgb head").reshape([r, n, 3])),
                    bt.rgb.clone(),
                ),
                LossTerm::Depth => loss::depth_mse(
                    render_depth(&w, bt.t_mid.clone()),
                    bt.depth.clone(),
                    bt.depth_valid.clone(),
                ),
            };
            (term, value)
        })
        .collect()
}

/// Sum of squares of every gradient, per parameter name.
struct GradSquares<'a> {
    grads: &'a GradientsParams,
    path: Vec<String>,
    names: Vec<String>,
    squares: Vec<Tensor<1>>,
}

impl ModuleVisitor for GradSquares<'_> {
    fn enter_module(&mut self, name: &str, _: &str) {
        self.path.push(name.to_string());
    }
    fn exit_module(&mut self, _: &str, _: &str) {
        self.path.pop();
    }
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if let Some(g) = self.grads.get::<D>(param.id) {
            self.names.push(self.path.join("."));
            self.squares.push(g.square().sum());
        }
    }
}

/// Scales every gradient by `factor`.
struct ScaleGrads<'a> {
    grads: &'a mut GradientsParams,
    factor: f32,
}

impl ModuleVisitor for ScaleGrads<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if let Some(g) = self.grads.remove::<D>(param.id) {
            self.grads.register(param.id, g.mul_scalar(self.factor));
        }
    }
}

/// Global gradient norm, or the name of the first parameter with a non-finite gradient.
fn grad_norm(field: &RadianceField, grads: &GradientsParams) -> Result<f32, String> {
    let mut v = GradSquares {
        grads,
        path: Vec::new(),
        names: Vec::new(),
        squares: Vec::new(),
    };
    field.visit(&mut v);
    if v.squares.is_empty() {
        return Ok(0.0);
    }
    let squares = Tensor::cat(v.squares, 0)
        .into_data()
        .try_to_vec::<f32>()
        .expect("f32");
    let mut total = 0f64;
    for (name, s) in v.names.iter().zip(squares) {
        if !s.is_finite() {
            return Err(name.clone());
        }
        total += s as f64;
    }
    Ok(total.sqrt() as f32)
}

/// Collects every parameter's gradient as a named row (zeros where a parameter got none).
#[cfg(test)]
struct CollectGrads<'a> {
    grads: &'a GradientsParams,
    path: Vec<String>,
    out: Vec<crate::field::NamedWeight>,
}

#[cfg(test)]
impl ModuleVisitor for CollectGrads<'_> {
    fn enter_module(&mut self, name: &str, _: &str) {
        self.path.push(name.to_string());
    }
    fn exit_module(&mut self, _: &str, _: &str) {
        self.path.pop();
    }
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let shape = param.val().dims().to_vec();
        let values = match self.grads.get::<D>(param.id) {
            Some(g) => g.into_data().try_to_vec::<f32>().expect("f32"),
            None => vec![0.0; shape.iter().product()],
        };
        self.out.push(crate::field::NamedWeight {
            name: self.path.join("."),
            shape,
            values,
        });
    }
}

/// The burn reference: unweighted loss values and the gradient of their weighted sum, per
/// named parameter (`field` must live on an autodiff device).
#[cfg(test)]
pub(crate) fn reference_gradients(
    field: &RadianceField,
    batch: &RayBatch,
    config: &TrainConfig,
) -> (Vec<(LossTerm, f32)>, Vec<crate::field::NamedWeight>) {
    let terms = config.losses.enabled();
    let values = losses(field, batch, config, &terms);
    let read: Vec<(LossTerm, f32)> = values
        .iter()
        .map(|(t, v)| {
            (
                *t,
                v.clone().detach().into_data().try_to_vec::<f32>().expect("f32")[0],
            )
        })
        .collect();
    let total = values
        .into_iter()
        .map(|(t, v)| v.mul_scalar(config.losses.get(t)))
        .reduce(|a, b| a + b)
        .expect("a term");
    let grads = GradientsParams::from_grads(total.backward(), field);
    let mut c = CollectGrads {
        grads: &grads,
        path: Vec::new(),
        out: Vec::new(),
    };
    field.visit(&mut c);
    (read, c.out)
}

/// Holds the field being trained and its optimiser state.
pub struct Trainer {
    field: Option<RadianceField>,
    optimizer: ModuleOptimizer,
    config: TrainConfig,
    terms: Vec<LossTerm>,
    iteration: usize,
}

impl Trainer {
    /// A fresh field from `spec` (its `config` is replaced by `config.field`) on the autodiff
    /// device of `backend`.
    pub fn new(config: TrainConfig, spec: FieldSpec, backend: Backend) -> Result<Self, TrainError> {
        config.validate().map_err(TrainError::Config)?;
        let spec = FieldSpec {
            config: config.field.clone(),
            ..spec
        };
        spec.validate().map_err(TrainError::Config)?;
        let field = spec.init(&backend.train_device());
        Ok(Self::from_field(config, field))
    }

    /// Continues training `field` (which must live on an autodiff device) with fresh Adam state.
    pub fn from_field(config: TrainConfig, field: RadianceField) -> Self {
        let optimizer = AdamConfig::new()
            .with_beta_1(config.adam_beta1)
            .with_beta_2(config.adam_beta2)
            .with_epsilon(config.adam_epsilon)
            .init();
        let terms = config.losses.enabled();
        Self {
            field: Some(field),
            optimizer,
            config,
            terms,
            iteration: 0,
        }
    }

    /// The field (on the autodiff device).
    pub fn field(&self) -> &RadianceField {
        self.field.as_ref().expect("field present between steps")
    }

    /// Steps done so far.
    pub fn iteration(&self) -> usize {
        self.iteration
    }

    /// The field without autodiff, for inference and export.
    pub fn into_field(self) -> RadianceField {
        self.field().valid()
    }

    /// One step on `batch`: forward, the enabled losses, backward, global-norm clipping, Adam.
    /// On error the weights are unchanged.
    pub fn step(&mut self, batch: &RayBatch) -> Result<LossTerms, TrainError> {
        batch.validate().map_err(TrainError::Batch)?;
        if batch.samples.classes != self.field().spec.num_classes {
            return Err(TrainError::Batch(format!(
                "batch has {} classes, the field {}",
                batch.samples.classes,
                self.field().spec.num_classes
            )));
        }
        let iteration = self.iteration;
        let lr = self.config.lr_at(iteration);
        let field = self.field.take().expect("field present between steps");
        let result = self.step_inner(&field, batch, iteration, lr);
        match result {
            Ok((grads, mut report)) => {
                report.lr = lr;
                self.field = Some(self.optimizer.step(lr, field, grads));
                self.iteration += 1;
                Ok(report)
            }
            Err(e) => {
                self.field = Some(field);
                Err(e)
            }
        }
    }

    fn step_inner(
        &self,
        field: &RadianceField,
        batch: &RayBatch,
        iteration: usize,
        lr: f64,
    ) -> Result<(GradientsParams, LossTerms), TrainError> {
        let values = losses(field, batch, &self.config, &self.terms);
        let read: Vec<f32> =
            Tensor::cat(values.iter().map(|(_, v)| v.clone().detach()).collect(), 0)
                .into_data()
                .try_to_vec::<f32>()
                .expect("f32");
        for ((term, _), &value) in values.iter().zip(&read) {
            if !value.is_finite() {
                return Err(TrainError::NonFiniteLoss {
                    iteration,
                    term: *term,
                    value,
                });
            }
        }
        let mut total_value = 0f32;
        let mut total: Option<Tensor<1>> = None;
        for ((term, v), &value) in values.into_iter().zip(&read) {
            let w = self.config.losses.get(term);
            total_value += w * value;
            let weighted = v.mul_scalar(w);
            total = Some(match total {
                Some(t) => t + weighted,
                None => weighted,
            });
        }
        let total = total.expect("at least one enabled term");
        let mut grads = GradientsParams::from_grads(total.backward(), field);
        let norm = match grad_norm(field, &grads) {
            Ok(n) if n.is_finite() => n,
            Ok(_) => return Err(self.blame_gradient(field, batch, iteration, "(norm overflow)")),
            Err(param) => return Err(self.blame_gradient(field, batch, iteration, &param)),
        };
        let clip = self.config.grad_clip_norm;
        if clip > 0.0 && norm > clip {
            let mut scale = ScaleGrads {
                grads: &mut grads,
                factor: clip / (norm + 1e-6),
            };
            field.visit(&mut scale);
        }
        let report = LossTerms {
            iteration,
            lr,
            terms: self.terms.iter().copied().zip(read).collect(),
            total: total_value,
            grad_norm: norm,
        };
        Ok((grads, report))
    }

    /// Failure path: which single term has a non-finite gradient (else `total`).
    fn blame_gradient(
        &self,
        field: &RadianceField,
        batch: &RayBatch,
        iteration: usize,
        param: &str,
    ) -> TrainError {
        for &term in &self.terms {
            let (_, value) = losses(field, batch, &self.config, &[term])
                .pop()
                .expect("one term");
            let grads = GradientsParams::from_grads(value.backward(), field);
            if let Err(p) = grad_norm(field, &grads) {
                return TrainError::NonFiniteGradient {
                    iteration,
                    term: term.name().to_string(),
                    param: p,
                };
            }
        }
        TrainError::NonFiniteGradient {
            iteration,
            term: "total".to_string(),
            param: param.to_string(),
        }
    }
}

/// The result of [`train`].
pub struct Trained {
    /// The trained field, without autodiff.
    pub field: RadianceField,
    pub log: Vec<LogRow>,
}

/// Trains a fresh field on `rays` for `config.iterations` steps of `config.rays_per_batch`
/// seeded-shuffled rays; `on_step` sees every step's losses (progress bars, early logging).
pub fn train(
    config: &TrainConfig,
    spec: FieldSpec,
    backend: Backend,
    rays: &RayBatch,
    mut on_step: impl FnMut(&LossTerms),
) -> Result<Trained, TrainError> {
    rays.validate().map_err(TrainError::Batch)?;
    if rays.rays() == 0 {
        return Err(TrainError::Batch("no rays to train on".into()));
    }
    let spec = FieldSpec {
        seed: config.seed,
        ..spec
    };
    let mut trainer = Trainer::new(config.clone(), spec, backend)?;
    let start = Instant::now();
    let mut log = Vec::with_capacity(config.iterations);
    for it in 0..config.iterations {
        let idx = batch_indices(config.seed, it, rays.rays(), config.rays_per_batch);
        let losses = trainer.step(&rays.select(&idx))?;
        on_step(&losses);
        log.push(LogRow {
            seconds: start.elapsed().as_secs_f64(),
            losses,
        });
    }
    Ok(Trained {
        field: trainer.into_field(),
        log,
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::field::{FieldConfig, GridConfig, NamedWeight};
    use crate::train::{render_rays, LossWeights, RaySamples, RayTargets};

    /// 64 rays along +z through a 2-class toy scene: left half hits a class-0 box, right half a
    /// class-1 box (z in [2, 3]), then a sky interval (z in [5, 7]); every 4th ray sees only
    /// the sky interval. Classes: [0, 1, sky].
    pub(crate) fn toy_scene() -> RayBatch {
        let (rays, n, c) = (64usize, 32usize, 3usize);
        let mut s = RaySamples {
            rays,
            samples: n,
            classes: c,
            ..Default::default()
        };
        let mut t = RayTargets::default();
        for i in 0..rays {
            let x = -0.9 + 1.8 * (i % 8) as f32 / 7.0;
            let y = -0.9 + 1.8 * (i / 8) as f32 / 7.0;
            let sky_only = i % 4 == 3;
            let class = if x < 0.0 { 0 } else { 1 };
            for k in 0..n {
                let (z, delta, label) = if sky_only {
                    (5.0 + 2.0 * (k as f32 + 0.5) / n as f32, 2.0 / n as f32, 2)
                } else if k < 16 {
                    (2.0 + (k as f32 + 0.5) / 16.0, 1.0 / 16.0, class)
                } else {
                    (5.0 + 2.0 * (k as f32 - 15.5) / 16.0, 2.0 / 16.0, 2)
                };
                s.positions.extend_from_slice(&[x, y, z]);
                s.deltas.push(delta);
                s.t_mid.push(z);
                let mut p = [0f32; 3];
                p[label] = 1.0;
                s.fixed_semantics.extend_from_slice(&p);
            }
            s.directions.extend_from_slice(&[0.0, 0.0, 1.0]);
            t.labels.push(if sky_only { 2 } else { class as i32 });
            t.ray_mask.push(1.0);
            t.depth.push(if sky_only { f32::NAN } else { 2.0 });
            t.depth_valid.push(!sky_only);
            t.rgb.extend_from_slice(match (sky_only, class) {
                (true, _) => &[0.5, 0.7, 1.0],
                (false, 0) => &[1.0, 0.0, 0.0],
                _ => &[0.0, 1.0, 0.0],
            });
        }
        let b = RayBatch {
            samples: s,
            targets: t,
        };
        b.validate().unwrap();
        b
    }

    pub(crate) fn toy_spec() -> FieldSpec {
        FieldSpec {
            config: toy_field(),
            num_classes: 3,
            aabb_min: [-1.0, -1.0, 0.0],
            aabb_max: [1.0, 1.0, 8.0],
            seed: 0,
        }
    }

    fn toy_field() -> FieldConfig {
        FieldConfig {
            grid: GridConfig {
                levels: 4,
                log2_table_size: 12,
                max_resolution: 64,
                ..Default::default()
            },
            ..Default::default()
        }
    }

    fn toy_config() -> TrainConfig {
        TrainConfig {
            field: toy_field(),
            lr: 1e-2,
            rays_per_batch: 64,
            iterations: 100,
            ..Default::default()
        }
    }

    fn mean(v: impl Iterator<Item = f32>) -> f32 {
        let v: Vec<f32> = v.collect();
        v.iter().sum::<f32>() / v.len() as f32
    }

    #[test]
    fn tiny_scene_overfits_every_loss_falls_and_labels_render_right() {
        let data = toy_scene();
        let config = toy_config();
        let trained = train(&config, toy_spec(), Backend::default(), &data, |_| {}).unwrap();
        let log = &trained.log;
        assert_eq!(log.len(), 100);
        let first = |term: LossTerm| mean(log[..5].iter().map(|r| r.losses.get(term).unwrap()));
        let last = |term: LossTerm| mean(log[95..].iter().map(|r| r.losses.get(term).unwrap()));
        for term in LossTerm::ALL {
            assert!(
                last(term) < 0.7 * first(term),
                "{term}: {} -> {}",
                first(term),
                last(term)
            );
        }
        let total0 = mean(log[..5].iter().map(|r| r.losses.total));
        let total1 = mean(log[95..].iter().map(|r| r.losses.total));
        assert!(total1 < 0.5 * total0, "total {total0} -> {total1}");

        let out = render_rays(&trained.field, &data.samples, 16).unwrap();
        let correct = out
            .semantics
            .chunks(3)
            .zip(&data.targets.labels)
            .filter(|(p, &l)| {
                let arg = (0..3).max_by(|&a, &b| p[a].total_cmp(&p[b])).unwrap();
                arg as i32 == l
            })
            .count();
        assert!(correct >= 60, "{correct}/64 rays rendered with their label");
        for p in out.semantics.chunks(3).chain(out.fixed_semantics.chunks(3)) {
            let sum: f32 = p.iter().sum();
            assert!(
                (sum - 1.0).abs() < 1e-4,
                "a rendered distribution sums to {sum}"
            );
        }
    }

    #[test]
    fn training_is_reproducible_from_the_seed() {
        let data = toy_scene();
        let config = TrainConfig {
            iterations: 3,
            rays_per_batch: 16,
            ..toy_config()
        };
        let a = train(&config, toy_spec(), Backend::default(), &data, |_| {}).unwrap();
        let b = train(&config, toy_spec(), Backend::default(), &data, |_| {}).unwrap();
        assert_eq!(a.field.weights(), b.field.weights());
        let la: Vec<_> = a.log.iter().map(|r| r.losses.clone()).collect();
        let lb: Vec<_> = b.log.iter().map(|r| r.losses.clone()).collect();
        assert_eq!(la, lb);
    }

    #[test]
    fn nan_weight_stops_training_naming_iteration_and_term() {
        let data = toy_scene();
        let mut trainer = Trainer::new(toy_config(), toy_spec(), Backend::default()).unwrap();
        trainer.step(&data).unwrap();
        // poison the semantic head: only the two terms that use it can go non-finite
        let mut rows: Vec<NamedWeight> = trainer.field().weights();
        let row = rows
            .iter_mut()
            .find(|r| r.name == "semantic.layers.1.bias")
            .unwrap();
        row.values[0] = f32::NAN;
        let poisoned = trainer.field().clone().load_weights(&rows).unwrap();
        let mut trainer = Trainer::from_field(toy_config(), poisoned);
        let before = trainer.field().weights();
        let err = trainer.step(&data).unwrap_err();
        match &err {
            TrainError::NonFiniteLoss {
                iteration: 0,
                term: LossTerm::Learned2d,
                ..
            } => {}
            other => panic!("unexpected error {other}"),
        }
        assert!(err.to_string().contains("iteration 0") && err.to_string().contains("learned_2d"));
        // weights untouched by the failed step
        let after = trainer.field().weights();
        assert_eq!(format!("{before:?}"), format!("{after:?}"));
    }

    #[test]
    fn nan_gradient_is_reported_with_term_and_parameter() {
        // A NaN gradient with finite losses is hard to provoke through the field, so the
        // detection (which names the parameter) is checked on a planted gradient.
        let field = toy_spec().init(&Backend::default().train_device());
        let mut grads = GradientsParams::new();
        let rows = field.weights();
        assert!(grad_norm(&field, &grads).unwrap() == 0.0 && !rows.is_empty());
        let id = field.semantic.layers[0].bias.id;
        grads.register::<1>(
            id,
            Tensor::from_floats([f32::NAN; 32].as_slice(), &Backend::default().device()),
        );
        assert_eq!(
            grad_norm(&field, &grads).unwrap_err(),
            "semantic.layers.0.bias"
        );
    }

    #[test]
    fn huge_density_and_tiny_deltas_train_without_error() {
        let mut data = toy_scene();
        for d in data.samples.deltas.iter_mut().step_by(2) {
            *d = 1e-9;
        }
        for (shift, labels) in [(1e10f32, true), (-1e4, false)] {
            let mut config = toy_config();
            config.field.density_shift = shift;
            if !labels {
                // all-zero density (softplus(-1e4) = 0): only the sky is rendered
                config.losses = LossWeights::default();
            }
            let mut trainer = Trainer::new(config, toy_spec(), Backend::default()).unwrap();
            for _ in 0..2 {
                let l = trainer
                    .step(&data)
                    .unwrap_or_else(|e| panic!("shift {shift}: {e}"));
                assert!(l.total.is_finite() && l.grad_norm.is_finite(), "{l:?}");
            }
        }
    }

    #[test]
    fn bad_batches_and_configs_are_errors_not_panics() {
        let mut data = toy_scene();
        data.targets.labels[3] = 7;
        let mut trainer = Trainer::new(toy_config(), toy_spec(), Backend::default()).unwrap();
        assert!(matches!(trainer.step(&data), Err(TrainError::Batch(m)) if m.contains("label 7")));
        let config = TrainConfig {
            losses: LossWeights {
                fixed_2d: 0.0,
                learned_2d: 0.0,
                point_3d: 0.0,
                rgb: 0.0,
                depth: 0.0,
            },
            ..toy_config()
        };
        assert!(matches!(
            Trainer::new(config, toy_spec(), Backend::default()),
            Err(TrainError::Config(_))
        ));
    }
}
