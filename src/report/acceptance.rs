//! Acceptance criteria (`--acceptance CRITERIA.toml`) and their verdicts.
//!
//! ```toml
//! # Optional: the run must record an elastomer build id (`--build-id` or the plan's
//! # `build_id`), else the verdict is FAIL.
//! require_build_id = true
//! # Optional: the run must have been measured on a real bench: a run on the simulated
//! # bench FAILs, and so does one whose manifest predates the `simulated` flag.
//! require_real_bench = true
//!
//! # Each criterion bounds one metric of the run (names: `tactbench report --help`,
//! # the README, or analysis::METRICS). At least one of min / max; bounds inclusive.
//! [[criterion]]
//! metric = "magnitude.r2"
//! min = 0.99
//! marginal_min = 0.995   # optional: 0.99 <= r2 <= 0.995 is MARGINAL
//!
//! [[criterion]]
//! metric = "magnitude.resolution_gf"
//! max = 40.0
//!
//! [[criterion]]
//! metric = "timing.forces_ms"
//! min = 0.0
//! max = 2.9
//! ```
//!
//! Bounds relative to a baseline run (judged by `tactbench compare`, which names the
//! baseline; `b` = the baseline's value of the metric, every key optional, each ≥ 0):
//!
//! ```toml
//! [[criterion]]
//! metric = "magnitude.resolution_gf"
//! max_relative_to_baseline = 0.10   # value <= b + 0.10 |b|: at most 10 % worse
//! # min_relative_to_baseline = 0.05 # value >= b - 0.05 |b|
//! # max_increase = 2.0              # value <= b + 2 (metric unit)
//! # max_decrease = 2.0              # value >= b - 2 (metric unit)
//! ```
//!
//! Bounds on the sensor model's fitted parameters (`tactbench fit`, issue 30): the
//! metric is `fit.<NAME>` with NAME a parameter of `fit.json` ([`crate::fit::doc`]:
//! `young_modulus_kpa`, `depth_mm.<layer>`, `ft_rotation_deg`, ...), judged on the
//! run's `fit.json` (`RUN_DIR/fit.json`, or `report --fit FILE`). Besides `min` / `max`
//! (and the baseline keys in `compare`), such a criterion may bound the parameter
//! relative to the nominal value the fit started from (`n` = the parameter's
//! `nominal` in `fit.json`, each key ≥ 0):
//!
//! ```toml
//! [[criterion]]
//! metric = "fit.young_modulus_kpa"
//! max_relative_to_nominal = 0.10    # |value - n| <= 0.10 |n|: within ±10 % of nominal
//!
//! [[criterion]]
//! metric = "fit.depth_mm.blue"
//! max_deviation_from_nominal = 0.3  # |value - n| <= 0.3 (the parameter's unit, mm)
//! ```
//!
//! A fitted parameter is judged with its 95 % interval: FAIL when the value is outside
//! the limits; MARGINAL when the value is inside but its interval straddles a limit
//! (the run cannot tell the build is within tolerance), or in a marginal band; PASS
//! otherwise. A criterion on a parameter the fit held at nominal or found not
//! identifiable, or on a run with no `fit.json`, is **NOT JUDGED** with the reason
//! (never PASS: [`Outcome::combine`] makes a verdict with a NOT JUDGED criterion and
//! no FAIL NOT JUDGED as a whole). A `fit.json` without the parameter (a layer the
//! sensor does not have) is an error naming the parameters it has.
//!
//! A criterion may mix absolute and relative bounds; the limits are the tightest of
//! them. `tactbench report` has no baseline: a criterion with a relative bound is an
//! error there ([`Criteria::evaluate`]), never a silent pass; so is a baseline that
//! lacks the metric or whose value is not finite ([`Criteria::evaluate_against`]).
//!
//! Outcome of one criterion: FAIL outside `[min, max]` (or not a finite number);
//! MARGINAL inside the limits but at or beyond a marginal bound (`value <= marginal_min`
//! or `value >= marginal_max`, OpenHTF's marginal band: within limits, close to them);
//! PASS otherwise.
//!
//! Rejected when loading (naming the file and the criterion): TOML errors and unknown
//! keys, no criterion, a criterion with neither bound, non-finite bounds, `min > max`,
//! a marginal bound outside the limits (`min <= marginal_min <= marginal_max <= max`),
//! and metric names the analyses never produce (the message lists the known ones).
//! A known metric that this run's sweep kind never has (e.g. `spatial.fwhm_mm` on a
//! magnitude run) is an error when evaluating, never a silent pass. A metric whose
//! analysis could not run on this run's data (too few rows) FAILs its criterion, with
//! the reason. A metric value that is not a finite number fails its criterion.

use std::fmt;
use std::path::{Path, PathBuf};

use serde::Deserialize;
use thiserror::Error;

use crate::analysis::{is_known_metric, Ci95, Metric, METRICS};
use crate::config::{self, ConfigError};
use crate::fit::{is_parameter_name, FitDoc, PARAMETER_NAMES};

/// An error in a criteria file or in applying it to a run.
#[derive(Debug, Error)]
pub enum AcceptanceError {
    /// Unreadable file or invalid TOML (with line and column).
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// A criterion is invalid.
    #[error("{path}: criterion {number} (`{metric}`): {message}")]
    Invalid {
        /// The criteria file.
        path: PathBuf,
        /// 1-based position of the criterion in the file.
        number: usize,
        /// Its metric as written.
        metric: String,
        /// What is wrong.
        message: String,
    },
    /// The file defines no criterion.
    #[error("{path}: no [[criterion]] entries and no requirement (require_build_id, require_real_bench): nothing to judge")]
    Empty {
        /// The criteria file.
        path: PathBuf,
    },
    /// A `fit.json` that cannot be read or does not hold what the criteria need.
    #[error("{path}: {message}")]
    Fit {
        /// The fit file.
        path: PathBuf,
        /// What is wrong: key, value, unit.
        message: String,
    },
}

/// One bound on one metric.
#[derive(Debug, Clone, PartialEq)]
pub struct Criterion {
    /// Metric name (see [`METRICS`]).
    pub metric: String,
    /// Inclusive lower bound.
    pub min: Option<f64>,
    /// Inclusive upper bound.
    pub max: Option<f64>,
    /// Values at or below it (within the limits) are MARGINAL.
    pub marginal_min: Option<f64>,
    /// Values at or above it (within the limits) are MARGINAL.
    pub marginal_max: Option<f64>,
    /// `value <= b + r |b|` with `b` the baseline's value (`compare` only).
    pub max_relative_to_baseline: Option<f64>,
    /// `value >= b - r |b|` (`compare` only).
    pub min_relative_to_baseline: Option<f64>,
    /// `value <= b + d`, metric unit (`compare` only).
    pub max_increase: Option<f64>,
    /// `value >= b - d`, metric unit (`compare` only).
    pub max_decrease: Option<f64>,
    /// Fitted parameters only: `|value - n| <= r |n|` with `n` the fit's nominal value.
    pub max_relative_to_nominal: Option<f64>,
    /// Fitted parameters only: `|value - n| <= d`, the parameter's unit.
    pub max_deviation_from_nominal: Option<f64>,
}

/// The bound keys relative to a fitted parameter's nominal value, for messages.
pub const NOMINAL_KEYS: [&str; 2] = ["max_relative_to_nominal", "max_deviation_from_nominal"];

/// The metric prefix of a fitted parameter (`fit.young_modulus_kpa`).
pub const FIT_PREFIX: &str = "fit.";

/// The fit parameter a metric name bounds (`fit.depth_mm.blue` -> `depth_mm.blue`),
/// `None` for a run metric.
pub fn fit_parameter(metric: &str) -> Option<&str> {
    metric
        .strip_prefix(FIT_PREFIX)
        .filter(|p| is_parameter_name(p))
}

/// The unit of a fitted parameter, from its name (what `fit.json` must record).
pub fn fit_unit(param: &str) -> &'static str {
    match param {
        "young_modulus_kpa" => "kPa",
        "poisson_ratio" => "1",
        "ft_rotation_deg" => "deg",
        p if p == "mm_per_px" || p.starts_with("mm_per_px.") => "mm/px",
        _ => "mm",
    }
}

/// The relative bound keys of a criterion, for messages.
pub const RELATIVE_KEYS: [&str; 4] = [
    "max_relative_to_baseline",
    "min_relative_to_baseline",
    "max_increase",
    "max_decrease",
];

/// The outcome of a criterion, a requirement or a whole verdict.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "UPPERCASE")]
pub enum Outcome {
    /// Nothing was judged: for a verdict, no criteria and no requirements, or a
    /// criterion nothing could judge (and none failed); for a criterion on a fitted
    /// parameter, no fit, or a parameter held at nominal or not identifiable (exit 0,
    /// shown neutrally, never as a pass).
    #[serde(rename = "NOT JUDGED")]
    NotJudged,
    /// Within the limits and outside any marginal band.
    Pass,
    /// Within the limits but in a marginal band (exit 0, shown).
    Marginal,
    /// Outside the limits, not a number, or a requirement not met.
    Fail,
    /// The run did not measure its whole plan (verdicts only).
    Incomplete,
}

impl Outcome {
    /// `NOT JUDGED`, `PASS`, `MARGINAL`, `FAIL`, `INCOMPLETE`.
    pub fn word(self) -> &'static str {
        match self {
            Outcome::NotJudged => "NOT JUDGED",
            Outcome::Pass => "PASS",
            Outcome::Marginal => "MARGINAL",
            Outcome::Fail => "FAIL",
            Outcome::Incomplete => "INCOMPLETE",
        }
    }

    /// The word as one token (`NOT_JUDGED`, `PASS`, ...): an HTML class name.
    pub fn token(self) -> &'static str {
        match self {
            Outcome::NotJudged => "NOT_JUDGED",
            o => o.word(),
        }
    }

    /// The outcome of several judged items (criteria, requirements): the worst of
    /// them (FAIL over MARGINAL over PASS), except that an item nothing could judge
    /// makes it NOT JUDGED unless something FAILs: a build never PASSes (nor is
    /// called MARGINAL, which passes) on a criterion that was not judged. No item:
    /// NOT JUDGED. INCOMPLETE, where given, stays the worst.
    pub fn combine(outcomes: impl IntoIterator<Item = Outcome>) -> Outcome {
        let mut worst = None::<Outcome>;
        let mut unjudged = false;
        for o in outcomes {
            unjudged |= o == Outcome::NotJudged;
            worst = Some(worst.map_or(o, |w| w.max(o)));
        }
        match worst {
            None => Outcome::NotJudged,
            Some(w) if unjudged && w < Outcome::Fail => Outcome::NotJudged,
            Some(w) => w,
        }
    }
}

impl fmt::Display for Outcome {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.word())
    }
}

impl fmt::Display for Criterion {
    /// The threshold as text: `>= 0.99`, `<= 2.9`, `in [0, 2.9]`; relative bounds as
    /// `<= baseline + 10 %`, `>= baseline - 2`, joined by `, `.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut parts: Vec<String> = Vec::new();
        match (self.min, self.max) {
            (Some(lo), Some(hi)) => parts.push(format!("in [{lo}, {hi}]")),
            (Some(lo), None) => parts.push(format!(">= {lo}")),
            (None, Some(hi)) => parts.push(format!("<= {hi}")),
            (None, None) => {}
        }
        let pct = |r: f64| fmt_value(r * 100.0);
        if let Some(r) = self.max_relative_to_baseline {
            parts.push(format!("<= baseline + {} %", pct(r)));
        }
        if let Some(r) = self.min_relative_to_baseline {
            parts.push(format!(">= baseline - {} %", pct(r)));
        }
        if let Some(d) = self.max_increase {
            parts.push(format!("<= baseline + {d}"));
        }
        if let Some(d) = self.max_decrease {
            parts.push(format!(">= baseline - {d}"));
        }
        if let Some(r) = self.max_relative_to_nominal {
            parts.push(format!("within ±{} % of nominal", pct(r)));
        }
        if let Some(d) = self.max_deviation_from_nominal {
            parts.push(format!("within ±{d} of nominal"));
        }
        if parts.is_empty() {
            f.write_str("(no bound)")?;
        } else {
            f.write_str(&parts.join(", "))?;
        }
        match (self.marginal_min, self.marginal_max) {
            (Some(lo), Some(hi)) => write!(f, ", marginal outside ({lo}, {hi})"),
            (Some(lo), None) => write!(f, ", marginal <= {lo}"),
            (None, Some(hi)) => write!(f, ", marginal >= {hi}"),
            (None, None) => Ok(()),
        }
    }
}

/// A validated criteria file.
#[derive(Debug, Clone, PartialEq)]
pub struct Criteria {
    /// The file.
    pub path: PathBuf,
    /// Criteria in file order.
    pub criteria: Vec<Criterion>,
    /// `require_build_id = true`: a run without a build id FAILs.
    pub require_build_id: bool,
    /// `require_real_bench = true`: a run on the simulated bench FAILs (and so does a
    /// run whose manifest does not record whether it was simulated).
    pub require_real_bench: bool,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCriteria {
    #[serde(default)]
    require_build_id: bool,
    #[serde(default)]
    require_real_bench: bool,
    #[serde(default)]
    criterion: Vec<RawCriterion>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCriterion {
    metric: String,
    min: Option<f64>,
    max: Option<f64>,
    marginal_min: Option<f64>,
    marginal_max: Option<f64>,
    max_relative_to_baseline: Option<f64>,
    min_relative_to_baseline: Option<f64>,
    max_increase: Option<f64>,
    max_decrease: Option<f64>,
    max_relative_to_nominal: Option<f64>,
    max_deviation_from_nominal: Option<f64>,
}

/// The known metric names, one per line, for messages and `--help`.
pub fn known_metrics_text() -> String {
    let mut lines: Vec<String> = METRICS
        .iter()
        .map(|(name, unit, what)| format!("  {name} [{unit}]: {what}"))
        .collect();
    for p in PARAMETER_NAMES {
        lines.push(format!(
            "  fit.{p} [{}]: fitted by `tactbench fit` (fit.json)",
            fit_unit(p)
        ));
    }
    lines.push(
        "  fit.depth_mm.<layer> [mm], fit.mm_per_px.<layer> [mm/px]: fitted per layer (fit.json)"
            .into(),
    );
    lines.join("\n")
}

impl Criteria {
    /// Reads and validates a criteria file.
    pub fn from_path(path: &Path) -> Result<Criteria, AcceptanceError> {
        let text = config::read_text(path, "acceptance criteria")?;
        Criteria::from_toml_str(&text, path)
    }

    /// Parses and validates criteria TOML; `path` names the file in errors.
    pub fn from_toml_str(text: &str, path: &Path) -> Result<Criteria, AcceptanceError> {
        let raw: RawCriteria = config::parse_toml(text, path)?;
        // A file of provenance requirements alone judges something; an empty one not.
        if raw.criterion.is_empty() && !raw.require_build_id && !raw.require_real_bench {
            return Err(AcceptanceError::Empty {
                path: path.to_path_buf(),
            });
        }
        let mut criteria = Vec::with_capacity(raw.criterion.len());
        for (i, c) in raw.criterion.into_iter().enumerate() {
            let invalid = |message: String| AcceptanceError::Invalid {
                path: path.to_path_buf(),
                number: i + 1,
                metric: c.metric.clone(),
                message,
            };
            let fitted = fit_parameter(&c.metric).is_some();
            if !is_known_metric(&c.metric) && !fitted {
                return Err(invalid(format!(
                    "unknown metric; known metrics (<layer> = a layer name of the sensor):\n{}",
                    known_metrics_text()
                )));
            }
            let nominal = [c.max_relative_to_nominal, c.max_deviation_from_nominal];
            for (key, v) in NOMINAL_KEYS.iter().zip(nominal) {
                let Some(v) = v else { continue };
                if !fitted {
                    return Err(invalid(format!(
                        "{key} applies to fitted parameters only (`fit.<parameter>`, which \
                         have a nominal value); bound a run metric with min / max"
                    )));
                }
                if !v.is_finite() || v < 0.0 {
                    return Err(invalid(format!(
                        "{key} = {v} must be a finite number >= 0 (how far from nominal the \
                         fitted value may be)"
                    )));
                }
            }
            let has_nominal = nominal.iter().any(Option::is_some);
            let relative = [
                c.max_relative_to_baseline,
                c.min_relative_to_baseline,
                c.max_increase,
                c.max_decrease,
            ];
            for (key, v) in RELATIVE_KEYS.iter().zip(relative) {
                if let Some(v) = v {
                    if !v.is_finite() || v < 0.0 {
                        return Err(invalid(format!(
                            "{key} = {v} must be a finite number >= 0 (how much worse than \
                             the baseline a run may be)"
                        )));
                    }
                }
            }
            let has_relative = relative.iter().any(Option::is_some);
            match (c.min, c.max) {
                (None, None) if !has_relative && !has_nominal => {
                    return Err(invalid(format!(
                        "give min, max or both (or a bound relative to a baseline run: {}{})",
                        RELATIVE_KEYS.join(", "),
                        if fitted {
                            format!("; or to the nominal value: {}", NOMINAL_KEYS.join(", "))
                        } else {
                            String::new()
                        }
                    )))
                }
                (Some(lo), Some(hi)) if lo > hi => {
                    return Err(invalid(format!("min = {lo} is greater than max = {hi}")))
                }
                _ => {}
            }
            let bounds = [
                ("min", c.min),
                ("marginal_min", c.marginal_min),
                ("marginal_max", c.marginal_max),
                ("max", c.max),
            ];
            for (key, v) in bounds {
                if let Some(v) = v {
                    if !v.is_finite() {
                        return Err(invalid(format!("{key} = {v} is not a finite number")));
                    }
                }
            }
            // min <= marginal_min <= marginal_max <= max, for the bounds given.
            let given: Vec<(&str, f64)> = bounds
                .iter()
                .filter_map(|(k, v)| v.map(|v| (*k, v)))
                .collect();
            for w in given.windows(2) {
                let ((ka, a), (kb, b)) = (w[0], w[1]);
                if a > b && !(ka == "min" && kb == "max") {
                    return Err(invalid(format!(
                        "{ka} = {a} is greater than {kb} = {b}; the marginal band lies within \
                         the limits (min <= marginal_min <= marginal_max <= max)"
                    )));
                }
            }
            criteria.push(Criterion {
                metric: c.metric,
                min: c.min,
                max: c.max,
                marginal_min: c.marginal_min,
                marginal_max: c.marginal_max,
                max_relative_to_baseline: c.max_relative_to_baseline,
                min_relative_to_baseline: c.min_relative_to_baseline,
                max_increase: c.max_increase,
                max_decrease: c.max_decrease,
                max_relative_to_nominal: c.max_relative_to_nominal,
                max_deviation_from_nominal: c.max_deviation_from_nominal,
            });
        }
        Ok(Criteria {
            path: path.to_path_buf(),
            criteria,
            require_build_id: raw.require_build_id,
            require_real_bench: raw.require_real_bench,
        })
    }

    /// Judges `metrics` (a run's [`crate::analysis::RunAnalysis::metrics`]); `sweep`
    /// names the run's sweep kind in messages; `absent` lists the analyses that could
    /// not run on this run's data as (metric prefix, reason): their criteria FAIL
    /// with the reason instead of being errors.
    ///
    /// Without a baseline, a criterion with a bound relative to one is an error.
    pub fn evaluate(
        &self,
        metrics: &[Metric],
        sweep: &str,
        absent: &[(String, String)],
    ) -> Result<Vec<Verdict>, AcceptanceError> {
        self.evaluate_against(metrics, sweep, absent, None)
    }

    /// Whether any criterion has a bound relative to a baseline.
    pub fn has_relative(&self) -> bool {
        self.criteria.iter().any(Criterion::is_relative)
    }

    /// As [`Criteria::evaluate`], with `baseline` the baseline run's metrics for the
    /// relative bounds (`None`: no baseline, a relative criterion is an error). A
    /// baseline that lacks the metric, or whose value is not a finite number, is an
    /// error naming the criterion. Criteria on fitted parameters are NOT JUDGED (no
    /// fit given): use [`Criteria::evaluate_with_fit`].
    pub fn evaluate_against(
        &self,
        metrics: &[Metric],
        sweep: &str,
        absent: &[(String, String)],
        baseline: Option<&[Metric]>,
    ) -> Result<Vec<Verdict>, AcceptanceError> {
        self.evaluate_with_fit(metrics, sweep, absent, baseline, None)
    }

    /// As [`Criteria::evaluate_against`], criteria on fitted parameters judged on
    /// `fit` (`None`: nothing says where a fit would be; they are NOT JUDGED). With a
    /// baseline, a bound relative to it on a fitted parameter takes the baseline's
    /// `fit.<NAME>` metric (see [`RunFit::metrics`]); a baseline without one leaves the
    /// criterion NOT JUDGED, saying so.
    pub fn evaluate_with_fit(
        &self,
        metrics: &[Metric],
        sweep: &str,
        absent: &[(String, String)],
        baseline: Option<&[Metric]>,
        fit: Option<&RunFit>,
    ) -> Result<Vec<Verdict>, AcceptanceError> {
        let mut out = Vec::with_capacity(self.criteria.len());
        for (i, c) in self.criteria.iter().enumerate() {
            let invalid = |message: String| AcceptanceError::Invalid {
                path: self.path.clone(),
                number: i + 1,
                metric: c.metric.clone(),
                message,
            };
            if let Some(param) = fit_parameter(&c.metric) {
                out.push(judge_fitted(c, param, baseline, fit).map_err(|e| match e {
                    FitJudgeError::Criterion(m) => invalid(m),
                    FitJudgeError::File(e) => e,
                })?);
                continue;
            }
            let base = if c.is_relative() {
                let Some(b) = baseline else {
                    return Err(invalid(NEEDS_BASELINE.into()));
                };
                match b.iter().find(|m| m.name == c.metric) {
                    Some(m) if m.value.is_finite() => Some(m.value),
                    Some(m) => {
                        return Err(invalid(format!(
                            "the baseline's value {} is not a finite number: no relative \
                             limit can be derived from it",
                            m.value
                        )))
                    }
                    None => {
                        return Err(invalid(
                            "the baseline run has no value for this metric, so the bound \
                             relative to it cannot be judged"
                                .into(),
                        ))
                    }
                }
            } else {
                None
            };
            let prefix = c.metric.split('.').next().unwrap_or_default();
            if let Some((_, why)) = absent.iter().find(|(p, _)| p == prefix) {
                if !metrics.iter().any(|m| m.name == c.metric) {
                    out.push(Verdict {
                        criterion: c.clone(),
                        value: f64::NAN,
                        unit: metric_unit(&c.metric),
                        outcome: Outcome::Fail,
                        note: Some(format!("not computed: {why}")),
                        baseline: base,
                        ci95: None,
                        nominal: None,
                    });
                    continue;
                }
            }
            let Some(m) = metrics.iter().find(|m| m.name == c.metric) else {
                let have: Vec<&str> = metrics.iter().map(|m| m.name.as_str()).collect();
                return Err(invalid(format!(
                    "this run ({sweep} sweep) has no such metric; it has: {}",
                    have.join(", ")
                )));
            };
            out.push(Verdict {
                criterion: c.clone(),
                value: m.value,
                unit: m.unit,
                outcome: c.judge_against(m.value, base),
                note: None,
                baseline: base,
                ci95: None,
                nominal: None,
            });
        }
        Ok(out)
    }
}

const NEEDS_BASELINE: &str = "a bound relative to a baseline run needs a baseline: judge it \
     with `tactbench compare RUN_DIR... --baseline BASELINE_DIR`";

enum FitJudgeError {
    /// The criterion cannot apply (named by the caller).
    Criterion(String),
    /// The fit file lacks what the criterion needs.
    File(AcceptanceError),
}

/// One criterion on the fitted parameter `param` (see the module docs).
fn judge_fitted(
    c: &Criterion,
    param: &str,
    baseline: Option<&[Metric]>,
    fit: Option<&RunFit>,
) -> Result<Verdict, FitJudgeError> {
    let unit = fit_unit(param);
    let not_judged = |note: String, baseline: Option<f64>, nominal: Option<f64>| Verdict {
        criterion: c.clone(),
        value: f64::NAN,
        unit,
        outcome: Outcome::NotJudged,
        note: Some(note),
        baseline,
        ci95: None,
        nominal,
    };
    if c.is_relative() && baseline.is_none() {
        return Err(FitJudgeError::Criterion(NEEDS_BASELINE.into()));
    }
    let (path, doc) =
        match fit {
            None => return Ok(not_judged(
                "no fit given: judge fitted parameters with `tactbench report RUN_DIR` on a run \
                 with fit.json, or `report --fit FILE`"
                    .into(),
                None,
                None,
            )),
            Some(RunFit::Missing(why)) => return Ok(not_judged(why.clone(), None, None)),
            Some(RunFit::Found { path, doc }) => (path, doc),
        };
    let Some(p) = doc.parameters.get(param) else {
        let have: Vec<&str> = doc.parameters.keys().map(String::as_str).collect();
        return Err(FitJudgeError::File(AcceptanceError::Fit {
            path: path.clone(),
            message: format!(
                "no parameter `{param}` (criterion `{}`); the fit has: {}",
                c.metric,
                have.join(", ")
            ),
        }));
    };
    let reason = p
        .reason
        .as_deref()
        .map_or(String::new(), |r| format!(": {r}"));
    if !p.fitted {
        return Ok(not_judged(
            format!(
                "not fitted: held at its nominal {} {unit}{reason}",
                fmt_value(p.nominal)
            ),
            None,
            Some(p.nominal),
        ));
    }
    if !p.identifiable {
        return Ok(not_judged(
            format!("not identifiable from this run{reason}"),
            None,
            Some(p.nominal),
        ));
    }
    let base = match baseline.filter(|_| c.is_relative()) {
        None => None,
        Some(b) => match b.iter().find(|m| m.name == c.metric) {
            Some(m) if m.value.is_finite() => Some(m.value),
            _ => {
                return Ok(not_judged(
                    format!(
                        "the baseline has no fitted value of `{param}` (no fit.json, or the \
                         parameter not fitted or not identifiable there): the bound relative \
                         to it cannot be judged"
                    ),
                    None,
                    Some(p.nominal),
                ))
            }
        },
    };
    Ok(Verdict {
        criterion: c.clone(),
        value: p.value,
        unit,
        outcome: c.judge_interval(p.value, p.ci95, base, Some(p.nominal)),
        note: None,
        baseline: base,
        ci95: p.ci95,
        nominal: Some(p.nominal),
    })
}

/// The fit a run's fitted-parameter criteria are judged on.
#[derive(Debug, Clone, PartialEq)]
pub enum RunFit {
    /// A `fit.json`, read and checked.
    Found {
        /// The file.
        path: PathBuf,
        /// Its content (boxed: a document is large next to a message).
        doc: Box<FitDoc>,
    },
    /// No fit for this run: why, and how to make one.
    Missing(String),
}

/// File name of the fit document in a run directory.
pub const FIT_FILE: &str = "fit.json";

impl RunFit {
    /// The fit of the run in `run_dir`: `explicit` (`report --fit FILE`: it must
    /// exist), else `RUN_DIR/fit.json` when it exists, else [`RunFit::Missing`]. A
    /// file that cannot be read, is not a `fit.json`, or holds an unknown parameter
    /// name, a non-finite value or interval, or a unit other than its parameter's, is
    /// an error naming the file and the key.
    pub fn load(run_dir: &Path, explicit: Option<&Path>) -> Result<RunFit, AcceptanceError> {
        let path = match explicit {
            Some(p) => p.to_path_buf(),
            None => {
                let p = run_dir.join(FIT_FILE);
                if !p.exists() {
                    return Ok(RunFit::Missing(format!(
                        "no fit: {} does not exist (write it with `tactbench fit {} --out \
                         fitted.toml --json {}`, or give `report --fit FILE`)",
                        p.display(),
                        run_dir.display(),
                        p.display()
                    )));
                }
                p
            }
        };
        let err = |message: String| AcceptanceError::Fit {
            path: path.clone(),
            message,
        };
        let text =
            std::fs::read_to_string(&path).map_err(|e| err(format!("cannot read the fit: {e}")))?;
        let doc = FitDoc::from_json_str(&text).map_err(err)?;
        check_fit_doc(&doc).map_err(err)?;
        Ok(RunFit::Found {
            path,
            doc: Box::new(doc),
        })
    }

    /// The document, when there is one.
    pub fn doc(&self) -> Option<&FitDoc> {
        match self {
            RunFit::Found { doc, .. } => Some(doc.as_ref()),
            RunFit::Missing(_) => None,
        }
    }

    /// The fitted, identifiable parameters as run metrics `fit.<NAME>` (value, unit,
    /// 95 % interval): what `summary.csv`, `verdict.json` and `compare` show and
    /// trend. Parameters held at nominal or not identifiable are left out: their
    /// value is not a measurement. The interval's method is `jacobian` or
    /// `bootstrap` as `fit.json`'s `ci_method` says (`fit` when it does not).
    pub fn metrics(&self) -> Vec<Metric> {
        let Some(doc) = self.doc() else {
            return Vec::new();
        };
        let method = match doc.extra.get("ci_method").and_then(|v| v.as_str()) {
            Some(m) if m.to_ascii_lowercase().contains("bootstrap") => "bootstrap",
            Some(m) if m.to_ascii_lowercase().contains("jacobian") => "jacobian",
            _ => "fit",
        };
        doc.parameters
            .iter()
            .filter(|(_, p)| p.fitted && p.identifiable)
            .map(|(name, p)| Metric {
                name: format!("{FIT_PREFIX}{name}"),
                value: p.value,
                unit: fit_unit(name),
                ci95: p.ci95.map(|[low, high]| Ci95 { low, high, method }),
            })
            .collect()
    }
}

/// What [`RunFit::load`] checks beyond the schema tag.
fn check_fit_doc(doc: &FitDoc) -> Result<(), String> {
    for (name, p) in &doc.parameters {
        if !is_parameter_name(name) {
            return Err(format!(
                "parameters.{name}: not a parameter of the fit (known: {}, depth_mm.<layer>, \
                 mm_per_px.<layer>)",
                PARAMETER_NAMES.join(", ")
            ));
        }
        let unit = fit_unit(name);
        if p.unit != unit {
            return Err(format!(
                "parameters.{name}.unit = {:?}, where {name} is in {unit:?}",
                p.unit
            ));
        }
        for (key, v) in [("value", p.value), ("nominal", p.nominal)] {
            if !v.is_finite() {
                return Err(format!(
                    "parameters.{name}.{key} = {v} {unit} is not a finite number"
                ));
            }
        }
        if let Some([lo, hi]) = p.ci95 {
            if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
                return Err(format!(
                    "parameters.{name}.ci95 = [{lo}, {hi}] {unit} is not a finite interval \
                     with low <= high"
                ));
            }
        }
    }
    Ok(())
}

impl Criterion {
    /// Whether a bound is relative to a fitted parameter's nominal value.
    pub fn is_nominal_relative(&self) -> bool {
        self.max_relative_to_nominal.is_some() || self.max_deviation_from_nominal.is_some()
    }

    /// Whether a bound is relative to a baseline.
    pub fn is_relative(&self) -> bool {
        self.max_relative_to_baseline.is_some()
            || self.min_relative_to_baseline.is_some()
            || self.max_increase.is_some()
            || self.max_decrease.is_some()
    }

    /// The criterion with its relative bounds removed (`None`: it had only those),
    /// what applies to the baseline run itself.
    pub fn absolute_part(&self) -> Option<Criterion> {
        if self.min.is_none()
            && self.max.is_none()
            && self.max_relative_to_nominal.is_none()
            && self.max_deviation_from_nominal.is_none()
        {
            return None;
        }
        Some(Criterion {
            max_relative_to_baseline: None,
            min_relative_to_baseline: None,
            max_increase: None,
            max_decrease: None,
            ..self.clone()
        })
    }

    /// The inclusive limits `(low, high)` for a baseline value `baseline` (ignored
    /// without relative bounds): the tightest of the absolute and relative bounds.
    pub fn limits(&self, baseline: Option<f64>) -> (Option<f64>, Option<f64>) {
        let mut lo = self.min;
        let mut hi = self.max;
        if let Some(b) = baseline {
            let tighten_hi = |hi: &mut Option<f64>, v: f64| {
                *hi = Some(hi.map_or(v, |h: f64| h.min(v)));
            };
            let tighten_lo = |lo: &mut Option<f64>, v: f64| {
                *lo = Some(lo.map_or(v, |l: f64| l.max(v)));
            };
            if let Some(r) = self.max_relative_to_baseline {
                tighten_hi(&mut hi, b + r * b.abs());
            }
            if let Some(d) = self.max_increase {
                tighten_hi(&mut hi, b + d);
            }
            if let Some(r) = self.min_relative_to_baseline {
                tighten_lo(&mut lo, b - r * b.abs());
            }
            if let Some(d) = self.max_decrease {
                tighten_lo(&mut lo, b - d);
            }
        }
        (lo, hi)
    }

    /// [`Criterion::limits`] further tightened by the bounds relative to a fitted
    /// parameter's nominal value `nominal` (ignored when `None`).
    pub fn limits_with(
        &self,
        baseline: Option<f64>,
        nominal: Option<f64>,
    ) -> (Option<f64>, Option<f64>) {
        let (mut lo, mut hi) = self.limits(baseline);
        if let Some(n) = nominal {
            let half_widths = [
                self.max_relative_to_nominal.map(|r| r * n.abs()),
                self.max_deviation_from_nominal,
            ];
            for h in half_widths.into_iter().flatten() {
                lo = Some(lo.map_or(n - h, |l: f64| l.max(n - h)));
                hi = Some(hi.map_or(n + h, |u: f64| u.min(n + h)));
            }
        }
        (lo, hi)
    }

    /// A fitted parameter's outcome: FAIL outside the limits of
    /// [`Criterion::limits_with`] (or not finite); MARGINAL inside them when the 95 %
    /// interval `ci95` straddles a limit, or at or beyond a marginal bound; PASS
    /// otherwise.
    pub fn judge_interval(
        &self,
        value: f64,
        ci95: Option<[f64; 2]>,
        baseline: Option<f64>,
        nominal: Option<f64>,
    ) -> Outcome {
        let (lo, hi) = self.limits_with(baseline, nominal);
        let outside = |v: f64| lo.is_some_and(|lo| v < lo) || hi.is_some_and(|hi| v > hi);
        if !value.is_finite() || outside(value) {
            Outcome::Fail
        } else if ci95.is_some_and(|[a, b]| outside(a) || outside(b)) {
            Outcome::Marginal
        } else {
            self.judge_band(value)
        }
    }

    /// MARGINAL at or beyond a marginal bound, else PASS (the value within limits).
    fn judge_band(&self, value: f64) -> Outcome {
        if self.marginal_min.is_some_and(|lo| value <= lo)
            || self.marginal_max.is_some_and(|hi| value >= hi)
        {
            Outcome::Marginal
        } else {
            Outcome::Pass
        }
    }

    /// FAIL outside `[min, max]` or not finite; MARGINAL at or beyond a marginal
    /// bound; PASS otherwise (relative bounds are not applied: see
    /// [`Criterion::judge_against`]).
    pub fn judge(&self, value: f64) -> Outcome {
        self.judge_against(value, None)
    }

    /// As [`Criterion::judge`], the limits from [`Criterion::limits`] with the
    /// baseline's value `baseline`.
    pub fn judge_against(&self, value: f64, baseline: Option<f64>) -> Outcome {
        let (lo, hi) = self.limits(baseline);
        if !value.is_finite() || lo.is_some_and(|lo| value < lo) || hi.is_some_and(|hi| value > hi)
        {
            Outcome::Fail
        } else {
            self.judge_band(value)
        }
    }
}

/// The unit of a metric name from [`METRICS`] (`1` when unknown).
fn metric_unit(name: &str) -> &'static str {
    METRICS
        .iter()
        .find(|(pattern, _, _)| {
            let p: Vec<&str> = pattern.split('.').collect();
            let n: Vec<&str> = name.split('.').collect();
            p.len() == n.len() && p.iter().zip(&n).all(|(a, b)| *a == "<layer>" || a == b)
        })
        .map_or("1", |(_, unit, _)| unit)
}

/// The outcome of one criterion.
#[derive(Debug, Clone, PartialEq)]
pub struct Verdict {
    /// The criterion.
    pub criterion: Criterion,
    /// The run's value (NaN when it could not be computed, see `note`).
    pub value: f64,
    /// Its unit.
    pub unit: &'static str,
    /// PASS, MARGINAL or FAIL; NOT JUDGED for a fitted parameter nothing determined.
    pub outcome: Outcome,
    /// Why there is no value (the analysis that could not run, the fit that is
    /// missing or could not determine the parameter), if so.
    pub note: Option<String>,
    /// The baseline's value the relative bounds were taken from (`None` without
    /// relative bounds).
    pub baseline: Option<f64>,
    /// A fitted parameter's 95 % interval, which the outcome took into account.
    pub ci95: Option<[f64; 2]>,
    /// A fitted parameter's nominal value (the bounds relative to it are taken from it).
    pub nominal: Option<f64>,
}

impl Verdict {
    /// True unless FAIL (MARGINAL passes, visibly; NOT JUDGED is no pass either, see
    /// [`Outcome::combine`]).
    pub fn pass(&self) -> bool {
        self.outcome != Outcome::Fail
    }

    /// The inclusive limits the value was judged against (baseline- and
    /// nominal-relative bounds applied).
    pub fn limits(&self) -> (Option<f64>, Option<f64>) {
        self.criterion.limits_with(self.baseline, self.nominal)
    }
}

impl fmt::Display for Verdict {
    /// `PASS magnitude.r2 = 0.9987 (>= 0.99)`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let unit = match self.unit {
            "1" | "count" => String::new(),
            u => format!(" {u}"),
        };
        let mut value = match &self.note {
            Some(n) => format!("? ({n})"),
            None => format!("{}{unit}", fmt_value(self.value)),
        };
        if let (Some([lo, hi]), None) = (self.ci95, &self.note) {
            value.push_str(&format!(
                ", 95 % CI [{}, {}]{unit}",
                fmt_value(lo),
                fmt_value(hi)
            ));
        }
        let nominal = self
            .nominal
            .filter(|_| self.note.is_none() && self.criterion.is_nominal_relative());
        let mut refs = Vec::new();
        if let Some(b) = self.baseline {
            refs.push(format!("baseline {}{unit}", fmt_value(b)));
        }
        if let Some(n) = nominal {
            refs.push(format!("nominal {}{unit}", fmt_value(n)));
        }
        if refs.is_empty() {
            return write!(
                f,
                "{} {} = {value} ({}{unit})",
                self.outcome, self.criterion.metric, self.criterion
            );
        }
        let limits = match self.limits() {
            (Some(lo), Some(hi)) => format!("in [{}, {}]", fmt_value(lo), fmt_value(hi)),
            (Some(lo), None) => format!(">= {}", fmt_value(lo)),
            (None, Some(hi)) => format!("<= {}", fmt_value(hi)),
            (None, None) => String::new(),
        };
        write!(
            f,
            "{} {} = {value} ({}; {}: {limits}{unit})",
            self.outcome,
            self.criterion.metric,
            self.criterion,
            refs.join(", ")
        )
    }
}

/// Six significant digits, plain notation where reasonable.
pub fn fmt_value(v: f64) -> String {
    if !v.is_finite() {
        return format!("{v}");
    }
    if v == 0.0 {
        return "0".into();
    }
    let mag = v.abs().log10().floor() as i32;
    if (-4..7).contains(&mag) {
        let decimals = (5 - mag).max(0) as usize;
        let s = format!("{v:.decimals$}");
        if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            s
        }
    } else {
        format!("{v:.5e}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::{ParamFit, Route};

    fn metric(name: &str, value: f64) -> Metric {
        Metric::new(name, value, "1")
    }

    #[test]
    fn bounds_are_inclusive_and_nan_fails() {
        let c = Criteria::from_toml_str(
            "[[criterion]]\nmetric = \"magnitude.r2\"\nmin = 0.99\n\
             [[criterion]]\nmetric = \"magnitude.slope\"\nmin = 0.9\nmax = 1.1\n\
             [[criterion]]\nmetric = \"magnitude.linearity_pct\"\nmax = 1.0\n",
            Path::new("c.toml"),
        )
        .unwrap();
        let v = c
            .evaluate(
                &[
                    metric("magnitude.r2", 0.99),
                    metric("magnitude.slope", 1.2),
                    metric("magnitude.linearity_pct", f64::NAN),
                ],
                "magnitude",
                &[],
            )
            .unwrap();
        assert_eq!(
            v.iter().map(|v| v.pass()).collect::<Vec<_>>(),
            [true, false, false]
        );
        assert_eq!(
            v[1].to_string(),
            "FAIL magnitude.slope = 1.2 (in [0.9, 1.1])"
        );
    }

    #[test]
    fn bad_files_are_rejected_naming_the_criterion() {
        let p = Path::new("c.toml");
        let e = Criteria::from_toml_str("[[criterion]]\nmetric = \"magnitude.r3\"\nmin = 1.0\n", p)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("c.toml: criterion 1 (`magnitude.r3`): unknown metric"),
            "{e}"
        );
        assert!(
            e.contains("magnitude.r2") && e.contains("timing.forces_ms"),
            "{e}"
        );
        let e = Criteria::from_toml_str("[[criterion]]\nmetric = \"magnitude.r2\"\n", p)
            .unwrap_err()
            .to_string();
        assert!(e.contains("give min, max or both"), "{e}");
        let e = Criteria::from_toml_str(
            "[[criterion]]\nmetric = \"magnitude.r2\"\nmin = 2.0\nmax = 1.0\n",
            p,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("min = 2 is greater than max = 1"), "{e}");
        let e = Criteria::from_toml_str("[[criterion]]\nmetric = \"magnitude.r2\"\nmin = nan\n", p)
            .unwrap_err()
            .to_string();
        assert!(e.contains("not a finite number"), "{e}");
        let e = Criteria::from_toml_str(
            "[[criterion]]\nmetric = \"magnitude.r2\"\nminimum = 1.0\n",
            p,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("minimum") && e.contains("line"), "{e}");
        let e = Criteria::from_toml_str("", p).unwrap_err().to_string();
        assert!(e.contains("no [[criterion]]"), "{e}");
    }

    #[test]
    fn a_metric_the_run_lacks_is_an_error_not_a_pass() {
        let c = Criteria::from_toml_str(
            "[[criterion]]\nmetric = \"spatial.fwhm_mm\"\nmax = 5.0\n",
            Path::new("c.toml"),
        )
        .unwrap();
        let e = c
            .evaluate(&[metric("magnitude.r2", 1.0)], "magnitude", &[])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("has no such metric") && e.contains("magnitude.r2"),
            "{e}"
        );
        // An analysis that could not run on this run's data: FAIL with the reason.
        let absent = [("spatial".to_string(), "needs 3 loads, has 1".to_string())];
        let v = c
            .evaluate(&[metric("magnitude.r2", 1.0)], "spatial", &absent)
            .unwrap();
        assert_eq!(v[0].outcome, Outcome::Fail);
        assert_eq!(v[0].unit, "mm");
        assert!(
            v[0].to_string().contains("not computed: needs 3 loads"),
            "{}",
            v[0]
        );
    }

    #[test]
    fn a_marginal_band_inside_the_limits_gives_marginal() {
        let c = Criteria::from_toml_str(
            "require_build_id = true\n\
             [[criterion]]\nmetric = \"magnitude.r2\"\nmin = 0.99\nmarginal_min = 0.995\n\
             [[criterion]]\nmetric = \"timing.forces_ms\"\nmax = 2.9\nmarginal_max = 2.5\n",
            Path::new("c.toml"),
        )
        .unwrap();
        assert!(c.require_build_id);
        let r2 = &c.criteria[0];
        assert_eq!(r2.judge(0.989), Outcome::Fail);
        assert_eq!(r2.judge(0.99), Outcome::Marginal);
        assert_eq!(r2.judge(0.995), Outcome::Marginal);
        assert_eq!(r2.judge(0.996), Outcome::Pass);
        let t = &c.criteria[1];
        assert_eq!(t.judge(2.6), Outcome::Marginal);
        assert_eq!(t.judge(2.4), Outcome::Pass);
        assert_eq!(t.judge(3.0), Outcome::Fail);
        assert_eq!(t.judge(f64::NAN), Outcome::Fail);
        assert_eq!(r2.to_string(), ">= 0.99, marginal <= 0.995");
        let v = c
            .evaluate(
                &[
                    metric("magnitude.r2", 0.993),
                    metric("timing.forces_ms", 1.0),
                ],
                "magnitude",
                &[],
            )
            .unwrap();
        assert_eq!(
            v[0].to_string(),
            "MARGINAL magnitude.r2 = 0.993 (>= 0.99, marginal <= 0.995)"
        );
        assert!(v[0].pass());
        // The band must lie within the limits.
        let e = Criteria::from_toml_str(
            "[[criterion]]\nmetric = \"magnitude.r2\"\nmin = 0.99\nmarginal_min = 0.98\n",
            Path::new("c.toml"),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("min = 0.99 is greater than marginal_min = 0.98"),
            "{e}"
        );
        let e = Criteria::from_toml_str(
            "[[criterion]]\nmetric = \"magnitude.r2\"\nmax = 1\nmarginal_max = 1.5\n",
            Path::new("c.toml"),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("marginal_max = 1.5 is greater than max = 1"),
            "{e}"
        );
    }

    #[test]
    fn relative_bounds_take_their_limits_from_the_baseline() {
        let c = Criteria::from_toml_str(
            "[[criterion]]\nmetric = \"magnitude.resolution_gf\"\nmax = 30.0\nmax_relative_to_baseline = 0.1\n\
             [[criterion]]\nmetric = \"magnitude.offset_n\"\nmin_relative_to_baseline = 0.5\nmax_increase = 0.2\n\
             [[criterion]]\nmetric = \"magnitude.r2\"\nmax_decrease = 0.01\n",
            Path::new("c.toml"),
        )
        .unwrap();
        assert!(c.has_relative());
        let res = &c.criteria[0];
        // The tightest of max = 30 and 20 + 10 % = 22.
        assert_eq!(res.limits(Some(20.0)), (None, Some(22.0)));
        assert_eq!(res.limits(Some(40.0)), (None, Some(30.0)));
        assert_eq!(res.judge_against(22.0, Some(20.0)), Outcome::Pass);
        assert_eq!(res.judge_against(22.01, Some(20.0)), Outcome::Fail);
        // A negative baseline: relative to |b|.
        let off = &c.criteria[1];
        let (lo, hi) = off.limits(Some(-0.4));
        assert!((lo.unwrap() - -0.6).abs() < 1e-12 && (hi.unwrap() - -0.2).abs() < 1e-12);
        assert_eq!(res.absolute_part().unwrap().max_relative_to_baseline, None);
        assert_eq!(off.absolute_part(), None);
        assert_eq!(res.to_string(), "<= 30, <= baseline + 10 %");
        assert_eq!(off.to_string(), ">= baseline - 50 %, <= baseline + 0.2");
        // Judged against a baseline's metrics.
        let base = [
            metric("magnitude.resolution_gf", 20.0),
            metric("magnitude.offset_n", -0.4),
            metric("magnitude.r2", 0.999),
        ];
        let run = [
            metric("magnitude.resolution_gf", 25.0),
            metric("magnitude.offset_n", -0.5),
            metric("magnitude.r2", 0.99),
        ];
        let v = c
            .evaluate_against(&run, "magnitude", &[], Some(&base))
            .unwrap();
        assert_eq!(
            v.iter().map(|v| v.outcome).collect::<Vec<_>>(),
            [Outcome::Fail, Outcome::Pass, Outcome::Pass]
        );
        assert_eq!(v[0].baseline, Some(20.0));
        assert_eq!(
            v[0].to_string(),
            "FAIL magnitude.resolution_gf = 25 (<= 30, <= baseline + 10 %; baseline 20: <= 22)"
        );
        // No baseline (`report`): an error naming compare; a baseline without the
        // metric or with a non-finite value: an error.
        let e = c.evaluate(&run, "magnitude", &[]).unwrap_err().to_string();
        assert!(
            e.contains("criterion 1") && e.contains("needs a baseline"),
            "{e}"
        );
        let e = c
            .evaluate_against(&run, "magnitude", &[], Some(&base[..1]))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("criterion 2") && e.contains("baseline run has no value"),
            "{e}"
        );
        let nan = [metric("magnitude.resolution_gf", f64::NAN)];
        let e = c
            .evaluate_against(&run, "magnitude", &[], Some(&nan))
            .unwrap_err()
            .to_string();
        assert!(e.contains("not a finite number"), "{e}");
        // Bad relative bounds are rejected when loading.
        for bad in ["max_relative_to_baseline = -0.1", "max_increase = inf"] {
            let e = Criteria::from_toml_str(
                &format!("[[criterion]]\nmetric = \"magnitude.r2\"\n{bad}\n"),
                Path::new("c.toml"),
            )
            .unwrap_err()
            .to_string();
            assert!(e.contains("must be a finite number >= 0"), "{e}");
        }
        let e = Criteria::from_toml_str(
            "[[criterion]]\nmetric = \"magnitude.r2\"\n",
            Path::new("c.toml"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("max_relative_to_baseline"), "{e}");
    }

    fn param(value: f64, ci95: Option<[f64; 2]>, nominal: f64, unit: &str) -> ParamFit {
        ParamFit {
            value,
            ci95,
            unit: unit.into(),
            identifiable: ci95.is_some(),
            route: Route::Both,
            nominal,
            sd: ci95.map(|[lo, hi]| (hi - lo) / 3.92),
            fitted: ci95.is_some(),
            reason: None,
        }
    }

    fn fit_doc(params: Vec<(&str, ParamFit)>) -> RunFit {
        RunFit::Found {
            path: PathBuf::from("runs/b1/fit.json"),
            doc: Box::new(FitDoc {
                schema: crate::fit::FIT_SCHEMA.into(),
                run: "runs/b1".into(),
                sensor: "s.toml".into(),
                parameters: params
                    .into_iter()
                    .map(|(k, v)| (k.to_string(), v))
                    .collect(),
                routes: serde_json::Value::Null,
                residual_rms_px: Default::default(),
                cross_validation: serde_json::Value::Null,
                extra: Default::default(),
            }),
        }
    }

    const FIT_CRITERIA: &str = "[[criterion]]\nmetric = \"fit.young_modulus_kpa\"\n\
         max_relative_to_nominal = 0.10\n\
         [[criterion]]\nmetric = \"fit.depth_mm.blue\"\nmax_deviation_from_nominal = 0.3\n";

    fn judge_fit(fit: &RunFit) -> Vec<Verdict> {
        Criteria::from_toml_str(FIT_CRITERIA, Path::new("c.toml"))
            .unwrap()
            .evaluate_with_fit(&[], "magnitude", &[], None, Some(fit))
            .unwrap()
    }

    #[test]
    fn a_fitted_parameter_is_marginal_when_its_interval_straddles_a_nominal_limit() {
        // E nominal 100 kPa, ±10 %: limits [90, 110]; depth nominal 3 mm, ±0.3 mm.
        let cases = [
            (
                104.0,
                [100.0, 108.0],
                3.2,
                [3.1, 3.25],
                [Outcome::Pass, Outcome::Pass],
            ),
            (
                104.0,
                [98.0, 111.0],
                3.25,
                [3.1, 3.35],
                [Outcome::Marginal, Outcome::Marginal],
            ),
            (
                112.0,
                [109.0, 115.0],
                3.5,
                [3.45, 3.55],
                [Outcome::Fail, Outcome::Fail],
            ),
            // Below the lower limit, its interval reaching inside: still FAIL.
            (
                89.0,
                [85.0, 93.0],
                2.65,
                [2.6, 2.75],
                [Outcome::Fail, Outcome::Fail],
            ),
        ];
        for (e, e_ci, d, d_ci, want) in cases {
            let fit = fit_doc(vec![
                ("young_modulus_kpa", param(e, Some(e_ci), 100.0, "kPa")),
                ("depth_mm.blue", param(d, Some(d_ci), 3.0, "mm")),
            ]);
            let v = judge_fit(&fit);
            assert_eq!([v[0].outcome, v[1].outcome], want, "E {e}, depth {d}");
            let (lo, hi) = v[0].limits();
            assert!((lo.unwrap() - 90.0).abs() < 1e-9 && (hi.unwrap() - 110.0).abs() < 1e-9);
            assert_eq!(v[0].unit, "kPa");
        }
        let fit = fit_doc(vec![
            (
                "young_modulus_kpa",
                param(104.0, Some([98.0, 111.0]), 100.0, "kPa"),
            ),
            ("depth_mm.blue", param(3.2, Some([3.1, 3.25]), 3.0, "mm")),
        ]);
        let v = judge_fit(&fit);
        assert_eq!(
            v[0].to_string(),
            "MARGINAL fit.young_modulus_kpa = 104 kPa, 95 % CI [98, 111] kPa \
             (within ±10 % of nominal; nominal 100 kPa: in [90, 110] kPa)"
        );
        // A fitted parameter's absolute bounds and marginal bands apply as for any
        // metric, and the tightest limit wins.
        let c = Criteria::from_toml_str(
            "[[criterion]]\nmetric = \"fit.young_modulus_kpa\"\nmax = 105.0\n\
             max_relative_to_nominal = 0.10\n",
            Path::new("c.toml"),
        )
        .unwrap();
        let v = c
            .evaluate_with_fit(&[], "magnitude", &[], None, Some(&fit))
            .unwrap();
        assert_eq!(v[0].limits(), (Some(90.0), Some(105.0)));
        assert_eq!(v[0].outcome, Outcome::Marginal);
    }

    #[test]
    fn an_unidentifiable_held_or_missing_parameter_is_not_judged_with_the_reason() {
        let mut held = param(3.0, None, 3.0, "mm");
        held.reason = Some("one layer and one load position: add positions".into());
        let mut unident = param(100.0, None, 100.0, "kPa");
        unident.fitted = true;
        unident.reason = Some("no setpoint loads past contact: add normal setpoints".into());
        let v = judge_fit(&fit_doc(vec![
            ("young_modulus_kpa", unident),
            ("depth_mm.blue", held),
        ]));
        assert_eq!(v[0].outcome, Outcome::NotJudged);
        assert!(
            v[0].to_string().contains(
                "not identifiable from this run: no setpoint loads past contact: add normal"
            ),
            "{}",
            v[0]
        );
        assert_eq!(v[1].outcome, Outcome::NotJudged);
        assert!(
            v[1].note
                .as_deref()
                .unwrap()
                .contains("not fitted: held at its nominal 3 mm: one layer"),
            "{:?}",
            v[1].note
        );
        assert!(v.iter().all(|v| v.value.is_nan() && v.ci95.is_none()));
        // No fit for the run: NOT JUDGED, saying how to make one.
        let v = judge_fit(&RunFit::Missing(
            "no fit: runs/b1/fit.json does not exist".into(),
        ));
        assert!(v.iter().all(|v| v.outcome == Outcome::NotJudged));
        assert!(v[0]
            .note
            .as_deref()
            .unwrap()
            .contains("fit.json does not exist"));
        let c = Criteria::from_toml_str(FIT_CRITERIA, Path::new("c.toml")).unwrap();
        let v = c.evaluate(&[], "magnitude", &[]).unwrap();
        assert!(v.iter().all(|v| v.outcome == Outcome::NotJudged));
        // A layer the fit does not have: an error naming what it has.
        let e = c
            .evaluate_with_fit(
                &[],
                "magnitude",
                &[],
                None,
                Some(&fit_doc(vec![(
                    "young_modulus_kpa",
                    param(100.0, Some([99.0, 101.0]), 100.0, "kPa"),
                )])),
            )
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("runs/b1/fit.json: no parameter `depth_mm.blue`")
                && e.contains("the fit has: young_modulus_kpa"),
            "{e}"
        );
    }

    #[test]
    fn a_verdict_with_a_criterion_nothing_judged_is_never_pass() {
        use Outcome::*;
        assert_eq!(Outcome::combine([]), NotJudged);
        assert_eq!(Outcome::combine([Pass, Pass]), Pass);
        assert_eq!(Outcome::combine([Pass, NotJudged]), NotJudged);
        assert_eq!(Outcome::combine([Marginal, NotJudged, Pass]), NotJudged);
        assert_eq!(Outcome::combine([NotJudged, Fail]), Fail);
        assert_eq!(Outcome::combine([Pass, Marginal]), Marginal);
    }

    #[test]
    fn nominal_bounds_are_for_fitted_parameters_only_and_checked_when_loading() {
        let p = Path::new("c.toml");
        let e = Criteria::from_toml_str(
            "[[criterion]]\nmetric = \"magnitude.r2\"\nmax_relative_to_nominal = 0.1\n",
            p,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("criterion 1 (`magnitude.r2`): max_relative_to_nominal applies to fitted parameters only"), "{e}");
        let e = Criteria::from_toml_str(
            "[[criterion]]\nmetric = \"fit.young_modulus_kpa\"\nmax_deviation_from_nominal = -1\n",
            p,
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("max_deviation_from_nominal = -1 must be a finite number >= 0"),
            "{e}"
        );
        let e = Criteria::from_toml_str(
            "[[criterion]]\nmetric = \"fit.youngs_modulus\"\nmax = 1\n",
            p,
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("unknown metric") && e.contains("fit.young_modulus_kpa [kPa]"),
            "{e}"
        );
        let e = Criteria::from_toml_str("[[criterion]]\nmetric = \"fit.depth_mm.blue\"\n", p)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("max_relative_to_nominal, max_deviation_from_nominal"),
            "{e}"
        );
        let c = Criteria::from_toml_str(FIT_CRITERIA, p).unwrap();
        assert_eq!(c.criteria[0].to_string(), "within ±10 % of nominal");
        assert_eq!(c.criteria[1].to_string(), "within ±0.3 of nominal");
        // Nominal bounds are not baseline-relative: the baseline run keeps them.
        assert_eq!(c.criteria[1].absolute_part().as_ref(), Some(&c.criteria[1]));
    }

    #[test]
    fn a_fit_file_is_checked_naming_the_key_and_its_fitted_parameters_become_metrics() {
        let tmp = tempfile::tempdir().unwrap();
        let run = tmp.path();
        match RunFit::load(run, None).unwrap() {
            RunFit::Missing(why) => assert!(why.contains("tactbench fit"), "{why}"),
            f => panic!("{f:?}"),
        }
        let e = RunFit::load(run, Some(&run.join("nope.json")))
            .unwrap_err()
            .to_string();
        assert!(e.contains("nope.json: cannot read the fit"), "{e}");
        let RunFit::Found { doc: boxed, .. } = fit_doc(vec![
            (
                "young_modulus_kpa",
                param(104.0, Some([98.0, 111.0]), 100.0, "kPa"),
            ),
            ("thickness_mm", param(40.0, None, 40.0, "mm")),
        ]) else {
            unreachable!()
        };
        let doc = *boxed;
        let path = run.join(FIT_FILE);
        let write =
            |doc: &FitDoc| std::fs::write(&path, serde_json::to_string(doc).unwrap()).unwrap();
        write(&doc);
        let fit = RunFit::load(run, None).unwrap();
        let m = fit.metrics();
        assert_eq!(m.len(), 1, "held parameters are no metric: {m:?}");
        assert_eq!(
            (m[0].name.as_str(), m[0].value, m[0].unit),
            ("fit.young_modulus_kpa", 104.0, "kPa")
        );
        assert_eq!(
            m[0].ci95.map(|c| (c.low, c.high, c.method)),
            Some((98.0, 111.0, "fit"))
        );
        let mut bad = doc.clone();
        bad.parameters.get_mut("young_modulus_kpa").unwrap().unit = "Pa".into();
        write(&bad);
        let e = RunFit::load(run, None).unwrap_err().to_string();
        assert!(e.contains("fit.json: parameters.young_modulus_kpa.unit = \"Pa\", where young_modulus_kpa is in \"kPa\""), "{e}");
        let mut bad = doc.clone();
        bad.parameters.get_mut("young_modulus_kpa").unwrap().ci95 = Some([111.0, 98.0]);
        write(&bad);
        let e = RunFit::load(run, None).unwrap_err().to_string();
        assert!(
            e.contains("parameters.young_modulus_kpa.ci95 = [111, 98] kPa"),
            "{e}"
        );
        let mut bad = doc.clone();
        let p = bad.parameters.remove("thickness_mm").unwrap();
        bad.parameters.insert("thickness".into(), p);
        write(&bad);
        let e = RunFit::load(run, None).unwrap_err().to_string();
        assert!(
            e.contains("parameters.thickness: not a parameter of the fit"),
            "{e}"
        );
        std::fs::write(&path, "{\"parameters\": 3}").unwrap();
        let e = RunFit::load(run, None).unwrap_err().to_string();
        assert!(e.contains("fit.json: not a fit.json"), "{e}");
    }

    #[test]
    fn values_print_with_six_significant_digits() {
        assert_eq!(fmt_value(0.998765432), "0.998765");
        assert_eq!(fmt_value(2.9), "2.9");
        assert_eq!(fmt_value(1234.5678), "1234.57");
        assert_eq!(fmt_value(1.5e-7), "1.50000e-7");
    }
}
