//! End-to-end tests of `tactbench reconstruct` and `tactbench model`, driven the way an
//! outside user (or checker) would: files on disk, the binary, its exit code and output.

use std::fmt::Write as _;
use std::path::Path;

use crate::util::{self, Rng};

/// An independent implementation of paper Eq. 1–2 (written from the paper, not from
/// `tactbench::model`), used to synthesise displacements the way an outside checker does.
fn eq12(dx: f64, dy: f64, z: f64, f: [f64; 3], e: f64, s: f64) -> [f64; 2] {
    let r = (dx * dx + dy * dy + z * z).sqrt();
    let k = (1.0 + s) / (2.0 * std::f64::consts::PI * e);
    let t1 = |c: f64| (c * z / r.powi(3) - (1.0 - 2.0 * s) * c / (r * (r + z))) * f[2];
    let t2 = |fc: f64| (2.0 * (1.0 - s) * r + z) / (r * (r + z)) * fc;
    let t3 = |c: f64| {
        (2.0 * r * (s * r + z) + z * z) * c / (r.powi(3) * (r + z).powi(2))
            * (dx * f[0] + dy * f[1])
    };
    [
        k * (t1(dx) + t2(f[0]) + t3(dx)),
        k * (t1(dy) + t2(f[1]) + t3(dy)),
    ]
}

struct Case {
    layers: Vec<(&'static str, f64)>,
    noise_mm: f64,
    seed: u64,
    /// Forces to apply (N, interleaved); `None` = uniform random in ±0.1 N.
    forces: Option<Vec<f64>>,
}

/// Writes a paper-geometry sensor file (markers every 1.5 mm, 10×8 forces every 2.2 mm)
/// and a displacement CSV for random forces; returns the forces (N, interleaved).
fn write_case(dir: &Path, case: &Case) -> Vec<f64> {
    let (e_kpa, nu) = (1000.0, 0.5);
    let mut toml = format!(
        "[elastomer]\nyoung_modulus_kpa = {e_kpa}\npoisson_ratio = {nu}\nthickness_mm = 40.0\n\n"
    );
    for (name, depth) in &case.layers {
        let _ = write!(
            toml,
            "[[layers]]\nname = \"{name}\"\ncolor = \"{name}\"\ndepth_mm = {depth}\n[layers.markers]\nnx = 13\nny = 10\npitch_mm = 1.5\norigin_mm = [0.0, 0.0]\ndiameter_mm = 0.6\n\n"
        );
    }
    toml.push_str("[force_grid]\nnx = 10\nny = 8\npitch_mm = 2.2\norigin_mm = [-0.9, -0.95]\n\n[camera]\nmm_per_px = 0.05\norigin_px = [25.0, 25.0]\nwidth_px = 430\nheight_px = 340\n");
    std::fs::write(dir.join("sensor.toml"), toml).unwrap();

    let mut rng = Rng::new(case.seed);
    let forces: Vec<f64> = match &case.forces {
        Some(f) => f.clone(),
        None => (0..240).map(|_| 0.2 * (rng.uniform() - 0.5)).collect(),
    };
    let mut csv = String::from("layer,marker,x_mm,y_mm,ux_mm,uy_mm\n");
    for (name, depth) in &case.layers {
        for iy in 0..10 {
            for ix in 0..13 {
                let (x, y) = (1.5 * ix as f64, 1.5 * iy as f64);
                let mut u = [0.0; 2];
                for fy in 0..8 {
                    for fx in 0..10 {
                        let j = fy * 10 + fx;
                        let (px, py) = (-0.9 + 2.2 * fx as f64, -0.95 + 2.2 * fy as f64);
                        let d = eq12(
                            x - px,
                            y - py,
                            *depth,
                            [forces[3 * j], forces[3 * j + 1], forces[3 * j + 2]],
                            e_kpa * 1e-3,
                            nu,
                        );
                        u[0] += d[0];
                        u[1] += d[1];
                    }
                }
                u[0] += case.noise_mm * rng.normal();
                u[1] += case.noise_mm * rng.normal();
                let _ = writeln!(csv, "{name},{},{x},{y},{},{}", iy * 13 + ix, u[0], u[1]);
            }
        }
    }
    std::fs::write(dir.join("d.csv"), csv).unwrap();
    forces
}

fn read_forces(path: &Path) -> Vec<f64> {
    tactbench::formats::read_forces(path)
        .unwrap()
        .iter()
        .flat_map(|r| r.f_n)
        .collect()
}

fn rel_err(a: &[f64], b: &[f64]) -> f64 {
    let num: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| (x - y).powi(2))
        .sum::<f64>()
        .sqrt();
    let den: f64 = b.iter().map(|y| y * y).sum::<f64>().sqrt();
    num / den
}

fn reconstruct(dir: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "reconstruct",
        "--sensor",
        "sensor.toml",
        "--displacements",
        "d.csv",
        "--out",
        "f.csv",
    ];
    args.extend_from_slice(extra);
    util::run_in(dir, &args)
}

#[test]
fn reconstruct_pinv_recovers_independent_eq12_forces_to_1e_6() {
    let dir = tempfile::tempdir().unwrap();
    let truth = write_case(
        dir.path(),
        &Case {
            layers: vec![("blue", 3.0), ("red", 6.0)],
            noise_mm: 0.0,
            seed: 7,
            forces: None,
        },
    );
    let out = reconstruct(dir.path(), &["--solver", "pinv"]);
    assert!(out.status.success(), "{}", util::stderr(&out));
    let f = read_forces(&dir.path().join("f.csv"));
    let e = rel_err(&f, &truth);
    assert!(e < 1e-6, "relative force error {e:e}");
    // Every value matches individually too (not only in the norm).
    let scale = truth.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    for (a, b) in f.iter().zip(&truth) {
        assert!((a - b).abs() < 1e-6 * scale, "{a} vs {b}");
    }
}

#[test]
fn reconstruct_writes_design_columns_in_row_major_order() {
    let dir = tempfile::tempdir().unwrap();
    write_case(
        dir.path(),
        &Case {
            layers: vec![("blue", 3.0), ("red", 6.0)],
            noise_mm: 0.0,
            seed: 1,
            forces: None,
        },
    );
    let out = reconstruct(dir.path(), &[]);
    assert!(out.status.success(), "{}", util::stderr(&out));
    let text = std::fs::read_to_string(dir.path().join("f.csv")).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("ix,iy,x_mm,y_mm,fx_n,fy_n,fz_n"));
    assert!(lines.next().unwrap().starts_with("0,0,-0.9,-0.95,"));
    assert!(lines.nth(9).unwrap().starts_with("0,1,-0.9,1.25"));
    assert_eq!(text.lines().count(), 81);
}

#[test]
fn regularised_solvers_stay_finite_and_accurate_on_noisy_single_layer() {
    let dir = tempfile::tempdir().unwrap();
    let truth = write_case(
        dir.path(),
        &Case {
            layers: vec![("blue", 3.0)],
            noise_mm: 0.005,
            seed: 3,
            forces: None,
        },
    );
    let mut errors = Vec::new();
    for args in [
        &["--solver", "pinv"][..],
        &["--solver", "tikhonov", "--lambda", "gcv"],
        &["--solver", "tikhonov", "--lambda", "lcurve"],
        &["--solver", "tsvd", "--rank", "auto"],
    ] {
        let out = reconstruct(dir.path(), args);
        if args[1] == "pinv" {
            // pinv's amplified noise is past the elastomer's load bound (issue 33):
            // refused (exit 1, NaN rows) instead of written as forces.
            pinv_is_refused_past_the_load_bound(&out);
            errors.push((args[1], f64::INFINITY));
            continue;
        }
        assert!(out.status.success(), "{args:?}: {}", util::stderr(&out));
        let f = read_forces(&dir.path().join("f.csv"));
        assert!(f.iter().all(|v| v.is_finite()), "{args:?}");
        errors.push((args[1], rel_err(&f, &truth)));
    }
    eprintln!("single layer, 0.005 mm noise, relative force error: {errors:?}");
    let pinv = errors[0].1;
    for (name, e) in &errors[1..] {
        // The single-layer system is ill-conditioned: the paper's pinv amplifies 0.1 px
        // noise, the regularised solvers must do clearly better and stay within 100 %
        // of the true force field's norm.
        assert!(
            *e < pinv && *e < 1.0,
            "{name}: {e} vs pinv {pinv} ({errors:?})"
        );
    }
}

#[test]
fn regularised_solvers_recover_a_smooth_press_on_noisy_single_layer() {
    // The paper's Fig. 6 load (100 gf normal, 50 gf tangential over 4×4 nodes) seen by
    // one layer only (condition number ~1e6) with 0.1 px = 0.005 mm noise.
    let truth = util_fig6_forces();
    let dir = tempfile::tempdir().unwrap();
    write_case(
        dir.path(),
        &Case {
            layers: vec![("blue", 3.0)],
            noise_mm: 0.005,
            seed: 11,
            forces: Some(truth.clone()),
        },
    );
    let sum = |f: &[f64], a: usize| f.iter().skip(a).step_by(3).sum::<f64>();
    let mut report = Vec::new();
    for args in [
        &["--solver", "pinv"][..],
        &["--solver", "tikhonov"],
        &["--solver", "tikhonov", "--lambda", "lcurve"],
        &["--solver", "tsvd"],
    ] {
        let out = reconstruct(dir.path(), args);
        if args[1] == "pinv" {
            pinv_is_refused_past_the_load_bound(&out);
            report.push(("pinv".into(), f64::INFINITY, f64::NAN, f64::NAN));
            continue;
        }
        assert!(out.status.success(), "{args:?}: {}", util::stderr(&out));
        let f = read_forces(&dir.path().join("f.csv"));
        assert!(f.iter().all(|v| v.is_finite()), "{args:?}");
        report.push((
            args.get(1..).map(|a| a.join(" ")).unwrap_or_default(),
            rel_err(&f, &truth),
            sum(&f, 2),
            sum(&f, 1),
        ));
    }
    eprintln!(
        "fig6 load, single layer, 0.005 mm noise (method, relative error, ΣFz, ΣFy): {report:?}"
    );
    let (fz, fy) = (sum(&truth, 2), sum(&truth, 1));
    for (name, e, sz, sy) in &report[1..] {
        // Measured: pinv is off by 3000× (ΣFz = −2047 N for 0.98 N); the regularised
        // solvers keep the field within 70 % of its norm and the tangential sum within
        // 5 %. Zero-order regularisation shrinks the normal sum on one layer (ΣFz 0.59–
        // 0.74 N of 0.98 N): bounded and explained, not accurate — use two layers.
        assert!(*e < 0.7 && *e < report[0].1 / 100.0, "{name}: {e}");
        assert!((sy - fy).abs() < 0.05 * fy, "{name}: ΣFy {sy} vs {fy}");
        assert!(
            *sz > 0.5 * fz && *sz < 1.05 * fz,
            "{name}: ΣFz {sz} vs {fz}"
        );
    }
}

/// The bundled Fig. 6 forces (N, interleaved).
fn util_fig6_forces() -> Vec<f64> {
    read_forces(&util::root("experiments/examples/fig6_forces.csv"))
}

#[test]
fn lost_markers_are_dropped_and_counted() {
    let dir = tempfile::tempdir().unwrap();
    let truth = write_case(
        dir.path(),
        &Case {
            layers: vec![("blue", 3.0), ("red", 6.0)],
            noise_mm: 0.0,
            seed: 5,
            forces: None,
        },
    );
    let text = std::fs::read_to_string(dir.path().join("d.csv")).unwrap();
    let mut out = String::new();
    for (i, line) in text.lines().enumerate() {
        if i > 0 && i % 10 == 0 {
            let cols: Vec<&str> = line.split(',').collect();
            let _ = writeln!(
                out,
                "{},{},{},{},{}",
                cols[0],
                cols[1],
                cols[2],
                cols[3],
                if i % 20 == 0 {
                    ",".to_string()
                } else {
                    "NaN,NaN".into()
                }
            );
        } else {
            let _ = writeln!(out, "{line}");
        }
    }
    std::fs::write(dir.path().join("d.csv"), out).unwrap();
    let o = reconstruct(dir.path(), &[]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    assert!(
        util::stderr(&o).contains("26 of 260 markers lost"),
        "{}",
        util::stderr(&o)
    );
    let f = read_forces(&dir.path().join("f.csv"));
    assert!(rel_err(&f, &truth) < 1e-6);
}

#[test]
fn bad_displacements_get_a_clear_error_and_no_output() {
    let dir = tempfile::tempdir().unwrap();
    write_case(
        dir.path(),
        &Case {
            layers: vec![("blue", 3.0), ("red", 6.0)],
            noise_mm: 0.0,
            seed: 2,
            forces: None,
        },
    );
    let text = std::fs::read_to_string(dir.path().join("d.csv")).unwrap();
    let edited: Vec<String> = text
        .lines()
        .map(|l| {
            let mut c: Vec<&str> = l.split(',').collect();
            if c[0] == "blue" && c[1] == "5" {
                c[4] = "inf";
            }
            c.join(",")
        })
        .collect();
    std::fs::write(dir.path().join("d.csv"), edited.join("\n")).unwrap();
    let o = reconstruct(dir.path(), &[]);
    assert_eq!(o.status.code(), Some(2));
    let e = util::stderr(&o);
    assert!(
        e.contains("d.csv")
            && e.contains("line 7")
            && e.contains("ux_mm")
            && e.contains("infinite"),
        "{e}"
    );
    assert!(!dir.path().join("f.csv").exists());

    let o = util::run_in(
        dir.path(),
        &[
            "reconstruct",
            "--sensor",
            "missing.toml",
            "--displacements",
            "d.csv",
            "--out",
            "f.csv",
        ],
    );
    assert_eq!(o.status.code(), Some(2));
    assert!(
        util::stderr(&o).contains("missing.toml"),
        "{}",
        util::stderr(&o)
    );
}

#[test]
fn model_inspect_reports_conditioning_and_fourier_compatibility() {
    let o = util::run(&[
        "model",
        "inspect",
        "--sensor",
        "experiments/paper_sensor.toml",
    ]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    let s = util::stdout(&o);
    assert!(s.contains("system H     520 x 240"), "{s}");
    assert!(s.contains("condition"), "{s}");
    // The paper's 2.2 mm force pitch and 1.5 mm marker pitch share no small grid.
    assert!(s.contains("fourier      not available"), "{s}");

    let o = util::run(&[
        "model",
        "inspect",
        "--sensor",
        "experiments/paper_sensor.toml",
        "--json",
    ]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    let v: serde_json::Value = serde_json::from_str(&util::stdout(&o)).unwrap();
    assert_eq!(v["rows"], 520);
    assert_eq!(v["singular_values_mm_per_n"].as_array().unwrap().len(), 240);
    assert!(v["condition_number"].as_f64().unwrap() > 1.0);
}

#[test]
fn model_forward_then_reconstruct_round_trips_the_bundled_example() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path().join("d.csv");
    let f = dir.path().join("f.csv");
    let o = util::run(&[
        "model",
        "forward",
        "--sensor",
        "experiments/paper_sensor.toml",
        "--forces",
        "experiments/examples/fig6_forces.csv",
        "--out",
        d.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    let o = util::run(&[
        "reconstruct",
        "--sensor",
        "experiments/paper_sensor.toml",
        "--displacements",
        d.to_str().unwrap(),
        "--out",
        f.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    let truth = read_forces(&util::root("experiments/examples/fig6_forces.csv"));
    assert!(rel_err(&read_forces(&f), &truth) < 1e-8);
    // The committed example displacements are exactly what `model forward` writes.
    assert_eq!(
        std::fs::read_to_string(&d).unwrap(),
        std::fs::read_to_string(util::root("experiments/examples/fig6_displacements.csv")).unwrap()
    );
}

#[test]
fn help_explains_units_and_formats() {
    let o = util::run(&["reconstruct", "--help"]);
    let s = util::stdout(&o);
    assert!(
        s.contains("layer,marker,x_mm,y_mm,ux_mm,uy_mm")
            && s.contains("ix,iy,x_mm,y_mm,fx_n,fy_n,fz_n"),
        "{s}"
    );
    assert!(s.contains("mm/N"));
}

/// The default build has no V4L2 backend (it needs libclang at build time): a camera
/// index is refused with the way to enable it, exit 2, and no file is written.
#[cfg(not(feature = "v4l"))]
#[test]
fn camera_index_without_the_v4l_feature_says_how_to_rebuild() {
    let dir = tempfile::tempdir().unwrap();
    for args in [
        &["camera", "grab", "--device", "0", "--out", "f.png"][..],
        &["camera", "list"][..],
    ] {
        let out = util::run_in(dir.path(), args);
        let err = util::stderr(&out);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains("--features v4l"), "{args:?}: {err}");
        assert!(err.contains("libclang-dev"), "{args:?}: {err}");
    }
    assert!(!dir.path().join("f.png").exists());
}

/// pinv on a noisy single-layer frame: the amplified noise is past what the elastomer
/// can carry, so `reconstruct` names the bound and exits 1 (issue 33, item 4).
fn pinv_is_refused_past_the_load_bound(out: &std::process::Output) {
    assert_eq!(out.status.code(), Some(1), "{}", util::stderr(out));
    assert!(
        util::stderr(out).contains("past what the elastomer can carry"),
        "{}",
        util::stderr(out)
    );
}
