//! The simulated bench: a stage simulator, a force-sensor simulator and a camera,
//! served on real pseudo-terminals and a Unix socket around one shared [`World`], so
//! the same drivers and commands that run a real bench run this one.
//!
//! - The stage simulator (GRBL, Zaber or Marlin) is wrapped in [`WorldStage`], which publishes
//!   the stage position to the world after every simulator step (and wakes every
//!   [`WORLD_TICK`] so motion is seen while nobody talks to the stage).
//! - The force-sensor simulator (DynPick, FT 300 or Bota on a pseudo-terminal; the
//!   ATI Net F/T on loopback UDP/TCP sockets with OS-chosen ports) reads its wrench from
//!   the world through [`WorldWrench`].
//! - The camera serves frames rendered from the world's current contact on
//!   `camera.sock` (protocol in [`crate::device::camera::socket`]), with the scene's
//!   effects and nothing else.
//!
//! The scene's `[load]` is not used here: the stage decides the load.

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use thiserror::Error;

use super::render::to_rgb8;
use super::scene::Scene;
use super::simulate::Simulation;
use super::world::{World, WorldGeometry};
use crate::device::bota::sim::{BotaSim, BotaSimConfig};
use crate::device::dynpick::sim::{DynPickSim, DynPickSimConfig};
use crate::device::fault::FaultConfig;
use crate::device::ft300::sim::{Ft300Sim, Ft300SimConfig};
use crate::device::ft_common::{no_faults, WrenchSource};
use crate::device::grbl::sim::{GrblSim, GrblSimConfig};
use crate::device::marlin::sim::{MarlinSim, MarlinSimConfig};
use crate::device::netft::sim::{NetFtCore, NetFtServer, NetFtSimConfig, NetFtSimError};
use crate::device::pty::{Flow, PtyError, PtyServer, Simulator};
use crate::device::zaber::sim::{ZaberSim, ZaberSimConfig};
use crate::device::zaber::DEFAULT_MM_PER_STEP;
use crate::device::Wrench;

/// How often the stage wrapper publishes the position while idle on the wire.
pub const WORLD_TICK: Duration = Duration::from_millis(2);

/// Zaber travel of the simulated bench, microsteps (≈ 47.6 mm at the default resolution).
pub const ZABER_TRAVEL_STEPS: i64 = 1_000_000;

/// Errors starting the simulated bench.
#[derive(Debug, Error)]
pub enum BenchError {
    /// A pseudo-terminal could not be opened or linked.
    #[error("cannot serve the {what} simulator: {source}")]
    Pty {
        /// `stage` or `force sensor`.
        what: &'static str,
        /// The cause.
        source: PtyError,
    },
    /// The simulated Net F/T's sockets could not be set up.
    #[error(transparent)]
    NetFt(#[from] NetFtSimError),
    /// The links directory or the camera socket could not be set up.
    #[error("{path}: {source}")]
    Io {
        /// The path.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
}

/// Which stage protocol to simulate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StageProtocol {
    /// GRBL 1.1 (machine coordinates ≤ 0, +z up).
    Grbl,
    /// Zaber ASCII, three single-axis devices (1, 2, 3 = x, y, z).
    Zaber,
    /// Marlin on a CR-10-like printer (travel 300 × 300 × 100 mm, +z up).
    Marlin,
}

/// Which force-sensor protocol to simulate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FtProtocol {
    /// WACOH DynPick.
    DynPick,
    /// Robotiq FT 300.
    Ft300,
    /// ATI Net F/T (loopback UDP and TCP).
    NetFt,
    /// Bota Systems serial sensor.
    Bota,
}

/// Where a simulated force sensor is reached.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FtEndpoint<'a> {
    /// A pseudo-terminal (its symlink).
    Serial(&'a Path),
    /// Loopback sockets: the RDT (UDP) address and the calibration (TCP) address.
    Network {
        /// UDP address of the RDT stream.
        rdt: std::net::SocketAddr,
        /// TCP address of the calibration query.
        cal: Option<std::net::SocketAddr>,
    },
}

impl std::fmt::Display for FtEndpoint<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FtEndpoint::Serial(p) => write!(f, "{}", p.display()),
            FtEndpoint::Network { rdt, cal } => {
                write!(f, "{} --rdt-port {}", rdt.ip(), rdt.port())?;
                if let Some(c) = cal {
                    write!(f, " --cal-port {}", c.port())?;
                }
                Ok(())
            }
        }
    }
}

impl StageProtocol {
    /// Where the sensor sits for this kind of stage, and where the stage starts.
    ///
    /// GRBL: travel `[-200, 0]` mm per axis (GRBL defaults), +z up: the sensor origin
    /// at stage xy (−100, −100), the surface at z = −30 mm, pressing towards −z;
    /// the stage starts at the origin (30 mm above the surface).
    /// Zaber: travel 0–47.6 mm, +z pressing: the sensor origin at stage xy (15, 15),
    /// the surface at z = 30 mm; the stage starts mid-travel (23.8 mm, above it).
    /// Marlin: travel 0..300 × 0..300 × 0..100 mm (soft endstops), +z up: the sensor
    /// on the bed with its origin at stage xy (150, 150), the surface at z = 30 mm,
    /// pressing towards −z; the head starts (homed) over the origin at z = 60 mm,
    /// 30 mm above the surface, as the GRBL bench does.
    pub fn default_geometry(self) -> (WorldGeometry, [f64; 3]) {
        match self {
            StageProtocol::Grbl => (
                WorldGeometry {
                    sensor_origin_in_stage_mm: [-100.0, -100.0],
                    surface_z_mm: -30.0,
                    press_direction: -1.0,
                    ..WorldGeometry::default()
                },
                [0.0; 3],
            ),
            StageProtocol::Zaber => {
                let mid = ZABER_TRAVEL_STEPS as f64 / 2.0 * DEFAULT_MM_PER_STEP;
                (
                    WorldGeometry {
                        sensor_origin_in_stage_mm: [15.0, 15.0],
                        surface_z_mm: 30.0,
                        press_direction: 1.0,
                        ..WorldGeometry::default()
                    },
                    [mid; 3],
                )
            }
            StageProtocol::Marlin => (
                WorldGeometry {
                    sensor_origin_in_stage_mm: [150.0, 150.0],
                    surface_z_mm: 30.0,
                    press_direction: -1.0,
                    ..WorldGeometry::default()
                },
                [150.0, 150.0, 60.0],
            ),
        }
    }
}

/// A stage simulator that tells the world where the stage is.
pub struct WorldStage<S> {
    sim: S,
    world: Arc<World>,
    position_mm: fn(&S) -> [f64; 3],
}

impl<S> WorldStage<S> {
    /// Wraps `sim`; `position_mm` reads its current position in mm.
    pub fn new(sim: S, world: Arc<World>, position_mm: fn(&S) -> [f64; 3]) -> Self {
        WorldStage {
            sim,
            world,
            position_mm,
        }
    }

    /// The wrapped simulator.
    pub fn inner(&self) -> &S {
        &self.sim
    }
}

impl<S: Simulator> Simulator for WorldStage<S> {
    fn step(&mut self, now: Duration, input: &[u8], output: &mut Vec<u8>) -> Flow {
        let flow = self.sim.step(now, input, output);
        self.world.set_stage_mm((self.position_mm)(&self.sim));
        flow
    }

    fn next_wake(&self, now: Duration) -> Option<Duration> {
        Some(
            self.sim
                .next_wake(now)
                .map_or(WORLD_TICK, |w| w.min(WORLD_TICK)),
        )
    }
}

fn grbl_position(s: &GrblSim) -> [f64; 3] {
    s.mpos_mm()
}

fn marlin_position(s: &MarlinSim) -> [f64; 3] {
    s.position_mm()
}

fn zaber_position(s: &ZaberSim) -> [f64; 3] {
    let mut p = [0.0; 3];
    for (i, dev) in [1u8, 2, 3].into_iter().enumerate() {
        if let Some(a) = s.axis(dev, 1) {
            p[i] = a.pos * DEFAULT_MM_PER_STEP;
        }
    }
    p
}

/// The world as the force sensor's load.
#[derive(Debug, Clone)]
pub struct WorldWrench(pub Arc<World>);

impl WrenchSource for WorldWrench {
    fn wrench_at(&mut self, _t: Duration) -> Wrench {
        self.0.wrench()
    }
}

enum StageServer {
    Grbl(PtyServer<WorldStage<GrblSim>>),
    Zaber(PtyServer<WorldStage<ZaberSim>>),
    Marlin(PtyServer<WorldStage<MarlinSim>>),
}

enum FtServer {
    DynPick(PtyServer<DynPickSim>),
    Ft300(PtyServer<Ft300Sim>),
    NetFt(NetFtServer),
    Bota(PtyServer<BotaSim>),
}

/// Options of [`VirtualBench::start_with`] beyond the scene and protocols.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BenchOptions {
    /// Geometry; `None`: the stage kind's default.
    pub geometry: Option<WorldGeometry>,
    /// Stage start position, mm; `None`: the stage kind's default.
    pub start_mm: Option<[f64; 3]>,
    /// Opt-in faults of the stage simulator.
    pub stage_faults: Option<FaultConfig>,
    /// Opt-in faults of the force-sensor simulator.
    pub ft_faults: Option<FaultConfig>,
}

/// A running simulated bench; everything stops and the links are removed when dropped.
pub struct VirtualBench {
    world: Arc<World>,
    stage: StageServer,
    ft: FtServer,
    camera: CameraServer,
    links: PathBuf,
}

impl VirtualBench {
    /// Starts the bench for `scene` with links `DIR/stage`, `DIR/ft` and
    /// `DIR/camera.sock`. `geometry` overrides the stage kind's default geometry.
    pub fn start(
        scene: &Scene,
        stage: StageProtocol,
        ft: FtProtocol,
        links: &Path,
        geometry: Option<WorldGeometry>,
    ) -> Result<VirtualBench, BenchError> {
        Self::start_with(
            scene,
            stage,
            ft,
            links,
            BenchOptions {
                geometry,
                ..BenchOptions::default()
            },
        )
    }

    /// [`VirtualBench::start`] with a start position and opt-in simulator faults. The
    /// scene's `[bench]` effects (force relaxation, F/T noise, a carried sensor) apply.
    pub fn start_with(
        scene: &Scene,
        stage: StageProtocol,
        ft: FtProtocol,
        links: &Path,
        options: BenchOptions,
    ) -> Result<VirtualBench, BenchError> {
        std::fs::create_dir_all(links).map_err(|source| BenchError::Io {
            path: links.to_path_buf(),
            source,
        })?;
        let (default_geometry, default_start_mm) = stage.default_geometry();
        let geometry = options.geometry.unwrap_or(default_geometry);
        let start_mm = options.start_mm.unwrap_or(default_start_mm);
        let sim = Simulation::from_scene(scene);
        let world = World::with_effects(sim, scene.indenter, geometry, start_mm, scene.bench);

        let stage_link = links.join("stage");
        let pty = |what| move |source| BenchError::Pty { what, source };
        let stage = match stage {
            StageProtocol::Grbl => {
                let cfg = GrblSimConfig {
                    start_mpos_mm: start_mm,
                    faults: options.stage_faults.clone(),
                    ..GrblSimConfig::default()
                };
                let s = WorldStage::new(GrblSim::new(cfg), Arc::clone(&world), grbl_position);
                StageServer::Grbl(PtyServer::spawn(s, Some(&stage_link)).map_err(pty("stage"))?)
            }
            StageProtocol::Zaber => {
                let mut cfg = ZaberSimConfig::three_single_axis(ZABER_TRAVEL_STEPS);
                cfg.faults = options.stage_faults.clone();
                let steps = |mm: f64| (mm / DEFAULT_MM_PER_STEP).round() as i64;
                for (i, dev) in [1u8, 2, 3].into_iter().enumerate() {
                    if let Some(axes) = cfg.devices.get_mut(&dev) {
                        for a in axes.iter_mut() {
                            a.pos = steps(start_mm[i]) as f64;
                        }
                    }
                }
                let s = WorldStage::new(ZaberSim::new(cfg), Arc::clone(&world), zaber_position);
                StageServer::Zaber(PtyServer::spawn(s, Some(&stage_link)).map_err(pty("stage"))?)
            }
            StageProtocol::Marlin => {
                let cfg = MarlinSimConfig {
                    start_mm,
                    faults: options.stage_faults.clone(),
                    ..MarlinSimConfig::default()
                };
                let s = WorldStage::new(MarlinSim::new(cfg), Arc::clone(&world), marlin_position);
                StageServer::Marlin(PtyServer::spawn(s, Some(&stage_link)).map_err(pty("stage"))?)
            }
        };
        let ft_link = links.join("ft");
        let source = WorldWrench(Arc::clone(&world));
        let ft = match ft {
            FtProtocol::DynPick => FtServer::DynPick(
                PtyServer::spawn(
                    DynPickSim::new(
                        DynPickSimConfig {
                            faults: options.ft_faults.clone().unwrap_or_else(no_faults),
                            ..DynPickSimConfig::default()
                        },
                        source,
                    ),
                    Some(&ft_link),
                )
                .map_err(pty("force sensor"))?,
            ),
            FtProtocol::Ft300 => FtServer::Ft300(
                PtyServer::spawn(
                    Ft300Sim::new(
                        Ft300SimConfig {
                            faults: options.ft_faults.clone().unwrap_or_else(no_faults),
                            ..Ft300SimConfig::default()
                        },
                        source,
                    ),
                    Some(&ft_link),
                )
                .map_err(pty("force sensor"))?,
            ),
            FtProtocol::NetFt => FtServer::NetFt(NetFtServer::spawn(
                NetFtCore::new(
                    NetFtSimConfig {
                        faults: options.ft_faults.clone().unwrap_or_else(no_faults),
                        ..NetFtSimConfig::default()
                    },
                    source,
                ),
                0,
                0,
            )?),
            FtProtocol::Bota => FtServer::Bota(
                PtyServer::spawn(
                    BotaSim::new(
                        BotaSimConfig {
                            faults: options.ft_faults.clone().unwrap_or_else(no_faults),
                            ..BotaSimConfig::default()
                        },
                        source,
                    ),
                    Some(&ft_link),
                )
                .map_err(pty("force sensor"))?,
            ),
        };
        let camera = CameraServer::start(&links.join("camera.sock"), Arc::clone(&world))?;
        Ok(VirtualBench {
            world,
            stage,
            ft,
            camera,
            links: links.to_path_buf(),
        })
    }

    /// The shared world.
    pub fn world(&self) -> &Arc<World> {
        &self.world
    }

    /// The stage's port (a symlink to its pseudo-terminal).
    pub fn stage_port(&self) -> &Path {
        match &self.stage {
            StageServer::Grbl(s) => s.port_path(),
            StageServer::Zaber(s) => s.port_path(),
            StageServer::Marlin(s) => s.port_path(),
        }
    }

    /// The stage's pseudo-terminal itself (`/dev/pts/N`), whatever the link's name.
    pub fn stage_device(&self) -> &Path {
        match &self.stage {
            StageServer::Grbl(s) => s.path(),
            StageServer::Zaber(s) => s.path(),
            StageServer::Marlin(s) => s.path(),
        }
    }

    /// The force sensor's pseudo-terminal itself (`/dev/pts/N`); `None` for the
    /// simulated Net F/T, which is served on loopback sockets.
    pub fn ft_device(&self) -> Option<&Path> {
        match &self.ft {
            FtServer::DynPick(s) => Some(s.path()),
            FtServer::Ft300(s) => Some(s.path()),
            FtServer::Bota(s) => Some(s.path()),
            FtServer::NetFt(_) => None,
        }
    }

    /// Where the force sensor is reached: a symlink to its pseudo-terminal, or the
    /// simulated Net F/T's loopback addresses.
    pub fn ft_endpoint(&self) -> FtEndpoint<'_> {
        match &self.ft {
            FtServer::DynPick(s) => FtEndpoint::Serial(s.port_path()),
            FtServer::Ft300(s) => FtEndpoint::Serial(s.port_path()),
            FtServer::Bota(s) => FtEndpoint::Serial(s.port_path()),
            FtServer::NetFt(s) => FtEndpoint::Network {
                rdt: s.rdt_addr(),
                cal: s.cal_addr(),
            },
        }
    }

    /// The camera socket.
    pub fn camera_socket(&self) -> &Path {
        &self.camera.path
    }

    /// The links directory.
    pub fn links(&self) -> &Path {
        &self.links
    }

    /// True once a simulator ended (a simulated disconnect).
    pub fn is_finished(&self) -> bool {
        let stage = match &self.stage {
            StageServer::Grbl(s) => s.is_finished(),
            StageServer::Zaber(s) => s.is_finished(),
            StageServer::Marlin(s) => s.is_finished(),
        };
        let ft = match &self.ft {
            FtServer::DynPick(s) => s.is_finished(),
            FtServer::Ft300(s) => s.is_finished(),
            FtServer::Bota(s) => s.is_finished(),
            FtServer::NetFt(s) => s.is_finished(),
        };
        stage || ft
    }
}

/// Serves camera frames on a Unix socket, one thread per client.
struct CameraServer {
    path: PathBuf,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl CameraServer {
    fn start(path: &Path, world: Arc<World>) -> Result<CameraServer, BenchError> {
        let io = |source| BenchError::Io {
            path: path.to_path_buf(),
            source,
        };
        // A socket file left by a killed run would make bind fail: replace it.
        if path.exists() {
            std::fs::remove_file(path).map_err(io)?;
        }
        let listener = UnixListener::bind(path).map_err(io)?;
        listener.set_nonblocking(true).map_err(io)?;
        let stop = Arc::new(AtomicBool::new(false));
        let flag = Arc::clone(&stop);
        let thread = std::thread::Builder::new()
            .name("sim-camera".into())
            .spawn(move || accept_loop(listener, world, flag))
            .map_err(io)?;
        Ok(CameraServer {
            path: path.to_path_buf(),
            stop,
            thread: Some(thread),
        })
    }
}

impl Drop for CameraServer {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        let _ = std::fs::remove_file(&self.path);
    }
}

fn accept_loop(listener: UnixListener, world: Arc<World>, stop: Arc<AtomicBool>) {
    let mut clients = Vec::new();
    while !stop.load(Ordering::SeqCst) {
        match listener.accept() {
            Ok((stream, _)) => {
                let world = Arc::clone(&world);
                let stop = Arc::clone(&stop);
                if let Ok(t) = std::thread::Builder::new()
                    .name("sim-camera-client".into())
                    .spawn(move || serve_client(stream, &world, &stop))
                {
                    clients.push(t);
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(5));
            }
            Err(_) => std::thread::sleep(Duration::from_millis(5)),
        }
        clients.retain(|t: &JoinHandle<()>| !t.is_finished());
    }
    for t in clients {
        let _ = t.join();
    }
}

/// One client: answers `grab` / `reference` lines until it hangs up or the bench stops.
fn serve_client(stream: UnixStream, world: &World, stop: &AtomicBool) {
    let _ = stream.set_read_timeout(Some(Duration::from_millis(100)));
    let Ok(mut writer) = stream.try_clone() else {
        return;
    };
    let mut reader = BufReader::new(stream);
    let mut frame = world.blank_frame();
    let mut line = String::new();
    while !stop.load(Ordering::SeqCst) {
        line.clear();
        match reader.read_line(&mut line) {
            Ok(0) => return,
            Ok(_) => {}
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                continue;
            }
            Err(_) => return,
        }
        let rendered = match line.trim() {
            "grab" => world.render(&mut frame).map(|t| t.frame),
            "reference" => world.render_reference(&mut frame).map(|t| t.frame),
            other => {
                let _ = writeln!(
                    writer,
                    "error unknown request `{other}`: expected grab or reference"
                );
                continue;
            }
        };
        let reply = match rendered {
            Ok(index) => {
                let img = to_rgb8(&frame);
                let ns = SystemTime::now()
                    .duration_since(UNIX_EPOCH)
                    .map(|d| d.as_nanos())
                    .unwrap_or(0);
                writeln!(
                    writer,
                    "ok {} {} {} {}",
                    img.width(),
                    img.height(),
                    index,
                    ns
                )
                .and_then(|_| writer.write_all(img.as_raw()))
            }
            Err(e) => writeln!(writer, "error {e}"),
        };
        if reply.and_then(|_| writer.flush()).is_err() {
            return;
        }
    }
}
