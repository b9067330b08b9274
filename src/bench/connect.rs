//! Opens the devices a [`BenchConfig`] names: real serial ports and a camera, or a
//! [`VirtualBench`] started in-process whose pseudo-terminals the *same* drivers then
//! open (`tactbench run --sim` is the hardware code path against simulators).

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde_json::json;
use thiserror::Error;

use super::config::{BenchConfig, BenchDevices, BenchGeometry, FtKind, NetFtConfig, StageKind};
use crate::device::bota::driver::{self as bota, Bota, BotaOptions};
use crate::device::camera::{self, SocketCamera};
use crate::device::dynpick::driver::{self as dynpick, DynPick};
use crate::device::fault::FaultConfig;
use crate::device::ft300::driver::{self as ft300, Ft300};
use crate::device::ft_common::open_serial;
use crate::device::grbl::{self, Grbl, GrblConfig};
use crate::device::marlin::{self, Marlin, MarlinConfig};
use crate::device::netft::codec::Scale;
use crate::device::netft::driver::{self as netft, read_calinfo, NetFt, NetFtOptions};
use crate::device::netft::UdpTransport;
use crate::device::zaber::{self, Zaber, ZaberConfig, DEFAULT_MM_PER_STEP};
use crate::device::{Camera, DeviceError, ForceSensor, Stage};
use crate::sim::bench::FtEndpoint;
use crate::sim::bench::{BenchError, BenchOptions, FtProtocol, StageProtocol, VirtualBench};
use crate::sim::scene::{Scene, SceneError};
use crate::sim::world::WorldGeometry;

/// An error opening the bench.
#[derive(Debug, Error)]
pub enum ConnectError {
    /// A device could not be opened or did not answer.
    #[error("{what}: {source}")]
    Device {
        /// Which device.
        what: &'static str,
        /// The driver's error.
        source: DeviceError,
    },
    /// The scene of a simulated bench.
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// The simulated bench could not start.
    #[error(transparent)]
    Sim(#[from] BenchError),
    /// The simulated bench's set-up cannot be used (a path it cannot name).
    #[error("{0}")]
    Setup(String),
}

/// Options for a simulated bench (tests inject faults here).
#[derive(Debug, Clone, Default)]
pub struct SimOptions {
    /// Where the pseudo-terminal links and the camera socket go.
    pub links: PathBuf,
    /// Sensor-frame point to start above (at twice the clearance); `None`: the stage
    /// kind's default start.
    pub start_over_mm: Option<[f64; 2]>,
    /// Opt-in stage simulator faults.
    pub stage_faults: Option<FaultConfig>,
    /// Opt-in force-sensor simulator faults.
    pub ft_faults: Option<FaultConfig>,
}

/// Open devices, ready for [`super::runner::run`].
pub struct Connected {
    /// The stage.
    pub stage: Box<dyn Stage>,
    /// The force sensor.
    pub ft: Box<dyn ForceSensor>,
    /// The camera.
    pub camera: Box<dyn Camera>,
    /// Where the sensor is in stage coordinates.
    pub geometry: BenchGeometry,
    /// Home at start / resume.
    pub home: bool,
    /// Tare at start / resume.
    pub tare: bool,
    /// Device identities for the manifest.
    pub identities: serde_json::Value,
    /// The bench description for the manifest.
    pub description: serde_json::Value,
    /// Things the user should know about how the devices were opened (a calibration
    /// overridden by the bench file), to print before the run.
    pub warnings: Vec<String>,
    /// The simulated bench, when simulated (dropped after the devices).
    pub sim: Option<VirtualBench>,
}

fn dev(what: &'static str) -> impl Fn(DeviceError) -> ConnectError {
    move |source| ConnectError::Device { what, source }
}

fn open_stage(
    kind: StageKind,
    port: &str,
    baud: u32,
    devices: [u8; 3],
    mm_per_step: f64,
    travel: Option<crate::device::TravelLimits>,
    marlin_max_feed_mm_min: Option<[f64; 3]>,
) -> Result<(Box<dyn Stage>, serde_json::Value), ConnectError> {
    Ok(match kind {
        StageKind::Grbl => {
            let p = grbl::open_serial(port, baud).map_err(dev("stage"))?;
            let cfg = GrblConfig {
                limits: travel,
                ..GrblConfig::default()
            };
            let g = Grbl::connect(p, cfg).map_err(dev("stage"))?;
            let id = json!({"protocol": "grbl", "port": port, "version": g.version()});
            (Box::new(g), id)
        }
        StageKind::Zaber => {
            let p = zaber::open_serial(port, baud).map_err(dev("stage"))?;
            let z = Zaber::connect(p, ZaberConfig::single_axis_devices(devices, mm_per_step))
                .map_err(dev("stage"))?;
            let id = json!({"protocol": "zaber", "port": port, "devices": devices});
            (Box::new(z), id)
        }
        StageKind::Marlin => {
            let p = marlin::open_serial(port, baud).map_err(dev("stage"))?;
            let cfg = MarlinConfig {
                limits: travel,
                max_feed_mm_min: marlin_max_feed_mm_min,
                ..MarlinConfig::default()
            };
            let m = Marlin::connect(p, cfg).map_err(dev("stage"))?;
            let i = m.info();
            let id = json!({
                "protocol": "marlin",
                "port": port,
                "firmware": i.firmware,
                "steps_per_mm": i.steps_per_mm,
                "max_feed_mm_min": i.max_feed_mm_min,
                "soft_endstops": i.soft_endstops.map(|s| json!({"enabled": s.enabled, "min_mm": s.min_mm, "max_mm": s.max_mm})),
            });
            (Box::new(m), id)
        }
    })
}

/// Reply deadline of the force-sensor drivers on the simulated bench. The simulators
/// share the host's CPU with the runner, the renderer and whatever else runs (tests run
/// in parallel), so the real sensors' deadlines (DynPick 50 ms, FT 300 100 ms) would
/// fail spuriously under load. The stage drivers' defaults (GRBL 2 s per line and
/// 500 ms per status report, Zaber 500 ms) already allow for this and are kept.
pub const SIM_FT_REPLY_TIMEOUT: Duration = Duration::from_millis(500);

/// Where a force sensor is reached.
enum FtTarget<'a> {
    /// A serial port (or a simulator's pseudo-terminal) at a baud rate.
    Serial { port: &'a str, baud: u32 },
    /// A network sensor.
    Network(&'a NetFtConfig),
}

fn open_ft(
    kind: FtKind,
    target: FtTarget<'_>,
    simulated: bool,
    warnings: &mut Vec<String>,
) -> Result<(Box<dyn ForceSensor>, serde_json::Value), ConnectError> {
    let reply_timeout = match (simulated, kind) {
        (true, _) => SIM_FT_REPLY_TIMEOUT,
        (false, FtKind::DynPick) => dynpick::REPLY_TIMEOUT,
        (false, FtKind::Ft300) => ft300::REPLY_TIMEOUT,
        (false, FtKind::Bota) => bota::REPLY_TIMEOUT,
        (false, FtKind::NetFt | FtKind::OnRobotHex) => netft::READ_TIMEOUT,
    };
    let serial = |device: &'static str| match target {
        FtTarget::Serial { port, baud } => {
            open_serial(device, port, baud).map(|p| (p, port.to_string()))
        }
        FtTarget::Network(n) => Err(DeviceError::new(
            crate::device::ErrorKind::Other,
            device,
            "open",
            format!(
                "{device} is a serial sensor, but a host ({}) was given",
                n.host
            ),
        )),
    };
    Ok(match kind {
        FtKind::DynPick => {
            let (p, port) = serial(dynpick::DEVICE).map_err(dev("force sensor"))?;
            let mut d = DynPick::connect_with(p, reply_timeout).map_err(dev("force sensor"))?;
            let fw = d.firmware_version().ok();
            (
                Box::new(d),
                json!({"protocol": "dynpick", "port": port, "firmware": fw}),
            )
        }
        FtKind::Ft300 => {
            let (p, port) = serial(ft300::DEVICE).map_err(dev("force sensor"))?;
            let mut d =
                Ft300::connect_with(p, crate::device::ft300::codec::SLAVE_ADDRESS, reply_timeout)
                    .map_err(dev("force sensor"))?;
            let info = d.info().ok().map(|i| format!("{i:?}"));
            // Runs read the stream (100 Hz, the newest frame), as Robotiq recommends for
            // acquisition: polling at 19200 baud tops out at 77 Hz.
            let s = d.start_stream().map_err(dev("force sensor"))?;
            (
                Box::new(s),
                json!({"protocol": "ft300", "port": port, "info": info, "mode": "stream"}),
            )
        }
        FtKind::Bota => {
            let (p, port) = serial(bota::DEVICE).map_err(dev("force sensor"))?;
            let d = Bota::connect(
                p,
                BotaOptions {
                    reply_timeout: reply_timeout.max(bota::REPLY_TIMEOUT),
                    ..BotaOptions::default()
                },
            )
            .map_err(dev("force sensor"))?;
            let last = d.last_frame();
            (
                Box::new(d),
                json!({
                    "protocol": "bota",
                    "port": port,
                    "sinc_len": bota::DEFAULT_SINC_LEN,
                    "temperature_c": last.map(|f| f.temperature_c),
                }),
            )
        }
        FtKind::NetFt | FtKind::OnRobotHex => {
            let FtTarget::Network(n) = target else {
                return Err(ConnectError::Device {
                    what: "force sensor",
                    source: DeviceError::new(
                        crate::device::ErrorKind::Other,
                        kind.name(),
                        "open",
                        format!(
                            "{} is a network sensor: give host, not a serial port",
                            kind.name()
                        ),
                    ),
                });
            };
            let (scale, source) = netft_scale(kind, n, warnings)?;
            let device = if kind == FtKind::NetFt {
                netft::DEVICE
            } else {
                netft::DEVICE_HEX
            };
            let link =
                UdpTransport::connect(device, &n.host, n.rdt_port).map_err(dev("force sensor"))?;
            let opts = NetFtOptions {
                scale,
                read_timeout: reply_timeout,
                device,
                stale_after: netft::MEAN_WINDOW,
            };
            let d = NetFt::connect(link, opts).map_err(dev("force sensor"))?;
            let id = json!({
                "protocol": kind.name(),
                "host": n.host,
                "rdt_port": n.rdt_port,
                "cal_port": (kind == FtKind::NetFt).then_some(n.cal_port),
                "counts_per_n": scale.counts_per_n,
                "counts_per_nm": scale.counts_per_nm,
                "calibration": source,
                "measured_rate_hz": d.measured_rate_hz(),
            });
            (Box::new(d), id)
        }
    })
}

/// The scale of a network sensor: the Net F/T's READCALINFO (a bench-file override
/// wins, with a warning when it differs), the HEX's fixed scale (or the override).
fn netft_scale(
    kind: FtKind,
    n: &NetFtConfig,
    warnings: &mut Vec<String>,
) -> Result<(Scale, &'static str), ConnectError> {
    let given = n.counts_override.map(|[f, t]| Scale {
        counts_per_n: f,
        counts_per_nm: t,
    });
    if kind == FtKind::OnRobotHex {
        return Ok(match given {
            Some(s) => (s, "bench file"),
            None => (Scale::ONROBOT_HEX, "OnRobot HEX fixed scale"),
        });
    }
    let device = match read_calinfo(&n.host, n.cal_port) {
        Ok(c) => c.scale().map_err(|e| ConnectError::Device {
            what: "force sensor",
            source: DeviceError::new(
                crate::device::ErrorKind::Protocol,
                netft::DEVICE,
                format!("READCALINFO {}:{}", n.host, n.cal_port),
                e.to_string(),
            ),
        })?,
        Err(e) => match given {
            Some(g) => {
                warnings.push(format!(
                    "force sensor: the calibration query failed ({e}); using counts_per_force / counts_per_torque from the bench file"
                ));
                return Ok((g, "bench file (device query failed)"));
            }
            None => return Err(dev("force sensor")(e)),
        },
    };
    Ok(match given {
        Some(g) => {
            if g != device {
                warnings.push(format!(
                    "force sensor: the bench file overrides the device's calibration ({} counts/N, {} counts/(N·m)) with {} counts/N, {} counts/(N·m)",
                    device.counts_per_n, device.counts_per_nm, g.counts_per_n, g.counts_per_nm
                ));
            }
            (g, "bench file (overrides the device)")
        }
        None => (device, "device (READCALINFO)"),
    })
}

/// Opens the bench. For `[sim]`, starts the virtual bench first (links under
/// `sim.links`) and connects the real drivers to it.
pub fn connect(bench: &BenchConfig, sim: &SimOptions) -> Result<Connected, ConnectError> {
    match &bench.devices {
        BenchDevices::Hardware {
            stage,
            force_sensor,
            camera: spec,
        } => {
            let geometry = bench.geometry.ok_or_else(|| ConnectError::Device {
                what: "bench",
                source: DeviceError::new(
                    crate::device::ErrorKind::Other,
                    "bench",
                    "connect",
                    "a hardware bench needs [geometry]",
                ),
            })?;
            let (s, sid) = open_stage(
                stage.protocol,
                &stage.port,
                stage.baud,
                stage.zaber_devices,
                stage.zaber_mm_per_step,
                stage.travel,
                stage.marlin_max_feed_mm_min,
            )?;
            let mut warnings = Vec::new();
            let target = match &force_sensor.network {
                Some(n) => FtTarget::Network(n),
                None => FtTarget::Serial {
                    port: &force_sensor.port,
                    baud: force_sensor.baud,
                },
            };
            let (f, fid) = open_ft(force_sensor.protocol, target, false, &mut warnings)?;
            let c = camera::open(spec).map_err(dev("camera"))?;
            Ok(Connected {
                stage: s,
                ft: f,
                camera: c,
                geometry,
                home: bench.home,
                tare: bench.tare,
                identities: json!({"stage": sid, "force_sensor": fid, "camera": format!("{spec:?}")}),
                description: json!({
                    "file": bench.path.display().to_string(),
                    "cwd": working_dir(),
                }),
                warnings,
                sim: None,
            })
        }
        BenchDevices::Sim(cfg) => {
            let (vb, geometry, world) = start_virtual(bench, cfg, sim)?;
            // Serial ports are opened by name (a `&str`): a link inside a run
            // directory whose path is not UTF-8 would be mangled by a lossy
            // conversion, so the pseudo-terminal's own name is used then.
            let port = port_name(vb.stage_port(), vb.stage_device())?;
            let (s, sid) = open_stage(
                cfg.stage,
                &port,
                115_200,
                [1, 2, 3],
                DEFAULT_MM_PER_STEP,
                None,
                None,
            )?;
            let mut warnings = Vec::new();
            let (f, fid) = open_sim_ft(&vb, cfg.force_sensor, &mut warnings)?;
            let c = SocketCamera::connect(vb.camera_socket()).map_err(dev("camera"))?;
            Ok(Connected {
                stage: s,
                ft: f,
                camera: Box::new(c),
                geometry,
                // The Zaber simulator starts unreferenced, as the devices do.
                home: bench.home || cfg.stage == StageKind::Zaber,
                tare: bench.tare,
                identities: json!({"stage": sid, "force_sensor": fid, "camera": "sim"}),
                description: json!({
                    "sim": {
                        "scene": cfg.scene.display().to_string(),
                        "scene_toml": std::fs::read_to_string(&cfg.scene).unwrap_or_default(),
                        "stage": format!("{:?}", cfg.stage),
                        "force_sensor": format!("{:?}", cfg.force_sensor),
                        "friction": world.friction,
                    },
                    "file": bench.path.display().to_string(),
                    "cwd": working_dir(),
                }),
                warnings,
                sim: Some(vb),
            })
        }
    }
}

/// Starts the virtual bench of a `[sim]` bench file: its world geometry from the
/// stage kind's defaults, overridden by the file's `[geometry]`.
fn start_virtual(
    bench: &BenchConfig,
    cfg: &super::config::SimConfig,
    sim: &SimOptions,
) -> Result<(VirtualBench, BenchGeometry, WorldGeometry), ConnectError> {
    let scene = Scene::from_path(&cfg.scene)?;
    let protocol = match cfg.stage {
        StageKind::Grbl => StageProtocol::Grbl,
        StageKind::Zaber => StageProtocol::Zaber,
        StageKind::Marlin => StageProtocol::Marlin,
    };
    let (mut world, _) = protocol.default_geometry();
    let geometry = match bench.geometry {
        Some(g) => {
            world.sensor_origin_in_stage_mm = g.sensor_origin_in_stage_mm;
            world.surface_z_mm = g.surface_z_mm;
            world.press_direction = g.press_direction;
            g
        }
        None => BenchGeometry {
            sensor_origin_in_stage_mm: world.sensor_origin_in_stage_mm,
            surface_z_mm: world.surface_z_mm,
            press_direction: world.press_direction,
            clearance_mm: 1.0,
        },
    };
    world.friction = cfg.friction.unwrap_or(scene.load.friction);
    let start_mm = sim
        .start_over_mm
        .map(|xy| geometry.stage_point(xy, -2.0 * geometry.clearance_mm));
    let vb = VirtualBench::start_with(
        &scene,
        protocol,
        match cfg.force_sensor {
            FtKind::DynPick => FtProtocol::DynPick,
            FtKind::Ft300 => FtProtocol::Ft300,
            // The HEX speaks the Net F/T's records: simulated by the same device
            // (config.rs refuses it for [sim] benches).
            FtKind::NetFt | FtKind::OnRobotHex => FtProtocol::NetFt,
            FtKind::Bota => FtProtocol::Bota,
        },
        &sim.links,
        BenchOptions {
            geometry: Some(world),
            start_mm,
            stage_faults: sim.stage_faults.clone(),
            ft_faults: sim.ft_faults.clone(),
        },
    )?;
    Ok((vb, geometry, world))
}

/// Connects the force-sensor driver to a virtual bench's simulator.
fn open_sim_ft(
    vb: &VirtualBench,
    kind: FtKind,
    warnings: &mut Vec<String>,
) -> Result<(Box<dyn ForceSensor>, serde_json::Value), ConnectError> {
    let baud = match kind {
        FtKind::DynPick => dynpick::BAUD,
        FtKind::Ft300 => ft300::BAUD,
        _ => bota::BAUD,
    };
    match vb.ft_endpoint() {
        FtEndpoint::Serial(p) => {
            let port = port_name(p, vb.ft_device().unwrap_or(p))?;
            open_ft(kind, FtTarget::Serial { port: &port, baud }, true, warnings)
        }
        FtEndpoint::Network { rdt, cal } => {
            let n = NetFtConfig {
                host: rdt.ip().to_string(),
                rdt_port: rdt.port(),
                cal_port: cal.map_or(0, |c| c.port()),
                counts_override: None,
            };
            open_ft(kind, FtTarget::Network(&n), true, warnings)
        }
    }
}

/// What `tactbench stage --bench` drives: the stage's port and protocol settings
/// (the CLI opens the stage itself, with the same drivers) and the force sensor,
/// opened; no camera.
pub struct StageBench {
    /// The stage: protocol, port (a simulated bench's pseudo-terminal), baud, ...
    pub stage: super::config::StageConfig,
    /// The force sensor the stage commands watch.
    pub ft: Box<dyn ForceSensor>,
    /// Things to tell the user about how the force sensor was opened.
    pub warnings: Vec<String>,
    /// The simulated bench, when simulated (it stops when dropped).
    pub sim: Option<VirtualBench>,
}

/// Opens what `tactbench stage --bench` needs: the force sensor, and for a `[sim]`
/// bench the virtual bench (links under `sim.links`) whose stage port it returns.
pub fn open_for_stage(bench: &BenchConfig, sim: &SimOptions) -> Result<StageBench, ConnectError> {
    match &bench.devices {
        BenchDevices::Hardware {
            stage,
            force_sensor,
            ..
        } => {
            let mut warnings = Vec::new();
            let target = match &force_sensor.network {
                Some(n) => FtTarget::Network(n),
                None => FtTarget::Serial {
                    port: &force_sensor.port,
                    baud: force_sensor.baud,
                },
            };
            let (ft, _) = open_ft(force_sensor.protocol, target, false, &mut warnings)?;
            Ok(StageBench {
                stage: stage.clone(),
                ft,
                warnings,
                sim: None,
            })
        }
        BenchDevices::Sim(cfg) => {
            let (vb, _, _) = start_virtual(bench, cfg, sim)?;
            let port = port_name(vb.stage_port(), vb.stage_device())?;
            let mut warnings = Vec::new();
            let (ft, _) = open_sim_ft(&vb, cfg.force_sensor, &mut warnings)?;
            Ok(StageBench {
                stage: super::config::StageConfig {
                    protocol: cfg.stage,
                    port,
                    baud: 115_200,
                    zaber_devices: [1, 2, 3],
                    zaber_mm_per_step: DEFAULT_MM_PER_STEP,
                    marlin_max_feed_mm_min: None,
                    travel: None,
                },
                ft,
                warnings,
                sim: Some(vb),
            })
        }
    }
}

/// The name to open a simulated device's port by: its link when the link's path is
/// UTF-8, else the pseudo-terminal it points to; an error naming the path when
/// neither is.
fn port_name(link: &Path, device: &Path) -> Result<String, ConnectError> {
    link.to_str()
        .or_else(|| device.to_str())
        .map(str::to_string)
        .ok_or_else(|| {
            ConnectError::Setup(format!(
                "the simulated bench's port {} is not a UTF-8 path, nor its pseudo-terminal {}",
                link.display(),
                device.display()
            ))
        })
}

/// The working directory the bench description's relative paths are relative to
/// (recorded so `run --resume` works from any directory).
fn working_dir() -> Option<String> {
    std::env::current_dir()
        .ok()
        .map(|d| d.display().to_string())
}

/// A temporary-directory-free default for the links of an in-process simulated bench:
/// `RUN_DIR/.sim` (removed when the bench drops).
pub fn default_links(run_dir: &Path) -> PathBuf {
    run_dir.join(".sim")
}

/// The geometry a bench config will use, without opening anything (for `--dry-run`).
pub fn geometry_of(bench: &BenchConfig) -> BenchGeometry {
    match (&bench.devices, bench.geometry) {
        (_, Some(g)) => g,
        (BenchDevices::Sim(cfg), None) => {
            let p = match cfg.stage {
                StageKind::Grbl => StageProtocol::Grbl,
                StageKind::Zaber => StageProtocol::Zaber,
                StageKind::Marlin => StageProtocol::Marlin,
            };
            let (w, _): (WorldGeometry, _) = p.default_geometry();
            BenchGeometry {
                sensor_origin_in_stage_mm: w.sensor_origin_in_stage_mm,
                surface_z_mm: w.surface_z_mm,
                press_direction: w.press_direction,
                clearance_mm: 1.0,
            }
        }
        (BenchDevices::Hardware { .. }, None) => BenchGeometry {
            sensor_origin_in_stage_mm: [0.0, 0.0],
            surface_z_mm: 0.0,
            press_direction: 1.0,
            clearance_mm: 1.0,
        },
    }
}
