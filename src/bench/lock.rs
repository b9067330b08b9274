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
        let io = |source| LockError::Io {
            path: path.clone(),
            source,
        };
        // Never truncate on open: the file names the holder until we hold the lock.
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
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
                    return Err(LockError::Held {
                        dir: dir.to_path_buf(),
                        holder: Holder::parse(&text),
                    });
                }
                Err(TryLockError::Error(e)) => return Err(io(e)),
            }
        }
        let me = Holder::me(command);
        file.set_len(0).map_err(io)?;
        file.seek(SeekFrom::Start(0)).map_err(io)?;
        file.write_all(me.to_text().as_bytes()).map_err(io)?;
        file.sync_all().map_err(io)?;
        Ok(RunLock { file, path })
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
    let path = dir.join(LOCK_FILE);
    let mut file = match File::open(&path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(LockState::NoLockFile),
        Err(source) => return Err(LockError::Io { path, source }),
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
        Err(TryLockError::Error(source)) => Err(LockError::Io { path, source }),
    }
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
