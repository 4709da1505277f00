//! The bench's results in long form, one row per (scene, variant, budget, seed, method, metric), read
//! from the cache after the run: the scoring stage's score table (`ScoreSpec::table`, columns
//! method, metric, value), and each stage's wall time, CPU time and peak RSS from its manifest
//! (method `stage:ROLE`). Written as `results.parquet` (readable with pandas / pyarrow).

use std::{collections::BTreeMap, sync::Arc};

use arrow::{
    array::{Array, ArrayRef, Float64Array, StringArray, UInt64Array},
    datatypes::{DataType, Field, Schema},
    record_batch::RecordBatch,
};

use super::{error::BenchError, plan::Plan};
use crate::store::{Entry, Manifest, Store};

/// One result.
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    pub scene: String,
    pub variant: String,
    pub budget: u64,
    /// The run's seed (`None`: the suite has no `seeds:`).
    pub seed: Option<u64>,
    pub method: String,
    pub metric: String,
    pub value: Option<f64>,
    /// Wall time of this run's training stage, seconds (from its cache entry).
    pub train_wall_s: f64,
}

/// Prefix of the `method` of stage timing rows.
pub const STAGE_PREFIX: &str = "stage:";

/// Per stage instance: its manifest (times, memory, params).
pub type Manifests = BTreeMap<String, Box<Manifest>>;

/// The manifest of every stage instance of the plan, from the run's keys.
pub fn manifests(store: &Store, keys: &BTreeMap<String, String>) -> Result<Manifests, BenchError> {
    keys.iter()
        .map(|(stage, key)| match store.check(key, false) {
            Entry::Valid(m) => Ok((stage.clone(), m)),
            Entry::Missing => Err(BenchError::MissingEntry {
                stage: stage.clone(),
                key: key.clone(),
            }),
            Entry::Corrupt(why) => Err(BenchError::CorruptEntry {
                stage: stage.clone(),
                why,
            }),
        })
        .collect()
}

fn column<'a, T: 'static>(
    b: &'a RecordBatch,
    table: &str,
    col: &str,
    ty: &'static str,
) -> Result<&'a T, BenchError> {
    b.column_by_name(col)
        .and_then(|c| c.as_any().downcast_ref::<T>())
        .ok_or_else(|| BenchError::ScoreColumn {
            table: table.to_string(),
            ty,
            column: col.to_string(),
        })
}

/// Every row of the bench, in plan order.
pub fn collect(plan: &Plan, store: &Store, m: &Manifests) -> Result<Vec<Row>, BenchError> {
    let table = plan.spec.table;
    let mut rows = Vec::new();
    for run in &plan.runs {
        let train_wall_s = m[&run.instances[&plan.train_role]].wall_s;
        let row = |method: &str, metric: &str, value: Option<f64>| Row {
            scene: run.scene.clone(),
            variant: run.variant.clone(),
            budget: run.budget,
            seed: run.seed,
            method: method.to_string(),
            metric: metric.to_string(),
            value,
            train_wall_s,
        };
        let eval = &m[&run.instances[&plan.eval_role]];
        let tables = store.load(eval).map_err(|source| BenchError::Load {
            stage: run.instances[&plan.eval_role].clone(),
            source,
        })?;
        let t = tables.get(table).ok_or_else(|| BenchError::NoScoreTable {
            stage: plan.eval_role.clone(),
            table: table.to_string(),
        })?;
        let method = column::<StringArray>(t, table, "method", "utf8")?;
        let metric = column::<StringArray>(t, table, "metric", "utf8")?;
        let value = column::<Float64Array>(t, table, "value", "float64")?;
        for i in 0..t.num_rows() {
            let v = (!value.is_null(i)).then(|| value.value(i));
            rows.push(row(method.value(i), metric.value(i), v));
        }
        for r in &plan.roles {
            let s = &m[&run.instances[r]];
            let method = format!("{STAGE_PREFIX}{r}");
            rows.push(row(&method, "wall_s", Some(s.wall_s)));
            rows.push(row(&method, "cpu_s", Some(s.cpu_s)));
            rows.push(row(
                &method,
                "peak_rss_bytes",
                Some(s.peak_rss_bytes as f64),
            ));
        }
    }
    Ok(rows)
}

/// One metric over the seeds of a (scene, variant, budget): the mean, the sample standard
/// deviation (0 for one seed) and how many seeds had a value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spread {
    pub mean: f64,
    pub sd: f64,
    pub n: usize,
}

/// [`Spread`] of one metric of one (scene, variant, budget) over its seeds; `None` where no
/// seed has a value.
pub fn spread(
    rows: &[Row],
    scene: &str,
    variant: &str,
    budget: u64,
    method: &str,
    metric: &str,
) -> Option<Spread> {
    let vs: Vec<f64> = rows
        .iter()
        .filter(|r| {
            r.scene == scene
                && r.variant == variant
                && r.budget == budget
                && r.method == method
                && r.metric == metric
        })
        .filter_map(|r| r.value)
        .collect();
    let n = vs.len();
    if n == 0 {
        return None;
    }
    let mean = vs.iter().sum::<f64>() / n as f64;
    let sd = if n > 1 {
        (vs.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt()
    } else {
        0.0
    };
    Some(Spread { mean, sd, n })
}

/// The rows as one Arrow batch (the schema of `results.parquet`).
pub fn to_batch(rows: &[Row]) -> Result<RecordBatch, BenchError> {
    let schema = Schema::new(vec![
        Field::new("scene", DataType::Utf8, false),
        Field::new("variant", DataType::Utf8, false),
        Field::new("budget", DataType::UInt64, false),
        Field::new("seed", DataType::UInt64, true),
        Field::new("method", DataType::Utf8, false),
        Field::new("metric", DataType::Utf8, false),
        Field::new("value", DataType::Float64, true),
        Field::new("train_wall_s", DataType::Float64, false),
    ]);
    let s = |f: fn(&Row) -> &str| -> ArrayRef {
        Arc::new(StringArray::from_iter_values(rows.iter().map(f)))
    };
    let cols: Vec<ArrayRef> = vec![
        s(|r| &r.scene),
        s(|r| &r.variant),
        Arc::new(UInt64Array::from_iter_values(rows.iter().map(|r| r.budget))),
        Arc::new(UInt64Array::from_iter(rows.iter().map(|r| r.seed))),
        s(|r| &r.method),
        s(|r| &r.metric),
        Arc::new(Float64Array::from_iter(rows.iter().map(|r| r.value))),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.train_wall_s),
        )),
    ];
    Ok(RecordBatch::try_new(Arc::new(schema), cols)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(seed: Option<u64>, metric: &str, value: Option<f64>) -> Row {
        Row {
            scene: "a".into(),
            variant: "v".into(),
            budget: 5,
            seed,
            method: "m".into(),
            metric: metric.into(),
            value,
            train_wall_s: 1.0,
        }
    }

    #[test]
    fn spread_is_the_mean_and_sample_deviation_over_seeds() {
        let rows = [
            row(Some(0), "x", Some(1.0)),
            row(Some(1), "x", Some(2.0)),
            row(Some(2), "x", Some(6.0)),
            row(Some(3), "x", None),
            row(None, "y", Some(4.0)),
        ];
        let s = spread(&rows, "a", "v", 5, "m", "x").unwrap();
        assert_eq!((s.mean, s.n), (3.0, 3));
        // Deviations -2, -1, 3: (4 + 1 + 9) / 2 = 7.
        assert!((s.sd - 7f64.sqrt()).abs() < 1e-12, "{}", s.sd);
        let one = spread(&rows, "a", "v", 5, "m", "y").unwrap();
        assert_eq!((one.mean, one.sd, one.n), (4.0, 0.0, 1));
        assert_eq!(spread(&rows, "a", "v", 6, "m", "x"), None);
        assert_eq!(spread(&rows[3..4], "a", "v", 5, "m", "x"), None);
    }
}
