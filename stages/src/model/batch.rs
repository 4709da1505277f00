//! Plain host-side ray data: what one training batch holds, independent of any table format
//! and of the engine ([`RayBatch::from_samples`] makes one from the sampling plan's batch), and
//! the epoch-wise ray order batches are drawn in.
//!
//! Every ray has the same number of samples `S`; pad shorter rays with samples of `delta = 0`
//! (they get zero weight). Classes are the scene's primitive classes followed by sky (last).

use crate::rng::SplitMix64;
use crate::sampling::SampleBatch;

/// Per-sample geometry of a set of rays (enough to render).
///
/// # Shapes
/// `positions`: `[rays, samples, 3]` (scene frame); `deltas`, `t_mid`: `[rays, samples]`;
/// `directions`: `[rays, 3]`; `fixed_semantics`: `[rays, samples, classes]`, each row the fixed
/// field s_hat at the sample (one-hot of the enclosing primitive's class, uniform over the
/// classes of overlapping primitives of different classes, one-hot sky for sky-interval
/// samples; all-zero rows are allowed for padding).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RaySamples {
    pub rays: usize,
    pub samples: usize,
    pub classes: usize,
    pub positions: Vec<f32>,
    pub deltas: Vec<f32>,
    pub t_mid: Vec<f32>,
    pub directions: Vec<f32>,
    pub fixed_semantics: Vec<f32>,
}

/// Per-ray supervision.
///
/// # Shapes
/// All `[rays]` except `rgb`: `[rays, 3]` in [0, 1].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RayTargets {
    /// Pseudo label: index into the classes (sky = `classes - 1`), or `-1` for none (the
    /// label is not a scene class or the pixel is void): such rays skip both 2D semantic terms.
    pub labels: Vec<i32>,
    /// u(r): 1 iff the pseudo label equals the class of a primitive the ray hits, or is sky.
    pub ray_mask: Vec<f32>,
    /// Stereo depth along the ray (same units as `t_mid`); ignored where `depth_valid` is false.
    pub depth: Vec<f32>,
    pub depth_valid: Vec<bool>,
    pub rgb: Vec<f32>,
    /// The training image of each ray (an index into the trainer's per-image exposures), or
    /// empty: no per-image exposure.
    pub image: Vec<u32>,
}

/// One training batch (or the whole training set, from which batches are drawn).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RayBatch {
    pub samples: RaySamples,
    pub targets: RayTargets,
}

impl RaySamples {
    /// Per sample: whether it lies in its ray's sky interval
    /// ([`crate::sampling::in_sky_rows`]).
    pub fn in_sky(&self) -> Vec<bool> {
        crate::sampling::in_sky_rows(&self.fixed_semantics, self.classes)
    }

    /// Checks lengths and values; errors name the field.
    pub fn validate(&self) -> Result<(), String> {
        let (r, s, c) = (self.rays, self.samples, self.classes);
        let check = |name: &str, len: usize, want: usize| {
            if len == want {
                Ok(())
            } else {
                Err(format!("{name} has {len} values, expected {want} ({r} rays x {s} samples x {c} classes)"))
            }
        };
        check("positions", self.positions.len(), r * s * 3)?;
        check("deltas", self.deltas.len(), r * s)?;
        check("t_mid", self.t_mid.len(), r * s)?;
        check("directions", self.directions.len(), r * 3)?;
        check("fixed_semantics", self.fixed_semantics.len(), r * s * c)?;
        if s == 0 || c < 2 {
            return Err(format!("need samples >= 1 and classes >= 2 (got {s}, {c})"));
        }
        if let Some(i) = self
            .deltas
            .iter()
            .position(|d| !(d.is_finite() && *d >= 0.0))
        {
            return Err(format!(
                "deltas[{i}] = {} must be finite and >= 0",
                self.deltas[i]
            ));
        }
        if let Some(i) = self
            .positions
            .iter()
            .chain(&self.t_mid)
            .position(|v| !v.is_finite())
        {
            return Err(format!("positions/t_mid value {i} is not finite"));
        }
        Ok(())
    }

    /// The rays at `indices`, in that order.
    pub fn select(&self, indices: &[usize]) -> RaySamples {
        let (s, c) = (self.samples, self.classes);
        RaySamples {
            rays: indices.len(),
            samples: s,
            classes: c,
            positions: gather(&self.positions, indices, s * 3),
            deltas: gather(&self.deltas, indices, s),
            t_mid: gather(&self.t_mid, indices, s),
            directions: gather(&self.directions, indices, 3),
            fixed_semantics: gather(&self.fixed_semantics, indices, s * c),
        }
    }

    /// u_i's first factor: 1 where the fixed distribution is one-hot (a unique class).
    ///
    /// # Shapes
    /// `[rays, samples]` flattened.
    pub fn unique_class_mask(&self) -> Vec<f32> {
        self.fixed_semantics
            .chunks_exact(self.classes)
            .map(|p| if is_one_hot(p) { 1.0 } else { 0.0 })
            .collect()
    }
}

/// A fixed-field row is one-hot (a unique class): the first factor of the L_3D point mask u_i.
#[inline(always)]
pub fn is_one_hot(p: &[f32]) -> bool {
    let max = p.iter().cloned().fold(0.0f32, f32::max);
    let sum: f32 = p.iter().sum();
    max > 0.999 && (sum - max).abs() < 1e-3
}

impl RayTargets {
    /// Checks lengths and values against `rays` rays of `classes` classes.
    pub fn validate(&self, rays: usize, classes: usize) -> Result<(), String> {
        for (name, len, want) in [
            ("labels", self.labels.len(), rays),
            ("ray_mask", self.ray_mask.len(), rays),
            ("depth", self.depth.len(), rays),
            ("depth_valid", self.depth_valid.len(), rays),
            ("rgb", self.rgb.len(), rays * 3),
        ] {
            if len != want {
                return Err(format!("targets.{name} has {len} values, expected {want}"));
            }
        }
        if !self.image.is_empty() && self.image.len() != rays {
            return Err(format!(
                "targets.image has {} values, expected {rays} (or none)",
                self.image.len()
            ));
        }
        if let Some(l) = self.labels.iter().find(|&&l| l < -1 || l >= classes as i32) {
            return Err(format!("label {l} is outside -1..{classes}"));
        }
        if let Some(i) = (0..rays).find(|&i| self.depth_valid[i] && !self.depth[i].is_finite()) {
            return Err(format!(
                "depth[{i}] is marked valid but is {}",
                self.depth[i]
            ));
        }
        if let Some(i) = self.rgb.iter().position(|v| !v.is_finite()) {
            return Err(format!("rgb value {i} is not finite"));
        }
        Ok(())
    }

    /// The rays at `indices`, in that order.
    pub fn select(&self, indices: &[usize]) -> RayTargets {
        RayTargets {
            labels: gather(&self.labels, indices, 1),
            ray_mask: gather(&self.ray_mask, indices, 1),
            depth: gather(&self.depth, indices, 1),
            depth_valid: gather(&self.depth_valid, indices, 1),
            rgb: gather(&self.rgb, indices, 3),
            image: if self.image.is_empty() {
                Vec::new()
            } else {
                gather(&self.image, indices, 1)
            },
        }
    }
}

impl RayBatch {
    /// The training batch of sampled rays. Stereo depth is a camera z-depth; the losses compare
    /// it with distances along the ray, so it is divided by the ray's z scale.
    pub fn from_samples(b: &SampleBatch) -> RayBatch {
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
                image: Vec::new(),
            },
        }
    }

    pub fn rays(&self) -> usize {
        self.samples.rays
    }

    /// Checks both parts.
    pub fn validate(&self) -> Result<(), String> {
        self.samples.validate()?;
        self.targets
            .validate(self.samples.rays, self.samples.classes)
    }

    /// The rays at `indices`, in that order.
    pub fn select(&self, indices: &[usize]) -> RayBatch {
        RayBatch {
            samples: self.samples.select(indices),
            targets: self.targets.select(indices),
        }
    }
}

/// `batch` ray indices out of `total` for iteration `iteration`: a seeded shuffle per epoch,
/// consumed in order, so every ray is seen once per epoch and a run is reproducible.
pub fn batch_indices(seed: u64, iteration: usize, total: usize, batch: usize) -> Vec<usize> {
    BatchOrder::new(seed, total, batch)
        .batch(iteration)
        .to_vec()
}

/// [`batch_indices`] for consecutive iterations, shuffling once per epoch instead of once per
/// call. [`BatchOrder::over`] shuffles the values themselves (ray ids), so a full-size scene's
/// candidate rays cost their own 4 bytes each and no 8-byte index beside them.
pub struct BatchOrder<T = usize> {
    seed: u64,
    batch: usize,
    epoch: Option<usize>,
    order: Vec<T>,
}

impl BatchOrder<usize> {
    pub fn new(seed: u64, total: usize, batch: usize) -> Self {
        Self::over(seed, (0..total).collect(), batch)
    }
}

impl<T: Copy + Ord> BatchOrder<T> {
    /// Batches of `values`, which must be strictly ascending: each epoch's shuffle starts from
    /// them in that order (restored by sorting), so the batches are `values[i]` for the indices
    /// [`batch_indices`] gives.
    pub fn over(seed: u64, values: Vec<T>, batch: usize) -> Self {
        assert!(!values.is_empty(), "no rays to draw from");
        debug_assert!(
            values.windows(2).all(|w| w[0] < w[1]),
            "values not ascending"
        );
        Self {
            seed,
            batch: batch.min(values.len()),
            epoch: None,
            order: values,
        }
    }

    /// The values of `iteration`'s batch.
    pub fn batch(&mut self, iteration: usize) -> &[T] {
        let total = self.order.len();
        let per_epoch = total / self.batch;
        let epoch = iteration / per_epoch;
        if self.epoch != Some(epoch) {
            if self.epoch.is_some() {
                self.order.sort_unstable();
            }
            // Hash the (seed, epoch) pair first: SplitMix streams seeded `k * GOLDEN` apart are
            // the same stream shifted by k, which would make consecutive epochs' orders nearly
            // equal.
            let mut rng = SplitMix64::new(
                SplitMix64::new(self.seed ^ (epoch as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15))
                    .next_u64(),
            );
            for i in (1..total).rev() {
                self.order.swap(i, rng.below(i + 1));
            }
            self.epoch = Some(epoch);
        }
        let start = (iteration % per_epoch) * self.batch;
        &self.order[start..start + self.batch]
    }
}

/// `k` of the `n` values `values` yields, chosen uniformly without replacement (Knuth's
/// selection sampling, algorithm S), in the order given; all of them when `k >= n`. A short run
/// over tens of millions of rays draws from such a sample what a shuffle of all of them would
/// give in law, without holding them all.
pub fn selection_sample<T>(
    seed: u64,
    n: usize,
    k: usize,
    values: impl Iterator<Item = T>,
) -> Vec<T> {
    if k >= n {
        let mut all = Vec::with_capacity(n);
        all.extend(values.take(n));
        return all;
    }
    let mut rng = SplitMix64::new(seed);
    let mut out = Vec::with_capacity(k);
    let mut left = n;
    for v in values {
        if out.len() == k || left == 0 {
            break;
        }
        // Each of the `left` values still to come is taken with the chance that the ones
        // still wanted give: every k-subset comes out equally likely.
        if rng.below(left) < k - out.len() {
            out.push(v);
        }
        left -= 1;
    }
    debug_assert_eq!(out.len(), k, "fewer than n values");
    out
}

fn gather<T: Copy>(values: &[T], indices: &[usize], width: usize) -> Vec<T> {
    let mut out = Vec::with_capacity(indices.len() * width);
    for &i in indices {
        out.extend_from_slice(&values[i * width..(i + 1) * width]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batches_cover_an_epoch_without_repeats() {
        let mut seen: Vec<usize> = (0..5).flat_map(|i| batch_indices(9, i, 50, 10)).collect();
        seen.sort();
        assert_eq!(seen, (0..50).collect::<Vec<_>>());
        assert_eq!(batch_indices(9, 3, 50, 10), batch_indices(9, 3, 50, 10));
        assert_ne!(batch_indices(9, 0, 50, 10), batch_indices(9, 5, 50, 10));
    }

    #[test]
    fn a_reused_order_gives_the_batches_of_a_fresh_shuffle() {
        let mut order = BatchOrder::new(4, 53, 10);
        // across epochs (5 batches each, 3 rays left over) and back to an earlier one
        for it in (0..23).chain([2, 17, 0]) {
            let fresh = BatchOrder::new(4, 53, 10).batch(it).to_vec();
            assert_eq!(order.batch(it), &fresh[..], "iteration {it}");
        }
    }

    #[test]
    fn an_order_over_values_gives_the_values_at_the_shuffled_indices() {
        let values: Vec<u32> = (0..53u32).map(|i| 7 + 3 * i).collect();
        let mut order = BatchOrder::over(4, values.clone(), 10);
        for it in (0..23).chain([2, 17, 0]) {
            let expected: Vec<u32> = batch_indices(4, it, 53, 10)
                .iter()
                .map(|&i| values[i])
                .collect();
            assert_eq!(order.batch(it), &expected[..], "iteration {it}");
        }
    }

    #[test]
    fn a_selection_sample_takes_k_in_order_each_value_equally_often() {
        assert_eq!(selection_sample(1, 5, 9, 10..15), vec![10, 11, 12, 13, 14]);
        assert_eq!(selection_sample(1, 5, 5, 10..15), vec![10, 11, 12, 13, 14]);
        assert!(selection_sample(1, 5, 0, 10..15).is_empty());
        let (n, k, draws) = (20usize, 6usize, 20_000u64);
        let mut count = vec![0u32; n];
        let mut pairs = 0u32;
        for seed in 0..draws {
            let s = selection_sample(seed, n, k, 0..n);
            assert_eq!(s.len(), k, "seed {seed}");
            assert!(s.windows(2).all(|w| w[0] < w[1]), "seed {seed}: {s:?}");
            for &v in &s {
                count[v] += 1;
            }
            pairs += u32::from(s.contains(&0) && s.contains(&(n - 1)));
        }
        // Each value with chance k/n (binomial sd ~ 65 of 6000); the first and last together
        // with chance k(k-1)/(n(n-1)), as for a uniform k-subset.
        let expect = draws as f64 * k as f64 / n as f64;
        for (v, &c) in count.iter().enumerate() {
            assert!(
                (c as f64 - expect).abs() < 5.0 * 65.0,
                "value {v}: {c} of ~{expect}"
            );
        }
        let pair = draws as f64 * (k * (k - 1)) as f64 / (n * (n - 1)) as f64;
        assert!(
            (pairs as f64 - pair).abs() < 5.0 * pair.sqrt(),
            "{pairs} pairs of ~{pair}"
        );
    }

    #[test]
    fn unique_class_mask_marks_one_hot_rows_only() {
        let s = RaySamples {
            rays: 1,
            samples: 3,
            classes: 2,
            fixed_semantics: vec![1.0, 0.0, 0.5, 0.5, 0.0, 0.0],
            ..Default::default()
        };
        assert_eq!(s.unique_class_mask(), vec![1.0, 0.0, 0.0]);
    }
}
