//! Marlin xyz stage (3D printers and small CNCs used as indenters): codec
//! ([`codec`]), driver ([`Marlin`], generic over `Read + Write`, implementing
//! [`Stage`]) and simulator ([`sim::MarlinSim`]). The spec is `protocols/marlin.md`.
//!
//! Marlin is not GRBL: there is no real-time status byte. Every line is answered
//! `ok` when the firmware has *taken* it (a `G1` as soon as it is planned, long before
//! the head arrives), `M114` reports the *planned* position, and only `M400` (wait for
//! the planner to empty) says the motion is over. So:
//! - connect: wait for the boot banner (`start`; the board resets when the port opens),
//!   `M110 N0`, then every line is `N<n> <cmd>*<cs>`; `M115` (firmware, and the
//!   `EMERGENCY_PARSER` capability the stop needs), `M92` (steps/mm), `M203` (maximum
//!   feed rates), `M211` (soft endstops), `G21 G90`, `M114`;
//! - a move is `G0`/`G1` then `M400`, which the driver leaves outstanding:
//!   [`Stage::state`] is `Moving` until the `M400`'s `ok` arrives, and
//!   [`Stage::wait_idle`] then checks `M114`'s step counts against the target (to the
//!   step: targets are rounded to whole steps before they are sent);
//! - `echo:busy: processing` keep-alives (every 2 s while a command blocks) extend the
//!   deadline; a silence longer than [`MarlinConfig::silence_timeout`] is answered by
//!   re-sending the oldest unacknowledged line (safe: line numbers make it idempotent:
//!   a line the firmware already took is refused with `Error:Line Number is not Last
//!   Line Number+1, Last Line: n`, which acknowledges it), and a second silence is a
//!   [`ErrorKind::Timeout`], never a hang;
//! - `Resend: n` (after `Error:checksum mismatch` and friends) re-sends lines n.. from
//!   the history; the `ok` Marlin prints right after `Resend:` acknowledges nothing;
//! - targets outside the bench's travel box or the firmware's soft endstops are refused
//!   before anything is sent, naming the limit (Marlin would clamp them silently);
//!   feed rates are validated per axis against the `M203` maxima (Marlin would clamp
//!   them too);
//! - a machine built with `NO_MOTION_BEFORE_HOMING` answers a move before homing with
//!   `echo:Home XYZ first` (and `ok`, without moving): a clear error here;
//! - stop = `M410` (quick stop), acted on at once by the emergency parser even while
//!   `M400` blocks the queue; then the outstanding `ok`s are collected and `M114`
//!   re-syncs the position. Without `EMERGENCY_PARSER` an `M410` would wait behind the
//!   `M400`, so connecting to such firmware is refused unless
//!   [`MarlinConfig::require_emergency_parser`] is off;
//! - [`Marlin::emergency_stop`] sends `M112`: the firmware halts (`Error:Printer
//!   halted. kill() called!`) and answers nothing until it is reset (reset button,
//!   power cycle, or re-opening the port on boards that reset on DTR).

pub mod codec;
pub mod sim;

use std::collections::VecDeque;
use std::io::{Read, Write};
use std::time::{Duration, Instant};

use self::codec::{
    decode, frame, move_command, parse_capabilities, parse_position, parse_setting,
    parse_soft_endstops, reset_line_numbers, Capabilities, ErrorLine, PositionReport, Reply,
    SoftEndstops,
};
use super::lineio::{open_stage_serial, LinePort};
use super::{
    DeviceError, DeviceResult, ErrorKind, Stage, StagePositionMm, StageState, TravelLimits,
};

/// Device name in errors.
pub const DEVICE: &str = "marlin";

/// Default baud rate (Marlin's `BAUDRATE` default; many printers use 250000).
pub const DEFAULT_BAUD: u32 = 115_200;

/// How long the board may take to print its boot banner after the port opens.
pub const BANNER_TIMEOUT: Duration = Duration::from_secs(3);

/// Longest silence while a command runs: Marlin's host keep-alive prints `busy:`
/// every 2 s (`DEFAULT_KEEPALIVE_INTERVAL`), so 5 s of nothing means a lost line.
pub const SILENCE_TIMEOUT: Duration = Duration::from_secs(5);

/// Time for the homing cycle.
pub const HOMING_TIMEOUT: Duration = Duration::from_secs(180);

/// How often the runner may ask [`Stage::state`] while a move runs: it only looks for
/// the `M400`'s `ok` (no command is sent), so it can be frequent.
pub const STATUS_INTERVAL: Duration = Duration::from_millis(50);

/// `Resend:` requests accepted for one command before giving up.
pub const MAX_RESENDS: u32 = 5;

/// How long after a line error (`Error:` / `Resend:`) the next `ok` is taken for the one
/// Marlin prints right after `Resend:` (it comes in the same burst).
const RESEND_OK_WINDOW: Duration = Duration::from_millis(250);

/// After the line end that flushes another protocol's leftover bytes, how long the
/// handshake reads away what the firmware answers at least (with a short banner wait).
const RESYNC_DRAIN: Duration = Duration::from_millis(200);

/// Line-counter resynchronisations (`M110`) allowed per connection.
const MAX_RESYNCS: u32 = 8;

/// Times a query whose reply held a garbled line (or, for `M115`, no firmware line) is
/// asked again before its answer is taken as it is.
const QUERY_TRIES: u32 = 4;

/// Lines kept for re-sending.
const HISTORY: usize = 32;

/// Driver configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct MarlinConfig {
    /// The bench's travel box, mm (checked before every move, with the soft endstops).
    pub limits: Option<TravelLimits>,
    /// Time for the boot banner after the port opens.
    pub banner_timeout: Duration,
    /// Longest silence while a command runs (see [`SILENCE_TIMEOUT`]).
    pub silence_timeout: Duration,
    /// Time for the homing cycle.
    pub homing_timeout: Duration,
    /// Maximum feed rates X, Y, Z in mm/min when the firmware does not report `M203`.
    pub max_feed_mm_min: Option<[f64; 3]>,
    /// Steps per mm X, Y, Z when the firmware does not report `M92`.
    pub steps_per_mm: Option<[f64; 3]>,
    /// Refuse firmware without `Cap:EMERGENCY_PARSER:1` (its `M410` cannot stop a move).
    pub require_emergency_parser: bool,
}

impl Default for MarlinConfig {
    fn default() -> Self {
        MarlinConfig {
            limits: None,
            banner_timeout: BANNER_TIMEOUT,
            silence_timeout: SILENCE_TIMEOUT,
            homing_timeout: HOMING_TIMEOUT,
            max_feed_mm_min: None,
            steps_per_mm: None,
            require_emergency_parser: true,
        }
    }
}

/// Opens a serial port for a Marlin board (8N1, short read timeout).
pub fn open_serial(path: &str, baud: u32) -> DeviceResult<Box<dyn serialport::SerialPort>> {
    open_stage_serial(
        DEVICE,
        path,
        baud,
        "Marlin boards use 115200 or 250000 baud",
    )
}

/// A move whose `M400` is outstanding.
#[derive(Debug, Clone, Copy)]
struct PendingMove {
    /// Line number of the `M400`.
    m400: u32,
    /// Target, mm (rounded to steps).
    target: StagePositionMm,
    /// Expected duration.
    expected: Duration,
    /// When the `M400` was sent.
    sent: Instant,
}

/// What the driver learnt at connect.
#[derive(Debug, Clone, PartialEq)]
pub struct MachineInfo {
    /// Firmware name and version from `M115`.
    pub firmware: Option<String>,
    /// Whether the firmware reported `Cap:EMERGENCY_PARSER:1`.
    pub emergency_parser: bool,
    /// Steps per mm X, Y, Z (`M92`, or the configured fallback).
    pub steps_per_mm: Option<[f64; 3]>,
    /// Maximum feed rates X, Y, Z in mm/min (`M203` × 60, or the configured fallback).
    pub max_feed_mm_min: Option<[f64; 3]>,
    /// Soft endstops (`M211`).
    pub soft_endstops: Option<SoftEndstops>,
    /// Whether the boot banner was seen at connect (the board reset when the port opened).
    pub banner_seen: bool,
}

/// A Marlin board driving an xyz stage.
#[derive(Debug)]
pub struct Marlin<P> {
    port: LinePort<P>,
    config: MarlinConfig,
    /// Line number of the next line.
    next_n: u32,
    /// Sent lines (number, framed text) for re-sending.
    history: VecDeque<(u32, String)>,
    /// Lines sent and not yet acknowledged, oldest first.
    outstanding: VecDeque<u32>,
    /// The `Resend:` that will follow a line error already acted on (the `Error:` line
    /// names the same line): it is not served a second time.
    handled_resend: Option<u32>,
    /// Until when an `ok` acknowledges nothing: Marlin prints one right after each
    /// line error's `Resend:`.
    swallow_ok_until: Option<Instant>,
    /// Unreadable lines since the last line was sent (a query's text may be lost).
    garbled: u32,
    /// Line-counter resynchronisations (`M110`) so far.
    resyncs: u32,
    /// `echo:` and other text lines seen since the last command was sent.
    text: Vec<String>,
    /// A position report seen since the last command was sent.
    report: Option<PositionReport>,
    /// `echo:Home .. first` seen since the last command was sent.
    home_first: Option<String>,
    pending: Option<PendingMove>,
    halted: bool,
    info: MachineInfo,
    resends: u32,
    probes: u32,
}

const AXES: [&str; 3] = ["x", "y", "z"];

impl<P: Read + Write> Marlin<P> {
    /// Connects: waits for the boot banner, resets the line numbers and reads the
    /// machine's configuration (see the module docs).
    pub fn connect(port: P, config: MarlinConfig) -> DeviceResult<Self> {
        let mut m = Marlin {
            port: LinePort::new(port, DEVICE),
            config,
            next_n: 1,
            history: VecDeque::new(),
            outstanding: VecDeque::new(),
            handled_resend: None,
            swallow_ok_until: None,
            garbled: 0,
            resyncs: 0,
            text: Vec::new(),
            report: None,
            home_first: None,
            pending: None,
            halted: false,
            info: MachineInfo {
                firmware: None,
                emergency_parser: false,
                steps_per_mm: None,
                max_feed_mm_min: None,
                soft_endstops: None,
                banner_seen: false,
            },
            resends: 0,
            probes: 0,
        };
        m.handshake()?;
        // Judge the firmware only on a whole `M115` answer: its `FIRMWARE_NAME` line
        // (leftover bytes of another protocol, or line noise, can cost the answer).
        let caps = m
            .query_until("M115", |lines| parse_capabilities(lines).firmware.is_some())
            .map(|lines| parse_capabilities(&lines))?;
        m.info.firmware = caps.firmware.clone();
        m.info.emergency_parser = caps.has("EMERGENCY_PARSER");
        if m.config.require_emergency_parser && !m.info.emergency_parser {
            return Err(no_emergency_parser(&caps));
        }
        let m92 = m.query("M92")?;
        m.info.steps_per_mm = parse_setting(&m92, "M92")
            .filter(|s| s.iter().all(|v| v.is_finite() && *v > 0.0))
            .or(m.config.steps_per_mm);
        let m203 = m.query("M203")?;
        m.info.max_feed_mm_min = parse_setting(&m203, "M203")
            .filter(|s| s.iter().all(|v| v.is_finite() && *v > 0.0))
            .map(|v| v.map(|x| x * 60.0))
            .or(m.config.max_feed_mm_min);
        let m211 = m.query("M211")?;
        m.info.soft_endstops = parse_soft_endstops(&m211);
        // Room for a silence probe: an `ok` lost here is recovered like any other.
        m.command("G21", m.config.silence_timeout * 3)?;
        m.command("G90", m.config.silence_timeout * 3)?;
        Ok(m)
    }

    /// What was read at connect.
    pub fn info(&self) -> &MachineInfo {
        &self.info
    }

    /// `Resend:` requests served and silence probes sent so far.
    pub fn recoveries(&self) -> (u32, u32) {
        (self.resends, self.probes)
    }

    /// Line-counter resynchronisations (`M110` after the firmware refused a line by a
    /// number this connection never sent) so far.
    pub fn resyncs(&self) -> u32 {
        self.resyncs
    }

    /// Whether the firmware reported a halt (`M112` or a fatal error).
    pub fn halted(&self) -> bool {
        self.halted
    }

    /// The port back.
    pub fn into_inner(self) -> P {
        self.port.into_inner()
    }

    /// Ends whatever partial line the firmware holds, waits for the boot banner (and
    /// reads away what the board prints), then `M110 N0`.
    ///
    /// Why the newline first: a board that does not reset when the port opens still
    /// holds the bytes of whatever spoke to it last (a GRBL `?`, a DynPick `R`, a
    /// Bota's binary configuration) without a line end; they would prefix our
    /// `N0 M110 N0` and make it an unknown command, leaving the firmware's line counter
    /// where the last session left it, so the next numbered line would be refused. The
    /// newline makes that junk a line of its own, answered (an unknown command and an
    /// `ok`) and read away here, at least [`RESYNC_DRAIN`] long, before any of our
    /// lines is sent.
    fn handshake(&mut self) -> DeviceResult<()> {
        let start = Instant::now();
        self.port.send(b"\n", "connect")?;
        let banner_deadline = start + self.config.banner_timeout.max(RESYNC_DRAIN);
        let mut received: Vec<String> = Vec::new();
        let mut garbage = 0usize;
        // Read until the banner has been seen and the board has been quiet for a
        // moment (it prints its configuration after `start`), or the banner time is up.
        let quiet = Duration::from_millis(300);
        loop {
            // A board that keeps talking after its banner is cut off 5 s later.
            let deadline = if self.info.banner_seen {
                (Instant::now() + quiet).min(banner_deadline + Duration::from_secs(5))
            } else {
                banner_deadline
            };
            match self.port.read_line(deadline, "connect") {
                Ok(raw) => match decode(&raw) {
                    Ok(Reply::Start) => self.info.banner_seen = true,
                    Ok(Reply::Error(ErrorLine::Halted)) => {
                        self.halted = true;
                        return Err(halted_error("connect"));
                    }
                    Ok(_) => received.push(String::from_utf8_lossy(&raw).into_owned()),
                    Err(_) => garbage += raw.len(),
                },
                Err(e) if e.kind() == ErrorKind::Timeout => break,
                Err(e) => return Err(e),
            }
        }
        let line = reset_line_numbers();
        self.port.send(format!("{line}\n").as_bytes(), "M110 N0")?;
        self.history.push_back((0, line));
        self.outstanding.push_back(0);
        self.next_n = 1;
        // Room for a silence probe (the `M110` re-sent): its `ok` may be lost too.
        let answer = self.collect(
            0,
            Instant::now() + self.config.silence_timeout * 3,
            "M110 N0",
        );
        match answer {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == ErrorKind::Timeout => {
                let waited = self.config.banner_timeout.as_secs_f64();
                let silence = self.config.silence_timeout.as_secs_f64();
                Err(
                    if !self.info.banner_seen && received.is_empty() && garbage == 0 {
                        DeviceError::new(
                        ErrorKind::Timeout,
                        DEVICE,
                        "M110 N0",
                        format!(
                            "nothing answered: no boot banner (`start`) within {waited:.1} s and no `ok` to `M110 N0` within {silence:.1} s, twice"
                        ),
                    )
                    .with_hint("check the port (`tactbench ports`), the cable and that the board is powered; Marlin uses 115200 or 250000 baud")
                    } else if !self.info.banner_seen {
                        DeviceError::new(
                        ErrorKind::Protocol,
                        DEVICE,
                        "M110 N0",
                        format!(
                            "the board sent {} line(s) and {garbage} unreadable byte(s) but never its boot banner (`start`) within {waited:.1} s nor an `ok` to `M110 N0` (sent twice){}",
                            received.len(),
                            received
                                .last()
                                .map(|l| format!(" (last line: {l:?})"))
                                .unwrap_or_default()
                        ),
                    )
                    .with_hint("wrong baud rate (Marlin: 115200 or 250000), or not Marlin firmware, or a board stuck in its bootloader: reset it")
                    } else {
                        DeviceError::new(
                        ErrorKind::Timeout,
                        DEVICE,
                        "M110 N0",
                        format!("the board printed its boot banner but did not answer `M110 N0` within {silence:.1} s, twice"),
                    )
                    .with_hint("the board may still be booting or waiting for a display: reset it and try again")
                    },
                )
            }
            Err(e) => Err(e),
        }
    }

    /// Sends one numbered line; it stays outstanding until its `ok`.
    fn send(&mut self, cmd: &str) -> DeviceResult<u32> {
        if self.halted {
            return Err(halted_error(cmd));
        }
        let n = self.next_n;
        self.next_n += 1;
        let line = frame(n, cmd);
        self.text.clear();
        self.report = None;
        self.home_first = None;
        self.garbled = 0;
        self.port.send(format!("{line}\n").as_bytes(), cmd)?;
        self.history.push_back((n, line));
        while self.history.len() > HISTORY {
            self.history.pop_front();
        }
        self.outstanding.push_back(n);
        Ok(n)
    }

    fn is_acked(&self, n: u32) -> bool {
        !self.outstanding.contains(&n)
    }

    /// Reads and handles lines until line `n` is acknowledged. Busy keep-alives and any
    /// other line extend the silence deadline; `overall` bounds the whole wait.
    fn collect(&mut self, n: u32, overall: Instant, command: &str) -> DeviceResult<()> {
        let mut last_activity = Instant::now();
        let mut probed = false;
        let mut resends = 0u32;
        while !self.is_acked(n) {
            let silence_end = last_activity + self.config.silence_timeout;
            let deadline = silence_end.min(overall);
            match self.read_one(deadline, command, &mut resends)? {
                Some(()) => {
                    last_activity = Instant::now();
                    probed = false;
                }
                None => {
                    if Instant::now() >= overall {
                        return Err(DeviceError::new(
                            ErrorKind::Timeout,
                            DEVICE,
                            command,
                            "not acknowledged within the time allowed",
                        ));
                    }
                    if probed {
                        return Err(DeviceError::new(
                            ErrorKind::Timeout,
                            DEVICE,
                            command,
                            format!(
                                "silence: nothing from the board for {:.1} s, twice (the second time after re-sending line {})",
                                self.config.silence_timeout.as_secs_f64(),
                                self.outstanding.front().copied().unwrap_or(n)
                            ),
                        )
                        .with_hint("the board stopped answering: check the cable; `tactbench stage --protocol marlin status`"));
                    }
                    self.probe(command)?;
                    probed = true;
                    last_activity = Instant::now();
                }
            }
        }
        Ok(())
    }

    /// After a silence: re-send the oldest outstanding line. If the firmware had taken
    /// it (its `ok` was lost) it refuses the copy by line number, which acknowledges it;
    /// if the line was lost on the way in, the copy is executed now.
    fn probe(&mut self, command: &str) -> DeviceResult<()> {
        let Some(&oldest) = self.outstanding.front() else {
            return Ok(());
        };
        let Some(line) = self
            .history
            .iter()
            .find(|(k, _)| *k == oldest)
            .map(|(_, l)| l.clone())
        else {
            return Ok(());
        };
        self.probes += 1;
        self.port.send(format!("{line}\n").as_bytes(), command)
    }

    /// Reads one line (until `deadline`) and handles it. `Ok(None)` on a timeout.
    fn read_one(
        &mut self,
        deadline: Instant,
        command: &str,
        resends: &mut u32,
    ) -> DeviceResult<Option<()>> {
        let raw = match self.port.read_line(deadline, command) {
            Ok(r) => r,
            Err(e) if e.kind() == ErrorKind::Timeout => return Ok(None),
            Err(e) => return Err(e),
        };
        let reply = match decode(&raw) {
            Ok(r) => r,
            // A garbled line may have been an `ok`: the silence probe recovers it. It
            // is not taken for anything now (a garbled `ok` taken for a garbled busy
            // line, or the reverse, would lose track of the queue).
            Err(_) => {
                self.garbled += 1;
                return Ok(Some(()));
            }
        };
        match reply {
            Reply::Ok(rest) => {
                // The `ok` Marlin prints after a line error's `Resend:` acknowledges
                // nothing (whether the `Error:` or the `Resend:` line, or both, came
                // through readable).
                if self
                    .swallow_ok_until
                    .take()
                    .is_some_and(|t| Instant::now() <= t)
                {
                    self.handled_resend = None;
                    return Ok(Some(()));
                }
                if self.outstanding.pop_front().is_some() {
                    if let Some(p) = parse_position(&rest) {
                        self.report = Some(p);
                    }
                }
            }
            Reply::Resend(r) => {
                self.swallow_ok_until = Some(Instant::now() + RESEND_OK_WINDOW);
                if self.handled_resend.take() == Some(r) || r >= self.next_n {
                    // Served from its `Error:` line already, or a request for a line
                    // not sent yet (after the refusal of a probe's copy): nothing to do.
                    return Ok(Some(()));
                }
                self.serve_resend(r, command, resends)?;
            }
            Reply::Error(ErrorLine::LineNumber { last }) => {
                self.swallow_ok_until = Some(Instant::now() + RESEND_OK_WINDOW);
                self.handled_resend = Some(last + 1);
                if last >= self.next_n {
                    // The firmware counts lines this connection never sent: its
                    // counter was left elsewhere (a `M110` lost or swallowed by another
                    // protocol's leftover bytes). Nothing of ours after the last `ok`
                    // was taken: reset the counter and send those lines again.
                    self.resync(command)?;
                    return Ok(Some(()));
                }
                // The refusal of a copy (a probe): every line up to `last` was taken.
                // Lines taken but not finished cannot be refused this way: the
                // firmware reads the copy only once it is free again. When `last` is
                // the newest line sent, the `Resend: last+1` that follows asks for
                // nothing; otherwise (a line lost on the way in) it is a real request,
                // served now (the `Resend:` line may come garbled).
                self.outstanding.retain(|k| *k > last);
                if last + 1 < self.next_n {
                    self.serve_resend(last + 1, command, resends)?;
                }
            }
            Reply::Error(ErrorLine::Checksum { last } | ErrorLine::NoChecksum { last }) => {
                self.swallow_ok_until = Some(Instant::now() + RESEND_OK_WINDOW);
                self.handled_resend = Some(last + 1);
                if last >= self.next_n {
                    self.resync(command)?;
                } else if self.outstanding.front() == Some(&0) {
                    // The connection's `M110 N0` (line 0) itself arrived corrupted:
                    // `Last Line` is the firmware's old counter, not about it.
                    self.serve_resend(0, command, resends)?;
                } else if last + 1 < self.next_n {
                    self.serve_resend(last + 1, command, resends)?;
                }
            }
            Reply::Error(ErrorLine::Halted) => {
                self.halted = true;
                self.pending = None;
                return Err(halted_error(command));
            }
            Reply::Error(ErrorLine::Stopped) => {
                return Err(DeviceError::new(
                    ErrorKind::Other,
                    DEVICE,
                    command,
                    "the firmware is stopped after an error (`Printer stopped due to errors`)",
                )
                .with_hint(
                    "fix the cause, then `tactbench stage --protocol marlin unlock` (M999)",
                ));
            }
            Reply::Error(ErrorLine::Other(t)) => self.text.push(format!("Error:{t}")),
            Reply::Busy(_) | Reply::Wait => {}
            Reply::Start => {
                self.pending = None;
                self.outstanding.clear();
                return Err(DeviceError::new(
                    ErrorKind::Other,
                    DEVICE,
                    command,
                    "the board reset (printed `start`): queued commands are lost and the position is unknown",
                )
                .with_hint("reconnect and home the machine"));
            }
            Reply::Position(p) => self.report = Some(p),
            Reply::Echo(t) => {
                let trimmed = t.trim();
                if trimmed.starts_with("Home ") && trimmed.ends_with("first") {
                    self.home_first = Some(trimmed.to_string());
                }
                self.text.push(t);
            }
            Reply::Other(t) => self.text.push(t),
        }
        Ok(Some(()))
    }

    /// Re-sends lines `r..` from the history (a `Resend: r` or the line error it
    /// follows). More than [`MAX_RESENDS`] for one command is an error.
    fn serve_resend(&mut self, r: u32, command: &str, resends: &mut u32) -> DeviceResult<()> {
        *resends += 1;
        self.resends += 1;
        if *resends > MAX_RESENDS {
            return Err(DeviceError::new(
                ErrorKind::Protocol,
                DEVICE,
                command,
                format!("the board asked {MAX_RESENDS} times to resend line {r}: the line keeps arriving corrupted"),
            )
            .with_hint("check the cable and the baud rate"));
        }
        let lines: Vec<String> = self
            .history
            .iter()
            .filter(|(k, _)| *k >= r)
            .map(|(_, l)| l.clone())
            .collect();
        if lines.is_empty() {
            return Err(DeviceError::new(
                ErrorKind::Protocol,
                DEVICE,
                command,
                format!("the board asked to resend line {r}, which is no longer kept"),
            ));
        }
        for l in lines {
            self.port.send(format!("{l}\n").as_bytes(), command)?;
        }
        Ok(())
    }

    /// Sets the firmware's line counter to the line before the oldest unacknowledged
    /// one (`N<k> M110 N<k>`, which Marlin takes whatever its counter says) and sends
    /// the unacknowledged lines again. The `M110`'s own `ok` is expected first.
    fn resync(&mut self, command: &str) -> DeviceResult<()> {
        self.resyncs += 1;
        if self.resyncs > MAX_RESYNCS {
            return Err(DeviceError::new(
                ErrorKind::Protocol,
                DEVICE,
                command,
                format!("the board's line counter disagrees with ours after {MAX_RESYNCS} resets (M110)"),
            )
            .with_hint("another program may be writing to the port: close it, reset the board"));
        }
        let k = self
            .outstanding
            .front()
            .copied()
            .unwrap_or(self.next_n)
            .saturating_sub(1);
        let m110 = frame(k, &format!("M110 N{k}"));
        self.port.send(format!("{m110}\n").as_bytes(), command)?;
        let lines: Vec<String> = self
            .history
            .iter()
            .filter(|(n, _)| self.outstanding.contains(n))
            .map(|(_, l)| l.clone())
            .collect();
        // A probe of `k` (its `ok` lost) re-sends the old line `k`, which the firmware
        // then refuses by number: acknowledged either way.
        self.outstanding.push_front(k);
        for l in lines {
            self.port.send(format!("{l}\n").as_bytes(), command)?;
        }
        Ok(())
    }

    /// Sends `cmd` and waits for its `ok`.
    fn command(&mut self, cmd: &str, overall: Duration) -> DeviceResult<()> {
        let n = self.send(cmd)?;
        self.collect(n, Instant::now() + overall, cmd)
    }

    /// Sends a query and returns the text lines it printed before its `ok`. A reply
    /// with a garbled line may lack the line asked for: the query is asked again, up
    /// to [`QUERY_TRIES`] times (queries change nothing), and the last answer is taken.
    fn query(&mut self, cmd: &str) -> DeviceResult<Vec<String>> {
        self.query_until(cmd, |_| true)
    }

    /// [`Marlin::query`], also asked again while `complete` says the answer is not.
    fn query_until(
        &mut self,
        cmd: &str,
        complete: impl Fn(&[String]) -> bool,
    ) -> DeviceResult<Vec<String>> {
        let mut tries = 0;
        loop {
            tries += 1;
            self.command(cmd, self.config.silence_timeout * 2)?;
            let text = std::mem::take(&mut self.text);
            if tries >= QUERY_TRIES || (self.garbled == 0 && complete(&text)) {
                return Ok(text);
            }
        }
    }

    /// `M114`: the position in mm, from the step counts when they agree with the
    /// logical position (no workspace offset), else the logical position.
    fn m114(&mut self) -> DeviceResult<StagePositionMm> {
        for attempt in 0..3 {
            self.command("M114", self.config.silence_timeout * 2)?;
            if let Some(p) = self.report.take() {
                return Ok(self.position_of(&p));
            }
            // The report line was garbled: M114 is a query, ask again.
            let _ = attempt;
        }
        Err(DeviceError::new(
            ErrorKind::Protocol,
            DEVICE,
            "M114",
            "no readable position report in three tries",
        ))
    }

    fn position_of(&self, p: &PositionReport) -> StagePositionMm {
        if let (Some(c), Some(spm)) = (p.count_steps, self.info.steps_per_mm) {
            let from_counts = [0, 1, 2].map(|i| c[i] as f64 / spm[i]);
            // M114 prints the logical position with 2 decimals.
            if (0..3).all(|i| (from_counts[i] - p.xyz_mm[i]).abs() <= 0.0051 + 0.5 / spm[i]) {
                return from_counts;
            }
        }
        p.xyz_mm
    }

    /// Rounds a target to whole steps.
    fn quantize(&self, t: StagePositionMm) -> StagePositionMm {
        match self.info.steps_per_mm {
            Some(spm) => [0, 1, 2].map(|i| (t[i] * spm[i]).round() / spm[i]),
            None => t,
        }
    }

    /// Checks a target against the bench's travel box and the soft endstops.
    fn check_target(&self, target: StagePositionMm, command: &str) -> DeviceResult<()> {
        let refuse = |m: String| {
            DeviceError::new(ErrorKind::Limit, DEVICE, command, m)
                .with_hint("the move was not sent")
        };
        if let Some(l) = &self.config.limits {
            l.check(target).map_err(|m| {
                refuse(format!(
                    "{m} (the bench's travel box, [stage] travel_min_mm / travel_max_mm)"
                ))
            })?;
        }
        if let Some(s) = self.info.soft_endstops.filter(|s| s.enabled) {
            for i in 0..3 {
                let v = target[i];
                if !v.is_finite() {
                    return Err(refuse(format!(
                        "requested {} = {v} mm is not a finite position",
                        AXES[i]
                    )));
                }
                // Half a step of slack: the firmware compares the same rounded value.
                if v < s.min_mm[i] - 1e-9 {
                    return Err(refuse(format!(
                        "requested {} = {v} mm is below the soft endstop {} mm (M211 Min); Marlin would clamp it silently",
                        AXES[i], s.min_mm[i]
                    )));
                }
                if v > s.max_mm[i] + 1e-9 {
                    return Err(refuse(format!(
                        "requested {} = {v} mm exceeds the soft endstop {} mm (M211 Max); Marlin would clamp it silently",
                        AXES[i], s.max_mm[i]
                    )));
                }
            }
        }
        for (i, v) in target.iter().enumerate() {
            if !v.is_finite() {
                return Err(refuse(format!(
                    "requested {} = {v} mm is not a finite position",
                    AXES[i]
                )));
            }
        }
        Ok(())
    }

    /// Validates a feed rate (mm/s from the caller) for a move from `from` to `to`
    /// and returns it in mm/min: zero, negative or a component above the machine's
    /// maximum for its axis (M203) is an error (Marlin would clamp it).
    fn feed(
        &self,
        speed_mm_s: Option<f64>,
        from: StagePositionMm,
        to: StagePositionMm,
        command: &str,
    ) -> DeviceResult<Option<f64>> {
        let Some(v) = speed_mm_s else { return Ok(None) };
        let f = v * 60.0;
        if !(f.is_finite() && f > 0.0) {
            return Err(DeviceError::new(
                ErrorKind::Rejected,
                DEVICE,
                command,
                format!("feed rate {f} mm/min ({v} mm/s) must be a positive number"),
            ));
        }
        if let Some(max) = self.info.max_feed_mm_min {
            let d = [0, 1, 2].map(|i| to[i] - from[i]);
            let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            for i in 0..3 {
                // The axis' share of the feed (all of it for a move along one axis).
                let share = if len > 0.0 { d[i].abs() / len } else { 1.0 };
                if share > 0.0 && f * share > max[i] * (1.0 + 1e-9) {
                    return Err(DeviceError::new(
                        ErrorKind::Rejected,
                        DEVICE,
                        command,
                        format!(
                            "feed rate {f:.1} mm/min ({v} mm/s) moves {} at {:.1} mm/min, above the machine's maximum {:.1} mm/min (M203 {} {:.2} mm/s)",
                            AXES[i],
                            f * share,
                            max[i],
                            AXES[i].to_ascii_uppercase(),
                            max[i] / 60.0
                        ),
                    )
                    .with_hint("lower the speed (the plan's safety.max_speed_mm_s / --speed); Marlin would clamp it silently"));
                }
            }
        }
        Ok(Some(f))
    }

    /// The planned position (M114 while nothing is pending).
    fn settled_position(&mut self, command: &str) -> DeviceResult<StagePositionMm> {
        if self.pending.is_some() {
            self.finish_pending(self.config.homing_timeout, command)?;
        }
        self.m114()
    }

    /// Sends a move (G0/G1) and its `M400`, leaving the `M400` outstanding.
    fn start_move(
        &mut self,
        target: StagePositionMm,
        speed_mm_s: Option<f64>,
        what: &str,
    ) -> DeviceResult<()> {
        if self.pending.is_some() {
            return Err(DeviceError::new(
                ErrorKind::Other,
                DEVICE,
                what,
                "a move is still running: wait for it or stop it first",
            ));
        }
        let target = self.quantize(target);
        self.check_target(target, what)?;
        let from = self.m114()?;
        let feed = self.feed(speed_mm_s, from, target, what)?;
        let cmd = move_command(target, feed);
        self.command(&cmd, self.config.silence_timeout * 2)?;
        if let Some(msg) = self.home_first.take() {
            return Err(DeviceError::new(
                ErrorKind::Other,
                DEVICE,
                cmd,
                format!("the machine must be homed before it moves (it answered `{msg}` and did not move)"),
            )
            .with_hint("home it first: `tactbench stage --protocol marlin home`, or `home = true` in the bench's [geometry]"));
        }
        let dist = (0..3)
            .map(|i| (target[i] - from[i]).powi(2))
            .sum::<f64>()
            .sqrt();
        let speed = match (feed, self.info.max_feed_mm_min) {
            (Some(f), _) => f / 60.0,
            (None, Some(m)) => m.iter().cloned().fold(f64::INFINITY, f64::min) / 60.0,
            (None, None) => 10.0,
        };
        let expected = Duration::from_secs_f64((dist / speed.max(1e-6)).min(3600.0));
        let m400 = self.send("M400")?;
        self.pending = Some(PendingMove {
            m400,
            target,
            expected,
            sent: Instant::now(),
        });
        Ok(())
    }

    /// Waits for the outstanding `M400` (busy keep-alives extend the wait; the silence
    /// limit starts after the move's expected duration).
    fn finish_pending(
        &mut self,
        timeout: Duration,
        command: &str,
    ) -> DeviceResult<Option<PendingMove>> {
        let Some(p) = self.pending else {
            return Ok(None);
        };
        let overall = Instant::now() + timeout;
        // The firmware prints keep-alives while M400 blocks, so silence is measured
        // from the later of now and the move's expected end.
        let earliest_silence = p.sent + p.expected;
        let mut resends = 0u32;
        let mut probed = false;
        let mut last_activity = Instant::now().max(earliest_silence);
        while !self.is_acked(p.m400) {
            let deadline = (last_activity + self.config.silence_timeout).min(overall);
            match self.read_one(deadline, command, &mut resends) {
                Ok(Some(())) => {
                    last_activity = Instant::now().max(earliest_silence);
                    probed = false;
                }
                Ok(None) => {
                    if Instant::now() >= overall {
                        return Err(DeviceError::new(
                            ErrorKind::Timeout,
                            DEVICE,
                            command,
                            format!("still moving after {:.1} s", timeout.as_secs_f64()),
                        ));
                    }
                    if probed {
                        self.pending = None;
                        return Err(DeviceError::new(
                            ErrorKind::Timeout,
                            DEVICE,
                            command,
                            format!(
                                "silence: no `ok` to M400 and no keep-alive for {:.1} s, twice",
                                self.config.silence_timeout.as_secs_f64()
                            ),
                        )
                        .with_hint(
                            "the board stopped answering: check the cable; the position is unknown",
                        ));
                    }
                    self.probe(command)?;
                    probed = true;
                    last_activity = Instant::now();
                }
                Err(e) => {
                    self.pending = None;
                    return Err(e);
                }
            }
        }
        self.pending = None;
        Ok(Some(p))
    }

    /// Waits for the move and checks the position against its target, to the step.
    fn wait_reached(&mut self, timeout: Duration, command: &str) -> DeviceResult<()> {
        let Some(p) = self.finish_pending(timeout, command)? else {
            return Ok(());
        };
        let here = self.m114()?;
        let tol = match self.info.steps_per_mm {
            Some(spm) => [0, 1, 2].map(|i| 0.5 / spm[i]),
            None => [0.0051; 3],
        };
        for i in 0..3 {
            if (here[i] - p.target[i]).abs() > tol[i] {
                return Err(DeviceError::new(
                    ErrorKind::Other,
                    DEVICE,
                    command,
                    format!(
                        "the machine stands at {} = {:.4} mm, not at the target {:.4} mm",
                        AXES[i], here[i], p.target[i]
                    ),
                )
                .with_hint("a clamp by the firmware's soft endstops or a stop: check `M211` and the bench's travel box"));
            }
        }
        Ok(())
    }

    /// Relative move by `delta_mm` (there is no jog mode in Marlin: the target is
    /// computed from `M114` and checked like any move).
    pub fn jog(&mut self, delta_mm: StagePositionMm, speed_mm_s: f64) -> DeviceResult<()> {
        let here = self.settled_position("jog")?;
        let target = [0, 1, 2].map(|i| here[i] + delta_mm[i]);
        self.start_move(target, Some(speed_mm_s), "jog")
    }

    /// `M112`: emergency stop. The firmware halts at once and answers nothing until
    /// it is reset (reset button, power cycle, or re-opening the port on a board that
    /// resets on DTR); the position is lost. Prefer [`Stage::stop`] (`M410`).
    pub fn emergency_stop(&mut self) -> DeviceResult<()> {
        // Unnumbered: the emergency parser acts on it whatever the line counter says.
        self.port.send(b"M112\n", "M112")?;
        self.halted = true;
        self.pending = None;
        self.outstanding.clear();
        // Collect the halt message if it comes (not required).
        let deadline = Instant::now() + Duration::from_millis(500);
        while let Ok(raw) = self.port.read_line(deadline, "M112") {
            if let Ok(Reply::Error(ErrorLine::Halted)) = decode(&raw) {
                break;
            }
        }
        Ok(())
    }

    /// `M108`: resume a firmware wait (for the user, a heater): Marlin's only "resume".
    pub fn resume(&mut self) -> DeviceResult<()> {
        self.command("M108", self.config.silence_timeout * 2)
    }
}

fn halted_error(command: &str) -> DeviceError {
    DeviceError::new(
        ErrorKind::Other,
        DEVICE,
        command,
        "the firmware is halted (`Error:Printer halted. kill() called!`, after M112 or a fatal fault) and answers nothing",
    )
    .with_hint("reset the board (reset button, power cycle, or re-open the port on boards that reset on DTR), then home it: the position is lost")
}

fn no_emergency_parser(caps: &Capabilities) -> DeviceError {
    DeviceError::new(
        ErrorKind::Other,
        DEVICE,
        "M115",
        format!(
            "the firmware ({}) does not report Cap:EMERGENCY_PARSER:1: its quick stop M410 would wait behind the M400 of a running move, so the bench could not stop a move",
            caps.firmware.as_deref().unwrap_or("unknown")
        ),
    )
    .with_hint("build Marlin with EMERGENCY_PARSER (Configuration_adv.h)")
}

impl<P: Read + Write> Stage for Marlin<P> {
    fn home(&mut self) -> DeviceResult<()> {
        if self.pending.is_some() {
            self.finish_pending(self.config.homing_timeout, "G28")?;
        }
        self.command("G28", self.config.homing_timeout)?;
        self.m114().map(|_| ())
    }

    fn move_to(&mut self, target_mm: StagePositionMm, speed_mm_s: Option<f64>) -> DeviceResult<()> {
        self.start_move(target_mm, speed_mm_s, "move")
    }

    fn move_by(&mut self, delta_mm: StagePositionMm, speed_mm_s: Option<f64>) -> DeviceResult<()> {
        let here = self.settled_position("move by")?;
        let target = [0, 1, 2].map(|i| here[i] + delta_mm[i]);
        self.start_move(target, speed_mm_s, "move by")
    }

    fn position(&mut self) -> DeviceResult<StagePositionMm> {
        self.settled_position("position")
    }

    fn state(&mut self) -> DeviceResult<StageState> {
        if self.halted {
            return Ok(StageState::Alarm);
        }
        let Some(p) = self.pending else {
            return Ok(StageState::Idle);
        };
        // Only look at what arrived: the M400's `ok` means the motion is over.
        let mut resends = 0;
        let deadline = Instant::now() + Duration::from_millis(1);
        while let Some(()) = self.read_one(deadline, "state", &mut resends)? {
            if self.is_acked(p.m400) {
                break;
            }
        }
        if self.is_acked(p.m400) {
            self.pending = None;
            return Ok(StageState::Idle);
        }
        // Silent for too long after the expected end: probe (via a bounded wait).
        let quiet_since = p.sent + p.expected + self.config.silence_timeout;
        if Instant::now() > quiet_since {
            self.finish_pending(self.config.silence_timeout * 2, "state")?;
            return Ok(StageState::Idle);
        }
        Ok(StageState::Moving)
    }

    fn wait_idle(&mut self, timeout: Duration) -> DeviceResult<()> {
        self.wait_reached(timeout, "wait idle")
    }

    fn stop(&mut self) -> DeviceResult<()> {
        let n = self.send("M410")?;
        let overall = Instant::now() + self.config.silence_timeout * 2;
        self.collect(n, overall, "M410")?;
        // The M400 was answered when the planner emptied (before M410's own ok).
        self.pending = None;
        self.m114().map(|_| ())
    }

    fn unlock(&mut self) -> DeviceResult<()> {
        if self.halted {
            return Err(halted_error("M999"));
        }
        self.command("M999", self.config.silence_timeout * 2)
    }

    fn limits(&self) -> TravelLimits {
        let mut axes_mm = self
            .config
            .limits
            .map_or([[f64::NEG_INFINITY, f64::INFINITY]; 3], |l| l.axes_mm);
        if let Some(s) = self.info.soft_endstops.filter(|s| s.enabled) {
            for (i, axis) in axes_mm.iter_mut().enumerate() {
                axis[0] = axis[0].max(s.min_mm[i]);
                axis[1] = axis[1].min(s.max_mm[i]);
            }
        }
        TravelLimits { axes_mm }
    }

    /// One step per axis (`M92`): targets are rounded to whole steps.
    fn resolution_mm(&self) -> [f64; 3] {
        self.info
            .steps_per_mm
            .map_or([0.0; 3], |s| s.map(|v| 1.0 / v))
    }

    /// Marlin has no status query to pace: [`Stage::state`] only looks for the
    /// `M400`'s `ok` among the lines already received.
    fn status_interval(&self) -> Duration {
        STATUS_INTERVAL
    }
}
