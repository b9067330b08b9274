//! `tactbench archive`: a compact copy of a run directory that still reports and
//! compares like the original.
//!
//! A run's record is `manifest.json` + `journal.csv`; the frames and per-setpoint
//! files are evidence (ARCHITECTURE.md, "The run directory"). An archive keeps:
//!
//! | `--keep` | files |
//! |---|---|
//! | every level | `manifest.json`, `journal.csv`; the report files of the source (`report.html`, `verdict.json`, `summary.csv`, `plots/`; written fresh into the archive, without criteria, when the source has none); the per-setpoint files a metric is computed from where the journal does not carry it: `forces/` of a `spatial` sweep (Fig. 9), `displacements/` of a `displacement` sweep (Table I) |
//! | `evidence` | also `frames/reference*.png` and, for the setpoints the camera evidence and the field figures show, their `displacements/`, `forces/` (with the per-node σ the run recorded in them) and frame files |
//! | `all` | every file of the run (not `run.lock`, `live.json`, `.sim/`, temporary files) |
//!
//! After copying, the archive is analysed like any run and its metrics compared with
//! the source's, value for value (bit-identical, CIs included); a mismatch removes the
//! archive and is an error. `archive.json` (schema `tactbench-archive/1`) records what
//! was kept. The source is only read; an existing non-empty `--out` is refused, and so
//! is a source a live process is still writing.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;
use thiserror::Error;

use super::{write_report_to, ReportError, ReportOptions, REPORT_FILE, SUMMARY_FILE};
use crate::analysis::{
    displacements_path, forces_path, AnalysisError, AnalysisOptions, Metric, RunAnalysis,
};
use crate::bench::integrity::{self, file_sha256, is_evidence};
use crate::bench::journal::{JOURNAL_FILE, MANIFEST_FILE};
use crate::bench::lock::{self, LockError, LockState};
use crate::bench::plan::Sweep;
use crate::report::verdict::VERDICT_FILE;

/// File name of the archive record inside an archive.
pub const ARCHIVE_FILE: &str = "archive.json";
/// `archive.json`'s schema identifier.
pub const SCHEMA: &str = "tactbench-archive/1";

/// What an archive keeps beyond the record and the report (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Keep {
    /// The record, the report and the metric inputs the journal lacks.
    None,
    /// Also the reference frame and the files of the setpoints the evidence shows.
    Evidence,
    /// Every file of the run.
    All,
}

impl Keep {
    /// `none`, `evidence`, `all`.
    pub fn word(self) -> &'static str {
        match self {
            Keep::None => "none",
            Keep::Evidence => "evidence",
            Keep::All => "all",
        }
    }
}

impl std::str::FromStr for Keep {
    type Err = String;

    fn from_str(s: &str) -> Result<Keep, String> {
        match s {
            "none" => Ok(Keep::None),
            "evidence" => Ok(Keep::Evidence),
            "all" => Ok(Keep::All),
            _ => Err(format!("{s:?}: give none, evidence or all")),
        }
    }
}

/// An error archiving a run. Every variant names the directory or file.
#[derive(Debug, Error)]
pub enum ArchiveError {
    /// The source is not a run directory.
    #[error("{dir}: not a run directory: {why}")]
    NotARun {
        /// The source as given.
        dir: PathBuf,
        /// What is missing.
        why: String,
    },
    /// The output exists and is not empty.
    #[error("{out}: exists and is not empty; an archive is written into a new or empty directory (nothing was written)")]
    OutNotEmpty {
        /// The output directory.
        out: PathBuf,
    },
    /// The output lies inside the source (or is the source).
    #[error("{out}: lies inside the run directory {source_dir}; write the archive elsewhere")]
    OutInsideSource {
        /// The output directory.
        out: PathBuf,
        /// The source.
        source_dir: PathBuf,
    },
    /// A live process is writing the source.
    #[error(
        "{dir}: a live process is still writing the run ({holder}); archive it when it has ended"
    )]
    InProgress {
        /// The source.
        dir: PathBuf,
        /// The lock holder.
        holder: String,
    },
    /// Probing the source's lock failed.
    #[error("checking for a live writer of {dir}: {source}")]
    Lock {
        /// The source.
        dir: PathBuf,
        /// The lock error.
        source: Box<LockError>,
    },
    /// Analysing the source or the archive failed.
    #[error("analysing {dir}: {source}")]
    Analysis {
        /// The directory analysed.
        dir: PathBuf,
        /// The analysis error.
        source: Box<AnalysisError>,
    },
    /// Writing the archive's report failed.
    #[error("writing the report of the archive {dir}: {source}")]
    Report {
        /// The archive.
        dir: PathBuf,
        /// The report error.
        source: Box<ReportError>,
    },
    /// The archive does not report the source's metrics (it was removed again).
    #[error("the archive of {dir} does not report the same metrics as the run ({}); the archive was removed", .differences.join("; "))]
    MetricsDiffer {
        /// The source.
        dir: PathBuf,
        /// Each differing metric, in words.
        differences: Vec<String>,
    },
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> ArchiveError + '_ {
    move |source| ArchiveError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// `archive.json`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ArchiveRecord {
    /// [`SCHEMA`].
    pub schema: String,
    /// When the archive was written, RFC 3339 UTC.
    pub created_at: String,
    /// The source run directory as given.
    pub source: String,
    /// `none`, `evidence` or `all`.
    pub keep: Keep,
    /// The files kept, relative to the archive, sorted (`archive.json` itself not
    /// listed).
    pub files: Vec<String>,
    /// Bytes of every regular file in the source directory.
    pub bytes_source: u64,
    /// Bytes of the files kept.
    pub bytes_archive: u64,
    /// The archive reports the same metrics as the source (always true in a written
    /// archive: a mismatch is an error).
    pub metrics_match: bool,
    /// SHA-256 of each record and evidence file kept (`manifest.json`,
    /// `journal.csv`, `frames/`, `displacements/`, `forces/`) as archived: `report`,
    /// `compare` and `archive` of the archive say "modified after the run" when one
    /// differs (the report files are left out: `report` rewrites them).
    pub sha256: BTreeMap<String, String>,
    /// The source's record checked against its manifest's digests when it was
    /// archived: one line per finding (empty: intact, or not recorded).
    pub source_record: Vec<String>,
}

/// What [`archive`] did.
#[derive(Debug, Clone)]
pub struct ArchiveOutcome {
    /// The record written to `archive.json`.
    pub record: ArchiveRecord,
    /// Metrics compared (identical in both).
    pub metrics: usize,
    /// The report files were written fresh (the source had none).
    pub report_written: bool,
    /// Lines on what the archive cannot show that the source could (evidence left out).
    pub missing: Vec<String>,
}

/// Files of the run not worth archiving: the lock, the live hint, the simulated
/// bench's links, temporary files.
fn never_copied(rel: &Path) -> bool {
    let first = rel
        .components()
        .next()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .unwrap_or_default();
    let name = rel
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    matches!(
        first.as_str(),
        "run.lock" | "live.json" | ".sim" | ARCHIVE_FILE
    ) || name.ends_with(".tmp")
}

/// Every regular file under `dir` (symbolic links not followed), relative, sorted.
fn walk(dir: &Path) -> Result<Vec<(PathBuf, u64)>, ArchiveError> {
    let mut out = Vec::new();
    let mut stack = vec![PathBuf::new()];
    while let Some(rel) = stack.pop() {
        let abs = dir.join(&rel);
        for entry in std::fs::read_dir(&abs).map_err(io(&abs))? {
            let entry = entry.map_err(io(&abs))?;
            let meta = entry.metadata().map_err(io(&entry.path()))?;
            let r = rel.join(entry.file_name());
            if meta.is_dir() {
                stack.push(r);
            } else if meta.is_file() {
                out.push((r, meta.len()));
            }
        }
    }
    out.sort();
    Ok(out)
}

/// The files `keep` selects from the analysed source (relative paths that exist).
fn selection(analysis: &RunAnalysis, keep: Keep) -> Result<Vec<PathBuf>, ArchiveError> {
    let run = &analysis.run;
    let dir = &run.dir;
    if keep == Keep::All {
        return Ok(walk(dir)?
            .into_iter()
            .map(|(p, _)| p)
            .filter(|p| !never_copied(p))
            .collect());
    }
    let rel = |p: &Path| p.strip_prefix(dir).map(Path::to_path_buf).ok();
    let mut files: Vec<PathBuf> = vec![MANIFEST_FILE.into(), JOURNAL_FILE.into()];
    for f in [REPORT_FILE, VERDICT_FILE, SUMMARY_FILE] {
        files.push(f.into());
    }
    // The report's figure files (also embedded in report.html).
    let plots = dir.join(super::PLOTS_DIR);
    if plots.is_dir() {
        files.extend(
            walk(&plots)?
                .into_iter()
                .map(|(p, _)| Path::new(super::PLOTS_DIR).join(p)),
        );
    }
    // Metric inputs the journal does not carry.
    for r in &run.rows {
        match run.plan.sweep {
            Sweep::Spatial { .. } => files.extend(rel(&forces_path(dir, r.index))),
            Sweep::Displacement { .. } => files.extend(rel(&displacements_path(dir, r.index))),
            _ => {}
        }
    }
    if keep == Keep::Evidence {
        let frames = dir.join("frames");
        if let Ok(entries) = std::fs::read_dir(&frames) {
            for e in entries.flatten() {
                let name = e.file_name().to_string_lossy().into_owned();
                if name.starts_with("reference") && name.ends_with(".png") {
                    files.push(PathBuf::from("frames").join(name));
                }
            }
        }
        let mut shown = super::evidence::chosen_setpoints(run);
        shown.extend(analysis.snapshot.as_ref().map(|s| s.index));
        for index in shown {
            files.extend(rel(&displacements_path(dir, index)));
            files.extend(rel(&forces_path(dir, index)));
            if let Some(row) = run.rows.iter().find(|r| r.index == index) {
                files.extend(
                    row.frames
                        .split(';')
                        .map(str::trim)
                        .filter(|f| !f.is_empty() && !f.contains(".."))
                        .map(PathBuf::from),
                );
            }
        }
    }
    files.sort();
    files.dedup();
    Ok(files
        .into_iter()
        .filter(|f| dir.join(f).is_file())
        .collect())
}

/// Compares two metric lists value for value; the differences in words.
pub fn metric_differences(source: &[Metric], archive: &[Metric]) -> Vec<String> {
    let mut out = Vec::new();
    for m in source {
        match archive.iter().find(|a| a.name == m.name) {
            None => out.push(format!("{} is missing from the archive", m.name)),
            Some(a) => {
                let same_value = a.value.to_bits() == m.value.to_bits()
                    || (a.value.is_nan() && m.value.is_nan());
                let same_ci = match (a.ci95, m.ci95) {
                    (None, None) => true,
                    (Some(x), Some(y)) => {
                        x.low.to_bits() == y.low.to_bits()
                            && x.high.to_bits() == y.high.to_bits()
                            && x.method == y.method
                    }
                    _ => false,
                };
                if !same_value || !same_ci || a.unit != m.unit {
                    out.push(format!(
                        "{}: {} {} in the run, {} {} in the archive",
                        m.name, m.value, m.unit, a.value, a.unit
                    ));
                }
            }
        }
    }
    for a in archive {
        if !source.iter().any(|m| m.name == a.name) {
            out.push(format!("{} is only in the archive", a.name));
        }
    }
    out
}

/// Writes a compact copy of the run `source` into `out` (see the module docs).
pub fn archive(source: &Path, out: &Path, keep: Keep) -> Result<ArchiveOutcome, ArchiveError> {
    if !source.is_dir() {
        return Err(ArchiveError::NotARun {
            dir: source.to_path_buf(),
            why: if source.exists() {
                "not a directory".into()
            } else {
                "no such directory".into()
            },
        });
    }
    for f in [MANIFEST_FILE, JOURNAL_FILE] {
        if !source.join(f).is_file() {
            return Err(ArchiveError::NotARun {
                dir: source.to_path_buf(),
                why: format!("no {f} (written by `tactbench run`)"),
            });
        }
    }
    let out_existed = out.exists();
    if out_existed {
        let mut entries = std::fs::read_dir(out).map_err(io(out))?;
        if entries.next().is_some() {
            return Err(ArchiveError::OutNotEmpty {
                out: out.to_path_buf(),
            });
        }
    }
    let canon_src = std::fs::canonicalize(source).map_err(io(source))?;
    // The output's nearest existing ancestor, canonical, then the rest as given.
    let canon_out = {
        let mut base = out.to_path_buf();
        let mut tail = Vec::new();
        while !base.exists() {
            match (base.file_name(), base.parent()) {
                (Some(n), Some(p)) => {
                    tail.push(n.to_os_string());
                    base = if p.as_os_str().is_empty() {
                        PathBuf::from(".")
                    } else {
                        p.to_path_buf()
                    };
                }
                _ => break,
            }
        }
        let mut c = std::fs::canonicalize(&base).unwrap_or(base);
        for n in tail.into_iter().rev() {
            c.push(n);
        }
        c
    };
    if canon_out.starts_with(&canon_src) {
        return Err(ArchiveError::OutInsideSource {
            out: out.to_path_buf(),
            source_dir: source.to_path_buf(),
        });
    }
    match lock::probe(source) {
        Ok(LockState::Held(h)) => {
            return Err(ArchiveError::InProgress {
                dir: source.to_path_buf(),
                holder: h.to_string(),
            })
        }
        Ok(_) => {}
        Err(e) => {
            return Err(ArchiveError::Lock {
                dir: source.to_path_buf(),
                source: Box::new(e),
            })
        }
    }
    let analysis_err = |dir: &Path| {
        let dir = dir.to_path_buf();
        move |e| ArchiveError::Analysis {
            dir,
            source: Box::new(e),
        }
    };
    let src =
        RunAnalysis::load(source, &AnalysisOptions::default()).map_err(analysis_err(source))?;
    // The source's record as the run wrote it (said, and kept in archive.json).
    let source_check = integrity::verify(source, &src.run.manifest);
    let files = selection(&src, keep)?;
    let bytes_source: u64 = walk(source)?.iter().map(|(_, n)| n).sum();

    // From here on a failure removes what was written.
    let result = (|| {
        std::fs::create_dir_all(out).map_err(io(out))?;
        for f in &files {
            let to = out.join(f);
            if let Some(parent) = to.parent() {
                std::fs::create_dir_all(parent).map_err(io(parent))?;
            }
            std::fs::copy(source.join(f), &to).map_err(io(&to))?;
        }
        let arch =
            RunAnalysis::load(out, &AnalysisOptions::default()).map_err(analysis_err(out))?;
        let report_written = [REPORT_FILE, VERDICT_FILE, SUMMARY_FILE]
            .iter()
            .any(|f| !out.join(f).is_file());
        if report_written {
            let options = ReportOptions {
                allow_partial: false,
                lock: LockState::NoLockFile,
            };
            write_report_to(&arch, None, &options, out).map_err(|e| ArchiveError::Report {
                dir: out.to_path_buf(),
                source: Box::new(e),
            })?;
        }
        let (sm, am) = (src.metrics(), arch.metrics());
        let differences = metric_differences(&sm, &am);
        if !differences.is_empty() {
            return Err(ArchiveError::MetricsDiffer {
                dir: source.to_path_buf(),
                differences,
            });
        }
        let kept: Vec<(PathBuf, u64)> = walk(out)?
            .into_iter()
            .filter(|(p, _)| p != Path::new(ARCHIVE_FILE))
            .collect();
        let sha256 = kept
            .iter()
            .map(|(p, _)| p.to_string_lossy().replace('\\', "/"))
            .filter(|p| p == MANIFEST_FILE || p == JOURNAL_FILE || is_evidence(p))
            .filter_map(|p| file_sha256(&out.join(&p)).map(|d| (p, d)))
            .collect();
        let record = ArchiveRecord {
            sha256,
            source_record: source_check.lines(),
            schema: SCHEMA.into(),
            created_at: crate::bench::runner::rfc3339_now(),
            source: source.display().to_string(),
            keep,
            files: kept
                .iter()
                .map(|(p, _)| p.to_string_lossy().replace('\\', "/"))
                .collect(),
            bytes_source,
            bytes_archive: kept.iter().map(|(_, n)| n).sum(),
            metrics_match: true,
        };
        let path = out.join(ARCHIVE_FILE);
        let json = serde_json::to_string_pretty(&record).map_err(|e| ArchiveError::Io {
            path: path.clone(),
            source: std::io::Error::other(e.to_string()),
        })?;
        std::fs::write(&path, format!("{json}\n")).map_err(io(&path))?;
        let missing = arch
            .missing
            .iter()
            .filter(|m| !src.missing.contains(m))
            .cloned()
            .collect();
        Ok(ArchiveOutcome {
            record,
            metrics: sm.len(),
            report_written,
            missing,
        })
    })();
    if result.is_err() {
        // Only what this call created: the directory, or its contents if it existed
        // empty before.
        if out_existed {
            if let Ok(entries) = std::fs::read_dir(out) {
                for e in entries.flatten() {
                    let p = e.path();
                    let _ = if p.is_dir() {
                        std::fs::remove_dir_all(&p)
                    } else {
                        std::fs::remove_file(&p)
                    };
                }
            }
        } else {
            let _ = std::fs::remove_dir_all(out);
        }
    }
    result
}
