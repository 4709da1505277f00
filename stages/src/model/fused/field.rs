//! The fused engine's view of the field: the parameter rows and where each layer lives in them.

use crate::model::config::{EncodingKind, FieldConfig, FieldSpec};
use crate::model::encoding::level_info;
use crate::model::error::ModelError;
use crate::model::params::{self, NamedWeight};

use super::mlp::Layer;

/// Field options this engine cannot run: the `pe` encoding (the fused kernels read a grid).
pub fn supports(config: &FieldConfig) -> Result<(), ModelError> {
    if config.encoding != EncodingKind::Grid {
        return Err(ModelError::Unsupported {
            engine: "fused",
            what: "supports `field.encoding: grid` only; use backend flex for pe".into(),
        });
    }
    Ok(())
}

/// Ray partitions of a step: fixed, so results do not depend on the number of threads. Many
/// small ones keep a partition's activations in cache (2048 samples at 4096 rays x 32) and
/// balance the threads' load.
pub const PARTITIONS: usize = 64;

/// The grid field's parameters as flat rows ([`params::layout`]), with each layer's place.
#[derive(Debug, Clone)]
pub struct FusedField {
    pub spec: FieldSpec,
    /// Parameters in the burn module's order and naming (`grid.table`, `trunk.layers.0.weight`).
    pub weights: Vec<NamedWeight>,
    pub(super) grid: usize,
    pub(super) trunk: Vec<Layer>,
    pub(super) colour: Vec<Layer>,
    pub(super) semantic: Vec<Layer>,
    pub(super) levels: Vec<(u32, bool)>,
}

impl FusedField {
    /// Builds the layout from named rows (checked against [`params::layout`]); the `pe`
    /// encoding is not supported.
    pub fn from_weights(spec: FieldSpec, weights: Vec<NamedWeight>) -> Result<Self, ModelError> {
        supports(&spec.config)?;
        params::check(&spec, &weights)?;
        let find = |name: &str| params::index(&weights, name);
        let grid = find("grid.table").expect("checked");
        let mlp = |prefix: &str| -> Vec<Layer> {
            let mut layers = Vec::new();
            while let Some(w) = find(&format!("{prefix}.layers.{}.weight", layers.len())) {
                let b = find(&format!("{prefix}.layers.{}.bias", layers.len())).expect("checked");
                let shape = &weights[w].shape;
                layers.push(Layer {
                    weight: w,
                    bias: b,
                    inputs: shape[0],
                    outputs: shape[1],
                });
            }
            layers
        };
        let (trunk, colour, semantic) = (mlp("trunk"), mlp("colour"), mlp("semantic"));
        let levels = level_info(&spec.config.grid);
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

    /// The initial field of `spec` ([`params::initial`]).
    pub fn init(spec: FieldSpec) -> Result<Self, ModelError> {
        let rows = params::initial(&spec);
        Self::from_weights(spec, rows)
    }

    pub(super) fn params(&self) -> Vec<&[f32]> {
        self.weights.iter().map(|w| w.values.as_slice()).collect()
    }
}
