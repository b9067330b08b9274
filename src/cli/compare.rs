//! `tactbench compare`: several run directories against a baseline ->
//! compare.html, compare.csv, plots/compare_*, with optional acceptance criteria
//! (absolute, or relative to the baseline) and an exit code that gates a build.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;

use tactbench::report::acceptance::{self, Criteria, Outcome};
use tactbench::report::compare::{self, Comparison};
use tactbench::report::verdict::{EXIT_FAIL, EXIT_INCOMPLETE, EXIT_PASS};

/// Compare run directories (elastomer builds) with a baseline run.
///
/// Loads each RUN_DIR as `report` does (manifest.json, journal.csv, per-setpoint
/// files; a run still in progress or incomplete is shown as such) and writes into
/// --out DIR one self-contained page compare.html (figures embedded, everything
/// escaped), compare.csv (one row per metric and run: value, 95 % CI, difference to the
/// baseline, its CI and significance, criterion and outcome; columns in the README)
/// and plots/compare_*.png|svg (metric trends over the runs in date order, labelled by
/// build id; applied-vs-measured curves overlaid, one colour per run).
///
/// The baseline is the first RUN_DIR, or --baseline (one of the RUN_DIRs, or an extra
/// run). Differences are value - baseline; significant when the difference's 95 % CI
/// (d ± 1.96 √(SE² + SE_b²), SE = CI half-width / 1.96, runs independent) excludes 0;
/// n/a where either run states no CI. Runs of different sweep kinds, plans (plan
/// SHA-256) or sensors (sensor SHA-256) are refused (exit 2, naming what differs)
/// unless --allow-different-plans, which the banner then states. The worst run is
/// named per metric where
/// "better" has a direction (lower resolution, SD, errors, times; R² higher; slope
/// closer to 1; biases and offsets closer to 0).
///
/// Criteria (--acceptance, the `report` format): absolute bounds apply to every run;
/// max_relative_to_baseline = r (value <= b + r|b|), min_relative_to_baseline = r
/// (value >= b - r|b|), max_increase = d (value <= b + d) and max_decrease = d
/// (value >= b - d), with b the baseline's value, apply to the other runs.
///
/// Exit codes, decided by the runs other than the baseline: 0 = every compared run
/// PASS or MARGINAL (or NOT JUDGED: no criteria); 1 = a compared run FAILs; 5 = no FAIL,
/// but a compared run, or the baseline, did not measure its whole plan (not graded;
/// --allow-partial grades it); 2 = error (not a run directory, the same run twice,
/// fewer than two runs, a bad criteria file, a criterion naming a metric a run does
/// not have, a relative criterion whose metric the baseline lacks).
#[derive(clap::Args)]
#[command(after_long_help = after_help())]
pub struct Args {
    /// Run directories written by `tactbench run` (the first is the baseline unless
    /// --baseline is given).
    #[arg(value_name = "RUN_DIR", required = true)]
    runs: Vec<PathBuf>,
    /// The baseline run (one of RUN_DIR..., or an extra run put first).
    #[arg(long, value_name = "RUN_DIR")]
    baseline: Option<PathBuf>,
    /// Acceptance criteria (TOML, the `report` format plus bounds relative to the
    /// baseline: max_relative_to_baseline, min_relative_to_baseline, max_increase,
    /// max_decrease).
    #[arg(long, value_name = "CRITERIA.toml")]
    acceptance: Option<PathBuf>,
    /// Grade runs that did not measure their whole plan instead of calling them
    /// INCOMPLETE.
    #[arg(long)]
    allow_partial: bool,
    /// Compare runs of different sweep kinds, plans or sensors anyway (refused
    /// otherwise, exit 2); the banner then says the runs are not like for like.
    #[arg(long)]
    allow_different_plans: bool,
    /// Output directory (created if missing).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
}

fn after_help() -> String {
    format!(
        "Examples:\n  \
         tactbench compare runs/build-41 runs/build-42 --out cmp\n  \
         tactbench compare runs/b42 runs/b43 --baseline runs/b41 --acceptance gate.toml --out cmp\n\n\
         Relative criteria (b = the baseline's value of the metric):\n  \
         [[criterion]]\n  metric = \"magnitude.resolution_gf\"\n  \
         max_relative_to_baseline = 0.10   # at most 10 % worse: value <= b + 0.10 |b|\n\n  \
         [[criterion]]\n  metric = \"magnitude.r2\"\n  min = 0.99                        # absolute: every run\n  \
         max_decrease = 0.002              # value >= b - 0.002\n\n\
         Exit codes (the runs other than the baseline decide):\n  \
         {EXIT_PASS}  every compared run PASS or MARGINAL (or NOT JUDGED: no criteria given)\n  \
         {EXIT_FAIL}  a compared run FAILs a criterion or a provenance requirement\n  \
         2  error: nothing judged\n  \
         {EXIT_INCOMPLETE}  INCOMPLETE: a compared run or the baseline did not measure its whole plan (--allow-partial grades it)\n\n\
         Metrics (<layer> = a layer name of the sensor):\n{}",
        acceptance::known_metrics_text()
    )
}

pub fn run(args: Args) -> Result<ExitCode> {
    let criteria = match &args.acceptance {
        Some(p) => Some(Criteria::from_path(p)?),
        None => None,
    };
    let (dirs, baseline) = compare::plan_runs(&args.runs, args.baseline.as_deref())?;
    let mut loaded = Vec::with_capacity(dirs.len());
    for d in &dirs {
        loaded.push(compare::load_run(d)?);
    }
    let c = Comparison::new(
        loaded,
        baseline,
        criteria.as_ref(),
        args.allow_partial,
        args.allow_different_plans,
    )?;
    for d in &c.differences {
        eprintln!("warning: not like for like (--allow-different-plans): {d}");
    }
    for (r, ins) in c.runs.iter().zip(&c.instruments) {
        let list: Vec<String> = ins
            .devices
            .iter()
            .map(|(d, id)| format!("{d}: {id}"))
            .collect();
        println!("instruments of {}: {}", r.label, list.join("; "));
    }
    for d in &c.instrument_differences {
        eprintln!("warning: different instruments: {d}");
    }
    for w in &c.record_warnings {
        eprintln!("warning: {w}");
    }
    for r in &c.runs {
        for f in &r.verdict.run.failed_rows {
            eprintln!(
                "note: {}: failed row skipped (no force): {f}",
                r.dir.display()
            );
        }
    }
    let written = compare::write_comparison(&c, &args.out)?;
    for r in &c.runs {
        let s = &r.verdict.run;
        if let Some(t) = &s.torn_journal_line {
            eprintln!(
                "warning: {}: journal line {} is torn ({} bytes cut mid-write); using the complete rows",
                r.dir.display(),
                t.line,
                t.bytes
            );
        }
        if let Some(w) = &s.writer {
            eprintln!("note: {} is still in progress ({w})", r.dir.display());
        }
        for (name, why) in &r.analysis.absent {
            eprintln!("note: {}: no {name} analysis: {why}", r.dir.display());
        }
    }
    println!("wrote {}", written.html.display());
    println!("wrote {}", written.csv.display());
    for f in &written.figures {
        println!("wrote {} and .svg", f.png.display());
    }
    println!(
        "baseline: {} ({})",
        c.baseline_run().label,
        c.baseline_run().dir.display()
    );
    for m in &c.metrics {
        if let Some(w) = m.worst {
            println!("worst {}: {}", m.name, c.runs[w].label);
        }
    }
    for r in &c.runs {
        for v in &r.verdicts {
            println!("{}: {v}", r.label);
        }
        let s = &r.verdict.run;
        println!(
            "{}{}: {} ({}, {} of {} planned setpoints{})",
            r.label,
            if r.is_baseline { " (baseline)" } else { "" },
            r.verdict.outcome,
            s.status,
            s.measured_setpoints,
            s.planned_setpoints,
            match r.verdict.simulated {
                Some(true) => ", SIMULATED bench",
                Some(false) => ", real bench",
                None => ", bench kind not recorded",
            }
        );
    }
    if c.outcome == Outcome::Incomplete {
        eprintln!("note: {}", c.summary);
    }
    println!("comparison: {}", c.summary);
    Ok(ExitCode::from(c.exit_code))
}
