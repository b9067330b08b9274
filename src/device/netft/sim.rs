//! ATI Net F/T (and OnRobot HEX) simulator: RDT over UDP and READCALINFO over TCP,
//! both bound to loopback on ports the OS chooses (or given ones), serving the wrench
//! of a [`WrenchSource`].
//!
//! [`NetFtCore`] is the device as a pure state machine (requests in, datagrams out,
//! driven by time), unit-tested without sockets; [`NetFtServer`] serves it on real
//! sockets from two threads. Behaviour:
//! - a start request (0x0002 / 0x0003) makes the device stream records to the address
//!   it came from, one every `1 / rate_hz` (record k due at start + k periods, caught
//!   up when the serving thread is late), `count` records or until stopped (0x0000);
//!   the RDT sequence starts at 1 on every start request, the F/T sequence counts
//!   internal samples since power-on;
//! - 0x0042 biases: later records read zero at the current load;
//! - OnRobot HEX: 0x0081 (filter) and 0x0082 (rate: period in ms) are accepted; the HEX
//!   serves no calibration query (its scale is fixed).
//!
//! Opt-in, seeded faults per record ([`FaultConfig`]), as UDP shows them:
//! `DroppedByte` loses the datagram, `Unsolicited` duplicates it, `LateReply` delays it
//! by `late_by` (it arrives out of order), `Garbled` truncates it (a datagram that is
//! not a record), `DeviceReset` reboots the device (stream stopped, bias and sequence
//! cleared), `Disconnect` makes it vanish (nothing answered any more, UDP or TCP).
//! A constant status word ([`NetFtSimConfig::status`]) marks every record as faulty.

use std::collections::VecDeque;
use std::io::{self, Read, Write};
use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4, TcpListener, TcpStream, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use super::codec::{CalInfo, Command, Record, Request, Scale, CAL_REQUEST_LEN, CMD_READCALINFO};
use crate::device::ft_common::{
    no_faults, FaultConfig, ReplyClass, SimCounters, SimFaults, WrenchSource,
};

/// Simulator configuration.
#[derive(Debug, Clone)]
pub struct NetFtSimConfig {
    /// The calibration served on TCP (and used to turn the wrench into counts).
    pub calinfo: CalInfo,
    /// Records per second.
    pub rate_hz: f64,
    /// Status word of every record (0 = healthy).
    pub status: u32,
    /// An OnRobot HEX: fixed scale ([`Scale::ONROBOT_HEX`]), no TCP calibration query.
    pub onrobot_hex: bool,
    /// Faults to inject (none by default).
    pub faults: FaultConfig,
}

/// The calibration of the simulated sensor: N and N·m, 1 000 000 counts per unit (as
/// LoomDeBWiles/cof_tester's simulator).
pub const DEFAULT_CALINFO: CalInfo = CalInfo {
    force_unit: 2,
    torque_unit: 3,
    counts_per_force: 1_000_000,
    counts_per_torque: 1_000_000,
    scale_factors: [1; 6],
};

impl Default for NetFtSimConfig {
    fn default() -> Self {
        NetFtSimConfig {
            calinfo: DEFAULT_CALINFO,
            rate_hz: 1000.0,
            status: 0,
            onrobot_hex: false,
            faults: no_faults(),
        }
    }
}

impl NetFtSimConfig {
    /// The scale the device uses to produce counts.
    pub fn scale(&self) -> Scale {
        if self.onrobot_hex {
            Scale::ONROBOT_HEX
        } else {
            self.calinfo.scale().unwrap_or(Scale {
                counts_per_n: 1e6,
                counts_per_nm: 1e6,
            })
        }
    }
}

struct Stream {
    client: SocketAddr,
    next_due: Duration,
    remaining: Option<u32>,
}

/// The device as a pure state machine.
pub struct NetFtCore {
    config: NetFtSimConfig,
    scale: Scale,
    source: Box<dyn WrenchSource>,
    faults: SimFaults,
    stream: Option<Stream>,
    rdt_seq: u32,
    ft_seq: u32,
    bias: [i32; 6],
    late: VecDeque<(Duration, SocketAddr, Vec<u8>)>,
    period: Duration,
    dead: bool,
}

impl NetFtCore {
    /// A device reading its load from `source`.
    pub fn new(config: NetFtSimConfig, source: impl WrenchSource + 'static) -> Self {
        let faults = SimFaults::new(config.faults.clone());
        let period = Duration::from_secs_f64(1.0 / config.rate_hz.clamp(1.0, 20_000.0));
        NetFtCore {
            scale: config.scale(),
            config,
            source: Box::new(source),
            faults,
            stream: None,
            rdt_seq: 0,
            ft_seq: 0,
            bias: [0; 6],
            late: VecDeque::new(),
            period,
            dead: false,
        }
    }

    /// Counters shared with the caller (records, injected faults).
    pub fn counters(&self) -> Arc<SimCounters> {
        self.faults.counters()
    }

    /// Whether the device has vanished (a `Disconnect` fault).
    pub fn is_dead(&self) -> bool {
        self.dead
    }

    /// Whether a stream is running.
    pub fn is_streaming(&self) -> bool {
        self.stream.is_some()
    }

    fn counts(&mut self, t: Duration) -> [i32; 6] {
        let c = self.scale.counts(&self.source.wrench_at(t));
        [0, 1, 2, 3, 4, 5].map(|i| c[i].saturating_sub(self.bias[i]))
    }

    /// Handles one request datagram from `from` at `now`.
    pub fn request(&mut self, now: Duration, bytes: &[u8], from: SocketAddr) {
        if self.dead {
            return;
        }
        let Ok(r) = Request::decode(bytes) else {
            return;
        };
        match r.command {
            Command::StartRealtime | Command::StartBuffered => {
                self.rdt_seq = 0;
                self.stream = Some(Stream {
                    client: from,
                    next_due: now,
                    remaining: (r.count > 0).then_some(r.count),
                });
            }
            Command::Stop => self.stream = None,
            Command::SetBias => {
                self.bias = [0; 6];
                self.bias = self.counts(now);
            }
            Command::OnRobotRate if self.config.onrobot_hex && r.count > 0 => {
                self.period = Duration::from_millis(r.count as u64);
            }
            Command::OnRobotFilter | Command::OnRobotRate | Command::Other(_) => {}
        }
    }

    /// The datagrams due by `now`, with their destinations.
    pub fn due(&mut self, now: Duration, out: &mut Vec<(SocketAddr, Vec<u8>)>) {
        while let Some(s) = self.stream.as_mut() {
            if self.dead || s.next_due > now {
                break;
            }
            let due = s.next_due;
            let client = s.client;
            s.next_due += self.period;
            if let Some(r) = s.remaining.as_mut() {
                *r -= 1;
                if *r == 0 {
                    self.stream = None;
                }
            }
            self.rdt_seq = self.rdt_seq.wrapping_add(1);
            self.ft_seq = self.ft_seq.wrapping_add(1);
            let rec = Record {
                rdt_seq: self.rdt_seq,
                ft_seq: self.ft_seq,
                status: self.config.status,
                counts: self.counts(due),
            }
            .encode()
            .to_vec();
            self.faults.counters().frames.fetch_add(1, Ordering::SeqCst);
            let plan = self.faults.plan(ReplyClass::Query);
            if plan.disconnect {
                self.dead = true;
                self.stream = None;
                self.late.clear();
                return;
            }
            if plan.reset {
                self.stream = None;
                self.bias = [0; 6];
                self.rdt_seq = 0;
                self.late.clear();
                return;
            }
            if plan.drop_at.is_some() {
                continue;
            }
            let mut rec = rec;
            if let Some(i) = plan.garble_at {
                rec.truncate(i % rec.len());
            }
            if plan.late {
                self.late
                    .push_back((due + self.faults.late_by(), client, rec));
                continue;
            }
            if plan.unsolicited > 0 {
                out.push((client, rec.clone()));
            }
            out.push((client, rec));
        }
        while self.late.front().is_some_and(|(t, _, _)| *t <= now) {
            if let Some((_, c, r)) = self.late.pop_front() {
                out.push((c, r));
            }
        }
    }

    /// Time from `now` until the next datagram is due.
    pub fn next_wake(&self, now: Duration) -> Option<Duration> {
        let s = self.stream.as_ref().map(|s| s.next_due);
        let l = self.late.front().map(|(t, _, _)| *t);
        match (s, l) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
        .map(|t| t.saturating_sub(now))
    }

    /// The reply to a TCP request, if the device answers it.
    pub fn tcp_reply(&self, request: &[u8]) -> Option<Vec<u8>> {
        (!self.dead
            && !self.config.onrobot_hex
            && request.len() == CAL_REQUEST_LEN
            && request[0] == CMD_READCALINFO)
            .then(|| self.config.calinfo.encode().to_vec())
    }
}

/// Errors starting the simulator's sockets.
#[derive(Debug, thiserror::Error)]
pub enum NetFtSimError {
    /// A socket could not be bound (a port in use, for example).
    #[error("cannot bind the simulated Net F/T's {what} socket on {addr}: {source}")]
    Bind {
        /// `UDP` or `TCP`.
        what: &'static str,
        /// The address.
        addr: SocketAddr,
        /// The cause.
        source: io::Error,
    },
    /// A thread could not be started.
    #[error("cannot start the simulated Net F/T's thread: {0}")]
    Thread(io::Error),
}

/// Longest sleep of the serving threads (stop latency).
const MAX_WAIT: Duration = Duration::from_millis(20);

/// The simulator served on loopback sockets; stops when dropped.
pub struct NetFtServer {
    udp: SocketAddr,
    tcp: Option<SocketAddr>,
    stop: Arc<AtomicBool>,
    threads: Vec<JoinHandle<()>>,
    core: Arc<Mutex<NetFtCore>>,
    counters: Arc<SimCounters>,
}

fn lock(c: &Mutex<NetFtCore>) -> std::sync::MutexGuard<'_, NetFtCore> {
    c.lock().unwrap_or_else(|p| p.into_inner())
}

impl NetFtServer {
    /// Serves `core` on 127.0.0.1: UDP on `rdt_port`, TCP on `cal_port` (0 = chosen by
    /// the OS; the HEX serves no TCP).
    pub fn spawn(core: NetFtCore, rdt_port: u16, cal_port: u16) -> Result<Self, NetFtSimError> {
        let lo = |p| SocketAddr::V4(SocketAddrV4::new(Ipv4Addr::LOCALHOST, p));
        let udp = UdpSocket::bind(lo(rdt_port)).map_err(|source| NetFtSimError::Bind {
            what: "UDP",
            addr: lo(rdt_port),
            source,
        })?;
        let tcp = if core.config.onrobot_hex {
            None
        } else {
            Some(
                TcpListener::bind(lo(cal_port)).map_err(|source| NetFtSimError::Bind {
                    what: "TCP",
                    addr: lo(cal_port),
                    source,
                })?,
            )
        };
        let udp_addr = udp.local_addr().map_err(NetFtSimError::Thread)?;
        let tcp_addr = match &tcp {
            Some(t) => Some(t.local_addr().map_err(NetFtSimError::Thread)?),
            None => None,
        };
        let counters = core.counters();
        let core = Arc::new(Mutex::new(core));
        let stop = Arc::new(AtomicBool::new(false));
        let mut threads = Vec::new();
        {
            let (core, stop) = (Arc::clone(&core), Arc::clone(&stop));
            threads.push(
                std::thread::Builder::new()
                    .name("netft-sim-udp".into())
                    .spawn(move || serve_udp(udp, &core, &stop))
                    .map_err(NetFtSimError::Thread)?,
            );
        }
        if let Some(listener) = tcp {
            let (core, flag) = (Arc::clone(&core), Arc::clone(&stop));
            let t = std::thread::Builder::new()
                .name("netft-sim-tcp".into())
                .spawn(move || serve_tcp(listener, &core, &flag));
            match t {
                Ok(t) => threads.push(t),
                Err(e) => {
                    stop.store(true, Ordering::SeqCst);
                    return Err(NetFtSimError::Thread(e));
                }
            }
        }
        Ok(NetFtServer {
            udp: udp_addr,
            tcp: tcp_addr,
            stop,
            threads,
            core,
            counters,
        })
    }

    /// The RDT (UDP) address.
    pub fn rdt_addr(&self) -> SocketAddr {
        self.udp
    }

    /// The calibration (TCP) address; `None` for the HEX.
    pub fn cal_addr(&self) -> Option<SocketAddr> {
        self.tcp
    }

    /// Counters (records, injected faults).
    pub fn counters(&self) -> Arc<SimCounters> {
        Arc::clone(&self.counters)
    }

    /// Whether the device vanished (a `Disconnect` fault).
    pub fn is_finished(&self) -> bool {
        lock(&self.core).is_dead()
    }

    /// Whether the device is streaming.
    pub fn is_streaming(&self) -> bool {
        lock(&self.core).is_streaming()
    }
}

impl Drop for NetFtServer {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

/// Waits shorter than this are slept (`nanosleep`, precise to tens of µs); longer ones
/// wait on the socket (`poll`, in whole ms) so a request ends them at once.
const SLEEP_BELOW: Duration = Duration::from_millis(2);

/// Serves the stream: sleeps to each record's absolute due time (start + k periods)
/// and sends every record due by then (a catch-up batch when the thread woke late), so
/// the rate holds at 7 kHz on a loaded machine; requests are taken at every wake.
fn serve_udp(socket: UdpSocket, core: &Mutex<NetFtCore>, stop: &AtomicBool) {
    use std::os::fd::AsRawFd;
    let start = Instant::now();
    let mut buf = [0u8; 64];
    let mut out = Vec::new();
    if socket.set_nonblocking(true).is_err() {
        return;
    }
    while !stop.load(Ordering::SeqCst) {
        while let Ok((n, from)) = socket.recv_from(&mut buf) {
            lock(core).request(start.elapsed(), &buf[..n], from);
        }
        out.clear();
        let wake = {
            let mut c = lock(core);
            c.due(start.elapsed(), &mut out);
            c.next_wake(start.elapsed())
        };
        for (to, d) in &out {
            // A client that went away (ICMP unreachable) is not the device's problem.
            let _ = socket.send_to(d, to);
        }
        let wait = wake.unwrap_or(MAX_WAIT).min(MAX_WAIT);
        if wait >= SLEEP_BELOW {
            let _ = super::transport::wait_readable(socket.as_raw_fd(), wait - SLEEP_BELOW / 2);
        } else if !wait.is_zero() {
            std::thread::sleep(wait);
        }
    }
}

fn serve_tcp(listener: TcpListener, core: &Arc<Mutex<NetFtCore>>, stop: &Arc<AtomicBool>) {
    let _ = listener.set_nonblocking(true);
    let mut clients: Vec<JoinHandle<()>> = Vec::new();
    while !stop.load(Ordering::SeqCst) {
        match listener.accept() {
            Ok((s, _)) => {
                let (core, stop) = (Arc::clone(core), Arc::clone(stop));
                if let Ok(t) = std::thread::Builder::new()
                    .name("netft-sim-tcp-client".into())
                    .spawn(move || serve_tcp_client(s, &core, &stop))
                {
                    clients.push(t);
                }
            }
            Err(_) => std::thread::sleep(Duration::from_millis(5)),
        }
        clients.retain(|t| !t.is_finished());
    }
    for t in clients {
        let _ = t.join();
    }
}

fn serve_tcp_client(mut s: TcpStream, core: &Mutex<NetFtCore>, stop: &AtomicBool) {
    let _ = s.set_nonblocking(false);
    let _ = s.set_read_timeout(Some(MAX_WAIT * 5));
    let mut req = Vec::new();
    let mut buf = [0u8; 64];
    while !stop.load(Ordering::SeqCst) {
        match s.read(&mut buf) {
            Ok(0) => return,
            Ok(n) => req.extend_from_slice(&buf[..n]),
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                continue
            }
            Err(_) => return,
        }
        while req.len() >= CAL_REQUEST_LEN {
            let r: Vec<u8> = req.drain(..CAL_REQUEST_LEN).collect();
            let reply = lock(core).tcp_reply(&r);
            if let Some(b) = reply {
                if s.write_all(&b).is_err() {
                    return;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::ft_common::{FaultKind, FaultTarget, SharedWrench};
    use crate::device::Wrench;

    const CLIENT: SocketAddr = SocketAddr::V4(SocketAddrV4::new(Ipv4Addr::LOCALHOST, 5000));

    fn core(faults: FaultConfig) -> NetFtCore {
        let w = SharedWrench::new(Wrench {
            force_n: [1.0, -2.0, 3.5],
            torque_nm: [0.1, 0.0, -0.25],
        });
        NetFtCore::new(
            NetFtSimConfig {
                faults,
                ..NetFtSimConfig::default()
            },
            w,
        )
    }

    fn start(c: &mut NetFtCore, count: u32) {
        let r = Request {
            command: Command::StartRealtime,
            count,
        };
        c.request(Duration::ZERO, &r.encode(), CLIENT);
    }

    #[test]
    fn streams_records_at_the_rate_and_count_then_stops() {
        let mut c = core(no_faults());
        start(&mut c, 5);
        let mut out = Vec::new();
        c.due(Duration::from_millis(100), &mut out);
        assert_eq!(out.len(), 5, "count 5");
        let r = Record::decode(&out[0].1).unwrap();
        assert_eq!((r.rdt_seq, r.status), (1, 0));
        assert_eq!(
            r.counts,
            [1_000_000, -2_000_000, 3_500_000, 100_000, 0, -250_000]
        );
        assert!(!c.is_streaming());
        start(&mut c, 0);
        out.clear();
        c.due(Duration::from_millis(9), &mut out);
        assert_eq!(out.len(), 10, "1 kHz: due at 0..=9 ms");
        assert_eq!(
            Record::decode(&out[0].1).unwrap().rdt_seq,
            1,
            "restarts at 1"
        );
    }

    #[test]
    fn bias_zeroes_later_records() {
        let mut c = core(no_faults());
        start(&mut c, 0);
        c.request(
            Duration::ZERO,
            &Request::new(Command::SetBias).encode(),
            CLIENT,
        );
        let mut out = Vec::new();
        c.due(Duration::from_millis(1), &mut out);
        assert_eq!(Record::decode(&out[1].1).unwrap().counts, [0; 6]);
    }

    #[test]
    fn faults_lose_duplicate_delay_and_truncate_records() {
        for (kind, expect) in [
            (FaultKind::DroppedByte, 9),
            (FaultKind::Unsolicited, 11),
            (FaultKind::LateReply, 9),
            (FaultKind::Garbled, 10),
        ] {
            let mut c = core(FaultConfig::once(kind, FaultTarget::Any, 3));
            start(&mut c, 0);
            let mut out = Vec::new();
            c.due(Duration::from_millis(9), &mut out);
            assert_eq!(out.len(), expect, "{kind:?}");
            if kind == FaultKind::Garbled {
                assert!(out.iter().any(|(_, d)| d.len() != 36));
            }
            if kind == FaultKind::LateReply {
                c.due(Duration::from_millis(1600), &mut Vec::new());
            }
        }
        let mut c = core(FaultConfig::once(
            FaultKind::Disconnect,
            FaultTarget::Any,
            0,
        ));
        start(&mut c, 0);
        let mut out = Vec::new();
        c.due(Duration::from_millis(5), &mut out);
        assert!(out.is_empty() && c.is_dead());
        assert!(c
            .tcp_reply(&super::super::codec::calinfo_request())
            .is_none());
    }

    #[test]
    fn answers_readcalinfo_only_to_command_1() {
        let c = core(no_faults());
        let r = c
            .tcp_reply(&super::super::codec::calinfo_request())
            .unwrap();
        assert_eq!(CalInfo::decode(&r).unwrap(), DEFAULT_CALINFO);
        assert!(c.tcp_reply(&[0u8; 20]).is_none());
    }
}
