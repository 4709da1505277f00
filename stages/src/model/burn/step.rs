//! The burn engine's optimisation step: forward, losses, backward, global-norm clipping, Adam
//! (burn's optimiser).
//!
//! Non-finite values are caught at two points and reported as [`TrainError`]s naming the
//! iteration and the loss term: the loss values (read back every step anyway for the log), and
//! the global gradient norm (one extra scalar read-back). A non-finite gradient re-runs the
//! forward/backward per term, only on that failure path, to name the term responsible. Either
//! way the weights are left as they were before the failing step.

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::activation::softmax;
use burn::tensor::{Device, Tensor, TensorData};

use super::backend::Backend;
use super::field::{FieldHead, RadianceField};
use super::loss;
use super::volume::{render_depth, render_rgb, render_semantics, render_weights};
use crate::model::batch::RayBatch;
use crate::model::config::{FieldSpec, TrainConfig};
use crate::model::error::TrainError;
use crate::model::loss::{LossTerm, LossTerms};
use crate::model::params::NamedWeight;
use crate::model::train::Gradients;

/// Device tensors of one batch.
struct BatchTensors {
    deltas: Tensor<2>,
    t_mid: Tensor<2>,
    fixed: Tensor<3>,
    unique: Tensor<2>,
    label_one_hot: Tensor<2>,
    labelled: Tensor<1>,
    unlabelled: Tensor<1>,
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
            unlabelled: t1(labelled.iter().map(|l| 1.0 - l).collect()),
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
    if terms.contains(&LossTerm::Rgb) || terms.contains(&LossTerm::SkyPrior) {
        heads.push(FieldHead::Rgb);
    }
    if terms.contains(&LossTerm::Learned2d) || terms.contains(&LossTerm::Point3d) {
        heads.push(FieldHead::Semantics);
    }
    let directions = heads
        .contains(&FieldHead::Rgb)
        .then_some(s.directions.as_slice());
    let input = field.prepare(&s.positions, directions, n, &s.in_sky());
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
                    config.losses.label_eps,
                ),
                LossTerm::Learned2d => loss::label_nll(
                    render_semantics(&w, softmax(logits.clone().expect("semantics head"), 2), sky),
                    bt.label_one_hot.clone(),
                    bt.learned_mask.clone(),
                    config.losses.label_eps,
                ),
                LossTerm::Point3d => loss::point_ce(
                    logits.clone().expect("semantics head"),
                    bt.fixed.clone(),
                    bt.unique.clone(),
                    density.clone(),
                    config.losses.sigma_threshold,
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
                LossTerm::SkyPrior => loss::sky_prior(
                    render_semantics(&w, bt.fixed.clone(), sky)
                        .narrow(1, sky, 1)
                        .reshape([r]),
                    out.rgb.clone().expect("rgb head").reshape([r, n, 3]),
                    bt.fixed.clone().narrow(2, sky, 1),
                    bt.rgb.clone(),
                    bt.unlabelled.clone(),
                    config.losses.sky_prior_colour,
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
            let n = g.shape().num_elements();
            self.squares.push(exact_sum(g.square().reshape([n])));
        }
    }
}

/// Elements per partial sum of [`exact_sum`].
const SUM_CHUNK: usize = 1 << 16;

/// The sum of `t`, as partial sums of at most [`SUM_CHUNK`] elements: on wgpu (burn 0.22,
/// cubecl 0.11, Mesa llvmpipe on an AVX-512 host) `sum` over a million elements returned a
/// quarter of the true value (a hash grid's table has 2^20), so the global gradient norm, and
/// with it the clipping of every step, was wrong. Tested in
/// `sums_over_a_whole_table_count_every_element`.
fn exact_sum(t: Tensor<1>) -> Tensor<1> {
    let n = t.dims()[0];
    if n <= SUM_CHUNK {
        return t.sum();
    }
    let parts: Vec<Tensor<1>> = (0..n)
        .step_by(SUM_CHUNK)
        .map(|s| t.clone().narrow(0, s, SUM_CHUNK.min(n - s)).sum())
        .collect();
    Tensor::cat(parts, 0).sum()
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
struct CollectGrads<'a> {
    grads: &'a GradientsParams,
    path: Vec<String>,
    out: Vec<NamedWeight>,
}

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
        self.out.push(NamedWeight {
            name: self.path.join("."),
            shape,
            values,
        });
    }
}

/// The burn reference: unweighted loss values and the gradient of their weighted sum, per
/// named parameter (`field` must live on an autodiff device).
pub fn reference_gradients(
    field: &RadianceField,
    batch: &RayBatch,
    config: &TrainConfig,
) -> (Vec<(LossTerm, f32)>, Vec<NamedWeight>) {
    let terms = config.losses.enabled();
    let values = losses(field, batch, config, &terms);
    let read: Vec<(LossTerm, f32)> = values
        .iter()
        .map(|(t, v)| {
            (
                *t,
                v.clone()
                    .detach()
                    .into_data()
                    .try_to_vec::<f32>()
                    .expect("f32")[0],
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
        config.validate()?;
        let spec = FieldSpec {
            config: config.field.clone(),
            ..spec
        };
        spec.validate()?;
        let field = RadianceField::init(spec, &backend.train_device());
        Ok(Self::from_field(config, field))
    }

    /// Continues training `field` (which must live on an autodiff device) with fresh Adam state.
    pub fn from_field(config: TrainConfig, field: RadianceField) -> Self {
        let optimizer = AdamConfig::new()
            .with_beta_1(config.optimiser.adam_beta1)
            .with_beta_2(config.optimiser.adam_beta2)
            .with_epsilon(config.optimiser.adam_epsilon)
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
        let clip = self.config.optimiser.grad_clip_norm;
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

impl crate::model::train::Trainer for Trainer {
    fn step(&mut self, batch: &RayBatch) -> Result<LossTerms, TrainError> {
        Trainer::step(self, batch)
    }

    fn gradients(&mut self, batch: &RayBatch) -> Result<Gradients, TrainError> {
        batch.validate().map_err(TrainError::Batch)?;
        let (terms, grads) = reference_gradients(self.field(), batch, &self.config);
        Ok(Gradients { terms, grads })
    }

    fn iteration(&self) -> usize {
        self.iteration
    }

    fn weights(&self) -> Vec<NamedWeight> {
        self.field().weights()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::testing::toy_spec;

    /// Sums over tensors as large as a hash grid's table (8 levels x 2^16 rows x 2 features)
    /// are right on every backend: the global norm decides the clipping of every step.
    #[test]
    fn sums_over_a_whole_table_count_every_element() {
        for b in Backend::available() {
            if b.check_device().is_err() && !std::env::var("CI").is_ok_and(|v| v == "true") {
                continue;
            }
            let d = b.train_device();
            for n in [1usize, 1 << 16, (1 << 16) + 1, 1 << 20, 3_000_001] {
                let v: Vec<f32> = (0..n).map(|i| (i % 4) as f32).collect();
                let want: f64 = v.iter().map(|&x| x as f64).sum();
                let t = Tensor::<1>::from_data(TensorData::new(v, [n]), &d);
                let got = exact_sum(t).into_data().try_to_vec::<f32>().unwrap()[0] as f64;
                assert!(
                    (got - want).abs() <= 1e-6 * want,
                    "{}: n {n}: {got} vs {want}",
                    b.name()
                );
            }
        }
    }

    #[test]
    fn nan_gradient_is_reported_with_term_and_parameter() {
        // A NaN gradient with finite losses is hard to provoke through the field, so the
        // detection (which names the parameter) is checked on a planted gradient.
        let field = RadianceField::init(toy_spec(), &Backend::REFERENCE.train_device());
        let mut grads = GradientsParams::new();
        assert!(grad_norm(&field, &grads).unwrap() == 0.0);
        let id = field.semantic.layers[0].bias.id;
        grads.register::<1>(
            id,
            Tensor::from_floats([f32::NAN; 32].as_slice(), &Backend::REFERENCE.device()),
        );
        assert_eq!(
            grad_norm(&field, &grads).unwrap_err(),
            "semantic.layers.0.bias"
        );
    }
}
