//! The runner's writes into the run directory, through one seam: every file it writes
//! during a session (reference and setpoint frames, displacement and force files,
//! journal rows, the closing manifest) goes through [`WriteGate`], which
//!
//! - records the **first** write that failed ([`WriteFailure`]: path relative to the
//!   run directory, the operating system's error text, the time) so the manifest can
//!   say which write stopped the run (a full disk shows up first on whichever file
//!   happens to be written, rarely on the manifest), and
//! - injects failures on request ([`WriteFault`], for tests: a disk that fills after
//!   N writes, for K writes or for good), the way `device::fault` injects device
//!   faults. Without a fault configured the gate only counts.

use std::collections::BTreeMap;
use std::error::Error;
use std::io;
use std::path::{Path, PathBuf};

use super::{rfc3339_now, Halt};
use crate::bench::integrity::{file_sha256, is_evidence};
use crate::bench::journal::WriteFailure;

/// Injected write failures (tests): the first `after_writes` writes of a session
/// succeed, then `failures` writes fail (`None`: every later write, a disk that stays
/// full) with the OS error `errno` (28 = ENOSPC, "No space left on device").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WriteFault {
    /// Writes that succeed first.
    pub after_writes: usize,
    /// Writes that fail from then on (`None`: all of them).
    pub failures: Option<usize>,
    /// The raw OS error number of the failure.
    pub errno: i32,
}

impl WriteFault {
    /// A disk that is full after `after_writes` writes and stays full.
    pub fn disk_full_after(after_writes: usize) -> WriteFault {
        WriteFault {
            after_writes,
            failures: None,
            errno: 28,
        }
    }
}

/// Counts writes, injects [`WriteFault`]s, keeps the first failure, and the SHA-256 of
/// every evidence file as written (`manifest.json` `record.evidence`).
#[derive(Debug, Default)]
pub(super) struct WriteGate {
    fault: Option<WriteFault>,
    writes: usize,
    injected: usize,
    first: Option<WriteFailure>,
    dir: PathBuf,
    evidence: BTreeMap<String, String>,
}

impl WriteGate {
    /// A gate for the run directory `dir`, continuing the `evidence` digests of the
    /// run's earlier sessions.
    pub(super) fn new(
        fault: Option<WriteFault>,
        dir: &Path,
        evidence: BTreeMap<String, String>,
    ) -> WriteGate {
        WriteGate {
            fault,
            dir: dir.to_path_buf(),
            evidence,
            ..WriteGate::default()
        }
    }

    /// Evidence file -> SHA-256 as written (earlier sessions' and this one's).
    pub(super) fn evidence(&self) -> &BTreeMap<String, String> {
        &self.evidence
    }

    /// The first write that failed this session, if one did.
    pub(super) fn first_failure(&self) -> Option<&WriteFailure> {
        self.first.as_ref()
    }

    /// Before a write: the injected failure due now, if any.
    fn injected(&mut self) -> io::Result<()> {
        let n = self.writes;
        self.writes += 1;
        if let Some(f) = self.fault {
            if n >= f.after_writes && f.failures.is_none_or(|k| self.injected < k) {
                self.injected += 1;
                return Err(io::Error::from_raw_os_error(f.errno));
            }
        }
        Ok(())
    }

    /// Records a failed write of `rel` (first one only) and returns the OS error text.
    pub(super) fn failed(&mut self, rel: &str, e: &(dyn Error + 'static)) -> String {
        let error = os_error_text(e);
        if self.first.is_none() {
            self.first = Some(WriteFailure {
                path: rel.to_string(),
                error: error.clone(),
                at: rfc3339_now(),
            });
        }
        error
    }

    /// Runs the write `w` of `rel` (relative to the run directory) through the gate;
    /// a failure is recorded and returned as its OS error text.
    pub(super) fn write<E: Error + 'static>(
        &mut self,
        rel: &str,
        w: impl FnOnce() -> Result<(), E>,
    ) -> Result<(), String> {
        if let Err(e) = self.injected() {
            return Err(self.failed(rel, &e));
        }
        w().map_err(|e| self.failed(rel, &e))
    }

    /// As [`WriteGate::write`] inside a setpoint: a failure aborts the run.
    pub(super) fn step<E: Error + 'static>(
        &mut self,
        rel: &str,
        w: impl FnOnce() -> Result<(), E>,
    ) -> Result<(), Halt> {
        self.write(rel, w)
            .map_err(|error| Halt::Abort(format!("cannot write {rel}: {error}")))?;
        if is_evidence(rel) {
            // Read back as it is on disk: the digest is of what a reader will find.
            if let Some(d) = file_sha256(&self.dir.join(rel)) {
                self.evidence.insert(rel.to_string(), d);
            }
        }
        Ok(())
    }
}

/// The operating system's error text: the innermost `io::Error` in the chain (the
/// writers wrap it with the path), else the error's own text.
pub(super) fn os_error_text(e: &(dyn Error + 'static)) -> String {
    let mut cur: Option<&(dyn Error + 'static)> = Some(e);
    let mut found = None;
    while let Some(c) = cur {
        if let Some(io) = c.downcast_ref::<io::Error>() {
            found = Some(io.to_string());
        }
        cur = c.source();
    }
    found.unwrap_or_else(|| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_failure_is_kept_and_injection_stops_after_its_count() {
        let mut g = WriteGate::new(
            Some(WriteFault {
                after_writes: 1,
                failures: Some(2),
                errno: 28,
            }),
            Path::new("."),
            BTreeMap::new(),
        );
        let ok = || Ok::<(), io::Error>(());
        assert!(g.write("a", ok).is_ok());
        let e = g.write("frames/00001_0.png", ok).unwrap_err();
        assert!(e.contains("No space left on device"), "{e}");
        assert!(g.write("journal.csv", ok).is_err());
        assert!(
            g.write("c", ok).is_ok(),
            "two failures, then the disk has room"
        );
        let f = g.first_failure().unwrap();
        assert_eq!(f.path, "frames/00001_0.png");
        assert!(f.error.contains("os error 28"), "{}", f.error);
    }

    #[test]
    fn a_real_writer_error_is_recorded_with_its_os_text() {
        let mut g = WriteGate::new(None, Path::new("."), BTreeMap::new());
        let e = g
            .write("forces/00000.csv", || {
                Err(crate::formats::FormatError::Io {
                    path: "/x/forces/00000.csv".into(),
                    source: io::Error::from_raw_os_error(5),
                })
            })
            .unwrap_err();
        assert!(e.contains("os error 5"), "{e}");
        assert!(!e.contains("/x/"), "the OS error alone: {e}");
        assert_eq!(g.first_failure().unwrap().path, "forces/00000.csv");
    }
}
