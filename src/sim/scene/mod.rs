//! `scene.toml`: a simulated experiment (sensor, indenter, load, frames, effects),
//! parsed once into a validated [`Scene`].
//!
//! Schema (every key is checked; unknown keys are rejected with their line):
//!
//! ```toml
//! sensor = "../paper_sensor.toml"   # sensor file, relative to this scene file
//! pixel_filter = "area"    # optional: area (default; exact pixel coverage) | tent
//!                          # (exact centroids, see sim::render::PixelFilter)
//!
//! [indenter]
//! kind = "flat"            # flat | hemisphere | point
//! diameter_mm = 5.0        # flat: face diameter
//! # radius_mm = 2.5        # hemisphere: radius
//!
//! [load]
//! position_mm = [9.0, 7.0] # indenter centre in the sensor frame
//! # exactly one of:
//! normal_force_gf = 910.0  # or normal_force_n: the normal component P
//! # total_force_n / total_force_gf: the force magnitude F, inclined by angle_deg
//! #                                 (P = F cos θ, |Q| = F sin θ)
//! # depth_mm = 0.5         # indentation depth (flat: P = 2aE*δ; hemisphere: Hertz)
//! # at most one of:
//! # tangential_force_n = 1.0 / tangential_force_gf = 100.0   # |Q|
//! # angle_deg = 20.0       # inclination from the normal, [0, 90): |Q| = P tan θ
//! direction_deg = 0.0      # azimuth of Q from +x towards +y (default 0)
//! friction_coefficient = 1.0  # μ (default 1.0): |Q| is clamped to μP, with a warning
//!
//! [sequence]               # optional
//! frames = 10              # load ramped linearly: loaded frame k = 1..N carries k/N
//!                          # of the normal force or depth and of a tangential force
//!                          # (an angle is kept); default 1
//!
//! [[effects]]              # optional, any number, applied in this order
//! kind = "pixel_noise"
//! sigma_8bit = 2.0
//! seed = 1
//! ```
//!
//! Effect kinds and their keys (see [`super::effects`] for the models):
//!
//! | kind | keys |
//! |---|---|
//! | `pixel_noise` | `sigma_8bit` (Gaussian σ in 8-bit levels), `seed` |
//! | `shot_noise` | `full_scale_photons` (photons at value 1.0), `seed` |
//! | `quantize8` | — (frames are then written as 8-bit PNG) |
//! | `blur` | `sigma_px = { <layer name> = σ, … }` (px; unlisted layers stay sharp) |
//! | `illumination` | `gradient = [g_x, g_y]` (relative gain change across the image) |
//! | `vignetting` | `strength` (relative loss at the farthest corner), optional `center_px` |
//! | `glare` | `center_px = [x, y]`, `sigma_px` (Gaussian σ of the bright spot), `amplitude` (level added at its centre, in [0, 1]) |
//! | `size_jitter` | `sigma_mm` (marker diameter σ), `seed` |
//! | `placement_jitter` | `sigma_mm` (per-axis marker position σ), `seed` |
//! | `shift` | `shift_px = [dx, dy]` (whole image, loaded frames only) |
//! | `drift` | `px_per_frame = [dx, dy]`, optional `random_walk_px` (σ per frame) and `seed` |
//! | `occlusion` | `rect_px = [x0, y0, x1, y1]` (pixel centres covered), optional `level` (grey, default 0.5) and `frames = [first, last]` (inclusive; default every loaded frame, 1 on; 0 = the reference) |
//!
//! | `perspective` | `distance_mm` (pinhole below the plate–elastomer interface, mm), exactly one of `focal_px` (focal length / pixel pitch, px) or `reference_depth_mm` (the depth shown at the `[camera]` `mm_per_px`), optional `principal_point_px = [x, y]` (default the image centre) |
//! | `refraction` | `plate_index`, `plate_thickness_mm` (< the perspective's `distance_mm`), `elastomer_index` (indices in [1, 4]); the elastomer thickness is the sensor's `thickness_mm`; needs `perspective` |
//! | `lens_distortion` | `k1`, `k2`, `k3`, `p1`, `p2` (Brown–Conrady, each default 0); with `perspective` about its principal point, normalised by its focal length; without it `norm_px` (required, px) and `center_px` (default the image centre) |
//!
//! The camera effects (models and geometry in [`super::camera`]) are opt-in: with none
//! listed, the frames are the linear `[camera]` mapping's, bit for bit. Each may be
//! listed once, e.g.
//!
//! ```toml
//! [[effects]]
//! kind = "perspective"
//! distance_mm = 30.0          # pinhole 30 mm below the plate-elastomer interface
//! reference_depth_mm = 3.0    # the 3 mm layer is imaged at [camera] mm_per_px
//! [[effects]]
//! kind = "refraction"
//! plate_index = 1.49          # acrylic
//! plate_thickness_mm = 5.0
//! elastomer_index = 1.41      # silicone
//! [[effects]]
//! kind = "lens_distortion"
//! k1 = -0.3
//! ```
//!
//! Marker-level effects (`size_jitter`, `placement_jitter`, `shift`, `drift`, `blur`,
//! the camera effects)
//! must come before image effects (`illumination`, `vignetting`, `glare`, `shot_noise`,
//! `pixel_noise`, `quantize8`, `occlusion`).
//!
//! Effects of the simulated bench (`tactbench sim bench`, `tactbench run --sim`), all
//! optional and off unless listed (models in [`super::world`]):
//!
//! ```toml
//! [bench]
//! ft_noise = { sigma_n = 0.005, seed = 1 }   # Gaussian σ (N) per force component
//!                                            # of every F/T sample, seeded
//! force_relaxation = { fraction = 0.05, time_constant_s = 0.3 }
//!                          # viscoelastic creep: a force step overshoots by `fraction`
//!                          # and relaxes with time constant τ (s)
//! stage_carries_sensor = true  # the stage's xy motion shifts the whole sensor under
//! carry_zero_mm = [9.0, 6.75]  # the camera; unshifted with the tip over this point
//! viscoelastic = { creep = 0.05, time_constant_s = 2.0, hysteresis = 0.02 }
//!                          # what the camera sees (the F/T side is force_relaxation):
//!                          # creep: under a constant load the marker displacements
//!                          # grow as 1 + creep·(1 − e^(−t/τ)) and recover with τ after
//!                          # unloading; hysteresis h: unloading from a peak P the
//!                          # field is that of F + 4h·F·(P − F)/P (loop width h·P at
//!                          # P/2). Either may be 0 (default); τ is needed with creep
//! ft_rotation_deg = 7.0    # the F/T sensor mounted rotated by +θ about z (degrees,
//!                          # [-180, 180]): it reports R(θ)ᵀF and R(θ)ᵀM
//! stage_offset_mm = [0.4, 0.0]  # the contact happens at the stage's notion of the
//!                          # contact point + [dx, dy] (mm, sensor frame, each within
//!                          # ±5); the runner and its journal still believe the stage
//! ```
//!
//! The elastic model the simulation renders with (independent of the sensor file's
//! `[elastomer] model`, which is what the solvers invert, so a scene can show the
//! model error of a solver):
//!
//! ```toml
//! [physics]
//! model = "bonded-layer"   # "half-space" (default: paper Eq. 1–2) | "bonded-layer"
//!                          # (the sensor's elastomer.thickness_mm on a rigid plate)
//! ```
//!
//! With no `[physics]` table the simulation renders with the half-space, exactly as
//! before the key existed.
//!
//! With no `[bench]` table the bench is ideal and exact. `[load]` is not used by the
//! simulated bench (the stage decides the load), except `friction_coefficient`, which
//! `tactbench run --sim` uses as the indenter/elastomer friction μ.

use std::path::{Path, PathBuf};

use thiserror::Error;

use super::contact::{Indenter, LoadCase};
use super::effects::{EffectError, Pipeline};
use super::render::PixelFilter;
use crate::sensor::{ModelKind, Sensor, SensorError};

mod validate;

use validate::parse_raw;

/// Largest number of frames in a sequence.
pub const MAX_FRAMES: usize = 100_000;

/// Gaussian noise on the force sensor's force components.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FtNoise {
    /// σ per component per sample, N.
    pub sigma_n: f64,
    /// Seed of the noise stream.
    pub seed: u64,
}

/// Viscoelastic force relaxation after a change of indentation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ForceRelaxation {
    /// Excess fraction `a` of a force step that relaxes away (≥ 0).
    pub fraction: f64,
    /// Relaxation time constant τ, s (> 0).
    pub time_constant_s: f64,
}

/// The elastomer's viscoelastic creep and rate-independent hysteresis as the camera
/// sees them (model in [`super::world`]): the marker displacement field is that of the
/// elastic contact scaled by `(F_e + c + h_term) / F_e`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Viscoelastic {
    /// Creep fraction `a` (≥ 0): under a constant load the displacements grow as
    /// `1 + a·(1 − e^{−t/τ})`.
    pub creep: f64,
    /// Creep (and recovery) time constant τ, s (> 0).
    pub time_constant_s: f64,
    /// Hysteresis width `h` (in [0, 1]): unloading from a peak `P`, the camera sees
    /// `F + 4h·F·(P − F)/P`, a loop whose widest point (at `P/2`) is `h·P`.
    pub hysteresis: f64,
}

/// Opt-in effects of the simulated bench (see the module docs). The default is none:
/// ideal and exact.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct BenchEffects {
    /// Noise on F/T samples.
    pub ft_noise: Option<FtNoise>,
    /// Force relaxation.
    pub force_relaxation: Option<ForceRelaxation>,
    /// The stage carries the sensor: the sensor-frame point where the image is
    /// unshifted (and where the contact stays), mm.
    pub carry_zero_mm: Option<[f64; 2]>,
    /// Creep and hysteresis of the displacement field the camera sees.
    pub viscoelastic: Option<Viscoelastic>,
    /// The F/T sensor is mounted rotated by +θ (degrees) about z relative to the
    /// sensor frame: it reports `R(θ)ᵀ F` and `R(θ)ᵀ M` (the convention of
    /// [`crate::fit::ModelParams`]).
    pub ft_rotation_deg: Option<f64>,
    /// The contact happens at the stage's notion of the contact point plus this
    /// offset `[dx, dy]` (mm, camera's sensor frame); the runner and the journal still
    /// believe the stage's notion.
    pub stage_offset_mm: Option<[f64; 2]>,
}

/// Largest `|ft_rotation_deg|` of the simulated bench, degrees (a mounting error, not a
/// different axis convention).
pub const MAX_FT_ROTATION_DEG: f64 = 180.0;

/// Largest `|dx|`, `|dy|` of `stage_offset_mm`, mm (beyond it the bench file's
/// `sensor_origin_in_stage_mm` is wrong, not the mount).
pub const MAX_STAGE_OFFSET_MM: f64 = 5.0;

/// An error reading or validating a scene file. Every variant names the file.
#[derive(Debug, Error)]
pub enum SceneError {
    /// The file could not be read.
    #[error("cannot read scene file {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// Not valid TOML for the schema (syntax, unknown key, wrong type), with line.
    #[error("{path}: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// The parser's message.
        message: String,
    },
    /// A value is invalid.
    #[error("{path}: {key} = {value} is invalid: {allowed}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// The key, e.g. `load.normal_force_gf`.
        key: String,
        /// The value as given.
        value: String,
        /// What is allowed, with units.
        allowed: String,
    },
    /// The referenced sensor file is invalid.
    #[error("{path}: sensor file: {source}")]
    Sensor {
        /// The scene file.
        path: PathBuf,
        /// The sensor error.
        source: SensorError,
    },
    /// An effect is invalid.
    #[error("{path}: {source}")]
    Effect {
        /// The scene file.
        path: PathBuf,
        /// The effect error.
        source: EffectError,
    },
}

/// Checks that the elastic model `physics` can render this sensor within its caps:
/// the bonded layer's tables cover the marker depths over twice the camera's field
/// (what [`super::Simulation::with_physics`] prepares), and their size is checked
/// before any is built.
pub fn check_physics(physics: ModelKind, sensor: &Sensor) -> Result<(), crate::model::ModelError> {
    use crate::model::ElasticModel;
    let cam = &sensor.camera;
    let reach = 2.0 * (cam.width_px as f64).hypot(cam.height_px as f64) * cam.mm_per_px;
    let depths: Vec<f64> = sensor.layers.iter().map(|l| l.depth_mm).collect();
    crate::model::ForwardModel::of_kind(physics, &sensor.elastomer).check_reach(&depths, reach)
}

/// A validated scene.
#[derive(Debug, Clone)]
pub struct Scene {
    /// The scene file (for messages).
    pub path: PathBuf,
    /// The sensor file, resolved against the scene's directory.
    pub sensor_path: PathBuf,
    /// The sensor.
    pub sensor: Sensor,
    /// The indenter.
    pub indenter: Indenter,
    /// The full load (the last frame of a sequence).
    pub load: LoadCase,
    /// Number of loaded frames (≥ 1).
    pub frames: usize,
    /// The effects.
    pub pipeline: Pipeline,
    /// The pixel response of the renderer.
    pub pixel_filter: PixelFilter,
    /// Opt-in effects of the simulated bench (`[bench]`; default none).
    pub bench: BenchEffects,
    /// The elastic model rendered (`[physics] model`; default the half-space).
    pub physics: ModelKind,
}

impl Scene {
    /// Reads and validates a scene file and the sensor file it references.
    pub fn from_path(path: impl AsRef<Path>) -> Result<Scene, SceneError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let raw = parse_raw(&text, path)?;
        let dir = path.parent().unwrap_or(Path::new("."));
        let sensor_path = dir.join(&raw.sensor);
        let sensor = Sensor::from_path(&sensor_path).map_err(|source| SceneError::Sensor {
            path: path.to_path_buf(),
            source,
        })?;
        raw.validate(path, sensor_path, sensor)
    }

    /// Parses scene TOML with an already loaded sensor (the `sensor` key is kept as
    /// written, unresolved); `path` is used in messages only.
    pub fn from_toml_str(
        text: &str,
        path: impl AsRef<Path>,
        sensor: Sensor,
    ) -> Result<Scene, SceneError> {
        let path = path.as_ref();
        let raw = parse_raw(text, path)?;
        let sensor_path = PathBuf::from(&raw.sensor);
        raw.validate(path, sensor_path, sensor)
    }

    /// The load of loaded frame `k` (1-based, `1..=frames`): the ramp step `k / frames`.
    pub fn frame_load(&self, k: usize) -> LoadCase {
        self.load.scaled(k as f64 / self.frames as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sensor::paper_sensor;

    fn scene(bench: &str) -> Result<Scene, SceneError> {
        let text = format!(
            "sensor = \"s.toml\"\n[indenter]\nkind = \"hemisphere\"\nradius_mm = 2.5\n[load]\nposition_mm = [9.0, 6.75]\nnormal_force_n = 1.0\n{bench}"
        );
        Scene::from_toml_str(&text, "scene.toml", paper_sensor())
    }

    #[test]
    fn without_mounting_keys_the_bench_is_as_before() {
        let s = scene("[bench]\nft_noise = { sigma_n = 0.01, seed = 3 }\n").unwrap();
        assert_eq!(s.bench.ft_rotation_deg, None);
        assert_eq!(s.bench.stage_offset_mm, None);
        assert_eq!(scene("").unwrap().bench, BenchEffects::default());
    }

    #[test]
    fn mounting_keys_are_read_in_degrees_and_mm() {
        let s = scene("[bench]\nft_rotation_deg = 7.0\nstage_offset_mm = [0.4, -0.1]\n").unwrap();
        assert_eq!(s.bench.ft_rotation_deg, Some(7.0));
        assert_eq!(s.bench.stage_offset_mm, Some([0.4, -0.1]));
    }

    #[test]
    fn mounting_keys_out_of_range_are_refused_naming_key_value_and_unit() {
        let e = scene("[bench]\nft_rotation_deg = 270.0\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("bench.ft_rotation_deg = 270") && e.contains("degrees"),
            "{e}"
        );
        let e = scene("[bench]\nstage_offset_mm = [0.4, 12.0]\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("bench.stage_offset_mm = [0.4, 12]") && e.contains("mm"),
            "{e}"
        );
        let e = scene("[bench]\nstage_offset_mm = [0.4]\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("stage_offset_mm"), "{e}");
        let e = scene(
            "[bench]\nstage_carries_sensor = true\ncarry_zero_mm = [9.0, 6.75]\nstage_offset_mm = [0.4, 0.0]\n",
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("stage_carries_sensor"), "{e}");
    }

    /// The error of a `[bench]` table, which must name the scene file.
    fn bench_error(bench: &str) -> String {
        let e = scene(bench).unwrap_err().to_string();
        assert!(e.contains("scene.toml"), "{e}");
        e
    }

    #[test]
    fn non_finite_mounting_keys_are_refused_naming_file_key_and_value() {
        for (text, key, value) in [
            ("ft_rotation_deg = nan", "bench.ft_rotation_deg", "NaN"),
            ("ft_rotation_deg = -inf", "bench.ft_rotation_deg", "-inf"),
            (
                "stage_offset_mm = [inf, 0.0]",
                "bench.stage_offset_mm",
                "[inf, 0]",
            ),
            (
                "stage_offset_mm = [0.4, nan]",
                "bench.stage_offset_mm",
                "[0.4, NaN]",
            ),
        ] {
            let e = bench_error(&format!("[bench]\n{text}\n"));
            assert!(e.contains(&format!("{key} = {value}")), "{text}: {e}");
        }
    }

    #[test]
    fn a_rotation_beyond_half_a_turn_is_refused_in_degrees() {
        let e = bench_error("[bench]\nft_rotation_deg = -180.5\n");
        assert!(e.contains("bench.ft_rotation_deg = -180.5"), "{e}");
        assert!(e.contains("[-180, 180] degrees"), "{e}");
        assert_eq!(
            scene("[bench]\nft_rotation_deg = -180.0\n")
                .unwrap()
                .bench
                .ft_rotation_deg,
            Some(-180.0)
        );
    }

    #[test]
    fn a_stage_offset_of_the_wrong_length_or_type_is_refused_naming_key_and_value() {
        // Fixed-length arrays are checked by the shared parser (config::exact_opt),
        // naming the key, the line and how many values were given.
        for (text, given) in [
            ("stage_offset_mm = [0.4]", "1 elements given"),
            ("stage_offset_mm = [0.4, 0.0, 0.1]", "3 elements given"),
        ] {
            let e = bench_error(&format!("[bench]\n{text}\n"));
            assert!(
                e.contains("bench.stage_offset_mm")
                    && e.contains("(line 9)")
                    && e.contains(given)
                    && e.contains("exactly 2 expected"),
                "{text}: {e}"
            );
        }
        // A value of the wrong type: the TOML parser quotes the line, key and value.
        for text in [
            "stage_offset_mm = 0.4",
            "stage_offset_mm = [\"0.4\", 0.0]",
            "ft_rotation_deg = \"7\"",
        ] {
            let e = bench_error(&format!("[bench]\n{text}\n"));
            assert!(
                e.contains("line 9") && e.contains(text) && e.contains("invalid type"),
                "{text}: {e}"
            );
        }
    }

    #[test]
    fn a_stage_offset_with_a_carried_sensor_is_refused_naming_both_keys_and_the_offset() {
        let e = bench_error(
            "[bench]\nstage_carries_sensor = true\ncarry_zero_mm = [9.0, 6.75]\nstage_offset_mm = [0.4, 0.0]\n",
        );
        assert!(
            e.contains("bench.stage_offset_mm = [0.4, 0]") && e.contains("stage_carries_sensor"),
            "{e}"
        );
    }
}
