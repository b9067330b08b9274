//! Onboarding a new sensor (`tactbench sensor init`): a sensor-file draft from one
//! unloaded frame.
//!
//! [`sensor_draft`] checks the frame (not blank, not saturated), finds the markers of
//! the requested appearance inside the ROI with the reference detector (no layout
//! assumed), measures what one frame can tell — marker count, spacing (median nearest
//! neighbour), diameter, contrast against the local background, the share of markers
//! whose tracking window crosses the ROI (or image) border — and, when the markers form
//! a square-pitched rectangular grid aligned with the image, that grid. The
//! [`SensorDraft::to_toml`] text loads with [`Sensor::from_toml_str`]; what a frame
//! cannot tell (elastomer, layer depth, the force grid, and `mm_per_px` without a
//! known pitch or scale) is written with a stated placeholder and a `# TODO: measure`
//! comment naming what to put there, and the file says so to the program: it starts
//! with `draft = true` and `placeholders = [...]` naming those keys
//! ([`SensorDraft::placeholders`]; see `crate::sensor` for what a draft may be used for).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use thiserror::Error;

use super::detect::{detect, DetectConfig, Reference};
use super::image::FrameView;
use super::{Pixels, VisionError};
use crate::sensor::{
    fmt_value, CameraMapping, Elastomer, Grid, KeyRange, Layer, MarkerColor, ModelKind, Roi,
    Sensor, MARKER_PITCH_MM, MM_PER_PX,
};

/// What sets the draft's `mm_per_px`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Scale {
    /// The markers' known pitch (centre-to-centre of neighbours), mm:
    /// `mm_per_px = pitch / measured spacing`.
    PitchMm(f64),
    /// The scale itself, mm per px.
    MmPerPx(f64),
    /// Unknown: written as a placeholder with a `# TODO: measure`.
    Unknown,
}

/// Options of [`sensor_draft`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DraftOptions {
    /// The markers' appearance (`[[layers]] color`).
    pub color: MarkerColor,
    /// Where to look (`[camera] roi_px`); `None`: the whole image.
    pub roi_px: Option<Roi>,
    /// What sets `mm_per_px`.
    pub scale: Scale,
}

/// Why no draft was written. Every variant names the frame's file and the value
/// that failed.
#[derive(Debug, Error)]
pub enum DraftError {
    /// The frame shows no structure.
    #[error("{path}: blank frame: 98 % of the pixels lie within {spread_percent:.1} % of full scale of each other (mean level {mean_percent:.1} %): nothing to detect; take the reference with the sensor's light on and the camera in focus")]
    Blank {
        /// The frame.
        path: PathBuf,
        /// Spread between the 1st and 99th percentile of the brightness, % of full scale.
        spread_percent: f64,
        /// Mean brightness, % of full scale.
        mean_percent: f64,
    },
    /// Most of the frame is saturated.
    #[error("{path}: saturated frame: {saturated_percent:.1} % of the pixels (inside the ROI) reach full scale (limit {limit_percent:.0} %): reduce the exposure or the light")]
    Saturated {
        /// The frame.
        path: PathBuf,
        /// Saturated share, %.
        saturated_percent: f64,
        /// The limit, %.
        limit_percent: f64,
    },
    /// No marker of the requested appearance.
    #[error("{path}: no {color} marker found (--color {color}{roi}): nothing in the frame stands out from its local background as a {color} marker; check --color (dark | bright | blue | red | green) and --roi")]
    NoMarkers {
        /// The frame.
        path: PathBuf,
        /// The appearance sought.
        color: MarkerColor,
        /// `, --roi …` when one was given.
        roi: String,
    },
    /// A coloured appearance asked of a greyscale frame.
    #[error("{path}: --color {color} needs a colour image, but the frame is greyscale: a greyscale frame serves --color dark or bright")]
    GrayscaleColour {
        /// The frame.
        path: PathBuf,
        /// The appearance asked for (blue, red or green).
        color: MarkerColor,
    },
    /// The ROI does not fit the frame.
    #[error("{path}: --roi {roi} is invalid: {allowed}")]
    Roi {
        /// The frame.
        path: PathBuf,
        /// The ROI as given.
        roi: Roi,
        /// What is allowed.
        allowed: String,
    },
    /// A scale option is not a positive number in the range the sensor file takes.
    #[error("{flag} {value} is invalid: {allowed}")]
    Scale {
        /// `--pitch-mm` or `--mm-per-px`.
        flag: &'static str,
        /// The value (with its unit).
        value: String,
        /// What is allowed: the sensor file's range for the key it sets.
        allowed: String,
    },
    /// Detection failed otherwise.
    #[error(transparent)]
    Vision(#[from] VisionError),
}

/// A regular grid found in the frame, px.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DraftGrid {
    /// Columns.
    pub nx: usize,
    /// Rows.
    pub ny: usize,
    /// Pitch, px (mean of the two axes).
    pub pitch_px: f64,
    /// Position of node (0, 0), px.
    pub origin_px: [f64; 2],
    /// Largest distance of a marker from its node, px.
    pub max_residual_px: f64,
}

/// What one frame tells about a new sensor.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorDraft {
    /// Frame width, px.
    pub width_px: u32,
    /// Frame height, px.
    pub height_px: u32,
    /// The appearance.
    pub color: MarkerColor,
    /// The ROI.
    pub roi_px: Option<Roi>,
    /// Marker centroids, px (sorted by row, then column).
    pub markers_px: Vec<[f64; 2]>,
    /// Median nearest-neighbour distance, px.
    pub spacing_px: f64,
    /// Marker diameter (measured), px.
    pub diameter_px: f64,
    /// Median marker contrast: the peak score above the local background, in % of
    /// the full scale of the score (`3 × max level` for brightness layers).
    pub contrast_percent: f64,
    /// For `dark`: the median marker contrast relative to its local illumination, %.
    pub relative_contrast_percent: Option<f64>,
    /// Share of the markers whose tracking window crosses the ROI border (the image
    /// border without an ROI): those are reported `lost` when tracked.
    pub near_border_fraction: f64,
    /// The square-pitched rectangular grid the markers form, when they do.
    pub grid: Option<DraftGrid>,
    /// Why there is no grid (for the draft's comments).
    pub no_grid_reason: Option<String>,
    /// The scale, mm/px, when known.
    pub mm_per_px: Option<f64>,
    /// How the scale was found (for the comments).
    pub scale_source: String,
}

/// Saturated share of the frame beyond which it is refused.
pub const MAX_SATURATED_FRACTION: f64 = 0.5;

/// A frame whose 1st–99th percentile brightness spread is below this share of full
/// scale is blank.
pub const MIN_SPREAD_FRACTION: f64 = 0.02;

/// Finds the markers of `options.color` in an unloaded frame and measures the
/// draft (see the module docs). `path` names the frame in errors.
pub fn sensor_draft(
    view: &FrameView<'_>,
    options: &DraftOptions,
    path: &Path,
) -> Result<SensorDraft, DraftError> {
    let (w, h) = (view.width_px(), view.height_px());
    check_options(view, options, path)?;
    let sensor = probe_sensor(options.color, w, h, options.roi_px);
    let no_markers = || DraftError::NoMarkers {
        path: path.to_path_buf(),
        color: options.color,
        roi: options
            .roi_px
            .map(|r| format!(", --roi {}", roi_arg(&r)))
            .unwrap_or_default(),
    };
    let reference = match detect(view, &sensor, &DetectConfig::default()) {
        Ok(r) => r,
        Err(VisionError::NoMarkers { .. }) => return Err(no_markers()),
        Err(e) => return Err(e.into()),
    };
    let layer = &reference.layers[0];
    let markers_px: Vec<[f64; 2]> = reference.markers.iter().map(|m| m.centroid_px).collect();
    if markers_px.is_empty() {
        return Err(no_markers());
    }
    let (contrast_percent, relative_contrast_percent) =
        contrasts(&reference, view.bit_depth(), options.color);
    let reach = layer.aperture_radius_px + 3.0;
    let border = options.roi_px.unwrap_or(Roi::Rect {
        min_px: [0.0, 0.0],
        max_px: [w as f64 - 1.0, h as f64 - 1.0],
    });
    let near = markers_px
        .iter()
        .filter(|p| !border.contains_disc(**p, reach))
        .count();
    let spacing_px = layer.spacing_px;
    let (grid, no_grid_reason) = match fit_grid(&markers_px, spacing_px) {
        Ok(g) => (Some(g), None),
        Err(reason) => (None, Some(reason)),
    };
    let pitch_px = grid.map_or(spacing_px, |g| g.pitch_px);
    let (mm_per_px, scale_source) = scale_of(options.scale, pitch_px)?;
    Ok(SensorDraft {
        width_px: w,
        height_px: h,
        color: options.color,
        roi_px: options.roi_px,
        markers_px,
        spacing_px,
        diameter_px: 2.0 * layer.marker_radius_px,
        contrast_percent,
        relative_contrast_percent,
        near_border_fraction: near as f64 / reference.markers.len() as f64,
        grid,
        no_grid_reason,
        mm_per_px,
        scale_source,
    })
}

/// The options against the frame before anything is detected: a colour a greyscale
/// frame can hold, the ROI inside the image, a scale the loader would take, the
/// frame's levels.
fn check_options(
    view: &FrameView<'_>,
    options: &DraftOptions,
    path: &Path,
) -> Result<(), DraftError> {
    let (w, h) = (view.width_px(), view.height_px());
    if view.pixels().is_gray() && !options.color.is_brightness() {
        return Err(DraftError::GrayscaleColour {
            path: path.to_path_buf(),
            color: options.color,
        });
    }
    if let Some(roi) = &options.roi_px {
        roi.check_in_image(w, h)
            .map_err(|allowed| DraftError::Roi {
                path: path.to_path_buf(),
                roi: *roi,
                allowed,
            })?;
    }
    // The loader's ranges: the draft must load (`layers.markers.pitch_mm`,
    // `camera.mm_per_px`).
    match options.scale {
        Scale::PitchMm(v) if !plausible(v, &MARKER_PITCH_MM) => {
            return Err(scale_error("--pitch-mm", v, &MARKER_PITCH_MM))
        }
        Scale::MmPerPx(v) if !plausible(v, &MM_PER_PX) => {
            return Err(scale_error("--mm-per-px", v, &MM_PER_PX))
        }
        _ => {}
    }
    check_frame_levels(view, options.roi_px.as_ref(), path)
}

/// Whether `v` is a finite positive value the loader takes for a key of `range`.
fn plausible(v: f64, range: &KeyRange) -> bool {
    v.is_finite() && v > 0.0 && range.check(v).is_ok()
}

/// The error for a scale flag's value outside the loader's `range`.
fn scale_error(flag: &'static str, value: f64, range: &KeyRange) -> DraftError {
    let allowed = if value.is_finite() && value > 0.0 {
        range.check(value).err().unwrap_or_default()
    } else {
        format!(
            "must be a finite number > 0 {}, within {} … {} {}",
            range.unit, range.lo, range.hi, range.unit
        )
    };
    DraftError::Scale {
        flag,
        value: format!("{} {}", fmt_value(value), range.unit),
        allowed,
    }
}

/// The markers' median contrast in % of full scale (three channels of `bit_depth`),
/// and for dark markers their median contrast relative to the illumination.
fn contrasts(reference: &Reference, bit_depth: u32, color: MarkerColor) -> (f64, Option<f64>) {
    let full = 3.0 * if bit_depth == 16 { 65535.0 } else { 255.0 };
    let mut peaks: Vec<f64> = reference.markers.iter().map(|m| m.peak).collect();
    let contrast_percent = 100.0 * median(&mut peaks) / full;
    let relative_contrast_percent = (color == MarkerColor::Dark).then(|| {
        // The dark score's ring level is −(R + G + B): the illumination.
        let mut rel: Vec<f64> = reference
            .markers
            .iter()
            .map(|m| 100.0 * m.peak / (-m.background).max(1.0))
            .collect();
        median(&mut rel)
    });
    (contrast_percent, relative_contrast_percent)
}

/// `mm_per_px` and where it came from, from the scale option and the measured pitch
/// `pitch_px`: the result must be a scale (and imply a pitch) the loader takes.
fn scale_of(scale: Scale, pitch_px: f64) -> Result<(Option<f64>, String), DraftError> {
    Ok(match scale {
        Scale::PitchMm(p) => {
            let k = p / pitch_px;
            if !plausible(k, &MM_PER_PX) {
                return Err(DraftError::Scale {
                    flag: "--pitch-mm",
                    value: format!("{} mm", fmt_value(p)),
                    allowed: format!(
                        "with the measured pitch of {pitch_px:.3} px it gives mm_per_px = {k:e} mm/px, {}",
                        MM_PER_PX.check(k).err().unwrap_or_default()
                    ),
                });
            }
            (
                Some(k),
                format!("from --pitch-mm {p}: {p} mm / {pitch_px:.3} px measured pitch"),
            )
        }
        Scale::MmPerPx(s) => {
            let pitch = pitch_px * s;
            if !plausible(pitch, &MARKER_PITCH_MM) {
                return Err(DraftError::Scale {
                    flag: "--mm-per-px",
                    value: format!("{} mm/px", fmt_value(s)),
                    allowed: format!(
                        "with the measured pitch of {pitch_px:.3} px it gives a marker pitch of {pitch:e} mm, {}",
                        MARKER_PITCH_MM.check(pitch).err().unwrap_or_default()
                    ),
                });
            }
            (Some(s), format!("--mm-per-px {s}"))
        }
        Scale::Unknown => (None, String::new()),
    })
}

/// `circle:X,Y,R` or `rect:X0,Y0,X1,Y1`, the `--roi` syntax.
pub fn roi_arg(roi: &Roi) -> String {
    match roi {
        Roi::Circle {
            center_px,
            radius_px,
        } => format!("circle:{},{},{}", center_px[0], center_px[1], radius_px),
        Roi::Rect { min_px, max_px } => {
            format!(
                "rect:{},{},{},{}",
                min_px[0], min_px[1], max_px[0], max_px[1]
            )
        }
    }
}

/// Parses the `--roi` syntax: `circle:X,Y,R` or `rect:X0,Y0,X1,Y1` (px). Sizes are
/// checked against the frame by [`sensor_draft`].
pub fn parse_roi_arg(text: &str) -> Result<Roi, String> {
    let usage = "expected circle:X,Y,R or rect:X0,Y0,X1,Y1 (pixels)";
    let (kind, nums) = text
        .split_once(':')
        .ok_or_else(|| format!("{text:?}: {usage}"))?;
    let v: Vec<f64> = nums
        .split(',')
        .map(|s| s.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("{text:?}: {e}: {usage}"))?;
    if v.iter().any(|x| !x.is_finite()) {
        return Err(format!("{text:?}: every number must be finite: {usage}"));
    }
    match (kind, v.as_slice()) {
        ("circle", &[x, y, r]) => Ok(Roi::Circle {
            center_px: [x, y],
            radius_px: r,
        }),
        ("rect", &[x0, y0, x1, y1]) => Ok(Roi::Rect {
            min_px: [x0, y0],
            max_px: [x1, y1],
        }),
        _ => Err(format!("{text:?}: {usage}")),
    }
}

/// A one-layer sensor for the detector: the appearance, no grid, the frame's size.
fn probe_sensor(color: MarkerColor, w: u32, h: u32, roi_px: Option<Roi>) -> Sensor {
    Sensor {
        elastomer: Elastomer {
            young_modulus_kpa: 1000.0,
            poisson_ratio: 0.5,
            thickness_mm: 10.0,
            model: ModelKind::HalfSpace,
        },
        layers: vec![Layer {
            name: "markers".into(),
            color,
            depth_mm: 1.0,
            markers: None,
        }],
        force_grid: Grid {
            nx: 1,
            ny: 1,
            pitch_mm: 1.0,
            origin_mm: [0.0, 0.0],
        },
        camera: CameraMapping {
            mm_per_px: 1.0,
            origin_px: [0.0, 0.0],
            width_px: w,
            height_px: h,
            roi_px,
        },
        draft: None,
    }
}

/// Refuses blank frames (1st–99th percentile brightness spread below
/// [`MIN_SPREAD_FRACTION`] of full scale) and saturated ones (over
/// [`MAX_SATURATED_FRACTION`] of the pixels at ≥ 98 % of full scale), counting the
/// pixels inside `roi`; `path` names the frame in the error. `sensor init` refuses such
/// a reference before searching it; `track` and `calibrate` name the cause this way
/// when their reference shows no marker.
pub fn check_frame_levels(
    view: &FrameView<'_>,
    roi: Option<&Roi>,
    path: &Path,
) -> Result<(), DraftError> {
    let w = view.width_px() as usize;
    let (max, values): (f64, Vec<(u32, u32)>) = {
        // (sum of the channels, brightest channel) per pixel inside the ROI.
        fn collect<T: Copy + Into<u32>>(
            data: &[T],
            c: usize,
            w: usize,
            roi: Option<&Roi>,
        ) -> Vec<(u32, u32)> {
            data.chunks_exact(c)
                .enumerate()
                .filter(|(i, _)| roi.is_none_or(|r| r.contains([(i % w) as f64, (i / w) as f64])))
                .map(|(_, px)| {
                    // A grey sample reads as (g, g, g).
                    let at = |k: usize| -> u32 { px[if c == 1 { 0 } else { k }].into() };
                    let (r, g, b) = (at(0), at(1), at(2));
                    (r + g + b, r.max(g).max(b))
                })
                .collect()
        }
        match view.pixels() {
            Pixels::Rgb8(d) => (255.0, collect(d, 3, w, roi)),
            Pixels::Rgba8(d) => (255.0, collect(d, 4, w, roi)),
            Pixels::Rgb16(d) => (65535.0, collect(d, 3, w, roi)),
            Pixels::Rgba16(d) => (65535.0, collect(d, 4, w, roi)),
            Pixels::Gray8(d) => (255.0, collect(d, 1, w, roi)),
            Pixels::Gray16(d) => (65535.0, collect(d, 1, w, roi)),
        }
    };
    if values.is_empty() {
        return Ok(());
    }
    let saturated =
        values.iter().filter(|v| v.1 as f64 >= 0.98 * max).count() as f64 / values.len() as f64;
    if saturated > MAX_SATURATED_FRACTION {
        return Err(DraftError::Saturated {
            path: path.to_path_buf(),
            saturated_percent: 100.0 * saturated,
            limit_percent: 100.0 * MAX_SATURATED_FRACTION,
        });
    }
    let mut sums: Vec<u32> = values.iter().map(|v| v.0).collect();
    let n = sums.len();
    let lo = *sums.select_nth_unstable(n / 100).1 as f64;
    let hi = *sums.select_nth_unstable((n * 99 / 100).min(n - 1)).1 as f64;
    let spread = (hi - lo) / (3.0 * max);
    if spread < MIN_SPREAD_FRACTION {
        let mean = sums.iter().map(|&v| v as f64).sum::<f64>() / n as f64 / (3.0 * max);
        return Err(DraftError::Blank {
            path: path.to_path_buf(),
            spread_percent: 100.0 * spread,
            mean_percent: 100.0 * mean,
        });
    }
    Ok(())
}

/// Median (reorders `v`); NaN for an empty slice.
fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Groups sorted values into clusters separated by gaps above `gap`; returns the
/// cluster index of each value (in the input order) and the cluster means.
fn clusters(values: &[f64], gap: f64) -> (Vec<usize>, Vec<f64>) {
    let mut order: Vec<usize> = (0..values.len()).collect();
    order.sort_by(|&a, &b| values[a].total_cmp(&values[b]));
    let mut index = vec![0usize; values.len()];
    let mut sums: Vec<(f64, usize)> = Vec::new();
    let mut last = f64::NEG_INFINITY;
    for &i in &order {
        if sums.is_empty() || values[i] - last > gap {
            sums.push((0.0, 0));
        }
        let k = sums.len() - 1;
        sums[k].0 += values[i];
        sums[k].1 += 1;
        index[i] = k;
        last = values[i];
    }
    (index, sums.iter().map(|(s, n)| s / *n as f64).collect())
}

/// The square-pitched rectangular grid the markers form, aligned with the image
/// axes, every node holding one marker; or why not. Columns and rows are clusters of
/// the x and y coordinates (gaps above half the spacing); the pitch per axis is the
/// slope of the cluster means; the grid is accepted when both pitches agree within
/// 3 %, every node has exactly one marker, and no marker lies more than 0.25 pitch
/// from its node (the tracker matches within 0.35).
fn fit_grid(markers: &[[f64; 2]], spacing_px: f64) -> Result<DraftGrid, String> {
    if markers.len() < 4 || !spacing_px.is_finite() {
        return Err("fewer than 4 markers: no grid to describe".into());
    }
    let xs: Vec<f64> = markers.iter().map(|p| p[0]).collect();
    let ys: Vec<f64> = markers.iter().map(|p| p[1]).collect();
    let (ix, cx) = clusters(&xs, 0.5 * spacing_px);
    let (iy, cy) = clusters(&ys, 0.5 * spacing_px);
    let (nx, ny) = (cx.len(), cy.len());
    if nx * ny != markers.len() {
        return Err(format!(
            "the {} markers do not form a rectangular grid aligned with the image ({nx} columns × {ny} rows by their coordinates): a hexagonal, rotated, perspective-distorted or irregular layout",
            markers.len()
        ));
    }
    let mut seen = vec![false; nx * ny];
    for (a, b) in ix.iter().zip(&iy) {
        let k = b * nx + a;
        if seen[k] {
            return Err("two markers fall on one grid node: not a rectangular grid".into());
        }
        seen[k] = true;
    }
    let pitch = |c: &[f64]| {
        if c.len() < 2 {
            None
        } else {
            Some((c[c.len() - 1] - c[0]) / (c.len() - 1) as f64)
        }
    };
    let (px, py) = match (pitch(&cx), pitch(&cy)) {
        (Some(a), Some(b)) => (a, b),
        (Some(a), None) => (a, a),
        (None, Some(b)) => (b, b),
        (None, None) => return Err("a single marker: no grid".into()),
    };
    if (px - py).abs() > 0.03 * px.max(py) {
        return Err(format!(
            "the markers form a {nx} × {ny} grid with pitch {px:.2} px along x and {py:.2} px along y: sensor files describe square pitches only (the camera may be tilted; `tactbench calibrate` or a layout-free layer handles it)"
        ));
    }
    let pitch_px = 0.5 * (px + py);
    // Least-squares origin of the nodes origin + pitch·(i, j).
    let n = markers.len() as f64;
    let ox = markers
        .iter()
        .zip(&ix)
        .map(|(p, &i)| p[0] - pitch_px * i as f64)
        .sum::<f64>()
        / n;
    let oy = markers
        .iter()
        .zip(&iy)
        .map(|(p, &j)| p[1] - pitch_px * j as f64)
        .sum::<f64>()
        / n;
    let max_residual_px = markers
        .iter()
        .zip(ix.iter().zip(&iy))
        .map(|(p, (&i, &j))| {
            (p[0] - ox - pitch_px * i as f64).hypot(p[1] - oy - pitch_px * j as f64)
        })
        .fold(0.0, f64::max);
    if max_residual_px > 0.25 * pitch_px {
        return Err(format!(
            "the markers lie up to {max_residual_px:.1} px ({:.0} % of the pitch) from the best square grid of {nx} × {ny} nodes every {pitch_px:.2} px: rotated or distorted",
            100.0 * max_residual_px / pitch_px
        ));
    }
    Ok(DraftGrid {
        nx,
        ny,
        pitch_px,
        origin_px: [ox, oy],
        max_residual_px,
    })
}

impl SensorDraft {
    /// The summary `sensor init` prints.
    pub fn summary(&self) -> String {
        let mut s = format!(
            "{} {} markers; spacing {:.2} px (median nearest neighbour); diameter {:.1} px; contrast {:.1} % of full scale",
            self.markers_px.len(),
            self.color,
            self.spacing_px,
            self.diameter_px,
            self.contrast_percent
        );
        if let Some(r) = self.relative_contrast_percent {
            let _ = write!(s, " ({r:.0} % of the local illumination)");
        }
        let _ = write!(
            s,
            "; {:.1} % of the markers near the {} border (their window crosses it: tracked as lost)",
            100.0 * self.near_border_fraction,
            if self.roi_px.is_some() { "ROI" } else { "image" }
        );
        match (&self.grid, &self.no_grid_reason) {
            (Some(g), _) => {
                let _ = write!(
                    s,
                    "; grid {} × {} every {:.3} px from ({:.2}, {:.2}) px (markers within {:.2} px of their nodes)",
                    g.nx, g.ny, g.pitch_px, g.origin_px[0], g.origin_px[1], g.max_residual_px
                );
            }
            (None, Some(r)) => {
                let _ = write!(s, "; no [layers.markers] grid: {r}");
            }
            (None, None) => {}
        }
        match self.mm_per_px {
            Some(v) => {
                let _ = write!(s, "; mm_per_px {v:.6} ({})", self.scale_source);
            }
            None => s.push_str("; mm_per_px unknown (give --pitch-mm or --mm-per-px)"),
        }
        s
    }

    /// The keys the draft fills with placeholders (its `placeholders` list): the
    /// elastomer and the marker depth always; `mm_per_px` and the force grid (in
    /// pixels then) without a scale.
    pub fn placeholders(&self) -> Vec<&'static str> {
        let mut keys = vec![
            "elastomer.young_modulus_kpa",
            "elastomer.poisson_ratio",
            "elastomer.thickness_mm",
            "layers[0].depth_mm",
        ];
        if self.mm_per_px.is_none() {
            keys.extend([
                "camera.mm_per_px",
                "force_grid.pitch_mm",
                "force_grid.origin_mm",
            ]);
        }
        keys
    }

    /// The sensor-file draft (see the module docs); `reference` names the frame in
    /// the header comment. It starts with `draft = true` and the `placeholders` list
    /// ([`SensorDraft::placeholders`]).
    pub fn to_toml(&self, reference: &str) -> String {
        let mut s = String::new();
        let todo = "# TODO: measure";
        let keys: Vec<String> = self
            .placeholders()
            .iter()
            .map(|k| format!("{k:?}"))
            .collect();
        let _ = writeln!(
            s,
            "# Sensor file draft written by `tactbench sensor init` from {reference}\n\
             # ({} {} markers found; see docs/real-sensors.md). Every value marked\n\
             # `{todo}` is a placeholder that a frame cannot tell: replace it.\n\
             # `draft = true` and `placeholders` say so to the program: `track` uses the\n\
             # draft as it is; `reconstruct`, `run` and `report` refuse it (or run with\n\
             # --allow-draft) until every key in `placeholders` is measured and removed\n\
             # from the list; remove `draft` and `placeholders` with the last one.\n\
             draft = true\n\
             placeholders = [{}]\n",
            self.markers_px.len(),
            self.color,
            keys.join(", ")
        );
        let _ = writeln!(
            s,
            "[elastomer]\n\
             young_modulus_kpa = 1000.0  {todo}: Young's modulus of the gel, kPa (placeholder)\n\
             poisson_ratio = 0.5         {todo}: Poisson ratio in [0, 0.5] (0.5: incompressible; placeholder)\n\
             thickness_mm = 10.0         {todo}: gel thickness, mm (placeholder)\n"
        );
        let scale = self.mm_per_px;
        let _ = writeln!(
            s,
            "[[layers]]\n\
             name = \"markers\"\n\
             color = \"{}\"\n\
             depth_mm = 1.0              {todo}: depth of the markers below the contact surface, mm (placeholder; < thickness_mm)",
            self.color
        );
        // The sensor-frame origin: node (0, 0) of a grid, else the markers' centre.
        let origin_px = match &self.grid {
            Some(g) => g.origin_px,
            None => {
                let n = self.markers_px.len() as f64;
                [
                    self.markers_px.iter().map(|p| p[0]).sum::<f64>() / n,
                    self.markers_px.iter().map(|p| p[1]).sum::<f64>() / n,
                ]
            }
        };
        match (&self.grid, scale) {
            (Some(g), Some(k)) => {
                let _ = writeln!(
                    s,
                    "[layers.markers]                # measured: {} × {} markers every {:.3} px\n\
                     nx = {}\nny = {}\npitch_mm = {:.6}\norigin_mm = [0.0, 0.0]\ndiameter_mm = {:.6}",
                    g.nx,
                    g.ny,
                    g.pitch_px,
                    g.nx,
                    g.ny,
                    g.pitch_px * k,
                    self.diameter_px * k
                );
            }
            (Some(g), None) => {
                let _ = writeln!(
                    s,
                    "# A {} × {} grid every {:.3} px was found; with mm_per_px measured, add:\n\
                     # [layers.markers]\n# nx = {}\n# ny = {}\n# pitch_mm = {:.3} px × mm_per_px\n\
                     # origin_mm = [0.0, 0.0]\n# diameter_mm = {:.2} px × mm_per_px",
                    g.nx, g.ny, g.pitch_px, g.nx, g.ny, g.pitch_px, self.diameter_px
                );
            }
            (None, _) => {
                let _ = writeln!(
                    s,
                    "# No [layers.markers]: {}.\n\
                     # The layout is taken from the reference frame (markers numbered by row, then column).",
                    self.no_grid_reason.as_deref().unwrap_or("no grid")
                );
            }
        }
        // Force grid: covers the markers' extent every two marker spacings.
        let (lo, hi) = self.markers_px.iter().fold(
            ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]),
            |(lo, hi), p| {
                (
                    [lo[0].min(p[0]), lo[1].min(p[1])],
                    [hi[0].max(p[0]), hi[1].max(p[1])],
                )
            },
        );
        let k = scale.unwrap_or(1.0);
        let pitch_px = 2.0 * self.spacing_px;
        let nx = ((hi[0] - lo[0]) / pitch_px).floor() as usize + 1;
        let ny = ((hi[1] - lo[1]) / pitch_px).floor() as usize + 1;
        let origin = [(lo[0] - origin_px[0]) * k, (lo[1] - origin_px[1]) * k];
        let _ = writeln!(
            s,
            "\n[force_grid]                     # TODO: choose: where forces are reconstructed (here: the markers' extent every two spacings{})\n\
             nx = {nx}\nny = {ny}\npitch_mm = {:.6}\norigin_mm = [{:.6}, {:.6}]\n",
            if scale.is_none() {
                ", in px until mm_per_px is known: then multiply pitch_mm and origin_mm by it"
            } else {
                ""
            },
            pitch_px * k,
            origin[0],
            origin[1]
        );
        let _ = writeln!(s, "[camera]");
        match scale {
            Some(v) => {
                let _ = writeln!(s, "mm_per_px = {v:.8}              # {}", self.scale_source);
            }
            None => {
                let _ = writeln!(
                    s,
                    "mm_per_px = 1.0             {todo}: mm per pixel (placeholder); or rerun with --pitch-mm P (the markers' pitch, mm: {:.3} px measured) or --mm-per-px S",
                    self.spacing_px
                );
            }
        }
        let _ = writeln!(
            s,
            "origin_px = [{:.3}, {:.3}]  # {}\nwidth_px = {}\nheight_px = {}",
            origin_px[0],
            origin_px[1],
            if self.grid.is_some() {
                "grid node (0, 0)"
            } else {
                "the markers' centre"
            },
            self.width_px,
            self.height_px
        );
        if let Some(roi) = &self.roi_px {
            let _ = writeln!(s, "roi_px = {roi}");
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roi_argument_parses_both_shapes_and_rejects_garbage() {
        assert_eq!(
            parse_roi_arg("circle:304,250,182").unwrap(),
            Roi::Circle {
                center_px: [304.0, 250.0],
                radius_px: 182.0
            }
        );
        assert_eq!(
            parse_roi_arg("rect:0,0,99.5,50").unwrap(),
            Roi::Rect {
                min_px: [0.0, 0.0],
                max_px: [99.5, 50.0]
            }
        );
        for bad in [
            "circle:1,2",
            "square:1,2,3",
            "rect:1,2,3,x",
            "304,250,182",
            "circle:1,2,inf",
        ] {
            assert!(parse_roi_arg(bad).is_err(), "{bad}");
        }
        let r = parse_roi_arg("rect:1,2,3,4").unwrap();
        assert_eq!(parse_roi_arg(&roi_arg(&r)).unwrap(), r);
    }

    #[test]
    fn grid_fit_finds_square_grids_and_names_what_else_it_sees() {
        let grid: Vec<[f64; 2]> = (0..4)
            .flat_map(|j| (0..5).map(move |i| [10.0 + 20.0 * i as f64, 7.0 + 20.0 * j as f64]))
            .collect();
        let g = fit_grid(&grid, 20.0).unwrap();
        assert_eq!((g.nx, g.ny), (5, 4));
        assert!((g.pitch_px - 20.0).abs() < 1e-12 && g.max_residual_px < 1e-9);
        assert!((g.origin_px[0] - 10.0).abs() < 1e-12 && (g.origin_px[1] - 7.0).abs() < 1e-12);
        // 29 × 26 px pitches (the FOTS gel): rectangular, not square.
        let rect: Vec<[f64; 2]> = (0..3)
            .flat_map(|j| (0..3).map(move |i| [29.0 * i as f64, 26.0 * j as f64]))
            .collect();
        assert!(fit_grid(&rect, 26.0).unwrap_err().contains("square"));
        // Hexagonal packing: odd rows shifted by half a pitch.
        let hex: Vec<[f64; 2]> = (0..4)
            .flat_map(|j| {
                (0..4).map(move |i| [20.0 * i as f64 + 10.0 * (j % 2) as f64, 17.32 * j as f64])
            })
            .collect();
        assert!(fit_grid(&hex, 20.0).is_err());
    }
}
