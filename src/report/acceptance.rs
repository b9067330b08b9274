//! Acceptance criteria (`--acceptance CRITERIA.toml`) and their verdicts.
//!
//! ```toml
//! # Optional: the run must record an elastomer build id (`--build-id` or the plan's
//! # `build_id`), else the verdict is FAIL.
//! require_build_id = true
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
    #[error("{path}: no [[criterion]] entries")]
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
}

/// The outcome of a criterion, a requirement or a whole verdict.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "UPPERCASE")]
pub enum Outcome {
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
    /// `PASS`, `MARGINAL`, `FAIL`, `INCOMPLETE`.
    pub fn word(self) -> &'static str {
        match self {
            Outcome::Pass => "PASS",
            Outcome::Marginal => "MARGINAL",
            Outcome::Fail => "FAIL",
            Outcome::Incomplete => "INCOMPLETE",
        }
    }
}

impl fmt::Display for Outcome {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.word())
    }
}

impl fmt::Display for Criterion {
    /// The threshold as text: `>= 0.99`, `<= 2.9`, `in [0, 2.9]`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match (self.min, self.max) {
            (Some(lo), Some(hi)) => write!(f, "in [{lo}, {hi}]"),
            (Some(lo), None) => write!(f, ">= {lo}"),
            (None, Some(hi)) => write!(f, "<= {hi}"),
            (None, None) => f.write_str("(no bound)"),
        }?;
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
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCriteria {
    #[serde(default)]
    require_build_id: bool,
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
        if raw.criterion.is_empty() {
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
            match (c.min, c.max) {
                (None, None) => return Err(invalid("give min, max or both".into())),
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
            });
        }
        Ok(Criteria {
            path: path.to_path_buf(),
            criteria,
            require_build_id: raw.require_build_id,
        })
    }

    /// Judges `metrics` (a run's [`crate::analysis::RunAnalysis::metrics`]); `sweep`
    /// names the run's sweep kind in messages; `absent` lists the analyses that could
    /// not run on this run's data as (metric prefix, reason): their criteria FAIL
    /// with the reason instead of being errors.
    pub fn evaluate(
        &self,
        metrics: &[Metric],
        sweep: &str,
        absent: &[(String, String)],
    ) -> Result<Vec<Verdict>, AcceptanceError> {
        let mut out = Vec::with_capacity(self.criteria.len());
        for (i, c) in self.criteria.iter().enumerate() {
            let prefix = c.metric.split('.').next().unwrap_or_default();
            if let Some((_, why)) = absent.iter().find(|(p, _)| p == prefix) {
                if !metrics.iter().any(|m| m.name == c.metric) {
                    out.push(Verdict {
                        criterion: c.clone(),
                        value: f64::NAN,
                        unit: metric_unit(&c.metric),
                        outcome: Outcome::Fail,
                        note: Some(format!("not computed: {why}")),
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
                outcome: c.judge(m.value),
                note: None,
            });
        }
        Ok(out)
    }
}

impl Criterion {
    /// FAIL outside `[min, max]` or not finite; MARGINAL at or beyond a marginal
    /// bound; PASS otherwise.
    pub fn judge(&self, value: f64) -> Outcome {
        if !value.is_finite()
            || self.min.is_some_and(|lo| value < lo)
            || self.max.is_some_and(|hi| value > hi)
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
        write!(
            f,
            "{} {} = {value} ({}{unit})",
            self.outcome, self.criterion.metric, self.criterion
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
    fn values_print_with_six_significant_digits() {
        assert_eq!(fmt_value(0.998765432), "0.998765");
        assert_eq!(fmt_value(2.9), "2.9");
        assert_eq!(fmt_value(1234.5678), "1234.57");
        assert_eq!(fmt_value(1.5e-7), "1.50000e-7");
    }
}
