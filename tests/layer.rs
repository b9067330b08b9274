//! The bonded-layer forward model (issue 14): an independent numerical reference, the
//! sensor/scene keys, and the dense solvers on bonded-layer data.

use std::path::Path;
use std::process::Command;

use nalgebra::{DMatrix, DVector};
use tactbench::model::{self, layer::scalar_kernels, ElasticModel, ForwardModel, MarkerSite};
use tactbench::sensor::{grid_sensor, paper_sensor, ModelKind, Sensor};
use tactbench::solve::{self, FrameSolver, Lambda, Method, Problem, Rank, SolverConfig};

use crate::util::interior;

/// Compares one line `h z nu k ll tt lz zl zz` of `tests/numpy_ref/layer_check.py`.
fn check_reference_line(line: &str, tol: f64) {
    let v: Vec<f64> = line
        .split_whitespace()
        .map(|t| t.parse().expect("number"))
        .collect();
    assert_eq!(v.len(), 9, "{line}");
    let (h, z, nu, k) = (v[0], v[1], v[2], v[3]);
    let g = scalar_kernels(k, z, h, 1.0, nu);
    let got = [g.ll, g.tt, g.lz, g.zl, g.zz];
    let scale = got
        .iter()
        .chain(&v[4..])
        .fold(0.0f64, |m, x| m.max(x.abs()));
    for (i, (a, b)) in got.iter().zip(&v[4..]).enumerate() {
        assert!(
            (a - b).abs() <= tol * scale,
            "h={h} z={z} nu={nu} k={k} kernel {i}: {a} vs {b} (numpy ODE)"
        );
    }
}

/// Values printed by `tests/numpy_ref/layer_check.py` (SciPy 1.17 DOP853 integration of
/// the displacement–stress ODE system, rtol 1e-12; E = 1 N/mm²) for a 3 mm gel and the
/// paper's 40 mm layer: `h z nu k ll tt lz zl zz`.
const NUMPY_ODE_VALUES: [&str; 4] = [
    "3.0 0.5 0.3 0.05 6.336688651029196e+00 6.444305835322504e+00 -1.236575395278046e-01 9.210645313982635e-03 1.859513477066861e+00",
    "3.0 0.5 0.49 0.5 1.471110874946432e+00 4.058577918032356e+00 -1.055826844062408e+00 3.311043868500869e-01 1.152317680772329e+00",
    "3.0 2.0 0.49 0.5 1.935293239041819e-02 1.320232667226928e+00 -8.923871532089088e-01 -4.797397745903491e-02 2.925539155835863e-01",
    "40.0 3.0 0.49 0.05 1.905978621897798e+01 4.913007440189921e+01 -8.472205118258614e+00 2.695211567129860e+00 1.857081544405747e+01",
];

#[test]
fn thin_layer_kernels_match_numpy_ode_values() {
    for line in NUMPY_ODE_VALUES {
        check_reference_line(line, 1e-8);
    }
}

/// Runs the NumPy/SciPy helper (needs `pip install numpy scipy`):
/// `TACTBENCH_PYTHON=python3 cargo test --test integration layer:: -- --ignored`.
#[test]
#[ignore]
fn numpy_reference_kernels_agree() {
    let python = std::env::var("TACTBENCH_PYTHON").expect("set TACTBENCH_PYTHON to a python");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/numpy_ref/layer_check.py");
    let out = Command::new(python)
        .arg(script)
        .output()
        .expect("python runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).expect("utf-8");
    let mut n = 0;
    for line in text.lines().filter(|l| !l.trim().is_empty()) {
        check_reference_line(line, 1e-8);
        n += 1;
    }
    assert!(n >= 20, "only {n} reference lines");
}

fn bonded(sensor: &Sensor, thickness_mm: f64) -> Sensor {
    let mut s = sensor.clone();
    s.elastomer.model = ModelKind::BondedLayer;
    s.elastomer.thickness_mm = thickness_mm;
    s
}

fn rel_err(a: &[f64], b: &[f64]) -> f64 {
    let d: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum();
    let n: f64 = b.iter().map(|y| y * y).sum();
    (d / n).sqrt()
}

/// A smooth load over the force grid (N).
fn smooth_load(sensor: &Sensor) -> Vec<f64> {
    let pts = sensor.force_points_mm();
    let c = pts
        .iter()
        .fold([0.0, 0.0], |a, p| [a[0] + p[0], a[1] + p[1]]);
    let c = [c[0] / pts.len() as f64, c[1] / pts.len() as f64];
    pts.iter()
        .flat_map(|p| {
            let r2 = (p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2);
            let g = (-r2 / 30.0).exp();
            [0.2 * g, -0.1 * g, 0.5 * g]
        })
        .collect()
}

#[test]
fn bonded_layer_solver_recovers_forces_like_the_half_space_solver() {
    let cfg = SolverConfig {
        method: Method::Pinv,
        ..SolverConfig::default()
    };
    let mut errs = Vec::new();
    for sensor in [
        paper_sensor(),
        bonded(&paper_sensor(), 40.0),
        bonded(&paper_sensor(), 8.0),
    ] {
        let sites = MarkerSite::from_sensor_grids(&sensor);
        let p = Problem::new(&sensor, &sites);
        let truth = smooth_load(&sensor);
        let fm = p.forward_model();
        assert_eq!(fm.kind(), sensor.elastomer.model);
        let u = model::forward(&fm, &sites, &sensor.force_points_mm(), &truth).unwrap();
        let t = std::time::Instant::now();
        let mut s = solve::precompute(&p, &cfg, Some(&u)).unwrap();
        eprintln!(
            "{} h={} mm: precompute (H + SVD) {:.3} s",
            sensor.elastomer.model,
            sensor.elastomer.thickness_mm,
            t.elapsed().as_secs_f64()
        );
        let mut f = vec![0.0; s.n_outputs()];
        s.apply(&u, &mut f).unwrap();
        errs.push(rel_err(&f, &truth));
    }
    eprintln!(
        "relative force error: half-space {:.2e}, layer 40 mm {:.2e}, 8 mm {:.2e}",
        errs[0], errs[1], errs[2]
    );
    // Noise-free data of the solver's own model: recovered to the accuracy the
    // half-space solver reaches on half-space data (within a factor 10, all tiny).
    for e in &errs[1..] {
        assert!(*e < (10.0 * errs[0]).max(1e-6), "{errs:?}");
    }
    // And the half-space solver on layer data is measurably off (the model error).
    let layer = bonded(&paper_sensor(), 8.0);
    let sites = MarkerSite::from_sensor_grids(&layer);
    let truth = smooth_load(&layer);
    let u = model::forward(
        &ForwardModel::from_elastomer(&layer.elastomer),
        &sites,
        &layer.force_points_mm(),
        &truth,
    )
    .unwrap();
    let hs = paper_sensor();
    let mut s = solve::precompute(&Problem::new(&hs, &sites), &cfg, Some(&u)).unwrap();
    let mut f = vec![0.0; s.n_outputs()];
    s.apply(&u, &mut f).unwrap();
    assert!(rel_err(&f, &truth) > 100.0 * errs[0]);
}

#[test]
fn half_space_sensor_builds_the_same_h_as_before() {
    let sensor = paper_sensor();
    let sites = MarkerSite::from_sensor_grids(&sensor);
    let p = Problem::new(&sensor, &sites);
    let a = model::transfer_matrix(&p.model, &sites, &sensor.force_points_mm()).unwrap();
    let b = model::transfer_matrix(&p.forward_model(), &sites, &sensor.force_points_mm()).unwrap();
    assert_eq!(a, b);
}

#[test]
fn bonded_layer_rejects_markers_below_the_plate() {
    let l = model::BondedLayer::new(1.0, 0.5, 2.0).unwrap();
    let m = [MarkerSite {
        layer: 0,
        position_mm: [0.0, 0.0],
        depth_mm: 3.0,
    }];
    assert!(matches!(
        model::transfer_matrix(&l, &m, &[[0.0, 0.0]]),
        Err(model::ModelError::BelowLayer { .. })
    ));
    assert!(model::BondedLayer::new(1.0, 0.5, 0.0).is_err());
    assert_eq!(l.max_depth_mm(), 2.0);
}

#[test]
fn model_forward_cli_uses_the_sensor_files_model() {
    let dir = std::env::temp_dir().join(format!("tactbench-layer-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let sensor = bonded(&paper_sensor(), 10.0);
    let sp = dir.join("s.toml");
    std::fs::write(&sp, sensor.to_toml_string()).unwrap();
    let fp = dir.join("f.csv");
    std::fs::write(
        &fp,
        "ix,iy,x_mm,y_mm,fx_n,fy_n,fz_n\n0,0,9.0,7.0,0.3,0.0,1.0\n",
    )
    .unwrap();
    let out = dir.join("d.csv");
    let o = crate::util::run(&[
        "model",
        "forward",
        "--sensor",
        sp.to_str().unwrap(),
        "--forces",
        fp.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", crate::util::stderr(&o));
    let text = std::fs::read_to_string(&out).unwrap();
    let sites = MarkerSite::from_sensor_grids(&sensor);
    let want = model::forward(
        &ForwardModel::from_elastomer(&sensor.elastomer),
        &sites,
        &[[9.0, 7.0]],
        &[0.3, 0.0, 1.0],
    )
    .unwrap();
    let hs = model::forward(
        &model::HalfSpace::from_elastomer(&sensor.elastomer),
        &sites,
        &[[9.0, 7.0]],
        &[0.3, 0.0, 1.0],
    )
    .unwrap();
    let header: Vec<&str> = text.lines().next().unwrap().split(',').collect();
    let ux = header.iter().position(|h| *h == "ux_mm").unwrap();
    let rows: Vec<f64> = text
        .lines()
        .skip(1)
        .map(|l| l.split(',').nth(ux).unwrap().parse().unwrap())
        .collect();
    assert_eq!(rows.len(), sites.len());
    let got = rows;
    let want_x: Vec<f64> = want.iter().step_by(2).copied().collect();
    let hs_x: Vec<f64> = hs.iter().step_by(2).copied().collect();
    assert!(rel_err(&got, &want_x) < 1e-6, "{}", rel_err(&got, &want_x));
    assert!(rel_err(&got, &hs_x) > 1e-3);
    let _ = std::fs::remove_dir_all(&dir);
}

const SCENE: &str = r#"
sensor = "../paper_sensor.toml"
[indenter]
kind = "flat"
diameter_mm = 5.0
[load]
position_mm = [9.0, 6.75]
normal_force_gf = 910.0
tangential_force_gf = 200.0
"#;

#[test]
fn scene_physics_selects_the_rendered_model_and_defaults_to_today() {
    use tactbench::sim::scene::Scene;
    use tactbench::sim::simulate::Simulation;
    let plain = Scene::from_toml_str(SCENE, "s.toml", paper_sensor()).unwrap();
    assert_eq!(plain.physics, ModelKind::HalfSpace);
    let text = format!("{SCENE}[physics]\nmodel = \"bonded-layer\"\n");
    let layer = Scene::from_toml_str(&text, "s.toml", paper_sensor()).unwrap();
    assert_eq!(layer.physics, ModelKind::BondedLayer);
    let bad = format!("{SCENE}[physics]\nmodel = \"fem\"\n");
    let e = Scene::from_toml_str(&bad, "s.toml", paper_sensor())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("s.toml") && e.contains("physics.model") && e.contains("\"fem\""),
        "{e}"
    );

    // No [physics]: bit-identical to a simulation built without the key.
    let mut a = Simulation::from_scene(&plain);
    let mut b = Simulation::new(plain.sensor.clone(), plain.indenter, plain.pipeline.clone())
        .with_pixel_filter(plain.pixel_filter);
    let (mut fa, mut fb) = (a.blank_frame(), b.blank_frame());
    let ta = a.render_load(&plain.load, 1, &mut fa).unwrap();
    let tb = b.render_load(&plain.load, 1, &mut fb).unwrap();
    assert_eq!(ta, tb);
    assert_eq!(fa.as_raw(), fb.as_raw());
    assert!(ta.elastic_uz_mm.iter().any(|v| *v > 0.0));

    // The bonded layer renders a different (smaller, the plate stiffens) field.
    let mut c = Simulation::from_scene(&layer);
    let mut fc = c.blank_frame();
    let tc = c.render_load(&layer.load, 1, &mut fc).unwrap();
    let d = rel_err(&tc.elastic_u_mm, &ta.elastic_u_mm);
    eprintln!(
        "scene: bonded-layer vs half-space marker displacements differ by {:.1} %",
        100.0 * d
    );
    assert!(d > 1e-3);
    assert_ne!(fc.as_raw(), fa.as_raw());
}

// ---- the Fourier solver and every solver on bonded-layer sensors (issue 14) -------

/// `grid_sensor` on the bonded-layer model: `thickness_mm`, markers at `depths_mm`.
fn layer_grid(grid: (usize, usize, f64, f64), thickness_mm: f64, depths_mm: [f64; 2]) -> Sensor {
    let mut s = grid_sensor(grid.0, grid.1, grid.2, grid.3);
    s.elastomer.model = ModelKind::BondedLayer;
    s.elastomer.thickness_mm = thickness_mm;
    s.layers[0].depth_mm = depths_mm[0];
    s.layers[1].depth_mm = depths_mm[1];
    s
}

/// The marker depths used in a layer of this thickness: the paper's 3 / 6 mm, or
/// 1 / 2 mm in a 3 mm gel.
fn depths_for(thickness_mm: f64) -> [f64; 2] {
    if thickness_mm < 6.0 {
        [1.0, 2.0]
    } else {
        [3.0, 6.0]
    }
}

/// A Gaussian load of width `w` mm centred at `c`, components `amp` N per node.
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

fn sums(f: &[f64]) -> [f64; 3] {
    let mut s = [0.0; 3];
    for (i, v) in f.iter().enumerate() {
        s[i % 3] += v;
    }
    s
}

/// Dense Tikhonov `V diag(σ/(σ²+λ²)) Uᵀ` at λ = `rel`·σ₁ on the sensor's own model
/// (nalgebra's SVD, independent of the solvers); returns it and λ.
fn dense_tikhonov(sensor: &Sensor, sites: &[MarkerSite], rel: f64) -> (DMatrix<f64>, f64) {
    let p = Problem::new(sensor, sites);
    let h = model::transfer_matrix(&p.forward_model(), sites, &sensor.force_points_mm()).unwrap();
    let svd = h.svd(true, true);
    let lambda = rel * svd.singular_values.max();
    let (uu, vt) = (svd.u.unwrap(), svd.v_t.unwrap());
    let mut v = vt.transpose();
    for (i, mut col) in v.column_iter_mut().enumerate() {
        let s = svd.singular_values[i];
        col *= s / (s * s + lambda * lambda);
    }
    (v * uu.transpose(), lambda)
}

#[test]
fn fourier_on_bonded_layers_agrees_with_dense_tikhonov_at_3_10_and_40_mm() {
    // The issue-12 acceptance bounds, on bonded-layer sensors: 16×16 forces and markers
    // at 1.1 mm (second layer offset by half a pitch), λ = 1e-2·σ₁ of the layer's dense
    // H, the default refinement; F_sum per axis within 2 % of the applied total,
    // cross-talk of single-axis loads ≤ 2 %, field within 10 % overall, 5 % interior.
    for thickness in [3.0, 10.0, 40.0] {
        let s = layer_grid((16, 16, 1.1, 1.1), thickness, depths_for(thickness));
        let sites = MarkerSite::from_sensor_grids(&s);
        let (pd, lambda) = dense_tikhonov(&s, &sites, 1e-2);
        let p = Problem::new(&s, &sites);
        let cfg = SolverConfig {
            method: Method::Fourier,
            lambda: Lambda::Fixed(lambda),
            ..SolverConfig::default()
        };
        let mut solver = solve::precompute(&p, &cfg, None).unwrap();
        let fm = p.forward_model();
        let c = 0.5 * 1.1 * 15.0;
        let loads = [
            ("centred fx", blob(&s, [c, c], 2.0, [0.1, 0.0, 0.0])),
            ("centred fz", blob(&s, [c, c], 2.0, [0.0, 0.0, 0.1])),
            ("centred mixed", blob(&s, [c, c], 2.0, [0.02, -0.01, 0.1])),
            (
                "off-centre fy",
                blob(&s, [c - 3.0, c + 2.0], 2.0, [0.0, 0.1, 0.0]),
            ),
            (
                "off-centre mixed",
                blob(&s, [c + 4.0, c + 3.0], 2.0, [0.02, -0.01, 0.1]),
            ),
        ];
        let mut f = vec![0.0; p.n_outputs()];
        for (name, f_true) in loads {
            let u = model::forward(&fm, &sites, &s.force_points_mm(), &f_true).unwrap();
            let dense = (&pd * DVector::from_column_slice(&u)).as_slice().to_vec();
            solver.apply(&u, &mut f).unwrap();
            let (st, sd, sf) = (sums(&f_true), sums(&dense), sums(&f));
            let total = st.iter().map(|v| v.abs()).fold(0.0, f64::max);
            let e_all = rel_err(&f, &dense);
            let e_int = rel_err(&interior(&s, &f, 4.0), &interior(&s, &dense, 4.0));
            let e_sum = (0..3)
                .map(|ax| (sf[ax] - sd[ax]).abs() / total)
                .fold(0.0, f64::max);
            eprintln!(
                "h = {thickness} mm, {name}: ΣF vs dense {:.3} % of the total, field {:.3} % \
                 overall, {:.3} % interior",
                100.0 * e_sum,
                100.0 * e_all,
                100.0 * e_int
            );
            assert!(e_sum <= 0.02, "h = {thickness}, {name}: ΣF off by {e_sum}");
            for ax in 0..3 {
                if st[ax] == 0.0 {
                    assert!(
                        sf[ax].abs() <= 0.02 * total,
                        "h = {thickness}, {name}: axis {ax}"
                    );
                }
            }
            assert!(e_all <= 0.10, "h = {thickness}, {name}: field {e_all}");
            assert!(e_int <= 0.05, "h = {thickness}, {name}: interior {e_int}");
        }
    }
}

/// Relative force error of each method (pinv, tikhonov, tsvd, fourier) on noisy data
/// of the sensor's own model: λ = 1e-2·σ₁ (tikhonov, fourier), GCV rank (tsvd).
fn method_errors(s: &Sensor, f_true: &[f64], noise_rel: f64) -> Vec<(Method, f64)> {
    let sites = MarkerSite::from_sensor_grids(s);
    let p = Problem::new(s, &sites);
    let mut u = model::forward(&p.forward_model(), &sites, &s.force_points_mm(), f_true).unwrap();
    let peak = u.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    // Deterministic pseudo-random noise, the same sequence for every sensor.
    let mut x = 0x9E37_79B9_7F4A_7C15u64;
    for v in u.iter_mut() {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        *v += noise_rel * peak * ((x >> 11) as f64 / (1u64 << 53) as f64 - 0.5);
    }
    let (_, lambda) = dense_tikhonov(s, &sites, 1e-2);
    [
        Method::Pinv,
        Method::Tikhonov,
        Method::Tsvd,
        Method::Fourier,
    ]
    .into_iter()
    .map(|method| {
        let cfg = SolverConfig {
            method,
            lambda: Lambda::Fixed(lambda),
            rank: Rank::Auto,
            ..SolverConfig::default()
        };
        let mut solver = solve::precompute(&p, &cfg, Some(&u)).unwrap();
        let mut f = vec![0.0; p.n_outputs()];
        solver.apply(&u, &mut f).unwrap();
        (method, rel_err(&f, f_true))
    })
    .collect()
}

#[test]
fn bonded_layer_solvers_recover_forces_like_the_half_space_solvers_on_their_own_data() {
    // Issue 14's test: every solver on bonded-layer data with the bonded-layer model,
    // against the same solver on half-space data with the half-space model (same grid,
    // same marker depths, same load, same relative noise). 10×8 forces at 2.2 mm on
    // 1.1 mm markers (the paper's force grid on a fourier-compatible marker pitch).
    let grid = (10, 8, 2.2, 1.1);
    let c = [0.5 * 2.2 * 9.0, 0.5 * 2.2 * 7.0];
    for noise in [0.0, 1e-3] {
        for thickness in [3.0, 10.0, 40.0, 1000.0] {
            let layer = layer_grid(grid, thickness, depths_for(thickness));
            let mut half = layer.clone();
            half.elastomer.model = ModelKind::HalfSpace;
            let f_true = blob(&layer, c, 2.0, [0.02, -0.01, 0.1]);
            let el = method_errors(&layer, &f_true, noise);
            let eh = method_errors(&half, &f_true, noise);
            for ((m, e_l), (_, e_h)) in el.iter().zip(&eh) {
                eprintln!(
                    "noise {noise:.0e} of peak, h = {thickness} mm, {m}: force error \
                     layer/layer {e_l:.3e}, half-space/half-space {e_h:.3e}"
                );
                assert!(
                    *e_l <= 1.5 * e_h + 1e-6,
                    "{m}, h = {thickness}, noise {noise}: layer {e_l} vs half-space {e_h}"
                );
            }
        }
    }
}

#[test]
fn a_1000_mm_bonded_layer_reconstructs_like_the_half_space() {
    // h → ∞ for the solvers: the bonded-layer sensor with h = 1000 mm against the
    // half-space sensor, same half-space data, every method (fourier included).
    let grid = (10, 8, 2.2, 1.1);
    let layer = layer_grid(grid, 1000.0, [3.0, 6.0]);
    let mut half = layer.clone();
    half.elastomer.model = ModelKind::HalfSpace;
    let sites = MarkerSite::from_sensor_grids(&half);
    let f_true = blob(&half, [9.9, 7.7], 2.0, [0.02, -0.01, 0.1]);
    let hs = model::HalfSpace::from_elastomer(&half.elastomer);
    let u = model::forward(&hs, &sites, &half.force_points_mm(), &f_true).unwrap();
    let (_, lambda) = dense_tikhonov(&half, &sites, 1e-2);
    for method in [
        Method::Pinv,
        Method::Tikhonov,
        Method::Tsvd,
        Method::Fourier,
    ] {
        // Fourier refined to convergence (tolerance 0, 200 iterations): at the default
        // tolerance each solve stops within ~2 % of its own dense Tikhonov solution, and
        // the two models' solves may stop on opposite sides of it.
        let cfg = SolverConfig {
            method,
            lambda: Lambda::Fixed(lambda),
            rank: Rank::Fixed(150),
            fourier_refine_iterations: 200,
            fourier_refine_tolerance: 0.0,
            ..SolverConfig::default()
        };
        let solve_with = |s: &Sensor| {
            let p = Problem::new(s, &sites);
            let mut solver: Box<dyn FrameSolver> = solve::precompute(&p, &cfg, None).unwrap();
            let mut f = vec![0.0; p.n_outputs()];
            solver.apply(&u, &mut f).unwrap();
            f
        };
        let (fl, fh) = (solve_with(&layer), solve_with(&half));
        let (d, el, eh) = (
            rel_err(&fl, &fh),
            rel_err(&fl, &f_true),
            rel_err(&fh, &f_true),
        );
        let (sl, sh) = (sums(&fl), sums(&fh));
        eprintln!(
            "{method}: h = 1000 mm vs half-space forces differ by {d:.2e}; error vs truth \
             {el:.3e} / {eh:.3e}; ΣF {sl:.4?} / {sh:.4?}"
        );
        // The rigid base 1000 mm down still shifts the responses by ~1.2 % of their
        // peak (falling like 1/h, `model::layer` tests); pinv amplifies that to 3 %,
        // the regularised methods do not.
        let bound = if method == Method::Pinv { 0.05 } else { 0.02 };
        assert!(d < bound, "{method}: {d}");
        for ax in 0..3 {
            assert!(
                (sl[ax] - sh[ax]).abs() < 0.02 * sh[2].abs(),
                "{method}: {sl:?} vs {sh:?}"
            );
        }
    }
}

/// `(2π)⁻¹ ∫₀^∞ F(k) J_n(kρ) k dk` by composite Simpson on `[0, kmax]`.
fn hankel(f: impl Fn(f64) -> f64, n: usize, rho: f64, kmax: f64) -> f64 {
    let m = 4000;
    let dk = kmax / m as f64;
    let mut acc = 0.0;
    for i in 0..=m {
        let k = i as f64 * dk;
        let w = if i == 0 || i == m {
            1.0
        } else if i % 2 == 1 {
            4.0
        } else {
            2.0
        };
        acc += w * f(k) * model::layer::bessel_j012(k * rho)[n] * k;
    }
    acc * dk / 3.0 / (2.0 * std::f64::consts::PI)
}

#[test]
fn thin_incompressible_layer_matches_the_lubrication_limit() {
    // Thin-layer case against an independently derived closed form: a bonded
    // incompressible layer (ν = 0.5) much thinner than its load behaves like a
    // lubricating film (the classical thin-layer, or lubrication, approximation,
    // derived here from equilibrium and incompressibility alone): the in-layer pressure equals
    // the applied p, μ ∂²u_x/∂z² = ∂p/∂x with ∂u_x/∂z = 0 at the free surface and
    // u_x = 0 at the plate gives u_x = −(h² − z²)/(2μ) ∂p/∂x; incompressibility and
    // u_z(h) = 0 give u_z = (h − z)²(2h + z)/(6μ) · (−∇²p). For the Gaussian
    // p = p₀ exp(−r²/(2σ²)) at its centre −∇²p = 2p₀/σ², and at r = σ on the x axis
    // ∂p/∂x = −p₀ e^{−1/2}/σ. The model's displacements (its Fourier kernels through
    // a Hankel transform of p̂ = 2πσ²p₀ exp(−k²σ²/2)) must approach these with a
    // relative error falling like (h/σ)².
    let (h, z, e) = (1.0, 0.3, 1.0);
    let mu = e / 3.0;
    let p0 = 1.0;
    let mut errs = Vec::new();
    for sigma in [10.0, 20.0, 40.0] {
        let ph = |k: f64| {
            2.0 * std::f64::consts::PI * sigma * sigma * p0 * (-0.5 * k * k * sigma * sigma).exp()
        };
        let kmax = 9.0 / sigma;
        let uz = hankel(|k| scalar_kernels(k, z, h, e, 0.5).zz * ph(k), 0, 0.0, kmax);
        let ux = -hankel(
            |k| scalar_kernels(k, z, h, e, 0.5).lz * ph(k),
            1,
            sigma,
            kmax,
        );
        let uz_lub = (h - z).powi(2) * (2.0 * h + z) / (6.0 * mu) * 2.0 * p0 / (sigma * sigma);
        let ux_lub = (h * h - z * z) / (2.0 * mu) * p0 * (-0.5f64).exp() / sigma;
        let ez = (uz - uz_lub).abs() / uz_lub;
        let ex = (ux - ux_lub).abs() / ux_lub;
        eprintln!(
            "h/σ = {:.3}: u_z {uz:.6e} vs lubrication {uz_lub:.6e} ({:.2e}); u_x {ux:.6e} \
             vs {ux_lub:.6e} ({:.2e})",
            h / sigma,
            ez,
            ex
        );
        errs.push(ez.max(ex));
    }
    // Quadratic convergence: halving h/σ divides the error by about 4.
    // Measured: 6.2e-2, 1.7e-2, 4.3e-3 (max of u_z and u_x) at h/σ = 0.1, 0.05, 0.025.
    assert!(errs[2] < 6e-3, "{errs:?}");
    for w in errs.windows(2) {
        let r = w[0] / w[1];
        assert!((3.0..5.0).contains(&r), "{errs:?}");
    }
}

#[test]
fn forward_with_a_wrong_force_length_is_an_error_not_a_panic() {
    let l = model::BondedLayer::new(1.0, 0.5, 5.0).unwrap();
    let m = [MarkerSite {
        layer: 0,
        position_mm: [0.0, 0.0],
        depth_mm: 1.0,
    }];
    for f in [vec![1.0, 2.0], vec![0.0; 4]] {
        assert!(matches!(
            model::forward(&l, &m, &[[0.0, 0.0]], &f),
            Err(model::ModelError::ForceLength { expected: 3, .. })
        ));
        assert!(matches!(
            model::forward3(
                &model::HalfSpace::new(1.0, 0.5).unwrap(),
                &m,
                &[[0.0, 0.0]],
                &f
            ),
            Err(model::ModelError::ForceLength { expected: 3, .. })
        ));
    }
}
