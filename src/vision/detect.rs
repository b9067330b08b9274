//! Reference layout: find every layer's markers in an unloaded frame and match them to
//! the layer grids of sensor.toml (paper Section II-A: "the position of markers is
//! determined from the CCD image when the elastic body doesn't vary ... markers at
//! arbitrary positions").
//!
//! Per layer: colour score map (see `window.rs`); robust statistics (median `b`, noise
//! `σ = 1.4826·MAD`, peak `p` = 20th largest score, immune to a few hot pixels);
//! threshold `T = b + max(6σ, 0.2·(p − b))`; 8-connected components above `T`; blobs
//! smaller than a fifth of the expected marker area dropped as noise. Brightness
//! layers (`dark`, `bright`) threshold their contrast map instead (`contrast.rs`),
//! keep blobs of 40 % of a marker's area that are round. A blob too small for the
//! layer's marker size but otherwise a marker is judged against its neighbours'
//! size instead (`keep_markers`: the far rows of a sensor seen in strong perspective);
//! its window must stay on it, or it is left to the second pass. Brightness layers
//! then run a second, low-threshold pass (`contrast::faint_spots`): local maxima of the smoothed map
//! outside the first pass's blobs, judged against the local noise by their own peak
//! and half-height area, so faint markers (a vignetted field's edge) are not lost to
//! a threshold the brightest markers set; the blobs the layer's size keeps alone set
//! the aperture and spacing, so their markers are measured as before. The aperture
//! radius is the marker's measured extent (where the score falls to 5 % of the blob's
//! peak, median over blobs and the four axis directions) plus 1.5 px, so soft edges of
//! any profile stay inside the aperture; it is capped so the background ring never
//! reaches the nearest same-layer neighbour. Each blob is then refined by the iterated
//! window centroid. A detection is matched to the nearest grid node when it lies
//! within `match_tolerance` pitches of it (the nearer of two claimants wins).

use super::camera::PixelMapping;
use super::contrast;
use super::image::{check_layers, FrameView};
use super::window::{dot_inside, score, score_bias, score_weights, Located, Raw, Sample, Window};
use super::{Pixels, VisionError};
use crate::sensor::{MarkerColor, Roi, Sensor};

/// Options of [`detect`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DetectConfig {
    /// A detection matches a grid node within this many pitches (default 0.35).
    pub match_tolerance: f64,
    /// Overrides the measured aperture radius, px.
    pub aperture_radius_px: Option<f64>,
}

impl Default for DetectConfig {
    fn default() -> Self {
        DetectConfig {
            match_tolerance: 0.35,
            aperture_radius_px: None,
        }
    }
}

/// Per-layer results of the reference detection.
#[derive(Debug, Clone, PartialEq)]
pub struct LayerReference {
    /// Layer name (sensor.toml).
    pub name: String,
    /// Layer colour.
    pub color: MarkerColor,
    /// Marker radius used for size checks, px (grid diameter / 2, else measured).
    pub marker_radius_px: f64,
    /// Aperture radius of the centroid window, px.
    pub aperture_radius_px: f64,
    /// Median distance to the nearest same-layer marker, px (infinite for one marker).
    pub spacing_px: f64,
    /// Median colour score of the image (the background's score).
    pub background_score: f64,
    /// Channel weights of the colour score (`window::score_weights`).
    pub score_weights: [i32; 3],
}

/// A marker found in the reference image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReferenceMarker {
    /// Layer index in the sensor.
    pub layer: usize,
    /// Marker id: row-major grid index when the layer has a grid, else the order of
    /// the centroids by image row, then column.
    pub id: u64,
    /// Sub-pixel centroid, px.
    pub centroid_px: [f64; 2],
    /// The centroid in the sensor frame, mm (`CameraMapping::px_to_mm`).
    pub position_mm: [f64; 2],
    /// Background-corrected signal (score × px), the scale for lost/merged checks.
    pub signal: f64,
    /// Largest colour score in the aperture, above the layer's background score.
    pub peak: f64,
    /// Background score of the window (the ring's plane fit at the centre).
    pub background: f64,
    /// Background plane slope, score per px. A frame whose ring plane differs from
    /// the reference's by more than 5 % of `peak` (level change + slope change × ring
    /// radius) is re-measured with the clamped score: another layer's marker is in the
    /// window.
    pub background_slope: [f64; 2],
    /// A `dark` marker with a specular highlight on it in the reference: a pixel
    /// within 60 % of its radius of its centroid at ≥ 98 % of full scale. Its reference
    /// centroid is pulled away from the highlight, so the tracker never reports it
    /// `ok`. Always `false` for other appearances.
    pub highlight: bool,
    /// A `bright` marker's saturated pixels in the reference (any channel at ≥ 98 %
    /// of full scale, centres within its radius of its centroid): how many, and their
    /// mean offset from the centroid, px (`[0, 0]` when none). A bright marker may
    /// saturate by itself; the tracker compares each frame's with these (see
    /// [`saturation_within`]). Zero for other appearances.
    pub saturation: Saturation,
}

/// Saturated pixels on a marker (see [`ReferenceMarker::saturation`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Saturation {
    /// Saturated pixels.
    pub count: u32,
    /// Their mean offset from the marker's centroid, px.
    pub offset_px: [f64; 2],
}

/// A grid node with no marker found near it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MissingMarker {
    /// Layer index.
    pub layer: usize,
    /// Row-major grid index.
    pub id: u64,
    /// Node position, mm.
    pub node_mm: [f64; 2],
}

/// A blob that matched no grid node (or lost a node to a nearer blob).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UnmatchedBlob {
    /// Layer index.
    pub layer: usize,
    /// Centroid, px.
    pub centroid_px: [f64; 2],
    /// Centroid, mm.
    pub position_mm: [f64; 2],
}

/// The reference layout: every found marker with its id, plus what did not match.
#[derive(Debug, Clone, PartialEq)]
pub struct Reference {
    /// Image width, px.
    pub width_px: u32,
    /// Image height, px.
    pub height_px: u32,
    /// One entry per sensor layer, in sensor order.
    pub layers: Vec<LayerReference>,
    /// Found markers, sorted by layer then id.
    pub markers: Vec<ReferenceMarker>,
    /// Grid nodes with no marker (tracked as lost in every frame).
    pub missing: Vec<MissingMarker>,
    /// Blobs without a grid node (not tracked).
    pub unmatched: Vec<UnmatchedBlob>,
    /// Bits per sample of the image the reference was found in (8 or 16). Signals,
    /// peaks and background scores above are in that image's levels; the tracker
    /// rescales them (× 257 or ÷ 257) for a frame of the other depth.
    pub bit_depth: u32,
    /// The sensor file's `[camera] roi_px`: markers were sought only inside it, and the
    /// tracker reports a marker whose window crosses its border `lost`.
    pub roi_px: Option<Roi>,
}

macro_rules! with_raw {
    ($view:expr, $img:ident => $body:expr) => {{
        let width = $view.width_px() as usize;
        let height = $view.height_px() as usize;
        match $view.pixels() {
            Pixels::Rgb8(data) => {
                let $img = Raw::<u8, 3> {
                    data,
                    width,
                    height,
                };
                $body
            }
            Pixels::Rgba8(data) => {
                let $img = Raw::<u8, 4> {
                    data,
                    width,
                    height,
                };
                $body
            }
            Pixels::Rgb16(data) => {
                let $img = Raw::<u16, 3> {
                    data,
                    width,
                    height,
                };
                $body
            }
            Pixels::Rgba16(data) => {
                let $img = Raw::<u16, 4> {
                    data,
                    width,
                    height,
                };
                $body
            }
            Pixels::Gray8(data) => {
                let $img = Raw::<u8, 1> {
                    data,
                    width,
                    height,
                };
                $body
            }
            Pixels::Gray16(data) => {
                let $img = Raw::<u16, 1> {
                    data,
                    width,
                    height,
                };
                $body
            }
        }
    }};
}
pub(crate) use with_raw;

/// A refined blob of one layer.
#[derive(Debug, Clone, Copy)]
struct Blob {
    centroid_px: [f64; 2],
    signal: f64,
    peak: f64,
    background: f64,
    slope: [f64; 2],
}

struct LayerBlobs {
    blobs: Vec<Blob>,
    marker_radius_px: f64,
    aperture_radius_px: f64,
    spacing_px: f64,
    background_score: f64,
}

impl LayerBlobs {
    /// A layer without markers.
    fn none(marker_radius_px: f64, aperture_radius_px: f64, background_score: f64) -> Self {
        LayerBlobs {
            blobs: Vec::new(),
            marker_radius_px,
            aperture_radius_px,
            spacing_px: f64::INFINITY,
            background_score,
        }
    }
}

/// Finds the markers of every layer in an unloaded frame and matches them to the
/// layer grids (see the module docs). Fails only when no layer has any marker.
pub fn detect(
    view: &FrameView<'_>,
    sensor: &Sensor,
    config: &DetectConfig,
) -> Result<Reference, VisionError> {
    detect_mapped(view, sensor, config, &PixelMapping::Linear(sensor.camera))
}

/// As [`detect`], converting pixels to the sensor frame with `mapping` (a camera
/// calibration, per layer) instead of the sensor file's `[camera]` mapping: blobs are
/// matched to grid nodes, and reference positions given, in that mapping.
pub fn detect_mapped(
    view: &FrameView<'_>,
    sensor: &Sensor,
    config: &DetectConfig,
    mapping: &PixelMapping,
) -> Result<Reference, VisionError> {
    check_layers(
        view,
        sensor.layers.iter().map(|l| (l.name.as_str(), l.color)),
    )?;
    let mut layers = Vec::with_capacity(sensor.layers.len());
    let mut markers = Vec::new();
    let mut missing = Vec::new();
    let mut unmatched = Vec::new();
    for (li, layer) in sensor.layers.iter().enumerate() {
        let mm_per_px = mapping.mm_per_px(li);
        let expected_r = layer.markers.map(|m| 0.5 * m.diameter_mm / mm_per_px);
        let used: Vec<MarkerColor> = sensor.layers.iter().map(|l| l.color).collect();
        let weights = score_weights(layer.color, &used);
        let found = with_raw!(view, img => detect_layer(img, layer.color, weights, expected_r, sensor.camera.roi_px.as_ref(), config));
        layers.push(LayerReference {
            name: layer.name.clone(),
            color: layer.color,
            marker_radius_px: found.marker_radius_px,
            aperture_radius_px: found.aperture_radius_px,
            spacing_px: found.spacing_px,
            background_score: found.background_score,
            score_weights: weights,
        });
        let inner_px = highlight_radius_px(found.marker_radius_px);
        let to_marker = |b: &Blob, id: u64| ReferenceMarker {
            highlight: layer.color == MarkerColor::Dark
                && with_raw!(view, img => highlight_within(&img, b.centroid_px, inner_px)),
            saturation: if layer.color == MarkerColor::Bright {
                with_raw!(view, img => saturation_within(&img, b.centroid_px, found.marker_radius_px))
            } else {
                Saturation::default()
            },
            layer: li,
            id,
            centroid_px: b.centroid_px,
            position_mm: mapping.px_to_mm(li, b.centroid_px),
            signal: b.signal,
            peak: b.peak,
            background: b.background,
            background_slope: b.slope,
        };
        match &layer.markers {
            Some(m) => {
                let grid = m.grid;
                // Best claimant per node: (blob index, distance mm).
                let mut claim: Vec<Option<(usize, f64)>> = vec![None; grid.len()];
                let mut rejected = Vec::new();
                for (bi, b) in found.blobs.iter().enumerate() {
                    let p = mapping.px_to_mm(li, b.centroid_px);
                    match grid.nearest_node(p) {
                        Some(((ix, iy), d)) if d <= config.match_tolerance * grid.pitch_mm => {
                            let k = iy * grid.nx + ix;
                            match claim[k] {
                                Some((_, od)) if od <= d => rejected.push(bi),
                                Some((other, _)) => {
                                    rejected.push(other);
                                    claim[k] = Some((bi, d));
                                }
                                None => claim[k] = Some((bi, d)),
                            }
                        }
                        _ => rejected.push(bi),
                    }
                }
                for (k, c) in claim.iter().enumerate() {
                    match c {
                        Some((bi, _)) => markers.push(to_marker(&found.blobs[*bi], k as u64)),
                        None => missing.push(MissingMarker {
                            layer: li,
                            id: k as u64,
                            node_mm: grid.node_mm(k % grid.nx, k / grid.nx),
                        }),
                    }
                }
                rejected.sort_unstable();
                for bi in rejected {
                    let b = &found.blobs[bi];
                    unmatched.push(UnmatchedBlob {
                        layer: li,
                        centroid_px: b.centroid_px,
                        position_mm: mapping.px_to_mm(li, b.centroid_px),
                    });
                }
            }
            None => {
                let mut blobs = found.blobs.clone();
                blobs.sort_by(|a, b| {
                    (a.centroid_px[1].round(), a.centroid_px[0])
                        .partial_cmp(&(b.centroid_px[1].round(), b.centroid_px[0]))
                        .unwrap_or(std::cmp::Ordering::Equal)
                });
                for (k, b) in blobs.iter().enumerate() {
                    markers.push(to_marker(b, k as u64));
                }
            }
        }
    }
    if markers.is_empty() {
        return Err(VisionError::NoMarkers {
            layers: sensor
                .layers
                .iter()
                .enumerate()
                .map(|(i, l)| format!("{}: layers[{i}].color = \"{}\"", l.name, l.color))
                .collect::<Vec<_>>()
                .join(", "),
        });
    }
    Ok(Reference {
        width_px: view.width_px(),
        height_px: view.height_px(),
        layers,
        markers,
        missing,
        unmatched,
        bit_depth: view.bit_depth(),
        roi_px: sensor.camera.roi_px,
    })
}

/// A sample at or above this share of full scale is saturated: on a `dark` marker, a
/// specular highlight (the reflection of a light source on the gel).
pub(crate) const HIGHLIGHT_LEVEL: f64 = 0.98;

/// The radius around a `dark` marker's centroid searched for highlights: 60 % of the
/// marker's, so that a dot stretched or compressed by the load (0.7–1.3 × on the real
/// FOTS pair) still covers it and the lit gel around the dot, saturated on many
/// GelSight-type sensors, stays out.
pub(crate) fn highlight_radius_px(marker_radius_px: f64) -> f64 {
    (0.6 * marker_radius_px).max(1.0)
}

/// Whether a pixel whose centre lies within `radius_px` of `centre_px` reaches
/// [`HIGHLIGHT_LEVEL`] of full scale in any colour channel. Inside a dark marker that
/// is a specular highlight: it hides part of the marker, and since it stays where the
/// light's reflection is while the marker moves (or changes shape with the load), it
/// moves the centroid by up to a pixel or more — a displacement no neighbour check
/// catches when it stays below a quarter spacing (measured: 2.15 px on a 30 px
/// pitch, `tests/vision_tracking.rs`).
pub(crate) fn highlight_within<T: Sample, const C: usize>(
    img: &Raw<'_, T, C>,
    centre_px: [f64; 2],
    radius_px: f64,
) -> bool {
    saturated_within(img, centre_px, radius_px).next().is_some()
}

/// The offsets `(dx, dy)` from `centre_px` of the pixels whose centres lie within
/// `radius_px` of it and that reach [`HIGHLIGHT_LEVEL`] of full scale in any colour
/// channel, row by row (nothing for a non-finite centre or radius).
fn saturated_within<'a, T: Sample, const C: usize>(
    img: &'a Raw<'_, T, C>,
    centre_px: [f64; 2],
    radius_px: f64,
) -> impl Iterator<Item = [f64; 2]> + 'a {
    let finite = centre_px[0].is_finite() && centre_px[1].is_finite() && radius_px.is_finite();
    let limit = (HIGHLIGHT_LEVEL * T::MAX as f64).ceil() as i32;
    let (w, h) = (img.width as f64, img.height as f64);
    let x0 = (centre_px[0] - radius_px).ceil().max(0.0);
    let x1 = (centre_px[0] + radius_px).floor().min(w - 1.0);
    let y0 = (centre_px[1] - radius_px).ceil().max(0.0);
    let y1 = (centre_px[1] + radius_px).floor().min(h - 1.0);
    // An empty range when the disc misses the image (or nothing is finite).
    let (ys, xs) = if finite && x0 <= x1 && y0 <= y1 {
        (y0 as usize..y1 as usize + 1, x0 as usize..x1 as usize + 1)
    } else {
        (0..0, 0..0)
    };
    let r2 = radius_px * radius_px;
    ys.flat_map(move |y| xs.clone().map(move |x| (x, y)))
        .filter_map(move |(x, y)| {
            let d = [x as f64 - centre_px[0], y as f64 - centre_px[1]];
            let px = &img.data[(y * img.width + x) * C..][..C.min(3)];
            (d[0] * d[0] + d[1] * d[1] <= r2 && px.iter().any(|v| v.value() >= limit)).then_some(d)
        })
}

/// The saturated pixels (any channel at [`HIGHLIGHT_LEVEL`] of full scale or more)
/// whose centres lie within `radius_px` of `centre_px`: their count and mean offset
/// from `centre_px`. A specular highlight on a `bright` marker stays where the light's
/// reflection is while the marker moves: against the reference its saturated pixels
/// grow, appear or vanish, or stay put relative to the image instead of moving with
/// the marker. A marker that saturates by itself keeps its saturated core centred on
/// it (see `Tracker::flag_highlights`).
pub(crate) fn saturation_within<T: Sample, const C: usize>(
    img: &Raw<'_, T, C>,
    centre_px: [f64; 2],
    radius_px: f64,
) -> Saturation {
    let (mut n, mut sx, mut sy) = (0u32, 0.0, 0.0);
    for [dx, dy] in saturated_within(img, centre_px, radius_px) {
        n += 1;
        sx += dx;
        sy += dy;
    }
    Saturation {
        count: n,
        offset_px: if n > 0 {
            [sx / n as f64, sy / n as f64]
        } else {
            [0.0; 2]
        },
    }
}

/// Largest elongation (√ of the ratio of the principal second moments) of a blob of a
/// brightness layer: a disc is 1, a disc seen at 60° from its normal 2; on the striped
/// GelSight frame a scratch measures 4.1 and the markers at most 1.3.
const MAX_ELONGATION: f64 = 2.2;

/// The `k`-th smallest of `v` (reorders `v`).
fn kth(v: &mut [i32], k: usize) -> i32 {
    let k = k.min(v.len() - 1);
    *v.select_nth_unstable(k).1
}

/// The layer's view of the frame, shared by the steps of [`detect_layer`].
struct LayerFrame<'a, T: Sample, const C: usize> {
    img: Raw<'a, T, C>,
    color: MarkerColor,
    weights: [i32; 3],
    roi: Option<&'a Roi>,
    /// The colour score of every pixel (`window::score`).
    score: Vec<i32>,
    /// Pixels whose centre lies inside the ROI (`None`: all, no ROI).
    inside: Option<Vec<bool>>,
}

impl<T: Sample, const C: usize> LayerFrame<'_, T, C> {
    /// The values of `m` the statistics see: those inside the ROI.
    fn inside_values(&self, m: &[i32]) -> Vec<i32> {
        match &self.inside {
            Some(mask) => m
                .iter()
                .zip(mask)
                .filter(|(_, &i)| i)
                .map(|(&v, _)| v)
                .collect(),
            None => m.to_vec(),
        }
    }

    /// `m` with every pixel outside the ROI below any threshold: the map blobs are
    /// found in.
    fn masked(&self, m: Vec<i32>) -> Vec<i32> {
        match &self.inside {
            Some(mask) => m
                .into_iter()
                .zip(mask)
                .map(|(v, &i)| if i { v } else { i32::MIN })
                .collect(),
            None => m,
        }
    }
}

/// The map one layer's blobs are found in and its statistics: the colour score itself
/// for colour layers (their score cancels grey illumination), the contrast against the
/// local illumination for brightness layers (their score does not; `contrast.rs`).
struct LayerMap {
    /// The map, every pixel outside the ROI at `i32::MIN`.
    map: Vec<i32>,
    /// The map's median inside the ROI (its background).
    median: i32,
    /// Pixels above this form the blobs.
    threshold: i32,
    /// Map units per score unit (1 for colour layers).
    map_per_score: f64,
    /// A brightness layer's illumination estimate (`contrast::ContrastMap`).
    illumination: Option<Vec<i32>>,
}

/// A brightness layer's contrast map and threshold, or `None` when nothing stands out
/// of the noise. Without an expected marker size (no grid), a first pass with a long
/// element measures it, and the map is made with the element that follows from it.
fn brightness_map<T: Sample, const C: usize>(
    f: &LayerFrame<'_, T, C>,
    expected_radius_px: Option<f64>,
) -> Option<LayerMap> {
    let (w, h) = (f.img.width, f.img.height);
    let noise = contrast::score_noise(&f.score, w, f.inside.as_deref());
    let min_contrast = contrast::min_contrast::<T>(f.color);
    let stats = |m: &[i32], map_per_score: f64| {
        contrast::threshold(&f.inside_values(m), noise * map_per_score, min_contrast)
    };
    let size = match expected_radius_px {
        Some(r) => contrast::element_size(r),
        None => {
            let first_size = contrast::default_element_size(w, h);
            let first = contrast::contrast_map::<T>(&f.score, w, h, f.color, first_size);
            let t = stats(&first.map, first.per_score)?;
            contrast::element_size(contrast::blob_radius(&f.masked(first.map), w, h, &t)?)
        }
    };
    let cm = contrast::contrast_map::<T>(&f.score, w, h, f.color, size);
    let t = stats(&cm.map, cm.per_score)?;
    Some(LayerMap {
        map: f.masked(cm.map),
        median: t.median,
        threshold: t.threshold,
        map_per_score: cm.per_score,
        illumination: cm.illumination,
    })
}

/// A colour layer's score map and threshold `T = b + max(6σ, 0.2·(p − b))` (see the
/// module docs), or `None` when the peak is within 8σ of the background.
fn colour_map<T: Sample, const C: usize>(f: &LayerFrame<'_, T, C>) -> Option<LayerMap> {
    let mut tmp = f.inside_values(&f.score);
    let n = tmp.len();
    let median = kth(&mut tmp, n / 2);
    let peak = kth(&mut tmp, n.saturating_sub(20));
    for v in tmp.iter_mut() {
        *v = (*v - median).abs();
    }
    let mad = kth(&mut tmp, n / 2);
    let noise = (1.4826 * mad as f64).max(1.0);
    let (b, p) = (median as f64, peak as f64);
    if p - b <= 8.0 * noise {
        return None;
    }
    Some(LayerMap {
        map: f.masked(f.score.clone()),
        median,
        threshold: (b + (6.0 * noise).max(0.2 * (p - b))).ceil() as i32,
        map_per_score: 1.0,
        illumination: None,
    })
}

/// An 8-connected component of the map above the threshold.
#[derive(Clone, Copy)]
struct Comp {
    area: usize,
    sum: f64,
    sx: f64,
    sy: f64,
    peak: i32,
    /// Unweighted pixel moments Σx, Σy, Σx², Σy², Σxy (shape).
    shape: [f64; 5],
    /// A pixel on the image's outermost rows or columns: the blob may be a marker
    /// cut by the edge.
    at_edge: bool,
}

impl Comp {
    /// √(λ₁/λ₂) of the pixels' covariance: 1 for a disc, large for a line.
    fn elongation(&self) -> f64 {
        contrast::elongation(self.area, &self.shape)
    }

    /// The signal-weighted centroid, px.
    fn seed(&self) -> [f64; 2] {
        [self.sx / self.sum, self.sy / self.sum]
    }
}

/// The 8-connected components of `m.map` above its threshold (flood fill with an
/// explicit stack), and each pixel's component (index + 1; 0: none).
fn components(m: &LayerMap, w: usize, h: usize) -> (Vec<Comp>, Vec<u32>) {
    let (map, threshold) = (&m.map[..], m.threshold);
    let n = map.len();
    let mut label = vec![0u32; n];
    let mut comps = Vec::new();
    let mut stack = Vec::new();
    for start in 0..n {
        if label[start] != 0 || map[start] <= threshold {
            continue;
        }
        let id = comps.len() as u32 + 1;
        label[start] = id;
        stack.push(start);
        let mut c = Comp {
            area: 0,
            sum: 0.0,
            sx: 0.0,
            sy: 0.0,
            peak: 0,
            shape: [0.0; 5],
            at_edge: false,
        };
        while let Some(i) = stack.pop() {
            let (x, y) = (i % w, i / w);
            let s = (map[i] - m.median) as f64;
            c.area += 1;
            c.sum += s;
            c.sx += s * x as f64;
            c.sy += s * y as f64;
            c.peak = c.peak.max(map[i]);
            c.at_edge |= x == 0 || y == 0 || x + 1 == w || y + 1 == h;
            let (fx, fy) = (x as f64, y as f64);
            for (m, v) in c.shape.iter_mut().zip([fx, fy, fx * fx, fy * fy, fx * fy]) {
                *m += v;
            }
            for dy in -1i64..=1 {
                for dx in -1i64..=1 {
                    let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                    if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 {
                        continue;
                    }
                    let j = ny as usize * w + nx as usize;
                    if label[j] == 0 && map[j] > threshold {
                        label[j] = id;
                        stack.push(j);
                    }
                }
            }
        }
        comps.push(c);
    }
    (comps, label)
}

/// The marker radius measured from the blobs' areas, px (a layer without a grid).
fn measured_radius(comps: &[Comp], color: MarkerColor) -> f64 {
    let mut areas: Vec<usize> = comps.iter().map(|c| c.area).collect();
    areas.sort_unstable();
    let radius = |a: usize| (a as f64 / std::f64::consts::PI).sqrt();
    if color.is_brightness() {
        // The area of the blob holding the median pixel above the threshold: noise
        // specks and dust, however many, hold few pixels.
        let total: usize = areas.iter().sum();
        let mut acc = 0;
        areas
            .iter()
            .find(|&&a| {
                acc += a;
                2 * acc >= total
            })
            .map_or(1.0, |&a| radius(a))
    } else {
        // Median blob size, ignoring the smallest half (noise specks).
        let big = &areas[areas.len() / 2..];
        big.get(big.len() / 2).map_or(1.0, |&a| radius(a))
    }
}

/// Whether a first-pass blob is a marker of radius `radius_px`. Brightness layers see
/// more than markers (dust, scratches, reflections of similar contrast on real gels):
/// a blob must hold 40 % of a marker's area and be round (elongation ≤
/// MAX_ELONGATION; a disc seen obliquely stays below it). A blob at the image's edge
/// may be a marker cut by it: 25 % of the area and an elongation of 3 suffice there (a
/// disc cut through its centre has 1.9). Colour layers keep the plain size check (a
/// fifth of the area).
fn is_marker(c: &Comp, color: MarkerColor, radius_px: f64) -> bool {
    if c.sum <= 0.0 {
        return false;
    }
    let disc_area = std::f64::consts::PI * radius_px * radius_px;
    if !color.is_brightness() {
        return c.area as f64 >= (0.2 * disc_area).max(3.0);
    }
    let (area, elongation) = if c.at_edge {
        (0.25, 3.0)
    } else {
        (0.4, MAX_ELONGATION)
    };
    c.area as f64 >= (area * disc_area).max(3.0) && c.elongation() <= elongation
}

/// Whether [`keep_markers`] keeps a blob, and by which size.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kept {
    No,
    /// Large enough for the layer's marker radius.
    ByLayer,
    /// Large enough for its neighbours' size only.
    ByNeighbours,
}

/// How many nearest markers set a blob's local expected size ([`keep_markers`]).
const LOCAL_NEIGHBOURS: usize = 6;

/// Which components are markers. First by the layer's radius ([`is_marker`]); then a
/// blob that fails only for its size is judged against its neighbours instead: the
/// layer's radius scaled by the median size (√(area/π)) of its [`LOCAL_NEIGHBOURS`]
/// nearest markers over the median size of all of them (never above 1). The far rows
/// of a sensor seen in strong perspective hold dots well below the layer's median
/// (GelSlim-like, 5 → 2.1 px) but close to their neighbours', while a speck among big
/// markers is still judged against those. Repeated while it finds more, so a smooth
/// gradient is followed row by row; each round judges against the same markers, so
/// the result does not depend on the blobs' order.
fn keep_markers(comps: &[Comp], color: MarkerColor, radius_px: f64) -> Vec<Kept> {
    let mut kept: Vec<Kept> = comps
        .iter()
        .map(|c| {
            if is_marker(c, color, radius_px) {
                Kept::ByLayer
            } else {
                Kept::No
            }
        })
        .collect();
    let size = |c: &Comp| (c.area as f64 / std::f64::consts::PI).sqrt();
    let mut markers: Vec<([f64; 2], f64)> = comps
        .iter()
        .zip(&kept)
        .filter(|(_, k)| **k == Kept::ByLayer)
        .map(|(c, _)| (c.seed(), size(c)))
        .collect();
    if markers.len() < LOCAL_NEIGHBOURS {
        return kept;
    }
    let mut sizes: Vec<f64> = markers.iter().map(|m| m.1).collect();
    sizes.sort_by(f64::total_cmp);
    let typical = sizes[sizes.len() / 2];
    // Blobs that pass every check but the size (a radius of 0 leaves the 3 px floor).
    let mut candidates: Vec<usize> = (0..comps.len())
        .filter(|&i| kept[i] == Kept::No && is_marker(&comps[i], color, 0.0))
        .collect();
    loop {
        let added: Vec<usize> = candidates
            .iter()
            .copied()
            .filter(|&i| {
                let local = local_size(comps[i].seed(), &markers);
                is_marker(&comps[i], color, radius_px * (local / typical).min(1.0))
            })
            .collect();
        if added.is_empty() {
            return kept;
        }
        for &i in &added {
            kept[i] = Kept::ByNeighbours;
            markers.push((comps[i].seed(), size(&comps[i])));
        }
        candidates.retain(|&i| kept[i] == Kept::No);
    }
}

/// The median size of the [`LOCAL_NEIGHBOURS`] markers (centre, size) nearest `p`.
fn local_size(p: [f64; 2], markers: &[([f64; 2], f64)]) -> f64 {
    let mut by_distance: Vec<(f64, f64)> = markers
        .iter()
        .map(|(c, s)| ((c[0] - p[0]).hypot(c[1] - p[1]), *s))
        .collect();
    let k = LOCAL_NEIGHBOURS.min(by_distance.len());
    if k < by_distance.len() {
        by_distance.select_nth_unstable_by(k, |a, b| a.0.total_cmp(&b.0));
    }
    let mut near: Vec<f64> = by_distance[..k].iter().map(|n| n.1).collect();
    near.sort_by(f64::total_cmp);
    near[k / 2]
}

/// A brightness layer's second pass (`contrast::faint_spots`): faint markers outside
/// the kept first-pass blobs (`kept[component]`), as components without shape.
fn faint_second_pass<T: Sample, const C: usize>(
    f: &LayerFrame<'_, T, C>,
    m: &LayerMap,
    label: &[u32],
    kept: &[bool],
    radius_px: f64,
) -> Vec<Comp> {
    let taken: Vec<bool> = label
        .iter()
        .map(|&l| l > 0 && kept[l as usize - 1])
        .collect();
    let structure: Vec<bool> = label.iter().map(|&l| l > 0).collect();
    let input = contrast::FaintInput {
        map: &m.map,
        score: &f.score,
        illumination: m.illumination.as_deref(),
        width: f.img.width,
        height: f.img.height,
        median: m.median,
        taken: &taken,
        structure: &structure,
        radius_px,
        min_contrast: contrast::min_contrast::<T>(f.color),
    };
    contrast::faint_spots(&input, MAX_ELONGATION)
        .into_iter()
        .map(|s| Comp {
            area: s.area,
            sum: s.sum,
            sx: s.sx,
            sy: s.sy,
            peak: s.peak,
            shape: [0.0; 5],
            at_edge: false,
        })
        .collect()
}

/// The markers' measured extent, px: where the score falls to 5 % of the blob's peak
/// above background, the median over (up to 200) blobs and the four axis directions,
/// at least `radius_px`.
fn marker_extent(m: &LayerMap, w: usize, h: usize, comps: &[Comp], radius_px: f64) -> f64 {
    let b = m.median as f64;
    let mut extents = Vec::new();
    for c in comps.iter().take(200) {
        let s = c.seed();
        let level = b + 0.05 * (c.peak as f64 - b);
        let (x0, y0) = (s[0].round() as i64, s[1].round() as i64);
        for (dx, dy) in [(1i64, 0i64), (-1, 0), (0, 1), (0, -1)] {
            let mut r = 0i64;
            loop {
                let (x, y) = (x0 + dx * (r + 1), y0 + dy * (r + 1));
                if x < 0 || y < 0 || x >= w as i64 || y >= h as i64 || r > 200 {
                    break;
                }
                if (m.map[y as usize * w + x as usize] as f64) <= level {
                    break;
                }
                r += 1;
            }
            extents.push(r as f64 + 0.5);
        }
    }
    extents.sort_by(f64::total_cmp);
    extents[extents.len() / 2].max(radius_px)
}

/// The median distance from each seed to its nearest neighbour, px (infinite for one).
fn median_spacing(seeds: &[[f64; 2]]) -> f64 {
    let mut nn: Vec<f64> = seeds
        .iter()
        .enumerate()
        .map(|(i, a)| {
            seeds
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, b)| ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt())
                .fold(f64::INFINITY, f64::min)
        })
        .collect();
    nn.sort_by(f64::total_cmp);
    nn[nn.len() / 2]
}

/// The window's aperture radius, px: the extent plus 1.5 px, capped so the background
/// ring (aperture + 3 px) stays clear of the neighbour's extent, at least the marker's
/// radius and 2 px (or the configured radius).
fn aperture_radius(config: &DetectConfig, extent: f64, spacing: f64, radius_px: f64) -> f64 {
    config.aperture_radius_px.unwrap_or_else(|| {
        let want = extent + 1.5;
        let cap = spacing - extent - 4.0;
        want.min(cap).max(radius_px.max(2.0))
    })
}

/// The aperture radius and the median spacing, px, from the blobs in `basis`.
fn layer_aperture(
    config: &DetectConfig,
    m: &LayerMap,
    (w, h): (usize, usize),
    basis: &[Comp],
    radius_px: f64,
) -> (f64, f64) {
    let extent = marker_extent(m, w, h, basis, radius_px);
    let seeds: Vec<[f64; 2]> = basis.iter().map(Comp::seed).collect();
    let spacing = median_spacing(&seeds);
    (aperture_radius(config, extent, spacing, radius_px), spacing)
}

/// The window's measurement from `seed`. Brightness layers (real frames, markers up to
/// the image's edge): a window cut by the edge is measured on its pixels inside the
/// image when the dot is inside (`window::dot_inside`), as the tracker measures it.
fn locate_seed<T: Sample, const C: usize>(
    f: &LayerFrame<'_, T, C>,
    window: &Window,
    seed: [f64; 2],
    radius_px: f64,
) -> Located {
    if !f.color.is_brightness() {
        return window.locate::<T, C>(f.img, seed, 20, false);
    }
    match window.locate_clipped::<T, C>(f.img, seed, 20, false) {
        Located::Found {
            centroid_px,
            clipped: true,
            ..
        } if !dot_inside(centroid_px, radius_px, f.img.width, f.img.height) => Located::OutOfImage,
        other => other,
    }
}

/// A brightness marker at the image border, its window cut by the edge: found (it is
/// there, and `sensor init` counts it near the border) at its blob's centroid, but
/// never measured — the tracker reports it lost while its window does not fit. Its
/// reference signal is the blob's contrast in score units (the above-threshold core
/// only: an underestimate of a window's signal, used only if it moves inside); its
/// background the median linear score on the window's ring, where the ring lies in
/// the image. `None` outside the ROI.
fn border_blob<T: Sample, const C: usize>(
    f: &LayerFrame<'_, T, C>,
    m: &LayerMap,
    window: &Window,
    comp: &Comp,
    score_median: f64,
) -> Option<Blob> {
    let s = comp.seed();
    if f.roi.is_some_and(|r| !r.contains(s)) {
        return None;
    }
    let (w, h) = (f.img.width, f.img.height);
    let ring = window.ring_radius_px();
    let mut level: Vec<i32> = (0..64)
        .filter_map(|k| {
            let a = k as f64 * std::f64::consts::TAU / 64.0;
            let (x, y) = (
                (s[0] + ring * a.cos()).round(),
                (s[1] + ring * a.sin()).round(),
            );
            (x >= 0.0 && y >= 0.0 && x < w as f64 && y < h as f64)
                .then(|| f.score[y as usize * w + x as usize])
        })
        .collect();
    let background = if level.is_empty() {
        score_median
    } else {
        let half = level.len() / 2;
        kth(&mut level, half) as f64
    } - score_bias::<T>(&f.weights) as f64;
    Some(Blob {
        centroid_px: s,
        signal: comp.sum / m.map_per_score,
        peak: (comp.peak - m.median) as f64 / m.map_per_score,
        background,
        slope: [0.0; 2],
    })
}

/// Refines every component by the iterated window centroid (see the module docs), and
/// lists the components whose window ran off them. From `check_from` on, components
/// are not the first pass's blobs (second-pass spots, or blobs kept for their
/// neighbours' size); one whose window ran off it was pulled by its neighbours (an
/// aperture sized for larger markers): not measurable, not a marker.
fn refine_blobs<T: Sample, const C: usize>(
    f: &LayerFrame<'_, T, C>,
    m: &LayerMap,
    window: &Window,
    comps: &[Comp],
    check_from: usize,
    radius_px: f64,
    score_median: f64,
) -> (Vec<Blob>, Vec<usize>) {
    let mut blobs: Vec<Blob> = Vec::with_capacity(comps.len());
    let mut ran_off = Vec::new();
    for (k, comp) in comps.iter().enumerate() {
        let s = comp.seed();
        let located = locate_seed(f, window, s, radius_px);
        if k >= check_from {
            if let Located::Found { centroid_px, .. } = located {
                let own = (comp.area as f64 / std::f64::consts::PI).sqrt();
                if (centroid_px[0] - s[0]).hypot(centroid_px[1] - s[1]) > (0.5 * own).max(1.0) {
                    ran_off.push(k);
                    continue;
                }
            }
        }
        if f.color.is_brightness() && matches!(located, Located::OutOfImage) {
            blobs.extend(border_blob(f, m, window, comp, score_median));
            continue;
        }
        if let Located::Found {
            centroid_px,
            m0,
            background,
            slope,
            ..
        } = located
        {
            if f.roi.is_some_and(|r| !r.contains(centroid_px)) {
                continue;
            }
            let c = [centroid_px[0].round() as i32, centroid_px[1].round() as i32];
            let pk = window.peak::<T, C>(f.img, c[0], c[1]).unwrap_or(0);
            // Above the layer's background: the image's median score for colour
            // layers, the window's own ring level for brightness layers (whose
            // background varies over the image).
            let base = if f.color.is_brightness() {
                background + score_bias::<T>(&f.weights) as f64
            } else {
                m.median as f64
            };
            blobs.push(Blob {
                centroid_px,
                signal: m0,
                peak: (pk as f64 - base).max(1.0).round(),
                background,
                slope,
            });
        }
    }
    (blobs, ran_off)
}

/// Fragments of one marker converge to the same centroid (within `radius_px`): keeps
/// the strongest.
fn merge_fragments(mut blobs: Vec<Blob>, radius_px: f64) -> Vec<Blob> {
    blobs.sort_by(|a, b| b.signal.total_cmp(&a.signal));
    let mut kept: Vec<Blob> = Vec::with_capacity(blobs.len());
    for b in blobs {
        let dup = kept.iter().any(|k| {
            (k.centroid_px[0] - b.centroid_px[0]).hypot(k.centroid_px[1] - b.centroid_px[1])
                < radius_px
        });
        if !dup {
            kept.push(b);
        }
    }
    kept
}

/// One layer's markers (see the module docs): the map and threshold, the blobs above
/// it kept as markers, a brightness layer's faint second pass, the aperture from the
/// first pass's blobs, and the window centroid of each.
fn detect_layer<T: Sample, const C: usize>(
    img: Raw<'_, T, C>,
    color: MarkerColor,
    weights: [i32; 3],
    expected_radius_px: Option<f64>,
    roi: Option<&Roi>,
    config: &DetectConfig,
) -> LayerBlobs {
    let (w, h) = (img.width, img.height);
    let f = LayerFrame {
        img,
        color,
        weights,
        roi,
        score: img
            .data
            .chunks_exact(C)
            .map(|px| score::<T, C>(px, &weights))
            .collect(),
        inside: roi.map(|r| {
            (0..w * h)
                .map(|i| r.contains([(i % w) as f64, (i / w) as f64]))
                .collect()
        }),
    };
    let mut score_values = f.inside_values(&f.score);
    if score_values.is_empty() {
        let aperture = config.aperture_radius_px.unwrap_or(1.0);
        return LayerBlobs::none(expected_radius_px.unwrap_or(1.0), aperture, 0.0);
    }
    let half = score_values.len() / 2;
    let score_median = kth(&mut score_values, half) as f64;
    let empty = |r: f64| {
        let aperture = config.aperture_radius_px.unwrap_or(r + 1.5);
        LayerBlobs::none(r, aperture, score_median)
    };
    let map = if color.is_brightness() {
        brightness_map(&f, expected_radius_px)
    } else {
        colour_map(&f)
    };
    let Some(map) = map else {
        return empty(expected_radius_px.unwrap_or(1.0));
    };
    let (comps, label) = components(&map, w, h);
    let radius_px = expected_radius_px.unwrap_or_else(|| measured_radius(&comps, color));
    let keep = keep_markers(&comps, color, radius_px);
    let mut kept: Vec<bool> = keep.iter().map(|k| *k != Kept::No).collect();
    let pick = |which: Kept| -> (Vec<usize>, Vec<Comp>) {
        (0..comps.len())
            .filter(|&i| keep[i] == which)
            .map(|i| (i, comps[i]))
            .unzip()
    };
    let (_, mut first) = pick(Kept::ByLayer);
    // The blobs the layer's radius keeps set the aperture and spacing: those kept for
    // their neighbours' size, and the second pass's, add markers without moving
    // theirs. One of the former whose window runs off it is left to the second pass.
    let first_pass = first.len();
    let sized = (first_pass > 0).then(|| layer_aperture(config, &map, (w, h), &first, radius_px));
    let mut blobs = Vec::new();
    if let Some((aperture, _)) = sized {
        let (index, local) = pick(Kept::ByNeighbours);
        let window = Window::new(aperture, weights);
        let (found, ran_off) = refine_blobs(&f, &map, &window, &local, 0, radius_px, score_median);
        blobs = found;
        ran_off.into_iter().for_each(|k| kept[index[k]] = false);
    }
    if color.is_brightness() {
        first.extend(faint_second_pass(&f, &map, &label, &kept, radius_px));
    }
    if first.is_empty() {
        return empty(radius_px);
    }
    let (aperture, spacing) =
        sized.unwrap_or_else(|| layer_aperture(config, &map, (w, h), &first, radius_px));
    let window = Window::new(aperture, weights);
    let (found, _) = refine_blobs(
        &f,
        &map,
        &window,
        &first,
        first_pass,
        radius_px,
        score_median,
    );
    blobs.extend(found);
    LayerBlobs {
        blobs: merge_fragments(blobs, radius_px),
        marker_radius_px: radius_px,
        aperture_radius_px: aperture,
        spacing_px: spacing,
        background_score: score_median,
    }
}
