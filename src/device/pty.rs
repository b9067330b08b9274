//! Serving a device simulator on a real pseudo-terminal.
//!
//! A [`PtyServer`] opens a pseudo-terminal pair (`serialport::TTYPort::pair`), runs a
//! [`Simulator`] on the master side in its own thread, and gives the slave path
//! (`/dev/pts/N`, optionally behind a symlink). The driver under test opens that
//! path with `serialport::new(path, baud).timeout(..).open()`, exactly as it opens
//! a USB serial adapter on hardware, so the whole stack (termios raw mode,
//! timeouts, partial reads, hang-ups) is exercised.
//!
//! The server keeps its own handle on the slave open for its whole life. That is
//! deliberate: a pty whose slave has no open handle makes the master report a
//! hang-up, so without it a driver closing and re-opening the port (the CLI does
//! this once per invocation) would kill the server. The server never reads from
//! its slave handle, so all bytes written by the simulator go to the driver.
//!
//! A simulator is a byte-level state machine driven by time: [`Simulator::step`]
//! receives whatever bytes arrived (possibly none: a timer tick) and the time since
//! the server started, and appends its replies. It returns [`Flow::Hangup`] to
//! emulate an unplugged device: the server then closes the master, the driver's
//! next read or write fails (POLLHUP / EIO) and the slave path disappears.
//!
//! Stopping ([`PtyServer::stop`] or drop) sets a flag the serving thread checks at
//! least every [`MAX_POLL_INTERVAL`], joins the thread and removes the symlink, so
//! tests leak no threads.

use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};

/// Longest the serving thread sleeps in one read; bounds the stop latency and the
/// timer resolution for simulators that do not ask for an earlier wake-up.
pub const MAX_POLL_INTERVAL: Duration = Duration::from_millis(20);

/// Shortest read timeout; keeps a simulator asking for "now" from spinning.
pub const MIN_POLL_INTERVAL: Duration = Duration::from_micros(500);

/// How long one write to the master may block before the bytes are kept for later
/// (nobody reading the slave: the kernel buffer is full).
const WRITE_TIMEOUT: Duration = Duration::from_millis(50);

/// What the serving loop does after a simulator step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Flow {
    /// Keep serving.
    Continue,
    /// Emulate a disconnect: flush what was produced, close the pseudo-terminal and
    /// end the serving thread.
    Hangup,
}

/// A device simulator serving a wire protocol as a byte-level state machine.
///
/// Implementations must be pure functions of (their state, `now`, `input`): no
/// clocks or I/O of their own, so the same simulator is unit-tested without a pty.
pub trait Simulator: Send + 'static {
    /// Handles `input` (the bytes received since the last step; empty on a timer
    /// tick) at `now` (time since the server started) and appends the bytes to send
    /// to `output`.
    fn step(&mut self, now: Duration, input: &[u8], output: &mut Vec<u8>) -> Flow;

    /// Time from `now` until the simulator next has something to do without input
    /// (a delayed reply, a streamed sample), or `None` if nothing is pending.
    fn next_wake(&self, now: Duration) -> Option<Duration> {
        let _ = now;
        None
    }
}

/// Errors opening or serving a pseudo-terminal.
#[derive(Debug, thiserror::Error)]
pub enum PtyError {
    /// The pseudo-terminal pair could not be opened.
    #[error("cannot open a pseudo-terminal pair: {0}")]
    Open(#[from] serialport::Error),
    /// The pseudo-terminal has no slave path (not expected on Linux).
    #[error("the pseudo-terminal slave has no path")]
    NoPath,
    /// The symlink to the slave could not be created.
    #[error("cannot create symlink {link} -> {target}: {source}")]
    Link {
        /// The symlink path requested.
        link: PathBuf,
        /// The slave path it should point to.
        target: PathBuf,
        /// The underlying error.
        source: io::Error,
    },
    /// The serving thread could not be started.
    #[error("cannot start the simulator thread: {0}")]
    Thread(io::Error),
}

/// A simulator served on a pseudo-terminal; stops and cleans up when dropped.
pub struct PtyServer<S: Simulator> {
    slave_path: PathBuf,
    link: Option<PathBuf>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<S>>,
}

impl<S: Simulator> PtyServer<S> {
    /// Opens a pseudo-terminal pair and serves `sim` on it. With `link`, also creates
    /// a symlink at that path pointing to the slave (an existing symlink there is
    /// replaced; any other existing file is an error).
    pub fn spawn(sim: S, link: Option<&Path>) -> Result<Self, PtyError> {
        let (mut master, slave) = TTYPort::pair()?;
        let slave_path = PathBuf::from(slave.name().ok_or(PtyError::NoPath)?);
        if let Some(link) = link {
            if link
                .symlink_metadata()
                .map(|m| m.file_type().is_symlink())
                .unwrap_or(false)
            {
                // A stale link from an earlier run; replacing it is what the user wants.
                let _ = std::fs::remove_file(link);
            }
            std::os::unix::fs::symlink(&slave_path, link).map_err(|source| PtyError::Link {
                link: link.to_path_buf(),
                target: slave_path.clone(),
                source,
            })?;
        }
        // The master is only polled with short timeouts; the real timeouts are chosen
        // per read in the loop.
        let _ = master.set_timeout(MAX_POLL_INTERVAL);
        let stop = Arc::new(AtomicBool::new(false));
        let stop_flag = Arc::clone(&stop);
        let name = format!(
            "pty-sim {}",
            slave_path
                .file_name()
                .and_then(|n| n.to_str())
                .unwrap_or("?")
        );
        let spawned = std::thread::Builder::new()
            .name(name)
            .spawn(move || serve(sim, master, slave, &stop_flag));
        let thread = match spawned {
            Ok(t) => t,
            Err(e) => {
                if let Some(link) = link {
                    let _ = std::fs::remove_file(link);
                }
                return Err(PtyError::Thread(e));
            }
        };
        Ok(PtyServer {
            slave_path,
            link: link.map(Path::to_path_buf),
            stop,
            thread: Some(thread),
        })
    }

    /// The slave path a driver opens (`/dev/pts/N`).
    pub fn path(&self) -> &Path {
        &self.slave_path
    }

    /// The symlink created at spawn, if any.
    pub fn link(&self) -> Option<&Path> {
        self.link.as_deref()
    }

    /// The path to hand to a driver: the symlink if one was made, else the slave.
    pub fn port_path(&self) -> &Path {
        self.link.as_deref().unwrap_or(&self.slave_path)
    }

    /// True once the serving thread has ended (after a simulated hang-up).
    pub fn is_finished(&self) -> bool {
        self.thread.as_ref().is_none_or(|t| t.is_finished())
    }

    /// Stops serving, joins the thread and returns the simulator (to inspect its
    /// final state). `None` only if the simulator thread panicked.
    pub fn stop(mut self) -> Option<S> {
        self.shutdown()
    }

    fn shutdown(&mut self) -> Option<S> {
        self.stop.store(true, Ordering::SeqCst);
        let sim = self.thread.take().and_then(|t| t.join().ok());
        if let Some(link) = self.link.take() {
            let _ = std::fs::remove_file(link);
        }
        sim
    }
}

impl<S: Simulator> Drop for PtyServer<S> {
    fn drop(&mut self) {
        let _ = self.shutdown();
    }
}

/// The serving loop: read what the driver sent (with a timeout bounded by the
/// simulator's next wake-up), step the simulator, write its output.
fn serve<S: Simulator>(mut sim: S, mut master: TTYPort, slave: TTYPort, stop: &AtomicBool) -> S {
    let start = Instant::now();
    let mut buf = [0u8; 4096];
    let mut pending: Vec<u8> = Vec::new();
    let mut out: Vec<u8> = Vec::new();
    while !stop.load(Ordering::SeqCst) {
        let now = start.elapsed();
        let timeout = sim
            .next_wake(now)
            .unwrap_or(MAX_POLL_INTERVAL)
            .clamp(MIN_POLL_INTERVAL, MAX_POLL_INTERVAL);
        let _ = master.set_timeout(timeout);
        let n = match master.read(&mut buf) {
            Ok(n) => n,
            Err(e) if e.kind() == io::ErrorKind::TimedOut => 0,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => 0,
            // Any other error on the master (should not happen while we hold the
            // slave open): back off briefly instead of spinning.
            Err(_) => {
                std::thread::sleep(MIN_POLL_INTERVAL);
                0
            }
        };
        out.clear();
        let flow = sim.step(start.elapsed(), &buf[..n], &mut out);
        pending.extend_from_slice(&out);
        write_pending(&mut master, &mut pending);
        if flow == Flow::Hangup {
            break;
        }
    }
    // Closing both ends makes the driver's next read see POLLHUP and removes the
    // slave device node once the driver closes its handle.
    drop(slave);
    drop(master);
    sim
}

/// Writes as much of `pending` as the master accepts within [`WRITE_TIMEOUT`]; the
/// rest stays queued for the next round (nobody is reading the slave).
fn write_pending(master: &mut TTYPort, pending: &mut Vec<u8>) {
    if pending.is_empty() {
        return;
    }
    let _ = master.set_timeout(WRITE_TIMEOUT);
    let mut written = 0;
    while written < pending.len() {
        match master.write(&pending[written..]) {
            Ok(0) => break,
            Ok(n) => written += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(_) => break,
        }
    }
    pending.drain(..written);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Upper-cases every byte it receives; hangs up on `!`.
    struct Upper;

    impl Simulator for Upper {
        fn step(&mut self, _now: Duration, input: &[u8], output: &mut Vec<u8>) -> Flow {
            output.extend(input.iter().map(|b| b.to_ascii_uppercase()));
            if input.contains(&b'!') {
                Flow::Hangup
            } else {
                Flow::Continue
            }
        }
    }

    fn read_exact_timeout(port: &mut dyn SerialPort, n: usize) -> Vec<u8> {
        let mut got = Vec::new();
        let mut buf = [0u8; 64];
        let deadline = Instant::now() + Duration::from_secs(2);
        while got.len() < n && Instant::now() < deadline {
            if let Ok(k) = port.read(&mut buf) {
                got.extend_from_slice(&buf[..k]);
            }
        }
        got
    }

    #[test]
    fn driver_opens_the_slave_path_like_a_serial_port_and_gets_replies() {
        let server = PtyServer::spawn(Upper, None).expect("pty");
        let mut port = serialport::new(server.path().to_string_lossy(), 115_200)
            .timeout(Duration::from_millis(100))
            .open()
            .expect("open slave");
        port.write_all(b"abc\n").expect("write");
        assert_eq!(read_exact_timeout(port.as_mut(), 4), b"ABC\n");
        drop(port);
        // Re-opening after close works: the server keeps the slave alive.
        let mut port = serialport::new(server.path().to_string_lossy(), 115_200)
            .timeout(Duration::from_millis(100))
            .open()
            .expect("reopen slave");
        port.write_all(b"xy").expect("write");
        assert_eq!(read_exact_timeout(port.as_mut(), 2), b"XY");
        assert!(
            server.stop().is_some(),
            "thread joined and returned the simulator"
        );
    }

    #[test]
    fn all_byte_values_pass_unchanged() {
        struct Echo;
        impl Simulator for Echo {
            fn step(&mut self, _now: Duration, input: &[u8], output: &mut Vec<u8>) -> Flow {
                output.extend_from_slice(input);
                Flow::Continue
            }
        }
        let server = PtyServer::spawn(Echo, None).expect("pty");
        let mut port = serialport::new(server.path().to_string_lossy(), 115_200)
            .timeout(Duration::from_millis(100))
            .open()
            .expect("open slave");
        let all: Vec<u8> = (0..=255u8).collect();
        port.write_all(&all).expect("write");
        assert_eq!(read_exact_timeout(port.as_mut(), 256), all);
    }

    #[test]
    fn hangup_makes_the_driver_see_a_broken_port_and_ends_the_thread() {
        let server = PtyServer::spawn(Upper, None).expect("pty");
        let mut port = serialport::new(server.path().to_string_lossy(), 115_200)
            .timeout(Duration::from_millis(100))
            .open()
            .expect("open slave");
        port.write_all(b"!").expect("write");
        let deadline = Instant::now() + Duration::from_secs(2);
        let mut buf = [0u8; 8];
        let mut saw_error = false;
        while Instant::now() < deadline {
            match port.read(&mut buf) {
                Ok(0) => {
                    saw_error = true;
                    break;
                }
                Ok(_) => continue,
                Err(e) if e.kind() == io::ErrorKind::TimedOut => continue,
                Err(_) => {
                    saw_error = true;
                    break;
                }
            }
        }
        assert!(
            saw_error,
            "read after hang-up must fail, not time out forever"
        );
        let deadline = Instant::now() + Duration::from_secs(2);
        while !server.is_finished() && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(5));
        }
        assert!(
            server.is_finished(),
            "serving thread ended after the hang-up"
        );
    }

    #[test]
    fn symlink_points_to_the_slave_and_is_removed_on_drop() {
        let dir = tempfile::tempdir().expect("tempdir");
        let link = dir.path().join("stage");
        let server = PtyServer::spawn(Upper, Some(&link)).expect("pty");
        assert_eq!(std::fs::read_link(&link).expect("link"), server.path());
        assert_eq!(server.port_path(), link.as_path());
        drop(server);
        assert!(link.symlink_metadata().is_err(), "link removed");
    }
}
