//! Camera models shared by the simulated camera and the tracker: the Brown–Conrady
//! lens distortion, a per-layer calibrated pixel ↔ sensor-frame mapping
//! ([`CameraCalibration`], the `camera.toml` file `tactbench calibrate` writes) and
//! [`PixelMapping`], the mapping the tracker converts pixels with (the sensor file's
//! linear `[camera]` mapping, or a calibration).
//!
//! **Brown–Conrady** (Brown 1966, "Decentering distortion of lenses"; the form OpenCV
//! uses): an undistorted image point `q` (px) is written in normalised coordinates
//! `x = (q − c)/N` about the centre `c` (the principal point), `r² = x² + y²`, and
//! moves to
//!
//! ```text
//! x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2 x²)
//! y_d = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2 y²) + 2 p2 x y
//! ```
//!
//! `p = c + N (x_d, y_d)`. `N` is the normalisation radius in px: the focal length in
//! px for the simulated pinhole camera (OpenCV's convention), half the image diagonal
//! in a calibration (the focal length is not known from one frame). Coefficients for
//! another `N'` follow as `k1' = k1 (N'/N)²`, `k2' = k2 (N'/N)⁴`, `k3' = k3 (N'/N)⁶`,
//! `p1' = p1 N'/N`, `p2' = p2 N'/N`. [`BrownConrady::undistort`] inverts it by Newton
//! iterations on the 2×2 Jacobian (to 1e-12 px).
//!
//! **Calibrated mapping.** Per marker layer `l` a scale `s_l` (px/mm) and an origin
//! `o_l` (px): a marker at sensor-frame `(x, y)` mm in layer `l` appears at
//! `p = D(o_l + s_l (x, y))`, `D` the distortion above. Perspective (each layer at its
//! own distance from the pinhole) and refraction (apparent depth) fold into the
//! per-layer scale and origin; what one frame cannot identify is listed in the
//! [`CameraCalibration`] docs and in README.

use std::fmt::Write as _;
use std::path::Path;

use serde::Deserialize;

use crate::config::{self, Checker, ConfigError};
use crate::sensor::{CameraMapping, Sensor};

/// The format tag of `camera.toml`.
pub const CAMERA_FORMAT: &str = "tactbench-camera/1";

/// Brown–Conrady radial (`k1, k2, k3`) and tangential (`p1, p2`) distortion about
/// `center_px`, in coordinates normalised by `norm_px` (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BrownConrady {
    /// Distortion centre (the principal point), px.
    pub center_px: [f64; 2],
    /// Normalisation radius, px (> 0).
    pub norm_px: f64,
    /// Radial coefficient of r².
    pub k1: f64,
    /// Radial coefficient of r⁴.
    pub k2: f64,
    /// Radial coefficient of r⁶.
    pub k3: f64,
    /// Tangential (decentring) coefficient p1.
    pub p1: f64,
    /// Tangential (decentring) coefficient p2.
    pub p2: f64,
}

impl BrownConrady {
    /// No distortion about `center_px` with normalisation `norm_px`.
    pub fn none(center_px: [f64; 2], norm_px: f64) -> Self {
        BrownConrady {
            center_px,
            norm_px,
            k1: 0.0,
            k2: 0.0,
            k3: 0.0,
            p1: 0.0,
            p2: 0.0,
        }
    }

    /// True when every coefficient is 0 (the identity).
    pub fn is_identity(&self) -> bool {
        [self.k1, self.k2, self.k3, self.p1, self.p2]
            .iter()
            .all(|v| *v == 0.0)
    }

    /// The distorted position of the undistorted image point `q_px`.
    pub fn distort(&self, q_px: [f64; 2]) -> [f64; 2] {
        let n = self.norm_px;
        let x = (q_px[0] - self.center_px[0]) / n;
        let y = (q_px[1] - self.center_px[1]) / n;
        let [xd, yd] = self.distort_normalised(x, y);
        [self.center_px[0] + n * xd, self.center_px[1] + n * yd]
    }

    fn distort_normalised(&self, x: f64, y: f64) -> [f64; 2] {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        [
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        ]
    }

    /// Jacobian of the normalised distortion at `(x, y)`.
    fn jacobian_normalised(&self, x: f64, y: f64) -> [[f64; 2]; 2] {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        // d(radial)/d(r²)
        let dr = self.k1 + r2 * (2.0 * self.k2 + 3.0 * r2 * self.k3);
        let (p1, p2) = (self.p1, self.p2);
        [
            [
                radial + 2.0 * x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x,
                2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y,
            ],
            [
                2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y,
                radial + 2.0 * y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x,
            ],
        ]
    }

    /// The undistorted point whose distorted image is `p_px` (Newton iterations from
    /// `p_px`; NaN when they do not converge, e.g. beyond a fold of a strong
    /// distortion).
    pub fn undistort(&self, p_px: [f64; 2]) -> [f64; 2] {
        if self.is_identity() {
            return p_px;
        }
        let n = self.norm_px;
        let tx = (p_px[0] - self.center_px[0]) / n;
        let ty = (p_px[1] - self.center_px[1]) / n;
        let (mut x, mut y) = (tx, ty);
        for _ in 0..50 {
            let [fx, fy] = self.distort_normalised(x, y);
            let (ex, ey) = (fx - tx, fy - ty);
            if ex.abs().max(ey.abs()) * n < 1e-12 {
                return [self.center_px[0] + n * x, self.center_px[1] + n * y];
            }
            let j = self.jacobian_normalised(x, y);
            let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
            if !det.is_finite() || det.abs() < 1e-12 {
                break;
            }
            x -= (j[1][1] * ex - j[0][1] * ey) / det;
            y -= (-j[1][0] * ex + j[0][0] * ey) / det;
        }
        [f64::NAN, f64::NAN]
    }
}

/// Largest local magnification (or demagnification, its inverse) the distortion may
/// have anywhere over the image: the singular values of its Jacobian must lie in
/// `[1/MAX_DISTORTION_STRETCH, MAX_DISTORTION_STRETCH]`. Real lenses stay within a
/// factor 2 or so; a fitted distortion beyond 20 is not a lens but a failed fit.
pub const MAX_DISTORTION_STRETCH: f64 = 20.0;

impl BrownConrady {
    /// Checks that the distortion can be inverted over a `width_px × height_px` image:
    /// every point of a 33 × 33 grid over the image (edges and corners included)
    /// undistorts (Newton converges and distorting the result gives the point back
    /// to 1e-6 px), the Jacobian there has a positive determinant and singular values
    /// within [`MAX_DISTORTION_STRETCH`], and along the ray from the centre to every
    /// border point the determinant stays positive (no fold inside the image).
    /// `Err` says where and why.
    pub fn check_invertible(&self, width_px: u32, height_px: u32) -> Result<(), String> {
        if self.is_identity() {
            return Ok(());
        }
        const N: usize = 33;
        let (w, h) = (width_px as f64, height_px as f64);
        let n = self.norm_px;
        let c = self.center_px;
        let stretch = |q: [f64; 2]| -> Result<(), String> {
            let x = (q[0] - c[0]) / n;
            let y = (q[1] - c[1]) / n;
            let j = self.jacobian_normalised(x, y);
            let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
            if !(det.is_finite() && det > 0.0) {
                return Err(
                    "the distortion folds over (its Jacobian determinant is not positive)".into(),
                );
            }
            // Singular values of a 2 × 2 matrix from its Frobenius norm and determinant.
            let f2: f64 = j.iter().flatten().map(|v| v * v).sum();
            let disc = (f2 * f2 - 4.0 * det * det).max(0.0).sqrt();
            let s_max = (0.5 * (f2 + disc)).sqrt();
            let s_min = det / s_max;
            if s_max > MAX_DISTORTION_STRETCH || s_min < 1.0 / MAX_DISTORTION_STRETCH {
                return Err(format!(
                    "the distortion stretches the image by {:.3e} to {:.3e} there (at most a factor {MAX_DISTORTION_STRETCH} either way is a lens)",
                    s_min, s_max
                ));
            }
            Ok(())
        };
        let at = |p: [f64; 2], why: String| {
            format!(
                "cannot be inverted over the {width_px} x {height_px} px image: at pixel ({:.1}, {:.1}) {why}",
                p[0], p[1]
            )
        };
        for iy in 0..N {
            for ix in 0..N {
                let p = [
                    w * ix as f64 / (N - 1) as f64,
                    h * iy as f64 / (N - 1) as f64,
                ];
                let q = self.undistort(p);
                if !(q[0].is_finite() && q[1].is_finite()) {
                    return Err(at(p, "no undistorted point maps to it".into()));
                }
                let back = self.distort(q);
                if (back[0] - p[0]).hypot(back[1] - p[1]) > 1e-6 {
                    return Err(at(p, "no undistorted point maps to it".into()));
                }
                stretch(q).map_err(|e| at(p, e))?;
                let border = ix == 0 || iy == 0 || ix == N - 1 || iy == N - 1;
                if border {
                    // The ray from the undistorted centre to this border point.
                    let c0 = self.undistort(c);
                    let c0 = if c0[0].is_finite() { c0 } else { c };
                    for t in 1..64 {
                        let f = t as f64 / 64.0;
                        let r = [c0[0] + f * (q[0] - c0[0]), c0[1] + f * (q[1] - c0[1])];
                        stretch(r).map_err(|e| at(self.distort(r), e))?;
                    }
                }
            }
        }
        Ok(())
    }
}

/// One layer of a [`CameraCalibration`].
#[derive(Debug, Clone, PartialEq)]
pub struct LayerCalibration {
    /// Layer name (sensor.toml).
    pub name: String,
    /// Scale s_l, px per mm (in the undistorted image).
    pub px_per_mm: f64,
    /// Undistorted pixel position of the sensor-frame origin in this layer, o_l.
    pub origin_px: [f64; 2],
    /// RMS of the fit residuals of this layer's markers, px.
    pub rms_px: f64,
    /// Markers of this layer used in the fit.
    pub markers: usize,
}

/// A camera calibration (`camera.toml`, written by `tactbench calibrate`): per-layer
/// scale and origin and a Brown–Conrady distortion about a principal point.
///
/// From one unloaded frame of a planar grid per layer:
/// - **identified**: per-layer scale and origin (what the tracker needs), radial
///   distortion k1 (k2, k3 weakly, over the radii the markers cover);
/// - **weakly**: the principal point, only through the distortion (with k = 0 it is
///   not identified at all) and coupled to k1;
/// - **not separately**: the pinhole distance and the focal length (only their ratio
///   per layer, i.e. the scale; two layers at known depths give the *reduced* depth
///   difference, which mixes in the elastomer's refractive index); refraction (folds
///   into each layer's scale and origin); tangential distortion against a shift of the
///   principal point (equal to first order, so `calibrate --tangential` holds the
///   principal point at the image centre); a rotation of the camera about its axis
///   (not modelled: the layer grids are assumed aligned with the image axes, as the
///   sensor file's `[camera]` mapping assumes).
#[derive(Debug, Clone, PartialEq)]
pub struct CameraCalibration {
    /// Image width, px.
    pub width_px: u32,
    /// Image height, px.
    pub height_px: u32,
    /// Lens distortion.
    pub distortion: BrownConrady,
    /// One entry per sensor layer, in sensor order.
    pub layers: Vec<LayerCalibration>,
    /// RMS of all fit residuals, px.
    pub rms_px: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCamera {
    format: String,
    width_px: i64,
    height_px: i64,
    rms_px: Option<f64>,
    distortion: RawDistortion,
    layers: Vec<RawLayer>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDistortion {
    #[serde(deserialize_with = "crate::config::exact")]
    center_px: [f64; 2],
    norm_px: f64,
    k1: f64,
    k2: f64,
    k3: f64,
    p1: f64,
    p2: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawLayer {
    name: String,
    px_per_mm: f64,
    #[serde(deserialize_with = "crate::config::exact")]
    origin_px: [f64; 2],
    rms_px: Option<f64>,
    markers: Option<i64>,
}

impl CameraCalibration {
    /// Reads and validates a `camera.toml` against the sensor it is used with: one
    /// `[[layers]]` entry per sensor layer (by name, any order; none unknown, none
    /// twice) and the sensor's image size.
    pub fn from_path(path: impl AsRef<Path>, sensor: &Sensor) -> Result<Self, ConfigError> {
        let path = path.as_ref();
        let text = config::read_text(path, "camera calibration file")?;
        Self::from_toml_str(&text, path, sensor)
    }

    /// As [`CameraCalibration::from_path`], from text; `path` is used in messages only.
    pub fn from_toml_str(text: &str, path: &Path, sensor: &Sensor) -> Result<Self, ConfigError> {
        let raw: RawCamera = config::parse_toml(text, path)?;
        let c = Checker { path };
        if raw.format != CAMERA_FORMAT {
            return Err(c.invalid(
                "format",
                format!("{:?}", raw.format),
                format!("expected \"{CAMERA_FORMAT}\""),
            ));
        }
        let cam = &sensor.camera;
        if raw.width_px != cam.width_px as i64 {
            return Err(c.invalid(
                "width_px",
                format!("{} px", raw.width_px),
                format!("the sensor's [camera] width_px is {} px", cam.width_px),
            ));
        }
        if raw.height_px != cam.height_px as i64 {
            return Err(c.invalid(
                "height_px",
                format!("{} px", raw.height_px),
                format!("the sensor's [camera] height_px is {} px", cam.height_px),
            ));
        }
        let d = &raw.distortion;
        let distortion = BrownConrady {
            center_px: [
                c.finite("distortion.center_px[0]", d.center_px[0], "px")?,
                c.finite("distortion.center_px[1]", d.center_px[1], "px")?,
            ],
            norm_px: c.positive("distortion.norm_px", d.norm_px, "px")?,
            k1: c.finite("distortion.k1", d.k1, "")?,
            k2: c.finite("distortion.k2", d.k2, "")?,
            k3: c.finite("distortion.k3", d.k3, "")?,
            p1: c.finite("distortion.p1", d.p1, "")?,
            p2: c.finite("distortion.p2", d.p2, "")?,
        };
        distortion
            .check_invertible(cam.width_px, cam.height_px)
            .map_err(|why| {
                c.invalid(
                    "distortion",
                    format!(
                        "k1 = {}, k2 = {}, k3 = {}, p1 = {}, p2 = {} (norm_px {} px)",
                        num(distortion.k1),
                        num(distortion.k2),
                        num(distortion.k3),
                        num(distortion.p1),
                        num(distortion.p2),
                        num(distortion.norm_px)
                    ),
                    format!("the distortion must be invertible over the image: it {why}"),
                )
            })?;
        let mut layers: Vec<Option<LayerCalibration>> = vec![None; sensor.layers.len()];
        for (i, l) in raw.layers.iter().enumerate() {
            let names: Vec<&str> = sensor.layers.iter().map(|l| l.name.as_str()).collect();
            let li = sensor.layer_index(&l.name).ok_or_else(|| {
                c.invalid(
                    &format!("layers[{i}].name"),
                    format!("{:?}", l.name),
                    format!("unknown layer: the sensor has {}", names.join(", ")),
                )
            })?;
            if layers[li].is_some() {
                return Err(c.invalid(
                    &format!("layers[{i}].name"),
                    format!("{:?}", l.name),
                    "given twice: one entry per layer",
                ));
            }
            layers[li] = Some(LayerCalibration {
                name: l.name.clone(),
                px_per_mm: c.positive(&format!("layers[{i}].px_per_mm"), l.px_per_mm, "px/mm")?,
                origin_px: [
                    c.finite(&format!("layers[{i}].origin_px[0]"), l.origin_px[0], "px")?,
                    c.finite(&format!("layers[{i}].origin_px[1]"), l.origin_px[1], "px")?,
                ],
                rms_px: l.rms_px.unwrap_or(f64::NAN),
                markers: l.markers.unwrap_or(0).max(0) as usize,
            });
        }
        let mut out = Vec::with_capacity(layers.len());
        for (li, l) in layers.into_iter().enumerate() {
            match l {
                Some(l) => out.push(l),
                None => {
                    return Err(c.invalid(
                        "layers",
                        format!("(no entry named {:?})", sensor.layers[li].name),
                        "needs one [[layers]] entry per sensor layer",
                    ))
                }
            }
        }
        Ok(CameraCalibration {
            width_px: cam.width_px,
            height_px: cam.height_px,
            distortion,
            layers: out,
            rms_px: raw.rms_px.unwrap_or(f64::NAN),
        })
    }

    /// The calibration that reproduces a linear `[camera]` mapping exactly (every layer
    /// at `1 / mm_per_px` px/mm and `origin_px`, no distortion).
    pub fn from_linear(camera: &CameraMapping, sensor: &Sensor) -> Self {
        let w = camera.width_px as f64;
        let h = camera.height_px as f64;
        CameraCalibration {
            width_px: camera.width_px,
            height_px: camera.height_px,
            distortion: BrownConrady::none(
                [(w - 1.0) / 2.0, (h - 1.0) / 2.0],
                0.5 * w.hypot(h).max(1.0),
            ),
            layers: sensor
                .layers
                .iter()
                .map(|l| LayerCalibration {
                    name: l.name.clone(),
                    px_per_mm: 1.0 / camera.mm_per_px,
                    origin_px: camera.origin_px,
                    rms_px: f64::NAN,
                    markers: 0,
                })
                .collect(),
            rms_px: f64::NAN,
        }
    }

    /// The undistorted image point of sensor-frame `p_mm` in layer `layer`.
    pub fn undistorted_px(&self, layer: usize, p_mm: [f64; 2]) -> [f64; 2] {
        let l = &self.layers[layer];
        [
            l.origin_px[0] + l.px_per_mm * p_mm[0],
            l.origin_px[1] + l.px_per_mm * p_mm[1],
        ]
    }

    /// Where sensor-frame `p_mm` of layer `layer` appears in the image, px.
    pub fn mm_to_px(&self, layer: usize, p_mm: [f64; 2]) -> [f64; 2] {
        self.distortion.distort(self.undistorted_px(layer, p_mm))
    }

    /// The sensor-frame position (mm) in layer `layer` seen at image point `p_px`.
    pub fn px_to_mm(&self, layer: usize, p_px: [f64; 2]) -> [f64; 2] {
        let q = self.distortion.undistort(p_px);
        let l = &self.layers[layer];
        [
            (q[0] - l.origin_px[0]) / l.px_per_mm,
            (q[1] - l.origin_px[1]) / l.px_per_mm,
        ]
    }

    /// `camera.toml` text (the format of README's *camera.toml*), with comments saying
    /// what one frame identifies. `sensor_note` and `reference_note` are recorded as
    /// comments (where the calibration came from).
    pub fn to_toml_string(&self, sensor_note: &str, reference_note: &str) -> String {
        let mut s = String::new();
        let d = &self.distortion;
        let _ = writeln!(
            s,
            "# tactbench camera calibration (tactbench calibrate), format {CAMERA_FORMAT}\n\
             # sensor: {sensor_note}\n# reference: {reference_note}\n#\n\
             # A marker at sensor-frame (x, y) mm in layer l appears at\n\
             #   p = D(origin_px + px_per_mm * (x, y)),\n\
             # D = Brown-Conrady distortion about distortion.center_px in units of norm_px:\n\
             #   x = (q - c) / norm_px, r^2 = x^2 + y^2,\n\
             #   x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)\n\
             #   y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y\n\
             #\n\
             # What one unloaded frame identifies: each layer's scale and origin (perspective and\n\
             # refraction fold into them) and radial distortion k1 (k2, k3 weakly). The principal\n\
             # point is seen only through the distortion (weakly, coupled to k1; not at all without\n\
             # distortion). Not identifiable: pinhole distance and focal length separately (only\n\
             # their ratio per layer), refraction apart from the scales, tangential distortion apart\n\
             # from a principal-point shift (equal to first order), rotation about the optical axis\n\
             # (not modelled). Marker motion along z (u_z) changes the apparent position by parallax;\n\
             # a calibration cannot remove it.\n"
        );
        let _ = writeln!(s, "format = \"{CAMERA_FORMAT}\"");
        let _ = writeln!(s, "width_px = {}", self.width_px);
        let _ = writeln!(s, "height_px = {}", self.height_px);
        let _ = writeln!(
            s,
            "rms_px = {}  # fit residual RMS over every marker, px",
            num(self.rms_px)
        );
        let _ = writeln!(s, "\n[distortion]");
        let _ = writeln!(
            s,
            "center_px = [{}, {}]  # principal point (distortion centre), px",
            num(d.center_px[0]),
            num(d.center_px[1])
        );
        let _ = writeln!(
            s,
            "norm_px = {}  # normalisation radius, px",
            num(d.norm_px)
        );
        for (k, v) in [
            ("k1", d.k1),
            ("k2", d.k2),
            ("k3", d.k3),
            ("p1", d.p1),
            ("p2", d.p2),
        ] {
            let _ = writeln!(s, "{k} = {}", num(v));
        }
        for l in &self.layers {
            let _ = writeln!(s, "\n[[layers]]");
            let _ = writeln!(s, "name = {:?}", l.name);
            let _ = writeln!(
                s,
                "px_per_mm = {}  # scale in the undistorted image",
                num(l.px_per_mm)
            );
            let _ = writeln!(
                s,
                "origin_px = [{}, {}]  # undistorted position of the sensor-frame origin",
                num(l.origin_px[0]),
                num(l.origin_px[1])
            );
            let _ = writeln!(
                s,
                "rms_px = {}  # this layer's residual RMS, px",
                num(l.rms_px)
            );
            let _ = writeln!(s, "markers = {}", l.markers);
        }
        s
    }
}

/// A TOML float (always with a decimal point or exponent; `nan` for NaN).
fn num(v: f64) -> String {
    if v.is_nan() {
        "nan".into()
    } else {
        format!("{v:?}")
    }
}

/// How the tracker converts pixels to the sensor frame.
#[derive(Debug, Clone, PartialEq)]
pub enum PixelMapping {
    /// The sensor file's `[camera]` mapping, the same for every layer (today's
    /// behaviour, bit for bit).
    Linear(CameraMapping),
    /// A camera calibration (per-layer scale and origin, distortion).
    Calibrated(CameraCalibration),
}

impl PixelMapping {
    /// Sensor-frame position (mm) of image point `p_px` in layer `layer`.
    pub fn px_to_mm(&self, layer: usize, p_px: [f64; 2]) -> [f64; 2] {
        match self {
            PixelMapping::Linear(c) => c.px_to_mm(p_px),
            PixelMapping::Calibrated(c) => c.px_to_mm(layer, p_px),
        }
    }

    /// Image point (px) of sensor-frame `p_mm` in layer `layer`.
    pub fn mm_to_px(&self, layer: usize, p_mm: [f64; 2]) -> [f64; 2] {
        match self {
            PixelMapping::Linear(c) => c.mm_to_px(p_mm),
            PixelMapping::Calibrated(c) => c.mm_to_px(layer, p_mm),
        }
    }

    /// The nominal scale of layer `layer`, mm per px (for marker sizes).
    pub fn mm_per_px(&self, layer: usize) -> f64 {
        match self {
            PixelMapping::Linear(c) => c.mm_per_px,
            PixelMapping::Calibrated(c) => 1.0 / c.layers[layer].px_per_mm,
        }
    }

    /// Displacement (mm) of a marker of layer `layer` whose reference centroid is
    /// `reference_px` and whose measured displacement is `u_px`. Linear: `u_px ·
    /// mm_per_px` (exactly today's arithmetic); calibrated: the difference of the two
    /// mapped positions.
    pub fn displacement_mm(
        &self,
        layer: usize,
        reference_px: [f64; 2],
        u_px: [f64; 2],
    ) -> [f64; 2] {
        match self {
            PixelMapping::Linear(c) => [u_px[0] * c.mm_per_px, u_px[1] * c.mm_per_px],
            PixelMapping::Calibrated(c) => {
                let a = c.px_to_mm(layer, reference_px);
                let b = c.px_to_mm(
                    layer,
                    [reference_px[0] + u_px[0], reference_px[1] + u_px[1]],
                );
                [b[0] - a[0], b[1] - a[1]]
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bc() -> BrownConrady {
        BrownConrady {
            center_px: [210.0, 170.0],
            norm_px: 300.0,
            k1: -0.2,
            k2: 0.05,
            k3: 0.01,
            p1: 1e-3,
            p2: -2e-3,
        }
    }

    #[test]
    fn undistort_inverts_distort_to_1e_10_px() {
        let d = bc();
        for p in [[0.0, 0.0], [429.0, 339.0], [210.0, 170.0], [100.5, 300.25]] {
            let q = d.undistort(d.distort(p));
            assert!(
                (q[0] - p[0]).abs() < 1e-10 && (q[1] - p[1]).abs() < 1e-10,
                "{p:?} {q:?}"
            );
        }
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let d = bc();
        let (x, y, h) = (0.3, -0.4, 1e-6);
        let j = d.jacobian_normalised(x, y);
        let fx1 = d.distort_normalised(x + h, y);
        let fx0 = d.distort_normalised(x - h, y);
        let fy1 = d.distort_normalised(x, y + h);
        let fy0 = d.distort_normalised(x, y - h);
        for a in 0..2 {
            assert!((j[a][0] - (fx1[a] - fx0[a]) / (2.0 * h)).abs() < 1e-8);
            assert!((j[a][1] - (fy1[a] - fy0[a]) / (2.0 * h)).abs() < 1e-8);
        }
    }

    #[test]
    fn linear_calibration_round_trips_and_equals_the_camera_mapping() {
        let s = crate::sensor::paper_sensor();
        let c = CameraCalibration::from_linear(&s.camera, &s);
        let text = c.to_toml_string("paper", "none");
        let back = CameraCalibration::from_toml_str(&text, Path::new("camera.toml"), &s).unwrap();
        assert_eq!(back.layers.len(), 2);
        let p = [3.3, 7.1];
        let a = s.camera.mm_to_px(p);
        let b = back.mm_to_px(1, p);
        assert!((a[0] - b[0]).abs() < 1e-12 && (a[1] - b[1]).abs() < 1e-12);
        let m = back.px_to_mm(0, a);
        assert!((m[0] - p[0]).abs() < 1e-12 && (m[1] - p[1]).abs() < 1e-12);
    }

    #[test]
    fn camera_toml_errors_name_the_key_and_value() {
        let s = crate::sensor::paper_sensor();
        let c = CameraCalibration::from_linear(&s.camera, &s);
        let text = c.to_toml_string("paper", "none");
        let path = Path::new("cam.toml");
        let bad = text.replacen("name = \"red\"", "name = \"green\"", 1);
        let e = CameraCalibration::from_toml_str(&bad, path, &s)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("cam.toml") && e.contains("layers[1].name") && e.contains("green"),
            "{e}"
        );
        let bad = text.replacen("width_px = 430", "width_px = 640", 1);
        let e = CameraCalibration::from_toml_str(&bad, path, &s)
            .unwrap_err()
            .to_string();
        assert!(e.contains("width_px") && e.contains("640"), "{e}");
        let bad = text.replacen("px_per_mm = 20.0", "px_per_mm = -1.0", 1);
        let e = CameraCalibration::from_toml_str(&bad, path, &s)
            .unwrap_err()
            .to_string();
        assert!(e.contains("px_per_mm") && e.contains("px/mm"), "{e}");
    }
}
