//! `tactbench run`: the product's main job. Runs an experiment plan on a bench (real
//! or simulated) into a run directory, drawing progress with indicatif (library:
//! [`tactbench::bench::runner`]).

use std::fmt::Write as _;
use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{bail, Context};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use super::signals::{install_stop_handlers, stop_flags};
use tactbench::bench::config::BenchConfig;
use tactbench::bench::connect::{self, SimOptions};
use tactbench::bench::journal::{Direction, Manifest, RunStatus};
use tactbench::bench::lock::RunLock;
use tactbench::bench::plan::{self, Plan};
use tactbench::bench::runner::{self, Devices, RunEvent, RunOptions};
use tactbench::sensor::Sensor;
use tactbench::units::ForceUnit;

/// `run --help` examples: one command per example, continued with `\` so no line
/// is longer than 80 columns (clap wraps longer lines mid-command).
const RUN_EXAMPLES: &str = "\
Examples:
  # The paper's Fig. 7 magnitude sweep on the simulated bench (same drivers,
  # pseudo-terminals):
  tactbench run experiments/fig7_magnitude.toml \\
      --sim experiments/scenes/fig7_hemisphere_ramp.toml --out runs/fig7
  # What a plan will do, without opening any device:
  tactbench run experiments/fig8_angle.toml \\
      --bench experiments/bench_example.toml --dry-run
  # A real bench:
  tactbench run experiments/fig7_magnitude.toml \\
      --bench experiments/bench_example.toml --out runs/fig7 \\
      --build-id E-2026-11
  # Continue a killed or interrupted run (plan and bench from its manifest):
  tactbench run --resume runs/fig7
  # A short trial: the first 5 setpoints only:
  tactbench run experiments/fig7_magnitude.toml \\
      --bench experiments/bench_sim.toml --out runs/try --limit 5";

/// Run an experiment plan on the bench: force-controlled setpoints, frames, forces.
///
/// For every setpoint of PLAN the stage moves to the target (checked against the
/// plan's travel box and the stage's limits first), approaches until contact, brings
/// the measured force to the target within the tolerance by closed-loop stage motion,
/// waits for the force to settle, averages the F/T samples, grabs the frames, tracks
/// them against the reference frame and reconstructs the surface forces. While the
/// stage moves the force is watched: any component beyond its safety limit stops the
/// stage, retracts it and aborts the run.
///
/// The run directory (--out) receives manifest.json, journal.csv (one row per
/// setpoint, synced before the next move), frames/reference.png, frames/NNNNN_K.png,
/// displacements/NNNNN.csv (as `tactbench track` writes) and forces/NNNNN.csv (as
/// `tactbench reconstruct` writes). The plan's [quality] gates: a reference frame that
/// does not show the sensor file's markers aborts the run before any setpoint (with the
/// likely cause: scale, origin, colour, exposure); a setpoint whose frames track too
/// few markers is re-acquired, then flagged in the journal or aborted. Ctrl-C stops
/// motion, retracts and marks the run interrupted; `--resume DIR` continues a killed
/// or interrupted run without repeating or losing a setpoint.
///
/// The plan is validated before anything is expanded: more than 100000 setpoints,
/// 200000 frames, 100 GB of frames or an estimated 168 h is refused (exit 2), naming
/// the key. On a terminal a progress bar is drawn; otherwise (nohup, CI, a pipe) and
/// with --no-progress, plain lines: the set-up steps and one line per setpoint
/// (index, target, measured, F_sum, settled or not, time). With --dry-run the exit
/// status is 0 when every check passes, 3 when a limit check fails, 2 when an input
/// is missing or invalid.
///
/// One writer per run directory: `run` and `run --resume` hold an exclusive lock on
/// DIR/run.lock for the whole run (released by the kernel when the process ends, even
/// on SIGKILL); a second writer is refused at once (exit 2) naming the holder's PID,
/// host and start time.
///
/// A draft sensor file (`sensor init`: `draft = true` with placeholders left) is
/// refused (exit 2, the placeholders listed), also by --dry-run and --resume, unless
/// --allow-draft: then its placeholders are printed at the start and the end of the
/// run (the manifest keeps the sensor file's text, draft keys included).
///
/// Exit status: 0 when every setpoint of the run was measured, 3 when the run was
/// aborted (device error, safety trip), 4 when interrupted (SIGINT, SIGTERM, SIGHUP),
/// 2 on other errors (including a run directory another process is writing); the
/// reason goes to stderr and into manifest.json.
#[derive(clap::Args)]
#[command(after_long_help = RUN_EXAMPLES, allow_negative_numbers = true)]
pub struct Args {
    /// Experiment plan (experiments/*.toml). Optional with --resume (taken from the
    /// run's manifest).
    #[arg(value_name = "PLAN.toml")]
    plan: Option<PathBuf>,
    /// Bench file naming the devices (or `[sim]` with a scene).
    #[arg(long, value_name = "bench.toml", conflicts_with = "sim")]
    bench: Option<PathBuf>,
    /// Run on the simulated bench for this scene (GRBL stage, DynPick F/T).
    #[arg(long, value_name = "SCENE.toml")]
    sim: Option<PathBuf>,
    /// Run directory to create (must not hold a run already).
    #[arg(long, value_name = "DIR", conflicts_with = "resume")]
    out: Option<PathBuf>,
    /// Continue the run in DIR: the setpoints of its plan not yet in its journal
    /// (all of them, or at most --limit N). A run stopped by --limit (status
    /// completed, verdict INCOMPLETE) is resumable to its full plan; only a run whose
    /// journal holds every planned setpoint is refused.
    #[arg(long, value_name = "DIR")]
    resume: Option<PathBuf>,
    /// Check everything the run would open (plan, sensor, bench file, scene, camera
    /// directory) and print the defaults used, the setpoints with their stage
    /// coordinates, the estimated duration and the limit checks (the plan's travel
    /// box, force limits, the stage's travel limits); move nothing and open no device.
    #[arg(long)]
    dry_run: bool,
    /// With --dry-run: write every setpoint with its stage coordinates to this CSV
    /// (the printed table shows the first and last 20 of a long plan).
    #[arg(long, value_name = "FILE.csv", requires = "dry_run")]
    setpoints_csv: Option<PathBuf>,
    /// Camera calibration (camera.toml, from `tactbench calibrate`): the run's tracker
    /// maps pixels to the sensor frame with its per-layer scale and origin, principal
    /// point and distortion instead of the sensor file's [camera] mapping. Recorded in
    /// the manifest (path and text); a resume uses the recorded one (giving --camera
    /// with --resume must name a file with the same text).
    #[arg(long, value_name = "camera.toml")]
    camera: Option<PathBuf>,
    /// Elastomer build id recorded in the manifest (overrides the plan's build_id).
    #[arg(long, value_name = "ID")]
    build_id: Option<String>,
    /// At most N setpoints in this session (N >= 1): a new run measures the plan's
    /// first N (a short trial run); `--resume DIR --limit N` measures at most N more,
    /// the next ones not yet in the journal. The limit caps the session, not the run:
    /// a run stopped by it stays resumable to its full plan (`run --resume DIR`, with
    /// or without a new --limit). Each session is recorded in manifest.json
    /// (`sessions`: started_at, limit, setpoints_before, setpoints_after).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    limit: Option<u64>,
    /// Print where the time went at the end (device waits, tracking, solving, file
    /// writes, controller overhead per setpoint).
    #[arg(long)]
    timings: bool,
    /// Run with a draft sensor file (`sensor init`) whose placeholder values were
    /// never measured: its placeholders are printed at the start and the end; the
    /// forces are not measurements.
    #[arg(long)]
    allow_draft: bool,
    /// No progress bar; one plain line per setpoint on stderr instead (the default
    /// when stderr is not a terminal: nohup, CI, a pipe).
    #[arg(long)]
    no_progress: bool,
    /// Watch the run in a browser: serve the live view on ADDR (default
    /// 127.0.0.1:7878; port 0 = any free port) and print its URL on stderr. A
    /// non-loopback address turns on a token (in the URL). The run never waits for
    /// the view. Give ADDR after the plan (or as --serve=ADDR).
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = tactbench::live::DEFAULT_ADDR)]
    serve: Option<String>,
    /// With --serve: acceptance criteria (as `report --acceptance`) for the live
    /// view's provisional verdict.
    #[arg(long, value_name = "CRITERIA.toml", requires = "serve")]
    acceptance: Option<PathBuf>,
    /// Test seam: the first N writes into the run directory succeed, then K writes
    /// fail with "No space left on device" (`N`: every later write, a disk that stays
    /// full; `N:K`: K writes, then the disk has room again).
    #[arg(long, value_name = "N[:K]", hide = true, value_parser = parse_write_fault)]
    fail_writes_after: Option<runner::WriteFault>,
}

/// `N` or `N:K` for --fail-writes-after.
fn parse_write_fault(text: &str) -> Result<runner::WriteFault, String> {
    let num = |s: &str| {
        s.trim()
            .parse::<usize>()
            .map_err(|e| format!("{s:?} is not a whole number: {e}"))
    };
    Ok(match text.split_once(':') {
        Some((n, k)) => runner::WriteFault {
            failures: Some(num(k)?),
            ..runner::WriteFault::disk_full_after(num(n)?)
        },
        None => runner::WriteFault::disk_full_after(num(text)?),
    })
}

/// What the manifest says about the bench, to reopen it on resume. Relative paths
/// are taken from the directory the run started in (`bench.cwd`), so a run resumes
/// from any working directory.
fn bench_from_manifest(m: &Manifest) -> anyhow::Result<BenchConfig> {
    let cwd = m.bench["cwd"].as_str().map(std::path::Path::new);
    let resolve = |p: &str| match cwd {
        Some(d) if std::path::Path::new(p).is_relative() => d.join(p),
        _ => std::path::PathBuf::from(p),
    };
    if let Some(scene) = m.bench["sim"]["scene"].as_str() {
        if let Some(file) = m.bench["file"].as_str() {
            if file != scene && resolve(file).exists() {
                return Ok(BenchConfig::from_path(resolve(file))?);
            }
        }
        let scene = resolve(scene);
        if !scene.exists() {
            bail!(
                "the run's scene {} is gone; give --sim SCENE.toml (or --bench) to resume",
                scene.display()
            );
        }
        return Ok(BenchConfig::sim(&scene));
    }
    if let Some(file) = m.bench["file"].as_str() {
        return Ok(BenchConfig::from_path(resolve(file))?);
    }
    bail!("the manifest does not say which bench ran; give --bench or --sim")
}

/// Checks one preview frame of the camera (not one of the run's frames) for a blank
/// or saturated image inside the sensor's ROI, and for a greyscale image when a layer
/// needs colour.
fn check_camera_levels(
    camera: &mut dyn tactbench::device::Camera,
    sensor: &Sensor,
) -> anyhow::Result<()> {
    let frame = camera
        .preview()
        .context("cannot grab the camera's frame to check its exposure")?;
    let view = tactbench::vision::FrameView::rgb8(&frame.image);
    tactbench::vision::onboard::check_frame_levels(
        &view,
        sensor.camera.roi_px.as_ref(),
        std::path::Path::new("the camera's reference frame"),
    )
    .context("run refused before anything moved")?;
    // A greyscale camera or recording (widened to RGB by the camera driver) serves
    // dark and bright layers only.
    if view.is_achromatic() {
        let layers = sensor.layers.iter().map(|l| (l.name.as_str(), l.color));
        if let Some(e) = tactbench::vision::colour_layer(layers) {
            return Err(anyhow::Error::new(e)
                .context("the camera's reference frame is greyscale (R = G = B in every pixel)")
                .context("run refused before anything moved"));
        }
    }
    Ok(())
}

/// What a run starts from: the plan, the sensor file, the camera mapping and the
/// bench, from the command line or (resume) from the run's manifest.
struct Inputs {
    plan: Plan,
    plan_toml: String,
    sensor: Sensor,
    sensor_toml: String,
    /// The draft sensor file's warning, when --allow-draft let it run.
    draft: Option<String>,
    /// The camera calibration: (path, text).
    camera: Option<(String, String)>,
    bench: Option<BenchConfig>,
}

/// The manifest of the run --resume continues (none for a new run).
fn read_resume_manifest(a: &Args) -> anyhow::Result<Option<Manifest>> {
    let manifest =
        match &a.resume {
            Some(dir) => Some(Manifest::read(dir).with_context(|| {
                format!("cannot resume {}: no readable manifest", dir.display())
            })?),
            None => None,
        };
    if let Some(w) = manifest.as_ref().and_then(|m| m.write_failure.as_ref()) {
        eprintln!("note: an earlier session of this run was aborted by a failed write: {w}");
    }
    Ok(manifest)
}

/// The plan and its text: from the command line, or (resume) from the manifest.
fn read_plan(a: &Args, manifest: Option<&Manifest>) -> anyhow::Result<(Plan, String)> {
    Ok(match (&a.plan, manifest) {
        (Some(p), _) => {
            let text = std::fs::read_to_string(p)
                .with_context(|| format!("cannot read plan {}", p.display()))?;
            (Plan::from_toml_str(&text, p)?, text)
        }
        (None, Some(m)) => (
            Plan::from_toml_str(&m.plan_toml, &m.plan_path)?,
            m.plan_toml.clone(),
        ),
        (None, None) => {
            bail!("give a plan: tactbench run PLAN.toml --sim SCENE.toml --out DIR (see --help)")
        }
    })
}

/// The sensor file (the plan's, or the manifest's text on resume), its text, and its
/// draft warning when --allow-draft lets a draft run (a draft is refused otherwise).
fn read_sensor(
    a: &Args,
    plan: &Plan,
    manifest: Option<&Manifest>,
) -> anyhow::Result<(Sensor, String, Option<String>)> {
    let sensor_toml = match manifest {
        Some(m) => m.sensor_toml.clone(),
        None => std::fs::read_to_string(&plan.sensor_path).with_context(|| {
            format!(
                "cannot read the plan's sensor file {}",
                plan.sensor_path.display()
            )
        })?,
    };
    let sensor = Sensor::from_toml_str(&sensor_toml, &plan.sensor_path)?;
    let draft = match sensor.draft_warning(&plan.sensor_path) {
        Some(w) if a.allow_draft => {
            eprintln!("warning: {w}");
            Some(w)
        }
        _ => {
            sensor.refuse_draft(&plan.sensor_path)?;
            None
        }
    };
    Ok((sensor, sensor_toml, draft))
}

/// The camera calibration: from the command line (checked against the sensor now,
/// before anything is written), or on resume the one the run started with.
fn read_camera(
    a: &Args,
    manifest: Option<&Manifest>,
    sensor: &Sensor,
) -> anyhow::Result<Option<(String, String)>> {
    Ok(match (&a.camera, manifest) {
        (Some(p), m) => {
            let text = std::fs::read_to_string(p)
                .with_context(|| format!("cannot read camera calibration {}", p.display()))?;
            tactbench::vision::CameraCalibration::from_toml_str(&text, p, sensor)?;
            if let Some(m) = m {
                if m.camera_toml.as_deref() != Some(text.as_str()) {
                    bail!(
                        "--camera {}: the run was tracked with {}; resume without --camera (the recorded mapping is used)",
                        p.display(),
                        m.camera_path
                            .as_deref()
                            .map_or("the sensor file's [camera] mapping".to_string(), |c| {
                                format!("another calibration ({c})")
                            })
                    );
                }
            }
            Some((p.display().to_string(), text))
        }
        (None, Some(m)) => m.camera_path.clone().zip(m.camera_toml.clone()),
        (None, None) => None,
    })
}

/// Everything the run reads before it opens a device, in the order the errors are
/// reported: manifest, plan, sensor (draft), camera calibration, bench, and the
/// frames the run would write.
fn read_inputs(a: &Args) -> anyhow::Result<Inputs> {
    let manifest = read_resume_manifest(a)?;
    let (plan, plan_toml) = read_plan(a, manifest.as_ref())?;
    let (sensor, sensor_toml, draft) = read_sensor(a, &plan, manifest.as_ref())?;
    let camera = read_camera(a, manifest.as_ref(), &sensor)?;
    let bench = match (&a.bench, &a.sim, &manifest) {
        (Some(b), _, _) => Some(BenchConfig::from_path(b)?),
        (None, Some(s), _) => Some(BenchConfig::sim(s)),
        (None, None, Some(m)) => Some(bench_from_manifest(m)?),
        (None, None, None) => None,
    };
    // The frames the run writes, now that the sensor gives the image size.
    plan.check_frames_on_disk(&sensor)?;
    Ok(Inputs {
        plan,
        plan_toml,
        sensor,
        sensor_toml,
        draft,
        camera,
        bench,
    })
}

/// The live view (--serve) on the run directory, its URL printed on stderr. Bound
/// before anything is created or opened: a bad address is an error that leaves
/// nothing behind.
fn start_live_view(
    a: &Args,
    dir: &std::path::Path,
) -> anyhow::Result<Option<tactbench::live::LiveServer>> {
    let Some(addr) = &a.serve else {
        return Ok(None);
    };
    let (stop, signal) = stop_flags();
    let server = tactbench::live::LiveServer::start(
        std::slice::from_ref(&dir.to_path_buf()),
        &tactbench::live::ServeOptions {
            addr: addr.clone(),
            criteria: a.acceptance.clone(),
        },
        Some(tactbench::live::StopHandle { stop, signal }),
    )?;
    eprintln!(
        "live view: {}{}",
        server.url(),
        if server.url().contains("token=") {
            " (not a loopback address: requests need this token)"
        } else {
            ""
        }
    );
    Ok(Some(server))
}

/// A new run's directory: refused when it holds a run already, created, and locked
/// before anything else is written (the simulated bench's links live in it). On
/// resume the lock taken at the start is kept. Returns the lock (held until the run
/// returns, or the process dies).
fn lock_run_dir(
    dir: &std::path::Path,
    resume: bool,
    run_lock: Option<RunLock>,
) -> anyhow::Result<RunLock> {
    let mut run_lock = run_lock;
    if !resume {
        let journal = dir.join(tactbench::bench::journal::JOURNAL_FILE);
        if journal.exists() || dir.join(tactbench::bench::journal::MANIFEST_FILE).exists() {
            // Refused before anything in it is touched (the lock file included).
            let live = match tactbench::bench::lock::probe(dir) {
                Ok(tactbench::bench::lock::LockState::Held(h)) => {
                    format!(" (in progress: {h})")
                }
                _ => String::new(),
            };
            bail!(
                "{} already holds a run{live}: choose another --out, or continue it with --resume {}",
                dir.display(),
                dir.display()
            );
        }
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create run directory {}", dir.display()))?;
        // Before anything else is written (the simulated bench's links live in DIR).
        run_lock = Some(RunLock::acquire(dir, "run")?);
    }
    run_lock.context("cannot resume: no such run directory")
}

/// Opens the bench's devices and checks the camera's levels. A blank or saturated
/// camera (light off, lens cap, exposure) is refused before anything moves, as
/// `track`, `calibrate` and `sensor init` refuse such a reference. On failure a run
/// directory this session `created` is removed again: a failed start leaves nothing
/// behind.
fn open_bench(
    bench: &BenchConfig,
    plan: &Plan,
    sensor: &Sensor,
    dir: &std::path::Path,
    created: bool,
    run_lock: &RunLock,
) -> anyhow::Result<connect::Connected> {
    let sim_options = SimOptions {
        links: connect::default_links(dir),
        start_over_mm: Some(plan.approach_position_mm),
        ..SimOptions::default()
    };
    let mut c = match connect::connect(bench, &sim_options) {
        Ok(c) => c,
        Err(e) => {
            if created {
                let _ = std::fs::remove_dir(&sim_options.links);
                let _ = std::fs::remove_file(run_lock.path());
                let _ = std::fs::remove_dir(dir);
            }
            return Err(anyhow::Error::new(e).context("cannot open the bench"));
        }
    };
    for w in &c.warnings {
        eprintln!("warning: {w}");
    }
    if let Err(e) = check_camera_levels(c.camera.as_mut(), sensor) {
        if created {
            drop(c);
            let _ = std::fs::remove_dir_all(&sim_options.links);
            let _ = std::fs::remove_file(run_lock.path());
            let _ = std::fs::remove_dir(dir);
        }
        return Err(e);
    }
    Ok(c)
}

pub fn run(a: Args) -> anyhow::Result<ExitCode> {
    let limit = a.limit.map(|n| usize::try_from(n).unwrap_or(usize::MAX));
    // One writer per run directory: a resume locks before it reads or writes anything.
    let run_lock = match (&a.resume, a.dry_run) {
        (Some(dir), false) if dir.is_dir() => Some(RunLock::acquire(dir, "run --resume")?),
        _ => None,
    };
    let Inputs {
        plan,
        plan_toml,
        sensor,
        sensor_toml,
        draft,
        camera,
        bench,
    } = read_inputs(&a)?;

    if a.dry_run {
        return dry_run(&a, &plan, &sensor, bench.as_ref(), limit, draft.as_deref());
    }

    let bench = bench.context("give a bench: --bench bench.toml or --sim SCENE.toml")?;
    let (dir, resume) = match (&a.out, &a.resume) {
        (Some(d), None) => (d.clone(), false),
        (None, Some(d)) => (d.clone(), true),
        _ => bail!("give --out DIR for a new run or --resume DIR to continue one"),
    };
    let live = start_live_view(&a, &dir)?;
    // Created here (the simulated bench's links live in it), removed again if the
    // bench cannot be opened: a failed start leaves nothing behind.
    let created = !resume && !dir.exists();
    // Held until this function returns (or the process dies).
    let run_lock = lock_run_dir(&dir, resume, run_lock)?;

    let (stop, stop_signal) = install_stop_handlers()?;
    // A real stage's port is claimed as `tactbench stage` claims it, so `stage stop`
    // in another terminal reaches this run (SIGINT: stop, retract, interrupted). Best
    // effort: a held claim means the port is busy, which connecting reports.
    let _port_claim = match &bench.devices {
        tactbench::bench::config::BenchDevices::Hardware { stage, .. } => {
            tactbench::bench::lock::PortClaim::acquire(&stage.port, "run").ok()
        }
        tactbench::bench::config::BenchDevices::Sim(_) => None,
    };
    let mut c = open_bench(&bench, &plan, &sensor, &dir, created, &run_lock)?;
    let options = RunOptions {
        dir: dir.clone(),
        resume,
        build_id: a.build_id.clone(),
        plan_toml,
        sensor_toml,
        camera,
        bench: c.description.clone(),
        devices: c.identities.clone(),
        home: c.home,
        tare: c.tare,
        simulated: c.sim.is_some(),
        write_fault: a.fail_writes_after,
        limit,
        stop,
        stop_signal,
    };

    let progress = Progress {
        bar: progress_bar(&a),
        unit: plan.force_unit,
        run_dir: dir.display().to_string(),
        live: live.as_ref().and_then(|s| s.sender()),
    };
    let mut on_event = |e: &RunEvent| progress.event(e);
    let summary = {
        let mut devices = Devices {
            stage: c.stage.as_mut(),
            ft: c.ft.as_mut(),
            camera: c.camera.as_mut(),
        };
        runner::run(
            &plan,
            &sensor,
            &c.geometry,
            &mut devices,
            &options,
            &mut on_event,
        )?
    };
    if let Some(b) = &progress.bar {
        b.finish_and_clear();
    }
    if let Some(server) = live {
        // Viewers get the final state, then the view closes with the process.
        server.finish(Duration::from_secs(3));
    }
    // Drivers first, then the simulated bench they talk to.
    drop(c.stage);
    drop(c.ft);
    drop(c.camera);
    drop(c.sim.take());
    // The simulated bench removed its links; drop their (now empty) directory.
    let _ = std::fs::remove_dir(connect::default_links(&dir));

    if a.timings {
        print_timings(&summary.timings);
    }
    Ok(report_end(summary, &plan, &dir, draft.as_deref()))
}

/// A progress bar only on a terminal: indicatif hides itself (and the lines printed
/// through it) when stderr is not one, so nohup, CI and pipes get plain lines.
fn progress_bar(a: &Args) -> Option<ProgressBar> {
    let plain = a.no_progress || !std::io::stderr().is_terminal();
    if plain {
        return None;
    }
    let b = ProgressBar::with_draw_target(Some(0), ProgressDrawTarget::stderr());
    b.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} setpoints, ETA {eta} {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    b.enable_steady_tick(Duration::from_millis(200));
    Some(b)
}

/// Where the run's events go: the progress bar (or plain lines on stderr) and the
/// live view.
struct Progress {
    bar: Option<ProgressBar>,
    unit: ForceUnit,
    run_dir: String,
    live: Option<tactbench::live::server::EventSender>,
}

impl Progress {
    /// A line above the bar, or on stderr without one.
    fn log(&self, line: String) {
        match &self.bar {
            Some(b) => b.println(line),
            None => eprintln!("{line}"),
        }
    }

    fn event(&self, e: &RunEvent) {
        // The live view never makes the run wait: a bounded queue, dropped when full.
        if let Some(s) = &self.live {
            s.send(e);
        }
        let (bar, unit, run_dir) = (&self.bar, self.unit, &self.run_dir);
        let sym = unit.symbol();
        match e {
            RunEvent::Started {
                total,
                done,
                truncated_bytes,
            } => {
                if let Some(b) = bar {
                    b.set_length(*total as u64);
                    b.set_position(*done as u64);
                    b.reset_eta();
                }
                if *done > 0 {
                    self.log(format!(
                        "resuming {run_dir}: {done} of {total} setpoints already measured{}",
                        if *truncated_bytes > 0 {
                            format!(" (cut a torn journal line of {truncated_bytes} bytes)")
                        } else {
                            String::new()
                        }
                    ));
                } else {
                    self.log(format!("run {run_dir}: {total} setpoints"));
                }
            }
            RunEvent::Homing => self.log("homing the stage".into()),
            RunEvent::Tared { residual_n } => self.log(format!(
                "force sensor tared (|F| = {residual_n:.4} N after)"
            )),
            RunEvent::Reference {
                path,
                markers,
                missing,
            } => self.log(format!(
                "reference frame {path}: {markers} markers, {missing} missing"
            )),
            RunEvent::SetpointStarted { setpoint, .. } => {
                if let Some(b) = bar {
                    b.set_message(format!(
                        "#{} target {:.1} {sym}",
                        setpoint.index,
                        unit.from_newtons(setpoint.normal_n)
                    ));
                }
            }
            RunEvent::Contact { .. } => {}
            RunEvent::Retry {
                index,
                attempt,
                reason,
            } => self.log(format!(
                "retry {attempt}{}: {reason}",
                index
                    .map(|i| format!(" at setpoint {i}"))
                    .unwrap_or_default()
            )),
            RunEvent::Warning { index, message } => {
                self.log(format!("warning: setpoint {index}: {message}"))
            }
            RunEvent::SetpointMeasured {
                index,
                done,
                total,
                target_n,
                force_n,
                fsum_n,
                settled,
                elapsed_s,
                ..
            } => match bar {
                Some(b) => {
                    b.set_position(*done as u64);
                    b.set_message(format!(
                        "last fz {:.1} {sym}",
                        unit.from_newtons(force_n[2])
                    ));
                }
                None => eprintln!(
                    "{}",
                    setpoint_line(
                        *index, *done, *total, unit, target_n, force_n, fsum_n, *settled,
                        *elapsed_s
                    )
                ),
            },
            RunEvent::SafetyTrip { reason, .. } => self.log(format!("SAFETY STOP: {reason}")),
            RunEvent::Finished { .. } | RunEvent::Phase { .. } | RunEvent::Reading { .. } => {}
        }
    }
}

/// `--timings`: where the session's time went.
fn print_timings(t: &runner::Timings) {
    let n = t.setpoints.max(1) as f64;
    eprintln!(
        "timings over {} setpoints: wall {:.2} s; device waits {:.2} s; tracking {:.3} s; solving {:.3} s (+ {:.3} s one-off solver precompute); file writes {:.3} s; controller overhead {:.3} ms mean, {:.3} ms max per setpoint",
        t.setpoints,
        t.wall_s,
        t.device_s,
        t.track_s,
        t.solve_s,
        t.precompute_s,
        t.io_s,
        t.overhead_s / n * 1e3,
        t.max_overhead_s * 1e3
    );
}

/// The end of the run on stderr (a failed write, an unrecorded end, the draft
/// warning again, how it ended and how to continue) and its exit status: 0
/// completed, 4 interrupted, 3 aborted.
fn report_end(
    summary: runner::RunSummary,
    plan: &Plan,
    dir: &std::path::Path,
    draft: Option<&str>,
) -> ExitCode {
    if let Some(w) = &summary.write_failure {
        eprintln!(
            "write failure: {w}{}",
            if summary.manifest_error.is_none() {
                " (recorded in the manifest's write_failure)"
            } else {
                ""
            }
        );
    }
    if let Some(e) = &summary.manifest_error {
        eprintln!(
            "error: the end of the run could not be recorded: {e}; manifest.json still says \
             `running` (the journal holds every completed setpoint: free space, then \
             `tactbench run --resume {}`)",
            dir.display()
        );
    }
    if let Some(w) = draft {
        eprintln!("warning: {w}");
    }
    match summary.status {
        RunStatus::Completed => {
            eprintln!(
                "run completed: {} setpoints ({} this session) in {}",
                summary.done,
                summary.measured,
                dir.display()
            );
            let planned = plan.setpoint_count();
            if summary.done < planned {
                // A session stopped by its --limit: say how to measure the rest.
                eprintln!(
                    "  {} of the plan's {planned} setpoints measured (--limit); `tactbench run --resume {}` measures the rest (add --limit N for N more)",
                    summary.done,
                    dir.display()
                );
            }
            ExitCode::SUCCESS
        }
        RunStatus::Interrupted => {
            eprintln!(
                "run interrupted: {} of {} setpoints measured; continue with `tactbench run --resume {}`: {}",
                summary.done,
                summary.total,
                dir.display(),
                summary.reason.unwrap_or_default()
            );
            ExitCode::from(4)
        }
        RunStatus::Aborted | RunStatus::Running => {
            eprintln!(
                "run aborted after {} of {} setpoints: {}",
                summary.done,
                summary.total,
                summary.reason.unwrap_or_default()
            );
            ExitCode::from(3)
        }
    }
}

/// The plain log line of a measured setpoint (README "Run logs"):
/// `setpoint INDEX (DONE/TOTAL): target fx/fy/fz X/Y/Z UNIT, measured X/Y/Z UNIT,
/// F_sum z V UNIT, settled|not settled, T s`.
#[allow(clippy::too_many_arguments)]
fn setpoint_line(
    index: usize,
    done: usize,
    total: usize,
    unit: ForceUnit,
    target_n: &[f64; 3],
    force_n: &[f64; 3],
    fsum_n: &[f64; 3],
    settled: bool,
    elapsed_s: f64,
) -> String {
    let sym = unit.symbol();
    let v = |f: &[f64; 3]| {
        format!(
            "{:.3}/{:.3}/{:.3}",
            unit.from_newtons(f[0]),
            unit.from_newtons(f[1]),
            unit.from_newtons(f[2])
        )
    };
    // A failed row has no force sum (the warning before said why).
    let fsum = if fsum_n[2].is_finite() {
        format!("F_sum z {:.3} {sym}", unit.from_newtons(fsum_n[2]))
    } else {
        "no F_sum (failed row)".to_string()
    };
    format!(
        "setpoint {index} ({done}/{total}): target fx/fy/fz {} {sym}, measured {} {sym}, {fsum}, {}, {elapsed_s:.2} s",
        v(target_n),
        v(force_n),
        if settled { "settled" } else { "not settled" }
    )
}

/// Setpoints printed at each end of a long dry-run table.
const DRY_RUN_ROWS: usize = 20;

/// `writeln!` into the dry run's text (a `String`: cannot fail).
macro_rules! outln {
    ($out:expr, $($t:tt)*) => {{
        let _ = writeln!($out, $($t)*);
    }};
}

/// `run --dry-run`: checks every file the run would open (plan, sensor and bench file
/// are parsed before; here the scene and camera directories), prints the defaults the
/// plan relies on, the setpoints with their stage coordinates, the limit checks and
/// the estimated duration. Opens no device. Exit 0 when every check passes, 3 when a
/// limit check fails, 2 (an `Err`) when an input is missing or invalid.
fn dry_run(
    a: &Args,
    plan: &Plan,
    sensor: &Sensor,
    bench: Option<&BenchConfig>,
    limit: Option<usize>,
    draft: Option<&str>,
) -> anyhow::Result<ExitCode> {
    use std::io::Write as _;
    // Printed at once at the end: `--dry-run | head` is not an error.
    let mut out = String::new();
    let n = plan.setpoint_count().min(limit.unwrap_or(usize::MAX));
    let mut input_checks = Vec::new();
    if let Some(b) = bench {
        input_checks = runner::check_bench_inputs(b, 1 + n * plan.frames)
            .with_context(|| format!("bench {}", b.path.display()))?;
    }
    let geometry = bench.map(connect::geometry_of);
    let limits = bench.and_then(runner::stage_limits_of);
    let report = runner::dry_run(
        plan,
        limit,
        geometry.as_ref(),
        limits.as_ref().map(|l| &l.0),
    );
    dry_run_plan(&mut out, plan, n, report.setpoints.len());
    if let Some(b) = bench {
        outln!(out, "bench {}:", b.path.display());
        for (_, what) in &input_checks {
            outln!(out, "  {what}");
        }
        match &limits {
            Some((_, from)) => outln!(out, "  stage travel limits from {from}"),
            None => outln!(
                out,
                "  stage travel limits: not in the bench file ([stage] travel_min_mm / travel_max_mm); the run reads them from the controller"
            ),
        }
    }
    let table = SetpointTable::new(plan, &report);
    table.print(&mut out);
    if let Some(path) = &a.setpoints_csv {
        std::fs::write(path, table.csv())
            .with_context(|| format!("cannot write {}", path.display()))?;
        outln!(out, "every setpoint written to {}", path.display());
    }
    let ok = dry_run_checks(&mut out, plan, sensor, &input_checks, &report.checks, draft);
    outln!(
        out,
        "estimated duration: {:.0} s ({:.1} min); nothing moved, no device opened",
        report.estimated_s,
        report.estimated_s / 60.0
    );
    match std::io::stdout().lock().write_all(out.as_bytes()) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => {
            return Err(anyhow::Error::new(e).context("cannot write to stdout"))
        }
        _ => {}
    }
    Ok(if ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(3)
    })
}

/// The dry run's head: the plan (`shown` of its setpoints, `n` with --limit), the
/// caps it is checked against, its sweep and the defaults it relies on.
fn dry_run_plan(out: &mut String, plan: &Plan, n: usize, shown: usize) {
    outln!(
        out,
        "plan {} ({}, {} sweep): {} setpoints{}, {} samples and {} frame(s) each",
        plan.path.display(),
        plan.name,
        runner::sweep_name(plan),
        shown,
        if n < plan.setpoint_count() {
            format!(" (--limit; the plan has {})", plan.setpoint_count())
        } else {
            String::new()
        },
        plan.samples,
        plan.frames
    );
    outln!(
        out,
        "caps: {} of {} setpoints, {} of {} frames, an estimated {} of {:.0} h",
        plan.setpoint_count(),
        plan::MAX_SETPOINTS,
        plan.frame_count(),
        plan::MAX_FRAMES,
        duration_text(plan.estimate_duration_s(plan::DEFAULT_CLEARANCE_MM, None)),
        plan::MAX_DURATION_S / 3600.0
    );
    for line in plan.sweep_summary() {
        outln!(out, "{line}");
    }
    if plan.defaults.is_empty() {
        outln!(out, "defaults used: none (every optional key is given)");
    } else {
        outln!(out, "defaults used (keys the plan leaves out):");
        for (key, value) in &plan.defaults {
            outln!(out, "  {key} = {value}");
        }
    }
}

/// The dry run's setpoint table: the setpoints in the plan's force unit, with their
/// stage coordinates when the bench is known, and direction, position and hold time
/// for the plans that have them.
struct SetpointTable<'a> {
    report: &'a runner::DryRun,
    unit: ForceUnit,
    /// The stage coordinates are known (a bench was given).
    stage: bool,
    /// Direction, position and hold time columns ('-' = empty).
    repeat: bool,
}

impl<'a> SetpointTable<'a> {
    fn new(plan: &Plan, report: &'a runner::DryRun) -> Self {
        SetpointTable {
            report,
            unit: plan.force_unit,
            stage: !report.stage.is_empty(),
            repeat: plan.sweep_direction == plan::SweepDirection::UpDown
                || !plan.positions_mm.is_empty()
                || matches!(plan.sweep, plan::Sweep::Hold { .. }),
        }
    }

    fn header(&self) -> String {
        let fu = self.unit.symbol();
        format!(
            "{:>6} {:>5} {:>10} {:>10} {:>12} {:>12} {:>12} {:>10}{}{}",
            "index",
            "trial",
            "x_mm",
            "y_mm",
            format!("normal_{fu}"),
            format!("tx_{fu}"),
            format!("ty_{fu}"),
            "swept",
            if self.stage {
                format!(
                    " {:>10} {:>10} {:>11} {:>13}",
                    "stage_x_mm", "stage_y_mm", "stage_z_clr", "stage_z_limit"
                )
            } else {
                String::new()
            },
            if self.repeat {
                format!(" {:>9} {:>8} {:>9}", "direction", "position", "hold_t_s")
            } else {
                String::new()
            }
        )
    }

    fn row(&self, i: usize) -> String {
        let (sp, u) = (&self.report.setpoints[i], self.unit);
        let mut line = format!(
            "{:>6} {:>5} {:>10.4} {:>10.4} {:>12.4} {:>12.4} {:>12.4} {:>10.4}",
            sp.index,
            sp.trial,
            sp.position_mm[0] + sp.shift_mm[0],
            sp.position_mm[1] + sp.shift_mm[1],
            u.from_newtons(sp.normal_n),
            u.from_newtons(sp.tangential_n[0]),
            u.from_newtons(sp.tangential_n[1]),
            sp.swept_value
        );
        if let Some(t) = self.report.stage.get(i) {
            line += &format!(
                " {:>10.4} {:>10.4} {:>11.4} {:>13.4}",
                t.xy_mm[0], t.xy_mm[1], t.z_clear_mm, t.z_deepest_mm
            );
        }
        if self.repeat {
            let dash = || "-".to_string();
            line += &format!(
                " {:>9} {:>8} {:>9}",
                sp.direction.map_or_else(dash, |d| match d {
                    Direction::Up => "up".into(),
                    Direction::Down => "down".into(),
                }),
                sp.position.map_or_else(dash, |p| p.to_string()),
                sp.hold_t_s.map_or_else(dash, |t| format!("{t}"))
            );
        }
        line
    }

    /// The table, the first and last [`DRY_RUN_ROWS`] rows of a long one.
    fn print(&self, out: &mut String) {
        if self.stage {
            outln!(
                out,
                "stage coordinates (machine mm): x, y over the setpoint; z at the retract height (clearance) and at the deepest indentation the plan allows (safety.travel_max_mm[2])"
            );
        }
        outln!(out, "{}", self.header());
        let total = self.report.setpoints.len();
        if total <= 2 * DRY_RUN_ROWS {
            for i in 0..total {
                outln!(out, "{}", self.row(i));
            }
        } else {
            for i in 0..DRY_RUN_ROWS {
                outln!(out, "{}", self.row(i));
            }
            outln!(
                out,
                "{:>6} ({} setpoints not shown; --setpoints-csv FILE writes every one)",
                "...",
                total - 2 * DRY_RUN_ROWS
            );
            for i in total - DRY_RUN_ROWS..total {
                outln!(out, "{}", self.row(i));
            }
        }
    }

    /// Every row, comma-separated (--setpoints-csv).
    fn csv(&self) -> String {
        let mut text = self
            .header()
            .split_whitespace()
            .collect::<Vec<_>>()
            .join(",")
            + "\n";
        for i in 0..self.report.setpoints.len() {
            text += &self.row(i).split_whitespace().collect::<Vec<_>>().join(",");
            text.push('\n');
        }
        text
    }
}

/// The dry run's checks (bench inputs, the sensor file's plausibility, the sensor
/// area, the plan's limit checks, draft or measured), each `[ok]` or `[FAIL]`.
/// Returns whether every check passed.
fn dry_run_checks(
    out: &mut String,
    plan: &Plan,
    sensor: &Sensor,
    input_checks: &[(bool, String)],
    plan_checks: &[(bool, String)],
    draft: Option<&str>,
) -> bool {
    outln!(out, "checks:");
    let mut ok = true;
    let area = runner::sensor_area_checks(plan, sensor);
    // The sensor file's plausibility (ranges, force grid over the markers): checked
    // when it was loaded (a failure is an error, exit 2); shown here with the values.
    let sensor_checks: Vec<(bool, String)> = sensor
        .plausibility_lines()
        .into_iter()
        .map(|l| (true, format!("sensor {}: {l}", plan.sensor_path.display())))
        .collect();
    for (pass, what) in input_checks
        .iter()
        .chain(&sensor_checks)
        .chain(&area)
        .chain(plan_checks)
    {
        ok &= pass;
        outln!(out, "  [{}] {what}", if *pass { "ok" } else { "FAIL" });
    }
    match draft {
        Some(w) => outln!(out, "  [DRAFT] {w} (--allow-draft)"),
        None => outln!(
            out,
            "  [ok] sensor {}: measured (not a draft with placeholders)",
            plan.sensor_path.display()
        ),
    }
    ok
}

/// A duration for people: seconds, minutes or hours.
fn duration_text(s: f64) -> String {
    if s < 120.0 {
        format!("{s:.0} s")
    } else if s < 7200.0 {
        format!("{:.1} min", s / 60.0)
    } else {
        format!("{:.1} h", s / 3600.0)
    }
}
