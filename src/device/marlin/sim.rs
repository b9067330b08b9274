//! Marlin simulator: a cartesian printer/CNC as a pure state machine, written from
//! Marlin's `gcode/queue.cpp` (line numbers, checksums, `Resend:`), `gcode/gcode.cpp`
//! and the handlers of the commands the driver uses (see `protocols/marlin.md`).
//!
//! Modelled:
//! - boot: after `boot_delay` the board prints `start` and a few `echo:` lines;
//!   input before that is lost (the bootloader does not listen);
//! - the serial reader: lines are read only while no command blocks (as Marlin's main
//!   loop reads serial only between commands); a numbered line with a wrong checksum
//!   or number gets `Error:<reason>, Last Line: <n>`, `Resend: <n+1>`, `ok`, and the
//!   rest of what was received is discarded (Marlin flushes its receive buffer);
//! - the emergency parser (on by default): `M410` and `M112` act the moment they
//!   arrive, even while `M400` or `G28` blocks; the line is still queued and answered;
//! - motion: `G0`/`G1` are planned (`ok` at once) and executed one after the other
//!   with trapezoidal speed profiles (acceleration `accel_mm_s2`, feed limited per
//!   axis by `max_feed_mm_s`, `G0` without `F` at the axes' maxima); targets outside
//!   the soft endstops are clamped silently, as Marlin does; positions are whole steps;
//! - `M400` blocks until the planner is empty, `G28` homes (z to its maximum, then
//!   x and y to 0) and blocks; while blocked the board prints `echo:busy: processing`
//!   every `keepalive`; `NO_MOTION_BEFORE_HOMING`: a move before homing answers
//!   `echo:Home XYZ first` and `ok` and does not move;
//! - `M114` (planned position + `Count` in steps), `M115` (firmware + `Cap:` lines),
//!   `M92`, `M203`, `M211 [S0|S1]`, `M110 N`, `G21`, `G90`, `G91`, `M999`, `M108`;
//!   `M410` quick stop (the position where the steppers stopped becomes the planned
//!   position); `M112` kill: `Error:Printer halted. kill() called!`, then nothing
//!   until the simulator is restarted (a real board needs a reset);
//! - unknown commands: `echo:Unknown command: "<cmd>"` and `ok`.
//!
//! Faults ([`FaultConfig`], opt-in, seeded) hit the reply to one received line:
//! `DroppedByte`: the `ok` is lost (a line-level drop: Marlin's `ok` is all-or-nothing
//! for the driver); `Garbled`: one byte of the first reply line is replaced by 0xFF;
//! `LateReply`: the reply comes `late_by` later; `Unsolicited`: an `echo:busy:` line
//! first; `DeviceReset`: the board reboots instead of answering (banner, position and
//! homing lost); `Disconnect`: the pseudo-terminal hangs up; `LimitTrip`: the reply
//! is followed by `echo:endstops hit: Z:<z>`. [`MarlinSimConfig::checksum_faults`]
//! separately corrupts received lines, so the firmware answers with a checksum error
//! and `Resend:`.

use std::collections::VecDeque;
use std::time::Duration;

use super::codec::checksum;
use crate::device::fault::{FaultConfig, FaultInjector, FaultKind, ReplyClass};
use crate::device::pty::{Flow, Simulator};

/// How the board behaves when it starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Boot {
    /// Prints `start` and its banner after [`MarlinSimConfig::boot_delay`].
    Banner,
    /// Never prints anything and never answers (a dead board, an empty port).
    Silent,
    /// Prints noise, as at a wrong baud rate, and never answers.
    Noise,
}

/// Simulator configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct MarlinSimConfig {
    /// Steps per mm X, Y, Z (`M92`).
    pub steps_per_mm: [f64; 3],
    /// Maximum feed rates X, Y, Z, mm/s (`M203`).
    pub max_feed_mm_s: [f64; 3],
    /// Acceleration, mm/s².
    pub accel_mm_s2: f64,
    /// Soft endstops, mm.
    pub soft_min_mm: [f64; 3],
    /// Soft endstops, mm.
    pub soft_max_mm: [f64; 3],
    /// Soft endstops on at boot.
    pub soft_endstops: bool,
    /// Where homing leaves the machine, mm.
    pub home_mm: [f64; 3],
    /// Homing speed, mm/s.
    pub homing_speed_mm_s: f64,
    /// Position at boot, mm.
    pub start_mm: [f64; 3],
    /// Homed at boot (a simulated bench may start homed).
    pub homed: bool,
    /// `NO_MOTION_BEFORE_HOMING`.
    pub require_homing: bool,
    /// `EMERGENCY_PARSER`.
    pub emergency_parser: bool,
    /// What happens at boot.
    pub boot: Boot,
    /// Time from start to the banner.
    pub boot_delay: Duration,
    /// Busy keep-alive interval (`DEFAULT_KEEPALIVE_INTERVAL`: 2 s).
    pub keepalive: Duration,
    /// Opt-in reply faults.
    pub faults: Option<FaultConfig>,
    /// Opt-in corruption of received numbered lines (a checksum mismatch).
    pub checksum_faults: Option<FaultConfig>,
}

impl Default for MarlinSimConfig {
    /// A CR-10-like machine: 80/80/400 steps/mm, 300/300/10 mm/s, 500 mm/s², travel
    /// 0..300 × 0..300 × 0..100 mm, z homing to its top; starts homed at home.
    fn default() -> Self {
        MarlinSimConfig {
            steps_per_mm: [80.0, 80.0, 400.0],
            max_feed_mm_s: [300.0, 300.0, 10.0],
            accel_mm_s2: 500.0,
            soft_min_mm: [0.0; 3],
            soft_max_mm: [300.0, 300.0, 100.0],
            soft_endstops: true,
            home_mm: [0.0, 0.0, 100.0],
            homing_speed_mm_s: 50.0,
            start_mm: [0.0, 0.0, 100.0],
            homed: true,
            require_homing: true,
            emergency_parser: true,
            boot: Boot::Banner,
            boot_delay: Duration::from_millis(50),
            keepalive: Duration::from_secs(2),
            faults: None,
            checksum_faults: None,
        }
    }
}

/// One planned straight move with a trapezoidal profile.
#[derive(Debug, Clone, Copy)]
struct Segment {
    from: [f64; 3],
    to: [f64; 3],
    /// Cruise speed along the path, mm/s.
    v: f64,
    /// Acceleration along the path, mm/s².
    a: f64,
    /// When it started (set when it becomes the current segment).
    t0: Option<Duration>,
}

impl Segment {
    fn length(&self) -> f64 {
        (0..3)
            .map(|i| (self.to[i] - self.from[i]).powi(2))
            .sum::<f64>()
            .sqrt()
    }

    /// Duration of the profile.
    fn duration(&self) -> f64 {
        let d = self.length();
        if d == 0.0 {
            return 0.0;
        }
        let (v, a) = (self.v, self.a);
        if v * v / a >= d {
            2.0 * (d / a).sqrt()
        } else {
            d / v + v / a
        }
    }

    /// Distance along the path after `t` seconds.
    fn distance_at(&self, t: f64) -> f64 {
        let d = self.length();
        let total = self.duration();
        if t >= total {
            return d;
        }
        let (v, a) = (self.v, self.a);
        let vp = (a * d).sqrt().min(v);
        let ta = vp / a;
        if t < ta {
            0.5 * a * t * t
        } else if t < total - ta {
            0.5 * a * ta * ta + vp * (t - ta)
        } else {
            let r = total - t;
            d - 0.5 * a * r * r
        }
    }

    fn point_at(&self, t: f64) -> [f64; 3] {
        let d = self.length();
        if d == 0.0 {
            return self.to;
        }
        let s = self.distance_at(t) / d;
        [0, 1, 2].map(|i| self.from[i] + (self.to[i] - self.from[i]) * s)
    }
}

/// What blocks the command queue.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Block {
    /// `M400`: until the planner is empty; then `ok` for this line.
    M400,
    /// `G28`: until the homing moves are done; then homed and `ok`.
    Homing,
}

/// The Marlin simulator.
#[derive(Debug, Clone)]
pub struct MarlinSim {
    cfg: MarlinSimConfig,
    booted: bool,
    killed: bool,
    stopped: bool,
    /// Raw received lines not yet read by the "main loop".
    rx: VecDeque<Vec<u8>>,
    partial: Vec<u8>,
    last_n: i64,
    relative: bool,
    homed: bool,
    soft: bool,
    /// Step-exact position where the planner ends (Marlin's `current_position`).
    planned: [f64; 3],
    /// Position of the head now.
    pos: [f64; 3],
    planner: VecDeque<Segment>,
    block: Option<Block>,
    last_keepalive: Duration,
    now: Duration,
    faults: Option<FaultInjector>,
    checksum_faults: Option<FaultInjector>,
    delayed: Vec<(Duration, Vec<u8>)>,
    hangup: bool,
    moves_accepted: u32,
    lines_executed: u32,
}

impl MarlinSim {
    /// A new simulator.
    pub fn new(cfg: MarlinSimConfig) -> Self {
        let start = cfg.start_mm;
        MarlinSim {
            booted: false,
            killed: false,
            stopped: false,
            rx: VecDeque::new(),
            partial: Vec::new(),
            last_n: 0,
            relative: false,
            homed: cfg.homed,
            soft: cfg.soft_endstops,
            planned: start,
            pos: start,
            planner: VecDeque::new(),
            block: None,
            last_keepalive: Duration::ZERO,
            now: Duration::ZERO,
            faults: cfg.faults.clone().map(FaultInjector::new),
            checksum_faults: cfg.checksum_faults.clone().map(FaultInjector::new),
            delayed: Vec::new(),
            hangup: false,
            moves_accepted: 0,
            lines_executed: 0,
            cfg,
        }
    }

    /// Where the head is now, mm.
    pub fn position_mm(&self) -> [f64; 3] {
        self.pos
    }

    /// Whether the machine is homed.
    pub fn homed(&self) -> bool {
        self.homed
    }

    /// Whether `M112` killed the firmware.
    pub fn killed(&self) -> bool {
        self.killed
    }

    /// Moves (`G0`/`G1`) and homing cycles executed so far (to check nothing ran twice).
    pub fn moves_accepted(&self) -> u32 {
        self.moves_accepted
    }

    /// Faults injected so far (reply and checksum faults).
    pub fn faults_injected(&self) -> u32 {
        self.faults.as_ref().map_or(0, |f| f.injected())
            + self.checksum_faults.as_ref().map_or(0, |f| f.injected())
    }

    fn steps(&self, mm: [f64; 3]) -> [i64; 3] {
        [0, 1, 2].map(|i| (mm[i] * self.cfg.steps_per_mm[i]).round() as i64)
    }

    fn snap(&self, mm: [f64; 3]) -> [f64; 3] {
        let s = self.steps(mm);
        [0, 1, 2].map(|i| s[i] as f64 / self.cfg.steps_per_mm[i])
    }

    /// Advances the motion to `now`.
    fn advance(&mut self, now: Duration) {
        self.now = now;
        while let Some(seg) = self.planner.front_mut() {
            let t0 = *seg.t0.get_or_insert(now);
            let t = now.saturating_sub(t0).as_secs_f64();
            if t >= seg.duration() {
                let end = seg.to;
                let dur = seg.duration();
                self.pos = end;
                self.planner.pop_front();
                // The next segment starts where this one ended in time.
                if let Some(next) = self.planner.front_mut() {
                    next.t0 = Some(t0 + Duration::from_secs_f64(dur));
                }
            } else {
                self.pos = seg.point_at(t);
                break;
            }
        }
    }

    fn boot_banner(&mut self, out: &mut Vec<u8>) {
        out.extend_from_slice(
            b"start\necho:Marlin 2.1.2.1 (tactbench simulator)\necho: Last Updated: 2023-07-11 | Author: (tactbench)\necho:Compiled: Jul 11 2023\necho: Free Memory: 3090  PlannerBufferBytes: 1488\n",
        );
    }

    fn reset(&mut self) {
        self.last_n = 0;
        self.relative = false;
        self.homed = false;
        self.soft = self.cfg.soft_endstops;
        self.planner.clear();
        self.planned = self.snap(self.pos);
        self.pos = self.planned;
        self.block = None;
        self.rx.clear();
        self.stopped = false;
    }

    /// Quick stop: the planner is emptied and the position where the steppers
    /// stopped becomes the planned position.
    fn quickstop(&mut self) {
        self.planner.clear();
        self.pos = self.snap(self.pos);
        self.planned = self.pos;
        if self.block == Some(Block::Homing) {
            // An interrupted homing leaves the machine unhomed.
            self.homed = false;
        }
    }

    fn plan(&mut self, to: [f64; 3], feed_mm_s: Option<f64>) {
        let from = self.planned;
        let d: Vec<f64> = (0..3).map(|i| to[i] - from[i]).collect();
        let len = d.iter().map(|x| x * x).sum::<f64>().sqrt();
        if len == 0.0 {
            return;
        }
        // Per-axis limit: the path speed at which no axis exceeds its maximum.
        let mut vmax = f64::INFINITY;
        for (di, max) in d.iter().zip(self.cfg.max_feed_mm_s) {
            if *di != 0.0 {
                vmax = vmax.min(max * len / di.abs());
            }
        }
        let v = feed_mm_s.map_or(vmax, |f| f.min(vmax));
        self.planner.push_back(Segment {
            from,
            to,
            v,
            a: self.cfg.accel_mm_s2,
            t0: None,
        });
        self.planned = to;
    }

    fn reply(&mut self, class: ReplyClass, mut lines: Vec<u8>, out: &mut Vec<u8>) -> Flow {
        let fault = self.faults.as_mut().and_then(|f| f.decide(class));
        match fault {
            None => out.extend_from_slice(&lines),
            Some(FaultKind::DroppedByte) => {
                // The `ok` line is lost.
                if let Some(i) = find_ok(&lines) {
                    let end = lines[i..]
                        .iter()
                        .position(|&b| b == b'\n')
                        .map_or(lines.len(), |e| i + e + 1);
                    lines.drain(i..end);
                }
                out.extend_from_slice(&lines);
            }
            Some(FaultKind::Garbled) => {
                if !lines.is_empty() {
                    lines[0] = 0xFF;
                }
                out.extend_from_slice(&lines);
            }
            Some(FaultKind::LateReply) => {
                let late = self
                    .faults
                    .as_ref()
                    .map_or(Duration::from_millis(1500), |f| f.config().late_by);
                self.delayed.push((self.now + late, lines));
            }
            Some(FaultKind::Unsolicited) => {
                out.extend_from_slice(b"echo:busy: processing\n");
                out.extend_from_slice(&lines);
            }
            Some(FaultKind::DeviceReset) => {
                self.reset();
                self.boot_banner(out);
            }
            Some(FaultKind::Disconnect) => {
                self.hangup = true;
                return Flow::Hangup;
            }
            Some(FaultKind::LimitTrip) => {
                out.extend_from_slice(&lines);
                out.extend_from_slice(
                    format!("echo:endstops hit: Z:{:.2}\n", self.pos[2]).as_bytes(),
                );
            }
        }
        Flow::Continue
    }

    /// Reads (validates) received lines and executes them while nothing blocks.
    fn run_queue(&mut self, out: &mut Vec<u8>) -> Flow {
        while self.block.is_none() && !self.killed {
            let Some(raw) = self.rx.pop_front() else {
                break;
            };
            let Ok(text) = String::from_utf8(raw) else {
                continue;
            };
            let mut line = text.trim().to_string();
            if line.is_empty() {
                continue;
            }
            if let Some(rest) = line.strip_prefix('N') {
                let num_end = rest
                    .find(|c: char| !c.is_ascii_digit() && c != '-')
                    .unwrap_or(rest.len());
                let n: i64 = rest[..num_end].parse().unwrap_or(-1);
                let is_m110 = line.contains("M110");
                if n != self.last_n + 1 && !is_m110 {
                    let e = format!(
                        "Error:Line Number is not Last Line Number+1, Last Line: {}\nResend: {}\nok\n",
                        self.last_n,
                        self.last_n + 1
                    );
                    out.extend_from_slice(e.as_bytes());
                    self.rx.clear();
                    continue;
                }
                let Some((body, cs)) = line.rsplit_once('*') else {
                    let e = format!(
                        "Error:No Checksum with line number, Last Line: {}\nResend: {}\nok\n",
                        self.last_n,
                        self.last_n + 1
                    );
                    out.extend_from_slice(e.as_bytes());
                    self.rx.clear();
                    continue;
                };
                let corrupt = self
                    .checksum_faults
                    .as_mut()
                    .and_then(|f| f.decide(ReplyClass::Command))
                    .is_some();
                if corrupt
                    || cs.trim().parse::<u32>().ok() != Some(u32::from(checksum(body.as_bytes())))
                {
                    let e = format!(
                        "Error:checksum mismatch, Last Line: {}\nResend: {}\nok\n",
                        self.last_n,
                        self.last_n + 1
                    );
                    out.extend_from_slice(e.as_bytes());
                    self.rx.clear();
                    continue;
                }
                self.last_n = n;
                // Strip `N<n> ` and `*<cs>`.
                line = body[1 + num_end..].trim().to_string();
                if is_m110 {
                    // `M110 N<k>` sets the counter from its own N (queue.cpp / M110.cpp).
                    if let Some(k) = line
                        .split_whitespace()
                        .find_map(|w| w.strip_prefix('N').and_then(|v| v.parse::<i64>().ok()))
                    {
                        self.last_n = k;
                    }
                }
            }
            if let Flow::Hangup = self.execute(&line, out) {
                return Flow::Hangup;
            }
        }
        Flow::Continue
    }

    fn execute(&mut self, line: &str, out: &mut Vec<u8>) -> Flow {
        self.lines_executed += 1;
        let mut words = line.split_whitespace();
        let code = words.next().unwrap_or("").to_ascii_uppercase();
        let args: Vec<&str> = words.collect();
        let arg = |letter: char| -> Option<f64> {
            args.iter()
                .find_map(|w| w.strip_prefix(letter).and_then(|v| v.parse::<f64>().ok()))
        };
        let ok = b"ok\n".to_vec();
        match code.as_str() {
            "G0" | "G1" | "G00" | "G01" => {
                if self.cfg.require_homing && !self.homed {
                    return self.reply(
                        ReplyClass::Command,
                        b"echo:Home XYZ first\nok\n".to_vec(),
                        out,
                    );
                }
                let mut to = self.planned;
                for (i, l) in ['X', 'Y', 'Z'].into_iter().enumerate() {
                    if let Some(v) = arg(l) {
                        to[i] = if self.relative { to[i] + v } else { v };
                    }
                }
                if self.soft {
                    for (i, t) in to.iter_mut().enumerate() {
                        *t = t.clamp(self.cfg.soft_min_mm[i], self.cfg.soft_max_mm[i]);
                    }
                }
                let to = self.snap(to);
                let feed = arg('F').map(|f| f / 60.0);
                self.plan(to, feed);
                self.moves_accepted += 1;
                self.reply(ReplyClass::Command, ok, out)
            }
            "G28" => {
                self.moves_accepted += 1;
                let home = self.cfg.home_mm;
                let v = Some(self.cfg.homing_speed_mm_s);
                let here = self.planned;
                // z first (up, away from the work), then x and y.
                self.plan([here[0], here[1], home[2]], v);
                self.plan(home, v);
                self.block = Some(Block::Homing);
                self.last_keepalive = self.now;
                Flow::Continue
            }
            "M400" => {
                self.block = Some(Block::M400);
                self.last_keepalive = self.now;
                Flow::Continue
            }
            "M410" => {
                self.quickstop();
                self.reply(ReplyClass::Command, ok, out)
            }
            "M112" => {
                self.kill(out);
                Flow::Continue
            }
            "M114" => {
                let p = self.planned;
                let c = self.steps(p);
                let r = format!(
                    "X:{:.2} Y:{:.2} Z:{:.2} E:0.00 Count X:{} Y:{} Z:{}\nok\n",
                    p[0], p[1], p[2], c[0], c[1], c[2]
                );
                self.reply(ReplyClass::Query, r.into_bytes(), out)
            }
            "M115" => {
                let r = format!(
                    "FIRMWARE_NAME:Marlin 2.1.2.1 (tactbench simulator) SOURCE_CODE_URL:github.com/MarlinFirmware/Marlin PROTOCOL_VERSION:1.0 MACHINE_TYPE:tactbench-sim EXTRUDER_COUNT:0 UUID:cede2a2f-41a2-4748-9b12-c55c62f367ff\nCap:SERIAL_XON_XOFF:0\nCap:EEPROM:0\nCap:AUTOREPORT_POS:0\nCap:EMERGENCY_PARSER:{}\nCap:SOFTWARE_POWER:0\nok\n",
                    u8::from(self.cfg.emergency_parser)
                );
                self.reply(ReplyClass::Query, r.into_bytes(), out)
            }
            "M92" => {
                let s = self.cfg.steps_per_mm;
                let r = format!(
                    "echo:; Steps per unit:\necho:  M92 X{:.2} Y{:.2} Z{:.2} E500.00\nok\n",
                    s[0], s[1], s[2]
                );
                self.reply(ReplyClass::Query, r.into_bytes(), out)
            }
            "M203" => {
                let s = self.cfg.max_feed_mm_s;
                let r = format!(
                    "echo:; Maximum feedrates (units/s):\necho:  M203 X{:.2} Y{:.2} Z{:.2} E25.00\nok\n",
                    s[0], s[1], s[2]
                );
                self.reply(ReplyClass::Query, r.into_bytes(), out)
            }
            "M211" => {
                if let Some(s) = arg('S') {
                    self.soft = s != 0.0;
                    return self.reply(ReplyClass::Command, ok, out);
                }
                let (a, b) = (self.cfg.soft_min_mm, self.cfg.soft_max_mm);
                let r = format!(
                    "echo:; Soft Endstops:\necho:  M211 S{} ; {}\necho:  Min:  X{:.2} Y{:.2} Z{:.2}   Max:  X{:.2} Y{:.2} Z{:.2}\nok\n",
                    u8::from(self.soft),
                    if self.soft { "ON" } else { "OFF" },
                    a[0], a[1], a[2], b[0], b[1], b[2]
                );
                self.reply(ReplyClass::Query, r.into_bytes(), out)
            }
            "G21" | "M110" | "M108" => self.reply(ReplyClass::Command, ok, out),
            "G90" => {
                self.relative = false;
                self.reply(ReplyClass::Command, ok, out)
            }
            "G91" => {
                self.relative = true;
                self.reply(ReplyClass::Command, ok, out)
            }
            "M999" => {
                self.stopped = false;
                self.reply(ReplyClass::Command, ok, out)
            }
            _ => {
                let r = format!("echo:Unknown command: \"{line}\"\nok\n");
                self.reply(ReplyClass::Command, r.into_bytes(), out)
            }
        }
    }

    fn kill(&mut self, out: &mut Vec<u8>) {
        self.quickstop();
        self.killed = true;
        self.rx.clear();
        out.extend_from_slice(b"Error:Printer halted. kill() called!\n");
    }
}

fn find_ok(bytes: &[u8]) -> Option<usize> {
    let mut start = 0;
    for (i, &b) in bytes.iter().enumerate() {
        if b == b'\n' {
            if &bytes[start..i] == b"ok" || bytes[start..i].starts_with(b"ok ") {
                return Some(start);
            }
            start = i + 1;
        }
    }
    None
}

impl Simulator for MarlinSim {
    fn step(&mut self, now: Duration, input: &[u8], out: &mut Vec<u8>) -> Flow {
        if self.hangup {
            return Flow::Hangup;
        }
        self.advance(now);
        if !self.booted {
            if now < self.cfg.boot_delay {
                // The bootloader does not listen.
                return Flow::Continue;
            }
            match self.cfg.boot {
                Boot::Banner => {
                    self.booted = true;
                    self.boot_banner(out);
                }
                Boot::Silent => return Flow::Continue,
                Boot::Noise => {
                    if !input.is_empty() || now.as_millis() % 500 < 25 {
                        out.extend_from_slice(b"\xfe\x80\x1f\xe0x\x00\xff\r\n");
                    }
                    return Flow::Continue;
                }
            }
        }
        // Delayed replies that are due.
        let mut i = 0;
        while i < self.delayed.len() {
            if self.delayed[i].0 <= now {
                let (_, bytes) = self.delayed.remove(i);
                out.extend_from_slice(&bytes);
            } else {
                i += 1;
            }
        }
        if self.killed {
            return Flow::Continue;
        }
        for &b in input {
            if b == b'\n' || b == b'\r' {
                let line = std::mem::take(&mut self.partial);
                if line.is_empty() {
                    continue;
                }
                // The emergency parser sees every line as it arrives.
                if self.cfg.emergency_parser {
                    let t = String::from_utf8_lossy(&line);
                    let body = strip_number(&t);
                    if body.starts_with("M112") {
                        self.kill(out);
                        return Flow::Continue;
                    }
                    if body.starts_with("M410") {
                        self.quickstop();
                    }
                }
                self.rx.push_back(line);
            } else if self.partial.len() < 4096 {
                self.partial.push(b);
            }
        }
        // Blocking commands finish when the planner is empty.
        if let Some(block) = self.block {
            if self.planner.is_empty() {
                self.block = None;
                if block == Block::Homing && !self.killed {
                    self.homed = true;
                    self.planned = self.snap(self.cfg.home_mm);
                    self.pos = self.planned;
                }
                if let Flow::Hangup = self.reply(ReplyClass::Command, b"ok\n".to_vec(), out) {
                    return Flow::Hangup;
                }
            } else if now.saturating_sub(self.last_keepalive) >= self.cfg.keepalive {
                self.last_keepalive = now;
                out.extend_from_slice(b"echo:busy: processing\n");
            }
        }
        self.run_queue(out)
    }

    fn next_wake(&self, now: Duration) -> Option<Duration> {
        let mut wake: Option<Duration> = None;
        let mut consider = |d: Duration| {
            wake = Some(wake.map_or(d, |w| w.min(d)));
        };
        if !self.booted {
            consider(self.cfg.boot_delay.saturating_sub(now));
        }
        for (t, _) in &self.delayed {
            consider(t.saturating_sub(now));
        }
        if !self.planner.is_empty() || self.block.is_some() {
            consider(Duration::from_millis(1));
        }
        wake
    }
}

/// The command of a line without its `N<n> ` prefix.
fn strip_number(line: &str) -> &str {
    let t = line.trim_start();
    match t.strip_prefix('N') {
        Some(rest) => rest
            .trim_start_matches(|c: char| c.is_ascii_digit() || c == '-')
            .trim_start(),
        None => t,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::marlin::codec::frame;

    fn send(sim: &mut MarlinSim, t: Duration, line: &str) -> String {
        let mut out = Vec::new();
        sim.step(t, format!("{line}\n").as_bytes(), &mut out);
        String::from_utf8_lossy(&out).into_owned()
    }

    fn booted() -> MarlinSim {
        let mut s = MarlinSim::new(MarlinSimConfig::default());
        let mut out = Vec::new();
        s.step(Duration::from_millis(100), b"", &mut out);
        assert!(String::from_utf8_lossy(&out).starts_with("start\n"));
        s
    }

    #[test]
    fn checksum_and_line_number_errors_ask_for_a_resend() {
        let mut s = booted();
        let t = Duration::from_millis(200);
        assert_eq!(send(&mut s, t, "N0 M110 N0*125"), "ok\n");
        let bad = frame(1, "M114").replace("*", "*1");
        assert_eq!(
            send(&mut s, t, &bad),
            "Error:checksum mismatch, Last Line: 0\nResend: 1\nok\n"
        );
        assert_eq!(
            send(&mut s, t, &frame(2, "M114")),
            "Error:Line Number is not Last Line Number+1, Last Line: 0\nResend: 1\nok\n"
        );
        let r = send(&mut s, t, &frame(1, "M114"));
        assert!(
            r.starts_with("X:0.00 Y:0.00 Z:100.00 E:0.00 Count X:0 Y:0 Z:40000\nok"),
            "{r}"
        );
        // A copy of a line already taken is refused by number.
        assert_eq!(
            send(&mut s, t, &frame(1, "M114")),
            "Error:Line Number is not Last Line Number+1, Last Line: 1\nResend: 2\nok\n"
        );
    }

    #[test]
    fn m400_blocks_until_the_move_ends_with_keepalives_and_m410_stops_at_once() {
        let mut s = booted();
        let ms = Duration::from_millis;
        send(&mut s, ms(200), "N0 M110 N0*125");
        // 10 mm in z at 5 mm/s: about 2.01 s with 500 mm/s².
        assert_eq!(
            send(&mut s, ms(200), &frame(1, "G1 X0 Y0 Z90 F300")),
            "ok\n"
        );
        assert_eq!(send(&mut s, ms(200), &frame(2, "M400")), "");
        let mut out = Vec::new();
        s.step(ms(1300), b"", &mut out);
        assert_eq!(out, b"");
        let z = s.position_mm()[2];
        assert!(z < 96.0 && z > 93.0, "{z}");
        // M410 acts on arrival although M400 blocks; M400 and M410 are then answered.
        let r = send(&mut s, ms(1300), &frame(3, "M410"));
        assert_eq!(r, "ok\nok\n");
        let r = send(&mut s, ms(1400), &frame(4, "M114"));
        let steps = (z * 400.0).round() as i64;
        assert!(
            r.contains(&format!("Count X:0 Y:0 Z:{steps}")),
            "{r} vs {steps}"
        );
        // Keep-alives while blocked.
        send(&mut s, ms(1400), &frame(5, "G1 Z0 F60"));
        send(&mut s, ms(1400), &frame(6, "M400"));
        let mut out = Vec::new();
        s.step(ms(3500), b"", &mut out);
        assert_eq!(String::from_utf8_lossy(&out), "echo:busy: processing\n");
    }

    #[test]
    fn soft_endstops_clamp_silently_and_homing_is_required() {
        let mut s = MarlinSim::new(MarlinSimConfig {
            homed: false,
            ..MarlinSimConfig::default()
        });
        let ms = Duration::from_millis;
        let mut out = Vec::new();
        s.step(ms(100), b"", &mut out);
        send(&mut s, ms(200), "N0 M110 N0*125");
        assert_eq!(
            send(&mut s, ms(200), &frame(1, "G0 X10")),
            "echo:Home XYZ first\nok\n"
        );
        send(&mut s, ms(200), &frame(2, "G28"));
        let mut out = Vec::new();
        s.step(ms(5000), b"", &mut out);
        assert!(String::from_utf8_lossy(&out).ends_with("ok\n"));
        assert!(s.homed());
        send(&mut s, ms(5000), &frame(3, "G0 X500"));
        send(&mut s, ms(5000), &frame(4, "M400"));
        let mut out = Vec::new();
        s.step(ms(9000), b"", &mut out);
        assert_eq!(s.position_mm()[0], 300.0, "clamped to the soft endstop");
    }
}
