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
//! the README's plan schema; [`Plan::defaults`] lists the ones a plan left out, and
//! `tactbench run --dry-run` prints them.
//!
//! **Caps, checked before anything is expanded.** The number of setpoints, the frames
//! they write and the estimated duration are computed arithmetically from the sweep's
//! parameters, and a plan above [`MAX_SETPOINTS`], [`MAX_FRAMES`] or
//! [`MAX_DURATION_S`] is refused with the file, the key, its value and the cap, so a
//! typo (`to = 1e9`) costs neither memory nor time. [`Plan::check_frames_on_disk`]
//! adds [`MAX_FRAME_BYTES`] once the sensor file (the image size) is known.

use std::fmt;
use std::path::{Path, PathBuf};

use super::journal::Direction;
use crate::config::{self, Checker, ConfigError};
use crate::solve::{Lambda, Method, Rank, SolverConfig};
use crate::units::ForceUnit;
use serde::Deserialize;

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

/// `[sweep] direction` of a magnitude sweep.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SweepDirection {
    /// `"up"` (default): each trial runs the levels from `from` up to `to`.
    #[default]
    Up,
    /// `"up-down"`: each trial runs up to `to` and back down to `from` (the top level
    /// measured once), starting and ending with an unloaded reading.
    UpDown,
}

impl SweepDirection {
    /// The name used in plans.
    pub fn name(self) -> &'static str {
        match self {
            SweepDirection::Up => "up",
            SweepDirection::UpDown => "up-down",
        }
    }
}

/// Which sweep the plan runs (display units kept for reports).
#[derive(Debug, Clone, PartialEq)]
pub enum Sweep {
    /// Paper Fig. 7: normal force from..to by step.
    Magnitude {
        /// First force (force_unit).
        from: f64,
        /// Last force (force_unit), inclusive.
        to: f64,
        /// Step (force_unit), > 0.
        step: f64,
        /// Repetitions.
        trials: usize,
    },
    /// Paper Fig. 8: fixed magnitude at angles from the normal.
    Angle {
        /// Force magnitude (force_unit).
        force: f64,
        /// First angle, degrees.
        from_deg: f64,
        /// Last angle, degrees, inclusive (< 90).
        to_deg: f64,
        /// Step, degrees, > 0.
        step_deg: f64,
        /// Azimuth of the tangential part in the sensor plane, degrees from +x.
        direction_deg: f64,
        /// Repetitions.
        trials: usize,
    },
    /// Paper Fig. 9: point loads at sub-steps along a segment.
    Spatial {
        /// Normal force (force_unit).
        force: f64,
        /// Segment start, mm.
        start_mm: [f64; 2],
        /// Segment end, mm.
        end_mm: [f64; 2],
        /// Number of intervals (positions = subdivisions + 1).
        subdivisions: usize,
    },
    /// Constant normal force held for a stated time, sampled through it (creep).
    Hold {
        /// Normal force held (force_unit).
        force: f64,
        /// How long each hold lasts after the force is reached, s.
        duration_s: f64,
        /// Time between samples, s (first at 0, last at `duration_s`).
        sample_interval_s: f64,
        /// Holds (contact released between them).
        trials: usize,
    },
    /// Paper Table I: whole-sensor shift, no load.
    Displacement {
        /// Shift, mm.
        shift_mm: [f64; 2],
        /// Repetitions.
        trials: usize,
    },
    /// An explicit list.
    Setpoints(Vec<ExplicitPoint>),
}

/// One explicit setpoint as written (force_unit).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExplicitPoint {
    /// Position, mm.
    pub position_mm: [f64; 2],
    /// Normal force (force_unit).
    pub normal: f64,
    /// Tangential force (force_unit).
    pub tangential: [f64; 2],
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
}

/// Default of `quality.reference_min_found_fraction`.
pub const DEFAULT_REFERENCE_MIN_FOUND_FRACTION: f64 = 0.9;
/// Default of `quality.min_ok_fraction`.
pub const DEFAULT_MIN_OK_FRACTION: f64 = 0.9;
/// Default of `quality.max_reacquire`.
pub const DEFAULT_MAX_REACQUIRE: usize = 2;
/// Largest `quality.max_reacquire`.
pub const MAX_REACQUIRE: i64 = 10;

impl Default for Quality {
    fn default() -> Self {
        Quality {
            reference_min_found_fraction: DEFAULT_REFERENCE_MIN_FOUND_FRACTION,
            min_ok_fraction: DEFAULT_MIN_OK_FRACTION,
            max_reacquire: DEFAULT_MAX_REACQUIRE,
            on_fail: OnFail::Flag,
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
        let raw: RawPlan = config::parse_toml(text, path)?;
        raw.validate(path)
    }

    /// Every setpoint in run order, in internal units. Bounded by [`MAX_SETPOINTS`]
    /// (validation refuses larger plans before anything is expanded).
    pub fn setpoints(&self) -> Vec<Setpoint> {
        let mut out = Vec::with_capacity(self.setpoint_count());
        out.extend(self.setpoints_iter());
        out
    }

    /// The number of setpoints, computed from the sweep's parameters (nothing is
    /// expanded).
    pub fn setpoint_count(&self) -> usize {
        // Validation bounded the count by MAX_SETPOINTS, so the conversion is exact.
        total_count(&self.sweep, self.sweep_direction, self.positions_mm.len()) as usize
    }

    /// The contact positions the trials run at, in turn: `(Some(index), position)`
    /// for each of `sweep.positions_mm`, or `(None, approach.position_mm)` without it.
    fn trial_positions(&self) -> Vec<(Option<usize>, [f64; 2])> {
        if self.positions_mm.is_empty() {
            vec![(None, self.approach_position_mm)]
        } else {
            self.positions_mm
                .iter()
                .enumerate()
                .map(|(i, p)| (Some(i), *p))
                .collect()
        }
    }

    /// The top level of a magnitude sweep, N (the largest `from + k·step` ≤ `to`);
    /// `None` for other sweeps. A resumed up-down trial loads to it before its next
    /// unloading level, so every `down` row is measured on unloading from the top.
    pub fn top_level_n(&self) -> Option<f64> {
        match &self.sweep {
            Sweep::Magnitude { from, to, step, .. } => {
                let n = level_count(*from, *to, *step);
                Some(self.force_unit.to_newtons(from + step * (n - 1.0)))
            }
            _ => None,
        }
    }

    /// Every setpoint in run order, generated one at a time (no list is built).
    pub fn setpoints_iter(&self) -> impl Iterator<Item = Setpoint> + '_ {
        let u = self.force_unit;
        let pos = self.approach_position_mm;
        let positions = self.trial_positions();
        let updown = self.sweep_direction == SweepDirection::UpDown;
        let raw: Box<dyn Iterator<Item = Raw> + '_> = match &self.sweep {
            Sweep::Magnitude {
                from,
                to,
                step,
                trials,
            } => {
                let (from, step, trials) = (*from, *step, *trials);
                let n = level_count(from, *to, step) as usize;
                // (level value, direction) of one trial.
                let level = move |i: usize, d: Option<Direction>| (from + step * i as f64, d);
                let one_trial = move || -> Box<dyn Iterator<Item = (f64, Option<Direction>)>> {
                    if !updown {
                        return Box::new((0..n).map(move |i| level(i, None)));
                    }
                    // Unloaded readings at both ends even when `from` > 0.
                    let extra = from > 0.0;
                    let up = Some(Direction::Up);
                    let down = Some(Direction::Down);
                    Box::new(
                        extra
                            .then_some((0.0, up))
                            .into_iter()
                            .chain((0..n).map(move |i| level(i, up)))
                            .chain((0..n.saturating_sub(1)).rev().map(move |i| level(i, down)))
                            .chain(extra.then_some((0.0, down))),
                    )
                };
                Box::new(
                    positions
                        .into_iter()
                        .enumerate()
                        .flat_map(move |(pi, (pidx, p))| {
                            (0..trials).flat_map(move |t| {
                                one_trial().map(move |(v, d)| Raw {
                                    trial: pi * trials + t,
                                    position_mm: p,
                                    normal_n: u.to_newtons(v),
                                    swept_value: v,
                                    direction: d,
                                    position: pidx,
                                    ..Raw::default()
                                })
                            })
                        }),
                )
            }
            Sweep::Angle {
                force,
                from_deg,
                to_deg,
                step_deg,
                direction_deg,
                trials,
            } => {
                let f = u.to_newtons(*force);
                let (from, step, trials) = (*from_deg, *step_deg, *trials);
                let n = level_count(from, *to_deg, step) as usize;
                let (dcos, dsin) = cos_sin_deg(*direction_deg);
                Box::new(
                    positions
                        .into_iter()
                        .enumerate()
                        .flat_map(move |(pi, (pidx, p))| {
                            (0..trials).flat_map(move |t| {
                                (0..n).map(move |i| {
                                    let a = from + step * i as f64;
                                    let (c, s) = cos_sin_deg(a);
                                    let tan = f * s;
                                    Raw {
                                        trial: pi * trials + t,
                                        position_mm: p,
                                        normal_n: f * c,
                                        tangential_n: [tan * dcos, tan * dsin],
                                        swept_value: a,
                                        position: pidx,
                                        ..Raw::default()
                                    }
                                })
                            })
                        }),
                )
            }
            Sweep::Hold {
                force,
                duration_s,
                sample_interval_s,
                trials,
            } => {
                let (force, d, dt, trials) = (*force, *duration_s, *sample_interval_s, *trials);
                let f = u.to_newtons(force);
                let unloaded = move |trial: usize| Raw {
                    trial,
                    position_mm: pos,
                    ..Raw::default()
                };
                Box::new(
                    std::iter::once(unloaded(0)).chain((0..trials).flat_map(move |k| {
                        hold_schedule(d, dt)
                            .map(move |t| Raw {
                                trial: k,
                                position_mm: pos,
                                normal_n: f,
                                swept_value: force,
                                hold_t_s: Some(t),
                                ..Raw::default()
                            })
                            .chain(std::iter::once(unloaded(k)))
                    })),
                )
            }
            Sweep::Spatial {
                force,
                start_mm,
                end_mm,
                subdivisions,
            } => {
                let f = u.to_newtons(*force);
                let (a, b, k) = (*start_mm, *end_mm, *subdivisions);
                let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
                Box::new((0..=k).map(move |i| {
                    let s = i as f64 / k as f64;
                    Raw {
                        position_mm: [a[0] + s * (b[0] - a[0]), a[1] + s * (b[1] - a[1])],
                        normal_n: f,
                        swept_value: s * len,
                        ..Raw::default()
                    }
                }))
            }
            Sweep::Displacement { shift_mm, trials } => {
                let shift = *shift_mm;
                Box::new((0..*trials).map(move |t| Raw {
                    trial: t,
                    position_mm: pos,
                    shift_mm: shift,
                    swept_value: shift[0].hypot(shift[1]),
                    ..Raw::default()
                }))
            }
            Sweep::Setpoints(points) => Box::new(points.iter().map(move |p| Raw {
                position_mm: p.position_mm,
                normal_n: u.to_newtons(p.normal),
                tangential_n: [u.to_newtons(p.tangential[0]), u.to_newtons(p.tangential[1])],
                swept_value: p.normal,
                ..Raw::default()
            })),
        };
        raw.enumerate().map(|(index, r)| Setpoint {
            index,
            trial: r.trial,
            position_mm: r.position_mm,
            normal_n: r.normal_n,
            tangential_n: r.tangential_n,
            shift_mm: r.shift_mm,
            swept_value: r.swept_value,
            direction: r.direction,
            position: r.position,
            hold_t_s: r.hold_t_s,
        })
    }

    /// What the sweep repeats and how, for `run --dry-run` (empty for a plain sweep):
    /// the direction of an up-down sweep, the contact positions, a hold's schedule.
    pub fn sweep_summary(&self) -> Vec<String> {
        let fu = self.force_unit.symbol();
        let mut out = Vec::new();
        if let Sweep::Magnitude { from, to, .. } = &self.sweep {
            if self.sweep_direction == SweepDirection::UpDown {
                out.push(format!(
                    "sweep.direction = \"up-down\": each trial runs from {from} up to {to} {fu} (top level once) and back down to {from} {fu}{}; rows direction = up | down",
                    if *from > 0.0 {
                        format!(", with an unloaded reading (0 {fu}, contact released) first (up) and last (down)")
                    } else {
                        String::new()
                    }
                ));
            }
        }
        if !self.positions_mm.is_empty() {
            let trials = match &self.sweep {
                Sweep::Magnitude { trials, .. } | Sweep::Angle { trials, .. } => *trials,
                _ => 0,
            };
            let list: Vec<String> = self
                .positions_mm
                .iter()
                .enumerate()
                .map(|(i, p)| {
                    format!(
                        "{i}: [{}, {}] mm (trials {}..{})",
                        p[0],
                        p[1],
                        i * trials,
                        (i + 1) * trials - 1
                    )
                })
                .collect();
            out.push(format!(
                "sweep.positions_mm: {trials} trial(s) at each of {} positions in turn, trials numbered across positions; {}",
                self.positions_mm.len(),
                list.join(", ")
            ));
        }
        if let Sweep::Hold {
            force,
            duration_s,
            sample_interval_s,
            trials,
        } = &self.sweep
        {
            let times: Vec<f64> = hold_schedule(*duration_s, *sample_interval_s).collect();
            let shown = if times.len() <= 12 {
                times
                    .iter()
                    .map(|t| format!("{t}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            } else {
                format!(
                    "{}, ... ({} samples), {}",
                    times[..5]
                        .iter()
                        .map(|t| format!("{t}"))
                        .collect::<Vec<_>>()
                        .join(", "),
                    times.len(),
                    times[times.len() - 1]
                )
            };
            out.push(format!(
                "hold: {force} {fu} for {duration_s} s, {trials} hold(s); samples at {shown} s after the force is reached (force controlled once, then the stage holds its position); unloaded readings before the first hold and after each (rows with target 0 and hold_t_s empty)"
            ));
        }
        out
    }

    /// Camera frames the whole plan writes (the reference frame not counted).
    pub fn frame_count(&self) -> usize {
        self.setpoint_count() * self.frames
    }

    /// A rough duration estimate for the first `limit` setpoints (all when `None`):
    /// moves at their speeds (retract to `clearance_mm` and back when the contact is
    /// renewed, lateral moves at the safety speed), four control steps per loaded
    /// setpoint, the settle window × 1.2 (or the dwell), acquisition at 1 kHz and
    /// 30 ms per frame. Streams over the setpoints: no list is built.
    pub fn estimate_duration_s(&self, clearance_mm: f64, limit: Option<usize>) -> f64 {
        let v = self.approach_speed_mm_s;
        let vmax = self.safety.max_speed_mm_s;
        let settle = if self.settle.dwell_s > 0.0 {
            self.settle.dwell_s
        } else {
            self.settle.window_s * 1.2
        };
        let per_setpoint = settle + self.samples as f64 * 1e-3 + self.frames as f64 * 0.03;
        let mut t = 0.0;
        let mut prev: Option<Setpoint> = None;
        let acquisition = self.samples as f64 * 1e-3 + self.frames as f64 * 0.03;
        for sp in self.setpoints_iter().take(limit.unwrap_or(usize::MAX)) {
            // A hold sample after the first waits for its time in the schedule (the
            // acquisition happens within that wait, or later when it is longer).
            if let (Some(t_hold), Some(t_prev)) = (sp.hold_t_s, prev.and_then(|p| p.hold_t_s)) {
                if t_hold > t_prev && !needs_retract(prev.as_ref(), &sp) {
                    t += (t_hold - t_prev).max(acquisition);
                    prev = Some(sp);
                    continue;
                }
            }
            if needs_retract(prev.as_ref(), &sp) {
                t += 2.0 * clearance_mm / vmax + 0.5;
                if let Some(p) = prev {
                    t += (p.position_mm[0] - sp.position_mm[0])
                        .hypot(p.position_mm[1] - sp.position_mm[1])
                        / vmax;
                }
                if sp.normal_n > 0.0 {
                    t += clearance_mm / v;
                }
            }
            if sp.normal_n > 0.0 {
                t += 4.0 * (0.1 / v + 0.02);
            }
            // The first sample of a hold is taken as soon as the force is reached.
            t += if sp.hold_t_s.is_some() {
                acquisition
            } else {
                per_setpoint
            };
            prev = Some(sp);
        }
        t
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

impl Sweep {
    /// The number of setpoints the sweep expands to, from its parameters alone (as
    /// f64: a typo can make it astronomically large, which validation refuses), for
    /// `direction = "up"` at one position; [`total_count`] includes both.
    pub fn count(&self) -> f64 {
        match self {
            Sweep::Magnitude {
                from,
                to,
                step,
                trials,
            } => level_count(*from, *to, *step) * *trials as f64,
            Sweep::Angle {
                from_deg,
                to_deg,
                step_deg,
                trials,
                ..
            } => level_count(*from_deg, *to_deg, *step_deg) * *trials as f64,
            Sweep::Spatial { subdivisions, .. } => *subdivisions as f64 + 1.0,
            Sweep::Hold {
                duration_s,
                sample_interval_s,
                trials,
                ..
            } => {
                // An unloaded reading before the first hold and after each.
                (hold_sample_count(*duration_s, *sample_interval_s) + 1.0) * *trials as f64 + 1.0
            }
            Sweep::Displacement { trials, .. } => *trials as f64,
            Sweep::Setpoints(points) => points.len() as f64,
        }
    }
}

/// A setpoint before it is numbered (internal units, as in [`Setpoint`]).
#[derive(Clone, Copy, Default)]
struct Raw {
    trial: usize,
    position_mm: [f64; 2],
    normal_n: f64,
    tangential_n: [f64; 2],
    shift_mm: [f64; 2],
    swept_value: f64,
    direction: Option<Direction>,
    position: Option<usize>,
    hold_t_s: Option<f64>,
}

/// Samples per hold: `0, dt, 2·dt, … ≤ duration`, plus `duration` itself when it is
/// not on that grid (as f64: a typo can make it astronomically large, which
/// validation refuses before anything is listed).
pub fn hold_sample_count(duration_s: f64, sample_interval_s: f64) -> f64 {
    let k = (duration_s / sample_interval_s + 1e-9).floor();
    let on_grid = (duration_s - k * sample_interval_s).abs() <= 1e-9 * duration_s.max(1.0);
    k + 1.0 + if on_grid { 0.0 } else { 1.0 }
}

/// The sample times of one hold, s after the hold force is reached: `0, dt, 2·dt, …`
/// and the last at `duration` (see [`hold_sample_count`]).
pub fn hold_schedule(duration_s: f64, sample_interval_s: f64) -> impl Iterator<Item = f64> {
    let n = hold_sample_count(duration_s, sample_interval_s) as usize;
    (0..n).map(move |k| (k as f64 * sample_interval_s).min(duration_s))
}

/// The number of setpoints of a sweep with its direction and `positions` contact
/// positions (0 = the approach position only), from the parameters alone.
pub fn total_count(sweep: &Sweep, direction: SweepDirection, positions: usize) -> f64 {
    let positions = positions.max(1) as f64;
    match sweep {
        Sweep::Magnitude {
            from,
            to,
            step,
            trials,
        } => {
            let n = level_count(*from, *to, *step);
            let per_trial = match direction {
                SweepDirection::Up => n,
                SweepDirection::UpDown => 2.0 * n - 1.0 + if *from > 0.0 { 2.0 } else { 0.0 },
            };
            per_trial * *trials as f64 * positions
        }
        Sweep::Angle { .. } => sweep.count() * positions,
        _ => sweep.count(),
    }
}

/// Whether the contact must be renewed (retract first) between `prev` and `sp`.
pub fn needs_retract(prev: Option<&Setpoint>, sp: &Setpoint) -> bool {
    let Some(p) = prev else { return true };
    let tangential = |s: &Setpoint| s.tangential_n != [0.0, 0.0];
    p.trial != sp.trial
        || p.position_mm != sp.position_mm
        || tangential(p)
        || tangential(sp)
        || sp.normal_n <= 0.0
        || p.normal_n <= 0.0
        || sp.shift_mm != [0.0, 0.0]
}

/// Rounds away unit-conversion noise for messages (1000 gf, not 999.9999999999999 gf).
fn round9(v: f64) -> f64 {
    (v * 1e9).round() / 1e9
}

/// The number of values `from, from+step, …` up to `to` inclusive (within a small
/// tolerance), computed without listing them.
fn level_count(from: f64, to: f64, step: f64) -> f64 {
    ((to - from) / step + 1e-9).floor() + 1.0
}

/// cos and sin of an angle in degrees, exact at multiples of 90° (so a tangential
/// load along +y has no 6e-17 x component).
fn cos_sin_deg(deg: f64) -> (f64, f64) {
    let quarter = deg / 90.0;
    if quarter.fract() == 0.0 && quarter.abs() < 1e15 {
        match (quarter as i64).rem_euclid(4) {
            0 => (1.0, 0.0),
            1 => (0.0, 1.0),
            2 => (-1.0, 0.0),
            _ => (0.0, -1.0),
        }
    } else {
        let r = deg.to_radians();
        (r.cos(), r.sin())
    }
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

// ---- raw schema ---------------------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPlan {
    name: String,
    sensor: String,
    build_id: Option<String>,
    force_unit: Option<String>,
    indenter: RawIndenter,
    approach: RawApproach,
    #[serde(default)]
    control: RawControl,
    #[serde(default)]
    settle: RawSettle,
    #[serde(default)]
    acquire: RawAcquire,
    safety: RawSafety,
    sweep: RawSweep,
    #[serde(default)]
    reconstruct: RawReconstruct,
    #[serde(default)]
    quality: RawQuality,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct RawQuality {
    reference_min_found_fraction: Option<f64>,
    min_ok_fraction: Option<f64>,
    max_reacquire: Option<i64>,
    on_fail: Option<String>,
}

impl RawQuality {
    fn validate(&self, c: &Checker<'_>) -> Result<Quality, PlanError> {
        let d = Quality::default();
        let fraction = |key: &str, v: Option<f64>, default: f64| {
            let v = v.unwrap_or(default);
            if v.is_finite() && (0.0..=1.0).contains(&v) {
                Ok(v)
            } else {
                Err(c.invalid(
                    key,
                    v,
                    "must be a fraction in [0, 1] of the sensor file's markers",
                ))
            }
        };
        let max_reacquire = match self.max_reacquire {
            None => d.max_reacquire,
            Some(v) if (0..=MAX_REACQUIRE).contains(&v) => v as usize,
            Some(v) => {
                return Err(c.invalid(
                    "quality.max_reacquire",
                    v,
                    format!("must be an integer in [0, {MAX_REACQUIRE}] (re-acquisitions)"),
                ))
            }
        };
        let on_fail = match self.on_fail.as_deref() {
            None | Some("flag") => OnFail::Flag,
            Some("abort") => OnFail::Abort,
            Some(other) => {
                return Err(c.invalid(
                    "quality.on_fail",
                    format!("{other:?}"),
                    "expected \"flag\" or \"abort\"",
                ))
            }
        };
        Ok(Quality {
            reference_min_found_fraction: fraction(
                "quality.reference_min_found_fraction",
                self.reference_min_found_fraction,
                d.reference_min_found_fraction,
            )?,
            min_ok_fraction: fraction(
                "quality.min_ok_fraction",
                self.min_ok_fraction,
                d.min_ok_fraction,
            )?,
            max_reacquire,
            on_fail,
        })
    }
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct RawReconstruct {
    solver: Option<String>,
    lambda: Option<toml::Value>,
    rank: Option<toml::Value>,
    refine_iterations: Option<i64>,
}

/// Defaults of the optional keys (README plan schema; echoed by `run --dry-run`).
const DEFAULT_FORCE_UNIT: &str = "N";
const DEFAULT_MAX_STEPS: i64 = 40;
const DEFAULT_WINDOW_S: f64 = 0.5;
const DEFAULT_TIMEOUT_S: f64 = 10.0;
const DEFAULT_DWELL_S: f64 = 0.0;
const DEFAULT_SAMPLES: i64 = 20;
const DEFAULT_FRAMES: i64 = 1;
const DEFAULT_DIRECTION_DEG: f64 = 0.0;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawIndenter {
    shape: String,
    diameter_mm: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawApproach {
    position_mm: [f64; 2],
    speed_mm_s: f64,
    contact_force: f64,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct RawControl {
    force_tolerance: Option<f64>,
    max_steps: Option<i64>,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct RawSettle {
    window_s: Option<f64>,
    max_sd: Option<f64>,
    timeout_s: Option<f64>,
    dwell_s: Option<f64>,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct RawAcquire {
    samples: Option<i64>,
    frames: Option<i64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSafety {
    max_force: [f64; 3],
    travel_min_mm: [f64; 3],
    travel_max_mm: [f64; 3],
    max_speed_mm_s: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSweep {
    kind: String,
    from: Option<f64>,
    to: Option<f64>,
    step: Option<f64>,
    trials: Option<i64>,
    force: Option<f64>,
    angle_from_deg: Option<f64>,
    angle_to_deg: Option<f64>,
    angle_step_deg: Option<f64>,
    direction_deg: Option<f64>,
    start_mm: Option<[f64; 2]>,
    end_mm: Option<[f64; 2]>,
    subdivisions: Option<i64>,
    shift_mm: Option<[f64; 2]>,
    points: Option<Vec<RawPoint>>,
    direction: Option<String>,
    positions_mm: Option<Vec<[f64; 2]>>,
    duration_s: Option<f64>,
    sample_interval_s: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPoint {
    position_mm: [f64; 2],
    normal: f64,
    tangential: Option<[f64; 2]>,
}

/// The optional keys a plan left out, with the defaults used (for `--dry-run`).
#[derive(Default)]
struct Defaults(Vec<(String, String)>);

impl Defaults {
    /// `v`, or `default` (recorded as `key = show(default)`) when the key is absent.
    fn take<T: Clone>(
        &mut self,
        v: Option<T>,
        default: T,
        key: &str,
        show: impl FnOnce(T) -> String,
    ) -> T {
        match v {
            Some(v) => v,
            None => {
                self.push(key, show(default.clone()));
                default
            }
        }
    }

    fn push(&mut self, key: &str, value: String) {
        self.0.push((key.to_string(), value));
    }
}

/// The setpoint and frame caps, from the sweep's parameters alone (before anything
/// is expanded). `max_normal` is `safety.max_force[2]` in the plan's force unit.
fn check_caps(
    c: &Checker<'_>,
    sweep: &Sweep,
    direction: SweepDirection,
    positions: usize,
    frames: usize,
    fu: &str,
    max_normal: f64,
) -> Result<(), PlanError> {
    if let Sweep::Hold {
        duration_s, trials, ..
    } = sweep
    {
        let hold_s = duration_s * *trials as f64;
        if hold_s > MAX_DURATION_S {
            return Err(c.invalid(
                "sweep.duration_s",
                format!("{duration_s} s"),
                format!(
                    "sweep.trials {trials} holds of sweep.duration_s {duration_s} s = {:.1} h of holding alone, above the cap of {:.0} h per plan",
                    hold_s / 3600.0,
                    MAX_DURATION_S / 3600.0
                ),
            ));
        }
    }
    let total = total_count(sweep, direction, positions);
    let base = sweep.count();
    // NaN (cannot happen after the range checks) is refused as well.
    if total.is_nan() || total > MAX_SETPOINTS as f64 {
        let (key, value, how) = match sweep {
            _ if base <= MAX_SETPOINTS as f64 && positions > 1 && base * positions as f64 > MAX_SETPOINTS as f64 => (
                "sweep.positions_mm",
                format!("{positions} positions"),
                format!(
                    "{base:.0} setpoints per position x {positions} positions = {total:.0} setpoints"
                ),
            ),
            Sweep::Hold {
                duration_s,
                sample_interval_s,
                trials,
                ..
            } => {
                let per_hold = hold_sample_count(*duration_s, *sample_interval_s);
                let how = format!(
                    "sweep.duration_s {duration_s} s sampled every sweep.sample_interval_s {sample_interval_s} s is {per_hold:.0} samples per hold x sweep.trials {trials} (+ {} unloaded readings) = {total:.0} setpoints",
                    trials + 1
                );
                if per_hold <= MAX_SETPOINTS as f64 {
                    ("sweep.trials", trials.to_string(), how)
                } else {
                    ("sweep.sample_interval_s", format!("{sample_interval_s} s"), how)
                }
            }
            Sweep::Magnitude {
                from,
                to,
                step,
                trials,
            } => {
                let levels = level_count(*from, *to, *step);
                let how = match direction {
                    SweepDirection::Up => format!(
                        "sweep.from {from} to sweep.to {to} {fu} by sweep.step {step} {fu} is {levels:.0} levels x sweep.trials {trials} = {total:.0} setpoints"
                    ),
                    SweepDirection::UpDown => format!(
                        "sweep.from {from} to sweep.to {to} {fu} by sweep.step {step} {fu} is {levels:.0} levels, up and down (sweep.direction = \"up-down\") x sweep.trials {trials} = {total:.0} setpoints"
                    ),
                };
                if levels <= MAX_SETPOINTS as f64 {
                    ("sweep.trials", trials.to_string(), how)
                } else if *to > max_normal {
                    (
                        "sweep.to",
                        format!("{to} {fu}"),
                        format!(
                            "{how} (and sweep.to is above safety.max_force[2] = {} {fu})",
                            round9(max_normal)
                        ),
                    )
                } else {
                    ("sweep.step", format!("{step} {fu}"), how)
                }
            }
            Sweep::Angle {
                from_deg,
                to_deg,
                step_deg,
                trials,
                ..
            } => {
                let levels = level_count(*from_deg, *to_deg, *step_deg);
                let how = format!(
                    "sweep.angle_from_deg {from_deg} to sweep.angle_to_deg {to_deg} deg by sweep.angle_step_deg {step_deg} deg is {levels:.0} angles x sweep.trials {trials} = {total:.0} setpoints"
                );
                if levels <= MAX_SETPOINTS as f64 {
                    ("sweep.trials", trials.to_string(), how)
                } else {
                    ("sweep.angle_step_deg", format!("{step_deg} deg"), how)
                }
            }
            _ => (
                "sweep",
                format!("{total:.0} setpoints"),
                "the sweep is too long".to_string(),
            ),
        };
        return Err(c.invalid(
            key,
            value,
            format!("{how}, above the cap of {MAX_SETPOINTS} setpoints per plan"),
        ));
    }
    let n_frames = total * frames as f64;
    if n_frames > MAX_FRAMES as f64 {
        return Err(c.invalid(
            "acquire.frames",
            frames,
            format!(
                "{total:.0} setpoints x {frames} frames = {n_frames:.0} frames, above the cap of {MAX_FRAMES} frames per plan"
            ),
        ));
    }
    Ok(())
}

/// A key the chosen sweep kind requires.
fn need<T>(c: &Checker<'_>, key: &str, v: Option<T>, kind: &str) -> Result<T, PlanError> {
    v.ok_or_else(|| {
        c.invalid(
            key,
            "(missing)",
            format!("required by sweep kind \"{kind}\""),
        )
    })
}

impl RawPlan {
    fn validate(self, path: &Path) -> Result<Plan, PlanError> {
        let c = Checker { path };
        let mut defaults = Defaults::default();
        let unit_text = defaults.take(
            self.force_unit.clone(),
            DEFAULT_FORCE_UNIT.to_string(),
            "force_unit",
            |v| format!("{v:?}"),
        );
        let unit: ForceUnit = unit_text
            .parse()
            .map_err(|e: String| c.invalid("force_unit", format!("{unit_text:?}"), e))?;
        let fu = unit.symbol();
        let n = |v: f64| unit.to_newtons(v);

        let indenter = match self.indenter.shape.as_str() {
            "flat" | "hemisphere" => {
                let d = need(
                    &c,
                    "indenter.diameter_mm",
                    self.indenter.diameter_mm,
                    &self.indenter.shape,
                )?;
                let diameter_mm = c.positive("indenter.diameter_mm", d, "mm")?;
                if self.indenter.shape == "flat" {
                    IndenterShape::Flat { diameter_mm }
                } else {
                    IndenterShape::Hemisphere { diameter_mm }
                }
            }
            "point" => IndenterShape::Point,
            other => {
                return Err(c.invalid(
                    "indenter.shape",
                    format!("{other:?}"),
                    "unknown shape: expected flat, hemisphere or point",
                ))
            }
        };

        let a = &self.approach;
        let approach_position_mm = [
            c.finite("approach.position_mm[0]", a.position_mm[0], "mm")?,
            c.finite("approach.position_mm[1]", a.position_mm[1], "mm")?,
        ];
        let approach_speed_mm_s = c.positive("approach.speed_mm_s", a.speed_mm_s, "mm/s")?;
        let contact_force_n = n(c.positive("approach.contact_force", a.contact_force, fu)?);

        let s = &self.safety;
        let mut max_force_n = [0.0; 3];
        for (i, v) in s.max_force.iter().enumerate() {
            max_force_n[i] = n(c.positive(&format!("safety.max_force[{i}]"), *v, fu)?);
        }
        for i in 0..3 {
            c.finite(
                &format!("safety.travel_min_mm[{i}]"),
                s.travel_min_mm[i],
                "mm",
            )?;
            c.finite(
                &format!("safety.travel_max_mm[{i}]"),
                s.travel_max_mm[i],
                "mm",
            )?;
            if s.travel_min_mm[i] >= s.travel_max_mm[i] {
                return Err(c.invalid(
                    &format!("safety.travel_max_mm[{i}]"),
                    format!("{} mm", s.travel_max_mm[i]),
                    format!(
                        "must exceed safety.travel_min_mm[{i}] = {} mm",
                        s.travel_min_mm[i]
                    ),
                ));
            }
        }
        let max_speed_mm_s = c.positive("safety.max_speed_mm_s", s.max_speed_mm_s, "mm/s")?;
        if approach_speed_mm_s > max_speed_mm_s {
            return Err(c.invalid(
                "approach.speed_mm_s",
                format!("{approach_speed_mm_s} mm/s"),
                format!("must not exceed safety.max_speed_mm_s = {max_speed_mm_s} mm/s"),
            ));
        }
        let safety = Safety {
            max_force_n,
            travel_min_mm: s.travel_min_mm,
            travel_max_mm: s.travel_max_mm,
            max_speed_mm_s,
        };

        let with_fu = |v: f64| format!("{} {fu}", round9(v));
        let tol_default = unit.from_newtons(contact_force_n);
        let force_tolerance_n = n(c.positive(
            "control.force_tolerance",
            defaults.take(
                self.control.force_tolerance,
                tol_default,
                "control.force_tolerance",
                |v| format!("{} (approach.contact_force)", with_fu(v)),
            ),
            fu,
        )?);
        let max_control_steps = c.count(
            "control.max_steps",
            defaults.take(
                self.control.max_steps,
                DEFAULT_MAX_STEPS,
                "control.max_steps",
                |v| v.to_string(),
            ),
            10_000,
        )?;

        let st = &self.settle;
        let secs = |v: f64| format!("{v} s");
        let settle = Settle {
            window_s: c.positive(
                "settle.window_s",
                defaults.take(st.window_s, DEFAULT_WINDOW_S, "settle.window_s", secs),
                "s",
            )?,
            max_sd_n: n(c.positive(
                "settle.max_sd",
                defaults.take(
                    st.max_sd,
                    unit.from_newtons(force_tolerance_n) / 2.0,
                    "settle.max_sd",
                    |v| format!("{} (control.force_tolerance / 2)", with_fu(v)),
                ),
                fu,
            )?),
            timeout_s: c.positive(
                "settle.timeout_s",
                defaults.take(st.timeout_s, DEFAULT_TIMEOUT_S, "settle.timeout_s", secs),
                "s",
            )?,
            dwell_s: c.non_negative(
                "settle.dwell_s",
                defaults.take(st.dwell_s, DEFAULT_DWELL_S, "settle.dwell_s", secs),
                "s",
            )?,
        };
        let samples = c.count(
            "acquire.samples",
            defaults.take(
                self.acquire.samples,
                DEFAULT_SAMPLES,
                "acquire.samples",
                |v| v.to_string(),
            ),
            100_000,
        )?;
        let frames = c.count(
            "acquire.frames",
            defaults.take(self.acquire.frames, DEFAULT_FRAMES, "acquire.frames", |v| {
                v.to_string()
            }),
            1000,
        )?;

        let sw = self.sweep;
        let kind = sw.kind.clone();
        let trials = |c: &Checker| {
            c.count(
                "sweep.trials",
                need(c, "sweep.trials", sw.trials, &kind)?,
                10_000,
            )
        };
        let sweep = match kind.as_str() {
            "magnitude" => {
                let from =
                    c.non_negative("sweep.from", need(&c, "sweep.from", sw.from, &kind)?, fu)?;
                let to = c.non_negative("sweep.to", need(&c, "sweep.to", sw.to, &kind)?, fu)?;
                let step = c.positive("sweep.step", need(&c, "sweep.step", sw.step, &kind)?, fu)?;
                if to < from {
                    return Err(c.invalid(
                        "sweep.to",
                        format!("{to} {fu}"),
                        format!("must be >= sweep.from = {from} {fu}"),
                    ));
                }
                Sweep::Magnitude {
                    from,
                    to,
                    step,
                    trials: trials(&c)?,
                }
            }
            "angle" => {
                let force =
                    c.positive("sweep.force", need(&c, "sweep.force", sw.force, &kind)?, fu)?;
                let from_deg = need(&c, "sweep.angle_from_deg", sw.angle_from_deg, &kind)?;
                let to_deg = need(&c, "sweep.angle_to_deg", sw.angle_to_deg, &kind)?;
                for (key, v) in [
                    ("sweep.angle_from_deg", from_deg),
                    ("sweep.angle_to_deg", to_deg),
                ] {
                    if !(v.is_finite() && (0.0..90.0).contains(&v)) {
                        return Err(c.invalid(
                            key,
                            format!("{v} deg"),
                            "must be in [0, 90) deg from the normal",
                        ));
                    }
                }
                if to_deg < from_deg {
                    return Err(c.invalid(
                        "sweep.angle_to_deg",
                        format!("{to_deg} deg"),
                        format!("must be >= sweep.angle_from_deg = {from_deg} deg"),
                    ));
                }
                Sweep::Angle {
                    force,
                    from_deg,
                    to_deg,
                    step_deg: c.positive(
                        "sweep.angle_step_deg",
                        need(&c, "sweep.angle_step_deg", sw.angle_step_deg, &kind)?,
                        "deg",
                    )?,
                    direction_deg: c.finite(
                        "sweep.direction_deg",
                        defaults.take(
                            sw.direction_deg,
                            DEFAULT_DIRECTION_DEG,
                            "sweep.direction_deg",
                            |v| format!("{v} deg (+x)"),
                        ),
                        "deg",
                    )?,
                    trials: trials(&c)?,
                }
            }
            "spatial" => {
                let force =
                    c.positive("sweep.force", need(&c, "sweep.force", sw.force, &kind)?, fu)?;
                let start_mm = need(&c, "sweep.start_mm", sw.start_mm, &kind)?;
                let end_mm = need(&c, "sweep.end_mm", sw.end_mm, &kind)?;
                for (key, p) in [("sweep.start_mm", start_mm), ("sweep.end_mm", end_mm)] {
                    c.finite(key, p[0], "mm")?;
                    c.finite(key, p[1], "mm")?;
                }
                Sweep::Spatial {
                    force,
                    start_mm,
                    end_mm,
                    subdivisions: c.count(
                        "sweep.subdivisions",
                        need(&c, "sweep.subdivisions", sw.subdivisions, &kind)?,
                        10_000,
                    )?,
                }
            }
            "hold" => {
                let force =
                    c.positive("sweep.force", need(&c, "sweep.force", sw.force, &kind)?, fu)?;
                let duration_s = c.positive(
                    "sweep.duration_s",
                    need(&c, "sweep.duration_s", sw.duration_s, &kind)?,
                    "s",
                )?;
                let sample_interval_s = c.positive(
                    "sweep.sample_interval_s",
                    need(&c, "sweep.sample_interval_s", sw.sample_interval_s, &kind)?,
                    "s",
                )?;
                if sample_interval_s > duration_s {
                    return Err(c.invalid(
                        "sweep.sample_interval_s",
                        format!("{sample_interval_s} s"),
                        format!("must not exceed sweep.duration_s = {duration_s} s"),
                    ));
                }
                Sweep::Hold {
                    force,
                    duration_s,
                    sample_interval_s,
                    trials: trials(&c)?,
                }
            }
            "displacement" => {
                let shift_mm = need(&c, "sweep.shift_mm", sw.shift_mm, &kind)?;
                c.finite("sweep.shift_mm[0]", shift_mm[0], "mm")?;
                c.finite("sweep.shift_mm[1]", shift_mm[1], "mm")?;
                Sweep::Displacement {
                    shift_mm,
                    trials: trials(&c)?,
                }
            }
            "setpoints" => {
                let points = need(&c, "sweep.points", sw.points, &kind)?;
                if points.is_empty() {
                    return Err(c.invalid(
                        "sweep.points",
                        "[]",
                        "at least one [[sweep.points]] is required",
                    ));
                }
                if points.len() > MAX_SETPOINTS {
                    return Err(c.invalid(
                        "sweep.points",
                        format!("{} points", points.len()),
                        format!("a plan may have at most {MAX_SETPOINTS} setpoints (cap)"),
                    ));
                }
                let mut out = Vec::with_capacity(points.len());
                let mut untangential = false;
                for (i, p) in points.into_iter().enumerate() {
                    untangential |= p.tangential.is_none();
                    let tangential = p.tangential.unwrap_or([0.0; 2]);
                    let key = format!("sweep.points[{i}]");
                    c.finite(&format!("{key}.position_mm[0]"), p.position_mm[0], "mm")?;
                    c.finite(&format!("{key}.position_mm[1]"), p.position_mm[1], "mm")?;
                    out.push(ExplicitPoint {
                        position_mm: p.position_mm,
                        normal: c.non_negative(&format!("{key}.normal"), p.normal, fu)?,
                        tangential: [
                            c.finite(&format!("{key}.tangential[0]"), tangential[0], fu)?,
                            c.finite(&format!("{key}.tangential[1]"), tangential[1], fu)?,
                        ],
                    });
                }
                if untangential {
                    defaults.push(
                        "sweep.points[].tangential",
                        format!("[0, 0] {fu} (where not given)"),
                    );
                }
                Sweep::Setpoints(out)
            }
            other => {
                return Err(c.invalid(
                    "sweep.kind",
                    format!("{other:?}"),
                    "unknown sweep: expected magnitude, angle, hold, spatial, displacement or setpoints",
                ))
            }
        };

        let sweep_direction = match (sw.direction.as_deref(), &sweep) {
            (None, Sweep::Magnitude { .. }) => {
                defaults.push("sweep.direction", "\"up\"".into());
                SweepDirection::Up
            }
            (None, _) => SweepDirection::Up,
            (Some(d), Sweep::Magnitude { .. }) => match d {
                "up" => SweepDirection::Up,
                "up-down" => SweepDirection::UpDown,
                other => {
                    return Err(c.invalid(
                        "sweep.direction",
                        format!("{other:?}"),
                        "expected \"up\" or \"up-down\"",
                    ))
                }
            },
            (Some(d), _) => {
                return Err(c.invalid(
                    "sweep.direction",
                    format!("{d:?}"),
                    format!("only magnitude sweeps run up and down (sweep kind is \"{kind}\")"),
                ))
            }
        };
        let positions_mm = match sw.positions_mm {
            None => Vec::new(),
            Some(_) if !matches!(sweep, Sweep::Magnitude { .. } | Sweep::Angle { .. }) => {
                return Err(c.invalid(
                    "sweep.positions_mm",
                    "(given)",
                    format!(
                        "only magnitude and angle sweeps repeat their trials at several positions (sweep kind is \"{kind}\")"
                    ),
                ))
            }
            Some(list) if list.is_empty() => {
                return Err(c.invalid(
                    "sweep.positions_mm",
                    "[]",
                    "give at least one [x, y] position (mm), or leave the key out",
                ))
            }
            Some(list) if list.len() > MAX_POSITIONS => {
                return Err(c.invalid(
                    "sweep.positions_mm",
                    format!("{} positions", list.len()),
                    format!("at most {MAX_POSITIONS} positions"),
                ))
            }
            Some(list) => {
                for (i, p) in list.iter().enumerate() {
                    for (a, axis) in ["x", "y"].iter().enumerate() {
                        let key = format!("sweep.positions_mm[{i}][{a}]");
                        c.finite(&key, p[a], "mm")?;
                        let (lo, hi) = (safety.travel_min_mm[a], safety.travel_max_mm[a]);
                        if p[a] < lo || p[a] > hi {
                            return Err(c.invalid(
                                &key,
                                format!("{} mm", p[a]),
                                format!(
                                    "{axis} is outside the travel box safety.travel_min_mm[{a}]..travel_max_mm[{a}] = {lo}..{hi} mm"
                                ),
                            ));
                        }
                    }
                }
                list
            }
        };

        check_caps(
            &c,
            &sweep,
            sweep_direction,
            positions_mm.len(),
            frames,
            fu,
            unit.from_newtons(max_force_n[2]),
        )?;

        let r = &self.reconstruct;
        let method: Method = match &r.solver {
            None => {
                defaults.push("reconstruct.solver", "\"pinv\"".into());
                Method::Pinv
            }
            Some(m) => m
                .parse()
                .map_err(|e: String| c.invalid("reconstruct.solver", format!("{m:?}"), e))?,
        };
        let as_text = |v: &toml::Value| match v {
            toml::Value::String(s) => s.clone(),
            other => other.to_string(),
        };
        let lambda: Lambda = match &r.lambda {
            None if method == Method::Fourier => {
                defaults.push("reconstruct.lambda", "\"lcurve\" (fourier)".into());
                Lambda::LCurve
            }
            None => {
                if matches!(method, Method::Tikhonov) {
                    defaults.push("reconstruct.lambda", "\"gcv\"".into());
                }
                Lambda::Gcv
            }
            Some(v) => as_text(v)
                .parse()
                .map_err(|e: String| c.invalid("reconstruct.lambda", v, e))?,
        };
        let rank: Rank = match &r.rank {
            None => {
                if matches!(method, Method::Tsvd) {
                    defaults.push("reconstruct.rank", "\"auto\"".into());
                }
                Rank::Auto
            }
            Some(v) => as_text(v)
                .parse()
                .map_err(|e: String| c.invalid("reconstruct.rank", v, e))?,
        };
        let max_refine = crate::solve::fourier::MAX_REFINE_ITERATIONS as i64;
        let fourier_refine_iterations = match self.reconstruct.refine_iterations {
            None => {
                if method == Method::Fourier {
                    defaults.push(
                        "reconstruct.refine_iterations",
                        crate::solve::fourier::DEFAULT_REFINE_ITERATIONS.to_string(),
                    );
                }
                crate::solve::fourier::DEFAULT_REFINE_ITERATIONS
            }
            Some(_) if method != Method::Fourier => {
                return Err(c.invalid(
                    "reconstruct.refine_iterations",
                    self.reconstruct.refine_iterations.unwrap_or(0),
                    format!("only the fourier solver refines (solver is {method})"),
                ))
            }
            Some(v) if (0..=max_refine).contains(&v) => v as usize,
            Some(v) => {
                return Err(c.invalid(
                    "reconstruct.refine_iterations",
                    v,
                    format!("must be an integer in [0, {max_refine}] (CGLS iterations)"),
                ))
            }
        };
        let solver = SolverConfig {
            method,
            lambda,
            rank,
            fourier_refine_iterations,
            ..SolverConfig::default()
        };

        let quality = self.quality.validate(&c)?;
        // The tracking gates the plan left at their defaults, echoed like the others.
        let q = &self.quality;
        if q.reference_min_found_fraction.is_none() {
            defaults.push(
                "quality.reference_min_found_fraction",
                format!("{}", quality.reference_min_found_fraction),
            );
        }
        if q.min_ok_fraction.is_none() {
            defaults.push(
                "quality.min_ok_fraction",
                format!("{}", quality.min_ok_fraction),
            );
        }
        if q.max_reacquire.is_none() {
            defaults.push(
                "quality.max_reacquire",
                format!("{}", quality.max_reacquire),
            );
        }
        if q.on_fail.is_none() {
            defaults.push("quality.on_fail", "\"flag\"".into());
        }
        let plan = Plan {
            sweep_direction,
            positions_mm,
            quality,
            solver,
            path: path.to_path_buf(),
            name: self.name,
            sensor_path: path.parent().unwrap_or(Path::new(".")).join(&self.sensor),
            build_id: self.build_id,
            force_unit: unit,
            indenter,
            approach_position_mm,
            approach_speed_mm_s,
            contact_force_n,
            force_tolerance_n,
            max_control_steps,
            settle,
            samples,
            frames,
            safety,
            sweep,
            defaults: defaults.0,
        };
        // The duration, from the (bounded) setpoints one at a time.
        let est = plan.estimate_duration_s(DEFAULT_CLEARANCE_MM, None);
        if est > MAX_DURATION_S {
            let (key, value) = if plan.settle.dwell_s > 0.0
                && plan.settle.dwell_s * plan.setpoint_count() as f64 > MAX_DURATION_S / 2.0
            {
                ("settle.dwell_s", format!("{} s", plan.settle.dwell_s))
            } else {
                ("sweep", format!("{} setpoints", plan.setpoint_count()))
            };
            return Err(c.invalid(
                key,
                value,
                format!(
                    "the plan's estimated duration is {:.1} h, above the cap of {:.0} h per plan",
                    est / 3600.0,
                    MAX_DURATION_S / 3600.0
                ),
            ));
        }
        // Every target must stay within the force limits and the travel box before
        // anything moves.
        for sp in plan.setpoints_iter() {
            for i in 0..2 {
                let v = sp.position_mm[i] + sp.shift_mm[i];
                let (lo, hi) = (plan.safety.travel_min_mm[i], plan.safety.travel_max_mm[i]);
                if v < lo || v > hi {
                    return Err(c.invalid(
                        "sweep",
                        format!("setpoint {} at {} = {} mm", sp.index, ["x", "y"][i], round9(v)),
                        format!(
                            "outside the travel box safety.travel_min_mm[{i}]..travel_max_mm[{i}] = {lo}..{hi} mm"
                        ),
                    ));
                }
            }
            let f = [sp.tangential_n[0], sp.tangential_n[1], sp.normal_n];
            for (i, axis) in ["x", "y", "z"].iter().enumerate() {
                if f[i].abs() > plan.safety.max_force_n[i] {
                    return Err(c.invalid(
                        "sweep",
                        format!(
                            "setpoint {} with f{axis} = {} {fu}",
                            sp.index,
                            round9(unit.from_newtons(f[i]))
                        ),
                        format!(
                            "exceeds safety.max_force[{i}] = {} {fu}",
                            round9(unit.from_newtons(plan.safety.max_force_n[i]))
                        ),
                    ));
                }
            }
        }
        Ok(plan)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::units::gf_to_n;

    const FIG7: &str = r#"
name = "fig7"
sensor = "paper_sensor.toml"
force_unit = "gf"
[indenter]
shape = "hemisphere"
diameter_mm = 5.0
[approach]
position_mm = [9.0, 6.75]
speed_mm_s = 0.5
contact_force = 5.0
[safety]
max_force = [300.0, 300.0, 1000.0]
travel_min_mm = [0.0, 0.0, -2.0]
travel_max_mm = [50.0, 50.0, 20.0]
max_speed_mm_s = 5.0
[sweep]
kind = "magnitude"
from = 0.0
to = 750.0
step = 50.0
trials = 10
"#;

    fn parse(t: &str) -> Result<Plan, PlanError> {
        Plan::from_toml_str(t, "experiments/p.toml")
    }

    #[test]
    fn magnitude_sweep_expands_to_the_papers_sixteen_levels_times_ten_trials() {
        let p = parse(FIG7).unwrap();
        let s = p.setpoints();
        assert_eq!(s.len(), 16 * 10);
        assert_eq!(s[15].normal_n, gf_to_n(750.0));
        assert_eq!(s[16].trial, 1);
        assert_eq!(s[16].normal_n, 0.0);
        assert_eq!(s[159].index, 159);
        assert_eq!(p.sensor_path, Path::new("experiments/paper_sensor.toml"));
        assert_eq!(p.force_tolerance_n, gf_to_n(5.0));
    }

    #[test]
    fn quality_section_has_documented_defaults_and_checked_values() {
        let p = parse(FIG7).unwrap();
        assert_eq!(
            p.quality,
            Quality {
                reference_min_found_fraction: 0.9,
                min_ok_fraction: 0.9,
                max_reacquire: 2,
                on_fail: OnFail::Flag,
            }
        );
        let q = parse(&format!(
            "{FIG7}[quality]\nreference_min_found_fraction = 0.5\nmin_ok_fraction = 0.75\nmax_reacquire = 0\non_fail = \"abort\"\n"
        ))
        .unwrap()
        .quality;
        assert_eq!(
            q,
            Quality {
                reference_min_found_fraction: 0.5,
                min_ok_fraction: 0.75,
                max_reacquire: 0,
                on_fail: OnFail::Abort,
            }
        );
        for (line, key, value) in [
            ("min_ok_fraction = 1.5", "quality.min_ok_fraction", "1.5"),
            (
                "reference_min_found_fraction = -0.1",
                "quality.reference_min_found_fraction",
                "-0.1",
            ),
            ("max_reacquire = 11", "quality.max_reacquire", "11"),
            ("on_fail = \"retry\"", "quality.on_fail", "\"retry\""),
        ] {
            let e = parse(&format!("{FIG7}[quality]\n{line}\n"))
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("experiments/p.toml") && e.contains(key) && e.contains(value),
                "{line}: {e}"
            );
        }
        let e = parse(&format!("{FIG7}[quality]\nmin_ok = 0.5\n"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("min_ok"), "{e}");
    }

    #[test]
    fn angle_sweep_splits_the_force_into_normal_and_tangential_parts() {
        let t = FIG7.replace(
            "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10",
            "kind = \"angle\"\nforce = 400.0\nangle_from_deg = 0.0\nangle_to_deg = 45.0\nangle_step_deg = 5.0\ndirection_deg = 90.0\ntrials = 1",
        );
        let s = parse(&t).unwrap().setpoints();
        assert_eq!(s.len(), 10);
        let last = s[9];
        let f = gf_to_n(400.0);
        assert!((last.normal_n - f * 45f64.to_radians().cos()).abs() < 1e-12);
        assert!(last.tangential_n[0].abs() < 1e-12);
        assert!((last.tangential_n[1] - f * 45f64.to_radians().sin()).abs() < 1e-12);
        assert_eq!(last.swept_value, 45.0);
    }

    #[test]
    fn spatial_sweep_steps_between_two_points() {
        let t = FIG7.replace(
            "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10",
            "kind = \"spatial\"\nforce = 200.0\nstart_mm = [8.9, 6.75]\nend_mm = [11.1, 6.75]\nsubdivisions = 6",
        );
        let s = parse(&t).unwrap().setpoints();
        assert_eq!(s.len(), 7);
        assert!((s[6].position_mm[0] - 11.1).abs() < 1e-12);
        assert!((s[1].swept_value - 2.2 / 6.0).abs() < 1e-12);
    }

    #[test]
    fn rejects_bad_values_naming_file_key_value_and_unit() {
        let e = parse(&FIG7.replace("step = 50.0", "step = -50.0"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("experiments/p.toml")
                && e.contains("sweep.step = -50 gf")
                && e.contains("> 0 gf"),
            "{e}"
        );
        let e = parse(&FIG7.replace("shape = \"hemisphere\"", "shape = \"cone\""))
            .unwrap_err()
            .to_string();
        assert!(e.contains("indenter.shape") && e.contains("cone"), "{e}");
        let e = parse(&FIG7.replace("force_unit = \"gf\"", "force_unit = \"lbf\""))
            .unwrap_err()
            .to_string();
        assert!(e.contains("force_unit") && e.contains("lbf"), "{e}");
        let e = parse(&FIG7.replace("trials = 10", "trials = 10\nbogus = 1"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("bogus") && e.contains("line"), "{e}");
        let e = parse(&FIG7.replace("speed_mm_s = 0.5", "speed_mm_s = 9.0"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("approach.speed_mm_s = 9 mm/s") && e.contains("max_speed_mm_s = 5"),
            "{e}"
        );
    }

    #[test]
    fn rejects_targets_beyond_the_force_limit_before_anything_moves() {
        let e = parse(&FIG7.replace("to = 750.0", "to = 1200.0"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("fz = 1000") || e.contains("fz = 1050"), "{e}");
        assert!(e.contains("safety.max_force[2] = 1000 gf"), "{e}");
    }

    #[test]
    fn a_sweep_to_1e9_is_refused_by_the_setpoint_cap_naming_key_value_and_cap() {
        let e = parse(&FIG7.replace("to = 750.0", "to = 1e9"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("experiments/p.toml")
                && e.contains("sweep.to = 1000000000 gf")
                && e.contains("200000010 setpoints")
                && e.contains(&format!("cap of {MAX_SETPOINTS} setpoints")),
            "{e}"
        );
        // A tiny step within the force limit names the step instead.
        let e = parse(&FIG7.replace("step = 50.0", "step = 1e-6"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("sweep.step = 0.000001 gf") && e.contains("cap"),
            "{e}"
        );
        let e = parse(&FIG7.replace(
            "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10",
            "kind = \"angle\"\nforce = 400.0\nangle_from_deg = 0.0\nangle_to_deg = 45.0\nangle_step_deg = 1e-12\ntrials = 1",
        ))
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("sweep.angle_step_deg") && e.contains("cap"),
            "{e}"
        );
    }

    #[test]
    fn the_frame_and_duration_caps_refuse_plans_that_would_run_for_weeks() {
        let e = parse(&FIG7.replace("trials = 10", "trials = 20\n[acquire]\nframes = 1000"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("acquire.frames = 1000")
                && e.contains("320000 frames")
                && e.contains(&format!("cap of {MAX_FRAMES} frames")),
            "{e}"
        );
        let e = parse(&FIG7.replace("trials = 10", "trials = 10\n[settle]\ndwell_s = 86400.0"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("settle.dwell_s = 86400 s") && e.contains("cap of 168 h"),
            "{e}"
        );
        let p = parse(FIG7).unwrap();
        let est = p.estimate_duration_s(DEFAULT_CLEARANCE_MM, None);
        assert!(est > 0.0 && est < MAX_DURATION_S);
        assert!(p.estimate_duration_s(DEFAULT_CLEARANCE_MM, Some(16)) < est / 5.0);
    }

    #[test]
    fn a_missing_trials_is_refused_instead_of_meaning_one() {
        let e = parse(&FIG7.replace("trials = 10\n", ""))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("sweep.trials = (missing)") && e.contains("required by sweep kind"),
            "{e}"
        );
    }

    #[test]
    fn fourier_refinement_is_a_plan_choice_checked_against_the_solver() {
        let p = parse(&format!("{FIG7}[reconstruct]\nsolver = \"fourier\"\n")).unwrap();
        assert_eq!(
            p.solver.fourier_refine_iterations,
            crate::solve::fourier::DEFAULT_REFINE_ITERATIONS
        );
        assert!(p
            .defaults
            .iter()
            .any(|(k, _)| k == "reconstruct.refine_iterations"));
        let p = parse(&format!(
            "{FIG7}[reconstruct]\nsolver = \"fourier\"\nrefine_iterations = 0\n"
        ))
        .unwrap();
        assert_eq!(p.solver.fourier_refine_iterations, 0);
        for (extra, needle) in [
            (
                "solver = \"pinv\"\nrefine_iterations = 5",
                "only the fourier solver",
            ),
            ("solver = \"fourier\"\nrefine_iterations = -1", "[0, 1000]"),
            (
                "solver = \"fourier\"\nrefine_iterations = 5000",
                "[0, 1000]",
            ),
        ] {
            let e = parse(&format!("{FIG7}[reconstruct]\n{extra}\n"))
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("reconstruct.refine_iterations") && e.contains(needle),
                "{extra}: {e}"
            );
        }
    }

    #[test]
    fn keys_left_out_are_listed_with_their_defaults() {
        let p = parse(FIG7).unwrap();
        let keys: Vec<&str> = p.defaults.iter().map(|(k, _)| k.as_str()).collect();
        assert_eq!(
            keys,
            [
                "control.force_tolerance",
                "control.max_steps",
                "settle.window_s",
                "settle.max_sd",
                "settle.timeout_s",
                "settle.dwell_s",
                "acquire.samples",
                "acquire.frames",
                "sweep.direction",
                "reconstruct.solver",
                "quality.reference_min_found_fraction",
                "quality.min_ok_fraction",
                "quality.max_reacquire",
                "quality.on_fail"
            ]
        );
        assert_eq!(p.defaults[0].1, "5 gf (approach.contact_force)");
        assert_eq!(p.defaults[3].1, "2.5 gf (control.force_tolerance / 2)");
        assert_eq!(p.settle.window_s, DEFAULT_WINDOW_S);
        let p = parse(&FIG7.replace("force_unit = \"gf\"\n", "")).unwrap();
        assert_eq!(p.force_unit, ForceUnit::Newton);
        assert_eq!(p.defaults[0], ("force_unit".into(), "\"N\"".into()));
    }

    #[test]
    fn a_tangential_load_along_y_has_an_exact_zero_x_part() {
        let t = FIG7.replace(
            "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10",
            "kind = \"angle\"\nforce = 200.0\nangle_from_deg = 0.0\nangle_to_deg = 30.0\nangle_step_deg = 30.0\ndirection_deg = 90.0\ntrials = 1",
        );
        let s = parse(&t).unwrap().setpoints();
        assert_eq!(s[1].tangential_n[0], 0.0);
        assert_eq!(s[0].tangential_n, [0.0, 0.0]);
        assert_eq!(cos_sin_deg(-90.0), (0.0, -1.0));
        assert_eq!(cos_sin_deg(180.0), (-1.0, 0.0));
    }

    #[test]
    fn the_setpoint_count_matches_the_expansion_for_every_kind() {
        let kinds = [
            FIG7.to_string(),
            FIG7.replace(
                "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10",
                "kind = \"angle\"\nforce = 400.0\nangle_from_deg = 0.0\nangle_to_deg = 45.0\nangle_step_deg = 5.0\ntrials = 3",
            ),
            FIG7.replace(
                "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10",
                "kind = \"displacement\"\nshift_mm = [0.1, 0.0]\ntrials = 4",
            ),
            FIG7.replace(
                "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10",
                "kind = \"magnitude\"\nfrom = 0.1\nto = 0.7\nstep = 0.1\ntrials = 2",
            ),
        ];
        for (t, n) in kinds.iter().zip([160, 30, 4, 14]) {
            let p = parse(t).unwrap();
            assert_eq!(p.setpoint_count(), n);
            assert_eq!(p.setpoints().len(), n);
            assert_eq!(p.frame_count(), n);
        }
    }

    const MAG: &str = "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 10";

    fn with_sweep(sweep: &str) -> String {
        FIG7.replace(MAG, sweep)
    }

    #[test]
    fn an_up_down_sweep_runs_each_trial_up_and_back_down_with_the_top_once() {
        let p = parse(&with_sweep(
            "kind = \"magnitude\"\nfrom = 0.0\nto = 300.0\nstep = 100.0\ntrials = 2\ndirection = \"up-down\"",
        ))
        .unwrap();
        assert_eq!(p.sweep_direction, SweepDirection::UpDown);
        let s = p.setpoints();
        let got: Vec<(usize, f64, Option<Direction>)> = s
            .iter()
            .map(|s| (s.trial, s.swept_value, s.direction))
            .collect();
        let (u, d) = (Some(Direction::Up), Some(Direction::Down));
        let one = |t| {
            vec![
                (t, 0.0, u),
                (t, 100.0, u),
                (t, 200.0, u),
                (t, 300.0, u),
                (t, 200.0, d),
                (t, 100.0, d),
                (t, 0.0, d),
            ]
        };
        assert_eq!(got, [one(0), one(1)].concat());
        assert!(s
            .iter()
            .all(|s| s.position.is_none() && s.hold_t_s.is_none()));
        assert_eq!(s[6].normal_n, 0.0, "the trial ends unloaded");
        assert_eq!(p.top_level_n(), Some(gf_to_n(300.0)));
        // From > 0: an unloaded reading is added at both ends of each trial.
        let p = parse(&with_sweep(
            "kind = \"magnitude\"\nfrom = 100.0\nto = 250.0\nstep = 100.0\ntrials = 1\ndirection = \"up-down\"",
        ))
        .unwrap();
        let got: Vec<(f64, Option<Direction>)> = p
            .setpoints()
            .iter()
            .map(|s| (s.swept_value, s.direction))
            .collect();
        assert_eq!(
            got,
            [(0.0, u), (100.0, u), (200.0, u), (100.0, d), (0.0, d)]
        );
        assert_eq!(
            p.top_level_n(),
            Some(gf_to_n(200.0)),
            "the top level, not `to`"
        );
        // The default ("up") is today's sweep: no direction in the rows.
        let p = parse(FIG7).unwrap();
        assert_eq!(p.sweep_direction, SweepDirection::Up);
        assert!(p.setpoints().iter().all(|s| s.direction.is_none()));
        let p = parse(&FIG7.replace("trials = 10", "trials = 10\ndirection = \"up\"")).unwrap();
        assert_eq!(p.setpoint_count(), 160);
        assert!(p.defaults.iter().all(|(k, _)| k != "sweep.direction"));
    }

    #[test]
    fn trials_repeat_at_each_listed_position_in_turn_numbered_across_positions() {
        let p = parse(&with_sweep(
            "kind = \"magnitude\"\nfrom = 0.0\nto = 100.0\nstep = 100.0\ntrials = 2\ndirection = \"up-down\"\npositions_mm = [[9.0, 6.75], [7.0, 5.0]]",
        ))
        .unwrap();
        let s = p.setpoints();
        assert_eq!(s.len(), 2 * 2 * 3);
        let got: Vec<(usize, Option<usize>, [f64; 2])> = s
            .iter()
            .map(|s| (s.trial, s.position, s.position_mm))
            .collect();
        let mut want = Vec::new();
        for (pi, pos) in [[9.0, 6.75], [7.0, 5.0]].iter().enumerate() {
            for t in 0..2 {
                want.extend([(pi * 2 + t, Some(pi), *pos); 3]);
            }
        }
        assert_eq!(got, want);
        // Angle sweeps repeat the same way; without the key, position is empty.
        let p = parse(&with_sweep(
            "kind = \"angle\"\nforce = 400.0\nangle_from_deg = 0.0\nangle_to_deg = 10.0\nangle_step_deg = 10.0\ntrials = 1\npositions_mm = [[9.0, 6.75], [10.0, 6.75], [11.0, 6.75]]",
        ))
        .unwrap();
        let s = p.setpoints();
        assert_eq!(s.len(), 6);
        assert_eq!(s[5].position, Some(2));
        assert_eq!(s[5].trial, 2);
        assert_eq!(s[5].position_mm, [11.0, 6.75]);
        assert!(parse(FIG7)
            .unwrap()
            .setpoints()
            .iter()
            .all(|s| s.position.is_none()));
    }

    #[test]
    fn a_hold_sweep_samples_each_hold_on_its_schedule_between_unloaded_readings() {
        let p = parse(&with_sweep(
            "kind = \"hold\"\nforce = 300.0\nduration_s = 2.5\nsample_interval_s = 1.0\ntrials = 2",
        ))
        .unwrap();
        let s = p.setpoints();
        let got: Vec<(usize, f64, Option<f64>)> = s
            .iter()
            .map(|s| (s.trial, s.normal_n, s.hold_t_s))
            .collect();
        let f = gf_to_n(300.0);
        let hold = |t| {
            vec![
                (t, f, Some(0.0)),
                (t, f, Some(1.0)),
                (t, f, Some(2.0)),
                (t, f, Some(2.5)),
                (t, 0.0, None),
            ]
        };
        assert_eq!(got, [vec![(0, 0.0, None)], hold(0), hold(1)].concat());
        assert_eq!(s[1].swept_value, 300.0);
        assert_eq!(s[0].swept_value, 0.0);
        assert!(s
            .iter()
            .all(|s| s.direction.is_none() && s.position.is_none()));
        // Consecutive samples of a hold keep the contact; each hold starts afresh.
        assert!(!needs_retract(Some(&s[1]), &s[2]));
        assert!(needs_retract(Some(&s[5]), &s[6]) && needs_retract(Some(&s[4]), &s[5]));
        assert_eq!(
            hold_schedule(3.0, 1.0).collect::<Vec<_>>(),
            [0.0, 1.0, 2.0, 3.0]
        );
        assert_eq!(hold_sample_count(0.3, 0.1), 4.0, "0.3 / 0.1 is on the grid");
        // The estimate includes the holds' own time.
        assert!(p.estimate_duration_s(DEFAULT_CLEARANCE_MM, None) > 2.0 * 2.5);
    }

    #[test]
    fn sweep_direction_positions_and_hold_keys_are_checked_naming_file_key_and_value() {
        let hold = "kind = \"hold\"\nforce = 300.0\nduration_s = 10.0\nsample_interval_s = 1.0\ntrials = 2";
        for (sweep, key, needle) in [
            (
                format!("{MAG}\ndirection = \"down\""),
                "sweep.direction = \"down\"",
                "expected \"up\" or \"up-down\"",
            ),
            (
                "kind = \"angle\"\nforce = 400.0\nangle_from_deg = 0.0\nangle_to_deg = 10.0\nangle_step_deg = 10.0\ntrials = 1\ndirection = \"up-down\"".into(),
                "sweep.direction",
                "only magnitude sweeps",
            ),
            (
                format!("{MAG}\npositions_mm = []"),
                "sweep.positions_mm = []",
                "at least one",
            ),
            (
                format!("{MAG}\npositions_mm = [[9.0, 6.75], [60.0, 6.75]]"),
                "sweep.positions_mm[1][0] = 60 mm",
                "travel box",
            ),
            (
                format!("{hold}\npositions_mm = [[9.0, 6.75]]"),
                "sweep.positions_mm",
                "only magnitude and angle",
            ),
            (
                hold.replace("duration_s = 10.0\n", ""),
                "sweep.duration_s = (missing)",
                "required by sweep kind \"hold\"",
            ),
            (
                hold.replace("sample_interval_s = 1.0", "sample_interval_s = 20.0"),
                "sweep.sample_interval_s = 20 s",
                "must not exceed sweep.duration_s = 10 s",
            ),
            (
                hold.replace("duration_s = 10.0", "duration_s = -1.0"),
                "sweep.duration_s = -1",
                "> 0",
            ),
            (
                hold.replace("force = 300.0", "force = 2000.0"),
                "fz = 2000 gf",
                "safety.max_force[2]",
            ),
            (
                hold.replace("trials = 2\n", "").replace("trials = 2", ""),
                "sweep.trials = (missing)",
                "required",
            ),
        ] {
            let e = parse(&with_sweep(&sweep)).unwrap_err().to_string();
            assert!(
                e.contains("experiments/p.toml") && e.contains(key) && e.contains(needle),
                "{sweep}: {e}"
            );
        }
        // An unknown key in [sweep] is named with its line.
        let e = parse(&with_sweep(&format!("{hold}\nhold_s = 3")))
            .unwrap_err()
            .to_string();
        assert!(e.contains("hold_s") && e.contains("line"), "{e}");
    }

    #[test]
    fn hold_caps_are_checked_before_anything_is_expanded() {
        let hold = "kind = \"hold\"\nforce = 300.0\nduration_s = 10.0\nsample_interval_s = 1.0\ntrials = 2";
        let e = parse(&with_sweep(
            &hold.replace("sample_interval_s = 1.0", "sample_interval_s = 1e-6"),
        ))
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("sweep.sample_interval_s = 0.000001 s")
                && e.contains("samples per hold")
                && e.contains(&format!("cap of {MAX_SETPOINTS} setpoints")),
            "{e}"
        );
        let e = parse(&with_sweep(
            &hold
                .replace("duration_s = 10.0", "duration_s = 1e9")
                .replace("sample_interval_s = 1.0", "sample_interval_s = 1e8"),
        ))
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("sweep.duration_s = 1000000000 s") && e.contains("cap of 168 h"),
            "{e}"
        );
        let e = parse(&with_sweep(&format!(
            "{MAG}\npositions_mm = [{}]",
            vec!["[9.0, 6.75]"; 1000].join(", ")
        )))
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("sweep.positions_mm = 1000 positions") && e.contains("cap"),
            "{e}"
        );
    }

    #[test]
    fn the_setpoint_count_matches_the_expansion_for_the_repeating_kinds() {
        for sweep in [
            "kind = \"magnitude\"\nfrom = 0.0\nto = 750.0\nstep = 50.0\ntrials = 3\ndirection = \"up-down\"",
            "kind = \"magnitude\"\nfrom = 50.0\nto = 700.0\nstep = 50.0\ntrials = 3\ndirection = \"up-down\"\npositions_mm = [[9.0, 6.75], [8.0, 6.0]]",
            "kind = \"magnitude\"\nfrom = 100.0\nto = 100.0\nstep = 50.0\ntrials = 2\ndirection = \"up-down\"",
            "kind = \"angle\"\nforce = 400.0\nangle_from_deg = 0.0\nangle_to_deg = 45.0\nangle_step_deg = 5.0\ntrials = 2\npositions_mm = [[9.0, 6.75], [8.0, 6.0], [10.0, 7.0]]",
            "kind = \"hold\"\nforce = 300.0\nduration_s = 10.0\nsample_interval_s = 0.3\ntrials = 3",
        ] {
            let p = parse(&with_sweep(sweep)).unwrap();
            assert_eq!(p.setpoint_count(), p.setpoints().len(), "{sweep}");
            assert_eq!(p.setpoints_iter().count(), p.setpoint_count(), "{sweep}");
            assert!(p.setpoints().iter().enumerate().all(|(i, s)| s.index == i));
        }
    }
}
