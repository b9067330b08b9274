//! The report page's metric tables: the **headline** table right after the verdict
//! banner (the key metrics of the run with units, 95 % confidence intervals and, where
//! acceptance criteria bound them, their limits and outcome), the full **metrics**
//! table (human-readable names with units; the machine names that acceptance criteria,
//! `summary.csv` and `verdict.json` use are kept visible in a small column), and the
//! **ISO 376** section (the class table and what each criterion implies).
//!
//! One unit per quantity on a page: forces are shown in the plan's force unit
//! ([`in_plan_unit`]: a plan in gf shows the offset, residual SDs and drifts in gf, with
//! criterion limits converted alike); the machine names and `summary.csv` keep their
//! own units (`magnitude.offset_n` is in N there). The metric of the other unit
//! (`magnitude.resolution_n` on a gf plan) is left off the page.

use std::fmt::Write;

use super::acceptance::{fmt_value, Criterion, Outcome, Verdict};
use super::markup::escape;
use crate::analysis::metrology::{MetrologyAnalysis, ISO376_CLASSES, NO_CLASS};
use crate::analysis::{Ci95, Metric, RunAnalysis};
use crate::units::ForceUnit;

/// `m` in the plan's force unit: a metric in N is converted to `unit` (value and CI);
/// every other metric is returned as it is.
pub fn in_plan_unit(m: &Metric, unit: ForceUnit) -> Metric {
    if m.unit != "N" || unit == ForceUnit::Newton {
        return m.clone();
    }
    let k = unit.from_newtons(1.0);
    Metric {
        name: m.name.clone(),
        value: m.value * k,
        unit: unit.symbol(),
        ci95: m.ci95.map(|c| Ci95 {
            low: c.low * k,
            high: c.high * k,
            method: c.method,
        }),
    }
}

/// A criterion's absolute bounds scaled by `k` (relative fractions unchanged), to show
/// it in the unit its metric is shown in.
pub fn scaled_criterion(c: &Criterion, k: f64) -> Criterion {
    let s = |v: Option<f64>| v.map(|v| v * k);
    Criterion {
        min: s(c.min),
        max: s(c.max),
        marginal_min: s(c.marginal_min),
        marginal_max: s(c.marginal_max),
        max_increase: s(c.max_increase),
        max_decrease: s(c.max_decrease),
        ..c.clone()
    }
}

/// The factor from a metric's unit to the unit it is shown in on a page of `unit`.
pub fn display_factor(metric_unit: &str, unit: ForceUnit) -> f64 {
    if metric_unit == "N" {
        unit.from_newtons(1.0)
    } else {
        1.0
    }
}

/// The resolution metric in the other force unit, left off a page in `unit`.
pub fn other_resolution(unit: ForceUnit) -> &'static str {
    match unit {
        ForceUnit::GramForce => "magnitude.resolution_n",
        ForceUnit::Newton => "magnitude.resolution_gf",
    }
}

/// Human-readable names of the metrics (exact names; patterns with `<layer>` fall back
/// to the machine name).
const TITLES: &[(&str, &str)] = &[
    ("run.rows", "journal rows"),
    ("run.unsettled", "unsettled rows"),
    ("magnitude.slope", "sensitivity (slope F^sum / F/T)"),
    ("magnitude.offset_n", "offset"),
    ("magnitude.r2", "R² of the fit"),
    (
        "magnitude.residual_sd_n",
        "residual SD (pooled within level)",
    ),
    ("magnitude.max_level_sd_n", "largest level residual SD"),
    ("magnitude.resolution_n", "force resolution"),
    ("magnitude.resolution_gf", "force resolution"),
    ("magnitude.resolution_method", "resolution spread used"),
    (
        "magnitude.linearity_pct",
        "linearity error (of output span)",
    ),
    ("magnitude.hysteresis_pct", "hysteresis (of output span)"),
    (
        "metrology.full_scale_n",
        "full scale FS (largest applied force)",
    ),
    (
        "metrology.repeatability_pct_fs",
        "repeatability SD s_r (ISO 376 b′ = 1.128 s_r)",
    ),
    (
        "metrology.reproducibility_pct_fs",
        "reproducibility SD across positions s_R (ISO 376 b = 1.693 s_R)",
    ),
    (
        "metrology.interpolation_pct_fs",
        "interpolation error (ISO 376 f_c)",
    ),
    ("metrology.zero_pct_fs", "zero error, mean (ISO 376 f_0)"),
    (
        "metrology.zero_max_pct_fs",
        "zero error, worst trial (ISO 376 f_0)",
    ),
    (
        "metrology.reversibility_pct_fs",
        "reversibility / hysteresis (ISO 376 v)",
    ),
    ("metrology.class", "ISO 376 class implied"),
    ("hold.full_scale_n", "full scale FS of the holds"),
    (
        "hold.creep_pct_fs_per_min",
        "creep of F^sum relative to the F/T",
    ),
    ("hold.ft_drift_pct_fs_per_min", "F/T drift during the holds"),
    ("hold.zero_drift_n", "zero drift over the run"),
    (
        "hold.zero_drift_pct_fs",
        "zero drift over the run, of full scale",
    ),
    ("angle.bias_deg", "angle bias"),
    ("angle.sd_deg", "angle error SD"),
    ("angle.bias_vs_target_deg", "angle bias against the target"),
    ("angle.resolution_deg", "angle resolution"),
    ("angle.resolution_method", "resolution spread used"),
    ("angle.slope", "angle slope"),
    ("angle.r2", "R² of the angle fit"),
    ("angle.linearity_pct", "angle linearity error"),
    ("spatial.fwhm_mm", "spatial resolution (FWHM)"),
    ("spatial.peak_offset_mm", "profile peak offset"),
    ("spatial.line_offset_mm", "profiled line offset"),
    ("displacement.max_sd_px", "largest displacement SD"),
    ("displacement.max_abs_bias_px", "largest displacement bias"),
    ("timing.tracking_ms", "tracking time per frame"),
    ("timing.reconstruction_ms", "reconstruction time per frame"),
    ("timing.forces_ms", "tracking + reconstruction per frame"),
    ("timing.forces_max_ms", "slowest tracking + reconstruction"),
    ("timing.rest_ms", "move + settle + acquire per frame"),
    ("tracking.min_ok_fraction", "markers ok, worst setpoint"),
    ("tracking.mean_ok_fraction", "markers ok, mean"),
    ("tracking.flagged_rows", "rows flagged by the quality gate"),
    ("tracking.reacquired_rows", "rows re-acquired"),
];

/// The metrics of the headline table, in order, when the run has them.
const HEADLINE: &[&str] = &[
    "metrology.class",
    "magnitude.resolution_gf",
    "magnitude.resolution_n",
    "magnitude.slope",
    "magnitude.offset_n",
    "magnitude.r2",
    "metrology.repeatability_pct_fs",
    "metrology.reproducibility_pct_fs",
    "metrology.interpolation_pct_fs",
    "metrology.zero_pct_fs",
    "metrology.reversibility_pct_fs",
    "hold.creep_pct_fs_per_min",
    "hold.zero_drift_n",
    "angle.bias_deg",
    "angle.sd_deg",
    "angle.resolution_deg",
    "spatial.fwhm_mm",
    "displacement.max_sd_px",
    "displacement.max_abs_bias_px",
    "timing.forces_ms",
    "tracking.min_ok_fraction",
];

/// The human-readable name of a metric (the machine name when it has none).
pub fn title(name: &str) -> &str {
    TITLES
        .iter()
        .find(|(n, _)| *n == name)
        .map_or(name, |(_, t)| t)
}

/// The value as shown: class names and resolution methods in words.
fn shown(m: &Metric) -> String {
    match m.name.as_str() {
        "metrology.class" => {
            if m.value >= NO_CLASS {
                "none (outside class 2)".into()
            } else {
                ISO376_CLASSES
                    .iter()
                    .find(|c| c.code == m.value)
                    .map_or(fmt_value(m.value), |c| format!("class {}", c.name))
            }
        }
        "magnitude.resolution_method" | "angle.resolution_method" => match m.value as i64 {
            1 => "1: pooled within-level SD".into(),
            2 => "2: SD about the fit line (one trial per level)".into(),
            _ => fmt_value(m.value),
        },
        _ => fmt_value(m.value),
    }
}

fn unit_of(m: &Metric) -> &'static str {
    match m.unit {
        "1" | "count" => "",
        u => u,
    }
}

fn ci_cells(m: &Metric) -> (String, String) {
    match m.ci95 {
        Some(c) => (
            format!("[{}, {}]", fmt_value(c.low), fmt_value(c.high)),
            escape(c.method),
        ),
        None => ("&mdash;".into(), String::new()),
    }
}

fn class_of(o: Outcome) -> &'static str {
    match o {
        Outcome::NotJudged => "",
        Outcome::Pass => "pass",
        Outcome::Marginal => "marginal",
        Outcome::Fail | Outcome::Incomplete => "fail",
    }
}

/// The headline table: key metrics (forces in the plan's force unit `unit`), then any
/// other metric an acceptance criterion bounds.
pub fn headline(o: &mut String, metrics: &[Metric], verdicts: Option<&[Verdict]>, unit: ForceUnit) {
    let vs = verdicts.unwrap_or(&[]);
    let other_resolution = other_resolution(unit);
    let mut names: Vec<&str> = HEADLINE
        .iter()
        .copied()
        .filter(|n| *n != other_resolution && metrics.iter().any(|m| m.name == *n))
        .collect();
    for v in vs {
        if !names.contains(&v.criterion.metric.as_str()) {
            names.push(&v.criterion.metric);
        }
    }
    if names.is_empty() {
        return;
    }
    o.push_str(
        "<section id=\"headline\"><h2>Key metrics</h2>\n<table class=\"headline\">\n<tr><th class=\"l\">metric</th>\
         <th>value</th><th class=\"l\">unit</th><th>95 % CI</th><th class=\"l\">CI method</th>\
         <th class=\"l\">limit</th><th class=\"l\">outcome</th></tr>\n",
    );
    for name in names {
        let m = metrics
            .iter()
            .find(|m| m.name == name)
            .map(|m| in_plan_unit(m, unit));
        let v = vs.iter().find(|v| v.criterion.metric == name);
        let (value, shown_unit, (ci, method)) = match &m {
            Some(m) => (shown(m), unit_of(m), ci_cells(m)),
            None => (
                v.and_then(|v| v.note.clone())
                    .map_or("&mdash;".into(), |n| escape(&n)),
                "",
                ("&mdash;".into(), String::new()),
            ),
        };
        let (limit, outcome) = match v {
            Some(v) => (
                escape(&scaled_criterion(&v.criterion, display_factor(v.unit, unit)).to_string()),
                format!(
                    "<span class=\"{}\">{}</span>",
                    class_of(v.outcome),
                    v.outcome.word()
                ),
            ),
            None => ("&mdash;".into(), String::new()),
        };
        let _ = writeln!(
            o,
            "<tr class=\"headline-metric\"><td class=\"l\">{}<br><small><code>{}</code></small></td>\
             <td>{value}</td><td class=\"l\">{}</td><td>{ci}</td><td class=\"l\">{method}</td>\
             <td class=\"l\">{limit}</td><td class=\"l\">{outcome}</td></tr>",
            escape(title(name)),
            escape(name),
            escape(shown_unit)
        );
    }
    o.push_str(
        "</table>\n<p><small>%FS = per cent of full scale, the largest applied F/T force of the \
         run. CI methods: <i>t</i> Student t on the analytic standard error, <i>chi2</i> \
         chi-squared interval of an SD, <i>bootstrap</i> percentile bootstrap over trials \
         (seeded, see below), <i>normal</i> from the propagated reconstruction SD.</small></p>\n\
         </section>\n",
    );
}

/// The sentence under a table whose forces are converted: the page's unit, and the
/// unit the machine names keep elsewhere (empty on a page in N).
pub fn unit_note(unit: ForceUnit) -> String {
    if unit == ForceUnit::Newton {
        return String::new();
    }
    format!(
        "<p class=\"unit-note\"><small>Forces are shown in the plan's force unit, {u}. The \
         names (<code>magnitude.offset_n</code>, …) are those of <code>summary.csv</code>, \
         <code>verdict.json</code> and acceptance criteria, where metrics named \
         <code>…_n</code> are in N.</small></p>\n",
        u = unit.symbol()
    )
}

/// The full metrics table (forces in the plan's force unit `unit`).
pub fn metrics_table(o: &mut String, metrics: &[Metric], unit: ForceUnit) {
    o.push_str(
        "<h2>Metrics</h2>\n<table>\n<tr><th class=\"l\">metric</th><th>value</th>\
         <th class=\"l\">unit</th><th>95 % CI</th><th class=\"l\">CI method</th>\
         <th class=\"l\">name</th></tr>\n",
    );
    for m in metrics.iter().filter(|m| m.name != other_resolution(unit)) {
        let m = &in_plan_unit(m, unit);
        let (ci, method) = ci_cells(m);
        let _ = writeln!(
            o,
            "<tr class=\"metric\"><td class=\"l\">{}</td><td>{}</td><td class=\"l\">{}</td>\
             <td>{ci}</td><td class=\"l\">{method}</td><td class=\"l\"><small><code>{}</code>\
             </small></td></tr>",
            escape(title(&m.name)),
            escape(&shown(m)),
            escape(unit_of(m)),
            escape(&m.name)
        );
    }
    o.push_str("</table>\n");
    o.push_str(&unit_note(unit));
}

/// The ISO 376 section: definitions in short, the class table and the class each
/// criterion of the run implies.
pub fn iso376_section(o: &mut String, analysis: &RunAnalysis) {
    let unit = analysis.run.plan.force_unit;
    let m: Option<&MetrologyAnalysis> = analysis.metrology.as_ref();
    let class = m
        .and_then(|m| m.class.as_ref())
        .or_else(|| analysis.hold.as_ref().and_then(|h| h.class.as_ref()));
    let Some(class) = class else { return };
    let fs = m
        .map(|m| m.full_scale_n)
        .or_else(|| analysis.hold.as_ref().map(|h| h.full_scale_n))
        .unwrap_or(f64::NAN);
    let _ = writeln!(
        o,
        "<h2 id=\"iso376\">Force metrology (ISO 376 style)</h2>\n<p>F<sup>sum</sup> against the F/T \
         reference, errors in % of full scale FS = {} {} (the largest applied force of the run). \
         ISO 376:2011 (calibration of force-proving instruments) relates b, b′, f<sub>c</sub> and v to \
         the reading at each force; dividing by FS instead is more lenient below full scale. \
         Definitions: repeatability SD s<sub>r</sub> = pooled SD of the residuals about the \
         calibration line over trials at the same position, level and direction, and b′ = 1.128 \
         s<sub>r</sub>, the expected range of two series, which the class table compares (7.5.1); \
         reproducibility SD s<sub>R</sub> = the same over all contact positions, and b = 1.693 \
         s<sub>R</sub>, the expected range of three series (7.5.1); interpolation f<sub>c</sub> = largest level mean residual of \
         the loading rows (7.5.2); zero f<sub>0</sub> = unloaded error at the end of a trial minus \
         at its start (7.5.3); reversibility v = unloading minus loading mean residual (7.5.4); creep \
         c = slope of F<sup>sum</sup> &minus; F/T against the time in a hold (7.5.5). Bootstrap \
         intervals: {} resamples of whole trials within each position, seed {}.</p>",
        fmt_value(unit.from_newtons(fs)),
        unit.symbol(),
        crate::analysis::metrology::BOOTSTRAP_RESAMPLES,
        crate::analysis::metrology::BOOTSTRAP_SEED
    );
    o.push_str("<table class=\"iso376\">\n<tr><th class=\"l\">criterion</th><th>this run (%)</th><th class=\"l\">compared as</th>");
    for c in &ISO376_CLASSES {
        let _ = write!(o, "<th>class {} limit (%)</th>", c.name);
    }
    o.push_str("<th class=\"l\">class met</th></tr>\n");
    for ch in &class.checks {
        let _ = write!(
            o,
            "<tr><td class=\"l\">{}</td><td>{}</td><td class=\"l\">{}</td>",
            escape(ch.criterion.symbol()),
            fmt_value(ch.value_pct),
            escape(ch.basis)
        );
        for c in &ISO376_CLASSES {
            let _ = write!(o, "<td>{}</td>", fmt_value(ch.criterion.limit(c)));
        }
        let _ = writeln!(
            o,
            "<td class=\"l {}\">{}</td></tr>",
            if ch.class.is_some() { "pass" } else { "fail" },
            ch.class
                .map_or("none (outside class 2)".to_string(), |c| c.name.to_string())
        );
    }
    let _ = writeln!(
        o,
        "</table>\n<p class=\"iso-class\"><b>Implied class: {}.</b> {}</p>",
        escape(class.name()),
        if class.code >= NO_CLASS {
            "A vision-based tactile sensor is not a force-proving instrument: its reconstructed \
             force misses the loosest ISO 376 class (2) by a wide margin. The numbers are for \
             comparing builds and sensors, not a calibration certificate."
        } else {
            "Judged only on the criteria listed, with errors relative to full scale; not a \
             calibration certificate."
        }
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    /// "Two different numbers are both called b′" (and `hold.zero_drift_n` and
    /// `hold.zero_drift_pct_fs` were both "zero drift over the run"): no two metrics
    /// that can stand on one page share a name. The exceptions never meet: the
    /// resolution in N and in gf (a page shows the plan's unit only) and the resolution
    /// method of a magnitude and of an angle run.
    #[test]
    fn no_two_metrics_on_one_page_share_a_name() {
        let never_together = [
            ("magnitude.resolution_n", "magnitude.resolution_gf"),
            ("magnitude.resolution_method", "angle.resolution_method"),
        ];
        for (i, (a, ta)) in TITLES.iter().enumerate() {
            for (b, tb) in &TITLES[i + 1..] {
                if ta == tb {
                    assert!(
                        never_together.contains(&(a, b)) || never_together.contains(&(b, a)),
                        "{a} and {b} are both called {ta:?}"
                    );
                }
            }
        }
        // b′ names the range the class table compares, not the repeatability SD.
        let sr = title("metrology.repeatability_pct_fs");
        assert!(sr.starts_with("repeatability SD s_r") && sr.contains("b′ = 1.128 s_r"));
    }
}
