//! The bonded layer: an elastic layer of thickness `h` whose free surface (z = 0) carries
//! the traction and whose bottom face (z = h) is bonded to a rigid plate (u = 0).
//!
//! # Solution in Fourier space
//!
//! Transform in the surface plane, `p̂(k) = ∫ p(x) e^{−i k·x} d²x`,
//! `u(x) = (2π)^{−2} ∫ û(k) e^{i k·x} d²k`; for each wave vector `k = |k| k̂` the
//! Navier equations become ODEs in z. In the frame of `k̂` (longitudinal `l` along
//! `k̂`, transverse `t = e_z × k̂`) the transverse (antiplane) problem decouples:
//! `μ(u_t'' − k²u_t) = 0`, `μ u_t'(0) = −p_t`, `u_t(h) = 0`, so
//!
//! ```text
//! G_tt = sinh(k(h−z)) / (μ k cosh(kh)) = (e^{−s} − e^{−(2t−s)}) / (μ k (1+q)),
//! s = kz, t = kh, q = e^{−2t}.
//! ```
//!
//! The in-plane (`l`, z) problem uses the Papkovich–Neuber form (Barber, *Elasticity*,
//! ch. 20; Johnson §3.2) for the mode `e^{ikx}`:
//! `2μ u = ∇(φ + zψ) − 4(1−ν) ψ e_z` with harmonic `φ = A e^{−kz} + B e^{−k(2h−z)}`,
//! `ψ = C e^{−kz} + D e^{−k(2h−z)}` (both exponentials normalised so that every term
//! is bounded for 0 ≤ z ≤ h). Then, with `κ = 3 − 4ν`,
//!
//! ```text
//! 2μ u_x = ik(φ + zψ),   2μ u_z = φ' + zψ' − κψ,
//! σ_xz = ik(φ' + zψ' − (1−2ν)ψ),   σ_zz = φ'' + zψ'' − 2(1−ν)ψ',
//! ```
//!
//! (the Lamé term `λ div u = −2νψ'` has been eliminated, which is why every formula
//! here stays finite at ν = 0.5, κ = 1). The surface z = 0 has outward normal −e_z, so
//! the applied traction `p` gives `σ_iz(0) = −p_i` (`f_z > 0` presses into the
//! elastomer); the bond gives `u(h) = 0`. Writing `α = kA`, `β = kB`, `γ = C`,
//! `δ = D`, the four conditions solve in closed form with the determinant
//!
//! ```text
//! N = κ + q(1 + κ²) + q²κ + 4 q t²        (> 0 for every k, ν ∈ [0, 0.5])
//! ```
//!
//! (`N/q = 2κ cosh 2t + 1 + κ² + 4t²`, the classical denominator of the bonded layer).
//! Per unit traction along `l` (factor `i/k`) and along z (factor `1/k`):
//!
//! ```text
//! N γ_l = κ + q + 2qt                 N γ_z = −(κ + q − 2qt)
//! N δ_l = 1 + qκ − 2t                 N δ_z = 1 + qκ + 2t
//! N α_l = −[κ(κ+1)(1+q)/2 + (1+κ)qt + 2qt²]
//! N β_l =   κ(κ+1)(1+q)/2 − (κ+1)t + 2t²
//! N α_z = (1−κ)qt − 2qt² − κ(1−κ)(1−q)/2
//! N β_z = κ(1−κ)(1−q)/2 + (κ−1)t − 2t²
//! X_j(s) =  (α_j + sγ_j) e^{−s} + (β_j + sδ_j) e^{−(2t−s)}
//! Z_j(s) = −(α_j + (s+κ)γ_j) e^{−s} + (β_j + (s−κ)δ_j) e^{−(2t−s)}
//! ```
//!
//! and the scalar kernels (mm/N·mm², i.e. û per unit p̂):
//!
//! ```text
//! û_l = G_ll p_l + i g_lz p_z,   û_z = i g_zl p_l + G_zz p_z,   û_t = G_tt p_t,
//! G_ll = −X_l/(2μk),  g_lz = X_z/(2μk),  g_zl = Z_l/(2μk),  G_zz = Z_z/(2μk).
//! ```
//!
//! With q → 0 (h → ∞) these become the half-space kernels
//! `G_ll = (2(1−ν) − s)e^{−s}/(2μk)`, `G_tt = e^{−s}/(μk)`,
//! `g_lz = (1−2ν − s)e^{−s}/(2μk)`, `g_zl = −(1−2ν + s)e^{−s}/(2μk)`,
//! `G_zz = (2(1−ν) + s)e^{−s}/(2μk)`, whose inverse transforms are exactly paper
//! Eq. 1–2 and the `u_z` of [`super::half_space`] (tested). Unlike the half-space's,
//! the layer's kernels are finite at k = 0, the uniform-traction layer:
//! `G_ll = G_tt = (h−z)/μ`, `G_zz = (h−z)(1−2ν)/(2μ(1−ν))`, `g_lz = g_zl = 0`. The
//! closed forms lose `≈ ε/(kh)` relative accuracy to cancellation as kh → 0, so below
//! kh = [`SERIES_BELOW_KH`] their Taylor series in `t = kh` (at fixed `ζ = z/h`, to
//! `t²` for `G_ll, G_tt, G_zz` and `t³` for `g_lz, g_zl`; no cancellation, exact at
//! k = 0) is used; `G_tt = (h−z)/μ · (1 + t²(ζ² − 2ζ − 2)/6)` is the simplest term.
//! Tested against 60-digit evaluations of the closed forms (mpmath) to 1e−12. In the lab frame
//! ([`layer_kernel3`]): `K_ab = G_tt δ_ab + (G_ll − G_tt) k̂_a k̂_b`,
//! `K_az = i g_lz k̂_a`, `K_zb = i g_zl k̂_b`, `K_zz = G_zz` (a, b ∈ {x, y}).
//!
//! The same layer problem is solved in finite-thickness traction force microscopy:
//! del Álamo et al., PNAS 104 (2007) 13343 (supplement); Trepat et al., Nat. Phys. 5
//! (2009) 426 (supplementary note); Xu et al., Biophys. J. 98 (2010) 2008; del Álamo
//! et al., PLoS ONE 8 (2013) e69850. The formulas above were derived here and are
//! checked by the tests below (boundary conditions by finite differences of the
//! kernels, incompressibility at ν = 0.5, the h → ∞ limit) and against an independent
//! numerical solution of the ODE system (`tests/numpy_ref/layer_check.py`).
//!
//! # Real space
//!
//! For a point force, `û = K f`. Axisymmetry reduces the inverse transform to Hankel
//! integrals `I_n[F](ρ) = (2π)^{−1} ∫₀^∞ F(k) J_n(kρ) k dk`:
//!
//! ```text
//! u_a/f_b = δ_ab I₀[(G_ll+G_tt)/2] − (ê_a ê_b − δ_ab/2) I₂[G_ll − G_tt]
//! u_a/f_z = −ê_a I₁[g_lz],   u_z/f_b = −ê_b I₁[g_zl],   u_z/f_z = I₀[G_zz]
//! ```
//!
//! with `ê = (dx, dy)/ρ`. The layer response is written as the closed-form half-space
//! response plus a correction whose kernels `ΔG = G_layer − G_half` are smooth in k and
//! decay like `t² e^{−k(2h−z)}`; the correction is integrated numerically once per
//! (material, thickness, depth): composite 16-point Gauss–Legendre on `[0, 60/(2h−z)]`
//! with panels no wider than `min(2/(2h−z), 3/ρ_max)` (≤ half a Bessel period), own
//! J₀/J₁/J₂ (power series below x = 14, Hankel's asymptotic expansion above; absolute
//! error < 1e−11), tabulated on `ρ = 0, Δρ, …` with `Δρ = (2h−z)/40` and interpolated
//! with 4-point Lagrange cubics (using the parity of `I_n` in ρ below the first node).
//! The correction field varies on the scale `2h − z ≥ h`, so the interpolation error is
//! ~(1/40)⁴ of it; the tests measure the table against a 4× finer direct quadrature
//! (relative to the peak response) and the Hankel machinery against Eq. 1–2.
//! Tables are cached process-wide (keyed by E, ν, h, depth) and grow when a larger
//! distance is asked for, so building `H` twice costs one table build.
//!
//! # The half-space's error in the paper's 40 mm layer (issue 14's FEM figures)
//!
//! Issue 14 quotes an independent FEM (ν = 0.49, 40 mm layer, markers at 3 / 6 mm): the
//! half-space's error in the horizontal displacement, as a share of its peak, is
//! 2.0 % / 3.2 % (normal load) and 6.9 % / 13.6 % (tangential load); measured here first
//! as 4.4 % / 6.9 % for the normal load. The kernel is not wrong: the figures depend on
//! the definition, and one definition reproduces all four FEM figures to the quoted
//! digit. Figures (max |u_x,layer − u_x,half| / max |u_x,half| along the load's line,
//! z = 3 / 6 mm, %; the test `paper_layer_half_space_error_reproduces_the_fem_figures`
//! and an independent NumPy Hankel quadrature of the same kernels agree):
//!
//! | load, ν = 0.49 | reach 5 mm | 10 mm | 20 mm | 40 mm |
//! |---|---|---|---|---|
//! | point, normal | 1.0 / 1.7 | **2.0 / 3.2** | 3.5 / 5.7 | 4.4 / 7.0 |
//! | point, tangential | 6.9 / 13.6 | **6.9 / 13.6** | 6.9 / 13.6 | 6.9 / 13.6 |
//! | Gaussian σ = 2 mm, normal / tangential | 1.9 / 2.1, 8.3 / 14.6 | 3.6 / 4.0, 8.3 / 14.6 | 6.4 / 7.0, 8.3 / 14.6 | 8.1 / 8.7, 8.3 / 14.6 |
//! | flat punch ⌀ 5 mm, normal / tangential | 1.5 / 1.9, 7.9 / 14.2 | 3.0 / 3.7, 7.9 / 14.2 | 5.2 / 6.4, 7.9 / 14.2 | 6.6 / 8.0, 7.9 / 14.2 |
//!
//! - **Reach** (the cause): the normal load's error grows with distance from the load
//!   (the plate's image field, ∝ ρ/h near the load) while its u_x decays, so the figure
//!   depends on how far out one looks; 10 mm (the half-width of the paper's
//!   19.8 × 15.4 mm force grid around a centred load) gives the FEM's 2.0 / 3.2 %,
//!   40 mm our earlier 4.4 / 7.0 %. The tangential error peaks under the load, so its
//!   figure does not depend on the reach.
//! - **Normalisation**: dividing by the layer's own peak instead of the half-space's
//!   gives 4.4 / 6.9 % (normal, 40 mm; the earlier figure) and 7.5 / 15.7 %
//!   (tangential), which does not match: the FEM divides by the half-space's peak.
//! - **Metric**: RMS instead of max over 10 mm gives 1.2 / 1.9 % and 6.9 / 13.5 %.
//! - **Load shape**: distributed loads raise the tangential figure to 7.7–8.3 % at
//!   3 mm (uniform disc ⌀ 5 mm 7.7 / 14.1 %), so the FEM's load was concentrated
//!   (point-like at these depths).
//! - **ν**: 0.5 instead of 0.49 changes the point-load figures by ≤ 0.1 point
//!   (2.0 / 3.2 % and 6.9 / 13.6 % at 10 mm; 4.3 / 6.9 % at 40 mm).

use std::collections::HashMap;
use std::f64::consts::PI;
use std::sync::{Arc, Mutex, OnceLock};

use rustfft::num_complex::Complex64;

use super::{ElasticModel, HalfSpace, ModelError, PointResponse3};

/// An elastic layer of finite thickness bonded to a rigid plate at z = h.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BondedLayer {
    /// Poisson ratio ν in [0, 0.5].
    pub poisson: f64,
    /// Young's modulus E in N/mm².
    pub young_n_per_mm2: f64,
    /// Thickness h in mm (the rigid plate's face).
    pub thickness_mm: f64,
}

/// The five scalar kernels of one wave number in the frame of the wave vector (see
/// the module docs): `û_l = ll p_l + i lz p_z`, `û_t = tt p_t`,
/// `û_z = i zl p_l + zz p_z`. Unit: mm/N · mm² (displacement per unit traction
/// transform).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LayerKernels {
    /// Longitudinal displacement per longitudinal traction, `G_ll`.
    pub ll: f64,
    /// Transverse per transverse, `G_tt`.
    pub tt: f64,
    /// Longitudinal per normal traction, `g_lz` (the kernel is `i g_lz`).
    pub lz: f64,
    /// Vertical per longitudinal traction, `g_zl` (the kernel is `i g_zl`).
    pub zl: f64,
    /// Vertical per normal traction, `G_zz`.
    pub zz: f64,
}

impl LayerKernels {
    fn sub(self, o: LayerKernels) -> LayerKernels {
        LayerKernels {
            ll: self.ll - o.ll,
            tt: self.tt - o.tt,
            lz: self.lz - o.lz,
            zl: self.zl - o.zl,
            zz: self.zz - o.zz,
        }
    }
}

/// The scalar kernels at wave number `k` (rad/mm, ≥ 0), depth `z` (mm), thickness `h`
/// (mm; `f64::INFINITY` gives the half-space), Young's modulus `young` (N/mm²) and
/// Poisson ratio `nu` (finite at 0.5). The half-space is singular at k = 0 (returns
/// non-finite values there); the layer has a finite limit.
pub fn scalar_kernels(k: f64, z: f64, h: f64, young: f64, nu: f64) -> LayerKernels {
    let mu = young / (2.0 * (1.0 + nu));
    let kappa = 3.0 - 4.0 * nu;
    let s = k * z;
    let c = 1.0 / (2.0 * mu * k);
    if h.is_infinite() {
        let e = (-s).exp();
        return LayerKernels {
            ll: (2.0 * (1.0 - nu) - s) * e * c,
            tt: 2.0 * e * c,
            lz: (1.0 - 2.0 * nu - s) * e * c,
            zl: -(1.0 - 2.0 * nu + s) * e * c,
            zz: (2.0 * (1.0 - nu) + s) * e * c,
        };
    }
    let t = k * h;
    if t < SERIES_BELOW_KH {
        return small_kh_series(t, z / h, h, mu, kappa);
    }
    let q = (-2.0 * t).exp();
    let ea = (-s).exp();
    let eb = (-(2.0 * t - s)).exp();
    let n = kappa + q * (1.0 + kappa * kappa) + q * q * kappa + 4.0 * q * t * t;
    let kk = kappa * (kappa + 1.0) * (1.0 + q) / 2.0;
    let gl = (kappa + q + 2.0 * q * t) / n;
    let dl = (1.0 + q * kappa - 2.0 * t) / n;
    let al = -(kk + (1.0 + kappa) * q * t + 2.0 * q * t * t) / n;
    let bl = (kk - (kappa + 1.0) * t + 2.0 * t * t) / n;
    let kz = kappa * (1.0 - kappa) * (1.0 - q) / 2.0;
    let gz = -(kappa + q - 2.0 * q * t) / n;
    let dz = (1.0 + q * kappa + 2.0 * t) / n;
    let az = ((1.0 - kappa) * q * t - 2.0 * q * t * t - kz) / n;
    let bz = (kz + (kappa - 1.0) * t - 2.0 * t * t) / n;
    let x = |a: f64, g: f64, b: f64, d: f64| (a + s * g) * ea + (b + s * d) * eb;
    let zf =
        |a: f64, g: f64, b: f64, d: f64| -(a + (s + kappa) * g) * ea + (b + (s - kappa) * d) * eb;
    LayerKernels {
        ll: -x(al, gl, bl, dl) * c,
        tt: (ea - eb) / (mu * k * (1.0 + q)),
        lz: x(az, gz, bz, dz) * c,
        zl: zf(al, gl, bl, dl) * c,
        zz: zf(az, gz, bz, dz) * c,
    }
}

/// Below this `kh` [`scalar_kernels`] uses its Taylor series (module docs): the closed
/// form loses about `ε/kh` to cancellation there (1e-12 at kh = 1e-4), the series'
/// first neglected terms are `O((kh)⁴)` (6e-14 at the switch).
pub const SERIES_BELOW_KH: f64 = 5e-4;

/// The kernels for `t = kh` below [`SERIES_BELOW_KH`]: the Taylor series in `t` of the
/// closed forms at fixed `ζ = z/h` (computed with SymPy from the formulas of the module
/// docs), even kernels to `t²`, odd ones to `t³`. At t = 0 this is the uniform-traction
/// limit: `G_ll = G_tt = (h−z)/μ`, `G_zz = (h−z)(1−2ν)/(2μ(1−ν))`, `g_lz = g_zl = 0`.
fn small_kh_series(t: f64, zeta: f64, h: f64, mu: f64, kappa: f64) -> LayerKernels {
    let (w, z, k) = (1.0 - zeta, zeta, kappa);
    let (z2, z3, k1) = (z * z, z * z * z, kappa + 1.0);
    let t2 = t * t;
    let pref = h / (2.0 * mu);
    let ll3 = w * (k * z2 - 2.0 * k * z + 4.0 * k + 3.0 * z2 - 12.0 * z - 24.0) / (3.0 * k1);
    let tt3 = w * (z2 - 2.0 * z - 2.0) / 3.0;
    let lz2 = 2.0 * w * (k - z - 2.0) / k1;
    let lz4 = w
        * (k * k * z2 - 2.0 * k * k * z + 2.0 * k * k - k * z3 + 3.0 * k * z2
            - 6.0 * k * z
            - 26.0 * k
            - z3
            - 6.0 * z2
            + 24.0 * z
            + 48.0)
        / (3.0 * k1 * k1);
    let zl2 = -2.0 * w * (k + z - 2.0) / k1;
    let zl4 = -w
        * (k * k * z2 - 2.0 * k * k * z + 2.0 * k * k + k * z3 - 5.0 * k * z2 + 10.0 * k * z
            - 26.0 * k
            + z3
            - 6.0 * z2
            - 24.0 * z
            + 48.0)
        / (3.0 * k1 * k1);
    let zz1 = 2.0 * (k - 1.0) * w / k1;
    let zz3 =
        (k - 3.0) * w * (k * z2 - 2.0 * k * z + 4.0 * k + z2 + 4.0 * z - 8.0) / (3.0 * k1 * k1);
    LayerKernels {
        ll: pref * (2.0 * w + ll3 * t2),
        tt: pref * (2.0 * w + tt3 * t2),
        lz: pref * t * (lz2 + lz4 * t2),
        zl: pref * t * (zl2 + zl4 * t2),
        zz: pref * (zz1 + zz3 * t2),
    }
}

/// The layer's frequency-space kernel with the vertical row: `K[a][b]` (a ∈ x, y, z;
/// b ∈ x, y, z) such that `û(k, z) = K p̂(k)` for the wave vector `(kx, ky)` (rad/mm),
/// depth `z` (mm, 0 ≤ z ≤ h), thickness `h` (mm; `f64::INFINITY` = half-space),
/// Young's modulus `young` (N/mm²) and Poisson ratio `nu`. Conventions of the module
/// docs: `p̂(k) = ∫ p(x) e^{−i k·x} d²x`, `u(x) = (2π)^{−2} ∫ û(k) e^{i k·x} d²k`;
/// z positive into the elastomer, `p_z > 0` presses in. Unit: mm/N · mm².
pub fn layer_kernel3(kx: f64, ky: f64, z: f64, h: f64, young: f64, nu: f64) -> [[Complex64; 3]; 3] {
    let k = kx.hypot(ky);
    let g = scalar_kernels(k, z, h, young, nu);
    let (ex, ey) = if k > 0.0 {
        (kx / k, ky / k)
    } else {
        (0.0, 0.0)
    };
    let e = [ex, ey];
    let re = |v: f64| Complex64::new(v, 0.0);
    let im = |v: f64| Complex64::new(0.0, v);
    let mut out = [[re(0.0); 3]; 3];
    for a in 0..2 {
        for b in 0..2 {
            let d = if a == b { g.tt } else { 0.0 };
            out[a][b] = re(d + (g.ll - g.tt) * e[a] * e[b]);
        }
        out[a][2] = im(g.lz * e[a]);
        out[2][a] = im(g.zl * e[a]);
    }
    out[2][2] = re(g.zz);
    out
}

/// The layer's frequency-space kernel for the horizontal displacements (the 2 × 3
/// matrix a Fourier solver inverts): rows u_x, u_y; columns p_x, p_y, p_z. See
/// [`layer_kernel3`] for the conventions.
pub fn layer_kernel(kx: f64, ky: f64, z: f64, h: f64, young: f64, nu: f64) -> [[Complex64; 3]; 2] {
    let k = layer_kernel3(kx, ky, z, h, young, nu);
    [k[0], k[1]]
}

impl BondedLayer {
    /// A layer with the given constants, checked (E > 0 N/mm², ν ∈ [0, 0.5],
    /// 0 < h < ∞ mm).
    pub fn new(young_n_per_mm2: f64, poisson: f64, thickness_mm: f64) -> Result<Self, ModelError> {
        HalfSpace::new(young_n_per_mm2, poisson)?;
        if !(thickness_mm.is_finite() && thickness_mm > 0.0) {
            return Err(ModelError::BadThickness { thickness_mm });
        }
        Ok(BondedLayer {
            poisson,
            young_n_per_mm2,
            thickness_mm,
        })
    }

    /// The half-space of the same material.
    pub fn half_space(&self) -> HalfSpace {
        HalfSpace {
            poisson: self.poisson,
            young_n_per_mm2: self.young_n_per_mm2,
        }
    }

    /// The scalar kernels of this layer at wave number `k` and depth `z`.
    pub fn kernels(&self, k: f64, z: f64) -> LayerKernels {
        scalar_kernels(k, z, self.thickness_mm, self.young_n_per_mm2, self.poisson)
    }

    /// Response with the vertical row at offset `(dx, dy)` mm and depth `0 < z ≤ h`
    /// mm (mm/N): the closed-form half-space response plus the tabulated correction.
    ///
    /// A table past [`MAX_TABLE_EVALUATIONS`] / [`MAX_TABLE_BYTES`] is never built:
    /// callers check the geometry first ([`Self::check_reach`]; every `model` entry
    /// point — `transfer_matrix`, `forward`, `forward3` — and the Fourier kernels do),
    /// and an unchecked call beyond the cap answers NaN rather than allocating
    /// without bound.
    pub fn point_response3(&self, dx: f64, dy: f64, z: f64) -> PointResponse3 {
        let mut r = self.half_space().point_response3(dx, dy, z);
        let rho = dx.hypot(dy);
        match self.table(z, rho) {
            Some(table) => add_correction(&mut r, dx, dy, rho, table.eval(rho)),
            None => r = [[f64::NAN; 3]; 3],
        }
        r
    }

    /// The work and memory of the correction table for depth `z` covering distances
    /// up to `rho` mm, computed from the geometry alone (nothing is allocated). The
    /// table grid spacing scales with `2h − z` and its quadrature with `1/(2h − z)`,
    /// so the cost grows like `(ρ / (2h − z))²`: a layer much thinner than the
    /// marker–force-point distances is refused by [`Self::check_reach`].
    pub fn table_size(&self, z: f64, rho: f64) -> TableSize {
        let rho_max = table_reach(self.thickness_mm, rho);
        let a = 2.0 * self.thickness_mm - z;
        let drho = (a / 40.0).min(rho_max / 8.0);
        let rows = (rho_max / drho).ceil() + 3.0;
        let w = (2.0 / a).min(3.0 / (rows * drho));
        let nodes = 16.0 * ((60.0 / a) / w).ceil().max(1.0);
        TableSize {
            rows,
            nodes,
            evaluations: rows * nodes,
            bytes: rows * 40.0 + nodes * 48.0,
        }
    }

    /// Checks that the tables for these marker depths and horizontal distances up to
    /// `rho_max_mm` stay within [`MAX_TABLE_EVALUATIONS`] and [`MAX_TABLE_BYTES`]
    /// (a few seconds, well under 1 GB), before anything is allocated. The error
    /// names the thickness, the depth, the distance, the cost and the largest
    /// distance this layer allows.
    pub fn check_reach(&self, depths_mm: &[f64], rho_max_mm: f64) -> Result<(), ModelError> {
        for &z in depths_mm {
            if !(z.is_finite() && z > 0.0 && z <= self.thickness_mm) {
                continue;
            }
            let size = self.table_size(z, rho_max_mm);
            if size.within_limits() {
                continue;
            }
            // The largest distance this layer and depth allow (the cost grows with ρ).
            let (mut lo, mut hi) = (0.0f64, rho_max_mm.max(1e-300));
            for _ in 0..200 {
                let mid = 0.5 * (lo + hi);
                if self.table_size(z, mid).within_limits() {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            return Err(ModelError::LayerTooThin {
                thickness_mm: self.thickness_mm,
                depth_mm: z,
                reach_mm: rho_max_mm,
                evaluations: size.evaluations,
                bytes: size.bytes,
                max_reach_mm: lo,
            });
        }
        Ok(())
    }

    /// The correction `I_n[ΔG]` at distance `rho` computed directly (no table), with
    /// `refine` times more quadrature panels than the table uses. For tests and
    /// accuracy statements.
    pub fn correction_direct(&self, z: f64, rho: f64, refine: usize) -> [f64; 5] {
        let nodes = self.nodes(z, rho.max(1.0), refine.max(1));
        hankel_sum(&nodes, rho)
    }

    /// The response from [`Self::correction_direct`] instead of the table.
    pub fn point_response3_direct(
        &self,
        dx: f64,
        dy: f64,
        z: f64,
        refine: usize,
    ) -> PointResponse3 {
        let mut r = self.half_space().point_response3(dx, dy, z);
        let rho = dx.hypot(dy);
        let v = self.correction_direct(z, rho, refine);
        add_correction(&mut r, dx, dy, rho, v);
        r
    }

    /// Quadrature nodes: `(k, [weights · k/(2π) · ΔG components])`.
    fn nodes(&self, z: f64, rho_max: f64, refine: usize) -> Vec<(f64, [f64; 5])> {
        let h = self.thickness_mm;
        let a = 2.0 * h - z;
        let kmax = 60.0 / a;
        let w = (2.0 / a).min(3.0 / rho_max) / refine as f64;
        let panels = (kmax / w).ceil().max(1.0) as usize;
        let (x, wt) = gauss_legendre_16();
        let mut out = Vec::with_capacity(panels * 16);
        for p in 0..panels {
            let k0 = p as f64 * w;
            for i in 0..16 {
                let k = k0 + 0.5 * w * (x[i] + 1.0);
                let wk = 0.5 * w * wt[i] * k / (2.0 * PI);
                let d = self.kernels(k, z).sub(scalar_kernels(
                    k,
                    z,
                    f64::INFINITY,
                    self.young_n_per_mm2,
                    self.poisson,
                ));
                out.push((
                    k,
                    [
                        wk * 0.5 * (d.ll + d.tt),
                        wk * (d.ll - d.tt),
                        wk * d.lz,
                        wk * d.zl,
                        wk * d.zz,
                    ],
                ));
            }
        }
        out
    }

    fn key(&self, z: f64) -> [u64; 4] {
        [
            self.young_n_per_mm2.to_bits(),
            self.poisson.to_bits(),
            self.thickness_mm.to_bits(),
            z.to_bits(),
        ]
    }

    /// The cached table for depth `z` covering `rho`, built or grown as needed;
    /// `None` (nothing built) when such a table would exceed the caps.
    fn table(&self, z: f64, rho: f64) -> Option<Arc<Table>> {
        let key = self.key(z);
        let cache = TABLES.get_or_init(|| Mutex::new(HashMap::new()));
        if let Some(t) = lock(cache).get(&key) {
            if rho <= t.rho_max {
                return Some(Arc::clone(t));
            }
        }
        if !self.table_size(z, rho).within_limits() {
            return None;
        }
        // Built outside the lock: other depths stay usable meanwhile.
        let t = Arc::new(Table::build(self, z, table_reach(self.thickness_mm, rho)));
        let mut map = lock(cache);
        let entry = map.entry(key).or_insert_with(|| Arc::clone(&t));
        if entry.rho_max < t.rho_max {
            *entry = Arc::clone(&t);
        }
        Some(Arc::clone(entry))
    }
}

/// Most Bessel-function evaluations one correction table may take (rows ×
/// quadrature nodes; about 0.1 µs each, so a few seconds per marker depth). The
/// paper's 40 mm layer needs ~1e5 per depth, a 3 mm layer over the paper's 20 × 15 mm
/// grid ~1e6; this cap refuses layers thinner than about 1/50 of the largest
/// marker–force-point distance (0.1 mm: 1e9 evaluations, ~100 s; 1 µm: 1e19).
pub const MAX_TABLE_EVALUATIONS: f64 = 3e7;

/// Most memory one correction table may take (rows and quadrature nodes), bytes.
pub const MAX_TABLE_BYTES: f64 = 256.0 * 1024.0 * 1024.0;

/// The size of one correction table, computed before it is built
/// ([`BondedLayer::table_size`]). Counts are `f64` so that absurd geometries
/// (a 1 µm layer under 30 mm distances) are computed without overflow.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TableSize {
    /// Rows of the table (distances tabulated).
    pub rows: f64,
    /// Quadrature nodes in wave number.
    pub nodes: f64,
    /// Bessel-function evaluations to build it (`rows × nodes`).
    pub evaluations: f64,
    /// Memory of the rows and the nodes, bytes.
    pub bytes: f64,
}

impl TableSize {
    /// Within [`MAX_TABLE_EVALUATIONS`] and [`MAX_TABLE_BYTES`] (and finite).
    pub fn within_limits(&self) -> bool {
        self.evaluations.is_finite()
            && self.evaluations <= MAX_TABLE_EVALUATIONS
            && self.bytes <= MAX_TABLE_BYTES
    }
}

/// The distance a table is built to when `rho` is asked for (with head room, so a
/// slightly larger later request does not rebuild it).
fn table_reach(thickness_mm: f64, rho: f64) -> f64 {
    rho.max(4.0 * thickness_mm) * 1.25
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

type TableMap = Mutex<HashMap<[u64; 4], Arc<Table>>>;
static TABLES: OnceLock<TableMap> = OnceLock::new();

fn add_correction(r: &mut PointResponse3, dx: f64, dy: f64, rho: f64, v: [f64; 5]) {
    let (ex, ey) = if rho > 0.0 {
        (dx / rho, dy / rho)
    } else {
        (0.0, 0.0)
    };
    let e = [ex, ey];
    let [a, b, c, d, zz] = v;
    for i in 0..2 {
        for j in 0..2 {
            let delta = if i == j { 1.0 } else { 0.0 };
            r[i][j] += delta * a - (e[i] * e[j] - 0.5 * delta) * b;
        }
        r[i][2] -= e[i] * c;
        r[2][i] -= e[i] * d;
    }
    r[2][2] += zz;
}

/// `Σ nodes · [J0, J2, J1, J1, J0](kρ)`.
fn hankel_sum(nodes: &[(f64, [f64; 5])], rho: f64) -> [f64; 5] {
    let mut acc = [0.0; 5];
    for (k, w) in nodes {
        let [j0, j1, j2] = bessel_j012(k * rho);
        acc[0] += w[0] * j0;
        acc[1] += w[1] * j2;
        acc[2] += w[2] * j1;
        acc[3] += w[3] * j1;
        acc[4] += w[4] * j0;
    }
    acc
}

/// The correction `I_n[ΔG]` tabulated on a uniform ρ grid for one depth.
#[derive(Debug)]
struct Table {
    rho_max: f64,
    drho: f64,
    rows: Vec<[f64; 5]>,
}

/// Parity of the five tabulated integrals in ρ (I₀, I₂ even; I₁ odd).
const PARITY: [f64; 5] = [1.0, 1.0, -1.0, -1.0, 1.0];

impl Table {
    fn build(layer: &BondedLayer, z: f64, rho_max: f64) -> Table {
        let a = 2.0 * layer.thickness_mm - z;
        let drho = (a / 40.0).min(rho_max / 8.0);
        let n = (rho_max / drho).ceil() as usize + 3;
        let nodes = layer.nodes(z, n as f64 * drho, 1);
        let rows = (0..n)
            .map(|i| hankel_sum(&nodes, i as f64 * drho))
            .collect();
        Table {
            rho_max: (n - 3) as f64 * drho,
            drho,
            rows,
        }
    }

    fn row(&self, i: isize, c: usize) -> f64 {
        if i < 0 {
            PARITY[c] * self.rows[(-i) as usize][c]
        } else {
            self.rows[i as usize][c]
        }
    }

    /// 4-point Lagrange interpolation; `rho ≤ rho_max` (guaranteed by the caller).
    fn eval(&self, rho: f64) -> [f64; 5] {
        let x = rho / self.drho;
        let i = (x.floor() as isize).min(self.rows.len() as isize - 3);
        let f = x - i as f64;
        // Nodes i−1, i, i+1, i+2 at offsets −1, 0, 1, 2.
        let w = [
            -f * (f - 1.0) * (f - 2.0) / 6.0,
            (f + 1.0) * (f - 1.0) * (f - 2.0) / 2.0,
            -(f + 1.0) * f * (f - 2.0) / 2.0,
            (f + 1.0) * f * (f - 1.0) / 6.0,
        ];
        std::array::from_fn(|c| (0..4).map(|m| w[m] * self.row(i - 1 + m as isize, c)).sum())
    }
}

impl ElasticModel for BondedLayer {
    fn point_response3(&self, dx: f64, dy: f64, z: f64) -> PointResponse3 {
        BondedLayer::point_response3(self, dx, dy, z)
    }

    fn max_depth_mm(&self) -> f64 {
        self.thickness_mm
    }

    fn check_reach(&self, depths_mm: &[f64], rho_max_mm: f64) -> Result<(), ModelError> {
        BondedLayer::check_reach(self, depths_mm, rho_max_mm)
    }

    fn prepare(&self, depths_mm: &[f64], rho_max_mm: f64) {
        for &z in depths_mm {
            if z.is_finite() && z > 0.0 && z <= self.thickness_mm {
                self.table(z, rho_max_mm);
            }
        }
    }
}

/// Nodes and weights of 16-point Gauss–Legendre on [−1, 1] (Newton on P₁₆).
fn gauss_legendre_16() -> &'static ([f64; 16], [f64; 16]) {
    static GL: OnceLock<([f64; 16], [f64; 16])> = OnceLock::new();
    GL.get_or_init(|| {
        const N: usize = 16;
        let mut x = [0.0; N];
        let mut w = [0.0; N];
        for i in 0..N {
            let mut r = (PI * (i as f64 + 0.75) / (N as f64 + 0.5)).cos();
            let mut dp = 0.0;
            for _ in 0..100 {
                let (mut p0, mut p1) = (1.0, r);
                for n in 2..=N {
                    let nf = n as f64;
                    let p2 = ((2.0 * nf - 1.0) * r * p1 - (nf - 1.0) * p0) / nf;
                    p0 = p1;
                    p1 = p2;
                }
                dp = N as f64 * (r * p1 - p0) / (r * r - 1.0);
                let dr = p1 / dp;
                r -= dr;
                if dr.abs() < 1e-16 {
                    break;
                }
            }
            x[i] = r;
            w[i] = 2.0 / ((1.0 - r * r) * dp * dp);
        }
        (x, w)
    })
}

/// Bessel functions `[J₀, J₁, J₂](x)` for `x ≥ 0`: power series below 14, Hankel's
/// asymptotic expansion (summed to its smallest term) above; absolute error < 1e−11.
pub fn bessel_j012(x: f64) -> [f64; 3] {
    let x = x.abs();
    if x < 14.0 {
        let y = 0.25 * x * x;
        let (mut t0, mut t1, mut t2) = (1.0, 0.5 * x, 0.5 * y);
        let (mut s0, mut s1, mut s2) = (t0, t1, t2);
        for m in 1..80 {
            let mf = m as f64;
            t0 *= -y / (mf * mf);
            t1 *= -y / (mf * (mf + 1.0));
            t2 *= -y / (mf * (mf + 2.0));
            s0 += t0;
            s1 += t1;
            s2 += t2;
            if t0.abs() + t1.abs() + t2.abs() < 1e-18 {
                break;
            }
        }
        [s0, s1, s2]
    } else {
        let j0 = bessel_asymptotic(0, x);
        let j1 = bessel_asymptotic(1, x);
        [j0, j1, 2.0 * j1 / x - j0]
    }
}

fn bessel_asymptotic(n: u32, x: f64) -> f64 {
    let mu = 4.0 * (n * n) as f64;
    let (mut p, mut q) = (1.0, 0.0);
    let mut term: f64 = 1.0;
    for k in 1..60u32 {
        let odd = (2 * k - 1) as f64;
        let next = term * (mu - odd * odd) / (k as f64 * 8.0 * x);
        if next.abs() >= term.abs() || next == 0.0 {
            break;
        }
        term = next;
        // a_k enters P (k even) or Q (k odd) with sign (−1)^{⌊k/2⌋}.
        let sign = if (k / 2) % 2 == 0 { 1.0 } else { -1.0 };
        if k % 2 == 0 {
            p += sign * term;
        } else {
            q += sign * term;
        }
        if term.abs() < 1e-17 {
            break;
        }
    }
    let chi = x - (0.5 * n as f64 + 0.25) * PI;
    (2.0 / (PI * x)).sqrt() * (p * chi.cos() - q * chi.sin())
}

#[cfg(test)]
mod tests {
    use super::*;

    const E: f64 = 1.0;

    fn rel(a: f64, b: f64, scale: f64) -> f64 {
        (a - b).abs() / scale
    }

    fn peak(r: &PointResponse3) -> f64 {
        r.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()))
    }

    #[test]
    fn bessel_functions_match_scipy_values() {
        // scipy.special.jv(n, x), SciPy 1.17 (Cephes / AMOS).
        let want: [(f64, [f64; 3]); 7] = [
            (
                0.5,
                [0.938469807240813, 0.2422684576748739, 0.030604023458682638],
            ),
            (
                3.0,
                [-0.2600519549019334, 0.33905895852593626, 0.4860912605858912],
            ),
            (
                13.9,
                [
                    0.18357985545786962,
                    0.11652489036905644,
                    -0.16681368418174639,
                ],
            ),
            (
                14.1,
                [
                    0.15695287703260136,
                    0.14878435129739367,
                    -0.1358487137280065,
                ],
            ),
            (
                20.0,
                [
                    0.16702466434058322,
                    0.06683312417584993,
                    -0.16034135192299823,
                ],
            ),
            (
                57.3,
                [
                    0.1053341332124604,
                    -0.0029007973423950915,
                    -0.10543538268339915,
                ],
            ),
            (
                300.0,
                [
                    -0.03329855487630566,
                    -0.03188743137749995,
                    0.03308597200045567,
                ],
            ),
        ];
        for (x, j) in want {
            let got = bessel_j012(x);
            for n in 0..3 {
                assert!(
                    (got[n] - j[n]).abs() < 1e-11,
                    "J{n}({x}) = {} vs {}",
                    got[n],
                    j[n]
                );
            }
        }
    }

    /// Direct Hankel quadrature of arbitrary kernels (the same formulas as the table).
    fn hankel_of(kern: impl Fn(f64) -> LayerKernels, kmax: f64, w: f64, rho: f64) -> [f64; 5] {
        let (x, wt) = gauss_legendre_16();
        let mut nodes = Vec::new();
        let panels = (kmax / w).ceil() as usize;
        for p in 0..panels {
            for i in 0..16 {
                let k = p as f64 * w + 0.5 * w * (x[i] + 1.0);
                let wk = 0.5 * w * wt[i] * k / (2.0 * PI);
                let d = kern(k);
                nodes.push((
                    k,
                    [
                        wk * 0.5 * (d.ll + d.tt),
                        wk * (d.ll - d.tt),
                        wk * d.lz,
                        wk * d.zl,
                        wk * d.zz,
                    ],
                ));
            }
        }
        hankel_sum(&nodes, rho)
    }

    #[test]
    fn hankel_transform_of_half_space_kernels_reproduces_eq_1_2_and_uz() {
        // Checks the Fourier-space half-space kernels, their signs and the Hankel
        // assembly against the closed forms of half_space.rs.
        for nu in [0.0, 0.3, 0.49, 0.5] {
            let hs = HalfSpace::new(E, nu).unwrap();
            let z = 3.0;
            for &(dx, dy) in &[(0.0, 0.0), (1.0, 0.5), (-2.0, 3.0), (6.0, -1.0)] {
                let rho: f64 = f64::hypot(dx, dy);
                let v = hankel_of(
                    |k| scalar_kernels(k, z, f64::INFINITY, E, nu),
                    50.0 / z,
                    (0.5 / z).min(2.0 / rho.max(1.0)),
                    rho,
                );
                let mut r = [[0.0; 3]; 3];
                add_correction(&mut r, dx, dy, rho, v);
                let want = hs.point_response3(dx, dy, z);
                let s = peak(&want);
                for a in 0..3 {
                    for b in 0..3 {
                        assert!(
                            rel(r[a][b], want[a][b], s) < 1e-9,
                            "nu={nu} ({dx},{dy}) [{a}][{b}]: {} vs {}",
                            r[a][b],
                            want[a][b]
                        );
                    }
                }
            }
        }
    }

    /// Fourier-space stresses of the mode `e^{ikx}` from the kernels by central
    /// differences in z: `[σ_xz, σ_zz, σ_yz]` per unit `p_l`, per unit `p_z` and
    /// per unit `p_t` (σ_xz and σ_zz as the real or imaginary part that carries them).
    fn stresses(k: f64, z: f64, h: f64, nu: f64) -> ([f64; 2], [f64; 2], f64) {
        let mu = E / (2.0 * (1.0 + nu));
        let lam = 2.0 * mu * nu / (1.0 - 2.0 * nu);
        let d = 1e-5 * h;
        let g = scalar_kernels(k, z, h, E, nu);
        let gp = scalar_kernels(k, z + d, h, E, nu);
        let gm = scalar_kernels(k, z - d, h, E, nu);
        let dz = |f: fn(&LayerKernels) -> f64| (f(&gp) - f(&gm)) / (2.0 * d);
        // p_l: u_x = ll, u_z = i zl.
        let l = [
            mu * (dz(|g| g.ll) - k * g.zl),
            lam * (k * g.ll + dz(|g| g.zl)) + 2.0 * mu * dz(|g| g.zl),
        ];
        // p_z: u_x = i lz, u_z = zz.
        let zc = [
            mu * (dz(|g| g.lz) + k * g.zz),
            lam * (-k * g.lz + dz(|g| g.zz)) + 2.0 * mu * dz(|g| g.zz),
        ];
        (l, zc, mu * dz(|g| g.tt))
    }

    #[test]
    fn layer_kernels_satisfy_the_boundary_conditions() {
        // Traction at z = 0 (σ_iz = −p_i) by finite differences of the displacement
        // kernels; zero displacement at z = h exactly.
        let h = 4.0;
        let mut worst: f64 = 0.0;
        for nu in [0.0, 0.3, 0.45, 0.49] {
            for k in [0.01, 0.2, 1.0, 3.0, 9.0] {
                let (l, zc, t) = stresses(k, 0.0, h, nu);
                // Finite differences carry λ/μ = 2ν/(1−2ν) (49 at ν = 0.49).
                let tol = 1e-7 * (1.0 + 2.0 * nu / (1.0 - 2.0 * nu));
                for (got, want) in [
                    (l[0], -1.0),
                    (l[1], 0.0),
                    (zc[0], 0.0),
                    (zc[1], -1.0),
                    (t, -1.0),
                ] {
                    worst = worst.max((got - want).abs());
                    assert!((got - want).abs() < tol, "nu={nu} k={k}: {got} vs {want}");
                }
                let g = scalar_kernels(k, h, h, E, nu);
                let s = scalar_kernels(k, 0.0, h, E, nu);
                let scale = s.ll.abs().max(s.zz.abs());
                for v in [g.ll, g.tt, g.lz, g.zl, g.zz] {
                    assert!(v.abs() < 1e-13 * scale, "nu={nu} k={k}: u(h) = {v}");
                }
            }
        }
        eprintln!("worst traction residual {worst:.2e}");
    }

    #[test]
    fn layer_kernels_satisfy_navier_inside() {
        // μ∇²u + (λ+μ)∇(div u) = 0 at interior depths, by finite differences.
        let (h, nu) = (3.0, 0.3);
        let mu = E / (2.0 * (1.0 + nu));
        let lam = 2.0 * mu * nu / (1.0 - 2.0 * nu);
        let d = 1e-3;
        for k in [0.3, 1.0, 2.5] {
            for z in [0.5, 1.5, 2.7] {
                let g = scalar_kernels(k, z, h, E, nu);
                let p = scalar_kernels(k, z + d, h, E, nu);
                let m = scalar_kernels(k, z - d, h, E, nu);
                let d1 = |f: fn(&LayerKernels) -> f64| (f(&p) - f(&m)) / (2.0 * d);
                let d2 = |f: fn(&LayerKernels) -> f64, c: f64| (f(&p) - 2.0 * c + f(&m)) / (d * d);
                // p_l: u_x = ll e^{ikx}, u_z = i zl e^{ikx}; div = i(k ll + zl').
                let div = k * g.ll + d1(|g| g.zl);
                let ddiv = k * d1(|g| g.ll) + d2(|g| g.zl, g.zl);
                let rx = mu * (d2(|g| g.ll, g.ll) - k * k * g.ll) - (lam + mu) * k * div;
                let rz = mu * (d2(|g| g.zl, g.zl) - k * k * g.zl) + (lam + mu) * ddiv;
                let scale = g.ll.abs() * k * k + 1.0;
                assert!(
                    rx.abs() < 1e-5 * scale && rz.abs() < 1e-5 * scale,
                    "k={k} z={z}: {rx} {rz}"
                );
            }
        }
    }

    #[test]
    fn incompressible_layer_is_finite_divergence_free_and_continuous_in_nu() {
        let h = 3.0;
        for k in [1e-3, 0.1, 1.0, 5.0] {
            for z in [0.0, 0.5, 2.0] {
                let g = scalar_kernels(k, z, h, E, 0.5);
                for v in [g.ll, g.tt, g.lz, g.zl, g.zz] {
                    assert!(v.is_finite());
                }
                // div u = 0 for both loads (ν = 0.5).
                let d = 1e-6;
                let p = scalar_kernels(k, z + d, h, E, 0.5);
                let m = scalar_kernels(k, z - d, h, E, 0.5);
                let div_l = k * g.ll + (p.zl - m.zl) / (2.0 * d);
                let div_z = -k * g.lz + (p.zz - m.zz) / (2.0 * d);
                assert!(div_l.abs() < 1e-6 && div_z.abs() < 1e-6, "k={k} z={z}");
                // ν → 0.5 is a continuous limit.
                let n = scalar_kernels(k, z, h, E, 0.5 - 1e-7);
                for (a, b) in [(g.ll, n.ll), (g.lz, n.lz), (g.zl, n.zl), (g.zz, n.zz)] {
                    assert!((a - b).abs() < 1e-5 * (g.ll.abs() + 1e-3), "k={k} z={z}");
                }
            }
        }
        // Real space at ν = 0.5 and 0.49: finite and close to each other.
        let a = BondedLayer::new(E, 0.5, 5.0)
            .unwrap()
            .point_response3(1.0, 0.5, 2.0);
        let b = BondedLayer::new(E, 0.49, 5.0)
            .unwrap()
            .point_response3(1.0, 0.5, 2.0);
        for i in 0..3 {
            for j in 0..3 {
                assert!(a[i][j].is_finite() && (a[i][j] - b[i][j]).abs() < 0.05 * peak(&a));
            }
        }
    }

    #[test]
    fn zero_wave_number_is_the_uniform_traction_limit() {
        let (h, z, nu) = (5.0, 1.0, 0.3);
        let a = scalar_kernels(0.0, z, h, E, nu);
        let b = scalar_kernels(1e-5, z, h, E, nu);
        for (x, y) in [(a.ll, b.ll), (a.tt, b.tt), (a.zz, b.zz)] {
            assert!((x - y).abs() < 1e-6 * x.abs(), "{x} vs {y}");
        }
        assert!(b.lz.abs() < 1e-3 * a.ll && b.zl.abs() < 1e-3 * a.ll);
    }

    /// The closed forms of the module docs evaluated with mpmath at 60 digits
    /// (`h z ν kh` → `ll tt lz zl zz`, E = 1 N/mm²), on both sides of the switch to the
    /// series and deep below it.
    #[allow(clippy::excessive_precision)] // 17 digits as mpmath printed them
    const SMALL_KH: [(f64, f64, f64, f64, [f64; 5]); 15] = [
        (
            3.0,
            1.0,
            0.3,
            1e-7,
            [
                5.1999999999999335,
                5.1999999999999778,
                -9.9047619047617919e-8,
                -2.4761904761905026e-8,
                1.4857142857142862,
            ],
        ),
        (
            3.0,
            1.0,
            0.3,
            1e-5,
            [
                5.1999999993355555,
                5.1999999997785185,
                -9.9047619036443426e-6,
                -2.476190476446612e-6,
                1.4857142857190023,
            ],
        ),
        (
            3.0,
            1.0,
            0.3,
            4.9e-4,
            [
                5.1999984046693483,
                5.1999994682230148,
                -0.00048533320185342536,
                -0.00012133336346735538,
                1.4857142970387261,
            ],
        ),
        (
            3.0,
            1.0,
            0.3,
            5.1e-4,
            [
                5.1999982717805391,
                5.1999994239267275,
                -0.00050514270889730593,
                -0.00012628574826227207,
                1.4857142979820361,
            ],
        ),
        (
            3.0,
            1.0,
            0.3,
            3e-3,
            [
                5.1999402006455615,
                5.1999800667395097,
                -0.0029713983976037021,
                -0.00074286405841661874,
                1.4857147101983205,
            ],
        ),
        (
            40.0,
            6.0,
            0.5,
            1e-7,
            [
                101.99999999999813,
                101.99999999999961,
                -5.864999999999888e-6,
                4.3349999999999091e-6,
                3.1067499999999454e-13,
            ],
        ),
        (
            40.0,
            6.0,
            0.5,
            1e-5,
            [
                101.9999999812915,
                101.99999999612825,
                -0.00058649999988801994,
                0.00043349999990912756,
                3.106749999454489e-9,
            ],
        ),
        (
            40.0,
            6.0,
            0.5,
            4.9e-4,
            [
                101.99995508091129,
                101.99999070392915,
                -0.028738486825663424,
                0.021241489308953303,
                7.4593036052391261e-6,
            ],
        ),
        (
            40.0,
            6.0,
            0.5,
            5.1e-4,
            [
                101.99995133921473,
                101.9999899295793,
                -0.02991148514573981,
                0.022108487945686037,
                8.0806530595103139e-6,
            ],
        ),
        (
            40.0,
            6.0,
            0.5,
            3e-3,
            [
                101.998316262812,
                101.99965154375974,
                -0.17594697658818107,
                0.13004754648464228,
                0.00027960308143354124,
            ],
        ),
        (
            2.0,
            0.5,
            0.49,
            1e-7,
            [
                4.4699999999999156,
                4.4699999999999818,
                -2.6513235294117164e-7,
                1.5557352941176137e-7,
                0.08764705882354083,
            ],
        ),
        (
            2.0,
            0.5,
            0.49,
            1e-5,
            [
                4.4699999991561231,
                4.4699999998184062,
                -2.6513235289305986e-5,
                1.5557352937849985e-5,
                0.087647058936949723,
            ],
        ),
        (
            2.0,
            0.5,
            0.49,
            4.9e-4,
            [
                4.4699979738525827,
                4.4699995639934485,
                -0.0012991479633250522,
                0.00076230990276026904,
                0.087647331145403868,
            ],
        ),
        (
            2.0,
            0.5,
            0.49,
            5.1e-4,
            [
                4.4699978050773662,
                4.4699995276747058,
                -0.0013521743617288221,
                0.00079342455873874242,
                0.087647353829431803,
            ],
        ),
        (
            2.0,
            0.5,
            0.49,
            3e-3,
            [
                4.4699240523087948,
                4.4699836566219137,
                -0.0079538406755127088,
                0.0046671160687244635,
                0.087657266490308604,
            ],
        ),
    ];

    #[test]
    fn small_kh_kernels_match_60_digit_values_on_both_sides_of_the_series_switch() {
        for (h, z, nu, t, want) in SMALL_KH {
            let g = scalar_kernels(t / h, z, h, E, nu);
            let got = [g.ll, g.tt, g.lz, g.zl, g.zz];
            let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for (i, (a, b)) in got.iter().zip(&want).enumerate() {
                assert!(
                    (a - b).abs() <= 1e-12 * scale,
                    "h={h} z={z} nu={nu} kh={t:e} kernel {i}: {a} vs {b}"
                );
            }
        }
    }

    #[test]
    fn thick_layer_kernels_equal_the_half_space_kernels() {
        // Fourier space: for kh ≫ 1 the layer terms are e^{−2kh} small.
        for nu in [0.3, 0.5] {
            for k in [0.05, 0.5, 3.0] {
                let a = scalar_kernels(k, 3.0, 1000.0, E, nu);
                let b = scalar_kernels(k, 3.0, f64::INFINITY, E, nu);
                for (x, y) in [
                    (a.ll, b.ll),
                    (a.tt, b.tt),
                    (a.lz, b.lz),
                    (a.zl, b.zl),
                    (a.zz, b.zz),
                ] {
                    assert!((x - y).abs() <= 1e-12 * b.tt.abs(), "k={k}: {x} vs {y}");
                }
            }
        }
    }

    #[test]
    fn thick_layer_converges_to_eq_1_2_at_the_rate_of_its_rigid_base() {
        // Real space: the rigid base at depth h changes the response near the surface
        // by O(ρ/h) (a uniform-ish image field of size f/(μh)), so the difference from
        // Eq. 1–2 must fall like 1/h: measured at h = 1000 and 2000 mm.
        let nu = 0.49;
        let hs = HalfSpace::new(E, nu).unwrap();
        let mut errs = Vec::new();
        for h in [1000.0, 2000.0] {
            let l = BondedLayer::new(E, nu, h).unwrap();
            let mut worst: f64 = 0.0;
            for &(dx, dy, z) in &[
                (1.0, 0.5, 3.0),
                (-2.0, 3.0, 6.0),
                (0.0, 0.0, 3.0),
                (10.0, 2.0, 6.0),
            ] {
                let a = l.point_response3(dx, dy, z);
                let b = hs.point_response3(dx, dy, z);
                let s = peak(&b);
                for i in 0..3 {
                    for j in 0..3 {
                        worst = worst.max(rel(a[i][j], b[i][j], s));
                    }
                }
            }
            errs.push(worst);
        }
        eprintln!(
            "h=1000: max rel diff {:.3e}; h=2000: {:.3e}",
            errs[0], errs[1]
        );
        assert!(errs[0] < 2e-2, "{errs:?}");
        let ratio = errs[0] / errs[1];
        assert!((1.8..2.2).contains(&ratio), "{errs:?}");
    }

    #[test]
    fn table_matches_a_four_times_finer_direct_quadrature() {
        for (h, z, nu) in [
            (3.0, 0.5, 0.49),
            (3.0, 2.0, 0.5),
            (40.0, 3.0, 0.5),
            (40.0, 6.0, 0.3),
        ] {
            let l = BondedLayer::new(E, nu, h).unwrap();
            let mut worst: f64 = 0.0;
            for &(dx, dy) in &[
                (0.0, 0.0),
                (0.37, 0.21),
                (1.3, -2.9),
                (7.7, 3.1),
                (-18.4, 11.0),
            ] {
                let a = l.point_response3(dx, dy, z);
                let b = l.point_response3_direct(dx, dy, z, 4);
                let s = peak(&l.point_response3(0.0, 0.0, z));
                for i in 0..3 {
                    for j in 0..3 {
                        worst = worst.max(rel(a[i][j], b[i][j], s));
                    }
                }
            }
            eprintln!("h={h} z={z}: table vs direct {worst:.2e} of the peak");
            assert!(worst < 1e-6, "h={h} z={z}: {worst}");
        }
    }

    #[test]
    fn layer_response_has_the_symmetries_and_vanishes_at_the_plate() {
        let l = BondedLayer::new(E, 0.49, 5.0).unwrap();
        let r = l.point_response3(1.3, -0.4, 2.0);
        assert!((r[0][1] - r[1][0]).abs() < 1e-14);
        let m = l.point_response3(-1.3, -0.4, 2.0);
        let s = peak(&r);
        assert!(rel(m[0][2], -r[0][2], s) < 1e-12 && rel(m[0][0], r[0][0], s) < 1e-12);
        assert!(rel(m[2][0], -r[2][0], s) < 1e-12 && rel(m[2][2], r[2][2], s) < 1e-12);
        let sw = l.point_response3(-0.4, 1.3, 2.0);
        assert!(rel(sw[1][1], r[0][0], s) < 1e-12 && rel(sw[2][1], r[2][0], s) < 1e-12);
        let c = l.point_response3(0.0, 0.0, 2.0);
        assert_eq!(c[0][2], 0.0);
        assert!((c[0][0] - c[1][1]).abs() < 1e-15);
        // At the bonded face everything vanishes (up to the table's accuracy).
        let b = l.point_response3(0.7, 0.2, 5.0);
        for v in b.iter().flatten() {
            assert!(v.abs() < 1e-6 * peak(&c), "{v}");
        }
    }

    #[test]
    fn lab_frame_kernel_rotates_the_scalar_kernels() {
        let (z, h, nu) = (1.0, 3.0, 0.45);
        let g = scalar_kernels(0.5, z, h, E, nu);
        let k = layer_kernel(0.5, 0.0, z, h, E, nu);
        let eq = |a: f64, b: f64| (a - b).abs() < 1e-15 * g.tt.abs();
        assert!(eq(k[0][0].re, g.ll) && eq(k[1][1].re, g.tt) && eq(k[0][2].im, g.lz));
        let k3 = layer_kernel3(0.0, 0.5, z, h, E, nu);
        assert!(eq(k3[1][1].re, g.ll) && eq(k3[2][1].im, g.zl) && eq(k3[2][2].re, g.zz));
        let d = layer_kernel(0.3, 0.4, z, h, E, nu);
        assert!((d[0][1] - d[1][0]).norm() < 1e-15);
    }

    /// max |u_layer − u_half| / max |u_half| (%) of `u_x` per unit force along axis
    /// `b`, along the x axis from the load out to `reach` mm (0.1 mm steps), and the
    /// same error as a share of the layer's own peak.
    fn half_space_error(l: &BondedLayer, b: usize, z: f64, reach: f64) -> (f64, f64) {
        let hs = l.half_space();
        let (mut d, mut ph, mut pl): (f64, f64, f64) = (0.0, 0.0, 0.0);
        for i in 0..=(10.0 * reach).round() as usize {
            let x = 0.1 * i as f64;
            let u = l.point_response3(x, 0.0, z)[0][b];
            let v = hs.point_response3(x, 0.0, z)[0][b];
            d = d.max((u - v).abs());
            ph = ph.max(v.abs());
            pl = pl.max(u.abs());
        }
        (100.0 * d / ph, 100.0 * d / pl)
    }

    #[test]
    fn paper_layer_half_space_error_reproduces_the_fem_figures() {
        // Issue 14 quotes an independent FEM (40 mm layer, ν = 0.49, markers at 3 / 6 mm):
        // the half-space's error in the horizontal displacement, as a share of its peak,
        // is 2.0 % / 3.2 % (normal load) and 6.9 % / 13.6 % (tangential load). Our
        // earlier 4.4 % / 6.9 % (normal) measured out to 40 mm from the load and divided
        // by the layer's peak. The FEM's figures are reproduced to the quoted digit by a
        // point load, max |Δu_x| / max |u_x(half-space)| along the load's line, within
        // 10 mm of the load (the half-width of the paper's 19.8 × 15.4 mm force grid
        // around a centred load): the normal-load error grows with distance (the plate's
        // image field), the tangential one peaks under the load (module docs).
        let l = BondedLayer::new(E, 0.49, 40.0).unwrap();
        let fem = [[2.0, 3.2], [6.9, 13.6]];
        for (i, (b, name)) in [(2usize, "normal"), (0, "tangential")]
            .into_iter()
            .enumerate()
        {
            for (j, z) in [3.0, 6.0].into_iter().enumerate() {
                let (near, near_own) = half_space_error(&l, b, z, 10.0);
                let (far, far_own) = half_space_error(&l, b, z, 40.0);
                eprintln!(
                    "{name} load, z = {z} mm: within 10 mm {near:.2} % of the half-space peak \
                     ({near_own:.2} % of the layer's); within 40 mm {far:.2} % ({far_own:.2} %); \
                     FEM {} %",
                    fem[i][j]
                );
                assert!(
                    (near - fem[i][j]).abs() < 0.05,
                    "{name}, z = {z}: {near:.3} % vs FEM {} %",
                    fem[i][j]
                );
            }
        }
        // The other definitions do not reproduce them: the 40 mm reach doubles the
        // normal-load figure, the layer's own peak inflates the tangential one.
        assert!(half_space_error(&l, 2, 3.0, 40.0).0 > 4.0);
        assert!(half_space_error(&l, 0, 6.0, 10.0).1 > 15.0);
    }
}
