//! Refinement of the direct periodic solve: CGLS on the exact (non-periodic) operator,
//! applied by the same FFTs, preconditioned by the periodic block inverse.

use super::transform::{
    forces_to_spectra, gather_force_block, markers_to_forces, neg, scatter_force_block,
    spectra_to_forces, transpose, Plan, Work, C64,
};
use super::FourierSolver;

/// `Hᵀ r`: the exact adjoint (unitary transforms, block `Aᴴ`).
pub(super) fn adjoint_op(plan: &Plan, w: &mut Work, amat: &[C64], r: &[f64], out: &mut [f64]) {
    markers_to_forces(plan, w, amat, true, r, 1.0, false, out);
}

/// `M s`: the block-circulant preconditioner `S_f (AᴴA + λ²I)⁻¹ S_fᵀ` (per block
/// `cols × cols`, Hermitian), symmetric positive definite on the force grid.
pub(super) fn precond_op(plan: &Plan, w: &mut Work, qmat: &[C64], s: &[f64], out: &mut [f64]) {
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
pub(super) fn forward_op(plan: &Plan, w: &mut Work, amat: &[C64], f: &[f64], out: &mut [f64]) {
    forces_to_lattice(plan, w, amat, f, false);
    let s = plan.scale;
    for (k, &(slot, idx)) in plan.site_map.iter().enumerate() {
        let v = w.z[slot][idx];
        out[2 * k] = v.re * s;
        out[2 * k + 1] = v.im * s;
    }
}

/// Forces → marker lattice through per-block `rows × cols` matrices `mats` (the forward
/// operator `A`, or `Pᴴ` for the transposed direct solve): afterwards `w.z[slot]` holds
/// `ux + i·uy` of every layer, unscaled (times [`Plan::scale`] is the result), row-major
/// `[iy][ix]` with row stride `mm_x`, on the rows that hold markers (`full = false`) or
/// on the whole lattice, padding included (`full = true`).
pub(super) fn forces_to_lattice(plan: &Plan, w: &mut Work, mats: &[C64], f: &[f64], full: bool) {
    let ([mx, my], [mmx, mmy]) = (plan.m, plan.mm);
    let (rows, cols, a) = (plan.rows, plan.cols, plan.a);
    forces_to_spectra(plan, w, f);
    for (bi, &c) in plan.blocks.iter().enumerate() {
        gather_force_block(plan, c, &w.gxy, &w.gz, &mut w.vin);
        let mat = &mats[bi * rows * cols..(bi + 1) * rows * cols];
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
        let n_rows = if full { mmy } else { lp.nm[1] };
        transpose(sp, mmy, z, mmx, mmx, n_rows);
        plan.inv_mx
            .process_with_scratch(&mut z[..n_rows * mmx], &mut w.scratch);
    }
}

impl FourierSolver {
    /// Preconditioned CGLS on `min ‖H f − u‖² + λ²‖f‖²` from the current `f` (Björck
    /// 1996, Alg. 7.4.1), with `H` the exact restricted operator applied by FFT. `u` is
    /// already scaled. Stops after [`FourierSolver::refine_iterations`] iterations or
    /// as soon as the preconditioned gradient `z = M (Hᵀ(u − H f) − λ² f)` is at most
    /// [`FourierSolver::refine_tolerance`] × `‖f‖` (λ > 0 only): `M ≈ (HᵀH + λ²I)⁻¹`,
    /// so `‖z‖/‖f‖` estimates the relative distance of `f` from the dense Tikhonov
    /// solution. Returns the iterations run.
    pub(super) fn refine(&mut self, u: &[f64], in_scale: f64, f: &mut [f64]) -> usize {
        let lam2 = self.lambda * self.lambda;
        let precondition = self.refine_preconditioned && self.lambda > 0.0;
        // The stopping test needs `z ≈ N⁻¹ s` (the preconditioned step). Below
        // `STAGNATION` the iterates are rounding noise, and CGLS run on past that point
        // diverged (600 iterations on the 16×16 issue-12 grid: ΣF of 5e6 N).
        let tol2 = if precondition {
            self.refine_tolerance.max(STAGNATION).powi(2)
        } else {
            0.0
        };
        let (plan, w, amat, qmat) = (&self.plan, &mut self.work, &self.a, &self.q);
        // The vectors are taken out of `w` so the operators can borrow it; no allocation.
        let mut q = std::mem::take(&mut w.q);
        let mut r = std::mem::take(&mut w.r);
        let mut s = std::mem::take(&mut w.s);
        let mut p = std::mem::take(&mut w.p);
        let mut z = std::mem::take(&mut w.zf);
        let converged =
            |z: &[f64], f: &[f64]| -> bool { tol2 > 0.0 && norm2(z) <= tol2 * norm2(f) };
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
        let gamma0 = gamma;
        let mut done = 0;
        while done < self.refine_iterations && !converged(&z, f) {
            if gamma <= STAGNATION * STAGNATION * gamma0 || !gamma.is_finite() {
                break;
            }
            forward_op(plan, w, amat, &p, &mut q);
            let delta: f64 = norm2(&q) + lam2 * norm2(&p);
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
            done += 1;
        }
        w.q = q;
        w.r = r;
        w.s = s;
        w.p = p;
        w.zf = z;
        done
    }
}

/// Relative size of the preconditioned gradient below which the refinement has
/// converged to rounding (λ > 0), or of `‖Hᵀr − λ²f‖²` against its start (λ = 0).
const STAGNATION: f64 = 1e-13;

/// `‖v‖²`.
fn norm2(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum()
}

#[cfg(test)]
mod tests {
    use super::super::tests::pseudo_random;
    use super::*;
    use crate::solve::{Lambda, Problem, SolverConfig};

    /// A 2.2 / 1.1 mm sensor whose red layer is offset by an arbitrary sub-pitch amount.
    fn offset_problem() -> (crate::sensor::Sensor, Vec<crate::model::MarkerSite>) {
        let mut s = crate::sensor::grid_sensor(7, 5, 2.2, 1.1);
        s.layers[1].markers.as_mut().unwrap().grid.origin_mm = [0.37, -0.21];
        let sites = crate::model::MarkerSite::from_sensor_grids(&s);
        (s, sites)
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
}
