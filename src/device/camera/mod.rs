//! Cameras: a real V4L2 camera through `nokhwa` ([`v4l`]), an image directory
//! replaying recorded frames ([`image_dir`]), and the simulated bench's camera served on
//! a Unix socket ([`socket`]). All implement [`Camera`]; [`open`] picks one from a
//! device spec (`0` = V4L2 index 0, `dir:PATH` = image directory, `sim:PATH` = the
//! simulated bench's `camera.sock`).

pub mod image_dir;
pub mod socket;
#[cfg(feature = "v4l")]
pub mod v4l;
/// Without the `v4l` feature, V4L2 cameras are not built in: listing and opening say
/// how to turn them on.
#[cfg(not(feature = "v4l"))]
#[path = "v4l_disabled.rs"]
pub mod v4l;

use std::path::PathBuf;

pub use image_dir::ImageDirCamera;
pub use socket::SocketCamera;
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
    /// The simulated bench's camera socket (`sim:PATH`).
    Sim(PathBuf),
}

impl CameraSpec {
    /// Parses `N`, `dir:PATH` or `sim:PATH`.
    pub fn parse(spec: &str) -> DeviceResult<Self> {
        if let Some(p) = spec.strip_prefix("sim:") {
            if p.is_empty() {
                return Err(DeviceError::new(
                    ErrorKind::Other,
                    DEVICE,
                    format!("open {spec}"),
                    "`sim:` needs the simulated bench's socket path, e.g. sim:links/camera.sock",
                ));
            }
            return Ok(CameraSpec::Sim(PathBuf::from(p)));
        }
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
                format!(
                    "camera `{spec}` is neither a V4L2 index (0, 1, ...), dir:PATH nor sim:PATH"
                ),
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
        CameraSpec::Sim(p) => Ok(Box::new(SocketCamera::connect(p)?)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(not(feature = "v4l"))]
    #[test]
    fn a_v4l_index_without_the_feature_names_the_feature_and_its_system_package() {
        let Err(e) = open(&CameraSpec::V4l(0)) else {
            panic!("a build without `v4l` opened a V4L2 camera");
        };
        let msg = e.to_string();
        assert!(msg.contains("--features v4l"), "{msg}");
        assert!(msg.contains("libclang-dev"), "{msg}");
        assert!(v4l::list().is_err());
    }

    /// With the feature, a machine without cameras gets a clear error, not a panic.
    #[cfg(feature = "v4l")]
    #[test]
    fn a_missing_v4l_camera_is_a_disconnected_error() {
        if std::path::Path::new("/dev/video99").exists() {
            return;
        }
        let Err(e) = open(&CameraSpec::V4l(99)) else {
            panic!("opened /dev/video99, which does not exist");
        };
        assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
    }

    #[test]
    fn specs_parse_to_their_kinds() {
        assert_eq!(CameraSpec::parse("3").unwrap(), CameraSpec::V4l(3));
        assert_eq!(
            CameraSpec::parse("dir:frames").unwrap(),
            CameraSpec::Dir(PathBuf::from("frames"))
        );
        assert_eq!(
            CameraSpec::parse("sim:links/camera.sock").unwrap(),
            CameraSpec::Sim(PathBuf::from("links/camera.sock"))
        );
        assert!(CameraSpec::parse("sim:").is_err());
        assert!(CameraSpec::parse("usb").is_err());
    }
}
