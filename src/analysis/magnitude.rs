//! Force magnitude (paper Fig. 7): the summed reconstructed normal force
//! `F_z^sum = Σ_k f_z(k)` (journal `fsum_z_n`) against the applied normal force measured
//! by the F/T sensor (journal `fz_n`), levels keyed by the plan's target
//! (`target_normal_n`). Every figure of merit (slope, offset, R², residual SD per level,
//! resolution, linearity error, hysteresis) is defined in [`super::calibration`]; all
//! values are in newtons.
//!
//! Loading and unloading are taken from the journal's `direction` column where the
//! runner wrote it (`up` / `down`, up-down sweeps), else told apart per trial from the
//! run order of the targets ([`super::calibration::directions`]): the paper's sweep
//! only loads, so hysteresis is `None` for it. The ISO 376-style metrics of up-down and
//! multi-position sweeps are in [`super::metrology`].

use std::collections::BTreeMap;

use super::calibration::{self, Calibration, CalibrationError, Sample};
use crate::bench::journal::{self, JournalRow};

/// One measurement: applied (F/T) and measured (F^sum) normal force, N.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ForcePair {
    /// Setpoint index.
    pub index: usize,
    /// Applied normal force from the F/T sensor, N.
    pub applied_n: f64,
    /// Reconstructed F_z^sum, N.
    pub measured_n: f64,
}

/// The magnitude analysis of a run.
#[derive(Debug, Clone, PartialEq)]
pub struct MagnitudeAnalysis {
    /// Fit and figures of merit, N.
    pub calibration: Calibration,
    /// Every measurement in journal order (for plots).
    pub pairs: Vec<ForcePair>,
}

/// Analyses the journal rows of a magnitude sweep.
pub fn analyze(rows: &[JournalRow]) -> Result<MagnitudeAnalysis, CalibrationError> {
    let samples = samples(rows, |r| (r.target_normal_n, r.fz_n, r.fsum_z_n));
    let calibration = calibration::calibrate(&samples)?;
    let pairs = rows
        .iter()
        .map(|r| ForcePair {
            index: r.index,
            applied_n: r.fz_n,
            measured_n: r.fsum_z_n,
        })
        .collect();
    Ok(MagnitudeAnalysis { calibration, pairs })
}

/// Builds calibration samples from rows with `(target, applied, measured)` taken by
/// `pick`, marking loading/unloading per trial in setpoint order.
pub(crate) fn samples(
    rows: &[JournalRow],
    pick: impl Fn(&JournalRow) -> (f64, f64, f64),
) -> Vec<Sample> {
    // A trial is a (position, trial) pair: sweeps repeated at several contact positions
    // may number their trials per position.
    let mut by_trial: BTreeMap<(Option<usize>, usize), Vec<&JournalRow>> = BTreeMap::new();
    for r in rows {
        by_trial.entry((r.position, r.trial)).or_default().push(r);
    }
    let mut out = Vec::with_capacity(rows.len());
    for trial in by_trial.values_mut() {
        trial.sort_by_key(|r| r.index);
        let targets: Vec<f64> = trial.iter().map(|r| pick(r).0).collect();
        let dirs = calibration::directions(&targets);
        for (r, d) in trial.iter().zip(dirs) {
            let d = match r.direction {
                Some(journal::Direction::Up) => calibration::Direction::Loading,
                Some(journal::Direction::Down) => calibration::Direction::Unloading,
                None => d,
            };
            let (target, applied, measured) = pick(r);
            out.push(Sample {
                target,
                applied,
                measured,
                direction: d,
            });
        }
    }
    out
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::units::gf_to_n;

    /// A journal row with the given force fields; everything else neutral.
    pub(crate) fn row(
        index: usize,
        trial: usize,
        target: f64,
        f: [f64; 3],
        fsum: [f64; 3],
    ) -> JournalRow {
        JournalRow {
            index,
            trial,
            swept_value: target,
            target_normal_n: target,
            fx_n: f[0],
            fy_n: f[1],
            fz_n: f[2],
            settled: true,
            frames: format!("frames/{index:05}_0.png"),
            fsum_x_n: fsum[0],
            fsum_y_n: fsum[1],
            fsum_z_n: fsum[2],
            completed_at: "2026-11-22T00:00:00Z".into(),
            ..JournalRow::default()
        }
    }

    #[test]
    fn papers_sweep_with_known_gain_offset_and_spread() {
        // 0..750 gf by 50, 10 trials; F^sum = 0.95·F + 0.01 N ± 0.03 N (alternating
        // sign per trial, so each level's residual SD is 0.03·sqrt(10/9)).
        let mut rows = Vec::new();
        let mut i = 0;
        for t in 0..10 {
            for k in 0..16 {
                let f = gf_to_n(50.0 * k as f64);
                let e = if t % 2 == 0 { 0.03 } else { -0.03 };
                rows.push(row(i, t, f, [0.0, 0.0, f], [0.0, 0.0, 0.95 * f + 0.01 + e]));
                i += 1;
            }
        }
        let m = analyze(&rows).unwrap();
        let c = &m.calibration;
        assert!((c.fit.slope - 0.95).abs() < 1e-9, "{}", c.fit.slope);
        assert!((c.fit.offset - 0.01).abs() < 1e-9);
        let sd = 0.03 * (10.0f64 / 9.0).sqrt();
        assert!((c.pooled_sd - sd).abs() < 1e-9);
        assert!((c.resolution - 2.0 * sd / 0.95).abs() < 1e-9);
        assert_eq!(c.levels.len(), 16);
        assert!(c.linearity_pct < 1e-6);
        assert_eq!(c.hysteresis_pct, None, "the paper's sweep only loads");
        assert!(c.fit.r2 > 0.99 && c.fit.r2 < 1.0);
        assert_eq!(m.pairs.len(), 160);
    }
}
