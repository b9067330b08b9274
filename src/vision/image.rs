//! Camera images as the tracker sees them: an owned decoded [`Frame`] (8- or 16-bit
//! RGB/RGBA or greyscale) and a borrowed, zero-copy [`FrameView`] over its samples.
//!
//! The tracker reads the interleaved samples directly inside its windows, so a frame
//! is never converted as a whole. A greyscale sample `g` reads as the RGB pixel
//! `(g, g, g)`: the `dark` and `bright` scores (`∓(R + G + B)`) see `∓3g`, bit for bit
//! what they see in the grey image widened to RGB. Coloured layers (blue, red, green)
//! need colour: [`check_layers`] refuses them on a greyscale frame, naming the layer.
//! Every load error names the file.

use std::path::Path;

use image::{DynamicImage, GrayImage, ImageBuffer, Luma, Rgb, RgbImage, Rgba, RgbaImage};

use super::VisionError;
use crate::sensor::{CameraMapping, MarkerColor};

/// Borrowed interleaved samples of an image, rows top to bottom, no padding.
#[derive(Debug, Clone, Copy)]
pub enum Pixels<'a> {
    /// 8-bit RGB, 3 samples per pixel.
    Rgb8(&'a [u8]),
    /// 8-bit RGBA, 4 samples per pixel (alpha ignored).
    Rgba8(&'a [u8]),
    /// 16-bit RGB, 3 samples per pixel.
    Rgb16(&'a [u16]),
    /// 16-bit RGBA, 4 samples per pixel (alpha ignored).
    Rgba16(&'a [u16]),
    /// 8-bit greyscale, 1 sample per pixel (read as `(g, g, g)`).
    Gray8(&'a [u8]),
    /// 16-bit greyscale, 1 sample per pixel (read as `(g, g, g)`).
    Gray16(&'a [u16]),
}

impl Pixels<'_> {
    /// Samples per pixel: 1 (grey), 3 (RGB) or 4 (RGBA).
    pub fn channels(&self) -> usize {
        match self {
            Pixels::Gray8(_) | Pixels::Gray16(_) => 1,
            Pixels::Rgb8(_) | Pixels::Rgb16(_) => 3,
            Pixels::Rgba8(_) | Pixels::Rgba16(_) => 4,
        }
    }

    /// Whether the image is greyscale (no colour to tell coloured layers apart).
    pub fn is_gray(&self) -> bool {
        self.channels() == 1
    }
}

/// Refuses a greyscale frame when a layer is coloured (blue, red, green): its score is
/// a colour excess, which a greyscale frame cannot show. `layers` gives each layer's
/// name and colour in sensor order; the error names the first coloured one. `dark`
/// and `bright` layers read any frame.
pub fn check_layers<'n>(
    view: &FrameView<'_>,
    layers: impl IntoIterator<Item = (&'n str, MarkerColor)>,
) -> Result<(), VisionError> {
    match view.pixels().is_gray() {
        true => colour_layer(layers).map_or(Ok(()), Err),
        false => Ok(()),
    }
}

/// The error for the first coloured layer of `layers` (name, colour in sensor order)
/// on a greyscale frame, `None` when every layer is `dark` or `bright`. For frames
/// that arrive as RGB but carry no colour (a monochrome camera, a recorded greyscale
/// directory widened to RGB: [`FrameView::is_achromatic`]).
pub fn colour_layer<'n>(
    layers: impl IntoIterator<Item = (&'n str, MarkerColor)>,
) -> Option<VisionError> {
    layers
        .into_iter()
        .enumerate()
        .find(|(_, (_, c))| !c.is_brightness())
        .map(|(index, (name, color))| VisionError::GrayscaleColourLayer {
            layer: name.to_string(),
            index,
            color,
        })
}

/// A borrowed colour image with its size checked against its samples.
#[derive(Debug, Clone, Copy)]
pub struct FrameView<'a> {
    pixels: Pixels<'a>,
    width_px: u32,
    height_px: u32,
}

impl<'a> FrameView<'a> {
    /// Wraps raw samples; fails when the sample count is not `width × height × channels`.
    pub fn new(pixels: Pixels<'a>, width_px: u32, height_px: u32) -> Result<Self, VisionError> {
        let len = match pixels {
            Pixels::Rgb8(d) | Pixels::Rgba8(d) | Pixels::Gray8(d) => d.len(),
            Pixels::Rgb16(d) | Pixels::Rgba16(d) | Pixels::Gray16(d) => d.len(),
        };
        let channels = pixels.channels();
        let expected = width_px as usize * height_px as usize * channels;
        if len != expected {
            return Err(VisionError::BufferSize {
                width_px,
                height_px,
                channels,
                expected,
                found: len,
            });
        }
        Ok(FrameView {
            pixels,
            width_px,
            height_px,
        })
    }

    /// A view of an 8-bit RGB image (as grabbed by a [`crate::device::Camera`]).
    pub fn rgb8(image: &'a RgbImage) -> Self {
        FrameView {
            pixels: Pixels::Rgb8(image.as_raw()),
            width_px: image.width(),
            height_px: image.height(),
        }
    }

    /// A view of an 8-bit greyscale image.
    pub fn gray8(image: &'a GrayImage) -> Self {
        FrameView {
            pixels: Pixels::Gray8(image.as_raw()),
            width_px: image.width(),
            height_px: image.height(),
        }
    }

    /// A view of an 8-bit RGBA image.
    pub fn rgba8(image: &'a RgbaImage) -> Self {
        FrameView {
            pixels: Pixels::Rgba8(image.as_raw()),
            width_px: image.width(),
            height_px: image.height(),
        }
    }

    /// Bits per sample: 8 or 16. The colour scores of a 16-bit image are 257 times
    /// those of the same image in 8 bits (`v16 = 257 · v8`, as PNG widens samples).
    pub fn bit_depth(&self) -> u32 {
        match self.pixels {
            Pixels::Rgb8(_) | Pixels::Rgba8(_) | Pixels::Gray8(_) => 8,
            Pixels::Rgb16(_) | Pixels::Rgba16(_) | Pixels::Gray16(_) => 16,
        }
    }

    /// Whether the frame carries no colour: greyscale, or RGB(A) with `R = G = B` in
    /// every pixel (a greyscale recording widened to RGB).
    pub fn is_achromatic(&self) -> bool {
        fn grey<T: PartialEq>(data: &[T], c: usize) -> bool {
            data.chunks_exact(c).all(|p| p[0] == p[1] && p[1] == p[2])
        }
        match self.pixels {
            Pixels::Gray8(_) | Pixels::Gray16(_) => true,
            Pixels::Rgb8(d) => grey(d, 3),
            Pixels::Rgba8(d) => grey(d, 4),
            Pixels::Rgb16(d) => grey(d, 3),
            Pixels::Rgba16(d) => grey(d, 4),
        }
    }

    /// The samples.
    pub fn pixels(&self) -> Pixels<'a> {
        self.pixels
    }

    /// Width in pixels.
    pub fn width_px(&self) -> u32 {
        self.width_px
    }

    /// Height in pixels.
    pub fn height_px(&self) -> u32 {
        self.height_px
    }
}

/// An owned decoded image.
#[derive(Debug, Clone)]
pub enum Frame {
    /// 8-bit RGB.
    Rgb8(RgbImage),
    /// 8-bit RGBA.
    Rgba8(RgbaImage),
    /// 16-bit RGB (the simulator's ideal renders).
    Rgb16(ImageBuffer<Rgb<u16>, Vec<u16>>),
    /// 16-bit RGBA.
    Rgba16(ImageBuffer<Rgba<u16>, Vec<u16>>),
    /// 8-bit greyscale (grey + alpha is decoded to this, alpha dropped).
    Gray8(GrayImage),
    /// 16-bit greyscale (grey + alpha is decoded to this, alpha dropped).
    Gray16(ImageBuffer<Luma<u16>, Vec<u16>>),
}

impl Frame {
    /// Converts a decoded image; floating-point images are rejected. Grey + alpha
    /// becomes greyscale (alpha ignored, as for RGBA).
    pub fn from_dynamic(image: DynamicImage, path: &Path) -> Result<Frame, VisionError> {
        let kind = |k: &str| VisionError::UnsupportedPixels {
            path: path.to_path_buf(),
            kind: k.to_string(),
        };
        match image {
            DynamicImage::ImageRgb8(i) => Ok(Frame::Rgb8(i)),
            DynamicImage::ImageRgba8(i) => Ok(Frame::Rgba8(i)),
            DynamicImage::ImageRgb16(i) => Ok(Frame::Rgb16(i)),
            DynamicImage::ImageRgba16(i) => Ok(Frame::Rgba16(i)),
            DynamicImage::ImageLuma8(i) => Ok(Frame::Gray8(i)),
            DynamicImage::ImageLuma16(i) => Ok(Frame::Gray16(i)),
            i @ DynamicImage::ImageLumaA8(_) => Ok(Frame::Gray8(i.into_luma8())),
            i @ DynamicImage::ImageLumaA16(_) => Ok(Frame::Gray16(i.into_luma16())),
            DynamicImage::ImageRgb32F(_) | DynamicImage::ImageRgba32F(_) => {
                Err(kind("32-bit floating point"))
            }
            _ => Err(kind("unknown pixel format")),
        }
    }

    /// A zero-copy view.
    pub fn view(&self) -> FrameView<'_> {
        let (pixels, w, h) = match self {
            Frame::Rgb8(i) => (Pixels::Rgb8(i.as_raw()), i.width(), i.height()),
            Frame::Rgba8(i) => (Pixels::Rgba8(i.as_raw()), i.width(), i.height()),
            Frame::Rgb16(i) => (Pixels::Rgb16(i.as_raw()), i.width(), i.height()),
            Frame::Rgba16(i) => (Pixels::Rgba16(i.as_raw()), i.width(), i.height()),
            Frame::Gray8(i) => (Pixels::Gray8(i.as_raw()), i.width(), i.height()),
            Frame::Gray16(i) => (Pixels::Gray16(i.as_raw()), i.width(), i.height()),
        };
        FrameView {
            pixels,
            width_px: w,
            height_px: h,
        }
    }
}

/// Reads a PNG, JPEG or BMP image (8- or 16-bit RGB, RGBA or greyscale) and checks its
/// size against the camera.
///
/// Errors (each naming the file): missing or unreadable file, undecodable data,
/// floating-point pixels, a size other than `[camera] width_px × height_px`.
pub fn load_frame(path: &Path, camera: &CameraMapping) -> Result<Frame, VisionError> {
    let image = decode(path)?;
    if image.width() != camera.width_px || image.height() != camera.height_px {
        return Err(VisionError::WrongSize {
            path: path.to_path_buf(),
            found: [image.width(), image.height()],
            expected: [camera.width_px, camera.height_px],
        });
    }
    Frame::from_dynamic(image, path)
}

/// Opens and decodes an image file (format guessed from the content), its size
/// checked from the header first ([`crate::frame_size`]).
fn decode(path: &Path) -> Result<DynamicImage, VisionError> {
    use crate::frame_size::{open_capped, FrameSizeError};
    let reader = open_capped(path).map_err(|e| match e {
        FrameSizeError::Open { path, source } => VisionError::Open { path, source },
        // The header's message is the decoder's; Decode names the file once.
        FrameSizeError::Header { path, message } => VisionError::Decode { path, message },
        e => VisionError::Decode {
            path: path.to_path_buf(),
            message: e.to_string(),
        },
    })?;
    reader.decode().map_err(|e| VisionError::Decode {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

impl Frame {
    /// Reads a PNG, JPEG or BMP image (8- or 16-bit RGB, RGBA or greyscale) of any
    /// size (`sensor init`: no sensor file yet). Errors name the file: missing or
    /// unreadable, undecodable, floating-point pixels.
    pub fn open(path: &Path) -> Result<Frame, VisionError> {
        Frame::from_dynamic(decode(path)?, path)
    }
}
