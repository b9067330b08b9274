//! Camera calibration from one unloaded frame: the detected marker grid of every
//! layer is the calibration target (its geometry is known from sensor.toml).
//!
//! Model ([`super::camera`]): marker `(x, y)` mm of layer `l` appears at
//! `p = D(o_l + s_l (x, y))`, with per-layer scale `s_l` (px/mm) and origin `o_l` (px)
//! and Brown–Conrady distortion `D` about the principal point `c`, normalised by half
//! the image diagonal. Unknowns: `3 L` layer parameters, `c`, `k1 … k_n` (n =
//! [`CalibrateConfig::radial_terms`], default 2; `k3` weakly determined over the radii
//! a marker grid covers) and, with [`CalibrateConfig::tangential`], `p1, p2` — then `c`
//! is held at the image centre, because a shift of the distortion centre and the
//! tangential terms are the same to first order (one frame cannot tell them apart).
//!
//! Procedure:
//! 1. [`super::detect`] finds the blobs of every layer (centroids are kept whether or
//!    not the sensor file's linear `[camera]` mapping matches them to a grid node);
//! 2. starting from the linear mapping, each blob is matched to the nearest grid node
//!    of its layer within 0.35 pitch under the current model (the nearer of two
//!    claimants wins), the model is fitted to the matches by least squares, and the
//!    matching is repeated with the fitted model until it no longer changes (so a
//!    scale several percent off the file's still matches every marker: the markers
//!    near the origin match first and fix the scale for the rest);
//! 3. the fit is a Levenberg–Marquardt minimisation of the pixel residuals (Marquardt
//!    scaling, central-difference Jacobian, nalgebra Cholesky); converged when a step
//!    changes the cost by less than 1e-12 relative or every parameter by less than
//!    1e-10 of its scale.
//!
//! Parameter standard deviations are `σ √diag((JᵀJ)⁻¹)` with `σ²` the residual
//! variance: large values name what the frame does not determine.

use nalgebra::{DMatrix, DVector};
use thiserror::Error;

use super::camera::{BrownConrady, CameraCalibration, LayerCalibration};
use super::detect::{detect, DetectConfig};
use super::image::FrameView;
use super::VisionError;
use crate::sensor::Sensor;

/// Fewest matched markers a layer needs (3 layer parameters, and a margin).
pub const MIN_MARKERS_PER_LAYER: usize = 6;

/// Options of [`calibrate`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CalibrateConfig {
    /// Radial coefficients fitted (0 to 3: k1 only with 1; 0 fits no distortion and
    /// holds the principal point at the image centre).
    pub radial_terms: usize,
    /// Fit the tangential coefficients p1, p2 (the principal point is then held at
    /// the image centre).
    pub tangential: bool,
    /// Levenberg–Marquardt iterations allowed per fit.
    pub max_iterations: usize,
    /// Blob-to-node matching tolerance, grid pitches.
    pub match_tolerance: f64,
}

impl Default for CalibrateConfig {
    fn default() -> Self {
        CalibrateConfig {
            radial_terms: 2,
            tangential: false,
            max_iterations: 200,
            match_tolerance: 0.35,
        }
    }
}

/// Why a calibration failed.
#[derive(Debug, Error)]
pub enum CalibrationError {
    /// The reference image could not be searched.
    #[error(transparent)]
    Vision(#[from] VisionError),
    /// A layer has no marker grid in the sensor file (nothing to calibrate against).
    #[error("layer {layer} has no [layers.markers] grid in the sensor file: calibration needs every layer's grid geometry")]
    NoGrid {
        /// Layer name.
        layer: String,
    },
    /// Too few markers of a layer were found and matched to its grid.
    #[error("layer {layer}: {found} markers matched to the grid, calibration needs at least {needed} per layer (check the reference frame: unloaded, in focus, the right sensor file)")]
    TooFewMarkers {
        /// Layer name.
        layer: String,
        /// Markers matched.
        found: usize,
        /// Markers needed.
        needed: usize,
    },
    /// The least-squares fit did not converge.
    #[error("the calibration fit did not converge in {iterations} iterations (residual RMS {rms_px:.3} px)")]
    NoConvergence {
        /// Iterations run.
        iterations: usize,
        /// Residual RMS at the end, px.
        rms_px: f64,
    },
    /// The model produced a non-finite value (e.g. a distortion strong enough to fold
    /// the image).
    #[error("the calibration fit diverged (non-finite residual after {iterations} iterations)")]
    Diverged {
        /// Iterations run.
        iterations: usize,
    },
}

/// A fitted calibration with the fit's statistics.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationFit {
    /// The calibration.
    pub calibration: CameraCalibration,
    /// Levenberg–Marquardt iterations of the last fit.
    pub iterations: usize,
    /// Matching rounds (match, fit) until the matches stopped changing.
    pub rounds: usize,
    /// Every fitted parameter: name, value, standard deviation (NaN when `JᵀJ` is
    /// singular: not determined by the frame). Held parameters are not listed.
    pub parameters: Vec<(String, f64, f64)>,
    /// Blobs found but matched to no grid node.
    pub unmatched: usize,
}

/// One matched marker: layer, node position (mm), measured centroid (px).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Match {
    layer: usize,
    node_mm: [f64; 2],
    centroid_px: [f64; 2],
}

/// Parameter layout: `[s_l, ox_l, oy_l] × L`, then `cx, cy, k1, k2, k3, p1, p2`.
#[derive(Debug, Clone)]
struct Layout {
    layers: usize,
    free: Vec<usize>,
}

const GLOBAL_NAMES: [&str; 7] = ["cx_px", "cy_px", "k1", "k2", "k3", "p1", "p2"];

impl Layout {
    fn new(layers: usize, config: &CalibrateConfig) -> Self {
        let mut free: Vec<usize> = (0..3 * layers).collect();
        let g = 3 * layers;
        let radial = config.radial_terms.min(3);
        if radial > 0 && !config.tangential {
            free.extend([g, g + 1]);
        }
        free.extend((0..radial).map(|k| g + 2 + k));
        if config.tangential {
            free.extend([g + 5, g + 6]);
        }
        Layout { layers, free }
    }

    fn name(&self, i: usize, sensor: &Sensor) -> String {
        if i < 3 * self.layers {
            let l = &sensor.layers[i / 3].name;
            match i % 3 {
                0 => format!("{l}.px_per_mm"),
                1 => format!("{l}.origin_x_px"),
                _ => format!("{l}.origin_y_px"),
            }
        } else {
            GLOBAL_NAMES[i - 3 * self.layers].to_string()
        }
    }

    fn to_calibration(&self, p: &[f64], base: &CameraCalibration) -> CameraCalibration {
        let g = 3 * self.layers;
        let mut c = base.clone();
        for (l, lc) in c.layers.iter_mut().enumerate() {
            lc.px_per_mm = p[3 * l];
            lc.origin_px = [p[3 * l + 1], p[3 * l + 2]];
        }
        c.distortion = BrownConrady {
            center_px: [p[g], p[g + 1]],
            norm_px: base.distortion.norm_px,
            k1: p[g + 2],
            k2: p[g + 3],
            k3: p[g + 4],
            p1: p[g + 5],
            p2: p[g + 6],
        };
        c
    }

    fn params_of(&self, c: &CameraCalibration) -> Vec<f64> {
        let mut p = Vec::with_capacity(3 * self.layers + 7);
        for l in &c.layers {
            p.extend([l.px_per_mm, l.origin_px[0], l.origin_px[1]]);
        }
        let d = &c.distortion;
        p.extend([d.center_px[0], d.center_px[1], d.k1, d.k2, d.k3, d.p1, d.p2]);
        p
    }
}

/// Residuals (predicted − measured, px; x then y per match).
fn residuals(layout: &Layout, p: &[f64], base: &CameraCalibration, matches: &[Match]) -> Vec<f64> {
    let c = layout.to_calibration(p, base);
    let mut r = Vec::with_capacity(2 * matches.len());
    for m in matches {
        let q = c.mm_to_px(m.layer, m.node_mm);
        r.push(q[0] - m.centroid_px[0]);
        r.push(q[1] - m.centroid_px[1]);
    }
    r
}

/// Levenberg–Marquardt on the free parameters. Returns (parameters, iterations, JᵀJ at
/// the solution over the free parameters, cost).
fn fit(
    layout: &Layout,
    start: Vec<f64>,
    base: &CameraCalibration,
    matches: &[Match],
    max_iterations: usize,
) -> Result<(Vec<f64>, usize, DMatrix<f64>, f64), CalibrationError> {
    let n = layout.free.len();
    let m = 2 * matches.len();
    let mut p = start;
    let cost_of = |p: &[f64]| -> f64 {
        residuals(layout, p, base, matches)
            .iter()
            .map(|v| v * v)
            .sum::<f64>()
    };
    let mut cost = cost_of(&p);
    if !cost.is_finite() {
        return Err(CalibrationError::Diverged { iterations: 0 });
    }
    let scale: Vec<f64> = layout
        .free
        .iter()
        .map(|&i| {
            if i < 3 * layout.layers {
                p[i].abs().max(1.0)
            } else {
                1.0
            }
        })
        .collect();
    let mut lambda = 1e-3;
    for it in 1..=max_iterations {
        // Central-difference Jacobian over the free parameters.
        let mut jac = DMatrix::<f64>::zeros(m, n);
        for (col, &i) in layout.free.iter().enumerate() {
            let h = 1e-6 * scale[col];
            let mut a = p.clone();
            let mut b = p.clone();
            a[i] += h;
            b[i] -= h;
            let (ra, rb) = (
                residuals(layout, &a, base, matches),
                residuals(layout, &b, base, matches),
            );
            for row in 0..m {
                jac[(row, col)] = (ra[row] - rb[row]) / (2.0 * h);
            }
        }
        let r = DVector::from_vec(residuals(layout, &p, base, matches));
        let jtj = jac.transpose() * &jac;
        let g = jac.transpose() * r;
        let max_diag = (0..n)
            .map(|i| jtj[(i, i)])
            .fold(0.0f64, f64::max)
            .max(1e-300);
        loop {
            let mut a = jtj.clone();
            for i in 0..n {
                a[(i, i)] += lambda * jtj[(i, i)].max(1e-9 * max_diag);
            }
            let step = a.cholesky().map(|ch| ch.solve(&(-&g)));
            let Some(step) = step else {
                lambda *= 10.0;
                if lambda > 1e16 {
                    break;
                }
                continue;
            };
            let mut trial = p.clone();
            for (col, &i) in layout.free.iter().enumerate() {
                trial[i] += step[col];
            }
            let c = cost_of(&trial);
            if c.is_finite() && c <= cost {
                let small_step = layout
                    .free
                    .iter()
                    .enumerate()
                    .all(|(col, _)| step[col].abs() <= 1e-10 * scale[col]);
                let small_change = cost - c <= 1e-12 * cost.max(1e-300);
                p = trial;
                cost = c;
                lambda = (lambda / 10.0).max(1e-12);
                if small_step || small_change {
                    return Ok((p, it, jtj, cost));
                }
                break;
            }
            lambda *= 10.0;
            if lambda > 1e16 {
                // No descent direction left: at a minimum to machine precision.
                return Ok((p, it, jtj, cost));
            }
        }
        if lambda > 1e16 {
            return Ok((p, it, jtj, cost));
        }
    }
    let rms = (cost / m.max(1) as f64).sqrt();
    if !rms.is_finite() {
        return Err(CalibrationError::Diverged {
            iterations: max_iterations,
        });
    }
    Err(CalibrationError::NoConvergence {
        iterations: max_iterations,
        rms_px: rms,
    })
}

/// Matches every blob to the nearest grid node of its layer under `model`.
fn match_blobs(
    sensor: &Sensor,
    model: &CameraCalibration,
    blobs: &[(usize, [f64; 2])],
    tolerance: f64,
) -> (Vec<Match>, usize) {
    let mut matches = Vec::new();
    let mut unmatched = 0;
    for (li, layer) in sensor.layers.iter().enumerate() {
        let Some(grid) = layer.markers.map(|m| m.grid) else {
            continue;
        };
        let mut claim: Vec<Option<(usize, f64)>> = vec![None; grid.len()];
        for (bi, (bl, c)) in blobs.iter().enumerate() {
            if *bl != li {
                continue;
            }
            let p = model.px_to_mm(li, *c);
            match grid.nearest_node(p) {
                Some(((ix, iy), d)) if d <= tolerance * grid.pitch_mm => {
                    let k = iy * grid.nx + ix;
                    match claim[k] {
                        Some((_, od)) if od <= d => unmatched += 1,
                        Some(_) => {
                            unmatched += 1;
                            claim[k] = Some((bi, d));
                        }
                        None => claim[k] = Some((bi, d)),
                    }
                }
                _ => unmatched += 1,
            }
        }
        for (k, c) in claim.iter().enumerate() {
            if let Some((bi, _)) = c {
                matches.push(Match {
                    layer: li,
                    node_mm: grid.node_mm(k % grid.nx, k / grid.nx),
                    centroid_px: blobs[*bi].1,
                });
            }
        }
    }
    (matches, unmatched)
}

/// Calibrates the camera from an unloaded reference frame (see the module docs).
pub fn calibrate(
    view: &FrameView<'_>,
    sensor: &Sensor,
    config: &CalibrateConfig,
) -> Result<CalibrationFit, CalibrationError> {
    for l in &sensor.layers {
        if l.markers.is_none() {
            return Err(CalibrationError::NoGrid {
                layer: l.name.clone(),
            });
        }
    }
    let reference = match detect(view, sensor, &DetectConfig::default()) {
        Ok(r) => r,
        Err(VisionError::NoMarkers { .. }) => {
            return Err(CalibrationError::TooFewMarkers {
                layer: sensor.layers[0].name.clone(),
                found: 0,
                needed: MIN_MARKERS_PER_LAYER,
            })
        }
        Err(e) => return Err(e.into()),
    };
    let blobs: Vec<(usize, [f64; 2])> = reference
        .markers
        .iter()
        .map(|m| (m.layer, m.centroid_px))
        .chain(reference.unmatched.iter().map(|u| (u.layer, u.centroid_px)))
        .collect();
    let base = CameraCalibration::from_linear(&sensor.camera, sensor);
    let layout = Layout::new(sensor.layers.len(), config);
    let linear_layout = Layout::new(
        sensor.layers.len(),
        &CalibrateConfig {
            radial_terms: 0,
            tangential: false,
            ..*config
        },
    );
    let mut model = base.clone();
    let mut last: Option<Vec<Match>> = None;
    let mut rounds = 0;
    loop {
        rounds += 1;
        let (matches, unmatched) = match_blobs(sensor, &model, &blobs, config.match_tolerance);
        for (li, l) in sensor.layers.iter().enumerate() {
            let found = matches.iter().filter(|m| m.layer == li).count();
            if found < MIN_MARKERS_PER_LAYER {
                return Err(CalibrationError::TooFewMarkers {
                    layer: l.name.clone(),
                    found,
                    needed: MIN_MARKERS_PER_LAYER,
                });
            }
        }
        // Round 1: scale and origin first (well posed from any start), then
        // everything; later rounds start from the last model.
        let p0 = if rounds == 1 {
            let (lin, _, _, _) = fit(
                &linear_layout,
                linear_layout.params_of(&model),
                &base,
                &matches,
                config.max_iterations,
            )?;
            lin
        } else {
            layout.params_of(&model)
        };
        let (p, iterations, jtj, cost) = fit(&layout, p0, &base, &matches, config.max_iterations)?;
        model = layout.to_calibration(&p, &base);
        let stable = last.as_ref() == Some(&matches);
        if stable || rounds >= 10 {
            let dof = (2 * matches.len()).saturating_sub(layout.free.len()).max(1);
            let sigma2 = cost / dof as f64;
            let cov = jtj.clone().try_inverse();
            let parameters = layout
                .free
                .iter()
                .enumerate()
                .map(|(col, &i)| {
                    let sd = cov
                        .as_ref()
                        .map(|c| (sigma2 * c[(col, col)]).max(0.0).sqrt())
                        .unwrap_or(f64::NAN);
                    (layout.name(i, sensor), p[i], sd)
                })
                .collect();
            let r = residuals(&layout, &p, &base, &matches);
            let mut per_layer = vec![(0.0f64, 0usize); sensor.layers.len()];
            for (k, m) in matches.iter().enumerate() {
                per_layer[m.layer].0 += r[2 * k].powi(2) + r[2 * k + 1].powi(2);
                per_layer[m.layer].1 += 1;
            }
            model.layers = model
                .layers
                .iter()
                .zip(&per_layer)
                .map(|(l, &(ss, n))| LayerCalibration {
                    rms_px: (ss / (2 * n).max(1) as f64).sqrt(),
                    markers: n,
                    ..l.clone()
                })
                .collect();
            model.rms_px = (cost / r.len().max(1) as f64).sqrt();
            return Ok(CalibrationFit {
                calibration: model,
                iterations,
                rounds,
                parameters,
                unmatched,
            });
        }
        last = Some(matches);
    }
}
