//! `tactbench reproduce-paper` on its short variant: every step runs (runs on the
//! simulated bench, reports, the three studies) and the README puts a figure of ours beside
//! each of the paper's.

use std::path::Path;
use std::process::Output;

use crate::util;

/// `tactbench reproduce-paper --out OUT ARGS…` from the crate root.
fn reproduce(out: &Path, args: &[&str]) -> Output {
    let mut all = vec!["reproduce-paper", "--out", out.to_str().unwrap()];
    all.extend_from_slice(args);
    util::run_in(&util::root(""), &all)
}

#[test]
fn reproduce_paper_quick_variant_writes_every_report_and_a_filled_readme() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("paper");
    let o = reproduce(&out, &["--quick", "2"]);
    assert!(
        o.status.success(),
        "reproduce-paper failed:\n{}",
        util::stderr(&o)
    );

    for run in [
        "table1_displacement",
        "fig7_magnitude",
        "fig8_angle",
        "fig9_spatial",
    ] {
        let d = out.join("runs").join(run);
        for f in ["manifest.json", "journal.csv", "report.html", "summary.csv"] {
            assert!(d.join(f).is_file(), "{run}: {f} missing");
        }
        let plots: Vec<_> = std::fs::read_dir(d.join("plots"))
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|e| e == "png"))
            .collect();
        assert!(!plots.is_empty(), "{run}: no plots");
        for p in plots {
            image::open(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
        }
    }
    for f in [
        "fig6_layer_separation/layer_separation.csv",
        "fig6_layer_separation/layer_separation.png",
        "accuracy_vs_time/accuracy_vs_time.csv",
        "accuracy_vs_time/budgets.csv",
        "accuracy_vs_time/accuracy_vs_time.png",
        "model_error/model_error.csv",
        "model_error/model_error.png",
        "model_error/model_error.svg",
        "model_error/README.md",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }

    let readme = std::fs::read_to_string(out.join("README.md")).unwrap();
    assert!(
        readme.contains("SHORT VARIANT"),
        "quick run not labelled:\n{readme}"
    );
    // Every row of the comparison table has a number of ours (not n/a) beside the
    // paper's figure, except the Fig. 6 row, which points at its plot.
    let (paper_part, metrology_part) = readme
        .split_once("## Beyond the paper: force metrology in the spirit of ISO 376")
        .expect("the metrology section");
    let rows: Vec<&str> = paper_part
        .lines()
        .filter(|l| l.starts_with("| ") && !l.starts_with("| quantity"))
        .collect();
    assert_eq!(rows.len(), 9, "table rows:\n{readme}");
    // The metrology table: one row per metric, each naming its run and metric; a
    // 2-setpoint quick run cannot support most of them, so n/a is allowed here, but
    // the up-down and hold runs exist and were reported.
    let metrology: Vec<&str> = metrology_part
        .lines()
        .take_while(|l| !l.starts_with("## "))
        .filter(|l| l.starts_with("| ") && !l.starts_with("| quantity"))
        .collect();
    assert_eq!(metrology.len(), 12, "metrology rows:\n{readme}");
    for row in &metrology {
        assert!(row.contains("(`") && row.contains("](runs/"), "{row:?}");
    }
    for run in ["updown_viscoelastic", "hold_viscoelastic"] {
        let d = out.join("runs").join(run);
        for f in ["journal.csv", "report.html", "summary.csv", "verdict.json"] {
            assert!(d.join(f).is_file(), "{run}: {f} missing");
        }
    }
    for row in &rows[..8] {
        let ours = row.split('|').nth(3).unwrap().trim();
        let number: String = ours
            .chars()
            .take_while(|c| !c.is_whitespace() && *c != '°')
            .collect();
        assert!(
            number.parse::<f64>().is_ok_and(f64::is_finite),
            "no figure of ours in {row:?}"
        );
    }

    // The model-error headline: the 40 mm and the 3 mm layer, both solvers, in numbers.
    let me: Vec<&str> = readme
        .lines()
        .filter(|l| l.starts_with("- ") && l.contains("mm layer, markers at"))
        .collect();
    assert_eq!(me.len(), 2, "model-error lines:\n{readme}");
    assert!(me[0].starts_with("- 40 mm layer, markers at 3 / 6 mm: F_sum error "));
    assert!(me[1].starts_with("- 3 mm layer, markers at 0.75 / 1.5 mm: F_sum error "));
    assert!(me.iter().all(|l| !l.contains("n/a")), "{me:?}");

    // --readme-only rewrites the README from the outputs already there.
    std::fs::remove_file(out.join("README.md")).unwrap();
    let o = reproduce(&out, &["--quick", "2", "--readme-only"]);
    assert!(
        o.status.success(),
        "--readme-only failed:\n{}",
        util::stderr(&o)
    );
    assert_eq!(
        std::fs::read_to_string(out.join("README.md")).unwrap(),
        readme
    );
}

#[test]
fn reproduce_paper_refuses_to_replace_a_directory_that_is_not_a_run() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("paper");
    let precious = out.join("runs").join("table1_displacement");
    std::fs::create_dir_all(&precious).unwrap();
    std::fs::write(precious.join("notes.txt"), "keep me").unwrap();
    let o = reproduce(&out, &["--quick", "2"]);
    assert!(!o.status.success());
    let err = util::stderr(&o);
    assert!(err.contains("is not a run directory"), "{err}");
    assert_eq!(
        std::fs::read_to_string(precious.join("notes.txt")).unwrap(),
        "keep me"
    );
}

#[test]
fn quick_below_its_minimum_is_refused_when_parsing_and_help_states_the_minimum() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("paper");
    for n in ["1", "0"] {
        let o = reproduce(&out, &["--quick", n]);
        let err = util::stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{err}");
        assert!(
            err.contains("--quick") && err.contains(&format!("N = {n} is below the minimum 2")),
            "{err}"
        );
        assert!(!out.exists(), "refused before anything was created");
    }
    let o = util::run(&["reproduce-paper", "--help"]);
    let help = util::stdout(&o);
    assert!(help.contains("N is at least 2"), "{help}");
}
