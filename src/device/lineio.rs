//! Line-oriented I/O over any `Read + Write` port, with a deadline on every read.
//!
//! Text protocols (GRBL, Zaber ASCII) frame replies as lines. [`LinePort`] keeps the
//! bytes read past the end of a line for the next call, treats both `\r` and `\n`
//! as terminators (skipping the empty lines a `\r\n` pair leaves), and turns the
//! port's own short read timeouts into one deadline per call. A port that reports
//! end-of-file or a broken pipe is [`ErrorKind::Disconnected`]; running past the
//! deadline is [`ErrorKind::Timeout`]. Both errors carry the command that failed.
//!
//! Ports must return from `read` now and then without data (a `serialport` port
//! with a short timeout returns `TimedOut`), or deadlines cannot be honoured:
//! [`PORT_READ_TIMEOUT`] is the timeout the drivers' `open` helpers set.

use std::io::{self, Read, Write};
use std::time::{Duration, Instant};

use super::{DeviceError, DeviceResult, ErrorKind};

/// Read timeout set on serial ports: the granularity with which deadlines are
/// checked. Data is returned as soon as it arrives, so this adds no latency.
pub const PORT_READ_TIMEOUT: Duration = Duration::from_millis(10);

/// Opens the serial port of a line-protocol stage controller (8N1, read timeout
/// [`PORT_READ_TIMEOUT`]); a port that cannot be opened is
/// [`ErrorKind::Disconnected`], naming `device`, the port and the baud rate, with a
/// hint to list the ports and the device's own `device_hint` (baud rates, permissions).
pub fn open_stage_serial(
    device: &'static str,
    path: &str,
    baud: u32,
    device_hint: &str,
) -> DeviceResult<Box<dyn serialport::SerialPort>> {
    serialport::new(path, baud)
        .timeout(PORT_READ_TIMEOUT)
        .open()
        .map_err(|e| {
            DeviceError::new(
                ErrorKind::Disconnected,
                device,
                format!("open {path}"),
                format!("cannot open serial port {path} at {baud} baud: {e}"),
            )
            .with_hint(format!("list ports with `tactbench ports`; {device_hint}"))
        })
}

/// Longest line accepted before the buffer is declared garbage.
const MAX_LINE: usize = 4096;

/// A port read line by line.
#[derive(Debug)]
pub struct LinePort<P> {
    port: P,
    device: &'static str,
    buf: Vec<u8>,
}

impl<P: Read + Write> LinePort<P> {
    /// Wraps a port; `device` names it in errors.
    pub fn new(port: P, device: &'static str) -> Self {
        LinePort {
            port,
            device,
            buf: Vec::new(),
        }
    }

    /// The wrapped port.
    pub fn into_inner(self) -> P {
        self.port
    }

    /// Mutable access to the wrapped port.
    pub fn get_mut(&mut self) -> &mut P {
        &mut self.port
    }

    /// Writes all bytes and flushes; `command` names what was sent, for errors.
    pub fn send(&mut self, bytes: &[u8], command: &str) -> DeviceResult<()> {
        let r = self.port.write_all(bytes).and_then(|_| self.port.flush());
        r.map_err(|e| self.io_error(e, command, "writing"))
    }

    /// Drops any buffered, not yet returned bytes.
    pub fn clear(&mut self) {
        self.buf.clear();
    }

    /// The next non-empty line (terminator stripped), or a timeout at `deadline`.
    pub fn read_line(&mut self, deadline: Instant, command: &str) -> DeviceResult<Vec<u8>> {
        loop {
            if let Some(line) = self.take_line() {
                return Ok(line);
            }
            if Instant::now() >= deadline {
                return Err(DeviceError::new(
                    ErrorKind::Timeout,
                    self.device,
                    command,
                    format!(
                        "no complete reply line in time{}",
                        if self.buf.is_empty() {
                            String::new()
                        } else {
                            format!(" (partial: {:?})", String::from_utf8_lossy(&self.buf))
                        }
                    ),
                ));
            }
            let mut chunk = [0u8; 512];
            match self.port.read(&mut chunk) {
                Ok(0) => {
                    return Err(DeviceError::new(
                        ErrorKind::Disconnected,
                        self.device,
                        command,
                        "the port reported end of file",
                    ))
                }
                Ok(n) => {
                    self.buf.extend_from_slice(&chunk[..n]);
                    if self.buf.len() > MAX_LINE {
                        let len = self.buf.len();
                        self.buf.clear();
                        return Err(DeviceError::new(
                            ErrorKind::Protocol,
                            self.device,
                            command,
                            format!("{len} bytes without a line terminator"),
                        ));
                    }
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::TimedOut
                            | io::ErrorKind::WouldBlock
                            | io::ErrorKind::Interrupted
                    ) => {}
                Err(e) => return Err(self.io_error(e, command, "reading")),
            }
        }
    }

    fn take_line(&mut self) -> Option<Vec<u8>> {
        loop {
            let end = self.buf.iter().position(|&b| b == b'\n' || b == b'\r')?;
            let line: Vec<u8> = self.buf[..end].to_vec();
            self.buf.drain(..=end);
            if !line.is_empty() {
                return Some(line);
            }
        }
    }

    fn io_error(&self, e: io::Error, command: &str, doing: &str) -> DeviceError {
        let kind = match e.kind() {
            io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock => ErrorKind::Timeout,
            _ => ErrorKind::Disconnected,
        };
        DeviceError::new(
            kind,
            self.device,
            command,
            format!("{doing} the port failed: {e}"),
        )
        .with_hint("check the cable / that the port still exists")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Reads from a script of chunks, then times out; records writes.
    struct Script {
        chunks: Vec<Vec<u8>>,
        written: Vec<u8>,
        eof: bool,
    }

    impl Read for Script {
        fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
            if self.chunks.is_empty() {
                if self.eof {
                    return Ok(0);
                }
                return Err(io::Error::new(io::ErrorKind::TimedOut, "t"));
            }
            let c = self.chunks.remove(0);
            buf[..c.len()].copy_from_slice(&c);
            Ok(c.len())
        }
    }

    impl Write for Script {
        fn write(&mut self, b: &[u8]) -> io::Result<usize> {
            self.written.extend_from_slice(b);
            Ok(b.len())
        }
        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn lines_split_across_chunks_and_crlf_pairs_are_joined_and_skipped() {
        let mut p = LinePort::new(
            Script {
                chunks: vec![
                    b"o".to_vec(),
                    b"k\r\n<Id".to_vec(),
                    b"le>\r\n\r\nx\n".to_vec(),
                ],
                written: vec![],
                eof: false,
            },
            "t",
        );
        let dl = Instant::now() + Duration::from_millis(100);
        assert_eq!(p.read_line(dl, "c").unwrap(), b"ok");
        assert_eq!(p.read_line(dl, "c").unwrap(), b"<Idle>");
        assert_eq!(p.read_line(dl, "c").unwrap(), b"x");
        let e = p.read_line(Instant::now(), "c").unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Timeout);
    }

    #[test]
    fn end_of_file_is_a_disconnect_naming_the_command() {
        let mut p = LinePort::new(
            Script {
                chunks: vec![],
                written: vec![],
                eof: true,
            },
            "t",
        );
        let e = p
            .read_line(Instant::now() + Duration::from_secs(1), "$H")
            .unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Disconnected);
        assert_eq!(e.command, "$H");
    }
}
