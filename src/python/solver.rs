//! `tactbench.Solver`: forces from displacements with the library's solvers, as
//! `tactbench reconstruct` runs them: lost markers (NaN) dropped, one precompute per
//! set of present markers (automatic λ / rank chosen on its first loaded frame, like
//! `--lambda-per file`), an all-zero frame is zero force, an all-lost frame NaN.

use std::collections::HashMap;
use std::sync::Mutex;

use numpy::{PyArray1, PyArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};

use super::sensor::PySensor;
use super::{to_py_err, value_error};
use crate::formats::{DisplacementFrame, DisplacementRecord};
use crate::model::MarkerSite;
use crate::sensor::Sensor;
use crate::solve::{
    self, Diagnostics, FrameSolver, Lambda, Method, Precision, Problem, Rank, SolverConfig,
};

type MarkerKey = Vec<(usize, u64, bool)>;

/// A frame's columns: layer indexes, marker ids, positions (x, y mm) if given, ux, uy.
type Columns = (
    Vec<usize>,
    Vec<u64>,
    Option<[Vec<f64>; 2]>,
    Vec<f64>,
    Vec<f64>,
);

struct State {
    cache: HashMap<MarkerKey, Box<dyn FrameSolver>>,
    last: Option<Diagnostics>,
}

/// Reconstructs surface forces from marker displacements.
#[pyclass(name = "Solver", module = "tactbench")]
pub struct PySolver {
    sensor: Sensor,
    config: SolverConfig,
    sigma_mm: Option<f64>,
    state: Mutex<State>,
}

/// A float array from any sequence (a copy in f64).
fn floats(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<Vec<f64>> {
    let numpy = obj.py().import("numpy")?;
    let a = numpy
        .call_method1("asarray", (obj, "float64"))
        .map_err(|e| value_error(format!("{what}: not an array of numbers ({e})")))?;
    let a = a.call_method0("ravel")?;
    let a = a
        .cast::<PyArray1<f64>>()
        .map_err(|_| value_error(format!("{what}: not an array of numbers")))?;
    Ok(a.readonly().as_array().iter().copied().collect())
}

fn lambda_option(lam: Option<&Bound<'_, PyAny>>, m: Method) -> PyResult<Lambda> {
    let auto = if m == Method::Fourier {
        Lambda::LCurve
    } else {
        Lambda::Gcv
    };
    let Some(lam) = lam else { return Ok(auto) };
    if matches!(m, Method::Pinv | Method::Tsvd) {
        return Err(value_error(format!(
            "lam does not apply to the {m} solver, which has no regularisation parameter lambda (tikhonov and fourier use it{})",
            if m == Method::Tsvd { "; tsvd is tuned with rank" } else { "" }
        )));
    }
    if let Ok(s) = lam.extract::<String>() {
        return if s == "auto" {
            Ok(auto)
        } else {
            s.parse().map_err(value_error)
        };
    }
    let v: f64 = lam.extract().map_err(|_| {
        value_error("lam: expected \"gcv\", \"lcurve\", \"auto\" or a number >= 0 (mm/N)")
    })?;
    format!("{v}").parse().map_err(value_error)
}

#[pymethods]
impl PySolver {
    #[new]
    #[pyo3(signature = (sensor, method="pinv", *, lam=None, precision="f64", uncertainty=false, noise_px=None, rank=None, rcond=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        sensor: &PySensor,
        method: &str,
        lam: Option<&Bound<'_, PyAny>>,
        precision: &str,
        uncertainty: bool,
        noise_px: Option<f64>,
        rank: Option<&Bound<'_, PyAny>>,
        rcond: Option<f64>,
    ) -> PyResult<Self> {
        let m: Method = method.parse().map_err(value_error)?;
        let lambda = lambda_option(lam, m)?;
        let rank = match rank {
            None => Rank::Auto,
            Some(_) if m != Method::Tsvd => {
                return Err(value_error(format!(
                    "rank does not apply to the {m} solver: only tsvd truncates at a rank"
                )))
            }
            Some(r) => match r.extract::<String>() {
                Ok(s) => s.parse().map_err(value_error)?,
                Err(_) => {
                    let k: i64 = r
                        .extract()
                        .map_err(|_| value_error("rank: expected \"auto\" or an integer >= 1"))?;
                    k.to_string().parse().map_err(value_error)?
                }
            },
        };
        let precision = match precision {
            "f64" => Precision::F64,
            "f32" if m == Method::Fourier => return Err(value_error(
                "precision=\"f32\" does not apply to the fourier solver: its per-frame solve runs in f64 only (f32 is for pinv, tikhonov and tsvd)",
            )),
            "f32" => Precision::F32,
            other => {
                return Err(value_error(format!(
                    "unknown precision {other:?}: expected \"f64\" or \"f32\""
                )))
            }
        };
        let sigma_mm = match (uncertainty, noise_px) {
            (false, None) => None,
            (false, Some(_)) => {
                return Err(value_error("noise_px needs uncertainty=True"));
            }
            (true, None) => return Err(value_error(
                "uncertainty=True needs noise_px: the displacement noise (standard deviation per ux / uy value) in camera pixels",
            )),
            (true, Some(px)) => {
                if !(px.is_finite() && px >= 0.0) {
                    return Err(value_error(format!(
                        "noise_px={}: the displacement noise must be a finite number >= 0 px",
                        solve::fmt_num(px)
                    )));
                }
                Some(solve::noise_px_to_mm(&sensor.sensor, px))
            }
        };
        Ok(PySolver {
            sensor: sensor.sensor.clone(),
            config: SolverConfig {
                method: m,
                lambda,
                rank,
                precision,
                rcond,
                ..SolverConfig::default()
            },
            sigma_mm,
            state: Mutex::new(State {
                cache: HashMap::new(),
                last: None,
            }),
        })
    }

    /// Solves one frame: `tracks` is `Tracker.track`'s dict (or any dict with `layer`,
    /// `marker`, `ux_mm`, `uy_mm`, optionally `x_mm`, `y_mm`), or a pair of arrays
    /// `(ux_mm, uy_mm)` in the marker order of the sensor's layer grids. NaN = lost.
    fn solve<'py>(
        &self,
        py: Python<'py>,
        tracks: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let frame = self.records(tracks)?;
        let n_out = 3 * self.sensor.force_grid.len();
        let sites = frame.sites(&self.sensor);
        let u = frame.u_mm();
        let key: MarkerKey = frame
            .records
            .iter()
            .map(|r| (r.layer, r.marker, r.u_mm.is_some()))
            .collect();
        let mut state = self
            .state
            .lock()
            .map_err(|_| value_error("solver state poisoned by an earlier failure"))?;
        let (f, sd) = if sites.is_empty() {
            (vec![f64::NAN; n_out], vec![f64::NAN; n_out])
        } else if u.iter().all(|&v| v == 0.0) {
            // As `reconstruct`: no loaded frame to choose automatic λ / rank from.
            (vec![0.0; n_out], vec![f64::NAN; n_out])
        } else {
            let (sensor, config, sigma) = (&self.sensor, &self.config, self.sigma_mm);
            let state = &mut *state;
            py.detach(|| -> Result<(Vec<f64>, Vec<f64>), solve::SolveError> {
                if !state.cache.contains_key(&key) {
                    let problem = Problem::new(sensor, &sites);
                    let s = solve::precompute(&problem, config, Some(&u))?;
                    state.cache.insert(key.clone(), s);
                }
                let s = state.cache.get_mut(&key).expect("inserted above");
                let mut f = vec![0.0; s.n_outputs()];
                s.apply(&u, &mut f)?;
                let mut sd = vec![f64::NAN; s.n_outputs()];
                if let Some(sigma) = sigma {
                    s.force_sd(sigma, &mut sd)?;
                }
                state.last = Some(s.diagnostics().clone());
                Ok((f, sd))
            })
            .map_err(|e| to_py_err(&e))?
        };
        let out = PyDict::new(py);
        let nodes = self.sensor.force_points_mm();
        let col =
            |v: &[f64], k: usize| -> Vec<f64> { v.iter().skip(k).step_by(3).copied().collect() };
        out.set_item(
            "x_mm",
            PyArray1::from_vec(py, nodes.iter().map(|p| p[0]).collect()),
        )?;
        out.set_item(
            "y_mm",
            PyArray1::from_vec(py, nodes.iter().map(|p| p[1]).collect()),
        )?;
        for (k, name) in ["fx_n", "fy_n", "fz_n"].iter().enumerate() {
            out.set_item(*name, PyArray1::from_vec(py, col(&f, k)))?;
        }
        let mut sum = [0.0; 3];
        for (j, v) in f.iter().enumerate() {
            sum[j % 3] += v;
        }
        out.set_item("fsum_n", PyArray1::from_slice(py, &sum))?;
        if self.sigma_mm.is_some() {
            for (k, name) in ["sd_fx_n", "sd_fy_n", "sd_fz_n"].iter().enumerate() {
                out.set_item(*name, PyArray1::from_vec(py, col(&sd, k)))?;
            }
        }
        Ok(out)
    }

    /// What the last solve's precompute found, with `model inspect --json`'s keys
    /// (condition number κ of H, effective rank, noise gain, λ, rank, notes); before
    /// any solve, a solver that needs no frame (pinv, fixed λ or rank) is set up on
    /// every marker of the sensor's layer grids, as `model inspect` does; else None.
    #[getter]
    fn diagnostics<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let last = self
            .state
            .lock()
            .map_err(|_| value_error("solver state poisoned by an earlier failure"))?
            .last
            .clone();
        let (d, markers) = match last {
            Some(d) => {
                let m = d.shape.0 / 2;
                (d, m)
            }
            None if !self.config.needs_frame() => {
                let sites = MarkerSite::from_sensor_grids(&self.sensor);
                let problem = Problem::new(&self.sensor, &sites);
                let s = py
                    .detach(|| solve::precompute(&problem, &self.config, None))
                    .map_err(|e| to_py_err(&e))?;
                (s.diagnostics().clone(), sites.len())
            }
            None => return Ok(None),
        };
        let out = PyDict::new(py);
        out.set_item("markers", markers)?;
        out.set_item("force_points", self.sensor.force_grid.len())?;
        out.set_item("rows", d.shape.0)?;
        out.set_item("columns", d.shape.1)?;
        out.set_item("solver", d.method.name())?;
        out.set_item(
            "singular_values_mm_per_n",
            PyArray1::from_slice(py, &d.singular_values),
        )?;
        out.set_item("condition_number", d.condition_of_h())?;
        out.set_item("effective_rank", d.effective_rank)?;
        out.set_item("noise_gain_n_per_mm", d.noise_gain)?;
        out.set_item("lambda_mm_per_n", d.lambda)?;
        out.set_item("rank", d.rank)?;
        out.set_item("notes", PyList::new(py, &d.notes)?)?;
        out.set_item("warnings", PyList::new(py, d.warnings())?)?;
        Ok(Some(out))
    }

    /// The method: pinv, tikhonov, tsvd or fourier.
    #[getter]
    fn method(&self) -> &'static str {
        self.config.method.name()
    }
}

impl PySolver {
    /// The frame as the library's displacement rows.
    fn records(&self, tracks: &Bound<'_, PyAny>) -> PyResult<DisplacementFrame> {
        let s = &self.sensor;
        let (layers, ids, positions, ux, uy): Columns = if let Ok(d) = tracks.cast::<PyDict>() {
            let get = |k: &str| -> PyResult<Bound<'_, PyAny>> {
                d.get_item(k)?.ok_or_else(|| {
                        value_error(format!(
                            "tracks: no {k:?} key (expected Tracker.track's dict: layer, marker, ux_mm, uy_mm)"
                        ))
                    })
            };
            let ux = floats(&get("ux_mm")?, "ux_mm")?;
            let uy = floats(&get("uy_mm")?, "uy_mm")?;
            let names: Vec<String> = get("layer")?
                .call_method0("__iter__")?
                .try_iter()?
                .map(|v| v.and_then(|v| v.str().map(|s| s.to_string())))
                .collect::<PyResult<_>>()?;
            let layers = names
                .iter()
                .map(|n| {
                    s.layer_index(n).ok_or_else(|| {
                        value_error(format!(
                            "tracks: layer {n:?} is not a layer of the sensor ({})",
                            s.layers
                                .iter()
                                .map(|l| l.name.as_str())
                                .collect::<Vec<_>>()
                                .join(", ")
                        ))
                    })
                })
                .collect::<PyResult<Vec<_>>>()?;
            let ids: Vec<u64> = floats(&get("marker")?, "marker")?
                .iter()
                .map(|&v| {
                    if v >= 0.0 && v.fract() == 0.0 && v < 9e15 {
                        Ok(v as u64)
                    } else {
                        Err(value_error(format!(
                            "tracks: marker id {v} is not an integer >= 0"
                        )))
                    }
                })
                .collect::<PyResult<_>>()?;
            let positions = match (d.get_item("x_mm")?, d.get_item("y_mm")?) {
                (Some(x), Some(y)) => Some([floats(&x, "x_mm")?, floats(&y, "y_mm")?]),
                _ => None,
            };
            (layers, ids, positions, ux, uy)
        } else if let Ok(t) = tracks
            .cast::<PyTuple>()
            .map(|t| t.as_any().clone())
            .or_else(|_| tracks.cast::<PyList>().map(|l| l.as_any().clone()))
        {
            let pair: Vec<Bound<'_, PyAny>> = t.try_iter()?.collect::<PyResult<_>>()?;
            if pair.len() != 2 {
                return Err(value_error(
                    "tracks: expected Tracker.track's dict or a pair (ux_mm, uy_mm)",
                ));
            }
            let ux = floats(&pair[0], "ux_mm")?;
            let uy = floats(&pair[1], "uy_mm")?;
            let mut layers = Vec::new();
            let mut ids = Vec::new();
            for (li, l) in s.layers.iter().enumerate() {
                if let Some(m) = &l.markers {
                    layers.extend(std::iter::repeat_n(li, m.grid.len()));
                    ids.extend(0..m.grid.len() as u64);
                }
            }
            (layers, ids, None, ux, uy)
        } else {
            return Err(value_error(
                "tracks: expected Tracker.track's dict or a pair (ux_mm, uy_mm)",
            ));
        };
        let n = layers.len();
        let lengths = [ids.len(), ux.len(), uy.len()];
        let pos_lengths = positions
            .as_ref()
            .map_or([n, n], |p| [p[0].len(), p[1].len()]);
        if lengths.iter().chain(&pos_lengths).any(|&l| l != n) || n == 0 {
            return Err(value_error(format!(
                "tracks: {n} markers (layer / sensor grids) but {} marker ids, {} ux_mm and {} uy_mm values",
                ids.len(),
                ux.len(),
                uy.len()
            )));
        }
        let mut records = Vec::with_capacity(n);
        for k in 0..n {
            let position_mm = match &positions {
                Some(p) => [p[0][k], p[1][k]],
                None => {
                    let grid = s.layers[layers[k]].markers.as_ref().ok_or_else(|| {
                        value_error(format!(
                            "tracks: layer {:?} has no grid in the sensor file: give x_mm, y_mm",
                            s.layers[layers[k]].name
                        ))
                    })?;
                    let (nx, id) = (grid.grid.nx as u64, ids[k]);
                    if id >= grid.grid.len() as u64 {
                        return Err(value_error(format!(
                            "tracks: marker {id} of layer {:?} is outside its {}×{} grid",
                            s.layers[layers[k]].name, grid.grid.nx, grid.grid.ny
                        )));
                    }
                    grid.grid.node_mm((id % nx) as usize, (id / nx) as usize)
                }
            };
            let u = [ux[k], uy[k]];
            records.push(DisplacementRecord {
                layer: layers[k],
                marker: ids[k],
                position_mm,
                u_mm: u.iter().all(|v| !v.is_nan()).then_some(u),
                line: 0,
            });
        }
        Ok(DisplacementFrame {
            frame: String::new(),
            records,
        })
    }
}
