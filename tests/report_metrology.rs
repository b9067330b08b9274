//! `tactbench report` on synthetic up-down, multi-position and hold runs: the ISO
//! 376-style metrics with known answers and their confidence intervals in summary.csv
//! and verdict.json, the headline table, the residual / hysteresis / creep figures
//! (decodable PNG), and the resolution method of a single-trial angle sweep.

use std::path::Path;

use tactbench::bench::journal::Direction;
use tactbench::bench::plan::Plan;
use tactbench::units::gf_to_n;

use super::report::{
    metric, report, verdict_json, write_displacements, write_forces, write_run, PLAN_HEAD,
};
use crate::util::stderr;

/// 28 setpoints: 2 positions × 2 trials × one up-down pass of 7 rows (0, 100, 200,
/// 300 gf up, 200, 100, 0 gf down), trials numbered across positions (0, 1 at the
/// first position, 2, 3 at the second).
const UP_DOWN: &str = "[sweep]\nkind = \"magnitude\"\nfrom = 0.0\nto = 300.0\nstep = 100.0\n\
     trials = 2\ndirection = \"up-down\"\npositions_mm = [[9.0, 6.75], [7.0, 6.75]]\n";
/// Trial error (±E by trial, N), position shift (P per position index, N) and the
/// down branch's offset (W, N) on loaded rows.
const E: f64 = 0.02;
const P: f64 = 0.04;
const W: f64 = 0.05;

/// summary.csv rows with all six fields.
fn summary_rows(dir: &Path) -> Vec<Vec<String>> {
    let text = std::fs::read_to_string(dir.join("summary.csv")).unwrap();
    text.lines()
        .skip(1)
        .map(|l| l.split(',').map(str::to_string).collect())
        .collect()
}

fn row_of<'a>(rows: &'a [Vec<String>], name: &str) -> &'a Vec<String> {
    rows.iter()
        .find(|r| r[0] == name)
        .unwrap_or_else(|| panic!("{name} missing from summary.csv"))
}

fn png_ok(dir: &Path, stem: &str) {
    let png = dir.join("plots").join(format!("{stem}.png"));
    let img = image::open(&png).unwrap_or_else(|e| panic!("{}: {e}", png.display()));
    assert_eq!(image::GenericImageView::dimensions(&img), (900, 680));
    let svg = std::fs::read_to_string(dir.join("plots").join(format!("{stem}.svg"))).unwrap();
    assert!(svg.starts_with("<svg"), "{stem}.svg");
}

/// The rows follow the plan's expansion (targets, trials, positions and directions
/// from `Plan::setpoints`, as `report` checks); F^sum = 0.95 F/T + 0.01 N plus, on
/// loaded rows, the trial error ±E, the position shift P and the down branch's W.
fn up_down_run(dir: &Path) {
    let plan = Plan::from_toml_str(&format!("{PLAN_HEAD}{UP_DOWN}"), "p.toml").unwrap();
    let sps = plan.setpoints();
    assert_eq!(sps.len(), 28);
    write_run(dir, UP_DOWN, |dir, r| {
        let sp = &sps[r.index];
        let position = sp.position.expect("the plan lists positions");
        r.position = Some(position);
        r.direction = sp.direction;
        r.fz_n = r.target_normal_n;
        let loaded = sp.normal_n > 0.0;
        let down = sp.direction == Some(Direction::Down);
        let e = if sp.trial.is_multiple_of(2) { E } else { -E };
        r.fsum_z_n = 0.95 * r.fz_n
            + 0.01
            + if loaded { e + P * position as f64 } else { 0.0 }
            + if loaded && down { W } else { 0.0 };
        let a = r.fz_n;
        write_displacements(dir, r.index, |_, p, _| {
            [0.01 * a * (p[0] - 9.0) / 10.0, 0.0]
        });
        write_forces(dir, r.index, |q| {
            a * (-((q[0] - 9.0).powi(2) + (q[1] - 6.75).powi(2)) / 4.0).exp()
        });
    });
}

#[test]
fn up_down_run_reports_iso376_metrics_with_intervals_headline_and_figures() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    up_down_run(dir);
    let criteria = dir.join("criteria.toml");
    std::fs::write(
        &criteria,
        "[[criterion]]\nmetric = \"metrology.reversibility_pct_fs\"\nmax = 10.0\n\
         [[criterion]]\nmetric = \"metrology.class\"\nmax = 2.0\n\
         [[criterion]]\nmetric = \"magnitude.slope\"\nmin = 0.9\nmax = 1.0\n",
    )
    .unwrap();
    let out = report(dir, &["--acceptance", criteria.to_str().unwrap()]);
    // Reversibility 1.7 %FS is outside class 2 (0.5 %): the class criterion fails.
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));

    let fs = gf_to_n(300.0);
    assert!((metric(dir, "metrology.full_scale_n") - fs).abs() < 1e-12);
    let rev = metric(dir, "metrology.reversibility_pct_fs");
    assert!((rev - 100.0 * W / fs).abs() < 1e-9, "{rev}");
    let rep = metric(dir, "metrology.repeatability_pct_fs");
    assert!((rep - 100.0 * 2f64.sqrt() * E / fs).abs() < 1e-9, "{rep}");
    let repro = metric(dir, "metrology.reproducibility_pct_fs");
    let sd = ((4.0 * E * E + P * P) / 3.0).sqrt();
    assert!((repro - 100.0 * sd / fs).abs() < 1e-9, "{repro}");
    assert!(metric(dir, "metrology.zero_pct_fs").abs() < 1e-9);
    assert_eq!(metric(dir, "metrology.class"), 3.0);
    assert_eq!(metric(dir, "magnitude.resolution_method"), 1.0);

    // Intervals and their methods in summary.csv.
    let rows = summary_rows(dir);
    for (name, method) in [
        ("magnitude.slope", "t"),
        ("magnitude.offset_n", "t"),
        ("magnitude.resolution_n", "chi2"),
        ("magnitude.resolution_gf", "chi2"),
        ("metrology.repeatability_pct_fs", "chi2"),
        ("metrology.reproducibility_pct_fs", "bootstrap"),
        ("metrology.interpolation_pct_fs", "bootstrap"),
        ("metrology.reversibility_pct_fs", "bootstrap"),
        ("metrology.zero_pct_fs", "t"),
    ] {
        let r = row_of(&rows, name);
        assert_eq!(r.len(), 6, "{r:?}");
        assert_eq!(r[5], method, "{name}");
        let (v, lo, hi): (f64, f64, f64) = (
            r[1].parse().unwrap(),
            r[3].parse().unwrap(),
            r[4].parse().unwrap(),
        );
        assert!(
            lo <= v + 1e-12 && v <= hi + 1e-12,
            "{name}: {v} not in [{lo}, {hi}]"
        );
    }
    // The repeatability interval is the chi-squared one: per position, cells of two
    // trials at 100 and 200 gf up and down and 300 gf up: 10 cells, 10 dof.
    let r = row_of(&rows, "metrology.repeatability_pct_fs");
    let hi: f64 = r[4].parse().unwrap();
    let chi2_lo_10 = 3.2470; // χ²(0.025, 10)
    assert!(
        (hi - rep * (10.0f64 / chi2_lo_10).sqrt()).abs() < 1e-3 * rep,
        "{hi}"
    );

    // verdict.json: every metric with its interval, each criterion with its own.
    let v = verdict_json(dir);
    let metrics = v["metrics"].as_array().unwrap();
    let m = metrics
        .iter()
        .find(|m| m["name"] == "metrology.reversibility_pct_fs")
        .unwrap();
    assert_eq!(m["unit"], "%FS");
    assert_eq!(m["ci95"]["method"], "bootstrap");
    assert!(m["ci95"]["low"].as_f64().unwrap() <= m["ci95"]["high"].as_f64().unwrap());
    let c = &v["criteria"][0];
    assert_eq!(c["metric"], "metrology.reversibility_pct_fs");
    assert_eq!(c["ci95"]["method"], "bootstrap");
    assert_eq!(v["criteria"][1]["outcome"], "FAIL");
    assert!(
        v["criteria"][1]["ci95"].is_null(),
        "no interval for a class"
    );
    assert_eq!(v["criteria"][2]["ci95"]["method"], "t");

    // The page: headline table right after the banner, with limits and outcomes; the
    // metrics table with human-readable names and the machine names; the ISO section.
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    let head = html.find("id=\"headline\"").expect("headline table");
    assert!(head > html.find("id=\"verdict\"").unwrap());
    assert!(head < html.find("<h2>Acceptance").unwrap());
    let table = &html[head..html[head..].find("</section>").unwrap() + head];
    assert!(
        table.contains("reversibility / hysteresis (ISO 376 v)"),
        "{table}"
    );
    assert!(table.contains("<code>metrology.reversibility_pct_fs</code>"));
    assert!(table.contains("&lt;= 10") && table.contains(">PASS<"));
    assert!(table.contains("none (outside class 2)") && table.contains(">FAIL<"));
    assert!(table.contains("bootstrap") && table.contains("chi2"));
    assert!(html.contains("Force metrology (ISO 376 style)"));
    assert!(html.contains("Implied class: none (outside class 2)."));
    assert!(html.contains("sensitivity (slope F^sum / F/T)"));
    for stem in ["residuals", "hysteresis"] {
        png_ok(dir, stem);
        assert!(html.contains(&format!("<figure id=\"{stem}\">")), "{stem}");
    }
}

/// Two holds of 200 gf sampled every 6 s for 54 s: rows 0 unloaded, 1-10 hold 0,
/// 11 unloaded, 12-21 hold 1, 22 unloaded.
const HOLD: &str = "[sweep]\nkind = \"hold\"\nforce = 200.0\nduration_s = 54.0\n\
     sample_interval_s = 6.0\ntrials = 2\n";

#[test]
fn hold_run_reports_creep_of_known_rate_zero_drift_and_the_creep_figure() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let plan = Plan::from_toml_str(&format!("{PLAN_HEAD}{HOLD}"), "p.toml").unwrap();
    let sps = plan.setpoints();
    assert_eq!(sps.len(), 23);
    write_run(dir, HOLD, |dir, r| {
        let (i, sp) = (r.index, &sps[r.index]);
        if let Some(t) = sp.hold_t_s {
            assert_eq!(t, 6.0 * ((i % 11) - 1) as f64);
            // The F/T relaxes from 2 N (the full scale) at 0.5 mN/s.
            r.hold_t_s = Some(t);
            r.fz_n = 2.0 - 0.0005 * t;
            // Creep 0.001 N/s relative to the F/T: 100·60·0.001/2 = 3 %FS/min.
            r.fsum_z_n = r.fz_n + 0.02 + 0.001 * t;
        } else {
            // Unloaded (target 0 in the plan): the F^sum zero moves 1 mN per row.
            assert_eq!(sp.normal_n, 0.0);
            r.fz_n = 0.0;
            r.fsum_z_n = 0.001 * i as f64;
            r.fsum_sd_z_n = Some(0.002);
        }
        let a = r.fz_n;
        write_displacements(dir, i, |_, _, _| [0.001 * a, 0.0]);
        write_forces(dir, i, |_| 0.01 * a);
    });
    let out = report(dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let creep = metric(dir, "hold.creep_pct_fs_per_min");
    assert!((creep - 3.0).abs() < 1e-9, "{creep}");
    assert!((metric(dir, "hold.ft_drift_pct_fs_per_min") + 1.5).abs() < 1e-9);
    assert!((metric(dir, "hold.zero_drift_n") - 0.022).abs() < 1e-12);
    assert!((metric(dir, "hold.zero_drift_pct_fs") - 1.1).abs() < 1e-9);
    assert_eq!(metric(dir, "metrology.class"), 3.0);
    let rows = summary_rows(dir);
    assert_eq!(row_of(&rows, "hold.creep_pct_fs_per_min")[5], "t");
    let z = row_of(&rows, "hold.zero_drift_n");
    assert_eq!(z[5], "normal");
    let hi: f64 = z[4].parse().unwrap();
    assert!(
        (hi - 0.022 - 1.96 * 0.002 * 2f64.sqrt()).abs() < 1e-9,
        "{hi}"
    );
    png_ok(dir, "creep");
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    assert!(html.contains("<figure id=\"creep\">"));
    assert!(html.contains("creep of F^sum relative to the F/T"));
    assert_eq!(verdict_json(dir)["metrics"][0]["name"], "run.rows");
}

#[test]
fn single_trial_angle_sweep_says_its_resolution_is_the_sd_about_the_fit() {
    let angle1 = "[sweep]\nkind = \"angle\"\nforce = 400.0\nangle_from_deg = 0.0\nangle_to_deg = 45.0\nangle_step_deg = 15.0\ndirection_deg = 90.0\ntrials = 1\n";
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let plan = Plan::from_toml_str(&format!("{PLAN_HEAD}{angle1}"), "p.toml").unwrap();
    let sps = plan.setpoints();
    write_run(dir, angle1, |dir, r| {
        let sp = sps[r.index];
        (r.fx_n, r.fy_n, r.fz_n) = (sp.tangential_n[0], sp.tangential_n[1], sp.normal_n);
        let f = r.fz_n.hypot(r.fy_n);
        let m = (sp.swept_value + [0.5, -0.5, 0.5, -0.5][r.index % 4]).to_radians();
        (r.fsum_y_n, r.fsum_z_n) = (0.9 * f * m.sin(), 0.9 * f * m.cos());
        write_displacements(dir, r.index, |_, _, _| [0.0, 0.001]);
        write_forces(dir, r.index, |_| 0.01);
    });
    let out = report(dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(metric(dir, "angle.resolution_method"), 2.0);
    assert!(metric(dir, "angle.resolution_deg") > 0.0);
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    assert!(
        html.contains("residual SD about the fit line / |slope| (no level has two trials"),
        "the page must say which resolution definition it used"
    );
    assert!(html.contains("2: SD about the fit line (one trial per level)"));
}
