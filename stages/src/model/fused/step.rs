//! One partition's share of a training step: rendering and the loss sums (forward), then the
//! gradients of the weighted losses back through rendering, the heads and the trunk.

// The kernels index several parallel per-sample arrays with one index; iterator chains over
// four zipped slices read worse than the formulas they implement.
#![allow(clippy::needless_range_loop)]

use super::field::FusedField;
use super::mlp::{self, add_column_sums, gemm, grow, View};
use super::work::{RayState, Sums, Work};
use crate::model::batch::{is_one_hot, RayBatch, RaySamples, RayTargets};
use crate::model::composite::softmax_into;
use crate::model::config::{SkyColourInput, TrainConfig};
use crate::model::field::Heads;
use crate::model::loss::LossTerm;

/// Loss weights and normalisers of one step (shared by all partitions).
#[derive(Debug, Clone, Copy)]
pub(super) struct Scale {
    pub(super) weights: [f32; LossTerm::ALL.len()],
    pub(super) fixed: f32,
    pub(super) learned: f32,
    pub(super) point: f32,
    pub(super) rgb: f32,
    pub(super) depth: f32,
    /// Rays in the batch (L_sky's mean).
    pub(super) rays: f32,
}

impl Work {
    /// Forward pass, rendering and loss sums of rays `r0..r1`; zeroes this partition's
    /// gradients.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    pub(super) fn forward_step(
        &mut self,
        f: &FusedField,
        params: &[&[f32]],
        batch: &RayBatch,
        r0: usize,
        r1: usize,
        heads: Heads,
        config: &TrainConfig,
        sky: usize,
        weights: &[f32; LossTerm::ALL.len()],
        gains: &[[f32; 3]],
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
        self.dexposure.clear();
        self.dexposure.resize(gains.len(), [0.0; 3]);
        if r1 == r0 {
            return;
        }
        let (p0, p1) = (r0 * ns, r1 * ns);
        let n = p1 - p0;
        let mut in_sky = std::mem::take(&mut self.in_sky);
        in_sky.clear();
        if f.spec.config.sky_colour == SkyColourInput::Direction {
            let fixed = s.fixed_semantics[p0 * c..p1 * c].chunks_exact(c);
            in_sky.extend(fixed.map(|row| row[sky] == 1.0));
        }
        self.forward_field(
            f,
            params,
            &s.positions[p0 * 3..p1 * 3],
            &s.directions[r0 * 3..r1 * 3],
            ns,
            &in_sky,
            heads,
            true,
        );
        self.in_sky = in_sky;
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
            let mut state = RayState {
                gain: if gains.is_empty() {
                    [1.0; 3]
                } else {
                    gains[t.image[r] as usize]
                },
                ..RayState::default()
            };
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
                if weights[2] != 0.0
                    && self.sigma[li] > config.losses.sigma_threshold
                    && is_one_hot(fixed)
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
            if label < 0 && weights[5] != 0.0 {
                self.sky_prior_forward(s, t, r, r0, config, sky, remainder, &mut state);
            }
            if label >= 0 {
                self.sums.terms[0] += -((shat + config.losses.label_eps).ln()) as f64;
                if !config.ray_mask || t.ray_mask[r] != 0.0 {
                    self.sums.terms[1] += -((sl + config.losses.label_eps).ln()) as f64;
                }
            }
            for ch in 0..3 {
                let d = state.gain[ch] * state.colour[ch] - t.rgb[r * 3 + ch];
                self.sums.terms[3] += (d * d) as f64;
            }
            if t.depth_valid[r] {
                let d = state.depth - t.depth[r];
                self.sums.terms[4] += (d * d) as f64;
            }
            self.rays[lr] = state;
        }
    }

    /// L_sky of unlabelled ray `r`: its gate (from the mean colour of its sky samples, which
    /// the colour head has computed) into `state`, `g (1 - S_hat(sky))` into the sums.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn sky_prior_forward(
        &mut self,
        s: &RaySamples,
        t: &RayTargets,
        r: usize,
        r0: usize,
        config: &TrainConfig,
        sky: usize,
        remainder: f32,
        state: &mut RayState,
    ) {
        let (ns, c) = (s.samples, s.classes);
        let (mut sky_rgb, mut count, mut shat_sky) = ([0f32; 3], 0f32, remainder.max(0.0));
        for i in 0..ns {
            let li = (r - r0) * ns + i;
            let m = s.fixed_semantics[(r * ns + i) * c + sky];
            shat_sky += self.weight[li] * m;
            if m != 0.0 {
                count += m;
                for ch in 0..3 {
                    sky_rgb[ch] += m * self.rgb[li * 3 + ch];
                }
            }
        }
        if count == 0.0 {
            return;
        }
        let d2: f32 = (0..3)
            .map(|ch| (state.gain[ch] * sky_rgb[ch] / count - t.rgb[r * 3 + ch]).powi(2))
            .sum();
        let tau = config.losses.sky_prior_colour;
        state.sky_gate = (-d2 / (tau * tau)).exp();
        self.sums.terms[5] += (state.sky_gate * (1.0 - shat_sky)) as f64;
    }

    /// Backward pass of rays `r0..r1` into this partition's gradients: through rendering and
    /// the losses ([`Work::backward_rays`]), then the heads and the trunk
    /// ([`Work::backward_field`]).
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    pub(super) fn backward_step(
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
        self.backward_rays(f, batch, r0, r1, heads, config, sky, scale);
        self.backward_field(
            f,
            params,
            batch.samples.samples,
            batch.samples.classes,
            r1 - r0,
            heads,
        );
    }

    /// Gradients of the weighted losses with respect to each sample's density (into the first
    /// column of `dtrunk`), logits (`dz`) and colour (`drgb`).
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn backward_rays(
        &mut self,
        f: &FusedField,
        batch: &RayBatch,
        r0: usize,
        r1: usize,
        heads: Heads,
        config: &TrainConfig,
        sky: usize,
        scale: &Scale,
    ) {
        let s = &batch.samples;
        let t = &batch.targets;
        let (ns, c) = (s.samples, s.classes);
        let spec_c = &f.spec.config;
        let width = 1 + spec_c.geo_features;
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
                -w[0] / scale.fixed / (st.shat_label + config.losses.label_eps)
            } else {
                0.0
            };
            let learned = label >= 0 && (!config.ray_mask || t.ray_mask[r] != 0.0);
            let cl = if learned && w[1] != 0.0 {
                -w[1] / scale.learned / (st.s_label + config.losses.label_eps)
            } else {
                0.0
            };
            // e g is d/dC of w (g C - C*)^2 for the rendered colour C and the image's gain
            // g = exp(a); e g C is d/da.
            let mut cc = [0f32; 3];
            if w[3] != 0.0 {
                for ch in 0..3 {
                    let g = st.gain[ch];
                    let e = w[3] * 2.0 * (g * st.colour[ch] - t.rgb[r * 3 + ch]) / scale.rgb;
                    cc[ch] = e * g;
                    if !self.dexposure.is_empty() {
                        self.dexposure[t.image[r] as usize][ch] += e * g * st.colour[ch];
                    }
                }
            }
            let cd = if w[4] != 0.0 && t.depth_valid[r] {
                w[4] * 2.0 * (st.depth - t.depth[r]) / scale.depth
            } else {
                0.0
            };
            let c3 = w[2] / scale.point;
            // L_sky: d/dw_i of -g S_hat(sky), S_hat(sky) = sum_i w_i fixed_i(sky) + remainder.
            let c_sky = -w[5] * st.sky_gate / scale.rays;
            let sky_live = if st.remainder_live { 1.0 } else { 0.0 };
            for i in 0..ns {
                let li = lr * ns + i;
                let gi = p0 + li;
                let wi = self.weight[li];
                let fixed = &s.fixed_semantics[gi * c..(gi + 1) * c];
                let mut g_w = cd * s.t_mid[gi];
                if c_sky != 0.0 {
                    g_w += c_sky * (fixed[sky] - sky_live);
                }
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
    }

    /// The heads and the trunk backwards, from the per-sample gradients of `backward_rays` to
    /// the parameters and the encoding (`denc`) of `rays` rays of `ns` samples and `c` classes.
    #[inline(always)]
    fn backward_field(
        &mut self,
        f: &FusedField,
        params: &[&[f32]],
        ns: usize,
        c: usize,
        rays: usize,
        heads: Heads,
    ) {
        let spec_c = &f.spec.config;
        let (g, width) = (spec_c.geo_features, 1 + spec_c.geo_features);
        let n = rays * ns;
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
            // The direction part sees the sum of its ray's samples.
            grow(&mut self.dray, rays * h);
            for (r, sum) in self.dray[..rays * h].chunks_exact_mut(h).enumerate() {
                sum.iter_mut().for_each(|v| *v = 0.0);
                for row in self.dcol[r * ns * h..(r + 1) * ns * h].chunks_exact(h) {
                    sum.iter_mut().zip(row).for_each(|(a, b)| *a += b);
                }
            }
            // Direction-only samples: nothing flows to the geometry part.
            for (row, &d) in self.dcol[..n * h]
                .chunks_exact_mut(h)
                .zip(&self.direction_only)
            {
                if d {
                    row.iter_mut().for_each(|v| *v = 0.0);
                }
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
