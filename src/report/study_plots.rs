//! Figures of the simulation studies, drawn through the shared [`super::plot::Figure`]:
//!
//! - [`ParetoFigure`]: error against time per frame (both log scales) for every setting
//!   of the accuracy-against-time study, coloured by sweep, the Pareto front joined and
//!   labelled, error budgets as dashed lines;
//! - [`LayerSeparationFigure`]: the paper's Fig. 6 — mean absolute force difference
//!   against the layer configuration, one line per solver, one panel per noise level;
//! - [`ModelErrorFigure`]: the model-error study — field and F_sum error against the
//!   elastomer thickness on bonded-layer data, the half-space solver (dashed) against
//!   the matching bonded-layer solver (solid), one colour per load.

use plotters::coord::Shift;
use plotters::prelude::*;

use super::plot::{Figure, FigureResult, FONT};
use crate::analysis::accuracy_time::{Metric, StudyResult, Sweep};
use crate::analysis::layer_separation::{LayerCase, LayerResult};
use crate::analysis::model_error::ModelErrorResult;
use crate::sensor::ModelKind;

/// Colours of the data series, in order (colour-blind friendly Okabe–Ito palette).
const SERIES: [RGBColor; 7] = [
    RGBColor(0, 114, 178),
    RGBColor(213, 94, 0),
    RGBColor(0, 158, 115),
    RGBColor(204, 121, 167),
    RGBColor(230, 159, 0),
    RGBColor(86, 180, 233),
    RGBColor(0, 0, 0),
];

/// One point of the Pareto plot.
#[derive(Debug, Clone, PartialEq)]
pub struct ParetoPoint {
    /// Setting label.
    pub label: String,
    /// Which sweep (colour).
    pub sweep: Sweep,
    /// Time per frame, µs.
    pub time_us: f64,
    /// Relative error, %.
    pub error_pct: f64,
    /// On the Pareto front.
    pub on_front: bool,
}

/// The accuracy-against-time plot.
#[derive(Debug, Clone, PartialEq)]
pub struct ParetoFigure {
    /// Title.
    pub title: String,
    /// y-axis description.
    pub error_desc: String,
    /// The points (non-finite ones are left out).
    pub points: Vec<ParetoPoint>,
    /// Error budgets to mark, %.
    pub budgets_pct: Vec<f64>,
}

impl ParetoFigure {
    /// The figure of a study result under `metric`, with `budgets` (relative errors).
    pub fn from_result(result: &StudyResult, metric: Metric, budgets: &[f64], title: &str) -> Self {
        let front = result.pareto(metric);
        ParetoFigure {
            title: title.to_string(),
            error_desc: format!("{} error, % ({})", metric.name(), metric.describe()),
            points: result
                .rows
                .iter()
                .zip(front)
                .map(|(r, on)| ParetoPoint {
                    label: r.label.clone(),
                    sweep: r.setting.sweep,
                    time_us: r.total_s * 1e6,
                    error_pct: r.error(metric) * 100.0,
                    on_front: on,
                })
                .collect(),
            budgets_pct: budgets.iter().map(|b| b * 100.0).collect(),
        }
    }
}

/// A tick value with at most 3 significant decimals, trailing zeros dropped.
fn short(v: f64) -> String {
    let s = if v >= 1.0 {
        format!("{v:.1}")
    } else {
        format!("{v:.3}")
    };
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

/// Log-axis range covering `values` with a margin (a decade when all are equal).
fn log_range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values.filter(|v| v.is_finite() && *v > 0.0) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() {
        return (0.1, 10.0);
    }
    (lo / 1.6, hi * 1.6)
}

impl Figure for ParetoFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let pts: Vec<&ParetoPoint> = self
            .points
            .iter()
            .filter(|p| p.time_us.is_finite() && p.time_us > 0.0 && p.error_pct.is_finite())
            .collect();
        // Zero errors (exact reconstructions) are drawn at the bottom of the log axis.
        let (x0, x1) = log_range(pts.iter().map(|p| p.time_us));
        let (y0, y1) = log_range(
            pts.iter()
                .map(|p| p.error_pct)
                .chain(self.budgets_pct.iter().copied()),
        );
        let floor = |e: f64| e.max(y0 * 1.01);
        let mut chart = ChartBuilder::on(root)
            .caption(&self.title, (FONT, 22))
            .margin(15)
            .x_label_area_size(45)
            .y_label_area_size(70)
            .build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())?;
        chart
            .configure_mesh()
            .x_label_formatter(&|v| format!("{v:.0}"))
            .y_label_formatter(&|v| short(*v))
            .x_desc("time per force frame, µs (log; median, this machine)")
            .y_desc(self.error_desc.as_str())
            .label_style((FONT, 13))
            .axis_desc_style((FONT, 14))
            .draw()?;
        for b in &self.budgets_pct {
            chart.draw_series(DashedLineSeries::new(
                [(x0, *b), (x1, *b)],
                6,
                4,
                RGBColor(160, 160, 160).into(),
            ))?;
            chart.draw_series(std::iter::once(Text::new(
                format!("{b} %"),
                (x0 * 1.05, *b * 1.04),
                (FONT, 12).into_font().color(&RGBColor(110, 110, 110)),
            )))?;
        }
        let mut front: Vec<&&ParetoPoint> = pts.iter().filter(|p| p.on_front).collect();
        front.sort_by(|a, b| a.time_us.total_cmp(&b.time_us));
        // The front as a staircase: each point is the best error up to the next one's time.
        let mut stairs = Vec::new();
        for (i, p) in front.iter().enumerate() {
            stairs.push((p.time_us, floor(p.error_pct)));
            if let Some(n) = front.get(i + 1) {
                stairs.push((n.time_us, floor(p.error_pct)));
            }
        }
        chart.draw_series(LineSeries::new(stairs, RED.stroke_width(2)))?;
        for (si, sweep) in Sweep::ALL.iter().enumerate() {
            let colour = SERIES[si % SERIES.len()];
            let of: Vec<&&ParetoPoint> = pts.iter().filter(|p| p.sweep == *sweep).collect();
            if of.is_empty() {
                continue;
            }
            chart
                .draw_series(
                    of.iter()
                        .map(|p| Circle::new((p.time_us, floor(p.error_pct)), 5, colour.filled())),
                )?
                .label(sweep.name())
                .legend(move |(x, y)| Circle::new((x + 8, y), 5, colour.filled()));
        }
        for p in &pts {
            if p.on_front {
                chart.draw_series(std::iter::once(Circle::new(
                    (p.time_us, floor(p.error_pct)),
                    8,
                    RED.stroke_width(2),
                )))?;
            }
            let font = if p.on_front {
                (FONT, 12).into_font().color(&BLACK)
            } else {
                (FONT, 10).into_font().color(&RGBColor(120, 120, 120))
            };
            chart.draw_series(std::iter::once(Text::new(
                p.label.clone(),
                (p.time_us * 1.04, floor(p.error_pct) * 1.02),
                font,
            )))?;
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font((FONT, 13))
            .draw()?;
        Ok(())
    }
}

/// One panel of [`LayerSeparationFigure`]: one noise level.
#[derive(Debug, Clone, PartialEq)]
pub struct LayerPanel {
    /// Displacement noise σ, px (0 = exact data).
    pub noise_px: f64,
    /// One series per solver: (label, error in gf per case, NaN where missing).
    pub series: Vec<(String, Vec<f64>)>,
}

/// The layer-separation plot (paper Fig. 6).
#[derive(Debug, Clone, PartialEq)]
pub struct LayerSeparationFigure {
    /// Title.
    pub title: String,
    /// Cases in plot order (x positions 0, 1, …).
    pub cases: Vec<LayerCase>,
    /// One panel per noise level.
    pub panels: Vec<LayerPanel>,
    /// A sentence on the load, shown under the title.
    pub load_note: String,
}

impl LayerSeparationFigure {
    /// The figure of a study result: one panel per noise level, one series per solver.
    pub fn from_result(result: &LayerResult, cases: &[LayerCase], load_note: &str) -> Self {
        let mut noises: Vec<f64> = Vec::new();
        let mut solvers: Vec<String> = Vec::new();
        for r in &result.rows {
            if !noises.contains(&r.noise_px) {
                noises.push(r.noise_px);
            }
            if !solvers.contains(&r.solver) {
                solvers.push(r.solver.clone());
            }
        }
        let panels = noises
            .iter()
            .map(|&n| {
                let series = solvers
                    .iter()
                    .map(|s| {
                        let ys = cases
                            .iter()
                            .map(|&c| result.find(c, s, n).map_or(f64::NAN, |r| r.mean_abs_gf))
                            .collect();
                        (s.clone(), ys)
                    })
                    .collect();
                LayerPanel {
                    noise_px: n,
                    series,
                }
            })
            .collect();
        LayerSeparationFigure {
            title: "Force error against layer separation (paper Fig. 6)".into(),
            cases: cases.to_vec(),
            panels,
            load_note: load_note.to_string(),
        }
    }
}

impl Figure for LayerSeparationFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let root = root.titled(&self.title, (FONT, 22))?;
        let (note, body) = root.split_vertically(24);
        note.draw(&Text::new(
            self.load_note.clone(),
            (15, 4),
            (FONT, 13).into_font(),
        ))?;
        let n = self.panels.len().max(1);
        let areas = body.split_evenly((1, n));
        let labels: Vec<String> = self
            .cases
            .iter()
            .map(|c| match c {
                LayerCase::SingleLayer => "1 layer".to_string(),
                LayerCase::Separation(d) => format!("{d}"),
            })
            .collect();
        for (area, panel) in areas.iter().zip(&self.panels) {
            let (noise, series) = (&panel.noise_px, &panel.series);
            let (y0, y1) = log_range(series.iter().flat_map(|(_, ys)| ys.iter().copied()));
            let caption = if *noise == 0.0 {
                "exact displacements".to_string()
            } else {
                format!("displacement noise σ = {noise} px")
            };
            let nx = self.cases.len() as f64;
            let mut chart = ChartBuilder::on(area)
                .caption(caption, (FONT, 16))
                .margin(12)
                .x_label_area_size(45)
                .y_label_area_size(70)
                .build_cartesian_2d(-0.5..nx - 0.5, (y0..y1).log_scale())?;
            let fmt = |x: &f64| {
                let i = x.round();
                if (x - i).abs() < 1e-6 && i >= 0.0 && (i as usize) < labels.len() {
                    labels[i as usize].clone()
                } else {
                    String::new()
                }
            };
            chart
                .configure_mesh()
                .x_labels(self.cases.len() * 4 + 1)
                .x_label_formatter(&fmt)
                .x_desc("layer configuration: single layer, or separation d, mm")
                .y_label_formatter(&|v| format!("{v:.1e}"))
                .y_desc("mean |f − f*| over points and axes, gf")
                .label_style((FONT, 12))
                .axis_desc_style((FONT, 13))
                .draw()?;
            for (si, (solver, ys)) in series.iter().enumerate() {
                let colour = SERIES[si % SERIES.len()];
                let pts: Vec<(f64, f64)> = ys
                    .iter()
                    .enumerate()
                    .filter(|(_, y)| y.is_finite() && **y > 0.0)
                    .map(|(i, y)| (i as f64, *y))
                    .collect();
                chart
                    .draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2)))?
                    .label(solver.clone())
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 16, y)], colour.stroke_width(2))
                    });
                chart.draw_series(pts.iter().map(|p| Circle::new(*p, 4, colour.filled())))?;
            }
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .label_font((FONT, 12))
                .draw()?;
        }
        Ok(())
    }
}

/// One line of [`ModelErrorFigure`]: one load, one solver model.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelErrorSeries {
    /// Load name.
    pub load: String,
    /// What the solver inverts.
    pub solver_model: ModelKind,
    /// `(thickness mm, field error %, F_sum error %)`, by thickness.
    pub points: Vec<(f64, f64, f64)>,
}

/// The model-error plot: error against thickness, half-space against matching solver.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelErrorFigure {
    /// Title.
    pub title: String,
    /// A sentence on the data, shown under the title.
    pub note: String,
    /// The lines.
    pub series: Vec<ModelErrorSeries>,
}

impl ModelErrorFigure {
    /// The figure of a study result: bonded-layer data, the headline effect set
    /// ([`ModelErrorResult::headline_effects`]), the first solver kind; one series per
    /// (load, solver model) with the rows that ran.
    pub fn from_result(result: &ModelErrorResult) -> Self {
        let o = &result.options;
        let eff = result.headline_effects();
        let method = o.solvers.first().map(|c| c.method).unwrap_or_default();
        let mut series = Vec::new();
        for &load in &o.loads {
            for &m in &o.solver_models {
                let points: Vec<(f64, f64, f64)> = o
                    .thicknesses_mm
                    .iter()
                    .filter_map(|&h| {
                        result
                            .find(h, ModelKind::BondedLayer, m, method, load, &eff)
                            .map(|r| (h, 100.0 * r.errors.field, 100.0 * r.errors.sum))
                    })
                    .collect();
                if !points.is_empty() {
                    series.push(ModelErrorSeries {
                        load: load.name().to_string(),
                        solver_model: m,
                        points,
                    });
                }
            }
        }
        ModelErrorFigure {
            title: "Model error: half-space vs bonded-layer solver on bonded-layer data".into(),
            note: format!(
                "solver {}, effects {eff}; load: paper Fig. 6 (normal 100 gf z, tangential 50 gf y, mixed both); dashed: half-space solver, solid: matching bonded-layer solver",
                method.name()
            ),
            series,
        }
    }
}

impl Figure for ModelErrorFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let root = root.titled(&self.title, (FONT, 22))?;
        let (note, body) = root.split_vertically(24);
        note.draw(&Text::new(
            self.note.clone(),
            (15, 4),
            (FONT, 13).into_font(),
        ))?;
        let areas = body.split_evenly((1, 2));
        let mut loads: Vec<&str> = Vec::new();
        for s in &self.series {
            if !loads.contains(&s.load.as_str()) {
                loads.push(&s.load);
            }
        }
        let (x0, x1) = log_range(
            self.series
                .iter()
                .flat_map(|s| s.points.iter().map(|p| p.0)),
        );
        for (panel, area) in areas.iter().enumerate() {
            let value = |p: &(f64, f64, f64)| if panel == 0 { p.1 } else { p.2 };
            let (y0, y1) = log_range(self.series.iter().flat_map(|s| s.points.iter().map(value)));
            // Zero errors (exact reconstructions) at the bottom of the log axis.
            let floor = |e: f64| e.max(y0 * 1.01);
            let caption = if panel == 0 {
                "force field: ‖f − f*‖ / ‖f*‖"
            } else {
                "total force: |ΣF − F_applied| / |F_applied|"
            };
            let mut chart = ChartBuilder::on(area)
                .caption(caption, (FONT, 16))
                .margin(12)
                .x_label_area_size(45)
                .y_label_area_size(70)
                .build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())?;
            chart
                .configure_mesh()
                .x_label_formatter(&|v| short(*v))
                .y_label_formatter(&|v| {
                    if *v >= 0.01 {
                        short(*v)
                    } else {
                        format!("{v:.0e}")
                    }
                })
                .x_desc("elastomer thickness h, mm (log)")
                .y_desc("relative error, % (log)")
                .label_style((FONT, 12))
                .axis_desc_style((FONT, 13))
                .draw()?;
            for s in &self.series {
                let li = loads.iter().position(|l| *l == s.load).unwrap_or(0);
                let colour = SERIES[li % SERIES.len()];
                let pts: Vec<(f64, f64)> = s
                    .points
                    .iter()
                    .filter(|p| p.0 > 0.0 && value(p).is_finite())
                    .map(|p| (p.0, floor(value(p))))
                    .collect();
                let label = format!(
                    "{}, {} solver",
                    s.load,
                    match s.solver_model {
                        ModelKind::HalfSpace => "half-space",
                        ModelKind::BondedLayer => "bonded-layer",
                    }
                );
                if s.solver_model == ModelKind::HalfSpace {
                    chart
                        .draw_series(DashedLineSeries::new(
                            pts.clone(),
                            8,
                            5,
                            colour.stroke_width(2),
                        ))?
                        .label(label)
                        .legend(move |(x, y)| {
                            PathElement::new(vec![(x, y), (x + 7, y)], colour.stroke_width(2))
                        });
                    chart.draw_series(
                        pts.iter()
                            .map(|p| Circle::new(*p, 5, colour.stroke_width(2))),
                    )?;
                } else {
                    chart
                        .draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2)))?
                        .label(label)
                        .legend(move |(x, y)| {
                            PathElement::new(vec![(x, y), (x + 16, y)], colour.stroke_width(2))
                        });
                    chart.draw_series(pts.iter().map(|p| Circle::new(*p, 4, colour.filled())))?;
                }
            }
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::MiddleRight)
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .label_font((FONT, 12))
                .draw()?;
        }
        Ok(())
    }
}
