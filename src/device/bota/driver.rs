//! Bota Systems serial sensor driver, generic over `Read + Write`: configures the
//! sensor (`C`, `c,…`, `f,…`, `R`, each confirmed by `r,0,<cmd>,0`) and reads the
//! binary stream it then sends.
//!
//! A sensor left streaming by an earlier program keeps sending frames while the
//! configuration is sent: the answers are looked for in whatever arrives, frames and
//! boot text around them are skipped. Each command has a deadline and is repeated up to
//! [`MAX_ATTEMPTS`] times.
//!
//! A reading ([`ForceSensor::read`]) is the mean of the frames received since the
//! previous reading (when that was recent, at most [`MEAN_WINDOW`] ago; after a longer
//! pause the queued frames are old and discarded, and the reading waits for a fresh
//! one). Frames whose status marks them overrange or invalid are never averaged: they
//! are counted and reported ([`Bota::take_status`]), and a reading that finds only such
//! frames fails ([`ErrorKind::Limit`]) naming the bits. A stream whose candidate frames
//! keep failing the CRC is a [`ErrorKind::Protocol`] error once the deadline passes.
//! The newest frame's timestamp and temperature are kept ([`Bota::last_frame`]) and
//! reported with the status.
//!
//! Tare is a software offset (the serial protocol has no zeroing command): the mean of
//! [`TARE_READINGS`] readings is subtracted from later readings.

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use super::codec::{status_names, Command, Frame, StreamDecoder, SINC_PERIOD_S};
use crate::device::ft_common::{self, show_bytes};
use crate::device::{DeviceError, DeviceResult, ErrorKind, ForceSensor, Wrench};

/// Device name in errors.
pub const DEVICE: &str = "bota";
/// Baud rate (8N1).
pub const BAUD: u32 = 460_800;
/// Deadline for a command's answer.
pub const REPLY_TIMEOUT: Duration = Duration::from_millis(300);
/// Attempts per configuration command.
pub const MAX_ATTEMPTS: u32 = 3;
/// Deadline for a new good frame per reading attempt (ten periods at 100 Hz).
pub const READ_TIMEOUT: Duration = Duration::from_millis(100);
/// Attempts of [`ForceSensor::read`].
pub const READ_ATTEMPTS: u32 = 3;
/// A reading averages the frames since the previous one only if that was this recent.
pub const MEAN_WINDOW: Duration = Duration::from_millis(20);
/// Readings averaged by tare.
pub const TARE_READINGS: usize = 10;
/// Sinc filter length the driver configures by default (512: 10 ms, 100 Hz; the
/// vendor example's setting).
pub const DEFAULT_SINC_LEN: u32 = 512;

/// Settings the driver sends.
#[derive(Debug, Clone, Copy)]
pub struct BotaOptions {
    /// Sinc filter length (sample period 19.53125 µs × this).
    pub sinc_len: u32,
    /// Deadline for a command's answer and for a new frame.
    pub reply_timeout: Duration,
    /// Frames queued longer than this after the previous reading are stale: a reading
    /// after a longer pause waits for a frame sent after it started.
    pub stale_after: Duration,
}

impl Default for BotaOptions {
    fn default() -> Self {
        BotaOptions {
            sinc_len: DEFAULT_SINC_LEN,
            reply_timeout: REPLY_TIMEOUT,
            stale_after: MEAN_WINDOW,
        }
    }
}

/// What the stream showed.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BotaStats {
    /// Frames decoded.
    pub frames: u64,
    /// Frames averaged.
    pub good: u64,
    /// Frames left out: overrange or invalid.
    pub bad: u64,
    /// Frames with "app took too long" (averaged, reported).
    pub late: u64,
    /// Status bits seen on frames since connect (OR).
    pub status_seen: u16,
    /// Candidate frames that failed the CRC.
    pub bad_crc: u64,
    /// Bytes skipped while resynchronising.
    pub skipped: u64,
    /// Configuration commands repeated.
    pub retries: u64,
}

/// A connected, streaming Bota sensor.
pub struct Bota<P> {
    port: P,
    opts: BotaOptions,
    decoder: StreamDecoder,
    pending: Vec<Wrench>,
    frames: Vec<Frame>,
    offset: Wrench,
    stats: BotaStats,
    reported: BotaStats,
    last: Option<Frame>,
    last_read: Option<Instant>,
    chunk: [u8; 512],
}

fn sub(a: Wrench, b: Wrench) -> Wrench {
    Wrench {
        force_n: [0, 1, 2].map(|i| a.force_n[i] - b.force_n[i]),
        torque_nm: [0, 1, 2].map(|i| a.torque_nm[i] - b.torque_nm[i]),
    }
}

impl<P: Read + Write> Bota<P> {
    /// Configures the sensor (binary format, calibration on, 460800 baud, the filter
    /// of `opts`) and starts the stream; fails if no frame follows.
    pub fn connect(port: P, opts: BotaOptions) -> DeviceResult<Self> {
        let mut d = Bota {
            port,
            opts,
            decoder: StreamDecoder::default(),
            pending: Vec::new(),
            frames: Vec::new(),
            offset: Wrench::default(),
            stats: BotaStats::default(),
            reported: BotaStats::default(),
            last: None,
            last_read: None,
            chunk: [0u8; 512],
        };
        d.command(Command::Config)?;
        d.command(Command::Comm {
            temp_comp: 0,
            use_calib: 1,
            format: 0,
            baud_index: 4,
        })?;
        d.command(Command::Filter {
            sinc_len: opts.sinc_len,
            chop: 0,
            fast: 0,
            fir_disable: 1,
        })?;
        d.command(Command::Run)?;
        // Frames that followed `r,0,R,0` are current: the first reading may use them.
        d.last_read = Some(Instant::now());
        d.wait_frame()?;
        Ok(d)
    }

    /// Statistics.
    pub fn stats(&self) -> BotaStats {
        let mut s = self.stats;
        s.bad_crc = self.decoder.stats.bad_crc;
        s.skipped = self.decoder.stats.skipped;
        s
    }

    /// The newest frame (its timestamp, temperature, status).
    pub fn last_frame(&self) -> Option<Frame> {
        self.last
    }

    /// Sample period configured, s.
    pub fn sample_period_s(&self) -> f64 {
        SINC_PERIOD_S * self.opts.sinc_len as f64
    }

    /// The software tare offset.
    pub fn offset(&self) -> Wrench {
        self.offset
    }

    /// Gives the port back (the sensor keeps streaming).
    pub fn into_inner(self) -> P {
        self.port
    }

    /// Sends `cmd` and waits for its `r,0,<cmd>,0`, skipping everything else (frames of
    /// a stream left running, boot text); repeated up to [`MAX_ATTEMPTS`] times.
    pub fn command(&mut self, cmd: Command) -> DeviceResult<()> {
        let bytes = cmd.encode();
        let text = String::from_utf8_lossy(&bytes).into_owned();
        let ack = cmd.ack().into_bytes();
        let mut seen: Vec<u8> = Vec::new();
        for attempt in 0..MAX_ATTEMPTS {
            if attempt > 0 {
                self.stats.retries += 1;
            }
            ft_common::send(&mut self.port, DEVICE, &text, &bytes)?;
            let deadline = Instant::now() + self.opts.reply_timeout;
            let mut rx: Vec<u8> = Vec::new();
            loop {
                if rx.windows(ack.len()).any(|w| w == ack.as_slice()) {
                    // Whatever followed the answer belongs to the stream (after `R`).
                    if let Some(p) = rx.windows(ack.len()).position(|w| w == ack.as_slice()) {
                        let rest = rx.split_off(p + ack.len());
                        self.decoder.clear();
                        let mut fr = Vec::new();
                        self.decoder.push(&rest, &mut fr);
                        for f in fr {
                            self.take_frame(f);
                        }
                    }
                    return Ok(());
                }
                match ft_common::read_until_deadline(
                    &mut self.port,
                    &mut self.chunk,
                    deadline,
                    DEVICE,
                    &text,
                ) {
                    Ok(n) => {
                        rx.extend_from_slice(&self.chunk[..n]);
                        // Keep the search bounded on a line that streams garbage.
                        if rx.len() > 1 << 16 {
                            rx.drain(..rx.len() - ack.len());
                        }
                    }
                    Err(e) if e.kind == ErrorKind::Timeout => break,
                    Err(e) => return Err(e),
                }
            }
            seen = rx;
        }
        let tail = &seen[seen.len().saturating_sub(48)..];
        Err(DeviceError::new(
            ErrorKind::Timeout,
            DEVICE,
            &text,
            format!(
                "no `{}` within {} ms (after {MAX_ATTEMPTS} attempts; {} bytes arrived{})",
                cmd.ack(),
                self.opts.reply_timeout.as_millis(),
                seen.len(),
                if tail.is_empty() {
                    String::new()
                } else {
                    format!(", last: `{}`", show_bytes(tail))
                }
            ),
        )
        .with_hint("check the port, the baud rate (460800) and that this is a Bota serial sensor"))
    }

    fn take_frame(&mut self, f: Frame) {
        self.stats.frames += 1;
        self.stats.status_seen |= f.status;
        self.last = Some(f);
        if f.is_bad() {
            self.stats.bad += 1;
            return;
        }
        if f.status & super::codec::STATUS_APP_TOO_LONG != 0 {
            self.stats.late += 1;
        }
        self.stats.good += 1;
        if self.pending.len() >= 100_000 {
            self.pending.remove(0);
        }
        self.pending.push(f.wrench());
    }

    /// Reads what the port has until `deadline`, or until a good frame is pending and
    /// the port has nothing more right now.
    fn poll(&mut self, deadline: Instant) -> DeviceResult<()> {
        loop {
            let d = if self.pending.is_empty() {
                deadline
            } else {
                Instant::now()
            };
            match ft_common::read_until_deadline(
                &mut self.port,
                &mut self.chunk,
                d,
                DEVICE,
                "stream",
            ) {
                Ok(n) => {
                    self.frames.clear();
                    let mut fr = std::mem::take(&mut self.frames);
                    self.decoder.push(&self.chunk[..n], &mut fr);
                    for f in fr.drain(..) {
                        self.take_frame(f);
                    }
                    self.frames = fr;
                }
                Err(e) if e.kind == ErrorKind::Timeout => return Ok(()),
                Err(e) => return Err(e),
            }
        }
    }

    /// Waits until a frame (good or flagged) arrived after `R`, without consuming the
    /// pending readings: connect's proof that the stream runs.
    fn wait_frame(&mut self) -> DeviceResult<()> {
        let deadline = Instant::now() + READ_TIMEOUT.max(self.opts.reply_timeout) * READ_ATTEMPTS;
        while self.stats.frames == 0 {
            if Instant::now() >= deadline {
                let crc = self.decoder.stats.bad_crc;
                return Err(DeviceError::new(
                    if crc > 0 { ErrorKind::Protocol } else { ErrorKind::Timeout },
                    DEVICE,
                    "R",
                    if crc > 0 {
                        format!("the stream started but no frame passed the CRC-16/X-25 ({crc} candidates failed)")
                    } else {
                        "no frame after `r,0,R,0`".to_string()
                    },
                )
                .with_hint("check the baud rate (460800) and the cable"));
            }
            let before = self.stats.frames;
            self.poll(deadline)?;
            if self.stats.frames == before && !self.pending.is_empty() {
                break;
            }
        }
        Ok(())
    }

    fn read_raw(&mut self, attempts: u32) -> DeviceResult<Wrench> {
        let bad_before = self.stats.bad;
        let crc_before = self.decoder.stats.bad_crc;
        let stale = self
            .last_read
            .is_none_or(|t| t.elapsed() > self.opts.stale_after);
        self.poll(Instant::now())?;
        if stale {
            self.pending.clear();
        }
        let wait = READ_TIMEOUT.max(self.opts.reply_timeout) * attempts.max(1);
        let deadline = Instant::now() + wait;
        loop {
            if !self.pending.is_empty() {
                let m = Wrench::mean(&self.pending);
                self.pending.clear();
                self.last_read = Some(Instant::now());
                return Ok(m);
            }
            if Instant::now() >= deadline {
                let bad = self.stats.bad - bad_before;
                let crc = self.decoder.stats.bad_crc - crc_before;
                return Err(if bad > 0 {
                    let status = self.last.map_or(0, |f| f.status);
                    DeviceError::new(
                        ErrorKind::Limit,
                        DEVICE,
                        "stream",
                        format!(
                            "every frame within {} ms was flagged ({bad} frames, status 0x{status:04x}: {}): not averaged",
                            wait.as_millis(),
                            status_names(status)
                        ),
                    )
                    .with_hint("unload the sensor (overrange) or check it (invalid measurement)")
                } else if crc > 0 {
                    DeviceError::new(
                        ErrorKind::Protocol,
                        DEVICE,
                        "stream",
                        format!(
                            "no valid frame within {} ms: {crc} candidate frames failed the CRC-16/X-25",
                            wait.as_millis()
                        ),
                    )
                    .with_hint("check the baud rate (460800) and the cable")
                } else {
                    DeviceError::new(
                        ErrorKind::Timeout,
                        DEVICE,
                        "stream",
                        format!("no frame within {} ms", wait.as_millis()),
                    )
                });
            }
            self.poll(deadline)?;
        }
    }
}

impl<P: Read + Write> ForceSensor for Bota<P> {
    fn read(&mut self) -> DeviceResult<Wrench> {
        Ok(sub(self.read_raw(READ_ATTEMPTS)?, self.offset))
    }

    fn read_once(&mut self) -> DeviceResult<Wrench> {
        Ok(sub(self.read_raw(1)?, self.offset))
    }

    /// Software tare: the mean of [`TARE_READINGS`] readings becomes the offset.
    fn tare(&mut self) -> DeviceResult<()> {
        let mut ws = Vec::with_capacity(TARE_READINGS);
        for _ in 0..TARE_READINGS {
            ws.push(self.read_raw(READ_ATTEMPTS)?);
        }
        self.offset = Wrench::mean(&ws);
        Ok(())
    }

    fn sample_rate_hz(&self) -> f64 {
        1.0 / self.sample_period_s()
    }

    /// The newest frame's timestamp and temperature, and the frames left out or
    /// flagged and CRC failures since the last call.
    fn take_status(&mut self) -> Option<String> {
        let (a, b) = (self.stats(), self.reported);
        self.reported = a;
        let mut parts = Vec::new();
        if let Some(f) = self.last {
            parts.push(format!("t {} us, {:.2} C", f.timestamp, f.temperature_c));
        }
        if a.bad > b.bad {
            parts.push(format!(
                "{} frames left out ({})",
                a.bad - b.bad,
                status_names(a.status_seen)
            ));
        }
        if a.late > b.late {
            parts.push(format!("{} frames app took too long", a.late - b.late));
        }
        if a.bad_crc > b.bad_crc {
            parts.push(format!("{} bad CRC", a.bad_crc - b.bad_crc));
        }
        (!parts.is_empty()).then(|| format!("{DEVICE}: {}", parts.join(", ")))
    }
}
