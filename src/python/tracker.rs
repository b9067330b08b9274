//! `tactbench.Tracker`: the library's [`Tracker`] on NumPy frames, one row per marker
//! in the order and with the values of `tactbench track`'s CSV (reference-missing grid
//! nodes included as `lost`); the GIL is released while a frame is measured.

use std::path::Path;

use numpy::{PyArray1, PyFixedUnicode};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::frame::{coloured_layers, parse_order, FrameInput, Order};
use super::sensor::PySensor;
use super::{to_py_err, value_error};
use crate::sensor::Sensor;
use crate::vision::onboard::check_frame_levels;
use crate::vision::{
    bgr_sensor, detect_mapped, DetectConfig, MarkerStatus, PixelMapping, TrackConfig, TrackMode,
    Tracker, VisionError,
};

/// One output row: the layer, marker id, reference position (mm), and the index into
/// the reference's markers (`None`: a grid node without a marker, always lost).
struct Row {
    layer: usize,
    id: u64,
    position_mm: [f64; 2],
    index: Option<usize>,
}

/// Tracks frames against an unloaded reference frame.
#[pyclass(name = "Tracker", module = "tactbench")]
pub struct PyTracker {
    tracker: Tracker,
    sensor: Sensor,
    order: Option<Order>,
    rows: Vec<Row>,
    /// The constant columns (layer names, marker ids, x/y mm and px), copied per call.
    constant: Py<PyDict>,
}

/// `mode=`: `None` (frame-to-frame, `track`'s default), `"frame-to-frame"`, `"per-window"`.
fn parse_mode(mode: Option<&str>) -> PyResult<TrackMode> {
    match mode {
        None | Some("frame-to-frame") => Ok(TrackMode::FrameToFrame),
        Some("per-window") => Ok(TrackMode::PerWindow),
        Some(other) => Err(value_error(format!(
            "mode={other:?}: expected \"frame-to-frame\" or \"per-window\" (track --mode)"
        ))),
    }
}

/// A 3/4-channel frame of a sensor with coloured layers needs its channel order.
fn check_order(sensor: &Sensor, order: Option<Order>, what: &str, channels: usize) -> PyResult<()> {
    let coloured = coloured_layers(sensor);
    if channels > 1 && order.is_none() && !coloured.is_empty() {
        return Err(value_error(format!(
            "{what}: {} told apart by colour: give channels=\"rgb\" or channels=\"bgr\" (OpenCV's cv2.imread order) for 3- or 4-channel frames",
            coloured.join(", ")
        )));
    }
    Ok(())
}

#[pymethods]
impl PyTracker {
    #[new]
    #[pyo3(signature = (sensor, reference, *, mode=None, channels=None))]
    fn new(
        py: Python<'_>,
        sensor: &PySensor,
        reference: &Bound<'_, PyAny>,
        mode: Option<&str>,
        channels: Option<&str>,
    ) -> PyResult<Self> {
        let order = parse_order(channels)?;
        let mode = parse_mode(mode)?;
        let s = &sensor.sensor;
        let input = FrameInput::extract(reference, "reference")?;
        check_order(s, order, "reference", input.channels())?;
        let expected = [s.camera.width_px, s.camera.height_px];
        if input.size() != expected {
            return Err(to_py_err(&VisionError::WrongSize {
                path: "reference array".into(),
                found: input.size(),
                expected,
            }));
        }
        let view = input.view()?;
        let seen = match order {
            Some(Order::Bgr) => bgr_sensor(s),
            _ => s.clone(),
        };
        let mapping = PixelMapping::Linear(s.camera);
        let detected =
            py.detach(|| detect_mapped(&view, &seen, &DetectConfig::default(), &mapping));
        let reference = match detected {
            Ok(r) => r,
            Err(e) => {
                // A blank or saturated reference is the likelier cause: say so first (as
                // `track` does).
                check_frame_levels(
                    &view,
                    s.camera.roi_px.as_ref(),
                    Path::new("reference array"),
                )
                .map_err(|e| to_py_err(&e))?;
                return Err(value_error(format!(
                    "reference array with sensor {}: {e}",
                    sensor.path
                )));
            }
        };
        let mut rows: Vec<Row> = reference
            .markers
            .iter()
            .enumerate()
            .map(|(i, m)| Row {
                layer: m.layer,
                id: m.id,
                position_mm: m.position_mm,
                index: Some(i),
            })
            .chain(reference.missing.iter().map(|m| Row {
                layer: m.layer,
                id: m.id,
                position_mm: m.node_mm,
                index: None,
            }))
            .collect();
        // `track`'s CSV row order (vision::write_tracks_mapped_to): layer, then id.
        rows.sort_by_key(|r| (r.layer, r.id));
        let constant = PyDict::new(py);
        let names: Vec<&str> = rows
            .iter()
            .map(|r| s.layers[r.layer].name.as_str())
            .collect();
        let numpy = py.import("numpy")?;
        constant.set_item("layer", numpy.call_method1("array", (names,))?)?;
        let ids: Vec<i64> = rows.iter().map(|r| r.id as i64).collect();
        constant.set_item("marker", PyArray1::from_vec(py, ids))?;
        let col = |f: &dyn Fn(&Row) -> f64| -> Vec<f64> { rows.iter().map(f).collect() };
        constant.set_item("x_mm", PyArray1::from_vec(py, col(&|r| r.position_mm[0])))?;
        constant.set_item("y_mm", PyArray1::from_vec(py, col(&|r| r.position_mm[1])))?;
        let px = |k: usize| {
            col(&|r: &Row| {
                r.index
                    .map_or(f64::NAN, |i| reference.markers[i].centroid_px[k])
            })
        };
        constant.set_item("x_px", PyArray1::from_vec(py, px(0)))?;
        constant.set_item("y_px", PyArray1::from_vec(py, px(1)))?;
        Ok(PyTracker {
            tracker: Tracker::new(
                reference,
                TrackConfig {
                    mode,
                    ..TrackConfig::default()
                },
            ),
            sensor: s.clone(),
            order,
            rows,
            constant: constant.unbind(),
        })
    }

    /// Measures one frame (same dtype rules, size and channel order as the reference);
    /// returns a dict of arrays, one row per marker (see the module docs).
    fn track<'py>(
        &mut self,
        py: Python<'py>,
        frame: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let input = FrameInput::extract(frame, "frame")?;
        check_order(&self.sensor, self.order, "frame", input.channels())?;
        let view = input.view()?;
        let tracker = &mut self.tracker;
        let tracks = py
            .detach(move || tracker.track(&view).map(|t| t.to_vec()))
            .map_err(|e| to_py_err(&e))?;
        let n = self.rows.len();
        let (mut ux_mm, mut uy_mm) = (vec![f64::NAN; n], vec![f64::NAN; n]);
        let (mut ux_px, mut uy_px) = (vec![f64::NAN; n], vec![f64::NAN; n]);
        let mut status = vec![status_name(MarkerStatus::Lost); n];
        let mapping = PixelMapping::Linear(self.sensor.camera);
        let reference = self.tracker.reference();
        for (k, row) in self.rows.iter().enumerate() {
            let Some(i) = row.index else { continue };
            let t = &tracks[i];
            status[k] = status_name(t.status);
            if t.status == MarkerStatus::Ok {
                let r = &reference.markers[i];
                let u = mapping.displacement_mm(row.layer, r.centroid_px, t.displacement_px);
                (ux_mm[k], uy_mm[k]) = (u[0], u[1]);
            }
            if t.status != MarkerStatus::Lost {
                (ux_px[k], uy_px[k]) = (t.displacement_px[0], t.displacement_px[1]);
            }
        }
        let out = PyDict::new(py);
        let constant = self.constant.bind(py);
        for key in ["layer", "marker", "x_mm", "y_mm"] {
            if let Some(v) = constant.get_item(key)? {
                out.set_item(key, v.call_method0("copy")?)?;
            }
        }
        out.set_item("ux_mm", PyArray1::from_vec(py, ux_mm))?;
        out.set_item("uy_mm", PyArray1::from_vec(py, uy_mm))?;
        for key in ["x_px", "y_px"] {
            if let Some(v) = constant.get_item(key)? {
                out.set_item(key, v.call_method0("copy")?)?;
            }
        }
        out.set_item("ux_px", PyArray1::from_vec(py, ux_px))?;
        out.set_item("uy_px", PyArray1::from_vec(py, uy_px))?;
        out.set_item("status", PyArray1::from_vec(py, status))?;
        Ok(out)
    }

    /// Forgets the sequence: the next frame starts from the reference positions.
    fn reset(&mut self) {
        self.tracker.reset();
    }

    /// Rows per frame (markers found in the reference plus grid nodes without one).
    fn __len__(&self) -> usize {
        self.rows.len()
    }
}

/// A status as `track`'s CSV writes it, as a NumPy `<U7` element.
fn status_name(s: MarkerStatus) -> PyFixedUnicode<7> {
    let mut out = [0u32; 7];
    for (o, c) in out.iter_mut().zip(s.name().chars()) {
        *o = c as u32;
    }
    PyFixedUnicode(out)
}
