//! Where a field's samples go along each ray ([`SamplingParams`]): as trained
//! ([`super::TrainSampling::params`]) and stored beside the weights for rendering.

use serde::{Deserialize, Serialize};

use crate::stage::{Result, StageError};

/// How samples are placed along a ray.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SamplingMode {
    /// Only inside the primitives a ray crosses, plus the sky interval (the method).
    Primitives,
    /// Evenly over [near, far] (ablation: "uniform sampling").
    Uniform,
}

/// Where a field's samples go along each ray, as trained ([`TrainSampling::params`]) and stored
/// beside its weights for rendering.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SamplingParams {
    /// Inside the primitives a ray crosses (the method) or evenly over [near, far].
    pub mode: SamplingMode,
    /// Samples per ray inside primitives (an equal share per interval the ray crosses).
    pub samples: usize,
    /// Samples in the sky interval (when the ray has one).
    pub sky_samples: usize,
    /// Uniform mode: nearest sample distance, metres.
    pub near: f32,
    /// Uniform mode: farthest sample distance, metres.
    pub far: f32,
}

impl Default for SamplingParams {
    fn default() -> Self {
        Self {
            mode: SamplingMode::Primitives,
            samples: 28,
            sky_samples: 4,
            near: 0.5,
            far: 80.0,
        }
    }
}

impl SamplingParams {
    pub fn validate(&self) -> Result<()> {
        if self.samples == 0 || self.samples > 512 {
            return Err(StageError::Params(format!(
                "`sampling.samples`: {} must be in 1..=512",
                self.samples
            )));
        }
        if self.sky_samples > 64 {
            return Err(StageError::Params(format!(
                "`sampling.sky_samples`: {} must be in 0..=64",
                self.sky_samples
            )));
        }
        if !(self.near >= 0.0 && self.far > self.near && self.far.is_finite()) {
            return Err(StageError::Params(format!(
                "`experimental.uniform_sampling`: [{}, {}] must be [near, far] metres with 0 <= \
                 near < far, both finite",
                self.near, self.far
            )));
        }
        Ok(())
    }

    /// Samples per ray in a batch.
    pub fn per_ray(&self) -> usize {
        match self.mode {
            SamplingMode::Primitives => self.samples + self.sky_samples,
            SamplingMode::Uniform => self.samples,
        }
    }
}
