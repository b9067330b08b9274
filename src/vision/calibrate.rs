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
//!
//! Gates (a calibration from a wrong frame is worse than none: every force measured
//! with it is biased):
//! - coverage: with distortion terms, every layer's matched markers must be at least
//!   [`MIN_COVERAGE`] of its grid and span [`MIN_EXTENT`] of its extent on both axes
//!   ([`CalibrationError::PartialCoverage`], which says what the fit cannot determine
//!   and suggests `--radial-terms 0`);
//! - residuals: the centroid noise is measured on the frame itself (robust second
//!   differences along the grid); the fit's RMS must stay within
//!   [`RMS_GATE_FACTOR`] × noise + [`RESIDUAL_FLOOR_PX`] and every marker within
//!   [`MAX_GATE_FACTOR`] × noise + 2 × [`RESIDUAL_FLOOR_PX`]. A loaded frame (its
//!   markers displaced around the contact) or a covered patch (centroids pulled by a
//!   shadow) fails it ([`CalibrationError::NotUnloaded`]).

use nalgebra::{DMatrix, DVector};
use thiserror::Error;

use super::camera::{BrownConrady, CameraCalibration, LayerCalibration};
use super::detect::{detect, DetectConfig};
use super::image::FrameView;
use super::VisionError;
use crate::sensor::{MarkerColor, Sensor};

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
    #[error("layer {layer} (layers[{index}].color = \"{color}\"): {found} markers matched to the grid, calibration needs at least {needed} per layer (check the reference frame: unloaded, in focus, the right sensor file, the layer's color)")]
    TooFewMarkers {
        /// Layer name.
        layer: String,
        /// Its index in the sensor file's `[[layers]]`.
        index: usize,
        /// Its `color`.
        color: MarkerColor,
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
    /// A layer's grid is only partly in the frame: a distortion fit cannot be trusted.
    #[error(
        "layer {layer}: {matched} of its {total} grid markers matched ({:.0} %), covering \
         x {:.1} ... {:.1} mm and y {:.1} ... {:.1} mm of its grid's {:.1} ... {:.1} mm and \
         {:.1} ... {:.1} mm: part of the grid is hidden, out of view or not detected. From part \
         of the grid the distortion (k1, k2, k3, p1, p2) and the principal point cannot be told \
         apart from the layer's scale and origin, so the fit cannot determine them; calibrate \
         from a frame that shows the whole grid, or fit scale and origin only with \
         --radial-terms 0",
        100.0 * *matched as f64 / *total as f64,
        covered_mm[0], covered_mm[2], covered_mm[1], covered_mm[3],
        grid_mm[0], grid_mm[2], grid_mm[1], grid_mm[3]
    )]
    PartialCoverage {
        /// Layer name.
        layer: String,
        /// Grid markers matched.
        matched: usize,
        /// Grid markers of the layer.
        total: usize,
        /// Extent of the matched nodes `[x_min, y_min, x_max, y_max]`, mm.
        covered_mm: [f64; 4],
        /// Extent of the whole grid, mm.
        grid_mm: [f64; 4],
    },
    /// The frame is not a clean unloaded frame: the grid does not fit within the
    /// centroid noise measured on the frame itself.
    #[error(
        "the reference frame does not look like a clean unloaded frame: the fitted grid \
         leaves residuals of {rms_px:.3} px RMS and up to {max_px:.3} px (layer {layer}, \
         marker at pixel ({:.0}, {:.0})), while the centroid noise measured on the frame is \
         {noise_px:.3} px (the gate: RMS at most {rms_gate_px:.3} px, any marker at most \
         {max_gate_px:.3} px). Markers displaced from a regular grid mean the sensor is \
         loaded or touched, or part of the frame is covered (dust, a shadow, a cable); \
         calibrate from a clean frame of the unloaded sensor",
        worst_px[0], worst_px[1]
    )]
    NotUnloaded {
        /// Residual RMS, px.
        rms_px: f64,
        /// Largest marker residual, px.
        max_px: f64,
        /// The layer of that marker.
        layer: String,
        /// Its centroid, px.
        worst_px: [f64; 2],
        /// Centroid noise estimated from the frame, px.
        noise_px: f64,
        /// The RMS gate, px.
        rms_gate_px: f64,
        /// The per-marker gate, px.
        max_gate_px: f64,
    },
}

/// Least share of a layer's grid markers a fit with distortion terms needs (with
/// `--radial-terms 0` and no tangential terms only [`MIN_MARKERS_PER_LAYER`]).
pub const MIN_COVERAGE: f64 = 0.85;

/// Least share of the grid's extent, per axis, the matched markers must span for a
/// fit with distortion terms.
pub const MIN_EXTENT: f64 = 0.85;

/// The residual gate: the fit's RMS may be at most this many times the centroid noise
/// measured on the frame (plus [`RESIDUAL_FLOOR_PX`]).
pub const RMS_GATE_FACTOR: f64 = 3.0;

/// The per-marker gate: no marker's residual may exceed this many times the noise
/// (plus [`RESIDUAL_FLOOR_PX`]).
pub const MAX_GATE_FACTOR: f64 = 8.0;

/// Residual allowance independent of the measured noise, px (what any detector's
/// centroid bias on a clean frame stays under).
pub const RESIDUAL_FLOOR_PX: f64 = 0.05;

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
    /// The centroid noise measured on the frame (px; NaN when too few markers for
    /// the estimate), which the residual gate is set against.
    pub noise_px: f64,
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

/// Refuses a layer whose matched markers cover too little of its grid, when the fit
/// has distortion terms (they are seen only across the whole image).
fn check_coverage(
    sensor: &Sensor,
    matches: &[Match],
    config: &CalibrateConfig,
) -> Result<(), CalibrationError> {
    if config.radial_terms == 0 && !config.tangential {
        return Ok(());
    }
    for (li, l) in sensor.layers.iter().enumerate() {
        let Some(grid) = l.markers.map(|m| m.grid) else {
            continue;
        };
        let a = grid.node_mm(0, 0);
        let b = grid.node_mm(grid.nx.saturating_sub(1), grid.ny.saturating_sub(1));
        let grid_mm = [
            a[0].min(b[0]),
            a[1].min(b[1]),
            a[0].max(b[0]),
            a[1].max(b[1]),
        ];
        let mut cov = [
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ];
        let mut matched = 0;
        for m in matches.iter().filter(|m| m.layer == li) {
            matched += 1;
            let p = m.node_mm;
            cov = [
                cov[0].min(p[0]),
                cov[1].min(p[1]),
                cov[2].max(p[0]),
                cov[3].max(p[1]),
            ];
        }
        let span = |lo: f64, hi: f64, glo: f64, ghi: f64| {
            if ghi > glo {
                (hi - lo) / (ghi - glo)
            } else {
                1.0
            }
        };
        let share = matched as f64 / grid.len().max(1) as f64;
        if share < MIN_COVERAGE
            || span(cov[0], cov[2], grid_mm[0], grid_mm[2]) < MIN_EXTENT
            || span(cov[1], cov[3], grid_mm[1], grid_mm[3]) < MIN_EXTENT
        {
            return Err(CalibrationError::PartialCoverage {
                layer: l.name.clone(),
                matched,
                total: grid.len(),
                covered_mm: cov,
                grid_mm,
            });
        }
    }
    Ok(())
}

/// The centroid noise of the matched markers, px, measured on the frame itself: the
/// second differences of the centroids along grid rows and columns (`p[i−1] − 2 p[i]
/// + p[i+1]`; any smooth mapping — scale, origin, lens distortion — leaves them near
/// zero at a grid's pitch, independent noise σ gives σ√6), taken robustly (1.4826 ×
/// the median absolute value / √6) so that a loaded or covered region does not raise
/// it. `None` with fewer than 10 triples.
fn centroid_noise_px(sensor: &Sensor, matches: &[Match]) -> Option<f64> {
    let mut d = Vec::new();
    for (li, l) in sensor.layers.iter().enumerate() {
        let Some(grid) = l.markers.map(|m| m.grid) else {
            continue;
        };
        let mut at: Vec<Option<[f64; 2]>> = vec![None; grid.len()];
        for m in matches.iter().filter(|m| m.layer == li) {
            if let Some(((ix, iy), _)) = grid.nearest_node(m.node_mm) {
                at[iy * grid.nx + ix] = Some(m.centroid_px);
            }
        }
        let get = |ix: usize, iy: usize| at[iy * grid.nx + ix];
        for iy in 0..grid.ny {
            for ix in 0..grid.nx {
                let c = get(ix, iy);
                let pairs = [
                    (ix >= 1 && ix + 1 < grid.nx).then(|| (get(ix - 1, iy), get(ix + 1, iy))),
                    (iy >= 1 && iy + 1 < grid.ny).then(|| (get(ix, iy - 1), get(ix, iy + 1))),
                ];
                for (a, b) in pairs.into_iter().flatten() {
                    if let (Some(a), Some(c), Some(b)) = (a, c, b) {
                        d.push((a[0] - 2.0 * c[0] + b[0]).abs());
                        d.push((a[1] - 2.0 * c[1] + b[1]).abs());
                    }
                }
            }
        }
    }
    if d.len() < 20 {
        return None;
    }
    d.sort_by(f64::total_cmp);
    let median = d[d.len() / 2];
    Some(1.4826 * median / 6f64.sqrt())
}

/// The residual gate: refuses a fit whose residuals exceed what the frame's own
/// centroid noise allows (a loaded frame, a covered patch).
fn check_residuals(sensor: &Sensor, matches: &[Match], r: &[f64]) -> Result<(), CalibrationError> {
    let Some(noise) = centroid_noise_px(sensor, matches) else {
        return Ok(());
    };
    let rms = (r.iter().map(|v| v * v).sum::<f64>() / r.len().max(1) as f64).sqrt();
    let (mut worst, mut max) = (0, 0.0f64);
    for k in 0..matches.len() {
        let e = r[2 * k].hypot(r[2 * k + 1]);
        if e > max {
            max = e;
            worst = k;
        }
    }
    let rms_gate = RMS_GATE_FACTOR * noise + RESIDUAL_FLOOR_PX;
    let max_gate = MAX_GATE_FACTOR * noise + 2.0 * RESIDUAL_FLOOR_PX;
    if rms > rms_gate || max > max_gate {
        let m = &matches[worst];
        return Err(CalibrationError::NotUnloaded {
            rms_px: rms,
            max_px: max,
            layer: sensor.layers[m.layer].name.clone(),
            worst_px: m.centroid_px,
            noise_px: noise,
            rms_gate_px: rms_gate,
            max_gate_px: max_gate,
        });
    }
    Ok(())
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
                index: 0,
                color: sensor.layers[0].color,
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
                    index: li,
                    color: l.color,
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
        let (p, iterations, jtj, cost) =
            match fit(&layout, p0, &base, &matches, config.max_iterations) {
                Ok(f) => f,
                // A fit on part of the grid fails for that reason: say so.
                Err(e) => return Err(check_coverage(sensor, &matches, config).err().unwrap_or(e)),
            };
        model = layout.to_calibration(&p, &base);
        let stable = last.as_ref() == Some(&matches);
        if stable || rounds >= 10 {
            check_coverage(sensor, &matches, config)?;
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
            check_residuals(sensor, &matches, &r)?;
            let noise_px = centroid_noise_px(sensor, &matches).unwrap_or(f64::NAN);
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
                noise_px,
            });
        }
        last = Some(matches);
    }
}
