//! GRBL 1.1h simulator: a pure state machine serving the GRBL protocol.
//!
//! Modelled (see `protocols/grbl.md` for the full list and the choices made):
//! - line protocol: each line answered by `ok` / `error:N`, lines processed in
//!   order; a line that must wait (dwell `G4`, homing `$H`, a full planner, the
//!   critical-alarm lock) blocks the lines behind it, as in GRBL's main loop;
//! - real-time bytes `?` `!` `~` 0x18 0x85 handled on arrival, anywhere in a line;
//! - motion: straight segments at constant speed (no acceleration), the position
//!   integrating over time, `F` feed or `G0` at the `$110..$112` max rate;
//! - work offsets as GRBL keeps them: `G10 L2 Pn` / `G10 L20 Pn` (G54..G59),
//!   `G54`..`G59` selection, `G92` / `G92.1`; WCO = active system + G92; `$#` lists
//!   them; absolute moves without `G53` are in work coordinates;
//! - status reports `<State|MPos:..|FS:..>` (or `WPos` when `$10` bit 0 is clear,
//!   `Bf:` when bit 1 is set), `WCO:` and `Ov:` with GRBL's refresh counters
//!   (`WCO:` every 10 reports when idle, 30 when busy, and on the next report after
//!   an offset changes; `Ov:` on the report after a `WCO:` one, then every 10/20);
//! - homing per `$22` (error:5 when disabled), ending at MPos = −`$27` pull-off;
//! - soft limits `$20` with `$130..$132` in GRBL's negative space
//!   (−max_travel ≤ MPos ≤ 0): G0/G1 beyond → `ALARM:2` + critical lock,
//!   `$J=` beyond → `error:15`;
//! - alarm state: only `$` commands accepted, G-code → `error:9`, `$J=` →
//!   `error:8`; critical alarms (1, 2) ignore everything, `?` included, but a soft
//!   reset (as the real firmware does, whatever its source comments say);
//! - during homing `?` is answered only when the cycle ends (as GRBL 1.1h);
//! - feed hold (immediate stop → `Hold:0`; no line is read while held), resume,
//!   jog cancel, soft reset (banner; `ALARM:3` if reset in motion;
//!   `[MSG:'$H'|'$X' to unlock]` when in alarm); check mode `$C` (parsed, not
//!   moved; leaving it resets); sleep `$SLP` (only `?` and reset answered; reset →
//!   alarm); `$I` (`[VER:1.1h.20190830:]`);
//! - probing `G38.2` against an optional contact plane `z = probe_contact_z_mm`.
//!
//! Faults from [`FaultConfig`] are applied to replies: see [`GrblSim::apply_fault`].
//!
//! This file holds the machine (state, motion in time, status reports, real-time
//! bytes, faults, serving); `commands` interprets the lines it reads (`$` commands,
//! G-code, jogs, work offsets).

mod commands;

use std::collections::{BTreeMap, VecDeque};
use std::time::Duration;

use super::codec::fmt_num;
use crate::device::fault::{FaultConfig, FaultInjector, FaultKind, ReplyClass};
use crate::device::pty::{Flow, Simulator};

/// The reset banner GRBL prints (preceded by an empty line, as the firmware does).
pub const BANNER: &str = "Grbl 1.1h ['$' for help]";

/// GRBL's serial line buffer: longer lines answer `error:11`.
const LINE_BUFFER_SIZE: usize = 80;

/// Planner blocks (GRBL on an ATmega328p: 16, one kept free).
const PLANNER_BLOCKS: usize = 15;

/// Settings that GRBL prints as integers.
const INTEGER_SETTINGS: [u16; 14] = [0, 1, 2, 3, 4, 5, 6, 10, 20, 21, 22, 23, 26, 30];

/// GRBL 1.1h default settings (`$RST=$`), numbers as printed by `$$`.
fn default_settings() -> BTreeMap<u16, f64> {
    [
        (0, 10.0),
        (1, 25.0),
        (2, 0.0),
        (3, 0.0),
        (4, 0.0),
        (5, 0.0),
        (6, 0.0),
        (10, 1.0),
        (11, 0.010),
        (12, 0.002),
        (13, 0.0),
        (20, 0.0),
        (21, 0.0),
        (22, 0.0),
        (23, 0.0),
        (24, 25.0),
        (25, 500.0),
        (26, 250.0),
        (27, 1.0),
        (30, 1000.0),
        (31, 0.0),
        (32, 0.0),
        (100, 250.0),
        (101, 250.0),
        (102, 250.0),
        (110, 500.0),
        (111, 500.0),
        (112, 500.0),
        (120, 10.0),
        (121, 10.0),
        (122, 10.0),
        (130, 200.0),
        (131, 200.0),
        (132, 200.0),
    ]
    .into_iter()
    .collect()
}

/// Simulator configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct GrblSimConfig {
    /// Setting overrides applied over the GRBL defaults (e.g. `(22, 1.0)` homing on).
    pub settings: Vec<(u16, f64)>,
    /// Start position in machine coordinates, mm.
    pub start_mpos_mm: [f64; 3],
    /// Start in the alarm state (GRBL does at power-up when homing is enabled).
    pub start_in_alarm: bool,
    /// G54 work offset at start, mm (`G10 L2 P1`), as left by another program.
    pub start_g54_mm: [f64; 3],
    /// Height of the contact plane for `G38.2` probing, machine z in mm (`None`:
    /// the probe never touches).
    pub probe_contact_z_mm: Option<f64>,
    /// Send the banner when the simulator starts (as an Arduino GRBL does when the
    /// port is opened and DTR resets it).
    pub banner_on_start: bool,
    /// Opt-in faults.
    pub faults: Option<FaultConfig>,
}

impl Default for GrblSimConfig {
    fn default() -> Self {
        GrblSimConfig {
            settings: Vec::new(),
            start_mpos_mm: [0.0; 3],
            start_in_alarm: false,
            start_g54_mm: [0.0; 3],
            probe_contact_z_mm: None,
            banner_on_start: true,
            faults: None,
        }
    }
}

impl GrblSimConfig {
    /// A typical bench: homing and soft limits on, travel 100 × 100 × 50 mm, homing
    /// seek 3000 mm/min, starting in the alarm state as GRBL does at power-up with
    /// homing enabled.
    pub fn homing_bench() -> Self {
        GrblSimConfig {
            settings: vec![
                (20, 1.0),
                (22, 1.0),
                (25, 3000.0),
                (130, 100.0),
                (131, 100.0),
                (132, 50.0),
            ],
            start_mpos_mm: [-50.0, -50.0, -25.0],
            start_in_alarm: true,
            ..Default::default()
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum SegKind {
    Line,
    Jog,
    Home,
    Probe,
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Segment {
    kind: SegKind,
    target: [f64; 3],
    speed_mm_s: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    Idle,
    Alarm,
    /// Critical alarm: nothing but a reset is answered (not even `?`).
    AlarmLocked,
    /// Check mode (`$C`): G-code parsed, nothing moves.
    Check,
    /// Sleep (`$SLP`): only `?` and reset.
    Sleep,
}

/// Output held back until its release time (late-reply fault). Everything sent
/// after a late reply queues behind it, as when the controller itself is slow, so
/// the order of lines is preserved.
#[derive(Debug, Clone)]
struct Delayed {
    at: Duration,
    bytes: Vec<u8>,
}

/// The GRBL simulator.
#[derive(Debug, Clone)]
pub struct GrblSim {
    settings: BTreeMap<u16, f64>,
    probe_contact_z_mm: Option<f64>,
    mpos: [f64; 3],
    mode: Mode,
    held: bool,
    queue: VecDeque<Segment>,
    last_time: Duration,
    line_buf: Vec<u8>,
    line_overflow: bool,
    lines: VecDeque<String>,
    dwell_until: Option<Duration>,
    feed_mm_min: Option<f64>,
    relative: bool,
    /// GRBL's `report_wco_counter` / `report_ovr_counter`.
    wco_counter: u32,
    ovr_counter: u32,
    /// Coordinate systems G54..G59, mm.
    systems: [[f64; 3]; 6],
    /// Active coordinate system (0 = G54).
    active_system: usize,
    /// G92 offset, mm.
    g92: [f64; 3],
    /// A `?` arrived during homing: answered when the cycle ends.
    report_pending: bool,
    pending_banner: bool,
    delayed: Option<Delayed>,
    faults: Option<FaultInjector>,
    /// After a `DeviceReset` or `Disconnect` fault the current reply is swallowed.
    hangup: bool,
    /// Line counter for diagnostics: lines answered so far.
    answered: u64,
    /// A G0/G1 hit the soft limit: GRBL answers its `ok` only after the reset.
    ok_on_reset: bool,
    /// Motion lines (G0/G1/G38.2/$J=) accepted into the planner.
    motions_accepted: u32,
}

impl GrblSim {
    /// A new simulator.
    pub fn new(config: GrblSimConfig) -> Self {
        let mut settings = default_settings();
        for (k, v) in &config.settings {
            settings.insert(*k, *v);
        }
        GrblSim {
            settings,
            probe_contact_z_mm: config.probe_contact_z_mm,
            mpos: config.start_mpos_mm,
            mode: if config.start_in_alarm {
                Mode::Alarm
            } else {
                Mode::Idle
            },
            held: false,
            queue: VecDeque::new(),
            last_time: Duration::ZERO,
            line_buf: Vec::new(),
            line_overflow: false,
            lines: VecDeque::new(),
            dwell_until: None,
            feed_mm_min: None,
            relative: false,
            wco_counter: 0,
            ovr_counter: 0,
            systems: {
                let mut s = [[0.0; 3]; 6];
                s[0] = config.start_g54_mm;
                s
            },
            active_system: 0,
            g92: [0.0; 3],
            report_pending: false,
            pending_banner: config.banner_on_start,
            delayed: None,
            faults: config.faults.map(FaultInjector::new),
            hangup: false,
            answered: 0,
            ok_on_reset: false,
            motions_accepted: 0,
        }
    }

    /// Machine position now, mm.
    pub fn mpos_mm(&self) -> [f64; 3] {
        self.mpos
    }

    /// True if the controller is in an alarm state.
    pub fn in_alarm(&self) -> bool {
        matches!(self.mode, Mode::Alarm | Mode::AlarmLocked)
    }

    /// True while a feed hold pauses motion.
    pub fn held(&self) -> bool {
        self.held && self.moving()
    }

    /// The work coordinate offset GRBL applies (active system + G92), mm.
    pub fn wco_mm(&self) -> [f64; 3] {
        let c = self.systems[self.active_system];
        [c[0] + self.g92[0], c[1] + self.g92[1], c[2] + self.g92[2]]
    }

    /// Marks the offsets changed: GRBL reports `WCO:` on the next report.
    fn wco_changed(&mut self) {
        self.wco_counter = 0;
    }

    /// Motion lines (G0/G1/G38.2/`$J=`) accepted so far: lets tests check that a
    /// driver never re-sent a move.
    pub fn motions_accepted(&self) -> u32 {
        self.motions_accepted
    }

    /// Faults injected so far.
    pub fn faults_injected(&self) -> u32 {
        self.faults.as_ref().map_or(0, |f| f.injected())
    }

    fn setting(&self, n: u16) -> f64 {
        self.settings.get(&n).copied().unwrap_or(0.0)
    }

    fn homing_enabled(&self) -> bool {
        self.setting(22) != 0.0
    }

    fn moving(&self) -> bool {
        !self.queue.is_empty()
    }

    fn state_text(&self) -> String {
        match self.mode {
            Mode::Alarm | Mode::AlarmLocked => return "Alarm".into(),
            Mode::Check => return "Check".into(),
            Mode::Sleep => return "Sleep".into(),
            Mode::Idle => {}
        }
        match self.queue.front() {
            Some(_) if self.held => "Hold:0".into(),
            Some(s) => match s.kind {
                SegKind::Line | SegKind::Probe => "Run".into(),
                SegKind::Jog => "Jog".into(),
                SegKind::Home => "Home".into(),
            },
            None => "Idle".into(),
        }
    }

    fn status_report(&mut self) -> String {
        let mask = self.setting(10) as u32;
        let wco = self.wco_mm();
        let shown = if mask & 1 == 1 {
            self.mpos
        } else {
            [
                self.mpos[0] - wco[0],
                self.mpos[1] - wco[1],
                self.mpos[2] - wco[2],
            ]
        };
        let pos = shown
            .iter()
            .map(|v| fmt_num(*v))
            .collect::<Vec<_>>()
            .join(",");
        let mut s = format!("<{}|", self.state_text());
        s.push_str(if mask & 1 == 1 { "MPos:" } else { "WPos:" });
        s.push_str(&pos);
        if mask & 2 == 2 {
            s.push_str(&format!(
                "|Bf:{},{}",
                PLANNER_BLOCKS - self.queue.len().min(PLANNER_BLOCKS),
                128
            ));
        }
        let feed = match self.queue.front() {
            Some(seg) if !self.held => seg.speed_mm_s * 60.0,
            _ => 0.0,
        };
        s.push_str(&format!("|FS:{},0", feed.round() as i64));
        // GRBL 1.1h report.c: the WCO counter first (a WCO report schedules Ov for
        // the next one), refreshed every 10 reports when idle, 30 when busy;
        // Ov every 10 / 20.
        let busy = self.moving();
        if self.wco_counter > 0 {
            self.wco_counter -= 1;
        } else {
            self.wco_counter = if busy { 29 } else { 9 };
            if self.ovr_counter == 0 {
                self.ovr_counter = 1;
            }
            let w: Vec<String> = wco.iter().map(|v| fmt_num(*v)).collect();
            s.push_str(&format!("|WCO:{}", w.join(",")));
        }
        if self.ovr_counter > 0 {
            self.ovr_counter -= 1;
        } else {
            self.ovr_counter = if busy { 19 } else { 9 };
            s.push_str("|Ov:100,100,100");
        }
        s.push('>');
        s
    }

    /// Moves the machine along its queued segments up to `now`.
    fn advance(&mut self, now: Duration, out: &mut Vec<u8>) {
        let mut dt = now.saturating_sub(self.last_time).as_secs_f64();
        self.last_time = now;
        if self.held || self.mode != Mode::Idle {
            return;
        }
        // Loop over segments, not `while dt > 0`: zero-length segments finish even
        // when no time has passed.
        while let Some(seg) = self.queue.front().copied() {
            let d = dist(self.mpos, seg.target);
            let t_needed = d / seg.speed_mm_s;
            if seg.kind == SegKind::Probe {
                if let Some(zc) = self.probe_contact_z_mm {
                    // Contact when z crosses the plane on the way to the target.
                    let crosses = (self.mpos[2] - zc) * (seg.target[2] - zc) <= 0.0
                        && self.mpos[2] != seg.target[2];
                    if crosses {
                        let frac_to_contact = (self.mpos[2] - zc) / (self.mpos[2] - seg.target[2]);
                        let t_contact = t_needed * frac_to_contact;
                        if dt >= t_contact {
                            let contact = lerp(self.mpos, seg.target, frac_to_contact);
                            self.mpos = contact;
                            self.queue.pop_front();
                            dt -= t_contact;
                            let p: Vec<String> = contact.iter().map(|v| fmt_num(*v)).collect();
                            push_line(out, &format!("[PRB:{}:1]", p.join(",")));
                            continue;
                        }
                    }
                }
            }
            if dt >= t_needed {
                self.mpos = seg.target;
                self.queue.pop_front();
                dt -= t_needed;
                match seg.kind {
                    SegKind::Home => {
                        let pulloff = self.setting(27);
                        self.mpos = [-pulloff; 3];
                        // The `$H` line is answered when homing completes, and a
                        // `?` asked during the cycle only then.
                        self.reply(out, "ok", ReplyClass::Command, now);
                        if std::mem::take(&mut self.report_pending) {
                            let report = self.status_report();
                            self.reply(out, &report, ReplyClass::Query, now);
                        }
                    }
                    SegKind::Probe => {
                        // Reached the target without contact: ALARM:5, probe fail.
                        self.queue.clear();
                        self.mode = Mode::Alarm;
                        push_line(out, "ALARM:5");
                        dt = 0.0;
                    }
                    _ => {}
                }
            } else {
                self.mpos = lerp(self.mpos, seg.target, dt / t_needed);
                break;
            }
        }
    }

    fn soft_reset(&mut self, out: &mut Vec<u8>) {
        if self.moving() && !self.held && self.mode == Mode::Idle {
            let homing = self.queue.front().is_some_and(|s| s.kind == SegKind::Home);
            push_line(out, if homing { "ALARM:6" } else { "ALARM:3" });
            self.mode = Mode::Alarm;
        }
        if matches!(self.mode, Mode::AlarmLocked | Mode::Sleep) {
            // GRBL re-initialises sleep as alarm (position not guaranteed).
            self.mode = Mode::Alarm;
        }
        if self.mode == Mode::Check {
            self.mode = Mode::Idle;
        }
        self.report_pending = false;
        self.wco_counter = 0;
        self.ovr_counter = 0;
        // A reset re-initialises the parser: G92 cleared, G54 active again.
        if self.g92 != [0.0; 3] || self.active_system != 0 {
            self.g92 = [0.0; 3];
            self.active_system = 0;
        }
        self.queue.clear();
        self.held = false;
        self.lines.clear();
        self.line_buf.clear();
        self.line_overflow = false;
        self.dwell_until = None;
        self.delayed = None;
        if std::mem::take(&mut self.ok_on_reset) {
            push_line(out, "ok");
        }
        self.feed_mm_min = None;
        self.relative = false;
        self.send_banner(out);
    }

    fn send_banner(&mut self, out: &mut Vec<u8>) {
        out.extend_from_slice(b"\r\n");
        push_line(out, BANNER);
        if self.in_alarm() {
            push_line(out, "[MSG:'$H'|'$X' to unlock]");
        }
    }

    fn critical_alarm(&mut self, code: u8, out: &mut Vec<u8>) {
        self.queue.clear();
        self.held = false;
        self.mode = Mode::AlarmLocked;
        push_line(out, &format!("ALARM:{code}"));
        push_line(out, "[MSG:Reset to continue]");
    }

    /// Sends a reply line, through the fault injector.
    fn reply(&mut self, out: &mut Vec<u8>, line: &str, class: ReplyClass, now: Duration) {
        self.answered += 1;
        let fault = self.faults.as_mut().and_then(|f| f.decide(class));
        self.apply_fault(fault, out, line, now);
    }

    /// Applies a fault to one reply line:
    /// - `LateReply`: the line is released `late_by` later;
    /// - `DroppedByte`: one content byte is removed;
    /// - `Garbled`: one content byte is replaced by 0xFE;
    /// - `Unsolicited`: `[MSG:Simulated unsolicited message]` precedes the line;
    /// - `DeviceReset`: the line is swallowed and the controller resets (banner;
    ///   `ALARM:3` if it was moving);
    /// - `LimitTrip`: the line is sent, then `ALARM:1` + `[MSG:Reset to continue]`
    ///   (hard limit: motion killed, critical lock until reset);
    /// - `Disconnect`: the line is swallowed and the port hangs up.
    fn apply_fault(
        &mut self,
        fault: Option<FaultKind>,
        out: &mut Vec<u8>,
        line: &str,
        now: Duration,
    ) {
        let mut bytes = line.as_bytes().to_vec();
        match fault {
            None => push_line(out, line),
            Some(FaultKind::LateReply) => {
                let late_by = self
                    .faults
                    .as_ref()
                    .map_or(Duration::ZERO, |f| f.config().late_by);
                // Output produced earlier in this step goes first, then the held line.
                let mut held = std::mem::take(out);
                held.extend_from_slice(&bytes);
                held.extend_from_slice(b"\r\n");
                match &mut self.delayed {
                    Some(d) => d.bytes.extend_from_slice(&held),
                    None => {
                        self.delayed = Some(Delayed {
                            at: now + late_by,
                            bytes: held,
                        })
                    }
                }
            }
            Some(FaultKind::DroppedByte) => {
                let i = self.faults.as_mut().map_or(0, |f| f.index(bytes.len()));
                if !bytes.is_empty() {
                    bytes.remove(i);
                }
                out.extend_from_slice(&bytes);
                out.extend_from_slice(b"\r\n");
            }
            Some(FaultKind::Garbled) => {
                let i = self.faults.as_mut().map_or(0, |f| f.index(bytes.len()));
                if let Some(b) = bytes.get_mut(i) {
                    *b = 0xFE;
                }
                out.extend_from_slice(&bytes);
                out.extend_from_slice(b"\r\n");
            }
            Some(FaultKind::Unsolicited) => {
                push_line(out, "[MSG:Simulated unsolicited message]");
                push_line(out, line);
            }
            Some(FaultKind::DeviceReset) => self.soft_reset(out),
            Some(FaultKind::LimitTrip) => {
                push_line(out, line);
                self.critical_alarm(1, out);
            }
            Some(FaultKind::Disconnect) => self.hangup = true,
        }
    }

    /// True if the front line must wait (GRBL's main loop is blocked).
    fn blocked(&self, now: Duration) -> bool {
        if matches!(self.mode, Mode::AlarmLocked | Mode::Sleep) {
            return true;
        }
        // A feed hold suspends GRBL's main loop: no line is read until resume.
        if self.held && self.moving() {
            return true;
        }
        if self.queue.front().is_some_and(|s| s.kind == SegKind::Home) {
            return true;
        }
        if let Some(t) = self.dwell_until {
            return !self.queue.is_empty() || now < t;
        }
        self.queue.len() >= PLANNER_BLOCKS
    }

    fn process_lines(&mut self, now: Duration, out: &mut Vec<u8>) {
        loop {
            if self.hangup {
                return;
            }
            if let Some(t) = self.dwell_until {
                if self.queue.is_empty() && now >= t {
                    self.dwell_until = None;
                    self.reply(out, "ok", ReplyClass::Query, now);
                    continue;
                }
            }
            if self.blocked(now) {
                return;
            }
            let Some(line) = self.lines.pop_front() else {
                return;
            };
            self.execute_line(&line, now, out);
        }
    }

    fn realtime(&mut self, b: u8, now: Duration, out: &mut Vec<u8>) {
        match b {
            // A critical alarm ignores `?`; during homing it is answered when the
            // cycle ends (GRBL 1.1h's homing loop does not serve reports).
            b'?' if self.mode == Mode::AlarmLocked => {}
            b'?' if self.queue.front().is_some_and(|s| s.kind == SegKind::Home) => {
                self.report_pending = true;
            }
            b'?' => {
                let report = self.status_report();
                self.reply(out, &report, ReplyClass::Query, now);
            }
            b'!' if self.queue.front().is_some_and(|s| s.kind != SegKind::Home) => {
                self.held = true;
            }
            b'~' => self.held = false,
            0x18 => self.soft_reset(out),
            0x85 if self.queue.front().is_some_and(|s| s.kind == SegKind::Jog) => {
                self.queue.clear();
                self.held = false;
            }
            _ => {}
        }
    }
}

impl Simulator for GrblSim {
    fn step(&mut self, now: Duration, input: &[u8], out: &mut Vec<u8>) -> Flow {
        if self.pending_banner {
            self.pending_banner = false;
            self.send_banner(out);
        }
        self.advance(now, out);
        for &b in input {
            if self.hangup {
                break;
            }
            if b == b'?' || b == b'!' || b == b'~' || b == 0x18 || b >= 0x80 {
                self.realtime(b, now, out);
                continue;
            }
            if b == b'\n' || b == b'\r' {
                let line = String::from_utf8_lossy(&self.line_buf).into_owned();
                self.line_buf.clear();
                if std::mem::take(&mut self.line_overflow) {
                    self.lines.push_back(String::from("\u{1}overflow"));
                } else if !line.trim().is_empty() {
                    self.lines.push_back(line);
                }
                continue;
            }
            if self.line_buf.len() >= LINE_BUFFER_SIZE {
                self.line_overflow = true;
            } else {
                self.line_buf.push(b);
            }
        }
        // Overflowed lines answer error:11 in order.
        if self.lines.front().is_some_and(|l| l == "\u{1}overflow") && !self.blocked(now) {
            self.lines.pop_front();
            self.reply(out, "error:11", ReplyClass::Command, now);
        }
        self.process_lines(now, out);
        // Hold everything behind a late reply until it is due, then release in order.
        if let Some(d) = &mut self.delayed {
            if d.at <= now {
                let mut released = std::mem::take(&mut d.bytes);
                released.append(out);
                *out = released;
                self.delayed = None;
            } else {
                d.bytes.append(out);
            }
        }
        if self.hangup {
            Flow::Hangup
        } else {
            Flow::Continue
        }
    }

    fn next_wake(&self, now: Duration) -> Option<Duration> {
        let mut wake: Option<Duration> = None;
        let mut consider = |t: Duration| {
            let dt = t.saturating_sub(now);
            wake = Some(wake.map_or(dt, |w| w.min(dt)));
        };
        if let Some(d) = &self.delayed {
            consider(d.at);
        }
        if let Some(t) = self.dwell_until {
            consider(t);
        }
        if self.moving() && !self.held {
            // Finish times matter for `ok` of `$H`/`G4`; 2 ms resolution is plenty.
            consider(now + Duration::from_millis(2));
        }
        wake
    }
}

/// A G-word number ×10 as an integer (`38.2` → 382), so codes match exactly.
fn g_code(v: f64) -> i64 {
    (v * 10.0).round() as i64
}

fn push_line(out: &mut Vec<u8>, line: &str) {
    out.extend_from_slice(line.as_bytes());
    out.extend_from_slice(b"\r\n");
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn lerp(a: [f64; 3], b: [f64; 3], t: f64) -> [f64; 3] {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(sim: &mut GrblSim, t_s: f64, input: &str) -> String {
        let mut out = Vec::new();
        sim.step(Duration::from_secs_f64(t_s), input.as_bytes(), &mut out);
        String::from_utf8_lossy(&out).into_owned()
    }

    #[test]
    fn banner_on_start_then_status_report_of_idle_machine() {
        let mut sim = GrblSim::new(GrblSimConfig::default());
        let out = run(&mut sim, 0.0, "?");
        assert!(
            out.starts_with("\r\nGrbl 1.1h ['$' for help]\r\n"),
            "{out:?}"
        );
        assert!(
            out.contains("<Idle|MPos:0.000,0.000,0.000|FS:0,0|WCO:0.000,0.000,0.000>\r\n"),
            "{out:?}"
        );
    }

    #[test]
    fn position_integrates_at_feed_rate_and_ok_means_queued() {
        let mut sim = GrblSim::new(GrblSimConfig {
            banner_on_start: false,
            ..Default::default()
        });
        // 300 mm/min = 5 mm/s along x for 10 mm (below the 500 mm/min $110 cap): 2 s.
        assert_eq!(run(&mut sim, 0.0, "G21 G53 G1 X-10 F300\n"), "ok\r\n");
        let _ = run(&mut sim, 0.5, "");
        assert!(
            (sim.mpos_mm()[0] + 2.5).abs() < 1e-9,
            "2.5 mm after 0.5 s: {:?}",
            sim.mpos_mm()
        );
        assert!(run(&mut sim, 0.5, "?").starts_with("<Run|MPos:-2.500,0.000,0.000|FS:300,0"));
        let _ = run(&mut sim, 2.1, "");
        assert_eq!(sim.mpos_mm(), [-10.0, 0.0, 0.0]);
        assert!(run(&mut sim, 2.1, "?").starts_with("<Idle|"));
        // F above the axis max rate is capped at $110 = 500 mm/min.
        run(&mut sim, 3.0, "G53 G1 X0 F6000\n");
        assert!(run(&mut sim, 3.1, "?").contains("|FS:500,0"));
    }

    #[test]
    fn dwell_zero_answers_only_after_motion_finishes() {
        let mut sim = GrblSim::new(GrblSimConfig {
            banner_on_start: false,
            ..Default::default()
        });
        assert_eq!(run(&mut sim, 0.0, "G53 G1 X-1 F60\nG4 P0\n"), "ok\r\n");
        assert_eq!(run(&mut sim, 0.5, ""), "", "still moving: no ok for G4");
        assert_eq!(run(&mut sim, 1.01, ""), "ok\r\n");
    }

    #[test]
    fn homing_disabled_answers_error_5_and_enabled_homes_to_pulloff() {
        let mut sim = GrblSim::new(GrblSimConfig {
            banner_on_start: false,
            ..Default::default()
        });
        assert_eq!(run(&mut sim, 0.0, "$H\n"), "error:5\r\n");
        let mut sim = GrblSim::new(GrblSimConfig {
            banner_on_start: false,
            ..GrblSimConfig::homing_bench()
        });
        assert!(
            run(&mut sim, 0.0, "G0 X-1\n").contains("error:9"),
            "alarm lock"
        );
        assert_eq!(run(&mut sim, 0.0, "$H\n"), "");
        // GRBL 1.1h serves no report during the homing cycle: the `?` is answered
        // when it ends.
        assert_eq!(run(&mut sim, 0.1, "?"), "");
        // |(-50,-50,-25)| = 75 mm at $25 = 3000 mm/min -> 1.5 s.
        assert_eq!(run(&mut sim, 1.4, ""), "", "still homing");
        let out = run(&mut sim, 1.51, "");
        assert!(
            out.starts_with("ok\r\n<Idle|MPos:-1.000,-1.000,-1.000|"),
            "{out:?}"
        );
        assert_eq!(sim.mpos_mm(), [-1.0; 3], "pull-off $27 = 1 mm");
    }

    #[test]
    fn soft_limit_on_g1_is_a_critical_alarm_and_on_jog_is_error_15() {
        let mut cfg = GrblSimConfig::homing_bench();
        cfg.start_in_alarm = false;
        cfg.banner_on_start = false;
        let mut sim = GrblSim::new(cfg);
        assert_eq!(run(&mut sim, 0.0, "$J=G91 X200 F100\n"), "error:15\r\n");
        let out = run(&mut sim, 0.0, "G53 G1 X5 F100\n");
        assert_eq!(out, "ALARM:2\r\n[MSG:Reset to continue]\r\n");
        assert_eq!(run(&mut sim, 0.0, "$X\n"), "", "locked until reset");
        let out = run(&mut sim, 0.1, "\u{18}");
        assert!(
            out.starts_with("ok\r\n\r\nGrbl 1.1h"),
            "the G1's ok comes after the reset: {out:?}"
        );
        assert!(out.contains("[MSG:'$H'|'$X' to unlock]"), "{out:?}");
        assert_eq!(
            run(&mut sim, 0.2, "$X\n"),
            "[MSG:Caution: Unlocked]\r\nok\r\n"
        );
    }

    #[test]
    fn feed_hold_stops_resume_continues_and_reset_in_motion_alarms_3() {
        let mut sim = GrblSim::new(GrblSimConfig {
            banner_on_start: false,
            ..Default::default()
        });
        run(&mut sim, 0.0, "G53 G1 X-10 F300\n");
        run(&mut sim, 0.2, "!");
        assert!(run(&mut sim, 0.8, "?").starts_with("<Hold:0|MPos:-1.000,"));
        run(&mut sim, 1.0, "~");
        let _ = run(&mut sim, 1.3, "");
        assert!((sim.mpos_mm()[0] + 2.5).abs() < 1e-9, "{:?}", sim.mpos_mm());
        let out = run(&mut sim, 1.3, "\u{18}");
        assert!(out.starts_with("ALARM:3\r\n\r\nGrbl 1.1h"), "{out:?}");
        assert!(sim.in_alarm());
    }

    fn quiet() -> GrblSim {
        GrblSim::new(GrblSimConfig {
            banner_on_start: false,
            ..Default::default()
        })
    }

    #[test]
    fn critical_alarm_ignores_status_queries_until_a_soft_reset() {
        let mut cfg = GrblSimConfig::homing_bench();
        cfg.start_in_alarm = false;
        cfg.banner_on_start = false;
        let mut sim = GrblSim::new(cfg);
        assert_eq!(
            run(&mut sim, 0.0, "G0 X5\n"),
            "ALARM:2\r\n[MSG:Reset to continue]\r\n"
        );
        // As the real firmware: `?` gets nothing, lines get nothing.
        assert_eq!(run(&mut sim, 0.1, "?"), "");
        assert_eq!(run(&mut sim, 0.2, "$G\n?"), "");
        let out = run(&mut sim, 0.3, "\u{18}");
        assert_eq!(
            out, "ok\r\n\r\nGrbl 1.1h ['$' for help]\r\n[MSG:'$H'|'$X' to unlock]\r\n",
            "the lines sent while locked were flushed by the reset"
        );
        assert!(run(&mut sim, 0.4, "?").starts_with("<Alarm|"));
    }

    #[test]
    fn feed_hold_reads_no_line_until_resume() {
        let mut sim = quiet();
        run(&mut sim, 0.0, "G53 G1 X-10 F300\n");
        run(&mut sim, 0.2, "!");
        assert_eq!(run(&mut sim, 0.3, "$G\n"), "", "no line read in a hold");
        assert_eq!(run(&mut sim, 0.4, "$$\n"), "");
        let out = run(&mut sim, 0.5, "~");
        assert!(
            out.starts_with("[GC:G1 G54 G17 G21 G90 G94 M5 M9 T0 F300 S0]\r\nok\r\nerror:8\r\n"),
            "on resume: $G answered, $$ refused while running: {out:?}"
        );
    }

    #[test]
    fn wco_reported_with_grbls_refresh_counters_and_on_change() {
        let mut sim = quiet();
        let reports: Vec<String> = (0..12)
            .map(|i| run(&mut sim, f64::from(i) * 0.01, "?"))
            .collect();
        // As recorded from GRBL 1.1h: WCO on reports 1 and 11, Ov on 2 and 12.
        for (i, r) in reports.iter().enumerate() {
            assert_eq!(r.contains("|WCO:"), i == 0 || i == 10, "report {i}: {r}");
            assert_eq!(r.contains("|Ov:"), i == 1 || i == 11, "report {i}: {r}");
        }
        // An offset change is reported on the next report.
        assert_eq!(run(&mut sim, 0.2, "G10 L2 P1 X-2 Y-3 Z-1\n"), "ok\r\n");
        assert!(run(&mut sim, 0.2, "?").contains("|WCO:-2.000,-3.000,-1.000"));
    }

    #[test]
    fn wpos_mask_g54_and_g92_offsets_and_the_offset_listing() {
        let mut sim = GrblSim::new(GrblSimConfig {
            banner_on_start: false,
            start_mpos_mm: [5.0, 0.0, 0.0],
            start_g54_mm: [-2.0, -3.0, -1.0],
            settings: vec![(10, 0.0)],
            ..Default::default()
        });
        assert_eq!(
            run(&mut sim, 0.0, "?"),
            "<Idle|WPos:7.000,3.000,1.000|FS:0,0|WCO:-2.000,-3.000,-1.000>\r\n"
        );
        assert_eq!(run(&mut sim, 0.0, "G92 X1\n"), "ok\r\n");
        assert_eq!(sim.wco_mm(), [4.0, -3.0, -1.0]);
        let out = run(&mut sim, 0.0, "$#\n");
        assert!(
            out.starts_with("[G54:-2.000,-3.000,-1.000]\r\n[G55:0.000,0.000,0.000]"),
            "{out}"
        );
        assert!(
            out.contains("[G92:6.000,0.000,0.000]\r\n[TLO:0.000]\r\n"),
            "{out}"
        );
        assert!(out.ends_with("ok\r\n"));
        // Absolute moves without G53 are in work coordinates.
        run(&mut sim, 0.0, "G92.1\nG0 X0 Y0 Z0\n");
        let _ = run(&mut sim, 5.0, "");
        assert_eq!(sim.mpos_mm(), [-2.0, -3.0, -1.0]);
        assert_eq!(
            run(&mut sim, 5.0, "$I\n"),
            "[VER:1.1h.20190830:]\r\n[OPT:V,15,128]\r\nok\r\n"
        );
    }

    #[test]
    fn homing_off_accepts_any_coordinate_and_sleep_resets_into_alarm() {
        let mut sim = quiet();
        assert_eq!(run(&mut sim, 0.0, "G53 G0 X5\n"), "ok\r\n");
        let _ = run(&mut sim, 2.0, "");
        assert_eq!(sim.mpos_mm(), [5.0, 0.0, 0.0]);
        assert_eq!(run(&mut sim, 2.0, "$SLP\n"), "ok\r\n[MSG:Sleeping]\r\n");
        assert!(run(&mut sim, 2.1, "?").starts_with("<Sleep|"));
        assert_eq!(run(&mut sim, 2.1, "$G\n"), "");
        assert!(run(&mut sim, 2.2, "\u{18}").ends_with("[MSG:'$H'|'$X' to unlock]\r\n"));
        assert!(sim.in_alarm());
    }

    #[test]
    fn check_mode_parses_without_moving_and_leaving_it_resets() {
        let mut sim = quiet();
        assert_eq!(run(&mut sim, 0.0, "$C\n"), "[MSG:Enabled]\r\nok\r\n");
        assert_eq!(run(&mut sim, 0.0, "G53 G0 X-10\n"), "ok\r\n");
        assert!(run(&mut sim, 1.0, "?").starts_with("<Check|MPos:0.000,0.000,0.000|"));
        assert_eq!(run(&mut sim, 1.0, "$#\n"), "error:8\r\n");
        let out = run(&mut sim, 1.0, "$C\n");
        assert!(
            out.starts_with("[MSG:Disabled]\r\nok\r\n\r\nGrbl 1.1h"),
            "{out:?}"
        );
        assert!(run(&mut sim, 1.1, "?").starts_with("<Idle|"));
    }

    #[test]
    fn probe_stops_at_contact_and_reports_prb() {
        let mut sim = GrblSim::new(GrblSimConfig {
            banner_on_start: false,
            probe_contact_z_mm: Some(-2.0),
            ..Default::default()
        });
        assert_eq!(run(&mut sim, 0.0, "G53 G38.2 Z-5 F60\n"), "error:30\r\n");
        assert_eq!(run(&mut sim, 0.0, "G91 G38.2 Z-5 F60\n"), "ok\r\n");
        let out = run(&mut sim, 3.0, "");
        assert_eq!(out, "[PRB:0.000,0.000,-2.000:1]\r\n");
        assert_eq!(sim.mpos_mm(), [0.0, 0.0, -2.0]);
    }
}
