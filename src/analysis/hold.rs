//! Creep and zero drift from `hold` sweeps: a constant force held for a stated time,
//! the F/T reference and the reconstruction sampled through it (journal `hold_t_s` =
//! seconds since the hold force was reached), with unloaded rows (target 0, `hold_t_s`
//! empty) before the first hold and after each one. Dispatched on the data: any run
//! whose journal has rows with `hold_t_s` gets this analysis.
//!
//! - **Holds**: consecutive rows (in setpoint order) with `hold_t_s`; a row without it,
//!   or a `hold_t_s` that does not increase, starts the next hold.
//! - **Creep** of F^sum relative to the F/T, ISO 376:2011 7.5.5 in spirit (the
//!   standard reads the change between 30 s and 300 s at constant maximum force): the
//!   least-squares slope `k` of `d = F^sum_z − F_z` (journal `fsum_z_n − fz_n`, N)
//!   against `hold_t_s`, common to every hold with one intercept per hold (pooled
//!   within-hold slope `k = ΣΣ(t − t̄_h)(d − d̄_h) / ΣΣ(t − t̄_h)²`; for one hold the
//!   ordinary slope). Metric `hold.creep_pct_fs_per_min` = `100·60·k / FS` in **% of
//!   full scale per minute**, FS = the largest applied force of the run (max `fz_n`).
//!   95 % CI: Student t on the slope's standard error with n − holds − 1 dof. The ISO
//!   criterion c is compared as the change over 4.5 min (30 s to 300 s) on that line.
//!   The F/T's own drift through the holds, the same slope of `fz_n`, is
//!   `hold.ft_drift_pct_fs_per_min` (a force-controlled hold keeps it near zero; a
//!   position hold shows the elastomer's relaxation).
//! - **Zero drift** over the run: the unloaded error `e = F^sum_z − F_z` of the last
//!   unloaded row minus that of the first (N, `hold.zero_drift_n`; also in %FS). 95 %
//!   CI where both rows carry the reconstruction's propagated SD (`fsum_sd_z_n`):
//!   `± 1.96·√(sd_first² + sd_last²)`, method `normal`.

use super::calibration::same_level;
use super::metrology::{ClassResult, Criterion, CREEP_INTERVAL_MIN};
use super::stats;
use super::Ci95;
use crate::bench::journal::JournalRow;

/// One sample of a hold.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HoldSample {
    /// Setpoint index.
    pub index: usize,
    /// Which hold (0-based, in run order).
    pub hold: usize,
    /// Seconds since the hold force was reached.
    pub t_s: f64,
    /// F/T `fz_n`, N.
    pub applied_n: f64,
    /// F^sum `fsum_z_n`, N.
    pub measured_n: f64,
}

/// One unloaded reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ZeroReading {
    /// Setpoint index.
    pub index: usize,
    /// `F^sum_z − F_z`, N.
    pub error_n: f64,
    /// Propagated SD of F^sum_z, N, if recorded.
    pub sd_n: Option<f64>,
}

/// A pooled within-group slope.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PooledSlope {
    /// Slope, per second.
    pub slope: f64,
    /// Intercept of each group.
    pub intercepts: usize,
    /// 95 % t interval of the slope, per second.
    pub ci95: Option<(f64, f64)>,
}

/// The hold analysis of a run.
#[derive(Debug, Clone, PartialEq)]
pub struct HoldAnalysis {
    /// Full scale: the largest applied force of the run, N.
    pub full_scale_n: f64,
    /// Every hold sample, in setpoint order.
    pub samples: Vec<HoldSample>,
    /// Number of holds.
    pub holds: usize,
    /// Slope of `F^sum − F/T` against `hold_t_s`, N/s.
    pub creep: PooledSlope,
    /// Intercept of `F^sum − F/T` per hold (at t = 0), N.
    pub creep_intercepts_n: Vec<f64>,
    /// Slope of the F/T against `hold_t_s`, N/s.
    pub ft_drift: Option<PooledSlope>,
    /// Unloaded readings in run order.
    pub zeros: Vec<ZeroReading>,
    /// The class the creep implies.
    pub class: Option<ClassResult>,
}

impl HoldAnalysis {
    /// `% of FS per minute` of a slope in N/s.
    pub fn pct_fs_per_min(&self, n_per_s: f64) -> f64 {
        100.0 * 60.0 * n_per_s / self.full_scale_n
    }

    /// Creep, %FS/min.
    pub fn creep_pct_fs_per_min(&self) -> f64 {
        self.pct_fs_per_min(self.creep.slope)
    }

    /// Its 95 % interval, %FS/min.
    pub fn creep_ci95(&self) -> Option<Ci95> {
        self.creep.ci95.map(|(lo, hi)| Ci95 {
            low: self.pct_fs_per_min(lo),
            high: self.pct_fs_per_min(hi),
            method: "t",
        })
    }

    /// Last minus first unloaded error, N (two or more unloaded rows).
    pub fn zero_drift_n(&self) -> Option<f64> {
        let (a, b) = (self.zeros.first()?, self.zeros.last()?);
        (self.zeros.len() >= 2).then_some(b.error_n - a.error_n)
    }

    /// Its 95 % interval from the propagated SDs, N.
    pub fn zero_drift_ci95(&self) -> Option<Ci95> {
        let d = self.zero_drift_n()?;
        let (a, b) = (self.zeros.first()?, self.zeros.last()?);
        let h = 1.96 * a.sd_n?.hypot(b.sd_n?);
        h.is_finite().then_some(Ci95 {
            low: d - h,
            high: d + h,
            method: "normal",
        })
    }
}

/// Pooled slope of `y` against `t` with one intercept per group: `(slope, intercepts,
/// ci)`; `None` when the times do not vary within any group.
pub fn pooled_slope(points: &[(usize, f64, f64)]) -> Option<(PooledSlope, Vec<f64>)> {
    let groups = points.iter().map(|p| p.0).max()? + 1;
    let mut n = vec![0usize; groups];
    let (mut st, mut sy) = (vec![0.0; groups], vec![0.0; groups]);
    for &(g, t, y) in points {
        n[g] += 1;
        st[g] += t;
        sy[g] += y;
    }
    let mt: Vec<f64> = (0..groups).map(|g| st[g] / n[g].max(1) as f64).collect();
    let my: Vec<f64> = (0..groups).map(|g| sy[g] / n[g].max(1) as f64).collect();
    let (mut sxx, mut sxy) = (0.0, 0.0);
    for &(g, t, y) in points {
        sxx += (t - mt[g]).powi(2);
        sxy += (t - mt[g]) * (y - my[g]);
    }
    if sxx.is_nan() || sxx <= 0.0 {
        return None;
    }
    let slope = sxy / sxx;
    let used = n.iter().filter(|&&k| k > 0).count();
    let dof = points.len().saturating_sub(used + 1);
    let ss: f64 = points
        .iter()
        .map(|&(g, t, y)| (y - my[g] - slope * (t - mt[g])).powi(2))
        .sum();
    let ci95 = (dof > 0)
        .then(|| {
            let se = (ss / dof as f64).sqrt() / sxx.sqrt();
            let h = stats::t_quantile(0.975, dof as f64)? * se;
            Some((slope - h, slope + h))
        })
        .flatten();
    let intercepts = (0..groups).map(|g| my[g] - slope * mt[g]).collect();
    Some((
        PooledSlope {
            slope,
            intercepts: used,
            ci95,
        },
        intercepts,
    ))
}

/// Analyses the rows of a run with hold samples (`None` when it has fewer than three,
/// or their times do not vary).
pub fn analyze(rows: &[JournalRow]) -> Option<HoldAnalysis> {
    let mut sorted: Vec<&JournalRow> = rows.iter().collect();
    sorted.sort_by_key(|r| r.index);
    let mut samples = Vec::new();
    let mut zeros = Vec::new();
    let mut hold = 0usize;
    let mut prev: Option<f64> = None;
    for r in &sorted {
        match r.hold_t_s {
            Some(t) if t.is_finite() => {
                if prev.is_some_and(|p| t <= p) {
                    hold += 1;
                }
                samples.push(HoldSample {
                    index: r.index,
                    hold,
                    t_s: t,
                    applied_n: r.fz_n,
                    measured_n: r.fsum_z_n,
                });
                prev = Some(t);
            }
            _ => {
                if prev.is_some() {
                    hold += 1;
                }
                prev = None;
                if same_level(r.target_normal_n, 0.0) {
                    zeros.push(ZeroReading {
                        index: r.index,
                        error_n: r.fsum_z_n - r.fz_n,
                        sd_n: r.fsum_sd_z_n,
                    });
                }
            }
        }
    }
    if samples.len() < 3 {
        return None;
    }
    // Renumber holds 0.. in order (a hold number is skipped after trailing unloaded rows).
    let mut ids: Vec<usize> = samples.iter().map(|s| s.hold).collect();
    ids.dedup();
    for s in &mut samples {
        s.hold = ids.iter().position(|&h| h == s.hold).unwrap_or(0);
    }
    let fs = rows
        .iter()
        .map(|r| r.fz_n)
        .fold(f64::NEG_INFINITY, f64::max);
    if !(fs.is_finite() && fs > 0.0) {
        return None;
    }
    let d: Vec<(usize, f64, f64)> = samples
        .iter()
        .map(|s| (s.hold, s.t_s, s.measured_n - s.applied_n))
        .collect();
    let (creep, creep_intercepts_n) = pooled_slope(&d)?;
    let f: Vec<(usize, f64, f64)> = samples
        .iter()
        .map(|s| (s.hold, s.t_s, s.applied_n))
        .collect();
    let ft_drift = pooled_slope(&f).map(|p| p.0);
    let c_iso = (100.0 * 60.0 * creep.slope / fs * CREEP_INTERVAL_MIN).abs();
    Some(HoldAnalysis {
        full_scale_n: fs,
        holds: ids.len(),
        samples,
        creep,
        creep_intercepts_n,
        ft_drift,
        zeros,
        class: ClassResult::judge(&[(
            Criterion::Creep,
            c_iso,
            "creep rate × 4.5 min (30 s to 300 s)",
        )]),
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Unloaded, a hold of `n` samples at `force` (F^sum − F/T = a + k·t + noise),
    /// unloaded, for each of `holds` holds.
    pub(crate) fn hold_rows(
        holds: usize,
        n: usize,
        force: f64,
        k: f64,
        noise: impl Fn(usize, usize) -> f64,
    ) -> Vec<JournalRow> {
        let mut rows = Vec::new();
        let mut i = 0;
        let zero = |i: usize| JournalRow {
            index: i,
            fsum_z_n: 0.01 * i as f64,
            fsum_sd_z_n: Some(0.003),
            ..JournalRow::default()
        };
        rows.push(zero(i));
        i += 1;
        for h in 0..holds {
            for s in 0..n {
                let t = 5.0 * s as f64;
                rows.push(JournalRow {
                    index: i,
                    trial: h,
                    target_normal_n: force,
                    fz_n: force - 0.001 * t,
                    fsum_z_n: force - 0.001 * t + 0.2 * h as f64 + k * t + noise(h, s),
                    hold_t_s: Some(t),
                    ..JournalRow::default()
                });
                i += 1;
            }
            rows.push(zero(i));
            i += 1;
        }
        rows
    }

    #[test]
    fn creep_of_known_rate_is_recovered_per_minute_of_full_scale() {
        // 3 holds at 4 N with different offsets, 0.002 N/s creep: 100·60·0.002/4 = 3 %FS/min.
        let rows = hold_rows(3, 13, 4.0, 0.002, |_, _| 0.0);
        let h = analyze(&rows).unwrap();
        assert_eq!(h.holds, 3);
        assert_eq!(h.full_scale_n, 4.0);
        assert!(
            (h.creep_pct_fs_per_min() - 3.0).abs() < 1e-9,
            "{}",
            h.creep_pct_fs_per_min()
        );
        // The F/T relaxes 0.001 N/s: −1.5 %FS/min.
        let ft = h.ft_drift.unwrap();
        assert!((h.pct_fs_per_min(ft.slope) + 1.5).abs() < 1e-9);
        assert!((h.creep_intercepts_n[2] - 0.4).abs() < 1e-9);
        // Unloaded rows 0, 14, 28, 42: zero drift 0.42 N, CI from 0.003 N SDs.
        assert_eq!(h.zeros.len(), 4);
        assert!((h.zero_drift_n().unwrap() - 0.42).abs() < 1e-9);
        let ci = h.zero_drift_ci95().unwrap();
        assert!((ci.high - 0.42 - 1.96 * 0.003 * 2f64.sqrt()).abs() < 1e-9);
        // c = 3 %FS/min × 4.5 min: no class.
        assert_eq!(h.class.unwrap().code, super::super::metrology::NO_CLASS);
    }

    #[test]
    fn too_few_hold_samples_give_no_analysis() {
        assert_eq!(analyze(&hold_rows(1, 2, 4.0, 0.0, |_, _| 0.0)), None);
    }
}
