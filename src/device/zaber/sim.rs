//! Zaber ASCII simulator: a chain of devices with axes, as a pure state machine.
//!
//! Modelled (see `protocols/zaber.md`): commands `home`, `move abs|rel|min|max N`,
//! `stop`, `get <setting>`, `set <setting> N` for `pos`, `limit.min`, `limit.max`,
//! `maxspeed`, `comm.checksum`; `warnings` and `warnings clear`; the empty command
//! (status). Positions are integer microsteps; motion is constant speed at
//! `maxspeed` (native units: 1.6384 × microsteps/s); an axis is `BUSY` while it
//! moves. Axes start unreferenced (`WR`) at their start position; `home` moves to
//! 0 and clears `WR`. `move abs` beyond `limit.min..limit.max` answers
//! `RJ .. BADDATA`; `stop` leaves `NI`. Replies echo the message id (two digits)
//! and carry a checksum when the command had one or `comm.checksum` is 1; a
//! command with a wrong checksum is dropped silently, as real devices do.
//!
//! Faults ([`FaultConfig`]) are applied to replies, see [`ZaberSim`] docs on
//! `apply_fault`.

use std::collections::BTreeMap;
use std::time::Duration;

use super::codec::{encode_alert, encode_info, lrc, Reply, ReplyFlag, Status, Warning};
use crate::device::fault::{FaultConfig, FaultInjector, FaultKind, ReplyClass};
use crate::device::pty::{Flow, Simulator};

/// Native velocity unit: 1 unit of `maxspeed` = 1/1.6384 microsteps/s.
pub const VELOCITY_UNITS_PER_STEP_S: f64 = 1.6384;

/// One simulated axis.
#[derive(Debug, Clone, PartialEq)]
pub struct SimAxis {
    /// Position, microsteps (fractional while moving).
    pub pos: f64,
    /// Travel limits, microsteps.
    pub limit_min: i64,
    /// Travel limits, microsteps.
    pub limit_max: i64,
    /// Speed, native units.
    pub maxspeed: i64,
    /// Has a reference position (homed).
    pub homed: bool,
    target: Option<f64>,
    warnings: Vec<Warning>,
}

impl SimAxis {
    /// An axis at `pos` steps with the given travel, not homed.
    pub fn new(pos: i64, limit_min: i64, limit_max: i64) -> Self {
        SimAxis {
            pos: pos as f64,
            limit_min,
            limit_max,
            // ~ 1 mm/s on a 0.047625 µm/step stage... fast enough for tests:
            // 2_000_000 steps/s × 1.6384.
            maxspeed: 3_276_800,
            homed: false,
            target: None,
            warnings: vec![Warning::NOT_HOMED],
        }
    }

    fn busy(&self) -> bool {
        self.target.is_some()
    }

    fn top_warning(&self) -> Warning {
        // Faults first, then warnings, then notes (Zaber's priority order).
        let rank = |w: &Warning| match w.0[0] {
            b'F' => 0,
            b'W' => 1,
            _ => 2,
        };
        self.warnings
            .iter()
            .min_by_key(|w| rank(w))
            .copied()
            .unwrap_or(Warning::NONE)
    }

    fn warn(&mut self, w: Warning) {
        if !self.warnings.contains(&w) {
            self.warnings.push(w);
        }
    }
}

/// Simulator configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct ZaberSimConfig {
    /// Devices by address, each a list of axes (axis 1, 2, ...).
    pub devices: BTreeMap<u8, Vec<SimAxis>>,
    /// Opt-in faults.
    pub faults: Option<FaultConfig>,
}

impl ZaberSimConfig {
    /// Three single-axis devices (addresses 1, 2, 3), travel 0..`travel_steps`,
    /// starting unhomed at the middle.
    pub fn three_single_axis(travel_steps: i64) -> Self {
        let devices = (1..=3)
            .map(|d| (d, vec![SimAxis::new(travel_steps / 2, 0, travel_steps)]))
            .collect();
        ZaberSimConfig {
            devices,
            faults: None,
        }
    }
}

/// The Zaber ASCII simulator.
#[derive(Debug, Clone)]
pub struct ZaberSim {
    devices: BTreeMap<u8, Vec<SimAxis>>,
    checksum_setting: BTreeMap<u8, bool>,
    line_buf: Vec<u8>,
    last_time: Duration,
    faults: Option<FaultInjector>,
    delayed: Option<(Duration, Vec<u8>)>,
    hangup: bool,
    moves_accepted: u32,
}

impl ZaberSim {
    /// A new simulator.
    pub fn new(config: ZaberSimConfig) -> Self {
        ZaberSim {
            checksum_setting: config.devices.keys().map(|d| (*d, false)).collect(),
            devices: config.devices,
            line_buf: Vec::new(),
            last_time: Duration::ZERO,
            faults: config.faults.map(FaultInjector::new),
            delayed: None,
            hangup: false,
            moves_accepted: 0,
        }
    }

    /// Axis state (device address, axis 1..).
    pub fn axis(&self, device: u8, axis: u8) -> Option<&SimAxis> {
        self.devices
            .get(&device)?
            .get(usize::from(axis).checked_sub(1)?)
    }

    /// Move and home commands accepted so far (to check nothing was re-sent).
    pub fn moves_accepted(&self) -> u32 {
        self.moves_accepted
    }

    /// Faults injected so far.
    pub fn faults_injected(&self) -> u32 {
        self.faults.as_ref().map_or(0, |f| f.injected())
    }

    fn advance(&mut self, now: Duration) {
        let dt = now.saturating_sub(self.last_time).as_secs_f64();
        self.last_time = now;
        for axes in self.devices.values_mut() {
            for ax in axes.iter_mut() {
                let Some(t) = ax.target else { continue };
                let v = ax.maxspeed as f64 / VELOCITY_UNITS_PER_STEP_S;
                let step = v * dt;
                if (t - ax.pos).abs() <= step {
                    ax.pos = t;
                    ax.target = None;
                } else {
                    ax.pos += step * (t - ax.pos).signum();
                }
            }
        }
    }

    fn handle_line(&mut self, line: &[u8], now: Duration, out: &mut Vec<u8>) {
        let Ok(text) = std::str::from_utf8(line) else {
            return;
        };
        let text = text.trim();
        let Some(body) = text.strip_prefix('/') else {
            return;
        };
        let (body, had_checksum) = match body.rsplit_once(':') {
            Some((b, cc)) if cc.len() == 2 => {
                match u8::from_str_radix(cc, 16) {
                    Ok(v) if v == lrc(b.as_bytes()) => (b, true),
                    // Bad checksum: the device ignores the command.
                    _ => return,
                }
            }
            _ => (body, false),
        };
        let mut tok = body.split_whitespace().peekable();
        let device: u8 = match tok.next().map(str::parse) {
            Some(Ok(d)) => d,
            None => 0,
            Some(Err(_)) => return,
        };
        let axis: u8 = match tok.peek().and_then(|t| t.parse().ok()) {
            Some(a) => {
                tok.next();
                a
            }
            None => 0,
        };
        let id: Option<u8> = match tok.peek().and_then(|t| t.parse::<u8>().ok()) {
            Some(i) if i <= 99 => {
                tok.next();
                Some(i)
            }
            _ => None,
        };
        let words: Vec<&str> = tok.collect();
        let targets: Vec<u8> = if device == 0 {
            self.devices.keys().copied().collect()
        } else if self.devices.contains_key(&device) {
            vec![device]
        } else {
            return; // no such device: silence, as on a real chain
        };
        for d in targets {
            let checksum = had_checksum || self.checksum_setting.get(&d).copied().unwrap_or(false);
            let (flag, data, class) = self.execute(d, axis, &words);
            let (status, warning) = self.status_of(d, axis);
            let reply = Reply {
                device: d,
                axis,
                id,
                flag,
                status,
                warning,
                data,
            };
            self.send_reply(out, reply, class, checksum, now);
            if self.hangup {
                return;
            }
        }
    }

    fn status_of(&self, device: u8, axis: u8) -> (Status, Warning) {
        let Some(axes) = self.devices.get(&device) else {
            return (Status::Idle, Warning::NONE);
        };
        let pick: Vec<&SimAxis> = if axis == 0 {
            axes.iter().collect()
        } else {
            axes.get(usize::from(axis) - 1).into_iter().collect()
        };
        let busy = pick.iter().any(|a| a.busy());
        let warning = pick
            .iter()
            .map(|a| a.top_warning())
            .find(|w| !w.is_none())
            .unwrap_or(Warning::NONE);
        (if busy { Status::Busy } else { Status::Idle }, warning)
    }

    /// Runs one command on a device; returns the reply flag, data and class.
    fn execute(&mut self, device: u8, axis: u8, words: &[&str]) -> (ReplyFlag, String, ReplyClass) {
        let rj = |reason: &str| (ReplyFlag::Rejected, reason.to_string(), ReplyClass::Command);
        let ok = |data: String, class| (ReplyFlag::Ok, data, class);
        let Some(axes) = self.devices.get_mut(&device) else {
            return rj("BADAXIS");
        };
        let n_axes = axes.len();
        if usize::from(axis) > n_axes {
            return rj("BADAXIS");
        }
        let sel: Vec<usize> = if axis == 0 {
            (0..n_axes).collect()
        } else {
            vec![usize::from(axis) - 1]
        };
        let num = |s: Option<&&str>| s.and_then(|v| v.parse::<i64>().ok());
        match words {
            [] => ok("0".into(), ReplyClass::Query),
            ["home"] => {
                for &i in &sel {
                    let ax = &mut axes[i];
                    ax.target = Some(0.0);
                    ax.homed = true;
                    ax.warnings
                        .retain(|w| *w != Warning::NOT_HOMED && *w != Warning::INTERRUPTED);
                }
                self.moves_accepted += 1;
                ok("0".into(), ReplyClass::Command)
            }
            ["move", kind, rest @ ..] => {
                let v = num(rest.first());
                let mut targets = Vec::new();
                for &i in &sel {
                    let ax = &axes[i];
                    let t = match (*kind, v) {
                        ("abs", Some(n)) => n as f64,
                        ("rel", Some(n)) => ax.pos.round() + n as f64,
                        ("min", _) => ax.limit_min as f64,
                        ("max", _) => ax.limit_max as f64,
                        _ => return rj("BADDATA"),
                    };
                    if t < ax.limit_min as f64 || t > ax.limit_max as f64 {
                        return rj("BADDATA");
                    }
                    targets.push((i, t));
                }
                for (i, t) in targets {
                    let ax = &mut axes[i];
                    if ax.busy() {
                        ax.warn(Warning::INTERRUPTED);
                    }
                    ax.target = Some(t);
                }
                self.moves_accepted += 1;
                ok("0".into(), ReplyClass::Command)
            }
            ["stop"] => {
                for &i in &sel {
                    let ax = &mut axes[i];
                    if ax.busy() {
                        ax.target = None;
                        ax.pos = ax.pos.round();
                        ax.warn(Warning::INTERRUPTED);
                    }
                }
                ok("0".into(), ReplyClass::Command)
            }
            ["warnings"] => {
                let ax = &axes[sel[0]];
                let mut data = format!("{:02}", ax.warnings.len());
                for w in &ax.warnings {
                    data.push(' ');
                    data.push_str(w.as_str());
                }
                ok(data, ReplyClass::Query)
            }
            ["warnings", "clear"] => {
                let mut data = String::new();
                for &i in &sel {
                    let ax = &mut axes[i];
                    data = format!("{:02}", ax.warnings.len());
                    for w in &ax.warnings {
                        data.push(' ');
                        data.push_str(w.as_str());
                    }
                    // WR reflects a fact (no reference), not an event: it stays.
                    ax.warnings.retain(|w| *w == Warning::NOT_HOMED);
                }
                ok(data, ReplyClass::Command)
            }
            ["get", setting] => {
                let values: Option<Vec<String>> = sel
                    .iter()
                    .map(|&i| {
                        let ax = &axes[i];
                        match *setting {
                            "pos" => Some((ax.pos.round() as i64).to_string()),
                            "limit.min" => Some(ax.limit_min.to_string()),
                            "limit.max" => Some(ax.limit_max.to_string()),
                            "maxspeed" => Some(ax.maxspeed.to_string()),
                            _ => None,
                        }
                    })
                    .collect();
                match (values, *setting) {
                    (_, "comm.checksum") => {
                        let on = self.checksum_setting.get(&device).copied().unwrap_or(false);
                        ok(u8::from(on).to_string(), ReplyClass::Query)
                    }
                    (Some(v), _) => ok(v.join(" "), ReplyClass::Query),
                    (None, _) => rj("BADCOMMAND"),
                }
            }
            ["set", setting, value] => {
                let Ok(v) = value.parse::<i64>() else {
                    return rj("BADDATA");
                };
                if *setting == "comm.checksum" {
                    if !(0..=1).contains(&v) {
                        return rj("BADDATA");
                    }
                    self.checksum_setting.insert(device, v == 1);
                    return ok("0".into(), ReplyClass::Command);
                }
                for &i in &sel {
                    let ax = &mut axes[i];
                    match *setting {
                        "maxspeed" if v > 0 => ax.maxspeed = v,
                        "limit.min" => ax.limit_min = v,
                        "limit.max" => ax.limit_max = v,
                        "pos" if !ax.busy() => ax.pos = v as f64,
                        "maxspeed" | "pos" => return rj("BADDATA"),
                        _ => return rj("BADCOMMAND"),
                    }
                }
                ok("0".into(), ReplyClass::Command)
            }
            _ => rj("BADCOMMAND"),
        }
    }

    /// Sends a reply through the fault injector:
    /// - `LateReply`: this reply and all output after it are held `late_by`;
    /// - `DroppedByte`: one byte of the reply is removed;
    /// - `Garbled`: one byte is replaced by `0xFE` (with checksums on, the reply
    ///   fails its checksum; without, it is non-ASCII);
    /// - `Unsolicited`: an alert `!dd a IDLE --` and an info `#dd a ...` precede it;
    /// - `DeviceReset`: the reply is swallowed; the device's axes stop, lose their
    ///   reference (position 0, `WR`);
    /// - `LimitTrip`: the reply is sent, then the device's moving axes stop with `WL`;
    /// - `Disconnect`: the reply is swallowed and the port hangs up.
    fn send_reply(
        &mut self,
        out: &mut Vec<u8>,
        reply: Reply,
        class: ReplyClass,
        checksum: bool,
        now: Duration,
    ) {
        let fault = self.faults.as_mut().and_then(|f| f.decide(class));
        let mut line = reply.encode(checksum).into_bytes();
        match fault {
            None => push(out, &line),
            Some(FaultKind::LateReply) => {
                let late_by = self
                    .faults
                    .as_ref()
                    .map_or(Duration::ZERO, |f| f.config().late_by);
                let mut held = std::mem::take(out);
                held.extend_from_slice(&line);
                held.extend_from_slice(b"\r\n");
                match &mut self.delayed {
                    Some((_, b)) => b.extend_from_slice(&held),
                    None => self.delayed = Some((now + late_by, held)),
                }
            }
            Some(FaultKind::DroppedByte) => {
                let i = self.faults.as_mut().map_or(0, |f| f.index(line.len()));
                line.remove(i);
                push(out, &line);
            }
            Some(FaultKind::Garbled) => {
                let i = self.faults.as_mut().map_or(0, |f| f.index(line.len()));
                line[i] = 0xFE;
                push(out, &line);
            }
            Some(FaultKind::Unsolicited) => {
                push(
                    out,
                    encode_alert(
                        reply.device,
                        reply.axis,
                        Status::Idle,
                        Warning::NONE,
                        checksum,
                    )
                    .as_bytes(),
                );
                push(
                    out,
                    encode_info(reply.device, reply.axis, "simulated info message", checksum)
                        .as_bytes(),
                );
                push(out, &line);
            }
            Some(FaultKind::DeviceReset) => {
                if let Some(axes) = self.devices.get_mut(&reply.device) {
                    for ax in axes.iter_mut() {
                        *ax = SimAxis {
                            pos: 0.0,
                            target: None,
                            homed: false,
                            warnings: vec![Warning::NOT_HOMED],
                            ..ax.clone()
                        };
                    }
                }
            }
            Some(FaultKind::LimitTrip) => {
                push(out, &line);
                if let Some(axes) = self.devices.get_mut(&reply.device) {
                    for ax in axes.iter_mut() {
                        ax.target = None;
                        ax.pos = ax.pos.round();
                        ax.warn(Warning::LIMIT);
                    }
                }
            }
            Some(FaultKind::Disconnect) => self.hangup = true,
        }
    }
}

impl Simulator for ZaberSim {
    fn step(&mut self, now: Duration, input: &[u8], out: &mut Vec<u8>) -> Flow {
        self.advance(now);
        for &b in input {
            if self.hangup {
                break;
            }
            if b == b'\n' || b == b'\r' {
                let line = std::mem::take(&mut self.line_buf);
                if !line.is_empty() {
                    self.handle_line(&line, now, out);
                }
            } else if self.line_buf.len() < 256 {
                self.line_buf.push(b);
            }
        }
        if let Some((at, bytes)) = &mut self.delayed {
            if *at <= now {
                let mut released = std::mem::take(bytes);
                released.append(out);
                *out = released;
                self.delayed = None;
            } else {
                bytes.append(out);
            }
        }
        if self.hangup {
            Flow::Hangup
        } else {
            Flow::Continue
        }
    }

    fn next_wake(&self, now: Duration) -> Option<Duration> {
        let moving = self.devices.values().flatten().any(SimAxis::busy);
        let late = self.delayed.as_ref().map(|(at, _)| at.saturating_sub(now));
        match (moving, late) {
            (true, Some(l)) => Some(l.min(Duration::from_millis(2))),
            (true, None) => Some(Duration::from_millis(2)),
            (false, l) => l,
        }
    }
}

fn push(out: &mut Vec<u8>, line: &[u8]) {
    out.extend_from_slice(line);
    out.extend_from_slice(b"\r\n");
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(sim: &mut ZaberSim, t_s: f64, input: &str) -> String {
        let mut out = Vec::new();
        sim.step(Duration::from_secs_f64(t_s), input.as_bytes(), &mut out);
        String::from_utf8_lossy(&out).into_owned()
    }

    fn one_axis() -> ZaberSim {
        let mut cfg = ZaberSimConfig::three_single_axis(1_000_000);
        for axes in cfg.devices.values_mut() {
            // 100_000 steps/s.
            axes[0].maxspeed = 163_840;
        }
        ZaberSim::new(cfg)
    }

    #[test]
    fn status_get_and_checksummed_replies() {
        let mut sim = one_axis();
        assert_eq!(run(&mut sim, 0.0, "/1 1\n"), "@01 1 OK IDLE WR 0\r\n");
        assert_eq!(
            run(&mut sim, 0.0, "/1 1 3 get pos\n"),
            "@01 1 03 OK IDLE WR 500000\r\n"
        );
        let cmd = super::super::codec::Command::new(2, 0, "get maxspeed").with_id(5);
        let out = run(&mut sim, 0.0, &format!("{}\n", cmd.encode(true)));
        assert_eq!(
            out,
            format!(
                "{}\r\n",
                Reply {
                    device: 2,
                    axis: 0,
                    id: Some(5),
                    flag: ReplyFlag::Ok,
                    status: Status::Idle,
                    warning: Warning::NOT_HOMED,
                    data: "163840".into()
                }
                .encode(true)
            )
        );
        assert_eq!(
            run(&mut sim, 0.0, "/2 0 5 get maxspeed:53\n"),
            "",
            "bad checksum: ignored"
        );
    }

    #[test]
    fn moves_are_busy_at_maxspeed_then_idle_and_limits_reject() {
        let mut sim = one_axis();
        assert_eq!(run(&mut sim, 0.0, "/1 1 home\n"), "@01 1 OK BUSY -- 0\r\n");
        // 500_000 steps at 100_000 steps/s: 5 s.
        let _ = run(&mut sim, 5.1, "");
        assert_eq!(
            run(&mut sim, 5.1, "/1 1 get pos\n"),
            "@01 1 OK IDLE -- 0\r\n"
        );
        assert_eq!(
            run(&mut sim, 5.1, "/1 1 move abs 2000000\n"),
            "@01 1 RJ IDLE -- BADDATA\r\n"
        );
        run(&mut sim, 6.0, "/1 1 move rel 100000\n");
        assert_eq!(
            run(&mut sim, 6.5, "/1 1 get pos\n"),
            "@01 1 OK BUSY -- 50000\r\n"
        );
        assert_eq!(run(&mut sim, 6.5, "/1 1 stop\n"), "@01 1 OK IDLE NI 0\r\n");
        assert_eq!(
            run(&mut sim, 7.0, "/1 1 warnings clear\n"),
            "@01 1 OK IDLE -- 01 NI\r\n",
            "flag after clearing, data lists what was cleared"
        );
        assert_eq!(
            run(&mut sim, 7.0, "/1 1 foo\n"),
            "@01 1 RJ IDLE -- BADCOMMAND\r\n"
        );
        assert_eq!(
            run(&mut sim, 7.0, "/1 4 get pos\n"),
            "@01 4 RJ IDLE -- BADAXIS\r\n"
        );
    }
}
