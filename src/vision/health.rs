//! Does a reference frame show the sensor the sensor file describes? The measured
//! numbers of a reference detection ([`ReferenceHealth`]) and, when markers are
//! missing, what is likely wrong ([`ReferenceHealth::diagnosis`]):
//!
//! * **scale** — the markers' measured pitch (median nearest same-layer neighbour,
//!   px) against the file's `pitch_mm / mm_per_px`; a pitch off by more than
//!   [`SCALE_TOLERANCE`] suggests `mm_per_px = pitch_mm / measured pitch`;
//! * **origin** — the centre of the blobs found against the centre of the grid nodes
//!   the file puts inside the image; an offset above [`ORIGIN_TOLERANCE`] pitches
//!   suggests moving `origin_px` by it;
//! * **colour** — a layer with no blob of its colour while another layer has some;
//! * **exposure** — the frame's mean level and saturated pixels (over-exposed, or too
//!   dark for any marker to stand out).

use std::fmt;

use super::detect::{detect, DetectConfig, Reference};
use super::image::FrameView;
use super::Pixels;
use crate::sensor::{MarkerColor, Sensor};

/// Relative pitch error beyond which the scale is reported as the likely cause.
pub const SCALE_TOLERANCE: f64 = 0.03;

/// Offset of the blobs' centre from the grid's, in pitches, beyond which the origin is
/// reported as the likely cause.
pub const ORIGIN_TOLERANCE: f64 = 0.2;

/// A pixel whose brightest channel reaches this fraction of full scale is saturated.
const SATURATION_LEVEL: f64 = 0.98;

/// One layer's numbers.
#[derive(Debug, Clone, PartialEq)]
pub struct LayerHealth {
    /// Layer name.
    pub name: String,
    /// Layer colour.
    pub color: MarkerColor,
    /// Markers the sensor file gives this layer (grid nodes; 0 without a grid).
    pub expected: usize,
    /// Markers matched to a grid node (every blob for a layer without a grid).
    pub found: usize,
    /// Blobs of the layer's colour, matched or not.
    pub blobs: usize,
    /// Measured marker pitch (median nearest-neighbour distance of the blobs), px;
    /// `None` with fewer than two blobs.
    pub pitch_px: Option<f64>,
    /// The pitch the sensor file implies (`pitch_mm / mm_per_px`), px.
    pub expected_pitch_px: Option<f64>,
    /// Centre of the blobs, px.
    pub centre_px: Option<[f64; 2]>,
    /// Centre of the file's grid nodes inside the image, px.
    pub expected_centre_px: Option<[f64; 2]>,
    /// Another layer most of whose blobs this layer's blobs sit on (within
    /// [`COINCIDENT_PX`]), with the count: its colour picks up that layer's markers.
    pub coincides_with: Option<(String, usize)>,
}

/// Blobs of two layers closer than this are the same marker seen by both colours, px.
pub const COINCIDENT_PX: f64 = 3.0;

/// What a reference frame shows, measured against the sensor file.
#[derive(Debug, Clone, PartialEq)]
pub struct ReferenceHealth {
    /// Per layer, in sensor order.
    pub layers: Vec<LayerHealth>,
    /// Mean sample level over the frame, fraction of full scale.
    pub mean_level: f64,
    /// Fraction of pixels whose brightest channel is saturated.
    pub saturated_fraction: f64,
    /// The sensor file's `mm_per_px`.
    pub mm_per_px: f64,
    /// The sensor file's `origin_px`.
    pub origin_px: [f64; 2],
}

impl ReferenceHealth {
    /// Measures `view` against `sensor` with the detection result (`None` when the
    /// detection failed: no blob matched any grid node; the blobs are then found again
    /// without the grids, so pitch and centre are still measured).
    pub fn of(reference: Option<&Reference>, sensor: &Sensor, view: &FrameView<'_>) -> Self {
        let cam = &sensor.camera;
        let gridless;
        let (reference, matched) = match reference {
            Some(r) => (Some(r), true),
            None => {
                let mut free = sensor.clone();
                for l in &mut free.layers {
                    l.markers = None;
                }
                gridless = detect(view, &free, &DetectConfig::default()).ok();
                (gridless.as_ref(), false)
            }
        };
        let (w, h) = (view.width_px() as f64, view.height_px() as f64);
        let mut layers: Vec<LayerHealth> = Vec::with_capacity(sensor.layers.len());
        let mut all_blobs: Vec<Vec<[f64; 2]>> = Vec::with_capacity(sensor.layers.len());
        for (li, layer) in sensor.layers.iter().enumerate() {
            let health = {
                let mut blobs: Vec<[f64; 2]> = Vec::new();
                let mut found = 0;
                if let Some(r) = reference {
                    for m in r.markers.iter().filter(|m| m.layer == li) {
                        blobs.push(m.centroid_px);
                        found += usize::from(matched);
                    }
                    blobs.extend(
                        r.unmatched
                            .iter()
                            .filter(|u| u.layer == li)
                            .map(|u| u.centroid_px),
                    );
                }
                let (expected, expected_pitch_px, expected_centre_px) = match &layer.markers {
                    Some(m) => {
                        let inside: Vec<[f64; 2]> = m
                            .grid
                            .nodes_mm()
                            .into_iter()
                            .map(|p| cam.mm_to_px(p))
                            .filter(|p| {
                                p[0] >= -0.5 && p[1] >= -0.5 && p[0] <= w - 0.5 && p[1] <= h - 0.5
                            })
                            .collect();
                        (
                            m.grid.len(),
                            Some(m.grid.pitch_mm / cam.mm_per_px),
                            mean_point(&inside),
                        )
                    }
                    None => (0, None, None),
                };
                let health = LayerHealth {
                    name: layer.name.clone(),
                    color: layer.color,
                    expected,
                    found,
                    blobs: blobs.len(),
                    pitch_px: nearest_neighbour_median(&blobs),
                    expected_pitch_px,
                    centre_px: mean_point(&blobs),
                    expected_centre_px,
                    coincides_with: None,
                };
                all_blobs.push(blobs);
                health
            };
            layers.push(health);
        }
        for li in 0..layers.len() {
            let mine = &all_blobs[li];
            let best = (0..layers.len())
                .filter(|&lj| lj != li)
                .map(|lj| {
                    let n = mine
                        .iter()
                        .filter(|a| {
                            all_blobs[lj]
                                .iter()
                                .any(|b| (a[0] - b[0]).hypot(a[1] - b[1]) < COINCIDENT_PX)
                        })
                        .count();
                    (n, lj)
                })
                .max();
            if let Some((n, lj)) = best {
                if n > 0 && 2 * n > mine.len() {
                    layers[li].coincides_with = Some((layers[lj].name.clone(), n));
                }
            }
        }
        let (mean_level, saturated_fraction) = levels(view);
        ReferenceHealth {
            layers,
            mean_level,
            saturated_fraction,
            mm_per_px: cam.mm_per_px,
            origin_px: cam.origin_px,
        }
    }

    /// Markers the sensor file gives all layers with a grid.
    pub fn expected(&self) -> usize {
        self.layers.iter().map(|l| l.expected).sum()
    }

    /// Markers matched to a grid node (layers with a grid only).
    pub fn found(&self) -> usize {
        self.layers
            .iter()
            .filter(|l| l.expected > 0)
            .map(|l| l.found)
            .sum()
    }

    /// `found / expected` (1 when no layer has a grid).
    pub fn found_fraction(&self) -> f64 {
        match self.expected() {
            0 => 1.0,
            n => self.found() as f64 / n as f64,
        }
    }

    /// The measured numbers, one clause per quantity: per-layer found counts, pitch,
    /// centre and frame levels.
    pub fn measurements(&self) -> String {
        let mut parts = Vec::new();
        let counts: Vec<String> = self
            .layers
            .iter()
            .map(|l| {
                format!(
                    "{} {} of {} ({} blobs of its colour)",
                    l.name, l.found, l.expected, l.blobs
                )
            })
            .collect();
        parts.push(format!("found per layer: {}", counts.join(", ")));
        for l in &self.layers {
            if let (Some(m), Some(e)) = (l.pitch_px, l.expected_pitch_px) {
                parts.push(format!(
                    "{} marker pitch {:.1} px (sensor file: {:.1} px)",
                    l.name, m, e
                ));
            }
        }
        for l in &self.layers {
            if let (Some(c), Some(e)) = (l.centre_px, l.expected_centre_px) {
                parts.push(format!(
                    "{} markers centred at ({:.1}, {:.1}) px (sensor file: ({:.1}, {:.1}) px)",
                    l.name, c[0], c[1], e[0], e[1]
                ));
            }
        }
        parts.push(format!(
            "frame mean level {:.0} % of full scale, {:.1} % of pixels saturated",
            100.0 * self.mean_level,
            100.0 * self.saturated_fraction
        ));
        parts.join("; ")
    }

    /// Likely causes of missing markers, most specific first, each with its numbers.
    /// Empty when nothing stands out.
    pub fn diagnosis(&self) -> Vec<String> {
        let mut out = Vec::new();
        if self.saturated_fraction > 0.5 || self.mean_level > 0.9 {
            out.push(format!(
                "exposure: the frame is over-exposed ({:.0} % of pixels saturated, mean level {:.0} % of full scale): reduce the exposure or the lighting",
                100.0 * self.saturated_fraction,
                100.0 * self.mean_level
            ));
        } else if self.mean_level < 0.03 {
            out.push(format!(
                "exposure: the frame is dark (mean level {:.1} % of full scale): check the lighting, the exposure and the lens cap",
                100.0 * self.mean_level
            ));
        }
        // Scale: the pitch of every layer that shows one, in agreement.
        let ratios: Vec<(f64, f64, f64)> = self
            .layers
            .iter()
            .filter_map(|l| match (l.pitch_px, l.expected_pitch_px) {
                (Some(m), Some(e)) if l.blobs >= 4 => Some((m, e, m / e)),
                _ => None,
            })
            .collect();
        let scale_off = !ratios.is_empty()
            && ratios
                .iter()
                .all(|(_, _, r)| (r - 1.0).abs() > SCALE_TOLERANCE);
        if scale_off {
            let (m, e, _) = ratios[0];
            let pitch_mm = e * self.mm_per_px;
            out.push(format!(
                "scale: the markers are {m:.1} px apart but the sensor file expects {e:.1} px (pitch {pitch_mm} mm / [camera] mm_per_px {}): mm_per_px is probably {:.4} ({pitch_mm} mm / {m:.1} px)",
                self.mm_per_px,
                pitch_mm / m
            ));
        }
        let any_blobs = self.layers.iter().any(|l| l.blobs > 0);
        let mut colour_suspect = vec![false; self.layers.len()];
        for (l, suspect) in self.layers.iter().zip(&mut colour_suspect) {
            if l.expected == 0 || l.found == l.expected {
                continue;
            }
            if l.blobs == 0 && any_blobs {
                *suspect = true;
                out.push(format!(
                    "colour: no {} blob for layer {} while other layers show theirs: check the layer's color in the sensor file",
                    l.color, l.name
                ));
            } else if let Some((other, n)) = &l.coincides_with {
                *suspect = true;
                out.push(format!(
                    "colour: {n} of the {} blobs found for layer {} ({}) sit on layer {other}'s markers: check the layer's color in the sensor file",
                    l.blobs, l.name, l.color
                ));
            }
        }
        if !scale_off {
            for (l, suspect) in self.layers.iter().zip(&colour_suspect) {
                if *suspect || l.found == l.expected {
                    continue;
                }
                if let (Some(c), Some(e), Some(p)) =
                    (l.centre_px, l.expected_centre_px, l.expected_pitch_px)
                {
                    let d = [c[0] - e[0], c[1] - e[1]];
                    if l.blobs >= 4 && d[0].hypot(d[1]) > ORIGIN_TOLERANCE * p {
                        out.push(format!(
                            "origin: the {} markers are centred at ({:.1}, {:.1}) px but the sensor file puts them at ({:.1}, {:.1}) px: [camera] origin_px ({}, {}) is probably off by ({:.1}, {:.1}) px",
                            l.name, c[0], c[1], e[0], e[1], self.origin_px[0], self.origin_px[1], d[0], d[1]
                        ));
                        break;
                    }
                }
            }
        }
        if !any_blobs && out.is_empty() {
            out.push(
                "no marker of any layer's colour stands out: the frame may be blank, out of focus or of another scene, or the layers' colors in the sensor file may be wrong"
                    .to_string(),
            );
        }
        out
    }
}

impl fmt::Display for ReferenceHealth {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.expected() == 0 {
            // No layer has a grid: nothing to count against (not "0 of 0 (100 %)").
            let blobs: usize = self.layers.iter().map(|l| l.blobs).sum();
            return write!(
                f,
                "{blobs} marker blob(s) found; no layer has a [layers.markers] grid, so the sensor file gives no count to check them against"
            );
        }
        write!(
            f,
            "{} of {} markers found ({:.0} %)",
            self.found(),
            self.expected(),
            100.0 * self.found_fraction()
        )
    }
}

fn mean_point(p: &[[f64; 2]]) -> Option<[f64; 2]> {
    if p.is_empty() {
        return None;
    }
    let n = p.len() as f64;
    Some([
        p.iter().map(|q| q[0]).sum::<f64>() / n,
        p.iter().map(|q| q[1]).sum::<f64>() / n,
    ])
}

/// Median distance from each point to its nearest neighbour (`None` below 2 points).
fn nearest_neighbour_median(p: &[[f64; 2]]) -> Option<f64> {
    if p.len() < 2 {
        return None;
    }
    let mut d: Vec<f64> = p
        .iter()
        .enumerate()
        .map(|(i, a)| {
            p.iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, b)| (a[0] - b[0]).hypot(a[1] - b[1]))
                .fold(f64::INFINITY, f64::min)
        })
        .collect();
    d.sort_by(f64::total_cmp);
    Some(d[d.len() / 2])
}

/// Mean sample level (fraction of full scale, alpha ignored) and the fraction of
/// saturated pixels.
fn levels(view: &FrameView<'_>) -> (f64, f64) {
    fn scan<T: Copy + Into<f64>>(data: &[T], channels: usize, full: f64) -> (f64, f64) {
        let (mut sum, mut saturated, mut n) = (0.0, 0usize, 0usize);
        for px in data.chunks_exact(channels) {
            // A grey sample reads as (g, g, g).
            let at = |k: usize| -> f64 { px[if channels == 1 { 0 } else { k }].into() };
            let rgb = [at(0), at(1), at(2)];
            sum += rgb[0] + rgb[1] + rgb[2];
            if rgb.iter().fold(0.0f64, |m, v| m.max(*v)) >= SATURATION_LEVEL * full {
                saturated += 1;
            }
            n += 1;
        }
        if n == 0 {
            return (0.0, 0.0);
        }
        (sum / (3.0 * n as f64 * full), saturated as f64 / n as f64)
    }
    match view.pixels() {
        Pixels::Rgb8(d) => scan(d, 3, 255.0),
        Pixels::Rgba8(d) => scan(d, 4, 255.0),
        Pixels::Rgb16(d) => scan(d, 3, 65535.0),
        Pixels::Rgba16(d) => scan(d, 4, 65535.0),
        Pixels::Gray8(d) => scan(d, 1, 255.0),
        Pixels::Gray16(d) => scan(d, 1, 65535.0),
    }
}
