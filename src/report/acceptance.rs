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

use crate::analysis::{is_known_metric, Metric, METRICS};
use crate::config::{self, ConfigError};

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
    /// Nothing was judged: no criteria and no requirements (verdicts only; exit 0,
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
}

/// The known metric names, one per line, for messages and `--help`.
pub fn known_metrics_text() -> String {
    METRICS
        .iter()
        .map(|(name, unit, what)| format!("  {name} [{unit}]: {what}"))
        .collect::<Vec<_>>()
        .join("\n")
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
            if !is_known_metric(&c.metric) {
                return Err(invalid(format!(
                    "unknown metric; known metrics (<layer> = a layer name of the sensor):\n{}",
                    known_metrics_text()
                )));
            }
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
                (None, None) if !has_relative => {
                    return Err(invalid(format!(
                        "give min, max or both (or a bound relative to a baseline run: {})",
                        RELATIVE_KEYS.join(", ")
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
    /// error naming the criterion.
    pub fn evaluate_against(
        &self,
        metrics: &[Metric],
        sweep: &str,
        absent: &[(String, String)],
        baseline: Option<&[Metric]>,
    ) -> Result<Vec<Verdict>, AcceptanceError> {
        let mut out = Vec::with_capacity(self.criteria.len());
        for (i, c) in self.criteria.iter().enumerate() {
            let invalid = |message: String| AcceptanceError::Invalid {
                path: self.path.clone(),
                number: i + 1,
                metric: c.metric.clone(),
                message,
            };
            let base = if c.is_relative() {
                let Some(b) = baseline else {
                    return Err(invalid(
                        "a bound relative to a baseline run needs a baseline: judge it with \
                         `tactbench compare RUN_DIR... --baseline BASELINE_DIR`"
                            .into(),
                    ));
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
                    });
                    continue;
                }
            }
            let Some(m) = metrics.iter().find(|m| m.name == c.metric) else {
                let have: Vec<&str> = metrics.iter().map(|m| m.name.as_str()).collect();
                return Err(AcceptanceError::Invalid {
                    path: self.path.clone(),
                    number: i + 1,
                    metric: c.metric.clone(),
                    message: format!(
                        "this run ({sweep} sweep) has no such metric; it has: {}",
                        have.join(", ")
                    ),
                });
            };
            out.push(Verdict {
                criterion: c.clone(),
                value: m.value,
                unit: m.unit,
                outcome: c.judge_against(m.value, base),
                note: None,
                baseline: base,
            });
        }
        Ok(out)
    }
}

impl Criterion {
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
        if self.min.is_none() && self.max.is_none() {
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
        } else if self.marginal_min.is_some_and(|lo| value <= lo)
            || self.marginal_max.is_some_and(|hi| value >= hi)
        {
            Outcome::Marginal
        } else {
            Outcome::Pass
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
    /// PASS, MARGINAL or FAIL.
    pub outcome: Outcome,
    /// Why there is no value (the analysis that could not run), if so.
    pub note: Option<String>,
    /// The baseline's value the relative bounds were taken from (`None` without
    /// relative bounds).
    pub baseline: Option<f64>,
}

impl Verdict {
    /// True unless FAIL (MARGINAL passes, visibly).
    pub fn pass(&self) -> bool {
        self.outcome != Outcome::Fail
    }
}

impl fmt::Display for Verdict {
    /// `PASS magnitude.r2 = 0.9987 (>= 0.99)`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let unit = match self.unit {
            "1" | "count" => String::new(),
            u => format!(" {u}"),
        };
        let value = match &self.note {
            Some(n) => format!("? ({n})"),
            None => format!("{}{unit}", fmt_value(self.value)),
        };
        let Some(b) = self.baseline else {
            return write!(
                f,
                "{} {} = {value} ({}{unit})",
                self.outcome, self.criterion.metric, self.criterion
            );
        };
        let (lo, hi) = self.criterion.limits(Some(b));
        let limits = match (lo, hi) {
            (Some(lo), Some(hi)) => format!("in [{}, {}]", fmt_value(lo), fmt_value(hi)),
            (Some(lo), None) => format!(">= {}", fmt_value(lo)),
            (None, Some(hi)) => format!("<= {}", fmt_value(hi)),
            (None, None) => String::new(),
        };
        write!(
            f,
            "{} {} = {value} ({}; baseline {}{unit}: {limits}{unit})",
            self.outcome,
            self.criterion.metric,
            self.criterion,
            fmt_value(b)
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

    #[test]
    fn values_print_with_six_significant_digits() {
        assert_eq!(fmt_value(0.998765432), "0.998765");
        assert_eq!(fmt_value(2.9), "2.9");
        assert_eq!(fmt_value(1234.5678), "1234.57");
        assert_eq!(fmt_value(1.5e-7), "1.50000e-7");
    }
}
