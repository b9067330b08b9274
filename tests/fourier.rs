//! The `fourier` solver against independent references: the exact forward model
//! (`model::forward`, direct summation of Eq. 1–2), a dense Tikhonov solution computed
//! here from nalgebra's SVD of `H`, and the geometries it must refuse.
//!
//! Error measures are relative 2-norms over all force components. "Interior" means force
//! nodes at least 4 mm from every edge of the force grid: the periodic direct solve has a
//! boundary error within a few elastomer depths (markers at 3 and 6 mm) of the edges
//! (module docs of `solve::fourier`); the CGLS refinement removes it.

use nalgebra::{DMatrix, DVector};
use tactbench::model::{self, transfer_matrix, MarkerSite};
use tactbench::sensor::{grid_sensor, paper_sensor, Sensor};
use tactbench::solve::fourier::FourierSolver;
use tactbench::solve::{self, FrameSolver, Lambda, Method, Problem, SolveError, SolverConfig};

use crate::util::interior;

fn config(lambda: Lambda) -> SolverConfig {
    SolverConfig {
        method: Method::Fourier,
        lambda,
        ..SolverConfig::default()
    }
}

/// A smooth load (Gaussian of width `w` mm) centred at `c`, components `amp` N.
fn blob(sensor: &Sensor, c: [f64; 2], w: f64, amp: [f64; 3]) -> Vec<f64> {
    sensor
        .force_points_mm()
        .iter()
        .flat_map(|p| {
            let g = (-((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2)) / (2.0 * w * w)).exp();
            [amp[0] * g, amp[1] * g, amp[2] * g]
        })
        .collect()
}

/// A blob in the middle of the force grid.
fn centre_blob(sensor: &Sensor) -> Vec<f64> {
    let g = sensor.force_grid;
    let c = [
        g.origin_mm[0] + 0.5 * g.pitch_mm * (g.nx - 1) as f64,
        g.origin_mm[1] + 0.5 * g.pitch_mm * (g.ny - 1) as f64,
    ];
    blob(sensor, c, 2.0, [0.02, -0.01, 0.05])
}

fn displacements(sensor: &Sensor, sites: &[MarkerSite], f: &[f64]) -> Vec<f64> {
    let p = Problem::new(sensor, sites);
    model::forward(&p.model, sites, &sensor.force_points_mm(), f).unwrap()
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

fn rel_err(got: &[f64], want: &[f64]) -> f64 {
    let d: Vec<f64> = got.iter().zip(want).map(|(a, b)| a - b).collect();
    norm(&d) / norm(want)
}

/// Dense Tikhonov reference `V diag(σ/(σ²+λ²)) Uᵀ u` from nalgebra's SVD of `H`; also
/// returns σ_max.
fn dense_tikhonov(sensor: &Sensor, sites: &[MarkerSite], u: &[f64], lambda: f64) -> Vec<f64> {
    let p = Problem::new(sensor, sites);
    let h: DMatrix<f64> = transfer_matrix(&p.model, sites, &sensor.force_points_mm()).unwrap();
    let svd = h.svd(true, true);
    let (uu, vt) = (svd.u.unwrap(), svd.v_t.unwrap());
    let mut c = uu.transpose() * DVector::from_column_slice(u);
    for (i, ci) in c.iter_mut().enumerate() {
        let s = svd.singular_values[i];
        *ci *= s / (s * s + lambda * lambda);
    }
    (vt.transpose() * c).as_slice().to_vec()
}

/// λ used by the comparisons: 1 % of the largest singular value of the periodic
/// operator, a moderate regularisation for these grids.
fn moderate_lambda(sensor: &Sensor, sites: &[MarkerSite]) -> f64 {
    periodic_lambda(&Problem::new(sensor, sites), 0.01)
}

/// `factor` × the largest singular value of the periodic operator (mm/N).
fn periodic_lambda(p: &Problem<'_>, factor: f64) -> f64 {
    let probe = FourierSolver::precompute(p, &config(Lambda::Fixed(1.0)), None).unwrap();
    factor * probe.diagnostics().singular_values[0]
}

/// Deterministic N(0, σ²) noise (xorshift64* + Box–Muller).
fn noise(n: usize, sigma: f64, mut seed: u64) -> Vec<f64> {
    let mut next = || {
        seed ^= seed >> 12;
        seed ^= seed << 25;
        seed ^= seed >> 27;
        (seed.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    };
    (0..n)
        .map(|_| {
            let (a, b) = (next().max(1e-300), next());
            sigma * (-2.0 * a.ln()).sqrt() * (2.0 * std::f64::consts::PI * b).cos()
        })
        .collect()
}

fn incompatible(r: Result<FourierSolver, SolveError>) -> String {
    match r {
        Err(SolveError::Incompatible(m)) => m,
        Err(e) => panic!("expected Incompatible, got {e}"),
        Ok(_) => panic!("expected Incompatible, got a solver"),
    }
}

// ---- refusals ---------------------------------------------------------------------

#[test]
fn refuses_the_paper_geometry_and_says_what_would_work() {
    let s = paper_sensor();
    let sites = MarkerSite::from_sensor_grids(&s);
    let p = Problem::new(&s, &sites);
    let m = incompatible(FourierSolver::precompute(
        &p,
        &config(Lambda::Fixed(0.1)),
        None,
    ));
    assert!(m.contains("2.2 mm") && m.contains("1.5 mm"), "{m}");
    assert!(m.contains("small integers"), "{m}");
    assert!(m.contains("1.1000 mm") && m.contains("2.2000 mm"), "{m}");
    assert!(m.contains("dense solver"), "{m}");
}

#[test]
fn refuses_a_rotated_marker_grid_naming_the_marker_and_distance() {
    let s = grid_sensor(10, 8, 2.2, 1.1);
    let c = [9.9, 7.7];
    let (sn, cs) = 2f64.to_radians().sin_cos();
    let sites: Vec<MarkerSite> = MarkerSite::from_sensor_grids(&s)
        .into_iter()
        .map(|mut m| {
            let (x, y) = (m.position_mm[0] - c[0], m.position_mm[1] - c[1]);
            m.position_mm = [c[0] + cs * x - sn * y, c[1] + sn * x + cs * y];
            m
        })
        .collect();
    let p = Problem::new(&s, &sites);
    let m = incompatible(FourierSolver::precompute(
        &p,
        &config(Lambda::Fixed(0.1)),
        None,
    ));
    assert!(m.starts_with("marker 0 of layer blue"), "{m}");
    assert!(
        m.contains("from its nearest grid node") && m.contains("rotated"),
        "{m}"
    );
}

#[test]
fn off_grid_tolerance_is_a_thousandth_of_the_pitch() {
    let s = grid_sensor(10, 8, 2.2, 1.1);
    let mut sites = MarkerSite::from_sensor_grids(&s);
    sites[17].position_mm[0] += 0.5e-3; // 0.00045 pitch: accepted
    let p = Problem::new(&s, &sites);
    assert!(FourierSolver::precompute(&p, &config(Lambda::Fixed(0.1)), None).is_ok());
    sites[17].position_mm[0] += 1.0e-3; // 0.0014 pitch: refused
    let p = Problem::new(&s, &sites);
    let m = incompatible(FourierSolver::precompute(
        &p,
        &config(Lambda::Fixed(0.1)),
        None,
    ));
    assert!(m.contains("marker 17") && m.contains("0.0015 mm"), "{m}");
}

#[test]
fn refuses_missing_markers_and_points_to_dense_solvers() {
    let s = grid_sensor(10, 8, 2.2, 1.1);
    let mut sites = MarkerSite::from_sensor_grids(&s);
    let lost = sites.len() - 5; // a red marker
    sites.remove(lost);
    let p = Problem::new(&s, &sites);
    let m = incompatible(FourierSolver::precompute(
        &p,
        &config(Lambda::Fixed(0.1)),
        None,
    ));
    assert!(m.starts_with("layer red: 1 of"), "{m}");
    assert!(m.contains("lost markers") && m.contains("dense"), "{m}");
}

#[test]
fn refuses_layers_with_different_pitches() {
    let mut s = grid_sensor(10, 8, 2.2, 1.1);
    let red = s.layers[1].markers.as_mut().unwrap();
    red.grid.pitch_mm = 2.2;
    red.grid.nx = 10;
    red.grid.ny = 8;
    let sites = MarkerSite::from_sensor_grids(&s);
    let p = Problem::new(&s, &sites);
    let m = incompatible(FourierSolver::precompute(
        &p,
        &config(Lambda::Fixed(0.1)),
        None,
    ));
    assert!(
        m.contains("layer red has marker pitch 2.2 mm but layer blue has 1.1 mm"),
        "{m}"
    );
}

#[test]
fn automatic_lambda_needs_a_frame() {
    let s = grid_sensor(10, 8, 2.2, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let p = Problem::new(&s, &sites);
    for l in [Lambda::Gcv, Lambda::LCurve] {
        assert!(matches!(
            FourierSolver::precompute(&p, &config(l), None),
            Err(SolveError::NeedsFrame(_))
        ));
    }
}

// ---- accuracy ---------------------------------------------------------------------

#[test]
fn recovers_a_compact_interior_load_on_both_grids() {
    // Noise-free, λ = 1e-3·σ_max of the periodic operator. Measured (direct interior /
    // direct all / 30 CGLS all / dense Tikhonov all): 16×16 0.27 / 0.37 / 0.24 / 0.25,
    // 10×8 0.25 / 0.35 / 0.25 / 0.25. At this λ the regularisation bias (the 2 mm blob is
    // smoothed) is most of the error; the rest of the direct solve's error sits at the
    // edges (boundary error of the periodic model).
    for (nx, ny, pf, pm) in [(16, 16, 1.1, 1.1), (10, 8, 2.2, 1.1)] {
        let s = grid_sensor(nx, ny, pf, pm);
        let sites = MarkerSite::from_sensor_grids(&s);
        let f_true = centre_blob(&s);
        let u = displacements(&s, &sites, &f_true);
        let lambda = 0.1 * moderate_lambda(&s, &sites);
        let p = Problem::new(&s, &sites);
        let mut solver =
            FourierSolver::precompute(&p, &config(Lambda::Fixed(lambda)), None).unwrap();
        solver.refine_iterations = 0;
        let mut f = vec![0.0; p.n_outputs()];
        solver.apply(&u, &mut f).unwrap();
        let e_int = rel_err(&interior(&s, &f, 4.0), &interior(&s, &f_true, 4.0));
        let e_all = rel_err(&f, &f_true);
        solver.refine_iterations = 30;
        solver.apply(&u, &mut f).unwrap();
        let e_ref = rel_err(&f, &f_true);
        println!(
            "{nx}x{ny} pitch {pf}/{pm}: λ = {lambda:.3e}; error vs truth: direct interior \
             {e_int:.3}, direct all {e_all:.3}, 30 CGLS all {e_ref:.3}"
        );
        assert!(e_int < 0.35, "{nx}x{ny}: interior error {e_int}");
        assert!(e_all < 0.45, "{nx}x{ny}: whole-grid error {e_all}");
        assert!(e_ref < 0.30, "{nx}x{ny}: refined error {e_ref}");
    }
}

#[test]
fn agrees_with_dense_tikhonov_at_the_same_lambda() {
    for (nx, ny, pf, pm) in [(16, 16, 1.1, 1.1), (10, 8, 2.2, 1.1)] {
        let s = grid_sensor(nx, ny, pf, pm);
        let sites = MarkerSite::from_sensor_grids(&s);
        let f_true = centre_blob(&s);
        let u = displacements(&s, &sites, &f_true);
        let lambda = moderate_lambda(&s, &sites);
        let dense = dense_tikhonov(&s, &sites, &u, lambda);
        let p = Problem::new(&s, &sites);
        let mut solver =
            FourierSolver::precompute(&p, &config(Lambda::Fixed(lambda)), None).unwrap();
        solver.refine_iterations = 0;
        let mut f = vec![0.0; p.n_outputs()];
        solver.apply(&u, &mut f).unwrap();
        let e_int = rel_err(&interior(&s, &f, 4.0), &interior(&s, &dense, 4.0));
        let e_all = rel_err(&f, &dense);
        solver.refine_iterations = 30;
        solver.refine_tolerance = 0.0;
        solver.apply(&u, &mut f).unwrap();
        let e_ref = rel_err(&f, &dense);
        println!(
            "{nx}x{ny}: λ = {lambda:.3e}; direct vs dense: interior {e_int:.4}, all {e_all:.4}; \
             30 CGLS: {e_ref:.2e}"
        );
        // Direct: the boundary error of the periodic model dominates (module docs).
        assert!(e_int < 0.15, "interior {e_int}");
        assert!(e_all < 0.30, "all {e_all}");
        // Refined: the exact operator, converged.
        assert!(e_ref < 1e-3, "refined {e_ref}");
    }
}

#[test]
fn arbitrary_layer_offsets_are_exact_after_refinement() {
    // Red layer offset by (0.37, -0.21) mm instead of half a pitch: the sub-pitch offset
    // lives in the sampled kernel, so the FFT operator is exact and the refined solution
    // converges to the dense one.
    let mut s = grid_sensor(10, 8, 2.2, 1.1);
    s.layers[1].markers.as_mut().unwrap().grid.origin_mm = [0.37, -0.21];
    let sites = MarkerSite::from_sensor_grids(&s);
    let f_true = centre_blob(&s);
    let u = displacements(&s, &sites, &f_true);
    let lambda = moderate_lambda(&s, &sites);
    let dense = dense_tikhonov(&s, &sites, &u, lambda);
    let p = Problem::new(&s, &sites);
    let mut solver = FourierSolver::precompute(&p, &config(Lambda::Fixed(lambda)), None)
        .unwrap()
        .with_refinement(60)
        .with_refine_tolerance(0.0);
    let mut f = vec![0.0; p.n_outputs()];
    solver.apply(&u, &mut f).unwrap();
    let e = rel_err(&f, &dense);
    assert!(e < 1e-6, "offset layers: refined vs dense {e}");
    solver.refine_iterations = 0;
    solver.apply(&u, &mut f).unwrap();
    let e_int = rel_err(&interior(&s, &f, 4.0), &interior(&s, &dense, 4.0));
    assert!(
        e_int < 0.15,
        "offset layers: direct interior vs dense {e_int}"
    );
}

#[test]
fn noisy_frames_give_finite_bounded_forces() {
    let s = grid_sensor(16, 16, 1.1, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let f_true = centre_blob(&s);
    let clean = displacements(&s, &sites, &f_true);
    let n = noise(clean.len(), 0.005, 0x5eed_1234);
    let noisy: Vec<f64> = clean.iter().zip(&n).map(|(a, b)| a + b).collect();
    let p = Problem::new(&s, &sites);
    let mut solver = FourierSolver::precompute(&p, &config(Lambda::Gcv), Some(&noisy)).unwrap();
    let d = solver.diagnostics().clone();
    assert!(d.lambda.unwrap() > 0.0 && d.noise_gain.is_finite());
    let mut f_noisy = vec![0.0; p.n_outputs()];
    let mut f_clean = vec![0.0; p.n_outputs()];
    solver.refine_iterations = 0;
    // Without the edge bridge the direct solve is `crop ∘ P ∘ zero-pad`, so the force
    // change is bounded by the periodic noise gain ‖P‖₂ times the noise norm.
    solver.bridge_edges = false;
    solver.apply(&noisy, &mut f_noisy).unwrap();
    solver.apply(&clean, &mut f_clean).unwrap();
    let df: Vec<f64> = f_noisy.iter().zip(&f_clean).map(|(a, b)| a - b).collect();
    assert!(f_noisy.iter().all(|v| v.is_finite()));
    assert!(norm(&df) <= d.noise_gain * norm(&n) * (1.0 + 1e-9));
    // With the bridge (default) the padding copies edge noise; measured amplification
    // relative to the zero-padded bound: 0.29.
    solver.bridge_edges = true;
    solver.apply(&noisy, &mut f_noisy).unwrap();
    solver.apply(&clean, &mut f_clean).unwrap();
    let df: Vec<f64> = f_noisy.iter().zip(&f_clean).map(|(a, b)| a - b).collect();
    let ratio = norm(&df) / (d.noise_gain * norm(&n));
    println!(
        "noise 0.005 mm, GCV λ = {:.3e} mm/N, noise gain {:.3} N/mm: force error {:.3} N \
         (truth {:.3} N), {ratio:.3} of the bound",
        d.lambda.unwrap(),
        d.noise_gain,
        norm(&df),
        norm(&f_true)
    );
    assert!(f_noisy.iter().all(|v| v.is_finite()));
    assert!(ratio < 1.0, "bridged noise amplification {ratio}");
}

// ---- robustness and the per-frame contract -----------------------------------------

#[test]
fn zero_and_huge_inputs_do_not_panic() {
    let s = grid_sensor(10, 8, 2.2, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let p = Problem::new(&s, &sites);
    let mut solver = FourierSolver::precompute(&p, &config(Lambda::Fixed(0.05)), None)
        .unwrap()
        .with_refinement(3);
    let mut f = vec![1.0; p.n_outputs()];
    solver.apply(&vec![0.0; p.n_inputs()], &mut f).unwrap();
    assert!(
        f.iter().all(|&v| v == 0.0),
        "zero displacements give zero forces"
    );
    let u = displacements(&s, &sites, &centre_blob(&s));
    let mut f1 = vec![0.0; p.n_outputs()];
    solver.apply(&u, &mut f1).unwrap();
    let huge: Vec<f64> = u.iter().map(|v| v * 1e300).collect();
    solver.apply(&huge, &mut f).unwrap();
    assert!(f.iter().all(|v| v.is_finite()));
    let back: Vec<f64> = f.iter().map(|v| v / 1e300).collect();
    assert!(rel_err(&back, &f1) < 1e-9, "linear up to 1e300 mm");
    // Wrong lengths and NaN are errors, not panics.
    assert!(matches!(
        solver.apply(&u[1..], &mut f),
        Err(SolveError::DimensionMismatch { .. })
    ));
    assert!(matches!(
        solver.apply(&u, &mut f[1..]),
        Err(SolveError::DimensionMismatch { .. })
    ));
    let mut bad = u.clone();
    bad[7] = f64::NAN;
    assert!(matches!(
        solver.apply(&bad, &mut f),
        Err(SolveError::NonFinite { index: 7, .. })
    ));
}

#[test]
fn repeated_applies_are_identical() {
    let s = grid_sensor(16, 16, 1.1, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let p = Problem::new(&s, &sites);
    let mut solver = FourierSolver::precompute(&p, &config(Lambda::Fixed(0.1)), None).unwrap();
    let u = displacements(&s, &sites, &centre_blob(&s));
    let other: Vec<f64> = u.iter().rev().map(|v| -v).collect();
    for k in [0, 4] {
        solver.refine_iterations = k;
        let mut a = vec![0.0; p.n_outputs()];
        let mut b = vec![0.0; p.n_outputs()];
        solver.apply(&u, &mut a).unwrap();
        solver.apply(&other, &mut b).unwrap(); // dirty every buffer in between
        solver.apply(&u, &mut b).unwrap();
        assert_eq!(a, b, "refinement {k}: buffers leak state between frames");
    }
}

#[test]
fn generic_entry_point_builds_the_fourier_solver() {
    let s = grid_sensor(10, 8, 2.2, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let p = Problem::new(&s, &sites);
    let u = displacements(&s, &sites, &centre_blob(&s));
    let solver = solve::precompute(&p, &config(Lambda::LCurve), Some(&u)).unwrap();
    let d = solver.diagnostics();
    assert_eq!(d.method, Method::Fourier);
    assert_eq!(d.shape, (p.n_inputs(), p.n_outputs()));
    assert!(d.singular_values.windows(2).all(|w| w[0] >= w[1]));
    assert!(d.lambda.unwrap() > 0.0 && d.effective_rank > 0.0);
}

#[test]
fn l_curve_lambda_is_near_the_best_fixed_lambda_on_a_noisy_frame() {
    // 0.005 mm noise on a load whose largest displacement is 0.046 mm. Measured errors:
    // L-curve (λ = 0.60) 0.55; fixed λ 0.1 / 0.3 / 1 / 3: 1.36 / 0.61 / 0.62 / 0.83;
    // GCV (λ = 0.081) 1.67. GCV on the periodic model under-regularises: the padding
    // rows look like noise-free measurements (module docs), so it is not asserted here.
    let s = grid_sensor(16, 16, 1.1, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let f_true = centre_blob(&s);
    let clean = displacements(&s, &sites, &f_true);
    let n = noise(clean.len(), 0.005, 0x5eed_1234);
    let noisy: Vec<f64> = clean.iter().zip(&n).map(|(a, b)| a + b).collect();
    let p = Problem::new(&s, &sites);
    let error = |l: Lambda| {
        let mut solver = FourierSolver::precompute(&p, &config(l), Some(&noisy)).unwrap();
        solver.refine_iterations = 0;
        let mut f = vec![0.0; p.n_outputs()];
        solver.apply(&noisy, &mut f).unwrap();
        rel_err(&f, &f_true)
    };
    let best = [0.1, 0.3, 1.0, 3.0]
        .iter()
        .map(|&l| error(Lambda::Fixed(l)))
        .fold(f64::INFINITY, f64::min);
    let lc = error(Lambda::LCurve);
    assert!(lc <= 1.1 * best, "L-curve error {lc}, best fixed {best}");
}

// ---- issue 12: agreement with dense Tikhonov, cross-talk, noise, uncertainty --------

fn sums(f: &[f64]) -> [f64; 3] {
    let mut s = [0.0; 3];
    for (i, v) in f.iter().enumerate() {
        s[i % 3] += v;
    }
    s
}

/// Dense Tikhonov operator `P = V diag(σ/(σ²+λ²)) Uᵀ` (rows: forces) at λ = 1e-2·σ₁ of
/// the dense `H`, the λ of issue 12's observations.
fn dense_operator(sensor: &Sensor, sites: &[MarkerSite]) -> (DMatrix<f64>, f64) {
    let p = Problem::new(sensor, sites);
    let h: DMatrix<f64> = transfer_matrix(&p.model, sites, &sensor.force_points_mm()).unwrap();
    let svd = h.svd(true, true);
    let lambda = 1e-2 * svd.singular_values.max();
    let (uu, vt) = (svd.u.unwrap(), svd.v_t.unwrap());
    let mut v = vt.transpose();
    for (i, mut col) in v.column_iter_mut().enumerate() {
        let s = svd.singular_values[i];
        col *= s / (s * s + lambda * lambda);
    }
    (v * uu.transpose(), lambda)
}

/// The loads of the acceptance checks: centred fx (observation 1), centred fz, centred
/// mixed, off-centre fy, off-centre mixed; Gaussians σ = 2 mm, peak 0.1 N (fz) per node.
fn acceptance_loads(sensor: &Sensor) -> Vec<(&'static str, Vec<f64>)> {
    let g = sensor.force_grid;
    let c = 0.5 * g.pitch_mm * (g.nx - 1) as f64;
    vec![
        ("centred fx", blob(sensor, [c, c], 2.0, [0.1, 0.0, 0.0])),
        ("centred fz", blob(sensor, [c, c], 2.0, [0.0, 0.0, 0.1])),
        (
            "centred mixed",
            blob(sensor, [c, c], 2.0, [0.02, -0.01, 0.1]),
        ),
        (
            "off-centre fy",
            blob(sensor, [c - 3.0, c + 2.0], 2.0, [0.0, 0.1, 0.0]),
        ),
        (
            "off-centre mixed",
            blob(sensor, [c + 4.0, c + 3.0], 2.0, [0.02, -0.01, 0.1]),
        ),
    ]
}

/// Checks one Fourier solution against the dense one: F_sum per axis within 2 % of the
/// applied total, cross-talk of single-axis loads ≤ 2 % of the applied total, field within
/// 10 % overall and 5 % on the interior (≥ 4 mm from the edges).
fn check_against_dense(s: &Sensor, name: &str, f_true: &[f64], f: &[f64], dense: &[f64]) {
    let (st, sd, sf) = (sums(f_true), sums(dense), sums(f));
    let total = st.iter().map(|v| v.abs()).fold(0.0, f64::max);
    let e_all = rel_err(f, dense);
    let e_int = rel_err(&interior(s, f, 4.0), &interior(s, dense, 4.0));
    println!(
        "{name}: applied {st:.4?}, dense {sd:.4?}, fourier {sf:.4?}; field vs dense: all \
         {e_all:.4}, interior {e_int:.4}"
    );
    for ax in 0..3 {
        let e = (sf[ax] - sd[ax]).abs() / total;
        assert!(
            e <= 0.02,
            "{name}: ΣF axis {ax} off dense by {e:.4} of the total"
        );
        if st[ax] == 0.0 {
            assert!(
                sf[ax].abs() <= 0.02 * total,
                "{name}: cross-talk into axis {ax}: {:.4} N of {total:.4} N",
                sf[ax]
            );
        }
    }
    assert!(e_all <= 0.10, "{name}: field error vs dense {e_all:.4}");
    assert!(
        e_int <= 0.05,
        "{name}: interior field error vs dense {e_int:.4}"
    );
}

#[test]
fn shear_load_gives_no_false_normal_force_and_agrees_with_dense_tikhonov() {
    // Issue 12, observation 1: 16×16 forces and markers at 1.1 mm, layers at 3 and 6 mm
    // (the second offset by half a pitch), E = 1 MPa, ν = 0.5, λ = 1e-2·σ₁. Before the fix
    // (direct periodic solve) the centred fx load gave F_sum = (1.09, 0.002, −2.16) N
    // against dense (2.09, 0.000, −0.002) N.
    let s = grid_sensor(16, 16, 1.1, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let (pd, lambda) = dense_operator(&s, &sites);
    let p = Problem::new(&s, &sites);
    let mut solver = FourierSolver::precompute(&p, &config(Lambda::Fixed(lambda)), None).unwrap();
    let mut f = vec![0.0; p.n_outputs()];
    for (name, f_true) in acceptance_loads(&s) {
        let u = displacements(&s, &sites, &f_true);
        let dense = (&pd * DVector::from_column_slice(&u)).as_slice().to_vec();
        solver.apply(&u, &mut f).unwrap();
        check_against_dense(&s, name, &f_true, &f, &dense);
    }
}

/// Refinement from the *direct* solve (on this grid the default two-level solve is dense
/// Tikhonov already, which would leave nothing to refine): relative field error against
/// dense Tikhonov after at most `cap` iterations (tolerance 0) on acceptance load `load`,
/// and the iterations run.
fn refined_from_direct(load: usize, cap: usize) -> (f64, usize) {
    let s = grid_sensor(16, 16, 1.1, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let (pd, lambda) = dense_operator(&s, &sites);
    let p = Problem::new(&s, &sites);
    let mut solver = FourierSolver::precompute(&p, &config(Lambda::Fixed(lambda)), None)
        .unwrap()
        .with_refinement(cap)
        .with_refine_tolerance(0.0);
    solver.coarse_correction = false;
    let (_, f_true) = acceptance_loads(&s).swap_remove(load);
    let u = displacements(&s, &sites, &f_true);
    let dense = (&pd * DVector::from_column_slice(&u)).as_slice().to_vec();
    let mut f = vec![0.0; p.n_outputs()];
    solver.apply(&u, &mut f).unwrap();
    (rel_err(&f, &dense), solver.last_refine_iterations())
}

#[test]
fn refinement_converges_to_dense_tikhonov_on_the_issue_geometry() {
    let (e, its) = refined_from_direct(0, 80);
    assert!(e < 1e-6, "80 CGLS iterations vs dense: {e:e}");
    assert!(
        its > 10,
        "the direct solve needs refining: {its} iterations"
    );
}

#[test]
fn refinement_run_far_past_convergence_stays_at_dense_tikhonov() {
    // Regression: CGLS run on after converging to rounding diverged (600 iterations at
    // tolerance 0 on the off-centre fy load gave ΣF of 5e6 N); it now stops at stagnation.
    let (e, its) = refined_from_direct(3, 600);
    assert!(e < 1e-6, "600 iterations vs dense: {e:e}");
    assert!(its < 600, "{its} iterations");
}

#[test]
fn refinement_stops_at_its_tolerance_well_before_the_cap() {
    // From the direct solve (no coarse correction) the refinement stops on the tolerance
    // (the shear test above checks its accuracy): measured 22 iterations at most on these
    // loads at λ = 1e-2·σ₁ (16 at tolerance 0.1, 31 at 1e-3), well below a cap of 50.
    // From the default two-level solve, which on this grid is dense Tikhonov already
    // (its coarse space is the whole 16×16 force grid), it stops at once. The default
    // runs no refinement.
    let s = grid_sensor(16, 16, 1.1, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let (_, lambda) = dense_operator(&s, &sites);
    let p = Problem::new(&s, &sites);
    let mut solver = FourierSolver::precompute(&p, &config(Lambda::Fixed(lambda)), None).unwrap();
    assert_eq!(solver.refine_iterations, 0);
    assert_eq!(
        solver.refine_tolerance,
        tactbench::solve::fourier::DEFAULT_REFINE_TOLERANCE
    );
    assert_eq!(solver.coarse_space(), Some((768, 1)));
    let mut f = vec![0.0; p.n_outputs()];
    solver.refine_iterations = 50;
    for (two_level, range) in [(false, 1..=30), (true, 0..=0)] {
        solver.coarse_correction = two_level;
        for (name, f_true) in acceptance_loads(&s) {
            let u = displacements(&s, &sites, &f_true);
            solver.apply(&u, &mut f).unwrap();
            let k = solver.last_refine_iterations();
            assert!(
                range.contains(&k),
                "{name} (two-level {two_level}): {k} iterations (cap 50)"
            );
        }
    }
    // A zero frame needs none.
    solver.apply(&vec![0.0; p.n_inputs()], &mut f).unwrap();
    assert_eq!(solver.last_refine_iterations(), 0);
    assert!(f.iter().all(|v| *v == 0.0));
}

#[test]
fn refinement_tolerance_outside_0_1_is_refused() {
    let s = grid_sensor(6, 6, 1.1, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let p = Problem::new(&s, &sites);
    for tol in [-1e-3, 1.0, f64::NAN] {
        let cfg = SolverConfig {
            fourier_refine_tolerance: tol,
            ..config(Lambda::Fixed(0.1))
        };
        match FourierSolver::precompute(&p, &cfg, None) {
            Err(SolveError::InvalidOption(m)) => assert!(m.contains("tolerance"), "{m}"),
            other => panic!("tolerance {tol}: {other:?}"),
        }
    }
}

#[test]
fn mixed_load_at_32x32_is_unbiased() {
    // Issue 12, observation 2: 32×32 at 1.1 mm, mixed load fx : fy : fz = 0.2 : −0.1 : 1.
    // Before: noise-free ΣFx = 0.263 N against 0.415 N applied. The dense reference here
    // is the refinement run to convergence (shown equal to dense Tikhonov to 1e-6 on
    // 16×16 above; a dense SVD at 3072 unknowns is too slow for a test).
    let s = grid_sensor(32, 32, 1.1, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let p = Problem::new(&s, &sites);
    // σ₁ of the dense H is below the periodic σ_max; λ = 1e-2 of the latter / 5.
    let lambda = periodic_lambda(&p, 2e-3);
    let mut solver = FourierSolver::precompute(&p, &config(Lambda::Fixed(lambda)), None).unwrap();
    let g = s.force_grid;
    let c = 0.5 * g.pitch_mm * (g.nx - 1) as f64;
    for (name, centre) in [("centred", [c, c]), ("off-centre", [c + 6.0, c - 5.0])] {
        let f_true = blob(&s, centre, 2.0, [0.02, -0.01, 0.1]);
        let u = displacements(&s, &sites, &f_true);
        solver.refine_iterations = 400;
        solver.refine_tolerance = 0.0;
        let mut dense = vec![0.0; p.n_outputs()];
        solver.apply(&u, &mut dense).unwrap();
        solver.refine_iterations = tactbench::solve::fourier::DEFAULT_REFINE_ITERATIONS;
        solver.refine_tolerance = tactbench::solve::fourier::DEFAULT_REFINE_TOLERANCE;
        let mut f = vec![0.0; p.n_outputs()];
        solver.apply(&u, &mut f).unwrap();
        check_against_dense(&s, name, &f_true, &f, &dense);
    }
}

/// Sample SD of each force component and of the force sums over `n` noise-only frames.
fn monte_carlo(
    solver: &mut FourierSolver,
    n_in: usize,
    n_out: usize,
    sigma: f64,
    n: usize,
) -> (Vec<f64>, [f64; 3]) {
    let mut var = vec![0.0; n_out];
    let mut svar = [0.0; 3];
    let mut f = vec![0.0; n_out];
    for k in 0..n {
        let u = noise(n_in, sigma, 0x9e37_79b9_7f4a_7c15 ^ (k as u64 + 1));
        solver.apply(&u, &mut f).unwrap();
        for (v, x) in var.iter_mut().zip(&f) {
            *v += x * x / n as f64;
        }
        for (sv, x) in svar.iter_mut().zip(sums(&f)) {
            *sv += x * x / n as f64;
        }
    }
    (var.iter().map(|v| v.sqrt()).collect(), svar.map(f64::sqrt))
}

#[test]
fn noise_only_force_sums_are_within_1_5x_of_dense_and_uncertainty_matches_monte_carlo() {
    // 0.1 px = 0.005 mm of noise on every displacement, 16×16 (observation 2's noise
    // level). Dense: exact SD of ΣF from P (‖Pᵀ 1_c‖·σ). Fourier: 300 seeded noise frames
    // (sample SD within ~4 % of the truth; the bounds are 1.5× and 10 %).
    let s = grid_sensor(16, 16, 1.1, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let (pd, lambda) = dense_operator(&s, &sites);
    let p = Problem::new(&s, &sites);
    let (n_in, n_out) = (p.n_inputs(), p.n_outputs());
    let sigma = 0.005;
    let mut dense_sd = [0.0; 3];
    for (c, d) in dense_sd.iter_mut().enumerate() {
        let w: Vec<f64> = (0..n_in)
            .map(|i| (c..n_out).step_by(3).map(|j| pd[(j, i)]).sum())
            .collect();
        *d = sigma * norm(&w);
    }
    let mut solver = FourierSolver::precompute(&p, &config(Lambda::Fixed(lambda)), None).unwrap();
    let (mc_force, mc_sum) = monte_carlo(&mut solver, n_in, n_out, sigma, 300);
    let predicted = solver.sum_sd(sigma).unwrap();
    println!(
        "ΣF SD: dense {dense_sd:.4?}, fourier MC {mc_sum:.4?}, fourier sum_sd {predicted:.4?}"
    );
    for ax in 0..3 {
        let r = mc_sum[ax] / dense_sd[ax];
        assert!(
            (1.0 / 1.5..=1.5).contains(&r),
            "axis {ax}: fourier/dense ΣF SD {r:.3}"
        );
        let e = (predicted[ax] - mc_sum[ax]).abs() / mc_sum[ax];
        assert!(
            e <= 0.10,
            "axis {ax}: sum_sd {} vs Monte Carlo {}",
            predicted[ax],
            mc_sum[ax]
        );
    }
    // Per node, the default (two-level) map by probing, and the refined one: the
    // refinement stops at its tolerance, so its map is the converged one, dense
    // Tikhonov, to within that tolerance; force_sd propagates through the latter.
    let exact: Vec<f64> = (0..n_out).map(|j| sigma * pd.row(j).norm()).collect();
    let mut sd = vec![0.0; n_out];
    for (label, iterations) in [("two-level", 0), ("refined", 50)] {
        solver.refine_iterations = iterations;
        let mc_force = if iterations == 0 {
            mc_force.clone()
        } else {
            monte_carlo(&mut solver, n_in, n_out, sigma, 300).0
        };
        solver.force_sd(sigma, &mut sd).unwrap();
        let worst = sd
            .iter()
            .zip(&exact)
            .map(|(a, b)| (a - b).abs() / b)
            .fold(0.0, f64::max);
        let e_int = rel_err(&interior(&s, &sd, 4.0), &interior(&s, &mc_force, 4.0));
        let e_all = rel_err(&sd, &mc_force);
        println!(
            "{label}: per-node force_sd vs Monte Carlo: interior {e_int:.3}, all {e_all:.3}; \
             vs the exact rows of dense P: worst node {worst:.3}"
        );
        assert!(
            worst <= 0.10,
            "{label}: worst node's force_sd vs exact {worst:.3}"
        );
        assert!(e_all <= 0.10, "{label}: per-node force_sd vs MC {e_all:.3}");
        assert!(e_int <= 0.10, "{label}: interior force_sd vs MC {e_int:.3}");
    }

    // The direct solve with the edge bridge (no coarse correction): per-node figures by
    // probing; its ΣF SDs are those of the zero-padded map (module docs).
    solver.refine_iterations = 0;
    solver.coarse_correction = false;
    let (mc_force, mc_sum) = monte_carlo(&mut solver, n_in, n_out, sigma, 300);
    solver.force_sd(sigma, &mut sd).unwrap();
    let predicted = solver.sum_sd(sigma).unwrap();
    let e_nodes = rel_err(&sd, &mc_force);
    println!(
        "bridged direct: ΣF SD MC {mc_sum:.4?} vs sum_sd {predicted:.4?}; per node {e_nodes:.3}"
    );
    assert!(
        e_nodes <= 0.10,
        "bridged direct: per-node force_sd vs Monte Carlo {e_nodes:.3}"
    );
    for ax in 0..3 {
        // Exact (P_perᵀ 1_a through the transposed direct solve); was the zero-padded
        // map's figure, 20× too small for ΣFz.
        let e = (predicted[ax] - mc_sum[ax]).abs() / mc_sum[ax];
        assert!(
            e <= 0.10,
            "bridged direct axis {ax}: sum_sd {} vs MC {}",
            predicted[ax],
            mc_sum[ax]
        );
    }

    // The direct solve without the edge bridge is a fixed linear map: exact figures.
    solver.refine_iterations = 0;
    solver.bridge_edges = false;
    let (mc_force, mc_sum) = monte_carlo(&mut solver, n_in, n_out, sigma, 300);
    let predicted = solver.sum_sd(sigma).unwrap();
    solver.force_sd(sigma, &mut sd).unwrap();
    let e_nodes = rel_err(&sd, &mc_force);
    println!("direct: ΣF SD MC {mc_sum:.4?} vs sum_sd {predicted:.4?}; per node {e_nodes:.3}");
    assert!(
        e_nodes <= 0.10,
        "direct: per-node force_sd vs Monte Carlo {e_nodes:.3}"
    );
    for ax in 0..3 {
        let e = (predicted[ax] - mc_sum[ax]).abs() / mc_sum[ax];
        assert!(
            e <= 0.10,
            "direct axis {ax}: sum_sd {} vs MC {}",
            predicted[ax],
            mc_sum[ax]
        );
    }
    assert!(solver.sum_sd(f64::NAN).is_err() && solver.force_sd(-1.0, &mut sd).is_err());
}

#[test]
#[ignore = "needs Python with NumPy: TACTBENCH_PYTHON=python3 cargo test --test integration fourier::numpy_reference -- --ignored"]
fn numpy_reference_agrees_with_fourier_output() {
    // The independent check of tests/numpy_ref/fourier_check.py (Eq. 1–2 and dense
    // Tikhonov in NumPy) on several grids, loads and noise levels; see that file.
    let Ok(python) = std::env::var("TACTBENCH_PYTHON") else {
        println!("TACTBENCH_PYTHON is not set: skipped (set it to a python with numpy)");
        return;
    };
    let grid = |g: &tactbench::sensor::Grid| serde_json::json!({"nx": g.nx, "ny": g.ny, "pitch_mm": g.pitch_mm, "origin_mm": g.origin_mm});
    let mut cases = Vec::new();
    // 16, 12 and 20: the two-level coarse space is the whole force grid; 32×32: hats
    // every 3 force nodes (k = 432 of 3072), the correction NumPy checks independently.
    for (n, pf, pm) in [
        (16, 1.1, 1.1),
        (12, 2.2, 1.1),
        (20, 1.1, 1.1),
        (32, 1.1, 1.1),
    ] {
        let s = grid_sensor(n, n, pf, pm);
        let sites = MarkerSite::from_sensor_grids(&s);
        let p = Problem::new(&s, &sites);
        let h: DMatrix<f64> = transfer_matrix(&p.model, &sites, &s.force_points_mm()).unwrap();
        let lambda = 1e-2 * h.singular_values().max();
        let mut solver =
            FourierSolver::precompute(&p, &config(Lambda::Fixed(lambda)), None).unwrap();
        let mut loads = acceptance_loads(&s);
        loads.truncate(if n == 20 { 5 } else { 3 });
        for (k, (name, f_true)) in loads.into_iter().enumerate() {
            let clean = displacements(&s, &sites, &f_true);
            let sigma = if k == 2 { 0.0005 } else { 0.0 };
            let nz = noise(clean.len(), sigma, 77 + k as u64);
            let u: Vec<f64> = clean.iter().zip(&nz).map(|(a, b)| a + b).collect();
            let mut f = vec![0.0; p.n_outputs()];
            solver.apply(&u, &mut f).unwrap();
            let layers: Vec<_> = s
                .layers
                .iter()
                .map(|l| {
                    let mut g = grid(&l.markers.unwrap().grid);
                    g["depth_mm"] = serde_json::json!(l.depth_mm);
                    g
                })
                .collect();
            let mut case = serde_json::json!({
                "name": format!("{n}x{n} pitch {pf}/{pm} {name} noise {sigma} mm"),
                "young_mpa": p.model.young_n_per_mm2, "poisson": p.model.poisson,
                "lambda": lambda, "force_grid": grid(&s.force_grid), "layers": layers,
                "f_true": f_true, "noise_mm": nz, "fourier": f,
            });
            if k == 0 {
                // The reported uncertainties (per node and of the force sums), checked
                // against NumPy's dense P: those of the refined solve, whose map is
                // dense Tikhonov. Where the two-level coarse space is every node (16, 12,
                // 20) that is the default map too; on 32×32 the default map is not dense
                // P (its own figures are checked against its Monte Carlo in
                // `two_level_uncertainty_matches_monte_carlo_at_32x32`).
                let sd_sigma = 0.005;
                let mut sd = vec![0.0; p.n_outputs()];
                if solver
                    .coarse_space()
                    .is_some_and(|(_, spacing)| spacing > 1)
                {
                    solver.refine_iterations = 50;
                }
                solver.force_sd(sd_sigma, &mut sd).unwrap();
                solver.refine_iterations = 0;
                case["sigma_mm"] = serde_json::json!(sd_sigma);
                case["force_sd"] = serde_json::json!(sd);
                case["sum_sd"] = serde_json::json!(solver.sum_sd(sd_sigma).unwrap());
            }
            cases.push(case);
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cases.json");
    std::fs::write(&path, serde_json::json!({ "cases": cases }).to_string()).unwrap();
    let script = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/numpy_ref/fourier_check.py"
    );
    let out = std::process::Command::new(&python)
        .arg(script)
        .arg(&path)
        .output()
        .expect("run python");
    println!("{}", String::from_utf8_lossy(&out.stdout));
    assert!(
        out.status.success(),
        "numpy check failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn two_level_uncertainty_matches_monte_carlo_at_32x32() {
    // At 32×32 the coarse correction is not the identity (hats every 3 force nodes), so
    // its part of every column is spread over a coarse cell: the probed per-node SDs and
    // the exact ΣF SDs are checked against 300 seeded noise-only frames.
    let s = grid_sensor(32, 32, 1.1, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let p = Problem::new(&s, &sites);
    let (n_in, n_out) = (p.n_inputs(), p.n_outputs());
    let lambda = periodic_lambda(&p, 2e-3);
    let mut solver = FourierSolver::precompute(&p, &config(Lambda::Fixed(lambda)), None).unwrap();
    assert!(solver.two_level());
    assert_eq!(solver.coarse_space(), Some((432, 3)));
    let sigma = 0.005;
    let (mc_force, mc_sum) = monte_carlo(&mut solver, n_in, n_out, sigma, 300);
    let mut sd = vec![0.0; n_out];
    solver.force_sd(sigma, &mut sd).unwrap();
    let predicted = solver.sum_sd(sigma).unwrap();
    let e_all = rel_err(&sd, &mc_force);
    let e_int = rel_err(&interior(&s, &sd, 4.0), &interior(&s, &mc_force, 4.0));
    println!(
        "32×32 two-level: ΣF SD MC {mc_sum:.4?} vs sum_sd {predicted:.4?}; per node all \
         {e_all:.3}, interior {e_int:.3}"
    );
    assert!(e_all <= 0.10, "per-node force_sd vs MC {e_all:.3}");
    assert!(e_int <= 0.10, "interior force_sd vs MC {e_int:.3}");
    for ax in 0..3 {
        let e = (predicted[ax] - mc_sum[ax]).abs() / mc_sum[ax];
        assert!(
            e <= 0.10,
            "axis {ax}: sum_sd {} vs MC {}",
            predicted[ax],
            mc_sum[ax]
        );
    }
}

#[test]
fn two_level_default_meets_the_bounds_at_64x64() {
    // The speed target's grid (64×64 forces and markers at 1.1 mm, two layers, 1.2 ms
    // per frame on-CPU: README *Performance*): the default two-level solve on the
    // acceptance loads against dense Tikhonov at λ = 2e-3 of the periodic σ_max, here
    // the refinement run to convergence (equal to dense Tikhonov to 1e-6 on 16×16 above;
    // a dense solve at 12288 unknowns is too slow for a test). Measured: force sums
    // within 1e-8 of the applied total, field within 3.6 % (interior 2.1 %).
    let s = grid_sensor(64, 64, 1.1, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let p = Problem::new(&s, &sites);
    let lambda = periodic_lambda(&p, 2e-3);
    let mut solver = FourierSolver::precompute(&p, &config(Lambda::Fixed(lambda)), None).unwrap();
    assert!(solver.two_level());
    assert_eq!(solver.coarse_space(), Some((147, 11)));
    let mut f = vec![0.0; p.n_outputs()];
    let mut dense = vec![0.0; p.n_outputs()];
    let loads = acceptance_loads(&s);
    for (name, f_true) in [&loads[0], &loads[4]] {
        let u = displacements(&s, &sites, f_true);
        solver.refine_iterations = 300;
        solver.refine_tolerance = 1e-9;
        solver.apply(&u, &mut dense).unwrap();
        solver.refine_iterations = 0;
        solver.apply(&u, &mut f).unwrap();
        check_against_dense(&s, name, f_true, &f, &dense);
        let (sf, sd) = (sums(&f), sums(&dense));
        let total = sums(f_true).iter().map(|v| v.abs()).fold(0.0, f64::max);
        for ax in 0..3 {
            assert!(
                (sf[ax] - sd[ax]).abs() <= 1e-6 * total,
                "{name}: two-level ΣF axis {ax} {} vs dense {}",
                sf[ax],
                sd[ax]
            );
        }
    }
}

#[test]
fn lambda_zero_has_no_two_level_correction_and_says_so() {
    // λ = 0 (the pseudo-inverse of each frequency block) has no Galerkin correction: the
    // solver warns that the direct periodic solve alone carries the boundary error,
    // instead of passing it off as the default's accuracy; its forces stay finite. A
    // usable λ builds the two-level solve with no warning.
    let s = grid_sensor(16, 16, 1.1, 1.1);
    let sites = MarkerSite::from_sensor_grids(&s);
    let p = Problem::new(&s, &sites);
    let mut solver = FourierSolver::precompute(&p, &config(Lambda::Fixed(0.0)), None).unwrap();
    assert!(!solver.two_level());
    let warnings: Vec<&str> = solver.diagnostics().warnings().collect();
    assert!(
        warnings
            .iter()
            .any(|w| w.starts_with("fourier: λ = 0 has no two-level correction")),
        "{warnings:?}"
    );
    let loads = acceptance_loads(&s);
    let u = displacements(&s, &sites, &loads[0].1);
    let mut f = vec![0.0; p.n_outputs()];
    solver.apply(&u, &mut f).unwrap();
    assert!(f.iter().all(|v| v.is_finite()));
    let sigma_max = solver.diagnostics().singular_values[0];
    let solver =
        FourierSolver::precompute(&p, &config(Lambda::Fixed(2e-3 * sigma_max)), None).unwrap();
    assert!(solver.two_level());
    assert_eq!(solver.diagnostics().warnings().count(), 0);
}
