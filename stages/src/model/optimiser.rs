//! The optimiser's settings (the `train` stage's `optimiser` group): Adam, its learning rate and
//! its decay over the run, and global-norm clipping. Each engine runs the same update with them
//! (the fused engine by hand, burn through its `Adam`).

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::error::ModelError;

/// Adam with an exponentially decaying learning rate and global gradient-norm clipping.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Optimiser {
    /// Adam's learning rate at the first step. The paper's 5e-4 suits its 8x256 MLP; the hash
    /// grid's tables learn far slower at that rate (docs/experiments/training-defaults.md).
    pub lr: f64,
    /// The rate decays exponentially to `lr * lr_final_factor` at the last step (1: constant).
    /// The published code halves it (0.5).
    pub lr_final_factor: f64,
    /// Clip the global gradient norm to this value (0 = no clipping).
    pub grad_clip_norm: f32,
    /// Adam's beta_1.
    pub adam_beta1: f32,
    /// Adam's beta_2.
    pub adam_beta2: f32,
    /// Adam's epsilon.
    pub adam_epsilon: f32,
}

impl Default for Optimiser {
    fn default() -> Self {
        Self {
            lr: 2e-2,
            lr_final_factor: 0.1,
            grad_clip_norm: 1.0,
            adam_beta1: 0.9,
            adam_beta2: 0.999,
            adam_epsilon: 1e-8,
        }
    }
}

fn invalid(message: String) -> ModelError {
    ModelError::Param(message)
}

impl Optimiser {
    /// Checks ranges; errors name the parameter (`optimiser.lr`, ...).
    pub fn validate(&self) -> Result<(), ModelError> {
        if !(self.lr.is_finite() && self.lr > 0.0) {
            return Err(invalid(format!("`optimiser.lr`: {} must be > 0", self.lr)));
        }
        if !(self.lr_final_factor.is_finite() && self.lr_final_factor > 0.0) {
            return Err(invalid(format!(
                "`optimiser.lr_final_factor`: {} must be > 0",
                self.lr_final_factor
            )));
        }
        if !(self.grad_clip_norm.is_finite() && self.grad_clip_norm >= 0.0) {
            return Err(invalid(format!(
                "`optimiser.grad_clip_norm`: {} must be >= 0",
                self.grad_clip_norm
            )));
        }
        for (name, beta) in [
            ("adam_beta1", self.adam_beta1),
            ("adam_beta2", self.adam_beta2),
        ] {
            if !(0.0..1.0).contains(&beta) {
                return Err(invalid(format!(
                    "`optimiser.{name}`: {beta} must be in [0, 1)"
                )));
            }
        }
        if !(self.adam_epsilon.is_finite() && self.adam_epsilon > 0.0) {
            return Err(invalid(format!(
                "`optimiser.adam_epsilon`: {} must be > 0",
                self.adam_epsilon
            )));
        }
        Ok(())
    }

    /// Learning rate at step `iteration` of a run of `iterations` steps.
    pub fn lr_at(&self, iteration: usize, iterations: usize) -> f64 {
        let progress = iteration as f64 / iterations.saturating_sub(1).max(1) as f64;
        self.lr * self.lr_final_factor.powf(progress.min(1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_rate_decays_to_the_final_factor() {
        let o = Optimiser {
            lr: 5e-4,
            lr_final_factor: 0.5,
            ..Optimiser::default()
        };
        assert_eq!(o.lr_at(0, 11), 5e-4);
        assert!((o.lr_at(10, 11) - 2.5e-4).abs() < 1e-12);
        assert!(o.lr_at(5, 11) < 5e-4 && o.lr_at(5, 11) > 2.5e-4);
        // Past the last step, and in a one-step run, the rate stays at its ends.
        assert!((o.lr_at(20, 11) - 2.5e-4).abs() < 1e-12);
        assert_eq!(o.lr_at(0, 1), 5e-4);
    }

    #[test]
    fn out_of_range_settings_are_named() {
        for (bad, key) in [
            (
                Optimiser {
                    lr: 0.0,
                    ..Default::default()
                },
                "optimiser.lr",
            ),
            (
                Optimiser {
                    lr: f64::NAN,
                    ..Default::default()
                },
                "optimiser.lr",
            ),
            (
                Optimiser {
                    lr_final_factor: -1.0,
                    ..Default::default()
                },
                "optimiser.lr_final_factor",
            ),
            (
                Optimiser {
                    grad_clip_norm: -1.0,
                    ..Default::default()
                },
                "optimiser.grad_clip_norm",
            ),
            (
                Optimiser {
                    adam_beta1: 1.0,
                    ..Default::default()
                },
                "optimiser.adam_beta1",
            ),
            (
                Optimiser {
                    adam_beta2: -0.1,
                    ..Default::default()
                },
                "optimiser.adam_beta2",
            ),
            (
                Optimiser {
                    adam_epsilon: 0.0,
                    ..Default::default()
                },
                "optimiser.adam_epsilon",
            ),
        ] {
            let e = bad.validate().unwrap_err().to_string();
            assert!(e.contains(key), "{e}");
        }
        Optimiser::default().validate().unwrap();
        assert!(serde_json::from_str::<Optimiser>(r#"{"learning_rate": 1}"#).is_err());
    }
}
