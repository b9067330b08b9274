//! Cameras: a real V4L2 camera through `nokhwa` ([`v4l`]), and an image directory
//! replaying recorded frames ([`image_dir`]). Both implement [`Camera`]; [`open`]
//! picks one from a device spec (`0` = V4L2 index 0, `dir:PATH` = image directory).
//! The simulated backend (frames rendered from the virtual scene) lives with the
//! renderer.

pub mod image_dir;
pub mod v4l;

use std::path::PathBuf;

pub use image_dir::ImageDirCamera;
pub use v4l::V4lCamera;

use super::{Camera, DeviceError, DeviceResult, ErrorKind};

/// Device name in errors.
pub const DEVICE: &str = "camera";

/// Which camera to open, parsed from a device spec.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CameraSpec {
    /// A V4L2 device index (`/dev/videoN`).
    V4l(u32),
    /// A directory of recorded frames (`dir:PATH`).
    Dir(PathBuf),
}

impl CameraSpec {
    /// Parses `N` or `dir:PATH`.
    pub fn parse(spec: &str) -> DeviceResult<Self> {
        if let Some(p) = spec.strip_prefix("dir:") {
            if p.is_empty() {
                return Err(DeviceError::new(
                    ErrorKind::Other,
                    DEVICE,
                    format!("open {spec}"),
                    "`dir:` needs a directory path, e.g. dir:frames/",
                ));
            }
            return Ok(CameraSpec::Dir(PathBuf::from(p)));
        }
        spec.parse::<u32>().map(CameraSpec::V4l).map_err(|_| {
            DeviceError::new(
                ErrorKind::Other,
                DEVICE,
                format!("open {spec}"),
                format!("camera `{spec}` is neither a V4L2 index (0, 1, ...) nor dir:PATH"),
            )
        })
    }
}

/// Opens the camera a spec names. Image directories are opened without looping (the
/// end of the recording is an error).
pub fn open(spec: &CameraSpec) -> DeviceResult<Box<dyn Camera>> {
    match spec {
        CameraSpec::V4l(i) => Ok(Box::new(V4lCamera::open(*i)?)),
        CameraSpec::Dir(p) => Ok(Box::new(ImageDirCamera::open(p, false)?)),
    }
}
