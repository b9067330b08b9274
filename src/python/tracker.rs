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
    bgr_sensor, detect_mapped, DetectConfig, MarkerStatus, MarkerTrack, PixelMapping, TrackConfig,
    TrackMode, Tracker, VisionError,
};

/// One output row: the layer, marker id, reference position (mm), and the index into
/// the reference's markers (`None`: a grid node without a marker, always lost).
struct Row {
    layer: usize,
    id: u64,
    position_mm: [f64; 2],
    /// The marker's centroid in the reference frame, px (NaN without a marker).
    centroid_px: [f64; 2],
    index: Option<usize>,
}

/// Tracks frames against an unloaded reference frame.
#[pyclass(name = "Tracker", module = "tactbench")]
pub struct PyTracker {
    tracker: Tracker,
    sensor: Sensor,
    order: Option<Order>,
    rows: Vec<Row>,
    /// The constant columns, copied into fresh arrays per call (a caller may change the
    /// arrays it got): layer names as a NumPy string array, the rest as Rust columns
    /// (a `memcpy` each, no Python call).
    layer_names: Py<PyAny>,
    constant: Constant,
}

/// The columns that do not change from frame to frame.
struct Constant {
    marker: Vec<i64>,
    x_mm: Vec<f64>,
    y_mm: Vec<f64>,
    x_px: Vec<f64>,
    y_px: Vec<f64>,
}

/// The per-frame columns, computed with the GIL released.
struct Moving {
    ux_mm: Vec<f64>,
    uy_mm: Vec<f64>,
    ux_px: Vec<f64>,
    uy_px: Vec<f64>,
    status: Vec<PyFixedUnicode<7>>,
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
                centroid_px: m.centroid_px,
                index: Some(i),
            })
            .chain(reference.missing.iter().map(|m| Row {
                layer: m.layer,
                id: m.id,
                position_mm: m.node_mm,
                centroid_px: [f64::NAN; 2],
                index: None,
            }))
            .collect();
        // `track`'s CSV row order (vision::write_tracks_mapped_to): layer, then id.
        rows.sort_by_key(|r| (r.layer, r.id));
        let names: Vec<&str> = rows
            .iter()
            .map(|r| s.layers[r.layer].name.as_str())
            .collect();
        let layer_names = py.import("numpy")?.call_method1("array", (names,))?;
        let col = |f: &dyn Fn(&Row) -> f64| -> Vec<f64> { rows.iter().map(f).collect() };
        let constant = Constant {
            marker: rows.iter().map(|r| r.id as i64).collect(),
            x_mm: col(&|r| r.position_mm[0]),
            y_mm: col(&|r| r.position_mm[1]),
            x_px: col(&|r| r.centroid_px[0]),
            y_px: col(&|r| r.centroid_px[1]),
        };
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
            layer_names: layer_names.unbind(),
            constant,
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
        let (tracker, rows, camera) = (&mut self.tracker, &self.rows, self.sensor.camera);
        let m = py
            .detach(move || {
                let tracks = tracker.track(&view)?;
                Ok::<_, VisionError>(moving_columns(rows, tracks, camera))
            })
            .map_err(|e| to_py_err(&e))?;
        let c = &self.constant;
        let out = PyDict::new(py);
        out.set_item("layer", self.layer_names.bind(py).call_method0("copy")?)?;
        out.set_item("marker", PyArray1::from_slice(py, &c.marker))?;
        out.set_item("x_mm", PyArray1::from_slice(py, &c.x_mm))?;
        out.set_item("y_mm", PyArray1::from_slice(py, &c.y_mm))?;
        out.set_item("ux_mm", PyArray1::from_vec(py, m.ux_mm))?;
        out.set_item("uy_mm", PyArray1::from_vec(py, m.uy_mm))?;
        out.set_item("x_px", PyArray1::from_slice(py, &c.x_px))?;
        out.set_item("y_px", PyArray1::from_slice(py, &c.y_px))?;
        out.set_item("ux_px", PyArray1::from_vec(py, m.ux_px))?;
        out.set_item("uy_px", PyArray1::from_vec(py, m.uy_px))?;
        out.set_item("status", PyArray1::from_vec(py, m.status))?;
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

/// The per-frame columns of `rows` from one frame's tracks (`track`'s CSV values: mm
/// only for `ok`, px for everything not `lost`, NaN elsewhere).
fn moving_columns(
    rows: &[Row],
    tracks: &[MarkerTrack],
    camera: crate::sensor::CameraMapping,
) -> Moving {
    let n = rows.len();
    let mut m = Moving {
        ux_mm: vec![f64::NAN; n],
        uy_mm: vec![f64::NAN; n],
        ux_px: vec![f64::NAN; n],
        uy_px: vec![f64::NAN; n],
        status: vec![status_name(MarkerStatus::Lost); n],
    };
    let mapping = PixelMapping::Linear(camera);
    for (k, row) in rows.iter().enumerate() {
        let Some(i) = row.index else { continue };
        let t = &tracks[i];
        m.status[k] = status_name(t.status);
        if t.status == MarkerStatus::Ok {
            let u = mapping.displacement_mm(row.layer, row.centroid_px, t.displacement_px);
            (m.ux_mm[k], m.uy_mm[k]) = (u[0], u[1]);
        }
        if t.status != MarkerStatus::Lost {
            (m.ux_px[k], m.uy_px[k]) = (t.displacement_px[0], t.displacement_px[1]);
        }
    }
    m
}

/// A status as `track`'s CSV writes it, as a NumPy `<U7` element.
fn status_name(s: MarkerStatus) -> PyFixedUnicode<7> {
    let mut out = [0u32; 7];
    for (o, c) in out.iter_mut().zip(s.name().chars()) {
        *o = c as u32;
    }
    PyFixedUnicode(out)
}
