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
            .filter(|(_, v)| v.is_finite())
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
    let x1 = iters.iter().cloned().fold(1.0, f64::max);
    let values = || series.iter().flat_map(|(_, pts)| pts.iter().map(|p| p.1));
    // A log axis while every value is positive; else symlog (log beyond a linear band around
    // zero), so a term that reaches zero or goes negative keeps its curve.
    let positive = values().all(|v| v > 0.0);
    let axis = if positive {
        Axis::Log
    } else {
        let smallest = values()
            .map(f64::abs)
            .filter(|v| *v > 0.0)
            .fold(f64::INFINITY, f64::min);
        let band = if smallest.is_finite() {
            10f64.powf(smallest.log10().floor()).max(1e-6)
        } else {
            1.0
        };
        Axis::Symlog(band)
    };
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (760, 360)).into_drawing_area();
        let err = |e: String| StageError::Failed(format!("plotting training curves: {e}"));
        root.fill(&WHITE).map_err(|e| err(e.to_string()))?;
        let caption = match axis {
            Axis::Log => "training losses (log scale, running mean over 2% of the steps)".into(),
            Axis::Symlog(b) => format!(
                "training losses (symlog scale, linear within ±{b:e}; running mean over 2% of the steps)"
            ),
        };
        let mut builder = ChartBuilder::on(&root);
        builder
            .caption(caption, ("sans-serif", 16))
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(60);
        let ys: Vec<f64> = values().map(|v| axis.to(v)).collect();
        let (y0, y1) = ys
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
        match axis {
            Axis::Log => {
                let mut chart = builder
                    .build_cartesian_2d(0f64..x1, (y0 * 0.8..y1 * 1.25).log_scale())
                    .map_err(|e| err(e.to_string()))?;
                chart
                    .configure_mesh()
                    .x_desc("iteration")
                    .y_desc("loss")
                    .draw()
                    .map_err(|e| err(e.to_string()))?;
                draw_lines(&mut chart, &series, |v| v).map_err(err)?;
            }
            Axis::Symlog(_) => {
                let pad = ((y1 - y0) * 0.05).max(0.05);
                let mut chart = builder
                    .build_cartesian_2d(0f64..x1, y0 - pad..y1 + pad)
                    .map_err(|e| err(e.to_string()))?;
                chart
                    .configure_mesh()
                    .x_desc("iteration")
                    .y_desc("loss")
                    .y_label_formatter(&|v| format!("{:.3}", axis.from(*v)))
                    .draw()
                    .map_err(|e| err(e.to_string()))?;
                draw_lines(&mut chart, &series, |v| axis.to(v)).map_err(err)?;
            }
        }
        root.present().map_err(|e| err(e.to_string()))?;
    }
    Ok(Some(svg))
}

/// The loss axis of [`training_svg`].
#[derive(Debug, Clone, Copy, PartialEq)]
enum Axis {
    Log,
    /// sign(v) * log10(1 + |v| / band): linear near zero, logarithmic beyond `band`.
    Symlog(f64),
}

impl Axis {
    fn to(self, v: f64) -> f64 {
        match self {
            Axis::Log => v,
            Axis::Symlog(b) => v.signum() * (1.0 + v.abs() / b).log10(),
        }
    }

    fn from(self, y: f64) -> f64 {
        match self {
            Axis::Log => y,
            Axis::Symlog(b) => y.signum() * (10f64.powf(y.abs()) - 1.0) * b,
        }
    }
}

/// Draws every series, mapped through `map`, with a legend.
fn draw_lines<'a, DB: DrawingBackend + 'a, X, Y>(
    chart: &mut ChartContext<'a, DB, Cartesian2d<X, Y>>,
    series: &[(String, Vec<(f64, f64)>)],
    map: impl Fn(f64) -> f64,
) -> std::result::Result<(), String>
where
    X: Ranged<ValueType = f64>,
    Y: Ranged<ValueType = f64>,
{
    for (k, (name, pts)) in series.iter().enumerate() {
        let color = Palette99::pick(k).to_rgba();
        chart
            .draw_series(LineSeries::new(
                pts.iter().map(|&(i, v)| (i, map(v))),
                color.stroke_width(2),
            ))
            .map_err(|e| e.to_string())?
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
        .map_err(|e| e.to_string())
}

/// One figure of a (frame, camera, score, coverage) row.
type FrameValue = fn(&(u32, u8, f64, f64)) -> f64;

/// Per-image review figures along the sequence as inline SVG: the frame score (left) and the
/// share the annotations cover (right), one line per camera. `rows`: (frame, camera, score,
/// coverage).
pub fn review_svg(rows: &[(u32, u8, f64, f64)]) -> Result<Option<String>> {
    if rows.is_empty() {
        return Ok(None);
    }
    let mut cameras: Vec<u8> = rows.iter().map(|r| r.1).collect();
    cameras.sort_unstable();
    cameras.dedup();
    let (f0, f1) = rows
        .iter()
        .fold((u32::MAX, 0), |(a, b), r| (a.min(r.0), b.max(r.0)));
    let (f0, f1) = (f0 as f64, (f1 as f64).max(f0 as f64 + 1.0));
    let smax = rows.iter().map(|r| r.2).fold(0.0, f64::max).max(1e-6) * 1.1;
    let cmin = rows.iter().map(|r| r.3).fold(1.0, f64::min).min(0.99);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (900, 280)).into_drawing_area();
        let err = |e: String| StageError::Failed(format!("plotting the review: {e}"));
        root.fill(&WHITE).map_err(|e| err(e.to_string()))?;
        let (left, right) = root.split_horizontally(470);
        let panels: [(&_, &str, std::ops::Range<f64>, FrameValue); 2] = [
            (
                &left,
                "frame score (mean squared review score)",
                0.0..smax,
                |r| r.2,
            ),
            (
                &right,
                "coverage (share not a coverage gap)",
                (cmin - 0.01).max(0.0)..1.0,
                |r| r.3,
            ),
        ];
        for (area, title, range, get) in panels {
            let mut chart = ChartBuilder::on(area)
                .caption(title, ("sans-serif", 14))
                .margin(8)
                .x_label_area_size(30)
                .y_label_area_size(55)
                .build_cartesian_2d(f0..f1, range)
                .map_err(|e| err(e.to_string()))?;
            chart
                .configure_mesh()
                .x_desc("frame")
                .draw()
                .map_err(|e| err(e.to_string()))?;
            let series: Vec<(String, Vec<(f64, f64)>)> = cameras
                .iter()
                .map(|&cam| {
                    let pts = rows
                        .iter()
                        .filter(|r| r.1 == cam)
                        .map(|r| (r.0 as f64, get(r)))
                        .collect();
                    (format!("image_{cam:02}"), pts)
                })
                .collect();
            draw_lines(&mut chart, &series, |v| v).map_err(err)?;
        }
        root.present().map_err(|e| err(e.to_string()))?;
    }
    Ok(Some(svg))
}

#[cfg(test)]
mod tests {
    use super::*;
    use arrow::datatypes::Float32Type;

    fn log(columns: &[(&str, Vec<f32>)]) -> RecordBatch {
        let n = columns[0].1.len();
        let mut cols: Vec<(&str, arrow::array::ArrayRef)> = vec![(
            "iteration",
            tables::prim::<UInt32Type>((0..n as u32).collect::<Vec<_>>()),
        )];
        for (name, v) in columns {
            cols.push((name, tables::prim::<Float32Type>(v.clone())));
        }
        RecordBatch::try_from_iter(cols).unwrap()
    }

    #[test]
    fn symlog_round_trips_and_is_odd() {
        let a = Axis::Symlog(0.01);
        for v in [-3.0, -0.004, 0.0, 0.005, 0.3, 42.0] {
            assert!((a.from(a.to(v)) - v).abs() < 1e-9 * v.abs().max(1.0), "{v}");
            assert_eq!(a.to(-v), -a.to(v));
        }
        assert!(a.to(1.0) > a.to(0.1) && a.to(0.1) > a.to(0.0));
    }

    #[test]
    fn a_term_at_zero_or_below_keeps_its_curve() {
        let svg = training_svg(&log(&[
            ("loss_total", vec![-0.5, -0.4, -0.45, -0.6]),
            ("loss_rgb", vec![0.2, 0.1, 0.05, 0.04]),
            ("loss_depth", vec![0.0, 0.0, 0.0, 0.0]),
        ]))
        .unwrap()
        .unwrap();
        assert!(svg.contains("symlog"), "a symlog axis");
        for name in ["loss_total", "loss_rgb", "loss_depth"] {
            assert!(svg.contains(name), "{name} is in the legend");
        }
        let positive = training_svg(&log(&[("loss_rgb", vec![0.2, 0.1, 0.05, 0.04])]))
            .unwrap()
            .unwrap();
        assert!(positive.contains("log scale"));
    }
}
