//! Applied-against-measured characterisation shared by the magnitude (paper Fig. 7) and
//! angle (Fig. 8) analyses: samples grouped into levels (one per target setpoint), a
//! least-squares line through all samples, and the figures of merit derived from it.
//!
//! Definitions (x = applied, y = measured, fit ŷ = slope·x + offset, residual
//! r = y − ŷ):
//!
//! - **slope, offset, R²**: ordinary least squares over every sample (see [`stats`]).
//! - **residual SD per level**: sample SD of the residuals of the level's samples. Using
//!   residuals rather than raw y removes the (small) spread of the applied value
//!   within a level, so it measures the sensor's spread only.
//! - **pooled SD** `s_p`: the per-level residual SDs pooled by degrees of freedom; when
//!   no level has two samples (one trial per level), the residual SD about the line
//!   (n − 2 dof) instead. Which one was used is recorded in
//!   [`Calibration::resolution_method`] (metrics `magnitude.resolution_method`,
//!   `angle.resolution_method`: 1 = pooled within-level, 2 = about the fit line) and
//!   said on the report page: with one trial per level the fallback also counts any
//!   nonlinearity as spread.
//! - **resolution**: the paper reads its 30 gf and 5° from the *data spread* of Fig. 7
//!   and 8 (the vertical scatter at each level). We take that spread as the ±1 SD band,
//!   `2·s_p`, and express it in applied units through the sensitivity:
//!   `resolution = 2·s_p / |slope|`. Two applied values closer than this produce
//!   overlapping ±1 SD bands of measured values.
//! - **linearity error**: the largest deviation of a level's mean residual from the fit,
//!   as a percentage of the full-scale output `FSO = |slope|·(x_max − x_min)` over the
//!   level means. Level means are used so that noise does not count as nonlinearity.
//! - **hysteresis**: for levels measured both while loading (target rising within a
//!   trial) and unloading (target falling), the largest difference of the two mean
//!   residuals, as a percentage of FSO; `None` when no level has both.
//!
//! [`stats`]: super::stats

use super::stats::{self, LineFit};

/// Whether a sample was taken with the target rising or falling within its trial.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Direction {
    /// Target rising (or the first sample of a trial).
    Loading,
    /// Target falling.
    Unloading,
}

/// One applied/measured pair.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// The level's target (groups samples into levels), applied units.
    pub target: f64,
    /// Applied value (reference instrument).
    pub applied: f64,
    /// Measured value (the sensor under test).
    pub measured: f64,
    /// Loading or unloading.
    pub direction: Direction,
}

/// Statistics of one level.
#[derive(Debug, Clone, PartialEq)]
pub struct Level {
    /// Target, applied units.
    pub target: f64,
    /// Samples in the level.
    pub n: usize,
    /// Mean applied value.
    pub applied_mean: f64,
    /// Mean measured value.
    pub measured_mean: f64,
    /// Sample SD of the measured values (0 for one sample).
    pub measured_sd: f64,
    /// Mean residual about the fit (the level's deviation from linearity).
    pub residual_mean: f64,
    /// Sample SD of the residuals (0 for one sample).
    pub residual_sd: f64,
}

/// Which spread the resolution is built on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ResolutionMethod {
    /// Pooled within-level residual SD (at least one level has two samples).
    PooledWithinLevel,
    /// Residual SD about the fit line, n − 2 dof (no level has two samples).
    FitLine,
}

impl ResolutionMethod {
    /// The metric code: 1 pooled within-level, 2 about the fit line.
    pub fn code(self) -> f64 {
        match self {
            ResolutionMethod::PooledWithinLevel => 1.0,
            ResolutionMethod::FitLine => 2.0,
        }
    }

    /// In words, for the report.
    pub fn describe(self) -> &'static str {
        match self {
            ResolutionMethod::PooledWithinLevel => "2 × pooled within-level residual SD / |slope|",
            ResolutionMethod::FitLine => {
                "2 × residual SD about the fit line / |slope| (no level has two trials, so there                  is no within-level spread; nonlinearity counts as spread)"
            }
        }
    }
}

/// Result of [`calibrate`].
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// The least-squares line through every sample.
    pub fit: LineFit,
    /// Levels in ascending target order.
    pub levels: Vec<Level>,
    /// Pooled within-level residual SD, measured units (the SD about the fit line when
    /// no level has two samples, see `resolution_method`).
    pub pooled_sd: f64,
    /// Degrees of freedom of `pooled_sd`.
    pub pooled_dof: usize,
    /// Which spread `pooled_sd` is.
    pub resolution_method: ResolutionMethod,
    /// `2·pooled_sd / |slope|`, applied units.
    pub resolution: f64,
    /// Full-scale output `|slope|·(x_max − x_min)`, measured units.
    pub full_scale: f64,
    /// Max |level mean residual| / FSO, %.
    pub linearity_pct: f64,
    /// Max |unloading − loading mean residual| / FSO, %, when both exist at a level.
    pub hysteresis_pct: Option<f64>,
    /// Number of samples.
    pub n: usize,
}

/// Why a calibration could not be computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibrationError {
    /// Fewer than two distinct applied values (or a non-finite value).
    #[error("{0}")]
    Insufficient(String),
}

/// Fits and characterises `samples` (see the module docs for every definition).
pub fn calibrate(samples: &[Sample]) -> Result<Calibration, CalibrationError> {
    if let Some(s) = samples
        .iter()
        .find(|s| !(s.applied.is_finite() && s.measured.is_finite() && s.target.is_finite()))
    {
        return Err(CalibrationError::Insufficient(format!(
            "non-finite sample: target {}, applied {}, measured {}",
            s.target, s.applied, s.measured
        )));
    }
    let x: Vec<f64> = samples.iter().map(|s| s.applied).collect();
    let y: Vec<f64> = samples.iter().map(|s| s.measured).collect();
    let fit = stats::fit_line(&x, &y).ok_or_else(|| {
        CalibrationError::Insufficient(format!(
            "a line fit needs at least two distinct applied values, got {} sample(s)",
            samples.len()
        ))
    })?;

    let mut targets: Vec<f64> = samples.iter().map(|s| s.target).collect();
    targets.sort_by(f64::total_cmp);
    targets.dedup_by(|a, b| same_level(*a, *b));
    let mut levels = Vec::with_capacity(targets.len());
    let mut hysteresis: Option<f64> = None;
    for &t in &targets {
        let in_level: Vec<&Sample> = samples.iter().filter(|s| same_level(s.target, t)).collect();
        let a: Vec<f64> = in_level.iter().map(|s| s.applied).collect();
        let m: Vec<f64> = in_level.iter().map(|s| s.measured).collect();
        let r: Vec<f64> = in_level
            .iter()
            .map(|s| s.measured - fit.at(s.applied))
            .collect();
        let mean_r = |d: Direction| {
            let v: Vec<f64> = in_level
                .iter()
                .filter(|s| s.direction == d)
                .map(|s| s.measured - fit.at(s.applied))
                .collect();
            stats::mean(&v)
        };
        if let (Some(up), Some(down)) = (mean_r(Direction::Loading), mean_r(Direction::Unloading)) {
            let d = (down - up).abs();
            hysteresis = Some(hysteresis.map_or(d, |h: f64| h.max(d)));
        }
        levels.push(Level {
            target: t,
            n: in_level.len(),
            applied_mean: stats::mean(&a).unwrap_or(f64::NAN),
            measured_mean: stats::mean(&m).unwrap_or(f64::NAN),
            measured_sd: stats::sample_sd(&m).unwrap_or(0.0),
            residual_mean: stats::mean(&r).unwrap_or(f64::NAN),
            residual_sd: stats::sample_sd(&r).unwrap_or(0.0),
        });
    }
    let (pooled_sd, pooled_dof, resolution_method) =
        match stats::pooled_sd(levels.iter().map(|l| (l.n, l.residual_sd))) {
            Some(s) => (
                s,
                levels.iter().map(|l| l.n.saturating_sub(1)).sum(),
                ResolutionMethod::PooledWithinLevel,
            ),
            None => (
                fit.residual_sd,
                samples.len().saturating_sub(2),
                ResolutionMethod::FitLine,
            ),
        };
    let (lo, hi) = levels
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), l| {
            (lo.min(l.applied_mean), hi.max(l.applied_mean))
        });
    let full_scale = fit.slope.abs() * (hi - lo);
    if full_scale.is_nan() || full_scale <= 0.0 {
        return Err(CalibrationError::Insufficient(format!(
            "full-scale output is {full_scale}: the sensor's response does not change with the applied value"
        )));
    }
    let max_dev = levels
        .iter()
        .fold(0.0f64, |m, l| m.max(l.residual_mean.abs()));
    Ok(Calibration {
        fit,
        pooled_sd,
        pooled_dof,
        resolution_method,
        resolution: 2.0 * pooled_sd / fit.slope.abs(),
        full_scale,
        linearity_pct: 100.0 * max_dev / full_scale,
        hysteresis_pct: hysteresis.map(|h| 100.0 * h / full_scale),
        n: samples.len(),
        levels,
    })
}

impl Calibration {
    /// 95 % chi-squared interval of the resolution `2·s_p/|slope|` (from the interval
    /// of `s_p` with its degrees of freedom; the slope's own uncertainty, far smaller in
    /// relative terms, is not propagated).
    pub fn resolution_ci95(&self) -> Option<(f64, f64)> {
        let (lo, hi) = stats::sd_ci95(self.pooled_sd, self.pooled_dof)?;
        let k = 2.0 / self.fit.slope.abs();
        Some((k * lo, k * hi))
    }
}

/// Targets within 1e-9 (relative to their size, or absolute near zero) are one level:
/// unit conversions of the same plan value differ only by rounding.
pub(crate) fn same_level(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1.0)
}

/// Marks each sample of a trial, given in run order, as loading or unloading from the
/// change of its target: rising or first → loading, falling → unloading, equal → as
/// the previous one.
pub fn directions(targets_in_run_order: &[f64]) -> Vec<Direction> {
    let mut out = Vec::with_capacity(targets_in_run_order.len());
    let mut prev: Option<(f64, Direction)> = None;
    for &t in targets_in_run_order {
        let d = match prev {
            None => Direction::Loading,
            Some((p, pd)) => {
                if same_level(t, p) {
                    pd
                } else if t > p {
                    Direction::Loading
                } else {
                    Direction::Unloading
                }
            }
        };
        out.push(d);
        prev = Some((t, d));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(target: f64, applied: f64, measured: f64) -> Sample {
        Sample {
            target,
            applied,
            measured,
            direction: Direction::Loading,
        }
    }

    #[test]
    fn known_spread_gives_the_defined_resolution() {
        // measured = 0.9·applied + 0.05 ± 0.02 (two samples per level, symmetric), so
        // the fit is exact, each level's residual SD is sqrt(2)·0.02 and the
        // resolution 2·sqrt(2)·0.02 / 0.9.
        let mut v = Vec::new();
        for k in 0..6 {
            let a = k as f64;
            v.push(s(a, a, 0.9 * a + 0.05 + 0.02));
            v.push(s(a, a, 0.9 * a + 0.05 - 0.02));
        }
        let c = calibrate(&v).unwrap();
        assert!((c.fit.slope - 0.9).abs() < 1e-12);
        assert!((c.fit.offset - 0.05).abs() < 1e-12);
        let sd = 2f64.sqrt() * 0.02;
        assert!((c.pooled_sd - sd).abs() < 1e-12, "{}", c.pooled_sd);
        assert!((c.resolution - 2.0 * sd / 0.9).abs() < 1e-12);
        assert!(c.linearity_pct < 1e-9);
        assert_eq!(c.hysteresis_pct, None);
        assert_eq!(c.levels.len(), 6);
        assert_eq!(c.n, 12);
    }

    #[test]
    fn quadratic_bow_gives_the_closed_form_linearity_error() {
        // y = x² at x = 0, 1, 2: the fit is y = 2x − 1/3, residuals +1/3, −2/3, +1/3;
        // FSO = 2·2 = 4, so linearity = (2/3)/4 = 16.67 %.
        let c = calibrate(&[s(0.0, 0.0, 0.0), s(1.0, 1.0, 1.0), s(2.0, 2.0, 4.0)]).unwrap();
        assert!((c.fit.slope - 2.0).abs() < 1e-12);
        assert!(
            (c.linearity_pct - 100.0 / 6.0).abs() < 1e-9,
            "{}",
            c.linearity_pct
        );
    }

    #[test]
    fn unloading_offset_gives_the_hysteresis() {
        // Loading on y = x; unloading reads 0.1 higher at levels 1 and 2 (not at 0 or
        // 3). Residual difference between the branches is 0.1 at those levels, FSO from
        // the fitted slope.
        let up = [0.0, 1.0, 2.0, 3.0];
        let down = [3.0, 2.0, 1.0, 0.0];
        let mut v = Vec::new();
        let targets: Vec<f64> = up.iter().chain(down.iter()).copied().collect();
        let dirs = directions(&targets);
        assert_eq!(
            dirs[4],
            Direction::Loading,
            "repeated top level stays loading"
        );
        assert_eq!(dirs[5], Direction::Unloading);
        for (i, &t) in targets.iter().enumerate() {
            let bump = if dirs[i] == Direction::Unloading && (t == 1.0 || t == 2.0) {
                0.1
            } else {
                0.0
            };
            v.push(Sample {
                target: t,
                applied: t,
                measured: t + bump,
                direction: dirs[i],
            });
        }
        let c = calibrate(&v).unwrap();
        let h = c.hysteresis_pct.unwrap();
        let expected = 100.0 * 0.1 / (c.fit.slope * 3.0);
        assert!((h - expected).abs() < 1e-9, "{h} vs {expected}");
    }

    #[test]
    fn one_level_is_rejected_with_a_reason() {
        let e = calibrate(&[s(1.0, 1.0, 1.0), s(1.0, 1.0, 1.1)]).unwrap_err();
        assert!(e.to_string().contains("two distinct applied values"), "{e}");
    }
}
