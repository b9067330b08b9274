//! The steps of [`super::FourierSolver::precompute`], in the order it runs them:
//! option checks, the layer slots and the commensurate fine grid, the sites on their
//! lattices, the kernel spectra, the per-block SVDs, the plan and work buffers, λ, the
//! solution operators `P = V diag(φ) Uᴴ` and the refinement preconditioner
//! `Q = (AᴴA + λ²I)⁻¹`, the diagnostics, and the noise figures with the two-level
//! correction. The equations are in the module docs of [`super`].

use nalgebra::DMatrix;
use rustfft::FftPlanner;

use super::grid::{commensurate, smooth_at_least, RATIO_TOLERANCE};
use super::lambda::choose_lambda;
use super::transform::{
    bridge_weights, gather_marker_block, markers_to_spectra, LayerPlan, Plan, Work, C64,
};
use super::{coarse, kernel, uncertainty, MAX_PADDING, MAX_REFINE_ITERATIONS, OFF_GRID_TOLERANCE};
use crate::model::{ForwardModel, MarkerSite};
use crate::sensor::{Grid, Sensor};
use crate::solve::{
    check_input, Diagnostics, Lambda, Method, Problem, SolveError, SolverConfig, WARNING_PREFIX,
};

/// Checks the solver options and the problem's sizes; returns `(n_in, n_out)`.
pub(super) fn check_options(
    problem: &Problem<'_>,
    config: &SolverConfig,
    frame: Option<&[f64]>,
) -> Result<(usize, usize), SolveError> {
    if problem.sites.is_empty() {
        return Err(SolveError::Empty("no markers carry data".into()));
    }
    let n_in = 2 * problem.sites.len();
    let n_out = 3 * problem.sensor.force_grid.len();
    if n_out == 0 {
        return Err(SolveError::Empty("the force grid has no nodes".into()));
    }
    if let Some(u) = frame {
        check_input(u, n_in)?;
    }
    if config.fourier_refine_iterations > MAX_REFINE_ITERATIONS {
        return Err(SolveError::InvalidOption(format!(
            "fourier refinement of {} iterations exceeds the maximum of {MAX_REFINE_ITERATIONS}",
            config.fourier_refine_iterations
        )));
    }
    let tol = config.fourier_refine_tolerance;
    if !(tol.is_finite() && (0.0..1.0).contains(&tol)) {
        return Err(SolveError::InvalidOption(format!(
            "fourier refinement tolerance {tol} must be a number in [0, 1)"
        )));
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
    Ok((n_in, n_out))
}

/// The marker layers that carry data, each a slot in layer order (so the block layout
/// does not depend on the order of the sites), and their common marker pitch.
pub(super) struct Slots {
    /// Slot of each sensor layer (`usize::MAX`: no data).
    pub(super) slot_of_layer: Vec<usize>,
    /// Sensor layer of each slot.
    pub(super) layer_of_slot: Vec<usize>,
    /// The marker pitch all layers share, mm.
    pub(super) marker_pitch_mm: f64,
}

/// Assigns the sites' layers to slots; refuses layers without a regular grid, sites off
/// their layer's depth, and layers of different pitches.
pub(super) fn layer_slots(sensor: &Sensor, sites: &[MarkerSite]) -> Result<Slots, SolveError> {
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
    Ok(Slots {
        slot_of_layer,
        layer_of_slot,
        marker_pitch_mm,
    })
}

/// The fine grid: pitch `h` with `p_f = a·h`, `p_m = b·h`, and the periodic lattice.
pub(super) struct FineGrid {
    pub(super) a: usize,
    pub(super) b: usize,
    /// The fine pitch `h`, mm.
    pub(super) h: f64,
    /// Markers per axis of each slot's layer.
    pub(super) layers: Vec<LayerPlan>,
    /// Force grid size per axis.
    pub(super) nf: [usize; 2],
    /// Fine period `N` per axis.
    pub(super) period: [usize; 2],
    /// Frequency blocks per axis (`N / (a·b)`).
    pub(super) m: [usize; 2],
    /// Marker lattice period per axis (`a·m`).
    pub(super) mm: [usize; 2],
    /// Force lattice period per axis (`b·m`).
    pub(super) mf: [usize; 2],
}

/// The fine period per axis: every (marker, force) offset plus `pad` times the larger
/// grid extent, a multiple of `L = a·b` with a 2-3-5-7-smooth block count.
pub(super) fn fine_grid(sensor: &Sensor, slots: &Slots, pad: f64) -> Result<FineGrid, SolveError> {
    let fg = sensor.force_grid;
    let (a, b) = commensurate(fg.pitch_mm, slots.marker_pitch_mm)?;
    let l = a * b;
    let layers: Vec<LayerPlan> = slots
        .layer_of_slot
        .iter()
        .map(|&li| {
            let g = sensor.layers[li].markers.map(|m| m.grid).unwrap_or(fg);
            LayerPlan { nm: [g.nx, g.ny] }
        })
        .collect();
    let nf = [fg.nx, fg.ny];
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
    Ok(FineGrid {
        a,
        b,
        h: fg.pitch_mm / a as f64,
        layers,
        nf,
        period,
        m,
        mm: [a * m[0], a * m[1]],
        mf: [b * m[0], b * m[1]],
    })
}

/// Each site's (slot, row-major index on its marker lattice); refuses sites off their
/// layer's grid, two sites on one node, and incomplete layer grids.
pub(super) fn site_map(
    sensor: &Sensor,
    sites: &[MarkerSite],
    slots: &Slots,
    fine: &FineGrid,
) -> Result<Vec<(usize, usize)>, SolveError> {
    let fg = sensor.force_grid;
    let mut map = Vec::with_capacity(sites.len());
    let mut seen: Vec<Vec<bool>> = fine
        .layers
        .iter()
        .map(|lp| vec![false; lp.nm[0] * lp.nm[1]])
        .collect();
    for (k, s) in sites.iter().enumerate() {
        let layer = &sensor.layers[s.layer];
        let slot = slots.slot_of_layer[s.layer];
        let grid = layer.markers.map(|m| m.grid).unwrap_or(fg);
        let (ix, iy) = node_of_site(k, s, &layer.name, &grid)?;
        let node = iy * grid.nx + ix;
        if seen[slot][node] {
            return Err(SolveError::Incompatible(format!(
                "marker {k} of layer {} is a second marker on grid node ({ix}, {iy})",
                layer.name
            )));
        }
        seen[slot][node] = true;
        map.push((slot, iy * fine.mm[0] + ix));
    }
    for (slot, s) in seen.iter().enumerate() {
        let missing = s.iter().filter(|&&x| !x).count();
        if let Some(first) = s.iter().position(|&x| !x) {
            let lp = fine.layers[slot];
            return Err(SolveError::Incompatible(format!(
                "layer {}: {missing} of {} grid markers carry no data (first missing node \
                 ({}, {})); the fourier solver needs complete marker grids, lost markers \
                 are handled by the dense solvers (pinv, tikhonov, tsvd)",
                sensor.layers[slots.layer_of_slot[slot]].name,
                lp.nm[0] * lp.nm[1],
                first % lp.nm[0],
                first / lp.nm[0]
            )));
        }
    }
    Ok(map)
}

/// The grid node of site `k`, within [`OFF_GRID_TOLERANCE`] pitch of its position.
fn node_of_site(
    k: usize,
    s: &MarkerSite,
    layer_name: &str,
    grid: &Grid,
) -> Result<(usize, usize), SolveError> {
    let tol = OFF_GRID_TOLERANCE * grid.pitch_mm;
    let Some(((ix, iy), d)) = grid.nearest_node(s.position_mm) else {
        return Err(SolveError::Incompatible(format!(
            "marker {k} of layer {layer_name} at ({:.4}, {:.4}) mm lies outside the layer's \
             {}×{} grid (origin ({}, {}) mm, pitch {} mm); use a dense solver",
            s.position_mm[0],
            s.position_mm[1],
            grid.nx,
            grid.ny,
            grid.origin_mm[0],
            grid.origin_mm[1],
            grid.pitch_mm
        )));
    };
    if d > tol {
        return Err(SolveError::Incompatible(format!(
            "marker {k} of layer {layer_name} at ({:.4}, {:.4}) mm is {d:.4} mm from its nearest \
             grid node ({ix}, {iy}) (tolerance {tol:.4} mm = {OFF_GRID_TOLERANCE} pitch): \
             the fourier solver needs markers on the layer's regular grid (a rotated or \
             distorted grid is not); use a dense solver (pinv, tikhonov, tsvd)",
            s.position_mm[0], s.position_mm[1]
        )));
    }
    Ok((ix, iy))
}

/// Per slot, the 6 kernel spectra (`[3·i + j]`: displacement `i`, force `j`) on the
/// fine period.
pub(super) type SlotSpectra = Vec<Vec<Vec<C64>>>;

/// The kernel spectra (`kernel.rs`): `exact`, the model's real-space responses on the
/// kernel window (the exact operator of the refinement), and `periodic`, what the
/// direct solve inverts: the bonded layer's Fourier kernel used directly (empty for the
/// half-space, which has no finite k = 0 term and uses the window-sampled kernel for both).
pub(super) fn kernel_spectra(
    model: &ForwardModel,
    sensor: &Sensor,
    slots: &Slots,
    fine: &FineGrid,
    planner: &mut FftPlanner<f64>,
) -> Result<(SlotSpectra, SlotSpectra), SolveError> {
    let fg = sensor.force_grid;
    let (a, b) = (fine.a, fine.b);
    let mut exact = Vec::with_capacity(fine.layers.len());
    let mut periodic = Vec::new();
    for (slot, lp) in fine.layers.iter().enumerate() {
        let layer = &sensor.layers[slots.layer_of_slot[slot]];
        let grid = layer.markers.map(|m| m.grid).unwrap_or(fg);
        let lo: [i64; 2] = std::array::from_fn(|ax| {
            let span = a * (fine.nf[ax] - 1) + b * (lp.nm[ax] - 1) + 1;
            -((a * (fine.nf[ax] - 1)) as i64) - ((fine.period[ax] - span) / 2) as i64
        });
        let sampling = kernel::LayerSampling {
            offset_mm: [
                grid.origin_mm[0] - fg.origin_mm[0],
                grid.origin_mm[1] - fg.origin_mm[1],
            ],
            depth_mm: layer.depth_mm,
            lo,
        };
        exact.push(kernel::sampled_spectra(
            model,
            &sampling,
            fine.period,
            fine.h,
            planner,
        )?);
        if let ForwardModel::BondedLayer(bl) = model {
            periodic.push(kernel::layer_spectra(bl, &sampling, fine.period, fine.h));
        }
    }
    Ok((exact, periodic))
}

/// The processed frequency blocks (`c_x ≤ M_x/2`; the others follow by Hermitian
/// symmetry).
pub(super) fn frequency_blocks(m: [usize; 2]) -> Vec<[usize; 2]> {
    let mut blocks = Vec::new();
    for cx in 0..=m[0] / 2 {
        for cy in 0..m[1] {
            blocks.push([cx, cy]);
        }
    }
    blocks
}

/// How many real blocks a processed block stands for (itself and its mirror image).
pub(super) fn block_weight(c: [usize; 2], m: [usize; 2]) -> f64 {
    if c[0] == 0 || 2 * c[0] == m[0] {
        1.0
    } else {
        2.0
    }
}

/// Every processed block's forward operator and its SVD, stored flat per block.
pub(super) struct BlockSvds {
    pub(super) rows: usize,
    pub(super) cols: usize,
    /// `min(rows, cols)`: singular values per block.
    pub(super) kmin: usize,
    /// Per block, `rows × cols` forward operator of the exact spectra (unitary scaling).
    pub(super) amat: Vec<C64>,
    /// Per block, the `kmin` singular values of the inverted (periodic) operator.
    pub(super) sig: Vec<f64>,
    /// Per block and singular value, the left (`rows`) and right (`cols`) vectors.
    pub(super) uvec: Vec<C64>,
    pub(super) vvec: Vec<C64>,
    /// Largest singular value over all blocks.
    pub(super) sigma_max: f64,
}

impl BlockSvds {
    /// Left singular vector `i` of block `bi`.
    pub(super) fn u(&self, bi: usize, i: usize) -> &[C64] {
        let k = bi * self.kmin + i;
        &self.uvec[k * self.rows..(k + 1) * self.rows]
    }

    /// Right singular vector `i` of block `bi`.
    pub(super) fn v(&self, bi: usize, i: usize) -> &[C64] {
        let k = bi * self.kmin + i;
        &self.vvec[k * self.cols..(k + 1) * self.cols]
    }
}

/// Adds block `c` (row-major `rows × cols`, unitary scaling) of one set of spectra to
/// `ab`: the entries `K̂_ℓ/(a·b)` of the module docs' block equation.
fn assemble_block(fine: &FineGrid, khat: &SlotSpectra, c: [usize; 2], cols: usize, ab: &mut [C64]) {
    let (a, b, m, period) = (fine.a, fine.b, fine.m, fine.period);
    let l = a * b;
    let inv_ab = 1.0 / (a * b) as f64;
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
}

/// Assembles every block from the exact spectra and takes the SVD of the operator the
/// direct solve inverts (the periodic spectra where the model has them).
pub(super) fn block_svds(
    fine: &FineGrid,
    blocks: &[[usize; 2]],
    exact: &SlotSpectra,
    periodic: &SlotSpectra,
) -> Result<BlockSvds, SolveError> {
    let rows = 2 * fine.layers.len() * fine.a * fine.a;
    let cols = 3 * fine.b * fine.b;
    let kmin = rows.min(cols);
    let nb = blocks.len();
    let mut out = BlockSvds {
        rows,
        cols,
        kmin,
        amat: vec![C64::default(); nb * rows * cols],
        sig: vec![0.0f64; nb * kmin],
        uvec: vec![C64::default(); nb * rows * kmin],
        vvec: vec![C64::default(); nb * cols * kmin],
        sigma_max: 0.0,
    };
    let mut periodic_block = vec![C64::default(); rows * cols];
    for (bi, &c) in blocks.iter().enumerate() {
        let ab = &mut out.amat[bi * rows * cols..(bi + 1) * rows * cols];
        assemble_block(fine, exact, c, cols, ab);
        let dm = if periodic.is_empty() {
            DMatrix::from_row_slice(rows, cols, ab)
        } else {
            periodic_block.fill(C64::default());
            assemble_block(fine, periodic, c, cols, &mut periodic_block);
            DMatrix::from_row_slice(rows, cols, &periodic_block)
        };
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
            out.sig[bi * kmin + i] = s;
            for r in 0..rows {
                out.uvec[(bi * kmin + i) * rows + r] = u[(r, i)];
            }
            for j in 0..cols {
                out.vvec[(bi * kmin + i) * cols + j] = vt[(i, j)].conj();
            }
        }
    }
    out.sigma_max = out.sig.iter().cloned().fold(0.0f64, f64::max);
    if out.sigma_max <= 0.0 {
        return Err(SolveError::Decomposition(
            "the periodic operator is zero".into(),
        ));
    }
    Ok(out)
}

/// The plan: sizes, index maps, edge-bridge weights and FFT plans.
pub(super) fn make_plan(
    fine: FineGrid,
    svds: &BlockSvds,
    blocks: Vec<[usize; 2]>,
    site_map: Vec<(usize, usize)>,
    planner: &mut FftPlanner<f64>,
) -> Plan {
    let (mm, mf) = (fine.mm, fine.mf);
    Plan {
        a: fine.a,
        b: fine.b,
        m: fine.m,
        mm,
        mf,
        nf: fine.nf,
        rows: svds.rows,
        cols: svds.cols,
        blocks,
        site_map,
        bridge_x: fine
            .layers
            .iter()
            .map(|lp| bridge_weights(mm[0] - lp.nm[0]))
            .collect(),
        bridge_y: fine
            .layers
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
        layers: fine.layers,
    }
}

/// The per-frame buffers of `plan`, allocated once.
pub(super) fn make_work(plan: &Plan, n_in: usize, n_out: usize) -> Work {
    let (mm, mf, nf) = (plan.mm, plan.mf, plan.nf);
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
    let rc = plan.rows.max(plan.cols);
    Work {
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
        vin: vec![C64::default(); rc],
        vout: vec![C64::default(); rc],
        r: vec![0.0; n_in],
        q: vec![0.0; n_in],
        s: vec![0.0; n_out],
        p: vec![0.0; n_out],
        zf: vec![0.0; n_out],
    }
}

/// The block filter: Tikhonov's `σ/(σ²+λ²)` for λ > 0, else `1/σ` above the cut-off
/// `rcond·σ_max` and 0 below it.
#[derive(Debug, Clone, Copy)]
pub(super) struct Filter {
    pub(super) lambda: f64,
    pub(super) cutoff: f64,
}

impl Filter {
    /// `φ(σ)`.
    pub(super) fn phi(&self, s: f64) -> f64 {
        if self.lambda > 0.0 {
            s / (s * s + self.lambda * self.lambda)
        } else if s > self.cutoff {
            1.0 / s
        } else {
            0.0
        }
    }

    /// The filter factor `σφ(σ)` (its sum is the effective rank).
    pub(super) fn factor(&self, s: f64) -> f64 {
        if self.lambda > 0.0 {
            s * s / (s * s + self.lambda * self.lambda)
        } else if s > self.cutoff {
            1.0
        } else {
            0.0
        }
    }
}

/// Rows of the whole periodic operator (each processed block counted with its mirror).
pub(super) fn total_rows(plan: &Plan) -> f64 {
    plan.blocks
        .iter()
        .map(|&c| block_weight(c, plan.m) * plan.rows as f64)
        .sum()
}

/// The cut-off below which λ = 0 drops a singular value: `rcond·σ_max`, with `rcond`
/// the configured one or the size of the periodic operator times ε.
pub(super) fn cutoff(plan: &Plan, svds: &BlockSvds, config: &SolverConfig) -> f64 {
    let n_cols: f64 = plan
        .blocks
        .iter()
        .map(|&c| block_weight(c, plan.m) * plan.cols as f64)
        .sum();
    let rcond = config
        .rcond
        .unwrap_or(total_rows(plan).max(n_cols) * f64::EPSILON);
    rcond * svds.sigma_max
}

/// λ: the fixed one, or GCV / L-curve on `frame` in the Fourier domain (the frame's
/// unitary spectrum projected on each block's left singular vectors). Pushes its note.
pub(super) fn select_lambda(
    config: &SolverConfig,
    frame: Option<&[f64]>,
    plan: &Plan,
    work: &mut Work,
    svds: &BlockSvds,
    notes: &mut Vec<String>,
) -> Result<f64, SolveError> {
    let u = match (config.lambda, frame) {
        (Lambda::Fixed(l), _) => {
            notes.push(format!("fixed λ = {l:e} mm/N"));
            return Ok(l);
        }
        (_, Some(u)) => u,
        (_, None) => return Err(SolveError::NeedsFrame("λ")),
    };
    let (rows, kmin) = (svds.rows, svds.kmin);
    // The frame is brought to unit peak first, as for the dense solvers.
    let in_scale = crate::solve::unit_peak_factor(u);
    markers_to_spectra(plan, work, u, in_scale, false);
    let unit = 1.0 / ((plan.mm[0] * plan.mm[1]) as f64).sqrt();
    let mut beta2 = vec![0.0f64; plan.blocks.len() * kmin];
    let mut rest = 0.0f64;
    let mut total = 0.0f64;
    for (bi, &c) in plan.blocks.iter().enumerate() {
        gather_marker_block(plan, &work.spec, c, &mut work.vin);
        let w = block_weight(c, plan.m);
        let norm2: f64 = work.vin[..rows].iter().map(|v| (v * unit).norm_sqr()).sum();
        let mut proj = 0.0;
        for i in 0..kmin {
            let beta: C64 = svds
                .u(bi, i)
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
        .flat_map(|&c| std::iter::repeat_n(block_weight(c, plan.m), kmin))
        .collect();
    let (l, note) = choose_lambda(
        config.lambda,
        &svds.sig,
        &beta2,
        &weights,
        rest,
        total_rows(plan),
        svds.sigma_max,
    );
    notes.push(note);
    Ok(l)
}

/// Per block, the `cols × rows` solution operator `P = V diag(φ) Uᴴ`.
pub(super) fn solution_operators(svds: &BlockSvds, nb: usize, filter: Filter) -> Vec<C64> {
    let (rows, cols) = (svds.rows, svds.cols);
    let mut pmat = vec![C64::default(); nb * cols * rows];
    for bi in 0..nb {
        let pb = &mut pmat[bi * cols * rows..(bi + 1) * cols * rows];
        for i in 0..svds.kmin {
            let phi = filter.phi(svds.sig[bi * svds.kmin + i]);
            if phi == 0.0 {
                continue;
            }
            let ui = svds.u(bi, i);
            for (j, vj) in svds.v(bi, i).iter().enumerate() {
                let vphi = vj * phi;
                for (r, ur) in ui.iter().enumerate() {
                    pb[j * rows + r] += vphi * ur.conj();
                }
            }
        }
    }
    pmat
}

/// Per block, the refinement preconditioner
/// `Q = (AᴴA + λ²I)⁻¹ = I/λ² + V diag(1/(σ²+λ²) − 1/λ²) Vᴴ` (zeros for λ = 0).
pub(super) fn preconditioner(svds: &BlockSvds, nb: usize, lambda: f64) -> Vec<C64> {
    let (cols, kmin) = (svds.cols, svds.kmin);
    let mut qmat = vec![C64::default(); nb * cols * cols];
    if lambda <= 0.0 {
        return qmat;
    }
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
            let s2 = svds.sig[bi * kmin + i].powi(2);
            let psi = if full {
                1.0 / (s2 + l2)
            } else {
                1.0 / (s2 + l2) - 1.0 / l2
            };
            let vi = svds.v(bi, i);
            for (j, vj) in vi.iter().enumerate() {
                for (k, vk) in vi.iter().enumerate() {
                    qb[j * cols + k] += vj * vk.conj() * psi;
                }
            }
        }
    }
    qmat
}

/// The diagnostics of the periodic operator: every singular value (mirrored blocks
/// twice), condition number, effective rank and noise gain under `filter`; the geometry
/// note first, then `notes`.
pub(super) fn diagnostics(
    plan: &Plan,
    svds: &BlockSvds,
    filter: Filter,
    h: f64,
    period: [usize; 2],
    (n_in, n_out): (usize, usize),
    mut notes: Vec<String>,
) -> Diagnostics {
    let kmin = svds.kmin;
    let mut all_sv = Vec::with_capacity(2 * svds.sig.len());
    let mut eff = 0.0;
    let mut gain = 0.0f64;
    for (bi, &c) in plan.blocks.iter().enumerate() {
        let w = block_weight(c, plan.m);
        for &s in &svds.sig[bi * kmin..(bi + 1) * kmin] {
            all_sv.push(s);
            if w > 1.0 {
                all_sv.push(s);
            }
            eff += w * filter.factor(s);
            gain = gain.max(filter.phi(s));
        }
    }
    all_sv.sort_by(|x, y| y.total_cmp(x));
    let smin = all_sv.last().copied().unwrap_or(0.0);
    let condition_number = if smin > filter.cutoff {
        svds.sigma_max / smin
    } else {
        f64::INFINITY
    };
    let (a, b, m, rows, cols) = (plan.a, plan.b, plan.m, plan.rows, plan.cols);
    notes.insert(
        0,
        format!(
            "fine pitch {h} mm (force pitch = {a}·h, marker pitch = {b}·h), period {}×{} fine \
             nodes, {}×{} frequency blocks of {rows}×{cols}; singular values are those of the \
             periodic operator (padding markers count as measured zeros)",
            period[0], period[1], m[0], m[1]
        ),
    );
    Diagnostics {
        method: Method::Fourier,
        shape: (n_in, n_out),
        singular_values: all_sv,
        condition_number,
        effective_rank: eff,
        noise_gain: gain,
        lambda: Some(filter.lambda),
        rank: None,
        notes,
    }
}

/// The noise figures of the solver's maps and its two-level correction.
pub(super) struct NoiseAndCoarse {
    pub(super) coarse: Option<coarse::Coarse>,
    pub(super) noise_direct: uncertainty::NoiseFigures,
    pub(super) noise_refined_sum: Option<[f64; 3]>,
    pub(super) noise_bridged_sum: [f64; 3],
}

/// A note for when the two-level correction is off: the direct solve alone carries the
/// periodic model's boundary error.
fn warn_direct(why: String) -> String {
    format!(
        "{WARNING_PREFIX}fourier: {why}: the direct periodic solve alone carries the periodic \
         model's boundary error (force sums off by tens of % on bounded grids); add \
         --refine-iterations, give another λ or use a dense solver"
    )
}

/// Noise propagation (per unit σ) and the two-level correction (`coarse.rs`): the
/// coarse space and its Galerkin solve first, which also precondition the force-sum
/// solves, then the exact sums of dense Tikhonov. Notes go to `diag`.
#[allow(clippy::too_many_arguments)]
pub(super) fn noise_and_coarse(
    plan: &Plan,
    work: &mut Work,
    ops: (&[C64], &[C64], &[C64]),
    lambda: f64,
    coarse_requested: bool,
    (n_in, n_out): (usize, usize),
    planner: &mut FftPlanner<f64>,
    diag: &mut Diagnostics,
) -> NoiseAndCoarse {
    let (pmat, amat, qmat) = ops;
    let noise_direct = uncertainty::direct_map(plan, work, pmat, planner);
    // The transposed direct solve gives the direct map's exact force sums, used by
    // the two-level build and by `sum_sd` of the bridged direct solve.
    let ph = coarse::blocks_adjoint(plan, pmat);
    let direct_sums = coarse::direct_sum_functionals(plan, work, &ph, n_in, n_out);
    let galerkin = if !coarse_requested {
        diag.notes
            .push("two-level correction not requested: the direct periodic solve alone".into());
        None
    } else if lambda <= 0.0 {
        diag.notes
            .push(warn_direct("λ = 0 has no two-level correction".into()));
        None
    } else {
        match coarse::Coarse::galerkin(
            plan,
            work,
            amat,
            &ph,
            lambda,
            n_in,
            n_out,
            coarse::COARSE_BUDGET,
        ) {
            Ok(g) => Some(g),
            Err(e) => {
                diag.notes
                    .push(warn_direct(format!("two-level correction off ({e})")));
                None
            }
        }
    };
    let converged = uncertainty::converged_sums(
        plan,
        work,
        amat,
        qmat,
        galerkin.as_ref().map(|g| g.space()),
        lambda,
        n_in,
        n_out,
    );
    let coarse = match (galerkin, &converged) {
        (Some(g), Some((_, funcs, residual))) => {
            finish_coarse(g, funcs, *residual, &direct_sums, n_out, diag)
        }
        _ => None,
    };
    NoiseAndCoarse {
        coarse,
        noise_direct,
        noise_refined_sum: converged.map(|(s, _, _)| s),
        // Force sums of the bridged direct map, exactly: ΣF_a = (P_perᵀ 1_a)ᵀ u.
        noise_bridged_sum: direct_sums.map(|t| t.iter().map(|v| v * v).sum::<f64>().sqrt()),
    }
}

/// Completes the two-level correction with dense Tikhonov's force sums when their
/// solves converged (else it keeps its Galerkin sums, with a warning).
fn finish_coarse(
    g: coarse::Galerkin,
    funcs: &[Vec<f64>; 3],
    residual: f64,
    direct_sums: &[Vec<f64>; 3],
    n_out: usize,
    diag: &mut Diagnostics,
) -> Option<coarse::Coarse> {
    let exact = residual <= uncertainty::SUM_ACCEPT;
    if !exact {
        diag.notes.push(format!(
            "{WARNING_PREFIX}fourier: the force-sum solves stopped at a relative residual of \
             {residual:.1e} (iteration cap): the two-level solve keeps its \
             Galerkin sums instead of dense Tikhonov's, and the force-sum SDs \
             are approximate; a larger λ converges faster"
        ));
    }
    let sums = exact.then_some(funcs);
    match coarse::Coarse::finish(g, sums, direct_sums, n_out) {
        Ok(c) => {
            let (s, nc) = c.shape();
            diag.notes.push(format!(
                "two-level solve: direct periodic solve + Galerkin correction on {} \
                 coarse functions (hats every {s} force nodes, {}×{} coarse nodes)",
                c.len(),
                nc[0],
                nc[1]
            ));
            Some(c)
        }
        Err(e) => {
            diag.notes
                .push(warn_direct(format!("two-level correction off ({e})")));
            None
        }
    }
}
