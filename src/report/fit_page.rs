//! `fit.html`: the page `tactbench fit` writes beside `fit.json`, drawn from the
//! [`FitDoc`] alone (it never re-fits). Self-contained like `report.html`: the figures
//! are PNGs drawn through [`super::plot::Figure`] and embedded as data URIs.
//!
//! Sections, each shown when the document holds its data (and said to be absent
//! otherwise, never drawn from made-up numbers):
//! - the parameter table: value, 95 % interval, unit, nominal, identifiable, fitted,
//!   route, and the reason a parameter is held or not identifiable;
//! - the two routes side by side (`routes.indentation`, `routes.displacement`: each a
//!   `parameters` map like the top-level one plus scalar figures), per parameter
//!   whether their intervals overlap, and the fit's own `agree` / `disagreements`;
//! - residual RMS per layer and the parameter correlations (`extra.correlations`);
//! - measured against predicted marker displacements at a few setpoints
//!   (`extra.examples`, quiver-style, one panel per setpoint);
//! - the residual RMS against setpoint (`extra.setpoint_residuals`);
//! - the indentation curve with the fitted contact law (`extra.indentation_curve`);
//! - cross-validation (`cross_validation`, every number it holds).
//!
//! The shapes of the `extra` entries are documented in [`crate::fit::doc`].

use std::collections::BTreeMap;
use std::fmt::Write;
use std::path::Path;

use base64::Engine;
use plotters::coord::Shift;
use plotters::prelude::*;
use serde_json::Value;

use super::acceptance::fmt_value;
use super::compare::RUN_COLORS;
use super::force_map::{arrow_parts, draw_arrows};
use super::markup::escape;
use super::plot::{self, titled_with_legend, Figure, FigureResult, LegendGlyph, FONT};
use super::ReportError;
use crate::fit::{FitDoc, Route};

/// Measured data (blue) and the model's prediction (vermillion), Okabe–Ito.
const MEASURED: RGBColor = RGBColor(0, 114, 178);
const PREDICTED: RGBColor = RGBColor(213, 94, 0);
/// Setpoints drawn in the displacement figure (the first ones `extra.examples` lists).
pub const MAX_EXAMPLE_SETPOINTS: usize = 4;

/// One indentation sample: depth past contact (mm), measured and predicted normal
/// force (N).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IndentationPoint {
    /// Depth past contact, mm.
    pub depth_mm: f64,
    /// F/T normal force, N.
    pub force_n: f64,
    /// The fitted contact law's force at that depth, N.
    pub predicted_n: f64,
}

/// The indentation curve: measured force against depth and the fitted law.
#[derive(Debug, Clone, PartialEq)]
pub struct IndentationFigure {
    /// The samples.
    pub points: Vec<IndentationPoint>,
}

/// The displacement route's residual RMS per setpoint (per layer where given).
#[derive(Debug, Clone, PartialEq)]
pub struct SetpointResidualFigure {
    /// `(layer or "", [(setpoint index, rms px)])`.
    pub series: Vec<(String, Vec<(f64, f64)>)>,
}

/// One marker's measured and predicted displacement at one setpoint.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExampleArrow {
    /// Marker position, mm (sensor frame).
    pub at_mm: [f64; 2],
    /// Measured displacement, px.
    pub measured_px: [f64; 2],
    /// Predicted displacement, px.
    pub predicted_px: [f64; 2],
}

/// Measured against predicted displacements, one panel per setpoint.
#[derive(Debug, Clone, PartialEq)]
pub struct DisplacementFigure {
    /// `(setpoint index, arrows)`.
    pub panels: Vec<(usize, Vec<ExampleArrow>)>,
}

fn num(v: &Value, key: &str) -> Option<f64> {
    v.get(key).and_then(Value::as_f64).filter(|x| x.is_finite())
}

impl IndentationFigure {
    /// From `extra.indentation_curve` (`None` without usable points).
    pub fn from_doc(doc: &FitDoc) -> Option<IndentationFigure> {
        let points: Vec<IndentationPoint> = doc
            .extra
            .get("indentation_curve")?
            .as_array()?
            .iter()
            .filter_map(|p| {
                Some(IndentationPoint {
                    depth_mm: num(p, "depth_mm")?,
                    force_n: num(p, "force_n")?,
                    predicted_n: num(p, "predicted_n")?,
                })
            })
            .collect();
        (!points.is_empty()).then_some(IndentationFigure { points })
    }
}

impl SetpointResidualFigure {
    /// From `extra.setpoint_residuals` (`None` without usable points).
    pub fn from_doc(doc: &FitDoc) -> Option<SetpointResidualFigure> {
        let mut series: BTreeMap<String, Vec<(f64, f64)>> = BTreeMap::new();
        for p in doc.extra.get("setpoint_residuals")?.as_array()? {
            let (Some(i), Some(r)) = (num(p, "index"), num(p, "rms_px")) else {
                continue;
            };
            let layer = p.get("layer").and_then(Value::as_str).unwrap_or_default();
            series.entry(layer.to_string()).or_default().push((i, r));
        }
        let series: Vec<_> = series.into_iter().collect();
        (!series.is_empty()).then_some(SetpointResidualFigure { series })
    }
}

impl DisplacementFigure {
    /// From `extra.examples`: the first [`MAX_EXAMPLE_SETPOINTS`] setpoints it lists
    /// (`None` without usable rows).
    pub fn from_doc(doc: &FitDoc) -> Option<DisplacementFigure> {
        let mut panels: Vec<(usize, Vec<ExampleArrow>)> = Vec::new();
        for e in doc.extra.get("examples")?.as_array()? {
            let vals =
                ["x_mm", "y_mm", "ux_px", "uy_px", "pred_ux_px", "pred_uy_px"].map(|k| num(e, k));
            let (Some(index), [Some(x), Some(y), Some(ux), Some(uy), Some(px), Some(py)]) =
                (e.get("index").and_then(Value::as_u64), vals)
            else {
                continue;
            };
            let arrow = ExampleArrow {
                at_mm: [x, y],
                measured_px: [ux, uy],
                predicted_px: [px, py],
            };
            let index = index as usize;
            if let Some((_, arrows)) = panels.iter_mut().find(|(i, _)| *i == index) {
                arrows.push(arrow);
            } else if panels.len() < MAX_EXAMPLE_SETPOINTS {
                panels.push((index, vec![arrow]));
            }
        }
        (!panels.is_empty()).then_some(DisplacementFigure { panels })
    }

    /// mm of plot per px of displacement: the longest arrow is drawn 0.9 marker
    /// spacings long (the spacing estimated as the extent over √markers), so arrows
    /// do not cross their neighbours.
    pub fn mm_per_px(&self) -> f64 {
        let all = self.panels.iter().flat_map(|(_, a)| a);
        let longest = all
            .clone()
            .flat_map(|a| [a.measured_px, a.predicted_px])
            .map(|u| u[0].hypot(u[1]))
            .fold(0.0f64, f64::max);
        let (xs, ys) = self.extent();
        let n = self.panels.iter().map(|(_, a)| a.len()).max().unwrap_or(1) as f64;
        let spacing = (xs.end - xs.start).max(ys.end - ys.start) / n.sqrt().max(1.0);
        if longest > 0.0 {
            0.9 * spacing / longest
        } else {
            0.0
        }
    }

    /// The markers' extent, mm, padded by 10 %.
    pub fn extent(&self) -> (std::ops::Range<f64>, std::ops::Range<f64>) {
        let pts: Vec<[f64; 2]> = self
            .panels
            .iter()
            .flat_map(|(_, a)| a.iter().map(|a| a.at_mm))
            .collect();
        let range = |k: usize| {
            let lo = pts.iter().map(|p| p[k]).fold(f64::INFINITY, f64::min);
            let hi = pts.iter().map(|p| p[k]).fold(f64::NEG_INFINITY, f64::max);
            let pad = (0.1 * (hi - lo)).max(0.5);
            (lo - pad)..(hi + pad)
        };
        (range(0), range(1))
    }
}

impl Figure for IndentationFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let legend = [
            (LegendGlyph::Dot(MEASURED), "F/T normal force".to_string()),
            (
                LegendGlyph::Line(PREDICTED),
                "fitted contact law".to_string(),
            ),
        ];
        let area = titled_with_legend(root, "indentation: force against depth", &legend)?;
        let xmax = self.points.iter().map(|p| p.depth_mm).fold(0.0, f64::max);
        let ys = self.points.iter().flat_map(|p| [p.force_n, p.predicted_n]);
        let ymax = ys.clone().fold(0.0, f64::max);
        let ymin = ys.fold(0.0, f64::min);
        let xmin = self.points.iter().map(|p| p.depth_mm).fold(0.0, f64::min);
        let mut chart = ChartBuilder::on(&area)
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(
                xmin..(xmax * 1.05).max(xmin + 1e-3),
                ymin..(ymax * 1.08).max(ymin + 1e-6),
            )?;
        chart
            .configure_mesh()
            .x_desc("depth past contact (mm)")
            .y_desc("normal force (N)")
            .label_style((FONT, 13))
            .draw()?;
        let mut curve: Vec<(f64, f64)> = self
            .points
            .iter()
            .map(|p| (p.depth_mm, p.predicted_n))
            .collect();
        curve.sort_by(|a, b| a.0.total_cmp(&b.0));
        chart.draw_series(LineSeries::new(curve, PREDICTED.stroke_width(2)))?;
        chart.draw_series(
            self.points
                .iter()
                .map(|p| Circle::new((p.depth_mm, p.force_n), 4, MEASURED.filled())),
        )?;
        Ok(())
    }
}

impl Figure for SetpointResidualFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let color = |i: usize| {
            let (r, g, b) = RUN_COLORS[i % RUN_COLORS.len()];
            RGBColor(r, g, b)
        };
        let legend: Vec<(LegendGlyph, String)> = self
            .series
            .iter()
            .enumerate()
            .map(|(i, (layer, _))| {
                let name = if layer.is_empty() {
                    "residual RMS".to_string()
                } else {
                    format!("layer {layer}")
                };
                (LegendGlyph::Dot(color(i)), name)
            })
            .collect();
        let area = titled_with_legend(root, "displacement residual RMS per setpoint", &legend)?;
        let pts = self.series.iter().flat_map(|(_, p)| p);
        let xmax = pts.clone().map(|p| p.0).fold(0.0, f64::max);
        let ymax = pts.map(|p| p.1).fold(0.0, f64::max);
        let mut chart = ChartBuilder::on(&area)
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(-0.5..xmax + 0.5, 0.0..(ymax * 1.1).max(1e-6))?;
        chart
            .configure_mesh()
            .x_desc("setpoint index")
            .y_desc("residual RMS (px)")
            .label_style((FONT, 13))
            .draw()?;
        for (i, (_, p)) in self.series.iter().enumerate() {
            let mut p = p.clone();
            p.sort_by(|a, b| a.0.total_cmp(&b.0));
            chart.draw_series(LineSeries::new(
                p.clone(),
                color(i).mix(0.5).stroke_width(1),
            ))?;
            chart.draw_series(p.into_iter().map(|q| Circle::new(q, 3, color(i).filled())))?;
        }
        Ok(())
    }
}

impl Figure for DisplacementFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let k = self.mm_per_px();
        let (xs, ys) = self.extent();
        let legend = [
            (
                LegendGlyph::Line(MEASURED),
                "measured (tracked)".to_string(),
            ),
            (
                LegendGlyph::Line(PREDICTED),
                "predicted (fitted model)".to_string(),
            ),
        ];
        let title = format!(
            "marker displacements: measured and predicted (1 px drawn {} mm long)",
            fmt_value(k)
        );
        let area = titled_with_legend(root, &title, &legend)?;
        let cols = self.panels.len().min(2);
        let rows = self.panels.len().div_ceil(2);
        let cells = area.split_evenly((rows, cols));
        for ((index, arrows), cell) in self.panels.iter().zip(cells.iter()) {
            let mut chart = ChartBuilder::on(cell)
                .caption(format!("setpoint {index}"), (FONT, 15))
                .margin(8)
                .x_label_area_size(28)
                .y_label_area_size(40)
                .build_cartesian_2d(xs.clone(), ys.clone())?;
            chart
                .configure_mesh()
                .x_desc("x (mm)")
                .y_desc("y (mm)")
                .label_style((FONT, 11))
                .draw()?;
            let head = 0.02 * (xs.end - xs.start);
            let parts = |f: fn(&ExampleArrow) -> [f64; 2]| -> Vec<_> {
                arrows
                    .iter()
                    .filter_map(|a| {
                        let u = f(a);
                        let b = (a.at_mm[0] + k * u[0], a.at_mm[1] + k * u[1]);
                        arrow_parts((a.at_mm[0], a.at_mm[1]), b, head)
                    })
                    .collect()
            };
            draw_arrows(&mut chart, &parts(|a| a.measured_px), MEASURED, 2)?;
            draw_arrows(&mut chart, &parts(|a| a.predicted_px), PREDICTED, 1)?;
            chart.draw_series(
                arrows
                    .iter()
                    .map(|a| Circle::new((a.at_mm[0], a.at_mm[1]), 1, BLACK.filled())),
            )?;
        }
        Ok(())
    }
}

/// The figure sizes, px.
const FIGURE_SIZE: (u32, u32) = (900, 560);
const QUIVER_SIZE: (u32, u32) = (1000, 900);

fn route_word(r: Route) -> &'static str {
    match r {
        Route::Indentation => "indentation",
        Route::Displacement => "displacement",
        Route::Both => "both",
    }
}

fn ci_text(ci: Option<[f64; 2]>) -> String {
    ci.map_or("&mdash;".into(), |[lo, hi]| {
        format!("[{}, {}]", fmt_value(lo), fmt_value(hi))
    })
}

fn unit_text(u: &str) -> &str {
    if u == "1" {
        ""
    } else {
        u
    }
}

/// The parameter table.
fn parameter_table(o: &mut String, doc: &FitDoc) {
    o.push_str(
        "<h2 id=\"parameters\">Parameters</h2>\n<table class=\"parameters\">\n<tr>\
         <th class=\"l\">parameter</th><th>value</th><th>95 % CI</th><th class=\"l\">unit</th>\
         <th>nominal</th><th>change</th><th class=\"l\">identifiable</th><th class=\"l\">fitted</th>\
         <th class=\"l\">route</th><th class=\"l\">reason</th></tr>\n",
    );
    for (name, p) in &doc.parameters {
        let change = if p.fitted && p.nominal != 0.0 {
            format!("{:+.1} %", 100.0 * (p.value - p.nominal) / p.nominal.abs())
        } else if p.fitted {
            format!("{:+}", fmt_value(p.value - p.nominal))
        } else {
            "&mdash;".into()
        };
        let class = if !p.identifiable {
            " class=\"held\""
        } else {
            ""
        };
        let _ = writeln!(
            o,
            "<tr{class}><td class=\"l\"><code>{}</code></td><td>{}</td><td>{}</td>\
             <td class=\"l\">{}</td><td>{}</td><td>{change}</td><td class=\"l\">{}</td>\
             <td class=\"l\">{}</td><td class=\"l\">{}</td><td class=\"l reason\">{}</td></tr>",
            escape(name),
            fmt_value(p.value),
            ci_text(p.ci95),
            escape(unit_text(&p.unit)),
            fmt_value(p.nominal),
            if p.identifiable { "yes" } else { "<b>no</b>" },
            if p.fitted { "yes" } else { "held at nominal" },
            route_word(p.route),
            p.reason.as_deref().map_or(String::new(), escape)
        );
    }
    o.push_str("</table>\n");
    let method = doc
        .extra
        .get("ci_method")
        .and_then(Value::as_str)
        .unwrap_or("not recorded");
    let _ = writeln!(
        o,
        "<p>Intervals: {}. A parameter the run cannot determine is held at its nominal \
         value and has no interval; the reason says what kind of setpoint would determine \
         it.</p>",
        escape(method)
    );
}

/// A route's parameters (`routes.<route>.parameters`, [`ParamFit`]-shaped).
fn route_params(route: &Value) -> BTreeMap<String, (f64, Option<[f64; 2]>)> {
    let mut out = BTreeMap::new();
    let Some(params) = route.get("parameters").and_then(Value::as_object) else {
        return out;
    };
    for (name, p) in params {
        let Some(v) = num(p, "value") else { continue };
        let ci = p.get("ci95").and_then(Value::as_array).and_then(|a| {
            let lo = a.first()?.as_f64()?;
            let hi = a.get(1)?.as_f64()?;
            (lo.is_finite() && hi.is_finite()).then_some([lo, hi])
        });
        out.insert(name.clone(), (v, ci));
    }
    out
}

/// Every scalar in `v`, with dotted keys (arrays of scalars joined), for the
/// key/value tables of the routes and cross-validation.
fn scalars(prefix: &str, v: &Value, out: &mut Vec<(String, String)>) {
    let key = |k: &str| {
        if prefix.is_empty() {
            k.to_string()
        } else {
            format!("{prefix}.{k}")
        }
    };
    match v {
        Value::Object(m) => {
            for (k, x) in m {
                if prefix.is_empty() && k == "parameters" {
                    continue;
                }
                scalars(&key(k), x, out);
            }
        }
        Value::Number(n) => out.push((prefix.into(), n.as_f64().map_or(n.to_string(), fmt_value))),
        Value::Bool(b) => out.push((prefix.into(), b.to_string())),
        Value::String(s) => out.push((prefix.into(), s.clone())),
        Value::Array(a) if a.iter().all(|x| !x.is_object() && !x.is_array()) => {
            let items: Vec<String> = a
                .iter()
                .map(|x| x.as_f64().map_or(x.to_string(), fmt_value))
                .collect();
            out.push((prefix.into(), items.join(", ")));
        }
        Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                scalars(&key(&i.to_string()), x, out);
            }
        }
        Value::Null => {}
    }
}

fn kv_table(o: &mut String, rows: &[(String, String)]) {
    o.push_str("<table class=\"kv\">\n");
    for (k, v) in rows {
        let _ = writeln!(
            o,
            "<tr><th class=\"l\"><code>{}</code></th><td class=\"l\">{}</td></tr>",
            escape(k),
            escape(v)
        );
    }
    o.push_str("</table>\n");
}

/// The routes side by side: per parameter each route's value and interval and whether
/// the intervals overlap; then each route's own figures and the fit's verdict.
fn routes_section(o: &mut String, doc: &FitDoc) {
    o.push_str("<h2 id=\"routes\">The two routes</h2>\n");
    let ind = doc
        .routes
        .get("indentation")
        .cloned()
        .unwrap_or(Value::Null);
    let dis = doc
        .routes
        .get("displacement")
        .cloned()
        .unwrap_or(Value::Null);
    if ind.is_null() && dis.is_null() {
        o.push_str("<p class=\"absent\">The fit recorded no per-route results.</p>\n");
        return;
    }
    let (pi, pd) = (route_params(&ind), route_params(&dis));
    let mut names: Vec<&String> = pi.keys().chain(pd.keys()).collect();
    names.sort();
    names.dedup();
    o.push_str(
        "<table class=\"routes\">\n<tr><th class=\"l\">parameter</th><th>indentation</th>\
         <th>95 % CI</th><th>displacement</th><th>95 % CI</th><th class=\"l\">intervals</th></tr>\n",
    );
    for n in names {
        let cell = |m: &BTreeMap<String, (f64, Option<[f64; 2]>)>| match m.get(n) {
            Some((v, ci)) => (fmt_value(*v), ci_text(*ci)),
            None => ("&mdash;".into(), "&mdash;".into()),
        };
        let ((vi, ci), (vd, cd)) = (cell(&pi), cell(&pd));
        let agree = match (pi.get(n).and_then(|p| p.1), pd.get(n).and_then(|p| p.1)) {
            (Some([a, b]), Some([c, d])) if a <= d && c <= b => {
                "<span class=\"pass\">overlap</span>"
            }
            (Some(_), Some(_)) => "<span class=\"fail\">disagree</span>",
            _ => "one route only",
        };
        let _ = writeln!(
            o,
            "<tr><td class=\"l\"><code>{}</code></td><td>{vi}</td><td>{ci}</td><td>{vd}</td>\
             <td>{cd}</td><td class=\"l\">{agree}</td></tr>",
            escape(n)
        );
    }
    o.push_str("</table>\n");
    match doc.routes.get("agree").and_then(Value::as_bool) {
        Some(true) => {
            o.push_str("<p class=\"agree\"><b>The routes agree</b> within their intervals.</p>\n")
        }
        Some(false) => o.push_str(
            "<p class=\"disagree\"><b class=\"fail\">The routes disagree</b> beyond their \
             intervals: the model does not describe this gel.</p>\n",
        ),
        None => {}
    }
    if let Some(d) = doc.routes.get("disagreements").and_then(Value::as_array) {
        o.push_str("<ul class=\"disagreements\">\n");
        for m in d.iter().filter_map(Value::as_str) {
            let _ = writeln!(o, "<li>{}</li>", escape(m));
        }
        o.push_str("</ul>\n");
    }
    for (name, route) in [("indentation", &ind), ("displacement", &dis)] {
        let mut rows = Vec::new();
        scalars("", route, &mut rows);
        if !rows.is_empty() {
            let _ = writeln!(o, "<h3>{name} route</h3>");
            kv_table(o, &rows);
        }
    }
}

/// Residual RMS per layer and the correlation matrix.
fn residuals_section(o: &mut String, doc: &FitDoc) {
    o.push_str("<h2 id=\"residuals\">Residuals and correlations</h2>\n");
    if doc.residual_rms_px.is_empty() {
        o.push_str("<p class=\"absent\">No residual RMS per layer recorded.</p>\n");
    } else {
        o.push_str("<table>\n<tr><th class=\"l\">layer</th><th>residual RMS (px)</th></tr>\n");
        for (layer, rms) in &doc.residual_rms_px {
            let _ = writeln!(
                o,
                "<tr><td class=\"l\">{}</td><td>{}</td></tr>",
                escape(layer),
                fmt_value(*rms)
            );
        }
        o.push_str("</table>\n");
    }
    let Some(c) = doc.extra.get("correlations") else {
        return;
    };
    let names: Vec<&str> = c
        .get("names")
        .and_then(Value::as_array)
        .map(|a| a.iter().filter_map(Value::as_str).collect())
        .unwrap_or_default();
    let Some(matrix) = c.get("matrix").and_then(Value::as_array) else {
        return;
    };
    o.push_str("<p>Parameter correlations (|r| near 1: the run barely tells them apart):</p>\n<table class=\"correlations\">\n<tr><th></th>");
    for n in &names {
        let _ = write!(o, "<th><code>{}</code></th>", escape(n));
    }
    o.push_str("</tr>\n");
    for (i, row) in matrix.iter().enumerate() {
        let _ = write!(
            o,
            "<tr><th class=\"l\"><code>{}</code></th>",
            escape(names.get(i).copied().unwrap_or("?"))
        );
        for r in row.as_array().into_iter().flatten() {
            let r = r.as_f64().unwrap_or(f64::NAN);
            // Shade by |r|: white at 0, orange at 1.
            let t = r.abs().clamp(0.0, 1.0);
            let shade = (255.0 - 90.0 * t) as u8;
            let _ = write!(
                o,
                "<td style=\"background:rgb(255,{shade},{})\">{:.2}</td>",
                (255.0 - 200.0 * t) as u8,
                r
            );
        }
        o.push_str("</tr>\n");
    }
    o.push_str("</table>\n");
}

fn embed(o: &mut String, id: &str, caption: &str, png: &[u8]) {
    let b64 = base64::engine::general_purpose::STANDARD;
    let _ = writeln!(
        o,
        "<figure id=\"{id}\"><img alt=\"{}\" src=\"data:image/png;base64,{}\">\
         <figcaption>{}</figcaption></figure>",
        escape(caption),
        b64.encode(png),
        escape(caption)
    );
}

fn png(fig: &impl Figure, size: (u32, u32), stem: &str) -> Result<Vec<u8>, ReportError> {
    plot::render_png(fig, size).map_err(|message| {
        ReportError::Plot(super::plot::PlotError::Draw {
            figure: stem.to_string(),
            message,
        })
    })
}

/// The figures, each or the sentence saying it is absent.
fn figures_section(o: &mut String, doc: &FitDoc) -> Result<(), ReportError> {
    o.push_str("<h2 id=\"figures\">Measured against predicted</h2>\n");
    match DisplacementFigure::from_doc(doc) {
        Some(f) => embed(
            o,
            "fit_displacements",
            &format!(
                "Marker displacements at {} setpoint(s): measured (tracked, blue) and predicted \
                 by the fitted model from the measured wrench (vermillion), drawn {} mm per px \
                 of displacement.",
                f.panels.len(),
                fmt_value(f.mm_per_px())
            ),
            &png(&f, QUIVER_SIZE, "fit_displacements")?,
        ),
        None => o.push_str("<p class=\"absent\">No example displacements recorded (fit.json <code>examples</code>).</p>\n"),
    }
    match SetpointResidualFigure::from_doc(doc) {
        Some(f) => embed(
            o,
            "fit_residuals",
            "Residual RMS of the displacement route per setpoint (px): a setpoint far above \
             the others is one the model does not describe (or a tracking fault).",
            &png(&f, FIGURE_SIZE, "fit_residuals")?,
        ),
        None => o.push_str("<p class=\"absent\">No per-setpoint residuals recorded (fit.json <code>setpoint_residuals</code>).</p>\n"),
    }
    match IndentationFigure::from_doc(doc) {
        Some(f) => embed(
            o,
            "fit_indentation",
            &format!(
                "Indentation route: F/T normal force against the stage's depth past contact \
                 ({} samples) and the fitted contact law.",
                f.points.len()
            ),
            &png(&f, FIGURE_SIZE, "fit_indentation")?,
        ),
        None => o.push_str("<p class=\"absent\">No indentation curve recorded (fit.json <code>indentation_curve</code>).</p>\n"),
    }
    Ok(())
}

const STYLE: &str = "body{font-family:sans-serif;max-width:70em;margin:1em auto;padding:0 1em;color:#222}\
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #bbb;padding:2px 8px;text-align:right}\
th{background:#eee}td{white-space:nowrap}td.l,th.l{text-align:left}td.reason{white-space:normal}.pass{color:#070;font-weight:bold}.fail{color:#b00;font-weight:bold}\
tr.held td{color:#777}.absent{color:#777;font-style:italic}figure{margin:1em 0}img{max-width:100%}\
figcaption{font-size:.9em;color:#444}";

/// The page as HTML text.
pub fn render_fit_page(doc: &FitDoc) -> Result<String, ReportError> {
    let mut o = String::new();
    let _ = writeln!(
        o,
        "<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>fit: {}</title>\
         <style>{STYLE}</style></head><body>\n<h1>Sensor-model fit</h1>\n<p>run <code>{}</code>, \
         nominal sensor <code>{}</code> ({} parameters, {} fitted, {} not identifiable)</p>",
        escape(&doc.run),
        escape(&doc.run),
        escape(&doc.sensor),
        doc.parameters.len(),
        doc.parameters.values().filter(|p| p.fitted).count(),
        doc.parameters.values().filter(|p| !p.identifiable).count()
    );
    parameter_table(&mut o, doc);
    routes_section(&mut o, doc);
    residuals_section(&mut o, doc);
    figures_section(&mut o, doc)?;
    o.push_str("<h2 id=\"cross-validation\">Cross-validation</h2>\n");
    let mut rows = Vec::new();
    scalars("", &doc.cross_validation, &mut rows);
    if rows.is_empty() {
        o.push_str("<p class=\"absent\">No cross-validation recorded.</p>\n");
    } else {
        o.push_str("<p>Force-sum error on held-out setpoints with the nominal and with the fitted sensor file:</p>\n");
        kv_table(&mut o, &rows);
    }
    let _ = writeln!(
        o,
        "<hr><p><small>generated by tactbench {} from fit.json ({})</small></p></body></html>",
        escape(env!("CARGO_PKG_VERSION")),
        escape(&doc.schema)
    );
    Ok(o)
}

/// Writes `fit.html` for `doc` at `out` (the `fit` command calls it beside `fit.json`).
pub fn write_fit_page(doc: &FitDoc, out: &Path) -> Result<(), ReportError> {
    let page = render_fit_page(doc)?;
    std::fs::write(out, page).map_err(|source| ReportError::Io {
        path: out.to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::{ParamFit, FIT_SCHEMA};
    use serde_json::json;

    fn fitted(value: f64, half: f64, nominal: f64, unit: &str, route: Route) -> ParamFit {
        ParamFit {
            value,
            ci95: Some([value - half, value + half]),
            unit: unit.into(),
            identifiable: true,
            route,
            nominal,
            sd: Some(half / 1.96),
            fitted: true,
            reason: None,
        }
    }

    /// A fit of a sphere (R = 2.5 mm) on a gel of E = 70 kPa, ν = 0.5: the indentation
    /// samples follow Hertz, F = 4/3 E/(1-ν²) √R d^1.5, measured with a small ripple;
    /// the example displacements are a radial field around the contact, the
    /// prediction 5 % short of it.
    pub(crate) fn sample_doc() -> FitDoc {
        let e_star = 0.070 / (1.0 - 0.25); // N/mm²
        let hertz = |d: f64| 4.0 / 3.0 * e_star * 2.5f64.sqrt() * d.powf(1.5);
        let curve: Vec<Value> = (1..=16)
            .map(|k| {
                let d = 0.1 * k as f64;
                let ripple = 0.004 * ((k * 7) % 5) as f64 - 0.008;
                json!({"depth_mm": d, "force_n": hertz(d) + ripple, "predicted_n": hertz(d)})
            })
            .collect();
        let mut examples = Vec::new();
        for (s, c) in [(3usize, [9.0, 6.75]), (7, [6.0, 6.0]), (11, [12.0, 8.0])] {
            for i in 0..7 {
                for j in 0..6 {
                    let (x, y) = (3.0 + 2.0 * i as f64, 2.0 + 2.0 * j as f64);
                    let (dx, dy) = (x - c[0], y - c[1]);
                    let g = 3.0 * (-(dx * dx + dy * dy) / 8.0).exp();
                    examples.push(json!({"index": s, "layer": "blue", "x_mm": x, "y_mm": y,
                        "ux_px": g * dx / 2.0, "uy_px": g * dy / 2.0,
                        "pred_ux_px": 0.95 * g * dx / 2.0, "pred_uy_px": 0.95 * g * dy / 2.0}));
                }
            }
        }
        let residuals: Vec<Value> = (0..12)
            .flat_map(|i| {
                let r = 0.05 + 0.01 * (i % 3) as f64;
                [
                    json!({"index": i, "layer": "blue", "rms_px": r}),
                    json!({"index": i, "layer": "red", "rms_px": 1.3 * r}),
                ]
            })
            .collect();
        let mut parameters = BTreeMap::new();
        parameters.insert(
            "young_modulus_kpa".into(),
            fitted(70.4, 2.1, 100.0, "kPa", Route::Both),
        );
        parameters.insert(
            "depth_mm.blue".into(),
            fitted(3.48, 0.06, 3.0, "mm", Route::Displacement),
        );
        let mut thick = fitted(40.0, 0.0, 40.0, "mm", Route::Displacement);
        (thick.ci95, thick.sd, thick.fitted, thick.identifiable) = (None, None, false, false);
        thick.reason = Some(
            "a 40 mm gel's field does not depend on its thickness <here>: a thin-layer \
             setpoint would"
                .into(),
        );
        parameters.insert("thickness_mm".into(), thick);
        let mut extra = BTreeMap::new();
        extra.insert("indentation_curve".into(), Value::Array(curve));
        extra.insert("examples".into(), Value::Array(examples));
        extra.insert("setpoint_residuals".into(), Value::Array(residuals));
        extra.insert(
            "correlations".into(),
            json!({"names": ["young_modulus_kpa", "depth_mm.blue"], "matrix": [[1.0, -0.62], [-0.62, 1.0]]}),
        );
        extra.insert(
            "ci_method".into(),
            json!("jacobian (Gauss-Newton covariance scaled by the residual variance)"),
        );
        FitDoc {
            schema: FIT_SCHEMA.into(),
            run: "runs/build-7".into(),
            sensor: "experiments/paper_sensor.toml".into(),
            parameters,
            routes: json!({
                "indentation": {"parameters": {"young_modulus_kpa": {"value": 70.9, "ci95": [68.0, 73.8]}},
                                "samples": 16, "residual_rms_n": 0.0041},
                "displacement": {"parameters": {"young_modulus_kpa": {"value": 69.8, "ci95": [67.1, 72.5]},
                                                "depth_mm.blue": {"value": 3.48, "ci95": [3.42, 3.54]}},
                                 "setpoints": 12},
                "agree": true, "disagreements": []}),
            residual_rms_px: BTreeMap::from([("blue".into(), 0.061), ("red".into(), 0.079)]),
            cross_validation: json!({"held_out": "trial 2 (12 setpoints)",
                "nominal": {"force_sum_error_n": 0.412}, "fitted": {"force_sum_error_n": 0.051}}),
            extra,
        }
    }

    fn figures(html: &str) -> Vec<(String, image::DynamicImage)> {
        let b64 = base64::engine::general_purpose::STANDARD;
        html.split("<figure id=\"")
            .skip(1)
            .map(|f| {
                let id = f[..f.find('"').unwrap()].to_string();
                let start = f.find("base64,").unwrap() + 7;
                let data = &f[start..start + f[start..].find('"').unwrap()];
                let img = image::load_from_memory(&b64.decode(data).unwrap()).unwrap();
                (id, img)
            })
            .collect()
    }

    #[test]
    fn the_fit_page_shows_every_parameter_the_routes_the_figures_and_cross_validation() {
        let doc = sample_doc();
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("fit.html");
        write_fit_page(&doc, &out).unwrap();
        let html = std::fs::read_to_string(&out).unwrap();
        // For a look in a browser: TACTBENCH_FIT_PAGE=/tmp/fit.html cargo test ...
        if let Ok(p) = std::env::var("TACTBENCH_FIT_PAGE") {
            std::fs::write(p, &html).unwrap();
        }
        assert!(!html.contains("src=\"http") && !html.contains("<script"));
        for needle in [
            "<code>young_modulus_kpa</code></td><td>70.4</td><td>[68.3, 72.5]</td><td class=\"l\">kPa</td><td>100</td><td>-29.6 %</td>",
            "<code>depth_mm.blue</code></td><td>3.48</td>",
            "<tr class=\"held\"><td class=\"l\"><code>thickness_mm</code></td><td>40</td><td>&mdash;</td>",
            "held at nominal",
            "thickness &lt;here&gt;: a thin-layer setpoint would",
            "Intervals: jacobian (Gauss-Newton covariance",
            "<b>The routes agree</b>",
            "<td>70.9</td><td>[68, 73.8]</td><td>69.8</td><td>[67.1, 72.5]</td><td class=\"l\"><span class=\"pass\">overlap</span>",
            "<code>samples</code></th><td class=\"l\">16</td>",
            "<td class=\"l\">red</td><td>0.079</td>",
            "<td style=\"background:rgb(255,199,131)\">-0.62</td>",
            "<code>nominal.force_sum_error_n</code></th><td class=\"l\">0.412</td>",
            "<code>fitted.force_sum_error_n</code></th><td class=\"l\">0.051</td>",
            "(3 parameters, 2 fitted, 1 not identifiable)",
        ] {
            assert!(html.contains(needle), "missing {needle}");
        }
        let figs = figures(&html);
        let ids: Vec<&str> = figs.iter().map(|(id, _)| id.as_str()).collect();
        assert_eq!(
            ids,
            ["fit_displacements", "fit_residuals", "fit_indentation"]
        );
        for (id, img) in &figs {
            let want = if id == "fit_displacements" {
                QUIVER_SIZE
            } else {
                FIGURE_SIZE
            };
            assert_eq!((img.width(), img.height()), want, "{id}");
        }
        // Three setpoint panels, the longest arrow 1.5 spacings: 12 mm wide / √42.
        let f = DisplacementFigure::from_doc(&doc).unwrap();
        assert_eq!(f.panels.iter().map(|p| p.0).collect::<Vec<_>>(), [3, 7, 11]);
        assert!(f.panels.iter().all(|p| p.1.len() == 42));
        let r = SetpointResidualFigure::from_doc(&doc).unwrap();
        assert_eq!(r.series.len(), 2);
        assert_eq!(r.series[1].0, "red");
    }

    #[test]
    fn a_fit_without_detail_says_what_is_absent_and_flags_disagreeing_routes() {
        let mut doc = sample_doc();
        doc.extra.clear();
        doc.residual_rms_px.clear();
        doc.cross_validation = Value::Null;
        doc.routes = json!({
            "indentation": {"parameters": {"young_modulus_kpa": {"value": 60.0, "ci95": [58.0, 62.0]}}},
            "displacement": {"parameters": {"young_modulus_kpa": {"value": 95.0, "ci95": [90.0, 100.0]}}},
            "agree": false,
            "disagreements": ["young_modulus_kpa: indentation 60 [58, 62] kPa, displacement 95 [90, 100] kPa: a thin layer fitted as a half-space?"]});
        let html = render_fit_page(&doc).unwrap();
        assert!(figures(&html).is_empty());
        for needle in [
            "No example displacements recorded",
            "No per-setpoint residuals recorded",
            "No indentation curve recorded",
            "No residual RMS per layer recorded",
            "No cross-validation recorded",
            "<span class=\"fail\">disagree</span>",
            "<b class=\"fail\">The routes disagree</b>",
            "<li>young_modulus_kpa: indentation 60 [58, 62] kPa, displacement 95 [90, 100] kPa: a thin layer fitted as a half-space?</li>",
            "Intervals: not recorded",
        ] {
            assert!(html.contains(needle), "missing {needle}");
        }
    }
}
