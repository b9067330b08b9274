//! Marlin wire codec: pure framing of host lines and decoding of the firmware's lines.
//!
//! Framing (see `protocols/marlin.md`, written from Marlin's `gcode/queue.cpp`): a
//! host line is `N<n> <command>*<checksum>` where the checksum is the XOR of every byte
//! before the `*`, written in decimal. `M110 N<n>` sets the firmware's line counter.
//! The firmware answers every accepted line with `ok` (possibly followed by more text:
//! `ok N12 P15 B3` with `ADVANCED_OK`, `ok X:.. Y:..` on firmware variants that put the
//! position into the acknowledgement). A line it could not take gets an `Error:`
//! line naming the reason and the last good line, then `Resend: <n>` and `ok`.
//!
//! Numbers are written with 4 decimals: 0.1 µm, finer than any printer's step
//! (a 400 steps/mm z axis has 2.5 µm steps); the driver rounds targets to whole steps
//! before formatting them.

use std::fmt;

/// XOR of the bytes: Marlin's line checksum (`queue.cpp`: `checksum ^= command[--count]`).
pub fn checksum(bytes: &[u8]) -> u8 {
    bytes.iter().fold(0u8, |a, b| a ^ b)
}

/// A host line with line number and checksum, without the terminating `\n`:
/// `N<n> <cmd>*<cs>`.
pub fn frame(n: u32, cmd: &str) -> String {
    let body = format!("N{n} {cmd}");
    let cs = checksum(body.as_bytes());
    format!("{body}*{cs}")
}

/// The `M110 N0` line that resets the firmware's line counter, framed as line 0
/// (`N0 M110 N0*125`): the firmware takes the counter from the second `N`.
pub fn reset_line_numbers() -> String {
    frame(0, "M110 N0")
}

/// Formats a length or rate with 4 decimals, never as `-0.0000`.
pub fn fmt_num(v: f64) -> String {
    let s = format!("{v:.4}");
    if s == "-0.0000" {
        "0.0000".to_string()
    } else {
        s
    }
}

/// A straight move, `G0` (no feed rate: the firmware's rapid rate) or `G1 .. F<mm/min>`,
/// absolute (`G90` mode, set at connect).
pub fn move_command(xyz_mm: [f64; 3], feed_mm_min: Option<f64>) -> String {
    let mut s = String::from(if feed_mm_min.is_some() { "G1" } else { "G0" });
    for (letter, v) in ['X', 'Y', 'Z'].iter().zip(xyz_mm) {
        s.push(' ');
        s.push(*letter);
        s.push_str(&fmt_num(v));
    }
    if let Some(f) = feed_mm_min {
        s.push_str(" F");
        s.push_str(&fmt_num(f));
    }
    s
}

/// An `Error:` line, by what it says.
#[derive(Debug, Clone, PartialEq)]
pub enum ErrorLine {
    /// `Error:checksum mismatch, Last Line: <n>`.
    Checksum {
        /// The last line the firmware accepted.
        last: u32,
    },
    /// `Error:Line Number is not Last Line Number+1, Last Line: <n>`.
    LineNumber {
        /// The last line the firmware accepted.
        last: u32,
    },
    /// `Error:No Checksum with line number, Last Line: <n>`.
    NoChecksum {
        /// The last line the firmware accepted.
        last: u32,
    },
    /// `Error:Printer halted. kill() called!`: M112 or a fatal fault; needs a reset.
    Halted,
    /// `Error:Printer stopped due to errors. Fix the error and use M999 to restart. ...`
    Stopped,
    /// Any other `Error:` text.
    Other(String),
}

/// The position report of `M114`: `X:10.00 Y:20.00 Z:5.00 E:0.00 Count X:800 Y:1600 Z:2000`.
#[derive(Debug, Clone, PartialEq)]
pub struct PositionReport {
    /// Logical X, Y, Z in mm (2 decimals on the wire).
    pub xyz_mm: [f64; 3],
    /// The planner's position in steps (`Count X: Y: Z:`), when reported for X/Y/Z
    /// (core kinematics report `Count A: B: C:`, which are motor counts, not axes).
    pub count_steps: Option<[i64; 3]>,
}

/// One line from the firmware.
#[derive(Debug, Clone, PartialEq)]
pub enum Reply {
    /// `ok`, with whatever follows it on the line (trimmed, may be empty).
    Ok(String),
    /// `Resend: <n>` (also the short `rs <n>`).
    Resend(u32),
    /// `Error:...`.
    Error(ErrorLine),
    /// `echo:busy: processing` and the other `busy:` keep-alives (the text after `busy:`).
    Busy(String),
    /// `start`: the firmware (re)booted.
    Start,
    /// `wait`: idle and waiting for commands (`NO_TIMEOUTS`).
    Wait,
    /// A position report (`M114`).
    Position(PositionReport),
    /// Any other `echo:` line (the text after `echo:`).
    Echo(String),
    /// Anything else printable (`FIRMWARE_NAME:..`, `Cap:..`, `//action:..`, ...).
    Other(String),
}

/// A line that cannot be a Marlin line: not UTF-8 or with control bytes (noise, a
/// wrong baud rate, a garbled reply).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Garbled(pub Vec<u8>);

impl fmt::Display for Garbled {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "garbled line {:?}", String::from_utf8_lossy(&self.0))
    }
}

fn last_line(text: &str) -> Option<u32> {
    let (_, tail) = text.rsplit_once("Last Line:")?;
    tail.trim().parse().ok()
}

/// Decodes one line (terminator stripped).
pub fn decode(line: &[u8]) -> Result<Reply, Garbled> {
    let Ok(text) = std::str::from_utf8(line) else {
        return Err(Garbled(line.to_vec()));
    };
    if text.chars().any(|c| c.is_control() && c != '\t') {
        return Err(Garbled(line.to_vec()));
    }
    let t = text.trim();
    if t == "ok" || t.starts_with("ok ") {
        return Ok(Reply::Ok(t[2..].trim().to_string()));
    }
    if let Some(r) = t.strip_prefix("Resend:").or_else(|| t.strip_prefix("rs ")) {
        return r
            .trim()
            .parse()
            .map(Reply::Resend)
            .map_err(|_| Garbled(line.to_vec()));
    }
    if let Some(e) = t.strip_prefix("Error:").or_else(|| t.strip_prefix("!!")) {
        let e = e.trim();
        let last = last_line(e);
        let err = if e.starts_with("checksum mismatch") {
            last.map(|last| ErrorLine::Checksum { last })
        } else if e.starts_with("Line Number is not Last Line Number+1") {
            last.map(|last| ErrorLine::LineNumber { last })
        } else if e.starts_with("No Checksum with line number") {
            last.map(|last| ErrorLine::NoChecksum { last })
        } else if e.starts_with("Printer halted") {
            Some(ErrorLine::Halted)
        } else if e.starts_with("Printer stopped due to errors") {
            Some(ErrorLine::Stopped)
        } else {
            None
        };
        return Ok(Reply::Error(
            err.unwrap_or_else(|| ErrorLine::Other(e.to_string())),
        ));
    }
    if t == "start" {
        return Ok(Reply::Start);
    }
    if t == "wait" {
        return Ok(Reply::Wait);
    }
    if let Some(e) = t.strip_prefix("echo:") {
        if let Some(b) = e.trim_start().strip_prefix("busy:") {
            return Ok(Reply::Busy(b.trim().to_string()));
        }
        return Ok(Reply::Echo(e.to_string()));
    }
    if let Some(b) = t.strip_prefix("busy:") {
        return Ok(Reply::Busy(b.trim().to_string()));
    }
    if let Some(p) = parse_position(t) {
        return Ok(Reply::Position(p));
    }
    Ok(Reply::Other(t.to_string()))
}

/// Parses `X:<v> Y:<v> Z:<v> [E:<v>] [Count X:<n> Y:<n> Z:<n>]` (spaces after the colons
/// are allowed: some firmware prints `X: 10.00`). `None` unless X, Y and Z are present.
pub fn parse_position(text: &str) -> Option<PositionReport> {
    let (head, count) = match text.find("Count") {
        Some(i) => (&text[..i], Some(&text[i + "Count".len()..])),
        None => (text, None),
    };
    let xyz = axis_values(head)?;
    let count_steps = count.and_then(|c| {
        let v = axis_values(c)?;
        let mut out = [0i64; 3];
        for (o, x) in out.iter_mut().zip(v) {
            if x.fract() != 0.0 || !x.is_finite() {
                return None;
            }
            *o = x as i64;
        }
        Some(out)
    });
    Some(PositionReport {
        xyz_mm: xyz,
        count_steps,
    })
}

/// Values of `X:`, `Y:`, `Z:` (with or without the colon, e.g. `X80.00` in `M92`
/// reports) in `text`; `None` unless all three are there and finite.
fn axis_values(text: &str) -> Option<[f64; 3]> {
    let mut out = [None; 3];
    let tokens: Vec<&str> = text.split_whitespace().collect();
    let mut i = 0;
    while i < tokens.len() {
        let tok = tokens[i];
        let mut chars = tok.chars();
        let letter = chars.next()?;
        let idx = match letter {
            'X' => Some(0),
            'Y' => Some(1),
            'Z' => Some(2),
            _ => None,
        };
        if let Some(idx) = idx {
            let rest = chars.as_str();
            let rest = rest.strip_prefix(':').unwrap_or(rest);
            let value = if rest.is_empty() {
                // `X: 10.00`: the value is the next token.
                i += 1;
                tokens.get(i).copied()
            } else {
                Some(rest)
            };
            if let Some(v) = value.and_then(|v| v.parse::<f64>().ok()) {
                if out[idx].is_none() && v.is_finite() {
                    out[idx] = Some(v);
                }
            }
        }
        i += 1;
    }
    Some([out[0]?, out[1]?, out[2]?])
}

/// Soft endstops as reported by `M211`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SoftEndstops {
    /// Whether the firmware enforces them (by clamping targets).
    pub enabled: bool,
    /// Lower limits X, Y, Z, mm (logical).
    pub min_mm: [f64; 3],
    /// Upper limits X, Y, Z, mm (logical).
    pub max_mm: [f64; 3],
}

/// Parses the lines `M211` printed. Both report styles of Marlin's `M211.cpp`:
/// `echo:Soft endstops: On  Min:  X0.00 Y0.00 Z0.00   Max:  X200.00 Y200.00 Z200.00`
/// (one line, 1.1 / 2.0) and
/// `echo:; Soft Endstops:` / `echo:  M211 S1 ; ON` / `echo:  Min:  X0.00 Y0.00 Z0.00   Max:  X200.00 ...`
/// (2.1). `None` when no Min/Max line was seen.
pub fn parse_soft_endstops(lines: &[String]) -> Option<SoftEndstops> {
    let mut enabled = None;
    let mut limits = None;
    for l in lines {
        let lower = l.to_ascii_lowercase();
        if let Some(i) = lower.find("m211 s") {
            match lower[i + 6..].chars().next() {
                Some('1') => enabled = Some(true),
                Some('0') => enabled = Some(false),
                _ => {}
            }
        }
        if let Some(i) = lower.find("soft endstops:") {
            let rest = lower[i + "soft endstops:".len()..].trim_start();
            if rest.starts_with("on") {
                enabled = Some(true);
            } else if rest.starts_with("off") {
                enabled = Some(false);
            }
        }
        if let (Some(a), Some(b)) = (l.find("Min:"), l.find("Max:")) {
            if a < b {
                let min = axis_values(&l[a + 4..b]);
                let max = axis_values(&l[b + 4..]);
                if let (Some(min), Some(max)) = (min, max) {
                    limits = Some((min, max));
                }
            }
        }
    }
    let (min_mm, max_mm) = limits?;
    Some(SoftEndstops {
        enabled: enabled.unwrap_or(true),
        min_mm,
        max_mm,
    })
}

/// Parses a settings report line such as `echo:  M92 X80.00 Y80.00 Z400.00 E500.00`
/// (steps per mm) or `echo:  M203 X300.00 Y300.00 Z5.00 E25.00` (maximum feed rates,
/// mm/s): the X, Y, Z values after `code`.
pub fn parse_setting(lines: &[String], code: &str) -> Option<[f64; 3]> {
    for l in lines {
        let mut words = l.split_whitespace().skip_while(|w| {
            let w = w.trim_start_matches("echo:");
            w != code
        });
        if words.next().is_some() {
            let rest: Vec<&str> = words.collect();
            if let Some(v) = axis_values(&rest.join(" ")) {
                return Some(v);
            }
        }
    }
    None
}

/// Capabilities from the `M115` report (`Cap:EMERGENCY_PARSER:1`), and the firmware name.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Capabilities {
    /// `FIRMWARE_NAME:` value up to the next key (e.g. `Marlin 2.1.2.1 (Jul 11 2023 12:00:00)`).
    pub firmware: Option<String>,
    /// `Cap:NAME:0|1` pairs.
    pub caps: Vec<(String, bool)>,
}

impl Capabilities {
    /// Whether capability `name` is reported as 1.
    pub fn has(&self, name: &str) -> bool {
        self.caps.iter().any(|(n, v)| n == name && *v)
    }
}

/// Parses the lines `M115` printed.
pub fn parse_capabilities(lines: &[String]) -> Capabilities {
    let mut c = Capabilities::default();
    for l in lines {
        let l = l.trim();
        if let Some(rest) = l.strip_prefix("FIRMWARE_NAME:") {
            let end = rest
                .find(" SOURCE_CODE_URL:")
                .or_else(|| rest.find(" FIRMWARE_URL:"))
                .or_else(|| rest.find(" PROTOCOL_VERSION:"))
                .unwrap_or(rest.len());
            c.firmware = Some(rest[..end].trim().to_string());
        } else if let Some(rest) = l.strip_prefix("Cap:") {
            if let Some((name, v)) = rest.rsplit_once(':') {
                c.caps.push((name.to_string(), v.trim() == "1"));
            }
        }
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_match_the_checksum_hosts_and_marlin_compute() {
        // The line every host sends first; its checksum is well known (125).
        assert_eq!(reset_line_numbers(), "N0 M110 N0*125");
        let f = frame(7, "G1 X1.0000 Y2.0000 Z3.0000 F600.0000");
        let (body, cs) = f.rsplit_once('*').unwrap();
        assert_eq!(cs.parse::<u8>().unwrap(), checksum(body.as_bytes()));
        assert_eq!(fmt_num(-0.00001), "0.0000");
        assert_eq!(
            move_command([1.0, -2.5, 0.0125], Some(600.0)),
            "G1 X1.0000 Y-2.5000 Z0.0125 F600.0000"
        );
        assert_eq!(move_command([0.0; 3], None), "G0 X0.0000 Y0.0000 Z0.0000");
    }

    #[test]
    fn decodes_marlins_reply_lines() {
        assert_eq!(decode(b"ok").unwrap(), Reply::Ok(String::new()));
        assert_eq!(
            decode(b"ok N12 P15 B3").unwrap(),
            Reply::Ok("N12 P15 B3".into())
        );
        assert_eq!(decode(b"Resend: 5").unwrap(), Reply::Resend(5));
        assert_eq!(decode(b"rs 5").unwrap(), Reply::Resend(5));
        assert_eq!(
            decode(b"Error:checksum mismatch, Last Line: 4").unwrap(),
            Reply::Error(ErrorLine::Checksum { last: 4 })
        );
        assert_eq!(
            decode(b"Error:Line Number is not Last Line Number+1, Last Line: 9").unwrap(),
            Reply::Error(ErrorLine::LineNumber { last: 9 })
        );
        assert_eq!(
            decode(b"Error:No Checksum with line number, Last Line: 0").unwrap(),
            Reply::Error(ErrorLine::NoChecksum { last: 0 })
        );
        assert_eq!(
            decode(b"Error:Printer halted. kill() called!").unwrap(),
            Reply::Error(ErrorLine::Halted)
        );
        assert_eq!(
            decode(b"echo:busy: processing").unwrap(),
            Reply::Busy("processing".into())
        );
        assert_eq!(decode(b"start").unwrap(), Reply::Start);
        assert_eq!(
            decode(b"echo:Home XYZ first").unwrap(),
            Reply::Echo("Home XYZ first".into())
        );
        assert!(decode(b"o\xffk").is_err());
        assert!(decode(b"o\x01k").is_err());
    }

    #[test]
    fn parses_m114_with_and_without_counts() {
        let Reply::Position(p) =
            decode(b"X:10.00 Y:20.00 Z:5.00 E:0.00 Count X:800 Y:1600 Z:2000").unwrap()
        else {
            panic!("position expected")
        };
        assert_eq!(p.xyz_mm, [10.0, 20.0, 5.0]);
        assert_eq!(p.count_steps, Some([800, 1600, 2000]));
        // OctoPrint's virtual printer and core kinematics: counts of motors A B C.
        let p = parse_position("X:10.0 Y:20.0 Z:5.0 E:0 Count: A:1 B:2 C:3").unwrap();
        assert_eq!(p.xyz_mm, [10.0, 20.0, 5.0]);
        assert_eq!(p.count_steps, None);
        let p = parse_position("X: 1.50 Y: -2.00 Z: 0.25 E: 0.00").unwrap();
        assert_eq!(p.xyz_mm, [1.5, -2.0, 0.25]);
        assert!(parse_position("X:1 Y:2").is_none());
    }

    #[test]
    fn parses_both_m211_report_styles_and_settings() {
        let old = vec![
            "Soft endstops: On  Min:  X0.00 Y0.00 Z0.00   Max:  X200.00 Y210.00 Z120.00"
                .to_string(),
        ];
        let s = parse_soft_endstops(&old).unwrap();
        assert!(s.enabled);
        assert_eq!(s.min_mm, [0.0; 3]);
        assert_eq!(s.max_mm, [200.0, 210.0, 120.0]);
        let new = vec![
            "; Soft Endstops:".to_string(),
            "  M211 S0 ; OFF".to_string(),
            "  Min:  X-5.00 Y0.00 Z0.00   Max:  X200.00 Y200.00 Z100.00".to_string(),
        ];
        let s = parse_soft_endstops(&new).unwrap();
        assert!(!s.enabled);
        assert_eq!(s.min_mm, [-5.0, 0.0, 0.0]);
        let m92 = vec![
            "; Steps per unit:".to_string(),
            "  M92 X80.00 Y80.00 Z400.00 E500.00".to_string(),
        ];
        assert_eq!(parse_setting(&m92, "M92"), Some([80.0, 80.0, 400.0]));
        assert_eq!(parse_setting(&m92, "M203"), None);
        let caps = parse_capabilities(&[
            "FIRMWARE_NAME:Marlin 2.1.2.1 (Jul 11 2023) SOURCE_CODE_URL:github.com/MarlinFirmware/Marlin PROTOCOL_VERSION:1.0".into(),
            "Cap:EMERGENCY_PARSER:1".into(),
            "Cap:AUTOREPORT_POS:0".into(),
        ]);
        assert_eq!(
            caps.firmware.as_deref(),
            Some("Marlin 2.1.2.1 (Jul 11 2023)")
        );
        assert!(caps.has("EMERGENCY_PARSER") && !caps.has("AUTOREPORT_POS"));
    }
}
