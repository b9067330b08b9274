//! WACOH DynPick driver, generic over `Read + Write`: polled records (`R`),
//! sensitivities read once at connect (`p`), tare by the device's offset zeroing (`O`,
//! verified by reading back and repeated if it did not take), firmware version (`V`)
//! and filter divider (`nF` / `0F`).
//!
//! A sensor may have been left in continuous output (`S`) by an earlier program: connect
//! first ends it (`E`) and discards what was already sent, until the line is quiet.
//!
//! Every reply has a deadline ([`REPLY_TIMEOUT`]). Reads are idempotent, so a failed
//! attempt (timeout, malformed record) is retried up to [`MAX_ATTEMPTS`] times after
//! draining the input (late replies and garbage are discarded, [`DRAIN_QUIET`]). A
//! line with garbage in front of a valid record is accepted by taking its last 27
//! bytes (resync). A closed port is never retried.

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use super::codec::{
    decode_filter, CodecError, Command, FilterDivider, Record, Sensitivities, RAW_ZERO, RECORD_LEN,
};
use crate::device::ft_common::{self, show_bytes, LinkStats, Retry};
use crate::device::{DeviceError, DeviceResult, ErrorKind, ForceSensor, Wrench};

/// Device name in errors.
pub const DEVICE: &str = "dynpick";
/// Baud rate (8N1).
pub const BAUD: u32 = 921_600;
/// Deadline for a complete reply line after the command was written. A record takes
/// 0.3 ms on the wire at 921600 baud; the margin is for USB-serial latency.
pub const REPLY_TIMEOUT: Duration = Duration::from_millis(50);
/// Attempts per command before giving up (reads are idempotent, so retrying is safe).
pub const MAX_ATTEMPTS: u32 = 3;
/// Before a retry, input is discarded until the line has been quiet this long, so a
/// reply arriving up to one more [`REPLY_TIMEOUT`] late is not taken for the next one.
pub const DRAIN_QUIET: Duration = REPLY_TIMEOUT;
/// Upper bound on one drain (a device spewing garbage must not hang the driver).
pub const DRAIN_MAX: Duration = Duration::from_millis(500);
/// Longest line accepted; anything longer is garbage.
pub const MAX_LINE: usize = 128;
/// At connect, after `E` the line must be quiet this long (a record every 1 ms in
/// continuous output) before the first command.
pub const STOP_QUIET: Duration = Duration::from_millis(20);
/// Rounds of `E` at connect, each waiting up to [`DRAIN_MAX`] for [`STOP_QUIET`],
/// before a line that keeps sending is an error.
pub const STOP_ATTEMPTS: u32 = 3;
/// Times [`ForceSensor::tare`] sends `O` before giving up. The open-source ROS driver
/// sends it 3 times blindly ("it only works when sent several times"); we read back
/// after each and stop as soon as it took.
pub const TARE_ATTEMPTS: u32 = 5;
/// A tare took when every channel of the record read after `O` is within this many
/// LSB of zero load (8192): 16 LSB = 0.49 N at 32.8 LSB/N, 0.01 N·m at
/// 1638.4 LSB/(N·m), 0.2 % of the 14-bit range; a sensor at rest is within a few LSB
/// (its noise), a load that was not zeroed is far outside.
pub const TARE_TOLERANCE_LSB: u16 = 16;
/// The device's internal sampling rate, Hz (what [`ForceSensor::sample_rate_hz`]
/// reports; the polled rate is lower and is measured, see `protocols/dynpick.md`).
pub const SAMPLE_RATE_HZ: f64 = 1000.0;

/// A connected DynPick.
pub struct DynPick<P> {
    port: P,
    sensitivities: Sensitivities,
    rx: Vec<u8>,
    retry: Retry,
    last_counter: Option<u8>,
}

/// Hint on a command that failed for good.
const HINT: &str = "check baud rate (921600) and cable; the device may be resetting";

impl<P: Read + Write> DynPick<P> {
    /// Connects: ends continuous output (`E`) and discards pending input until the line
    /// is quiet (see [`stop_continuous`]), then reads the sensitivities (`p`).
    pub fn connect(port: P) -> DeviceResult<Self> {
        Self::connect_with(port, REPLY_TIMEOUT)
    }

    /// [`DynPick::connect`] with another reply deadline (default [`REPLY_TIMEOUT`]; also
    /// the quiet time before a retry), used from the first command on. A simulated
    /// sensor shares the host's CPU with everything else, so the simulated bench allows
    /// more than a real sensor on its own cable needs.
    pub fn connect_with(mut port: P, reply_timeout: Duration) -> DeviceResult<Self> {
        stop_continuous(&mut port)?;
        let mut d = DynPick {
            port,
            sensitivities: Sensitivities([1.0; 6]),
            rx: Vec::new(),
            retry: Retry::new(DEVICE, reply_timeout, DRAIN_QUIET, DRAIN_MAX, HINT),
            last_counter: None,
        };
        d.sensitivities = d.transact(Command::Sensitivities, |l| {
            Sensitivities::decode(l).map(|s| (s, false))
        })?;
        Ok(d)
    }

    /// The sensitivities read at connect (LSB per N, LSB per N·m).
    pub fn sensitivities(&self) -> Sensitivities {
        self.sensitivities
    }

    /// Link statistics (retries, timeouts, protocol errors, resyncs).
    pub fn stats(&self) -> LinkStats {
        self.retry.stats
    }

    /// Counter digit of the last record.
    pub fn last_counter(&self) -> Option<u8> {
        self.last_counter
    }

    /// One raw record (`R`).
    pub fn read_record(&mut self) -> DeviceResult<Record> {
        let r = self.transact(Command::Read, decode_record_resync)?;
        self.last_counter = Some(r.counter);
        Ok(r)
    }

    /// One raw record in a single attempt (see [`ForceSensor::read_once`]).
    pub fn read_record_once(&mut self) -> DeviceResult<Record> {
        let r = self.transact_n(Command::Read, decode_record_resync, 1)?;
        self.last_counter = Some(r.counter);
        Ok(r)
    }

    /// Firmware version line (`V`), CR LF stripped. A data record is never taken for
    /// the version (a stray record from continuous output is skipped, the reader keeps
    /// listening).
    pub fn firmware_version(&mut self) -> DeviceResult<String> {
        self.transact(Command::Version, |l| {
            if Record::decode(l).is_ok() {
                return Err(CodecError::Unexpected {
                    what: "a data record",
                    bytes: show_bytes(l),
                });
            }
            Ok((String::from_utf8_lossy(l).trim_end().to_string(), false))
        })
    }

    /// Zeroes the offset (`O`) and checks it took: after each `O` one record is read;
    /// the tare took when every channel is within [`TARE_TOLERANCE_LSB`] of zero load.
    /// Otherwise `O` is sent again, up to [`TARE_ATTEMPTS`] times; then the error
    /// ([`ErrorKind::Rejected`]) gives the last reading. Returns the `O` commands sent.
    pub fn tare_verified(&mut self) -> DeviceResult<u32> {
        let cmd = Command::ZeroOffset;
        let mut last = None;
        for attempt in 1..=TARE_ATTEMPTS {
            self.rx.clear();
            ft_common::send(&mut self.port, DEVICE, &cmd.text(), &cmd.encode())?;
            let r = self.read_record()?;
            if r.raw
                .iter()
                .all(|&v| v.abs_diff(RAW_ZERO) <= TARE_TOLERANCE_LSB)
            {
                return Ok(attempt);
            }
            last = Some(r);
        }
        let shown = last.map_or(String::new(), |r| {
            let off: Vec<String> = r
                .raw
                .iter()
                .map(|&v| format!("{:+}", v as i32 - RAW_ZERO as i32))
                .collect();
            format!(
                ": the record read after the last still has {} LSB from zero (Fx Fy Fz Mx My Mz), \
                 tolerance ±{TARE_TOLERANCE_LSB} LSB",
                off.join(" ")
            )
        });
        Err(DeviceError::new(
            ErrorKind::Rejected,
            DEVICE,
            cmd.text(),
            format!("tare did not take after {TARE_ATTEMPTS} `O` commands{shown}"),
        )
        .with_hint("keep the sensor still and unloaded while taring; check the cable"))
    }

    /// The filter divider (`0F`).
    pub fn filter(&mut self) -> DeviceResult<FilterDivider> {
        self.transact(Command::GetFilter, |l| decode_filter(l).map(|f| (f, false)))
    }

    /// Sets the filter divider (`nF`) and checks it by reading it back.
    pub fn set_filter(&mut self, d: FilterDivider) -> DeviceResult<()> {
        let cmd = Command::SetFilter(d);
        ft_common::send(&mut self.port, DEVICE, &cmd.text(), &cmd.encode())?;
        let back = self.filter()?;
        if back != d {
            return Err(DeviceError::new(
                ErrorKind::Rejected,
                DEVICE,
                cmd.text(),
                format!(
                    "filter divider reads back {} after setting {}",
                    back.n(),
                    d.n()
                ),
            ));
        }
        Ok(())
    }

    /// Gives the port back.
    pub fn into_inner(self) -> P {
        self.port
    }

    /// Sends `cmd` and parses its reply line, retrying failed attempts. `parse`
    /// returns the value and whether it had to resync (skip garbage).
    fn transact<T>(
        &mut self,
        cmd: Command,
        parse: impl Fn(&[u8]) -> Result<(T, bool), CodecError>,
    ) -> DeviceResult<T> {
        self.transact_n(cmd, parse, MAX_ATTEMPTS)
    }

    /// [`DynPick::transact`] with `attempts` attempts.
    fn transact_n<T>(
        &mut self,
        cmd: Command,
        parse: impl Fn(&[u8]) -> Result<(T, bool), CodecError>,
        attempts: u32,
    ) -> DeviceResult<T> {
        let text = cmd.text();
        let rx = &mut self.rx;
        let timeout = self.retry.reply_timeout;
        self.retry.transact(
            &mut self.port,
            &text,
            &cmd.encode(),
            attempts,
            |port, deadline, stats| {
                // Bytes read before this command cannot be its reply.
                rx.clear();
                let mut bad: Option<String> = None;
                loop {
                    match read_line(port, rx, deadline, &text) {
                        Ok(line) => match parse(&line) {
                            Ok((v, resynced)) => {
                                if resynced || bad.is_some() {
                                    stats.resyncs += 1;
                                }
                                return Ok(v);
                            }
                            // Keep listening: the reply may follow a garbage line.
                            Err(e) => bad = Some(e.to_string()),
                        },
                        Err(e) if e.kind == ErrorKind::Protocol => bad = Some(e.message),
                        Err(e) if e.kind == ErrorKind::Timeout => {
                            return Err(match bad {
                                Some(b) => DeviceError::new(ErrorKind::Protocol, DEVICE, &text, b),
                                None => DeviceError::new(
                                    ErrorKind::Timeout,
                                    DEVICE,
                                    &text,
                                    format!("no reply within {} ms", timeout.as_millis()),
                                ),
                            })
                        }
                        Err(e) => return Err(e),
                    }
                }
            },
        )
    }
}

/// Ends continuous output (`E`, no reply) and discards input until the line has been
/// quiet for [`STOP_QUIET`]; while records keep coming for [`DRAIN_MAX`], sends `E`
/// again, at most [`STOP_ATTEMPTS`] rounds, then fails with [`ErrorKind::Protocol`].
/// A sensor in polled mode ignores the `E`. Returns the bytes discarded.
pub fn stop_continuous<P: Read + Write>(port: &mut P) -> DeviceResult<usize> {
    let cmd = Command::StopContinuous;
    let mut dropped = 0;
    for _ in 0..STOP_ATTEMPTS {
        ft_common::send(port, DEVICE, &cmd.text(), &cmd.encode())?;
        let start = Instant::now();
        let n = ft_common::drain(port, STOP_QUIET, DRAIN_MAX, DEVICE, &cmd.text())?;
        dropped += n;
        if start.elapsed() < DRAIN_MAX {
            return Ok(dropped);
        }
    }
    Err(DeviceError::new(
        ErrorKind::Protocol,
        DEVICE,
        cmd.text(),
        format!(
            "the sensor kept sending after {STOP_ATTEMPTS} `E` commands ({dropped} bytes discarded, \
             never quiet for {} ms)",
            STOP_QUIET.as_millis()
        ),
    )
    .with_hint(HINT))
}

/// Reads one line (LF-terminated, LF included) before `deadline`, keeping what
/// follows it in `rx`.
fn read_line<P: Read>(
    port: &mut P,
    rx: &mut Vec<u8>,
    deadline: Instant,
    command: &str,
) -> DeviceResult<Vec<u8>> {
    let mut buf = [0u8; 64];
    loop {
        if let Some(pos) = rx.iter().position(|&b| b == b'\n') {
            let rest = rx.split_off(pos + 1);
            return Ok(std::mem::replace(rx, rest));
        }
        if rx.len() > MAX_LINE {
            let bytes = std::mem::take(rx);
            return Err(DeviceError::new(
                ErrorKind::Protocol,
                DEVICE,
                command,
                format!(
                    "no line end within {MAX_LINE} bytes: `{}`",
                    show_bytes(&bytes)
                ),
            ));
        }
        let n = ft_common::read_until_deadline(port, &mut buf, deadline, DEVICE, command)?;
        rx.extend_from_slice(&buf[..n]);
    }
}

/// Decodes a record line; a longer line whose last 27 bytes are a valid record is
/// accepted (garbage in front of the reply: resync).
pub fn decode_record_resync(line: &[u8]) -> Result<(Record, bool), CodecError> {
    match Record::decode(line) {
        Ok(r) => Ok((r, false)),
        Err(e) if line.len() > RECORD_LEN => Record::decode(&line[line.len() - RECORD_LEN..])
            .map(|r| (r, true))
            .map_err(|_| e),
        Err(e) => Err(e),
    }
}

impl<P: Read + Write> ForceSensor for DynPick<P> {
    fn read(&mut self) -> DeviceResult<Wrench> {
        let s = self.sensitivities;
        Ok(self.read_record()?.to_wrench(&s))
    }

    fn read_once(&mut self) -> DeviceResult<Wrench> {
        let s = self.sensitivities;
        Ok(self.read_record_once()?.to_wrench(&s))
    }

    /// Zeroes the device's offset (`O`), verified and repeated as
    /// [`DynPick::tare_verified`]. A device reset loses it (see `protocols/dynpick.md`).
    fn tare(&mut self) -> DeviceResult<()> {
        self.tare_verified().map(|_| ())
    }

    fn sample_rate_hz(&self) -> f64 {
        SAMPLE_RATE_HZ
    }
}
