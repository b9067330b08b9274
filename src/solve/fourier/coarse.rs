//! Two-level solve: the direct periodic solve plus a Galerkin correction on a coarse
//! space of the force grid, with the force sums of dense Tikhonov exactly.
//!
//! # Why
//!
//! The direct periodic solve `f_d = P_per u` (bridged padding, module docs of
//! [`super`]) differs from dense Tikhonov `f* = N⁻¹Hᵀu`, `N = HᵀH + λ²I`, by a boundary
//! error that is mostly *smooth*: on the issue-12 loads it is a force-sum error of 29 %
//! (64×64) to 126 % (16×16) of the applied total, with a false normal load under shear.
//! Smooth errors live in a small space, so they can be removed once and for all at
//! precompute instead of by ~20 CGLS iterations per frame.
//!
//! # What
//!
//! `Φ` (`n_f × k`) spans bilinear hats on a coarse grid of the force grid (every `s`
//! nodes per axis and the last node, one hat per node and force component). The
//! correction is the Galerkin projection of the remaining error onto `span Φ` in the
//! `N`-norm, i.e. the best correction from `span Φ` for `min ‖Hf − u‖² + λ²‖f‖²`:
//!
//! ```text
//! f = f_d + Φ c,   (ΦᵀNΦ) c = Φᵀ(Hᵀu − N f_d)   ⇒   c = C u,
//! C = (ΦᵀNΦ)⁻¹ [ (HΦ)ᵀ − (P_perᵀ N Φ)ᵀ ]          (k × n_in, precomputed)
//! ```
//!
//! and then the force sums are made those of dense Tikhonov exactly: `ΣF_a = w_aᵀu` with
//! `w_a = H N⁻¹ 1_a` (three converged CG solves, shared with the uncertainty figures),
//! by the smallest change in `span Φ` in the `N`-norm, `c += E (w − Sᵀ) u` with
//! `E = G⁻¹B (BᵀG⁻¹B)⁻¹`, `G = ΦᵀNΦ`, `B = Φᵀ[1_x 1_y 1_z]` and `Sᵀu` the sums of the
//! corrected solve. Both steps are linear in `u`, so they fold into one `k × n_in`
//! matrix: per frame the correction is `k·n_in` multiply-adds plus the sparse `Φ c`.
//! With `s = 1` (`Φ = I`) the two-level solve *is* dense Tikhonov.
//!
//! `s` is the smallest spacing whose matrix fits [`COARSE_BUDGET`] multiply-adds per
//! frame: 16×16 force grid with markers every 1.1 mm (1024 inputs) → `s = 1`, exact;
//! 32×32 (4096) → `s = 3`, `k = 432`; 64×64 (16384) → `s = 11`, `k = 147`.
//!
//! Precompute: `k` applies of `N` (forward + adjoint FFT pipelines), `k` transposed
//! direct solves and one Cholesky solve with `n_in` right-hand sides.
//!
//! Measured against dense Tikhonov at λ = 2e-3 of the periodic σ_max (five issue-12
//! loads, worst; README *Performance*): see the table there and
//! `examples/fourier_refine_tradeoff.rs`.

use nalgebra::{Cholesky, DMatrix, Dyn};

use super::refine::{adjoint_op, forces_to_lattice, forward_op};
use super::transform::{Plan, Work, C64};

/// Largest number of multiply-adds per frame (`k × inputs`) the coarse correction may
/// cost: ~0.5 ms on one core of the bench machine (a 9.6 MB f32 matrix streamed from
/// memory; 1.0 ms in f64), beside the 64×64 direct solve's ~0.69 ms: the 64×64 two-level
/// solve takes 1.2 ms, under 2 ms.
pub const COARSE_BUDGET: usize = 2_500_000;

/// Largest condition number of the Galerkin matrix `ΦᵀNΦ` the correction is built
/// with (its solve then keeps ~4 significant digits in f64).
const MAX_CONDITION: f64 = 1e12;

/// The coarse space: tensor products of 1-D hat functions, one per coarse node and force
/// component. Column `j = (c_y·n_cx + c_x)·3 + component`.
#[derive(Debug, Clone)]
pub(super) struct Basis {
    nf: [usize; 2],
    nc: [usize; 2],
    /// Coarse spacing in force nodes.
    spacing: usize,
    /// `nc[0] × nf[0]` and `nc[1] × nf[1]`, row-major.
    bx: Vec<f64>,
    by: Vec<f64>,
}

/// 1-D hats on nodes `0..n`, coarse nodes every `s` and the last node: (count, `count × n`).
fn hats(n: usize, s: usize) -> (usize, Vec<f64>) {
    let mut nodes: Vec<usize> = (0..n).step_by(s.max(1)).collect();
    if nodes.last() != Some(&(n - 1)) {
        nodes.push(n - 1);
    }
    let nc = nodes.len();
    let mut b = vec![0.0; nc * n];
    for (k, &c) in nodes.iter().enumerate() {
        let row = &mut b[k * n..(k + 1) * n];
        row[c] = 1.0;
        if k > 0 {
            let l = nodes[k - 1];
            for (i, v) in row.iter_mut().enumerate().take(c).skip(l + 1) {
                *v = (i - l) as f64 / (c - l) as f64;
            }
        }
        if k + 1 < nc {
            let r = nodes[k + 1];
            for (i, v) in row.iter_mut().enumerate().take(r).skip(c + 1) {
                *v = (r - i) as f64 / (r - c) as f64;
            }
        }
    }
    (nc, b)
}

/// Coarse nodes per axis at spacing `s` on `n` nodes.
fn count(n: usize, s: usize) -> usize {
    (n - 1).div_ceil(s) + 1
}

/// The smallest coarse spacing (force nodes) whose correction matrix has at most
/// `budget` entries for `n_in` inputs.
pub(super) fn spacing_for(nf: [usize; 2], n_in: usize, budget: usize) -> usize {
    let k = |s: usize| 3 * count(nf[0], s) * count(nf[1], s);
    let mut s = 1;
    while k(s).saturating_mul(n_in) > budget && s < nf[0].max(nf[1]) {
        s += 1;
    }
    s
}

impl Basis {
    pub(super) fn new(nf: [usize; 2], spacing: usize) -> Basis {
        let (ncx, bx) = hats(nf[0], spacing);
        let (ncy, by) = hats(nf[1], spacing);
        Basis {
            nf,
            nc: [ncx, ncy],
            spacing,
            bx,
            by,
        }
    }

    /// Number of basis functions `k`.
    pub(super) fn len(&self) -> usize {
        3 * self.nc[0] * self.nc[1]
    }

    /// Scratch length of [`Basis::add`] and [`Basis::project`].
    fn scratch_len(&self) -> usize {
        3 * (self.nc[1] * self.nf[0]).max(self.nf[1] * self.nc[0])
    }

    /// `f += Φ c`.
    fn add(&self, coef: &[f64], tmp: &mut [f64], f: &mut [f64]) {
        let ([nx, ny], [ncx, ncy]) = (self.nf, self.nc);
        let tmp = &mut tmp[..3 * ncy * nx];
        tmp.fill(0.0);
        for cy in 0..ncy {
            for cx in 0..ncx {
                let c3 = &coef[(cy * ncx + cx) * 3..(cy * ncx + cx) * 3 + 3];
                let row = &self.bx[cx * nx..(cx + 1) * nx];
                for (ix, &b) in row.iter().enumerate() {
                    if b != 0.0 {
                        let t = &mut tmp[(cy * nx + ix) * 3..(cy * nx + ix) * 3 + 3];
                        for (tv, cv) in t.iter_mut().zip(c3) {
                            *tv += b * cv;
                        }
                    }
                }
            }
        }
        for iy in 0..ny {
            let fr = &mut f[3 * iy * nx..3 * (iy + 1) * nx];
            for cy in 0..ncy {
                let b = self.by[cy * ny + iy];
                if b != 0.0 {
                    for (fv, tv) in fr.iter_mut().zip(&tmp[3 * cy * nx..3 * (cy + 1) * nx]) {
                        *fv += b * tv;
                    }
                }
            }
        }
    }

    /// `coef = Φᵀ v`.
    fn project(&self, v: &[f64], tmp: &mut [f64], coef: &mut [f64]) {
        let ([nx, ny], [ncx, ncy]) = (self.nf, self.nc);
        let tmp = &mut tmp[..3 * ny * ncx];
        for iy in 0..ny {
            for cx in 0..ncx {
                let mut acc = [0.0; 3];
                for (ix, &b) in self.bx[cx * nx..(cx + 1) * nx].iter().enumerate() {
                    if b != 0.0 {
                        let k = 3 * (iy * nx + ix);
                        for (a, x) in acc.iter_mut().zip(&v[k..k + 3]) {
                            *a += b * x;
                        }
                    }
                }
                tmp[3 * (iy * ncx + cx)..3 * (iy * ncx + cx) + 3].copy_from_slice(&acc);
            }
        }
        coef.fill(0.0);
        for cy in 0..ncy {
            for iy in 0..ny {
                let b = self.by[cy * ny + iy];
                if b != 0.0 {
                    let src = &tmp[3 * iy * ncx..3 * (iy + 1) * ncx];
                    let dst = &mut coef[3 * cy * ncx..3 * (cy + 1) * ncx];
                    for (d, s) in dst.iter_mut().zip(src) {
                        *d += b * s;
                    }
                }
            }
        }
    }
}

/// The coarse space with the Cholesky factor of its Galerkin matrix `G = ΦᵀNΦ`: the
/// coarse solve `Φ G⁻¹ Φᵀ`, also the coarse half of the two-level preconditioner
/// `M + Φ G⁻¹ Φᵀ` of the CG solves on `N` at precompute (force sums, probing). (In the
/// per-frame refinement it saved ~15 % of the iterations at 64×64 for ~25 % more time
/// per iteration, so the refinement keeps `M`.)
#[derive(Clone)]
pub(super) struct CoarseSpace {
    basis: Basis,
    chol: Cholesky<f64, Dyn>,
}

impl CoarseSpace {
    /// `z += Φ G⁻¹ Φᵀ r`, with scratch `coef` (`k`) and `tmp` ([`Basis::scratch_len`]).
    pub(super) fn add_solve(&self, r: &[f64], coef: &mut [f64], tmp: &mut [f64], z: &mut [f64]) {
        self.basis.project(r, tmp, coef);
        let mut v = nalgebra::DVectorViewMut::from_slice(coef, self.basis.len());
        self.chol.solve_mut(&mut v);
        self.basis.add(coef, tmp, z);
    }

    /// Scratch sizes of [`CoarseSpace::add_solve`]: (`coef`, `tmp`).
    pub(super) fn scratch(&self) -> (Vec<f64>, Vec<f64>) {
        (
            vec![0.0; self.basis.len()],
            vec![0.0; self.basis.scratch_len()],
        )
    }
}

/// The first half of the two-level build: the coarse space, its Galerkin factor and
/// `G⁻¹ Φᵀ(Hᵀ − N P_per)` (`k × n_in`), before the force sums are made exact.
pub(super) struct Galerkin {
    space: CoarseSpace,
    c: DMatrix<f64>,
}

impl Galerkin {
    /// The coarse space, for the two-level preconditioner of the force-sum solves.
    pub(super) fn space(&self) -> &CoarseSpace {
        &self.space
    }
}

/// The precomputed correction `c = C u`, `f += Φ c`, and the coarse space.
#[derive(Clone)]
pub(super) struct Coarse {
    space: CoarseSpace,
    /// `k × n_in`, row-major, in f32: the per-frame product streams this matrix from
    /// memory (19 MB in f64 at 64×64), so f32 halves its cost; it is accumulated in f64.
    c: Vec<f32>,
    n_in: usize,
    coef: Vec<f64>,
    tmp: Vec<f64>,
}

impl std::fmt::Debug for Coarse {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Coarse")
            .field("spacing", &self.space.basis.spacing)
            .field("nodes", &self.space.basis.nc)
            .finish_non_exhaustive()
    }
}

/// `Σ a_i b_i` in f64 with independent partial sums (vectorises).
fn dot(a: &[f32], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 8];
    let n8 = a.len() / 8 * 8;
    for (x, y) in a[..n8].chunks_exact(8).zip(b[..n8].chunks_exact(8)) {
        for i in 0..8 {
            acc[i] += f64::from(x[i]) * y[i];
        }
    }
    let tail: f64 = a[n8..]
        .iter()
        .zip(&b[n8..])
        .map(|(x, y)| f64::from(*x) * y)
        .sum();
    acc.iter().sum::<f64>() + tail
}

/// `P_perᵀ f`: the transpose of the direct solve (`bridge`: with the edge bridge).
/// `ph` holds, per processed block, `Pᴴ` (`rows × cols`) of the block solution operator.
pub(super) fn direct_transpose(
    plan: &Plan,
    w: &mut Work,
    ph: &[C64],
    bridge: bool,
    f: &[f64],
    out: &mut [f64],
) {
    forces_to_lattice(plan, w, ph, f, true);
    let mmx = plan.mm[0];
    if bridge {
        // The bridge is `B = B_y ∘ B_x` (rows extended along x, then the extended rows
        // blended along y); its transpose folds the padding back: y first, then x.
        for (slot, lp) in plan.layers.iter().enumerate() {
            let [nmx, nmy] = lp.nm;
            let (data, pad) = w.z[slot].split_at_mut(nmy * mmx);
            for (prow, &s) in pad.chunks_exact(mmx).zip(&plan.bridge_y[slot]) {
                for (d, p) in data[..mmx].iter_mut().zip(prow) {
                    *d += p * s;
                }
                for (d, p) in data[(nmy - 1) * mmx..].iter_mut().zip(prow) {
                    *d += p * (1.0 - s);
                }
            }
            for row in data.chunks_exact_mut(mmx) {
                let (d, p) = row.split_at_mut(nmx);
                for (&pv, &s) in p.iter().zip(&plan.bridge_x[slot]) {
                    d[0] += pv * s;
                    d[nmx - 1] += pv * (1.0 - s);
                }
            }
        }
    }
    let s = plan.scale;
    for (k, &(slot, idx)) in plan.site_map.iter().enumerate() {
        let v = w.z[slot][idx];
        out[2 * k] = v.re * s;
        out[2 * k + 1] = v.im * s;
    }
}

/// The indicator `1_a` of force component `a` on `n_out / 3` force nodes.
pub(super) fn indicator(n_out: usize, a: usize) -> Vec<f64> {
    (0..n_out).map(|j| f64::from(j % 3 == a)).collect()
}

/// The force-sum functionals of the bridged direct map, `P_perᵀ 1_a` (`ΣF_a = (P_perᵀ
/// 1_a)ᵀ u`), through the transposed direct solve; `ph` from [`blocks_adjoint`].
pub(super) fn direct_sum_functionals(
    plan: &Plan,
    w: &mut Work,
    ph: &[C64],
    n_in: usize,
    n_out: usize,
) -> [Vec<f64>; 3] {
    std::array::from_fn(|a| {
        let mut t = vec![0.0; n_in];
        direct_transpose(plan, w, ph, true, &indicator(n_out, a), &mut t);
        t
    })
}

/// Per processed block, the conjugate transpose (`rows × cols`) of the `cols × rows`
/// block solution operators `pmat`.
pub(super) fn blocks_adjoint(plan: &Plan, pmat: &[C64]) -> Vec<C64> {
    let (rows, cols) = (plan.rows, plan.cols);
    let mut ph = vec![C64::default(); pmat.len()];
    for (dst, src) in ph
        .chunks_exact_mut(rows * cols)
        .zip(pmat.chunks_exact(rows * cols))
    {
        for j in 0..cols {
            for r in 0..rows {
                dst[r * cols + j] = src[j * rows + r].conj();
            }
        }
    }
    ph
}

impl Coarse {
    /// First half of the build (module docs), λ > 0: the coarse space, `G` and its
    /// factor, and the correction before the force-sum constraint. Errors describe why
    /// no correction could be built (the caller falls back to the direct solve).
    #[allow(clippy::too_many_arguments)]
    /// `ph` is [`blocks_adjoint`] of the direct solve's block operators.
    pub(super) fn galerkin(
        plan: &Plan,
        w: &mut Work,
        amat: &[C64],
        ph: &[C64],
        lambda: f64,
        n_in: usize,
        n_out: usize,
        budget: usize,
    ) -> Result<Galerkin, String> {
        if lambda <= 0.0 {
            return Err("λ = 0: the Galerkin matrix is not definite".into());
        }
        let basis = Basis::new(plan.nf, spacing_for(plan.nf, n_in, budget));
        let k = basis.len();
        let lam2 = lambda * lambda;
        let mut tmp = vec![0.0; basis.scratch_len()];
        let mut coef = vec![0.0; k];
        let mut phi = vec![0.0; n_out];
        let mut hphi = vec![0.0; n_in];
        let mut nphi = vec![0.0; n_out];
        let mut t = vec![0.0; n_in];
        let mut g = DMatrix::<f64>::zeros(k, k);
        // Φᵀ(Hᵀ − N P_per), row by row.
        let mut rhs = DMatrix::<f64>::zeros(k, n_in);
        for j in 0..k {
            coef.fill(0.0);
            coef[j] = 1.0;
            phi.fill(0.0);
            basis.add(&coef, &mut tmp, &mut phi);
            forward_op(plan, w, amat, &phi, &mut hphi);
            adjoint_op(plan, w, amat, &hphi, &mut nphi);
            for (n, p) in nphi.iter_mut().zip(&phi) {
                *n += lam2 * p;
            }
            basis.project(&nphi, &mut tmp, &mut coef);
            g.column_mut(j).copy_from_slice(&coef);
            direct_transpose(plan, w, ph, true, &nphi, &mut t);
            for (i, (h, tv)) in hphi.iter().zip(&t).enumerate() {
                rhs[(j, i)] = h - tv;
            }
        }
        let g = (&g + g.transpose()) * 0.5;
        let chol = g.cholesky().ok_or_else(|| {
            format!("the {k}×{k} Galerkin matrix ΦᵀNΦ is not positive definite at λ = {lambda:e}")
        })?;
        // κ(G) from the Cholesky factor's diagonal (a lower bound, ≤ κ(G) ≤ κ(N)): past
        // MAX_CONDITION the correction would carry more rounding than signal.
        let (dmin, dmax) = chol
            .l_dirty()
            .diagonal()
            .iter()
            .fold((f64::INFINITY, 0.0f64), |(lo, hi), &d| {
                (lo.min(d), hi.max(d))
            });
        let kappa = (dmax / dmin).powi(2);
        if kappa.is_nan() || kappa > MAX_CONDITION {
            return Err(format!(
                "the {k}×{k} Galerkin matrix ΦᵀNΦ is too ill-conditioned at λ = {lambda:e} \
                 (condition ≥ {kappa:.1e})"
            ));
        }
        let c = chol.solve(&rhs);
        Ok(Galerkin {
            space: CoarseSpace { basis, chol },
            c,
        })
    }

    /// Second half: the force sums made those of dense Tikhonov exactly, `sums` being
    /// the functionals `w_a = H N⁻¹ 1_a` (module docs) and `direct_sums` those of the
    /// direct solve, `P_perᵀ 1_a` ([`direct_sum_functionals`]); `None` keeps the
    /// Galerkin correction's own sums.
    pub(super) fn finish(
        galerkin: Galerkin,
        sums: Option<&[Vec<f64>; 3]>,
        direct_sums: &[Vec<f64>; 3],
        n_out: usize,
    ) -> Result<Coarse, String> {
        let Galerkin { space, mut c } = galerkin;
        let (k, n_in) = c.shape();
        let (mut coef, mut tmp) = space.scratch();
        if let Some(sums) = sums {
            Self::constrain_sums(&space, &mut c, sums, direct_sums, n_out)?;
        }
        let mut rm = vec![0.0f32; k * n_in];
        for (j, row) in rm.chunks_exact_mut(n_in).enumerate() {
            for (i, v) in row.iter_mut().enumerate() {
                *v = c[(j, i)] as f32;
            }
        }
        if rm.iter().any(|v| !v.is_finite()) {
            return Err("the coarse correction is not finite".into());
        }
        coef.fill(0.0);
        tmp.fill(0.0);
        Ok(Coarse {
            tmp,
            coef,
            space,
            c: rm,
            n_in,
        })
    }

    /// `c += E (w − Sᵀ)`: the smallest change in `span Φ` (`N`-norm) that gives the
    /// two-level solve the force sums `w_aᵀu` (module docs).
    fn constrain_sums(
        space: &CoarseSpace,
        c: &mut DMatrix<f64>,
        sums: &[Vec<f64>; 3],
        direct_sums: &[Vec<f64>; 3],
        n_out: usize,
    ) -> Result<(), String> {
        let (k, n_in) = c.shape();
        let (mut coef, mut tmp) = space.scratch();
        // The two-level sums are (P_perᵀ1_a + CᵀB_a)ᵀ u, B_a = Φᵀ1_a.
        let mut b = DMatrix::<f64>::zeros(k, 3);
        let mut d = DMatrix::<f64>::zeros(3, n_in);
        for (a, (wa, t)) in sums.iter().zip(direct_sums).enumerate() {
            space
                .basis
                .project(&indicator(n_out, a), &mut tmp, &mut coef);
            b.column_mut(a).copy_from_slice(&coef);
            let ctb = c.transpose() * b.column(a);
            for i in 0..n_in {
                d[(a, i)] = wa[i] - t[i] - ctb[i];
            }
        }
        let gib = space.chol.solve(&b);
        let m = b.transpose() * &gib;
        let minv = m
            .try_inverse()
            .ok_or_else(|| "the force-sum constraint matrix BᵀG⁻¹B is singular".to_string())?;
        *c += gib * minv * d;
        Ok(())
    }

    /// `f += Φ C (in_scale · u)`.
    pub(super) fn apply(&mut self, u: &[f64], in_scale: f64, f: &mut [f64]) {
        let n = self.n_in;
        for (co, row) in self.coef.iter_mut().zip(self.c.chunks_exact(n)) {
            *co = dot(row, u) * in_scale;
        }
        self.space.basis.add(&self.coef, &mut self.tmp, f);
    }

    /// The coarse space.
    pub(super) fn space(&self) -> &CoarseSpace {
        &self.space
    }

    /// Coarse spacing (force nodes) and coarse nodes per axis.
    pub(super) fn shape(&self) -> (usize, [usize; 2]) {
        (self.space.basis.spacing, self.space.basis.nc)
    }

    /// `k`, the number of coarse functions.
    pub(super) fn len(&self) -> usize {
        self.space.basis.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hats_are_a_partition_of_unity_with_nodes_every_s_and_at_the_end() {
        for (n, s) in [(1, 1), (2, 1), (16, 1), (16, 4), (64, 11), (7, 3), (5, 9)] {
            let (nc, b) = hats(n, s);
            assert_eq!(nc, count(n, s), "n {n} s {s}");
            for i in 0..n {
                let total: f64 = (0..nc).map(|k| b[k * n + i]).sum();
                assert!((total - 1.0).abs() < 1e-15, "n {n} s {s} node {i}: {total}");
            }
        }
    }

    #[test]
    fn coarse_spacing_fits_the_budget() {
        assert_eq!(spacing_for([16, 16], 1024, COARSE_BUDGET), 1);
        assert_eq!(spacing_for([32, 32], 4096, COARSE_BUDGET), 3);
        assert_eq!(spacing_for([64, 64], 16384, COARSE_BUDGET), 11);
        // Huge problems end at two coarse nodes per axis (k = 12), over budget or not.
        assert_eq!(spacing_for([200, 200], 1 << 24, COARSE_BUDGET), 200);
    }

    use super::super::tests::pseudo_random;
    use super::super::transform::markers_to_forces;
    use super::super::FourierSolver;
    use crate::solve::{Lambda, Problem, SolverConfig};

    #[test]
    fn transposed_direct_solve_is_the_transpose_with_and_without_the_bridge() {
        // <P_per u, f> = <u, P_perᵀ f> on a multi-rate grid with an offset layer.
        let mut s = crate::sensor::grid_sensor(7, 5, 2.2, 1.1);
        s.layers[1].markers.as_mut().unwrap().grid.origin_mm = [0.37, -0.21];
        let sites = crate::model::MarkerSite::from_sensor_grids(&s);
        let p = Problem::new(&s, &sites);
        let cfg = SolverConfig {
            lambda: Lambda::Fixed(0.1),
            ..SolverConfig::default()
        };
        let mut solver = FourierSolver::precompute(&p, &cfg, None).unwrap();
        let ph = blocks_adjoint(&solver.plan, &solver.p);
        let u = pseudo_random(p.n_inputs(), 11);
        let f = pseudo_random(p.n_outputs(), 13);
        for bridge in [false, true] {
            let mut pu = vec![0.0; p.n_outputs()];
            let mut ptf = vec![0.0; p.n_inputs()];
            let (plan, w) = (&solver.plan, &mut solver.work);
            markers_to_forces(plan, w, &solver.p, false, &u, 1.0, bridge, &mut pu);
            direct_transpose(plan, w, &ph, bridge, &f, &mut ptf);
            let lhs: f64 = pu.iter().zip(&f).map(|(a, b)| a * b).sum();
            let rhs: f64 = u.iter().zip(&ptf).map(|(a, b)| a * b).sum();
            assert!(
                (lhs - rhs).abs() <= 1e-12 * lhs.abs().max(rhs.abs()),
                "bridge {bridge}: {lhs} vs {rhs}"
            );
        }
    }

    #[test]
    fn basis_add_and_project_are_transposes() {
        let basis = Basis::new([9, 6], 4);
        let k = basis.len();
        let n = 3 * 9 * 6;
        let c: Vec<f64> = (0..k).map(|i| ((i * 37) % 11) as f64 - 5.0).collect();
        let v: Vec<f64> = (0..n).map(|i| ((i * 53) % 13) as f64 - 6.0).collect();
        let mut tmp = vec![0.0; basis.scratch_len()];
        let mut phic = vec![0.0; n];
        basis.add(&c, &mut tmp, &mut phic);
        let mut ptv = vec![0.0; k];
        basis.project(&v, &mut tmp, &mut ptv);
        let lhs: f64 = phic.iter().zip(&v).map(|(a, b)| a * b).sum();
        let rhs: f64 = c.iter().zip(&ptv).map(|(a, b)| a * b).sum();
        assert!(
            (lhs - rhs).abs() < 1e-9 * lhs.abs().max(1.0),
            "{lhs} vs {rhs}"
        );
    }
}
