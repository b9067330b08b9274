//! The GRBL driver's line exchange: sending a line and reading its `ok` / `error:N`
//! under a deadline, queries retried (`?`, `$$`, `$G`, `G4 P0`), status reports, the
//! reply-stream resynchronisation after a lost or garbled reply, and the pushed lines
//! (`ALARM:N`, `[MSG:..]`, banners, stray reports) noted wherever they arrive.

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use super::codec::{decode, error_text, Command, MachineState, Realtime, Response, StatusReport};
use super::{
    looks_like_status, reads_lines, status_state, Grbl, DEVICE, MALFORMED_STATUS_RETRIES,
    POLL_INTERVAL, QUERY_RETRIES, RESET_TIMEOUT,
};
use crate::device::{DeviceError, DeviceResult, ErrorKind};

impl<P: Read + Write> Grbl<P> {
    /// Handles a pushed line; returns true if it was one.
    pub(super) fn note_pushed(&mut self, r: &Response) {
        match r {
            Response::Alarm(n) => {
                self.alarm = Some(*n);
                if *n == 1 || *n == 2 {
                    self.needs_reset = true;
                }
            }
            Response::Message(m) => {
                if m == "Reset to continue" {
                    self.needs_reset = true;
                }
                if m == "Caution: Unlocked" {
                    self.alarm = None;
                }
                if m.contains("to unlock") && self.alarm.is_none() {
                    self.alarm = Some(0);
                }
                self.last_message = Some(m.clone());
            }
            Response::Banner(v) => {
                self.version = Some(v.clone());
                self.resets_seen += 1;
                self.needs_reset = false;
                // GRBL flushes its buffers on reset: no reply is outstanding.
                self.needs_resync = false;
            }
            Response::Feedback(f) => self.last_feedback = Some(f.clone()),
            Response::ParserState(p) => self.parser_state = Some(p.clone()),
            Response::Status(s) => {
                if let Some(w) = s.wco_mm {
                    self.wco_mm = Some(w);
                }
                let state = status_state(s);
                self.last_state = Some(state);
                if state == MachineState::Alarm && self.alarm.is_none() {
                    self.alarm = Some(0);
                }
                if state != MachineState::Alarm {
                    // Reported out of alarm (unlocked or homed by someone else).
                    self.alarm = None;
                    self.needs_reset = false;
                }
            }
            _ => {}
        }
    }

    /// Sends a query line (retried on a timeout or garbled reply) and folds every line
    /// before its `ok` into a `T` with `take`; each attempt starts from `T::default()`,
    /// so a retry never mixes in the lines of an attempt that failed.
    pub(super) fn query_lines<T: Default>(
        &mut self,
        cmd: &Command,
        mut take: impl FnMut(&mut T, &Response),
    ) -> DeviceResult<T> {
        let text = cmd.encode();
        let mut last = None;
        for _ in 0..=QUERY_RETRIES {
            if self.needs_resync {
                self.resync()?;
            }
            self.port.send(&cmd.to_bytes(), &text)?;
            let deadline = Instant::now() + self.config.reply_timeout;
            let mut got = T::default();
            let result = loop {
                let line = match self.port.read_line(deadline, &text) {
                    Ok(l) => l,
                    Err(e) => break Err(e),
                };
                match decode(&line) {
                    Ok(Response::Ok) => break Ok(()),
                    Ok(Response::Error(n)) => break Err(self.rejected(cmd, &text, n)),
                    Ok(r) => {
                        self.note_pushed(&r);
                        take(&mut got, &r);
                    }
                    Err(e) => {
                        break Err(DeviceError::new(
                            ErrorKind::Protocol,
                            DEVICE,
                            text.clone(),
                            e.to_string(),
                        ))
                    }
                }
            };
            match result {
                Ok(()) => return Ok(got),
                Err(e) if matches!(e.kind(), ErrorKind::Timeout | ErrorKind::Protocol) => {
                    self.needs_resync = true;
                    last = Some(e);
                }
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| DeviceError::new(ErrorKind::Timeout, DEVICE, text, "no reply")))
    }

    /// One `?` → status report, without retries.
    pub(super) fn status_once(&mut self, timeout: Duration) -> DeviceResult<StatusReport> {
        self.port.send(&[Realtime::StatusQuery.byte()], "?")?;
        let deadline = Instant::now() + timeout;
        loop {
            let line = self.port.read_line(deadline, "?")?;
            match decode(&line) {
                Ok(Response::Status(s)) => {
                    self.note_pushed(&Response::Status(s.clone()));
                    return Ok(s);
                }
                // A banner means a reset mid-query: the `?` may have been flushed
                // or answered; if no report comes, `status` asks again.
                Ok(r) => {
                    self.note_pushed(&r);
                    // A critical alarm: GRBL will not answer `?` until a reset.
                    if self.needs_reset {
                        if let Response::Message(_) | Response::Alarm(_) = r {
                            return Err(self.alarm_error("?", self.alarm.unwrap_or(0)));
                        }
                    }
                }
                Err(e) => {
                    return Err(DeviceError::new(
                        ErrorKind::Protocol,
                        DEVICE,
                        "?",
                        e.to_string(),
                    ));
                }
            }
        }
    }

    /// The current status report, retrying lost or garbled reports (safe: `?` only reads).
    pub fn status(&mut self) -> DeviceResult<StatusReport> {
        let mut last = None;
        for _ in 0..=QUERY_RETRIES {
            match self.status_once(self.config.status_timeout) {
                Ok(s) => return Ok(s),
                Err(e) if matches!(e.kind(), ErrorKind::Disconnected | ErrorKind::Limit) => {
                    return Err(e)
                }
                Err(e) => last = Some(e),
            }
        }
        Err(last.unwrap_or_else(|| {
            DeviceError::new(ErrorKind::Timeout, DEVICE, "?", "no status report")
        }))
    }

    /// Reads replies until the stream is known clean: sends `$G` and discards
    /// everything up to its `[GC:..]` and the `ok` after it. If nothing at all
    /// arrives for a reply timeout, another `$G` is sent, and then as many
    /// `[GC:..]` + `ok` pairs as `$G` lines sent are awaited, so no reply of the
    /// resync itself is left behind to be mistaken for the next command's.
    pub(super) fn resync(&mut self) -> DeviceResult<()> {
        self.resync_within(self.config.reply_timeout)
    }

    /// [`Self::resync`] waiting at most `per_reply` for each `$G` answer.
    pub(super) fn resync_within(&mut self, per_reply: Duration) -> DeviceResult<()> {
        let cmd = Command::ParserState;
        let text = cmd.encode();
        let total_deadline = Instant::now() + per_reply * (QUERY_RETRIES + 1);
        self.port.send(&cmd.to_bytes(), &text)?;
        let (mut sent, mut answered) = (1u32, 0u32);
        let mut seen_gc = false;
        let mut quiet_deadline = Instant::now() + self.config.reply_timeout;
        loop {
            match self
                .port
                .read_line(quiet_deadline.min(total_deadline), &text)
            {
                Ok(line) => {
                    quiet_deadline = Instant::now() + self.config.reply_timeout;
                    match decode(&line) {
                        Ok(r @ Response::ParserState(_)) => {
                            self.note_pushed(&r);
                            seen_gc = true;
                        }
                        Ok(Response::Ok | Response::Error(_)) if seen_gc => {
                            seen_gc = false;
                            answered += 1;
                            if answered >= sent {
                                self.needs_resync = false;
                                return Ok(());
                            }
                        }
                        Ok(r @ Response::Banner(_)) => {
                            // The controller reset and flushed our `$G`s: start over.
                            self.note_pushed(&r);
                            self.port.send(&cmd.to_bytes(), &text)?;
                            (sent, answered, seen_gc) = (1, 0, false);
                        }
                        Ok(r) => self.note_pushed(&r),
                        // Garbage in the stale part of the stream is expected here.
                        Err(_) => {}
                    }
                }
                Err(e) if e.kind() == ErrorKind::Timeout && Instant::now() < total_deadline => {
                    self.port.send(&cmd.to_bytes(), &text)?;
                    sent += 1;
                    quiet_deadline = Instant::now() + per_reply;
                }
                Err(mut e) => {
                    if e.kind() == ErrorKind::Timeout {
                        e.message = format!(
                            "could not resynchronise the reply stream ({answered} of {sent} `$G` answered)"
                        );
                    }
                    return Err(e);
                }
            }
        }
    }

    /// Sends one line and waits for its `ok`/`error:N`, polling `?` every
    /// [`POLL_INTERVAL`] if `poll` (to see alarms while a long line blocks).
    pub(super) fn line(
        &mut self,
        cmd: &Command,
        timeout: Duration,
        poll: bool,
    ) -> DeviceResult<()> {
        let text = cmd.encode();
        let attempts = if cmd.is_query() { QUERY_RETRIES + 1 } else { 1 };
        let mut last = None;
        for _ in 0..attempts {
            // A critical alarm blocks every line until reset: fail fast.
            if self.needs_reset {
                return Err(self.alarm_error(&text, self.alarm.unwrap_or(0)));
            }
            if self.needs_resync {
                self.resync_when_reading(&text)?;
            }
            match self.line_once(cmd, &text, timeout, poll) {
                Ok(()) => return Ok(()),
                Err(e) => {
                    let retry = cmd.is_query()
                        && matches!(e.kind(), ErrorKind::Timeout | ErrorKind::Protocol);
                    if !retry {
                        return Err(e);
                    }
                    last = Some(e);
                }
            }
        }
        Err(last.unwrap_or_else(|| DeviceError::new(ErrorKind::Timeout, DEVICE, text, "no reply")))
    }

    /// Resynchronises, unless the controller was last seen in a state where it reads
    /// no lines (Hold, Door, Home, Sleep): then it is asked for its state first, and
    /// if it is still there the caller gets that state's error at once instead of
    /// waiting out a resync GRBL cannot answer.
    pub(super) fn resync_when_reading(&mut self, command: &str) -> DeviceResult<()> {
        if let Some(state) = self.last_state {
            if !reads_lines(state) && !matches!(state, MachineState::Run | MachineState::Jog) {
                let s = self.status()?;
                let now = status_state(&s);
                if !reads_lines(now) && !matches!(now, MachineState::Run | MachineState::Jog) {
                    return Err(self.state_error(command, now));
                }
            }
        }
        self.resync()
    }

    pub(super) fn line_once(
        &mut self,
        cmd: &Command,
        text: &str,
        timeout: Duration,
        poll: bool,
    ) -> DeviceResult<()> {
        self.port.send(&cmd.to_bytes(), text)?;
        let deadline = Instant::now() + timeout;
        let mut next_poll = Instant::now() + POLL_INTERVAL;
        let mut malformed = 0u32;
        loop {
            let slice_end = if poll {
                deadline.min(next_poll)
            } else {
                deadline
            };
            let line = match self.port.read_line(slice_end, text) {
                Ok(l) => l,
                Err(e) if e.kind() == ErrorKind::Timeout && Instant::now() < deadline => {
                    self.port.send(&[Realtime::StatusQuery.byte()], "?")?;
                    next_poll = Instant::now() + POLL_INTERVAL;
                    continue;
                }
                Err(mut e) => {
                    if e.kind() == ErrorKind::Timeout {
                        // The reply may still come: discard it before the next line.
                        self.needs_resync = true;
                        e.message = format!(
                            "no `ok`/`error` within {:.1} s{}",
                            timeout.as_secs_f64(),
                            if cmd.is_query() {
                                ""
                            } else {
                                "; not re-sent (it may have been executed)"
                            }
                        );
                    }
                    return Err(e);
                }
            };
            match decode(&line) {
                Ok(Response::Ok) => return Ok(()),
                Ok(Response::Error(n)) => return Err(self.rejected(cmd, text, n)),
                Ok(Response::Alarm(n)) => {
                    self.note_pushed(&Response::Alarm(n));
                    // The line's own reply may still follow (after a reset, for
                    // soft limits): resync before the next line.
                    self.needs_resync = true;
                    return Err(self.alarm_error(text, n));
                }
                Ok(r @ Response::Banner(_)) => {
                    self.note_pushed(&r);
                    return Err(DeviceError::new(
                        ErrorKind::Other,
                        DEVICE,
                        text,
                        "the controller reset (banner received) before answering; queued motion was discarded",
                    )
                    .with_hint("check `status`; unlock or home if it reports an alarm"));
                }
                Ok(Response::Status(s)) => {
                    malformed = 0;
                    let state = status_state(&s);
                    self.note_pushed(&Response::Status(s));
                    if poll
                        && matches!(
                            state,
                            MachineState::Alarm | MachineState::Hold(_) | MachineState::Door(_)
                        )
                    {
                        // The line stays in GRBL's buffer (answered on resume, or
                        // flushed by a reset): resync before the next line.
                        self.needs_resync = true;
                        return Err(self.state_error(text, state));
                    }
                }
                Ok(r) => self.note_pushed(&r),
                // A garbled status report (a `?` of ours is outstanding): ask again,
                // a bounded number of times, instead of failing the wait.
                Err(e) if poll && looks_like_status(&line) => {
                    malformed += 1;
                    if malformed > MALFORMED_STATUS_RETRIES {
                        self.needs_resync = true;
                        return Err(DeviceError::new(
                            ErrorKind::Protocol,
                            DEVICE,
                            "?",
                            format!("{malformed} malformed status reports in a row; last: {e}"),
                        ));
                    }
                    self.port.send(&[Realtime::StatusQuery.byte()], "?")?;
                    next_poll = Instant::now() + POLL_INTERVAL;
                }
                Err(e) => {
                    self.needs_resync = true;
                    return Err(DeviceError::new(
                        ErrorKind::Protocol,
                        DEVICE,
                        text,
                        format!(
                            "{e}{}",
                            if cmd.is_query() {
                                ""
                            } else {
                                "; the command may or may not have been accepted and is not re-sent"
                            }
                        ),
                    ));
                }
            }
        }
    }

    pub(super) fn rejected(&self, cmd: &Command, text: &str, code: u8) -> DeviceError {
        let msg = format!("error:{code}: {}", error_text(code));
        let e = DeviceError::new(ErrorKind::Rejected, DEVICE, text, msg);
        match (cmd, code) {
            (Command::Home, 5) => DeviceError::new(
                ErrorKind::Rejected,
                DEVICE,
                text,
                "homing is disabled on the controller ($22=0); error:5",
            )
            .with_hint("enable homing with `$22=1` if the stage has limit switches, or use `unlock` and skip homing"),
            (_, 9) => e.with_hint("the controller is in alarm: run `unlock` ($X) or `home` ($H)"),
            (_, 15) => e.with_hint("the jog target is outside the controller's soft limits ($130..$132)"),
            _ => e,
        }
    }

    /// Reads until a banner arrives (after a reset GRBL does by itself).
    pub(super) fn wait_banner(&mut self) -> DeviceResult<()> {
        let before = self.resets_seen;
        let deadline = Instant::now() + RESET_TIMEOUT;
        while self.resets_seen == before {
            let line = self.port.read_line(deadline, "banner")?;
            if let Ok(r) = decode(&line) {
                self.note_pushed(&r);
            }
        }
        Ok(())
    }

    /// `G4 P0` with status polling: answered once the planner is empty.
    pub(super) fn line_once_checked(&mut self, timeout: Duration) -> DeviceResult<()> {
        let cmd = Command::Dwell { seconds: 0.0 };
        if self.needs_resync {
            self.resync()?;
        }
        let text = cmd.encode();
        self.line_once(&cmd, &text, timeout, true)
    }
}
