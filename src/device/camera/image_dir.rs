//! A camera replaying recorded frames from a directory: every PNG, JPEG or BMP file
//! (by extension, case-insensitive) in file-name order, converted to 8-bit RGB. At the
//! end it either loops or fails with a clear error; an empty directory fails at open.

use std::path::{Path, PathBuf};
use std::time::SystemTime;

use super::DEVICE;
use crate::device::{Camera, CameraFrame, DeviceError, DeviceResult, ErrorKind};

/// File extensions replayed.
pub const EXTENSIONS: [&str; 4] = ["png", "jpg", "jpeg", "bmp"];

/// Replays image files as camera frames.
#[derive(Debug)]
pub struct ImageDirCamera {
    dir: PathBuf,
    files: Vec<PathBuf>,
    next: usize,
    looping: bool,
}

impl ImageDirCamera {
    /// Lists the frames in `dir`; `looping` restarts at the first frame after the last.
    pub fn open(dir: &Path, looping: bool) -> DeviceResult<Self> {
        let cmd = format!("open dir:{}", dir.display());
        let entries = std::fs::read_dir(dir).map_err(|e| {
            DeviceError::new(
                ErrorKind::Disconnected,
                DEVICE,
                &cmd,
                format!("cannot read image directory {}: {e}", dir.display()),
            )
        })?;
        let mut files: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.is_file()
                    && p.extension()
                        .and_then(|e| e.to_str())
                        .is_some_and(|e| EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
            })
            .collect();
        files.sort();
        if files.is_empty() {
            return Err(DeviceError::new(
                ErrorKind::Disconnected,
                DEVICE,
                &cmd,
                format!("no PNG/JPEG/BMP frames in {}", dir.display()),
            ));
        }
        Ok(ImageDirCamera {
            dir: dir.to_path_buf(),
            files,
            next: 0,
            looping,
        })
    }

    /// The frame files in replay order.
    pub fn files(&self) -> &[PathBuf] {
        &self.files
    }

    /// The index of the frame a `grab` returns next.
    fn next_index(&self) -> DeviceResult<usize> {
        match (self.next >= self.files.len(), self.looping) {
            (false, _) => Ok(self.next),
            (true, true) => Ok(0),
            (true, false) => Err(DeviceError::new(
                ErrorKind::Disconnected,
                DEVICE,
                format!("grab dir:{}", self.dir.display()),
                format!(
                    "end of recorded frames: all {} frames of {} replayed",
                    self.files.len(),
                    self.dir.display()
                ),
            )),
        }
    }

    fn load(&self, index: usize) -> DeviceResult<CameraFrame> {
        let path = &self.files[index];
        // Its size checked from the header before decoding (crate::frame_size).
        let image = crate::frame_size::open_capped(path)
            .map_err(|e| e.to_string())
            .and_then(|r| r.decode().map_err(|e| e.to_string()))
            .map_err(|e| {
                DeviceError::new(
                    ErrorKind::Protocol,
                    DEVICE,
                    format!("grab {}", path.display()),
                    format!("cannot decode frame {}: {e}", path.display()),
                )
            })?
            .to_rgb8();
        Ok(CameraFrame {
            image,
            timestamp: SystemTime::now(),
        })
    }
}

impl Camera for ImageDirCamera {
    fn grab(&mut self) -> DeviceResult<CameraFrame> {
        let index = self.next_index()?;
        // Consumed even when it does not decode: a retry moves on to the next file.
        self.next = index + 1;
        self.load(index)
    }

    fn preview(&mut self) -> DeviceResult<CameraFrame> {
        self.load(self.next_index()?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(v: u8) -> image::RgbImage {
        image::RgbImage::from_pixel(4, 3, image::Rgb([v, 255 - v, 7]))
    }

    #[test]
    fn replays_frames_in_name_order_then_ends_with_error() {
        let dir = tempfile::tempdir().unwrap();
        frame(20).save(dir.path().join("f002.png")).unwrap();
        frame(10).save(dir.path().join("f001.bmp")).unwrap();
        std::fs::write(dir.path().join("notes.txt"), "not a frame").unwrap();
        let mut cam = ImageDirCamera::open(dir.path(), false).unwrap();
        assert_eq!(cam.files().len(), 2);
        assert_eq!(cam.preview().unwrap().image, frame(10), "preview");
        assert_eq!(
            cam.grab().unwrap().image,
            frame(10),
            "not consumed by preview"
        );
        assert_eq!(cam.grab().unwrap().image, frame(20));
        let e = cam.grab().unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Disconnected);
        assert!(e.message.contains("end of recorded frames"), "{e}");
    }

    #[test]
    fn looping_restarts_at_the_first_frame() {
        let dir = tempfile::tempdir().unwrap();
        frame(1).save(dir.path().join("a.png")).unwrap();
        frame(2).save(dir.path().join("b.png")).unwrap();
        let mut cam = ImageDirCamera::open(dir.path(), true).unwrap();
        let seq: Vec<u8> = (0..5)
            .map(|_| cam.grab().unwrap().image.get_pixel(0, 0).0[0])
            .collect();
        assert_eq!(seq, [1, 2, 1, 2, 1]);
    }

    #[test]
    fn empty_or_missing_directory_is_a_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        let e = ImageDirCamera::open(dir.path(), false).unwrap_err();
        assert!(e.message.contains("no PNG/JPEG/BMP frames"), "{e}");
        let e = ImageDirCamera::open(&dir.path().join("missing"), false).unwrap_err();
        assert!(e.message.contains("cannot read image directory"), "{e}");
    }

    #[test]
    fn undecodable_frame_is_a_protocol_error() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("bad.png"), b"not a png").unwrap();
        let mut cam = ImageDirCamera::open(dir.path(), false).unwrap();
        assert_eq!(cam.grab().unwrap_err().kind(), ErrorKind::Protocol);
    }
}
