//! The report's figures, each a [`Figure`] drawn by plotters (written as PNG and SVG by
//! [`super::plot::save_figure`]):
//!
//! - [`CalibrationFigure`]: applied against measured with ±1 SD error bars per level, the
//!   individual samples, the least-squares line and the identity (paper Fig. 7 and 8);
//! - [`ProfileFigure`]: the normalised f_z profile of the spatial sweep with the
//!   half-maximum crossings (Fig. 9);
//! - [`QuiverFigure`]: tracked marker displacements as arrows, coloured by layer (Fig. 4);
//! - the force field (Fig. 5) is [`super::force_map::ForceMapFigure`];
//! - [`MarkerHealthFigure`]: the fractions of markers ok / lost / merged / outlier per
//!   setpoint, the plan's `min_ok_fraction` gate, flagged rows marked.
//!
//! Arrow lengths in the quiver figure are scaled so the longest arrow spans 90 % of
//! the marker pitch; the scale factor is printed in the caption (the paper draws Fig. 4
//! five times longer than real). Arrowheads are filled triangles.

use plotters::coord::Shift;
use plotters::prelude::*;

use super::force_map::{arrow_parts, draw_arrows};
use super::plot::{titled_with_legend, Figure, FigureResult, LegendGlyph, FONT};
use crate::analysis::calibration::Calibration;
use crate::analysis::spatial::SpatialAnalysis;
use crate::analysis::tracking::{SetpointHealth, TrackingAnalysis};
use crate::formats::DisplacementFrame;
use crate::sensor::{MarkerColor, Sensor};

/// Applied against measured (Fig. 7, 8).
#[derive(Debug, Clone)]
pub struct CalibrationFigure {
    /// Caption.
    pub title: String,
    /// x axis label (applied, with unit).
    pub x_label: String,
    /// y axis label (measured, with unit).
    pub y_label: String,
    /// Multiplies every value for display (e.g. N -> gf); 1 for none.
    pub display_scale: f64,
    /// Unit of the displayed values (the fit offset's unit in the legend).
    pub unit: String,
    /// The calibration (levels and fit).
    pub calibration: Calibration,
    /// Every `(applied, measured)` sample.
    pub samples: Vec<(f64, f64)>,
}

/// Padded range covering `values`.
fn range(values: impl Iterator<Item = f64>, pad_frac: f64) -> std::ops::Range<f64> {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if !lo.is_finite() {
        return 0.0..1.0;
    }
    let span = (hi - lo).max(1e-9 * hi.abs().max(1.0));
    (lo - pad_frac * span)..(hi + pad_frac * span)
}

/// The colour of the samples behind the level means (light blue, opaque, so the
/// legend swatch is the colour drawn).
const SAMPLE_COLOR: RGBColor = RGBColor(166, 166, 255);

impl Figure for CalibrationFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let k = self.display_scale;
        let c = &self.calibration;
        let fit = c.fit;
        let grey = RGBColor(179, 179, 179);
        // The legend in a strip above the plot, clear of every point.
        let entries = [
            (LegendGlyph::Line(grey), "identity".to_string()),
            (LegendGlyph::Dot(SAMPLE_COLOR), "samples".to_string()),
            (
                LegendGlyph::ErrorBar(BLACK),
                "level mean ± 1 SD".to_string(),
            ),
            (
                LegendGlyph::Line(RED),
                format!(
                    "fit: slope {:.4}, offset {:.4} {}, R² {:.5}",
                    fit.slope,
                    fit.offset * k,
                    self.unit,
                    fit.r2
                ),
            ),
        ];
        let area = titled_with_legend(root, &self.title, &entries)?;
        let xs = range(self.samples.iter().map(|s| s.0 * k), 0.05);
        let ys = range(self.samples.iter().map(|s| s.1 * k), 0.05);
        // Same span on both axes when the identity line is near the data (they are
        // the same quantity), so the eye can judge the slope.
        let lo = xs.start.min(ys.start);
        let hi = xs.end.max(ys.end);
        let mut chart = ChartBuilder::on(&area)
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(lo..hi, lo..hi)?;
        chart
            .configure_mesh()
            .x_desc(self.x_label.as_str())
            .y_desc(self.y_label.as_str())
            .label_style((FONT, 13))
            .draw()?;
        chart.draw_series(LineSeries::new([(lo, lo), (hi, hi)], grey.stroke_width(1)))?;
        chart.draw_series(
            self.samples
                .iter()
                .map(|s| Circle::new((s.0 * k, s.1 * k), 2, SAMPLE_COLOR.filled())),
        )?;
        chart.draw_series(c.levels.iter().map(|l| {
            ErrorBar::new_vertical(
                l.applied_mean * k,
                (l.measured_mean - l.measured_sd) * k,
                l.measured_mean * k,
                (l.measured_mean + l.measured_sd) * k,
                BLACK.stroke_width(2),
                8,
            )
        }))?;
        chart.draw_series(LineSeries::new(
            [lo, hi].map(|x| (x, fit.at(x / k) * k)),
            RED.stroke_width(2),
        ))?;
        Ok(())
    }
}

/// The normalised f_z profile (Fig. 9).
#[derive(Debug, Clone)]
pub struct ProfileFigure {
    /// The spatial analysis.
    pub spatial: SpatialAnalysis,
}

impl Figure for ProfileFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let s = &self.spatial;
        let grey = RGBColor(153, 153, 153);
        let entries = [
            (
                LegendGlyph::Line(BLUE),
                "fz / max fz of the force nodes, by distance from the load".to_string(),
            ),
            (LegendGlyph::Line(grey), "half maximum".to_string()),
            (
                LegendGlyph::Line(RED),
                format!("full width at half maximum, {:.2} mm", s.fwhm_mm),
            ),
        ];
        let area = titled_with_legend(
            root,
            &format!("normalised fz profile, FWHM {:.2} mm", s.fwhm_mm),
            &entries,
        )?;
        let xs = range(s.profile.iter().map(|p| p.distance_mm), 0.03);
        let ymin = s.profile.iter().fold(0.0f64, |m, p| m.min(p.normalized)) - 0.05;
        let mut chart = ChartBuilder::on(&area)
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(50)
            .build_cartesian_2d(xs.clone(), ymin..1.08)?;
        chart
            .configure_mesh()
            .x_desc("distance from the load (mm)")
            .y_desc("fz / max fz")
            .label_style((FONT, 13))
            .draw()?;
        chart.draw_series(LineSeries::new(
            s.profile.iter().map(|p| (p.distance_mm, p.normalized)),
            BLUE.stroke_width(2),
        ))?;
        chart.draw_series(
            s.profile
                .iter()
                .map(|p| Circle::new((p.distance_mm, p.normalized), 3, BLUE.filled())),
        )?;
        chart.draw_series(LineSeries::new(
            [(xs.start, 0.5), (xs.end, 0.5)],
            grey.stroke_width(1),
        ))?;
        chart.draw_series(LineSeries::new(
            [(s.half_left_mm, 0.5), (s.half_right_mm, 0.5)],
            RED.stroke_width(3),
        ))?;
        Ok(())
    }
}

fn layer_color(c: MarkerColor) -> RGBColor {
    match c {
        MarkerColor::Blue => RGBColor(20, 60, 220),
        MarkerColor::Red => RGBColor(210, 30, 30),
        MarkerColor::Green => RGBColor(20, 150, 40),
        MarkerColor::Dark => RGBColor(40, 40, 40),
        MarkerColor::Bright => RGBColor(230, 159, 0),
    }
}

/// Tracked displacements as arrows per marker (Fig. 4).
#[derive(Debug, Clone)]
pub struct QuiverFigure {
    /// Caption prefix.
    pub title: String,
    /// The sensor (layer names and colours, marker pitch).
    pub sensor: Sensor,
    /// The frame to draw.
    pub frame: DisplacementFrame,
}

impl QuiverFigure {
    /// Arrow scale: the longest displacement spans 90 % of the smallest marker pitch.
    pub fn scale(&self) -> f64 {
        let pitch = self
            .sensor
            .layers
            .iter()
            .filter_map(|l| l.markers.map(|m| m.grid.pitch_mm))
            .fold(f64::INFINITY, f64::min);
        let pitch = if pitch.is_finite() { pitch } else { 1.0 };
        let umax = self
            .frame
            .records
            .iter()
            .filter_map(|r| r.u_mm)
            .fold(0.0f64, |m, u| m.max(u[0].hypot(u[1])));
        if umax > 0.0 {
            0.9 * pitch / umax
        } else {
            1.0
        }
    }

    /// The plot's x and y ranges: every marker and every arrow's tip (a rigid shift
    /// carries the tips of the last column past the markers' extent), padded 5 %.
    pub fn extent(&self) -> (std::ops::Range<f64>, std::ops::Range<f64>) {
        let k = self.scale();
        let ends = |axis: usize| {
            self.frame.records.iter().flat_map(move |r| {
                let p = r.position_mm[axis];
                [p, p + k * r.u_mm.map_or(0.0, |u| u[axis])]
            })
        };
        (range(ends(0), 0.05), range(ends(1), 0.05))
    }
}

impl Figure for QuiverFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let k = self.scale();
        let recs = &self.frame.records;
        // One colour per layer, keyed in a strip above the plot (the arrows fill it).
        let mut entries: Vec<(LegendGlyph, String)> = self
            .sensor
            .layers
            .iter()
            .map(|l| {
                (
                    LegendGlyph::Line(layer_color(l.color)),
                    format!("layer {}", l.name),
                )
            })
            .collect();
        if recs.iter().any(|r| r.u_mm.is_none()) {
            entries.push((
                LegendGlyph::Cross(BLACK),
                "lost marker (cross, in its layer's colour)".to_string(),
            ));
        }
        let area = titled_with_legend(root, &format!("{} (arrows ×{k:.1})", self.title), &entries)?;
        let (xs, ys) = self.extent();
        let mut chart = ChartBuilder::on(&area)
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(50)
            .build_cartesian_2d(xs, ys)?;
        chart
            .configure_mesh()
            .x_desc("x (mm)")
            .y_desc("y (mm)")
            .label_style((FONT, 13))
            .draw()?;
        for (li, layer) in self.sensor.layers.iter().enumerate() {
            let color = layer_color(layer.color);
            let arrows: Vec<_> = recs
                .iter()
                .filter(|r| r.layer == li)
                .filter_map(|r| r.u_mm.map(|u| (r.position_mm, u)))
                .filter_map(|(p, u)| {
                    let a = (p[0], p[1]);
                    let b = (p[0] + k * u[0], p[1] + k * u[1]);
                    let len = (k * u[0]).hypot(k * u[1]);
                    arrow_parts(a, b, 0.3 * len)
                })
                .collect();
            draw_arrows(&mut chart, &arrows, color, 1)?;
            chart.draw_series(
                recs.iter()
                    .filter(|r| r.layer == li && r.u_mm.is_none())
                    .map(|r| Cross::new((r.position_mm[0], r.position_mm[1]), 3, color)),
            )?;
        }
        Ok(())
    }
}

/// One status count of a setpoint (for the stacked bands of [`MarkerHealthFigure`]).
type CountOf = fn(&SetpointHealth) -> usize;

/// Marker health per setpoint: stacked fractions ok / outlier / merged / lost (bottom
/// to top), the `min_ok_fraction` gate as a dashed line, flagged rows as red crosses
/// above their bar.
#[derive(Debug, Clone)]
pub struct MarkerHealthFigure {
    /// The analysis.
    pub tracking: TrackingAnalysis,
}

impl Figure for MarkerHealthFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let t = &self.tracking;
        let n = t.setpoints.len();
        let bands: [(&str, RGBColor, CountOf); 4] = [
            ("ok", RGBColor(60, 150, 60), |s| s.ok),
            ("outlier", RGBColor(230, 160, 30), |s| s.outlier),
            ("merged", RGBColor(140, 80, 170), |s| s.merged),
            ("lost", RGBColor(200, 40, 40), |s| s.lost),
        ];
        let gate = t.gate;
        let any_flagged = t.setpoints.iter().any(|s| s.flagged);
        // The legend in a strip above the plot: the bars fill the whole plot area.
        let mut entries: Vec<(LegendGlyph, String)> = bands
            .iter()
            .map(|(name, color, _)| (LegendGlyph::Swatch(*color), name.to_string()))
            .collect();
        entries.push((
            LegendGlyph::Dashed(BLACK),
            format!("min_ok_fraction {gate}"),
        ));
        if any_flagged {
            entries.push((LegendGlyph::Cross(RED), "flagged row".into()));
        }
        let area = titled_with_legend(root, "marker health per setpoint", &entries)?;
        let mut chart = ChartBuilder::on(&area)
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(-0.5..(n as f64 - 0.5).max(0.5), 0.0..1.08)?;
        // Bars in journal order, labelled with their setpoint index.
        let label = |x: &f64| {
            let k = x.round();
            match t.setpoints.get(k as usize) {
                Some(s) if k >= 0.0 && (x - k).abs() < 1e-6 => s.index.to_string(),
                _ => String::new(),
            }
        };
        chart
            .configure_mesh()
            .x_desc("setpoint (journal order)")
            .y_desc("fraction of the sensor's markers")
            .x_labels(n.clamp(1, 20))
            .x_label_formatter(&label)
            .disable_x_mesh()
            .label_style((FONT, 13))
            .draw()?;
        let half = 0.4;
        let mut base = vec![0.0f64; n];
        for (_, color, count) in bands {
            let rects: Vec<_> = t
                .setpoints
                .iter()
                .enumerate()
                .map(|(i, s)| {
                    let lo = base[i];
                    let hi = lo + s.fraction(count(s));
                    base[i] = hi;
                    Rectangle::new(
                        [(i as f64 - half, lo), (i as f64 + half, hi)],
                        color.filled(),
                    )
                })
                .collect();
            chart.draw_series(rects)?;
        }
        chart.draw_series(DashedLineSeries::new(
            [(-0.5, gate), (n as f64 - 0.5, gate)],
            6,
            4,
            BLACK.stroke_width(2),
        ))?;
        let flagged: Vec<_> = t
            .setpoints
            .iter()
            .enumerate()
            .filter(|(_, s)| s.flagged)
            .map(|(i, _)| Cross::new((i as f64, 1.04), 6, RED.stroke_width(3)))
            .collect();
        if !flagged.is_empty() {
            chart.draw_series(flagged)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::QuiverFigure;
    use crate::formats::{DisplacementFrame, DisplacementRecord};
    use crate::sensor::paper_sensor;

    /// Regression (the committed Table I page): the x range covered the markers only,
    /// so under a rigid shift along +x the arrows of the last column ran off the plot.
    #[test]
    fn quiver_range_holds_the_arrow_tips_of_a_rigid_shift() {
        let records: Vec<DisplacementRecord> = (0..5)
            .flat_map(|ix| {
                (0..3).map(move |iy| DisplacementRecord {
                    layer: 0,
                    marker: (iy * 5 + ix) as u64,
                    position_mm: [1.5 * ix as f64, 1.5 * iy as f64],
                    u_mm: Some([0.05, -0.01]),
                    line: 0,
                })
            })
            .collect();
        let fig = QuiverFigure {
            title: "t".into(),
            sensor: paper_sensor(),
            frame: DisplacementFrame {
                frame: String::new(),
                records,
            },
        };
        let k = fig.scale();
        let (xs, ys) = fig.extent();
        let tip_x = 6.0 + k * 0.05;
        assert!(
            xs.end > tip_x,
            "x range {xs:?} ends before the last tip {tip_x}"
        );
        assert!(xs.start < 0.0);
        assert!(ys.start < -k * 0.01, "y range {ys:?}");
        assert!(ys.end > 3.0);
    }
}
