//! Contact models: the surface traction under an indenter, discretised into point
//! loads, pushed through the half-space model to marker displacements, and integrated
//! over the force grid's cells as ground truth.
//!
//! Normal pressure (Johnson, *Contact Mechanics*, 1985, §3.8 and §4.2), contact radius
//! `a`, total normal load `P`, `E* = E/(1−ν²)`:
//!
//! - **Flat cylindrical punch** (diameter `2a`): `p(r) = P / (2πa √(a²−r²))`, singular
//!   at the edge; from an indentation depth `δ`: `P = 2 a E* δ`.
//! - **Hemisphere** (radius `R`, Hertz): `p(r) = p0 √(1−r²/a²)`, `p0 = 3P/(2πa²)`;
//!   from a load `a = (3PR/(4E*))^{1/3}`, from a depth `a = √(Rδ)`,
//!   `P = 4/3 E* √R δ^{3/2}`. Rejected when `a > R` (outside Hertz's validity).
//! - **Point**: the whole load at one point.
//!
//! Tangential traction is proportional to the normal pressure, `q = (Q/P) p`, in the
//! load's direction (full sliding under Coulomb friction, Johnson §7.1); when the
//! requested tangential load `|Q|` exceeds `μP` it is clamped to `μP` and the clamp is
//! reported in [`Contact::clamped_tangential_n`].
//!
//! **Discretisation.** The contact disc is cut into polar cells: rings of width at most
//! [`CELL_MM`] (0.05 mm), each cut into sectors of arc length at most `CELL_MM`. The
//! load of a ring is integrated exactly from the cumulative load `P(ρ)` inside radius
//! `ρ` (flat: `P(1 − √(1−ρ²/a²))`; Hertz: `P(1 − (1−ρ²/a²)^{3/2})`), which handles
//! the flat punch's edge singularity, and shared equally among its sectors. Each cell's
//! force acts at the cell's centre of load (exact radial first moment of the pressure
//! over the ring, in closed form with `ρ = a sin φ`, times the sector's `sin(Δθ/2)/(Δθ/2)`
//! factor). The cell forces therefore sum to the applied force exactly (to rounding)
//! and keep its first moment. Marker displacements are the sum of the half-space point
//! responses ([`HalfSpace::displacement`]) of all cells; the markers are ≥ 3 mm deep,
//! 60 cell sizes, so the discretisation error is far below the tracker's resolution.
//!
//! **Force-grid truth.** Each cell force is added to the force-grid node whose cell
//! (the square of one pitch around the node; border cells extend outward) contains its
//! point of action, so the node forces sum to the applied force. Polar cells straddling
//! a force-cell border are assigned whole: a position error of at most one cell size.

use thiserror::Error;

use crate::model::{HalfSpace, MarkerSite};
use crate::sensor::Grid;

/// Largest polar cell size (ring width and sector arc length), mm.
pub const CELL_MM: f64 = 0.05;

/// An invalid contact.
#[derive(Debug, Error, PartialEq)]
pub enum ContactError {
    /// A parameter out of range.
    #[error("{key} = {value} is invalid: {allowed}")]
    Invalid {
        /// The parameter.
        key: &'static str,
        /// The value.
        value: f64,
        /// What is allowed, with units.
        allowed: String,
    },
    /// The Hertz contact radius exceeds the hemisphere radius.
    #[error(
        "hemisphere of radius {radius_mm} mm: the contact radius a = {contact_radius_mm:.3} mm exceeds \
         the radius (Hertz needs a <= R): reduce the load or depth"
    )]
    HertzOutOfRange {
        /// Indenter radius.
        radius_mm: f64,
        /// Computed contact radius.
        contact_radius_mm: f64,
    },
    /// An indentation depth was given for a point load.
    #[error("a point indenter has no indentation depth: give a normal force instead")]
    PointDepth,
}

/// The indenter's shape.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Indenter {
    /// Flat-ended cylinder pressed face-on.
    Flat {
        /// Face diameter, mm.
        diameter_mm: f64,
    },
    /// Hemisphere (Hertz contact).
    Hemisphere {
        /// Radius, mm.
        radius_mm: f64,
    },
    /// Concentrated load.
    Point,
}

/// How hard the indenter presses.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Normal {
    /// Total normal force, N (≥ 0).
    ForceN(f64),
    /// Indentation depth, mm (≥ 0; flat or hemisphere only).
    DepthMm(f64),
}

/// The tangential part of a load.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Tangential {
    /// A tangential force `[Qx, Qy]`, N.
    ForceN([f64; 2]),
    /// The force inclined by `angle_deg` from the normal towards the azimuth
    /// `direction_deg` (from +x towards +y): `|Q| = P tan(angle)`.
    Angle {
        /// Inclination from the surface normal, degrees in [0, 90).
        angle_deg: f64,
        /// Azimuth of the tangential part, degrees.
        direction_deg: f64,
    },
}

impl Tangential {
    /// No tangential load.
    pub const NONE: Tangential = Tangential::ForceN([0.0, 0.0]);
}

/// A load case: where, how hard, and the tangential part.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoadCase {
    /// Indenter centre on the surface, mm.
    pub position_mm: [f64; 2],
    /// Normal load.
    pub normal: Normal,
    /// Requested tangential load.
    pub tangential: Tangential,
    /// Friction coefficient μ limiting `|Q| ≤ μ P`.
    pub friction: f64,
}

impl LoadCase {
    /// This load scaled by `s` (a ramp step): the normal force or depth and a
    /// tangential force are scaled, an inclination angle is kept.
    pub fn scaled(&self, s: f64) -> LoadCase {
        LoadCase {
            normal: match self.normal {
                Normal::ForceN(f) => Normal::ForceN(f * s),
                Normal::DepthMm(d) => Normal::DepthMm(d * s),
            },
            tangential: match self.tangential {
                Tangential::ForceN(q) => Tangential::ForceN([q[0] * s, q[1] * s]),
                a @ Tangential::Angle { .. } => a,
            },
            ..*self
        }
    }
}

/// One discretised surface force.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointLoad {
    /// Point of action on the surface, mm.
    pub position_mm: [f64; 2],
    /// Force `[fx, fy, fz]`, N (`fz > 0` presses in).
    pub force_n: [f64; 3],
}

/// A solved contact: the discretised traction and its resultants.
#[derive(Debug, Clone, PartialEq)]
pub struct Contact {
    /// The cell forces.
    pub loads: Vec<PointLoad>,
    /// Total normal force P, N.
    pub normal_force_n: f64,
    /// Total tangential force applied (after clamping), N.
    pub tangential_n: [f64; 2],
    /// Contact radius a, mm (0 for a point load).
    pub contact_radius_mm: f64,
    /// Indentation depth δ, mm (`None` for a point load).
    pub indentation_mm: Option<f64>,
    /// `Some(|Q| requested)` when the tangential load was clamped to `μP`.
    pub clamped_tangential_n: Option<f64>,
}

/// Pressure profile of a ring model.
#[derive(Clone, Copy)]
enum Profile {
    Flat,
    Hertz,
}

impl Profile {
    /// Fraction of the load inside radius `ρ = a sin φ`.
    fn cumulative(self, phi: f64) -> f64 {
        match self {
            Profile::Flat => 1.0 - phi.cos(),
            Profile::Hertz => 1.0 - phi.cos().powi(3),
        }
    }

    /// `∫ ρ dP / a` over `[φ0, φ1]`, in the same normalisation as [`Self::cumulative`].
    fn first_moment(self, phi0: f64, phi1: f64) -> f64 {
        // dP ∝ sin φ dφ (flat) or 3 cos²φ sin φ dφ (Hertz); ρ/a = sin φ.
        let f = |p: f64| match self {
            Profile::Flat => p / 2.0 - (2.0 * p).sin() / 4.0,
            Profile::Hertz => 3.0 * (p / 8.0 - (4.0 * p).sin() / 32.0),
        };
        f(phi1) - f(phi0)
    }
}

fn reduced_modulus(m: &HalfSpace) -> f64 {
    m.young_n_per_mm2 / (1.0 - m.poisson * m.poisson)
}

/// Hertz: normal force (N) for an indentation depth δ (mm) of a sphere of radius R (mm).
pub fn hertz_force_n(m: &HalfSpace, radius_mm: f64, depth_mm: f64) -> f64 {
    4.0 / 3.0 * reduced_modulus(m) * radius_mm.sqrt() * depth_mm.powf(1.5)
}

/// Hertz: contact radius (mm) for a normal force P (N) on a sphere of radius R (mm).
pub fn hertz_radius_mm(m: &HalfSpace, radius_mm: f64, force_n: f64) -> f64 {
    (3.0 * force_n * radius_mm / (4.0 * reduced_modulus(m))).cbrt()
}

/// `v` when it is a finite number ≥ 0 (`what`: its unit, for the message).
fn nonneg(key: &'static str, v: f64, what: &str) -> Result<f64, ContactError> {
    if v.is_finite() && v >= 0.0 {
        Ok(v)
    } else {
        Err(ContactError::Invalid {
            key,
            value: v,
            allowed: format!("must be a finite number >= 0 {what}"),
        })
    }
}

/// The normal part of a solved contact.
struct NormalContact {
    /// Total normal force P, N.
    p: f64,
    /// Contact radius a, mm (0 for a point load).
    a: f64,
    /// Indentation depth δ, mm (`None` for a point load).
    delta: Option<f64>,
    /// Pressure profile (`None` for a point load).
    profile: Option<Profile>,
}

/// The normal contact of `indenter` under `normal` (the laws in the module docs).
fn normal_contact(
    model: &HalfSpace,
    indenter: Indenter,
    normal: Normal,
) -> Result<NormalContact, ContactError> {
    match (indenter, normal) {
        (Indenter::Flat { diameter_mm }, n) => flat_contact(reduced_modulus(model), diameter_mm, n),
        (Indenter::Hemisphere { radius_mm }, n) => hertz_contact(model, radius_mm, n),
        (Indenter::Point, Normal::ForceN(f)) => Ok(NormalContact {
            p: nonneg("normal force", f, "N")?,
            a: 0.0,
            delta: None,
            profile: None,
        }),
        (Indenter::Point, Normal::DepthMm(_)) => Err(ContactError::PointDepth),
    }
}

/// Flat punch of diameter `2a` on `E*` = `es`: `P = 2 a E* δ`.
fn flat_contact(es: f64, diameter_mm: f64, n: Normal) -> Result<NormalContact, ContactError> {
    let a = 0.5 * diameter_mm;
    if !(a.is_finite() && a > 0.0) {
        return Err(ContactError::Invalid {
            key: "diameter_mm",
            value: diameter_mm,
            allowed: "must be > 0 mm".into(),
        });
    }
    let (p, delta) = match n {
        Normal::ForceN(f) => {
            let f = nonneg("normal force", f, "N")?;
            (f, f / (2.0 * a * es))
        }
        Normal::DepthMm(d) => {
            let d = nonneg("depth_mm", d, "mm")?;
            (2.0 * a * es * d, d)
        }
    };
    Ok(NormalContact {
        p,
        a,
        delta: Some(delta),
        profile: Some(Profile::Flat),
    })
}

/// Hertz contact of a hemisphere of radius `R`: from a load `a = (3PR/(4E*))^{1/3}`,
/// `δ = a²/R`; from a depth `a = √(Rδ)`, `P = 4/3 E* √R δ^{3/2}`; refused when `a > R`.
fn hertz_contact(
    model: &HalfSpace,
    radius_mm: f64,
    n: Normal,
) -> Result<NormalContact, ContactError> {
    if !(radius_mm.is_finite() && radius_mm > 0.0) {
        return Err(ContactError::Invalid {
            key: "radius_mm",
            value: radius_mm,
            allowed: "must be > 0 mm".into(),
        });
    }
    let (p, a, d) = match n {
        Normal::ForceN(f) => {
            let f = nonneg("normal force", f, "N")?;
            let a = hertz_radius_mm(model, radius_mm, f);
            (f, a, a * a / radius_mm)
        }
        Normal::DepthMm(d) => {
            let d = nonneg("depth_mm", d, "mm")?;
            (
                hertz_force_n(model, radius_mm, d),
                (radius_mm * d).sqrt(),
                d,
            )
        }
    };
    if a > radius_mm {
        return Err(ContactError::HertzOutOfRange {
            radius_mm,
            contact_radius_mm: a,
        });
    }
    Ok(NormalContact {
        p,
        a,
        delta: Some(d),
        profile: Some(Profile::Hertz),
    })
}

/// The tangential force requested, `[Qx, Qy]` N, before the friction limit: as given,
/// or `|Q| = P tan θ` along the azimuth of an inclined load.
fn requested_tangential(tangential: Tangential, p: f64) -> Result<[f64; 2], ContactError> {
    match tangential {
        Tangential::ForceN(q) => {
            for (key, v) in [("tangential force x", q[0]), ("tangential force y", q[1])] {
                if !v.is_finite() {
                    return Err(ContactError::Invalid {
                        key,
                        value: v,
                        allowed: "must be finite (N)".into(),
                    });
                }
            }
            Ok(q)
        }
        Tangential::Angle {
            angle_deg,
            direction_deg,
        } => {
            if !(angle_deg.is_finite() && (0.0..90.0).contains(&angle_deg)) {
                return Err(ContactError::Invalid {
                    key: "angle_deg",
                    value: angle_deg,
                    allowed: "must be in [0, 90) degrees from the normal".into(),
                });
            }
            if !direction_deg.is_finite() {
                return Err(ContactError::Invalid {
                    key: "direction_deg",
                    value: direction_deg,
                    allowed: "must be finite (degrees)".into(),
                });
            }
            let qm = p * angle_deg.to_radians().tan();
            let d = direction_deg.to_radians();
            Ok([qm * d.cos(), qm * d.sin()])
        }
    }
}

/// Coulomb's limit `|Q| ≤ μP`: a larger request is scaled down to `μP` in its
/// direction; the requested `|Q|` is returned when it was.
fn friction_limit(q_wanted: [f64; 2], mu: f64, p: f64) -> ([f64; 2], Option<f64>) {
    let q_req = q_wanted[0].hypot(q_wanted[1]);
    if q_req > mu * p {
        let s = if q_req > 0.0 { mu * p / q_req } else { 0.0 };
        ([q_wanted[0] * s, q_wanted[1] * s], Some(q_req))
    } else {
        (q_wanted, None)
    }
}

/// The cell forces of the force `total` = `[Qx, Qy, P]` centred at `c` (see
/// "Discretisation" in the module docs): one load at `c` for a point load or when
/// there is nothing to spread, else each ring's exact share of the load over its
/// sectors, at the sectors' centres of load.
fn cell_loads(profile: Option<Profile>, a: f64, c: [f64; 2], total: [f64; 3]) -> Vec<PointLoad> {
    let (p, q) = (total[2], [total[0], total[1]]);
    let profile = match profile {
        Some(profile) if !(a == 0.0 || p == 0.0 && q == [0.0, 0.0]) => profile,
        _ => {
            return vec![PointLoad {
                position_mm: c,
                force_n: total,
            }]
        }
    };
    let mut loads = Vec::new();
    let n_rings = (a / CELL_MM).ceil().max(1.0) as usize;
    for k in 0..n_rings {
        let rho0 = a * k as f64 / n_rings as f64;
        let rho1 = a * (k + 1) as f64 / n_rings as f64;
        let phi0 = (rho0 / a).clamp(0.0, 1.0).asin();
        let phi1 = (rho1 / a).clamp(0.0, 1.0).asin();
        let frac = profile.cumulative(phi1) - profile.cumulative(phi0);
        if frac <= 0.0 {
            continue;
        }
        let rho_mean = a * profile.first_moment(phi0, phi1) / frac;
        let circumference = 2.0 * std::f64::consts::PI * 0.5 * (rho0 + rho1);
        let n_sec = (circumference / CELL_MM).ceil().max(3.0) as usize;
        let dth = 2.0 * std::f64::consts::PI / n_sec as f64;
        let r_c = rho_mean * (0.5 * dth).sin() / (0.5 * dth);
        let share = frac / n_sec as f64;
        for s in 0..n_sec {
            let th = (s as f64 + 0.5) * dth;
            loads.push(PointLoad {
                position_mm: [c[0] + r_c * th.cos(), c[1] + r_c * th.sin()],
                force_n: [total[0] * share, total[1] * share, total[2] * share],
            });
        }
    }
    loads
}

impl Contact {
    /// Solves a load case for an indenter on the half-space `model`: the normal
    /// contact, the tangential force requested and clamped to `μP`, the cell forces.
    pub fn solve(
        model: &HalfSpace,
        indenter: Indenter,
        load: &LoadCase,
    ) -> Result<Contact, ContactError> {
        for (key, v) in [
            ("position_mm[0]", load.position_mm[0]),
            ("position_mm[1]", load.position_mm[1]),
        ] {
            if !v.is_finite() {
                return Err(ContactError::Invalid {
                    key,
                    value: v,
                    allowed: "must be finite (mm)".into(),
                });
            }
        }
        let mu = nonneg("friction_coefficient", load.friction, "")?;
        let NormalContact {
            p,
            a,
            delta,
            profile,
        } = normal_contact(model, indenter, load.normal)?;
        let q_wanted = requested_tangential(load.tangential, p)?;
        let (q, clamped) = friction_limit(q_wanted, mu, p);
        let loads = cell_loads(profile, a, load.position_mm, [q[0], q[1], p]);
        Ok(Contact {
            loads,
            normal_force_n: p,
            tangential_n: q,
            contact_radius_mm: a,
            indentation_mm: delta,
            clamped_tangential_n: clamped,
        })
    }

    /// Sum of the cell forces, N.
    pub fn total_force_n(&self) -> [f64; 3] {
        let mut t = [0.0; 3];
        for l in &self.loads {
            for (ti, fi) in t.iter_mut().zip(l.force_n) {
                *ti += fi;
            }
        }
        t
    }

    /// Marker displacements (interleaved `ux, uy`, mm) at `sites` (depths > 0).
    pub fn marker_displacements_mm(&self, model: &HalfSpace, sites: &[MarkerSite]) -> Vec<f64> {
        let mut u = vec![0.0; 2 * sites.len()];
        for (k, s) in sites.iter().enumerate() {
            let mut acc = [0.0; 2];
            for l in &self.loads {
                let d = model.displacement(
                    s.position_mm[0] - l.position_mm[0],
                    s.position_mm[1] - l.position_mm[1],
                    s.depth_mm,
                    l.force_n,
                );
                acc[0] += d[0];
                acc[1] += d[1];
            }
            u[2 * k] = acc[0];
            u[2 * k + 1] = acc[1];
        }
        u
    }

    /// The traction integrated over each node's cell of `grid` (interleaved `fx, fy, fz`
    /// per node, row-major, N); sums to [`Self::total_force_n`].
    pub fn force_grid_n(&self, grid: &Grid) -> Vec<f64> {
        let mut f = vec![0.0; 3 * grid.len()];
        for l in &self.loads {
            let ix = ((l.position_mm[0] - grid.origin_mm[0]) / grid.pitch_mm).round();
            let iy = ((l.position_mm[1] - grid.origin_mm[1]) / grid.pitch_mm).round();
            let ix = ix.clamp(0.0, (grid.nx - 1) as f64) as usize;
            let iy = iy.clamp(0.0, (grid.ny - 1) as f64) as usize;
            let j = iy * grid.nx + ix;
            for b in 0..3 {
                f[3 * j + b] += l.force_n[b];
            }
        }
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn paper_model() -> HalfSpace {
        HalfSpace::new(1.0, 0.5).unwrap()
    }

    fn load(normal: Normal, q: [f64; 2]) -> LoadCase {
        LoadCase {
            position_mm: [4.0, 3.0],
            normal,
            tangential: Tangential::ForceN(q),
            friction: 1.0,
        }
    }

    #[test]
    fn angle_gives_tangential_load_p_tan_angle_in_its_direction() {
        let m = paper_model();
        let mut l = load(Normal::ForceN(2.0), [0.0, 0.0]);
        l.tangential = Tangential::Angle {
            angle_deg: 30.0,
            direction_deg: 90.0,
        };
        let c = Contact::solve(&m, Indenter::Flat { diameter_mm: 5.0 }, &l).unwrap();
        let t = c.total_force_n();
        assert!(t[0].abs() < 1e-12 && (t[1] - 2.0 * 30f64.to_radians().tan()).abs() < 1e-12);
        assert!((t[1].atan2(t[2]).to_degrees() - 30.0).abs() < 1e-9);
    }

    #[test]
    fn flat_punch_cells_sum_to_the_applied_force_and_centre() {
        let m = paper_model();
        let c = Contact::solve(
            &m,
            Indenter::Flat { diameter_mm: 5.0 },
            &load(Normal::ForceN(8.924), [1.0, -2.0]),
        )
        .unwrap();
        let t = c.total_force_n();
        assert!(
            (t[2] - 8.924).abs() < 1e-12
                && (t[0] - 1.0).abs() < 1e-12
                && (t[1] + 2.0).abs() < 1e-12,
            "{t:?}"
        );
        // First moment: centre of pressure at the indenter centre (1e-9 mm).
        let mx: f64 = c
            .loads
            .iter()
            .map(|l| l.force_n[2] * l.position_mm[0])
            .sum::<f64>()
            / t[2];
        assert!((mx - 4.0).abs() < 1e-9, "{mx}");
        assert!(c
            .loads
            .iter()
            .all(|l| ((l.position_mm[0] - 4.0).hypot(l.position_mm[1] - 3.0)) <= 2.5));
    }

    #[test]
    fn flat_punch_ring_loads_follow_the_singular_pressure() {
        // Load within radius ρ: P (1 − √(1 − ρ²/a²)); at ρ = a/2: P (1 − √0.75).
        let m = paper_model();
        let c = Contact::solve(
            &m,
            Indenter::Flat { diameter_mm: 4.0 },
            &load(Normal::ForceN(1.0), [0.0, 0.0]),
        )
        .unwrap();
        let inner: f64 = c
            .loads
            .iter()
            .filter(|l| (l.position_mm[0] - 4.0).hypot(l.position_mm[1] - 3.0) < 1.0)
            .map(|l| l.force_n[2])
            .sum();
        assert!((inner - (1.0 - 0.75f64.sqrt())).abs() < 1e-12, "{inner}");
        // Flat-punch stiffness P = 2 a E* δ, E* = 4/3 for E = 1, ν = 0.5.
        assert!((c.indentation_mm.unwrap() - 1.0 / (2.0 * 2.0 * 4.0 / 3.0)).abs() < 1e-15);
    }

    #[test]
    fn hertz_force_depth_relation_and_consistency() {
        let m = paper_model();
        let r = 2.5;
        let by_depth = Contact::solve(
            &m,
            Indenter::Hemisphere { radius_mm: r },
            &load(Normal::DepthMm(0.8), [0.0, 0.0]),
        )
        .unwrap();
        // P = 4/3 E* √R δ^{3/2} with E* = 4/3.
        let p = 4.0 / 3.0 * 4.0 / 3.0 * r.sqrt() * 0.8f64.powf(1.5);
        assert!((by_depth.normal_force_n - p).abs() < 1e-12 * p);
        assert!((by_depth.contact_radius_mm - (r * 0.8f64).sqrt()).abs() < 1e-12);
        let by_force = Contact::solve(
            &m,
            Indenter::Hemisphere { radius_mm: r },
            &load(Normal::ForceN(p), [0.0, 0.0]),
        )
        .unwrap();
        assert!((by_force.contact_radius_mm - by_depth.contact_radius_mm).abs() < 1e-12);
        assert!((by_force.indentation_mm.unwrap() - 0.8).abs() < 1e-12);
        assert!((by_force.total_force_n()[2] - p).abs() < 1e-12 * p);
    }

    #[test]
    fn hertz_rejects_contact_wider_than_the_sphere() {
        let m = paper_model();
        let e = Contact::solve(
            &m,
            Indenter::Hemisphere { radius_mm: 1.0 },
            &load(Normal::ForceN(50.0), [0.0, 0.0]),
        )
        .unwrap_err();
        assert!(matches!(e, ContactError::HertzOutOfRange { .. }));
        assert!(e.to_string().contains("radius 1 mm"), "{e}");
    }

    #[test]
    fn tangential_load_is_clamped_at_friction_limit_and_reported() {
        let m = paper_model();
        let mut l = load(Normal::ForceN(2.0), [3.0, 4.0]);
        l.friction = 0.5;
        let c = Contact::solve(&m, Indenter::Point, &l).unwrap();
        assert_eq!(c.clamped_tangential_n, Some(5.0));
        let q = c.tangential_n;
        assert!((q[0].hypot(q[1]) - 1.0).abs() < 1e-12 && (q[1] / q[0] - 4.0 / 3.0).abs() < 1e-12);
        l.friction = 3.0;
        assert_eq!(
            Contact::solve(&m, Indenter::Point, &l)
                .unwrap()
                .clamped_tangential_n,
            None
        );
    }

    #[test]
    fn distributed_load_acts_like_a_point_load_far_away() {
        // At 15 mm from a 5 mm flat punch the multipole correction is O((a/r)²) ≈ 3%.
        let m = paper_model();
        let l = load(Normal::ForceN(5.0), [1.0, 0.5]);
        let flat = Contact::solve(&m, Indenter::Flat { diameter_mm: 5.0 }, &l).unwrap();
        let point = Contact::solve(&m, Indenter::Point, &l).unwrap();
        let site = [MarkerSite {
            layer: 0,
            position_mm: [19.0, 3.0],
            depth_mm: 3.0,
        }];
        let uf = flat.marker_displacements_mm(&m, &site);
        let up = point.marker_displacements_mm(&m, &site);
        assert!(
            (uf[0] - up[0]).abs() < 0.03 * up[0].abs(),
            "{uf:?} vs {up:?}"
        );
    }

    #[test]
    fn force_grid_truth_sums_to_the_load() {
        let m = paper_model();
        let g = Grid {
            nx: 10,
            ny: 8,
            pitch_mm: 2.2,
            origin_mm: [-0.9, -0.95],
        };
        let c = Contact::solve(
            &m,
            Indenter::Hemisphere { radius_mm: 2.5 },
            &load(Normal::ForceN(7.0), [1.5, 0.0]),
        )
        .unwrap();
        let f = c.force_grid_n(&g);
        for b in 0..3 {
            let s: f64 = f.iter().skip(b).step_by(3).sum();
            assert!((s - c.total_force_n()[b]).abs() < 1e-12, "axis {b}: {s}");
        }
    }
}
