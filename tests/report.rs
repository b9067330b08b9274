//! `tactbench report` on synthetic run directories written with the journal API:
//! metric values with known answers in summary.csv and report.html, decodable PNG and
//! present SVG figures, HTML escaping of file content, acceptance verdicts and exit codes,
//! and clear errors for bad criteria files and incomplete run directories.

use std::path::Path;

use tactbench::analysis::{displacements_path, forces_path};
use tactbench::bench::journal::{Journal, JournalRow, Manifest, RunStatus};
use tactbench::bench::plan::Plan;
use tactbench::formats::{self, DisplacementRecord};
use tactbench::sensor::{Sensor, PAPER_SENSOR_TOML};
use tactbench::units::gf_to_n;

use crate::util::{self, run, stderr, stdout};

pub(crate) const PLAN_HEAD: &str = r#"
name = "report test <b>&amp;</b>"
sensor = "paper_sensor.toml"
build_id = "elastomer-<x>"
force_unit = "gf"
[indenter]
shape = "hemisphere"
diameter_mm = 5.0
[approach]
position_mm = [9.0, 6.75]
speed_mm_s = 0.5
contact_force = 5.0
[safety]
max_force = [300.0, 300.0, 1000.0]
travel_min_mm = [0.0, 0.0, -2.0]
travel_max_mm = [50.0, 50.0, 20.0]
max_speed_mm_s = 5.0
"#;

const MAGNITUDE: &str =
    "[sweep]\nkind = \"magnitude\"\nfrom = 0.0\nto = 300.0\nstep = 100.0\ntrials = 3\n";
/// From force node (4, 3) to node (5, 3) of the paper grid in 6 steps.
const SPATIAL: &str = "[sweep]\nkind = \"spatial\"\nforce = 200.0\nstart_mm = [7.9, 5.65]\nend_mm = [10.1, 5.65]\nsubdivisions = 6\n";
/// 400 gf at 0, 15, 30, 45° from the normal, tangential part along +y, two trials.
const ANGLE: &str = "[sweep]\nkind = \"angle\"\nforce = 400.0\nangle_from_deg = 0.0\nangle_to_deg = 45.0\nangle_step_deg = 15.0\ndirection_deg = 90.0\ntrials = 2\n";
/// 3 px at 0.05 mm/px along x.
const DISPLACEMENT: &str = "[sweep]\nkind = \"displacement\"\nshift_mm = [0.15, 0.0]\ntrials = 2\n";

/// Magnitude runs: per-trial error on F^sum (N), mean zero per level, so the fit is
/// exactly F^sum = 0.95·Fz + 0.01 and each level's residual SD is `E`.
const E: f64 = 0.02;
const TRIAL_ERR: [f64; 3] = [E, -E, 0.0];

pub(crate) fn sensor() -> Sensor {
    Sensor::from_toml_str(PAPER_SENSOR_TOML, "paper_sensor.toml").unwrap()
}

pub(crate) fn empty_row(index: usize, trial: usize) -> JournalRow {
    JournalRow {
        index,
        trial,
        settled: true,
        frames: format!("frames/{index:05}_0.png"),
        t_move_s: 0.5,
        t_settle_s: 0.2,
        t_acquire_s: 0.05,
        t_track_s: 2e-3,
        t_solve_s: 1e-3,
        completed_at: "2026-11-22T01:00:00Z".into(),
        ..JournalRow::default()
    }
}

/// Displacements: every marker moves by `u(p)` (mm).
pub(crate) fn write_displacements(
    dir: &Path,
    index: usize,
    u: impl Fn(usize, [f64; 2], u64) -> [f64; 2],
) {
    let s = sensor();
    let mut recs = Vec::new();
    for (li, layer) in s.layers.iter().enumerate() {
        let g = layer.markers.unwrap().grid;
        for (k, p) in g.nodes_mm().into_iter().enumerate() {
            recs.push(DisplacementRecord {
                layer: li,
                marker: k as u64,
                position_mm: p,
                u_mm: Some(u(li, p, k as u64)),
                line: 0,
            });
        }
    }
    std::fs::create_dir_all(dir.join("displacements")).unwrap();
    formats::write_displacements(&displacements_path(dir, index), &s, &recs).unwrap();
}

/// Forces: fz(q) = `fz(q)` at every node, a small tangential part along +y.
pub(crate) fn write_forces(dir: &Path, index: usize, fz: impl Fn([f64; 2]) -> f64) {
    let g = sensor().force_grid;
    let f: Vec<f64> = g
        .nodes_mm()
        .into_iter()
        .flat_map(|q| {
            let z = fz(q);
            [0.0, 0.1 * z, z]
        })
        .collect();
    std::fs::create_dir_all(dir.join("forces")).unwrap();
    formats::write_forces(&forces_path(dir, index), &g, &[(String::new(), f)]).unwrap();
}

/// Writes manifest and journal for `sweep`; `fill` sets each row's measured values and
/// writes its per-setpoint files.
pub(crate) fn write_run(dir: &Path, sweep: &str, mut fill: impl FnMut(&Path, &mut JournalRow)) {
    let plan_toml = format!("{PLAN_HEAD}{sweep}");
    let plan = Plan::from_toml_str(&plan_toml, "experiments/test.toml").unwrap();
    let setpoints = plan.setpoints();
    Manifest {
        plan_path: "experiments/test.toml".into(),
        plan_name: plan.name.clone(),
        plan_toml,
        sensor_path: "experiments/paper_sensor.toml".into(),
        sensor_toml: PAPER_SENSOR_TOML.into(),
        bench: serde_json::json!({"kind": "simulated", "scene": "<scene>.toml"}),
        devices: serde_json::json!({"stage": "grbl 1.1h", "ft": "dynpick sim 0001"}),
        build_id: Some("elastomer-<x>".into()),
        software_version: "0.1.0-test".into(),
        started_at: "2026-11-22T01:00:00Z".into(),
        resumed_at: vec![],
        sessions: vec![],
        setpoints: setpoints.len(),
        planned_setpoints: Some(setpoints.len()),
        limit: None,
        measured_setpoints: setpoints.len(),
        status: RunStatus::Completed,
        end_reason: None,
        stop_signal: None,
        incomplete_reason: None,
        ended_at: Some("2026-11-22T01:10:00Z".into()),
        software_commit: Some("0123abcd".into()),
        camera_path: None,
        camera_toml: None,
        simulated: None,
        write_failure: None,
        device_provenance: vec![],
        record: None,
    }
    .write(dir)
    .unwrap();
    let mut j = Journal::create(dir).unwrap();
    for sp in &setpoints {
        let mut r = empty_row(sp.index, sp.trial);
        r.swept_value = sp.swept_value;
        r.target_normal_n = sp.normal_n;
        r.stage_x_mm = sp.position_mm[0];
        r.stage_y_mm = sp.position_mm[1];
        fill(dir, &mut r);
        j.append(&r).unwrap();
    }
}

/// A magnitude run: 0..300 gf by 100, 3 trials, known fit and spread; a radial
/// displacement field and a Gaussian fz bump around the load for the field figures.
fn magnitude_run(dir: &Path) {
    write_run(dir, MAGNITUDE, |dir, r| {
        r.fz_n = r.target_normal_n;
        r.fsum_z_n = 0.95 * r.fz_n + 0.01 + TRIAL_ERR[r.trial];
        r.fsum_y_n = 0.1 * r.fsum_z_n;
        let c = [9.0, 6.75];
        let a = r.fz_n;
        write_displacements(dir, r.index, |li, p, _| {
            let d = [p[0] - c[0], p[1] - c[1]];
            let w = a * 0.05 / (1.0 + li as f64) / (1.0 + d[0] * d[0] + d[1] * d[1]);
            [w * d[0], w * d[1]]
        });
        write_forces(dir, r.index, |q| {
            a * (-((q[0] - c[0]).powi(2) + (q[1] - c[1]).powi(2)) / 4.0).exp()
        });
    });
}

pub(crate) fn summary(dir: &Path) -> Vec<(String, f64, String)> {
    let text = std::fs::read_to_string(dir.join("summary.csv")).unwrap();
    let mut lines = text.lines();
    assert_eq!(
        lines.next(),
        Some("metric,value,unit,ci95_low,ci95_high,ci_method")
    );
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[0].to_string(), f[1].parse().unwrap(), f[2].to_string())
        })
        .collect()
}

pub(crate) fn metric(dir: &Path, name: &str) -> f64 {
    summary(dir)
        .into_iter()
        .find(|m| m.0 == name)
        .unwrap_or_else(|| panic!("{name} missing from summary.csv"))
        .1
}

pub(crate) fn report(dir: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec!["report", dir.to_str().unwrap()];
    args.extend_from_slice(extra);
    run(&args)
}

#[test]
fn magnitude_report_has_known_values_figures_and_escaped_provenance() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    magnitude_run(dir);
    let out = report(dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(out.status.code(), Some(0));

    // Known answers (tolerance 1e-9 relative to the 1e-2 N scale).
    assert!((metric(dir, "magnitude.slope") - 0.95).abs() < 1e-9);
    assert!((metric(dir, "magnitude.offset_n") - 0.01).abs() < 1e-9);
    assert!((metric(dir, "magnitude.residual_sd_n") - E).abs() < 1e-9);
    let res = metric(dir, "magnitude.resolution_n");
    assert!((res - 2.0 * E / 0.95).abs() < 1e-9, "{res}");
    let res_gf = metric(dir, "magnitude.resolution_gf");
    assert!((gf_to_n(res_gf) - res).abs() < 1e-12);
    assert!(metric(dir, "magnitude.linearity_pct") < 1e-6);
    assert_eq!(metric(dir, "run.rows"), 12.0);
    assert!((metric(dir, "timing.forces_ms") - 3.0).abs() < 1e-9);
    assert!((metric(dir, "timing.rest_ms") - 750.0).abs() < 1e-9);
    assert!(summary(dir)
        .iter()
        .all(|m| m.0 != "magnitude.hysteresis_pct"));

    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    // The values printed in the report are those of summary.csv (6 significant digits),
    // forces in the plan's unit (gf): one unit per quantity on the page.
    assert!(
        html.contains(&tactbench::report::acceptance::fmt_value(res_gf)),
        "resolution missing"
    );
    let offset_gf = tactbench::units::ForceUnit::GramForce.from_newtons(0.01);
    assert!(
        html.contains(&format!(
            "<td>{}</td><td class=\"l\">gf</td>",
            tactbench::report::acceptance::fmt_value(offset_gf)
        )),
        "the offset is shown in gf on a gf plan"
    );
    assert!(
        !html.contains("<code>magnitude.resolution_n</code>"),
        "the resolution in N is left off a gf page"
    );
    assert!(html.contains("magnitude.r2"));
    // Provenance, escaped.
    assert!(
        html.contains("report test &lt;b&gt;&amp;amp;&lt;/b&gt;"),
        "plan name not escaped"
    );
    assert!(!html.contains("<b>&amp;</b>"));
    assert!(html.contains("elastomer-&lt;x&gt;") && html.contains("0.1.0-test"));
    assert!(html.contains("dynpick sim 0001") && html.contains("&lt;scene&gt;.toml"));
    assert!(html.contains("2026-11-22T01:10:00Z") && html.contains("completed"));
    // Self-contained: four figures embedded (Fig. 7, residuals, Fig. 4, Fig. 5; no
    // hysteresis loop for a sweep that only loads), nothing fetched.
    assert_eq!(html.matches("src=\"data:image/png;base64,").count(), 4);
    assert!(!dir.join("plots/hysteresis.png").exists());
    assert!(!html.contains("http://") && !html.contains("https://"));

    for stem in ["magnitude", "residuals", "displacements", "force_field"] {
        let png = dir.join("plots").join(format!("{stem}.png"));
        let img = image::open(&png).unwrap_or_else(|e| panic!("{}: {e}", png.display()));
        let dims = image::GenericImageView::dimensions(&img);
        if stem == "force_field" {
            // Sized for equal mm per pixel on both axes.
            assert!(dims.0 >= 800 && dims.1 >= 360, "{dims:?}");
        } else {
            assert_eq!(dims, (900, 680));
        }
        let svg = std::fs::read_to_string(dir.join("plots").join(format!("{stem}.svg"))).unwrap();
        assert!(svg.starts_with("<svg"), "{stem}.svg");
    }
}

#[test]
fn acceptance_verdicts_set_the_exit_code() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    magnitude_run(dir);
    let pass = dir.join("pass.toml");
    std::fs::write(
        &pass,
        "[[criterion]]\nmetric = \"magnitude.r2\"\nmin = 0.99\n\
         [[criterion]]\nmetric = \"magnitude.slope\"\nmin = 0.9\nmax = 1.0\n\
         [[criterion]]\nmetric = \"run.unsettled\"\nmax = 0\n",
    )
    .unwrap();
    let out = report(dir, &["--acceptance", pass.to_str().unwrap()]);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}{}",
        stdout(&out),
        stderr(&out)
    );
    let so = stdout(&out);
    assert!(
        so.contains("PASS magnitude.slope = 0.95 (in [0.9, 1])"),
        "{so}"
    );
    assert!(so.contains("acceptance: PASS (3 criteria)"), "{so}");
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    assert_eq!(html.matches("<tr class=\"verdict\">").count(), 3);
    assert!(!html.contains(">FAIL<"));

    // 2·0.02/0.95 N = 4.29 gf: a 4 gf limit fails, the other criterion passes.
    let fail = dir.join("fail.toml");
    std::fs::write(
        &fail,
        "[[criterion]]\nmetric = \"magnitude.resolution_gf\"\nmax = 4.0\n\
         [[criterion]]\nmetric = \"magnitude.r2\"\nmin = 0.99\n",
    )
    .unwrap();
    let out = report(dir, &["--acceptance", fail.to_str().unwrap()]);
    assert_eq!(
        out.status.code(),
        Some(1),
        "{}{}",
        stdout(&out),
        stderr(&out)
    );
    let so = stdout(&out);
    assert!(
        so.contains("FAIL magnitude.resolution_gf = 4.2") && so.contains("(<= 4 gf)"),
        "{so}"
    );
    assert!(so.contains("PASS magnitude.r2"), "{so}");
    assert!(
        so.contains("acceptance: FAIL (1 of 2 criteria failed)"),
        "{so}"
    );
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    assert!(html.contains("<td class=\"l fail\">FAIL</td>"));
}

#[test]
fn bad_criteria_are_errors_with_exit_code_two() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    magnitude_run(dir);
    let cases: [(&str, &[&str]); 4] = [
        (
            "[[criterion]]\nmetric = \"magnitude.rsquared\"\nmin = 0.9\n",
            &[
                "criterion 1 (`magnitude.rsquared`): unknown metric",
                "magnitude.r2 [1]",
            ],
        ),
        (
            "[[criterion]]\nmetric = \"spatial.fwhm_mm\"\nmax = 5.0\n",
            &["has no such metric", "magnitude sweep", "magnitude.r2"],
        ),
        (
            "[[criterion]]\nmetric = \"magnitude.r2\"\nmin = \n",
            &["bad.toml", "line 3"],
        ),
        (
            "[[criterion]]\nmetric = \"magnitude.r2\"\n",
            &["give min, max or both"],
        ),
    ];
    for (text, expected) in cases {
        let p = dir.join("bad.toml");
        std::fs::write(&p, text).unwrap();
        let out = report(dir, &["--acceptance", p.to_str().unwrap()]);
        assert_eq!(out.status.code(), Some(2), "{text}: {}", stdout(&out));
        let e = stderr(&out);
        for x in expected {
            assert!(e.contains(x), "{text}: `{x}` missing from: {e}");
        }
    }
    let out = report(
        dir,
        &["--acceptance", dir.join("nope.toml").to_str().unwrap()],
    );
    assert_eq!(out.status.code(), Some(2));
    assert!(stderr(&out).contains("nope.toml"), "{}", stderr(&out));
}

#[test]
fn missing_evidence_is_noted_and_broken_run_directories_are_named_in_the_error() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    magnitude_run(dir);
    // The field figures use the row with the largest F^sum: setpoint 3 (300 gf, trial
    // 0). Its forces file is evidence, not record: the report says what it cannot show.
    std::fs::remove_file(forces_path(dir, 3)).unwrap();
    let out = report(dir, &[]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let e = stderr(&out);
    assert!(
        e.contains("not shown: force-field figure")
            && e.contains(
                "forces/00003.csv (reconstructed forces of setpoint 3) is not in the run directory"
            ),
        "{e}"
    );

    let out = report(dir, &["--setpoint", "99"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(stderr(&out).contains("setpoint 99"), "{}", stderr(&out));

    // A non-finite journal value names file, line and column.
    let j = dir.join("journal.csv");
    let text = std::fs::read_to_string(&j).unwrap();
    let mut lines: Vec<String> = text.lines().map(String::from).collect();
    let col = lines[0].split(',').position(|c| c == "fsum_z_n").unwrap();
    let mut f: Vec<String> = lines[3].split(',').map(String::from).collect();
    f[col] = "NaN".into();
    lines[3] = f.join(",");
    std::fs::write(&j, lines.join("\n") + "\n").unwrap();
    // A NaN force sum (written by older versions for a failed reconstruction) is a
    // failed row since issue 33: skipped, counted, never the whole journal refused.
    let out = report(dir, &[]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("verdict.json")).unwrap()).unwrap();
    let failed = v["run"]["failed_rows"].as_array().map(Vec::len);
    assert_eq!(failed, Some(1), "{v}");

    std::fs::remove_file(&j).unwrap();
    let out = report(dir, &[]);
    assert_eq!(out.status.code(), Some(2));
    assert!(stderr(&out).contains("journal.csv"), "{}", stderr(&out));
    std::fs::remove_file(dir.join("manifest.json")).unwrap();
    let out = report(dir, &[]);
    assert!(stderr(&out).contains("manifest.json"), "{}", stderr(&out));
}

/// A spatial run: fz = 2·max(0, 1 − r/3) around each load (r the distance to it):
/// along the load line the profile is triangular, FWHM exactly 3 mm.
fn spatial_run(dir: &Path) {
    write_run(dir, SPATIAL, |dir, r| {
        let p = [r.stage_x_mm, r.stage_y_mm];
        r.fz_n = r.target_normal_n;
        r.fsum_z_n = r.fz_n;
        write_displacements(dir, r.index, |_, _, _| [0.0, 0.0]);
        write_forces(dir, r.index, |q| {
            2.0 * (1.0 - (q[0] - p[0]).hypot(q[1] - p[1]) / 3.0).max(0.0)
        });
    });
}

#[test]
fn spatial_run_reports_the_profile_width() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    spatial_run(dir);
    let out = report(dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!((metric(dir, "spatial.fwhm_mm") - 3.0).abs() < 1e-9);
    assert!(metric(dir, "spatial.peak_offset_mm").abs() < 1e-9);
    let img = image::open(dir.join("plots/spatial_profile.png")).unwrap();
    assert_eq!(image::GenericImageView::dimensions(&img), (900, 680));
    assert!(dir.join("plots/spatial_profile.svg").is_file());
    // The plan is in gf: the profile's forces too (they were in N).
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    assert!(html.contains("<th>fz (gf)</th>"), "profile table not in gf");
    let n = util::newton_units(&util::page_text(&html));
    assert!(n.is_empty(), "forces in N on a gf page: {n:?}");
}

/// The complaint that started issue 23: "one plan in gf, yet the key metrics show the
/// offset in N", and the force-field figure and camera evidence stayed in N after the
/// metrics were converted. Every force on the page and in every figure of a gf plan
/// is in gf; only the machine names (`magnitude.offset_n`) keep theirs.
#[test]
fn a_gf_plan_report_shows_no_force_in_newtons_on_the_page_or_in_its_figures() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    magnitude_run(dir);
    let out = report(dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    let text = util::page_text(&html);
    let n = util::newton_units(&text);
    assert!(n.is_empty(), "forces in N on a gf page: {n:?}");
    // What used to be in N: the field's caption (the camera evidence, which these
    // synthetic track files cannot show, is checked on the committed reproduction runs
    // in archive::the_committed_reproduction_runs_report_and_compare).
    assert!(text.contains("largest |fz|") && text.contains("(gf; red presses"));
    assert!(html.contains("where metrics named <code>…_n</code> are in N"));
    let mut svgs = 0;
    for e in std::fs::read_dir(dir.join("plots")).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "svg") {
            let svg = std::fs::read_to_string(&p).unwrap();
            let n = util::newton_units(&svg);
            assert!(n.is_empty(), "{}: forces in N: {n:?}", p.display());
            svgs += 1;
        }
    }
    assert!(svgs >= 4, "{svgs} figures");
    let field = std::fs::read_to_string(dir.join("plots/force_field.svg")).unwrap();
    assert!(field.contains("fz (gf), red presses in") && field.contains("gf per mm)"));
}

/// "The residual and marker-health legends sit on the data, the creep plot's colours
/// have no key": every report figure with a legend draws it in a strip between its
/// title and the plot (above the topmost axis label), and every colour is keyed —
/// here the Fig. 7 plot, the marker displacements (one colour per layer), the
/// residuals (one colour per trial, each named) and the Fig. 9 profile.
#[test]
fn legends_sit_above_the_plot_and_key_every_colour() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    magnitude_run(dir);
    let out = report(dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let check = |dir: &Path, stem: &str, labels: &[&str]| {
        let svg = std::fs::read_to_string(dir.join(format!("plots/{stem}.svg"))).unwrap();
        let top = util::svg_top_tick_y(&svg);
        assert!(top.is_finite(), "{stem}: no tick labels");
        let texts = util::svg_texts(&svg);
        for l in labels {
            let (_, y, _) = texts
                .iter()
                .find(|(_, _, t)| t.starts_with(l))
                .unwrap_or_else(|| panic!("{stem}: no legend entry {l:?} in {texts:?}"));
            assert!(
                *y < top - 5.0,
                "{stem}: legend {l:?} at y {y}, plot from {top}"
            );
        }
    };
    check(
        dir,
        "magnitude",
        &["identity", "samples", "level mean", "fit: slope"],
    );
    check(dir, "displacements", &["layer blue", "layer red"]);
    // magnitude_run: 3 trials at one position, each colour named.
    check(
        dir,
        "residuals",
        &["loading (up)", "trial 0", "trial 1", "trial 2"],
    );

    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    spatial_run(dir);
    let out = report(dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    check(
        dir,
        "spatial_profile",
        &["fz / max fz", "half maximum", "full width at half maximum"],
    );
}

#[test]
fn displacement_run_reports_table_one_in_pixels() {
    // 3 px shift (0.15 mm); blue markers ±0.003 mm alternating in x (0.06 px), red
    // markers exact. Two trials of 130 markers per layer.
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write_run(dir, DISPLACEMENT, |dir, r| {
        write_displacements(dir, r.index, |li, _, k| {
            let e = if li == 0 {
                if k % 2 == 0 {
                    0.003
                } else {
                    -0.003
                }
            } else {
                0.0
            };
            [0.15 + e, 0.0]
        });
    });
    let out = report(dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!((metric(dir, "displacement.blue.x.mean_px") - 3.0).abs() < 1e-9);
    let n = 260.0f64;
    let sd = 0.06 * (n / (n - 1.0)).sqrt();
    assert!((metric(dir, "displacement.blue.x.sd_px") - sd).abs() < 1e-9);
    assert!(metric(dir, "displacement.red.x.sd_px") < 1e-9);
    assert!(metric(dir, "displacement.red.y.mean_px").abs() < 1e-12);
    assert!((metric(dir, "displacement.max_sd_px") - sd).abs() < 1e-9);
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    assert!(html.contains("Displacement accuracy (paper Table I)"));
    // No forces files: the quiver is drawn, the force field is not.
    assert!(dir.join("plots/displacements.png").is_file());
    assert!(!dir.join("plots/force_field.png").exists());
}

#[test]
fn angle_run_reports_bias_and_resolution() {
    // The F/T reads the target wrench; F^sum is 0.9 of it, turned 1° further from the
    // normal in trial 0 and 3° in trial 1: bias 2°, per-level residual SD sqrt(2)°,
    // resolution 2·sqrt(2)° (slope 1).
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let plan = Plan::from_toml_str(&format!("{PLAN_HEAD}{ANGLE}"), "p.toml").unwrap();
    let sps = plan.setpoints();
    write_run(dir, ANGLE, |dir, r| {
        let sp = sps[r.index];
        (r.fx_n, r.fy_n, r.fz_n) = (sp.tangential_n[0], sp.tangential_n[1], sp.normal_n);
        let f = r.fz_n.hypot(r.fy_n);
        let m = (sp.swept_value + if r.trial == 0 { 1.0 } else { 3.0 }).to_radians();
        (r.fsum_y_n, r.fsum_z_n) = (0.9 * f * m.sin(), 0.9 * f * m.cos());
        write_displacements(dir, r.index, |_, _, _| [0.0, 0.001]);
        write_forces(dir, r.index, |_| 0.01);
    });
    let out = report(dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!((metric(dir, "angle.bias_deg") - 2.0).abs() < 1e-9);
    assert!((metric(dir, "angle.bias_vs_target_deg") - 2.0).abs() < 1e-9);
    assert!((metric(dir, "angle.slope") - 1.0).abs() < 1e-9);
    let res = metric(dir, "angle.resolution_deg");
    assert!((res - 2.0 * 2f64.sqrt()).abs() < 1e-9, "{res}");
    let img = image::open(dir.join("plots/angle.png")).unwrap();
    assert_eq!(image::GenericImageView::dimensions(&img), (900, 680));
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    assert!(html.contains("Force angle (paper Fig. 8)"));
}

/// Fig. 9 through the real model and solvers: point loads of 200 gf stepped in 6 from
/// force node (4, 3) to node (5, 3) of the paper sensor, displacements by the half-space
/// model (plus 0.1 px Gaussian noise for Tikhonov), forces reconstructed, the run
/// analysed through `RunAnalysis`. Returns the FWHM, mm.
fn model_fwhm(config: tactbench::solve::SolverConfig, noise_px: f64) -> f64 {
    use tactbench::analysis::{AnalysisOptions, RunAnalysis};
    use tactbench::model::{forward, HalfSpace, MarkerSite};
    use tactbench::solve::{precompute, Problem};
    let s = sensor();
    let sites = MarkerSite::from_sensor_grids(&s);
    let model = HalfSpace::from_elastomer(&s.elastomer);
    let problem = Problem::new(&s, &sites);
    let mut rng = crate::util::Rng::new(7);
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let noise_mm = noise_px * s.camera.mm_per_px;
    write_run(dir, SPATIAL, |dir, r| {
        let p = [r.stage_x_mm, r.stage_y_mm];
        let mut u = forward(&model, &sites, &[p], &[0.0, 0.0, r.target_normal_n]).unwrap();
        for v in &mut u {
            *v += noise_mm * rng.normal();
        }
        let mut solver = precompute(&problem, &config, Some(&u)).unwrap();
        let mut f = vec![0.0; problem.n_outputs()];
        solver.apply(&u, &mut f).unwrap();
        r.fz_n = r.target_normal_n;
        r.fsum_z_n = f.iter().skip(2).step_by(3).sum();
        write_displacements(dir, r.index, |_, _, _| [0.0, 0.0]);
        std::fs::create_dir_all(dir.join("forces")).unwrap();
        formats::write_forces(
            &forces_path(dir, r.index),
            &s.force_grid,
            &[(String::new(), f)],
        )
        .unwrap();
    });
    let a = RunAnalysis::load(dir, &AnalysisOptions::default()).unwrap();
    a.spatial.unwrap().fwhm_mm
}

#[test]
fn spatial_resolution_of_the_paper_geometry_through_model_and_solvers() {
    use tactbench::solve::{Lambda, Method, SolverConfig};
    // Noiseless pinv: a load on a node comes back on that node only, a load between
    // nodes is spread over its neighbours; the merged profile is about one pitch wide
    // (measured 2.32 mm). Bounds: more than half a pitch, less than the paper's 4 mm.
    let pinv = model_fwhm(SolverConfig::default(), 0.0);
    eprintln!("FWHM pinv, no noise: {pinv:.3} mm");
    assert!(pinv > 1.1 && pinv < 4.0, "{pinv}");
    // Tikhonov (GCV) with the paper's 0.1 px noise smooths more: wider (measured
    // 2.93 mm, seed 7), still below the paper's ~4 mm (its pinv on measured data).
    let tik = model_fwhm(
        SolverConfig {
            method: Method::Tikhonov,
            lambda: Lambda::Gcv,
            ..SolverConfig::default()
        },
        0.1,
    );
    eprintln!("FWHM tikhonov gcv, 0.1 px noise: {tik:.3} mm");
    assert!(tik >= pinv - 1e-9 && tik < 4.4, "{tik}");
}

#[test]
fn the_example_criteria_file_is_valid() {
    let c = tactbench::report::acceptance::Criteria::from_path(&crate::util::root(
        "experiments/acceptance_example.toml",
    ))
    .unwrap();
    assert!(c
        .criteria
        .iter()
        .any(|c| c.metric == "magnitude.resolution_gf"));
}

/// Every file under `dir` (relative path -> bytes), to prove a report changed nothing.
fn snapshot(dir: &Path) -> std::collections::BTreeMap<std::path::PathBuf, Vec<u8>> {
    let mut out = std::collections::BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.insert(
                    p.strip_prefix(dir).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                );
            }
        }
    }
    out
}

/// Keeps the first `keep` journal rows of a complete synthetic run and records in the
/// manifest how the run ended.
fn cut_run(dir: &Path, keep: usize, status: RunStatus, reason: Option<&str>) {
    let j = dir.join("journal.csv");
    let text = std::fs::read_to_string(&j).unwrap();
    let kept: Vec<&str> = text.lines().take(keep + 1).collect();
    std::fs::write(&j, kept.join("\n") + "\n").unwrap();
    let mut m = Manifest::read(dir).unwrap();
    m.finish(
        status,
        reason.map(String::from),
        keep,
        (status == RunStatus::Interrupted).then_some(2),
        "2026-11-22T01:05:00Z".into(),
    );
    m.write(dir).unwrap();
}

pub(crate) fn verdict_json(dir: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("verdict.json")).unwrap()).unwrap()
}

const PASSING: &str = "[[criterion]]\nmetric = \"magnitude.r2\"\nmin = 0.99\n";

#[test]
fn a_partial_run_is_incomplete_whatever_its_metrics_unless_graded_on_purpose() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("run");
    std::fs::create_dir(&dir).unwrap();
    magnitude_run(&dir);
    // 8 of 12 rows: every level present, the fit perfect, r2 passes by far.
    cut_run(
        &dir,
        8,
        RunStatus::Interrupted,
        Some("interrupted by SIGINT (Ctrl-C)"),
    );
    let c = tmp.path().join("c.toml");
    std::fs::write(&c, PASSING).unwrap();
    let out = report(&dir, &["--acceptance", c.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(5), "{}", stderr(&out));
    let so = stdout(&out);
    assert!(
        so.contains("PASS magnitude.r2"),
        "the criterion itself passes: {so}"
    );
    assert!(
        so.contains("acceptance: INCOMPLETE (8 of 12 planned setpoints measured; not graded)"),
        "{so}"
    );
    let v = verdict_json(&dir);
    assert_eq!(v["outcome"], "INCOMPLETE");
    assert_eq!(v["exit_code"], 5);
    assert_eq!(v["graded_partial"], false);
    assert_eq!(v["criteria"][0]["outcome"], "PASS");
    let why = v["run"]["incomplete_reason"].as_str().unwrap();
    assert!(
        why.contains("interrupted by SIGINT") && why.contains("8 of the plan's 12"),
        "{why}"
    );
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    assert!(
        !html.contains("class=\"PASS\""),
        "no green banner on a partial run"
    );
    assert!(
        html.contains("criteria alone: <span class=\"\">PASS</span>"),
        "no green overall PASS on a partial run"
    );
    assert!(html.contains("<div class=\"outcome\">INCOMPLETE</div>"));

    let out = report(
        &dir,
        &["--acceptance", c.to_str().unwrap(), "--allow-partial"],
    );
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    assert!(
        stdout(&out)
            .contains("acceptance: PASS (1 criteria, PARTIAL RUN graded with --allow-partial)"),
        "{}",
        stdout(&out)
    );
    let v = verdict_json(&dir);
    assert_eq!(v["outcome"], "PASS");
    assert_eq!(v["graded_partial"], true);

    // Without criteria a partial run is INCOMPLETE too (the exit code gates a build).
    let out = report(&dir, &[]);
    assert_eq!(out.status.code(), Some(5), "{}", stderr(&out));
}

#[test]
fn a_value_in_the_marginal_band_is_marginal_with_exit_code_zero() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    magnitude_run(dir);
    // slope is 0.95: within [0.9, 1.1], at or below marginal_min 0.96.
    let c = dir.join("m.toml");
    std::fs::write(
        &c,
        "[[criterion]]\nmetric = \"magnitude.slope\"\nmin = 0.9\nmax = 1.1\nmarginal_min = 0.96\n\
         [[criterion]]\nmetric = \"magnitude.r2\"\nmin = 0.99\n",
    )
    .unwrap();
    let out = report(dir, &["--acceptance", c.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let so = stdout(&out);
    assert!(
        so.contains("MARGINAL magnitude.slope = 0.95 (in [0.9, 1.1], marginal <= 0.96)"),
        "{so}"
    );
    assert!(
        so.contains("acceptance: MARGINAL (1 of 2 criteria marginal)"),
        "{so}"
    );
    let v = verdict_json(dir);
    assert_eq!(v["outcome"], "MARGINAL");
    assert_eq!(v["criteria"][0]["outcome"], "MARGINAL");
    assert_eq!(v["criteria"][0]["marginal_min"], 0.96);
    assert_eq!(v["criteria"][1]["outcome"], "PASS");
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    assert!(html.contains("<section id=\"verdict\" class=\"MARGINAL\">"));
    assert!(html.contains("<td class=\"l marginal\">MARGINAL</td>"));
}

#[test]
fn require_build_id_fails_a_run_that_recorded_none() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    magnitude_run(dir);
    let c = dir.join("b.toml");
    std::fs::write(&c, format!("require_build_id = true\n{PASSING}")).unwrap();
    let out = report(dir, &["--acceptance", c.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    assert!(stdout(&out).contains("PASS provenance: build_id = elastomer-<x>"));
    assert_eq!(
        verdict_json(dir)["requirements"][0]["value"],
        "elastomer-<x>"
    );

    let mut m = Manifest::read(dir).unwrap();
    m.build_id = None;
    m.write(dir).unwrap();
    let out = report(dir, &["--acceptance", c.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    let so = stdout(&out);
    assert!(
        so.contains("FAIL provenance: build_id = (none recorded)"),
        "{so}"
    );
    assert!(
        so.contains("acceptance: FAIL (1 of 2 criteria failed)"),
        "{so}"
    );
    let v = verdict_json(dir);
    assert_eq!(v["outcome"], "FAIL");
    assert_eq!(v["requirements"][0]["outcome"], "FAIL");
    assert!(v["requirements"][0]["value"].is_null());
}

/// Asserts `v[key]` exists and has the JSON type `ty` (`string`, `number`, `bool`,
/// `array`, `object`, `null`, or `a|b` alternatives).
fn has(v: &serde_json::Value, path: &str, ty: &str) {
    let mut x = v;
    for k in path.split('.') {
        x = x
            .get(k)
            .unwrap_or_else(|| panic!("verdict.json: `{path}` missing in {v:#}"));
    }
    let actual = match x {
        serde_json::Value::Null => "null",
        serde_json::Value::Bool(_) => "bool",
        serde_json::Value::Number(_) => "number",
        serde_json::Value::String(_) => "string",
        serde_json::Value::Array(_) => "array",
        serde_json::Value::Object(_) => "object",
    };
    assert!(
        ty.split('|').any(|t| t == actual),
        "verdict.json: `{path}` is {actual}, expected {ty}"
    );
}

#[test]
fn verdict_json_has_every_documented_field_with_its_type() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    magnitude_run(dir);
    let c = dir.join("c.toml");
    std::fs::write(
        &c,
        format!("require_build_id = true\n{PASSING}marginal_min = 0.995\n"),
    )
    .unwrap();
    let out = report(dir, &["--acceptance", c.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let v = verdict_json(dir);
    for (path, ty) in [
        ("schema", "string"),
        ("outcome", "string"),
        ("exit_code", "number"),
        ("summary", "string"),
        ("graded_partial", "bool"),
        ("criteria_file", "string"),
        ("criteria", "array"),
        ("requirements", "array"),
        ("run.dir", "string"),
        ("run.status", "string"),
        ("run.in_progress", "bool"),
        ("run.writer", "null"),
        ("run.planned_setpoints", "number"),
        ("run.run_setpoints", "number"),
        ("run.measured_setpoints", "number"),
        ("run.limit", "null"),
        ("run.stop_signal", "null"),
        ("run.end_reason", "null"),
        ("run.complete", "bool"),
        ("run.incomplete_reason", "null"),
        ("run.torn_journal_line", "null"),
        ("provenance.plan_name", "string"),
        ("provenance.plan_path", "string"),
        ("provenance.plan_sha256", "string"),
        ("provenance.sensor_path", "string"),
        ("provenance.sensor_sha256", "string"),
        ("provenance.build_id", "string"),
        ("provenance.software_version", "string"),
        ("provenance.git_commit", "string"),
        ("provenance.devices", "object"),
        ("provenance.bench", "object"),
        ("provenance.started_at", "string"),
        ("provenance.resumed_at", "array"),
        ("provenance.ended_at", "string"),
        ("report.software_version", "string"),
        ("report.git_commit", "string"),
        ("report.generated_at", "string"),
    ] {
        has(&v, path, ty);
    }
    assert_eq!(v["schema"], "tactbench-verdict/1");
    assert_eq!(v["outcome"], "PASS");
    assert_eq!(v["run"]["status"], "completed");
    assert_eq!(v["run"]["planned_setpoints"], 12);
    assert_eq!(v["provenance"]["git_commit"], "0123abcd");
    // The plan hash is the SHA-256 of the plan text recorded in the manifest.
    let m = Manifest::read(dir).unwrap();
    assert_eq!(
        v["provenance"]["plan_sha256"],
        tactbench::report::sha256::sha256_hex(m.plan_toml.as_bytes())
    );
    assert_eq!(v["provenance"]["plan_sha256"].as_str().unwrap().len(), 64);
    let crit = &v["criteria"][0];
    for (k, ty) in [
        ("metric", "string"),
        ("value", "number"),
        ("unit", "string"),
        ("min", "number"),
        ("max", "null"),
        ("marginal_min", "number"),
        ("marginal_max", "null"),
        ("outcome", "string"),
        ("note", "null"),
    ] {
        has(crit, k, ty);
    }
    let req = &v["requirements"][0];
    has(req, "requirement", "string");
    has(req, "value", "string");
    has(req, "outcome", "string");
    // The report binary's commit: 40 hex digits, or `unknown` outside git.
    let commit = v["report"]["git_commit"].as_str().unwrap();
    assert!(
        commit == "unknown"
            || (commit.len() == 40 && commit.chars().all(|c| c.is_ascii_hexdigit())),
        "{commit}"
    );
}

#[test]
fn reports_of_empty_one_row_and_torn_runs_leave_the_run_directory_untouched() {
    let tmp = tempfile::tempdir().unwrap();
    let c = tmp.path().join("c.toml");
    std::fs::write(&c, PASSING).unwrap();
    for (name, keep, torn) in [("empty", 0, false), ("one", 1, false), ("torn", 5, true)] {
        let dir = tmp.path().join(name);
        std::fs::create_dir(&dir).unwrap();
        magnitude_run(&dir);
        cut_run(&dir, keep, RunStatus::Aborted, Some("stage: limit switch"));
        if torn {
            // What a kill in the middle of appending row 5 leaves.
            use std::io::Write as _;
            let mut f = std::fs::OpenOptions::new()
                .append(true)
                .open(dir.join("journal.csv"))
                .unwrap();
            f.write_all(b"5,2,100,0.98,0,0,0.0").unwrap();
        }
        let before = snapshot(&dir);
        // Into another directory: the run directory stays byte-identical.
        let elsewhere = tmp.path().join(format!("{name}_report"));
        let out = report(
            &dir,
            &[
                "--acceptance",
                c.to_str().unwrap(),
                "--out",
                elsewhere.to_str().unwrap(),
            ],
        );
        assert_eq!(out.status.code(), Some(5), "{name}: {}", stderr(&out));
        assert_eq!(snapshot(&dir), before, "{name}: the run directory changed");
        let v = verdict_json(&elsewhere);
        assert_eq!(v["outcome"], "INCOMPLETE", "{name}");
        assert_eq!(v["run"]["status"], "aborted");
        assert_eq!(v["run"]["measured_setpoints"], keep);
        assert_eq!(v["run"]["end_reason"], "stage: limit switch");
        let html = std::fs::read_to_string(elsewhere.join("report.html")).unwrap();
        assert!(html.contains("stage: limit switch"), "{name}: stop reason");
        assert!(html.contains("elastomer-&lt;x&gt;"), "{name}: provenance");
        if keep <= 1 {
            // One level (or none): no line fit, and the report says why.
            let e = stderr(&out);
            assert!(e.contains("no magnitude analysis"), "{name}: {e}");
            assert!(html.contains("Analyses not computed"), "{name}");
            assert_eq!(v["criteria"][0]["outcome"], "FAIL");
            assert!(v["criteria"][0]["value"].is_null());
            assert!(
                v["criteria"][0]["note"]
                    .as_str()
                    .unwrap()
                    .starts_with("not computed:"),
                "{name}"
            );
        }
        if torn {
            assert_eq!(v["run"]["torn_journal_line"]["line"], 7);
            assert_eq!(v["run"]["torn_journal_line"]["bytes"], 20);
            assert!(stderr(&out).contains("line 7 is torn"), "{}", stderr(&out));
            assert!(html.contains("torn journal"));
        } else {
            assert!(v["run"]["torn_journal_line"].is_null());
        }
        // In place: only the report's own files are added; the record is unchanged.
        let out = report(&dir, &["--allow-partial"]);
        assert_eq!(out.status.code(), Some(0), "{name}: {}", stderr(&out));
        let after = snapshot(&dir);
        for (path, bytes) in &before {
            assert_eq!(
                after.get(path),
                Some(bytes),
                "{name}: {} changed",
                path.display()
            );
        }
        for path in after.keys().filter(|p| !before.contains_key(*p)) {
            let first = path
                .components()
                .next()
                .unwrap()
                .as_os_str()
                .to_string_lossy();
            assert!(
                ["report.html", "verdict.json", "summary.csv", "plots"].contains(&first.as_ref()),
                "{name}: report wrote {}",
                path.display()
            );
        }
    }
}

#[test]
fn a_run_whose_writer_is_live_is_reported_in_progress_and_incomplete() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    magnitude_run(dir);
    let mut m = Manifest::read(dir).unwrap();
    m.status = RunStatus::Running;
    m.ended_at = None;
    m.write(dir).unwrap();
    // This test process plays the live writer.
    let lock = tactbench::bench::lock::RunLock::acquire(dir, "run").unwrap();
    let lock_text = std::fs::read(lock.path()).unwrap();
    let out = report(dir, &[]);
    assert_eq!(out.status.code(), Some(5), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("still in progress"),
        "{}",
        stderr(&out)
    );
    let v = verdict_json(dir);
    assert_eq!(v["run"]["status"], "in_progress");
    assert_eq!(v["run"]["in_progress"], true);
    assert!(v["run"]["writer"]
        .as_str()
        .unwrap()
        .contains(&format!("PID {}", std::process::id())));
    assert_eq!(
        std::fs::read(lock.path()).unwrap(),
        lock_text,
        "report only reads"
    );
    drop(lock);
    // The writer died without recording an end: killed, not in progress.
    let out = report(dir, &[]);
    let v = verdict_json(dir);
    assert_eq!(v["run"]["status"], "killed");
    // Every planned setpoint is in the journal, so the run is complete all the same.
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
}

#[test]
fn caused_by_lines_do_not_repeat_the_message() {
    // An empty directory: the manifest is missing. The error travels through three
    // wrappers that each print it (transparent, `{path}: {source}`, the OS error).
    let tmp = tempfile::tempdir().unwrap();
    let out = report(tmp.path(), &[]);
    assert_eq!(out.status.code(), Some(2));
    let e = stderr(&out);
    assert_eq!(e.matches("No such file or directory").count(), 1, "{e}");
    assert_eq!(e.matches("manifest.json").count(), 1, "{e}");
    assert!(e.starts_with("error: analysing run directory"), "{e}");
    assert!(e.contains("  caused by: "), "{e}");
}

/// The base64 PNG of `<figure id="ID">` in the page, decoded.
fn embedded_png(html: &str, id: &str) -> image::RgbImage {
    use base64::Engine;
    let at = html
        .find(&format!("<figure id=\"{id}\""))
        .unwrap_or_else(|| panic!("figure {id} missing"));
    let rest = &html[at..];
    let start = rest.find("base64,").unwrap() + 7;
    let end = start + rest[start..].find('"').unwrap();
    let bytes = base64::engine::general_purpose::STANDARD
        .decode(&rest[start..end])
        .unwrap();
    image::load_from_memory(&bytes)
        .unwrap_or_else(|e| panic!("figure {id}: {e}"))
        .to_rgb8()
}

/// A loaded run's force field is an fz map with a colour bar and arrows; the caption
/// states the arrow scale (in the plan's unit, gf per mm) and why there is no σ panel.
#[test]
fn force_field_is_a_heat_map_with_arrow_scale_and_colour_bar() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    magnitude_run(dir);
    let out = report(dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    let img = embedded_png(&html, "force_field");
    // Both ends of the diverging scale are drawn (colour bar), and the pressing
    // cells are red.
    let near = |c: [u8; 3], p: &image::Rgb<u8>| {
        p.0.iter()
            .zip(c)
            .all(|(a, b)| (*a as i32 - b as i32).abs() <= 3)
    };
    let red = img.pixels().filter(|p| near([178, 24, 43], p)).count();
    let blue = img.pixels().filter(|p| near([33, 102, 172], p)).count();
    assert!(red > 200 && blue > 20, "red {red}, blue {blue}");
    assert!(html.contains("gf per mm of arrow"), "arrow scale missing");
    assert!(html.contains("No per-node uncertainty"), "σ note missing");
    assert!(!html.contains("class=\"no-force-field\""));
}

/// Table I shifts the whole sensor with no load: no force field is drawn even when
/// the run has forces files, and the page says why.
#[test]
fn unloaded_displacement_run_has_no_force_field_and_says_why() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write_run(dir, DISPLACEMENT, |dir, r| {
        write_displacements(dir, r.index, |_, _, _| [0.15, 0.0]);
        // What a solver returns for a rigid shift: not a force.
        write_forces(dir, r.index, |q| 0.1 * (q[0] - 9.0));
    });
    let out = report(dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    assert!(!dir.join("plots/force_field.png").exists());
    assert!(!html.contains("<figure id=\"force_field\""));
    let note = html
        .split("<p class=\"no-force-field\">")
        .nth(1)
        .expect("no reason given for the missing force field");
    assert!(note.contains("displacement sweep") && note.contains("not a measured force"));
    // The synthetic track files have no tracker columns: said, not drawn.
    assert!(html.contains("class=\"no-camera-evidence\""));
}

/// A run whose setpoints were tracked from real frames shows the reference and the
/// chosen loaded frames, cropped, with markers in their status colours and arrows.
#[test]
fn camera_evidence_shows_reference_and_loaded_frames_with_statuses() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    magnitude_run(dir);
    // Real frames: the flat-punch scene rendered, tracked by `tactbench track`.
    let scene = tmp.path().join("scene");
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = run(&[
        "sim",
        "render",
        "--scene",
        root.join("experiments/scenes/fig4_flat_910gf.toml")
            .to_str()
            .unwrap(),
        "--out",
        scene.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    std::fs::create_dir_all(dir.join("frames")).unwrap();
    std::fs::copy(
        scene.join("reference.png"),
        dir.join("frames/reference.png"),
    )
    .unwrap();
    std::fs::copy(scene.join("frame_000.png"), dir.join("frames/loaded.png")).unwrap();
    let sensor_path = root.join("experiments/paper_sensor.toml");
    let out = crate::util::run_in(
        dir,
        &[
            "track",
            "--sensor",
            sensor_path.to_str().unwrap(),
            "--reference",
            "frames/reference.png",
            "frames/loaded.png",
            "--out",
            "track.csv",
        ],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    let run_data = tactbench::analysis::RunData::load(dir).unwrap();
    let chosen = tactbench::report::evidence::chosen_setpoints(&run_data);
    assert_eq!(chosen.len(), 2, "{chosen:?}");
    for &i in &chosen {
        std::fs::copy(dir.join("track.csv"), displacements_path(dir, i)).unwrap();
    }
    let out = report(dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    assert!(html.contains("id=\"camera-evidence\""));
    let green = |img: &image::RgbImage| {
        img.pixels()
            .filter(|p| p.0[0] < 40 && p.0[1] > 170 && p.0[2] < 100)
            .count()
    };
    let yellow = |img: &image::RgbImage| {
        img.pixels()
            .filter(|p| p.0[0] > 220 && p.0[1] > 200 && p.0[2] < 60)
            .count()
    };
    let reference = embedded_png(&html, "camera_reference");
    assert!(green(&reference) > 1000, "reference: markers not circled");
    assert_eq!(yellow(&reference), 0, "the reference has no displacements");
    for &i in &chosen {
        let stem = format!("camera_{i:05}");
        let img = embedded_png(&html, &stem);
        // Cropped (the markers span less than the 430 × 340 frame) and enlarged.
        assert!(img.width() >= 430, "{stem}: {}", img.width());
        assert!(green(&img) > 1000, "{stem}: ok markers not circled");
        assert!(yellow(&img) > 50, "{stem}: no displacement arrows");
        let file = image::open(dir.join("plots").join(format!("{stem}.png"))).unwrap();
        assert_eq!(file.to_rgb8(), img, "{stem}: plots/ and the page differ");
    }
    // Scale and statuses are stated.
    assert!(html.contains("drawn ×") && html.contains("green ok"));
}

// ---- issue 33: failed rows, edited journals, digests, provenance -----------------

/// Sets column `name` of journal line `line` (1-based, header = 1) to `value`.
fn set_journal_field(dir: &Path, line: usize, name: &str, value: &str) {
    let path = dir.join("journal.csv");
    let text = std::fs::read_to_string(&path).unwrap();
    let mut lines: Vec<String> = text.lines().map(String::from).collect();
    let col = lines[0].split(',').position(|c| c == name).unwrap();
    let mut fields: Vec<String> = lines[line - 1].split(',').map(String::from).collect();
    fields[col] = value.to_string();
    lines[line - 1] = fields.join(",");
    std::fs::write(&path, lines.join("\n") + "\n").unwrap();
}

/// Swaps the values of two columns in every row (the header left as it is).
fn swap_journal_columns(dir: &Path, a: &str, b: &str) {
    let path = dir.join("journal.csv");
    let text = std::fs::read_to_string(&path).unwrap();
    let header: Vec<&str> = text.lines().next().unwrap().split(',').collect();
    let (ia, ib) = (
        header.iter().position(|c| *c == a).unwrap(),
        header.iter().position(|c| *c == b).unwrap(),
    );
    let mut out = String::new();
    for (i, l) in text.lines().enumerate() {
        let mut f: Vec<&str> = l.split(',').collect();
        if i > 0 {
            f.swap(ia, ib);
        }
        out.push_str(&f.join(","));
        out.push('\n');
    }
    std::fs::write(&path, out).unwrap();
}

/// Issue 33, item 1: older versions journalled a failed reconstruction as `NaN`, and
/// `report` then refused the whole journal ("value NaN is not a finite number"). The
/// reader now treats such a row as a failed row: skipped, counted, named; the run is
/// at most MARGINAL.
#[test]
fn an_old_journal_with_nan_force_sums_reports_with_the_row_skipped() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    magnitude_run(dir);
    for c in ["fsum_x_n", "fsum_y_n", "fsum_z_n"] {
        set_journal_field(dir, 3, c, "NaN");
    }
    let criteria = dir.join("criteria.toml");
    std::fs::write(
        &criteria,
        "[[criterion]]\nmetric = \"magnitude.r2\"\nmin = 0.5\n",
    )
    .unwrap();
    let o = report(dir, &["--acceptance", criteria.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let err = stderr(&o);
    assert!(
        err.contains("1 failed row(s)") && err.contains("setpoint 1 (journal line 3)"),
        "{err}"
    );
    assert!(err.contains("`fsum_x_n` is NaN"), "{err}");
    let v = util::json(&dir.join("verdict.json"));
    assert_eq!(v["outcome"], "MARGINAL", "{v}");
    assert_eq!(v["run"]["measured_setpoints"], 12);
    assert_eq!(metric(dir, "run.rows"), 11.0);
    assert_eq!(metric(dir, "run.failed_rows"), 1.0);
    // The fit is that of the other eleven rows (one trial error no longer cancels).
    assert!((metric(dir, "magnitude.slope") - 0.95).abs() < 0.01);
    // Without criteria: NOT JUDGED, still saying so.
    let o = report(dir, &[]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("1 failed row(s) skipped"),
        "{}",
        stdout(&o)
    );
}

/// Issue 33, item 9: a journal with two columns' values swapped, or its header
/// reordered, was analysed without a word (fz of −31 N on a 0–2.9 N plan). Values
/// that cannot have been measured under the plan, and a header that is not the one
/// the runner writes, are refused naming line, column and value.
#[test]
fn a_journal_with_swapped_columns_or_a_reordered_header_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    // fz beyond the plan's safety limit (no journalled mean can exceed it).
    let dir = tmp.path().join("fz");
    std::fs::create_dir_all(&dir).unwrap();
    magnitude_run(&dir);
    set_journal_field(&dir, 5, "fz_n", "-31.0");
    let o = report(&dir, &[]);
    assert_eq!(o.status.code(), Some(2), "{}", stdout(&o));
    let err = stderr(&o);
    assert!(
        err.contains("line 5, column `fz_n`")
            && err.contains("-31")
            && err.contains("safety limit"),
        "{err}"
    );
    // Two columns' values swapped: the swept value is no longer the plan's.
    let dir = tmp.path().join("swap");
    std::fs::create_dir_all(&dir).unwrap();
    magnitude_run(&dir);
    swap_journal_columns(&dir, "swept_value", "fz_n");
    let err = stderr(&report(&dir, &[]));
    assert!(
        err.contains("column `swept_value`") && err.contains("edited after the run"),
        "{err}"
    );
    // The header reordered (values left): refused by the header check.
    let dir = tmp.path().join("header");
    std::fs::create_dir_all(&dir).unwrap();
    magnitude_run(&dir);
    let path = dir.join("journal.csv");
    let text = std::fs::read_to_string(&path).unwrap();
    std::fs::write(&path, text.replacen("fz_n,mx_nm", "mx_nm,fz_n", 1)).unwrap();
    let o = report(&dir, &[]);
    assert_eq!(o.status.code(), Some(2));
    let err = stderr(&o);
    assert!(
        err.contains("line 1")
            && err.contains("column 9 is `mx_nm` where a tactbench journal has `fz_n`"),
        "{err}"
    );
}

/// Issue 33, item 9: the manifest's digests (taken by the runner) make an edit that
/// stays plausible visible: "modified after the run", and a judged run FAILs.
#[test]
fn a_journal_modified_after_the_run_is_named_by_its_digest() {
    use tactbench::bench::integrity::RecordDigests;
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    magnitude_run(dir);
    let mut m = Manifest::read(dir).unwrap();
    m.record = Some(
        RecordDigests::journal_now(dir, Default::default(), 12, "2026-11-22T01:10:00Z".into())
            .unwrap(),
    );
    m.write(dir).unwrap();
    let criteria = dir.join("criteria.toml");
    std::fs::write(
        &criteria,
        "[[criterion]]\nmetric = \"magnitude.r2\"\nmin = 0.5\n",
    )
    .unwrap();
    let o = report(dir, &["--acceptance", criteria.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(!stderr(&o).contains("modified"), "{}", stderr(&o));
    // A plausible edit: one force sum changed.
    set_journal_field(dir, 4, "fsum_z_n", "0.5");
    let o = report(dir, &["--acceptance", criteria.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1), "{}", stdout(&o));
    assert!(
        stderr(&o).contains("journal.csv modified after the run"),
        "{}",
        stderr(&o)
    );
    let v = util::json(&dir.join("verdict.json"));
    assert_eq!(v["outcome"], "FAIL");
    assert!(v["summary"]
        .as_str()
        .unwrap()
        .contains("RECORD MODIFIED AFTER THE RUN"));
    assert_eq!(v["run"]["record"]["recorded"], true);
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    assert!(html.contains("modified after the run"));
}

/// Issue 33, item 5: a bench whose camera reads recorded PNGs (`dir:`) and whose stage
/// reports the tactbench simulator's firmware was judged "real bench" by
/// `require_real_bench`. Every device must be real; the report names the device.
#[test]
fn a_replayed_camera_or_a_simulator_firmware_is_not_a_real_bench() {
    let tmp = tempfile::tempdir().unwrap();
    let criteria = tmp.path().join("real.toml");
    std::fs::write(&criteria, "require_real_bench = true\n").unwrap();
    for (name, devices, word, needle) in [
        (
            "dir",
            serde_json::json!({"stage": {"protocol": "grbl", "version": "1.1h"},
                "force_sensor": {"protocol": "dynpick", "firmware": "DynPick 2.0"},
                "camera": "Dir(\"recorded\")"}),
            "REPLAYED",
            "camera: the camera reads recorded frames",
        ),
        (
            "fw",
            serde_json::json!({"stage": {"protocol": "marlin", "firmware": "Marlin 2.1.2.1 (tactbench simulator)"},
                "force_sensor": {"protocol": "dynpick", "firmware": "DynPick 2.0"},
                "camera": "V4l(0)"}),
            "SIMULATED",
            "stage: the stage reports a simulator's firmware",
        ),
    ] {
        let dir = tmp.path().join(name);
        std::fs::create_dir_all(&dir).unwrap();
        magnitude_run(&dir);
        let mut m = Manifest::read(&dir).unwrap();
        m.simulated = Some(false);
        m.devices = devices;
        m.write(&dir).unwrap();
        let o = report(&dir, &["--acceptance", criteria.to_str().unwrap()]);
        assert_eq!(o.status.code(), Some(1), "{name}: {}", stdout(&o));
        let so = stdout(&o);
        assert!(
            so.contains(&format!("bench: {word} ({needle}")),
            "{name}: {so}"
        );
        assert!(so.contains("FAIL provenance: real_bench"), "{name}: {so}");
        let v = util::json(&dir.join("verdict.json"));
        assert_ne!(v["provenance"]["bench_kind"], "real bench", "{name}");
    }
}
