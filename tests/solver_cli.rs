//! Issue 12 from the command line: flags that do not apply, multi-frame files with a
//! zero or all-lost frame, `--lambda-per`, `--uncertainty`, honest `model inspect`
//! diagnostics and short messages. Files on disk, the binary, exit code and output.

use std::fmt::Write as _;
use std::path::Path;

use tactbench::model::{self, HalfSpace, MarkerSite};
use tactbench::sensor::Sensor;
use tactbench::solve::{self, Lambda, Method, Problem, SolverConfig};

use crate::util::{self, Rng};

const SENSOR: &str = "experiments/paper_sensor.toml";

fn paper() -> Sensor {
    Sensor::from_path(util::root(SENSOR)).unwrap()
}

/// Displacements (mm, interleaved, in the order of `MarkerSite::from_sensor_grids`) of
/// a smooth press centred at `c` (peak `peak` N per node, proportional shear) with
/// seeded noise of `noise_mm`.
fn press(sensor: &Sensor, c: [f64; 2], peak: f64, noise_mm: f64, seed: u64) -> Vec<f64> {
    let f: Vec<f64> = sensor
        .force_points_mm()
        .iter()
        .flat_map(|p| {
            let w = peak * (-((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2)) / 18.0).exp();
            [0.3 * w, -0.2 * w, w]
        })
        .collect();
    let sites = MarkerSite::from_sensor_grids(sensor);
    let m = HalfSpace::from_elastomer(&sensor.elastomer);
    let mut u = model::forward(&m, &sites, &sensor.force_points_mm(), &f).unwrap();
    let mut rng = Rng::new(seed);
    for v in &mut u {
        *v += noise_mm * rng.normal();
    }
    u
}

/// A displacement CSV with a `frame` column; `frames` pairs a label with the
/// displacements of every grid marker (`None` per marker = lost).
fn write_frames(path: &Path, sensor: &Sensor, frames: &[(&str, Vec<Option<[f64; 2]>>)]) {
    let mut csv = String::from("layer,marker,x_mm,y_mm,ux_mm,uy_mm,frame\n");
    for (label, u) in frames {
        let mut k = 0;
        for layer in &sensor.layers {
            let grid = layer.markers.as_ref().unwrap().grid;
            for (id, p) in grid.nodes_mm().into_iter().enumerate() {
                match u[k] {
                    Some(d) => writeln!(
                        csv,
                        "{},{id},{},{},{},{},{label}",
                        layer.name, p[0], p[1], d[0], d[1]
                    ),
                    None => writeln!(csv, "{},{id},{},{},,,{label}", layer.name, p[0], p[1]),
                }
                .unwrap();
                k += 1;
            }
        }
    }
    std::fs::write(path, csv).unwrap();
}

fn pairs(u: &[f64]) -> Vec<Option<[f64; 2]>> {
    u.chunks(2).map(|c| Some([c[0], c[1]])).collect()
}

/// Forces CSV rows as (frame label, the numeric columns after `y_mm`).
fn read_rows(path: &Path) -> (Vec<String>, Vec<(String, Vec<f64>)>) {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let header: Vec<String> = lines.next().unwrap().split(',').map(String::from).collect();
    let fcol = header.iter().position(|h| h == "frame");
    let rows = lines
        .map(|l| {
            let c: Vec<&str> = l.split(',').collect();
            let label = fcol.map(|i| c[i].to_string()).unwrap_or_default();
            let vals = c[4..]
                .iter()
                .enumerate()
                .filter(|(i, _)| Some(i + 4) != fcol)
                .map(|(_, v)| v.parse::<f64>().unwrap())
                .collect();
            (label, vals)
        })
        .collect();
    (header, rows)
}

fn run_in(dir: &Path, args: &[&str]) -> std::process::Output {
    let mut a = vec!["reconstruct", "--sensor"];
    let sensor = util::root(SENSOR);
    let sensor = sensor.to_str().unwrap().to_string();
    a.push(&sensor);
    a.extend_from_slice(&["--displacements", "d.csv", "--out", "f.csv"]);
    a.extend_from_slice(args);
    util::run_in(dir, &a)
}

/// Obs. 6 of issue 12: `--rank` with pinv, `--lambda` with tsvd, `--precision f32`
/// with fourier were silently ignored (bit-identical output). Each is an error (exit
/// 2) naming the solver and the flag, for reconstruct and model inspect.
#[test]
fn flags_that_do_not_apply_are_errors_naming_solver_and_flag() {
    let dir = tempfile::tempdir().unwrap();
    let s = paper();
    write_frames(
        &dir.path().join("d.csv"),
        &s,
        &[("a", pairs(&press(&s, [9.0, 7.0], 0.3, 0.0, 1)))],
    );
    let cases: [(&[&str], &str, &str); 7] = [
        (
            &["--solver", "tikhonov", "--refine-iterations", "5"],
            "--refine-iterations",
            "tikhonov",
        ),
        (&["--solver", "pinv", "--rank", "5"], "--rank", "pinv"),
        (
            &["--solver", "tikhonov", "--rank", "5"],
            "--rank",
            "tikhonov",
        ),
        (
            &["--solver", "tsvd", "--lambda", "0.01"],
            "--lambda",
            "tsvd",
        ),
        (&["--solver", "pinv", "--lambda", "gcv"], "--lambda", "pinv"),
        (
            &["--solver", "fourier", "--precision", "f32"],
            "--precision f32",
            "fourier",
        ),
        (
            &["--solver", "pinv", "--lambda-per", "frame"],
            "--lambda-per",
            "pinv",
        ),
    ];
    for (args, flag, solver) in cases {
        let o = run_in(dir.path(), args);
        let e = util::stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {e}");
        assert!(e.contains(flag) && e.contains(solver), "{args:?}: {e}");
        assert!(!dir.path().join("f.csv").exists(), "{args:?} wrote output");
        if !args.contains(&"--lambda-per") {
            let mut a = vec!["model", "inspect", "--sensor", SENSOR];
            a.extend_from_slice(args);
            let o = util::run(&a);
            assert_eq!(
                o.status.code(),
                Some(2),
                "inspect {args:?}: {}",
                util::stderr(&o)
            );
            assert!(util::stderr(&o).contains(flag), "{}", util::stderr(&o));
        }
    }
    // The flags that do apply still work.
    for args in [
        &["--solver", "tsvd", "--rank", "40"][..],
        &[
            "--solver",
            "tikhonov",
            "--lambda",
            "0.01",
            "--precision",
            "f32",
        ],
        &["--solver", "pinv", "--precision", "f32", "--rcond", "1e-6"],
    ] {
        let o = run_in(dir.path(), args);
        assert!(o.status.success(), "{args:?}: {}", util::stderr(&o));
    }
}

/// Obs. 5 of issue 12: a zero frame (the unloaded reference, first in the file)
/// aborted tikhonov with automatic λ (exit 2). It gives zero force, an all-lost frame
/// a flagged (NaN) row, and the loaded frames the same forces as on their own.
#[test]
fn a_zero_or_all_lost_frame_does_not_stop_a_multi_frame_file() {
    let dir = tempfile::tempdir().unwrap();
    let s = paper();
    let n = MarkerSite::from_sensor_grids(&s).len();
    let loaded = press(&s, [9.0, 7.0], 0.3, 0.005, 2);
    let loaded2 = press(&s, [12.0, 6.0], 0.2, 0.005, 3);
    write_frames(
        &dir.path().join("d.csv"),
        &s,
        &[
            ("ref", vec![Some([0.0, 0.0]); n]),
            ("lost", vec![None; n]),
            ("p1", pairs(&loaded)),
            ("p2", pairs(&loaded2)),
        ],
    );
    for solver in [
        &["--solver", "tikhonov"][..],
        &["--solver", "tsvd"],
        &["--solver", "tikhonov", "--lambda", "lcurve"],
    ] {
        for per in ["file", "frame"] {
            let mut args = solver.to_vec();
            args.extend_from_slice(&["--lambda-per", per]);
            let o = run_in(dir.path(), &args);
            let e = util::stderr(&o);
            assert!(o.status.success(), "{args:?}: {e}");
            assert!(e.contains("all 260 markers lost (frame lost)"), "{e}");
            let (_, rows) = read_rows(&dir.path().join("f.csv"));
            assert_eq!(rows.len(), 4 * 80);
            for (label, v) in &rows {
                match label.as_str() {
                    "ref" => assert!(v.iter().all(|&x| x == 0.0), "{v:?}"),
                    "lost" => assert!(v.iter().all(|x| x.is_nan()), "{v:?}"),
                    _ => assert!(v.iter().all(|x| x.is_finite()) && v.iter().any(|&x| x != 0.0)),
                }
            }
            // Per file: λ chosen on p1 (the first loaded frame) serves p2; per frame:
            // each frame on its own. Either way p1 is p1 reconstructed alone.
            let cfg = SolverConfig {
                method: if solver[1] == "tsvd" {
                    Method::Tsvd
                } else {
                    Method::Tikhonov
                },
                lambda: if solver.contains(&"lcurve") {
                    Lambda::LCurve
                } else {
                    Lambda::Gcv
                },
                ..SolverConfig::default()
            };
            let sites = MarkerSite::from_sensor_grids(&s);
            let p = Problem::new(&s, &sites);
            for (label, u, chooser) in [
                ("p1", &loaded, &loaded),
                (
                    "p2",
                    &loaded2,
                    if per == "file" { &loaded } else { &loaded2 },
                ),
            ] {
                let mut sv = solve::precompute(&p, &cfg, Some(chooser.as_slice())).unwrap();
                let mut want = vec![0.0; 240];
                sv.apply(u, &mut want).unwrap();
                let got: Vec<f64> = rows
                    .iter()
                    .filter(|r| r.0 == label)
                    .flat_map(|r| r.1.clone())
                    .collect();
                let err = got
                    .iter()
                    .zip(&want)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max);
                let scale = want.iter().map(|v| v.abs()).fold(0.0, f64::max);
                assert!(
                    err <= 1e-9 * scale,
                    "{args:?} {label}: {err:e} of {scale:e}"
                );
            }
        }
    }
    // pinv needs no choice: the zero frame is zero, the lost one flagged, exit 0.
    let o = run_in(dir.path(), &[]);
    assert!(o.status.success(), "{}", util::stderr(&o));
}

/// Deliver 6 of issue 12 from the command line: `--uncertainty --noise-px` adds
/// `sfx_n,sfy_n,sfz_n` (equal to the library's force_sd at 0.1 px = 0.005 mm) and
/// prints the SD of F_sum; without --noise-px it is an error.
#[test]
fn uncertainty_adds_sd_columns_and_the_sd_of_the_force_sum() {
    let dir = tempfile::tempdir().unwrap();
    let s = paper();
    let u = press(&s, [9.0, 7.0], 0.3, 0.005, 4);
    write_frames(&dir.path().join("d.csv"), &s, &[("a", pairs(&u))]);
    let o = run_in(
        dir.path(),
        &["--solver", "tikhonov", "--uncertainty", "--noise-px", "0.1"],
    );
    let e = util::stderr(&o);
    assert!(o.status.success(), "{e}");
    assert!(e.contains("0.1 px = 0.005 mm"), "{e}");
    let (header, rows) = read_rows(&dir.path().join("f.csv"));
    assert_eq!(
        header,
        ["ix", "iy", "x_mm", "y_mm", "fx_n", "fy_n", "fz_n", "sfx_n", "sfy_n", "sfz_n"]
    );
    let sites = MarkerSite::from_sensor_grids(&s);
    let p = Problem::new(&s, &sites);
    let cfg = SolverConfig {
        method: Method::Tikhonov,
        ..SolverConfig::default()
    };
    let sv = solve::precompute(&p, &cfg, Some(&u[..])).unwrap();
    let mut sd = vec![0.0; 240];
    sv.force_sd(0.005, &mut sd).unwrap();
    let got: Vec<f64> = rows.iter().flat_map(|r| r.1[3..6].to_vec()).collect();
    for (a, b) in got.iter().zip(&sd) {
        assert!((a - b).abs() <= 1e-11 * b, "{a} vs {b}");
    }
    let sums = solve::force_sum_sd(sv.as_ref(), 0.005).unwrap();
    let line = e.lines().find(|l| l.contains("sd of F_sum")).expect(&e);
    assert!(
        line.contains(&format!("{:.6}", sums[2])),
        "{line} vs {sums:?}"
    );

    let o = run_in(dir.path(), &["--solver", "tikhonov", "--uncertainty"]);
    assert_eq!(o.status.code(), Some(2), "{}", util::stderr(&o));
    assert!(
        util::stderr(&o).contains("--noise-px"),
        "{}",
        util::stderr(&o)
    );
}

/// Obs. 4 and 7 of issue 12: `model inspect --rcond 0.5` printed "condition inf" (κ
/// = 1.78e4), and "0.1 px (0.005000000000000001 mm)". κ is that of H whatever the
/// cut-off, JSON a number; the cut-off shows as the rank used.
#[test]
fn model_inspect_condition_is_that_of_h_whatever_rcond() {
    let base = ["model", "inspect", "--sensor", SENSOR];
    let text = |extra: &[&str]| {
        let mut a = base.to_vec();
        a.extend_from_slice(extra);
        let o = util::run(&a);
        assert!(o.status.success(), "{}", util::stderr(&o));
        util::stdout(&o)
    };
    let cond = |s: &str| -> String {
        s.lines()
            .find(|l| l.starts_with("condition"))
            .unwrap()
            .to_string()
    };
    let full = text(&[]);
    let cut = text(&["--rcond", "0.5"]);
    assert!(!cut.contains("inf"), "{cut}");
    assert_eq!(cond(&full), cond(&cut));
    assert!(full.contains("0.1 px (0.005 mm)"), "{full}");
    assert!(cut.contains("rank used"), "{cut}");
    let json = |extra: &[&str]| -> serde_json::Value {
        let mut a = base.to_vec();
        a.push("--json");
        a.extend_from_slice(extra);
        serde_json::from_str(&util::stdout(&util::run(&a))).unwrap()
    };
    let (j0, j1) = (json(&[]), json(&["--rcond", "0.5"]));
    let k = j1["condition_number"].as_f64().expect("a number, not null");
    assert_eq!(Some(k), j0["condition_number"].as_f64());
    let sv = j0["singular_values_mm_per_n"].as_array().unwrap();
    let want = sv[0].as_f64().unwrap() / sv.last().unwrap().as_f64().unwrap();
    assert!((k - want).abs() <= 1e-12 * want);
    assert!(j1["rank"].as_u64().unwrap() < j0["rank"].as_u64().unwrap());
}

/// Obs. 7 of issue 12: a 1e306 mm displacement was refused with a 710-character
/// number.
#[test]
fn a_huge_displacement_is_refused_with_a_short_number() {
    let dir = tempfile::tempdir().unwrap();
    let s = paper();
    let mut u = pairs(&press(&s, [9.0, 7.0], 0.3, 0.0, 5));
    u[7] = Some([1e306, 0.0]);
    write_frames(&dir.path().join("d.csv"), &s, &[("a", u)]);
    let o = run_in(dir.path(), &[]);
    let e = util::stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(e.contains("1.000e306"), "{e}");
    let longest_number = e
        .split(|c: char| !c.is_ascii_digit())
        .map(str::len)
        .max()
        .unwrap_or(0);
    assert!(longest_number < 12, "{e}");
}

/// The Fourier solver's accuracy is the user's choice against time:
/// `--coarse-correction off --refine-iterations 0` is the direct per-frequency solve,
/// the default adds the two-level correction (on this small grid its coarse space is the
/// whole force grid, so it is dense Tikhonov exactly), and refinement iterations approach
/// dense Tikhonov at the same λ from either start; the choice changes the output (it was
/// not selectable from the command line at all). Geometry of issue 12, observation 1 at
/// 12×12: force grid and both marker layers at 1.1 mm, the deeper layer offset by half a
/// pitch.
#[test]
fn fourier_refinement_is_selectable_and_converges_to_dense_tikhonov() {
    let dir = tempfile::tempdir().unwrap();
    let text = grid_sensor_toml();
    let sensor_path = dir.path().join("grid.toml");
    std::fs::write(&sensor_path, &text).unwrap();
    let s = Sensor::from_path(&sensor_path).unwrap();
    assert_eq!(s.force_grid.len(), 144, "the grid sensor was not rewritten");
    write_frames(
        &dir.path().join("d.csv"),
        &s,
        &[("a", pairs(&press(&s, [6.0, 6.0], 0.05, 0.0, 1)))],
    );
    let sensor_arg = sensor_path.to_str().unwrap().to_string();
    let forces = |args: &[&str]| {
        let mut a = vec![
            "reconstruct",
            "--sensor",
            &sensor_arg,
            "--displacements",
            "d.csv",
            "--out",
            "f.csv",
            // 1e-2 σ₁ (σ₁ = 8.65 mm/N), as in issue 12's observation 1.
            "--lambda",
            "0.0865",
        ];
        a.extend_from_slice(args);
        let o = util::run_in(dir.path(), &a);
        (o.status.code(), util::stderr(&o), {
            let (_, rows) = if o.status.success() {
                read_rows(&dir.path().join("f.csv"))
            } else {
                (Vec::new(), Vec::new())
            };
            rows.into_iter()
                .flat_map(|(_, v)| v.into_iter().take(3))
                .collect::<Vec<f64>>()
        })
    };
    let ok = |args: &[&str]| {
        let (code, err, f) = forces(args);
        assert_eq!(code, Some(0), "{args:?}: {err}");
        f
    };
    let dense = ok(&["--solver", "tikhonov"]);
    let err = |f: &[f64]| {
        let num: f64 = f.iter().zip(&dense).map(|(a, b)| (a - b).powi(2)).sum();
        let den: f64 = dense.iter().map(|b| b * b).sum();
        (num / den).sqrt()
    };
    // From the direct solve: `--refine-iterations` is the cap; `--refine-tolerance 0`
    // runs all of them.
    let direct = |n: &str, tol: &str| {
        err(&ok(&[
            "--solver",
            "fourier",
            "--coarse-correction",
            "off",
            "--refine-iterations",
            n,
            "--refine-tolerance",
            tol,
        ]))
    };
    let e0 = err(&ok(&["--solver", "fourier", "--coarse-correction", "off"]));
    let (e20, e80) = (direct("20", "0"), direct("80", "0"));
    let e_default = err(&ok(&["--solver", "fourier"]));
    let (e_tight, e_loose) = (direct("50", "0.02"), direct("50", "0.3"));
    let e_two_level_refined = err(&ok(&["--solver", "fourier", "--refine-iterations", "5"]));
    eprintln!(
        "field error against dense tikhonov: direct {e0:.3e}, 20 iterations {e20:.3e}, 80 \
         iterations {e80:.3e}, tolerance 0.02 {e_tight:.3e}, tolerance 0.3 {e_loose:.3e}; \
         two-level (default) {e_default:.3e}, two-level + 5 iterations {e_two_level_refined:.3e}"
    );
    assert!(e20 < e0 && e80 < e20, "errors {e0:e} {e20:e} {e80:e}");
    assert!(
        e0 > 1e-2,
        "the direct solve carries its boundary error: {e0:e}"
    );
    assert!(e80 < 1e-4, "80 iterations: {e80:e}");
    assert!(e_tight < 0.05, "tolerance 0.02: {e_tight:e}");
    assert!(
        e_loose > e_tight,
        "tolerance 0.3 {e_loose:e} vs 0.02 {e_tight:e}"
    );
    assert!(e_default < 1e-6, "two-level on a 12×12 grid: {e_default:e}");
    assert!(e_two_level_refined < 1e-6, "{e_two_level_refined:e}");
    let (code, e, _) = forces(&["--solver", "fourier", "--refine-tolerance", "0.1"]);
    assert_eq!(code, Some(2), "{e}");
    assert!(
        e.contains("--refine-tolerance") && e.contains("--refine-iterations"),
        "{e}"
    );
    let (code, e, _) = forces(&["--solver", "tikhonov", "--coarse-correction", "off"]);
    assert_eq!(code, Some(2), "{e}");
    assert!(
        e.contains("--coarse-correction") && e.contains("tikhonov"),
        "{e}"
    );
    let (code, e, _) = forces(&["--solver", "fourier", "--coarse-correction", "maybe"]);
    assert_eq!(code, Some(2), "{e}");
    assert!(e.contains("on or off"), "{e}");
    let (code, e, _) = forces(&["--solver", "tikhonov", "--refine-tolerance", "0.1"]);
    assert_eq!(code, Some(2), "{e}");
    assert!(
        e.contains("--refine-tolerance") && e.contains("tikhonov"),
        "{e}"
    );
    let (code, e, _) = forces(&[
        "--solver",
        "fourier",
        "--refine-iterations",
        "5",
        "--refine-tolerance",
        "1.5",
    ]);
    assert_eq!(code, Some(2), "{e}");
    assert!(e.contains("tolerance"), "{e}");
    let (code, e, _) = forces(&["--solver", "fourier", "--refine-iterations", "100000"]);
    assert_eq!(code, Some(2), "{e}");
    assert!(e.contains("1000"), "{e}");
}

/// The paper sensor file rewritten to issue 12's observation-1 geometry at 12×12: force
/// grid and both marker layers every 1.1 mm, the deeper layer offset by half a pitch
/// (a geometry the fourier solver handles).
fn grid_sensor_toml() -> String {
    std::fs::read_to_string(util::root(SENSOR))
        .unwrap()
        .replace(
            "nx = 13\nny = 10\npitch_mm = 1.5",
            "nx = 12\nny = 12\npitch_mm = 1.1",
        )
        .replace("origin_mm = [0.75, 0.75]", "origin_mm = [0.55, 0.55]")
        .replace(
            "nx = 10\nny = 8\npitch_mm = 2.2\norigin_mm = [-0.9, -0.95]",
            "nx = 12\nny = 12\npitch_mm = 1.1\norigin_mm = [0.0, 0.0]",
        )
}

/// The fourier solver's automatic λ (GCV and L-curve on the periodic problem) must
/// not change when the displacements are scaled by 1e-160 or 1e300 (its sums of
/// squares under- or overflowed, as the dense solvers' did), and a search that ends
/// on the boundary of its range is a warning, never "nearly noise-free".
#[test]
fn fourier_automatic_lambda_is_the_same_at_1e_minus_160_and_1e300_scalings() {
    let s = Sensor::from_toml_str(&grid_sensor_toml(), Path::new("grid.toml")).unwrap();
    let u = press(&s, [6.0, 6.0], 0.05, 2e-4, 9);
    let sites = MarkerSite::from_sensor_grids(&s);
    let problem = Problem::new(&s, &sites);
    for lambda in [Lambda::Gcv, Lambda::LCurve] {
        let cfg = SolverConfig {
            method: Method::Fourier,
            lambda,
            ..SolverConfig::default()
        };
        let l0 = solve::precompute(&problem, &cfg, Some(&u))
            .unwrap()
            .diagnostics()
            .lambda
            .unwrap();
        for scale in [1e-160, 1e300] {
            let scaled: Vec<f64> = u.iter().map(|v| v * scale).collect();
            let solver = solve::precompute(&problem, &cfg, Some(&scaled)).unwrap();
            let d = solver.diagnostics();
            let l = d.lambda.unwrap();
            assert!(
                ((l - l0) / l0).abs() < 1e-6,
                "{lambda:?} ×{scale:e}: λ = {l:e} vs {l0:e} unscaled: {:?}",
                d.notes
            );
            assert!(d.warnings().next().is_none(), "{:?}", d.notes);
            assert!(
                !d.notes.iter().any(|n| n.contains("noise-free")),
                "{:?}",
                d.notes
            );
        }
    }
}
