//! `metrics.json`: the evaluate stage's tables as JSON.

use arrow::{
    array::{Array, Float64Array},
    datatypes::UInt64Type,
    record_batch::RecordBatch,
};

use crate::{tables, Result, StageError, Tables};

/// `[{group, bin, pixels, rmse, mean_error, delta_1_25, share_sq_error}]` from the
/// `depth_breakdown` table.
pub fn depth_breakdown_json(t: &RecordBatch) -> Result<serde_json::Value> {
    let table = "depth_breakdown";
    let group = tables::get_strings(t, table, "group")?;
    let bin = tables::get_strings(t, table, "bin")?;
    let pixels = tables::get_prim::<UInt64Type>(t, table, "pixels")?;
    let mut out = Vec::new();
    for (i, &px) in pixels.iter().enumerate() {
        let mut row = serde_json::json!({
            "group": group.value(i),
            "bin": bin.value(i),
            "pixels": px,
        });
        for col in ["rmse", "mean_error", "delta_1_25", "share_sq_error"] {
            let v = t
                .column_by_name(col)
                .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
                .ok_or_else(|| StageError::Input(format!("{table}.{col} is not float64")))?;
            row[col] = value_at(v, i);
        }
        out.push(row);
    }
    Ok(serde_json::Value::Array(out))
}

/// `{camera model: {method: {metric: value, ..., "class_iou": {class name: iou}}}}` from the
/// `camera_metrics` and `camera_class_iou` tables.
pub fn camera_metrics_json(t: &RecordBatch, classes: &RecordBatch) -> Result<serde_json::Value> {
    let mut out = grouped_json(t, "camera_metrics", "camera_model")?;
    add_class_iou(&mut out, classes, "camera_class_iou")?;
    Ok(out)
}

/// `{part: {method: {metric: value}}}` from the `motion_metrics` table (static and moving
/// pixels; empty where the scene has no moving objects).
pub fn motion_metrics_json(t: &RecordBatch) -> Result<serde_json::Value> {
    grouped_json(t, "motion_metrics", "part")
}

/// `{group: {method: {metric: value}}}` from a metrics table with a first column `key`.
fn grouped_json(t: &RecordBatch, table: &str, key: &str) -> Result<serde_json::Value> {
    let groups = tables::get_strings(t, table, key)?;
    let methods = tables::get_strings(t, table, "method")?;
    let metrics = tables::get_strings(t, table, "metric")?;
    let values = t
        .column_by_name("value")
        .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
        .ok_or_else(|| StageError::Input(format!("{table}.value is not float64")))?;
    let mut out = serde_json::json!({});
    for i in 0..t.num_rows() {
        entry_of(entry_of(&mut out, groups.value(i)), methods.value(i))[metrics.value(i)] =
            value_at(values, i);
    }
    Ok(out)
}

/// `{method: {metric: value, ..., "class_iou": {class name: iou}}}` from the stage's tables.
pub fn metrics_json(t: &Tables) -> Result<serde_json::Value> {
    let get = |name: &str| {
        t.get(name)
            .ok_or_else(|| StageError::Input(format!("evaluate output lacks table `{name}`")))
    };
    let m = get("metrics")?;
    let methods = tables::get_strings(m, "metrics", "method")?;
    let metrics = tables::get_strings(m, "metrics", "metric")?;
    let values = m
        .column_by_name("value")
        .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
        .ok_or_else(|| StageError::Input("metrics.value is not float64".into()))?;
    let mut out = serde_json::json!({});
    for i in 0..m.num_rows() {
        entry_of(&mut out, methods.value(i))[metrics.value(i)] = value_at(values, i);
    }
    add_class_iou(&mut out, get("class_iou")?, "class_iou")?;
    Ok(out)
}

/// Adds `"class_iou": {class name: iou}` under each method of `out` (under each camera model,
/// then method, for the `camera_class_iou` table).
fn add_class_iou(out: &mut serde_json::Value, c: &RecordBatch, table: &str) -> Result<()> {
    let models = if table == "camera_class_iou" {
        Some(tables::get_strings(c, table, "camera_model")?)
    } else {
        None
    };
    let cm = tables::get_strings(c, table, "method")?;
    let cn = tables::get_strings(c, table, "name")?;
    let ci = c
        .column_by_name("iou")
        .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
        .ok_or_else(|| StageError::Input(format!("{table}.iou is not float64")))?;
    for i in 0..c.num_rows() {
        let mut entry = &mut *out;
        if let Some(models) = models {
            entry = entry_of(entry, models.value(i));
        }
        let entry = entry_of(entry_of(entry, cm.value(i)), "class_iou");
        entry[cn.value(i)] = value_at(ci, i);
    }
    Ok(())
}

/// Row `i` of `col` as JSON: null where the column is null.
fn value_at(col: &Float64Array, i: usize) -> serde_json::Value {
    if col.is_null(i) {
        serde_json::Value::Null
    } else {
        serde_json::json!(col.value(i))
    }
}

/// `v[key]`, made an empty object first where absent.
fn entry_of<'v>(v: &'v mut serde_json::Value, key: &str) -> &'v mut serde_json::Value {
    v.as_object_mut()
        .expect("an object")
        .entry(key)
        .or_insert_with(|| serde_json::json!({}))
}
