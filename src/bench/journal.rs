//! The run directory's crash-safe record: `journal.csv` (one row per completed
//! measurement, appended, flushed and synced to disk before the next move) and
//! `manifest.json` (what ran, on what, by which software, and how it ended).
//!
//! Resume rules: a row is only ever written once its measurement is complete, so after
//! a kill (even SIGKILL) the journal holds every completed setpoint exactly once, plus
//! at most one torn last line, which [`Journal::open_resume`] cuts off (and reports).
//! The runner then continues with the first setpoint index not in the journal.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt;
use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::device::Wrench;
use crate::vision::StatusCounts;

/// File name of the journal inside a run directory.
pub const JOURNAL_FILE: &str = "journal.csv";
/// File name of the manifest inside a run directory.
pub const MANIFEST_FILE: &str = "manifest.json";

/// An error reading or writing a run directory.
#[derive(Debug, Error)]
pub enum JournalError {
    /// File system error.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The journal's content is not a valid journal.
    #[error("{path}: line {line}: {message}")]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// 1-based line.
        line: u64,
        /// What is wrong.
        message: String,
    },
    /// The manifest is not valid JSON for the schema.
    #[error("{path}: {message}")]
    Manifest {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

/// One completed measurement. Forces in N, torques in N·m, positions in mm, times in s.
/// `Default` is an all-zero, unsettled row without frames (a base for building rows).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JournalRow {
    /// Setpoint index in the plan's expanded list.
    pub index: usize,
    /// Trial number.
    pub trial: usize,
    /// The swept quantity in its display unit.
    pub swept_value: f64,
    /// Target normal force, N.
    pub target_normal_n: f64,
    /// Target tangential force x, N.
    pub target_tx_n: f64,
    /// Target tangential force y, N.
    pub target_ty_n: f64,
    /// Measured force mean, N.
    pub fx_n: f64,
    /// Measured force mean, N.
    pub fy_n: f64,
    /// Measured force mean, N.
    pub fz_n: f64,
    /// Measured torque mean, N·m.
    pub mx_nm: f64,
    /// Measured torque mean, N·m.
    pub my_nm: f64,
    /// Measured torque mean, N·m.
    pub mz_nm: f64,
    /// Measured force SD, N.
    pub fx_sd_n: f64,
    /// Measured force SD, N.
    pub fy_sd_n: f64,
    /// Measured force SD, N.
    pub fz_sd_n: f64,
    /// Stage position at acquisition, mm.
    pub stage_x_mm: f64,
    /// Stage position at acquisition, mm.
    pub stage_y_mm: f64,
    /// Stage position at acquisition, mm.
    pub stage_z_mm: f64,
    /// Whether the settle criterion was met (false: timed out, row kept and flagged).
    pub settled: bool,
    /// Frame files, relative to the run directory, `;`-separated.
    pub frames: String,
    /// Reconstructed force sums Σfx (paper F^sum), N. Empty (NaN in memory) in a
    /// failed row (see `failure`); older versions wrote `NaN`, which reads the same.
    #[serde(with = "empty_nan")]
    pub fsum_x_n: f64,
    /// Σfy, N.
    #[serde(with = "empty_nan")]
    pub fsum_y_n: f64,
    /// Σfz, N.
    #[serde(with = "empty_nan")]
    pub fsum_z_n: f64,
    /// Time moving and force-controlling, s.
    pub t_move_s: f64,
    /// Time settling, s.
    pub t_settle_s: f64,
    /// Time reading the F/T sensor and grabbing frames, s.
    pub t_acquire_s: f64,
    /// Time tracking markers, s.
    pub t_track_s: f64,
    /// Time reconstructing forces, s.
    pub t_solve_s: f64,
    /// Completion time, RFC 3339 UTC.
    pub completed_at: String,
    /// Markers ok in every frame of the setpoint (of the sensor file's markers; the
    /// four counts add up to that number). Empty in rows written before these columns.
    #[serde(default)]
    pub markers_ok: Option<usize>,
    /// Markers lost in some frame (reference-missing markers included).
    #[serde(default)]
    pub markers_lost: Option<usize>,
    /// Markers merged in some frame (and lost in none).
    #[serde(default)]
    pub markers_merged: Option<usize>,
    /// Markers that were outliers in some frame (and neither lost nor merged).
    #[serde(default)]
    pub markers_outlier: Option<usize>,
    /// Times the frames were re-acquired because too few markers were ok.
    #[serde(default)]
    pub reacquired: Option<usize>,
    /// Tracking quality against the plan's `[quality] min_ok_fraction`: `ok`, or
    /// `flagged` when still below it after `max_reacquire` re-acquisitions, or
    /// `implausible` when the reconstructed force sum does not fit the F/T reading
    /// (see `plausibility`).
    #[serde(default)]
    pub quality: Option<RowQuality>,
    /// Standard deviation of F^sum x (N) from the displacement noise propagated through
    /// the solver (issue 12's uncertainty); empty when no noise estimate was available.
    #[serde(default)]
    pub fsum_sd_x_n: Option<f64>,
    /// As `fsum_sd_x_n`, y (N).
    #[serde(default)]
    pub fsum_sd_y_n: Option<f64>,
    /// As `fsum_sd_x_n`, z (N).
    #[serde(default)]
    pub fsum_sd_z_n: Option<f64>,
    /// Magnitude sweeps with `sweep.direction = "up-down"`: whether this row was
    /// measured on the way up or back down; empty for sweeps without a direction.
    #[serde(default)]
    pub direction: Option<Direction>,
    /// Index (0-based) of the contact position in the plan's `sweep.positions_mm`
    /// for sweeps repeated at several positions; empty otherwise.
    #[serde(default)]
    pub position: Option<usize>,
    /// `hold` sweeps: seconds since the hold force was reached when this sample was
    /// taken; empty for other sweeps.
    #[serde(default)]
    pub hold_t_s: Option<f64>,
    /// What the force sensor reported since the previous row beyond its readings
    /// ([`crate::device::ForceSensor::take_status`]): status flags (samples left out of
    /// the mean as overrange / invalid / faulted), records lost on the network, and for
    /// a Bota sensor its own timestamp and temperature. Empty when nothing was reported
    /// (and in rows written before this column).
    #[serde(default)]
    pub ft_status: Option<String>,
    /// Why the setpoint has no force (tracking or reconstruction failed, the frames
    /// were blank or saturated): the row is a *failed row*, its `fsum_*` columns are
    /// empty, and analyses skip it, count it and say so. Empty in every measured row
    /// (and in rows written before this column).
    #[serde(default)]
    pub failure: Option<String>,
    /// Run-side plausibility: the reconstructed |F^sum| against the F/T sensor's
    /// |F| (`[quality] force_ratio_min` .. `force_ratio_max`), in words, when the row
    /// failed it (`quality` is then `implausible`); empty when it passed or was not
    /// checked (and in rows written before this column).
    #[serde(default)]
    pub plausibility: Option<String>,
}

/// `fsum_*` columns: NaN is written as an empty field (a failed row has no force), and
/// an empty field or the `NaN` older versions wrote reads as NaN.
mod empty_nan {
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        if v.is_nan() {
            s.serialize_str("")
        } else {
            s.serialize_f64(*v)
        }
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        let text = String::deserialize(d)?;
        let t = text.trim();
        if t.is_empty() {
            return Ok(f64::NAN);
        }
        t.parse::<f64>()
            .map_err(|_| serde::de::Error::custom(format!("{t:?} is not a number")))
    }
}

/// Which way a magnitude sweep was going when a row was measured.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Direction {
    /// Loading: the force level rises from the previous row of the trial.
    Up,
    /// Unloading: the force level falls.
    Down,
}

/// The tracking-quality verdict of one journal row.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RowQuality {
    /// At or above the plan's `min_ok_fraction`.
    Ok,
    /// Below it after every re-acquisition: kept, but not to be trusted.
    Flagged,
    /// The reconstructed |F^sum| is outside `[quality] force_ratio_min ..
    /// force_ratio_max` times the F/T sensor's |F| (units of the sensor file, an
    /// unfitted modulus): kept, but not to be trusted.
    Implausible,
}

impl JournalRow {
    /// Markers ok / all markers of the sensor file, when the row has the counts.
    pub fn ok_fraction(&self) -> Option<f64> {
        let (ok, total) = self.marker_total()?;
        (total > 0).then(|| ok as f64 / total as f64)
    }

    /// `(ok, ok + lost + merged + outlier)`, when the row has the counts.
    pub fn marker_total(&self) -> Option<(usize, usize)> {
        let ok = self.markers_ok?;
        Some((
            ok,
            ok + self.markers_lost? + self.markers_merged? + self.markers_outlier?,
        ))
    }

    /// True when the row is flagged for tracking quality.
    pub fn flagged(&self) -> bool {
        self.quality == Some(RowQuality::Flagged)
    }

    /// True when the row failed the run-side force plausibility check.
    pub fn implausible(&self) -> bool {
        self.quality == Some(RowQuality::Implausible)
    }

    /// Why the row has no usable force, when it is a failed row: its `failure`
    /// reason, or (a row an older version wrote with NaN) the first measured column
    /// that is not a finite number.
    pub fn failed(&self) -> Option<String> {
        if let Some(f) = &self.failure {
            return Some(f.clone());
        }
        let columns = [
            ("fsum_x_n", self.fsum_x_n),
            ("fsum_y_n", self.fsum_y_n),
            ("fsum_z_n", self.fsum_z_n),
        ];
        columns.iter().find(|(_, v)| !v.is_finite()).map(|(c, v)| {
            format!("`{c}` is {v} (a failed reconstruction, journalled by an older version)")
        })
    }
}

/// The times a row's steps took, s (the journal's `t_*_s` columns); `Default`: zero,
/// for the steps a writer does not have (an import neither moves nor settles).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StepTimes {
    /// Moving and force-controlling.
    pub move_s: f64,
    /// Settling.
    pub settle_s: f64,
    /// Reading the F/T sensor and grabbing frames.
    pub acquire_s: f64,
    /// Tracking markers.
    pub track_s: f64,
    /// Reconstructing forces.
    pub solve_s: f64,
}

/// The one way a measured setpoint's row is built (the runner, `bench::synthetic_run`
/// and `import` all go through it): each step maps one group of what was measured
/// onto its columns, so a new column is added here, once.
impl JournalRow {
    /// A setpoint's row before its measurement: its key (`index`, `trial`), the swept
    /// value and the targets (normal N; tangential x, y N); settled, every measured
    /// column zero or empty until a step below sets it.
    pub fn setpoint(
        index: usize,
        trial: usize,
        swept_value: f64,
        target_normal_n: f64,
        target_tangential_n: [f64; 2],
    ) -> JournalRow {
        JournalRow {
            index,
            trial,
            swept_value,
            target_normal_n,
            target_tx_n: target_tangential_n[0],
            target_ty_n: target_tangential_n[1],
            settled: true,
            ..JournalRow::default()
        }
    }

    /// Where the row stands in its sweep: up or down, the contact position's index,
    /// the hold sample's time (s).
    pub fn in_sweep(
        self,
        direction: Option<Direction>,
        position: Option<usize>,
        hold_t_s: Option<f64>,
    ) -> JournalRow {
        JournalRow {
            direction,
            position,
            hold_t_s,
            ..self
        }
    }

    /// The F/T sensor's mean wrench (N, N·m) and the SDs of its force (N).
    pub fn with_wrench(self, mean: &Wrench, force_sd_n: [f64; 3]) -> JournalRow {
        let (f, m) = (mean.force_n, mean.torque_nm);
        JournalRow {
            fx_n: f[0],
            fy_n: f[1],
            fz_n: f[2],
            mx_nm: m[0],
            my_nm: m[1],
            mz_nm: m[2],
            fx_sd_n: force_sd_n[0],
            fy_sd_n: force_sd_n[1],
            fz_sd_n: force_sd_n[2],
            ..self
        }
    }

    /// The stage position at acquisition (x, y, z mm) and whether the settle
    /// criterion was met.
    pub fn at_stage(self, stage_mm: [f64; 3], settled: bool) -> JournalRow {
        JournalRow {
            stage_x_mm: stage_mm[0],
            stage_y_mm: stage_mm[1],
            stage_z_mm: stage_mm[2],
            settled,
            ..self
        }
    }

    /// The frames (paths relative to the run directory) and their markers: the
    /// counts of each status over the frames and the re-acquisitions it took.
    pub fn with_frames<S: AsRef<str>>(
        self,
        frames: &[S],
        counts: &StatusCounts,
        reacquired: usize,
    ) -> JournalRow {
        let frames: Vec<&str> = frames.iter().map(AsRef::as_ref).collect();
        JournalRow {
            frames: frames.join(";"),
            markers_ok: Some(counts.ok),
            markers_lost: Some(counts.lost),
            markers_merged: Some(counts.merged),
            markers_outlier: Some(counts.outlier),
            reacquired: Some(reacquired),
            ..self
        }
    }

    /// The reconstructed force sums (N; NaN in a failed row) and their SDs (N) when
    /// the noise was estimated.
    pub fn with_force_sum(self, fsum_n: [f64; 3], fsum_sd_n: Option<[f64; 3]>) -> JournalRow {
        JournalRow {
            fsum_x_n: fsum_n[0],
            fsum_y_n: fsum_n[1],
            fsum_z_n: fsum_n[2],
            fsum_sd_x_n: fsum_sd_n.map(|v| v[0]),
            fsum_sd_y_n: fsum_sd_n.map(|v| v[1]),
            fsum_sd_z_n: fsum_sd_n.map(|v| v[2]),
            ..self
        }
    }

    /// What the row says of itself: its quality, why it failed (a failed row) and the
    /// plausibility finding that made it `implausible`.
    pub fn with_verdict(
        self,
        quality: RowQuality,
        failure: Option<String>,
        plausibility: Option<String>,
    ) -> JournalRow {
        JournalRow {
            quality: Some(quality),
            failure,
            plausibility,
            ..self
        }
    }

    /// The times the row's steps took.
    pub fn timed(self, t: StepTimes) -> JournalRow {
        JournalRow {
            t_move_s: t.move_s,
            t_settle_s: t.settle_s,
            t_acquire_s: t.acquire_s,
            t_track_s: t.track_s,
            t_solve_s: t.solve_s,
            ..self
        }
    }
}

/// How a run ended (or that it is still going).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RunStatus {
    /// In progress (or killed without a chance to say so).
    Running,
    /// Stopped by the user (Ctrl-C): motion stopped, retracted, journal flushed.
    Interrupted,
    /// Stopped by an error or a safety trip; the reason is in `end_reason`.
    Aborted,
    /// Every setpoint measured.
    Completed,
}

/// The digests of a run's record (`manifest.json` `record`); taken and checked by
/// [`super::integrity`] (`RecordDigests::journal_now`, `verify`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RecordDigests {
    /// SHA-256 (lowercase hex) of the journal's first `journal_bytes` bytes.
    pub journal_sha256: String,
    /// Length of the journal when its digest was taken, bytes.
    pub journal_bytes: u64,
    /// Rows in the journal then.
    pub journal_rows: usize,
    /// When the digest was taken, RFC 3339 UTC.
    pub at: String,
    /// Evidence file (relative to the run directory) -> SHA-256 as the runner wrote it.
    #[serde(default)]
    pub evidence: BTreeMap<String, String>,
}

/// `manifest.json`: provenance of a run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Plan file as given.
    pub plan_path: String,
    /// Plan name.
    pub plan_name: String,
    /// Full plan text, so the run is self-describing.
    pub plan_toml: String,
    /// Sensor file as resolved.
    pub sensor_path: String,
    /// Full sensor text.
    pub sensor_toml: String,
    /// Bench description (devices, ports, protocols or the simulated scene).
    pub bench: serde_json::Value,
    /// Identities the devices reported (firmware, serial numbers).
    pub devices: serde_json::Value,
    /// Elastomer build id.
    pub build_id: Option<String>,
    /// `tactbench` version.
    pub software_version: String,
    /// Start time, RFC 3339 UTC.
    pub started_at: String,
    /// Times the run was resumed, RFC 3339 UTC.
    #[serde(default)]
    pub resumed_at: Vec<String>,
    /// Setpoints the run is to have measured at the end of its latest session: the
    /// plan's, or fewer when that session ran with `--limit`.
    pub setpoints: usize,
    /// Setpoints in the plan, before any `--limit` (`None` in manifests written before
    /// it was recorded; [`Manifest::planned`] falls back to `setpoints`).
    #[serde(default)]
    pub planned_setpoints: Option<usize>,
    /// The `--limit N` of the latest session (`run` or `run --resume`), if any.
    #[serde(default)]
    pub limit: Option<usize>,
    /// One entry per session (`run`, then each `run --resume`), in order; empty in
    /// manifests written before sessions were recorded.
    #[serde(default)]
    pub sessions: Vec<Session>,
    /// Setpoints in the journal when the manifest was last written (at the start and
    /// the end of each session; after a kill, the journal is the authority).
    #[serde(default)]
    pub measured_setpoints: usize,
    /// How it ended.
    pub status: RunStatus,
    /// Why it ended that way (abort reason, safety trip), if not completed.
    #[serde(default)]
    pub end_reason: Option<String>,
    /// The signal that interrupted the run (`SIGINT`, `SIGTERM`, `SIGHUP`), if one did.
    #[serde(default)]
    pub stop_signal: Option<String>,
    /// Why fewer setpoints than planned were measured (`--limit`, interrupted by a
    /// signal, aborted with its reason); `None` when the whole plan was measured or the
    /// run is still going.
    #[serde(default)]
    pub incomplete_reason: Option<String>,
    /// End time, RFC 3339 UTC.
    #[serde(default)]
    pub ended_at: Option<String>,
    /// The git commit the `tactbench` binary that ran (or last resumed) the run was
    /// built from (`unknown` when built outside git).
    #[serde(default)]
    pub software_commit: Option<String>,
    /// Camera calibration file as given (`run --camera`), when the run tracks with one.
    #[serde(default)]
    pub camera_path: Option<String>,
    /// Full text of that camera calibration (camera.toml, `tactbench-camera/1`), so a
    /// resume tracks with exactly the mapping the run started with; `None`: the sensor
    /// file's linear `[camera]` mapping.
    #[serde(default)]
    pub camera_toml: Option<String>,
    /// Whether the run was measured on the built-in simulated bench (a `[sim]` bench
    /// file or `run --sim`); true when any session of it was. `None` in manifests
    /// written before it was recorded ("not recorded": a gate cannot tell).
    #[serde(default)]
    pub simulated: Option<bool>,
    /// The first write into the run directory that failed during a session (the run
    /// ended `aborted` because of it); `None` when every write succeeded.
    #[serde(default)]
    pub write_failure: Option<WriteFailure>,
    /// Where each device's data came from (`real`, `simulated`, `replayed`) and why
    /// ([`crate::bench::provenance`]); a run is a real-bench run only when every
    /// device is real. Empty in manifests written before it was recorded.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub device_provenance: Vec<DeviceProvenance>,
    /// SHA-256 digests of the journal and the evidence files as the runner wrote them
    /// ([`crate::bench::integrity`]); `None` in manifests written before they were.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub record: Option<RecordDigests>,
}

/// One device's provenance (`manifest.json` `device_provenance`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DeviceProvenance {
    /// `stage`, `force_sensor` or `camera`.
    pub device: String,
    /// What the device reported (or how it was opened), as recorded in `devices`.
    pub identity: String,
    /// `real`, `simulated` or `replayed`.
    pub provenance: Provenance,
    /// Why it is not real (`None` for a real device).
    #[serde(default)]
    pub why: Option<String>,
}

/// Where a device's data came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Provenance {
    /// A physical device.
    Real,
    /// Recorded data played back (a `dir:` camera, a replayed transcript).
    Replayed,
    /// A simulator (the built-in bench, a simulator's firmware, a loopback simulator).
    Simulated,
}

impl Provenance {
    /// `real`, `replayed`, `simulated`.
    pub fn word(self) -> &'static str {
        match self {
            Provenance::Real => "real",
            Provenance::Replayed => "replayed",
            Provenance::Simulated => "simulated",
        }
    }
}

/// The first failed write of a run (`manifest.json` `write_failure`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WriteFailure {
    /// The file, relative to the run directory.
    pub path: String,
    /// The operating system's error text (e.g. `No space left on device (os error 28)`).
    pub error: String,
    /// When it failed, RFC 3339 UTC.
    pub at: String,
}

impl fmt::Display for WriteFailure {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "writing {} failed at {}: {}",
            self.path, self.at, self.error
        )
    }
}

/// One session of a run: a `run` or a `run --resume` invocation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Session {
    /// Start time, RFC 3339 UTC.
    pub started_at: String,
    /// Its `--limit N`: at most N setpoints measured by this session.
    #[serde(default)]
    pub limit: Option<usize>,
    /// Setpoints in the journal when the session started.
    pub setpoints_before: usize,
    /// Setpoints in the journal when it ended (equal to `setpoints_before` while it
    /// runs, or when it was killed before it could say).
    pub setpoints_after: usize,
}

/// The git commit this binary was built from (`git rev-parse HEAD` at build time,
/// `unknown` when built outside a git checkout).
pub const GIT_COMMIT: &str = env!("TACTBENCH_GIT_COMMIT");

impl Manifest {
    /// Setpoints in the plan (before any `--limit`).
    pub fn planned(&self) -> usize {
        self.planned_setpoints.unwrap_or(self.setpoints)
    }

    /// Records how a session ended: status, reason, end time, the journal's row count,
    /// the interrupting signal, and why the run measured less than its plan
    /// (`incomplete_reason`, `None` when it measured every planned setpoint).
    pub fn finish(
        &mut self,
        status: RunStatus,
        end_reason: Option<String>,
        measured: usize,
        signal: Option<i32>,
        ended_at: String,
    ) {
        let planned = self.planned();
        self.status = status;
        self.measured_setpoints = measured;
        if let Some(last) = self.sessions.last_mut() {
            last.setpoints_after = measured;
        }
        self.stop_signal = signal.map(signal_name);
        self.ended_at = Some(ended_at);
        self.incomplete_reason = if measured >= planned {
            None
        } else {
            let of = format!("{measured} of the plan's {planned} setpoints measured");
            Some(match status {
                RunStatus::Completed | RunStatus::Running => match self.limit {
                    Some(n) => format!("limited by --limit {n}: {of}"),
                    None => of,
                },
                RunStatus::Interrupted => {
                    format!("interrupted by {}: {of}", stop_cause(signal.unwrap_or(0)))
                }
                RunStatus::Aborted => format!(
                    "aborted: {of}: {}",
                    end_reason.as_deref().unwrap_or("no reason recorded")
                ),
            })
        };
        self.end_reason = end_reason;
    }

    /// Makes `sessions` agree with the journal after a session that could not record
    /// its end (`kill -9`, power loss): a session's `setpoints_after` is at least the
    /// next session's `setpoints_before`, and the last one's at least `journal_rows`
    /// when the manifest still says `running`. Returns whether anything changed.
    pub fn reconcile_sessions(&mut self, journal_rows: usize) -> bool {
        let mut changed = false;
        let n = self.sessions.len();
        for i in 0..n {
            let next = if i + 1 < n {
                Some(self.sessions[i + 1].setpoints_before)
            } else if self.status == RunStatus::Running {
                Some(journal_rows)
            } else {
                None
            };
            if let Some(next) = next {
                let s = &mut self.sessions[i];
                if next > s.setpoints_after {
                    s.setpoints_after = next;
                    changed = true;
                }
            }
        }
        if self.status == RunStatus::Running && journal_rows > self.measured_setpoints {
            self.measured_setpoints = journal_rows;
            changed = true;
        }
        changed
    }

    /// Writes `manifest.json` atomically (temp file + rename) and syncs it.
    pub fn write(&self, dir: &Path) -> Result<(), JournalError> {
        let path = dir.join(MANIFEST_FILE);
        let tmp = dir.join(".manifest.json.tmp");
        let io = |source| JournalError::Io {
            path: path.clone(),
            source,
        };
        let text = serde_json::to_string_pretty(self).map_err(|e| JournalError::Manifest {
            path: path.clone(),
            message: e.to_string(),
        })?;
        let mut f = File::create(&tmp).map_err(io)?;
        f.write_all(text.as_bytes()).map_err(io)?;
        f.write_all(b"\n").map_err(io)?;
        f.sync_all().map_err(io)?;
        std::fs::rename(&tmp, &path).map_err(io)?;
        Ok(())
    }

    /// Reads `manifest.json` from a run directory.
    pub fn read(dir: &Path) -> Result<Manifest, JournalError> {
        let path = dir.join(MANIFEST_FILE);
        let text = std::fs::read_to_string(&path).map_err(|source| JournalError::Io {
            path: path.clone(),
            source,
        })?;
        serde_json::from_str(&text).map_err(|e| JournalError::Manifest {
            path,
            message: e.to_string(),
        })
    }
}

/// A signal's name (`SIGINT`, `SIGTERM`, `SIGHUP`, `SIGQUIT`, else `signal N`).
pub fn signal_name(signal: i32) -> String {
    match signal {
        1 => "SIGHUP".into(),
        2 => "SIGINT".into(),
        3 => "SIGQUIT".into(),
        15 => "SIGTERM".into(),
        n => format!("signal {n}"),
    }
}

/// What stopped a run, for messages: `SIGINT (Ctrl-C)`, `SIGTERM`, ... (0: a stop
/// request that was not a signal).
pub fn stop_cause(signal: i32) -> String {
    match signal {
        0 => "a stop request".into(),
        2 => "SIGINT (Ctrl-C)".into(),
        15 => "SIGTERM (a termination request, e.g. `kill` or a service manager)".into(),
        n => signal_name(n),
    }
}

/// An open journal: appends rows durably.
#[derive(Debug)]
pub struct Journal {
    path: PathBuf,
    file: File,
    done: BTreeSet<usize>,
}

/// What [`Journal::open_resume`] found.
#[derive(Debug)]
pub struct Resumed {
    /// The journal, positioned for appending.
    pub journal: Journal,
    /// Rows already completed, in file order.
    pub rows: Vec<JournalRow>,
    /// Bytes of a torn last line that were cut off (0 when the file was clean).
    pub truncated_bytes: u64,
}

impl Journal {
    /// Creates a new journal (fails if one exists: never overwrite a run).
    pub fn create(dir: &Path) -> Result<Journal, JournalError> {
        let path = dir.join(JOURNAL_FILE);
        let io = |source| JournalError::Io {
            path: path.clone(),
            source,
        };
        let mut file = OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&path)
            .map_err(io)?;
        let mut w = csv::Writer::from_writer(Vec::new());
        w.write_record(header())
            .map_err(|e| corrupt(&path, 1, e.to_string()))?;
        let bytes = w
            .into_inner()
            .map_err(|e| corrupt(&path, 1, e.to_string()))?;
        file.write_all(&bytes).map_err(io)?;
        file.sync_all().map_err(io)?;
        sync_dir(dir);
        Ok(Journal {
            path,
            file,
            done: BTreeSet::new(),
        })
    }

    /// Opens an existing journal to continue a run: reads the completed rows, cuts off
    /// a torn last line, rejects duplicates and foreign headers.
    pub fn open_resume(dir: &Path) -> Result<Resumed, JournalError> {
        let path = dir.join(JOURNAL_FILE);
        let io = |source| JournalError::Io {
            path: path.clone(),
            source,
        };
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .open(&path)
            .map_err(io)?;
        let mut bytes = Vec::new();
        file.read_to_end(&mut bytes).map_err(io)?;
        // Everything after the last newline is a torn write: drop it.
        let keep = complete_len(&bytes);
        let truncated_bytes = (bytes.len() - keep) as u64;
        if truncated_bytes > 0 {
            file.set_len(keep as u64).map_err(io)?;
            file.sync_all().map_err(io)?;
        }
        let mut done = BTreeSet::new();
        let (rows, legacy) = parse_complete(&path, &bytes[..keep], |before, row| {
            if done.insert(row.index) {
                Ok(())
            } else {
                Err(corrupt(
                    &path,
                    before as u64 + 2,
                    format!("setpoint {} appears twice", row.index),
                ))
            }
        })?;
        if let Some(width) = legacy {
            // A journal from before some of today's columns: rewrite it with the
            // current header and those columns empty in the old rows (atomically:
            // temp file, sync, rename), so the rows appended now line up.
            drop(file);
            file = upgrade_legacy(dir, &bytes[..keep], width)?;
        }
        file.seek(SeekFrom::End(0)).map_err(io)?;
        Ok(Resumed {
            journal: Journal { path, file, done },
            rows,
            truncated_bytes,
        })
    }

    /// Appends one completed row and makes it durable (write, flush, fsync) before
    /// returning, so the next move only starts once the row is on disk.
    pub fn append(&mut self, row: &JournalRow) -> Result<(), JournalError> {
        if self.done.contains(&row.index) {
            return Err(corrupt(
                &self.path,
                0,
                format!("setpoint {} is already in the journal", row.index),
            ));
        }
        let mut w = csv::WriterBuilder::new()
            .has_headers(false)
            .from_writer(Vec::new());
        w.serialize(row)
            .map_err(|e| corrupt(&self.path, 0, e.to_string()))?;
        let bytes = w
            .into_inner()
            .map_err(|e| corrupt(&self.path, 0, e.to_string()))?;
        // Numbers as every CSV writes them (no `7.8500000000000005`, no `-2.2e-16`).
        let bytes = crate::formats::tidy_csv_records(&bytes)
            .map_err(|e| corrupt(&self.path, 0, e.to_string()))?;
        let io = |source| JournalError::Io {
            path: self.path.clone(),
            source,
        };
        // One write call for the whole line keeps a torn line to the very end.
        self.file.write_all(&bytes).map_err(io)?;
        self.file.flush().map_err(io)?;
        self.file.sync_data().map_err(io)?;
        self.done.insert(row.index);
        Ok(())
    }

    /// Setpoint indices already completed.
    pub fn completed(&self) -> &BTreeSet<usize> {
        &self.done
    }

    /// The journal file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Columns of journals written before the tracking-quality columns (`markers_ok` on).
pub const LEGACY_COLUMNS: usize = 29;

/// The widths of every earlier journal header, oldest first. The header is append-only
/// (new columns go at its end, and their row fields are `Option`s read as absent), so
/// a journal with one of these widths whose header is the current header's prefix is
/// resumed by upgrading it. A change that appends columns adds the old width here.
pub const PRIOR_WIDTHS: &[usize] = &[LEGACY_COLUMNS, 35, 41, 42];

/// Rewrites a legacy journal (`text`: header and complete lines, `width` columns) with
/// the current header, appending empty new columns to every old row; returns it open
/// for append.
fn upgrade_legacy(dir: &Path, text: &[u8], width: usize) -> Result<File, JournalError> {
    let path = dir.join(JOURNAL_FILE);
    let tmp = dir.join(".journal.csv.tmp");
    let io = |source| JournalError::Io {
        path: path.clone(),
        source,
    };
    let empty = ",".repeat(header().len() - width);
    let mut out = Vec::with_capacity(text.len() + 64);
    for (i, line) in text.split_inclusive(|&b| b == b'\n').enumerate() {
        let body = line.strip_suffix(b"\n").unwrap_or(line);
        let body = body.strip_suffix(b"\r").unwrap_or(body);
        if i == 0 {
            out.extend_from_slice(header().join(",").as_bytes());
        } else {
            out.extend_from_slice(body);
            out.extend_from_slice(empty.as_bytes());
        }
        out.push(b'\n');
    }
    let mut f = File::create(&tmp).map_err(io)?;
    f.write_all(&out).map_err(io)?;
    f.sync_all().map_err(io)?;
    drop(f);
    std::fs::rename(&tmp, &path).map_err(io)?;
    sync_dir(dir);
    OpenOptions::new()
        .read(true)
        .write(true)
        .open(&path)
        .map_err(io)
}

/// Reads every row of a run's journal (for analysis and reports); a torn last line
/// is an error here (see [`read_journal`] to skip it).
pub fn read_rows(dir: &Path) -> Result<Vec<JournalRow>, JournalError> {
    let j = read_journal(dir)?;
    if let Some(t) = j.torn {
        return Err(corrupt(
            &dir.join(JOURNAL_FILE),
            t.line,
            format!(
                "torn last line ({} bytes without a line end: the writer died mid-write)",
                t.bytes
            ),
        ));
    }
    Ok(j.rows)
}

/// A journal's last line cut mid-write (what a crash or kill during the append
/// leaves): everything after the last line end.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TornLine {
    /// 1-based line number of the torn line.
    pub line: u64,
    /// Its length in bytes.
    pub bytes: u64,
}

/// A journal as read by [`read_journal`].
#[derive(Debug, Clone, PartialEq)]
pub struct JournalContents {
    /// The complete rows, in file order.
    pub rows: Vec<JournalRow>,
    /// A torn last line that was skipped (never a row), if any.
    pub torn: Option<TornLine>,
}

/// Reads a run's journal without changing it: the complete rows, and a torn last
/// line (no line end) reported instead of parsed. Any other malformed line is an
/// error naming its line. Unlike [`Journal::open_resume`] the file is never
/// truncated, so readers (`report`) leave the run directory as they found it.
pub fn read_journal(dir: &Path) -> Result<JournalContents, JournalError> {
    let path = dir.join(JOURNAL_FILE);
    let bytes = std::fs::read(&path).map_err(|source| JournalError::Io {
        path: path.clone(),
        source,
    })?;
    let keep = complete_len(&bytes);
    let torn = (keep < bytes.len()).then(|| TornLine {
        line: bytes[..keep].iter().filter(|&&b| b == b'\n').count() as u64 + 1,
        bytes: (bytes.len() - keep) as u64,
    });
    let mut rows = Vec::new();
    if keep > 0 {
        rows = parse_complete(&path, &bytes[..keep], |_, _| Ok(()))?.0;
    }
    Ok(JournalContents { rows, torn })
}

/// The length of a journal's text up to and including its last line end: what follows
/// is a torn write (a crash or kill mid-append), never a row.
fn complete_len(bytes: &[u8]) -> usize {
    bytes
        .iter()
        .rposition(|&b| b == b'\n')
        .map(|i| i + 1)
        .unwrap_or(0)
}

/// Parses a journal's complete lines (`text`, the file `path`): the header checked
/// ([`check_header`]: `Some(width)` for an earlier, narrower journal), then the rows
/// in file order, each handed to `accept` with the number of rows before it (which may
/// refuse it) before the next is parsed. A malformed row is an error naming its line.
fn parse_complete(
    path: &Path,
    text: &[u8],
    mut accept: impl FnMut(usize, &JournalRow) -> Result<(), JournalError>,
) -> Result<(Vec<JournalRow>, Option<usize>), JournalError> {
    let mut rdr = csv::Reader::from_reader(text);
    let headers = rdr
        .headers()
        .map_err(|e| corrupt(path, 1, e.to_string()))?
        .clone();
    let legacy = check_header(path, &headers.iter().collect::<Vec<_>>())?;
    let mut rows = Vec::new();
    for rec in rdr.deserialize::<JournalRow>() {
        let row = rec.map_err(|e| {
            let line = e.position().map(|p| p.line()).unwrap_or(0);
            corrupt(path, line, e.to_string())
        })?;
        accept(rows.len(), &row)?;
        rows.push(row);
    }
    Ok((rows, legacy))
}

/// Checks a journal's header against the one this version writes: the current header,
/// or (the header only ever grows at its end) one of [`PRIOR_WIDTHS`]' prefixes of it,
/// whose width is returned. Anything else (a reordered, renamed or foreign header) is
/// refused with the first column that differs: the columns would be read by name, so a
/// header reordered after the run would silently put values under other columns.
fn check_header(path: &Path, found: &[&str]) -> Result<Option<usize>, JournalError> {
    let current = header();
    if found == current.as_slice() {
        return Ok(None);
    }
    if let Some(w) = PRIOR_WIDTHS
        .iter()
        .copied()
        .find(|&w| w < current.len() && found == &current[..w])
    {
        return Ok(Some(w));
    }
    let differs = found
        .iter()
        .zip(&current)
        .position(|(a, b)| a != b)
        .map(|i| {
            format!(
                "column {} is `{}` where a tactbench journal has `{}`",
                i + 1,
                found[i],
                current[i]
            )
        })
        .unwrap_or_else(|| {
            format!(
                "{} columns, where a tactbench journal has {} (or one of the earlier widths {:?})",
                found.len(),
                current.len(),
                PRIOR_WIDTHS
            )
        });
    Err(corrupt(
        path,
        1,
        format!(
            "not the journal header this version writes ({differs}): reordered or edited after the run, or not a tactbench journal"
        ),
    ))
}

/// The journal's column names, in order (the serde field order of [`JournalRow`]).
pub fn header() -> Vec<&'static str> {
    vec![
        "index",
        "trial",
        "swept_value",
        "target_normal_n",
        "target_tx_n",
        "target_ty_n",
        "fx_n",
        "fy_n",
        "fz_n",
        "mx_nm",
        "my_nm",
        "mz_nm",
        "fx_sd_n",
        "fy_sd_n",
        "fz_sd_n",
        "stage_x_mm",
        "stage_y_mm",
        "stage_z_mm",
        "settled",
        "frames",
        "fsum_x_n",
        "fsum_y_n",
        "fsum_z_n",
        "t_move_s",
        "t_settle_s",
        "t_acquire_s",
        "t_track_s",
        "t_solve_s",
        "completed_at",
        "markers_ok",
        "markers_lost",
        "markers_merged",
        "markers_outlier",
        "reacquired",
        "quality",
        "fsum_sd_x_n",
        "fsum_sd_y_n",
        "fsum_sd_z_n",
        "direction",
        "position",
        "hold_t_s",
        "ft_status",
        "failure",
        "plausibility",
    ]
}

fn corrupt(path: &Path, line: u64, message: String) -> JournalError {
    JournalError::Corrupt {
        path: path.to_path_buf(),
        line,
        message,
    }
}

/// Syncs a directory so a newly created file's entry survives a crash (best effort:
/// not every file system supports it).
fn sync_dir(dir: &Path) {
    if let Ok(d) = File::open(dir) {
        let _ = d.sync_all();
    }
}

/// A minimal manifest for unit tests elsewhere in the crate.
#[cfg(test)]
pub(crate) mod tests_support {
    use super::*;

    pub(crate) fn manifest() -> Manifest {
        Manifest {
            plan_path: "p.toml".into(),
            plan_name: "p".into(),
            plan_toml: String::new(),
            sensor_path: "s.toml".into(),
            sensor_toml: String::new(),
            bench: serde_json::Value::Null,
            devices: serde_json::Value::Null,
            build_id: None,
            software_version: "0".into(),
            started_at: "t0".into(),
            resumed_at: vec![],
            sessions: vec![],
            setpoints: 1,
            planned_setpoints: Some(1),
            limit: None,
            measured_setpoints: 0,
            status: RunStatus::Running,
            end_reason: None,
            stop_signal: None,
            incomplete_reason: None,
            ended_at: None,
            software_commit: None,
            camera_path: None,
            camera_toml: None,
            simulated: None,
            write_failure: None,
            device_provenance: Vec::new(),
            record: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(index: usize) -> JournalRow {
        JournalRow {
            index,
            swept_value: index as f64 * 50.0,
            target_normal_n: 0.49,
            fx_n: 0.001,
            fy_n: -0.002,
            fz_n: 0.488,
            fx_sd_n: 1e-3,
            fy_sd_n: 1e-3,
            fz_sd_n: 2e-3,
            stage_x_mm: 9.0,
            stage_y_mm: 6.75,
            stage_z_mm: 1.25,
            settled: true,
            frames: format!("frames/{index:05}_0.png"),
            fsum_z_n: 0.47,
            t_move_s: 0.5,
            t_settle_s: 0.2,
            t_acquire_s: 0.01,
            t_track_s: 1e-4,
            t_solve_s: 1e-5,
            completed_at: "2026-11-22T00:00:00Z".into(),
            ..JournalRow::default()
        }
    }

    /// The steps a measured row is built with put each value in its own column: every
    /// input distinct, the journal line they make spelled out column by column.
    #[test]
    fn measured_row_steps_fill_each_column_from_its_own_input() {
        let counts = StatusCounts {
            ok: 41,
            lost: 42,
            merged: 43,
            outlier: 44,
        };
        let mean = Wrench {
            force_n: [0.1, 0.2, 0.3],
            torque_nm: [0.4, 0.5, 0.6],
        };
        let row = JournalRow {
            completed_at: "2026-11-28T00:00:00Z".into(),
            ft_status: Some("flags 0x1".into()),
            ..JournalRow::setpoint(7, 2, 150.0, 1.5, [0.25, -0.75])
                .in_sweep(Some(Direction::Down), Some(3), Some(12.5))
                .with_wrench(&mean, [0.01, 0.02, 0.03])
                .at_stage([-91.0, -93.25, -30.5], false)
                .with_frames(&["frames/00007_0.png", "frames/00007_1.png"], &counts, 5)
                .with_force_sum([1.1, 1.2, 1.3], Some([0.11, 0.12, 0.13]))
                .with_verdict(
                    RowQuality::Implausible,
                    Some("why not".into()),
                    Some("ratio 9".into()),
                )
                .timed(StepTimes {
                    move_s: 0.61,
                    settle_s: 0.62,
                    acquire_s: 0.63,
                    track_s: 0.64,
                    solve_s: 0.65,
                })
        };
        let dir = tempfile::tempdir().unwrap();
        let mut j = Journal::create(dir.path()).unwrap();
        j.append(&row).unwrap();
        let text = std::fs::read_to_string(dir.path().join(JOURNAL_FILE)).unwrap();
        let line = text.lines().nth(1).unwrap();
        let expected = [
            "7",
            "2",
            "150",
            "1.5",
            "0.25",
            "-0.75", // index .. target_ty_n
            "0.1",
            "0.2",
            "0.3",
            "0.4",
            "0.5",
            "0.6", // fx_n .. mz_nm
            "0.01",
            "0.02",
            "0.03", // fx_sd_n .. fz_sd_n
            "-91",
            "-93.25",
            "-30.5",
            "false", // stage, settled
            "frames/00007_0.png;frames/00007_1.png",
            "1.1",
            "1.2",
            "1.3", // fsum
            "0.61",
            "0.62",
            "0.63",
            "0.64",
            "0.65", // t_*_s
            "2026-11-28T00:00:00Z",
            "41",
            "42",
            "43",
            "44",
            "5",
            "implausible", // markers, reacquired, quality
            "0.11",
            "0.12",
            "0.13", // fsum_sd
            "down",
            "3",
            "12.5",
            "flags 0x1",
            "why not",
            "ratio 9",
        ];
        assert_eq!(expected.len(), header().len());
        assert_eq!(line, expected.join(","));
        // An import's row: no sweep placement, no SDs, one frame; settled, and the
        // steps it does not take leave their columns zero or empty.
        let plain = JournalRow::setpoint(0, 0, 0.0, 0.0, [0.0; 2]).with_frames(
            &["frames/00000_0.png"],
            &counts,
            0,
        );
        assert!(plain.settled && plain.direction.is_none() && plain.fsum_sd_x_n.is_none());
        assert_eq!(plain.frames, "frames/00000_0.png");
    }

    #[test]
    fn header_matches_row_fields() {
        let mut w = csv::Writer::from_writer(Vec::new());
        w.serialize(row(0)).unwrap();
        let text = String::from_utf8(w.into_inner().unwrap()).unwrap();
        assert_eq!(text.lines().next().unwrap(), header().join(","));
    }

    #[test]
    fn rows_survive_reopen_and_a_torn_last_line_is_cut() {
        let dir = tempfile::tempdir().unwrap();
        let mut j = Journal::create(dir.path()).unwrap();
        for i in 0..3 {
            j.append(&row(i)).unwrap();
        }
        drop(j);
        // Simulate a kill in the middle of writing row 3.
        let mut f = OpenOptions::new()
            .append(true)
            .open(dir.path().join(JOURNAL_FILE))
            .unwrap();
        f.write_all(b"3,0,150,0.49,0,0,0.0").unwrap();
        drop(f);
        let r = Journal::open_resume(dir.path()).unwrap();
        assert_eq!(r.rows.len(), 3);
        assert_eq!(r.truncated_bytes, 20);
        assert_eq!(r.rows[2], row(2));
        let mut j = r.journal;
        assert!(
            j.append(&row(1)).is_err(),
            "a completed setpoint cannot be journalled twice"
        );
        j.append(&row(3)).unwrap();
        drop(j);
        let rows = read_rows(dir.path()).unwrap();
        assert_eq!(
            rows.iter().map(|r| r.index).collect::<Vec<_>>(),
            vec![0, 1, 2, 3]
        );
    }

    #[test]
    fn a_journal_without_the_quality_columns_resumes_and_is_upgraded() {
        let dir = tempfile::tempdir().unwrap();
        // A journal as written before the marker-count columns: the first 29 columns.
        let mut w = csv::Writer::from_writer(Vec::new());
        w.write_record(&header()[..LEGACY_COLUMNS]).unwrap();
        for i in 0..2 {
            let mut full = csv::WriterBuilder::new()
                .has_headers(false)
                .from_writer(Vec::new());
            full.serialize(row(i)).unwrap();
            let text = String::from_utf8(full.into_inner().unwrap()).unwrap();
            let fields: Vec<&str> = text.trim_end().split(',').collect();
            w.write_record(&fields[..LEGACY_COLUMNS]).unwrap();
        }
        let old = String::from_utf8(w.into_inner().unwrap()).unwrap();
        std::fs::write(dir.path().join(JOURNAL_FILE), &old).unwrap();
        // Reports read it as it is: the new columns are absent.
        let rows = read_rows(dir.path()).unwrap();
        assert_eq!(rows.len(), 2);
        assert_eq!((rows[1].markers_ok, rows[1].quality), (None, None));
        assert_eq!(rows[1].ok_fraction(), None);
        // Resume: rows kept, the file rewritten with the current header, new rows line up.
        let r = Journal::open_resume(dir.path()).unwrap();
        assert_eq!(r.rows, vec![row(0), row(1)]);
        let mut j = r.journal;
        let mut new = row(2);
        new.markers_ok = Some(250);
        new.markers_lost = Some(6);
        new.markers_merged = Some(3);
        new.markers_outlier = Some(1);
        new.reacquired = Some(1);
        new.quality = Some(RowQuality::Ok);
        j.append(&new).unwrap();
        drop(j);
        let text = std::fs::read_to_string(dir.path().join(JOURNAL_FILE)).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], header().join(","));
        let added = header().len() - LEGACY_COLUMNS;
        assert!(lines[1].ends_with(&",".repeat(added)), "{}", lines[1]);
        assert!(
            lines[3].ends_with(",250,6,3,1,1,ok,,,,,,,,,"),
            "{}",
            lines[3]
        );
        assert_eq!(
            old.lines().nth(1).unwrap(),
            &lines[1][..lines[1].len() - added],
            "old rows keep their bytes"
        );
        let rows = read_rows(dir.path()).unwrap();
        assert_eq!(rows, vec![row(0), row(1), new.clone()]);
        assert_eq!(rows[2].ok_fraction(), Some(250.0 / 260.0));
        assert!(!dir.path().join(".journal.csv.tmp").exists());
        // A second resume sees the current header: nothing to upgrade.
        let r = Journal::open_resume(dir.path()).unwrap();
        assert_eq!(r.rows.len(), 3);
    }

    #[test]
    fn a_journal_without_the_uncertainty_and_direction_columns_resumes_and_is_upgraded() {
        // A journal of the 35-column header (quality columns, no F^sum SD, direction,
        // position or hold time): every earlier width in PRIOR_WIDTHS resumes.
        for &width in PRIOR_WIDTHS {
            let dir = tempfile::tempdir().unwrap();
            let mut w = csv::Writer::from_writer(Vec::new());
            w.write_record(&header()[..width]).unwrap();
            let mut full = csv::WriterBuilder::new()
                .has_headers(false)
                .from_writer(Vec::new());
            full.serialize(row(0)).unwrap();
            let text = String::from_utf8(full.into_inner().unwrap()).unwrap();
            let fields: Vec<&str> = text.trim_end().split(',').collect();
            w.write_record(&fields[..width]).unwrap();
            let old = String::from_utf8(w.into_inner().unwrap()).unwrap();
            std::fs::write(dir.path().join(JOURNAL_FILE), &old).unwrap();
            let r = Journal::open_resume(dir.path()).unwrap();
            assert_eq!(r.rows, vec![row(0)], "width {width}");
            let mut j = r.journal;
            let mut new = row(1);
            new.fsum_sd_z_n = Some(0.25);
            new.direction = Some(Direction::Down);
            new.position = Some(2);
            new.hold_t_s = Some(1.5);
            j.append(&new).unwrap();
            drop(j);
            let text = std::fs::read_to_string(dir.path().join(JOURNAL_FILE)).unwrap();
            let lines: Vec<&str> = text.lines().collect();
            assert_eq!(lines[0], header().join(","), "width {width}");
            assert!(lines[2].ends_with(",0.25,down,2,1.5,,,"), "{}", lines[2]);
            assert_eq!(read_rows(dir.path()).unwrap(), vec![row(0), new]);
        }
    }

    #[test]
    fn read_journal_skips_a_torn_last_line_without_changing_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let mut j = Journal::create(dir.path()).unwrap();
        j.append(&row(0)).unwrap();
        drop(j);
        let path = dir.path().join(JOURNAL_FILE);
        let mut f = OpenOptions::new().append(true).open(&path).unwrap();
        f.write_all(b"1,0,50,0.49,0,0,0.0").unwrap();
        drop(f);
        let before = std::fs::read(&path).unwrap();
        let c = read_journal(dir.path()).unwrap();
        assert_eq!(c.rows, vec![row(0)]);
        assert_eq!(c.torn, Some(TornLine { line: 3, bytes: 19 }));
        assert_eq!(std::fs::read(&path).unwrap(), before, "never truncated");
        let e = read_rows(dir.path()).unwrap_err().to_string();
        assert!(e.contains("line 3") && e.contains("torn"), "{e}");
        // A header cut mid-write: no rows, the torn line is line 1.
        std::fs::write(&path, b"index,tri").unwrap();
        let c = read_journal(dir.path()).unwrap();
        assert!(c.rows.is_empty());
        assert_eq!(c.torn, Some(TornLine { line: 1, bytes: 9 }));
    }

    #[test]
    fn finish_says_why_the_run_measured_less_than_its_plan() {
        let dir = tempfile::tempdir().unwrap();
        Journal::create(dir.path()).unwrap();
        let mut m = Manifest {
            plan_path: "p.toml".into(),
            plan_name: "p".into(),
            plan_toml: String::new(),
            sensor_path: "s.toml".into(),
            sensor_toml: String::new(),
            bench: serde_json::Value::Null,
            devices: serde_json::Value::Null,
            build_id: None,
            software_version: "0".into(),
            started_at: "t0".into(),
            resumed_at: vec![],
            sessions: vec![],
            setpoints: 8,
            planned_setpoints: Some(160),
            limit: Some(8),
            measured_setpoints: 0,
            status: RunStatus::Running,
            end_reason: None,
            stop_signal: None,
            incomplete_reason: None,
            ended_at: None,
            software_commit: None,
            camera_path: None,
            camera_toml: None,
            simulated: None,
            write_failure: None,
            device_provenance: Vec::new(),
            record: None,
        };
        m.finish(RunStatus::Completed, None, 8, None, "t1".into());
        assert_eq!(
            m.incomplete_reason.as_deref(),
            Some("limited by --limit 8: 8 of the plan's 160 setpoints measured")
        );
        m.limit = None;
        m.finish(
            RunStatus::Interrupted,
            Some("x".into()),
            18,
            Some(15),
            "t2".into(),
        );
        assert_eq!(m.stop_signal.as_deref(), Some("SIGTERM"));
        let r = m.incomplete_reason.clone().unwrap();
        assert!(
            r.starts_with("interrupted by SIGTERM") && !r.contains("Ctrl-C"),
            "{r}"
        );
        m.finish(RunStatus::Interrupted, None, 18, Some(2), "t2".into());
        assert!(m
            .incomplete_reason
            .clone()
            .unwrap()
            .contains("SIGINT (Ctrl-C)"));
        m.finish(
            RunStatus::Aborted,
            Some("safety trip".into()),
            3,
            None,
            "t3".into(),
        );
        assert_eq!(m.stop_signal, None);
        assert!(m
            .incomplete_reason
            .clone()
            .unwrap()
            .ends_with(": safety trip"));
        m.finish(RunStatus::Completed, None, 160, None, "t4".into());
        assert_eq!(m.incomplete_reason, None);
    }

    #[test]
    fn manifests_written_before_the_counts_were_recorded_still_read() {
        let dir = tempfile::tempdir().unwrap();
        let old = r#"{"plan_path":"p.toml","plan_name":"p","plan_toml":"","sensor_path":"s.toml",
            "sensor_toml":"","bench":null,"devices":null,"build_id":null,"software_version":"0.1.0",
            "started_at":"2026-11-22T00:00:00Z","setpoints":12,"status":"completed"}"#;
        std::fs::write(dir.path().join(MANIFEST_FILE), old).unwrap();
        let m = Manifest::read(dir.path()).unwrap();
        assert_eq!((m.planned(), m.measured_setpoints, m.limit), (12, 0, None));
        assert_eq!(m.software_commit, None);
    }

    #[test]
    fn create_never_overwrites_an_existing_run() {
        let dir = tempfile::tempdir().unwrap();
        Journal::create(dir.path()).unwrap();
        assert!(Journal::create(dir.path()).is_err());
    }

    #[test]
    fn duplicate_rows_and_foreign_files_are_rejected_on_resume() {
        let dir = tempfile::tempdir().unwrap();
        let mut j = Journal::create(dir.path()).unwrap();
        j.append(&row(0)).unwrap();
        drop(j);
        let text = std::fs::read_to_string(dir.path().join(JOURNAL_FILE)).unwrap();
        let dup = format!("{text}{}", text.lines().nth(1).unwrap()) + "\n";
        std::fs::write(dir.path().join(JOURNAL_FILE), dup).unwrap();
        let e = Journal::open_resume(dir.path()).unwrap_err().to_string();
        assert!(e.contains("appears twice"), "{e}");
        std::fs::write(dir.path().join(JOURNAL_FILE), "a,b\n1,2\n").unwrap();
        assert!(Journal::open_resume(dir.path())
            .unwrap_err()
            .to_string()
            .contains("header"));
        // A reordered header is refused by readers too, naming the first column.
        let mut j = Journal::create(&dir.path().join("r")).ok();
        if j.is_none() {
            std::fs::create_dir_all(dir.path().join("r")).unwrap();
            j = Journal::create(&dir.path().join("r")).ok();
        }
        j.unwrap().append(&row(0)).unwrap();
        let path = dir.path().join("r").join(JOURNAL_FILE);
        let text = std::fs::read_to_string(&path).unwrap();
        std::fs::write(&path, text.replacen("fx_n,fy_n,fz_n", "fx_n,fz_n,fy_n", 1)).unwrap();
        let e = read_rows(&dir.path().join("r")).unwrap_err().to_string();
        assert!(
            e.contains("line 1")
                && e.contains("column 8 is `fz_n` where a tactbench journal has `fy_n`"),
            "{e}"
        );
    }

    #[test]
    fn manifest_round_trips_atomically() {
        let dir = tempfile::tempdir().unwrap();
        let m = Manifest {
            plan_path: "experiments/p.toml".into(),
            plan_name: "p".into(),
            plan_toml: "name = \"p\"".into(),
            sensor_path: "s.toml".into(),
            sensor_toml: String::new(),
            bench: serde_json::json!({"sim": "scene.toml"}),
            devices: serde_json::json!({"stage": "grbl 1.1h"}),
            build_id: Some("b1".into()),
            software_version: env!("CARGO_PKG_VERSION").into(),
            started_at: "2026-11-22T00:00:00Z".into(),
            resumed_at: vec![],
            sessions: vec![],
            setpoints: 160,
            planned_setpoints: Some(160),
            limit: None,
            measured_setpoints: 0,
            status: RunStatus::Running,
            end_reason: None,
            stop_signal: None,
            incomplete_reason: None,
            ended_at: None,
            software_commit: Some(GIT_COMMIT.into()),
            camera_path: None,
            camera_toml: None,
            simulated: None,
            write_failure: None,
            device_provenance: Vec::new(),
            record: None,
        };
        m.write(dir.path()).unwrap();
        assert_eq!(Manifest::read(dir.path()).unwrap(), m);
        assert!(!dir.path().join(".manifest.json.tmp").exists());
    }
}
