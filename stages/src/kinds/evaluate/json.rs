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
            row[col] = if v.is_null(i) {
                serde_json::Value::Null
            } else {
                serde_json::json!(v.value(i))
            };
        }
        out.push(row);
    }
    Ok(serde_json::Value::Array(out))
}

/// `{camera model: {method: {metric: value}}}` from the `camera_metrics` table.
pub fn camera_metrics_json(t: &RecordBatch) -> Result<serde_json::Value> {
    let models = tables::get_strings(t, "camera_metrics", "camera_model")?;
    let methods = tables::get_strings(t, "camera_metrics", "method")?;
    let metrics = tables::get_strings(t, "camera_metrics", "metric")?;
    let values = t
        .column_by_name("value")
        .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
        .ok_or_else(|| StageError::Input("camera_metrics.value is not float64".into()))?;
    let mut out = serde_json::json!({});
    for i in 0..t.num_rows() {
        let v = if values.is_null(i) {
            serde_json::Value::Null
        } else {
            serde_json::json!(values.value(i))
        };
        let model = out
            .as_object_mut()
            .expect("an object")
            .entry(models.value(i))
            .or_insert_with(|| serde_json::json!({}));
        let method = model
            .as_object_mut()
            .expect("an object")
            .entry(methods.value(i))
            .or_insert_with(|| serde_json::json!({}));
        method[metrics.value(i)] = v;
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
    let mut out = serde_json::Map::new();
    for i in 0..m.num_rows() {
        let entry = out
            .entry(methods.value(i).to_string())
            .or_insert_with(|| serde_json::json!({}));
        let v = if values.is_null(i) {
            serde_json::Value::Null
        } else {
            serde_json::json!(values.value(i))
        };
        entry[metrics.value(i)] = v;
    }
    let c = get("class_iou")?;
    let cm = tables::get_strings(c, "class_iou", "method")?;
    let cn = tables::get_strings(c, "class_iou", "name")?;
    let ci = c
        .column_by_name("iou")
        .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
        .ok_or_else(|| StageError::Input("class_iou.iou is not float64".into()))?;
    for i in 0..c.num_rows() {
        let entry = out
            .entry(cm.value(i).to_string())
            .or_insert_with(|| serde_json::json!({}));
        if entry.get("class_iou").is_none() {
            entry["class_iou"] = serde_json::json!({});
        }
        entry["class_iou"][cn.value(i)] = if ci.is_null(i) {
            serde_json::Value::Null
        } else {
            serde_json::json!(ci.value(i))
        };
    }
    Ok(serde_json::Value::Object(out))
}
