//! Camera images as the tracker sees them: an owned decoded [`Frame`] (8- or 16-bit
//! RGB/RGBA) and a borrowed, zero-copy [`FrameView`] over its samples.
//!
//! The tracker reads the interleaved samples directly inside its windows, so a frame
//! is never converted as a whole. Grayscale images are rejected: the layers are told
//! apart by colour only. Every load error names the file.

use std::path::Path;

use image::{DynamicImage, ImageBuffer, Rgb, RgbImage, Rgba, RgbaImage};

use super::VisionError;
use crate::sensor::CameraMapping;

/// Borrowed interleaved samples of an RGB or RGBA image, rows top to bottom, no padding.
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
        let (len, channels) = match pixels {
            Pixels::Rgb8(d) => (d.len(), 3),
            Pixels::Rgba8(d) => (d.len(), 4),
            Pixels::Rgb16(d) => (d.len(), 3),
            Pixels::Rgba16(d) => (d.len(), 4),
        };
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
            Pixels::Rgb8(_) | Pixels::Rgba8(_) => 8,
            Pixels::Rgb16(_) | Pixels::Rgba16(_) => 16,
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

/// An owned decoded colour image.
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
}

impl Frame {
    /// Converts a decoded image; grayscale and floating-point images are rejected.
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
            DynamicImage::ImageLuma8(_)
            | DynamicImage::ImageLumaA8(_)
            | DynamicImage::ImageLuma16(_)
            | DynamicImage::ImageLumaA16(_) => Err(VisionError::Grayscale {
                path: path.to_path_buf(),
            }),
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
        };
        FrameView {
            pixels,
            width_px: w,
            height_px: h,
        }
    }
}

/// Reads a PNG, JPEG or BMP colour image and checks its size against the camera.
///
/// Errors (each naming the file): missing or unreadable file, undecodable data,
/// grayscale or floating-point pixels, a size other than `[camera] width_px × height_px`.
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
    /// Reads a PNG, JPEG or BMP colour image of any size (`sensor init`: no sensor
    /// file yet). Errors name the file: missing or unreadable, undecodable, grayscale
    /// or floating-point pixels.
    pub fn open(path: &Path) -> Result<Frame, VisionError> {
        Frame::from_dynamic(decode(path)?, path)
    }
}
