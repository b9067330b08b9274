//! Pieces shared by the two force/torque devices (`dynpick`, `ft300`): the wrench
//! source their simulators sample, seeded fault injection for those simulators, the
//! output queue for late replies, and deadline-bounded reads for the drivers. The
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

use super::{DeviceError, DeviceResult, ErrorKind, Wrench};

/// Read timeout the serial helpers configure on a port: short, so that driver deadlines
/// and simulator cadences (100 Hz streams) are honoured to about this granularity.
pub const PORT_READ_TIMEOUT: Duration = Duration::from_millis(2);

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

/// Faults a force-sensor simulator injects, opt-in and seeded (same seed, same faults
/// for the same traffic). Probabilities apply per reply (polled) or per frame
/// (stream); all zero by default.
#[derive(Debug, Clone, PartialEq)]
pub struct FaultConfig {
    /// Seed of the fault generator.
    pub seed: u64,
    /// Probability that a reply is sent `late_by` later than normal.
    pub late_reply: f64,
    /// Delay of a late reply.
    pub late_by: Duration,
    /// Probability that one byte of a reply is dropped.
    pub drop_byte: f64,
    /// Probability that a reply is garbled (DynPick: a hex digit replaced by `G`;
    /// FT 300: one payload bit flipped, so the CRC fails).
    pub garble: f64,
    /// Probability that unsolicited garbage precedes a reply.
    pub unsolicited: f64,
    /// Probability that the device resets instead of replying (state back to
    /// power-on: offset zeroing lost, filter default, stream off; request dropped).
    pub reset: f64,
    /// The link drops (port closed) after this many replies / frames.
    pub disconnect_after: Option<u64>,
    /// The first this many replies / frames are served clean (lets a driver connect
    /// before the faults start).
    pub clean_first: u64,
}

impl Default for FaultConfig {
    fn default() -> Self {
        FaultConfig {
            seed: 0,
            late_reply: 0.0,
            late_by: Duration::from_millis(0),
            drop_byte: 0.0,
            garble: 0.0,
            unsolicited: 0.0,
            reset: 0.0,
            disconnect_after: None,
            clean_first: 0,
        }
    }
}

/// What the fault injector decided for one reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FaultPlan {
    /// Delay the reply by [`FaultConfig::late_by`].
    pub late: bool,
    /// Drop the byte at this index (modulo the reply length).
    pub drop_at: Option<usize>,
    /// Garble the byte at this index (modulo the reply length).
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

impl SimCounters {
    /// Reads one counter.
    pub fn get(c: &AtomicU64) -> u64 {
        c.load(Ordering::SeqCst)
    }
}

/// Seeded fault generator (SplitMix64: tiny, deterministic, good enough for choosing
/// faults; not for statistics).
#[derive(Debug, Clone)]
pub struct FaultInjector {
    config: FaultConfig,
    state: u64,
    replies: u64,
    counters: Arc<SimCounters>,
}

impl FaultInjector {
    /// An injector for `config`.
    pub fn new(config: FaultConfig) -> Self {
        let state = config.seed ^ 0x9E37_79B9_7F4A_7C15;
        FaultInjector {
            config,
            state,
            replies: 0,
            counters: Arc::new(SimCounters::default()),
        }
    }

    /// The shared counters.
    pub fn counters(&self) -> Arc<SimCounters> {
        Arc::clone(&self.counters)
    }

    /// The configuration.
    pub fn config(&self) -> &FaultConfig {
        &self.config
    }

    /// Next pseudo-random 64-bit value (SplitMix64).
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn chance(&mut self, p: f64) -> bool {
        if p <= 0.0 {
            return false;
        }
        // 53 random bits -> uniform in [0, 1).
        let u = (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        u < p
    }

    /// Decides the faults of the next reply. Draws a fixed number of values per reply
    /// so that enabling one fault does not shift the others' sequence.
    pub fn plan(&mut self) -> FaultPlan {
        self.replies += 1;
        let c = self.config.clone();
        let late = self.chance(c.late_reply);
        let drop = self.chance(c.drop_byte);
        let garble = self.chance(c.garble);
        let unsolicited = self.chance(c.unsolicited);
        let reset = self.chance(c.reset);
        let idx_a = self.next_u64() as usize;
        let idx_b = self.next_u64() as usize;
        let n_garbage = 1 + (self.next_u64() % 8) as usize;
        let disconnect = c.disconnect_after.is_some_and(|n| self.replies > n);
        if self.replies <= c.clean_first {
            // The draws above still happened, so reply k gets the same faults whatever
            // `clean_first` is; only the first ones are suppressed.
            return FaultPlan {
                disconnect,
                ..FaultPlan::default()
            };
        }
        let plan = FaultPlan {
            late,
            drop_at: drop.then_some(idx_a),
            garble_at: garble.then_some(idx_b),
            unsolicited: if unsolicited { n_garbage } else { 0 },
            reset,
            disconnect,
        };
        let c = &self.counters;
        let bump = |a: &AtomicU64, on: bool| {
            if on {
                a.fetch_add(1, Ordering::SeqCst);
            }
        };
        bump(&c.late, plan.late);
        bump(&c.dropped, plan.drop_at.is_some());
        bump(&c.garbled, plan.garble_at.is_some());
        bump(&c.unsolicited, plan.unsolicited > 0);
        bump(&c.resets, plan.reset);
        if plan.disconnect {
            c.disconnected.store(true, Ordering::SeqCst);
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

    /// Garbage bytes for an unsolicited burst (printable junk and line breaks
    /// mixed in, so line-based readers meet both kinds).
    pub fn garbage(&mut self, n: usize) -> Vec<u8> {
        const ALPHABET: &[u8] = b"#!?xq\r\n\xfe\x00ZZ";
        (0..n)
            .map(|_| ALPHABET[(self.next_u64() % ALPHABET.len() as u64) as usize])
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

    #[test]
    fn same_seed_gives_same_fault_sequence() {
        let cfg = FaultConfig {
            seed: 42,
            garble: 0.3,
            drop_byte: 0.2,
            ..FaultConfig::default()
        };
        let a: Vec<_> = {
            let mut f = FaultInjector::new(cfg.clone());
            (0..50).map(|_| f.plan()).collect()
        };
        let mut f = FaultInjector::new(cfg);
        let b: Vec<_> = (0..50).map(|_| f.plan()).collect();
        assert_eq!(a, b);
        assert!(a.iter().any(|p| p.garble_at.is_some()));
        assert!(a.iter().any(|p| p.garble_at.is_none()));
    }

    #[test]
    fn no_faults_by_default() {
        let mut f = FaultInjector::new(FaultConfig::default());
        for _ in 0..100 {
            assert_eq!(f.plan(), FaultPlan::default());
        }
    }

    #[test]
    fn disconnect_after_n_replies() {
        let mut f = FaultInjector::new(FaultConfig {
            disconnect_after: Some(3),
            ..FaultConfig::default()
        });
        let d: Vec<bool> = (0..5).map(|_| f.plan().disconnect).collect();
        assert_eq!(d, [false, false, false, true, true]);
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
