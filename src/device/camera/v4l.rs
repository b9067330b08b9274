//! Real cameras through `nokhwa`'s V4L2 backend (Linux). With no camera attached the
//! query returns an empty list and opening fails; both are reported as a clear
//! [`ErrorKind::Disconnected`] error naming the index and what was found.

use std::time::SystemTime;

use nokhwa::pixel_format::RgbFormat;
use nokhwa::utils::{ApiBackend, CameraIndex, RequestedFormat, RequestedFormatType};

use super::DEVICE;
use crate::device::{Camera, CameraFrame, DeviceError, DeviceResult, ErrorKind};

/// A V4L2 camera found by [`list`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CameraDescription {
    /// Index to pass to [`V4lCamera::open`].
    pub index: String,
    /// Human-readable name.
    pub name: String,
    /// Driver description.
    pub description: String,
}

/// Lists V4L2 cameras (an empty list when there are none).
pub fn list() -> DeviceResult<Vec<CameraDescription>> {
    let found = nokhwa::query(ApiBackend::Video4Linux).map_err(|e| {
        DeviceError::new(
            ErrorKind::Other,
            DEVICE,
            "list",
            format!("cannot query V4L2 cameras: {e}"),
        )
    })?;
    Ok(found
        .iter()
        .map(|c| CameraDescription {
            index: c.index().to_string(),
            name: c.human_name(),
            description: c.description().to_string(),
        })
        .collect())
}

/// An open V4L2 camera streaming RGB frames.
pub struct V4lCamera {
    camera: nokhwa::Camera,
    index: u32,
}

impl V4lCamera {
    /// Opens `/dev/video<index>` at its highest frame rate and starts streaming.
    pub fn open(index: u32) -> DeviceResult<Self> {
        let cmd = format!("open {index}");
        let none_found = || {
            let n = list().map(|l| l.len()).unwrap_or(0);
            format!("{n} V4L2 camera(s) found")
        };
        let format =
            RequestedFormat::new::<RgbFormat>(RequestedFormatType::AbsoluteHighestFrameRate);
        let mut camera = nokhwa::Camera::new(CameraIndex::Index(index), format).map_err(|e| {
            DeviceError::new(
                ErrorKind::Disconnected,
                DEVICE,
                &cmd,
                format!("cannot open V4L2 camera {index} ({}): {e}", none_found()),
            )
            .with_hint("connect a camera (ls /dev/video*), or replay recorded frames with dir:PATH")
        })?;
        camera.open_stream().map_err(|e| {
            DeviceError::new(
                ErrorKind::Disconnected,
                DEVICE,
                &cmd,
                format!("cannot start streaming from V4L2 camera {index}: {e}"),
            )
        })?;
        Ok(V4lCamera { camera, index })
    }
}

impl Camera for V4lCamera {
    fn grab(&mut self) -> DeviceResult<CameraFrame> {
        let cmd = format!("grab {}", self.index);
        let buffer = self.camera.frame().map_err(|e| {
            DeviceError::new(
                ErrorKind::Disconnected,
                DEVICE,
                &cmd,
                format!("no frame: {e}"),
            )
        })?;
        let timestamp = SystemTime::now();
        let image = buffer.decode_image::<RgbFormat>().map_err(|e| {
            DeviceError::new(
                ErrorKind::Protocol,
                DEVICE,
                &cmd,
                format!("cannot decode frame: {e}"),
            )
        })?;
        Ok(CameraFrame { image, timestamp })
    }
}
