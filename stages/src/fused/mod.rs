//! The fused CPU path of the grid field: forward, volume rendering, the five losses, their
//! backward pass and Adam in plain Rust over flat buffers, with `sgemm` for the dense layers and
//! rayon across ray partitions.
//!
//! Why: burn's CPU backends keep about one core busy and spend most of a step on small-tensor
//! overhead; this path computes the same function (same parameters, names, initialisation and
//! loss definitions as [`crate::field::RadianceField`] + [`crate::train`]) several times faster.
//! The burn model stays the one definition for every other backend, and the tests hold this
//! path's losses and gradients to burn's autodiff.
//!
//! Determinism: rays are split into a fixed number of partitions ([`PARTITIONS`], independent
//! of the thread count); each partition accumulates its own gradients and they are summed in
//! partition order, so a seed gives the same bytes on any machine with the same float
//! semantics.

// The kernels index several parallel per-sample arrays with one index; iterator chains over
// four zipped slices read worse than the formulas they implement.
#![allow(clippy::needless_range_loop)]

pub mod mlp;

use std::time::Instant;

use rayon::prelude::*;

use crate::compose::softmax_into;
use crate::field::encoding::{level_info, lookup_level, positional_encoding};
use crate::field::radiance::unit_direction;
use crate::field::{EncodingKind, FieldSpec, NamedWeight, RadianceField};
use crate::train::batch::is_one_hot;
use crate::train::{LossTerm, LossTerms, RayBatch, TrainConfig, TrainError, PROB_EPS};
use mlp::{add_bias, add_column_sums, gemm, grow, relu_in_place, Layer, View};

/// Ray partitions of a step: fixed, so results do not depend on the number of threads.
pub const PARTITIONS: usize = 8;

/// The grid field's parameters as flat rows, with the layout of the burn module.
#[derive(Debug, Clone)]
pub struct FusedField {
    pub spec: FieldSpec,
    /// Parameters in the burn module's order and naming (`grid.table`, `trunk.layers.0.weight`).
    pub weights: Vec<NamedWeight>,
    grid: usize,
    trunk: Vec<Layer>,
    colour: Vec<Layer>,
    semantic: Vec<Layer>,
    levels: Vec<(u32, bool)>,
}

/// Which heads a pass computes (density always).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Heads {
    pub rgb: bool,
    pub semantics: bool,
}

impl FusedField {
    /// The fused view of a burn field's parameters (grid encoding only).
    pub fn from_field(field: &RadianceField) -> Result<Self, String> {
        Self::from_weights(field.spec.clone(), field.weights())
    }

    /// Builds the layout from named rows; errors name a missing or misshapen parameter.
    pub fn from_weights(spec: FieldSpec, weights: Vec<NamedWeight>) -> Result<Self, String> {
        if spec.config.encoding != EncodingKind::Grid {
            return Err(
                "the fused CPU path supports `field.encoding: grid` only; use backend flex for pe"
                    .into(),
            );
        }
        let find = |name: &str| weights.iter().position(|w| w.name == name);
        let grid = find("grid.table").ok_or("weights have no `grid.table`")?;
        let g = &spec.config.grid;
        if weights[grid].shape != [g.levels * g.table_size(), g.features_per_level] {
            return Err(format!(
                "`grid.table` has shape {:?}, the spec needs [{}, {}]",
                weights[grid].shape,
                g.levels * g.table_size(),
                g.features_per_level
            ));
        }
        let mlp = |prefix: &str| -> Result<Vec<Layer>, String> {
            let mut layers = Vec::new();
            while let Some(w) = find(&format!("{prefix}.layers.{}.weight", layers.len())) {
                let b = find(&format!("{prefix}.layers.{}.bias", layers.len()))
                    .ok_or_else(|| format!("`{prefix}` layer {} has no bias", layers.len()))?;
                let shape = &weights[w].shape;
                if shape.len() != 2 || weights[b].shape != [shape[1]] {
                    return Err(format!("`{prefix}` layer {} is misshapen", layers.len()));
                }
                layers.push(Layer {
                    weight: w,
                    bias: b,
                    inputs: shape[0],
                    outputs: shape[1],
                });
            }
            if layers.is_empty() {
                return Err(format!("weights have no `{prefix}` layers"));
            }
            Ok(layers)
        };
        let (trunk, colour, semantic) = (mlp("trunk")?, mlp("colour")?, mlp("semantic")?);
        let c = &spec.config;
        let chained = |l: &[Layer]| l.windows(2).all(|p| p[0].outputs == p[1].inputs);
        if trunk[0].inputs != c.position_dim()
            || trunk.last().map(|l| l.outputs) != Some(1 + c.geo_features)
            || colour[0].inputs != c.geo_features + c.direction_dim()
            || colour.last().map(|l| l.outputs) != Some(3)
            || semantic[0].inputs != c.geo_features
            || semantic.last().map(|l| l.outputs) != Some(spec.num_classes)
            || !(chained(&trunk) && chained(&colour) && chained(&semantic))
        {
            return Err("the weights do not match the field spec".into());
        }
        let levels = level_info(g);
        Ok(Self {
            spec,
            weights,
            grid,
            trunk,
            colour,
            semantic,
            levels,
        })
    }

    /// The burn field with these parameters on `device`.
    pub fn to_field(&self, device: &burn::tensor::Device) -> Result<RadianceField, String> {
        self.spec.init(device).load_weights(&self.weights)
    }

    fn params(&self) -> Vec<&[f32]> {
        self.weights.iter().map(|w| w.values.as_slice()).collect()
    }

    /// Field outputs for `rays` rays of `samples` points each (inference, parallel over rays):
    /// density `[R*S]`, rgb `[R*S*3]` (empty unless `heads.rgb`), logits `[R*S*C]` (empty unless
    /// `heads.semantics`).
    pub fn evaluate(
        &self,
        positions: &[f32],
        directions: &[f32],
        samples: usize,
        heads: Heads,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let rays = directions.len() / 3;
        let n = rays * samples;
        assert_eq!(
            positions.len(),
            n * 3,
            "positions must be [rays, samples, 3]"
        );
        let c = self.spec.num_classes;
        let chunk = 256;
        let params = self.params();
        let last = self.semantic.len() - 1;
        let parts: Vec<(Vec<f32>, Vec<f32>, Vec<f32>)> = (0..rays.div_ceil(chunk))
            .into_par_iter()
            .map(|ci| {
                let (r0, r1) = (ci * chunk, ((ci + 1) * chunk).min(rays));
                let m = (r1 - r0) * samples;
                let mut w = Work::default();
                w.forward_field(
                    self,
                    &params,
                    &positions[r0 * samples * 3..r1 * samples * 3],
                    &directions[r0 * 3..r1 * 3],
                    samples,
                    heads,
                );
                (
                    w.sigma[..m].to_vec(),
                    if heads.rgb {
                        w.rgb[..m * 3].to_vec()
                    } else {
                        Vec::new()
                    },
                    if heads.semantics {
                        w.sem[last][..m * c].to_vec()
                    } else {
                        Vec::new()
                    },
                )
            })
            .collect();
        let mut sigma = Vec::with_capacity(n);
        let mut rgb = Vec::new();
        let mut logits = Vec::new();
        for (s, r, l) in parts {
            sigma.extend(s);
            rgb.extend(r);
            logits.extend(l);
        }
        (sigma, rgb, logits)
    }
}

/// Per-ray results of the forward pass that the backward pass needs.
#[derive(Debug, Clone, Copy, Default)]
struct RayState {
    shat_label: f32,
    s_label: f32,
    colour: [f32; 3],
    depth: f32,
    /// 1 - opacity > 0: the sky remainder is live (its gradient flows).
    remainder_live: bool,
}

/// Unnormalised loss sums of a partition, and the L_3D point count.
#[derive(Debug, Clone, Copy, Default)]
struct Sums {
    terms: [f64; 5],
    points_3d: f64,
}

/// Buffers of one partition, reused across steps (they only grow).
#[derive(Default)]
struct Work {
    unit: Vec<f32>,
    /// Corner rows and weights, level-major: `[levels, points, 8]`.
    idx: Vec<i32>,
    wts: Vec<f32>,
    enc: Vec<f32>,
    trunk: Vec<Vec<f32>>,
    sem: Vec<Vec<f32>>,
    col: Vec<Vec<f32>>,
    /// Per ray: the direction encoding `[rays, dd]` and its term in the colour head's first
    /// layer (with the bias), `[rays, hidden]`.
    dir_pe: Vec<f32>,
    dir_term: Vec<f32>,
    dcol: Vec<f32>,
    dray: Vec<f32>,
    sigma: Vec<f32>,
    dsigma: Vec<f32>,
    probs: Vec<f32>,
    rgb: Vec<f32>,
    weight: Vec<f32>,
    trans: Vec<f32>,
    survive: Vec<f32>,
    point_mask: Vec<f32>,
    rays: Vec<RayState>,
    dy: Vec<f32>,
    scratch: Vec<f32>,
    dgeo: Vec<f32>,
    dgeo_col: Vec<f32>,
    dtrunk: Vec<f32>,
    denc: Vec<f32>,
    dz: Vec<f32>,
    drgb: Vec<f32>,
    grads: Vec<Vec<f32>>,
    sums: Sums,
}

fn softplus(x: f32) -> f32 {
    if x > 20.0 {
        x
    } else {
        x.exp().ln_1p()
    }
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

impl Work {
    /// Encoding, trunk, density and the requested heads for `positions` (`[n, 3]`) whose rays
    /// (`directions`, `[n / samples, 3]`) have `samples` points each.
    fn forward_field(
        &mut self,
        f: &FusedField,
        params: &[&[f32]],
        positions: &[f32],
        directions: &[f32],
        samples: usize,
        heads: Heads,
    ) {
        let spec = &f.spec;
        let c = &spec.config;
        let n = positions.len() / 3;
        let (levels, feats) = (c.grid.levels, c.grid.features_per_level);
        let e = levels * feats;
        let corners = levels * 8;
        self.idx.resize(n * corners, 0);
        grow(&mut self.wts, n * corners);
        grow(&mut self.enc, n * e);
        grow(&mut self.unit, n * 3);
        for (u, p) in self.unit.chunks_exact_mut(3).zip(positions.chunks_exact(3)) {
            for a in 0..3 {
                u[a] = spec.unit_coordinate(a, p[a]);
            }
        }
        let table = params[f.grid];
        // Level by level: one level's table (512 KiB by default) stays in cache while every
        // point reads it.
        for (l, &level) in f.levels.iter().enumerate() {
            let idx = &mut self.idx[l * n * 8..(l + 1) * n * 8];
            let w = &mut self.wts[l * n * 8..(l + 1) * n * 8];
            // Corners first, then the reads: a tight gather loop keeps many loads in flight.
            for ((idx, w), u) in idx
                .chunks_exact_mut(8)
                .zip(w.chunks_exact_mut(8))
                .zip(self.unit.chunks_exact(3))
            {
                lookup_level(&c.grid, l, level, u, idx, w);
            }
            let enc = self.enc[..n * e].chunks_exact_mut(e);
            // The default 2 features per level, unrolled: the generic loop made the whole step
            // ~20 % slower (train_step 4096x32: 81.9 vs 101.6 ms).
            if feats == 2 {
                for ((out, idx), w) in enc.zip(idx.chunks_exact(8)).zip(w.chunks_exact(8)) {
                    let mut acc = [0f32; 2];
                    for k in 0..8 {
                        let row = idx[k] as usize * 2;
                        acc[0] += w[k] * table[row];
                        acc[1] += w[k] * table[row + 1];
                    }
                    out[l * 2..l * 2 + 2].copy_from_slice(&acc);
                }
            } else {
                for ((out, idx), w) in enc.zip(idx.chunks_exact(8)).zip(w.chunks_exact(8)) {
                    let out = &mut out[l * feats..(l + 1) * feats];
                    out.iter_mut().for_each(|v| *v = 0.0);
                    for k in 0..8 {
                        let row = idx[k] as usize * feats;
                        for ft in 0..feats {
                            out[ft] += w[k] * table[row + ft];
                        }
                    }
                }
            }
        }
        self.trunk.resize_with(f.trunk.len(), Vec::new);
        mlp::forward(
            &f.trunk,
            params,
            n,
            View::rows(&self.enc, e),
            &mut self.trunk,
        );
        let width = 1 + c.geo_features;
        let trunk_out = &self.trunk[f.trunk.len() - 1];
        grow(&mut self.sigma, n);
        grow(&mut self.dsigma, n);
        for i in 0..n {
            let x = trunk_out[i * width] + c.density_shift;
            self.sigma[i] = softplus(x);
            self.dsigma[i] = sigmoid(x);
        }
        let geo = View {
            data: &trunk_out[1..],
            rs: width,
            cs: 1,
        };
        if heads.semantics {
            self.sem.resize_with(f.semantic.len(), Vec::new);
            mlp::forward(&f.semantic, params, n, geo, &mut self.sem);
        }
        if heads.rgb {
            // The first colour layer splits into a per-sample geometry part and a per-ray
            // direction part: x W = geo W_geo + dir W_dir, and dir is constant along a ray.
            let (g, h) = (c.geo_features, f.colour[0].outputs);
            let rays = n / samples;
            let units: Vec<f32> = directions
                .chunks_exact(3)
                .flat_map(unit_direction)
                .collect();
            self.dir_pe = positional_encoding(&units, 3, c.pe_direction_frequencies);
            let dd = self.dir_pe.len() / rays.max(1);
            let w0 = params[f.colour[0].weight];
            grow(&mut self.dir_term, rays * h);
            gemm(
                rays,
                dd,
                h,
                View::rows(&self.dir_pe, dd),
                View::rows(&w0[g * h..], h),
                0.0,
                &mut self.dir_term,
                h,
            );
            add_bias(&mut self.dir_term[..rays * h], params[f.colour[0].bias]);
            self.col.resize_with(f.colour.len(), Vec::new);
            let (first, rest) = self.col.split_at_mut(1);
            let h0 = &mut first[0];
            grow(h0, n * h);
            gemm(n, g, h, geo, View::rows(&w0[..g * h], h), 0.0, h0, h);
            for (i, row) in h0[..n * h].chunks_exact_mut(h).enumerate() {
                let d = &self.dir_term[(i / samples) * h..(i / samples + 1) * h];
                row.iter_mut().zip(d).for_each(|(v, t)| *v += t);
            }
            if !rest.is_empty() {
                relu_in_place(&mut h0[..n * h]);
                mlp::forward(&f.colour[1..], params, n, View::rows(h0, h), rest);
            }
            grow(&mut self.rgb, n * 3);
            let out = &self.col[f.colour.len() - 1];
            for i in 0..n * 3 {
                self.rgb[i] = sigmoid(out[i]);
            }
        }
    }
}

/// The grid table's gradient from every partition's encoding gradient (`denc`), one level per
/// task: a level's rows are written by one task only, in partition and point order, so the sum
/// is deterministic, and each task's slice of the table (512 KiB by default) stays in cache.
fn scatter_grid(
    f: &FusedField,
    work: &[Work],
    bounds: &[(usize, usize)],
    samples: usize,
    table: &mut [f32],
) {
    let grid = &f.spec.config.grid;
    let feats = grid.features_per_level;
    let e = grid.levels * feats;
    let rows = grid.table_size();
    table
        .par_chunks_mut(rows * feats)
        .enumerate()
        .for_each(|(l, level)| {
            level.iter_mut().for_each(|v| *v = 0.0);
            let base = l * rows;
            for (w, &(r0, r1)) in work.iter().zip(bounds) {
                let n = (r1 - r0) * samples;
                let idx = &w.idx[l * n * 8..(l + 1) * n * 8];
                let wts = &w.wts[l * n * 8..(l + 1) * n * 8];
                let denc = w.denc[..n * e].chunks_exact(e);
                if feats == 2 {
                    for ((d, idx), wts) in denc.zip(idx.chunks_exact(8)).zip(wts.chunks_exact(8)) {
                        let d = [d[l * 2], d[l * 2 + 1]];
                        for k in 0..8 {
                            let row = (idx[k] as usize - base) * 2;
                            level[row] += wts[k] * d[0];
                            level[row + 1] += wts[k] * d[1];
                        }
                    }
                } else {
                    for ((d, idx), wts) in denc.zip(idx.chunks_exact(8)).zip(wts.chunks_exact(8)) {
                        let d = &d[l * feats..(l + 1) * feats];
                        for k in 0..8 {
                            let row = (idx[k] as usize - base) * feats;
                            for ft in 0..feats {
                                level[row + ft] += wts[k] * d[ft];
                            }
                        }
                    }
                }
            }
        });
}

/// Loss weights and normalisers of one step (shared by all partitions).
#[derive(Debug, Clone, Copy)]
struct Scale {
    weights: [f32; 5],
    fixed: f32,
    learned: f32,
    point: f32,
    rgb: f32,
    depth: f32,
}

/// Trains a [`FusedField`] with the losses, clipping and Adam of [`crate::train::Trainer`].
pub struct FusedTrainer {
    field: FusedField,
    config: TrainConfig,
    terms: Vec<LossTerm>,
    iteration: usize,
    moment1: Vec<Vec<f32>>,
    moment2: Vec<Vec<f32>>,
    work: Vec<Work>,
    /// Seconds spent in the last step's phases (forward, backward, reduce + Adam).
    pub timings: [f64; 3],
}

/// Gradients of one batch with the losses (for tests and the failure path).
pub struct Gradients {
    pub terms: Vec<(LossTerm, f32)>,
    pub grads: Vec<NamedWeight>,
}

impl FusedTrainer {
    /// Starts from the initial parameters of `field` (same seed => same start as burn).
    pub fn new(config: TrainConfig, field: FusedField) -> Result<Self, TrainError> {
        config.validate().map_err(TrainError::Config)?;
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
        let mut weights = [0f32; 5];
        for (k, term) in LossTerm::ALL.into_iter().enumerate() {
            if terms.contains(&term) {
                weights[k] = self.config.losses.get(term);
            }
        }
        let heads = Heads {
            rgb: weights[3] != 0.0,
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
        let start = Instant::now();
        self.work[..parts]
            .par_iter_mut()
            .zip(&bounds)
            .for_each(|(w, &(r0, r1))| {
                w.forward_step(field, &params, batch, r0, r1, heads, config, sky, &weights);
            });
        let mut sums = Sums::default();
        for w in &self.work[..parts] {
            for k in 0..5 {
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
        };
        let norms = [
            scale.fixed,
            scale.learned,
            scale.point,
            scale.rgb,
            scale.depth,
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
                w.backward_step(field, &params, batch, r0, r1, heads, config, sky, &scale);
            });
        let mut table = std::mem::take(&mut self.work[0].grads[field.grid]);
        table.resize(field.weights[field.grid].values.len(), 0.0);
        scatter_grid(field, &self.work[..parts], &bounds, s.samples, &mut table);
        self.work[0].grads[field.grid] = table;
        self.timings[0] = forward;
        self.timings[1] = start.elapsed().as_secs_f64() - forward;
        // Sum the partitions' MLP gradients into the first, in partition order.
        let (first, rest) = self.work.split_at_mut(1);
        let rest = &rest[..parts - 1];
        for (k, g) in first[0].grads.iter_mut().enumerate() {
            if k == field.grid {
                continue;
            }
            g.par_chunks_mut(1 << 14)
                .enumerate()
                .for_each(|(ci, chunk)| {
                    let (o, len) = (ci << 14, chunk.len());
                    for w in rest {
                        chunk
                            .iter_mut()
                            .zip(&w.grads[k][o..o + len])
                            .for_each(|(a, b)| *a += b);
                    }
                });
        }
        Ok(values)
    }

    /// Loss values and gradients of `batch` without updating anything.
    pub fn gradients(&mut self, batch: &RayBatch) -> Result<Gradients, TrainError> {
        let terms = self.compute(batch, None)?;
        let grads = self
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
        let clip = self.config.grad_clip_norm;
        let factor = if clip > 0.0 && norm > clip {
            clip / (norm + 1e-6)
        } else {
            1.0
        };
        let (b1, b2, eps) = (
            self.config.adam_beta1,
            self.config.adam_beta2,
            self.config.adam_epsilon,
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
                    for i in 0..p.len() {
                        let gi = g[i] * factor;
                        m[i] = b1 * m[i] + (1.0 - b1) * gi;
                        v[i] = b2 * v[i] + (1.0 - b2) * gi * gi;
                        let update = (m[i] / c1) / ((v[i] / c2).sqrt() + eps);
                        p[i] -= lr * update;
                    }
                });
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

impl Work {
    /// Forward pass, rendering and loss sums of rays `r0..r1`; zeroes this partition's
    /// gradients.
    #[allow(clippy::too_many_arguments)]
    fn forward_step(
        &mut self,
        f: &FusedField,
        params: &[&[f32]],
        batch: &RayBatch,
        r0: usize,
        r1: usize,
        heads: Heads,
        config: &TrainConfig,
        sky: usize,
        weights: &[f32; 5],
    ) {
        let s = &batch.samples;
        let t = &batch.targets;
        let (ns, c) = (s.samples, s.classes);
        self.grads.resize_with(f.weights.len(), Vec::new);
        for (k, (g, w)) in self.grads.iter_mut().zip(&f.weights).enumerate() {
            // The grid's gradient is not per partition: see `scatter_grid`.
            if k != f.grid {
                g.clear();
                g.resize(w.values.len(), 0.0);
            }
        }
        self.sums = Sums::default();
        if r1 == r0 {
            return;
        }
        let (p0, p1) = (r0 * ns, r1 * ns);
        let n = p1 - p0;
        self.forward_field(
            f,
            params,
            &s.positions[p0 * 3..p1 * 3],
            &s.directions[r0 * 3..r1 * 3],
            ns,
            heads,
        );
        if heads.semantics {
            grow(&mut self.probs, n * c);
            let logits = &self.sem[f.semantic.len() - 1];
            for i in 0..n {
                softmax_into(
                    &logits[i * c..(i + 1) * c],
                    &mut self.probs[i * c..(i + 1) * c],
                );
            }
        }
        grow(&mut self.weight, n);
        grow(&mut self.trans, n);
        grow(&mut self.survive, n);
        grow(&mut self.point_mask, n);
        self.rays.resize(r1 - r0, RayState::default());
        for r in r0..r1 {
            let lr = r - r0;
            let mut excl = 0f32;
            let mut opacity = 0f32;
            let mut state = RayState::default();
            let label = t.labels[r];
            let mut shat = 0f32;
            let mut sl = 0f32;
            for i in 0..ns {
                let li = lr * ns + i;
                let gi = p0 + li;
                let optical = self.sigma[li] * s.deltas[gi];
                let tr = (-excl).exp();
                let survive = (-optical).exp();
                let w = tr * (1.0 - survive);
                excl += optical;
                self.trans[li] = tr;
                self.survive[li] = survive;
                self.weight[li] = w;
                opacity += w;
                let fixed = &s.fixed_semantics[gi * c..(gi + 1) * c];
                if label >= 0 {
                    shat += w * fixed[label as usize];
                    if heads.semantics {
                        sl += w * self.probs[li * c + label as usize];
                    }
                }
                if heads.rgb {
                    for ch in 0..3 {
                        state.colour[ch] += w * self.rgb[li * 3 + ch];
                    }
                }
                state.depth += w * s.t_mid[gi];
                let mut mask = 0.0;
                if weights[2] != 0.0 && self.sigma[li] > config.sigma_threshold && is_one_hot(fixed)
                {
                    mask = 1.0;
                    let z = &self.sem[f.semantic.len() - 1][li * c..(li + 1) * c];
                    let max = z.iter().cloned().fold(f32::NEG_INFINITY, f32::max);
                    let lse = max + z.iter().map(|v| (v - max).exp()).sum::<f32>().ln();
                    let ce: f32 = fixed.iter().zip(z).map(|(fk, zk)| -fk * (zk - lse)).sum();
                    self.sums.terms[2] += ce as f64;
                    self.sums.points_3d += 1.0;
                }
                self.point_mask[li] = mask;
            }
            let remainder = 1.0 - opacity;
            state.remainder_live = remainder > 0.0;
            if label >= 0 && label as usize == sky {
                shat += remainder.max(0.0);
                sl += remainder.max(0.0);
            }
            state.shat_label = shat;
            state.s_label = sl;
            if label >= 0 {
                self.sums.terms[0] += -((shat + PROB_EPS).ln()) as f64;
                if !config.ray_mask || t.ray_mask[r] != 0.0 {
                    self.sums.terms[1] += -((sl + PROB_EPS).ln()) as f64;
                }
            }
            for ch in 0..3 {
                let d = state.colour[ch] - t.rgb[r * 3 + ch];
                self.sums.terms[3] += (d * d) as f64;
            }
            if t.depth_valid[r] {
                let d = state.depth - t.depth[r];
                self.sums.terms[4] += (d * d) as f64;
            }
            self.rays[lr] = state;
        }
    }

    /// Backward pass of rays `r0..r1` into this partition's gradients.
    #[allow(clippy::too_many_arguments)]
    fn backward_step(
        &mut self,
        f: &FusedField,
        params: &[&[f32]],
        batch: &RayBatch,
        r0: usize,
        r1: usize,
        heads: Heads,
        config: &TrainConfig,
        sky: usize,
        scale: &Scale,
    ) {
        if r1 == r0 {
            return;
        }
        let s = &batch.samples;
        let t = &batch.targets;
        let (ns, c) = (s.samples, s.classes);
        let spec_c = &f.spec.config;
        let (g, width) = (spec_c.geo_features, 1 + spec_c.geo_features);
        let p0 = r0 * ns;
        let n = (r1 - r0) * ns;
        let w = &scale.weights;
        grow(&mut self.dtrunk, n * width);
        if heads.semantics {
            grow(&mut self.dz, n * c);
            self.dz[..n * c].iter_mut().for_each(|v| *v = 0.0);
        }
        if heads.rgb {
            grow(&mut self.drgb, n * 3);
        }
        let mut gw = vec![0f32; ns];
        for r in r0..r1 {
            let lr = r - r0;
            let st = self.rays[lr];
            let label = t.labels[r];
            let sky_live = label >= 0 && label as usize == sky && st.remainder_live;
            let sky_term = if sky_live { 1.0 } else { 0.0 };
            let cf = if label >= 0 && w[0] != 0.0 {
                -w[0] / scale.fixed / (st.shat_label + PROB_EPS)
            } else {
                0.0
            };
            let learned = label >= 0 && (!config.ray_mask || t.ray_mask[r] != 0.0);
            let cl = if learned && w[1] != 0.0 {
                -w[1] / scale.learned / (st.s_label + PROB_EPS)
            } else {
                0.0
            };
            let mut cc = [0f32; 3];
            if w[3] != 0.0 {
                for ch in 0..3 {
                    cc[ch] = w[3] * 2.0 * (st.colour[ch] - t.rgb[r * 3 + ch]) / scale.rgb;
                }
            }
            let cd = if w[4] != 0.0 && t.depth_valid[r] {
                w[4] * 2.0 * (st.depth - t.depth[r]) / scale.depth
            } else {
                0.0
            };
            let c3 = w[2] / scale.point;
            for i in 0..ns {
                let li = lr * ns + i;
                let gi = p0 + li;
                let wi = self.weight[li];
                let fixed = &s.fixed_semantics[gi * c..(gi + 1) * c];
                let mut g_w = cd * s.t_mid[gi];
                if label >= 0 {
                    let l = label as usize;
                    g_w += cf * (fixed[l] - sky_term);
                    if heads.semantics {
                        let p = &self.probs[li * c..(li + 1) * c];
                        g_w += cl * (p[l] - sky_term);
                        // dS_l/dz_k = w p_l (delta_lk - p_k)
                        let a = cl * wi * p[l];
                        if a != 0.0 {
                            let dz = &mut self.dz[li * c..(li + 1) * c];
                            for k in 0..c {
                                dz[k] -= a * p[k];
                            }
                            dz[l] += a;
                        }
                    }
                }
                if heads.rgb {
                    for ch in 0..3 {
                        let col = self.rgb[li * 3 + ch];
                        g_w += cc[ch] * col;
                        self.drgb[li * 3 + ch] = cc[ch] * wi * col * (1.0 - col);
                    }
                }
                if self.point_mask[li] != 0.0 {
                    let p = &self.probs[li * c..(li + 1) * c];
                    let fsum: f32 = fixed.iter().sum();
                    let dz = &mut self.dz[li * c..(li + 1) * c];
                    for k in 0..c {
                        dz[k] += c3 * (fsum * p[k] - fixed[k]);
                    }
                }
                gw[i] = g_w;
            }
            // dL/do_i = gw_i T_i e^{-o_i} - sum_{j > i} gw_j w_j
            let mut later = 0f32;
            for i in (0..ns).rev() {
                let li = lr * ns + i;
                let d_optical = gw[i] * self.trans[li] * self.survive[li] - later;
                later += gw[i] * self.weight[li];
                self.dtrunk[li * width] = d_optical * s.deltas[p0 + li] * self.dsigma[li];
            }
        }
        let trunk_out_idx = f.trunk.len() - 1;
        // Heads back to the geometry features.
        grow(&mut self.dgeo, n * g);
        self.dgeo[..n * g].iter_mut().for_each(|v| *v = 0.0);
        if heads.semantics {
            let geo = View {
                data: &self.trunk[trunk_out_idx][1..],
                rs: width,
                cs: 1,
            };
            grow(&mut self.dy, n * c);
            self.dy[..n * c].copy_from_slice(&self.dz[..n * c]);
            mlp::backward(
                &f.semantic,
                params,
                &mut self.grads,
                n,
                geo,
                None,
                &self.sem,
                &mut self.dy,
                &mut self.scratch,
                Some(&mut self.dgeo),
            );
        }
        if heads.rgb {
            let l0 = f.colour[0];
            let h = l0.outputs;
            let rays = r1 - r0;
            let dd = self.dir_pe.len() / rays;
            // dcol: gradient of the first colour layer's pre-activation
            grow(&mut self.dcol, n * h);
            if f.colour.len() > 1 {
                grow(&mut self.dy, n * 3);
                self.dy[..n * 3].copy_from_slice(&self.drgb[..n * 3]);
                mlp::backward(
                    &f.colour[1..],
                    params,
                    &mut self.grads,
                    n,
                    View::rows(&self.col[0], h),
                    None,
                    &self.col[1..],
                    &mut self.dy,
                    &mut self.scratch,
                    Some(&mut self.dcol),
                );
                self.dcol[..n * h]
                    .iter_mut()
                    .zip(&self.col[0][..n * h])
                    .for_each(|(d, &a)| {
                        if a <= 0.0 {
                            *d = 0.0
                        }
                    });
            } else {
                self.dcol[..n * 3].copy_from_slice(&self.drgb[..n * 3]);
            }
            let dcol = &self.dcol[..n * h];
            let geo = &self.trunk[trunk_out_idx][1..];
            let (wg, wd) = self.grads[l0.weight].split_at_mut(g * h);
            gemm(
                g,
                n,
                h,
                View {
                    data: geo,
                    rs: 1,
                    cs: width,
                },
                View::rows(dcol, h),
                1.0,
                wg,
                h,
            );
            // The direction part sees the sum of its ray's samples.
            grow(&mut self.dray, rays * h);
            for (r, sum) in self.dray[..rays * h].chunks_exact_mut(h).enumerate() {
                sum.iter_mut().for_each(|v| *v = 0.0);
                for row in dcol[r * ns * h..(r + 1) * ns * h].chunks_exact(h) {
                    sum.iter_mut().zip(row).for_each(|(a, b)| *a += b);
                }
            }
            gemm(
                dd,
                rays,
                h,
                View::transposed(&self.dir_pe, dd),
                View::rows(&self.dray, h),
                1.0,
                wd,
                h,
            );
            add_column_sums(&mut self.grads[l0.bias], &self.dray[..rays * h]);
            grow(&mut self.dgeo_col, n * g);
            gemm(
                n,
                h,
                g,
                View::rows(dcol, h),
                View::transposed(&params[l0.weight][..g * h], h),
                0.0,
                &mut self.dgeo_col,
                g,
            );
            self.dgeo[..n * g]
                .iter_mut()
                .zip(&self.dgeo_col[..n * g])
                .for_each(|(a, b)| *a += b);
        }
        for i in 0..n {
            self.dtrunk[i * width + 1..(i + 1) * width]
                .copy_from_slice(&self.dgeo[i * g..(i + 1) * g]);
        }
        let e = spec_c.grid.levels * spec_c.grid.features_per_level;
        grow(&mut self.dy, n * width);
        self.dy[..n * width].copy_from_slice(&self.dtrunk[..n * width]);
        mlp::backward(
            &f.trunk,
            params,
            &mut self.grads,
            n,
            View::rows(&self.enc, e),
            None,
            &self.trunk,
            &mut self.dy,
            &mut self.scratch,
            Some(&mut self.denc),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::mlp::SplitMix64;
    use crate::field::{Backend, FieldConfig, GridConfig};
    use crate::train::step::reference_gradients;
    use crate::train::step::tests::{toy_scene, toy_spec};
    use crate::train::LossWeights;

    /// A toy field whose grid holds large random values, so every path carries signal.
    fn toy_fields() -> (RadianceField, FusedField) {
        toy_fields_with_heads(1)
    }

    /// [`toy_fields`] with `head_layers` hidden layers in the colour and semantic heads.
    fn toy_fields_with_heads(head_layers: usize) -> (RadianceField, FusedField) {
        let mut spec = toy_spec();
        spec.config = FieldConfig {
            grid: GridConfig {
                levels: 3,
                log2_table_size: 10,
                base_resolution: 4,
                max_resolution: 32,
                ..Default::default()
            },
            hidden: 16,
            geo_features: 7,
            trunk_layers: 2,
            head_layers,
            ..Default::default()
        };
        let device = Backend::default().device();
        let mut weights = spec.init(&device).weights();
        let mut rng = SplitMix64::new(9);
        for v in &mut weights[0].values {
            *v = rng.uniform(-0.5, 0.5);
        }
        for w in &mut weights[1..] {
            if w.name.ends_with("bias") {
                w.values
                    .iter_mut()
                    .for_each(|v| *v = rng.uniform(-0.2, 0.2));
            }
        }
        let burn = spec
            .init(&Backend::default().train_device())
            .load_weights(&weights)
            .unwrap();
        let fused = FusedField::from_weights(spec, weights).unwrap();
        (burn, fused)
    }

    /// The toy scene with overlapping (two-class) samples, varied deltas, some unlabelled rays
    /// and rays masked out by u(r).
    fn varied_batch() -> RayBatch {
        let mut b = toy_scene();
        let (c, n) = (b.samples.classes, b.samples.samples);
        for r in 0..b.samples.rays {
            if r % 5 == 1 {
                for k in 2..6 {
                    let row = &mut b.samples.fixed_semantics[(r * n + k) * c..(r * n + k + 1) * c];
                    row.copy_from_slice(&[0.5, 0.5, 0.0]);
                }
            }
            if r % 7 == 2 {
                b.targets.labels[r] = -1;
            }
            if r % 6 == 0 {
                b.targets.ray_mask[r] = 0.0;
            }
            for k in 0..n {
                b.samples.deltas[r * n + k] *= 1.0 + 0.5 * ((r * 31 + k * 7) % 5) as f32 / 5.0;
            }
        }
        b
    }

    fn assert_close(what: &str, fused: &[NamedWeight], burn: &[NamedWeight]) {
        assert_eq!(fused.len(), burn.len());
        for (a, b) in fused.iter().zip(burn) {
            assert_eq!(a.name, b.name);
            let scale = b.values.iter().fold(0f32, |m, v| m.max(v.abs()));
            let worst = a
                .values
                .iter()
                .zip(&b.values)
                .map(|(x, y)| (x - y).abs())
                .fold(0f32, f32::max);
            assert!(
                worst <= 2e-3 * scale + 1e-6,
                "{what}: gradient of `{}` differs by {worst} (scale {scale})",
                a.name
            );
        }
    }

    #[test]
    fn losses_and_gradients_match_burn_autodiff_per_term_and_together() {
        let batch = varied_batch();
        let mut configs: Vec<(String, TrainConfig)> = Vec::new();
        let base = TrainConfig {
            sigma_threshold: 0.3,
            ..Default::default()
        };
        configs.push(("all terms".into(), base.clone()));
        for term in LossTerm::ALL {
            let mut c = base.clone();
            c.losses = LossWeights {
                fixed_2d: 0.0,
                learned_2d: 0.0,
                point_3d: 0.0,
                rgb: 0.0,
                depth: 0.0,
            };
            match term {
                LossTerm::Fixed2d => c.losses.fixed_2d = 1.0,
                LossTerm::Learned2d => c.losses.learned_2d = 1.0,
                LossTerm::Point3d => c.losses.point_3d = 1.0,
                LossTerm::Rgb => c.losses.rgb = 1.0,
                LossTerm::Depth => c.losses.depth = 0.1,
            }
            configs.push((term.name().to_string(), c));
        }
        configs.push((
            "without u(r)".into(),
            TrainConfig {
                ray_mask: false,
                ..base.clone()
            },
        ));
        for (what, config) in configs {
            let (burn, fused) = toy_fields();
            let (want_terms, want) = reference_gradients(&burn, &batch, &config);
            let mut trainer = FusedTrainer::new(config, fused).unwrap();
            let got = trainer.gradients(&batch).unwrap();
            for ((t1, v1), (t2, v2)) in got.terms.iter().zip(&want_terms) {
                assert_eq!(t1, t2);
                assert!(
                    (v1 - v2).abs() <= 1e-4 * v2.abs().max(1.0),
                    "{what}: loss {t1} fused {v1} burn {v2}"
                );
            }
            assert_close(&what, &got.grads, &want);
        }
    }

    /// The colour head's split first layer (per-sample geometry, per-ray direction) holds with
    /// no hidden head layer (the first layer is the output) and with two.
    #[test]
    fn gradients_match_burn_for_other_head_depths() {
        let batch = varied_batch();
        let config = TrainConfig {
            sigma_threshold: 0.3,
            ..Default::default()
        };
        for head_layers in [0, 2] {
            let (burn, fused) = toy_fields_with_heads(head_layers);
            let (want_terms, want) = reference_gradients(&burn, &batch, &config);
            let mut trainer = FusedTrainer::new(config.clone(), fused).unwrap();
            let got = trainer.gradients(&batch).unwrap();
            for ((t1, v1), (_, v2)) in got.terms.iter().zip(&want_terms) {
                assert!(
                    (v1 - v2).abs() <= 1e-4 * v2.abs().max(1.0),
                    "head_layers {head_layers}: loss {t1} fused {v1} burn {v2}"
                );
            }
            assert_close(&format!("head_layers {head_layers}"), &got.grads, &want);
        }
    }

    #[test]
    fn inference_matches_the_burn_forward() {
        let (burn, fused) = toy_fields();
        let batch = varied_batch();
        let s = &batch.samples;
        let heads = Heads {
            rgb: true,
            semantics: true,
        };
        let (sigma, rgb, logits) = fused.evaluate(&s.positions, &s.directions, s.samples, heads);
        let input = burn.prepare(&s.positions, Some(&s.directions), s.samples);
        let o = burn.forward(
            &input,
            &[
                crate::field::FieldHead::Rgb,
                crate::field::FieldHead::Semantics,
            ],
        );
        let read1 = |t: burn::tensor::Tensor<1>| t.into_data().try_to_vec::<f32>().unwrap();
        let read2 = |t: burn::tensor::Tensor<2>| t.into_data().try_to_vec::<f32>().unwrap();
        for (name, a, b) in [
            ("density", sigma, read1(o.density)),
            ("rgb", rgb, read2(o.rgb.unwrap())),
            ("logits", logits, read2(o.logits.unwrap())),
        ] {
            assert_eq!(a.len(), b.len(), "{name}");
            for (x, y) in a.iter().zip(&b) {
                assert!(
                    (x - y).abs() <= 1e-4 * y.abs().max(1.0),
                    "{name}: {x} vs {y}"
                );
            }
        }
    }

    #[test]
    fn training_lowers_every_loss_and_is_deterministic() {
        let batch = varied_batch();
        let config = TrainConfig {
            lr: 1e-2,
            ..Default::default()
        };
        let run = || {
            let (_, fused) = toy_fields();
            let mut t = FusedTrainer::new(config.clone(), fused).unwrap();
            let first = t.step(&batch).unwrap();
            let mut last = first.clone();
            for _ in 0..150 {
                last = t.step(&batch).unwrap();
            }
            (first, last, t.into_field().weights)
        };
        let (first, last, w1) = run();
        for (term, v) in &first.terms {
            let after = last.get(*term).unwrap();
            assert!(after < 0.7 * v, "{term}: {v} -> {after}");
        }
        let (_, _, w2) = run();
        assert_eq!(w1, w2, "same seed and batch, same bytes");
    }

    #[test]
    fn non_finite_targets_are_named_not_trained_on() {
        let (_, fused) = toy_fields();
        let mut batch = varied_batch();
        batch.samples.deltas[5] = 1e38;
        batch.samples.positions[0] = 1e30;
        let mut t = FusedTrainer::new(TrainConfig::default(), fused).unwrap();
        let before = t.field().weights.clone();
        let r = t.step(&batch);
        if let Err(e) = &r {
            let msg = e.to_string();
            assert!(msg.contains("iteration 0"), "{msg}");
            assert_eq!(t.field().weights, before, "weights unchanged on error");
        } else {
            // Extreme but finite inputs may train; then every weight stays finite.
            assert!(t
                .field()
                .weights
                .iter()
                .all(|w| w.values.iter().all(|v| v.is_finite())));
        }
    }
}
