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

/// The contrast map of a brightness layer (see the module docs) from its clamped
/// score `score` (row-major, `width × height`), with a line element of `size` px;
/// and the map units per score unit at the median illumination (1 for bright; for
/// dark `DARK_UNIT / I`), to express the score's pixel noise in map units.
pub(crate) fn contrast_map<T: Sample>(
    score: &[i32],
    width: usize,
    height: usize,
    color: MarkerColor,
    size: usize,
) -> (Vec<i32>, f64) {
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
            let mut lit: Vec<i32> = opening.iter().map(|&o| illumination(o)).collect();
            let n = lit.len();
            let median = if n == 0 {
                floor
            } else {
                *lit.select_nth_unstable(n / 2).1
            };
            (map, DARK_UNIT as f64 / median as f64)
        }
        _ => (
            score.iter().zip(&opening).map(|(&s, &o)| s - o).collect(),
            1.0,
        ),
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
    fn top_hat_removes_a_gradient_and_keeps_a_narrow_bump() {
        let (w, h) = (60, 40);
        // A ramp of 10 levels per column plus a 5×5 bump of 300 at (30, 20).
        let mut v: Vec<i32> = (0..w * h).map(|i| 10 * (i % w) as i32).collect();
        for y in 18..=22 {
            for x in 28..=32 {
                v[y * w + x] += 300;
            }
        }
        let (c, k) = contrast_map::<u8>(&v, w, h, MarkerColor::Bright, element_size(2.5));
        assert_eq!(k, 1.0);
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
        let (c, _) = contrast_map::<u8>(&score, w, h, MarkerColor::Dark, element_size(2.5));
        assert_eq!(c[10 * w + 20], DARK_UNIT);
        assert_eq!(c[10 * w + 60], DARK_UNIT);
        assert_eq!(c[2 * w + 5], 0);
    }
}
