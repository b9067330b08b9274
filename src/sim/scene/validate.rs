//! Reading a `scene.toml`: the file's raw schema (serde, every key checked, unknown
//! keys rejected with their line) and its validation into a [`Scene`], one step per
//! table in the order the errors are reported (the schema is in the [`super`] docs).

use std::fmt;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::{
    check_physics, BenchEffects, ForceRelaxation, FtNoise, Scene, SceneError, Viscoelastic,
    MAX_FRAMES, MAX_FT_ROTATION_DEG, MAX_STAGE_OFFSET_MM,
};
use crate::sensor::{ModelKind, Sensor};
use crate::sim::camera::CameraOptics;
use crate::sim::contact::{Indenter, LoadCase, Normal, Tangential};
use crate::sim::effects::{Effect, Focal, Pipeline};
use crate::sim::render::PixelFilter;
use crate::units;

/// Parses scene TOML into its raw schema; the errors name the file (and the line).
pub(super) fn parse_raw(text: &str, path: &Path) -> Result<RawScene, SceneError> {
    // Through the shared parser so fixed-length arrays are checked alike (config::exact).
    crate::config::parse_toml(text, path).map_err(|e| match e {
        crate::config::ConfigError::Invalid {
            path,
            key,
            value,
            allowed,
        } => SceneError::Invalid {
            path,
            key,
            value,
            allowed,
        },
        other => SceneError::Parse {
            path: path.to_path_buf(),
            message: match other {
                crate::config::ConfigError::Parse { message, .. } => message,
                e => e.to_string(),
            },
        },
    })
}

// ---- raw schema -----------------------------------------------------------------------

/// A scene file as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawScene {
    /// The sensor file as written (relative to the scene file).
    pub(super) sensor: String,
    pixel_filter: Option<String>,
    indenter: RawIndenter,
    load: RawLoad,
    sequence: Option<RawSequence>,
    #[serde(default)]
    effects: Vec<RawEffect>,
    bench: Option<RawSceneBench>,
    physics: Option<RawPhysics>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPhysics {
    model: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSceneBench {
    ft_noise: Option<RawFtNoise>,
    force_relaxation: Option<RawRelaxation>,
    #[serde(default)]
    stage_carries_sensor: bool,
    #[serde(default, deserialize_with = "crate::config::exact_opt")]
    carry_zero_mm: Option<[f64; 2]>,
    viscoelastic: Option<RawViscoelastic>,
    ft_rotation_deg: Option<f64>,
    #[serde(default, deserialize_with = "crate::config::exact_opt")]
    stage_offset_mm: Option<[f64; 2]>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawViscoelastic {
    creep: Option<f64>,
    time_constant_s: Option<f64>,
    hysteresis: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawFtNoise {
    sigma_n: f64,
    seed: u64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRelaxation {
    fraction: f64,
    time_constant_s: f64,
}

#[derive(Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
enum RawIndenter {
    Flat { diameter_mm: f64 },
    Hemisphere { radius_mm: f64 },
    Point {},
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawLoad {
    #[serde(deserialize_with = "crate::config::exact")]
    position_mm: [f64; 2],
    normal_force_n: Option<f64>,
    normal_force_gf: Option<f64>,
    total_force_n: Option<f64>,
    total_force_gf: Option<f64>,
    depth_mm: Option<f64>,
    tangential_force_n: Option<f64>,
    tangential_force_gf: Option<f64>,
    angle_deg: Option<f64>,
    direction_deg: Option<f64>,
    friction_coefficient: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSequence {
    frames: i64,
}

#[derive(Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
enum RawEffect {
    PixelNoise {
        sigma_8bit: f64,
        seed: u64,
    },
    ShotNoise {
        full_scale_photons: f64,
        seed: u64,
    },
    Quantize8 {},
    Blur {
        sigma_px: std::collections::BTreeMap<String, f64>,
    },
    Illumination {
        #[serde(deserialize_with = "crate::config::exact")]
        gradient: [f64; 2],
    },
    Vignetting {
        strength: f64,
        #[serde(default, deserialize_with = "crate::config::exact_opt")]
        center_px: Option<[f64; 2]>,
    },
    Glare {
        center_px: [f64; 2],
        sigma_px: f64,
        amplitude: f64,
    },
    SizeJitter {
        sigma_mm: f64,
        seed: u64,
    },
    PlacementJitter {
        sigma_mm: f64,
        seed: u64,
    },
    Shift {
        #[serde(deserialize_with = "crate::config::exact")]
        shift_px: [f64; 2],
    },
    Drift {
        #[serde(deserialize_with = "crate::config::exact")]
        px_per_frame: [f64; 2],
        random_walk_px: Option<f64>,
        seed: Option<u64>,
    },
    Occlusion {
        #[serde(deserialize_with = "crate::config::exact")]
        rect_px: [f64; 4],
        level: Option<f64>,
        #[serde(default, deserialize_with = "crate::config::exact_opt")]
        frames: Option<[u64; 2]>,
    },
    Perspective {
        distance_mm: f64,
        focal_px: Option<f64>,
        reference_depth_mm: Option<f64>,
        #[serde(default, deserialize_with = "crate::config::exact_opt")]
        principal_point_px: Option<[f64; 2]>,
    },
    Refraction {
        plate_index: f64,
        plate_thickness_mm: f64,
        elastomer_index: f64,
    },
    LensDistortion {
        k1: Option<f64>,
        k2: Option<f64>,
        k3: Option<f64>,
        p1: Option<f64>,
        p2: Option<f64>,
        #[serde(default, deserialize_with = "crate::config::exact_opt")]
        center_px: Option<[f64; 2]>,
        norm_px: Option<f64>,
    },
}

// ---- validation: one step per table, in the order the file's errors are reported ------

/// Builds the `SceneError::Invalid` of one scene file and checks the common ranges.
struct Check<'a> {
    path: &'a Path,
}

impl Check<'_> {
    fn invalid(&self, key: &str, value: &dyn fmt::Display, allowed: &str) -> SceneError {
        SceneError::Invalid {
            path: self.path.to_path_buf(),
            key: key.to_string(),
            value: value.to_string(),
            allowed: allowed.to_string(),
        }
    }

    fn positive(&self, key: &str, v: f64, unit: &str) -> Result<f64, SceneError> {
        if v.is_finite() && v > 0.0 {
            Ok(v)
        } else {
            Err(self.invalid(key, &v, &format!("must be a finite number > 0 {unit}")))
        }
    }

    fn nonneg(&self, key: &str, v: f64, unit: &str) -> Result<f64, SceneError> {
        if v.is_finite() && v >= 0.0 {
            Ok(v)
        } else {
            Err(self.invalid(key, &v, &format!("must be a finite number >= 0 {unit}")))
        }
    }

    /// `load.angle_deg`: an inclination from the normal, `[0, 90)` degrees.
    fn angle(&self, v: f64) -> Result<f64, SceneError> {
        if v.is_finite() && (0.0..90.0).contains(&v) {
            Ok(v)
        } else {
            Err(self.invalid(
                "load.angle_deg",
                &v,
                "must be in [0, 90) degrees from the normal",
            ))
        }
    }
}

impl RawScene {
    /// Validates the tables in the file's order of checks (indenter, load, sequence,
    /// effects, pixel filter, bench, physics): the first invalid value is reported.
    pub(super) fn validate(
        self,
        path: &Path,
        sensor_path: PathBuf,
        sensor: Sensor,
    ) -> Result<Scene, SceneError> {
        let ck = Check { path };
        let indenter = self.indenter.validate(&ck)?;
        let load = self.load.validate(&ck, indenter)?;
        let frames = sequence_frames(&ck, self.sequence)?;
        let pipeline = effects_pipeline(&ck, self.effects, &sensor)?;
        let pixel_filter = pixel_filter(&ck, self.pixel_filter.as_deref())?;
        let bench = match self.bench {
            None => BenchEffects::default(),
            Some(b) => b.validate(&ck)?,
        };
        let physics = physics_model(&ck, self.physics, &sensor)?;
        Ok(Scene {
            bench,
            physics,
            pixel_filter,
            path: path.to_path_buf(),
            sensor_path,
            sensor,
            indenter,
            load,
            frames,
            pipeline,
        })
    }
}

impl RawIndenter {
    /// `[indenter]`: the shape, its size > 0 mm.
    fn validate(self, ck: &Check) -> Result<Indenter, SceneError> {
        Ok(match self {
            RawIndenter::Flat { diameter_mm } => Indenter::Flat {
                diameter_mm: ck.positive("indenter.diameter_mm", diameter_mm, "mm")?,
            },
            RawIndenter::Hemisphere { radius_mm } => Indenter::Hemisphere {
                radius_mm: ck.positive("indenter.radius_mm", radius_mm, "mm")?,
            },
            RawIndenter::Point {} => Indenter::Point,
        })
    }
}

/// A `[load]` key given and its value.
type KeyValue = (&'static str, f64);

/// The keys of `[load]` that say how hard the indenter presses: exactly one is given.
const NORMAL_KEYS: &str =
    "give exactly one of normal_force_n, normal_force_gf, total_force_n, total_force_gf, depth_mm";

impl RawLoad {
    /// `[load]`: the position, exactly one normal key, at most one tangential key
    /// (see the module docs), the direction and the friction coefficient.
    fn validate(self, ck: &Check, indenter: Indenter) -> Result<LoadCase, SceneError> {
        for (i, v) in self.position_mm.iter().enumerate() {
            if !v.is_finite() {
                return Err(ck.invalid(
                    &format!("load.position_mm[{i}]"),
                    v,
                    "must be finite (mm)",
                ));
            }
        }
        let ((nkey, nval), tangential) = self.given_keys(ck)?;
        let key = format!("load.{nkey}");
        let unit = if nkey.ends_with("_gf") {
            "gf"
        } else if nkey == "depth_mm" {
            "mm"
        } else {
            "N"
        };
        let nval = ck.nonneg(&key, nval, unit)?;
        let direction_deg = self.direction_deg.unwrap_or(0.0);
        if !direction_deg.is_finite() {
            return Err(ck.invalid(
                "load.direction_deg",
                &direction_deg,
                "must be finite (degrees)",
            ));
        }
        let (normal, tangential) = match nkey {
            "total_force_n" | "total_force_gf" => {
                total_force(ck, nkey, nval, tangential, direction_deg)?
            }
            _ => (
                normal_load(ck, nkey, nval, indenter)?,
                tangential_load(ck, tangential, direction_deg)?,
            ),
        };
        let friction = ck.nonneg(
            "load.friction_coefficient",
            self.friction_coefficient.unwrap_or(1.0),
            "",
        )?;
        Ok(LoadCase {
            position_mm: self.position_mm,
            normal,
            tangential,
            friction,
        })
    }

    /// The one normal key with its value, and the tangential key given, if any.
    fn given_keys(&self, ck: &Check) -> Result<(KeyValue, Option<KeyValue>), SceneError> {
        let normals: Vec<(&str, f64)> = [
            ("normal_force_n", self.normal_force_n),
            ("normal_force_gf", self.normal_force_gf),
            ("total_force_n", self.total_force_n),
            ("total_force_gf", self.total_force_gf),
            ("depth_mm", self.depth_mm),
        ]
        .into_iter()
        .filter_map(|(k, v)| v.map(|v| (k, v)))
        .collect();
        let tangentials: Vec<(&str, f64)> = [
            ("tangential_force_n", self.tangential_force_n),
            ("tangential_force_gf", self.tangential_force_gf),
            ("angle_deg", self.angle_deg),
        ]
        .into_iter()
        .filter_map(|(k, v)| v.map(|v| (k, v)))
        .collect();
        let (nkey, nval) = match normals.as_slice() {
            [one] => *one,
            [] => return Err(ck.invalid("load", &"(none)", NORMAL_KEYS)),
            many => {
                let keys: Vec<&str> = many.iter().map(|(k, _)| *k).collect();
                return Err(ck.invalid("load", &keys.join(" and "), NORMAL_KEYS));
            }
        };
        if tangentials.len() > 1 {
            let keys: Vec<&str> = tangentials.iter().map(|(k, _)| *k).collect();
            return Err(ck.invalid(
                "load",
                &keys.join(" and "),
                "give at most one of tangential_force_n, tangential_force_gf, angle_deg",
            ));
        }
        Ok(((nkey, nval), tangentials.first().copied()))
    }
}

/// A total force `F` (N after conversion) inclined by `angle_deg`: `P = F cos θ`, and
/// the tangential part is kept as the angle (`|Q| = P tan θ = F sin θ`).
fn total_force(
    ck: &Check,
    nkey: &str,
    nval: f64,
    tangential: Option<(&str, f64)>,
    direction_deg: f64,
) -> Result<(Normal, Tangential), SceneError> {
    let f = if nkey == "total_force_gf" {
        units::gf_to_n(nval)
    } else {
        nval
    };
    Ok(match tangential {
        Some((k, _)) if k != "angle_deg" => {
            return Err(ck.invalid(
                &format!("load.{k}"),
                &"(given)",
                "a total force takes angle_deg, not a tangential force: use normal_force_* with it",
            ))
        }
        Some((_, a)) => {
            let a = ck.angle(a)?;
            (
                Normal::ForceN(f * a.to_radians().cos()),
                Tangential::Angle {
                    angle_deg: a,
                    direction_deg,
                },
            )
        }
        None => (Normal::ForceN(f), Tangential::NONE),
    })
}

/// `normal_force_*` (N after conversion) or `depth_mm` (not for a point indenter).
fn normal_load(
    ck: &Check,
    nkey: &str,
    nval: f64,
    indenter: Indenter,
) -> Result<Normal, SceneError> {
    Ok(match nkey {
        "normal_force_n" => Normal::ForceN(nval),
        "normal_force_gf" => Normal::ForceN(units::gf_to_n(nval)),
        _ => {
            if indenter == Indenter::Point {
                return Err(ck.invalid(
                    "load.depth_mm",
                    &nval,
                    "a point indenter has no indentation depth: give a normal force",
                ));
            }
            Normal::DepthMm(nval)
        }
    })
}

/// The tangential part beside a normal force or depth: an angle from the normal, or a
/// force `|Q|` (N after conversion) along the azimuth `direction_deg`.
fn tangential_load(
    ck: &Check,
    tangential: Option<(&str, f64)>,
    direction_deg: f64,
) -> Result<Tangential, SceneError> {
    let d = direction_deg.to_radians();
    Ok(match tangential {
        None => Tangential::NONE,
        Some(("angle_deg", a)) => Tangential::Angle {
            angle_deg: ck.angle(a)?,
            direction_deg,
        },
        Some((k, q)) => {
            let q = ck.nonneg(
                &format!("load.{k}"),
                q,
                if k.ends_with("_gf") { "gf" } else { "N" },
            )?;
            let q = if k.ends_with("_gf") {
                units::gf_to_n(q)
            } else {
                q
            };
            Tangential::ForceN([q * d.cos(), q * d.sin()])
        }
    })
}

/// `[sequence] frames`, 1 without the table.
fn sequence_frames(ck: &Check, sequence: Option<RawSequence>) -> Result<usize, SceneError> {
    match sequence {
        None => Ok(1),
        Some(s) => {
            if (1..=MAX_FRAMES as i64).contains(&s.frames) {
                Ok(s.frames as usize)
            } else {
                Err(ck.invalid(
                    "sequence.frames",
                    &s.frames,
                    &format!("must be an integer in [1, {MAX_FRAMES}]"),
                ))
            }
        }
    }
}

/// `[[effects]]`: each read in list order, then the list checked as a whole
/// ([`Pipeline::new`]: ranges and order) and against the sensor's camera
/// ([`CameraOptics::check`]).
fn effects_pipeline(
    ck: &Check,
    raw: Vec<RawEffect>,
    sensor: &Sensor,
) -> Result<Pipeline, SceneError> {
    let mut effects = Vec::with_capacity(raw.len());
    for (i, e) in raw.into_iter().enumerate() {
        effects.push(e.validate(ck, i, sensor)?);
    }
    Pipeline::new(effects, sensor.layers.len())
        .and_then(|p| CameraOptics::check(&p, sensor).map(|()| p))
        .map_err(|source| SceneError::Effect {
            path: ck.path.to_path_buf(),
            source,
        })
}

impl RawEffect {
    /// Effect `i` of the list: its keys resolved (layer names, defaults); the ranges
    /// are [`Pipeline::new`]'s to check.
    fn validate(self, ck: &Check, i: usize, sensor: &Sensor) -> Result<Effect, SceneError> {
        Ok(match self {
            RawEffect::PixelNoise { sigma_8bit, seed } => Effect::PixelNoise { sigma_8bit, seed },
            RawEffect::ShotNoise {
                full_scale_photons,
                seed,
            } => Effect::ShotNoise {
                full_scale_photons,
                seed,
            },
            RawEffect::Quantize8 {} => Effect::Quantize8,
            RawEffect::Blur { sigma_px } => Effect::Blur {
                sigma_px: blur_by_layer(ck, i, sigma_px, sensor)?,
            },
            RawEffect::Illumination { gradient } => Effect::Illumination { gradient },
            RawEffect::Vignetting {
                strength,
                center_px,
            } => Effect::Vignetting {
                strength,
                center_px,
            },
            RawEffect::Glare {
                center_px,
                sigma_px,
                amplitude,
            } => Effect::Glare {
                center_px,
                sigma_px,
                amplitude,
            },
            RawEffect::SizeJitter { sigma_mm, seed } => Effect::SizeJitter { sigma_mm, seed },
            RawEffect::PlacementJitter { sigma_mm, seed } => {
                Effect::PlacementJitter { sigma_mm, seed }
            }
            RawEffect::Shift { shift_px } => Effect::Shift { shift_px },
            RawEffect::Drift {
                px_per_frame,
                random_walk_px,
                seed,
            } => drift(ck, i, px_per_frame, random_walk_px, seed)?,
            RawEffect::Occlusion {
                rect_px,
                level,
                frames,
            } => Effect::Occlusion {
                rect_px,
                level: level.unwrap_or(0.5),
                first_frame: frames.map_or(1, |f| f[0]),
                last_frame: frames.map(|f| f[1]),
            },
            RawEffect::Perspective {
                distance_mm,
                focal_px,
                reference_depth_mm,
                principal_point_px,
            } => Effect::Perspective {
                distance_mm,
                focal: focal(ck, i, focal_px, reference_depth_mm)?,
                principal_point_px,
            },
            RawEffect::Refraction {
                plate_index,
                plate_thickness_mm,
                elastomer_index,
            } => Effect::Refraction {
                plate_index,
                plate_thickness_mm,
                elastomer_index,
            },
            RawEffect::LensDistortion {
                k1,
                k2,
                k3,
                p1,
                p2,
                center_px,
                norm_px,
            } => Effect::LensDistortion {
                k1: k1.unwrap_or(0.0),
                k2: k2.unwrap_or(0.0),
                k3: k3.unwrap_or(0.0),
                p1: p1.unwrap_or(0.0),
                p2: p2.unwrap_or(0.0),
                center_px,
                norm_px,
            },
        })
    }
}

/// A blur's `sigma_px` by layer name, as σ per layer index (unlisted layers 0: sharp).
fn blur_by_layer(
    ck: &Check,
    i: usize,
    by_name: std::collections::BTreeMap<String, f64>,
    sensor: &Sensor,
) -> Result<Vec<f64>, SceneError> {
    let mut sigma_px = vec![0.0; sensor.layers.len()];
    for (name, s) in by_name {
        let li = sensor.layer_index(&name).ok_or_else(|| {
            let names: Vec<&str> = sensor.layers.iter().map(|l| l.name.as_str()).collect();
            ck.invalid(
                &format!("effects[{i}].sigma_px.{name}"),
                &s,
                &format!("unknown layer: the sensor has {}", names.join(", ")),
            )
        })?;
        sigma_px[li] = s;
    }
    Ok(sigma_px)
}

/// A drift; a random walk needs a seed (none is only allowed without one).
fn drift(
    ck: &Check,
    i: usize,
    px_per_frame: [f64; 2],
    random_walk_px: Option<f64>,
    seed: Option<u64>,
) -> Result<Effect, SceneError> {
    let random_walk_px = random_walk_px.unwrap_or(0.0);
    if random_walk_px > 0.0 && seed.is_none() {
        return Err(ck.invalid(
            &format!("effects[{i}].seed"),
            &"(missing)",
            "a drift with random_walk_px > 0 needs a seed",
        ));
    }
    Ok(Effect::Drift {
        px_per_frame,
        random_walk_px,
        seed: seed.unwrap_or(0),
    })
}

/// A perspective's focal length: exactly one of `focal_px` or `reference_depth_mm`.
fn focal(
    ck: &Check,
    i: usize,
    focal_px: Option<f64>,
    reference_depth_mm: Option<f64>,
) -> Result<Focal, SceneError> {
    match (focal_px, reference_depth_mm) {
        (Some(f), None) => Ok(Focal::Px(f)),
        (None, Some(d)) => Ok(Focal::ReferenceDepthMm(d)),
        (given, _) => Err(ck.invalid(
            &format!("effects[{i}]"),
            &if given.is_some() {
                "focal_px and reference_depth_mm"
            } else {
                "(neither)"
            },
            "perspective needs exactly one of focal_px (focal length / pixel pitch, px) or reference_depth_mm (the depth imaged at [camera] mm_per_px)",
        )),
    }
}

/// `pixel_filter`: `area` (the default) or `tent`.
fn pixel_filter(ck: &Check, name: Option<&str>) -> Result<PixelFilter, SceneError> {
    match name {
        None | Some("area") => Ok(PixelFilter::Area),
        Some("tent") => Ok(PixelFilter::Tent),
        Some(other) => Err(ck.invalid(
            "pixel_filter",
            &format!("{other:?}"),
            "expected \"area\" or \"tent\"",
        )),
    }
}

impl RawSceneBench {
    /// `[bench]`: each effect's ranges, then the keys that exclude each other.
    fn validate(self, ck: &Check) -> Result<BenchEffects, SceneError> {
        let ft_noise = match self.ft_noise {
            None => None,
            Some(n) => Some(FtNoise {
                sigma_n: ck.positive("bench.ft_noise.sigma_n", n.sigma_n, "N")?,
                seed: n.seed,
            }),
        };
        let force_relaxation = match self.force_relaxation {
            None => None,
            Some(r) => Some(ForceRelaxation {
                fraction: ck.nonneg("bench.force_relaxation.fraction", r.fraction, "")?,
                time_constant_s: ck.positive(
                    "bench.force_relaxation.time_constant_s",
                    r.time_constant_s,
                    "s",
                )?,
            }),
        };
        let carry_zero_mm = carry_zero(ck, self.stage_carries_sensor, self.carry_zero_mm)?;
        let viscoelastic = match self.viscoelastic {
            None => None,
            Some(v) => Some(v.validate(ck)?),
        };
        let ft_rotation_deg = match self.ft_rotation_deg {
            Some(t) if !(t.is_finite() && t.abs() <= MAX_FT_ROTATION_DEG) => {
                return Err(ck.invalid(
                    "bench.ft_rotation_deg",
                    &t,
                    &format!(
                        "must be in [-{MAX_FT_ROTATION_DEG}, {MAX_FT_ROTATION_DEG}] degrees (the F/T sensor's rotation about z)"
                    ),
                ))
            }
            t => t,
        };
        let stage_offset_mm = stage_offset(ck, self.stage_offset_mm, carry_zero_mm)?;
        Ok(BenchEffects {
            ft_noise,
            force_relaxation,
            carry_zero_mm,
            viscoelastic,
            ft_rotation_deg,
            stage_offset_mm,
        })
    }
}

/// `carry_zero_mm`: required with `stage_carries_sensor = true`, refused without it.
fn carry_zero(
    ck: &Check,
    stage_carries_sensor: bool,
    carry_zero_mm: Option<[f64; 2]>,
) -> Result<Option<[f64; 2]>, SceneError> {
    match (stage_carries_sensor, carry_zero_mm) {
        (true, Some(z)) if z.iter().all(|v| v.is_finite()) => Ok(Some(z)),
        (true, Some(z)) => Err(ck.invalid(
            "bench.carry_zero_mm",
            &format!("{z:?}"),
            "must be finite (mm)",
        )),
        (true, None) => Err(ck.invalid(
            "bench.carry_zero_mm",
            &"(missing)",
            "stage_carries_sensor = true needs carry_zero_mm = [x, y] (mm)",
        )),
        (false, Some(_)) => Err(ck.invalid(
            "bench.carry_zero_mm",
            &"(given)",
            "only used with stage_carries_sensor = true",
        )),
        (false, None) => Ok(None),
    }
}

impl RawViscoelastic {
    /// `bench.viscoelastic`: creep ≥ 0 (with a time constant > 0 s when > 0),
    /// hysteresis in `[0, 1]`, and at least one of them > 0.
    fn validate(self, ck: &Check) -> Result<Viscoelastic, SceneError> {
        let creep = ck.nonneg("bench.viscoelastic.creep", self.creep.unwrap_or(0.0), "")?;
        let hysteresis = self.hysteresis.unwrap_or(0.0);
        if !(hysteresis.is_finite() && (0.0..=1.0).contains(&hysteresis)) {
            return Err(ck.invalid(
                "bench.viscoelastic.hysteresis",
                &hysteresis,
                "must be in [0, 1] (widest down - up difference / peak force)",
            ));
        }
        let time_constant_s = match self.time_constant_s {
            Some(t) => ck.positive("bench.viscoelastic.time_constant_s", t, "s")?,
            None if creep > 0.0 => {
                return Err(ck.invalid(
                    "bench.viscoelastic.time_constant_s",
                    &"(missing)",
                    "creep > 0 needs a time constant > 0 s",
                ))
            }
            None => 1.0,
        };
        if creep == 0.0 && hysteresis == 0.0 {
            return Err(ck.invalid(
                "bench.viscoelastic",
                &"(no effect)",
                "give creep > 0 and/or hysteresis > 0, or leave the effect out",
            ));
        }
        Ok(Viscoelastic {
            creep,
            time_constant_s,
            hysteresis,
        })
    }
}

/// `stage_offset_mm`: each component within ±[`MAX_STAGE_OFFSET_MM`], and not with a
/// carried sensor (whose contact stays at `carry_zero_mm`).
fn stage_offset(
    ck: &Check,
    offset: Option<[f64; 2]>,
    carry_zero_mm: Option<[f64; 2]>,
) -> Result<Option<[f64; 2]>, SceneError> {
    let stage_offset_mm = match offset {
        Some(o) if !o.iter().all(|v| v.is_finite() && v.abs() <= MAX_STAGE_OFFSET_MM) => {
            return Err(ck.invalid(
                "bench.stage_offset_mm",
                &format!("[{}, {}]", o[0], o[1]),
                &format!(
                    "each component must be in [-{MAX_STAGE_OFFSET_MM}, {MAX_STAGE_OFFSET_MM}] mm (a larger offset is a wrong [geometry] sensor_origin_in_stage_mm)"
                ),
            ))
        }
        o => o,
    };
    if let (Some(o), Some(_)) = (stage_offset_mm, carry_zero_mm) {
        return Err(ck.invalid(
            "bench.stage_offset_mm",
            &format!("[{}, {}]", o[0], o[1]),
            "cannot be combined with stage_carries_sensor = true (the contact stays at carry_zero_mm): remove one of them",
        ));
    }
    Ok(stage_offset_mm)
}

/// `[physics] model` (default the half-space), checked against the sensor's caps
/// ([`check_physics`]).
fn physics_model(
    ck: &Check,
    physics: Option<RawPhysics>,
    sensor: &Sensor,
) -> Result<ModelKind, SceneError> {
    let physics = match physics.and_then(|p| p.model) {
        None => ModelKind::HalfSpace,
        Some(name) => ModelKind::from_name(&name).ok_or_else(|| {
            ck.invalid(
                "physics.model",
                &format!("{name:?}"),
                "must be \"half-space\" or \"bonded-layer\"",
            )
        })?,
    };
    check_physics(physics, sensor).map_err(|e| {
        ck.invalid(
            "physics.model",
            &format!("{:?}", physics.name()),
            &e.to_string(),
        )
    })?;
    Ok(physics)
}
