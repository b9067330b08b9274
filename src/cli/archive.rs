//! `tactbench archive`: a compact copy of a run directory (library:
//! [`tactbench::report::archive`]).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;

use tactbench::report::archive::{self, Keep};

/// Write a compact copy of a run directory that reports and compares like the run.
///
/// Keeps the record (manifest.json, journal.csv), the report (report.html,
/// verdict.json, summary.csv, plots/; written fresh, without criteria, when the run
/// has none)
/// and the per-setpoint files a metric needs that the journal does not carry (forces/
/// of a spatial sweep, displacements/ of a displacement sweep). --keep evidence also
/// keeps frames/reference*.png and the displacements, forces and frames of the
/// setpoints the camera evidence and the field figures show; --keep all keeps every
/// file (not run.lock, live.json, .sim/, temporary files).
///
/// The archive is then analysed like any run and must give exactly the run's metrics
/// (values and CIs); otherwise it is removed and the command fails. OUT/archive.json
/// (schema tactbench-archive/1) records the source, the level, the files kept and the
/// bytes of both. RUN_DIR is only read. An existing non-empty --out, an --out inside
/// RUN_DIR and a run still being written are refused.
///
/// Exit codes: 0 = archive written and checked; 2 = error (nothing left behind).
#[derive(clap::Args)]
#[command(
    after_long_help = "Examples:\n  tactbench archive runs/fig7 --out archive/fig7\n  tactbench archive runs/fig7 --keep evidence --out archive/fig7\n  tactbench report archive/fig7          # the same metrics as runs/fig7\n  tactbench compare archive/fig7 runs/fig7b --out cmp"
)]
pub struct Args {
    /// The run directory written by `tactbench run`.
    #[arg(value_name = "RUN_DIR")]
    run_dir: PathBuf,
    /// What to keep beyond the record and the report: none, evidence, all.
    #[arg(long, value_name = "none|evidence|all", default_value = "none")]
    keep: Keep,
    /// The archive directory (must not exist, or be empty).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
}

fn mib(b: u64) -> String {
    format!("{:.2} MiB", b as f64 / (1024.0 * 1024.0))
}

pub fn run(args: Args) -> Result<ExitCode> {
    let o = archive::archive(&args.run_dir, &args.out, args.keep)?;
    let r = &o.record;
    let count = |dir: &str| {
        r.files
            .iter()
            .filter(|f| f.starts_with(&format!("{dir}/")))
            .count()
    };
    let top: Vec<&str> = r
        .files
        .iter()
        .filter(|f| !f.contains('/'))
        .map(String::as_str)
        .collect();
    println!(
        "archived {} -> {} (--keep {})",
        args.run_dir.display(),
        args.out.display(),
        r.keep.word()
    );
    println!(
        "kept: {}; frames/: {} file(s), displacements/: {}, forces/: {}, plots/: {}",
        top.join(", "),
        count("frames"),
        count("displacements"),
        count("forces"),
        count("plots")
    );
    if o.report_written {
        println!("the run had no report: wrote one into the archive (no criteria: NOT JUDGED)");
    }
    for m in &o.missing {
        println!("not in the archive: {m}");
    }
    for l in &r.source_record {
        eprintln!("warning: {}: {l}", args.run_dir.display());
    }
    println!(
        "digests: SHA-256 of {} record and evidence file(s) in {}",
        r.sha256.len(),
        args.out
            .join(tactbench::report::archive::ARCHIVE_FILE)
            .display()
    );
    let saved = r.bytes_source.saturating_sub(r.bytes_archive);
    println!(
        "bytes: run {} ({}), archive {} ({}), saved {} ({:.1} %)",
        r.bytes_source,
        mib(r.bytes_source),
        r.bytes_archive,
        mib(r.bytes_archive),
        mib(saved),
        if r.bytes_source > 0 {
            100.0 * saved as f64 / r.bytes_source as f64
        } else {
            0.0
        }
    );
    println!(
        "checked: the archive reports the same {} metrics as the run (values and CIs identical)",
        o.metrics
    );
    println!("wrote {}", args.out.join(archive::ARCHIVE_FILE).display());
    Ok(ExitCode::SUCCESS)
}
