//! The ideal marker renderer: what the sensor's camera sees, computed exactly.
//!
//! The camera looks at the marker layers from below, through the acrylic board, with
//! the opaque black shading layer of the surface behind them (paper Section III): a
//! dark background with coloured discs of the marker diameter. Markers are spheres,
//! seen as discs.
//!
//! **Coordinates.** Pixel `(i, j)` (column `i`, row `j`) covers the square
//! `[i − ½, i + ½] × [j − ½, j + ½]` in pixel coordinates: pixel *centres* are at
//! integer coordinates, so an intensity-weighted centroid `Σ w·i / Σ w` computed with
//! integer indices is directly a position in the frame of
//! [`CameraMapping::mm_to_px`].
//!
//! **Exact coverage.** Each pixel inside a disc's bounding box receives the exact
//! area `a ∈ [0, 1]` of the pixel square covered by the disc, from the analytic
//! circle–rectangle intersection: for a circle of radius `r` at the origin, the area
//! between `x0 ≤ x ≤ x1` above the line `y = h ≥ 0` is `G(c1) − h c1 − G(c0) + h c0`
//! with `G(x) = ½ (x √(r² − x²) + r² asin(x/r))` (the antiderivative of the chord
//! half-height) and `c = clamp(x, −s, s)`, `s = √(r² − h²)`; a rectangle is a
//! difference of two such strips (split at `y = 0` when it straddles the centre).
//! `G` is evaluated once per column edge and once per row edge of the disc's bounding
//! box, so the per-pixel cost is a few multiplications. Everything is computed in
//! `f64` and stored in `f32` (relative error ≤ 6e-8). Pixels fully inside the disc get
//! `a = 1` and pixels fully outside are not touched. The covered area of a disc is
//! therefore `π r²` to rounding; its intensity-weighted centroid differs from the true
//! centre only by the pixel-sampling (anti-aliasing) error of assigning each covered
//! area to its pixel centre, measured below 1e-3 px for the paper's 12 px discs
//! (`tests/sim.rs`).
//!
//! **Compositing.** A pixel of colour `p` covered by fraction `a` of a marker of colour
//! `c` becomes `p + a (c − p)` ("over" compositing). Layers are drawn from the
//! shallowest to the deepest: the camera is under the elastomer, so deeper markers are
//! nearer to it and hide shallower ones. Within a layer markers are drawn in their
//! order (they do not overlap in a valid sensor).
//!
//! **Speed.** The background is a fill; only pixels in disc bounding boxes are visited.
//!
//! The float frame is [`image::Rgb32FImage`] with linear intensities in `[0, 1]`;
//! [`to_rgb8`] and [`to_rgb16`] round to the nearest code value and clamp.

use image::{ImageBuffer, Rgb, Rgb32FImage, RgbImage};
use thiserror::Error;

use crate::sensor::{CameraMapping, MarkerColor, Sensor};

/// A 16-bit RGB image (PNG-compatible), the lossless output for ideal renders.
pub type Rgb16Image = ImageBuffer<Rgb<u16>, Vec<u16>>;

/// An error rendering a frame.
#[derive(Debug, Error, PartialEq)]
pub enum RenderError {
    /// A marker's centre is NaN or infinite.
    #[error("marker {index} of layer {layer} has a non-finite centre ({x_px}, {y_px}) px")]
    NonFiniteCentre {
        /// Layer index.
        layer: usize,
        /// Marker index in the list.
        index: usize,
        /// x in px.
        x_px: f64,
        /// y in px.
        y_px: f64,
    },
    /// A marker's diameter is not a finite number ≥ 0.
    #[error("marker {index} has diameter {diameter_mm} mm: must be a finite number >= 0 mm")]
    BadDiameter {
        /// Marker index in the list.
        index: usize,
        /// The diameter.
        diameter_mm: f64,
    },
    /// A marker names a layer the sensor does not have.
    #[error("marker {index} names layer {layer}, but the sensor has {layers} layers")]
    UnknownLayer {
        /// Marker index in the list.
        index: usize,
        /// The layer index.
        layer: usize,
        /// Number of sensor layers.
        layers: usize,
    },
    /// The output buffer does not have the camera's size.
    #[error("frame is {width}x{height} px, the camera is {camera_width}x{camera_height} px")]
    FrameSize {
        /// Buffer width.
        width: u32,
        /// Buffer height.
        height: u32,
        /// Camera width.
        camera_width: u32,
        /// Camera height.
        camera_height: u32,
    },
}

/// One marker to draw: its layer, its current centre in the sensor frame and its
/// diameter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Marker {
    /// Index of its layer in the sensor's layer list.
    pub layer: usize,
    /// Current centre (reference + displacement), mm.
    pub position_mm: [f64; 2],
    /// Diameter, mm.
    pub diameter_mm: f64,
}

/// Colours of the rendered image, linear RGB in `[0, 1]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Palette {
    /// The black shading layer seen through the elastomer.
    pub background: [f32; 3],
    /// Blue markers.
    pub blue: [f32; 3],
    /// Red markers.
    pub red: [f32; 3],
    /// Green markers.
    pub green: [f32; 3],
}

impl Default for Palette {
    /// Dark background, saturated marker colours with a little cross-talk between
    /// channels (as a colour camera sees plastic balls): each marker colour dominates
    /// its own channel by at least 0.7 so colour segmentation is easy but not trivial.
    fn default() -> Self {
        Palette {
            background: [0.04, 0.04, 0.05],
            blue: [0.10, 0.20, 0.90],
            red: [0.90, 0.12, 0.10],
            green: [0.12, 0.85, 0.18],
        }
    }
}

impl Palette {
    /// The colour of a marker layer.
    pub fn color(&self, c: MarkerColor) -> [f32; 3] {
        match c {
            MarkerColor::Blue => self.blue,
            MarkerColor::Red => self.red,
            MarkerColor::Green => self.green,
        }
    }
}

/// Every marker of every layer grid at its reference (unloaded) position, layer by
/// layer, row-major within a layer (the order of [`crate::model::MarkerSite::from_sensor_grids`]),
/// with the grid's diameter.
pub fn reference_markers(sensor: &Sensor) -> Vec<Marker> {
    let mut out = Vec::new();
    for (layer, l) in sensor.layers.iter().enumerate() {
        if let Some(m) = &l.markers {
            out.extend(m.grid.nodes_mm().into_iter().map(|p| Marker {
                layer,
                position_mm: p,
                diameter_mm: m.diameter_mm,
            }));
        }
    }
    out
}

/// `markers` moved by interleaved displacements `u_mm` (`ux, uy` per marker, the
/// order of [`crate::model::forward`]). Panics if the lengths disagree (a caller bug).
pub fn displaced(markers: &[Marker], u_mm: &[f64]) -> Vec<Marker> {
    assert_eq!(u_mm.len(), 2 * markers.len(), "displacement length");
    markers
        .iter()
        .enumerate()
        .map(|(k, m)| Marker {
            position_mm: [
                m.position_mm[0] + u_mm[2 * k],
                m.position_mm[1] + u_mm[2 * k + 1],
            ],
            ..*m
        })
        .collect()
}

/// Renders marker frames of one sensor. Holds the camera, the layer colours and the
/// drawing order; reusable across frames (no allocation in [`Renderer::render_into`]).
#[derive(Debug, Clone)]
pub struct Renderer {
    camera: CameraMapping,
    palette: Palette,
    layer_colors: Vec<[f32; 3]>,
    /// Layer indices from the shallowest to the deepest (drawing order).
    draw_order: Vec<usize>,
}

impl Renderer {
    /// A renderer for `sensor` with the default [`Palette`].
    pub fn new(sensor: &Sensor) -> Self {
        Self::with_palette(sensor, Palette::default())
    }

    /// A renderer with explicit colours.
    pub fn with_palette(sensor: &Sensor, palette: Palette) -> Self {
        let mut draw_order: Vec<usize> = (0..sensor.layers.len()).collect();
        // Stable sort: equal depths keep file order.
        draw_order.sort_by(|&a, &b| {
            sensor.layers[a]
                .depth_mm
                .total_cmp(&sensor.layers[b].depth_mm)
        });
        Renderer {
            camera: sensor.camera,
            palette,
            layer_colors: sensor
                .layers
                .iter()
                .map(|l| palette.color(l.color))
                .collect(),
            draw_order,
        }
    }

    /// The camera mapping used.
    pub fn camera(&self) -> &CameraMapping {
        &self.camera
    }

    /// The colours used.
    pub fn palette(&self) -> &Palette {
        &self.palette
    }

    /// Layer indices in drawing order (shallowest first; deeper layers drawn on top).
    pub fn draw_order(&self) -> &[usize] {
        &self.draw_order
    }

    /// A background-filled frame of the camera's size.
    pub fn blank(&self) -> Rgb32FImage {
        let mut f = Rgb32FImage::new(self.camera.width_px, self.camera.height_px);
        fill(&mut f, self.palette.background);
        f
    }

    /// Renders `markers` into a new frame.
    pub fn render(&self, markers: &[Marker]) -> Result<Rgb32FImage, RenderError> {
        let mut f = Rgb32FImage::new(self.camera.width_px, self.camera.height_px);
        self.render_into(markers, &mut f)?;
        Ok(f)
    }

    /// Clears `frame` to the background and draws `markers` layer by layer, shallowest
    /// first. `frame` must have the camera's size.
    pub fn render_into(
        &self,
        markers: &[Marker],
        frame: &mut Rgb32FImage,
    ) -> Result<(), RenderError> {
        self.check(markers, frame)?;
        fill(frame, self.palette.background);
        for &layer in &self.draw_order {
            let color = self.layer_colors[layer];
            for m in markers.iter().filter(|m| m.layer == layer) {
                let c = self.camera.mm_to_px(m.position_mm);
                let r = 0.5 * m.diameter_mm / self.camera.mm_per_px;
                draw_disc(frame, c, r, |p, a| {
                    if a >= 1.0 {
                        // Exact colour for covered pixels (p + 1·(c − p) rounds in f32).
                        p.copy_from_slice(&color);
                    } else {
                        for ch in 0..3 {
                            p[ch] += a * (color[ch] - p[ch]);
                        }
                    }
                });
            }
        }
        Ok(())
    }

    /// Coverage map of one layer: `coverage[j * width + i]` is the fraction of pixel
    /// `(i, j)` covered by the layer's markers (accumulated and clamped to 1, exact when
    /// markers do not overlap). `coverage` is cleared first and must hold
    /// `width × height` values. Used by effects that act per layer (depth defocus).
    pub fn layer_coverage_into(
        &self,
        markers: &[Marker],
        layer: usize,
        coverage: &mut [f32],
    ) -> Result<(), RenderError> {
        let (w, h) = (self.camera.width_px, self.camera.height_px);
        assert_eq!(
            coverage.len(),
            (w as usize) * (h as usize),
            "coverage length"
        );
        self.check_markers(markers)?;
        coverage.fill(0.0);
        for m in markers.iter().filter(|m| m.layer == layer) {
            let c = self.camera.mm_to_px(m.position_mm);
            let r = 0.5 * m.diameter_mm / self.camera.mm_per_px;
            disc_coverage_visit(w, h, c, r, |i, j, a| {
                let v = &mut coverage[j * w as usize + i];
                *v = (*v + a).min(1.0);
            });
        }
        Ok(())
    }

    /// The colour of a layer.
    pub fn layer_color(&self, layer: usize) -> [f32; 3] {
        self.layer_colors[layer]
    }

    fn check_markers(&self, markers: &[Marker]) -> Result<(), RenderError> {
        for (index, m) in markers.iter().enumerate() {
            if m.layer >= self.layer_colors.len() {
                return Err(RenderError::UnknownLayer {
                    index,
                    layer: m.layer,
                    layers: self.layer_colors.len(),
                });
            }
            if !(m.position_mm[0].is_finite() && m.position_mm[1].is_finite()) {
                let c = self.camera.mm_to_px(m.position_mm);
                return Err(RenderError::NonFiniteCentre {
                    layer: m.layer,
                    index,
                    x_px: c[0],
                    y_px: c[1],
                });
            }
            if !(m.diameter_mm.is_finite() && m.diameter_mm >= 0.0) {
                return Err(RenderError::BadDiameter {
                    index,
                    diameter_mm: m.diameter_mm,
                });
            }
        }
        Ok(())
    }

    fn check(&self, markers: &[Marker], frame: &Rgb32FImage) -> Result<(), RenderError> {
        if frame.dimensions() != (self.camera.width_px, self.camera.height_px) {
            return Err(RenderError::FrameSize {
                width: frame.width(),
                height: frame.height(),
                camera_width: self.camera.width_px,
                camera_height: self.camera.height_px,
            });
        }
        self.check_markers(markers)
    }
}

/// Fills a frame with one colour.
pub fn fill(frame: &mut Rgb32FImage, color: [f32; 3]) {
    if color[0] == color[1] && color[1] == color[2] {
        frame.as_mut().fill(color[0]);
    } else {
        for p in frame.as_mut().chunks_exact_mut(3) {
            p.copy_from_slice(&color);
        }
    }
}

/// Draws one disc (centre `c_px`, radius `r_px`) into `frame`, calling `blend(pixel,
/// coverage)` for every pixel with coverage > 0. Parts outside the frame are clipped.
pub fn draw_disc(
    frame: &mut Rgb32FImage,
    c_px: [f64; 2],
    r_px: f64,
    mut blend: impl FnMut(&mut [f32], f32),
) {
    let (w, h) = frame.dimensions();
    let data: &mut [f32] = frame.as_mut();
    disc_coverage_visit(w, h, c_px, r_px, |i, j, a| {
        let k = 3 * (j * w as usize + i);
        blend(&mut data[k..k + 3], a);
    });
}

/// Largest bounding box (pixels per side) a disc may have; larger discs are still
/// drawn, but with per-pixel evaluation of the edge terms.
const MAX_CACHED_EDGES: usize = 130;

/// Calls `visit(i, j, coverage)` for every pixel `(i, j)` of a `w × h` image that a
/// disc of centre `c_px` and radius `r_px` covers, with the exact covered area
/// (see the module docs). Pixels with zero coverage are not visited.
pub fn disc_coverage_visit(
    w: u32,
    h: u32,
    c_px: [f64; 2],
    r_px: f64,
    mut visit: impl FnMut(usize, usize, f32),
) {
    let usable = r_px > 0.0 && r_px.is_finite() && c_px[0].is_finite() && c_px[1].is_finite();
    if !usable {
        return;
    }
    let r = r_px;
    // Pixel i covers [i - 0.5, i + 0.5]; the disc spans [cx - r, cx + r].
    let i0 = ((c_px[0] - r + 0.5).floor()).max(0.0);
    let i1 = ((c_px[0] + r + 0.5).floor()).min(w as f64 - 1.0);
    let j0 = ((c_px[1] - r + 0.5).floor()).max(0.0);
    let j1 = ((c_px[1] + r + 0.5).floor()).min(h as f64 - 1.0);
    if i1 < i0 || j1 < j0 {
        return;
    }
    let (i0, i1, j0, j1) = (i0 as usize, i1 as usize, j0 as usize, j1 as usize);
    let nx = i1 - i0 + 1;
    let ny = j1 - j0 + 1;
    let r2 = r * r;
    let g = |x: f64| -> f64 {
        let x = x.clamp(-r, r);
        0.5 * (x * (r2 - x * x).max(0.0).sqrt() + r2 * (x / r).clamp(-1.0, 1.0).asin())
    };
    // Column edges x_e = i - 0.5 - cx and row lines |y_e|, relative to the centre.
    let mut xe = [0.0f64; MAX_CACHED_EDGES + 1];
    let mut gx = [0.0f64; MAX_CACHED_EDGES + 1];
    let mut ye = [0.0f64; MAX_CACHED_EDGES + 1];
    let mut lines = [Line::default(); MAX_CACHED_EDGES + 1];
    let cached = nx <= MAX_CACHED_EDGES && ny <= MAX_CACHED_EDGES;
    if cached {
        for k in 0..=nx {
            xe[k] = (i0 + k) as f64 - 0.5 - c_px[0];
            gx[k] = g(xe[k]);
        }
        for k in 0..=ny {
            ye[k] = (j0 + k) as f64 - 0.5 - c_px[1];
            lines[k] = Line::new(ye[k].abs(), r, &g);
        }
    }
    let zero = Line::new(0.0, r, &g);
    for jj in 0..ny {
        let (ya, yb, la, lb) = if cached {
            (ye[jj], ye[jj + 1], lines[jj], lines[jj + 1])
        } else {
            let ya = (j0 + jj) as f64 - 0.5 - c_px[1];
            let yb = ya + 1.0;
            (
                ya,
                yb,
                Line::new(ya.abs(), r, &g),
                Line::new(yb.abs(), r, &g),
            )
        };
        // Nearest |y| of the row to the centre, for the quick outside test.
        let ny_near = if ya <= 0.0 && yb >= 0.0 {
            0.0
        } else {
            ya.abs().min(yb.abs())
        };
        let ny_far = ya.abs().max(yb.abs());
        for ii in 0..nx {
            let (xa, xb, gxa, gxb) = if cached {
                (xe[ii], xe[ii + 1], gx[ii], gx[ii + 1])
            } else {
                let xa = (i0 + ii) as f64 - 0.5 - c_px[0];
                (xa, xa + 1.0, g(xa), g(xa + 1.0))
            };
            let nx_near = if xa <= 0.0 && xb >= 0.0 {
                0.0
            } else {
                xa.abs().min(xb.abs())
            };
            if nx_near * nx_near + ny_near * ny_near >= r2 {
                continue; // entirely outside
            }
            let nx_far = xa.abs().max(xb.abs());
            let a = if nx_far * nx_far + ny_far * ny_far <= r2 {
                1.0 // entirely inside
            } else {
                let ex = [Edge { x: xa, g: gxa }, Edge { x: xb, g: gxb }];
                let v = if ya >= 0.0 {
                    strip(ex, la) - strip(ex, lb)
                } else if yb <= 0.0 {
                    strip(ex, lb) - strip(ex, la)
                } else {
                    (strip(ex, zero) - strip(ex, la)) + (strip(ex, zero) - strip(ex, lb))
                };
                v.clamp(0.0, 1.0)
            };
            if a > 0.0 {
                visit(i0 + ii, j0 + jj, a as f32);
            }
        }
    }
}

/// A vertical edge at `x` (relative to the circle centre) with `G(x)` precomputed.
#[derive(Clone, Copy)]
struct Edge {
    x: f64,
    g: f64,
}

/// A horizontal line `y = h ≥ 0` (relative to the centre): half-chord `s` and `G(s)`.
#[derive(Clone, Copy, Default)]
struct Line {
    h: f64,
    s: f64,
    gs: f64,
}

impl Line {
    fn new(h: f64, r: f64, g: &impl Fn(f64) -> f64) -> Self {
        let s = if h < r { (r * r - h * h).sqrt() } else { 0.0 };
        Line { h, s, gs: g(s) }
    }
}

/// Area of the circle above the line `l` between the edges `e[0].x ≤ e[1].x`:
/// `[G(c) − h c]` between `c0 = clamp(x0, −s, s)` and `c1 = clamp(x1, −s, s)`.
#[inline]
fn strip(e: [Edge; 2], l: Line) -> f64 {
    let f = |ed: Edge| -> f64 {
        if ed.x <= -l.s {
            -l.gs + l.h * l.s
        } else if ed.x >= l.s {
            l.gs - l.h * l.s
        } else {
            ed.g - l.h * ed.x
        }
    };
    f(e[1]) - f(e[0])
}

/// Exact area of the pixel `(i, j)` (the unit square centred on integer coordinates)
/// covered by a disc of centre `c_px` and radius `r_px`.
pub fn pixel_coverage(i: i64, j: i64, c_px: [f64; 2], r_px: f64) -> f64 {
    // Reuse the visitor on a one-pixel window translated to the origin.
    let mut out = 0.0;
    let c = [c_px[0] - i as f64, c_px[1] - j as f64];
    disc_coverage_visit(1, 1, c, r_px, |_, _, a| out = a as f64);
    out
}

/// Converts a float frame to 8 bits per channel: `round(255 v)`, clamped to `[0, 255]`.
pub fn to_rgb8(frame: &Rgb32FImage) -> RgbImage {
    let data = frame
        .as_raw()
        .iter()
        .map(|&v| (v * 255.0).round().clamp(0.0, 255.0) as u8)
        .collect();
    // The lengths match by construction (same dimensions, 3 channels).
    RgbImage::from_raw(frame.width(), frame.height(), data)
        .unwrap_or_else(|| RgbImage::new(frame.width(), frame.height()))
}

/// Converts a float frame to 16 bits per channel: `round(65535 v)`, clamped.
pub fn to_rgb16(frame: &Rgb32FImage) -> Rgb16Image {
    let data = frame
        .as_raw()
        .iter()
        .map(|&v| (v * 65535.0).round().clamp(0.0, 65535.0) as u16)
        .collect();
    Rgb16Image::from_raw(frame.width(), frame.height(), data)
        .unwrap_or_else(|| Rgb16Image::new(frame.width(), frame.height()))
}

/// Convenience: renders `sensor`'s grid markers moved by `u_mm` (interleaved, the
/// order of [`reference_markers`]; `None` renders the reference frame) with the default
/// palette.
pub fn render_sensor(sensor: &Sensor, u_mm: Option<&[f64]>) -> Result<Rgb32FImage, RenderError> {
    let markers = reference_markers(sensor);
    let markers = match u_mm {
        Some(u) => displaced(&markers, u),
        None => markers,
    };
    Renderer::new(sensor).render(&markers)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Coverage by brute-force supersampling (n × n samples per pixel).
    fn supersampled(i: i64, j: i64, c: [f64; 2], r: f64, n: usize) -> f64 {
        let mut hits = 0usize;
        for a in 0..n {
            for b in 0..n {
                let x = i as f64 - 0.5 + (a as f64 + 0.5) / n as f64;
                let y = j as f64 - 0.5 + (b as f64 + 0.5) / n as f64;
                if (x - c[0]).powi(2) + (y - c[1]).powi(2) < r * r {
                    hits += 1;
                }
            }
        }
        hits as f64 / (n * n) as f64
    }

    #[test]
    fn pixel_coverage_matches_supersampling_within_sampling_error() {
        // 1000×1000 samples: area error ≲ perimeter-in-pixel / n ≈ 1.5e-3.
        let c = [0.31, -0.22];
        for r in [0.3, 0.7, 1.3, 2.9] {
            for j in -3..=3 {
                for i in -3..=3 {
                    let exact = pixel_coverage(i, j, c, r);
                    let approx = supersampled(i, j, c, r, 1000);
                    assert!(
                        (exact - approx).abs() < 2e-3,
                        "r={r} ({i},{j}): {exact} vs {approx}"
                    );
                }
            }
        }
    }

    #[test]
    fn total_coverage_equals_disc_area() {
        for (c, r) in [
            ([20.3, 19.7], 6.0),
            ([20.0, 20.0], 0.4),
            ([21.77, 18.13], 9.41),
        ] {
            let mut sum = 0.0f64;
            disc_coverage_visit(64, 64, c, r, |_, _, a| sum += a as f64);
            let area = std::f64::consts::PI * r * r;
            assert!((sum - area).abs() < 1e-5 * area, "r={r}: {sum} vs {area}");
        }
    }

    #[test]
    fn discs_are_clipped_at_the_frame_border() {
        let mut sum = 0.0f64;
        disc_coverage_visit(64, 64, [0.0 - 0.5, 30.0], 5.0, |i, _, a| {
            assert!(i < 64);
            sum += a as f64;
        });
        // Centre on the left edge of pixel 0: exactly half the disc is inside.
        let half = 0.5 * std::f64::consts::PI * 25.0;
        assert!((sum - half).abs() < 1e-4, "{sum} vs {half}");
        let mut n = 0;
        disc_coverage_visit(64, 64, [-20.0, 30.0], 5.0, |_, _, _| n += 1);
        assert_eq!(n, 0);
    }

    #[test]
    fn deeper_layer_is_drawn_on_top() {
        let s = crate::sensor::paper_sensor();
        let r = Renderer::new(&s);
        assert_eq!(r.draw_order(), &[0, 1]); // blue 3 mm, red 6 mm
        let p = [2.0, 2.0];
        let ms = [
            Marker {
                layer: 1,
                position_mm: p,
                diameter_mm: 0.6,
            },
            Marker {
                layer: 0,
                position_mm: p,
                diameter_mm: 0.6,
            },
        ];
        let f = r.render(&ms).unwrap();
        let c = s.camera.mm_to_px(p);
        let px = f.get_pixel(c[0].round() as u32, c[1].round() as u32);
        assert_eq!(px.0, r.palette().red, "red (6 mm) is nearer the camera");
    }
}
