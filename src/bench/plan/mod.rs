//! Experiment plans (`experiments/*.toml`): what a bench run does, parsed once into
//! validated types with errors that name the file, the key, the value and its unit.
//!
//! ```toml
//! name = "paper-fig7-magnitude"     # free text, used in reports
//! sensor = "paper_sensor.toml"      # relative to the plan file
//! build_id = "elastomer-2026-11"    # optional; `tactbench run --build-id` overrides
//! force_unit = "gf"                 # N | gf: the unit of every force value below
//!
//! [indenter]
//! shape = "hemisphere"              # flat | hemisphere | point
//! diameter_mm = 5.0                 # flat: cylinder diameter; hemisphere: 2 × radius
//!
//! [approach]
//! position_mm = [9.0, 6.75]         # sensor-frame point the indenter is centred on
//! speed_mm_s = 0.5                  # approach / force-control speed
//! contact_force = 5.0               # force (force_unit) that counts as contact
//!
//! [control]
//! force_tolerance = 5.0             # |measured − target| accepted (force_unit)
//! max_steps = 40                    # force-control iterations per setpoint
//!
//! [settle]
//! window_s = 0.5                    # force SD is computed over this window
//! max_sd = 1.0                      # settled when SD < max_sd (force_unit)
//! timeout_s = 10.0                  # give up settling (the row is flagged)
//! dwell_s = 0.0                     # > 0: fixed dwell instead of the SD criterion
//!
//! [acquire]
//! samples = 20                      # F/T samples averaged per setpoint
//! frames = 1                        # camera frames per setpoint
//!
//! [safety]
//! max_force = [300.0, 300.0, 1000.0]  # per component |F| limit (force_unit)
//! travel_min_mm = [0.0, 0.0, -5.0]    # travel box in the SENSOR frame: x, y of the
//! travel_max_mm = [18.0, 13.5, 3.0]   # tip, z = indentation depth (> 0 into the
//!                                     # elastomer, < 0 above it); bench-independent
//! max_speed_mm_s = 5.0
//!
//! [quality]                         # optional: tracking quality gates (defaults shown)
//! reference_min_found_fraction = 0.9  # the reference frame must show this fraction of
//!                                   # the sensor file's markers, else the run stops
//!                                   # before any setpoint (with a diagnosis)
//! min_ok_fraction = 0.9             # a setpoint whose frames leave fewer markers ok
//!                                   # (ok in every frame) is re-acquired ...
//! max_reacquire = 2                 # ... at most this many times (new frames, 0..=10)
//! on_fail = "flag"                  # then: flag (journal quality = "flagged", go on)
//!                                   # | abort (stop the run)
//!
//! [reconstruct]                     # optional: the solver run on every setpoint
//! solver = "pinv"                   # pinv (default) | tikhonov | tsvd | fourier
//! lambda = "gcv"                    # tikhonov / fourier: gcv | lcurve | number (mm/N)
//! rank = "auto"                     # tsvd: auto | integer
//! refine_iterations = 0             # fourier: CGLS iterations after the two-level solve (cap)
//!
//! [sweep]                           # exactly one kind:
//! kind = "magnitude"                # normal force from..to by step, `trials` times
//! from = 0.0
//! to = 750.0
//! step = 50.0
//! trials = 10
//! direction = "up"                  # optional: "up" (default) | "up-down"
//! positions_mm = [[9.0, 6.75], [7.5, 6.75]]  # optional (magnitude, angle): repeat
//!                                   # the trials at each contact position in turn
//! # kind = "angle":        force, angle_from_deg, angle_to_deg, angle_step_deg,
//! #                        direction_deg (azimuth of the tangential part), trials
//! # kind = "hold":         force, duration_s, sample_interval_s, trials (constant
//! #                        normal force held, sampled through it: creep)
//! # kind = "spatial":      force, start_mm = [x, y], end_mm = [x, y], subdivisions
//! #                        (the paper's sub-stepped point loads between two force nodes)
//! # kind = "displacement": shift_mm = [dx, dy], trials (whole-sensor shift, no load)
//! # kind = "setpoints":    [[sweep.points]] with position_mm, normal, tangential = [tx, ty]
//! ```
//!
//! **Up-down sweeps** (`direction = "up-down"`, magnitude only): each trial runs the
//! levels `from, from + step, …` up to the top level (the largest ≤ `to`, measured
//! once) and back down to `from` through the same levels (ISO 376 style). Every row
//! has `direction` = `up` or `down` (the top level is `up`). A trial starts and ends
//! with an unloaded reading (target 0, contact released): with `from = 0` these are
//! the `from` level itself (`swept_value` 0, `up` first, `down` last); with `from >
//! 0` two rows are added, `swept_value` 0, the first `up` and the last `down`. With
//! `"up"` (the default) the sweep is today's and `direction` stays empty. A `down`
//! row reached from a fresh contact (a resumed run) is reached by loading to the top
//! level first (not journalled), so it is measured on unloading as in one pass; the
//! runner approaches every level of such a sweep from one side (no overshoot).
//!
//! **Positions** (`positions_mm = [[x, y], …]`, magnitude and angle): sensor-frame
//! points, mm, in the same frame as `approach.position_mm` (which still places the
//! reference frame), each inside the plan's travel box (checked here) and the
//! sensor's force grid (`run --dry-run`). The plan's trials run at position 0, then
//! all of them at position 1, …; trials are numbered across positions (`trial =
//! position × trials + repetition`, so a trial number names one pass), and every
//! row's `position` is its index in the list (empty without the key).
//!
//! **Hold sweeps** (`kind = "hold"`): `force` (force_unit) held for `duration_s`,
//! sampled at `0, sample_interval_s, 2·sample_interval_s, …` and at `duration_s`
//! ([`hold_schedule`]) after the force is reached; `trials` holds, the contact
//! released between them. The force is controlled once, at the first sample; the
//! stage then holds its position (creep shows as the F/T and F^sum changing) and
//! each sample acquires the F/T mean, the frames and the reconstruction at its time
//! (no settling; journal `hold_t_s` = measured seconds since the force was reached,
//! ≥ the schedule's). An unloaded reading (target 0, `hold_t_s` empty, settled as
//! usual) comes before the first hold (trial 0) and after each hold (that hold's
//! trial), for the drift of the zero. `swept_value` is the target force (force_unit;
//! 0 for the unloaded readings). Caps: the samples and the hold time (`trials ×
//! duration_s` ≤ [`MAX_DURATION_S`]) are checked before anything is expanded.
//!
//! Every setpoint is numbered up front ([`Plan::setpoints`], [`Plan::setpoints_iter`])
//! so `--dry-run`, the journal and resume all see the same numbered list.
//!
//! **Required and default keys.** `name`, `sensor`, `[indenter] shape` (+
//! `diameter_mm` unless `point`), `[approach]`, `[safety]`, `[sweep] kind` and the
//! keys of that kind are required; so is `sweep.trials` for the kinds that repeat
//! (`magnitude`, `angle`, `hold`, `displacement`). Every other key has the default shown in
//! the plan schema of `docs/plans.md`; [`Plan::defaults`] lists the ones a plan left out, and
//! `tactbench run --dry-run` prints them.
//!
//! **Caps, checked before anything is expanded.** The number of setpoints, the frames
//! they write and the estimated duration are computed arithmetically from the sweep's
//! parameters, and a plan above [`MAX_SETPOINTS`], [`MAX_FRAMES`] or
//! [`MAX_DURATION_S`] is refused with the file, the key, its value and the cap, so a
//! typo (`to = 1e9`) costs neither memory nor time. [`Plan::check_frames_on_disk`]
//! adds [`MAX_FRAME_BYTES`] once the sensor file (the image size) is known.
//!
//! The module is split by responsibility: `raw` is the TOML schema as parsed
//! (serde, unknown keys denied), `validate` checks it into a [`Plan`] (defaults
//! recorded, caps computed before anything is expanded), `sweep` the sweep kinds and
//! their setpoint counts, `expand` the numbered setpoints, `schedule` the hold
//! schedule, contact renewal and the duration estimate.

use std::fmt;
use std::path::{Path, PathBuf};

use super::journal::Direction;
use crate::config::{self, Checker, ConfigError};
use crate::solve::SolverConfig;
use crate::units::ForceUnit;

mod expand;
#[cfg(test)]
mod fixtures;
mod raw;
mod schedule;
mod sweep;
mod validate;

pub use schedule::{hold_sample_count, hold_schedule, needs_retract};
pub use sweep::{total_count, ExplicitPoint, Sweep, SweepDirection};

/// An error reading or validating a plan (file, key, value with unit, allowed range).
pub type PlanError = ConfigError;

/// Most setpoints a plan may expand to (the paper's largest plan has 160).
pub const MAX_SETPOINTS: usize = 100_000;

/// Most camera frames a run may write (setpoints × `acquire.frames`).
pub const MAX_FRAMES: usize = 200_000;

/// Longest estimated duration of a plan, s (7 days).
pub const MAX_DURATION_S: f64 = 7.0 * 86_400.0;

/// Most bytes of frames a run may write, estimated as width × height × 3 bytes per
/// frame (uncompressed 8-bit RGB: PNG only makes it smaller), 100 GB.
pub const MAX_FRAME_BYTES: u64 = 100_000_000_000;

/// Most contact positions in `sweep.positions_mm`.
pub const MAX_POSITIONS: usize = 10_000;

/// Largest `settle.timeout_s`, s: ten minutes per setpoint. A settle that has not
/// settled by then will not (the row is flagged anyway); a larger value is a typo (ms
/// for s, an extra digit) that would hold every unsettled setpoint for hours.
pub const MAX_SETTLE_TIMEOUT_S: f64 = 600.0;

/// Retract height above the surface assumed by the plan's own duration estimate
/// (the bench file's `geometry.clearance_mm` default), mm.
pub const DEFAULT_CLEARANCE_MM: f64 = 1.0;

/// The indenter mounted on the stage.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum IndenterShape {
    /// Flat-ended cylinder of the given diameter.
    Flat {
        /// Diameter, mm.
        diameter_mm: f64,
    },
    /// Hemispherical tip of the given diameter.
    Hemisphere {
        /// Diameter, mm.
        diameter_mm: f64,
    },
    /// A (very small) point-like tip.
    Point,
}

impl fmt::Display for IndenterShape {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            IndenterShape::Flat { diameter_mm } => write!(f, "flat cylinder {diameter_mm} mm"),
            IndenterShape::Hemisphere { diameter_mm } => write!(f, "hemisphere {diameter_mm} mm"),
            IndenterShape::Point => f.write_str("point"),
        }
    }
}

/// One target of the run, in internal units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Setpoint {
    /// 0-based index in the plan's expanded list (the journal's key).
    pub index: usize,
    /// Trial number (0-based) for repeated sweeps.
    pub trial: usize,
    /// Where the indenter is centred, sensor frame, mm.
    pub position_mm: [f64; 2],
    /// Target normal force, N (≥ 0; 0 = no contact).
    pub normal_n: f64,
    /// Target tangential force, N (x, y).
    pub tangential_n: [f64; 2],
    /// Whole-sensor shift for displacement-accuracy runs, mm (no load).
    pub shift_mm: [f64; 2],
    /// The swept quantity in its display unit (force_unit, degrees, mm), for reports.
    pub swept_value: f64,
    /// `sweep.direction = "up-down"` magnitude sweeps: loading (`Up`, the top level
    /// and the trial's first unloaded reading included) or unloading (`Down`); `None`
    /// for every other sweep (journal `direction`).
    pub direction: Option<Direction>,
    /// Index into `sweep.positions_mm` when the plan lists contact positions (journal
    /// `position`); `None` otherwise.
    pub position: Option<usize>,
    /// `hold` sweeps: the scheduled time of this sample after the hold force is
    /// reached, s (the journal's `hold_t_s` records the measured time); `None` for the
    /// unloaded readings and every other sweep.
    pub hold_t_s: Option<f64>,
}

/// Safety limits, internal units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Safety {
    /// Per-component |F| limit, N.
    pub max_force_n: [f64; 3],
    /// Travel box minimum in the sensor frame (x, y of the tip; z = indentation depth,
    /// negative above the surface), mm.
    pub travel_min_mm: [f64; 3],
    /// Travel box maximum in the sensor frame (z = deepest allowed indentation), mm.
    pub travel_max_mm: [f64; 3],
    /// Maximum stage speed, mm/s.
    pub max_speed_mm_s: f64,
}

/// Settle criterion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Settle {
    /// Window over which the force SD is computed, s.
    pub window_s: f64,
    /// Settled when the SD of |F| over the window is below this, N.
    pub max_sd_n: f64,
    /// Give up after this long, s.
    pub timeout_s: f64,
    /// When > 0: wait this fixed dwell instead of the SD criterion, s.
    pub dwell_s: f64,
}

/// What a run does with a setpoint that stays below the tracking gate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OnFail {
    /// Journal the row with `quality = flagged` and go on.
    Flag,
    /// Stop the run (aborted); the row is not journalled.
    Abort,
}

impl OnFail {
    /// The name used in plans.
    pub fn name(self) -> &'static str {
        match self {
            OnFail::Flag => "flag",
            OnFail::Abort => "abort",
        }
    }
}

/// Tracking quality gates (`[quality]`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Quality {
    /// Fraction of the sensor file's markers the reference frame must show, else the
    /// run stops before any setpoint (default 0.9).
    pub reference_min_found_fraction: f64,
    /// Fraction of the sensor file's markers that must be ok in every frame of a
    /// setpoint, else its frames are re-acquired (default 0.9).
    pub min_ok_fraction: f64,
    /// Re-acquisitions (new frames at the same setpoint) before the row is flagged or
    /// the run aborts (default 2).
    pub max_reacquire: usize,
    /// What happens then (default flag).
    pub on_fail: OnFail,
    /// A dead camera stops the run: after this many consecutive setpoints whose frames
    /// were blank, saturated or showed no marker in every acquisition (the first and
    /// each re-acquisition), the run stops the stage, retracts and ends aborted
    /// (INCOMPLETE) naming the frame (default 3).
    pub dead_camera_setpoints: usize,
    /// Run-side force plausibility: a row whose |F^sum| is below `force_ratio_min`
    /// times the F/T sensor's |F| (when that is above `force_noise_floor_n`) is
    /// journalled `quality = implausible` (default 0.1).
    pub force_ratio_min: f64,
    /// ... or above `force_ratio_max` times max(|F_ft|, `force_noise_floor_n`)
    /// (default 10).
    pub force_ratio_max: f64,
    /// The F/T magnitude below which the ratio's lower bound is not checked, N (also
    /// three times the row's F/T SD, whichever is larger; default 0.05 N).
    pub force_noise_floor_n: f64,
    /// After this many consecutive implausible rows the run stops, naming the rows and
    /// the likely cause (units of the sensor file, an unfitted modulus; default 3).
    pub max_implausible_rows: usize,
}

/// Default of `quality.reference_min_found_fraction`.
pub const DEFAULT_REFERENCE_MIN_FOUND_FRACTION: f64 = 0.9;
/// Default of `quality.min_ok_fraction`.
pub const DEFAULT_MIN_OK_FRACTION: f64 = 0.9;
/// Default of `quality.max_reacquire`.
pub const DEFAULT_MAX_REACQUIRE: usize = 2;
/// Largest `quality.max_reacquire`.
pub const MAX_REACQUIRE: i64 = 10;
/// Default of `quality.dead_camera_setpoints`.
pub const DEFAULT_DEAD_CAMERA_SETPOINTS: usize = 3;
/// Default of `quality.force_ratio_min`.
pub const DEFAULT_FORCE_RATIO_MIN: f64 = 0.1;
/// Default of `quality.force_ratio_max`.
pub const DEFAULT_FORCE_RATIO_MAX: f64 = 10.0;
/// Default of `quality.force_noise_floor_n`, N.
pub const DEFAULT_FORCE_NOISE_FLOOR_N: f64 = 0.05;
/// Default of `quality.max_implausible_rows`.
pub const DEFAULT_MAX_IMPLAUSIBLE_ROWS: usize = 3;
/// Largest `quality.dead_camera_setpoints` and `quality.max_implausible_rows`.
pub const MAX_CONSECUTIVE: i64 = 1000;

impl Default for Quality {
    fn default() -> Self {
        Quality {
            reference_min_found_fraction: DEFAULT_REFERENCE_MIN_FOUND_FRACTION,
            min_ok_fraction: DEFAULT_MIN_OK_FRACTION,
            max_reacquire: DEFAULT_MAX_REACQUIRE,
            on_fail: OnFail::Flag,
            dead_camera_setpoints: DEFAULT_DEAD_CAMERA_SETPOINTS,
            force_ratio_min: DEFAULT_FORCE_RATIO_MIN,
            force_ratio_max: DEFAULT_FORCE_RATIO_MAX,
            force_noise_floor_n: DEFAULT_FORCE_NOISE_FLOOR_N,
            max_implausible_rows: DEFAULT_MAX_IMPLAUSIBLE_ROWS,
        }
    }
}

/// A validated plan.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    /// The plan file.
    pub path: PathBuf,
    /// Name for reports.
    pub name: String,
    /// Sensor file, resolved relative to the plan.
    pub sensor_path: PathBuf,
    /// Elastomer build id, if given.
    pub build_id: Option<String>,
    /// Unit of the force values as written.
    pub force_unit: ForceUnit,
    /// The indenter.
    pub indenter: IndenterShape,
    /// Sensor-frame point the indenter is centred on, mm.
    pub approach_position_mm: [f64; 2],
    /// Approach speed, mm/s.
    pub approach_speed_mm_s: f64,
    /// Contact detection threshold, N.
    pub contact_force_n: f64,
    /// Force-control tolerance, N.
    pub force_tolerance_n: f64,
    /// Force-control iterations per setpoint.
    pub max_control_steps: usize,
    /// Settle criterion.
    pub settle: Settle,
    /// F/T samples averaged per setpoint.
    pub samples: usize,
    /// Camera frames per setpoint.
    pub frames: usize,
    /// Safety limits.
    pub safety: Safety,
    /// The sweep.
    pub sweep: Sweep,
    /// Solver for the per-setpoint reconstruction (`[reconstruct]`, default pinv).
    pub solver: SolverConfig,
    /// The keys the plan left out and the defaults used for them, `(key, value with
    /// unit)`, in schema order (echoed by `run --dry-run`).
    pub defaults: Vec<(String, String)>,
    /// Tracking quality gates (`[quality]`, defaults when absent).
    pub quality: Quality,
    /// `[sweep] direction` (magnitude sweeps; `Up` for every other kind).
    pub sweep_direction: SweepDirection,
    /// `[sweep] positions_mm`: contact positions (sensor frame, mm) the trials are
    /// repeated at, in turn; empty when the key is absent (the trials run at
    /// `approach.position_mm`).
    pub positions_mm: Vec<[f64; 2]>,
}

impl Plan {
    /// Reads and validates a plan file.
    pub fn from_path(path: impl AsRef<Path>) -> Result<Plan, PlanError> {
        let path = path.as_ref();
        let text = config::read_text(path, "plan")?;
        Plan::from_toml_str(&text, path)
    }

    /// Parses and validates plan TOML; `path` locates the sensor file and names errors.
    pub fn from_toml_str(text: &str, path: impl AsRef<Path>) -> Result<Plan, PlanError> {
        let path = path.as_ref();
        let raw: raw::RawPlan = config::parse_toml(text, path)?;
        raw.validate(path)
    }

    /// Camera frames the whole plan writes (the reference frame not counted).
    pub fn frame_count(&self) -> usize {
        self.setpoint_count() * self.frames
    }

    /// Checks the bytes of frames the run would write against [`MAX_FRAME_BYTES`],
    /// now that the sensor file gives the image size; returns the estimate (bytes,
    /// width × height × 3 per frame, the reference frame included).
    pub fn check_frames_on_disk(&self, sensor: &crate::sensor::Sensor) -> Result<u64, PlanError> {
        let cam = &sensor.camera;
        let per_frame = u64::from(cam.width_px) * u64::from(cam.height_px) * 3;
        let bytes = (self.frame_count() as u64 + 1).saturating_mul(per_frame);
        if bytes > MAX_FRAME_BYTES {
            let c = Checker { path: &self.path };
            return Err(c.invalid(
                "acquire.frames",
                self.frames,
                format!(
                    "{} setpoints x {} frame(s) of {}x{} px (sensor {}) = about {:.1} GB of frames, above the cap of {:.0} GB per run",
                    self.setpoint_count(),
                    self.frames,
                    cam.width_px,
                    cam.height_px,
                    self.sensor_path.display(),
                    bytes as f64 / 1e9,
                    MAX_FRAME_BYTES as f64 / 1e9
                ),
            ));
        }
        Ok(bytes)
    }
}
