//! Figures of the simulation studies, drawn through the shared [`super::plot::Figure`]:
//!
//! - [`ParetoFigure`]: error against time per frame (both log scales) for every setting
//!   of the accuracy-against-time study, coloured by sweep, the Pareto front joined and
//!   labelled, error budgets as dashed lines; labels are placed by [`place_labels`]
//!   (greedy: Pareto-front labels first, each at the first of a ring of positions
//!   around its point that overlaps no placed label, no point and stays inside the
//!   plot area; a label with no free position is left out and its point keeps its
//!   colour);
//! - [`LayerSeparationFigure`]: the paper's Fig. 6 — mean absolute force difference
//!   against the layer separation on a true distance axis (mm), one line per solver with
//!   its own colour, marker and dash pattern, the single layer as a dashed level of the
//!   same colour, one panel per noise level, the legend in headroom above the data;
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

/// The 1-2-5 values in `[lo, hi]` (positive): labels of a log axis that spans any range
/// without crowding (plotters' own choice for 35–1300 µs labelled only 100…1000, with
/// 900 and 1000 running into each other, and nothing below 100).
fn one_two_five(lo: f64, hi: f64) -> Vec<f64> {
    let mut out = Vec::new();
    if !(lo > 0.0 && hi > lo && hi.is_finite()) {
        return out;
    }
    let mut decade = 10f64.powf(lo.log10().floor());
    while decade <= hi {
        for m in [1.0, 2.0, 5.0] {
            let v = m * decade;
            if v >= lo && v <= hi {
                out.push(v);
            }
        }
        decade *= 10.0;
    }
    out
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
            .build_cartesian_2d(
                (x0..x1).log_scale().with_key_points(one_two_five(x0, x1)),
                (y0..y1).log_scale(),
            )?;
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
        for p in pts.iter().filter(|p| p.on_front) {
            chart.draw_series(std::iter::once(Circle::new(
                (p.time_us, floor(p.error_pct)),
                8,
                RED.stroke_width(2),
            )))?;
        }
        // Labels: front first, then by error; pixel boxes placed without overlap.
        let mut order: Vec<&&ParetoPoint> = pts.iter().collect();
        order.sort_by(|a, b| {
            b.on_front
                .cmp(&a.on_front)
                .then(a.error_pct.total_cmp(&b.error_pct))
        });
        let base = root.get_base_pixel();
        let area = chart.plotting_area().get_pixel_range();
        let bounds = (
            area.0.start - base.0,
            area.1.start - base.1,
            area.0.end - base.0,
            area.1.end - base.1,
        );
        let font_of = |front: bool| {
            if front {
                (FONT, 12).into_font().color(&BLACK)
            } else {
                (FONT, 11).into_font().color(&RGBColor(110, 110, 110))
            }
        };
        let anchor = |p: &ParetoPoint| {
            let c = chart.backend_coord(&(p.time_us, floor(p.error_pct)));
            (c.0 - base.0, c.1 - base.1)
        };
        let obstacles: Vec<Rect> = pts
            .iter()
            .map(|p| {
                let (x, y) = anchor(p);
                (x - 6, y - 6, x + 6, y + 6)
            })
            .collect();
        let mut items = Vec::new();
        for p in &order {
            let (w, h) = root
                .estimate_text_size(&p.label, &font_of(p.on_front))
                .unwrap_or((6 * p.label.len() as u32, 12));
            items.push((anchor(p), (w as i32, h as i32)));
        }
        let placed = place_labels(&items, &obstacles, bounds);
        for (p, at) in order.iter().zip(placed) {
            if let Some((x, y)) = at {
                root.draw(&Text::new(p.label.clone(), (x, y), font_of(p.on_front)))?;
            }
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

/// A pixel box `(x0, y0, x1, y1)`.
pub type Rect = (i32, i32, i32, i32);

/// A label to place: its anchor point and its (width, height), px.
pub type LabelItem = ((i32, i32), (i32, i32));

fn overlaps(a: Rect, b: Rect) -> bool {
    a.0 < b.2 && b.0 < a.2 && a.1 < b.3 && b.1 < a.3
}

/// Greedy label placement: `items` are `(anchor point, (width, height))` in priority
/// order; each label goes to the first position of a ring around its anchor (right,
/// left, above, below, the diagonals, then the same one and two label heights farther
/// out) whose box lies inside `bounds`, overlaps no placed label and no `obstacles`
/// box (the points; the label's own point included). Returns each label's top-left
/// corner, `None` where no position is free.
pub fn place_labels(
    items: &[LabelItem],
    obstacles: &[Rect],
    bounds: Rect,
) -> Vec<Option<(i32, i32)>> {
    let mut placed: Vec<Rect> = Vec::new();
    let gap = 8;
    items
        .iter()
        .map(|&((ax, ay), (w, h))| {
            let mut candidates = Vec::new();
            for ring in 0..3 {
                let r = ring * (h + 2);
                candidates.extend([
                    (ax + gap + r, ay - h / 2),
                    (ax - gap - r - w, ay - h / 2),
                    (ax - w / 2, ay - gap - r - h),
                    (ax - w / 2, ay + gap + r),
                    (ax + gap + r, ay - gap - r - h),
                    (ax + gap + r, ay + gap + r),
                    (ax - gap - r - w, ay - gap - r - h),
                    (ax - gap - r - w, ay + gap + r),
                ]);
            }
            let free = candidates.into_iter().find(|&(x, y)| {
                let b = (x, y, x + w, y + h);
                b.0 >= bounds.0
                    && b.1 >= bounds.1
                    && b.2 <= bounds.2
                    && b.3 <= bounds.3
                    && !placed.iter().any(|p| overlaps(*p, b))
                    && !obstacles.iter().any(|o| overlaps(*o, b))
            });
            if let Some((x, y)) = free {
                placed.push((x, y, x + w, y + h));
            }
            free
        })
        .collect()
}

/// Line and marker style of the `i`-th solver series of the layer-separation plot.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mark {
    /// Hollow circle.
    Ring,
    /// Filled square.
    Square,
    /// Filled triangle.
    Triangle,
    /// Cross.
    Cross,
}

/// `(marker, dash: (on, off) px; (0, 0) solid, marker size px)` of series `i`: the
/// first series (pinv) is drawn largest and hollow, later ones smaller, so series that
/// coincide stay visible.
pub fn series_style(i: usize) -> (Mark, (u32, u32), i32) {
    match i % 4 {
        0 => (Mark::Ring, (0, 0), 7),
        1 => (Mark::Square, (10, 5), 5),
        2 => (Mark::Triangle, (3, 4), 5),
        _ => (Mark::Cross, (12, 4), 4),
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
        let dmax = self
            .cases
            .iter()
            .filter_map(|c| c.separation_mm())
            .fold(0.0f64, f64::max);
        let (x0, x1) = (-0.04 * dmax.max(1.0), dmax.max(1.0) * 1.04);
        for (area, panel) in areas.iter().zip(&self.panels) {
            let (noise, series) = (&panel.noise_px, &panel.series);
            let (y0, y1) = log_range(series.iter().flat_map(|(_, ys)| ys.iter().copied()));
            // Headroom above the data for the legend (40 % of the decades shown).
            let y1 = y1 * (y1 / y0).powf(0.4);
            let caption = if *noise == 0.0 {
                "exact displacements".to_string()
            } else {
                format!("displacement noise σ = {noise} px")
            };
            let base = area.get_base_pixel();
            let mut chart = ChartBuilder::on(area)
                .caption(caption, (FONT, 16))
                .margin(12)
                .x_label_area_size(45)
                .y_label_area_size(70)
                .build_cartesian_2d(x0..x1, (y0..y1).log_scale())?;
            chart
                .configure_mesh()
                .x_label_formatter(&|x| format!("{x:.0}"))
                .x_desc("separation d between the marker layers, mm (dashed level: single layer)")
                .y_label_formatter(&|v| format!("{v:.0e}"))
                .y_desc("mean |f − f*| over points and axes, gf")
                .label_style((FONT, 12))
                .axis_desc_style((FONT, 13))
                .draw()?;
            for (si, (_, ys)) in series.iter().enumerate() {
                let colour = SERIES[si % SERIES.len()];
                let (mark, dash, size) = series_style(si);
                let mut pts = Vec::new();
                let mut single = None;
                for (c, y) in self.cases.iter().zip(ys) {
                    if !(y.is_finite() && *y > 0.0) {
                        continue;
                    }
                    match c.separation_mm() {
                        Some(d) => pts.push((d, *y)),
                        None => single = Some(*y),
                    }
                }
                pts.sort_by(|a, b| a.0.total_cmp(&b.0));
                let line = colour.stroke_width(2);
                if dash.0 == 0 {
                    chart.draw_series(LineSeries::new(pts.clone(), line))?;
                } else {
                    chart.draw_series(DashedLineSeries::new(pts.clone(), dash.0, dash.1, line))?;
                }
                for p in &pts {
                    let c = chart.backend_coord(p);
                    mark_px(area, mark, colour, size, (c.0 - base.0, c.1 - base.1))?;
                }
                if let Some(y) = single {
                    chart.draw_series(DashedLineSeries::new(
                        [(x0, y), (x1, y)],
                        4,
                        6,
                        colour.mix(0.8).stroke_width(1),
                    ))?;
                }
            }
            // Legend, drawn by hand (each entry: line in its dash pattern + marker) in
            // the headroom at the top right of the plotting area.
            let (xr, yr) = chart.plotting_area().get_pixel_range();
            let font = (FONT, 12).into_font();
            let wmax = series
                .iter()
                .map(|(n, _)| {
                    area.estimate_text_size(n, &TextStyle::from(font.clone()))
                        .map_or(80, |s| s.0 as i32)
                })
                .max()
                .unwrap_or(80);
            let (lw, lh) = (wmax + 56, 20 * series.len() as i32 + 10);
            let (lx, ly) = (xr.end - base.0 - lw - 8, yr.start - base.1 + 8);
            area.draw(&Rectangle::new(
                [(lx, ly), (lx + lw, ly + lh)],
                WHITE.mix(0.9).filled(),
            ))?;
            area.draw(&Rectangle::new(
                [(lx, ly), (lx + lw, ly + lh)],
                BLACK.stroke_width(1),
            ))?;
            for (si, (solver, _)) in series.iter().enumerate() {
                let colour = SERIES[si % SERIES.len()];
                let (mark, dash, size) = series_style(si);
                let y = ly + 15 + 20 * si as i32;
                let (x0l, x1l) = (lx + 8, lx + 40);
                let line = colour.stroke_width(2);
                if dash.0 == 0 {
                    area.draw(&PathElement::new(vec![(x0l, y), (x1l, y)], line))?;
                } else {
                    let mut a = x0l;
                    while a < x1l {
                        let b = (a + dash.0 as i32).min(x1l);
                        area.draw(&PathElement::new(vec![(a, y), (b, y)], line))?;
                        a += (dash.0 + dash.1) as i32;
                    }
                }
                mark_px(area, mark, colour, size, ((x0l + x1l) / 2, y))?;
                area.draw(&Text::new(solver.clone(), (x1l + 8, y - 7), font.clone()))?;
            }
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

/// Draws marker `mark` centred on pixel `p` of `area` (pixel coordinates of the area).
fn mark_px<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    mark: Mark,
    colour: RGBColor,
    size: i32,
    p: (i32, i32),
) -> FigureResult<DB> {
    let (x, y) = p;
    match mark {
        Mark::Ring => area.draw(&Circle::new(p, size, colour.stroke_width(2)))?,
        Mark::Square => area.draw(&Rectangle::new(
            [(x - size, y - size), (x + size, y + size)],
            colour.filled(),
        ))?,
        Mark::Triangle => area.draw(&Polygon::new(
            vec![
                (x, y - size - 1),
                (x - size - 1, y + size),
                (x + size + 1, y + size),
            ],
            colour.filled(),
        ))?,
        Mark::Cross => area.draw(&Cross::new(p, size, colour.stroke_width(2)))?,
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pareto_time_axis_is_labelled_1_2_5_across_the_whole_range() {
        // The accuracy-vs-time plot spanned 35–1300 µs and was labelled 100, 200, …, 900,
        // 1000 with the last two overlapping and nothing below 100.
        assert_eq!(
            one_two_five(35.0, 1300.0),
            vec![50.0, 100.0, 200.0, 500.0, 1000.0]
        );
        assert_eq!(one_two_five(0.8, 3.0), vec![1.0, 2.0]);
        assert!(one_two_five(0.0, 10.0).is_empty());
    }

    /// The 90–130 µs cluster of the Pareto plot: ten points a few pixels apart, and a
    /// point at the right edge. Placed labels never overlap each other or a point, and
    /// stay inside the plot area (the rightmost label went out of it before).
    #[test]
    fn pareto_labels_in_a_cluster_do_not_overlap_and_stay_inside() {
        let bounds = (80, 40, 1380, 820);
        let mut anchors: Vec<(i32, i32)> =
            (0..10).map(|i| (300 + 9 * i, 500 + 7 * (i % 3))).collect();
        anchors.push((1370, 780));
        let items: Vec<_> = anchors.iter().map(|&a| (a, (150, 13))).collect();
        let obstacles: Vec<Rect> = anchors
            .iter()
            .map(|&(x, y)| (x - 6, y - 6, x + 6, y + 6))
            .collect();
        let placed = place_labels(&items, &obstacles, bounds);
        let boxes: Vec<Rect> = placed
            .iter()
            .zip(&items)
            .filter_map(|(p, (_, (w, h)))| p.map(|(x, y)| (x, y, x + w, y + h)))
            .collect();
        assert!(boxes.len() >= 8, "only {} of 11 labels placed", boxes.len());
        assert!(placed[10].is_some(), "the edge label was dropped");
        for (i, a) in boxes.iter().enumerate() {
            assert!(
                a.0 >= bounds.0 && a.1 >= bounds.1 && a.2 <= bounds.2 && a.3 <= bounds.3,
                "{a:?} outside"
            );
            for b in &boxes[i + 1..] {
                assert!(!overlaps(*a, *b), "{a:?} overlaps {b:?}");
            }
            for o in &obstacles {
                assert!(!overlaps(*a, *o), "{a:?} covers a point");
            }
        }
    }

    /// pinv and tsvd coincide on exact data: every series has its own marker and dash
    /// pattern, and the first (pinv) is a hollow ring larger than the later markers.
    #[test]
    fn layer_series_styles_are_distinct_and_pinv_stays_visible_under_tsvd() {
        let styles: Vec<_> = (0..4).map(series_style).collect();
        for i in 0..4 {
            for j in i + 1..4 {
                assert_ne!(styles[i].0, styles[j].0);
                assert_ne!(styles[i].1, styles[j].1);
            }
        }
        assert_eq!(styles[0].0, Mark::Ring);
        assert!(styles[0].2 > styles[3].2);
    }
}
