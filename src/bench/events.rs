//! What the runner tells its watchers, and the clock format they share: [`RunEvent`]
//! (progress, sent by `runner`), [`Phase`] (what the runner is doing, in events and in
//! `live.json`) and RFC 3339 timestamps. Its own room so that `runner` (which sends
//! events and writes `live.json` through `live::LiveWriter`) and `live` (which turns
//! events into the document) both depend on it and not on each other.

use std::time::{SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

use super::journal::RunStatus;
use super::plan::Setpoint;

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
    /// The runner entered a phase (sent when the phase changes).
    Phase {
        /// Setpoint index, when in a setpoint.
        index: Option<usize>,
        /// The phase.
        phase: Phase,
    },
    /// The latest force reading and commanded stage position, at most
    /// `runner::READING_EVENTS_PER_S` times a second (for live views).
    Reading {
        /// Setpoint index, when in a setpoint.
        index: Option<usize>,
        /// fx, fy, fz (N), mx, my, mz (N·m).
        ft: [f64; 6],
        /// Commanded stage position, machine mm (`None` before the first move).
        stage_mm: Option<[f64; 3]>,
    },
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
    /// A non-fatal problem (e.g. a reconstruction that failed: a failed row without
    /// force; an implausible force sum).
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

/// What the runner is doing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    /// The homing cycle.
    Home,
    /// Taring the force sensor.
    Tare,
    /// Taking the reference frame.
    Reference,
    /// Retract, lateral move and approach to contact.
    Approach,
    /// Closed-loop force control at the setpoint.
    ForceControl,
    /// Waiting for the force to settle (or a hold's next sample time).
    Settle,
    /// F/T samples, frames and tracking.
    Acquire,
    /// Reconstruction and the journal row.
    Solve,
    /// Leaving the contact (end of run, stop, abort).
    Retract,
    /// Nothing (before the first step, after the end).
    Idle,
}

impl Phase {
    /// The name in `live.json` and the API.
    pub fn name(self) -> &'static str {
        match self {
            Phase::Home => "home",
            Phase::Tare => "tare",
            Phase::Reference => "reference",
            Phase::Approach => "approach",
            Phase::ForceControl => "force_control",
            Phase::Settle => "settle",
            Phase::Acquire => "acquire",
            Phase::Solve => "solve",
            Phase::Retract => "retract",
            Phase::Idle => "idle",
        }
    }
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
