//! The size cap of decoded camera frames. Every image file that `track`, `calibrate`,
//! `sensor init`, `run` (its reference checks) or a recorded-frames camera (`dir:`)
//! decodes is measured from its header first ([`open_capped`]) and refused past
//! [`MAX_FRAME_PIXELS`] before a byte of pixels is decoded; the decoder then runs with
//! `image::Limits` at the same size, so a header that lies is stopped by the decoder's
//! own checks. (Before: a 108-megapixel frame was decoded and tracked at 2.43 GB.)
//!
//! Depends on nothing in the crate, so that `vision` and `device::camera` share it.

use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use image::{ImageReader, Limits};
use thiserror::Error;

/// Largest decoded frame, pixels: an 8K UHD frame (7680 × 4320), four times the
/// largest (4K) cameras tactile sensors use; the tracker needs about 22 bytes per
/// pixel of a colour frame (measured: 2.43 GB at 108 megapixels), so this keeps one
/// frame under 1 GB.
pub const MAX_FRAME_PIXELS: u64 = 7680 * 4320;

/// Largest side, pixels (as `[camera] width_px` / `height_px`).
pub const MAX_FRAME_SIDE_PX: u32 = 65_535;

/// The decoder's allocation limit, bytes: the largest frame at 16-bit RGBA (8 bytes
/// per pixel).
pub const MAX_DECODE_BYTES: u64 = MAX_FRAME_PIXELS * 8;

/// Why an image file was not opened for decoding. Every variant names the file.
#[derive(Debug, Error)]
pub enum FrameSizeError {
    /// The file could not be opened or read.
    #[error("cannot open image {path}: {source}")]
    Open {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The header could not be read (not an image, or a format we do not read).
    #[error("cannot decode image {path}: {message}")]
    Header {
        /// The file.
        path: PathBuf,
        /// The decoder's message.
        message: String,
    },
    /// The image is larger than [`MAX_FRAME_PIXELS`] or [`MAX_FRAME_SIDE_PX`].
    #[error(
        "{path}: image is {width}×{height} px ({megapixels:.1} megapixels), past the cap of \
         {cap_mp:.1} megapixels ({cap} px, sides up to {side} px) for a camera frame: decoding \
         and tracking it would take about {gb:.1} GB; crop it to the sensor or downscale it \
         (docs/limits.md)",
        megapixels = *width as f64 * *height as f64 / 1e6,
        cap_mp = MAX_FRAME_PIXELS as f64 / 1e6,
        cap = MAX_FRAME_PIXELS,
        side = MAX_FRAME_SIDE_PX,
        gb = *width as f64 * *height as f64 * 22.5 / 1e9
    )]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// Width from the header, px.
        width: u32,
        /// Height from the header, px.
        height: u32,
    },
}

/// Checks a frame's dimensions against the caps.
pub fn check_dimensions(path: &Path, width: u32, height: u32) -> Result<(), FrameSizeError> {
    if width as u64 * height as u64 > MAX_FRAME_PIXELS
        || width > MAX_FRAME_SIDE_PX
        || height > MAX_FRAME_SIDE_PX
    {
        Err(FrameSizeError::TooLarge {
            path: path.to_path_buf(),
            width,
            height,
        })
    } else {
        Ok(())
    }
}

fn open(path: &Path) -> Result<ImageReader<BufReader<File>>, FrameSizeError> {
    let io = |source| FrameSizeError::Open {
        path: path.to_path_buf(),
        source,
    };
    ImageReader::open(path)
        .map_err(io)?
        .with_guessed_format()
        .map_err(io)
}

/// Opens an image file for decoding (format guessed from the content) after reading
/// its dimensions from the header and checking them ([`check_dimensions`]); the reader
/// carries decoder limits at the cap.
pub fn open_capped(path: &Path) -> Result<ImageReader<BufReader<File>>, FrameSizeError> {
    let (width, height) = open(path)?
        .into_dimensions()
        .map_err(|e| FrameSizeError::Header {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
    check_dimensions(path, width, height)?;
    let mut reader = open(path)?;
    let mut limits = Limits::default();
    limits.max_image_width = Some(MAX_FRAME_SIDE_PX);
    limits.max_image_height = Some(MAX_FRAME_SIDE_PX);
    // The decoder's own buffers come on top of the image's: leave it room.
    limits.max_alloc = Some(MAX_DECODE_BYTES + (64 << 20));
    reader.limits(limits);
    Ok(reader)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dimensions_past_the_cap_are_refused_naming_the_size() {
        let p = Path::new("big.png");
        assert!(check_dimensions(p, 7680, 4320).is_ok());
        assert!(check_dimensions(p, 65_535, 500).is_ok());
        let e = check_dimensions(p, 12_000, 9_000).unwrap_err().to_string();
        assert!(
            e.contains("big.png") && e.contains("12000×9000 px") && e.contains("108.0 megapixels"),
            "{e}"
        );
        assert!(check_dimensions(p, 70_000, 10).is_err());
    }
}
