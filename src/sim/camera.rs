//! The simulated camera's optics: the opt-in camera effects `perspective`,
//! `refraction` and `lens_distortion` of a scene (see [`super::effects`] for their
//! keys). With none listed the camera is the sensor file's linear `[camera]` mapping
//! (an orthographic camera, every layer at `mm_per_px`) and nothing here runs.
//!
//! **Geometry** (sensor frame, z positive into the elastomer, surface at z = 0): the
//! elastomer of `[elastomer] thickness_mm` = h lies on a plate; the camera looks up
//! through the plate. The pinhole is `distance_mm` = D below the plate–elastomer
//! interface (z = h + D), on the vertical through the sensor-frame point that the
//! `[camera]` mapping puts at the principal point `c` (default the image centre). A
//! marker at `(x, y)` and depth `z` (its layer's depth plus its `u_z`) is at
//! horizontal distance `ρ` from that axis and `a = h − z` above the interface.
//!
//! **Perspective** (pinhole, no refraction): the marker appears at
//! `p = c + f (x − x_c, y − y_c) / Z`, `Z = a + D`, `f` the focal length in px (given,
//! or chosen so that a stated reference depth `d_ref` shows exactly the `[camera]`
//! scale: `f = Z(d_ref) / mm_per_px`). Markers of different layers get different
//! magnifications `f / Z`, and `u_z > 0` (towards the camera) magnifies: the apparent
//! displacement is `f (X + u_x)/(Z − u_z) − f X / Z` (parallax `≈ f X u_z / Z²`).
//!
//! **Refraction** (needs `perspective`; an orthographic camera's rays are parallel to
//! the axis and cross the flat interfaces at normal incidence, so they are not bent):
//! the ray from the marker to the pinhole crosses the elastomer (index `n_e`,
//! thickness `a`), the plate (`n_p`, thickness `t_p`, which is part of D) and air (1,
//! `g = D − t_p`). The interfaces are planes normal to the axis, so the ray stays in
//! the plane through the axis and the marker, and Snell's law keeps `s = n sin θ`
//! constant along it. The ray is solved exactly: `s` is the root in `[0, 1)` of
//!
//! ```text
//! F(s) = a s/√(n_e² − s²) + t_p s/√(n_p² − s²) + g s/√(1 − s²) − ρ = 0,
//! ```
//!
//! (the horizontal travel in each medium, `t tan θ`), strictly increasing from `−ρ`
//! to `+∞` (indices ≥ 1, `g > 0`): Newton's method from the paraxial root
//! `ρ / (a/n_e + t_p/n_p + g)`, safeguarded by bisection, to `|ΔF| ≤ 1e-13 ρ`. The
//! marker then appears at `c + f tan θ_air (x − x_c, y − y_c)/ρ`. Refraction moves
//! the markers' apparent depth to the *reduced* distance `a/n_e + t_p/n_p + g`
//! (paraxially), so it changes each layer's magnification; the marker discs are drawn
//! with the local tangential magnification `f tan θ_air / ρ`.
//!
//! **Lens distortion** (Brown–Conrady, [`crate::vision::BrownConrady`]): applied to
//! the projected centre about the principal point, normalised by the focal length
//! (with `perspective`; OpenCV's convention), or, without `perspective`, about
//! `center_px` (default the image centre) normalised by `norm_px` (required).
//!
//! Markers are spheres; each is drawn as a disc centred on the image of its centre,
//! with radius `r · m` (`m` the local magnification in px/mm; distortion moves the
//! centre only). The small ellipticity of an off-axis sphere's image and of a disc
//! under distortion is not modelled: centroids follow the projected centres.

// `Focal` is declared with the effect it parameterises (effects does not import this
// module); re-exported here under its old path.
pub use super::effects::Focal;
use super::effects::{Effect, EffectError, Pipeline};
use crate::sensor::{CameraMapping, Sensor};
use crate::vision::BrownConrady;

/// The resolved pinhole camera.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Pinhole {
    principal_px: [f64; 2],
    focal_px: f64,
    /// Sensor-frame point above the pinhole, mm.
    axis_mm: [f64; 2],
    distance_mm: f64,
    /// `(n_e, n_p, t_p)` when refraction is listed.
    refraction: Option<(f64, f64, f64)>,
}

/// The camera optics of a scene (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct CameraOptics {
    camera: CameraMapping,
    thickness_mm: f64,
    pinhole: Option<Pinhole>,
    distortion: Option<BrownConrady>,
}

/// The solved refracted ray: `tan θ_air / ρ` (px-free), i.e. the inverse of the
/// effective distance, for a marker `a` mm above the interface at horizontal distance
/// `rho` mm, with the pinhole `d` mm below the interface.
pub fn refracted_inverse_distance(
    rho: f64,
    a: f64,
    d: f64,
    elastomer_index: f64,
    plate_index: f64,
    plate_thickness_mm: f64,
) -> f64 {
    let (ne, np, tp) = (elastomer_index, plate_index, plate_thickness_mm);
    let g = d - tp;
    let reduced = a / ne + tp / np + g;
    if rho <= 0.0 {
        return 1.0 / reduced;
    }
    let f = |s: f64| -> (f64, f64) {
        // Value and derivative of F(s).
        let term = |t: f64, n: f64| {
            let q = n * n - s * s;
            (t * s / q.sqrt(), t * n * n / (q * q.sqrt()))
        };
        let (ae, de) = term(a, ne);
        let (ap, dp) = term(tp, np);
        let (aa, da) = term(g, 1.0);
        (ae + ap + aa - rho, de + dp + da)
    };
    let (mut lo, mut hi) = (0.0f64, 1.0f64);
    let mut s = (rho / reduced).min(0.5);
    for _ in 0..200 {
        let (v, dv) = f(s);
        if v.abs() <= 1e-13 * rho {
            break;
        }
        if v > 0.0 {
            hi = s;
        } else {
            lo = s;
        }
        let newton = s - v / dv;
        s = if newton > lo && newton < hi && newton.is_finite() {
            newton
        } else {
            0.5 * (lo + hi)
        };
    }
    let tan = s / (1.0 - s * s).sqrt();
    tan / rho
}

impl CameraOptics {
    /// The optics of `pipeline`'s camera effects on `sensor`, `None` when the scene
    /// lists none (the linear `[camera]` mapping; frames as before, bit for bit).
    pub fn from_pipeline(pipeline: &Pipeline, sensor: &Sensor) -> Option<CameraOptics> {
        let mut perspective = None;
        let mut refraction = None;
        let mut distortion = None;
        for e in pipeline.effects() {
            match e {
                Effect::Perspective {
                    distance_mm,
                    focal,
                    principal_point_px,
                } => perspective = Some((*distance_mm, *focal, *principal_point_px)),
                Effect::Refraction {
                    plate_index,
                    plate_thickness_mm,
                    elastomer_index,
                } => refraction = Some((*elastomer_index, *plate_index, *plate_thickness_mm)),
                Effect::LensDistortion { .. } => distortion = Some(e.clone()),
                _ => {}
            }
        }
        if perspective.is_none() && distortion.is_none() {
            return None;
        }
        let cam = sensor.camera;
        let h = sensor.elastomer.thickness_mm;
        let centre = [
            (cam.width_px as f64 - 1.0) / 2.0,
            (cam.height_px as f64 - 1.0) / 2.0,
        ];
        let pinhole = perspective.map(|(distance_mm, focal, pp)| {
            let principal_px = pp.unwrap_or(centre);
            let focal_px = match focal {
                Focal::Px(f) => f,
                Focal::ReferenceDepthMm(d) => {
                    let a = h - d;
                    let reduced = match refraction {
                        Some((ne, np, tp)) => a / ne + tp / np + (distance_mm - tp),
                        None => a + distance_mm,
                    };
                    reduced / cam.mm_per_px
                }
            };
            Pinhole {
                principal_px,
                focal_px,
                axis_mm: cam.px_to_mm(principal_px),
                distance_mm,
                refraction,
            }
        });
        let distortion = distortion.map(|e| match e {
            Effect::LensDistortion {
                k1,
                k2,
                k3,
                p1,
                p2,
                center_px,
                norm_px,
            } => {
                let (center_px, norm_px) = match &pinhole {
                    Some(p) => (p.principal_px, p.focal_px),
                    None => (center_px.unwrap_or(centre), norm_px.unwrap_or(1.0)),
                };
                BrownConrady {
                    center_px,
                    norm_px,
                    k1,
                    k2,
                    k3,
                    p1,
                    p2,
                }
            }
            _ => BrownConrady::none(centre, 1.0),
        });
        Some(CameraOptics {
            camera: cam,
            thickness_mm: h,
            pinhole,
            distortion,
        })
    }

    /// Checks what needs the sensor: a `reference_depth_mm` within the elastomer.
    pub fn check(pipeline: &Pipeline, sensor: &Sensor) -> Result<(), EffectError> {
        let h = sensor.elastomer.thickness_mm;
        for (index, e) in pipeline.effects().iter().enumerate() {
            if let Effect::Perspective {
                focal: Focal::ReferenceDepthMm(d),
                ..
            } = e
            {
                if !(*d >= 0.0 && *d <= h) {
                    return Err(EffectError::Invalid {
                        index,
                        kind: "perspective",
                        key: "reference_depth_mm",
                        value: format!("{d} mm"),
                        allowed: format!(
                            "must be a depth in [0, {h}] mm (the sensor's elastomer thickness_mm)"
                        ),
                    });
                }
            }
        }
        Ok(())
    }

    /// The focal length in px (`None` without `perspective`).
    pub fn focal_px(&self) -> Option<f64> {
        self.pinhole.map(|p| p.focal_px)
    }

    /// The principal point in px (`None` without `perspective`).
    pub fn principal_px(&self) -> Option<[f64; 2]> {
        self.pinhole.map(|p| p.principal_px)
    }

    /// The lens distortion, if listed (with its resolved centre and normalisation).
    pub fn distortion(&self) -> Option<&BrownConrady> {
        self.distortion.as_ref()
    }

    /// Where a marker centre at sensor-frame `p_mm` and depth `z_mm` (layer depth plus
    /// `u_z`) appears in the image, px, and the local magnification there, px/mm.
    pub fn project(&self, p_mm: [f64; 2], z_mm: f64) -> ([f64; 2], f64) {
        let (q, m) = match &self.pinhole {
            None => (self.camera.mm_to_px(p_mm), 1.0 / self.camera.mm_per_px),
            Some(ph) => {
                let x = p_mm[0] - ph.axis_mm[0];
                let y = p_mm[1] - ph.axis_mm[1];
                let a = self.thickness_mm - z_mm;
                let inv = match ph.refraction {
                    None => 1.0 / (a + ph.distance_mm),
                    Some((ne, np, tp)) => {
                        refracted_inverse_distance(x.hypot(y), a, ph.distance_mm, ne, np, tp)
                    }
                };
                let m = ph.focal_px * inv;
                ([ph.principal_px[0] + m * x, ph.principal_px[1] + m * y], m)
            }
        };
        match &self.distortion {
            None => (q, m),
            Some(d) => (d.distort(q), m),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refracted_ray_obeys_snell_and_reaches_the_marker() {
        let (ne, np, tp, a, d) = (1.41, 1.49, 5.0, 34.0, 30.0);
        for rho in [0.0, 0.3, 4.0, 12.0, 40.0] {
            let inv = refracted_inverse_distance(rho, a, d, ne, np, tp);
            let tan_air = inv * rho;
            let s = tan_air / (1.0 + tan_air * tan_air).sqrt();
            // Horizontal travel in each medium with n sin θ = s.
            let travel = |t: f64, n: f64| t * s / (n * n - s * s).sqrt();
            let total = travel(a, ne) + travel(tp, np) + travel(d - tp, 1.0);
            assert!(
                (total - rho).abs() <= 1e-10 * rho.max(1.0),
                "rho {rho}: {total}"
            );
        }
        // Index 1 everywhere: the straight line.
        let inv = refracted_inverse_distance(7.0, a, d, 1.0, 1.0, tp);
        assert!((inv - 1.0 / (a + d)).abs() < 1e-15);
    }
}
