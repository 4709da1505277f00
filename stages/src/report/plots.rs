//! Plots for the run report (inline SVG).

use arrow::array::Array;
use arrow::datatypes::{DataType, UInt32Type};
use arrow::record_batch::RecordBatch;
use plotters::prelude::*;

use crate::stage::{Result, StageError};
use crate::tables;

/// Training curves as inline SVG: every loss column of the train log against iteration.
pub fn training_svg(log: &RecordBatch) -> Result<Option<String>> {
    let Some(iter_col) = log.column_by_name("iteration") else {
        return Ok(None);
    };
    let iters: Vec<f64> = match iter_col.data_type() {
        DataType::UInt32 => tables::get_prim::<UInt32Type>(log, "train_log", "iteration")?
            .iter()
            .map(|&v| v as f64)
            .collect(),
        _ => return Ok(None),
    };
    if iters.is_empty() {
        return Ok(None);
    }
    let mut series: Vec<(String, Vec<(f64, f64)>)> = Vec::new();
    for (f, col) in log.schema().fields().iter().zip(log.columns()) {
        let name = f.name();
        if !name.starts_with("loss_") {
            continue;
        }
        let vals: Vec<f64> = match col.data_type() {
            DataType::Float32 => {
                let a = col
                    .as_any()
                    .downcast_ref::<arrow::array::Float32Array>()
                    .unwrap();
                (0..a.len())
                    .map(|i| {
                        if a.is_null(i) {
                            f64::NAN
                        } else {
                            a.value(i) as f64
                        }
                    })
                    .collect()
            }
            DataType::Float64 => {
                tables::get_prim::<arrow::datatypes::Float64Type>(log, "train_log", name)?.to_vec()
            }
            _ => continue,
        };
        let raw: Vec<(f64, f64)> = iters
            .iter()
            .zip(vals)
            .filter(|(_, v)| v.is_finite() && *v > 0.0)
            .map(|(&i, v)| (i, v))
            .collect();
        // Per-batch losses are noisy: plot a trailing running mean so the trend is readable.
        let window = (raw.len() / 50).max(1);
        let mut sum = 0.0;
        let pts: Vec<(f64, f64)> = raw
            .iter()
            .enumerate()
            .map(|(k, &(i, v))| {
                sum += v;
                if k >= window {
                    sum -= raw[k - window].1;
                }
                (i, sum / (k + 1).min(window) as f64)
            })
            .collect();
        if !pts.is_empty() {
            series.push((name.clone(), pts));
        }
    }
    if series.is_empty() {
        return Ok(None);
    }
    let (x1, mut y0, mut y1) = (
        iters.iter().cloned().fold(1.0, f64::max),
        f64::MAX,
        f64::MIN,
    );
    for (_, pts) in &series {
        for &(_, v) in pts {
            y0 = y0.min(v);
            y1 = y1.max(v);
        }
    }
    let (y0, y1) = (y0 * 0.8, y1 * 1.25);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (760, 360)).into_drawing_area();
        let err = |e: String| StageError::Failed(format!("plotting training curves: {e}"));
        root.fill(&WHITE).map_err(|e| err(e.to_string()))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(
                "training losses (log scale, running mean over 2% of the steps)",
                ("sans-serif", 16),
            )
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(60)
            .build_cartesian_2d(0f64..x1, (y0..y1).log_scale())
            .map_err(|e| err(e.to_string()))?;
        chart
            .configure_mesh()
            .x_desc("iteration")
            .y_desc("loss")
            .draw()
            .map_err(|e| err(e.to_string()))?;
        for (k, (name, pts)) in series.iter().enumerate() {
            let color = Palette99::pick(k).to_rgba();
            chart
                .draw_series(LineSeries::new(pts.iter().cloned(), color.stroke_width(2)))
                .map_err(|e| err(e.to_string()))?
                .label(name.clone())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 16, y)], color.stroke_width(2))
                });
        }
        chart
            .configure_series_labels()
            .border_style(BLACK)
            .background_style(WHITE.mix(0.8))
            .draw()
            .map_err(|e| err(e.to_string()))?;
        root.present().map_err(|e| err(e.to_string()))?;
    }
    Ok(Some(svg))
}
