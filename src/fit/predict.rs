//! `tactbench fit --plan PLAN --sensor S.toml --predict`: the 95 % interval each
//! parameter can expect from a plan, before anything moves.
//!
//! The plan's loaded setpoints on the nominal sensor ([`DisplacementRoute::from_plan`],
//! every grid marker, the setpoint's target wrench; [`IndentationRoute::from_plan`],
//! the depth the nominal law needs for each target normal force), the declared noise
//! (tracking σ per frame / √frames; F/T σ per sample / √samples), and the Jacobian at
//! the nominal values: `1.96 × sqrt(diag (JᵀJ)⁻¹)`, with the F/T error added as the fit
//! adds it ([`ForceError`]: the mean's σ per setpoint, one sample's σ shared by the
//! setpoints of one target and by all). Model error (a fit's χ²/(n − p) above 1) is
//! not in a prediction: obtained intervals are wider by about its square root. The same identifiability rule as
//! the fit holds parameters the plan cannot determine. Beside the intervals: the
//! plan's setpoint count and its estimated bench time (`Plan::estimate_duration_s`),
//! so what calibration accuracy costs in bench time is on one screen.

use serde_json::json;

use super::displacement::DisplacementRoute;
use super::force_error::ForceError;
use super::indentation::IndentationRoute;
use super::lm::{expected_sd, jacobian, LmFit, Stack};
use super::space::{default_params, parse_list, ParamId};
use super::{FitError, ModelParams, Residuals};
use crate::bench::plan::Plan;
use crate::sensor::Sensor;

/// The declared noise of the bench.
#[derive(Debug, Clone, Copy)]
pub struct DeclaredNoise {
    /// Tracking noise of one frame, px.
    pub tracking_px: f64,
    /// F/T noise of one sample, N.
    pub ft_n: f64,
}

/// One parameter's expected interval.
#[derive(Debug, Clone)]
pub struct Expected {
    /// Name.
    pub name: String,
    /// Unit.
    pub unit: &'static str,
    /// Nominal value.
    pub nominal: f64,
    /// Expected 95 % half-width (infinite: undetermined).
    pub half_width: f64,
    /// Whether the plan determines it.
    pub identifiable: bool,
    /// What would determine it, when it is not.
    pub needs: Option<&'static str>,
}

/// The prediction for a plan.
#[derive(Debug, Clone)]
pub struct Prediction {
    /// Per parameter.
    pub params: Vec<Expected>,
    /// Loaded setpoints used.
    pub setpoints: usize,
    /// All setpoints of the plan.
    pub plan_setpoints: usize,
    /// Estimated bench time, s.
    pub bench_time_s: f64,
    /// Why there is no indentation route (None: there is one).
    pub no_indentation: Option<String>,
    /// The noise used (per mean): tracking px, F/T N.
    pub noise_of_mean: (f64, f64),
}

impl Prediction {
    /// As JSON (`fit --predict --json`).
    pub fn to_json(&self) -> serde_json::Value {
        json!({
            "setpoints": self.setpoints, "plan_setpoints": self.plan_setpoints,
            "bench_time_s": self.bench_time_s,
            "indentation_route": self.no_indentation.as_ref().map_or(json!(true), |w| json!(w)),
            "noise_of_mean": {"tracking_px": self.noise_of_mean.0, "ft_n": self.noise_of_mean.1},
            "parameters": self.params.iter().map(|p| (p.name.clone(), json!({
                "nominal": p.nominal, "unit": p.unit,
                "ci95_half_width": if p.half_width.is_finite() { json!(p.half_width) } else { serde_json::Value::Null },
                "identifiable": p.identifiable, "needs": p.needs}))).collect::<serde_json::Map<_, _>>(),
        })
    }
}

/// Predicts the intervals of a plan on the nominal sensor (module docs).
pub fn predict(
    plan: &Plan,
    sensor: &Sensor,
    noise: DeclaredNoise,
    params: Option<&str>,
) -> Result<Prediction, FitError> {
    let bad = |m: String| FitError::Input {
        path: plan.path.clone(),
        message: m,
    };
    if !(noise.tracking_px.is_finite() && noise.tracking_px > 0.0) {
        return Err(bad(format!(
            "tracking noise {} px must be > 0",
            noise.tracking_px
        )));
    }
    if !(noise.ft_n.is_finite() && noise.ft_n > 0.0) {
        return Err(bad(format!("F/T noise {} N must be > 0", noise.ft_n)));
    }
    let track = noise.tracking_px / (plan.frames.max(1) as f64).sqrt();
    let ft = noise.ft_n / (plan.samples.max(1) as f64).sqrt();
    let disp = DisplacementRoute::from_plan(plan, sensor, track)?;
    let (ind, no_ind) = match IndentationRoute::from_plan(plan, sensor, ft) {
        Ok(r) => (Some(r), None),
        Err(w) => (None, Some(w)),
    };
    let mut free = match params {
        Some(l) => parse_list(l, sensor)?,
        None => default_params(sensor, ind.is_some(), true),
    };
    if ind.is_none() {
        free.retain(|p| *p != ParamId::ContactZ);
    }
    let p0 = ModelParams::nominal(sensor, 0.0);
    let stack = match ind.as_ref() {
        Some(r) => Stack::new(vec![&disp, r as &dyn Residuals]),
        None => Stack::new(vec![&disp]),
    };
    let kind = sensor.elastomer.model;
    let scales: Vec<f64> = free.iter().map(|f| f.scale(&p0)).collect();
    let mut r0 = vec![0.0; stack.len()];
    stack.eval(&p0, &mut r0).map_err(FitError::Numerical)?;
    let j = jacobian(&stack, &p0, &free, &scales, &r0, kind)?;
    // The F/T error as the fit counts it (force_error), with the declared noise: the
    // mean's σ per setpoint, one sample's σ shared (the tare is one sample).
    let force_error = ForceError::declared(&plan.setpoints(), ft, noise.ft_n);
    // Hold the worst-determined parameter while one exceeds its limit, as the fit does.
    let mut cols: Vec<usize> = (0..free.len()).collect();
    let mut held: Vec<(usize, f64)> = Vec::new();
    let groups = stack.groups();
    let half = loop {
        let sub = j.select_columns(cols.iter());
        let sub_free: Vec<ParamId> = cols.iter().map(|c| free[*c]).collect();
        let at_nominal = LmFit {
            params: p0.clone(),
            free: sub_free,
            chi2: (stack.len().saturating_sub(cols.len())).max(1) as f64,
            n: stack.len(),
            iterations: 0,
            converged: true,
            jac: sub,
            resid: vec![0.0; stack.len()],
        };
        let sd: Vec<f64> = if cols.is_empty() {
            Vec::new()
        } else {
            let u = force_error.uncertainty(
                &at_nominal,
                &groups,
                None,
                &p0,
                Some(&disp),
                ind.as_ref(),
            )?;
            // u.sd is in parameter units; expected_sd (declared noise alone) in scaled ones.
            let base = expected_sd(&at_nominal.jac);
            u.sd.iter()
                .zip(&base)
                .zip(&cols)
                .map(|((s, b), c)| s.max(b * scales[*c]) / scales[*c])
                .collect()
        };
        let hw: Vec<f64> = sd
            .iter()
            .zip(&cols)
            .map(|(s, &c)| 1.96 * s * scales[c])
            .collect();
        let worst = cols
            .iter()
            .zip(&hw)
            .enumerate()
            .map(|(k, (&c, h))| (k, h / free[c].threshold(&p0)))
            .filter(|(_, r)| !(r.is_finite() && *r <= 1.0))
            .max_by(|a, b| a.1.total_cmp(&b.1));
        match worst {
            Some((k, _)) => {
                held.push((cols[k], hw[k]));
                cols.remove(k);
            }
            None => break hw,
        }
    };
    let layers: Vec<String> = sensor.layers.iter().map(|l| l.name.clone()).collect();
    let mut out = Vec::new();
    for (k, id) in free.iter().enumerate() {
        let (hw, ok) = match cols.iter().position(|c| *c == k) {
            Some(i) => (half[i], true),
            None => (
                held.iter()
                    .find(|h| h.0 == k)
                    .map_or(f64::INFINITY, |h| h.1),
                false,
            ),
        };
        out.push(Expected {
            name: id.name(&layers),
            unit: id.unit(),
            nominal: id.get(&p0),
            half_width: hw,
            identifiable: ok,
            needs: (!ok).then(|| id.needs()),
        });
    }
    Ok(Prediction {
        params: out,
        setpoints: disp.setpoints().len(),
        plan_setpoints: plan.setpoints().len(),
        bench_time_s: plan.estimate_duration_s(2.0, None),
        no_indentation: no_ind,
        noise_of_mean: (track, ft),
    })
}
