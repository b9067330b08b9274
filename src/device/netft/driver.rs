//! ATI Net F/T (and OnRobot HEX) driver, generic over a [`Datagram`] transport: starts
//! real-time RDT streaming, keeps it running, and turns the records that arrive into
//! readings; the calibration (counts per force / torque unit) is read from the device
//! over TCP ([`read_calinfo`]) by whoever opens the driver.
//!
//! UDP is lossy by design, so the driver expects and handles:
//! - **losses**: a record whose RDT sequence skips ahead counts the gap as lost;
//! - **duplicates and stale records**: a sequence that does not advance is dropped
//!   (never averaged); a sequence far behind (more than [`STALE_WINDOW`] records and
//!   [`STALE_SPAN`] at the measured rate) is a restarted stream (device reboot, a
//!   re-sent start request) and becomes the new baseline;
//! - **a stream that never pauses**: every wait ends on a deadline or a datagram
//!   count ([`MAX_DRAIN`]), never on the socket falling silent, so reads return at
//!   100 Hz, 1 kHz and 7 kHz alike;
//! - **silence**: the start request is re-sent after [`START_RESEND`] without a
//!   datagram; after [`DEAD_AFTER`] of silence the sensor is `Disconnected`, named;
//! - **datagrams that are not records** (wrong length): counted and dropped;
//! - **a non-zero status word**: the record is not averaged, the word is counted and
//!   reported ([`NetFt::take_status`]); a reading that finds only such records fails
//!   with the status word in the message.
//!
//! A reading ([`ForceSensor::read`]) is the mean of the good records received since the
//! previous reading, at most the newest [`MEAN_WINDOW`] of them (the socket may have
//! queued older ones while nobody read), waiting for at least one new good record.
//! At up to 7000 records/s this averages at the device's rate without handing every
//! record to the caller; [`ForceSensor::sample_rate_hz`] reports at most
//! [`READ_RATE_CAP_HZ`] so callers that pace their reads to it do not spin.
//!
//! Tare sends the device's software bias (0x0042) and then takes the mean of the next
//! records as a residual offset in the driver, so a bias request lost on the way (UDP)
//! still leaves the readings zeroed.

use std::collections::VecDeque;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

use super::codec::{
    calinfo_request, CalInfo, Command, Record, Request, Scale, CAL_REPLY_LEN, RECORD_LEN,
};
use super::transport::{resolve, Datagram};
use crate::device::{DeviceError, DeviceResult, ErrorKind, ForceSensor, Wrench};

/// Device name in errors (ATI Net F/T).
pub const DEVICE: &str = "netft";
/// Device name in errors (OnRobot HEX).
pub const DEVICE_HEX: &str = "onrobot-hex";
/// Deadline for a new good record per reading attempt.
pub const READ_TIMEOUT: Duration = Duration::from_millis(100);
/// Attempts of [`ForceSensor::read`] ([`ForceSensor::read_once`] makes one).
pub const MAX_ATTEMPTS: u32 = 3;
/// Silence after which the start request is sent again.
pub const START_RESEND: Duration = Duration::from_millis(50);
/// Silence after which the sensor is declared gone (`Disconnected`).
pub const DEAD_AFTER: Duration = Duration::from_secs(2);
/// Deadline for the first record at connect.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(2);
/// Deadline of the TCP calibration query (connect, request, reply).
pub const CAL_TIMEOUT: Duration = Duration::from_secs(2);
/// How long connect watches the stream to estimate the record rate.
pub const RATE_PROBE: Duration = Duration::from_millis(100);
/// A sequence this far (or further) behind the newest is a restarted stream, not a
/// stale record, unless [`STALE_SPAN`] of records at the measured rate is more.
pub const STALE_WINDOW: u32 = 256;
/// A record delayed by up to this much is stale (reordered), not a restart, at any
/// rate (at 7 kHz, 700 records).
pub const STALE_SPAN: Duration = Duration::from_millis(100);
/// A reading averages at most the records of this last stretch of the stream.
pub const MEAN_WINDOW: Duration = Duration::from_millis(10);
/// [`ForceSensor::sample_rate_hz`] reports at most this (each reading averages the
/// records in between).
pub const READ_RATE_CAP_HZ: f64 = 500.0;
/// Good records kept for the next reading at most (older ones are dropped first).
pub const MAX_PENDING: usize = 100_000;
/// Datagrams taken by one drain of the socket at most (a full default socket buffer
/// holds a few hundred records).
pub const MAX_DRAIN: usize = 4096;
/// Record rate assumed until measured.
pub const DEFAULT_RATE_HZ: f64 = 1000.0;
/// Readings averaged by tare for the residual offset.
pub const TARE_READINGS: usize = 10;
/// After a bias request, records for this long are discarded (produced before the
/// device applied it, or in flight).
pub const BIAS_SETTLE: Duration = Duration::from_millis(30);

/// What happened on the stream since the driver connected.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct StreamStats {
    /// Datagrams received.
    pub datagrams: u64,
    /// Records accepted (good or with a status word).
    pub records: u64,
    /// Records averaged (status 0).
    pub good: u64,
    /// Records missing (gaps in the RDT sequence).
    pub lost: u64,
    /// Records dropped as duplicates (same sequence as the newest).
    pub duplicates: u64,
    /// Records dropped as stale (behind the newest, arrived out of order).
    pub stale: u64,
    /// Stream restarts seen (the sequence jumped back).
    pub restarts: u64,
    /// Datagrams that were not records (wrong length).
    pub malformed: u64,
    /// Records with a non-zero status word (never averaged).
    pub bad_status: u64,
    /// The last non-zero status word.
    pub last_status: u32,
    /// Start requests sent (the first included).
    pub start_requests: u64,
}

/// Options of a [`NetFt`] connection.
#[derive(Debug, Clone, Copy)]
pub struct NetFtOptions {
    /// Counts per N and per N·m.
    pub scale: Scale,
    /// Deadline for a new good record per reading attempt.
    pub read_timeout: Duration,
    /// Device name in errors ([`DEVICE`] or [`DEVICE_HEX`]).
    pub device: &'static str,
    /// Records queued longer than this after the previous reading are stale: a reading
    /// after a longer pause waits for records sent after it started.
    pub stale_after: Duration,
}

impl NetFtOptions {
    /// Defaults for an ATI Net F/T with `scale`.
    pub fn netft(scale: Scale) -> Self {
        NetFtOptions {
            scale,
            read_timeout: READ_TIMEOUT,
            device: DEVICE,
            stale_after: MEAN_WINDOW,
        }
    }

    /// Defaults for an OnRobot HEX (its fixed scale).
    pub fn onrobot_hex() -> Self {
        NetFtOptions {
            scale: Scale::ONROBOT_HEX,
            read_timeout: READ_TIMEOUT,
            device: DEVICE_HEX,
            stale_after: MEAN_WINDOW,
        }
    }
}

/// A streaming Net F/T.
pub struct NetFt<T: Datagram> {
    link: T,
    opts: NetFtOptions,
    /// Newest accepted RDT sequence.
    last_seq: Option<u32>,
    /// F/T sequence of that record.
    last_ft: Option<u32>,
    /// Good records since the last reading: (sequence, raw wrench).
    pending: VecDeque<(u32, Wrench)>,
    offset: Wrench,
    stats: StreamStats,
    /// Stats at the last [`NetFt::take_status`].
    reported: StreamStats,
    last_rx: Instant,
    last_start: Instant,
    rate_hz: f64,
    /// When the last reading returned.
    last_read: Option<Instant>,
    buf: [u8; 64],
}

/// The software offset subtracted from a raw wrench.
fn sub(a: Wrench, b: Wrench) -> Wrench {
    Wrench {
        force_n: [0, 1, 2].map(|i| a.force_n[i] - b.force_n[i]),
        torque_nm: [0, 1, 2].map(|i| a.torque_nm[i] - b.torque_nm[i]),
    }
}

impl<T: Datagram> NetFt<T> {
    /// Starts real-time streaming on `link` and waits for the first record (re-sending
    /// the start request every [`START_RESEND`]), then watches the stream for
    /// [`RATE_PROBE`] to measure its rate. Nothing within [`CONNECT_TIMEOUT`] is
    /// `Disconnected`, naming the peer.
    pub fn connect(link: T, opts: NetFtOptions) -> DeviceResult<Self> {
        let now = Instant::now();
        let mut d = NetFt {
            link,
            opts,
            last_seq: None,
            last_ft: None,
            pending: VecDeque::new(),
            offset: Wrench::default(),
            stats: StreamStats::default(),
            reported: StreamStats::default(),
            last_rx: now,
            last_start: now,
            rate_hz: DEFAULT_RATE_HZ,
            last_read: None,
            buf: [0u8; 64],
        };
        d.send(Request::new(Command::StartRealtime))?;
        d.stats.start_requests += 1;
        let deadline = now + CONNECT_TIMEOUT;
        while d.stats.records == 0 {
            if Instant::now() >= deadline {
                return Err(DeviceError::new(
                    ErrorKind::Disconnected,
                    d.opts.device,
                    Request::new(Command::StartRealtime).text(),
                    format!(
                        "no RDT record from {} within {} ms ({} start requests sent)",
                        d.link.peer(),
                        CONNECT_TIMEOUT.as_millis(),
                        d.stats.start_requests
                    ),
                )
                .with_hint("check the sensor's address, that it is powered and on this network, and the RDT port (49152)"));
            }
            d.take_one(Instant::now() + START_RESEND.min(deadline - Instant::now()))?;
            d.resend_if_silent()?;
        }
        // Rate from the sequence advance over the probe (records sent, lost or not).
        let first = (d.last_seq.unwrap_or(0), Instant::now());
        d.take_until(first.1 + RATE_PROBE)?;
        if let Some(last) = d.last_seq {
            let n = last.wrapping_sub(first.0);
            let dt = first.1.elapsed().as_secs_f64();
            if n > 0 && n < u32::MAX / 2 && dt > 0.0 {
                d.rate_hz = n as f64 / dt;
            }
        }
        // The records just watched are current: the first reading averages them.
        d.last_read = Some(Instant::now());
        Ok(d)
    }

    /// Link statistics.
    pub fn stats(&self) -> StreamStats {
        self.stats
    }

    /// The record rate measured at connect, Hz.
    pub fn measured_rate_hz(&self) -> f64 {
        self.rate_hz
    }

    /// The scale in use.
    pub fn scale(&self) -> Scale {
        self.opts.scale
    }

    /// The software offset subtracted from readings.
    pub fn offset(&self) -> Wrench {
        self.offset
    }

    /// What the stream reported since the last call, when anything is worth saying:
    /// records with a non-zero status word (never averaged), losses, duplicates,
    /// stale records, restarts, malformed datagrams. `None` for a clean stretch.
    pub fn take_status(&mut self) -> Option<String> {
        let (a, b) = (self.stats, self.reported);
        self.reported = a;
        let mut parts = Vec::new();
        if a.bad_status > b.bad_status {
            parts.push(format!(
                "{} records with status 0x{:08x} (not averaged)",
                a.bad_status - b.bad_status,
                a.last_status
            ));
        }
        for (what, x, y) in [
            ("lost", a.lost, b.lost),
            ("duplicate", a.duplicates, b.duplicates),
            ("stale", a.stale, b.stale),
            ("restart", a.restarts, b.restarts),
            ("malformed", a.malformed, b.malformed),
        ] {
            if x > y {
                parts.push(format!("{} {what}", x - y));
            }
        }
        (!parts.is_empty()).then(|| format!("{}: {}", self.opts.device, parts.join(", ")))
    }

    /// Stops streaming (UDP gives no acknowledgement; dropping the driver sends it too).
    pub fn stop(&mut self) -> DeviceResult<()> {
        self.send(Request::new(Command::Stop))
    }

    /// Sends the device's software bias (0x0042): later records read zero at the
    /// current load. Not acknowledged (UDP); see [`ForceSensor::tare`] for the
    /// verified form.
    pub fn set_bias(&mut self) -> DeviceResult<()> {
        self.send(Request::new(Command::SetBias))
    }

    /// Sends an OnRobot HEX filter (0x0081) or rate (0x0082) command.
    pub fn send_command(&mut self, command: Command, argument: u32) -> DeviceResult<()> {
        self.send(Request {
            command,
            count: argument,
        })
    }

    fn send(&mut self, r: Request) -> DeviceResult<()> {
        self.link.send(&r.encode()).map_err(|e| {
            let kind = if e.kind() == std::io::ErrorKind::ConnectionRefused {
                ErrorKind::Disconnected
            } else {
                ErrorKind::Other
            };
            DeviceError::new(
                kind,
                self.opts.device,
                r.text(),
                format!("cannot send to {}: {e}", self.link.peer()),
            )
        })
    }

    fn resend_if_silent(&mut self) -> DeviceResult<()> {
        let silent = self.last_rx.max(self.last_start).elapsed();
        if silent >= START_RESEND {
            self.send(Request::new(Command::StartRealtime))?;
            self.stats.start_requests += 1;
            self.last_start = Instant::now();
        }
        Ok(())
    }

    /// Receives at most one datagram, waiting until `deadline` (a past deadline takes
    /// only one already waiting), and handles it. `false` when none came.
    fn take_one(&mut self, deadline: Instant) -> DeviceResult<bool> {
        let n = match self.link.recv(&mut self.buf, deadline) {
            Ok(Some(n)) => n,
            Ok(None) => return Ok(false),
            Err(e) => {
                let refused = e.kind() == std::io::ErrorKind::ConnectionRefused;
                return Err(DeviceError::new(
                    if refused {
                        ErrorKind::Disconnected
                    } else {
                        ErrorKind::Other
                    },
                    self.opts.device,
                    "RDT stream",
                    if refused {
                        format!(
                            "{} refused the RDT request: nothing listens on that UDP port",
                            self.link.peer()
                        )
                    } else {
                        format!("receiving from {}: {e}", self.link.peer())
                    },
                ));
            }
        };
        self.last_rx = Instant::now();
        self.stats.datagrams += 1;
        match Record::decode(&self.buf[..n.min(self.buf.len())]) {
            Ok(r) if n == RECORD_LEN => self.accept(r),
            _ => self.stats.malformed += 1,
        }
        Ok(true)
    }

    /// Takes the datagrams already waiting, never waiting for more, and at most
    /// [`MAX_DRAIN`] of them: a stream that never pauses (1 kHz, 7 kHz) cannot hold
    /// the caller, whatever the socket's timing.
    fn drain(&mut self) -> DeviceResult<()> {
        let past = Instant::now();
        for _ in 0..MAX_DRAIN {
            if !self.take_one(past)? {
                break;
            }
        }
        Ok(())
    }

    /// Takes every datagram that arrives until `deadline`, and stops at it however
    /// busy the stream is.
    fn take_until(&mut self, deadline: Instant) -> DeviceResult<()> {
        while Instant::now() < deadline {
            self.take_one(deadline)?;
        }
        Ok(())
    }

    /// Waits until a good record is pending or `deadline` passes, then takes what else
    /// is already waiting.
    fn wait_good(&mut self, deadline: Instant) -> DeviceResult<()> {
        while self.pending.is_empty() && Instant::now() < deadline {
            self.take_one(deadline)?;
        }
        self.drain()
    }

    /// Sequence bookkeeping for one record; a good one joins the pending readings.
    fn accept(&mut self, r: Record) {
        if let Some(last) = self.last_seq {
            let ahead = r.rdt_seq.wrapping_sub(last);
            let behind = last.wrapping_sub(r.rdt_seq);
            if ahead == 0 {
                self.stats.duplicates += 1;
                return;
            }
            // Behind in the RDT sequence: stale, unless the device's own F/T sample
            // counter (which a new start request does not reset) moved on, which makes
            // it a restarted stream.
            let ft_ahead = self
                .last_ft
                .is_some_and(|f| r.ft_seq.wrapping_sub(f).wrapping_sub(1) < u32::MAX / 2);
            let window = STALE_WINDOW.max((self.rate_hz * STALE_SPAN.as_secs_f64()) as u32);
            if behind > 0 && behind < window && !ft_ahead {
                self.stats.stale += 1;
                return;
            }
            if behind > 0 && behind < window {
                self.stats.restarts += 1;
                self.pending.clear();
                self.last_seq = Some(r.rdt_seq);
                self.last_ft = Some(r.ft_seq);
                self.take_record(r);
                return;
            }
            if ahead < u32::MAX / 2 {
                self.stats.lost += (ahead - 1) as u64;
            } else {
                // Far behind: the device restarted its sequence.
                self.stats.restarts += 1;
                self.pending.clear();
            }
        }
        self.last_seq = Some(r.rdt_seq);
        self.last_ft = Some(r.ft_seq);
        self.take_record(r);
    }

    fn take_record(&mut self, r: Record) {
        self.stats.records += 1;
        if r.status != 0 {
            self.stats.bad_status += 1;
            self.stats.last_status = r.status;
            return;
        }
        self.stats.good += 1;
        if self.pending.len() >= MAX_PENDING {
            self.pending.pop_front();
        }
        self.pending
            .push_back((r.rdt_seq, self.opts.scale.wrench(&r.counts)));
    }

    /// The mean raw wrench of the pending good records (the newest [`MEAN_WINDOW`]),
    /// waiting for one in up to `attempts` windows of the read deadline.
    fn read_raw(&mut self, attempts: u32) -> DeviceResult<Wrench> {
        let bad_before = self.stats.bad_status;
        // What the socket queued since the previous reading: when that reading was
        // recent, these are the records in between (averaged); after a longer pause
        // the queue may hold old records (a full socket buffer drops the new ones),
        // so they are discarded and the reading waits for records sent from now on.
        let stale = self
            .last_read
            .is_none_or(|t| t.elapsed() > self.opts.stale_after);
        self.drain()?;
        if stale {
            self.pending.clear();
        }
        let deadline = Instant::now() + self.opts.read_timeout * attempts.max(1);
        loop {
            if let Some(w) = self.mean_pending() {
                self.last_read = Some(Instant::now());
                return Ok(w);
            }
            let now = Instant::now();
            if self.last_rx.elapsed() >= DEAD_AFTER {
                return Err(DeviceError::new(
                    ErrorKind::Disconnected,
                    self.opts.device,
                    "RDT stream",
                    format!(
                        "no datagram from {} for {} ms ({} start requests sent)",
                        self.link.peer(),
                        self.last_rx.elapsed().as_millis(),
                        self.stats.start_requests
                    ),
                )
                .with_hint("the sensor vanished from the network: check its power and cable"));
            }
            if now >= deadline {
                let bad = self.stats.bad_status - bad_before;
                return Err(if bad > 0 {
                    DeviceError::new(
                        ErrorKind::Limit,
                        self.opts.device,
                        "RDT stream",
                        format!(
                            "every record within {} ms had a non-zero status word ({bad} records, last 0x{:08x}): not averaged",
                            (self.opts.read_timeout * attempts.max(1)).as_millis(),
                            self.stats.last_status
                        ),
                    )
                    .with_hint("the sensor reports a fault (saturation or a hardware error): see its web page's status")
                } else {
                    DeviceError::new(
                        ErrorKind::Timeout,
                        self.opts.device,
                        "RDT stream",
                        format!(
                            "no good record from {} within {} ms",
                            self.link.peer(),
                            (self.opts.read_timeout * attempts.max(1)).as_millis()
                        ),
                    )
                });
            }
            self.resend_if_silent()?;
            self.wait_good((now + START_RESEND).min(deadline))?;
        }
    }

    /// Mean of the pending records of the newest [`MEAN_WINDOW`], `None` when none.
    fn mean_pending(&mut self) -> Option<Wrench> {
        let newest = self.pending.back()?.0;
        let window = ((self.rate_hz * MEAN_WINDOW.as_secs_f64()).ceil() as u32).max(1);
        let recent: Vec<Wrench> = self
            .pending
            .iter()
            .filter(|(s, _)| newest.wrapping_sub(*s) < window)
            .map(|(_, w)| *w)
            .collect();
        self.pending.clear();
        Some(Wrench::mean(&recent))
    }
}

impl<T: Datagram> ForceSensor for NetFt<T> {
    fn read(&mut self) -> DeviceResult<Wrench> {
        Ok(sub(self.read_raw(MAX_ATTEMPTS)?, self.offset))
    }

    fn read_once(&mut self) -> DeviceResult<Wrench> {
        Ok(sub(self.read_raw(1)?, self.offset))
    }

    /// Device bias (0x0042), records of [`BIAS_SETTLE`] discarded, then the mean of
    /// [`TARE_READINGS`] readings becomes the residual offset.
    fn tare(&mut self) -> DeviceResult<()> {
        self.set_bias()?;
        self.take_until(Instant::now() + BIAS_SETTLE)?;
        self.pending.clear();
        let mut ws = Vec::with_capacity(TARE_READINGS);
        for _ in 0..TARE_READINGS {
            ws.push(self.read_raw(MAX_ATTEMPTS)?);
        }
        self.offset = Wrench::mean(&ws);
        Ok(())
    }

    fn sample_rate_hz(&self) -> f64 {
        self.rate_hz.min(READ_RATE_CAP_HZ)
    }

    fn take_status(&mut self) -> Option<String> {
        NetFt::take_status(self)
    }
}

impl<T: Datagram> Drop for NetFt<T> {
    fn drop(&mut self) {
        // Best effort: do not leave the sensor streaming at us.
        let _ = self.link.send(&Request::new(Command::Stop).encode());
    }
}

/// Reads the calibration over TCP (READCALINFO on `port`, 49151 on a Net F/T), every
/// step within [`CAL_TIMEOUT`]. Errors name the host and port.
pub fn read_calinfo(host: &str, port: u16) -> DeviceResult<CalInfo> {
    let addr: SocketAddr = resolve(DEVICE, host, port)?;
    let what = format!("READCALINFO {host}:{port}");
    let fail = |kind: ErrorKind, msg: String| {
        DeviceError::new(kind, DEVICE, &what, msg).with_hint(
            "the Net F/T answers READCALINFO on TCP 49151; give counts_per_force / counts_per_torque in the bench file to skip the query",
        )
    };
    let mut s = TcpStream::connect_timeout(&addr, CAL_TIMEOUT).map_err(|e| {
        let kind = match e.kind() {
            std::io::ErrorKind::TimedOut => ErrorKind::Timeout,
            _ => ErrorKind::Disconnected,
        };
        fail(kind, format!("cannot connect to {addr}: {e}"))
    })?;
    let io = |e: std::io::Error| {
        let kind = match e.kind() {
            std::io::ErrorKind::TimedOut | std::io::ErrorKind::WouldBlock => ErrorKind::Timeout,
            std::io::ErrorKind::UnexpectedEof => ErrorKind::Protocol,
            _ => ErrorKind::Disconnected,
        };
        fail(kind, format!("READCALINFO exchange with {addr}: {e}"))
    };
    s.set_read_timeout(Some(CAL_TIMEOUT)).map_err(io)?;
    s.set_write_timeout(Some(CAL_TIMEOUT)).map_err(io)?;
    calinfo_exchange(&mut s, &what, Instant::now() + CAL_TIMEOUT)
        .map_err(|e| e.with_hint("the Net F/T answers READCALINFO on TCP 49151; give counts_per_force / counts_per_torque in the bench file to skip the query"))
}

/// The READCALINFO exchange over any byte stream (a TCP connection, a transcript
/// replay): writes the 20-byte request and reads the 24-byte reply before `deadline`.
pub fn calinfo_exchange<S: Read + Write>(
    s: &mut S,
    what: &str,
    deadline: Instant,
) -> DeviceResult<CalInfo> {
    crate::device::ft_common::send(s, DEVICE, what, &calinfo_request())?;
    let mut b = [0u8; CAL_REPLY_LEN];
    let mut got = 0;
    while got < CAL_REPLY_LEN {
        match crate::device::ft_common::read_until_deadline(
            s,
            &mut b[got..],
            deadline,
            DEVICE,
            what,
        ) {
            Ok(n) => got += n,
            Err(e) if e.kind == ErrorKind::Timeout => {
                return Err(DeviceError::new(
                    ErrorKind::Timeout,
                    DEVICE,
                    what,
                    format!("READCALINFO reply incomplete: {got} of {CAL_REPLY_LEN} bytes"),
                ))
            }
            Err(e) => return Err(e),
        }
    }
    CalInfo::decode(&b)
        .map_err(|e| DeviceError::new(ErrorKind::Protocol, DEVICE, what, e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::ft_common::{no_faults, SharedWrench};
    use crate::device::netft::sim::{NetFtCore, NetFtSimConfig, DEFAULT_CALINFO};
    use std::collections::VecDeque;
    use std::io;
    use std::net::{Ipv4Addr, SocketAddrV4};

    const CLIENT: SocketAddr = SocketAddr::V4(SocketAddrV4::new(Ipv4Addr::LOCALHOST, 5000));

    /// A network between the driver and the simulated device, without sockets: every
    /// `lose`-th record is lost, every `dup`-th sent twice, every `swap`-th swapped with
    /// the one after it (reordering); `silent` drops everything.
    struct Net {
        core: NetFtCore,
        start: Instant,
        inbox: VecDeque<Vec<u8>>,
        held: Option<Vec<u8>>,
        k: u64,
        lose: u64,
        dup: u64,
        swap: u64,
        silent: bool,
        requests: Vec<Request>,
    }

    impl Net {
        fn new(core: NetFtCore, lose: u64, dup: u64, swap: u64) -> Self {
            Net {
                core,
                start: Instant::now(),
                inbox: VecDeque::new(),
                held: None,
                k: 0,
                lose,
                dup,
                swap,
                silent: false,
                requests: Vec::new(),
            }
        }

        fn pump(&mut self) {
            let mut out = Vec::new();
            self.core.due(self.start.elapsed(), &mut out);
            for (_, d) in out {
                self.k += 1;
                let k = self.k;
                if self.silent || (self.lose > 0 && k.is_multiple_of(self.lose)) {
                    continue;
                }
                if self.swap > 0 && k.is_multiple_of(self.swap) && self.held.is_none() {
                    self.held = Some(d);
                    continue;
                }
                if self.dup > 0 && k.is_multiple_of(self.dup) {
                    self.inbox.push_back(d.clone());
                }
                self.inbox.push_back(d);
                if let Some(h) = self.held.take() {
                    self.inbox.push_back(h);
                }
            }
        }
    }

    impl Datagram for Net {
        fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
            if let Ok(r) = Request::decode(bytes) {
                self.requests.push(r);
            }
            if !self.silent {
                self.core.request(self.start.elapsed(), bytes, CLIENT);
            }
            Ok(())
        }
        fn recv(&mut self, buf: &mut [u8], deadline: Instant) -> io::Result<Option<usize>> {
            loop {
                self.pump();
                if let Some(d) = self.inbox.pop_front() {
                    let n = d.len().min(buf.len());
                    buf[..n].copy_from_slice(&d[..n]);
                    return Ok(Some(n));
                }
                if Instant::now() >= deadline {
                    return Ok(None);
                }
                std::thread::sleep(Duration::from_micros(200));
            }
        }
        fn peer(&self) -> String {
            "sim:49152".into()
        }
    }

    const LOAD: Wrench = Wrench {
        force_n: [1.5, -2.25, 12.34],
        torque_nm: [0.125, -0.05, 0.3],
    };

    fn opts() -> NetFtOptions {
        NetFtOptions::netft(DEFAULT_CALINFO.scale().unwrap())
    }

    fn device(load: SharedWrench, status: u32) -> NetFtCore {
        device_at(load, status, 1000.0)
    }

    fn device_at(load: SharedWrench, status: u32, rate_hz: f64) -> NetFtCore {
        NetFtCore::new(
            NetFtSimConfig {
                status,
                rate_hz,
                faults: no_faults(),
                ..NetFtSimConfig::default()
            },
            load,
        )
    }

    #[test]
    fn readings_exact_at_100_1000_and_7000_hz_despite_loss_duplicates_and_reordering() {
        for rate in [100.0, 1000.0, 7000.0] {
            let net = Net::new(device_at(SharedWrench::new(LOAD), 0, rate), 7, 5, 11);
            let mut d = NetFt::connect(net, opts()).unwrap();
            let mut reads = 0;
            while d.stats().good < 200 || reads < 20 {
                assert_exact(&d.read().unwrap(), &LOAD);
                reads += 1;
            }
            let s = d.stats();
            assert!(
                s.lost > 0 && s.duplicates > 0 && s.stale > 0,
                "{rate} Hz: {s:?}"
            );
            // Every 7th record lost, every 5th sent twice, every 11th late: each
            // record is accounted for once (received, lost or dropped as a copy).
            assert_eq!(
                s.bad_status + s.malformed + s.restarts,
                0,
                "{rate} Hz: {s:?}"
            );
            let sent = d.link.k;
            assert!(
                s.good + s.lost >= sent.saturating_sub(2 * 11),
                "{rate} Hz: {s:?}, {sent} sent"
            );
        }
    }

    /// A device that always has the next record waiting: the datagram stream never
    /// pauses, as a 1 or 7 kHz stream does not for a kernel that rounds socket
    /// timeouts up to a scheduler tick. Panics if one call takes 20 million datagrams (seconds of them).
    struct Firehose {
        seq: u32,
        calls: u64,
    }

    impl Datagram for Firehose {
        fn send(&mut self, _: &[u8]) -> io::Result<()> {
            Ok(())
        }
        fn recv(&mut self, buf: &mut [u8], _: Instant) -> io::Result<Option<usize>> {
            self.calls += 1;
            assert!(
                self.calls < 20_000_000,
                "a call never stopped taking datagrams"
            );
            self.seq += 1;
            let r = Record {
                rdt_seq: self.seq,
                ft_seq: self.seq,
                status: 0,
                counts: opts().scale.counts(&LOAD),
            }
            .encode();
            buf[..r.len()].copy_from_slice(&r);
            Ok(Some(r.len()))
        }
        fn peer(&self) -> String {
            "firehose".into()
        }
    }

    #[test]
    fn a_stream_that_never_pauses_does_not_hold_connect_read_or_tare() {
        let mut d = NetFt::connect(Firehose { seq: 0, calls: 0 }, opts()).unwrap();
        for _ in 0..5 {
            d.link.calls = 0;
            assert_exact(&d.read().unwrap(), &LOAD);
            assert!(d.link.calls <= 2 * MAX_DRAIN as u64 + 2, "{}", d.link.calls);
        }
        d.link.calls = 0;
        d.tare().unwrap();
        assert_exact(&d.read().unwrap(), &Wrench::default());
    }

    fn assert_exact(got: &Wrench, want: &Wrench) {
        for i in 0..3 {
            assert!(
                (got.force_n[i] - want.force_n[i]).abs() <= 0.5e-6,
                "{got:?}"
            );
            assert!(
                (got.torque_nm[i] - want.torque_nm[i]).abs() <= 0.5e-6,
                "{got:?}"
            );
        }
    }

    #[test]
    fn readings_exact_despite_loss_duplicates_and_reordering() {
        let net = Net::new(device(SharedWrench::new(LOAD), 0), 7, 5, 11);
        let mut d = NetFt::connect(net, opts()).unwrap();
        for _ in 0..20 {
            assert_exact(&d.read().unwrap(), &LOAD);
        }
        let s = d.stats();
        assert!(s.lost > 0 && s.duplicates > 0 && s.stale > 0, "{s:?}");
        assert_eq!(s.bad_status, 0);
        let note = d.take_status().unwrap();
        assert!(
            note.contains("lost") && note.contains("duplicate"),
            "{note}"
        );
        assert!(d.take_status().is_none() || d.stats().lost > s.lost);
    }

    #[test]
    fn tare_biases_the_device_and_zeroes_readings() {
        let load = SharedWrench::new(LOAD);
        let net = Net::new(device(load.clone(), 0), 0, 0, 0);
        let mut d = NetFt::connect(net, opts()).unwrap();
        d.tare().unwrap();
        assert_exact(&d.read().unwrap(), &Wrench::default());
        assert_exact(&d.offset(), &Wrench::default());
        let w2 = Wrench {
            force_n: [1.5, -2.25, 14.34],
            ..LOAD
        };
        load.set(w2);
        // The stream may still deliver records of the old load for a moment.
        std::thread::sleep(Duration::from_millis(20));
        let _ = d.read().unwrap();
        let r = d.read().unwrap();
        assert!((r.force_n[2] - 2.0).abs() <= 1e-6, "{r:?}");
        d.stop().unwrap();
        assert!(d
            .link
            .requests
            .iter()
            .any(|r| r.command == Command::SetBias));
        assert_eq!(d.link.requests.last().unwrap().command, Command::Stop);
    }

    #[test]
    fn a_nonzero_status_word_is_never_averaged_and_fails_the_reading() {
        let net = Net::new(device(SharedWrench::new(LOAD), 0x8000_0001), 0, 0, 0);
        let mut d = NetFt::connect(net, opts()).unwrap();
        let e = d.read_once().unwrap_err();
        assert_eq!(e.kind, ErrorKind::Limit, "{e}");
        assert!(e.message.contains("0x80000001"), "{e}");
        assert!(d.take_status().unwrap().contains("status 0x80000001"));
    }

    #[test]
    fn silence_resends_start_then_reports_disconnected_naming_the_peer() {
        let mut net = Net::new(device(SharedWrench::new(LOAD), 0), 0, 0, 0);
        net.silent = true;
        let t0 = Instant::now();
        let e = NetFt::connect(net, opts()).err().unwrap();
        assert_eq!(e.kind, ErrorKind::Disconnected);
        assert!(e.message.contains("sim:49152"), "{e}");
        assert!(t0.elapsed() < Duration::from_secs(3));
        assert!(e.message.contains("start requests"), "{e}");
    }

    #[test]
    fn a_restarted_sequence_is_followed() {
        let net = Net::new(device(SharedWrench::new(LOAD), 0), 0, 0, 0);
        let mut d = NetFt::connect(net, opts()).unwrap();
        d.read().unwrap();
        // The device reboots and a new start request restarts its sequence at 1.
        d.link.core.request(
            d.link.start.elapsed(),
            &Request::new(Command::StartRealtime).encode(),
            CLIENT,
        );
        std::thread::sleep(Duration::from_millis(5));
        for _ in 0..5 {
            assert_exact(&d.read().unwrap(), &LOAD);
        }
        assert!(
            d.stats().restarts >= 1 || d.stats().stale > 0,
            "{:?}",
            d.stats()
        );
    }
}
