//! `live.json`: what the runner is doing right now, for watchers in other processes
//! (`tactbench serve RUN_DIR`). Schema `tactbench-live/1` (ARCHITECTURE.md, "The run
//! directory"):
//!
//! ```json
//! {"schema": "tactbench-live/1", "updated_at": "…Z", "pid": 4242, "state": "running",
//!  "setpoint_index": 12, "setpoints_done": 12, "setpoints_total": 40,
//!  "phase": "settle", "phase_started_at": "…Z",
//!  "ft": [fx, fy, fz, mx, my, mz] | null, "stage_mm": [x, y, z] | null,
//!  "warnings": ["…", …], "end_reason": null}
//! ```
//!
//! It is a hint, not part of the record: the runner replaces it atomically
//! (`.live.json.tmp`, rename; no fsync) at phase changes, at most
//! [`MAX_WRITES_PER_S`] times a second (a change inside that interval is written with
//! the next event after it), and always at the end of the run. `report`, `compare` and
//! `archive` ignore it; a failed write never stops a run.
//!
//! [`LiveDoc::apply`] turns [`RunEvent`]s into the document; the runner's file and the
//! in-process live view (`run --serve`) use the same function, so both show the same.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};
use thiserror::Error;

pub use super::events::Phase;
use super::events::{rfc3339, RunEvent};
use super::journal::RunStatus;

/// The file's name in the run directory.
pub const LIVE_FILE: &str = "live.json";
/// The temporary file it is written through.
pub const LIVE_TMP_FILE: &str = ".live.json.tmp";
/// The schema tag.
pub const LIVE_SCHEMA: &str = "tactbench-live/1";
/// Most writes of `live.json` per second (phase changes and readings).
pub const MAX_WRITES_PER_S: u32 = 5;
/// Warnings kept (the newest).
pub const MAX_WARNINGS: usize = 20;

/// A `live.json` that cannot be read.
#[derive(Debug, Error)]
pub enum LiveFileError {
    /// Reading the file.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// Not a `tactbench-live/1` document.
    #[error("{path}: not a {LIVE_SCHEMA} document: {message}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

/// The `live.json` document.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LiveDoc {
    /// Always [`LIVE_SCHEMA`].
    pub schema: String,
    /// When this document was made, RFC 3339 UTC with milliseconds.
    pub updated_at: String,
    /// The writing process.
    pub pid: u32,
    /// The run's state as the runner knows it.
    pub state: RunStatus,
    /// The setpoint being measured (its index in the expanded plan), if any.
    pub setpoint_index: Option<usize>,
    /// Setpoints in the journal.
    pub setpoints_done: usize,
    /// Setpoints in the run.
    pub setpoints_total: usize,
    /// What the runner is doing.
    pub phase: Phase,
    /// When that began, RFC 3339 UTC with milliseconds.
    pub phase_started_at: String,
    /// The latest F/T reading: fx, fy, fz (N), mx, my, mz (N·m).
    pub ft: Option<[f64; 6]>,
    /// The stage's commanded position, machine mm.
    pub stage_mm: Option<[f64; 3]>,
    /// The newest warnings, retries and safety trips (at most [`MAX_WARNINGS`]).
    pub warnings: VecDeque<String>,
    /// Why the run ended, when it ended other than completed.
    pub end_reason: Option<String>,
}

impl LiveDoc {
    /// The document of a run that has not reported anything yet.
    pub fn new() -> LiveDoc {
        let now = rfc3339_millis_now();
        LiveDoc {
            schema: LIVE_SCHEMA.to_string(),
            updated_at: now.clone(),
            pid: std::process::id(),
            state: RunStatus::Running,
            setpoint_index: None,
            setpoints_done: 0,
            setpoints_total: 0,
            phase: Phase::Idle,
            phase_started_at: now,
            ft: None,
            stage_mm: None,
            warnings: VecDeque::new(),
            end_reason: None,
        }
    }

    /// Takes an event into the document. Returns whether it must be written at once
    /// (a phase change, the start or the end of the run), as opposed to a reading or
    /// a count that may wait for the rate limit.
    pub fn apply(&mut self, e: &RunEvent) -> bool {
        match e {
            RunEvent::Started { total, done, .. } => {
                self.setpoints_total = *total;
                self.setpoints_done = *done;
                self.state = RunStatus::Running;
                self.end_reason = None;
                true
            }
            RunEvent::Phase { index, phase } => {
                self.setpoint_index = *index;
                if *phase != self.phase {
                    self.phase = *phase;
                    self.phase_started_at = rfc3339_millis_now();
                    true
                } else {
                    false
                }
            }
            RunEvent::Reading {
                index,
                ft,
                stage_mm,
            } => {
                self.setpoint_index = *index;
                self.ft = Some(*ft);
                if stage_mm.is_some() {
                    self.stage_mm = *stage_mm;
                }
                false
            }
            RunEvent::SetpointStarted {
                setpoint,
                done,
                total,
            } => {
                self.setpoint_index = Some(setpoint.index);
                self.setpoints_done = *done;
                self.setpoints_total = *total;
                false
            }
            RunEvent::SetpointMeasured { done, total, .. } => {
                self.setpoints_done = *done;
                self.setpoints_total = *total;
                true
            }
            RunEvent::Warning { index, message } => {
                self.warn(format!("setpoint {index}: {message}"));
                true
            }
            RunEvent::Retry {
                index,
                attempt,
                reason,
            } => {
                self.warn(format!(
                    "retry {attempt}{}: {reason}",
                    index
                        .map(|i| format!(" at setpoint {i}"))
                        .unwrap_or_default()
                ));
                true
            }
            RunEvent::SafetyTrip { reason, .. } => {
                self.warn(format!("SAFETY STOP: {reason}"));
                true
            }
            RunEvent::Finished { status, reason } => {
                self.state = *status;
                self.end_reason = reason.clone();
                self.setpoint_index = None;
                if self.phase != Phase::Idle {
                    self.phase = Phase::Idle;
                    self.phase_started_at = rfc3339_millis_now();
                }
                true
            }
            RunEvent::Homing
            | RunEvent::Tared { .. }
            | RunEvent::Reference { .. }
            | RunEvent::Contact { .. } => false,
        }
    }

    fn warn(&mut self, w: String) {
        if self.warnings.len() == MAX_WARNINGS {
            self.warnings.pop_front();
        }
        self.warnings.push_back(w);
    }

    /// Reads `DIR/live.json`; `Ok(None)` when there is none (a run written before
    /// the live file existed, or that has not started).
    pub fn read(dir: &Path) -> Result<Option<LiveDoc>, LiveFileError> {
        let path = dir.join(LIVE_FILE);
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(source) => return Err(LiveFileError::Io { path, source }),
        };
        let doc: LiveDoc = serde_json::from_str(&text).map_err(|e| LiveFileError::Format {
            path: path.clone(),
            message: e.to_string(),
        })?;
        if doc.schema != LIVE_SCHEMA {
            return Err(LiveFileError::Format {
                path,
                message: format!("schema {:?}", doc.schema),
            });
        }
        Ok(Some(doc))
    }

    /// Writes `DIR/live.json` atomically (temporary file, rename; no fsync).
    pub fn write(&mut self, dir: &Path) -> std::io::Result<()> {
        self.updated_at = rfc3339_millis_now();
        let text = serde_json::to_vec(self).map_err(std::io::Error::other)?;
        let tmp = dir.join(LIVE_TMP_FILE);
        std::fs::write(&tmp, text)?;
        std::fs::rename(&tmp, dir.join(LIVE_FILE))
    }
}

impl Default for LiveDoc {
    fn default() -> Self {
        LiveDoc::new()
    }
}

/// The runner's `live.json` writer: observes every event, writes at phase changes
/// and at most [`MAX_WRITES_PER_S`] times a second.
#[derive(Debug)]
pub struct LiveWriter {
    dir: PathBuf,
    doc: LiveDoc,
    last_write: Option<Instant>,
    /// The first failed write (the file is a hint: the run goes on without it).
    pub error: Option<String>,
}

impl LiveWriter {
    /// A writer for the run directory `dir`.
    pub fn new(dir: &Path) -> LiveWriter {
        LiveWriter {
            dir: dir.to_path_buf(),
            doc: LiveDoc::new(),
            last_write: None,
            error: None,
        }
    }

    /// Takes an event; writes the file when due.
    pub fn observe(&mut self, e: &RunEvent) {
        self.doc.apply(e);
        let interval = Duration::from_secs(1) / MAX_WRITES_PER_S;
        let now = Instant::now();
        let due = self
            .last_write
            .is_none_or(|t| now.duration_since(t) >= interval);
        if due || matches!(e, RunEvent::Finished { .. }) {
            self.last_write = Some(now);
            if let Err(err) = self.doc.write(&self.dir) {
                self.error.get_or_insert_with(|| {
                    format!("{}: {err}", self.dir.join(LIVE_FILE).display())
                });
            }
        }
    }

    /// The document as last observed.
    pub fn doc(&self) -> &LiveDoc {
        &self.doc
    }
}

/// Now as RFC 3339 UTC with milliseconds (`2026-11-26T15:04:05.123Z`).
pub fn rfc3339_millis_now() -> String {
    let d = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default();
    let s = rfc3339(d.as_secs() as i64);
    format!("{}.{:03}Z", s.trim_end_matches('Z'), d.subsec_millis())
}

/// Seconds since the Unix epoch of an RFC 3339 UTC time as the runner writes them
/// (`YYYY-MM-DDTHH:MM:SS[.fff]Z`); `None` for anything else.
pub fn parse_rfc3339(s: &str) -> Option<f64> {
    let s = s.strip_suffix('Z')?;
    let (date, time) = s.split_once('T')?;
    let mut d = date.splitn(3, '-');
    let y: i64 = d.next()?.parse().ok()?;
    let m: i64 = d.next()?.parse().ok()?;
    let day: i64 = d.next()?.parse().ok()?;
    let mut t = time.splitn(3, ':');
    let hh: i64 = t.next()?.parse().ok()?;
    let mm: i64 = t.next()?.parse().ok()?;
    let ss: f64 = t.next()?.parse().ok()?;
    if !(1..=12).contains(&m)
        || !(1..=31).contains(&day)
        || hh > 23
        || mm > 59
        || !(0.0..61.0).contains(&ss)
    {
        return None;
    }
    // Days from civil (H. Hinnant), the inverse of `events::rfc3339`.
    let y = if m <= 2 { y - 1 } else { y };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (m + 9) % 12;
    let doy = (153 * mp + 2) / 5 + day - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    let days = era * 146_097 + doe - 719_468;
    Some((days * 86_400 + hh * 3600 + mm * 60) as f64 + ss)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bench::events::rfc3339;

    #[test]
    fn rfc3339_parses_back_what_the_runner_writes() {
        for secs in [0i64, 951_827_696, 1_795_305_600, 4_102_444_799] {
            assert_eq!(parse_rfc3339(&rfc3339(secs)), Some(secs as f64));
        }
        let t = parse_rfc3339("2026-11-22T00:00:00.250Z").unwrap();
        assert!((t - 1_795_305_600.25).abs() < 1e-6);
        assert_eq!(parse_rfc3339("2026-13-01T00:00:00Z"), None);
        assert_eq!(parse_rfc3339("yesterday"), None);
        assert!(parse_rfc3339(&rfc3339_millis_now()).is_some());
    }

    #[test]
    fn events_make_the_live_document_and_warnings_keep_the_newest_twenty() {
        let mut d = LiveDoc::new();
        assert!(d.apply(&RunEvent::Started {
            total: 5,
            done: 1,
            truncated_bytes: 0
        }));
        assert!(d.apply(&RunEvent::Phase {
            index: Some(1),
            phase: Phase::Settle
        }));
        assert!(!d.apply(&RunEvent::Phase {
            index: Some(1),
            phase: Phase::Settle
        }));
        assert!(!d.apply(&RunEvent::Reading {
            index: Some(1),
            ft: [0.0, 0.0, 1.5, 0.0, 0.0, 0.0],
            stage_mm: Some([1.0, 2.0, 3.0])
        }));
        for i in 0..25 {
            d.apply(&RunEvent::Warning {
                index: i,
                message: "w".into(),
            });
        }
        assert_eq!(d.warnings.len(), MAX_WARNINGS);
        assert_eq!(d.warnings[0], "setpoint 5: w");
        d.apply(&RunEvent::Finished {
            status: RunStatus::Interrupted,
            reason: Some("interrupted by SIGINT (Ctrl-C)".into()),
        });
        assert_eq!(d.state, RunStatus::Interrupted);
        assert_eq!(d.phase, Phase::Idle);
        assert_eq!((d.setpoints_done, d.setpoints_total), (1, 5));
        assert_eq!(d.ft.unwrap()[2], 1.5);
        let text = serde_json::to_string(&d).unwrap();
        for key in [
            "\"schema\":\"tactbench-live/1\"",
            "\"state\":\"interrupted\"",
            "\"phase\":\"idle\"",
            "\"setpoints_total\":5",
            "\"stage_mm\":[1.0,2.0,3.0]",
        ] {
            assert!(text.contains(key), "{key} in {text}");
        }
    }

    #[test]
    fn the_writer_replaces_the_file_and_writes_the_end_at_once() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = LiveWriter::new(dir.path());
        w.observe(&RunEvent::Started {
            total: 3,
            done: 0,
            truncated_bytes: 0,
        });
        let first = LiveDoc::read(dir.path()).unwrap().unwrap();
        assert_eq!(first.setpoints_total, 3);
        assert_eq!(first.pid, std::process::id());
        // Inside the rate limit: not written yet...
        w.observe(&RunEvent::Reading {
            index: None,
            ft: [0.0; 6],
            stage_mm: None,
        });
        assert_eq!(LiveDoc::read(dir.path()).unwrap().unwrap().ft, None);
        // ...but the end always is.
        w.observe(&RunEvent::Finished {
            status: RunStatus::Completed,
            reason: None,
        });
        let end = LiveDoc::read(dir.path()).unwrap().unwrap();
        assert_eq!(end.state, RunStatus::Completed);
        assert_eq!(end.ft, Some([0.0; 6]));
        assert!(!dir.path().join(LIVE_TMP_FILE).exists());
        assert!(w.error.is_none());
    }

    #[test]
    fn a_live_file_of_another_schema_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        assert!(LiveDoc::read(dir.path()).unwrap().is_none());
        std::fs::write(dir.path().join(LIVE_FILE), "{\"schema\": \"x\"}").unwrap();
        let e = LiveDoc::read(dir.path()).unwrap_err().to_string();
        assert!(e.contains("live.json") && e.contains(LIVE_SCHEMA), "{e}");
    }
}
