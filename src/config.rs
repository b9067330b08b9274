//! What the TOML file formats (sensor.toml, experiment plans) share: one error type
//! that names the file, the key, the value with its unit and what is allowed, and the
//! range checks that produce it. Raw TOML is parsed once (serde, unknown keys denied)
//! and then validated into typed values through a [`Checker`].

use std::fmt;
use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use thiserror::Error;

/// An error reading or validating a configuration file. Every variant names the file.
#[derive(Debug, Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read {what} {path}: {source}")]
    Io {
        /// What the file is (`sensor file`, `plan`).
        what: &'static str,
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// Not valid TOML for the schema (syntax, unknown key, wrong type), with line and
    /// column.
    #[error("{path}: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// The parser's message.
        message: String,
    },
    /// A value is out of its allowed range.
    #[error("{path}: {key} = {value} is invalid: {allowed}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// The offending key, e.g. `elastomer.poisson_ratio` or `layers[1].depth_mm`.
        key: String,
        /// The offending value as written, with its unit.
        value: String,
        /// What is allowed, with units.
        allowed: String,
    },
}

/// Reads a file as text; `what` names it in the error.
pub fn read_text(path: &Path, what: &'static str) -> Result<String, ConfigError> {
    std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
        what,
        path: path.to_path_buf(),
        source,
    })
}

/// Parses TOML text into the raw schema type; `path` names the file in errors.
pub fn parse_toml<T: DeserializeOwned>(text: &str, path: &Path) -> Result<T, ConfigError> {
    toml::from_str(text).map_err(|e| ConfigError::Parse {
        path: path.to_path_buf(),
        message: e.to_string().trim_end().to_string(),
    })
}

/// Range checks for one file; every error names the file, key, value and unit.
#[derive(Debug, Clone, Copy)]
pub struct Checker<'a> {
    /// The file being validated.
    pub path: &'a Path,
}

impl Checker<'_> {
    /// An `Invalid` error for `key`.
    pub fn invalid(
        &self,
        key: &str,
        value: impl fmt::Display,
        allowed: impl Into<String>,
    ) -> ConfigError {
        ConfigError::Invalid {
            path: self.path.to_path_buf(),
            key: key.to_string(),
            value: value.to_string(),
            allowed: allowed.into(),
        }
    }

    /// `v` finite and > 0 (in `unit`).
    pub fn positive(&self, key: &str, v: f64, unit: &str) -> Result<f64, ConfigError> {
        if v.is_finite() && v > 0.0 {
            Ok(v)
        } else {
            Err(self.invalid(
                key,
                with_unit(v, unit),
                format!("must be a finite number > 0 {unit}"),
            ))
        }
    }

    /// `v` finite and ≥ 0 (in `unit`).
    pub fn non_negative(&self, key: &str, v: f64, unit: &str) -> Result<f64, ConfigError> {
        if v.is_finite() && v >= 0.0 {
            Ok(v)
        } else {
            Err(self.invalid(
                key,
                with_unit(v, unit),
                format!("must be a finite number >= 0 {unit}"),
            ))
        }
    }

    /// `v` finite (in `unit`).
    pub fn finite(&self, key: &str, v: f64, unit: &str) -> Result<f64, ConfigError> {
        if v.is_finite() {
            Ok(v)
        } else {
            Err(self.invalid(
                key,
                with_unit(v, unit),
                format!("must be a finite number ({unit})"),
            ))
        }
    }

    /// An integer count in `[1, max]`.
    pub fn count(&self, key: &str, v: i64, max: i64) -> Result<usize, ConfigError> {
        if (1..=max).contains(&v) {
            Ok(v as usize)
        } else {
            Err(self.invalid(key, v, format!("must be an integer in [1, {max}]")))
        }
    }
}

fn with_unit(v: f64, unit: &str) -> String {
    if unit.is_empty() {
        v.to_string()
    } else {
        format!("{v} {unit}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_name_file_key_value_unit_and_range() {
        let c = Checker {
            path: Path::new("x.toml"),
        };
        let e = c
            .positive("a.pitch_mm", -1.5, "mm")
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            "x.toml: a.pitch_mm = -1.5 mm is invalid: must be a finite number > 0 mm"
        );
        assert!(c.finite("b", f64::NAN, "mm").is_err());
        assert_eq!(c.count("n", 3, 4).unwrap(), 3);
        assert!(c
            .count("n", 0, 4)
            .unwrap_err()
            .to_string()
            .contains("[1, 4]"));
        assert_eq!(c.non_negative("z", 0.0, "s").unwrap(), 0.0);
        let e = read_text(Path::new("/nonexistent/s.toml"), "sensor file")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("cannot read sensor file /nonexistent/s.toml"),
            "{e}"
        );
    }
}
