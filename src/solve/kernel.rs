//! Dense matrix–vector kernel `y = A x` for the per-frame apply of the dense solvers.
//!
//! `A` is row-major (`rows × cols`), in `f64` or `f32`; `x` has the element type of
//! `A`, the result is always written as `f64`. Each output is a dot product of a
//! contiguous row with `x`:
//!
//! ```text
//! y_i = Σ_j A[i·cols + j] · x_j
//! ```
//!
//! Why it is written this way: the paper system (`A` is 240 × 520) is 1 MB in f64 and
//! 0.5 MB in f32, so the product streams `A` once from L2 and is bound by load
//! bandwidth, not arithmetic. To keep the load ports busy the kernel
//!
//! - walks two rows at once so each `x` chunk loaded is used twice,
//! - keeps `W` independent partial sums per row (several SIMD registers), which hides
//!   the 4-cycle latency of a fused multiply-add (a single accumulator serialises the
//!   whole row on that latency),
//! - processes columns in fixed-size chunks (`chunks_exact`) with constant-index
//!   inner loops, which LLVM turns into packed SIMD without bounds checks.
//!
//! The same generic body is compiled three times: for AVX-512F (+FMA), for AVX2+FMA
//! (`#[target_feature]`, chosen at run time with `is_x86_feature_detected!`), and a
//! portable version (plain `a*b + c`, SSE2 on x86-64, whatever the target has
//! elsewhere). `f64::mul_add` is only used where FMA is enabled: without it, it would
//! become a slow libm call.
//!
//! Alignment is the caller's business: a 64-byte load that straddles two cache lines
//! costs a second access, so [`super::dense`] stores `A` and `x` from a cache-line
//! boundary with rows zero-padded to whole lines (measured on the paper system: f32
//! 9.5 → 7.7 µs, f64 11.5 → 10.9 µs per product).
//!
//! Summation order differs from a naive loop (partial sums), so results agree with a
//! sequential dot product to rounding (relative `~cols·ε` in the worst case).

use std::ops::{Add, Mul};

/// The instruction set a kernel call uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Isa {
    /// AVX-512F with FMA (x86-64).
    Avx512,
    /// AVX2 with FMA (x86-64).
    Avx2Fma,
    /// Portable code (baseline target features only).
    Portable,
}

impl Isa {
    /// The best instruction set this CPU supports, detected at run time.
    pub fn detect() -> Isa {
        #[cfg(target_arch = "x86_64")]
        {
            if is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("fma") {
                return Isa::Avx512;
            }
            if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
                return Isa::Avx2Fma;
            }
        }
        Isa::Portable
    }

    /// Whether this CPU can run code for this instruction set.
    pub fn is_supported(self) -> bool {
        match self {
            Isa::Portable => true,
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("fma"),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2Fma => is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma"),
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }

    /// Short name (`avx512`, `avx2+fma`, `portable`).
    pub fn name(self) -> &'static str {
        match self {
            Isa::Avx512 => "avx512",
            Isa::Avx2Fma => "avx2+fma",
            Isa::Portable => "portable",
        }
    }
}

/// An element type of the kernel: `f64` or `f32`.
pub trait Element: Copy + Default + Add<Output = Self> + Mul<Output = Self> + Send + Sync {
    /// Fused multiply-add `self·b + c` (only called where FMA is enabled).
    fn fused(self, b: Self, c: Self) -> Self;
    /// Widening to `f64`.
    fn to_f64(self) -> f64;
}

impl Element for f64 {
    #[inline(always)]
    fn fused(self, b: f64, c: f64) -> f64 {
        self.mul_add(b, c)
    }
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self
    }
}

impl Element for f32 {
    #[inline(always)]
    fn fused(self, b: f32, c: f32) -> f32 {
        self.mul_add(b, c)
    }
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self as f64
    }
}

#[inline(always)]
fn madd<T: Element, const FMA: bool>(a: T, b: T, c: T) -> T {
    if FMA {
        a.fused(b, c)
    } else {
        a * b + c
    }
}

/// Pairwise (tree) sum of the partial sums, in `T`, then widened.
#[inline(always)]
fn reduce<T: Element, const W: usize>(mut acc: [T; W]) -> f64 {
    let mut n = W;
    while n > 1 {
        let h = n / 2;
        for k in 0..h {
            acc[k] = acc[k] + acc[k + h];
        }
        if n % 2 == 1 {
            acc[0] = acc[0] + acc[n - 1];
        }
        n = h;
    }
    acc[0].to_f64()
}

/// Dot product of one row with `x`: `W` partial sums (several SIMD registers), main
/// loop over `chunks_exact(W)`, the `cols % W` tail one by one.
#[inline(always)]
fn dot1<T: Element, const FMA: bool, const W: usize>(a: &[T], x: &[T]) -> f64 {
    let mut acc = [T::default(); W];
    let ac = a.chunks_exact(W);
    let xc = x.chunks_exact(W);
    let (at, xt) = (ac.remainder(), xc.remainder());
    for (a, x) in ac.zip(xc) {
        for k in 0..W {
            acc[k] = madd::<T, FMA>(a[k], x[k], acc[k]);
        }
    }
    for (k, (&a, &x)) in at.iter().zip(xt).enumerate() {
        acc[k] = madd::<T, FMA>(a, x, acc[k]);
    }
    reduce::<T, W>(acc)
}

/// Two rows at once: each chunk of `x` loaded once is used twice (the kernel is bound
/// by loads), `2·W` partial sums in flight.
#[inline(always)]
fn dot2<T: Element, const FMA: bool, const W: usize>(a0: &[T], a1: &[T], x: &[T]) -> [f64; 2] {
    let mut acc0 = [T::default(); W];
    let mut acc1 = [T::default(); W];
    let c0 = a0.chunks_exact(W);
    let c1 = a1.chunks_exact(W);
    let cx = x.chunks_exact(W);
    let (t0, t1, tx) = (c0.remainder(), c1.remainder(), cx.remainder());
    for ((r0, r1), xc) in c0.zip(c1).zip(cx) {
        for k in 0..W {
            acc0[k] = madd::<T, FMA>(r0[k], xc[k], acc0[k]);
            acc1[k] = madd::<T, FMA>(r1[k], xc[k], acc1[k]);
        }
    }
    for (k, ((&p0, &p1), &xv)) in t0.iter().zip(t1).zip(tx).enumerate() {
        acc0[k] = madd::<T, FMA>(p0, xv, acc0[k]);
        acc1[k] = madd::<T, FMA>(p1, xv, acc1[k]);
    }
    [reduce::<T, W>(acc0), reduce::<T, W>(acc1)]
}

/// The full product: pairs of rows, then the odd row left over.
#[inline(always)]
fn gemv_body<T: Element, const FMA: bool, const W: usize>(
    a: &[T],
    rows: usize,
    cols: usize,
    x: &[T],
    y: &mut [f64],
) {
    if cols == 0 {
        y.fill(0.0);
        return;
    }
    let mut pairs = a.chunks_exact(2 * cols);
    let mut yp = y.chunks_exact_mut(2);
    for (ab, yb) in (&mut pairs).zip(&mut yp) {
        let (a0, a1) = ab.split_at(cols);
        let r = dot2::<T, FMA, W>(a0, a1, x);
        yb[0] = r[0];
        yb[1] = r[1];
    }
    if rows % 2 == 1 {
        y[rows - 1] = dot1::<T, FMA, W>(pairs.remainder(), x);
    }
}

// Widths W: four vectors of partial sums per row (AVX-512: 4×8 f64 / 4×16 f32; AVX2:
// 4×4 / 4×8; SSE2: 4×2 / 4×4), so eight independent chains for the two rows: enough to
// cover the 4-cycle FMA latency on two ports.

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn gemv_f64_avx512(a: &[f64], rows: usize, cols: usize, x: &[f64], y: &mut [f64]) {
    gemv_body::<f64, true, 32>(a, rows, cols, x, y)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn gemv_f32_avx512(a: &[f32], rows: usize, cols: usize, x: &[f32], y: &mut [f64]) {
    gemv_body::<f32, true, 64>(a, rows, cols, x, y)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn gemv_f64_avx2(a: &[f64], rows: usize, cols: usize, x: &[f64], y: &mut [f64]) {
    gemv_body::<f64, true, 16>(a, rows, cols, x, y)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn gemv_f32_avx2(a: &[f32], rows: usize, cols: usize, x: &[f32], y: &mut [f64]) {
    gemv_body::<f32, true, 32>(a, rows, cols, x, y)
}

fn gemv_f64_portable(a: &[f64], rows: usize, cols: usize, x: &[f64], y: &mut [f64]) {
    gemv_body::<f64, false, 8>(a, rows, cols, x, y)
}

fn gemv_f32_portable(a: &[f32], rows: usize, cols: usize, x: &[f32], y: &mut [f64]) {
    gemv_body::<f32, false, 16>(a, rows, cols, x, y)
}

/// Checks the shapes shared by both entry points.
fn check_shapes(a_len: usize, rows: usize, cols: usize, x_len: usize, y_len: usize) {
    assert_eq!(
        Some(a_len),
        rows.checked_mul(cols),
        "matrix is not rows × cols"
    );
    assert_eq!(x_len, cols, "x length differs from cols");
    assert_eq!(y_len, rows, "y length differs from rows");
}

/// `y = A x` in f64 with the given instruction set (falls back to portable code if the
/// CPU lacks it).
///
/// # Panics
/// If `a.len() != rows·cols`, `x.len() != cols` or `y.len() != rows` (callers check
/// lengths of user data before calling).
pub fn gemv_f64(isa: Isa, a: &[f64], rows: usize, cols: usize, x: &[f64], y: &mut [f64]) {
    check_shapes(a.len(), rows, cols, x.len(), y.len());
    match isa {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: the CPU supports the features the function is compiled for.
        Isa::Avx512 if isa.is_supported() => unsafe { gemv_f64_avx512(a, rows, cols, x, y) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: as above.
        Isa::Avx2Fma if isa.is_supported() => unsafe { gemv_f64_avx2(a, rows, cols, x, y) },
        _ => gemv_f64_portable(a, rows, cols, x, y),
    }
}

/// `y = A x` with `A` and `x` in f32, accumulated in f32 per partial sum and widened
/// to f64 for the final sum and the output.
///
/// # Panics
/// As [`gemv_f64`].
pub fn gemv_f32(isa: Isa, a: &[f32], rows: usize, cols: usize, x: &[f32], y: &mut [f64]) {
    check_shapes(a.len(), rows, cols, x.len(), y.len());
    match isa {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: the CPU supports the features the function is compiled for.
        Isa::Avx512 if isa.is_supported() => unsafe { gemv_f32_avx512(a, rows, cols, x, y) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: as above.
        Isa::Avx2Fma if isa.is_supported() => unsafe { gemv_f32_avx2(a, rows, cols, x, y) },
        _ => gemv_f32_portable(a, rows, cols, x, y),
    }
}

#[cfg(test)]
mod tests {
    //! Every instruction set against a sequential f64 dot product, over shapes that
    //! exercise the row blocking and all three column tails.
    use super::*;

    fn lcg(state: &mut u64) -> f64 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*state >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    fn reference(a: &[f64], rows: usize, cols: usize, x: &[f64]) -> Vec<f64> {
        (0..rows)
            .map(|i| (0..cols).map(|j| a[i * cols + j] * x[j]).sum())
            .collect()
    }

    const SHAPES: [(usize, usize); 9] = [
        (1, 1),
        (3, 7),
        (5, 33),
        (4, 64),
        (7, 95),
        (9, 130),
        (240, 520),
        (2, 0),
        (0, 5),
    ];

    #[test]
    fn every_isa_matches_sequential_dot_products_in_f64_and_f32() {
        let mut s = 42u64;
        for isa in [Isa::Avx512, Isa::Avx2Fma, Isa::Portable] {
            for &(rows, cols) in &SHAPES {
                let a: Vec<f64> = (0..rows * cols).map(|_| lcg(&mut s)).collect();
                let x: Vec<f64> = (0..cols).map(|_| lcg(&mut s)).collect();
                let want = reference(&a, rows, cols, &x);
                let mut y = vec![f64::NAN; rows];
                gemv_f64(isa, &a, rows, cols, &x, &mut y);
                // |terms| ≤ 1: rounding error of any summation order ≤ cols·ε.
                let tol64 = 1e-15 * (cols as f64 + 1.0);
                for (g, w) in y.iter().zip(&want) {
                    assert!((g - w).abs() <= tol64, "{isa:?} {rows}x{cols}: {g} vs {w}");
                }
                let a32: Vec<f32> = a.iter().map(|&v| v as f32).collect();
                let x32: Vec<f32> = x.iter().map(|&v| v as f32).collect();
                let mut y = vec![f64::NAN; rows];
                gemv_f32(isa, &a32, rows, cols, &x32, &mut y);
                // f32 inputs (rel. 6e-8 each) and f32 partial sums: ≤ 2·cols·6e-8.
                let tol32 = 1.2e-7 * (cols as f64 + 1.0);
                for (g, w) in y.iter().zip(&want) {
                    assert!(
                        (g - w).abs() <= tol32,
                        "{isa:?} f32 {rows}x{cols}: {g} vs {w}"
                    );
                }
            }
        }
    }

    #[test]
    fn detected_isa_is_supported() {
        assert!(Isa::detect().is_supported());
        assert!(Isa::Portable.is_supported());
    }
}
