//! The GRBL simulator's line interpreter: `$` system commands (settings, `$#`, `$G`,
//! `$I`, homing, unlock, check mode, sleep, jog), G-code words (motion in machine or
//! work coordinates, dwell, units, probing, work offsets `G10` / `G92`), each answered
//! `ok` or with GRBL's error code, and the travel checks they make.

use std::time::Duration;

use super::{dist, g_code, push_line, GrblSim, Mode, SegKind, Segment, INTEGER_SETTINGS};
use crate::device::fault::ReplyClass;
use crate::device::grbl::codec::fmt_num;

impl GrblSim {
    pub(super) fn execute_line(&mut self, raw: &str, now: Duration, out: &mut Vec<u8>) {
        // GRBL strips spaces and upper-cases before parsing.
        let line: String = raw
            .chars()
            .filter(|c| !c.is_whitespace())
            .map(|c| c.to_ascii_uppercase())
            .collect();
        if line.is_empty() {
            self.reply(out, "ok", ReplyClass::Query, now);
            return;
        }
        let result = if let Some(sys) = line.strip_prefix('$') {
            self.system_command(sys, out)
        } else if self.in_alarm()
            || (self.moving() && self.queue.front().is_some_and(|s| s.kind == SegKind::Jog))
        {
            // G-code is locked out in alarm and while jogging.
            Err(9)
        } else {
            self.gcode(&line, now, out)
        };
        match result {
            Ok(Some(class)) => self.reply(out, "ok", class, now),
            // Answered later (homing, dwell).
            Ok(None) => {}
            Err(code) => self.reply(out, &format!("error:{code}"), ReplyClass::Command, now),
        }
    }

    /// A `$` system command (`sys` without the `$`): help, settings, parser state,
    /// unlock, offsets, build info, check mode, sleep, homing, jog, or a setting
    /// `$N=v`. `Ok(None)`: the reply comes later (or was already sent); `Err`: GRBL's
    /// error code.
    pub(super) fn system_command(
        &mut self,
        sys: &str,
        out: &mut Vec<u8>,
    ) -> Result<Option<ReplyClass>, u8> {
        match sys {
            "" => {
                push_line(
                    out,
                    "[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]",
                );
                Ok(Some(ReplyClass::Query))
            }
            "$" => self.report_settings(out),
            "G" => self.report_parser_state(out),
            "X" => {
                if self.in_alarm() {
                    push_line(out, "[MSG:Caution: Unlocked]");
                    self.mode = Mode::Idle;
                }
                Ok(Some(ReplyClass::Command))
            }
            "#" => self.report_offsets(out),
            "I" => {
                if self.moving() {
                    return Err(8);
                }
                push_line(out, "[VER:1.1h.20190830:]");
                push_line(out, "[OPT:V,15,128]");
                Ok(Some(ReplyClass::Query))
            }
            "C" => self.toggle_check_mode(out),
            "SLP" => {
                if self.moving() || self.mode == Mode::Check {
                    return Err(8);
                }
                self.reply(out, "ok", ReplyClass::Command, self.last_time);
                push_line(out, "[MSG:Sleeping]");
                self.mode = Mode::Sleep;
                Ok(None)
            }
            "H" => self.start_homing(),
            _ => match sys.strip_prefix("J=") {
                Some(jog) => self.start_jog(jog),
                None => self.set_setting(sys),
            },
        }
    }

    /// `$$`: every setting, integers without a fraction (refused while moving).
    fn report_settings(&mut self, out: &mut Vec<u8>) -> Result<Option<ReplyClass>, u8> {
        if self.moving() {
            return Err(8);
        }
        let lines: Vec<String> = self
            .settings
            .iter()
            .map(|(k, v)| {
                if INTEGER_SETTINGS.contains(k) {
                    format!("${k}={}", *v as i64)
                } else {
                    format!("${k}={}", fmt_num(*v))
                }
            })
            .collect();
        for l in lines {
            push_line(out, &l);
        }
        Ok(Some(ReplyClass::Query))
    }

    /// `$G`: the parser state (motion mode, coordinate system, distance mode, feed).
    fn report_parser_state(&mut self, out: &mut Vec<u8>) -> Result<Option<ReplyClass>, u8> {
        let motion = if self.feed_mm_min.is_some() {
            "G1"
        } else {
            "G0"
        };
        let dist = if self.relative { "G91" } else { "G90" };
        let f = self.feed_mm_min.unwrap_or(0.0);
        push_line(
            out,
            &format!(
                "[GC:{motion} G5{} G17 G21 {dist} G94 M5 M9 T0 F{} S0]",
                4 + self.active_system,
                f.round() as i64
            ),
        );
        Ok(Some(ReplyClass::Query))
    }

    /// `$#`: the work coordinate offsets G54–G59, G28, G30, G92, tool length, probe
    /// (refused while moving or in check mode).
    fn report_offsets(&mut self, out: &mut Vec<u8>) -> Result<Option<ReplyClass>, u8> {
        if self.moving() || self.mode == Mode::Check {
            return Err(8);
        }
        let f = |v: [f64; 3]| v.iter().map(|x| fmt_num(*x)).collect::<Vec<_>>().join(",");
        for (i, c) in self.systems.iter().enumerate() {
            push_line(out, &format!("[G5{}:{}]", 4 + i, f(*c)));
        }
        push_line(out, "[G28:0.000,0.000,0.000]");
        push_line(out, "[G30:0.000,0.000,0.000]");
        push_line(out, &format!("[G92:{}]", f(self.g92)));
        push_line(out, "[TLO:0.000]");
        push_line(out, "[PRB:0.000,0.000,0.000:0]");
        Ok(Some(ReplyClass::Query))
    }

    /// `$C`: enters check mode from idle; leaving it resets, as GRBL does.
    fn toggle_check_mode(&mut self, out: &mut Vec<u8>) -> Result<Option<ReplyClass>, u8> {
        match self.mode {
            Mode::Check => {
                // GRBL resets when leaving check mode.
                push_line(out, "[MSG:Disabled]");
                self.reply(out, "ok", ReplyClass::Command, self.last_time);
                self.soft_reset(out);
                return Ok(None);
            }
            Mode::Idle if !self.moving() => {
                self.mode = Mode::Check;
                push_line(out, "[MSG:Enabled]");
            }
            _ => return Err(8),
        }
        Ok(Some(ReplyClass::Command))
    }

    /// `$H`: queues a homing cycle at the seek rate `$25` (answered when it ends).
    fn start_homing(&mut self) -> Result<Option<ReplyClass>, u8> {
        if !self.homing_enabled() {
            return Err(5);
        }
        if self.moving() {
            return Err(8);
        }
        self.mode = Mode::Idle;
        let seek = self.setting(25).max(1.0) / 60.0;
        self.queue.push_back(Segment {
            kind: SegKind::Home,
            target: [0.0; 3],
            speed_mm_s: seek,
        });
        Ok(None)
    }

    /// `$J=…`: a jog, from idle or behind other jogs only.
    fn start_jog(&mut self, jog: &str) -> Result<Option<ReplyClass>, u8> {
        if self.mode != Mode::Idle
            || (self.moving() && self.queue.front().is_some_and(|s| s.kind != SegKind::Jog))
        {
            return Err(8);
        }
        self.jog(jog).map(|_| Some(ReplyClass::Command))
    }

    /// `$N=v`: sets a known setting (not while moving, not negative; homing `$20`
    /// needs `$22`).
    fn set_setting(&mut self, sys: &str) -> Result<Option<ReplyClass>, u8> {
        let (n, v) = sys.split_once('=').ok_or(3u8)?;
        let n: u16 = n.parse().map_err(|_| 3u8)?;
        let v: f64 = v.parse().map_err(|_| 2u8)?;
        if !self.settings.contains_key(&n) {
            return Err(3);
        }
        if self.moving() {
            return Err(8);
        }
        if v < 0.0 {
            return Err(4);
        }
        if n == 20 && v != 0.0 && !self.homing_enabled() {
            return Err(10);
        }
        self.settings.insert(n, v);
        Ok(Some(ReplyClass::Command))
    }

    /// Parses `G21 G91 X1 F100`-style words (spaces already stripped).
    pub(super) fn words(line: &str) -> Result<Vec<(char, f64)>, u8> {
        let b = line.as_bytes();
        let mut i = 0;
        let mut words = Vec::new();
        while i < b.len() {
            let letter = b[i] as char;
            if !letter.is_ascii_alphabetic() {
                return Err(1);
            }
            i += 1;
            let start = i;
            while i < b.len()
                && (b[i].is_ascii_digit() || b[i] == b'.' || b[i] == b'-' || b[i] == b'+')
            {
                i += 1;
            }
            let v: f64 = line[start..i].parse().map_err(|_| 2u8)?;
            words.push((letter, v));
        }
        Ok(words)
    }

    pub(super) fn axis_words(words: &[(char, f64)]) -> [Option<f64>; 3] {
        let mut xyz = [None; 3];
        for (l, v) in words {
            match l {
                'X' => xyz[0] = Some(*v),
                'Y' => xyz[1] = Some(*v),
                'Z' => xyz[2] = Some(*v),
                _ => {}
            }
        }
        xyz
    }

    /// End of the queued motion (where a new segment starts).
    pub(super) fn planned_end(&self) -> [f64; 3] {
        self.queue.back().map_or(self.mpos, |s| s.target)
    }

    pub(super) fn resolve(&self, xyz: [Option<f64>; 3], relative: bool) -> [f64; 3] {
        let base = self.planned_end();
        let mut t = base;
        for i in 0..3 {
            if let Some(v) = xyz[i] {
                t[i] = if relative { base[i] + v } else { v };
            }
        }
        t
    }

    pub(super) fn within_travel(&self, t: [f64; 3]) -> bool {
        (0..3).all(|i| t[i] <= 1e-9 && t[i] >= -self.setting(130 + i as u16) - 1e-9)
    }

    pub(super) fn rapid_speed(&self, from: [f64; 3], to: [f64; 3]) -> f64 {
        // Each axis component must stay below its own max rate ($110..$112 mm/min).
        let d = dist(from, to);
        let mut v = f64::INFINITY;
        for i in 0..3 {
            let comp = (to[i] - from[i]).abs();
            if comp > 0.0 {
                v = v.min(self.setting(110 + i as u16) / 60.0 * d / comp);
            }
        }
        if v.is_finite() {
            v
        } else {
            1.0
        }
    }

    pub(super) fn capped(&self, from: [f64; 3], to: [f64; 3], feed_mm_min: f64) -> f64 {
        (feed_mm_min / 60.0).min(self.rapid_speed(from, to))
    }

    pub(super) fn jog(&mut self, body: &str) -> Result<(), u8> {
        let words = Self::words(body)?;
        let mut relative = false;
        let mut feed = None;
        for (l, v) in &words {
            match (l, g_code(*v)) {
                ('G', 910) => relative = true,
                ('G', 900 | 530 | 210) => {}
                ('F', _) => feed = Some(*v),
                ('X' | 'Y' | 'Z', _) => {}
                _ => return Err(16),
            }
        }
        let feed = feed.ok_or(16u8)?;
        let xyz = Self::axis_words(&words);
        if xyz.iter().all(Option::is_none) {
            return Err(16);
        }
        let target = self.resolve(xyz, relative);
        if self.setting(20) != 0.0 && !self.within_travel(target) {
            return Err(15);
        }
        let from = self.planned_end();
        let speed = self.capped(from, target, feed);
        self.motions_accepted += 1;
        self.queue.push_back(Segment {
            kind: SegKind::Jog,
            target,
            speed_mm_s: speed,
        });
        Ok(())
    }

    pub(super) fn gcode(
        &mut self,
        line: &str,
        now: Duration,
        out: &mut Vec<u8>,
    ) -> Result<Option<ReplyClass>, u8> {
        let words = Self::words(line)?;
        let mut motion: Option<SegKind> = None;
        let mut rapid = false;
        let mut machine = false;
        let mut dwell = false;
        let mut relative = self.relative;
        let mut feed = self.feed_mm_min;
        let mut p = None;
        let mut l_word = None;
        let mut offset_cmd: Option<i64> = None;
        let mut select: Option<usize> = None;
        for (l, v) in &words {
            match (l, g_code(*v)) {
                ('G', 0) => {
                    motion = Some(SegKind::Line);
                    rapid = true;
                }
                ('G', 10) => {
                    motion = Some(SegKind::Line);
                    rapid = false;
                }
                ('G', 382) => motion = Some(SegKind::Probe),
                ('G', 40) => dwell = true,
                ('G', 210) => {}
                // Inches are valid G-code but the driver never sends them; refusing
                // keeps the simulator in one unit (documented in protocols/grbl.md).
                ('G', 200) => return Err(20),
                ('G', 530) => machine = true,
                ('G', code @ (100 | 920 | 921)) => offset_cmd = Some(code),
                ('G', code @ (540 | 550 | 560 | 570 | 580 | 590)) => {
                    select = Some(((code - 540) / 10) as usize)
                }
                ('L', _) => l_word = Some(*v),
                ('G', 900) => relative = false,
                ('G', 910) => relative = true,
                ('F', _) => {
                    let f = *v;
                    if f <= 0.0 {
                        return Err(4);
                    }
                    feed = Some(f)
                }
                ('P', _) => p = Some(*v),
                ('X' | 'Y' | 'Z', _) => {}
                ('N', _) => {}
                _ => return Err(20),
            }
        }
        self.relative = relative;
        self.feed_mm_min = feed;
        let xyz = Self::axis_words(&words);
        if let Some(cs) = select {
            if cs != self.active_system {
                self.active_system = cs;
                self.wco_changed();
            }
        }
        if let Some(code) = offset_cmd {
            self.set_offsets(code, l_word, p, xyz)?;
            return Ok(Some(ReplyClass::Command));
        }
        if dwell {
            let p = p.ok_or(28u8)?;
            if p < 0.0 {
                return Err(4);
            }
            if self.mode == Mode::Check {
                return Ok(Some(ReplyClass::Command));
            }
            self.dwell_until = Some(now + Duration::from_secs_f64(p));
            return Ok(None);
        }
        if machine && motion != Some(SegKind::Line) {
            return Err(30);
        }
        let Some(kind) = motion else {
            return Ok(Some(ReplyClass::Command));
        };
        if xyz.iter().all(Option::is_none) {
            return Err(26);
        }
        let target = if relative && !machine {
            self.resolve(xyz, true)
        } else if machine {
            self.resolve(xyz, false)
        } else {
            // Absolute in work coordinates: machine = work + WCO.
            let w = self.wco_mm();
            let mut xyz_m = xyz;
            for i in 0..3 {
                xyz_m[i] = xyz[i].map(|v| v + w[i]);
            }
            self.resolve(xyz_m, false)
        };
        let from = self.planned_end();
        let speed = if rapid {
            self.rapid_speed(from, target)
        } else {
            self.capped(from, target, feed.ok_or(22u8)?)
        };
        if self.setting(20) != 0.0 && !self.within_travel(target) {
            // GRBL checks soft limits when planning a G0/G1: alarm, critical lock.
            self.critical_alarm(2, out);
            self.ok_on_reset = true;
            return Ok(None);
        }
        if kind == SegKind::Probe && self.moving() {
            return Err(8);
        }
        if self.mode == Mode::Check {
            // Check mode: parsed and answered, nothing moves.
            return Ok(Some(ReplyClass::Command));
        }
        self.motions_accepted += 1;
        self.queue.push_back(Segment {
            kind,
            target,
            speed_mm_s: speed,
        });
        Ok(Some(ReplyClass::Command))
    }

    /// `G10 L2 Pn` (set system n), `G10 L20 Pn` (set system n so that the current
    /// position reads the given values), `G92` (offset so that it reads them),
    /// `G92.1` (clear G92). P0 = the active system.
    pub(super) fn set_offsets(
        &mut self,
        code: i64,
        l_word: Option<f64>,
        p: Option<f64>,
        xyz: [Option<f64>; 3],
    ) -> Result<(), u8> {
        // GRBL syncs the planner before changing offsets.
        if self.moving() {
            return Err(8);
        }
        match code {
            100 => {
                let l = l_word.ok_or(17u8)?.round() as i64;
                let p = p.ok_or(28u8)?.round() as i64;
                if !(0..=6).contains(&p) {
                    return Err(29);
                }
                let cs = if p == 0 {
                    self.active_system
                } else {
                    (p - 1) as usize
                };
                for (i, v) in xyz.iter().enumerate() {
                    if let Some(v) = v {
                        self.systems[cs][i] = match l {
                            2 => *v,
                            20 => self.mpos[i] - self.g92[i] - v,
                            _ => return Err(17),
                        };
                    }
                }
            }
            920 => {
                if xyz.iter().all(Option::is_none) {
                    return Err(26);
                }
                let c = self.systems[self.active_system];
                for (i, v) in xyz.iter().enumerate() {
                    if let Some(v) = v {
                        self.g92[i] = self.mpos[i] - c[i] - v;
                    }
                }
            }
            _ => self.g92 = [0.0; 3],
        }
        self.wco_changed();
        Ok(())
    }
}
