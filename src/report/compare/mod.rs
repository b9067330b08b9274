//! Build-to-build comparison (`tactbench compare RUN_DIR... [--baseline RUN_DIR]
//! [--acceptance CRITERIA.toml] --out DIR`): several analysed run directories side by
//! side against one baseline run.
//!
//! ```text
//! DIR/compare.html            self-contained (figures embedded as PNG data URIs)
//! DIR/compare.csv             one row per (metric, run), columns in CSV_HEADER
//! DIR/plots/compare_*.png|svg trends over the runs; applied-vs-measured overlays
//! ```
//!
//! **Difference and significance.** For a metric with value `v` (CI `[l, h]`) in a
//! run and `b` (CI `[lb, hb]`) in the baseline, the difference is `d = v - b` and
//! `d_pct = 100 d / |b|`. Each 95 % CI gives a standard error `SE = (h - l) / 2 /
//! 1.96` (half-width / z_0.975; an asymmetric interval is taken by its mean
//! half-width), and, the two runs being independent measurements, the difference's
//! 95 % CI is `d ± 1.96 sqrt(SE² + SE_b²)` (normal approximation). The difference is
//! **significant** when that interval excludes 0. This is less conservative than
//! asking the two CIs not to overlap (which amounts to a test at about the 0.6 %
//! level). A metric without a CI in either run is `n/a`, never significant.
//!
//! **Worse.** [`better`] gives, per metric name, which direction is better (lower,
//! higher, or closer to a target value); the run whose value is furthest on the bad
//! side is named the worst for that metric ([`worst_run`]); metrics without a
//! direction (counts of rows, mean displacements) name none.
//!
//! **Outcome and exit code.** Absolute criteria apply to every run as in `report`;
//! bounds relative to the baseline ([`super::acceptance`]) apply to the other runs.
//! Each run gets a [`VerdictDoc`] as `report` would give it. The comparison's outcome
//! is decided by the runs other than the baseline: FAIL if any FAILs; else INCOMPLETE
//! if any is INCOMPLETE or the baseline itself did not measure its whole plan (the
//! relative limits come from it; `--allow-partial` grades partial runs); else NOT
//! JUDGED if any has a criterion nothing could judge (a fitted parameter without a
//! fit, or not identifiable: never PASS on it); else MARGINAL if any is MARGINAL; else
//! PASS. Without criteria (or when no compared run has
//! anything to judge) the outcome is NOT JUDGED (exit 0), never PASS. The baseline's own
//! criteria are shown, not counted; a baseline that FAILs its own absolute criteria is
//! flagged on the banner and in `compare.csv` (`baseline_outcome`): relative limits
//! taken from a failing run are no assurance.
//!
//! **Fitted parameters.** A run with a `fit.json` ([`RunFit`]) has its fitted,
//! identifiable parameters as metrics `fit.<NAME>`: compared, tabled and written to
//! `compare.csv` like the others (no better direction), trended in
//! `plots/compare_fit` against the nominal value, and judged by criteria on them.
//!
//! **Like for like.** Runs of different sweep kinds, plans (SHA-256 of the plan text in
//! the manifest) or sensors (SHA-256 of the sensor text) measure different things:
//! [`Comparison::new`] refuses them ([`CompareError::NotLikeForLike`], naming each
//! difference against the baseline) unless `allow_different_plans` is set, and then the
//! banner says so ([`Comparison::differences`]).

mod figures;
mod page;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use thiserror::Error;

pub use figures::{
    fit_trend_figure, OverlayCurve, OverlayFigure, TrendFigure, TrendPanel, TrendPoint, RUN_COLORS,
};

use super::acceptance::{fmt_value, AcceptanceError, Criteria, Outcome, RunFit, Verdict};
use super::plot::{FigureFiles, PlotError};
use super::verdict::{exit_code, RunState, VerdictDoc};
use crate::analysis::{AnalysisError, AnalysisOptions, Ci95, Metric, RunAnalysis};
use crate::bench::journal::{JOURNAL_FILE, MANIFEST_FILE};
use crate::bench::lock::{self, LockError, LockState};

/// File name of the comparison page in the output directory.
pub const COMPARE_HTML: &str = "compare.html";
/// File name of the comparison table in the output directory.
pub const COMPARE_CSV: &str = "compare.csv";
/// Folder of the figure files in the output directory.
pub const PLOTS_DIR: &str = "plots";

/// z quantile of a two-sided 95 % interval.
pub const Z95: f64 = 1.959_963_984_540_054;

/// The columns of `compare.csv` (a public contract: documented in the README).
pub const CSV_HEADER: [&str; 22] = [
    "metric",
    "unit",
    "run",
    "build_id",
    "date",
    "value",
    "ci95_low",
    "ci95_high",
    "ci_method",
    "baseline_value",
    "difference",
    "difference_pct",
    "significant",
    "criterion",
    "outcome",
    "role",
    "difference_ci95_low",
    "difference_ci95_high",
    "better",
    "worst",
    "simulated",
    "baseline_outcome",
];

/// An error comparing runs. Every variant names the run directory or file.
#[derive(Debug, Error)]
pub enum CompareError {
    /// Fewer than two distinct runs.
    #[error("compare needs at least two run directories (a baseline and a run to compare with it); got {given}")]
    TooFewRuns {
        /// Runs given (with the baseline).
        given: usize,
    },
    /// A path that is not a run directory.
    #[error("{dir}: not a run directory: {why}")]
    NotARun {
        /// The path as given.
        dir: PathBuf,
        /// What is missing.
        why: String,
    },
    /// The same run given twice.
    #[error("{first} and {second} are the same run ({why}); give each run once")]
    Duplicate {
        /// The first occurrence, as given.
        first: PathBuf,
        /// The second, as given.
        second: PathBuf,
        /// Same directory, or identical manifest and journal.
        why: &'static str,
    },
    /// Probing the run's lock failed.
    #[error("checking for a live writer of {dir}: {source}")]
    Lock {
        /// The run directory.
        dir: PathBuf,
        /// The lock error.
        source: Box<LockError>,
    },
    /// Loading or analysing a run failed.
    #[error("analysing run directory {dir}: {source}")]
    Analysis {
        /// The run directory.
        dir: PathBuf,
        /// The analysis error.
        source: Box<AnalysisError>,
    },
    /// The criteria do not apply to a run (or to the baseline).
    #[error("judging {dir}: {source}")]
    Acceptance {
        /// The run directory.
        dir: PathBuf,
        /// The criteria error.
        source: Box<AcceptanceError>,
    },
    /// Runs that do not measure the same thing (sweep kind, plan or sensor differ).
    #[error("the runs are not like for like: {}; compare runs of one plan on one sensor, or give --allow-different-plans to compare them anyway", .differences.join("; "))]
    NotLikeForLike {
        /// Each difference against the baseline, in words.
        differences: Vec<String>,
    },
    /// Drawing or writing a figure failed.
    #[error(transparent)]
    Plot(#[from] PlotError),
    /// Writing an output file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
}

/// One loaded run: its directory as given, the analysis and whether a writer is live.
#[derive(Debug, Clone)]
pub struct LoadedRun {
    /// The directory as given on the command line.
    pub dir: PathBuf,
    /// Its analysis.
    pub analysis: RunAnalysis,
    /// What [`lock::probe`] found before it was read.
    pub lock: LockState,
    /// Its `fit.json`, if it has one ([`RunFit::load`]).
    pub fit: RunFit,
}

/// Loads one run directory (as `report` does: lock probe first, then the analysis).
pub fn load_run(dir: &Path) -> Result<LoadedRun, CompareError> {
    if !dir.is_dir() {
        return Err(CompareError::NotARun {
            dir: dir.to_path_buf(),
            why: if dir.exists() {
                "not a directory".into()
            } else {
                "no such directory".into()
            },
        });
    }
    for f in [MANIFEST_FILE, JOURNAL_FILE] {
        if !dir.join(f).is_file() {
            return Err(CompareError::NotARun {
                dir: dir.to_path_buf(),
                why: format!("no {f} (written by `tactbench run`)"),
            });
        }
    }
    let lock = lock::probe(dir).map_err(|source| CompareError::Lock {
        dir: dir.to_path_buf(),
        source: Box::new(source),
    })?;
    let analysis = RunAnalysis::load(dir, &AnalysisOptions::default()).map_err(|source| {
        CompareError::Analysis {
            dir: dir.to_path_buf(),
            source: Box::new(source),
        }
    })?;
    let fit = RunFit::load(dir, None).map_err(|source| CompareError::Acceptance {
        dir: dir.to_path_buf(),
        source: Box::new(source),
    })?;
    Ok(LoadedRun {
        dir: dir.to_path_buf(),
        analysis,
        lock,
        fit,
    })
}

/// The run directories to compare, in order, and which is the baseline: `runs` as
/// given, and `baseline` (when given) either one of them (same directory) or an extra
/// run put first. Two entries naming the same directory, or two directories with
/// byte-identical `manifest.json` and `journal.csv` (a copy of a run), are an error.
pub fn plan_runs(
    runs: &[PathBuf],
    baseline: Option<&Path>,
) -> Result<(Vec<PathBuf>, usize), CompareError> {
    let mut dirs: Vec<PathBuf> = runs.to_vec();
    let canon = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    let mut base_index = 0;
    if let Some(b) = baseline {
        let cb = canon(b);
        match dirs.iter().position(|d| canon(d) == cb) {
            Some(i) => base_index = i,
            None => dirs.insert(0, b.to_path_buf()),
        }
    }
    for (i, d) in dirs.iter().enumerate() {
        for e in &dirs[..i] {
            if canon(d) == canon(e) {
                return Err(CompareError::Duplicate {
                    first: e.clone(),
                    second: d.clone(),
                    why: "the same directory",
                });
            }
        }
    }
    if dirs.len() < 2 {
        return Err(CompareError::TooFewRuns { given: dirs.len() });
    }
    // Before anything is analysed: a copied run is refused by name, not by whatever
    // the copy happens to lack.
    for (i, d) in dirs.iter().enumerate() {
        for e in &dirs[..i] {
            if same_record(e, d) {
                return Err(CompareError::Duplicate {
                    first: e.clone(),
                    second: d.clone(),
                    why: "identical manifest.json and journal.csv: a copy of one run",
                });
            }
        }
    }
    Ok((dirs, base_index))
}

/// Whether two loaded runs are copies of one record (identical manifest and journal).
fn same_record(a: &Path, b: &Path) -> bool {
    [MANIFEST_FILE, JOURNAL_FILE].iter().all(|f| {
        match (std::fs::read(a.join(f)), std::fs::read(b.join(f))) {
            (Ok(x), Ok(y)) => x == y,
            _ => false,
        }
    })
}

/// Which direction of a metric is better.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Better {
    /// Smaller values are better (resolution, SDs, errors, times, counts of problems).
    Lower,
    /// Larger values are better (R², fractions of markers ok).
    Higher,
    /// Values closer to this target are better (slope: 1; biases, offsets: 0).
    CloserTo(f64),
}

impl Better {
    /// `lower`, `higher`, `closer_to_1`, `closer_to_0` (the CSV's `better` column).
    pub fn word(self) -> String {
        match self {
            Better::Lower => "lower".into(),
            Better::Higher => "higher".into(),
            Better::CloserTo(t) => format!("closer_to_{}", fmt_value(t)),
        }
    }

    /// How bad `v` is: larger is worse.
    pub fn badness(self, v: f64) -> f64 {
        match self {
            Better::Lower => v,
            Better::Higher => -v,
            Better::CloserTo(t) => (v - t).abs(),
        }
    }
}

/// The direction table: which way is better for a metric name (`None`: undefined,
/// e.g. `run.rows` or a mean displacement). Rules in order (the README repeats them):
///
/// | metrics | better |
/// |---|---|
/// | `*.slope` | closer to 1 |
/// | `*.r2`, `*ok_fraction` | higher |
/// | `spatial.line_offset_mm`, `run.rows`, `*.mean_px`, `*_method`, `*full_scale*` | undefined |
/// | `*.class` (ISO 376 class code, 0 = class 00 ... 3 = outside class 2) | lower |
/// | names with `bias`, `offset`, `zero`, `creep`, `drift` (signed errors) | closer to 0 |
/// | `timing.*`, `run.unsettled`, `tracking.flagged_rows`, `tracking.reacquired_rows` | lower |
/// | names with `resolution`, `sd`, `linearity`, `hysteresis`, `fwhm`, `repeatab`, `reproducib`, `interpolation`, `reversib`, `error`, `uncertainty` | lower |
pub fn better(metric: &str) -> Option<Better> {
    let last = metric.rsplit('.').next().unwrap_or(metric);
    let words: Vec<&str> = metric.split(['.', '_']).collect();
    let has = |w: &str| words.contains(&w);
    let contains = |s: &str| metric.contains(s);
    if last == "slope" {
        return Some(Better::CloserTo(1.0));
    }
    if last == "r2" || last.ends_with("ok_fraction") {
        return Some(Better::Higher);
    }
    if metric == "spatial.line_offset_mm"
        || metric == "run.rows"
        || last == "mean_px"
        || last.ends_with("_method")
        || contains("full_scale")
    {
        return None;
    }
    if last == "class" {
        // ISO 376 class code: 0 (class 00), 0.5, 1, 2, 3 (outside class 2).
        return Some(Better::Lower);
    }
    if ["bias", "offset", "zero", "creep", "drift"]
        .iter()
        .any(|w| contains(w))
    {
        return Some(Better::CloserTo(0.0));
    }
    if metric.starts_with("timing.")
        || matches!(
            metric,
            "run.unsettled"
                | "run.failed_rows"
                | "run.implausible_rows"
                | "tracking.flagged_rows"
                | "tracking.reacquired_rows"
        )
    {
        return Some(Better::Lower);
    }
    if has("sd")
        || [
            "resolution",
            "linearity",
            "hysteresis",
            "fwhm",
            "repeatab",
            "reproducib",
            "interpolation",
            "reversib",
            "error",
            "uncertainty",
        ]
        .iter()
        .any(|w| contains(w))
    {
        return Some(Better::Lower);
    }
    None
}

/// Whether a difference to the baseline is significant.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Significance {
    /// The difference's 95 % CI excludes 0.
    Significant,
    /// It includes 0.
    NotSignificant,
    /// No CI in the run or the baseline (or no difference: the baseline itself).
    NotAvailable,
}

impl Significance {
    /// `yes`, `no`, `n/a` (the CSV's `significant` column).
    pub fn word(self) -> &'static str {
        match self {
            Significance::Significant => "yes",
            Significance::NotSignificant => "no",
            Significance::NotAvailable => "n/a",
        }
    }
}

/// The standard error a 95 % CI implies: its mean half-width / z_0.975 (`None` when
/// the bounds are not finite or reversed).
pub fn standard_error(ci: &Ci95) -> Option<f64> {
    let w = ci.high - ci.low;
    (w.is_finite() && w >= 0.0).then(|| w / 2.0 / Z95)
}

/// A run's difference to the baseline for one metric.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Difference {
    /// `value - baseline`.
    pub value: f64,
    /// `100 (value - baseline) / |baseline|` (`None` when the baseline is 0).
    pub pct: Option<f64>,
    /// 95 % CI of the difference, `d ± 1.96 sqrt(SE² + SE_b²)` (`None` without both
    /// CIs).
    pub ci95: Option<(f64, f64)>,
    /// Whether that CI excludes 0.
    pub significance: Significance,
}

/// The difference of `value` (CI `ci`) to `baseline` (CI `baseline_ci`), the two
/// taken as independent (see the module documentation).
pub fn difference(
    value: f64,
    ci: Option<&Ci95>,
    baseline: f64,
    baseline_ci: Option<&Ci95>,
) -> Difference {
    let d = value - baseline;
    let pct = (baseline != 0.0 && baseline.is_finite()).then(|| 100.0 * d / baseline.abs());
    let se = ci
        .and_then(standard_error)
        .zip(baseline_ci.and_then(standard_error));
    let ci95 = match se {
        Some((a, b)) if d.is_finite() => {
            let half = Z95 * a.hypot(b);
            Some((d - half, d + half))
        }
        _ => None,
    };
    let significance = match ci95 {
        Some((lo, hi)) if lo > 0.0 || hi < 0.0 => Significance::Significant,
        Some(_) => Significance::NotSignificant,
        None => Significance::NotAvailable,
    };
    Difference {
        value: d,
        pct,
        ci95,
        significance,
    }
}

/// The index of the worst of `values` (`None` entries have no value) for direction
/// `better`: the largest [`Better::badness`] among the finite values, when at least
/// two runs have one and the worst is unique (no worst among equals).
pub fn worst_run(values: &[Option<f64>], better: Better) -> Option<usize> {
    let finite: Vec<(usize, f64)> = values
        .iter()
        .enumerate()
        .filter_map(|(i, v)| v.filter(|v| v.is_finite()).map(|v| (i, better.badness(v))))
        .collect();
    if finite.len() < 2 {
        return None;
    }
    let max = finite
        .iter()
        .map(|&(_, b)| b)
        .fold(f64::NEG_INFINITY, f64::max);
    let at_max: Vec<usize> = finite
        .iter()
        .filter(|&&(_, b)| b == max)
        .map(|&(i, _)| i)
        .collect();
    (at_max.len() == 1).then(|| at_max[0])
}

/// One compared run.
#[derive(Debug, Clone)]
pub struct ComparedRun {
    /// The directory as given.
    pub dir: PathBuf,
    /// A short unique label (build id, else the directory name).
    pub label: String,
    /// Whether it is the baseline.
    pub is_baseline: bool,
    /// Its analysis.
    pub analysis: RunAnalysis,
    /// Its metrics, the fitted parameters (`fit.<NAME>`) included when it has a
    /// `fit.json`.
    pub metrics: Vec<Metric>,
    /// Its fit.
    pub fit: RunFit,
    /// Criteria verdicts (absolute bounds only for the baseline).
    pub verdicts: Vec<Verdict>,
    /// What `report` would decide for it (with the relative bounds).
    pub verdict: VerdictDoc,
}

impl ComparedRun {
    /// The run's metric `name`, if it has it.
    pub fn metric(&self, name: &str) -> Option<&Metric> {
        self.metrics.iter().find(|m| m.name == name)
    }

    /// The manifest's build id, if any.
    pub fn build_id(&self) -> Option<&str> {
        self.analysis
            .run
            .manifest
            .build_id
            .as_deref()
            .filter(|b| !b.trim().is_empty())
    }

    /// The manifest's start time (RFC 3339).
    pub fn date(&self) -> &str {
        &self.analysis.run.manifest.started_at
    }
}

/// One metric over every run.
#[derive(Debug, Clone)]
pub struct MetricComparison {
    /// The metric name.
    pub name: String,
    /// Its unit.
    pub unit: &'static str,
    /// Which way is better (`None`: undefined).
    pub better: Option<Better>,
    /// Per run (in [`Comparison::runs`] order): its difference to the baseline (`None`
    /// for the baseline itself and where either has no finite value).
    pub differences: Vec<Option<Difference>>,
    /// The worst run (index into [`Comparison::runs`]).
    pub worst: Option<usize>,
}

/// Several runs compared with a baseline.
#[derive(Debug, Clone)]
pub struct Comparison {
    /// The runs, in the order given (an extra `--baseline` first).
    pub runs: Vec<ComparedRun>,
    /// Index of the baseline in `runs`.
    pub baseline: usize,
    /// Every metric any run has, in first-seen order (baseline first).
    pub metrics: Vec<MetricComparison>,
    /// The criteria file, if any.
    pub criteria_file: Option<String>,
    /// The comparison's outcome (see the module documentation).
    pub outcome: Outcome,
    /// Its exit code (0, 1, 5).
    pub exit_code: u8,
    /// One line: the outcome and why.
    pub summary: String,
    /// Partial runs graded (`--allow-partial`).
    pub allow_partial: bool,
    /// How the runs differ from the baseline in sweep kind, plan or sensor (empty:
    /// like for like; non-empty only with `--allow-different-plans`).
    pub differences: Vec<String>,
    /// Each run's instruments as its manifest records them, in `runs` order.
    pub instruments: Vec<Instruments>,
    /// How the runs' instruments differ from the baseline's (F/T sensor, stage,
    /// camera), in words: warnings, the comparison is still made.
    pub instrument_differences: Vec<String>,
    /// Records that no longer match their digests ("modified after the run"), one
    /// line per finding, naming the run.
    pub record_warnings: Vec<String>,
}

/// A run's instruments: `(device, identity)` for the stage, the F/T sensor and the
/// camera, from the manifest's `devices` without what changes from session to
/// session on the same instrument (port, temperature, measured rate).
#[derive(Debug, Clone, PartialEq)]
pub struct Instruments {
    /// `(stage|force_sensor|camera, identity)`.
    pub devices: Vec<(String, String)>,
}

/// The identity of one instrument from its recorded `devices` entry.
pub fn instrument_identity(v: &serde_json::Value) -> String {
    const VOLATILE: [&str; 5] = ["port", "temperature_c", "measured_rate_hz", "cwd", "file"];
    match v {
        serde_json::Value::Null => "not recorded".into(),
        serde_json::Value::String(s) => s.clone(),
        serde_json::Value::Object(m) => {
            let parts: Vec<String> = m
                .iter()
                .filter(|(k, _)| !VOLATILE.contains(&k.as_str()))
                .map(|(k, v)| match v {
                    serde_json::Value::String(s) => format!("{k} {s}"),
                    other => format!("{k} {other}"),
                })
                .collect();
            parts.join(", ")
        }
        other => other.to_string(),
    }
}

impl Instruments {
    /// The instruments a manifest records.
    pub fn of(m: &crate::bench::journal::Manifest) -> Instruments {
        Instruments {
            devices: crate::bench::provenance::DEVICES
                .iter()
                .map(|d| {
                    (
                        d.to_string(),
                        instrument_identity(m.devices.get(*d).unwrap_or(&serde_json::Value::Null)),
                    )
                })
                .collect(),
        }
    }
}

/// How each run's instruments differ from the baseline's, in words.
fn instrument_differences(
    runs: &[ComparedRun],
    instruments: &[Instruments],
    baseline: usize,
) -> Vec<String> {
    let mut out = Vec::new();
    let b = &instruments[baseline];
    for (i, ins) in instruments.iter().enumerate() {
        if i == baseline {
            continue;
        }
        for ((device, id), (_, bid)) in ins.devices.iter().zip(&b.devices) {
            if id != bid {
                out.push(format!(
                    "{} used a different {} ({id}) from the baseline {} ({bid})",
                    runs[i].label,
                    device
                        .replace('_', " ")
                        .replace("force sensor", "F/T sensor"),
                    runs[baseline].label
                ));
            }
        }
    }
    out
}

/// Unique short labels: the build id, else the directory's name; repeated labels get
/// the directory name (or position) appended.
fn labels(loaded: &[LoadedRun]) -> Vec<String> {
    let dir_name = |d: &Path| {
        d.file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| d.display().to_string())
    };
    let base: Vec<String> = loaded
        .iter()
        .map(|r| {
            r.analysis
                .run
                .manifest
                .build_id
                .clone()
                .filter(|b| !b.trim().is_empty())
                .unwrap_or_else(|| dir_name(&r.dir))
        })
        .collect();
    let mut out = Vec::with_capacity(base.len());
    for (i, l) in base.iter().enumerate() {
        let repeated = base.iter().filter(|m| *m == l).count() > 1;
        let mut label = if repeated {
            format!("{l} ({})", dir_name(&loaded[i].dir))
        } else {
            l.clone()
        };
        if out.contains(&label) {
            label = format!("{label} #{}", i + 1);
        }
        out.push(label);
    }
    out
}

impl Comparison {
    /// Judges and compares loaded runs; `baseline` indexes `loaded`.
    pub fn new(
        loaded: Vec<LoadedRun>,
        baseline: usize,
        criteria: Option<&Criteria>,
        allow_partial: bool,
        allow_different_plans: bool,
    ) -> Result<Comparison, CompareError> {
        if loaded.len() < 2 {
            return Err(CompareError::TooFewRuns {
                given: loaded.len(),
            });
        }
        let differences = like_for_like(&loaded, baseline);
        if !differences.is_empty() && !allow_different_plans {
            return Err(CompareError::NotLikeForLike { differences });
        }
        for (i, a) in loaded.iter().enumerate() {
            for b in &loaded[..i] {
                if same_record(&a.dir, &b.dir) {
                    return Err(CompareError::Duplicate {
                        first: b.dir.clone(),
                        second: a.dir.clone(),
                        why: "identical manifest.json and journal.csv: a copy of one run",
                    });
                }
            }
        }
        let labels = labels(&loaded);
        let metrics_of = |l: &LoadedRun| {
            let mut m = l.analysis.metrics();
            m.extend(l.fit.metrics());
            m
        };
        let base_metrics = metrics_of(&loaded[baseline]);
        // The baseline is judged on the absolute bounds only.
        let base_criteria = criteria.map(|c| Criteria {
            criteria: c
                .criteria
                .iter()
                .filter_map(|k| k.absolute_part())
                .collect(),
            ..c.clone()
        });
        let mut runs = Vec::with_capacity(loaded.len());
        for (i, (l, label)) in loaded.into_iter().zip(labels).enumerate() {
            let metrics = metrics_of(&l);
            let is_baseline = i == baseline;
            let judge_err = |source| CompareError::Acceptance {
                dir: l.dir.clone(),
                source: Box::new(source),
            };
            let (crit, verdicts) = if is_baseline {
                let c = base_criteria.as_ref();
                let v = match c {
                    Some(c) => c
                        .evaluate_with_fit(
                            &metrics,
                            l.analysis.run.sweep_kind(),
                            &l.analysis.absent,
                            None,
                            Some(&l.fit),
                        )
                        .map_err(judge_err)?,
                    None => Vec::new(),
                };
                (c, v)
            } else {
                let v = match criteria {
                    Some(c) => c
                        .evaluate_with_fit(
                            &metrics,
                            l.analysis.run.sweep_kind(),
                            &l.analysis.absent,
                            Some(&base_metrics),
                            Some(&l.fit),
                        )
                        .map_err(judge_err)?,
                    None => Vec::new(),
                };
                (criteria, v)
            };
            let state = RunState::of(&l.analysis, &l.lock);
            let verdict = VerdictDoc::judge(&l.analysis, crit, &verdicts, state, allow_partial);
            runs.push(ComparedRun {
                dir: l.dir,
                label,
                is_baseline,
                analysis: l.analysis,
                metrics,
                fit: l.fit,
                verdicts,
                verdict,
            });
        }
        let metrics = compare_metrics(&runs, baseline);
        let (outcome, summary) = overall(&runs, baseline, criteria.is_some());
        let instruments: Vec<Instruments> = runs
            .iter()
            .map(|r| Instruments::of(&r.analysis.run.manifest))
            .collect();
        let instrument_differences = instrument_differences(&runs, &instruments, baseline);
        let record_warnings = runs
            .iter()
            .flat_map(|r| {
                r.verdict
                    .run
                    .record
                    .lines()
                    .into_iter()
                    .map(move |l| format!("{}: {l}", r.dir.display()))
            })
            .collect();
        Ok(Comparison {
            instruments,
            instrument_differences,
            record_warnings,
            exit_code: exit_code(outcome),
            runs,
            baseline,
            metrics,
            criteria_file: criteria.map(|c| c.path.display().to_string()),
            outcome,
            summary,
            allow_partial,
            differences,
        })
    }

    /// The force unit of the page (`compare.html`, its figures): the plans' force unit
    /// when every run's plan has the same one, else newtons. `compare.csv` keeps each
    /// metric's own unit, as `summary.csv` does.
    pub fn force_unit(&self) -> crate::units::ForceUnit {
        let mut units = self.runs.iter().map(|r| r.analysis.run.plan.force_unit);
        match units.next() {
            Some(u) if units.all(|v| v == u) => u,
            _ => crate::units::ForceUnit::Newton,
        }
    }

    /// The baseline run.
    pub fn baseline_run(&self) -> &ComparedRun {
        &self.runs[self.baseline]
    }

    /// Run indices sorted by start date (then given order): the trend plots' x axis.
    pub fn date_order(&self) -> Vec<usize> {
        let mut order: Vec<usize> = (0..self.runs.len()).collect();
        order.sort_by(|&a, &b| self.runs[a].date().cmp(self.runs[b].date()).then(a.cmp(&b)));
        order
    }
}

/// How each run differs from the baseline in sweep kind, plan or sensor, in words
/// (empty when every run measures the same plan on the same sensor).
pub fn like_for_like(loaded: &[LoadedRun], baseline: usize) -> Vec<String> {
    let key = |r: &LoadedRun| {
        let run = &r.analysis.run;
        let m = &run.manifest;
        (
            run.sweep_kind(),
            super::sha256::sha256_hex(m.plan_toml.as_bytes()),
            super::sha256::sha256_hex(m.sensor_toml.as_bytes()),
        )
    };
    let b = &loaded[baseline];
    let (bk, bp, bs) = key(b);
    let bm = &b.analysis.run.manifest;
    let mut out = Vec::new();
    for (i, r) in loaded.iter().enumerate() {
        if i == baseline {
            continue;
        }
        let (k, p, s) = key(r);
        let m = &r.analysis.run.manifest;
        let name = r.dir.display();
        if k != bk {
            out.push(format!(
                "{name} has sweep kind `{k}`, the baseline {} sweep kind `{bk}`",
                b.dir.display()
            ));
        }
        if p != bp {
            out.push(format!(
                "{name} ran plan {:?} ({}, sha256 {}), the baseline plan {:?} ({}, sha256 {})",
                m.plan_name,
                m.plan_path,
                &p[..12],
                bm.plan_name,
                bm.plan_path,
                &bp[..12]
            ));
        }
        if s != bs {
            out.push(format!(
                "{name} used sensor {} (sha256 {}), the baseline sensor {} (sha256 {})",
                m.sensor_path,
                &s[..12],
                bm.sensor_path,
                &bs[..12]
            ));
        }
    }
    out
}

/// Every metric of any run, with differences to the baseline and the worst run.
fn compare_metrics(runs: &[ComparedRun], baseline: usize) -> Vec<MetricComparison> {
    let mut names: Vec<(String, &'static str)> = Vec::new();
    let mut seen = BTreeSet::new();
    let order = std::iter::once(baseline).chain((0..runs.len()).filter(|&i| i != baseline));
    for i in order {
        for m in &runs[i].metrics {
            if seen.insert(m.name.clone()) {
                names.push((m.name.clone(), m.unit));
            }
        }
    }
    names
        .into_iter()
        .map(|(name, unit)| {
            let base = runs[baseline].metric(&name).filter(|m| m.value.is_finite());
            let differences = runs
                .iter()
                .enumerate()
                .map(|(i, r)| {
                    if i == baseline {
                        return None;
                    }
                    let m = r.metric(&name).filter(|m| m.value.is_finite())?;
                    let b = base?;
                    Some(difference(
                        m.value,
                        m.ci95.as_ref(),
                        b.value,
                        b.ci95.as_ref(),
                    ))
                })
                .collect();
            let better = better(&name);
            let values: Vec<Option<f64>> = runs
                .iter()
                .map(|r| r.metric(&name).map(|m| m.value))
                .collect();
            let worst = better.and_then(|b| worst_run(&values, b));
            MetricComparison {
                name,
                unit,
                better,
                differences,
                worst,
            }
        })
        .collect()
}

/// The comparison's outcome from the runs other than the baseline (module docs).
fn overall(runs: &[ComparedRun], baseline: usize, has_criteria: bool) -> (Outcome, String) {
    let compared: Vec<&ComparedRun> = runs.iter().filter(|r| !r.is_baseline).collect();
    let with = |o: Outcome| -> Vec<&str> {
        compared
            .iter()
            .filter(|r| r.verdict.outcome == o)
            .map(|r| r.label.as_str())
            .collect()
    };
    let base = &runs[baseline];
    let base_incomplete = base.verdict.outcome == Outcome::Incomplete;
    let failed = with(Outcome::Fail);
    let incomplete = with(Outcome::Incomplete);
    let marginal = with(Outcome::Marginal);
    let unjudged = with(Outcome::NotJudged);
    let n = compared.len();
    if !failed.is_empty() {
        return (
            Outcome::Fail,
            format!(
                "FAIL: {} of {n} compared run(s) failed: {}",
                failed.len(),
                failed.join(", ")
            ),
        );
    }
    if !incomplete.is_empty() || base_incomplete {
        let mut why = Vec::new();
        if !incomplete.is_empty() {
            why.push(format!(
                "{} of {n} compared run(s) did not measure their whole plan: {}",
                incomplete.len(),
                incomplete.join(", ")
            ));
        }
        if base_incomplete {
            why.push(format!(
                "the baseline {} did not measure its whole plan",
                base.label
            ));
        }
        return (
            Outcome::Incomplete,
            format!(
                "INCOMPLETE: {}; not graded (grade partial runs with --allow-partial)",
                why.join("; ")
            ),
        );
    }
    // A run whose criteria could not all be judged (a fitted parameter without a fit,
    // or not identifiable) keeps the comparison NOT JUDGED: never PASS on it.
    if has_criteria && !unjudged.is_empty() {
        return (
            Outcome::NotJudged,
            format!(
                "NOT JUDGED: {} of {n} compared run(s) have criteria nothing could judge: {}",
                unjudged.len(),
                unjudged.join(", ")
            ),
        );
    }
    if !marginal.is_empty() {
        return (
            Outcome::Marginal,
            format!(
                "MARGINAL: {} of {n} compared run(s) marginal: {}",
                marginal.len(),
                marginal.join(", ")
            ),
        );
    }
    // Nothing judged in any compared run (no criteria, no requirement): NOT JUDGED.
    if !has_criteria
        || compared
            .iter()
            .all(|r| r.verdict.outcome == Outcome::NotJudged)
    {
        return (
            Outcome::NotJudged,
            format!(
                "NOT JUDGED: no acceptance criteria given; {n} run(s) compared with the baseline"
            ),
        );
    }
    (
        Outcome::Pass,
        format!("PASS: every one of the {n} compared run(s) passed"),
    )
}

/// What [`write_comparison`] wrote.
#[derive(Debug, Clone)]
pub struct CompareOutcome {
    /// `compare.html`.
    pub html: PathBuf,
    /// `compare.csv`.
    pub csv: PathBuf,
    /// The figure files.
    pub figures: Vec<FigureFiles>,
}

/// Text of a criterion verdict for the CSV and the page: the bound, and with a
/// baseline the limits it gives.
pub fn criterion_text(v: &Verdict) -> String {
    criterion_text_scaled(v, 1.0)
}

/// [`criterion_text`] with every force bound, the baseline and the limits multiplied
/// by `k` (the page shows an N metric in the plans' unit; relative fractions are
/// unchanged).
pub fn criterion_text_scaled(v: &Verdict, k: f64) -> String {
    let c = super::headline::scaled_criterion(&v.criterion, k);
    let mut s = c.to_string();
    let nominal = v
        .nominal
        .filter(|_| c.is_nominal_relative() && v.note.is_none())
        .map(|n| n * k);
    if let Some(n) = nominal {
        s.push_str(&format!(" (nominal {})", fmt_value(n)));
    }
    if let Some(b) = v.baseline.map(|b| b * k) {
        let (lo, hi) = c.limits_with(Some(b), nominal);
        let limits = match (lo, hi) {
            (Some(lo), Some(hi)) => format!("in [{}, {}]", fmt_value(lo), fmt_value(hi)),
            (Some(lo), None) => format!(">= {}", fmt_value(lo)),
            (None, Some(hi)) => format!("<= {}", fmt_value(hi)),
            (None, None) => String::new(),
        };
        s.push_str(&format!(" (baseline {}: {limits})", fmt_value(b)));
    }
    s
}

/// The verdicts of run `r` on metric `name`.
pub fn verdicts_of<'a>(r: &'a ComparedRun, name: &str) -> Vec<&'a Verdict> {
    r.verdicts
        .iter()
        .filter(|v| v.criterion.metric == name)
        .collect()
}

fn num(v: f64) -> String {
    crate::formats::Num(v).to_string()
}

/// `compare.csv` as bytes.
pub fn csv_bytes(c: &Comparison) -> Result<Vec<u8>, csv::Error> {
    let mut w = csv::Writer::from_writer(Vec::new());
    w.write_record(CSV_HEADER)?;
    let base = c.baseline_run();
    let base_outcome = base.verdict.outcome.word().to_string();
    for m in &c.metrics {
        let base_value = base
            .metric(&m.name)
            .map(|b| b.value)
            .filter(|v| v.is_finite());
        for (i, r) in c.runs.iter().enumerate() {
            let metric = r.metric(&m.name);
            let value = metric.map(|x| num(x.value)).unwrap_or_default();
            let (low, high, method) = match metric.and_then(|x| x.ci95) {
                Some(ci) => (num(ci.low), num(ci.high), ci.method.to_string()),
                None => Default::default(),
            };
            let d = m.differences[i];
            let opt = |v: Option<f64>| v.map(num).unwrap_or_default();
            let verdicts = verdicts_of(r, &m.name);
            let criterion = verdicts
                .iter()
                .map(|v| criterion_text(v))
                .collect::<Vec<_>>()
                .join("; ");
            let outcome = if verdicts.is_empty() {
                String::new()
            } else {
                Outcome::combine(verdicts.iter().map(|v| v.outcome))
                    .word()
                    .to_string()
            };
            let worst = match (m.better, m.worst) {
                (Some(_), Some(w)) => if w == i { "yes" } else { "no" }.to_string(),
                _ => String::new(),
            };
            w.write_record([
                m.name.clone(),
                m.unit.to_string(),
                r.dir.display().to_string(),
                r.build_id().unwrap_or_default().to_string(),
                r.date().to_string(),
                value,
                low,
                high,
                method,
                if r.is_baseline {
                    String::new()
                } else {
                    opt(base_value)
                },
                opt(d.map(|d| d.value)),
                opt(d.and_then(|d| d.pct)),
                d.map_or(Significance::NotAvailable, |d| d.significance)
                    .word()
                    .to_string(),
                criterion,
                outcome,
                if r.is_baseline {
                    "baseline"
                } else {
                    "compared"
                }
                .to_string(),
                opt(d.and_then(|d| d.ci95.map(|c| c.0))),
                opt(d.and_then(|d| d.ci95.map(|c| c.1))),
                m.better.map(Better::word).unwrap_or_default(),
                worst,
                r.verdict
                    .simulated
                    .map(|s| s.to_string())
                    .unwrap_or_default(),
                base_outcome.clone(),
            ])?;
        }
    }
    w.into_inner().map_err(|e| e.into_error().into())
}

/// Figure size of the overlays (pixels / SVG user units).
const OVERLAY_SIZE: (u32, u32) = (1000, 720);

/// Writes `compare.html`, `compare.csv` and `plots/compare_*` into `out_dir`
/// (created if missing).
pub fn write_comparison(c: &Comparison, out_dir: &Path) -> Result<CompareOutcome, CompareError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| CompareError::Io { path, source }
    };
    std::fs::create_dir_all(out_dir).map_err(io(out_dir))?;
    let plots = out_dir.join(PLOTS_DIR);
    let mut files = Vec::new();
    let mut embedded = Vec::new();
    let mut save = |stem: &str, caption: String, fig: &dyn figures::AnyFigure, size| {
        let f = fig.save(&plots, stem, size)?;
        let png = std::fs::read(&f.png).map_err(io(&f.png))?;
        embedded.push(super::html::EmbeddedFigure {
            stem: stem.to_string(),
            caption,
            png,
        });
        files.push(f);
        Ok::<(), CompareError>(())
    };
    if let Some(t) = figures::trend_figure(c) {
        let size = t.size();
        save(
            "compare_trends",
            format!(
                "Metrics over the runs, in order of their start date (x labels: build id or \
                 directory). Points: value; bars: 95 % CI where the analysis states one; \
                 dashed: the baseline {}'s value. Each y axis includes at least ± {} % of the \
                 baseline's value, so small differences look small. Title: metric [unit] and \
                 which way is better{}.",
                c.baseline_run().label,
                figures::TREND_MIN_HALF_SPAN * 100.0,
                match c.force_unit() {
                    crate::units::ForceUnit::Newton => String::new(),
                    u => format!(
                        "; forces in the plans' unit, {u} (see the note on the metrics table)"
                    ),
                }
            ),
            &t,
            size,
        )?;
    }
    if let Some(t) = figures::fit_trend_figure(c) {
        let size = t.size();
        save(
            "compare_fit",
            "Fitted sensor-model parameters (`tactbench fit`, each run's fit.json) over the \
             builds, in order of their start date. Points: fitted value; bars: its 95 % \
             interval; dashed: the nominal value of the sensor file. A run without a fit, or \
             whose fit could not determine a parameter, has no point for it."
                .to_string(),
            &t,
            size,
        )?;
    }
    for (stem, caption, fig) in figures::overlay_figures(c) {
        save(&stem, caption, &fig, OVERLAY_SIZE)?;
    }
    let csv_path = out_dir.join(COMPARE_CSV);
    let bytes = csv_bytes(c).map_err(|e| CompareError::Io {
        path: csv_path.clone(),
        source: std::io::Error::other(e.to_string()),
    })?;
    std::fs::write(&csv_path, bytes).map_err(io(&csv_path))?;
    let html_path = out_dir.join(COMPARE_HTML);
    let page = page::render(c, &embedded);
    std::fs::write(&html_path, page).map_err(io(&html_path))?;
    Ok(CompareOutcome {
        html: html_path,
        csv: csv_path,
        figures: files,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ci(low: f64, high: f64) -> Ci95 {
        Ci95 {
            low,
            high,
            method: "t",
        }
    }

    #[test]
    fn standard_error_is_the_half_width_over_1_96() {
        assert!((standard_error(&ci(8.04, 11.96)).unwrap() - 1.0).abs() < 1e-3);
        // Asymmetric: its mean half-width.
        let se = standard_error(&ci(0.0, Z95 * 3.0)).unwrap();
        assert!((se - 1.5).abs() < 1e-12, "{se}");
        assert_eq!(standard_error(&ci(2.0, 1.0)), None);
        assert_eq!(standard_error(&ci(f64::NAN, 1.0)), None);
    }

    #[test]
    fn difference_ci_combines_known_standard_errors() {
        // SE 3 and 4 -> SE of the difference 5; half-width 1.96 * 5 = 9.8.
        let a = ci(20.0 - Z95 * 3.0, 20.0 + Z95 * 3.0);
        let b = ci(10.0 - Z95 * 4.0, 10.0 + Z95 * 4.0);
        let d = difference(20.0, Some(&a), 10.0, Some(&b));
        assert_eq!(d.value, 10.0);
        assert_eq!(d.pct, Some(100.0));
        let (lo, hi) = d.ci95.unwrap();
        assert!((lo - (10.0 - Z95 * 5.0)).abs() < 1e-9, "{lo}");
        assert!((hi - (10.0 + Z95 * 5.0)).abs() < 1e-9, "{hi}");
        // 10 > 9.8: significant, although the two CIs overlap ([14.1, 25.9] and
        // [2.2, 17.8]): the non-overlap rule would have missed it.
        assert_eq!(d.significance, Significance::Significant);
        assert!(a.low < b.high);
        // Half the difference: 5 < 9.8, not significant.
        let d = difference(15.0, Some(&a), 10.0, Some(&b));
        assert_eq!(d.significance, Significance::NotSignificant);
        // Just inside / outside the boundary.
        let half = Z95 * 5.0;
        let at = |v: f64| difference(10.0 + v, Some(&a), 10.0, Some(&b)).significance;
        assert_eq!(at(half * 1.001), Significance::Significant);
        assert_eq!(at(-half * 1.001), Significance::Significant);
        assert_eq!(at(half * 0.999), Significance::NotSignificant);
    }

    #[test]
    fn a_metric_without_a_ci_is_never_significant() {
        let a = ci(9.0, 11.0);
        for (x, y) in [(None, Some(&a)), (Some(&a), None), (None, None)] {
            let d = difference(1000.0, x, 1.0, y);
            assert_eq!(d.significance, Significance::NotAvailable);
            assert_eq!(d.ci95, None);
            assert_eq!(d.significance.word(), "n/a");
        }
        // A zero baseline has no percentage.
        assert_eq!(difference(1.0, None, 0.0, None).pct, None);
        // Negative baselines: the percentage is relative to |b|.
        assert_eq!(difference(-1.0, None, -2.0, None).pct, Some(50.0));
    }

    #[test]
    fn the_direction_table_names_the_worse_side() {
        assert_eq!(better("magnitude.resolution_gf"), Some(Better::Lower));
        assert_eq!(better("magnitude.residual_sd_n"), Some(Better::Lower));
        assert_eq!(better("magnitude.hysteresis_pct"), Some(Better::Lower));
        assert_eq!(better("displacement.blue.x.sd_px"), Some(Better::Lower));
        assert_eq!(better("timing.forces_ms"), Some(Better::Lower));
        assert_eq!(better("magnitude.slope"), Some(Better::CloserTo(1.0)));
        assert_eq!(better("magnitude.r2"), Some(Better::Higher));
        assert_eq!(better("tracking.min_ok_fraction"), Some(Better::Higher));
        assert_eq!(better("angle.bias_deg"), Some(Better::CloserTo(0.0)));
        assert_eq!(better("magnitude.offset_n"), Some(Better::CloserTo(0.0)));
        assert_eq!(better("run.rows"), None);
        assert_eq!(better("displacement.blue.x.mean_px"), None);
        assert_eq!(better("spatial.line_offset_mm"), None);
        // The metrology metrics (issue 13).
        assert_eq!(better("magnitude.resolution_method"), None);
        assert_eq!(better("metrology.full_scale_n"), None);
        assert_eq!(better("metrology.class"), Some(Better::Lower));
        for m in [
            "metrology.repeatability_pct_fs",
            "metrology.reproducibility_pct_fs",
            "metrology.interpolation_pct_fs",
            "metrology.reversibility_pct_fs",
        ] {
            assert_eq!(better(m), Some(Better::Lower), "{m}");
        }
        for m in [
            "metrology.zero_pct_fs",
            "hold.creep_pct_fs_per_min",
            "hold.zero_drift_n",
        ] {
            assert_eq!(better(m), Some(Better::CloserTo(0.0)), "{m}");
        }
        // Slope 0.9 is worse than 1.05; an offset of -3 worse than 2.
        let s = Better::CloserTo(1.0);
        assert_eq!(worst_run(&[Some(1.05), Some(0.9)], s), Some(1));
        let o = Better::CloserTo(0.0);
        assert_eq!(worst_run(&[Some(-3.0), Some(2.0)], o), Some(0));
        assert_eq!(
            worst_run(&[Some(1.0), None, Some(2.0)], Better::Lower),
            Some(2)
        );
        assert_eq!(
            worst_run(&[Some(0.99), Some(0.999)], Better::Higher),
            Some(0)
        );
        // Ties and single values name nobody.
        assert_eq!(worst_run(&[Some(0.0), Some(0.0)], Better::Lower), None);
        assert_eq!(worst_run(&[Some(1.0), None], Better::Lower), None);
        assert_eq!(worst_run(&[Some(f64::NAN), Some(1.0)], Better::Lower), None);
    }

    #[test]
    fn duplicate_directories_are_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let a = tmp.path().join("a");
        std::fs::create_dir(&a).unwrap();
        let e = plan_runs(&[a.clone(), tmp.path().join("./a")], None).unwrap_err();
        assert!(e.to_string().contains("the same directory"), "{e}");
        let e = plan_runs(std::slice::from_ref(&a), None).unwrap_err();
        assert!(e.to_string().contains("at least two"), "{e}");
        // --baseline naming one of the runs: that one, no extra run.
        let b = tmp.path().join("b");
        std::fs::create_dir(&b).unwrap();
        let (dirs, i) = plan_runs(&[a.clone(), b.clone()], Some(&b)).unwrap();
        assert_eq!((dirs.len(), i), (2, 1));
        let c = tmp.path().join("c");
        let (dirs, i) = plan_runs(&[a, b], Some(&c)).unwrap();
        assert_eq!((dirs.len(), i, dirs[0].clone()), (3, 0, c));
    }
}
