//! Background-corrected contrast for brightness layers (`dark`, `bright`): where a
//! marker stands out from the *local* illumination, so colour gradients, vignetting,
//! shading and stripes neither hide markers nor make blobs of their own.
//!
//! The layer's score `s` (window.rs: `R + G + B` for bright, `bias − (R + G + B)` for
//! dark, so a marker is a positive bump in both) is compared with a morphological
//! **opening** `o`: the larger of the grey openings (erosion then dilation) by a
//! horizontal and by a vertical line of `L` px. A marker is compact: no line of `L`
//! px fits inside it, so both openings remove it and follow the background below;
//! the top-hat `s − o` is the markers' contrast over a background of any large-scale
//! shape. Elongated structures — stripes, the gel's edge, scratches — hold a line of
//! one of the two directions and stay in the background (a square element, which fits
//! in neither, would leave them all in the contrast: on the striped GelSight frame the
//! stripes then rise to 60 % of the dots' contrast). `L` is set from the marker
//! diameter `D` (the sensor file's `diameter_mm / mm_per_px`, or measured by a first
//! pass with a long element): `L = 2·⌈D⌉ + 1`, longer than a marker with a soft edge,
//! short enough to follow the illumination between markers.
//!
//! * **bright**: the contrast is the top-hat itself (score units): pins on a black skin
//!   have no illumination to be relative to.
//! * **dark**: the contrast is relative to the illumination, `(I − Y) / I` in 1/1024,
//!   with `Y = R + G + B` and `I = closing(Y) = bias − o` the lit gel's level around
//!   the marker (floored at 1/16 of full scale so black regions do not amplify noise):
//!   a dark dot under a dim LED contrasts as much as one under a bright LED.
//!
//! Erosion and dilation along a line are computed with a monotonic queue, O(1) per
//! pixel whatever `L` is; windows are clipped at the image border. The tracker's per-window centroid needs none of this: its background plane,
//! fitted on a ring around each marker, removes the local illumination already (see
//! `window.rs`); the contrast map serves the reference detection (thresholds, blob
//! extents) where one threshold must hold over the whole image.
//!
//! One threshold cannot serve faint and bright markers at once: [`faint_spots`] is the
//! reference detection's second pass over what the first left, with the noise and
//! baseline measured per 32 px tile and each spot judged by its own peak and
//! half-height area (the floors it gives: docs/real-sensors.md, "Faint and small
//! markers").

use std::collections::VecDeque;

use super::window::{score_bias, Sample};
use crate::sensor::MarkerColor;

/// Relative contrast unit of dark layers: 1024 = the marker is black.
pub(crate) const DARK_UNIT: i32 = 1024;

/// Side of the square structuring element for markers of radius `radius_px`: odd,
/// twice the diameter plus one, at least 5 px.
pub(crate) fn element_size(radius_px: f64) -> usize {
    let d = (2.0 * radius_px.max(1.0)).ceil() as usize;
    (2 * d + 1).max(5)
}

/// The element of the first pass when the marker size is unknown: an eighth of the
/// image's shorter side (odd, at least 15 px): larger than the markers of any usable
/// frame (a frame whose markers are wider than that shows a handful of them).
pub(crate) fn default_element_size(width: usize, height: usize) -> usize {
    (width.min(height) / 8).max(15) | 1
}

/// A brightness layer's contrast map (see [`contrast_map`]).
pub(crate) struct ContrastMap {
    /// The contrast, row-major, map units.
    pub map: Vec<i32>,
    /// Map units per score unit at the median illumination (1 for bright; for dark
    /// `DARK_UNIT / I`), to express the score's pixel noise in map units.
    pub per_score: f64,
    /// Dark layers: the illumination `I` per pixel (score units), whose local level
    /// scales the local noise ([`faint_spots`]); `None` for bright layers.
    pub illumination: Option<Vec<i32>>,
}

/// The contrast map of a brightness layer (see the module docs) from its clamped
/// score `score` (row-major, `width × height`), with a line element of `size` px.
pub(crate) fn contrast_map<T: Sample>(
    score: &[i32],
    width: usize,
    height: usize,
    color: MarkerColor,
    size: usize,
) -> ContrastMap {
    let opening = opening(score, width, height, size / 2);
    match color {
        MarkerColor::Dark => {
            let bias = score_bias::<T>(&[-1, -1, -1]);
            let floor = (3 * T::MAX / 16).max(1);
            let illumination = |o: i32| (bias - o).max(floor);
            let map = score
                .iter()
                .zip(&opening)
                .map(|(&s, &o)| ((s - o) as i64 * DARK_UNIT as i64 / illumination(o) as i64) as i32)
                .collect();
            let lit: Vec<i32> = opening.iter().map(|&o| illumination(o)).collect();
            let mut tmp = lit.clone();
            let n = tmp.len();
            let median = if n == 0 {
                floor
            } else {
                *tmp.select_nth_unstable(n / 2).1
            };
            ContrastMap {
                map,
                per_score: DARK_UNIT as f64 / median as f64,
                illumination: Some(lit),
            }
        }
        _ => ContrastMap {
            map: score.iter().zip(&opening).map(|(&s, &o)| s - o).collect(),
            per_score: 1.0,
            illumination: None,
        },
    }
}

/// The background under compact bumps: the larger of the grey openings of `v` by a
/// horizontal and by a vertical line of `2r + 1` px (see the module docs).
pub(crate) fn opening(v: &[i32], width: usize, height: usize, r: usize) -> Vec<i32> {
    let mut line = LineOpening::new(r, width.max(height));
    let mut h = vec![0i32; v.len()];
    for y in 0..height {
        let row = y * width..(y + 1) * width;
        line.open(&v[row.clone()], &mut h[row]);
    }
    let mut col = vec![0i32; height];
    let mut out = vec![0i32; height];
    for x in 0..width {
        for (y, c) in col.iter_mut().enumerate() {
            *c = v[y * width + x];
        }
        line.open(&col, &mut out);
        for (y, &c) in out.iter().enumerate() {
            let o = &mut h[y * width + x];
            *o = (*o).max(c);
        }
    }
    h
}

/// The grey opening of a line by a segment of `2r + 1` px, windows clipped at the
/// ends. (Extending the line by copies of its end values instead would make a ramp
/// running into the border exactly its own opening, but would also extend a marker cut
/// by the border beyond it, and a segment would then fit inside: the marker would
/// vanish from the contrast. Clipping under-estimates a ramp's opening within `r` px of
/// the border by at most `r` × its slope: 2.5 % of the illumination for a 30 % fall-off
/// over 160 px and `r` = 13 px, below a quarter of the least marker contrast.)
struct LineOpening {
    r: usize,
    eroded: Vec<i32>,
    queue: VecDeque<usize>,
}

impl LineOpening {
    fn new(r: usize, max_len: usize) -> Self {
        LineOpening {
            r,
            eroded: vec![0; max_len],
            queue: VecDeque::new(),
        }
    }

    fn open(&mut self, src: &[i32], out: &mut [i32]) {
        let n = src.len();
        sliding(src, &mut self.eroded[..n], self.r, true, &mut self.queue);
        sliding(&self.eroded[..n], out, self.r, false, &mut self.queue);
    }
}

/// Separable min (`min = true`) or max filter over a `(2r+1)²` square, clipped at
/// the border (tests: checks [`sliding`] against brute force).
#[cfg(test)]
fn filter2(v: &[i32], width: usize, height: usize, r: usize, min: bool) -> Vec<i32> {
    let mut rows = vec![0i32; v.len()];
    let mut queue = VecDeque::new();
    for y in 0..height {
        let line = &v[y * width..(y + 1) * width];
        sliding(
            line,
            &mut rows[y * width..(y + 1) * width],
            r,
            min,
            &mut queue,
        );
    }
    let mut out = vec![0i32; v.len()];
    let mut col = vec![0i32; height];
    let mut res = vec![0i32; height];
    for x in 0..width {
        for (y, c) in col.iter_mut().enumerate() {
            *c = rows[y * width + x];
        }
        sliding(&col, &mut res, r, min, &mut queue);
        for (y, &c) in res.iter().enumerate() {
            out[y * width + x] = c;
        }
    }
    out
}

/// `out[i] = min/max(src[i − r ..= i + r])` (clipped), by a monotonic queue of indices.
fn sliding(src: &[i32], out: &mut [i32], r: usize, min: bool, queue: &mut VecDeque<usize>) {
    queue.clear();
    let n = src.len();
    let better = |a: i32, b: i32| if min { a <= b } else { a >= b };
    let mut next = 0;
    for (i, o) in out.iter_mut().enumerate() {
        // Admit every index up to i + r.
        while next < n && next <= i + r {
            while let Some(&back) = queue.back() {
                if better(src[next], src[back]) {
                    queue.pop_back();
                } else {
                    break;
                }
            }
            queue.push_back(next);
            next += 1;
        }
        // Drop indices below i − r.
        while let Some(&front) = queue.front() {
            if front + r < i {
                queue.pop_front();
            } else {
                break;
            }
        }
        *o = queue.front().map_or(0, |&f| src[f]);
    }
}

/// The typical blob radius in a contrast map, px: 8-connected components above the
/// threshold `t.threshold`, the area of the component that holds the median pixel
/// above it (an area-weighted median: noise specks, however many, hold few pixels),
/// as a disc. `None` when nothing stands out.
pub(crate) fn blob_radius(map: &[i32], width: usize, height: usize, t: &Threshold) -> Option<f64> {
    let threshold = t.threshold;
    let mut label = vec![false; map.len()];
    let mut stack = Vec::new();
    let mut areas = Vec::new();
    for start in 0..map.len() {
        if label[start] || map[start] <= threshold {
            continue;
        }
        label[start] = true;
        stack.push(start);
        let mut area = 0usize;
        while let Some(i) = stack.pop() {
            area += 1;
            let (x, y) = ((i % width) as i64, (i / width) as i64);
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (nx, ny) = (x + dx, y + dy);
                    if nx < 0 || ny < 0 || nx >= width as i64 || ny >= height as i64 {
                        continue;
                    }
                    let j = ny as usize * width + nx as usize;
                    if !label[j] && map[j] > threshold {
                        label[j] = true;
                        stack.push(j);
                    }
                }
            }
        }
        areas.push(area);
    }
    areas.sort_unstable();
    let total: usize = areas.iter().sum();
    let mut acc = 0;
    areas
        .iter()
        .find(|&&a| {
            acc += a;
            2 * acc >= total
        })
        .map(|&a| (a as f64 / std::f64::consts::PI).sqrt())
}

/// Robust statistics of a brightness layer's contrast map and the threshold blobs
/// are found above (see [`threshold`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Threshold {
    /// Median of the map (the background's contrast, ~0).
    pub median: i32,
    /// The 20th-largest value (immune to a few hot pixels).
    pub peak: i32,
    /// Noise σ, map units.
    pub noise: f64,
    /// Blobs are the pixels above this.
    pub threshold: i32,
}

/// The least contrast a marker of a brightness layer must have, map units: a dark
/// marker 10 % darker than its illumination; a bright marker 5 % of full scale
/// (`3 × max`) above its background. Below that, a "marker" is gel texture, dust or
/// noise: a frame without markers gives none.
pub(crate) fn min_contrast<T: Sample>(color: MarkerColor) -> i32 {
    match color {
        MarkerColor::Dark => DARK_UNIT / 10,
        _ => 3 * T::MAX / 20,
    }
}

/// The threshold on a brightness layer's map `map` (values of `inside` pixels only,
/// see `detect.rs`): median `b`, noise `σ` = the larger of the map's MAD·1.4826 and the
/// pixel noise of the score (`score_noise`, in map units), peak `p` = 20th largest;
/// `T = b + max(6σ, 0.2·(p − b), c/2)` with `c` = [`min_contrast`]. `None` when the
/// peak does not rise above `max(8σ, c)`: nothing stands out. (The map is 0 over most
/// of the background, where its MAD says nothing about the noise: hence the score's.)
pub(crate) fn threshold(values: &[i32], score_noise: f64, min_contrast: i32) -> Option<Threshold> {
    if values.is_empty() {
        return None;
    }
    let mut tmp = values.to_vec();
    let n = tmp.len();
    let median = *tmp.select_nth_unstable(n / 2).1;
    let peak = *tmp.select_nth_unstable(n.saturating_sub(20)).1;
    for v in tmp.iter_mut() {
        *v = (*v - median).abs();
    }
    let mad = *tmp.select_nth_unstable(n / 2).1;
    let noise = (1.4826 * mad as f64).max(score_noise).max(1.0);
    let (b, p, c) = (median as f64, peak as f64, min_contrast as f64);
    if p - b <= (8.0 * noise).max(c) {
        return None;
    }
    Some(Threshold {
        median,
        peak,
        noise,
        threshold: (b + (6.0 * noise).max(0.2 * (p - b)).max(0.5 * c)).ceil() as i32,
    })
}

/// Pixel noise σ of a score image, from horizontal neighbour differences
/// (`1.4826 · median|s(x+1) − s(x)| / √2`) over the pixels `inside` selects: smooth
/// illumination and markers (few pixels) barely move the median difference.
pub(crate) fn score_noise(score: &[i32], width: usize, inside: Option<&[bool]>) -> f64 {
    let mut d: Vec<i32> = Vec::with_capacity(score.len());
    for (i, pair) in score.windows(2).enumerate() {
        if (i + 1) % width == 0 || inside.is_some_and(|m| !(m[i] && m[i + 1])) {
            continue;
        }
        d.push((pair[1] - pair[0]).abs());
    }
    if d.is_empty() {
        return 0.0;
    }
    let n = d.len();
    let med = *d.select_nth_unstable(n / 2).1;
    1.4826 * med as f64 / std::f64::consts::SQRT_2
}

/// Side of the square tiles the second pass measures its local noise and baseline in,
/// px: large enough for a robust median (hundreds of samples between the markers),
/// small enough to follow the noise as it changes with the illumination.
const TILE: usize = 32;

/// How far above its tile's baseline the smoothed contrast of a second-pass spot must
/// peak, in local noise σ of the smoothed score: a Gaussian noise bump reaches ~4.5 σ
/// once in a 640 × 480 frame's 34 000 independent 3 × 3 boxes.
const FAINT_SIGMA: f64 = 8.0;

/// The least half-height area of a second-pass spot, in discs of the expected marker
/// radius `r` (`π r²`), never less than 3 px. A faint marker's half-height area is
/// its disc (0.85–1 on the rendered pins of `tests/vision_faint.rs`); on the real
/// striped GelSight frame the specks and stripe crossings that pass every other test
/// hold at most 0.56 of a dot's disc, and on the FOTS frame the slivers of dots cut by
/// the image edge 0.18. (So a dot smaller than 0.77 r, the far rows of a sensor seen
/// in strong perspective, is found only by the first pass: 0.63 r.)
const LEAST_AREA: f64 = 0.6;

/// What the second, low-threshold pass ([`faint_spots`]) reads.
pub(crate) struct FaintInput<'a> {
    /// The layer's contrast map, `i32::MIN` outside the ROI.
    pub map: &'a [i32],
    /// The layer's score (same pixels), for the noise.
    pub score: &'a [i32],
    /// Dark layers: the illumination per pixel ([`ContrastMap::illumination`]).
    pub illumination: Option<&'a [i32]>,
    pub width: usize,
    pub height: usize,
    /// The map's median (the first pass's `b`).
    pub median: i32,
    /// Pixels of the blobs the first pass kept: a spot reaching one is its flank.
    pub taken: &'a [bool],
    /// Pixels above the first pass's threshold (kept or not): markers, left out of the
    /// local noise and baseline.
    pub structure: &'a [bool],
    /// Expected marker radius, px.
    pub radius_px: f64,
    /// [`min_contrast`] of the layer.
    pub min_contrast: i32,
}

/// A marker found by the second pass: the moments of its half-maximum pixels,
/// weighted by their smoothed contrast above the local baseline.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct FaintSpot {
    /// Half-maximum pixels.
    pub area: usize,
    /// Σ weights, Σ weight·x, Σ weight·y (map units, px).
    pub sum: f64,
    pub sx: f64,
    pub sy: f64,
    /// Largest map value of the spot (raw, not smoothed).
    pub peak: i32,
}

/// Local statistics of the smoothed map, per [`TILE`]: baseline (median of the
/// smoothed map) and noise σ of the smoothed score (map units).
struct Tiles {
    nx: usize,
    baseline: Vec<f64>,
    sigma: Vec<f64>,
}

impl Tiles {
    fn at(&self, i: usize, width: usize) -> (f64, f64) {
        let t = (i / width / TILE) * self.nx + (i % width) / TILE;
        (self.baseline[t], self.sigma[t])
    }
}

/// The 3 × 3 box mean of `v` over the pixels `valid` selects (NaN where none is).
fn box_mean(v: &[i32], valid: &[bool], width: usize, height: usize) -> Vec<f32> {
    let mut out = vec![f32::NAN; v.len()];
    for y in 0..height {
        for x in 0..width {
            if !valid[y * width + x] {
                continue;
            }
            let (mut sum, mut n) = (0i64, 0u32);
            for yy in y.saturating_sub(1)..(y + 2).min(height) {
                for xx in x.saturating_sub(1)..(x + 2).min(width) {
                    let j = yy * width + xx;
                    if valid[j] {
                        sum += v[j] as i64;
                        n += 1;
                    }
                }
            }
            out[y * width + x] = sum as f32 / n as f32;
        }
    }
    out
}

/// `mask` grown by a square of `2r + 1` px.
fn dilate(mask: &[bool], width: usize, height: usize, r: usize) -> Vec<bool> {
    let v: Vec<i32> = mask.iter().map(|&m| m as i32).collect();
    let mut rows = vec![0i32; v.len()];
    let mut queue = VecDeque::new();
    for y in 0..height {
        let line = y * width..(y + 1) * width;
        sliding(&v[line.clone()], &mut rows[line], r, false, &mut queue);
    }
    let (mut col, mut res) = (vec![0i32; height], vec![0i32; height]);
    let mut out = vec![false; v.len()];
    for x in 0..width {
        for (y, c) in col.iter_mut().enumerate() {
            *c = rows[y * width + x];
        }
        sliding(&col, &mut res, r, false, &mut queue);
        for (y, &c) in res.iter().enumerate() {
            out[y * width + x] = c > 0;
        }
    }
    out
}

/// The median of `v` (reorders it); `None` when empty.
fn median_f32(v: &mut [f32]) -> Option<f64> {
    let n = v.len();
    (n > 0).then(|| *v.select_nth_unstable_by(n / 2, f32::total_cmp).1 as f64)
}

/// Baseline and noise of the smoothed map per tile, over the pixels `quiet` selects
/// (away from the first pass's markers, whose edges would dominate a dense lattice's
/// statistics). The noise is that of the smoothed *score* — `1.4826 · median|B(x+3) −
/// B(x)| / √2`, lag 3 so the two boxes share no pixel: right for white noise and for
/// noise correlated between neighbours (demosaicing, compression), which a lag-1
/// difference underestimates — times the tile's map units per score unit (dark:
/// `DARK_UNIT / I` at the tile's median illumination, as the first pass scales its
/// global noise). Tiles with too few quiet samples take the frame's values.
fn tile_stats(
    input: &FaintInput<'_>,
    quiet: &[bool],
    smooth_map: &[f32],
    smooth_score: &[f32],
) -> Tiles {
    let (w, h) = (input.width, input.height);
    let (nx, ny) = (w.div_ceil(TILE), h.div_ceil(TILE));
    let stats = |xs: std::ops::Range<usize>, ys: std::ops::Range<usize>| {
        let (mut base, mut diff, mut lit) = (Vec::new(), Vec::new(), Vec::new());
        for y in ys {
            for x in xs.clone() {
                let i = y * w + x;
                if smooth_map[i].is_nan() || !quiet[i] {
                    continue;
                }
                base.push(smooth_map[i]);
                if let Some(l) = input.illumination {
                    lit.push(l[i] as f32);
                }
                if x + 3 < w && quiet[i + 3] && !smooth_map[i + 3].is_nan() {
                    diff.push((smooth_score[i + 3] - smooth_score[i]).abs());
                }
            }
        }
        let scale = match input.illumination {
            Some(_) => median_f32(&mut lit).map(|l| DARK_UNIT as f64 / l.max(1.0)),
            None => Some(1.0),
        };
        let enough = diff.len() >= 64;
        let sigma = median_f32(&mut diff)
            .zip(scale)
            .map(|(d, k)| (1.4826 * d / std::f64::consts::SQRT_2).max(1.0 / 3.0) * k);
        (enough, median_f32(&mut base), sigma)
    };
    let (_, frame_base, frame_sigma) = stats(0..w, 0..h);
    let (frame_base, frame_sigma) = (
        frame_base.unwrap_or(input.median as f64),
        frame_sigma.unwrap_or(1.0),
    );
    let mut tiles = Tiles {
        nx,
        baseline: Vec::with_capacity(nx * ny),
        sigma: Vec::with_capacity(nx * ny),
    };
    for ty in 0..ny {
        for tx in 0..nx {
            let xs = tx * TILE..((tx + 1) * TILE).min(w);
            let ys = ty * TILE..((ty + 1) * TILE).min(h);
            let (b, s) = match stats(xs, ys) {
                (true, Some(b), Some(s)) => (b, s),
                _ => (frame_base, frame_sigma),
            };
            tiles.baseline.push(b);
            tiles.sigma.push(s);
        }
    }
    tiles
}

/// The second, low-threshold pass of the reference detection on a brightness layer:
/// markers too faint for the first pass's one threshold (set by the frame's noise and
/// its brightest markers: a pin at the vignetted edge of a field, a small dot in the
/// far rows of a perspective view). Candidates are the local maxima of the 3 × 3 box
/// mean of the map outside the first pass's blobs; each is grown to the 8-connected
/// pixels above half its height over its tile's baseline. A candidate is a marker when
///
/// * its smoothed peak rises [`FAINT_SIGMA`] local σ above the baseline (noise does
///   not: the test `a_noise_only_frame_finds_no_markers`),
/// * its raw peak rises `min_contrast / 2` above the map's median (the first pass's
///   per-blob floor: gel texture and dust stay below it),
/// * its half-height area neither reaches a first-pass blob nor a higher peak, and
///   holds at least `max(LEAST_AREA · πr², 3)` px (a quarter less on the image's edge) and at
///   most `5 πr²`, r the expected marker radius: an area relative to the spot's own
///   contrast, so a faint marker is judged by its whole disc, not by the core that
///   clears a threshold set by brighter ones,
/// * and that area is round (elongation ≤ `max_elongation`, 3 on the image's edge):
///   streaks and edges are not.
pub(crate) fn faint_spots(input: &FaintInput<'_>, max_elongation: f64) -> Vec<FaintSpot> {
    let (w, h) = (input.width, input.height);
    let valid: Vec<bool> = input.map.iter().map(|&v| v != i32::MIN).collect();
    let smooth_map = box_mean(input.map, &valid, w, h);
    let smooth_score = box_mean(input.score, &valid, w, h);
    let reach = input.radius_px.ceil() as usize + 2;
    let quiet: Vec<bool> = dilate(input.structure, w, h, reach)
        .into_iter()
        .map(|m| !m)
        .collect();
    let tiles = tile_stats(input, &quiet, &smooth_map, &smooth_score);
    let disc = std::f64::consts::PI * input.radius_px * input.radius_px;
    let mut spots = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let v = smooth_map[i];
            if v.is_nan() || input.taken[i] {
                continue;
            }
            let (base, sigma) = tiles.at(i, w);
            if (v as f64 - base) < FAINT_SIGMA * sigma {
                continue;
            }
            let is_max = !(y.saturating_sub(1)..(y + 2).min(h))
                .flat_map(|yy| (x.saturating_sub(1)..(x + 2).min(w)).map(move |xx| yy * w + xx))
                .any(|j| smooth_map[j] > v);
            if is_max {
                spots.extend(judge(
                    input,
                    &smooth_map,
                    i,
                    (base, sigma),
                    disc,
                    max_elongation,
                ));
            }
        }
    }
    spots
}

/// Whether the local maximum `top` of [`faint_spots`] (its tile's baseline and σ in
/// `local`) is a marker, and its moments if so.
fn judge(
    input: &FaintInput<'_>,
    smooth_map: &[f32],
    top: usize,
    local: (f64, f64),
    disc: f64,
    max_elongation: f64,
) -> Option<FaintSpot> {
    let (w, h) = (input.width, input.height);
    let (base, _) = local;
    let peak = smooth_map[top];
    let half = (base + 0.5 * (peak as f64 - base)) as f32;
    let most = (5.0 * disc).max(9.0) as usize;
    // The half-height area, grown from the peak; given up as soon as it reaches a
    // first-pass blob, a higher peak (or an equal one earlier in raster order), or
    // more than five markers' area.
    let mut pixels = vec![top];
    let mut seen = std::collections::HashSet::from([top]);
    let mut k = 0;
    while k < pixels.len() {
        let i = pixels[k];
        k += 1;
        let (x, y) = (i % w, i / w);
        for ny in y.saturating_sub(1)..(y + 2).min(h) {
            for nx in x.saturating_sub(1)..(x + 2).min(w) {
                let j = ny * w + nx;
                let v = smooth_map[j];
                if v.is_nan() || v < half || !seen.insert(j) {
                    continue;
                }
                // A tie on a plateau goes to its first pixel in raster order.
                let higher = v > peak || (v == peak && j < top);
                if input.taken[j] || higher || pixels.len() >= most {
                    return None;
                }
                pixels.push(j);
            }
        }
    }
    let raw_peak = pixels.iter().map(|&i| input.map[i]).max()?;
    if ((raw_peak - input.median) as f64) < 0.5 * input.min_contrast as f64 {
        return None;
    }
    let (mut sum, mut sx, mut sy) = (0.0, 0.0, 0.0);
    let mut shape = [0.0f64; 5];
    let mut at_edge = false;
    for &i in &pixels {
        let wgt = smooth_map[i] as f64 - base;
        let (x, y) = ((i % w) as f64, (i / w) as f64);
        at_edge |= i % w == 0 || i / w == 0 || i % w + 1 == w || i / w + 1 == h;
        sum += wgt;
        sx += wgt * x;
        sy += wgt * y;
        for (m, d) in shape.iter_mut().zip([x, y, x * x, y * y, x * y]) {
            *m += d;
        }
    }
    let area = pixels.len();
    let (least, most_elongated) = if at_edge {
        (0.75 * LEAST_AREA, 3.0)
    } else {
        (LEAST_AREA, max_elongation)
    };
    let ok = area as f64 >= (least * disc).max(3.0)
        && elongation(area, &shape) <= most_elongated
        && sum > 0.0;
    ok.then_some(FaintSpot {
        area,
        sum,
        sx,
        sy,
        peak: raw_peak,
    })
}

/// √(λ₁/λ₂) of the covariance of `n` pixels with moments Σx, Σy, Σx², Σy², Σxy: 1 for
/// a disc, large for a line.
pub(crate) fn elongation(n: usize, shape: &[f64; 5]) -> f64 {
    let n = n as f64;
    let [x, y, xx, yy, xy] = *shape;
    let (cxx, cyy, cxy) = (
        xx / n - (x / n).powi(2),
        yy / n - (y / n).powi(2),
        xy / n - x * y / (n * n),
    );
    let (m, d) = (
        0.5 * (cxx + cyy),
        (0.25 * (cxx - cyy).powi(2) + cxy * cxy).sqrt(),
    );
    ((m + d) / (m - d).max(1e-9)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The brute-force filter, for comparison.
    fn naive(v: &[i32], w: usize, h: usize, r: usize, min: bool) -> Vec<i32> {
        let mut out = vec![0; v.len()];
        for y in 0..h {
            for x in 0..w {
                let mut best = if min { i32::MAX } else { i32::MIN };
                for yy in y.saturating_sub(r)..=(y + r).min(h - 1) {
                    for xx in x.saturating_sub(r)..=(x + r).min(w - 1) {
                        let s = v[yy * w + xx];
                        best = if min { best.min(s) } else { best.max(s) };
                    }
                }
                out[y * w + x] = best;
            }
        }
        out
    }

    #[test]
    fn separable_queue_filter_matches_brute_force() {
        let (w, h) = (23, 17);
        // A deterministic pseudo-random image with ties.
        let v: Vec<i32> = (0..w * h)
            .map(|i| ((i as u64 * 2_654_435_761) % 97) as i32 / 3)
            .collect();
        for r in [0, 1, 2, 5, 30] {
            for min in [true, false] {
                assert_eq!(
                    filter2(&v, w, h, r, min),
                    naive(&v, w, h, r, min),
                    "r={r} min={min}"
                );
            }
        }
    }

    #[test]
    fn dilate_matches_a_brute_force_square_maximum() {
        let (w, h) = (19, 13);
        let mask: Vec<bool> = (0..w * h)
            .map(|i| (i as u64 * 2_654_435_761).is_multiple_of(23))
            .collect();
        let as_int: Vec<i32> = mask.iter().map(|&m| m as i32).collect();
        for r in [0, 1, 3, 20] {
            let brute: Vec<bool> = naive(&as_int, w, h, r, false)
                .iter()
                .map(|&v| v > 0)
                .collect();
            assert_eq!(dilate(&mask, w, h, r), brute, "r={r}");
        }
    }

    /// One faint disc beside a bright one the first pass took: the second pass finds
    /// the faint one (its centroid within 0.3 px) and nothing of the bright one's flank.
    #[test]
    fn faint_spots_finds_a_faint_disc_and_not_the_first_pass_blob() {
        let (w, h) = (64, 48);
        let disc = |cx: f64, cy: f64, r: f64, v: i32, m: &mut Vec<i32>| {
            for y in 0..h {
                for x in 0..w {
                    if (x as f64 - cx).hypot(y as f64 - cy) <= r {
                        m[y * w + x] += v;
                    }
                }
            }
        };
        // Deterministic noise of a few levels (the score) and its top-hat-like map.
        let noise: Vec<i32> = (0..w * h)
            .map(|i| ((i as u64 * 2_654_435_761) % 7) as i32)
            .collect();
        let mut map = noise.clone();
        disc(16.0, 24.0, 3.0, 200, &mut map);
        disc(44.3, 24.6, 3.0, 40, &mut map);
        let score = map.clone();
        let taken: Vec<bool> = (0..w * h)
            .map(|i| ((i % w) as f64 - 16.0).hypot((i / w) as f64 - 24.0) <= 3.0)
            .collect();
        let input = FaintInput {
            map: &map,
            score: &score,
            illumination: None,
            width: w,
            height: h,
            median: 3,
            taken: &taken,
            structure: &taken,
            radius_px: 3.0,
            min_contrast: 38,
        };
        let spots = faint_spots(&input, 2.2);
        assert_eq!(spots.len(), 1, "{spots:?}");
        let c = [spots[0].sx / spots[0].sum, spots[0].sy / spots[0].sum];
        assert!((c[0] - 44.0).hypot(c[1] - 25.0) < 0.8, "{c:?}");
    }

    #[test]
    fn top_hat_removes_a_gradient_and_keeps_a_narrow_bump() {
        let (w, h) = (60, 40);
        // A ramp of 10 levels per column plus a 5×5 bump of 300 at (30, 20).
        let mut v: Vec<i32> = (0..w * h).map(|i| 10 * (i % w) as i32).collect();
        for y in 18..=22 {
            for x in 28..=32 {
                v[y * w + x] += 300;
            }
        }
        let cm = contrast_map::<u8>(&v, w, h, MarkerColor::Bright, element_size(2.5));
        let c = cm.map;
        assert_eq!(cm.per_score, 1.0);
        // On the bump the larger opening is the horizontal one, which on a ramp takes
        // the level of the first column past the bump (3 columns right of its centre):
        // the bump's contrast is measured against its brighter side, 300 - 3 × 10.
        assert_eq!(c[20 * w + 30], 270);
        // Off the bump the ramp is gone everywhere, borders included: the vertical
        // opening of a ramp along x is the ramp itself, and the larger opening is taken.
        assert_eq!(c[5 * w + 5], 0);
        assert_eq!(c[35 * w + 50], 0);
        assert_eq!(c[35 * w + 59], 0);
        assert!((0..w).all(|x| c[5 * w + x] == 0), "{:?}", &c[5 * w..6 * w]);
    }

    #[test]
    fn dark_contrast_is_relative_to_the_illumination() {
        // Two black dots (Y = 0) under illumination 600 and 300 (sum of channels):
        // both contrast fully, 1024.
        let (w, h) = (80, 20);
        let bias = score_bias::<u8>(&[-1, -1, -1]);
        let mut y: Vec<i32> = (0..w * h)
            .map(|i| if i % w < 40 { 600 } else { 300 })
            .collect();
        for (cx, cy) in [(20usize, 10usize), (60, 10)] {
            for yy in cy - 2..=cy + 2 {
                for xx in cx - 2..=cx + 2 {
                    y[yy * w + xx] = 0;
                }
            }
        }
        let score: Vec<i32> = y.iter().map(|&v| bias - v).collect();
        let c = contrast_map::<u8>(&score, w, h, MarkerColor::Dark, element_size(2.5)).map;
        assert_eq!(c[10 * w + 20], DARK_UNIT);
        assert_eq!(c[10 * w + 60], DARK_UNIT);
        assert_eq!(c[2 * w + 5], 0);
    }
}
