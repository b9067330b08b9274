//! `tactbench stage`: drive an xyz stage (GRBL, Zaber ASCII or Marlin) over a serial port,
//! and the hidden `tactbench sim-serve-stage` helper that serves a stage
//! simulator on a pseudo-terminal (used by the CLI tests and for manual trials).

use std::io::{Read, Write};
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use clap::{Args as ClapArgs, Subcommand, ValueEnum};
use serde::Serialize;

use super::signals::{install_stop_handlers, stop_signal_time};
use tactbench::bench::config::{BenchConfig, StageConfig, StageKind};
use tactbench::bench::connect::{self, SimOptions};
use tactbench::bench::guard::{watch_move, MotionWatch, StopCause, Stopped, Watched};
use tactbench::bench::lock::{self, ClaimError, Holder, PortClaim};
use tactbench::device::fault::{FaultConfig, FaultKind, FaultTarget};
use tactbench::device::grbl::sim::{GrblSim, GrblSimConfig};
use tactbench::device::grbl::{self, Grbl, GrblConfig};
use tactbench::device::marlin::sim::{Boot, MarlinSim, MarlinSimConfig};
use tactbench::device::marlin::{self, Marlin, MarlinConfig};
use tactbench::device::pty::PtyServer;
use tactbench::device::zaber::sim::{ZaberSim, ZaberSimConfig};
use tactbench::device::zaber::{self, Zaber, ZaberAxis, ZaberConfig};
use tactbench::device::{ForceSensor, Stage, StageState};

/// Wire protocol of the stage controller.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Protocol {
    /// GRBL 1.1 (G-code; CNC-style controllers).
    Grbl,
    /// Zaber ASCII (motorised linear stages, one device or axis per stage axis).
    Zaber,
    /// Marlin (3D printers and small CNCs; line numbers and checksums, M400 + M114).
    Marlin,
}

/// Drive an xyz stage: status, unlock, home, position, move, jog.
///
/// Ctrl-C (SIGINT), SIGTERM or SIGHUP during `move`, `jog` or `home` stops the
/// stage (GRBL: jog cancel, or feed hold then reset; Marlin: M410 then M114; Zaber:
/// stop), prints where it stopped and exits 4. `stop` in another terminal signals the
/// process that holds the port. With `--bench bench.toml`, `move` and `jog` watch the
/// bench's force sensor and stop at its `[safety] max_force_n` (exit 3).
///
/// Positions are in mm in the controller's own frame: GRBL machine coordinates
/// (MPos; after homing GRBL's travel is negative, e.g. x in [-200, 0] mm), Zaber
/// device positions (microsteps × resolution), Marlin's logical position (from the
/// step counts of M114). Moves wait until the stage is idle (Marlin: M400, then
/// M114 checked against the target to the step).
///
/// Examples:
///   tactbench stage --port /dev/ttyUSB0 --protocol grbl status
///   tactbench stage --port /dev/ttyUSB0 --protocol grbl unlock
///   tactbench stage --port /dev/ttyUSB0 --protocol grbl move -10 -10 -2.5 --speed 5
///   tactbench stage --port /dev/ttyUSB0 --protocol zaber --zaber-devices 1,2,3 position --json
///   tactbench stage --port /dev/ttyUSB0 --protocol marlin --baud 250000 home
#[derive(Debug, ClapArgs)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// Serial port of the controller (see `tactbench ports`).
    #[arg(long, global = true, value_name = "PATH")]
    port: Option<String>,
    /// Bench file: the stage (`[stage]`, or the simulated bench of `[sim]`) instead of
    /// --port/--protocol, and the force sensor that `move` and `jog` watch against
    /// `[safety] max_force_n`.
    #[arg(long, global = true, value_name = "BENCH_TOML")]
    bench: Option<PathBuf>,
    /// Controller protocol.
    #[arg(long, global = true, value_enum)]
    protocol: Option<Protocol>,
    /// Baud rate [default: 115200 for all protocols; older Zaber devices use 9600,
    /// many Marlin printers 250000].
    #[arg(long, global = true, value_name = "N")]
    baud: Option<u32>,
    /// Print machine-readable JSON instead of text.
    #[arg(long, global = true)]
    json: bool,
    /// Speed of moves and jogs in mm/s [default: the controller's rapid rate for
    /// moves, 5 mm/s for jogs].
    #[arg(long, global = true, value_name = "MM_S")]
    speed: Option<f64>,
    /// Longest time to wait for a move or homing to finish, seconds.
    #[arg(long, global = true, value_name = "S", default_value_t = 120.0)]
    timeout: f64,
    /// Zaber: device addresses of the x, y, z axes (axis 1 of each device), or one
    /// address for a 3-axis device (axes 1, 2, 3).
    #[arg(long, global = true, value_name = "X,Y,Z", value_delimiter = ',', default_values_t = [1u8, 2, 3])]
    zaber_devices: Vec<u8>,
    /// Zaber: resolution in mm per microstep, one value for all axes or three
    /// (x,y,z) [default: 0.000047625 = 0.047625 µm, Zaber's common lead-screw
    /// stages; check your device's datasheet].
    #[arg(long, global = true, value_name = "MM", value_delimiter = ',')]
    zaber_mm_per_step: Vec<f64>,
    /// Zaber: send commands without LRC checksums.
    #[arg(long, global = true)]
    zaber_no_checksum: bool,
    /// Marlin: how long to wait for the boot banner after opening the port (the
    /// board resets when the port opens), seconds.
    #[arg(long, global = true, value_name = "S", default_value_t = 3.0)]
    marlin_banner_timeout: f64,
    /// Marlin: maximum feed rates x,y,z in mm/min, for firmware that does not report
    /// M203 (a faster move is refused).
    #[arg(long, global = true, value_name = "X,Y,Z", value_delimiter = ',')]
    marlin_max_feed: Vec<f64>,
    #[command(subcommand)]
    action: Action,
}

/// What to do.
#[derive(Debug, Subcommand)]
enum Action {
    /// Show the motion state and position without changing anything (GRBL: works
    /// in every state, also the raw state, firmware version, work offset and alarm;
    /// Zaber: warning flags per axis).
    Status,
    /// Clear an alarm and say what was done (GRBL: `$X`; a critical alarm, or a
    /// controller that answers nothing, first gets a soft reset 0x18; sleep: reset;
    /// check mode: `$C`. Zaber: `warnings clear`. Marlin: `M999` after a stop on
    /// errors; a halt by M112 needs a board reset). Does not establish a reference
    /// position: home does.
    Unlock,
    /// Resume motion paused by a feed hold or a closed safety door (GRBL `~`;
    /// Marlin `M108`, which ends a firmware wait for the user).
    Resume,
    /// Stop motion now (GRBL: feed hold, then a soft reset that discards the queued
    /// moves and keeps the position; jogs are cancelled; Zaber `stop`; Marlin `M410`
    /// quick stop, then M114 re-syncs the position).
    Stop,
    /// Run the homing cycle and wait for it (GRBL `$H` needs `$22=1`; Marlin `G28`).
    Home,
    /// Print the position in mm (`--json`: {"x_mm":…,"y_mm":…,"z_mm":…}).
    Position,
    /// Move to an absolute position X Y Z in mm and wait until idle
    /// (negative values are fine: `move -10 -5 -1`).
    #[command(allow_negative_numbers = true)]
    Move {
        /// Target x, mm.
        x: f64,
        /// Target y, mm.
        y: f64,
        /// Target z, mm.
        z: f64,
    },
    /// Move by DX DY DZ mm (GRBL `$J=` jog; Zaber `move rel`; Marlin: a G1 to the
    /// position + the step, checked like a move) and wait until idle.
    #[command(allow_negative_numbers = true)]
    Jog {
        /// Step in x, mm.
        dx: f64,
        /// Step in y, mm.
        dy: f64,
        /// Step in z, mm.
        dz: f64,
    },
}

/// The JSON of `position --json`: exactly these keys, in this order.
#[derive(Serialize)]
struct PositionJson {
    x_mm: f64,
    y_mm: f64,
    z_mm: f64,
}

#[derive(Serialize)]
struct StatusJson {
    state: &'static str,
    x_mm: f64,
    y_mm: f64,
    z_mm: f64,
    detail: String,
}

fn state_name(s: StageState) -> &'static str {
    match s {
        StageState::Idle => "idle",
        StageState::Moving => "moving",
        StageState::Held => "held",
        StageState::Homing => "homing",
        StageState::Alarm => "alarm",
    }
}

/// Default jog speed when `--speed` is not given, mm/s.
const DEFAULT_JOG_SPEED_MM_S: f64 = 5.0;

/// Validated connection options.
struct Conn {
    port: String,
    protocol: Protocol,
    baud: u32,
    /// The bench file's `[stage]` (or its simulated stage), with `--bench`.
    bench_stage: Option<StageConfig>,
}

fn validate(a: &Args, bench_stage: Option<&StageConfig>) -> anyhow::Result<Conn> {
    let (port, protocol, baud) = match bench_stage {
        Some(st) => {
            if a.port.is_some() || a.protocol.is_some() || a.baud.is_some() {
                bail!("give --bench or --port/--protocol/--baud, not both: the bench file names the stage");
            }
            let protocol = match st.protocol {
                StageKind::Grbl => Protocol::Grbl,
                StageKind::Zaber => Protocol::Zaber,
                StageKind::Marlin => Protocol::Marlin,
            };
            (st.port.clone(), protocol, st.baud)
        }
        None => {
            let port = a.port.clone().context(
                "missing --port PATH (list ports with `tactbench ports`) or --bench bench.toml",
            )?;
            let protocol = a.protocol.context("missing --protocol grbl|zaber|marlin")?;
            let baud = a.baud.unwrap_or(match protocol {
                Protocol::Grbl => grbl::DEFAULT_BAUD,
                Protocol::Zaber => zaber::DEFAULT_BAUD,
                Protocol::Marlin => marlin::DEFAULT_BAUD,
            });
            (port, protocol, baud)
        }
    };
    if !(a.timeout.is_finite() && a.timeout > 0.0) {
        bail!(
            "--timeout {} s must be a positive number of seconds",
            a.timeout
        );
    }
    if let Some(v) = a.speed {
        if !(v.is_finite() && v > 0.0) {
            bail!("--speed {v} mm/s must be a positive number");
        }
    }
    Ok(Conn {
        port,
        protocol,
        baud,
        bench_stage: bench_stage.cloned(),
    })
}

fn zaber_config(a: &Args, bench: Option<&StageConfig>) -> anyhow::Result<ZaberConfig> {
    if let Some(st) = bench {
        let mut c = ZaberConfig::single_axis_devices(st.zaber_devices, st.zaber_mm_per_step);
        c.checksums = !a.zaber_no_checksum;
        return Ok(c);
    }
    let res: [f64; 3] = match a.zaber_mm_per_step.as_slice() {
        [] => [zaber::DEFAULT_MM_PER_STEP; 3],
        [r] => [*r; 3],
        [x, y, z] => [*x, *y, *z],
        other => bail!(
            "--zaber-mm-per-step takes 1 or 3 values (x,y,z), got {}",
            other.len()
        ),
    };
    if let Some(bad) = res.iter().find(|r| !(r.is_finite() && **r > 0.0)) {
        bail!("--zaber-mm-per-step {bad} must be a positive resolution in mm per microstep");
    }
    let axes: [ZaberAxis; 3] = match a.zaber_devices.as_slice() {
        [d] => [1u8, 2, 3].map(|ax| ZaberAxis {
            device: *d,
            axis: ax,
            mm_per_step: res[usize::from(ax) - 1],
        }),
        [x, y, z] => [0usize, 1, 2].map(|i| ZaberAxis {
            device: [*x, *y, *z][i],
            axis: 1,
            mm_per_step: res[i],
        }),
        other => bail!(
            "--zaber-devices takes 1 address (a 3-axis device) or 3 (x,y,z), got {}",
            other.len()
        ),
    };
    if let Some(d) = axes.iter().find(|a| a.device == 0 || a.device > 99) {
        bail!("--zaber-devices: address {} is outside 1..=99", d.device);
    }
    let mut c = ZaberConfig::single_axis_devices([1, 2, 3], zaber::DEFAULT_MM_PER_STEP);
    c.axes = axes;
    c.checksums = !a.zaber_no_checksum;
    Ok(c)
}

fn marlin_config(a: &Args, bench: Option<&StageConfig>) -> anyhow::Result<MarlinConfig> {
    if !(a.marlin_banner_timeout.is_finite() && a.marlin_banner_timeout >= 0.0) {
        bail!(
            "--marlin-banner-timeout {} s must be a number of seconds >= 0",
            a.marlin_banner_timeout
        );
    }
    let max_feed_mm_min = match a.marlin_max_feed.as_slice() {
        [] => bench.and_then(|st| st.marlin_max_feed_mm_min),
        [x, y, z] => {
            if let Some(bad) = [x, y, z].iter().find(|v| !(v.is_finite() && ***v > 0.0)) {
                bail!("--marlin-max-feed {bad} mm/min must be a positive feed rate");
            }
            Some([*x, *y, *z])
        }
        other => bail!(
            "--marlin-max-feed takes 3 values (x,y,z mm/min), got {}",
            other.len()
        ),
    };
    Ok(MarlinConfig {
        banner_timeout: Duration::from_secs_f64(a.marlin_banner_timeout),
        max_feed_mm_min,
        ..MarlinConfig::default()
    })
}

/// The Marlin part of `status`: firmware, capabilities and limits read at connect.
fn marlin_detail<P: std::io::Read + std::io::Write>(m: &Marlin<P>) -> String {
    let i = m.info();
    let mut d = format!(
        "marlin {}; emergency parser {}",
        i.firmware
            .as_deref()
            .unwrap_or("(M115 gave no FIRMWARE_NAME)"),
        if i.emergency_parser { "yes" } else { "no" }
    );
    if let Some(s) = i.steps_per_mm {
        d.push_str(&format!("; steps/mm {} {} {}", s[0], s[1], s[2]));
    }
    if let Some(f) = i.max_feed_mm_min {
        d.push_str(&format!(
            "; max feed {:.0} {:.0} {:.0} mm/min",
            f[0], f[1], f[2]
        ));
    }
    match i.soft_endstops {
        Some(s) => d.push_str(&format!(
            "; soft endstops {} x {}..{} y {}..{} z {}..{} mm",
            if s.enabled { "on" } else { "off" },
            s.min_mm[0],
            s.max_mm[0],
            s.min_mm[1],
            s.max_mm[1],
            s.min_mm[2],
            s.max_mm[2]
        )),
        None => d.push_str("; soft endstops not reported"),
    }
    d
}

/// The stop handling of a command that moves: the signal flags, and with
/// `--bench` the force sensor and its limits.
struct Guard {
    stop: Arc<AtomicBool>,
    signal: Arc<AtomicI32>,
    force: Option<(Box<dyn ForceSensor>, [f64; 3])>,
    /// The bench file, for messages.
    bench: Option<PathBuf>,
    /// `home`: a second handle on the port to stop the homing cycle with, which the
    /// drivers run as one blocking command.
    interrupt: Option<HomeInterrupt>,
}

/// How a homing cycle is stopped: bytes written on a second handle of the port while
/// the driver waits for the cycle's end.
struct HomeInterrupt {
    port: Box<dyn serialport::SerialPort>,
    bytes: &'static [u8],
    /// What the bytes are, for the message.
    how: &'static str,
}

impl HomeInterrupt {
    /// The protocol's stop for a homing cycle: GRBL answers nothing but real-time
    /// bytes while homing, so its soft reset 0x18; Zaber `stop` to every device
    /// (`/0 0 stop`); Marlin `M112` (its firmware kills itself after an `M410`
    /// anyway, when the interrupted homing move found no endstop).
    fn new(port: &dyn serialport::SerialPort, protocol: Protocol) -> Option<HomeInterrupt> {
        let (bytes, how): (&'static [u8], &'static str) = match protocol {
            Protocol::Grbl => (&[0x18], "GRBL soft reset 0x18"),
            Protocol::Zaber => (b"/0 0 stop\n", "Zaber `/0 0 stop` to every device"),
            Protocol::Marlin => (b"M112\n", "Marlin M112 emergency stop"),
        };
        port.try_clone()
            .ok()
            .map(|port| HomeInterrupt { port, bytes, how })
    }
}

impl Guard {
    /// Fails (exit 4) when a stop signal arrived before the motion started.
    fn check_before_moving(&self) -> anyhow::Result<()> {
        if self.stop.load(Ordering::SeqCst) {
            bail!(Interrupted(format!(
                "{}: nothing was moved",
                tactbench::bench::journal::stop_cause(self.signal.load(Ordering::SeqCst))
            )));
        }
        Ok(())
    }
}

/// A stop by a signal: exit 4 after the message (see [`run`]'s exit codes).
#[derive(Debug)]
struct Interrupted(String);

impl std::fmt::Display for Interrupted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "stopped by {}", self.0)
    }
}

impl std::error::Error for Interrupted {}

/// Exit code of a move stopped by a signal (as `run`'s).
const EXIT_INTERRUPTED: u8 = 4;
/// Exit code of a move stopped by the force limit or a failed force reading (as
/// `run`'s abort).
const EXIT_FORCE_STOP: u8 = 3;

/// Runs `tactbench stage`.
pub fn run(a: Args) -> anyhow::Result<ExitCode> {
    match run_inner(a) {
        Err(e) if e.downcast_ref::<Interrupted>().is_some() => {
            eprintln!("error: {e}");
            Ok(ExitCode::from(EXIT_INTERRUPTED))
        }
        r => r,
    }
}

fn run_inner(a: Args) -> anyhow::Result<ExitCode> {
    let moves = matches!(
        a.action,
        Action::Move { .. } | Action::Jog { .. } | Action::Home
    );
    // Before anything opens: a signal from here on stops the motion instead of
    // killing the process with the controller executing its buffer.
    let (stop, signal) = if moves {
        install_stop_handlers()?
    } else {
        (
            Arc::new(AtomicBool::new(false)),
            Arc::new(AtomicI32::new(0)),
        )
    };
    let bench = a.bench.as_ref().map(BenchConfig::from_path).transpose()?;
    let links = std::env::temp_dir().join(format!("tactbench-stage-{}", std::process::id()));
    let opened = match &bench {
        Some(b) => Some(
            connect::open_for_stage(
                b,
                &SimOptions {
                    links: links.clone(),
                    ..SimOptions::default()
                },
            )
            .with_context(|| format!("opening the bench of {}", b.path.display()))?,
        ),
        None => None,
    };
    let conn = validate(&a, opened.as_ref().map(|o| &o.stage))?;
    let mut guard = Guard {
        stop,
        signal,
        force: None,
        bench: a.bench.clone(),
        interrupt: None,
    };
    let mut sim = None;
    if let (Some(b), Some(o)) = (&bench, opened) {
        for w in &o.warnings {
            eprintln!("warning: {w}");
        }
        if matches!(a.action, Action::Move { .. } | Action::Jog { .. }) {
            let limits = b.max_force_n.with_context(|| {
                format!(
                    "{} has no [safety] max_force_n: `stage --bench` watches the force sensor against it while moving (|fx|, |fy|, |fz| in N)",
                    b.path.display()
                )
            })?;
            guard.force = Some((o.ft, limits));
        }
        sim = o.sim;
    }
    let claim = match PortClaim::acquire(&conn.port, &command_name(&a.action)) {
        Ok(c) => Some(c),
        Err(ClaimError::Held { holder, .. }) if matches!(a.action, Action::Stop) => {
            stop_holder(&conn.port, &holder)?;
            None
        }
        Err(e @ ClaimError::Held { .. }) => return Err(e.into()),
        Err(ClaimError::Lock(e)) => {
            // Without the claim, a `stage stop` elsewhere cannot find this process:
            // say so, but drive the stage.
            eprintln!("warning: cannot claim {} for this process ({e}): `tactbench stage stop` in another terminal will not reach it; Ctrl-C here stops the motion", conn.port);
            None
        }
    };
    let claim = match claim {
        Some(c) => Some(c),
        // The holder released the port: claim it now to stop the stage ourselves.
        None if matches!(a.action, Action::Stop) => {
            PortClaim::acquire(&conn.port, "stage stop").ok()
        }
        None => None,
    };
    let r = drive(&a, &conn, &mut guard);
    drop(claim);
    drop(sim);
    if a.bench.is_some() {
        let _ = std::fs::remove_dir_all(&links);
    }
    r
}

/// `stage move`, `stage jog`, ...: what a holder is recorded as doing.
fn command_name(action: &Action) -> String {
    let name = match action {
        Action::Status => "status",
        Action::Unlock => "unlock",
        Action::Resume => "resume",
        Action::Stop => "stop",
        Action::Home => "home",
        Action::Position => "position",
        Action::Move { .. } => "move",
        Action::Jog { .. } => "jog",
    };
    format!("stage {name}")
}

/// How long `stage stop` waits for the process it signalled to release the port.
const HOLDER_STOP_WAIT: Duration = Duration::from_secs(15);

/// `stage stop` while another tactbench process holds the port: SIGINT to it (its
/// Ctrl-C: it stops the motion and exits), then wait until it has let the port go.
fn stop_holder(port: &str, holder: &Holder) -> anyhow::Result<()> {
    let pid = holder.pid.with_context(|| {
        format!("{port} is held by another tactbench process ({holder}) that has not recorded its PID yet: press Ctrl-C in its terminal, that is the stop")
    })?;
    let here = lock::hostname();
    if holder.host.as_deref().is_some_and(|h| h != here) {
        bail!("{port} is held by {holder}, not on this host ({here}): press Ctrl-C in its terminal, that is the stop");
    }
    let target = libc::pid_t::try_from(pid)
        .with_context(|| format!("{port}: holder PID {pid} is out of range"))?;
    // SAFETY: kill has no memory preconditions; a stale PID is ruled out by the
    // claim's lock, which only a live process holds.
    if unsafe { libc::kill(target, libc::SIGINT) } != 0 {
        bail!(
            "cannot signal {holder}, which holds {port}: {}; press Ctrl-C in its terminal, that is the stop",
            std::io::Error::last_os_error()
        );
    }
    eprintln!(
        "{port} is held by {holder}: sent it SIGINT (its Ctrl-C: it stops the stage and exits)"
    );
    let deadline = Instant::now() + HOLDER_STOP_WAIT;
    while lock::port_holder(port)?.is_some() {
        if Instant::now() > deadline {
            bail!(
                "{holder} still holds {port} {} s after SIGINT: press Ctrl-C in its terminal, or stop the controller by hand",
                HOLDER_STOP_WAIT.as_secs()
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Ok(())
}

/// Opens the controller and does the action.
fn drive(a: &Args, conn: &Conn, guard: &mut Guard) -> anyhow::Result<ExitCode> {
    drive_open(a, conn, guard).map_err(|e| {
        let busy = e
            .chain()
            .any(|c| c.to_string().contains("cannot open serial port"));
        if busy && matches!(a.action, Action::Stop) {
            e.context(format!(
                "no tactbench process has claimed {}: if another program holds the port, Ctrl-C in that program's terminal is the stop",
                conn.port
            ))
        } else {
            e
        }
    })
}

fn drive_open(a: &Args, conn: &Conn, guard: &mut Guard) -> anyhow::Result<ExitCode> {
    let travel = conn.bench_stage.as_ref().and_then(|s| s.travel);
    match conn.protocol {
        Protocol::Grbl => {
            let port = grbl::open_serial(&conn.port, conn.baud)?;
            if matches!(a.action, Action::Home) {
                guard.interrupt = HomeInterrupt::new(port.as_ref(), conn.protocol);
            }
            // Only `unlock` may reset a controller that answers nothing (a critical
            // alarm); `status` and the rest leave it as it is.
            let connect = if matches!(a.action, Action::Unlock) {
                Grbl::connect_resetting
            } else {
                Grbl::connect
            };
            let cfg = GrblConfig {
                limits: travel,
                ..GrblConfig::default()
            };
            let mut g = connect(port, cfg)
                .with_context(|| format!("connecting to GRBL on {}", conn.port))?;
            match a.action {
                Action::Jog { dx, dy, dz } => {
                    guard.check_before_moving()?;
                    g.jog([dx, dy, dz], a.speed.unwrap_or(DEFAULT_JOG_SPEED_MM_S))?;
                    return watched(&mut g, a, guard, format!("jog by {dx}, {dy}, {dz} mm"));
                }
                Action::Unlock => {
                    let r = g.unlock_report()?;
                    if a.json {
                        print_position(&mut g, true)?;
                    } else {
                        for step in &r.actions {
                            println!("{step}");
                        }
                        println!("unlocked; state: {}", state_name(g.state()?));
                    }
                    return Ok(ExitCode::SUCCESS);
                }
                Action::Resume => {
                    let s = g.resume()?;
                    if !a.json {
                        println!("resumed (`~`); state: {s}");
                    }
                    return Ok(ExitCode::SUCCESS);
                }
                _ => {}
            }
            let d = grbl_detail(&mut g)?;
            act(&mut g, a, d, guard)
        }
        Protocol::Zaber => {
            let cfg = zaber_config(a, conn.bench_stage.as_ref())?;
            let port = zaber::open_serial(&conn.port, conn.baud)?;
            if matches!(a.action, Action::Home) {
                guard.interrupt = HomeInterrupt::new(port.as_ref(), conn.protocol);
            }
            let mut z = Zaber::connect(port, cfg)
                .with_context(|| format!("connecting to Zaber devices on {}", conn.port))?;
            let w = z.warnings();
            let d = format!("zaber warnings x {} y {} z {}", w[0], w[1], w[2]);
            act(&mut z, a, d, guard)
        }
        Protocol::Marlin => {
            let mut cfg = marlin_config(a, conn.bench_stage.as_ref())?;
            cfg.limits = travel;
            let port = marlin::open_serial(&conn.port, conn.baud)?;
            if matches!(a.action, Action::Home) {
                guard.interrupt = HomeInterrupt::new(port.as_ref(), conn.protocol);
            }
            let mut m = Marlin::connect(port, cfg)
                .with_context(|| format!("connecting to Marlin on {}", conn.port))?;
            match a.action {
                Action::Jog { dx, dy, dz } => {
                    guard.check_before_moving()?;
                    m.jog([dx, dy, dz], a.speed.unwrap_or(DEFAULT_JOG_SPEED_MM_S))?;
                    return watched(&mut m, a, guard, format!("jog by {dx}, {dy}, {dz} mm"));
                }
                Action::Resume => {
                    m.resume()?;
                    if !a.json {
                        println!("resumed (`M108`); state: {}", state_name(m.state()?));
                    }
                    return Ok(ExitCode::SUCCESS);
                }
                _ => {}
            }
            let d = marlin_detail(&m);
            act(&mut m, a, d, guard)
        }
    }
}

/// Waits for a started move under the guard: the stop signals and, with `--bench`,
/// the force limits. Ended: the target is checked ([`Stage::wait_idle`]) and the
/// position printed. Stopped: [`report_stop`].
fn watched(
    stage: &mut dyn Stage,
    a: &Args,
    guard: &mut Guard,
    what: String,
) -> anyhow::Result<ExitCode> {
    let timeout = Duration::from_secs_f64(a.timeout);
    // Also the line a script (or a test) waits for before it may signal.
    eprintln!("{what}: under way; Ctrl-C stops the stage");
    let outcome = watch_move(
        stage,
        MotionWatch {
            stop: &guard.stop,
            stop_asked_ns: stop_signal_time(),
            force: guard
                .force
                .as_mut()
                .map(|(f, l)| (f.as_mut() as &mut dyn ForceSensor, *l)),
            timeout,
        },
    )
    .with_context(|| format!("watching the {what}"))?;
    match outcome {
        Watched::Ended => {
            stage.wait_idle(timeout)?;
            print_position(stage, a.json)?;
            Ok(ExitCode::SUCCESS)
        }
        Watched::Stopped(s) => report_stop(stage, a, guard, &what, *s),
    }
}

/// Says why and where a watched move stopped, leaves the controller usable (a stop
/// that left it in alarm is unlocked, or the alarm named), prints the position as a
/// finished move does, and returns the exit code: 4 for a signal, 3 for the force.
fn report_stop(
    stage: &mut dyn Stage,
    a: &Args,
    guard: &Guard,
    what: &str,
    s: Stopped,
) -> anyhow::Result<ExitCode> {
    let at = match &s.position {
        Ok(p) => format!(
            "at x = {:.4} mm  y = {:.4} mm  z = {:.4} mm",
            p[0], p[1], p[2]
        ),
        Err(e) => format!("at an unknown position ({e})"),
    };
    let mut notes = Vec::new();
    if let Some(e) = &s.stop_error {
        notes.push(format!("the stop command failed: {e}"));
    }
    match &s.state {
        Ok(StageState::Alarm) => match stage.unlock() {
            Ok(()) => notes.push(format!(
                "the stop left the controller in alarm: unlocked; state: {}",
                stage
                    .state()
                    .map_or_else(|e| e.to_string(), |v| state_name(v).to_string())
            )),
            Err(e) => notes.push(format!("the controller is in alarm after the stop: {e}")),
        },
        Ok(v) => notes.push(format!("state: {}", state_name(*v))),
        Err(e) => notes.push(format!("state unknown: {e}")),
    }
    let ms = s.latency.as_secs_f64() * 1e3;
    let (message, code) = match &s.cause {
        StopCause::Requested => (
            format!(
                "stopped by {}: the {what} was abandoned; the stage stood still {ms:.1} ms after the signal, {at}",
                tactbench::bench::journal::stop_cause(guard.signal.load(Ordering::SeqCst))
            ),
            EXIT_INTERRUPTED,
        ),
        StopCause::ForceLimit(trip) => (
            format!(
                "stopped at the force limit of {}: {trip} ([safety] max_force_n); the stage stood still {ms:.1} ms after the reading, {at}",
                guard.bench.as_ref().map_or_else(|| "the bench".into(), |p| p.display().to_string())
            ),
            EXIT_FORCE_STOP,
        ),
        StopCause::ForceUnread(e) => (
            format!(
                "stopped: the force sensor gave no reading while moving ({e}); the stage stood still {ms:.1} ms later, {at}"
            ),
            EXIT_FORCE_STOP,
        ),
        StopCause::Timeout(t) => (
            format!(
                "stopped: the {what} did not end within --timeout {:.1} s; {at}",
                t.as_secs_f64()
            ),
            2,
        ),
    };
    eprintln!("error: {message}; {}", notes.join("; "));
    if let Ok(p) = s.position {
        print_xyz(p, a.json)?;
    }
    Ok(ExitCode::from(code))
}

/// The GRBL part of `status`: raw state, firmware version, alarm, work offset and
/// the last message, from what was read at connect and one status report.
fn grbl_detail<P: std::io::Read + std::io::Write>(g: &mut Grbl<P>) -> anyhow::Result<String> {
    let s = g.status()?;
    let mut d = format!(
        "grbl {}; state {}",
        g.version()
            .unwrap_or("(version unknown: `$I` is answered only when idle or in alarm)"),
        s.state.map_or_else(|| "?".to_string(), |v| v.to_string())
    );
    if let Some(code) = g.alarm() {
        if code == 0 {
            d.push_str("; alarm (raised before this connection)");
        } else {
            d.push_str(&format!(
                "; ALARM:{code} ({})",
                grbl::codec::alarm_text(code)
            ));
        }
    }
    if let Some(w) = g.wco_mm() {
        d.push_str(&format!(
            "; work offset (WCO) {:.3}, {:.3}, {:.3} mm",
            w[0], w[1], w[2]
        ));
    }
    if let Some(m) = g.last_message() {
        d.push_str(&format!("; last message: {m}"));
    }
    Ok(d)
}

/// Runs the homing cycle; a stop signal meanwhile writes the protocol's interrupt
/// ([`HomeInterrupt`]) on the port's second handle, which ends the driver's wait.
fn home_interruptible(
    stage: &mut dyn Stage,
    guard: &mut Guard,
) -> tactbench::device::DeviceResult<()> {
    eprintln!("homing: under way; Ctrl-C stops the stage");
    let Some(interrupt) = guard.interrupt.as_mut() else {
        return stage.home();
    };
    let done = AtomicBool::new(false);
    let stop = &guard.stop;
    std::thread::scope(|scope| {
        scope.spawn(|| {
            while !done.load(Ordering::SeqCst) {
                if stop.load(Ordering::SeqCst) {
                    let _ = interrupt.port.write_all(interrupt.bytes);
                    let _ = interrupt.port.flush();
                    return;
                }
                std::thread::sleep(tactbench::bench::guard::FLAG_POLL);
            }
        });
        let r = stage.home();
        done.store(true, Ordering::SeqCst);
        r
    })
}

/// A homing cycle a signal stopped: what was sent, how the cycle ended, the state
/// and position the controller now reports (the reference is lost: home again).
fn report_home_stop(
    stage: &mut dyn Stage,
    a: &Args,
    guard: &Guard,
    home_error: Option<tactbench::device::DeviceError>,
) -> anyhow::Result<ExitCode> {
    let sent = guard
        .interrupt
        .as_ref()
        .map_or("nothing (no second handle on the port)", |i| i.how);
    let ended = match &home_error {
        Some(e) => format!("the cycle ended with: {e}"),
        None => "the controller went idle (the homing wait returned)".to_string(),
    };
    let state = stage
        .state()
        .map_or_else(|e| format!("unknown ({e})"), |s| state_name(s).to_string());
    let position = stage.position();
    let at = match &position {
        Ok(p) => format!("x = {:.4} mm  y = {:.4} mm  z = {:.4} mm", p[0], p[1], p[2]),
        Err(e) => format!("unknown ({e})"),
    };
    eprintln!(
        "error: homing stopped by {}: sent {sent}; {ended}; state: {state}; position: {at}; the reference position is not established: run `home` again",
        tactbench::bench::journal::stop_cause(guard.signal.load(Ordering::SeqCst))
    );
    if let Ok(p) = position {
        print_xyz(p, a.json)?;
    }
    Ok(ExitCode::from(EXIT_INTERRUPTED))
}

fn print_position(stage: &mut dyn Stage, json: bool) -> anyhow::Result<()> {
    let p = stage.position()?;
    print_xyz(p, json)
}

fn print_xyz(p: [f64; 3], json: bool) -> anyhow::Result<()> {
    if json {
        let j = PositionJson {
            x_mm: p[0],
            y_mm: p[1],
            z_mm: p[2],
        };
        println!("{}", serde_json::to_string(&j)?);
    } else {
        println!("x = {:.4} mm  y = {:.4} mm  z = {:.4} mm", p[0], p[1], p[2]);
    }
    Ok(())
}

fn act(
    stage: &mut dyn Stage,
    a: &Args,
    detail: String,
    guard: &mut Guard,
) -> anyhow::Result<ExitCode> {
    match a.action {
        Action::Status => {
            let s = stage.state()?;
            let p = stage.position()?;
            if a.json {
                let j = StatusJson {
                    state: state_name(s),
                    x_mm: p[0],
                    y_mm: p[1],
                    z_mm: p[2],
                    detail,
                };
                println!("{}", serde_json::to_string(&j)?);
            } else {
                println!("state: {}", state_name(s));
                println!(
                    "position: x = {:.4} mm  y = {:.4} mm  z = {:.4} mm",
                    p[0], p[1], p[2]
                );
                println!("{detail}");
                match s {
                    StageState::Alarm => println!("hint: `home` establishes the reference position (needed after power-up); `unlock` clears an alarm or warning flags"),
                    StageState::Held => println!("hint: motion is paused: `resume` continues it (GRBL `~`), `stop` aborts it"),
                    _ => {}
                }
            }
        }
        Action::Unlock => {
            stage.unlock()?;
            if !a.json {
                println!("unlocked; state: {}", state_name(stage.state()?));
            } else {
                print_position(stage, true)?;
            }
        }
        Action::Home => {
            guard.check_before_moving()?;
            let r = home_interruptible(stage, guard);
            if guard.stop.load(Ordering::SeqCst) {
                return report_home_stop(stage, a, guard, r.err());
            }
            r?;
            print_position(stage, a.json)?;
        }
        Action::Position => print_position(stage, a.json)?,
        Action::Resume => bail!("resume is a GRBL command (`~`); Zaber stages do not hold"),
        Action::Stop => {
            stage.stop()?;
            if !a.json {
                println!("stopped; state: {}", state_name(stage.state()?));
            } else {
                print_position(stage, true)?;
            }
        }
        Action::Move { x, y, z } => {
            guard.check_before_moving()?;
            stage.move_to([x, y, z], a.speed)?;
            return watched(stage, a, guard, format!("move to {x}, {y}, {z} mm"));
        }
        Action::Jog { dx, dy, dz } => {
            guard.check_before_moving()?;
            stage.move_by([dx, dy, dz], a.speed)?;
            return watched(stage, a, guard, format!("jog by {dx}, {dy}, {dz} mm"));
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Serve a stage simulator on a pseudo-terminal until stdin closes (hidden helper
/// for tests and manual trials: `tactbench sim-serve-stage --protocol grbl --link /tmp/grbl`).
#[derive(Debug, ClapArgs)]
pub struct ServeArgs {
    /// Protocol to simulate.
    #[arg(long, value_enum)]
    protocol: Protocol,
    /// Create this symlink to the pseudo-terminal's slave.
    #[arg(long, value_name = "PATH")]
    link: PathBuf,
    /// GRBL: homing and soft limits on ($22=1, $20=1, travel 100×100×50 mm),
    /// starting in alarm as at power-up. Marlin: starts unhomed and refuses moves
    /// before `G28` (NO_MOTION_BEFORE_HOMING).
    #[arg(long)]
    homing: bool,
    /// Marlin: how the board boots (banner; silent: never answers; noise: prints
    /// garbage as at a wrong baud rate).
    #[arg(long, value_enum, default_value = "banner")]
    marlin_boot: BootArg,
    /// Inject one fault of this kind.
    #[arg(long, value_enum)]
    fault: Option<FaultArg>,
    /// Which replies the fault may hit.
    #[arg(long, value_enum, default_value = "any")]
    fault_target: TargetArg,
    /// Eligible replies passed untouched before the fault.
    #[arg(long, default_value_t = 0)]
    fault_skip: u32,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum BootArg {
    Banner,
    Silent,
    Noise,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum FaultArg {
    /// Marlin: the received line arrives corrupted (checksum error, `Resend:`).
    Checksum,
    Late,
    DroppedByte,
    Garbled,
    Unsolicited,
    Reset,
    Limit,
    Disconnect,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum TargetArg {
    Any,
    Queries,
    Commands,
}

/// Runs the hidden `sim-serve-stage` helper.
pub fn serve(a: ServeArgs) -> anyhow::Result<ExitCode> {
    let checksum = matches!(a.fault, Some(FaultArg::Checksum));
    if checksum && !matches!(a.protocol, Protocol::Marlin) {
        bail!("--fault checksum is a Marlin fault (a corrupted line answered by `Resend:`)");
    }
    let faults = a.fault.map(|f| {
        let kind = match f {
            FaultArg::Checksum => FaultKind::Garbled,
            FaultArg::Late => FaultKind::LateReply,
            FaultArg::DroppedByte => FaultKind::DroppedByte,
            FaultArg::Garbled => FaultKind::Garbled,
            FaultArg::Unsolicited => FaultKind::Unsolicited,
            FaultArg::Reset => FaultKind::DeviceReset,
            FaultArg::Limit => FaultKind::LimitTrip,
            FaultArg::Disconnect => FaultKind::Disconnect,
        };
        let target = match a.fault_target {
            TargetArg::Any => FaultTarget::Any,
            TargetArg::Queries => FaultTarget::Queries,
            TargetArg::Commands => FaultTarget::Commands,
        };
        FaultConfig::once(kind, target, a.fault_skip)
    });
    match a.protocol {
        Protocol::Grbl => {
            let mut cfg = if a.homing {
                GrblSimConfig::homing_bench()
            } else {
                GrblSimConfig::default()
            };
            cfg.faults = faults;
            let server = PtyServer::spawn(GrblSim::new(cfg), Some(&a.link))?;
            wait_for_stdin_eof(&server.path().display().to_string(), || {
                server.is_finished()
            });
        }
        Protocol::Marlin => {
            let mut cfg = MarlinSimConfig {
                boot: match a.marlin_boot {
                    BootArg::Banner => Boot::Banner,
                    BootArg::Silent => Boot::Silent,
                    BootArg::Noise => Boot::Noise,
                },
                ..MarlinSimConfig::default()
            };
            if a.homing {
                cfg.homed = false;
            }
            if checksum {
                cfg.checksum_faults = faults;
            } else {
                cfg.faults = faults;
            }
            let server = PtyServer::spawn(MarlinSim::new(cfg), Some(&a.link))?;
            wait_for_stdin_eof(&server.path().display().to_string(), || {
                server.is_finished()
            });
        }
        Protocol::Zaber => {
            // 1_000_000 steps = 47.6 mm at the default resolution.
            let mut cfg = ZaberSimConfig::three_single_axis(1_000_000);
            cfg.faults = faults;
            let server = PtyServer::spawn(ZaberSim::new(cfg), Some(&a.link))?;
            wait_for_stdin_eof(&server.path().display().to_string(), || {
                server.is_finished()
            });
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn wait_for_stdin_eof(path: &str, finished: impl Fn() -> bool) {
    println!("serving on {path}; close stdin to stop");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut sink = Vec::new();
        let _ = std::io::stdin().read_to_end(&mut sink);
        let _ = tx.send(());
    });
    while rx.recv_timeout(Duration::from_millis(50)).is_err() {
        if finished() {
            break;
        }
    }
}
