//! The plan TOML as parsed, before validation: serde types mirroring the schema, every
//! table denying unknown keys so a typo is an error naming the line.

use serde::Deserialize;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawPlan {
    pub(super) name: String,
    pub(super) sensor: String,
    pub(super) build_id: Option<String>,
    pub(super) force_unit: Option<String>,
    pub(super) indenter: RawIndenter,
    pub(super) approach: RawApproach,
    #[serde(default)]
    pub(super) control: RawControl,
    #[serde(default)]
    pub(super) settle: RawSettle,
    #[serde(default)]
    pub(super) acquire: RawAcquire,
    pub(super) safety: RawSafety,
    pub(super) sweep: RawSweep,
    #[serde(default)]
    pub(super) reconstruct: RawReconstruct,
    #[serde(default)]
    pub(super) quality: RawQuality,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub(super) struct RawQuality {
    pub(super) reference_min_found_fraction: Option<f64>,
    pub(super) min_ok_fraction: Option<f64>,
    pub(super) max_reacquire: Option<i64>,
    pub(super) on_fail: Option<String>,
    pub(super) dead_camera_setpoints: Option<i64>,
    pub(super) force_ratio_min: Option<f64>,
    pub(super) force_ratio_max: Option<f64>,
    pub(super) force_noise_floor_n: Option<f64>,
    pub(super) max_implausible_rows: Option<i64>,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub(super) struct RawReconstruct {
    pub(super) solver: Option<String>,
    pub(super) lambda: Option<toml::Value>,
    pub(super) rank: Option<toml::Value>,
    pub(super) refine_iterations: Option<i64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawIndenter {
    pub(super) shape: String,
    pub(super) diameter_mm: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawApproach {
    #[serde(deserialize_with = "crate::config::exact")]
    pub(super) position_mm: [f64; 2],
    pub(super) speed_mm_s: f64,
    pub(super) contact_force: f64,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub(super) struct RawControl {
    pub(super) force_tolerance: Option<f64>,
    pub(super) max_steps: Option<i64>,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub(super) struct RawSettle {
    pub(super) window_s: Option<f64>,
    pub(super) max_sd: Option<f64>,
    pub(super) timeout_s: Option<f64>,
    pub(super) dwell_s: Option<f64>,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub(super) struct RawAcquire {
    pub(super) samples: Option<i64>,
    pub(super) frames: Option<i64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawSafety {
    #[serde(deserialize_with = "crate::config::exact")]
    pub(super) max_force: [f64; 3],
    #[serde(deserialize_with = "crate::config::exact")]
    pub(super) travel_min_mm: [f64; 3],
    #[serde(deserialize_with = "crate::config::exact")]
    pub(super) travel_max_mm: [f64; 3],
    pub(super) max_speed_mm_s: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawSweep {
    pub(super) kind: String,
    pub(super) from: Option<f64>,
    pub(super) to: Option<f64>,
    pub(super) step: Option<f64>,
    pub(super) trials: Option<i64>,
    pub(super) force: Option<f64>,
    pub(super) angle_from_deg: Option<f64>,
    pub(super) angle_to_deg: Option<f64>,
    pub(super) angle_step_deg: Option<f64>,
    pub(super) direction_deg: Option<f64>,
    #[serde(default, deserialize_with = "crate::config::exact_opt")]
    pub(super) start_mm: Option<[f64; 2]>,
    #[serde(default, deserialize_with = "crate::config::exact_opt")]
    pub(super) end_mm: Option<[f64; 2]>,
    pub(super) subdivisions: Option<i64>,
    #[serde(default, deserialize_with = "crate::config::exact_opt")]
    pub(super) shift_mm: Option<[f64; 2]>,
    pub(super) points: Option<Vec<RawPoint>>,
    pub(super) direction: Option<String>,
    #[serde(default, deserialize_with = "crate::config::exact_each_opt")]
    pub(super) positions_mm: Option<Vec<[f64; 2]>>,
    pub(super) duration_s: Option<f64>,
    pub(super) sample_interval_s: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawPoint {
    #[serde(deserialize_with = "crate::config::exact")]
    pub(super) position_mm: [f64; 2],
    pub(super) normal: f64,
    #[serde(default, deserialize_with = "crate::config::exact_opt")]
    pub(super) tangential: Option<[f64; 2]>,
}
