//! PNG plots of the bench: per scene, the score spec's plotted metrics (e.g. mIoU, PQ and depth
//! RMSE) against training wall time, one line per variant and the baselines that do not depend
//! on the budget as flat lines. Drawn with plotters' bitmap backend;
//! text comes from the public-domain 8x8 glyphs of `font8x8` (no font files, no font stack).

use plotters::prelude::*;
use plotters_backend::{
    text_anchor::{HPos, VPos},
    BackendColor, BackendCoord, BackendStyle, BackendTextStyle, DrawingErrorKind,
};

use stages::ScoreSpec;

use super::{error::BenchError, results::Row};

/// A bitmap backend that draws text itself from 8x8 glyphs.
struct Canvas<'a>(BitMapBackend<'a>);

type CanvasError = DrawingErrorKind<<BitMapBackend<'static> as DrawingBackend>::ErrorType>;

/// Glyph magnification for a font size. Sizes are chosen so plotters' own width estimate
/// (0.7 em per character) matches the 8 px glyphs: 18 for 8 px text, 28 for 16 px titles.
fn glyph_scale(size: f64) -> i32 {
    if size >= 24.0 {
        2
    } else {
        1
    }
}

impl DrawingBackend for Canvas<'_> {
    type ErrorType = <BitMapBackend<'static> as DrawingBackend>::ErrorType;

    fn get_size(&self) -> (u32, u32) {
        self.0.get_size()
    }
    fn ensure_prepared(&mut self) -> Result<(), CanvasError> {
        self.0.ensure_prepared()
    }
    fn present(&mut self) -> Result<(), CanvasError> {
        self.0.present()
    }
    fn draw_pixel(&mut self, p: BackendCoord, c: BackendColor) -> Result<(), CanvasError> {
        self.0.draw_pixel(p, c)
    }
    fn draw_line<S: BackendStyle>(
        &mut self,
        a: BackendCoord,
        b: BackendCoord,
        s: &S,
    ) -> Result<(), CanvasError> {
        self.0.draw_line(a, b, s)
    }
    fn draw_rect<S: BackendStyle>(
        &mut self,
        a: BackendCoord,
        b: BackendCoord,
        s: &S,
        fill: bool,
    ) -> Result<(), CanvasError> {
        self.0.draw_rect(a, b, s, fill)
    }
    fn draw_path<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
        &mut self,
        path: I,
        s: &S,
    ) -> Result<(), CanvasError> {
        self.0.draw_path(path, s)
    }
    fn draw_circle<S: BackendStyle>(
        &mut self,
        c: BackendCoord,
        r: u32,
        s: &S,
        fill: bool,
    ) -> Result<(), CanvasError> {
        self.0.draw_circle(c, r, s, fill)
    }
    fn fill_polygon<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
        &mut self,
        vert: I,
        s: &S,
    ) -> Result<(), CanvasError> {
        self.0.fill_polygon(vert, s)
    }
    fn estimate_text_size<T: BackendTextStyle>(
        &self,
        text: &str,
        style: &T,
    ) -> Result<(u32, u32), CanvasError> {
        let k = glyph_scale(style.size()) as u32;
        Ok((8 * k * text.chars().count() as u32, 8 * k))
    }
    fn draw_text<T: BackendTextStyle>(
        &mut self,
        text: &str,
        style: &T,
        pos: BackendCoord,
    ) -> Result<(), CanvasError> {
        let k = glyph_scale(style.size());
        let color = style.color();
        let (w, h) = (8 * k * text.chars().count() as i32, 8 * k);
        let anchor = style.anchor();
        let dx = match anchor.h_pos {
            HPos::Left => 0,
            HPos::Center => -w / 2,
            HPos::Right => -w,
        };
        let dy = match anchor.v_pos {
            VPos::Top => 0,
            VPos::Center => -h / 2,
            VPos::Bottom => -h,
        };
        let trans = style.transform();
        let (cw, ch) = self.get_size();
        for (n, c) in text.chars().enumerate() {
            let g = font8x8::legacy::BASIC_LEGACY[if c.is_ascii() {
                c as usize
            } else {
                b'?' as usize
            }];
            for (row, bits) in g.iter().enumerate() {
                for col in 0..8 {
                    if bits & (1 << col) == 0 {
                        continue;
                    }
                    for sy in 0..k {
                        for sx in 0..k {
                            let x = dx + (n as i32 * 8 + col) * k + sx;
                            let y = dy + row as i32 * k + sy;
                            let (x, y) = trans.transform(x, y);
                            let (x, y) = (pos.0 + x, pos.1 + y);
                            if x >= 0 && y >= 0 && (x as u32) < cw && (y as u32) < ch {
                                self.0.draw_pixel((x, y), color)?;
                            }
                        }
                    }
                }
            }
        }
        Ok(())
    }
}

/// One line of a panel: a variant's (time, value) points, or a flat baseline.
pub struct Series {
    pub label: String,
    pub points: Vec<(f64, f64)>,
    /// Drawn across the whole time axis at this value.
    pub flat: bool,
    /// Index into the palette (stable across panels).
    pub color: usize,
}

/// One panel: a metric against training wall time.
pub struct Panel {
    pub title: String,
    pub series: Vec<Series>,
}

const COLORS: [RGBColor; 10] = [
    RGBColor(60, 60, 60),
    RGBColor(170, 170, 170),
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
];

fn draw_err<E: std::fmt::Debug>(e: E) -> BenchError {
    BenchError::Plot(format!("{e:?}"))
}

/// The corner whose legend box would cover the fewest points of the panel's lines (sampled along
/// every segment), so the legend does not hide the data; ties prefer the upper right.
fn legend_corner(panel: &Panel, x_max: f64, y_min: f64, y_max: f64) -> SeriesLabelPosition {
    let (w, h) = (x_max.max(1e-12), (y_max - y_min).max(1e-12));
    let mut samples = Vec::new();
    for s in &panel.series {
        let line: Vec<(f64, f64)> = if s.flat {
            let y = s.points.first().map_or(0.0, |p| p.1);
            vec![(0.0, y), (x_max, y)]
        } else {
            s.points.clone()
        };
        samples.extend(line.first().copied());
        for seg in line.windows(2) {
            samples.extend((1..=16).map(|k| {
                let t = k as f64 / 16.0;
                (
                    seg[0].0 + t * (seg[1].0 - seg[0].0),
                    seg[0].1 + t * (seg[1].1 - seg[0].1),
                )
            }));
        }
    }
    // A legend box spans about 45 % of the width and 35 % of the height from its corner.
    let covered = |right: bool, upper: bool| {
        samples
            .iter()
            .filter(|&&(x, y)| {
                let (fx, fy) = (x / w, (y - y_min) / h);
                (if right { fx > 0.55 } else { fx < 0.45 })
                    && (if upper { fy > 0.65 } else { fy < 0.35 })
            })
            .count()
    };
    [
        (SeriesLabelPosition::UpperRight, true, true),
        (SeriesLabelPosition::LowerRight, true, false),
        (SeriesLabelPosition::UpperLeft, false, true),
        (SeriesLabelPosition::LowerLeft, false, false),
    ]
    .into_iter()
    .min_by_key(|&(_, right, upper)| covered(right, upper))
    .map(|(p, ..)| p)
    .expect("four corners")
}

/// Draws the panels side by side and encodes the image as PNG.
pub fn render_png(title: &str, panels: &[Panel]) -> Result<Vec<u8>, BenchError> {
    let (pw, h) = (440u32, 380u32);
    let w = pw * panels.len().max(1) as u32;
    let mut buf = vec![255u8; (w * h * 3) as usize];
    {
        let root = Canvas(BitMapBackend::with_buffer(&mut buf, (w, h))).into_drawing_area();
        root.fill(&WHITE).map_err(draw_err)?;
        let root = root
            .titled(title, ("sans-serif", 28).into_font())
            .map_err(draw_err)?;
        let areas = root.split_evenly((1, panels.len().max(1)));
        for (panel, area) in panels.iter().zip(&areas) {
            let pts = panel.series.iter().flat_map(|s| s.points.iter());
            let (mut x1, mut y0, mut y1) = (1e-9f64, f64::INFINITY, f64::NEG_INFINITY);
            for &(x, y) in pts {
                x1 = x1.max(x);
                y0 = y0.min(y);
                y1 = y1.max(y);
            }
            if !y0.is_finite() {
                (y0, y1) = (0.0, 1.0);
            }
            let pad = ((y1 - y0) * 0.1).max(1e-3);
            let mut chart = ChartBuilder::on(area)
                .caption(&panel.title, ("sans-serif", 18).into_font())
                .margin(8)
                .x_label_area_size(28)
                .y_label_area_size(52)
                .build_cartesian_2d(0.0..x1 * 1.08, (y0 - pad)..(y1 + pad))
                .map_err(draw_err)?;
            chart
                .configure_mesh()
                .x_desc("training wall time, s")
                .x_labels(5)
                .y_labels(6)
                .label_style(("sans-serif", 18).into_font())
                .draw()
                .map_err(draw_err)?;
            for s in &panel.series {
                let color = COLORS[s.color % COLORS.len()];
                let line: Vec<(f64, f64)> = if s.flat {
                    let y = s.points.first().map_or(0.0, |p| p.1);
                    vec![(0.0, y), (x1 * 1.08, y)]
                } else {
                    s.points.clone()
                };
                let style = ShapeStyle::from(&color).stroke_width(if s.flat { 1 } else { 2 });
                chart
                    .draw_series(LineSeries::new(line, style))
                    .map_err(draw_err)?
                    .label(s.label.clone())
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], color));
                if !s.flat {
                    chart
                        .draw_series(s.points.iter().map(|&p| Circle::new(p, 3, color.filled())))
                        .map_err(draw_err)?;
                }
            }
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .label_font(("sans-serif", 18).into_font())
                .position(legend_corner(panel, x1 * 1.08, y0 - pad, y1 + pad))
                .draw()
                .map_err(draw_err)?;
        }
        root.present().map_err(draw_err)?;
    }
    let img = image::RgbImage::from_raw(w, h, buf)
        .ok_or_else(|| BenchError::Plot("plot buffer size".into()))?;
    let mut png = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .map_err(BenchError::Png)?;
    Ok(png)
}

/// The time-vs-error panels of one scene, one per plotted metric of `spec` (scaled as the spec
/// says). `variants` are (name, label, whether its semantic metrics mean anything); the
/// baselines that do not depend on the budget are drawn flat in grey.
pub fn time_vs_error(
    rows: &[Row],
    scene: &str,
    variants: &[(String, String, bool)],
    spec: &ScoreSpec,
) -> Vec<Panel> {
    let any_curve = variants.iter().any(|(name, ..)| {
        let budgets: std::collections::BTreeSet<u64> = rows
            .iter()
            .filter(|r| r.scene == scene && &r.variant == name)
            .map(|r| r.budget)
            .collect();
        budgets.len() >= 2
    });
    let flat: Vec<_> = spec
        .baselines
        .iter()
        .filter(|b| !b.depends_on_budget)
        .collect();
    spec.plotted
        .iter()
        .filter_map(|&metric| spec.metric(metric))
        .map(|m| {
            let mut series = Vec::new();
            for (k, (name, label, semantic)) in variants.iter().enumerate() {
                if !semantic && m.semantic {
                    continue;
                }
                // One point per budget: the mean over its seeds of time and value.
                let mut by_budget: std::collections::BTreeMap<u64, (f64, f64, f64)> =
                    Default::default();
                for r in rows.iter().filter(|r| {
                    r.scene == scene
                        && &r.variant == name
                        && r.method == spec.method
                        && r.metric == m.name
                }) {
                    if let Some(v) = r.value {
                        let e = by_budget.entry(r.budget).or_default();
                        *e = (e.0 + r.train_wall_s, e.1 + v * m.scale, e.2 + 1.0);
                    }
                }
                let mut points: Vec<(f64, f64)> = by_budget
                    .values()
                    .map(|&(t, v, n)| (t / n, v / n))
                    .collect();
                points.sort_by(|a, b| a.0.total_cmp(&b.0));
                // Variants run at one budget only belong to the ablation table, not here.
                if points.len() >= 2 || (!points.is_empty() && !any_curve) {
                    series.push(Series {
                        label: label.clone(),
                        points,
                        flat: false,
                        color: k + 2,
                    });
                }
            }
            for (k, b) in flat.iter().enumerate() {
                let v = rows
                    .iter()
                    .find(|r| r.scene == scene && r.method == b.name && r.metric == m.name)
                    .and_then(|r| r.value);
                if let Some(v) = v {
                    series.push(Series {
                        label: b.label.to_string(),
                        points: vec![(0.0, v * m.scale)],
                        flat: true,
                        color: k,
                    });
                }
            }
            Panel {
                title: format!("{}, {}", m.label, m.unit),
                series,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn panel(points: &[(f64, f64)], flat_at: Option<f64>) -> Panel {
        let mut series = vec![Series {
            label: "ours".into(),
            points: points.to_vec(),
            flat: false,
            color: 2,
        }];
        if let Some(y) = flat_at {
            series.push(Series {
                label: "baseline".into(),
                points: vec![(0.0, y)],
                flat: true,
                color: 0,
            });
        }
        Panel {
            title: "t".into(),
            series,
        }
    }

    #[test]
    fn the_legend_goes_where_the_lines_are_not() {
        // rising to the upper right: the lower right is free
        let rising = panel(&[(0.0, 0.0), (1.0, 8.0), (10.0, 10.0)], None);
        assert_eq!(
            legend_corner(&rising, 10.0, 0.0, 10.0),
            SeriesLabelPosition::LowerRight
        );
        // falling, with a baseline along the bottom: only the upper right is free
        let falling = panel(&[(0.0, 10.0), (2.0, 5.0), (10.0, 4.0)], Some(0.5));
        assert_eq!(
            legend_corner(&falling, 10.0, 0.0, 10.0),
            SeriesLabelPosition::UpperRight
        );
        // rising with a baseline across the bottom: the upper left is free
        let crowded = panel(&[(0.0, 4.0), (5.0, 5.0), (10.0, 10.0)], Some(0.5));
        assert_eq!(
            legend_corner(&crowded, 10.0, 0.0, 10.0),
            SeriesLabelPosition::UpperLeft
        );
    }
}
