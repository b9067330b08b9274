//! The F/T reading's own error in a fit's intervals.
//!
//! Both routes are driven by (the displacement route) or compared with (the
//! indentation route) the F/T reading of each setpoint, so an error δF of that reading
//! moves the setpoint's residuals by `g δF` (`g` = [`DisplacementRoute::force_sensitivity`]
//! for the displacements, `−1/σ` for the indentation row's `F_z`). Two parts:
//!
//! - **random**, per setpoint and axis: the journal's sample SD over √samples;
//! - **shared** by every setpoint of one target ([`ForceError::share`]): readings on a
//!   lattice of step `r` ([`force_resolution_n`]; a DynPick counts 1/32.8 N) are off by
//!   up to `r/2`, and when the noise is below a count every sample rounds alike, so
//!   setpoints with the same target read the same offset. σ = the largest of `r/√12`,
//!   one sample's σ (the median non-zero sample SD: the tare is one sample) and the
//!   F/T scatter about the contact law (the indentation route's noise), per
//!   target and axis, the sensitivities of the target's setpoints summed first
//!   (coherent); and the same σ once more as an offset common to every setpoint (a
//!   tare that missed its zero moves every reading alike).
//!
//! The tracker's displacement gain is added the same way: a tracked displacement is
//! `(1 + g)` times the true one, `g` common to a layer's markers at every setpoint
//! (a centroid's systematic error under a moving blob: no clustering sees it), with
//! σ = [`TRACKING_GAIN_SD`] per layer and `∂r/∂g = −u_pred/σ_px`
//! ([`DisplacementRoute::gain_sensitivity`]).
//!
//! Each part adds `(JᵀJ)⁻¹ (Σ Jᵀg gᵀJ σ²) (JᵀJ)⁻¹` to the classical covariance
//! ([`crate::fit::lm::uncertainty_with`]).

use std::collections::HashMap;

use nalgebra::{DMatrix, DVector};

use super::displacement::{DisplacementRoute, TRACKING_GAIN_SD};
use super::indentation::IndentationRoute;
use super::lm::{uncertainty_two_way, LmFit, Uncertainty};
use super::{FitError, ModelParams};
use crate::analysis::RunData;

/// The F/T sensor's resolution as the journal shows it. A reading that is the mean of
/// `n` samples on a lattice of step `r` is `Σk·r / n`, so `n × reading` lies on the
/// lattice whatever the noise: `lattice_values` are those products (every reading,
/// not only the ones whose samples all rounded alike: readings at round loads, 1, 2 and
/// 3 N on a DynPick, are all multiples of 33 counts, and their largest common step is
/// 1 N). The result is the largest step every distinct non-zero value is a multiple
/// of, tried among the differences between neighbouring values and their halves,
/// thirds and quarters; `None` with fewer than 3 distinct values, no common step (a
/// sensor reporting floating-point values: Net F/T, Bota), or a step coarser than a
/// twentieth of `largest_reading_n` (no sensor is used at a handful of counts; such a
/// "step" is a common factor of the loads).
pub fn force_resolution_n(lattice_values: &[f64], largest_reading_n: f64) -> Option<f64> {
    let mut v: Vec<f64> = lattice_values
        .iter()
        .filter(|f| f.is_finite() && f.abs() > 1e-12)
        .map(|f| f.abs())
        .collect();
    v.sort_by(f64::total_cmp);
    v.dedup_by(|a, b| (*a - *b).abs() <= 1e-9 * b.abs().max(1e-9));
    if v.len() < 3 {
        return None;
    }
    let mut steps: Vec<f64> = v
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|d| *d > 1e-9)
        .flat_map(|d| (1..=4).map(move |k| d / k as f64))
        .collect();
    steps.sort_by(|a, b| b.total_cmp(a));
    steps
        .into_iter()
        .find(|step| {
            v.iter()
                .all(|x| ((*x / step) - (*x / step).round()).abs() < 1e-3)
        })
        .filter(|step| *step <= largest_reading_n.abs() / 20.0)
}

/// The F/T error model of a run.
#[derive(Debug, Clone)]
pub struct ForceError {
    /// Random σ per setpoint index and axis, N.
    random: HashMap<usize, [f64; 3]>,
    /// Target of each setpoint index (normal, tx, ty as bits), for the shared part.
    target: HashMap<usize, [u64; 3]>,
    /// Lattice step, N.
    pub resolution_n: Option<f64>,
    /// One F/T sample's σ: the median of the journal's non-zero sample SDs, N.
    pub sample_sd_n: Option<f64>,
    /// σ of the error shared by the setpoints of one target, N (see
    /// [`ForceError::share`]).
    pub shared_n: Option<f64>,
}

impl ForceError {
    /// The declared F/T noise of a plan (for `fit --predict`): every loaded setpoint's
    /// mean off by `random_n` on its own, and `shared_n` shared by the setpoints of one
    /// target and by all (a tare of one sample).
    pub fn declared(
        setpoints: &[crate::bench::plan::Setpoint],
        random_n: f64,
        shared_n: f64,
    ) -> ForceError {
        ForceError {
            random: setpoints.iter().map(|s| (s.index, [random_n; 3])).collect(),
            target: setpoints
                .iter()
                .map(|s| {
                    (
                        s.index,
                        [s.normal_n, s.tangential_n[0], s.tangential_n[1]].map(f64::to_bits),
                    )
                })
                .collect(),
            resolution_n: None,
            sample_sd_n: Some(shared_n),
            shared_n: Some(shared_n),
        }
    }

    /// From the run's journal.
    pub fn of_run(run: &RunData) -> ForceError {
        let samples = run.plan.samples.max(1) as f64;
        let readings = || {
            run.rows
                .iter()
                .flat_map(|r| [r.fx_n, r.fy_n, r.fz_n])
                .filter(|f| f.is_finite())
        };
        let lattice: Vec<f64> = readings().map(|f| f * samples).collect();
        let largest = readings().fold(0.0f64, |m, f| m.max(f.abs()));
        let n = (run.plan.samples.max(1) as f64).sqrt();
        ForceError {
            random: run
                .rows
                .iter()
                .map(|r| {
                    let s = [r.fx_sd_n, r.fy_sd_n, r.fz_sd_n].map(|v| {
                        if v.is_finite() {
                            v.abs() / n
                        } else {
                            0.0
                        }
                    });
                    (r.index, s)
                })
                .collect(),
            target: run
                .rows
                .iter()
                .map(|r| {
                    (
                        r.index,
                        [r.target_normal_n, r.target_tx_n, r.target_ty_n].map(f64::to_bits),
                    )
                })
                .collect(),
            resolution_n: force_resolution_n(&lattice, largest),
            sample_sd_n: median_nonzero(
                run.rows
                    .iter()
                    .flat_map(|r| [r.fx_sd_n, r.fy_sd_n, r.fz_sd_n])
                    .filter(|v| v.is_finite() && *v > 0.0)
                    .collect(),
            ),
            shared_n: None,
        }
        .share(None)
    }

    /// Sets the σ shared by the setpoints of one target and by all: the largest of
    /// the resolution's `r/√12`, one sample's σ (the tare is taken from one sample)
    /// and the F/T's scatter about the contact law (the indentation route's noise,
    /// when there is one): what a tare, a count's rounding or the control loop's
    /// stopping point leave alike at equal loads does not average out over setpoints.
    pub fn share(mut self, indentation_noise_n: Option<f64>) -> ForceError {
        let q = self.resolution_n.map(|r| r / 12f64.sqrt());
        self.shared_n = [q, self.sample_sd_n, indentation_noise_n]
            .into_iter()
            .flatten()
            .reduce(f64::max);
        self
    }

    /// The covariance of `fit` with the F/T error added (module docs). The fit's
    /// residuals are the displacement route's, then (when `ind` is given) the
    /// indentation route's.
    pub fn uncertainty(
        &self,
        fit: &LmFit,
        groups: &[usize],
        groups2: Option<&[usize]>,
        start: &ModelParams,
        disp: Option<&DisplacementRoute>,
        ind: Option<&IndentationRoute>,
    ) -> Result<Uncertainty, FitError> {
        let np = fit.jac.ncols();
        // Σ over each setpoint's residuals of J_i g_i, per axis.
        let mut per_sp: HashMap<usize, [DVector<f64>; 3]> = HashMap::new();
        let zero = || [DVector::zeros(np), DVector::zeros(np), DVector::zeros(np)];
        let mut at = 0;
        if let Some(d) = disp {
            let g = d
                .force_sensitivity(&fit.params)
                .map_err(FitError::Numerical)?;
            for sp in d.setpoints() {
                let n = 2 * sp.markers.len();
                let e = per_sp.entry(sp.index).or_insert_with(zero);
                for (a, ga) in g.iter().enumerate() {
                    for (i, gi) in ga.iter().enumerate().skip(at).take(n) {
                        e[a] += fit.jac.row(i).transpose() * *gi;
                    }
                }
                at += n;
            }
        }
        if let Some(r) = ind {
            for row in r.rows() {
                let e = per_sp.entry(row.index).or_insert_with(zero);
                e[2] -= fit.jac.row(at).transpose() / r.noise_n();
                at += 1;
            }
        }
        let mut meat = DMatrix::zeros(np, np);
        let mut shared: HashMap<[u64; 3], [DVector<f64>; 3]> = HashMap::new();
        for (index, v) in &per_sp {
            let s = self.random.get(index).copied().unwrap_or([0.0; 3]);
            for a in 0..3 {
                meat += &v[a] * v[a].transpose() * (s[a] * s[a]);
            }
            if self.shared_n.is_some() {
                let key = self
                    .target
                    .get(index)
                    .copied()
                    .unwrap_or([*index as u64; 3]);
                let e = shared.entry(key).or_insert_with(zero);
                for a in 0..3 {
                    e[a] += &v[a];
                }
            }
        }
        if let Some(q) = self.shared_n {
            for v in shared.values() {
                for va in v {
                    meat += va * va.transpose() * (q * q);
                }
            }
            // And an offset common to every setpoint (a tare that missed its zero).
            for a in 0..3 {
                let mut all = DVector::zeros(np);
                for v in per_sp.values() {
                    all += &v[a];
                }
                meat += &all * all.transpose() * (q * q);
            }
        }
        if let Some(d) = disp {
            let sg = TRACKING_GAIN_SD;
            let g = d
                .gain_sensitivity(&fit.params)
                .map_err(FitError::Numerical)?;
            let nl = g.iter().map(|(l, _)| l + 1).max().unwrap_or(0);
            let mut per_layer = vec![DVector::zeros(np); nl];
            for (i, (l, gi)) in g.iter().enumerate() {
                per_layer[*l] += fit.jac.row(i).transpose() * *gi;
            }
            for v in &per_layer {
                meat += v * v.transpose() * (sg * sg);
            }
        }
        let mut u = uncertainty_two_way(fit, groups, groups2, start, Some(&meat));
        u.method.push_str(&match self.shared_n {
            Some(q) => format!("; the F/T reading's error added: sample SD / sqrt(samples) per setpoint, and {q:.4} N shared by the setpoints of one target and again by all (the largest of the resolution / sqrt(12), one sample's SD and the F/T scatter about the contact law)"),
            None => "; the F/T reading's error added: sample SD / sqrt(samples) per setpoint".into(),
        });
        if disp.is_some() {
            u.method.push_str(&format!(
                "; the tracker's displacement gain added: {:.1} % per layer",
                100.0 * TRACKING_GAIN_SD
            ));
        }
        Ok(u)
    }
}

fn median_nonzero(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    Some(v[v.len() / 2])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dynpick_counts_show_their_resolution_and_readings_off_any_lattice_show_none() {
        let lsb = 1.0 / 32.8;
        let f: Vec<f64> = [16, 33, 66, 98, 0, 20]
            .iter()
            .map(|c| *c as f64 * lsb)
            .collect();
        let r = force_resolution_n(&f, 3.0).unwrap();
        assert!((r - lsb).abs() < 1e-9, "{r}");
        let noisy = [0.4987, 1.0031, 2.0113, 2.9977, 0.5021];
        assert_eq!(force_resolution_n(&noisy, 3.0), None);
    }

    /// Regression (a seed of the coverage study): the readings whose samples all
    /// rounded alike were at 1, 2 and 3 N, 33, 66 and 99 counts, so the resolution
    /// came out as 33 counts (1.006 N) and every interval ±20×. The means of 20
    /// samples carry the lattice too (20 × mean is a whole number of counts).
    #[test]
    fn readings_at_round_loads_do_not_make_a_one_newton_resolution() {
        let lsb = 1.0 / 32.8;
        let exact_only: Vec<f64> = [33, 66, 99, 33, 66]
            .iter()
            .map(|c| *c as f64 * lsb)
            .collect();
        assert_eq!(force_resolution_n(&exact_only, 99.0 * lsb), None);
        // Means of 20 samples (sums of counts / 20), times 20: the lattice again.
        let sums = [331, 338, 661, 659, 987, 994, 164, 170, 20 * 33];
        let lattice: Vec<f64> = sums.iter().map(|s| *s as f64 * lsb).collect();
        let r = force_resolution_n(&lattice, 994.0 / 20.0 * lsb).unwrap();
        assert!((r - lsb).abs() < 1e-9, "{r}");
    }
}
