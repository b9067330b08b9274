//! `--dry-run`: everything a run would open checked without opening a device (the
//! scene of a simulated bench, a `dir:PATH` camera's frames), the setpoints with the
//! stage coordinates they send, an estimated duration and the limit checks (the plan's
//! travel box and force limits, the stage's travel limits as far as they are known).

use std::path::Path;

use crate::bench::config::{BenchConfig, BenchDevices, BenchGeometry, StageKind};
pub use crate::bench::plan::needs_retract;
use crate::bench::plan::{Plan, Setpoint, DEFAULT_CLEARANCE_MM};
use crate::device::camera::image_dir::ImageDirCamera;
use crate::device::camera::CameraSpec;
use crate::device::zaber::DEFAULT_MM_PER_STEP;
use crate::device::{DeviceError, TravelLimits};
use crate::sensor::Sensor;
use crate::sim::bench::ZABER_TRAVEL_STEPS;
use crate::sim::scene::{Scene, SceneError};

/// Stage coordinates one setpoint sends (machine mm), from the bench geometry.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StageTargets {
    /// Stage x, y over the setpoint (its position plus any shift), mm.
    pub xy_mm: [f64; 2],
    /// Stage z of the retract height (lateral moves, start of the approach), mm.
    pub z_clear_mm: f64,
    /// Stage z of the deepest indentation the plan allows (`safety.travel_max_mm[2]`;
    /// force control stops at the target force, usually well above it), mm.
    pub z_deepest_mm: f64,
}

/// What `--dry-run` reports: the setpoints, their stage coordinates, an estimated
/// duration and the limit checks.
#[derive(Debug, Clone, PartialEq)]
pub struct DryRun {
    /// Every setpoint, in run order (at most `plan::MAX_SETPOINTS`).
    pub setpoints: Vec<Setpoint>,
    /// The stage coordinates of each setpoint (same order), when the bench geometry
    /// is known; empty without a bench.
    pub stage: Vec<StageTargets>,
    /// Estimated duration, s.
    pub estimated_s: f64,
    /// Checks performed, each `(passed, description)`.
    pub checks: Vec<(bool, String)>,
}

/// Failing setpoints listed one by one before the rest are counted.
const LISTED_FAILURES: usize = 10;

/// Plans a run without touching any device: setpoints, their stage coordinates,
/// estimated duration and limit checks (plan box, force limits, and the stage's travel
/// limits when the bench geometry and the limits are known, see [`stage_limits_of`]).
pub fn dry_run(
    plan: &Plan,
    limit: Option<usize>,
    geometry: Option<&BenchGeometry>,
    stage_limits: Option<&TravelLimits>,
) -> DryRun {
    // Bounded: validation refused plans above plan::MAX_SETPOINTS.
    let n = plan.setpoint_count().min(limit.unwrap_or(usize::MAX));
    let setpoints: Vec<Setpoint> = plan.setpoints_iter().take(n).collect();
    let s = &plan.safety;
    let u = plan.force_unit;
    let fu = u.symbol();
    let mut checks = Vec::new();
    let max = setpoints.iter().fold([0.0f64; 3], |m, sp| {
        [
            m[0].max(sp.tangential_n[0].abs()),
            m[1].max(sp.tangential_n[1].abs()),
            m[2].max(sp.normal_n),
        ]
    });
    for (i, axis) in ["fx", "fy", "fz"].iter().enumerate() {
        checks.push((
            max[i] <= s.max_force_n[i],
            format!(
                "largest target |{axis}| {:.4} {fu} within safety.max_force[{i}] = {:.4} {fu}",
                u.from_newtons(max[i]),
                u.from_newtons(s.max_force_n[i])
            ),
        ));
    }
    let clearance = geometry.map_or(DEFAULT_CLEARANCE_MM, |g| g.clearance_mm);
    checks.push((
        -clearance >= s.travel_min_mm[2],
        format!(
            "retract height {clearance} mm above the surface within travel_min_mm[2] = {} mm",
            s.travel_min_mm[2]
        ),
    ));
    let mut stage = Vec::new();
    let mut box_failures = Vec::new();
    let mut stage_failures = Vec::new();
    for sp in &setpoints {
        let p = [
            sp.position_mm[0] + sp.shift_mm[0],
            sp.position_mm[1] + sp.shift_mm[1],
        ];
        for i in 0..2 {
            if p[i] < s.travel_min_mm[i] || p[i] > s.travel_max_mm[i] {
                box_failures.push(format!(
                    "setpoint {}: {} = {} mm outside the plan's travel box",
                    sp.index,
                    ["x", "y"][i],
                    p[i]
                ));
            }
        }
        if let Some(g) = geometry {
            let t = StageTargets {
                xy_mm: g.stage_xy(p),
                z_clear_mm: g.stage_z(-clearance),
                z_deepest_mm: g.stage_z(s.travel_max_mm[2]),
            };
            if let Some(lim) = stage_limits {
                for (what, z) in [("retract", t.z_clear_mm), ("deepest", t.z_deepest_mm)] {
                    if let Err(e) = lim.check([t.xy_mm[0], t.xy_mm[1], z]) {
                        stage_failures
                            .push(format!("setpoint {} ({what} point): stage {e}", sp.index));
                    }
                }
            }
            stage.push(t);
        }
    }
    for failures in [box_failures, stage_failures] {
        let more = failures.len().saturating_sub(LISTED_FAILURES);
        checks.extend(
            failures
                .into_iter()
                .take(LISTED_FAILURES)
                .map(|f| (false, f)),
        );
        if more > 0 {
            checks.push((false, format!("... and {more} more like these")));
        }
    }
    let stage_text = match (geometry, stage_limits) {
        (Some(_), Some(lim)) => {
            let a = lim.axes_mm;
            format!(
                " and the stage's travel limits x {}..{}, y {}..{}, z {}..{} mm (retract and deepest point of each)",
                a[0][0], a[0][1], a[1][0], a[1][1], a[2][0], a[2][1]
            )
        }
        (Some(_), None) => " (the bench file states no stage travel limits, [stage] travel_min_mm / travel_max_mm: the controller's are checked when the run starts)".to_string(),
        (None, _) => " (stage limits unknown without a bench: checked when the run starts)".to_string(),
    };
    checks.push((
        true,
        format!(
            "{} setpoint positions checked against the plan's travel box x {}..{} mm, y {}..{} mm{stage_text}",
            setpoints.len(),
            s.travel_min_mm[0],
            s.travel_max_mm[0],
            s.travel_min_mm[1],
            s.travel_max_mm[1],
        ),
    ));
    DryRun {
        estimated_s: plan.estimate_duration_s(clearance, limit),
        setpoints,
        stage,
        checks,
    }
}

/// The plan's `sweep.positions_mm` against the sensor's area: the bounding box of its
/// force grid, where forces are reconstructed. One `(passed, description)` per
/// position, none without the key (the stage's travel is checked per setpoint by
/// [`dry_run`]).
pub fn sensor_area_checks(plan: &Plan, sensor: &Sensor) -> Vec<(bool, String)> {
    let g = &sensor.force_grid;
    let lo = g.origin_mm;
    let hi = [
        g.origin_mm[0] + (g.nx.saturating_sub(1)) as f64 * g.pitch_mm,
        g.origin_mm[1] + (g.ny.saturating_sub(1)) as f64 * g.pitch_mm,
    ];
    let inside = |p: [f64; 2]| (0..2).all(|i| p[i] >= lo[i] - 1e-9 && p[i] <= hi[i] + 1e-9);
    let area = format!(
        "the sensor's force grid x {:.4}..{:.4} mm, y {:.4}..{:.4} mm ({})",
        lo[0],
        hi[0],
        lo[1],
        hi[1],
        plan.sensor_path.display()
    );
    plan.positions_mm
        .iter()
        .enumerate()
        .map(|(i, p)| {
            (
                inside(*p),
                format!(
                    "sweep.positions_mm[{i}] [{}, {}] mm {} {area}",
                    p[0],
                    p[1],
                    if inside(*p) { "within" } else { "OUTSIDE" }
                ),
            )
        })
        .collect()
}

/// Travel of each axis of the simulated GRBL stage: GRBL 1.1's default `$130..$132`
/// (the simulator's), machine coordinates `[-200, 0]` mm.
const SIM_GRBL_TRAVEL_MM: f64 = 200.0;

/// The stage's travel limits as far as they are known without opening it: the bench
/// file's `[stage] travel_min_mm / travel_max_mm`, or the simulated stage's travel.
/// Returns the limits and where they come from.
pub fn stage_limits_of(bench: &BenchConfig) -> Option<(TravelLimits, String)> {
    match &bench.devices {
        BenchDevices::Hardware { stage, .. } => stage.travel.map(|t| {
            (
                t,
                format!(
                    "{} [stage] travel_min_mm / travel_max_mm",
                    bench.path.display()
                ),
            )
        }),
        BenchDevices::Sim(cfg) => Some(match cfg.stage {
            StageKind::Grbl => (
                TravelLimits {
                    axes_mm: [[-SIM_GRBL_TRAVEL_MM, 0.0]; 3],
                },
                "the simulated GRBL stage ($130..$132 = 200 mm)".to_string(),
            ),
            StageKind::Zaber => {
                let hi = ZABER_TRAVEL_STEPS as f64 * DEFAULT_MM_PER_STEP;
                (
                    TravelLimits {
                        axes_mm: [[0.0, hi]; 3],
                    },
                    format!("the simulated Zaber stage (0..{hi} mm)"),
                )
            }
            StageKind::Marlin => {
                let c = crate::device::marlin::sim::MarlinSimConfig::default();
                (
                    TravelLimits {
                        axes_mm: [0, 1, 2].map(|i| [c.soft_min_mm[i], c.soft_max_mm[i]]),
                    },
                    "the simulated Marlin stage (soft endstops 0..300 × 0..300 × 0..100 mm)"
                        .to_string(),
                )
            }
        }),
    }
}

/// An input file a run would open that is missing or invalid (what `--dry-run`
/// checks besides the plan, the sensor and the bench file, which are parsed before).
#[derive(Debug, thiserror::Error)]
pub enum InputError {
    /// The scene of a simulated bench.
    #[error("the bench's scene: {0}")]
    Scene(#[from] SceneError),
    /// A recorded-frames camera directory.
    #[error("the bench's camera: {0}")]
    Camera(#[from] DeviceError),
}

/// Reads and validates every file the bench would open, without opening a device:
/// the scene of a simulated bench (and its sensor file), the frames of a `dir:PATH`
/// camera. Returns one line per file checked (`frames_needed` = frames the run
/// grabs, compared with a non-looping frame directory).
pub fn check_bench_inputs(
    bench: &BenchConfig,
    frames_needed: usize,
) -> Result<Vec<(bool, String)>, InputError> {
    let mut out = Vec::new();
    match &bench.devices {
        BenchDevices::Sim(cfg) => {
            Scene::from_path(&cfg.scene)?;
            out.push((
                true,
                format!("scene {} and its sensor file read", cfg.scene.display()),
            ));
        }
        BenchDevices::Hardware {
            stage,
            force_sensor,
            camera,
        } => {
            let mut ports = vec![("stage", &stage.port)];
            match &force_sensor.network {
                None => ports.push(("force sensor", &force_sensor.port)),
                Some(n) => {
                    // A network sensor: the host must resolve; it is not contacted.
                    let resolved = crate::device::netft::transport::resolve(
                        force_sensor.protocol.name(),
                        &n.host,
                        n.rdt_port,
                    );
                    let ports = if force_sensor.protocol == crate::bench::config::FtKind::NetFt {
                        format!("UDP {} (RDT), TCP {} (calibration)", n.rdt_port, n.cal_port)
                    } else {
                        format!("UDP {} (RDT)", n.rdt_port)
                    };
                    out.push(match resolved {
                        Ok(a) => (
                            true,
                            format!(
                                "force sensor {} at {} ({}), {ports} (not contacted by a dry run)",
                                force_sensor.protocol.name(),
                                n.host,
                                a.ip()
                            ),
                        ),
                        Err(e) => (
                            false,
                            format!(
                                "force sensor {}: {}",
                                force_sensor.protocol.name(),
                                e.message
                            ),
                        ),
                    });
                }
            }
            for (what, port) in ports {
                let present = Path::new(port).exists();
                out.push((
                    true,
                    format!(
                        "{what} port {port} {} (not opened by a dry run)",
                        if present {
                            "present"
                        } else {
                            "not present now"
                        }
                    ),
                ));
            }
            match camera {
                CameraSpec::Dir(dir) => {
                    let cam = ImageDirCamera::open(dir, false)?;
                    let n = cam.files().len();
                    out.push((
                        n >= frames_needed,
                        format!(
                            "camera dir:{} holds {n} frames; the run grabs {frames_needed} (reference + setpoints x acquire.frames)",
                            dir.display()
                        ),
                    ));
                }
                CameraSpec::Sim(sock) => out.push((
                    true,
                    format!(
                        "camera sim:{} {} (not opened by a dry run)",
                        sock.display(),
                        if sock.exists() {
                            "present"
                        } else {
                            "not present now"
                        }
                    ),
                )),
                CameraSpec::V4l(i) => out.push((
                    true,
                    format!("camera V4L2 index {i} (not opened by a dry run)"),
                )),
            }
        }
    }
    Ok(out)
}
