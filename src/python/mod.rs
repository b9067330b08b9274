//! The Python package `tactbench` (feature `python`; maturin builds it from
//! pyproject.toml as `tactbench._native`, re-exported by `src/python/tactbench/`).
//!
//! A thin layer: NumPy arrays and Python values are converted and handed to the
//! library; nothing here measures, solves or parses a format itself. `sensor` loads a
//! sensor file, `frame` turns a NumPy array into a [`crate::vision::FrameView`] (or a
//! clear `ValueError`), `tracker` and `solver` wrap [`crate::vision::Tracker`] and
//! [`crate::solve::precompute`] (GIL released while they run), `run` reads a run
//! directory's files. Errors become `FileNotFoundError` / `OSError` (a file that could
//! not be read) or `ValueError`, carrying the CLI's message and its causes.

use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyValueError};
use pyo3::prelude::*;

mod frame;
mod run;
mod sensor;
mod solver;
mod tracker;

/// An error and its causes as the CLI prints them (`error: A`, `caused by: B`), on one
/// line, as a Python exception: `FileNotFoundError` when a cause is a missing file,
/// `OSError` for another I/O error, else `ValueError`.
pub(crate) fn to_py_err(err: &(dyn std::error::Error + 'static)) -> PyErr {
    let mut shown: Vec<String> = Vec::new();
    let mut io_kind = None;
    let mut cause: Option<&(dyn std::error::Error + 'static)> = Some(err);
    while let Some(e) = cause {
        if let Some(io) = e.downcast_ref::<std::io::Error>() {
            io_kind.get_or_insert(io.kind());
        }
        let text = e.to_string();
        if !shown.iter().any(|s| s.contains(&text)) {
            shown.push(text);
        }
        cause = e.source();
    }
    let message = shown.join(": caused by: ");
    match io_kind {
        Some(std::io::ErrorKind::NotFound) => PyFileNotFoundError::new_err(message),
        Some(_) => PyOSError::new_err(message),
        None => PyValueError::new_err(message),
    }
}

/// A `ValueError` with this message.
pub(crate) fn value_error(message: impl Into<String>) -> PyErr {
    PyValueError::new_err(message.into())
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<sensor::PySensor>()?;
    m.add_class::<tracker::PyTracker>()?;
    m.add_class::<solver::PySolver>()?;
    m.add_function(wrap_pyfunction!(run::read_run_parts, m)?)?;
    m.add_function(wrap_pyfunction!(run::read_csv_columns, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
