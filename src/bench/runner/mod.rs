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
//!    (`displacements/NNNNN.csv`, as `tactbench track` writes it). When fewer than
//!    `[quality] min_ok_fraction` of the sensor's markers are ok in every frame, the
//!    frames are grabbed again (at most `max_reacquire` times); still below, the row
//!    is journalled `quality = flagged` or the run aborts (`on_fail`). Forces from the
//!    mean displacement over the frames (`forces/NNNNN.csv`) with the plan's solver,
//!    precomputed once per set of tracked markers.
//! 7. **Journal**: the row (with its marker counts) is appended and synced before the
//!    next move. A setpoint whose tracking or reconstruction failed, or whose frames
//!    were blank, saturated or markerless in every acquisition, is a *failed row*
//!    (empty force sums, `failure` says why) and the run goes on; `[quality]
//!    dead_camera_setpoints` consecutive dead setpoints stop it (a dead camera).
//! 8. **Force plausibility**: |F^sum| against the F/T's |F| (`[quality]
//!    force_ratio_min .. force_ratio_max` above `force_noise_floor_n`): outside, the
//!    row is `quality = implausible`; `max_implausible_rows` consecutive ones stop the
//!    run naming the likely cause (the sensor file's units, an unfitted modulus).
//!
//! **Record digests.** At the start and end of every session the manifest's `record`
//! gets the journal's SHA-256 (of its length then) and every evidence file's as
//! written ([`super::integrity`]); a resume refuses a record modified since, and
//! reconciles `sessions` with the journal after a session killed before its end.
//! Each device's provenance (real, simulated, replayed) is recorded at the start
//! ([`super::provenance`]).
//!
//! **Reference gate.** The reference frame (taken at the clearance height above the
//! approach position, after homing and taring) must show `[quality]
//! reference_min_found_fraction` of the sensor file's markers; otherwise the run
//! aborts before any setpoint with the measured numbers (found per layer, marker
//! pitch, centre, frame levels) and the likely cause (scale, origin, colour, exposure).
//!
//! Code layout: this file holds the public types, [`run`] and set-up (`prepare`);
//! `motion` the timed device calls, travel checks, guarded moves with the safety
//! watchdog, retract and approach; `acquire` force control, settling, acquisition,
//! tracking and reconstruction of one setpoint; `dry_run` planning without devices.
//!
//! **Safety watchdog.** While the stage moves, the runner reads the force sensor in a
//! loop; any component beyond `safety.max_force` stops the stage (GRBL feed hold,
//! Zaber `stop`), the time from the offending reading to the stage standing still is
//! measured (stop latency), the stage retracts, and the run aborts with the reason
//! and latency in the manifest. Settling and acquisition check the limits as well.
//!
//! **Stop flag.** When the caller's flag (SIGINT, SIGTERM, SIGHUP) is set, motion
//! stops, the stage retracts, the journal is already durable, and the manifest says
//! `interrupted` and by which signal.
//!
//! **Resume.** [`run`] with `resume = true` reopens the journal (a torn last line is
//! cut), skips completed indices, homes / tares as the bench requires, and takes a new
//! reference frame (`frames/reference_resumeN.png`; `frames/reference.png` stays the
//! first run's). Rows are never overwritten, so:
//! - a **hold** interrupted part-way is not re-run from its start (its rows exist):
//!   its force is re-established (approach and control) and its remaining samples
//!   are taken at their scheduled times counted from that moment (`hold_t_s` keeps
//!   meaning "seconds since the force of this loading was reached"); those rows are
//!   journalled `settled = false` and a warning is logged;
//! - a **`down` row** of an up-down sweep reached from a fresh contact first loads to
//!   the sweep's top level (not journalled), then unloads to its level.
//!
//! **Hold samples** (plan `hold` sweeps) skip settling: the first is taken as soon as
//! force control reached the target, the later ones wait (reading the F/T every
//! 20 ms for the safety limits, stopping at once on a stop request) until their time.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use thiserror::Error;

use super::config::BenchGeometry;
use super::control::ForceController;
pub use super::events::{rfc3339, rfc3339_now, Phase, RunEvent};
use super::journal::{
    Journal, JournalError, Manifest, RunStatus, Session, WriteFailure, MANIFEST_FILE,
};
use super::live::LiveWriter;
use super::plan::{Plan, Setpoint, Sweep};
use crate::device::{
    Camera, DeviceError, ForceSensor, Stage, StagePositionMm, TravelLimits, Wrench,
};
use crate::sensor::Sensor;
use crate::solve::FrameSolver;
use crate::vision::camera::{CameraCalibration, PixelMapping};
use crate::vision::{TrackConfig, Tracker};

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

/// Most [`RunEvent::Reading`]s per second.
pub const READING_EVENTS_PER_S: u32 = 5;

/// Position tolerance for "the stage reached its target", mm.
pub const POSITION_TOLERANCE_MM: f64 = 0.005;

/// Longest wait for a stage to finish a move beyond its nominal duration.
pub const MOVE_GRACE: Duration = Duration::from_secs(5);

mod acquire;
pub use acquire::{mean_over_frames, solve_setpoint, SolvedSetpoint};
mod dry_run;
mod motion;
mod record;

pub use dry_run::{
    check_bench_inputs, dry_run, needs_retract, sensor_area_checks, stage_limits_of, DryRun,
    InputError, StageTargets,
};
use motion::Timed;
pub use motion::{ft_sample_period, STATUS_MISSES};
pub use record::WriteFault;
use record::WriteGate;

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
    /// A camera calibration (`run --camera camera.toml`): `(path as given, text)`. The
    /// tracker maps pixels to the sensor frame with it instead of the sensor file's
    /// `[camera]` mapping; recorded in the manifest, and a resume must use the same.
    pub camera: Option<(String, String)>,
    /// Bench description for the manifest.
    pub bench: serde_json::Value,
    /// Device identities for the manifest.
    pub devices: serde_json::Value,
    /// Run the homing cycle before the first setpoint.
    pub home: bool,
    /// Tare the force sensor unloaded before the reference frame.
    pub tare: bool,
    /// At most `limit` setpoints measured by this session: the next ones of the plan
    /// not yet in the journal (a new run: the first `limit`). Recorded per session in
    /// the manifest; a run stopped by its limit stays resumable to its full plan.
    pub limit: Option<usize>,
    /// The bench is the built-in simulated bench (recorded in the manifest as
    /// `simulated`, shown on reports; `require_real_bench` criteria fail such a run).
    pub simulated: bool,
    /// Injected write failures (tests; `None` on every real run): see [`WriteFault`].
    pub write_fault: Option<WriteFault>,
    /// Set by the caller (Ctrl-C) to stop the run cleanly.
    pub stop: Arc<AtomicBool>,
    /// The signal number that set `stop` (0: none, or not a signal), recorded in the
    /// manifest and the stop reason (SIGINT and SIGTERM are told apart).
    pub stop_signal: Arc<AtomicI32>,
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
    /// The first write into the run directory that failed this session (the run then
    /// ends `aborted`; recorded in the manifest when it could still be written).
    pub write_failure: Option<WriteFailure>,
    /// Why the closing manifest could not be written (the manifest still says
    /// `running`; the caller must report the end and the write failure itself).
    pub manifest_error: Option<String>,
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
    /// Pixels -> sensor frame: the sensor file's `[camera]` mapping, or the run's
    /// camera calibration.
    mapping: PixelMapping,
    /// The `run --camera` calibration file the mapping came from (named in errors).
    camera_path: Option<String>,
    solvers: HashMap<Vec<bool>, Box<dyn FrameSolver>>,
    index: Option<usize>,
    /// When the force of the current hold (`hold` sweeps) was reached; `None` when no
    /// hold is under way in this contact (released by every retract).
    hold_t0: Option<Instant>,
    /// The current hold was re-established part-way (a resumed run): its samples are
    /// journalled `settled = false`.
    hold_restarted: bool,
    /// The phase last reported ([`RunEvent::Phase`]).
    phase: Option<Phase>,
    /// When the last [`RunEvent::Reading`] was sent.
    last_reading: Option<Instant>,
    /// Every write into the run directory goes through it (first failure, faults).
    fs: WriteGate,
    /// Consecutive setpoints whose every acquisition was a dead frame (blank,
    /// saturated, no marker): `[quality] dead_camera_setpoints` of them stop the run.
    dead_run: Vec<usize>,
    /// Consecutive rows that failed the force plausibility check.
    implausible_run: Vec<usize>,
    /// Why the run stops once the current row is journalled (a dead camera, persistent
    /// implausible forces).
    pending_abort: Option<String>,
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
    // Every event also goes into live.json (a hint for watchers in other processes).
    let mut live = LiveWriter::new(&dir);
    let events = &mut |e: &RunEvent| {
        live.observe(e);
        events(e);
    };
    let mut setpoints = plan.setpoints();
    let planned = setpoints.len();
    let (mut journal, mut manifest, truncated_bytes, resume_no) = if options.resume {
        open_resumed(&dir, options, planned)?
    } else {
        let manifest = create_run(&dir, plan, options, planned, geometry)?;
        (Journal::create(&dir)?, manifest, 0, 0)
    };
    for sub in ["frames", "displacements", "forces"] {
        create_dir(&dir.join(sub))?;
    }
    // This session's setpoints: the plan's not yet in the journal, in plan order, at
    // most `--limit` of them (a limit caps this session, never the run).
    let before = journal.completed().len();
    setpoints.retain(|sp| !journal.completed().contains(&sp.index));
    if let Some(n) = options.limit {
        setpoints.truncate(n);
    }
    start_session(
        &mut manifest,
        options,
        &journal,
        before + setpoints.len(),
        planned,
    );
    record_provenance(&mut manifest, options);
    let evidence = record_session_start(&dir, &mut manifest, &journal, before)?;
    manifest.write(&dir)?;
    let mut tally = Tally {
        total: before + setpoints.len(),
        done: before,
        measured: 0,
        timings: Timings::default(),
    };
    events(&RunEvent::Started {
        total: tally.total,
        done: tally.done,
        truncated_bytes,
    });

    let mut r = Runner::start(plan, sensor, geometry, devices, options, events, evidence)?;
    let outcome = r.session(options, resume_no, &setpoints, &mut journal, &mut tally);
    if outcome.is_err() {
        r.set_phase(Phase::Retract);
    }
    let signal = options.stop_signal.load(Ordering::SeqCst);
    let ended = r.leave(outcome, signal);
    Ok(r.close(&mut manifest, &journal, tally, ended, signal))
}

/// This session's progress: setpoints in the run and in the journal, measured by
/// this session, and where their time went.
struct Tally {
    total: usize,
    done: usize,
    measured: usize,
    timings: Timings,
}

/// The manifest and journal of the run a resume continues, after checking that it
/// can be continued: the same plan and camera mapping, not complete, its record as
/// the run wrote it. Returns the journal, the manifest (its sessions reconciled with
/// the journal), the bytes of a torn journal line cut, and the resume's number.
fn open_resumed(
    dir: &Path,
    options: &RunOptions,
    planned: usize,
) -> Result<(Journal, Manifest, u64, usize), RunError> {
    let manifest = Manifest::read(dir)?;
    if manifest.plan_toml != options.plan_toml {
        return Err(RunError::Setup(format!(
            "{}: the run was made with another plan (manifest plan {:?}); resume with the plan it was started with",
            dir.display(),
            manifest.plan_path
        )));
    }
    if manifest.camera_toml.as_deref() != options.camera.as_ref().map(|(_, t)| t.as_str()) {
        return Err(RunError::Setup(format!(
            "{}: the run was tracked with {}; resume with the same camera mapping",
            dir.display(),
            match &manifest.camera_path {
                Some(p) => format!("the camera calibration {p:?} (recorded in its manifest)"),
                None => "the sensor file's [camera] mapping (no --camera)".to_string(),
            }
        )));
    }
    // A run is complete when its journal holds the whole plan; a run a `--limit`
    // stopped ("completed" what that session was asked) stays resumable.
    let planned_of_run = manifest.planned_setpoints.unwrap_or(planned);
    if manifest.status == RunStatus::Completed && manifest.measured_setpoints >= planned_of_run {
        return Err(RunError::Setup(format!(
            "{}: the run is already completed (all {} setpoints of its plan measured)",
            dir.display(),
            manifest.measured_setpoints
        )));
    }
    // The record must be as the run wrote it: a resume would otherwise record
    // digests of an edited journal as the run's own.
    let check = super::integrity::verify(dir, &manifest);
    if check.modified() {
        return Err(RunError::Setup(format!(
            "{}: the record was modified after the run ({}); not resuming it",
            dir.display(),
            check.lines().join("; ")
        )));
    }
    let r = Journal::open_resume(dir)?;
    let mut manifest = manifest;
    // A session killed before it could record its end (kill -9) measured rows
    // the manifest does not count: the journal is the authority.
    manifest.reconcile_sessions(r.rows.len());
    let resume_no = manifest.resumed_at.len() + 1;
    Ok((r.journal, manifest, r.truncated_bytes, resume_no))
}

/// A new run: its directory (refused when it holds a run already) and its first
/// manifest, written.
fn create_run(
    dir: &Path,
    plan: &Plan,
    options: &RunOptions,
    planned: usize,
    geometry: &BenchGeometry,
) -> Result<Manifest, RunError> {
    if dir.join(super::journal::JOURNAL_FILE).exists()
        || dir.join(super::journal::MANIFEST_FILE).exists()
    {
        return Err(RunError::Setup(format!(
            "{} already holds a run: choose another --out, or continue it with --resume {}",
            dir.display(),
            dir.display()
        )));
    }
    create_dir(dir)?;
    let manifest = Manifest {
        plan_path: plan.path.display().to_string(),
        plan_name: plan.name.clone(),
        plan_toml: options.plan_toml.clone(),
        sensor_path: plan.sensor_path.display().to_string(),
        sensor_toml: options.sensor_toml.clone(),
        bench: with_geometry(options.bench.clone(), geometry),
        devices: options.devices.clone(),
        build_id: options.build_id.clone().or_else(|| plan.build_id.clone()),
        software_version: env!("CARGO_PKG_VERSION").to_string(),
        started_at: rfc3339_now(),
        resumed_at: Vec::new(),
        sessions: Vec::new(),
        setpoints: planned.min(options.limit.unwrap_or(usize::MAX)),
        planned_setpoints: Some(planned),
        limit: options.limit,
        measured_setpoints: 0,
        status: RunStatus::Running,
        end_reason: None,
        stop_signal: None,
        incomplete_reason: None,
        ended_at: None,
        software_commit: Some(super::journal::GIT_COMMIT.to_string()),
        camera_path: options.camera.as_ref().map(|(p, _)| p.clone()),
        camera_toml: options.camera.as_ref().map(|(_, t)| t.clone()),
        simulated: Some(options.simulated),
        write_failure: None,
        device_provenance: Vec::new(),
        record: None,
    };
    manifest.write(dir)?;
    Ok(manifest)
}

/// Records this session's start in the manifest: on resume the run is running
/// again towards `setpoints` (those in the journal and this session's), and a new
/// entry in `sessions`.
fn start_session(
    manifest: &mut Manifest,
    options: &RunOptions,
    journal: &Journal,
    setpoints: usize,
    planned: usize,
) {
    let before = journal.completed().len();
    let session_started = rfc3339_now();
    if options.resume {
        manifest.resumed_at.push(session_started.clone());
        manifest.limit = options.limit;
        manifest.setpoints = setpoints;
        manifest.status = RunStatus::Running;
        manifest.end_reason = None;
        manifest.ended_at = None;
        manifest.stop_signal = None;
        manifest.incomplete_reason = None;
        manifest.planned_setpoints.get_or_insert(planned);
        manifest.measured_setpoints = journal.completed().len();
        manifest.software_commit = Some(super::journal::GIT_COMMIT.to_string());
        // A run is simulated when any of its sessions was; a manifest from before the
        // flag stays "not recorded" unless this session is simulated.
        if options.simulated || manifest.simulated.is_some() {
            manifest.simulated = Some(options.simulated || manifest.simulated == Some(true));
        }
        if options.devices != serde_json::Value::Null {
            manifest.devices = options.devices.clone();
        }
    }
    manifest.sessions.push(Session {
        started_at: session_started,
        limit: options.limit,
        setpoints_before: before,
        setpoints_after: before,
    });
}

/// Every device's provenance (a run is real only when every device is); a run is
/// simulated when any of its sessions was not all real.
fn record_provenance(manifest: &mut Manifest, options: &RunOptions) {
    let provenance = super::provenance::judge(&options.devices, options.simulated);
    let not_real = provenance
        .iter()
        .any(|d| d.provenance != super::journal::Provenance::Real);
    if options.simulated || not_real || !options.resume {
        manifest.simulated = Some(not_real || manifest.simulated == Some(true));
    }
    if options.devices != serde_json::Value::Null || manifest.device_provenance.is_empty() {
        // The least real provenance of each device over the sessions is kept.
        let mut merged = provenance;
        for d in &mut merged {
            if let Some(old) = manifest
                .device_provenance
                .iter()
                .find(|o| o.device == d.device && o.provenance > d.provenance)
            {
                *d = old.clone();
            }
        }
        manifest.device_provenance = merged;
    }
}

/// The journal's digest as this session starts (after a resume cut a torn line or
/// upgraded an old header): rows appended from here on are covered at the end.
/// Returns the evidence digests of the earlier sessions.
fn record_session_start(
    dir: &Path,
    manifest: &mut Manifest,
    journal: &Journal,
    before: usize,
) -> Result<std::collections::BTreeMap<String, String>, RunError> {
    let evidence = manifest
        .record
        .as_ref()
        .map(|r| r.evidence.clone())
        .unwrap_or_default();
    manifest.record = Some(
        super::integrity::RecordDigests::journal_now(dir, evidence.clone(), before, rfc3339_now())
            .map_err(|source| RunError::Io {
                path: journal.path().to_path_buf(),
                source,
            })?,
    );
    Ok(evidence)
}

impl<'p, 'd, 'a, 'e> Runner<'p, 'd, 'a, 'e> {
    /// The runner of this session: the pixel mapping (the sensor file's, or the run's
    /// camera calibration), the stage's limits, every write through a gate that
    /// continues the earlier sessions' `evidence` digests.
    fn start(
        plan: &'p Plan,
        sensor: &'p Sensor,
        geometry: &BenchGeometry,
        devices: &'d mut Devices<'a>,
        options: &RunOptions,
        events: &'e mut dyn FnMut(&RunEvent),
        evidence: std::collections::BTreeMap<String, String>,
    ) -> Result<Self, RunError> {
        let dir = options.dir.clone();
        let mapping = match &options.camera {
            None => PixelMapping::Linear(sensor.camera),
            Some((path, text)) => PixelMapping::Calibrated(
                CameraCalibration::from_toml_str(text, Path::new(path), sensor)
                    .map_err(|e| RunError::Setup(e.to_string()))?,
            ),
        };
        let stage_limits = devices.stage.limits();
        Ok(Runner {
            plan,
            sensor,
            geom: *geometry,
            dir: dir.clone(),
            dev: Timed::new(devices),
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
            mapping,
            camera_path: options.camera.as_ref().map(|(p, _)| p.clone()),
            solvers: HashMap::new(),
            index: None,
            hold_t0: None,
            hold_restarted: false,
            phase: None,
            last_reading: None,
            fs: WriteGate::new(options.write_fault, &dir, evidence),
            dead_run: Vec::new(),
            implausible_run: Vec::new(),
            pending_abort: None,
            track_s: 0.0,
            solve_s: 0.0,
            precompute_s: 0.0,
            io_s: 0.0,
        })
    }
}

impl Runner<'_, '_, '_, '_> {
    /// The session: set-up (retract, home, tare, reference), this session's
    /// setpoints in plan order (each journalled before the next move), and the
    /// retract at the end.
    fn session(
        &mut self,
        options: &RunOptions,
        resume_no: usize,
        setpoints: &[Setpoint],
        journal: &mut Journal,
        tally: &mut Tally,
    ) -> Step<()> {
        self.prepare(options, resume_no)?;
        let mut prev: Option<Setpoint> = None;
        for sp in setpoints {
            if journal.completed().contains(&sp.index) {
                continue;
            }
            if self.stop.load(Ordering::SeqCst) {
                return Err(Halt::Interrupted);
            }
            // After a skip (resume) the previous setpoint's contact is gone.
            let fresh = prev.is_some_and(|p| p.index + 1 != sp.index);
            let retract = needs_retract(if fresh { None } else { prev.as_ref() }, sp);
            self.setpoint(sp, retract, journal, tally)?;
            prev = Some(*sp);
            if let Some(reason) = self.pending_abort.take() {
                return Err(Halt::Abort(reason));
            }
        }
        self.index = None;
        self.set_phase(Phase::Retract);
        self.retract()?;
        Ok(())
    }

    /// One setpoint: measured, its row appended to the journal (synced), its time
    /// accounted (device waits, tracking, solving, writes, the rest is overhead).
    fn setpoint(
        &mut self,
        sp: &Setpoint,
        retract: bool,
        journal: &mut Journal,
        tally: &mut Tally,
    ) -> Step<()> {
        (self.events)(&RunEvent::SetpointStarted {
            setpoint: *sp,
            done: tally.done,
            total: tally.total,
        });
        let t0 = Instant::now();
        let blocked0 = self.dev.blocked;
        self.track_s = 0.0;
        self.solve_s = 0.0;
        self.precompute_s = 0.0;
        self.io_s = 0.0;
        self.index = Some(sp.index);
        let mut row = self.measure(sp, retract)?;
        let t_io = Instant::now();
        row.completed_at = rfc3339_now();
        self.fs
            .step(super::journal::JOURNAL_FILE, || journal.append(&row))?;
        self.io_s += t_io.elapsed().as_secs_f64();
        tally.done += 1;
        tally.measured += 1;
        let elapsed_s = t0.elapsed().as_secs_f64();
        let device_s = (self.dev.blocked - blocked0).as_secs_f64();
        let overhead_s =
            (elapsed_s - device_s - self.track_s - self.solve_s - self.precompute_s - self.io_s)
                .max(0.0);
        let timings = &mut tally.timings;
        timings.setpoints += 1;
        timings.wall_s += elapsed_s;
        timings.device_s += device_s;
        timings.track_s += self.track_s;
        timings.solve_s += self.solve_s;
        timings.precompute_s += self.precompute_s;
        timings.io_s += self.io_s;
        timings.overhead_s += overhead_s;
        timings.max_overhead_s = timings.max_overhead_s.max(overhead_s);
        (self.events)(&RunEvent::SetpointMeasured {
            index: sp.index,
            done: tally.done,
            total: tally.total,
            target_n: [sp.tangential_n[0], sp.tangential_n[1], sp.normal_n],
            force_n: [row.fx_n, row.fy_n, row.fz_n],
            fsum_n: [row.fsum_x_n, row.fsum_y_n, row.fsum_z_n],
            settled: row.settled,
            elapsed_s,
            device_s,
            overhead_s,
        });
        Ok(())
    }

    /// How the session ended, and the stage out of contact: after an interruption
    /// (by `signal`) or an abort, motion is stopped first, then the stage retracts
    /// (the journal is already durable).
    fn leave(&mut self, outcome: Step<()>, signal: i32) -> (RunStatus, Option<String>) {
        match outcome {
            Ok(()) => (RunStatus::Completed, None),
            Err(Halt::Interrupted) => {
                // Stop motion first, then leave the contact; the journal is already durable.
                let _ = self.dev.stop();
                let retract = self.retract_unguarded();
                let by = super::journal::stop_cause(signal);
                let reason = match retract {
                    Ok(()) => format!("interrupted by {by}: motion stopped, stage retracted"),
                    Err(e) => format!("interrupted by {by}; retract failed: {e:?}"),
                };
                (RunStatus::Interrupted, Some(reason))
            }
            Err(Halt::Abort(reason)) => {
                let _ = self.dev.stop();
                let reason = match self.retract_unguarded() {
                    Ok(()) => reason,
                    Err(e) => format!("{reason}; retract after abort failed: {e:?}"),
                };
                (RunStatus::Aborted, Some(reason))
            }
        }
    }

    /// Records the session's end in the manifest (status, the record's digests as
    /// the session leaves it, the run's first failed write), reports it
    /// ([`RunEvent::Finished`]) and sums it up. A completed run whose closing manifest
    /// cannot be written ends `aborted`.
    fn close(
        &mut self,
        manifest: &mut Manifest,
        journal: &Journal,
        tally: Tally,
        (status, reason): (RunStatus, Option<String>),
        signal: i32,
    ) -> RunSummary {
        let dir = self.dir.clone();
        manifest.finish(
            status,
            reason.clone(),
            journal.completed().len(),
            (status == RunStatus::Interrupted && signal != 0).then_some(signal),
            rfc3339_now(),
        );
        // The record's digests as this session leaves it (the journal as a whole, every
        // evidence file written so far).
        if let Ok(rec) = super::integrity::RecordDigests::journal_now(
            &dir,
            self.fs.evidence().clone(),
            journal.completed().len(),
            rfc3339_now(),
        ) {
            manifest.record = Some(rec);
        }
        let write_failure = self.fs.first_failure().cloned();
        if manifest.write_failure.is_none() {
            // The run's first failed write (an earlier session's stays: it was first).
            manifest.write_failure = write_failure.clone();
        }
        // Through the gate too: on a full disk the manifest usually fails as well, and the
        // run's end is then only on stderr (the caller prints `manifest_error`).
        let m = &*manifest;
        let manifest_error = self
            .fs
            .write(MANIFEST_FILE, || m.write(&dir))
            .err()
            .map(|e| format!("{}: {e}", dir.join(MANIFEST_FILE).display()));
        let (status, reason) = match (&manifest_error, status) {
            (Some(e), RunStatus::Completed) => (
                RunStatus::Aborted,
                Some(format!(
                    "every setpoint was measured, but the closing manifest could not be written: {e}"
                )),
            ),
            _ => (status, reason),
        };
        (self.events)(&RunEvent::Finished {
            status,
            reason: reason.clone(),
        });
        RunSummary {
            status,
            reason,
            total: tally.total,
            done: journal.completed().len(),
            measured: tally.measured,
            timings: tally.timings,
            write_failure: write_failure.or_else(|| self.fs.first_failure().cloned()),
            manifest_error,
        }
    }
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

    /// Reports a phase change ([`RunEvent::Phase`]); nothing when the phase is the same.
    fn set_phase(&mut self, phase: Phase) {
        if self.phase != Some(phase) {
            self.phase = Some(phase);
            (self.events)(&RunEvent::Phase {
                index: self.index,
                phase,
            });
        }
    }

    /// Reports a force reading ([`RunEvent::Reading`]), at most
    /// [`READING_EVENTS_PER_S`] times a second: one `Instant` comparison otherwise.
    fn reading(&mut self, w: &Wrench) {
        let now = Instant::now();
        let interval = Duration::from_secs(1) / READING_EVENTS_PER_S;
        if self
            .last_reading
            .is_some_and(|t| now.duration_since(t) < interval)
        {
            return;
        }
        self.last_reading = Some(now);
        let (f, t) = (w.force_n, w.torque_nm);
        (self.events)(&RunEvent::Reading {
            index: self.index,
            ft: [f[0], f[1], f[2], t[0], t[1], t[2]],
            stage_mm: self.commanded,
        });
    }

    /// Homing, retract, tare and the reference frame.
    fn prepare(&mut self, options: &RunOptions, resume_no: usize) -> Step<()> {
        // Leave any contact a killed run left behind before anything else moves.
        self.set_phase(Phase::Retract);
        self.retract()?;
        if options.home {
            self.set_phase(Phase::Home);
            (self.events)(&RunEvent::Homing);
            self.dev.home().map_err(|e| dev_abort("homing", &e))?;
            self.commanded = None;
        }
        let xy = self.plan.approach_position_mm;
        self.move_lateral_at_clearance(xy)?;
        if options.tare {
            self.set_phase(Phase::Tare);
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
        self.set_phase(Phase::Reference);
        let frame = self.grab_retry()?;
        let name = if resume_no == 0 {
            "frames/reference.png".to_string()
        } else {
            format!("frames/reference_resume{resume_no}.png")
        };
        let t_io = Instant::now();
        let path = self.dir.join(&name);
        self.fs.step(&name, || frame.image.save(&path))?;
        self.io_s += t_io.elapsed().as_secs_f64();
        let reference = self.reference_layout(&name, &frame)?;
        self.tracker = Some(Tracker::new(reference, TrackConfig::default()));
        Ok(())
    }
}

/// The bench description for the manifest with the geometry the run used added as
/// `geometry` ([`BenchGeometry::to_json`]): press direction, surface z and sensor
/// origin are what turns the journal's stage coordinates into depths and positions.
pub fn with_geometry(bench: serde_json::Value, geometry: &BenchGeometry) -> serde_json::Value {
    match bench {
        serde_json::Value::Object(mut m) => {
            m.insert("geometry".into(), geometry.to_json());
            serde_json::Value::Object(m)
        }
        serde_json::Value::Null => serde_json::json!({ "geometry": geometry.to_json() }),
        other => other,
    }
}

/// The planned sweep kind's name (for messages and the CLI).
pub fn sweep_name(plan: &Plan) -> &'static str {
    match plan.sweep {
        Sweep::Magnitude { .. } => "magnitude",
        Sweep::Angle { .. } => "angle",
        Sweep::Spatial { .. } => "spatial",
        Sweep::Displacement { .. } => "displacement",
        Sweep::Setpoints(_) => "setpoints",
        Sweep::Hold { .. } => "hold",
    }
}

#[cfg(test)]
mod tests {
    use super::acquire::mean_sd;
    use super::*;
    use crate::device::Wrench;

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
            direction: None,
            position: None,
            hold_t_s: None,
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
