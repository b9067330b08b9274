//! Marker vision: colour separation, sub-pixel centroids, the reference layout and
//! per-window / frame-to-frame tracking with per-marker status (paper Section II-A).
//!
//! Pipeline:
//! 1. [`load_frame`] reads a PNG/JPEG/BMP image (8- or 16-bit RGB/RGBA or greyscale)
//!    and checks its size against `[camera]`; [`FrameView`] borrows any such buffer
//!    (e.g. a [`crate::device::CameraFrame`]) without copying. A greyscale frame serves
//!    `dark` and `bright` layers; a coloured layer on it is refused by name.
//! 2. [`detect`] finds every layer's markers in an unloaded frame (anywhere, no grid
//!    assumed), refines them to sub-pixel centroids and, when the layer has a grid in
//!    sensor.toml, matches them to its nodes (marker id = row-major grid index).
//!    The result is a [`Reference`]; grid nodes without a marker and blobs without a
//!    node are listed in it.
//! 3. [`Tracker::track`] measures one frame against the reference, allocation-free,
//!    and gives every marker a [`MarkerStatus`]. Reference and frames may differ in
//!    bit depth (the reference's levels are rescaled to the frame's).
//!
//! [`camera`] holds the camera models (Brown–Conrady distortion, the per-layer
//! calibration `camera.toml`, [`PixelMapping`]: the sensor file's linear `[camera]`
//! mapping or a calibration) and [`calibrate`] fits a calibration to an unloaded frame
//! (`tactbench calibrate`); [`detect_mapped`], [`write_tracks_mapped`] and
//! [`Tracker::displacement_records_mapped`] convert pixels with a calibration.
//!
//! [`ReferenceHealth`] measures a reference against the sensor file (found markers per
//! layer, marker pitch, centre, frame levels) and names the likely cause when markers
//! are missing (scale, origin, colour, exposure).
//!
//! Centroids are the centre of mass of a colour score after local background
//! removal, in a window re-centred on the marker (see `window.rs` for the equations).
//! Pixel `(i, j)` covers `[i − 0.5, i + 0.5] × [j − 0.5, j + 0.5]`: a centroid of
//! `(i, j)` is the centre of that pixel, as in [`crate::sensor::CameraMapping`].

use std::fmt;
use std::path::PathBuf;

use thiserror::Error;

pub mod calibrate;
pub mod camera;
mod channels;
mod contrast;
mod detect;
mod health;
mod image;
pub mod onboard;
mod output;
mod prefetch;
mod track;
mod window;

pub use self::calibrate::{calibrate, CalibrateConfig, CalibrationError, CalibrationFit};
pub use self::camera::{BrownConrady, CameraCalibration, PixelMapping};
pub use self::channels::bgr_sensor;
pub use self::detect::{
    detect, detect_mapped, DetectConfig, LayerReference, MissingMarker, Reference, ReferenceMarker,
    Saturation, UnmatchedBlob,
};
pub use self::health::{LayerHealth, ReferenceHealth, ORIGIN_TOLERANCE, SCALE_TOLERANCE};
pub use self::image::{check_layers, colour_layer, load_frame, Frame, FrameView, Pixels};
pub use self::output::{
    write_tracks, write_tracks_mapped, write_tracks_mapped_to, write_tracks_to, TRACK_EXTRA_COLUMNS,
};
pub use self::prefetch::{decode_ahead, decoder_threads};
pub use self::track::{
    MarkerTrack, StatusCounts, TrackConfig, TrackMode, Tracker, DEFAULT_APPEARANCE_TOLERANCE,
};

/// An error of the vision module. File errors name the file.
#[derive(Debug, Error)]
pub enum VisionError {
    /// The image file could not be opened.
    #[error("cannot open image {path}: {source}")]
    Open {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The image could not be decoded.
    #[error("cannot decode image {path}: {message}")]
    Decode {
        /// The file.
        path: PathBuf,
        /// The decoder's message.
        message: String,
    },
    /// A coloured layer on a greyscale frame: its markers are told apart by colour.
    #[error("layer {layer} (layers[{index}].color = \"{color}\") needs a colour image, but the frame is greyscale: a greyscale frame serves only dark and bright layers")]
    GrayscaleColourLayer {
        /// The layer's name.
        layer: String,
        /// Its index in the sensor file.
        index: usize,
        /// Its colour (blue, red or green).
        color: crate::sensor::MarkerColor,
    },
    /// A pixel format the tracker does not read.
    #[error("{path}: unsupported pixel format ({kind}): expected 8- or 16-bit RGB or RGBA")]
    UnsupportedPixels {
        /// The file.
        path: PathBuf,
        /// What was found.
        kind: String,
    },
    /// The image size disagrees with the sensor's `[camera]`.
    #[error("{path}: image is {}×{} px but [camera] says {}×{} px", found[0], found[1], expected[0], expected[1])]
    WrongSize {
        /// The file.
        path: PathBuf,
        /// Width, height found, px.
        found: [u32; 2],
        /// Width, height from sensor.toml, px.
        expected: [u32; 2],
    },
    /// A raw buffer's length does not match its stated size.
    #[error("pixel buffer holds {found} samples but {width_px}×{height_px} px × {channels} channels needs {expected}")]
    BufferSize {
        /// Width, px.
        width_px: u32,
        /// Height, px.
        height_px: u32,
        /// Samples per pixel.
        channels: usize,
        /// Expected sample count.
        expected: usize,
        /// Actual sample count.
        found: usize,
    },
    /// A frame's size differs from the reference's.
    #[error("frame is {}×{} px but the reference is {}×{} px", found[0], found[1], expected[0], expected[1])]
    FrameSize {
        /// Width, height of the frame, px.
        found: [u32; 2],
        /// Width, height of the reference, px.
        expected: [u32; 2],
    },
    /// No marker of any layer was found in the reference image.
    #[error("no markers found in the reference image (layers searched: {layers}): nothing in the frame stands out as a marker of that color; check each layer's color against the frame (dark: dark dots on a lit gel; bright: light pins or dots on a dark skin; blue, red, green: coloured markers), [camera] roi_px and the exposure")]
    NoMarkers {
        /// The layers searched: `name: layers[i].color = "color"`, comma-separated.
        layers: String,
    },
}

/// The outcome of tracking one marker in one frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MarkerStatus {
    /// Measured; the displacement is trusted.
    Ok,
    /// Not found: no signal, too weak, outside the image, missing from the reference,
    /// its window crosses the border of the sensor file's `[camera] roi_px`, or its
    /// window ended on a blob that belongs to a nearer-predicted neighbour.
    Lost,
    /// Its window converged onto the same blob as a neighbour's (or onto a blob with
    /// about twice the reference signal), or another layer's marker overlaps it too
    /// much: two markers merged in the image.
    Merged,
    /// Found, but not trusted: its displacement disagrees with its neighbours', or
    /// its appearance changed against the reference (its signal differs from its
    /// neighbours': part of it covered, a blob of another size or contrast).
    Outlier,
}

impl MarkerStatus {
    /// All statuses, in report order.
    pub const ALL: [MarkerStatus; 4] = [
        MarkerStatus::Ok,
        MarkerStatus::Lost,
        MarkerStatus::Merged,
        MarkerStatus::Outlier,
    ];

    /// The name written in CSV files.
    pub fn name(self) -> &'static str {
        match self {
            MarkerStatus::Ok => "ok",
            MarkerStatus::Lost => "lost",
            MarkerStatus::Merged => "merged",
            MarkerStatus::Outlier => "outlier",
        }
    }
}

impl fmt::Display for MarkerStatus {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}
