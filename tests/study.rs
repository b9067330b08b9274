//! The simulation studies: accuracy against time (library and `tactbench study
//! accuracy-vs-time`) and layer separation (paper Fig. 6, library and CLI).

use std::path::Path;

use tactbench::analysis::accuracy_time::{
    run_study, Metric, Setting, SolverChoice, StudyError, StudyOptions, Sweep, STUDY_COLUMNS,
};
use tactbench::analysis::layer_separation::{
    paper_fig6_load, run_layer_separation, LayerCase, LayerOptions, LayerSolver, LAYER_COLUMNS,
};
use tactbench::sensor::paper_sensor;
use tactbench::sim::scene::Scene;
use tactbench::solve::{Method, Precision, SolverConfig};

use crate::util;

/// A point load of 2 N normal + 0.5 N shear exactly on force node (4, 3) of the paper
/// grid, rendered without effects with the tent pixel filter (exact centroids): the
/// node model represents the load exactly and the tracker measures the true motion.
fn ideal_point_scene(dir: &Path) -> Scene {
    let sensor = util::root("experiments/paper_sensor.toml");
    let text = format!(
        "sensor = {:?}\npixel_filter = \"tent\"\n[indenter]\nkind = \"point\"\n[load]\nposition_mm = [7.9, 5.65]\nnormal_force_n = 2.0\ntangential_force_n = 0.5\ndirection_deg = 30.0\n",
        sensor.display().to_string()
    );
    let path = dir.join("point.toml");
    std::fs::write(&path, text).unwrap();
    Scene::from_path(&path).unwrap()
}

#[test]
fn exact_data_pinv_f64_recovers_a_point_load_on_a_node_within_0_1_percent() {
    let dir = tempfile::tempdir().unwrap();
    let scene = ideal_point_scene(dir.path());
    let options = StudyOptions {
        settings: vec![Setting::baseline()],
        reps: 1,
        realisations: 1,
    };
    let mut events = 0;
    let r = run_study(&scene, &options, &mut |_| events += 1).unwrap();
    assert_eq!(events, 3, "render, prepared and measured events");
    let row = &r.rows[0];
    assert_eq!(row.label, "pinv");
    // Measured 0.017 % (sum) and 0.037 % (field): the residual is the tracker's.
    assert!(row.sum_error < 1e-3, "sum error {}", row.sum_error);
    assert!(row.field_error < 2e-3, "field error {}", row.field_error);
    assert_eq!(row.markers_used, (260, 260));
    assert!(row.total_s > 0.0 && row.precompute_s > 0.0);
}

#[test]
fn study_on_a_tiny_configuration_gives_finite_errors_and_skips_what_cannot_run() {
    let scene =
        Scene::from_path(util::root("experiments/scenes/study_hemisphere_noisy.toml")).unwrap();
    let tik32 = SolverChoice {
        precision: Precision::F32,
        ..SolverChoice::new(Method::Tikhonov)
    };
    let settings = vec![
        Setting::baseline(),
        Setting {
            solver: tik32,
            frames_averaged: 2,
            sweep: Sweep::Frames,
            ..Setting::baseline()
        },
        // 2.2 mm force pitch against 1.5 mm markers: no common lattice for fourier.
        Setting {
            solver: SolverChoice::new(Method::Fourier),
            ..Setting::baseline()
        },
    ];
    let options = StudyOptions {
        settings,
        reps: 2,
        realisations: 2,
    };
    let r = run_study(&scene, &options, &mut |_| {}).unwrap();
    assert_eq!(r.rows.len(), 2);
    assert_eq!(r.skipped.len(), 1);
    assert!(
        r.skipped[0].reason.contains("fourier"),
        "{}",
        r.skipped[0].reason
    );
    for row in &r.rows {
        assert!(
            row.sum_error.is_finite() && row.field_error.is_finite(),
            "{row:?}"
        );
        assert!(row.total_s > 0.0 && row.track_s > 0.0 && row.solve_s > 0.0);
        // Tracking + solve are the parts of the total (medians of separate passes,
        // so allow the medians' slack of one part).
        assert!(row.total_s <= 2.0 * (row.track_s + row.solve_s));
        // Per repetition CPU time ≤ wall time over the same interval, so the medians
        // keep that order (1 µs for the two clocks' granularity).
        #[cfg(target_os = "linux")]
        assert!(
            row.total_cpu_s > 0.0 && row.total_cpu_s <= row.total_s + 1e-6,
            "cpu {} s, wall {} s",
            row.total_cpu_s,
            row.total_s
        );
    }
    // The applied force is the scene's: 400 gf normal, 100 gf along +x.
    let gf = 9.80665e-3;
    assert!((r.applied_n[2] - 400.0 * gf).abs() < 1e-3 * 400.0 * gf);
    assert!((r.applied_n[0] - 100.0 * gf).abs() < 1e-3 * 100.0 * gf);
}

#[test]
fn study_rejects_bad_options_with_clear_errors() {
    let scene = Scene::from_path(util::root("experiments/scenes/fig4_flat_910gf.toml")).unwrap();
    let bad = |settings: Vec<Setting>, reps, realisations| {
        let o = StudyOptions {
            settings,
            reps,
            realisations,
        };
        match run_study(&scene, &o, &mut |_| {}) {
            Err(StudyError::InvalidOption(m)) => m,
            other => panic!("expected an invalid option, got {other:?}"),
        }
    };
    let b = Setting::baseline();
    assert!(bad(vec![], 1, 1).contains("no settings"));
    assert!(bad(vec![b], 0, 1).contains("reps = 0"));
    assert!(bad(vec![b], 1, 0).contains("realisations = 0"));
    let m = bad(
        vec![Setting {
            frames_averaged: 0,
            ..b
        }],
        1,
        1,
    );
    assert!(m.contains("frames averaged = 0"), "{m}");
    let m = bad(
        vec![Setting {
            force_pitch_mm: Some(-1.0),
            ..b
        }],
        1,
        1,
    );
    assert!(m.contains("-1 mm"), "{m}");
}

#[test]
fn cli_accuracy_vs_time_writes_table_budgets_and_decodable_plots() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("study");
    let scene = util::root("experiments/scenes/study_hemisphere_noisy.toml");
    let o = util::run(&[
        "study",
        "accuracy-vs-time",
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--sweeps",
        "frames",
        "--frames",
        "2",
        "--reps",
        "2",
        "--realisations",
        "1",
        "--budgets",
        "0.001,5,1000",
    ]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    let csv = std::fs::read_to_string(out.join("accuracy_vs_time.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next().unwrap(), STUDY_COLUMNS.join(","));
    // The frames sweep: pinv and tikhonov, averaging 2 frames.
    let rows: Vec<&str> = lines.collect();
    assert_eq!(rows.len(), 2, "{csv}");
    assert!(
        rows[0].starts_with("pinv | avg 2,frames,pinv,f64,"),
        "{}",
        rows[0]
    );
    let budgets = std::fs::read_to_string(out.join("budgets.csv")).unwrap();
    let b: Vec<&str> = budgets.lines().collect();
    assert_eq!(b[0], "metric,budget,label,error,total_us");
    // 0.001 % cannot be met; 1000 % is met by the faster of the two.
    assert!(b[1].starts_with("sum,0.00001,,"), "{}", b[1]);
    assert!(
        b[3].starts_with("sum,10,") && b[3].contains("avg 2"),
        "{}",
        b[3]
    );
    let stdout = util::stdout(&o);
    assert!(stdout.contains("0.001 %: no setting meets it"), "{stdout}");
    for ext in ["png", "svg"] {
        assert!(out.join(format!("accuracy_vs_time.{ext}")).exists());
    }
    let img = image::open(out.join("accuracy_vs_time.png")).unwrap();
    assert_eq!((img.width(), img.height()), (1400, 900));
    let svg = std::fs::read_to_string(out.join("accuracy_vs_time.svg")).unwrap();
    assert!(svg.contains("avg 2"), "point labels missing from the SVG");
    let err = util::stderr(&o);
    assert!(
        err.contains("[ 2/2] tikhonov gcv | avg 2: tracked"),
        "progress: {err}"
    );
}

#[test]
fn cli_study_rejects_bad_arguments() {
    let scene = util::root("experiments/scenes/fig4_flat_910gf.toml");
    let scene = scene.to_str().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().to_str().unwrap();
    let cases: [(&[&str], &str); 5] = [
        (&["--metric", "rms"], "unknown metric `rms`"),
        (&["--sweeps", "solver,colour"], "unknown sweep `colour`"),
        (&["--budgets", "-5"], "-5 % is not a positive percentage"),
        (&["--frames", "0"], "0 frames averaged"),
        (&["--reps", "0"], "reps = 0"),
    ];
    for (extra, expected) in cases {
        let mut args = vec!["study", "accuracy-vs-time", "--scene", scene, "--out", out];
        args.extend_from_slice(extra);
        let o = util::run(&args);
        assert!(!o.status.success(), "{extra:?} accepted");
        assert!(
            util::stderr(&o).contains(expected),
            "{extra:?}: {}",
            util::stderr(&o)
        );
    }
    let o = util::run(&[
        "study",
        "accuracy-vs-time",
        "--scene",
        "/nonexistent/s.toml",
    ]);
    assert!(!o.status.success());
    assert!(util::stderr(&o).contains("/nonexistent/s.toml"));
    let o = util::run(&[
        "study",
        "layer-separation",
        "--separations",
        "-1",
        "--out",
        out,
    ]);
    assert!(!o.status.success());
    assert!(util::stderr(&o).contains("-1 mm"), "{}", util::stderr(&o));
}

fn pinv_only(noise_px: Vec<f64>) -> LayerOptions {
    LayerOptions {
        solvers: vec![LayerSolver {
            label: "pinv".into(),
            config: SolverConfig::default(),
        }],
        noise_px,
        ..LayerOptions::default()
    }
}

#[test]
fn layer_separation_exact_data_with_pinv_is_exact_at_every_distance() {
    let s = paper_sensor();
    let load = paper_fig6_load(&s.force_grid).unwrap();
    let o = pinv_only(vec![0.0]);
    let r = run_layer_separation(&s, &load, &o, &mut |_| {}).unwrap();
    assert_eq!(r.rows.len(), o.cases.len());
    for row in &r.rows {
        // Measured 3e-13..3e-11 gf (the single layer is the worst conditioned);
        // the load is 6.1 gf per loaded node along z.
        assert!(row.mean_abs_gf < 1e-6, "{row:?}");
        assert!(row.rel_l2 < 1e-6, "{row:?}");
    }
}

#[test]
fn layer_separation_with_noise_error_grows_as_the_layers_approach_and_part() {
    // Paper Fig. 6: single layer ≳ same depth > 2–3 mm (minimum) < wide separation.
    // Checked with pinv (the paper's method) at 0.1 px, 20 seeded draws shared by all
    // cases (paired comparison). Measured: single 1.1e4 gf, d=0 122, d=1 108, d=2 115,
    // d=13 634.
    let s = paper_sensor();
    let load = paper_fig6_load(&s.force_grid).unwrap();
    let o = pinv_only(vec![0.1]);
    let r = run_layer_separation(&s, &load, &o, &mut |_| {}).unwrap();
    let e = |c| r.find(c, "pinv", 0.1).unwrap().mean_abs_gf;
    let d = LayerCase::Separation;
    assert!(e(LayerCase::SingleLayer) > 10.0 * e(d(0.0)));
    assert!(e(d(0.0)) > e(d(1.0)), "{} vs {}", e(d(0.0)), e(d(1.0)));
    assert!(e(d(13.0)) > 2.0 * e(d(2.0)));
    // Beyond the minimum the error grows monotonically with the separation.
    let wide = [2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 13.0];
    for w in wide.windows(2) {
        assert!(e(d(w[1])) > e(d(w[0])), "d = {} vs {}", w[1], w[0]);
    }
}

#[test]
fn cli_layer_separation_writes_csv_and_decodable_plot() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ls");
    let o = util::run(&[
        "study",
        "layer-separation",
        "--out",
        out.to_str().unwrap(),
        "--separations",
        "0,3",
        "--trials",
        "2",
    ]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    let csv = std::fs::read_to_string(out.join("layer_separation.csv")).unwrap();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines[0], LAYER_COLUMNS.join(","));
    // 3 cases x 4 solvers x 2 noise levels.
    assert_eq!(lines.len(), 1 + 3 * 4 * 2, "{csv}");
    assert!(
        lines[1].starts_with("single layer,,pinv,0,1,"),
        "{}",
        lines[1]
    );
    let img = image::open(out.join("layer_separation.png")).unwrap();
    assert_eq!((img.width(), img.height()), (1400, 650));
    assert!(out.join("layer_separation.svg").exists());
    assert!(util::stdout(&o).contains("d = 3 mm"));
}

#[test]
fn metric_names_round_trip() {
    for m in [Metric::Sum, Metric::Field] {
        assert_eq!(m.name().parse::<Metric>().unwrap(), m);
    }
    for s in Sweep::ALL {
        assert_eq!(s.name().parse::<Sweep>().unwrap(), s);
    }
}
