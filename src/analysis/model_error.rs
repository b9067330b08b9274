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

/// The camera effects available to the effect axis: the `[[effects]]` tables (and the
/// `pixel_filter`) of a base scene file, in the file's order.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraEffects {
    /// The file they came from (for messages; `(default camera)` for the built-in).
    pub source: PathBuf,
    /// `pixel_filter`, when the file sets it.
    pub pixel_filter: Option<String>,
    /// The effect tables, each with its `kind`.
    pub tables: Vec<toml::Table>,
}

impl CameraEffects {
    /// The built-in default ([`DEFAULT_CAMERA_SCENE`]).
    pub fn default_camera() -> Self {
        // A constant of this module, covered by a test.
        Self::from_scene_text(DEFAULT_CAMERA_SCENE, Path::new("(default camera)")).unwrap_or_else(
            |_| CameraEffects {
                source: PathBuf::from("(default camera)"),
                pixel_filter: None,
                tables: Vec::new(),
            },
        )
    }

    /// The effects of scene TOML text (`path` for messages). Only `[[effects]]` and
    /// `pixel_filter` are read; every other key (sensor, indenter, load, …) is replaced
    /// by the study's. Each table must have a string `kind`; its other keys are checked
    /// by the scene parser when the study builds its scenes ([`Self::validate`]).
    pub fn from_scene_text(text: &str, path: &Path) -> Result<Self, ModelErrorStudyError> {
        let err = |message: String| ModelErrorStudyError::Effects {
            path: path.to_path_buf(),
            message,
        };
        let table: toml::Table = text.parse().map_err(|e: toml::de::Error| {
            err(format!("not valid TOML: {}", e.to_string().trim_end()))
        })?;
        let pixel_filter = match table.get("pixel_filter") {
            None => None,
            Some(toml::Value::String(s)) => Some(s.clone()),
            Some(v) => return Err(err(format!("pixel_filter = {v} must be a string"))),
        };
        let mut tables = Vec::new();
        match table.get("effects") {
            None => {}
            Some(toml::Value::Array(a)) => {
                for (i, v) in a.iter().enumerate() {
                    let Some(t) = v.as_table() else {
                        return Err(err(format!("effects[{i}] must be a table ([[effects]])")));
                    };
                    match t.get("kind") {
                        Some(toml::Value::String(_)) => tables.push(t.clone()),
                        _ => {
                            return Err(err(format!(
                                "effects[{i}] needs kind = \"<effect kind>\" (a string)"
                            )))
                        }
                    }
                }
            }
            Some(_) => {
                return Err(err(
                    "effects must be an array of tables ([[effects]])".into()
                ))
            }
        }
        Ok(CameraEffects {
            source: path.to_path_buf(),
            pixel_filter,
            tables,
        })
    }

    /// Reads a base scene file.
    pub fn from_path(path: &Path) -> Result<Self, ModelErrorStudyError> {
        let text = std::fs::read_to_string(path).map_err(|e| ModelErrorStudyError::Effects {
            path: path.to_path_buf(),
            message: format!("cannot read: {e}"),
        })?;
        Self::from_scene_text(&text, path)
    }

    /// The effect kinds available, in file order (a kind may appear more than once).
    pub fn kinds(&self) -> Vec<String> {
        self.tables
            .iter()
            .filter_map(|t| t.get("kind").and_then(|k| k.as_str()).map(String::from))
            .collect()
    }

    /// The tables of the listed kinds, in the file's order; an error names a kind the
    /// file does not have.
    pub fn select(&self, kinds: &[String]) -> Result<Vec<toml::Table>, ModelErrorStudyError> {
        let have = self.kinds();
        if let Some(k) = kinds.iter().find(|k| !have.contains(k)) {
            return Err(ModelErrorStudyError::Effects {
                path: self.source.clone(),
                message: format!(
                    "effect `{k}` is not among the scene's [[effects]] (it has: {}); add a \
                     [[effects]] table with kind = \"{k}\" and its parameters (see the scene.toml \
                     docs) and pass the file with --scene",
                    if have.is_empty() {
                        "none".to_string()
                    } else {
                        have.join(", ")
                    }
                ),
            });
        }
        Ok(self
            .tables
            .iter()
            .filter(|t| {
                t.get("kind")
                    .and_then(|k| k.as_str())
                    .is_some_and(|k| kinds.iter().any(|x| x == k))
            })
            .cloned()
            .collect())
    }

    /// Checks every effect table through the scene parser on `sensor` (errors name the
    /// base file and the effect's index in it), and that every kind of `sets` exists.
    pub fn validate(
        &self,
        sensor: &Sensor,
        sets: &[EffectSet],
    ) -> Result<(), ModelErrorStudyError> {
        for s in sets {
            if let EffectSet::Pipeline(k) = s {
                self.select(k)?;
            }
        }
        if sets.iter().any(|s| matches!(s, EffectSet::Pipeline(_))) {
            pipeline_scene(
                self,
                &self.tables,
                sensor.clone(),
                ModelKind::HalfSpace,
                LoadKind::Normal,
            )?;
        }
        Ok(())
    }
}

/// Where the pipeline's probe is centred: the centre of the Fig. 6 patch (nodes
/// `ix ∈ 3..=6, iy ∈ 2..=5`), mm.
fn patch_centre_mm(sensor: &Sensor) -> [f64; 2] {
    let g = &sensor.force_grid;
    [
        g.origin_mm[0] + 4.5 * g.pitch_mm,
        g.origin_mm[1] + 3.5 * g.pitch_mm,
    ]
}

/// The scene of a pipeline data set (see the module docs): `effects` through the
/// scene's own parser, errors naming the base scene file.
fn pipeline_scene(
    camera: &CameraEffects,
    effects: &[toml::Table],
    sensor: Sensor,
    physics: ModelKind,
    load: LoadKind,
) -> Result<Scene, ModelErrorStudyError> {
    use toml::Value;
    let c = patch_centre_mm(&sensor);
    let mut t = toml::Table::new();
    t.insert("sensor".into(), Value::String("(model-error study)".into()));
    if let Some(p) = &camera.pixel_filter {
        t.insert("pixel_filter".into(), Value::String(p.clone()));
    }
    let mut ind = toml::Table::new();
    ind.insert("kind".into(), Value::String("flat".into()));
    ind.insert("diameter_mm".into(), Value::Float(PROBE_DIAMETER_MM));
    t.insert("indenter".into(), Value::Table(ind));
    let mut l = toml::Table::new();
    l.insert(
        "position_mm".into(),
        Value::Array(vec![Value::Float(c[0]), Value::Float(c[1])]),
    );
    l.insert("normal_force_gf".into(), Value::Float(100.0));
    if load == LoadKind::Mixed {
        l.insert("tangential_force_gf".into(), Value::Float(50.0));
        l.insert("direction_deg".into(), Value::Float(90.0));
    }
    t.insert("load".into(), Value::Table(l));
    let mut p = toml::Table::new();
    p.insert("model".into(), Value::String(physics.name().into()));
    t.insert("physics".into(), Value::Table(p));
    t.insert(
        "effects".into(),
        Value::Array(effects.iter().cloned().map(Value::Table).collect()),
    );
    let text = toml::to_string(&t).map_err(|e| ModelErrorStudyError::Effects {
        path: camera.source.clone(),
        message: format!("cannot write the study's scene: {e}"),
    })?;
    Ok(Scene::from_toml_str(&text, &camera.source, sensor)?)
}

/// `base` at thickness `h` (mm) with its marker depths scaled, when needed, so that the
/// deepest lies at `max_depth_fraction · h` (see the module docs). The solver model is
/// left as in `base`.
pub fn sensor_at_thickness(
    base: &Sensor,
    h: f64,
    max_depth_fraction: f64,
) -> Result<Sensor, ModelErrorStudyError> {
    if !(h.is_finite() && h > 0.0) {
        return Err(ModelErrorStudyError::InvalidOption(format!(
            "thickness {h} mm must be a finite number > 0"
        )));
    }
    if !(max_depth_fraction.is_finite() && max_depth_fraction > 0.0 && max_depth_fraction <= 1.0) {
        return Err(ModelErrorStudyError::InvalidOption(format!(
            "max depth fraction {max_depth_fraction} must be in (0, 1]"
        )));
    }
    let deepest = base
        .layers
        .iter()
        .map(|l| l.depth_mm)
        .fold(0.0f64, f64::max);
    if deepest.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
        return Err(ModelErrorStudyError::Sensor(
            "the sensor has no marker layer below the surface".into(),
        ));
    }
    let mut s = base.clone();
    s.elastomer.thickness_mm = h;
    let scale = (max_depth_fraction * h / deepest).min(1.0);
    for l in &mut s.layers {
        l.depth_mm *= scale;
    }
    Ok(s)
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

/// A dense `H` for the full marker set with its build time (s), or why it failed.
type Operator = Result<(DMatrix<f64>, f64), String>;

/// The data of one (thickness, physics, effect set, load).
struct Data {
    /// Per realisation, displacements of the used markers, mm.
    frames: Vec<Vec<f64>>,
    /// Indices of the used markers into the sensor's full marker list.
    used: Vec<usize>,
    truth: Vec<f64>,
    applied: [f64; 3],
    track_s: Option<f64>,
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
    // Every thickness's bonded layer is checked before any work: a layer too thin
    // for the sensor's distances (a table of 1e19 Bessel evaluations at 1 µm) is an
    // error naming it, not hours of work or an abort allocating terabytes.
    let layer_wanted = options.physics.contains(&ModelKind::BondedLayer)
        || options.solver_models.contains(&ModelKind::BondedLayer);
    if layer_wanted {
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
    }
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
        let mut operators: Vec<(ModelKind, Sensor, Operator)> = Vec::new();
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
                            &sites,
                            &points,
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
        let depths: Vec<f64> = sensor_h.layers.iter().map(|l| l.depth_mm).collect();
        for &physics in &options.physics {
            for set in &options.effects {
                for &load in &options.loads {
                    let data = make_data(&sensor_h, &sites, camera, set, physics, load, options);
                    let mut group: Vec<(ModelErrorRow, Option<Box<dyn FrameSolver>>)> = Vec::new();
                    for (m, s, op) in &operators {
                        for config in &options.solvers {
                            let mut row = ModelErrorRow {
                                thickness_mm: h,
                                depths_mm: depths.clone(),
                                physics,
                                solver_model: *m,
                                solver: config.method,
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
                                markers_used: (0, sites.len()),
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
                            };
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

/// The data of one (thickness, physics, effect set, load); `Err` is why it cannot be
/// made (reported in the rows).
fn make_data(
    sensor: &Sensor,
    sites: &[MarkerSite],
    camera: &CameraEffects,
    set: &EffectSet,
    physics: ModelKind,
    load: LoadKind,
    options: &ModelErrorOptions,
) -> Result<Data, String> {
    match set {
        EffectSet::Forward => {
            let truth = load.node_forces(sensor).map_err(|e| e.to_string())?;
            let mut applied = [0.0; 3];
            for (i, v) in truth.iter().enumerate() {
                applied[i % 3] += v;
            }
            let m = ForwardModel::of_kind(physics, &sensor.elastomer);
            let mut u = model::forward(&m, sites, &sensor.force_points_mm(), &truth)
                .map_err(|e| e.to_string())?;
            if options.noise_px > 0.0 {
                // One draw per data set, from a stream of its own.
                let stream = (sensor.elastomer.thickness_mm.to_bits())
                    ^ ((physics as u64) << 2)
                    ^ (load as u64);
                let mut rng = Rng::stream(options.seed, stream);
                let s = options.noise_px * sensor.camera.mm_per_px;
                u.iter_mut().for_each(|v| *v += s * rng.normal());
            }
            Ok(Data {
                frames: vec![u],
                used: (0..sites.len()).collect(),
                truth,
                applied,
                track_s: None,
            })
        }
        EffectSet::Pipeline(kinds) => {
            if load == LoadKind::Tangential {
                return Err(
                    "a contact cannot carry a tangential load without a normal one \
                            (Coulomb friction: |Q| <= mu P), so the pipeline has no purely \
                            tangential load; see the forward (effects none) rows"
                        .into(),
                );
            }
            let effects = camera.select(kinds).map_err(|e| e.to_string())?;
            let scene = pipeline_scene(camera, &effects, sensor.clone(), physics, load)
                .map_err(|e| e.to_string())?;
            pipeline_data(&scene, sites, options)
        }
    }
}

/// Renders, detects and tracks a pipeline data set.
fn pipeline_data(
    scene: &Scene,
    sites: &[MarkerSite],
    options: &ModelErrorOptions,
) -> Result<Data, String> {
    let sensor = &scene.sensor;
    crate::sim::scene::check_physics(scene.physics, sensor).map_err(|e| e.to_string())?;
    let mut sim = Simulation::from_scene(scene);
    let eight_bit = sim.pipeline().quantizes_to_8bit();
    let convert = |img: &image::Rgb32FImage| {
        if eight_bit {
            Frame::Rgb8(to_rgb8(img))
        } else {
            Frame::Rgb16(to_rgb16(img))
        }
    };
    let mut buf = sim.blank_frame();
    sim.render_reference(&mut buf).map_err(|e| e.to_string())?;
    let reference = convert(&buf);
    let mut frames = Vec::with_capacity(options.realisations);
    let mut contact = None;
    for k in 1..=options.realisations {
        let t = sim
            .render_load(&scene.load, k as u64, &mut buf)
            .map_err(|e| e.to_string())?;
        frames.push(convert(&buf));
        if contact.is_none() {
            contact = t.contact;
        }
    }
    let contact = contact.ok_or("the scene rendered no contact")?;
    let reference = detect(&reference.view(), sensor, &DetectConfig::default())
        .map_err(|e| format!("reference detection: {e}"))?;
    // Index of each layer's first marker in the full marker list.
    let mut offsets = Vec::with_capacity(sensor.layers.len());
    let mut n = 0;
    for l in &sensor.layers {
        offsets.push(n);
        n += l.markers.map_or(0, |m| m.grid.len());
    }
    let mut tracker = Tracker::new(
        reference,
        TrackConfig {
            mode: TrackMode::PerWindow,
            ..TrackConfig::default()
        },
    );
    let n_ref = tracker.reference().markers.len();
    let mut ok = vec![true; n_ref];
    for f in &frames {
        let tracks = tracker.track(&f.view()).map_err(|e| e.to_string())?;
        for (o, t) in ok.iter_mut().zip(tracks) {
            *o &= t.status == MarkerStatus::Ok;
        }
    }
    let tracked: Vec<usize> = (0..n_ref).filter(|&i| ok[i]).collect();
    let used: Vec<usize> = tracked
        .iter()
        .map(|&i| {
            let m = &tracker.reference().markers[i];
            offsets[m.layer] + m.id as usize
        })
        .collect();
    if used.is_empty() || used.iter().any(|&i| i >= sites.len()) {
        return Err("no marker was tracked in every frame".into());
    }
    let mm = sensor.camera.mm_per_px;
    let mut us = Vec::with_capacity(frames.len());
    for f in &frames {
        let tracks = tracker.track(&f.view()).map_err(|e| e.to_string())?;
        let mut u = Vec::with_capacity(2 * tracked.len());
        for &i in &tracked {
            u.push(tracks[i].displacement_px[0] * mm);
            u.push(tracks[i].displacement_px[1] * mm);
        }
        us.push(u);
    }
    // Tracking time per frame: median over reps, each after an untimed pass.
    let mut times = Vec::with_capacity(options.reps);
    let view = frames[0].view();
    for _ in 0..options.reps {
        tracker.track(&view).map_err(|e| e.to_string())?;
        let t = Instant::now();
        tracker.track(&view).map_err(|e| e.to_string())?;
        times.push(t.elapsed().as_secs_f64());
    }
    Ok(Data {
        frames: us,
        used,
        truth: contact.force_grid_n(&sensor.force_grid),
        applied: contact.total_force_n(),
        track_s: Some(median(&mut times)),
    })
}

/// Builds the row's solver, scores it on every realisation; `Err` is the refusal.
fn solve_row(
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
fn time_group(
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

/// Columns of `model_error.csv` (documented in the README): errors relative (0.05 =
/// 5 %), forces N, build times ms, per-frame times µs, λ mm/N.
pub const MODEL_ERROR_COLUMNS: [&str; 38] = [
    "thickness_mm",
    "depths_mm",
    "physics",
    "solver_model",
    "matched",
    "solver",
    "load",
    "effects",
    "data",
    "status",
    "reason",
    "applied_fx_n",
    "applied_fy_n",
    "applied_fz_n",
    "fsum_x_n",
    "fsum_y_n",
    "fsum_z_n",
    "field_error",
    "field_error_x",
    "field_error_y",
    "field_error_z",
    "sum_error",
    "sum_error_x",
    "sum_error_y",
    "sum_error_z",
    "mean_abs_gf",
    "markers_used",
    "markers_total",
    "realisations",
    "t_h_ms",
    "t_precompute_ms",
    "t_build_ms",
    "t_track_us",
    "t_solve_us",
    "t_frame_us",
    "lambda_mm_per_n",
    "rank",
    "condition_number",
];

/// A number for the CSV: `fmt` when finite, empty otherwise.
fn num(v: f64, scale: f64, digits: usize, sci: bool) -> String {
    if !v.is_finite() {
        return String::new();
    }
    if sci {
        format!("{:.digits$e}", v * scale)
    } else {
        format!("{:.digits$}", v * scale)
    }
}

impl ModelErrorResult {
    /// Writes `model_error.csv` ([`MODEL_ERROR_COLUMNS`]); refused rows have empty
    /// numbers and their reason.
    pub fn write_csv(&self, path: &Path) -> Result<(), ModelErrorStudyError> {
        let werr = |e: &dyn std::fmt::Display| ModelErrorStudyError::Write {
            path: path.to_path_buf(),
            message: e.to_string(),
        };
        let mut w = csv::Writer::from_path(path).map_err(|e| werr(&e))?;
        w.write_record(MODEL_ERROR_COLUMNS).map_err(|e| werr(&e))?;
        for r in &self.rows {
            let ok = r.is_ok();
            let e = |v: f64| {
                if ok {
                    num(v, 1.0, 6, true)
                } else {
                    String::new()
                }
            };
            let f = |v: f64| {
                if ok {
                    num(v, 1.0, 6, false)
                } else {
                    String::new()
                }
            };
            let ms = |v: f64| {
                if ok {
                    num(v, 1e3, 3, false)
                } else {
                    String::new()
                }
            };
            let us = |v: f64| {
                if ok {
                    num(v, 1e6, 3, false)
                } else {
                    String::new()
                }
            };
            let depths: Vec<String> = r.depths_mm.iter().map(|d| format!("{d}")).collect();
            let mut rec = vec![
                format!("{}", r.thickness_mm),
                depths.join(";"),
                r.physics.name().to_string(),
                r.solver_model.name().to_string(),
                r.matched().to_string(),
                r.solver.name().to_string(),
                r.load.name().to_string(),
                r.effects.clone(),
                r.data.name().to_string(),
                match &r.status {
                    RowStatus::Ok => "ok".to_string(),
                    RowStatus::Refused(_) => "refused".to_string(),
                },
                match &r.status {
                    RowStatus::Ok => String::new(),
                    RowStatus::Refused(why) => why.clone(),
                },
            ];
            rec.extend(r.applied_n.map(|v| num(v, 1.0, 6, false)));
            rec.extend(r.errors.fsum_n.map(f));
            rec.push(e(r.errors.field));
            rec.extend(r.errors.field_axis.map(e));
            rec.push(e(r.errors.sum));
            rec.extend(r.errors.sum_axis.map(e));
            rec.push(e(r.errors.mean_abs_gf));
            rec.push(if ok {
                r.markers_used.0.to_string()
            } else {
                String::new()
            });
            rec.push(r.markers_used.1.to_string());
            rec.push(if ok {
                r.realisations.to_string()
            } else {
                String::new()
            });
            rec.push(r.t_h_s.map_or(String::new(), ms));
            rec.push(ms(r.t_precompute_s));
            rec.push(ms(r.t_build_s));
            rec.push(r.t_track_s.map_or(String::new(), us));
            rec.push(us(r.t_solve_s));
            rec.push(us(r.t_frame_s));
            rec.push(r.lambda.map_or(String::new(), |l| num(l, 1.0, 6, true)));
            rec.push(r.rank.map_or(String::new(), |k| k.to_string()));
            rec.push(e(r.condition_number));
            w.write_record(&rec).map_err(|e| werr(&e))?;
        }
        w.flush().map_err(|e| werr(&e))
    }

    /// The measured row of a combination, if any.
    #[allow(clippy::too_many_arguments)]
    pub fn find(
        &self,
        thickness_mm: f64,
        physics: ModelKind,
        solver_model: ModelKind,
        solver: Method,
        load: LoadKind,
        effects: &str,
    ) -> Option<&ModelErrorRow> {
        self.rows.iter().find(|r| {
            r.thickness_mm == thickness_mm
                && r.physics == physics
                && r.solver_model == solver_model
                && r.solver == solver
                && r.load == load
                && r.effects == effects
                && r.is_ok()
        })
    }

    /// The effect-set label the headline figures use: `none` when it ran, else the
    /// first set.
    pub fn headline_effects(&self) -> String {
        let labels: Vec<String> = self.options.effects.iter().map(EffectSet::label).collect();
        if labels.iter().any(|l| l == "none") {
            "none".into()
        } else {
            labels.first().cloned().unwrap_or_default()
        }
    }

    /// Writes the out directory's `README.md`: what ran (`command`), the definitions,
    /// the headline table (bonded-layer data, half-space against matching solver) and
    /// the refused rows.
    pub fn write_readme(&self, path: &Path, command: &str) -> Result<(), ModelErrorStudyError> {
        let text = self.readme(command);
        std::fs::write(path, text).map_err(|e| ModelErrorStudyError::Write {
            path: path.to_path_buf(),
            message: e.to_string(),
        })
    }

    /// The text of [`Self::write_readme`].
    pub fn readme(&self, command: &str) -> String {
        use std::fmt::Write as _;
        let o = &self.options;
        let mut s = String::new();
        let _ = writeln!(s, "# Model error: half-space against bonded-layer solver\n");
        let _ = writeln!(
            s,
            "Generated by `{command}` ({}; do not edit by hand).\n",
            if cfg!(debug_assertions) {
                "dev profile: crate at opt-level 1, dependencies at 3"
            } else {
                "release"
            }
        );
        let _ = writeln!(
            s,
            "Data made with each physics (`bonded-layer` at the row's thickness, and the \
             `half-space` reference) is solved by a solver inverting the half-space and one \
             inverting the bonded layer of the same thickness (`matched` = the solver's model \
             is the data's). Load: the paper's Fig. 6 load (100 gf z + 50 gf y over force \
             points (4,3)-(7,6)): `normal` its z part, `tangential` its y part, `mixed` both. \
             Effects `none`: forward-model marker displacements, nodal load{}; other effect \
             sets: rendered, tracked and solved (5 mm flat probe on the patch centre, {} \
             loaded frame(s)). Markers: deepest at most {} of the thickness.\n",
            if o.noise_px > 0.0 {
                format!(", {} px noise", o.noise_px)
            } else {
                ", exact".to_string()
            },
            o.realisations,
            o.max_depth_fraction
        );
        let _ = writeln!(
            s,
            "Errors: `field` = ‖f − f*‖ / ‖f*‖ over nodes and axes; `F_sum` = |ΣF − \
             F_applied| / |F_applied|; per-axis columns in `model_error.csv` (see the \
             project README). Times: build = H (cold) + solver precompute, per frame = \
             tracking + solve, medians over {} repetitions on this machine.\n",
            o.reps
        );
        let sets: Vec<String> = o.effects.iter().map(EffectSet::label).collect();
        for (eff, config) in sets
            .iter()
            .flat_map(|e| o.solvers.iter().map(move |c| (e.clone(), c)))
        {
            let m = config.method;
            let _ = writeln!(
                s,
                "## Bonded-layer data, effects `{eff}`, solver `{}`\n",
                m.name()
            );
            let _ = writeln!(
                s,
                "| thickness, mm | depths, mm | load | field error, half-space solver | field error, matching | F_sum error, half-space | F_sum error, matching | build, half-space / matching, ms | per frame, half-space / matching, µs |"
            );
            let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|");
            for &h in &o.thicknesses_mm {
                for &load in &o.loads {
                    let hs = self.find(
                        h,
                        ModelKind::BondedLayer,
                        ModelKind::HalfSpace,
                        m,
                        load,
                        &eff,
                    );
                    let bl = self.find(
                        h,
                        ModelKind::BondedLayer,
                        ModelKind::BondedLayer,
                        m,
                        load,
                        &eff,
                    );
                    if hs.is_none() && bl.is_none() {
                        continue;
                    }
                    let depths = hs
                        .or(bl)
                        .map(|r| {
                            r.depths_mm
                                .iter()
                                .map(|d| format!("{d}"))
                                .collect::<Vec<_>>()
                                .join(" / ")
                        })
                        .unwrap_or_default();
                    let pct = |r: Option<&ModelErrorRow>, f: fn(&ModelErrorRow) -> f64| {
                        r.map_or("refused".to_string(), |r| format!("{:.2} %", 100.0 * f(r)))
                    };
                    let t = |r: Option<&ModelErrorRow>, f: fn(&ModelErrorRow) -> f64, sc: f64| {
                        r.map_or("—".to_string(), |r| format!("{:.1}", f(r) * sc))
                    };
                    let _ = writeln!(
                        s,
                        "| {h} | {depths} | {} | {} | {} | {} | {} | {} / {} | {} / {} |",
                        load.name(),
                        pct(hs, |r| r.errors.field),
                        pct(bl, |r| r.errors.field),
                        pct(hs, |r| r.errors.sum),
                        pct(bl, |r| r.errors.sum),
                        t(hs, |r| r.t_build_s, 1e3),
                        t(bl, |r| r.t_build_s, 1e3),
                        t(hs, |r| r.t_frame_s, 1e6),
                        t(bl, |r| r.t_frame_s, 1e6),
                    );
                }
            }
            let _ = writeln!(s);
        }
        let shallow: Vec<f64> = o
            .thicknesses_mm
            .iter()
            .copied()
            .filter(|&h| {
                self.rows.iter().any(|r| {
                    r.thickness_mm == h
                        && r.data == DataPath::Pipeline
                        && r.depths_mm.iter().fold(f64::INFINITY, |a, b| a.min(*b))
                            < 0.75 * self.force_pitch_mm
                })
            })
            .collect();
        if !shallow.is_empty() {
            let _ = writeln!(
                s,
                "Note on the rendered rows at {} mm: the upper marker layer lies at less than \
                 3/4 of the force-grid pitch ({} mm), so its markers see the contact's traction \
                 in more detail than point forces on the grid nodes can represent; the errors \
                 of both \
                 solvers on those rows are dominated by that discretisation, not by the elastic \
                 model (the forward rows, load on the nodes, show the model error alone). A thin \
                 gel needs a force grid about as fine as its marker depth.\n",
                shallow
                    .iter()
                    .map(|h| h.to_string())
                    .collect::<Vec<_>>()
                    .join(", "),
                self.force_pitch_mm
            );
        }
        let refused: Vec<&ModelErrorRow> = self.rows.iter().filter(|r| !r.is_ok()).collect();
        if !refused.is_empty() {
            let _ = writeln!(s, "## Refused rows ({})\n", refused.len());
            let mut reasons: Vec<(String, usize)> = Vec::new();
            for r in refused {
                let RowStatus::Refused(why) = &r.status else {
                    continue;
                };
                let key = format!(
                    "{} solver, {} load, effects {}: {}",
                    r.solver.name(),
                    r.load.name(),
                    r.effects,
                    why.split("; ").next().unwrap_or_default()
                );
                match reasons.iter_mut().find(|(k, _)| *k == key) {
                    Some((_, n)) => *n += 1,
                    None => reasons.push((key, 1)),
                }
            }
            for (k, n) in reasons {
                let _ = writeln!(s, "- {n} × {k}");
            }
            let _ = writeln!(s);
        }
        let _ = writeln!(
            s,
            "Files: `model_error.csv` (every row, columns in the project README), \
             `model_error.png` / `.svg` (error against thickness)."
        );
        s
    }
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
