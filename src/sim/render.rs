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
//! (`tests/sim.rs`). For tracker tests that need the rendering error out of the way,
//! [`PixelFilter::Tent`] gives each pixel the disc's integral against the tent
//! `t(x − i) t(y − j)` instead (exact moments per cell between pixel centres), and the
//! centroid is then exact (≤ 1e-5 px measured, limited by `f32`).
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

/// How a pixel integrates the scene (the pixel's spatial response).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PixelFilter {
    /// Box response: the exact area of the pixel square covered by the disc (a camera
    /// pixel with 100 % fill factor). The default. Centroids carry the area-sampling
    /// error (≤ 1.53e-3 px for 12 px discs).
    #[default]
    Area,
    /// Tent response `t(x)t(y)`, `t(x) = max(0, 1 − |x|)` (the box convolved with
    /// itself: a pixel with a one-pixel optical blur). Linear interpolation reproduces
    /// linear functions, `Σ_i t(x − i) i = x`, so the intensity-weighted centroid of a
    /// disc equals its centre exactly (to `f32` storage, ~1e-6 px): for testing trackers
    /// independently of rendering error.
    Tent,
}

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
    /// `dark` markers (drawn on [`Palette::lit_background`]).
    pub dark: [f32; 3],
    /// `bright` markers (light pins on the dark background).
    pub bright: [f32; 3],
    /// The lit gel a sensor with `dark` layers shows instead of `background`.
    pub lit_background: [f32; 3],
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
            dark: [0.06, 0.06, 0.07],
            bright: [0.85, 0.86, 0.88],
            lit_background: [0.82, 0.80, 0.78],
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
            MarkerColor::Dark => self.dark,
            MarkerColor::Bright => self.bright,
        }
    }

    /// The palette for `sensor`: the default, except that a sensor with a `dark`
    /// layer is seen against the lit gel (dark markers on a dark background would be
    /// invisible). Sensors of coloured and bright layers keep the dark background, so
    /// their frames are unchanged.
    pub fn for_sensor(sensor: &Sensor) -> Palette {
        let mut p = Palette::default();
        if sensor.layers.iter().any(|l| l.color == MarkerColor::Dark) {
            p.background = p.lit_background;
        }
        p
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
    filter: PixelFilter,
}

impl Renderer {
    /// A renderer for `sensor` with [`Palette::for_sensor`] (the default palette,
    /// with the lit gel behind `dark` layers).
    pub fn new(sensor: &Sensor) -> Self {
        Self::with_palette(sensor, Palette::for_sensor(sensor))
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
            filter: PixelFilter::Area,
        }
    }

    /// This renderer with another pixel response.
    pub fn with_filter(mut self, filter: PixelFilter) -> Self {
        self.filter = filter;
        self
    }

    /// The pixel response used.
    pub fn filter(&self) -> PixelFilter {
        self.filter
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
                draw_disc(frame, self.filter, c, r, |p, a| {
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
            disc_visit(self.filter, w, h, c, r, |i, j, a| {
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

    /// Checks that `frame` has the camera's size and every marker a known layer, a
    /// finite centre and a finite diameter ≥ 0 (what [`Renderer::render_into`] checks).
    pub fn check(&self, markers: &[Marker], frame: &Rgb32FImage) -> Result<(), RenderError> {
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

/// Fills a frame with one colour: the first row by pixels, the others by copying it
/// (memcpy speed; a plain memset when the colour is grey).
pub fn fill(frame: &mut Rgb32FImage, color: [f32; 3]) {
    let row_len = 3 * frame.width() as usize;
    let data: &mut [f32] = frame.as_mut();
    if color[0] == color[1] && color[1] == color[2] {
        data.fill(color[0]);
        return;
    }
    if row_len == 0 {
        return;
    }
    let (first, rest) = data.split_at_mut(row_len);
    for p in first.chunks_exact_mut(3) {
        p.copy_from_slice(&color);
    }
    for row in rest.chunks_exact_mut(row_len) {
        row.copy_from_slice(first);
    }
}

/// Draws one disc (centre `c_px`, radius `r_px`) into `frame`, calling `blend(pixel,
/// coverage)` for every pixel with coverage > 0. Parts outside the frame are clipped.
pub fn draw_disc(
    frame: &mut Rgb32FImage,
    filter: PixelFilter,
    c_px: [f64; 2],
    r_px: f64,
    mut blend: impl FnMut(&mut [f32], f32),
) {
    let (w, h) = frame.dimensions();
    let data: &mut [f32] = frame.as_mut();
    disc_visit(filter, w, h, c_px, r_px, |i, j, a| {
        let k = 3 * (j * w as usize + i);
        blend(&mut data[k..k + 3], a);
    });
}

/// Edge tables of [`disc_coverage_visit`]: column edges, their `G`, row lines.
#[derive(Default)]
struct EdgeTables {
    xe: Vec<f64>,
    gx: Vec<f64>,
    lines: Vec<Line>,
}

std::thread_local! {
    /// Reused across discs (taken out while in use, so a nested call only allocates).
    static EDGE_TABLES: std::cell::Cell<EdgeTables> = std::cell::Cell::new(EdgeTables::default());
}

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
    // Column edges x_e = i - 0.5 - cx with G(x_e), and row lines y_e = j - 0.5 - cy
    // (signed, with the half-chord and G of |y_e|), relative to the centre.
    let mut t = EDGE_TABLES.with(|c| c.take());
    t.xe.clear();
    t.gx.clear();
    t.lines.clear();
    for k in 0..=nx {
        let x = (i0 + k) as f64 - 0.5 - c_px[0];
        t.xe.push(x);
        t.gx.push(g(x));
    }
    for k in 0..=ny {
        let y = (j0 + k) as f64 - 0.5 - c_px[1];
        t.lines.push(Line::new(y, r, &g));
    }
    let zero = Line::new(0.0, r, &g);
    for jj in 0..ny {
        let (la, lb) = (t.lines[jj], t.lines[jj + 1]);
        let (ya, yb) = (la.y, lb.y);
        // Nearest and farthest |y| of the row from the centre, for the quick tests.
        let ny_near = if ya <= 0.0 && yb >= 0.0 {
            0.0
        } else {
            la.h.min(lb.h)
        };
        let ny_far = la.h.max(lb.h);
        for ii in 0..nx {
            let (xa, xb) = (t.xe[ii], t.xe[ii + 1]);
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
                let ex = [
                    Edge { x: xa, g: t.gx[ii] },
                    Edge {
                        x: xb,
                        g: t.gx[ii + 1],
                    },
                ];
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
    EDGE_TABLES.with(|c| c.set(t));
}

/// Calls `visit(i, j, value)` for every pixel of a `w × h` image a disc reaches, with
/// the pixel's response to the disc under `filter` (see [`PixelFilter`]).
pub fn disc_visit(
    filter: PixelFilter,
    w: u32,
    h: u32,
    c_px: [f64; 2],
    r_px: f64,
    visit: impl FnMut(usize, usize, f32),
) {
    match filter {
        PixelFilter::Area => disc_coverage_visit(w, h, c_px, r_px, visit),
        PixelFilter::Tent => disc_tent_visit(w, h, c_px, r_px, visit),
    }
}

std::thread_local! {
    /// Node accumulator of [`disc_tent_visit`], reused across discs (taken out while
    /// in use, so a nested call only allocates).
    static TENT_NODES: std::cell::Cell<Vec<f64>> = const { std::cell::Cell::new(Vec::new()) };
}

/// Tent-filtered disc: `v(i, j) = ∫∫_disc t(x − i) t(y − j)`. The plane is cut into the
/// unit cells between pixel centres; on each cell the moments `∫1, ∫u, ∫v, ∫uv` of
/// the disc part (exact, from [`rect_moments`]) give the bilinear shares of its four
/// corner pixels. Values within 1e-9 of 1 are snapped to 1.
pub fn disc_tent_visit(
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
    let (ci0, ci1) = ((c_px[0] - r).floor(), (c_px[0] + r).floor());
    let (cj0, cj1) = ((c_px[1] - r).floor(), (c_px[1] + r).floor());
    // Nodes ci0 ..= ci1 + 1; skip discs whose nodes all lie outside the image.
    if ci1 + 1.0 < 0.0 || cj1 + 1.0 < 0.0 || ci0 > w as f64 - 1.0 || cj0 > h as f64 - 1.0 {
        return;
    }
    let ncx = (ci1 - ci0) as usize + 1;
    let ncy = (cj1 - cj0) as usize + 1;
    let (nw, nh) = (ncx + 1, ncy + 1);
    let r2 = r * r;
    let mut nodes = TENT_NODES.with(|c| c.take());
    {
        nodes.clear();
        nodes.resize(nw * nh, 0.0);
        for cj in 0..ncy {
            let jg = cj0 + cj as f64;
            let (y0, y1) = (jg - c_px[1], jg + 1.0 - c_px[1]);
            let ny_near = if y0 <= 0.0 && y1 >= 0.0 {
                0.0
            } else {
                y0.abs().min(y1.abs())
            };
            let ny_far = y0.abs().max(y1.abs());
            for ci in 0..ncx {
                let ig = ci0 + ci as f64;
                let (x0, x1) = (ig - c_px[0], ig + 1.0 - c_px[0]);
                let nx_near = if x0 <= 0.0 && x1 >= 0.0 {
                    0.0
                } else {
                    x0.abs().min(x1.abs())
                };
                if nx_near * nx_near + ny_near * ny_near >= r2 {
                    continue;
                }
                let nx_far = x0.abs().max(x1.abs());
                let m = if nx_far * nx_far + ny_far * ny_far <= r2 {
                    let (mx, my) = (0.5 * (x0 + x1), 0.5 * (y0 + y1));
                    [1.0, mx, my, mx * my]
                } else {
                    rect_moments(x0, x1, y0, y1, r)
                };
                // Moments in the cell's local frame u = x − i, v = y − j.
                let (dx, dy) = (c_px[0] - ig, c_px[1] - jg);
                let a = m[0];
                let u = m[1] + dx * a;
                let v = m[2] + dy * a;
                let uv = m[3] + dy * m[1] + dx * m[2] + dx * dy * a;
                let k = cj * nw + ci;
                nodes[k] += a - u - v + uv;
                nodes[k + 1] += u - uv;
                nodes[k + nw] += v - uv;
                nodes[k + nw + 1] += uv;
            }
        }
        for lj in 0..nh {
            let j = cj0 + lj as f64;
            if j < 0.0 || j > h as f64 - 1.0 {
                continue;
            }
            for li in 0..nw {
                let i = ci0 + li as f64;
                if i < 0.0 || i > w as f64 - 1.0 {
                    continue;
                }
                let val = nodes[lj * nw + li];
                if val > 0.0 {
                    let val = if val > 1.0 - 1e-9 { 1.0 } else { val };
                    visit(i as usize, j as usize, val as f32);
                }
            }
        }
    }
    TENT_NODES.with(|c| c.set(nodes));
}

/// Moments `[∫1, ∫x, ∫y, ∫xy]` of the part of a circle (radius `r`, centred at the
/// origin) inside the rectangle `[x0, x1] × [y0, y1]` (`x0 ≤ x1`, `y0 ≤ y1`), exact.
/// Strips above `y = h ≥ 0` are integrated in closed form between `c = clamp(x, ±s)`:
/// `∫1 = G(x) − hx`, `∫x = −(r²−x²)^{3/2}/3 − hx²/2`, `∫y = ((r²−h²)x − x³/3)/2`,
/// `∫xy = ((r²−h²)x²/2 − x⁴/4)/2`; parts below `y = 0` are mirrored.
pub fn rect_moments(x0: f64, x1: f64, y0: f64, y1: f64, r: f64) -> [f64; 4] {
    let strip = |h: f64| -> [f64; 4] {
        let r2 = r * r;
        let s = if h < r { (r2 - h * h).sqrt() } else { 0.0 };
        let k = r2 - h * h;
        let f = |x: f64| -> [f64; 4] {
            let q = (r2 - x * x).max(0.0);
            let g = 0.5 * (x * q.sqrt() + r2 * (x / r).clamp(-1.0, 1.0).asin());
            [
                g - h * x,
                -q * q.sqrt() / 3.0 - 0.5 * h * x * x,
                0.5 * (k * x - x * x * x / 3.0),
                0.5 * (0.5 * k * x * x - 0.25 * x * x * x * x),
            ]
        };
        let (a, b) = (f(x1.clamp(-s, s)), f(x0.clamp(-s, s)));
        [a[0] - b[0], a[1] - b[1], a[2] - b[2], a[3] - b[3]]
    };
    let sub = |a: [f64; 4], b: [f64; 4]| [a[0] - b[0], a[1] - b[1], a[2] - b[2], a[3] - b[3]];
    let flip = |m: [f64; 4]| [m[0], m[1], -m[2], -m[3]];
    if y0 >= 0.0 {
        sub(strip(y0), strip(y1))
    } else if y1 <= 0.0 {
        flip(sub(strip(-y1), strip(-y0)))
    } else {
        let lo = flip(sub(strip(0.0), strip(-y0)));
        let hi = sub(strip(0.0), strip(y1));
        [lo[0] + hi[0], lo[1] + hi[1], lo[2] + hi[2], lo[3] + hi[3]]
    }
}

/// A vertical edge at `x` (relative to the circle centre) with `G(x)` precomputed.
#[derive(Clone, Copy)]
struct Edge {
    x: f64,
    g: f64,
}

/// A horizontal line at signed height `y` (relative to the centre), with `h = |y|`,
/// the half-chord `s` at `h` and `G(s)`.
#[derive(Clone, Copy, Default)]
struct Line {
    y: f64,
    h: f64,
    s: f64,
    gs: f64,
}

impl Line {
    fn new(y: f64, r: f64, g: &impl Fn(f64) -> f64) -> Self {
        let h = y.abs();
        let s = if h < r { (r * r - h * h).sqrt() } else { 0.0 };
        Line { y, h, s, gs: g(s) }
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

/// `round(full · clamp(v, 0, 1))` for a non-negative code range. Adding ½ and
/// truncating equals rounding (half away from zero) for non-negative values and
/// compiles to one conversion instruction, where `f32::round` is a library call on
/// baseline x86-64 (4× slower here). NaN maps to 0.
#[inline]
pub fn round_code(v: f32, full: f32) -> u32 {
    (v.clamp(0.0, 1.0) * full + 0.5) as u32
}

/// Converts a float frame to 8 bits per channel: `round(255 v)`, clamped to `[0, 255]`.
pub fn to_rgb8(frame: &Rgb32FImage) -> RgbImage {
    let data = frame
        .as_raw()
        .iter()
        .map(|&v| round_code(v, 255.0) as u8)
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
        .map(|&v| round_code(v, 65535.0) as u16)
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
    fn tent_response_sums_to_the_area_and_centroid_is_exact() {
        for (c, r) in [
            ([20.3, 19.7], 6.0),
            ([20.0, 20.0], 0.4),
            ([21.77, 18.13], 9.41),
        ] {
            let (mut s, mut sx, mut sy) = (0.0f64, 0.0f64, 0.0f64);
            disc_tent_visit(64, 64, c, r, |i, j, a| {
                s += a as f64;
                sx += a as f64 * i as f64;
                sy += a as f64 * j as f64;
            });
            let area = std::f64::consts::PI * r * r;
            assert!((s - area).abs() < 1e-5 * area, "r={r}: {s} vs {area}");
            // f32 values: relative 6e-8 each.
            assert!(
                (sx / s - c[0]).abs() < 1e-5 && (sy / s - c[1]).abs() < 1e-5,
                "r={r}"
            );
        }
    }

    #[test]
    fn tent_response_matches_supersampled_tent_integral() {
        // 800×800 samples over [i−1, i+1]²: error ≲ 2e-3 per node.
        let (c, r) = ([10.37, 9.81], 2.3);
        let mut exact = std::collections::HashMap::new();
        disc_tent_visit(32, 32, c, r, |i, j, a| {
            exact.insert((i, j), a as f64);
        });
        for (i, j) in [(10usize, 10usize), (8, 9), (12, 11), (10, 7), (13, 10)] {
            let n = 800;
            let mut acc = 0.0;
            for a in 0..n {
                for b in 0..n {
                    let x = i as f64 - 1.0 + 2.0 * (a as f64 + 0.5) / n as f64;
                    let y = j as f64 - 1.0 + 2.0 * (b as f64 + 0.5) / n as f64;
                    if (x - c[0]).powi(2) + (y - c[1]).powi(2) < r * r {
                        acc += (1.0 - (x - i as f64).abs()) * (1.0 - (y - j as f64).abs());
                    }
                }
            }
            acc *= 4.0 / (n * n) as f64;
            let e = exact.get(&(i, j)).copied().unwrap_or(0.0);
            assert!((e - acc).abs() < 2e-3, "({i},{j}): {e} vs {acc}");
        }
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
