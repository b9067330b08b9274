//! The datagram transport the Net F/T driver is generic over ([`Datagram`]), and its
//! UDP implementation ([`UdpTransport`]) with a deadline on every receive.
//!
//! The socket is non-blocking and waits with `poll(2)`: a receive whose deadline has
//! passed is a true poll (it never sleeps), and a wait ends when a datagram arrives.
//! (A socket read timeout would not do: the kernel rounds it up to a scheduler tick,
//! longer than the 143 µs between records at 7 kHz, so a "poll" would sleep and keep
//! finding the next record waiting.)
//!
//! Why a trait: UDP loses, duplicates and reorders datagrams, and the driver's answer
//! to each (drop duplicates and stale records, count losses, resend the start request)
//! is tested with a transport that does exactly that on purpose, without sockets
//! (`driver` tests), as well as over real loopback sockets against the simulator.

use std::io;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr, ToSocketAddrs, UdpSocket};
use std::time::{Duration, Instant};

use crate::device::{DeviceError, DeviceResult, ErrorKind};

/// A connected datagram link to one device.
pub trait Datagram: Send {
    /// Sends one datagram.
    fn send(&mut self, bytes: &[u8]) -> io::Result<()>;
    /// Receives one datagram into `buf` (its length), waiting until `deadline` at most;
    /// `Ok(None)` when nothing arrived by then. A deadline already past still takes a
    /// datagram that is waiting (a non-blocking poll).
    fn recv(&mut self, buf: &mut [u8], deadline: Instant) -> io::Result<Option<usize>>;
    /// The peer, for messages (`host:port`).
    fn peer(&self) -> String;
}

/// Waits until `fd` is readable (or has an error to report) or `wait` has passed,
/// whichever is first; an interrupted wait returns early (the caller loops). The wait
/// is rounded up to whole milliseconds (poll's unit): a wait ends late by < 1 ms when
/// nothing arrives, never early, and at once when something does.
pub fn wait_readable(fd: std::os::fd::RawFd, wait: Duration) -> io::Result<()> {
    let ms = wait.as_nanos().div_ceil(1_000_000).min(i32::MAX as u128) as i32;
    let mut p = libc::pollfd {
        fd,
        events: libc::POLLIN,
        revents: 0,
    };
    // SAFETY: one valid pollfd for the duration of the call.
    let r = unsafe { libc::poll(&mut p, 1, ms) };
    if r < 0 {
        let e = io::Error::last_os_error();
        if e.kind() != io::ErrorKind::Interrupted {
            return Err(e);
        }
    }
    Ok(())
}

/// A UDP socket connected to the device: only its datagrams are received, and an ICMP
/// "port unreachable" (nothing listens there) surfaces as `ConnectionRefused`.
#[derive(Debug)]
pub struct UdpTransport {
    socket: UdpSocket,
    peer: SocketAddr,
    name: String,
}

/// Resolves `host:port` to one socket address, preferring IPv4. The error names the
/// host and says it does not resolve.
pub fn resolve(device: &'static str, host: &str, port: u16) -> DeviceResult<SocketAddr> {
    let what = format!("resolve {host}");
    let addrs: Vec<SocketAddr> = (host, port)
        .to_socket_addrs()
        .map_err(|e| {
            DeviceError::new(
                ErrorKind::Other,
                device,
                &what,
                format!("host {host:?} does not resolve: {e}"),
            )
            .with_hint("give the sensor's IP address (e.g. 192.168.1.1) or a name in /etc/hosts")
        })?
        .collect();
    addrs
        .iter()
        .find(|a| a.is_ipv4())
        .or_else(|| addrs.first())
        .copied()
        .ok_or_else(|| {
            DeviceError::new(
                ErrorKind::Other,
                device,
                what,
                format!("host {host:?} resolves to no address"),
            )
        })
}

impl UdpTransport {
    /// A socket connected to `host:port`. The local end binds the loopback address
    /// when the device is on loopback (simulators, tests), else the unspecified address
    /// of the same family; its port is chosen by the OS.
    pub fn connect(device: &'static str, host: &str, port: u16) -> DeviceResult<Self> {
        let peer = resolve(device, host, port)?;
        let local: IpAddr = match peer.ip() {
            ip if ip.is_loopback() => ip,
            IpAddr::V4(_) => IpAddr::V4(Ipv4Addr::UNSPECIFIED),
            IpAddr::V6(_) => IpAddr::V6(Ipv6Addr::UNSPECIFIED),
        };
        let fail = |e: io::Error, what: &str| {
            DeviceError::new(
                ErrorKind::Other,
                device,
                format!("udp {what} {peer}"),
                format!("cannot {what} a UDP socket for {host}:{port}: {e}"),
            )
        };
        let socket = UdpSocket::bind(SocketAddr::new(local, 0)).map_err(|e| fail(e, "bind"))?;
        socket.connect(peer).map_err(|e| fail(e, "connect"))?;
        socket
            .set_nonblocking(true)
            .map_err(|e| fail(e, "configure"))?;
        Ok(UdpTransport {
            socket,
            peer,
            name: format!("{host}:{port}"),
        })
    }

    /// The device's address.
    pub fn peer_addr(&self) -> SocketAddr {
        self.peer
    }
}

impl Datagram for UdpTransport {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.socket.send(bytes).map(|_| ())
    }

    fn recv(&mut self, buf: &mut [u8], deadline: Instant) -> io::Result<Option<usize>> {
        use std::os::fd::AsRawFd;
        loop {
            match self.socket.recv(buf) {
                Ok(n) => return Ok(Some(n)),
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted
                    ) => {}
                Err(e) => return Err(e),
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            wait_readable(self.socket.as_raw_fd(), deadline - now)?;
        }
    }

    fn peer(&self) -> String {
        self.name.clone()
    }
}

/// A recorded datagram session replayed as a [`Datagram`] transport: the datagram
/// counterpart of [`crate::device::replay::Replay`]. The transcript has one datagram
/// per line, `> HEX` sent by the host, `< HEX` by the device (hexadecimal bytes,
/// spaces allowed), `#` comments. A device datagram becomes receivable once every
/// host datagram before it was sent; a host datagram that differs from the next
/// recorded one is an I/O error naming both, and [`DatagramReplay::finish`] fails if
/// any recorded datagram was not used.
#[derive(Debug)]
pub struct DatagramReplay {
    steps: Vec<(bool, Vec<u8>)>,
    next: usize,
    failure: Option<String>,
}

impl DatagramReplay {
    /// Parses transcript text; the error names the line.
    pub fn parse(text: &str) -> Result<Self, String> {
        let mut steps = Vec::new();
        for (n, raw) in text.lines().enumerate() {
            let line = raw.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let (host, rest) = match (line.strip_prefix("> "), line.strip_prefix("< ")) {
                (Some(r), _) => (true, r),
                (_, Some(r)) => (false, r),
                _ => return Err(format!("line {}: expected `> ` or `< `", n + 1)),
            };
            let hex: String = rest.chars().filter(|c| !c.is_whitespace()).collect();
            if !hex.len().is_multiple_of(2) {
                return Err(format!("line {}: odd number of hex digits", n + 1));
            }
            let bytes = (0..hex.len())
                .step_by(2)
                .map(|i| u8::from_str_radix(&hex[i..i + 2], 16))
                .collect::<Result<Vec<u8>, _>>()
                .map_err(|e| format!("line {}: {e}", n + 1))?;
            steps.push((host, bytes));
        }
        Ok(DatagramReplay {
            steps,
            next: 0,
            failure: None,
        })
    }

    /// Ok when every datagram was used and no sent datagram differed.
    pub fn finish(&self) -> Result<(), String> {
        if let Some(f) = &self.failure {
            return Err(f.clone());
        }
        if self.next < self.steps.len() {
            let (host, b) = &self.steps[self.next];
            return Err(format!(
                "transcript not fully used: datagram {} of {} ({}, {})",
                self.next + 1,
                self.steps.len(),
                if *host {
                    "host datagram never sent"
                } else {
                    "device datagram never received"
                },
                hex(b)
            ));
        }
        Ok(())
    }
}

/// Bytes as lower-case hex.
pub fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

impl Datagram for DatagramReplay {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        match self.steps.get(self.next) {
            Some((true, b)) if b.as_slice() == bytes => {
                self.next += 1;
                Ok(())
            }
            other => {
                let want = match other {
                    Some((true, b)) => format!("expected {}", hex(b)),
                    Some((false, b)) => format!("expected the host to receive {} first", hex(b)),
                    None => "the transcript has ended".into(),
                };
                let msg = format!("replay: unexpected datagram {}: {want}", hex(bytes));
                self.failure.get_or_insert(msg.clone());
                Err(io::Error::other(msg))
            }
        }
    }

    fn recv(&mut self, buf: &mut [u8], deadline: Instant) -> io::Result<Option<usize>> {
        match self.steps.get(self.next) {
            Some((false, b)) => {
                let n = b.len().min(buf.len());
                buf[..n].copy_from_slice(&b[..n]);
                self.next += 1;
                Ok(Some(n))
            }
            _ => {
                // Nothing to receive before the host sends more: wait like a socket.
                std::thread::sleep(deadline.saturating_duration_since(Instant::now()));
                Ok(None)
            }
        }
    }

    fn peer(&self) -> String {
        "replay".into()
    }
}
