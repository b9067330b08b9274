//! `tactbench report`: run directory -> report.html, verdict.json, summary.csv,
//! plots/, with optional acceptance verdicts and an exit code that gates a build.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};

use tactbench::analysis::{AnalysisOptions, RunAnalysis};
use tactbench::bench::journal::{Manifest, JOURNAL_FILE};
use tactbench::bench::lock;
use tactbench::report::acceptance::{Criteria, Outcome, RunFit, Verdict};
use tactbench::report::verdict::{VerdictDoc, EXIT_FAIL, EXIT_INCOMPLETE, EXIT_PASS};
use tactbench::report::{self, ReportOptions};
use tactbench::sensor::Sensor;

/// Analyse a run directory, write its report and judge it.
///
/// Reads RUN_DIR (manifest.json, journal.csv, displacements/, forces/), computes the
/// paper's evaluation for the plan's sweep kind (magnitude: Fig. 7; angle: Fig. 8;
/// spatial: Fig. 9; displacement: Table I; timing of every run: Table II) and writes
/// OUT/report.html (self-contained, figures embedded, opening with the verdict
/// banner), OUT/verdict.json (the machine-readable verdict, schema in the README),
/// OUT/summary.csv (metric,value,unit,ci95_low,ci95_high,ci_method) and OUT/plots/*.png|svg, where OUT is RUN_DIR
/// unless --out is given.
///
/// The report only reads the run: it never changes manifest.json, journal.csv or the
/// frames, so it works on a run still in progress (and says so), on runs with 0 or 1
/// rows (analyses that need more data say why they are absent) and on a journal whose
/// last line was torn by a crash (the complete rows are used; the cut line is named).
///
/// Verdict: a run that did not measure its whole plan (--limit, interrupted, aborted,
/// killed, in progress) is INCOMPLETE whatever its metrics, unless --allow-partial
/// grades it anyway (the verdict then says so). Otherwise, with --acceptance, each
/// criterion of CRITERIA.toml is PASS, MARGINAL (within limits, in the marginal band)
/// or FAIL, printed with the value and the threshold; the verdict is the worst of them.
///
/// Without criteria (or with neither criteria nor requirements) a complete run is NOT
/// JUDGED (exit 0, never called PASS). A run on the simulated bench says SIMULATED on
/// the banner and `"simulated": true` in verdict.json; `require_real_bench = true`
/// FAILs it.
///
/// A run measured with a draft sensor file (`run --allow-draft`: placeholders never
/// measured) is refused (exit 2, the placeholders listed) unless --allow-draft, which
/// names them on stderr and on the report's banner.
///
/// Exit codes: 0 = PASS, MARGINAL or NOT JUDGED (no criteria given, complete run);
/// 1 = FAIL (a criterion or a provenance requirement failed); 5 = INCOMPLETE (the run
/// did not measure its whole plan; not graded); 2 = error (unreadable or invalid run
/// directory or criteria file, a criterion naming a metric the run's sweep kind does
/// not have); nothing is judged then.
#[derive(clap::Args)]
#[command(after_long_help = after_help(), allow_negative_numbers = true)]
pub struct Args {
    /// The run directory written by `tactbench run`.
    #[arg(value_name = "RUN_DIR")]
    run_dir: PathBuf,
    /// Acceptance criteria (TOML, `[[criterion]]` with metric, min and/or max,
    /// optional marginal_min / marginal_max; optional top-level require_build_id).
    #[arg(long, value_name = "CRITERIA.toml")]
    acceptance: Option<PathBuf>,
    /// Grade a run that did not measure its whole plan instead of calling it
    /// INCOMPLETE (the verdict says it graded a partial run).
    #[arg(long)]
    allow_partial: bool,
    /// Write the report files into DIR instead of RUN_DIR.
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Setpoint index for the displacement and force-field figures (default: the row
    /// with the largest reconstructed force sum).
    #[arg(long, value_name = "INDEX")]
    setpoint: Option<usize>,
    /// Report a run measured with a draft sensor file (placeholder values never
    /// measured): the placeholders are named on stderr and on the report's banner.
    #[arg(long)]
    allow_draft: bool,
    /// The run's fit (`tactbench fit --json`) for criteria on fitted parameters
    /// (`fit.<NAME>`); default RUN_DIR/fit.json when it exists.
    #[arg(long, value_name = "FIT.json")]
    fit: Option<PathBuf>,
}

/// Examples, the criteria format, the exit codes and the metric names (from the
/// library's table).
fn after_help() -> String {
    format!(
        "Examples:\n  \
         tactbench report runs/fig7\n  \
         tactbench report runs/fig7 --acceptance experiments/acceptance_example.toml\n  \
         tactbench report runs/try --allow-partial   # grade a --limit / interrupted run\n  \
         tactbench report runs/fig7 --setpoint 15    # field figures of setpoint 15\n\n\
         Criteria file (bounds inclusive, at least one of min / max):\n  \
         require_build_id = true     # optional: no build id recorded -> FAIL\n  \
         require_real_bench = true   # optional: simulated (or not recorded) -> FAIL\n\n  \
         [[criterion]]\n  metric = \"magnitude.r2\"\n  min = 0.99\n  \
         marginal_min = 0.995        # optional: r2 <= 0.995 (but >= 0.99) is MARGINAL\n\n  \
         [[criterion]]\n  metric = \"timing.forces_ms\"\n  max = 2.9\n\n  \
         [[criterion]]           # a fitted parameter, from RUN_DIR/fit.json or --fit\n  \
         metric = \"fit.young_modulus_kpa\"\n  \
         max_relative_to_nominal = 0.10   # within ±10 % of the fit's nominal value\n  \
         # max_deviation_from_nominal = 0.3  (same unit as the parameter)\n  \
         # MARGINAL when the 95 % interval straddles a limit; NOT JUDGED (never PASS)\n  \
         # when there is no fit or the parameter is not identifiable\n\n\
         Exit codes:\n  \
         {EXIT_PASS}  PASS, MARGINAL, or NOT JUDGED (no criteria given, complete run)\n  \
         {EXIT_FAIL}  FAIL: a criterion or a provenance requirement failed\n  \
         2  error: nothing judged (bad run directory or criteria file)\n  \
         {EXIT_INCOMPLETE}  INCOMPLETE: the run did not measure its whole plan (--allow-partial grades it)\n\n\
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
    // Before reading: a writer that ends meanwhile leaves a complete record, one that
    // is live keeps the run INCOMPLETE either way.
    let lock = lock::probe(&args.run_dir)
        .with_context(|| format!("checking for a live writer of {}", args.run_dir.display()))?;
    // A draft's forces are not measurements: refused before the (slower) analysis.
    let manifest = Manifest::read(&args.run_dir)
        .with_context(|| format!("analysing run directory {}", args.run_dir.display()))?;
    let sensor = Sensor::from_toml_str(&manifest.sensor_toml, &manifest.sensor_path)
        .with_context(|| format!("the sensor file recorded in {}", args.run_dir.display()))?;
    let draft = sensor.draft_warning(std::path::Path::new(&manifest.sensor_path));
    if !args.allow_draft {
        sensor
            .refuse_draft(std::path::Path::new(&manifest.sensor_path))
            .with_context(|| format!("run {} was measured with a draft", args.run_dir.display()))?;
    }
    if let Some(w) = &draft {
        eprintln!("warning: {w}");
    }
    let analysis = RunAnalysis::load(&args.run_dir, &options)
        .with_context(|| format!("analysing run directory {}", args.run_dir.display()))?;
    let report_options = ReportOptions {
        allow_partial: args.allow_partial,
        lock,
    };
    let out_dir = args.out.as_deref().unwrap_or(&args.run_dir);
    let fit = RunFit::load(&args.run_dir, args.fit.as_deref())
        .with_context(|| format!("reading the fit of {}", args.run_dir.display()))?;
    let outcome =
        report::write_report_with_fit(&analysis, criteria.as_ref(), &report_options, out_dir, &fit)
            .with_context(|| format!("writing the report of {}", args.run_dir.display()))?;
    let v = &outcome.verdict;
    if let Some(t) = &v.run.torn_journal_line {
        eprintln!(
            "warning: {}: line {} is torn ({} bytes cut mid-write); using the {} complete rows, the file is left as it is",
            analysis.run.dir.join(JOURNAL_FILE).display(),
            t.line,
            t.bytes,
            v.run.measured_setpoints
        );
    }
    if let Some(w) = &v.run.writer {
        eprintln!("note: the run is still in progress ({w})");
    }
    if let Some(w) = &v.run.write_failure {
        eprintln!("note: the run was aborted by a failed write: {w}");
    }
    if !v.run.failed_rows.is_empty() {
        eprintln!(
            "note: {} failed row(s) without force, skipped by every analysis (the run is at most MARGINAL):",
            v.run.failed_rows.len()
        );
        for f in &v.run.failed_rows {
            eprintln!("  {f}");
        }
    }
    if v.run.implausible_rows > 0 {
        eprintln!(
            "note: {} row(s) journalled quality = implausible (force sum does not fit the F/T reading)",
            v.run.implausible_rows
        );
    }
    for line in v.run.record.lines() {
        eprintln!("warning: {line}");
    }
    for (name, why) in &analysis.absent {
        eprintln!("note: no {name} analysis: {why}");
    }
    for m in &analysis.missing {
        eprintln!("note: not shown: {m}");
    }
    println!("wrote {}", outcome.html.display());
    println!("wrote {}", outcome.verdict_file.display());
    println!("wrote {}", outcome.summary.display());
    for f in &outcome.figures {
        println!("wrote {} and .svg", f.png.display());
    }
    for c in &outcome.verdicts {
        println!("{c}");
    }
    for r in &v.requirements {
        println!(
            "{} provenance: {} = {}",
            r.outcome,
            r.requirement,
            r.value.as_deref().unwrap_or("(none recorded)")
        );
    }
    println!(
        "run: {}, {} of {} planned setpoints measured; bench: {}",
        v.run.status,
        v.run.measured_setpoints,
        v.run.planned_setpoints,
        report::html::bench_line(v)
    );
    if criteria.is_some() {
        println!("acceptance: {}", acceptance_line(v, &outcome.verdicts));
    }
    println!("verdict: {}", v.summary);
    if let Some(w) = &draft {
        eprintln!("warning: {w}");
    }
    Ok(ExitCode::from(v.exit_code))
}

/// `PASS (3 criteria)`, `FAIL (1 of 2 criteria failed)`, `INCOMPLETE (...)`.
fn acceptance_line(v: &VerdictDoc, verdicts: &[Verdict]) -> String {
    let n = verdicts.len() + v.requirements.len();
    let failed = verdicts.iter().filter(|c| !c.pass()).count()
        + v.requirements
            .iter()
            .filter(|r| r.outcome == Outcome::Fail)
            .count();
    let marginal = verdicts
        .iter()
        .filter(|c| c.outcome == Outcome::Marginal)
        .count();
    let partial = if v.graded_partial {
        ", PARTIAL RUN graded with --allow-partial"
    } else {
        ""
    };
    let unjudged = verdicts
        .iter()
        .filter(|c| c.outcome == Outcome::NotJudged)
        .count();
    match v.outcome {
        Outcome::NotJudged if unjudged > 0 => {
            format!("NOT JUDGED ({unjudged} of {n} criteria not judged{partial})")
        }
        Outcome::NotJudged => "NOT JUDGED (no criteria, no requirement)".to_string(),
        Outcome::Pass => format!("PASS ({n} criteria{partial})"),
        Outcome::Marginal => format!("MARGINAL ({marginal} of {n} criteria marginal{partial})"),
        Outcome::Fail => format!("FAIL ({failed} of {n} criteria failed{partial})"),
        Outcome::Incomplete => format!(
            "INCOMPLETE ({} of {} planned setpoints measured; not graded)",
            v.run.measured_setpoints, v.run.planned_setpoints
        ),
    }
}
