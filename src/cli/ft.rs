//! `tactbench ft`: read, tare and identify a 6-axis force/torque sensor (WACOH DynPick
//! or Robotiq FT 300) on a serial port; the hidden `sim-serve-ft` command serves a
//! simulated sensor on a pseudo-terminal for tests and dry runs.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{bail, Context};
use clap::{Args as ClapArgs, Subcommand, ValueEnum};
use serde::Serialize;

use tactbench::device::dynpick::{DynPick, DynPickSim, DynPickSimConfig};
use tactbench::device::ft300::{Ft300, Ft300Sim, Ft300SimConfig};
use tactbench::device::ft_common::{
    no_faults, open_serial, FaultConfig, FaultKind, FaultTarget, SharedWrench,
};
use tactbench::device::pty::{PtyServer, Simulator};
use tactbench::device::{ForceSensor, Wrench};

/// Force/torque sensor commands.
#[derive(ClapArgs)]
pub struct Args {
    /// Serial port of the sensor (e.g. /dev/ttyUSB0).
    #[arg(long, global = true)]
    port: Option<String>,
    /// Wire protocol.
    #[arg(long, value_enum, global = true)]
    protocol: Option<Protocol>,
    #[command(subcommand)]
    action: Action,
}

/// `tactbench sim-serve-ft`: serve a simulated sensor on a pseudo-terminal until killed
/// (tests, dry runs).
#[derive(ClapArgs)]
pub struct ServeArgs {
    /// Wire protocol to simulate.
    #[arg(long, value_enum)]
    protocol: Protocol,
    /// Symlink to create pointing at the pseudo-terminal.
    #[arg(long)]
    link: PathBuf,
    /// Constant load: Fx,Fy,Fz (N),Mx,My,Mz (N·m).
    #[arg(long, default_value = "0,0,0,0,0,0", allow_hyphen_values = true)]
    wrench: String,
    /// Stop after this many seconds (default: serve until killed).
    #[arg(long)]
    duration_s: Option<f64>,
    /// Inject one fault of this kind (as `sim-serve-stage --fault`).
    #[arg(long, value_enum)]
    fault: Option<FaultArg>,
    /// Replies passed untouched before the fault.
    #[arg(long, default_value_t = 0)]
    fault_skip: u32,
    /// The sensor is already streaming when the host connects (DynPick: continuous
    /// output `S`; FT 300: the 100 Hz stream), as left by an earlier program.
    #[arg(long)]
    streaming: bool,
    /// FT 300: the Modbus echo of the stream-start write is lost (the stream starts).
    #[arg(long)]
    drop_stream_echo: bool,
    /// DynPick: the first N tare commands (`O`) do nothing.
    #[arg(long, default_value_t = 0)]
    tare_ignored: u32,
}

/// Fault kinds a force-sensor simulator can inject.
#[derive(Debug, Clone, Copy, ValueEnum)]
enum FaultArg {
    Late,
    DroppedByte,
    Garbled,
    Unsolicited,
    Reset,
    Disconnect,
}

/// Supported sensors.
#[derive(Clone, Copy, ValueEnum, PartialEq, Eq, Debug)]
enum Protocol {
    /// WACOH DynPick (921600 baud, ASCII records).
    Dynpick,
    /// Robotiq FT 300 (19200 baud, Modbus RTU + stream).
    Ft300,
}

impl Protocol {
    fn name(self) -> &'static str {
        match self {
            Protocol::Dynpick => "dynpick",
            Protocol::Ft300 => "ft300",
        }
    }
}

#[derive(Subcommand)]
enum Action {
    /// Read the wrench: Fx Fy Fz in N, Mx My Mz in N·m.
    Read {
        /// Number of samples to read and print; the mean is printed when N > 1.
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
        samples: u32,
        /// Zero the sensor before reading (FT 300: software offset of this run).
        #[arg(long)]
        tare: bool,
        /// FT 300: use the 100 Hz stream instead of polled Modbus reads.
        #[arg(long)]
        stream: bool,
        /// Machine-readable output (one JSON object).
        #[arg(long)]
        json: bool,
    },
    /// Zero the sensor's offset at the current load (DynPick only: the FT 300's tare
    /// is a software offset that lives in one run; use `read --tare`).
    Tare,
    /// Firmware, serial number, sensitivities.
    Info {
        /// Machine-readable output.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Serialize)]
struct WrenchJson {
    fx_n: f64,
    fy_n: f64,
    fz_n: f64,
    mx_nm: f64,
    my_nm: f64,
    mz_nm: f64,
}

impl From<Wrench> for WrenchJson {
    fn from(w: Wrench) -> Self {
        WrenchJson {
            fx_n: w.force_n[0],
            fy_n: w.force_n[1],
            fz_n: w.force_n[2],
            mx_nm: w.torque_nm[0],
            my_nm: w.torque_nm[1],
            mz_nm: w.torque_nm[2],
        }
    }
}

fn show(w: &Wrench) -> String {
    format!(
        "Fx {:+9.3} N  Fy {:+9.3} N  Fz {:+9.3} N  Mx {:+8.4} N·m  My {:+8.4} N·m  Mz {:+8.4} N·m",
        w.force_n[0], w.force_n[1], w.force_n[2], w.torque_nm[0], w.torque_nm[1], w.torque_nm[2]
    )
}

/// Runs `tactbench ft`.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let protocol = args
        .protocol
        .context("--protocol is required (dynpick or ft300)")?;
    let port_path = args.port.as_deref().context("--port is required")?;
    match args.action {
        Action::Read {
            samples,
            tare,
            stream,
            json,
        } => {
            let ws = match protocol {
                Protocol::Dynpick => {
                    if stream {
                        bail!("--stream is only available for the ft300 protocol");
                    }
                    let port = open_serial(
                        "dynpick",
                        port_path,
                        tactbench::device::dynpick::driver::BAUD,
                    )?;
                    let mut d = DynPick::connect(port)?;
                    read_n(&mut d, samples, tare)?
                }
                Protocol::Ft300 => {
                    let port =
                        open_serial("ft300", port_path, tactbench::device::ft300::driver::BAUD)?;
                    let d = Ft300::connect(port)?;
                    if stream {
                        let mut s = d.start_stream()?;
                        let ws = read_n(&mut s, samples, tare)?;
                        s.stop()?;
                        ws
                    } else {
                        let mut d = d;
                        read_n(&mut d, samples, tare)?
                    }
                }
            };
            let m = Wrench::mean(&ws);
            if json {
                #[derive(Serialize)]
                struct Out {
                    protocol: String,
                    samples: Vec<WrenchJson>,
                    mean: WrenchJson,
                }
                let out = Out {
                    protocol: protocol.name().to_string(),
                    samples: ws.iter().map(|w| WrenchJson::from(*w)).collect(),
                    mean: m.into(),
                };
                println!("{}", serde_json::to_string(&out)?);
            } else {
                for w in &ws {
                    println!("{}", show(w));
                }
                if ws.len() > 1 {
                    println!("mean of {}: {}", ws.len(), show(&m));
                }
            }
        }
        Action::Tare => match protocol {
            Protocol::Dynpick => {
                let port = open_serial(
                    "dynpick",
                    port_path,
                    tactbench::device::dynpick::driver::BAUD,
                )?;
                let mut d = DynPick::connect(port)?;
                // Verified: read back after each `O`, repeated until it took.
                let sent = d.tare_verified()?;
                let w = d.read()?;
                println!(
                    "tared ({sent} `O` command{} sent); now {}",
                    if sent == 1 { "" } else { "s" },
                    show(&w)
                );
            }
            Protocol::Ft300 => bail!(
                "the ft300 tare is a software offset held by the driver for one run; \
                 it cannot persist across commands: use `tactbench ft read --tare`"
            ),
        },
        Action::Info { json } => {
            let fields: Vec<(&str, String)> = match protocol {
                Protocol::Dynpick => {
                    let port = open_serial(
                        "dynpick",
                        port_path,
                        tactbench::device::dynpick::driver::BAUD,
                    )?;
                    let mut d = DynPick::connect(port)?;
                    let fw = d.firmware_version()?;
                    let f = d.filter()?;
                    vec![
                        ("protocol", "dynpick".into()),
                        ("firmware", fw),
                        ("sensitivities", d.sensitivities().to_string()),
                        ("filter_divider", f.n().to_string()),
                    ]
                }
                Protocol::Ft300 => {
                    let port =
                        open_serial("ft300", port_path, tactbench::device::ft300::driver::BAUD)?;
                    let mut d = Ft300::connect(port)?;
                    let i = d.info()?;
                    vec![
                        ("protocol", "ft300".into()),
                        ("firmware", i.firmware),
                        ("serial", i.serial),
                        ("production_year", i.year.to_string()),
                    ]
                }
            };
            if json {
                let map: serde_json::Map<String, serde_json::Value> = fields
                    .into_iter()
                    .map(|(k, v)| (k.to_string(), serde_json::Value::String(v)))
                    .collect();
                println!("{}", serde_json::Value::Object(map));
            } else {
                for (k, v) in fields {
                    println!("{k}: {v}");
                }
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn read_n(s: &mut dyn ForceSensor, n: u32, tare: bool) -> anyhow::Result<Vec<Wrench>> {
    if tare {
        s.tare()?;
    }
    (0..n).map(|_| s.read().map_err(Into::into)).collect()
}

fn parse_wrench(text: &str) -> anyhow::Result<Wrench> {
    let v: Vec<f64> = text
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("--wrench `{text}` is not six comma-separated numbers"))?;
    if v.len() != 6 || v.iter().any(|x| !x.is_finite()) {
        bail!("--wrench `{text}` must be six finite numbers: Fx,Fy,Fz (N),Mx,My,Mz (N·m)");
    }
    Ok(Wrench {
        force_n: [v[0], v[1], v[2]],
        torque_nm: [v[3], v[4], v[5]],
    })
}

/// Runs `tactbench sim-serve-ft`.
pub fn serve(args: ServeArgs) -> anyhow::Result<ExitCode> {
    let ServeArgs {
        protocol,
        link,
        wrench,
        duration_s,
        fault,
        fault_skip,
        streaming,
        drop_stream_echo,
        tare_ignored,
    } = args;
    let link = link.as_path();
    let source = SharedWrench::new(parse_wrench(&wrench)?);
    let faults = match fault {
        None => no_faults(),
        Some(f) => {
            let kind = match f {
                FaultArg::Late => FaultKind::LateReply,
                FaultArg::DroppedByte => FaultKind::DroppedByte,
                FaultArg::Garbled => FaultKind::Garbled,
                FaultArg::Unsolicited => FaultKind::Unsolicited,
                FaultArg::Reset => FaultKind::DeviceReset,
                FaultArg::Disconnect => FaultKind::Disconnect,
            };
            FaultConfig::once(kind, FaultTarget::Any, fault_skip)
        }
    };
    match protocol {
        Protocol::Dynpick => {
            let cfg = DynPickSimConfig {
                faults,
                streaming_at_start: streaming,
                tare_ignored,
                ..Default::default()
            };
            let sim = DynPickSim::new(cfg, source);
            serve_until(PtyServer::spawn(sim, Some(link))?, protocol, duration_s)
        }
        Protocol::Ft300 => {
            let cfg = Ft300SimConfig {
                faults,
                streaming_at_start: streaming,
                drop_stream_echo,
                ..Default::default()
            };
            let sim = Ft300Sim::new(cfg, source);
            serve_until(PtyServer::spawn(sim, Some(link))?, protocol, duration_s)
        }
    }
}

/// Serves until the duration passes, the simulator hangs up, or the process is killed.
fn serve_until<S: Simulator>(
    server: PtyServer<S>,
    protocol: Protocol,
    duration_s: Option<f64>,
) -> anyhow::Result<ExitCode> {
    println!(
        "serving simulated {} on {} (link {})",
        protocol.name(),
        server.path().display(),
        server.port_path().display()
    );
    std::io::stdout().flush()?;
    let start = std::time::Instant::now();
    while !server.is_finished() && duration_s.is_none_or(|d| start.elapsed().as_secs_f64() < d) {
        std::thread::sleep(Duration::from_millis(50));
    }
    server.stop();
    Ok(ExitCode::SUCCESS)
}
