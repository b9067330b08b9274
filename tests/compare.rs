//! `tactbench compare` on simulated runs: the same short Fig. 7 magnitude plan on the
//! ideal camera and on the camera with pixel noise (σ = 2 of 255 levels), run through
//! `tactbench run --sim` once for the whole module. The noisy build is named worse on
//! resolution; relative criteria pass and fail as their bounds say and set the exit
//! code; compare.csv has its documented header and one row per (metric, run); the page
//! is self-contained with decodable figures; bad input is a clear error (exit 2); a
//! partial run makes the comparison INCOMPLETE (exit 5) unless --allow-partial.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use base64::Engine;

use tactbench::report::compare::{CSV_HEADER, Z95};

use crate::util::{self, run, stderr, stdout, write};

/// The runs shared by every test here: `ideal`, `noisy` (complete, 8 setpoints each)
/// and `partial` (the ideal scene, `--limit 4`).
struct Runs {
    _tmp: tempfile::TempDir,
    root: PathBuf,
}

impl Runs {
    fn dir(&self, name: &str) -> PathBuf {
        self.root.join(name)
    }
    fn arg(&self, name: &str) -> String {
        self.dir(name).display().to_string()
    }
}

fn sim_run(plan: &Path, scene: &str, out: &Path, build: &str, limit: Option<&str>) {
    let scene = util::root(scene);
    let mut args = vec![
        "run",
        plan.to_str().unwrap(),
        "--sim",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--build-id",
        build,
        "--no-progress",
    ];
    if let Some(n) = limit {
        args.extend(["--limit", n]);
    }
    let o = run(&args);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
}

fn runs() -> &'static Runs {
    static RUNS: OnceLock<Runs> = OnceLock::new();
    RUNS.get_or_init(|| {
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path().to_path_buf();
        let plan = util::eight_setpoint_fig7_plan(&root, "plan.toml");
        sim_run(
            &plan,
            "experiments/scenes/fig7_hemisphere_ramp.toml",
            &root.join("ideal"),
            "build-ideal",
            None,
        );
        sim_run(
            &plan,
            "experiments/scenes/fig7_hemisphere_camera_noise.toml",
            &root.join("noisy"),
            "build-noisy",
            None,
        );
        sim_run(
            &plan,
            "experiments/scenes/fig7_hemisphere_ramp.toml",
            &root.join("partial"),
            "build-partial",
            Some("4"),
        );
        Runs { _tmp: tmp, root }
    })
}

type Row = BTreeMap<String, String>;

/// compare.csv as (header, rows keyed by column name).
fn read_csv(path: &Path) -> (Vec<String>, Vec<Row>) {
    let mut r = csv::Reader::from_path(path).unwrap();
    let header: Vec<String> = r.headers().unwrap().iter().map(String::from).collect();
    let rows = r
        .records()
        .map(|rec| {
            let rec = rec.unwrap();
            header
                .iter()
                .cloned()
                .zip(rec.iter().map(String::from))
                .collect()
        })
        .collect();
    (header, rows)
}

fn row<'a>(rows: &'a [Row], metric: &str, run_dir: &str) -> &'a Row {
    rows.iter()
        .find(|r| r["metric"] == metric && r["run"] == run_dir)
        .unwrap_or_else(|| panic!("no row for {metric} / {run_dir}"))
}

fn num(s: &str) -> f64 {
    s.parse()
        .unwrap_or_else(|e| panic!("{s:?} is not a number: {e}"))
}

#[test]
fn the_noisy_build_is_worse_on_resolution_and_relative_criteria_set_the_exit_code() {
    let r = runs();
    let tmp = tempfile::tempdir().unwrap();
    // Passes: the resolution may grow by 10 kgf, the run must not lose rows. Fails:
    // the resolution no more than 10 % worse than the baseline's.
    let criteria = write(
        tmp.path(),
        "criteria.toml",
        "[[criterion]]\nmetric = \"magnitude.resolution_gf\"\nmax_increase = 10000.0\n\
         [[criterion]]\nmetric = \"run.rows\"\nmin = 1\nmax_decrease = 0.0\nmax_relative_to_baseline = 0.0\n\
         [[criterion]]\nmetric = \"magnitude.resolution_gf\"\nmax_relative_to_baseline = 0.10\n",
    );
    let out = tmp.path().join("cmp");
    let (ideal, noisy) = (r.arg("ideal"), r.arg("noisy"));
    let o = run(&[
        "compare",
        &ideal,
        &noisy,
        "--acceptance",
        criteria.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let text = stdout(&o);
    assert_eq!(o.status.code(), Some(1), "{text}\n{}", stderr(&o));
    assert!(
        text.contains("worst magnitude.resolution_gf: build-noisy"),
        "{text}"
    );
    assert!(text.contains("comparison: FAIL"), "{text}");
    // Each criterion on the compared run, with the baseline's limits.
    let lines: Vec<&str> = text
        .lines()
        .filter(|l| l.starts_with("build-noisy: ") && l.contains(" = "))
        .collect();
    assert_eq!(lines.len(), 3, "{text}");
    assert!(
        lines[0].contains("PASS magnitude.resolution_gf"),
        "{}",
        lines[0]
    );
    assert!(lines[1].contains("PASS run.rows"), "{}", lines[1]);
    assert!(
        lines[2].contains("FAIL magnitude.resolution_gf")
            && lines[2].contains("<= baseline + 10 %"),
        "{}",
        lines[2]
    );
    // The baseline is judged on absolute bounds only (run.rows min = 1).
    assert!(
        text.contains("build-ideal: PASS run.rows = 8 (>= 1)"),
        "{text}"
    );

    // compare.csv: the documented header, one row per (metric, run).
    let (header, rows) = read_csv(&out.join("compare.csv"));
    assert_eq!(header, CSV_HEADER);
    assert_eq!(
        header[..15].join(","),
        "metric,unit,run,build_id,date,value,ci95_low,ci95_high,ci_method,baseline_value,\
         difference,difference_pct,significant,criterion,outcome"
    );
    let metrics: Vec<&String> = rows.iter().map(|r| &r["metric"]).collect();
    let distinct: std::collections::BTreeSet<&String> = metrics.iter().copied().collect();
    assert_eq!(rows.len(), 2 * distinct.len());
    for m in &distinct {
        assert_eq!(metrics.iter().filter(|x| x == &m).count(), 2, "{m}");
    }
    let base_res = row(&rows, "magnitude.resolution_gf", &ideal);
    let res = row(&rows, "magnitude.resolution_gf", &noisy);
    assert_eq!(base_res["role"], "baseline");
    assert_eq!(res["role"], "compared");
    assert_eq!(res["build_id"], "build-noisy");
    assert_eq!(res["unit"], "gf");
    assert_eq!(res["better"], "lower");
    assert_eq!(
        (res["worst"].as_str(), base_res["worst"].as_str()),
        ("yes", "no")
    );
    let (v, b) = (num(&res["value"]), num(&base_res["value"]));
    assert!(v > b, "noisy {v} gf is not above ideal {b} gf");
    assert_eq!(num(&res["baseline_value"]), b);
    assert!((num(&res["difference"]) - (v - b)).abs() <= 1e-9 * v.abs().max(1.0));
    if b != 0.0 {
        let pct = num(&res["difference_pct"]);
        assert!((pct - 100.0 * (v - b) / b.abs()).abs() < 1e-6 * pct.abs().max(1.0));
    }
    assert_eq!(res["outcome"], "FAIL");
    assert!(
        res["criterion"].contains("<= baseline + 10 %"),
        "{}",
        res["criterion"]
    );
    assert!(res["date"].starts_with("20") && res["date"].ends_with('Z'));

    // Significance only where both runs state a CI; otherwise n/a, never "yes".
    for rw in rows.iter().filter(|r| r["role"] == "compared") {
        let base = row(&rows, &rw["metric"], &ideal);
        let has_ci = |r: &Row| !r["ci95_low"].is_empty() && !r["ci95_high"].is_empty();
        if has_ci(rw) && has_ci(base) && !rw["difference"].is_empty() {
            let se = |r: &Row| (num(&r["ci95_high"]) - num(&r["ci95_low"])) / 2.0 / Z95;
            let half = Z95 * se(rw).hypot(se(base));
            let d = num(&rw["difference"]);
            let expected = if d - half > 0.0 || d + half < 0.0 {
                "yes"
            } else {
                "no"
            };
            assert_eq!(rw["significant"], expected, "{rw:?}");
            assert!((num(&rw["difference_ci95_low"]) - (d - half)).abs() < 1e-6 * half.max(1e-9));
        } else {
            assert_eq!(rw["significant"], "n/a", "{rw:?}");
            assert!(rw["difference_ci95_low"].is_empty());
        }
    }

    // The page: self-contained, figures decodable, runs and the worst one named.
    let html = std::fs::read_to_string(out.join("compare.html")).unwrap();
    assert!(html.contains("build-noisy") && html.contains("build-ideal"));
    assert!(html.contains("id=\"verdict\" class=\"FAIL\""));
    assert!(!html.contains("href="), "no links out of the page");
    let srcs: Vec<&str> = html.split("src=\"").skip(1).collect();
    assert!(srcs.len() >= 2, "trend and overlay figures expected");
    let b64 = base64::engine::general_purpose::STANDARD;
    for s in srcs {
        let data = s
            .strip_prefix("data:image/png;base64,")
            .unwrap_or_else(|| panic!("external src: {}", &s[..40.min(s.len())]));
        let end = data.find('"').unwrap();
        let png = b64.decode(&data[..end]).unwrap();
        let img = image::load_from_memory(&png).unwrap();
        assert!(image::GenericImageView::dimensions(&img).0 >= 900);
    }
    for stem in ["compare_trends", "compare_magnitude"] {
        assert!(html.contains(&format!("id=\"{stem}\"")), "{stem} missing");
        let svg = std::fs::read_to_string(out.join("plots").join(format!("{stem}.svg"))).unwrap();
        assert!(svg.starts_with("<svg"));
    }
}

#[test]
fn relative_criteria_follow_the_baseline_and_pass_the_better_build() {
    let r = runs();
    let tmp = tempfile::tempdir().unwrap();
    let criteria = write(
        tmp.path(),
        "criteria.toml",
        "[[criterion]]\nmetric = \"magnitude.resolution_gf\"\nmax_relative_to_baseline = 0.10\n",
    );
    // The noisy build as baseline: the ideal one is better, so within 10 %: exit 0.
    let out = tmp.path().join("cmp");
    let o = run(&[
        "compare",
        &r.arg("ideal"),
        "--baseline",
        &r.arg("noisy"),
        "--acceptance",
        criteria.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let text = stdout(&o);
    assert_eq!(o.status.code(), Some(0), "{text}\n{}", stderr(&o));
    assert!(
        text.contains("build-ideal: PASS magnitude.resolution_gf"),
        "{text}"
    );
    assert!(
        text.contains("worst magnitude.resolution_gf: build-noisy"),
        "{text}"
    );
    let (_, rows) = read_csv(&out.join("compare.csv"));
    let base = row(&rows, "magnitude.resolution_gf", &r.arg("noisy"));
    assert_eq!(base["role"], "baseline");
    // Relative-only criteria are not applied to the baseline itself.
    assert_eq!(base["outcome"], "");
    // Without criteria: exit 0, nothing judged.
    let o = run(&[
        "compare",
        &r.arg("noisy"),
        &r.arg("ideal"),
        "--out",
        tmp.path().join("plain").to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("comparison: NOT JUDGED"),
        "{}",
        stdout(&o)
    );
}

#[test]
fn a_partial_run_makes_the_comparison_incomplete_unless_allow_partial() {
    let r = runs();
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("cmp");
    let args = |extra: &'static [&'static str]| {
        let mut a = vec![
            "compare".to_string(),
            r.arg("ideal"),
            r.arg("partial"),
            "--out".into(),
            out.display().to_string(),
        ];
        a.extend(extra.iter().map(|s| s.to_string()));
        a
    };
    let a = args(&[]);
    let o = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
    assert_eq!(o.status.code(), Some(5), "{}", stdout(&o));
    assert!(
        stdout(&o).contains("comparison: INCOMPLETE"),
        "{}",
        stdout(&o)
    );
    let html = std::fs::read_to_string(out.join("compare.html")).unwrap();
    assert!(html.contains("limited by --limit 4"), "the page says why");
    let a = args(&["--allow-partial"]);
    let o = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
    assert_eq!(o.status.code(), Some(0), "{}", stdout(&o));
    // An incomplete baseline: no grading either.
    let o = run(&[
        "compare",
        &r.arg("partial"),
        &r.arg("ideal"),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(5), "{}", stdout(&o));
    assert!(stdout(&o).contains("the baseline build-partial did not measure its whole plan"));
}

#[test]
fn bad_input_is_a_clear_error_never_a_panic() {
    let r = runs();
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("cmp");
    let out = out.to_str().unwrap();
    let check = |args: &[&str], needles: &[&str]| {
        let o = run(args);
        let e = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {e}");
        assert!(!e.contains("panicked"), "{e}");
        for n in needles {
            assert!(e.contains(n), "{n:?} not in: {e}");
        }
    };
    let (ideal, noisy) = (r.arg("ideal"), r.arg("noisy"));
    // Not a run directory.
    let empty = tmp.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    check(
        &["compare", &ideal, empty.to_str().unwrap(), "--out", out],
        &["not a run directory", "no manifest.json"],
    );
    check(
        &["compare", &ideal, "/no/such/run", "--out", out],
        &["/no/such/run: not a run directory: no such directory"],
    );
    // The same run twice, directly or as a copy.
    check(
        &["compare", &ideal, &ideal, "--out", out],
        &["are the same run", "the same directory"],
    );
    let copy = tmp.path().join("copy");
    std::fs::create_dir(&copy).unwrap();
    for f in ["manifest.json", "journal.csv"] {
        std::fs::copy(r.dir("ideal").join(f), copy.join(f)).unwrap();
    }
    check(
        &["compare", &ideal, copy.to_str().unwrap(), "--out", out],
        &["identical manifest.json and journal.csv"],
    );
    check(
        &["compare", &ideal, "--out", out],
        &["at least two run directories"],
    );
    // Criteria: an unknown metric, a negative relative bound, a relative bound on a
    // metric the baseline lacks (an up-only sweep has no hysteresis).
    let crit = |name: &str, text: &str| write(tmp.path(), name, text).display().to_string();
    let unknown = crit(
        "unknown.toml",
        "[[criterion]]\nmetric = \"magnitude.resolution_furlongs\"\nmax_relative_to_baseline = 0.1\n",
    );
    check(
        &[
            "compare",
            &ideal,
            &noisy,
            "--acceptance",
            &unknown,
            "--out",
            out,
        ],
        &["criterion 1 (`magnitude.resolution_furlongs`): unknown metric"],
    );
    let negative = crit(
        "negative.toml",
        "[[criterion]]\nmetric = \"magnitude.resolution_gf\"\nmax_relative_to_baseline = -0.1\n",
    );
    check(
        &[
            "compare",
            &ideal,
            &noisy,
            "--acceptance",
            &negative,
            "--out",
            out,
        ],
        &["max_relative_to_baseline = -0.1 must be a finite number >= 0"],
    );
    let lacking = crit(
        "lacking.toml",
        "[[criterion]]\nmetric = \"magnitude.hysteresis_pct\"\nmax_relative_to_baseline = 0.1\n",
    );
    check(
        &[
            "compare",
            &ideal,
            &noisy,
            "--acceptance",
            &lacking,
            "--out",
            out,
        ],
        &[
            "magnitude.hysteresis_pct",
            "the baseline run has no value for this metric",
        ],
    );
    // `report` has no baseline: a relative criterion is an error there, not a pass.
    let relative = crit(
        "relative.toml",
        "[[criterion]]\nmetric = \"magnitude.resolution_gf\"\nmax_relative_to_baseline = 0.1\n",
    );
    check(
        &["report", &noisy, "--acceptance", &relative, "--out", out],
        &["needs a baseline", "tactbench compare"],
    );
}

/// "The compare page still shows N on gf plans": the runs' plans are in gf, so the
/// page's table, criteria and figures show forces in gf, and the resolution in N (the
/// same number in the other unit) is left off the page; `compare.csv` keeps each
/// metric's own unit, as `summary.csv` does.
#[test]
fn a_gf_plan_comparison_shows_forces_in_gf_on_the_page_and_in_its_figures() {
    let r = runs();
    let tmp = tempfile::tempdir().unwrap();
    let crit = write(
        tmp.path(),
        "crit.toml",
        "[[criterion]]\nmetric = \"magnitude.residual_sd_n\"\nmax = 5.0\nmax_relative_to_baseline = 1000.0\n",
    );
    let out = tmp.path().join("cmp");
    let o = run(&[
        "compare",
        &r.arg("ideal"),
        &r.arg("noisy"),
        "--acceptance",
        crit.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(matches!(o.status.code(), Some(0 | 1)), "{}", stderr(&o));
    let html = std::fs::read_to_string(out.join("compare.html")).unwrap();
    let n = util::newton_units(&util::page_text(&html));
    assert!(n.is_empty(), "forces in N on a gf comparison: {n:?}");
    assert!(html.contains("where metrics named <code>…_n</code> are in N"));
    assert!(!html.contains("<code>magnitude.resolution_n</code>"));
    assert!(html.contains("<code>magnitude.resolution_gf</code>"));
    // The 5 N limit is shown as 509.9 gf.
    assert!(html.contains("&lt;= 509.858"), "criterion not converted");
    for stem in ["compare_trends", "compare_magnitude"] {
        let svg = std::fs::read_to_string(out.join(format!("plots/{stem}.svg"))).unwrap();
        let n = util::newton_units(&svg);
        assert!(n.is_empty(), "{stem}: forces in N: {n:?}");
        // The legend strip keys every run's colour, above the panels.
        let top = util::svg_top_tick_y(&svg);
        let texts = util::svg_texts(&svg);
        for label in ["build-ideal", "build-noisy"] {
            let y = texts
                .iter()
                .filter(|(_, _, t)| t.starts_with(label))
                .map(|t| t.1)
                .fold(f64::INFINITY, f64::min);
            assert!(y < top - 5.0, "{stem}: {label} at {y}, plot from {top}");
        }
    }
    let trends = std::fs::read_to_string(out.join("plots/compare_trends.svg")).unwrap();
    assert!(trends.contains("magnitude.offset_n [gf]"));
    assert!(!trends.contains("magnitude.resolution_n"));
    let (_, rows) = read_csv(&out.join("compare.csv"));
    assert_eq!(
        row(&rows, "magnitude.offset_n", &r.arg("ideal"))["unit"],
        "N"
    );
    assert_eq!(
        row(&rows, "magnitude.resolution_n", &r.arg("noisy"))["unit"],
        "N"
    );
}
