//! Figure output shared by every plot: a [`Figure`] draws itself on any plotters
//! backend, and [`save_figure`] writes it as PNG (bitmap drawn into a buffer, encoded
//! with `image`) and SVG (text), so both files come from the same drawing code.
//!
//! Text uses DejaVu Sans from the `dejavu` crate, registered once as plotters'
//! `"sans-serif"` family through its `ab_glyph` backend: no system fonts, fontconfig
//! or freetype are needed, so plots look the same on every machine.
//!
//! PNGs are drawn through [`PngBackend`], plotters' bitmap backend with two primitives
//! replaced: text in the bundled font is rasterised here with `ab_glyph` on one exact
//! baseline (plotters' glue truncates each glyph's offset toward zero, so glyphs that
//! sit low — `.`, `,`, `-` — came out a pixel higher than the digits: "700·0"), and
//! wide strokes are drawn segment by segment (plotters fills one polygon around the
//! whole path, which leaves dotted seams where a path turns back on itself, as an
//! arrowhead's barbs do). SVG output is unchanged (text is SVG `<text>`).

use std::path::{Path, PathBuf};
use std::sync::Once;

use ab_glyph::{Font, FontRef, ScaleFont};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters_backend::{
    text_anchor::{HPos, VPos},
    BackendColor, BackendCoord, BackendStyle, BackendTextStyle, DrawingErrorKind,
};
use thiserror::Error;

/// Font family name every figure should use for text.
pub const FONT: &str = "sans-serif";

/// An error drawing or writing a figure.
#[derive(Debug, Error)]
pub enum PlotError {
    /// Drawing failed (plotters' message, which names the element).
    #[error("drawing {figure}: {message}")]
    Draw {
        /// File stem of the figure.
        figure: String,
        /// What plotters said.
        message: String,
    },
    /// Writing a file failed.
    #[error("{path}: {message}")]
    Write {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
}

/// The files one figure was written to.
#[derive(Debug, Clone, PartialEq)]
pub struct FigureFiles {
    /// The PNG file.
    pub png: PathBuf,
    /// The SVG file.
    pub svg: PathBuf,
}

/// Result of drawing on backend `DB`.
pub type FigureResult<DB> = Result<(), DrawingAreaErrorKind<<DB as DrawingBackend>::ErrorType>>;

/// A figure that can draw itself on any plotters backend.
pub trait Figure {
    /// Draws the whole figure on `root` (already sized; not yet filled).
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB>;
}

/// Registers the bundled font for [`FONT`]; idempotent, called by [`save_figure`].
pub fn register_fonts() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The bundled font is valid TrueType; a failure here would only mean plotters
        // falls back to drawing no text, never a crash, so the result is not fatal.
        let _ = plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular());
        let _ = plotters::style::register_font(FONT, FontStyle::Bold, dejavu::sans::bold());
    });
}

/// Draws `figure` at `size_px` (width, height) and writes `STEM.png` and `STEM.svg`
/// in `dir` (created if missing).
pub fn save_figure(
    figure: &impl Figure,
    dir: &Path,
    stem: &str,
    size_px: (u32, u32),
) -> Result<FigureFiles, PlotError> {
    register_fonts();
    std::fs::create_dir_all(dir).map_err(|e| PlotError::Write {
        path: dir.to_path_buf(),
        message: e.to_string(),
    })?;
    let draw_err = |e: String| PlotError::Draw {
        figure: stem.to_string(),
        message: e,
    };

    let png = dir.join(format!("{stem}.png"));
    let png_bytes = render_png(figure, size_px).map_err(draw_err)?;
    write_file(&png, &png_bytes)?;

    let svg = dir.join(format!("{stem}.svg"));
    let svg_text = render_svg(figure, size_px).map_err(draw_err)?;
    write_file(&svg, svg_text.as_bytes())?;
    Ok(FigureFiles { png, svg })
}

/// Draws `figure` into an RGB buffer and encodes it as PNG bytes.
pub fn render_png(figure: &impl Figure, size_px: (u32, u32)) -> Result<Vec<u8>, String> {
    register_fonts();
    let (w, h) = size_px;
    let mut rgb = vec![0u8; w as usize * h as usize * 3];
    {
        let root = PngBackend::new(&mut rgb, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        figure.draw(&root).map_err(|e| e.to_string())?;
        root.present().map_err(|e| e.to_string())?;
    }
    encode_png(&rgb, w, h)
}

/// Draws `figure` as SVG text.
pub fn render_svg(figure: &impl Figure, size_px: (u32, u32)) -> Result<String, String> {
    register_fonts();
    let mut text = String::new();
    {
        let root = SVGBackend::with_string(&mut text, size_px).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        figure.draw(&root).map_err(|e| e.to_string())?;
        root.present().map_err(|e| e.to_string())?;
    }
    Ok(text)
}

/// Encodes an RGB buffer as PNG bytes.
pub fn encode_png(rgb: &[u8], w: u32, h: u32) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image_rgb8(rgb, w, h)
        .map_err(|e| e.to_string())?;
    Ok(out)
}

/// The bundled font for a plotters family and style, `None` for any other family.
fn bundled_font(family: &str, style: FontStyle) -> Option<&'static FontRef<'static>> {
    static FONTS: std::sync::OnceLock<Option<(FontRef<'static>, FontRef<'static>)>> =
        std::sync::OnceLock::new();
    if family != FONT {
        return None;
    }
    let fonts = FONTS.get_or_init(|| {
        let regular = FontRef::try_from_slice(dejavu::sans::regular()).ok()?;
        let bold = FontRef::try_from_slice(dejavu::sans::bold()).ok()?;
        Some((regular, bold))
    });
    let (regular, bold) = fonts.as_ref()?;
    Some(if matches!(style, FontStyle::Bold) {
        bold
    } else {
        regular
    })
}

/// Plotters' bitmap backend over an RGB buffer, with exact text in the bundled font
/// and seam-free wide strokes (see the module docs). Everything else is the bitmap
/// backend's.
pub struct PngBackend<'a> {
    inner: BitMapBackend<'a>,
}

impl<'a> PngBackend<'a> {
    /// A backend drawing into `rgb` (`w × h × 3` bytes).
    pub fn new(rgb: &'a mut [u8], size: (u32, u32)) -> Self {
        PngBackend {
            inner: BitMapBackend::with_buffer(rgb, size),
        }
    }
}

/// The pixels of `text` drawn with its first character's pen at x = 0 and the
/// baseline at y = `baseline`: `(x, y, coverage)`.
pub fn rasterize_text(
    font: &FontRef<'_>,
    size: f32,
    baseline: f32,
    text: &str,
) -> Vec<(i32, i32, f32)> {
    let scaled = font.as_scaled(size);
    let mut out = Vec::new();
    let mut pen = 0f32;
    let mut prev = None;
    for c in text.chars() {
        let id = scaled.glyph_id(c);
        if let Some(p) = prev {
            pen += scaled.kern(p, id);
        }
        prev = Some(id);
        let glyph = id.with_scale_and_position(size, ab_glyph::point(pen, baseline));
        if let Some(q) = font.outline_glyph(glyph) {
            let b = q.px_bounds();
            let (x0, y0) = (b.min.x as i32, b.min.y as i32);
            q.draw(|x, y, cov| {
                if cov > 0.0 {
                    out.push((x0 + x as i32, y0 + y as i32, cov.min(1.0)));
                }
            });
        }
        pen += scaled.h_advance(id);
    }
    out
}

impl DrawingBackend for PngBackend<'_> {
    type ErrorType = <BitMapBackend<'static> as DrawingBackend>::ErrorType;

    fn get_size(&self) -> (u32, u32) {
        self.inner.get_size()
    }
    fn ensure_prepared(&mut self) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.ensure_prepared()
    }
    fn present(&mut self) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.present()
    }
    fn draw_pixel(
        &mut self,
        point: BackendCoord,
        color: BackendColor,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.draw_pixel(point, color)
    }
    fn draw_line<S: BackendStyle>(
        &mut self,
        from: BackendCoord,
        to: BackendCoord,
        style: &S,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.draw_line(from, to, style)
    }
    fn draw_rect<S: BackendStyle>(
        &mut self,
        upper_left: BackendCoord,
        bottom_right: BackendCoord,
        style: &S,
        fill: bool,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.draw_rect(upper_left, bottom_right, style, fill)
    }
    fn draw_path<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
        &mut self,
        path: I,
        style: &S,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        let width = style.stroke_width();
        if width <= 1 || style.color().alpha == 0.0 {
            return self.inner.draw_path(path, style);
        }
        // One quad per segment and a disc at each inner joint: no seams where the path
        // turns back.
        let pts: Vec<BackendCoord> = path.into_iter().collect();
        let half = width as f64 / 2.0;
        let color = style.color();
        for (i, w) in pts.windows(2).enumerate() {
            let (a, b) = (w[0], w[1]);
            let (dx, dy) = ((b.0 - a.0) as f64, (b.1 - a.1) as f64);
            let len = dx.hypot(dy);
            if len == 0.0 {
                continue;
            }
            let (nx, ny) = (-dy / len * half, dx / len * half);
            let q = |p: BackendCoord, s: f64| {
                (
                    (p.0 as f64 + s * nx).round() as i32,
                    (p.1 as f64 + s * ny).round() as i32,
                )
            };
            self.inner
                .fill_polygon([q(a, 1.0), q(b, 1.0), q(b, -1.0), q(a, -1.0)], &color)?;
            if i + 2 < pts.len() && width > 2 {
                self.inner
                    .draw_circle(b, (half.floor() as u32).max(1), &color, true)?;
            }
        }
        Ok(())
    }
    fn draw_circle<S: BackendStyle>(
        &mut self,
        center: BackendCoord,
        radius: u32,
        style: &S,
        fill: bool,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.draw_circle(center, radius, style, fill)
    }
    fn fill_polygon<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
        &mut self,
        vert: I,
        style: &S,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.fill_polygon(vert, style)
    }
    fn draw_text<TStyle: BackendTextStyle>(
        &mut self,
        text: &str,
        style: &TStyle,
        pos: BackendCoord,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        let Some(font) = bundled_font(style.family().as_str(), style.style()) else {
            return self.inner.draw_text(text, style, pos);
        };
        let color = style.color();
        if color.alpha == 0.0 {
            return Ok(());
        }
        // The anchor box and the baseline (half the size below the box's top) are
        // plotters' own, so text lands where the charts' layout expects it.
        let ((min_x, min_y), (max_x, max_y)) = style
            .layout_box(text)
            .map_err(|e| DrawingErrorKind::FontError(Box::new(e)))?;
        let (width, height) = (max_x - min_x, max_y - min_y);
        let dx = match style.anchor().h_pos {
            HPos::Left => 0,
            HPos::Right => -width,
            HPos::Center => -width / 2,
        };
        let dy = match style.anchor().v_pos {
            VPos::Top => 0,
            VPos::Center => -height / 2,
            VPos::Bottom => -height,
        };
        let size = style.size() as f32;
        let trans = style.transform();
        let (w, h) = self.get_size();
        // A whole-pixel baseline keeps flat glyph bottoms crisp.
        for (x, y, cov) in rasterize_text(font, size, (size / 2.0).round(), text) {
            let (x, y) = trans.transform(x + dx - min_x, y + dy - min_y);
            let (x, y) = (pos.0 + x, pos.1 + y);
            if x >= 0 && x < w as i32 && y >= 0 && y < h as i32 {
                self.inner.draw_pixel((x, y), color.mix(cov as f64))?;
            }
        }
        Ok(())
    }
    fn blit_bitmap(
        &mut self,
        pos: BackendCoord,
        size: (u32, u32),
        src: &[u8],
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.inner.blit_bitmap(pos, size, src)
    }
}

/// PNG encoding through the `image` crate's encoder trait.
trait WriteRgb8 {
    fn write_image_rgb8(self, rgb: &[u8], w: u32, h: u32) -> image::ImageResult<()>;
}

impl<W: std::io::Write> WriteRgb8 for image::codecs::png::PngEncoder<W> {
    fn write_image_rgb8(self, rgb: &[u8], w: u32, h: u32) -> image::ImageResult<()> {
        use image::ImageEncoder;
        self.write_image(rgb, w, h, image::ExtendedColorType::Rgb8)
    }
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<(), PlotError> {
    std::fs::write(path, bytes).map_err(|e| PlotError::Write {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A line y = x² over [0, 1] with a title and labelled axes.
    struct Parabola;

    impl Figure for Parabola {
        fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
            let mut chart = ChartBuilder::on(root)
                .caption("parabola", (FONT, 20))
                .margin(10)
                .x_label_area_size(30)
                .y_label_area_size(40)
                .build_cartesian_2d(0.0..1.0, 0.0..1.0)?;
            chart.configure_mesh().x_desc("x").y_desc("y").draw()?;
            chart.draw_series(LineSeries::new(
                (0..=20).map(|i| {
                    let x = i as f64 / 20.0;
                    (x, x * x)
                }),
                &BLUE,
            ))?;
            Ok(())
        }
    }

    #[test]
    fn figure_is_written_as_decodable_png_and_svg_with_text() {
        let dir = tempfile::tempdir().unwrap();
        let files = save_figure(&Parabola, dir.path(), "parabola", (320, 240)).unwrap();
        let img = image::open(&files.png).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (320, 240));
        // Something other than the white background was drawn: axes, text, the line.
        let dark = img
            .pixels()
            .filter(|p| p.0.iter().all(|&c| c < 128))
            .count();
        let blue = img
            .pixels()
            .filter(|p| p.0[2] > 200 && p.0[0] < 80 && p.0[1] < 80)
            .count();
        assert!(dark > 100, "only {dark} dark pixels: text/axes missing");
        assert!(blue > 50, "only {blue} blue pixels: the line is missing");
        let svg = std::fs::read_to_string(&files.svg).unwrap();
        assert!(svg.starts_with("<svg"), "{}", &svg[..40.min(svg.len())]);
        assert!(
            svg.contains("parabola"),
            "caption text missing from the SVG"
        );
    }

    /// A text label drawn at a given place.
    struct Label(&'static str, f64);

    impl Figure for Label {
        fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
            root.draw(&Text::new(self.0, (10, 10), (FONT, self.1).into_font()))?;
            Ok(())
        }
    }

    /// Ink of a PNG: per column, the (first, last) row darker than mid-grey.
    fn ink_columns(png: &[u8]) -> Vec<Option<(u32, u32)>> {
        let img = image::load_from_memory(png).unwrap().to_rgb8();
        (0..img.width())
            .map(|x| {
                let rows: Vec<u32> = (0..img.height())
                    .filter(|&y| img.get_pixel(x, y).0[0] < 128)
                    .collect();
                Some((*rows.first()?, *rows.last()?))
            })
            .collect()
    }

    /// Runs of inked columns: (first row, last row) of each glyph, left to right.
    fn glyph_rows(png: &[u8]) -> Vec<(u32, u32)> {
        let mut out: Vec<(u32, u32)> = Vec::new();
        let mut inside = false;
        for c in ink_columns(png) {
            match (c, inside) {
                (Some((t, b)), true) => {
                    let last = out.last_mut().unwrap();
                    *last = (last.0.min(t), last.1.max(b));
                }
                (Some(tb), false) => {
                    out.push(tb);
                    inside = true;
                }
                (None, _) => inside = false,
            }
        }
        out
    }

    /// plotters' own ab_glyph glue truncated each glyph's vertical offset toward zero,
    /// drawing '.' a pixel or two above the digits' baseline at odd sizes ("700·0").
    #[test]
    fn png_decimal_point_sits_on_the_baseline_at_every_size() {
        for size in [11.0, 12.0, 13.0, 14.0, 15.0, 17.0, 20.0] {
            let png = render_png(&Label("0.5", size), (120, 60)).unwrap();
            let g = glyph_rows(&png);
            assert_eq!(g.len(), 3, "size {size}: glyphs {g:?}");
            let (zero, dot, five) = (g[0], g[1], g[2]);
            // The point's ink ends on the digits' baseline row, and is a small mark
            // near it (not raised to mid-height).
            assert_eq!(
                dot.1, zero.1,
                "size {size}: '.' bottom {} vs '0' bottom {}",
                dot.1, zero.1
            );
            assert!(
                (dot.1 as i64 - five.1 as i64).abs() <= 1,
                "size {size}: {g:?}"
            );
            assert!(dot.0 > zero.0 + (zero.1 - zero.0) / 2, "size {size}: {g:?}");
        }
    }

    /// A wide arrow drawn as shaft + filled head: the head's interior is solid ink
    /// (plotters' one-polygon stroke of a path that turns back left dotted seams).
    #[test]
    fn png_arrowheads_are_filled_and_wide_paths_have_no_seams() {
        struct Arrow;
        impl Figure for Arrow {
            fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> FigureResult<DB> {
                root.draw(&PathElement::new(
                    vec![(10, 50), (150, 50)],
                    ShapeStyle::from(&BLACK).stroke_width(3),
                ))?;
                root.draw(&Polygon::new(
                    vec![(190, 50), (150, 30), (150, 70)],
                    BLACK.filled(),
                ))?;
                // A path that turns back on itself, as the old arrow barbs did.
                root.draw(&PathElement::new(
                    vec![(20, 90), (180, 90), (160, 80), (180, 90), (160, 100)],
                    ShapeStyle::from(&BLACK).stroke_width(2),
                ))?;
                Ok(())
            }
        }
        let png = render_png(&Arrow, (200, 120)).unwrap();
        let img = image::load_from_memory(&png).unwrap().to_rgb8();
        let dark = |x: u32, y: u32| img.get_pixel(x, y).0[0] < 100;
        // Every pixel well inside the head's triangle is ink.
        for x in 153..185 {
            let half = (70.0 - 30.0) / 2.0 * (190.0 - x as f64) / 40.0;
            for y in (50.0 - half + 1.5).ceil() as u32..=(50.0 + half - 1.5).floor() as u32 {
                assert!(dark(x, y), "hole in the arrowhead at ({x}, {y})");
            }
        }
        // The doubled-back barb is a continuous line: every column 162..178 has ink
        // between rows 80 and 90.
        for x in 162..178 {
            assert!(
                (80..=91).any(|y| dark(x, y)),
                "gap in the barb at column {x}"
            );
        }
        // The shaft's rows are solid along its length.
        for x in 12..148 {
            assert!(dark(x, 50), "gap in the shaft at column {x}");
        }
    }
}

/// The symbol of one legend entry drawn by [`legend_strip`].
#[derive(Debug, Clone, Copy)]
pub enum LegendGlyph {
    /// A filled square (bars, bands).
    Swatch(RGBColor),
    /// A solid line.
    Line(RGBColor),
    /// A dashed line.
    Dashed(RGBColor),
    /// A filled circle (points).
    Dot(RGBColor),
    /// An open triangle (points).
    Triangle(RGBColor),
    /// A cross (flags).
    Cross(RGBColor),
    /// A vertical error bar with caps (means ± SD).
    ErrorBar(RGBColor),
}

/// Height of one row of a [`legend_strip`], pixels.
pub const LEGEND_ROW_PX: u32 = 22;

/// Rows [`legend_strip`] needs for `entries` on a strip `width_px` wide (the same
/// estimate it lays out with: 7.5 px per character at 13 px type).
pub fn legend_rows(entries: &[(LegendGlyph, String)], width_px: u32) -> u32 {
    let mut rows = 1;
    let mut x = 10.0;
    for (_, label) in entries {
        let w = 34.0 + 7.5 * label.chars().count() as f64 + 18.0;
        if x + w > width_px as f64 && x > 10.0 {
            rows += 1;
            x = 10.0;
        }
        x += w;
    }
    rows
}

/// Draws a legend as rows of entries across `area` (a strip outside the plotting
/// area, so no entry ever covers data), wrapping when a row is full.
pub fn legend_strip<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    entries: &[(LegendGlyph, String)],
) -> FigureResult<DB> {
    let width = area.dim_in_pixel().0 as f64;
    let style = TextStyle::from((FONT, 13).into_font()).color(&BLACK);
    let (mut x, mut row) = (10.0f64, 0i32);
    for (glyph, label) in entries {
        let w = 34.0 + 7.5 * label.chars().count() as f64 + 18.0;
        if x + w > width && x > 10.0 {
            row += 1;
            x = 10.0;
        }
        let y = row * LEGEND_ROW_PX as i32 + LEGEND_ROW_PX as i32 / 2;
        let x0 = x as i32;
        match *glyph {
            LegendGlyph::Swatch(c) => area.draw(&Rectangle::new(
                [(x0, y - 6), (x0 + 22, y + 6)],
                Color::filled(&c),
            ))?,
            LegendGlyph::Line(c) => area.draw(&PathElement::new(
                [(x0, y), (x0 + 24, y)],
                Color::stroke_width(&c, 2),
            ))?,
            LegendGlyph::Dashed(c) => {
                for k in 0..3 {
                    area.draw(&PathElement::new(
                        [(x0 + 9 * k, y), (x0 + 9 * k + 5, y)],
                        Color::stroke_width(&c, 2),
                    ))?;
                }
            }
            LegendGlyph::Dot(c) => area.draw(&Circle::new((x0 + 12, y), 4, Color::filled(&c)))?,
            LegendGlyph::Triangle(c) => area.draw(&TriangleMarker::new(
                (x0 + 12, y),
                5,
                Color::stroke_width(&c, 1),
            ))?,
            LegendGlyph::Cross(c) => {
                area.draw(&Cross::new((x0 + 12, y), 5, Color::stroke_width(&c, 3)))?
            }
            LegendGlyph::ErrorBar(c) => {
                let st = Color::stroke_width(&c, 2);
                area.draw(&PathElement::new([(x0 + 12, y - 7), (x0 + 12, y + 7)], st))?;
                area.draw(&PathElement::new([(x0 + 8, y - 7), (x0 + 16, y - 7)], st))?;
                area.draw(&PathElement::new([(x0 + 8, y + 7), (x0 + 16, y + 7)], st))?;
                area.draw(&Circle::new((x0 + 12, y), 3, Color::filled(&c)))?;
            }
        }
        area.draw(&Text::new(label.clone(), (x0 + 32, y - 7), style.clone()))?;
        x += w;
    }
    Ok(())
}

/// `root` with `title` on top and `entries` in a [`legend_strip`] below it: the area
/// left for the plot. Every report and comparison figure with a legend draws it this
/// way, so no legend entry ever covers data and every colour the figure uses is keyed.
pub fn titled_with_legend<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    entries: &[(LegendGlyph, String)],
) -> Result<DrawingArea<DB, Shift>, DrawingAreaErrorKind<DB::ErrorType>> {
    let area = root.titled(title, (FONT, 20))?;
    let rows = legend_rows(entries, area.dim_in_pixel().0);
    let (strip, area) = area.split_vertically(rows * LEGEND_ROW_PX + 8);
    legend_strip(&strip, entries)?;
    Ok(area)
}
