//! The comparison's figures:
//!
//! - [`TrendFigure`]: one small panel per metric (those with a direction, present in at
//!   least two runs), value with its 95 % CI against the runs in order of their start
//!   date, x labelled by build id; the baseline's value dashed;
//! - the fitted parameters' trend ([`fit_trend_figure`], a [`TrendFigure`] too): one
//!   panel per `fit.<NAME>` any run has (runs with a `fit.json` whose fit determined
//!   it), value and 95 % interval per build, the nominal value dashed;
//! - [`OverlayFigure`]: applied against measured (F^sum_z against the F/T Fz of
//!   magnitude runs; measured against applied angle of angle runs), one colour per run:
//!   the samples, the level means ± 1 SD joined by a line, the identity.

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;

use super::{Better, Comparison};
use crate::report::acceptance::fmt_value;
use crate::report::acceptance::FIT_PREFIX;
use crate::report::headline::{display_factor, other_resolution};
use crate::report::plot::{
    self, titled_with_legend, Figure, FigureFiles, FigureResult, LegendGlyph, PlotError, FONT,
};

/// One colour per run, in [`Comparison::runs`] order (cycled past eight): the
/// Okabe–Ito colour-blind-safe palette, as the study plots use. The page shows the
/// same colours as CSS in its runs table.
pub const RUN_COLORS: [(u8, u8, u8); 8] = [
    (0, 114, 178),
    (213, 94, 0),
    (0, 158, 115),
    (204, 121, 167),
    (230, 159, 0),
    (86, 180, 233),
    (0, 0, 0),
    (240, 228, 66),
];

/// The colour of run `i`.
pub fn run_color(i: usize) -> RGBColor {
    let (r, g, b) = RUN_COLORS[i % RUN_COLORS.len()];
    RGBColor(r, g, b)
}

/// A figure behind a trait object (the [`Figure`] trait is generic).
pub(crate) trait AnyFigure {
    fn save(&self, dir: &Path, stem: &str, size: (u32, u32)) -> Result<FigureFiles, PlotError>;
}

impl<F: Figure> AnyFigure for F {
    fn save(&self, dir: &Path, stem: &str, size: (u32, u32)) -> Result<FigureFiles, PlotError> {
        plot::save_figure(self, dir, stem, size)
    }
}

/// `(x, value, 95 % CI)` of one run in a trend panel.
pub type TrendPoint = (usize, f64, Option<(f64, f64)>);

/// One metric over the runs.
#[derive(Debug, Clone, PartialEq)]
pub struct TrendPanel {
    /// Metric name.
    pub metric: String,
    /// Its unit.
    pub unit: String,
    /// Which way is better.
    pub better: Option<Better>,
    /// `(x, value, CI)` per run that has a finite value; `x` indexes the labels.
    pub points: Vec<TrendPoint>,
    /// The baseline's value (dashed line), if finite.
    pub baseline: Option<f64>,
}

/// Metrics over runs sorted by date.
#[derive(Debug, Clone, PartialEq)]
pub struct TrendFigure {
    /// x labels (build id or directory), in date order.
    pub labels: Vec<String>,
    /// The colour index (the run's position in the comparison) of each x.
    pub colors: Vec<usize>,
    /// The panels.
    pub panels: Vec<TrendPanel>,
    /// The figure's title.
    pub title: String,
    /// What each panel's dashed line is (legend text).
    pub reference: String,
}

/// Smallest half-span of a trend panel's y axis, as a fraction of the baseline's value
/// (of the first run's without a baseline value): the axis always includes
/// `b ± 5 % |b|`, so a 1 % change between runs moves a point a tenth of the axis, not
/// from bottom to top (autoscaling alone makes noise look like a cliff).
pub const TREND_MIN_HALF_SPAN: f64 = 0.05;

/// `ys` widened to include `b ± TREND_MIN_HALF_SPAN · |b|`.
pub fn trend_axis(ys: std::ops::Range<f64>, b: Option<f64>) -> std::ops::Range<f64> {
    match b.filter(|b| b.is_finite() && *b != 0.0) {
        Some(b) => {
            let h = TREND_MIN_HALF_SPAN * b.abs();
            ys.start.min(b - h)..ys.end.max(b + h)
        }
        None => ys,
    }
}

/// Panels per row of the trend figure.
const TREND_COLUMNS: usize = 3;
/// Largest number of trend panels (the rest are in the table and the CSV).
pub const MAX_TREND_PANELS: usize = 30;

impl TrendFigure {
    /// Pixel size: 3 columns, 250 px per row of panels, and the title and legend.
    pub fn size(&self) -> (u32, u32) {
        let rows = self.panels.len().div_ceil(TREND_COLUMNS).max(1);
        let legend = plot::legend_rows(&self.legend(), 1200) * plot::LEGEND_ROW_PX + 8;
        (1200, 250 * rows as u32 + legend + 30)
    }
}

/// The trend figure of a comparison (`None` when no metric qualifies).
/// Forces in the page's unit ([`Comparison::force_unit`]); the resolution metric of the
/// other unit gets no panel.
pub fn trend_figure(c: &Comparison) -> Option<TrendFigure> {
    let order = c.date_order();
    let labels: Vec<String> = order.iter().map(|&i| c.runs[i].label.clone()).collect();
    let unit = c.force_unit();
    let mut panels = Vec::new();
    for m in &c.metrics {
        if m.better.is_none()
            || panels.len() >= MAX_TREND_PANELS
            || m.name == other_resolution(unit)
        {
            continue;
        }
        let k = display_factor(m.unit, unit);
        let points: Vec<TrendPoint> = order
            .iter()
            .enumerate()
            .filter_map(|(x, &i)| {
                let mt = c.runs[i].metric(&m.name)?;
                mt.value.is_finite().then(|| {
                    (
                        x,
                        mt.value * k,
                        mt.ci95
                            .filter(|ci| ci.low.is_finite() && ci.high.is_finite())
                            .map(|ci| (ci.low * k, ci.high * k)),
                    )
                })
            })
            .collect();
        if points.len() < 2 {
            continue;
        }
        panels.push(TrendPanel {
            metric: m.name.clone(),
            unit: if k == 1.0 { m.unit } else { unit.symbol() }.to_string(),
            better: m.better,
            points,
            baseline: c
                .baseline_run()
                .metric(&m.name)
                .map(|b| b.value * k)
                .filter(|v| v.is_finite()),
        });
    }
    (!panels.is_empty()).then_some(TrendFigure {
        labels,
        colors: order,
        panels,
        title: "metrics over the runs".into(),
        reference: "the baseline's value".into(),
    })
}

/// The fitted parameters over the runs (`None` when no run has a fitted parameter):
/// one panel per `fit.<NAME>` metric, the runs in date order, the value with its 95 %
/// interval, and the nominal value (the sensor file's, which like-for-like runs share)
/// dashed. A run without a `fit.json`, or whose fit did not determine the parameter,
/// has no point in that panel.
pub fn fit_trend_figure(c: &Comparison) -> Option<TrendFigure> {
    let order = c.date_order();
    let labels: Vec<String> = order.iter().map(|&i| c.runs[i].label.clone()).collect();
    let mut panels = Vec::new();
    for m in &c.metrics {
        let Some(param) = m.name.strip_prefix(FIT_PREFIX) else {
            continue;
        };
        if panels.len() >= MAX_TREND_PANELS {
            break;
        }
        let points: Vec<TrendPoint> = order
            .iter()
            .enumerate()
            .filter_map(|(x, &i)| {
                let mt = c.runs[i].metric(&m.name)?;
                mt.value.is_finite().then(|| {
                    (
                        x,
                        mt.value,
                        mt.ci95
                            .filter(|ci| ci.low.is_finite() && ci.high.is_finite())
                            .map(|ci| (ci.low, ci.high)),
                    )
                })
            })
            .collect();
        if points.is_empty() {
            continue;
        }
        let nominal = c
            .runs
            .iter()
            .filter_map(|r| r.fit.doc()?.parameters.get(param).map(|p| p.nominal))
            .find(|v| v.is_finite());
        panels.push(TrendPanel {
            metric: m.name.clone(),
            unit: m.unit.to_string(),
            better: None,
            points,
            baseline: nominal,
        });
    }
    (!panels.is_empty()).then_some(TrendFigure {
        labels,
        colors: order,
        panels,
        title: "fitted sensor-model parameters over the builds".into(),
        reference: "the nominal value (sensor file)".into(),
    })
}

/// Padded `lo..hi` over finite values (a flat set gets a span of its own size).
fn span(values: impl Iterator<Item = f64>) -> std::ops::Range<f64> {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if !lo.is_finite() {
        return 0.0..1.0;
    }
    // A flat set (every run equal, e.g. 0 unsettled rows) gets a readable span
    // around its value instead of a rounding-error one.
    let flat = 0.1 * hi.abs().max(lo.abs());
    let s = if hi - lo > 1e-9 * hi.abs().max(lo.abs()) {
        hi - lo
    } else if flat > 0.0 {
        flat
    } else {
        1.0
    };
    (lo - 0.12 * s)..(hi + 0.12 * s)
}

/// `v`, with values within 1e-9 of the axis span from 0 printed as 0 (axis key points
/// land on -5.6e-17 instead of 0).
fn snap(v: f64, axis: &std::ops::Range<f64>) -> f64 {
    if v.abs() < 1e-9 * (axis.end - axis.start).abs() {
        0.0
    } else {
        v
    }
}

fn short(label: &str, n: usize) -> String {
    if label.chars().count() <= n {
        label.to_string()
    } else {
        let s: String = label.chars().take(n - 1).collect();
        format!("{s}…")
    }
}

impl TrendFigure {
    /// The key: each run's colour with its full label (the x labels are cut to 14
    /// characters), the baseline's dashed line and the CI bars.
    pub fn legend(&self) -> Vec<(LegendGlyph, String)> {
        let mut entries: Vec<(LegendGlyph, String)> = self
            .colors
            .iter()
            .zip(&self.labels)
            .map(|(&c, l)| (LegendGlyph::Dot(run_color(c)), l.clone()))
            .collect();
        entries.push((LegendGlyph::Dashed(BLACK), self.reference.clone()));
        entries.push((LegendGlyph::ErrorBar(BLACK), "value and 95 % CI".into()));
        entries
    }
}

impl Figure for TrendFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let rows = self.panels.len().div_ceil(TREND_COLUMNS).max(1);
        let root = titled_with_legend(root, &self.title, &self.legend())?;
        let areas = root.split_evenly((rows, TREND_COLUMNS));
        let n = self.labels.len();
        let labels: Vec<String> = self.labels.iter().map(|l| short(l, 14)).collect();
        for (panel, area) in self.panels.iter().zip(areas.iter()) {
            let ys = span(
                panel
                    .points
                    .iter()
                    .flat_map(|&(_, v, ci)| {
                        let (lo, hi) = ci.unwrap_or((v, v));
                        [v, lo, hi]
                    })
                    .chain(panel.baseline),
            );
            let ys = trend_axis(ys, panel.baseline.or(panel.points.first().map(|p| p.1)));
            let better = match panel.better {
                Some(b) => format!(" · {} is better", b.word().replace('_', " ")),
                None => String::new(),
            };
            let unit = match panel.unit.as_str() {
                "1" => String::new(),
                u => format!(" [{u}]"),
            };
            let mut chart = ChartBuilder::on(area)
                .caption(format!("{}{unit}{better}", panel.metric), (FONT, 13))
                .margin(8)
                .x_label_area_size(22)
                .y_label_area_size(58)
                .build_cartesian_2d(-0.5..(n as f64 - 0.5), ys.clone())?;
            let fmt_x = |x: &f64| {
                let r = x.round();
                if (x - r).abs() < 1e-6 && r >= 0.0 && (r as usize) < n {
                    labels[r as usize].clone()
                } else {
                    String::new()
                }
            };
            chart
                .configure_mesh()
                .disable_x_mesh()
                .x_labels(n + 2)
                .x_label_formatter(&fmt_x)
                .y_labels(5)
                .y_label_formatter(&|y| fmt_value(snap(*y, &ys)))
                .light_line_style(WHITE)
                .label_style((FONT, 11))
                .draw()?;
            if let Some(b) = panel.baseline {
                chart.draw_series(DashedLineSeries::new(
                    [(-0.5, b), (n as f64 - 0.5, b)],
                    4,
                    3,
                    BLACK.mix(0.45).stroke_width(1),
                ))?;
            }
            chart.draw_series(LineSeries::new(
                panel.points.iter().map(|&(x, v, _)| (x as f64, v)),
                BLACK.mix(0.35).stroke_width(1),
            ))?;
            chart.draw_series(panel.points.iter().filter_map(|&(x, v, ci)| {
                ci.map(|(lo, hi)| {
                    ErrorBar::new_vertical(x as f64, lo, v, hi, BLACK.stroke_width(1), 8)
                })
            }))?;
            chart.draw_series(panel.points.iter().map(|&(x, v, _)| {
                Circle::new((x as f64, v), 5, run_color(self.colors[x]).filled())
            }))?;
        }
        Ok(())
    }
}

/// One run's applied-vs-measured data.
#[derive(Debug, Clone, PartialEq)]
pub struct OverlayCurve {
    /// Legend label.
    pub label: String,
    /// Colour index (the run's position).
    pub color: usize,
    /// `(applied, measured)` samples (display unit).
    pub samples: Vec<(f64, f64)>,
    /// `(applied mean, measured mean, measured SD)` per level (display unit).
    pub levels: Vec<(f64, f64, f64)>,
}

/// Applied against measured, one colour per run.
#[derive(Debug, Clone, PartialEq)]
pub struct OverlayFigure {
    /// Title.
    pub title: String,
    /// x axis (applied, unit).
    pub x_label: String,
    /// y axis (measured, unit).
    pub y_label: String,
    /// One curve per run.
    pub curves: Vec<OverlayCurve>,
}

/// The overlays of a comparison: `(file stem, caption, figure)`; magnitude runs in the
/// first magnitude run's force unit (N when they differ), angle runs in degrees.
pub fn overlay_figures(c: &Comparison) -> Vec<(String, String, OverlayFigure)> {
    let mut out = Vec::new();
    let mags: Vec<usize> = (0..c.runs.len())
        .filter(|&i| c.runs[i].analysis.magnitude.is_some())
        .collect();
    if !mags.is_empty() {
        let units: BTreeUnits = mags
            .iter()
            .map(|&i| c.runs[i].analysis.run.plan.force_unit)
            .collect();
        let unit = units.common();
        let k = unit.from_newtons(1.0);
        let u = unit.symbol();
        let curves = mags
            .iter()
            .map(|&i| {
                let r = &c.runs[i];
                let m = r.analysis.magnitude.as_ref().expect("filtered above");
                OverlayCurve {
                    label: run_legend(c, i),
                    color: i,
                    samples: m
                        .pairs
                        .iter()
                        .map(|p| (p.applied_n * k, p.measured_n * k))
                        .collect(),
                    levels: m
                        .calibration
                        .levels
                        .iter()
                        .map(|l| (l.applied_mean * k, l.measured_mean * k, l.measured_sd * k))
                        .collect(),
                }
            })
            .collect();
        out.push((
            "compare_magnitude".to_string(),
            format!(
                "Applied normal force (F/T sensor) against the reconstructed F^sum_z ({u}), one \
                 colour per run: samples (dots), level means ± 1 SD joined (lines); grey: identity"
            ),
            OverlayFigure {
                title: "force magnitude: applied against measured".into(),
                x_label: format!("applied Fz, F/T sensor ({u})"),
                y_label: format!("measured Fz sum ({u})"),
                curves,
            },
        ));
    }
    let angles: Vec<usize> = (0..c.runs.len())
        .filter(|&i| c.runs[i].analysis.angle.is_some())
        .collect();
    if !angles.is_empty() {
        let curves = angles
            .iter()
            .map(|&i| {
                let a = c.runs[i].analysis.angle.as_ref().expect("filtered above");
                OverlayCurve {
                    label: run_legend(c, i),
                    color: i,
                    samples: a
                        .pairs
                        .iter()
                        .map(|p| (p.applied_deg, p.measured_deg))
                        .collect(),
                    levels: a
                        .calibration
                        .levels
                        .iter()
                        .map(|l| (l.applied_mean, l.measured_mean, l.measured_sd))
                        .collect(),
                }
            })
            .collect();
        out.push((
            "compare_angle".to_string(),
            "Applied angle from the normal (F/T wrench) against the measured angle of F^sum \
             (deg), one colour per run: samples, level means ± 1 SD joined; grey: identity"
                .to_string(),
            OverlayFigure {
                title: "force angle: applied against measured".into(),
                x_label: "applied angle, F/T sensor (deg)".into(),
                y_label: "measured angle, F sum (deg)".into(),
                curves,
            },
        ));
    }
    out
}

fn run_legend(c: &Comparison, i: usize) -> String {
    let r = &c.runs[i];
    if r.is_baseline {
        format!("{} (baseline)", short(&r.label, 40))
    } else {
        short(&r.label, 40)
    }
}

/// The force units of several runs.
struct BTreeUnits(Vec<crate::units::ForceUnit>);

impl FromIterator<crate::units::ForceUnit> for BTreeUnits {
    fn from_iter<T: IntoIterator<Item = crate::units::ForceUnit>>(iter: T) -> Self {
        BTreeUnits(iter.into_iter().collect())
    }
}

impl BTreeUnits {
    /// The unit they share, else newtons.
    fn common(&self) -> crate::units::ForceUnit {
        match self.0.first() {
            Some(&u) if self.0.iter().all(|&v| v == u) => u,
            _ => crate::units::ForceUnit::Newton,
        }
    }
}

impl Figure for OverlayFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let grey = RGBColor(179, 179, 179);
        // The key in a strip above the plot, clear of the data.
        let mut entries = vec![(LegendGlyph::Line(grey), "identity".to_string())];
        entries.extend(
            self.curves
                .iter()
                .map(|c| (LegendGlyph::Line(run_color(c.color)), c.label.clone())),
        );
        entries.push((
            LegendGlyph::ErrorBar(BLACK),
            "level mean ± 1 SD, in the run's colour (light dots: its samples)".into(),
        ));
        let root = titled_with_legend(root, &self.title, &entries)?;
        let all = || self.curves.iter().flat_map(|c| c.samples.iter());
        let xs = span(all().map(|s| s.0));
        let ys = span(all().map(|s| s.1));
        let lo = xs.start.min(ys.start);
        let hi = xs.end.max(ys.end);
        let mut chart = ChartBuilder::on(&root)
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(64)
            .build_cartesian_2d(lo..hi, lo..hi)?;
        chart
            .configure_mesh()
            .x_desc(self.x_label.as_str())
            .y_desc(self.y_label.as_str())
            .x_label_formatter(&|v| fmt_value(snap(*v, &(lo..hi))))
            .y_label_formatter(&|v| fmt_value(snap(*v, &(lo..hi))))
            .label_style((FONT, 13))
            .draw()?;
        chart.draw_series(LineSeries::new([(lo, lo), (hi, hi)], grey.stroke_width(1)))?;
        for c in &self.curves {
            let color = run_color(c.color);
            chart.draw_series(
                c.samples
                    .iter()
                    .map(|&(x, y)| Circle::new((x, y), 2, color.mix(0.35).filled())),
            )?;
            chart.draw_series(c.levels.iter().map(|&(x, m, sd)| {
                ErrorBar::new_vertical(x, m - sd, m, m + sd, color.stroke_width(2), 8)
            }))?;
            chart.draw_series(LineSeries::new(
                c.levels.iter().map(|&(x, m, _)| (x, m)),
                color.stroke_width(2),
            ))?;
        }
        Ok(())
    }
}
