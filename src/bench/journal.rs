//! The run directory's crash-safe record: `journal.csv` (one row per completed
//! measurement, appended, flushed and synced to disk before the next move) and
//! `manifest.json` (what ran, on what, by which software, and how it ended).
//!
//! Resume rules: a row is only ever written once its measurement is complete, so after
//! a kill (even SIGKILL) the journal holds every completed setpoint exactly once, plus
//! at most one torn last line, which [`Journal::open_resume`] cuts off (and reports).
//! The runner then continues with the first setpoint index not in the journal.

use std::collections::BTreeSet;
use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use thiserror::Error;

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
    /// Reconstructed force sums Σfx (paper F^sum), N.
    pub fsum_x_n: f64,
    /// Σfy, N.
    pub fsum_y_n: f64,
    /// Σfz, N.
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
    /// Number of setpoints in the plan.
    pub setpoints: usize,
    /// How it ended.
    pub status: RunStatus,
    /// Why it ended that way (abort reason, safety trip), if not completed.
    #[serde(default)]
    pub end_reason: Option<String>,
    /// End time, RFC 3339 UTC.
    #[serde(default)]
    pub ended_at: Option<String>,
}

impl Manifest {
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
        let keep = bytes
            .iter()
            .rposition(|&b| b == b'\n')
            .map(|i| i + 1)
            .unwrap_or(0);
        let truncated_bytes = (bytes.len() - keep) as u64;
        if truncated_bytes > 0 {
            file.set_len(keep as u64).map_err(io)?;
            file.sync_all().map_err(io)?;
        }
        let mut rdr = csv::Reader::from_reader(&bytes[..keep]);
        let headers = rdr
            .headers()
            .map_err(|e| corrupt(&path, 1, e.to_string()))?
            .clone();
        if headers.iter().collect::<Vec<_>>() != header() {
            return Err(corrupt(
                &path,
                1,
                "not a tactbench journal (unexpected header)".into(),
            ));
        }
        let mut rows = Vec::new();
        let mut done = BTreeSet::new();
        for rec in rdr.deserialize::<JournalRow>() {
            let row = rec.map_err(|e| {
                let line = e.position().map(|p| p.line()).unwrap_or(0);
                corrupt(&path, line, e.to_string())
            })?;
            if !done.insert(row.index) {
                return Err(corrupt(
                    &path,
                    rows.len() as u64 + 2,
                    format!("setpoint {} appears twice", row.index),
                ));
            }
            rows.push(row);
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

/// Reads every row of a run's journal (for analysis and reports).
pub fn read_rows(dir: &Path) -> Result<Vec<JournalRow>, JournalError> {
    let path = dir.join(JOURNAL_FILE);
    let mut rdr = csv::Reader::from_path(&path).map_err(|e| corrupt(&path, 0, e.to_string()))?;
    let mut rows = Vec::new();
    for rec in rdr.deserialize::<JournalRow>() {
        rows.push(rec.map_err(|e| {
            let line = e.position().map(|p| p.line()).unwrap_or(0);
            corrupt(&path, line, e.to_string())
        })?);
    }
    Ok(rows)
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
            setpoints: 160,
            status: RunStatus::Running,
            end_reason: None,
            ended_at: None,
        };
        m.write(dir.path()).unwrap();
        assert_eq!(Manifest::read(dir.path()).unwrap(), m);
        assert!(!dir.path().join(".manifest.json.tmp").exists());
    }
}
