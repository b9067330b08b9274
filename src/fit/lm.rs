//! The least-squares engine of `tactbench fit`: Levenberg–Marquardt over the free
//! parameters, the covariance of the result, and the expected intervals of a design.
//!
//! The engine works in scaled coordinates `θ_i = (v_i − v0_i)/s_i` (`s_i` =
//! [`ParamId::scale`]) so E in kPa and a depth in mm weigh alike. Every residual
//! arrives divided by its noise (the routes do it), so the cost is `χ² = Σ r²`.
//!
//! - **Jacobian**: forward differences with step `10⁻⁴` in θ (a part in 10⁴ of E,
//!   0.1 µm of a depth), the columns evaluated on every core.
//! - **Step**: `(JᵀJ + λ diag(JᵀJ)) δ = −Jᵀr` (Marquardt's scaling), λ ÷10 on a
//!   step that lowers χ², ×10 otherwise; a step into an invalid model (E ≤ 0, a
//!   depth below the surface or through a bonded layer) counts as a failed step.
//!   Stops when χ² falls by less than 10⁻¹⁰ of itself, or λ passes 10¹⁰.
//! - **Covariance** ("from the residuals and the Jacobian"; the largest kept per
//!   parameter; a third, two-way by setpoint and marker, in [`uncertainty_two_way`]): the classical `s² (JᵀJ)⁻¹` with `s² = χ²/(n − p)`, and the
//!   cluster-robust sandwich `(JᵀJ)⁻¹ (Σ_g J_gᵀ r_g r_gᵀ J_g) (JᵀJ)⁻¹ · G/(G−1)` with
//!   one cluster per setpoint, which stays honest when a setpoint's residuals are
//!   correlated (one contact mis-modelled moves every marker of that setpoint). The
//!   95 % interval is `±t σ` with Student's t at `min(n − p, G − 1)` degrees of freedom.
//! - **Expected intervals** of a design (`fit --predict`, and the identifiability
//!   check before a fit): `(JᵀJ)^{-1}` at the nominal parameters with the declared
//!   noise (`s = 1`): what the design can determine before anything is measured.

use std::collections::HashMap;

use nalgebra::{DMatrix, DVector};
use statrs::distribution::{ContinuousCDF, StudentsT};

use super::space::{check_valid, ParamId};
use super::{FitError, ModelParams, Residuals};
use crate::sensor::ModelKind;

/// Relative step of the forward differences, in scaled units.
const FD_STEP: f64 = 1e-4;

/// Several routes' residuals, end to end.
pub struct Stack<'a> {
    parts: Vec<&'a dyn Residuals>,
}

impl<'a> Stack<'a> {
    /// The stacked problem.
    pub fn new(parts: Vec<&'a dyn Residuals>) -> Self {
        Stack { parts }
    }
}

impl Residuals for Stack<'_> {
    fn len(&self) -> usize {
        self.parts.iter().map(|p| p.len()).sum()
    }

    fn eval(&self, p: &ModelParams, out: &mut [f64]) -> Result<(), String> {
        let mut at = 0;
        for part in &self.parts {
            let n = part.len();
            part.eval(p, &mut out[at..at + n])?;
            at += n;
        }
        Ok(())
    }

    fn groups(&self) -> Vec<usize> {
        self.parts.iter().flat_map(|p| p.groups()).collect()
    }

    fn marker_groups(&self) -> Vec<usize> {
        self.parts.iter().flat_map(|p| p.marker_groups()).collect()
    }
}

/// The parameters at scaled coordinates `theta` about `base`.
pub fn params_at(
    base: &ModelParams,
    free: &[ParamId],
    scales: &[f64],
    theta: &[f64],
) -> ModelParams {
    let mut p = base.clone();
    for ((id, s), t) in free.iter().zip(scales).zip(theta) {
        id.set(&mut p, id.get(base) + s * t);
    }
    p
}

/// Residuals at `p`, or why the model cannot be evaluated there.
fn residuals(
    problem: &dyn Residuals,
    p: &ModelParams,
    kind: ModelKind,
) -> Result<Vec<f64>, String> {
    check_valid(p, kind)?;
    let mut r = vec![0.0; problem.len()];
    problem.eval(p, &mut r)?;
    if r.iter().any(|v| !v.is_finite()) {
        return Err("a residual is not finite".into());
    }
    Ok(r)
}

/// The Jacobian `∂r/∂θ` (n × p, scaled units) at `p` by forward differences from the
/// residuals `r0` there, the columns shared among the cores.
pub fn jacobian(
    problem: &dyn Residuals,
    p: &ModelParams,
    free: &[ParamId],
    scales: &[f64],
    r0: &[f64],
    kind: ModelKind,
) -> Result<DMatrix<f64>, FitError> {
    let n = r0.len();
    let np = free.len();
    let column = |k: usize| -> Result<Vec<f64>, FitError> {
        // Step away from an invalid region: backwards when forwards is invalid.
        for sign in [1.0, -1.0] {
            let mut q = p.clone();
            let h = sign * FD_STEP;
            free[k].set(&mut q, free[k].get(p) + scales[k] * h);
            if let Ok(r) = residuals(problem, &q, kind) {
                return Ok(r.iter().zip(r0).map(|(a, b)| (a - b) / h).collect());
            }
        }
        Err(FitError::Numerical(format!(
            "the model cannot be evaluated on either side of {} = {}",
            free[k].name(&[]),
            free[k].get(p)
        )))
    };
    let threads = std::thread::available_parallelism()
        .map(|t| t.get())
        .unwrap_or(1)
        .clamp(1, np.max(1));
    let mut cols: Vec<Option<Result<Vec<f64>, FitError>>> = (0..np).map(|_| None).collect();
    std::thread::scope(|s| {
        let chunks: Vec<_> = cols
            .chunks_mut(np.div_ceil(threads).max(1))
            .enumerate()
            .map(|(ci, chunk)| {
                let column = &column;
                s.spawn(move || {
                    let start = ci * np.div_ceil(threads).max(1);
                    for (j, slot) in chunk.iter_mut().enumerate() {
                        *slot = Some(column(start + j));
                    }
                })
            })
            .collect();
        for h in chunks {
            let _ = h.join();
        }
    });
    let mut j = DMatrix::zeros(n, np);
    for (k, c) in cols.into_iter().enumerate() {
        let c =
            c.unwrap_or_else(|| Err(FitError::Numerical("a Jacobian worker stopped".into())))?;
        j.set_column(k, &DVector::from_vec(c));
    }
    Ok(j)
}

/// What [`levenberg_marquardt`] found.
#[derive(Debug, Clone)]
pub struct LmFit {
    /// The fitted parameters (the held ones at their start values).
    pub params: ModelParams,
    /// The free parameters, in column order.
    pub free: Vec<ParamId>,
    /// Sum of squared (noise-normalised) residuals at the fit.
    pub chi2: f64,
    /// Number of residuals.
    pub n: usize,
    /// Iterations taken.
    pub iterations: usize,
    /// Whether the relative change of χ² fell below the tolerance.
    pub converged: bool,
    /// Scaled Jacobian at the fit.
    pub jac: DMatrix<f64>,
    /// Residuals at the fit.
    pub resid: Vec<f64>,
}

/// Engine options.
#[derive(Debug, Clone, Copy)]
pub struct LmOptions {
    /// Largest number of iterations (Jacobians).
    pub max_iter: usize,
}

impl Default for LmOptions {
    fn default() -> Self {
        LmOptions { max_iter: 40 }
    }
}

/// Minimises `χ²(θ)` from `start` over `free` (module docs). `progress(iteration,
/// χ²)` is called after every accepted step.
pub fn levenberg_marquardt(
    problem: &dyn Residuals,
    start: &ModelParams,
    free: &[ParamId],
    kind: ModelKind,
    opts: LmOptions,
    progress: &mut dyn FnMut(usize, f64),
) -> Result<LmFit, FitError> {
    let scales: Vec<f64> = free.iter().map(|f| f.scale(start)).collect();
    let np = free.len();
    let mut theta = vec![0.0; np];
    let mut p = start.clone();
    let mut r = residuals(problem, &p, kind)
        .map_err(|e| FitError::Numerical(format!("at the starting parameters: {e}")))?;
    let mut chi2: f64 = r.iter().map(|v| v * v).sum();
    let mut lambda = 1e-3;
    let mut iterations = 0;
    let mut converged = np == 0;
    let mut jac = DMatrix::zeros(r.len(), np);
    while np > 0 && iterations < opts.max_iter {
        iterations += 1;
        jac = jacobian(problem, &p, free, &scales, &r, kind)?;
        let jt = jac.transpose();
        let a = &jt * &jac;
        let g = &jt * DVector::from_column_slice(&r);
        let mut accepted = false;
        while lambda < 1e10 {
            let mut m = a.clone();
            for i in 0..np {
                m[(i, i)] += lambda * a[(i, i)].max(1e-12);
            }
            let Some(chol) = m.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let delta = chol.solve(&(-&g));
            let trial: Vec<f64> = theta.iter().zip(delta.iter()).map(|(t, d)| t + d).collect();
            let q = params_at(start, free, &scales, &trial);
            match residuals(problem, &q, kind) {
                Ok(rq) => {
                    let c: f64 = rq.iter().map(|v| v * v).sum();
                    if c < chi2 {
                        let drop = (chi2 - c) / chi2.max(f64::MIN_POSITIVE);
                        theta = trial;
                        p = q;
                        r = rq;
                        chi2 = c;
                        lambda = (lambda / 10.0).max(1e-12);
                        accepted = true;
                        progress(iterations, chi2);
                        if drop < 1e-10 {
                            converged = true;
                        }
                        break;
                    }
                    lambda *= 10.0;
                }
                Err(_) => lambda *= 10.0,
            }
        }
        if !accepted {
            // No step lowers χ²: at a minimum to working precision.
            converged = true;
            break;
        }
        if converged {
            break;
        }
    }
    if np > 0 {
        jac = jacobian(problem, &p, free, &scales, &r, kind)?;
    }
    Ok(LmFit {
        params: p,
        free: free.to_vec(),
        chi2,
        n: r.len(),
        iterations,
        converged,
        jac,
        resid: r,
    })
}

/// Inverse of a symmetric positive semi-definite matrix through its eigenvalues;
/// directions with eigenvalue below `1e-13 × largest` get infinite variance (the
/// parameters loading on them are not determined).
fn spd_inverse(a: &DMatrix<f64>) -> DMatrix<f64> {
    let n = a.nrows();
    if n == 0 {
        // No free parameter (all held): nalgebra's eigen decomposition panics on 0×0.
        return DMatrix::zeros(0, 0);
    }
    let eig = a.clone().symmetric_eigen();
    let top = eig.eigenvalues.iter().cloned().fold(0.0, f64::max);
    let mut inv = DMatrix::zeros(n, n);
    for k in 0..n {
        let l = eig.eigenvalues[k];
        let v = eig.eigenvectors.column(k);
        if l > 1e-13 * top && l > 0.0 {
            inv += (v * v.transpose()) / l;
        } else {
            for i in 0..n {
                if v[i].abs() > 1e-6 {
                    inv[(i, i)] = f64::INFINITY;
                }
            }
        }
    }
    inv
}

/// Standard deviations (scaled units) a design is expected to give with the
/// declared noise: `sqrt(diag (JᵀJ)⁻¹)`; infinite where undetermined.
pub fn expected_sd(jac: &DMatrix<f64>) -> Vec<f64> {
    let inv = spd_inverse(&(jac.transpose() * jac));
    (0..inv.nrows()).map(|i| inv[(i, i)].sqrt()).collect()
}

/// The uncertainty of a fit.
#[derive(Debug, Clone)]
pub struct Uncertainty {
    /// Standard deviation per free parameter, in the parameter's unit.
    pub sd: Vec<f64>,
    /// 95 % half-width per free parameter (`t × sd`).
    pub half_width: Vec<f64>,
    /// Correlation matrix of the free parameters.
    pub correlation: Vec<Vec<f64>>,
    /// Student's t used.
    pub t: f64,
    /// Degrees of freedom of t.
    pub dof: usize,
    /// `χ²/(n − p)`.
    pub reduced_chi2: f64,
    /// Number of clusters (setpoints).
    pub clusters: usize,
    /// How the intervals were made (for `fit.json` `ci_method`).
    pub method: String,
}

/// The covariance of a fit (module docs), with the clusters of
/// [`Residuals::groups`].
pub fn uncertainty(fit: &LmFit, groups: &[usize], start: &ModelParams) -> Uncertainty {
    uncertainty_with(fit, groups, start, None)
}

/// [`uncertainty`] with a known extra source of error on the data: `extra_meat` =
/// `Σ Jᵀ g gᵀ J σ²` over independent error sources `g` (scaled units), added to the
/// classical covariance as `(JᵀJ)⁻¹ M (JᵀJ)⁻¹` before the larger of it and the
/// cluster-robust one is kept.
pub fn uncertainty_with(
    fit: &LmFit,
    groups: &[usize],
    start: &ModelParams,
    extra_meat: Option<&DMatrix<f64>>,
) -> Uncertainty {
    uncertainty_two_way(fit, groups, None, start, extra_meat)
}

/// [`uncertainty_with`] clustered two ways (Cameron, Gelbach & Miller 2011): by
/// setpoint (`groups`) and by a second key (`groups2`, the marker: a marker's
/// centroid bias, or the contact model's error at its place, repeats at every
/// setpoint). The two-way variance `V_1 + V_2 − V_each-residual` joins the larger-of.
pub fn uncertainty_two_way(
    fit: &LmFit,
    groups: &[usize],
    groups2: Option<&[usize]>,
    start: &ModelParams,
    extra_meat: Option<&DMatrix<f64>>,
) -> Uncertainty {
    let np = fit.free.len();
    let scales: Vec<f64> = fit.free.iter().map(|f| f.scale(start)).collect();
    let dof_res = fit.n.saturating_sub(np).max(1);
    let s2 = fit.chi2 / dof_res as f64;
    let ainv = spd_inverse(&(fit.jac.transpose() * &fit.jac));
    // Cluster scores: Σ over each setpoint's residuals of J_i r_i.
    let mut scores: HashMap<usize, DVector<f64>> = HashMap::new();
    let mut singles = Vec::new();
    for (i, g) in groups.iter().enumerate().take(fit.n) {
        let row = fit.jac.row(i).transpose() * fit.resid[i];
        if *g == usize::MAX {
            singles.push(row);
        } else {
            *scores.entry(*g).or_insert_with(|| DVector::zeros(np)) += row;
        }
    }
    let g_count = scores.len() + singles.len();
    let mut meat = DMatrix::zeros(np, np);
    for s in scores.values().chain(singles.iter()) {
        meat += s * s.transpose();
    }
    let finite = |m: &DMatrix<f64>| m.iter().all(|v| v.is_finite());
    let robust = if g_count >= 2 && finite(&ainv) {
        Some(&ainv * &meat * &ainv * (g_count as f64 / (g_count as f64 - 1.0)))
    } else {
        None
    };
    let two_way = match groups2 {
        Some(g2) if finite(&ainv) => {
            let mut by: HashMap<usize, DVector<f64>> = HashMap::new();
            let mut each = DMatrix::zeros(np, np);
            let mut m2 = DMatrix::zeros(np, np);
            for (i, g) in g2.iter().enumerate().take(fit.n) {
                let row = fit.jac.row(i).transpose() * fit.resid[i];
                each += &row * row.transpose();
                if *g == usize::MAX {
                    m2 += &row * row.transpose();
                } else {
                    *by.entry(*g).or_insert_with(|| DVector::zeros(np)) += row;
                }
            }
            for v in by.values() {
                m2 += v * v.transpose();
            }
            Some(&ainv * (&meat + m2 - each) * &ainv)
        }
        _ => None,
    };
    let mut classic = &ainv * s2;
    if let (Some(m), true) = (extra_meat, finite(&ainv)) {
        classic += &ainv * m * &ainv;
    }
    let mut sd = Vec::with_capacity(np);
    for i in 0..np {
        let c = classic[(i, i)];
        let r = robust.as_ref().map_or(0.0, |m| m[(i, i)]);
        let w = two_way.as_ref().map_or(0.0, |m| m[(i, i)]);
        sd.push(c.max(r).max(w).sqrt() * scales[i]);
    }
    let dof = dof_res.min(g_count.saturating_sub(1).max(1));
    let t = StudentsT::new(0.0, 1.0, dof as f64)
        .map(|d| d.inverse_cdf(0.975))
        .unwrap_or(1.96);
    let correlation = (0..np)
        .map(|i| {
            (0..np)
                .map(|j| {
                    let d = (classic[(i, i)] * classic[(j, j)]).sqrt();
                    if d.is_finite() && d > 0.0 {
                        classic[(i, j)] / d
                    } else if i == j {
                        1.0
                    } else {
                        0.0
                    }
                })
                .collect()
        })
        .collect();
    Uncertainty {
        half_width: sd.iter().map(|s| t * s).collect(),
        sd,
        correlation,
        t,
        dof,
        reduced_chi2: s2,
        clusters: g_count,
        method: format!(
            "jacobian: the largest of s^2 (J^T J)^-1 (s^2 = chi^2/(n-p) = {s2:.3}), the cluster-robust sandwich over {g_count} setpoints{}, per parameter; 95 % = +/- t({dof}) sd", if two_way.is_some() { " and the two-way one (setpoints and markers)" } else { "" }
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sensor::paper_sensor;

    /// `r_i = (E·x_i + z·1 − y_i)/σ`: linear least squares in (E, contact z), whose
    /// solution and covariance are closed forms.
    struct Line {
        x: Vec<f64>,
        y: Vec<f64>,
        sigma: f64,
    }

    impl Residuals for Line {
        fn len(&self) -> usize {
            self.x.len()
        }
        fn eval(&self, p: &ModelParams, out: &mut [f64]) -> Result<(), String> {
            for ((o, x), y) in out.iter_mut().zip(&self.x).zip(&self.y) {
                *o = (p.young_modulus_kpa * x + p.contact_z_mm - y) / self.sigma;
            }
            Ok(())
        }
    }

    fn line(noise: &[f64]) -> Line {
        let x: Vec<f64> = (0..noise.len()).map(|i| i as f64 / 10.0).collect();
        let y = x
            .iter()
            .zip(noise)
            .map(|(x, e)| 700.0 * x + 2.0 + e)
            .collect();
        Line { x, y, sigma: 1.0 }
    }

    #[test]
    fn a_linear_problem_gives_the_normal_equations_solution_and_its_covariance() {
        // Deterministic "noise" with zero mean over the points.
        let noise: Vec<f64> = (0..40)
            .map(|i| ((i * 7919) % 13) as f64 / 6.0 - 1.0)
            .collect();
        let prob = line(&noise);
        let start = ModelParams::nominal(&paper_sensor(), 0.0);
        let free = [ParamId::YoungModulus, ParamId::ContactZ];
        let fit = levenberg_marquardt(
            &prob,
            &start,
            &free,
            ModelKind::HalfSpace,
            LmOptions::default(),
            &mut |_, _| {},
        )
        .unwrap();
        // Closed form: ordinary least squares of y on (x, 1).
        let n = prob.x.len() as f64;
        let (sx, sy) = (prob.x.iter().sum::<f64>(), prob.y.iter().sum::<f64>());
        let sxx: f64 = prob.x.iter().map(|x| x * x).sum();
        let sxy: f64 = prob.x.iter().zip(&prob.y).map(|(x, y)| x * y).sum();
        let slope = (n * sxy - sx * sy) / (n * sxx - sx * sx);
        let icpt = (sy - slope * sx) / n;
        assert!(
            (fit.params.young_modulus_kpa - slope).abs() < 1e-6 * slope,
            "{}",
            fit.params.young_modulus_kpa
        );
        assert!(
            (fit.params.contact_z_mm - icpt).abs() < 1e-6,
            "{}",
            fit.params.contact_z_mm
        );
        let u = uncertainty(&fit, &vec![usize::MAX; prob.len()], &start);
        let s2 = fit.chi2 / (n - 2.0);
        let sd_slope = (s2 * n / (n * sxx - sx * sx)).sqrt();
        // The classical variance is one of the two the engine keeps the larger of.
        assert!(u.sd[0] >= sd_slope * (1.0 - 1e-4), "{} {sd_slope}", u.sd[0]);
        assert!(u.sd[0] < 3.0 * sd_slope, "{} {sd_slope}", u.sd[0]);
        assert!(
            u.correlation[0][1] < -0.5,
            "slope and intercept anti-correlate: {:?}",
            u.correlation
        );
    }

    #[test]
    fn a_fit_with_every_parameter_held_gives_an_empty_uncertainty_without_panicking() {
        let prob = line(&[0.1, -0.2, 0.3]);
        let start = ModelParams::nominal(&paper_sensor(), 0.0);
        let fit = levenberg_marquardt(
            &prob,
            &start,
            &[],
            ModelKind::HalfSpace,
            LmOptions::default(),
            &mut |_, _| {},
        )
        .unwrap();
        let u = uncertainty(&fit, &vec![usize::MAX; prob.len()], &start);
        assert!(u.sd.is_empty() && u.correlation.is_empty());
        assert!(expected_sd(&DMatrix::zeros(3, 0)).is_empty());
    }

    #[test]
    fn a_parameter_the_residuals_do_not_depend_on_has_infinite_expected_sd() {
        let prob = line(&[0.1, -0.2, 0.3, 0.0, -0.1]);
        let start = ModelParams::nominal(&paper_sensor(), 0.0);
        let free = [ParamId::YoungModulus, ParamId::FtRotation];
        let scales: Vec<f64> = free.iter().map(|f| f.scale(&start)).collect();
        let r0 = residuals(&prob, &start, ModelKind::HalfSpace).unwrap();
        let j = jacobian(&prob, &start, &free, &scales, &r0, ModelKind::HalfSpace).unwrap();
        let sd = expected_sd(&j);
        assert!(sd[0].is_finite() && sd[1].is_infinite(), "{sd:?}");
    }
}
