//! The simulated bench's camera: frames rendered by the virtual world, fetched over a
//! Unix socket (`DIR/camera.sock` of `tactbench sim bench`).
//!
//! Protocol (one request line, one reply): the client sends `grab\n` (the next frame
//! of the current contact) or `reference\n` (the unloaded frame); the server answers
//! `ok <width> <height> <frame index> <unix time ns>\n` followed by exactly
//! `width × height × 3` bytes of 8-bit RGB, row-major, or `error <message>\n`.

use std::io::{BufRead, BufReader, Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use super::DEVICE;
use crate::device::{Camera, CameraFrame, DeviceError, DeviceResult, ErrorKind};

/// Longest wait for a frame: rendering a loaded frame takes tens of ms; effects more.
pub const FRAME_TIMEOUT: Duration = Duration::from_secs(10);

/// Largest frame accepted, pixels (guards against a garbled header).
const MAX_PIXELS: u64 = 64 * 1024 * 1024;

/// A camera served by `tactbench sim bench`.
#[derive(Debug)]
pub struct SocketCamera {
    path: PathBuf,
    reader: BufReader<UnixStream>,
    writer: UnixStream,
}

impl SocketCamera {
    /// Connects to the socket.
    pub fn connect(path: &Path) -> DeviceResult<SocketCamera> {
        let cmd = format!("connect {}", path.display());
        let stream = UnixStream::connect(path).map_err(|e| {
            DeviceError::new(
                ErrorKind::Disconnected,
                DEVICE,
                &cmd,
                format!("cannot connect: {e}"),
            )
            .with_hint(
                "start the simulated bench first: tactbench sim bench --scene S.toml --links DIR",
            )
        })?;
        let io =
            |e: std::io::Error| DeviceError::new(ErrorKind::Other, DEVICE, &cmd, e.to_string());
        stream.set_read_timeout(Some(FRAME_TIMEOUT)).map_err(io)?;
        let writer = stream.try_clone().map_err(io)?;
        Ok(SocketCamera {
            path: path.to_path_buf(),
            reader: BufReader::new(stream),
            writer,
        })
    }

    /// The unloaded reference frame.
    pub fn grab_reference(&mut self) -> DeviceResult<CameraFrame> {
        self.request("reference")
    }

    fn request(&mut self, what: &str) -> DeviceResult<CameraFrame> {
        let cmd = what.to_string();
        let fail = |kind, msg: String| DeviceError::new(kind, DEVICE, &cmd, msg);
        let io = |e: std::io::Error| {
            let kind = match e.kind() {
                std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut => ErrorKind::Timeout,
                std::io::ErrorKind::UnexpectedEof
                | std::io::ErrorKind::BrokenPipe
                | std::io::ErrorKind::ConnectionReset => ErrorKind::Disconnected,
                _ => ErrorKind::Other,
            };
            DeviceError::new(
                kind,
                DEVICE,
                what,
                format!("{e} (is the simulated bench still running?)"),
            )
        };
        writeln!(self.writer, "{what}")
            .and_then(|_| self.writer.flush())
            .map_err(io)?;
        let mut header = String::new();
        let n = self.reader.read_line(&mut header).map_err(io)?;
        if n == 0 {
            return Err(fail(
                ErrorKind::Disconnected,
                format!("{} closed the connection", self.path.display()),
            ));
        }
        let header = header.trim_end();
        if let Some(msg) = header.strip_prefix("error ") {
            return Err(fail(ErrorKind::Rejected, msg.to_string()));
        }
        let parts: Vec<&str> = header.split(' ').collect();
        let parsed = match parts.as_slice() {
            ["ok", w, h, _frame, ns] => {
                match (w.parse::<u32>(), h.parse::<u32>(), ns.parse::<u64>()) {
                    (Ok(w), Ok(h), Ok(ns))
                        if w > 0 && h > 0 && u64::from(w) * u64::from(h) <= MAX_PIXELS =>
                    {
                        Some((w, h, ns))
                    }
                    _ => None,
                }
            }
            _ => None,
        };
        let Some((w, h, ns)) = parsed else {
            return Err(fail(
                ErrorKind::Protocol,
                format!("unexpected reply header `{header}`"),
            ));
        };
        let mut pixels = vec![0u8; w as usize * h as usize * 3];
        self.reader.read_exact(&mut pixels).map_err(io)?;
        let image = image::RgbImage::from_raw(w, h, pixels).ok_or_else(|| {
            fail(
                ErrorKind::Protocol,
                "frame size does not match its header".into(),
            )
        })?;
        Ok(CameraFrame {
            image,
            timestamp: UNIX_EPOCH + Duration::from_nanos(ns),
        })
    }
}

impl Camera for SocketCamera {
    fn grab(&mut self) -> DeviceResult<CameraFrame> {
        let mut f = self.request("grab")?;
        // Frames carry the server's render time; fall back to now if it was unset.
        if f.timestamp == UNIX_EPOCH {
            f.timestamp = SystemTime::now();
        }
        Ok(f)
    }

    fn preview(&mut self) -> DeviceResult<CameraFrame> {
        self.grab_reference()
    }
}
