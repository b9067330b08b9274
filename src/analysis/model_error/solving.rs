//! Solving the model-error study's rows: each solver built and scored on a data set
//! (see [`super`]), and the solvers of one data set timed round-robin.

use super::*;

/// A dense `H` for the full marker set with its build time (s), or why it failed.
pub(super) type Operator = Result<(DMatrix<f64>, f64), String>;

/// Builds the row's solver, scores it on every realisation; `Err` is the refusal.
pub(super) fn solve_row(
    row: &mut ModelErrorRow,
    sensor: &Sensor,
    sites: &[MarkerSite],
    operator: &Operator,
    data: &Data,
    config: &SolverConfig,
) -> Result<Box<dyn FrameSolver>, String> {
    row.applied_n = data.applied;
    row.markers_used = (data.used.len(), sites.len());
    row.t_track_s = data.track_s;
    let frame0 = &data.frames[0];
    let mut solver: Box<dyn FrameSolver> = if config.method == Method::Fourier {
        let used: Vec<MarkerSite> = data.used.iter().map(|&i| sites[i]).collect();
        let problem = Problem::new(sensor, &used);
        let t = Instant::now();
        let s = solve::precompute(&problem, config, Some(frame0)).map_err(|e| e.to_string())?;
        row.t_precompute_s = t.elapsed().as_secs_f64();
        row.t_build_s = row.t_precompute_s;
        s
    } else {
        let (h_full, t_h) = operator.as_ref().map_err(|e| e.clone())?;
        let h = if data.used.len() == sites.len() {
            h_full.clone()
        } else {
            let rows: Vec<usize> = data.used.iter().flat_map(|&i| [2 * i, 2 * i + 1]).collect();
            h_full.select_rows(&rows)
        };
        let t = Instant::now();
        let s = DenseSolver::from_matrix(h, config, Some(frame0)).map_err(|e| e.to_string())?;
        row.t_precompute_s = t.elapsed().as_secs_f64();
        row.t_h_s = Some(*t_h);
        row.t_build_s = t_h + row.t_precompute_s;
        Box::new(s)
    };
    let mut f = vec![0.0; solver.n_outputs()];
    let r = data.frames.len() as f64;
    let mut acc = ForceErrors {
        field: 0.0,
        field_axis: [0.0; 3],
        sum: 0.0,
        sum_axis: [0.0; 3],
        mean_abs_gf: 0.0,
        fsum_n: [0.0; 3],
    };
    for u in &data.frames {
        solver.apply(u, &mut f).map_err(|e| e.to_string())?;
        let e = force_errors(&f, &data.truth, data.applied);
        acc.field += e.field * e.field / r;
        acc.sum += e.sum * e.sum / r;
        acc.mean_abs_gf += e.mean_abs_gf / r;
        for a in 0..3 {
            acc.field_axis[a] += e.field_axis[a] * e.field_axis[a] / r;
            acc.sum_axis[a] += e.sum_axis[a] / r;
            acc.fsum_n[a] += e.fsum_n[a] / r;
        }
    }
    acc.field = acc.field.sqrt();
    acc.sum = acc.sum.sqrt();
    acc.field_axis = acc.field_axis.map(f64::sqrt);
    row.errors = acc;
    row.realisations = data.frames.len();
    let d = solver.diagnostics();
    row.lambda = d.lambda;
    row.rank = d.rank;
    row.condition_number = d.condition_of_h();
    Ok(solver)
}

/// Times the solvers of one data set round-robin; fills `t_solve` and `t_frame`.
pub(super) fn time_group(
    group: &mut [(ModelErrorRow, Option<Box<dyn FrameSolver>>)],
    data: &Data,
    reps: usize,
) {
    let u = &data.frames[0];
    let mut times: Vec<Vec<f64>> = vec![Vec::with_capacity(reps); group.len()];
    let mut failed = vec![None; group.len()];
    let mut f = Vec::new();
    for _ in 0..reps {
        for (i, (_, solver)) in group.iter_mut().enumerate() {
            let Some(s) = solver else { continue };
            if failed[i].is_some() {
                continue;
            }
            f.resize(s.n_outputs(), 0.0);
            let r = s.apply(u, &mut f);
            let t = Instant::now();
            let r2 = s.apply(u, &mut f);
            times[i].push(t.elapsed().as_secs_f64());
            if let Err(e) = r.and(r2) {
                failed[i] = Some(e.to_string());
            }
        }
    }
    for (i, (row, solver)) in group.iter_mut().enumerate() {
        if solver.is_none() {
            continue;
        }
        if let Some(reason) = failed[i].take() {
            row.status = RowStatus::Refused(reason);
            continue;
        }
        row.t_solve_s = median(&mut times[i]);
        row.t_frame_s = row.t_solve_s + row.t_track_s.unwrap_or(0.0);
    }
}

/// Each solver model's sensor and dense `H` for the full marker set of one thickness
/// (built first, while the thickness's layer tables are cold; its build time is the
/// rows' `t_h`), reported through `progress`.
pub(super) fn build_operators(
    sensor_h: &Sensor,
    sites: &[MarkerSite],
    points: &[[f64; 2]],
    h: f64,
    options: &ModelErrorOptions,
    progress: &mut dyn FnMut(ModelErrorEvent<'_>),
) -> Vec<(ModelKind, Sensor, Operator)> {
    let mut operators = Vec::new();
    let any_dense = options.solvers.iter().any(|c| c.method != Method::Fourier);
    for &m in &options.solver_models {
        let mut s = sensor_h.clone();
        s.elastomer.model = m;
        let op = if any_dense {
            let t = Instant::now();
            let r = crate::solve::dense::check_dense_size(2 * sites.len(), 3 * points.len())
                .map_err(|e| e.to_string())
                .and_then(|()| {
                    model::transfer_matrix(
                        &ForwardModel::from_elastomer(&s.elastomer),
                        sites,
                        points,
                    )
                    .map_err(|e| e.to_string())
                })
                .map(|hm| (hm, t.elapsed().as_secs_f64()));
            progress(ModelErrorEvent::Operator {
                thickness_mm: h,
                model: m,
                seconds: r.as_ref().map_or(f64::NAN, |x| x.1),
            });
            r
        } else {
            Err("no dense solver".into())
        };
        operators.push((m, s, op));
    }
    operators
}
