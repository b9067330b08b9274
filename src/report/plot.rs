//! Figure output shared by every plot: a [`Figure`] draws itself on any plotters
//! backend, and [`save_figure`] writes it as PNG (bitmap drawn into a buffer, encoded
//! with `image`) and SVG (text), so both files come from the same drawing code.
//!
//! Text uses DejaVu Sans from the `dejavu` crate, registered once as plotters'
//! `"sans-serif"` family through its `ab_glyph` backend: no system fonts, fontconfig
//! or freetype are needed, so plots look the same on every machine.

use std::path::{Path, PathBuf};
use std::sync::Once;

use plotters::coord::Shift;
use plotters::prelude::*;
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
        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        figure.draw(&root).map_err(|e| e.to_string())?;
        root.present().map_err(|e| e.to_string())?;
    }
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image_rgb8(&rgb, w, h)
        .map_err(|e| e.to_string())?;
    Ok(out)
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
}
