//! `tactbench serve`: the live view of runs written by other processes (or finished
//! ones), side by side (library: [`tactbench::live`]).

use std::path::PathBuf;
use std::process::ExitCode;

use tactbench::live::{LiveServer, ServeOptions, DEFAULT_ADDR};

/// Watch runs in the browser: the live view of run directories another process is
/// writing (`tactbench run`), or finished ones, side by side.
///
/// Prints the page's URL on stderr and serves until interrupted (Ctrl-C). The page
/// shows, per run: its state, setpoint k of n, elapsed and remaining time, the
/// current phase, the newest camera frame with marker statuses and displacement
/// arrows, the newest force field, applied against measured force (or angle) point by
/// point, the provisional verdict per criterion (with --acceptance), the F/T reading
/// and stage position during the setpoint, marker health over the run, warnings, the
/// end reason, and a link to report.html once `tactbench report` wrote it. It is
/// updated by push (server-sent events) and reads the run directories only:
/// manifest.json, journal.csv (new lines only), live.json (the runner's activity),
/// the newest frame, track and force files.
///
/// Access: on a loopback address (the default) the page is open to this machine;
/// any other address (e.g. 0.0.0.0:7878) turns on a random token, printed in the URL,
/// without which every request gets 401. The page is read-only except its Stop button
/// (behind a confirmation), which sends the run's process SIGINT, as Ctrl-C does.
///
/// Exit status: 2 when an address or a directory is bad (in use, not of this machine,
/// not a run); otherwise serves until interrupted.
#[derive(clap::Args)]
#[command(after_long_help = "Examples:
  # Watch a run written by another terminal's `tactbench run`:
  tactbench serve runs/fig7
  # Two runs side by side, from another machine (token printed in the URL):
  tactbench serve runs/fig7 runs/fig8 --addr 0.0.0.0:7878
  # With the provisional verdict against acceptance criteria:
  tactbench serve runs/fig7 --acceptance experiments/acceptance_example.toml")]
pub struct Args {
    /// Run directories (written by `tactbench run`, running or finished).
    #[arg(value_name = "RUN_DIR", required = true)]
    runs: Vec<PathBuf>,
    /// Address to serve on, HOST:PORT (port 0: any free port).
    #[arg(long, value_name = "ADDR", default_value = DEFAULT_ADDR)]
    addr: String,
    /// Acceptance criteria (as `report --acceptance`): the page shows the verdict so
    /// far per criterion, marked provisional until the run completes.
    #[arg(long, value_name = "CRITERIA.toml")]
    acceptance: Option<PathBuf>,
}

pub fn run(a: Args) -> anyhow::Result<ExitCode> {
    let server = LiveServer::start(
        &a.runs,
        &ServeOptions {
            addr: a.addr.clone(),
            criteria: a.acceptance.clone(),
        },
        None,
    )?;
    eprintln!(
        "live view of {} run(s): {}{}",
        a.runs.len(),
        server.url(),
        if server.url().contains("token=") {
            " (not a loopback address: requests need this token)"
        } else {
            ""
        }
    );
    eprintln!("serving until interrupted (Ctrl-C)");
    server.wait();
    Ok(ExitCode::SUCCESS)
}
