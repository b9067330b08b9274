//! Motion: device calls with their time accounted ([`Timed`]), travel checks, guarded
//! moves under the force watchdog, retract, lateral moves and the approach with contact
//! detection.
//!
//! Pacing (issue 11): the loop blocks on the devices instead of spinning.
//! - Force/torque reads (everywhere in the run, not only in motion) are paced to the
//!   sensor's own rate, [`ForceSensor::sample_rate_hz`](crate::device::ForceSensor):
//!   a read starts at least one sample period after the previous one started
//!   (DynPick 1 ms, FT 300 stream 10 ms, FT 300 polled 13 ms at 19200 baud). The
//!   watchdog sees every sample the sensor produces and no duplicate.
//! - Stage status during a move is paced to the controller's documented rate,
//!   [`Stage::status_interval`](crate::device::Stage) (GRBL 200 ms = 5 Hz, its
//!   interface guide's recommendation; Zaber 20 ms), plus one query at the move's
//!   expected end (distance / speed + [`STATUS_ETA_MARGIN`]): completion is `Idle`
//!   in a paced report (GRBL) / `IDLE` (Zaber), usually seen at that first query.
//! - A status query that gets no (or a garbled) answer is tolerated while the force
//!   is still watched: the move aborts only after [`STATUS_MISSES`] in a row (GRBL
//!   does not guarantee an answer to every `?`).

use std::time::{Duration, Instant};

use super::{
    dev_abort, Devices, Halt, RunEvent, Runner, Step, MOVE_GRACE, POSITION_TOLERANCE_MM,
    READ_RETRIES,
};
use crate::bench::control::check_force_limits;
use crate::device::{CameraFrame, DeviceResult, ErrorKind, StagePositionMm, StageState, Wrench};

/// Consecutive unanswered (or garbled) stage status queries a move tolerates.
pub const STATUS_MISSES: u32 = 3;
/// The status query at a move's expected end comes this long after it (the
/// controller starts the move a little after it acknowledged it).
pub const STATUS_ETA_MARGIN: Duration = Duration::from_millis(5);
/// Longest pause between force readings, whatever the sensor claims as its rate.
pub const MAX_FT_PERIOD: Duration = Duration::from_millis(20);

/// One sample period of a sensor delivering `rate_hz` samples per second, at most
/// [`MAX_FT_PERIOD`]; zero (no pacing) for a rate that is not a positive number.
pub fn ft_sample_period(rate_hz: f64) -> Duration {
    if rate_hz.is_finite() && rate_hz > 0.0 {
        Duration::from_secs_f64((1.0 / rate_hz).min(MAX_FT_PERIOD.as_secs_f64()))
    } else {
        Duration::ZERO
    }
}

/// When to ask the stage for its status during a move: every `interval`, and once at
/// the move's expected end `eta`.
#[derive(Debug, Clone, Copy)]
pub struct StatusPacer {
    interval: Duration,
    eta: Instant,
    next: Instant,
}

impl StatusPacer {
    /// A move starting `now` and expected to end at `eta`.
    pub fn new(interval: Duration, now: Instant, eta: Instant) -> Self {
        StatusPacer {
            interval,
            eta,
            next: (now + interval).min(eta.max(now)),
        }
    }
    /// When the next query is due.
    pub fn next(&self) -> Instant {
        self.next
    }
    /// Whether a query is due at `now`.
    pub fn due(&self, now: Instant) -> bool {
        now >= self.next
    }
    /// A query was made at `now`: the next one is an interval later, or at the
    /// expected end if that comes first.
    pub fn queried(&mut self, now: Instant) {
        let after = now + self.interval;
        self.next = if self.eta > now && self.eta < after {
            self.eta
        } else {
            after
        };
    }
}

/// Device calls with the time spent in them accounted; force readings paced to the
/// sensor's rate.
pub(super) struct Timed<'d, 'a> {
    pub(super) dev: &'d mut Devices<'a>,
    pub(super) blocked: Duration,
    /// Shortest interval between the starts of two force readings.
    ft_period: Duration,
    /// When the last force reading started.
    last_ft_read: Option<Instant>,
}

macro_rules! timed {
    ($self:ident, $e:expr) => {{
        let t0 = Instant::now();
        let r = $e;
        $self.blocked += t0.elapsed();
        r
    }};
}

impl<'d, 'a> Timed<'d, 'a> {
    pub(super) fn new(dev: &'d mut Devices<'a>) -> Self {
        let ft_period = ft_sample_period(dev.ft.sample_rate_hz());
        Timed {
            dev,
            blocked: Duration::ZERO,
            ft_period,
            last_ft_read: None,
        }
    }
}

impl Timed<'_, '_> {
    /// Sleeps until one sample period has passed since the last reading started.
    fn pace_ft(&mut self) {
        if let Some(last) = self.last_ft_read {
            let due = last + self.ft_period;
            let now = Instant::now();
            if due > now {
                timed!(self, std::thread::sleep(due - now));
            }
        }
        self.last_ft_read = Some(Instant::now());
    }
    pub(super) fn read(&mut self) -> DeviceResult<Wrench> {
        self.pace_ft();
        timed!(self, self.dev.ft.read())
    }
    pub(super) fn read_once(&mut self) -> DeviceResult<Wrench> {
        self.pace_ft();
        timed!(self, self.dev.ft.read_once())
    }
    pub(super) fn tare(&mut self) -> DeviceResult<()> {
        timed!(self, self.dev.ft.tare())
    }
    pub(super) fn take_ft_status(&mut self) -> Option<String> {
        self.dev.ft.take_status()
    }
    pub(super) fn move_to(&mut self, p: StagePositionMm, v: f64) -> DeviceResult<()> {
        timed!(self, self.dev.stage.move_to(p, Some(v)))
    }
    pub(super) fn position(&mut self) -> DeviceResult<StagePositionMm> {
        timed!(self, self.dev.stage.position())
    }
    pub(super) fn state(&mut self) -> DeviceResult<StageState> {
        timed!(self, self.dev.stage.state())
    }
    pub(super) fn stop(&mut self) -> DeviceResult<()> {
        timed!(self, self.dev.stage.stop())
    }
    pub(super) fn wait_idle(&mut self, t: Duration) -> DeviceResult<()> {
        timed!(self, self.dev.stage.wait_idle(t))
    }
    pub(super) fn home(&mut self) -> DeviceResult<()> {
        timed!(self, self.dev.stage.home())
    }
    pub(super) fn grab(&mut self) -> DeviceResult<CameraFrame> {
        timed!(self, self.dev.camera.grab())
    }
    pub(super) fn sleep(&mut self, d: Duration) {
        timed!(self, std::thread::sleep(d))
    }
}

impl Runner<'_, '_, '_, '_> {
    /// Checks a stage target against the plan's sensor-frame box and the stage box.
    pub(super) fn check_target(&self, target: StagePositionMm) -> Step<()> {
        let s = &self.plan.safety;
        let xy = self.geom.sensor_xy(target);
        let depth = self.geom.depth(target[2]);
        let p = [xy[0], xy[1], depth];
        for (i, name) in ["x", "y", "depth z"].iter().enumerate() {
            let v = p[i];
            if !(v.is_finite() && v >= s.travel_min_mm[i] - 1e-9 && v <= s.travel_max_mm[i] + 1e-9)
            {
                return Err(Halt::Abort(format!(
                    "refused before moving: sensor-frame {name} = {v:.4} mm is outside the plan's travel box {}..{} mm",
                    s.travel_min_mm[i], s.travel_max_mm[i]
                )));
            }
        }
        self.stage_limits
            .check(target)
            .map_err(|e| Halt::Abort(format!("refused before moving: stage {e}")))
    }

    /// The watchdog fired at `detected`: stop, measure the latency, retract, abort.
    pub(super) fn trip(&mut self, what: String, detected: Instant) -> Halt {
        let stop = self.dev.stop();
        // Standing still: the stop call returned and the stage reports no motion.
        let deadline = Instant::now() + Duration::from_secs(2);
        while let Ok(StageState::Moving) = self.dev.state() {
            if Instant::now() > deadline {
                break;
            }
        }
        let latency = detected.elapsed().as_secs_f64();
        let stop_note = match stop {
            Ok(()) => String::new(),
            Err(e) => format!(" (stop command failed: {e})"),
        };
        let reason = format!(
            "safety limit: {what}{}; stage stopped {:.1} ms after the reading{stop_note}",
            self.index
                .map(|i| format!(" at setpoint {i}"))
                .unwrap_or_default(),
            latency * 1e3
        );
        (self.events)(&RunEvent::SafetyTrip {
            index: self.index,
            reason: reason.clone(),
            stop_latency_s: latency,
        });
        self.commanded = None;
        Halt::Abort(reason)
    }

    /// A move under the watchdog. With `contact_n`, stops as soon as fz ≥ it and
    /// returns `true` (contact); otherwise returns once the target is reached.
    pub(super) fn guarded_move(
        &mut self,
        target: StagePositionMm,
        speed_mm_s: f64,
        contact_n: Option<f64>,
    ) -> Step<bool> {
        self.check_target(target)?;
        if self.stopped() {
            return Err(Halt::Interrupted);
        }
        let speed = speed_mm_s.min(self.plan.safety.max_speed_mm_s);
        let from = self.commanded;
        self.dev
            .move_to(target, speed)
            .map_err(|e| dev_abort(&format!("moving to {target:?} mm"), &e))?;
        self.commanded = Some(target);
        let distance = from.map_or(100.0, |f| {
            ((f[0] - target[0]).powi(2) + (f[1] - target[1]).powi(2) + (f[2] - target[2]).powi(2))
                .sqrt()
        });
        let expected = Duration::from_secs_f64(distance / speed);
        let mut deadline = Instant::now() + expected * 2 + MOVE_GRACE;
        let interval = self.dev.dev.stage.status_interval();
        let now = Instant::now();
        let mut pacer = StatusPacer::new(interval, now, now + expected + STATUS_ETA_MARGIN);
        let mut read_failures = 0;
        let mut misses = 0;
        loop {
            if self.stopped() {
                let _ = self.dev.stop();
                return Err(Halt::Interrupted);
            }
            // One attempt per reading: the driver's retries would keep the stage
            // moving blind for several reply deadlines.
            let w = match self.dev.read_once() {
                Ok(w) => w,
                Err(e) => {
                    // Blind while moving: stop first, then try to recover the sensor
                    // and finish the move from where the stage stopped.
                    let _ = self.dev.stop();
                    if e.kind() == ErrorKind::Disconnected || read_failures >= READ_RETRIES {
                        return Err(dev_abort("reading the force sensor while moving", &e));
                    }
                    read_failures += 1;
                    (self.events)(&RunEvent::Retry {
                        index: self.index,
                        attempt: read_failures,
                        reason: format!(
                            "force sensor read failed while moving ({e}): stage stopped, resuming the move"
                        ),
                    });
                    let w = self.read_retry()?;
                    if let Some(trip) = check_force_limits(&w, &self.plan.safety.max_force_n) {
                        return Err(self.trip(format!("{trip}"), Instant::now()));
                    }
                    self.dev.move_to(target, speed).map_err(|e| {
                        dev_abort(&format!("resuming the move to {target:?} mm"), &e)
                    })?;
                    deadline += MOVE_GRACE;
                    let now = Instant::now();
                    pacer = StatusPacer::new(interval, now, now + expected + STATUS_ETA_MARGIN);
                    continue;
                }
            };
            if let Some(trip) = check_force_limits(&w, &self.plan.safety.max_force_n) {
                return Err(self.trip(format!("{trip}"), Instant::now()));
            }
            self.reading(&w);
            if let Some(c) = contact_n {
                if w.force_n[2] >= c {
                    self.dev
                        .stop()
                        .map_err(|e| dev_abort("stopping at contact", &e))?;
                    let p = self
                        .dev
                        .position()
                        .map_err(|e| dev_abort("reading the position at contact", &e))?;
                    self.commanded = Some(p);
                    (self.events)(&RunEvent::Contact {
                        index: self.index.unwrap_or(0),
                        depth_mm: self.geom.depth(p[2]),
                        fz_n: w.force_n[2],
                    });
                    return Ok(true);
                }
            }
            let now = Instant::now();
            if pacer.due(now) {
                pacer.queried(now);
                if let Some(state) = self.paced_state(&mut misses, interval)? {
                    match state {
                        StageState::Idle => {
                            let p = self
                                .dev
                                .position()
                                .map_err(|e| dev_abort("reading the position", &e))?;
                            let tol = self.reached_tolerance();
                            if (0..3).all(|i| (p[i] - target[i]).abs() <= tol[i]) {
                                return Ok(false);
                            }
                        }
                        StageState::Alarm => {
                            return Err(Halt::Abort(format!(
                                "the stage entered its alarm state while moving to {target:?} mm"
                            )))
                        }
                        _ => {}
                    }
                }
            }
            if Instant::now() > deadline {
                let _ = self.dev.stop();
                return Err(Halt::Abort(format!(
                    "the stage did not reach {target:?} mm within {:.1} s",
                    (distance / speed) * 2.0 + MOVE_GRACE.as_secs_f64()
                )));
            }
        }
    }

    /// Per axis, how far from its target a stage standing still counts as arrived:
    /// [`POSITION_TOLERANCE_MM`], or half the stage's step where that is coarser
    /// (Marlin rounds targets to whole steps, e.g. 12.5 µm at 80 steps/mm).
    fn reached_tolerance(&self) -> [f64; 3] {
        let r = self.dev.dev.stage.resolution_mm();
        [0, 1, 2].map(|i| POSITION_TOLERANCE_MM.max(0.5 * r[i] + 1e-9))
    }

    /// A paced status query during a move: the state, or `None` when the controller
    /// did not answer (or garbled the answer) and fewer than [`STATUS_MISSES`] queries
    /// in a row went so (reported as a retry; the caller keeps watching the force).
    fn paced_state(&mut self, misses: &mut u32, interval: Duration) -> Step<Option<StageState>> {
        match self.dev.state() {
            Ok(s) => {
                *misses = 0;
                Ok(Some(s))
            }
            Err(e)
                if matches!(e.kind(), ErrorKind::Timeout | ErrorKind::Protocol)
                    && *misses + 1 < STATUS_MISSES =>
            {
                *misses += 1;
                (self.events)(&RunEvent::Retry {
                    index: self.index,
                    attempt: *misses as usize,
                    reason: format!(
                        "stage status query unanswered while moving ({e}): asking again in {} ms",
                        interval.as_millis()
                    ),
                });
                Ok(None)
            }
            Err(e) => Err(dev_abort("polling the stage", &e)),
        }
    }

    /// Stage z of the retract height.
    pub(super) fn safe_z(&self) -> f64 {
        self.geom.stage_z(-self.geom.clearance_mm)
    }

    /// Moves up to the retract height (z only) under the watchdog, unless already there.
    pub(super) fn retract(&mut self) -> Step<()> {
        let here = match self.commanded {
            Some(p) => p,
            None => {
                let p = self
                    .dev
                    .position()
                    .map_err(|e| dev_abort("reading the position", &e))?;
                self.commanded = Some(p);
                p
            }
        };
        self.in_contact = false;
        self.hold_t0 = None;
        self.normal_ctl.reset();
        if let Some(t) = self.tracker.as_mut() {
            t.reset();
        }
        if self.geom.depth(here[2]) <= -self.geom.clearance_mm + 1e-6 {
            return Ok(());
        }
        let target = [here[0], here[1], self.safe_z()];
        // Only the stage box applies to a retract (the plan box may not contain the
        // position a killed run or a homing cycle left).
        self.stage_limits
            .check(target)
            .map_err(|e| Halt::Abort(format!("refused before moving: stage {e}")))?;
        let v = self.plan.safety.max_speed_mm_s;
        self.dev
            .move_to(target, v)
            .map_err(|e| dev_abort("retracting", &e))?;
        self.commanded = Some(target);
        let expected = Duration::from_secs_f64((here[2] - target[2]).abs() / v);
        self.wait_reached(target, expected)
    }

    /// Retract after a stop or abort: no watchdog (the force only falls), best effort.
    pub(super) fn retract_unguarded(&mut self) -> Result<(), String> {
        let here = self.dev.position().map_err(|e| e.to_string())?;
        self.commanded = Some(here);
        if self.geom.depth(here[2]) <= -self.geom.clearance_mm + 1e-6 {
            return Ok(());
        }
        let target = [here[0], here[1], self.safe_z()];
        self.stage_limits.check(target)?;
        // A stop may have left the controller held or locked.
        if let Ok(StageState::Alarm) = self.dev.state() {
            let _ = self.dev.dev.stage.unlock();
        }
        self.dev
            .move_to(target, self.plan.safety.max_speed_mm_s)
            .map_err(|e| e.to_string())?;
        self.dev
            .wait_idle(Duration::from_secs(30))
            .map_err(|e| e.to_string())?;
        self.commanded = Some(target);
        self.in_contact = false;
        self.hold_t0 = None;
        Ok(())
    }

    /// Waits for a move the watchdog need not see (retract, the force only falls),
    /// expected to take `expected`: blocks until the next paced status query
    /// ([`StatusPacer`]), done when the stage is idle at the target.
    pub(super) fn wait_reached(&mut self, target: StagePositionMm, expected: Duration) -> Step<()> {
        let now = Instant::now();
        let deadline = now + expected * 2 + MOVE_GRACE * 4;
        let interval = self.dev.dev.stage.status_interval();
        let mut pacer = StatusPacer::new(interval, now, now + expected + STATUS_ETA_MARGIN);
        let mut misses = 0;
        loop {
            if self.stopped() {
                let _ = self.dev.stop();
                return Err(Halt::Interrupted);
            }
            let wait = pacer.next().saturating_duration_since(Instant::now());
            if !wait.is_zero() {
                self.dev.sleep(wait);
            }
            pacer.queried(Instant::now());
            match self.paced_state(&mut misses, interval)? {
                Some(StageState::Idle) => {
                    let p = self
                        .dev
                        .position()
                        .map_err(|e| dev_abort("reading the position", &e))?;
                    let tol = self.reached_tolerance();
                    if (0..3).all(|i| (p[i] - target[i]).abs() <= tol[i]) {
                        return Ok(());
                    }
                }
                Some(StageState::Alarm) => {
                    return Err(Halt::Abort(format!(
                        "the stage entered its alarm state while moving to {target:?} mm"
                    )));
                }
                _ => {}
            }
            if Instant::now() > deadline {
                return Err(Halt::Abort(format!(
                    "the stage did not reach {target:?} mm in time"
                )));
            }
        }
    }

    /// Retract (if needed) and move to a sensor-frame point at the retract height.
    pub(super) fn move_lateral_at_clearance(&mut self, xy_mm: [f64; 2]) -> Step<()> {
        self.retract()?;
        let target = self.geom.stage_point(xy_mm, -self.geom.clearance_mm);
        if let Some(c) = self.commanded {
            if (0..3).all(|i| (c[i] - target[i]).abs() <= 1e-9) {
                return Ok(());
            }
        }
        self.guarded_move(target, self.plan.safety.max_speed_mm_s, None)?;
        Ok(())
    }

    /// Approach until contact at `xy_mm`.
    pub(super) fn approach(&mut self, xy_mm: [f64; 2]) -> Step<()> {
        let deepest = self
            .geom
            .stage_point(xy_mm, self.plan.safety.travel_max_mm[2]);
        let contact = self.guarded_move(
            deepest,
            self.plan.approach_speed_mm_s,
            Some(self.plan.contact_force_n),
        )?;
        if !contact {
            return Err(Halt::Abort(format!(
                "no contact (fz < {:.4} N) down to the deepest allowed indentation {} mm (safety.travel_max_mm[2]): check the bench geometry's surface_z_mm",
                self.plan.contact_force_n, self.plan.safety.travel_max_mm[2]
            )));
        }
        self.in_contact = true;
        self.hold_t0 = None;
        self.normal_ctl.reset();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn status_pacer_queries_every_interval_and_once_at_the_expected_end() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        // GRBL's 200 ms, a move expected to end at 450 ms.
        let mut p = StatusPacer::new(ms(200), t0, t0 + ms(450));
        assert_eq!(p.next(), t0 + ms(200));
        assert!(!p.due(t0 + ms(199)) && p.due(t0 + ms(200)));
        p.queried(t0 + ms(200));
        assert_eq!(p.next(), t0 + ms(400));
        p.queried(t0 + ms(400));
        assert_eq!(p.next(), t0 + ms(450), "the expected end comes first");
        p.queried(t0 + ms(450));
        assert_eq!(p.next(), t0 + ms(650), "then every interval again");
        // A move shorter than one interval: the first query at its end.
        let p = StatusPacer::new(ms(200), t0, t0 + ms(30));
        assert_eq!(p.next(), t0 + ms(30));
        // Expected end already past: at once.
        let p = StatusPacer::new(ms(200), t0 + ms(10), t0);
        assert_eq!(p.next(), t0 + ms(10));
    }

    #[test]
    fn force_reads_are_paced_to_one_sample_period() {
        assert_eq!(ft_sample_period(1000.0), Duration::from_millis(1));
        assert_eq!(ft_sample_period(100.0), Duration::from_millis(10));
        assert_eq!(ft_sample_period(1.0), MAX_FT_PERIOD);
        for bad in [0.0, -5.0, f64::NAN, f64::INFINITY] {
            assert_eq!(ft_sample_period(bad), Duration::ZERO, "{bad}");
        }
    }
}
