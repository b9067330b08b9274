//! GRBL 1.1 wire codec: pure encoding of commands and decoding of reply lines.
//!
//! Framing (see `protocols/grbl.md`): lines the host sends end with `\n` and are
//! each answered by exactly one `ok` or `error:N`; real-time commands are single
//! bytes, never followed by a newline and never answered with `ok`. The controller
//! ends its lines with `\r\n`; the decoder takes one line without terminator.
//!
//! Numbers are written with 3 decimals (1 µm in mm mode, GRBL's own report
//! resolution); feed rates are mm/min on the wire.

use std::fmt;

/// A line command (answered by `ok` / `error:N`).
#[derive(Debug, Clone, PartialEq)]
pub enum Command {
    /// `G21`: millimetre units.
    Millimetres,
    /// `G90`: absolute distances.
    Absolute,
    /// `G91`: relative distances.
    Relative,
    /// A straight move. `G53` makes it absolute in machine coordinates (the frame
    /// the driver uses); `relative` makes it `G91`. `feed_mm_min: None` is a rapid
    /// (`G0`), otherwise a feed move (`G1 .. F`).
    Move {
        /// Axis targets (or deltas), mm; `None` leaves the axis out of the line.
        xyz_mm: [Option<f64>; 3],
        /// Feed rate in mm/min; `None` for a rapid move.
        feed_mm_min: Option<f64>,
        /// Relative (`G91`) instead of machine-absolute (`G53`).
        relative: bool,
    },
    /// `G4 P<s>`: dwell; `G4 P0` also waits for all queued motion to finish.
    Dwell {
        /// Dwell time in seconds.
        seconds: f64,
    },
    /// `G38.2`: probe toward contact by the given distances (relative, `G91`, as
    /// `G53` does not combine with probing), alarm 5 if no contact.
    Probe {
        /// Axis distances, mm.
        xyz_mm: [Option<f64>; 3],
        /// Feed rate, mm/min.
        feed_mm_min: f64,
    },
    /// `$X`: kill the alarm lock.
    Unlock,
    /// `$H`: run the homing cycle.
    Home,
    /// `$$`: list the settings.
    Settings,
    /// `$G`: report the parser state (`[GC:..]`); the driver uses it to resynchronise.
    ParserState,
    /// `$#`: list the coordinate offsets (`[G54:..]` .. `[G59:..]`, `[G92:..]`,
    /// `[TLO:..]`, ...); answered in Idle and Alarm only (`error:8` otherwise).
    Offsets,
    /// `$C`: toggle check mode (GRBL resets when leaving it).
    CheckMode,
    /// `$I`: build info (`[VER:1.1h.20190830:]`, `[OPT:..]`); Idle and Alarm only.
    BuildInfo,
    /// `$N=V`: store a setting.
    SetSetting {
        /// Setting number.
        number: u16,
        /// Value as written.
        value: f64,
    },
    /// `$J=`: jog, relative (`G91`) or machine-absolute (`G53`), feed mm/min.
    Jog {
        /// Axis targets or deltas, mm.
        xyz_mm: [Option<f64>; 3],
        /// Feed rate, mm/min (required by GRBL for jogs).
        feed_mm_min: f64,
        /// Relative instead of machine-absolute.
        relative: bool,
    },
}

/// Formats a length or rate with 3 decimals, never as `-0.000`.
pub fn fmt_num(v: f64) -> String {
    let s = format!("{v:.3}");
    if s == "-0.000" {
        "0.000".to_string()
    } else {
        s
    }
}

fn push_axes(out: &mut String, xyz: &[Option<f64>; 3]) {
    for (letter, v) in ['X', 'Y', 'Z'].iter().zip(xyz) {
        if let Some(v) = v {
            out.push(' ');
            out.push(*letter);
            out.push_str(&fmt_num(*v));
        }
    }
}

impl Command {
    /// The line as sent, without the terminating `\n`.
    pub fn encode(&self) -> String {
        match self {
            Command::Millimetres => "G21".into(),
            Command::Absolute => "G90".into(),
            Command::Relative => "G91".into(),
            Command::Move {
                xyz_mm,
                feed_mm_min,
                relative,
            } => {
                let mut s = String::from("G21 ");
                s.push_str(if *relative { "G91" } else { "G53" });
                s.push_str(if feed_mm_min.is_some() { " G1" } else { " G0" });
                push_axes(&mut s, xyz_mm);
                if let Some(f) = feed_mm_min {
                    s.push_str(" F");
                    s.push_str(&fmt_num(*f));
                }
                s
            }
            Command::Dwell { seconds } => format!("G4 P{}", fmt_num(*seconds)),
            Command::Probe {
                xyz_mm,
                feed_mm_min,
            } => {
                let mut s = String::from("G21 G91 G38.2");
                push_axes(&mut s, xyz_mm);
                s.push_str(" F");
                s.push_str(&fmt_num(*feed_mm_min));
                s
            }
            Command::Unlock => "$X".into(),
            Command::Home => "$H".into(),
            Command::Settings => "$$".into(),
            Command::ParserState => "$G".into(),
            Command::Offsets => "$#".into(),
            Command::BuildInfo => "$I".into(),
            Command::CheckMode => "$C".into(),
            Command::SetSetting { number, value } => format!("${number}={}", fmt_num(*value)),
            Command::Jog {
                xyz_mm,
                feed_mm_min,
                relative,
            } => {
                let mut s = String::from("$J=G21 ");
                s.push_str(if *relative { "G91" } else { "G53" });
                push_axes(&mut s, xyz_mm);
                s.push_str(" F");
                s.push_str(&fmt_num(*feed_mm_min));
                s
            }
        }
    }

    /// The bytes on the wire: the line plus `\n`.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut b = self.encode().into_bytes();
        b.push(b'\n');
        b
    }

    /// True for commands that only read state, which a driver may re-send safely.
    pub fn is_query(&self) -> bool {
        matches!(
            self,
            Command::Settings
                | Command::ParserState
                | Command::Offsets
                | Command::BuildInfo
                | Command::Dwell { .. }
        )
    }
}

/// A real-time command: one byte, no newline, no `ok`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Realtime {
    /// `?`: status report.
    StatusQuery,
    /// `!`: feed hold.
    FeedHold,
    /// `~`: cycle start / resume.
    CycleStart,
    /// 0x18 (Ctrl-X): soft reset.
    SoftReset,
    /// 0x85: jog cancel.
    JogCancel,
}

impl Realtime {
    /// The byte on the wire.
    pub fn byte(self) -> u8 {
        match self {
            Realtime::StatusQuery => b'?',
            Realtime::FeedHold => b'!',
            Realtime::CycleStart => b'~',
            Realtime::SoftReset => 0x18,
            Realtime::JogCancel => 0x85,
        }
    }

    /// The real-time command for a byte, if it is one.
    pub fn from_byte(b: u8) -> Option<Self> {
        match b {
            b'?' => Some(Realtime::StatusQuery),
            b'!' => Some(Realtime::FeedHold),
            b'~' => Some(Realtime::CycleStart),
            0x18 => Some(Realtime::SoftReset),
            0x85 => Some(Realtime::JogCancel),
            _ => None,
        }
    }
}

/// Machine state as reported in a status report.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MachineState {
    /// Idle.
    Idle,
    /// Running a G-code motion.
    Run,
    /// Feed hold; 0 = hold complete, 1 = decelerating.
    Hold(u8),
    /// Jogging.
    Jog,
    /// Alarm lock.
    Alarm,
    /// Safety door; 0..3 sub-states.
    Door(u8),
    /// G-code check mode.
    Check,
    /// Homing cycle.
    Home,
    /// Sleep.
    Sleep,
}

impl fmt::Display for MachineState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            MachineState::Idle => f.write_str("Idle"),
            MachineState::Run => f.write_str("Run"),
            MachineState::Hold(n) => write!(f, "Hold:{n}"),
            MachineState::Jog => f.write_str("Jog"),
            MachineState::Alarm => f.write_str("Alarm"),
            MachineState::Door(n) => write!(f, "Door:{n}"),
            MachineState::Check => f.write_str("Check"),
            MachineState::Home => f.write_str("Home"),
            MachineState::Sleep => f.write_str("Sleep"),
        }
    }
}

impl MachineState {
    fn parse(s: &str) -> Option<Self> {
        let (name, sub) = match s.split_once(':') {
            Some((n, v)) => (n, Some(v.parse::<u8>().ok()?)),
            None => (s, None),
        };
        Some(match (name, sub) {
            ("Idle", None) => MachineState::Idle,
            ("Run", None) => MachineState::Run,
            // GRBL 1.1 always sends the sub-state; tolerate its absence (0.9 style).
            ("Hold", n) => MachineState::Hold(n.unwrap_or(0)),
            ("Jog", None) => MachineState::Jog,
            ("Alarm", None) => MachineState::Alarm,
            ("Door", n) => MachineState::Door(n.unwrap_or(0)),
            ("Check", None) => MachineState::Check,
            ("Home", None) => MachineState::Home,
            ("Sleep", None) => MachineState::Sleep,
            _ => return None,
        })
    }
}

/// A decoded status report `<State|MPos:..|FS:..|...>`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct StatusReport {
    /// Machine state (`None` only in a default value).
    pub state: Option<MachineState>,
    /// Machine position, mm (`$10` bit 0 = 1).
    pub mpos_mm: Option<[f64; 3]>,
    /// Work position, mm (`$10` bit 0 = 0).
    pub wpos_mm: Option<[f64; 3]>,
    /// Work coordinate offset, mm (sent every 10..30 reports): MPos = WPos + WCO.
    pub wco_mm: Option<[f64; 3]>,
    /// Current feed rate, mm/min (`FS:` or `F:`).
    pub feed_mm_min: Option<f64>,
    /// Spindle speed (`FS:` second value).
    pub spindle_rpm: Option<f64>,
    /// Planner blocks and serial bytes free (`Bf:`).
    pub buffer_free: Option<(u32, u32)>,
    /// Input pins (`Pn:`), e.g. `XZ`, `P`.
    pub pins: Option<String>,
}

/// One decoded line from the controller.
#[derive(Debug, Clone, PartialEq)]
pub enum Response {
    /// `ok`.
    Ok,
    /// `error:N`.
    Error(u8),
    /// `ALARM:N` (pushed).
    Alarm(u8),
    /// `<...>` status report.
    Status(StatusReport),
    /// `[MSG:..]` (pushed).
    Message(String),
    /// `[GC:..]` parser state.
    ParserState(String),
    /// Any other `[...]` feedback (`[PRB:..]`, `[VER:..]`, `[HLP:..]`, ...), inner text.
    Feedback(String),
    /// The reset banner, e.g. `Grbl 1.1h ['$' for help]`; carries the version `1.1h`.
    Banner(String),
    /// `$N=V` setting line.
    Setting {
        /// Setting number.
        number: u16,
        /// Value as text (numbers, or strings for `$N` startup lines).
        value: String,
    },
}

/// Why a line could not be decoded.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("unrecognised line from the controller: {line:?} ({reason})")]
pub struct DecodeError {
    /// The offending line (lossy text).
    pub line: String,
    /// What was wrong.
    pub reason: &'static str,
}

fn parse_triple(s: &str) -> Option<[f64; 3]> {
    // GRBL sends N_AXIS values; take the first three (x, y, z).
    let mut it = s.split(',');
    let mut v = [0.0; 3];
    for slot in &mut v {
        *slot = it.next()?.trim().parse::<f64>().ok()?;
        if !slot.is_finite() {
            return None;
        }
    }
    Some(v)
}

fn parse_status(inner: &str) -> Option<StatusReport> {
    let mut fields = inner.split('|');
    let mut r = StatusReport {
        state: Some(MachineState::parse(fields.next()?)?),
        ..Default::default()
    };
    for field in fields {
        let (key, val) = field.split_once(':')?;
        match key {
            "MPos" => r.mpos_mm = Some(parse_triple(val)?),
            "WPos" => r.wpos_mm = Some(parse_triple(val)?),
            "WCO" => r.wco_mm = Some(parse_triple(val)?),
            "FS" => {
                let (f, s) = val.split_once(',')?;
                r.feed_mm_min = Some(f.parse().ok()?);
                r.spindle_rpm = Some(s.parse().ok()?);
            }
            "F" => r.feed_mm_min = Some(val.parse().ok()?),
            "Bf" => {
                let (a, b) = val.split_once(',')?;
                r.buffer_free = Some((a.parse().ok()?, b.parse().ok()?));
            }
            "Pn" => r.pins = Some(val.to_string()),
            // Ln, Ov, A and future fields: valid, not needed.
            _ => {}
        }
    }
    if r.mpos_mm.is_none() && r.wpos_mm.is_none() {
        return None;
    }
    Some(r)
}

/// The work coordinate offsets from a `$#` listing, combined as GRBL combines them
/// into the `WCO:` of its status reports: the active coordinate system (`G54`..`G59`)
/// plus `G92` plus the tool length offset on z.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Offsets {
    /// `G54`..`G59` offsets, mm (index 0 = G54); `None` where the listing lacked one.
    pub systems_mm: [Option<[f64; 3]>; 6],
    /// `G92` offset, mm.
    pub g92_mm: Option<[f64; 3]>,
    /// Tool length offset (`TLO`), mm, applied to z.
    pub tlo_mm: Option<f64>,
}

impl Offsets {
    /// Takes one `[...]` feedback line of a `$#` listing (inner text, e.g.
    /// `G54:-2.000,-3.000,-1.000`); returns false if it is not an offset line.
    pub fn take(&mut self, feedback: &str) -> bool {
        let Some((key, val)) = feedback.split_once(':') else {
            return false;
        };
        match key {
            "G54" | "G55" | "G56" | "G57" | "G58" | "G59" => {
                let i = usize::from(key.as_bytes()[2] - b'4');
                self.systems_mm[i] = parse_triple(val);
                self.systems_mm[i].is_some()
            }
            "G92" => {
                self.g92_mm = parse_triple(val);
                self.g92_mm.is_some()
            }
            "TLO" => {
                self.tlo_mm = val.trim().parse().ok().filter(|v: &f64| v.is_finite());
                self.tlo_mm.is_some()
            }
            // G28, G30, PRB: listed, not part of the work offset.
            "G28" | "G30" | "PRB" => true,
            _ => false,
        }
    }

    /// The work coordinate offset (MPos = WPos + WCO) with coordinate system
    /// `system` active (0 = G54 .. 5 = G59); `None` if the listing lacked a part.
    pub fn wco_mm(&self, system: usize) -> Option<[f64; 3]> {
        let cs = (*self.systems_mm.get(system)?)?;
        let g92 = self.g92_mm?;
        let tlo = self.tlo_mm?;
        Some([cs[0] + g92[0], cs[1] + g92[1], cs[2] + g92[2] + tlo])
    }
}

/// The active coordinate system (0 = G54 .. 5 = G59) in a `$G` parser state
/// (`G0 G54 G17 G21 G90 ...`); `None` if the state names none.
pub fn active_coordinate_system(parser_state: &str) -> Option<usize> {
    parser_state.split_whitespace().find_map(|w| match w {
        "G54" => Some(0),
        "G55" => Some(1),
        "G56" => Some(2),
        "G57" => Some(3),
        "G58" => Some(4),
        "G59" => Some(5),
        _ => None,
    })
}

/// The firmware version in a `$I` line (`VER:1.1h.20190830:` → `1.1h.20190830`).
pub fn build_version(feedback: &str) -> Option<&str> {
    let v = feedback.strip_prefix("VER:")?;
    let v = v.split(':').next().unwrap_or(v).trim();
    (!v.is_empty()).then_some(v)
}

/// Decodes one line (terminators already stripped).
pub fn decode(line: &[u8]) -> Result<Response, DecodeError> {
    let err = |reason| DecodeError {
        line: String::from_utf8_lossy(line).into_owned(),
        reason,
    };
    // GRBL output is plain printable ASCII; anything else is line noise.
    if !line.iter().all(|b| (0x20..0x7f).contains(b)) {
        return Err(err("non-ASCII or control bytes"));
    }
    let s = std::str::from_utf8(line)
        .map_err(|_| err("not UTF-8"))?
        .trim();
    if s == "ok" {
        return Ok(Response::Ok);
    }
    if let Some(n) = s.strip_prefix("error:") {
        return n
            .parse()
            .map(Response::Error)
            .map_err(|_| err("bad error code"));
    }
    if let Some(n) = s.strip_prefix("ALARM:") {
        return n
            .parse()
            .map(Response::Alarm)
            .map_err(|_| err("bad alarm code"));
    }
    if let Some(inner) = s.strip_prefix('<') {
        let inner = inner
            .strip_suffix('>')
            .ok_or_else(|| err("unterminated status report"))?;
        return parse_status(inner)
            .map(Response::Status)
            .ok_or_else(|| err("malformed status report"));
    }
    if let Some(inner) = s.strip_prefix('[') {
        let inner = inner
            .strip_suffix(']')
            .ok_or_else(|| err("unterminated feedback"))?;
        if let Some(m) = inner.strip_prefix("MSG:") {
            return Ok(Response::Message(m.to_string()));
        }
        if let Some(m) = inner.strip_prefix("GC:") {
            return Ok(Response::ParserState(m.to_string()));
        }
        return Ok(Response::Feedback(inner.to_string()));
    }
    if let Some(rest) = s.strip_prefix("Grbl ") {
        let version = rest.split_whitespace().next().unwrap_or("");
        if version.is_empty() {
            return Err(err("banner without version"));
        }
        return Ok(Response::Banner(version.to_string()));
    }
    if let Some(rest) = s.strip_prefix('$') {
        if let Some((n, v)) = rest.split_once('=') {
            if let Ok(number) = n.parse() {
                return Ok(Response::Setting {
                    number,
                    value: v.to_string(),
                });
            }
        }
        return Err(err("malformed setting line"));
    }
    Err(err("unknown line"))
}

/// GRBL 1.1 `error:N` meanings (from the GRBL 1.1 interface documentation).
pub fn error_text(code: u8) -> &'static str {
    match code {
        1 => "g-code words consist of a letter and a value; letter was not found",
        2 => "numeric value format is not valid or missing an expected value",
        3 => "grbl '$' system command was not recognized or supported",
        4 => "negative value received for an expected positive value",
        5 => "homing cycle is not enabled via settings",
        6 => "minimum step pulse time must be greater than 3 µs",
        7 => "eeprom read failed; reset and restored to default values",
        8 => "grbl '$' command cannot be used unless grbl is idle",
        9 => "g-code locked out during alarm or jog state",
        10 => "soft limits cannot be enabled without homing also enabled",
        11 => "max characters per line exceeded; line was not processed",
        12 => "grbl '$' setting value exceeds the maximum step rate supported",
        13 => "safety door detected as opened and door state initiated",
        14 => "build info or startup line exceeded eeprom line length limit",
        15 => "jog target exceeds machine travel; command ignored",
        16 => "jog command with no '=' or contains prohibited g-code",
        17 => "laser mode requires pwm output",
        20 => "unsupported or invalid g-code command found in block",
        21 => "more than one g-code command from same modal group found in block",
        22 => "feed rate has not yet been set or is undefined",
        23 => "g-code command in block requires an integer value",
        24 => "two g-code commands that both require the use of the xyz axis words were detected",
        25 => "a g-code word was repeated in the block",
        26 => "a g-code command implicitly or explicitly requires xyz axis words, none found",
        27 => "n line number value is not within the valid range of 1 - 9,999,999",
        28 => "a g-code command was sent, but is missing some required p or l value words",
        29 => "grbl supports six work coordinate systems g54-g59",
        30 => "the g53 g-code command requires either a g0 seek or g1 feed motion mode",
        31 => "there are unused axis words in the block and g80 motion mode cancel is active",
        32 => "a g2 or g3 arc was commanded but there are no xyz axis words in the selected plane",
        33 => "the motion command has an invalid target",
        36 => "there are unused, leftover g-code words that aren't used by any command in the block",
        37 => "the g43.1 dynamic tool length offset command cannot apply an offset to an axis other than its configured axis",
        38 => "tool number greater than max supported value",
        _ => "unknown error code",
    }
}

/// GRBL 1.1 `ALARM:N` meanings.
pub fn alarm_text(code: u8) -> &'static str {
    match code {
        1 => "hard limit triggered; machine position is likely lost",
        2 => "soft limit: motion target exceeds machine travel",
        3 => "reset while in motion; machine position is likely lost",
        4 => "probe fail: probe not in the expected initial state",
        5 => "probe fail: probe did not contact the workpiece",
        6 => "homing fail: reset during the homing cycle",
        7 => "homing fail: safety door opened during homing",
        8 => "homing fail: pull-off failed to clear the limit switch",
        9 => "homing fail: could not find the limit switch",
        10 => "homing fail: second dual-axis switch not found",
        _ => "unknown alarm code",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offsets_listing_of_real_grbl_combines_into_the_wco_of_its_reports() {
        // `$#` and `$G` as GRBL 1.1h answered after `G10 L2 P1 X-2 Y-3 Z-1` and
        // `G92 X1` at WPos x 7 (its reports then carried WCO:4.000,-3.000,-1.000).
        let mut o = Offsets::default();
        for line in [
            "G54:-2.000,-3.000,-1.000",
            "G55:0.000,0.000,0.000",
            "G56:0.000,0.000,0.000",
            "G57:0.000,0.000,0.000",
            "G58:0.000,0.000,0.000",
            "G59:0.000,0.000,0.000",
            "G28:0.000,0.000,0.000",
            "G30:0.000,0.000,0.000",
            "G92:6.000,0.000,0.000",
            "TLO:0.000",
            "PRB:0.000,0.000,0.000:0",
        ] {
            assert!(o.take(line), "{line}");
        }
        assert!(!o.take("VER:1.1h.20190830:"));
        let cs = active_coordinate_system("G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0");
        assert_eq!(cs, Some(0));
        assert_eq!(o.wco_mm(0), Some([4.0, -3.0, -1.0]));
        assert_eq!(o.wco_mm(1), Some([6.0, 0.0, 0.0]));
        assert_eq!(Offsets::default().wco_mm(0), None, "incomplete listing");
        assert_eq!(Command::Offsets.to_bytes(), b"$#\n");
        assert!(Command::Offsets.is_query() && Command::BuildInfo.is_query());
    }

    #[test]
    fn build_version_from_the_ver_line_of_dollar_i() {
        assert_eq!(build_version("VER:1.1h.20190830:"), Some("1.1h.20190830"));
        assert_eq!(
            build_version("VER:1.1f.20170801:My machine"),
            Some("1.1f.20170801")
        );
        assert_eq!(build_version("OPT:V,15,128"), None);
        assert_eq!(build_version("VER::"), None);
        assert_eq!(Command::BuildInfo.encode(), "$I");
    }

    #[test]
    fn commands_encode_to_the_documented_lines() {
        let mv = Command::Move {
            xyz_mm: [Some(1.0), Some(2.5), Some(-0.5)],
            feed_mm_min: Some(600.0),
            relative: false,
        };
        assert_eq!(mv.encode(), "G21 G53 G1 X1.000 Y2.500 Z-0.500 F600.000");
        let rapid = Command::Move {
            xyz_mm: [None, None, Some(-0.0)],
            feed_mm_min: None,
            relative: true,
        };
        assert_eq!(rapid.encode(), "G21 G91 G0 Z0.000");
        assert_eq!(Command::Dwell { seconds: 0.0 }.encode(), "G4 P0.000");
        assert_eq!(Command::Home.to_bytes(), b"$H\n");
        assert_eq!(Command::Unlock.encode(), "$X");
        assert_eq!(Command::Settings.encode(), "$$");
        assert_eq!(
            Command::SetSetting {
                number: 22,
                value: 1.0
            }
            .encode(),
            "$22=1.000"
        );
        let jog = Command::Jog {
            xyz_mm: [Some(0.1), None, None],
            feed_mm_min: 120.0,
            relative: true,
        };
        assert_eq!(jog.encode(), "$J=G21 G91 X0.100 F120.000");
        let probe = Command::Probe {
            xyz_mm: [None, None, Some(-5.0)],
            feed_mm_min: 30.0,
        };
        assert_eq!(probe.encode(), "G21 G91 G38.2 Z-5.000 F30.000");
        assert_eq!(Command::Millimetres.encode(), "G21");
        assert_eq!(Command::Absolute.encode(), "G90");
        assert_eq!(Command::Relative.encode(), "G91");
    }

    #[test]
    fn realtime_bytes_match_the_spec_and_round_trip() {
        let all = [
            (Realtime::StatusQuery, b'?'),
            (Realtime::FeedHold, b'!'),
            (Realtime::CycleStart, b'~'),
            (Realtime::SoftReset, 0x18),
            (Realtime::JogCancel, 0x85),
        ];
        for (rt, b) in all {
            assert_eq!(rt.byte(), b);
            assert_eq!(Realtime::from_byte(b), Some(rt));
        }
        assert_eq!(Realtime::from_byte(b'G'), None);
    }

    #[test]
    fn status_report_from_the_spec_decodes() {
        let r = decode(b"<Idle|MPos:1.000,2.000,-0.500|FS:0,0|WCO:0.000,0.000,0.000>").unwrap();
        let Response::Status(s) = r else {
            panic!("not a status: {r:?}")
        };
        assert_eq!(s.state, Some(MachineState::Idle));
        assert_eq!(s.mpos_mm, Some([1.0, 2.0, -0.5]));
        assert_eq!(s.wco_mm, Some([0.0; 3]));
        assert_eq!(s.feed_mm_min, Some(0.0));
    }

    #[test]
    fn every_state_decodes_including_substates_wpos_and_f_only() {
        let cases = [
            ("Idle", MachineState::Idle),
            ("Run", MachineState::Run),
            ("Hold:0", MachineState::Hold(0)),
            ("Hold:1", MachineState::Hold(1)),
            ("Jog", MachineState::Jog),
            ("Alarm", MachineState::Alarm),
            ("Door:2", MachineState::Door(2)),
            ("Check", MachineState::Check),
            ("Home", MachineState::Home),
            ("Sleep", MachineState::Sleep),
        ];
        for (text, state) in cases {
            let line =
                format!("<{text}|WPos:0.000,-1.250,3.000|F:500|Bf:15,128|Pn:XZ|Ov:100,100,100>");
            let Ok(Response::Status(s)) = decode(line.as_bytes()) else {
                panic!("{line} did not decode")
            };
            assert_eq!(s.state, Some(state));
            assert_eq!(state.to_string(), text);
            assert_eq!(s.wpos_mm, Some([0.0, -1.25, 3.0]));
            assert_eq!(s.mpos_mm, None);
            assert_eq!(s.feed_mm_min, Some(500.0));
            assert_eq!(s.buffer_free, Some((15, 128)));
            assert_eq!(s.pins.as_deref(), Some("XZ"));
        }
    }

    #[test]
    fn pushed_and_reply_lines_decode() {
        assert_eq!(decode(b"ok"), Ok(Response::Ok));
        assert_eq!(decode(b"error:9"), Ok(Response::Error(9)));
        assert_eq!(decode(b"ALARM:2"), Ok(Response::Alarm(2)));
        assert_eq!(
            decode(b"Grbl 1.1h ['$' for help]"),
            Ok(Response::Banner("1.1h".into()))
        );
        assert_eq!(
            decode(b"[MSG:'$H'|'$X' to unlock]"),
            Ok(Response::Message("'$H'|'$X' to unlock".into()))
        );
        assert_eq!(
            decode(b"[PRB:0.000,0.000,-1.500:1]"),
            Ok(Response::Feedback("PRB:0.000,0.000,-1.500:1".into()))
        );
        assert_eq!(
            decode(b"[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]"),
            Ok(Response::ParserState(
                "G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0".into()
            ))
        );
        assert_eq!(
            decode(b"$130=200.000"),
            Ok(Response::Setting {
                number: 130,
                value: "200.000".into()
            })
        );
    }

    #[test]
    fn garbled_lines_are_decode_errors_not_panics() {
        for bad in [
            &b"o"[..],
            b"k",
            b"o\xfek",
            b"<Idle|MPos:1.000,2.000>",
            b"<Idle|MPos:1.000,2.000,3.000",
            b"<Bogus|MPos:0,0,0>",
            b"error:x",
            b"ALARM:",
            b"$abc",
            b"[MSG:unterminated",
        ] {
            assert!(
                decode(bad).is_err(),
                "{:?} must not decode",
                String::from_utf8_lossy(bad)
            );
        }
    }

    #[test]
    fn common_error_and_alarm_codes_have_texts() {
        for code in [1, 2, 3, 5, 8, 9, 15, 20, 22, 33] {
            assert_ne!(error_text(code), "unknown error code");
        }
        for code in 1..=10 {
            assert_ne!(alarm_text(code), "unknown alarm code");
        }
        assert_eq!(error_text(200), "unknown error code");
    }

    proptest::proptest! {
        #[test]
        fn status_reports_of_any_position_decode_to_within_half_a_micron(
            x in -1000.0f64..1000.0, y in -1000.0f64..1000.0, z in -1000.0f64..1000.0, feed in 0u32..30000,
        ) {
            let line = format!("<Run|MPos:{},{},{}|FS:{feed},0>", fmt_num(x), fmt_num(y), fmt_num(z));
            let Ok(Response::Status(s)) = decode(line.as_bytes()) else {
                return Err(proptest::test_runner::TestCaseError::fail(line));
            };
            let p = s.mpos_mm.unwrap();
            for (got, want) in p.iter().zip([x, y, z]) {
                proptest::prop_assert!((got - want).abs() <= 5e-4 + 1e-12);
            }
            proptest::prop_assert_eq!(s.feed_mm_min, Some(f64::from(feed)));
        }
    }
}
