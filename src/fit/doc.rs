//! `fit.json`: the document `tactbench fit --json` writes, `report --acceptance` judges
//! fitted-parameter criteria on, `compare` trends across builds, and `fit.html` is drawn
//! from (so the page reads what the fit recorded; it never re-fits).
//!
//! Shape (issue 30; NAME exactly as [`PARAMETER_NAMES`] / `depth_mm.<layer>` /
//! `mm_per_px.<layer>`):
//!
//! ```json
//! {"schema": "tactbench-fit/1",
//!  "parameters": {NAME: {"value": v, "ci95": [lo, hi], "unit": "kPa",
//!                        "identifiable": true, "route": "indentation" | "displacement" | "both",
//!                        "nominal": v0, "sd": s, "fitted": true, "reason": null}},
//!  "routes": {"indentation": {...}, "displacement": {...}, "agree": true, "disagreements": []},
//!  "residual_rms_px": {LAYER: rms},
//!  "cross_validation": {...},
//!  ...}
//! ```
//!
//! What `fit.html` ([`crate::report::fit_page`]) and `report` read besides
//! `parameters` (every entry optional; the page says which it lacks):
//! - `routes.indentation` / `routes.displacement`: `{"parameters": {NAME: {"value": v,
//!   "ci95": [lo, hi] | null}}, ...scalar figures of the route (samples, residual RMS,
//!   ...)}`; `routes.agree` (bool), `routes.disagreements` (messages);
//! - `cross_validation`: numbers, nested objects allowed (shown with dotted keys), e.g.
//!   `{"held_out": "...", "nominal": {"force_sum_error_n": e0}, "fitted": {...}}`;
//! - in `extra` (top-level keys of the document): `ci_method` (string; `jacobian` or
//!   `bootstrap` in it names the method of the intervals `report` shows),
//!   `correlations` = `{"names": [NAME...], "matrix": [[r...]...]}`,
//!   `examples` = `[{"index", "layer", "x_mm", "y_mm", "ux_px", "uy_px", "pred_ux_px",
//!   "pred_uy_px"}]` (measured and predicted displacement of each marker at a few
//!   setpoints), `setpoint_residuals` = `[{"index", "rms_px", "layer"?}]`,
//!   `indentation_curve` = `[{"depth_mm", "force_n", "predicted_n"}]`.
//!
//! `report` checks, when it reads a `fit.json` for acceptance criteria: known parameter
//! names, `unit` the parameter's own (`kPa`, `1`, `mm`, `mm/px`, `deg`), finite `value`
//! and `nominal`, `ci95` finite with `low <= high`.
//!
//! A parameter that was not fitted (not listed in `--params`) or that the run cannot
//! determine keeps its nominal `value`, has `"fitted": false` and a `reason`; a
//! not-identifiable one has `"identifiable": false` and `ci95: null`: never a made-up
//! number.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// The schema tag of `fit.json`.
pub const FIT_SCHEMA: &str = "tactbench-fit/1";

/// The parameter names of issue 30 that do not carry a layer suffix. Layer-specific
/// names are `depth_mm.<layer>` and, where the layers' scales differ, `mm_per_px.<layer>`.
pub const PARAMETER_NAMES: &[&str] = &[
    "young_modulus_kpa",
    "poisson_ratio",
    "thickness_mm",
    "mm_per_px",
    "ft_rotation_deg",
    "contact_offset_x_mm",
    "contact_offset_y_mm",
    "contact_z_mm",
];

/// Which data determined a parameter.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Route {
    /// Stage depth past contact against the F/T normal force (contact law).
    Indentation,
    /// The forward model driven by the measured wrench against tracked displacements.
    Displacement,
    /// Both routes, fitted jointly.
    Both,
}

/// One parameter's entry in `fit.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParamFit {
    /// Fitted value (the nominal value when not fitted or not identifiable).
    pub value: f64,
    /// 95 % confidence interval; `None` (JSON null) when not identifiable or not fitted.
    pub ci95: Option<[f64; 2]>,
    /// Unit of `value` (`kPa`, `mm`, `mm/px`, `deg`, `1` for ν).
    pub unit: String,
    /// Whether the run determines this parameter.
    pub identifiable: bool,
    /// The data that determined it.
    pub route: Route,
    /// The value in the nominal sensor / bench file (what the fit started from).
    pub nominal: f64,
    /// Standard deviation of `value` (same unit); `None` when not fitted.
    #[serde(default)]
    pub sd: Option<f64>,
    /// Whether the value comes from the fit (false: held at nominal).
    #[serde(default)]
    pub fitted: bool,
    /// Why a parameter is held or not identifiable, and what kind of setpoint would
    /// determine it; `None` for a fitted, identifiable parameter.
    #[serde(default)]
    pub reason: Option<String>,
}

/// The whole `fit.json` document. Fields other than `parameters` are the fit's own
/// detail (routes side by side, residuals, cross-validation, the page's curves) and are
/// written as `serde_json::Value`s by the fit so this type stays stable while that
/// detail grows; readers that judge or trend parameters use `parameters` only.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FitDoc {
    /// [`FIT_SCHEMA`].
    pub schema: String,
    /// The run directory the fit came from, as given.
    #[serde(default)]
    pub run: String,
    /// The nominal sensor file, as given.
    #[serde(default)]
    pub sensor: String,
    /// NAME -> entry, for every parameter the model has (fitted or held).
    pub parameters: BTreeMap<String, ParamFit>,
    /// The two routes side by side: `{"indentation": {...}, "displacement": {...},
    /// "agree": bool, "disagreements": [messages]}`.
    #[serde(default)]
    pub routes: serde_json::Value,
    /// Residual RMS of the displacement route per layer, px.
    #[serde(default)]
    pub residual_rms_px: BTreeMap<String, f64>,
    /// Held-out force-sum error with the nominal and with the fitted sensor file.
    #[serde(default)]
    pub cross_validation: serde_json::Value,
    /// Everything else the fit records (CI method, correlations, curves for the page).
    #[serde(flatten)]
    pub extra: BTreeMap<String, serde_json::Value>,
}

impl FitDoc {
    /// Reads a `fit.json`, checking its schema tag.
    pub fn from_json_str(text: &str) -> Result<FitDoc, String> {
        let doc: FitDoc = serde_json::from_str(text).map_err(|e| format!("not a fit.json: {e}"))?;
        if doc.schema != FIT_SCHEMA {
            return Err(format!(
                "schema {:?}, where this version reads {FIT_SCHEMA:?}",
                doc.schema
            ));
        }
        Ok(doc)
    }
}

/// Whether `name` is a parameter name of the fit: one of [`PARAMETER_NAMES`], or
/// `depth_mm.<layer>` / `mm_per_px.<layer>` with a non-empty layer name.
pub fn is_parameter_name(name: &str) -> bool {
    if PARAMETER_NAMES.contains(&name) {
        return true;
    }
    ["depth_mm.", "mm_per_px."]
        .iter()
        .any(|p| name.strip_prefix(p).is_some_and(|l| !l.is_empty()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_fit_doc_round_trips_with_nulls_for_held_parameters() {
        let mut parameters = BTreeMap::new();
        parameters.insert(
            "thickness_mm".to_string(),
            ParamFit {
                value: 40.0,
                ci95: None,
                unit: "mm".into(),
                identifiable: false,
                route: Route::Displacement,
                nominal: 40.0,
                sd: None,
                fitted: false,
                reason: Some("a 40 mm gel's field does not depend on its thickness".into()),
            },
        );
        let doc = FitDoc {
            schema: FIT_SCHEMA.into(),
            run: "runs/x".into(),
            sensor: "s.toml".into(),
            parameters,
            routes: serde_json::json!({"agree": true}),
            residual_rms_px: BTreeMap::from([("blue".to_string(), 0.05)]),
            cross_validation: serde_json::Value::Null,
            extra: BTreeMap::new(),
        };
        let text = serde_json::to_string(&doc).unwrap();
        assert!(text.contains("\"ci95\":null"), "{text}");
        assert_eq!(FitDoc::from_json_str(&text).unwrap(), doc);
        let wrong = text.replace(FIT_SCHEMA, "tactbench-fit/0");
        assert!(FitDoc::from_json_str(&wrong)
            .unwrap_err()
            .contains("schema"));
    }

    #[test]
    fn parameter_names_take_layer_suffixes_only_where_the_issue_gives_them() {
        assert!(is_parameter_name("young_modulus_kpa"));
        assert!(is_parameter_name("depth_mm.blue"));
        assert!(is_parameter_name("mm_per_px.red"));
        assert!(is_parameter_name("mm_per_px"));
        assert!(!is_parameter_name("depth_mm"));
        assert!(!is_parameter_name("depth_mm."));
        assert!(!is_parameter_name("young_modulus"));
    }
}
