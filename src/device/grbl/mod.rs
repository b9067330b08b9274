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
    active_coordinate_system, alarm_text, decode, error_text, Command, MachineState, Offsets,
    Realtime, Response, StatusReport,
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

/// Interval of the `?` sent at connect until the first report (16 over
/// [`CONNECT_TIMEOUT`]).
pub const CONNECT_STATUS_INTERVAL: Duration = Duration::from_millis(250);

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
    /// Settings (`$$`), read at connect when the controller reads lines, else
    /// before the first move.
    settings: Option<BTreeMap<u16, String>>,
    /// Work coordinate offset (from `WCO:` or `$#`), to convert WPos to MPos;
    /// `None` until known (never assumed zero).
    wco_mm: Option<[f64; 3]>,
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
    /// Version from `$I` (`1.1h.20190830`).
    build_version: Option<String>,
    /// State in the last status report.
    last_state: Option<MachineState>,
    /// The connection began with a soft reset of a silent controller.
    reset_at_connect: bool,
    /// Last `[GC:..]` parser state.
    parser_state: Option<String>,
}

/// No travel limit.
const UNBOUNDED: TravelLimits = TravelLimits {
    axes_mm: [[f64::NEG_INFINITY, f64::INFINITY]; 3],
};

/// Consecutive malformed status reports tolerated while waiting (each is re-queried).
pub const MALFORMED_STATUS_RETRIES: u32 = 3;

/// Status reports polled at most for a `WCO:` field (GRBL sends one every 10 reports
/// when idle, every 30 when busy).
pub const WCO_POLL_REPORTS: u32 = 32;

/// True in the states where GRBL's main loop reads lines (and so answers `$G`,
/// `$$`, ...). In Run and Jog it reads them too, but refuses `$$`/`$#`/`$I` with
/// `error:8`; in Hold, Door, Home and Sleep it reads none.
fn reads_lines(s: MachineState) -> bool {
    matches!(
        s,
        MachineState::Idle | MachineState::Alarm | MachineState::Check
    )
}

/// What [`Grbl::unlock_report`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnlockReport {
    /// The steps taken, in order, in words (e.g. "soft reset (0x18): ...").
    pub actions: Vec<String>,
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

/// True for a line that was meant to be a status report (`<...>`, possibly cut).
fn looks_like_status(line: &[u8]) -> bool {
    line.first() == Some(&b'<') || line.last() == Some(&b'>')
}

impl<P: Read + Write> Grbl<P> {
    /// Connects in whatever state the controller is in, without changing it: waits
    /// for a status report (`?`, answered in every state but a critical alarm and a
    /// homing cycle); then, only where GRBL reads lines (Idle, Alarm, Check),
    /// resynchronises the reply stream (`$G`), reads the version (`$I`), the settings
    /// (`$$`) and, when reports carry `WPos`, the work offsets (`$#`). In a busy
    /// state (Run, Jog, Hold, Door, Home, Sleep) only `?` is used; the settings are
    /// read before the first move, once the controller is idle.
    ///
    /// A controller that answers nothing was most likely left in a critical alarm
    /// (hard or soft limit: it ignores everything but a soft reset): the error says so
    /// and that [`Grbl::connect_resetting`] (the CLI's `unlock`) resets it.
    pub fn connect(port: P, config: GrblConfig) -> DeviceResult<Self> {
        Self::connect_with(port, config, false)
    }

    /// [`Grbl::connect`], but a controller that answers no status report is sent a
    /// soft reset (0x18), the only thing a critical alarm answers; the reset is
    /// reported by [`Grbl::reset_at_connect`]. For `unlock`, not for `status`.
    pub fn connect_resetting(port: P, config: GrblConfig) -> DeviceResult<Self> {
        Self::connect_with(port, config, true)
    }

    fn connect_with(port: P, config: GrblConfig, reset_if_silent: bool) -> DeviceResult<Self> {
        let mut g = Grbl {
            port: LinePort::new(port, DEVICE),
            limits: config.limits.unwrap_or(UNBOUNDED),
            config,
            settings: None,
            wco_mm: None,
            alarm: None,
            needs_reset: false,
            needs_resync: true,
            resets_seen: 0,
            last_feedback: None,
            last_message: None,
            version: None,
            build_version: None,
            last_state: None,
            reset_at_connect: false,
            parser_state: None,
        };
        let status = match g.first_status() {
            Ok(s) => s,
            Err(e) if reset_if_silent && e.kind() == ErrorKind::Timeout => {
                g.soft_reset()?;
                g.reset_at_connect = true;
                g.status()?
            }
            Err(e) => return Err(e),
        };
        let state = status_state(&status);
        if state == MachineState::Alarm && g.alarm.is_none() {
            g.alarm = Some(0);
        }
        if reads_lines(state) {
            g.read_configuration(state)?;
        } else if status.wpos_mm.is_some() && g.wco_mm.is_none() {
            g.poll_for_wco()?;
        }
        Ok(g)
    }

    /// The first status report, asking every 250 ms for up to [`CONNECT_TIMEOUT`].
    fn first_status(&mut self) -> DeviceResult<StatusReport> {
        // A fixed number of attempts (not a deadline), so a recorded session
        // replays with the same number of `?`.
        let per_try = CONNECT_STATUS_INTERVAL.min(self.config.status_timeout);
        let tries = (CONNECT_TIMEOUT.as_millis() / CONNECT_STATUS_INTERVAL.as_millis()).max(1);
        let mut garbage = None;
        for _ in 0..tries {
            match self.status_once(per_try) {
                Ok(s) => return Ok(s),
                Err(e) if e.kind() == ErrorKind::Disconnected => return Err(e),
                Err(e) if e.kind() == ErrorKind::Protocol => garbage = Some(e.message),
                Err(_) => {}
            }
        }
        let secs = CONNECT_TIMEOUT.as_secs_f64();
        Err(match garbage {
            Some(g) => DeviceError::new(
                ErrorKind::Timeout,
                DEVICE,
                "?",
                format!("no status report within {secs} s; only unreadable bytes: {g}"),
            )
            .with_hint("is this a GRBL controller, at the right baud rate (115200)?"),
            None => DeviceError::new(
                ErrorKind::Timeout,
                DEVICE,
                "?",
                format!(
                    "no status report within {secs} s: the controller answers nothing. Likely cause: \
                     a critical alarm (ALARM:1 hard limit or ALARM:2 soft limit, \"Reset to continue\"), \
                     in which GRBL ignores everything, even `?`, until a soft reset"
                ),
            )
            .with_hint(
                "`tactbench stage --port PORT --protocol grbl unlock` resets it (0x18) and clears the alarm ($X); \
                 clear the cause first (limit switch, out-of-travel target). If that does not help: \
                 is this a GRBL controller, at 115200 baud?",
            ),
        })
    }

    /// In a state where GRBL reads lines: resync (`$G`, noting the active
    /// coordinate system), version (`$I`), settings (`$$`), offsets (`$#`, when
    /// reports carry `WPos`; in check mode GRBL refuses `$#` and a `WCO:` report is
    /// awaited instead).
    fn read_configuration(&mut self, state: MachineState) -> DeviceResult<()> {
        self.resync_within(self.config.reply_timeout.min(CONNECT_RESYNC_TIMEOUT))?;
        // Check mode refuses `$I` and `$#` (error:8), as the real firmware does.
        if state != MachineState::Check {
            self.read_build_info()?;
        }
        self.read_settings()?;
        self.update_limits();
        if self.reports_wpos() && self.wco_mm.is_none() {
            if state == MachineState::Check {
                self.poll_for_wco()?;
            } else {
                self.read_offsets()?;
            }
        }
        Ok(())
    }

    /// True when the controller reports `WPos` (`$10` bit 0 clear).
    fn reports_wpos(&self) -> bool {
        self.settings
            .as_ref()
            .and_then(|s| s.get(&10))
            .and_then(|v| v.parse::<u32>().ok())
            .is_some_and(|m| m & 1 == 0)
    }

    /// The travel box: GRBL's soft-limit box `[-$13x, 0]` where homing (`$22=1`) and
    /// soft limits (`$20=1`) are both on, intersected with the configured (bench)
    /// box; otherwise the configured box alone (unbounded without one: GRBL then
    /// accepts any coordinate and so does the driver).
    fn update_limits(&mut self) {
        let mut lim = self.config.limits.unwrap_or(UNBOUNDED);
        if let Some(grbl_box) = self.soft_limit_box() {
            for i in 0..3 {
                lim.axes_mm[i][0] = lim.axes_mm[i][0].max(grbl_box.axes_mm[i][0]);
                lim.axes_mm[i][1] = lim.axes_mm[i][1].min(grbl_box.axes_mm[i][1]);
            }
        }
        self.limits = lim;
    }

    /// GRBL's soft-limit box, if the controller enforces one (`$20=1` and `$22=1`).
    pub fn soft_limit_box(&self) -> Option<TravelLimits> {
        let s = self.settings.as_ref()?;
        let flag = |n: u16| s.get(&n).and_then(|v| v.parse::<f64>().ok()) == Some(1.0);
        if !(flag(20) && flag(22)) {
            return None;
        }
        let mut axes_mm = [[0.0; 2]; 3];
        for (i, axis) in axes_mm.iter_mut().enumerate() {
            let v: f64 = s
                .get(&(130 + i as u16))
                .and_then(|v| v.parse().ok())
                .filter(|v: &f64| v.is_finite() && *v > 0.0)?;
            *axis = [-v, 0.0];
        }
        Some(TravelLimits { axes_mm })
    }

    /// True if the connection began with a soft reset of a silent controller
    /// ([`Grbl::connect_resetting`]).
    pub fn reset_at_connect(&self) -> bool {
        self.reset_at_connect
    }

    /// The state in the last status report seen.
    pub fn last_state(&self) -> Option<MachineState> {
        self.last_state
    }

    /// The work coordinate offset in use (MPos = WPos + WCO), once known.
    pub fn wco_mm(&self) -> Option<[f64; 3]> {
        self.wco_mm
    }

    /// The alarm code seen (0: the controller is in alarm, raised before this
    /// connection, code unknown); `None` when not in alarm.
    pub fn alarm(&self) -> Option<u8> {
        self.alarm
    }

    /// The firmware version: from `$I` (`1.1h.20190830`) when the controller answered
    /// it, else from the last banner seen (`1.1h`).
    pub fn version(&self) -> Option<&str> {
        self.build_version.as_deref().or(self.version.as_deref())
    }

    /// Settings (`$N` → value text); empty until read (a controller busy at
    /// connect is asked once it is idle).
    pub fn settings(&self) -> BTreeMap<u16, String> {
        self.settings.clone().unwrap_or_default()
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

    /// The error for a controller that cannot take `command` in `state` (anything but
    /// Idle, and Run for queued moves): Hold/Door → [`ErrorKind::Held`], Alarm →
    /// [`ErrorKind::Limit`], the others [`ErrorKind::Other`], each with a hint.
    fn state_error(&self, command: &str, state: MachineState) -> DeviceError {
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
    fn require_state(
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

    /// Makes sure the settings (and so the travel limits) are known before a move:
    /// a controller connected while busy is asked now (it must be idle or in alarm).
    fn ensure_settings(&mut self, command: &str) -> DeviceResult<()> {
        if self.settings.is_some() {
            return Ok(());
        }
        let s = self.status()?;
        let state = status_state(&s);
        if !reads_lines(state) {
            return Err(self.state_error(command, state));
        }
        self.read_configuration(state)
    }

    /// `$I`: the build version (`[VER:1.1h.20190830:]`).
    fn read_build_info(&mut self) -> DeviceResult<()> {
        self.last_feedback = None;
        let mut version = None;
        self.query_lines(&Command::BuildInfo, |r| {
            if let Response::Feedback(f) = r {
                if let Some(v) = codec::build_version(f) {
                    version = Some(v.to_string());
                }
            }
        })?;
        if version.is_some() {
            self.build_version = version;
        }
        Ok(())
    }

    /// `$#` (and `$G` for the active coordinate system): the work coordinate offset.
    fn read_offsets(&mut self) -> DeviceResult<()> {
        let mut offsets = Offsets::default();
        self.query_lines(&Command::Offsets, |r| {
            if let Response::Feedback(f) = r {
                offsets.take(f);
            }
        })?;
        if self.parser_state.is_none() {
            self.query_lines(&Command::ParserState, |_| {})?;
        }
        let system = self
            .parser_state
            .as_deref()
            .and_then(active_coordinate_system)
            .unwrap_or(0);
        match offsets.wco_mm(system) {
            Some(w) => {
                self.wco_mm = Some(w);
                Ok(())
            }
            None => Err(DeviceError::new(
                ErrorKind::Protocol,
                DEVICE,
                "$#",
                "the `$#` listing lacks the active coordinate system, G92 or TLO offset",
            )),
        }
    }

    /// Polls `?` until a report carries `WCO:` (GRBL sends it every 10 reports when
    /// idle, every 30 when busy): works in every state that answers `?`.
    fn poll_for_wco(&mut self) -> DeviceResult<()> {
        for _ in 0..WCO_POLL_REPORTS {
            let s = self.status()?;
            if s.mpos_mm.is_some() || self.wco_mm.is_some() {
                return Ok(());
            }
        }
        Err(DeviceError::new(
            ErrorKind::Protocol,
            DEVICE,
            "?",
            format!(
                "no `WCO:` field in {WCO_POLL_REPORTS} status reports: cannot convert the reported work position (WPos) to machine position"
            ),
        )
        .with_hint("set `$10=1` on the controller to report machine positions (MPos)"))
    }

    /// Sends a query line (retried on a timeout or garbled reply) and passes every
    /// line before its `ok` to `take`.
    fn query_lines(&mut self, cmd: &Command, mut take: impl FnMut(&Response)) -> DeviceResult<()> {
        let text = cmd.encode();
        let mut last = None;
        for _ in 0..=QUERY_RETRIES {
            if self.needs_resync {
                self.resync()?;
            }
            self.port.send(&cmd.to_bytes(), &text)?;
            let deadline = Instant::now() + self.config.reply_timeout;
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
                        take(&r);
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
                Ok(()) => return Ok(()),
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

    /// Machine position from a report: MPos, or WPos + WCO when the controller
    /// reports WPos (`$10=0`). A WCO not yet seen is asked for (`$#` where GRBL
    /// answers it, else a report carrying `WCO:`), never assumed zero.
    fn mpos_of(&mut self, s: &StatusReport) -> DeviceResult<StagePositionMm> {
        match (s.mpos_mm, s.wpos_mm) {
            (Some(m), _) => Ok(m),
            (None, Some(w)) => {
                if self.wco_mm.is_none() {
                    let state = status_state(s);
                    if matches!(state, MachineState::Idle | MachineState::Alarm) {
                        self.read_offsets()?;
                    } else {
                        self.poll_for_wco()?;
                    }
                }
                let c = self.wco_mm.unwrap_or([0.0; 3]);
                Ok([w[0] + c[0], w[1] + c[1], w[2] + c[2]])
            }
            // parse_status guarantees one of the two.
            (None, None) => Err(DeviceError::new(
                ErrorKind::Protocol,
                DEVICE,
                "?",
                "status report without a position",
            )),
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
    fn resync_when_reading(&mut self, command: &str) -> DeviceResult<()> {
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
                    self.settings = Some(settings);
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

    /// Position and state in one status query, refusing if not idle (relative
    /// moves start from a stopped stage).
    fn idle_position(&mut self, command: &str) -> DeviceResult<StagePositionMm> {
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
            MachineState::Idle | MachineState::Check => StageState::Idle,
            // Asleep, GRBL moves nothing until a reset, after which it is in alarm.
            MachineState::Sleep => StageState::Alarm,
            MachineState::Run | MachineState::Jog => StageState::Moving,
            MachineState::Hold(_) | MachineState::Door(_) => StageState::Held,
            MachineState::Home => StageState::Homing,
            MachineState::Alarm => StageState::Alarm,
        }
    }
}

impl<P: Read + Write> Grbl<P> {
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

    /// Reads until a banner arrives (after a reset GRBL does by itself).
    fn wait_banner(&mut self) -> DeviceResult<()> {
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
