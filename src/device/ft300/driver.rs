//! Robotiq FT 300 driver, generic over `Read + Write`: polled Modbus RTU reads of the
//! wrench registers ([`Ft300`]) and the binary stream ([`Ft300Stream`], a reader
//! thread keeping the newest sample and every frame since the last
//! [`Ft300Stream::take_samples`]).
//!
//! Tare is a software offset (the FT 300 has no zeroing command in the subset we
//! use): the mean of [`TARE_SAMPLES`] readings is subtracted from later readings.
//! It lives in the driver, so it survives a device reset and carries over between
//! polled and stream mode.
//!
//! Polled replies are framed by length (function code, byte count); bytes before the
//! slave address are skipped, and a frame with a bad CRC makes the reader move on by
//! one byte (resync) until the deadline. Failed attempts are retried (reads are
//! idempotent) after draining; exceptions are [`ErrorKind::Rejected`], never retried.

use std::collections::VecDeque;
use std::io::{Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use super::codec::{
    crc_ok, decode_serial, show_bytes_hex, wrench_from_raw, ExceptionCode, Request, Response,
    StreamDecoder, StreamFrame, StreamStats, FN_WRITE_MULTIPLE, REG_FIRMWARE, REG_SERIAL,
    REG_STREAM, REG_WRENCH, REG_YEAR, SLAVE_ADDRESS, STOP_STREAM, STREAM_START,
};
use crate::device::ft_common::{self, LinkStats, Retry};
use crate::device::{DeviceError, DeviceResult, ErrorKind, ForceSensor, Wrench};

/// Device name in errors.
pub const DEVICE: &str = "ft300";
/// Baud rate (8N1).
pub const BAUD: u32 = 19_200;
/// Deadline for a complete reply: a 17-byte reply takes 8.9 ms at 19200 baud, plus the
/// device's turnaround and USB latency.
pub const REPLY_TIMEOUT: Duration = Duration::from_millis(100);
/// Attempts per command (reads and the stream-start write are idempotent).
pub const MAX_ATTEMPTS: u32 = 3;
/// Quiet time required by the drain before a retry (discards late replies).
pub const DRAIN_QUIET: Duration = REPLY_TIMEOUT;
/// Upper bound on one drain. A streaming device never goes quiet; this bounds it.
pub const DRAIN_MAX: Duration = Duration::from_millis(500);
/// Readings averaged by [`ForceSensor::tare`].
pub const TARE_SAMPLES: usize = 10;
/// Nominal stream rate, Hz.
pub const STREAM_RATE_HZ: f64 = 100.0;
/// Polled rate the wire allows: 8-byte request + 17-byte reply = 250 bit times at
/// 19200 baud = 13.0 ms (turnaround not included).
pub const POLL_RATE_HZ: f64 = 19_200.0 / 250.0;
/// [`Ft300Stream::read`] waits this long for a frame newer than the last one returned.
pub const STREAM_READ_TIMEOUT: Duration = Duration::from_millis(100);
/// With no valid frame for this long, the reader re-sends the stream start (the
/// device may have reset).
pub const STREAM_STALL: Duration = Duration::from_millis(100);
/// After the stop bytes, frames still in flight are decoded until the line is quiet
/// this long (five stream periods).
pub const STOP_QUIET: Duration = Duration::from_millis(50);
/// Rounds of stop bytes before a line that keeps sending is an error: Robotiq's driver
/// repeats its jam signal until the stream stops; we repeat it at most this often,
/// each round waiting up to [`DRAIN_MAX`] for [`STOP_QUIET`].
pub const STOP_ATTEMPTS: u32 = 3;
/// Stream frames a stream-start attempt waits for, beyond the reply deadline, before
/// it is repeated: the write's echo or one valid frame confirms the start.
pub const START_CONFIRM_FRAMES: u32 = 3;
/// Stream period (100 Hz).
pub const STREAM_PERIOD: Duration = Duration::from_millis(10);
/// Frames kept for [`Ft300Stream::take_samples`] (10 s at 100 Hz); older ones are
/// dropped and counted.
pub const SAMPLE_BUFFER: usize = 1000;

/// Identity registers.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Ft300Info {
    /// Firmware version, e.g. `FTS-3.0.1` (registers 500–502).
    pub firmware: String,
    /// Serial number, e.g. `FTS-1234` (registers 510–513: three characters, then a
    /// 32-bit number, 513 the high word; see [`super::codec::decode_serial`]).
    pub serial: String,
    /// Production year (register 514).
    pub year: u16,
}

/// A connected FT 300 in polled (Modbus) mode.
pub struct Ft300<P> {
    port: P,
    slave: u8,
    offset: Wrench,
    retry: Retry,
}

/// Hint on a command that failed for good.
const HINT: &str = "check baud rate (19200), slave address (9) and cable";

fn sub(a: Wrench, b: Wrench) -> Wrench {
    Wrench {
        force_n: [0, 1, 2].map(|i| a.force_n[i] - b.force_n[i]),
        torque_nm: [0, 1, 2].map(|i| a.torque_nm[i] - b.torque_nm[i]),
    }
}

fn mean(ws: &[Wrench]) -> Wrench {
    let n = ws.len().max(1) as f64;
    let mut m = Wrench::default();
    for w in ws {
        for i in 0..3 {
            m.force_n[i] += w.force_n[i] / n;
            m.torque_nm[i] += w.torque_nm[i] / n;
        }
    }
    m
}

impl<P: Read + Write> Ft300<P> {
    /// Connects to slave [`SLAVE_ADDRESS`]: stops a stream left running (sends the stop
    /// bytes until the line is quiet, see [`stop_stream_on`]), then checks the device
    /// answers by reading the wrench registers.
    pub fn connect(port: P) -> DeviceResult<Self> {
        Self::connect_slave(port, SLAVE_ADDRESS)
    }

    /// Connects to another slave address.
    pub fn connect_slave(port: P, slave: u8) -> DeviceResult<Self> {
        Self::connect_with(port, slave, REPLY_TIMEOUT)
    }

    /// Connects to `slave` with another reply deadline (default [`REPLY_TIMEOUT`]; also
    /// the quiet time before a retry). A simulated sensor shares the host's CPU with
    /// everything else, so the simulated bench allows more than a real sensor needs.
    pub fn connect_with(mut port: P, slave: u8, reply_timeout: Duration) -> DeviceResult<Self> {
        stop_stream_on(&mut port, &mut StreamDecoder::default(), &mut Vec::new())?;
        let mut d = Ft300 {
            port,
            slave,
            offset: Wrench::default(),
            retry: Retry::new(DEVICE, reply_timeout, DRAIN_QUIET, DRAIN_MAX, HINT),
        };
        d.read_raw_wrench()?;
        Ok(d)
    }

    /// Link statistics.
    pub fn stats(&self) -> LinkStats {
        self.retry.stats
    }

    /// The software tare offset subtracted from readings.
    pub fn offset(&self) -> Wrench {
        self.offset
    }

    /// Gives the port back.
    pub fn into_inner(self) -> P {
        self.port
    }

    /// Reads `count` holding registers from `start` (function 03).
    pub fn read_registers(&mut self, start: u16, count: u16) -> DeviceResult<Vec<u16>> {
        self.read_registers_n(start, count, MAX_ATTEMPTS)
    }

    fn read_registers_n(
        &mut self,
        start: u16,
        count: u16,
        attempts: u32,
    ) -> DeviceResult<Vec<u16>> {
        let req = Request::ReadHolding {
            slave: self.slave,
            start,
            count,
        };
        match self.transact_n(&req, attempts)? {
            Response::ReadHolding { values, .. } if values.len() == count as usize => Ok(values),
            other => Err(DeviceError::new(
                ErrorKind::Protocol,
                DEVICE,
                req.text(),
                format!("reply does not match the request: {other:?}"),
            )),
        }
    }

    /// Writes registers from `start` (function 16).
    pub fn write_registers(&mut self, start: u16, values: &[u16]) -> DeviceResult<()> {
        let req = Request::WriteMultiple {
            slave: self.slave,
            start,
            values: values.to_vec(),
        };
        match self.transact(&req)? {
            Response::WriteMultiple {
                start: s, count, ..
            } if s == start && count as usize == values.len() => Ok(()),
            other => Err(DeviceError::new(
                ErrorKind::Protocol,
                DEVICE,
                req.text(),
                format!("reply does not match the request: {other:?}"),
            )),
        }
    }

    /// The wrench without the tare offset.
    pub fn read_raw_wrench(&mut self) -> DeviceResult<Wrench> {
        self.read_raw_wrench_n(MAX_ATTEMPTS)
    }

    fn read_raw_wrench_n(&mut self, attempts: u32) -> DeviceResult<Wrench> {
        let v = self.read_registers_n(REG_WRENCH, 6, attempts)?;
        let raw: [i16; 6] = [0, 1, 2, 3, 4, 5].map(|i| v[i] as i16);
        Ok(wrench_from_raw(raw))
    }

    /// Firmware, serial number and production year.
    pub fn info(&mut self) -> DeviceResult<Ft300Info> {
        let fw = self.read_registers(REG_FIRMWARE, 3)?;
        let serial = self.read_registers(REG_SERIAL, 4)?;
        let serial = [serial[0], serial[1], serial[2], serial[3]];
        let year = self.read_registers(REG_YEAR, 1)?;
        let b: Vec<u8> = fw.iter().flat_map(|r| r.to_be_bytes()).collect();
        let letters: String = b[..3]
            .iter()
            .map(|&c| if c.is_ascii_graphic() { c as char } else { '?' })
            .collect();
        Ok(Ft300Info {
            firmware: format!("{letters}-{}.{}.{}", b[3], b[4], b[5]),
            serial: decode_serial(serial),
            year: year[0],
        })
    }

    /// Starts the stream (writes 0x0200 to register 410) and hands the port to a reader
    /// thread. As Robotiq's driver, the start is confirmed by the write's echo *or* by
    /// the stream itself: one valid frame counts when the echo is lost. Each attempt
    /// waits the reply deadline plus [`START_CONFIRM_FRAMES`] stream periods; the write
    /// is repeated (idempotent) up to [`MAX_ATTEMPTS`] times without draining (a
    /// streaming line never goes quiet). Frames that arrive while confirming are kept
    /// (the first samples of the stream). A Modbus exception is `Rejected`.
    ///
    /// On any failure the stop bytes are sent (until the line is quiet, as at connect),
    /// so the sensor is never left streaming: it may have taken the write while both
    /// the echo and the frames were lost or garbled.
    pub fn start_stream(mut self) -> DeviceResult<Ft300Stream<P>>
    where
        P: Send + 'static,
    {
        match self.confirm_stream_start() {
            Ok((decoder, frames)) => Ok(Ft300Stream::spawn(self, decoder, frames)),
            Err(e) if e.kind == ErrorKind::Disconnected => Err(e),
            Err(e) => {
                let stopped = stop_stream_on(
                    &mut self.port,
                    &mut StreamDecoder::default(),
                    &mut Vec::new(),
                );
                let note = match stopped {
                    Ok(()) => "stop bytes sent, the line is quiet".to_string(),
                    Err(s) => format!("stop bytes sent, but {}", s.message),
                };
                Err(DeviceError {
                    message: format!("{}; {note}", e.message),
                    ..e
                })
            }
        }
    }

    /// Sends the stream-start write until its echo or a valid frame arrives; returns
    /// the decoder (fed every byte after the echo, or every byte when no echo came)
    /// and the frames decoded so far.
    fn confirm_stream_start(&mut self) -> DeviceResult<(StreamDecoder, Vec<StreamFrame>)> {
        let req = Request::WriteMultiple {
            slave: self.slave,
            start: REG_STREAM,
            values: vec![STREAM_START],
        };
        let text = req.text();
        let bytes = req.encode();
        let echo = Response::WriteMultiple {
            slave: self.slave,
            start: REG_STREAM,
            count: 1,
        }
        .encode();
        let wait = self.retry.reply_timeout + STREAM_PERIOD * START_CONFIRM_FRAMES;
        let mut rx: Vec<u8> = Vec::new();
        let mut decoder = StreamDecoder::default();
        let mut frames = Vec::new();
        let mut chunk = [0u8; 256];
        self.retry.stats.commands += 1;
        for attempt in 0..MAX_ATTEMPTS {
            if attempt > 0 {
                self.retry.stats.retries += 1;
            }
            ft_common::send(&mut self.port, DEVICE, &text, &bytes)?;
            let deadline = Instant::now() + wait;
            loop {
                if let Some(i) = find(&rx, &echo) {
                    // Confirmed by the echo: decode what surrounds it (frames may
                    // follow it in the same read).
                    let mut d = StreamDecoder::default();
                    let mut f = Vec::new();
                    d.push(&rx[..i], &mut f);
                    d.push(&rx[i + echo.len()..], &mut f);
                    return Ok((d, f));
                }
                if let Some(code) = find_exception(&rx, self.slave, FN_WRITE_MULTIPLE) {
                    return Err(DeviceError::new(
                        ErrorKind::Rejected,
                        DEVICE,
                        &text,
                        format!(
                            "modbus exception {:02x} ({}) to function {FN_WRITE_MULTIPLE:02x}",
                            code.byte(),
                            code.describe()
                        ),
                    ));
                }
                if !frames.is_empty() {
                    // Confirmed by the stream itself: the echo was lost.
                    return Ok((decoder, frames));
                }
                match ft_common::read_until_deadline(
                    &mut self.port,
                    &mut chunk,
                    deadline,
                    DEVICE,
                    &text,
                ) {
                    Ok(n) => {
                        rx.extend_from_slice(&chunk[..n]);
                        decoder.push(&chunk[..n], &mut frames);
                    }
                    Err(e) if e.kind == ErrorKind::Timeout => break,
                    Err(e) => return Err(e),
                }
            }
            self.retry.stats.timeouts += 1;
        }
        let seen = if rx.is_empty() {
            "nothing arrived".to_string()
        } else {
            format!(
                "{} bytes arrived, {} candidate frames failed the CRC: `{}`",
                rx.len(),
                decoder.stats.bad_crc,
                show_bytes_hex(&rx[..rx.len().min(48)])
            )
        };
        Err(DeviceError::new(
            ErrorKind::Timeout,
            DEVICE,
            &text,
            format!(
                "stream start not confirmed: neither the write's echo nor a valid stream \
                 frame within {} ms ({seen}) (after {MAX_ATTEMPTS} attempts)",
                wait.as_millis()
            ),
        )
        .with_hint(HINT))
    }

    /// Sends `req` and reads its reply, retrying timeouts and malformed replies.
    fn transact(&mut self, req: &Request) -> DeviceResult<Response> {
        self.transact_n(req, MAX_ATTEMPTS)
    }

    /// [`Ft300::transact`] with `attempts` attempts. A Modbus exception is a
    /// rejection, never retried.
    fn transact_n(&mut self, req: &Request, attempts: u32) -> DeviceResult<Response> {
        let text = req.text();
        let (slave, timeout) = (self.slave, self.retry.reply_timeout);
        let r = self.retry.transact(
            &mut self.port,
            &text,
            &req.encode(),
            attempts,
            |port, deadline, stats| read_reply(port, slave, deadline, timeout, stats, &text),
        )?;
        match r {
            Response::Exception { function, code, .. } => Err(DeviceError::new(
                ErrorKind::Rejected,
                DEVICE,
                &text,
                format!(
                    "modbus exception {:02x} ({}) to function {function:02x}",
                    code.byte(),
                    code.describe()
                ),
            )),
            r => Ok(r),
        }
    }
}

/// Where `needle` first occurs in `hay`.
fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

/// A Modbus exception reply to `function` from `slave` somewhere in `rx` (CRC checked).
fn find_exception(rx: &[u8], slave: u8, function: u8) -> Option<ExceptionCode> {
    rx.windows(5)
        .find(|w| w[0] == slave && w[1] == function | 0x80 && crc_ok(w))
        .map(|w| ExceptionCode::from_byte(w[2]))
}

/// Stops a stream that may be running: sends the stop bytes (Robotiq's jam signal,
/// 50 × 0xFF) and reads until the line has been quiet for [`STOP_QUIET`], decoding
/// frames still in flight into `frames`. While bytes keep coming for [`DRAIN_MAX`]
/// the stop bytes are sent again, at most [`STOP_ATTEMPTS`] rounds; a line that is
/// still busy then is a [`ErrorKind::Protocol`] error. A device that is not streaming
/// ignores the bytes (a Modbus slave discards a frame that fails its CRC).
pub fn stop_stream_on<P: Read + Write>(
    port: &mut P,
    decoder: &mut StreamDecoder,
    frames: &mut Vec<StreamFrame>,
) -> DeviceResult<()> {
    let what = "stop stream";
    let mut buf = [0u8; 256];
    let mut received = 0usize;
    for _ in 0..STOP_ATTEMPTS {
        ft_common::send(port, DEVICE, what, &STOP_STREAM)?;
        let start = Instant::now();
        let mut last = Instant::now();
        loop {
            if last.elapsed() >= STOP_QUIET {
                return Ok(());
            }
            if start.elapsed() >= DRAIN_MAX {
                break;
            }
            match port.read(&mut buf) {
                Ok(0) => {
                    return Err(DeviceError::new(
                        ErrorKind::Disconnected,
                        DEVICE,
                        what,
                        "port reached end of file",
                    ))
                }
                Ok(n) => {
                    decoder.push(&buf[..n], frames);
                    received += n;
                    last = Instant::now();
                }
                Err(e) if ft_common::is_quiet(&e) => {}
                Err(e) => return Err(ft_common::io_error(DEVICE, what, &e)),
            }
        }
    }
    Err(DeviceError::new(
        ErrorKind::Protocol,
        DEVICE,
        what,
        format!(
            "the line never went quiet for {} ms after {STOP_ATTEMPTS} rounds of stop bytes \
             ({received} bytes received, {} valid frames)",
            STOP_QUIET.as_millis(),
            decoder.stats.frames
        ),
    )
    .with_hint("the device keeps sending: check the baud rate (19200) and that this is an FT 300"))
}

/// Reads one reply frame addressed to `slave` before `deadline` (`timeout` after the
/// request), resynchronising on garbage: the result is Timeout if nothing framed
/// arrived, Protocol if only frames with a bad CRC did.
fn read_reply<P: Read>(
    port: &mut P,
    slave: u8,
    deadline: Instant,
    timeout: Duration,
    stats: &mut LinkStats,
    text: &str,
) -> DeviceResult<Response> {
    let mut buf: Vec<u8> = Vec::with_capacity(64);
    let mut chunk = [0u8; 64];
    let mut bad: Option<String> = None;
    let mut skipped = false;
    loop {
        // Frame what we have.
        loop {
            while !buf.is_empty() && buf[0] != slave {
                buf.remove(0);
                skipped = true;
            }
            match Response::frame_len(&buf) {
                None => break,
                Some(Err(_)) => {
                    buf.remove(0);
                    skipped = true;
                }
                Some(Ok(n)) if buf.len() >= n => match Response::decode(&buf[..n]) {
                    Ok(r) => {
                        if skipped || bad.is_some() {
                            stats.resyncs += 1;
                        }
                        return Ok(r);
                    }
                    Err(e) => {
                        bad = Some(e.to_string());
                        buf.remove(0);
                        skipped = true;
                    }
                },
                Some(Ok(_)) => break,
            }
        }
        match ft_common::read_until_deadline(port, &mut chunk, deadline, DEVICE, text) {
            Ok(n) => buf.extend_from_slice(&chunk[..n]),
            Err(e) if e.kind == ErrorKind::Timeout => {
                return Err(match bad {
                    Some(b) => DeviceError::new(ErrorKind::Protocol, DEVICE, text, b),
                    None if !buf.is_empty() => DeviceError::new(
                        ErrorKind::Timeout,
                        DEVICE,
                        text,
                        format!(
                            "incomplete reply within {} ms: `{}`",
                            timeout.as_millis(),
                            show_bytes_hex(&buf)
                        ),
                    ),
                    None => DeviceError::new(
                        ErrorKind::Timeout,
                        DEVICE,
                        text,
                        format!("no reply within {} ms", timeout.as_millis()),
                    ),
                })
            }
            Err(e) => return Err(e),
        }
    }
}

impl<P: Read + Write> ForceSensor for Ft300<P> {
    fn read(&mut self) -> DeviceResult<Wrench> {
        Ok(sub(self.read_raw_wrench()?, self.offset))
    }

    fn read_once(&mut self) -> DeviceResult<Wrench> {
        Ok(sub(self.read_raw_wrench_n(1)?, self.offset))
    }

    /// Software tare: the mean of [`TARE_SAMPLES`] raw readings becomes the offset.
    fn tare(&mut self) -> DeviceResult<()> {
        let mut ws = Vec::with_capacity(TARE_SAMPLES);
        for _ in 0..TARE_SAMPLES {
            ws.push(self.read_raw_wrench()?);
        }
        self.offset = mean(&ws);
        Ok(())
    }

    fn sample_rate_hz(&self) -> f64 {
        POLL_RATE_HZ
    }
}

/// A streamed sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StreamSample {
    /// Sequence number of the frame since the stream started (1, 2, ...).
    pub seq: u64,
    /// The wrench, tare offset not applied.
    pub raw_wrench: Wrench,
    /// When the reader decoded it.
    pub received: Instant,
}

/// What [`Ft300Stream::stop`] reports.
#[derive(Debug, Clone)]
pub struct StreamSummary {
    /// Final decoder counters (frames, bad CRC, bytes skipped, restarts).
    pub stats: StreamStats,
    /// Samples dropped from the buffer because nobody took them.
    pub overflowed: u64,
    /// Samples not yet taken, in-flight frames decoded after the stop bytes included.
    pub remaining: Vec<StreamSample>,
}

#[derive(Default)]
struct Shared {
    latest: Option<StreamSample>,
    samples: VecDeque<StreamSample>,
    overflowed: u64,
    stats: StreamStats,
    error: Option<DeviceError>,
}

type SharedState = Arc<(Mutex<Shared>, Condvar)>;

/// An FT 300 in stream mode: a reader thread owns the port until [`Ft300Stream::stop`].
pub struct Ft300Stream<P: Read + Write + Send + 'static> {
    shared: SharedState,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<(P, StreamDecoder)>>,
    slave: u8,
    offset: Wrench,
    /// The polled link's retry policy and statistics, restored by [`Ft300Stream::stop`].
    retry: Retry,
    last_seq: u64,
}

fn lock(s: &SharedState) -> std::sync::MutexGuard<'_, Shared> {
    s.0.lock().unwrap_or_else(|p| p.into_inner())
}

impl<P: Read + Write + Send + 'static> Ft300Stream<P> {
    /// Hands the port to a reader thread; `decoder` and `frames` are what the start
    /// confirmation already read (the first frames become samples 1, 2, ...).
    fn spawn(d: Ft300<P>, decoder: StreamDecoder, frames: Vec<StreamFrame>) -> Self {
        let mut state = Shared::default();
        let now = Instant::now();
        for (seq, f) in (1..).zip(&frames) {
            push_sample(
                &mut state,
                StreamSample {
                    seq,
                    raw_wrench: f.wrench(),
                    received: now,
                },
            );
        }
        state.stats = decoder.stats;
        let first_seq = frames.len() as u64;
        let shared: SharedState = Arc::new((Mutex::new(state), Condvar::new()));
        let stop = Arc::new(AtomicBool::new(false));
        let (s2, stop2) = (Arc::clone(&shared), Arc::clone(&stop));
        let slave = d.slave;
        let port = d.port;
        let thread = std::thread::spawn(move || reader(port, slave, decoder, first_seq, s2, stop2));
        Ft300Stream {
            shared,
            stop,
            thread: Some(thread),
            slave,
            offset: d.offset,
            retry: d.retry,
            last_seq: 0,
        }
    }

    /// Decoder counters (frames, bad CRC, bytes skipped, restarts).
    pub fn stream_stats(&self) -> StreamStats {
        lock(&self.shared).stats
    }

    /// Frames dropped from the sample buffer because nobody took them.
    pub fn overflowed(&self) -> u64 {
        lock(&self.shared).overflowed
    }

    /// Every frame decoded since the last call (oldest first, at most
    /// [`SAMPLE_BUFFER`]).
    pub fn take_samples(&mut self) -> Vec<StreamSample> {
        let mut g = lock(&self.shared);
        g.samples.drain(..).collect()
    }

    /// The newest sample, waiting up to [`STREAM_READ_TIMEOUT`] (or the polled link's
    /// longer reply deadline, see [`Ft300::connect_with`]) for one newer than the
    /// last returned. Samples in between are skipped (see [`Self::take_samples`]).
    pub fn read_sample(&mut self) -> DeviceResult<StreamSample> {
        // A polled link given a longer reply deadline (the simulated bench) waits as
        // long for a frame.
        let timeout = STREAM_READ_TIMEOUT.max(self.retry.reply_timeout);
        let deadline = Instant::now() + timeout;
        let (m, cv) = &*self.shared;
        let mut g = m.lock().unwrap_or_else(|p| p.into_inner());
        loop {
            if let Some(s) = g.latest {
                if s.seq > self.last_seq {
                    self.last_seq = s.seq;
                    return Ok(s);
                }
            }
            if let Some(e) = &g.error {
                return Err(e.clone());
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(DeviceError::new(
                    ErrorKind::Timeout,
                    DEVICE,
                    "stream",
                    format!("no new frame within {} ms", timeout.as_millis()),
                ));
            }
            g = cv
                .wait_timeout(g, deadline - now)
                .map(|(g, _)| g)
                .unwrap_or_else(|p| p.into_inner().0);
        }
    }

    /// Stops the stream: ends the reader, sends the stop bytes, decodes frames still in
    /// flight until the line is quiet, and returns the polled driver with a summary
    /// (final counters and the samples nobody took yet).
    pub fn stop(mut self) -> DeviceResult<(Ft300<P>, StreamSummary)> {
        self.stop.store(true, Ordering::SeqCst);
        let (mut port, mut decoder) = match self.thread.take().map(|t| t.join()) {
            Some(Ok(pd)) => pd,
            _ => {
                return Err(DeviceError::new(
                    ErrorKind::Other,
                    DEVICE,
                    "stop stream",
                    "stream reader thread panicked",
                ))
            }
        };
        if let Some(e) = lock(&self.shared).error.clone() {
            if e.kind != ErrorKind::Disconnected {
                // The reader failed but the link may be up: do not leave the sensor
                // streaming.
                let _ = stop_stream_on(&mut port, &mut decoder, &mut Vec::new());
            }
            return Err(e);
        }
        let mut frames = Vec::new();
        stop_stream_on(&mut port, &mut decoder, &mut frames)?;
        let summary = {
            let mut g = lock(&self.shared);
            let restarts = g.stats.restarts;
            g.stats = decoder.stats;
            g.stats.restarts = restarts;
            let first = g.latest.map_or(0, |s| s.seq) + 1;
            for (seq, f) in (first..).zip(frames) {
                let s = StreamSample {
                    seq,
                    raw_wrench: f.wrench(),
                    received: Instant::now(),
                };
                push_sample(&mut g, s);
            }
            StreamSummary {
                stats: g.stats,
                overflowed: g.overflowed,
                remaining: g.samples.drain(..).collect(),
            }
        };
        let d = Ft300 {
            port,
            slave: self.slave,
            offset: self.offset,
            retry: self.retry.clone(),
        };
        Ok((d, summary))
    }
}

fn push_sample(g: &mut Shared, s: StreamSample) {
    g.latest = Some(s);
    if g.samples.len() >= SAMPLE_BUFFER {
        g.samples.pop_front();
        g.overflowed += 1;
    }
    g.samples.push_back(s);
}

/// The reader thread: decode, publish, restart a stalled stream, stop on request or
/// when the port goes away.
fn reader<P: Read + Write>(
    mut port: P,
    slave: u8,
    mut decoder: StreamDecoder,
    mut seq: u64,
    shared: SharedState,
    stop: Arc<AtomicBool>,
) -> (P, StreamDecoder) {
    let mut buf = [0u8; 512];
    let mut frames: Vec<StreamFrame> = Vec::new();
    let mut last_frame = Instant::now();
    let restart = Request::WriteMultiple {
        slave,
        start: REG_STREAM,
        values: vec![STREAM_START],
    }
    .encode();
    let fail = |e: DeviceError| {
        let (m, cv) = &*shared;
        m.lock().unwrap_or_else(|p| p.into_inner()).error = Some(e);
        cv.notify_all();
    };
    while !stop.load(Ordering::SeqCst) {
        match port.read(&mut buf) {
            Ok(0) => {
                fail(DeviceError::new(
                    ErrorKind::Disconnected,
                    DEVICE,
                    "stream",
                    "port reached end of file",
                ));
                break;
            }
            Ok(n) => {
                frames.clear();
                decoder.push(&buf[..n], &mut frames);
                if !frames.is_empty() {
                    last_frame = Instant::now();
                    let (m, cv) = &*shared;
                    let mut g = m.lock().unwrap_or_else(|p| p.into_inner());
                    for f in &frames {
                        seq += 1;
                        push_sample(
                            &mut g,
                            StreamSample {
                                seq,
                                raw_wrench: f.wrench(),
                                received: last_frame,
                            },
                        );
                    }
                    let restarts = g.stats.restarts;
                    g.stats = decoder.stats;
                    g.stats.restarts = restarts;
                    cv.notify_all();
                }
            }
            Err(e) if ft_common::is_quiet(&e) => {}
            Err(e) => {
                fail(ft_common::io_error(DEVICE, "stream", &e));
                break;
            }
        }
        if last_frame.elapsed() > STREAM_STALL {
            // No frame for 10 periods: the device may have reset and left stream mode.
            // Re-sending the start is safe (idempotent); its acknowledgement is skipped
            // by the frame decoder.
            if let Err(e) = port.write_all(&restart).and_then(|_| port.flush()) {
                fail(ft_common::io_error(DEVICE, "stream restart", &e));
                break;
            }
            lock(&shared).stats.restarts += 1;
            last_frame = Instant::now();
        }
    }
    (port, decoder)
}

impl<P: Read + Write + Send + 'static> ForceSensor for Ft300Stream<P> {
    fn read(&mut self) -> DeviceResult<Wrench> {
        Ok(sub(self.read_sample()?.raw_wrench, self.offset))
    }

    /// Software tare: the mean of the next [`TARE_SAMPLES`] frames becomes the offset.
    fn tare(&mut self) -> DeviceResult<()> {
        let mut ws = Vec::with_capacity(TARE_SAMPLES);
        for _ in 0..TARE_SAMPLES {
            ws.push(self.read_sample()?.raw_wrench);
        }
        self.offset = mean(&ws);
        Ok(())
    }

    fn sample_rate_hz(&self) -> f64 {
        STREAM_RATE_HZ
    }
}

impl<P: Read + Write + Send + 'static> Drop for Ft300Stream<P> {
    fn drop(&mut self) {
        // Stop the reader thread, then the device's stream (best effort: a stream
        // dropped on an error path must not leave the sensor streaming), without
        // waiting for the line to go quiet.
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            if let Ok((mut port, _)) = t.join() {
                let _ = port.write_all(&STOP_STREAM).and_then(|_| port.flush());
            }
        }
    }
}
