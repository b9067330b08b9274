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
//! CGLS refinement is not a fixed linear map (its step lengths depend on the frame), but
//! it converges to dense Tikhonov `P = (HᵀH + λ²I)⁻¹Hᵀ` on the real geometry. For that map
//! the force-sum weights are exact and cheap: `w_c = H y_c` with `(HᵀH + λ²I) y_c = 1_c`
//! (the indicator of component `c` on the force grid), three preconditioned CG solves at
//! precompute. The per-node figures of the refined solve are the per-frequency ones
//! above, an approximation: exact per-node figures of the converged map would need one
//! solve per force component. Measured against 300 Monte Carlo frames on
//! `grid_sensor(16,16,1.1,1.1)` at λ = 1e-2·σ₁ (`tests/fourier.rs`): force sums within
//! 2 % (refined), per-node SDs within 4 % (direct, zero-padded), 11 % on the interior and
//! 27 % overall (refined, the edges worst).

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

/// Relative residual at which the force-sum solves stop.
const SUM_TOLERANCE: f64 = 1e-10;
/// Iteration cap of the force-sum solves.
const SUM_MAX_ITERATIONS: usize = 2000;

/// SDs (per unit σ) of the force sums of the converged refined map, dense Tikhonov
/// `(HᵀH + λ²I)⁻¹Hᵀ` (module docs). `None` for λ = 0 (no unique converged map).
pub(super) fn converged_sums(
    plan: &Plan,
    w: &mut Work,
    amat: &[C64],
    qmat: &[C64],
    lambda: f64,
    n_in: usize,
    n_out: usize,
) -> Option<[f64; 3]> {
    if lambda <= 0.0 {
        return None;
    }
    let lam2 = lambda * lambda;
    let mut sum = [0.0; 3];
    let mut hp = vec![0.0; n_in];
    let mut q = vec![0.0; n_out];
    for (c, out) in sum.iter_mut().enumerate() {
        // PCG on (HᵀH + λ²I) y = 1_c, preconditioned by the periodic block inverse.
        let rhs: Vec<f64> = (0..n_out).map(|j| f64::from(j % 3 == c)).collect();
        let bnorm = rhs.iter().map(|v| v * v).sum::<f64>().sqrt();
        let mut y = vec![0.0; n_out];
        let mut r = rhs.clone();
        let mut z = vec![0.0; n_out];
        precond_op(plan, w, qmat, &r, &mut z);
        let mut p = z.clone();
        let mut gamma: f64 = r.iter().zip(&z).map(|(a, b)| a * b).sum();
        for _ in 0..SUM_MAX_ITERATIONS {
            forward_op(plan, w, amat, &p, &mut hp);
            adjoint_op(plan, w, amat, &hp, &mut q);
            for (qi, pi) in q.iter_mut().zip(&p) {
                *qi += lam2 * pi;
            }
            let pq: f64 = p.iter().zip(&q).map(|(a, b)| a * b).sum();
            if !(pq > 0.0 && pq.is_finite()) {
                break;
            }
            let alpha = gamma / pq;
            for ((yi, ri), (pi, qi)) in y.iter_mut().zip(r.iter_mut()).zip(p.iter().zip(&q)) {
                *yi += alpha * pi;
                *ri -= alpha * qi;
            }
            if r.iter().map(|v| v * v).sum::<f64>().sqrt() <= SUM_TOLERANCE * bnorm {
                break;
            }
            precond_op(plan, w, qmat, &r, &mut z);
            let g2: f64 = r.iter().zip(&z).map(|(a, b)| a * b).sum();
            let beta = g2 / gamma;
            gamma = g2;
            for (pi, zi) in p.iter_mut().zip(&z) {
                *pi = zi + beta * *pi;
            }
        }
        forward_op(plan, w, amat, &y, &mut hp);
        *out = hp.iter().map(|v| v * v).sum::<f64>().sqrt();
    }
    Some(sum)
}
