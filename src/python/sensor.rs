//! `tactbench.Sensor`: a sensor file loaded with the CLI's validation and messages.

use numpy::{PyArray2, PyArrayMethods};
use pyo3::prelude::*;

use super::{to_py_err, value_error};
use crate::sensor::Sensor;

/// A validated sensor description (sensor.toml).
#[pyclass(name = "Sensor", module = "tactbench", frozen)]
pub struct PySensor {
    pub(crate) sensor: Sensor,
    pub(crate) path: String,
}

/// N×2 array of positions, mm.
fn points<'py>(py: Python<'py>, p: &[[f64; 2]]) -> Bound<'py, PyArray2<f64>> {
    let flat: Vec<f64> = p.iter().flatten().copied().collect();
    numpy::PyArray1::from_vec(py, flat)
        .reshape([p.len(), 2])
        .expect("n×2 holds 2n values")
}

#[pymethods]
impl PySensor {
    #[new]
    fn new(path: std::path::PathBuf) -> PyResult<Self> {
        let sensor = Sensor::from_path(&path).map_err(|e| to_py_err(&e))?;
        Ok(PySensor {
            sensor,
            path: path.display().to_string(),
        })
    }

    /// The layer names, in the sensor file's order.
    #[getter]
    fn layers(&self) -> Vec<String> {
        self.sensor.layers.iter().map(|l| l.name.clone()).collect()
    }

    /// The marker positions of a layer's grid (N×2, mm, row-major: marker id = row).
    fn markers<'py>(&self, py: Python<'py>, layer: &str) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let i = self.layer_index(layer)?;
        let l = &self.sensor.layers[i];
        let grid = l.markers.as_ref().ok_or_else(|| {
            value_error(format!(
                "{}: layer {layer:?} has no [layers.markers] grid: its marker positions come from a reference frame",
                self.path
            ))
        })?;
        Ok(points(py, &grid.grid.nodes_mm()))
    }

    /// The force-grid node positions (M×2, mm, row-major).
    #[getter]
    fn force_grid<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        points(py, &self.sensor.force_points_mm())
    }

    /// Width, height of the camera image, px (`[camera]`).
    #[getter]
    fn image_size(&self) -> (u32, u32) {
        (self.sensor.camera.width_px, self.sensor.camera.height_px)
    }

    /// The file this sensor was read from.
    #[getter]
    fn path(&self) -> &str {
        &self.path
    }

    fn __repr__(&self) -> String {
        format!("tactbench.Sensor({:?})", self.path)
    }
}

impl PySensor {
    pub(crate) fn layer_index(&self, name: &str) -> PyResult<usize> {
        self.sensor.layer_index(name).ok_or_else(|| {
            value_error(format!(
                "{}: no layer named {name:?} (layers: {})",
                self.path,
                self.layers().join(", ")
            ))
        })
    }
}
