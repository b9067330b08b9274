//! Indentation laws: the normal force and contact radius of a rigid indenter pressed a
//! depth δ into the elastomer, as functions of the reduced modulus `E* = E/(1−ν²)`
//! (N/mm²), the indenter geometry and δ (mm). The simulated bench's force law
//! (`sim::world`) and the fit's indentation route (`fit::indentation`) both call
//! [`indentation_force`], so the bench a fit is tested on and the fit share one law.
//!
//! Half-space (Johnson, *Contact Mechanics*, §3.8 and §5.2 (Hertz), §5.2(a) (punch)):
//! - flat cylinder of radius `a`: `P = 2 a E* δ`, contact radius `a` at every depth;
//! - sphere of radius `R` (Hertz): `P = 4/3 E* √R δ^{3/2}`, `a = √(Rδ)`;
//! - hemisphere past its equator (δ > R, where Hertz's `a = √(Rδ)` would exceed `R`):
//!   the contact radius stays `R` and the flank presses like a flat punch of radius R,
//!   `P = P(R) + 2 R E* (δ − R)` (continuous in P, its slope jumps from `2RE*·…` by the
//!   punch stiffness; what the simulated bench has always done).
//!
//! Bonded layer of thickness `h` on a rigid plate (the `bonded-layer` model): the
//! finite-thickness corrections of Shull, *Contact mechanics and the adhesion of soft
//! solids*, Mater. Sci. Eng. R 36 (2002) 1–45, §4 (fits to finite-element results for
//! an incompressible layer bonded to a rigid substrate):
//! - flat punch: `P = 2 a E* δ · (1 + 1.33 (a/h) + 1.33 (a/h)³)`;
//! - sphere: `P = 4 E* a³ / (3R) · (1 + 0.33 (a/h)³)` at
//!   `δ = a²/R · (0.4 + 0.6 e^{−1.8 a/h})` (solved for `a` given δ; δ(a) is strictly
//!   increasing, so the root is unique);
//! - hemisphere past its equator: as the half-space, with the layer's punch stiffness
//!   and the layer's equator depth `δ(a = R)`.
//!
//! Validity: the corrections were fitted for `a/h` up to about 2 ([`LAYER_A_OVER_H_MAX`])
//! with ν = 0.5; they are applied with the sensor's ν through `E*` (exact in the
//! half-space limit, approximate for a compressible thin layer), and beyond
//! `a/h = 2` they are extrapolated (the contact then reports `beyond_validity`). As
//! h → ∞ every layer law is exactly the half-space law (tested).

/// The largest contact radius / thickness ratio the bonded-layer corrections were
/// fitted for (Shull 2002); beyond it [`Contact::beyond_validity`] is set.
pub const LAYER_A_OVER_H_MAX: f64 = 2.0;

/// The indenter's shape, lengths in mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    /// Flat-ended cylinder of face radius `a`.
    Flat {
        /// Face radius, mm.
        radius_mm: f64,
    },
    /// Hemispherical tip of radius `R` (Hertz while δ ≤ the equator depth).
    Hemisphere {
        /// Radius, mm.
        radius_mm: f64,
    },
}

/// The elastic body the indenter presses into.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Body {
    /// An elastic half-space (the `half-space` model).
    HalfSpace,
    /// A layer of this thickness (mm) bonded to a rigid plate (the `bonded-layer` model).
    BondedLayer {
        /// Thickness h, mm.
        thickness_mm: f64,
    },
}

/// The contact at one depth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Contact {
    /// Normal force P, N (0 when δ ≤ 0).
    pub force_n: f64,
    /// Contact radius a, mm.
    pub radius_mm: f64,
    /// True when a bonded layer's law was used past `a/h =` [`LAYER_A_OVER_H_MAX`].
    pub beyond_validity: bool,
}

/// The reduced modulus `E* = E/(1−ν²)`, N/mm² from E in N/mm².
pub fn reduced_modulus(young_n_per_mm2: f64, poisson: f64) -> f64 {
    young_n_per_mm2 / (1.0 - poisson * poisson)
}

/// Hertz: a rigid sphere of radius `r` pressed `d` into a half-space.
pub fn hertz_sphere(e_star: f64, r: f64, d: f64) -> Contact {
    if d <= 0.0 {
        return Contact::NONE;
    }
    Contact {
        force_n: 4.0 / 3.0 * e_star * r.sqrt() * d.powf(1.5),
        radius_mm: (r * d).sqrt(),
        beyond_validity: false,
    }
}

/// Boussinesq: a rigid flat punch of radius `a` pressed `d` into a half-space.
pub fn flat_punch(e_star: f64, a: f64, d: f64) -> Contact {
    if d <= 0.0 {
        return Contact::NONE;
    }
    Contact {
        force_n: 2.0 * a * e_star * d,
        radius_mm: a,
        beyond_validity: false,
    }
}

/// Shull's load factor for a flat punch on a bonded layer at `x = a/h`.
fn layer_punch_factor(x: f64) -> f64 {
    1.0 + 1.33 * x + 1.33 * x * x * x
}

/// Shull's load factor for a sphere on a bonded layer at `x = a/h`.
fn layer_sphere_load_factor(x: f64) -> f64 {
    1.0 + 0.33 * x * x * x
}

/// Shull's depth factor for a sphere on a bonded layer at `x = a/h`.
fn layer_sphere_depth_factor(x: f64) -> f64 {
    0.4 + 0.6 * (-1.8 * x).exp()
}

/// The depth at which a sphere of radius `r` on a layer of thickness `h` has contact
/// radius `a`.
fn layer_sphere_depth(r: f64, h: f64, a: f64) -> f64 {
    a * a / r * layer_sphere_depth_factor(a / h)
}

/// A flat punch of radius `a` pressed `d` into a layer of thickness `h` (Shull 2002).
pub fn layer_flat_punch(e_star: f64, a: f64, h: f64, d: f64) -> Contact {
    let mut c = flat_punch(e_star, a, d);
    c.force_n *= layer_punch_factor(a / h);
    c.beyond_validity = d > 0.0 && a / h > LAYER_A_OVER_H_MAX;
    c
}

/// A sphere of radius `r` pressed `d` into a layer of thickness `h` (Shull 2002): the
/// contact radius solved from Shull's δ(a) by bisection on `[0, √(Rd/0.4)]` (δ(a) is
/// increasing: `d/da [a² f(a/h)] = a (0.8 + e^{−x}(1.2 − 1.08x)) > 0`).
pub fn layer_sphere(e_star: f64, r: f64, h: f64, d: f64) -> Contact {
    if d <= 0.0 {
        return Contact::NONE;
    }
    // f ≥ 0.4, so a² ≤ R d / 0.4; f ≤ 1, so a² ≥ R d.
    let (mut lo, mut hi) = ((r * d).sqrt(), (r * d / 0.4).sqrt());
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if layer_sphere_depth(r, h, mid) < d {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo <= 1e-15 * hi {
            break;
        }
    }
    let a = 0.5 * (lo + hi);
    Contact {
        force_n: 4.0 * e_star * a * a * a / (3.0 * r) * layer_sphere_load_factor(a / h),
        radius_mm: a,
        beyond_validity: a / h > LAYER_A_OVER_H_MAX,
    }
}

impl Contact {
    /// No contact.
    pub const NONE: Contact = Contact {
        force_n: 0.0,
        radius_mm: 0.0,
        beyond_validity: false,
    };
}

/// The contact of `shape` pressed `d` (mm) into `body` of reduced modulus `e_star`
/// (N/mm²): the law the module docs give for that pair.
pub fn indentation_force(shape: Shape, body: Body, e_star: f64, d: f64) -> Contact {
    if d <= 0.0 {
        return Contact::NONE;
    }
    match (shape, body) {
        (Shape::Flat { radius_mm }, Body::HalfSpace) => flat_punch(e_star, radius_mm, d),
        (Shape::Flat { radius_mm }, Body::BondedLayer { thickness_mm }) => {
            layer_flat_punch(e_star, radius_mm, thickness_mm, d)
        }
        (Shape::Hemisphere { radius_mm: r }, Body::HalfSpace) => {
            // Past the equator (a = R at δ = R) the flank presses like a punch.
            if d <= r {
                hertz_sphere(e_star, r, d)
            } else {
                let eq = hertz_sphere(e_star, r, r);
                Contact {
                    force_n: eq.force_n + flat_punch(e_star, r, d - r).force_n,
                    radius_mm: r,
                    beyond_validity: false,
                }
            }
        }
        (Shape::Hemisphere { radius_mm: r }, Body::BondedLayer { thickness_mm: h }) => {
            let d_eq = layer_sphere_depth(r, h, r);
            if d <= d_eq {
                layer_sphere(e_star, r, h, d)
            } else {
                let eq = layer_sphere(e_star, r, h, d_eq);
                let flank = layer_flat_punch(e_star, r, h, d - d_eq);
                Contact {
                    force_n: eq.force_n + flank.force_n,
                    radius_mm: r,
                    beyond_validity: eq.beyond_validity || flank.beyond_validity,
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::layer::{bessel_j012, scalar_kernels};

    const E_STAR: f64 = 0.2; // N/mm² (≈ 150 kPa at ν = 0.5)

    fn rel(a: f64, b: f64) -> f64 {
        (a - b).abs() / b.abs()
    }

    #[test]
    fn hertz_and_punch_match_their_closed_forms() {
        // Johnson (4.22)/(5.2): at R = 4 mm, δ = 1 mm, P = 4/3 · 0.2 · 2 · 1.
        let c = hertz_sphere(E_STAR, 4.0, 1.0);
        assert!(rel(c.force_n, 4.0 / 3.0 * 0.2 * 2.0) < 1e-15);
        assert!(rel(c.radius_mm, 2.0) < 1e-15);
        let p = flat_punch(E_STAR, 2.0, 0.5);
        assert!(rel(p.force_n, 2.0 * 2.0 * 0.2 * 0.5) < 1e-15);
        assert_eq!(
            indentation_force(
                Shape::Flat { radius_mm: 2.0 },
                Body::HalfSpace,
                E_STAR,
                -0.1
            ),
            Contact::NONE
        );
    }

    #[test]
    fn a_hemisphere_past_its_equator_presses_on_like_a_punch_continuously() {
        let s = Shape::Hemisphere { radius_mm: 2.0 };
        let below = indentation_force(s, Body::HalfSpace, E_STAR, 2.0 - 1e-9);
        let above = indentation_force(s, Body::HalfSpace, E_STAR, 2.0 + 1e-9);
        assert!(rel(below.force_n, above.force_n) < 1e-8);
        let deep = indentation_force(s, Body::HalfSpace, E_STAR, 3.0);
        let slope = 2.0 * 2.0 * E_STAR;
        assert!(rel(deep.force_n - above.force_n, slope * (1.0 - 1e-9)) < 1e-9);
        assert_eq!(deep.radius_mm, 2.0);
        // The layer's law is continuous at its own equator too.
        let b = Body::BondedLayer { thickness_mm: 3.0 };
        let d_eq = layer_sphere_depth(2.0, 3.0, 2.0);
        let lo = indentation_force(s, b, E_STAR, d_eq - 1e-9);
        let hi = indentation_force(s, b, E_STAR, d_eq + 1e-9);
        assert!(rel(lo.force_n, hi.force_n) < 1e-7, "{lo:?} {hi:?}");
    }

    #[test]
    fn a_thick_bonded_layer_indents_as_the_half_space() {
        for shape in [
            Shape::Flat { radius_mm: 2.0 },
            Shape::Hemisphere { radius_mm: 3.0 },
        ] {
            for d in [0.1, 0.8, 2.5] {
                let hs = indentation_force(shape, Body::HalfSpace, E_STAR, d);
                let layer =
                    indentation_force(shape, Body::BondedLayer { thickness_mm: 1e7 }, E_STAR, d);
                assert!(
                    rel(layer.force_n, hs.force_n) < 1e-5,
                    "{shape:?} {d}: {layer:?} {hs:?}"
                );
                assert!(rel(layer.radius_mm, hs.radius_mm) < 1e-5);
            }
        }
    }

    #[test]
    fn a_thin_bonded_layer_is_stiffer_and_its_sphere_contact_smaller() {
        let (r, d) = (3.0, 0.5);
        let hs = hertz_sphere(E_STAR, r, d);
        let mut last = hs;
        for h in [20.0, 6.0, 3.0, 1.5] {
            let c = layer_sphere(E_STAR, r, h, d);
            assert!(c.force_n > last.force_n, "h = {h}: {c:?} vs {last:?}");
            assert!(c.radius_mm > last.radius_mm || h == 20.0 || c.radius_mm >= hs.radius_mm);
            last = c;
        }
        // The thin limit of the sphere: δ → 0.4 a²/R (Shull's f_δ(∞)), so a → √(Rδ/0.4).
        let thin = layer_sphere(E_STAR, r, 1e-4, d);
        assert!(rel(thin.radius_mm, (r * d / 0.4).sqrt()) < 1e-9);
        assert!(thin.beyond_validity);
        // The punch's thin limit is the cubic term.
        let a = 2.0;
        let p = layer_flat_punch(E_STAR, a, 0.01, d);
        assert!(
            rel(
                p.force_n,
                2.0 * a * E_STAR * d * 1.33 * (a / 0.01f64).powi(3)
            ) < 2e-4
        );
    }

    /// The punch stiffness of our own bonded-layer model (`model::layer`'s surface
    /// kernel `G_zz(k, 0)`), by a two-term Galerkin (Ritz) estimate of the punch's
    /// compliance over trial pressures `1/√(a²−r²)` (Boussinesq's) and `(a²−r²)`:
    /// `C = min_c cᵀAc` over unit total force, `A_ij = 1/(2π) ∫ p̂_i p̂_j G_zz k dk`
    /// (an upper bound on the compliance, exact in the half-space). Returns the
    /// stiffness `1/C`, N/mm.
    fn ritz_punch_stiffness(young: f64, nu: f64, a: f64, h: f64) -> f64 {
        let (n, k_max) = (200_000, 400.0 / a);
        let dk = k_max / n as f64;
        let mut m = [[0.0; 2]; 2];
        for i in 0..n {
            let k = (i as f64 + 0.5) * dk;
            let x = k * a;
            let g = scalar_kernels(k, 0.0, h, young, nu).zz;
            let p = [x.sin() / x, 8.0 * bessel_j012(x)[2] / (x * x)];
            for (r, pr) in p.iter().enumerate() {
                for (c, pc) in p.iter().enumerate() {
                    m[r][c] += pr * pc * g * k * dk / (2.0 * std::f64::consts::PI);
                }
            }
        }
        // The half-space tail beyond k_max: G_zz → 2/(E* k); only the Boussinesq
        // term decays slowly enough to matter: ∫ sin²(ka)/(ka)² dk/π / E*.
        let e_star = reduced_modulus(young, nu);
        m[0][0] += 1.0 / (std::f64::consts::PI * e_star) * 0.5 / (a * a * k_max);
        // Minimise cᵀMc with c0 + c1 = 1.
        let (a00, a01, a11) = (m[0][0], m[0][1], m[1][1]);
        let c1 = (a00 - a01) / (a00 - 2.0 * a01 + a11);
        let c0 = 1.0 - c1;
        let compliance = c0 * c0 * a00 + 2.0 * c0 * c1 * a01 + c1 * c1 * a11;
        1.0 / compliance
    }

    #[test]
    fn the_punch_law_agrees_with_the_bonded_layer_models_own_compliance() {
        let (young, nu, a) = (0.15, 0.5, 2.0);
        let e_star = reduced_modulus(young, nu);
        // Half-space: the Ritz estimate reproduces 2aE* (the Boussinesq pressure is
        // the exact solution there).
        let k_hs = ritz_punch_stiffness(young, nu, a, f64::INFINITY);
        assert!(
            rel(k_hs, 2.0 * a * e_star) < 2e-3,
            "{k_hs} vs {}",
            2.0 * a * e_star
        );
        // Finite layers: Shull's law against our model's kernel (a Ritz lower bound on
        // the stiffness, so the law may lie a few per cent above it).
        for h in [20.0, 8.0, 4.0, 2.0] {
            let ours = ritz_punch_stiffness(young, nu, a, h);
            let shull = layer_flat_punch(e_star, a, h, 1.0).force_n;
            let r = shull / ours;
            eprintln!("a/h = {:.2}: Shull {shull:.4} N/mm, bonded-layer kernel (Ritz) {ours:.4} N/mm, ratio {r:.4}", a / h);
            assert!(
                (0.9..1.15).contains(&r),
                "a/h = {}: {shull} vs {ours}",
                a / h
            );
        }
    }
}
