//! The figures the front pages quote from the committed reproduction are the figures
//! the reproduction recorded (issue 32, item 4): every claim below is checked against
//! the `verdict.json` of the committed run it comes from, so a regenerated
//! reproduction whose numbers moved fails here until the pages say the new numbers.
//!
//! Two kinds of claim are checked:
//! - the metrology table of `reports/paper/README.md`, parsed row by row (the metric
//!   name in backticks, the run link, the value and its 95 % interval);
//! - quoted figures in `reports/paper/README.md`, `docs/paper-reproduction.md` and
//!   `docs/real-sensors.md`, listed in [`QUOTES`] with the metric they quote.

use std::fs;
use std::path::PathBuf;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// One metric of a committed run's verdict.json: value and 95 % interval.
fn metric(run: &str, name: &str) -> (f64, Option<(f64, f64)>) {
    let path = root()
        .join("reports/paper/runs")
        .join(run)
        .join("verdict.json");
    let text = fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let doc: serde_json::Value = serde_json::from_str(&text).unwrap();
    let m = doc["metrics"]
        .as_array()
        .unwrap()
        .iter()
        .find(|m| m["name"] == name)
        .unwrap_or_else(|| panic!("{}: no metric {name}", path.display()));
    let v = m["value"].as_f64().unwrap();
    let ci = m["ci95"]
        .as_object()
        .map(|c| (c["low"].as_f64().unwrap(), c["high"].as_f64().unwrap()));
    (v, ci)
}

/// Whether `text` (a number as a page prints it, e.g. "97.8", "0.9995") is `value`
/// rounded to the digits `text` shows.
fn shows(text: &str, value: f64) -> bool {
    let decimals = text.split('.').nth(1).map_or(0, str::len);
    format!("{value:.decimals$}") == text || format!("{:.decimals$}", value + 0.0) == text
}

/// (page, the text it quotes, run, metric, the number inside the text, scale from the
/// metric's unit to the quoted one).
const QUOTES: &[(&str, &str, &str, &str, &str, f64)] = &[
    (
        "reports/paper/README.md",
        "| 0.0141 px |",
        "table1_displacement",
        "displacement.max_sd_px",
        "0.0141",
        1.0,
    ),
    (
        "reports/paper/README.md",
        "| 0.0019 px |",
        "table1_displacement",
        "displacement.max_abs_bias_px",
        "0.0019",
        1.0,
    ),
    (
        "reports/paper/README.md",
        "| 3.9 gf |",
        "fig7_magnitude",
        "magnitude.resolution_gf",
        "3.9",
        1.0,
    ),
    (
        "reports/paper/README.md",
        "| 97.8 gf |",
        "fig7_magnitude_camera_noise",
        "magnitude.resolution_gf",
        "97.8",
        1.0,
    ),
    (
        "reports/paper/README.md",
        "| 0.9995 |",
        "fig7_magnitude",
        "magnitude.r2",
        "0.9995",
        1.0,
    ),
    (
        "reports/paper/README.md",
        "| 0.83° |",
        "fig8_angle",
        "angle.resolution_deg",
        "0.83",
        1.0,
    ),
    (
        "reports/paper/README.md",
        "| 2.31 mm |",
        "fig9_spatial",
        "spatial.fwhm_mm",
        "2.31",
        1.0,
    ),
    (
        "reports/paper/README.md",
        "| 0.315 ms |",
        "fig7_magnitude",
        "timing.forces_ms",
        "0.315",
        1.0,
    ),
    (
        "docs/paper-reproduction.md",
        "| 0.0141 px |",
        "table1_displacement",
        "displacement.max_sd_px",
        "0.0141",
        1.0,
    ),
    (
        "docs/paper-reproduction.md",
        "3.9 gf / 97.8 gf",
        "fig7_magnitude",
        "magnitude.resolution_gf",
        "3.9",
        1.0,
    ),
    (
        "docs/paper-reproduction.md",
        "3.9 gf / 97.8 gf",
        "fig7_magnitude_camera_noise",
        "magnitude.resolution_gf",
        "97.8",
        1.0,
    ),
    (
        "docs/paper-reproduction.md",
        "| 0.83° |",
        "fig8_angle",
        "angle.resolution_deg",
        "0.83",
        1.0,
    ),
    (
        "docs/paper-reproduction.md",
        "| 2.31 mm |",
        "fig9_spatial",
        "spatial.fwhm_mm",
        "2.31",
        1.0,
    ),
    (
        "docs/paper-reproduction.md",
        "| 0.315 ms (",
        "fig7_magnitude",
        "timing.forces_ms",
        "0.315",
        1.0,
    ),
    (
        "docs/paper-reproduction.md",
        "6.17 %FS (5.51–7.00)",
        "fig7_magnitude_camera_noise",
        "metrology.repeatability_pct_fs",
        "6.17",
        1.0,
    ),
    (
        "docs/paper-reproduction.md",
        "4.98 %FS (4.30–9.64)",
        "fig7_magnitude_camera_noise",
        "metrology.interpolation_pct_fs",
        "4.98",
        1.0,
    ),
    (
        "docs/real-sensors.md",
        "| 4.2 gf | 3.9 gf |",
        "fig7_magnitude",
        "magnitude.resolution_gf",
        "3.9",
        1.0,
    ),
    (
        "docs/real-sensors.md",
        "| 98.1 gf | 97.8 gf (CI 87.7–110.6) |",
        "fig7_magnitude_camera_noise",
        "magnitude.resolution_gf",
        "97.8",
        1.0,
    ),
    (
        "docs/real-sensors.md",
        "| 0.80° | 0.83° |",
        "fig8_angle",
        "angle.resolution_deg",
        "0.83",
        1.0,
    ),
];

fn read(rel: &str) -> String {
    let p = root().join(rel);
    fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

#[test]
fn quoted_reproduction_figures_are_the_committed_runs_figures() {
    let mut wrong = Vec::new();
    for &(page, quote, run, name, number, scale) in QUOTES {
        assert!(quote.contains(number), "{quote:?} must contain {number}");
        if !read(page).contains(quote) {
            wrong.push(format!(
                "{page}: no longer says {quote:?} (update QUOTES with the page)"
            ));
            continue;
        }
        let (v, _) = metric(run, name);
        if !shows(number, v * scale) {
            wrong.push(format!(
                "{page}: says {number} for {run} {name}, the committed run records {v}"
            ));
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

/// A row of the metrology table: `| label (`metric`) | [run](runs/RUN/report.html) |
/// VALUE UNIT | LO – HI (method) |`.
struct Row {
    metric: String,
    run: String,
    value: String,
    /// The unit the page prints (`gf` for a metric recorded in N is converted).
    unit: String,
    ci: Option<(String, String)>,
}

/// Scale from a metric's recorded unit to the unit a page prints it in.
fn page_scale(metric: &str, unit: &str) -> f64 {
    if metric.ends_with("_n") && unit == "gf" {
        1.0 / 0.00980665
    } else {
        1.0
    }
}

fn metrology_rows(text: &str) -> Vec<Row> {
    let mut rows = Vec::new();
    for line in text.lines().filter(|l| l.starts_with("| ")) {
        let cells: Vec<&str> = line.trim_matches('|').split(" | ").map(str::trim).collect();
        if cells.len() != 4 {
            continue;
        }
        let Some(metric) = cells[0].split('`').nth(1) else {
            continue;
        };
        let Some(run) = cells[1]
            .split("runs/")
            .nth(1)
            .and_then(|r| r.split('/').next())
        else {
            continue;
        };
        let mut words = cells[2].split_whitespace();
        let value = words.next().unwrap_or("").to_string();
        let unit = words.next().unwrap_or("").to_string();
        let ci = cells[3]
            .split(" (")
            .next()
            .and_then(|r| r.split_once(" – "))
            .map(|(a, b)| (a.to_string(), b.to_string()));
        rows.push(Row {
            metric: metric.to_string(),
            run: run.to_string(),
            value,
            unit,
            ci,
        });
    }
    rows
}

#[test]
fn the_reproduction_metrology_table_is_the_committed_runs_verdicts() {
    let text = read("reports/paper/README.md");
    let rows = metrology_rows(&text);
    assert!(
        rows.len() >= 10,
        "the metrology table has {} rows: parser out of date",
        rows.len()
    );
    let mut wrong = Vec::new();
    for r in &rows {
        let (v, ci) = metric(&r.run, &r.metric);
        let k = page_scale(&r.metric, &r.unit);
        let (v, ci) = (v * k, ci.map(|(l, h)| (l * k, h * k)));
        if !shows(&r.value, v) {
            wrong.push(format!(
                "{} {}: page {} against recorded {v}",
                r.run, r.metric, r.value
            ));
        }
        if let (Some((lo, hi)), Some((l, h))) = (&r.ci, ci) {
            if !shows(lo, l) || !shows(hi, h) {
                wrong.push(format!(
                    "{} {}: page CI {lo} – {hi} against recorded {l} – {h}",
                    r.run, r.metric
                ));
            }
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

#[test]
fn a_figure_that_moved_is_caught() {
    // The check itself: a page saying 3.8 where the run records 3.94575 fails, and the
    // rounding rule accepts the digits a page shows.
    assert!(shows("3.9", 3.94575));
    assert!(!shows("3.8", 3.94575));
    assert!(shows("0.315", 0.31464));
    assert!(!shows("0.108", 0.31464));
    let rows = metrology_rows(
        "| repeatability (`metrology.repeatability_pct_fs`) | [x](runs/fig7_magnitude_camera_noise/report.html) | 6.18 %FS | 5.51 – 7.00 (chi2) |",
    );
    let (v, _) = metric(&rows[0].run, &rows[0].metric);
    assert!(!shows(&rows[0].value, v));
}

/// A merge once committed its conflict markers into ARCHITECTURE.md: no text file of
/// the repository may hold a line that starts with one.
#[test]
fn no_file_holds_merge_conflict_markers() {
    let markers = [format!("{} ", "<".repeat(7)), format!("{} ", ">".repeat(7))];
    let mut found = Vec::new();
    let mut stack = vec![crate::util::root("")];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            let name = p.file_name().unwrap().to_string_lossy().to_string();
            if p.is_dir() {
                if !name.starts_with('.') && name != "target" && name != "runs" {
                    stack.push(p);
                }
                continue;
            }
            let Ok(text) = std::fs::read_to_string(&p) else {
                continue; // binary files
            };
            for (i, line) in text.lines().enumerate() {
                if markers.iter().any(|m| line.starts_with(m.as_str())) {
                    found.push(format!("{}:{}", p.display(), i + 1));
                }
            }
        }
    }
    assert!(found.is_empty(), "conflict markers: {found:?}");
}
