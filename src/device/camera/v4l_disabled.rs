//! V4L2 cameras in a build without the `v4l` feature: the same API as the real module,
//! whose every call fails with an error saying how to rebuild with V4L2 support.
//! (nokhwa's V4L2 backend runs bindgen at build time and needs libclang, so the default
//! build leaves it out and needs no system library.)

use super::DEVICE;
use crate::device::{Camera, CameraFrame, DeviceError, DeviceResult, ErrorKind};

/// What to do to get V4L2 support.
pub const REBUILD_HINT: &str = "rebuild with `--features v4l` (needs libclang-dev: \
     apt-get install libclang-dev), or replay recorded frames with dir:PATH";

/// A V4L2 camera found by [`list`] (same fields as with the `v4l` feature).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CameraDescription {
    /// Index to pass to [`V4lCamera::open`].
    pub index: String,
    /// Human-readable name.
    pub name: String,
    /// Driver description.
    pub description: String,
}

fn not_built(cmd: &str) -> DeviceError {
    DeviceError::new(
        ErrorKind::Other,
        DEVICE,
        cmd,
        "this tactbench was built without V4L2 camera support (cargo feature `v4l`)",
    )
    .with_hint(REBUILD_HINT)
}

/// Always an error: this build has no V4L2 backend.
pub fn list() -> DeviceResult<Vec<CameraDescription>> {
    Err(not_built("list"))
}

/// A V4L2 camera; cannot be opened in this build.
pub struct V4lCamera {
    _never: std::convert::Infallible,
}

impl V4lCamera {
    /// Always an error naming the feature to enable.
    pub fn open(index: u32) -> DeviceResult<Self> {
        Err(not_built(&format!("open {index}")))
    }
}

impl Camera for V4lCamera {
    fn grab(&mut self) -> DeviceResult<CameraFrame> {
        match self._never {}
    }
}
