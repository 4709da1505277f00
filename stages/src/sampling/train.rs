//! What training draws (the `train` stage's `sampling` group): samples per ray, and where inside
//! its pixel each training ray goes, early and late in training (the jitter schedule). Rendering
//! keeps the pixel centres and the samples the field was trained with ([`SamplingParams`]).

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::params::{SamplingMode, SamplingParams};
use crate::stage::{Result, StageError};

/// Samples per training ray and the pixel jitter schedule.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct TrainSampling {
    /// Samples per ray inside the primitives it crosses (an equal share per interval).
    pub samples: usize,
    /// Samples in the ray's sky interval (when it has one).
    pub sky_samples: usize,
    /// Width (pixels, 0..=1) of the window around its pixel's centre a training ray goes through.
    /// The point is drawn anew each time the ray is drawn; its targets stay the pixel's. With 0
    /// every pass repeats the same rays and the 2D label terms fit the pseudo labels' boundary
    /// mistakes ray by ray (docs/experiments/depth-drift.md).
    pub pixel_jitter: f32,
    /// The pseudo label a jittered ray trains on: its own pixel's or a neighbour's (`bilinear`).
    /// `bilinear` draws the neighbour with the bilinear weight of the ray's point.
    pub jitter_labels: JitterLabels,
    /// The window and labels after `after_passes` passes over the training rays (null: never).
    /// Late passes over few pixels make the depth drift; a wider window with `bilinear` labels
    /// stops it. A full-size run (0.12 passes) never gets there.
    pub late_jitter: Option<LateJitter>,
}

impl Default for TrainSampling {
    fn default() -> Self {
        Self {
            samples: 28,
            sky_samples: 4,
            pixel_jitter: 0.25,
            jitter_labels: JitterLabels::Pixel,
            late_jitter: Some(LateJitter::default()),
        }
    }
}

/// See [`TrainSampling::late_jitter`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct LateJitter {
    /// Passes over the training rays after which these settings replace the early ones.
    /// A pass is as many rays as training has (steps x rays per step / training rays).
    pub after_passes: f32,
    /// Window width in pixels, as `pixel_jitter`.
    pub pixel_jitter: f32,
    /// Labels of the jittered rays, as `jitter_labels`.
    pub jitter_labels: JitterLabels,
}

impl Default for LateJitter {
    fn default() -> Self {
        Self {
            after_passes: 8.0,
            pixel_jitter: 0.5,
            jitter_labels: JitterLabels::Bilinear,
        }
    }
}

/// See [`TrainSampling::jitter_labels`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum JitterLabels {
    #[default]
    Pixel,
    Bilinear,
}

/// The window and labels of `pixel_jitter` / `jitter_labels` (under `prefix`) make sense.
fn check_jitter(prefix: &str, width: f32, labels: JitterLabels) -> Result<()> {
    if !(width.is_finite() && (0.0..=1.0).contains(&width)) {
        return Err(StageError::Params(format!(
            "`{prefix}pixel_jitter`: {width} must be in [0, 1] (pixels)"
        )));
    }
    if labels == JitterLabels::Bilinear && width == 0.0 {
        return Err(StageError::Params(format!(
            "`{prefix}jitter_labels`: bilinear labels jittered rays by their point, but \
             `{prefix}pixel_jitter` 0 casts every ray through its pixel's centre: set it > 0 \
             (e.g. 0.5)"
        )));
    }
    Ok(())
}

impl TrainSampling {
    /// Checks ranges; errors name the parameter (`sampling.samples`, ...).
    pub fn validate(&self) -> Result<()> {
        self.params(None).validate()?;
        check_jitter("sampling.", self.pixel_jitter, self.jitter_labels)?;
        if let Some(late) = &self.late_jitter {
            if !(late.after_passes.is_finite() && late.after_passes >= 0.0) {
                return Err(StageError::Params(format!(
                    "`sampling.late_jitter.after_passes`: {} must be finite and >= 0",
                    late.after_passes
                )));
            }
            check_jitter(
                "sampling.late_jitter.",
                late.pixel_jitter,
                late.jitter_labels,
            )?;
        }
        Ok(())
    }

    /// Where samples go along each ray: inside the primitives, or evenly over `uniform`'s
    /// [near, far] metres (the ablation "uniform sampling").
    pub fn params(&self, uniform: Option<[f32; 2]>) -> SamplingParams {
        let defaults = SamplingParams::default();
        let (mode, [near, far]) = match uniform {
            Some(range) => (SamplingMode::Uniform, range),
            None => (SamplingMode::Primitives, [defaults.near, defaults.far]),
        };
        SamplingParams {
            mode,
            samples: self.samples,
            sky_samples: self.sky_samples,
            near,
            far,
        }
    }

    /// The jitter window (pixels) and labels of a batch drawn after `passes` passes over the
    /// training rays.
    pub fn jitter_at(&self, passes: f64) -> (f32, JitterLabels) {
        match &self.late_jitter {
            Some(late) if passes >= late.after_passes as f64 => {
                (late.pixel_jitter, late.jitter_labels)
            }
            _ => (self.pixel_jitter, self.jitter_labels),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jitter_settings_are_checked_by_name() {
        let c = TrainSampling::default();
        c.validate().unwrap();
        for jitter in [-0.1, 1.5, f32::NAN] {
            let bad = TrainSampling {
                pixel_jitter: jitter,
                ..Default::default()
            };
            let e = bad.validate().unwrap_err().to_string();
            assert!(e.contains("sampling.pixel_jitter"), "{e}");
        }
        for jitter in [0.0, 1.0] {
            let ok = TrainSampling {
                pixel_jitter: jitter,
                ..Default::default()
            };
            ok.validate().unwrap();
        }
        let idle = TrainSampling {
            pixel_jitter: 0.0,
            jitter_labels: JitterLabels::Bilinear,
            ..Default::default()
        };
        let e = idle.validate().unwrap_err().to_string();
        assert!(
            e.contains("sampling.jitter_labels") && e.contains("sampling.pixel_jitter"),
            "{e}"
        );
        let e = serde_json::from_str::<TrainSampling>(r#"{"jitter_labels": "bilinar"}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("bilinar") && e.contains("bilinear"), "{e}");
        let none = TrainSampling {
            samples: 0,
            ..Default::default()
        };
        let e = none.validate().unwrap_err().to_string();
        assert!(e.contains("samples"), "{e}");
    }

    #[test]
    fn late_jitter_takes_over_after_its_passes_and_is_checked() {
        let c = TrainSampling::default();
        assert_eq!(c.jitter_at(0.0), (0.25, JitterLabels::Pixel));
        assert_eq!(c.jitter_at(7.99), (0.25, JitterLabels::Pixel));
        assert_eq!(c.jitter_at(8.0), (0.5, JitterLabels::Bilinear));
        let off: TrainSampling = serde_json::from_str(r#"{"late_jitter": null}"#).unwrap();
        assert_eq!(off.jitter_at(1e6), (0.25, JitterLabels::Pixel));
        // Settings not given keep their defaults (`--set train.sampling.late_jitter.after_passes=2`).
        let partial: TrainSampling =
            serde_json::from_str(r#"{"late_jitter": {"after_passes": 2}}"#).unwrap();
        assert_eq!(partial.jitter_at(2.0), (0.5, JitterLabels::Bilinear));
        assert_eq!(partial.jitter_at(1.9), (0.25, JitterLabels::Pixel));
        assert!(serde_json::from_str::<TrainSampling>(r#"{"late_jitter": {"after": 2}}"#).is_err());
        for (late, key) in [
            (
                LateJitter {
                    after_passes: f32::NAN,
                    ..Default::default()
                },
                "sampling.late_jitter.after_passes",
            ),
            (
                LateJitter {
                    pixel_jitter: 2.0,
                    ..Default::default()
                },
                "sampling.late_jitter.pixel_jitter",
            ),
            (
                LateJitter {
                    pixel_jitter: 0.0,
                    ..Default::default()
                },
                "sampling.late_jitter.jitter_labels",
            ),
        ] {
            let bad = TrainSampling {
                late_jitter: Some(late),
                ..Default::default()
            };
            let e = bad.validate().unwrap_err().to_string();
            assert!(e.contains(key), "{e}");
        }
    }

    #[test]
    fn the_plan_samples_inside_primitives_unless_uniform_is_asked() {
        let c = TrainSampling::default();
        let p = c.params(None);
        assert_eq!(p.mode, SamplingMode::Primitives);
        assert_eq!((p.samples, p.sky_samples), (28, 4));
        let u = c.params(Some([1.0, 60.0]));
        assert_eq!(u.mode, SamplingMode::Uniform);
        assert_eq!((u.near, u.far), (1.0, 60.0));
        let e = c
            .params(Some([5.0, 2.0]))
            .validate()
            .unwrap_err()
            .to_string();
        assert!(e.contains("near") && e.contains("far"), "{e}");
    }
}
