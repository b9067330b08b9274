//! Analysis of a run directory: the paper's evaluation (Section IV) computed from what
//! the runner recorded.
//!
//! | module | paper | input |
//! |---|---|---|
//! | [`magnitude`] | Fig. 7 | journal `fz_n` (applied, F/T) against `fsum_z_n` (F^sum) |
//! | [`angle`] | Fig. 8 | journal F/T wrench against `fsum_*` |
//! | [`spatial`] | Fig. 9 | `forces/NNNNN.csv` of a `spatial` sweep |
//! | [`displacement`] | Table I | `displacements/NNNNN.csv` of a `displacement` sweep |
//! | [`timing`] | Table II | journal `t_*` columns |
//! | [`tracking`] | — | journal `markers_*`, `reacquired`, `quality` columns (marker health) |
//! | [`metrology`] | ISO 376 | magnitude rows with `direction`, `position`: repeatability, reproducibility, interpolation, zero, reversibility, class |
//! | [`hold`] | ISO 376 | rows with `hold_t_s`: creep of F^sum against the F/T, zero drift |
//!
//! [`calibration`] holds the definitions shared by Fig. 7 and 8 (fit, resolution,
//! linearity, hysteresis); [`stats`] the small statistics they use.
//!
//! [`RunData::load`] reads a run directory (`manifest.json` with the embedded plan and
//! sensor, `journal.csv`), validating every value it uses with errors that name the
//! file, line and column; it only reads (a torn last journal line, what a crash
//! mid-write leaves, is skipped and reported in [`RunData::torn`], never cut off).
//! [`RunAnalysis::new`] dispatches on the plan's sweep kind and
//! [`RunAnalysis::metrics`] flattens the results into named scalar [`Metric`]s (the
//! names acceptance criteria refer to, listed in [`METRICS`]). An analysis the run's
//! rows cannot support (0 or 1 rows, a single level) is left out and listed in
//! [`RunAnalysis::absent`] with the reason, so every run gets a report.
//!
//! **Archived runs.** The record is `manifest.json` + `journal.csv`; `frames/`,
//! `displacements/` and `forces/` are evidence that may be gone (`tactbench archive`,
//! or a lab that keeps old runs as journals). Every metric the journal carries is
//! computed from the journal alone, so it is the same with or without them. The field
//! figures then have no snapshot, and each thing that could not be shown is listed in
//! [`RunAnalysis::missing`] (one line each). Two analyses are not in the journal:
//! Fig. 9 (`spatial`: the force profile of each point load) and Table I
//! (`displacement`: the tracked displacements of each shift) read their per-setpoint
//! files; without them those analyses are absent with the reason (and
//! `tactbench archive` always keeps those files for those sweeps).
//!
//! The simulation studies live here too: [`accuracy_time`] (force error against time
//! per frame over solver, force-grid, tracking and averaging choices; Pareto front and
//! budgets), [`layer_separation`] (force error against the distance between the two
//! marker layers, paper Fig. 6, per solver) and [`model_error`] (what the half-space
//! assumption costs a bonded layer of each thickness, against a solver that models the
//! layer, with camera effects; issue 14).

pub mod accuracy_time;
pub mod angle;
pub mod calibration;
pub mod displacement;
pub mod hold;
pub mod layer_separation;
pub mod magnitude;
pub mod metrology;
pub mod model_error;
pub mod spatial;
pub mod stats;
pub mod timing;
pub mod tracking;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use thiserror::Error;

use crate::bench::journal::{self, JournalError, JournalRow, Manifest, TornLine, JOURNAL_FILE};
use crate::bench::plan::{Plan, Setpoint, Sweep};
use crate::config::ConfigError;
use crate::formats::{self, DisplacementFrame, ForceRecord, FormatError};
use crate::sensor::{Sensor, SensorError};

/// An error loading or analysing a run directory. Every variant names what failed.
#[derive(Debug, Error)]
pub enum AnalysisError {
    /// Reading `journal.csv` or `manifest.json` failed.
    #[error(transparent)]
    Journal(#[from] JournalError),
    /// The plan embedded in the manifest is invalid.
    #[error("{manifest}: embedded plan: {source}")]
    Plan {
        /// The manifest file.
        manifest: PathBuf,
        /// The plan's error.
        source: ConfigError,
    },
    /// The sensor embedded in the manifest is invalid.
    #[error("{manifest}: embedded sensor: {source}")]
    Sensor {
        /// The manifest file.
        manifest: PathBuf,
        /// The sensor's error.
        source: SensorError,
    },
    /// A journal value is unusable.
    #[error("{path}: line {line}, column `{column}`: {message}")]
    JournalValue {
        /// The journal file.
        path: PathBuf,
        /// 1-based line.
        line: u64,
        /// Column name.
        column: &'static str,
        /// What is wrong, with the value.
        message: String,
    },
    /// A per-setpoint file the analysis needs is missing.
    #[error("{path}: missing ({what} of setpoint {index}, journal line {line})")]
    MissingFile {
        /// The expected file.
        path: PathBuf,
        /// What it should hold.
        what: &'static str,
        /// Setpoint index.
        index: usize,
        /// Journal line of that setpoint.
        line: u64,
    },
    /// A per-setpoint file is malformed.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// The data do not support the analysis (too few levels, a flat profile...).
    #[error("{path}: {message}")]
    Insufficient {
        /// The run directory.
        path: PathBuf,
        /// What is missing, from the analysis that failed.
        message: String,
    },
}

/// A loaded run directory.
#[derive(Debug, Clone)]
pub struct RunData {
    /// The run directory.
    pub dir: PathBuf,
    /// `manifest.json`.
    pub manifest: Manifest,
    /// The plan embedded in the manifest.
    pub plan: Plan,
    /// The sensor embedded in the manifest.
    pub sensor: Sensor,
    /// Every setpoint of the plan (the journal's `index` refers to these).
    pub setpoints: Vec<Setpoint>,
    /// The journal rows with a measurement, in file order (complete lines only);
    /// failed rows are in `failed`.
    pub rows: Vec<JournalRow>,
    /// Failed rows (no force: tracking or reconstruction failed, a dead camera, or a
    /// NaN an older version wrote): skipped by every analysis, counted and named.
    pub failed: Vec<FailedRow>,
    /// A torn last journal line that was skipped (the file is left as it is).
    pub torn: Option<TornLine>,
}

/// A journal row without a usable force ([`JournalRow::failed`]).
#[derive(Debug, Clone, PartialEq)]
pub struct FailedRow {
    /// Setpoint index.
    pub index: usize,
    /// Journal line.
    pub line: u64,
    /// Why it has no force.
    pub reason: String,
}

impl FailedRow {
    /// `setpoint 3 (journal line 5): why`.
    pub fn describe(&self) -> String {
        format!(
            "setpoint {} (journal line {}): {}",
            self.index, self.line, self.reason
        )
    }
}

/// `displacements/NNNNN.csv` of setpoint `index`.
pub fn displacements_path(dir: &Path, index: usize) -> PathBuf {
    dir.join("displacements").join(format!("{index:05}.csv"))
}

/// `forces/NNNNN.csv` of setpoint `index`.
pub fn forces_path(dir: &Path, index: usize) -> PathBuf {
    dir.join("forces").join(format!("{index:05}.csv"))
}

impl RunData {
    /// Reads and validates a run directory's manifest and journal.
    pub fn load(dir: &Path) -> Result<RunData, AnalysisError> {
        let manifest = Manifest::read(dir)?;
        let mpath = dir.join(journal::MANIFEST_FILE);
        let plan =
            Plan::from_toml_str(&manifest.plan_toml, &manifest.plan_path).map_err(|source| {
                AnalysisError::Plan {
                    manifest: mpath.clone(),
                    source,
                }
            })?;
        let sensor = Sensor::from_toml_str(&manifest.sensor_toml, &manifest.sensor_path).map_err(
            |source| AnalysisError::Sensor {
                manifest: mpath.clone(),
                source,
            },
        )?;
        let contents = journal::read_journal(dir)?;
        let (rows, torn) = (contents.rows, contents.torn);
        let setpoints = plan.setpoints();
        let jpath = dir.join(JOURNAL_FILE);
        let mut seen = BTreeSet::new();
        for (i, r) in rows.iter().enumerate() {
            // Header is line 1; rows have no embedded newlines (the journal writes none).
            let line = i as u64 + 2;
            let bad = |column: &'static str, message: String| AnalysisError::JournalValue {
                path: jpath.clone(),
                line,
                column,
                message,
            };
            if r.index >= setpoints.len() {
                return Err(bad(
                    "index",
                    format!(
                        "setpoint {} is not in the plan, which has {} setpoints",
                        r.index,
                        setpoints.len()
                    ),
                ));
            }
            if !seen.insert(r.index) {
                return Err(bad("index", format!("setpoint {} appears twice", r.index)));
            }
            let failure = r.failed();
            for (column, v) in numeric_columns(r) {
                // A failed row's force sums are empty (NaN): it is skipped, not refused.
                if failure.is_some() && column.starts_with("fsum_") {
                    continue;
                }
                if !v.is_finite() {
                    return Err(bad(column, format!("value {v} is not a finite number")));
                }
            }
            plausible_row(r, &setpoints[r.index], &plan).map_err(|(c, m)| bad(c, m))?;
        }
        // After a session that could not record its end (kill -9) the journal is the
        // authority on what each session measured (read-only: the file is unchanged).
        let mut manifest = manifest;
        manifest.reconcile_sessions(rows.len());
        let (mut good, mut failed) = (Vec::with_capacity(rows.len()), Vec::new());
        for (i, r) in rows.into_iter().enumerate() {
            match r.failed() {
                Some(reason) => failed.push(FailedRow {
                    index: r.index,
                    line: i as u64 + 2,
                    reason,
                }),
                None => good.push(r),
            }
        }
        Ok(RunData {
            dir: dir.to_path_buf(),
            manifest,
            plan,
            sensor,
            setpoints,
            rows: good,
            failed,
            torn,
        })
    }

    /// Setpoints in the journal: measured rows and failed rows.
    pub fn journalled(&self) -> usize {
        self.rows.len() + self.failed.len()
    }

    /// Journal line of the row for setpoint `index` (0 when absent).
    pub fn line_of(&self, index: usize) -> u64 {
        let mut lines: Vec<(usize, u64)> = self.failed.iter().map(|f| (f.index, f.line)).collect();
        // Measured rows fill the lines the failed ones leave, in file order.
        let taken: BTreeSet<u64> = lines.iter().map(|l| l.1).collect();
        let mut line = 2;
        for r in &self.rows {
            while taken.contains(&line) {
                line += 1;
            }
            lines.push((r.index, line));
            line += 1;
        }
        lines
            .iter()
            .find(|(i, _)| *i == index)
            .map_or(0, |(_, l)| *l)
    }

    /// Reads setpoint `index`'s forces file.
    pub fn forces(&self, index: usize) -> Result<Vec<ForceRecord>, AnalysisError> {
        let path = forces_path(&self.dir, index);
        if !path.is_file() {
            return Err(AnalysisError::MissingFile {
                path,
                what: "reconstructed forces",
                index,
                line: self.line_of(index),
            });
        }
        Ok(formats::read_forces(&path)?)
    }

    /// Reads setpoint `index`'s displacement file (every frame).
    pub fn displacements(&self, index: usize) -> Result<Vec<DisplacementFrame>, AnalysisError> {
        let path = displacements_path(&self.dir, index);
        if !path.is_file() {
            return Err(AnalysisError::MissingFile {
                path,
                what: "tracked displacements",
                index,
                line: self.line_of(index),
            });
        }
        Ok(formats::read_displacements(&path, &self.sensor)?)
    }

    /// The plan's sweep kind as written in plans (`magnitude`, `angle`, ...).
    pub fn sweep_kind(&self) -> &'static str {
        match self.plan.sweep {
            Sweep::Magnitude { .. } => "magnitude",
            Sweep::Angle { .. } => "angle",
            Sweep::Spatial { .. } => "spatial",
            Sweep::Displacement { .. } => "displacement",
            Sweep::Setpoints(_) => "setpoints",
            Sweep::Hold { .. } => "hold",
        }
    }
}

/// How far a journalled mean force may exceed the plan's safety limit (relative): the
/// watchdog checks every reading that goes into the mean, so a mean beyond it cannot
/// have been measured; the slack only absorbs the journal's number formatting.
const LIMIT_SLACK: f64 = 1e-6;

/// Whether a row's values fit its plan (the journal was not edited, its columns not
/// swapped): the targets and swept value are the plan's for that setpoint, the F/T
/// means within the plan's safety limits (the watchdog stops a run before a reading
/// beyond them), the times not negative. `Err((column, message))` names the value and
/// the range it is outside.
fn plausible_row(r: &JournalRow, sp: &Setpoint, plan: &Plan) -> Result<(), (&'static str, String)> {
    let same = |a: f64, b: f64| (a - b).abs() <= 1e-6 * a.abs().max(b.abs()).max(1e-3);
    let edited = "the journal was edited after the run or its columns swapped";
    for (column, v, want) in [
        ("target_normal_n", r.target_normal_n, sp.normal_n),
        ("swept_value", r.swept_value, sp.swept_value),
    ] {
        if !same(v, want) {
            return Err((
                column,
                format!(
                    "{v} is not the plan's {want} for setpoint {} ({edited})",
                    r.index
                ),
            ));
        }
    }
    if r.trial != sp.trial {
        return Err((
            "trial",
            format!(
                "{} is not the plan's trial {} for setpoint {} ({edited})",
                r.trial, sp.trial, r.index
            ),
        ));
    }
    let limits = plan.safety.max_force_n;
    for (k, (column, v)) in [("fx_n", r.fx_n), ("fy_n", r.fy_n), ("fz_n", r.fz_n)]
        .into_iter()
        .enumerate()
    {
        if v.abs() > limits[k] * (1.0 + LIMIT_SLACK) {
            return Err((
                column,
                format!(
                    "{v} N is outside the plan's safety limit ±{} N, which no journalled mean can exceed (the watchdog stops the run first): {edited}",
                    limits[k]
                ),
            ));
        }
    }
    for (column, v) in [
        ("fx_sd_n", r.fx_sd_n),
        ("fy_sd_n", r.fy_sd_n),
        ("fz_sd_n", r.fz_sd_n),
        ("t_move_s", r.t_move_s),
        ("t_settle_s", r.t_settle_s),
        ("t_acquire_s", r.t_acquire_s),
        ("t_track_s", r.t_track_s),
        ("t_solve_s", r.t_solve_s),
    ] {
        if v < 0.0 {
            return Err((
                column,
                format!(
                    "{v} is negative, which a standard deviation or a duration cannot be: {edited}"
                ),
            ));
        }
    }
    Ok(())
}

/// The journal columns the analyses use, with their values.
fn numeric_columns(r: &JournalRow) -> [(&'static str, f64); 16] {
    [
        ("swept_value", r.swept_value),
        ("target_normal_n", r.target_normal_n),
        ("fx_n", r.fx_n),
        ("fy_n", r.fy_n),
        ("fz_n", r.fz_n),
        ("fsum_x_n", r.fsum_x_n),
        ("fsum_y_n", r.fsum_y_n),
        ("fsum_z_n", r.fsum_z_n),
        ("t_move_s", r.t_move_s),
        ("t_settle_s", r.t_settle_s),
        ("t_acquire_s", r.t_acquire_s),
        ("t_track_s", r.t_track_s),
        ("t_solve_s", r.t_solve_s),
        ("stage_x_mm", r.stage_x_mm),
        ("stage_y_mm", r.stage_y_mm),
        ("stage_z_mm", r.stage_z_mm),
    ]
}

/// One setpoint's tracked displacements and reconstructed forces, for the field
/// figures (paper Fig. 4 and 5).
#[derive(Debug, Clone, PartialEq)]
pub struct Snapshot {
    /// Setpoint index.
    pub index: usize,
    /// First frame of its displacement file.
    pub displacements: DisplacementFrame,
    /// Its forces (`None` for displacement sweeps, which may not reconstruct).
    pub forces: Option<Vec<ForceRecord>>,
}

/// Options of [`RunAnalysis::new`].
#[derive(Debug, Clone, Default)]
pub struct AnalysisOptions {
    /// Setpoint for the field figures; default: the row with the largest |F^sum|.
    pub snapshot_index: Option<usize>,
}

/// Everything computed from one run; each part present when the sweep kind has it.
#[derive(Debug, Clone)]
pub struct RunAnalysis {
    /// The loaded run.
    pub run: RunData,
    /// Fig. 7 (magnitude sweeps).
    pub magnitude: Option<magnitude::MagnitudeAnalysis>,
    /// Fig. 8 (angle sweeps).
    pub angle: Option<angle::AngleAnalysis>,
    /// Fig. 9 (spatial sweeps).
    pub spatial: Option<spatial::SpatialAnalysis>,
    /// Table I (displacement sweeps).
    pub displacement: Option<displacement::DisplacementAnalysis>,
    /// Table II (every run with rows).
    pub timing: Option<timing::TimingAnalysis>,
    /// Fig. 4 and 5 data (every run with rows).
    pub snapshot: Option<Snapshot>,
    /// Marker health per setpoint (rows with marker counts).
    pub tracking: Option<tracking::TrackingAnalysis>,
    /// ISO 376-style metrics (magnitude sweeps).
    pub metrology: Option<metrology::MetrologyAnalysis>,
    /// Creep and zero drift (rows with `hold_t_s`, whatever the sweep kind).
    pub hold: Option<hold::HoldAnalysis>,
    /// Analyses left out because the rows cannot support them: (metric prefix, e.g.
    /// `magnitude`, and why). Their metrics are absent.
    pub absent: Vec<(String, String)>,
    /// What could not be shown because an evidence file (`frames/`, `displacements/`,
    /// `forces/`) is not in the run directory: one line each, naming the file.
    pub missing: Vec<String>,
}

/// Whether an analysis error is an evidence file missing from the run directory.
fn missing_file(e: &AnalysisError) -> Option<String> {
    match e {
        AnalysisError::MissingFile {
            path, what, index, ..
        } => Some(format!(
            "{} ({what} of setpoint {index}) is not in the run directory",
            path.display()
        )),
        _ => None,
    }
}

/// A named scalar result.
#[derive(Debug, Clone, PartialEq)]
pub struct Metric {
    /// Dotted name, e.g. `magnitude.r2` (see [`METRICS`]).
    pub name: String,
    /// The value.
    pub value: f64,
    /// Unit (`N`, `gf`, `deg`, `mm`, `px`, `ms`, `%`, `1` for dimensionless, `count`).
    pub unit: &'static str,
    /// 95 % confidence interval `(low, high)` in the metric's unit, where the analysis
    /// can state one; `None` where it cannot (counts, a single trial per level, ...).
    pub ci95: Option<Ci95>,
}

/// A 95 % confidence interval and how it was obtained.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ci95 {
    /// Lower bound (metric unit).
    pub low: f64,
    /// Upper bound (metric unit).
    pub high: f64,
    /// How: `t` (Student t on an analytic standard error), `bootstrap` (percentile
    /// bootstrap over trials, seeded), `chi2` (chi-squared interval of an SD), ...
    pub method: &'static str,
}

impl Metric {
    /// A metric without a confidence interval.
    pub fn new(name: impl Into<String>, value: f64, unit: &'static str) -> Metric {
        Metric {
            name: name.into(),
            value,
            unit,
            ci95: None,
        }
    }

    /// The same metric with a 95 % confidence interval.
    pub fn with_ci(mut self, ci: Option<Ci95>) -> Metric {
        self.ci95 = ci;
        self
    }
}

/// Every metric the analyses can produce: `(name pattern, unit, meaning)`. `<layer>`
/// stands for a layer name of the run's sensor.
pub const METRICS: &[(&str, &str, &str)] = &[
    ("run.rows", "count", "completed measurements in the journal"),
    (
        "run.unsettled",
        "count",
        "rows whose settle criterion timed out",
    ),
    (
        "run.failed_rows",
        "count",
        "failed rows (no force: tracking or reconstruction failed, a dead camera), skipped by the analyses; present only when there are some",
    ),
    (
        "run.implausible_rows",
        "count",
        "rows journalled quality = implausible (|F^sum| / |F_ft| outside the plan's force_ratio range); present only when there are some",
    ),
    (
        "magnitude.slope",
        "1",
        "least-squares slope of F^sum against applied Fz",
    ),
    ("magnitude.offset_n", "N", "least-squares offset"),
    (
        "magnitude.r2",
        "1",
        "coefficient of determination of the fit",
    ),
    (
        "magnitude.residual_sd_n",
        "N",
        "pooled within-level residual SD",
    ),
    (
        "magnitude.max_level_sd_n",
        "N",
        "largest per-level residual SD",
    ),
    (
        "magnitude.resolution_n",
        "N",
        "2 x pooled residual SD / |slope|",
    ),
    (
        "magnitude.resolution_gf",
        "gf",
        "the resolution in gram-force",
    ),
    (
        "magnitude.resolution_method",
        "1",
        "spread behind the resolution: 1 = pooled within-level residual SD, 2 = residual SD about the fit line (no level has two trials)",
    ),
    (
        "magnitude.linearity_pct",
        "%",
        "max level deviation from the fit / full-scale output",
    ),
    (
        "magnitude.hysteresis_pct",
        "%",
        "max unloading-loading difference / full-scale output",
    ),
    (
        "metrology.full_scale_n",
        "N",
        "full scale FS of the ISO 376-style metrics: the largest applied F/T force",
    ),
    (
        "metrology.repeatability_pct_fs",
        "%FS",
        "repeatability SD s_r: pooled SD of F^sum residuals over trials at the same position, level and direction (ISO 376 b′, the range the class table compares, is 1.128 s_r)",
    ),
    (
        "metrology.reproducibility_pct_fs",
        "%FS",
        "reproducibility SD s_R: pooled SD of F^sum residuals over trials and contact positions at the same level and direction (ISO 376 b, the range the class table compares, is 1.693 s_R)",
    ),
    (
        "metrology.interpolation_pct_fs",
        "%FS",
        "ISO 376 f_c: max |mean loading residual| of a level about the line through the loading rows",
    ),
    (
        "metrology.zero_pct_fs",
        "%FS",
        "ISO 376 f_0: mean over trials of the unloaded error (F^sum - F/T) at the end minus at the start",
    ),
    (
        "metrology.zero_max_pct_fs",
        "%FS",
        "ISO 376 f_0: the largest |zero error| of a trial",
    ),
    (
        "metrology.reversibility_pct_fs",
        "%FS",
        "ISO 376 v (hysteresis): max over levels of |mean unloading - mean loading residual|",
    ),
    (
        "metrology.class",
        "1",
        "ISO 376 class the metrics imply: 0 = class 00, 0.5, 1, 2; 3 = outside class 2",
    ),
    (
        "angle.bias_deg",
        "deg",
        "mean measured - applied angle from the normal",
    ),
    ("angle.sd_deg", "deg", "SD of measured - applied angle"),
    (
        "angle.bias_vs_target_deg",
        "deg",
        "mean measured - target angle",
    ),
    (
        "angle.resolution_deg",
        "deg",
        "2 x pooled residual SD / |slope|",
    ),
    (
        "angle.resolution_method",
        "1",
        "spread behind the resolution: 1 = pooled within-level residual SD, 2 = residual SD about the fit line (no level has two trials)",
    ),
    (
        "angle.slope",
        "1",
        "least-squares slope of measured against applied angle",
    ),
    (
        "angle.r2",
        "1",
        "coefficient of determination of the angle fit",
    ),
    (
        "angle.linearity_pct",
        "%",
        "max level deviation from the fit / full-scale output",
    ),
    (
        "spatial.fwhm_mm",
        "mm",
        "full width at half maximum of the fz profile",
    ),
    (
        "spatial.peak_offset_mm",
        "mm",
        "distance of the profile maximum from the load",
    ),
    (
        "displacement.<layer>.x.mean_px",
        "px",
        "mean tracked x displacement",
    ),
    (
        "displacement.<layer>.x.sd_px",
        "px",
        "SD of tracked x displacement",
    ),
    (
        "displacement.<layer>.x.bias_px",
        "px",
        "mean x displacement - commanded shift",
    ),
    (
        "displacement.<layer>.y.mean_px",
        "px",
        "mean tracked y displacement",
    ),
    (
        "displacement.<layer>.y.sd_px",
        "px",
        "SD of tracked y displacement",
    ),
    (
        "displacement.<layer>.y.bias_px",
        "px",
        "mean y displacement - commanded shift",
    ),
    (
        "displacement.<layer>.x.sd_mm",
        "mm",
        "SD of tracked x displacement",
    ),
    (
        "displacement.<layer>.y.sd_mm",
        "mm",
        "SD of tracked y displacement",
    ),
    (
        "displacement.max_sd_px",
        "px",
        "largest SD over layers and axes",
    ),
    (
        "displacement.max_abs_bias_px",
        "px",
        "largest |bias| over layers and axes",
    ),
    (
        "hold.full_scale_n",
        "N",
        "full scale of the hold metrics: the largest applied F/T force",
    ),
    (
        "hold.creep_pct_fs_per_min",
        "%FS/min",
        "creep: slope of (F^sum - F/T) against hold_t_s (one intercept per hold)",
    ),
    (
        "hold.ft_drift_pct_fs_per_min",
        "%FS/min",
        "slope of the F/T force against hold_t_s during the holds",
    ),
    (
        "hold.zero_drift_n",
        "N",
        "unloaded error (F^sum - F/T): last unloaded row minus first",
    ),
    (
        "hold.zero_drift_pct_fs",
        "%FS",
        "the zero drift in % of full scale",
    ),
    ("timing.tracking_ms", "ms", "mean tracking time per frame"),
    (
        "timing.reconstruction_ms",
        "ms",
        "mean reconstruction time per frame",
    ),
    (
        "timing.forces_ms",
        "ms",
        "mean tracking + reconstruction per frame",
    ),
    (
        "timing.forces_max_ms",
        "ms",
        "largest tracking + reconstruction per frame",
    ),
    (
        "timing.rest_ms",
        "ms",
        "mean move + settle + acquire per frame",
    ),
    (
        "tracking.min_ok_fraction",
        "1",
        "smallest fraction of the markers ok (in every frame) at any setpoint",
    ),
    (
        "tracking.mean_ok_fraction",
        "1",
        "mean fraction of the markers ok over the setpoints",
    ),
    (
        "tracking.flagged_rows",
        "count",
        "rows flagged below [quality] min_ok_fraction after every re-acquisition",
    ),
    (
        "tracking.reacquired_rows",
        "count",
        "rows whose frames were re-acquired at least once",
    ),
];

/// Whether `name` is one of [`METRICS`] (`<layer>` matching any one dot-free word).
pub fn is_known_metric(name: &str) -> bool {
    METRICS.iter().any(|(pattern, _, _)| {
        let p: Vec<&str> = pattern.split('.').collect();
        let n: Vec<&str> = name.split('.').collect();
        p.len() == n.len()
            && p.iter()
                .zip(&n)
                .all(|(a, b)| (*a == "<layer>" && !b.is_empty()) || a == b)
    })
}

impl RunAnalysis {
    /// Loads `dir` and analyses it.
    pub fn load(dir: &Path, options: &AnalysisOptions) -> Result<RunAnalysis, AnalysisError> {
        RunAnalysis::new(RunData::load(dir)?, options)
    }

    /// Analyses a loaded run according to its sweep kind.
    pub fn new(run: RunData, options: &AnalysisOptions) -> Result<RunAnalysis, AnalysisError> {
        let rows = &run.rows;
        let (mut magnitude, mut angle, mut spatial, mut displacement) = (None, None, None, None);
        let mut absent: Vec<(String, String)> = Vec::new();
        let mut missing: Vec<String> = Vec::new();
        let n_rows = format!(
            "{} journal row{}",
            rows.len(),
            if rows.len() == 1 { "" } else { "s" }
        );
        match &run.plan.sweep {
            Sweep::Magnitude { .. } => match magnitude::analyze(rows) {
                Ok(m) => magnitude = Some(m),
                Err(e) => absent.push(("magnitude".into(), format!("{n_rows}: {e}"))),
            },
            Sweep::Angle { .. } => match angle::analyze(rows) {
                Ok(a) => angle = Some(a),
                Err(e) => absent.push(("angle".into(), format!("{n_rows}: {e}"))),
            },
            Sweep::Spatial {
                start_mm, end_mm, ..
            } => {
                let mut loads = Vec::with_capacity(rows.len());
                let mut gone = None;
                for r in rows {
                    let forces = match run.forces(r.index) {
                        Ok(f) => f,
                        Err(e) => match missing_file(&e) {
                            Some(m) => {
                                gone = Some(m);
                                break;
                            }
                            None => return Err(e),
                        },
                    };
                    loads.push(spatial::PointLoad {
                        index: r.index,
                        position_mm: run.setpoints[r.index].position_mm,
                        forces,
                    });
                }
                if let Some(m) = gone {
                    missing.push(format!("spatial profile (Fig. 9) and its metrics: {m}"));
                    absent.push((
                        "spatial".into(),
                        format!("{m}: the force profile is not in the journal; it needs every setpoint's forces file"),
                    ));
                } else {
                    let dir = [end_mm[0] - start_mm[0], end_mm[1] - start_mm[1]];
                    let tol = 0.25 * run.sensor.force_grid.pitch_mm;
                    match spatial::analyze(&loads, dir, tol) {
                        Ok(s) => spatial = Some(s),
                        Err(e) => absent.push(("spatial".into(), format!("{n_rows}: {e}"))),
                    }
                }
            }
            Sweep::Displacement { .. } => {
                let mut ms = Vec::with_capacity(rows.len());
                let mut gone = None;
                for r in rows {
                    let frames = match run.displacements(r.index) {
                        Ok(f) => f,
                        Err(e) => match missing_file(&e) {
                            Some(m) => {
                                gone = Some(m);
                                break;
                            }
                            None => return Err(e),
                        },
                    };
                    ms.push(displacement::ShiftMeasurement {
                        index: r.index,
                        shift_mm: run.setpoints[r.index].shift_mm,
                        frames,
                    });
                }
                if let Some(m) = gone {
                    missing.push(format!(
                        "displacement accuracy (Table I) and its metrics: {m}"
                    ));
                    absent.push((
                        "displacement".into(),
                        format!("{m}: the tracked displacements are not in the journal; Table I needs every setpoint's displacements file"),
                    ));
                } else {
                    let names: Vec<String> =
                        run.sensor.layers.iter().map(|l| l.name.clone()).collect();
                    match displacement::analyze(&ms, &names, run.sensor.camera.mm_per_px) {
                        Ok(d) => displacement = Some(d),
                        Err(e) => absent.push(("displacement".into(), format!("{n_rows}: {e}"))),
                    }
                }
            }
            Sweep::Setpoints(_) => {}
            // Hold sweeps: the creep and zero-drift analysis below runs on the rows'
            // `hold_t_s`, whatever the plan kind.
            Sweep::Hold { .. } => {}
        }
        // Dispatched on the data, not the plan: magnitude rows give the ISO 376-style
        // metrics, rows with `hold_t_s` the creep analysis.
        let metrology = if magnitude.is_some() {
            let m = metrology::analyze(rows);
            if let Some(m) = &m {
                if !m.absent.is_empty() {
                    let why: Vec<String> =
                        m.absent.iter().map(|(n, w)| format!("{n}: {w}")).collect();
                    absent.push(("metrology".into(), why.join("; ")));
                }
            }
            m
        } else {
            None
        };
        let hold = if rows.iter().any(|r| r.hold_t_s.is_some()) {
            let h = hold::analyze(rows);
            if h.is_none() {
                absent.push((
                    "hold".into(),
                    format!("{n_rows}: a creep slope needs three or more hold samples at different hold_t_s"),
                ));
            }
            h
        } else {
            None
        };
        let timing = timing::analyze(&run.rows);
        if timing.is_none() {
            absent.push(("timing".into(), format!("{n_rows}: nothing was timed")));
        }
        let mut out = RunAnalysis {
            magnitude,
            angle,
            spatial,
            displacement,
            timing,
            tracking: tracking::analyze(&run.rows, run.plan.quality.min_ok_fraction),
            metrology,
            hold,
            snapshot: None,
            absent,
            missing,
            run,
        };
        out.snapshot = out.load_snapshot(options.snapshot_index)?;
        Ok(out)
    }

    /// The field figures' setpoint; `None` (and a line in [`RunAnalysis::missing`])
    /// when its displacements file is not in the run directory.
    fn load_snapshot(
        &mut self,
        requested: Option<usize>,
    ) -> Result<Option<Snapshot>, AnalysisError> {
        let run = &self.run;
        let index = match requested {
            Some(i) => {
                if !run.rows.iter().any(|r| r.index == i) {
                    return Err(AnalysisError::Insufficient {
                        path: run.dir.clone(),
                        message: format!(
                            "setpoint {i} requested for the field figures is not in the journal ({} rows)",
                            run.rows.len()
                        ),
                    });
                }
                i
            }
            None => match run.rows.iter().max_by(|a, b| {
                let m = |r: &JournalRow| r.fsum_x_n.hypot(r.fsum_y_n).hypot(r.fsum_z_n);
                m(a).total_cmp(&m(b))
            }) {
                Some(r) => r.index,
                None => return Ok(None),
            },
        };
        let mut frames = match run.displacements(index) {
            Ok(f) => f,
            Err(e) => match missing_file(&e) {
                Some(m) => {
                    self.missing
                        .push(format!("marker displacement and force-field figures: {m}"));
                    return Ok(None);
                }
                None => return Err(e),
            },
        };
        if frames.is_empty() {
            return Ok(None);
        }
        let displacements = frames.swap_remove(0);
        let forces = if !forces_path(&run.dir, index).is_file() {
            if !matches!(run.plan.sweep, Sweep::Displacement { .. }) {
                self.missing.push(format!(
                    "force-field figure: {} (reconstructed forces of setpoint {index}) is not in the run directory",
                    forces_path(&run.dir, index).display()
                ));
            }
            None
        } else {
            Some(run.forces(index)?)
        };
        Ok(Some(Snapshot {
            index,
            displacements,
            forces,
        }))
    }

    /// Every scalar result, in the order of [`METRICS`]: the run's counts, then each
    /// analysis the run has, in a fixed order.
    pub fn metrics(&self) -> Vec<Metric> {
        let mut v = Vec::new();
        run_metrics(&mut v, &self.run);
        if let Some(m) = &self.magnitude {
            magnitude_metrics(&mut v, m);
        }
        if let Some(m) = &self.metrology {
            metrology_metrics(&mut v, m);
        }
        if let Some(a) = &self.angle {
            angle_metrics(&mut v, a);
        }
        if let Some(h) = &self.hold {
            hold_metrics(&mut v, h, self.metrology.is_none());
        }
        if let Some(s) = &self.spatial {
            push(&mut v, "spatial.fwhm_mm".into(), s.fwhm_mm, "mm");
            push(
                &mut v,
                "spatial.peak_offset_mm".into(),
                s.peak_distance_mm,
                "mm",
            );
            push(
                &mut v,
                "spatial.line_offset_mm".into(),
                s.line_offset_mm,
                "mm",
            );
        }
        if let Some(d) = &self.displacement {
            displacement_metrics(&mut v, d);
        }
        if let Some(t) = &self.timing {
            timing_metrics(&mut v, t);
        }
        if let Some(t) = &self.tracking {
            tracking_metrics(&mut v, t);
        }
        v
    }
}

/// Appends the metric `name` without a CI.
fn push(v: &mut Vec<Metric>, name: String, value: f64, unit: &'static str) {
    v.push(Metric::new(name, value, unit));
}

/// A Student-t interval `(lo, hi)` scaled by `k` (ordered again when `k < 0`).
fn ci_t(ci: Option<(f64, f64)>, k: f64) -> Option<Ci95> {
    ci.map(|(lo, hi)| Ci95 {
        low: (lo * k).min(hi * k),
        high: (lo * k).max(hi * k),
        method: "t",
    })
}

/// A chi-squared interval `(lo, hi)` of an SD scaled by `k`.
fn ci_chi2(ci: Option<(f64, f64)>, k: f64) -> Option<Ci95> {
    ci.map(|(lo, hi)| Ci95 {
        low: lo * k,
        high: hi * k,
        method: "chi2",
    })
}

/// The run's rows, unsettled rows, and (only when there are some: runs without them
/// keep their metric list) failed and implausible rows.
fn run_metrics(v: &mut Vec<Metric>, run: &RunData) {
    push(v, "run.rows".into(), run.rows.len() as f64, "count");
    let unsettled = run.rows.iter().filter(|r| !r.settled).count();
    push(v, "run.unsettled".into(), unsettled as f64, "count");
    // Only when there are some: runs without them keep their metric list.
    if !run.failed.is_empty() {
        push(
            v,
            "run.failed_rows".into(),
            run.failed.len() as f64,
            "count",
        );
    }
    let implausible = run.rows.iter().filter(|r| r.implausible()).count();
    if implausible > 0 {
        push(
            v,
            "run.implausible_rows".into(),
            implausible as f64,
            "count",
        );
    }
}

/// Fig. 7: the calibration line with its CIs, residual SD, resolution (N and gf) and
/// how it was found, linearity and hysteresis.
fn magnitude_metrics(v: &mut Vec<Metric>, m: &magnitude::MagnitudeAnalysis) {
    let c = &m.calibration;
    let gf = crate::units::n_to_gf(1.0);
    v.push(Metric::new("magnitude.slope", c.fit.slope, "1").with_ci(ci_t(c.fit.slope_ci95(), 1.0)));
    v.push(
        Metric::new("magnitude.offset_n", c.fit.offset, "N")
            .with_ci(ci_t(c.fit.offset_ci95(), 1.0)),
    );
    v.push(Metric::new("magnitude.r2", c.fit.r2, "1"));
    v.push(
        Metric::new("magnitude.residual_sd_n", c.pooled_sd, "N")
            .with_ci(ci_chi2(stats::sd_ci95(c.pooled_sd, c.pooled_dof), 1.0)),
    );
    let max_sd = c.levels.iter().fold(0.0f64, |a, l| a.max(l.residual_sd));
    v.push(Metric::new("magnitude.max_level_sd_n", max_sd, "N"));
    v.push(
        Metric::new("magnitude.resolution_n", c.resolution, "N")
            .with_ci(ci_chi2(c.resolution_ci95(), 1.0)),
    );
    v.push(
        Metric::new("magnitude.resolution_gf", c.resolution * gf, "gf")
            .with_ci(ci_chi2(c.resolution_ci95(), gf)),
    );
    v.push(Metric::new(
        "magnitude.resolution_method",
        c.resolution_method.code(),
        "1",
    ));
    v.push(Metric::new("magnitude.linearity_pct", c.linearity_pct, "%"));
    if let Some(h) = c.hysteresis_pct {
        v.push(Metric::new("magnitude.hysteresis_pct", h, "%"));
    }
}

/// ISO 376 style: full scale, the estimates in % of full scale with their CIs, the
/// largest zero error, the class.
fn metrology_metrics(v: &mut Vec<Metric>, m: &metrology::MetrologyAnalysis) {
    v.push(Metric::new("metrology.full_scale_n", m.full_scale_n, "N"));
    let mut est = |name: &str, e: &Option<metrology::Estimate>| {
        if let Some(e) = e {
            v.push(Metric::new(name, e.pct_fs, "%FS").with_ci(e.ci95));
        }
    };
    est("metrology.repeatability_pct_fs", &m.repeatability);
    est("metrology.reproducibility_pct_fs", &m.reproducibility);
    est("metrology.interpolation_pct_fs", &m.interpolation);
    est("metrology.zero_pct_fs", &m.zero);
    est("metrology.reversibility_pct_fs", &m.reversibility);
    if let Some(z) = m.zero_max_pct_fs {
        v.push(Metric::new("metrology.zero_max_pct_fs", z, "%FS"));
    }
    if let Some(c) = &m.class {
        v.push(Metric::new("metrology.class", c.code, "1"));
    }
}

/// Fig. 8: bias and SD of the measured angle with their CIs, bias against the
/// target, resolution and how it was found, the calibration line.
fn angle_metrics(v: &mut Vec<Metric>, a: &angle::AngleAnalysis) {
    let c = &a.calibration;
    let e: Vec<f64> = a
        .pairs
        .iter()
        .map(|p| p.measured_deg - p.applied_deg)
        .collect();
    v.push(
        Metric::new("angle.bias_deg", a.bias_deg, "deg").with_ci(ci_t(stats::mean_ci95(&e), 1.0)),
    );
    v.push(
        Metric::new("angle.sd_deg", a.sd_deg, "deg").with_ci(ci_chi2(
            stats::sd_ci95(a.sd_deg, e.len().saturating_sub(1)),
            1.0,
        )),
    );
    v.push(Metric::new(
        "angle.bias_vs_target_deg",
        a.bias_vs_target_deg,
        "deg",
    ));
    v.push(
        Metric::new("angle.resolution_deg", c.resolution, "deg")
            .with_ci(ci_chi2(c.resolution_ci95(), 1.0)),
    );
    v.push(Metric::new(
        "angle.resolution_method",
        c.resolution_method.code(),
        "1",
    ));
    v.push(Metric::new("angle.slope", c.fit.slope, "1").with_ci(ci_t(c.fit.slope_ci95(), 1.0)));
    v.push(Metric::new("angle.r2", c.fit.r2, "1"));
    v.push(Metric::new("angle.linearity_pct", c.linearity_pct, "%"));
}

/// Creep: full scale, creep and the F/T's own drift in % of full scale per minute,
/// zero drift (N and % of full scale), and the class when no metrology analysis
/// gave one (`class_from_hold`).
fn hold_metrics(v: &mut Vec<Metric>, h: &hold::HoldAnalysis, class_from_hold: bool) {
    v.push(Metric::new("hold.full_scale_n", h.full_scale_n, "N"));
    v.push(
        Metric::new(
            "hold.creep_pct_fs_per_min",
            h.creep_pct_fs_per_min(),
            "%FS/min",
        )
        .with_ci(h.creep_ci95()),
    );
    if let Some(ft) = &h.ft_drift {
        let ci = ft.ci95.map(|(lo, hi)| Ci95 {
            low: h.pct_fs_per_min(lo),
            high: h.pct_fs_per_min(hi),
            method: "t",
        });
        v.push(
            Metric::new(
                "hold.ft_drift_pct_fs_per_min",
                h.pct_fs_per_min(ft.slope),
                "%FS/min",
            )
            .with_ci(ci),
        );
    }
    if let Some(d) = h.zero_drift_n() {
        let ci = h.zero_drift_ci95();
        let k = 100.0 / h.full_scale_n;
        v.push(Metric::new("hold.zero_drift_n", d, "N").with_ci(ci));
        v.push(
            Metric::new("hold.zero_drift_pct_fs", d * k, "%FS").with_ci(ci.map(|c| Ci95 {
                low: c.low * k,
                high: c.high * k,
                method: c.method,
            })),
        );
    }
    if class_from_hold {
        if let Some(c) = &h.class {
            v.push(Metric::new("metrology.class", c.code, "1"));
        }
    }
}

/// Table I: per layer and axis mean, SD and bias of the displacement; the largest SD
/// and |bias|.
fn displacement_metrics(v: &mut Vec<Metric>, d: &displacement::DisplacementAnalysis) {
    for a in &d.axes {
        let base = format!("displacement.{}.{}", a.layer, a.axis);
        push(v, format!("{base}.mean_px"), a.mean_px, "px");
        push(v, format!("{base}.sd_px"), a.sd_px, "px");
        push(v, format!("{base}.bias_px"), a.bias_px, "px");
        push(v, format!("{base}.sd_mm"), a.sd_mm, "mm");
    }
    let max_sd = d.axes.iter().fold(0.0f64, |m, a| m.max(a.sd_px));
    let max_bias = d.axes.iter().fold(0.0f64, |m, a| m.max(a.bias_px.abs()));
    push(v, "displacement.max_sd_px".into(), max_sd, "px");
    push(v, "displacement.max_abs_bias_px".into(), max_bias, "px");
}

/// Table II: mean per-frame times of the stages (NaN where a stage was not timed),
/// the longest forces time.
fn timing_metrics(v: &mut Vec<Metric>, t: &timing::TimingAnalysis) {
    let ms = |s: &str| t.stage(s).map_or(f64::NAN, |s| s.mean_s * 1e3);
    push(v, "timing.tracking_ms".into(), ms("tracking"), "ms");
    push(
        v,
        "timing.reconstruction_ms".into(),
        ms("reconstruction"),
        "ms",
    );
    push(v, "timing.forces_ms".into(), ms("forces"), "ms");
    let max = t.stage("forces").map_or(f64::NAN, |s| s.max_s * 1e3);
    push(v, "timing.forces_max_ms".into(), max, "ms");
    push(v, "timing.rest_ms".into(), ms("rest"), "ms");
}

/// Marker health: the fractions of markers ok, flagged and re-acquired rows.
fn tracking_metrics(v: &mut Vec<Metric>, t: &tracking::TrackingAnalysis) {
    push(
        v,
        "tracking.min_ok_fraction".into(),
        t.min_ok_fraction(),
        "1",
    );
    push(
        v,
        "tracking.mean_ok_fraction".into(),
        t.mean_ok_fraction(),
        "1",
    );
    push(
        v,
        "tracking.flagged_rows".into(),
        t.flagged().count() as f64,
        "count",
    );
    push(
        v,
        "tracking.reacquired_rows".into(),
        t.reacquired_rows() as f64,
        "count",
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metric_names_match_their_patterns() {
        assert!(is_known_metric("magnitude.r2"));
        assert!(is_known_metric("displacement.red.x.sd_px"));
        assert!(!is_known_metric("displacement.red.z.sd_px"));
        assert!(!is_known_metric("magnitude.r3"));
        assert!(!is_known_metric("displacement..x.sd_px"));
    }
}
