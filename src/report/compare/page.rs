//! `compare.html`: one self-contained page (figures as base64 PNG data URIs, no
//! external resources). First the comparison's banner, then the runs (with their state
//! and verdicts), every metric side by side with CIs, differences to the baseline and
//! significance, the criteria per run, the method, and the figures. Everything taken
//! from the runs' files is HTML-escaped.

use std::fmt::Write;

use base64::Engine;

use super::figures::RUN_COLORS;
use super::{
    criterion_text_scaled, verdicts_of, Better, ComparedRun, Comparison, MetricComparison,
    Significance, Z95,
};
use crate::report::acceptance::{fmt_value, Outcome};
use crate::report::headline::{display_factor, other_resolution};
use crate::report::html::{escape, EmbeddedFigure};
use crate::units::ForceUnit;

const STYLE: &str = "body{font-family:sans-serif;max-width:90em;margin:1em auto;padding:0 1em;color:#222}\
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #bbb;padding:2px 6px;text-align:right;vertical-align:top}\
th{background:#eee}td.l,th.l{text-align:left}.pass{color:#070;font-weight:bold}.fail{color:#b00;font-weight:bold}\
.marginal{color:#a60;font-weight:bold}.incomplete{color:#555;font-weight:bold}\
.sig{font-weight:bold}.small{font-size:85%;color:#555}td.worst{background:#fde8e8}\
td.base{background:#f3f3f3}figure{margin:1em 0}img{max-width:100%}\
.swatch{display:inline-block;width:.9em;height:.9em;border:1px solid #444;vertical-align:middle;margin-right:.3em}\
#verdict{border:4px solid;border-radius:8px;padding:.6em 1em;margin:.5em 0 1em}\
#verdict .outcome{font-size:3em;font-weight:bold;line-height:1.1}\
#verdict.PASS{border-color:#070;background:#efe}#verdict.PASS .outcome{color:#070}\
#verdict.MARGINAL{border-color:#c80;background:#fff6e0}#verdict.MARGINAL .outcome{color:#a60}\
#verdict.FAIL{border-color:#b00;background:#fee}#verdict.FAIL .outcome{color:#b00}\
#verdict.INCOMPLETE{border-color:#555;background:#eee}#verdict.INCOMPLETE .outcome{color:#333}\
#verdict.NOT_JUDGED{border-color:#468;background:#eef2f7}#verdict.NOT_JUDGED .outcome{color:#346}\
.sim{color:#804;font-weight:bold}";

fn class_of(o: Outcome) -> &'static str {
    match o {
        Outcome::NotJudged => "",
        Outcome::Pass => "pass",
        Outcome::Marginal => "marginal",
        Outcome::Fail => "fail",
        Outcome::Incomplete => "incomplete",
    }
}

fn swatch(i: usize) -> String {
    let (r, g, b) = RUN_COLORS[i % RUN_COLORS.len()];
    format!("<span class=\"swatch\" style=\"background:rgb({r},{g},{b})\"></span>")
}

fn better_text(b: Option<Better>) -> String {
    match b {
        Some(Better::Lower) => "lower".into(),
        Some(Better::Higher) => "higher".into(),
        Some(Better::CloserTo(t)) => format!("closer to {}", fmt_value(t)),
        None => "&mdash;".into(),
    }
}

fn signed(v: f64) -> String {
    if v > 0.0 {
        format!("+{}", fmt_value(v))
    } else {
        fmt_value(v)
    }
}

/// The banner's warnings: runs not like for like, a baseline failing its own
/// criteria, simulated runs and runs whose manifest does not say.
fn banner_flags(c: &Comparison) -> String {
    let mut o = String::new();
    if !c.differences.is_empty() {
        let _ = writeln!(
            o,
            "<p class=\"fail\">NOT LIKE FOR LIKE (--allow-different-plans): {}</p>",
            escape(&c.differences.join("; "))
        );
    }
    if !c.instrument_differences.is_empty() {
        let _ = writeln!(
            o,
            "<p class=\"fail\">DIFFERENT INSTRUMENTS: {}</p>",
            escape(&c.instrument_differences.join("; "))
        );
    }
    if !c.record_warnings.is_empty() {
        let _ = writeln!(
            o,
            "<p class=\"fail\">RECORD MODIFIED AFTER THE RUN: {}</p>",
            escape(&c.record_warnings.join("; "))
        );
    }
    let failed: Vec<String> = c
        .runs
        .iter()
        .filter(|r| !r.verdict.run.failed_rows.is_empty())
        .map(|r| {
            format!(
                "{}: {} failed row(s) skipped",
                r.label,
                r.verdict.run.failed_rows.len()
            )
        })
        .collect();
    if !failed.is_empty() {
        let _ = writeln!(o, "<p>{}</p>", escape(&failed.join("; ")));
    }
    let instruments: Vec<String> = c
        .runs
        .iter()
        .zip(&c.instruments)
        .map(|(r, ins)| {
            let list: Vec<String> = ins
                .devices
                .iter()
                .map(|(d, id)| format!("{d}: {id}"))
                .collect();
            format!("{}: {}", r.label, list.join("; "))
        })
        .collect();
    let _ = writeln!(
        o,
        "<p class=\"instruments\">Instruments: {}</p>",
        escape(&instruments.join(" | "))
    );
    let base = c.baseline_run();
    if base.verdict.outcome == Outcome::Fail {
        let _ = writeln!(
            o,
            "<p class=\"fail\">The baseline {} FAILS its own absolute criteria ({}): limits \
             relative to it are no assurance.</p>",
            escape(&base.label),
            escape(&base.verdict.summary)
        );
    }
    let sim: Vec<String> = c
        .runs
        .iter()
        .filter(|r| r.verdict.simulated == Some(true))
        .map(|r| escape(&r.label))
        .collect();
    if !sim.is_empty() {
        let _ = writeln!(
            o,
            "<p class=\"sim\">SIMULATED bench: {} (not hardware)</p>",
            sim.join(", ")
        );
    }
    let unknown: Vec<String> = c
        .runs
        .iter()
        .filter(|r| r.verdict.simulated.is_none())
        .map(|r| escape(&r.label))
        .collect();
    if !unknown.is_empty() {
        let _ = writeln!(
            o,
            "<p class=\"small\">Bench kind not recorded (manifest from before the simulated \
             flag): {}</p>",
            unknown.join(", ")
        );
    }
    o
}

/// The sentence saying which unit the page's forces are in, when it is not the unit
/// the machine names and `compare.csv` use.
fn unit_note(unit: crate::units::ForceUnit) -> String {
    if unit == crate::units::ForceUnit::Newton {
        return String::new();
    }
    format!(
        "<p class=\"unit-note\">Forces are shown in the plans' unit, {u}, in the table and \
         the figures; the machine names under each metric are those of \
         <code>compare.csv</code>, <code>summary.csv</code> and acceptance criteria, where \
         metrics named <code>…_n</code> are in N.</p>\n",
        u = unit.symbol()
    )
}

/// `u` as the page shows it: forces in the page's unit `unit` (the plans' unit, N
/// when the plans differ), everything else as it is.
fn shown_unit(u: &'static str, unit: ForceUnit) -> &'static str {
    if display_factor(u, unit) == 1.0 {
        u
    } else {
        unit.symbol()
    }
}

/// Renders the page: head and banner ([`head`]), the runs ([`runs_section`]), the
/// metrics side by side ([`metrics_section`]), the criteria per run
/// ([`criteria_section`]), the method ([`method_section`]) and the figures.
pub fn render(c: &Comparison, figures: &[EmbeddedFigure]) -> String {
    let mut o = String::new();
    // One unit per quantity on the page: forces in the plans' unit (N when the plans
    // differ); the resolution metric of the other unit is left off.
    let unit = c.force_unit();
    head(&mut o, c);
    runs_section(&mut o, c);
    metrics_section(&mut o, c, unit);
    if let Some(file) = &c.criteria_file {
        criteria_section(&mut o, c, file, unit);
    }
    method_section(&mut o);
    figures_section(&mut o, figures);
    let _ = writeln!(
        o,
        "<hr><p><small>generated by tactbench {}</small></p></body></html>",
        escape(env!("CARGO_PKG_VERSION"))
    );
    o
}

/// The page's head, the comparison's banner (outcome, summary, baseline, exit code,
/// criteria, flags) and the title.
fn head(o: &mut String, c: &Comparison) {
    let base = c.baseline_run();
    let title = format!("tactbench comparison: {} runs", c.runs.len());
    let _ = write!(
        o,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>{}</title><style>{STYLE}</style></head><body>\n",
        escape(&title)
    );
    let _ = write!(
        o,
        "<section id=\"verdict\" class=\"{t}\">\n<div class=\"outcome\">{w}</div>\n<p>{}</p>\n\
         <p>baseline: <b>{}</b> ({}); exit code {}; criteria: {}{}</p>\n{}</section>\n",
        escape(&c.summary),
        escape(&base.label),
        escape(&base.dir.display().to_string()),
        c.exit_code,
        c.criteria_file
            .as_deref()
            .map_or("none given".to_string(), escape),
        if c.allow_partial {
            "; partial runs graded (--allow-partial)"
        } else {
            ""
        },
        banner_flags(c),
        w = c.outcome.word(),
        t = c.outcome.token(),
    );
    let _ = writeln!(o, "<h1>{}</h1>", escape(&title));
}

/// The runs: one row each (role, directory, build, plan, start, bench, status,
/// setpoints, outcome), then the analyses each run lacks and why.
fn runs_section(o: &mut String, c: &Comparison) {
    o.push_str(
        "<h2>Runs</h2>\n<p>The outcome of each run is what <code>tactbench report</code> \
         would decide with the same criteria (the baseline on its absolute bounds only); \
         the comparison's outcome is decided by the runs other than the baseline.</p>\n\
         <table id=\"runs\">\n<tr><th class=\"l\">run</th><th class=\"l\">role</th>\
         <th class=\"l\">directory</th><th class=\"l\">build id</th><th class=\"l\">plan</th>\
         <th class=\"l\">started</th><th class=\"l\">bench</th><th class=\"l\">status</th><th>setpoints measured / planned</th>\
         <th class=\"l\">outcome</th></tr>\n",
    );
    for (i, r) in c.runs.iter().enumerate() {
        let s = &r.verdict.run;
        let mut status = escape(&s.status);
        if let Some(w) = &s.writer {
            status.push_str(&format!(" ({})", escape(w)));
        }
        if let Some(why) = &s.incomplete_reason {
            status.push_str(&format!("<br><span class=\"small\">{}</span>", escape(why)));
        }
        if let Some(t) = &s.torn_journal_line {
            status.push_str(&format!(
                "<br><span class=\"small\">torn journal line {} ({} bytes) not used</span>",
                t.line, t.bytes
            ));
        }
        let _ = writeln!(
            o,
            "<tr class=\"run\"><td class=\"l\">{}{}</td><td class=\"l\">{}</td><td class=\"l\">{}</td>\
             <td class=\"l\">{}</td><td class=\"l\">{}</td><td class=\"l\">{}</td><td class=\"l\">{}</td><td class=\"l\">{status}</td>\
             <td>{} / {}</td><td class=\"l\"><span class=\"{}\">{}</span><br><span class=\"small\">{}</span></td></tr>",
            swatch(i),
            escape(&r.label),
            if r.is_baseline { "baseline" } else { "compared" },
            escape(&r.dir.display().to_string()),
            r.build_id().map_or("&mdash;".to_string(), escape),
            escape(&r.analysis.run.manifest.plan_name),
            escape(r.date()),
            match r.verdict.simulated {
                Some(true) => "<span class=\"sim\">SIMULATED</span>",
                Some(false) => "real",
                None => "not recorded",
            },
            s.measured_setpoints,
            s.planned_setpoints,
            class_of(r.verdict.outcome),
            r.verdict.outcome.word(),
            escape(&r.verdict.summary),
        );
    }
    o.push_str("</table>\n");
    for r in &c.runs {
        for (name, why) in &r.analysis.absent {
            let _ = writeln!(
                o,
                "<p class=\"small\">{}: no {} analysis: {}</p>",
                escape(&r.label),
                escape(name),
                escape(why)
            );
        }
    }
}

/// Every metric side by side: one row per metric (the resolution metric of the
/// other unit left off), one cell per run ([`metric_cell`]), the worst run.
fn metrics_section(o: &mut String, c: &Comparison, unit: ForceUnit) {
    let base = c.baseline_run();
    let _ = write!(
        o,
        "<h2>Metrics</h2>\n<p>Each cell: the value, its 95 % CI [low, high] where the \
         analysis states one; for the other runs the difference to the baseline <b>{}</b> \
         (absolute and %), its 95 % CI and whether it is significant (<b>sig.</b>: the CI of \
         the difference excludes 0; n/a: no CI in one of the two runs). A red cell is the \
         worst run for the metric, where the direction of “better” is defined.</p>\n{}\
         <table id=\"metrics\">\n<tr><th class=\"l\">metric</th><th class=\"l\">unit</th>\
         <th class=\"l\">better</th>",
        escape(&base.label),
        unit_note(unit)
    );
    for (i, r) in c.runs.iter().enumerate() {
        let _ = write!(
            o,
            "<th class=\"l\">{}{}{}</th>",
            swatch(i),
            escape(&r.label),
            if r.is_baseline { " (baseline)" } else { "" }
        );
    }
    o.push_str("<th class=\"l\">worst</th></tr>\n");
    for m in c
        .metrics
        .iter()
        .filter(|m| m.name != other_resolution(unit))
    {
        let k = display_factor(m.unit, unit);
        let _ = write!(
            o,
            "<tr class=\"metric\"><td class=\"l\">{}<br><small><code>{}</code></small></td>\
             <td class=\"l\">{}</td><td class=\"l\">{}</td>",
            escape(crate::report::headline::title(&m.name)),
            escape(&m.name),
            escape(shown_unit(m.unit, unit)),
            better_text(m.better.map(|b| match b {
                Better::CloserTo(t) => Better::CloserTo(t * k),
                b => b,
            }))
        );
        for (i, r) in c.runs.iter().enumerate() {
            metric_cell(o, m, i, r, k);
        }
        let worst = m
            .worst
            .map_or("&mdash;".to_string(), |w| escape(&c.runs[w].label));
        let _ = writeln!(o, "<td class=\"l\">{worst}</td></tr>");
    }
    o.push_str("</table>\n");
}

/// The cell of metric `m` for run `r` (the `i`-th), forces scaled by `k`: its value
/// and CI, its difference to the baseline with the difference's CI and
/// significance, and the criteria judged on it.
fn metric_cell(o: &mut String, m: &MetricComparison, i: usize, r: &ComparedRun, k: f64) {
    let mut cell = String::new();
    let mut classes = Vec::new();
    if r.is_baseline {
        classes.push("base");
    }
    if m.worst == Some(i) {
        classes.push("worst");
    }
    match r.metric(&m.name) {
        None => cell.push_str("&mdash;"),
        Some(mt) => {
            cell.push_str(&fmt_value(mt.value * k));
            if let Some(ci) = mt.ci95 {
                let _ = write!(
                    cell,
                    "<br><span class=\"small\">[{}, {}] {}</span>",
                    fmt_value(ci.low * k),
                    fmt_value(ci.high * k),
                    escape(ci.method)
                );
            }
        }
    }
    if let Some(d) = m.differences[i] {
        let pct = d
            .pct
            .map_or(String::new(), |p| format!(" ({} %)", signed(p)));
        let _ = write!(cell, "<br>Δ {}{pct}", signed(d.value * k));
        match (d.ci95, d.significance) {
            (Some((lo, hi)), s) => {
                let _ = write!(
                    cell,
                    "<br><span class=\"small\">Δ CI [{}, {}]</span> {}",
                    fmt_value(lo * k),
                    fmt_value(hi * k),
                    if s == Significance::Significant {
                        "<span class=\"sig\">sig.</span>"
                    } else {
                        "<span class=\"small\">not sig.</span>"
                    }
                );
            }
            (None, _) => cell.push_str(" <span class=\"small\">(n/a)</span>"),
        }
    }
    for v in verdicts_of(r, &m.name) {
        let _ = write!(
            cell,
            "<br><span class=\"{}\">{}</span> <span class=\"small\">{}</span>",
            class_of(v.outcome),
            v.outcome.word(),
            escape(&criterion_text_scaled(v, k))
        );
    }
    let _ = write!(o, "<td class=\"{}\">{cell}</td>", classes.join(" "));
}

/// The criteria per run (criteria file `file`): each criterion's verdict and each
/// provenance requirement.
fn criteria_section(o: &mut String, c: &Comparison, file: &str, unit: ForceUnit) {
    let _ = write!(
        o,
        "<h2>Acceptance</h2>\n<p>criteria: {}. Absolute bounds apply to every run; bounds \
         relative to the baseline (<code>max_relative_to_baseline</code>, \
         <code>min_relative_to_baseline</code>, <code>max_increase</code>, \
         <code>max_decrease</code>) to the other runs, with limits from the baseline's \
         value.</p>\n<table id=\"criteria\">\n<tr><th class=\"l\">run</th>\
         <th class=\"l\">verdict</th><th class=\"l\">metric</th><th>value</th>\
         <th class=\"l\">unit</th><th class=\"l\">threshold</th></tr>\n",
        escape(file)
    );
    for r in &c.runs {
        for v in &r.verdicts {
            let k = display_factor(v.unit, unit);
            let value = match &v.note {
                Some(n) => escape(n),
                None => fmt_value(v.value * k),
            };
            let _ = writeln!(
                o,
                "<tr class=\"verdict\"><td class=\"l\">{}</td><td class=\"l {}\">{}</td>\
                 <td class=\"l\">{}</td><td>{value}</td><td class=\"l\">{}</td><td class=\"l\">{}</td></tr>",
                escape(&r.label),
                class_of(v.outcome),
                v.outcome.word(),
                escape(&v.criterion.metric),
                escape(shown_unit(v.unit, unit)),
                escape(&criterion_text_scaled(v, k))
            );
        }
        for q in &r.verdict.requirements {
            let _ = writeln!(
                o,
                "<tr class=\"requirement\"><td class=\"l\">{}</td><td class=\"l {}\">{}</td>\
                 <td class=\"l\">provenance: {}</td><td>{}</td><td class=\"l\"></td>\
                 <td class=\"l\">required</td></tr>",
                escape(&r.label),
                class_of(q.outcome),
                q.outcome.word(),
                escape(&q.requirement),
                q.value.as_deref().map_or("(none)".to_string(), escape)
            );
        }
    }
    o.push_str("</table>\n");
}

/// The figures, embedded as base64 PNG data URIs.
fn figures_section(o: &mut String, figures: &[EmbeddedFigure]) {
    if !figures.is_empty() {
        o.push_str("<h2>Figures</h2>\n");
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
}

/// The method: how differences, their significance and the worst run are decided.
fn method_section(o: &mut String) {
    let _ = write!(
        o,
        "<h2>Method</h2>\n<p><b>Difference and significance.</b> d = value − baseline; \
         d % = 100 d / |baseline|. Each 95 % CI gives a standard error SE = (high − low) / 2 / \
         {z:.2} (half-width / z<sub>0.975</sub>); the runs being independent measurements, the \
         difference's 95 % CI is d ± {z:.2} √(SE² + SE<sub>baseline</sub>²). The difference is \
         significant when that interval excludes 0 (less conservative than asking the two \
         CIs not to overlap). Metrics without a CI in either run are n/a, never significant.</p>\n\
         <p><b>Worse.</b> Which direction is better, by metric: closer to 1 for slopes; higher \
         for R² and fractions of markers ok; closer to 0 for biases, offsets, zero errors, creep \
         and drift; lower for resolution, SDs, linearity, hysteresis, FWHM, repeatability, \
         reproducibility, interpolation and reversibility errors, the ISO 376 class code, times \
         and counts of unsettled, flagged or re-acquired rows; undefined otherwise (e.g. rows, \
         mean displacements, full scale, which resolution method was used). The \
         worst run is named when at least two runs have the metric and one is uniquely worst.</p>\n",
        z = Z95
    );
}
