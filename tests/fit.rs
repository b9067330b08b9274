//! `tactbench fit` from outside: a short calibration run on the simulated bench (the
//! paper's sensor, the camera noise of Fig. 7's noisy scene, a DynPick F/T), fitted;
//! the outputs' contracts (fit.json shape, fitted.toml loading in `track`, fit.html);
//! the verdicts on runs that cannot determine a parameter; bad input; `--predict`.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use tactbench::sensor::Sensor;

use crate::util::{arg, eight_setpoint_fig7_plan, json, root, run, stderr, stdout};

/// A 12-setpoint calibration plan: normal loads of 0.5, 1.5 and 3 N at three
/// positions, and 0.5 N of shear along ±x and ±y under 2 N at the centre.
fn calibration_plan(dir: &Path) -> PathBuf {
    let sensor = root("experiments/paper_sensor.toml");
    let mut text = format!(
        "name = \"fit-test\"\nsensor = {:?}\nforce_unit = \"N\"\n\n[indenter]\nshape = \"hemisphere\"\ndiameter_mm = 5.0\n\n\
         [approach]\nposition_mm = [9.0, 6.75]\nspeed_mm_s = 2.0\ncontact_force = 0.05\n\n\
         [control]\nforce_tolerance = 0.03\nmax_steps = 40\n\n[settle]\nwindow_s = 0.2\nmax_sd = 0.02\ntimeout_s = 3.0\n\n\
         [acquire]\nsamples = 20\nframes = 2\n\n\
         [safety]\nmax_force = [3.0, 3.0, 6.0]\ntravel_min_mm = [0.0, 0.0, -5.0]\ntravel_max_mm = [18.0, 13.5, 2.5]\nmax_speed_mm_s = 5.0\n\n\
         [sweep]\nkind = \"setpoints\"\n",
        sensor.display().to_string()
    );
    for pos in ["[9.0, 6.75]", "[5.0, 4.0]", "[13.0, 9.5]"] {
        for n in [0.5, 1.5, 3.0] {
            text.push_str(&format!(
                "\n[[sweep.points]]\nposition_mm = {pos}\nnormal = {n}\n"
            ));
        }
    }
    for t in ["[0.5, 0.0]", "[0.0, 0.5]", "[-0.5, 0.0]"] {
        text.push_str(&format!(
            "\n[[sweep.points]]\nposition_mm = [9.0, 6.75]\nnormal = 2.0\ntangential = {t}\n"
        ));
    }
    let p = dir.join("calibration.toml");
    std::fs::write(&p, text).unwrap();
    p
}

/// The calibration run, made once for every test here.
fn calibration_run() -> &'static Path {
    static RUN: OnceLock<PathBuf> = OnceLock::new();
    RUN.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap().keep();
        let plan = calibration_plan(&dir);
        let out = dir.join("run");
        let o = run(&[
            "run",
            arg(&plan),
            "--sim",
            arg(&root(
                "experiments/scenes/fig7_hemisphere_camera_noise.toml",
            )),
            "--out",
            arg(&out),
            "--no-progress",
        ]);
        assert!(o.status.success(), "run --sim: {}", stderr(&o));
        out
    })
}

fn fit(run_dir: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    let fitted = out.join("fitted.toml");
    let j = out.join("fit.json");
    let mut args = vec![
        "fit",
        arg(run_dir),
        "--out",
        arg(&fitted),
        "--json",
        arg(&j),
    ];
    args.extend_from_slice(extra);
    run(&args)
}

#[test]
fn fit_json_has_the_issue_shape_and_the_nominal_gel_lies_in_its_intervals() {
    let tmp = tempfile::tempdir().unwrap();
    let o = fit(calibration_run(), tmp.path(), &[]);
    assert!(o.status.success(), "fit: {}", stderr(&o));
    let doc = json(&tmp.path().join("fit.json"));
    let params = doc["parameters"].as_object().unwrap();
    let mut names: Vec<&str> = params.keys().map(|k| k.as_str()).collect();
    names.sort_unstable();
    assert_eq!(
        names,
        [
            "contact_offset_x_mm",
            "contact_offset_y_mm",
            "contact_z_mm",
            "depth_mm.blue",
            "depth_mm.red",
            "ft_rotation_deg",
            "mm_per_px",
            "poisson_ratio",
            "thickness_mm",
            "young_modulus_kpa"
        ]
    );
    for (name, p) in params {
        for key in ["value", "ci95", "unit", "identifiable", "route"] {
            assert!(p.get(key).is_some(), "{name} lacks {key}: {p}");
        }
        let route = p["route"].as_str().unwrap();
        assert!(
            ["indentation", "displacement", "both"].contains(&route),
            "{name}: {route}"
        );
    }
    // The half-space has no thickness: not identifiable, no interval, nominal value.
    let h = &params["thickness_mm"];
    assert_eq!(h["identifiable"], false);
    assert!(h["ci95"].is_null());
    assert_eq!(h["value"], 40.0);
    // E from both routes; the contact z from the indentation route alone.
    assert_eq!(params["young_modulus_kpa"]["route"], "both");
    assert_eq!(params["contact_z_mm"]["route"], "indentation");
    // The simulated gel is the nominal one: its E and depths lie in their intervals.
    for (name, truth) in [
        ("young_modulus_kpa", 1000.0),
        ("depth_mm.blue", 3.0),
        ("depth_mm.red", 6.0),
    ] {
        let p = &params[name];
        assert_eq!(p["identifiable"], true, "{name}: {p}");
        let ci = p["ci95"].as_array().unwrap();
        let (lo, hi) = (ci[0].as_f64().unwrap(), ci[1].as_f64().unwrap());
        assert!(
            lo <= truth && truth <= hi,
            "{name}: {truth} outside [{lo}, {hi}]"
        );
        // And the interval is informative: narrower than ±10 % of the value.
        assert!(hi - lo < 0.2 * truth, "{name}: [{lo}, {hi}]");
    }
    for key in ["routes", "residual_rms_px", "cross_validation"] {
        assert!(doc.get(key).is_some(), "fit.json lacks {key}");
    }
    assert!(doc["routes"]["indentation"]["parameters"]["young_modulus_kpa"].is_object());
    assert!(doc["routes"]["displacement"]["parameters"]["young_modulus_kpa"].is_object());
    assert!(doc["residual_rms_px"]["blue"].as_f64().unwrap() > 0.0);
    assert!(doc["cross_validation"]["rms_error_n"]["fitted"].is_number());
    // The page is written beside fitted.toml and is self-contained.
    let html = std::fs::read_to_string(tmp.path().join("fit.html")).unwrap();
    assert!(html.contains("young_modulus_kpa") && !html.contains("src=\"http"));
}

#[test]
fn the_fitted_sensor_file_loads_in_track_unedited_and_names_its_run() {
    let tmp = tempfile::tempdir().unwrap();
    let o = fit(calibration_run(), tmp.path(), &[]);
    assert!(o.status.success(), "fit: {}", stderr(&o));
    let fitted = tmp.path().join("fitted.toml");
    let text = std::fs::read_to_string(&fitted).unwrap();
    assert!(text.contains("# fitted: 95 % CI ["), "{text}");
    assert!(text.contains(arg(calibration_run())), "{text}");
    let s = Sensor::from_path(&fitted).unwrap();
    let doc = json(&tmp.path().join("fit.json"));
    let e = doc["parameters"]["young_modulus_kpa"]["value"]
        .as_f64()
        .unwrap();
    assert!((s.elastomer.young_modulus_kpa - e).abs() < 1e-6 * e);
    let frames = calibration_run().join("frames");
    let out = tmp.path().join("tracked.csv");
    let o = run(&[
        "track",
        "--sensor",
        arg(&fitted),
        "--reference",
        arg(&frames.join("reference.png")),
        "--out",
        arg(&out),
        arg(&frames.join("00002_0.png")),
    ]);
    assert!(o.status.success(), "track with fitted.toml: {}", stderr(&o));
}

#[test]
fn a_run_without_shear_or_positions_reports_what_it_cannot_determine() {
    let tmp = tempfile::tempdir().unwrap();
    let plan = eight_setpoint_fig7_plan(tmp.path(), "fig7.toml");
    let r = tmp.path().join("run");
    let o = run(&[
        "run",
        arg(&plan),
        "--sim",
        arg(&root(
            "experiments/scenes/fig7_hemisphere_camera_noise.toml",
        )),
        "--out",
        arg(&r),
        "--no-progress",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = fit(&r, tmp.path(), &[]);
    assert!(o.status.success(), "fit: {}", stderr(&o));
    let doc = json(&tmp.path().join("fit.json"));
    let rot = &doc["parameters"]["ft_rotation_deg"];
    assert_eq!(rot["identifiable"], false, "{rot}");
    assert!(rot["ci95"].is_null());
    assert_eq!(rot["value"], 0.0, "held at nominal");
    assert!(
        rot["reason"].as_str().unwrap().contains("shear setpoints"),
        "{rot}"
    );
    assert!(stdout(&o).contains("NOT IDENTIFIABLE"), "{}", stdout(&o));
}

#[test]
fn bad_input_is_refused_naming_what_is_wrong() {
    let tmp = tempfile::tempdir().unwrap();
    let r = calibration_run();
    // An unknown parameter name.
    let o = fit(r, tmp.path(), &["--params", "young_modulus_kpa,stiffness"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("\"stiffness\""), "{}", stderr(&o));
    // Not a run directory.
    let o = fit(tmp.path(), tmp.path(), &[]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("not a run directory"), "{}", stderr(&o));
    // A sensor file whose layers are not the run's.
    let one = tmp.path().join("one_layer.toml");
    let text = std::fs::read_to_string(root("experiments/paper_sensor.toml")).unwrap();
    let cut = text
        .split("[[layers]]\nname = \"red\"")
        .next()
        .unwrap()
        .to_string()
        + &text[text.find("[force_grid]").unwrap()..];
    std::fs::write(&one, cut).unwrap();
    let o = fit(r, tmp.path(), &["--sensor", arg(&one)]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("do not match the run"),
        "{}",
        stderr(&o)
    );
    // A run whose displacements are gone.
    let copy = tmp.path().join("bare");
    copy_dir(r, &copy);
    std::fs::remove_dir_all(copy.join("displacements")).unwrap();
    let o = fit(&copy, tmp.path(), &[]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("displacements"), "{}", stderr(&o));
}

#[test]
fn a_run_without_ft_readings_or_with_one_setpoint_gets_an_error_not_a_number() {
    let tmp = tempfile::tempdir().unwrap();
    let r = calibration_run();
    let copy = tmp.path().join("noft");
    copy_dir(r, &copy);
    let journal = std::fs::read_to_string(copy.join("journal.csv")).unwrap();
    let mut lines = journal.lines();
    let head = lines.next().unwrap();
    let cols: Vec<&str> = head.split(',').collect();
    let idx: Vec<usize> = ["fx_n", "fy_n", "fz_n"]
        .iter()
        .map(|c| cols.iter().position(|x| x == c).unwrap())
        .collect();
    let mut out = vec![head.to_string()];
    for l in lines {
        let mut f: Vec<String> = l.split(',').map(String::from).collect();
        for i in &idx {
            f[*i] = "0".into();
        }
        out.push(f.join(","));
    }
    std::fs::write(copy.join("journal.csv"), out.join("\n") + "\n").unwrap();
    let o = fit(&copy, tmp.path(), &[]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("no F/T reading"), "{}", stderr(&o));
    assert!(!tmp.path().join("fitted.toml").exists());

    let one = tmp.path().join("one");
    copy_dir(r, &one);
    let journal = std::fs::read_to_string(one.join("journal.csv")).unwrap();
    let two: Vec<&str> = journal.lines().take(2).collect();
    std::fs::write(one.join("journal.csv"), two.join("\n") + "\n").unwrap();
    let o = fit(&one, tmp.path(), &[]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("1 measured setpoint"), "{}", stderr(&o));
}

#[test]
fn predict_gives_each_parameter_an_expected_interval_and_the_bench_time() {
    let tmp = tempfile::tempdir().unwrap();
    let plan = calibration_plan(tmp.path());
    let j = tmp.path().join("predict.json");
    let o = run(&[
        "fit",
        "--predict",
        "--plan",
        arg(&plan),
        "--sensor",
        arg(&root("experiments/paper_sensor.toml")),
        "--json",
        arg(&j),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("estimated bench time"),
        "{}",
        stdout(&o)
    );
    let p = json(&j);
    for name in [
        "young_modulus_kpa",
        "depth_mm.red",
        "ft_rotation_deg",
        "contact_z_mm",
    ] {
        let e = &p["parameters"][name];
        assert_eq!(e["identifiable"], true, "{name}: {e}");
        assert!(e["ci95_half_width"].as_f64().unwrap() > 0.0, "{name}: {e}");
    }
    // Without shear the rotation cannot be determined, and predict says so.
    let fig7 = eight_setpoint_fig7_plan(tmp.path(), "fig7.toml");
    let o = run(&[
        "fit",
        "--predict",
        "--plan",
        arg(&fig7),
        "--sensor",
        arg(&root("experiments/paper_sensor.toml")),
        "--json",
        arg(&j),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let p = json(&j);
    assert_eq!(p["parameters"]["ft_rotation_deg"]["identifiable"], false);
    assert!(p["parameters"]["ft_rotation_deg"]["needs"]
        .as_str()
        .unwrap()
        .contains("shear"));
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let t = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &t);
        } else {
            std::fs::copy(e.path(), &t).unwrap();
        }
    }
}

#[test]
fn a_fit_written_into_the_run_is_judged_by_report_acceptance() {
    let tmp = tempfile::tempdir().unwrap();
    let r = tmp.path().join("run");
    copy_dir(calibration_run(), &r);
    let o = run(&[
        "fit",
        arg(&r),
        "--out",
        arg(&tmp.path().join("fitted.toml")),
        "--json",
        arg(&r.join("fit.json")),
    ]);
    assert!(o.status.success(), "fit: {}", stderr(&o));
    let crit = tmp.path().join("build.toml");
    std::fs::write(
        &crit,
        "[[criterion]]\nmetric = \"fit.young_modulus_kpa\"\nmax_relative_to_nominal = 0.10\n\
         [[criterion]]\nmetric = \"fit.depth_mm.red\"\nmax_deviation_from_nominal = 0.3\n",
    )
    .unwrap();
    let o = run(&["report", arg(&r), "--acceptance", arg(&crit)]);
    // The simulated gel is the nominal one: both criteria pass, with their intervals.
    assert_eq!(o.status.code(), Some(0), "{}{}", stdout(&o), stderr(&o));
    let text = stdout(&o);
    assert!(text.contains("PASS fit.young_modulus_kpa"), "{text}");
    assert!(text.contains("PASS fit.depth_mm.red"), "{text}");
    let v = json(&r.join("verdict.json"));
    assert_eq!(v["outcome"], "PASS");
    assert!(v["criteria"][0]["ci95"]["method"]
        .as_str()
        .unwrap()
        .contains("jacobian"));
}
