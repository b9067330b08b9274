//! One setpoint's measurement: force control, settling, F/T averaging, frames,
//! tracking against the reference and reconstruction; and the tracking quality gates
//! of the plan's `[quality]`: the reference frame against the sensor file, and per
//! setpoint the markers ok (re-acquire the frames, then flag the row or abort).

use std::collections::HashMap;
use std::path::Path;
use std::time::{Duration, Instant};

use super::{
    dev_abort, Halt, Phase, RunEvent, Runner, Step, CONTROL_SAMPLES, INITIAL_STIFFNESS_N_PER_MM,
    MAX_CONTROL_STEP_MM, READ_RETRIES, SETTLE_RETRIES,
};
use crate::bench::control::{check_force_limits, ForceController, SettleDetector};
use crate::bench::journal::{Direction, JournalRow, RowQuality, StepTimes};
use crate::bench::plan::{OnFail, Setpoint};
use crate::device::{CameraFrame, ErrorKind, StagePositionMm, Wrench};
use crate::formats::{self, DisplacementFrame};
use crate::sensor::Sensor;
use crate::solve::{self, FrameSolver, Problem, SolverConfig};
use crate::vision::{self, FrameView, MarkerTrack, Reference, ReferenceHealth, StatusCounts};

/// Fraction of the force controller's step taken towards the target on the rows of
/// an up-down sweep (approached from one side; see `control`).
pub const MONOTONIC_STEP_FRACTION: f64 = 0.6;

/// How often a hold reads the force sensor for the safety limits while it waits for
/// its next sample.
pub const HOLD_POLL: Duration = Duration::from_millis(20);

/// One setpoint's frames: `(relative path, tracks)` per frame.
type Tracked = Vec<(String, Vec<MarkerTrack>)>;

/// How a setpoint's force was reached: settled or not, the time moving and settling,
/// and (a hold) the sample's time since the hold's force was reached.
struct Reached {
    settled: bool,
    t_move: f64,
    t_settle: f64,
    hold_t_s: Option<f64>,
}

/// A setpoint's F/T acquisition.
struct Readings {
    mean: Wrench,
    sd: [f64; 3],
    /// The sensor's flags and counts since the previous row.
    ft_status: Option<String>,
    stage: StagePositionMm,
    /// Acquisition time, s (readings, then the frames' grabs added).
    t_acquire: f64,
}

/// A setpoint's frames after the last (re-)acquisition.
struct Frames {
    /// `None` when tracking failed (`track_error` says why).
    tracked: Option<Tracked>,
    t_track: f64,
    counts: StatusCounts,
    reacquired: usize,
    /// Every acquisition had a blank, saturated or markerless frame: the last one's,
    /// in words.
    dead: Option<String>,
    track_error: Option<String>,
    /// The acquisition time, readings and grabs, s.
    t_acquire: f64,
}

/// A setpoint's reconstruction.
struct Forces {
    /// The frames' paths relative to the run directory.
    frames: Vec<String>,
    fsum: [f64; 3],
    fsum_sd: Option<[f64; 3]>,
    t_solve: f64,
    /// Why the reconstruction failed.
    error: Option<String>,
}

/// What the row says of itself: its quality, the force plausibility finding and why
/// it failed.
struct Verdict {
    quality: RowQuality,
    plausibility: Option<String>,
    failure: Option<String>,
}

/// The journal row of a measured setpoint.
fn journal_row(
    sp: &Setpoint,
    reached: &Reached,
    ft: Readings,
    frames: &Frames,
    forces: Forces,
    verdict: Verdict,
) -> JournalRow {
    JournalRow {
        ft_status: ft.ft_status,
        ..JournalRow::setpoint(
            sp.index,
            sp.trial,
            sp.swept_value,
            sp.normal_n,
            sp.tangential_n,
        )
        .in_sweep(sp.direction, sp.position, reached.hold_t_s)
        .with_wrench(&ft.mean, ft.sd)
        .at_stage(ft.stage, reached.settled)
        .with_frames(&forces.frames, &frames.counts, frames.reacquired)
        .with_force_sum(forces.fsum, forces.fsum_sd)
        .with_verdict(verdict.quality, verdict.failure, verdict.plausibility)
        .timed(StepTimes {
            move_s: reached.t_move,
            settle_s: reached.t_settle,
            acquire_s: frames.t_acquire,
            track_s: frames.t_track,
            solve_s: forces.t_solve,
        })
    }
}

impl Runner<'_, '_, '_, '_> {
    pub(super) fn read_retry(&mut self) -> Step<Wrench> {
        let mut attempt = 0;
        loop {
            match self.dev.read() {
                Ok(w) => {
                    self.reading(&w);
                    return Ok(w);
                }
                Err(e) if attempt < READ_RETRIES && e.kind() != ErrorKind::Disconnected => {
                    attempt += 1;
                    (self.events)(&RunEvent::Retry {
                        index: self.index,
                        attempt,
                        reason: format!("force sensor read failed: {e}"),
                    });
                }
                Err(e) => return Err(dev_abort("reading the force sensor", &e)),
            }
        }
    }

    pub(super) fn grab_retry(&mut self) -> Step<CameraFrame> {
        let mut attempt = 0;
        loop {
            match self.dev.grab() {
                Ok(f) => return Ok(f),
                Err(e) if attempt < READ_RETRIES && e.kind() != ErrorKind::Disconnected => {
                    attempt += 1;
                    (self.events)(&RunEvent::Retry {
                        index: self.index,
                        attempt,
                        reason: format!("camera grab failed: {e}"),
                    });
                }
                Err(e) => return Err(dev_abort("grabbing a frame", &e)),
            }
        }
    }

    pub(super) fn mean_force(&mut self, n: usize) -> Step<Wrench> {
        let mut m = Wrench::default();
        for _ in 0..n {
            let w = self.read_retry()?;
            if let Some(trip) = check_force_limits(&w, &self.plan.safety.max_force_n) {
                return Err(self.trip(format!("{trip}"), Instant::now()));
            }
            for i in 0..3 {
                m.force_n[i] += w.force_n[i] / n as f64;
                m.torque_nm[i] += w.torque_nm[i] / n as f64;
            }
        }
        Ok(m)
    }

    /// Normal (and tangential) force control at the setpoint.
    pub(super) fn control(&mut self, sp: &Setpoint, lateral: &mut [f64; 2]) -> Step<()> {
        self.set_phase(Phase::ForceControl);
        let tol = self.plan.force_tolerance_n;
        let t_mag = sp.tangential_n[0].hypot(sp.tangential_n[1]);
        let dir = if t_mag > 0.0 {
            [sp.tangential_n[0] / t_mag, sp.tangential_n[1] / t_mag]
        } else {
            [0.0, 0.0]
        };
        let max_t = self.plan.safety.max_force_n[0].min(self.plan.safety.max_force_n[1]);
        let mut tan_ctl =
            ForceController::new(INITIAL_STIFFNESS_N_PER_MM, MAX_CONTROL_STEP_MM, max_t);
        let max_depth = self.plan.safety.travel_max_mm[2];
        for _ in 0..self.plan.max_control_steps {
            let w = self.mean_force(CONTROL_SAMPLES)?;
            let f = w.force_n;
            let q = f[0] * dir[0] + f[1] * dir[1];
            let normal_ok = (f[2] - sp.normal_n).abs() <= tol;
            let tangential_ok = t_mag == 0.0 || (q - t_mag).abs() <= tol;
            if normal_ok && tangential_ok {
                return Ok(());
            }
            let here = self
                .commanded
                .unwrap_or(self.geom.stage_point(sp.position_mm, 0.0));
            let xy = self.geom.sensor_xy(here);
            if !normal_ok {
                let depth = self.geom.depth(here[2]);
                let mut next = self.normal_ctl.next_z(depth, f[2], sp.normal_n);
                // Up-down sweeps approach each level from one side (loading from
                // below, unloading from above): a step towards the target is cut to
                // MONOTONIC_STEP_FRACTION of the secant's, so a contact that stiffens
                // with depth (Hertz: local stiffness up to 1.5x the secant) is not
                // overshot, which would put an `up` row on an unloading branch.
                let towards = match sp.direction {
                    Some(Direction::Up) => next > depth,
                    Some(Direction::Down) => next < depth,
                    None => false,
                };
                if towards {
                    next = depth + (next - depth) * MONOTONIC_STEP_FRACTION;
                }
                let next = next.min(max_depth);
                if next <= depth + 1e-9 && f[2] < sp.normal_n - tol {
                    return Err(Halt::Abort(format!(
                        "cannot reach fz = {:.4} N: {:.4} N at the deepest allowed indentation {max_depth} mm",
                        sp.normal_n, f[2]
                    )));
                }
                let target = self.geom.stage_point(xy, next);
                self.guarded_move(target, self.plan.approach_speed_mm_s, None)?;
            } else {
                // Lateral travel s along the direction; Q grows with s (Mindlin).
                let s = lateral[0] * dir[0] + lateral[1] * dir[1];
                let next = tan_ctl.next_z(s, q, t_mag);
                let d = next - s;
                let target_xy = [xy[0] + d * dir[0], xy[1] + d * dir[1]];
                lateral[0] += d * dir[0];
                lateral[1] += d * dir[1];
                let target = [
                    self.geom.stage_xy(target_xy)[0],
                    self.geom.stage_xy(target_xy)[1],
                    here[2],
                ];
                self.guarded_move(target, self.plan.approach_speed_mm_s, None)?;
            }
        }
        let w = self.mean_force(CONTROL_SAMPLES)?;
        Err(Halt::Abort(format!(
            "force control did not converge in {} steps (control.max_steps): measured ({:.4}, {:.4}, {:.4}) N, target ({:.4}, {:.4}, {:.4}) N ± {:.4} N",
            self.plan.max_control_steps,
            w.force_n[0],
            w.force_n[1],
            w.force_n[2],
            sp.tangential_n[0],
            sp.tangential_n[1],
            sp.normal_n,
            tol
        )))
    }

    /// Waits for the force to settle (or the fixed dwell). Returns whether it settled.
    pub(super) fn settle(&mut self) -> Step<bool> {
        self.set_phase(Phase::Settle);
        let st = self.plan.settle;
        let t0 = Instant::now();
        if st.dwell_s > 0.0 {
            while t0.elapsed().as_secs_f64() < st.dwell_s {
                if self.stopped() {
                    return Err(Halt::Interrupted);
                }
                let left = st.dwell_s - t0.elapsed().as_secs_f64();
                self.dev
                    .sleep(Duration::from_secs_f64(left.clamp(0.0, 0.05)));
            }
            return Ok(true);
        }
        let mut det = SettleDetector::new(st.window_s, st.max_sd_n);
        loop {
            if self.stopped() {
                return Err(Halt::Interrupted);
            }
            let w = self.read_retry()?;
            if let Some(trip) = check_force_limits(&w, &self.plan.safety.max_force_n) {
                return Err(self.trip(format!("{trip}"), Instant::now()));
            }
            let f = w.force_n;
            let t = t0.elapsed().as_secs_f64();
            if det.push(t, (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt()) {
                return Ok(true);
            }
            if t >= st.timeout_s {
                return Ok(false);
            }
        }
    }

    /// One setpoint, from motion to the journal row (not yet appended).
    pub(super) fn measure(&mut self, sp: &Setpoint, retract: bool) -> Step<JournalRow> {
        self.set_phase(Phase::Approach);
        let t_move0 = Instant::now();
        let mut lateral = self.position_at(sp, retract)?;
        let reached = match sp.hold_t_s {
            Some(t_sched) => self.hold_sample(sp, t_sched, &mut lateral, t_move0)?,
            None => self.control_and_settle(sp, &mut lateral, t_move0)?,
        };
        self.set_phase(Phase::Acquire);
        let ft = self.acquire_readings()?;
        let frames = self.acquire_frames(sp, ft.t_acquire)?;
        let quality = self.frames_quality(sp, &frames)?;
        let mut forces = self.forces(sp, frames.tracked.as_ref())?;
        // A failed row: no force, and why (the frames first: a dead camera is the
        // cause of whatever tracking and the solver then did).
        let failure = match (&frames.dead, &frames.track_error, &forces.error) {
            (Some(d), _, _) => Some(format!("camera: {d}")),
            (None, Some(t), _) => Some(format!("tracking failed: {t}")),
            (None, None, Some(e)) => Some(format!("reconstruction failed: {e}")),
            (None, None, None) => None,
        };
        if failure.is_some() {
            forces.fsum = [f64::NAN; 3];
            forces.fsum_sd = None;
        }
        if let Some(f) = &failure {
            (self.events)(&RunEvent::Warning {
                index: sp.index,
                message: format!("{f}: row journalled without force (failed row)"),
            });
        }
        self.count_dead(sp.index, frames.dead.as_deref());
        let (quality, plausibility) = if failure.is_none() {
            self.plausibility(sp, &ft.mean.force_n, &ft.sd, &forces.fsum, quality)
        } else {
            self.implausible_run.clear();
            (quality, None)
        };
        let verdict = Verdict {
            quality,
            plausibility,
            failure,
        };
        Ok(journal_row(sp, &reached, ft, &frames, forces, verdict))
    }

    /// Checks before any motion (the lateral target at the retract height and the
    /// deepest allowed indentation there), then, when the contact is to be renewed,
    /// the lateral move at the clearance height, the approach and (up-down sweeps) the
    /// preload. Returns the lateral travel so far (tangential control).
    fn position_at(&mut self, sp: &Setpoint, retract: bool) -> Step<[f64; 2]> {
        let target_xy = [
            sp.position_mm[0] + sp.shift_mm[0],
            sp.position_mm[1] + sp.shift_mm[1],
        ];
        if sp.normal_n > 0.0 {
            let deepest = self
                .geom
                .stage_point(target_xy, self.plan.safety.travel_max_mm[2]);
            self.check_target(deepest)?;
        }
        let safe = self.geom.stage_point(target_xy, -self.geom.clearance_mm);
        self.check_target(safe)?;

        let mut lateral = [0.0; 2];
        if retract || !self.in_contact {
            if sp.shift_mm != [0.0, 0.0] {
                // Displacement trials start from the unshifted position.
                self.move_lateral_at_clearance(sp.position_mm)?;
            }
            self.move_lateral_at_clearance(target_xy)?;
            if sp.normal_n > 0.0 {
                self.approach(target_xy)?;
                self.preload_for_unloading(sp, &mut lateral)?;
            }
        }
        Ok(lateral)
    }

    /// A hold's sample at `t_sched` s: the force is controlled once (its first sample,
    /// or the first one of a resumed hold), then the stage holds its position and each
    /// sample waits for its time in the schedule; no settling.
    fn hold_sample(
        &mut self,
        sp: &Setpoint,
        t_sched: f64,
        lateral: &mut [f64; 2],
        t_move0: Instant,
    ) -> Step<Reached> {
        if self.hold_t0.is_none() {
            self.control(sp, lateral)?;
            self.hold_t0 = Some(Instant::now());
            self.hold_restarted = t_sched > 0.0;
            if self.hold_restarted {
                (self.events)(&RunEvent::Warning {
                    index: sp.index,
                    message: format!(
                        "hold of trial {} resumed part-way: its force was re-established now, and this and its remaining samples are taken at their scheduled times after it (hold_t_s counts from the re-established force; rows journalled settled = false)",
                        sp.trial
                    ),
                });
            }
        }
        let t_move = t_move0.elapsed().as_secs_f64();
        let t0 = self
            .hold_t0
            .ok_or_else(|| Halt::Abort("hold: the force was not reached".into()))?;
        let t_w = Instant::now();
        self.set_phase(Phase::Settle);
        self.hold_wait(t0 + Duration::from_secs_f64(t_sched))?;
        Ok(Reached {
            settled: !self.hold_restarted,
            t_move,
            t_settle: t_w.elapsed().as_secs_f64(),
            hold_t_s: Some(t0.elapsed().as_secs_f64()),
        })
    }

    /// Force control and settling; when the force drifted out of tolerance while
    /// settling (creep), both again, at most [`SETTLE_RETRIES`] times.
    fn control_and_settle(
        &mut self,
        sp: &Setpoint,
        lateral: &mut [f64; 2],
        t_move0: Instant,
    ) -> Step<Reached> {
        let mut settled = true;
        let mut t_settle = 0.0;
        let mut t_move = 0.0;
        for attempt in 0..=SETTLE_RETRIES {
            let t_c = Instant::now();
            if sp.normal_n > 0.0 {
                self.control(sp, lateral)?;
            }
            t_move += if attempt == 0 {
                t_move0.elapsed().as_secs_f64()
            } else {
                t_c.elapsed().as_secs_f64()
            };
            let t_s = Instant::now();
            settled = self.settle()?;
            t_settle += t_s.elapsed().as_secs_f64();
            if sp.normal_n <= 0.0 || attempt == SETTLE_RETRIES {
                break;
            }
            let f = self.mean_force(CONTROL_SAMPLES)?.force_n;
            let dz = (f[2] - sp.normal_n).abs();
            if dz <= self.plan.force_tolerance_n {
                break;
            }
            (self.events)(&RunEvent::Retry {
                index: Some(sp.index),
                attempt: attempt + 1,
                reason: format!(
                    "fz drifted to {:.4} N while settling (target {:.4} N ± {:.4} N): controlling again",
                    f[2], sp.normal_n, self.plan.force_tolerance_n
                ),
            });
        }
        Ok(Reached {
            settled,
            t_move,
            t_settle,
            hold_t_s: None,
        })
    }

    /// The F/T samples (mean and SD, each checked against the safety limits), the
    /// sensor's status since the previous row and the stage position.
    fn acquire_readings(&mut self) -> Step<Readings> {
        let t_acq = Instant::now();
        let n = self.plan.samples;
        let mut samples = Vec::with_capacity(n);
        for _ in 0..n {
            let w = self.read_retry()?;
            if let Some(trip) = check_force_limits(&w, &self.plan.safety.max_force_n) {
                return Err(self.trip(format!("{trip}"), Instant::now()));
            }
            samples.push(w);
        }
        let (mean, sd) = mean_sd(&samples);
        // Flags and counts the sensor reported since the previous row (samples it left
        // out of the readings, network losses, Bota's timestamp and temperature).
        let ft_status = self.dev.take_ft_status();
        let stage = self
            .dev
            .position()
            .map_err(|e| dev_abort("reading the position", &e))?;
        Ok(Readings {
            mean,
            sd,
            ft_status,
            stage,
            t_acquire: t_acq.elapsed().as_secs_f64(),
        })
    }

    /// Frames and tracking; below [quality] min_ok_fraction the frames are grabbed
    /// again (at most max_reacquire times). `t_acquire`: the acquisition time so far,
    /// to which the grabs are added.
    fn acquire_frames(&mut self, sp: &Setpoint, t_acquire: f64) -> Step<Frames> {
        let q = self.plan.quality;
        let mut t_acquire = t_acquire;
        let mut reacquired = 0;
        // `dead`: every acquisition so far had a blank, saturated or markerless frame
        // (the last one's, in words); a dead camera is counted over setpoints.
        let mut dead: Option<String> = None;
        loop {
            let t_f = Instant::now();
            let mut frames = Vec::with_capacity(self.plan.frames);
            for _ in 0..self.plan.frames {
                frames.push(self.grab_retry()?);
            }
            t_acquire += t_f.elapsed().as_secs_f64();
            let this_dead = self.dead_frame(sp.index, &frames);
            let (tracked, t_track, counts, track_error) =
                match self.track_frames(sp.index, &frames)? {
                    Ok((tracked, t_track)) => {
                        let counts = self.setpoint_counts(&tracked);
                        (Some(tracked), t_track, counts, None)
                    }
                    Err(e) => (None, 0.0, self.all_lost(), Some(e)),
                };
            let this_dead = this_dead.or_else(|| {
                (tracked.is_some() && counts.ok + counts.merged + counts.outlier == 0).then(|| {
                    format!(
                        "frames/{:05}_K.png: no marker found in any frame ({})",
                        sp.index,
                        describe(&counts)
                    )
                })
            });
            dead = match (reacquired, this_dead) {
                (0, d) => d,
                (_, Some(d)) if dead.is_some() => Some(d),
                _ => None,
            };
            if tracked.is_some() && ok_fraction(&counts) >= q.min_ok_fraction
                || reacquired >= q.max_reacquire
            {
                return Ok(Frames {
                    tracked,
                    t_track,
                    counts,
                    reacquired,
                    dead,
                    track_error,
                    t_acquire,
                });
            }
            reacquired += 1;
            let what = match &dead {
                Some(d) => d.clone(),
                None => format!("tracking: {}", describe(&counts)),
            };
            (self.events)(&RunEvent::Retry {
                index: Some(sp.index),
                attempt: reacquired,
                reason: format!(
                    "{what}; below [quality] min_ok_fraction {}: re-acquiring the frames ({reacquired} of at most {})",
                    q.min_ok_fraction,
                    q.max_reacquire
                ),
            });
        }
    }

    /// The row's quality after the re-acquisitions: ok, or below [quality]
    /// min_ok_fraction flagged (a warning) or the run aborted (`on_fail`).
    fn frames_quality(&mut self, sp: &Setpoint, f: &Frames) -> Step<RowQuality> {
        let q = self.plan.quality;
        if f.tracked.is_some() && ok_fraction(&f.counts) >= q.min_ok_fraction {
            return Ok(RowQuality::Ok);
        }
        let reacquired = f.reacquired;
        let what = match &f.dead {
            Some(d) => format!("{d} after {reacquired} re-acquisition(s)"),
            None => format!(
                "tracking {} after {reacquired} re-acquisition(s), below [quality] min_ok_fraction {}",
                describe(&f.counts),
                q.min_ok_fraction
            ),
        };
        match q.on_fail {
            OnFail::Flag => {
                (self.events)(&RunEvent::Warning {
                    index: sp.index,
                    message: format!("{what}: row journalled with quality = flagged"),
                });
                Ok(RowQuality::Flagged)
            }
            OnFail::Abort => Err(Halt::Abort(format!(
                "setpoint {}: {what} ([quality] on_fail = \"abort\"); the row is not journalled (its last frames are frames/{:05}_K.png)",
                sp.index,
                sp.index
            ))),
        }
    }

    /// The setpoint's forces from its tracked frames (none when tracking failed: the
    /// frames' names, NaN force sums).
    fn forces(&mut self, sp: &Setpoint, tracked: Option<&Tracked>) -> Step<Forces> {
        Ok(match tracked {
            Some(tracked) => {
                let frames: Vec<String> = tracked.iter().map(|(name, _)| name.clone()).collect();
                self.set_phase(Phase::Solve);
                let (fsum, fsum_sd, t_solve, error) = self.reconstruct(sp.index, tracked)?;
                Forces {
                    frames,
                    fsum,
                    fsum_sd,
                    t_solve,
                    error,
                }
            }
            None => Forces {
                frames: (0..self.plan.frames)
                    .map(|k| format!("frames/{:05}_{k}.png", sp.index))
                    .collect(),
                fsum: [f64::NAN; 3],
                fsum_sd: None,
                t_solve: 0.0,
                error: None,
            },
        })
    }

    /// The markers of the sensor file, all lost (a setpoint whose tracking failed).
    fn all_lost(&self) -> StatusCounts {
        let lost = self.tracker.as_ref().map_or(0, |t| {
            t.reference().markers.len() + t.reference().missing.len()
        });
        StatusCounts {
            lost,
            ..StatusCounts::default()
        }
    }

    /// The first blank or saturated frame of an acquisition, in words (the check `run`
    /// applies to its reference frame before anything moves).
    fn dead_frame(&self, index: usize, frames: &[CameraFrame]) -> Option<String> {
        frames.iter().enumerate().find_map(|(k, f)| {
            let name = format!("frames/{index:05}_{k}.png");
            vision::onboard::check_frame_levels(
                &FrameView::rgb8(&f.image),
                self.sensor.camera.roi_px.as_ref(),
                Path::new(&name),
            )
            .err()
            .map(|e| e.to_string())
        })
    }

    /// Counts consecutive setpoints whose every acquisition was dead; at `[quality]
    /// dead_camera_setpoints` of them the run is to stop after this row is journalled.
    fn count_dead(&mut self, index: usize, dead: Option<&str>) {
        let Some(d) = dead else {
            self.dead_run.clear();
            return;
        };
        self.dead_run.push(index);
        let n = self.plan.quality.dead_camera_setpoints;
        if self.dead_run.len() >= n {
            let list: Vec<String> = self.dead_run.iter().map(|i| i.to_string()).collect();
            self.pending_abort = Some(format!(
                "the camera is dead: {n} consecutive setpoints ({}) gave blank, saturated or markerless frames in every acquisition ([quality] dead_camera_setpoints = {n}); the last: {d}. Likely cause: the camera is covered, unlit, overexposed or disconnected; stage stopped and retracted",
                list.join(", ")
            ));
        }
    }

    /// Run-side force plausibility (module docs of `runner`): the reconstructed
    /// |F^sum| against the F/T sensor's |F|. Returns the row's quality (`implausible`
    /// when the ratio is outside `[quality] force_ratio_min .. force_ratio_max`) and the
    /// finding in words; at `max_implausible_rows` consecutive implausible rows the run
    /// is to stop after this row.
    fn plausibility(
        &mut self,
        sp: &Setpoint,
        ft: &[f64; 3],
        ft_sd: &[f64; 3],
        fsum: &[f64; 3],
        quality: RowQuality,
    ) -> (RowQuality, Option<String>) {
        // A displacement sweep shifts the sensor under a constant load: its force sums
        // are not a measurement of the F/T's load.
        if matches!(
            self.plan.sweep,
            crate::bench::plan::Sweep::Displacement { .. }
        ) {
            return (quality, None);
        }
        let q = self.plan.quality;
        let norm = |v: &[f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        let (f_ft, f_sum) = (norm(ft), norm(fsum));
        let floor = q.force_noise_floor_n.max(3.0 * norm(ft_sd));
        let finding = if !f_sum.is_finite() {
            Some(format!("|F_sum| is {f_sum}"))
        } else if f_sum > q.force_ratio_max * f_ft.max(floor) {
            Some(format!(
                "|F_sum| = {f_sum:.4e} N is more than {} × {} ({:.4} N)",
                q.force_ratio_max,
                if f_ft > floor {
                    "the F/T sensor's |F|"
                } else {
                    "the noise floor"
                },
                f_ft.max(floor)
            ))
        } else if f_ft > floor && f_sum < q.force_ratio_min * f_ft {
            Some(format!(
                "|F_sum| = {f_sum:.4e} N is less than {} × the F/T sensor's |F| ({f_ft:.4} N)",
                q.force_ratio_min
            ))
        } else {
            None
        };
        let Some(finding) = finding else {
            self.implausible_run.clear();
            return (quality, None);
        };
        let ratio = if f_ft > 0.0 {
            f_sum / f_ft
        } else {
            f64::INFINITY
        };
        let text = format!(
            "{finding} (ratio {ratio:.3e}, [quality] force_ratio_min {} .. force_ratio_max {})",
            q.force_ratio_min, q.force_ratio_max
        );
        // A row the tracking gates already flagged keeps that quality: its markers were
        // occluded or lost, which explains the force; the finding is still journalled,
        // and it does not count towards stopping the run.
        if quality == RowQuality::Flagged {
            return (quality, Some(text));
        }
        (self.events)(&RunEvent::Warning {
            index: sp.index,
            message: format!(
                "implausible force: {text}: row journalled with quality = implausible"
            ),
        });
        self.implausible_run.push(sp.index);
        let n = q.max_implausible_rows;
        if self.implausible_run.len() >= n {
            let list: Vec<String> = self.implausible_run.iter().map(|i| i.to_string()).collect();
            let cause = if ratio < 1.0 {
                "the reconstructed force is far too small: the sensor file's lengths in the wrong unit (metres for millimetres: thickness_mm, depth_mm, pitch_mm, mm_per_px), or young_modulus_kpa far too low (not fitted)"
            } else {
                "the reconstructed force is far too large: young_modulus_kpa in the wrong unit (Pa for kPa) or not fitted, the sensor file's lengths or mm_per_px off, or a regularisation too weak for the noise (lambda)"
            };
            self.pending_abort = Some(format!(
                "{n} consecutive rows ({}) failed the force plausibility check ([quality] max_implausible_rows = {n}); the last: {text}. Likely cause: {cause}; stage stopped and retracted",
                list.join(", ")
            ));
        }
        (RowQuality::Implausible, Some(text))
    }

    /// A `down` row of an up-down sweep reached from a fresh contact (a resumed run, or
    /// after a retry that released the contact) is reached by loading to the sweep's
    /// top level first (not journalled), so every `down` row is measured on unloading
    /// from the top, as in an uninterrupted trial.
    fn preload_for_unloading(&mut self, sp: &Setpoint, lateral: &mut [f64; 2]) -> Step<()> {
        let Some(top) = self.plan.top_level_n() else {
            return Ok(());
        };
        if sp.direction != Some(Direction::Down) || top <= sp.normal_n {
            return Ok(());
        }
        (self.events)(&RunEvent::Retry {
            index: Some(sp.index),
            attempt: 1,
            reason: format!(
                "unloading row from a fresh contact: loading to the sweep's top level {top:.4} N first (not journalled), then down to {:.4} N",
                sp.normal_n
            ),
        });
        let top_sp = Setpoint {
            normal_n: top,
            ..*sp
        };
        self.control(&top_sp, lateral)
    }

    /// Waits until `until` with the stage holding its position (a hold sample's time
    /// in the schedule), reading the force sensor every [`HOLD_POLL`] for the safety
    /// limits and stopping at once when asked.
    fn hold_wait(&mut self, until: Instant) -> Step<()> {
        loop {
            if self.stopped() {
                return Err(Halt::Interrupted);
            }
            let now = Instant::now();
            if now >= until {
                return Ok(());
            }
            self.dev.sleep((until - now).min(HOLD_POLL));
            let w = self.read_retry()?;
            if let Some(trip) = check_force_limits(&w, &self.plan.safety.max_force_n) {
                return Err(self.trip(format!("{trip}"), Instant::now()));
            }
        }
    }

    /// Per-setpoint marker counts: each marker's worst status over the frames (lost
    /// before merged before outlier before ok), reference-missing markers lost.
    fn setpoint_counts(&self, tracked: &Tracked) -> StatusCounts {
        let missing = self
            .tracker
            .as_ref()
            .map_or(0, |t| t.reference().missing.len());
        StatusCounts::of_frames(tracked.iter().map(|(_, t)| t.as_slice()), missing)
    }

    /// Detects the reference layout in the reference frame `name` and checks it against
    /// the sensor file: below `[quality] reference_min_found_fraction` of the expected
    /// markers the run stops here, before any setpoint, with the measured numbers and
    /// the likely cause.
    pub(super) fn reference_layout(&mut self, name: &str, frame: &CameraFrame) -> Step<Reference> {
        let view = FrameView::rgb8(&frame.image);
        // A greyscale camera or recording (widened to RGB by its driver, `dir:`
        // included) serves dark and bright layers only: name the coloured one.
        if view.is_achromatic() {
            let layers = self
                .sensor
                .layers
                .iter()
                .map(|l| (l.name.as_str(), l.color));
            if let Some(e) = vision::colour_layer(layers) {
                return Err(Halt::Abort(format!(
                    "reference frame {name} is greyscale (R = G = B in every pixel): {e}; stopped before any setpoint motion (nothing was pressed)"
                )));
            }
        }
        let detected = vision::detect_mapped(
            &view,
            self.sensor,
            &vision::DetectConfig::default(),
            &self.mapping,
        );
        let health = ReferenceHealth::of(detected.as_ref().ok(), self.sensor, &view);
        if let Ok(r) = &detected {
            (self.events)(&RunEvent::Reference {
                path: name.to_string(),
                markers: r.markers.len(),
                missing: r.missing.len(),
            });
        }
        let gate = self.plan.quality.reference_min_found_fraction;
        match detected {
            Ok(r) if health.found_fraction() >= gate => Ok(r),
            other => {
                let mut found = match &other {
                    Ok(_) => health.to_string(),
                    Err(e) => format!("{health} ({e})"),
                };
                // A frame that went blank or saturated after the start's check: say so.
                if let Err(e) = vision::onboard::check_frame_levels(
                    &view,
                    self.sensor.camera.roi_px.as_ref(),
                    Path::new(name),
                ) {
                    found = format!("{e}; {found}");
                }
                let diagnosis = health.diagnosis();
                // With `run --camera` the pixels are mapped by that calibration: it is
                // named, and it is a cause as likely as the sensor file's mapping.
                let through = match &self.camera_path {
                    Some(c) => format!(" through the camera calibration {c}"),
                    None => String::new(),
                };
                let camera_cause = match &self.camera_path {
                    Some(c) => format!(
                        "; or the camera calibration {c} (its scale, origin or distortion) does not fit this camera"
                    ),
                    None => String::new(),
                };
                Err(Halt::Abort(format!(
                    "reference frame {name} does not match the sensor file {}{through}: {found}, below [quality] reference_min_found_fraction {gate}; stopped before any setpoint motion (nothing was pressed). Likely cause: {}{camera_cause}. Measured: {}",
                    self.plan.sensor_path.display(),
                    if diagnosis.is_empty() {
                        "unclear (scale, origin, colours and exposure look right: is the sensor occluded or loaded?)".to_string()
                    } else {
                        diagnosis.join("; ")
                    },
                    health.measurements()
                )))
            }
        }
    }

    /// Saves and tracks a setpoint's frames (`frames/NNNNN_K.png`, overwriting an
    /// earlier acquisition's). Returns the tracks and the tracking time.
    #[allow(clippy::type_complexity)]
    fn track_frames(
        &mut self,
        index: usize,
        frames: &[CameraFrame],
    ) -> Step<Result<(Tracked, f64), String>> {
        let mut tracked: Tracked = Vec::with_capacity(frames.len());
        let mut t_track = 0.0;
        for (k, f) in frames.iter().enumerate() {
            let name = format!("frames/{index:05}_{k}.png");
            let t_io = Instant::now();
            let path = self.dir.join(&name);
            self.fs.step(&name, || f.image.save(&path))?;
            self.io_s += t_io.elapsed().as_secs_f64();
            let t0 = Instant::now();
            let tracker = self
                .tracker
                .as_mut()
                .ok_or_else(|| Halt::Abort("no reference frame".into()))?;
            // A frame the tracker cannot take (a different size, ...) fails this
            // setpoint (a failed row), not the run.
            let tracks = match tracker.track(&FrameView::rgb8(&f.image)) {
                Ok(t) => t.to_vec(),
                Err(e) => return Ok(Err(format!("{name}: {e}"))),
            };
            t_track += t0.elapsed().as_secs_f64();
            tracked.push((name, tracks));
        }
        self.track_s += t_track;
        Ok(Ok((tracked, t_track)))
    }

    /// Writes a setpoint's displacement file and reconstructs its forces from the mean
    /// displacement over the frames. Returns the force sums, their standard deviation
    /// from the tracking noise ([`frame_scatter_mm`] propagated through the solver;
    /// `None` with one frame or when the solve failed) and the solving time.
    #[allow(clippy::type_complexity)]
    fn reconstruct(
        &mut self,
        index: usize,
        tracked: &Tracked,
    ) -> Step<([f64; 3], Option<[f64; 3]>, f64, Option<String>)> {
        let sensor = self.sensor;
        let tracker = self
            .tracker
            .as_ref()
            .ok_or_else(|| Halt::Abort("no reference frame".into()))?;
        let t_io = Instant::now();
        let dpath = format!("displacements/{index:05}.csv");
        let path = self.dir.join(&dpath);
        let mapping = &self.mapping;
        self.fs.step(&dpath, || {
            vision::write_tracks_mapped(&path, sensor, tracker.reference(), tracked, mapping)
        })?;
        self.io_s += t_io.elapsed().as_secs_f64();

        // Mean displacement over the frames; a marker lost in any frame is lost.
        let t0 = Instant::now();
        let (records, sigma_mean_mm) = mean_over_frames(
            tracked
                .iter()
                .map(|(_, tracks)| tracker.displacement_records_mapped(tracks, &self.mapping)),
        );
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
        let precompute_s = solved.precompute_s;
        let t_solve = (t0.elapsed().as_secs_f64() - precompute_s).max(0.0);
        self.precompute_s += precompute_s;
        let SolvedSetpoint {
            f,
            fsum,
            fsum_sd,
            node_sd,
            error,
            ..
        } = solved;
        let t_io = Instant::now();
        let fpath = format!("forces/{index:05}.csv");
        let path = self.dir.join(&fpath);
        self.fs.step(&fpath, || match node_sd {
            Some(sd) => {
                formats::write_forces_sd(&path, &sensor.force_grid, &[(String::new(), f)], &[sd])
            }
            None => formats::write_forces(&path, &sensor.force_grid, &[(String::new(), f)]),
        })?;
        self.io_s += t_io.elapsed().as_secs_f64();
        self.solve_s += t_solve;
        Ok((fsum, fsum_sd, t_solve, error))
    }
}

/// A setpoint's forces from its mean displacements (`frame`) and the noise of that
/// mean: what the runner and `bench::synthetic_run` record.
pub struct SolvedSetpoint {
    /// Node forces (interleaved `fx, fy, fz`, N); NaN when the solve failed.
    pub f: Vec<f64>,
    /// Their sum, N.
    pub fsum: [f64; 3],
    /// σ of the sum from the frames' scatter (`None` without an estimate or on failure).
    pub fsum_sd: Option<[f64; 3]>,
    /// Per-node σ of the same noise, per component, when the solver gives it.
    pub node_sd: Option<Vec<f64>>,
    /// Seconds spent building a solver for a new set of markers (0 when cached).
    pub precompute_s: f64,
    /// Why the solve failed.
    pub error: Option<String>,
}

/// Solves a setpoint with the plan's solver, one cached per set of markers found
/// (`solvers`, keyed by which markers carry a displacement). An exactly unmoved frame
/// (an ideal unloaded setpoint) is zero force for every linear solver; solving it would
/// let automatic λ / rank be chosen (and cached for the run) on a frame with no signal,
/// which fails. Frames that agree exactly (`sigma_mean_mm == Some(0)`) carry no noise,
/// whatever the solver. A solver that cannot give per-node σ still solves: the forces
/// file then carries no σ columns and the report says the run did not record it.
pub fn solve_setpoint(
    solvers: &mut HashMap<Vec<bool>, Box<dyn FrameSolver>>,
    sensor: &Sensor,
    config: &SolverConfig,
    frame: &DisplacementFrame,
    sigma_mean_mm: Option<f64>,
) -> SolvedSetpoint {
    let sites = frame.sites(sensor);
    let u = frame.u_mm();
    let key: Vec<bool> = frame.records.iter().map(|r| r.u_mm.is_some()).collect();
    let n_out = 3 * sensor.force_grid.len();
    let mut f = vec![f64::NAN; n_out];
    let mut precompute_s = 0.0;
    let mut fsum_sd = None;
    let mut node_sd: Option<Vec<f64>> = None;
    let solved: Result<(), String> = (|| {
        if !u.is_empty() && u.iter().all(|v| *v == 0.0) {
            f.iter_mut().for_each(|v| *v = 0.0);
            if sigma_mean_mm == Some(0.0) {
                fsum_sd = Some([0.0; 3]);
                node_sd = Some(vec![0.0; n_out]);
            }
            return Ok(());
        }
        if !solvers.contains_key(&key) {
            let tp = Instant::now();
            let problem = Problem::new(sensor, &sites);
            let s = solve::precompute(&problem, config, Some(&u)).map_err(|e| e.to_string())?;
            solvers.insert(key.clone(), s);
            precompute_s = tp.elapsed().as_secs_f64();
        }
        let s = solvers
            .get_mut(&key)
            .ok_or_else(|| "solver cache".to_string())?;
        s.apply(&u, &mut f).map_err(|e| e.to_string())?;
        if let Some(sigma) = sigma_mean_mm {
            fsum_sd = Some(solve::force_sum_sd(&**s, sigma).map_err(|e| e.to_string())?);
            let mut sd = vec![0.0; n_out];
            node_sd = s.force_sd(sigma, &mut sd).ok().map(|()| sd);
        }
        Ok(())
    })();
    let error = solved.err();
    if error.is_some() {
        fsum_sd = None;
        node_sd = None;
        f.iter_mut().for_each(|v| *v = f64::NAN);
    }
    let mut fsum = [0.0; 3];
    for (j, v) in f.iter().enumerate() {
        fsum[j % 3] += v;
    }
    SolvedSetpoint {
        f,
        fsum,
        fsum_sd,
        node_sd,
        precompute_s,
        error,
    }
}

/// A setpoint's displacement records averaged over its frames (a marker lost in any
/// frame is lost), and the noise of that mean: the frames' scatter
/// ([`frame_scatter_mm`]) / √frames. Shared by the runner and `bench::synthetic_run`.
pub fn mean_over_frames(
    frames: impl Iterator<Item = Vec<formats::DisplacementRecord>>,
) -> (Vec<formats::DisplacementRecord>, Option<f64>) {
    let mut records: Vec<formats::DisplacementRecord> = Vec::new();
    let mut per_frame = Vec::new();
    for (k, r) in frames.enumerate() {
        per_frame.push(r.iter().map(|x| x.u_mm).collect::<Vec<_>>());
        if k == 0 {
            records = r;
        } else {
            for (acc, x) in records.iter_mut().zip(r) {
                acc.u_mm = match (acc.u_mm, x.u_mm) {
                    (Some(a), Some(b)) => Some([a[0] + b[0], a[1] + b[1]]),
                    _ => None,
                };
            }
        }
    }
    let nf = per_frame.len().max(1) as f64;
    for r in &mut records {
        if let Some(u) = r.u_mm.as_mut() {
            u[0] /= nf;
            u[1] /= nf;
        }
    }
    (records, frame_scatter_mm(&per_frame).map(|s| s / nf.sqrt()))
}

/// The tracking noise of one displacement component, mm: the pooled frame-to-frame
/// scatter `sqrt(Σ (u_k − ū)² / (n_markers · 2 · (frames − 1)))` over the markers found
/// in every frame of a setpoint. `None` with fewer than two frames or no such marker.
pub fn frame_scatter_mm(frames: &[Vec<Option<[f64; 2]>>]) -> Option<f64> {
    let nf = frames.len();
    let first = frames.first()?;
    if nf < 2 {
        return None;
    }
    let (mut ss, mut dof) = (0.0f64, 0usize);
    for i in 0..first.len() {
        let us: Option<Vec<[f64; 2]>> =
            frames.iter().map(|f| f.get(i).copied().flatten()).collect();
        let Some(us) = us else { continue };
        for ax in 0..2 {
            let mean = us.iter().map(|u| u[ax]).sum::<f64>() / nf as f64;
            ss += us.iter().map(|u| (u[ax] - mean).powi(2)).sum::<f64>();
            dof += nf - 1;
        }
    }
    (dof > 0).then(|| (ss / dof as f64).sqrt())
}

/// Markers ok / all markers of the sensor file.
fn ok_fraction(c: &StatusCounts) -> f64 {
    let total = c.ok + c.lost + c.merged + c.outlier;
    if total == 0 {
        0.0
    } else {
        c.ok as f64 / total as f64
    }
}

/// `"200 of 260 markers ok (77 %; 50 lost, 8 merged, 2 outliers)"`.
fn describe(c: &StatusCounts) -> String {
    format!(
        "{} of {} markers ok ({:.0} %; {} lost, {} merged, {} outliers)",
        c.ok,
        c.ok + c.lost + c.merged + c.outlier,
        100.0 * ok_fraction(c),
        c.lost,
        c.merged,
        c.outlier
    )
}

/// Mean wrench and per-component force SD (sample SD; 0 for one sample).
pub(super) fn mean_sd(samples: &[Wrench]) -> (Wrench, [f64; 3]) {
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
