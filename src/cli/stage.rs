//! `tactbench stage`: drive an xyz stage (GRBL, Zaber ASCII or Marlin) over a serial port,
//! and the hidden `tactbench sim-serve-stage` helper that serves a stage
//! simulator on a pseudo-terminal (used by the CLI tests and for manual trials).

use std::io::Read;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{bail, Context};
use clap::{Args as ClapArgs, Subcommand, ValueEnum};
use serde::Serialize;

use tactbench::device::fault::{FaultConfig, FaultKind, FaultTarget};
use tactbench::device::grbl::sim::{GrblSim, GrblSimConfig};
use tactbench::device::grbl::{self, Grbl, GrblConfig};
use tactbench::device::marlin::sim::{Boot, MarlinSim, MarlinSimConfig};
use tactbench::device::marlin::{self, Marlin, MarlinConfig};
use tactbench::device::pty::PtyServer;
use tactbench::device::zaber::sim::{ZaberSim, ZaberSimConfig};
use tactbench::device::zaber::{self, Zaber, ZaberAxis, ZaberConfig};
use tactbench::device::{Stage, StageState};

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
}

fn validate(a: &Args) -> anyhow::Result<Conn> {
    let port = a
        .port
        .clone()
        .context("missing --port PATH (list ports with `tactbench ports`)")?;
    let protocol = a.protocol.context("missing --protocol grbl|zaber|marlin")?;
    let baud = a.baud.unwrap_or(match protocol {
        Protocol::Grbl => grbl::DEFAULT_BAUD,
        Protocol::Zaber => zaber::DEFAULT_BAUD,
        Protocol::Marlin => marlin::DEFAULT_BAUD,
    });
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
    })
}

fn zaber_config(a: &Args) -> anyhow::Result<ZaberConfig> {
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

fn marlin_config(a: &Args) -> anyhow::Result<MarlinConfig> {
    if !(a.marlin_banner_timeout.is_finite() && a.marlin_banner_timeout >= 0.0) {
        bail!(
            "--marlin-banner-timeout {} s must be a number of seconds >= 0",
            a.marlin_banner_timeout
        );
    }
    let max_feed_mm_min = match a.marlin_max_feed.as_slice() {
        [] => None,
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

/// Runs `tactbench stage`.
pub fn run(a: Args) -> anyhow::Result<ExitCode> {
    let conn = validate(&a)?;
    match conn.protocol {
        Protocol::Grbl => {
            let port = grbl::open_serial(&conn.port, conn.baud)?;
            // Only `unlock` may reset a controller that answers nothing (a critical
            // alarm); `status` and the rest leave it as it is.
            let connect = if matches!(a.action, Action::Unlock) {
                Grbl::connect_resetting
            } else {
                Grbl::connect
            };
            let mut g = connect(port, GrblConfig::default())
                .with_context(|| format!("connecting to GRBL on {}", conn.port))?;
            match a.action {
                Action::Jog { dx, dy, dz } => {
                    g.jog([dx, dy, dz], a.speed.unwrap_or(DEFAULT_JOG_SPEED_MM_S))?;
                    g.wait_idle(Duration::from_secs_f64(a.timeout))?;
                    print_position(&mut g, a.json)?;
                    return Ok(ExitCode::SUCCESS);
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
            act(&mut g, &a, d)
        }
        Protocol::Zaber => {
            let cfg = zaber_config(&a)?;
            let port = zaber::open_serial(&conn.port, conn.baud)?;
            let mut z = Zaber::connect(port, cfg)
                .with_context(|| format!("connecting to Zaber devices on {}", conn.port))?;
            let w = z.warnings();
            let d = format!("zaber warnings x {} y {} z {}", w[0], w[1], w[2]);
            act(&mut z, &a, d)
        }
        Protocol::Marlin => {
            let cfg = marlin_config(&a)?;
            let port = marlin::open_serial(&conn.port, conn.baud)?;
            let mut m = Marlin::connect(port, cfg)
                .with_context(|| format!("connecting to Marlin on {}", conn.port))?;
            match a.action {
                Action::Jog { dx, dy, dz } => {
                    m.jog([dx, dy, dz], a.speed.unwrap_or(DEFAULT_JOG_SPEED_MM_S))?;
                    m.wait_idle(Duration::from_secs_f64(a.timeout))?;
                    print_position(&mut m, a.json)?;
                    return Ok(ExitCode::SUCCESS);
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
            act(&mut m, &a, d)
        }
    }
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

fn print_position(stage: &mut dyn Stage, json: bool) -> anyhow::Result<()> {
    let p = stage.position()?;
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

fn act(stage: &mut dyn Stage, a: &Args, detail: String) -> anyhow::Result<ExitCode> {
    let timeout = Duration::from_secs_f64(a.timeout);
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
            stage.home()?;
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
            stage.move_to([x, y, z], a.speed)?;
            stage.wait_idle(timeout)?;
            print_position(stage, a.json)?;
        }
        Action::Jog { dx, dy, dz } => {
            stage.move_by([dx, dy, dz], a.speed)?;
            stage.wait_idle(timeout)?;
            print_position(stage, a.json)?;
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
