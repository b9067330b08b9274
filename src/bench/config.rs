//! `bench.toml`: which devices a run drives (or the simulated bench), and where the
//! sensor sits in the stage's coordinates. Parsed once into a validated
//! [`BenchConfig`]; errors name the file, the key, the value and its unit, like plans.
//!
//! A real bench:
//!
//! ```toml
//! [stage]
//! protocol = "grbl"                 # grbl | zaber | marlin
//! port = "/dev/ttyUSB0"
//! baud = 115200                     # optional (grbl, zaber, marlin: 115200; many
//!                                   # Marlin printers use 250000)
//! # zaber only: devices = [1, 2, 3] (x, y, z addresses), mm_per_step = 0.000047625
//! # marlin only: max_feed_mm_min = [18000.0, 18000.0, 600.0] (x, y, z; used only
//! #   when the firmware does not report M203; a feed above it is refused)
//! travel_min_mm = [-200.0, -200.0, -200.0]  # optional, stage machine coordinates:
//! travel_max_mm = [0.0, 0.0, 0.0]           # what `run --dry-run` checks targets
//!                                   # against; a GRBL driver also enforces it on
//!                                   # every move (with GRBL's own [-$13x, 0] where
//!                                   # homing $22=1 and soft limits $20=1 are on)
//!
//! [force_sensor]
//! protocol = "dynpick"              # dynpick | ft300 | bota (serial); netft | onrobot-hex (network)
//! port = "/dev/ttyUSB1"             # serial sensors
//! baud = 921600                     # optional (dynpick 921600, ft300 19200, bota 460800)
//! # network sensors instead: host = "192.168.1.1", rdt_port = 49152 (UDP, optional),
//! # cal_port = 49151 (TCP READCALINFO, optional, netft only); counts_per_force /
//! # counts_per_torque (optional, both or neither) override the device's calibration
//! # (netft, with a warning) or the HEX's fixed scale
//!
//! [camera]
//! device = "0"                      # V4L2 index, "dir:PATH" (recorded frames) or
//!                                   # "sim:PATH" (a simulated bench's camera.sock)
//!
//! [geometry]                        # stage machine coordinates, mm
//! sensor_origin_in_stage_mm = [-100.0, -100.0]  # stage x, y with the tip over the
//!                                               # sensor-frame origin
//! surface_z_mm = -30.0              # stage z where the tip touches the surface
//! press_direction = -1              # -1: decreasing z presses (GRBL, +z up); +1
//! clearance_mm = 1.0                # retract height above the surface for lateral moves
//! home = false                      # run the homing cycle at start and on resume
//! tare = true                       # tare the F/T sensor unloaded at start / resume
//!
//! [safety]                          # optional
//! max_force_n = [3.0, 3.0, 10.0]    # |fx|, |fy|, |fz| limits in N that `tactbench
//!                                   # stage --bench` watches while moving (a run
//!                                   # uses its plan's safety.max_force)
//! ```
//!
//! The simulated bench (the same drivers, talking to simulators on pseudo-terminals):
//!
//! ```toml
//! [sim]
//! scene = "scenes/fig7_hemisphere_ramp.toml"   # relative to this file
//! stage = "grbl"                    # optional: grbl (default) | zaber | marlin
//! force_sensor = "dynpick"          # optional: dynpick (default) | ft300 | netft | bota
//! friction = 1.0                    # optional: indenter/elastomer friction μ
//!                                   # (default: the scene's load.friction_coefficient)
//! # [geometry] optional: defaults from the stage kind (see sim::bench)
//! ```
//!
//! The contact surface only needs to be known roughly: the runner approaches from
//! `clearance_mm` above it and detects contact on the force reading.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::config::{self, Checker, ConfigError};
use crate::device::camera::CameraSpec;
use crate::device::TravelLimits;

/// Which stage protocol.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StageKind {
    /// GRBL 1.1.
    Grbl,
    /// Zaber ASCII.
    Zaber,
    /// Marlin (3D printers, small CNCs).
    Marlin,
}

/// Which force-sensor protocol.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FtKind {
    /// WACOH DynPick.
    DynPick,
    /// Robotiq FT 300.
    Ft300,
    /// ATI Net F/T (network: RDT over UDP, calibration over TCP).
    NetFt,
    /// OnRobot HEX (network: the Net F/T's RDT records, fixed scale).
    OnRobotHex,
    /// Bota Systems serial sensor.
    Bota,
}

impl FtKind {
    /// The protocol's name in bench files and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            FtKind::DynPick => "dynpick",
            FtKind::Ft300 => "ft300",
            FtKind::NetFt => "netft",
            FtKind::OnRobotHex => "onrobot-hex",
            FtKind::Bota => "bota",
        }
    }

    /// Whether the sensor is reached over the network (a host) rather than a port.
    pub fn is_network(self) -> bool {
        matches!(self, FtKind::NetFt | FtKind::OnRobotHex)
    }
}

/// Where a network force sensor is.
#[derive(Debug, Clone, PartialEq)]
pub struct NetFtConfig {
    /// Host name or address.
    pub host: String,
    /// UDP port of the RDT stream (49152).
    pub rdt_port: u16,
    /// TCP port of the calibration query (49151).
    pub cal_port: u16,
    /// Counts per N and per N·m given in the bench file (overrides the device).
    pub counts_override: Option<[f64; 2]>,
}

/// A real stage.
#[derive(Debug, Clone, PartialEq)]
pub struct StageConfig {
    /// Protocol.
    pub protocol: StageKind,
    /// Serial port path.
    pub port: String,
    /// Baud rate.
    pub baud: u32,
    /// Zaber: device addresses of x, y, z.
    pub zaber_devices: [u8; 3],
    /// Zaber: resolution, mm per microstep.
    pub zaber_mm_per_step: f64,
    /// Marlin: maximum feed rates x, y, z in mm/min, for firmware that does not
    /// report `M203`.
    pub marlin_max_feed_mm_min: Option<[f64; 3]>,
    /// The stage's travel box as the bench file states it (`travel_min_mm`,
    /// `travel_max_mm`), for dry runs; `None` when not given.
    pub travel: Option<TravelLimits>,
}

/// A real force sensor.
#[derive(Debug, Clone, PartialEq)]
pub struct FtConfig {
    /// Protocol.
    pub protocol: FtKind,
    /// Serial port path (empty for a network sensor).
    pub port: String,
    /// Baud rate.
    pub baud: u32,
    /// A network sensor's address and calibration override.
    pub network: Option<NetFtConfig>,
}

/// Where the sensor is in stage coordinates (mm) and how to approach it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BenchGeometry {
    /// Stage x, y with the tip over the sensor-frame origin, mm.
    pub sensor_origin_in_stage_mm: [f64; 2],
    /// Stage z where the tip touches the surface, mm.
    pub surface_z_mm: f64,
    /// +1: increasing stage z presses; −1: decreasing z presses.
    pub press_direction: f64,
    /// Retract height above the surface, mm (> 0).
    pub clearance_mm: f64,
}

impl BenchGeometry {
    /// The geometry as the manifest records it (`bench.geometry`: the keys of the
    /// bench file's `[geometry]`), so a run's stage coordinates can be read back into
    /// depths and sensor-frame points (e.g. by `tactbench fit`).
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({
            "sensor_origin_in_stage_mm": self.sensor_origin_in_stage_mm,
            "surface_z_mm": self.surface_z_mm,
            "press_direction": self.press_direction,
            "clearance_mm": self.clearance_mm,
        })
    }

    /// The geometry recorded in a manifest's `bench` description (`bench.geometry`,
    /// see [`BenchGeometry::to_json`]); `None` when it was not recorded (runs made
    /// before it was) or is incomplete.
    pub fn from_manifest_bench(bench: &serde_json::Value) -> Option<BenchGeometry> {
        let g = bench.get("geometry")?;
        let num = |k: &str| g.get(k).and_then(serde_json::Value::as_f64);
        let origin = g.get("sensor_origin_in_stage_mm")?.as_array()?;
        let (x, y) = (origin.first()?.as_f64()?, origin.get(1)?.as_f64()?);
        Some(BenchGeometry {
            sensor_origin_in_stage_mm: [x, y],
            surface_z_mm: num("surface_z_mm")?,
            press_direction: num("press_direction")?,
            clearance_mm: num("clearance_mm")?,
        })
    }

    /// Stage x, y of a sensor-frame point, mm.
    pub fn stage_xy(&self, sensor_xy_mm: [f64; 2]) -> [f64; 2] {
        [
            sensor_xy_mm[0] + self.sensor_origin_in_stage_mm[0],
            sensor_xy_mm[1] + self.sensor_origin_in_stage_mm[1],
        ]
    }

    /// Sensor-frame x, y of a stage position, mm.
    pub fn sensor_xy(&self, stage_mm: [f64; 3]) -> [f64; 2] {
        [
            stage_mm[0] - self.sensor_origin_in_stage_mm[0],
            stage_mm[1] - self.sensor_origin_in_stage_mm[1],
        ]
    }

    /// Stage z of an indentation depth (mm; negative = above the surface).
    pub fn stage_z(&self, depth_mm: f64) -> f64 {
        self.surface_z_mm + self.press_direction * depth_mm
    }

    /// Indentation depth of a stage z, mm.
    pub fn depth(&self, stage_z_mm: f64) -> f64 {
        self.press_direction * (stage_z_mm - self.surface_z_mm)
    }

    /// The stage position of a sensor-frame point at a depth.
    pub fn stage_point(&self, sensor_xy_mm: [f64; 2], depth_mm: f64) -> [f64; 3] {
        let xy = self.stage_xy(sensor_xy_mm);
        [xy[0], xy[1], self.stage_z(depth_mm)]
    }
}

/// The simulated bench.
#[derive(Debug, Clone, PartialEq)]
pub struct SimConfig {
    /// The scene file, resolved.
    pub scene: PathBuf,
    /// Stage protocol to simulate.
    pub stage: StageKind,
    /// Force-sensor protocol to simulate.
    pub force_sensor: FtKind,
    /// Friction coefficient; `None`: the scene's `load.friction_coefficient`.
    pub friction: Option<f64>,
}

/// What the run drives.
#[derive(Debug, Clone, PartialEq)]
pub enum BenchDevices {
    /// Real devices.
    Hardware {
        /// The stage.
        stage: StageConfig,
        /// The force sensor.
        force_sensor: FtConfig,
        /// The camera.
        camera: CameraSpec,
    },
    /// The simulated bench, started in-process.
    Sim(SimConfig),
}

/// A validated bench file.
#[derive(Debug, Clone, PartialEq)]
pub struct BenchConfig {
    /// The file (for messages and the manifest).
    pub path: PathBuf,
    /// The devices.
    pub devices: BenchDevices,
    /// Geometry; `None` for a simulated bench without `[geometry]` (the stage kind's
    /// defaults apply).
    pub geometry: Option<BenchGeometry>,
    /// Home at start and on resume.
    pub home: bool,
    /// Tare the force sensor unloaded at start and on resume.
    pub tare: bool,
    /// `[safety] max_force_n`: per-component force limits |fx|, |fy|, |fz| in N that
    /// `tactbench stage --bench` watches while it moves (a run uses its plan's
    /// `safety.max_force`); `None` when the file has no `[safety]`.
    pub max_force_n: Option<[f64; 3]>,
}

impl BenchConfig {
    /// Reads and validates a bench file.
    pub fn from_path(path: impl AsRef<Path>) -> Result<BenchConfig, ConfigError> {
        let path = path.as_ref();
        let text = config::read_text(path, "bench file")?;
        BenchConfig::from_toml_str(&text, path)
    }

    /// Parses bench TOML; `path` resolves the scene and names errors.
    pub fn from_toml_str(text: &str, path: impl AsRef<Path>) -> Result<BenchConfig, ConfigError> {
        let path = path.as_ref();
        let raw: RawBench = config::parse_toml(text, path)?;
        raw.validate(path)
    }

    /// A simulated bench for `scene` with the default protocols (what `run --sim` uses).
    pub fn sim(scene: &Path) -> BenchConfig {
        BenchConfig {
            path: scene.to_path_buf(),
            devices: BenchDevices::Sim(SimConfig {
                scene: scene.to_path_buf(),
                stage: StageKind::Grbl,
                force_sensor: FtKind::DynPick,
                friction: None,
            }),
            geometry: None,
            home: false,
            tare: true,
            max_force_n: None,
        }
    }
}

// ---- raw schema ---------------------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawBench {
    stage: Option<RawStage>,
    force_sensor: Option<RawFt>,
    camera: Option<RawCamera>,
    sim: Option<RawSim>,
    geometry: Option<RawGeometry>,
    safety: Option<RawSafety>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSafety {
    #[serde(deserialize_with = "crate::config::exact")]
    max_force_n: [f64; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawStage {
    protocol: String,
    port: String,
    baud: Option<i64>,
    #[serde(default, deserialize_with = "crate::config::exact_opt")]
    devices: Option<[i64; 3]>,
    mm_per_step: Option<f64>,
    #[serde(default, deserialize_with = "crate::config::exact_opt")]
    max_feed_mm_min: Option<[f64; 3]>,
    #[serde(default, deserialize_with = "crate::config::exact_opt")]
    travel_min_mm: Option<[f64; 3]>,
    #[serde(default, deserialize_with = "crate::config::exact_opt")]
    travel_max_mm: Option<[f64; 3]>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawFt {
    protocol: String,
    port: Option<String>,
    baud: Option<i64>,
    host: Option<String>,
    rdt_port: Option<i64>,
    cal_port: Option<i64>,
    counts_per_force: Option<f64>,
    counts_per_torque: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCamera {
    device: toml::Value,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSim {
    scene: String,
    stage: Option<String>,
    force_sensor: Option<String>,
    friction: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawGeometry {
    #[serde(deserialize_with = "crate::config::exact")]
    sensor_origin_in_stage_mm: [f64; 2],
    surface_z_mm: f64,
    press_direction: i64,
    #[serde(default = "default_clearance")]
    clearance_mm: f64,
    home: Option<bool>,
    #[serde(default = "default_true")]
    tare: bool,
}

fn default_clearance() -> f64 {
    1.0
}

fn default_true() -> bool {
    true
}

fn stage_kind(c: &Checker<'_>, key: &str, v: &str) -> Result<StageKind, ConfigError> {
    match v {
        "grbl" => Ok(StageKind::Grbl),
        "zaber" => Ok(StageKind::Zaber),
        "marlin" => Ok(StageKind::Marlin),
        other => Err(c.invalid(
            key,
            format!("{other:?}"),
            "unknown stage protocol: expected grbl, zaber or marlin",
        )),
    }
}

fn ft_kind(c: &Checker<'_>, key: &str, v: &str) -> Result<FtKind, ConfigError> {
    match v {
        "dynpick" => Ok(FtKind::DynPick),
        "ft300" => Ok(FtKind::Ft300),
        "netft" => Ok(FtKind::NetFt),
        "onrobot-hex" => Ok(FtKind::OnRobotHex),
        "bota" => Ok(FtKind::Bota),
        other => Err(c.invalid(
            key,
            format!("{other:?}"),
            "unknown force-sensor protocol: expected dynpick, ft300, bota, netft or onrobot-hex",
        )),
    }
}

fn baud(c: &Checker<'_>, key: &str, v: Option<i64>, default: u32) -> Result<u32, ConfigError> {
    match v {
        None => Ok(default),
        Some(b) if (50..=4_000_000).contains(&b) => Ok(b as u32),
        Some(b) => Err(c.invalid(key, b, "must be a baud rate in [50, 4000000]")),
    }
}

impl RawBench {
    /// Checks the sections in the order their errors are reported — `[geometry]`,
    /// `[safety]`, then the simulated bench or the three hardware devices — and builds
    /// the bench.
    fn validate(self, path: &Path) -> Result<BenchConfig, ConfigError> {
        let c = Checker { path };
        let geometry = self.geometry.as_ref().map(|g| g.validate(&c)).transpose()?;
        let tare = self.geometry.as_ref().is_none_or(|g| g.tare);
        let max_force_n = self.safety.as_ref().map(|sf| sf.validate(&c)).transpose()?;
        let home_given = self.geometry.as_ref().and_then(|g| g.home);

        if let Some(s) = self.sim {
            let hardware_given = [
                ("stage", self.stage.is_some()),
                ("force_sensor", self.force_sensor.is_some()),
                ("camera", self.camera.is_some()),
            ];
            return Ok(BenchConfig {
                path: path.to_path_buf(),
                devices: BenchDevices::Sim(s.validate(&c, hardware_given)?),
                geometry,
                home: home_given.unwrap_or(false),
                tare,
                max_force_n,
            });
        }

        let missing = |key: &str| {
            c.invalid(
                key,
                "(missing)",
                "a bench needs [stage], [force_sensor] and [camera] (or [sim] with a scene)",
            )
        };
        let s = self.stage.ok_or_else(|| missing("stage"))?;
        let f = self.force_sensor.ok_or_else(|| missing("force_sensor"))?;
        let cam = self.camera.ok_or_else(|| missing("camera"))?;
        let geometry = geometry.ok_or_else(|| {
            c.invalid(
                "geometry",
                "(missing)",
                "a hardware bench needs [geometry]: sensor_origin_in_stage_mm, surface_z_mm, press_direction",
            )
        })?;
        let stage = s.validate(&c)?;
        let force_sensor = ft_config(&c, f)?;
        let camera = cam.validate(&c)?;
        // Zaber stages lose their reference at power-up, and so does a Marlin
        // machine (which resets when the port opens): home by default.
        let home_by_default = matches!(stage.protocol, StageKind::Zaber | StageKind::Marlin);
        Ok(BenchConfig {
            path: path.to_path_buf(),
            devices: BenchDevices::Hardware {
                stage,
                force_sensor,
                camera,
            },
            geometry: Some(geometry),
            home: home_given.unwrap_or(home_by_default),
            tare,
            max_force_n,
        })
    }
}

impl RawGeometry {
    /// `[geometry]`: finite coordinates, a press direction of ±1, a positive clearance.
    fn validate(&self, c: &Checker<'_>) -> Result<BenchGeometry, ConfigError> {
        for i in 0..2 {
            c.finite(
                &format!("geometry.sensor_origin_in_stage_mm[{i}]"),
                self.sensor_origin_in_stage_mm[i],
                "mm",
            )?;
        }
        c.finite("geometry.surface_z_mm", self.surface_z_mm, "mm")?;
        if self.press_direction != 1 && self.press_direction != -1 {
            return Err(c.invalid(
                "geometry.press_direction",
                self.press_direction,
                "must be 1 (increasing z presses) or -1 (decreasing z presses)",
            ));
        }
        Ok(BenchGeometry {
            sensor_origin_in_stage_mm: self.sensor_origin_in_stage_mm,
            surface_z_mm: self.surface_z_mm,
            press_direction: self.press_direction as f64,
            clearance_mm: c.positive("geometry.clearance_mm", self.clearance_mm, "mm")?,
        })
    }
}

impl RawSafety {
    /// `[safety] max_force_n`: three positive limits, N.
    fn validate(&self, c: &Checker<'_>) -> Result<[f64; 3], ConfigError> {
        let mut v = [0.0; 3];
        for (i, f) in self.max_force_n.iter().enumerate() {
            v[i] = c.positive(&format!("safety.max_force_n[{i}]"), *f, "N")?;
        }
        Ok(v)
    }
}

impl RawSim {
    /// `[sim]`: no hardware section beside it (`hardware_given`: each section's key and
    /// whether the file has it), simulated protocols only, the scene resolved against
    /// the bench file's folder.
    fn validate(
        self,
        c: &Checker<'_>,
        hardware_given: [(&str, bool); 3],
    ) -> Result<SimConfig, ConfigError> {
        for (key, present) in hardware_given {
            if present {
                return Err(c.invalid(
                    key,
                    "(given)",
                    "a [sim] bench simulates its devices: remove [stage], [force_sensor] and [camera], or remove [sim]",
                ));
            }
        }
        let stage = match &self.stage {
            None => StageKind::Grbl,
            Some(v) => stage_kind(c, "sim.stage", v)?,
        };
        let force_sensor = match &self.force_sensor {
            None => FtKind::DynPick,
            Some(v) => ft_kind(c, "sim.force_sensor", v)?,
        };
        if force_sensor == FtKind::OnRobotHex {
            return Err(c.invalid(
                "sim.force_sensor",
                "\"onrobot-hex\"",
                "the simulated bench serves dynpick, ft300, netft or bota (the HEX shares the netft simulator: use netft)",
            ));
        }
        let friction = match self.friction {
            None => None,
            Some(v) => Some(c.non_negative("sim.friction", v, "")?),
        };
        let dir = c.path.parent().unwrap_or(Path::new("."));
        Ok(SimConfig {
            scene: dir.join(&self.scene),
            stage,
            force_sensor,
            friction,
        })
    }
}

impl RawStage {
    /// `[stage]`: the protocol, the keys that only one protocol takes, the travel box,
    /// the port and the baud rate (checked in that order).
    fn validate(self, c: &Checker<'_>) -> Result<StageConfig, ConfigError> {
        let protocol = stage_kind(c, "stage.protocol", &self.protocol)?;
        let (zaber_devices, zaber_mm_per_step) = self.zaber_keys(c, protocol)?;
        let marlin_max_feed_mm_min = self.marlin_max_feed(c, protocol)?;
        let travel = self.travel(c)?;
        let default_baud = match protocol {
            StageKind::Grbl => crate::device::grbl::DEFAULT_BAUD,
            StageKind::Zaber => crate::device::zaber::DEFAULT_BAUD,
            StageKind::Marlin => crate::device::marlin::DEFAULT_BAUD,
        };
        Ok(StageConfig {
            protocol,
            port: non_empty(c, "stage.port", self.port)?,
            baud: baud(c, "stage.baud", self.baud, default_baud)?,
            zaber_devices,
            zaber_mm_per_step,
            marlin_max_feed_mm_min,
            travel,
        })
    }

    /// Zaber's `devices` (addresses in [1, 99], default 1, 2, 3) and `mm_per_step`
    /// (positive, default the driver's); refused on other protocols.
    fn zaber_keys(
        &self,
        c: &Checker<'_>,
        protocol: StageKind,
    ) -> Result<([u8; 3], f64), ConfigError> {
        let mut zaber_devices = [1u8, 2, 3];
        if let Some(d) = self.devices {
            for (i, v) in d.iter().enumerate() {
                if !(1..=99).contains(v) {
                    return Err(c.invalid(
                        &format!("stage.devices[{i}]"),
                        v,
                        "must be a Zaber device address in [1, 99]",
                    ));
                }
                zaber_devices[i] = *v as u8;
            }
        }
        let zaber_mm_per_step = c.positive(
            "stage.mm_per_step",
            self.mm_per_step
                .unwrap_or(crate::device::zaber::DEFAULT_MM_PER_STEP),
            "mm",
        )?;
        if protocol != StageKind::Zaber && (self.devices.is_some() || self.mm_per_step.is_some()) {
            return Err(c.invalid(
                "stage.devices",
                "(given)",
                "devices and mm_per_step apply to zaber stages only",
            ));
        }
        Ok((zaber_devices, zaber_mm_per_step))
    }

    /// Marlin's `max_feed_mm_min` (three positive feeds); refused on other protocols.
    fn marlin_max_feed(
        &self,
        c: &Checker<'_>,
        protocol: StageKind,
    ) -> Result<Option<[f64; 3]>, ConfigError> {
        match self.max_feed_mm_min {
            None => Ok(None),
            Some(_) if protocol != StageKind::Marlin => Err(c.invalid(
                "stage.max_feed_mm_min",
                "(given)",
                "max_feed_mm_min applies to marlin stages only",
            )),
            Some(v) => {
                let mut out = [0.0; 3];
                for i in 0..3 {
                    out[i] = c.positive(&format!("stage.max_feed_mm_min[{i}]"), v[i], "mm/min")?;
                }
                Ok(Some(out))
            }
        }
    }

    /// The travel box: `travel_min_mm` and `travel_max_mm` both or neither, finite,
    /// each axis's maximum above its minimum.
    fn travel(&self, c: &Checker<'_>) -> Result<Option<TravelLimits>, ConfigError> {
        match (self.travel_min_mm, self.travel_max_mm) {
            (None, None) => Ok(None),
            (Some(lo), Some(hi)) => {
                let mut axes_mm = [[0.0; 2]; 3];
                for i in 0..3 {
                    let lo = c.finite(&format!("stage.travel_min_mm[{i}]"), lo[i], "mm")?;
                    let hi = c.finite(&format!("stage.travel_max_mm[{i}]"), hi[i], "mm")?;
                    if lo >= hi {
                        return Err(c.invalid(
                            &format!("stage.travel_max_mm[{i}]"),
                            format!("{hi} mm"),
                            format!("must exceed stage.travel_min_mm[{i}] = {lo} mm"),
                        ));
                    }
                    axes_mm[i] = [lo, hi];
                }
                Ok(Some(TravelLimits { axes_mm }))
            }
            (Some(_), None) | (None, Some(_)) => {
                let key = if self.travel_min_mm.is_none() {
                    "stage.travel_min_mm"
                } else {
                    "stage.travel_max_mm"
                };
                Err(c.invalid(
                    key,
                    "(missing)",
                    "give both stage.travel_min_mm and stage.travel_max_mm, or neither",
                ))
            }
        }
    }
}

impl RawCamera {
    /// `[camera] device`: a V4L2 index (number or string), `"dir:PATH"` or `"sim:PATH"`.
    fn validate(&self, c: &Checker<'_>) -> Result<CameraSpec, ConfigError> {
        let spec_text = match &self.device {
            toml::Value::String(s) => s.clone(),
            toml::Value::Integer(i) => i.to_string(),
            other => {
                return Err(c.invalid(
                    "camera.device",
                    other,
                    "expected a V4L2 index (0, 1, ...), \"dir:PATH\" or \"sim:PATH\"",
                ))
            }
        };
        CameraSpec::parse(&spec_text)
            .map_err(|e| c.invalid("camera.device", format!("{spec_text:?}"), e.message))
    }
}

/// Validates `[force_sensor]`: serial sensors need `port`, network sensors `host`, and
/// neither accepts the other's keys.
fn ft_config(c: &Checker<'_>, f: RawFt) -> Result<FtConfig, ConfigError> {
    let protocol = ft_kind(c, "force_sensor.protocol", &f.protocol)?;
    if !protocol.is_network() {
        for (key, given) in [
            ("force_sensor.host", f.host.is_some()),
            ("force_sensor.rdt_port", f.rdt_port.is_some()),
            ("force_sensor.cal_port", f.cal_port.is_some()),
            (
                "force_sensor.counts_per_force",
                f.counts_per_force.is_some(),
            ),
            (
                "force_sensor.counts_per_torque",
                f.counts_per_torque.is_some(),
            ),
        ] {
            if given {
                return Err(c.invalid(
                    key,
                    "(given)",
                    format!(
                        "{} is a serial sensor: give port (and optionally baud), not network keys",
                        protocol.name()
                    ),
                ));
            }
        }
        let default_baud = match protocol {
            FtKind::DynPick => crate::device::dynpick::driver::BAUD,
            FtKind::Ft300 => crate::device::ft300::driver::BAUD,
            _ => crate::device::bota::driver::BAUD,
        };
        let port = f.port.ok_or_else(|| {
            c.invalid(
                "force_sensor.port",
                "(missing)",
                "a serial force sensor needs port, e.g. /dev/ttyUSB1",
            )
        })?;
        return Ok(FtConfig {
            protocol,
            port: non_empty(c, "force_sensor.port", port)?,
            baud: baud(c, "force_sensor.baud", f.baud, default_baud)?,
            network: None,
        });
    }
    if let Some(p) = &f.port {
        return Err(c.invalid(
            "force_sensor.port",
            format!("{p:?}"),
            format!(
                "{} is a network sensor: give host = \"<address>\" (and optionally rdt_port, cal_port), not a serial port",
                protocol.name()
            ),
        ));
    }
    if f.baud.is_some() {
        return Err(c.invalid(
            "force_sensor.baud",
            "(given)",
            format!(
                "{} is a network sensor: it has no baud rate",
                protocol.name()
            ),
        ));
    }
    let host = f.host.ok_or_else(|| {
        c.invalid(
            "force_sensor.host",
            "(missing)",
            format!(
                "{} is a network sensor: give host = \"<address>\", e.g. \"192.168.1.1\"",
                protocol.name()
            ),
        )
    })?;
    if host.trim().is_empty() || host.contains(char::is_whitespace) {
        return Err(c.invalid(
            "force_sensor.host",
            format!("{host:?}"),
            "must be a host name or address, e.g. 192.168.1.1",
        ));
    }
    let net_port = |key: &str, v: Option<i64>, default: u16| match v {
        None => Ok(default),
        Some(p) if (1..=65535).contains(&p) => Ok(p as u16),
        Some(p) => Err(c.invalid(key, p, "must be a port number in [1, 65535]")),
    };
    let rdt_port = net_port(
        "force_sensor.rdt_port",
        f.rdt_port,
        crate::device::netft::codec::RDT_PORT,
    )?;
    let cal_port = net_port(
        "force_sensor.cal_port",
        f.cal_port,
        crate::device::netft::codec::CAL_PORT,
    )?;
    if protocol == FtKind::OnRobotHex && f.cal_port.is_some() {
        return Err(c.invalid(
            "force_sensor.cal_port",
            "(given)",
            "the OnRobot HEX has no calibration query (its scale is fixed): remove cal_port",
        ));
    }
    let counts_override = match (f.counts_per_force, f.counts_per_torque) {
        (None, None) => None,
        (Some(cf), Some(ct)) => Some([
            c.positive("force_sensor.counts_per_force", cf, "counts/N")?,
            c.positive("force_sensor.counts_per_torque", ct, "counts/(N·m)")?,
        ]),
        (Some(_), None) | (None, Some(_)) => {
            let key = if f.counts_per_force.is_none() {
                "force_sensor.counts_per_force"
            } else {
                "force_sensor.counts_per_torque"
            };
            return Err(c.invalid(
                key,
                "(missing)",
                "give both counts_per_force (counts/N) and counts_per_torque (counts/(N·m)), or neither",
            ));
        }
    };
    Ok(FtConfig {
        protocol,
        port: String::new(),
        baud: 0,
        network: Some(NetFtConfig {
            host,
            rdt_port,
            cal_port,
            counts_override,
        }),
    })
}

fn non_empty(c: &Checker<'_>, key: &str, v: String) -> Result<String, ConfigError> {
    if v.trim().is_empty() {
        Err(c.invalid(key, "\"\"", "must name a serial port, e.g. /dev/ttyUSB0"))
    } else {
        Ok(v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HW: &str = r#"
[stage]
protocol = "grbl"
port = "/dev/ttyUSB0"
[force_sensor]
protocol = "dynpick"
port = "/dev/ttyUSB1"
[camera]
device = 0
[geometry]
sensor_origin_in_stage_mm = [-100.0, -100.0]
surface_z_mm = -30.0
press_direction = -1
"#;

    fn parse(t: &str) -> Result<BenchConfig, ConfigError> {
        BenchConfig::from_toml_str(t, "experiments/bench.toml")
    }

    #[test]
    fn hardware_bench_gets_protocol_default_bauds_and_geometry() {
        let b = parse(HW).unwrap();
        let BenchDevices::Hardware {
            stage,
            force_sensor,
            camera,
        } = &b.devices
        else {
            panic!("hardware expected")
        };
        assert_eq!(stage.baud, 115_200);
        assert_eq!(force_sensor.baud, 921_600);
        assert_eq!(*camera, CameraSpec::V4l(0));
        let g = b.geometry.unwrap();
        assert_eq!(g.clearance_mm, 1.0);
        // Depth 0.5 mm on a CNC stage is 0.5 mm below the surface z.
        assert_eq!(g.stage_z(0.5), -30.5);
        assert_eq!(g.depth(-30.5), 0.5);
        assert_eq!(g.stage_xy([9.0, 6.75]), [-91.0, -93.25]);
        assert!(!b.home && b.tare);
    }

    #[test]
    fn sim_bench_resolves_the_scene_next_to_the_file() {
        let b = parse("[sim]\nscene = \"scenes/s.toml\"\nstage = \"zaber\"\n").unwrap();
        let BenchDevices::Sim(s) = &b.devices else {
            panic!("sim expected")
        };
        assert_eq!(s.scene, Path::new("experiments/scenes/s.toml"));
        assert_eq!(s.stage, StageKind::Zaber);
        assert_eq!(s.force_sensor, FtKind::DynPick);
        assert!(b.geometry.is_none());
    }

    #[test]
    fn rejects_bad_benches_naming_key_and_value() {
        let e = parse(&HW.replace("\"grbl\"", "\"marlinx\""))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("experiments/bench.toml")
                && e.contains("stage.protocol")
                && e.contains("marlinx"),
            "{e}"
        );
        let e = parse(&HW.replace("press_direction = -1", "press_direction = 0"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("geometry.press_direction = 0"), "{e}");
        let e = parse(&HW.replace("device = 0", "device = \"webcam\""))
            .unwrap_err()
            .to_string();
        assert!(e.contains("camera.device") && e.contains("webcam"), "{e}");
        let e = parse(&HW.replace("[camera]\ndevice = 0\n", ""))
            .unwrap_err()
            .to_string();
        assert!(e.contains("camera = (missing)"), "{e}");
        let e = parse(&format!("{HW}\n[sim]\nscene = \"s.toml\"\n"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("[sim]"), "{e}");
        let e = parse(&HW.replace(
            "port = \"/dev/ttyUSB1\"",
            "port = \"/dev/ttyUSB1\"\nbaud = 7",
        ))
        .unwrap_err()
        .to_string();
        assert!(e.contains("force_sensor.baud = 7"), "{e}");
    }

    #[test]
    fn network_force_sensors_take_a_host_and_reject_a_serial_port() {
        let net = HW.replace(
            "protocol = \"dynpick\"\nport = \"/dev/ttyUSB1\"",
            "protocol = \"netft\"\nhost = \"192.168.1.1\"",
        );
        let BenchDevices::Hardware { force_sensor, .. } = parse(&net).unwrap().devices else {
            panic!("hardware expected")
        };
        let n = force_sensor.network.unwrap();
        assert_eq!(
            (n.host.as_str(), n.rdt_port, n.cal_port),
            ("192.168.1.1", 49152, 49151)
        );
        assert_eq!(n.counts_override, None);
        let e = parse(&HW.replace("protocol = \"dynpick\"", "protocol = \"netft\""))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("force_sensor.port") && e.contains("network sensor") && e.contains("host"),
            "{e}"
        );
        let e = parse(&net.replace(
            "host = \"192.168.1.1\"",
            "host = \"192.168.1.1\"\ncounts_per_force = 1e6",
        ))
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("force_sensor.counts_per_torque = (missing)"),
            "{e}"
        );
        let e = parse(&net.replace("host = \"192.168.1.1\"", "host = \"h\"\nrdt_port = 70000"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("force_sensor.rdt_port = 70000"), "{e}");
        let e = parse(&HW.replace(
            "port = \"/dev/ttyUSB1\"",
            "port = \"/dev/ttyUSB1\"\nhost = \"x\"",
        ))
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("force_sensor.host") && e.contains("serial sensor"),
            "{e}"
        );
        let bota = HW.replace("\"dynpick\"", "\"bota\"");
        let BenchDevices::Hardware { force_sensor, .. } = parse(&bota).unwrap().devices else {
            panic!("hardware expected")
        };
        assert_eq!(
            (force_sensor.protocol, force_sensor.baud),
            (FtKind::Bota, 460_800)
        );
    }

    #[test]
    fn stage_travel_limits_are_optional_and_checked_in_pairs() {
        let with = HW.replace(
            "port = \"/dev/ttyUSB0\"",
            "port = \"/dev/ttyUSB0\"\ntravel_min_mm = [-200.0, -200.0, -50.0]\ntravel_max_mm = [0.0, 0.0, 0.0]",
        );
        let BenchDevices::Hardware { stage, .. } = parse(&with).unwrap().devices else {
            panic!("hardware expected")
        };
        assert_eq!(
            stage.travel.unwrap().axes_mm,
            [[-200.0, 0.0], [-200.0, 0.0], [-50.0, 0.0]]
        );
        let e = parse(&HW.replace(
            "port = \"/dev/ttyUSB0\"",
            "port = \"/dev/ttyUSB0\"\ntravel_min_mm = [0.0, 0.0, 0.0]",
        ))
        .unwrap_err()
        .to_string();
        assert!(e.contains("stage.travel_max_mm = (missing)"), "{e}");
        let e = parse(&with.replace("[0.0, 0.0, 0.0]", "[0.0, -300.0, 0.0]"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("stage.travel_max_mm[1] = -300 mm"), "{e}");
    }

    /// Every error `validate` reports, whole, for one bench a branch (and which error
    /// wins where a file has two), so splitting `validate` keeps each text and order.
    #[test]
    fn every_validate_error_keeps_its_text_and_precedence() {
        let zaber = HW.replace("\"grbl\"", "\"zaber\"");
        let marlin = HW.replace("\"grbl\"", "\"marlin\"");
        let sim = "[sim]\nscene = \"s.toml\"\n".to_string();
        let cases: Vec<(String, &str)> = vec![
            (HW.replace("[-100.0, -100.0]", "[-100.0, nan]"), "geometry.sensor_origin_in_stage_mm[1] = NaN mm is invalid: must be a finite number (mm)"),
            (HW.replace("surface_z_mm = -30.0", "surface_z_mm = inf"), "geometry.surface_z_mm = inf mm is invalid: must be a finite number (mm)"),
            (HW.replace("press_direction = -1", "press_direction = -1\nclearance_mm = 0.0"), "geometry.clearance_mm = 0 mm is invalid: must be a finite number > 0 mm"),
            (format!("{HW}\n[safety]\nmax_force_n = [3.0, -1.0, 10.0]\n"), "safety.max_force_n[1] = -1 N is invalid: must be a finite number > 0 N"),
            // [geometry] is checked before [sim] and the hardware sections.
            (format!("{}\n[sim]\nscene = \"s.toml\"\n", HW.replace("press_direction = -1", "press_direction = 2")), "geometry.press_direction = 2 is invalid: must be 1 (increasing z presses) or -1 (decreasing z presses)"),
            (format!("{HW}\n[sim]\nscene = \"s.toml\"\n"), "stage = (given) is invalid: a [sim] bench simulates its devices: remove [stage], [force_sensor] and [camera], or remove [sim]"),
            (HW.replace("[stage]\nprotocol = \"grbl\"\nport = \"/dev/ttyUSB0\"\n", "") + &sim, "force_sensor = (given) is invalid: a [sim] bench simulates its devices: remove [stage], [force_sensor] and [camera], or remove [sim]"),
            (format!("{sim}stage = \"cnc\"\n"), "sim.stage = \"cnc\" is invalid: unknown stage protocol: expected grbl, zaber or marlin"),
            (format!("{sim}force_sensor = \"onrobot-hex\"\n"), "sim.force_sensor = \"onrobot-hex\" is invalid: the simulated bench serves dynpick, ft300, netft or bota (the HEX shares the netft simulator: use netft)"),
            (format!("{sim}force_sensor = \"ati\"\n"), "sim.force_sensor = \"ati\" is invalid: unknown force-sensor protocol: expected dynpick, ft300, bota, netft or onrobot-hex"),
            (format!("{sim}friction = -0.5\n"), "sim.friction = -0.5 is invalid: must be a finite number >= 0 "),
            // [safety] is checked before the missing sections.
            ("[safety]\nmax_force_n = [0.0, 1.0, 1.0]\n".to_string(), "safety.max_force_n[0] = 0 N is invalid: must be a finite number > 0 N"),
            (String::new(), "stage = (missing) is invalid: a bench needs [stage], [force_sensor] and [camera] (or [sim] with a scene)"),
            (HW.replace("[stage]\nprotocol = \"grbl\"\nport = \"/dev/ttyUSB0\"\n", ""), "stage = (missing) is invalid: a bench needs [stage], [force_sensor] and [camera] (or [sim] with a scene)"),
            (HW.replace("[force_sensor]\nprotocol = \"dynpick\"\nport = \"/dev/ttyUSB1\"\n", ""), "force_sensor = (missing) is invalid: a bench needs [stage], [force_sensor] and [camera] (or [sim] with a scene)"),
            (HW.replace("[geometry]\nsensor_origin_in_stage_mm = [-100.0, -100.0]\nsurface_z_mm = -30.0\npress_direction = -1\n", ""), "geometry = (missing) is invalid: a hardware bench needs [geometry]: sensor_origin_in_stage_mm, surface_z_mm, press_direction"),
            (zaber.replace("port = \"/dev/ttyUSB0\"", "port = \"/dev/ttyUSB0\"\ndevices = [1, 100, 3]"), "stage.devices[1] = 100 is invalid: must be a Zaber device address in [1, 99]"),
            (zaber.replace("port = \"/dev/ttyUSB0\"", "port = \"/dev/ttyUSB0\"\nmm_per_step = 0.0"), "stage.mm_per_step = 0 mm is invalid: must be a finite number > 0 mm"),
            (HW.replace("port = \"/dev/ttyUSB0\"", "port = \"/dev/ttyUSB0\"\ndevices = [1, 2, 3]"), "stage.devices = (given) is invalid: devices and mm_per_step apply to zaber stages only"),
            (HW.replace("port = \"/dev/ttyUSB0\"", "port = \"/dev/ttyUSB0\"\nmm_per_step = 0.001"), "stage.devices = (given) is invalid: devices and mm_per_step apply to zaber stages only"),
            (HW.replace("port = \"/dev/ttyUSB0\"", "port = \"/dev/ttyUSB0\"\nmax_feed_mm_min = [1.0, 1.0, 1.0]"), "stage.max_feed_mm_min = (given) is invalid: max_feed_mm_min applies to marlin stages only"),
            (marlin.replace("port = \"/dev/ttyUSB0\"", "port = \"/dev/ttyUSB0\"\nmax_feed_mm_min = [1.0, 0.0, 1.0]"), "stage.max_feed_mm_min[1] = 0 mm/min is invalid: must be a finite number > 0 mm/min"),
            (HW.replace("port = \"/dev/ttyUSB0\"", "port = \"/dev/ttyUSB0\"\ntravel_max_mm = [0.0, 0.0, 0.0]"), "stage.travel_min_mm = (missing) is invalid: give both stage.travel_min_mm and stage.travel_max_mm, or neither"),
            (HW.replace("port = \"/dev/ttyUSB0\"", "port = \"/dev/ttyUSB0\"\ntravel_min_mm = [0.0, 0.0, 0.0]"), "stage.travel_max_mm = (missing) is invalid: give both stage.travel_min_mm and stage.travel_max_mm, or neither"),
            (HW.replace("port = \"/dev/ttyUSB0\"", "port = \"/dev/ttyUSB0\"\ntravel_min_mm = [0.0, 0.0, 0.0]\ntravel_max_mm = [1.0, 0.0, 1.0]"), "stage.travel_max_mm[1] = 0 mm is invalid: must exceed stage.travel_min_mm[1] = 0 mm"),
            (HW.replace("port = \"/dev/ttyUSB0\"", "port = \"/dev/ttyUSB0\"\ntravel_min_mm = [nan, 0.0, 0.0]\ntravel_max_mm = [1.0, 1.0, 1.0]"), "stage.travel_min_mm[0] = NaN mm is invalid: must be a finite number (mm)"),
            // The travel box is checked before the port and the baud rate.
            (HW.replace("port = \"/dev/ttyUSB0\"", "port = \"\"\nbaud = 7\ntravel_max_mm = [0.0, 0.0, 0.0]"), "stage.travel_min_mm = (missing) is invalid: give both stage.travel_min_mm and stage.travel_max_mm, or neither"),
            (HW.replace("port = \"/dev/ttyUSB0\"", "port = \" \"\nbaud = 7"), "stage.port = \"\" is invalid: must name a serial port, e.g. /dev/ttyUSB0"),
            (HW.replace("port = \"/dev/ttyUSB0\"", "port = \"/dev/ttyUSB0\"\nbaud = 7"), "stage.baud = 7 is invalid: must be a baud rate in [50, 4000000]"),
            // The stage is checked before the force sensor, the force sensor before the camera.
            (HW.replace("port = \"/dev/ttyUSB0\"", "port = \"/dev/ttyUSB0\"\nbaud = 7").replace("protocol = \"dynpick\"", "protocol = \"x\"").replace("device = 0", "device = 1.5"), "stage.baud = 7 is invalid: must be a baud rate in [50, 4000000]"),
            (HW.replace("protocol = \"dynpick\"", "protocol = \"x\"").replace("device = 0", "device = 1.5"), "force_sensor.protocol = \"x\" is invalid: unknown force-sensor protocol: expected dynpick, ft300, bota, netft or onrobot-hex"),
            (HW.replace("device = 0", "device = 1.5"), "camera.device = 1.5 is invalid: expected a V4L2 index (0, 1, ...), \"dir:PATH\" or \"sim:PATH\""),
            (HW.replace("device = 0", "device = \"dir:\""), "camera.device = \"dir:\" is invalid: `dir:` needs a directory path, e.g. dir:frames/"),
        ];
        for (text, expected) in &cases {
            let e = parse(text).unwrap_err().to_string();
            assert_eq!(
                e,
                format!("experiments/bench.toml: {expected}"),
                "bench:\n{text}"
            );
        }
        // What validate decides beside the errors: homing by default on the stages that
        // lose their reference, never on a simulated bench unless asked.
        let home = |t: &str| parse(t).unwrap().home;
        assert!(!home(HW) && home(&zaber) && home(&marlin) && !home(&sim));
        assert!(!home(&marlin.replace(
            "press_direction = -1",
            "press_direction = -1\nhome = false"
        )));
    }
}
