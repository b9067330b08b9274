//! A stage move outside a run (`tactbench stage move|jog`), watched as the runner's
//! safety watchdog watches its moves (`runner/motion.rs`): until the stage is idle,
//! the loop looks at a stop flag (set by the CLI's signal handler: Ctrl-C, SIGTERM)
//! every [`FLAG_POLL`], reads the force sensor when one is given (one attempt per
//! reading, paced to the sensor's rate, [`ft_sample_period`]) against per-component
//! limits, and asks the stage for its state at the controller's own rate
//! ([`Stage::status_interval`], unanswered queries tolerated as the runner does).
//!
//! When it must stop, it stops as the watchdog does: [`Stage::stop`] (GRBL: jog cancel,
//! or feed hold then a soft reset that discards the buffered moves; Marlin: `M410`
//! through the emergency parser, then `M114` re-syncs the position; Zaber: `stop`),
//! waits until the stage reports no motion, and measures the stop latency: from the
//! signal (or the offending force reading) to the stage standing still. It returns
//! where the stage stopped and its state, for the caller to report.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use super::control::{check_force_limits, LimitTrip};
use super::runner::{ft_sample_period, STATUS_MISSES};
use crate::device::{
    DeviceError, DeviceResult, ErrorKind, ForceSensor, Stage, StagePositionMm, StageState,
};

/// How often the loop looks at the stop flag: the part of the stop latency spent
/// noticing a signal.
pub const FLAG_POLL: Duration = Duration::from_millis(1);

/// Longest wait for the stage to report no motion after the stop command. Longer
/// than the runner's 2 s (`Runner::trip`, which retracts afterwards): the command must
/// not exit and report a position while the stage still decelerates (GRBL's jog cancel
/// and feed hold ramp down at `$120..$122`; the real firmware on grbl-sim under load
/// runs several times slower than real time and took over 2 s).
pub const STANDSTILL_WAIT: Duration = Duration::from_secs(10);

/// `CLOCK_MONOTONIC` in nanoseconds: what a signal handler may read
/// (`clock_gettime` is async-signal-safe), comparable across threads.
pub fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec; CLOCK_MONOTONIC always exists on
    // Linux, and clock_gettime only writes `ts`.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    if rc != 0 {
        return 0;
    }
    (ts.tv_sec as u64)
        .saturating_mul(1_000_000_000)
        .saturating_add(ts.tv_nsec as u64)
}

/// What a watched move looks at.
pub struct MotionWatch<'a> {
    /// Set to ask for a stop (the CLI's signal handler).
    pub stop: &'a AtomicBool,
    /// When the stop was asked, [`monotonic_ns`] (0: unknown; the latency then counts
    /// from the moment the loop noticed the flag).
    pub stop_asked_ns: &'a AtomicU64,
    /// The force sensor and the per-component limits |fx|, |fy|, |fz| in N.
    pub force: Option<(&'a mut dyn ForceSensor, [f64; 3])>,
    /// Longest time the move may take before it is stopped.
    pub timeout: Duration,
}

/// Why a watched move was stopped.
#[derive(Debug, Clone)]
pub enum StopCause {
    /// The stop flag was set (a signal).
    Requested,
    /// A force component beyond its limit.
    ForceLimit(LimitTrip),
    /// The force sensor gave no reading: stopped rather than moving blind.
    ForceUnread(String),
    /// The move did not end within the timeout.
    Timeout(Duration),
}

/// A watched move that was stopped: why, how fast, and where the stage stands.
#[derive(Debug)]
pub struct Stopped {
    /// Why.
    pub cause: StopCause,
    /// From the signal (or the offending reading) to the stage reporting no motion.
    pub latency: Duration,
    /// The stop command's error, when it failed.
    pub stop_error: Option<DeviceError>,
    /// Where the stage stands after the stop.
    pub position: DeviceResult<StagePositionMm>,
    /// Its state after the stop.
    pub state: DeviceResult<StageState>,
}

/// How a watched move ended.
#[derive(Debug)]
pub enum Watched {
    /// The stage reported no motion on its own: the move is over (the caller checks
    /// the target with [`Stage::wait_idle`]).
    Ended,
    /// It was stopped (boxed: the report is large, the common outcome is `Ended`).
    Stopped(Box<Stopped>),
}

/// Watches a move that has been started on `stage` until it ends or must be stopped
/// (see the module doc). Errors only when the stage cannot be polled (after trying to
/// stop it).
pub fn watch_move(stage: &mut dyn Stage, w: MotionWatch<'_>) -> DeviceResult<Watched> {
    let MotionWatch {
        stop,
        stop_asked_ns,
        mut force,
        timeout,
    } = w;
    let t0 = Instant::now();
    let deadline = t0 + timeout;
    let interval = stage.status_interval();
    let ft_period = force.as_ref().map_or(Duration::ZERO, |(f, _)| {
        ft_sample_period(f.sample_rate_hz())
    });
    let mut next_status = t0 + interval;
    let mut next_ft = t0;
    let mut misses = 0;
    loop {
        if stop.load(Ordering::SeqCst) {
            let asked = stop_asked_ns.load(Ordering::SeqCst);
            let already = if asked == 0 {
                Duration::ZERO
            } else {
                Duration::from_nanos(monotonic_ns().saturating_sub(asked))
            };
            return Ok(Watched::Stopped(Box::new(halt(
                stage,
                StopCause::Requested,
                Instant::now(),
                already,
            ))));
        }
        let now = Instant::now();
        if let Some((ft, limits)) = force.as_mut() {
            if now >= next_ft {
                next_ft = now + ft_period;
                match ft.read_once() {
                    Ok(reading) => {
                        if let Some(trip) = check_force_limits(&reading, limits) {
                            let cause = StopCause::ForceLimit(trip);
                            return Ok(Watched::Stopped(Box::new(halt(
                                stage,
                                cause,
                                now,
                                Duration::ZERO,
                            ))));
                        }
                    }
                    Err(e) => {
                        let cause = StopCause::ForceUnread(e.to_string());
                        return Ok(Watched::Stopped(Box::new(halt(
                            stage,
                            cause,
                            now,
                            Duration::ZERO,
                        ))));
                    }
                }
            }
        }
        if now >= next_status {
            next_status = now + interval;
            match stage.state() {
                Ok(StageState::Moving | StageState::Homing) => misses = 0,
                Ok(_) => return Ok(Watched::Ended),
                Err(e)
                    if matches!(e.kind(), ErrorKind::Timeout | ErrorKind::Protocol)
                        && misses + 1 < STATUS_MISSES =>
                {
                    misses += 1;
                }
                Err(e) => {
                    let _ = stage.stop();
                    return Err(e);
                }
            }
        }
        if now > deadline {
            let cause = StopCause::Timeout(timeout);
            return Ok(Watched::Stopped(Box::new(halt(
                stage,
                cause,
                now,
                Duration::ZERO,
            ))));
        }
        let mut wake = next_status.min(now + FLAG_POLL);
        if force.is_some() {
            wake = wake.min(next_ft);
        }
        let pause = wake.saturating_duration_since(Instant::now());
        if !pause.is_zero() {
            std::thread::sleep(pause);
        }
    }
}

/// Stops the stage, waits (at most [`STANDSTILL_WAIT`]) until it reports no motion,
/// and reads where it stands. `detected` is when the cause was seen; `already` how
/// long before that it arose (a signal's time until the loop saw the flag).
fn halt(stage: &mut dyn Stage, cause: StopCause, detected: Instant, already: Duration) -> Stopped {
    let stop_error = stage.stop().err();
    let wait_until = Instant::now() + STANDSTILL_WAIT;
    while let Ok(StageState::Moving | StageState::Homing) = stage.state() {
        if Instant::now() > wait_until {
            break;
        }
        std::thread::sleep(FLAG_POLL);
    }
    let latency = already + detected.elapsed();
    let position = stage.position();
    let state = stage.state();
    Stopped {
        cause,
        latency,
        stop_error,
        position,
        state,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_monotonic_clock_advances_at_least_as_far_as_a_sleep() {
        let a = monotonic_ns();
        let t = Instant::now();
        std::thread::sleep(Duration::from_millis(5));
        let b = monotonic_ns();
        assert!(a > 0 && b > a, "{a} {b}");
        assert!(Duration::from_nanos(b - a) >= t.elapsed().min(Duration::from_millis(5)));
    }
}
