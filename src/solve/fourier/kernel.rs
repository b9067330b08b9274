//! The kernel spectra the `fourier` solver's frequency blocks are built from, per marker
//! layer: `K̂_ℓ[q]` (2 × 3 per fine frequency `q`, unnormalised DFT convention of
//! `transform.rs`, layout `[comp][qx·N_y + qy]` with `comp = 3·axis_u + axis_f`).
//!
//! Two sources, one per use:
//!
//! - [`sampled_spectra`]: any [`ElasticModel`]'s real-space point responses sampled on
//!   the kernel window (every marker–force offset of the real grids occurs exactly
//!   once in it) and transformed. This is the **exact operator `H`** of the refinement
//!   (`refine.rs`: `forward_op` / `adjoint_op`): restricted to the measured markers and
//!   the force grid, the circular convolution is the linear one, so CGLS converges to
//!   dense Tikhonov on the `H` the dense solvers build from the same model (half-space
//!   Eq. 1–2, or the bonded layer's tabulated responses). For the half-space these
//!   spectra are also the periodic operator of the direct solve (its `k = 0` term is
//!   infinite, so the window-sampled kernel is the only periodic model it has).
//! - [`layer_spectra`]: the bonded layer's closed-form Fourier kernel
//!   ([`crate::model::layer_kernel`]) used **directly in frequency space** for the
//!   direct per-frequency solve, the λ search and the preconditioner. On the fine
//!   lattice of pitch `h` and period `N_x × N_y` the truly periodic layer problem (every
//!   force repeated with the period, which the layer's finite `k → 0` limit makes
//!   well defined) has, by Poisson summation,
//!
//! ```text
//! K̂_ℓ[q] = h⁻² Σ_{m ∈ Z²} K(k_q + 2πm/h, z_ℓ) · exp(i (k_q + 2πm/h)·d_ℓ),
//! k_q = 2π (q_x/(N_x h), q_y/(N_y h)),   d_ℓ = o_ℓ − o_f,
//! ```
//!
//! the aliases `m` of the fine frequency folded in, and `d_ℓ` the in-plane offset of
//! the layer's marker grid from the force grid (the same `marker − force` offset the
//! sampled kernel absorbs). `K` decays like `e^{−|k|z}`, so the alias sum is cut at
//! `|k| z ≤ 40` (the omitted terms are below `40·e^{−40} ≈ 2e−16` of the kernel at
//! `|k| ≈ 1/z`). The `k = 0` term is the uniform-traction layer, finite and exact
//! (the kernels' series branch, [`crate::model::layer::SERIES_BELOW_KH`]).
//! The sum costs about `π (40 h / (2π z))²` kernel evaluations per fine frequency and
//! layer: ~17 for markers at 3 mm on a 1.1 mm fine lattice (~4 at 6 mm), ~150 at
//! 1 mm depth, ~4000 at 0.2 mm (precompute only; very shallow markers on a large grid
//! make it the slowest part of the precompute).
//!
//! The direct solve with [`layer_spectra`] is exact on the periodic layer problem
//! (unit test below, against a dense Tikhonov solve of the periodic `H` written as a
//! Fourier series, to 1e−10); the refinement then removes the periodic model's
//! boundary error exactly as for the half-space.

use std::f64::consts::PI;

use rustfft::FftPlanner;

use super::transform::{fft2_transposed, C64};
use crate::model::{layer_kernel, BondedLayer, ElasticModel};

/// Where one marker layer's kernel lives on the fine lattice.
#[derive(Debug, Clone, Copy)]
pub(super) struct LayerSampling {
    /// Marker-grid origin minus force-grid origin, mm.
    pub(super) offset_mm: [f64; 2],
    /// The layer's depth, mm.
    pub(super) depth_mm: f64,
    /// First fine-lattice offset of the kernel window per axis: offsets `lo .. lo + N`.
    pub(super) lo: [i64; 2],
}

/// `|k|·z` beyond which alias terms are left out of [`layer_spectra`].
const ALIAS_KZ: f64 = 40.0;

/// The real-space responses of `model` sampled on the window and transformed (see the
/// module docs): `[comp][qx·N_y + qy]`.
pub(super) fn sampled_spectra<M: ElasticModel + ?Sized>(
    model: &M,
    s: &LayerSampling,
    period: [usize; 2],
    h: f64,
    planner: &mut FftPlanner<f64>,
) -> Result<Vec<Vec<C64>>, crate::model::ModelError> {
    let [nx, ny] = period;
    // Let a tabulated model build its table once for the whole window.
    let corner = |ax: usize, t: i64| s.offset_mm[ax] + h * t as f64;
    let reach = |ax: usize, n: usize| {
        corner(ax, s.lo[ax])
            .abs()
            .max(corner(ax, s.lo[ax] + n as i64 - 1).abs())
    };
    let rho_max = reach(0, nx).hypot(reach(1, ny));
    // The size of a tabulated model's table is checked before it is built.
    model.check_reach(&[s.depth_mm], rho_max)?;
    model.prepare(&[s.depth_mm], rho_max);
    let mut comps = vec![vec![C64::default(); nx * ny]; 6];
    for ty in s.lo[1]..s.lo[1] + ny as i64 {
        let iy = ty.rem_euclid(ny as i64) as usize;
        let dy = corner(1, ty);
        for tx in s.lo[0]..s.lo[0] + nx as i64 {
            let ix = tx.rem_euclid(nx as i64) as usize;
            let dx = corner(0, tx);
            let r = model.point_response(dx, dy, s.depth_mm);
            for (c, comp) in comps.iter_mut().enumerate() {
                comp[iy * nx + ix] = C64::new(r[c / 3][c % 3], 0.0);
            }
        }
    }
    Ok(comps
        .iter_mut()
        .map(|c| fft2_transposed(planner, c, nx, ny))
        .collect())
}

/// The bonded layer's periodic kernel spectra from its closed-form Fourier kernel (the
/// alias sum of the module docs): `[comp][qx·N_y + qy]`.
pub(super) fn layer_spectra(
    layer: &BondedLayer,
    s: &LayerSampling,
    period: [usize; 2],
    h: f64,
) -> Vec<Vec<C64>> {
    let [nx, ny] = period;
    let z = s.depth_mm;
    let kc = ALIAS_KZ / z;
    let g = 2.0 * PI / h;
    let inv_h2 = 1.0 / (h * h);
    // Centred representative of a fine frequency index (the alias sum is over all of
    // them; centring keeps the cut symmetric).
    let base = |q: usize, n: usize| {
        let qs = if 2 * q <= n {
            q as f64
        } else {
            q as f64 - n as f64
        };
        2.0 * PI * qs / (n as f64 * h)
    };
    let mut comps = vec![vec![C64::default(); nx * ny]; 6];
    for qx in 0..nx {
        let kx0 = base(qx, nx);
        let mx_lo = ((-kc - kx0) / g).ceil() as i64;
        let mx_hi = ((kc - kx0) / g).floor() as i64;
        for qy in 0..ny {
            let ky0 = base(qy, ny);
            let my_lo = ((-kc - ky0) / g).ceil() as i64;
            let my_hi = ((kc - ky0) / g).floor() as i64;
            let mut acc = [C64::default(); 6];
            for mx in mx_lo.min(0)..=mx_hi.max(0) {
                let kx = kx0 + g * mx as f64;
                for my in my_lo.min(0)..=my_hi.max(0) {
                    let ky = ky0 + g * my as f64;
                    let k2 = kx * kx + ky * ky;
                    // The fundamental (m = 0) always counts, however deep the layer.
                    if k2 > kc * kc && (mx, my) != (0, 0) {
                        continue;
                    }
                    let kern = layer_kernel(
                        kx,
                        ky,
                        z,
                        layer.thickness_mm,
                        layer.young_n_per_mm2,
                        layer.poisson,
                    );
                    let (sn, cs) = (kx * s.offset_mm[0] + ky * s.offset_mm[1]).sin_cos();
                    let phase = C64::new(cs, sn);
                    for (c, a) in acc.iter_mut().enumerate() {
                        *a += kern[c / 3][c % 3] * phase;
                    }
                }
            }
            let q = qx * ny + qy;
            for (comp, a) in comps.iter_mut().zip(acc) {
                comp[q] = a * inv_h2;
            }
        }
    }
    comps
}

#[cfg(test)]
mod tests {
    //! The bonded layer in the `fourier` solver: the direct solve is exact on the
    //! periodic layer problem, and the refinement's operator is the model's exact `H`.
    use super::super::refine::forward_op;
    use super::super::tests::{periodic_solve_error, pseudo_random};
    use super::super::FourierSolver;
    use super::*;
    use crate::model::{layer_kernel, MarkerSite};
    use crate::sensor::{grid_sensor, ModelKind, Sensor};
    use crate::solve::{Lambda, Method, Problem, SolverConfig};
    use nalgebra::DMatrix;

    /// A grid sensor on the bonded-layer model with the given thickness, layer depths
    /// and red-layer offset.
    fn layer_sensor(
        grid: (usize, usize, f64, f64),
        thickness_mm: f64,
        depths_mm: [f64; 2],
        offset: [f64; 2],
    ) -> Sensor {
        let mut s = grid_sensor(grid.0, grid.1, grid.2, grid.3);
        s.elastomer.model = ModelKind::BondedLayer;
        s.elastomer.thickness_mm = thickness_mm;
        s.layers[0].depth_mm = depths_mm[0];
        s.layers[1].depth_mm = depths_mm[1];
        s.layers[1].markers.as_mut().unwrap().grid.origin_mm = offset;
        s
    }

    /// Dense Tikhonov on the periodic layer operator, its entries the periodic Green's
    /// function written as a Fourier series over the reciprocal lattice of the period
    /// `(L_x, L_y)`, `G(Δ) = (L_x L_y)⁻¹ Σ_k K(k) e^{ik·Δ}` (cut at |k| z ≤ 50), against
    /// the solver's per-frequency solve of the same whole-lattice data.
    fn periodic_layer_case(s: &Sensor) {
        let sites = MarkerSite::from_sensor_grids(s);
        let p = Problem::new(s, &sites);
        let lambda = 0.05;
        let cfg = SolverConfig {
            method: Method::Fourier,
            lambda: Lambda::Fixed(lambda),
            fourier_padding: 0.0,
            ..SolverConfig::default()
        };
        let solver = FourierSolver::precompute(&p, &cfg, None).unwrap();
        let g = solver.geometry();
        let (a, b, h, period) = (g.force_factor, g.marker_factor, g.fine_pitch_mm, g.period);
        let (mm, mf) = (solver.plan.mm, solver.plan.mf);
        let fg = s.force_grid;
        let nl = s.layers.len();
        let e = &s.elastomer;
        let len = [period[0] as f64 * h, period[1] as f64 * h];
        let (nrow, ncol) = (2 * nl * mm[0] * mm[1], 3 * mf[0] * mf[1]);
        let mut c = DMatrix::<f64>::zeros(nrow, ncol);
        for (li, layer) in s.layers.iter().enumerate() {
            let grid = layer.markers.unwrap().grid;
            let z = layer.depth_mm;
            // The reciprocal lattice of the period, with the kernel at each point.
            let kc = 50.0 / z;
            let n = [
                (kc * len[0] / (2.0 * PI)).ceil() as i64,
                (kc * len[1] / (2.0 * PI)).ceil() as i64,
            ];
            let mut terms = Vec::new();
            for jx in -n[0]..=n[0] {
                for jy in -n[1]..=n[1] {
                    let k = [2.0 * PI * jx as f64 / len[0], 2.0 * PI * jy as f64 / len[1]];
                    if k[0].hypot(k[1]) <= kc {
                        let kern = layer_kernel(
                            k[0],
                            k[1],
                            z,
                            e.thickness_mm,
                            e.young_modulus_n_per_mm2(),
                            e.poisson_ratio,
                        );
                        terms.push((k, kern));
                    }
                }
            }
            let green = |d: [f64; 2]| {
                let mut acc = [[C64::default(); 3]; 2];
                for (k, kern) in &terms {
                    let (sn, cs) = (k[0] * d[0] + k[1] * d[1]).sin_cos();
                    for i in 0..2 {
                        for j in 0..3 {
                            acc[i][j] += kern[i][j] * C64::new(cs, sn);
                        }
                    }
                }
                acc.map(|row| row.map(|v| v.re / (len[0] * len[1])))
            };
            for iy in 0..mm[1] {
                for ix in 0..mm[0] {
                    for jy in 0..mf[1] {
                        for jx in 0..mf[0] {
                            let d = [
                                grid.origin_mm[0] - fg.origin_mm[0]
                                    + h * ((b * ix) as f64 - (a * jx) as f64),
                                grid.origin_mm[1] - fg.origin_mm[1]
                                    + h * ((b * iy) as f64 - (a * jy) as f64),
                            ];
                            let r = green(d);
                            let row = ((li * mm[1] + iy) * mm[0] + ix) * 2;
                            let col = (jy * mf[0] + jx) * 3;
                            for i in 0..2 {
                                for k in 0..3 {
                                    c[(row + i, col + k)] = r[i][k];
                                }
                            }
                        }
                    }
                }
            }
        }
        let (err, scale) = periodic_solve_error(&solver, &c, lambda, nl);
        eprintln!(
            "h = {} mm, depths {:?}: periodic solve vs dense periodic Tikhonov {:.2e} of {scale:.3e}",
            e.thickness_mm,
            [s.layers[0].depth_mm, s.layers[1].depth_mm],
            err
        );
        assert!(
            err <= 1e-10 * scale,
            "bonded layer h = {} mm: periodic solve differs from dense periodic Tikhonov by \
             {err:e} (scale {scale:e})",
            e.thickness_mm
        );
    }

    #[test]
    fn periodic_bonded_layer_problem_is_solved_exactly_with_a_half_pitch_offset() {
        periodic_layer_case(&layer_sensor(
            (4, 4, 1.1, 1.1),
            10.0,
            [3.0, 6.0],
            [0.55, 0.55],
        ));
    }

    #[test]
    fn periodic_thin_layer_problem_is_solved_exactly_on_multi_rate_grids() {
        // A 3 mm gel with markers at 1 and 2 mm (many aliases), forces every 2.2 mm on
        // 1.1 mm markers and markers every 2.2 mm on 1.1 mm forces, arbitrary offsets.
        periodic_layer_case(&layer_sensor(
            (3, 3, 2.2, 1.1),
            3.0,
            [1.0, 2.0],
            [0.37, -0.21],
        ));
        periodic_layer_case(&layer_sensor((5, 4, 1.1, 2.2), 3.0, [1.0, 2.0], [0.9, 0.3]));
    }

    #[test]
    fn refinement_operator_of_a_bonded_layer_is_its_exact_h() {
        // forward_op (window-sampled real-space responses of the layer) against direct
        // summation of the same model's point responses.
        for (t, depths) in [(3.0, [1.0, 2.0]), (40.0, [3.0, 6.0])] {
            let s = layer_sensor((7, 5, 2.2, 1.1), t, depths, [0.37, -0.21]);
            let sites = MarkerSite::from_sensor_grids(&s);
            let p = Problem::new(&s, &sites);
            let cfg = SolverConfig {
                method: Method::Fourier,
                lambda: Lambda::Fixed(0.1),
                ..SolverConfig::default()
            };
            let mut solver = FourierSolver::precompute(&p, &cfg, None).unwrap();
            let f = pseudo_random(p.n_outputs(), 7);
            let want = crate::model::forward(&p.forward_model(), &sites, &s.force_points_mm(), &f)
                .unwrap();
            let hs = crate::model::forward(&p.model, &sites, &s.force_points_mm(), &f).unwrap();
            let mut got = vec![0.0; p.n_inputs()];
            forward_op(&solver.plan, &mut solver.work, &solver.a, &f, &mut got);
            let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let err = got
                .iter()
                .zip(&want)
                .fold(0.0f64, |m, (g, w)| m.max((g - w).abs()));
            let model_gap = hs
                .iter()
                .zip(&want)
                .fold(0.0f64, |m, (g, w)| m.max((g - w).abs()));
            assert!(err <= 1e-12 * scale, "h = {t}: {err:e} of {scale:e}");
            // And it is the layer, not the half-space.
            assert!(model_gap > 1e-3 * scale, "h = {t}: {model_gap:e}");
        }
    }
}
