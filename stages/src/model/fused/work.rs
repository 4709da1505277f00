//! Buffers of one ray partition, reused across steps, and the field's forward pass over them.

use super::field::FusedField;
use rayon::prelude::*;

use super::mlp::{self, add_bias, gemm, grow, relu_in_place, View};
use super::simd::dispatch;
use crate::model::config::SkyColourInput;
use crate::model::encoding::{lookup_level, positional_encoding, unit_direction};
use crate::model::field::Heads;
use crate::model::loss::LossTerm;

/// Per-ray results of the forward pass that the backward pass needs.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct RayState {
    pub(super) shat_label: f32,
    pub(super) s_label: f32,
    pub(super) colour: [f32; 3],
    pub(super) depth: f32,
    /// 1 - opacity > 0: the sky remainder is live (its gradient flows).
    pub(super) remainder_live: bool,
    /// The gate of L_sky (0: the term does not act on this ray).
    pub(super) sky_gate: f32,
    /// The colour gain of the ray's image (1 without per-image exposure).
    pub(super) gain: [f32; 3],
}

/// Unnormalised loss sums of a partition, and the L_3D point count.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Sums {
    pub(super) terms: [f64; LossTerm::ALL.len()],
    pub(super) points_3d: f64,
}

/// Buffers of one partition, reused across steps (they only grow).
#[derive(Default)]
pub(super) struct Work {
    /// Gradient of the loss with respect to each image's log colour gain.
    pub(super) dexposure: Vec<[f32; 3]>,
    pub(super) unit: Vec<f32>,
    /// Corner rows and weights, level-major: `[levels, points, 8]`.
    pub(super) idx: Vec<i32>,
    pub(super) wts: Vec<f32>,
    pub(super) enc: Vec<f32>,
    pub(super) trunk: Vec<Vec<f32>>,
    pub(super) sem: Vec<Vec<f32>>,
    pub(super) col: Vec<Vec<f32>>,
    /// Per ray: the direction encoding `[rays, dd]` and its term in the colour head's first
    /// layer (with the bias), `[rays, hidden]`.
    pub(super) dir_pe: Vec<f32>,
    pub(super) dir_term: Vec<f32>,
    pub(super) dcol: Vec<f32>,
    pub(super) dray: Vec<f32>,
    pub(super) sigma: Vec<f32>,
    pub(super) dsigma: Vec<f32>,
    pub(super) probs: Vec<f32>,
    pub(super) rgb: Vec<f32>,
    pub(super) weight: Vec<f32>,
    pub(super) trans: Vec<f32>,
    pub(super) survive: Vec<f32>,
    pub(super) point_mask: Vec<f32>,
    pub(super) rays: Vec<RayState>,
    pub(super) dy: Vec<f32>,
    pub(super) scratch: Vec<f32>,
    pub(super) dgeo: Vec<f32>,
    pub(super) dgeo_col: Vec<f32>,
    pub(super) dtrunk: Vec<f32>,
    pub(super) denc: Vec<f32>,
    pub(super) dz: Vec<f32>,
    pub(super) drgb: Vec<f32>,
    pub(super) grads: Vec<Vec<f32>>,
    pub(super) sums: Sums,
    /// Per sample of the last forward pass: the colour head saw the direction only (a sky
    /// sample under `sky_colour: direction`); empty: no sample did.
    pub(super) direction_only: Vec<bool>,
    /// Scratch for a training step's sky flags.
    pub(super) in_sky: Vec<bool>,
}

/// Points ahead whose table rows the gather asks the cache for: a level's table (2 MiB at the
/// full-size grid) does not fit in L2, and the rows are random.
const PREFETCH_AHEAD: usize = 16;

/// Hints the cache to load the table rows (`width` floats each) of point `i`'s eight corners in
/// `idx`, if there is such a point; never faults.
#[inline(always)]
fn prefetch_rows(table: &[f32], idx: &[i32], i: usize, width: usize) {
    let Some(corners) = idx.get(i * 8..(i + 1) * 8) else {
        return;
    };
    for &row in corners {
        let p = table.as_ptr().wrapping_add(row as usize * width);
        #[cfg(target_arch = "x86_64")]
        // SAFETY: a prefetch only hints the cache, for any address.
        unsafe {
            use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
            _mm_prefetch(p.cast::<i8>(), _MM_HINT_T0)
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = p;
    }
}

#[inline(always)]
pub(super) fn softplus(x: f32) -> f32 {
    if x > 20.0 {
        x
    } else {
        x.exp().ln_1p()
    }
}

#[inline(always)]
pub(super) fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

impl Work {
    /// Encoding, trunk, density and the requested heads for `positions` (`[n, 3]`) whose rays
    /// (`directions`, `[n / samples, 3]`) have `samples` points each; with `gradients`, also
    /// the density's derivative the backward pass needs. `in_sky` (`[n]` or empty): the
    /// samples in their ray's sky interval.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    pub(super) fn forward_field(
        &mut self,
        f: &FusedField,
        params: &[&[f32]],
        positions: &[f32],
        directions: &[f32],
        samples: usize,
        in_sky: &[bool],
        heads: Heads,
        gradients: bool,
    ) {
        let spec = &f.spec;
        let c = &spec.config;
        let n = positions.len() / 3;
        self.direction_only.clear();
        if c.sky_colour == SkyColourInput::Direction && in_sky.contains(&true) {
            assert_eq!(in_sky.len(), n, "in_sky must have one flag per sample");
            self.direction_only.extend_from_slice(in_sky);
        }
        self.encode(f, params[f.grid], positions);
        let e = c.grid.levels * c.grid.features_per_level;
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
        for i in 0..n {
            self.sigma[i] = softplus(trunk_out[i * width] + c.density_shift);
        }
        if gradients {
            grow(&mut self.dsigma, n);
            for i in 0..n {
                self.dsigma[i] = sigmoid(trunk_out[i * width] + c.density_shift);
            }
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
            // Sky samples under `sky_colour: direction`: the geometry part is zero.
            for (row, &d) in h0[..n * h].chunks_exact_mut(h).zip(&self.direction_only) {
                if d {
                    row.iter_mut().for_each(|v| *v = 0.0);
                }
            }
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

    /// The grid encoding of `positions` (`[n, 3]`) into `enc`, keeping each point's corner rows
    /// and weights (`idx`, `wts`) for the backward pass.
    #[inline(always)]
    fn encode(&mut self, f: &FusedField, table: &[f32], positions: &[f32]) {
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
                for (i, ((out, corners), w)) in enc
                    .zip(idx.chunks_exact(8))
                    .zip(w.chunks_exact(8))
                    .enumerate()
                {
                    prefetch_rows(table, idx, i + PREFETCH_AHEAD, 2);
                    let mut acc = [0f32; 2];
                    for k in 0..8 {
                        let row = corners[k] as usize * 2;
                        acc[0] += w[k] * table[row];
                        acc[1] += w[k] * table[row + 1];
                    }
                    out[l * 2..l * 2 + 2].copy_from_slice(&acc);
                }
            } else {
                for (i, ((out, corners), w)) in enc
                    .zip(idx.chunks_exact(8))
                    .zip(w.chunks_exact(8))
                    .enumerate()
                {
                    prefetch_rows(table, idx, i + PREFETCH_AHEAD, feats);
                    let out = &mut out[l * feats..(l + 1) * feats];
                    out.iter_mut().for_each(|v| *v = 0.0);
                    for k in 0..8 {
                        let row = corners[k] as usize * feats;
                        for ft in 0..feats {
                            out[ft] += w[k] * table[row + ft];
                        }
                    }
                }
            }
        }
    }
}

/// The grid table's gradient from every partition's encoding gradient (`denc`), one level per
/// task: a level's rows are written by one task only, in partition and point order, so the sum
/// is deterministic, and each task's slice of the table (512 KiB by default) stays in cache.
pub(super) fn scatter_grid(
    f: &FusedField,
    work: &[Work],
    bounds: &[(usize, usize)],
    samples: usize,
    table: &mut [f32],
) {
    let grid = &f.spec.config.grid;
    let feats = grid.features_per_level;
    let rows = grid.table_size();
    table
        .par_chunks_mut(rows * feats)
        .enumerate()
        .for_each(|(l, level)| {
            dispatch(
                #[inline(always)]
                || scatter_level(f, work, bounds, samples, l, level),
            )
        });
}

/// Level `l`'s rows of the grid table's gradient (see [`scatter_grid`]).
#[inline(always)]
fn scatter_level(
    f: &FusedField,
    work: &[Work],
    bounds: &[(usize, usize)],
    samples: usize,
    l: usize,
    level: &mut [f32],
) {
    let grid = &f.spec.config.grid;
    let feats = grid.features_per_level;
    let e = grid.levels * feats;
    let rows = grid.table_size();
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
}
