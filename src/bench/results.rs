//! The bench's results in long form, one row per (scene, variant, budget, method, metric), read
//! from the cache after the run: the `evaluate` stage's `metrics` table, and each stage's wall
//! time, CPU time and peak RSS from its manifest (method `stage:ROLE`). Written as
//! `results.parquet` (readable with pandas / pyarrow).

use std::{collections::BTreeMap, sync::Arc};

use anyhow::{anyhow, Context, Result};
use arrow::{
    array::{Array, ArrayRef, Float64Array, StringArray, UInt64Array},
    datatypes::{DataType, Field, Schema},
    record_batch::RecordBatch,
};

use super::plan::Plan;
use crate::store::{Entry, Manifest, Store};

/// One result.
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    pub scene: String,
    pub variant: String,
    pub budget: u64,
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
pub fn manifests(store: &Store, keys: &BTreeMap<String, String>) -> Result<Manifests> {
    keys.iter()
        .map(|(stage, key)| match store.check(key, false) {
            Entry::Valid(m) => Ok((stage.clone(), m)),
            Entry::Missing => Err(anyhow!("stage `{stage}`: cache entry {key} is missing")),
            Entry::Corrupt(why) => Err(anyhow!("stage `{stage}`: cache entry corrupt: {why}")),
        })
        .collect()
}

fn strings<'a>(b: &'a RecordBatch, col: &str) -> Result<&'a StringArray> {
    b.column_by_name(col)
        .and_then(|c| c.as_any().downcast_ref::<StringArray>())
        .ok_or_else(|| anyhow!("metrics table: no utf8 column `{col}`"))
}

/// Every row of the bench, in plan order.
pub fn collect(plan: &Plan, store: &Store, m: &Manifests) -> Result<Vec<Row>> {
    let mut rows = Vec::new();
    for run in &plan.runs {
        let train_wall_s = m[&run.instances[&plan.train_role]].wall_s;
        let row = |method: &str, metric: &str, value: Option<f64>| Row {
            scene: run.scene.clone(),
            variant: run.variant.clone(),
            budget: run.budget,
            method: method.to_string(),
            metric: metric.to_string(),
            value,
            train_wall_s,
        };
        let eval = &m[&run.instances[&plan.eval_role]];
        let tables = store
            .load(eval)
            .with_context(|| format!("loading {}", run.instances[&plan.eval_role]))?;
        let t = tables
            .get("metrics")
            .ok_or_else(|| anyhow!("stage `{}` wrote no `metrics` table", plan.eval_role))?;
        let (method, metric) = (strings(t, "method")?, strings(t, "metric")?);
        let value = t
            .column_by_name("value")
            .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
            .ok_or_else(|| anyhow!("metrics table: no float64 column `value`"))?;
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

/// The value of one metric of one run, if present and not null.
pub fn value(
    rows: &[Row],
    scene: &str,
    variant: &str,
    budget: u64,
    method: &str,
    metric: &str,
) -> Option<f64> {
    rows.iter()
        .find(|r| {
            r.scene == scene
                && r.variant == variant
                && r.budget == budget
                && r.method == method
                && r.metric == metric
        })
        .and_then(|r| r.value)
}

/// The rows as one Arrow batch (the schema of `results.parquet`).
pub fn to_batch(rows: &[Row]) -> Result<RecordBatch> {
    let schema = Schema::new(vec![
        Field::new("scene", DataType::Utf8, false),
        Field::new("variant", DataType::Utf8, false),
        Field::new("budget", DataType::UInt64, false),
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
        s(|r| &r.method),
        s(|r| &r.metric),
        Arc::new(Float64Array::from_iter(rows.iter().map(|r| r.value))),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.train_wall_s),
        )),
    ];
    Ok(RecordBatch::try_new(Arc::new(schema), cols)?)
}
