//! Pieces shared by the serial force/torque devices (`dynpick`, `ft300`, `bota`): the
//! wrench source their simulators sample, their use of the shared seeded fault
//! injection ([`crate::device::fault`]), the output queue for late replies,
//! deadline-bounded reads for the drivers, and the frame splitter of the streamed
//! protocols ([`resync_frames`]). The
//! simulators are served on pseudo-terminals by [`crate::device::pty`].
//!
//! Why a deadline loop instead of one blocking read: drivers are generic over
//! `Read + Write`, so they cannot set a timeout on the port themselves. The port is
//! expected to return from `read` within a short time ([`PORT_READ_TIMEOUT`] is what
//! [`open_serial`] configures) with `TimedOut`/`WouldBlock` when nothing arrived; the
//! driver then enforces its own per-reply deadline across however many partial reads
//! a reply takes. A port that blocks forever defeats this (documented, not detected).

use std::collections::VecDeque;
use std::io::{self, Read, Write};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::fault::FaultInjector;
pub use super::fault::{FaultConfig, FaultKind, FaultTarget, ReplyClass};
use super::{DeviceError, DeviceResult, ErrorKind, Wrench};

/// Read timeout the serial helpers configure on a port: short, so that driver deadlines
/// and simulator cadences (100 Hz streams) are honoured to about this granularity.
pub const PORT_READ_TIMEOUT: Duration = Duration::from_millis(2);

/// What one [`resync_frames`] pass found.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Resync {
    /// Frames decoded.
    pub frames: u64,
    /// Candidate frames (header found, whole frame buffered) that failed to decode.
    pub rejected: u64,
    /// Bytes skipped while looking for a header (a rejected frame's first byte not
    /// included: the search restarts right after it).
    pub skipped: u64,
}

/// Splits the fixed-length frames that start with `header` out of a byte stream
/// (Bota's and the FT 300's streams): bytes before a header are skipped, a whole
/// candidate frame is `decode`d, and when it is rejected (bad CRC) the search moves on
/// by one byte only, since the real header may sit inside the rejected bytes (after a
/// dropped byte). Decoded frames are appended to `out`; the bytes consumed are removed
/// from `buf`, which keeps an incomplete frame, or the last `header.len() - 1` bytes
/// when no header was found (they may begin one).
pub fn resync_frames<F>(
    buf: &mut Vec<u8>,
    header: &[u8],
    frame_len: usize,
    mut decode: impl FnMut(&[u8]) -> Option<F>,
    out: &mut Vec<F>,
) -> Resync {
    debug_assert!(!header.is_empty() && frame_len >= header.len());
    let mut r = Resync::default();
    let mut i = 0;
    loop {
        match buf[i..].windows(header.len()).position(|w| w == header) {
            None => {
                let keep = (header.len() - 1).min(buf.len() - i);
                r.skipped += (buf.len() - i - keep) as u64;
                i = buf.len() - keep;
                break;
            }
            Some(k) => {
                r.skipped += k as u64;
                i += k;
            }
        }
        if buf.len() - i < frame_len {
            break;
        }
        match decode(&buf[i..i + frame_len]) {
            Some(f) => {
                out.push(f);
                r.frames += 1;
                i += frame_len;
            }
            None => {
                r.rejected += 1;
                i += 1;
            }
        }
    }
    buf.drain(..i);
    r
}

/// Opens a serial port (or pseudo-terminal path) at `baud` 8N1 with
/// [`PORT_READ_TIMEOUT`]. The error names the path and the baud rate.
pub fn open_serial(
    device: &'static str,
    path: &str,
    baud: u32,
) -> DeviceResult<Box<dyn serialport::SerialPort>> {
    serialport::new(path, baud)
        .timeout(PORT_READ_TIMEOUT)
        .open()
        .map_err(|e| {
            let kind = match e.kind() {
                serialport::ErrorKind::NoDevice => ErrorKind::Disconnected,
                _ => ErrorKind::Other,
            };
            DeviceError::new(
                kind,
                device,
                format!("open {path}"),
                format!("cannot open serial port {path} at {baud} baud: {e}"),
            )
            .with_hint("check the port path (ls /dev/ttyUSB* /dev/ttyACM*) and permissions (dialout group)")
        })
}

/// The load a simulated force sensor feels. The virtual world implements this; tests
/// use closures or [`SharedWrench`].
pub trait WrenchSource: Send {
    /// The true wrench at `t` since the simulator started.
    fn wrench_at(&mut self, t: Duration) -> Wrench;
}

impl<F: FnMut(Duration) -> Wrench + Send> WrenchSource for F {
    fn wrench_at(&mut self, t: Duration) -> Wrench {
        self(t)
    }
}

/// A wrench another thread sets (a test, the virtual world's contact model).
#[derive(Debug, Clone, Default)]
pub struct SharedWrench(pub Arc<Mutex<Wrench>>);

impl SharedWrench {
    /// A shared wrench starting at `w`.
    pub fn new(w: Wrench) -> Self {
        SharedWrench(Arc::new(Mutex::new(w)))
    }
    /// Sets the wrench the sensor feels from now on.
    pub fn set(&self, w: Wrench) {
        // A poisoned lock only means another thread panicked mid-set; the value is
        // still a plain Copy wrench, so keep serving it.
        *self.0.lock().unwrap_or_else(|p| p.into_inner()) = w;
    }
    /// The current wrench.
    pub fn get(&self) -> Wrench {
        *self.0.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl WrenchSource for SharedWrench {
    fn wrench_at(&mut self, _t: Duration) -> Wrench {
        self.get()
    }
}

/// An empty fault configuration: no faults (what the simulators use by default).
pub fn no_faults() -> FaultConfig {
    FaultConfig {
        seed: 0,
        kinds: Vec::new(),
        probability: 0.0,
        target: FaultTarget::Any,
        skip: 0,
        max_faults: 0,
        late_by: Duration::ZERO,
    }
}

/// What the fault injector decided for one reply or stream frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FaultPlan {
    /// Delay the reply by [`FaultConfig::late_by`].
    pub late: bool,
    /// Drop the byte at this index (modulo the reply length).
    pub drop_at: Option<usize>,
    /// Garble the byte at this index (the device's own rule decides where exactly).
    pub garble_at: Option<usize>,
    /// Prepend this many garbage bytes.
    pub unsolicited: usize,
    /// Reset instead of replying.
    pub reset: bool,
    /// Close the link instead of replying.
    pub disconnect: bool,
}

/// Counters a simulator keeps, shared with whoever started it (tests relate outcomes
/// to causes with them; the serve thread owns the simulator itself).
#[derive(Debug, Default)]
pub struct SimCounters {
    /// Replies (polled) produced, faulty or not.
    pub replies: AtomicU64,
    /// Stream frames produced, faulty or not.
    pub frames: AtomicU64,
    /// Replies / frames delayed.
    pub late: AtomicU64,
    /// Replies / frames with a byte dropped.
    pub dropped: AtomicU64,
    /// Replies / frames garbled.
    pub garbled: AtomicU64,
    /// Replies / frames preceded by garbage.
    pub unsolicited: AtomicU64,
    /// Resets.
    pub resets: AtomicU64,
    /// Whether the simulator dropped the link.
    pub disconnected: AtomicBool,
}

/// The force-sensor simulators' use of the shared [`FaultInjector`]: turns its
/// decision into byte-level actions and counts them. Every reply and every stream
/// frame is a [`ReplyClass::Query`] (reading a force sensor is idempotent), except
/// the FT 300 stream-start acknowledgement, a [`ReplyClass::Command`].
/// [`FaultKind::LimitTrip`] has no meaning for these sensors and does nothing.
#[derive(Debug)]
pub struct SimFaults {
    injector: FaultInjector,
    counters: Arc<SimCounters>,
}

impl SimFaults {
    /// Faults drawn from `config`.
    pub fn new(config: FaultConfig) -> Self {
        SimFaults {
            injector: FaultInjector::new(config),
            counters: Arc::new(SimCounters::default()),
        }
    }

    /// The shared counters.
    pub fn counters(&self) -> Arc<SimCounters> {
        Arc::clone(&self.counters)
    }

    /// Delay of a late reply.
    pub fn late_by(&self) -> Duration {
        self.injector.config().late_by
    }

    /// Decides the faults of the next reply or frame.
    pub fn plan(&mut self, class: ReplyClass) -> FaultPlan {
        let Some(kind) = self.injector.decide(class) else {
            return FaultPlan::default();
        };
        let c = &self.counters;
        let bump = |a: &AtomicU64| {
            a.fetch_add(1, Ordering::SeqCst);
        };
        let mut plan = FaultPlan::default();
        match kind {
            FaultKind::LateReply => {
                bump(&c.late);
                plan.late = true;
            }
            FaultKind::DroppedByte => {
                bump(&c.dropped);
                plan.drop_at = Some(self.injector.index(usize::MAX));
            }
            FaultKind::Garbled => {
                bump(&c.garbled);
                plan.garble_at = Some(self.injector.index(usize::MAX));
            }
            FaultKind::Unsolicited => {
                bump(&c.unsolicited);
                plan.unsolicited = 1 + self.injector.index(8);
            }
            FaultKind::DeviceReset => {
                bump(&c.resets);
                plan.reset = true;
            }
            FaultKind::Disconnect => {
                c.disconnected.store(true, Ordering::SeqCst);
                plan.disconnect = true;
            }
            FaultKind::LimitTrip => {}
        }
        plan
    }

    /// Applies a plan's byte-level faults to a reply: garble (with the device's own
    /// `garble` rule), drop one byte, prepend garbage. Timing, reset and disconnect are
    /// the simulator's to act on.
    pub fn shape(
        &mut self,
        plan: &FaultPlan,
        mut bytes: Vec<u8>,
        garble: fn(&mut [u8], usize),
    ) -> Vec<u8> {
        if let Some(i) = plan.garble_at {
            garble(&mut bytes, i);
        }
        if let Some(i) = plan.drop_at {
            if !bytes.is_empty() {
                let i = i % bytes.len();
                bytes.remove(i);
            }
        }
        if plan.unsolicited > 0 {
            let mut g = self.garbage(plan.unsolicited);
            g.extend_from_slice(&bytes);
            bytes = g;
        }
        bytes
    }

    /// Garbage bytes for an unsolicited burst (printable junk and line breaks mixed
    /// in, so line-based readers meet both kinds).
    fn garbage(&mut self, n: usize) -> Vec<u8> {
        const ALPHABET: &[u8] = b"#!?xq\r\n\xfe\x00ZZ";
        (0..n)
            .map(|_| ALPHABET[self.injector.index(ALPHABET.len())])
            .collect()
    }
}

/// A scheduled output queue for simulators (late replies), keyed by time since the
/// simulator's server started (the clock of [`crate::device::pty::Simulator::step`]).
#[derive(Debug, Default)]
pub struct OutQueue {
    items: VecDeque<(Duration, Vec<u8>)>,
}

impl OutQueue {
    /// Queues `bytes` to go out at `at` (kept in time order; equal times keep FIFO).
    pub fn push(&mut self, at: Duration, bytes: Vec<u8>) {
        let pos = self.items.iter().position(|(t, _)| *t > at);
        match pos {
            Some(i) => self.items.insert(i, (at, bytes)),
            None => self.items.push_back((at, bytes)),
        }
    }
    /// Moves everything due by `now` into `out`.
    pub fn drain_due(&mut self, now: Duration, out: &mut Vec<u8>) {
        while self.items.front().is_some_and(|(t, _)| *t <= now) {
            if let Some((_, b)) = self.items.pop_front() {
                out.extend_from_slice(&b);
            }
        }
    }
    /// When the next queued output is due.
    pub fn next_due(&self) -> Option<Duration> {
        self.items.front().map(|(t, _)| *t)
    }
    /// Forgets everything queued (device reset).
    pub fn clear(&mut self) {
        self.items.clear();
    }
}

/// Errors that only mean "nothing arrived yet".
pub fn is_quiet(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted
    )
}

/// Errors that mean the other end is gone (EOF-like, EIO on a hung-up tty).
pub fn is_disconnect(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::BrokenPipe
            | io::ErrorKind::UnexpectedEof
            | io::ErrorKind::ConnectionReset
            | io::ErrorKind::ConnectionAborted
            | io::ErrorKind::NotConnected
    ) || e.raw_os_error() == Some(5) // EIO: the pty master was closed
        // serialport's `flush` is tcdrain and reports its failure (EIO on a hung-up
        // port) as this bare message, without the OS error code.
        || (e.kind() == io::ErrorKind::Other && e.to_string() == "flush failed")
}

/// Maps an I/O error on `command` to a device error.
pub fn io_error(device: &'static str, command: &str, e: &io::Error) -> DeviceError {
    if is_disconnect(e) {
        DeviceError::new(
            ErrorKind::Disconnected,
            device,
            command,
            format!("port closed: {e}"),
        )
        .with_hint("check the cable / that the simulator is running")
    } else {
        DeviceError::new(ErrorKind::Other, device, command, format!("i/o error: {e}"))
    }
}

/// Writes a whole command, mapping errors.
pub fn send<P: Write>(
    port: &mut P,
    device: &'static str,
    command: &str,
    bytes: &[u8],
) -> DeviceResult<()> {
    port.write_all(bytes)
        .and_then(|_| port.flush())
        .map_err(|e| io_error(device, command, &e))
}

/// Reads at least one byte into `buf` before `deadline`. `Ok(0)` from the port is a
/// disconnect (EOF); a deadline passing is [`ErrorKind::Timeout`].
pub fn read_until_deadline<P: Read>(
    port: &mut P,
    buf: &mut [u8],
    deadline: Instant,
    device: &'static str,
    command: &str,
) -> DeviceResult<usize> {
    loop {
        match port.read(buf) {
            Ok(0) => {
                return Err(DeviceError::new(
                    ErrorKind::Disconnected,
                    device,
                    command,
                    "port reached end of file",
                ))
            }
            Ok(n) => return Ok(n),
            Err(e) if is_quiet(&e) => {}
            Err(e) => return Err(io_error(device, command, &e)),
        }
        if Instant::now() >= deadline {
            return Err(DeviceError::new(
                ErrorKind::Timeout,
                device,
                command,
                "no reply before the deadline",
            ));
        }
    }
}

/// Discards input until the port has been quiet for `quiet` (or `max` has passed):
/// throws away late replies and garbage before a retry. Only a disconnect is an error.
pub fn drain<P: Read>(
    port: &mut P,
    quiet: Duration,
    max: Duration,
    device: &'static str,
    command: &str,
) -> DeviceResult<usize> {
    let start = Instant::now();
    let mut last = Instant::now();
    let mut dropped = 0;
    let mut buf = [0u8; 256];
    while last.elapsed() < quiet && start.elapsed() < max {
        match port.read(&mut buf) {
            Ok(0) => {
                return Err(DeviceError::new(
                    ErrorKind::Disconnected,
                    device,
                    command,
                    "port reached end of file",
                ))
            }
            Ok(n) => {
                dropped += n;
                last = Instant::now();
            }
            Err(e) if is_quiet(&e) => {}
            Err(e) => return Err(io_error(device, command, &e)),
        }
    }
    Ok(dropped)
}

/// Shows bytes for error messages: printable ASCII as is, the rest as `\xNN`.
pub fn show_bytes(bytes: &[u8]) -> String {
    let mut s = String::with_capacity(bytes.len() + 2);
    for &b in bytes {
        match b {
            b'\r' => s.push_str("\\r"),
            b'\n' => s.push_str("\\n"),
            0x20..=0x7e => s.push(b as char),
            _ => s.push_str(&format!("\\x{b:02x}")),
        }
    }
    s
}

/// The retry policy of the polled F/T drivers (DynPick, FT 300). A command is sent
/// and its reply read before [`Retry::reply_timeout`]; a timeout or a malformed reply
/// is retried (reads are idempotent) after draining the input until it has been
/// quiet for a reply deadline, so a late reply is not taken for the next command's.
/// After a command failed for good its reply may still come, so the next command
/// drains first. Any other error (a closed port, a rejection) is returned at once.
#[derive(Debug, Clone)]
pub struct Retry {
    /// Device name in errors.
    pub device: &'static str,
    /// Deadline for a complete reply after the command was written.
    pub reply_timeout: Duration,
    /// Least quiet time of a drain (raised to the reply deadline).
    pub drain_quiet: Duration,
    /// Least upper bound on one drain (raised to four quiet times): a device spewing
    /// garbage must not hang the driver.
    pub drain_max: Duration,
    /// Hint added to a command that failed for good.
    pub hint: &'static str,
    /// What happened on the link.
    pub stats: LinkStats,
    /// A command failed for good: drain before the next one.
    dirty: bool,
}

impl Retry {
    /// A policy for `device` with the given deadline, drain bounds and hint.
    pub fn new(
        device: &'static str,
        reply_timeout: Duration,
        drain_quiet: Duration,
        drain_max: Duration,
        hint: &'static str,
    ) -> Self {
        Retry {
            device,
            reply_timeout,
            drain_quiet,
            drain_max,
            hint,
            stats: LinkStats::default(),
            dirty: false,
        }
    }

    /// Sends `bytes` (the command `text`) and returns what `reply` reads before the
    /// deadline it is given, in up to `attempts` attempts. `reply` reports a late or
    /// missing reply as [`ErrorKind::Timeout`] and a malformed one as
    /// [`ErrorKind::Protocol`] (both retried), and counts its resyncs in the stats.
    pub fn transact<P: Read + Write, T>(
        &mut self,
        port: &mut P,
        text: &str,
        bytes: &[u8],
        attempts: u32,
        mut reply: impl FnMut(&mut P, Instant, &mut LinkStats) -> DeviceResult<T>,
    ) -> DeviceResult<T> {
        let device = self.device;
        self.stats.commands += 1;
        let mut last_err = None;
        for attempt in 0..attempts {
            if attempt > 0 || std::mem::take(&mut self.dirty) {
                if attempt > 0 {
                    self.stats.retries += 1;
                }
                let quiet = self.drain_quiet.max(self.reply_timeout);
                drain(port, quiet, self.drain_max.max(quiet * 4), device, text)?;
            }
            send(port, device, text, bytes)?;
            let deadline = Instant::now() + self.reply_timeout;
            match reply(port, deadline, &mut self.stats) {
                Ok(v) => return Ok(v),
                Err(e) if matches!(e.kind, ErrorKind::Timeout | ErrorKind::Protocol) => {
                    if e.kind == ErrorKind::Timeout {
                        self.stats.timeouts += 1;
                    } else {
                        self.stats.protocol_errors += 1;
                    }
                    last_err = Some(e);
                }
                Err(e) => return Err(e),
            }
        }
        self.dirty = true;
        let e = last_err.unwrap_or_else(|| {
            DeviceError::new(ErrorKind::Other, device, text, "no attempt was made")
        });
        Err(DeviceError {
            message: format!(
                "{} (after {attempts} attempt{})",
                e.message,
                if attempts == 1 { "" } else { "s" }
            ),
            ..e
        }
        .with_hint(self.hint))
    }
}

/// Link statistics a driver keeps (for the runner's journal and the tests).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct LinkStats {
    /// Commands sent (first attempts).
    pub commands: u64,
    /// Retries after a failed attempt.
    pub retries: u64,
    /// Attempts that timed out.
    pub timeouts: u64,
    /// Attempts that received malformed bytes (bad record, bad CRC).
    pub protocol_errors: u64,
    /// Replies found after skipping unexpected bytes.
    pub resyncs: u64,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 4-byte frames `AB x y` that decode when `x + 1 == y`.
    fn toy(f: &[u8]) -> Option<(u8, u8)> {
        (f[2].wrapping_add(1) == f[3]).then_some((f[2], f[3]))
    }

    #[test]
    fn resync_frames_skips_garbage_slides_past_a_rejected_frame_and_keeps_a_possible_header() {
        let mut out = Vec::new();
        // Garbage, a frame, a rejected frame whose bytes hide the next header (as after
        // a dropped byte), that frame, then a lone `A` that may start the next one.
        let mut buf = b"xyAB12AB5AB67A".to_vec();
        buf.iter_mut().for_each(|b| {
            if b.is_ascii_digit() {
                *b -= b'0';
            }
        });
        let r = resync_frames(&mut buf, b"AB", 4, toy, &mut out);
        assert_eq!(out, vec![(1, 2), (6, 7)]);
        assert_eq!(
            r,
            Resync {
                frames: 2,
                rejected: 1,
                skipped: 2 + 2
            },
            "x y, then the rejected frame's B 5 after its A"
        );
        assert_eq!(buf, b"A", "kept: it may begin a header");
        // The rest arrives: the kept byte completes a frame.
        buf.extend_from_slice(&[b'B', 3, 4]);
        let r = resync_frames(&mut buf, b"AB", 4, toy, &mut out);
        assert_eq!((r.frames, r.skipped), (1, 0));
        assert_eq!(out.last(), Some(&(3, 4)));
        assert!(buf.is_empty());
        // A one-byte header keeps nothing back; an incomplete frame is kept whole.
        let (mut buf, mut bytes) = (vec![9, 9, 0xAA, 1], Vec::new());
        let r = resync_frames(&mut buf, &[0xAA], 3, |f| Some(f[1]), &mut bytes);
        assert!(bytes.is_empty());
        assert_eq!((r.frames, r.skipped), (0, 2));
        assert_eq!(buf, [0xAA, 1]);
    }

    #[test]
    fn plan_maps_each_kind_to_its_action_and_counts_it() {
        let cfg = FaultConfig {
            kinds: vec![FaultKind::Garbled],
            probability: 1.0,
            max_faults: 2,
            ..no_faults()
        };
        let mut f = SimFaults::new(cfg);
        let p = f.plan(ReplyClass::Query);
        assert!(p.garble_at.is_some() && !p.late && p.drop_at.is_none());
        f.plan(ReplyClass::Query);
        assert_eq!(
            f.plan(ReplyClass::Query),
            FaultPlan::default(),
            "max_faults"
        );
        assert_eq!(f.counters().garbled.load(Ordering::SeqCst), 2);
    }

    #[test]
    fn no_faults_injects_nothing() {
        let mut f = SimFaults::new(no_faults());
        for _ in 0..100 {
            assert_eq!(f.plan(ReplyClass::Query), FaultPlan::default());
        }
    }

    #[test]
    fn unsolicited_burst_is_prepended() {
        let cfg = FaultConfig {
            kinds: vec![FaultKind::Unsolicited],
            probability: 1.0,
            max_faults: 1,
            ..no_faults()
        };
        let mut f = SimFaults::new(cfg);
        let p = f.plan(ReplyClass::Query);
        let out = f.shape(&p, b"R1".to_vec(), |_, _| {});
        assert_eq!(out.len(), 2 + p.unsolicited);
        assert!(out.ends_with(b"R1"));
    }

    #[test]
    fn out_queue_releases_in_time_order() {
        let t0 = Duration::from_millis(3);
        let mut q = OutQueue::default();
        q.push(t0 + Duration::from_millis(5), b"late".to_vec());
        q.push(t0, b"now".to_vec());
        let mut out = Vec::new();
        q.drain_due(t0, &mut out);
        assert_eq!(out, b"now");
        q.drain_due(t0 + Duration::from_millis(5), &mut out);
        assert_eq!(out, b"nowlate");
    }
}
