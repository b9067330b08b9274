//! Acceptance criteria (`--acceptance CRITERIA.toml`) and their verdicts.
//!
//! ```toml
//! # Each criterion bounds one metric of the run (names: `tactbench report --help`,
//! # the README, or analysis::METRICS). At least one of min / max; bounds inclusive.
//! [[criterion]]
//! metric = "magnitude.r2"
//! min = 0.99
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
//! Rejected when loading (naming the file and the criterion): TOML errors and unknown
//! keys, no criterion, a criterion with neither bound, non-finite bounds, `min > max`,
//! and metric names the analyses never produce (the message lists the known ones).
//! A known metric that this run does not have (e.g. `spatial.fwhm_mm` on a magnitude
//! run) is an error when evaluating, never a silent pass. A metric value that is not a
//! finite number fails its criterion.

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
}

impl fmt::Display for Criterion {
    /// The threshold as text: `>= 0.99`, `<= 2.9`, `in [0, 2.9]`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match (self.min, self.max) {
            (Some(lo), Some(hi)) => write!(f, "in [{lo}, {hi}]"),
            (Some(lo), None) => write!(f, ">= {lo}"),
            (None, Some(hi)) => write!(f, "<= {hi}"),
            (None, None) => f.write_str("(no bound)"),
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
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCriteria {
    #[serde(default)]
    criterion: Vec<RawCriterion>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCriterion {
    metric: String,
    min: Option<f64>,
    max: Option<f64>,
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
            for (key, v) in [("min", c.min), ("max", c.max)] {
                if let Some(v) = v {
                    if !v.is_finite() {
                        return Err(invalid(format!("{key} = {v} is not a finite number")));
                    }
                }
            }
            criteria.push(Criterion {
                metric: c.metric,
                min: c.min,
                max: c.max,
            });
        }
        Ok(Criteria {
            path: path.to_path_buf(),
            criteria,
        })
    }

    /// Judges `metrics` (a run's [`crate::analysis::RunAnalysis::metrics`]); `sweep`
    /// names the run's sweep kind in messages.
    pub fn evaluate(
        &self,
        metrics: &[Metric],
        sweep: &str,
    ) -> Result<Vec<Verdict>, AcceptanceError> {
        let mut out = Vec::with_capacity(self.criteria.len());
        for (i, c) in self.criteria.iter().enumerate() {
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
            let pass = m.value.is_finite()
                && c.min.is_none_or(|lo| m.value >= lo)
                && c.max.is_none_or(|hi| m.value <= hi);
            out.push(Verdict {
                criterion: c.clone(),
                value: m.value,
                unit: m.unit,
                pass,
            });
        }
        Ok(out)
    }
}

/// The outcome of one criterion.
#[derive(Debug, Clone, PartialEq)]
pub struct Verdict {
    /// The criterion.
    pub criterion: Criterion,
    /// The run's value.
    pub value: f64,
    /// Its unit.
    pub unit: &'static str,
    /// Whether the value is within the bounds.
    pub pass: bool,
}

impl fmt::Display for Verdict {
    /// `PASS magnitude.r2 = 0.9987 (>= 0.99)`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let unit = match self.unit {
            "1" | "count" => String::new(),
            u => format!(" {u}"),
        };
        write!(
            f,
            "{} {} = {}{unit} ({}{unit})",
            if self.pass { "PASS" } else { "FAIL" },
            self.criterion.metric,
            fmt_value(self.value),
            self.criterion
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
        Metric {
            name: name.into(),
            value,
            unit: "1",
        }
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
            )
            .unwrap();
        assert_eq!(
            v.iter().map(|v| v.pass).collect::<Vec<_>>(),
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
            .evaluate(&[metric("magnitude.r2", 1.0)], "magnitude")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("has no such metric") && e.contains("magnitude.r2"),
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
