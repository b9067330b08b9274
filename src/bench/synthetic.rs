//! A fast characterization-run generator: the run directory `tactbench run --sim`
//! would write for a plan on a scene, made without devices or device timing, for the
//! coverage tests of `tactbench fit` (20 seeds × several mis-built sensors cannot go
//! through the simulated bench's pseudo-terminals in a test).
//!
//! [`synthetic_run`] writes exactly the runner's format ([`crate::bench::runner`]):
//! `manifest.json` (the plan's text, the PLAN's nominal sensor file, the bench
//! description with the scene and the geometry, `simulated`, device provenance,
//! record digests), `journal.csv` rows through [`crate::bench::journal::Journal`],
//! `frames/reference.png` and `frames/NNNNN_K.png`, `displacements/NNNNN.csv` tracked
//! by [`crate::vision::Tracker`] against the reference (the sensor file's linear
//! `[camera]` mapping), and `forces/NNNNN.csv` (with the per-node σ columns when the
//! setpoint has several frames) with the force sums reconstructed by the plan's solver
//! from the nominal sensor, as the runner does.
//!
//! What differs from the runner, and why it does not matter for what the run records:
//! - each setpoint is reached directly: the depth that gives the target normal force
//!   by inverting the world's contact law ([`World::indentation_for_normal_force`]),
//!   then the lateral stage travel that gives the tangential target *as the F/T
//!   sensor reads it along the target direction* (the runner's control loop stops on
//!   the same reading: with a rotated F/T sensor the true tangential force is then
//!   `target / cos θ`). The runner stops anywhere within `control.force_tolerance`;
//!   here the F/T mean misses the target only by its noise, tare and quantisation,
//!   unless [`SyntheticOptions::stop_spread_seed`] asks for the runner's spread (a
//!   seeded uniform miss within the tolerance).
//!   Every setpoint starts from a fresh contact (the runner keeps the contact along a
//!   normal ramp; the elastic world has no memory of it);
//! - F/T readings are `acquire.samples` draws of [`World::wrench`] (noise, rotation
//!   and stage offset applied) read as `run --sim`'s simulated DynPick reads them:
//!   less the tare taken unloaded at the approach position (one noisy sample), then
//!   quantised to its resolution (1/32.8 N, 1/1638.4 N·m, [`DEFAULT_SENSITIVITIES`]:
//!   a 30 mN step, coarser than the scenes' 5 mN noise, so it shows in the means);
//!   no settling, so `t_move_s`, `t_settle_s` and `t_acquire_s` are 0 and `settled`
//!   is true; `t_track_s` and `t_solve_s` are measured (the solver's one-off
//!   precompute excluded, as the runner does);
//! - no tracking re-acquisition (the frames of a setpoint are rendered once; a row
//!   below `[quality] min_ok_fraction` is journalled `flagged`), and the force
//!   plausibility check marks rows `implausible` without ever stopping the run;
//! - scenes with time-dependent bench effects (`force_relaxation`, `viscoelastic`) or
//!   a carried sensor are refused: without device timing they would be wrong.
//!
//! [`SyntheticOptions::seed`] reseeds every seeded camera effect and the F/T noise of
//! the scene (each seed mixed with it), so one scene gives independent runs.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::time::Instant;

use image::RgbImage;
use serde_json::json;
use thiserror::Error;

use crate::bench::config::BenchGeometry;
use crate::bench::integrity::{file_sha256, RecordDigests};
use crate::bench::journal::{
    DeviceProvenance, Journal, JournalError, JournalRow, Manifest, Provenance, RowQuality,
    RunStatus, Session, StepTimes, GIT_COMMIT,
};
use crate::bench::plan::{Plan, Setpoint, Sweep};
use crate::bench::runner::{
    mean_over_frames, rfc3339_now, solve_setpoint, with_geometry, SolvedSetpoint,
};
use crate::device::dynpick::codec::Record;
use crate::device::dynpick::sim::DEFAULT_SENSITIVITIES;
use crate::device::Wrench;
use crate::formats::{self, DisplacementFrame};
use crate::sensor::Sensor;
use crate::sim::effects::{Effect, Pipeline};
use crate::sim::render::to_rgb8;
use crate::sim::rng::Rng;
use crate::sim::scene::Scene;
use crate::sim::simulate::Simulation;
use crate::sim::world::{World, WorldGeometry};
use crate::solve::FrameSolver;
use crate::vision::{
    self, DetectConfig, FrameView, MarkerTrack, PixelMapping, StatusCounts, TrackConfig, Tracker,
};

/// Why a synthetic run could not be made. Each variant names the file or setpoint.
#[derive(Debug, Error)]
pub enum SyntheticError {
    /// Writing into the run directory failed.
    #[error("{path}: {message}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The cause.
        message: String,
    },
    /// The journal or manifest.
    #[error(transparent)]
    Journal(#[from] JournalError),
    /// The inputs cannot make a synthetic run (an unsupported scene, an existing run).
    #[error("{0}")]
    Input(String),
    /// A setpoint cannot be reached on this scene (beyond the friction limit, no depth
    /// gives the force), or its reference frame does not match the sensor file.
    #[error("setpoint {index}: {message}")]
    Setpoint {
        /// Setpoint index in the expanded plan.
        index: usize,
        /// What went wrong.
        message: String,
    },
}

/// How to generate a run.
#[derive(Debug, Clone, Default)]
pub struct SyntheticOptions {
    /// Reseed every seeded camera effect and the F/T noise with this seed (mixed
    /// with each effect's own seed); `None`: the scene's seeds as written.
    pub seed: Option<u64>,
    /// Where the sensor sits in stage coordinates; `None`: the GRBL simulated bench's
    /// (`tactbench run --sim`'s stage) with a clearance of 1 mm.
    pub geometry: Option<BenchGeometry>,
    /// Do not write `frames/*.png` (they are evidence: readers say they are missing;
    /// the journal still names them). Saves the PNG encoding time.
    pub skip_frames: bool,
    /// Where the controller stops. `None`: exactly at each setpoint's target (the
    /// true normal force, and the tangential force as the F/T sensor reads it).
    /// `Some(seed)`: anywhere within `control.force_tolerance` of it, as the runner's
    /// loop stops at its first reading inside the band: a miss drawn uniformly in
    /// `[−tol, tol]` per setpoint and axis (stream = setpoint index). With exact
    /// stops every seed of a study puts the same force on the same count of the F/T
    /// sensor's lattice, so its rounding error is one draw repeated, not a random
    /// error; a coverage study over seeds needs the spread.
    pub stop_spread_seed: Option<u64>,
}

/// What was generated.
#[derive(Debug, Clone, PartialEq)]
pub struct SyntheticSummary {
    /// Rows journalled.
    pub setpoints: usize,
    /// Rows without force (tracking or reconstruction failed).
    pub failed: usize,
    /// Rows flagged or implausible.
    pub flagged: usize,
    /// The geometry recorded in the manifest.
    pub geometry: BenchGeometry,
    /// Stage z of first contact (the world's surface), mm: the truth of the fit's
    /// `contact_z_mm`.
    pub contact_z_mm: f64,
}

/// Mixes a run seed into an effect's seed (SplitMix64 finaliser of both).
fn mix_seed(effect_seed: u64, run_seed: u64) -> u64 {
    let mut z = effect_seed ^ run_seed.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The scene with every seed mixed with `seed`.
fn reseeded(scene: &Scene, seed: u64) -> Result<Scene, SyntheticError> {
    let mut s = scene.clone();
    let effects: Vec<Effect> = scene
        .pipeline
        .effects()
        .iter()
        .cloned()
        .map(|mut e| {
            match &mut e {
                Effect::PixelNoise { seed: s, .. }
                | Effect::ShotNoise { seed: s, .. }
                | Effect::SizeJitter { seed: s, .. }
                | Effect::PlacementJitter { seed: s, .. }
                | Effect::Drift { seed: s, .. } => *s = mix_seed(*s, seed),
                _ => {}
            }
            e
        })
        .collect();
    s.pipeline = Pipeline::new(effects, scene.sensor.layers.len())
        .map_err(|e| SyntheticError::Input(format!("{}: {e}", scene.path.display())))?;
    if let Some(n) = s.bench.ft_noise.as_mut() {
        n.seed = mix_seed(n.seed, seed);
    }
    Ok(s)
}

/// Refuses scenes whose bench effects need device timing or a carried sensor.
fn check_scene(scene: &Scene) -> Result<(), SyntheticError> {
    let b = &scene.bench;
    let refused = [
        (b.force_relaxation.is_some(), "bench.force_relaxation"),
        (b.viscoelastic.is_some(), "bench.viscoelastic"),
        (b.carry_zero_mm.is_some(), "bench.stage_carries_sensor"),
    ];
    match refused.iter().find(|(on, _)| *on) {
        Some((_, key)) => Err(SyntheticError::Input(format!(
            "{}: {key} is not supported by a synthetic run (it has no device timing and no carried sensor): use `tactbench run --sim` for this scene",
            scene.path.display()
        ))),
        None => Ok(()),
    }
}

/// The GRBL simulated bench's geometry (`tactbench run --sim`), clearance 1 mm.
pub fn default_geometry() -> BenchGeometry {
    let (w, _) = crate::sim::bench::StageProtocol::Grbl.default_geometry();
    BenchGeometry {
        sensor_origin_in_stage_mm: w.sensor_origin_in_stage_mm,
        surface_z_mm: w.surface_z_mm,
        press_direction: w.press_direction,
        clearance_mm: 1.0,
    }
}

/// The run's fixed state.
struct Gen<'a> {
    plan: &'a Plan,
    sensor: &'a Sensor,
    geom: BenchGeometry,
    world: std::sync::Arc<World>,
    /// The F/T reading unloaded at the approach position, subtracted as a tare.
    tare: Wrench,
    dir: &'a Path,
    skip_frames: bool,
    stop_spread_seed: Option<u64>,
    tracker: Tracker,
    mapping: PixelMapping,
    solvers: HashMap<Vec<bool>, Box<dyn FrameSolver>>,
    evidence: BTreeMap<String, String>,
}

/// Writes the run directory `out` (which must not hold a run) for `plan` (its text
/// `plan_toml`, as the manifest records it; its sensor file is the nominal sensor the
/// run reconstructs with) measured on `scene` (the truth: sensor, indenter, camera
/// effects and `[bench]` effects).
pub fn synthetic_run(
    plan: &Plan,
    plan_toml: &str,
    scene: &Scene,
    out: &Path,
    options: &SyntheticOptions,
) -> Result<SyntheticSummary, SyntheticError> {
    check_scene(scene)?;
    let scene = match options.seed {
        Some(seed) => reseeded(scene, seed)?,
        None => scene.clone(),
    };
    let sensor_toml =
        std::fs::read_to_string(&plan.sensor_path).map_err(|e| io(&plan.sensor_path, e))?;
    let sensor = Sensor::from_toml_str(&sensor_toml, &plan.sensor_path)
        .map_err(|e| SyntheticError::Input(e.to_string()))?;
    if out.join("journal.csv").exists() || out.join("manifest.json").exists() {
        return Err(SyntheticError::Input(format!(
            "{} already holds a run: choose another directory",
            out.display()
        )));
    }
    for sub in ["", "frames", "displacements", "forces"] {
        let d = out.join(sub);
        std::fs::create_dir_all(&d).map_err(|e| io(&d, e))?;
    }
    let geom = options.geometry.unwrap_or_else(default_geometry);
    let world_geometry = WorldGeometry {
        sensor_origin_in_stage_mm: geom.sensor_origin_in_stage_mm,
        surface_z_mm: geom.surface_z_mm,
        press_direction: geom.press_direction,
        friction: scene.load.friction,
        ..WorldGeometry::default()
    };
    let start = geom.stage_point(plan.approach_position_mm, -geom.clearance_mm);
    let world = World::with_effects(
        Simulation::from_scene(&scene),
        scene.indenter,
        world_geometry,
        start,
        scene.bench,
    );
    let mut manifest = manifest(
        plan,
        plan_toml,
        &sensor_toml,
        &scene,
        &geom,
        world_geometry.friction,
    );
    manifest.write(out)?;
    let mut journal = Journal::create(out)?;

    // The reference at the clearance height above the approach position, as the
    // runner takes it (after taring: the ideal F/T sensor has no offset).
    let mut img = world.blank_frame();
    world
        .render_reference(&mut img)
        .map_err(|e| SyntheticError::Input(e.to_string()))?;
    let reference = to_rgb8(&img);
    let mut evidence = BTreeMap::new();
    save_png(
        out,
        "frames/reference.png",
        &reference,
        options.skip_frames,
        &mut evidence,
    )?;
    let mapping = PixelMapping::Linear(sensor.camera);
    let layout = vision::detect_mapped(
        &FrameView::rgb8(&reference),
        &sensor,
        &DetectConfig::default(),
        &mapping,
    )
    .map_err(|e| SyntheticError::Input(format!("frames/reference.png: {e}")))?;
    // The runner tares unloaded at the approach position before the reference.
    let tare = world.wrench();
    let mut g = Gen {
        plan,
        sensor: &sensor,
        geom,
        world,
        tare,
        dir: out,
        skip_frames: options.skip_frames,
        stop_spread_seed: options.stop_spread_seed,
        tracker: Tracker::new(layout, TrackConfig::default()),
        mapping,
        solvers: HashMap::new(),
        evidence,
    };
    let (mut failed, mut flagged, mut rows) = (0, 0, 0);
    for sp in plan.setpoints() {
        let mut row = g.measure(&sp, &mut img)?;
        row.completed_at = rfc3339_now();
        failed += usize::from(row.failure.is_some());
        flagged += usize::from(row.quality != Some(RowQuality::Ok));
        journal.append(&row)?;
        rows += 1;
    }
    let now = rfc3339_now();
    manifest.record = Some(
        RecordDigests::journal_now(out, g.evidence, rows, now.clone())
            .map_err(|e| io(&out.join("journal.csv"), e))?,
    );
    manifest.finish(RunStatus::Completed, None, rows, None, now);
    manifest.write(out)?;
    Ok(SyntheticSummary {
        setpoints: rows,
        failed,
        flagged,
        geometry: geom,
        contact_z_mm: geom.surface_z_mm,
    })
}

fn io(path: &Path, e: impl std::fmt::Display) -> SyntheticError {
    SyntheticError::Io {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// Saves a frame (unless frames are skipped) and records its digest.
fn save_png(
    dir: &Path,
    rel: &str,
    img: &RgbImage,
    skip: bool,
    evidence: &mut BTreeMap<String, String>,
) -> Result<(), SyntheticError> {
    if skip {
        return Ok(());
    }
    let path = dir.join(rel);
    img.save(&path).map_err(|e| io(&path, e))?;
    if let Some(d) = file_sha256(&path) {
        evidence.insert(rel.to_string(), d);
    }
    Ok(())
}

/// The manifest of a new synthetic run, as the runner writes it for `run --sim`.
fn manifest(
    plan: &Plan,
    plan_toml: &str,
    sensor_toml: &str,
    scene: &Scene,
    geom: &BenchGeometry,
    friction: f64,
) -> Manifest {
    let now = rfc3339_now();
    let setpoints = plan.setpoints().len();
    let bench = json!({
        "sim": {
            "scene": scene.path.display().to_string(),
            "scene_toml": std::fs::read_to_string(&scene.path).unwrap_or_default(),
            "stage": "Grbl",
            "force_sensor": "DynPick",
            "friction": friction,
            "synthetic": true,
        },
        // As `run --sim` records it: the bench file is the scene (`run --resume`
        // reopens a `[sim]` bench file only when it differs from the scene).
        "file": scene.path.display().to_string(),
        "cwd": std::env::current_dir().map(|d| d.display().to_string()).unwrap_or_default(),
    });
    let why = "a synthetic run (bench::synthetic_run: the simulated bench's world without devices)";
    let devices = ["stage", "force_sensor", "camera"];
    Manifest {
        plan_path: plan.path.display().to_string(),
        plan_name: plan.name.clone(),
        plan_toml: plan_toml.to_string(),
        sensor_path: plan.sensor_path.display().to_string(),
        sensor_toml: sensor_toml.to_string(),
        bench: with_geometry(bench, geom),
        devices: json!({"stage": "synthetic", "force_sensor": "synthetic", "camera": "synthetic"}),
        build_id: plan.build_id.clone(),
        software_version: env!("CARGO_PKG_VERSION").to_string(),
        started_at: now.clone(),
        resumed_at: Vec::new(),
        setpoints,
        planned_setpoints: Some(setpoints),
        limit: None,
        sessions: vec![Session {
            started_at: now,
            limit: None,
            setpoints_before: 0,
            setpoints_after: 0,
        }],
        measured_setpoints: 0,
        status: RunStatus::Running,
        end_reason: None,
        stop_signal: None,
        incomplete_reason: None,
        ended_at: None,
        software_commit: Some(GIT_COMMIT.to_string()),
        camera_path: None,
        camera_toml: None,
        simulated: Some(true),
        write_failure: None,
        device_provenance: devices
            .iter()
            .map(|d| DeviceProvenance {
                device: d.to_string(),
                identity: "synthetic".into(),
                provenance: Provenance::Simulated,
                why: Some(why.into()),
            })
            .collect(),
        record: None,
    }
}

impl Gen<'_> {
    /// Puts the stage where the runner's control would leave it for `sp`.
    /// The controller's miss of the normal and tangential targets at `sp`, N
    /// ([`SyntheticOptions::stop_spread_seed`]).
    fn stop_miss(&self, sp: &Setpoint) -> [f64; 2] {
        let Some(seed) = self.stop_spread_seed else {
            return [0.0, 0.0];
        };
        let mut rng = Rng::stream(seed, sp.index as u64);
        let tol = self.plan.force_tolerance_n;
        [
            (2.0 * rng.uniform() - 1.0) * tol,
            (2.0 * rng.uniform() - 1.0) * tol,
        ]
    }

    fn reach(&self, sp: &Setpoint) -> Result<(), SyntheticError> {
        let at = |message: String| SyntheticError::Setpoint {
            index: sp.index,
            message,
        };
        let xy = [
            sp.position_mm[0] + sp.shift_mm[0],
            sp.position_mm[1] + sp.shift_mm[1],
        ];
        // A fresh contact: retract (releases the stick point), move over the target.
        self.world
            .set_stage_mm(self.geom.stage_point(xy, -self.geom.clearance_mm));
        if sp.normal_n <= 0.0 {
            return Ok(());
        }
        let [miss_n, miss_t] = self.stop_miss(sp);
        // A miss never reverses a load (tolerances are far below the loads).
        let normal_n = (sp.normal_n + miss_n).max(0.5 * sp.normal_n);
        let depth = self
            .world
            .indentation_for_normal_force(normal_n)
            .ok_or_else(|| at(format!("no indentation reaches fz = {normal_n} N")))?;
        let max_depth = self.plan.safety.travel_max_mm[2];
        if depth > max_depth {
            return Err(at(format!(
                "fz = {} N needs an indentation of {depth:.4} mm, deeper than safety.travel_max_mm[2] = {max_depth} mm",
                sp.normal_n
            )));
        }
        // Through the surface vertically, as the approach does.
        self.world.set_stage_mm(self.geom.stage_point(xy, 0.0));
        self.world.set_stage_mm(self.geom.stage_point(xy, depth));
        let t = sp.tangential_n;
        let t_target = t[0].hypot(t[1]);
        if t_target == 0.0 {
            return Ok(());
        }
        let dir = [t[0] / t_target, t[1] / t_target];
        let t_mag = (t_target + miss_t).max(0.5 * t_target);
        // The runner's loop travels along `dir` until the F/T reading along `dir` is
        // the target. While stuck the reading is linear in the travel: one probe step
        // gives its slope.
        let along = |s: f64| {
            let p = self
                .geom
                .stage_point([xy[0] + s * dir[0], xy[1] + s * dir[1]], depth);
            self.world.set_stage_mm(p);
            let f = self.world.wrench_without_noise().force_n;
            f[0] * dir[0] + f[1] * dir[1]
        };
        let probe = 1e-4;
        let slope = along(probe) / probe;
        if slope.is_nan() || slope <= 0.0 {
            return Err(at(format!(
                "the F/T reading along the tangential target does not grow with lateral travel (slope {slope:.4e} N/mm): a F/T rotation of 90° or more?"
            )));
        }
        let s = t_mag / slope;
        // Back to the stick point first: the travel is measured from it.
        along(0.0);
        let q = along(s);
        if self.world.contact().sliding || (q - t_mag).abs() > 1e-6 * t_mag.max(1.0) {
            return Err(at(format!(
                "tangential target {t_mag} N is beyond the friction limit at fz = {} N (reached {q:.4} N): lower it or raise the friction",
                sp.normal_n
            )));
        }
        Ok(())
    }

    /// One setpoint, from the stage position to the journal row (not yet appended).
    fn measure(
        &mut self,
        sp: &Setpoint,
        img: &mut image::Rgb32FImage,
    ) -> Result<JournalRow, SyntheticError> {
        self.reach(sp)?;
        let samples: Vec<Wrench> = (0..self.plan.samples)
            .map(|_| dynpick_reading(&self.world.wrench(), &self.tare))
            .collect();
        let (mean, sd) = mean_sd(&samples);
        let stage = self.world.stage_mm();
        let mut tracked: Vec<(String, Vec<MarkerTrack>)> = Vec::with_capacity(self.plan.frames);
        let mut t_track = 0.0;
        let mut track_error = None;
        for k in 0..self.plan.frames {
            let name = format!("frames/{:05}_{k}.png", sp.index);
            self.world
                .render(img)
                .map_err(|e| SyntheticError::Setpoint {
                    index: sp.index,
                    message: e.to_string(),
                })?;
            let frame = to_rgb8(img);
            save_png(
                self.dir,
                &name,
                &frame,
                self.skip_frames,
                &mut self.evidence,
            )?;
            let t0 = Instant::now();
            match self.tracker.track(&FrameView::rgb8(&frame)) {
                Ok(t) => tracked.push((name, t.to_vec())),
                Err(e) => {
                    track_error = Some(format!("{name}: {e}"));
                    break;
                }
            }
            t_track += t0.elapsed().as_secs_f64();
        }
        let missing = self.tracker.reference().missing.len();
        let counts = if track_error.is_some() {
            StatusCounts {
                lost: self.tracker.reference().markers.len() + missing,
                ..StatusCounts::default()
            }
        } else {
            StatusCounts::of_frames(tracked.iter().map(|(_, t)| t.as_slice()), missing)
        };
        let total = counts.ok + counts.lost + counts.merged + counts.outlier;
        let ok_fraction = if total == 0 {
            0.0
        } else {
            counts.ok as f64 / total as f64
        };
        let mut quality =
            if track_error.is_none() && ok_fraction >= self.plan.quality.min_ok_fraction {
                RowQuality::Ok
            } else {
                RowQuality::Flagged
            };
        let t_solve0 = Instant::now();
        let (fsum, fsum_sd, failure, precompute_s) = match &track_error {
            Some(e) => (
                [f64::NAN; 3],
                None,
                Some(format!("tracking failed: {e}")),
                0.0,
            ),
            None => match self.reconstruct(sp.index, &tracked)? {
                Ok((fsum, sd, p)) => (fsum, sd, None, p),
                Err(e) => (
                    [f64::NAN; 3],
                    None,
                    Some(format!("reconstruction failed: {e}")),
                    0.0,
                ),
            },
        };
        // As the runner: the one-off solver precompute is not the setpoint's solve.
        let t_solve = (t_solve0.elapsed().as_secs_f64() - precompute_s).max(0.0);
        let mut plausibility = None;
        if failure.is_none() && quality == RowQuality::Ok {
            if let Some(text) = self.implausible(&mean.force_n, &sd, &fsum) {
                quality = RowQuality::Implausible;
                plausibility = Some(text);
            }
        }
        let frames: Vec<String> = (0..self.plan.frames)
            .map(|k| format!("frames/{:05}_{k}.png", sp.index))
            .collect();
        Ok(JournalRow::setpoint(
            sp.index,
            sp.trial,
            sp.swept_value,
            sp.normal_n,
            sp.tangential_n,
        )
        .in_sweep(sp.direction, sp.position, sp.hold_t_s)
        .with_wrench(&mean, sd)
        .at_stage(stage, true)
        .with_frames(&frames, &counts, 0)
        .with_force_sum(fsum, fsum_sd)
        .with_verdict(quality, failure, plausibility)
        .timed(StepTimes {
            track_s: t_track,
            solve_s: t_solve,
            ..StepTimes::default()
        }))
    }

    /// The runner's force plausibility finding for a row, if it fails it.
    fn implausible(&self, ft: &[f64; 3], ft_sd: &[f64; 3], fsum: &[f64; 3]) -> Option<String> {
        if matches!(self.plan.sweep, Sweep::Displacement { .. }) {
            return None;
        }
        let q = self.plan.quality;
        let norm = |v: &[f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        let (f_ft, f_sum) = (norm(ft), norm(fsum));
        let floor = q.force_noise_floor_n.max(3.0 * norm(ft_sd));
        let bad = !f_sum.is_finite()
            || f_sum > q.force_ratio_max * f_ft.max(floor)
            || (f_ft > floor && f_sum < q.force_ratio_min * f_ft);
        bad.then(|| {
            format!(
                "|F_sum| = {f_sum:.4e} N against the F/T sensor's |F| = {f_ft:.4} N, outside [quality] force_ratio_min {} .. force_ratio_max {}",
                q.force_ratio_min, q.force_ratio_max
            )
        })
    }

    /// Writes the displacement and force files of a setpoint and reconstructs its force
    /// sums from the mean displacement over the frames, as the runner does. The inner
    /// error is a failed reconstruction (a failed row, not a failed run).
    #[allow(clippy::type_complexity)]
    fn reconstruct(
        &mut self,
        index: usize,
        tracked: &[(String, Vec<MarkerTrack>)],
    ) -> Result<Result<([f64; 3], Option<[f64; 3]>, f64), String>, SyntheticError> {
        let sensor = self.sensor;
        let rel = format!("displacements/{index:05}.csv");
        let path = self.dir.join(&rel);
        vision::write_tracks_mapped(
            &path,
            sensor,
            self.tracker.reference(),
            tracked,
            &self.mapping,
        )
        .map_err(|e| io(&path, e))?;
        if let Some(d) = file_sha256(&path) {
            self.evidence.insert(rel, d);
        }
        // Mean displacement over the frames; a marker lost in any frame is lost.
        let (records, sigma_mean_mm) = mean_over_frames(tracked.iter().map(|(_, tracks)| {
            self.tracker
                .displacement_records_mapped(tracks, &self.mapping)
        }));
        let frame = DisplacementFrame {
            frame: String::new(),
            records,
        };
        let solved = solve_setpoint(
            &mut self.solvers,
            sensor,
            &self.plan.solver,
            &frame,
            sigma_mean_mm,
        );
        let SolvedSetpoint {
            f,
            fsum,
            fsum_sd,
            node_sd,
            precompute_s,
            error,
        } = solved;
        let rel = format!("forces/{index:05}.csv");
        let path = self.dir.join(&rel);
        let frames = [(String::new(), f)];
        match node_sd {
            Some(sd) => formats::write_forces_sd(&path, &sensor.force_grid, &frames, &[sd]),
            None => formats::write_forces(&path, &sensor.force_grid, &frames),
        }
        .map_err(|e| io(&path, e))?;
        if let Some(d) = file_sha256(&path) {
            self.evidence.insert(rel, d);
        }
        Ok(match error {
            None => Ok((fsum, fsum_sd, precompute_s)),
            Some(e) => Err(e),
        })
    }
}

/// What the simulated DynPick of `run --sim` reports for the wrench `w` after a tare
/// that read `tare`: the difference quantised by the codec's rounding rule.
fn dynpick_reading(w: &Wrench, tare: &Wrench) -> Wrench {
    let s = DEFAULT_SENSITIVITIES;
    let d = Wrench {
        force_n: [0, 1, 2].map(|i| w.force_n[i] - tare.force_n[i]),
        torque_nm: [0, 1, 2].map(|i| w.torque_nm[i] - tare.torque_nm[i]),
    };
    Record {
        counter: 0,
        raw: Record::raw_from_wrench(&d, &s),
    }
    .to_wrench(&s)
}

/// Mean wrench and per-component force SD (sample SD; 0 for one sample), as the
/// runner averages its F/T samples.
fn mean_sd(samples: &[Wrench]) -> (Wrench, [f64; 3]) {
    let n = samples.len().max(1) as f64;
    let m = Wrench::mean(samples);
    let mut sd = [0.0; 3];
    if samples.len() > 1 {
        for (i, s) in sd.iter_mut().enumerate() {
            let ss: f64 = samples
                .iter()
                .map(|w| (w.force_n[i] - m.force_n[i]).powi(2))
                .sum();
            *s = (ss / (n - 1.0)).sqrt();
        }
    }
    (m, sd)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn synthetic_ft_readings_are_tared_and_quantised_like_the_simulated_dynpick() {
        let w = Wrench {
            force_n: [0.0101, -0.52, 1.0],
            torque_nm: [0.0004, 0.0, -0.03],
        };
        let tare = Wrench {
            force_n: [0.004, 0.0, -0.006],
            torque_nm: [0.0; 3],
        };
        let r = dynpick_reading(&w, &tare);
        // One LSB is 1/32.8 N and 1/1638.4 N·m; each channel is the nearest count of
        // the tared value.
        let counts = [
            (r.force_n[0], 0.0061f64 * 32.8, 32.8),
            (r.force_n[1], -0.52 * 32.8, 32.8),
            (r.force_n[2], 1.006 * 32.8, 32.8),
            (r.torque_nm[0], 0.0004 * 1638.4, 1638.4),
            (r.torque_nm[2], -0.03 * 1638.4, 1638.4),
        ];
        for (got, lsb, s) in counts {
            assert_eq!(got, lsb.round() / s, "{r:?}");
        }
        // The same reading through the simulator's own codec path.
        let s = DEFAULT_SENSITIVITIES;
        let raw = Record::raw_from_wrench(&r, &s);
        assert_eq!(Record { counter: 0, raw }.to_wrench(&s), r);
    }
}
