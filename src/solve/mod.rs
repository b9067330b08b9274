//! Inverse solvers: surface forces from marker displacements, `f ≈ H⁺ u`.
//!
//! Every solver is split in two (DESIGN.md): a **precompute** step per sensor and
//! marker set (decompositions, regularisation choice, kernels), and a per-frame
//! [`FrameSolver::apply`] that performs no heap allocation, so the same solver can run
//! at camera rate. The methods:
//!
//! | method | precompute | per frame | when |
//! |---|---|---|---|
//! | `pinv` | SVD of `H`, singular values below `rcond·σ_max` dropped | dense `P u` | the paper's method; well-posed geometries |
//! | `tikhonov` | SVD, filter `σ/(σ²+λ²)`, λ fixed or by GCV / L-curve | dense `P u` | noisy or ill-conditioned systems |
//! | `tsvd` | SVD, first `k` singular triplets, `k` fixed or automatic | dense `P u` | ill-conditioned systems, sharp cut |
//! | `fourier` | per-frequency regularised solves | FFTs, `O(N log N)` | regular grids, dense force grids (64×64 and up) |
//!
//! Units: displacements in mm (interleaved `ux, uy` per marker, the row order of `H`,
//! see [`crate::model`]), forces in N (interleaved `fx, fy, fz` per force point,
//! row-major over the force grid).

pub mod dense;
pub mod fourier;
pub mod kernel;

use std::fmt;
use std::str::FromStr;

use thiserror::Error;

use crate::model::{HalfSpace, MarkerSite, ModelError};
use crate::sensor::Sensor;
/// Message formatting of numbers and byte counts lives in `units` (the model uses it too,
/// and `solve` is built on `model`); re-exported for the solver's callers.
pub use crate::units::{fmt_bytes, fmt_num};

/// An error from a solver.
#[derive(Debug, Error)]
pub enum SolveError {
    /// An input vector has the wrong length.
    #[error("{what} has {got} values, expected {expected}")]
    DimensionMismatch {
        /// Which vector.
        what: &'static str,
        /// Expected length.
        expected: usize,
        /// Actual length.
        got: usize,
    },
    /// An input value is NaN or infinite.
    #[error("displacement value {index} (marker {marker}, {axis}) is {value:e}: inputs must be finite (drop lost markers before solving)")]
    NonFinite {
        /// Index into the displacement vector.
        index: usize,
        /// Marker index (`index / 2`).
        marker: usize,
        /// `ux` or `uy`.
        axis: &'static str,
        /// The value.
        value: f64,
    },
    /// The system has no equations or no unknowns.
    #[error("empty system: {0}")]
    Empty(String),
    /// The forward model could not be built.
    #[error(transparent)]
    Model(#[from] ModelError),
    /// A decomposition did not converge or produced non-finite values.
    #[error("decomposition failed: {0}")]
    Decomposition(String),
    /// An option is out of range for this problem.
    #[error("invalid solver option: {0}")]
    InvalidOption(String),
    /// The Fourier solver cannot represent this geometry.
    #[error("the fourier solver cannot handle this geometry: {0}")]
    Incompatible(String),
    /// Automatic λ or rank selection needs a displacement frame and none was given.
    #[error("automatic {0} selection needs a displacement frame to choose from")]
    NeedsFrame(&'static str),
    /// The dense system would take more memory than the cap
    /// ([`dense::MAX_DENSE_BYTES`]), checked before it is built.
    #[error(
        "the dense system is {rows}x{cols} ({} marker values for {} force unknowns): building \
         and decomposing it takes about {}, past the limit of {}; the `fourier` solver \
         (--solver fourier, markers on regular grids) or fewer markers (a coarser marker \
         grid, or the markers of one frame at a time) would do",
        rows,
        cols,
        fmt_bytes(*bytes),
        fmt_bytes(*limit_bytes)
    )]
    TooBig {
        /// Rows of `H` (2 × markers).
        rows: usize,
        /// Columns of `H` (3 × force points).
        cols: usize,
        /// Estimated working memory, bytes.
        bytes: f64,
        /// The cap, bytes.
        limit_bytes: f64,
    },
    /// Displacements so large that the forces would overflow `f64`.
    #[error("largest displacement {max_abs_mm:.3e} mm exceeds the solver's limit of {limit_mm:.3e} mm: the forces would overflow")]
    TooLarge {
        /// Largest |displacement| in the frame, mm.
        max_abs_mm: f64,
        /// Largest |displacement| the solver accepts, mm.
        limit_mm: f64,
    },
}

/// Which inverse method to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Method {
    /// Moore–Penrose pseudo-inverse via SVD (the paper's method).
    #[default]
    Pinv,
    /// Tikhonov regularisation.
    Tikhonov,
    /// Truncated SVD.
    Tsvd,
    /// Per-frequency solve on regular grids.
    Fourier,
}

impl Method {
    /// Name as used on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Method::Pinv => "pinv",
            Method::Tikhonov => "tikhonov",
            Method::Tsvd => "tsvd",
            Method::Fourier => "fourier",
        }
    }
}

impl fmt::Display for Method {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Method {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "pinv" => Ok(Method::Pinv),
            "tikhonov" => Ok(Method::Tikhonov),
            "tsvd" => Ok(Method::Tsvd),
            "fourier" => Ok(Method::Fourier),
            _ => Err(format!(
                "unknown solver `{s}`: expected pinv, tikhonov, tsvd or fourier"
            )),
        }
    }
}

/// How the Tikhonov (and Fourier) regularisation parameter λ is chosen.
///
/// λ has the units of a singular value of `H` (mm/N): the filter factor of singular
/// value σ is `σ²/(σ²+λ²)`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Lambda {
    /// Generalised cross-validation on the given frame.
    #[default]
    Gcv,
    /// Corner of the L-curve (maximum curvature) on the given frame.
    LCurve,
    /// A fixed value (mm/N), ≥ 0.
    Fixed(f64),
}

impl FromStr for Lambda {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "gcv" => Ok(Lambda::Gcv),
            "lcurve" | "l-curve" => Ok(Lambda::LCurve),
            v => match v.parse::<f64>() {
                Ok(x) if x.is_finite() && x >= 0.0 => Ok(Lambda::Fixed(x)),
                _ => Err(format!(
                    "invalid lambda `{v}`: expected gcv, lcurve or a number >= 0 (mm/N)"
                )),
            },
        }
    }
}

/// How the truncated-SVD rank is chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Rank {
    /// Chosen automatically (GCV over the rank on the given frame).
    #[default]
    Auto,
    /// Keep the first `k` singular triplets.
    Fixed(usize),
}

impl FromStr for Rank {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(Rank::Auto),
            v => match v.parse::<usize>() {
                Ok(k) if k > 0 => Ok(Rank::Fixed(k)),
                _ => Err(format!(
                    "invalid rank `{v}`: expected auto or an integer >= 1"
                )),
            },
        }
    }
}

/// Arithmetic used by the per-frame apply (precompute is always f64).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Precision {
    /// Double precision: exact to ~1e-12 relative.
    #[default]
    F64,
    /// Single precision: about twice as fast; measured at the paper size
    /// ‖f32 − f64‖/‖f64‖ = 9.9e-6 (pinv), 2.7e-7 (tikhonov, GCV λ), 1.3e-7 (tsvd, GCV
    /// rank): the error grows with the largest filter factor φ_i/σ_i kept.
    F32,
}

/// Everything that selects and tunes a solver.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolverConfig {
    /// The method.
    pub method: Method,
    /// λ choice (Tikhonov, Fourier).
    pub lambda: Lambda,
    /// Rank choice (TSVD).
    pub rank: Rank,
    /// Per-frame arithmetic (dense methods).
    pub precision: Precision,
    /// Relative singular-value cutoff of `pinv`; `None` = `max(rows, cols) · ε · σ_max`
    /// (the LAPACK / NumPy default).
    pub rcond: Option<f64>,
    /// Fourier solver: zero padding added around the grids, as a fraction of the
    /// larger grid extent (see [`fourier`]).
    pub fourier_padding: f64,
    /// Fourier solver: add the precomputed coarse-grid correction with the force sums of
    /// dense Tikhonov to the per-frequency solve (the two-level solve, default true;
    /// false = the direct periodic solve alone: fastest, but with the periodic model's
    /// boundary error; see [`fourier`]).
    pub fourier_coarse: bool,
    /// Fourier solver: CGLS refinement iterations on the exact operator after the
    /// two-level (or direct) solve, converging to dense Tikhonov. Default
    /// [`fourier::DEFAULT_REFINE_ITERATIONS`] (none).
    pub fourier_refine_iterations: usize,
    /// Fourier solver: the refinement stops before `fourier_refine_iterations` once its
    /// estimated relative distance to dense Tikhonov is at most this. Default
    /// [`fourier::DEFAULT_REFINE_TOLERANCE`]; 0 runs the full count.
    pub fourier_refine_tolerance: f64,
}

impl Default for SolverConfig {
    fn default() -> Self {
        SolverConfig {
            method: Method::Pinv,
            lambda: Lambda::Gcv,
            rank: Rank::Auto,
            precision: Precision::F64,
            rcond: None,
            fourier_padding: 1.0,
            fourier_coarse: true,
            fourier_refine_iterations: fourier::DEFAULT_REFINE_ITERATIONS,
            fourier_refine_tolerance: fourier::DEFAULT_REFINE_TOLERANCE,
        }
    }
}

impl SolverConfig {
    /// Whether precompute needs a displacement frame: automatic λ (`tikhonov`,
    /// `fourier`) or automatic rank (`tsvd`) choose from data.
    pub fn needs_frame(&self) -> bool {
        match self.method {
            Method::Pinv => false,
            Method::Tikhonov | Method::Fourier => {
                matches!(self.lambda, Lambda::Gcv | Lambda::LCurve)
            }
            Method::Tsvd => self.rank == Rank::Auto,
        }
    }
}

/// The geometry of one reconstruction problem: material, sensor (force grid, layer
/// grids) and the markers actually present in the data (lost markers already dropped).
#[derive(Debug, Clone, Copy)]
pub struct Problem<'a> {
    /// Material.
    pub model: HalfSpace,
    /// The sensor; its force grid defines the unknowns.
    pub sensor: &'a Sensor,
    /// The markers that carry data, in the order of the displacement vector.
    pub sites: &'a [MarkerSite],
}

impl<'a> Problem<'a> {
    /// A problem on the sensor's own material and force grid.
    pub fn new(sensor: &'a Sensor, sites: &'a [MarkerSite]) -> Self {
        Problem {
            model: HalfSpace::from_elastomer(&sensor.elastomer),
            sensor,
            sites,
        }
    }

    /// The forward model the sensor file selects (`[elastomer] model`) on this
    /// problem's material: what builds `H` for the dense solvers.
    pub fn forward_model(&self) -> crate::model::ForwardModel {
        crate::model::ForwardModel::with_material(
            self.sensor.elastomer.model,
            self.model,
            self.sensor.elastomer.thickness_mm,
        )
    }

    /// Length of the displacement vector.
    pub fn n_inputs(&self) -> usize {
        2 * self.sites.len()
    }

    /// Length of the force vector.
    pub fn n_outputs(&self) -> usize {
        3 * self.sensor.force_grid.len()
    }
}

/// What a precompute learned about the system. Fields that do not apply to a method
/// are `None` / empty.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Diagnostics {
    /// Method that produced this.
    pub method: Method,
    /// Rows × columns of the system (`2·markers`, `3·force points`).
    pub shape: (usize, usize),
    /// Singular values of `H`, descending, mm/N (dense methods; for `fourier` the
    /// per-frequency singular values gathered and sorted).
    pub singular_values: Vec<f64>,
    /// `σ_max / σ_min` of `H` itself over all its singular values, whatever cut-off
    /// (`rcond`) or regularisation the solver applies; ∞ only when `σ_min` is exactly 0
    /// (dense methods; the rank actually used is [`Diagnostics::rank`] /
    /// [`Diagnostics::effective_rank`]).
    pub condition_number: f64,
    /// Number of singular values the solver actually uses (or the sum of filter
    /// factors for Tikhonov).
    pub effective_rank: f64,
    /// ‖P‖₂: worst-case force error per unit displacement error, N/mm.
    pub noise_gain: f64,
    /// λ in use, mm/N.
    pub lambda: Option<f64>,
    /// Rank in use: the truncation rank (TSVD) or the numerical rank kept (pinv).
    pub rank: Option<usize>,
    /// Free-text notes (why an automatic choice came out as it did, cut-offs used).
    /// Notes that start with [`WARNING_PREFIX`] are warnings (e.g. an automatic λ or
    /// rank search that ended on the boundary of its range): front ends print them as
    /// such, see [`Diagnostics::warnings`].
    pub notes: Vec<String>,
}

/// Largest |value| of a displacement frame (0 when empty).
pub(crate) fn max_abs(u: &[f64]) -> f64 {
    u.iter().fold(0.0f64, |m, v| m.max(v.abs()))
}

/// The factor that brings a frame to unit peak for the automatic λ / rank searches
/// (GCV's and the L-curve's optimum do not change under `u → a·u`, but their sums of
/// squares under- or overflow at displacements of order 1e-160 or 1e300 mm); 1 for an
/// all-zero frame.
pub(crate) fn unit_peak_factor(u: &[f64]) -> f64 {
    let peak = max_abs(u);
    if peak > 0.0 && peak.is_finite() {
        1.0 / peak
    } else {
        1.0
    }
}

/// Prefix of the [`Diagnostics::notes`] that are warnings.
pub const WARNING_PREFIX: &str = "warning: ";

impl Diagnostics {
    /// The notes that are warnings, without their prefix.
    pub fn warnings(&self) -> impl Iterator<Item = &str> {
        self.notes
            .iter()
            .filter_map(|n| n.strip_prefix(WARNING_PREFIX))
    }

    /// `σ_max / σ_min` of the listed singular values: the condition number of `H`
    /// itself, whatever cut-off or regularisation the solver applies (∞ only when the
    /// smallest singular value is exactly 0; `NaN` when none are listed).
    pub fn condition_of_h(&self) -> f64 {
        match (self.singular_values.first(), self.singular_values.last()) {
            (Some(&max), Some(&min)) if min > 0.0 => max / min,
            (Some(_), Some(_)) => f64::INFINITY,
            _ => f64::NAN,
        }
    }
}

/// A precomputed solver for one marker set: call [`FrameSolver::apply`] per frame.
pub trait FrameSolver: Send {
    /// Length of the displacement vector it takes.
    fn n_inputs(&self) -> usize;
    /// Length of the force vector it writes.
    fn n_outputs(&self) -> usize;
    /// Reconstructs forces (N) from displacements (mm); no heap allocation.
    /// Errors on wrong lengths or non-finite input, never panics.
    fn apply(&mut self, u_mm: &[f64], f_n: &mut [f64]) -> Result<(), SolveError>;
    /// What the precompute found.
    fn diagnostics(&self) -> &Diagnostics;
    /// Standard deviation (N) of every reconstructed force component (length
    /// `n_outputs`, order fx, fy, fz per force point) when every displacement input
    /// carries independent zero-mean noise of standard deviation `sigma_mm`.
    fn force_sd(&self, sigma_mm: f64, out: &mut [f64]) -> Result<(), SolveError>;
    /// Standard deviation (N) of the force sum (ΣFx, ΣFy, ΣFz) for the same noise,
    /// correlations between nodes included.
    fn sum_sd(&self, sigma_mm: f64) -> Result<[f64; 3], SolveError>;
}

/// Precomputes the configured solver for a problem. `frame` (displacements, mm) is used
/// by automatic λ / rank selection, which needs data; methods with fixed parameters
/// ignore it.
pub fn precompute(
    problem: &Problem<'_>,
    config: &SolverConfig,
    frame: Option<&[f64]>,
) -> Result<Box<dyn FrameSolver>, SolveError> {
    if problem.sites.is_empty() {
        return Err(SolveError::Empty("no markers carry data".into()));
    }
    if let Some(u) = frame {
        check_input(u, problem.n_inputs())?;
    }
    match config.method {
        Method::Fourier => Ok(Box::new(fourier::FourierSolver::precompute(
            problem, config, frame,
        )?)),
        _ => Ok(Box::new(dense::DenseSolver::precompute(
            problem, config, frame,
        )?)),
    }
}

/// Standard deviation (N) of the force sum `(ΣFx, ΣFy, ΣFz)` reconstructed by
/// `solver` when every displacement input carries independent zero-mean noise of
/// standard deviation `sigma_mm` (mm): [`FrameSolver::sum_sd`]. This is what a caller
/// that journals the uncertainty of a measurement (the runner, per setpoint) calls;
/// [`noise_px_to_mm`] converts a tracker noise in pixels.
pub fn force_sum_sd(solver: &dyn FrameSolver, sigma_mm: f64) -> Result<[f64; 3], SolveError> {
    solver.sum_sd(sigma_mm)
}

/// A displacement noise in camera pixels converted to mm with the sensor's image
/// scale (`[camera] mm_per_px`).
pub fn noise_px_to_mm(sensor: &Sensor, noise_px: f64) -> f64 {
    noise_px * sensor.camera.mm_per_px
}

/// Checks a noise standard deviation (mm) given to [`FrameSolver::force_sd`] /
/// [`FrameSolver::sum_sd`]: finite and ≥ 0.
pub fn check_sigma(sigma_mm: f64) -> Result<(), SolveError> {
    if sigma_mm.is_finite() && sigma_mm >= 0.0 {
        Ok(())
    } else {
        Err(SolveError::InvalidOption(format!(
            "displacement noise σ = {} mm must be a finite number >= 0",
            fmt_num(sigma_mm)
        )))
    }
}

/// Checks a displacement vector's length and finiteness (shared by every solver).
pub fn check_input(u_mm: &[f64], expected: usize) -> Result<(), SolveError> {
    if u_mm.len() != expected {
        return Err(SolveError::DimensionMismatch {
            what: "displacement vector",
            expected,
            got: u_mm.len(),
        });
    }
    if let Some((index, &value)) = u_mm.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(SolveError::NonFinite {
            index,
            marker: index / 2,
            axis: if index % 2 == 0 { "ux" } else { "uy" },
            value,
        });
    }
    Ok(())
}

/// Checks the output buffer's length (shared by every solver).
pub fn check_output(f_n: &[f64], expected: usize) -> Result<(), SolveError> {
    if f_n.len() != expected {
        return Err(SolveError::DimensionMismatch {
            what: "force vector",
            expected,
            got: f_n.len(),
        });
    }
    Ok(())
}
