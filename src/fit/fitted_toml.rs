//! `fitted.toml`: the nominal sensor file with the fitted values written in, each with
//! a comment giving its 95 % interval and the run it came from. Everything else in the
//! file (comments, layout, keys the fit does not touch) is kept as it was, so the file
//! diffs cleanly against the nominal one and `track`, `run` and `reconstruct` load it
//! unedited (checked here: the text is parsed back before it is returned).
//!
//! Edited keys: `[elastomer] young_modulus_kpa`, `poisson_ratio`, `thickness_mm`;
//! each `[[layers]] depth_mm`; `[camera] mm_per_px` (the shared scale). What a
//! sensor file cannot hold (the F/T mounting, the contact offset and z, per-layer
//! scales) is listed in the header comment, with its interval.

use std::path::Path;

use super::doc::{FitDoc, ParamFit};
use super::FitError;
use crate::sensor::Sensor;

/// `value  # fitted: 95 % CI [lo, hi] unit, nominal v0 (run R)`.
fn line(key: &str, p: &ParamFit, run: &str) -> String {
    let ci = p
        .ci95
        .map(|[a, b]| format!("[{}, {}]", num(a), num(b)))
        .unwrap_or_else(|| "none".into());
    format!(
        "{key} = {}  # fitted: 95 % CI {ci} {}, nominal {} (tactbench fit, run {run})",
        num(p.value),
        p.unit,
        num(p.nominal)
    )
}

/// Seven significant digits, shortest form, always a float in TOML.
fn num(v: f64) -> String {
    let s = format!("{v:.7e}");
    let parsed: f64 = s.parse().unwrap_or(v);
    let mut t = format!("{parsed}");
    if !t.contains('.') && !t.contains('e') && !t.contains("inf") && !t.contains("NaN") {
        t.push_str(".0");
    }
    t
}

/// Which table a line opens: `elastomer`, `camera`, `layers` (a new layer), or
/// another (`None` keeps the key rules off).
fn header(line: &str) -> Option<String> {
    let t = line.trim();
    if t.starts_with("[[") {
        return Some(t.trim_matches(|c| c == '[' || c == ']').trim().to_string() + "[]");
    }
    if t.starts_with('[') {
        return Some(t.trim_matches(|c| c == '[' || c == ']').trim().to_string());
    }
    None
}

fn key_of(line: &str) -> Option<&str> {
    let t = line.trim_start();
    if t.starts_with('#') {
        return None;
    }
    let (k, _) = t.split_once('=')?;
    Some(k.trim())
}

/// The fitted file's text (module docs), checked to load as a sensor file.
pub fn fitted_toml(
    nominal_text: &str,
    doc: &FitDoc,
    sensor: &Sensor,
    date: &str,
) -> Result<String, FitError> {
    let run = doc.run.as_str();
    let fitted = |name: &str| doc.parameters.get(name).filter(|p| p.fitted);
    let mut out: Vec<String> = Vec::new();
    out.push(format!(
        "# Fitted by `tactbench fit` ({} {}) from run {run} on {date}.",
        env!("CARGO_PKG_NAME"),
        env!("CARGO_PKG_VERSION")
    ));
    out.push(format!(
        "# Nominal sensor file: {}. Values the fit did not determine keep their nominal values.",
        doc.sensor
    ));
    let bench: Vec<String> = doc
        .parameters
        .iter()
        .filter(|(k, p)| {
            p.fitted
                && (k.starts_with("ft_")
                    || k.starts_with("contact_")
                    || k.starts_with("mm_per_px."))
        })
        .map(|(k, p)| {
            let ci = p
                .ci95
                .map(|[a, b]| format!(" (95 % CI [{}, {}])", num(a), num(b)))
                .unwrap_or_default();
            format!("#   {k} = {} {}{ci}", num(p.value), p.unit)
        })
        .collect();
    if !bench.is_empty() {
        out.push(
            "# Fitted, not part of a sensor file (the bench's mounting, per-layer scales):".into(),
        );
        out.extend(bench);
    }
    out.push(String::new());
    let mut table: Option<String> = None;
    let mut layer: isize = -1;
    let mut seen: Vec<(String, isize, String)> = Vec::new();
    for raw in nominal_text.lines() {
        if let Some(h) = header(raw) {
            if h == "layers[]" {
                layer += 1;
            }
            table = Some(h.clone());
            out.push(raw.to_string());
            continue;
        }
        let name = match (table.as_deref(), key_of(raw)) {
            (
                Some("elastomer"),
                Some(k @ ("young_modulus_kpa" | "poisson_ratio" | "thickness_mm")),
            ) => Some(k.to_string()),
            (Some("layers[]"), Some("depth_mm")) => sensor
                .layers
                .get(layer.max(0) as usize)
                .map(|l| format!("depth_mm.{}", l.name)),
            (Some("camera"), Some("mm_per_px")) => Some("mm_per_px".to_string()),
            _ => None,
        };
        if let (Some(name), Some(t)) = (name, table.as_ref()) {
            seen.push((t.clone(), layer, name.clone()));
            if let Some(p) = fitted(&name) {
                let key = key_of(raw).unwrap_or_default();
                let indent: String = raw.chars().take_while(|c| c.is_whitespace()).collect();
                out.push(format!("{indent}{}", line(key, p, run)));
                continue;
            }
        }
        out.push(raw.to_string());
    }
    // Every fitted value a sensor file holds must have found its line (a sensor file
    // always spells them: none of them has a default).
    for (name, p) in &doc.parameters {
        let in_file = name == "young_modulus_kpa"
            || name == "poisson_ratio"
            || name == "thickness_mm"
            || name == "mm_per_px"
            || name.starts_with("depth_mm.");
        if p.fitted && in_file && !seen.iter().any(|(_, _, n)| n == name) {
            return Err(FitError::Input {
                path: doc.sensor.clone().into(),
                message: format!("{name}: no line for it in the nominal sensor file to write the fitted value into"),
            });
        }
    }
    let mut text = out.join("\n");
    text.push('\n');
    Sensor::from_toml_str(&text, Path::new("fitted.toml")).map_err(|e| {
        FitError::Numerical(format!(
            "the fitted sensor file does not load back ({e}): please report this"
        ))
    })?;
    Ok(text)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::doc::{Route, FIT_SCHEMA};
    use std::collections::BTreeMap;

    fn fitted(value: f64, nominal: f64, unit: &str) -> ParamFit {
        ParamFit {
            value,
            ci95: Some([value * 0.97, value * 1.03]),
            unit: unit.into(),
            identifiable: true,
            route: Route::Both,
            nominal,
            sd: Some(value * 0.015),
            fitted: true,
            reason: None,
        }
    }

    #[test]
    fn a_fitted_file_carries_the_values_with_their_intervals_and_loads_back() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("experiments/paper_sensor.toml");
        let text = std::fs::read_to_string(&path).unwrap();
        let s = Sensor::from_toml_str(&text, &path).unwrap();
        let mut parameters = BTreeMap::new();
        parameters.insert("young_modulus_kpa".into(), fitted(712.5, 1000.0, "kPa"));
        parameters.insert("depth_mm.red".into(), fitted(6.5, 6.0, "mm"));
        parameters.insert("ft_rotation_deg".into(), fitted(7.1, 0.0, "deg"));
        let doc = FitDoc {
            schema: FIT_SCHEMA.into(),
            run: "runs/calib".into(),
            sensor: "paper_sensor.toml".into(),
            parameters,
            routes: serde_json::Value::Null,
            residual_rms_px: BTreeMap::new(),
            cross_validation: serde_json::Value::Null,
            extra: BTreeMap::new(),
        };
        let out = fitted_toml(&text, &doc, &s, "2026-11-28").unwrap();
        let back = Sensor::from_toml_str(&out, "fitted.toml").unwrap();
        assert_eq!(back.elastomer.young_modulus_kpa, 712.5);
        assert_eq!(back.layers[1].depth_mm, 6.5);
        assert_eq!(
            back.layers[0].depth_mm, 3.0,
            "the blue layer was not fitted"
        );
        assert!(out.contains("young_modulus_kpa = 712.5  # fitted: 95 % CI [691.125, 733.875] kPa, nominal 1000.0 (tactbench fit, run runs/calib)"), "{out}");
        assert!(out.contains("#   ft_rotation_deg = 7.1 deg"), "{out}");
        // Untouched lines stay as they were.
        assert!(out.contains("# The sensor of the paper (Section III)"));
    }
}
