//! The bench runner: drives a stage, a force/torque sensor and a camera through a
//! plan's setpoints and records each measurement in a crash-safe run directory. It
//! works on the capability traits only (`&mut dyn Stage`, `&mut dyn ForceSensor`,
//! `&mut dyn Camera`), so the same code runs a real bench and the simulated one, and
//! it never prints: progress goes to a callback as [`RunEvent`]s.
//!
//! Per setpoint (index `NNNNN`):
//! 1. **Checks before motion**: every target (stage xy, deepest allowed indentation,
//!    retract height) against the plan's sensor-frame travel box and the stage's own
//!    travel limits.
//! 2. **Position**: retract to `clearance_mm` above the surface when the contact must
//!    be renewed (new position or trial, a tangential load before or now, no load),
//!    move laterally, then approach at the plan's speed until the normal force exceeds
//!    `approach.contact_force` (contact detection on the force reading).
//! 3. **Force control**: closed-loop z steps ([`ForceController`], secant stiffness,
//!    never planning past the safety limit) until `|fz − target| ≤ tolerance`;
//!    tangential targets by lateral steps along the target direction, alternating
//!    with the normal loop until both hold.
//! 4. **Settle**: force SD over `settle.window_s` below `settle.max_sd` (timeout
//!    `settle.timeout_s`, the row is flagged `settled = false`), or a fixed
//!    `settle.dwell_s`. If the force drifted out of tolerance while settling (creep),
//!    control and settling are retried (at most [`SETTLE_RETRIES`] times).
//! 5. **Acquire**: mean and SD of `acquire.samples` F/T readings, the stage position,
//!    `acquire.frames` frames (`frames/NNNNN_K.png`).
//! 6. **Track and reconstruct**: every frame against the run's reference frame
//!    (`displacements/NNNNN.csv`, as `tactbench track` writes it); forces from the
//!    mean displacement over the frames (`forces/NNNNN.csv`) with the plan's solver,
//!    precomputed once per set of tracked markers.
//! 7. **Journal**: the row is appended and synced before the next move.
//!
//! **Safety watchdog.** While the stage moves, the runner reads the force sensor in a
//! loop; any component beyond `safety.max_force` stops the stage (GRBL feed hold,
//! Zaber `stop`), the time from the offending reading to the stage standing still is
//! measured (stop latency), the stage retracts, and the run aborts with the reason
//! and latency in the manifest. Settling and acquisition check the limits as well.
//!
//! **Stop flag.** When the caller's flag (Ctrl-C) is set, motion stops, the stage
//! retracts, the journal is already durable, and the manifest says `interrupted`.
//!
//! **Resume.** [`run`] with `resume = true` reopens the journal (a torn last line is
//! cut), skips completed indices, homes / tares as the bench requires, and takes a new
//! reference frame (`frames/reference_resumeN.png`; `frames/reference.png` stays the
//! first run's).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use thiserror::Error;

use super::config::BenchGeometry;
use super::control::{check_force_limits, ForceController, SettleDetector};
use super::journal::{Journal, JournalError, JournalRow, Manifest, RunStatus};
use super::plan::{Plan, Setpoint, Sweep};
use crate::device::{
    Camera, CameraFrame, DeviceError, DeviceResult, ErrorKind, ForceSensor, Stage, StagePositionMm,
    StageState, TravelLimits, Wrench,
};
use crate::formats::{self, DisplacementFrame};
use crate::sensor::Sensor;
use crate::solve::{self, FrameSolver, Problem};
use crate::vision::{self, FrameView, MarkerTrack, TrackConfig, Tracker};

/// Times control and settling are redone when the force left the tolerance while
/// settling (elastomer creep).
pub const SETTLE_RETRIES: usize = 2;

/// Retries of a failed F/T read or camera grab before the run aborts.
pub const READ_RETRIES: usize = 3;

/// F/T readings averaged per force-control step (the control input).
pub const CONTROL_SAMPLES: usize = 3;

/// Largest z step of the force controller, mm.
pub const MAX_CONTROL_STEP_MM: f64 = 0.5;

/// Initial contact stiffness estimate of the force controller, N/mm (stiff enough
/// that the first step undershoots on the paper's elastomer; the secant takes over).
pub const INITIAL_STIFFNESS_N_PER_MM: f64 = 4.0;

/// Position tolerance for "the stage reached its target", mm.
pub const POSITION_TOLERANCE_MM: f64 = 0.005;

/// Longest wait for a stage to finish a move beyond its nominal duration.
pub const MOVE_GRACE: Duration = Duration::from_secs(5);

/// An error that prevents a run from starting or recording (device and safety
/// problems during the run end it as `aborted` instead, see [`RunSummary`]).
#[derive(Debug, Error)]
pub enum RunError {
    /// The run directory or its journal / manifest.
    #[error(transparent)]
    Journal(#[from] JournalError),
    /// A file in the run directory.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The run cannot start as asked (existing run, resume of another plan).
    #[error("{0}")]
    Setup(String),
}

/// The devices a run drives.
pub struct Devices<'a> {
    /// The stage.
    pub stage: &'a mut dyn Stage,
    /// The force/torque sensor.
    pub ft: &'a mut dyn ForceSensor,
    /// The camera.
    pub camera: &'a mut dyn Camera,
}

/// How to run.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// The run directory.
    pub dir: PathBuf,
    /// Continue the run in `dir` (else `dir` must not hold a run).
    pub resume: bool,
    /// Elastomer build id (overrides the plan's).
    pub build_id: Option<String>,
    /// The plan file's text (for the manifest).
    pub plan_toml: String,
    /// The sensor file's text (for the manifest).
    pub sensor_toml: String,
    /// Bench description for the manifest.
    pub bench: serde_json::Value,
    /// Device identities for the manifest.
    pub devices: serde_json::Value,
    /// Run the homing cycle before the first setpoint.
    pub home: bool,
    /// Tare the force sensor unloaded before the reference frame.
    pub tare: bool,
    /// Only the first `limit` setpoints of the plan (a new run records the count in
    /// the manifest; a resume takes it from there).
    pub limit: Option<usize>,
    /// Set by the caller (Ctrl-C) to stop the run cleanly.
    pub stop: Arc<AtomicBool>,
    /// The signal number that set `stop` (0: none, or not a signal), recorded in the
    /// manifest and the stop reason (SIGINT and SIGTERM are told apart).
    pub stop_signal: Arc<AtomicI32>,
}

/// Progress, for the CLI's progress bar and logs.
#[derive(Debug, Clone, PartialEq)]
pub enum RunEvent {
    /// The run starts: `done` of `total` setpoints are already in the journal.
    Started {
        /// Setpoints in the run.
        total: usize,
        /// Already completed (resume).
        done: usize,
        /// A torn journal line was cut on resume (bytes).
        truncated_bytes: u64,
    },
    /// The stage is homing.
    Homing,
    /// The force sensor was tared; `residual_n` = |F| right after.
    Tared {
        /// |F| after taring, N.
        residual_n: f64,
    },
    /// The reference frame was taken.
    Reference {
        /// Its file, relative to the run directory.
        path: String,
        /// Markers found.
        markers: usize,
        /// Grid nodes without a marker.
        missing: usize,
    },
    /// A setpoint starts.
    SetpointStarted {
        /// The setpoint.
        setpoint: Setpoint,
        /// Completed so far.
        done: usize,
        /// Setpoints in the run.
        total: usize,
    },
    /// Contact found during the approach.
    Contact {
        /// Setpoint index.
        index: usize,
        /// Indentation depth at contact (from the bench geometry), mm.
        depth_mm: f64,
        /// Normal force at contact, N.
        fz_n: f64,
    },
    /// Something was retried.
    Retry {
        /// Setpoint index, when in a setpoint.
        index: Option<usize>,
        /// Attempt number (1 = first retry).
        attempt: usize,
        /// Why.
        reason: String,
    },
    /// A non-fatal problem (e.g. a reconstruction that failed; the row keeps NaN).
    Warning {
        /// Setpoint index.
        index: usize,
        /// What happened.
        message: String,
    },
    /// A setpoint was measured and journalled.
    SetpointMeasured {
        /// Setpoint index.
        index: usize,
        /// Completed so far (including this one).
        done: usize,
        /// Setpoints in the run.
        total: usize,
        /// Target force (fx, fy, fz), N.
        target_n: [f64; 3],
        /// Measured mean force, N.
        force_n: [f64; 3],
        /// Reconstructed force sums, N.
        fsum_n: [f64; 3],
        /// Settle criterion met.
        settled: bool,
        /// Wall time of the setpoint, s.
        elapsed_s: f64,
        /// Time blocked in device calls and waits, s.
        device_s: f64,
        /// Controller overhead: wall − device − tracking − solving − file writes, s.
        overhead_s: f64,
    },
    /// The safety watchdog stopped the stage.
    SafetyTrip {
        /// Setpoint index, when in a setpoint.
        index: Option<usize>,
        /// What exceeded which limit.
        reason: String,
        /// Time from the offending reading to the stage standing still, s.
        stop_latency_s: f64,
    },
    /// The run ended.
    Finished {
        /// How.
        status: RunStatus,
        /// Why, when not completed.
        reason: Option<String>,
    },
}

/// Where the time of the measured setpoints went (this session only).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Timings {
    /// Setpoints measured.
    pub setpoints: usize,
    /// Wall time of those setpoints, s.
    pub wall_s: f64,
    /// Blocked in device calls (moves, reads, grabs, waits) and dwell sleeps, s.
    pub device_s: f64,
    /// Tracking, s.
    pub track_s: f64,
    /// Reconstruction per setpoint (averaging + solver apply), s.
    pub solve_s: f64,
    /// One-off solver precomputes (first setpoint, and whenever the set of tracked
    /// markers changes), s; kept out of `solve_s` and the journal's `t_solve_s`, which
    /// are per-frame costs (paper Table II).
    pub precompute_s: f64,
    /// Writing frames, CSVs and the journal, s.
    pub io_s: f64,
    /// Controller overhead (the rest), summed, s.
    pub overhead_s: f64,
    /// Largest controller overhead of one setpoint, s.
    pub max_overhead_s: f64,
}

/// How a run ended.
#[derive(Debug, Clone, PartialEq)]
pub struct RunSummary {
    /// Final status (also in the manifest).
    pub status: RunStatus,
    /// Why, when not completed.
    pub reason: Option<String>,
    /// Setpoints in the run.
    pub total: usize,
    /// Setpoints in the journal now.
    pub done: usize,
    /// Setpoints measured in this session.
    pub measured: usize,
    /// Where the time went.
    pub timings: Timings,
}

/// Why the run stops early.
#[derive(Debug, Clone, PartialEq)]
enum Halt {
    Interrupted,
    Abort(String),
}

type Step<T> = Result<T, Halt>;

fn dev_abort(context: &str, e: &DeviceError) -> Halt {
    Halt::Abort(format!("{context}: {e}"))
}

/// Current time as RFC 3339 UTC (seconds).
pub fn rfc3339_now() -> String {
    let secs = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs() as i64)
        .unwrap_or(0);
    rfc3339(secs)
}

/// Seconds since the Unix epoch as RFC 3339 UTC (civil-from-days, H. Hinnant).
pub fn rfc3339(secs: i64) -> String {
    let days = secs.div_euclid(86_400);
    let sod = secs.rem_euclid(86_400);
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let y = yoe + era * 400;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = if m <= 2 { y + 1 } else { y };
    format!(
        "{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}Z",
        sod / 3600,
        (sod / 60) % 60,
        sod % 60
    )
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

/// What `--dry-run` reports: the setpoints, an estimated duration and the limit checks.
#[derive(Debug, Clone, PartialEq)]
pub struct DryRun {
    /// Every setpoint, in run order.
    pub setpoints: Vec<Setpoint>,
    /// Estimated duration, s.
    pub estimated_s: f64,
    /// Checks performed, each `(passed, description)`.
    pub checks: Vec<(bool, String)>,
}

/// Plans a run without touching any device: setpoints, estimated duration and limit
/// checks (plan box, force limits, and the stage box when the bench geometry and the
/// stage limits are known).
pub fn dry_run(
    plan: &Plan,
    limit: Option<usize>,
    geometry: Option<&BenchGeometry>,
    stage_limits: Option<&TravelLimits>,
) -> DryRun {
    let mut setpoints = plan.setpoints();
    if let Some(n) = limit {
        setpoints.truncate(n);
    }
    let s = &plan.safety;
    let u = plan.force_unit;
    let fu = u.symbol();
    let mut checks = Vec::new();
    let max = setpoints.iter().fold([0.0f64; 3], |m, sp| {
        [
            m[0].max(sp.tangential_n[0].abs()),
            m[1].max(sp.tangential_n[1].abs()),
            m[2].max(sp.normal_n),
        ]
    });
    for (i, axis) in ["fx", "fy", "fz"].iter().enumerate() {
        checks.push((
            max[i] <= s.max_force_n[i],
            format!(
                "largest target |{axis}| {:.4} {fu} within safety.max_force[{i}] = {:.4} {fu}",
                u.from_newtons(max[i]),
                u.from_newtons(s.max_force_n[i])
            ),
        ));
    }
    let clearance = geometry.map_or(1.0, |g| g.clearance_mm);
    checks.push((
        -clearance >= s.travel_min_mm[2],
        format!(
            "retract height {clearance} mm above the surface within travel_min_mm[2] = {} mm",
            s.travel_min_mm[2]
        ),
    ));
    for sp in &setpoints {
        let p = [
            sp.position_mm[0] + sp.shift_mm[0],
            sp.position_mm[1] + sp.shift_mm[1],
        ];
        for i in 0..2 {
            if p[i] < s.travel_min_mm[i] || p[i] > s.travel_max_mm[i] {
                checks.push((
                    false,
                    format!(
                        "setpoint {}: {} = {} mm outside the plan's travel box",
                        sp.index,
                        ["x", "y"][i],
                        p[i]
                    ),
                ));
            }
        }
        if let (Some(g), Some(lim)) = (geometry, stage_limits) {
            for depth in [-clearance, s.travel_max_mm[2]] {
                if let Err(e) = lim.check(g.stage_point(p, depth)) {
                    checks.push((false, format!("setpoint {}: stage {e}", sp.index)));
                }
            }
        }
    }
    checks.push((
        true,
        format!(
            "{} setpoint positions checked against the plan's travel box x {}..{} mm, y {}..{} mm{}",
            setpoints.len(),
            s.travel_min_mm[0],
            s.travel_max_mm[0],
            s.travel_min_mm[1],
            s.travel_max_mm[1],
            if stage_limits.is_some() {
                " and the stage's travel limits"
            } else {
                " (stage limits unknown without a bench: checked when the run starts)"
            }
        ),
    ));
    DryRun {
        estimated_s: estimate_duration(plan, &setpoints, clearance),
        setpoints,
        checks,
    }
}

/// A rough duration estimate: moves at their speeds, a few control steps per loaded
/// setpoint, the settle window (or dwell), acquisition at 1 kHz, 30 ms per frame.
pub fn estimate_duration(plan: &Plan, setpoints: &[Setpoint], clearance_mm: f64) -> f64 {
    let v = plan.approach_speed_mm_s;
    let vmax = plan.safety.max_speed_mm_s;
    let settle = if plan.settle.dwell_s > 0.0 {
        plan.settle.dwell_s
    } else {
        plan.settle.window_s * 1.2
    };
    let mut t = 0.0;
    let mut prev: Option<&Setpoint> = None;
    for sp in setpoints {
        if needs_retract(prev, sp) {
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
        t += settle + plan.samples as f64 * 1e-3 + plan.frames as f64 * 0.03;
        prev = Some(sp);
    }
    t
}

/// Device calls with the time spent in them accounted.
struct Timed<'d, 'a> {
    dev: &'d mut Devices<'a>,
    blocked: Duration,
}

macro_rules! timed {
    ($self:ident, $e:expr) => {{
        let t0 = Instant::now();
        let r = $e;
        $self.blocked += t0.elapsed();
        r
    }};
}

impl Timed<'_, '_> {
    fn read(&mut self) -> DeviceResult<Wrench> {
        timed!(self, self.dev.ft.read())
    }
    fn read_once(&mut self) -> DeviceResult<Wrench> {
        timed!(self, self.dev.ft.read_once())
    }
    fn tare(&mut self) -> DeviceResult<()> {
        timed!(self, self.dev.ft.tare())
    }
    fn move_to(&mut self, p: StagePositionMm, v: f64) -> DeviceResult<()> {
        timed!(self, self.dev.stage.move_to(p, Some(v)))
    }
    fn position(&mut self) -> DeviceResult<StagePositionMm> {
        timed!(self, self.dev.stage.position())
    }
    fn state(&mut self) -> DeviceResult<StageState> {
        timed!(self, self.dev.stage.state())
    }
    fn stop(&mut self) -> DeviceResult<()> {
        timed!(self, self.dev.stage.stop())
    }
    fn wait_idle(&mut self, t: Duration) -> DeviceResult<()> {
        timed!(self, self.dev.stage.wait_idle(t))
    }
    fn home(&mut self) -> DeviceResult<()> {
        timed!(self, self.dev.stage.home())
    }
    fn grab(&mut self) -> DeviceResult<CameraFrame> {
        timed!(self, self.dev.camera.grab())
    }
    fn sleep(&mut self, d: Duration) {
        timed!(self, std::thread::sleep(d))
    }
}

/// The run's mutable state.
struct Runner<'p, 'd, 'a, 'e> {
    plan: &'p Plan,
    sensor: &'p Sensor,
    geom: BenchGeometry,
    dir: PathBuf,
    dev: Timed<'d, 'a>,
    events: &'e mut dyn FnMut(&RunEvent),
    stop: Arc<AtomicBool>,
    stage_limits: TravelLimits,
    /// Stage position commanded last (the runner's belief), mm.
    commanded: Option<StagePositionMm>,
    /// In contact at the current setpoint's position.
    in_contact: bool,
    normal_ctl: ForceController,
    tracker: Option<Tracker>,
    solvers: HashMap<Vec<bool>, Box<dyn FrameSolver>>,
    index: Option<usize>,
    /// Per-setpoint accounting.
    track_s: f64,
    solve_s: f64,
    precompute_s: f64,
    io_s: f64,
}

/// Runs (or resumes) a plan on the given devices, writing the run directory.
///
/// Returns `Ok` with the final status whenever the run directory could be written,
/// including aborts (device errors, safety trips) and interruptions: the reason is in
/// the summary and the manifest. `Err` only when the run could not start or record.
pub fn run(
    plan: &Plan,
    sensor: &Sensor,
    geometry: &BenchGeometry,
    devices: &mut Devices<'_>,
    options: &RunOptions,
    events: &mut dyn FnMut(&RunEvent),
) -> Result<RunSummary, RunError> {
    let dir = options.dir.clone();
    let mut setpoints = plan.setpoints();
    let planned = setpoints.len();
    let (mut journal, mut manifest, truncated_bytes, resume_no) = if options.resume {
        let manifest = Manifest::read(&dir)?;
        if manifest.plan_toml != options.plan_toml {
            return Err(RunError::Setup(format!(
                "{}: the run was made with another plan (manifest plan {:?}); resume with the plan it was started with",
                dir.display(),
                manifest.plan_path
            )));
        }
        if manifest.status == RunStatus::Completed {
            return Err(RunError::Setup(format!(
                "{}: the run is already completed ({} setpoints)",
                dir.display(),
                manifest.setpoints
            )));
        }
        setpoints.truncate(manifest.setpoints);
        let r = Journal::open_resume(&dir)?;
        let resume_no = manifest.resumed_at.len() + 1;
        (r.journal, manifest, r.truncated_bytes, resume_no)
    } else {
        if dir.join(super::journal::JOURNAL_FILE).exists()
            || dir.join(super::journal::MANIFEST_FILE).exists()
        {
            return Err(RunError::Setup(format!(
                "{} already holds a run: choose another --out, or continue it with --resume {}",
                dir.display(),
                dir.display()
            )));
        }
        if let Some(n) = options.limit {
            setpoints.truncate(n);
        }
        create_dir(&dir)?;
        let manifest = Manifest {
            plan_path: plan.path.display().to_string(),
            plan_name: plan.name.clone(),
            plan_toml: options.plan_toml.clone(),
            sensor_path: plan.sensor_path.display().to_string(),
            sensor_toml: options.sensor_toml.clone(),
            bench: options.bench.clone(),
            devices: options.devices.clone(),
            build_id: options.build_id.clone().or_else(|| plan.build_id.clone()),
            software_version: env!("CARGO_PKG_VERSION").to_string(),
            started_at: rfc3339_now(),
            resumed_at: Vec::new(),
            setpoints: setpoints.len(),
            planned_setpoints: Some(planned),
            limit: options.limit,
            measured_setpoints: 0,
            status: RunStatus::Running,
            end_reason: None,
            stop_signal: None,
            incomplete_reason: None,
            ended_at: None,
            software_commit: Some(super::journal::GIT_COMMIT.to_string()),
        };
        manifest.write(&dir)?;
        (Journal::create(&dir)?, manifest, 0, 0)
    };
    for sub in ["frames", "displacements", "forces"] {
        create_dir(&dir.join(sub))?;
    }
    if options.resume {
        manifest.resumed_at.push(rfc3339_now());
        manifest.status = RunStatus::Running;
        manifest.end_reason = None;
        manifest.ended_at = None;
        manifest.stop_signal = None;
        manifest.incomplete_reason = None;
        manifest.planned_setpoints.get_or_insert(planned);
        manifest.measured_setpoints = journal.completed().len();
        manifest.software_commit = Some(super::journal::GIT_COMMIT.to_string());
        if options.devices != serde_json::Value::Null {
            manifest.devices = options.devices.clone();
        }
        manifest.write(&dir)?;
    }
    let total = setpoints.len();
    let mut done = journal.completed().len();
    events(&RunEvent::Started {
        total,
        done,
        truncated_bytes,
    });

    let stage_limits = devices.stage.limits();
    let mut r = Runner {
        plan,
        sensor,
        geom: *geometry,
        dir: dir.clone(),
        dev: Timed {
            dev: devices,
            blocked: Duration::ZERO,
        },
        events,
        stop: Arc::clone(&options.stop),
        stage_limits,
        commanded: None,
        in_contact: false,
        normal_ctl: ForceController::new(
            INITIAL_STIFFNESS_N_PER_MM,
            MAX_CONTROL_STEP_MM,
            plan.safety.max_force_n[2],
        ),
        tracker: None,
        solvers: HashMap::new(),
        index: None,
        track_s: 0.0,
        solve_s: 0.0,
        precompute_s: 0.0,
        io_s: 0.0,
    };
    let mut timings = Timings::default();
    let mut measured = 0;

    let outcome: Step<()> = (|| {
        r.prepare(options, resume_no)?;
        let mut prev: Option<Setpoint> = None;
        for sp in &setpoints {
            if journal.completed().contains(&sp.index) {
                continue;
            }
            if r.stop.load(Ordering::SeqCst) {
                return Err(Halt::Interrupted);
            }
            // After a skip (resume) the previous setpoint's contact is gone.
            let fresh = prev.is_some_and(|p| p.index + 1 != sp.index);
            let retract = needs_retract(if fresh { None } else { prev.as_ref() }, sp);
            (r.events)(&RunEvent::SetpointStarted {
                setpoint: *sp,
                done,
                total,
            });
            let t0 = Instant::now();
            let blocked0 = r.dev.blocked;
            r.track_s = 0.0;
            r.solve_s = 0.0;
            r.precompute_s = 0.0;
            r.io_s = 0.0;
            r.index = Some(sp.index);
            let mut row = r.measure(sp, retract)?;
            let t_io = Instant::now();
            row.completed_at = rfc3339_now();
            journal
                .append(&row)
                .map_err(|e| Halt::Abort(format!("cannot write the journal: {e}")))?;
            r.io_s += t_io.elapsed().as_secs_f64();
            done += 1;
            measured += 1;
            let elapsed_s = t0.elapsed().as_secs_f64();
            let device_s = (r.dev.blocked - blocked0).as_secs_f64();
            let overhead_s =
                (elapsed_s - device_s - r.track_s - r.solve_s - r.precompute_s - r.io_s).max(0.0);
            timings.setpoints += 1;
            timings.wall_s += elapsed_s;
            timings.device_s += device_s;
            timings.track_s += r.track_s;
            timings.solve_s += r.solve_s;
            timings.precompute_s += r.precompute_s;
            timings.io_s += r.io_s;
            timings.overhead_s += overhead_s;
            timings.max_overhead_s = timings.max_overhead_s.max(overhead_s);
            (r.events)(&RunEvent::SetpointMeasured {
                index: sp.index,
                done,
                total,
                target_n: [sp.tangential_n[0], sp.tangential_n[1], sp.normal_n],
                force_n: [row.fx_n, row.fy_n, row.fz_n],
                fsum_n: [row.fsum_x_n, row.fsum_y_n, row.fsum_z_n],
                settled: row.settled,
                elapsed_s,
                device_s,
                overhead_s,
            });
            prev = Some(*sp);
        }
        r.index = None;
        r.retract()?;
        Ok(())
    })();

    let signal = options.stop_signal.load(Ordering::SeqCst);
    let (status, reason) = match outcome {
        Ok(()) => (RunStatus::Completed, None),
        Err(Halt::Interrupted) => {
            // Stop motion first, then leave the contact; the journal is already durable.
            let _ = r.dev.stop();
            let retract = r.retract_unguarded();
            let by = super::journal::stop_cause(signal);
            let reason = match retract {
                Ok(()) => format!("interrupted by {by}: motion stopped, stage retracted"),
                Err(e) => format!("interrupted by {by}; retract failed: {e:?}"),
            };
            (RunStatus::Interrupted, Some(reason))
        }
        Err(Halt::Abort(reason)) => {
            let _ = r.dev.stop();
            let reason = match r.retract_unguarded() {
                Ok(()) => reason,
                Err(e) => format!("{reason}; retract after abort failed: {e:?}"),
            };
            (RunStatus::Aborted, Some(reason))
        }
    };
    manifest.finish(
        status,
        reason.clone(),
        journal.completed().len(),
        (status == RunStatus::Interrupted && signal != 0).then_some(signal),
        rfc3339_now(),
    );
    manifest.write(&dir)?;
    (r.events)(&RunEvent::Finished {
        status,
        reason: reason.clone(),
    });
    Ok(RunSummary {
        status,
        reason,
        total,
        done: journal.completed().len(),
        measured,
        timings,
    })
}

fn create_dir(p: &Path) -> Result<(), RunError> {
    std::fs::create_dir_all(p).map_err(|source| RunError::Io {
        path: p.to_path_buf(),
        source,
    })
}

impl Runner<'_, '_, '_, '_> {
    fn stopped(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }

    /// Homing, retract, tare and the reference frame.
    fn prepare(&mut self, options: &RunOptions, resume_no: usize) -> Step<()> {
        // Leave any contact a killed run left behind before anything else moves.
        self.retract()?;
        if options.home {
            (self.events)(&RunEvent::Homing);
            self.dev.home().map_err(|e| dev_abort("homing", &e))?;
            self.commanded = None;
        }
        let xy = self.plan.approach_position_mm;
        self.move_lateral_at_clearance(xy)?;
        if options.tare {
            self.dev.tare().map_err(|e| dev_abort("taring", &e))?;
            // The next samples reflect the new offset (DynPick applies it to the next
            // record; FT 300 at once).
            self.dev.sleep(Duration::from_millis(20));
            let w = self.read_retry()?;
            let f = w.force_n;
            (self.events)(&RunEvent::Tared {
                residual_n: (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt(),
            });
        }
        let frame = self.grab_retry()?;
        let name = if resume_no == 0 {
            "frames/reference.png".to_string()
        } else {
            format!("frames/reference_resume{resume_no}.png")
        };
        let t_io = Instant::now();
        frame
            .image
            .save(self.dir.join(&name))
            .map_err(|e| Halt::Abort(format!("cannot write {name}: {e}")))?;
        self.io_s += t_io.elapsed().as_secs_f64();
        let reference = vision::detect(
            &FrameView::rgb8(&frame.image),
            self.sensor,
            &vision::DetectConfig::default(),
        )
        .map_err(|e| Halt::Abort(format!("reference frame {name}: {e}")))?;
        (self.events)(&RunEvent::Reference {
            path: name,
            markers: reference.markers.len(),
            missing: reference.missing.len(),
        });
        self.tracker = Some(Tracker::new(reference, TrackConfig::default()));
        Ok(())
    }

    /// Checks a stage target against the plan's sensor-frame box and the stage box.
    fn check_target(&self, target: StagePositionMm) -> Step<()> {
        let s = &self.plan.safety;
        let xy = self.geom.sensor_xy(target);
        let depth = self.geom.depth(target[2]);
        let p = [xy[0], xy[1], depth];
        for (i, name) in ["x", "y", "depth z"].iter().enumerate() {
            let v = p[i];
            if !(v.is_finite() && v >= s.travel_min_mm[i] - 1e-9 && v <= s.travel_max_mm[i] + 1e-9)
            {
                return Err(Halt::Abort(format!(
                    "refused before moving: sensor-frame {name} = {v:.4} mm is outside the plan's travel box {}..{} mm",
                    s.travel_min_mm[i], s.travel_max_mm[i]
                )));
            }
        }
        self.stage_limits
            .check(target)
            .map_err(|e| Halt::Abort(format!("refused before moving: stage {e}")))
    }

    fn read_retry(&mut self) -> Step<Wrench> {
        let mut attempt = 0;
        loop {
            match self.dev.read() {
                Ok(w) => return Ok(w),
                Err(e) if attempt < READ_RETRIES && e.kind() != ErrorKind::Disconnected => {
                    attempt += 1;
                    (self.events)(&RunEvent::Retry {
                        index: self.index,
                        attempt,
                        reason: format!("force sensor read failed: {e}"),
                    });
                }
                Err(e) => return Err(dev_abort("reading the force sensor", &e)),
            }
        }
    }

    fn grab_retry(&mut self) -> Step<CameraFrame> {
        let mut attempt = 0;
        loop {
            match self.dev.grab() {
                Ok(f) => return Ok(f),
                Err(e) if attempt < READ_RETRIES && e.kind() != ErrorKind::Disconnected => {
                    attempt += 1;
                    (self.events)(&RunEvent::Retry {
                        index: self.index,
                        attempt,
                        reason: format!("camera grab failed: {e}"),
                    });
                }
                Err(e) => return Err(dev_abort("grabbing a frame", &e)),
            }
        }
    }

    fn mean_force(&mut self, n: usize) -> Step<Wrench> {
        let mut m = Wrench::default();
        for _ in 0..n {
            let w = self.read_retry()?;
            if let Some(trip) = check_force_limits(&w, &self.plan.safety.max_force_n) {
                return Err(self.trip(format!("{trip}"), Instant::now()));
            }
            for i in 0..3 {
                m.force_n[i] += w.force_n[i] / n as f64;
                m.torque_nm[i] += w.torque_nm[i] / n as f64;
            }
        }
        Ok(m)
    }

    /// The watchdog fired at `detected`: stop, measure the latency, retract, abort.
    fn trip(&mut self, what: String, detected: Instant) -> Halt {
        let stop = self.dev.stop();
        // Standing still: the stop call returned and the stage reports no motion.
        let deadline = Instant::now() + Duration::from_secs(2);
        while let Ok(StageState::Moving) = self.dev.state() {
            if Instant::now() > deadline {
                break;
            }
        }
        let latency = detected.elapsed().as_secs_f64();
        let stop_note = match stop {
            Ok(()) => String::new(),
            Err(e) => format!(" (stop command failed: {e})"),
        };
        let reason = format!(
            "safety limit: {what}{}; stage stopped {:.1} ms after the reading{stop_note}",
            self.index
                .map(|i| format!(" at setpoint {i}"))
                .unwrap_or_default(),
            latency * 1e3
        );
        (self.events)(&RunEvent::SafetyTrip {
            index: self.index,
            reason: reason.clone(),
            stop_latency_s: latency,
        });
        self.commanded = None;
        Halt::Abort(reason)
    }

    /// A move under the watchdog. With `contact_n`, stops as soon as fz ≥ it and
    /// returns `true` (contact); otherwise returns once the target is reached.
    fn guarded_move(
        &mut self,
        target: StagePositionMm,
        speed_mm_s: f64,
        contact_n: Option<f64>,
    ) -> Step<bool> {
        self.check_target(target)?;
        if self.stopped() {
            return Err(Halt::Interrupted);
        }
        let speed = speed_mm_s.min(self.plan.safety.max_speed_mm_s);
        let from = self.commanded;
        self.dev
            .move_to(target, speed)
            .map_err(|e| dev_abort(&format!("moving to {target:?} mm"), &e))?;
        self.commanded = Some(target);
        let distance = from.map_or(100.0, |f| {
            ((f[0] - target[0]).powi(2) + (f[1] - target[1]).powi(2) + (f[2] - target[2]).powi(2))
                .sqrt()
        });
        let mut deadline =
            Instant::now() + Duration::from_secs_f64(distance / speed) * 2 + MOVE_GRACE;
        let mut read_failures = 0;
        loop {
            if self.stopped() {
                let _ = self.dev.stop();
                return Err(Halt::Interrupted);
            }
            // One attempt per reading: the driver's retries would keep the stage
            // moving blind for several reply deadlines.
            let w = match self.dev.read_once() {
                Ok(w) => w,
                Err(e) => {
                    // Blind while moving: stop first, then try to recover the sensor
                    // and finish the move from where the stage stopped.
                    let _ = self.dev.stop();
                    if e.kind() == ErrorKind::Disconnected || read_failures >= READ_RETRIES {
                        return Err(dev_abort("reading the force sensor while moving", &e));
                    }
                    read_failures += 1;
                    (self.events)(&RunEvent::Retry {
                        index: self.index,
                        attempt: read_failures,
                        reason: format!(
                            "force sensor read failed while moving ({e}): stage stopped, resuming the move"
                        ),
                    });
                    let w = self.read_retry()?;
                    if let Some(trip) = check_force_limits(&w, &self.plan.safety.max_force_n) {
                        return Err(self.trip(format!("{trip}"), Instant::now()));
                    }
                    self.dev.move_to(target, speed).map_err(|e| {
                        dev_abort(&format!("resuming the move to {target:?} mm"), &e)
                    })?;
                    deadline += MOVE_GRACE;
                    continue;
                }
            };
            if let Some(trip) = check_force_limits(&w, &self.plan.safety.max_force_n) {
                return Err(self.trip(format!("{trip}"), Instant::now()));
            }
            if let Some(c) = contact_n {
                if w.force_n[2] >= c {
                    self.dev
                        .stop()
                        .map_err(|e| dev_abort("stopping at contact", &e))?;
                    let p = self
                        .dev
                        .position()
                        .map_err(|e| dev_abort("reading the position at contact", &e))?;
                    self.commanded = Some(p);
                    (self.events)(&RunEvent::Contact {
                        index: self.index.unwrap_or(0),
                        depth_mm: self.geom.depth(p[2]),
                        fz_n: w.force_n[2],
                    });
                    return Ok(true);
                }
            }
            let state = self
                .dev
                .state()
                .map_err(|e| dev_abort("polling the stage", &e))?;
            match state {
                StageState::Idle => {
                    let p = self
                        .dev
                        .position()
                        .map_err(|e| dev_abort("reading the position", &e))?;
                    let off = (0..3).map(|i| (p[i] - target[i]).abs()).fold(0.0, f64::max);
                    if off <= POSITION_TOLERANCE_MM {
                        return Ok(false);
                    }
                }
                StageState::Alarm => {
                    return Err(Halt::Abort(format!(
                        "the stage entered its alarm state while moving to {target:?} mm"
                    )))
                }
                _ => {}
            }
            if Instant::now() > deadline {
                let _ = self.dev.stop();
                return Err(Halt::Abort(format!(
                    "the stage did not reach {target:?} mm within {:.1} s",
                    (distance / speed) * 2.0 + MOVE_GRACE.as_secs_f64()
                )));
            }
        }
    }

    /// Stage z of the retract height.
    fn safe_z(&self) -> f64 {
        self.geom.stage_z(-self.geom.clearance_mm)
    }

    /// Moves up to the retract height (z only) under the watchdog, unless already there.
    fn retract(&mut self) -> Step<()> {
        let here = match self.commanded {
            Some(p) => p,
            None => {
                let p = self
                    .dev
                    .position()
                    .map_err(|e| dev_abort("reading the position", &e))?;
                self.commanded = Some(p);
                p
            }
        };
        self.in_contact = false;
        self.normal_ctl.reset();
        if let Some(t) = self.tracker.as_mut() {
            t.reset();
        }
        if self.geom.depth(here[2]) <= -self.geom.clearance_mm + 1e-6 {
            return Ok(());
        }
        let target = [here[0], here[1], self.safe_z()];
        // Only the stage box applies to a retract (the plan box may not contain the
        // position a killed run or a homing cycle left).
        self.stage_limits
            .check(target)
            .map_err(|e| Halt::Abort(format!("refused before moving: stage {e}")))?;
        let v = self.plan.safety.max_speed_mm_s;
        self.dev
            .move_to(target, v)
            .map_err(|e| dev_abort("retracting", &e))?;
        self.commanded = Some(target);
        self.wait_reached(target)
    }

    /// Retract after a stop or abort: no watchdog (the force only falls), best effort.
    fn retract_unguarded(&mut self) -> Result<(), String> {
        let here = self.dev.position().map_err(|e| e.to_string())?;
        self.commanded = Some(here);
        if self.geom.depth(here[2]) <= -self.geom.clearance_mm + 1e-6 {
            return Ok(());
        }
        let target = [here[0], here[1], self.safe_z()];
        self.stage_limits.check(target)?;
        // A stop may have left the controller held or locked.
        if let Ok(StageState::Alarm) = self.dev.state() {
            let _ = self.dev.dev.stage.unlock();
        }
        self.dev
            .move_to(target, self.plan.safety.max_speed_mm_s)
            .map_err(|e| e.to_string())?;
        self.dev
            .wait_idle(Duration::from_secs(30))
            .map_err(|e| e.to_string())?;
        self.commanded = Some(target);
        self.in_contact = false;
        Ok(())
    }

    /// Waits for a move the watchdog need not see (retract): polls state and force.
    fn wait_reached(&mut self, target: StagePositionMm) -> Step<()> {
        let deadline = Instant::now() + MOVE_GRACE * 4;
        loop {
            if self.stopped() {
                let _ = self.dev.stop();
                return Err(Halt::Interrupted);
            }
            let s = self
                .dev
                .state()
                .map_err(|e| dev_abort("polling the stage", &e))?;
            if s == StageState::Idle {
                let p = self
                    .dev
                    .position()
                    .map_err(|e| dev_abort("reading the position", &e))?;
                if (0..3).all(|i| (p[i] - target[i]).abs() <= POSITION_TOLERANCE_MM) {
                    return Ok(());
                }
            }
            if s == StageState::Alarm {
                return Err(Halt::Abort(format!(
                    "the stage entered its alarm state while moving to {target:?} mm"
                )));
            }
            if Instant::now() > deadline {
                return Err(Halt::Abort(format!(
                    "the stage did not reach {target:?} mm in time"
                )));
            }
            self.dev.sleep(Duration::from_millis(2));
        }
    }

    /// Retract (if needed) and move to a sensor-frame point at the retract height.
    fn move_lateral_at_clearance(&mut self, xy_mm: [f64; 2]) -> Step<()> {
        self.retract()?;
        let target = self.geom.stage_point(xy_mm, -self.geom.clearance_mm);
        if let Some(c) = self.commanded {
            if (0..3).all(|i| (c[i] - target[i]).abs() <= 1e-9) {
                return Ok(());
            }
        }
        self.guarded_move(target, self.plan.safety.max_speed_mm_s, None)?;
        Ok(())
    }

    /// Approach until contact at `xy_mm`.
    fn approach(&mut self, xy_mm: [f64; 2]) -> Step<()> {
        let deepest = self
            .geom
            .stage_point(xy_mm, self.plan.safety.travel_max_mm[2]);
        let contact = self.guarded_move(
            deepest,
            self.plan.approach_speed_mm_s,
            Some(self.plan.contact_force_n),
        )?;
        if !contact {
            return Err(Halt::Abort(format!(
                "no contact (fz < {:.4} N) down to the deepest allowed indentation {} mm (safety.travel_max_mm[2]): check the bench geometry's surface_z_mm",
                self.plan.contact_force_n, self.plan.safety.travel_max_mm[2]
            )));
        }
        self.in_contact = true;
        self.normal_ctl.reset();
        Ok(())
    }

    /// Normal (and tangential) force control at the setpoint.
    fn control(&mut self, sp: &Setpoint, lateral: &mut [f64; 2]) -> Step<()> {
        let tol = self.plan.force_tolerance_n;
        let t_mag = sp.tangential_n[0].hypot(sp.tangential_n[1]);
        let dir = if t_mag > 0.0 {
            [sp.tangential_n[0] / t_mag, sp.tangential_n[1] / t_mag]
        } else {
            [0.0, 0.0]
        };
        let max_t = self.plan.safety.max_force_n[0].min(self.plan.safety.max_force_n[1]);
        let mut tan_ctl =
            ForceController::new(INITIAL_STIFFNESS_N_PER_MM, MAX_CONTROL_STEP_MM, max_t);
        let max_depth = self.plan.safety.travel_max_mm[2];
        for _ in 0..self.plan.max_control_steps {
            let w = self.mean_force(CONTROL_SAMPLES)?;
            let f = w.force_n;
            let q = f[0] * dir[0] + f[1] * dir[1];
            let normal_ok = (f[2] - sp.normal_n).abs() <= tol;
            let tangential_ok = t_mag == 0.0 || (q - t_mag).abs() <= tol;
            if normal_ok && tangential_ok {
                return Ok(());
            }
            let here = self
                .commanded
                .unwrap_or(self.geom.stage_point(sp.position_mm, 0.0));
            let xy = self.geom.sensor_xy(here);
            if !normal_ok {
                let depth = self.geom.depth(here[2]);
                let next = self
                    .normal_ctl
                    .next_z(depth, f[2], sp.normal_n)
                    .min(max_depth);
                if next <= depth + 1e-9 && f[2] < sp.normal_n - tol {
                    return Err(Halt::Abort(format!(
                        "cannot reach fz = {:.4} N: {:.4} N at the deepest allowed indentation {max_depth} mm",
                        sp.normal_n, f[2]
                    )));
                }
                let target = self.geom.stage_point(xy, next);
                self.guarded_move(target, self.plan.approach_speed_mm_s, None)?;
            } else {
                // Lateral travel s along the direction; Q grows with s (Mindlin).
                let s = lateral[0] * dir[0] + lateral[1] * dir[1];
                let next = tan_ctl.next_z(s, q, t_mag);
                let d = next - s;
                let target_xy = [xy[0] + d * dir[0], xy[1] + d * dir[1]];
                lateral[0] += d * dir[0];
                lateral[1] += d * dir[1];
                let target = [
                    self.geom.stage_xy(target_xy)[0],
                    self.geom.stage_xy(target_xy)[1],
                    here[2],
                ];
                self.guarded_move(target, self.plan.approach_speed_mm_s, None)?;
            }
        }
        let w = self.mean_force(CONTROL_SAMPLES)?;
        Err(Halt::Abort(format!(
            "force control did not converge in {} steps (control.max_steps): measured ({:.4}, {:.4}, {:.4}) N, target ({:.4}, {:.4}, {:.4}) N ± {:.4} N",
            self.plan.max_control_steps,
            w.force_n[0],
            w.force_n[1],
            w.force_n[2],
            sp.tangential_n[0],
            sp.tangential_n[1],
            sp.normal_n,
            tol
        )))
    }

    /// Waits for the force to settle (or the fixed dwell). Returns whether it settled.
    fn settle(&mut self) -> Step<bool> {
        let st = self.plan.settle;
        let t0 = Instant::now();
        if st.dwell_s > 0.0 {
            while t0.elapsed().as_secs_f64() < st.dwell_s {
                if self.stopped() {
                    return Err(Halt::Interrupted);
                }
                let left = st.dwell_s - t0.elapsed().as_secs_f64();
                self.dev
                    .sleep(Duration::from_secs_f64(left.clamp(0.0, 0.05)));
            }
            return Ok(true);
        }
        let mut det = SettleDetector::new(st.window_s, st.max_sd_n);
        loop {
            if self.stopped() {
                return Err(Halt::Interrupted);
            }
            let w = self.read_retry()?;
            if let Some(trip) = check_force_limits(&w, &self.plan.safety.max_force_n) {
                return Err(self.trip(format!("{trip}"), Instant::now()));
            }
            let f = w.force_n;
            let t = t0.elapsed().as_secs_f64();
            if det.push(t, (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt()) {
                return Ok(true);
            }
            if t >= st.timeout_s {
                return Ok(false);
            }
        }
    }

    /// One setpoint, from motion to the journal row (not yet appended).
    fn measure(&mut self, sp: &Setpoint, retract: bool) -> Step<JournalRow> {
        let t_move0 = Instant::now();
        let target_xy = [
            sp.position_mm[0] + sp.shift_mm[0],
            sp.position_mm[1] + sp.shift_mm[1],
        ];
        // Checks before any motion: the lateral target at the retract height and the
        // deepest allowed indentation there.
        if sp.normal_n > 0.0 {
            let deepest = self
                .geom
                .stage_point(target_xy, self.plan.safety.travel_max_mm[2]);
            self.check_target(deepest)?;
        }
        let safe = self.geom.stage_point(target_xy, -self.geom.clearance_mm);
        self.check_target(safe)?;

        let mut lateral = [0.0; 2];
        if retract || !self.in_contact {
            if sp.shift_mm != [0.0, 0.0] {
                // Displacement trials start from the unshifted position.
                self.move_lateral_at_clearance(sp.position_mm)?;
            }
            self.move_lateral_at_clearance(target_xy)?;
            if sp.normal_n > 0.0 {
                self.approach(target_xy)?;
            }
        }
        let mut settled = true;
        let mut t_settle = 0.0;
        let mut t_move = 0.0;
        for attempt in 0..=SETTLE_RETRIES {
            let t_c = Instant::now();
            if sp.normal_n > 0.0 {
                self.control(sp, &mut lateral)?;
            }
            t_move += if attempt == 0 {
                t_move0.elapsed().as_secs_f64()
            } else {
                t_c.elapsed().as_secs_f64()
            };
            let t_s = Instant::now();
            settled = self.settle()?;
            t_settle += t_s.elapsed().as_secs_f64();
            if sp.normal_n <= 0.0 || attempt == SETTLE_RETRIES {
                break;
            }
            let f = self.mean_force(CONTROL_SAMPLES)?.force_n;
            let dz = (f[2] - sp.normal_n).abs();
            if dz <= self.plan.force_tolerance_n {
                break;
            }
            (self.events)(&RunEvent::Retry {
                index: Some(sp.index),
                attempt: attempt + 1,
                reason: format!(
                    "fz drifted to {:.4} N while settling (target {:.4} N ± {:.4} N): controlling again",
                    f[2], sp.normal_n, self.plan.force_tolerance_n
                ),
            });
        }

        // Acquire.
        let t_acq = Instant::now();
        let n = self.plan.samples;
        let mut samples = Vec::with_capacity(n);
        for _ in 0..n {
            let w = self.read_retry()?;
            if let Some(trip) = check_force_limits(&w, &self.plan.safety.max_force_n) {
                return Err(self.trip(format!("{trip}"), Instant::now()));
            }
            samples.push(w);
        }
        let (mean, sd) = mean_sd(&samples);
        let stage = self
            .dev
            .position()
            .map_err(|e| dev_abort("reading the position", &e))?;
        let mut frames = Vec::with_capacity(self.plan.frames);
        for _ in 0..self.plan.frames {
            frames.push(self.grab_retry()?);
        }
        let t_acquire = t_acq.elapsed().as_secs_f64();

        let (rel, fsum, t_track, t_solve) = self.process_frames(sp.index, &frames)?;
        Ok(JournalRow {
            index: sp.index,
            trial: sp.trial,
            swept_value: sp.swept_value,
            target_normal_n: sp.normal_n,
            target_tx_n: sp.tangential_n[0],
            target_ty_n: sp.tangential_n[1],
            fx_n: mean.force_n[0],
            fy_n: mean.force_n[1],
            fz_n: mean.force_n[2],
            mx_nm: mean.torque_nm[0],
            my_nm: mean.torque_nm[1],
            mz_nm: mean.torque_nm[2],
            fx_sd_n: sd[0],
            fy_sd_n: sd[1],
            fz_sd_n: sd[2],
            stage_x_mm: stage[0],
            stage_y_mm: stage[1],
            stage_z_mm: stage[2],
            settled,
            frames: rel.join(";"),
            fsum_x_n: fsum[0],
            fsum_y_n: fsum[1],
            fsum_z_n: fsum[2],
            t_move_s: t_move,
            t_settle_s: t_settle,
            t_acquire_s: t_acquire,
            t_track_s: t_track,
            t_solve_s: t_solve,
            completed_at: String::new(),
        })
    }

    /// Saves, tracks and reconstructs a setpoint's frames. Returns the frame paths
    /// (relative), the force sums and the tracking / solving times.
    #[allow(clippy::type_complexity)]
    fn process_frames(
        &mut self,
        index: usize,
        frames: &[CameraFrame],
    ) -> Step<(Vec<String>, [f64; 3], f64, f64)> {
        let sensor = self.sensor;
        let mut rel = Vec::with_capacity(frames.len());
        let mut tracked: Vec<(String, Vec<MarkerTrack>)> = Vec::with_capacity(frames.len());
        let mut t_track = 0.0;
        for (k, f) in frames.iter().enumerate() {
            let name = format!("frames/{index:05}_{k}.png");
            let t_io = Instant::now();
            f.image
                .save(self.dir.join(&name))
                .map_err(|e| Halt::Abort(format!("cannot write {name}: {e}")))?;
            self.io_s += t_io.elapsed().as_secs_f64();
            let t0 = Instant::now();
            let tracker = self
                .tracker
                .as_mut()
                .ok_or_else(|| Halt::Abort("no reference frame".into()))?;
            let tracks = tracker
                .track(&FrameView::rgb8(&f.image))
                .map_err(|e| Halt::Abort(format!("tracking {name}: {e}")))?
                .to_vec();
            t_track += t0.elapsed().as_secs_f64();
            tracked.push((name.clone(), tracks));
            rel.push(name);
        }
        let tracker = self
            .tracker
            .as_ref()
            .ok_or_else(|| Halt::Abort("no reference frame".into()))?;
        let t_io = Instant::now();
        let dpath = format!("displacements/{index:05}.csv");
        vision::write_tracks(
            &self.dir.join(&dpath),
            sensor,
            tracker.reference(),
            &tracked,
        )
        .map_err(|e| Halt::Abort(format!("cannot write {dpath}: {e}")))?;
        self.io_s += t_io.elapsed().as_secs_f64();

        // Mean displacement over the frames; a marker lost in any frame is lost.
        let t0 = Instant::now();
        let mut records = Vec::new();
        for (k, (_, tracks)) in tracked.iter().enumerate() {
            let r = tracker.displacement_records(tracks, &sensor.camera);
            if k == 0 {
                records = r;
            } else {
                for (acc, x) in records.iter_mut().zip(r) {
                    acc.u_mm = match (acc.u_mm, x.u_mm) {
                        (Some(a), Some(b)) => Some([a[0] + b[0], a[1] + b[1]]),
                        _ => None,
                    };
                }
            }
        }
        let nf = tracked.len().max(1) as f64;
        for r in &mut records {
            if let Some(u) = r.u_mm.as_mut() {
                u[0] /= nf;
                u[1] /= nf;
            }
        }
        let frame = DisplacementFrame {
            frame: String::new(),
            records,
        };
        let sites = frame.sites(sensor);
        let u = frame.u_mm();
        let key: Vec<bool> = frame.records.iter().map(|r| r.u_mm.is_some()).collect();
        let n_out = 3 * sensor.force_grid.len();
        let mut f = vec![f64::NAN; n_out];
        let mut precompute_s = 0.0;
        let solved: Result<(), String> = (|| {
            if !self.solvers.contains_key(&key) {
                let tp = Instant::now();
                let problem = Problem::new(sensor, &sites);
                let s = solve::precompute(&problem, &self.plan.solver, Some(&u))
                    .map_err(|e| e.to_string())?;
                self.solvers.insert(key.clone(), s);
                precompute_s = tp.elapsed().as_secs_f64();
            }
            let s = self
                .solvers
                .get_mut(&key)
                .ok_or_else(|| "solver cache".to_string())?;
            s.apply(&u, &mut f).map_err(|e| e.to_string())
        })();
        if let Err(e) = solved {
            f.iter_mut().for_each(|v| *v = f64::NAN);
            (self.events)(&RunEvent::Warning {
                index,
                message: format!("reconstruction failed ({e}); force sums recorded as NaN"),
            });
        }
        let t_solve = (t0.elapsed().as_secs_f64() - precompute_s).max(0.0);
        self.precompute_s += precompute_s;
        let mut fsum = [0.0; 3];
        for (j, v) in f.iter().enumerate() {
            fsum[j % 3] += v;
        }
        let t_io = Instant::now();
        let fpath = format!("forces/{index:05}.csv");
        formats::write_forces(
            &self.dir.join(&fpath),
            &sensor.force_grid,
            &[(String::new(), f)],
        )
        .map_err(|e| Halt::Abort(format!("cannot write {fpath}: {e}")))?;
        self.io_s += t_io.elapsed().as_secs_f64();
        self.track_s += t_track;
        self.solve_s += t_solve;
        Ok((rel, fsum, t_track, t_solve))
    }
}

/// Mean wrench and per-component force SD (sample SD; 0 for one sample).
fn mean_sd(samples: &[Wrench]) -> (Wrench, [f64; 3]) {
    let n = samples.len().max(1) as f64;
    let m = Wrench::mean(samples);
    let mut sd = [0.0; 3];
    if samples.len() > 1 {
        for (i, s) in sd.iter_mut().enumerate() {
            let ss: f64 = samples
                .iter()
                .map(|w| (w.force_n[i] - m.force_n[i]).powi(2))
                .sum();
            *s = (ss / (n - 1.0)).sqrt();
        }
    }
    (m, sd)
}

/// The planned sweep kind's name (for messages and the CLI).
pub fn sweep_name(plan: &Plan) -> &'static str {
    match plan.sweep {
        Sweep::Magnitude { .. } => "magnitude",
        Sweep::Angle { .. } => "angle",
        Sweep::Spatial { .. } => "spatial",
        Sweep::Displacement { .. } => "displacement",
        Sweep::Setpoints(_) => "setpoints",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rfc3339_matches_known_instants() {
        assert_eq!(rfc3339(0), "1970-01-01T00:00:00Z");
        // 2000-02-29 (leap day) 12:34:56 UTC = 951827696.
        assert_eq!(rfc3339(951_827_696), "2000-02-29T12:34:56Z");
        assert_eq!(rfc3339(1_795_305_600), "2026-11-22T00:00:00Z");
    }

    fn sp(index: usize, trial: usize, normal_n: f64, tangential_n: [f64; 2]) -> Setpoint {
        Setpoint {
            index,
            trial,
            position_mm: [9.0, 6.75],
            normal_n,
            tangential_n,
            shift_mm: [0.0; 2],
            swept_value: 0.0,
        }
    }

    #[test]
    fn contact_is_kept_only_along_a_normal_ramp() {
        let a = sp(1, 0, 0.5, [0.0; 2]);
        let b = sp(2, 0, 1.0, [0.0; 2]);
        assert!(!needs_retract(Some(&a), &b), "ramp continues in contact");
        assert!(needs_retract(None, &b), "first setpoint");
        assert!(
            needs_retract(Some(&a), &sp(2, 1, 1.0, [0.0; 2])),
            "new trial"
        );
        assert!(
            needs_retract(Some(&a), &sp(2, 0, 1.0, [0.1, 0.0])),
            "tangential"
        );
        assert!(needs_retract(Some(&a), &sp(2, 0, 0.0, [0.0; 2])), "unload");
        let mut c = b;
        c.position_mm = [9.5, 6.75];
        assert!(needs_retract(Some(&a), &c), "new position");
    }

    #[test]
    fn mean_and_sample_sd_of_readings() {
        let w = |fz| Wrench {
            force_n: [0.0, 0.0, fz],
            torque_nm: [0.0; 3],
        };
        let (m, sd) = mean_sd(&[w(1.0), w(2.0), w(3.0)]);
        assert!((m.force_n[2] - 2.0).abs() < 1e-15);
        assert!((sd[2] - 1.0).abs() < 1e-15);
        assert_eq!(sd[0], 0.0);
    }
}
