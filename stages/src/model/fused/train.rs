//! The fused engine's trainer: the step split over a fixed number of ray partitions, the
//! gradients reduced in partition order, global-norm clipping and Adam.

use std::time::Instant;

use rayon::prelude::*;

use super::field::{FusedField, PARTITIONS};
use super::simd::dispatch;
use super::step::Scale;
use super::work::{scatter_grid, Sums, Work};
use crate::model::batch::RayBatch;
use crate::model::config::TrainConfig;
use crate::model::error::TrainError;
use crate::model::field::Heads;
use crate::model::loss::{LossTerm, LossTerms};
use crate::model::params::NamedWeight;
use crate::model::train::Gradients;

/// Name of the per-image log colour gains in [`FusedTrainer::gradients`].
pub const EXPOSURE: &str = "exposure.log_gain";

/// Trains a [`FusedField`] with the losses, clipping and Adam of the burn engine's trainer.
pub struct FusedTrainer {
    field: FusedField,
    config: TrainConfig,
    terms: Vec<LossTerm>,
    iteration: usize,
    moment1: Vec<Vec<f32>>,
    moment2: Vec<Vec<f32>>,
    /// Per training image (`losses.exposure`): the log colour gain, its gradient of the last
    /// step and Adam's moments; grown to the largest image index a batch names.
    exposure: Vec<[f32; 3]>,
    exposure_grad: Vec<[f32; 3]>,
    exposure_m1: Vec<[f32; 3]>,
    exposure_m2: Vec<[f32; 3]>,
    work: Vec<Work>,
    /// Seconds spent in the last step's phases (forward, backward, reduce + Adam).
    pub timings: [f64; 3],
}

impl FusedTrainer {
    /// Starts from the initial parameters of `field` (same seed => same start as burn).
    pub fn new(config: TrainConfig, field: FusedField) -> Result<Self, TrainError> {
        config.validate()?;
        let zeros: Vec<Vec<f32>> = field
            .weights
            .iter()
            .map(|w| vec![0.0; w.values.len()])
            .collect();
        let terms = config.losses.enabled();
        Ok(Self {
            field,
            config,
            terms,
            iteration: 0,
            moment1: zeros.clone(),
            moment2: zeros,
            exposure: Vec::new(),
            exposure_grad: Vec::new(),
            exposure_m1: Vec::new(),
            exposure_m2: Vec::new(),
            work: (0..PARTITIONS).map(|_| Work::default()).collect(),
            timings: [0.0; 3],
        })
    }

    pub fn field(&self) -> &FusedField {
        &self.field
    }

    pub fn into_field(self) -> FusedField {
        self.field
    }

    pub fn iteration(&self) -> usize {
        self.iteration
    }

    /// Each training image's log colour gain (`losses.exposure`), by image index.
    pub fn exposure(&self) -> &[[f32; 3]] {
        &self.exposure
    }

    /// Sets the log colour gains (tests), resetting their optimiser state.
    pub fn set_exposure(&mut self, log_gains: Vec<[f32; 3]>) {
        let n = log_gains.len();
        self.exposure = log_gains;
        self.exposure_m1 = vec![[0.0; 3]; n];
        self.exposure_m2 = vec![[0.0; 3]; n];
    }

    /// Loss values and summed gradients of `batch` (all enabled terms, or only `only`),
    /// left in `self.work[0].grads`.
    fn compute(
        &mut self,
        batch: &RayBatch,
        only: Option<LossTerm>,
    ) -> Result<Vec<(LossTerm, f32)>, TrainError> {
        batch.validate().map_err(TrainError::Batch)?;
        let s = &batch.samples;
        let t = &batch.targets;
        if s.classes != self.field.spec.num_classes {
            return Err(TrainError::Batch(format!(
                "batch has {} classes, the field {}",
                s.classes, self.field.spec.num_classes
            )));
        }
        let terms: Vec<LossTerm> = match only {
            Some(t) => vec![t],
            None => self.terms.clone(),
        };
        let mut weights = [0f32; LossTerm::ALL.len()];
        for (k, term) in LossTerm::ALL.into_iter().enumerate() {
            if terms.contains(&term) {
                weights[k] = self.config.losses.get(term);
            }
        }
        let heads = Heads {
            rgb: weights[3] != 0.0 || weights[5] != 0.0,
            semantics: weights[1] != 0.0 || weights[2] != 0.0,
        };
        let rays = s.rays;
        let parts = PARTITIONS.min(rays.max(1));
        let bounds: Vec<(usize, usize)> = (0..parts)
            .map(|p| (p * rays / parts, (p + 1) * rays / parts))
            .collect();
        let field = &self.field;
        let params = field.params();
        let config = &self.config;
        let sky = s.classes - 1;
        let mut gains: Vec<[f32; 3]> = Vec::new();
        if config.losses.exposure && !t.image.is_empty() {
            let n = t.image.iter().map(|&i| i as usize + 1).max().unwrap_or(0);
            if n > self.exposure.len() {
                self.exposure.resize(n, [0.0; 3]);
                self.exposure_m1.resize(n, [0.0; 3]);
                self.exposure_m2.resize(n, [0.0; 3]);
            }
            gains = self.exposure.iter().map(|a| a.map(f32::exp)).collect();
        }
        let start = Instant::now();
        self.work[..parts]
            .par_iter_mut()
            .zip(&bounds)
            .for_each(|(w, &(r0, r1))| {
                dispatch(
                    #[inline(always)]
                    || {
                        w.forward_step(
                            field, &params, batch, r0, r1, heads, config, sky, &weights, &gains,
                        )
                    },
                );
            });
        let mut sums = Sums::default();
        for w in &self.work[..parts] {
            for k in 0..LossTerm::ALL.len() {
                sums.terms[k] += w.sums.terms[k];
            }
            sums.points_3d += w.sums.points_3d;
        }
        let labelled = t.labels.iter().filter(|&&l| l >= 0).count();
        let learned = t
            .labels
            .iter()
            .zip(&t.ray_mask)
            .filter(|(&l, &m)| l >= 0 && (!config.ray_mask || m != 0.0))
            .count();
        let valid = t.depth_valid.iter().filter(|&&v| v).count();
        let scale = Scale {
            weights,
            fixed: labelled.max(1) as f32,
            learned: learned.max(1) as f32,
            point: (sums.points_3d as f32).max(1.0),
            rgb: (3 * rays).max(1) as f32,
            depth: valid.max(1) as f32,
            rays: rays.max(1) as f32,
        };
        let norms = [
            scale.fixed,
            scale.learned,
            scale.point,
            scale.rgb,
            scale.depth,
            scale.rays,
        ];
        let values: Vec<(LossTerm, f32)> = terms
            .iter()
            .map(|&term| {
                let k = LossTerm::ALL.iter().position(|&x| x == term).expect("term");
                (term, (sums.terms[k] / norms[k] as f64) as f32)
            })
            .collect();
        for &(term, value) in &values {
            if !value.is_finite() {
                return Err(TrainError::NonFiniteLoss {
                    iteration: self.iteration,
                    term,
                    value,
                });
            }
        }
        let forward = start.elapsed().as_secs_f64();
        self.work[..parts]
            .par_iter_mut()
            .zip(&bounds)
            .for_each(|(w, &(r0, r1))| {
                dispatch(
                    #[inline(always)]
                    || w.backward_step(field, &params, batch, r0, r1, heads, config, sky, &scale),
                );
            });
        let mut table = std::mem::take(&mut self.work[0].grads[field.grid]);
        table.resize(field.weights[field.grid].values.len(), 0.0);
        scatter_grid(field, &self.work[..parts], &bounds, s.samples, &mut table);
        self.work[0].grads[field.grid] = table;
        self.timings[0] = forward;
        self.timings[1] = start.elapsed().as_secs_f64() - forward;
        self.exposure_grad.clear();
        self.exposure_grad.resize(gains.len(), [0.0; 3]);
        for w in &self.work[..parts] {
            for (sum, g) in self.exposure_grad.iter_mut().zip(&w.dexposure) {
                for ch in 0..3 {
                    sum[ch] += g[ch];
                }
            }
        }
        sum_into_first(&mut self.work[..parts], field.grid);
        Ok(values)
    }

    /// Loss values and gradients of `batch` without updating anything.
    pub fn gradients(&mut self, batch: &RayBatch) -> Result<Gradients, TrainError> {
        let terms = self.compute(batch, None)?;
        let mut grads: Vec<NamedWeight> = self
            .field
            .weights
            .iter()
            .zip(&self.work[0].grads)
            .map(|(w, g)| NamedWeight {
                name: w.name.clone(),
                shape: w.shape.clone(),
                values: g.clone(),
            })
            .collect();
        if !self.exposure_grad.is_empty() {
            grads.push(NamedWeight {
                name: EXPOSURE.to_string(),
                shape: vec![self.exposure_grad.len(), 3],
                values: self.exposure_grad.concat(),
            });
        }
        Ok(Gradients { terms, grads })
    }

    /// Global gradient norm of `work[0].grads`, or the name of a parameter with a non-finite
    /// gradient.
    fn grad_norm(&self) -> Result<f32, String> {
        let mut total = 0f64;
        for (w, g) in self.field.weights.iter().zip(&self.work[0].grads) {
            let s: f64 = g.par_iter().map(|&v| (v as f64) * (v as f64)).sum();
            if !s.is_finite() {
                return Err(w.name.clone());
            }
            total += s;
        }
        let s: f64 = self
            .exposure_grad
            .iter()
            .flatten()
            .map(|&v| (v as f64) * (v as f64))
            .sum();
        if !s.is_finite() {
            return Err(EXPOSURE.to_string());
        }
        total += s;
        Ok(total.sqrt() as f32)
    }

    /// One step: forward, losses, backward, global-norm clipping, Adam. On error the weights are
    /// unchanged.
    pub fn step(&mut self, batch: &RayBatch) -> Result<LossTerms, TrainError> {
        let iteration = self.iteration;
        let lr = self.config.lr_at(iteration);
        let values = self.compute(batch, None)?;
        let adam_start = Instant::now();
        let norm = match self.grad_norm() {
            Ok(n) if n.is_finite() => n,
            Ok(_) => return Err(self.blame(batch, "(norm overflow)")),
            Err(p) => return Err(self.blame(batch, &p)),
        };
        let clip = self.config.optimiser.grad_clip_norm;
        let factor = if clip > 0.0 && norm > clip {
            clip / (norm + 1e-6)
        } else {
            1.0
        };
        let (b1, b2, eps) = (
            self.config.optimiser.adam_beta1,
            self.config.optimiser.adam_beta2,
            self.config.optimiser.adam_epsilon,
        );
        let time = (iteration + 1) as i32;
        let (c1, c2) = (1.0 - b1.powi(time), 1.0 - b2.powi(time));
        let lr = lr as f32;
        for (k, w) in self.field.weights.iter_mut().enumerate() {
            let g = &self.work[0].grads[k];
            w.values
                .par_chunks_mut(1 << 14)
                .zip(self.moment1[k].par_chunks_mut(1 << 14))
                .zip(self.moment2[k].par_chunks_mut(1 << 14))
                .zip(g.par_chunks(1 << 14))
                .for_each(|(((p, m), v), g)| {
                    dispatch(
                        #[inline(always)]
                        || {
                            for i in 0..p.len() {
                                let gi = g[i] * factor;
                                m[i] = b1 * m[i] + (1.0 - b1) * gi;
                                v[i] = b2 * v[i] + (1.0 - b2) * gi * gi;
                                let update = (m[i] / c1) / ((v[i] / c2).sqrt() + eps);
                                p[i] -= lr * update;
                            }
                        },
                    )
                });
        }
        for (k, g) in self.exposure_grad.iter().enumerate() {
            let (p, m, v) = (
                &mut self.exposure[k],
                &mut self.exposure_m1[k],
                &mut self.exposure_m2[k],
            );
            for ch in 0..3 {
                let gi = g[ch] * factor;
                m[ch] = b1 * m[ch] + (1.0 - b1) * gi;
                v[ch] = b2 * v[ch] + (1.0 - b2) * gi * gi;
                p[ch] -= lr * (m[ch] / c1) / ((v[ch] / c2).sqrt() + eps);
            }
        }
        self.timings[2] = adam_start.elapsed().as_secs_f64();
        self.iteration += 1;
        let total = values
            .iter()
            .map(|&(t, v)| self.config.losses.get(t) * v)
            .sum();
        Ok(LossTerms {
            iteration,
            lr: lr as f64,
            terms: values,
            total,
            grad_norm: norm,
        })
    }

    /// Failure path: the first single term whose gradient is not finite (else `total`).
    fn blame(&mut self, batch: &RayBatch, param: &str) -> TrainError {
        let iteration = self.iteration;
        for term in self.terms.clone() {
            if self.compute(batch, Some(term)).is_ok() {
                if let Err(p) = self.grad_norm() {
                    return TrainError::NonFiniteGradient {
                        iteration,
                        term: term.name().to_string(),
                        param: p,
                    };
                }
            }
        }
        TrainError::NonFiniteGradient {
            iteration,
            term: "total".to_string(),
            param: param.to_string(),
        }
    }
}

impl crate::model::train::Trainer for FusedTrainer {
    fn step(&mut self, batch: &RayBatch) -> Result<LossTerms, TrainError> {
        FusedTrainer::step(self, batch)
    }

    fn gradients(&mut self, batch: &RayBatch) -> Result<Gradients, TrainError> {
        FusedTrainer::gradients(self, batch)
    }

    fn iteration(&self) -> usize {
        self.iteration
    }

    fn weights(&self) -> Vec<NamedWeight> {
        self.field.weights.clone()
    }
}

/// Sums the partitions' MLP gradients into the first partition's, in partition order (the grid's,
/// slot `grid`, is summed by `scatter_grid`).
fn sum_into_first(work: &mut [Work], grid: usize) {
    let (first, rest) = work.split_at_mut(1);
    for (k, g) in first[0].grads.iter_mut().enumerate() {
        if k == grid {
            continue;
        }
        g.par_chunks_mut(1 << 14)
            .enumerate()
            .for_each(|(ci, chunk)| {
                let (o, len) = (ci << 14, chunk.len());
                for w in rest.iter() {
                    chunk
                        .iter_mut()
                        .zip(&w.grads[k][o..o + len])
                        .for_each(|(a, b)| *a += b);
                }
            });
    }
}
