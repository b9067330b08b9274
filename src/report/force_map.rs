//! The reconstructed force field (paper Fig. 5) as a map: one cell of the force grid
//! per node, coloured by the signed normal force fz (diverging scale, red presses into
//! the sensor, blue pulls out, with a colour bar), the tangential force (fx, fy) as an
//! arrow from the node on a stated scale (force per mm of arrow, with a key arrow),
//! and, where the run recorded it, a second panel with the per-node standard
//! deviation σ(fz) (the `sfz_n` column of the setpoint's forces file).
//!
//! The forces are held in newtons (as the forces CSV records them) and drawn in the
//! plan's force unit ([`ForceMapFigure::unit`]): a plan in gf gets a colour bar, key
//! arrow, arrow scale and title in gf, like every other force on its report page.
//!
//! Arrows are at most [`ARROW_FRACTION`] of the pitch long, so arrows from neighbouring
//! nodes pointing at each other never cross: at 0.9 pitch (the earlier figure), the four
//! nodes around a load between nodes drew an X over the contact.

use plotters::coord::Shift;
use plotters::prelude::*;

use super::plot::{Figure, FigureResult, FONT};
use crate::formats::ForceRecord;
use crate::units::ForceUnit;

/// Longest arrow as a fraction of the force-grid pitch.
pub const ARROW_FRACTION: f64 = 0.45;

/// Width of the colour-bar strip beside a map, px.
const BAR_PX: u32 = 95;

/// Per-node uncertainty of fz for the second panel.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeSd {
    /// σ(fz) per node, N, in the order of the forces.
    pub fz_sd_n: Vec<f64>,
    /// The displacement noise it was propagated from, px.
    pub noise_px: f64,
    /// Where that noise estimate comes from (one phrase).
    pub source: String,
}

/// The force-field map of one setpoint.
#[derive(Debug, Clone)]
pub struct ForceMapFigure {
    /// Title.
    pub title: String,
    /// Force-grid pitch, mm.
    pub pitch_mm: f64,
    /// The forces (one per grid node).
    pub forces: Vec<ForceRecord>,
    /// Per-node σ(fz), when a noise estimate exists.
    pub sd: Option<NodeSd>,
    /// The unit the forces are drawn in (the plan's force unit).
    pub unit: ForceUnit,
}

/// The largest of 1, 2, 5 × 10^k that is ≤ `v` (`v` > 0).
pub fn nice_floor(v: f64) -> f64 {
    let e = 10f64.powf(v.log10().floor());
    [5.0, 2.0, 1.0]
        .into_iter()
        .map(|m| m * e)
        .find(|c| *c <= v * (1.0 + 1e-12))
        .unwrap_or(e)
}

/// The smallest of 1, 1.5, 2, 2.5, 3, 4, 5, 6, 8 × 10^k that is ≥ `v` (`v` > 0).
pub fn nice_ceil(v: f64) -> f64 {
    let e = 10f64.powf(v.log10().floor());
    [1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0]
        .into_iter()
        .map(|m| m * e)
        .find(|c| *c >= v * (1.0 - 1e-12))
        .unwrap_or(10.0 * e)
}

/// Diverging colour (blue – white – red) of `t` in [−1, 1].
pub fn diverging(t: f64) -> RGBColor {
    let t = if t.is_finite() {
        t.clamp(-1.0, 1.0)
    } else {
        0.0
    };
    let white = (247.0, 247.0, 247.0);
    let end = if t >= 0.0 {
        (178.0, 24.0, 43.0)
    } else {
        (33.0, 102.0, 172.0)
    };
    let a = t.abs();
    let mix = |w: f64, e: f64| (w + (e - w) * a).round() as u8;
    RGBColor(
        mix(white.0, end.0),
        mix(white.1, end.1),
        mix(white.2, end.2),
    )
}

/// Sequential colour (white – purple) of `t` in [0, 1].
pub fn sequential(t: f64) -> RGBColor {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let mix = |w: f64, e: f64| (w + (e - w) * t).round() as u8;
    RGBColor(mix(252.0, 84.0), mix(251.0, 39.0), mix(253.0, 143.0))
}

/// An arrow from `a` to `b` as its shaft (from `a` to the base of the head) and its
/// head (tip, barb, barb), the head `head` long and as wide; `None` for a zero or
/// non-finite arrow.
pub type ArrowParts = ([(f64, f64); 2], [(f64, f64); 3]);

/// See [`ArrowParts`].
pub fn arrow_parts(a: (f64, f64), b: (f64, f64), head: f64) -> Option<ArrowParts> {
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let len = dx.hypot(dy);
    if !len.is_finite() || len <= 0.0 {
        return None;
    }
    let (ux, uy) = (dx / len, dy / len);
    let h = head.min(0.6 * len);
    let base = (b.0 - h * ux, b.1 - h * uy);
    let side = |s: f64| (base.0 - s * 0.5 * h * uy, base.1 + s * 0.5 * h * ux);
    Some(([a, base], [b, side(1.0), side(-1.0)]))
}

/// Draws filled-head arrows on a chart.
pub fn draw_arrows<DB: DrawingBackend>(
    chart: &mut ChartContext<
        '_,
        DB,
        Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>,
    >,
    arrows: &[ArrowParts],
    color: RGBColor,
    width: u32,
) -> FigureResult<DB> {
    chart.draw_series(
        arrows
            .iter()
            .map(|(shaft, _)| PathElement::new(shaft.to_vec(), color.stroke_width(width))),
    )?;
    chart.draw_series(
        arrows
            .iter()
            .map(|(_, head)| Polygon::new(head.to_vec(), color.filled())),
    )?;
    Ok(())
}

impl ForceMapFigure {
    /// Largest |fz| over the finite nodes, N.
    pub fn fz_max(&self) -> f64 {
        self.forces
            .iter()
            .map(|r| r.f_n[2].abs())
            .filter(|v| v.is_finite())
            .fold(0.0, f64::max)
    }

    /// Largest tangential force |(fx, fy)|, N.
    pub fn tangential_max(&self) -> f64 {
        self.forces
            .iter()
            .map(|r| r.f_n[0].hypot(r.f_n[1]))
            .filter(|v| v.is_finite())
            .fold(0.0, f64::max)
    }

    /// Newtons to [`Self::unit`].
    pub fn shown(&self, newtons: f64) -> f64 {
        self.unit.from_newtons(newtons)
    }

    /// Arrow scale, in [`Self::unit`] per mm of arrow: the round value ([`nice_ceil`])
    /// that keeps the longest arrow within [`ARROW_FRACTION`] of the pitch (0 when there
    /// is no tangential force). Round in the unit shown, so the key reads 50 gf, not
    /// 0.5 N = 50.99 gf.
    pub fn per_mm(&self) -> f64 {
        let t = self.shown(self.tangential_max());
        if t > 0.0 {
            nice_ceil(t / (ARROW_FRACTION * self.pitch_mm))
        } else {
            0.0
        }
    }

    /// The key arrow: (force in [`Self::unit`], length mm), at most [`ARROW_FRACTION`]
    /// of the pitch.
    pub fn key(&self) -> (f64, f64) {
        let k = self.per_mm();
        if k <= 0.0 {
            return (0.0, 0.0);
        }
        let f = nice_floor(k * ARROW_FRACTION * self.pitch_mm);
        (f, f / k)
    }

    /// The tangential arrows on the scale of [`Self::per_mm`].
    pub fn arrows(&self) -> Vec<ArrowParts> {
        let k = self.per_mm();
        if k <= 0.0 {
            return Vec::new();
        }
        self.forces
            .iter()
            .filter_map(|r| {
                let a = (r.position_mm[0], r.position_mm[1]);
                let b = (
                    a.0 + self.shown(r.f_n[0]) / k,
                    a.1 + self.shown(r.f_n[1]) / k,
                );
                let len = (b.0 - a.0).hypot(b.1 - a.1);
                arrow_parts(a, b, (0.4 * len).min(0.2 * self.pitch_mm))
            })
            .collect()
    }

    /// A figure size (px) giving both axes about the same mm per pixel.
    pub fn size_px(&self) -> (u32, u32) {
        let (xs, ys) = self.extent();
        let panels = if self.sd.is_some() { 2 } else { 1 };
        let panel_w = 820.0;
        let plot_w = panel_w - BAR_PX as f64 - 90.0;
        let plot_h = plot_w * (ys.end - ys.start) / (xs.end - xs.start);
        let h = (plot_h + 110.0).clamp(360.0, 1000.0);
        ((panel_w as u32) * panels, h as u32)
    }

    /// The map's x and y ranges, mm (cells of one pitch, a band on top for the key).
    fn extent(&self) -> (std::ops::Range<f64>, std::ops::Range<f64>) {
        let p = self.pitch_mm;
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for r in &self.forces {
            x0 = x0.min(r.position_mm[0]);
            x1 = x1.max(r.position_mm[0]);
            y0 = y0.min(r.position_mm[1]);
            y1 = y1.max(r.position_mm[1]);
        }
        if x0 > x1 {
            return (0.0..1.0, 0.0..1.0);
        }
        (
            (x0 - 0.5 * p)..(x1 + 0.5 * p),
            (y0 - 0.5 * p)..(y1 + 1.4 * p),
        )
    }

    /// One panel: cells coloured by `value` through `color`, a colour bar over
    /// `bar_range` titled `bar_label`, arrows and key when `arrows`.
    #[allow(clippy::too_many_arguments)]
    fn panel<DB: DrawingBackend>(
        &self,
        area: &DrawingArea<DB, Shift>,
        caption: &str,
        value: &dyn Fn(usize) -> f64,
        color: &dyn Fn(f64) -> RGBColor,
        bar_range: std::ops::Range<f64>,
        bar_label: &str,
        arrows: bool,
    ) -> FigureResult<DB> {
        let (w, _) = area.dim_in_pixel();
        let (map, bar) = area.split_horizontally(w.saturating_sub(BAR_PX));
        let (xs, ys) = self.extent();
        let p = self.pitch_mm;
        let mut chart = ChartBuilder::on(&map)
            .caption(caption, (FONT, 17))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(50)
            .build_cartesian_2d(xs.clone(), ys.clone())?;
        chart
            .configure_mesh()
            .disable_mesh()
            .x_desc("x (mm)")
            .y_desc("y (mm)")
            .label_style((FONT, 13))
            .draw()?;
        chart.draw_series(self.forces.iter().enumerate().map(|(i, r)| {
            let (x, y) = (r.position_mm[0], r.position_mm[1]);
            let v = value(i);
            let fill = if v.is_finite() {
                color(v)
            } else {
                RGBColor(200, 200, 200)
            };
            Rectangle::new(
                [(x - 0.5 * p, y - 0.5 * p), (x + 0.5 * p, y + 0.5 * p)],
                fill.filled(),
            )
        }))?;
        // Node markers, so the grid is visible where the field is white.
        chart.draw_series(self.forces.iter().map(|r| {
            Circle::new(
                (r.position_mm[0], r.position_mm[1]),
                2,
                RGBColor(90, 90, 90).filled(),
            )
        }))?;
        let top = ys.end - 0.45 * p;
        if arrows {
            draw_arrows(&mut chart, &self.arrows(), BLACK, 2)?;
            let (kf, kl) = self.key();
            if kl > 0.0 {
                let a = (xs.start + 0.3 * p, top);
                if let Some(k) = arrow_parts(a, (a.0 + kl, a.1), (0.4 * kl).min(0.2 * p)) {
                    draw_arrows(&mut chart, &[k], BLACK, 2)?;
                }
                let u = self.unit.symbol();
                chart.draw_series(std::iter::once(Text::new(
                    format!(
                        "= {} {u}  (arrows: {} {u} per mm)",
                        fmt_short(kf),
                        fmt_short(self.per_mm())
                    ),
                    (a.0 + kl + 0.15 * p, top + 0.2 * p),
                    (FONT, 14).into_font(),
                )))?;
            } else {
                chart.draw_series(std::iter::once(Text::new(
                    "no tangential force".to_string(),
                    (xs.start + 0.3 * p, top + 0.2 * p),
                    (FONT, 14).into_font(),
                )))?;
            }
        }
        // Colour bar.
        let bar_span = bar_range.end - bar_range.start;
        let mut cb = ChartBuilder::on(&bar)
            .margin_top(40)
            .margin_bottom(50)
            .margin_right(8)
            .y_label_area_size(55)
            .build_cartesian_2d(0.0..1.0, bar_range.clone())?;
        cb.configure_mesh()
            .disable_mesh()
            .disable_x_axis()
            .y_desc(bar_label)
            .y_label_formatter(&|v| bar_tick(*v, bar_span))
            .label_style((FONT, 12))
            .axis_desc_style((FONT, 13))
            .draw()?;
        let steps = 100;
        let span = bar_range.end - bar_range.start;
        cb.draw_series((0..steps).map(|i| {
            let v0 = bar_range.start + span * i as f64 / steps as f64;
            let v1 = bar_range.start + span * (i + 1) as f64 / steps as f64;
            Rectangle::new([(0.0, v0), (1.0, v1)], color(0.5 * (v0 + v1)).filled())
        }))?;
        Ok(())
    }
}

/// A colour-bar tick label: [`fmt_short`], with a tick that is zero up to rounding in
/// the bar's span (e.g. -1.1e-16 N on a ±0.7 N bar, drawn before as
/// "-0.000000000000000111" across the map) shown as 0.
fn bar_tick(v: f64, span: f64) -> String {
    if v.abs() <= 1e-9 * span.abs() {
        "0".to_string()
    } else {
        fmt_short(v)
    }
}

/// A force given in newtons, shown in `unit` with 4 significant digits and the unit's
/// symbol: `fmt_force(7.317, GramForce)` = "746.1 gf".
pub fn fmt_force(newtons: f64, unit: ForceUnit) -> String {
    let v = unit.from_newtons(newtons);
    if v == 0.0 || !v.is_finite() {
        return format!("{v} {}", unit.symbol());
    }
    let digits = (3 - v.abs().log10().floor() as i32).max(0) as usize;
    format!("{v:.digits$} {}", unit.symbol())
}

/// A number with at most 3 significant digits, no trailing zeros.
pub fn fmt_short(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    let digits = (2 - v.abs().log10().floor() as i32).max(0) as usize;
    let s = format!("{v:.digits$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

impl Figure for ForceMapFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
        let root = root.titled(&self.title, (FONT, 20))?;
        let u = self.unit.symbol();
        let l = self.shown(self.fz_max());
        let l = if l > 0.0 { l } else { 1.0 };
        let panels = match &self.sd {
            Some(_) => root.split_evenly((1, 2)),
            None => vec![root.clone()],
        };
        self.panel(
            &panels[0],
            "fz (colour) and tangential force (arrows)",
            &|i| self.shown(self.forces[i].f_n[2]),
            &|v| diverging(v / l),
            -l..l,
            &format!("fz ({u}), red presses in"),
            true,
        )?;
        if let (Some(sd), Some(area)) = (&self.sd, panels.get(1)) {
            let m = sd
                .fz_sd_n
                .iter()
                .map(|v| self.shown(*v))
                .filter(|v| v.is_finite())
                .fold(0.0, f64::max);
            let m = if m > 0.0 { m } else { 1.0 };
            self.panel(
                area,
                &format!("σ(fz) per node, noise {} px", fmt_short(sd.noise_px)),
                &|i| sd.fz_sd_n.get(i).map_or(f64::NAN, |v| self.shown(*v)),
                &|v| sequential(v / m),
                0.0..m,
                &format!("σ(fz) ({u})"),
                false,
            )?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {

    #[test]
    fn a_colour_bar_tick_at_zero_up_to_rounding_is_labelled_0() {
        assert_eq!(bar_tick(-1.1102230246251565e-16, 1.44), "0");
        assert_eq!(bar_tick(0.0, 1.44), "0");
        assert_eq!(bar_tick(-0.2, 1.44), "-0.2");
        assert_eq!(bar_tick(0.6, 1.44), "0.6");
    }

    use super::*;

    fn rec(ix: usize, iy: usize, p: f64, f: [f64; 3]) -> ForceRecord {
        ForceRecord {
            ix,
            iy,
            position_mm: [ix as f64 * p, iy as f64 * p],
            f_n: f,
        }
    }

    #[test]
    fn forces_are_shown_in_the_plans_unit_with_four_significant_digits() {
        assert_eq!(fmt_force(7.317, ForceUnit::Newton), "7.317 N");
        assert_eq!(fmt_force(7.317, ForceUnit::GramForce), "746.1 gf");
        assert_eq!(fmt_force(0.0098, ForceUnit::GramForce), "0.9993 gf");
        assert_eq!(fmt_force(0.0, ForceUnit::GramForce), "0 gf");
    }

    /// A gf plan's force map: the key arrow is a round force in gf (not a round N
    /// converted), on the same scale as the arrows, and the scale is the N one × 1/g.
    #[test]
    fn a_gf_force_map_keys_its_arrows_in_round_gram_force() {
        let p = 2.2;
        let forces = vec![
            rec(0, 0, p, [0.3, 0.0, 1.0]),
            rec(1, 0, p, [0.0, -0.1, 0.5]),
        ];
        let fig = |unit| ForceMapFigure {
            title: String::new(),
            pitch_mm: p,
            forces: forces.clone(),
            sd: None,
            unit,
        };
        let (n, gf) = (fig(ForceUnit::Newton), fig(ForceUnit::GramForce));
        let (kf, kl) = gf.key();
        assert_eq!(kf, nice_floor(kf), "key force {kf} gf is a 1-2-5 value");
        assert!((kf / kl - gf.per_mm()).abs() < 1e-9);
        // The longest arrow stays within the limit in either unit.
        for f in [&n, &gf] {
            let longest = f
                .arrows()
                .iter()
                .map(|(s, h)| (h[0].0 - s[0].0).hypot(h[0].1 - s[0].1))
                .fold(0.0, f64::max);
            assert!(longest > 0.0 && longest <= ARROW_FRACTION * p + 1e-12);
        }
        assert!(
            gf.per_mm() > 50.0 * n.per_mm(),
            "{} {}",
            gf.per_mm(),
            n.per_mm()
        );
    }

    #[test]
    fn nice_numbers_are_round_steps() {
        assert_eq!(nice_ceil(0.7), 0.8);
        assert_eq!(nice_ceil(0.95), 1.0);
        assert_eq!(nice_ceil(1.3), 1.5);
        assert_eq!(nice_ceil(2.0), 2.0);
        assert!((nice_ceil(0.031) - 0.04).abs() < 1e-15);
        assert_eq!(nice_floor(7.0), 5.0);
        assert_eq!(nice_floor(1.9), 1.0);
        assert!((nice_floor(0.25) - 0.2).abs() < 1e-15);
    }

    /// The four nodes around a load between them carry inward tangential forces of
    /// the field's largest size: their arrows must not reach the centre (the X seen
    /// on the Fig. 7 report at 0.9 pitch), and must point where the force points.
    #[test]
    fn arrows_around_a_load_between_nodes_point_inward_and_do_not_cross() {
        let p = 2.2;
        let t = 0.85;
        let forces = vec![
            rec(0, 0, p, [t, t, 1.7]),
            rec(1, 0, p, [-t, t, 1.7]),
            rec(0, 1, p, [t, -t, 1.7]),
            rec(1, 1, p, [-t, -t, 1.7]),
        ];
        let fig = ForceMapFigure {
            title: String::new(),
            pitch_mm: p,
            forces: forces.clone(),
            sd: None,
            unit: ForceUnit::Newton,
        };
        let arrows = fig.arrows();
        assert_eq!(arrows.len(), 4);
        let centre = (0.5 * p, 0.5 * p);
        for ((shaft, head), r) in arrows.iter().zip(&forces) {
            let tip = head[0];
            // Along the force.
            let (dx, dy) = (tip.0 - shaft[0].0, tip.1 - shaft[0].1);
            assert!(dx * r.f_n[0] > 0.0 && dy * r.f_n[1] > 0.0, "{dx} {dy}");
            // Shorter than ARROW_FRACTION of the pitch, so short of the centre.
            assert!(dx.hypot(dy) <= ARROW_FRACTION * p + 1e-12);
            let d_tip = (tip.0 - centre.0).hypot(tip.1 - centre.1);
            let d_node = (shaft[0].0 - centre.0).hypot(shaft[0].1 - centre.1);
            assert!(
                d_tip < d_node && d_tip > 0.2 * p,
                "tip {d_tip}, node {d_node}"
            );
        }
        // The key: a 1-2-5 force, length within the arrow limit, on the arrows' scale.
        let (kf, kl) = fig.key();
        assert!(kl > 0.0 && kl <= ARROW_FRACTION * p + 1e-12);
        assert!((kf / kl - fig.per_mm()).abs() < 1e-12);
    }

    #[test]
    fn arrow_head_is_a_triangle_at_the_tip() {
        let (shaft, head) = arrow_parts((0.0, 0.0), (10.0, 0.0), 2.0).unwrap();
        assert_eq!(head[0], (10.0, 0.0));
        assert_eq!(shaft[1], (8.0, 0.0));
        assert!((head[1].0 - 8.0).abs() < 1e-12 && (head[1].1.abs() - 1.0).abs() < 1e-12);
        assert!((head[2].1 + head[1].1).abs() < 1e-12);
        assert!(arrow_parts((1.0, 1.0), (1.0, 1.0), 1.0).is_none());
    }
}
