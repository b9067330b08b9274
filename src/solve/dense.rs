//! Dense inverse solvers (`pinv`, `tikhonov`, `tsvd`) built on the SVD of the transfer
//! matrix `H` (paper Eq. 5, `m = 2·markers` rows, `n = 3·force points` columns, mm/N).
//!
//! # Method
//!
//! With the thin SVD `H = U Σ Vᵀ`, `Σ = diag(σ_1 ≥ … ≥ σ_p)`, `p = min(m, n)`, every
//! method here is a *filtered* pseudo-inverse (Hansen, *Rank-Deficient and Discrete
//! Ill-Posed Problems*, SIAM 1998, §4):
//!
//! ```text
//! f = P u,    P = V · diag(φ_i / σ_i) · Uᵀ      (n × m, N/mm)
//! ```
//!
//! with filter factors `φ_i ∈ [0, 1]`:
//!
//! | method | `φ_i` |
//! |---|---|
//! | `pinv` (the paper's method) | 1 if `σ_i > rcond·σ_1`, else 0 |
//! | `tikhonov` | `σ_i² / (σ_i² + λ²)` (equivalently `f = argmin ‖Hf − u‖² + λ²‖f‖²`) |
//! | `tsvd` | 1 for `i ≤ k`, else 0 |
//!
//! The relative cut-off `rcond` defaults to `max(m, n)·ε` (ε = 2.2·10⁻¹⁶, the LAPACK /
//! NumPy `pinv` convention). Singular values at or below `rcond·σ_1` are numerically
//! zero: every method drops them (`φ_i = 0`), which keeps `P` bounded
//! (`‖P‖₂ = max φ_i/σ_i`) on rank-deficient systems and yields the minimum-norm
//! solution there and on underdetermined ones (`m < n`).
//!
//! # Automatic parameters
//!
//! With `β = Uᵀu` and the part of `u` outside the range of `U`,
//! `δ₀² = ‖u‖² − ‖β‖²` (non-zero when `m > n`):
//!
//! - **GCV** (Golub, Heath & Wahba 1979) minimises
//!   `G = ‖H f − u‖² / (m − Σφ_i)²`, with `‖H f − u‖² = Σ (1−φ_i)² β_i² + δ₀²`.
//!   For Tikhonov λ runs over a logarithmic grid from `σ_r/10` to `σ_1` (`σ_r` the
//!   smallest singular value kept), then a golden-section search refines the best
//!   bracket in `log λ`. For TSVD, `k` runs over `1 … min(r, m−1)`.
//! - **L-curve** (Hansen & O'Leary 1993) takes λ at the maximum curvature of
//!   `(log ‖Hf − u‖, log ‖f‖)`, computed from the closed-form derivatives of the
//!   filter factors (as in Hansen's Regularization Tools, `lcfun`), on the same grid
//!   and refinement.
//!
//! λ has the units of a singular value (mm/N). Both selectors need a displacement
//! frame; without one [`SolveError::NeedsFrame`] is returned.
//!
//! # Decomposition
//!
//! The SVD is faer's thin SVD; nalgebra's `try_svd` is the fallback should faer not
//! converge (either failing gives [`SolveError::Decomposition`]). Measured in release
//! on this project's 2-core machine (`examples/dense_cost.rs`), faer is 2.4–4× faster
//! on the paper's 520×240 system and 5.5× faster on the 1024×768 system of a 16×16
//! force grid; both agree to `|Δσ|/σ_max ≤ 2·10⁻¹⁵`. Dense methods stop being
//! practical around a 32×32 force grid (`H` 4096×3072): larger grids are the Fourier
//! solver's job.
//!
//! # Per-frame apply
//!
//! Precompute forms `P` once (f64), stores it row-major in f64 or f32
//! ([`Precision`]) and applies it with the SIMD kernel of [`super::kernel`]; apply
//! allocates nothing. In f32, the frame is scaled by a power of two (exact) so any
//! finite input stays in f32 range.

use nalgebra::DMatrix;

use super::kernel::{self, Isa};
use super::*;
use crate::model;

/// Points of the logarithmic λ grid searched before refinement.
const LAMBDA_GRID_POINTS: usize = 120;
/// Golden-section iterations refining λ (bracket shrinks by 0.618 each time).
const REFINE_ITERATIONS: usize = 60;
/// Note added when the per-frame apply runs in f32.
const F32_NOTE: &str = "per-frame apply in f32: measured at the paper size ‖f32 − f64‖/‖f64‖ ≈ 1e-5 for pinv, 3e-7 for tikhonov";
/// Condition number above which the notes warn that noise is strongly amplified.
const ILL_CONDITIONED: f64 = 1e6;

/// Alignment of the operator rows and the frame scratch, bytes: one cache line, so
/// no SIMD load of the kernel straddles two lines.
const ALIGN_BYTES: usize = 64;

/// A zero-initialised buffer whose usable part starts on a cache line. (A `Vec` of
/// this size comes from `mmap` 16 bytes past a page start: every 64-byte load would
/// split across two lines.)
#[derive(Debug, Clone)]
struct Aligned<T> {
    buf: Vec<T>,
    off: usize,
    len: usize,
}

impl<T: Copy + Default> Aligned<T> {
    fn zeroed(len: usize) -> Self {
        let extra = ALIGN_BYTES / std::mem::size_of::<T>();
        let buf = vec![T::default(); len + extra];
        // align_offset may decline (usize::MAX); the buffer is then merely unaligned.
        let off = match buf.as_ptr().align_offset(ALIGN_BYTES) {
            o if o <= extra => o,
            _ => 0,
        };
        Aligned { buf, off, len }
    }
    fn as_slice(&self) -> &[T] {
        &self.buf[self.off..self.off + self.len]
    }
    fn as_mut_slice(&mut self) -> &mut [T] {
        &mut self.buf[self.off..self.off + self.len]
    }
}

/// The filtered operator `P`, row-major `n_out × stride` (the `n_in` columns zero-padded
/// to a whole number of cache lines), with a frame scratch of `stride` values, in the
/// apply precision.
#[derive(Debug, Clone)]
enum Operator {
    F64 { p: Aligned<f64>, x: Aligned<f64> },
    F32 { p: Aligned<f32>, x: Aligned<f32> },
}

impl Operator {
    /// From `P` as row-major `n_out × n_in` f64 values.
    fn new(p: &[f64], n_out: usize, n_in: usize, precision: Precision) -> (Operator, usize) {
        fn pad<T: Copy + Default>(
            p: &[f64],
            n_out: usize,
            n_in: usize,
            conv: impl Fn(f64) -> T,
        ) -> (Aligned<T>, Aligned<T>, usize) {
            let lane = ALIGN_BYTES / std::mem::size_of::<T>();
            let stride = n_in.div_ceil(lane) * lane;
            let mut a = Aligned::zeroed(n_out * stride);
            if stride > 0 {
                for (dst, src) in a
                    .as_mut_slice()
                    .chunks_exact_mut(stride)
                    .zip(p.chunks_exact(n_in))
                {
                    for (d, &v) in dst.iter_mut().zip(src) {
                        *d = conv(v);
                    }
                }
            }
            (a, Aligned::zeroed(stride), stride)
        }
        match precision {
            Precision::F64 => {
                let (p, x, stride) = pad(p, n_out, n_in, |v| v);
                (Operator::F64 { p, x }, stride)
            }
            Precision::F32 => {
                let (p, x, stride) = pad(p, n_out, n_in, |v| v as f32);
                (Operator::F32 { p, x }, stride)
            }
        }
    }
}

/// Largest working memory a dense precompute may take, bytes (1 GiB): `H`, its copy
/// for the SVD, `U`, `V` and the operator. The paper's sensor (about 3,400 marker
/// values for 2,800 force unknowns at the finest grids the README measures) takes
/// ~0.3 GB; a million markers in one frame would take 15 GB.
pub const MAX_DENSE_BYTES: f64 = 1024.0 * 1024.0 * 1024.0;

/// Working memory of a dense precompute on an `m × n` system, bytes, estimated from
/// the shapes alone (nothing is allocated): `H` (`m n`), faer's copy of it (`m n`),
/// the thin factors `U` (`m p`) and `V` (`n p`, `p = min(m, n)`), the operator `Pᵀ`
/// (`m n`) and the padded per-frame operator (`m n`), 8 bytes each. Measured peaks
/// (`/usr/bin/time -v`, docs/limits.md) lie below it.
pub fn dense_memory_bytes(m: usize, n: usize) -> f64 {
    let (m, n) = (m as f64, n as f64);
    let p = m.min(n);
    8.0 * (4.0 * m * n + m * p + n * p)
}

/// Refuses a dense system whose precompute would take more than [`MAX_DENSE_BYTES`]
/// (checked before `H` is built): the error says how much, for how many markers and
/// force points, and that the `fourier` solver or fewer markers would do.
pub fn check_dense_size(m: usize, n: usize) -> Result<(), SolveError> {
    let bytes = dense_memory_bytes(m, n);
    if bytes <= MAX_DENSE_BYTES {
        return Ok(());
    }
    Err(SolveError::TooBig {
        rows: m,
        cols: n,
        bytes,
        limit_bytes: MAX_DENSE_BYTES,
    })
}

/// A precomputed dense solver (`pinv`, `tikhonov` or `tsvd`): `f = P u` per frame.
#[derive(Debug, Clone)]
pub struct DenseSolver {
    n_in: usize,
    n_out: usize,
    op: Operator,
    /// Row length of the padded operator (≥ `n_in`).
    stride: usize,
    isa: Isa,
    /// Largest accepted |u| (mm): beyond it `P u` could overflow.
    limit_mm: f64,
    /// Euclidean norm of every row of `P` (N/mm): the force SD per mm of independent
    /// displacement noise, `sqrt(diag(P Pᵀ))`.
    row_norm: Vec<f64>,
    /// Norm of the sum of the fx, fy, fz rows of `P` (N/mm): the SD of ΣF per mm of
    /// noise, correlations between nodes included.
    sum_norm: [f64; 3],
    diag: Diagnostics,
}

/// The SVD of `H` with singular values descending.
struct Svd {
    u: DMatrix<f64>,
    v_t: DMatrix<f64>,
    sigma: Vec<f64>,
}

/// SVD of `H`: faer's (blocked bidiagonalisation, divide and conquer; several times
/// faster than nalgebra's implicit-shift QR at our sizes, see the module docs), with
/// nalgebra as a fallback if faer does not converge.
fn svd(h: DMatrix<f64>) -> Result<Svd, SolveError> {
    let (m, n) = h.shape();
    if h.iter().any(|v| !v.is_finite()) {
        return Err(SolveError::Decomposition(
            "transfer matrix has non-finite entries".into(),
        ));
    }
    let s = match svd_faer(&h) {
        Some(s) => s,
        None => svd_nalgebra(h)?,
    };
    if s.sigma.iter().any(|v| !v.is_finite() || *v < 0.0) || s.sigma.windows(2).any(|w| w[0] < w[1])
    {
        return Err(SolveError::Decomposition(format!(
            "svd of the {m}×{n} transfer matrix produced non-finite or unsorted singular values"
        )));
    }
    Ok(s)
}

/// faer's thin SVD, converted to nalgebra matrices; `None` if it did not converge.
fn svd_faer(h: &DMatrix<f64>) -> Option<Svd> {
    let (m, n) = h.shape();
    let p = m.min(n);
    let a = faer::Mat::<f64>::from_fn(m, n, |i, j| h[(i, j)]);
    let s = a.thin_svd().ok()?;
    let (fu, fv) = (s.U(), s.V());
    let u = DMatrix::from_fn(m, p, |i, j| fu[(i, j)]);
    let v_t = DMatrix::from_fn(p, n, |i, j| fv[(j, i)]);
    let sigma: Vec<f64> = s.S().column_vector().iter().copied().collect();
    Some(Svd { u, v_t, sigma })
}

/// nalgebra's SVD (singular values sorted descending).
fn svd_nalgebra(h: DMatrix<f64>) -> Result<Svd, SolveError> {
    let (m, n) = h.shape();
    let p = m.min(n);
    // nalgebra counts iterations over the whole bidiagonal; a few hundred per singular
    // value is far above what converging problems use.
    let max_iter = 500 * p + 1000;
    let s = h
        .try_svd(true, true, f64::EPSILON, max_iter)
        .ok_or_else(|| {
            SolveError::Decomposition(format!(
                "svd of the {m}×{n} transfer matrix did not converge in {max_iter} iterations"
            ))
        })?;
    let (Some(u), Some(v_t)) = (s.u, s.v_t) else {
        return Err(SolveError::Decomposition(
            "svd returned no singular vectors".into(),
        ));
    };
    let sigma: Vec<f64> = s.singular_values.iter().copied().collect();
    Ok(Svd { u, v_t, sigma })
}

/// Spectral quantities of one frame, shared by the GCV and L-curve criteria.
struct Spectrum<'a> {
    sigma: &'a [f64],
    /// `β_i = (Uᵀu)_i`, i < p.
    beta: Vec<f64>,
    /// `‖u‖² − ‖β‖²`, the squared residual no filter can remove.
    delta0_sq: f64,
    /// Number of rows `m`.
    m: usize,
    /// Numerical rank `r`: indices ≥ r are never used.
    rank: usize,
}

impl<'a> Spectrum<'a> {
    /// The spectrum of `frame` divided by its largest |value|: GCV's and the
    /// L-curve's optimum are invariant under `u → a·u`, but their values are not, and
    /// `‖u‖²` under- or overflows for displacements of order 1e-160 or 1e300 mm.
    /// `frame` must not be all zero.
    fn new(svd: &'a Svd, rank: usize, frame: &[f64]) -> Self {
        let factor = super::unit_peak_factor(frame);
        let unit: Vec<f64> = frame.iter().map(|v| v * factor).collect();
        let beta: Vec<f64> = svd
            .u
            .tr_mul(&nalgebra::DVector::from_column_slice(&unit))
            .iter()
            .copied()
            .collect();
        let u_sq: f64 = unit.iter().map(|v| v * v).sum();
        let beta_sq: f64 = beta.iter().map(|v| v * v).sum();
        Spectrum {
            sigma: &svd.sigma,
            beta,
            delta0_sq: (u_sq - beta_sq).max(0.0),
            m: frame.len(),
            rank,
        }
    }

    /// Squared residual `‖Hf − u‖²` for the given filter factors (`phi.len() == rank`).
    fn residual_sq(&self, phi: impl Fn(usize) -> f64) -> f64 {
        let mut r = self.delta0_sq;
        for (i, b) in self.beta.iter().enumerate() {
            let keep = if i < self.rank { 1.0 - phi(i) } else { 1.0 };
            r += keep * keep * b * b;
        }
        r
    }

    fn tikhonov_phi(&self, lambda: f64, i: usize) -> f64 {
        let s2 = self.sigma[i] * self.sigma[i];
        s2 / (s2 + lambda * lambda)
    }

    /// GCV function of Tikhonov at λ.
    fn gcv_tikhonov(&self, lambda: f64) -> f64 {
        let res = self.residual_sq(|i| self.tikhonov_phi(lambda, i));
        let dof = self.m as f64
            - (0..self.rank)
                .map(|i| self.tikhonov_phi(lambda, i))
                .sum::<f64>();
        res / (dof * dof)
    }

    /// GCV function of TSVD at rank k (`k < m`).
    fn gcv_tsvd(&self, k: usize) -> f64 {
        let res = self.residual_sq(|i| if i < k { 1.0 } else { 0.0 });
        let dof = (self.m - k) as f64;
        res / (dof * dof)
    }

    /// Curvature of the L-curve `(log ‖Hf−u‖, log ‖f‖)` at λ (Hansen, `lcfun`), > 0 at
    /// a corner.
    fn lcurve_curvature(&self, lambda: f64) -> f64 {
        let (mut eta2, mut rho2) = (0.0, self.delta0_sq);
        let (mut phi, mut psi, mut dphi, mut dpsi) = (0.0, 0.0, 0.0, 0.0);
        for (i, &b) in self.beta.iter().enumerate() {
            if i >= self.rank {
                rho2 += b * b;
                continue;
            }
            let s = self.sigma[i];
            let xi = b / s;
            let f = self.tikhonov_phi(lambda, i);
            let cf = 1.0 - f;
            let f1 = -2.0 * f * cf / lambda;
            let f2 = -f1 * (3.0 - 4.0 * f) / lambda;
            eta2 += (f * xi) * (f * xi);
            rho2 += (cf * b) * (cf * b);
            phi += f * f1 * xi * xi;
            psi += cf * f1 * b * b;
            dphi += (f1 * f1 + f * f2) * xi * xi;
            dpsi += (-f1 * f1 + cf * f2) * b * b;
        }
        let (eta, rho) = (eta2.sqrt(), rho2.sqrt());
        let deta = phi / eta;
        let drho = -psi / rho;
        let ddeta = dphi / eta - deta * (deta / eta);
        let ddrho = -dpsi / rho - drho * (drho / rho);
        let dlogeta = deta / eta;
        let dlogrho = drho / rho;
        let ddlogeta = ddeta / eta - dlogeta * dlogeta;
        let ddlogrho = ddrho / rho - dlogrho * dlogrho;
        let k = (dlogrho * ddlogeta - ddlogrho * dlogeta)
            / (dlogrho * dlogrho + dlogeta * dlogeta).powf(1.5);
        if k.is_finite() {
            k
        } else {
            f64::NEG_INFINITY
        }
    }
}

/// Minimises `cost` over `log λ` in `[lo, hi]`: grid, then golden section around the
/// best grid point. Returns `(λ, cost, grid index of the best point)`.
fn minimise_log(lo: f64, hi: f64, cost: impl Fn(f64) -> f64) -> (f64, f64, usize) {
    let (tlo, thi) = (lo.ln(), hi.ln());
    let n = LAMBDA_GRID_POINTS;
    let t_at = |k: usize| tlo + (thi - tlo) * k as f64 / (n - 1) as f64;
    let c = |t: f64| {
        let v = cost(t.exp());
        if v.is_nan() {
            f64::INFINITY
        } else {
            v
        }
    };
    let (mut best_k, mut best_c) = (0, f64::INFINITY);
    for k in 0..n {
        let v = c(t_at(k));
        if v < best_c {
            best_c = v;
            best_k = k;
        }
    }
    // Golden section on the bracket around the best grid point.
    let (mut a, mut b) = (
        t_at(best_k.saturating_sub(1)),
        t_at((best_k + 1).min(n - 1)),
    );
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let mut x1 = b - g * (b - a);
    let mut x2 = a + g * (b - a);
    let (mut c1, mut c2) = (c(x1), c(x2));
    for _ in 0..REFINE_ITERATIONS {
        if c1 <= c2 {
            b = x2;
            x2 = x1;
            c2 = c1;
            x1 = b - g * (b - a);
            c1 = c(x1);
        } else {
            a = x1;
            x1 = x2;
            c1 = c2;
            x2 = a + g * (b - a);
            c2 = c(x2);
        }
    }
    let (t, v) = if c1 <= c2 { (x1, c1) } else { (x2, c2) };
    if v <= best_c {
        (t.exp(), v, best_k)
    } else {
        (t_at(best_k).exp(), best_c, best_k)
    }
}

fn fmt_g(x: f64) -> String {
    format!("{x:.3e}")
}

fn check_frame<'f>(
    frame: Option<&'f [f64]>,
    m: usize,
    what: &'static str,
) -> Result<&'f [f64], SolveError> {
    let u = frame.ok_or(SolveError::NeedsFrame(what))?;
    check_input(u, m)?;
    if u.iter().all(|&v| v == 0.0) {
        return Err(SolveError::InvalidOption(format!(
            "the frame given for automatic {what} selection is all zero: gcv and the l-curve need a loaded frame"
        )));
    }
    Ok(u)
}

/// Checks the system's size and the options for a dense method; returns `rcond`
/// (the configured one, or `max(m, n)·ε`).
fn check_config(
    m: usize,
    n: usize,
    config: &SolverConfig,
    frame: Option<&[f64]>,
) -> Result<f64, SolveError> {
    if m == 0 || n == 0 {
        return Err(SolveError::Empty(format!("the system is {m}×{n}")));
    }
    check_dense_size(m, n)?;
    if config.method == Method::Fourier {
        return Err(SolveError::InvalidOption(
            "the dense solver does not run method fourier".into(),
        ));
    }
    if let Some(u) = frame {
        check_input(u, m)?;
    }
    let rcond = match config.rcond {
        None => m.max(n) as f64 * f64::EPSILON,
        Some(r) if r.is_finite() && (0.0..1.0).contains(&r) => r,
        Some(r) => {
            return Err(SolveError::InvalidOption(format!(
                "rcond = {} must be a number in [0, 1)",
                fmt_num(r)
            )))
        }
    };
    if let Lambda::Fixed(l) = config.lambda {
        if config.method == Method::Tikhonov && !(l.is_finite() && l >= 0.0) {
            return Err(SolveError::InvalidOption(format!(
                "lambda = {} mm/N must be a finite number >= 0",
                fmt_num(l)
            )));
        }
    }
    Ok(rcond)
}

/// The condition number of `H` itself (σ_max/σ_min over all `min(m, n)` singular
/// values, whatever cut-off or regularisation the method applies; ∞ only if σ_min is
/// exactly 0) and the notes on the system's shape and numerical rank.
fn structure_notes(
    m: usize,
    n: usize,
    sigma: &[f64],
    rank: usize,
    rcond: f64,
) -> (f64, Vec<String>) {
    let p = sigma.len();
    let s_max = sigma[0];
    let tol = rcond * s_max;
    let mut notes = Vec::new();
    if m < n {
        notes.push(format!(
            "underdetermined: {m} displacement values for {n} force unknowns; the solution is the minimum-norm one (force patterns invisible to the markers are set to zero)"
        ));
    }
    let condition_number = if sigma[p - 1] > 0.0 {
        s_max / sigma[p - 1]
    } else {
        f64::INFINITY
    };
    if rank == 0 {
        notes.push("the transfer matrix is zero: every force maps to zero".into());
    } else if rank < p {
        notes.push(format!(
            "rank {rank} of {p} after the cut-off: {} singular value(s) ≤ rcond·σ_max = {} mm/N (rcond = {}) are treated as zero; σ_max/σ_r over the kept ones = {} (the condition number of H itself is σ_max/σ_min over all of them)",
            p - rank,
            fmt_g(tol),
            fmt_g(rcond),
            fmt_g(s_max / sigma[rank - 1])
        ));
    }
    (condition_number, notes)
}

/// A method's filter factors `φ_i` (zero beyond the numerical rank) and the parameter
/// it used.
struct Filter {
    phi: Vec<f64>,
    lambda: Option<f64>,
    rank: Option<usize>,
}

/// The filter factors of the configured method (module docs' table), choosing the
/// TSVD rank or the Tikhonov λ on `frame` when they are automatic.
fn filter_factors(
    config: &SolverConfig,
    svd: &Svd,
    rank: usize,
    rcond: f64,
    frame: Option<&[f64]>,
    m: usize,
    notes: &mut Vec<String>,
) -> Result<Filter, SolveError> {
    let p = svd.sigma.len();
    let mut phi = vec![0.0; p];
    match config.method {
        Method::Pinv => {
            phi[..rank].fill(1.0);
            notes.push(format!(
                "pinv: {rank} of {p} singular values kept (cut-off rcond·σ_max = {} mm/N, rcond = {})",
                fmt_g(rcond * svd.sigma[0]),
                fmt_g(rcond)
            ));
            Ok(Filter {
                phi,
                lambda: None,
                rank: Some(rank),
            })
        }
        Method::Tsvd => {
            let k = tsvd_rank(config.rank, svd, rank, frame, m, notes)?;
            phi[..k].fill(1.0);
            Ok(Filter {
                phi,
                lambda: None,
                rank: Some(k),
            })
        }
        Method::Tikhonov => {
            let lambda = tikhonov_lambda(config.lambda, svd, rank, frame, m, notes)?;
            for (f, s) in phi.iter_mut().zip(&svd.sigma).take(rank) {
                let s2 = s * s;
                *f = s2 / (s2 + lambda * lambda);
            }
            Ok(Filter {
                phi,
                lambda: Some(lambda),
                rank: None,
            })
        }
        Method::Fourier => Err(SolveError::InvalidOption(
            "the dense solver does not run method fourier".into(),
        )),
    }
}

/// The TSVD rank: the fixed one (within the numerical rank) or GCV's over
/// `1 … min(rank, m − 1)`, with a warning when it lands on the range's boundary.
fn tsvd_rank(
    choice: Rank,
    svd: &Svd,
    rank: usize,
    frame: Option<&[f64]>,
    m: usize,
    notes: &mut Vec<String>,
) -> Result<usize, SolveError> {
    let sigma = &svd.sigma;
    let n = svd.v_t.ncols();
    if let Rank::Fixed(k) = choice {
        if k == 0 || k > rank {
            return Err(SolveError::InvalidOption(format!(
                "tsvd rank k = {k} is out of range: this {m}×{n} system has numerical rank {rank}, so k must be in 1..={rank}"
            )));
        }
        notes.push(format!("tsvd: fixed rank k = {k} of numerical rank {rank}"));
        return Ok(k);
    }
    let u = check_frame(frame, m, "rank")?;
    let spec = Spectrum::new(svd, rank, u);
    let k_max = rank.min(m - 1);
    if k_max == 0 {
        notes.push(format!(
            "tsvd: gcv needs fewer kept values than rows ({m}); using the full rank {rank}"
        ));
        return Ok(rank);
    }
    let (mut best_k, mut best) = (1, f64::INFINITY);
    for k in 1..=k_max {
        let g = spec.gcv_tsvd(k);
        if g < best {
            best = g;
            best_k = k;
        }
    }
    notes.push(format!(
        "tsvd: rank k = {best_k} chosen by gcv over 1..={k_max} (gcv = {} for the frame scaled to max |u| = 1, σ_k = {} mm/N, next σ = {} mm/N)",
        fmt_g(best),
        fmt_g(sigma[best_k - 1]),
        sigma.get(best_k).map_or("none".into(), |s| fmt_g(*s))
    ));
    if k_max > 1 && (best_k == k_max || best_k == 1) {
        notes.push(format!(
            "{WARNING_PREFIX}tsvd: the gcv search for the rank ended on the {} boundary of its range 1..={k_max} (k = {best_k}): the best rank may lie outside it{}; give --rank <k> to choose another",
            if best_k == 1 { "lower" } else { "upper" },
            if best_k == 1 { "" } else { " (the largest allowed is min(numerical rank, rows - 1))" }
        ));
    }
    Ok(best_k)
}

/// The Tikhonov λ: the fixed one, or GCV's / the L-curve's on `frame` over
/// `[σ_r/10, σ_1]`, with a warning when it lands on the range's boundary.
fn tikhonov_lambda(
    choice: Lambda,
    svd: &Svd,
    rank: usize,
    frame: Option<&[f64]>,
    m: usize,
    notes: &mut Vec<String>,
) -> Result<f64, SolveError> {
    let sigma = &svd.sigma;
    let sel = match choice {
        Lambda::Fixed(l) => {
            notes.push(format!("tikhonov: fixed λ = {} mm/N", fmt_g(l)));
            if l == 0.0 {
                notes.push(
                    "tikhonov: λ = 0 is the plain pseudo-inverse (with the rcond cut-off)".into(),
                );
            }
            return Ok(l);
        }
        sel @ (Lambda::Gcv | Lambda::LCurve) if rank > 0 => sel,
        _ => {
            check_frame(frame, m, "lambda")?;
            notes.push("tikhonov: zero matrix, λ is irrelevant".into());
            return Ok(0.0);
        }
    };
    let u = check_frame(frame, m, "lambda")?;
    let spec = Spectrum::new(svd, rank, u);
    let lo = 0.1 * sigma[rank - 1];
    let hi = sigma[0];
    let (l, value, k) = if sel == Lambda::Gcv {
        minimise_log(lo, hi, |l| spec.gcv_tikhonov(l))
    } else {
        let (l, v, k) = minimise_log(lo, hi, |l| -spec.lcurve_curvature(l));
        (l, -v, k)
    };
    let name = if sel == Lambda::Gcv { "gcv" } else { "l-curve" };
    let what = if sel == Lambda::Gcv {
        format!("gcv = {} for the frame scaled to max |u| = 1", fmt_g(value))
    } else {
        format!("curvature = {}", fmt_g(value))
    };
    notes.push(format!(
        "tikhonov: λ = {} mm/N chosen by {name} ({what}) over [{}, {}] mm/N ({LAMBDA_GRID_POINTS} log-spaced points, golden-section refined)",
        fmt_g(l),
        fmt_g(lo),
        fmt_g(hi)
    ));
    // At the edge: on the first or last grid point, or refined to within one grid
    // step of the range's end.
    let step = (hi / lo).ln() / (LAMBDA_GRID_POINTS - 1) as f64;
    let low_edge = k == 0 || (l / lo).ln() < step;
    let high_edge = k == LAMBDA_GRID_POINTS - 1 || (hi / l).ln() < step;
    if low_edge || high_edge {
        notes.push(format!(
            "{WARNING_PREFIX}tikhonov: the {name} search for λ ended on the {} boundary of its range [{}, {}] mm/N (λ = {} mm/N): the optimum may lie outside it; give --lambda <mm/N> to choose another",
            if low_edge { "lower" } else { "upper" },
            fmt_g(lo),
            fmt_g(hi),
            fmt_g(l)
        ));
    }
    Ok(l)
}

/// `Pᵀ = U diag(g) Vᵀ` (`m × n`, column-major, so its storage is row-major `P`) with
/// `g_i = φ_i/σ_i`, and `g`; refuses non-finite entries.
fn filtered_inverse(
    svd: &Svd,
    phi: &[f64],
    m: usize,
    n: usize,
) -> Result<(DMatrix<f64>, Vec<f64>), SolveError> {
    let g: Vec<f64> = phi
        .iter()
        .zip(&svd.sigma)
        .map(|(&f, &s)| if f > 0.0 { f / s } else { 0.0 })
        .collect();
    let k = g.iter().rposition(|&v| v > 0.0).map_or(0, |i| i + 1);
    let pt = if k == 0 {
        DMatrix::<f64>::zeros(m, n)
    } else {
        let mut us = svd.u.columns(0, k).into_owned();
        for (i, mut col) in us.column_iter_mut().enumerate() {
            col *= g[i];
        }
        us * svd.v_t.rows(0, k)
    };
    if pt.iter().any(|v| !v.is_finite()) {
        return Err(SolveError::Decomposition(
            "the filtered pseudo-inverse has non-finite entries".into(),
        ));
    }
    Ok((pt, g))
}

/// Noise propagation through `P`: with `u = u₀ + e`, `e ~ (0, σ² I)`, `Cov(f) = σ² P Pᵀ`,
/// so `SD(f_j) = σ·‖P_j‖` and `SD(Σ_a f) = σ·‖Σ_{j on axis a} P_j‖`; and the input
/// bound that keeps `f` finite.
struct NoiseNorms {
    row_norm: Vec<f64>,
    sum_norm: [f64; 3],
    limit_mm: f64,
}

impl NoiseNorms {
    /// From `Pᵀ` (`m × n`): column `j` of `Pᵀ` is row `j` of `P`.
    fn of(pt: &DMatrix<f64>) -> NoiseNorms {
        let (m, n) = pt.shape();
        let row_norm: Vec<f64> = pt.column_iter().map(|c| c.norm()).collect();
        let mut sum_norm = [0.0; 3];
        for (a, sn) in sum_norm.iter_mut().enumerate() {
            let mut acc = nalgebra::DVector::<f64>::zeros(m);
            for j in (a..n).step_by(3) {
                acc += pt.column(j);
            }
            *sn = acc.norm();
        }
        // ‖P‖_∞ (max row sum of |P|) bounds |f_i| ≤ ‖P‖_∞ · max|u_j|.
        let row_sum_max = pt
            .column_iter()
            .map(|c| c.iter().map(|v| v.abs()).sum::<f64>())
            .fold(0.0, f64::max);
        let limit_mm = if row_sum_max > 0.0 {
            0.5 * f64::MAX / row_sum_max
        } else {
            f64::MAX
        };
        NoiseNorms {
            row_norm,
            sum_norm,
            limit_mm,
        }
    }
}

impl DenseSolver {
    /// Builds `H` for the problem (paper Eq. 5) and precomputes the configured dense
    /// method (`pinv`, `tikhonov` or `tsvd`). `frame` (mm) is needed for automatic λ or
    /// rank selection and ignored otherwise.
    pub fn precompute(
        problem: &Problem<'_>,
        config: &SolverConfig,
        frame: Option<&[f64]>,
    ) -> Result<DenseSolver, SolveError> {
        if problem.sites.is_empty() {
            return Err(SolveError::Empty("no markers carry data".into()));
        }
        if problem.sensor.force_grid.is_empty() {
            return Err(SolveError::Empty("the force grid has no points".into()));
        }
        check_dense_size(2 * problem.sites.len(), 3 * problem.sensor.force_grid.len())?;
        let h = model::transfer_matrix(
            &problem.forward_model(),
            problem.sites,
            &problem.sensor.force_points_mm(),
        )?;
        Self::from_matrix(h, config, frame)
    }

    /// Precomputes the configured dense method for a given transfer matrix `H`
    /// (`m × n`, mm/N; rows and columns in the order of [`crate::model`]): the SVD, the
    /// filter factors of the method, the filtered pseudo-inverse `P = V diag(φ/σ) Uᵀ`
    /// and its noise norms.
    pub fn from_matrix(
        h: DMatrix<f64>,
        config: &SolverConfig,
        frame: Option<&[f64]>,
    ) -> Result<DenseSolver, SolveError> {
        let (m, n) = h.shape();
        let rcond = check_config(m, n, config, frame)?;
        let svd = svd(h)?;
        let s_max = svd.sigma[0];
        let tol = rcond * s_max;
        let rank = svd
            .sigma
            .iter()
            .take_while(|&&s| s > tol && s > 0.0)
            .count();
        let (condition_number, mut notes) = structure_notes(m, n, &svd.sigma, rank, rcond);
        let filter = filter_factors(config, &svd, rank, rcond, frame, m, &mut notes)?;
        let (pt, g) = filtered_inverse(&svd, &filter.phi, m, n)?;
        let noise_gain = g.iter().copied().fold(0.0, f64::max);
        let effective_rank: f64 = filter.phi.iter().sum();
        let norms = NoiseNorms::of(&pt);
        if condition_number > ILL_CONDITIONED && rank > 0 {
            notes.push(format!(
                "ill-conditioned (σ_max/σ_min = {}): displacement noise is amplified by up to ‖P‖₂ = {} N/mm; tikhonov or tsvd with automatic parameters suit noisy data better",
                fmt_g(condition_number),
                fmt_g(noise_gain)
            ));
        }
        let isa = Isa::detect();
        // Column-major Pᵀ (m × n) is row-major P (n × m).
        let (op, stride) = Operator::new(pt.as_slice(), n, m, config.precision);
        drop(pt);
        if config.precision == Precision::F32 {
            notes.push(F32_NOTE.into());
        }
        notes.push(format!("per-frame kernel: {}", isa.name()));
        Ok(DenseSolver {
            n_in: m,
            n_out: n,
            op,
            stride,
            isa,
            limit_mm: norms.limit_mm,
            row_norm: norms.row_norm,
            sum_norm: norms.sum_norm,
            diag: Diagnostics {
                method: config.method,
                shape: (m, n),
                singular_values: svd.sigma,
                condition_number,
                effective_rank,
                noise_gain,
                lambda: filter.lambda,
                rank: filter.rank,
                notes,
            },
        })
    }

    /// The instruction set of the per-frame kernel.
    pub fn isa(&self) -> Isa {
        self.isa
    }

    /// Bytes held by the operator `P` and the apply scratch.
    pub fn operator_bytes(&self) -> usize {
        match &self.op {
            Operator::F64 { p, x } => (p.buf.len() + x.buf.len()) * 8,
            Operator::F32 { p, x } => (p.buf.len() + x.buf.len()) * 4,
        }
    }

    /// The same solver with its per-frame arithmetic in `precision`: the operator is
    /// converted (f64 → f32 rounds it; f32 → f64 widens the rounded values), no new
    /// decomposition.
    pub fn with_precision(&self, precision: Precision) -> DenseSolver {
        let (op, stride) = Operator::new(&self.operator(), self.n_out, self.n_in, precision);
        let mut diag = self.diag.clone();
        diag.notes.retain(|n| n != F32_NOTE);
        if precision == Precision::F32 {
            diag.notes.push(F32_NOTE.into());
        }
        DenseSolver {
            op,
            stride,
            diag,
            row_norm: self.row_norm.clone(),
            ..*self
        }
    }

    /// The operator `P` (N/mm), row-major `n_outputs × n_inputs`, widened to f64.
    pub fn operator(&self) -> Vec<f64> {
        let mut out = Vec::with_capacity(self.n_out * self.n_in);
        if self.stride == 0 {
            return out;
        }
        match &self.op {
            Operator::F64 { p, .. } => {
                for row in p.as_slice().chunks_exact(self.stride) {
                    out.extend_from_slice(&row[..self.n_in]);
                }
            }
            Operator::F32 { p, .. } => {
                for row in p.as_slice().chunks_exact(self.stride) {
                    out.extend(row[..self.n_in].iter().map(|&v| v as f64));
                }
            }
        }
        out
    }
}

impl FrameSolver for DenseSolver {
    fn n_inputs(&self) -> usize {
        self.n_in
    }

    fn n_outputs(&self) -> usize {
        self.n_out
    }

    fn apply(&mut self, u_mm: &[f64], f_n: &mut [f64]) -> Result<(), SolveError> {
        check_input(u_mm, self.n_in)?;
        check_output(f_n, self.n_out)?;
        let max_abs = super::max_abs(u_mm);
        if max_abs > self.limit_mm {
            return Err(SolveError::TooLarge {
                max_abs_mm: max_abs,
                limit_mm: self.limit_mm,
            });
        }
        match &mut self.op {
            Operator::F64 { p, x } => {
                // Copied into the aligned, zero-padded scratch (n_in values, ~50 ns).
                x.as_mut_slice()[..self.n_in].copy_from_slice(u_mm);
                kernel::gemv_f64(
                    self.isa,
                    p.as_slice(),
                    self.n_out,
                    self.stride,
                    x.as_slice(),
                    f_n,
                )
            }
            Operator::F32 { p, x } => {
                if max_abs == 0.0 {
                    f_n.fill(0.0);
                    return Ok(());
                }
                // Scale by a power of two (exact) so |x| ≤ 1 fits f32 for any finite u.
                // Clamped so both 2^-e and 2^e stay normal f64 numbers.
                let e = (max_abs.log2().ceil() as i32).clamp(-1000, 1000);
                let down = 2f64.powi(-e);
                for (xi, ui) in x.as_mut_slice().iter_mut().zip(u_mm) {
                    *xi = (ui * down) as f32;
                }
                kernel::gemv_f32(
                    self.isa,
                    p.as_slice(),
                    self.n_out,
                    self.stride,
                    x.as_slice(),
                    f_n,
                );
                let up = 2f64.powi(e);
                for fi in f_n.iter_mut() {
                    *fi *= up;
                }
            }
        }
        Ok(())
    }

    fn diagnostics(&self) -> &Diagnostics {
        &self.diag
    }

    fn force_sd(&self, sigma_mm: f64, out: &mut [f64]) -> Result<(), SolveError> {
        check_sigma(sigma_mm)?;
        check_output(out, self.n_out)?;
        for (o, r) in out.iter_mut().zip(&self.row_norm) {
            *o = r * sigma_mm;
        }
        Ok(())
    }

    fn sum_sd(&self, sigma_mm: f64) -> Result<[f64; 3], SolveError> {
        check_sigma(sigma_mm)?;
        Ok(self.sum_norm.map(|s| s * sigma_mm))
    }
}
