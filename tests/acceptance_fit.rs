//! Acceptance on fitted parameters (issue 30 part 6): `tactbench report RUN_DIR
//! --acceptance A.toml` judges `fit.<NAME>` criteria from RUN_DIR/fit.json (or
//! `--fit FILE`) with the PASS / MARGINAL (the 95 % interval straddles a limit) /
//! FAIL / NOT JUDGED rules, shows them in verdict.json, summary.csv and report.html,
//! never PASSes a build on a criterion nothing judged, and `tactbench compare` trends
//! the fitted parameters across builds in compare.csv / compare.html.
//!
//! The fit.json files are written here as JSON (the contract of `fit::doc`), not
//! through the library's types.

use std::path::Path;

use serde_json::{json, Value};

use super::report::{report, verdict_json, write_displacements, write_forces, write_run};
use crate::util::{run, stderr, stdout, write};

const MAGNITUDE: &str =
    "[sweep]\nkind = \"magnitude\"\nfrom = 0.0\nto = 300.0\nstep = 100.0\ntrials = 3\n";

/// A magnitude run whose F^sum is 0.95 F/T + `offset` N, with small per-trial errors.
fn build_run(dir: &Path, offset: f64) {
    std::fs::create_dir_all(dir).unwrap();
    write_run(dir, MAGNITUDE, |dir, r| {
        r.fz_n = r.target_normal_n;
        r.fsum_z_n = 0.95 * r.fz_n + offset + [0.02, -0.02, 0.0][r.trial];
        let a = r.fz_n;
        write_displacements(dir, r.index, |_, _, _| [0.001 * a, 0.0]);
        write_forces(dir, r.index, |_| 0.01 * a);
    });
}

fn fitted(value: f64, ci: [f64; 2], nominal: f64, unit: &str) -> Value {
    json!({"value": value, "ci95": ci, "unit": unit, "identifiable": true, "route": "both",
           "nominal": nominal, "sd": (ci[1] - ci[0]) / 3.92, "fitted": true, "reason": null})
}

/// fit.json with E (nominal 100 kPa), the blue layer's depth (nominal 3 mm) and a
/// thickness the run could not determine.
fn fit_json(e: f64, e_ci: [f64; 2], depth: f64, depth_ci: [f64; 2]) -> String {
    json!({
        "schema": "tactbench-fit/1",
        "run": "runs/b",
        "sensor": "experiments/paper_sensor.toml",
        "parameters": {
            "young_modulus_kpa": fitted(e, e_ci, 100.0, "kPa"),
            "depth_mm.blue": fitted(depth, depth_ci, 3.0, "mm"),
            "thickness_mm": {"value": 40.0, "ci95": null, "unit": "mm", "identifiable": false,
                "route": "displacement", "nominal": 40.0, "sd": null, "fitted": true,
                "reason": "a 40 mm gel's field does not depend on its thickness"}
        },
        "routes": {"agree": true},
        "residual_rms_px": {"blue": 0.06},
        "cross_validation": null,
        "ci_method": "jacobian"
    })
    .to_string()
}

const CRITERIA: &str = "[[criterion]]\nmetric = \"magnitude.r2\"\nmin = 0.9\n\
     [[criterion]]\nmetric = \"fit.young_modulus_kpa\"\nmax_relative_to_nominal = 0.10\n\
     [[criterion]]\nmetric = \"fit.depth_mm.blue\"\nmax_deviation_from_nominal = 0.3\n";

#[test]
fn fitted_parameters_are_judged_from_fit_json_with_their_interval() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("run");
    build_run(&dir, 0.01);
    // E 104 kPa, 95 % CI [98, 111]: inside ±10 % of 100, the interval straddles 110.
    write(
        &dir,
        "fit.json",
        &fit_json(104.0, [98.0, 111.0], 3.2, [3.1, 3.25]),
    );
    let crit = write(tmp.path(), "a.toml", CRITERIA);
    let out = report(&dir, &["--acceptance", crit.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let text = stdout(&out);
    assert!(
        text.contains(
            "MARGINAL fit.young_modulus_kpa = 104 kPa, 95 % CI [98, 111] kPa (within ±10 % of \
             nominal; nominal 100 kPa: in [90, 110] kPa)"
        ),
        "{text}"
    );
    assert!(text.contains("PASS fit.depth_mm.blue = 3.2 mm"), "{text}");
    let v = verdict_json(&dir);
    assert_eq!(v["outcome"], "MARGINAL");
    let c = &v["criteria"][1];
    assert_eq!(c["metric"], "fit.young_modulus_kpa");
    assert_eq!(c["outcome"], "MARGINAL");
    assert_eq!(
        (c["value"].as_f64(), c["unit"].as_str()),
        (Some(104.0), Some("kPa"))
    );
    assert_eq!(c["nominal"], 100.0);
    assert_eq!(c["max_relative_to_nominal"], 0.1);
    assert_eq!(c["limits"], json!([90.0, 110.0]));
    assert_eq!(
        c["ci95"],
        json!({"low": 98.0, "high": 111.0, "method": "jacobian"})
    );
    assert_eq!(v["criteria"][2]["outcome"], "PASS");
    // The fitted (identifiable) parameters join the run's metrics; the held one not.
    let summary = std::fs::read_to_string(dir.join("summary.csv")).unwrap();
    assert!(
        summary.contains("fit.young_modulus_kpa,104,kPa,98,111,jacobian"),
        "{summary}"
    );
    assert!(!summary.contains("fit.thickness_mm"), "{summary}");
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    assert!(
        html.contains("104 <small>(95 % CI [98, 111])</small>")
            && html.contains("within ±10 % of nominal (nominal 100: [90, 110])"),
        "the acceptance table shows the interval and the limits"
    );

    // Outside the limits: FAIL (exit 1), through --fit from elsewhere.
    let other = write(
        tmp.path(),
        "elsewhere.json",
        &fit_json(113.0, [110.5, 115.5], 3.2, [3.1, 3.25]),
    );
    let out = report(
        &dir,
        &[
            "--acceptance",
            crit.to_str().unwrap(),
            "--fit",
            other.to_str().unwrap(),
        ],
    );
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    assert_eq!(verdict_json(&dir)["criteria"][1]["outcome"], "FAIL");
}

/// Regression: a criterion nothing could judge (no fit.json; a parameter the run
/// cannot determine) must never let the build PASS.
#[test]
fn a_criterion_nothing_judged_keeps_the_verdict_not_judged_never_pass() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("run");
    build_run(&dir, 0.01);
    let crit = write(tmp.path(), "a.toml", CRITERIA);
    // No fit.json: the two fit criteria are NOT JUDGED, r2 PASSes.
    let out = report(&dir, &["--acceptance", crit.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let v = verdict_json(&dir);
    assert_eq!(v["outcome"], "NOT JUDGED", "{v}");
    assert_eq!(v["criteria"][0]["outcome"], "PASS");
    let note = v["criteria"][1]["note"].as_str().unwrap();
    assert!(
        note.contains("fit.json does not exist") && note.contains("tactbench fit"),
        "{note}"
    );
    assert!(
        v["summary"]
            .as_str()
            .unwrap()
            .starts_with("NOT JUDGED: 2 of 3 criteria not judged"),
        "{}",
        v["summary"]
    );
    assert!(stdout(&out).contains("acceptance: NOT JUDGED (2 of 3 criteria not judged)"));

    // A parameter the fit could not determine: NOT JUDGED with its reason, the others
    // PASS; the whole still NOT JUDGED.
    write(
        &dir,
        "fit.json",
        &fit_json(101.0, [99.0, 103.0], 3.1, [3.0, 3.2]),
    );
    let crit = write(
        tmp.path(),
        "b.toml",
        &format!("{CRITERIA}[[criterion]]\nmetric = \"fit.thickness_mm\"\nmax_deviation_from_nominal = 1.0\n"),
    );
    let out = report(&dir, &["--acceptance", crit.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let v = verdict_json(&dir);
    assert_eq!(v["outcome"], "NOT JUDGED");
    let outcomes: Vec<&str> = v["criteria"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["outcome"].as_str().unwrap())
        .collect();
    assert_eq!(outcomes, ["PASS", "PASS", "PASS", "NOT JUDGED"]);
    assert!(v["criteria"][3]["note"].as_str().unwrap().contains(
        "not identifiable from this run: a 40 mm gel's field does not depend on its thickness"
    ));
    // A FAIL still fails the build.
    write(
        &dir,
        "fit.json",
        &fit_json(80.0, [78.0, 82.0], 3.1, [3.0, 3.2]),
    );
    let out = report(&dir, &["--acceptance", crit.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    assert_eq!(verdict_json(&dir)["outcome"], "FAIL");
}

#[test]
fn bad_fit_files_and_criteria_are_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("run");
    build_run(&dir, 0.01);
    let crit = write(tmp.path(), "a.toml", CRITERIA);
    let a = crit.to_str().unwrap();
    let missing = tmp.path().join("nope.json");
    let out = report(
        &dir,
        &["--acceptance", a, "--fit", missing.to_str().unwrap()],
    );
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr(&out).contains("nope.json: cannot read the fit"),
        "{}",
        stderr(&out)
    );
    // A unit that is not the parameter's.
    let bad = fit_json(104.0, [98.0, 111.0], 3.2, [3.1, 3.25]).replace("\"kPa\"", "\"Pa\"");
    write(&dir, "fit.json", &bad);
    let out = report(&dir, &["--acceptance", a]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr(&out).contains("fit.json: parameters.young_modulus_kpa.unit = \"Pa\""),
        "{}",
        stderr(&out)
    );
    // A layer the fit does not have.
    write(
        &dir,
        "fit.json",
        &fit_json(104.0, [98.0, 111.0], 3.2, [3.1, 3.25]),
    );
    let red = write(
        tmp.path(),
        "red.toml",
        "[[criterion]]\nmetric = \"fit.depth_mm.red\"\nmax = 7\n",
    );
    let out = report(&dir, &["--acceptance", red.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(2));
    let e = stderr(&out);
    assert!(
        e.contains("no parameter `depth_mm.red`") && e.contains("depth_mm.blue"),
        "{e}"
    );
    // Nominal bounds on a run metric.
    let wrong = write(
        tmp.path(),
        "w.toml",
        "[[criterion]]\nmetric = \"magnitude.slope\"\nmax_relative_to_nominal = 0.1\n",
    );
    let out = report(&dir, &["--acceptance", wrong.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr(&out).contains("applies to fitted parameters only"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn compare_trends_fitted_parameters_across_builds() {
    let tmp = tempfile::tempdir().unwrap();
    let (b1, b2, b3) = (
        tmp.path().join("b1"),
        tmp.path().join("b2"),
        tmp.path().join("b3"),
    );
    build_run(&b1, 0.01);
    build_run(&b2, 0.02);
    build_run(&b3, 0.03);
    write(
        &b1,
        "fit.json",
        &fit_json(97.0, [95.0, 99.0], 3.05, [3.0, 3.1]),
    );
    write(
        &b2,
        "fit.json",
        &fit_json(104.0, [98.0, 111.0], 3.2, [3.1, 3.25]),
    );
    // b3 has no fit: it has no point in the trend and its fit criterion is NOT JUDGED.
    let crit = write(
        tmp.path(),
        "a.toml",
        "[[criterion]]\nmetric = \"fit.young_modulus_kpa\"\nmax_relative_to_nominal = 0.10\n",
    );
    let out_dir = tmp.path().join("cmp");
    let out = run(&[
        "compare",
        b1.to_str().unwrap(),
        b2.to_str().unwrap(),
        b3.to_str().unwrap(),
        "--acceptance",
        crit.to_str().unwrap(),
        "--out",
        out_dir.to_str().unwrap(),
    ]);
    // b2 MARGINAL, b3 NOT JUDGED: the comparison is NOT JUDGED (exit 0), never PASS.
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let csv = std::fs::read_to_string(out_dir.join("compare.csv")).unwrap();
    let rows: Vec<Vec<&str>> = csv
        .lines()
        .filter(|l| l.starts_with("fit.young_modulus_kpa,"))
        .map(|l| l.split(',').collect())
        .collect();
    assert_eq!(rows.len(), 3, "{csv}");
    // metric,unit,run,build_id,date,value,ci95_low,ci95_high,ci_method,baseline_value,
    // difference,...,outcome (14)
    assert_eq!(&rows[0][5..9], ["97", "95", "99", "jacobian"]);
    assert_eq!(&rows[1][5..11], ["104", "98", "111", "jacobian", "97", "7"]);
    assert_eq!(rows[1][14], "MARGINAL");
    assert_eq!(&rows[2][5..9], ["", "", "", ""]);
    assert_eq!(rows[2][14], "NOT JUDGED");
    let html = std::fs::read_to_string(out_dir.join("compare.html")).unwrap();
    assert!(
        html.contains("NOT JUDGED: 1 of 2 compared run(s) have criteria nothing could judge"),
        "banner"
    );
    assert!(html.contains("<figure id=\"compare_fit\">"));
    assert!(html.contains("fit.young_modulus_kpa"));
    let png = image::open(out_dir.join("plots/compare_fit.png")).unwrap();
    assert_eq!(png.width(), 1200);
    let svg = std::fs::read_to_string(out_dir.join("plots/compare_fit.svg")).unwrap();
    assert!(svg.contains("fitted sensor-model parameters over the builds"));
    assert!(svg.contains("the nominal value (sensor file)"));
}
