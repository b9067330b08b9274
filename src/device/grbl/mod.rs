//! GRBL 1.1 xyz stage: codec ([`codec`]), driver ([`Grbl`], generic over
//! `Read + Write`, implementing [`Stage`]) and simulator ([`sim::GrblSim`]).
//! The spec is `protocols/grbl.md`.
//!
//! Frame: the driver works in GRBL's machine coordinates (MPos), mm. Absolute moves
//! are sent as `G53 G0/G1` (machine coordinates whatever the work offsets are),
//! relative moves and jogs as `G91`; every motion line carries `G21` so a
//! controller left in inches by another program still moves in mm. Status reports
//! in work coordinates (`$10` bit 0 clear) are converted with the last `WCO:` seen.
//!
//! Reliability rules:
//! - every read has a deadline (named constants below, overridable in
//!   [`GrblConfig`]);
//! - queries (`?`, `$$`, `$G`, `G4 P0`) are retried after a timeout or a garbled
//!   reply; commands that move the machine are never re-sent: a lost or garbled
//!   reply to a move is an error, and the reply stream is resynchronised (`$G`, read
//!   up to its `[GC:..]` and `ok`) before the next line;
//! - pushed lines (`ALARM:N`, `[MSG:..]`, the banner, stray status reports) are
//!   handled wherever they arrive: an alarm fails the waiting call with
//!   [`ErrorKind::Limit`], a banner means the controller reset (queued motion lost);
//! - completion: a move's `ok` means queued; [`Stage::wait_idle`] sends `G4 P0`
//!   (answered only when the planner is empty) while polling `?` to see alarms.

pub mod codec;
pub mod sim;

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::time::{Duration, Instant};

use self::codec::{
    alarm_text, decode, error_text, Command, MachineState, Realtime, Response, StatusReport,
};
use super::lineio::{LinePort, PORT_READ_TIMEOUT};
use super::{
    DeviceError, DeviceResult, ErrorKind, Stage, StagePositionMm, StageState, TravelLimits,
};

/// Device name in errors.
pub const DEVICE: &str = "grbl";

/// Default baud rate of GRBL 1.1.
pub const DEFAULT_BAUD: u32 = 115_200;

/// Time for `ok`/`error:N` to an ordinary line (GRBL parses a line in < 10 ms; a
/// full planner can delay the `ok` until a block finishes).
pub const REPLY_TIMEOUT: Duration = Duration::from_secs(2);

/// Time for a status report after `?` (GRBL answers within one main-loop pass).
pub const STATUS_TIMEOUT: Duration = Duration::from_millis(500);

/// Time for the banner after a soft reset.
pub const RESET_TIMEOUT: Duration = Duration::from_secs(2);

/// Time for the homing cycle (`$H` is answered when it ends).
pub const HOMING_TIMEOUT: Duration = Duration::from_secs(120);

/// Time to wait for the controller on connect (an Arduino resets when the port
/// opens and its bootloader takes 1–2 s before the banner).
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(4);

/// Interval of `?` polling while waiting for motion to finish (GRBL recommends
/// at most 5 Hz for GUIs; a bench wants to see alarms sooner, 50 Hz is fine).
pub const POLL_INTERVAL: Duration = Duration::from_millis(20);

/// The rate at which a caller polls `?` while a move runs: GRBL's interface guide
/// recommends status reports at no more than 5 Hz ("10 Hz may be possible"; a report
/// takes ~5-20 ms to generate, and not every `?` is guaranteed an answer).
pub const STATUS_INTERVAL: Duration = Duration::from_millis(200);

/// Time for the controller to come to a stop after a feed hold.
pub const STOP_TIMEOUT: Duration = Duration::from_secs(10);

/// Retries of a query after a timeout or garbled reply.
pub const QUERY_RETRIES: u32 = 2;

/// Time per `$G` answer when resynchronising at connect (a locked controller never
/// answers; a working one answers in milliseconds).
pub const CONNECT_RESYNC_TIMEOUT: Duration = Duration::from_millis(300);

/// Driver configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct GrblConfig {
    /// Travel box the driver enforces, machine coordinates, mm. `None`: derived
    /// from the controller's `$130..$132` as GRBL's own soft-limit box
    /// `[-max_travel, 0]` per axis.
    pub limits: Option<TravelLimits>,
    /// Timeout for line replies.
    pub reply_timeout: Duration,
    /// Timeout for status reports.
    pub status_timeout: Duration,
    /// Timeout for the homing cycle.
    pub homing_timeout: Duration,
}

impl Default for GrblConfig {
    fn default() -> Self {
        GrblConfig {
            limits: None,
            reply_timeout: REPLY_TIMEOUT,
            status_timeout: STATUS_TIMEOUT,
            homing_timeout: HOMING_TIMEOUT,
        }
    }
}

/// A GRBL 1.1 controller driving an xyz stage.
#[derive(Debug)]
pub struct Grbl<P> {
    port: LinePort<P>,
    config: GrblConfig,
    limits: TravelLimits,
    settings: BTreeMap<u16, String>,
    /// Last work coordinate offset seen, to convert WPos to MPos.
    wco_mm: [f64; 3],
    /// The controller announced an alarm we have not cleared.
    alarm: Option<u8>,
    /// A critical alarm ("Reset to continue"): only reset gets out.
    needs_reset: bool,
    /// The reply stream may hold stale replies (a reply was lost or garbled).
    needs_resync: bool,
    /// Banners seen (controller resets).
    resets_seen: u32,
    /// Last `[...]` feedback (e.g. `PRB:..`) and `[MSG:..]` seen.
    last_feedback: Option<String>,
    last_message: Option<String>,
    version: Option<String>,
}

/// Opens a serial port for a GRBL controller (8N1, short read timeout).
pub fn open_serial(path: &str, baud: u32) -> DeviceResult<Box<dyn serialport::SerialPort>> {
    serialport::new(path, baud)
        .timeout(PORT_READ_TIMEOUT)
        .open()
        .map_err(|e| {
            DeviceError::new(
                ErrorKind::Disconnected,
                DEVICE,
                format!("open {path}"),
                format!("cannot open serial port {path} at {baud} baud: {e}"),
            )
            .with_hint("list ports with `tactbench ports`; check permissions (dialout group)")
        })
}

fn status_state(s: &StatusReport) -> MachineState {
    s.state.unwrap_or(MachineState::Idle)
}

impl<P: Read + Write> Grbl<P> {
    /// Connects: waits for the controller to answer a status query (noting a
    /// banner), resynchronises the reply stream, and reads the settings (`$$`) for
    /// travel limits. Works whether or not the controller is in alarm.
    pub fn connect(port: P, config: GrblConfig) -> DeviceResult<Self> {
        let mut g = Grbl {
            port: LinePort::new(port, DEVICE),
            limits: config.limits.unwrap_or(TravelLimits {
                axes_mm: [[f64::NEG_INFINITY, f64::INFINITY]; 3],
            }),
            config,
            settings: BTreeMap::new(),
            wco_mm: [0.0; 3],
            alarm: None,
            needs_reset: false,
            needs_resync: true,
            resets_seen: 0,
            last_feedback: None,
            last_message: None,
            version: None,
        };
        let deadline = Instant::now() + CONNECT_TIMEOUT;
        let status = loop {
            match g.status_once(g.config.status_timeout.min(Duration::from_millis(250))) {
                Ok(s) => break s,
                Err(e) if e.kind() == ErrorKind::Disconnected => return Err(e),
                Err(e) if Instant::now() >= deadline => {
                    return Err(DeviceError::new(
                        ErrorKind::Timeout,
                        DEVICE,
                        "?",
                        format!(
                            "no status report within {} s: {}",
                            CONNECT_TIMEOUT.as_secs_f64(),
                            e.message
                        ),
                    )
                    .with_hint("is this a GRBL controller, at the right baud rate (115200)?"))
                }
                Err(_) => {}
            }
        };
        let in_alarm = status_state(&status) == MachineState::Alarm;
        if in_alarm && g.alarm.is_none() {
            g.alarm = Some(0);
        }
        // GRBL answers `$G` within milliseconds unless it is locked: do not wait
        // the full reply timeout to find out.
        match g.resync_within(g.config.reply_timeout.min(CONNECT_RESYNC_TIMEOUT)) {
            Ok(()) => {}
            // A critical alarm (hard/soft limit) left by an earlier session blocks
            // every line until a reset; a reset in alarm moves nothing and keeps
            // the alarm, so it is safe here.
            Err(e) if in_alarm && e.kind() == ErrorKind::Timeout => {
                g.soft_reset()?;
                g.resync()?;
            }
            Err(e) => return Err(e),
        }
        g.read_settings()?;
        if g.config.limits.is_none() {
            g.limits = g.limits_from_settings()?;
        }
        Ok(g)
    }

    /// The firmware version from the last banner seen (e.g. `1.1h`).
    pub fn version(&self) -> Option<&str> {
        self.version.as_deref()
    }

    /// Settings read at connect (`$N` → value text).
    pub fn settings(&self) -> &BTreeMap<u16, String> {
        &self.settings
    }

    /// Number of controller resets (banners) seen since connect.
    pub fn resets_seen(&self) -> u32 {
        self.resets_seen
    }

    /// The last `[MSG:..]` the controller pushed.
    pub fn last_message(&self) -> Option<&str> {
        self.last_message.as_deref()
    }

    /// The port back.
    pub fn into_inner(self) -> P {
        self.port.into_inner()
    }

    fn limits_from_settings(&self) -> DeviceResult<TravelLimits> {
        let mut axes_mm = [[0.0; 2]; 3];
        for (i, axis) in axes_mm.iter_mut().enumerate() {
            let n = 130 + i as u16;
            let v: f64 = self
                .settings
                .get(&n)
                .and_then(|v| v.parse().ok())
                .filter(|v: &f64| v.is_finite() && *v > 0.0)
                .ok_or_else(|| {
                    DeviceError::new(
                        ErrorKind::Protocol,
                        DEVICE,
                        "$$",
                        format!("setting ${n} (max travel, mm) missing or invalid"),
                    )
                })?;
            *axis = [-v, 0.0];
        }
        Ok(TravelLimits { axes_mm })
    }

    /// Handles a pushed line; returns true if it was one.
    fn note_pushed(&mut self, r: &Response) {
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
            Response::Status(s) => {
                if let Some(w) = s.wco_mm {
                    self.wco_mm = w;
                }
                if status_state(s) == MachineState::Alarm && self.alarm.is_none() {
                    self.alarm = Some(0);
                }
            }
            _ => {}
        }
    }

    fn alarm_error(&self, command: &str, code: u8) -> DeviceError {
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

    /// One `?` → status report, without retries.
    fn status_once(&mut self, timeout: Duration) -> DeviceResult<StatusReport> {
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
                Ok(r) => self.note_pushed(&r),
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
                Err(e) if e.kind() == ErrorKind::Disconnected => return Err(e),
                Err(e) => last = Some(e),
            }
        }
        Err(last.unwrap_or_else(|| {
            DeviceError::new(ErrorKind::Timeout, DEVICE, "?", "no status report")
        }))
    }

    /// Machine position from a report (WPos + WCO when the controller reports WPos).
    fn mpos_of(&self, s: &StatusReport) -> StagePositionMm {
        match (s.mpos_mm, s.wpos_mm) {
            (Some(m), _) => m,
            (None, Some(w)) => [
                w[0] + self.wco_mm[0],
                w[1] + self.wco_mm[1],
                w[2] + self.wco_mm[2],
            ],
            // parse_status guarantees one of the two.
            (None, None) => [f64::NAN; 3],
        }
    }

    /// Reads replies until the stream is known clean: sends `$G` and discards
    /// everything up to its `[GC:..]` and the `ok` after it. If nothing at all
    /// arrives for a reply timeout, another `$G` is sent, and then as many
    /// `[GC:..]` + `ok` pairs as `$G` lines sent are awaited, so no reply of the
    /// resync itself is left behind to be mistaken for the next command's.
    fn resync(&mut self) -> DeviceResult<()> {
        self.resync_within(self.config.reply_timeout)
    }

    /// [`Self::resync`] waiting at most `per_reply` for each `$G` answer.
    fn resync_within(&mut self, per_reply: Duration) -> DeviceResult<()> {
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
                        Ok(Response::ParserState(_)) => seen_gc = true,
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
    fn line(&mut self, cmd: &Command, timeout: Duration, poll: bool) -> DeviceResult<()> {
        let text = cmd.encode();
        let attempts = if cmd.is_query() { QUERY_RETRIES + 1 } else { 1 };
        let mut last = None;
        for _ in 0..attempts {
            // A critical alarm blocks every line until reset: fail fast.
            if self.needs_reset {
                return Err(self.alarm_error(&text, self.alarm.unwrap_or(0)));
            }
            if self.needs_resync {
                self.resync()?;
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

    fn line_once(
        &mut self,
        cmd: &Command,
        text: &str,
        timeout: Duration,
        poll: bool,
    ) -> DeviceResult<()> {
        self.port.send(&cmd.to_bytes(), text)?;
        let deadline = Instant::now() + timeout;
        let mut next_poll = Instant::now() + POLL_INTERVAL;
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
                    let state = status_state(&s);
                    self.note_pushed(&Response::Status(s));
                    if state == MachineState::Alarm && poll {
                        self.needs_resync = true;
                        return Err(self.alarm_error(text, self.alarm.unwrap_or(0)));
                    }
                }
                Ok(r) => self.note_pushed(&r),
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

    fn rejected(&self, cmd: &Command, text: &str, code: u8) -> DeviceError {
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

    fn read_settings(&mut self) -> DeviceResult<()> {
        let cmd = Command::Settings;
        let text = cmd.encode();
        let mut last = None;
        for _ in 0..=QUERY_RETRIES {
            if self.needs_resync {
                self.resync()?;
            }
            self.port.send(&cmd.to_bytes(), &text)?;
            let deadline = Instant::now() + self.config.reply_timeout;
            let mut settings = BTreeMap::new();
            let result = loop {
                let line = match self.port.read_line(deadline, &text) {
                    Ok(l) => l,
                    Err(e) => break Err(e),
                };
                match decode(&line) {
                    Ok(Response::Setting { number, value }) => {
                        settings.insert(number, value);
                    }
                    Ok(Response::Ok) => break Ok(()),
                    Ok(Response::Error(n)) => break Err(self.rejected(&cmd, &text, n)),
                    Ok(r) => self.note_pushed(&r),
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
                Ok(()) => {
                    self.settings = settings;
                    return Ok(());
                }
                Err(e) if matches!(e.kind(), ErrorKind::Timeout | ErrorKind::Protocol) => {
                    self.needs_resync = true;
                    last = Some(e);
                }
                Err(e) => return Err(e),
            }
        }
        Err(last
            .unwrap_or_else(|| DeviceError::new(ErrorKind::Timeout, DEVICE, text, "no settings")))
    }

    fn check_target(&self, target_mm: StagePositionMm, command: &str) -> DeviceResult<()> {
        self.limits.check(target_mm).map_err(|m| {
            DeviceError::new(ErrorKind::Limit, DEVICE, command, m)
                .with_hint("the move was not sent")
        })
    }

    fn feed(speed_mm_s: Option<f64>, command: &str) -> DeviceResult<Option<f64>> {
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

    /// Position and state in one status query, refusing if not idle.
    fn idle_position(&mut self, command: &str) -> DeviceResult<StagePositionMm> {
        let s = self.status()?;
        match status_state(&s) {
            MachineState::Idle => Ok(self.mpos_of(&s)),
            MachineState::Alarm => Err(self.alarm_error(command, self.alarm.unwrap_or(0))),
            other => Err(DeviceError::new(
                ErrorKind::Other,
                DEVICE,
                command,
                format!("the stage is not idle (state {other}); relative moves start from a stopped stage"),
            )
            .with_hint("wait for the previous move to finish")),
        }
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
    fn map_state(s: MachineState) -> StageState {
        match s {
            MachineState::Idle | MachineState::Check | MachineState::Sleep => StageState::Idle,
            MachineState::Run | MachineState::Jog => StageState::Moving,
            MachineState::Hold(_) | MachineState::Door(_) => StageState::Held,
            MachineState::Home => StageState::Homing,
            MachineState::Alarm => StageState::Alarm,
        }
    }
}

impl<P: Read + Write> Stage for Grbl<P> {
    fn home(&mut self) -> DeviceResult<()> {
        if self.needs_reset {
            self.soft_reset()?;
        }
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
        self.check_target(target_mm, &cmd.encode())?;
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
        Ok(self.mpos_of(&s))
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
        // wait for a jog: poll the state until the jog ends.
        let deadline = Instant::now() + timeout;
        loop {
            let s = self.status()?;
            if status_state(&s) != MachineState::Jog {
                break;
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
            MachineState::Run | MachineState::Hold(_) => {
                self.port.send(&[Realtime::FeedHold.byte()], "!")?;
                // Wait for the hold to complete (Hold:0), then reset to discard the
                // rest of the queued motion; a reset after a completed hold does
                // not raise alarm 3 in GRBL 1.1.
                let deadline = Instant::now() + STOP_TIMEOUT;
                loop {
                    let s = self.status()?;
                    match status_state(&s) {
                        MachineState::Hold(0) => break,
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
        if self.needs_reset {
            self.soft_reset()?;
        }
        self.line(&Command::Unlock, self.config.reply_timeout, false)?;
        self.alarm = None;
        Ok(())
    }

    fn limits(&self) -> TravelLimits {
        self.limits
    }

    fn status_interval(&self) -> Duration {
        STATUS_INTERVAL
    }
}

impl<P: Read + Write> Grbl<P> {
    /// `G4 P0` with status polling: answered once the planner is empty.
    fn line_once_checked(&mut self, timeout: Duration) -> DeviceResult<()> {
        let cmd = Command::Dwell { seconds: 0.0 };
        if self.needs_resync {
            self.resync()?;
        }
        let text = cmd.encode();
        self.line_once(&cmd, &text, timeout, true)
    }
}
