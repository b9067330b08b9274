//! The self-contained HTML report: one large verdict banner first (outcome, run
//! status, measured/planned setpoints, build id), then the acceptance verdicts,
//! provenance, metrics, the analysis tables (or why an analysis is absent) and the
//! figures embedded as base64 PNG data URIs (one file, no external resources).
//! Everything taken from the run's files is HTML-escaped.

use std::fmt::Write;

use base64::Engine;

use super::acceptance::{fmt_value, Outcome, Verdict};
// The escaping lives in `markup` so the table builders (`headline`, `evidence`) need
// not import this page; re-exported here under its old path.
pub use super::markup::escape;
use super::verdict::VerdictDoc;
use crate::analysis::calibration::Calibration;
use crate::analysis::tracking::TrackingAnalysis;
use crate::analysis::{Metric, RunAnalysis};

/// One embedded figure.
#[derive(Debug, Clone)]
pub struct EmbeddedFigure {
    /// File stem (also the anchor id).
    pub stem: String,
    /// Caption text.
    pub caption: String,
    /// PNG bytes.
    pub png: Vec<u8>,
}

const STYLE: &str = "body{font-family:sans-serif;max-width:70em;margin:1em auto;padding:0 1em;color:#222}\
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #bbb;padding:2px 8px;text-align:right}\
th{background:#eee}td.l,th.l{text-align:left}.pass{color:#070;font-weight:bold}.fail{color:#b00;font-weight:bold}\
pre{background:#f6f6f6;padding:.5em;overflow:auto}figure{margin:1em 0}img{max-width:100%}\
.marginal{color:#a60;font-weight:bold}small code{color:#666}\
#verdict{border:4px solid;border-radius:8px;padding:.6em 1em;margin:.5em 0 1em}\
#verdict .outcome{font-size:3em;font-weight:bold;line-height:1.1}\
#verdict.PASS{border-color:#070;background:#efe}#verdict.PASS .outcome{color:#070}\
#verdict.MARGINAL{border-color:#c80;background:#fff6e0}#verdict.MARGINAL .outcome{color:#a60}\
#verdict.FAIL{border-color:#b00;background:#fee}#verdict.FAIL .outcome{color:#b00}\
#verdict.INCOMPLETE{border-color:#555;background:#eee}#verdict.INCOMPLETE .outcome{color:#333}\
#verdict.NOT_JUDGED{border-color:#468;background:#eef2f7}#verdict.NOT_JUDGED .outcome{color:#346}\
.simflag{display:inline-block;border:2px solid #804;color:#804;font-weight:bold;padding:0 .4em;margin-left:.5em;border-radius:4px;font-size:.4em;vertical-align:middle}\
#verdict table{margin:.3em 0}#verdict td,#verdict th{border:none;padding:1px 8px 1px 0}";

/// The verdict banner: the first thing on the page.
fn banner(o: &mut String, v: &VerdictDoc) {
    let r = &v.run;
    let status = if r.in_progress {
        format!(
            "in progress: {}",
            r.writer.as_deref().unwrap_or("a live writer holds the run")
        )
    } else {
        r.status.clone()
    };
    let _ = write!(
        o,
        "<section id=\"verdict\" class=\"{}\">\n<div class=\"outcome\">{}{}</div>\n\
         <p>{}</p>\n<table>\n",
        v.outcome.token(),
        v.outcome.word(),
        if v.simulated == Some(true) {
            "<span class=\"simflag\">SIMULATED</span>"
        } else {
            ""
        },
        escape(&v.summary)
    );
    let items = [
        ("run status", escape(&status)),
        (
            "setpoints measured / planned",
            format!(
                "{} / {}{}",
                r.measured_setpoints,
                r.planned_setpoints,
                r.limit.map_or(String::new(), |n| format!(" (--limit {n})"))
            ),
        ),
        (
            "build id",
            v.provenance
                .build_id
                .as_deref()
                .map_or("&mdash; (none recorded)".to_string(), escape),
        ),
        ("bench", escape(&bench_line(v))),
    ];
    for (k, val) in items {
        let _ = writeln!(
            o,
            "<tr><th class=\"l\">{k}</th><td class=\"l\">{val}</td></tr>"
        );
    }
    if let Some(why) = &r.incomplete_reason {
        let _ = writeln!(
            o,
            "<tr><th class=\"l\">incomplete</th><td class=\"l\">{}</td></tr>",
            escape(why)
        );
    }
    if let Some(w) = &r.write_failure {
        let _ = writeln!(
            o,
            "<tr><th class=\"l\">write failure</th><td class=\"l\">{}</td></tr>",
            escape(&w.to_string())
        );
    }
    if !r.failed_rows.is_empty() {
        let _ = writeln!(
            o,
            "<tr><th class=\"l\">failed rows</th><td class=\"l\">{} row(s) without force, skipped by every analysis: {}</td></tr>",
            r.failed_rows.len(),
            escape(&r.failed_rows.join("; "))
        );
    }
    if r.implausible_rows > 0 {
        let _ = writeln!(
            o,
            "<tr><th class=\"l\">implausible rows</th><td class=\"l\">{} row(s) whose force sum does not fit the F/T reading (quality = implausible)</td></tr>",
            r.implausible_rows
        );
    }
    if r.record.recorded {
        let _ = writeln!(
            o,
            "<tr><th class=\"l\">record</th><td class=\"l\">{}</td></tr>",
            escape(&r.record.to_string())
        );
    }
    if let Some(t) = &r.torn_journal_line {
        let _ = writeln!(
            o,
            "<tr><th class=\"l\">torn journal</th><td class=\"l\">line {} ({} bytes) was cut \
             mid-write and is not used; the journal file is left as it is</td></tr>",
            t.line, t.bytes
        );
    }
    o.push_str("</table>\n</section>\n");
}

/// The bench line of a report: [`bench_text`] for the built-in simulated bench, a
/// real bench and old manifests; a bench that is simulated or replayed by one of its
/// devices names the device and why.
pub fn bench_line(v: &VerdictDoc) -> String {
    let p = &v.provenance;
    let why: Vec<String> = p
        .device_provenance
        .iter()
        .filter(|d| d.provenance != crate::bench::journal::Provenance::Real)
        .map(|d| format!("{}: {}", d.device, d.why.clone().unwrap_or_default()))
        .collect();
    match p.bench_kind.as_str() {
        "replayed bench" => format!("REPLAYED ({})", why.join("; ")),
        "simulated bench" if p.bench.get("sim").is_none() && !why.is_empty() => {
            format!("SIMULATED ({})", why.join("; "))
        }
        _ => bench_text(v.simulated).to_string(),
    }
}

/// The bench line of a banner: simulated, real, or not recorded (old manifests).
pub fn bench_text(simulated: Option<bool>) -> &'static str {
    match simulated {
        Some(true) => "SIMULATED (the built-in simulated bench, not hardware)",
        Some(false) => "real bench",
        None => "not recorded (manifest from before the simulated flag)",
    }
}

fn row(out: &mut String, cells: &[String]) {
    out.push_str("<tr>");
    for (i, c) in cells.iter().enumerate() {
        let class = if i == 0 { " class=\"l\"" } else { "" };
        let _ = write!(out, "<td{class}>{c}</td>");
    }
    out.push_str("</tr>\n");
}

fn header(out: &mut String, cells: &[&str]) {
    out.push_str("<tr>");
    for (i, c) in cells.iter().enumerate() {
        let class = if i == 0 { " class=\"l\"" } else { "" };
        let _ = write!(out, "<th{class}>{}</th>", escape(c));
    }
    out.push_str("</tr>\n");
}

fn calibration_table(out: &mut String, c: &Calibration, unit: &str, scale: f64) {
    out.push_str("<table>\n");
    header(
        out,
        &[
            &format!("target ({unit})"),
            "n",
            &format!("applied mean ({unit})"),
            &format!("measured mean ({unit})"),
            &format!("measured SD ({unit})"),
            &format!("residual mean ({unit})"),
            &format!("residual SD ({unit})"),
        ],
    );
    for l in &c.levels {
        row(
            out,
            &[
                fmt_value(l.target * scale),
                l.n.to_string(),
                fmt_value(l.applied_mean * scale),
                fmt_value(l.measured_mean * scale),
                fmt_value(l.measured_sd * scale),
                fmt_value(l.residual_mean * scale),
                fmt_value(l.residual_sd * scale),
            ],
        );
    }
    out.push_str("</table>\n");
}

/// Renders the report. `verdicts` is `None` without `--acceptance`; `sections` is
/// ready HTML placed after the figures (force-field note, camera evidence:
/// [`super::evidence::write_sections`]).
#[allow(clippy::too_many_arguments)]
pub fn render(
    analysis: &RunAnalysis,
    verdict: &VerdictDoc,
    metrics: &[Metric],
    verdicts: Option<&[Verdict]>,
    criteria_path: Option<&str>,
    figures: &[EmbeddedFigure],
    sections: &str,
) -> String {
    let run = &analysis.run;
    let m = &run.manifest;
    let mut o = String::new();
    let title = format!("tactbench report: {}", m.plan_name);
    let _ = write!(
        o,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>{}</title><style>{STYLE}</style></head><body>\n",
        escape(&title)
    );
    banner(&mut o, verdict);
    // A run measured with a draft sensor file (`report --allow-draft`): said first.
    if let Some(w) = run
        .sensor
        .draft_warning(std::path::Path::new(&m.sensor_path))
    {
        let _ = writeln!(
            o,
            "<p class=\"draft\" style=\"border:3px solid #b60;padding:.5em\"><b>DRAFT SENSOR FILE</b>: {}; the forces are not measurements.</p>",
            escape(&w)
        );
    }
    let _ = writeln!(o, "<h1>{}</h1>", escape(&title));
    super::headline::headline(&mut o, metrics, verdicts, run.plan.force_unit);

    if let Some(vs) = verdicts {
        let worst = Outcome::combine(
            vs.iter()
                .map(|v| v.outcome)
                .chain(verdict.requirements.iter().map(|r| r.outcome)),
        );
        // On an INCOMPLETE run the criteria are shown but are not the verdict: no
        // coloured PASS next to them.
        let class = if verdict.outcome == Outcome::Incomplete {
            ""
        } else {
            class_of(worst)
        };
        let _ = write!(
            o,
            "<h2>Acceptance</h2>\n<p>criteria: {} &mdash; criteria alone: <span class=\"{class}\">{}</span> \
             ({} of {} passed, {} marginal){}</p>\n<table>\n",
            escape(criteria_path.unwrap_or("")),
            worst.word(),
            vs.iter().filter(|v| v.outcome == Outcome::Pass).count(),
            vs.len(),
            vs.iter().filter(|v| v.outcome == Outcome::Marginal).count(),
            if verdict.outcome == Outcome::Incomplete {
                " &mdash; not the verdict: the run is INCOMPLETE"
            } else {
                ""
            }
        );
        header(&mut o, &["verdict", "metric", "value", "unit", "threshold"]);
        let plan_unit = run.plan.force_unit;
        for v in vs {
            // In the page's force unit, as the metrics are shown.
            let k = super::headline::display_factor(v.unit, plan_unit);
            let shown_unit = if k == 1.0 { v.unit } else { plan_unit.symbol() };
            let value = match (&v.note, v.ci95) {
                (Some(n), _) => escape(n),
                // A fitted parameter: its interval decided MARGINAL.
                (None, Some([lo, hi])) => format!(
                    "{} <small>(95 % CI [{}, {}])</small>",
                    fmt_value(v.value * k),
                    fmt_value(lo * k),
                    fmt_value(hi * k)
                ),
                (None, None) => fmt_value(v.value * k),
            };
            let mut threshold = super::headline::scaled_criterion(&v.criterion, k).to_string();
            if let (Some(n), None, true) = (v.nominal, &v.note, v.criterion.is_nominal_relative()) {
                let limits = match v.limits() {
                    (Some(lo), Some(hi)) => format!("[{}, {}]", fmt_value(lo), fmt_value(hi)),
                    (Some(lo), None) => format!(">= {}", fmt_value(lo)),
                    (None, Some(hi)) => format!("<= {}", fmt_value(hi)),
                    (None, None) => String::new(),
                };
                threshold.push_str(&format!(" (nominal {}: {limits})", fmt_value(n)));
            }
            let _ = writeln!(
                o,
                "<tr class=\"verdict\"><td class=\"l {}\">{}</td><td class=\"l\">{}</td>\
                 <td>{value}</td><td class=\"l\">{}</td><td class=\"l\">{}</td></tr>",
                class_of(v.outcome),
                v.outcome.word(),
                escape(&v.criterion.metric),
                escape(shown_unit),
                escape(&threshold)
            );
        }
        for r in &verdict.requirements {
            let _ = writeln!(
                o,
                "<tr class=\"requirement\"><td class=\"l {}\">{}</td><td class=\"l\">provenance: {}</td>\
                 <td>{}</td><td class=\"l\"></td><td class=\"l\">required</td></tr>",
                class_of(r.outcome),
                r.outcome.word(),
                escape(&r.requirement),
                r.value.as_deref().map_or("(none)".to_string(), escape)
            );
        }
        o.push_str("</table>\n");
    }

    o.push_str("<h2>Provenance</h2>\n<table>\n");
    let opt = |s: &Option<String>| s.as_deref().map_or("&mdash;".to_string(), escape);
    let items: Vec<(&str, String)> = vec![
        ("plan", escape(&m.plan_name)),
        ("plan file", escape(&m.plan_path)),
        ("sweep", escape(run.sweep_kind())),
        ("sensor file", escape(&m.sensor_path)),
        ("build id", opt(&m.build_id)),
        ("software version", escape(&m.software_version)),
        ("started", escape(&m.started_at)),
        (
            "resumed",
            if m.resumed_at.is_empty() {
                "&mdash;".to_string()
            } else {
                escape(&m.resumed_at.join(", "))
            },
        ),
        ("ended", opt(&m.ended_at)),
        ("status", escape(&verdict.run.status)),
        ("end reason", opt(&m.end_reason)),
        ("stop signal", opt(&m.stop_signal)),
        (
            "measurements",
            format!(
                "{} of {} setpoints ({} planned{})",
                run.rows.len(),
                m.setpoints,
                m.planned(),
                m.limit.map_or(String::new(), |n| format!(", --limit {n}"))
            ),
        ),
        ("plan SHA-256", escape(&verdict.provenance.plan_sha256)),
        ("sensor SHA-256", escape(&verdict.provenance.sensor_sha256)),
        ("software commit", opt(&m.software_commit)),
    ];
    for (k, v) in items {
        let _ = writeln!(
            o,
            "<tr><th class=\"l\">{k}</th><td class=\"l\">{v}</td></tr>"
        );
    }
    o.push_str("</table>\n");
    let json = |v: &serde_json::Value| serde_json::to_string_pretty(v).unwrap_or_default();
    let _ = write!(
        o,
        "<h3>Devices</h3>\n<pre>{}</pre>\n<h3>Bench</h3>\n<pre>{}</pre>\n\
         <details><summary>Plan</summary><pre>{}</pre></details>\n\
         <details><summary>Sensor</summary><pre>{}</pre></details>\n",
        escape(&json(&m.devices)),
        escape(&json(&m.bench)),
        escape(&m.plan_toml),
        escape(&m.sensor_toml)
    );

    if !analysis.absent.is_empty() {
        o.push_str("<h2>Analyses not computed</h2>\n<ul class=\"absent\">\n");
        for (name, why) in &analysis.absent {
            let _ = writeln!(o, "<li><b>{}</b>: {}</li>", escape(name), escape(why));
        }
        o.push_str("</ul>\n");
    }

    super::headline::metrics_table(&mut o, metrics, run.plan.force_unit);
    super::headline::iso376_section(&mut o, analysis);

    let unit = run.plan.force_unit;
    let scale = unit.from_newtons(1.0);
    if let Some(mag) = &analysis.magnitude {
        let _ = writeln!(
            o,
            "<h2>Force magnitude (paper Fig. 7)</h2>\n<p>F<sup>sum</sup><sub>z</sub> against the \
             applied Fz of the F/T sensor, per target level, in {}. <span class=\"resolution-method\">\
             Resolution = {}</span> = {} {}.</p>",
            unit.symbol(),
            escape(mag.calibration.resolution_method.describe()),
            fmt_value(mag.calibration.resolution * scale),
            unit.symbol()
        );
        calibration_table(&mut o, &mag.calibration, unit.symbol(), scale);
    }
    if let Some(a) = &analysis.angle {
        let _ = writeln!(
            o,
            "<h2>Force angle (paper Fig. 8)</h2>\n<p>Angle from the normal measured from \
             F<sup>sum</sup> against the applied angle from the F/T wrench, degrees. Bias {} deg, \
             SD {} deg, <span class=\"resolution-method\">resolution ({})</span> {} deg.</p>",
            fmt_value(a.bias_deg),
            fmt_value(a.sd_deg),
            escape(a.calibration.resolution_method.describe()),
            fmt_value(a.calibration.resolution)
        );
        calibration_table(&mut o, &a.calibration, "deg", 1.0);
    }
    if let Some(s) = &analysis.spatial {
        let u = unit.symbol();
        let _ = writeln!(
            o,
            "<h2>Spatial resolution (paper Fig. 9)</h2>\n<p>Full width at half maximum of the \
             normalised fz profile: <b>{} mm</b> (half-maximum crossings at {} and {} mm; maximum \
             {} {u} at {} mm from the load; profiled grid nodes {} mm from the load line).</p>\n\
             <details><summary>profile</summary><table>",
            fmt_value(s.fwhm_mm),
            fmt_value(s.half_left_mm),
            fmt_value(s.half_right_mm),
            fmt_value(s.peak_fz_n * scale),
            fmt_value(s.peak_distance_mm),
            fmt_value(s.line_offset_mm)
        );
        header(
            &mut o,
            &["distance (mm)", &format!("fz ({u})"), "fz / max", "samples"],
        );
        for p in &s.profile {
            row(
                &mut o,
                &[
                    fmt_value(p.distance_mm),
                    fmt_value(p.fz_n * scale),
                    fmt_value(p.normalized),
                    p.n.to_string(),
                ],
            );
        }
        o.push_str("</table></details>\n");
    }
    if let Some(d) = &analysis.displacement {
        o.push_str(
            "<h2>Displacement accuracy (paper Table I)</h2>\n<p>Tracked marker displacements \
             against the commanded shift, per layer and axis.</p>\n<table>\n",
        );
        header(
            &mut o,
            &[
                "layer",
                "axis",
                "commanded (px)",
                "mean (px)",
                "SD (px)",
                "bias (px)",
                "SD (µm)",
                "n",
            ],
        );
        for a in &d.axes {
            row(
                &mut o,
                &[
                    escape(&a.layer),
                    a.axis.to_string(),
                    fmt_value(a.commanded_mm / run.sensor.camera.mm_per_px),
                    fmt_value(a.mean_px),
                    fmt_value(a.sd_px),
                    fmt_value(a.bias_px),
                    fmt_value(a.sd_mm * 1e3),
                    a.n.to_string(),
                ],
            );
        }
        o.push_str("</table>\n<p>lost marker samples: ");
        let lost: Vec<String> = d
            .lost
            .iter()
            .map(|(l, n)| format!("{} {n}", escape(l)))
            .collect();
        o.push_str(&lost.join(", "));
        o.push_str("</p>\n");
    }
    if let Some(t) = &analysis.timing {
        let _ = writeln!(
            o,
            "<h2>Timing (paper Table II)</h2>\n<p>Per frame, over {} rows ({} frames). \
             <i>forces</i> = tracking + reconstruction (the paper's 2.9 ms); <i>rest</i> = \
             move + settle + acquire.</p>\n<table>",
            t.rows, t.frames
        );
        header(
            &mut o,
            &["stage", "mean (ms)", "SD (ms)", "min (ms)", "max (ms)"],
        );
        for s in &t.stages {
            row(
                &mut o,
                &[
                    s.stage.to_string(),
                    fmt_value(s.mean_s * 1e3),
                    fmt_value(s.sd_s * 1e3),
                    fmt_value(s.min_s * 1e3),
                    fmt_value(s.max_s * 1e3),
                ],
            );
        }
        o.push_str("</table>\n");
    }

    if let Some(t) = &analysis.tracking {
        marker_health(&mut o, t);
    }

    if !figures.is_empty() || !analysis.missing.is_empty() {
        o.push_str("<h2>Figures</h2>\n");
    }
    if !analysis.missing.is_empty() {
        // An archived run (or one whose evidence files were removed): each thing not
        // shown, in one line; every metric above comes from the journal.
        o.push_str("<ul class=\"missing-evidence\">\n");
        for m in &analysis.missing {
            let _ = writeln!(o, "<li>Not shown: {}.</li>", escape(m));
        }
        o.push_str("</ul>\n");
    }
    let b64 = base64::engine::general_purpose::STANDARD;
    for f in figures {
        let _ = writeln!(
            o,
            "<figure id=\"{}\"><img alt=\"{}\" src=\"data:image/png;base64,{}\">\
             <figcaption>{}</figcaption></figure>",
            escape(&f.stem),
            escape(&f.caption),
            b64.encode(&f.png),
            escape(&f.caption)
        );
    }
    o.push_str(sections);
    let _ = writeln!(
        o,
        "<hr><p><small>generated by tactbench {}</small></p></body></html>",
        escape(env!("CARGO_PKG_VERSION"))
    );
    o
}

/// The marker-health section: a summary line, and a table of the rows that were
/// re-acquired, flagged or below the gate (flagged rows marked).
fn marker_health(o: &mut String, t: &TrackingAnalysis) {
    let flagged = t.flagged().count();
    let _ = writeln!(
        o,
        "<h2>Marker health</h2>\n<p>Fraction of the sensor's markers ok in every frame of a \
         setpoint: min {}, mean {} over {} rows; gate [quality] min_ok_fraction {}; \
         <span class=\"{}\">{flagged} flagged row(s)</span>, {} re-acquired.{}</p>",
        fmt_value(t.min_ok_fraction()),
        fmt_value(t.mean_ok_fraction()),
        t.setpoints.len(),
        fmt_value(t.gate),
        if flagged > 0 { "fail" } else { "pass" },
        t.reacquired_rows(),
        if t.rows_without_counts > 0 {
            format!(
                " {} row(s) have no marker counts (journalled before these columns).",
                t.rows_without_counts
            )
        } else {
            String::new()
        }
    );
    let notable: Vec<_> = t
        .setpoints
        .iter()
        .filter(|s| s.flagged || s.reacquired > 0 || s.ok_fraction() < t.gate)
        .collect();
    if notable.is_empty() {
        return;
    }
    o.push_str("<table>\n");
    header(
        o,
        &[
            "setpoint",
            "ok",
            "lost",
            "merged",
            "outlier",
            "ok fraction",
            "re-acquired",
            "quality",
        ],
    );
    for s in notable {
        let quality = if s.flagged {
            "<span class=\"fail\">FLAGGED</span>"
        } else {
            "ok"
        };
        let _ = writeln!(
            o,
            "<tr class=\"health{}\"><td class=\"l\">{}</td><td>{}</td><td>{}</td><td>{}</td>\
             <td>{}</td><td>{}</td><td>{}</td><td class=\"l\">{quality}</td></tr>",
            if s.flagged { " flagged" } else { "" },
            s.index,
            s.ok,
            s.lost,
            s.merged,
            s.outlier,
            fmt_value(s.ok_fraction()),
            s.reacquired
        );
    }
    o.push_str("</table>\n");
}

fn class_of(o: Outcome) -> &'static str {
    match o {
        Outcome::NotJudged => "",
        Outcome::Pass => "pass",
        Outcome::Marginal => "marginal",
        Outcome::Fail | Outcome::Incomplete => "fail",
    }
}
