//! The metrology figures (ISO 376-style analysis, [`crate::analysis::metrology`] and
//! [`crate::analysis::hold`]), each a [`Figure`] written as PNG and SVG:
//!
//! - [`ResidualFigure`]: measured − applied (F^sum − F/T) against applied, one colour
//!   per trial, loading rows circles and unloading rows triangles, with the
//!   calibration line's error `(slope − 1)·F + offset` dashed;
//! - [`HysteresisFigure`]: the loop, F^sum against applied with the level means of the
//!   loading (up) and unloading (down) branches joined, samples behind; an inset of the
//!   down − up difference per level, where the loop itself is thinner than a line;
//! - [`CreepFigure`]: two panels against `hold_t_s`: the F/T force and F^sum (top), and
//!   their difference F^sum − F/T with the fitted creep line of each hold (bottom).
//!
//! Forces are drawn in the plan's force unit (`scale` converts from newtons).

use plotters::coord::Shift;
use plotters::prelude::*;

use super::plot::{titled_with_legend, Figure, FigureResult, LegendGlyph, FONT};
use crate::analysis::hold::HoldAnalysis;
use crate::analysis::metrology::{LevelBranches, MetrologyAnalysis};

/// Colours cycled over trials / holds (matplotlib's tab10: ten distinct colours, so
/// the paper's ten trials and three positions × three trials each get their own).
const PALETTE: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

/// The colour of item `i` (trial, hold) of a figure.
fn palette(i: usize) -> RGBColor {
    PALETTE[i % PALETTE.len()]
}

/// The legend entries keying each colour of `items` (item `i` drawn in
/// [`palette`]`(i)`): one swatch per colour, naming every item drawn in it (past ten
/// items the colours repeat, and the key says which items share one).
pub fn colour_key(items: &[String]) -> Vec<(LegendGlyph, String)> {
    (0..items.len().min(PALETTE.len()))
        .map(|c| {
            let names: Vec<&str> = items
                .iter()
                .enumerate()
                .filter(|(i, _)| i % PALETTE.len() == c)
                .map(|(_, n)| n.as_str())
                .collect();
            (LegendGlyph::Swatch(palette(c)), names.join(" and "))
        })
        .collect()
}

/// Padded range of `values` (0..1 when empty).
fn span(values: impl Iterator<Item = f64>, pad: f64) -> std::ops::Range<f64> {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if !lo.is_finite() {
        return 0.0..1.0;
    }
    let w = (hi - lo).max(1e-9 * hi.abs().max(1.0));
    (lo - pad * w)..(hi + pad * w)
}

/// Measured − applied against applied, per trial.
#[derive(Debug, Clone)]
pub struct ResidualFigure {
    /// The metrology analysis (readings and calibration line).
    pub metrology: MetrologyAnalysis,
    /// Newtons -> display unit.
    pub scale: f64,
    /// Display unit symbol.
    pub unit: String,
}

impl Figure for ResidualFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let k = self.scale;
        let m = &self.metrology;
        let mut units: Vec<(Option<usize>, usize)> =
            m.readings.iter().map(|r| (r.position, r.trial)).collect();
        units.sort();
        units.dedup();
        let pts: Vec<(f64, f64, usize, bool)> = {
            m.readings
                .iter()
                .map(|r| {
                    let u = units
                        .iter()
                        .position(|&x| x == (r.position, r.trial))
                        .unwrap_or(0);
                    (r.applied_n * k, (r.measured_n - r.applied_n) * k, u, r.down)
                })
                .collect()
        };
        let xs = span(pts.iter().map(|p| p.0), 0.05);
        let line = |x: f64| ((m.fit.slope - 1.0) * x / k + m.fit.offset) * k;
        let ys = span(
            pts.iter()
                .map(|p| p.1)
                .chain([line(xs.start), line(xs.end), 0.0]),
            0.08,
        );
        // The legend in a strip above the plot, clear of every point; every trial's
        // colour keyed (journal numbering of trials and positions).
        let mut entries = vec![
            (
                LegendGlyph::Dashed(BLACK),
                format!(
                    "calibration line error: (slope − 1)·F + offset, slope {:.4}",
                    m.fit.slope
                ),
            ),
            (LegendGlyph::Dot(BLACK), "loading (up)".to_string()),
        ];
        if pts.iter().any(|p| p.3) {
            entries.push((LegendGlyph::Triangle(BLACK), "unloading (down)".to_string()));
        }
        let names: Vec<String> = units
            .iter()
            .map(|(p, t)| match p {
                Some(p) => format!("position {p} trial {t}"),
                None => format!("trial {t}"),
            })
            .collect();
        entries.extend(colour_key(&names));
        let area = titled_with_legend(root, "measured − applied", &entries)?;
        let mut chart = ChartBuilder::on(&area)
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(xs.clone(), ys)?;
        chart
            .configure_mesh()
            .x_desc(format!("applied Fz, F/T ({})", self.unit))
            .y_desc(format!("F sum − F/T ({})", self.unit))
            .label_style((FONT, 13))
            .draw()?;
        chart.draw_series(LineSeries::new(
            [(xs.start, 0.0), (xs.end, 0.0)],
            BLACK.mix(0.3),
        ))?;
        chart.draw_series(DashedLineSeries::new(
            [xs.start, xs.end].map(|x| (x, line(x))),
            8,
            5,
            BLACK.stroke_width(1),
        ))?;
        let up = pts.iter().filter(|p| !p.3);
        chart.draw_series(up.map(|p| Circle::new((p.0, p.1), 3, palette(p.2).filled())))?;
        chart.draw_series(
            pts.iter()
                .filter(|p| p.3)
                .map(|p| TriangleMarker::new((p.0, p.1), 5, palette(p.2).stroke_width(1))),
        )?;
        Ok(())
    }
}

/// F^sum against applied: up and down branches.
#[derive(Debug, Clone)]
pub struct HysteresisFigure {
    /// The metrology analysis (levels and readings).
    pub metrology: MetrologyAnalysis,
    /// Newtons -> display unit.
    pub scale: f64,
    /// Display unit symbol.
    pub unit: String,
}

/// One branch of the hysteresis loop: `(applied, F^sum)` points.
type Branch = Vec<(f64, f64)>;

/// The loop's two branches, `(applied, F^sum)` level means in display units (`k` per N),
/// by applied force: loading, and unloading. The unloading branch starts where loading
/// turned: the top level is measured once (on the way up), so it opens the down line
/// too and the loop closes (with one down level the down line was a lone point before).
/// `levels` are the unloaded level (when recorded) and the loaded ones: the analysis
/// keeps the unloaded level apart from the loaded ones, and without it both lines
/// started at the first load although the run measured 0.
fn loop_branches<'a>(
    levels: impl IntoIterator<Item = &'a LevelBranches> + Clone,
    k: f64,
) -> (Branch, Branch) {
    let branch = |down: bool| -> Vec<(f64, f64)> {
        let mut v: Vec<(f64, f64)> = levels
            .clone()
            .into_iter()
            .filter_map(|l| {
                let (a, y) = if down {
                    (l.down_applied_n?, l.down_measured_n?)
                } else {
                    (l.up_applied_n?, l.up_measured_n?)
                };
                Some((a * k, y * k))
            })
            .collect();
        v.sort_by(|a, b| a.0.total_cmp(&b.0));
        v
    };
    let up = branch(false);
    let mut down = branch(true);
    if let Some(&top) = up.last() {
        if !down.is_empty() && down.iter().all(|p| p.0 < top.0) {
            down.push(top);
        }
    }
    (up, down)
}

impl HysteresisFigure {
    /// The loading and unloading lines drawn, from the unloaded level through the
    /// loaded ones (see [`loop_branches`]).
    fn branches(&self) -> (Branch, Branch) {
        let m = &self.metrology;
        loop_branches(m.unloaded_level.iter().chain(&m.levels), self.scale)
    }
}

impl Figure for HysteresisFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let k = self.scale;
        let m = &self.metrology;
        let blue = RGBColor(31, 90, 200);
        let red = RGBColor(200, 40, 40);
        let sample = RGBColor(204, 204, 204);
        let (up, down) = self.branches();
        let mut entries = vec![
            (LegendGlyph::Dot(sample), "samples".to_string()),
            (
                LegendGlyph::Line(blue),
                "loading (up), level means".to_string(),
            ),
        ];
        if !down.is_empty() {
            entries.push((
                LegendGlyph::Line(red),
                "unloading (down), level means; below: down − up per level".to_string(),
            ));
        }
        let area = titled_with_legend(root, "hysteresis loop: F sum against applied", &entries)?;
        let (main, inset) = area.split_vertically(area.dim_in_pixel().1 * 62 / 100);
        let xs = span(m.readings.iter().map(|r| r.applied_n * k), 0.05);
        let ys = span(m.readings.iter().map(|r| r.measured_n * k), 0.05);
        let mut chart = ChartBuilder::on(&main)
            .margin(12)
            .x_label_area_size(35)
            .y_label_area_size(70)
            .build_cartesian_2d(xs.clone(), ys)?;
        chart
            .configure_mesh()
            .x_desc(format!("applied Fz, F/T ({})", self.unit))
            .y_desc(format!("F sum ({})", self.unit))
            .label_style((FONT, 13))
            .draw()?;
        chart.draw_series(
            m.readings
                .iter()
                .map(|r| Circle::new((r.applied_n * k, r.measured_n * k), 2, sample.filled())),
        )?;
        chart.draw_series(LineSeries::new(up, blue.stroke_width(2)))?;
        if !down.is_empty() {
            chart.draw_series(
                down.iter()
                    .map(|&p| TriangleMarker::new(p, 5, red.filled())),
            )?;
            chart.draw_series(LineSeries::new(down, red.stroke_width(2)))?;
        }
        // Inset: down − up per level (the loop's width).
        let diffs: Vec<(f64, f64)> = m
            .levels
            .iter()
            .filter_map(|l| Some((l.target_n * k, l.reversibility_n()? * k)))
            .collect();
        let ys = span(diffs.iter().map(|d| d.1).chain([0.0]), 0.15);
        let mut c2 = ChartBuilder::on(&inset)
            .margin(12)
            .x_label_area_size(35)
            .y_label_area_size(70)
            .build_cartesian_2d(xs.clone(), ys)?;
        c2.configure_mesh()
            .x_desc(format!("target level ({})", self.unit))
            .y_desc(format!("down − up ({})", self.unit))
            .label_style((FONT, 13))
            .draw()?;
        c2.draw_series(LineSeries::new(
            [(xs.start, 0.0), (xs.end, 0.0)],
            BLACK.mix(0.3),
        ))?;
        c2.draw_series(LineSeries::new(diffs.clone(), red.stroke_width(1)))?;
        c2.draw_series(diffs.iter().map(|d| Circle::new(*d, 4, red.filled())))?;
        Ok(())
    }
}

/// Creep through the holds.
#[derive(Debug, Clone)]
pub struct CreepFigure {
    /// The hold analysis.
    pub hold: HoldAnalysis,
    /// Newtons -> display unit.
    pub scale: f64,
    /// Display unit symbol.
    pub unit: String,
}

impl Figure for CreepFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let k = self.scale;
        let h = &self.hold;
        let title = format!(
            "creep during the holds: {:.4} %FS/min (F sum − F/T)",
            h.creep_pct_fs_per_min()
        );
        // Every colour keyed (one per hold; line styles for the two readings), in a
        // strip clear of the data.
        let mut entries = vec![
            (LegendGlyph::Line(BLACK), "F/T (solid)".to_string()),
            (LegendGlyph::Dashed(BLACK), "F sum (dashed)".to_string()),
        ];
        for hold in 0..h.holds {
            let at = h
                .samples
                .iter()
                .filter(|s| s.hold == hold)
                .map(|s| s.applied_n * k)
                .sum::<f64>()
                / h.samples.iter().filter(|s| s.hold == hold).count().max(1) as f64;
            entries.push((
                LegendGlyph::Swatch(palette(hold)),
                format!("hold {} (≈ {:.0} {})", hold + 1, at, self.unit),
            ));
        }
        if !h.creep_intercepts_n.is_empty() {
            entries.push((
                LegendGlyph::Line(BLACK),
                format!(
                    "below: fitted creep line, slope {:.4} {}/min",
                    h.creep.slope * 60.0 * k,
                    self.unit
                ),
            ));
        }
        let area = titled_with_legend(root, &title, &entries)?;
        let (top, bottom) = area.split_vertically(area.dim_in_pixel().1 / 2);
        let ts = span(h.samples.iter().map(|s| s.t_s), 0.03);
        let ys = span(
            h.samples
                .iter()
                .flat_map(|s| [s.applied_n * k, s.measured_n * k]),
            0.08,
        );
        let mut c1 = ChartBuilder::on(&top)
            .margin(12)
            .x_label_area_size(35)
            .y_label_area_size(70)
            .build_cartesian_2d(ts.clone(), ys)?;
        c1.configure_mesh()
            .x_desc("hold_t_s (s)")
            .y_desc(format!("force ({})", self.unit))
            .label_style((FONT, 13))
            .draw()?;
        for hold in 0..h.holds {
            let c = palette(hold);
            let pts: Vec<_> = h.samples.iter().filter(|s| s.hold == hold).collect();
            c1.draw_series(LineSeries::new(
                pts.iter().map(|s| (s.t_s, s.applied_n * k)),
                c.stroke_width(2),
            ))?;
            c1.draw_series(DashedLineSeries::new(
                pts.iter().map(|s| (s.t_s, s.measured_n * k)),
                6,
                4,
                c.stroke_width(2),
            ))?;
        }
        let d = |s: &crate::analysis::hold::HoldSample| (s.measured_n - s.applied_n) * k;
        let ys = span(h.samples.iter().map(d), 0.1);
        let mut c2 = ChartBuilder::on(&bottom)
            .margin(12)
            .x_label_area_size(35)
            .y_label_area_size(70)
            .build_cartesian_2d(ts.clone(), ys)?;
        c2.configure_mesh()
            .x_desc("hold_t_s (s)")
            .y_desc(format!("F sum − F/T ({})", self.unit))
            .label_style((FONT, 13))
            .draw()?;
        for hold in 0..h.holds {
            let c = palette(hold);
            c2.draw_series(
                h.samples
                    .iter()
                    .filter(|s| s.hold == hold)
                    .map(|s| Circle::new((s.t_s, d(s)), 3, c.filled())),
            )?;
            let (t0, t1) = h
                .samples
                .iter()
                .filter(|s| s.hold == hold)
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), s| {
                    (a.min(s.t_s), b.max(s.t_s))
                });
            if let Some(&b0) = h.creep_intercepts_n.get(hold) {
                c2.draw_series(LineSeries::new(
                    [t0, t1].map(|t| (t, (b0 + h.creep.slope * t) * k)),
                    BLACK.stroke_width(2),
                ))?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analysis::metrology::{analyze_readings, Reading};

    fn level(target: f64, up: Option<f64>, down: Option<f64>) -> LevelBranches {
        LevelBranches {
            target_n: target,
            up_applied_n: up.map(|_| target),
            up_measured_n: up,
            up_residual_n: up.map(|u| u - target),
            down_applied_n: down.map(|_| target),
            down_measured_n: down,
            down_residual_n: down.map(|d| d - target),
        }
    }

    /// "The creep plot's colours have no key" (and the residual plot's trials had
    /// none): every colour drawn is named; past ten items the shared colours say which
    /// items they stand for.
    #[test]
    fn every_trial_colour_is_keyed_and_a_shared_colour_names_each_of_its_trials() {
        let names: Vec<String> = (0..9).map(|t| format!("trial {t}")).collect();
        let key = colour_key(&names);
        assert_eq!(key.len(), 9);
        for (i, (g, label)) in key.iter().enumerate() {
            assert_eq!(label, &format!("trial {i}"));
            assert!(matches!(g, LegendGlyph::Swatch(c) if *c == palette(i)));
        }
        let names: Vec<String> = (0..12).map(|t| format!("trial {t}")).collect();
        let key = colour_key(&names);
        assert_eq!(key.len(), PALETTE.len());
        assert_eq!(key[0].1, "trial 0 and trial 10");
        assert_eq!(key[1].1, "trial 1 and trial 11");
        assert_eq!(key[2].1, "trial 2");
        assert_eq!(palette(10), palette(0));
    }

    #[test]
    fn unloading_branch_with_one_down_level_starts_at_the_top_and_closes_the_loop() {
        // 0 -> 1.5 -> 3 N up, back down to 1.5 N: the down line runs from the top
        // (measured once, on the way up) through 1.5 N, two points, not a lone one.
        let levels = [
            level(0.0, Some(0.05), Some(0.08)),
            level(1.5, Some(1.4), Some(1.7)),
            level(3.0, Some(2.9), None),
        ];
        let (up, down) = loop_branches(&levels, 1.0);
        assert_eq!(up, vec![(0.0, 0.05), (1.5, 1.4), (3.0, 2.9)]);
        assert_eq!(down, vec![(0.0, 0.08), (1.5, 1.7), (3.0, 2.9)]);
        // Without any unloading row there is no down branch at all.
        let only_up = [level(0.0, Some(0.0), None), level(1.0, Some(1.0), None)];
        assert!(loop_branches(&only_up, 1.0).1.is_empty());
    }

    /// "The loading line starts at 150 gf and is not joined to the 0 gf point" of the
    /// committed up-down run (0, 150, 300, 150, 0 gf per trial, every row recorded):
    /// the analysis keeps the unloaded level out of its loaded `levels`, and the figure
    /// drew only those. Both lines now run from the recorded 0 gf means.
    #[test]
    fn loading_line_is_joined_to_the_recorded_zero_level() {
        let gf = crate::units::NEWTONS_PER_GF;
        let targets = [0.0, 150.0, 300.0, 150.0, 0.0];
        let mut readings = Vec::new();
        for trial in 0..3 {
            for (k, &t) in targets.iter().enumerate() {
                let down = k > 2;
                // F^sum reads 10 % low loading, 10 % high unloading, +0.01 N at zero
                // on the way back.
                let f = t * gf;
                let measured = if down { 1.1 * f + 0.01 } else { 0.9 * f };
                readings.push(Reading {
                    index: 5 * trial + k,
                    trial,
                    position: None,
                    target_n: f,
                    applied_n: f,
                    measured_n: measured + 0.001 * trial as f64,
                    down,
                });
            }
        }
        let m = analyze_readings(readings).unwrap();
        // The analysis' loaded levels are unchanged: 150 and 300 gf only.
        assert_eq!(m.levels.len(), 2);
        let zero = m.unloaded_level.clone().unwrap();
        assert_eq!(zero.up_applied_n, Some(0.0));
        assert!((zero.down_measured_n.unwrap() - 0.011).abs() < 1e-12);
        let fig = HysteresisFigure {
            metrology: m,
            scale: 1.0 / gf,
            unit: "gf".into(),
        };
        let (up, down) = fig.branches();
        let near =
            |a: (f64, f64), b: (f64, f64)| (a.0 - b.0).abs() < 1e-9 && (a.1 - b.1).abs() < 1e-9;
        let zero_up = 0.001 / gf;
        let zero_down = 0.011 / gf;
        assert_eq!(up.len(), 3, "{up:?}");
        assert!(near(up[0], (0.0, zero_up)), "{up:?}");
        assert!(near(up[1], (150.0, 135.0 + zero_up)), "{up:?}");
        assert!(near(up[2], (300.0, 270.0 + zero_up)), "{up:?}");
        assert_eq!(down.len(), 3, "{down:?}");
        assert!(near(down[0], (0.0, zero_down)), "{down:?}");
        assert!(near(down[1], (150.0, 165.0 + zero_down)), "{down:?}");
        // The down line opens where loading turned (the top is measured once).
        assert!(near(down[2], up[2]), "{down:?}");
    }
}
