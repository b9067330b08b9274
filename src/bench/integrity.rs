//! The record protects itself: SHA-256 digests of `journal.csv` and of every evidence
//! file (`frames/`, `displacements/`, `forces/`) as the runner wrote them, kept in the
//! manifest (`record`), and their verification by the readers (`report`, `archive`,
//! `compare`), which say "modified after the run" when a file no longer matches.
//!
//! **The journal grows**, so its digest is of a prefix: at the start and at the end
//! of every session the runner records the SHA-256 of the whole journal as it is then
//! and its length in bytes. A reader hashes the journal's first `journal_bytes` bytes:
//! a different digest (or a shorter journal) is a journal modified after the run;
//! rows beyond the recorded length were written by a session that did not record its
//! end (killed): they are counted as "not covered by a digest", not as modified.
//! Evidence files get their digest when the runner writes them (re-acquired frames:
//! the last write); a missing evidence file is not a modification (archives leave
//! them out), a different one is.
//!
//! Manifests written before digests were recorded have none: the check says "not
//! recorded" and changes nothing.

use std::collections::BTreeMap;
use std::fmt;
use std::io::Read;
use std::path::Path;

use serde::Serialize;
use sha2::{Digest, Sha256};

pub use super::journal::RecordDigests;
use super::journal::{Manifest, JOURNAL_FILE};

/// SHA-256 of `data` as 64 lowercase hex digits.
pub fn sha256_hex(data: &[u8]) -> String {
    Sha256::digest(data)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// SHA-256 of a file, read in blocks; `None` when it cannot be read.
pub fn file_sha256(path: &Path) -> Option<String> {
    let mut f = std::fs::File::open(path).ok()?;
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 16];
    loop {
        let n = f.read(&mut buf).ok()?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Some(h.finalize().iter().map(|b| format!("{b:02x}")).collect())
}

/// Whether a path relative to the run directory is an evidence file.
pub fn is_evidence(rel: &str) -> bool {
    ["frames/", "displacements/", "forces/"]
        .iter()
        .any(|p| rel.starts_with(p))
}

impl RecordDigests {
    /// The journal's digest now (keeping `evidence`), taken at `at`.
    pub fn journal_now(
        dir: &Path,
        evidence: BTreeMap<String, String>,
        rows: usize,
        at: String,
    ) -> std::io::Result<RecordDigests> {
        let bytes = std::fs::read(dir.join(JOURNAL_FILE))?;
        Ok(RecordDigests {
            journal_sha256: sha256_hex(&bytes),
            journal_bytes: bytes.len() as u64,
            journal_rows: rows,
            at,
            evidence,
        })
    }
}

/// What the verification of a run's record found.
#[derive(Debug, Clone, PartialEq, Default, Serialize)]
pub struct RecordCheck {
    /// The manifest records digests (false: a run from before they were recorded).
    pub recorded: bool,
    /// The journal no longer matches its digest: why, in words.
    pub journal_modified: Option<String>,
    /// Bytes of journal after the digested prefix (rows of a session killed before it
    /// recorded its end).
    pub journal_uncovered_bytes: u64,
    /// Evidence files whose content differs from what the runner wrote.
    pub evidence_modified: Vec<String>,
    /// Evidence files with a digest that are not in the directory (archives).
    pub evidence_missing: usize,
    /// Evidence files checked and intact.
    pub evidence_intact: usize,
}

impl RecordCheck {
    /// True when something recorded no longer matches.
    pub fn modified(&self) -> bool {
        self.journal_modified.is_some() || !self.evidence_modified.is_empty()
    }

    /// The findings in one line each (empty when there is nothing to say beyond
    /// "intact").
    pub fn lines(&self) -> Vec<String> {
        let mut out = Vec::new();
        if !self.recorded {
            return out;
        }
        if let Some(j) = &self.journal_modified {
            out.push(format!("{JOURNAL_FILE} modified after the run: {j}"));
        }
        if !self.evidence_modified.is_empty() {
            let n = self.evidence_modified.len();
            let shown: Vec<&str> = self
                .evidence_modified
                .iter()
                .take(5)
                .map(String::as_str)
                .collect();
            out.push(format!(
                "{n} evidence file(s) modified after the run: {}{}",
                shown.join(", "),
                if n > 5 { ", …" } else { "" }
            ));
        }
        if self.journal_uncovered_bytes > 0 {
            out.push(format!(
                "the last {} bytes of {JOURNAL_FILE} are not covered by a digest (written by a session that ended without recording its end, e.g. killed)",
                self.journal_uncovered_bytes
            ));
        }
        out
    }
}

impl fmt::Display for RecordCheck {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if !self.recorded {
            return write!(
                f,
                "record digests: not recorded (a run from before they were)"
            );
        }
        let lines = self.lines();
        if lines.is_empty() || !self.modified() && self.journal_uncovered_bytes == 0 {
            write!(
                f,
                "record digests: intact (journal and {} evidence file(s) as written{})",
                self.evidence_intact,
                if self.evidence_missing > 0 {
                    format!("; {} not in this directory", self.evidence_missing)
                } else {
                    String::new()
                }
            )
        } else {
            write!(f, "record digests: {}", lines.join("; "))
        }
    }
}

/// Verifies a run directory's journal and evidence against the manifest's digests,
/// and, in an archive, every file against `archive.json`'s `sha256` (which covers the
/// manifest too).
pub fn verify(dir: &Path, manifest: &Manifest) -> RecordCheck {
    let mut check = verify_manifest(dir, manifest);
    let Some(archived) = archive_digests(dir) else {
        return check;
    };
    check.recorded = true;
    for (rel, digest) in archived {
        let path = dir.join(&rel);
        if !path.exists() {
            if rel == JOURNAL_FILE || rel == super::journal::MANIFEST_FILE {
                check
                    .evidence_modified
                    .push(format!("{rel} (missing; archive.json has its SHA-256)"));
            }
            continue;
        }
        if file_sha256(&path).as_deref() != Some(digest.as_str()) {
            let what = format!("{rel} (differs from the SHA-256 archive.json recorded)");
            if rel == JOURNAL_FILE {
                check.journal_modified.get_or_insert(what);
            } else if !check.evidence_modified.contains(&rel) {
                check.evidence_modified.push(what);
            }
        }
    }
    check
}

/// `archive.json`'s `sha256` map, when the directory is an archive that has one.
fn archive_digests(dir: &Path) -> Option<BTreeMap<String, String>> {
    let text = std::fs::read_to_string(dir.join("archive.json")).ok()?;
    let v: serde_json::Value = serde_json::from_str(&text).ok()?;
    let m = v.get("sha256")?.as_object()?;
    Some(
        m.iter()
            .filter_map(|(k, v)| v.as_str().map(|d| (k.clone(), d.to_string())))
            .collect(),
    )
}

fn verify_manifest(dir: &Path, manifest: &Manifest) -> RecordCheck {
    let Some(rec) = &manifest.record else {
        return RecordCheck::default();
    };
    let mut check = RecordCheck {
        recorded: true,
        ..RecordCheck::default()
    };
    match std::fs::read(dir.join(JOURNAL_FILE)) {
        Err(e) => check.journal_modified = Some(format!("cannot be read: {e}")),
        Ok(bytes) => {
            let n = rec.journal_bytes as usize;
            if bytes.len() < n {
                check.journal_modified = Some(format!(
                    "{} bytes, shorter than the {n} bytes recorded at {}",
                    bytes.len(),
                    rec.at
                ));
            } else if sha256_hex(&bytes[..n]) != rec.journal_sha256 {
                check.journal_modified = Some(format!(
                    "its first {n} bytes ({} rows) differ from the SHA-256 recorded at {}",
                    rec.journal_rows, rec.at
                ));
            } else {
                check.journal_uncovered_bytes = (bytes.len() - n) as u64;
            }
        }
    }
    for (rel, digest) in &rec.evidence {
        let path = dir.join(rel);
        if !path.exists() {
            check.evidence_missing += 1;
            continue;
        }
        match file_sha256(&path) {
            Some(d) if &d == digest => check.evidence_intact += 1,
            _ => check.evidence_modified.push(rel.clone()),
        }
    }
    check
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prefix_digest_tells_appended_rows_from_edits() {
        let dir = tempfile::tempdir().unwrap();
        let j = dir.path().join(JOURNAL_FILE);
        std::fs::write(&j, "index,x\n0,1\n").unwrap();
        let rec = RecordDigests::journal_now(dir.path(), BTreeMap::new(), 1, "t".into()).unwrap();
        let m = Manifest {
            record: Some(rec),
            ..crate::bench::journal::tests_support::manifest()
        };
        assert!(!verify(dir.path(), &m).modified());
        std::fs::write(&j, "index,x\n0,1\n1,2\n").unwrap();
        let c = verify(dir.path(), &m);
        assert!(!c.modified());
        assert_eq!(c.journal_uncovered_bytes, 4);
        std::fs::write(&j, "index,x\n0,2\n1,2\n").unwrap();
        let c = verify(dir.path(), &m);
        assert!(c.modified(), "{c}");
        assert!(c.to_string().contains("modified after the run"), "{c}");
    }
}
