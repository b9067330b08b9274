//! Accuracy against time: what each choice that trades one for the other costs, measured
//! side by side on a simulated scene with known ground truth (issue 6, item 2).
//!
//! # What is swept
//!
//! Around a baseline (the paper's pipeline: `pinv` in f64 on the sensor's force grid,
//! per-window tracking with the measured aperture and 8 re-centring iterations, one
//! frame), one thing at a time ([`Sweep`]):
//!
//! - **solver**: `pinv`, `tikhonov` (λ by GCV, L-curve, or fixed at a fraction of
//!   `σ_max`, the largest singular value of `H`), `tsvd` (automatic or fixed rank),
//!   `fourier` (L-curve λ, two-level solve + 0 / 10 / 30 CGLS refinements; only where the grids allow it),
//!   f32 against f64 for the dense methods;
//! - **force grid**: the density of force points (pitch), same area as the sensor's grid;
//! - **tracking**: the centroid window's aperture radius (scale of the measured one) and
//!   the maximum number of window re-centrings;
//! - **frames averaged**: `N` loaded frames rendered with the scene's seeded effects
//!   (frame `k` draws its noise from stream `k`, so the frames are independent), tracked
//!   one by one, displacements averaged, then one solve.
//!
//! # Metrics
//!
//! The scene's full load (its last frame) is applied in every frame. One reconstruction
//! is one noise realisation, and with noisy scenes single realisations scatter widely
//! (the paper's `pinv` `F^sum` error moves by several percent from frame to frame), so
//! every error is the root mean square over `realisations` independent force frames
//! (realisation `g` of an `N`-frame setting averages loaded frames `gN+1 … gN+N`). With `f` the
//! reconstructed forces on the (possibly re-gridded) force grid and `f*` the scene's
//! traction integrated over each node's cell of that grid (`Contact::force_grid_n`):
//!
//! - **sum error** `e_sum = |ΣF − F_applied| / |F_applied|`: the relative error of the
//!   total force vector `F^sum` (paper Sec. IV-B-2) against the applied force (sum of
//!   the contact's cell forces, what the bench's force/torque sensor reads);
//! - **field error** `e_field = ‖f − f*‖₂ / ‖f*‖₂` over all nodes and axes: the force
//!   distribution itself. It includes the model error of representing a distributed
//!   traction by point forces at the nodes, so it has a floor well above zero even with
//!   exact data, and it is only comparable between grids as a relative figure.
//!
//! # Time
//!
//! Time per force frame = tracking the `N` frames + averaging + one `FrameSolver::apply`,
//! wall clock on this machine, the median over `reps` repetitions taken round-robin over
//! the settings (so load changes on a shared machine hit all alike), each timed pass
//! right after an untimed one (warm caches, as at camera rate); tracking and solve
//! medians are also given separately. Rendering (the camera) is not counted. The same
//! total is also measured in this thread's CPU time (Linux `CLOCK_THREAD_CPUTIME_ID`;
//! NaN elsewhere): on a shared machine the wall clock includes waiting for a core, the
//! CPU time does not. The precompute (reference detection + solver precompute, once
//! per sensor and marker set) is reported separately: it is paid once, not per frame.
//! Automatic λ and rank are chosen on the first realisation and kept for the others,
//! as a running sensor would.
//!
//! The solver's marker sites are the markers' nominal grid positions from the sensor
//! file (marker id = row-major grid index; the design positions a user knows without a
//! calibration), at their layer's depth; markers not tracked ok in every frame used are
//! dropped from the system.
//!
//! The library does not print: progress is reported through a callback ([`StudyEvent`]).

use std::path::Path;
use std::time::Instant;

use thiserror::Error;

use crate::model::MarkerSite;
use crate::sensor::{Grid, Sensor};
use crate::sim::contact::Contact;
use crate::sim::render::{to_rgb16, to_rgb8};
use crate::sim::scene::Scene;
use crate::sim::simulate::{SimError, Simulation};
use crate::solve::fourier::FourierSolver;
use crate::solve::{
    self, FrameSolver, Lambda, Method, Precision, Problem, Rank, SolveError, SolverConfig,
};
use crate::vision::{
    detect, DetectConfig, Frame, MarkerStatus, TrackConfig, TrackMode, Tracker, VisionError,
};

/// Largest number of frames averaged in one setting (bounds rendering time and memory).
pub const MAX_FRAMES_AVERAGED: usize = 64;
/// Largest number of timing repetitions.
pub const MAX_REPS: usize = 100_000;
/// Largest number of error realisations.
pub const MAX_REALISATIONS: usize = 64;

/// An error of the accuracy-against-time study.
#[derive(Debug, Error)]
pub enum StudyError {
    /// An option is out of range.
    #[error("invalid study option: {0}")]
    InvalidOption(String),
    /// The scene could not be simulated.
    #[error("simulating the scene: {0}")]
    Sim(#[from] SimError),
    /// The reference frame could not be analysed.
    #[error("tracking: {0}")]
    Vision(#[from] VisionError),
    /// The scene's load is zero: relative errors are undefined.
    #[error("the scene's applied force is zero: relative errors need a load (give the scene a normal force)")]
    NoLoad,
    /// Writing a result file failed.
    #[error("{path}: {message}")]
    Write {
        /// The file.
        path: std::path::PathBuf,
        /// What went wrong.
        message: String,
    },
}

/// Which sweep a setting belongs to (one thing varied around the baseline).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Sweep {
    /// Solver, regularisation and precision.
    Solver,
    /// Force-grid density.
    ForceGrid,
    /// Tracking window aperture and re-centring iterations.
    Tracking,
    /// Frames averaged.
    Frames,
}

impl Sweep {
    /// All sweeps, in report order.
    pub const ALL: [Sweep; 4] = [
        Sweep::Solver,
        Sweep::ForceGrid,
        Sweep::Tracking,
        Sweep::Frames,
    ];

    /// Name as used on the command line and in the CSV.
    pub fn name(self) -> &'static str {
        match self {
            Sweep::Solver => "solver",
            Sweep::ForceGrid => "grid",
            Sweep::Tracking => "tracking",
            Sweep::Frames => "frames",
        }
    }
}

impl std::str::FromStr for Sweep {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Sweep::ALL
            .into_iter()
            .find(|w| w.name() == s)
            .ok_or_else(|| {
                format!("unknown sweep `{s}`: expected solver, grid, tracking or frames")
            })
    }
}

/// How λ is chosen in a study setting.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StudyLambda {
    /// Generalised cross-validation on the (averaged) frame.
    Gcv,
    /// L-curve corner on the (averaged) frame.
    LCurve,
    /// A fixed λ = `r · σ_max(H)` (σ_max of the dense `H` of the setting's grid).
    RelativeToSigmaMax(f64),
}

/// A solver choice of the study: the library's [`SolverConfig`] plus what the study
/// resolves per problem (λ relative to σ_max) and the Fourier refinement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolverChoice {
    /// The method.
    pub method: Method,
    /// λ choice (tikhonov, fourier).
    pub lambda: StudyLambda,
    /// Rank choice (tsvd).
    pub rank: Rank,
    /// Per-frame arithmetic (dense methods; fourier always f64).
    pub precision: Precision,
    /// CGLS refinement iterations (fourier only).
    pub refine_iterations: usize,
}

impl SolverChoice {
    /// A method with its usual automatic choices (GCV for tikhonov, L-curve for fourier,
    /// automatic rank), f64, no refinement.
    pub fn new(method: Method) -> Self {
        SolverChoice {
            method,
            lambda: if method == Method::Fourier {
                StudyLambda::LCurve
            } else {
                StudyLambda::Gcv
            },
            rank: Rank::Auto,
            precision: Precision::F64,
            refine_iterations: 0,
        }
    }

    /// Short label, e.g. `tikhonov λ=1e-2σmax f32`.
    pub fn label(&self) -> String {
        let mut s = self.method.name().to_string();
        match self.method {
            Method::Tikhonov | Method::Fourier => match self.lambda {
                StudyLambda::Gcv => s.push_str(" gcv"),
                StudyLambda::LCurve => s.push_str(" lcurve"),
                StudyLambda::RelativeToSigmaMax(r) => s.push_str(&format!(" λ={r:.0e}σmax")),
            },
            Method::Tsvd => match self.rank {
                Rank::Auto => s.push_str(" auto"),
                Rank::Fixed(k) => s.push_str(&format!(" k={k}")),
            },
            Method::Pinv => {}
        }
        if self.method == Method::Fourier {
            if self.refine_iterations > 0 {
                s.push_str(&format!(" +{} cgls", self.refine_iterations));
            }
        } else if self.precision == Precision::F32 {
            s.push_str(" f32");
        }
        s
    }
}

/// One point of the study.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Setting {
    /// Which sweep it belongs to.
    pub sweep: Sweep,
    /// The solver.
    pub solver: SolverChoice,
    /// Force-grid pitch, mm (`None`: the sensor's force grid). The grid covers the
    /// sensor grid's area, centred on it.
    pub force_pitch_mm: Option<f64>,
    /// Tracking aperture radius as a multiple of the one measured by reference
    /// detection (1 = measured).
    pub aperture_scale: f64,
    /// Maximum window re-centrings per marker.
    pub max_iterations: u32,
    /// Frames tracked and averaged per force frame (≥ 1).
    pub frames_averaged: usize,
}

impl Setting {
    /// The baseline: the paper's pipeline (pinv, f64, sensor grid, measured aperture,
    /// 8 re-centrings, one frame).
    pub fn baseline() -> Self {
        Setting {
            sweep: Sweep::Solver,
            solver: SolverChoice::new(Method::Pinv),
            force_pitch_mm: None,
            aperture_scale: 1.0,
            max_iterations: TrackConfig::default().max_iterations,
            frames_averaged: 1,
        }
    }

    /// Label: the solver, then what differs from the baseline.
    pub fn label(&self) -> String {
        let b = Setting::baseline();
        let mut s = self.solver.label();
        if let Some(p) = self.force_pitch_mm {
            s.push_str(&format!(" | grid {} mm", short(p)));
        }
        if self.aperture_scale != b.aperture_scale {
            s.push_str(&format!(" | window x{}", short(self.aperture_scale)));
        }
        if self.max_iterations != b.max_iterations {
            s.push_str(&format!(" | iter {}", self.max_iterations));
        }
        if self.frames_averaged != b.frames_averaged {
            s.push_str(&format!(" | avg {}", self.frames_averaged));
        }
        s
    }

    fn validate(&self) -> Result<(), StudyError> {
        if self.frames_averaged == 0 || self.frames_averaged > MAX_FRAMES_AVERAGED {
            return Err(StudyError::InvalidOption(format!(
                "frames averaged = {} must be in 1..={MAX_FRAMES_AVERAGED}",
                self.frames_averaged
            )));
        }
        if !(self.aperture_scale.is_finite() && (0.25..=4.0).contains(&self.aperture_scale)) {
            return Err(StudyError::InvalidOption(format!(
                "aperture scale = {} must be in [0.25, 4] (multiple of the measured aperture)",
                self.aperture_scale
            )));
        }
        if self.max_iterations == 0 {
            return Err(StudyError::InvalidOption(
                "max_iterations = 0: the tracker needs at least 1 window re-centring".into(),
            ));
        }
        if let Some(p) = self.force_pitch_mm {
            if !(p.is_finite() && p > 0.0) {
                return Err(StudyError::InvalidOption(format!(
                    "force-grid pitch = {p} mm must be finite and > 0"
                )));
            }
        }
        if let StudyLambda::RelativeToSigmaMax(r) = self.solver.lambda {
            if !(r.is_finite() && r >= 0.0) {
                return Err(StudyError::InvalidOption(format!(
                    "relative lambda = {r} must be finite and >= 0 (fraction of sigma_max)"
                )));
            }
        }
        Ok(())
    }
}

/// A number with at most 3 decimals, trailing zeros dropped (labels).
fn short(v: f64) -> String {
    let s = format!("{v:.3}");
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

/// The default sweep for `sensor` restricted to `sweeps`, with `frames` the numbers of
/// frames averaged to try (besides 1). See the module docs for what each sweep holds.
pub fn default_settings(sensor: &Sensor, sweeps: &[Sweep], frames: &[usize]) -> Vec<Setting> {
    let base = Setting::baseline();
    let mut out = Vec::new();
    let with = |sweep: Sweep, solver: SolverChoice| Setting {
        sweep,
        solver,
        ..base
    };
    let n_unknowns = 3 * sensor.force_grid.len();
    let tik = SolverChoice::new(Method::Tikhonov);
    let fourier = SolverChoice::new(Method::Fourier);
    if sweeps.contains(&Sweep::Solver) {
        let f32 = |c: SolverChoice| SolverChoice {
            precision: Precision::F32,
            ..c
        };
        let pinv = SolverChoice::new(Method::Pinv);
        let mut solvers = vec![pinv, f32(pinv), tik, f32(tik)];
        solvers.push(SolverChoice {
            lambda: StudyLambda::LCurve,
            ..tik
        });
        for r in [1e-3, 1e-2, 1e-1] {
            solvers.push(SolverChoice {
                lambda: StudyLambda::RelativeToSigmaMax(r),
                ..tik
            });
        }
        let tsvd = SolverChoice::new(Method::Tsvd);
        solvers.push(tsvd);
        for frac in [2, 4] {
            solvers.push(SolverChoice {
                rank: Rank::Fixed((n_unknowns / frac).max(1)),
                ..tsvd
            });
        }
        for k in [0, 10, 30] {
            solvers.push(SolverChoice {
                refine_iterations: k,
                ..fourier
            });
        }
        out.extend(solvers.into_iter().map(|c| with(Sweep::Solver, c)));
    }
    if sweeps.contains(&Sweep::ForceGrid) {
        // Pitches the Fourier solver can also use (marker pitch and twice it), and a
        // coarser grid 1.5x the sensor's.
        let mut pitches = Vec::new();
        if let Some(m) = sensor.layers.iter().find_map(|l| l.markers) {
            pitches.push(m.grid.pitch_mm);
            pitches.push(2.0 * m.grid.pitch_mm);
        }
        pitches.push(1.5 * sensor.force_grid.pitch_mm);
        pitches.retain(|p| (p - sensor.force_grid.pitch_mm).abs() > 1e-9);
        for p in pitches {
            for c in [
                SolverChoice::new(Method::Pinv),
                tik,
                SolverChoice {
                    refine_iterations: 10,
                    ..fourier
                },
            ] {
                out.push(Setting {
                    force_pitch_mm: Some(p),
                    ..with(Sweep::ForceGrid, c)
                });
            }
        }
    }
    if sweeps.contains(&Sweep::Tracking) {
        for s in [0.6, 0.8, 1.25] {
            out.push(Setting {
                sweep: Sweep::Tracking,
                aperture_scale: s,
                ..base
            });
        }
        for it in [1, 2, 4] {
            out.push(Setting {
                sweep: Sweep::Tracking,
                max_iterations: it,
                ..base
            });
        }
    }
    if sweeps.contains(&Sweep::Frames) {
        for &n in frames.iter().filter(|&&n| n > 1) {
            for c in [SolverChoice::new(Method::Pinv), tik] {
                out.push(Setting {
                    frames_averaged: n,
                    ..with(Sweep::Frames, c)
                });
            }
        }
    }
    out
}

/// A force grid of pitch `pitch_mm` covering `grid`'s area, centred on it.
pub fn regrid(grid: &Grid, pitch_mm: f64) -> Grid {
    let extent = [
        grid.pitch_mm * (grid.nx - 1) as f64,
        grid.pitch_mm * (grid.ny - 1) as f64,
    ];
    // A tolerance of 1e-9 pitches so exact multiples are not lost to rounding.
    let n = |e: f64| (e / pitch_mm + 1e-9).floor() as usize + 1;
    let (nx, ny) = (n(extent[0]), n(extent[1]));
    let centre = [
        grid.origin_mm[0] + 0.5 * extent[0],
        grid.origin_mm[1] + 0.5 * extent[1],
    ];
    Grid {
        nx,
        ny,
        pitch_mm,
        origin_mm: [
            centre[0] - 0.5 * pitch_mm * (nx - 1) as f64,
            centre[1] - 0.5 * pitch_mm * (ny - 1) as f64,
        ],
    }
}

/// Which error the Pareto front and the budgets use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Metric {
    /// Relative error of the total force vector `F^sum` (see the module docs).
    #[default]
    Sum,
    /// Relative L2 error of the force field on the force grid.
    Field,
}

impl Metric {
    /// Name as used on the command line and in files.
    pub fn name(self) -> &'static str {
        match self {
            Metric::Sum => "sum",
            Metric::Field => "field",
        }
    }

    /// Axis / column description.
    pub fn describe(self) -> &'static str {
        match self {
            Metric::Sum => "relative error of the total force |ΣF − F_applied| / |F_applied|",
            Metric::Field => "relative L2 error of the force field ‖f − f*‖ / ‖f*‖",
        }
    }
}

impl std::str::FromStr for Metric {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "sum" => Ok(Metric::Sum),
            "field" => Ok(Metric::Field),
            _ => Err(format!("unknown metric `{s}`: expected sum or field")),
        }
    }
}

/// Options of [`run_study`].
#[derive(Debug, Clone, PartialEq)]
pub struct StudyOptions {
    /// The settings to measure.
    pub settings: Vec<Setting>,
    /// Timing repetitions per setting (median reported), ≥ 1.
    pub reps: usize,
    /// Independent force frames the errors are averaged over (RMS), ≥ 1.
    pub realisations: usize,
}

/// The measured accuracy and time of one setting.
#[derive(Debug, Clone, PartialEq)]
pub struct StudyRow {
    /// The setting.
    pub setting: Setting,
    /// Its label ([`Setting::label`]).
    pub label: String,
    /// Relative error of `F^sum` (see the module docs), RMS over the realisations.
    pub sum_error: f64,
    /// Relative L2 error of the force field, RMS over the realisations.
    pub field_error: f64,
    /// Reconstructed total force `F^sum`, N, mean over the realisations.
    pub fsum_n: [f64; 3],
    /// Median time per force frame: tracking `N` frames + averaging + solve, s.
    pub total_s: f64,
    /// Median thread CPU time per force frame (same work as `total_s`), s; NaN where
    /// the platform has no thread CPU clock.
    pub total_cpu_s: f64,
    /// Median time of the tracking part (all `N` frames and the averaging), s.
    pub track_s: f64,
    /// Median time of the solve, s.
    pub solve_s: f64,
    /// Reference detection + solver precompute, s (once per marker set, not per frame).
    pub precompute_s: f64,
    /// Markers used (ok in every averaged frame) / markers in the reference.
    pub markers_used: (usize, usize),
    /// Force points of the grid used.
    pub force_points: usize,
    /// Tracking aperture radius used (first layer), px.
    pub aperture_px: f64,
    /// λ in use, mm/N.
    pub lambda: Option<f64>,
    /// Rank in use.
    pub rank: Option<usize>,
}

impl StudyRow {
    /// The error under `metric`.
    pub fn error(&self, metric: Metric) -> f64 {
        match metric {
            Metric::Sum => self.sum_error,
            Metric::Field => self.field_error,
        }
    }
}

/// A setting that could not be run (e.g. the Fourier solver on incompatible grids).
#[derive(Debug, Clone, PartialEq)]
pub struct Skipped {
    /// The setting.
    pub setting: Setting,
    /// Its label.
    pub label: String,
    /// Why (the library error's message).
    pub reason: String,
}

/// Everything the study measured.
#[derive(Debug, Clone, PartialEq)]
pub struct StudyResult {
    /// One row per setting that ran, in the order given.
    pub rows: Vec<StudyRow>,
    /// Settings that could not run.
    pub skipped: Vec<Skipped>,
    /// The applied total force, N.
    pub applied_n: [f64; 3],
    /// Timing repetitions used.
    pub reps: usize,
    /// Realisations the errors are averaged over.
    pub realisations: usize,
}

/// Progress of [`run_study`].
#[derive(Debug)]
pub enum StudyEvent<'a> {
    /// The reference and `frames` loaded frames were rendered.
    Rendered {
        /// Loaded frames rendered.
        frames: usize,
        /// Wall time, s.
        seconds: f64,
    },
    /// Setting `index` (0-based) of `total` was tracked, solved and scored; its timing
    /// follows (all settings are timed together, round-robin).
    Prepared {
        /// Index.
        index: usize,
        /// Number of settings.
        total: usize,
        /// Its label.
        label: &'a str,
    },
    /// Setting `index` (0-based) of `total` was measured.
    Measured {
        /// Index.
        index: usize,
        /// Number of settings.
        total: usize,
        /// The result.
        row: &'a StudyRow,
    },
    /// Setting `index` of `total` could not run.
    Skipped {
        /// Index.
        index: usize,
        /// Number of settings.
        total: usize,
        /// What and why.
        skipped: &'a Skipped,
    },
}

/// Runs the study on `scene` (its full load, see the module docs).
pub fn run_study(
    scene: &Scene,
    options: &StudyOptions,
    progress: &mut dyn FnMut(StudyEvent<'_>),
) -> Result<StudyResult, StudyError> {
    if options.settings.is_empty() {
        return Err(StudyError::InvalidOption("no settings to measure".into()));
    }
    if options.reps == 0 || options.reps > MAX_REPS {
        return Err(StudyError::InvalidOption(format!(
            "reps = {} must be in 1..={MAX_REPS}",
            options.reps
        )));
    }
    if options.realisations == 0 || options.realisations > MAX_REALISATIONS {
        return Err(StudyError::InvalidOption(format!(
            "realisations = {} must be in 1..={MAX_REALISATIONS}",
            options.realisations
        )));
    }
    for s in &options.settings {
        s.validate()?;
    }
    let max_frames = options.realisations
        * options
            .settings
            .iter()
            .map(|s| s.frames_averaged)
            .max()
            .unwrap_or(1);

    // Render the reference and the loaded frames once; every setting tracks the same
    // images, as a camera would deliver them (8-bit when the scene quantises).
    let t0 = Instant::now();
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
    sim.render_reference(&mut buf)?;
    let reference_frame = convert(&buf);
    let mut frames = Vec::with_capacity(max_frames);
    let mut contact: Option<Contact> = None;
    for k in 1..=max_frames {
        let truth = sim.render_load(&scene.load, k as u64, &mut buf)?;
        frames.push(convert(&buf));
        if contact.is_none() {
            contact = truth.contact;
        }
    }
    progress(StudyEvent::Rendered {
        frames: max_frames,
        seconds: t0.elapsed().as_secs_f64(),
    });
    let contact = contact.ok_or(StudyError::NoLoad)?;
    let applied_n = contact.total_force_n();
    if norm(&applied_n) == 0.0 {
        return Err(StudyError::NoLoad);
    }

    let sensor = &scene.sensor;
    let total = options.settings.len();
    let rendered = Rendered {
        reference: &reference_frame,
        frames: &frames,
        contact: &contact,
        applied_n,
    };
    let mut prepared = Vec::new();
    let mut skipped = Vec::new();
    for (index, setting) in options.settings.iter().enumerate() {
        match prepare(setting, sensor, &rendered, options) {
            Ok(p) => {
                progress(StudyEvent::Prepared {
                    index,
                    total,
                    label: &p.row.label,
                });
                prepared.push((index, p));
            }
            Err(reason) => skip(progress, (index, total), setting, reason, &mut skipped),
        }
    }
    // Timing round-robin: repetition r of every setting before repetition r + 1 of
    // any, so a change of machine load during the study affects all settings alike.
    let mut failed: Vec<(usize, String)> = Vec::new();
    for _ in 0..options.reps {
        for (index, p) in prepared.iter_mut() {
            if failed.iter().any(|(i, _)| i == index) {
                continue;
            }
            if let Err(reason) = p.time_once(&frames) {
                failed.push((*index, reason));
            }
        }
    }
    let mut rows = Vec::new();
    for (index, p) in prepared {
        if let Some((_, reason)) = failed.iter().find(|(i, _)| *i == index) {
            skip(
                progress,
                (index, total),
                &options.settings[index],
                reason.clone(),
                &mut skipped,
            );
            continue;
        }
        let row = p.finish();
        progress(StudyEvent::Measured {
            index,
            total,
            row: &row,
        });
        rows.push(row);
    }
    Ok(StudyResult {
        rows,
        skipped,
        applied_n,
        reps: options.reps,
        realisations: options.realisations,
    })
}

/// Records a setting that could not run and reports it.
fn skip(
    progress: &mut dyn FnMut(StudyEvent<'_>),
    (index, total): (usize, usize),
    setting: &Setting,
    reason: String,
    skipped: &mut Vec<Skipped>,
) {
    let s = Skipped {
        setting: *setting,
        label: setting.label(),
        reason,
    };
    progress(StudyEvent::Skipped {
        index,
        total,
        skipped: &s,
    });
    skipped.push(s);
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

/// Median of `v` (sorted in place); NaN for an empty slice.
pub fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// The two relative errors of a reconstruction: (`e_sum`, `e_field`), see the module
/// docs. `f_n` and `truth_n` interleave `fx, fy, fz` per node.
pub fn force_errors(f_n: &[f64], truth_n: &[f64], applied_n: [f64; 3]) -> (f64, f64) {
    let mut sum = [0.0; 3];
    for (i, v) in f_n.iter().enumerate() {
        sum[i % 3] += v;
    }
    let d = [
        sum[0] - applied_n[0],
        sum[1] - applied_n[1],
        sum[2] - applied_n[2],
    ];
    let e_sum = norm(&d) / norm(&applied_n);
    let diff: f64 = f_n
        .iter()
        .zip(truth_n)
        .map(|(a, b)| (a - b) * (a - b))
        .sum();
    let e_field = diff.sqrt() / norm(truth_n);
    (e_sum, e_field)
}

/// The rendered frames and their truth, shared by every setting.
struct Rendered<'a> {
    reference: &'a Frame,
    frames: &'a [Frame],
    contact: &'a Contact,
    applied_n: [f64; 3],
}

/// Tracks, solves and scores one setting (untimed); an `Err` is the reason it could
/// not run (reported, not fatal).
fn prepare(
    setting: &Setting,
    sensor: &Sensor,
    rendered: &Rendered<'_>,
    options: &StudyOptions,
) -> Result<Prepared, String> {
    let (reps, realisations) = (options.reps, options.realisations);
    let (contact, applied_n) = (rendered.contact, rendered.applied_n);
    let t_pre = Instant::now();
    // Reference detection with the default aperture, then again with the scaled one
    // (the measured aperture is the unit of the scale).
    let view = rendered.reference.view();
    let mut reference =
        detect(&view, sensor, &DetectConfig::default()).map_err(|e| e.to_string())?;
    if setting.aperture_scale != 1.0 {
        let r = reference
            .layers
            .first()
            .map(|l| l.aperture_radius_px)
            .unwrap_or(f64::NAN);
        let config = DetectConfig {
            aperture_radius_px: Some(setting.aperture_scale * r),
            ..DetectConfig::default()
        };
        reference = detect(&view, sensor, &config).map_err(|e| e.to_string())?;
    }
    let aperture_px = reference
        .layers
        .first()
        .map(|l| l.aperture_radius_px)
        .unwrap_or(f64::NAN);
    let n_ref = reference.markers.len();
    let mut tracker = Tracker::new(
        reference,
        TrackConfig {
            mode: TrackMode::PerWindow,
            max_iterations: setting.max_iterations,
            ..TrackConfig::default()
        },
    );
    let n = setting.frames_averaged;
    let all_frames = &rendered.frames[..n * realisations];

    // Untimed pass: which markers are ok in every frame used (the solver's marker set).
    let mut ok_all = vec![true; n_ref];
    for f in all_frames {
        let tracks = tracker.track(&f.view()).map_err(|e| e.to_string())?;
        for (o, t) in ok_all.iter_mut().zip(tracks) {
            *o &= t.status == MarkerStatus::Ok;
        }
    }
    let used: Vec<usize> = (0..n_ref).filter(|&i| ok_all[i]).collect();
    if used.is_empty() {
        return Err("no marker was tracked in every frame".into());
    }
    let sites: Vec<MarkerSite> = used
        .iter()
        .map(|&i| {
            let m = &tracker.reference().markers[i];
            let layer = &sensor.layers[m.layer];
            let position_mm = layer
                .markers
                .map(|g| {
                    let k = m.id as usize;
                    g.grid.node_mm(k % g.grid.nx, k / g.grid.nx)
                })
                .unwrap_or(m.position_mm);
            MarkerSite {
                layer: m.layer,
                position_mm,
                depth_mm: layer.depth_mm,
            }
        })
        .collect();
    let mm_per_px = sensor.camera.mm_per_px;
    let mut u = vec![0.0; 2 * used.len()];
    let first = &all_frames[..n];
    track_average(&mut tracker, first, &used, mm_per_px, &mut u)?;

    // The problem on the setting's force grid; automatic choices on realisation 0.
    let mut grid_sensor = sensor.clone();
    if let Some(p) = setting.force_pitch_mm {
        grid_sensor.force_grid = regrid(&sensor.force_grid, p);
    }
    let problem = Problem::new(&grid_sensor, &sites);
    let mut solver = build_solver(&problem, &setting.solver, &u).map_err(|e| e.to_string())?;
    let precompute_s = t_pre.elapsed().as_secs_f64();

    let truth = contact.force_grid_n(&grid_sensor.force_grid);
    let mut f = vec![0.0; solver.n_outputs()];
    let (mut sum_sq, mut field_sq) = (0.0, 0.0);
    let mut fsum_n = [0.0; 3];
    for group in all_frames.chunks(n) {
        track_average(&mut tracker, group, &used, mm_per_px, &mut u)?;
        solver.apply(&u, &mut f).map_err(|e| e.to_string())?;
        let (e_sum, e_field) = force_errors(&f, &truth, applied_n);
        sum_sq += e_sum * e_sum;
        field_sq += e_field * e_field;
        for (i, v) in f.iter().enumerate() {
            fsum_n[i % 3] += v / realisations as f64;
        }
    }
    let sum_error = (sum_sq / realisations as f64).sqrt();
    let field_error = (field_sq / realisations as f64).sqrt();

    let d = solver.diagnostics();
    let row = StudyRow {
        setting: *setting,
        label: setting.label(),
        sum_error,
        field_error,
        fsum_n,
        total_s: f64::NAN,
        total_cpu_s: f64::NAN,
        track_s: f64::NAN,
        solve_s: f64::NAN,
        precompute_s,
        markers_used: (used.len(), n_ref),
        force_points: grid_sensor.force_grid.len(),
        aperture_px,
        lambda: d.lambda,
        rank: d.rank,
    };
    Ok(Prepared {
        row,
        tracker,
        solver,
        used,
        mm_per_px,
        frames: n,
        u,
        f,
        times: std::array::from_fn(|_| Vec::with_capacity(reps)),
    })
}

/// Tracks `group`, averages the displacements of the `used` markers into `u` (mm).
fn track_average(
    tracker: &mut Tracker,
    group: &[Frame],
    used: &[usize],
    mm_per_px: f64,
    u: &mut [f64],
) -> Result<(), String> {
    u.iter_mut().for_each(|v| *v = 0.0);
    for f in group {
        let tracks = tracker.track(&f.view()).map_err(|e| e.to_string())?;
        for (k, &i) in used.iter().enumerate() {
            // Every used marker was ok in every frame of the untimed pass, and the
            // frames are fixed, so the marker set cannot change here.
            u[2 * k] += tracks[i].displacement_px[0];
            u[2 * k + 1] += tracks[i].displacement_px[1];
        }
    }
    let s = mm_per_px / group.len() as f64;
    u.iter_mut().for_each(|v| *v *= s);
    Ok(())
}

/// A setting ready to be timed: its errors are known, its tracker and solver built.
struct Prepared {
    row: StudyRow,
    tracker: Tracker,
    solver: Box<dyn FrameSolver>,
    used: Vec<usize>,
    mm_per_px: f64,
    /// Frames averaged.
    frames: usize,
    u: Vec<f64>,
    f: Vec<f64>,
    /// Per repetition: tracking, solve, total (wall, s), total (thread CPU, s).
    times: [Vec<f64>; 4],
}

impl Prepared {
    /// One timed repetition on the first realisation's frames.
    fn time_once(&mut self, frames: &[Frame]) -> Result<(), String> {
        let group = &frames[..self.frames];
        // An untimed pass first: round-robin leaves this setting's operator and
        // buffers cold, while a running sensor applies the same solver every frame.
        self.track(group)?;
        self.solve()?;
        // The CPU interval lies inside the wall interval, so CPU ≤ wall per repetition.
        let a = Instant::now();
        let cpu0 = crate::clock::thread_cpu_s();
        self.track(group)?;
        let b = Instant::now();
        self.solve()?;
        let cpu1 = crate::clock::thread_cpu_s();
        let c = Instant::now();
        self.times[0].push((b - a).as_secs_f64());
        self.times[1].push((c - b).as_secs_f64());
        self.times[2].push((c - a).as_secs_f64());
        self.times[3].push(cpu1 - cpu0);
        Ok(())
    }

    /// Tracks `group` and averages its displacements into `u`.
    fn track(&mut self, group: &[Frame]) -> Result<(), String> {
        track_average(
            &mut self.tracker,
            group,
            &self.used,
            self.mm_per_px,
            &mut self.u,
        )
    }

    /// Solves `u` into `f`.
    fn solve(&mut self) -> Result<(), String> {
        self.solver
            .apply(&self.u, &mut self.f)
            .map_err(|e| e.to_string())
    }

    /// The row with the median times.
    fn finish(mut self) -> StudyRow {
        let [t_track, t_solve, t_total, t_cpu] = &mut self.times;
        self.row.track_s = median(t_track);
        self.row.solve_s = median(t_solve);
        self.row.total_s = median(t_total);
        self.row.total_cpu_s = median(t_cpu);
        self.row
    }
}

/// Precomputes the solver of a study choice; `frame` feeds automatic λ / rank.
fn build_solver(
    problem: &Problem<'_>,
    choice: &SolverChoice,
    frame: &[f64],
) -> Result<Box<dyn FrameSolver>, SolveError> {
    let lambda = match choice.lambda {
        StudyLambda::Gcv => Lambda::Gcv,
        StudyLambda::LCurve => Lambda::LCurve,
        StudyLambda::RelativeToSigmaMax(r) => {
            // σ_max of H by power iteration on HᵀH (a dense SVD would double the
            // precompute just to scale λ).
            Lambda::Fixed(r * sigma_max(problem)?)
        }
    };
    let config = SolverConfig {
        method: choice.method,
        lambda,
        rank: choice.rank,
        precision: choice.precision,
        ..SolverConfig::default()
    };
    if choice.method == Method::Fourier {
        // The study times exactly the named count (no early stop at the tolerance).
        let s = FourierSolver::precompute(problem, &config, Some(frame))?
            .with_refinement(choice.refine_iterations)
            .with_refine_tolerance(0.0);
        Ok(Box::new(s))
    } else {
        solve::precompute(problem, &config, Some(frame))
    }
}

/// Largest singular value of the problem's `H`, mm/N, by 100 power iterations on `HᵀH`
/// (relative accuracy far below the decades λ is varied by).
fn sigma_max(problem: &Problem<'_>) -> Result<f64, SolveError> {
    crate::solve::dense::check_dense_size(
        2 * problem.sites.len(),
        3 * problem.sensor.force_grid.len(),
    )?;
    let h = crate::model::transfer_matrix(
        &problem.model,
        problem.sites,
        &problem.sensor.force_points_mm(),
    )?;
    let mut x = nalgebra::DVector::<f64>::from_element(h.ncols(), 1.0);
    let mut sigma = 0.0;
    for _ in 0..100 {
        let y = &h * &x;
        let z = h.tr_mul(&y);
        let nz = z.norm();
        if nz == 0.0 || !nz.is_finite() {
            return Err(SolveError::Decomposition(
                "power iteration for sigma_max found H x = 0".into(),
            ));
        }
        sigma = nz.sqrt() / x.norm().sqrt();
        x = z / nz;
    }
    // With x normalised, ‖HᵀH x‖ → σ_max²; the last update used ‖x‖ = 1.
    Ok(sigma)
}

/// Pareto front of `points` (`time`, `error`), both minimised: `true` where no other
/// point is at least as good in both and strictly better in one. Points with a
/// non-finite coordinate are never on the front and dominate nothing.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<bool> {
    let finite = |p: &(f64, f64)| p.0.is_finite() && p.1.is_finite();
    points
        .iter()
        .map(|p| {
            finite(p)
                && !points
                    .iter()
                    .any(|q| finite(q) && q.0 <= p.0 && q.1 <= p.1 && (q.0 < p.0 || q.1 < p.1))
        })
        .collect()
}

/// Index of the fastest point with `error ≤ budget` (`points` as in [`pareto_front`]);
/// on equal times the smaller error, then the first. `None` when none qualifies.
pub fn fastest_within(points: &[(f64, f64)], budget: f64) -> Option<usize> {
    points
        .iter()
        .enumerate()
        .filter(|(_, p)| p.0.is_finite() && p.1.is_finite() && p.1 <= budget)
        .min_by(|(_, a), (_, b)| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)))
        .map(|(i, _)| i)
}

/// The fastest setting within one error budget.
#[derive(Debug, Clone, PartialEq)]
pub struct BudgetChoice {
    /// The budget (relative error, e.g. 0.05 for 5 %).
    pub budget: f64,
    /// Index into [`StudyResult::rows`], `None` when no setting meets the budget.
    pub row: Option<usize>,
}

impl StudyResult {
    /// `(time per frame, error)` of every row under `metric`.
    pub fn points(&self, metric: Metric) -> Vec<(f64, f64)> {
        self.rows
            .iter()
            .map(|r| (r.total_s, r.error(metric)))
            .collect()
    }

    /// Pareto flags of the rows under `metric`.
    pub fn pareto(&self, metric: Metric) -> Vec<bool> {
        pareto_front(&self.points(metric))
    }

    /// The fastest row within each budget (relative errors) under `metric`.
    pub fn budgets(&self, metric: Metric, budgets: &[f64]) -> Vec<BudgetChoice> {
        let pts = self.points(metric);
        budgets
            .iter()
            .map(|&b| BudgetChoice {
                budget: b,
                row: fastest_within(&pts, b),
            })
            .collect()
    }

    /// Writes the table: one row per setting (columns in [`STUDY_COLUMNS`]), `pareto`
    /// under `metric`.
    pub fn write_csv(&self, path: &Path, metric: Metric) -> Result<(), StudyError> {
        let werr = |e: &dyn std::fmt::Display| StudyError::Write {
            path: path.to_path_buf(),
            message: e.to_string(),
        };
        let mut w = csv::Writer::from_path(path).map_err(|e| werr(&e))?;
        w.write_record(STUDY_COLUMNS).map_err(|e| werr(&e))?;
        let front = self.pareto(metric);
        for (r, on) in self.rows.iter().zip(front) {
            let s = &r.setting;
            let opt = |v: Option<String>| v.unwrap_or_default();
            w.write_record([
                r.label.clone(),
                s.sweep.name().to_string(),
                s.solver.method.name().to_string(),
                match s.solver.precision {
                    Precision::F64 => "f64".to_string(),
                    Precision::F32 => "f32".to_string(),
                },
                s.solver.refine_iterations.to_string(),
                opt(s.force_pitch_mm.map(short)),
                r.force_points.to_string(),
                format!("{:.3}", r.aperture_px),
                s.max_iterations.to_string(),
                s.frames_averaged.to_string(),
                r.markers_used.0.to_string(),
                r.markers_used.1.to_string(),
                format!("{:.6e}", r.sum_error),
                format!("{:.6e}", r.field_error),
                format!("{:.6}", r.fsum_n[0]),
                format!("{:.6}", r.fsum_n[1]),
                format!("{:.6}", r.fsum_n[2]),
                format!("{:.3}", r.track_s * 1e6),
                format!("{:.3}", r.solve_s * 1e6),
                format!("{:.3}", r.total_s * 1e6),
                format!("{:.3}", r.total_cpu_s * 1e6),
                format!("{:.3}", r.precompute_s * 1e3),
                opt(r.lambda.map(|l| format!("{l:.6e}"))),
                opt(r.rank.map(|k| k.to_string())),
                on.to_string(),
            ])
            .map_err(|e| werr(&e))?;
        }
        w.flush().map_err(|e| werr(&e))
    }
}

/// Columns of `accuracy_vs_time.csv`: errors are relative (0.05 = 5 %), times in µs
/// per force frame (medians; `total_cpu_us` in thread CPU time), precompute in ms, forces in N, λ in mm/N.
pub const STUDY_COLUMNS: [&str; 25] = [
    "label",
    "sweep",
    "solver",
    "precision",
    "refine_iterations",
    "force_pitch_mm",
    "force_points",
    "aperture_px",
    "max_iterations",
    "frames_averaged",
    "markers_used",
    "markers_total",
    "sum_error",
    "field_error",
    "fsum_x_n",
    "fsum_y_n",
    "fsum_z_n",
    "track_us",
    "solve_us",
    "total_us",
    "total_cpu_us",
    "precompute_ms",
    "lambda_mm_per_n",
    "rank",
    "pareto",
];

/// Writes `budgets.csv`: `metric,budget,label,error,total_us` (empty label when no
/// setting meets the budget).
pub fn write_budgets_csv(
    path: &Path,
    result: &StudyResult,
    metric: Metric,
    choices: &[BudgetChoice],
) -> Result<(), StudyError> {
    let werr = |e: &dyn std::fmt::Display| StudyError::Write {
        path: path.to_path_buf(),
        message: e.to_string(),
    };
    let mut w = csv::Writer::from_path(path).map_err(|e| werr(&e))?;
    w.write_record(["metric", "budget", "label", "error", "total_us"])
        .map_err(|e| werr(&e))?;
    for c in choices {
        let (label, err, t) = match c.row.map(|i| &result.rows[i]) {
            Some(r) => (
                r.label.clone(),
                format!("{:.6e}", r.error(metric)),
                format!("{:.3}", r.total_s * 1e6),
            ),
            None => (String::new(), String::new(), String::new()),
        };
        w.write_record([
            metric.name().to_string(),
            c.budget.to_string(),
            label,
            err,
            t,
        ])
        .map_err(|e| werr(&e))?;
    }
    w.flush().map_err(|e| werr(&e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pareto_front_of_known_points() {
        // (time, error): a=(1,10) b=(2,5) c=(3,6) [dominated by b] d=(4,1)
        // e=(2,5) [ties b: both stay] f=(5,1) [dominated by d] g=(NaN, 0) [ignored].
        let pts = [
            (1.0, 10.0),
            (2.0, 5.0),
            (3.0, 6.0),
            (4.0, 1.0),
            (2.0, 5.0),
            (5.0, 1.0),
            (f64::NAN, 0.0),
        ];
        assert_eq!(
            pareto_front(&pts),
            vec![true, true, false, true, true, false, false]
        );
    }

    #[test]
    fn budgets_pick_the_fastest_qualifying_point() {
        let pts = [
            (3.0, 0.04),
            (1.0, 0.30),
            (2.0, 0.09),
            (2.0, 0.08),
            (5.0, 0.005),
        ];
        assert_eq!(fastest_within(&pts, 0.01), Some(4));
        assert_eq!(fastest_within(&pts, 0.05), Some(0));
        // Two at time 2 qualify for 10 %: the smaller error wins.
        assert_eq!(fastest_within(&pts, 0.10), Some(3));
        assert_eq!(fastest_within(&pts, 0.5), Some(1));
        assert_eq!(fastest_within(&pts, 0.001), None);
    }

    #[test]
    fn median_of_odd_and_even_lengths() {
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0]), 2.5);
        assert!(median(&mut []).is_nan());
    }

    #[test]
    fn force_errors_of_a_known_field() {
        // Two nodes; truth (0,0,1),(0,0,1); reconstruction (0,0,1.1),(0.1,0,0.9).
        let truth = [0.0, 0.0, 1.0, 0.0, 0.0, 1.0];
        let f = [0.0, 0.0, 1.1, 0.1, 0.0, 0.9];
        let (e_sum, e_field) = force_errors(&f, &truth, [0.0, 0.0, 2.0]);
        // ΣF = (0.1, 0, 2.0): |(0.1,0,0)| / 2 = 0.05.
        assert!((e_sum - 0.05).abs() < 1e-12, "{e_sum}");
        // ‖(0,0,0.1,0.1,0,-0.1)‖ / √2 = √0.03 / √2.
        assert!((e_field - (0.03f64).sqrt() / 2f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn regrid_keeps_the_centre_and_covers_the_area() {
        let g = Grid {
            nx: 10,
            ny: 8,
            pitch_mm: 2.2,
            origin_mm: [-0.9, -0.95],
        };
        let r = regrid(&g, 1.1);
        assert_eq!((r.nx, r.ny), (19, 15));
        assert!((r.origin_mm[0] - g.origin_mm[0]).abs() < 1e-9);
        let r = regrid(&g, 3.0);
        // Extent 19.8 × 15.4 mm: 7 × 6 nodes, centred.
        assert_eq!((r.nx, r.ny), (7, 6));
        let c =
            |g: &Grid, a: usize| g.origin_mm[a] + 0.5 * g.pitch_mm * ([g.nx, g.ny][a] - 1) as f64;
        assert!((c(&r, 0) - c(&g, 0)).abs() < 1e-9 && (c(&r, 1) - c(&g, 1)).abs() < 1e-9);
    }

    #[test]
    fn sigma_max_matches_the_svd() {
        let sensor = crate::sensor::paper_sensor();
        let sites = MarkerSite::from_sensor_grids(&sensor);
        let p = Problem::new(&sensor, &sites);
        let s = sigma_max(&p).unwrap();
        let h = crate::model::transfer_matrix(&p.model, &sites, &sensor.force_points_mm()).unwrap();
        let svd = h.svd(false, false);
        let exact = svd.singular_values.max();
        assert!((s - exact).abs() < 1e-6 * exact, "{s} vs {exact}");
    }

    #[test]
    fn labels_name_what_differs_from_the_baseline() {
        assert_eq!(Setting::baseline().label(), "pinv");
        let s = Setting {
            solver: SolverChoice {
                lambda: StudyLambda::RelativeToSigmaMax(1e-2),
                precision: Precision::F32,
                ..SolverChoice::new(Method::Tikhonov)
            },
            frames_averaged: 4,
            max_iterations: 2,
            ..Setting::baseline()
        };
        assert_eq!(s.label(), "tikhonov λ=1e-2σmax f32 | iter 2 | avg 4");
    }
}
