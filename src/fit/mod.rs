//! Identifying the sensor model from a characterization run (`tactbench fit`, issue 30).
//!
//! `doc`: the `fit.json` document (the contract `report`, `compare` and `fit.html`
//! read). The fit itself (run data, the indentation and displacement routes, the
//! least-squares engine, intervals and identifiability, cross-validation, `fitted.toml`)
//! lives in the sibling files this module lists as they are built.

pub mod crossval;
pub mod displacement;
pub mod doc;
pub mod fitted_toml;
pub mod force_error;
pub mod identify;
pub mod indentation;
pub mod lm;
pub mod predict;
pub mod space;

pub use doc::{is_parameter_name, FitDoc, ParamFit, Route, FIT_SCHEMA, PARAMETER_NAMES};
pub mod params;

pub use params::{ModelParams, Residuals};

use std::path::PathBuf;

use thiserror::Error;

/// Why a fit could not be made. Bad input names the file, the key or column, and the
/// value; a run that cannot determine what was asked says what kind of setpoint would.
#[derive(Debug, Error)]
pub enum FitError {
    /// Unreadable or invalid input (run directory, sensor file, plan, parameter list).
    #[error("{path}: {message}")]
    Input {
        /// The file or directory at fault.
        path: PathBuf,
        /// What is wrong with it: key or column, value, unit.
        message: String,
    },
    /// The run holds too little of what the fit needs (no F/T data, no displacements,
    /// one setpoint, no shear): the message names what to measure.
    #[error("{0}")]
    NotEnoughData(String),
    /// The least-squares problem failed numerically (the message says how).
    #[error("{0}")]
    Numerical(String),
}
