//! Model error: what the half-space assumption costs a sensor whose elastomer is a
//! finite layer bonded to a rigid plate, and what a solver that models the layer buys
//! back, per thickness and per camera effect, with the time each solver costs
//! (issue 14, deliverable 5).
//!
//! # What is swept
//!
//! For every elastomer thickness `h` (default 3, 5, 10, 20, 40 mm), every *physics* the
//! data is made with (`bonded-layer` at that thickness — what a scene's `[physics]
//! model` renders — and the `half-space` reference), every *camera effect set* and
//! every *load*, the forces are reconstructed by each configured solver kind (default
//! `tikhonov`, λ by GCV) inverting each *solver model*: the half-space (`[elastomer]
//! model = "half-space"`, the paper's) and the bonded layer of the same thickness
//! (`"bonded-layer"`). A row is *matched* when the solver model is the physics.
//!
//! **Marker depths.** The sensor's layers keep their depths while the deepest lies
//! within `max_depth_fraction · h` (default 0.5); otherwise every depth is scaled by the
//! same factor so that the deepest sits at `max_depth_fraction · h` (the paper's
//! 3 / 6 mm markers stay at 20 and 40 mm, become 2.5 / 5 mm at 10 mm, and 0.75 / 1.5 mm
//! in a 3 mm gel, inside the 0.5–2 mm of today's thin gels). The depths of each row are
//! in the CSV.
//!
//! **Loads** (the paper's Fig. 6 load, the one its accuracy simulation uses, spread
//! equally over the 4 × 4 force points (4, 3)–(7, 6) of the 10 × 8 grid, see
//! [`paper_fig6_load`]): `normal` = its 100 gf along z, `tangential` = its 50 gf along
//! y, `mixed` = both (the paper's load itself).
//!
//! **Camera effect sets** ([`EffectSet`]): `none` = no camera: the marker displacements
//! of the forward model ([`crate::model::forward`] with the physics' model) at the
//! nominal marker positions, the load on the force nodes exactly (so with the matched
//! solver only regularisation is left, and every other error is model error);
//! `ideal` = the full pipeline with no effect; any other set names scene effects
//! (`kind`s of a scene's `[[effects]]`, joined by `+`), whose parameters are taken from
//! a base scene file's `[[effects]]` tables and parsed by the scene's own parser
//! ([`crate::sim::scene`]), so every effect a scene accepts works here, including ones
//! added later. Pipeline sets render → track → solve: the scene (built by the study:
//! the sensor at the row's thickness, `[physics] model`, the selected effects) renders
//! the reference frame and `realisations` loaded frames (frame `k` draws its seeded
//! noise from stream `k`), the per-window tracker measures them, and the solver uses
//! the markers tracked ok in every frame at their nominal positions. A scene load is a
//! contact, so the pipeline's load is the paper's 5 mm flat cylindrical probe (its
//! Fig. 4 and 8) centred on the Fig. 6 patch, 100 gf normal (`normal`) plus 50 gf along
//! +y (`mixed`); its truth is the contact traction integrated over each node's cell
//! ([`Contact::force_grid_n`]), which adds the point-force discretisation error. A
//! contact cannot carry a tangential load without a normal one (Coulomb friction), so
//! `tangential` pipeline rows are reported as refused. The CSV's `data` column says
//! which path (`forward` or `pipeline`) made each row.
//!
//! # Errors (relative; `f` reconstructed, `f*` true node forces, N)
//!
//! - **field error** `‖f − f*‖₂ / ‖f*‖₂` over all nodes and axes, and per axis
//!   `field_error_a = ‖f_a − f*_a‖₂ / ‖f*‖₂` (normalised by the whole field, so an axis
//!   that carries no load still has a finite error; `Σ_a field_error_a² =
//!   field_error²`);
//! - **F_sum error** `|ΣF − F_applied| / |F_applied|` (the total force vector, paper
//!   Sec. IV-B-2) and per axis, signed, `sum_error_a = (ΣF_a − F_applied,a) /
//!   |F_applied|` (negative = underestimate);
//! - **mean |f − f*|**, gf: the paper's Fig. 6 metric, averaged over nodes and axes.
//!
//! Over several realisations (pipeline rows), field and F_sum errors are root mean
//! squares, the signed per-axis F_sum errors and the mean |f − f*| are means.
//!
//! # Time
//!
//! - **build**: `t_h` = building `H` for the sensor's full marker set (for the bonded
//!   layer this includes the Hankel tables, measured cold: the operators of a thickness
//!   are built before any data of that thickness is made, because the tables are
//!   cached process-wide), `t_precompute` = the solver's precompute on `H` (SVD and
//!   automatic λ / rank on the row's first frame); `t_build = t_h + t_precompute`. The
//!   dense solvers of a pipeline row use the rows of the full `H` for the tracked
//!   markers. A Fourier solver builds its own operator: its `t_build` is its whole
//!   precompute and `t_h` is empty.
//! - **per frame**: `t_solve` = one `FrameSolver::apply`, `t_track` = tracking one frame
//!   (pipeline rows), `t_frame = t_track + t_solve`; wall-clock medians over `reps`
//!   repetitions, each right after an untimed one; the rows of one data set (both
//!   solver models, every solver kind) are timed round-robin, so a change of machine
//!   load hits them alike.
//!
//! A solver that refuses a problem (e.g. `fourier` on grids it cannot represent, or on
//! a bonded-layer sensor before it learns the layer kernel) gives a row with status
//! `refused` and the solver's reason, not a missing row.
//!
//! The library does not print: progress is reported through a callback
//! ([`ModelErrorEvent`]).

mod cases;
mod output;
mod solving;

use std::path::{Path, PathBuf};
use std::time::Instant;

use nalgebra::DMatrix;
use thiserror::Error;

use super::accuracy_time::median;
use super::layer_separation::paper_fig6_load;
use crate::model::{self, ForwardModel, MarkerSite};
use crate::sensor::{ModelKind, Sensor};
use crate::sim::render::{to_rgb16, to_rgb8};
use crate::sim::rng::Rng;
use crate::sim::scene::{Scene, SceneError};
use crate::sim::simulate::Simulation;
use crate::solve::dense::DenseSolver;
use crate::solve::{self, FrameSolver, Method, Problem, SolverConfig};
use crate::units;
use crate::vision::{detect, DetectConfig, Frame, MarkerStatus, TrackConfig, TrackMode, Tracker};

#[cfg(test)]
use cases::patch_centre_mm;
use cases::{make_data, Data};
pub use cases::{sensor_at_thickness, CameraEffects};
pub use output::MODEL_ERROR_COLUMNS;
use solving::{build_operators, solve_row, time_group};

/// The default thicknesses, mm.
pub const DEFAULT_THICKNESSES_MM: [f64; 5] = [3.0, 5.0, 10.0, 20.0, 40.0];
/// Largest number of timing repetitions.
pub const MAX_REPS: usize = 100_000;
/// Largest number of pipeline realisations.
pub const MAX_REALISATIONS: usize = 64;
/// Largest number of thicknesses.
pub const MAX_THICKNESSES: usize = 64;
/// Diameter of the pipeline's flat probe, mm (the paper's Fig. 4 and 8 cylinder).
pub const PROBE_DIAMETER_MM: f64 = 5.0;

/// The camera of the default base scene: the Table I camera of
/// `experiments/scenes/study_hemisphere_noisy.toml` (8-bit, pixel noise σ = 2 levels).
pub const DEFAULT_CAMERA_SCENE: &str =
    "# Default camera effects of `tactbench study model-error`: the Table I camera
# (pixel noise sigma = 2 of 255 levels, seeded, then 8-bit quantisation).
[[effects]]
kind = \"pixel_noise\"
sigma_8bit = 2.0
seed = 7

[[effects]]
kind = \"quantize8\"
";

/// An error of the model-error study (invalid options or inputs; a solver refusing a
/// problem is a row, not an error).
#[derive(Debug, Error)]
pub enum ModelErrorStudyError {
    /// An option is out of range.
    #[error("invalid model-error option: {0}")]
    InvalidOption(String),
    /// The sensor does not fit the study.
    #[error("sensor: {0}")]
    Sensor(String),
    /// The base scene (camera effects) is invalid.
    #[error("{path}: {message}")]
    Effects {
        /// The base scene file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A scene the study built could not be parsed (an effect's parameters).
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// The forward model could not be evaluated.
    #[error("forward model: {0}")]
    Model(#[from] model::ModelError),
    /// Writing a result file failed.
    #[error("{path}: {message}")]
    Write {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
}

/// One load of the study (parts of the paper's Fig. 6 load).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LoadKind {
    /// 100 gf along z.
    Normal,
    /// 50 gf along y.
    Tangential,
    /// 100 gf along z and 50 gf along y (the paper's).
    Mixed,
}

impl LoadKind {
    /// All loads, in report order.
    pub const ALL: [LoadKind; 3] = [LoadKind::Normal, LoadKind::Tangential, LoadKind::Mixed];

    /// Name on the command line and in the CSV.
    pub fn name(self) -> &'static str {
        match self {
            LoadKind::Normal => "normal",
            LoadKind::Tangential => "tangential",
            LoadKind::Mixed => "mixed",
        }
    }

    /// The load's node forces on `sensor`'s force grid (interleaved fx, fy, fz, N).
    pub fn node_forces(self, sensor: &Sensor) -> Result<Vec<f64>, ModelErrorStudyError> {
        let mut f = paper_fig6_load(&sensor.force_grid)
            .map_err(|e| ModelErrorStudyError::Sensor(e.to_string()))?;
        for (i, v) in f.iter_mut().enumerate() {
            let keep = match self {
                LoadKind::Normal => i % 3 == 2,
                LoadKind::Tangential => i % 3 == 1,
                LoadKind::Mixed => true,
            };
            if !keep {
                *v = 0.0;
            }
        }
        Ok(f)
    }
}

impl std::str::FromStr for LoadKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        LoadKind::ALL
            .into_iter()
            .find(|l| l.name() == s)
            .ok_or_else(|| format!("unknown load `{s}`: expected normal, tangential or mixed"))
    }
}

/// One entry of the camera-effect axis.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum EffectSet {
    /// `none`: no camera, forward-model marker displacements.
    Forward,
    /// Render → track → solve with these scene effect kinds (empty: `ideal`).
    Pipeline(Vec<String>),
}

impl EffectSet {
    /// Label: `none`, `ideal`, or the kinds joined by `+`.
    pub fn label(&self) -> String {
        match self {
            EffectSet::Forward => "none".into(),
            EffectSet::Pipeline(k) if k.is_empty() => "ideal".into(),
            EffectSet::Pipeline(k) => k.join("+"),
        }
    }

    /// The data path of this set.
    pub fn data(&self) -> DataPath {
        match self {
            EffectSet::Forward => DataPath::Forward,
            EffectSet::Pipeline(_) => DataPath::Pipeline,
        }
    }
}

impl std::str::FromStr for EffectSet {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim() {
            "none" => Ok(EffectSet::Forward),
            "ideal" => Ok(EffectSet::Pipeline(Vec::new())),
            "" => Err("empty effect set: expected none, ideal or effect kinds joined by +".into()),
            t => {
                let mut kinds: Vec<String> = Vec::new();
                for k in t.split('+').map(str::trim) {
                    if k.is_empty()
                        || !k
                            .chars()
                            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
                    {
                        return Err(format!(
                            "effect set `{t}`: `{k}` is not an effect kind (lower-case scene \
                             effect kinds such as pixel_noise, joined by +; or none, ideal)"
                        ));
                    }
                    if k == "none" || k == "ideal" {
                        return Err(format!(
                            "effect set `{t}`: `{k}` stands alone, it cannot be combined with +"
                        ));
                    }
                    if kinds.iter().any(|x| x == k) {
                        return Err(format!("effect set `{t}`: `{k}` is listed twice"));
                    }
                    kinds.push(k.to_string());
                }
                Ok(EffectSet::Pipeline(kinds))
            }
        }
    }
}

/// Which path made a row's data.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DataPath {
    /// Forward-model marker displacements, nodal load.
    Forward,
    /// Rendered frames, tracked (contact load).
    Pipeline,
}

impl DataPath {
    /// Name in the CSV.
    pub fn name(self) -> &'static str {
        match self {
            DataPath::Forward => "forward",
            DataPath::Pipeline => "pipeline",
        }
    }
}

/// Options of [`run_model_error`].
#[derive(Debug, Clone, PartialEq)]
pub struct ModelErrorOptions {
    /// Elastomer thicknesses, mm (distinct, > 0).
    pub thicknesses_mm: Vec<f64>,
    /// What the data is made with.
    pub physics: Vec<ModelKind>,
    /// What the solvers invert.
    pub solver_models: Vec<ModelKind>,
    /// Solver kinds (each with its λ / rank choice).
    pub solvers: Vec<SolverConfig>,
    /// Loads.
    pub loads: Vec<LoadKind>,
    /// The camera-effect axis.
    pub effects: Vec<EffectSet>,
    /// Deepest marker at most this fraction of the thickness (0, 1].
    pub max_depth_fraction: f64,
    /// Timing repetitions per row (median), ≥ 1.
    pub reps: usize,
    /// Loaded frames per pipeline data set (errors RMS over them), ≥ 1.
    pub realisations: usize,
    /// Gaussian noise added to the forward path's displacements, px (σ per component,
    /// converted with the camera's mm/px; 0 = exact data).
    pub noise_px: f64,
    /// Seed of that noise.
    pub seed: u64,
}

impl Default for ModelErrorOptions {
    /// The defaults of `tactbench study model-error` (see the module docs).
    fn default() -> Self {
        ModelErrorOptions {
            thicknesses_mm: DEFAULT_THICKNESSES_MM.to_vec(),
            physics: vec![ModelKind::BondedLayer, ModelKind::HalfSpace],
            solver_models: vec![ModelKind::HalfSpace, ModelKind::BondedLayer],
            solvers: vec![SolverConfig {
                method: Method::Tikhonov,
                ..SolverConfig::default()
            }],
            loads: LoadKind::ALL.to_vec(),
            effects: vec![
                EffectSet::Forward,
                EffectSet::Pipeline(Vec::new()),
                EffectSet::Pipeline(vec!["pixel_noise".into(), "quantize8".into()]),
            ],
            max_depth_fraction: 0.5,
            reps: 30,
            realisations: 4,
            noise_px: 0.0,
            seed: 14,
        }
    }
}

impl ModelErrorOptions {
    fn validate(&self) -> Result<(), ModelErrorStudyError> {
        let bad = |m: String| Err(ModelErrorStudyError::InvalidOption(m));
        if self.thicknesses_mm.is_empty() || self.thicknesses_mm.len() > MAX_THICKNESSES {
            return bad(format!(
                "give 1 to {MAX_THICKNESSES} thicknesses, got {}",
                self.thicknesses_mm.len()
            ));
        }
        for (i, h) in self.thicknesses_mm.iter().enumerate() {
            if !(h.is_finite() && *h > 0.0) {
                return bad(format!("thickness {h} mm must be a finite number > 0"));
            }
            if self.thicknesses_mm[..i].contains(h) {
                return bad(format!("thickness {h} mm is listed twice"));
            }
        }
        if self.physics.is_empty()
            || self.solver_models.is_empty()
            || self.solvers.is_empty()
            || self.loads.is_empty()
            || self.effects.is_empty()
        {
            return bad(
                "physics, solver models, solvers, loads and effects need at least one entry each"
                    .into(),
            );
        }
        if self.reps == 0 || self.reps > MAX_REPS {
            return bad(format!("reps = {} must be in 1..={MAX_REPS}", self.reps));
        }
        if self.realisations == 0 || self.realisations > MAX_REALISATIONS {
            return bad(format!(
                "realisations = {} must be in 1..={MAX_REALISATIONS}",
                self.realisations
            ));
        }
        if !(self.noise_px.is_finite() && self.noise_px >= 0.0) {
            return bad(format!(
                "noise {} px must be a finite number >= 0",
                self.noise_px
            ));
        }
        if !(self.max_depth_fraction.is_finite()
            && self.max_depth_fraction > 0.0
            && self.max_depth_fraction <= 1.0)
        {
            return bad(format!(
                "max depth fraction {} must be in (0, 1]",
                self.max_depth_fraction
            ));
        }
        Ok(())
    }
}

/// A row's outcome.
#[derive(Debug, Clone, PartialEq)]
pub enum RowStatus {
    /// Measured.
    Ok,
    /// The solver refused the problem, or the data could not be made; the reason.
    Refused(String),
}

/// The errors of one reconstruction (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ForceErrors {
    /// `‖f − f*‖ / ‖f*‖`.
    pub field: f64,
    /// Per axis, normalised by `‖f*‖`.
    pub field_axis: [f64; 3],
    /// `|ΣF − F_applied| / |F_applied|`.
    pub sum: f64,
    /// Per axis, signed, normalised by `|F_applied|`.
    pub sum_axis: [f64; 3],
    /// Mean |f − f*| over nodes and axes, gf.
    pub mean_abs_gf: f64,
    /// `ΣF`, N.
    pub fsum_n: [f64; 3],
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

/// The errors of `f_n` against `truth_n` (both interleaved fx, fy, fz per node, N) and
/// the applied total force.
pub fn force_errors(f_n: &[f64], truth_n: &[f64], applied_n: [f64; 3]) -> ForceErrors {
    let mut fsum = [0.0; 3];
    let mut d2 = [0.0; 3];
    let mut abs = 0.0;
    for (i, (a, b)) in f_n.iter().zip(truth_n).enumerate() {
        fsum[i % 3] += a;
        d2[i % 3] += (a - b) * (a - b);
        abs += (a - b).abs();
    }
    let tn = norm(truth_n);
    let an = norm(&applied_n);
    let sum_axis: [f64; 3] = std::array::from_fn(|a| (fsum[a] - applied_n[a]) / an);
    ForceErrors {
        field: (d2[0] + d2[1] + d2[2]).sqrt() / tn,
        field_axis: d2.map(|v| v.sqrt() / tn),
        sum: norm(&sum_axis),
        sum_axis,
        mean_abs_gf: units::n_to_gf(abs / f_n.len().max(1) as f64),
        fsum_n: fsum,
    }
}

/// One row of `model_error.csv`.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelErrorRow {
    /// Elastomer thickness, mm.
    pub thickness_mm: f64,
    /// Marker layer depths used at this thickness, mm.
    pub depths_mm: Vec<f64>,
    /// What made the data.
    pub physics: ModelKind,
    /// What the solver inverts.
    pub solver_model: ModelKind,
    /// The solver kind.
    pub solver: Method,
    /// The load.
    pub load: LoadKind,
    /// The camera-effect set's label.
    pub effects: String,
    /// Which path made the data.
    pub data: DataPath,
    /// Outcome.
    pub status: RowStatus,
    /// Applied total force, N (NaN when the data could not be made).
    pub applied_n: [f64; 3],
    /// Errors (field and F_sum RMS over realisations; signed F_sum per axis and mean
    /// |f − f*| averaged); NaN when refused.
    pub errors: ForceErrors,
    /// Markers used / in the sensor's grids.
    pub markers_used: (usize, usize),
    /// Realisations the errors are over.
    pub realisations: usize,
    /// `H` build for the full marker set, s (dense solvers).
    pub t_h_s: Option<f64>,
    /// Solver precompute on `H`, s (the whole precompute for fourier).
    pub t_precompute_s: f64,
    /// `t_h + t_precompute`, s.
    pub t_build_s: f64,
    /// Tracking one frame, s (pipeline rows; median).
    pub t_track_s: Option<f64>,
    /// One solve, s (median).
    pub t_solve_s: f64,
    /// `t_track + t_solve`, s.
    pub t_frame_s: f64,
    /// λ in use, mm/N.
    pub lambda: Option<f64>,
    /// Rank in use.
    pub rank: Option<usize>,
    /// Condition number of `H`.
    pub condition_number: f64,
}

impl ModelErrorRow {
    /// A row with every measured value unset (NaN / None), status ok: filled in by
    /// the solve and the timing. `(physics, solver model, solver)` name its cell.
    fn blank(
        thickness_mm: f64,
        depths_mm: Vec<f64>,
        (physics, solver_model, solver): (ModelKind, ModelKind, Method),
        load: LoadKind,
        set: &EffectSet,
        markers: usize,
    ) -> ModelErrorRow {
        ModelErrorRow {
            thickness_mm,
            depths_mm,
            physics,
            solver_model,
            solver,
            load,
            effects: set.label(),
            data: set.data(),
            status: RowStatus::Ok,
            applied_n: [f64::NAN; 3],
            errors: ForceErrors {
                field: f64::NAN,
                field_axis: [f64::NAN; 3],
                sum: f64::NAN,
                sum_axis: [f64::NAN; 3],
                mean_abs_gf: f64::NAN,
                fsum_n: [f64::NAN; 3],
            },
            markers_used: (0, markers),
            realisations: 0,
            t_h_s: None,
            t_precompute_s: f64::NAN,
            t_build_s: f64::NAN,
            t_track_s: None,
            t_solve_s: f64::NAN,
            t_frame_s: f64::NAN,
            lambda: None,
            rank: None,
            condition_number: f64::NAN,
        }
    }

    /// The solver inverts the model that made the data.
    pub fn matched(&self) -> bool {
        self.physics == self.solver_model
    }

    /// Measured (not refused).
    pub fn is_ok(&self) -> bool {
        self.status == RowStatus::Ok
    }
}

/// Everything the study measured.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelErrorResult {
    /// Rows: by thickness, physics, effect set, load, solver model, solver kind.
    pub rows: Vec<ModelErrorRow>,
    /// The options used.
    pub options: ModelErrorOptions,
    /// The sensor's force-grid pitch, mm.
    pub force_pitch_mm: f64,
}

/// Progress of [`run_model_error`].
#[derive(Debug)]
pub enum ModelErrorEvent<'a> {
    /// The operators `H` of one thickness and solver model were built (cold).
    Operator {
        /// Thickness, mm.
        thickness_mm: f64,
        /// The solver model.
        model: ModelKind,
        /// Build time, s (NaN when it failed).
        seconds: f64,
    },
    /// One data set (thickness, physics, effect set, load) was solved by every solver.
    Group {
        /// Data sets done.
        done: usize,
        /// Data sets in all.
        total: usize,
        /// Its rows.
        rows: &'a [ModelErrorRow],
    },
}

/// Runs the study on `base` (a sensor with two marker layers and a force grid of at
/// least 7 × 6 nodes; its thickness and model are replaced per row).
pub fn run_model_error(
    base: &Sensor,
    camera: &CameraEffects,
    options: &ModelErrorOptions,
    progress: &mut dyn FnMut(ModelErrorEvent<'_>),
) -> Result<ModelErrorResult, ModelErrorStudyError> {
    options.validate()?;
    camera.validate(base, &options.effects)?;
    // Fails early on a grid too small for the paper's load.
    LoadKind::Mixed.node_forces(base)?;
    let total = options.thicknesses_mm.len()
        * options.physics.len()
        * options.effects.len()
        * options.loads.len();
    check_layers(base, options)?;
    let mut done = 0;
    let mut rows = Vec::new();
    for &h in &options.thicknesses_mm {
        let sensor_h = sensor_at_thickness(base, h, options.max_depth_fraction)?;
        let sites = MarkerSite::from_sensor_grids(&sensor_h);
        if sites.is_empty() {
            return Err(ModelErrorStudyError::Sensor(
                "the sensor has no marker grids (`[layers.markers]`)".into(),
            ));
        }
        let points = sensor_h.force_points_mm();
        // The operators first, while this thickness's layer tables are cold.
        let operators = build_operators(&sensor_h, &sites, &points, h, options, progress);
        let depths: Vec<f64> = sensor_h.layers.iter().map(|l| l.depth_mm).collect();
        for &physics in &options.physics {
            for set in &options.effects {
                for &load in &options.loads {
                    let data = make_data(&sensor_h, &sites, camera, set, physics, load, options);
                    let mut group: Vec<(ModelErrorRow, Option<Box<dyn FrameSolver>>)> = Vec::new();
                    for (m, s, op) in &operators {
                        for config in &options.solvers {
                            let mut row = ModelErrorRow::blank(
                                h,
                                depths.clone(),
                                (physics, *m, config.method),
                                load,
                                set,
                                sites.len(),
                            );
                            let solver = match &data {
                                Err(reason) => {
                                    row.status = RowStatus::Refused(reason.clone());
                                    None
                                }
                                Ok(d) => match solve_row(&mut row, s, &sites, op, d, config) {
                                    Ok(solver) => Some(solver),
                                    Err(reason) => {
                                        row.status = RowStatus::Refused(reason);
                                        None
                                    }
                                },
                            };
                            group.push((row, solver));
                        }
                    }
                    if let Ok(d) = &data {
                        time_group(&mut group, d, options.reps);
                    }
                    let first = rows.len();
                    rows.extend(group.into_iter().map(|(r, _)| r));
                    done += 1;
                    progress(ModelErrorEvent::Group {
                        done,
                        total,
                        rows: &rows[first..],
                    });
                }
            }
        }
    }
    Ok(ModelErrorResult {
        rows,
        options: options.clone(),
        force_pitch_mm: base.force_grid.pitch_mm,
    })
}

/// Checks every thickness's bonded layer before any work: a layer too thin for the
/// sensor's distances (a table of 1e19 Bessel evaluations at 1 µm) is an error naming
/// it, not hours of work or an abort allocating terabytes.
fn check_layers(base: &Sensor, options: &ModelErrorOptions) -> Result<(), ModelErrorStudyError> {
    let layer_wanted = options.physics.contains(&ModelKind::BondedLayer)
        || options.solver_models.contains(&ModelKind::BondedLayer);
    if !layer_wanted {
        return Ok(());
    }
    for &h in &options.thicknesses_mm {
        let sensor_h = sensor_at_thickness(base, h, options.max_depth_fraction)?;
        let layer = ForwardModel::of_kind(ModelKind::BondedLayer, &sensor_h.elastomer);
        let sites = MarkerSite::from_sensor_grids(&sensor_h);
        model::check_reach_for(&layer, &sites, &sensor_h.force_points_mm())?;
        if options.physics.contains(&ModelKind::BondedLayer)
            && options
                .effects
                .iter()
                .any(|e| !matches!(e, EffectSet::Forward))
        {
            crate::sim::scene::check_physics(ModelKind::BondedLayer, &sensor_h)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sensor::paper_sensor;

    #[test]
    fn force_errors_of_a_known_field_per_axis() {
        // Truth (0,0,1),(0,1,1); reconstruction (0.1,0,1),(0,0.8,1.2).
        let truth = [0.0, 0.0, 1.0, 0.0, 1.0, 1.0];
        let f = [0.1, 0.0, 1.0, 0.0, 0.8, 1.2];
        let e = force_errors(&f, &truth, [0.0, 1.0, 2.0]);
        let tn = 3f64.sqrt();
        assert!((e.field_axis[0] - 0.1 / tn).abs() < 1e-12);
        assert!((e.field_axis[1] - 0.2 / tn).abs() < 1e-12);
        assert!((e.field_axis[2] - 0.2 / tn).abs() < 1e-12);
        let f2: f64 = e.field_axis.iter().map(|v| v * v).sum();
        assert!((e.field - f2.sqrt()).abs() < 1e-12);
        // ΣF = (0.1, 0.8, 2.2) against (0, 1, 2): signed per axis over |F| = √5.
        let an = 5f64.sqrt();
        assert!((e.sum_axis[0] - 0.1 / an).abs() < 1e-12);
        assert!((e.sum_axis[1] + 0.2 / an).abs() < 1e-12);
        assert!((e.sum_axis[2] - 0.2 / an).abs() < 1e-12);
        assert!((e.sum - (0.09f64).sqrt() / an).abs() < 1e-12);
        assert!((e.mean_abs_gf - units::n_to_gf(0.5 / 6.0)).abs() < 1e-9);
    }

    #[test]
    fn loads_are_the_parts_of_the_fig6_load() {
        let s = paper_sensor();
        let total = |l: LoadKind, a: usize| {
            units::n_to_gf(l.node_forces(&s).unwrap().iter().skip(a).step_by(3).sum())
        };
        assert!((total(LoadKind::Normal, 2) - 100.0).abs() < 1e-9);
        assert_eq!(total(LoadKind::Normal, 1), 0.0);
        assert!((total(LoadKind::Tangential, 1) - 50.0).abs() < 1e-9);
        assert_eq!(total(LoadKind::Tangential, 2), 0.0);
        assert!((total(LoadKind::Mixed, 1) - 50.0).abs() < 1e-9);
        assert!((total(LoadKind::Mixed, 2) - 100.0).abs() < 1e-9);
        let c = patch_centre_mm(&s);
        assert!(
            (c[0] - 9.0).abs() < 1e-12 && (c[1] - 6.75).abs() < 1e-12,
            "{c:?}"
        );
    }

    #[test]
    fn marker_depths_scale_only_when_the_layer_is_too_thin() {
        let s = paper_sensor();
        let at = |h| {
            sensor_at_thickness(&s, h, 0.5)
                .unwrap()
                .layers
                .iter()
                .map(|l| l.depth_mm)
                .collect::<Vec<_>>()
        };
        assert_eq!(at(40.0), vec![3.0, 6.0]);
        assert_eq!(at(12.0), vec![3.0, 6.0]);
        assert_eq!(at(10.0), vec![2.5, 5.0]);
        assert_eq!(at(3.0), vec![0.75, 1.5]);
        assert_eq!(
            sensor_at_thickness(&s, 3.0, 0.5)
                .unwrap()
                .elastomer
                .thickness_mm,
            3.0
        );
        assert!(sensor_at_thickness(&s, 0.0, 0.5).is_err());
        assert!(sensor_at_thickness(&s, 3.0, 1.5).is_err());
    }

    #[test]
    fn effect_sets_parse_and_refuse_malformed_lists() {
        assert_eq!("none".parse::<EffectSet>().unwrap(), EffectSet::Forward);
        assert_eq!(
            "ideal".parse::<EffectSet>().unwrap(),
            EffectSet::Pipeline(vec![])
        );
        let s: EffectSet = "perspective+refraction".parse().unwrap();
        assert_eq!(s.label(), "perspective+refraction");
        assert_eq!(s.data(), DataPath::Pipeline);
        for bad in ["", "a++b", "none+pixel_noise", "Pixel", "x+x", "a b"] {
            assert!(bad.parse::<EffectSet>().is_err(), "{bad:?}");
        }
    }

    #[test]
    fn default_camera_parses_and_selects_by_kind_in_file_order() {
        let c = CameraEffects::default_camera();
        assert_eq!(c.kinds(), vec!["pixel_noise", "quantize8"]);
        let t = c
            .select(&["quantize8".into(), "pixel_noise".into()])
            .unwrap();
        assert_eq!(t[0]["kind"].as_str(), Some("pixel_noise"));
        let e = c.select(&["perspective".into()]).unwrap_err().to_string();
        assert!(
            e.contains("perspective") && e.contains("pixel_noise, quantize8"),
            "{e}"
        );
        c.validate(
            &paper_sensor(),
            &[EffectSet::Pipeline(vec!["pixel_noise".into()])],
        )
        .unwrap();
    }

    #[test]
    fn effects_go_through_the_scene_parser() {
        let text = "[[effects]]\nkind = \"pixel_noise\"\nsigma_8bit = 2.0\n";
        let c = CameraEffects::from_scene_text(text, Path::new("base.toml")).unwrap();
        // Missing seed: the scene parser's own message, naming the base file.
        let e = c
            .validate(
                &paper_sensor(),
                &[EffectSet::Pipeline(vec!["pixel_noise".into()])],
            )
            .unwrap_err()
            .to_string();
        assert!(e.contains("base.toml") && e.contains("seed"), "{e}");
        let c = CameraEffects::from_scene_text(
            "[[effects]]\nkind = \"no_such_effect\"\n",
            Path::new("base.toml"),
        )
        .unwrap();
        let e = c
            .validate(
                &paper_sensor(),
                &[EffectSet::Forward, EffectSet::Pipeline(vec![])],
            )
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("base.toml") && e.contains("no_such_effect"),
            "{e}"
        );
        // Only the forward path: the effects are not needed, nothing to validate.
        c.validate(&paper_sensor(), &[EffectSet::Forward]).unwrap();
    }
}
