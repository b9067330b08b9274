//! `tactbench ft`: read, tare and identify a 6-axis force/torque sensor (WACOH DynPick,
//! Robotiq FT 300 or Bota on a serial port; ATI Net F/T or OnRobot HEX on the network);
//! the hidden `sim-serve-ft` command serves a simulated sensor (on a pseudo-terminal, or
//! on loopback sockets for the Net F/T) for tests and dry runs.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{bail, Context};
use clap::{Args as ClapArgs, Subcommand, ValueEnum};
use serde::Serialize;

use tactbench::device::bota::{self, Bota, BotaOptions, BotaSim, BotaSimConfig};
use tactbench::device::dynpick::{DynPick, DynPickSim, DynPickSimConfig};
use tactbench::device::ft300::{Ft300, Ft300Sim, Ft300SimConfig};
use tactbench::device::ft_common::{
    no_faults, open_serial, FaultConfig, FaultKind, FaultTarget, SharedWrench,
};
use tactbench::device::netft::codec::Scale;
use tactbench::device::netft::driver::NetFtOptions;
use tactbench::device::netft::{
    read_calinfo, NetFt, NetFtCore, NetFtServer, NetFtSimConfig, UdpTransport,
};
use tactbench::device::pty::{PtyServer, Simulator};
use tactbench::device::{ForceSensor, Wrench};

/// Force/torque sensor commands.
#[derive(ClapArgs)]
pub struct Args {
    /// Serial port of the sensor (e.g. /dev/ttyUSB0); for netft / onrobot-hex the
    /// sensor's host name or IP address.
    #[arg(long, global = true)]
    port: Option<String>,
    /// Wire protocol.
    #[arg(long, value_enum, global = true)]
    protocol: Option<Protocol>,
    /// netft / onrobot-hex: UDP port of the RDT stream.
    #[arg(long, global = true, default_value_t = tactbench::device::netft::codec::RDT_PORT)]
    rdt_port: u16,
    /// netft: TCP port of the calibration query (READCALINFO).
    #[arg(long, global = true, default_value_t = tactbench::device::netft::codec::CAL_PORT)]
    cal_port: u16,
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
    /// Symlink to create pointing at the pseudo-terminal (serial protocols).
    #[arg(long)]
    link: Option<PathBuf>,
    /// netft / onrobot-hex: UDP port to serve RDT on, on 127.0.0.1 (0: chosen by the OS).
    #[arg(long, default_value_t = 0)]
    rdt_port: u16,
    /// netft: TCP port to serve READCALINFO on, on 127.0.0.1 (0: chosen by the OS).
    #[arg(long, default_value_t = 0)]
    cal_port: u16,
    /// netft / onrobot-hex: records per second.
    #[arg(long, default_value_t = 1000.0)]
    rate_hz: f64,
    /// netft: status word of every record; bota: status bits of every frame (e.g. 0x2
    /// overrange). Hexadecimal with 0x, or decimal.
    #[arg(long, default_value = "0")]
    status: String,
    /// bota: repeat the boot text `App Init` this often until configured (a real sensor
    /// reboots when its port is opened; a pseudo-terminal cannot tell the simulator).
    #[arg(long)]
    banner_every_ms: Option<u64>,
    /// Fault probability per reply / record for the --fault kinds (seeded, unlimited);
    /// without it, one fault after --fault-skip replies.
    #[arg(long)]
    fault_probability: Option<f64>,
    /// Seed of the fault draws.
    #[arg(long, default_value_t = 1)]
    fault_seed: u64,
    /// Constant load: Fx,Fy,Fz (N),Mx,My,Mz (N·m).
    #[arg(long, default_value = "0,0,0,0,0,0", allow_hyphen_values = true)]
    wrench: String,
    /// Stop after this many seconds (default: serve until killed).
    #[arg(long)]
    duration_s: Option<f64>,
    /// Inject faults of these kinds (repeatable; as `sim-serve-stage --fault`). On UDP
    /// (netft): loss, duplicate, reorder, garbled (a truncated datagram), reset,
    /// disconnect.
    #[arg(long, value_enum)]
    fault: Vec<FaultArg>,
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
    /// UDP: a record lost (the dropped-byte fault of the serial simulators).
    Loss,
    /// UDP: a record sent twice (the unsolicited fault of the serial simulators).
    Duplicate,
    /// UDP: a record delayed past later ones (the late fault of the serial simulators).
    Reorder,
}

/// Supported sensors.
#[derive(Clone, Copy, ValueEnum, PartialEq, Eq, Debug)]
enum Protocol {
    /// WACOH DynPick (921600 baud, ASCII records).
    Dynpick,
    /// Robotiq FT 300 (19200 baud, Modbus RTU + stream).
    Ft300,
    /// ATI Net F/T (network: RDT over UDP, calibration over TCP; --port HOST).
    Netft,
    /// OnRobot HEX (network: the Net F/T's RDT records, fixed scale; --port HOST).
    OnrobotHex,
    /// Bota Systems serial sensor (460800 baud, binary stream).
    Bota,
}

impl Protocol {
    fn name(self) -> &'static str {
        match self {
            Protocol::Dynpick => "dynpick",
            Protocol::Ft300 => "ft300",
            Protocol::Netft => "netft",
            Protocol::OnrobotHex => "onrobot-hex",
            Protocol::Bota => "bota",
        }
    }
}

/// Opens a Net F/T (scale from READCALINFO) or an OnRobot HEX (fixed scale).
fn open_netft(
    protocol: Protocol,
    host: &str,
    rdt_port: u16,
    cal_port: u16,
) -> anyhow::Result<(
    NetFt<UdpTransport>,
    Option<tactbench::device::netft::codec::CalInfo>,
)> {
    let (opts, cal) = if protocol == Protocol::Netft {
        let cal = read_calinfo(host, cal_port)?;
        let scale: Scale = cal
            .scale()
            .with_context(|| format!("READCALINFO from {host}:{cal_port}"))?;
        (NetFtOptions::netft(scale), Some(cal))
    } else {
        (NetFtOptions::onrobot_hex(), None)
    };
    let link = UdpTransport::connect(opts.device, host, rdt_port)?;
    Ok((NetFt::connect(link, opts)?, cal))
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

/// The sensor a `tactbench ft` command talks to.
#[derive(Clone, Copy)]
struct Target<'a> {
    protocol: Protocol,
    /// Serial port, or the host of a netft / onrobot-hex.
    port: &'a str,
    rdt_port: u16,
    cal_port: u16,
}

impl Target<'_> {
    /// Connects a DynPick on the serial port.
    fn dynpick(&self) -> anyhow::Result<DynPick<Box<dyn serialport::SerialPort>>> {
        let port = open_serial(
            "dynpick",
            self.port,
            tactbench::device::dynpick::driver::BAUD,
        )?;
        Ok(DynPick::connect(port)?)
    }

    /// Opens the Net F/T or OnRobot HEX at the host (see [`open_netft`]).
    fn netft(
        &self,
    ) -> anyhow::Result<(
        NetFt<UdpTransport>,
        Option<tactbench::device::netft::codec::CalInfo>,
    )> {
        open_netft(self.protocol, self.port, self.rdt_port, self.cal_port)
    }

    /// Connects a Bota on the serial port.
    fn bota(&self) -> anyhow::Result<Bota<Box<dyn serialport::SerialPort>>> {
        let port = open_serial(bota::driver::DEVICE, self.port, bota::driver::BAUD)?;
        Ok(Bota::connect(port, BotaOptions::default())?)
    }
}

/// Runs `tactbench ft`: `read`, `tare` or `info` on the sensor `--protocol` and
/// `--port` name.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let protocol = args
        .protocol
        .context("--protocol is required (dynpick, ft300, bota, netft or onrobot-hex)")?;
    let port = args
        .port
        .as_deref()
        .context("--port is required (a serial port; for netft / onrobot-hex the sensor's host)")?;
    let t = Target {
        protocol,
        port,
        rdt_port: args.rdt_port,
        cal_port: args.cal_port,
    };
    match args.action {
        Action::Read {
            samples,
            tare,
            stream,
            json,
        } => {
            let ws = read(t, samples, tare, stream)?;
            print_readings(protocol, &ws, json)?;
        }
        Action::Tare => tare_sensor(t)?,
        Action::Info { json } => {
            let fields = info(t)?;
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

/// `ft read`: `samples` readings (after a tare with `tare`; the FT 300's stream with
/// `stream`); the streaming sensors' status since connecting on stderr.
fn read(t: Target<'_>, samples: u32, tare: bool, stream: bool) -> anyhow::Result<Vec<Wrench>> {
    Ok(match t.protocol {
        Protocol::Dynpick => {
            if stream {
                bail!("--stream is only available for the ft300 protocol");
            }
            let mut d = t.dynpick()?;
            read_n(&mut d, samples, tare)?
        }
        Protocol::Ft300 => {
            let port = open_serial("ft300", t.port, tactbench::device::ft300::driver::BAUD)?;
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
        Protocol::Netft | Protocol::OnrobotHex => {
            if stream {
                bail!("--stream is only available for the ft300 protocol (netft always streams)");
            }
            let (mut d, _) = t.netft()?;
            let ws = read_n(&mut d, samples, tare)?;
            if let Some(s) = d.take_status() {
                eprintln!("{s}");
            }
            ws
        }
        Protocol::Bota => {
            if stream {
                bail!("--stream is only available for the ft300 protocol (bota always streams)");
            }
            let mut d = t.bota()?;
            let ws = read_n(&mut d, samples, tare)?;
            if let Some(s) = d.take_status() {
                eprintln!("{s}");
            }
            ws
        }
    })
}

/// The readings and their mean, as text or one JSON object.
fn print_readings(protocol: Protocol, ws: &[Wrench], json: bool) -> anyhow::Result<()> {
    let m = Wrench::mean(ws);
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
        for w in ws {
            println!("{}", show(w));
        }
        if ws.len() > 1 {
            println!("mean of {}: {}", ws.len(), show(&m));
        }
    }
    Ok(())
}

/// `ft tare`: zeroes the sensor where it can hold a zero (DynPick verified, Net F/T
/// bias), a software offset for this command only on a Bota; refused on an FT 300.
fn tare_sensor(t: Target<'_>) -> anyhow::Result<()> {
    match t.protocol {
        Protocol::Dynpick => {
            let mut d = t.dynpick()?;
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
        Protocol::Netft | Protocol::OnrobotHex => {
            let (mut d, _) = t.netft()?;
            // The device's software bias (0x0042) persists until the sensor is
            // power-cycled or biased again; the residual is checked by reading.
            d.tare()?;
            let residual = d.offset();
            let w = d.read()?;
            println!(
                "biased (RDT 0x0042; residual after the bias {}); now {}",
                show(&residual),
                show(&w)
            );
        }
        Protocol::Bota => {
            let mut d = t.bota()?;
            d.tare()?;
            let w = d.read()?;
            println!(
                "software offset {} taken (the Bota serial protocol has no zeroing command: \
                 the offset holds for this command only; runs tare at start and on resume, \
                 or use `tactbench ft read --tare`); now {}",
                show(&d.offset()),
                show(&w)
            );
        }
    }
    Ok(())
}

/// `ft info`: what the sensor says about itself, as (field, value) pairs.
fn info(t: Target<'_>) -> anyhow::Result<Vec<(&'static str, String)>> {
    Ok(match t.protocol {
        Protocol::Dynpick => {
            let mut d = t.dynpick()?;
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
            let port = open_serial("ft300", t.port, tactbench::device::ft300::driver::BAUD)?;
            let mut d = Ft300::connect(port)?;
            let i = d.info()?;
            vec![
                ("protocol", "ft300".into()),
                ("firmware", i.firmware),
                ("serial", i.serial),
                ("production_year", i.year.to_string()),
            ]
        }
        Protocol::Netft | Protocol::OnrobotHex => netft_info(t)?,
        Protocol::Bota => bota_info(t)?,
    })
}

/// `ft info` of a Net F/T or OnRobot HEX: host, calibration, scale, measured rate,
/// stream counters, a reading.
fn netft_info(t: Target<'_>) -> anyhow::Result<Vec<(&'static str, String)>> {
    let (mut d, cal) = t.netft()?;
    let w = d.read()?;
    let st = d.stats();
    let scale = d.scale();
    let mut v = vec![
        ("protocol", t.protocol.name().to_string()),
        ("host", format!("{} (RDT UDP {})", t.port, t.rdt_port)),
    ];
    if let Some(c) = cal {
        v.push((
            "calibration",
            format!(
                "READCALINFO TCP {}: force unit {}, torque unit {}, {} counts per force unit, {} counts per torque unit",
                t.cal_port, c.force_unit, c.torque_unit, c.counts_per_force, c.counts_per_torque
            ),
        ));
    } else {
        v.push(("calibration", "OnRobot HEX fixed scale".into()));
    }
    v.push(("counts_per_n", format!("{}", scale.counts_per_n)));
    v.push(("counts_per_nm", format!("{}", scale.counts_per_nm)));
    v.push(("rate_hz", format!("{:.0}", d.measured_rate_hz())));
    v.push((
        "stream",
        format!(
            "{} records, {} lost, {} duplicate, {} stale, {} with a status word, {} malformed, {} start requests",
            st.records, st.lost, st.duplicates, st.stale, st.bad_status, st.malformed, st.start_requests
        ),
    ));
    v.push(("reading", show(&w)));
    Ok(v)
}

/// `ft info` of a Bota: sample period, the last frame's status, timestamp and
/// temperature, stream counters, a reading.
fn bota_info(t: Target<'_>) -> anyhow::Result<Vec<(&'static str, String)>> {
    let mut d = t.bota()?;
    let w = d.read()?;
    let f = d
        .last_frame()
        .context("no frame received from the sensor")?;
    let st = d.stats();
    Ok(vec![
        ("protocol", "bota".into()),
        (
            "sample_period",
            format!(
                "{} ms (sinc {})",
                d.sample_period_s() * 1000.0,
                bota::driver::DEFAULT_SINC_LEN
            ),
        ),
        (
            "status",
            format!("0x{:04x} {}", f.status, bota::codec::status_names(f.status)),
        ),
        ("timestamp_us", f.timestamp.to_string()),
        ("temperature_c", format!("{:.2}", f.temperature_c)),
        (
            "stream",
            format!(
                "{} frames, {} left out (overrange/invalid), {} bad CRC, {} bytes skipped",
                st.frames, st.bad, st.bad_crc, st.skipped
            ),
        ),
        ("reading", show(&w)),
    ])
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
        rdt_port,
        cal_port,
        rate_hz,
        status,
        banner_every_ms,
        fault_probability,
        fault_seed,
        wrench,
        duration_s,
        fault,
        fault_skip,
        streaming,
        drop_stream_echo,
        tare_ignored,
    } = args;
    let source = SharedWrench::new(parse_wrench(&wrench)?);
    let kinds: Vec<FaultKind> = fault
        .iter()
        .map(|f| match f {
            FaultArg::Late | FaultArg::Reorder => FaultKind::LateReply,
            FaultArg::DroppedByte | FaultArg::Loss => FaultKind::DroppedByte,
            FaultArg::Garbled => FaultKind::Garbled,
            FaultArg::Unsolicited | FaultArg::Duplicate => FaultKind::Unsolicited,
            FaultArg::Reset => FaultKind::DeviceReset,
            FaultArg::Disconnect => FaultKind::Disconnect,
        })
        .collect();
    let faults = match (kinds.is_empty(), fault_probability) {
        (true, _) => no_faults(),
        (false, None) => FaultConfig {
            kinds,
            ..FaultConfig::once(FaultKind::LateReply, FaultTarget::Any, fault_skip)
        },
        (false, Some(p)) => {
            if !(0.0..=1.0).contains(&p) {
                bail!("--fault-probability {p} must be in [0, 1]");
            }
            FaultConfig {
                seed: fault_seed,
                kinds,
                probability: p,
                target: FaultTarget::Any,
                skip: fault_skip,
                max_faults: u32::MAX,
                // Late enough that a record arrives after later ones; short enough
                // that a late reply still arrives within a serial driver's retries.
                late_by: Duration::from_millis(20),
            }
        }
    };
    let status_word = parse_status(&status)?;
    let need_link = || {
        link.as_deref().with_context(|| {
            format!(
                "--link is required for the serial protocol {}",
                protocol.name()
            )
        })
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
            serve_until(
                PtyServer::spawn(sim, Some(need_link()?))?,
                protocol,
                duration_s,
            )
        }
        Protocol::Ft300 => {
            let cfg = Ft300SimConfig {
                faults,
                streaming_at_start: streaming,
                drop_stream_echo,
                ..Default::default()
            };
            let sim = Ft300Sim::new(cfg, source);
            serve_until(
                PtyServer::spawn(sim, Some(need_link()?))?,
                protocol,
                duration_s,
            )
        }
        Protocol::Bota => {
            let cfg = BotaSimConfig {
                faults,
                status: u16::try_from(status_word)
                    .with_context(|| format!("--status {status}: bota status is 16 bits"))?,
                banner_every: banner_every_ms.map(Duration::from_millis),
                ..Default::default()
            };
            let sim = BotaSim::new(cfg, source);
            serve_until(
                PtyServer::spawn(sim, Some(need_link()?))?,
                protocol,
                duration_s,
            )
        }
        Protocol::Netft | Protocol::OnrobotHex => {
            if !(rate_hz.is_finite() && (1.0..=20_000.0).contains(&rate_hz)) {
                bail!("--rate-hz {rate_hz} must be in [1, 20000]");
            }
            let cfg = NetFtSimConfig {
                faults,
                status: status_word,
                rate_hz,
                onrobot_hex: protocol == Protocol::OnrobotHex,
                ..Default::default()
            };
            let server = NetFtServer::spawn(NetFtCore::new(cfg, source), rdt_port, cal_port)?;
            match server.cal_addr() {
                Some(c) => println!(
                    "serving simulated {} on {} --rdt-port {} --cal-port {}",
                    protocol.name(),
                    server.rdt_addr().ip(),
                    server.rdt_addr().port(),
                    c.port()
                ),
                None => println!(
                    "serving simulated {} on {} --rdt-port {}",
                    protocol.name(),
                    server.rdt_addr().ip(),
                    server.rdt_addr().port()
                ),
            }
            std::io::stdout().flush()?;
            let start = std::time::Instant::now();
            while !server.is_finished()
                && duration_s.is_none_or(|d| start.elapsed().as_secs_f64() < d)
            {
                std::thread::sleep(Duration::from_millis(50));
            }
            drop(server);
            Ok(ExitCode::SUCCESS)
        }
    }
}

/// `--status`: hexadecimal with `0x`, or decimal.
fn parse_status(text: &str) -> anyhow::Result<u32> {
    let t = text.trim();
    let v = match t.strip_prefix("0x").or_else(|| t.strip_prefix("0X")) {
        Some(h) => u32::from_str_radix(h, 16),
        None => t.parse(),
    };
    v.with_context(|| format!("--status {text:?} is not a number (0x… or decimal)"))
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
