//! Noise propagation of the `fourier` solver: the standard deviation of every force
//! component and of the force sum when every displacement input carries independent
//! noise of standard deviation σ (issue 12, Deliver 6). Everything is computed once at
//! precompute, per unit σ, and scaled per call.
//!
//! # Direct solve: per-frequency propagation (exact)
//!
//! The direct solve without the edge bridge is `f = crop ∘ P_per ∘ zero-pad (u)`, with
//! `P_per` the periodic block solve. `P_per` commutes with lattice shifts: an impulse on
//! marker `(s_x + a·t_x, s_y + a·t_y)` of a layer (`s` the phase, `0 ≤ s < a`) gives the
//! force response of the impulse on marker `s` shifted by `(b·t_x, b·t_y)` force nodes.
//! So `2·layers·a²` impulse responses `R` (each one pass through the blocks and one
//! inverse 2-D FFT of the whole force lattice) give every column of the map, and
//!
//! ```text
//! Var f_{j,c} = σ² Σ_{real markers i} R_{ch(i)}[j − b·t(i)]_c²,
//! ΣF_c = Σ_i w_c[i] u_i,  w_c[i] = Σ_{j ∈ force grid} R_{ch(i)}[j − b·t(i)]_c,  SD = σ‖w_c‖.
//! ```
//!
//! This is exact for the zero-padded direct map (checked against Monte Carlo in
//! `tests/fourier.rs`). With the edge bridge the padding copies edge markers, which adds
//! correlated terms the formula leaves out.
//!
//! # Refined solve: the converged map
//!
//! The refinement stops at a tolerance ([`super::FourierSolver::refine_tolerance`]): its
//! output is dense Tikhonov `P = (HᵀH + λ²I)⁻¹Hᵀ` on the real geometry to within that
//! tolerance (2 % by default), and the figures are those of `P` (CGLS with data-dependent
//! steps is not itself a fixed linear map, but it is this map to within the tolerance).
//!
//! - Force sums, exact: `w_c = H y_c` with `(HᵀH + λ²I) y_c = 1_c` (the indicator of
//!   component `c` on the force grid), three preconditioned CG solves at precompute.
//! - Per node, by probing ([`probe_force_var`]) with a control variate: the inputs are
//!   split into `2·layers·d²` classes (layer, axis, grid phase mod `d = PROBE_SPACING`);
//!   each class with random signs is one probe `z_C`, solved once (`P z_C`, one PCG
//!   solve). `Σ_C (P z_C)_j²` is `Σ_i P_ji²` plus cross terms between inputs ≥ `d`
//!   pitches apart. The same probes through the zero-padded direct map `D`, whose exact
//!   figures are known (above), have nearly the same cross terms (same Tikhonov filter),
//!   so `Var_j ≈ Σ_C (P z_C)_j² − Σ_C (D z_C)_j² + Σ_i D_ji²`. Measured against the
//!   exact rows of NumPy's dense `P` at λ = 1e-2·σ₁ (`d = 10`, the default): worst node
//!   4.9 % on `grid_sensor(16,16,1.1,1.1)`, 6.0 % on 20×20, 6.5 % on 32×32 (`d = 8`:
//!   6.5 %, 8.4 %, 10.1 %; `d = 4` on 16×16: 22 %; without the control variate, `d = 6`:
//!   14 %). Computed on first use of `force_sd` and cached (`2·layers·100` PCG solves:
//!   400 for two layers).
//! - The bridged direct map is probed the same way (direct applies), and so is the
//!   two-level map (the default; `coarse.rs`): its coarse part is smooth, and its
//!   cross terms average out like the others (32×32, hats every 3 nodes: 4.3 % overall
//!   against 300 Monte Carlo frames).
//! - Force sums of the two-level map: exactly those of the converged map (it has dense
//!   Tikhonov's sums). Of the bridged direct map: exact, `‖P_perᵀ 1_c‖` through the
//!   transposed direct solve (`coarse.rs`).
//!
//! Checked against 300 Monte Carlo frames and the exact dense rows in `tests/fourier.rs`.

use super::coarse::CoarseSpace;
use super::refine::{adjoint_op, forward_op, precond_op};
use super::transform::{
    gather_marker_block, markers_to_spectra, scatter_force_block, transpose, Plan, Work, C64,
};
use rustfft::FftPlanner;

/// Per-unit-σ noise figures of one map.
#[derive(Debug, Clone, Default)]
pub(super) struct NoiseFigures {
    /// SD (N per mm of input noise) of every force component.
    pub(super) force: Vec<f64>,
    /// SD (N per mm) of ΣFx, ΣFy, ΣFz.
    pub(super) sum: [f64; 3],
}

/// The periodic direct solve of whole-lattice data: `spec[slot]` holds the unnormalised
/// DFT of `ux + i·uy` of every layer on its full marker lattice (layout `[px][py]`);
/// returns `(fx, fy, fz)` on the full force lattice, row-major `[qy][qx]` (precompute and
/// tests only: allocates).
pub(super) fn solve_lattice(
    plan: &Plan,
    spec: &[Vec<C64>],
    pmat: &[C64],
    planner: &mut FftPlanner<f64>,
) -> Vec<[f64; 3]> {
    let [mfx, mfy] = plan.mf;
    let (rows, cols) = (plan.rows, plan.cols);
    let mut vin = vec![C64::default(); rows];
    let mut vout = vec![C64::default(); cols];
    let mut gxy = vec![C64::default(); mfx * mfy];
    let mut gz = vec![C64::default(); mfx * mfy];
    for (bi, &c) in plan.blocks.iter().enumerate() {
        gather_marker_block(plan, spec, c, &mut vin);
        let mat = &pmat[bi * rows * cols..(bi + 1) * rows * cols];
        for (j, o) in vout.iter_mut().enumerate() {
            let row = &mat[j * rows..(j + 1) * rows];
            *o = row.iter().zip(&vin).map(|(m, v)| m * v).sum();
        }
        scatter_force_block(plan, c, &vout, &mut gxy, &mut gz);
    }
    let inv_y = planner.plan_fft_inverse(mfy);
    let inv_x = planner.plan_fft_inverse(mfx);
    let mut scratch = vec![
        C64::default();
        inv_x
            .get_inplace_scratch_len()
            .max(inv_y.get_inplace_scratch_len())
    ];
    let mut rxy = vec![C64::default(); mfx * mfy];
    let mut rz = vec![C64::default(); mfx * mfy];
    // [qx][qy]: along y, transpose to [qy][qx], along x.
    for (g, r) in [(&mut gxy, &mut rxy), (&mut gz, &mut rz)] {
        inv_y.process_with_scratch(g, &mut scratch);
        transpose(g, mfy, r, mfx, mfx, mfy);
        inv_x.process_with_scratch(r, &mut scratch);
    }
    let s = plan.scale;
    rxy.iter()
        .zip(&rz)
        .map(|(xy, z)| [xy.re * s, xy.im * s, z.re * s])
        .collect()
}

/// The exact per-node and force-sum SDs of the zero-padded direct map (module docs).
pub(super) fn direct_map(
    plan: &Plan,
    w: &mut Work,
    pmat: &[C64],
    planner: &mut FftPlanner<f64>,
) -> NoiseFigures {
    let (a, b) = (plan.a, plan.b);
    let ([nfx, nfy], [mfx, mfy], [mmx, _]) = (plan.nf, plan.mf, plan.mm);
    let n_sites = plan.site_map.len();
    let mut var = vec![0.0f64; 3 * nfx * nfy];
    let mut wsum = vec![[0.0f64; 3]; 2 * n_sites];
    let mut e = vec![0.0f64; 2 * n_sites];
    for slot in 0..plan.layers.len() {
        for sy in 0..a {
            for sx in 0..a {
                // The input (if any) sitting on marker (sx, sy) of this layer.
                let Some(k0) = plan
                    .site_map
                    .iter()
                    .position(|&(s, idx)| s == slot && idx == sy * mmx + sx)
                else {
                    continue;
                };
                for axis in 0..2 {
                    e.fill(0.0);
                    e[2 * k0 + axis] = 1.0;
                    markers_to_spectra(plan, w, &e, 1.0, false);
                    let resp = solve_lattice(plan, &w.spec, pmat, planner);
                    // Every input of this channel and phase: a shifted copy of `resp`.
                    for (k, &(sl, idx)) in plan.site_map.iter().enumerate() {
                        let (ix, iy) = (idx % mmx, idx / mmx);
                        if sl != slot || ix % a != sx || iy % a != sy {
                            continue;
                        }
                        let (tx, ty) = ((ix - sx) / a * b % mfx, (iy - sy) / a * b % mfy);
                        let mut acc = [0.0f64; 3];
                        for jy in 0..nfy {
                            let qy = (jy + mfy - ty) % mfy;
                            for jx in 0..nfx {
                                let qx = (jx + mfx - tx) % mfx;
                                let r = resp[qy * mfx + qx];
                                let node = jy * nfx + jx;
                                for ci in 0..3 {
                                    var[3 * node + ci] += r[ci] * r[ci];
                                    acc[ci] += r[ci];
                                }
                            }
                        }
                        wsum[2 * k + axis] = acc;
                    }
                }
            }
        }
    }
    let mut sum = [0.0; 3];
    for (ci, s) in sum.iter_mut().enumerate() {
        *s = wsum.iter().map(|v| v[ci] * v[ci]).sum::<f64>().sqrt();
    }
    NoiseFigures {
        force: var.iter().map(|v| v.sqrt()).collect(),
        sum,
    }
}

/// Relative residual at which the force-sum solves stop when the two-level solve takes
/// its force sums from them.
const SUM_TOLERANCE: f64 = 1e-8;
/// ... and when they give SDs only.
const SUM_TOLERANCE_SD: f64 = 1e-6;
/// Largest relative residual of the force-sum solves the two-level solve accepts as
/// exact sums (else it keeps the Galerkin correction's own sums and warns).
pub(super) const SUM_ACCEPT: f64 = 1e-6;
/// Iteration cap of the force-sum solves.
const SUM_MAX_ITERATIONS: usize = 2000;

/// PCG on the normal equations `(HᵀH + λ²I) y = rhs`, preconditioned by the periodic
/// block inverse `M` (plus the coarse solve `Φ G⁻¹ Φᵀ` when a coarse space is given: the
/// two-level preconditioner, `coarse.rs`), from `y = 0`, to a relative residual of
/// `tol`. `hp` (markers) and `q`, `r`, `z`, `p` (forces) are scratch. Returns the
/// relative residual reached (above `tol` when the iteration cap came first).
#[allow(clippy::too_many_arguments)]
fn solve_normal(
    plan: &Plan,
    w: &mut Work,
    amat: &[C64],
    qmat: &[C64],
    coarse: Option<&CoarseSpace>,
    lam2: f64,
    rhs: &[f64],
    tol: f64,
    y: &mut [f64],
    hp: &mut [f64],
    [q, r, z, p]: [&mut [f64]; 4],
) -> f64 {
    let bnorm = rhs.iter().map(|v| v * v).sum::<f64>().sqrt();
    y.fill(0.0);
    if bnorm == 0.0 {
        return 0.0;
    }
    let mut scratch = coarse.map(|c| c.scratch());
    let mut precondition = |w: &mut Work, r: &[f64], z: &mut [f64]| {
        precond_op(plan, w, qmat, r, z);
        if let (Some(c), Some((coef, tmp))) = (coarse, scratch.as_mut()) {
            c.add_solve(r, coef, tmp, z);
        }
    };
    r.copy_from_slice(rhs);
    precondition(w, r, z);
    p.copy_from_slice(z);
    let mut gamma: f64 = r.iter().zip(z.iter()).map(|(a, b)| a * b).sum();
    for _ in 0..SUM_MAX_ITERATIONS {
        forward_op(plan, w, amat, p, hp);
        adjoint_op(plan, w, amat, hp, q);
        for (qi, pi) in q.iter_mut().zip(p.iter()) {
            *qi += lam2 * pi;
        }
        let pq: f64 = p.iter().zip(q.iter()).map(|(a, b)| a * b).sum();
        if !(pq > 0.0 && pq.is_finite()) {
            break;
        }
        let alpha = gamma / pq;
        for ((yi, ri), (pi, qi)) in y.iter_mut().zip(r.iter_mut()).zip(p.iter().zip(q.iter())) {
            *yi += alpha * pi;
            *ri -= alpha * qi;
        }
        if r.iter().map(|v| v * v).sum::<f64>().sqrt() <= tol * bnorm {
            return r.iter().map(|v| v * v).sum::<f64>().sqrt() / bnorm;
        }
        precondition(w, r, z);
        let g2: f64 = r.iter().zip(z.iter()).map(|(a, b)| a * b).sum();
        let beta = g2 / gamma;
        gamma = g2;
        for (pi, zi) in p.iter_mut().zip(z.iter()) {
            *pi = zi + beta * *pi;
        }
    }
    r.iter().map(|v| v * v).sum::<f64>().sqrt() / bnorm
}

/// The force-sum functionals of the converged refined map, dense Tikhonov
/// `(HᵀH + λ²I)⁻¹Hᵀ`: `ΣF_c = w_cᵀu` (module docs), with their SDs per unit σ `‖w_c‖`
/// and the largest relative residual its CG solves reached.
/// `None` for λ = 0 (no unique converged map). With a coarse space the solves use the
/// two-level preconditioner and run to [`SUM_TOLERANCE`] (the two-level solve takes its
/// force sums from these functionals); without, to [`SUM_TOLERANCE_SD`] (SDs only).
#[allow(clippy::too_many_arguments)]
pub(super) fn converged_sums(
    plan: &Plan,
    w: &mut Work,
    amat: &[C64],
    qmat: &[C64],
    coarse: Option<&CoarseSpace>,
    lambda: f64,
    n_in: usize,
    n_out: usize,
) -> Option<([f64; 3], [Vec<f64>; 3], f64)> {
    if lambda <= 0.0 {
        return None;
    }
    let lam2 = lambda * lambda;
    let mut sum = [0.0; 3];
    let mut funcs: [Vec<f64>; 3] = std::array::from_fn(|_| vec![0.0; n_in]);
    let mut y = vec![0.0; n_out];
    let mut scratch: [Vec<f64>; 4] = std::array::from_fn(|_| vec![0.0; n_out]);
    let mut worst = 0.0f64;
    for (c, (out, hp)) in sum.iter_mut().zip(funcs.iter_mut()).enumerate() {
        // (HᵀH + λ²I) y = 1_c, the indicator of component c; w_c = H y.
        let rhs = super::coarse::indicator(n_out, c);
        let [q, r, z, p] = &mut scratch;
        let residual = solve_normal(
            plan,
            w,
            amat,
            qmat,
            coarse,
            lam2,
            &rhs,
            if coarse.is_some() {
                SUM_TOLERANCE
            } else {
                SUM_TOLERANCE_SD
            },
            &mut y,
            hp,
            [q, r, z, p],
        );
        worst = worst.max(residual);
        forward_op(plan, w, amat, &y, hp);
        *out = hp.iter().map(|v| v * v).sum::<f64>().sqrt();
    }
    Some((sum, funcs, worst))
}

/// Marker spacing (per axis, in marker pitches) of the probing estimate of per-node SDs
/// ([`probe_force_sd`]).
pub(super) const PROBE_SPACING: usize = 10;

/// Relative residual at which the probe solves stop (the SDs need ~1e-3).
const PROBE_TOLERANCE: f64 = 1e-4;

/// Per-node SDs (per unit σ) of a linear map `L` (markers → forces) whose columns are
/// local (the response to one marker decays away from it), from `2·layers·d²` probes
/// instead of one apply per input (Tang & Saad's probing of a diagonal, 2012): the
/// inputs of each layer, axis and grid phase `(ix mod d, iy mod d)` form one probe
/// `z_C = Σ_{i∈C} s_i e_i` with pseudo-random signs `s_i = ±1`, and
///
/// ```text
/// Var f_j / σ² = Σ_i L_ji² = Σ_C (L z_C)_j² − Σ_C Σ_{i≠i' ∈ C} s_i s_i' L_ji L_ji'.
/// ```
///
/// Two inputs of one class are at least `d` marker pitches apart, so at most one of
/// them is near node `j` and the cross terms are products of a near and a far
/// response, with random signs (zero mean); they are dropped. `apply(z, out)` is `L`.
pub(super) fn probe_force_var(
    plan: &Plan,
    spacing: usize,
    n_out: usize,
    mut apply: impl FnMut(&[f64], &mut [f64]),
) -> Vec<f64> {
    let n_in = 2 * plan.site_map.len();
    let mmx = plan.mm[0];
    let mut var = vec![0.0f64; n_out];
    let mut z = vec![0.0f64; n_in];
    let mut out = vec![0.0f64; n_out];
    let mut seed = 0x2545_f491_4f6c_dd1du64;
    for slot in 0..plan.layers.len() {
        for axis in 0..2 {
            for py in 0..spacing {
                for px in 0..spacing {
                    z.fill(0.0);
                    let mut any = false;
                    for (k, &(sl, idx)) in plan.site_map.iter().enumerate() {
                        let (ix, iy) = (idx % mmx, idx / mmx);
                        if sl == slot && ix % spacing == px && iy % spacing == py {
                            seed ^= seed << 13;
                            seed ^= seed >> 7;
                            seed ^= seed << 17;
                            z[2 * k + axis] = if seed & 1 == 0 { 1.0 } else { -1.0 };
                            any = true;
                        }
                    }
                    if !any {
                        continue;
                    }
                    apply(&z, &mut out);
                    for (v, o) in var.iter_mut().zip(&out) {
                        *v += o * o;
                    }
                }
            }
        }
    }
    var
}

/// Per-node SDs (per unit σ) of the converged refined map `(HᵀH + λ²I)⁻¹Hᵀ` by probing
/// ([`probe_force_sd`]; each probe is one PCG solve). `None` for λ = 0.
#[allow(clippy::too_many_arguments)]
pub(super) fn converged_force_sd(
    plan: &Plan,
    w: &mut Work,
    amat: &[C64],
    qmat: &[C64],
    coarse: Option<&CoarseSpace>,
    lambda: f64,
    spacing: usize,
    n_in: usize,
    n_out: usize,
) -> Option<Vec<f64>> {
    if lambda <= 0.0 {
        return None;
    }
    let lam2 = lambda * lambda;
    let mut hp = vec![0.0; n_in];
    let mut rhs = vec![0.0; n_out];
    let mut scratch: [Vec<f64>; 4] = std::array::from_fn(|_| vec![0.0; n_out]);
    Some(probe_force_var(plan, spacing, n_out, |z, out| {
        adjoint_op(plan, w, amat, z, &mut rhs);
        let [q, r, zz, p] = &mut scratch;
        solve_normal(
            plan,
            w,
            amat,
            qmat,
            coarse,
            lam2,
            &rhs,
            PROBE_TOLERANCE,
            out,
            &mut hp,
            [q, r, zz, p],
        );
    }))
}
