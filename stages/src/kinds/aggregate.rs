//! The `aggregate` stage kind: dataset-level results. It reads the `metrics` tables of every
//! scene of a scene matrix (a gathered input: the runner hands it all scenes' rows with a
//! leading `scene` column) and writes `dataset_metrics`: each scene's rows and the mean over
//! scenes, the way the paper's tables report a data set. `pipe export` writes the summary as
//! Markdown (`summary.md`) and JSON (`summary.json`).

use std::{collections::BTreeMap, path::Path, path::PathBuf, sync::Arc};

use arrow::{
    array::{Array, ArrayRef, Float64Array},
    datatypes::Int64Type,
};
use serde::{Deserialize, Serialize};

use crate::{
    tables, InputSlot, Inputs, Progress, Result, StageError, TableSet, Tables, TypedStage,
};

/// The scene name of the mean rows.
pub const MEAN: &str = "mean";

#[derive(Debug, Clone, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct AggregateParams {
    /// Metrics shown as columns of the exported Markdown tables (all stay in the table).
    pub columns: Vec<String>,
    /// Methods given a Markdown table each, in this order (empty: every method).
    pub methods: Vec<String>,
}

impl Default for AggregateParams {
    fn default() -> Self {
        let s = |v: &[&str]| v.iter().map(|x| x.to_string()).collect();
        Self {
            columns: s(&[
                "miou",
                "acc",
                "pq",
                "pq_things",
                "pq_stuff",
                "mc",
                "depth_rmse",
                "depth_delta_1_25",
            ]),
            methods: s(&[
                "panoptic_nerf",
                "fixed_field",
                "pseudo_labels",
                "first_primitive",
            ]),
        }
    }
}

/// One value of the data set: (scene, method, metric) -> value.
type Cells = BTreeMap<(String, String, String), Option<f64>>;

/// Mean over scenes of every (method, metric): the rows of scene [`MEAN`].
struct Summary {
    scenes: Vec<String>,
    /// (method, metric) in first-seen order.
    keys: Vec<(String, String)>,
    cells: Cells,
    means: BTreeMap<(String, String), (Option<f64>, i64)>,
}

fn summarise(scene: &[&str], method: &[&str], metric: &[&str], value: &[Option<f64>]) -> Summary {
    let mut scenes: Vec<String> = Vec::new();
    let mut keys: Vec<(String, String)> = Vec::new();
    let mut cells = Cells::new();
    for i in 0..scene.len() {
        if !scenes.iter().any(|s| s == scene[i]) {
            scenes.push(scene[i].to_string());
        }
        let k = (method[i].to_string(), metric[i].to_string());
        if !keys.contains(&k) {
            keys.push(k.clone());
        }
        cells.insert((scene[i].to_string(), k.0, k.1), value[i]);
    }
    let mut means = BTreeMap::new();
    for (m, k) in &keys {
        let vals: Vec<f64> = scenes
            .iter()
            .filter_map(|s| {
                cells
                    .get(&(s.clone(), m.clone(), k.clone()))
                    .copied()
                    .flatten()
            })
            .filter(|v| v.is_finite())
            .collect();
        let mean = (!vals.is_empty()).then(|| vals.iter().sum::<f64>() / vals.len() as f64);
        means.insert((m.clone(), k.clone()), (mean, vals.len() as i64));
    }
    Summary {
        scenes,
        keys,
        cells,
        means,
    }
}

fn read_summary(t: &arrow::record_batch::RecordBatch, table: &str, has_n: bool) -> Result<Summary> {
    let col = |c: &str| tables::get_strings(t, table, c);
    let scene = col("scene").map_err(|_| {
        StageError::Input(format!(
            "table `{table}` has no `scene` column: `aggregate` reads every scene's metrics, so declare it under `dataset:` of a pipeline with `scenes:`"
        ))
    })?;
    let (method, metric) = (col("method")?, col("metric")?);
    let value = t
        .column_by_name("value")
        .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
        .ok_or_else(|| StageError::Input(format!("{table}.value is not float64")))?;
    fn strs(a: &arrow::array::StringArray) -> Vec<&str> {
        (0..a.len()).map(|i| a.value(i)).collect()
    }
    let (sc, me, mt) = (strs(scene), strs(method), strs(metric));
    let vals: Vec<Option<f64>> = (0..value.len())
        .map(|i| (!value.is_null(i)).then(|| value.value(i)))
        .collect();
    // Exported tables already hold the mean rows: summarise the scene rows only.
    let keep: Vec<usize> = (0..sc.len()).filter(|&i| !has_n || sc[i] != MEAN).collect();
    fn pick<'a>(keep: &[usize], v: &[&'a str]) -> Vec<&'a str> {
        keep.iter().map(|&i| v[i]).collect()
    }
    let vals: Vec<Option<f64>> = keep.iter().map(|&i| vals[i]).collect();
    Ok(summarise(
        &pick(&keep, &sc),
        &pick(&keep, &me),
        &pick(&keep, &mt),
        &vals,
    ))
}

/// Metrics in [0, 1] are shown in percent; depth RMSE in metres; counts as they are.
fn show(metric: &str, v: Option<f64>) -> String {
    match v {
        None => "-".into(),
        Some(v) if metric == "depth_rmse" => format!("{v:.3}"),
        Some(v) if metric == "frames" || metric == "pixels" => format!("{v:.0}"),
        Some(v) => format!("{:.1}", v * 100.0),
    }
}

/// Mean over scenes of every scene's evaluation metrics.
pub struct Aggregate;

impl TypedStage for Aggregate {
    type Params = AggregateParams;
    const KIND: &'static str = "aggregate";
    const VERSION: u32 = 1;
    const DESCRIPTION: &'static str =
        "dataset-level metrics: every scene's evaluation metrics and their mean over scenes (a `dataset:` stage of a scene matrix)";
    const INPUTS: &'static [InputSlot] = &[InputSlot {
        name: "evaluate",
        tables: &["metrics"],
        optional: false,
        doc: "the evaluate stage of every scene (gathered)",
    }];
    const OUTPUTS: &'static [&'static str] = &["dataset_metrics"];

    fn run(&self, _: &AggregateParams, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        let t = inputs.table("evaluate", "metrics")?;
        let s = read_summary(t, "metrics", false)?;
        progress.update(0, 1, &format!("{} scenes", s.scenes.len()));
        let (mut sc, mut me, mut mt, mut va, mut n) = (vec![], vec![], vec![], vec![], vec![]);
        let mut push = |scene: &str, m: &str, k: &str, v: Option<f64>, c: i64| {
            sc.push(scene.to_string());
            me.push(m.to_string());
            mt.push(k.to_string());
            va.push(v);
            n.push(c);
        };
        for scene in &s.scenes {
            for (m, k) in &s.keys {
                if let Some(v) = s.cells.get(&(scene.clone(), m.clone(), k.clone())) {
                    push(scene, m, k, *v, 1);
                }
            }
        }
        for (m, k) in &s.keys {
            let (v, c) = s.means[&(m.clone(), k.clone())];
            push(MEAN, m, k, v, c);
        }
        let out = tables::build(
            "dataset_metrics",
            vec![
                tables::strings(sc),
                tables::strings(me),
                tables::strings(mt),
                Arc::new(Float64Array::from(va)) as ArrayRef,
                tables::prim::<Int64Type>(n),
            ],
        )?;
        progress.update(1, 1, "done");
        Ok(Tables::from([("dataset_metrics".to_string(), out)]))
    }

    fn export(&self, p: &AggregateParams, t: &TableSet, dir: &Path) -> Result<Vec<PathBuf>> {
        let table = t.table("dataset_metrics")?;
        let s = read_summary(table, "dataset_metrics", true)?;
        let mut methods: Vec<String> = s.keys.iter().map(|(m, _)| m.clone()).collect();
        methods.dedup();
        if !p.methods.is_empty() {
            methods.retain(|m| p.methods.contains(m));
            methods.sort_by_key(|m| p.methods.iter().position(|x| x == m));
        }
        let mut md = format!(
            "# Dataset results\n\n{} scenes: {}. Semantic and panoptic metrics in %, depth RMSE in metres; `mean` is the mean over the scenes that have a value.\n",
            s.scenes.len(),
            s.scenes.join(", ")
        );
        let mut json = serde_json::Map::new();
        for m in &methods {
            let cols: Vec<&String> = p
                .columns
                .iter()
                .filter(|k| s.means.contains_key(&(m.clone(), k.to_string())))
                .collect();
            md.push_str(&format!("\n## {m}\n\n| scene |"));
            for k in &cols {
                md.push_str(&format!(" {k} |"));
            }
            md.push_str("\n| --- |");
            md.push_str(&" ---: |".repeat(cols.len()));
            md.push('\n');
            let mut per_scene = serde_json::Map::new();
            for scene in &s.scenes {
                md.push_str(&format!("| {scene} |"));
                let mut row = serde_json::Map::new();
                for k in &cols {
                    let v = s
                        .cells
                        .get(&(scene.clone(), m.clone(), k.to_string()))
                        .copied()
                        .flatten();
                    md.push_str(&format!(" {} |", show(k, v)));
                }
                for (mm, k) in &s.keys {
                    if mm == m {
                        let v = s
                            .cells
                            .get(&(scene.clone(), m.clone(), k.clone()))
                            .copied()
                            .flatten();
                        row.insert(k.clone(), serde_json::json!(v));
                    }
                }
                md.push('\n');
                per_scene.insert(scene.clone(), row.into());
            }
            md.push_str(&format!("| **{MEAN}** |"));
            for k in &cols {
                let (v, _) = s.means[&(m.clone(), k.to_string())];
                md.push_str(&format!(" **{}** |", show(k, v)));
            }
            md.push('\n');
            let mean: serde_json::Map<String, serde_json::Value> = s
                .keys
                .iter()
                .filter(|(mm, _)| mm == m)
                .map(|(_, k)| {
                    (
                        k.clone(),
                        serde_json::json!(s.means[&(m.clone(), k.clone())].0),
                    )
                })
                .collect();
            json.insert(
                m.clone(),
                serde_json::json!({"per_scene": per_scene, "mean": mean}),
            );
        }
        let write = |name: &str, bytes: &[u8]| -> Result<PathBuf> {
            let path = dir.join(name);
            std::fs::write(&path, bytes)
                .map_err(|e| StageError::Failed(format!("writing {}: {e}", path.display())))?;
            Ok(path)
        };
        let doc = serde_json::json!({"scenes": s.scenes, "methods": json});
        Ok(vec![
            write("summary.md", md.as_bytes())?,
            write(
                "summary.json",
                &serde_json::to_vec_pretty(&doc).unwrap_or_default(),
            )?,
        ])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_mean_skips_missing_values_and_counts_scenes() {
        let s = summarise(
            &["a", "a", "b", "b"],
            &["ours", "ours", "ours", "ours"],
            &["miou", "pq", "miou", "pq"],
            &[Some(0.5), None, Some(0.7), Some(0.4)],
        );
        assert_eq!(s.scenes, vec!["a", "b"]);
        let (m, n) = s.means[&("ours".into(), "miou".into())];
        assert!((m.unwrap() - 0.6).abs() < 1e-12);
        assert_eq!(n, 2);
        assert_eq!(s.means[&("ours".into(), "pq".into())], (Some(0.4), 1));
        assert_eq!(show("miou", Some(0.6)), "60.0");
        assert_eq!(show("depth_rmse", Some(1.23456)), "1.235");
    }
}
