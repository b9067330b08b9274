//! Transcript replay: a `Read + Write` transport that checks a driver writes exactly
//! the recorded bytes and feeds it the recorded replies.
//!
//! A transcript (`protocols/transcripts/*.txt`) is a list of exchanges, one per
//! line: `> bytes` is what the host sends, `< bytes` what the device answers; `#`
//! starts a comment. Bytes are text with escapes `\r`, `\n`, `\\`, `\xHH`.
//! Consecutive lines of the same direction are concatenated. A device line is
//! made readable only once every host byte before it has been written, so the
//! driver sees replies in the recorded order relative to its own writes.
//!
//! Like an expectation mock, the transport fails loudly: a write that differs from
//! the transcript is an I/O error naming the position and both byte strings, and
//! [`Replay::finish`] fails if not every expectation was used. Reads with nothing
//! available behave like a serial port with a short timeout (`TimedOut`).

use std::io::{self, Read, Write};
use std::time::Duration;

/// Direction of one transcript step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dir {
    /// Host to device (`>`).
    Host,
    /// Device to host (`<`).
    Device,
}

/// A parsed transcript: alternating steps of bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Transcript {
    /// Steps in order.
    pub steps: Vec<(Dir, Vec<u8>)>,
}

/// Errors parsing a transcript.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("transcript line {line}: {message}")]
pub struct TranscriptError {
    /// 1-based line number.
    pub line: usize,
    /// What is wrong.
    pub message: String,
}

impl Transcript {
    /// Parses transcript text.
    pub fn parse(text: &str) -> Result<Self, TranscriptError> {
        let mut steps: Vec<(Dir, Vec<u8>)> = Vec::new();
        for (n, raw) in text.lines().enumerate() {
            let line = raw.trim_end();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let (dir, rest) = if let Some(r) = line.strip_prefix("> ") {
                (Dir::Host, r)
            } else if let Some(r) = line.strip_prefix("< ") {
                (Dir::Device, r)
            } else {
                return Err(TranscriptError {
                    line: n + 1,
                    message: format!("expected `> ` or `< ` at the start, got {line:?}"),
                });
            };
            let bytes = unescape(rest).map_err(|message| TranscriptError {
                line: n + 1,
                message,
            })?;
            match steps.last_mut() {
                Some((d, b)) if *d == dir => b.extend_from_slice(&bytes),
                _ => steps.push((dir, bytes)),
            }
        }
        Ok(Transcript { steps })
    }
}

fn unescape(s: &str) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    let b = s.as_bytes();
    let mut i = 0;
    while i < b.len() {
        if b[i] != b'\\' {
            out.push(b[i]);
            i += 1;
            continue;
        }
        match b.get(i + 1) {
            Some(b'n') => out.push(b'\n'),
            Some(b'r') => out.push(b'\r'),
            Some(b'\\') => out.push(b'\\'),
            Some(b'x') => {
                let hex = s.get(i + 2..i + 4).ok_or("truncated \\x escape")?;
                out.push(
                    u8::from_str_radix(hex, 16).map_err(|_| format!("bad \\x escape {hex:?}"))?,
                );
                i += 2;
            }
            other => {
                return Err(format!(
                    "unknown escape \\{}",
                    other.map(|c| *c as char).unwrap_or(' ')
                ))
            }
        }
        i += 2;
    }
    Ok(out)
}

/// The replay transport.
#[derive(Debug)]
pub struct Replay {
    steps: Vec<(Dir, Vec<u8>)>,
    /// Current step and offset in it.
    step: usize,
    offset: usize,
    failure: Option<String>,
    written_total: usize,
}

/// How long a read with nothing to return waits before `TimedOut`, like a port.
const READ_IDLE: Duration = Duration::from_millis(1);

impl Replay {
    /// A transport replaying `t`.
    pub fn new(t: Transcript) -> Self {
        Replay {
            steps: t.steps,
            step: 0,
            offset: 0,
            failure: None,
            written_total: 0,
        }
    }

    /// Ok if every recorded byte was written and read and no write differed.
    pub fn finish(&self) -> Result<(), String> {
        if let Some(f) = &self.failure {
            return Err(f.clone());
        }
        let (mut step, mut offset) = (self.step, self.offset);
        while step < self.steps.len() && offset >= self.steps[step].1.len() {
            step += 1;
            offset = 0;
        }
        if step < self.steps.len() {
            let (dir, bytes) = &self.steps[step];
            return Err(format!(
                "transcript not fully used: step {} of {} ({}) has {:?} left",
                step + 1,
                self.steps.len(),
                match dir {
                    Dir::Host => "host bytes never written",
                    Dir::Device => "device bytes never read",
                },
                String::from_utf8_lossy(&bytes[offset..])
            ));
        }
        Ok(())
    }

    fn advance_if_done(&mut self) {
        while self.step < self.steps.len() && self.offset >= self.steps[self.step].1.len() {
            self.step += 1;
            self.offset = 0;
        }
    }
}

impl Read for Replay {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        self.advance_if_done();
        match self.steps.get(self.step) {
            Some((Dir::Device, bytes)) => {
                let n = (bytes.len() - self.offset).min(buf.len());
                buf[..n].copy_from_slice(&bytes[self.offset..self.offset + n]);
                self.offset += n;
                Ok(n)
            }
            _ => {
                std::thread::sleep(READ_IDLE);
                Err(io::Error::new(
                    io::ErrorKind::TimedOut,
                    "replay: nothing to read yet",
                ))
            }
        }
    }
}

impl Write for Replay {
    fn write(&mut self, data: &[u8]) -> io::Result<usize> {
        for (k, &b) in data.iter().enumerate() {
            self.advance_if_done();
            let expected = match self.steps.get(self.step) {
                Some((Dir::Host, bytes)) => Some(bytes[self.offset]),
                _ => None,
            };
            if expected != Some(b) {
                let what = match self.steps.get(self.step) {
                    Some((Dir::Host, bytes)) => format!(
                        "expected {:?}",
                        String::from_utf8_lossy(&bytes[self.offset..])
                    ),
                    Some((Dir::Device, bytes)) => format!(
                        "expected the host to read {:?} first",
                        String::from_utf8_lossy(&bytes[self.offset..])
                    ),
                    None => "the transcript has ended".to_string(),
                };
                let msg = format!(
                    "replay: unexpected write {:?} at host byte {}: {what}",
                    String::from_utf8_lossy(&data[k..]),
                    self.written_total
                );
                self.failure.get_or_insert(msg.clone());
                return Err(io::Error::other(msg));
            }
            self.offset += 1;
            self.written_total += 1;
        }
        Ok(data.len())
    }

    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_escapes_and_merges_same_direction_lines() {
        let t = Transcript::parse("# c\n> ?\n< <Idle>\\r\\n\n< ok\\r\\n\n> \\x18\n").unwrap();
        assert_eq!(
            t.steps,
            vec![
                (Dir::Host, b"?".to_vec()),
                (Dir::Device, b"<Idle>\r\nok\r\n".to_vec()),
                (Dir::Host, vec![0x18]),
            ]
        );
        assert!(Transcript::parse("x nope").is_err());
        assert!(Transcript::parse("> \\q").is_err());
    }

    #[test]
    fn mismatched_write_fails_and_unused_steps_fail_finish() {
        let mut r = Replay::new(Transcript::parse("> ab\n< ok\n> c\n").unwrap());
        r.write_all(b"a").unwrap();
        let mut buf = [0u8; 4];
        assert!(
            r.read(&mut buf).is_err(),
            "reply not readable before all host bytes"
        );
        r.write_all(b"b").unwrap();
        assert_eq!(r.read(&mut buf).unwrap(), 2);
        assert!(r.finish().unwrap_err().contains("host bytes never written"));
        assert!(r.write_all(b"x").is_err());
        assert!(r.finish().unwrap_err().contains("unexpected write"));
    }
}
