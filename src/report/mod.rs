//! Reports: plots (plotters), the self-contained HTML report and acceptance verdicts.
//!
//! [`plot`] is the shared figure output used by reports and studies: one drawing
//! routine per figure, written to PNG and SVG from the same code. [`figures`] holds the
//! report's figures, [`html`] the HTML page, [`acceptance`] the criteria file and its
//! verdicts, [`verdict`] the run's overall outcome and `verdict.json`, [`fit_page`] the
//! `fit.html` page of a sensor-model fit. [`write_report`]
//! puts them together for one analysed run directory:
//!
//! ```text
//! RUN_DIR/report.html          self-contained (PNG figures embedded as data URIs),
//!                              opening with the verdict banner
//! RUN_DIR/verdict.json         outcome, criteria, run state, provenance (README schema)
//! RUN_DIR/summary.csv          metric,value,unit,ci95_low,ci95_high,ci_method (every metric
//!                              of the run; the CI columns empty where none is stated)
//! RUN_DIR/plots/STEM.png|svg   each figure
//! ```
//!
//! A report only adds these files: it never changes the run's own record (manifest,
//! journal, frames), so it can run while the run is still going, or on a torn journal.

pub mod acceptance;
pub mod archive;
pub mod compare;
pub mod evidence;
pub mod figures;
pub mod figures_metrology;
pub mod fit_page;
pub mod force_map;
pub mod headline;
pub mod html;
pub mod markup;
pub mod plot;
pub mod sha256;
pub mod study_plots;
pub mod verdict;

use std::path::{Path, PathBuf};

use thiserror::Error;

use crate::analysis::{Metric, RunAnalysis};
use crate::bench::lock::LockState;
use acceptance::{AcceptanceError, Criteria, Outcome, RunFit, Verdict};
use figures::{CalibrationFigure, MarkerHealthFigure, ProfileFigure, QuiverFigure};
use figures_metrology::{CreepFigure, HysteresisFigure, ResidualFigure};
use force_map::ForceMapFigure;
use plot::{Figure, FigureFiles, FigureResult, PlotError};
use verdict::{RunState, VerdictDoc, VERDICT_FILE};

/// File name of the HTML report inside the run directory.
pub const REPORT_FILE: &str = "report.html";
/// File name of the metric summary inside the run directory.
pub const SUMMARY_FILE: &str = "summary.csv";
/// Folder of the figure files inside the run directory.
pub const PLOTS_DIR: &str = "plots";

/// Figure size in pixels (PNG) / user units (SVG).
const FIGURE_SIZE: (u32, u32) = (900, 680);

/// An error writing a report.
#[derive(Debug, Error)]
pub enum ReportError {
    /// Drawing or writing a figure failed.
    #[error(transparent)]
    Plot(#[from] PlotError),
    /// The criteria do not apply to this run.
    #[error(transparent)]
    Acceptance(#[from] AcceptanceError),
    /// Writing a report file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
}

/// What [`write_report`] wrote and decided.
#[derive(Debug, Clone)]
pub struct ReportOutcome {
    /// `report.html`.
    pub html: PathBuf,
    /// `summary.csv`.
    pub summary: PathBuf,
    /// `verdict.json`.
    pub verdict_file: PathBuf,
    /// The overall verdict (also in `verdict.json`).
    pub verdict: VerdictDoc,
    /// The figure files.
    pub figures: Vec<FigureFiles>,
    /// The run's metrics.
    pub metrics: Vec<Metric>,
    /// Verdicts (empty without criteria).
    pub verdicts: Vec<Verdict>,
}

impl ReportOutcome {
    /// The overall outcome.
    pub fn outcome(&self) -> Outcome {
        self.verdict.outcome
    }
}

/// How to judge a run.
#[derive(Debug, Clone)]
pub struct ReportOptions {
    /// Grade a run that did not measure its whole plan (else it is INCOMPLETE).
    pub allow_partial: bool,
    /// Whether a live writer holds the run ([`crate::bench::lock::probe`]).
    pub lock: LockState,
}

impl Default for ReportOptions {
    fn default() -> Self {
        ReportOptions {
            allow_partial: false,
            lock: LockState::NoLockFile,
        }
    }
}

/// Any of the report's figures (the [`Figure`] trait is generic, so not object safe).
#[derive(Debug, Clone)]
pub enum ReportFigure {
    /// Fig. 7 / 8.
    Calibration(CalibrationFigure),
    /// Fig. 9.
    Profile(ProfileFigure),
    /// Fig. 4.
    Quiver(QuiverFigure),
    /// Fig. 5.
    ForceField(ForceMapFigure),
    /// Marker health per setpoint.
    MarkerHealth(MarkerHealthFigure),
    /// Measured − applied per trial.
    Residual(ResidualFigure),
    /// Up and down branches.
    Hysteresis(HysteresisFigure),
    /// Creep through the holds.
    Creep(CreepFigure),
}

impl Figure for ReportFigure {
    fn draw<DB: plotters::prelude::DrawingBackend>(
        &self,
        root: &plotters::prelude::DrawingArea<DB, plotters::coord::Shift>,
    ) -> FigureResult<DB> {
        match self {
            ReportFigure::Calibration(f) => f.draw(root),
            ReportFigure::Profile(f) => f.draw(root),
            ReportFigure::Quiver(f) => f.draw(root),
            ReportFigure::ForceField(f) => f.draw(root),
            ReportFigure::MarkerHealth(f) => f.draw(root),
            ReportFigure::Residual(f) => f.draw(root),
            ReportFigure::Hysteresis(f) => f.draw(root),
            ReportFigure::Creep(f) => f.draw(root),
        }
    }
}

impl ReportFigure {
    /// The figure's size in pixels.
    pub fn size_px(&self) -> (u32, u32) {
        match self {
            ReportFigure::ForceField(f) => f.size_px(),
            _ => FIGURE_SIZE,
        }
    }
}

/// The figures of an analysed run: `(file stem, caption, figure)`.
pub fn run_figures(analysis: &RunAnalysis) -> Vec<(String, String, ReportFigure)> {
    let run = &analysis.run;
    let unit = run.plan.force_unit;
    let u = unit.symbol();
    let mut out = Vec::new();
    if let Some(m) = &analysis.magnitude {
        out.push((
            "magnitude".to_string(),
            format!("Applied against measured normal force ({u}), level means ± 1 SD and least-squares fit (paper Fig. 7)"),
            ReportFigure::Calibration(CalibrationFigure {
                title: "force magnitude".into(),
                x_label: format!("applied Fz, F/T sensor ({u})"),
                y_label: format!("measured Fz sum ({u})"),
                display_scale: unit.from_newtons(1.0),
                unit: u.to_string(),
                calibration: m.calibration.clone(),
                samples: m.pairs.iter().map(|p| (p.applied_n, p.measured_n)).collect(),
            }),
        ));
    }
    let k = unit.from_newtons(1.0);
    if let Some(m) = &analysis.metrology {
        out.push((
            "residuals".to_string(),
            format!("Measured − applied (F^sum − F/T, {u}) against applied force, one colour per trial; circles loading, triangles unloading; dashed: the calibration line's own error"),
            ReportFigure::Residual(ResidualFigure {
                metrology: m.clone(),
                scale: k,
                unit: u.to_string(),
            }),
        ));
        if m.levels.iter().any(|l| l.reversibility_n().is_some()) {
            out.push((
                "hysteresis".to_string(),
                format!(
                    "Hysteresis loop: F^sum against applied ({u}), level means of the loading and unloading branches; below, unloading − loading mean residual per level (reversibility {} %FS)",
                    m.reversibility.map_or("-".to_string(), |e| acceptance::fmt_value(e.pct_fs))
                ),
                ReportFigure::Hysteresis(HysteresisFigure {
                    metrology: m.clone(),
                    scale: k,
                    unit: u.to_string(),
                }),
            ));
        }
    }
    if let Some(h) = &analysis.hold {
        out.push((
            "creep".to_string(),
            format!(
                "Creep during {} hold(s): F/T and F^sum ({u}) against time since the hold force was reached (top); F^sum − F/T with the fitted creep line, {} %FS/min, FS = {} {u} (bottom)",
                h.holds,
                acceptance::fmt_value(h.creep_pct_fs_per_min()),
                acceptance::fmt_value(h.full_scale_n * k)
            ),
            ReportFigure::Creep(CreepFigure {
                hold: h.clone(),
                scale: k,
                unit: u.to_string(),
            }),
        ));
    }
    if let Some(a) = &analysis.angle {
        out.push((
            "angle".to_string(),
            "Applied against measured angle from the normal (deg), level means ± 1 SD and fit (paper Fig. 8)".to_string(),
            ReportFigure::Calibration(CalibrationFigure {
                title: "force angle from the normal".into(),
                x_label: "applied angle, F/T sensor (deg)".into(),
                y_label: "measured angle, F sum (deg)".into(),
                display_scale: 1.0,
                unit: "deg".into(),
                calibration: a.calibration.clone(),
                samples: a.pairs.iter().map(|p| (p.applied_deg, p.measured_deg)).collect(),
            }),
        ));
    }
    if let Some(s) = &analysis.spatial {
        out.push((
            "spatial_profile".to_string(),
            format!(
                "Normalised fz profile of the subdivided point loads; FWHM {} mm (paper Fig. 9)",
                acceptance::fmt_value(s.fwhm_mm)
            ),
            ReportFigure::Profile(ProfileFigure { spatial: s.clone() }),
        ));
    }
    if let Some(snap) = &analysis.snapshot {
        out.push((
            "displacements".to_string(),
            format!(
                "Tracked marker displacements of setpoint {} by layer (paper Fig. 4)",
                snap.index
            ),
            ReportFigure::Quiver(QuiverFigure {
                title: format!("marker displacements, setpoint {}", snap.index),
                sensor: run.sensor.clone(),
                frame: snap.displacements.clone(),
            }),
        ));
    }
    if let Some(evidence::ForceField::Map(fig)) = evidence::force_field(analysis) {
        let why = match &fig.sd {
            Some(_) => None,
            None => evidence::why_no_sd(analysis),
        };
        out.push((
            "force_field".to_string(),
            evidence::force_map_caption(&fig, why.as_deref()),
            ReportFigure::ForceField(*fig),
        ));
    }
    if let Some(t) = &analysis.tracking {
        out.push((
            "marker_health".to_string(),
            format!(
                "Fraction of the sensor's markers ok / outlier / merged / lost per setpoint (ok = ok in every frame); dashed: [quality] min_ok_fraction {}; {} flagged row(s) marked with a red cross",
                t.gate,
                t.flagged().count()
            ),
            ReportFigure::MarkerHealth(MarkerHealthFigure {
                tracking: t.clone(),
            }),
        ));
    }
    out
}

/// Writes `report.html`, `verdict.json`, `summary.csv` and `plots/` into the analysed
/// run's directory and judges `criteria` (if any) against its metrics.
pub fn write_report(
    analysis: &RunAnalysis,
    criteria: Option<&Criteria>,
    options: &ReportOptions,
) -> Result<ReportOutcome, ReportError> {
    write_report_to(analysis, criteria, options, &analysis.run.dir)
}

/// As [`write_report`], into `out_dir` (created if missing). The run's fit is
/// `RUN_DIR/fit.json` when it exists ([`RunFit::load`]; an invalid one is an error).
pub fn write_report_to(
    analysis: &RunAnalysis,
    criteria: Option<&Criteria>,
    options: &ReportOptions,
    out_dir: &Path,
) -> Result<ReportOutcome, ReportError> {
    let fit = RunFit::load(&analysis.run.dir, None)?;
    write_report_with_fit(analysis, criteria, options, out_dir, &fit)
}

/// As [`write_report_to`] with the run's fit given (`report --fit FILE`): its fitted
/// parameters join the metrics as `fit.<NAME>` and criteria on them are judged on it.
pub fn write_report_with_fit(
    analysis: &RunAnalysis,
    criteria: Option<&Criteria>,
    options: &ReportOptions,
    out_dir: &Path,
    fit: &RunFit,
) -> Result<ReportOutcome, ReportError> {
    let mut metrics = analysis.metrics();
    metrics.extend(fit.metrics());
    // Judge first: a criterion the run cannot answer is an error before anything is
    // written.
    let verdicts = match criteria {
        Some(c) => c.evaluate_with_fit(
            &metrics,
            analysis.run.sweep_kind(),
            &analysis.absent,
            None,
            Some(fit),
        )?,
        None => Vec::new(),
    };
    let state = RunState::of(analysis, &options.lock);
    let verdict = VerdictDoc::judge(analysis, criteria, &verdicts, state, options.allow_partial)
        .with_metrics(&metrics);
    std::fs::create_dir_all(out_dir).map_err(|source| ReportError::Io {
        path: out_dir.to_path_buf(),
        source,
    })?;
    let plots = out_dir.join(PLOTS_DIR);
    let mut files = Vec::new();
    let mut embedded = Vec::new();
    for (stem, caption, fig) in run_figures(analysis) {
        let f = plot::save_figure(&fig, &plots, &stem, fig.size_px())?;
        let png = std::fs::read(&f.png).map_err(|source| ReportError::Io {
            path: f.png.clone(),
            source,
        })?;
        embedded.push(html::EmbeddedFigure { stem, caption, png });
        files.push(f);
    }
    let summary = out_dir.join(SUMMARY_FILE);
    // Through the csv writer: layer names in metric names come from the sensor file.
    let csv_err = |e: csv::Error| ReportError::Io {
        path: summary.clone(),
        source: std::io::Error::other(e.to_string()),
    };
    let mut w = csv::Writer::from_writer(Vec::new());
    w.write_record([
        "metric",
        "value",
        "unit",
        "ci95_low",
        "ci95_high",
        "ci_method",
    ])
    .map_err(csv_err)?;
    for m in &metrics {
        let (low, high, method) = match m.ci95 {
            Some(ci) => (
                crate::formats::Num(ci.low).to_string(),
                crate::formats::Num(ci.high).to_string(),
                ci.method,
            ),
            None => (String::new(), String::new(), ""),
        };
        w.write_record([
            m.name.as_str(),
            &crate::formats::Num(m.value).to_string(),
            m.unit,
            &low,
            &high,
            method,
        ])
        .map_err(csv_err)?;
    }
    let bytes = w.into_inner().map_err(|e| csv_err(e.into_error().into()))?;
    write(&summary, &bytes)?;
    let force_note = match evidence::force_field(analysis) {
        Some(evidence::ForceField::Absent(why)) => Some(why),
        _ => None,
    };
    let camera = evidence::camera_evidence(analysis);
    let (sections, _camera_files) =
        evidence::write_sections(&plots, force_note.as_deref(), &camera)
            .map_err(|(path, source)| ReportError::Io { path, source })?;
    let criteria_path = criteria.map(|c| c.path.display().to_string());
    let page = html::render(
        analysis,
        &verdict,
        &metrics,
        criteria.map(|_| verdicts.as_slice()),
        criteria_path.as_deref(),
        &embedded,
        &sections,
    );
    let html_path = out_dir.join(REPORT_FILE);
    write(&html_path, page.as_bytes())?;
    let verdict_file = out_dir.join(VERDICT_FILE);
    let json = serde_json::to_string_pretty(&verdict).map_err(|e| ReportError::Io {
        path: verdict_file.clone(),
        source: std::io::Error::other(e.to_string()),
    })?;
    write(&verdict_file, format!("{json}\n").as_bytes())?;
    Ok(ReportOutcome {
        html: html_path,
        summary,
        verdict_file,
        verdict,
        figures: files,
        metrics,
        verdicts,
    })
}

fn write(path: &Path, bytes: &[u8]) -> Result<(), ReportError> {
    std::fs::write(path, bytes).map_err(|source| ReportError::Io {
        path: path.to_path_buf(),
        source,
    })
}
