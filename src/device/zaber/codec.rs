//! Zaber ASCII wire codec: pure encoding of commands and decoding of replies,
//! info and alert messages, with the optional LRC checksum.
//!
//! Command: `/[device] [axis] [id] command[:CC]\n`. Reply:
//! `@dd a [id] OK|RJ IDLE|BUSY FLAG data[:CC]\r\n`. Info: `#dd a [id] text`.
//! Alert: `!dd a IDLE|BUSY FLAG [data]`.
//!
//! Checksum (LRC): sum of the bytes after the leading `/`, `@`, `#` or `!` up to
//! (not including) the `:`, modulo 256, two's complement, as two upper-case hex
//! digits. `/2 0 5 get maxspeed` → `52`; `@01 0 OK IDLE -- 0` → `8D`.

use std::fmt;

/// The LRC checksum of a message body (the bytes between the type character and `:`).
pub fn lrc(body: &[u8]) -> u8 {
    let sum = body.iter().fold(0u8, |acc, b| acc.wrapping_add(*b));
    sum.wrapping_neg()
}

/// A command addressed to one device (1..=99; 0 = all) and axis (0 = all axes).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Command {
    /// Device address.
    pub device: u8,
    /// Axis number (0 = the whole device).
    pub axis: u8,
    /// Message id (0..=99) echoed in the reply, if used.
    pub id: Option<u8>,
    /// The command text, e.g. `move abs 10000`, `get pos`, `home`, `` (status).
    pub text: String,
}

impl Command {
    /// A command without message id.
    pub fn new(device: u8, axis: u8, text: impl Into<String>) -> Self {
        Command {
            device,
            axis,
            id: None,
            text: text.into(),
        }
    }

    /// The same command with a message id.
    pub fn with_id(mut self, id: u8) -> Self {
        self.id = Some(id);
        self
    }

    /// The line without terminator, with `:CC` if `checksum`.
    pub fn encode(&self, checksum: bool) -> String {
        let mut body = format!("{} {}", self.device, self.axis);
        if let Some(id) = self.id {
            body.push_str(&format!(" {id}"));
        }
        if !self.text.is_empty() {
            body.push(' ');
            body.push_str(&self.text);
        }
        if checksum {
            let cc = lrc(body.as_bytes());
            format!("/{body}:{cc:02X}")
        } else {
            format!("/{body}")
        }
    }

    /// The bytes on the wire (line + `\n`).
    pub fn to_bytes(&self, checksum: bool) -> Vec<u8> {
        let mut b = self.encode(checksum).into_bytes();
        b.push(b'\n');
        b
    }
}

/// Reply flag.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReplyFlag {
    /// `OK`: accepted.
    Ok,
    /// `RJ`: rejected; the data is the reason.
    Rejected,
}

/// Device / axis status.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Status {
    /// `IDLE`.
    Idle,
    /// `BUSY`: moving.
    Busy,
}

/// A warning flag: two upper-case letters, `--` when none.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Warning(pub [u8; 2]);

impl Warning {
    /// `--`.
    pub const NONE: Warning = Warning(*b"--");
    /// `WR`: no reference position (not homed).
    pub const NOT_HOMED: Warning = Warning(*b"WR");
    /// `NI`: a move was interrupted (e.g. by `stop` or a new command).
    pub const INTERRUPTED: Warning = Warning(*b"NI");
    /// `WL`: unexpected limit trigger.
    pub const LIMIT: Warning = Warning(*b"WL");
    /// `FF`: critical system error / fault.
    pub const FAULT: Warning = Warning(*b"FF");

    /// True for `--`.
    pub fn is_none(self) -> bool {
        self == Warning::NONE
    }

    /// Faults start with `F`, warnings with `W`, notes with `N` (Zaber convention).
    pub fn is_fault(self) -> bool {
        self.0[0] == b'F'
    }

    /// The two characters.
    pub fn as_str(&self) -> &str {
        std::str::from_utf8(&self.0).unwrap_or("??")
    }

    /// What the flag means, for messages.
    pub fn meaning(self) -> &'static str {
        match &self.0 {
            b"--" => "no warning",
            b"WR" => "no reference position (not homed)",
            b"NI" => "move interrupted",
            b"WL" => "unexpected limit trigger",
            b"FF" => "critical system fault",
            b"FS" => "stalled and stopped",
            b"FQ" => "encoder error",
            b"WV" => "voltage out of range",
            b"WT" => "temperature high",
            b"NC" => "manual control",
            _ => "device-specific warning",
        }
    }
}

impl fmt::Display for Warning {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A reply `@..`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Reply {
    /// Device address.
    pub device: u8,
    /// Axis number.
    pub axis: u8,
    /// Message id, if the command had one.
    pub id: Option<u8>,
    /// `OK` or `RJ`.
    pub flag: ReplyFlag,
    /// `IDLE` or `BUSY`.
    pub status: Status,
    /// Highest-priority warning.
    pub warning: Warning,
    /// Data (the value of a `get`, the rejection reason, or `0`).
    pub data: String,
}

impl Reply {
    /// The reply line without terminator, with `:CC` if `checksum`.
    pub fn encode(&self, checksum: bool) -> String {
        let mut body = format!("{:02} {}", self.device, self.axis);
        if let Some(id) = self.id {
            body.push_str(&format!(" {id:02}"));
        }
        body.push_str(match self.flag {
            ReplyFlag::Ok => " OK",
            ReplyFlag::Rejected => " RJ",
        });
        body.push_str(match self.status {
            Status::Idle => " IDLE",
            Status::Busy => " BUSY",
        });
        body.push(' ');
        body.push_str(self.warning.as_str());
        body.push(' ');
        body.push_str(&self.data);
        with_checksum('@', &body, checksum)
    }
}

fn with_checksum(kind: char, body: &str, checksum: bool) -> String {
    if checksum {
        format!("{kind}{body}:{:02X}", lrc(body.as_bytes()))
    } else {
        format!("{kind}{body}")
    }
}

/// One decoded message from a device.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Message {
    /// `@` reply.
    Reply(Reply),
    /// `#` info line (extra lines of a reply, e.g. `help`).
    Info {
        /// Device address.
        device: u8,
        /// Axis.
        axis: u8,
        /// Text after the address.
        text: String,
    },
    /// `!` alert (pushed, when `comm.alert` = 1).
    Alert {
        /// Device address.
        device: u8,
        /// Axis.
        axis: u8,
        /// Status.
        status: Status,
        /// Warning.
        warning: Warning,
    },
}

/// Why a line could not be decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unrecognised zaber message {line:?} ({reason})")]
pub struct DecodeError {
    /// The offending line.
    pub line: String,
    /// What was wrong.
    pub reason: &'static str,
}

/// Decodes one line (terminator stripped). A checksum, when present, must match.
pub fn decode(line: &[u8]) -> Result<Message, DecodeError> {
    let err = |reason| DecodeError {
        line: String::from_utf8_lossy(line).into_owned(),
        reason,
    };
    if !line.iter().all(|b| (0x20..0x7f).contains(b)) {
        return Err(err("non-ASCII or control bytes"));
    }
    let s = std::str::from_utf8(line)
        .map_err(|_| err("not UTF-8"))?
        .trim_end();
    let mut chars = s.chars();
    let kind = chars.next().ok_or_else(|| err("empty"))?;
    let rest = chars.as_str();
    // A checksum is `:` + 2 hex digits at the very end.
    let body = match rest
        .len()
        .checked_sub(3)
        .and_then(|i| rest.get(i..).map(|t| (i, t)))
    {
        Some((i, tail))
            if tail.starts_with(':') && tail[1..].chars().all(|c| c.is_ascii_hexdigit()) =>
        {
            let cc = u8::from_str_radix(&tail[1..], 16).map_err(|_| err("bad checksum digits"))?;
            let body = &rest[..i];
            if lrc(body.as_bytes()) != cc {
                return Err(err("checksum mismatch"));
            }
            body
        }
        _ => rest,
    };
    let mut tok = body.split(' ');
    let device: u8 = tok
        .next()
        .filter(|t| t.len() == 2)
        .and_then(|t| t.parse().ok())
        .ok_or_else(|| err("bad device address"))?;
    let axis: u8 = tok
        .next()
        .and_then(|t| t.parse().ok())
        .ok_or_else(|| err("bad axis"))?;
    let parse_status = |t: Option<&str>| match t {
        Some("IDLE") => Ok(Status::Idle),
        Some("BUSY") => Ok(Status::Busy),
        _ => Err(err("bad status")),
    };
    let parse_warning = |t: Option<&str>| match t {
        Some(w) if w.len() == 2 && (w == "--" || w.chars().all(|c| c.is_ascii_uppercase())) => {
            let b = w.as_bytes();
            Ok(Warning([b[0], b[1]]))
        }
        _ => Err(err("bad warning flag")),
    };
    match kind {
        '@' => {
            let mut t = tok.next();
            let mut id = None;
            if let Some(v) = t.filter(|v| v.chars().all(|c| c.is_ascii_digit())) {
                id = Some(v.parse().map_err(|_| err("bad message id"))?);
                t = tok.next();
            }
            let flag = match t {
                Some("OK") => ReplyFlag::Ok,
                Some("RJ") => ReplyFlag::Rejected,
                _ => return Err(err("bad reply flag")),
            };
            let status = parse_status(tok.next())?;
            let warning = parse_warning(tok.next())?;
            let data = tok.collect::<Vec<_>>().join(" ");
            if data.is_empty() {
                return Err(err("missing data"));
            }
            Ok(Message::Reply(Reply {
                device,
                axis,
                id,
                flag,
                status,
                warning,
                data,
            }))
        }
        '#' => Ok(Message::Info {
            device,
            axis,
            text: tok.collect::<Vec<_>>().join(" "),
        }),
        '!' => {
            let status = parse_status(tok.next())?;
            let warning = parse_warning(tok.next())?;
            Ok(Message::Alert {
                device,
                axis,
                status,
                warning,
            })
        }
        _ => Err(err("unknown message type")),
    }
}

/// Encodes an alert line (for the simulator).
pub fn encode_alert(
    device: u8,
    axis: u8,
    status: Status,
    warning: Warning,
    checksum: bool,
) -> String {
    let st = match status {
        Status::Idle => "IDLE",
        Status::Busy => "BUSY",
    };
    with_checksum('!', &format!("{device:02} {axis} {st} {warning}"), checksum)
}

/// Encodes an info line (for the simulator).
pub fn encode_info(device: u8, axis: u8, text: &str, checksum: bool) -> String {
    with_checksum('#', &format!("{device:02} {axis} {text}"), checksum)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checksum_examples_from_the_spec() {
        let cmd = Command::new(2, 0, "get maxspeed").with_id(5);
        assert_eq!(cmd.encode(true), "/2 0 5 get maxspeed:52");
        assert_eq!(lrc(b"01 0 OK IDLE -- 0"), 0x8D);
        let r = decode(b"@01 0 OK IDLE -- 0:8D").unwrap();
        let Message::Reply(r) = r else {
            panic!("not a reply")
        };
        assert_eq!((r.device, r.axis, r.id), (1, 0, None));
        assert_eq!(r.encode(true), "@01 0 OK IDLE -- 0:8D");
    }

    #[test]
    fn bad_checksum_is_rejected() {
        assert_eq!(
            decode(b"@01 0 OK IDLE -- 0:8E").unwrap_err().reason,
            "checksum mismatch"
        );
        assert_eq!(
            decode(b"@01 0 OK IDLE -- 1:8D").unwrap_err().reason,
            "checksum mismatch"
        );
    }

    #[test]
    fn commands_encode_per_the_spec() {
        assert_eq!(Command::new(1, 0, "home").encode(false), "/1 0 home");
        assert_eq!(
            Command::new(2, 1, "move abs 10000").encode(false),
            "/2 1 move abs 10000"
        );
        assert_eq!(
            Command::new(1, 0, "get pos").to_bytes(false),
            b"/1 0 get pos\n"
        );
        assert_eq!(Command::new(1, 1, "").with_id(7).encode(false), "/1 1 7");
    }

    #[test]
    fn replies_round_trip_with_and_without_ids_and_checksums() {
        let replies = [
            Reply {
                device: 1,
                axis: 1,
                id: Some(42),
                flag: ReplyFlag::Ok,
                status: Status::Busy,
                warning: Warning::NOT_HOMED,
                data: "0".into(),
            },
            Reply {
                device: 12,
                axis: 2,
                id: None,
                flag: ReplyFlag::Rejected,
                status: Status::Idle,
                warning: Warning::NONE,
                data: "BADDATA".into(),
            },
            Reply {
                device: 3,
                axis: 1,
                id: Some(0),
                flag: ReplyFlag::Ok,
                status: Status::Idle,
                warning: Warning::INTERRUPTED,
                data: "-123456".into(),
            },
        ];
        for r in replies {
            for cs in [false, true] {
                let line = r.encode(cs);
                assert_eq!(
                    decode(line.as_bytes()),
                    Ok(Message::Reply(r.clone())),
                    "{line}"
                );
            }
        }
        assert_eq!(
            decode(b"@01 1 07 OK IDLE -- 0"),
            Ok(Message::Reply(Reply {
                device: 1,
                axis: 1,
                id: Some(7),
                flag: ReplyFlag::Ok,
                status: Status::Idle,
                warning: Warning::NONE,
                data: "0".into()
            }))
        );
    }

    #[test]
    fn info_and_alerts_decode() {
        assert_eq!(
            decode(b"#01 0 COMMAND home").unwrap(),
            Message::Info {
                device: 1,
                axis: 0,
                text: "COMMAND home".into()
            }
        );
        let line = encode_alert(1, 1, Status::Idle, Warning::NONE, true);
        assert_eq!(
            decode(line.as_bytes()).unwrap(),
            Message::Alert {
                device: 1,
                axis: 1,
                status: Status::Idle,
                warning: Warning::NONE
            }
        );
    }

    #[test]
    fn garbled_lines_are_errors() {
        for bad in [
            &b"@1 0 OK IDLE -- 0"[..],
            b"@01 0 OK",
            b"@01 0 XX IDLE -- 0",
            b"@01 0 OK IDLE -- ",
            b"$01",
            b"@01 0 OK IDLE w- 0",
            b"@01 \xfe OK",
        ] {
            assert!(decode(bad).is_err(), "{:?}", String::from_utf8_lossy(bad));
        }
    }

    proptest::proptest! {
        #[test]
        fn any_reply_round_trips_with_and_without_checksum(
            device in 1u8..=99,
            axis in 0u8..=9,
            id in proptest::option::of(0u8..=99),
            rejected: bool,
            busy: bool,
            w in 0usize..5,
            data in -2_000_000_000i64..2_000_000_000,
            checksum: bool,
        ) {
            let warnings = [Warning::NONE, Warning::NOT_HOMED, Warning::INTERRUPTED, Warning::LIMIT, Warning::FAULT];
            let r = Reply {
                device,
                axis,
                id,
                flag: if rejected { ReplyFlag::Rejected } else { ReplyFlag::Ok },
                status: if busy { Status::Busy } else { Status::Idle },
                warning: warnings[w],
                data: data.to_string(),
            };
            let line = r.encode(checksum);
            proptest::prop_assert_eq!(decode(line.as_bytes()), Ok(Message::Reply(r)));
        }

        #[test]
        fn checksummed_commands_verify_under_the_lrc(device in 0u8..=99, axis in 0u8..=9, steps: i32) {
            let line = Command::new(device, axis, format!("move abs {steps}")).encode(true);
            let (body, cc) = line[1..].rsplit_once(':').unwrap();
            let sum = body.bytes().fold(0u32, |a, b| a + u32::from(b)) + u32::from(u8::from_str_radix(cc, 16).unwrap());
            // Body plus checksum sums to 0 mod 256: the LRC definition.
            proptest::prop_assert_eq!(sum % 256, 0);
        }
    }
}
