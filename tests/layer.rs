//! The bonded-layer forward model (issue 14): an independent numerical reference, the
//! sensor/scene keys, and the dense solvers on bonded-layer data.

use std::path::Path;
use std::process::Command;

use tactbench::model::{self, layer::scalar_kernels, ElasticModel, ForwardModel, MarkerSite};
use tactbench::sensor::{paper_sensor, ModelKind, Sensor};
use tactbench::solve::{self, Method, Problem, SolveError, SolverConfig};

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
fn fourier_solver_refuses_a_bonded_layer_sensor() {
    let sensor = bonded(&paper_sensor(), 40.0);
    let sites = MarkerSite::from_sensor_grids(&sensor);
    let cfg = SolverConfig {
        method: Method::Fourier,
        ..SolverConfig::default()
    };
    let err = solve::precompute(&Problem::new(&sensor, &sites), &cfg, None)
        .err()
        .expect("refused");
    assert!(
        matches!(&err, SolveError::Incompatible(m) if m.contains("bonded-layer")),
        "{err}"
    );
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
    let got: Vec<f64> = rows.iter().copied().collect();
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
