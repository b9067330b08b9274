//! `tactbench fit RUN_DIR`: the whole identification, from a run directory to the
//! [`FitDoc`] (`fit.json`) and the fitted parameters.
//!
//! 1. **Data**: the run's journal and displacements ([`DisplacementRoute::from_run`])
//!    and, where the run offers it, the stage depth against the F/T normal force
//!    ([`IndentationRoute::from_run`]; why not, otherwise, is recorded).
//! 2. **Indentation route alone** (E, the contact z, a bonded layer's h): fitted
//!    first; its RMS residual becomes its noise σ, so both routes' residuals are in
//!    units of their own noise and can be stacked.
//! 3. **Identifiability before the fit**: the joint Jacobian at the nominal values
//!    gives each free parameter's expected 95 % half-width; while one exceeds its
//!    threshold ([`ParamId::threshold`]) the worst (by ratio) is held at nominal and
//!    marked not identifiable, with what kind of setpoint would determine it.
//! 4. **Joint fit** of both routes (Levenberg–Marquardt, [`super::lm`]); intervals
//!    from its Jacobian and residuals. A parameter whose obtained interval still
//!    exceeds its threshold is held and the fit repeated.
//! 5. **Routes side by side**: each route fitted alone on the parameters it sees,
//!    started at the joint solution; E (and h) compared: beyond
//!    `1.96 √(σ₁² + σ₂²)` they disagree and the document says the model does not
//!    describe this gel.
//! 6. **Cross-validation** ([`super::crossval`]): refits on the training folds
//!    (started at the joint solution) and the held-out force-sum error with the
//!    nominal and the fitted sensor file.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde_json::json;

use super::crossval::cross_validate;
use super::displacement::DisplacementRoute;
use super::doc::{FitDoc, ParamFit, Route, FIT_SCHEMA};
use super::force_error::ForceError;
use super::indentation::IndentationRoute;
use super::lm::{
    expected_sd, jacobian, levenberg_marquardt, params_at, uncertainty, LmFit, LmOptions, Stack,
    Uncertainty,
};
use super::space::{at_bound, bounds, default_params, parse_list, ParamId};
use super::{FitError, ModelParams, Residuals};
use crate::analysis::RunData;
use crate::sensor::{ModelKind, Sensor};

/// What `tactbench fit` is asked.
#[derive(Debug, Clone)]
pub struct FitOptions {
    /// The run directory.
    pub run_dir: PathBuf,
    /// The nominal sensor file (default: the one embedded in the run's manifest).
    pub sensor: Option<PathBuf>,
    /// `--params`: comma-separated names (default: every parameter the run can hold).
    pub params: Option<String>,
    /// Cross-validation folds (0: none).
    pub folds: usize,
}

/// A finished fit.
#[derive(Debug, Clone)]
pub struct FitOutcome {
    /// The `fit.json` document.
    pub doc: FitDoc,
    /// The fitted parameters (held ones at nominal).
    pub fitted: ModelParams,
    /// The nominal sensor.
    pub nominal: Sensor,
    /// The nominal sensor file's text (what `fitted.toml` is written from).
    pub nominal_text: String,
    /// Wall time of the fit, s.
    pub seconds: f64,
}

/// A parameter held at nominal, and why.
#[derive(Debug, Clone)]
struct Held {
    id: ParamId,
    identifiable: bool,
    reason: String,
}

/// Loads the nominal sensor (file or the run's own) and its text.
fn nominal_sensor(opts: &FitOptions, run: &RunData) -> Result<(Sensor, String, String), FitError> {
    match &opts.sensor {
        Some(p) => {
            let text = std::fs::read_to_string(p).map_err(|e| FitError::Input {
                path: p.clone(),
                message: format!("cannot read the sensor file: {e}"),
            })?;
            let s = Sensor::from_toml_str(&text, p).map_err(|e| FitError::Input {
                path: p.clone(),
                message: e.to_string(),
            })?;
            Ok((s, text, p.display().to_string()))
        }
        None => Ok((
            run.sensor.clone(),
            run.manifest.sensor_toml.clone(),
            format!(
                "{} (embedded in the run's manifest)",
                run.manifest.sensor_path
            ),
        )),
    }
}

/// Refuses runs that cannot be fitted, naming what is missing.
fn check_run(run: &RunData, dir: &Path) -> Result<(), FitError> {
    if run.rows.len() < 2 {
        return Err(FitError::NotEnoughData(format!(
            "{}: {} measured setpoint(s): a fit needs loaded setpoints at several positions and depths (see experiments/calibrate_elastomer.toml)",
            dir.display(),
            run.rows.len()
        )));
    }
    let has_ft = run.rows.iter().any(|r| {
        [r.fx_n, r.fy_n, r.fz_n]
            .iter()
            .any(|v| v.is_finite() && *v != 0.0)
    });
    if !has_ft {
        return Err(FitError::NotEnoughData(format!(
            "{}: journal.csv has no F/T reading (fx_n, fy_n, fz_n are 0 or empty in every row): both routes are driven by the measured wrench",
            dir.display()
        )));
    }
    if let Some(r) = run
        .rows
        .iter()
        .find(|r| [r.fx_n, r.fy_n, r.fz_n].iter().any(|v| !v.is_finite()))
    {
        return Err(FitError::Input {
            path: dir.join("journal.csv"),
            message: format!(
                "setpoint {}: a non-finite force (fx_n {}, fy_n {}, fz_n {})",
                r.index, r.fx_n, r.fy_n, r.fz_n
            ),
        });
    }
    Ok(())
}

/// The candidate free parameters, and those that cannot enter at all.
fn candidates(
    opts: &FitOptions,
    sensor: &Sensor,
    ind: Option<&IndentationRoute>,
    ind_why: &str,
) -> Result<(Vec<ParamId>, Vec<Held>), FitError> {
    let mut free = match &opts.params {
        Some(list) => parse_list(list, sensor)?,
        None => default_params(sensor, ind.is_some(), true),
    };
    let mut held = Vec::new();
    if ind.is_none() {
        if let Some(k) = free.iter().position(|p| *p == ParamId::ContactZ) {
            free.remove(k);
            held.push(Held {
                id: ParamId::ContactZ,
                identifiable: false,
                reason: format!("no indentation route: {ind_why}"),
            });
        }
    }
    Ok((free, held))
}

/// The nominal parameters: the sensor file's, the bench's contact z.
fn nominal_params(sensor: &Sensor, ind: Option<&IndentationRoute>) -> ModelParams {
    ModelParams::nominal(sensor, ind.map_or(0.0, |r| r.nominal_contact_z().0))
}

/// 95 % half-widths (parameter units) the problem is expected to give at `p`.
fn expected_half_widths(
    problem: &dyn Residuals,
    p: &ModelParams,
    free: &[ParamId],
    kind: ModelKind,
) -> Result<Vec<f64>, FitError> {
    let scales: Vec<f64> = free.iter().map(|f| f.scale(p)).collect();
    let mut r0 = vec![0.0; problem.len()];
    problem.eval(p, &mut r0).map_err(FitError::Numerical)?;
    let j = jacobian(problem, p, free, &scales, &r0, kind)?;
    Ok(expected_sd(&j)
        .iter()
        .zip(&scales)
        .map(|(s, k)| 1.96 * s * k)
        .collect())
}

/// Drops, one at a time, the parameter whose half-width most exceeds its threshold.
fn prune(
    half: impl Fn(&[ParamId]) -> Result<Vec<f64>, FitError>,
    mut free: Vec<ParamId>,
    nominal: &ModelParams,
    layers: &[String],
    held: &mut Vec<Held>,
    when: &str,
) -> Result<Vec<ParamId>, FitError> {
    while !free.is_empty() {
        let hw = half(&free)?;
        let worst = free
            .iter()
            .zip(&hw)
            .enumerate()
            .map(|(k, (id, h))| (k, h / id.threshold(nominal)))
            .filter(|(_, r)| !(r.is_finite() && *r <= 1.0))
            .max_by(|a, b| a.1.total_cmp(&b.1));
        let Some((k, _)) = worst else { break };
        let id = free.remove(k);
        let width = if hw[k].is_finite() {
            format!("+/- {:.3e} {}", hw[k], id.unit())
        } else {
            "unbounded".into()
        };
        held.push(Held {
            id,
            identifiable: false,
            reason: format!(
                "not determined by this run ({when} 95 % half-width {width}, limit +/- {:.3e} {}): held at nominal; it needs {}",
                id.threshold(nominal),
                id.unit(),
                id.needs()
            ),
        });
        let _ = layers;
    }
    Ok(free)
}

struct Joint {
    fit: LmFit,
    unc: Uncertainty,
}

/// The uncertainty of a fit of the joint problem (the F/T error included).
type UncOf<'a> = dyn Fn(&LmFit) -> Result<Uncertainty, FitError> + 'a;

fn fit_joint(
    problem: &dyn Residuals,
    start: &ModelParams,
    free: &[ParamId],
    kind: ModelKind,
    progress: &mut dyn FnMut(&str),
    label: &str,
    unc_of: &UncOf<'_>,
) -> Result<Joint, FitError> {
    let fit = levenberg_marquardt(
        problem,
        start,
        free,
        kind,
        LmOptions::default(),
        &mut |it, c| progress(&format!("{label}: iteration {it}, chi^2 {c:.6e}")),
    )?;
    let unc = unc_of(&fit)?;
    Ok(Joint { fit, unc })
}

/// Reads and checks the run directory.
fn load_run(dir: &Path) -> Result<RunData, FitError> {
    if !dir.join("manifest.json").is_file() {
        return Err(FitError::Input {
            path: dir.to_path_buf(),
            message: "not a run directory (no manifest.json): give a directory `tactbench run` or `tactbench import` wrote".into(),
        });
    }
    let run = RunData::load(dir).map_err(|e| FitError::Input {
        path: dir.to_path_buf(),
        message: e.to_string(),
    })?;
    check_run(&run, dir)?;
    Ok(run)
}

/// Fits the indentation route alone on what it sees and makes its RMS residual its
/// noise σ, so its residuals stack with the displacement route's.
fn set_indentation_noise(
    route: &mut IndentationRoute,
    nominal: &ModelParams,
    free: &[ParamId],
    kind: ModelKind,
    progress: &mut dyn FnMut(&str),
) -> Result<(), FitError> {
    let sees: Vec<ParamId> = free
        .iter()
        .copied()
        .filter(|p| p.enters().indentation && *p != ParamId::Poisson)
        .collect();
    if sees.is_empty() {
        return Ok(());
    }
    progress("indentation route");
    let f = levenberg_marquardt(
        &*route,
        nominal,
        &sees,
        kind,
        LmOptions::default(),
        &mut |_, _| {},
    )?;
    let dof = f.n.saturating_sub(sees.len()).max(1);
    route.set_noise((f.chi2 / dof as f64).sqrt() * route.noise_n());
    Ok(())
}

/// The joint fit; then, while the obtained intervals (with the F/T reading's error:
/// `unc_of`) or the plausible ranges say a parameter is not determined, holds it (with
/// why) and refits. The intervals judged are the ones reported: a parameter that only
/// the F/T sensor's noise seems to determine (an in-plane rotation fitted to the
/// few-count noise of `fx`, `fy` on a run without shear) is held, not reported.
#[allow(clippy::too_many_arguments)]
fn hold_and_refit(
    stack: &Stack,
    nominal: &ModelParams,
    mut free: Vec<ParamId>,
    held: &mut Vec<Held>,
    layers: &[String],
    kind: ModelKind,
    progress: &mut dyn FnMut(&str),
    unc_of: &UncOf<'_>,
) -> Result<(Joint, Vec<ParamId>), FitError> {
    let mut joint = fit_joint(stack, nominal, &free, kind, progress, "joint fit", unc_of)?;
    for _ in 0..4 {
        let before = free.len();
        let hw = joint.unc.half_width.clone();
        let ids = free.clone();
        free = prune(
            |f| {
                Ok(f.iter()
                    .map(|id| hw[ids.iter().position(|x| x == id).unwrap_or(0)])
                    .collect())
            },
            free,
            nominal,
            layers,
            held,
            "obtained",
        )?;
        let edge: Vec<ParamId> = free
            .iter()
            .copied()
            .filter(|id| at_bound(*id, &joint.fit.params, nominal))
            .collect();
        for id in edge {
            free.retain(|x| *x != id);
            let (lo, hi) = bounds(id, &joint.fit.params);
            held.push(Held {
                id,
                identifiable: false,
                reason: format!(
                    "the fit ran to the edge of its plausible range [{lo}, {hi}] {} ({}): the model does not describe these data for it; held at nominal. Check the sensor file, the indenter and the contact positions; it needs {}",
                    id.unit(),
                    id.get(&joint.fit.params),
                    id.needs()
                ),
            });
        }
        if free.len() == before {
            break;
        }
        joint = fit_joint(
            stack,
            nominal,
            &free,
            kind,
            progress,
            "joint fit (refit)",
            unc_of,
        )?;
    }
    Ok((joint, free))
}

/// Cross-validation (`--folds`): each fold's parameters are one Gauss–Newton step from
/// the joint solution on the fold's training setpoints (the joint Jacobian and
/// residuals restricted to them), and its held-out force sums are reconstructed with
/// them and with the nominal ones.
#[allow(clippy::too_many_arguments)]
fn cross_validation(
    opts: &FitOptions,
    run: &RunData,
    sensor: &Sensor,
    nominal: &ModelParams,
    disp: &DisplacementRoute,
    joint: &Joint,
    free: &[ParamId],
    groups: &[usize],
    progress: &mut dyn FnMut(&str),
) -> serde_json::Value {
    if opts.folds >= 2 {
        progress("cross-validation");
        // One Gauss–Newton step from the joint solution on the fold's training rows:
        // the joint fit's Jacobian and residuals restricted to them (no new model
        // evaluation; the fold's optimum lies a small step from the whole run's).
        let scales: Vec<f64> = free.iter().map(|f| f.scale(nominal)).collect();
        let res = cross_validate(
            disp,
            sensor,
            nominal,
            &run.plan.solver,
            opts.folds,
            |train| {
                let train: std::collections::HashSet<usize> = train.iter().copied().collect();
                let np = free.len();
                let mut a = nalgebra::DMatrix::zeros(np, np);
                let mut g = nalgebra::DVector::zeros(np);
                for (i, grp) in groups.iter().enumerate().take(joint.fit.n) {
                    if train.contains(grp) {
                        let row = joint.fit.jac.row(i).transpose();
                        a += &row * row.transpose();
                        g += row * joint.fit.resid[i];
                    }
                }
                let step = a.cholesky().map(|c| c.solve(&(-g))).ok_or_else(|| {
                    FitError::Numerical(
                        "cross-validation: a fold's normal equations are singular".into(),
                    )
                })?;
                Ok(params_at(&joint.fit.params, free, &scales, step.as_slice()))
            },
        );
        match res {
            Ok(v) => v,
            Err(e) => json!({"available": false, "reason": e.to_string()}),
        }
    } else {
        json!({"available": false, "reason": "not asked (--folds 0)"})
    }
}

/// Runs the identification (module docs). `progress` receives one line per step.
pub fn fit_run(opts: &FitOptions, progress: &mut dyn FnMut(&str)) -> Result<FitOutcome, FitError> {
    let t0 = Instant::now();
    let dir = &opts.run_dir;
    let run = load_run(dir)?;
    let (sensor, text, sensor_label) = nominal_sensor(opts, &run)?;
    let kind = sensor.elastomer.model;
    let layers: Vec<String> = sensor.layers.iter().map(|l| l.name.clone()).collect();
    progress("reading the run's displacements");
    let disp = DisplacementRoute::from_run(dir, &sensor)?;
    let (mut ind, ind_why) = match IndentationRoute::from_run(&run, &sensor) {
        Ok(r) => (Some(r), String::new()),
        Err(why) => (None, why),
    };
    let (free, mut held) = candidates(opts, &sensor, ind.as_ref(), &ind_why)?;
    let nominal = nominal_params(&sensor, ind.as_ref());

    // 2. The indentation route alone sets its own noise.
    let mut ind_alone = None;
    if let Some(route) = ind.as_mut() {
        set_indentation_noise(route, &nominal, &free, kind, progress)?;
    }

    // 3. Identifiability at nominal on the joint problem.
    let stack: Stack = match ind.as_ref() {
        Some(r) => Stack::new(vec![&disp, r]),
        None => Stack::new(vec![&disp]),
    };
    progress("identifiability at the nominal parameters");
    let free = prune(
        |f| expected_half_widths(&stack, &nominal, f, kind),
        free,
        &nominal,
        &layers,
        &mut held,
        "expected",
    )?;

    // 4. Joint fit; hold what the data still do not determine, and refit.
    let force_error = ForceError::of_run(&run).share(ind.as_ref().map(|r| r.noise_n()));
    let (groups, marker_groups) = (stack.groups(), stack.marker_groups());
    let unc_of = |fit: &LmFit| {
        force_error.uncertainty(
            fit,
            &groups,
            Some(&marker_groups),
            &nominal,
            Some(&disp),
            ind.as_ref(),
        )
    };
    let (joint, free) = hold_and_refit(
        &stack, &nominal, free, &mut held, &layers, kind, progress, &unc_of,
    )?;
    if let Some(route) = ind.as_ref() {
        if route.noise_n() > 0.0 {
            ind_alone = Some(side_fit(route, &joint.fit.params, &free, kind, |p| {
                p.enters().indentation && *p != ParamId::Poisson
            })?);
        }
    }
    if let (Some(Some(j)), Some(route)) = (ind_alone.as_mut(), ind.as_ref()) {
        j.unc =
            force_error.uncertainty(&j.fit, &route.groups(), None, &nominal, None, Some(route))?;
    }
    progress("displacement route alone");
    let mut disp_alone = side_fit(&disp, &joint.fit.params, &free, kind, |p| {
        p.enters().displacement
    })?;
    if let Some(j) = disp_alone.as_mut() {
        j.unc = force_error.uncertainty(
            &j.fit,
            &disp.groups(),
            Some(&disp.marker_groups()),
            &nominal,
            Some(&disp),
            None,
        )?;
    }

    // 6. Cross-validation.
    let cv = cross_validation(
        opts,
        &run,
        &sensor,
        &nominal,
        &disp,
        &joint,
        &free,
        &stack.groups(),
        progress,
    );

    let doc = build_doc(DocParts {
        opts,
        sensor_label,
        layers: &layers,
        kind,
        nominal: &nominal,
        joint: &joint,
        free: &free,
        held: &held,
        disp: &disp,
        ind: ind.as_ref(),
        ind_why: &ind_why,
        ind_alone: ind_alone.as_ref(),
        disp_alone: &disp_alone,
        cv,
        seconds: t0.elapsed().as_secs_f64(),
        resolution: force_error.resolution_n,
    })?;
    Ok(FitOutcome {
        doc,
        fitted: joint.fit.params,
        nominal: sensor,
        nominal_text: text,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// One route alone on the parameters it sees, from the joint solution.
fn side_fit(
    route: &dyn Residuals,
    start: &ModelParams,
    free: &[ParamId],
    kind: ModelKind,
    sees: impl Fn(&ParamId) -> bool,
) -> Result<Option<Joint>, FitError> {
    let f: Vec<ParamId> = free.iter().copied().filter(|p| sees(p)).collect();
    if f.is_empty() || route.is_empty() {
        return Ok(None);
    }
    let fit = levenberg_marquardt(
        route,
        start,
        &f,
        kind,
        LmOptions { max_iter: 20 },
        &mut |_, _| {},
    )?;
    let unc = uncertainty(&fit, &route.groups(), start);
    Ok(Some(Joint { fit, unc }))
}

struct DocParts<'a> {
    opts: &'a FitOptions,
    sensor_label: String,
    layers: &'a [String],
    kind: ModelKind,
    nominal: &'a ModelParams,
    joint: &'a Joint,
    free: &'a [ParamId],
    held: &'a [Held],
    disp: &'a DisplacementRoute,
    ind: Option<&'a IndentationRoute>,
    ind_why: &'a str,
    ind_alone: Option<&'a Option<Joint>>,
    disp_alone: &'a Option<Joint>,
    cv: serde_json::Value,
    seconds: f64,
    resolution: Option<f64>,
}

/// Every parameter the model has, in a fixed order.
fn all_params(sensor_layers: usize) -> Vec<ParamId> {
    let mut v = vec![ParamId::YoungModulus, ParamId::Poisson, ParamId::Thickness];
    v.extend((0..sensor_layers).map(ParamId::Depth));
    v.extend([
        ParamId::MmPerPx,
        ParamId::FtRotation,
        ParamId::OffsetX,
        ParamId::OffsetY,
        ParamId::ContactZ,
    ]);
    v
}

fn route_of(id: ParamId, has_ind: bool) -> Route {
    let e = id.enters();
    match (e.indentation && has_ind, e.displacement) {
        (true, true) => Route::Both,
        (true, false) => Route::Indentation,
        _ => Route::Displacement,
    }
}

/// `{NAME: {"value", "ci95"}}` of a route fitted alone.
fn route_params(j: &Joint, layers: &[String]) -> serde_json::Value {
    let m: serde_json::Map<String, serde_json::Value> = j
        .fit
        .free
        .iter()
        .zip(&j.unc.half_width)
        .map(|(id, h)| {
            let v = id.get(&j.fit.params);
            (
                id.name(layers),
                json!({"value": v, "ci95": [v - h, v + h], "unit": id.unit()}),
            )
        })
        .collect();
    serde_json::Value::Object(m)
}

fn build_doc(d: DocParts) -> Result<FitDoc, FitError> {
    let j = d.joint;
    let has_ind = d.ind.is_some();
    let mut parameters = BTreeMap::new();
    // Per-layer scales when fitted that way; otherwise the shared one.
    let mut ids = all_params(d.layers.len());
    for id in d.free.iter().chain(d.held.iter().map(|h| &h.id)) {
        if let ParamId::MmPerPxLayer(_) = id {
            if !ids.contains(id) {
                ids.push(*id);
            }
        }
    }
    if ids.iter().any(|p| matches!(p, ParamId::MmPerPxLayer(_))) {
        ids.retain(|p| *p != ParamId::MmPerPx);
    }
    for id in ids {
        let name = id.name(d.layers);
        let nominal = id.get(d.nominal);
        let entry = if let Some(k) = d.free.iter().position(|p| *p == id) {
            let v = id.get(&j.fit.params);
            let h = j.unc.half_width[k];
            ParamFit {
                value: v,
                ci95: Some([v - h, v + h]),
                unit: id.unit().into(),
                identifiable: true,
                route: route_of(id, has_ind),
                nominal,
                sd: Some(j.unc.sd[k]),
                fitted: true,
                reason: None,
            }
        } else {
            let (identifiable, reason) = match d.held.iter().find(|h| h.id == id) {
                Some(h) => (h.identifiable, h.reason.clone()),
                None if id == ParamId::Thickness && d.kind == ModelKind::HalfSpace => (
                    false,
                    "the sensor's model is the half-space, whose field does not depend on a thickness".into(),
                ),
                None => (true, "not fitted (not in --params): held at nominal".into()),
            };
            ParamFit {
                value: nominal,
                ci95: None,
                unit: id.unit().into(),
                identifiable,
                route: route_of(id, has_ind),
                nominal,
                sd: None,
                fitted: false,
                reason: Some(reason),
            }
        };
        parameters.insert(name, entry);
    }
    let (per_sp, per_layer) = d
        .disp
        .residual_rms_px(&j.fit.params)
        .map_err(FitError::Numerical)?;
    let residual_rms_px: BTreeMap<String, f64> = per_layer.into_iter().collect();
    let routes = routes_doc(&d)?;
    let mut extra = BTreeMap::new();
    extra.insert("ci_method".into(), json!(j.unc.method));
    extra.insert(
        "correlations".into(),
        json!({"names": d.free.iter().map(|p| p.name(d.layers)).collect::<Vec<_>>(), "matrix": j.unc.correlation}),
    );
    extra.insert("examples".into(), examples(d.disp, &j.fit.params)?);
    extra.insert(
        "setpoint_residuals".into(),
        json!(per_sp
            .iter()
            .map(|(i, r)| json!({"index": i, "rms_px": r}))
            .collect::<Vec<_>>()),
    );
    if let Some(r) = d.ind {
        extra.insert("indentation_curve".into(), r.curve(&j.fit.params));
    }
    extra.insert(
        "fit".into(),
        json!({"residuals": j.fit.n, "chi2": j.fit.chi2, "ft_resolution_n": d.resolution, "reduced_chi2": j.unc.reduced_chi2,
               "iterations": j.fit.iterations, "converged": j.fit.converged,
               "clusters": j.unc.clusters, "t": j.unc.t, "dof": j.unc.dof,
               "seconds": d.seconds, "model": d.kind.name()}),
    );
    Ok(FitDoc {
        schema: FIT_SCHEMA.into(),
        run: d.opts.run_dir.display().to_string(),
        sensor: d.sensor_label.clone(),
        parameters,
        routes,
        residual_rms_px,
        cross_validation: d.cv.clone(),
        extra,
    })
}

/// Flattens [`DisplacementRoute::vectors`] of the 3 most loaded setpoints into the
/// page's `examples` rows.
fn examples(disp: &DisplacementRoute, p: &ModelParams) -> Result<serde_json::Value, FitError> {
    let v = disp.vectors(p, 3).map_err(FitError::Numerical)?;
    let mut rows = Vec::new();
    for sp in v.as_array().into_iter().flatten() {
        for m in sp["markers"].as_array().into_iter().flatten() {
            let layer = m["layer"].as_str().unwrap_or_default();
            let l = disp.layer_index(layer).unwrap_or(0);
            let s = p.mm_per_px[l];
            let x = m["x_px"].as_f64().unwrap_or(f64::NAN) * s;
            let y = m["y_px"].as_f64().unwrap_or(f64::NAN) * s;
            rows.push(
                json!({"index": sp["index"], "layer": layer, "x_mm": x, "y_mm": y,
                "ux_px": m["measured_px"][0], "uy_px": m["measured_px"][1],
                "pred_ux_px": m["predicted_px"][0], "pred_uy_px": m["predicted_px"][1]}),
            );
        }
    }
    Ok(serde_json::Value::Array(rows))
}

/// `routes`: each route alone, side by side, and whether they agree on what both see.
fn routes_doc(d: &DocParts) -> Result<serde_json::Value, FitError> {
    let p = &d.joint.fit.params;
    let mut disp = d.disp.summary(p).map_err(FitError::Numerical)?;
    if let Some(j) = d.disp_alone {
        disp["parameters"] = route_params(j, d.layers);
    }
    let ind = match (d.ind, d.ind_alone) {
        (Some(r), alone) => {
            let mut v = r.summary(p);
            if let Some(Some(j)) = alone {
                v["parameters"] = route_params(j, d.layers);
            }
            v
        }
        (None, _) => json!({"available": false, "reason": d.ind_why}),
    };
    let mut disagreements = Vec::new();
    if let (Some(Some(a)), Some(b)) = (d.ind_alone, d.disp_alone) {
        for id in [ParamId::YoungModulus, ParamId::Thickness] {
            let (Some(ka), Some(kb)) = (
                a.fit.free.iter().position(|x| *x == id),
                b.fit.free.iter().position(|x| *x == id),
            ) else {
                continue;
            };
            let (va, vb) = (id.get(&a.fit.params), id.get(&b.fit.params));
            let (sa, sb) = (a.unc.sd[ka], b.unc.sd[kb]);
            let lim = 1.96 * sa.hypot(sb);
            if (va - vb).abs() > lim {
                disagreements.push(format!(
                    "{}: the indentation route gives {va:.4} +/- {:.3} {u} and the displacement route {vb:.4} +/- {:.3} {u}, {:.1} sigma apart: the {} model does not describe this gel (a thin layer fitted as a half-space, a wrong indenter, or a mis-set scale)",
                    id.name(d.layers),
                    1.96 * sa,
                    1.96 * sb,
                    (va - vb).abs() / sa.hypot(sb),
                    d.kind.name(),
                    u = id.unit()
                ));
            }
        }
    }
    Ok(json!({
        "indentation": ind,
        "displacement": disp,
        "agree": disagreements.is_empty(),
        "disagreements": disagreements,
    }))
}
