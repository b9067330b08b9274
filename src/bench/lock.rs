//! One writer per run directory: an exclusive OS lock (`flock(2)` through
//! [`std::fs::File::try_lock`]) on `RUN_DIR/run.lock`, taken by `run` and
//! `run --resume` before anything else is written and held until the process ends.
//! The kernel releases it when the process dies, however it dies (even SIGKILL), so a
//! stale lock file never blocks a resume: only a live holder does.
//!
//! The holder writes who it is into the lock file (`pid`, `host`, `started_at`,
//! `command`, one `key=value` per line), so a refused second writer can name it. The
//! file stays in the run directory after the run (its content then names the last
//! writer); whether a run is live is decided by the lock, never by the file's presence.
//!
//! The same lock guards a serial port ([`PortClaim`]): each `tactbench stage` command
//! (and `run` on a real bench) claims its port in [`port_claim_dir`], so a `stage
//! stop` elsewhere learns from [`port_holder`] which process to signal.
//!
//! [`probe`] lets readers (`report`) ask whether a writer is live without blocking it:
//! it opens the file read-only (never creating it) and takes a shared lock for an
//! instant. A writer that starts during that instant retries for
//! [`ACQUIRE_GRACE`] before refusing, so a probe never makes a writer fail.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use thiserror::Error;

/// File name of the lock inside a run directory.
pub const LOCK_FILE: &str = "run.lock";

/// How long a writer retries a held lock before refusing (covers a reader's probe,
/// which holds a shared lock for microseconds; far shorter than any run).
pub const ACQUIRE_GRACE: Duration = Duration::from_millis(300);

/// An error taking a run directory's lock.
#[derive(Debug, Error)]
pub enum LockError {
    /// Another live process writes this run directory.
    #[error(
        "{dir} is in use by another tactbench process ({holder}); refusing a second writer \
         (wait for it to end, or stop it and then resume)"
    )]
    Held {
        /// The run directory.
        dir: PathBuf,
        /// Who holds the lock, as it recorded itself.
        holder: Holder,
    },
    /// The lock file cannot be opened, locked or written.
    #[error("{path}: {source}")]
    Io {
        /// The lock file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
}

/// Who holds (or last held) a run directory's lock, as recorded in the lock file.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Holder {
    /// Process id.
    pub pid: Option<u32>,
    /// Host name.
    pub host: Option<String>,
    /// When the holder took the lock, RFC 3339 UTC.
    pub started_at: Option<String>,
    /// What the holder runs (`run` or `run --resume`).
    pub command: Option<String>,
}

impl std::fmt::Display for Holder {
    /// `PID 1234 on host lab-3, since 2026-11-24T01:00:00Z, 'tactbench run --resume'`
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.pid.is_none() && self.host.is_none() && self.started_at.is_none() {
            return f.write_str("holder not yet recorded: it has just started");
        }
        let unknown = || "unknown".to_string();
        write!(
            f,
            "PID {} on host {}, since {}",
            self.pid.map_or_else(unknown, |p| p.to_string()),
            self.host.clone().unwrap_or_else(unknown),
            self.started_at.clone().unwrap_or_else(unknown)
        )?;
        if let Some(c) = &self.command {
            write!(f, ", 'tactbench {c}'")?;
        }
        Ok(())
    }
}

impl Holder {
    /// This process.
    fn me(command: &str) -> Holder {
        Holder {
            pid: Some(std::process::id()),
            host: Some(hostname()),
            started_at: Some(crate::bench::runner::rfc3339_now()),
            command: Some(command.to_string()),
        }
    }

    /// Parses the lock file's `key=value` lines (unknown keys and junk are ignored).
    pub fn parse(text: &str) -> Holder {
        let mut h = Holder::default();
        for line in text.lines() {
            let Some((k, v)) = line.split_once('=') else {
                continue;
            };
            let v = v.trim().to_string();
            match k.trim() {
                "pid" => h.pid = v.parse().ok(),
                "host" => h.host = Some(v),
                "started_at" => h.started_at = Some(v),
                "command" => h.command = Some(v),
                _ => {}
            }
        }
        h
    }

    fn to_text(&self) -> String {
        let mut s = String::new();
        if let Some(p) = self.pid {
            s.push_str(&format!("pid={p}\n"));
        }
        for (k, v) in [
            ("host", &self.host),
            ("started_at", &self.started_at),
            ("command", &self.command),
        ] {
            if let Some(v) = v {
                // One line per key: a newline in a value would forge another key.
                s.push_str(&format!("{k}={}\n", v.replace(['\n', '\r'], " ")));
            }
        }
        s
    }
}

/// The machine's host name (`/proc/sys/kernel/hostname`, else `$HOSTNAME`, else
/// `unknown`).
pub fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .or_else(|| std::env::var("HOSTNAME").ok().filter(|s| !s.is_empty()))
        .unwrap_or_else(|| "unknown".into())
}

/// A held run-directory lock; released when dropped (or when the process dies).
#[derive(Debug)]
pub struct RunLock {
    file: File,
    path: PathBuf,
}

impl RunLock {
    /// Takes the exclusive lock of `dir` (which must exist) for `command` (recorded
    /// for a refused second writer), or fails at once with [`LockError::Held`] naming
    /// the live holder.
    pub fn acquire(dir: &Path, command: &str) -> Result<RunLock, LockError> {
        let path = dir.join(LOCK_FILE);
        match take(&path, command)? {
            Taken::Mine(file) => Ok(RunLock { file, path }),
            Taken::Held(holder) => Err(LockError::Held {
                dir: dir.to_path_buf(),
                holder,
            }),
        }
    }

    /// The lock file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Releases the lock explicitly (dropping does the same).
    pub fn release(self) {
        let _ = self.file.unlock();
    }
}

/// What [`take`] got.
enum Taken {
    /// The lock, with this process recorded in the file.
    Mine(File),
    /// A live process holds it.
    Held(Holder),
}

/// Takes the exclusive lock of the file at `path` (created if missing, never
/// truncated before it is held) for `command`, retrying for [`ACQUIRE_GRACE`], and
/// records this process in it; or names the live holder.
fn take(path: &Path, command: &str) -> Result<Taken, LockError> {
    let io = |source| LockError::Io {
        path: path.to_path_buf(),
        source,
    };
    // Never truncate on open: the file names the holder until we hold the lock.
    let mut file = OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(path)
        .map_err(io)?;
    let t0 = Instant::now();
    loop {
        match file.try_lock() {
            Ok(()) => break,
            Err(TryLockError::WouldBlock) if t0.elapsed() < ACQUIRE_GRACE => {
                std::thread::sleep(Duration::from_millis(20));
            }
            Err(TryLockError::WouldBlock) => {
                let mut text = String::new();
                let _ = file.read_to_string(&mut text);
                return Ok(Taken::Held(Holder::parse(&text)));
            }
            Err(TryLockError::Error(e)) => return Err(io(e)),
        }
    }
    let me = Holder::me(command);
    file.set_len(0).map_err(io)?;
    file.seek(SeekFrom::Start(0)).map_err(io)?;
    file.write_all(me.to_text().as_bytes()).map_err(io)?;
    file.sync_all().map_err(io)?;
    Ok(Taken::Mine(file))
}

/// What [`probe`] found about a run directory's writer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LockState {
    /// No lock file: the run predates locking, or no writer ever started.
    NoLockFile,
    /// Nobody holds the lock: no process is writing the run.
    Free,
    /// A live process holds the lock: the run is in progress.
    Held(Holder),
}

/// Whether a live process writes `dir`, without creating or changing anything.
pub fn probe(dir: &Path) -> Result<LockState, LockError> {
    probe_file(&dir.join(LOCK_FILE))
}

/// Whether a live process holds the lock file at `path`, without creating or
/// changing anything.
fn probe_file(path: &Path) -> Result<LockState, LockError> {
    let mut file = match File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(LockState::NoLockFile),
        Err(source) => {
            return Err(LockError::Io {
                path: path.to_path_buf(),
                source,
            })
        }
    };
    match file.try_lock_shared() {
        Ok(()) => {
            let _ = file.unlock();
            Ok(LockState::Free)
        }
        Err(TryLockError::WouldBlock) => {
            let mut text = String::new();
            let _ = file.read_to_string(&mut text);
            Ok(LockState::Held(Holder::parse(&text)))
        }
        Err(TryLockError::Error(source)) => Err(LockError::Io {
            path: path.to_path_buf(),
            source,
        }),
    }
}

/// The directory of the serial ports' claim files: `$XDG_RUNTIME_DIR/tactbench`, or
/// `tactbench-UID` in the temporary directory (per user: a process can only signal
/// its own user's processes anyway).
pub fn port_claim_dir() -> PathBuf {
    match std::env::var_os("XDG_RUNTIME_DIR").map(PathBuf::from) {
        Some(d) if d.is_dir() => d.join("tactbench"),
        _ => {
            // SAFETY: getuid has no preconditions and cannot fail.
            let uid = unsafe { libc::getuid() };
            std::env::temp_dir().join(format!("tactbench-{uid}"))
        }
    }
}

/// The claim file of a serial port: named after the device the path resolves to
/// (`/dev/pts/5` -> `port_dev_pts_5.lock`), so a symlink and its target share one.
pub fn port_claim_path(port: &str) -> PathBuf {
    let device = std::fs::canonicalize(port).unwrap_or_else(|_| PathBuf::from(port));
    let name: String = device
        .to_string_lossy()
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '.' || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    port_claim_dir().join(format!("port{name}.lock"))
}

/// One tactbench process per serial port: a `stage` command holds the claim of its
/// port while it has the port open, so a second one (`stage stop` in another
/// terminal) learns which process to signal instead of failing to open the port.
/// Released when dropped or when the process dies.
#[derive(Debug)]
pub struct PortClaim {
    _file: File,
}

/// An error claiming a serial port.
#[derive(Debug, Error)]
pub enum ClaimError {
    /// Another live tactbench process drives this port.
    #[error(
        "serial port {port} is in use by another tactbench process ({holder}): wait for it to end, \
         or stop its motion with Ctrl-C in its terminal or `tactbench stage --port {port} --protocol ... stop` here"
    )]
    Held {
        /// The port as given.
        port: String,
        /// Who holds it.
        holder: Holder,
    },
    /// The claim file cannot be created, locked or written.
    #[error(transparent)]
    Lock(#[from] LockError),
}

impl PortClaim {
    /// Claims `port` for `command` (recorded for a `stage stop` elsewhere), or names
    /// the live holder.
    pub fn acquire(port: &str, command: &str) -> Result<PortClaim, ClaimError> {
        let dir = port_claim_dir();
        std::fs::create_dir_all(&dir).map_err(|source| LockError::Io {
            path: dir.clone(),
            source,
        })?;
        match take(&port_claim_path(port), command)? {
            Taken::Mine(file) => Ok(PortClaim { _file: file }),
            Taken::Held(holder) => Err(ClaimError::Held {
                port: port.to_string(),
                holder,
            }),
        }
    }
}

/// Which live tactbench process holds `port`'s claim, if one does.
pub fn port_holder(port: &str) -> Result<Option<Holder>, LockError> {
    Ok(match probe_file(&port_claim_path(port))? {
        LockState::Held(h) => Some(h),
        LockState::Free | LockState::NoLockFile => None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_writer_is_refused_naming_the_holder_and_the_lock_frees_on_drop() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(probe(dir.path()).unwrap(), LockState::NoLockFile);
        let lock = RunLock::acquire(dir.path(), "run").unwrap();
        let e = RunLock::acquire(dir.path(), "run --resume").unwrap_err();
        let text = e.to_string();
        assert!(
            text.contains(&format!("PID {}", std::process::id()))
                && text.contains(&hostname())
                && text.contains("'tactbench run'")
                && text.contains(&dir.path().display().to_string()),
            "{text}"
        );
        match probe(dir.path()).unwrap() {
            LockState::Held(h) => assert_eq!(h.pid, Some(std::process::id())),
            s => panic!("{s:?}"),
        }
        drop(lock);
        assert_eq!(probe(dir.path()).unwrap(), LockState::Free);
        let again = RunLock::acquire(dir.path(), "run --resume").unwrap();
        let text = std::fs::read_to_string(again.path()).unwrap();
        assert!(text.contains("command=run --resume"), "{text}");
    }

    #[test]
    fn a_port_claim_names_its_holder_through_a_symlink_and_frees_on_drop() {
        let dir = tempfile::tempdir().unwrap();
        let device = dir.path().join("ttyFAKE0");
        std::fs::write(&device, b"").unwrap();
        let link = dir.path().join("stage");
        std::os::unix::fs::symlink(&device, &link).unwrap();
        let (d, l) = (device.to_str().unwrap(), link.to_str().unwrap());
        assert_eq!(port_claim_path(d), port_claim_path(l));
        assert_eq!(port_holder(d).unwrap(), None);
        let claim = PortClaim::acquire(l, "stage move").unwrap();
        let h = port_holder(d).unwrap().expect("held");
        assert_eq!(h.pid, Some(std::process::id()));
        assert_eq!(h.command.as_deref(), Some("stage move"));
        let e = PortClaim::acquire(d, "stage jog").unwrap_err().to_string();
        assert!(
            e.contains(&format!("serial port {d} is in use"))
                && e.contains("'tactbench stage move'"),
            "{e}"
        );
        drop(claim);
        assert_eq!(port_holder(l).unwrap(), None);
    }

    #[test]
    fn holder_text_round_trips_and_junk_is_ignored() {
        let h = Holder {
            pid: Some(7),
            host: Some("lab\n3".into()),
            started_at: Some("2026-11-24T00:00:00Z".into()),
            command: Some("run".into()),
        };
        let back = Holder::parse(&h.to_text());
        assert_eq!(back.pid, Some(7));
        assert_eq!(back.host.as_deref(), Some("lab 3"));
        assert_eq!(Holder::parse("garbage\npid=x\n"), Holder::default());
        assert!(Holder::default().to_string().contains("just started"));
    }
}
