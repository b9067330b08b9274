//! Wrong and hard input (issue 24): each case a user typed by mistake (or a frame that
//! is not what it claims) gives a clear error or the right result, within seconds and
//! well under 2 GB, never a crash, a hang, motion nobody asked for or data that is not.
//! Test names carry the issue's case number.

use std::path::{Path, PathBuf};
use std::process::Output;
use std::time::{Duration, Instant};

use tactbench::bench::journal::{Manifest, RunStatus};
use tactbench::sensor::paper_sensor;

use crate::util;

/// The paper sensor file with the elastomer and depths changed (text substitution on
/// experiments/paper_sensor.toml), written into `dir`.
fn sensor_file(dir: &Path, name: &str, edits: &[(&str, &str)]) -> PathBuf {
    let mut text = util::paper_sensor_text();
    for (from, to) in edits {
        assert!(text.contains(from), "{from}");
        text = text.replace(from, to);
    }
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

/// A displacement CSV of the paper sensor's 260 grid markers, every value `u`
/// (`None`: lost), with one frame.
fn displacement_csv(
    dir: &Path,
    name: &str,
    u: impl Fn(usize, usize) -> Option<[f64; 2]>,
) -> PathBuf {
    let sensor = paper_sensor();
    let mut text = String::from("layer,marker,x_mm,y_mm,ux_mm,uy_mm\n");
    for (li, l) in sensor.layers.iter().enumerate() {
        for (k, p) in l.markers.unwrap().grid.nodes_mm().into_iter().enumerate() {
            match u(li, k) {
                Some([ux, uy]) => {
                    text.push_str(&format!("{},{k},{},{},{ux:e},{uy:e}\n", l.name, p[0], p[1]))
                }
                None => text.push_str(&format!("{},{k},{},{},,\n", l.name, p[0], p[1])),
            }
        }
    }
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

/// `tactbench reconstruct` of the displacement CSV `d` on the paper sensor into `out`.
fn reconstruct(d: &Path, out: &Path) -> Output {
    util::run(&[
        "reconstruct",
        "--sensor",
        "experiments/paper_sensor.toml",
        "--displacements",
        util::arg(d),
        "--out",
        util::arg(out),
    ])
}

// ---- case 1: a thin bonded layer -----------------------------------------------------

#[test]
fn case1_thin_bonded_layer_in_a_sensor_file_typed_in_metres_is_refused_in_seconds() {
    let dir = tempfile::tempdir().unwrap();
    let sensor = sensor_file(
        dir.path(),
        "metres.toml",
        &[
            (
                "thickness_mm = 40.0",
                "thickness_mm = 0.04\nmodel = \"bonded-layer\"",
            ),
            ("depth_mm = 3.0", "depth_mm = 0.003"),
            ("depth_mm = 6.0", "depth_mm = 0.006"),
        ],
    );
    let t = Instant::now();
    let o = util::run(&["model", "inspect", "--sensor", util::arg(&sensor)]);
    let e = util::stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(t.elapsed() < Duration::from_secs(20), "{:?}", t.elapsed());
    // Since issue 33 the sensor file's plausible ranges refuse it at load, before the
    // model's table cap is reached (the study test below still reaches that cap).
    for want in [
        "metres.toml",
        "elastomer.thickness_mm = 0.04 mm",
        "looks like metres",
    ] {
        assert!(e.contains(want), "{want}: {e}");
    }
}

#[test]
fn case1_thin_layers_in_the_model_error_study_are_refused_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    for h in ["1e-6", "0.01", "0.1"] {
        let out = dir.path().join(h);
        let t = Instant::now();
        let o = util::run(&[
            "study",
            "model-error",
            "--thickness",
            h,
            "--effects",
            "none",
            "--loads",
            "mixed",
            "--reps",
            "1",
            "--out",
            util::arg(&out),
        ]);
        let e = util::stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{h}: {e}");
        assert!(
            t.elapsed() < Duration::from_secs(20),
            "{h}: {:?}",
            t.elapsed()
        );
        assert!(e.contains("bonded layer of thickness"), "{h}: {e}");
        assert!(e.contains("allows distances up to"), "{h}: {e}");
    }
}

// ---- case 2: reconstruct's size cap --------------------------------------------------

#[test]
fn case2_reconstruct_refuses_a_dense_system_past_the_memory_cap_before_building_it() {
    let dir = tempfile::tempdir().unwrap();
    // 80,000 markers in one frame: a 160,000 x 240 system (~1.3 GB to decompose).
    let mut text = String::from("layer,marker,x_mm,y_mm,ux_mm,uy_mm\n");
    let mut rng = util::Rng::new(24);
    for k in 0..80_000 {
        let (x, y) = (19.0 * rng.uniform(), 14.0 * rng.uniform());
        text.push_str(&format!("blue,{k},{x:.4},{y:.4},0.001,0\n"));
    }
    let d = dir.path().join("many.csv");
    std::fs::write(&d, text).unwrap();
    let out = dir.path().join("f.csv");
    let t = Instant::now();
    let o = reconstruct(&d, &out);
    let e = util::stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(t.elapsed() < Duration::from_secs(20), "{:?}", t.elapsed());
    for want in [
        "160000x240",
        "GB",
        "past the limit",
        "fourier",
        "fewer markers",
    ] {
        assert!(e.contains(want), "{want}: {e}");
    }
    assert!(!out.exists(), "no output file");
}

// ---- case 3: run --resume --limit ----------------------------------------------------

#[test]
fn case3_resume_with_limit_runs_at_most_n_more_and_a_limited_run_resumes_to_its_plan() {
    let dir = tempfile::tempdir().unwrap();
    // A 6-setpoint version of the Fig. 7 plan (0 ... 250 gf, one trial).
    let plan = util::fig7_plan_cut(dir.path(), "short.toml", 250.0, 1);
    let out = dir.path().join("run");
    let o = util::run(&[
        "run",
        util::arg(&plan),
        "--sim",
        "experiments/scenes/fig7_hemisphere_ramp.toml",
        "--out",
        util::arg(&out),
        "--limit",
        "2",
        "--no-progress",
    ]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    assert_eq!(util::journal_rows(&out), 2);
    let m = Manifest::read(&out).unwrap();
    assert_eq!(m.status, RunStatus::Completed);
    assert_eq!(m.planned(), 6);
    // The report says INCOMPLETE (limited), and why.
    let r = util::run(&["report", util::arg(&out)]);
    assert!(
        util::stdout(&r).contains("limited by --limit 2"),
        "{}",
        util::stdout(&r)
    );

    // A resume with --limit 3 measures 3 more, not the rest of the plan.
    let o = util::run(&[
        "run",
        "--resume",
        util::arg(&out),
        "--limit",
        "3",
        "--no-progress",
    ]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    assert_eq!(util::journal_rows(&out), 5);
    let m = Manifest::read(&out).unwrap();
    assert_eq!(m.limit, Some(3));
    assert!(m
        .incomplete_reason
        .as_deref()
        .unwrap()
        .contains("5 of the plan's 6"));

    // Without --limit: the rest of the plan, then the run is complete.
    let o = util::run(&["run", "--resume", util::arg(&out), "--no-progress"]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    assert_eq!(util::journal_rows(&out), 6);
    let m = Manifest::read(&out).unwrap();
    assert_eq!(m.incomplete_reason, None);
    let sessions: Vec<_> = m
        .sessions
        .iter()
        .map(|s| (s.limit, s.setpoints_before, s.setpoints_after))
        .collect();
    assert_eq!(
        sessions,
        vec![(Some(2), 0, 2), (Some(3), 2, 5), (None, 5, 6)],
        "one entry per session"
    );
    assert!(m.sessions.iter().all(|s| !s.started_at.is_empty()));
    // Complete: a further resume is refused without moving anything.
    let o = util::run(&[
        "run",
        "--resume",
        util::arg(&out),
        "--limit",
        "1",
        "--no-progress",
    ]);
    assert_eq!(o.status.code(), Some(2));
    assert!(
        util::stderr(&o).contains("already completed"),
        "{}",
        util::stderr(&o)
    );
    assert_eq!(util::journal_rows(&out), 6);
    // --help says both.
    let h = util::stdout(&util::run(&["run", "--help"]));
    assert!(h.contains("measures at most N more"), "{h}");
    assert!(h.contains("resumable to its full plan"), "{h}");
}

#[test]
fn case3_manifests_without_sessions_still_load() {
    let dir = tempfile::tempdir().unwrap();
    let text = r#"{"plan_path":"p.toml","plan_name":"p","plan_toml":"","sensor_path":"s.toml",
        "sensor_toml":"","bench":null,"devices":null,"build_id":null,"software_version":"0",
        "started_at":"t","setpoints":3,"status":"completed"}"#;
    std::fs::write(dir.path().join("manifest.json"), text).unwrap();
    let m = Manifest::read(dir.path()).unwrap();
    assert!(m.sessions.is_empty());
}

// ---- case 6: absurd values -----------------------------------------------------------

#[test]
fn case6_absurd_displacements_and_positions_are_errors_naming_line_and_value() {
    let dir = tempfile::tempdir().unwrap();
    let d = displacement_csv(dir.path(), "huge.csv", |li, k| {
        Some(if li == 0 && k == 5 {
            [1e300, 0.0]
        } else {
            [0.001, 0.0]
        })
    });
    let out = dir.path().join("f.csv");
    let o = reconstruct(&d, &out);
    let e = util::stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    // Line 7: the header, then markers 0..5 of blue.
    assert!(
        e.contains("line 7") && e.contains("ux_mm") && e.contains("1e300"),
        "{e}"
    );
    assert!(e.contains("larger than the sensor"), "{e}");
    assert!(!out.exists());
    assert!(e.len() < 2000, "no 300-digit numbers: {e}");

    let mut text = std::fs::read_to_string(&d)
        .unwrap()
        .replace("1e300", "0.001");
    text = text.replacen("blue,0,0,0,", "blue,0,1000000000,0,", 1);
    std::fs::write(&d, &text).unwrap();
    let o = reconstruct(&d, &out);
    let e = util::stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(
        e.contains("line 2") && e.contains("x_mm") && e.contains("outside the sensor"),
        "{e}"
    );
}

#[test]
fn case6_absurd_forces_given_to_model_forward_are_errors() {
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("f.csv");
    std::fs::write(&f, "ix,iy,x_mm,y_mm,fx_n,fy_n,fz_n\n0,0,9,6.75,0,0,1e301\n").unwrap();
    let o = util::run(&[
        "model",
        "forward",
        "--sensor",
        "experiments/paper_sensor.toml",
        "--forces",
        util::arg(&f),
        "--out",
        util::arg(&dir.path().join("u.csv")),
    ]);
    let e = util::stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(
        e.contains("line 2") && e.contains("fz_n") && e.contains("1e301"),
        "{e}"
    );
}

// ---- case 8: errors that blame the wrong thing ---------------------------------------

#[test]
fn case8_a_camera_file_whose_distortion_cannot_be_inverted_fails_at_load_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let sensor = paper_sensor();
    let base = tactbench::vision::CameraCalibration::from_linear(&sensor.camera, &sensor)
        .to_toml_string("paper_sensor.toml", "none");
    for k1 in ["1000000.0", "-5.0"] {
        let text = base
            .lines()
            .map(|l| {
                if l.trim_start().starts_with("k1 =") {
                    format!("k1 = {k1}")
                } else {
                    l.to_string()
                }
            })
            .collect::<Vec<_>>()
            .join("\n");
        let cam = dir.path().join(format!("camera_{k1}.toml"));
        std::fs::write(&cam, text).unwrap();
        let o = util::run_fig7_sim(&["--camera", util::arg(&cam), "--dry-run"]);
        let e = util::stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{k1}: {e}");
        assert!(
            e.contains(util::arg(&cam)),
            "{k1}: names the camera file: {e}"
        );
        assert!(e.contains("invertible"), "{k1}: {e}");
    }
}

#[test]
fn case8_a_run_directory_whose_name_is_not_utf8_works() {
    use std::ffi::OsStr;
    use std::os::unix::ffi::OsStrExt;
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join(OsStr::from_bytes(b"run-\xff\xfe"));
    let o = std::process::Command::new(util::bin())
        .args(util::FIG7_SIM_RUN)
        .args(["--limit", "1", "--no-progress", "--out"])
        .arg(&out)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", util::stderr(&o));
    assert_eq!(util::journal_rows(&out), 1);
}

// ---- case 9: numeric edge cases ------------------------------------------------------

#[test]
fn case9_forces_written_for_tiny_displacements_are_the_scaled_forces() {
    // The same frame at 1, 1e-12 and 1e-13: every force value scales exactly (to the
    // CSV's 12 digits), none is cut to zero by an absolute threshold. (Scaled up by
    // 1e6 a file is refused: 5 m displacements; the solvers' own linearity up to 1e6
    // is the next test.)
    let dir = tempfile::tempdir().unwrap();
    let field = |li: usize, k: usize| {
        [
            0.01 * ((k * 7 + li) % 13) as f64 / 13.0,
            -0.004 * ((k * 3) % 5) as f64,
        ]
    };
    let read = |p: &Path| -> Vec<f64> {
        std::fs::read_to_string(p)
            .unwrap()
            .lines()
            .skip(1)
            .flat_map(|l| {
                l.split(',')
                    .skip(4)
                    .take(3)
                    .map(|v| v.parse::<f64>().unwrap())
                    .collect::<Vec<_>>()
            })
            .collect()
    };
    let mut results = Vec::new();
    for scale in [1.0, 1e-12, 1e-13] {
        let d = displacement_csv(dir.path(), "d.csv", |li, k| {
            let u = field(li, k);
            Some([u[0] * scale, u[1] * scale])
        });
        for solver in ["pinv", "tikhonov"] {
            let out = dir.path().join(format!("f_{solver}_{scale}.csv"));
            let mut args = vec![
                "reconstruct".to_string(),
                "--sensor".into(),
                "experiments/paper_sensor.toml".into(),
                "--displacements".into(),
                util::arg(&d).to_string(),
                "--out".into(),
                util::arg(&out).to_string(),
                "--solver".into(),
                solver.into(),
            ];
            if solver == "tikhonov" {
                args.extend(["--lambda".into(), "0.001".into()]);
            }
            let args: Vec<&str> = args.iter().map(String::as_str).collect();
            let o = util::run(&args);
            assert!(o.status.success(), "{}", util::stderr(&o));
            results.push((solver, scale, read(&out)));
        }
    }
    for (solver, scale, f) in &results {
        let base = &results
            .iter()
            .find(|r| r.0 == *solver && r.1 == 1.0)
            .unwrap()
            .2;
        let peak = base.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let nonzero = f.iter().filter(|v| **v != 0.0).count();
        let base_nonzero = base.iter().filter(|v| **v != 0.0).count();
        assert_eq!(
            nonzero, base_nonzero,
            "{solver} x{scale}: no value cut to zero"
        );
        for (a, b) in f.iter().zip(base) {
            assert!(
                (a / scale - b).abs() <= 1e-9 * peak,
                "{solver} x{scale}: {a} vs {b} scaled"
            );
        }
    }
}

#[test]
fn case9_no_usable_marker_anywhere_is_an_error_for_reconstruct_and_model_inspect() {
    let dir = tempfile::tempdir().unwrap();
    let d = displacement_csv(dir.path(), "lost.csv", |_, _| None);
    let out = dir.path().join("f.csv");
    let o = reconstruct(&d, &out);
    let e = util::stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(e.contains("no usable marker"), "{e}");
    assert!(
        e.contains("blue (130 lost: 0-129)") && e.contains("red (130 lost: 0-129)"),
        "{e}"
    );
    assert!(!out.exists(), "no output file");
    let o = util::run(&[
        "model",
        "inspect",
        "--sensor",
        "experiments/paper_sensor.toml",
        "--displacements",
        util::arg(&d),
    ]);
    let e = util::stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(e.contains("no usable marker"), "{e}");
}

#[test]
fn case9_every_solver_is_linear_over_scalings_from_1e_minus_12_to_1e6() {
    use tactbench::model::MarkerSite;
    use tactbench::sensor::grid_sensor;
    use tactbench::solve::{self, Lambda, Method, Precision, Problem, Rank, SolverConfig};
    let sensor = grid_sensor(10, 8, 2.2, 1.1);
    let sites = MarkerSite::from_sensor_grids(&sensor);
    let problem = Problem::new(&sensor, &sites);
    let mut rng = util::Rng::new(9);
    let u: Vec<f64> = (0..2 * sites.len()).map(|_| 0.01 * rng.normal()).collect();
    let configs = [
        (Method::Pinv, Lambda::Gcv, Rank::Auto, Precision::F64),
        (Method::Pinv, Lambda::Gcv, Rank::Auto, Precision::F32),
        (
            Method::Tikhonov,
            Lambda::Fixed(1e-3),
            Rank::Auto,
            Precision::F64,
        ),
        (
            Method::Tikhonov,
            Lambda::Fixed(1e-3),
            Rank::Auto,
            Precision::F32,
        ),
        (Method::Tsvd, Lambda::Gcv, Rank::Fixed(60), Precision::F64),
        (
            Method::Fourier,
            Lambda::Fixed(1e-3),
            Rank::Auto,
            Precision::F64,
        ),
    ];
    for (method, lambda, rank, precision) in configs {
        let config = SolverConfig {
            method,
            lambda,
            rank,
            precision,
            ..SolverConfig::default()
        };
        let mut solver = solve::precompute(&problem, &config, Some(&u)).unwrap();
        let mut f1 = vec![0.0; solver.n_outputs()];
        solver.apply(&u, &mut f1).unwrap();
        let peak = f1.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(peak > 0.0);
        for scale in [1e-12, 1e-9, 1e-6, 1e-3, 1e3, 1e6] {
            let us: Vec<f64> = u.iter().map(|v| v * scale).collect();
            let mut fs = vec![0.0; solver.n_outputs()];
            solver.apply(&us, &mut fs).unwrap();
            let worst = fs
                .iter()
                .zip(&f1)
                .map(|(a, b)| (a / scale - b).abs())
                .fold(0.0f64, f64::max);
            // f64 is linear to rounding; f32 rounds the (power-of-two scaled) inputs
            // and the operator to 24 bits, its documented ~1e-5 relative accuracy.
            let tol = if precision == Precision::F32 {
                1e-5
            } else {
                1e-9
            };
            assert!(
                worst <= tol * peak,
                "{method:?} {precision:?} x{scale:e}: worst deviation {worst:e} of peak {peak:e}"
            );
        }
    }
}

// ---- case 4: calibrate refuses a frame that is not a clean unloaded frame -----------

mod calibrate_frames {
    use image::Rgb32FImage;
    use tactbench::sim::render::to_rgb16;
    use tactbench::sim::scene::Scene;
    use tactbench::sim::simulate::Simulation;
    use tactbench::vision::{calibrate, CalibrateConfig, CalibrationError, FrameView, Pixels};

    use crate::util;

    /// The reference frame and the 750 gf frame of the Fig. 7 scene, and the
    /// background colour.
    fn frames() -> (Simulation, Rgb32FImage, Rgb32FImage, [f32; 3]) {
        let scene =
            Scene::from_path(util::root("experiments/scenes/fig7_hemisphere_ramp.toml")).unwrap();
        let mut sim = Simulation::from_scene(&scene);
        let mut r = sim.blank_frame();
        sim.render_reference(&mut r).unwrap();
        let mut f = sim.blank_frame();
        sim.render_load(&scene.frame_load(scene.frames), 1, &mut f)
            .unwrap();
        let bg = sim.renderer().palette().background;
        (sim, r, f, bg)
    }

    fn fit(
        frame: &Rgb32FImage,
        sim: &Simulation,
        config: &CalibrateConfig,
    ) -> Result<f64, CalibrationError> {
        let img = to_rgb16(frame);
        let (w, h) = (img.width(), img.height());
        let data = img.into_raw();
        let view = FrameView::new(Pixels::Rgb16(&data), w, h).unwrap();
        calibrate(&view, sim.sensor(), config).map(|f| f.calibration.rms_px)
    }

    #[test]
    fn case4_a_clean_unloaded_frame_still_calibrates() {
        let (sim, r, _, _) = frames();
        let rms = fit(&r, &sim, &CalibrateConfig::default()).unwrap();
        assert!(rms < 0.05, "{rms}");
    }

    #[test]
    fn case4_a_loaded_frame_is_refused_as_not_unloaded() {
        let (sim, _, f, _) = frames();
        let e = fit(&f, &sim, &CalibrateConfig::default()).unwrap_err();
        assert!(matches!(e, CalibrationError::NotUnloaded { .. }), "{e}");
        let m = e.to_string();
        assert!(m.contains("loaded") && m.contains("noise"), "{m}");
    }

    #[test]
    fn case4_an_unloaded_frame_with_a_dark_patch_is_refused() {
        let (sim, mut r, _, _) = frames();
        // A shadow over part of the grid (dust, a cable): 40 % darker.
        for y in 120..175 {
            for x in 170..232 {
                let p = r.get_pixel_mut(x, y);
                for c in 0..3 {
                    p.0[c] *= 0.6;
                }
            }
        }
        let e = fit(&r, &sim, &CalibrateConfig::default()).unwrap_err();
        assert!(
            matches!(
                e,
                CalibrationError::NotUnloaded { .. } | CalibrationError::PartialCoverage { .. }
            ),
            "{e}"
        );
    }

    #[test]
    fn case4_half_the_grid_hidden_names_the_coverage_and_suggests_radial_terms_0() {
        let (sim, mut r, _, bg) = frames();
        let w = r.width();
        for y in 0..r.height() {
            for x in 0..w / 2 {
                r.get_pixel_mut(x, y).0 = bg;
            }
        }
        let e = fit(&r, &sim, &CalibrateConfig::default()).unwrap_err();
        assert!(matches!(e, CalibrationError::PartialCoverage { .. }), "{e}");
        let m = e.to_string();
        assert!(
            m.contains("--radial-terms 0") && m.contains("cannot determine"),
            "{m}"
        );
        assert!(!m.contains("did not converge"), "{m}");
        // Scale and origin alone are determined by half a grid.
        let rms = fit(
            &r,
            &sim,
            &CalibrateConfig {
                radial_terms: 0,
                ..CalibrateConfig::default()
            },
        )
        .unwrap();
        assert!(rms < 0.05, "{rms}");
    }
}
