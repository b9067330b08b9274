//! `tactbench report`: run directory -> report.html, summary.csv, plots/, with optional
//! acceptance verdicts and an exit code that gates a build.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};

use tactbench::analysis::{AnalysisOptions, RunAnalysis};
use tactbench::report::{self, acceptance::Criteria};

/// Exit code when at least one acceptance criterion fails.
pub const EXIT_FAIL: u8 = 1;

/// Analyse a run directory and write its report.
///
/// Reads RUN_DIR (manifest.json, journal.csv, displacements/, forces/), computes the
/// paper's evaluation for the plan's sweep kind (magnitude: Fig. 7; angle: Fig. 8;
/// spatial: Fig. 9; displacement: Table I; timing of every run: Table II) and writes
/// RUN_DIR/report.html (self-contained, figures embedded), RUN_DIR/summary.csv
/// (metric,value,unit) and RUN_DIR/plots/*.png|svg.
///
/// With --acceptance, each criterion of CRITERIA.toml is judged and printed as a
/// PASS/FAIL line with the value and the threshold; the verdicts are also in the report.
///
/// Exit codes: 0 = report written and every criterion passed (or none given);
/// 1 = report written and at least one criterion FAILED; 2 = error (unreadable or
/// invalid run directory or criteria file, a criterion naming a metric the run does not
/// have); nothing is judged then.
#[derive(clap::Args)]
#[command(after_long_help = after_help())]
pub struct Args {
    /// The run directory written by `tactbench run`.
    #[arg(value_name = "RUN_DIR")]
    run_dir: PathBuf,
    /// Acceptance criteria (TOML, `[[criterion]]` with metric and min and/or max).
    #[arg(long, value_name = "CRITERIA.toml")]
    acceptance: Option<PathBuf>,
    /// Setpoint index for the displacement and force-field figures (default: the row
    /// with the largest reconstructed force sum).
    #[arg(long, value_name = "INDEX")]
    setpoint: Option<usize>,
}

/// Examples, the criteria format and the metric names (from the library's table).
fn after_help() -> String {
    format!(
        "Examples:\n  \
         tactbench report runs/fig7\n  \
         tactbench report runs/fig7 --acceptance experiments/acceptance_example.toml\n  \
         tactbench report runs/fig7 --setpoint 15    # field figures of setpoint 15\n\n\
         Criteria file (bounds inclusive, at least one of min / max):\n  \
         [[criterion]]\n  metric = \"magnitude.r2\"\n  min = 0.99\n\n  \
         [[criterion]]\n  metric = \"timing.forces_ms\"\n  max = 2.9\n\n\
         Exit codes: 0 all criteria pass (or none given), {EXIT_FAIL} a criterion FAILED, 2 error.\n\n\
         Metrics (<layer> = a layer name of the sensor):\n{}",
        report::acceptance::known_metrics_text()
    )
}

pub fn run(args: Args) -> Result<ExitCode> {
    // Validate the criteria before the (slower) analysis so a typo fails fast.
    let criteria = match &args.acceptance {
        Some(p) => Some(Criteria::from_path(p)?),
        None => None,
    };
    let options = AnalysisOptions {
        snapshot_index: args.setpoint,
    };
    let analysis = RunAnalysis::load(&args.run_dir, &options)
        .with_context(|| format!("analysing run directory {}", args.run_dir.display()))?;
    let outcome = report::write_report(&analysis, criteria.as_ref())
        .with_context(|| format!("writing the report of {}", args.run_dir.display()))?;
    println!("wrote {}", outcome.html.display());
    println!("wrote {}", outcome.summary.display());
    for f in &outcome.figures {
        println!("wrote {} and .svg", f.png.display());
    }
    for v in &outcome.verdicts {
        println!("{v}");
    }
    if criteria.is_none() {
        return Ok(ExitCode::SUCCESS);
    }
    let failed = outcome.verdicts.iter().filter(|v| !v.pass).count();
    if failed == 0 {
        println!("acceptance: PASS ({} criteria)", outcome.verdicts.len());
        Ok(ExitCode::SUCCESS)
    } else {
        println!(
            "acceptance: FAIL ({failed} of {} criteria failed)",
            outcome.verdicts.len()
        );
        Ok(ExitCode::from(EXIT_FAIL))
    }
}
