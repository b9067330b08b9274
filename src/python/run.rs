//! `tactbench.read_run`'s native half: a run directory's files as Python values.
//! `manifest.json` is validated by the library's reader (its errors are the CLI's) and
//! handed over as text for `json.loads` (every key kept); CSVs (the journal, a
//! setpoint's displacements and forces) become columns: int64 when every cell is an
//! integer, bool when every cell is true/false, float64 when every non-empty cell is a
//! number (empty cells NaN: a failed setpoint's force columns), else str. Unknown
//! columns are kept as they come. A journal's torn last line (a live or killed run
//! mid-append) is skipped, as the library's `read_journal` does.

use std::path::{Path, PathBuf};

use numpy::PyArray1;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::to_py_err;
use crate::analysis::{displacements_path, forces_path};
use crate::bench::journal::{JournalError, Manifest, JOURNAL_FILE, MANIFEST_FILE};
use crate::report::verdict::VERDICT_FILE;

fn read(path: &Path) -> PyResult<Vec<u8>> {
    std::fs::read(path).map_err(|source| {
        to_py_err(&JournalError::Io {
            path: path.to_path_buf(),
            source,
        })
    })
}

/// The columns of CSV text (complete lines only) as a dict of arrays, in file order.
fn columns<'py>(py: Python<'py>, bytes: &[u8], path: &Path) -> PyResult<Bound<'py, PyDict>> {
    let keep = bytes
        .iter()
        .rposition(|&b| b == b'\n')
        .map_or(bytes.len(), |i| i + 1);
    let mut rdr = csv::ReaderBuilder::new()
        .flexible(true)
        .from_reader(&bytes[..keep]);
    let corrupt = |e: csv::Error| {
        let line = e.position().map_or(0, |p| p.line());
        super::value_error(format!("{}:{line}: {e}", path.display()))
    };
    let header: Vec<String> = rdr
        .headers()
        .map_err(corrupt)?
        .iter()
        .map(str::to_string)
        .collect();
    let mut cells: Vec<Vec<String>> = vec![Vec::new(); header.len()];
    for rec in rdr.records() {
        let rec = rec.map_err(corrupt)?;
        for (k, col) in cells.iter_mut().enumerate() {
            col.push(rec.get(k).unwrap_or("").to_string());
        }
    }
    let out = PyDict::new(py);
    for (name, col) in header.iter().zip(cells) {
        let ints: Option<Vec<i64>> = col.iter().map(|c| c.parse().ok()).collect();
        let bools: Option<Vec<bool>> = col.iter().map(|c| c.parse().ok()).collect();
        let floats: Option<Vec<f64>> = col
            .iter()
            .map(|c| {
                if c.is_empty() {
                    Some(f64::NAN)
                } else {
                    c.parse().ok()
                }
            })
            .collect();
        match (ints, bools, floats) {
            (Some(v), _, _) if !v.is_empty() => out.set_item(name, PyArray1::from_vec(py, v))?,
            (_, Some(v), _) if !v.is_empty() => out.set_item(name, PyArray1::from_vec(py, v))?,
            (_, _, Some(v)) => out.set_item(name, PyArray1::from_vec(py, v))?,
            _ => {
                let numpy = py.import("numpy")?;
                out.set_item(name, numpy.call_method1("array", (col, "str"))?)?
            }
        }
    }
    Ok(out)
}

/// `(manifest JSON text, journal columns, verdict JSON text or None)` of a run directory.
#[pyfunction]
pub fn read_run_parts<'py>(
    py: Python<'py>,
    path: PathBuf,
) -> PyResult<(String, Bound<'py, PyDict>, Option<String>)> {
    if !path.is_dir() {
        let source = std::io::Error::new(
            if path.exists() {
                std::io::ErrorKind::NotADirectory
            } else {
                std::io::ErrorKind::NotFound
            },
            "not a run directory",
        );
        return Err(to_py_err(&JournalError::Io { path, source }));
    }
    Manifest::read(&path).map_err(|e| to_py_err(&e))?;
    let manifest = String::from_utf8_lossy(&read(&path.join(MANIFEST_FILE))?).into_owned();
    let journal_path = path.join(JOURNAL_FILE);
    let journal = columns(py, &read(&journal_path)?, &journal_path)?;
    let verdict_path = path.join(VERDICT_FILE);
    let verdict = if verdict_path.exists() {
        Some(String::from_utf8_lossy(&read(&verdict_path)?).into_owned())
    } else {
        None
    };
    Ok((manifest, journal, verdict))
}

/// The columns of a setpoint's `displacements/NNNNN.csv` (`kind="displacements"`) or
/// `forces/NNNNN.csv` (`kind="forces"`).
#[pyfunction]
pub fn read_csv_columns<'py>(
    py: Python<'py>,
    run: PathBuf,
    kind: &str,
    setpoint: usize,
) -> PyResult<Bound<'py, PyDict>> {
    let path = match kind {
        "displacements" => displacements_path(&run, setpoint),
        "forces" => forces_path(&run, setpoint),
        other => {
            return Err(super::value_error(format!(
                "unknown setpoint file kind {other:?}"
            )))
        }
    };
    columns(py, &read(&path)?, &path)
}
