//! Imaging and manufacturing effects, each a separate unit with its own parameters
//! (and its own seed when random), applied only when a scene lists it, in the listed
//! order. With no effects the render is the ideal one of [`super::render`], bit for bit.
//!
//! Effects act at three stages of a frame:
//!
//! 1. **Build** (once per scene, on the reference marker list, before the contact
//!    model): [`Effect::SizeJitter`] and [`Effect::PlacementJitter`] model marker
//!    manufacturing: each marker's diameter / reference position is perturbed once and
//!    stays so in every frame (the ground truth reports the perturbed positions).
//! 2. **Scene** (per frame, before rasterisation): [`Effect::Shift`] (a rigid
//!    whole-image shift of the loaded frames, not the reference: the paper's Table I
//!    test), [`Effect::Drift`] (an image offset growing frame by frame) move every disc
//!    by a sub-pixel offset, so centroids move by exactly the offset; [`Effect::Blur`]
//!    (depth defocus) rasterises each layer to a coverage map, blurs it with the
//!    layer's Gaussian σ and composites the layers (a layer can only be blurred before
//!    it is composited behind the deeper ones).
//! 3. **Image** (per frame, on the float RGB frame, in list order):
//!    [`Effect::Illumination`], [`Effect::Vignetting`], [`Effect::Glare`], [`Effect::ShotNoise`],
//!    [`Effect::PixelNoise`], [`Effect::Quantize8`], [`Effect::Occlusion`].
//!
//! The camera effects [`Effect::Perspective`], [`Effect::Refraction`] and
//! [`Effect::LensDistortion`] are scene-stage effects too: they decide where each
//! marker centre appears in the image (from its depth and `u_z`) and how large its
//! disc is; the models are in [`super::camera`]. Each may be listed once; refraction
//! needs perspective.
//!
//! Because of this, build and scene effects must be listed before image effects
//! ([`Pipeline::new`] rejects other orders rather than silently reordering).
//!
//! Frame indices: the reference (unloaded) frame is index 0, loaded frames 1, 2, ….
//! Random image effects draw frame `k` from stream `k` of their seed, so each frame is
//! reproducible alone and the reference and the loaded frames get independent noise.

use image::Rgb32FImage;
use thiserror::Error;

use super::render::{disc_visit, fill, round_code, Marker, RenderError, Renderer};
use super::rng::Rng;

/// How the focal length of `perspective` is given.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Focal {
    /// Focal length in px (focal length / pixel pitch).
    Px(f64),
    /// The depth (mm) at which the camera shows exactly the `[camera]` `mm_per_px`.
    ReferenceDepthMm(f64),
}

/// An invalid effect parameter.
#[derive(Debug, Error, PartialEq)]
pub enum EffectError {
    /// A parameter is out of range.
    #[error("effects[{index}] ({kind}): {key} = {value} is invalid: {allowed}")]
    Invalid {
        /// Position in the effect list.
        index: usize,
        /// Effect kind.
        kind: &'static str,
        /// The parameter.
        key: &'static str,
        /// The value as given.
        value: String,
        /// What is allowed, with units.
        allowed: String,
    },
    /// An effect acting before rasterisation is listed after an image effect.
    #[error(
        "effects[{index}] ({kind}) acts on the markers before rasterisation and must be listed \
         before the image effect effects[{image_index}] ({image_kind})"
    )]
    Order {
        /// Position of the misplaced effect.
        index: usize,
        /// Its kind.
        kind: &'static str,
        /// Position of the earlier image effect.
        image_index: usize,
        /// Its kind.
        image_kind: &'static str,
    },
}

/// One effect with its parameters.
#[derive(Debug, Clone, PartialEq)]
pub enum Effect {
    /// Additive Gaussian pixel noise, σ in 8-bit levels (σ/255 in float), independent
    /// per pixel and channel.
    PixelNoise {
        /// Standard deviation in 8-bit levels (≥ 0).
        sigma_8bit: f64,
        /// Seed.
        seed: u64,
    },
    /// Photon shot noise: a value `v` becomes `Poisson(v N) / N` with `N` the photons
    /// collected at full scale (v = 1), per pixel and channel.
    ShotNoise {
        /// Photons (electrons) at full scale, > 0.
        full_scale_photons: f64,
        /// Seed.
        seed: u64,
    },
    /// Rounding to 8-bit code values: `round(255 clamp(v, 0, 1)) / 255`.
    Quantize8,
    /// Depth defocus: each layer's coverage blurred by a Gaussian of σ px (0 = sharp),
    /// truncated at ±4σ. Several blur entries compose (their variances add).
    Blur {
        /// σ in px per layer index of the sensor.
        sigma_px: Vec<f64>,
    },
    /// Linear illumination gradient: gain `1 + g_x (x/(W−1) − ½) + g_y (y/(H−1) − ½)`
    /// on pixel centres (`g` is the relative gain change across the whole image).
    Illumination {
        /// `[g_x, g_y]`, with `|g_x| + |g_y| ≤ 2` so the gain stays ≥ 0.
        gradient: [f64; 2],
    },
    /// Radial fall-off: gain `1 − strength (ρ/ρ_max)²`, `ρ` the distance from the
    /// centre, `ρ_max` that of the farthest image corner.
    Vignetting {
        /// Relative loss at the farthest corner, in [0, 1].
        strength: f64,
        /// Optical centre in px (default: the image centre).
        center_px: Option<[f64; 2]>,
    },
    /// Glare: a bright spot (a reflection of the light source on the gel or the
    /// plate) added to every channel, `amplitude · exp(−ρ² / (2σ²))`, `ρ` the distance
    /// from `center_px`; deterministic, in every frame.
    Glare {
        /// Centre of the spot, px.
        center_px: [f64; 2],
        /// Gaussian σ of the spot, px (> 0).
        sigma_px: f64,
        /// Added level at the centre (1 = full scale), in [0, 1].
        amplitude: f64,
    },
    /// Marker diameters perturbed once: `d + N(0, σ)`, clamped at 0.
    SizeJitter {
        /// σ in mm.
        sigma_mm: f64,
        /// Seed.
        seed: u64,
    },
    /// Marker reference positions perturbed once by `N(0, σ)` per axis.
    PlacementJitter {
        /// σ in mm.
        sigma_mm: f64,
        /// Seed.
        seed: u64,
    },
    /// Rigid image shift of the loaded frames (frame index ≥ 1), px.
    Shift {
        /// `[dx, dy]` in px.
        shift_px: [f64; 2],
    },
    /// Image offset at frame `k`: `k · px_per_frame + Σ_{i=1..k} N(0, σ_walk)` per axis.
    Drift {
        /// Deterministic drift per frame, px.
        px_per_frame: [f64; 2],
        /// Random-walk step σ per frame, px (0 = none).
        random_walk_px: f64,
        /// Seed (used only when `random_walk_px > 0`).
        seed: u64,
    },
    /// Something in front of the markers (a finger, dust, a cable) in some frames:
    /// the pixels whose centres lie in the rectangle become a flat grey `level`, so
    /// the markers under it are lost.
    Occlusion {
        /// `[x0, y0, x1, y1]`, px: pixel centres with `x0 ≤ x < x1`, `y0 ≤ y < y1`.
        rect_px: [f64; 4],
        /// Grey level in [0, 1].
        level: f64,
        /// First frame occluded (0 = the reference).
        first_frame: u64,
        /// Last frame occluded, inclusive (`None`: every frame from `first_frame` on).
        last_frame: Option<u64>,
    },
    /// A pinhole camera below the plate (see [`super::camera`]): each marker is
    /// projected from its depth (layer depth plus `u_z`).
    Perspective {
        /// Pinhole below the plate–elastomer interface, mm (> 0).
        distance_mm: f64,
        /// Focal length, or the depth imaged at the `[camera]` scale.
        focal: Focal,
        /// Principal point, px (default the image centre).
        principal_point_px: Option<[f64; 2]>,
    },
    /// Snell refraction at the elastomer–plate and plate–air interfaces along each
    /// marker's ray to the pinhole (needs `perspective`).
    Refraction {
        /// Refractive index of the plate (≥ 1; acrylic 1.49).
        plate_index: f64,
        /// Plate thickness, mm (≥ 0, less than the perspective's `distance_mm`).
        plate_thickness_mm: f64,
        /// Refractive index of the elastomer (≥ 1; silicone ≈ 1.41).
        elastomer_index: f64,
    },
    /// Brown–Conrady lens distortion of the projected marker centres.
    LensDistortion {
        /// Radial r² coefficient.
        k1: f64,
        /// Radial r⁴ coefficient.
        k2: f64,
        /// Radial r⁶ coefficient.
        k3: f64,
        /// Tangential p1.
        p1: f64,
        /// Tangential p2.
        p2: f64,
        /// Centre, px (only without `perspective`; default the image centre).
        center_px: Option<[f64; 2]>,
        /// Normalisation radius, px (only and required without `perspective`).
        norm_px: Option<f64>,
    },
}

/// Stage of an effect (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Stage {
    /// Once per scene, on the reference markers.
    Build,
    /// Per frame, before or during rasterisation.
    Scene,
    /// Per frame, on the float image.
    Image,
}

impl Effect {
    /// The kind name used in scene files.
    pub fn kind(&self) -> &'static str {
        match self {
            Effect::PixelNoise { .. } => "pixel_noise",
            Effect::ShotNoise { .. } => "shot_noise",
            Effect::Quantize8 => "quantize8",
            Effect::Blur { .. } => "blur",
            Effect::Illumination { .. } => "illumination",
            Effect::Vignetting { .. } => "vignetting",
            Effect::Glare { .. } => "glare",
            Effect::SizeJitter { .. } => "size_jitter",
            Effect::PlacementJitter { .. } => "placement_jitter",
            Effect::Shift { .. } => "shift",
            Effect::Drift { .. } => "drift",
            Effect::Occlusion { .. } => "occlusion",
            Effect::Perspective { .. } => "perspective",
            Effect::Refraction { .. } => "refraction",
            Effect::LensDistortion { .. } => "lens_distortion",
        }
    }

    /// Where in the frame pipeline the effect acts.
    pub fn stage(&self) -> Stage {
        match self {
            Effect::SizeJitter { .. } | Effect::PlacementJitter { .. } => Stage::Build,
            Effect::Shift { .. }
            | Effect::Drift { .. }
            | Effect::Blur { .. }
            | Effect::Perspective { .. }
            | Effect::Refraction { .. }
            | Effect::LensDistortion { .. } => Stage::Scene,
            _ => Stage::Image,
        }
    }

    /// Checks the effect's own parameters (`index`: its place in the list, for the
    /// message); what depends on the other effects is [`Pipeline::new`]'s.
    fn check(&self, index: usize) -> Result<(), EffectError> {
        let ck = Check {
            index,
            kind: self.kind(),
        };
        match self {
            Effect::PixelNoise { sigma_8bit, .. } => {
                ck.nonneg("sigma_8bit", *sigma_8bit, "(8-bit levels)")
            }
            Effect::ShotNoise {
                full_scale_photons, ..
            } => {
                if full_scale_photons.is_finite() && *full_scale_photons > 0.0 {
                    Ok(())
                } else {
                    Err(ck.bad(
                        "full_scale_photons",
                        full_scale_photons.to_string(),
                        "must be a finite number > 0 (photons at full scale)",
                    ))
                }
            }
            Effect::Quantize8 => Ok(()),
            Effect::Blur { sigma_px } => {
                for &s in sigma_px {
                    ck.nonneg("sigma_px", s, "px")?;
                }
                Ok(())
            }
            Effect::Illumination { gradient } => check_illumination(&ck, *gradient),
            Effect::Vignetting {
                strength,
                center_px,
            } => check_vignetting(&ck, *strength, *center_px),
            Effect::Glare {
                center_px,
                sigma_px,
                amplitude,
            } => check_glare(&ck, *center_px, *sigma_px, *amplitude),
            Effect::SizeJitter { sigma_mm, .. } | Effect::PlacementJitter { sigma_mm, .. } => {
                ck.nonneg("sigma_mm", *sigma_mm, "mm")
            }
            Effect::Shift { shift_px } => ck.finite2("shift_px", *shift_px, "px"),
            Effect::Drift {
                px_per_frame,
                random_walk_px,
                ..
            } => {
                ck.finite2("px_per_frame", *px_per_frame, "px per frame")?;
                ck.nonneg("random_walk_px", *random_walk_px, "px")
            }
            Effect::Occlusion {
                rect_px,
                level,
                first_frame,
                last_frame,
            } => check_occlusion(&ck, *rect_px, *level, *first_frame, *last_frame),
            Effect::Perspective {
                distance_mm,
                focal,
                principal_point_px,
            } => check_perspective(&ck, *distance_mm, *focal, *principal_point_px),
            Effect::Refraction {
                plate_index,
                plate_thickness_mm,
                elastomer_index,
            } => check_refraction(&ck, *plate_index, *plate_thickness_mm, *elastomer_index),
            Effect::LensDistortion {
                k1,
                k2,
                k3,
                p1,
                p2,
                center_px,
                norm_px,
            } => check_lens_distortion(
                &ck,
                [
                    ("k1", *k1),
                    ("k2", *k2),
                    ("k3", *k3),
                    ("p1", *p1),
                    ("p2", *p2),
                ],
                *center_px,
                *norm_px,
            ),
        }
    }
}

/// Builds the `EffectError::Invalid` of one effect and checks the common ranges.
struct Check {
    /// Position in the effect list.
    index: usize,
    /// Effect kind.
    kind: &'static str,
}

impl Check {
    fn bad(&self, key: &'static str, value: String, allowed: &str) -> EffectError {
        EffectError::Invalid {
            index: self.index,
            kind: self.kind,
            key,
            value,
            allowed: allowed.to_string(),
        }
    }

    fn nonneg(&self, key: &'static str, v: f64, unit: &str) -> Result<(), EffectError> {
        if v.is_finite() && v >= 0.0 {
            Ok(())
        } else {
            Err(self.bad(
                key,
                v.to_string(),
                &format!("must be a finite number >= 0 {unit}"),
            ))
        }
    }

    fn finite2(&self, key: &'static str, v: [f64; 2], unit: &str) -> Result<(), EffectError> {
        if v[0].is_finite() && v[1].is_finite() {
            Ok(())
        } else {
            Err(self.bad(
                key,
                format!("{v:?}"),
                &format!("must be two finite numbers ({unit})"),
            ))
        }
    }
}

/// `illumination`: finite, and `|g_x| + |g_y| ≤ 2` so the gain stays ≥ 0 everywhere.
fn check_illumination(ck: &Check, gradient: [f64; 2]) -> Result<(), EffectError> {
    ck.finite2(
        "gradient",
        gradient,
        "relative gain change across the image",
    )?;
    if gradient[0].abs() + gradient[1].abs() <= 2.0 {
        Ok(())
    } else {
        Err(ck.bad(
            "gradient",
            format!("{gradient:?}"),
            "needs |g_x| + |g_y| <= 2 (gain >= 0)",
        ))
    }
}

/// `vignetting`: a relative loss in `[0, 1]`, a finite centre.
fn check_vignetting(
    ck: &Check,
    strength: f64,
    center_px: Option<[f64; 2]>,
) -> Result<(), EffectError> {
    if !(strength.is_finite() && (0.0..=1.0).contains(&strength)) {
        return Err(ck.bad(
            "strength",
            strength.to_string(),
            "must be in [0, 1] (relative loss at the corner)",
        ));
    }
    match center_px {
        Some(c) => ck.finite2("center_px", c, "px"),
        None => Ok(()),
    }
}

/// `glare`: a finite centre, σ > 0 px, an added level in `[0, 1]`.
fn check_glare(
    ck: &Check,
    center_px: [f64; 2],
    sigma_px: f64,
    amplitude: f64,
) -> Result<(), EffectError> {
    ck.finite2("center_px", center_px, "px")?;
    if !(sigma_px.is_finite() && sigma_px > 0.0) {
        return Err(ck.bad(
            "sigma_px",
            format!("{sigma_px} px"),
            "must be a finite number > 0 px (Gaussian σ of the spot)",
        ));
    }
    if !(amplitude.is_finite() && (0.0..=1.0).contains(&amplitude)) {
        return Err(ck.bad(
            "amplitude",
            amplitude.to_string(),
            "must be in [0, 1] (added level at the centre, 1 = full scale)",
        ));
    }
    Ok(())
}

/// `occlusion`: a non-empty finite rectangle, a grey level in `[0, 1]`, and
/// `first <= last` frames.
fn check_occlusion(
    ck: &Check,
    rect_px: [f64; 4],
    level: f64,
    first_frame: u64,
    last_frame: Option<u64>,
) -> Result<(), EffectError> {
    if !(rect_px.iter().all(|v| v.is_finite())
        && rect_px[0] < rect_px[2]
        && rect_px[1] < rect_px[3])
    {
        return Err(ck.bad(
            "rect_px",
            format!("{rect_px:?}"),
            "must be [x0, y0, x1, y1] px with x0 < x1 and y0 < y1",
        ));
    }
    if !(level.is_finite() && (0.0..=1.0).contains(&level)) {
        return Err(ck.bad("level", level.to_string(), "must be a grey level in [0, 1]"));
    }
    match last_frame {
        Some(l) if l < first_frame => Err(ck.bad(
            "frames",
            format!("[{first_frame}, {l}]"),
            "must be [first, last] with first <= last (frame indices, 0 = reference)",
        )),
        _ => Ok(()),
    }
}

/// `perspective`: the pinhole's distance > 0 mm, a focal length > 0 px or a reference
/// depth >= 0 mm, a finite principal point.
fn check_perspective(
    ck: &Check,
    distance_mm: f64,
    focal: Focal,
    principal_point_px: Option<[f64; 2]>,
) -> Result<(), EffectError> {
    if !(distance_mm.is_finite() && distance_mm > 0.0) {
        return Err(ck.bad(
            "distance_mm",
            format!("{distance_mm} mm"),
            "must be a finite number > 0 mm (pinhole below the plate-elastomer interface)",
        ));
    }
    match focal {
        Focal::Px(f) if !(f.is_finite() && f > 0.0) => {
            return Err(ck.bad(
                "focal_px",
                format!("{f} px"),
                "must be a finite number > 0 px (focal length / pixel pitch)",
            ))
        }
        Focal::ReferenceDepthMm(d) if !(d.is_finite() && d >= 0.0) => {
            return Err(ck.bad(
                "reference_depth_mm",
                format!("{d} mm"),
                "must be a finite depth >= 0 mm",
            ))
        }
        _ => {}
    }
    match principal_point_px {
        Some(c) => ck.finite2("principal_point_px", c, "px"),
        None => Ok(()),
    }
}

/// `refraction`: both indices in `[1, 4]`, a plate thickness >= 0 mm (that it is less
/// than the perspective's distance is [`Pipeline::new`]'s check).
fn check_refraction(
    ck: &Check,
    plate_index: f64,
    plate_thickness_mm: f64,
    elastomer_index: f64,
) -> Result<(), EffectError> {
    for (key, n) in [
        ("plate_index", plate_index),
        ("elastomer_index", elastomer_index),
    ] {
        if !(n.is_finite() && (1.0..=4.0).contains(&n)) {
            return Err(ck.bad(
                key,
                n.to_string(),
                "must be a refractive index in [1, 4] (acrylic 1.49, silicone 1.41)",
            ));
        }
    }
    ck.nonneg("plate_thickness_mm", plate_thickness_mm, "mm")
}

/// `lens_distortion`: finite coefficients `k1, k2, k3, p1, p2` (by name), a finite
/// centre, a normalisation radius > 0 px (whether they may or must be given is
/// [`Pipeline::new`]'s check).
fn check_lens_distortion(
    ck: &Check,
    coefficients: [(&'static str, f64); 5],
    center_px: Option<[f64; 2]>,
    norm_px: Option<f64>,
) -> Result<(), EffectError> {
    for (key, v) in coefficients {
        if !v.is_finite() {
            return Err(ck.bad(key, v.to_string(), "must be finite"));
        }
    }
    if let Some(c) = center_px {
        ck.finite2("center_px", c, "px")?;
    }
    match norm_px {
        Some(n) if !(n.is_finite() && n > 0.0) => Err(ck.bad(
            "norm_px",
            format!("{n} px"),
            "must be a finite number > 0 px",
        )),
        _ => Ok(()),
    }
}

/// A validated, ordered list of effects, and the frame pipeline that applies them.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Pipeline {
    effects: Vec<Effect>,
}

/// Reusable buffers of the blur path.
#[derive(Debug, Default)]
pub struct Scratch {
    coverage: Vec<f32>,
    tmp: Vec<f32>,
    moved: Vec<Marker>,
}

impl Pipeline {
    /// Checks every parameter and the stage order (build and scene effects before image
    /// effects). `layers` is the sensor's layer count (for blur's per-layer σ).
    pub fn new(effects: Vec<Effect>, layers: usize) -> Result<Self, EffectError> {
        let mut first_image: Option<(usize, &'static str)> = None;
        for (i, e) in effects.iter().enumerate() {
            e.check(i)?;
            if let Effect::Blur { sigma_px } = e {
                if sigma_px.len() != layers {
                    return Err(EffectError::Invalid {
                        index: i,
                        kind: "blur",
                        key: "sigma_px",
                        value: format!("{} values", sigma_px.len()),
                        allowed: format!("needs one σ per sensor layer ({layers})"),
                    });
                }
            }
            if matches!(
                e,
                Effect::Perspective { .. }
                    | Effect::Refraction { .. }
                    | Effect::LensDistortion { .. }
            ) {
                if let Some(j) = effects[..i].iter().position(|o| o.kind() == e.kind()) {
                    return Err(EffectError::Invalid {
                        index: i,
                        kind: e.kind(),
                        key: "kind",
                        value: format!("{:?}", e.kind()),
                        allowed: format!(
                            "listed twice (also effects[{j}]): one camera of each kind"
                        ),
                    });
                }
            }
            match (e.stage(), first_image) {
                (Stage::Image, None) => first_image = Some((i, e.kind())),
                (Stage::Build | Stage::Scene, Some((image_index, image_kind))) => {
                    return Err(EffectError::Order {
                        index: i,
                        kind: e.kind(),
                        image_index,
                        image_kind,
                    })
                }
                _ => {}
            }
        }
        let perspective = effects.iter().find_map(|e| match e {
            Effect::Perspective { distance_mm, .. } => Some(*distance_mm),
            _ => None,
        });
        for (i, e) in effects.iter().enumerate() {
            let bad = |key: &'static str, value: String, allowed: &str| EffectError::Invalid {
                index: i,
                kind: e.kind(),
                key,
                value,
                allowed: allowed.to_string(),
            };
            match (e, perspective) {
                (Effect::Refraction { .. }, None) => {
                    return Err(bad(
                        "kind",
                        "\"refraction\"".into(),
                        "needs the perspective effect: an orthographic camera's rays cross the flat interfaces at normal incidence and are not refracted",
                    ))
                }
                (
                    Effect::Refraction {
                        plate_thickness_mm, ..
                    },
                    Some(d),
                ) if *plate_thickness_mm >= d => {
                    return Err(bad(
                        "plate_thickness_mm",
                        format!("{plate_thickness_mm} mm"),
                        &format!("must be less than the perspective's distance_mm = {d} mm (the plate lies between the elastomer and the pinhole)"),
                    ))
                }
                (
                    Effect::LensDistortion {
                        center_px,
                        norm_px,
                        ..
                    },
                    Some(_),
                ) if center_px.is_some() || norm_px.is_some() => {
                    let key = if center_px.is_some() { "center_px" } else { "norm_px" };
                    return Err(bad(
                        key,
                        "(given)".into(),
                        "with perspective the distortion is about its principal point, normalised by its focal length: remove the key",
                    ));
                }
                (Effect::LensDistortion { norm_px: None, .. }, None) => {
                    return Err(bad(
                        "norm_px",
                        "(missing)".into(),
                        "without perspective the distortion needs norm_px, the radius in px that counts as r = 1",
                    ))
                }
                _ => {}
            }
        }
        Ok(Pipeline { effects })
    }

    /// True when the list has a camera effect (`perspective`, `refraction`,
    /// `lens_distortion`): marker centres are then projected by
    /// [`super::camera::CameraOptics`] instead of the linear `[camera]` mapping.
    pub fn has_camera_effects(&self) -> bool {
        self.effects.iter().any(|e| {
            matches!(
                e,
                Effect::Perspective { .. }
                    | Effect::Refraction { .. }
                    | Effect::LensDistortion { .. }
            )
        })
    }

    /// No effects: the ideal render.
    pub fn ideal() -> Self {
        Pipeline::default()
    }

    /// The effects, in order.
    pub fn effects(&self) -> &[Effect] {
        &self.effects
    }

    /// True when the list contains [`Effect::Quantize8`] (frames are then written as
    /// 8-bit PNG).
    pub fn quantizes_to_8bit(&self) -> bool {
        self.effects.iter().any(|e| matches!(e, Effect::Quantize8))
    }

    /// Applies the build-stage effects (size and placement jitter) to the reference
    /// markers, in list order. Marker `k` always receives draw `k` of the effect's
    /// seed, so the perturbation of a marker does not depend on the other effects.
    pub fn build_markers(&self, markers: &mut [Marker]) {
        for e in &self.effects {
            match *e {
                Effect::SizeJitter { sigma_mm, seed } => {
                    let mut rng = Rng::new(seed);
                    for m in markers.iter_mut() {
                        m.diameter_mm = (m.diameter_mm + sigma_mm * rng.normal()).max(0.0);
                    }
                }
                Effect::PlacementJitter { sigma_mm, seed } => {
                    let mut rng = Rng::new(seed);
                    for m in markers.iter_mut() {
                        m.position_mm[0] += sigma_mm * rng.normal();
                        m.position_mm[1] += sigma_mm * rng.normal();
                    }
                }
                _ => {}
            }
        }
    }

    /// The whole-image offset in px of frame `frame` (0 = reference) from the shift and
    /// drift effects.
    pub fn image_offset_px(&self, frame: u64) -> [f64; 2] {
        let mut off = [0.0, 0.0];
        for e in &self.effects {
            match *e {
                Effect::Shift { shift_px } if frame > 0 => {
                    off[0] += shift_px[0];
                    off[1] += shift_px[1];
                }
                Effect::Drift {
                    px_per_frame,
                    random_walk_px,
                    seed,
                } => {
                    let k = frame as f64;
                    off[0] += k * px_per_frame[0];
                    off[1] += k * px_per_frame[1];
                    if random_walk_px > 0.0 {
                        let mut rng = Rng::new(seed);
                        for _ in 0..frame {
                            off[0] += random_walk_px * rng.normal();
                            off[1] += random_walk_px * rng.normal();
                        }
                    }
                }
                _ => {}
            }
        }
        off
    }

    /// Renders frame `frame` (0 = reference) of `markers` (already built, i.e. after
    /// [`Pipeline::build_markers`], and displaced) into `out`: image offset, ideal or
    /// blurred rasterisation, then the image effects in list order.
    pub fn render_frame(
        &self,
        renderer: &Renderer,
        markers: &[Marker],
        frame: u64,
        out: &mut Rgb32FImage,
        scratch: &mut Scratch,
    ) -> Result<(), RenderError> {
        let off = self.image_offset_px(frame);
        let mm = renderer.camera().mm_per_px;
        let src: &[Marker] = if off == [0.0, 0.0] {
            markers
        } else {
            scratch.moved.clear();
            scratch.moved.extend(markers.iter().map(|m| Marker {
                position_mm: [
                    m.position_mm[0] + off[0] * mm,
                    m.position_mm[1] + off[1] * mm,
                ],
                ..*m
            }));
            &scratch.moved
        };
        // Several blur entries compose: Gaussians add their variances per layer.
        let mut blur: Option<Vec<f64>> = None;
        for e in &self.effects {
            if let Effect::Blur { sigma_px } = e {
                let acc = blur.get_or_insert_with(|| vec![0.0; sigma_px.len()]);
                for (a, s) in acc.iter_mut().zip(sigma_px) {
                    *a = a.hypot(*s);
                }
            }
        }
        match blur {
            None => renderer.render_into(src, out)?,
            Some(sigma_px) => {
                // Temporarily take the moved list out so the scratch buffers can be
                // borrowed mutably alongside it.
                let moved = std::mem::take(&mut scratch.moved);
                let src: &[Marker] = if off == [0.0, 0.0] { markers } else { &moved };
                let r = render_blurred(renderer, src, &sigma_px, out, scratch);
                scratch.moved = moved;
                r?
            }
        }
        for e in &self.effects {
            apply_image_effect(e, out, frame);
        }
        Ok(())
    }
}

/// Rasterises each layer to a padded coverage map, blurs it with the layer's σ and
/// composites the layers shallowest first.
fn render_blurred(
    renderer: &Renderer,
    markers: &[Marker],
    sigma_px: &[f64],
    out: &mut Rgb32FImage,
    scratch: &mut Scratch,
) -> Result<(), RenderError> {
    renderer.check(markers, out)?;
    for (index, m) in markers.iter().enumerate() {
        if m.layer >= sigma_px.len() {
            return Err(RenderError::UnknownLayer {
                index,
                layer: m.layer,
                layers: sigma_px.len(),
            });
        }
    }
    let cam = *renderer.camera();
    let (w, h) = (cam.width_px as usize, cam.height_px as usize);
    fill(out, renderer.palette().background);
    for &layer in renderer.draw_order() {
        let sigma = sigma_px[layer];
        // Margin so discs just outside the frame blur into it.
        let m = (4.0 * sigma).ceil() as usize;
        let (pw, ph) = (w + 2 * m, h + 2 * m);
        scratch.coverage.clear();
        scratch.coverage.resize(pw * ph, 0.0);
        for mk in markers.iter().filter(|mk| mk.layer == layer) {
            let c = cam.mm_to_px(mk.position_mm);
            let r = 0.5 * mk.diameter_mm / cam.mm_per_px;
            let cov = &mut scratch.coverage;
            disc_visit(
                renderer.filter(),
                pw as u32,
                ph as u32,
                [c[0] + m as f64, c[1] + m as f64],
                r,
                |i, j, a| {
                    let v = &mut cov[j * pw + i];
                    *v = (*v + a).min(1.0);
                },
            );
        }
        if sigma > 0.0 {
            gaussian_blur(&mut scratch.coverage, &mut scratch.tmp, pw, ph, sigma);
        }
        let color = renderer.layer_color(layer);
        let data: &mut [f32] = out.as_mut();
        for j in 0..h {
            let row = &scratch.coverage[(j + m) * pw + m..(j + m) * pw + m + w];
            for (i, &a) in row.iter().enumerate() {
                if a > 0.0 {
                    let p = &mut data[3 * (j * w + i)..3 * (j * w + i) + 3];
                    for ch in 0..3 {
                        p[ch] += a * (color[ch] - p[ch]);
                    }
                }
            }
        }
    }
    Ok(())
}

/// Separable Gaussian blur of a `w × h` map, kernel truncated at ±4σ and normalised,
/// zero outside the map.
fn gaussian_blur(map: &mut [f32], tmp: &mut Vec<f32>, w: usize, h: usize, sigma: f64) {
    let rad = (4.0 * sigma).ceil() as isize;
    let mut k: Vec<f32> = (-rad..=rad)
        .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp() as f32)
        .collect();
    let sum: f32 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= sum);
    tmp.clear();
    tmp.resize(w * h, 0.0);
    // Horizontal pass: map -> tmp.
    for j in 0..h {
        let row = &map[j * w..(j + 1) * w];
        let trow = &mut tmp[j * w..(j + 1) * w];
        for (i, &v) in row.iter().enumerate() {
            if v == 0.0 {
                continue;
            }
            for (t, &kv) in k.iter().enumerate() {
                let ii = i as isize + t as isize - rad;
                if ii >= 0 && (ii as usize) < w {
                    trow[ii as usize] += v * kv;
                }
            }
        }
    }
    // Vertical pass: tmp -> map.
    map.fill(0.0);
    for j in 0..h {
        for (t, &kv) in k.iter().enumerate() {
            let jj = j as isize + t as isize - rad;
            if jj < 0 || jj as usize >= h {
                continue;
            }
            let (src, dst) = (j * w, jj as usize * w);
            for i in 0..w {
                map[dst + i] += tmp[src + i] * kv;
            }
        }
    }
}

/// Applies one image-stage effect to frame `frame` (other stages: no-op).
pub fn apply_image_effect(e: &Effect, out: &mut Rgb32FImage, frame: u64) {
    let (w, h) = out.dimensions();
    match *e {
        Effect::PixelNoise { sigma_8bit, seed } => {
            let s = (sigma_8bit / 255.0) as f32;
            let mut rng = Rng::stream(seed, frame);
            for v in out.as_mut().iter_mut() {
                *v += s * rng.normal() as f32;
            }
        }
        Effect::ShotNoise {
            full_scale_photons,
            seed,
        } => {
            let mut rng = Rng::stream(seed, frame);
            for v in out.as_mut().iter_mut() {
                let lambda = (*v as f64).max(0.0) * full_scale_photons;
                *v = (rng.poisson(lambda) / full_scale_photons) as f32;
            }
        }
        Effect::Quantize8 => {
            for v in out.as_mut().iter_mut() {
                *v = round_code(*v, 255.0) as f32 / 255.0;
            }
        }
        Effect::Illumination { gradient } => {
            let sx = if w > 1 { 1.0 / (w - 1) as f64 } else { 0.0 };
            let sy = if h > 1 { 1.0 / (h - 1) as f64 } else { 0.0 };
            for (i, j, p) in out.enumerate_pixels_mut() {
                let g =
                    1.0 + gradient[0] * (i as f64 * sx - 0.5) + gradient[1] * (j as f64 * sy - 0.5);
                p.0.iter_mut().for_each(|v| *v *= g as f32);
            }
        }
        Effect::Vignetting {
            strength,
            center_px,
        } => {
            let c = center_px.unwrap_or([(w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0]);
            let corners = [
                [0.0, 0.0],
                [w as f64 - 1.0, 0.0],
                [0.0, h as f64 - 1.0],
                [w as f64 - 1.0, h as f64 - 1.0],
            ];
            let rho2_max = corners
                .iter()
                .map(|q| (q[0] - c[0]).powi(2) + (q[1] - c[1]).powi(2))
                .fold(0.0f64, f64::max)
                .max(f64::MIN_POSITIVE);
            for (i, j, p) in out.enumerate_pixels_mut() {
                let rho2 = (i as f64 - c[0]).powi(2) + (j as f64 - c[1]).powi(2);
                let g = 1.0 - strength * rho2 / rho2_max;
                p.0.iter_mut().for_each(|v| *v *= g as f32);
            }
        }
        Effect::Glare {
            center_px,
            sigma_px,
            amplitude,
        } => {
            let k = -0.5 / (sigma_px * sigma_px);
            // Beyond 6σ the spot adds less than 1e-7 of full scale: not visited.
            let reach = 6.0 * sigma_px;
            let x0 = (center_px[0] - reach).floor().max(0.0) as u32;
            let y0 = (center_px[1] - reach).floor().max(0.0) as u32;
            let x1 = ((center_px[0] + reach).ceil().max(0.0) as u32).min(w.saturating_sub(1));
            let y1 = ((center_px[1] + reach).ceil().max(0.0) as u32).min(h.saturating_sub(1));
            for j in y0..=y1.min(h.saturating_sub(1)) {
                for i in x0..=x1 {
                    let r2 = (i as f64 - center_px[0]).powi(2) + (j as f64 - center_px[1]).powi(2);
                    let add = (amplitude * (k * r2).exp()) as f32;
                    out.get_pixel_mut(i, j).0.iter_mut().for_each(|v| *v += add);
                }
            }
        }
        Effect::Occlusion {
            rect_px,
            level,
            first_frame,
            last_frame,
        } => {
            if frame < first_frame || last_frame.is_some_and(|l| frame > l) {
                return;
            }
            let v = level as f32;
            for (i, j, p) in out.enumerate_pixels_mut() {
                let (x, y) = (i as f64, j as f64);
                if x >= rect_px[0] && x < rect_px[2] && y >= rect_px[1] && y < rect_px[3] {
                    p.0 = [v; 3];
                }
            }
        }
        _ => {}
    }
}
