//! The engine seam: which implementation trains and evaluates the field. Everything above it
//! (the `train` and `render` kinds) sees only [`Engine`], [`Trainer`] and [`Field`]; weights
//! cross it as named rows ([`crate::model::params`]) that every engine reads and writes.
//!
//! Engines: `fused` (hand-written CPU kernels of the grid field, the default) and the burn
//! backends `flex`, `ndarray`, `wgpu`, `cuda` (the last three behind cargo features). The burn
//! engine is the reference; tests hold every other engine to it
//! ([`crate::model`]'s parity tests).

use std::fmt;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

use super::burn::{self, Backend};
use super::config::{FieldConfig, FieldSpec, TrainConfig};
use super::error::{ModelError, TrainError};
use super::field::Field;
use super::fused::{self, FusedField, FusedTrainer};
use super::params::{self, NamedWeight};
use super::train::Trainer;

/// An implementation of the model. Written in pipeline files by [`Engine::name`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Engine {
    /// The fused CPU kernels (grid encoding only).
    #[default]
    Fused,
    /// The burn modules on a burn backend.
    Burn(Backend),
}

impl Engine {
    /// The engines this build has: fused, then the compiled-in burn backends.
    pub fn available() -> Vec<Engine> {
        let mut all = vec![Engine::Fused];
        all.extend(Backend::available().into_iter().map(Engine::Burn));
        all
    }

    /// `fused`, or the burn backend's name (`flex`, `ndarray`, `wgpu`, `cuda`).
    pub fn name(self) -> &'static str {
        match self {
            Engine::Fused => "fused",
            Engine::Burn(b) => b.name(),
        }
    }

    /// Parses [`Engine::name`]; an error names the engines this build has.
    pub fn from_name(name: &str) -> Result<Engine, ModelError> {
        Self::available()
            .into_iter()
            .find(|e| e.name() == name)
            .ok_or_else(|| ModelError::UnknownEngine {
                name: name.to_string(),
                available: Self::available()
                    .iter()
                    .map(|e| e.name())
                    .collect::<Vec<_>>()
                    .join(", "),
            })
    }

    /// The engine to use when none is named: fused where it supports the field, else the
    /// default burn backend (a GPU when one is compiled in).
    pub fn for_field(config: &FieldConfig) -> Engine {
        if Engine::Fused.supports(config).is_ok() {
            Engine::Fused
        } else {
            Engine::Burn(Backend::default())
        }
    }

    /// Whether this engine has a device to run on here (see [`Backend::check_device`]).
    pub fn check_device(self) -> Result<(), ModelError> {
        match self {
            Engine::Fused => Ok(()),
            Engine::Burn(b) => b.check_device().map_err(|why| ModelError::NoDevice {
                engine: b.name(),
                why,
            }),
        }
    }

    /// The engines this build has that can run here: [`Engine::available`] less GPU backends
    /// without a device. Under CI (`CI=true`) every compiled-in engine must run: a missing
    /// device panics, naming it, so CI never passes without executing the GPU code path.
    pub fn usable() -> Vec<Engine> {
        let ci = std::env::var("CI").is_ok_and(|v| v == "true");
        Engine::available()
            .into_iter()
            .filter(|e| match e.check_device() {
                Ok(()) => true,
                Err(err) if ci => panic!("CI=true, but {err}"),
                Err(err) => {
                    eprintln!("skipping engine `{}`: {err}", e.name());
                    false
                }
            })
            .collect()
    }

    /// Whether this engine runs on a GPU (a burn GPU backend).
    pub fn is_gpu(self) -> bool {
        matches!(self, Engine::Burn(Backend::Wgpu | Backend::Cuda))
    }

    /// The engine that renders a field trained with `trained` when none is named: the same GPU
    /// when the field was trained on one this build has, else [`Engine::for_field`].
    pub fn for_rendering(trained: Option<Engine>, config: &FieldConfig) -> Engine {
        trained
            .filter(|e| e.is_gpu())
            .unwrap_or_else(|| Engine::for_field(config))
    }

    /// Whether this engine can run a field with `config`; the error names the option.
    pub fn supports(self, config: &FieldConfig) -> Result<(), ModelError> {
        match self {
            Engine::Fused => fused::supports(config),
            Engine::Burn(_) => Ok(()),
        }
    }

    /// Training options this engine cannot run: per-image exposure on burn.
    pub fn supports_train(self, config: &TrainConfig) -> Result<(), ModelError> {
        match self {
            Engine::Burn(_) if config.losses.exposure => Err(ModelError::Unsupported {
                engine: self.name(),
                what: "has no per-image exposure (`losses.exposure`); use backend fused".into(),
            }),
            _ => Ok(()),
        }
    }

    /// A trainer starting from the initial weights of `spec` with `config.field` as its
    /// architecture.
    pub fn trainer(
        self,
        config: &TrainConfig,
        spec: FieldSpec,
    ) -> Result<Box<dyn Trainer>, TrainError> {
        let spec = FieldSpec {
            config: config.field.clone(),
            ..spec
        };
        spec.validate()?;
        let rows = params::initial(&spec);
        self.trainer_from(config, spec, rows)
    }

    /// A trainer continuing from `weights` (fresh optimiser state).
    pub fn trainer_from(
        self,
        config: &TrainConfig,
        spec: FieldSpec,
        weights: Vec<NamedWeight>,
    ) -> Result<Box<dyn Trainer>, TrainError> {
        config.validate()?;
        spec.validate()?;
        if spec.config != config.field {
            return Err(TrainError::Config(
                "the field spec's config differs from the trainer's `field`".into(),
            ));
        }
        self.supports(&spec.config)?;
        self.supports_train(config)?;
        self.check_device()?;
        Ok(match self {
            Engine::Fused => Box::new(FusedTrainer::new(
                config.clone(),
                FusedField::from_weights(spec, weights)?,
            )?),
            Engine::Burn(b) => {
                let field = burn::RadianceField::from_weights(spec, &weights, &b.train_device())?;
                Box::new(burn::Trainer::from_field(config.clone(), field))
            }
        })
    }

    /// The field `spec` with trained `weights`, for inference.
    pub fn field(
        self,
        spec: FieldSpec,
        weights: Vec<NamedWeight>,
    ) -> Result<Box<dyn Field>, ModelError> {
        self.supports(&spec.config)?;
        self.check_device()?;
        Ok(match self {
            Engine::Fused => Box::new(FusedField::from_weights(spec, weights)?),
            Engine::Burn(b) => Box::new(burn::RadianceField::from_weights(
                spec,
                &weights,
                &b.device(),
            )?),
        })
    }
}

impl fmt::Display for Engine {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl Serialize for Engine {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl<'de> Deserialize<'de> for Engine {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        Engine::from_name(&name).map_err(serde::de::Error::custom)
    }
}

/// Every engine name, whether this build has it or not (the documented type; `pipe kinds`).
const ENGINE_NAMES: [&str; 5] = ["fused", "flex", "ndarray", "wgpu", "cuda"];

impl schemars::JsonSchema for Engine {
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "Engine".into()
    }
    fn json_schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
        schemars::json_schema!({ "type": "string", "enum": ENGINE_NAMES })
    }
}

impl schemars::JsonSchema for EngineChoice {
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "EngineChoice".into()
    }
    fn json_schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
        let mut names = vec![""];
        names.extend(ENGINE_NAMES);
        schemars::json_schema!({ "type": "string", "enum": names })
    }
}

/// An engine, or the best one for the field ([`Engine::for_field`]), written `""`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct EngineChoice(pub Option<Engine>);

impl EngineChoice {
    /// The chosen engine for a field with `config` trained with `trained`: the one named, else
    /// [`Engine::for_rendering`].
    pub fn resolve(self, config: &FieldConfig, trained: Option<Engine>) -> Engine {
        self.0
            .unwrap_or_else(|| Engine::for_rendering(trained, config))
    }
}

impl Serialize for EngineChoice {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.0.map_or("", Engine::name))
    }
}

impl<'de> Deserialize<'de> for EngineChoice {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        if name.is_empty() {
            return Ok(EngineChoice(None));
        }
        Engine::from_name(&name)
            .map(|e| EngineChoice(Some(e)))
            .map_err(serde::de::Error::custom)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_through_serde_and_unknown_ones_list_the_available() {
        for e in Engine::available() {
            let v = serde_json::to_value(e).unwrap();
            assert_eq!(v, serde_json::json!(e.name()));
            assert_eq!(serde_json::from_value::<Engine>(v).unwrap(), e);
        }
        assert_eq!(serde_json::to_value(Engine::default()).unwrap(), "fused");
        let err = serde_json::from_value::<Engine>(serde_json::json!("tpu")).unwrap_err();
        assert!(
            err.to_string()
                .contains("`tpu` is not compiled in (available: fused, "),
            "{err}"
        );
        assert_eq!(serde_json::to_value(EngineChoice(None)).unwrap(), "");
        let c: EngineChoice = serde_json::from_value(serde_json::json!("")).unwrap();
        assert_eq!(c, EngineChoice(None));
        let c: EngineChoice = serde_json::from_value(serde_json::json!("fused")).unwrap();
        assert_eq!(c.0, Some(Engine::Fused));
    }

    #[test]
    fn rendering_runs_on_the_gpu_the_field_was_trained_on() {
        let grid = FieldConfig::default();
        for gpu in [Backend::Wgpu, Backend::Cuda] {
            let e = Engine::Burn(gpu);
            assert_eq!(Engine::for_rendering(Some(e), &grid), e);
            assert_eq!(EngineChoice(None).resolve(&grid, Some(e)), e);
            assert_eq!(
                EngineChoice(Some(Engine::Fused)).resolve(&grid, Some(e)),
                Engine::Fused,
                "a named engine wins"
            );
        }
        // Trained on a CPU engine (or one this build lacks): the best CPU engine renders.
        for trained in [None, Some(Engine::Burn(Backend::Flex)), Some(Engine::Fused)] {
            assert_eq!(Engine::for_rendering(trained, &grid), Engine::Fused);
        }
    }

    #[test]
    fn per_image_exposure_is_the_fused_engine_s_alone() {
        let mut config = TrainConfig::default();
        config.losses.exposure = true;
        assert!(Engine::Fused.supports_train(&config).is_ok());
        let err = Engine::Burn(Backend::default())
            .supports_train(&config)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains(&format!("`backend: {}`", Backend::default().name()))
                && err.contains("`losses.exposure`"),
            "{err}"
        );
        assert!(Engine::Burn(Backend::default())
            .supports_train(&TrainConfig::default())
            .is_ok());
    }

    #[test]
    fn the_documented_engine_names_are_every_engine() {
        let mut names: Vec<&str> = vec!["fused"];
        names.extend(super::super::burn::Backend::ALL.iter().map(|b| b.name()));
        assert_eq!(names, ENGINE_NAMES);
    }

    #[test]
    fn the_automatic_choice_falls_back_to_burn_for_what_fused_lacks() {
        assert_eq!(Engine::for_field(&FieldConfig::default()), Engine::Fused);
        let pe = FieldConfig::pe();
        assert_eq!(Engine::for_field(&pe), Engine::Burn(Backend::default()));
        let err = Engine::Fused.supports(&pe).unwrap_err().to_string();
        assert!(
            err.contains("`backend: fused`") && err.contains("grid"),
            "{err}"
        );
    }
}
