//! The trained model as tables: the `weights` table (`name`, `shape`, `values` rows, readable
//! from pyarrow) and the `model` table (the spec and sampling needed to rebuild and render the
//! field, its classes, the engine that trained it). Any engine reads what any engine wrote.

use arrow::array::Array;
use arrow::datatypes::{Float32Type, UInt32Type, UInt8Type};
use arrow::record_batch::RecordBatch;
use serde::{Deserialize, Serialize};

use super::config::FieldSpec;
use super::engine::Engine;
use super::params::NamedWeight;
use crate::sampling::SamplingParams;
use crate::stage::{Result, StageError};
use crate::tables;

/// The model description stored beside the weights.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ModelInfo {
    pub spec: FieldSpec,
    pub sampling: SamplingParams,
    /// Label ids of the semantic head's classes (sky last).
    pub classes: Vec<u8>,
}

/// The `weights` table of `rows`.
pub fn weights_table(rows: &[NamedWeight]) -> Result<RecordBatch> {
    tables::build(
        "weights",
        vec![
            tables::strings(rows.iter().map(|x| x.name.as_str())),
            tables::list::<UInt32Type>(
                rows.iter()
                    .map(|x| x.shape.iter().map(|&s| s as u32).collect()),
            ),
            tables::list::<Float32Type>(rows.iter().map(|x| x.values.clone())),
        ],
    )
}

/// The `model` table: `info` as JSON, the classes, the engine's name.
pub fn model_table(info: &ModelInfo, engine: Engine) -> Result<RecordBatch> {
    tables::build(
        "model",
        vec![
            tables::strings([
                serde_json::to_string(info).map_err(|e| StageError::Failed(e.to_string()))?
            ]),
            tables::list::<UInt8Type>([info.classes.clone()]),
            tables::strings([engine.name()]),
        ],
    )
}

/// The engine a model was trained with, if this build has it.
pub fn trained_engine(model: &RecordBatch) -> Result<Option<Engine>> {
    let names = tables::get_strings(model, "model", "backend")?;
    Ok((!names.is_empty())
        .then(|| Engine::from_name(names.value(0)).ok())
        .flatten())
}

/// Reads a trained model back from its `weights` and `model` tables.
pub fn read(weights: &RecordBatch, model: &RecordBatch) -> Result<(ModelInfo, Vec<NamedWeight>)> {
    let info_col = tables::get_strings(model, "model", "info")?;
    if info_col.is_empty() {
        return Err(StageError::Input("table `model` is empty".into()));
    }
    let info: ModelInfo = serde_json::from_str(info_col.value(0))
        .map_err(|e| StageError::Input(format!("table `model` column `info`: {e}")))?;
    let names = tables::get_strings(weights, "weights", "name")?;
    let shapes = tables::get_list::<UInt32Type>(weights, "weights", "shape")?;
    let values = tables::get_list::<Float32Type>(weights, "weights", "values")?;
    let rows = (0..weights.num_rows())
        .map(|i| NamedWeight {
            name: names.value(i).to_string(),
            shape: shapes.row(i).iter().map(|&s| s as usize).collect(),
            values: values.row(i).to_vec(),
        })
        .collect();
    Ok((info, rows))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{params, FieldConfig};

    #[test]
    fn tables_round_trip_the_rows_and_the_info() {
        let spec = FieldSpec {
            config: FieldConfig::default(),
            num_classes: 3,
            aabb_min: [-1.0; 3],
            aabb_max: [2.0; 3],
            seed: 4,
        };
        let rows = params::initial(&spec);
        let info = ModelInfo {
            spec: spec.clone(),
            sampling: SamplingParams::default(),
            classes: vec![7, 26, 23],
        };
        let w = weights_table(&rows).unwrap();
        let m = model_table(&info, Engine::Fused).unwrap();
        let (back, got) = read(&w, &m).unwrap();
        assert_eq!(got, rows);
        assert_eq!(back.spec, spec);
        assert_eq!(back.classes, info.classes);
        assert_eq!(
            tables::get_strings(&m, "model", "backend")
                .unwrap()
                .value(0),
            "fused"
        );
    }
}
