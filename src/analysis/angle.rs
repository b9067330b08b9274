//! Force direction (paper Fig. 8): the angle of the force from the surface normal,
//! measured from the reconstructed sums, `θ_meas = atan2(√(F_x^sum² + F_y^sum²),
//! F_z^sum)`, against the applied angle from the F/T wrench,
//! `θ_app = atan2(√(f_x² + f_y²), f_z)` (journal `fx_n, fy_n, fz_n`, assumed in the
//! sensor frame with f_z > 0 pressing), levels keyed by the plan's target angle
//! (journal `swept_value`, degrees).
//!
//! Error `e = θ_meas − θ_app`: **bias** = mean(e), **SD** = sample SD(e) over all
//! samples. **Resolution**, slope, R² and linearity follow [`super::calibration`]
//! (resolution = 2·pooled within-level residual SD / |slope|, degrees). The bias
//! against the plan's target angle is reported too, since the applied angle depends on
//! the F/T sensor's alignment.

use super::calibration::{self, Calibration, CalibrationError};
use super::magnitude::samples;
use super::stats;
use crate::bench::journal::JournalRow;

/// One measurement, degrees from the normal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AnglePair {
    /// Setpoint index.
    pub index: usize,
    /// Target angle, degrees.
    pub target_deg: f64,
    /// Applied angle from the F/T wrench, degrees.
    pub applied_deg: f64,
    /// Measured angle from F^sum, degrees.
    pub measured_deg: f64,
}

/// The angle analysis of a run.
#[derive(Debug, Clone, PartialEq)]
pub struct AngleAnalysis {
    /// Fit and figures of merit, degrees.
    pub calibration: Calibration,
    /// Mean of measured − applied, degrees.
    pub bias_deg: f64,
    /// Sample SD of measured − applied, degrees.
    pub sd_deg: f64,
    /// Mean of measured − target, degrees.
    pub bias_vs_target_deg: f64,
    /// Every measurement in journal order.
    pub pairs: Vec<AnglePair>,
}

/// Angle of a force from the +z normal, degrees in [0, 180].
pub fn angle_from_normal_deg(f: [f64; 3]) -> f64 {
    f[0].hypot(f[1]).atan2(f[2]).to_degrees()
}

/// Analyses the journal rows of an angle sweep.
pub fn analyze(rows: &[JournalRow]) -> Result<AngleAnalysis, CalibrationError> {
    let pairs: Vec<AnglePair> = rows
        .iter()
        .map(|r| AnglePair {
            index: r.index,
            target_deg: r.swept_value,
            applied_deg: angle_from_normal_deg([r.fx_n, r.fy_n, r.fz_n]),
            measured_deg: angle_from_normal_deg([r.fsum_x_n, r.fsum_y_n, r.fsum_z_n]),
        })
        .collect();
    let s = samples(rows, |r| {
        (
            r.swept_value,
            angle_from_normal_deg([r.fx_n, r.fy_n, r.fz_n]),
            angle_from_normal_deg([r.fsum_x_n, r.fsum_y_n, r.fsum_z_n]),
        )
    });
    let calibration = calibration::calibrate(&s)?;
    let e: Vec<f64> = pairs
        .iter()
        .map(|p| p.measured_deg - p.applied_deg)
        .collect();
    let et: Vec<f64> = pairs
        .iter()
        .map(|p| p.measured_deg - p.target_deg)
        .collect();
    Ok(AngleAnalysis {
        calibration,
        bias_deg: stats::mean(&e).unwrap_or(f64::NAN),
        sd_deg: stats::sample_sd(&e).unwrap_or(0.0),
        bias_vs_target_deg: stats::mean(&et).unwrap_or(f64::NAN),
        pairs,
    })
}

#[cfg(test)]
mod tests {
    use super::super::magnitude::tests::row;
    use super::*;

    #[test]
    fn angles_follow_the_force_components() {
        assert!((angle_from_normal_deg([1.0, 0.0, 1.0]) - 45.0).abs() < 1e-12);
        assert!((angle_from_normal_deg([0.0, -3.0, 3.0f64.sqrt() * 3.0]) - 30.0).abs() < 1e-12);
        assert!(angle_from_normal_deg([0.0, 0.0, 2.0]).abs() < 1e-12);
    }

    #[test]
    fn papers_sweep_with_a_known_angle_bias_and_spread() {
        // 400 gf at 0..45° by 5°, 4 trials, tangential part along +y. The reconstructed
        // force is rotated by +1° ± 0.5° (alternating by trial) further from the
        // normal: bias 1°, per-level SD 0.5·sqrt(4/3)°, slope 1.
        let f = crate::units::gf_to_n(400.0);
        let mut rows = Vec::new();
        let mut i = 0;
        for t in 0..4 {
            for k in 0..10 {
                let a = 5.0 * k as f64;
                let m = a + 1.0 + if t % 2 == 0 { 0.5 } else { -0.5 };
                let (ar, mr) = (a.to_radians(), m.to_radians());
                let mut r = row(
                    i,
                    t,
                    f * ar.cos(),
                    [0.0, f * ar.sin(), f * ar.cos()],
                    [0.0, 0.9 * f * mr.sin(), 0.9 * f * mr.cos()],
                );
                r.swept_value = a;
                rows.push(r);
                i += 1;
            }
        }
        let an = analyze(&rows).unwrap();
        assert!((an.bias_deg - 1.0).abs() < 1e-9, "{}", an.bias_deg);
        assert!((an.bias_vs_target_deg - 1.0).abs() < 1e-9);
        // 40 alternating ±0.5 errors: sample SD = 0.5·sqrt(40/39).
        assert!((an.sd_deg - 0.5 * (40.0f64 / 39.0).sqrt()).abs() < 1e-9);
        let c = &an.calibration;
        assert!((c.fit.slope - 1.0).abs() < 1e-9);
        let sd = 0.5 * (4.0f64 / 3.0).sqrt();
        assert!((c.resolution - 2.0 * sd).abs() < 1e-9, "{}", c.resolution);
        assert_eq!(c.levels.len(), 10);
    }
}
