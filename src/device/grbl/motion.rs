//! The GRBL driver as a [`Stage`]: absolute and relative moves in machine
//! coordinates (checked against the travel box before anything is sent), homing, jog
//! and jog cancel, probing, waiting for idle and stopping.

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use super::codec::{Command, MachineState, Realtime};
use super::{status_state, Grbl, DEVICE, POLL_INTERVAL, STATUS_INTERVAL, STOP_TIMEOUT};
use crate::device::{
    DeviceError, DeviceResult, ErrorKind, Stage, StagePositionMm, StageState, TravelLimits,
};

impl<P: Read + Write> Grbl<P> {
    pub(super) fn check_target(
        &self,
        target_mm: StagePositionMm,
        command: &str,
    ) -> DeviceResult<()> {
        self.limits.check(target_mm).map_err(|m| {
            DeviceError::new(ErrorKind::Limit, DEVICE, command, m)
                .with_hint("the move was not sent")
        })
    }

    pub(super) fn feed(speed_mm_s: Option<f64>, command: &str) -> DeviceResult<Option<f64>> {
        match speed_mm_s {
            None => Ok(None),
            Some(v) if v.is_finite() && v > 0.0 => Ok(Some(v * 60.0)),
            Some(v) => Err(DeviceError::new(
                ErrorKind::Other,
                DEVICE,
                command,
                format!("speed {v} mm/s must be a positive finite number"),
            )),
        }
    }

    /// Position and state in one status query, refusing if not idle (relative
    /// moves start from a stopped stage).
    pub(super) fn idle_position(&mut self, command: &str) -> DeviceResult<StagePositionMm> {
        self.ensure_settings(command)?;
        let s = self.require_state(command, &[MachineState::Idle])?;
        self.mpos_of(&s)
    }

    /// Starts a jog by `delta_mm` at `speed_mm_s` (`$J=G91 ..`), checked against the
    /// travel limits from the current position. Cancel with [`Grbl::jog_cancel`].
    pub fn jog(&mut self, delta_mm: StagePositionMm, speed_mm_s: f64) -> DeviceResult<()> {
        let here = self.idle_position("$J=")?;
        let target = [
            here[0] + delta_mm[0],
            here[1] + delta_mm[1],
            here[2] + delta_mm[2],
        ];
        let feed = Self::feed(Some(speed_mm_s), "$J=")?.unwrap_or(0.0);
        let cmd = Command::Jog {
            xyz_mm: delta_mm.map(Some),
            feed_mm_min: feed,
            relative: true,
        };
        self.check_target(target, &cmd.encode())?;
        self.line(&cmd, self.config.reply_timeout, false)
    }

    /// Cancels a jog (real-time 0x85).
    pub fn jog_cancel(&mut self) -> DeviceResult<()> {
        self.port.send(&[Realtime::JogCancel.byte()], "0x85")
    }

    /// Probes down (`G38.2`) by at most `distance_mm` along z at `speed_mm_s`, waits
    /// for contact and returns the contact position (from `[PRB:..]`).
    pub fn probe_z(
        &mut self,
        distance_mm: f64,
        speed_mm_s: f64,
        timeout: Duration,
    ) -> DeviceResult<StagePositionMm> {
        let here = self.idle_position("G38.2")?;
        let target = [here[0], here[1], here[2] + distance_mm];
        let cmd = Command::Probe {
            xyz_mm: [None, None, Some(distance_mm)],
            feed_mm_min: Self::feed(Some(speed_mm_s), "G38.2")?.unwrap_or(0.0),
        };
        self.check_target(target, &cmd.encode())?;
        self.last_feedback = None;
        self.line(&cmd, self.config.reply_timeout, false)?;
        self.wait_idle(timeout)?;
        let fb = self.last_feedback.clone().unwrap_or_default();
        let prb = fb.strip_prefix("PRB:").ok_or_else(|| {
            DeviceError::new(
                ErrorKind::Protocol,
                DEVICE,
                cmd.encode(),
                "no [PRB:..] report after probing",
            )
        })?;
        let (xyz, _ok) = prb.rsplit_once(':').unwrap_or((prb, "1"));
        let v: Vec<f64> = xyz.split(',').filter_map(|t| t.parse().ok()).collect();
        if v.len() < 3 {
            return Err(DeviceError::new(
                ErrorKind::Protocol,
                DEVICE,
                cmd.encode(),
                format!("bad probe report {fb:?}"),
            ));
        }
        Ok([v[0], v[1], v[2]])
    }
}

impl<P: Read + Write> Stage for Grbl<P> {
    fn home(&mut self) -> DeviceResult<()> {
        if self.needs_reset {
            self.soft_reset()?;
        }
        self.ensure_settings("$H")?;
        self.require_state("$H", &[MachineState::Idle, MachineState::Alarm])?;
        self.line(&Command::Home, self.config.homing_timeout, true)?;
        self.alarm = None;
        Ok(())
    }

    fn move_to(&mut self, target_mm: StagePositionMm, speed_mm_s: Option<f64>) -> DeviceResult<()> {
        let cmd = Command::Move {
            xyz_mm: target_mm.map(Some),
            feed_mm_min: Self::feed(speed_mm_s, "G53 G1")?,
            relative: false,
        };
        let text = cmd.encode();
        if self.needs_reset {
            return Err(self.alarm_error(&text, self.alarm.unwrap_or(0)));
        }
        self.ensure_settings(&text)?;
        self.check_target(target_mm, &text)?;
        // Queued behind a running move is fine; held, alarmed, ... is not.
        self.require_state(&text, &[MachineState::Idle, MachineState::Run])?;
        self.line(&cmd, self.config.reply_timeout, false)
    }

    fn move_by(&mut self, delta_mm: StagePositionMm, speed_mm_s: Option<f64>) -> DeviceResult<()> {
        let here = self.idle_position("G91 G1")?;
        let target = [
            here[0] + delta_mm[0],
            here[1] + delta_mm[1],
            here[2] + delta_mm[2],
        ];
        let cmd = Command::Move {
            xyz_mm: delta_mm.map(Some),
            feed_mm_min: Self::feed(speed_mm_s, "G91 G1")?,
            relative: true,
        };
        self.check_target(target, &cmd.encode())?;
        self.line(&cmd, self.config.reply_timeout, false)
    }

    fn position(&mut self) -> DeviceResult<StagePositionMm> {
        let s = self.status()?;
        self.mpos_of(&s)
    }

    fn state(&mut self) -> DeviceResult<StageState> {
        let s = self.status()?;
        Ok(Self::map_state(status_state(&s)))
    }

    fn wait_idle(&mut self, timeout: Duration) -> DeviceResult<()> {
        if self.needs_reset {
            return Err(self.alarm_error("G4 P0", self.alarm.unwrap_or(0)));
        }
        // GRBL locks G-code (error:9) while jogging, so `G4 P0` cannot be used to
        // wait for a jog: poll the state until the jog ends. A held, door-opened or
        // alarmed controller fails the wait at once.
        let deadline = Instant::now() + timeout;
        loop {
            let s = self.status()?;
            match status_state(&s) {
                MachineState::Jog => {}
                state @ (MachineState::Hold(_)
                | MachineState::Door(_)
                | MachineState::Alarm
                | MachineState::Sleep) => return Err(self.state_error("G4 P0", state)),
                _ => break,
            }
            if Instant::now() >= deadline {
                return Err(DeviceError::new(
                    ErrorKind::Timeout,
                    DEVICE,
                    "?",
                    format!("jog still running after {:.1} s", timeout.as_secs_f64()),
                ));
            }
            std::thread::sleep(POLL_INTERVAL);
        }
        match self.line_once_checked(deadline.saturating_duration_since(Instant::now())) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == ErrorKind::Rejected && self.alarm.is_some() => {
                Err(self.alarm_error("G4 P0", self.alarm.unwrap_or(0)))
            }
            Err(e) => Err(e),
        }
    }

    fn stop(&mut self) -> DeviceResult<()> {
        let s = self.status()?;
        match status_state(&s) {
            MachineState::Jog => {
                self.jog_cancel()?;
            }
            MachineState::Run | MachineState::Hold(_) | MachineState::Door(_) => {
                self.port.send(&[Realtime::FeedHold.byte()], "!")?;
                // Wait for the hold to complete (Hold:0, or a door's stop), then
                // reset to discard the rest of the queued motion; a reset after a
                // completed hold does not raise alarm 3 in GRBL 1.1.
                let deadline = Instant::now() + STOP_TIMEOUT;
                loop {
                    let s = self.status()?;
                    match status_state(&s) {
                        MachineState::Hold(0) | MachineState::Door(0 | 1) => break,
                        MachineState::Idle | MachineState::Alarm => return Ok(()),
                        _ if Instant::now() >= deadline => {
                            return Err(DeviceError::new(
                                ErrorKind::Timeout,
                                DEVICE,
                                "!",
                                format!(
                                    "feed hold not complete within {} s",
                                    STOP_TIMEOUT.as_secs()
                                ),
                            ))
                        }
                        _ => std::thread::sleep(POLL_INTERVAL),
                    }
                }
                self.soft_reset()?;
            }
            _ => {}
        }
        Ok(())
    }

    fn unlock(&mut self) -> DeviceResult<()> {
        self.unlock_report().map(|_| ())
    }

    fn limits(&self) -> TravelLimits {
        self.limits
    }

    fn status_interval(&self) -> Duration {
        STATUS_INTERVAL
    }
}
