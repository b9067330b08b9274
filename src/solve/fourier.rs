//! `fourier`: regularised inversion on regular grids by per-frequency solves, `O(N log N)`
//! per frame.
//!
//! # Model
//!
//! The half-space response (Eq. 1–2, [`HalfSpace::point_response`]) depends only on the
//! horizontal offset between marker and force point, so on regular grids `u = H f` is a
//! (multi-channel, multi-rate) convolution. Force nodes sit at `x_j = o_f + p_f·j`
//! (`sensor.force_grid`), markers of layer `ℓ` at `y_i = o_ℓ + p_m·i` (the layer's marker
//! grid; all layers share one pitch `p_m`, origins are arbitrary). With a fine pitch `h`,
//! `p_f = a·h`, `p_m = b·h` (`a`, `b` coprime, `a·b ≤` [`MAX_LCM`]):
//!
//! ```text
//! u_ℓ[i] = Σ_j k_ℓ[b·i − a·j] f[j],     k_ℓ[t] = K(o_ℓ − o_f + h·t, depth_ℓ)      (per axis)
//!        = down_b( k_ℓ ∗ up_a(f) )[i]
//! ```
//!
//! Any sub-pitch offset between a layer and the force grid is absorbed exactly into the
//! sampled kernel `k_ℓ`. On a periodic fine grid of `N` nodes per axis (`N` a multiple of
//! `L = a·b`, 2-3-5-7-smooth) the DFT turns this into (per axis, unnormalised DFTs, `M = N/L`,
//! marker lattice period `N/b = a·M`, force lattice period `N/a = b·M`):
//!
//! ```text
//! U_ℓ[c + s'M] = (1/b) Σ_{t=0}^{L−1, t ≡ s' (mod a)} K̂_ℓ[c + tM] · F[c + (t mod b)M]
//! ```
//!
//! so the operator is block-diagonal: block `c = (c_x, c_y)` couples `b²` force
//! frequencies (3 unknowns each) with `a²` marker frequencies (2 values per layer). In the
//! unitary scaling (`Ũ = U/√(#markers of the lattice)`, `F̃ = F/√(#force nodes)`) the block
//! entries are `K̂_ℓ/(a·b)` and the block singular values are exactly the singular values
//! of the periodic operator. Each block is solved by Tikhonov regularisation from its SVD
//! `A_c = U Σ Vᴴ`: `P_c = V diag(σ/(σ²+λ²)) Uᴴ` (λ = 0: `1/σ` above the cut-off
//! `rcond·σ_max`, else 0, so null blocks such as the uniform normal load stay finite).
//! λ is fixed or chosen by GCV / L-curve on the given frame, evaluated in the Fourier
//! domain (Hansen, *Rank-Deficient and Discrete Ill-Posed Problems*, SIAM 1998, §7),
//! which is exact for the periodic operator because the transform is unitary.
//!
//! # Boundaries
//!
//! `N ≥ b(n_m − 1) + a(n_f − 1) + 1 + padding`, where the padding is
//! `fourier_padding × (larger of the force and marker grid extents)` per axis, so circular
//! convolution equals linear convolution for every (marker, force node) pair of the real
//! grids: the kernel window contains every offset that occurs. The periodic *model*,
//! however, has markers in the padding, which are not measured, and forces on the whole
//! periodic force lattice, which are cropped to the force grid afterwards:
//!
//! - by default ([`FourierSolver::bridge_edges`]) each padding marker gets a raised-cosine
//!   blend of the two opposite edge markers of its row / column, so the periodic
//!   displacement field has no jump at the grid boundary; with `bridge_edges = false` the
//!   padding counts as measured zero displacement (the textbook periodic model);
//! - λ selection (GCV, L-curve) and the diagnostics use the zero-padded periodic model.
//!   The L-curve corner works well there; GCV under-regularises, because the padding rows
//!   look like noise-free measurements (16×16 grid, 0.005 mm noise: GCV picks λ ≈ 10×
//!   too small, force error 1.7 vs 0.55 with the L-curve). Prefer `lcurve` or a fixed λ.
//!
//! Real displacements do not vanish (nor follow the bridge) outside the marker area: they
//! decay like `1/r`. The direct solve therefore has a boundary error: forces within a few
//! elastomer depths of the grid edges are biased, and the bias leaks into the interior
//! because the kernel is wide. Measured on `grid_sensor(16,16,1.1,1.1)` and
//! `grid_sensor(10,8,2.2,1.1)` with a 2 mm Gaussian load, noise-free, λ = 1e-3·σ_max
//! (σ_max of the periodic operator, about 5× that of the dense `H`): the direct solve is
//! within ~25 % of the truth in the interior (≥ 4 mm from the edges), about the same as
//! the dense Tikhonov solution at that λ (regularisation bias), and within ~35 % over the
//! whole grid; at λ = 1e-2·σ_max it agrees with dense Tikhonov at the same λ to ~10 % in
//! the interior and ~20 % overall (zero padding instead of the bridge: 2–5× worse).
//! Smaller λ does not help the direct solve: its error floor (~20 % interior on the
//! 10×8 grid) is the boundary model, while dense Tikhonov goes to 0.
//!
//! Optional refinement ([`FourierSolver::refine_iterations`]) removes the boundary error:
//! CGLS (conjugate gradients on the normal equations of `min ‖H f − u‖² + λ²‖f‖²`,
//! Björck, *Numerical Methods for Least Squares Problems*, SIAM 1996, §7.4) on the exact
//! operator `H` restricted to the measured markers and the force grid, applied by the
//! same FFTs (exact: the kernel window holds every offset), started from the direct
//! solve and preconditioned by the periodic block inverse `(AᴴA + λ²I)⁻¹` (a block
//! circulant preconditioner, T. Chan 1988). Each iteration costs about three applies. It
//! converges to the dense Tikhonov solution (30 iterations: 1e-11 relative at
//! λ = 1e-2·σ_max); for small λ (≲ 1e-3·σ_max) convergence is slow and the first
//! iterates can be worse than the direct solve (CGLS minimises the residual, not the
//! force error), so use it with moderate λ.
//!
//! # Per frame
//!
//! `ux + i·uy` of each layer goes through one complex 2-D FFT (x then y; the x pass runs
//! on the marker rows only: padding rows are zero or, with the bridge, blends of two
//! transformed rows, since the transform is linear); the real spectra are separated by conjugate symmetry; the
//! blocks with `c_x ≤ M_x/2` are applied (the others follow by Hermitian symmetry);
//! `fx + i·fy` and `fz` are transformed back (only the rows of the force grid in the last
//! pass) and cropped. Plans, scratch and all buffers live in the struct: no allocation.
//!
//! # Refused geometries
//!
//! [`SolveError::Incompatible`] when a marker is not on its layer's regular grid (more
//! than `1e-3` pitch off, e.g. a rotated grid), when markers of a layer grid are missing
//! (lost markers: use a dense solver), when layers have different pitches or a layer has
//! no regular grid, or when `p_f/p_m` is not a ratio of small integers (the paper's
//! 2.2 mm / 1.5 mm = 22/15 is refused; markers every 1.1 mm or 2.2 mm would work).

use std::sync::Arc;

use nalgebra::DMatrix;
use rustfft::num_complex::Complex64;
use rustfft::{Fft, FftPlanner};

use super::{
    check_input, check_output, Diagnostics, FrameSolver, Lambda, Method, Problem, SolveError,
    SolverConfig,
};
use crate::model::HalfSpace;

type C64 = Complex64;

/// Largest accepted `lcm(a, b)` of the pitch ratio `p_f : p_m = a : b`. Block sizes grow
/// like `a²` and `b²`; beyond 8 the blocks stop being "small" and a dense solver is the
/// better tool anyway.
pub const MAX_LCM: usize = 8;

/// Markers further than this fraction of the pitch from their grid node are refused.
pub const OFF_GRID_TOLERANCE: f64 = 1e-3;

/// Relative tolerance on `p_f·b = p_m·a`.
const RATIO_TOLERANCE: f64 = 1e-9;

/// Largest accepted `fourier_padding`: beyond it the FFTs grow without improving the
/// periodic model noticeably.
const MAX_PADDING: f64 = 8.0;

/// Points of the log-spaced λ scan used by GCV and the L-curve.
const LAMBDA_SCAN: usize = 161;

/// The fine-grid geometry a [`FourierSolver`] found for its problem.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FourierGeometry {
    /// `a` in `p_f = a·h`.
    pub force_factor: usize,
    /// `b` in `p_m = b·h`.
    pub marker_factor: usize,
    /// The fine pitch `h`, mm.
    pub fine_pitch_mm: f64,
    /// Fine period `N` per axis (x, y), nodes.
    pub period: [usize; 2],
    /// Number of frequency blocks per axis (`N / (a·b)`).
    pub blocks: [usize; 2],
    /// Rows × columns of one frequency block (`2·layers·a²`, `3·b²`).
    pub block_shape: (usize, usize),
}

/// One marker layer that carries data.
#[derive(Debug, Clone, Copy)]
struct LayerPlan {
    /// Markers per axis.
    nm: [usize; 2],
}

/// Everything fixed after precompute: sizes, index maps, FFT plans.
struct Plan {
    a: usize,
    b: usize,
    /// Blocks per axis.
    m: [usize; 2],
    /// Marker lattice period per axis (`a·m`).
    mm: [usize; 2],
    /// Force lattice period per axis (`b·m`).
    mf: [usize; 2],
    /// Force grid size per axis.
    nf: [usize; 2],
    layers: Vec<LayerPlan>,
    rows: usize,
    cols: usize,
    /// Processed blocks (`c_x ≤ M_x/2`).
    blocks: Vec<[usize; 2]>,
    /// For each input marker: (layer slot, row-major index `iy·mm_x + ix` in its buffer).
    site_map: Vec<(usize, usize)>,
    /// Per layer, edge-bridge weights of the padding columns / rows.
    bridge_x: Vec<Vec<f64>>,
    bridge_y: Vec<Vec<f64>>,
    /// `1/√(#marker lattice · #force lattice)`: the DFT normalisation of both pipelines.
    scale: f64,
    fwd_mx: Arc<dyn Fft<f64>>,
    fwd_my: Arc<dyn Fft<f64>>,
    inv_mx: Arc<dyn Fft<f64>>,
    inv_my: Arc<dyn Fft<f64>>,
    fwd_fx: Arc<dyn Fft<f64>>,
    fwd_fy: Arc<dyn Fft<f64>>,
    inv_fx: Arc<dyn Fft<f64>>,
    inv_fy: Arc<dyn Fft<f64>>,
}

/// Per-frame buffers, allocated once.
struct Work {
    scratch: Vec<C64>,
    /// Per layer: `nm_y × mm_x`, row-major (the rows of the marker lattice that hold data).
    z: Vec<Vec<C64>>,
    /// Per layer: spectrum `mm_x × mm_y` (transposed layout `[px][py]`).
    spec: Vec<Vec<C64>>,
    /// Force spectra `mf_x × mf_y` (`[qx][qy]`) of `fx + i·fy` and `fz`.
    gxy: Vec<C64>,
    gz: Vec<C64>,
    /// Force-grid rows `nf_y × mf_x` of `fx + i·fy` and `fz`.
    hxy: Vec<C64>,
    hz: Vec<C64>,
    /// Output spectra of the preconditioner (`mf_x × mf_y`).
    gtmp_xy: Vec<C64>,
    gtmp_z: Vec<C64>,
    /// One block's input and output.
    vin: Vec<C64>,
    vout: Vec<C64>,
    /// CGLS vectors: markers (`r`, `q`) and forces (`s`, `p`).
    r: Vec<f64>,
    q: Vec<f64>,
    s: Vec<f64>,
    p: Vec<f64>,
    /// Preconditioned gradient `M s` (forces).
    zf: Vec<f64>,
}

/// The `fourier` solver: precomputed per-frequency Tikhonov solutions.
pub struct FourierSolver {
    plan: Plan,
    work: Work,
    /// Per processed block, `cols × rows` solution operator (unitary scaling).
    p: Vec<C64>,
    /// Per processed block, `rows × cols` forward operator (unitary scaling).
    a: Vec<C64>,
    /// Per processed block, `cols × cols` preconditioner `(AᴴA + λ²I)⁻¹` (λ > 0 only).
    q: Vec<C64>,
    lambda: f64,
    geometry: FourierGeometry,
    diag: Diagnostics,
    n_in: usize,
    n_out: usize,
    /// CGLS iterations on the exact (non-periodic) operator after the direct periodic
    /// solve; 0 (the default) is the plain direct solve. Each iteration costs about two
    /// applies; see the module docs.
    pub refine_iterations: usize,
    /// Precondition the refinement with the periodic block inverse `(AᴴA + λ²I)⁻¹`
    /// (default true; ignored for λ = 0).
    pub refine_preconditioned: bool,
    /// Fill the padding with a smooth bridge between opposite edges of each marker grid
    /// instead of zeros before the direct solve (default true; see the module docs).
    pub bridge_edges: bool,
}

impl std::fmt::Debug for FourierSolver {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FourierSolver")
            .field("geometry", &self.geometry)
            .field("lambda", &self.lambda)
            .field("refine_iterations", &self.refine_iterations)
            .finish_non_exhaustive()
    }
}

fn gcd(a: usize, b: usize) -> usize {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

/// All accepted `(a, b)`: coprime, `a·b ≤ MAX_LCM`.
fn ratio_candidates() -> impl Iterator<Item = (usize, usize)> {
    (1..=MAX_LCM)
        .flat_map(|a| (1..=MAX_LCM).map(move |b| (a, b)))
        .filter(|&(a, b)| gcd(a, b) == 1 && a * b <= MAX_LCM)
}

/// `(a, b)` with `p_f/p_m = a/b` and the smallest `a·b`, or an error saying what would work.
fn commensurate(force_pitch_mm: f64, marker_pitch_mm: f64) -> Result<(usize, usize), SolveError> {
    let mut best: Option<(usize, usize)> = None;
    for (a, b) in ratio_candidates() {
        let lhs = force_pitch_mm * b as f64;
        let rhs = marker_pitch_mm * a as f64;
        if (lhs - rhs).abs() <= RATIO_TOLERANCE * lhs.abs()
            && best.is_none_or(|(x, y)| a * b < x * y)
        {
            best = Some((a, b));
        }
    }
    if let Some(ab) = best {
        return Ok(ab);
    }
    // Suggest the nearest commensurate marker pitches and force pitches.
    let nearest = |target: f64, make: &dyn Fn(usize, usize) -> f64| -> Vec<f64> {
        let mut c: Vec<f64> = ratio_candidates().map(|(a, b)| make(a, b)).collect();
        c.sort_by(|x, y| (x - target).abs().total_cmp(&(y - target).abs()));
        c.dedup_by(|x, y| (*x - *y).abs() < 1e-9);
        c.truncate(2);
        c
    };
    let fmt = |v: Vec<f64>| {
        v.iter()
            .map(|x| format!("{x:.4} mm"))
            .collect::<Vec<_>>()
            .join(" or ")
    };
    let markers = nearest(marker_pitch_mm, &|a, b| {
        force_pitch_mm * b as f64 / a as f64
    });
    let forces = nearest(force_pitch_mm, &|a, b| {
        marker_pitch_mm * a as f64 / b as f64
    });
    let simple = [force_pitch_mm / 2.0, force_pitch_mm]
        .iter()
        .map(|x| format!("{x:.4} mm"))
        .collect::<Vec<_>>()
        .join(" or ");
    Err(SolveError::Incompatible(format!(
        "force pitch {force_pitch_mm} mm and marker pitch {marker_pitch_mm} mm have ratio {:.6}, \
         which is not a ratio a:b of small integers (a·b ≤ {MAX_LCM}), so the grids share no \
         common fine lattice; markers every {simple} (or {}) would work, as would force points \
         every {}; otherwise use a dense solver (pinv, tikhonov, tsvd)",
        force_pitch_mm / marker_pitch_mm,
        fmt(markers),
        fmt(forces)
    )))
}

/// Index of `−i` modulo `n` for `i < n` (no integer division in the hot loops).
#[inline(always)]
fn neg(i: usize, n: usize) -> usize {
    if i == 0 {
        0
    } else {
        n - i
    }
}

/// Smallest 2-3-5-7-smooth integer ≥ n (fast FFT sizes).
fn smooth_at_least(n: usize) -> usize {
    let mut k = n.max(1);
    loop {
        let mut r = k;
        for p in [2, 3, 5, 7] {
            while r.is_multiple_of(p) {
                r /= p;
            }
        }
        if r == 1 {
            return k;
        }
        k += 1;
    }
}

/// Cache-friendly out-of-place transpose: `dst[c·dst_stride + r] = src[r·src_stride + c]`
/// for `r < rows`, `c < cols`.
fn transpose(
    src: &[C64],
    src_stride: usize,
    dst: &mut [C64],
    dst_stride: usize,
    rows: usize,
    cols: usize,
) {
    const T: usize = 16;
    for r0 in (0..rows).step_by(T) {
        let r1 = (r0 + T).min(rows);
        for c0 in (0..cols).step_by(T) {
            let c1 = (c0 + T).min(cols);
            for r in r0..r1 {
                let row = &src[r * src_stride..];
                for c in c0..c1 {
                    dst[c * dst_stride + r] = row[c];
                }
            }
        }
    }
}

/// Unnormalised forward 2-D DFT of a row-major `ny × nx` array; returns the spectrum in
/// transposed layout `[qx][qy]` (precompute only: allocates).
fn fft2_transposed(
    planner: &mut FftPlanner<f64>,
    data: &mut [C64],
    nx: usize,
    ny: usize,
) -> Vec<C64> {
    let fx = planner.plan_fft_forward(nx);
    let fy = planner.plan_fft_forward(ny);
    let mut scratch = vec![
        C64::default();
        fx.get_inplace_scratch_len()
            .max(fy.get_inplace_scratch_len())
    ];
    fx.process_with_scratch(data, &mut scratch);
    let mut out = vec![C64::default(); nx * ny];
    transpose(data, nx, &mut out, ny, ny, nx);
    fy.process_with_scratch(&mut out, &mut scratch);
    out
}

impl FourierSolver {
    /// Precomputes the solver for `problem` (see the module docs). `frame` (mm, the order
    /// of `problem.sites`) is needed for automatic λ (GCV, L-curve) and ignored for a
    /// fixed λ.
    pub fn precompute(
        problem: &Problem<'_>,
        config: &SolverConfig,
        frame: Option<&[f64]>,
    ) -> Result<FourierSolver, SolveError> {
        let sensor = problem.sensor;
        let sites = problem.sites;
        if sites.is_empty() {
            return Err(SolveError::Empty("no markers carry data".into()));
        }
        let n_in = 2 * sites.len();
        let n_out = 3 * sensor.force_grid.len();
        if n_out == 0 {
            return Err(SolveError::Empty("the force grid has no nodes".into()));
        }
        if let Some(u) = frame {
            check_input(u, n_in)?;
        }
        let pad = config.fourier_padding;
        if !(pad.is_finite() && (0.0..=MAX_PADDING).contains(&pad)) {
            return Err(SolveError::InvalidOption(format!(
                "fourier_padding = {pad} must be in [0, {MAX_PADDING}] (fraction of the grid extent)"
            )));
        }
        if let Lambda::Fixed(l) = config.lambda {
            if !(l.is_finite() && l >= 0.0) {
                return Err(SolveError::InvalidOption(format!(
                    "lambda = {l} mm/N must be a finite number >= 0"
                )));
            }
        } else if frame.is_none() {
            return Err(SolveError::NeedsFrame("λ"));
        }
        if let Some(r) = config.rcond {
            if !(r.is_finite() && r >= 0.0) {
                return Err(SolveError::InvalidOption(format!(
                    "rcond = {r} must be a finite number >= 0"
                )));
            }
        }

        // ---- map sites to (layer, ix, iy) ----
        let fg = sensor.force_grid;
        let mut slot_of_layer = vec![usize::MAX; sensor.layers.len()];
        let mut layer_of_slot: Vec<usize> = Vec::new();
        let mut marker_pitch: Option<(f64, usize)> = None;
        for (k, s) in sites.iter().enumerate() {
            let Some(layer) = sensor.layers.get(s.layer) else {
                return Err(SolveError::Incompatible(format!(
                    "marker {k} refers to layer {} but the sensor has {} layers",
                    s.layer,
                    sensor.layers.len()
                )));
            };
            let Some(mg) = layer.markers else {
                return Err(SolveError::Incompatible(format!(
                    "layer {} (marker {k}) has no regular marker grid in sensor.toml; \
                     use a dense solver (pinv, tikhonov, tsvd)",
                    layer.name
                )));
            };
            if (s.depth_mm - layer.depth_mm).abs() > 1e-9 * layer.depth_mm.abs().max(1.0) {
                return Err(SolveError::Incompatible(format!(
                    "marker {k} of layer {} has depth {} mm but the layer is at {} mm: the \
                     fourier solver needs one depth per layer",
                    layer.name, s.depth_mm, layer.depth_mm
                )));
            }
            match marker_pitch {
                None => marker_pitch = Some((mg.grid.pitch_mm, s.layer)),
                Some((p, l0)) => {
                    if (p - mg.grid.pitch_mm).abs() > RATIO_TOLERANCE * p {
                        return Err(SolveError::Incompatible(format!(
                            "layer {} has marker pitch {} mm but layer {} has {} mm: the \
                             fourier solver needs one marker pitch for all layers",
                            layer.name, mg.grid.pitch_mm, sensor.layers[l0].name, p
                        )));
                    }
                }
            }
            if slot_of_layer[s.layer] == usize::MAX {
                slot_of_layer[s.layer] = layer_of_slot.len();
                layer_of_slot.push(s.layer);
            }
        }
        // Slots in layer order, so the block layout does not depend on site order.
        layer_of_slot.sort_unstable();
        for (slot, &l) in layer_of_slot.iter().enumerate() {
            slot_of_layer[l] = slot;
        }
        let (marker_pitch_mm, _) =
            marker_pitch.ok_or_else(|| SolveError::Empty("no markers".into()))?;
        let (a, b) = commensurate(fg.pitch_mm, marker_pitch_mm)?;
        let l = a * b;
        let h = fg.pitch_mm / a as f64;

        let layers: Vec<LayerPlan> = layer_of_slot
            .iter()
            .map(|&li| {
                let g = sensor.layers[li].markers.map(|m| m.grid).unwrap_or(fg);
                LayerPlan { nm: [g.nx, g.ny] }
            })
            .collect();
        let nf = [fg.nx, fg.ny];

        // Fine period per axis: every (marker, force) offset plus padding, a multiple of L
        // with smooth block count.
        let mut period = [0usize; 2];
        let mut m = [0usize; 2];
        for ax in 0..2 {
            let mut span = 0usize;
            let mut ext = a * (nf[ax] - 1);
            for lp in &layers {
                span = span.max(a * (nf[ax] - 1) + b * (lp.nm[ax] - 1) + 1);
                ext = ext.max(b * (lp.nm[ax] - 1));
            }
            let want = span + (pad * ext as f64).ceil() as usize;
            m[ax] = smooth_at_least(want.div_ceil(l));
            period[ax] = m[ax] * l;
        }
        let mm = [a * m[0], a * m[1]];
        let mf = [b * m[0], b * m[1]];

        let mut site_map = Vec::with_capacity(sites.len());
        let mut seen: Vec<Vec<bool>> = layers
            .iter()
            .map(|lp| vec![false; lp.nm[0] * lp.nm[1]])
            .collect();
        for (k, s) in sites.iter().enumerate() {
            let layer = &sensor.layers[s.layer];
            let slot = slot_of_layer[s.layer];
            let grid = layer.markers.map(|m| m.grid).unwrap_or(fg);
            let tol = OFF_GRID_TOLERANCE * grid.pitch_mm;
            let ((ix, iy), d) = match grid.nearest_node(s.position_mm) {
                Some(v) => v,
                None => {
                    return Err(SolveError::Incompatible(format!(
                        "marker {k} of layer {} at ({:.4}, {:.4}) mm lies outside the layer's \
                         {}×{} grid (origin ({}, {}) mm, pitch {} mm); use a dense solver",
                        layer.name,
                        s.position_mm[0],
                        s.position_mm[1],
                        grid.nx,
                        grid.ny,
                        grid.origin_mm[0],
                        grid.origin_mm[1],
                        grid.pitch_mm
                    )))
                }
            };
            if d > tol {
                return Err(SolveError::Incompatible(format!(
                    "marker {k} of layer {} at ({:.4}, {:.4}) mm is {d:.4} mm from its nearest \
                     grid node ({ix}, {iy}) (tolerance {tol:.4} mm = {OFF_GRID_TOLERANCE} pitch): \
                     the fourier solver needs markers on the layer's regular grid (a rotated or \
                     distorted grid is not); use a dense solver (pinv, tikhonov, tsvd)",
                    layer.name, s.position_mm[0], s.position_mm[1]
                )));
            }
            let node = iy * grid.nx + ix;
            if seen[slot][node] {
                return Err(SolveError::Incompatible(format!(
                    "marker {k} of layer {} is a second marker on grid node ({ix}, {iy})",
                    layer.name
                )));
            }
            seen[slot][node] = true;
            site_map.push((slot, iy * mm[0] + ix));
        }
        for (slot, s) in seen.iter().enumerate() {
            let missing = s.iter().filter(|&&x| !x).count();
            if let Some(first) = s.iter().position(|&x| !x) {
                let lp = layers[slot];
                return Err(SolveError::Incompatible(format!(
                    "layer {}: {missing} of {} grid markers carry no data (first missing node \
                     ({}, {})); the fourier solver needs complete marker grids, lost markers \
                     are handled by the dense solvers (pinv, tikhonov, tsvd)",
                    sensor.layers[layer_of_slot[slot]].name,
                    lp.nm[0] * lp.nm[1],
                    first % lp.nm[0],
                    first / lp.nm[0]
                )));
            }
        }

        // ---- kernel spectra on the fine grid ----
        let model: HalfSpace = problem.model;
        let mut planner = FftPlanner::<f64>::new();
        let nfine = period[0] * period[1];
        // khat[slot][comp][qx·N_y + qy], comp = 3·axis_u + axis_f.
        let mut khat: Vec<Vec<Vec<C64>>> = Vec::with_capacity(layers.len());
        for (slot, lp) in layers.iter().enumerate() {
            let layer = &sensor.layers[layer_of_slot[slot]];
            let grid = layer.markers.map(|m| m.grid).unwrap_or(fg);
            let mut lo = [0i64; 2];
            for ax in 0..2 {
                let span = a * (nf[ax] - 1) + b * (lp.nm[ax] - 1) + 1;
                lo[ax] = -((a * (nf[ax] - 1)) as i64) - ((period[ax] - span) / 2) as i64;
            }
            let mut comps = vec![vec![C64::default(); nfine]; 6];
            for ty in lo[1]..lo[1] + period[1] as i64 {
                let iy = ty.rem_euclid(period[1] as i64) as usize;
                let dy = grid.origin_mm[1] - fg.origin_mm[1] + h * ty as f64;
                for tx in lo[0]..lo[0] + period[0] as i64 {
                    let ix = tx.rem_euclid(period[0] as i64) as usize;
                    let dx = grid.origin_mm[0] - fg.origin_mm[0] + h * tx as f64;
                    let r = model.point_response(dx, dy, layer.depth_mm);
                    for (c, comp) in comps.iter_mut().enumerate() {
                        comp[iy * period[0] + ix] = C64::new(r[c / 3][c % 3], 0.0);
                    }
                }
            }
            let spectra = comps
                .iter_mut()
                .map(|c| fft2_transposed(&mut planner, c, period[0], period[1]))
                .collect();
            khat.push(spectra);
        }

        // ---- blocks ----
        let rows = 2 * layers.len() * a * a;
        let cols = 3 * b * b;
        let kmin = rows.min(cols);
        let mut blocks = Vec::new();
        for cx in 0..=m[0] / 2 {
            for cy in 0..m[1] {
                blocks.push([cx, cy]);
            }
        }
        let weight = |c: [usize; 2]| {
            if c[0] == 0 || 2 * c[0] == m[0] {
                1.0
            } else {
                2.0
            }
        };
        let inv_ab = 1.0 / (a * b) as f64;
        let nb = blocks.len();
        let mut amat = vec![C64::default(); nb * rows * cols];
        let mut sig = vec![0.0f64; nb * kmin];
        let mut uvec = vec![C64::default(); nb * rows * kmin];
        let mut vvec = vec![C64::default(); nb * cols * kmin];
        for (bi, c) in blocks.iter().enumerate() {
            let ab = &mut amat[bi * rows * cols..(bi + 1) * rows * cols];
            for ty in 0..l {
                let qy = c[1] + ty * m[1];
                let (sry, sfy) = (ty % a, ty % b);
                for tx in 0..l {
                    let qx = c[0] + tx * m[0];
                    let (srx, sfx) = (tx % a, tx % b);
                    let q = qx * period[1] + qy;
                    for (slot, kh) in khat.iter().enumerate() {
                        let row0 = ((slot * a + sry) * a + srx) * 2;
                        let col0 = (sfy * b + sfx) * 3;
                        for i in 0..2 {
                            for j in 0..3 {
                                ab[(row0 + i) * cols + col0 + j] += kh[3 * i + j][q] * inv_ab;
                            }
                        }
                    }
                }
            }
            let dm = DMatrix::from_row_slice(rows, cols, ab);
            let svd = dm
                .try_svd_unordered(true, true, f64::EPSILON, 10_000)
                .ok_or_else(|| {
                    SolveError::Decomposition(format!(
                        "svd of frequency block ({}, {}) did not converge",
                        c[0], c[1]
                    ))
                })?;
            let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
                return Err(SolveError::Decomposition(
                    "svd returned no singular vectors".into(),
                ));
            };
            for i in 0..kmin {
                let s = svd.singular_values[i];
                if !s.is_finite() {
                    return Err(SolveError::Decomposition(format!(
                        "frequency block ({}, {}) has a non-finite singular value",
                        c[0], c[1]
                    )));
                }
                sig[bi * kmin + i] = s;
                for r in 0..rows {
                    uvec[(bi * kmin + i) * rows + r] = u[(r, i)];
                }
                for j in 0..cols {
                    vvec[(bi * kmin + i) * cols + j] = vt[(i, j)].conj();
                }
            }
        }
        let sigma_max = sig.iter().cloned().fold(0.0f64, f64::max);
        if sigma_max <= 0.0 {
            return Err(SolveError::Decomposition(
                "the periodic operator is zero".into(),
            ));
        }
        let n_total_rows: f64 = blocks.iter().map(|&c| weight(c) * rows as f64).sum();
        let n_total_cols: f64 = blocks.iter().map(|&c| weight(c) * cols as f64).sum();
        let rcond = config
            .rcond
            .unwrap_or(n_total_rows.max(n_total_cols) * f64::EPSILON);
        let cutoff = rcond * sigma_max;

        // ---- plan and work buffers ----
        let plan = Plan {
            a,
            b,
            m,
            mm,
            mf,
            nf,
            rows,
            cols,
            blocks,
            site_map,
            bridge_x: layers
                .iter()
                .map(|lp| bridge_weights(mm[0] - lp.nm[0]))
                .collect(),
            bridge_y: layers
                .iter()
                .map(|lp| bridge_weights(mm[1] - lp.nm[1]))
                .collect(),
            scale: 1.0 / ((mm[0] * mm[1]) as f64 * (mf[0] * mf[1]) as f64).sqrt(),
            fwd_mx: planner.plan_fft_forward(mm[0]),
            fwd_my: planner.plan_fft_forward(mm[1]),
            inv_mx: planner.plan_fft_inverse(mm[0]),
            inv_my: planner.plan_fft_inverse(mm[1]),
            fwd_fx: planner.plan_fft_forward(mf[0]),
            fwd_fy: planner.plan_fft_forward(mf[1]),
            inv_fx: planner.plan_fft_inverse(mf[0]),
            inv_fy: planner.plan_fft_inverse(mf[1]),
            layers,
        };
        let scratch_len = [
            &plan.fwd_mx,
            &plan.fwd_my,
            &plan.inv_mx,
            &plan.inv_my,
            &plan.fwd_fx,
            &plan.fwd_fy,
            &plan.inv_fx,
            &plan.inv_fy,
        ]
        .iter()
        .map(|f| f.get_inplace_scratch_len())
        .max()
        .unwrap_or(0);
        let mut work = Work {
            scratch: vec![C64::default(); scratch_len],
            z: plan
                .layers
                .iter()
                .map(|_| vec![C64::default(); mm[1] * mm[0]])
                .collect(),
            spec: plan
                .layers
                .iter()
                .map(|_| vec![C64::default(); mm[0] * mm[1]])
                .collect(),
            gxy: vec![C64::default(); mf[0] * mf[1]],
            gz: vec![C64::default(); mf[0] * mf[1]],
            hxy: vec![C64::default(); nf[1] * mf[0]],
            hz: vec![C64::default(); nf[1] * mf[0]],
            gtmp_xy: vec![C64::default(); mf[0] * mf[1]],
            gtmp_z: vec![C64::default(); mf[0] * mf[1]],
            vin: vec![C64::default(); rows.max(cols)],
            vout: vec![C64::default(); rows.max(cols)],
            r: vec![0.0; n_in],
            q: vec![0.0; n_in],
            s: vec![0.0; n_out],
            p: vec![0.0; n_out],
            zf: vec![0.0; n_out],
        };

        // ---- λ ----
        let mut notes = Vec::new();
        let lambda = match (config.lambda, frame) {
            (Lambda::Fixed(l), _) => {
                notes.push(format!("fixed λ = {l:e} mm/N"));
                l
            }
            (choice, Some(u)) => {
                // Project the frame's (unitary) spectrum on each block's left singular vectors.
                markers_to_spectra(&plan, &mut work, u, 1.0, false);
                let unit = 1.0 / ((mm[0] * mm[1]) as f64).sqrt();
                let mut beta2 = vec![0.0f64; nb * kmin];
                let mut rest = 0.0f64;
                let mut total = 0.0f64;
                for (bi, &c) in plan.blocks.iter().enumerate() {
                    gather_marker_block(&plan, &work.spec, c, &mut work.vin);
                    let w = weight(c);
                    let norm2: f64 = work.vin[..rows].iter().map(|v| (v * unit).norm_sqr()).sum();
                    let mut proj = 0.0;
                    for i in 0..kmin {
                        let ui = &uvec[(bi * kmin + i) * rows..(bi * kmin + i + 1) * rows];
                        let beta: C64 = ui
                            .iter()
                            .zip(&work.vin[..rows])
                            .map(|(uu, v)| uu.conj() * v * unit)
                            .sum();
                        beta2[bi * kmin + i] = beta.norm_sqr();
                        proj += beta.norm_sqr();
                    }
                    rest += w * (norm2 - proj).max(0.0);
                    total += w * norm2;
                }
                if total <= 0.0 {
                    return Err(SolveError::InvalidOption(
                        "automatic λ selection needs a frame with nonzero displacements; the given frame is all zero".into(),
                    ));
                }
                let weights: Vec<f64> = plan
                    .blocks
                    .iter()
                    .flat_map(|&c| std::iter::repeat_n(weight(c), kmin))
                    .collect();
                let (l, note) = choose_lambda(
                    choice,
                    &sig,
                    &beta2,
                    &weights,
                    rest,
                    n_total_rows,
                    sigma_max,
                );
                notes.push(note);
                l
            }
            (_, None) => return Err(SolveError::NeedsFrame("λ")),
        };

        // ---- solution operators P = V diag(φ) Uᴴ ----
        let filter = |s: f64| -> f64 {
            if lambda > 0.0 {
                s / (s * s + lambda * lambda)
            } else if s > cutoff {
                1.0 / s
            } else {
                0.0
            }
        };
        let mut pmat = vec![C64::default(); nb * cols * rows];
        for bi in 0..nb {
            let pb = &mut pmat[bi * cols * rows..(bi + 1) * cols * rows];
            for i in 0..kmin {
                let phi = filter(sig[bi * kmin + i]);
                if phi == 0.0 {
                    continue;
                }
                let ui = &uvec[(bi * kmin + i) * rows..(bi * kmin + i + 1) * rows];
                let vi = &vvec[(bi * kmin + i) * cols..(bi * kmin + i + 1) * cols];
                for (j, vj) in vi.iter().enumerate() {
                    let vphi = vj * phi;
                    for (r, ur) in ui.iter().enumerate() {
                        pb[j * rows + r] += vphi * ur.conj();
                    }
                }
            }
        }

        // ---- refinement preconditioner Q = (AᴴA + λ²I)⁻¹ = I/λ² + V diag(1/(σ²+λ²) − 1/λ²) Vᴴ ----
        let mut qmat = vec![C64::default(); nb * cols * cols];
        if lambda > 0.0 {
            let l2 = lambda * lambda;
            let full = kmin == cols;
            for bi in 0..nb {
                let qb = &mut qmat[bi * cols * cols..(bi + 1) * cols * cols];
                if !full {
                    for j in 0..cols {
                        qb[j * cols + j] = C64::new(1.0 / l2, 0.0);
                    }
                }
                for i in 0..kmin {
                    let s2 = sig[bi * kmin + i].powi(2);
                    let psi = if full {
                        1.0 / (s2 + l2)
                    } else {
                        1.0 / (s2 + l2) - 1.0 / l2
                    };
                    let vi = &vvec[(bi * kmin + i) * cols..(bi * kmin + i + 1) * cols];
                    for (j, vj) in vi.iter().enumerate() {
                        for (k, vk) in vi.iter().enumerate() {
                            qb[j * cols + k] += vj * vk.conj() * psi;
                        }
                    }
                }
            }
        }

        // ---- diagnostics ----
        let mut all_sv = Vec::with_capacity(2 * sig.len());
        let mut eff = 0.0;
        let mut gain = 0.0f64;
        for (bi, &c) in plan.blocks.iter().enumerate() {
            let w = weight(c);
            for &s in &sig[bi * kmin..(bi + 1) * kmin] {
                all_sv.push(s);
                if w > 1.0 {
                    all_sv.push(s);
                }
                eff += w * if lambda > 0.0 {
                    s * s / (s * s + lambda * lambda)
                } else if s > cutoff {
                    1.0
                } else {
                    0.0
                };
                gain = gain.max(filter(s));
            }
        }
        all_sv.sort_by(|x, y| y.total_cmp(x));
        let smin = all_sv.last().copied().unwrap_or(0.0);
        let condition_number = if smin > cutoff {
            sigma_max / smin
        } else {
            f64::INFINITY
        };
        let geometry = FourierGeometry {
            force_factor: a,
            marker_factor: b,
            fine_pitch_mm: h,
            period,
            blocks: m,
            block_shape: (rows, cols),
        };
        notes.insert(
            0,
            format!(
                "fine pitch {h} mm (force pitch = {a}·h, marker pitch = {b}·h), period {}×{} fine \
                 nodes, {}×{} frequency blocks of {rows}×{cols}; singular values are those of the \
                 periodic operator (padding markers count as measured zeros)",
                period[0], period[1], m[0], m[1]
            ),
        );
        let diag = Diagnostics {
            method: Method::Fourier,
            shape: (n_in, n_out),
            singular_values: all_sv,
            condition_number,
            effective_rank: eff,
            noise_gain: gain,
            lambda: Some(lambda),
            rank: None,
            notes,
        };
        Ok(FourierSolver {
            plan,
            work,
            p: pmat,
            a: amat,
            q: qmat,
            lambda,
            geometry,
            diag,
            n_in,
            n_out,
            refine_iterations: 0,
            refine_preconditioned: true,
            bridge_edges: true,
        })
    }

    /// The fine-grid geometry in use.
    pub fn geometry(&self) -> FourierGeometry {
        self.geometry
    }

    /// λ in use, mm/N.
    pub fn lambda(&self) -> f64 {
        self.lambda
    }

    /// Sets the number of CGLS refinement iterations (builder style).
    pub fn with_refinement(mut self, iterations: usize) -> Self {
        self.refine_iterations = iterations;
        self
    }

    /// CGLS on `min ‖H f − u‖² + λ²‖f‖²` from the current `f` (Björck 1996, Alg. 7.4.1),
    /// with `H` the exact restricted operator applied by FFT. `u` is already scaled.
    fn refine(&mut self, u: &[f64], in_scale: f64, f: &mut [f64]) {
        let lam2 = self.lambda * self.lambda;
        let precondition = self.refine_preconditioned && self.lambda > 0.0;
        let (plan, w, amat, qmat) = (&self.plan, &mut self.work, &self.a, &self.q);
        // The vectors are taken out of `w` so the operators can borrow it; no allocation.
        let mut q = std::mem::take(&mut w.q);
        let mut r = std::mem::take(&mut w.r);
        let mut s = std::mem::take(&mut w.s);
        let mut p = std::mem::take(&mut w.p);
        let mut z = std::mem::take(&mut w.zf);
        // r = u − H f, s = Hᵀ r − λ² f (the negative gradient), z = M s.
        forward_op(plan, w, amat, f, &mut r);
        for (ri, ui) in r.iter_mut().zip(u) {
            *ri = ui * in_scale - *ri;
        }
        adjoint_op(plan, w, amat, &r, &mut s);
        for (si, fi) in s.iter_mut().zip(f.iter()) {
            *si -= lam2 * fi;
        }
        if precondition {
            precond_op(plan, w, qmat, &s, &mut z);
        } else {
            z.copy_from_slice(&s);
        }
        p.copy_from_slice(&z);
        let mut gamma: f64 = s.iter().zip(&z).map(|(x, y)| x * y).sum();
        for _ in 0..self.refine_iterations {
            if gamma <= 0.0 || !gamma.is_finite() {
                break;
            }
            forward_op(plan, w, amat, &p, &mut q);
            let delta: f64 =
                q.iter().map(|x| x * x).sum::<f64>() + lam2 * p.iter().map(|x| x * x).sum::<f64>();
            if delta <= 0.0 || !delta.is_finite() {
                break;
            }
            let alpha = gamma / delta;
            for (fi, pi) in f.iter_mut().zip(&p) {
                *fi += alpha * pi;
            }
            for (ri, qi) in r.iter_mut().zip(&q) {
                *ri -= alpha * qi;
            }
            adjoint_op(plan, w, amat, &r, &mut s);
            for (si, fi) in s.iter_mut().zip(f.iter()) {
                *si -= lam2 * fi;
            }
            if precondition {
                precond_op(plan, w, qmat, &s, &mut z);
            } else {
                z.copy_from_slice(&s);
            }
            let g2: f64 = s.iter().zip(&z).map(|(x, y)| x * y).sum();
            let beta = g2 / gamma;
            gamma = g2;
            for (pi, zi) in p.iter_mut().zip(&z) {
                *pi = zi + beta * *pi;
            }
        }
        w.q = q;
        w.r = r;
        w.s = s;
        w.p = p;
        w.zf = z;
    }
}

/// Scatters a displacement vector (times `in_scale`) into the layer buffers and
/// transforms it: afterwards `w.spec[slot]` holds the unnormalised DFT of `ux + i·uy`.
fn markers_to_spectra(plan: &Plan, w: &mut Work, u: &[f64], in_scale: f64, bridge: bool) {
    let [mmx, mmy] = plan.mm;
    for (z, lp) in w.z.iter_mut().zip(&plan.layers) {
        z[..lp.nm[1] * mmx].fill(C64::default());
    }
    for (k, &(slot, idx)) in plan.site_map.iter().enumerate() {
        w.z[slot][idx] = C64::new(u[2 * k] * in_scale, u[2 * k + 1] * in_scale);
    }
    for (slot, lp) in plan.layers.iter().enumerate() {
        let [nmx, nmy] = lp.nm;
        let z = &mut w.z[slot];
        if bridge {
            // Along x in space, row by row.
            let wx = &plan.bridge_x[slot];
            for row in z[..nmy * mmx].chunks_exact_mut(mmx) {
                let (first, last) = (row[0], row[nmx - 1]);
                for (v, &s) in row[nmx..].iter_mut().zip(wx) {
                    *v = last * (1.0 - s) + first * s;
                }
            }
        }
        plan.fwd_mx
            .process_with_scratch(&mut z[..nmy * mmx], &mut w.scratch);
        let rows = if bridge {
            // Along y: the padding rows are blends of the first and last data row, and
            // the row transform is linear, so blend the transformed rows (saves the FFTs).
            let wy = &plan.bridge_y[slot];
            let (data, pad) = z.split_at_mut(nmy * mmx);
            let (first, last) = (&data[..mmx], &data[(nmy - 1) * mmx..]);
            for (row, &s) in pad.chunks_exact_mut(mmx).zip(wy) {
                for ((v, f), l) in row.iter_mut().zip(first).zip(last) {
                    *v = l * (1.0 - s) + f * s;
                }
            }
            mmy
        } else {
            nmy
        };
        let spec = &mut w.spec[slot];
        transpose(z, mmx, spec, mmy, rows, mmx);
        // Rows of the lattice beyond the used rows are zero.
        if rows < mmy {
            for px in 0..mmx {
                spec[px * mmy + rows..(px + 1) * mmy].fill(C64::default());
            }
        }
        plan.fwd_my.process_with_scratch(spec, &mut w.scratch);
    }
}

/// Raised-cosine weights of the opposite edge for the `gap` padding nodes between the
/// last data node and the first one (periodically): 0 at the last node, 1 at the first.
fn bridge_weights(gap: usize) -> Vec<f64> {
    (1..=gap)
        .map(|k| 0.5 * (1.0 - (std::f64::consts::PI * k as f64 / (gap + 1) as f64).cos()))
        .collect()
}

/// Gathers the marker values of block `c` as `(Ux, Uy)` per (layer, s'y, s'x), separated
/// from the packed spectra by conjugate symmetry (unnormalised DFT scale).
#[inline]
fn gather_marker_block(plan: &Plan, spec: &[Vec<C64>], c: [usize; 2], out: &mut [C64]) {
    let (a, [mx, my], [mmx, mmy]) = (plan.a, plan.m, plan.mm);
    let mut r = 0;
    for sp in spec {
        for sy in 0..a {
            let py = c[1] + sy * my;
            let ny = neg(py, mmy);
            for sx in 0..a {
                let px = c[0] + sx * mx;
                let nx = neg(px, mmx);
                let s = sp[px * mmy + py];
                let sn = sp[nx * mmy + ny].conj();
                out[r] = (s + sn) * 0.5;
                let d = (s - sn) * 0.5;
                out[r + 1] = C64::new(d.im, -d.re); // −i·d
                r += 2;
            }
        }
    }
}

/// Markers → forces through per-block matrices: `P` (`cols × rows`, direct solve) or the
/// adjoint of `A` (`rows × cols`, for `Hᵀ`).
#[allow(clippy::too_many_arguments)]
fn markers_to_forces(
    plan: &Plan,
    w: &mut Work,
    mats: &[C64],
    adjoint: bool,
    u: &[f64],
    in_scale: f64,
    bridge: bool,
    f: &mut [f64],
) {
    markers_to_spectra(plan, w, u, in_scale, bridge);
    let (rows, cols) = (plan.rows, plan.cols);
    for (bi, &c) in plan.blocks.iter().enumerate() {
        gather_marker_block(plan, &w.spec, c, &mut w.vin);
        let mat = &mats[bi * rows * cols..(bi + 1) * rows * cols];
        let vin = &w.vin[..rows];
        let vout = &mut w.vout[..cols];
        if adjoint {
            vout.fill(C64::default());
            for (r, &v) in vin.iter().enumerate() {
                let row = &mat[r * cols..(r + 1) * cols];
                for (o, m) in vout.iter_mut().zip(row) {
                    *o += m.conj() * v;
                }
            }
        } else {
            for (j, o) in vout.iter_mut().enumerate() {
                let row = &mat[j * rows..(j + 1) * rows];
                *o = row.iter().zip(vin).map(|(m, v)| m * v).sum();
            }
        }
        scatter_force_block(plan, c, &w.vout[..cols], &mut w.gxy, &mut w.gz);
    }
    let ForceBufs {
        gxy,
        gz,
        hxy,
        hz,
        scratch,
    } = w.force_bufs();
    spectra_to_forces(plan, gxy, gz, hxy, hz, scratch, plan.scale, f);
}

/// Borrowed force-side buffers (split borrows of [`Work`]).
struct ForceBufs<'a> {
    gxy: &'a mut [C64],
    gz: &'a mut [C64],
    hxy: &'a mut [C64],
    hz: &'a mut [C64],
    scratch: &'a mut [C64],
}

impl Work {
    fn force_bufs(&mut self) -> ForceBufs<'_> {
        ForceBufs {
            gxy: &mut self.gxy,
            gz: &mut self.gz,
            hxy: &mut self.hxy,
            hz: &mut self.hz,
            scratch: &mut self.scratch,
        }
    }
}

/// Writes one block's force spectrum `(Fx, Fy, Fz)` per (s_y, s_x) into the packed
/// spectra of `fx + i·fy` and `fz`, and its Hermitian partner at `−q`.
#[inline]
fn scatter_force_block(plan: &Plan, c: [usize; 2], v: &[C64], gxy: &mut [C64], gz: &mut [C64]) {
    let (b, [mx, my], [mfx, mfy]) = (plan.b, plan.m, plan.mf);
    let mut j = 0;
    for sy in 0..b {
        let qy = c[1] + sy * my;
        let ny = neg(qy, mfy);
        for sx in 0..b {
            let qx = c[0] + sx * mx;
            let nx = neg(qx, mfx);
            let (fx, fy, fz) = (v[j], v[j + 1], v[j + 2]);
            let q = qx * mfy + qy;
            let nq = nx * mfy + ny;
            gxy[q] = fx + C64::new(-fy.im, fy.re); // Fx + i·Fy
            gz[q] = fz;
            gxy[nq] = fx.conj() + C64::new(fy.im, fy.re); // conj(Fx) + i·conj(Fy)
            gz[nq] = fz.conj();
            j += 3;
        }
    }
}

/// Reads one block's force spectrum `(Fx, Fy, Fz)` per (s_y, s_x) from the packed spectra.
#[inline]
fn gather_force_block(plan: &Plan, c: [usize; 2], gxy: &[C64], gz: &[C64], out: &mut [C64]) {
    let (b, [mx, my], [mfx, mfy]) = (plan.b, plan.m, plan.mf);
    let mut j = 0;
    for sy in 0..b {
        let qy = c[1] + sy * my;
        let ny = neg(qy, mfy);
        for sx in 0..b {
            let qx = c[0] + sx * mx;
            let nx = neg(qx, mfx);
            let g = gxy[qx * mfy + qy];
            let gn = gxy[nx * mfy + ny].conj();
            out[j] = (g + gn) * 0.5;
            let d = (g - gn) * 0.5;
            out[j + 1] = C64::new(d.im, -d.re); // −i·d
            out[j + 2] = gz[qx * mfy + qy];
            j += 3;
        }
    }
}

/// Inverse transform of the packed force spectra (along y for every qx, then along x for
/// the force-grid rows only) and crop to the force grid, times `scale`.
#[allow(clippy::too_many_arguments)]
fn spectra_to_forces(
    plan: &Plan,
    gxy: &mut [C64],
    gz: &mut [C64],
    hxy: &mut [C64],
    hz: &mut [C64],
    scratch: &mut [C64],
    scale: f64,
    f: &mut [f64],
) {
    let ([nfx, nfy], [mfx, mfy]) = (plan.nf, plan.mf);
    for (g, hbuf) in [(&mut *gxy, &mut *hxy), (&mut *gz, &mut *hz)] {
        plan.inv_fy.process_with_scratch(g, scratch);
        transpose(g, mfy, hbuf, mfx, mfx, nfy);
        plan.inv_fx.process_with_scratch(hbuf, scratch);
    }
    for jy in 0..nfy {
        for jx in 0..nfx {
            let k = jy * nfx + jx;
            let i = jy * mfx + jx;
            f[3 * k] = hxy[i].re * scale;
            f[3 * k + 1] = hxy[i].im * scale;
            f[3 * k + 2] = hz[i].re * scale;
        }
    }
}

/// Scatters a force vector into the force-grid rows and transforms it: afterwards
/// `gxy`, `gz` hold the unnormalised DFTs of `fx + i·fy` and `fz` on the force lattice.
fn forces_to_spectra(plan: &Plan, w: &mut Work, f: &[f64]) {
    let ([nfx, nfy], [mfx, mfy]) = (plan.nf, plan.mf);
    for jy in 0..nfy {
        for jx in 0..nfx {
            let k = jy * nfx + jx;
            w.hxy[jy * mfx + jx] = C64::new(f[3 * k], f[3 * k + 1]);
            w.hz[jy * mfx + jx] = C64::new(f[3 * k + 2], 0.0);
        }
        w.hxy[jy * mfx + nfx..(jy + 1) * mfx].fill(C64::default());
        w.hz[jy * mfx + nfx..(jy + 1) * mfx].fill(C64::default());
    }
    for (hbuf, g) in [(&mut w.hxy, &mut w.gxy), (&mut w.hz, &mut w.gz)] {
        plan.fwd_fx.process_with_scratch(hbuf, &mut w.scratch);
        transpose(hbuf, mfx, g, mfy, nfy, mfx);
        for qx in 0..mfx {
            g[qx * mfy + nfy..(qx + 1) * mfy].fill(C64::default());
        }
        plan.fwd_fy.process_with_scratch(g, &mut w.scratch);
    }
}

/// `Hᵀ r`: the exact adjoint (unitary transforms, block `Aᴴ`).
fn adjoint_op(plan: &Plan, w: &mut Work, amat: &[C64], r: &[f64], out: &mut [f64]) {
    markers_to_forces(plan, w, amat, true, r, 1.0, false, out);
}

/// `M s`: the block-circulant preconditioner `S_f (AᴴA + λ²I)⁻¹ S_fᵀ` (per block
/// `cols × cols`, Hermitian), symmetric positive definite on the force grid.
fn precond_op(plan: &Plan, w: &mut Work, qmat: &[C64], s: &[f64], out: &mut [f64]) {
    forces_to_spectra(plan, w, s);
    let cols = plan.cols;
    for (bi, &c) in plan.blocks.iter().enumerate() {
        gather_force_block(plan, c, &w.gxy, &w.gz, &mut w.vin);
        let mat = &qmat[bi * cols * cols..(bi + 1) * cols * cols];
        for (j, o) in w.vout[..cols].iter_mut().enumerate() {
            let row = &mat[j * cols..(j + 1) * cols];
            *o = row.iter().zip(&w.vin[..cols]).map(|(m, v)| m * v).sum();
        }
        // Writes go to the marker-side scratch (`gtmp`), not to the spectra being read.
        scatter_force_block(plan, c, &w.vout[..cols], &mut w.gtmp_xy, &mut w.gtmp_z);
    }
    let [mfx, mfy] = plan.mf;
    let scale = 1.0 / (mfx * mfy) as f64;
    spectra_to_forces(
        plan,
        &mut w.gtmp_xy,
        &mut w.gtmp_z,
        &mut w.hxy,
        &mut w.hz,
        &mut w.scratch,
        scale,
        out,
    );
}

/// `H f`: the exact forward operator restricted to the measured markers and the force grid
/// (the kernel window holds every offset between them, so the circular convolution is exact).
fn forward_op(plan: &Plan, w: &mut Work, amat: &[C64], f: &[f64], out: &mut [f64]) {
    let ([mx, my], [mmx, mmy]) = (plan.m, plan.mm);
    let (rows, cols, a) = (plan.rows, plan.cols, plan.a);
    forces_to_spectra(plan, w, f);
    for (bi, &c) in plan.blocks.iter().enumerate() {
        gather_force_block(plan, c, &w.gxy, &w.gz, &mut w.vin);
        let mat = &amat[bi * rows * cols..(bi + 1) * rows * cols];
        for r in 0..rows {
            let row = &mat[r * cols..(r + 1) * cols];
            w.vout[r] = row.iter().zip(&w.vin[..cols]).map(|(m, v)| m * v).sum();
        }
        let mut r = 0;
        for sp in w.spec.iter_mut() {
            for sy in 0..a {
                let py = c[1] + sy * my;
                let ny = neg(py, mmy);
                for sx in 0..a {
                    let px = c[0] + sx * mx;
                    let nx = neg(px, mmx);
                    let (ux, uy) = (w.vout[r], w.vout[r + 1]);
                    sp[px * mmy + py] = ux + C64::new(-uy.im, uy.re);
                    sp[nx * mmy + ny] = ux.conj() + C64::new(uy.im, uy.re);
                    r += 2;
                }
            }
        }
    }
    for (slot, lp) in plan.layers.iter().enumerate() {
        let sp = &mut w.spec[slot];
        plan.inv_my.process_with_scratch(sp, &mut w.scratch);
        let z = &mut w.z[slot];
        transpose(sp, mmy, z, mmx, mmx, lp.nm[1]);
        plan.inv_mx.process_with_scratch(z, &mut w.scratch);
    }
    let s = plan.scale;
    for (k, &(slot, idx)) in plan.site_map.iter().enumerate() {
        let v = w.z[slot][idx];
        out[2 * k] = v.re * s;
        out[2 * k + 1] = v.im * s;
    }
}

/// Chooses λ by GCV or the L-curve from per-singular-value data of the periodic operator:
/// `sig` singular values, `beta2` squared projections of the frame on the left singular
/// vectors, `weights` multiplicities (Hermitian partners), `rest` the frame energy outside
/// the range, `m` the number of (periodic) measurements.
fn choose_lambda(
    choice: Lambda,
    sig: &[f64],
    beta2: &[f64],
    weights: &[f64],
    rest: f64,
    m: f64,
    sigma_max: f64,
) -> (f64, String) {
    let terms = |lam: f64| -> (f64, f64, f64) {
        // (residual², solution², trace of the influence matrix)
        let l2 = lam * lam;
        let mut res = rest;
        let mut sol = 0.0;
        let mut tr = 0.0;
        for ((&s, &b2), &w) in sig.iter().zip(beta2).zip(weights) {
            let d = s * s + l2;
            if d <= 0.0 {
                continue;
            }
            let fres = l2 / d;
            res += w * fres * fres * b2;
            sol += w * s * s * b2 / (d * d);
            tr += w * s * s / d;
        }
        (res, sol, tr)
    };
    let lo = (sigma_max * 1e-9).ln();
    let hi = sigma_max.ln();
    let grid: Vec<f64> = (0..LAMBDA_SCAN)
        .map(|i| (lo + (hi - lo) * i as f64 / (LAMBDA_SCAN - 1) as f64).exp())
        .collect();
    match choice {
        Lambda::LCurve => {
            let pts: Vec<(f64, f64)> = grid
                .iter()
                .map(|&l| {
                    let (res, sol, _) = terms(l);
                    (0.5 * res.max(1e-300).ln(), 0.5 * sol.max(1e-300).ln())
                })
                .collect();
            let dt = (hi - lo) / (LAMBDA_SCAN - 1) as f64;
            let mut best = (f64::NEG_INFINITY, grid[LAMBDA_SCAN / 2]);
            for i in 1..LAMBDA_SCAN - 1 {
                let (x0, y0) = pts[i - 1];
                let (x1, y1) = pts[i];
                let (x2, y2) = pts[i + 1];
                let (dx, dy) = ((x2 - x0) / (2.0 * dt), (y2 - y0) / (2.0 * dt));
                let (ddx, ddy) = (
                    (x2 - 2.0 * x1 + x0) / (dt * dt),
                    (y2 - 2.0 * y1 + y0) / (dt * dt),
                );
                let den = (dx * dx + dy * dy).powf(1.5);
                if den > 0.0 {
                    let k = (dx * ddy - dy * ddx) / den;
                    if k.is_finite() && k > best.0 {
                        best = (k, grid[i]);
                    }
                }
            }
            (
                best.1,
                format!(
                    "λ = {:e} mm/N at the L-curve corner (curvature {:.3}) of the periodic problem",
                    best.1, best.0
                ),
            )
        }
        _ => {
            let gcv = |l: f64| {
                let (res, _, tr) = terms(l);
                let den = (m - tr).max(1e-12 * m);
                res / (den * den)
            };
            let vals: Vec<f64> = grid.iter().map(|&l| gcv(l)).collect();
            let mut ib = 0;
            for (i, v) in vals.iter().enumerate() {
                if *v < vals[ib] {
                    ib = i;
                }
            }
            // Golden-section refinement in ln λ between the scan neighbours.
            let (mut x0, mut x1) = (
                grid[ib.saturating_sub(1)].ln(),
                grid[(ib + 1).min(LAMBDA_SCAN - 1)].ln(),
            );
            let g = 0.5 * (5f64.sqrt() - 1.0);
            for _ in 0..40 {
                let c = x1 - g * (x1 - x0);
                let d = x0 + g * (x1 - x0);
                if gcv(c.exp()) < gcv(d.exp()) {
                    x1 = d;
                } else {
                    x0 = c;
                }
            }
            let l = (0.5 * (x0 + x1)).exp();
            let edge = if ib == 0 || ib == LAMBDA_SCAN - 1 {
                " (at the edge of the scanned range: the frame may be nearly noise-free)"
            } else {
                ""
            };
            (
                l,
                format!("λ = {l:e} mm/N by GCV on the given frame, periodic problem{edge}"),
            )
        }
    }
}

impl FrameSolver for FourierSolver {
    fn n_inputs(&self) -> usize {
        self.n_in
    }

    fn n_outputs(&self) -> usize {
        self.n_out
    }

    fn apply(&mut self, u_mm: &[f64], f_n: &mut [f64]) -> Result<(), SolveError> {
        check_input(u_mm, self.n_in)?;
        check_output(f_n, self.n_out)?;
        // The operator is linear: rescale huge inputs so intermediate sums cannot overflow.
        let umax = u_mm.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let in_scale = if umax > 1e100 { 1.0 / umax } else { 1.0 };
        markers_to_forces(
            &self.plan,
            &mut self.work,
            &self.p,
            false,
            u_mm,
            in_scale,
            self.bridge_edges,
            f_n,
        );
        if self.refine_iterations > 0 {
            self.refine(u_mm, in_scale, f_n);
        }
        if in_scale != 1.0 {
            for v in f_n.iter_mut() {
                *v /= in_scale;
            }
        }
        Ok(())
    }

    fn diagnostics(&self) -> &Diagnostics {
        &self.diag
    }

    fn force_sd(&self, _sigma_mm: f64, _out: &mut [f64]) -> Result<(), SolveError> {
        Err(SolveError::InvalidOption(
            "per-node uncertainty is not available for the fourier solver yet: use pinv, tikhonov or tsvd".into(),
        ))
    }

    fn sum_sd(&self, _sigma_mm: f64) -> Result<[f64; 3], SolveError> {
        Err(SolveError::InvalidOption(
            "force-sum uncertainty is not available for the fourier solver yet: use pinv, tikhonov or tsvd".into(),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn commensurate_pitches_give_the_smallest_factors() {
        assert_eq!(commensurate(1.1, 1.1).unwrap(), (1, 1));
        assert_eq!(commensurate(2.2, 1.1).unwrap(), (2, 1));
        assert_eq!(commensurate(1.0, 1.5).unwrap(), (2, 3));
        assert_eq!(commensurate(0.5, 2.0).unwrap(), (1, 4));
    }

    #[test]
    fn paper_pitches_are_refused_with_suggestions() {
        let e = commensurate(2.2, 1.5).unwrap_err().to_string();
        assert!(e.contains("2.2 mm") && e.contains("1.5 mm"), "{e}");
        assert!(e.contains("1.1000 mm") && e.contains("2.2000 mm"), "{e}");
        assert!(e.contains("dense solver"), "{e}");
    }

    #[test]
    fn smooth_sizes_are_smooth_and_minimal() {
        assert_eq!(smooth_at_least(97), 98);
        assert_eq!(smooth_at_least(190), 192);
        assert_eq!(smooth_at_least(11), 12);
        assert_eq!(smooth_at_least(1), 1);
    }

    /// A 2.2 / 1.1 mm sensor whose red layer is offset by an arbitrary sub-pitch amount.
    fn offset_problem() -> (crate::sensor::Sensor, Vec<crate::model::MarkerSite>) {
        let mut s = crate::sensor::grid_sensor(7, 5, 2.2, 1.1);
        s.layers[1].markers.as_mut().unwrap().grid.origin_mm = [0.37, -0.21];
        let sites = crate::model::MarkerSite::from_sensor_grids(&s);
        (s, sites)
    }

    fn pseudo_random(n: usize, seed: u64) -> Vec<f64> {
        let mut x = seed;
        (0..n)
            .map(|_| {
                x = x
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (x >> 11) as f64 / (1u64 << 53) as f64 - 0.5
            })
            .collect()
    }

    #[test]
    fn fft_forward_operator_equals_direct_summation_of_eq_1_2() {
        let (s, sites) = offset_problem();
        let p = Problem::new(&s, &sites);
        let cfg = SolverConfig {
            lambda: Lambda::Fixed(0.1),
            ..SolverConfig::default()
        };
        let mut solver = FourierSolver::precompute(&p, &cfg, None).unwrap();
        let f = pseudo_random(p.n_outputs(), 7);
        let want = crate::model::forward(&p.model, &sites, &s.force_points_mm(), &f).unwrap();
        let mut got = vec![0.0; p.n_inputs()];
        forward_op(&solver.plan, &mut solver.work, &solver.a, &f, &mut got);
        let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() <= 1e-12 * scale, "{g} vs {w}");
        }
    }

    #[test]
    fn fft_adjoint_is_the_transpose() {
        // <H f, u> = <f, Hᵀ u> for random f, u.
        let (s, sites) = offset_problem();
        let p = Problem::new(&s, &sites);
        let cfg = SolverConfig {
            lambda: Lambda::Fixed(0.1),
            ..SolverConfig::default()
        };
        let mut solver = FourierSolver::precompute(&p, &cfg, None).unwrap();
        let f = pseudo_random(p.n_outputs(), 3);
        let u = pseudo_random(p.n_inputs(), 5);
        let mut hf = vec![0.0; p.n_inputs()];
        let mut htu = vec![0.0; p.n_outputs()];
        forward_op(&solver.plan, &mut solver.work, &solver.a, &f, &mut hf);
        adjoint_op(&solver.plan, &mut solver.work, &solver.a, &u, &mut htu);
        let lhs: f64 = hf.iter().zip(&u).map(|(a, b)| a * b).sum();
        let rhs: f64 = f.iter().zip(&htu).map(|(a, b)| a * b).sum();
        assert!(
            (lhs - rhs).abs() <= 1e-12 * lhs.abs().max(rhs.abs()),
            "{lhs} vs {rhs}"
        );
    }

    #[test]
    fn transpose_moves_every_element() {
        let src: Vec<C64> = (0..35).map(|i| C64::new(i as f64, 0.0)).collect();
        let mut dst = vec![C64::default(); 35];
        transpose(&src, 7, &mut dst, 5, 5, 7);
        for r in 0..5 {
            for c in 0..7 {
                assert_eq!(dst[c * 5 + r], src[r * 7 + c]);
            }
        }
    }
}
