//! The elastic half-space: Boussinesq (normal load) and Cerruti (tangential load)
//! point responses, paper Eq. 1–2, and their vertical components.
//!
//! A point force `f = (fx, fy, fz)` applied at the origin of the surface of a
//! homogeneous, isotropic, linear-elastic half-space (Young's modulus `E`, Poisson
//! ratio `σ`) moves an interior point `r = (x, y, z)`, `z > 0` below the surface, by
//! (paper Eq. 1 and 2, which combine the Boussinesq solution for the normal load with
//! the Cerruti solution for the tangential load; Johnson, *Contact Mechanics*, §3.2):
//!
//! ```text
//! u_x = (1+σ)/(2πE) { [xz/r³ − (1−2σ)x/(r(r+z))] f_z + (2(1−σ)r + z)/(r(r+z)) f_x
//!                     + [2r(σr + z) + z²] x / (r³(r+z)²) (x f_x + y f_y) }
//! u_y = (1+σ)/(2πE) { [yz/r³ − (1−2σ)y/(r(r+z))] f_z + (2(1−σ)r + z)/(r(r+z)) f_y
//!                     + [2r(σr + z) + z²] y / (r³(r+z)²) (x f_x + y f_y) }
//! ```
//!
//! and, out of plane (z positive into the elastomer, so `u_z > 0` moves a point
//! deeper; Johnson Eq. 3.22c for the normal load and 3.86c for the tangential load,
//! with `(1+σ)/(2πE) = 1/(4πG)`):
//!
//! ```text
//! u_z = (1+σ)/(2πE) { [2(1−σ)/r + z²/r³] f_z + [z/r³ + (1−2σ)/(r(r+z))] (x f_x + y f_y) }
//! ```
//!
//! with `r = |r|`. Units: mm, N and N/mm² give displacements in mm. `f_z > 0` presses
//! into the elastomer (+z is depth). The paper fixes σ = 0.5 and E = 1; here both come
//! from `sensor.toml` (`young_modulus_kpa` is converted to N/mm² once, in
//! [`crate::units`]).

use super::{ElasticModel, ModelError, PointResponse, PointResponse3};
use crate::sensor::Elastomer;

/// The half-space material: everything Eq. 1–2 need besides geometry.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HalfSpace {
    /// Poisson ratio σ in [0, 0.5].
    pub poisson: f64,
    /// Young's modulus E in N/mm².
    pub young_n_per_mm2: f64,
}

impl HalfSpace {
    /// A half-space with the given constants, checked.
    pub fn new(young_n_per_mm2: f64, poisson: f64) -> Result<Self, ModelError> {
        let ok = young_n_per_mm2.is_finite()
            && young_n_per_mm2 > 0.0
            && poisson.is_finite()
            && (0.0..=0.5).contains(&poisson);
        if ok {
            Ok(HalfSpace {
                poisson,
                young_n_per_mm2,
            })
        } else {
            Err(ModelError::BadMaterial {
                young_n_per_mm2,
                poisson,
            })
        }
    }

    /// The material of a (validated) elastomer.
    pub fn from_elastomer(e: &Elastomer) -> Self {
        HalfSpace {
            poisson: e.poisson_ratio,
            young_n_per_mm2: e.young_modulus_n_per_mm2(),
        }
    }

    /// Eq. 1–2: response at offset `(dx, dy)` mm from the force point and depth `z` mm.
    ///
    /// Finite for every `z > 0`, including a marker exactly above the force point
    /// (`dx = dy = 0`, `r = z`). At `z = 0` and `r = 0` the point load is singular;
    /// callers guarantee `z > 0` (sensor validation and [`transfer_matrix`] check it).
    #[inline]
    pub fn point_response(&self, dx: f64, dy: f64, z: f64) -> PointResponse {
        let s = self.poisson;
        let c = (1.0 + s) / (2.0 * std::f64::consts::PI * self.young_n_per_mm2);
        let r2 = dx * dx + dy * dy + z * z;
        let r = r2.sqrt();
        let r3 = r2 * r;
        let rz = r + z;
        // Normal load (Boussinesq): [xz/r³ − (1−2σ)x/(r(r+z))].
        let a = z / r3 - (1.0 - 2.0 * s) / (r * rz);
        // Tangential load (Cerruti), isotropic part and the (x fx + y fy) part.
        let b = (2.0 * (1.0 - s) * r + z) / (r * rz);
        let g = (2.0 * r * (s * r + z) + z * z) / (r3 * rz * rz);
        [
            [c * (b + g * dx * dx), c * g * dx * dy, c * a * dx],
            [c * g * dx * dy, c * (b + g * dy * dy), c * a * dy],
        ]
    }

    /// Displacement `(u_x, u_y)` in mm at offset `(dx, dy)` and depth `z` from a force
    /// `f` in N applied at the surface point.
    #[inline]
    pub fn displacement(&self, dx: f64, dy: f64, z: f64, f: [f64; 3]) -> [f64; 2] {
        let h = self.point_response(dx, dy, z);
        [
            h[0][0] * f[0] + h[0][1] * f[1] + h[0][2] * f[2],
            h[1][0] * f[0] + h[1][1] * f[1] + h[1][2] * f[2],
        ]
    }

    /// Eq. 1–2 and the vertical components: the full 3 × 3 response at offset
    /// `(dx, dy)` mm and depth `z > 0` mm, `h[a][b]` = displacement along `a`
    /// (x, y, z) per newton along `b` (x, y, z), mm/N. Rows 0 and 1 are exactly
    /// [`HalfSpace::point_response`].
    #[inline]
    pub fn point_response3(&self, dx: f64, dy: f64, z: f64) -> PointResponse3 {
        let [hx, hy] = self.point_response(dx, dy, z);
        let s = self.poisson;
        let c = (1.0 + s) / (2.0 * std::f64::consts::PI * self.young_n_per_mm2);
        let r2 = dx * dx + dy * dy + z * z;
        let r = r2.sqrt();
        let r3 = r2 * r;
        // Boussinesq u_z and Cerruti u_z (per unit of x f_x + y f_y).
        let n = 2.0 * (1.0 - s) / r + z * z / r3;
        let t = z / r3 + (1.0 - 2.0 * s) / (r * (r + z));
        [hx, hy, [c * t * dx, c * t * dy, c * n]]
    }

    /// Displacement `(u_x, u_y, u_z)` in mm at offset `(dx, dy)` and depth `z` from a
    /// force `f` in N applied at the surface point.
    #[inline]
    pub fn displacement3(&self, dx: f64, dy: f64, z: f64, f: [f64; 3]) -> [f64; 3] {
        let h = self.point_response3(dx, dy, z);
        std::array::from_fn(|a| h[a][0] * f[0] + h[a][1] * f[1] + h[a][2] * f[2])
    }
}

impl ElasticModel for HalfSpace {
    fn point_response(&self, dx: f64, dy: f64, z: f64) -> PointResponse {
        HalfSpace::point_response(self, dx, dy, z)
    }

    fn point_response3(&self, dx: f64, dy: f64, z: f64) -> PointResponse3 {
        HalfSpace::point_response3(self, dx, dy, z)
    }

    fn displacement(&self, dx: f64, dy: f64, z: f64, f: [f64; 3]) -> [f64; 2] {
        HalfSpace::displacement(self, dx, dy, z, f)
    }

    fn max_depth_mm(&self) -> f64 {
        f64::INFINITY
    }
}

#[cfg(test)]
mod tests {
    //! Eq. 1–2 against the textbook closed forms, written independently here
    //! (Johnson, Contact Mechanics, Eq. 3.22 Boussinesq and 3.34 Cerruti, rotated).
    use super::*;
    use crate::model::ElasticModel;
    use crate::model::{forward, forward3, transfer_matrix, MarkerSite};
    use std::f64::consts::PI;

    /// Boussinesq, horizontal displacement of a normal point load P (into the solid).
    fn boussinesq_ur(p: f64, rho: f64, z: f64, nu: f64, e: f64) -> f64 {
        let r = (rho * rho + z * z).sqrt();
        p * (1.0 + nu) / (2.0 * PI * e * r) * (rho * z / (r * r) - (1.0 - 2.0 * nu) * rho / (r + z))
    }

    /// Cerruti, displacements of a tangential point load Q along x.
    fn cerruti(q: f64, x: f64, y: f64, z: f64, nu: f64, e: f64) -> [f64; 2] {
        let r = (x * x + y * y + z * z).sqrt();
        let k = q * (1.0 + nu) / (2.0 * PI * e * r);
        let ux = k
            * (1.0
                + x * x / (r * r)
                + (1.0 - 2.0 * nu) * (r / (r + z) - x * x / ((r + z) * (r + z))));
        let uy = k * (x * y / (r * r) - (1.0 - 2.0 * nu) * x * y / ((r + z) * (r + z)));
        [ux, uy]
    }

    fn close(a: f64, b: f64, rel: f64) -> bool {
        (a - b).abs() <= rel * a.abs().max(b.abs()).max(1e-300)
    }

    const NUS: [f64; 4] = [0.0, 0.25, 0.45, 0.5];

    #[test]
    fn normal_load_matches_boussinesq_for_all_poisson_ratios() {
        for nu in NUS {
            let m = HalfSpace::new(0.7, nu).unwrap();
            for &(x, y, z) in &[
                (1.0, 0.0, 3.0),
                (0.3, -2.0, 6.0),
                (-4.0, 5.0, 0.5),
                (0.0, 1e-3, 13.0),
            ] {
                let u = m.displacement(x, y, z, [0.0, 0.0, 2.5]);
                let rho = (x * x + y * y).sqrt();
                let ur = boussinesq_ur(2.5, rho, z, nu, 0.7);
                assert!(
                    close(u[0], ur * x / rho, 1e-12),
                    "nu={nu} ({x},{y},{z}): {} vs {}",
                    u[0],
                    ur * x / rho
                );
                assert!(close(u[1], ur * y / rho, 1e-12));
            }
        }
    }

    #[test]
    fn tangential_load_matches_cerruti_along_both_axes() {
        for nu in NUS {
            let m = HalfSpace::new(1.3, nu).unwrap();
            for &(x, y, z) in &[(1.0, 0.5, 3.0), (-2.0, 1.0, 6.0), (0.2, -0.1, 0.3)] {
                let u = m.displacement(x, y, z, [0.8, 0.0, 0.0]);
                let c = cerruti(0.8, x, y, z, nu, 1.3);
                assert!(
                    close(u[0], c[0], 1e-12) && close(u[1], c[1], 1e-12),
                    "nu={nu}"
                );
                // A load along y is the x case rotated by 90°: (x, y) -> (y, -x).
                let u = m.displacement(x, y, z, [0.0, 0.8, 0.0]);
                let c = cerruti(0.8, y, -x, z, nu, 1.3);
                assert!(
                    close(u[1], c[0], 1e-12) && close(-u[0], c[1], 1e-12),
                    "nu={nu}"
                );
            }
        }
    }

    #[test]
    fn surface_limit_matches_johnson_surface_displacements() {
        // z -> 0: u_r = -(1-2ν)(1+ν)P/(2πE r) and Cerruti surface u_x = Q(1+ν)/(πE r)[(1-ν) + ν x²/r²].
        for nu in NUS {
            let m = HalfSpace::new(1.0, nu).unwrap();
            let (x, y, z): (f64, f64, f64) = (1.2, 0.9, 1e-9);
            let rho = (x * x + y * y).sqrt();
            let u = m.displacement(x, y, z, [0.0, 0.0, 1.0]);
            let ur = -(1.0 - 2.0 * nu) * (1.0 + nu) / (2.0 * PI * rho);
            assert!((u[0] - ur * x / rho).abs() < 1e-8, "nu={nu}");
            let u = m.displacement(x, y, z, [1.0, 0.0, 0.0]);
            let ux = (1.0 + nu) / (PI * rho) * ((1.0 - nu) + nu * x * x / (rho * rho));
            assert!((u[0] - ux).abs() < 1e-8, "nu={nu}: {} vs {ux}", u[0]);
        }
    }

    #[test]
    fn response_has_the_half_space_symmetries() {
        let m = HalfSpace::new(1.0, 0.5).unwrap();
        let h = m.point_response(1.3, -0.4, 3.0);
        // Reciprocity of the tangential block: h_xy = h_yx.
        assert_eq!(h[0][1], h[1][0]);
        // Mirror x -> -x flips u_x for fz and fy, keeps it for fx.
        let hm = m.point_response(-1.3, -0.4, 3.0);
        assert!(close(hm[0][2], -h[0][2], 1e-14) && close(hm[1][2], h[1][2], 1e-14));
        assert!(close(hm[0][0], h[0][0], 1e-14) && close(hm[0][1], -h[0][1], 1e-14));
        // Swapping x and y swaps the roles of the axes.
        let hs = m.point_response(-0.4, 1.3, 3.0);
        assert!(close(hs[1][1], h[0][0], 1e-14) && close(hs[1][2], h[0][2], 1e-14));
        // Directly above the load: no horizontal motion from fz, isotropic in x/y.
        let h0 = m.point_response(0.0, 0.0, 3.0);
        assert_eq!(h0[0][2], 0.0);
        assert_eq!(h0[0][0], h0[1][1]);
        assert!(h0[0][0].is_finite() && h0[0][0] > 0.0);
    }

    #[test]
    fn scales_inversely_with_modulus_and_linearly_with_force() {
        let a = HalfSpace::new(1.0, 0.4)
            .unwrap()
            .displacement(0.5, 0.7, 2.0, [0.1, 0.2, 0.3]);
        let b = HalfSpace::new(2.0, 0.4)
            .unwrap()
            .displacement(0.5, 0.7, 2.0, [0.2, 0.4, 0.6]);
        assert!(close(a[0], b[0], 1e-14) && close(a[1], b[1], 1e-14));
    }

    #[test]
    fn transfer_matrix_follows_design_row_column_order() {
        let m = HalfSpace::new(1.0, 0.5).unwrap();
        let markers = [
            MarkerSite {
                layer: 0,
                position_mm: [0.0, 0.0],
                depth_mm: 3.0,
            },
            MarkerSite {
                layer: 1,
                position_mm: [1.0, 2.0],
                depth_mm: 6.0,
            },
        ];
        let fps = [[0.5, 0.5], [2.0, -1.0], [3.0, 3.0]];
        let h = transfer_matrix(&m, &markers, &fps).unwrap();
        assert_eq!(h.shape(), (4, 9));
        let r = m.point_response(1.0 - 2.0, 2.0 + 1.0, 6.0);
        assert_eq!(h[(3, 3 + 2)], r[1][2]); // marker 1 uy, force point 1 fz
        assert_eq!(h[(2, 3)], r[0][0]); // marker 1 ux, force point 1 fx
        let f = [0.1, -0.2, 0.3, 0.0, 0.5, 1.0, -0.3, 0.2, 0.1];
        let u = forward(&m, &markers, &fps, &f).unwrap();
        let hu = &h * nalgebra::DVector::from_column_slice(&f);
        for i in 0..4 {
            assert!(close(u[i], hu[i], 1e-13));
        }
    }

    #[test]
    fn rejects_markers_on_the_surface_and_bad_material() {
        let m = HalfSpace::new(1.0, 0.5).unwrap();
        let markers = [MarkerSite {
            layer: 0,
            position_mm: [0.0, 0.0],
            depth_mm: 0.0,
        }];
        assert!(matches!(
            transfer_matrix(&m, &markers, &[[0.0, 0.0]]),
            Err(ModelError::BadDepth { .. })
        ));
        assert!(HalfSpace::new(1.0, 0.6).is_err());
        assert!(HalfSpace::new(0.0, 0.3).is_err());
        let nan = [MarkerSite {
            layer: 0,
            position_mm: [f64::NAN, 0.0],
            depth_mm: 1.0,
        }];
        assert!(transfer_matrix(&m, &nan, &[[0.0, 0.0]]).is_err());
    }

    /// Johnson Eq. 3.22c (Boussinesq) and 3.86c (Cerruti) vertical displacements,
    /// written independently: u_z = P/(4πG)[2(1−ν)/r + z²/r³],
    /// u_z = Q/(4πG)[xz/r³ + (1−2ν)x/(r(r+z))].
    fn johnson_uz(f: [f64; 3], x: f64, y: f64, z: f64, nu: f64, e: f64) -> f64 {
        let g = e / (2.0 * (1.0 + nu));
        let r = (x * x + y * y + z * z).sqrt();
        let k = 1.0 / (4.0 * PI * g);
        let t = |c: f64| c * z / r.powi(3) + (1.0 - 2.0 * nu) * c / (r * (r + z));
        k * (f[2] * (2.0 * (1.0 - nu) / r + z * z / r.powi(3)) + f[0] * t(x) + f[1] * t(y))
    }

    #[test]
    fn vertical_displacement_matches_johnson_and_its_surface_limit() {
        for nu in NUS {
            let m = HalfSpace::new(0.9, nu).unwrap();
            for &(x, y, z) in &[
                (1.0, 0.5, 3.0),
                (-2.0, 1.0, 6.0),
                (0.0, 0.0, 2.0),
                (4.0, -3.0, 0.2),
            ] {
                let f = [0.3, -0.7, 1.1];
                let u = m.displacement3(x, y, z, f);
                let want = johnson_uz(f, x, y, z, nu, 0.9);
                assert!(close(u[2], want, 1e-12), "nu={nu}: {} vs {want}", u[2]);
                // Rows x, y are Eq. 1–2 exactly.
                let h = m.displacement(x, y, z, f);
                assert_eq!([u[0], u[1]], h);
            }
            // Surface (z -> 0): u_z = (1−ν²)P/(πE ρ) under a normal load and
            // (1−2ν)(1+ν)Q x/(2πE ρ²) ahead of a tangential load.
            let (x, y, z) = (1.2, 0.9, 1e-9);
            let rho = f64::hypot(x, y);
            let u = m.displacement3(x, y, z, [0.0, 0.0, 1.0]);
            assert!((u[2] - (1.0 - nu * nu) / (PI * 0.9 * rho)).abs() < 1e-8);
            let u = m.displacement3(x, y, z, [1.0, 0.0, 0.0]);
            let want = (1.0 - 2.0 * nu) * (1.0 + nu) * x / (2.0 * PI * 0.9 * rho * rho);
            assert!((u[2] - want).abs() < 1e-8, "nu={nu}");
        }
    }

    #[test]
    fn vertical_displacement_symmetries_and_forward3() {
        let m = HalfSpace::new(1.0, 0.5).unwrap();
        let h = m.point_response3(1.3, -0.4, 3.0);
        let hm = m.point_response3(-1.3, -0.4, 3.0);
        // u_z under f_z is even in x; under f_x odd in x; above the load only f_z acts.
        assert!(close(hm[2][2], h[2][2], 1e-14) && close(hm[2][0], -h[2][0], 1e-14));
        let h0 = m.point_response3(0.0, 0.0, 3.0);
        assert_eq!(h0[2][0], 0.0);
        assert!(h0[2][2] > 0.0);
        let markers = [MarkerSite {
            layer: 0,
            position_mm: [1.0, 2.0],
            depth_mm: 6.0,
        }];
        let fps = [[0.5, 0.5], [2.0, -1.0]];
        let f = [0.1, -0.2, 0.3, 0.0, 0.5, 1.0];
        let u3 = forward3(&m, &markers, &fps, &f).unwrap();
        let u2 = forward(&m, &markers, &fps, &f).unwrap();
        assert!(close(u3[0], u2[0], 1e-14) && close(u3[1], u2[1], 1e-14));
        let want = m.displacement3(0.5, 1.5, 6.0, [0.1, -0.2, 0.3])[2]
            + m.displacement3(-1.0, 3.0, 6.0, [0.0, 0.5, 1.0])[2];
        assert!(close(u3[2], want, 1e-14));
        // The trait's generic path gives the inherent results bit for bit.
        assert_eq!(
            ElasticModel::point_response(&m, 0.3, 0.2, 3.0),
            m.point_response(0.3, 0.2, 3.0)
        );
    }
}
