//! Layer separation (paper Sec. IV-B-1, Fig. 6): force reconstruction error against the
//! distance between the two marker layers, from simulation, per solver.
//!
//! # Procedure (the paper's)
//!
//! For each case — the first layer alone, then the second layer at the first layer's
//! depth plus `d` for each separation `d` (the paper: 0, 1, …, 6, 8, 13 mm; `d = 0` is
//! one layer with twice the marker density) — the marker displacements of a known force
//! distribution `f*` on the force grid are computed with the forward model (Eq. 5,
//! `u = H f*`), Gaussian noise of σ px (the paper: 0.1 px; converted with the camera's
//! mm/px) is added independently to each component, and the forces are reconstructed
//! with each solver. Each noisy case is repeated over `trials` seeded noise draws
//! (trial `t` draws from stream `t` of the seed); the solver (and its automatic λ or
//! rank) is precomputed on the first trial's frame and kept for the others, as a
//! running sensor would.
//!
//! # Metrics
//!
//! - the paper's: the **mean absolute difference** between calculated and actual force
//!   per axis, `m_a = (1/n) Σ_j |f_ja − f*_ja|` over the `n` force points, reported in N
//!   per axis and, averaged over the three axes, in gf (the figure's value);
//! - the relative L2 error `‖f − f*‖₂ / ‖f*‖₂`.
//!
//! Both are averaged over the trials (with their standard deviation across trials).
//!
//! # Load
//!
//! [`paper_fig6_load`]: 100 gf along z and 50 gf along y spread equally over the 4 × 4
//! force points between (4, 3) and (7, 6) (the paper's 1-based indices) of the 10 × 8
//! grid — `experiments/examples/fig6_forces.csv`.

use thiserror::Error;

use crate::model::{self, HalfSpace, MarkerSite};
use crate::sensor::{Grid, Sensor};
use crate::sim::rng::Rng;
use crate::solve::{self, FrameSolver, Lambda, Method, Problem, Rank, SolverConfig};
use crate::units;

/// Largest number of noise trials.
pub const MAX_TRIALS: usize = 10_000;

/// An error of the layer-separation study.
#[derive(Debug, Error)]
pub enum LayerError {
    /// An option is out of range.
    #[error("invalid layer-separation option: {0}")]
    InvalidOption(String),
    /// The sensor does not fit the study.
    #[error("sensor: {0}")]
    Sensor(String),
    /// The forward model could not be evaluated.
    #[error("forward model: {0}")]
    Model(#[from] model::ModelError),
}

/// The force distribution of the paper's Fig. 6 on `grid` (interleaved `fx, fy, fz` per
/// node, N): 100 gf along z and 50 gf along y, spread equally over nodes
/// `ix ∈ 3..=6, iy ∈ 2..=5` (0-based; the paper's (4, 3)–(7, 6)). Fails when the grid
/// is smaller than 7 × 6 nodes.
pub fn paper_fig6_load(grid: &Grid) -> Result<Vec<f64>, LayerError> {
    if grid.nx < 7 || grid.ny < 6 {
        return Err(LayerError::Sensor(format!(
            "the fig. 6 load needs a force grid of at least 7 x 6 nodes, got {} x {}",
            grid.nx, grid.ny
        )));
    }
    let per_node = 1.0 / 16.0;
    let fz = units::gf_to_n(100.0) * per_node;
    let fy = units::gf_to_n(50.0) * per_node;
    let mut f = vec![0.0; 3 * grid.len()];
    for iy in 2..=5 {
        for ix in 3..=6 {
            let j = iy * grid.nx + ix;
            f[3 * j + 1] = fy;
            f[3 * j + 2] = fz;
        }
    }
    Ok(f)
}

/// One layer configuration of the study.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LayerCase {
    /// The first layer only.
    SingleLayer,
    /// The second layer this far (mm, ≥ 0) below the first.
    Separation(f64),
}

impl LayerCase {
    /// Label for tables and plots: `single layer` or `d = 3 mm`.
    pub fn label(self) -> String {
        match self {
            LayerCase::SingleLayer => "single layer".into(),
            LayerCase::Separation(d) => format!("d = {d} mm"),
        }
    }

    /// Separation in mm (`None` for a single layer).
    pub fn separation_mm(self) -> Option<f64> {
        match self {
            LayerCase::SingleLayer => None,
            LayerCase::Separation(d) => Some(d),
        }
    }
}

/// `base` with its layers arranged for `case`: the first layer as is, the second one
/// (kept with its own marker grid) moved to `first depth + d`, or dropped. Further
/// layers are dropped.
pub fn layer_sensor(base: &Sensor, case: LayerCase) -> Result<Sensor, LayerError> {
    if base.layers.len() < 2 || base.layers.iter().take(2).any(|l| l.markers.is_none()) {
        return Err(LayerError::Sensor(
            "layer separation needs a sensor with two layers that have marker grids".into(),
        ));
    }
    let mut s = base.clone();
    s.layers.truncate(2);
    match case {
        LayerCase::SingleLayer => {
            s.layers.truncate(1);
        }
        LayerCase::Separation(d) => {
            if !(d.is_finite() && d >= 0.0) {
                return Err(LayerError::InvalidOption(format!(
                    "layer separation {d} mm must be finite and >= 0"
                )));
            }
            s.layers[1].depth_mm = s.layers[0].depth_mm + d;
        }
    }
    Ok(s)
}

/// A solver of the study, with its label.
#[derive(Debug, Clone, PartialEq)]
pub struct LayerSolver {
    /// Label, e.g. `tikhonov gcv`.
    pub label: String,
    /// The configuration.
    pub config: SolverConfig,
}

/// The default solvers: pinv, tikhonov (GCV), tikhonov (L-curve), tsvd (automatic rank).
pub fn default_solvers() -> Vec<LayerSolver> {
    let c = |method, lambda| SolverConfig {
        method,
        lambda,
        rank: Rank::Auto,
        ..SolverConfig::default()
    };
    vec![
        LayerSolver {
            label: "pinv".into(),
            config: c(Method::Pinv, Lambda::Gcv),
        },
        LayerSolver {
            label: "tikhonov gcv".into(),
            config: c(Method::Tikhonov, Lambda::Gcv),
        },
        LayerSolver {
            label: "tikhonov lcurve".into(),
            config: c(Method::Tikhonov, Lambda::LCurve),
        },
        LayerSolver {
            label: "tsvd auto".into(),
            config: c(Method::Tsvd, Lambda::Gcv),
        },
    ]
}

/// The paper's separations, mm: 0 (same depth), 1–6, 8, 13.
pub const PAPER_SEPARATIONS_MM: [f64; 9] = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 13.0];

/// Options of [`run_layer_separation`].
#[derive(Debug, Clone, PartialEq)]
pub struct LayerOptions {
    /// Cases, in plot order.
    pub cases: Vec<LayerCase>,
    /// Solvers.
    pub solvers: Vec<LayerSolver>,
    /// Displacement noise levels, px (σ per component; 0 = exact data, one trial).
    pub noise_px: Vec<f64>,
    /// Noise draws per noisy case (≥ 1).
    pub trials: usize,
    /// Seed of the noise.
    pub seed: u64,
}

impl Default for LayerOptions {
    /// Single layer + the paper's separations; default solvers; exact data and the
    /// paper's 0.1 px; 20 trials; seed 6.
    fn default() -> Self {
        let mut cases = vec![LayerCase::SingleLayer];
        cases.extend(PAPER_SEPARATIONS_MM.map(LayerCase::Separation));
        LayerOptions {
            cases,
            solvers: default_solvers(),
            noise_px: vec![0.0, 0.1],
            trials: 20,
            seed: 6,
        }
    }
}

/// The error of one (case, solver, noise level).
#[derive(Debug, Clone, PartialEq)]
pub struct LayerRow {
    /// The case.
    pub case: LayerCase,
    /// Solver label.
    pub solver: String,
    /// Noise σ, px.
    pub noise_px: f64,
    /// Trials averaged.
    pub trials: usize,
    /// Paper metric per axis (mean |f − f*| over the force points), N, trial mean.
    pub mean_abs_n: [f64; 3],
    /// The paper metric averaged over the axes, gf, trial mean.
    pub mean_abs_gf: f64,
    /// Its standard deviation across trials, gf (0 for one trial).
    pub mean_abs_gf_sd: f64,
    /// Relative L2 error, trial mean.
    pub rel_l2: f64,
    /// Condition number of `H` for this case.
    pub condition_number: f64,
    /// λ chosen (mm/N), when the solver has one.
    pub lambda: Option<f64>,
    /// Rank used, when the solver reports one.
    pub rank: Option<usize>,
}

/// A (case, solver, noise) combination that could not run.
#[derive(Debug, Clone, PartialEq)]
pub struct LayerSkipped {
    /// The case.
    pub case: LayerCase,
    /// Solver label.
    pub solver: String,
    /// Noise σ, px.
    pub noise_px: f64,
    /// The solver's error message.
    pub reason: String,
}

/// The study's results.
#[derive(Debug, Clone, PartialEq)]
pub struct LayerResult {
    /// Rows, by noise level, then case, then solver.
    pub rows: Vec<LayerRow>,
    /// What could not run.
    pub skipped: Vec<LayerSkipped>,
}

/// Progress of [`run_layer_separation`]: one event per (case, noise level) done.
#[derive(Debug, Clone, Copy)]
pub struct LayerProgress {
    /// Combinations done.
    pub done: usize,
    /// Combinations in all.
    pub total: usize,
}

/// Runs the study for the force distribution `load_n` (on `base`'s force grid).
pub fn run_layer_separation(
    base: &Sensor,
    load_n: &[f64],
    options: &LayerOptions,
    progress: &mut dyn FnMut(LayerProgress),
) -> Result<LayerResult, LayerError> {
    if load_n.len() != 3 * base.force_grid.len() {
        return Err(LayerError::InvalidOption(format!(
            "the load has {} values but the force grid needs {} (3 per node)",
            load_n.len(),
            3 * base.force_grid.len()
        )));
    }
    if load_n.iter().all(|v| *v == 0.0) || load_n.iter().any(|v| !v.is_finite()) {
        return Err(LayerError::InvalidOption(
            "the load must be finite and not all zero".into(),
        ));
    }
    if options.trials == 0 || options.trials > MAX_TRIALS {
        return Err(LayerError::InvalidOption(format!(
            "trials = {} must be in 1..={MAX_TRIALS}",
            options.trials
        )));
    }
    if options.cases.is_empty() || options.solvers.is_empty() || options.noise_px.is_empty() {
        return Err(LayerError::InvalidOption(
            "cases, solvers and noise levels must each have at least one entry".into(),
        ));
    }
    if let Some(n) = options
        .noise_px
        .iter()
        .find(|n| !(n.is_finite() && **n >= 0.0))
    {
        return Err(LayerError::InvalidOption(format!(
            "noise {n} px must be finite and >= 0"
        )));
    }
    let model = HalfSpace::from_elastomer(&base.elastomer);
    let points = base.force_points_mm();
    let mm_per_px = base.camera.mm_per_px;
    let n_points = base.force_grid.len() as f64;
    let load_norm = load_n.iter().map(|v| v * v).sum::<f64>().sqrt();
    let total = options.noise_px.len() * options.cases.len();
    let mut done = 0;
    let mut rows = Vec::new();
    let mut skipped = Vec::new();
    let mut f = vec![0.0; load_n.len()];
    for &noise in &options.noise_px {
        for &case in &options.cases {
            let sensor = layer_sensor(base, case)?;
            let sites = MarkerSite::from_sensor_grids(&sensor);
            let u_exact = model::forward(&model, &sites, &points, load_n)?;
            let trials = if noise == 0.0 { 1 } else { options.trials };
            let frames: Vec<Vec<f64>> = (0..trials)
                .map(|t| {
                    let mut rng = Rng::stream(options.seed, t as u64);
                    u_exact
                        .iter()
                        .map(|u| u + noise * mm_per_px * rng.normal())
                        .collect()
                })
                .collect();
            let problem = Problem::new(&sensor, &sites);
            for s in &options.solvers {
                let mut solver: Box<dyn FrameSolver> =
                    match solve::precompute(&problem, &s.config, Some(&frames[0])) {
                        Ok(x) => x,
                        Err(e) => {
                            skipped.push(LayerSkipped {
                                case,
                                solver: s.label.clone(),
                                noise_px: noise,
                                reason: e.to_string(),
                            });
                            continue;
                        }
                    };
                let mut per_trial_gf = Vec::with_capacity(trials);
                let mut mean_abs_n = [0.0; 3];
                let mut rel_l2 = 0.0;
                let mut failed = None;
                for u in &frames {
                    if let Err(e) = solver.apply(u, &mut f) {
                        failed = Some(e.to_string());
                        break;
                    }
                    let mut m = [0.0; 3];
                    let mut d2 = 0.0;
                    for (i, (a, b)) in f.iter().zip(load_n).enumerate() {
                        m[i % 3] += (a - b).abs() / n_points;
                        d2 += (a - b) * (a - b);
                    }
                    for a in 0..3 {
                        mean_abs_n[a] += m[a] / trials as f64;
                    }
                    rel_l2 += d2.sqrt() / load_norm / trials as f64;
                    per_trial_gf.push(units::n_to_gf((m[0] + m[1] + m[2]) / 3.0));
                }
                if let Some(reason) = failed {
                    skipped.push(LayerSkipped {
                        case,
                        solver: s.label.clone(),
                        noise_px: noise,
                        reason,
                    });
                    continue;
                }
                let mean_gf = per_trial_gf.iter().sum::<f64>() / trials as f64;
                let sd_gf = if trials > 1 {
                    (per_trial_gf
                        .iter()
                        .map(|v| (v - mean_gf) * (v - mean_gf))
                        .sum::<f64>()
                        / (trials - 1) as f64)
                        .sqrt()
                } else {
                    0.0
                };
                let d = solver.diagnostics();
                rows.push(LayerRow {
                    case,
                    solver: s.label.clone(),
                    noise_px: noise,
                    trials,
                    mean_abs_n,
                    mean_abs_gf: mean_gf,
                    mean_abs_gf_sd: sd_gf,
                    rel_l2,
                    condition_number: d.condition_number,
                    lambda: d.lambda,
                    rank: d.rank,
                });
            }
            done += 1;
            progress(LayerProgress { done, total });
        }
    }
    Ok(LayerResult { rows, skipped })
}

/// Columns of `layer_separation.csv`: separation empty for the single-layer case;
/// errors in N (per axis) and gf (axis mean), λ in mm/N.
pub const LAYER_COLUMNS: [&str; 14] = [
    "case",
    "separation_mm",
    "solver",
    "noise_px",
    "trials",
    "mean_abs_fx_n",
    "mean_abs_fy_n",
    "mean_abs_fz_n",
    "mean_abs_gf",
    "mean_abs_gf_sd",
    "rel_l2",
    "condition_number",
    "lambda_mm_per_n",
    "rank",
];

impl LayerResult {
    /// Writes the rows as CSV ([`LAYER_COLUMNS`]).
    pub fn write_csv(&self, path: &std::path::Path) -> Result<(), std::io::Error> {
        let mut w = csv::Writer::from_path(path)?;
        w.write_record(LAYER_COLUMNS)?;
        for r in &self.rows {
            w.write_record([
                r.case.label(),
                r.case
                    .separation_mm()
                    .map(|d| d.to_string())
                    .unwrap_or_default(),
                r.solver.clone(),
                r.noise_px.to_string(),
                r.trials.to_string(),
                format!("{:.6e}", r.mean_abs_n[0]),
                format!("{:.6e}", r.mean_abs_n[1]),
                format!("{:.6e}", r.mean_abs_n[2]),
                format!("{:.6e}", r.mean_abs_gf),
                format!("{:.6e}", r.mean_abs_gf_sd),
                format!("{:.6e}", r.rel_l2),
                format!("{:.6e}", r.condition_number),
                r.lambda.map(|l| format!("{l:.6e}")).unwrap_or_default(),
                r.rank.map(|k| k.to_string()).unwrap_or_default(),
            ])?;
        }
        w.flush()
    }

    /// The row of (case, solver, noise), if it ran.
    pub fn find(&self, case: LayerCase, solver: &str, noise_px: f64) -> Option<&LayerRow> {
        self.rows
            .iter()
            .find(|r| r.case == case && r.solver == solver && r.noise_px == noise_px)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sensor::paper_sensor;

    #[test]
    fn fig6_load_matches_the_example_file_totals() {
        let s = paper_sensor();
        let f = paper_fig6_load(&s.force_grid).unwrap();
        let sum = |a: usize| f.iter().skip(a).step_by(3).sum::<f64>();
        assert!((units::n_to_gf(sum(2)) - 100.0).abs() < 1e-9);
        assert!((units::n_to_gf(sum(1)) - 50.0).abs() < 1e-9);
        assert_eq!(sum(0), 0.0);
        assert_eq!(f.iter().filter(|v| **v != 0.0).count(), 32);
    }

    #[test]
    fn layer_sensor_moves_or_drops_the_second_layer() {
        let s = paper_sensor();
        let one = layer_sensor(&s, LayerCase::SingleLayer).unwrap();
        assert_eq!(one.layers.len(), 1);
        let d = layer_sensor(&s, LayerCase::Separation(5.0)).unwrap();
        assert_eq!(d.layers[1].depth_mm, 8.0);
        assert!(layer_sensor(&s, LayerCase::Separation(-1.0)).is_err());
    }
}
