//! The GRBL driver's state rules and recovery: which states allow a command and the
//! errors that say why not (alarm codes, hold / door, check mode, with the hint that
//! gets out), mapping GRBL's states to the bench's, soft reset, unlock and resume.

use std::io::{Read, Write};
use std::time::Instant;

use super::codec::{alarm_text, decode, Command, MachineState, Realtime, StatusReport};
use super::{
    reads_lines, status_state, Grbl, UnlockReport, DEVICE, POLL_INTERVAL, RESET_TIMEOUT,
    STOP_TIMEOUT,
};
use crate::device::{DeviceError, DeviceResult, ErrorKind, StageState};

impl<P: Read + Write> Grbl<P> {
    pub(super) fn alarm_error(&self, command: &str, code: u8) -> DeviceError {
        let what = if code == 0 {
            "the controller is in the alarm state".to_string()
        } else {
            format!("ALARM:{code}: {}", alarm_text(code))
        };
        DeviceError::new(ErrorKind::Limit, DEVICE, command, what).with_hint(if self.needs_reset {
            "clear the cause, then `tactbench stage ... unlock` (soft reset + $X) or home"
        } else {
            "run `unlock` ($X) or `home` ($H) before moving"
        })
    }

    /// The error for a controller that cannot take `command` in `state` (anything but
    /// Idle, and Run for queued moves): Hold/Door → [`ErrorKind::Held`], Alarm →
    /// [`ErrorKind::Limit`], the others [`ErrorKind::Other`], each with a hint.
    pub(super) fn state_error(&self, command: &str, state: MachineState) -> DeviceError {
        let other = |what: String, hint: &str| {
            DeviceError::new(ErrorKind::Other, DEVICE, command, what).with_hint(hint)
        };
        match state {
            MachineState::Hold(n) => DeviceError::new(
                ErrorKind::Held,
                DEVICE,
                command,
                format!(
                    "the controller is in feed hold (Hold:{n}{}): motion is paused, queued moves wait",
                    if n == 0 { ", stopped" } else { ", decelerating" }
                ),
            )
            .with_hint(
                "resume with `~` (cycle start: `tactbench stage ... resume`), or abort the held motion with `tactbench stage ... stop` (feed hold + soft reset)",
            ),
            MachineState::Door(n) => DeviceError::new(
                ErrorKind::Held,
                DEVICE,
                command,
                format!(
                    "the safety door is open (Door:{n}: {}): motion is paused",
                    match n {
                        0 => "door closed, ready to resume",
                        1 => "machine stopped, door still ajar",
                        2 => "door opened, parking in progress",
                        _ => "door closed, restoring from park",
                    }
                ),
            )
            .with_hint(
                "close the door, then resume with `~` (`tactbench stage ... resume`), or abort with `tactbench stage ... stop`",
            ),
            MachineState::Alarm => self.alarm_error(command, self.alarm.unwrap_or(0)),
            MachineState::Check => DeviceError::new(
                ErrorKind::Rejected,
                DEVICE,
                command,
                "the controller is in check mode ($C): G-code is parsed but nothing moves",
            )
            .with_hint("leave check mode with `$C` (or `tactbench stage ... unlock`)"),
            MachineState::Sleep => other(
                "the controller is asleep ($SLP): only a soft reset wakes it".into(),
                "`tactbench stage ... unlock` resets and unlocks it; home if homing is enabled",
            ),
            MachineState::Home => other(
                "a homing cycle is running".into(),
                "wait for it to end, or abort it with a soft reset (`unlock`)",
            ),
            MachineState::Jog => other(
                "a jog is running".into(),
                "wait for it to end, or cancel it (`stop`)",
            ),
            MachineState::Run => other(
                "the stage is moving (Run)".into(),
                "wait for the move to finish, or `stop` it",
            ),
            MachineState::Idle => other("the stage is idle".into(), ""),
        }
    }

    /// The current state, refusing unless it is one of `allowed`.
    pub(super) fn require_state(
        &mut self,
        command: &str,
        allowed: &[MachineState],
    ) -> DeviceResult<StatusReport> {
        let s = self.status()?;
        let state = status_state(&s);
        if allowed.contains(&state) {
            Ok(s)
        } else {
            Err(self.state_error(command, state))
        }
    }

    /// Soft reset (0x18): flushes all queued motion; waits for the banner. If the
    /// machine was moving, GRBL enters alarm 3 (position possibly lost).
    pub fn soft_reset(&mut self) -> DeviceResult<()> {
        let before = self.resets_seen;
        self.port.send(&[Realtime::SoftReset.byte()], "0x18")?;
        let deadline = Instant::now() + RESET_TIMEOUT;
        while self.resets_seen == before {
            let line = self.port.read_line(deadline, "0x18 (soft reset)")?;
            if let Ok(r) = decode(&line) {
                self.note_pushed(&r);
            }
        }
        self.needs_reset = false;
        self.needs_resync = false;
        Ok(())
    }

    /// Reads the current state as the bench sees it.
    pub(super) fn map_state(s: MachineState) -> StageState {
        match s {
            MachineState::Idle | MachineState::Check => StageState::Idle,
            // Asleep, GRBL moves nothing until a reset, after which it is in alarm.
            MachineState::Sleep => StageState::Alarm,
            MachineState::Run | MachineState::Jog => StageState::Moving,
            MachineState::Hold(_) | MachineState::Door(_) => StageState::Held,
            MachineState::Home => StageState::Homing,
            MachineState::Alarm => StageState::Alarm,
        }
    }

    /// Clears whatever keeps the controller from moving, and says what it did:
    /// a critical alarm (known, or a controller that answered nothing at connect)
    /// or sleep → soft reset (0x18), then `$X`; an alarm → `$X`; check mode → `$C`
    /// (GRBL resets after it). Idle: nothing to do. Hold and Door are not alarms:
    /// [`ErrorKind::Held`] with the resume / abort hint; Run, Jog, Home: refused.
    pub fn unlock_report(&mut self) -> DeviceResult<UnlockReport> {
        let mut actions = Vec::new();
        if self.reset_at_connect {
            actions.push(
                "soft reset (0x18): the controller answered nothing, as GRBL does in a critical alarm \
                 (hard or soft limit, \"Reset to continue\")"
                    .to_string(),
            );
        }
        if self.needs_reset {
            let code = self.alarm.unwrap_or(0);
            self.soft_reset()?;
            actions.push(format!(
                "soft reset (0x18): needed to leave the critical alarm{}",
                if code == 0 {
                    String::new()
                } else {
                    format!(" ALARM:{code} ({})", alarm_text(code))
                }
            ));
        }
        let mut state = status_state(&self.status()?);
        if state == MachineState::Sleep {
            self.soft_reset()?;
            actions.push("soft reset (0x18): wakes the controller from sleep".to_string());
            state = status_state(&self.status()?);
        }
        match state {
            MachineState::Alarm => {
                let code = self.alarm.unwrap_or(0);
                self.line(&Command::Unlock, self.config.reply_timeout, false)?;
                self.alarm = None;
                actions.push(format!(
                    "`$X`: cleared the alarm{}",
                    if code == 0 {
                        " (raised before this connection; code not seen)".to_string()
                    } else {
                        format!(" ALARM:{code} ({})", alarm_text(code))
                    }
                ));
                if self.soft_limit_box().is_some() || code == 1 || code == 3 {
                    actions.push(
                        "the position may have been lost: home (`$H`) before relying on it"
                            .to_string(),
                    );
                }
            }
            MachineState::Check => {
                self.line(&Command::CheckMode, self.config.reply_timeout, false)?;
                self.wait_banner()?;
                actions.push("`$C`: left check mode (GRBL resets after it)".to_string());
            }
            MachineState::Idle if actions.is_empty() => {
                actions.push("nothing to unlock: the controller is idle".to_string());
            }
            MachineState::Idle => {}
            other => return Err(self.state_error("$X", other)),
        }
        if self.settings.is_none() {
            let s = status_state(&self.status()?);
            if reads_lines(s) {
                self.read_configuration(s)?;
            }
        }
        Ok(UnlockReport { actions })
    }

    /// Resumes a feed hold or a closed safety door (`~`, cycle start) and waits
    /// until the controller reports that motion continues (or is done).
    pub fn resume(&mut self) -> DeviceResult<MachineState> {
        let s = self.status()?;
        match status_state(&s) {
            MachineState::Hold(_) | MachineState::Door(0) => {}
            other @ MachineState::Door(_) => return Err(self.state_error("~", other)),
            other => {
                return Err(DeviceError::new(
                    ErrorKind::Other,
                    DEVICE,
                    "~",
                    format!("nothing to resume: the controller is not held (state {other})"),
                ))
            }
        }
        self.port.send(&[Realtime::CycleStart.byte()], "~")?;
        let deadline = Instant::now() + STOP_TIMEOUT;
        loop {
            let state = status_state(&self.status()?);
            match state {
                MachineState::Hold(_) | MachineState::Door(_) if Instant::now() < deadline => {
                    std::thread::sleep(POLL_INTERVAL)
                }
                MachineState::Hold(_) | MachineState::Door(_) => {
                    return Err(DeviceError::new(
                        ErrorKind::Timeout,
                        DEVICE,
                        "~",
                        format!("still {state} {} s after `~`", STOP_TIMEOUT.as_secs()),
                    ))
                }
                other => return Ok(other),
            }
        }
    }
}
