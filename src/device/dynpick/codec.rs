//! WACOH DynPick wire codec (pure, no I/O): single-byte commands and the ASCII replies.
//!
//! Record (reply to `R`), 27 bytes: one counter digit, six 4-digit upper-case hex
//! channel values (Fx Fy Fz Mx My Mz), CR LF. Channel value in physical units:
//!
//! ```text
//! value = (raw − 8192) / sensitivity      [N for forces, N·m for torques]
//! ```
//!
//! with the sensitivities (LSB per N, LSB per N·m) from the `p` reply: six
//! comma-separated decimal numbers and CR LF. See `protocols/dynpick.md`.

use std::fmt;

use crate::device::Wrench;

/// Record length in bytes, CR LF included.
pub const RECORD_LEN: usize = 27;
/// Raw value of zero load.
pub const RAW_ZERO: u16 = 8192;
/// Largest raw value (the converter is 14-bit: 0..=16383); the simulator saturates here.
pub const RAW_MAX: u16 = 0x3FFF;

/// Filter divider (`nF`, n = 1, 2, 4, 8).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FilterDivider {
    /// No averaging.
    D1,
    /// Average of 2 samples.
    D2,
    /// Average of 4 samples.
    D4,
    /// Average of 8 samples.
    D8,
}

impl FilterDivider {
    /// From the divider value; `None` unless 1, 2, 4 or 8.
    pub fn from_n(n: u32) -> Option<Self> {
        match n {
            1 => Some(Self::D1),
            2 => Some(Self::D2),
            4 => Some(Self::D4),
            8 => Some(Self::D8),
            _ => None,
        }
    }
    /// The divider value.
    pub fn n(self) -> u32 {
        match self {
            Self::D1 => 1,
            Self::D2 => 2,
            Self::D4 => 4,
            Self::D8 => 8,
        }
    }
}

/// A host command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Command {
    /// `R`: one record.
    Read,
    /// `p`: the six sensitivities.
    Sensitivities,
    /// `O`: zero the offset at the current load (no reply).
    ZeroOffset,
    /// `V`: firmware version line.
    Version,
    /// `nF`: set the filter divider (no reply).
    SetFilter(FilterDivider),
    /// `0F`: read the filter divider back (one line with the digit).
    GetFilter,
    /// `S`: start continuous output (a record per internal sample until `E`).
    StartContinuous,
    /// `E`: end continuous output (no reply).
    StopContinuous,
}

impl Command {
    /// The bytes sent.
    pub fn encode(self) -> Vec<u8> {
        match self {
            Command::Read => b"R".to_vec(),
            Command::Sensitivities => b"p".to_vec(),
            Command::ZeroOffset => b"O".to_vec(),
            Command::Version => b"V".to_vec(),
            Command::SetFilter(d) => format!("{}F", d.n()).into_bytes(),
            Command::GetFilter => b"0F".to_vec(),
            Command::StartContinuous => b"S".to_vec(),
            Command::StopContinuous => b"E".to_vec(),
        }
    }
    /// The command as text, for error messages.
    pub fn text(self) -> String {
        String::from_utf8_lossy(&self.encode()).into_owned()
    }
    /// Whether the device answers this command with a line.
    pub fn has_reply(self) -> bool {
        !matches!(
            self,
            Command::ZeroOffset | Command::SetFilter(_) | Command::StopContinuous
        )
    }
}

/// A reply that does not follow the protocol.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CodecError {
    /// A record of the wrong length.
    #[error("record has {len} bytes, expected {RECORD_LEN}: `{bytes}`")]
    RecordLength {
        /// Bytes received.
        len: usize,
        /// The bytes, escaped.
        bytes: String,
    },
    /// A record with a bad character.
    #[error("record byte {index} is {found:?}, expected {expected}: `{bytes}`")]
    RecordChar {
        /// Byte index in the record.
        index: usize,
        /// What was found.
        found: char,
        /// What was expected.
        expected: &'static str,
        /// The bytes, escaped.
        bytes: String,
    },
    /// A sensitivity line that does not hold six positive numbers.
    #[error("sensitivity line `{bytes}` is not six positive comma-separated numbers")]
    Sensitivities {
        /// The bytes, escaped.
        bytes: String,
    },
    /// A reply of the wrong kind (a data record where a text line was expected).
    #[error("expected another reply, got {what}: `{bytes}`")]
    Unexpected {
        /// What arrived.
        what: &'static str,
        /// The bytes, escaped.
        bytes: String,
    },
    /// A filter read-back that is not 1, 2, 4 or 8.
    #[error("filter read-back `{bytes}` is not 1, 2, 4 or 8")]
    Filter {
        /// The bytes, escaped.
        bytes: String,
    },
}

/// One decoded record: counter digit and six raw channel values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Record {
    /// Counter digit 0–9 (increments per record, wraps).
    pub counter: u8,
    /// Raw values Fx Fy Fz Mx My Mz.
    pub raw: [u16; 6],
}

fn hex_digit(b: u8) -> Option<u16> {
    match b {
        b'0'..=b'9' => Some((b - b'0') as u16),
        b'A'..=b'F' => Some((b - b'A' + 10) as u16),
        b'a'..=b'f' => Some((b - b'a' + 10) as u16),
        _ => None,
    }
}

impl Record {
    /// The 27 bytes on the wire.
    pub fn encode(&self) -> [u8; RECORD_LEN] {
        let mut out = [0u8; RECORD_LEN];
        out[0] = b'0' + self.counter % 10;
        const HEX: &[u8; 16] = b"0123456789ABCDEF";
        for (ch, &v) in self.raw.iter().enumerate() {
            for k in 0..4 {
                out[1 + 4 * ch + k] = HEX[((v >> (12 - 4 * k)) & 0xF) as usize];
            }
        }
        out[25] = b'\r';
        out[26] = b'\n';
        out
    }

    /// Decodes exactly one record (27 bytes, CR LF included).
    pub fn decode(bytes: &[u8]) -> Result<Record, CodecError> {
        let shown = || super::super::ft_common::show_bytes(bytes);
        if bytes.len() != RECORD_LEN {
            return Err(CodecError::RecordLength {
                len: bytes.len(),
                bytes: shown(),
            });
        }
        let bad = |index: usize, expected: &'static str| CodecError::RecordChar {
            index,
            found: bytes[index] as char,
            expected,
            bytes: shown(),
        };
        if !bytes[0].is_ascii_digit() {
            return Err(bad(0, "a counter digit"));
        }
        let mut raw = [0u16; 6];
        for (ch, r) in raw.iter_mut().enumerate() {
            let mut v = 0u16;
            for k in 0..4 {
                let i = 1 + 4 * ch + k;
                let d = hex_digit(bytes[i]).ok_or_else(|| bad(i, "a hex digit"))?;
                v = (v << 4) | d;
            }
            *r = v;
        }
        if bytes[25] != b'\r' {
            return Err(bad(25, "CR"));
        }
        if bytes[26] != b'\n' {
            return Err(bad(26, "LF"));
        }
        Ok(Record {
            counter: bytes[0] - b'0',
            raw,
        })
    }

    /// Physical wrench: `(raw − 8192) / sensitivity` per channel.
    pub fn to_wrench(&self, s: &Sensitivities) -> Wrench {
        let v: Vec<f64> = (0..6)
            .map(|i| (self.raw[i] as f64 - RAW_ZERO as f64) / s.0[i])
            .collect();
        Wrench {
            force_n: [v[0], v[1], v[2]],
            torque_nm: [v[3], v[4], v[5]],
        }
    }

    /// Raw values for a wrench (rounded, saturated to `0..=RAW_MAX`): the inverse of
    /// [`Record::to_wrench`] up to quantisation (1 LSB = 1/sensitivity).
    pub fn raw_from_wrench(w: &Wrench, s: &Sensitivities) -> [u16; 6] {
        let v = [
            w.force_n[0],
            w.force_n[1],
            w.force_n[2],
            w.torque_nm[0],
            w.torque_nm[1],
            w.torque_nm[2],
        ];
        let mut raw = [0u16; 6];
        for i in 0..6 {
            let r = (RAW_ZERO as f64 + v[i] * s.0[i]).round();
            raw[i] = if r.is_nan() {
                RAW_ZERO
            } else {
                r.clamp(0.0, RAW_MAX as f64) as u16
            };
        }
        raw
    }
}

/// Sensitivities: LSB per N for Fx Fy Fz, LSB per N·m for Mx My Mz.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sensitivities(pub [f64; 6]);

impl Sensitivities {
    /// The reply line to `p`: values with 3 decimals, comma-separated, CR LF.
    pub fn encode(&self) -> Vec<u8> {
        let parts: Vec<String> = self.0.iter().map(|v| format!("{v:.3}")).collect();
        format!("{}\r\n", parts.join(",")).into_bytes()
    }

    /// Parses a `p` reply (CR LF optional). All six values must be finite and > 0
    /// (they are divisors).
    pub fn decode(line: &[u8]) -> Result<Sensitivities, CodecError> {
        let err = || CodecError::Sensitivities {
            bytes: super::super::ft_common::show_bytes(line),
        };
        let text = std::str::from_utf8(line).map_err(|_| err())?;
        let parts: Vec<&str> = text.trim_end_matches(['\r', '\n']).split(',').collect();
        if parts.len() != 6 {
            return Err(err());
        }
        let mut s = [0.0; 6];
        for (v, p) in s.iter_mut().zip(parts) {
            *v = p.trim().parse::<f64>().map_err(|_| err())?;
            if !(v.is_finite() && *v > 0.0) {
                return Err(err());
            }
        }
        Ok(Sensitivities(s))
    }
}

impl fmt::Display for Sensitivities {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s = &self.0;
        write!(
            f,
            "Fx {:.3} Fy {:.3} Fz {:.3} LSB/N, Mx {:.3} My {:.3} Mz {:.3} LSB/(N·m)",
            s[0], s[1], s[2], s[3], s[4], s[5]
        )
    }
}

/// Parses a `0F` reply line (`1`, `2`, `4` or `8`, CR LF optional).
pub fn decode_filter(line: &[u8]) -> Result<FilterDivider, CodecError> {
    let err = || CodecError::Filter {
        bytes: super::super::ft_common::show_bytes(line),
    };
    let text = std::str::from_utf8(line).map_err(|_| err())?;
    let n: u32 = text.trim().parse().map_err(|_| err())?;
    FilterDivider::from_n(n).ok_or_else(err)
}

/// The `0F` reply line.
pub fn encode_filter(d: FilterDivider) -> Vec<u8> {
    format!("{}\r\n", d.n()).into_bytes()
}

#[cfg(test)]
mod tests {
    use super::*;

    const SENS: Sensitivities = Sensitivities([32.8, 32.8, 32.8, 1638.4, 1638.4, 1638.4]);

    #[test]
    fn record_known_bytes_decode_to_spec_values() {
        // Counter 3, Fx = 0x2000 (zero), Fy = 0x2148 = 8520 (+328 LSB = +10 N at
        // 32.8 LSB/N), Fz = 0x1EB8 = 7864 (−328 LSB = −10 N), Mx = 0x2666 = 9830
        // (+1638 LSB = 0.99976 N·m), My = Mz = 0x2000.
        let bytes = b"3200021481EB8266620002000\r\n";
        assert_eq!(bytes.len(), RECORD_LEN);
        let r = Record::decode(bytes).unwrap();
        assert_eq!(r.counter, 3);
        assert_eq!(r.raw, [0x2000, 0x2148, 0x1EB8, 0x2666, 0x2000, 0x2000]);
        let w = r.to_wrench(&SENS);
        assert!((w.force_n[0]).abs() < 1e-12);
        assert!((w.force_n[1] - 10.0).abs() < 1e-9, "{w:?}");
        assert!((w.force_n[2] + 10.0).abs() < 1e-9);
        assert!((w.torque_nm[0] - 1638.0 / 1638.4).abs() < 1e-12);
        assert_eq!(&r.encode()[..], &bytes[..]);
    }

    #[test]
    fn record_round_trips_all_counters_and_extremes() {
        for c in 0..10u8 {
            let r = Record {
                counter: c,
                raw: [0, RAW_MAX, RAW_ZERO, 1, 0xABCD, 0x0F0F],
            };
            assert_eq!(Record::decode(&r.encode()).unwrap(), r);
        }
    }

    #[test]
    fn wrench_to_raw_inverts_within_one_lsb() {
        let w = Wrench {
            force_n: [1.234, -45.6, 100.0],
            torque_nm: [0.5, -1.25, 2.0],
        };
        let back = Record {
            counter: 0,
            raw: Record::raw_from_wrench(&w, &SENS),
        }
        .to_wrench(&SENS);
        for i in 0..3 {
            assert!((back.force_n[i] - w.force_n[i]).abs() <= 0.5 / SENS.0[i] + 1e-12);
            assert!((back.torque_nm[i] - w.torque_nm[i]).abs() <= 0.5 / SENS.0[3 + i] + 1e-12);
        }
    }

    #[test]
    fn raw_saturates_at_converter_range() {
        let w = Wrench {
            force_n: [1e6, -1e6, f64::NAN],
            torque_nm: [0.0; 3],
        };
        let raw = Record::raw_from_wrench(&w, &SENS);
        assert_eq!(&raw[..3], &[RAW_MAX, 0, RAW_ZERO]);
    }

    #[test]
    fn bad_records_name_the_offending_byte() {
        let mut b = Record {
            counter: 1,
            raw: [RAW_ZERO; 6],
        }
        .encode();
        b[7] = b'G';
        match Record::decode(&b) {
            Err(CodecError::RecordChar {
                index: 7,
                found: 'G',
                ..
            }) => {}
            other => panic!("unexpected {other:?}"),
        }
        assert!(matches!(
            Record::decode(&b[1..]),
            Err(CodecError::RecordLength { len: 26, .. })
        ));
        let mut c = b;
        c[7] = b'0';
        c[0] = b'x';
        assert!(matches!(
            Record::decode(&c),
            Err(CodecError::RecordChar { index: 0, .. })
        ));
    }

    #[test]
    fn sensitivities_round_trip_and_reject_bad_lines() {
        let line = SENS.encode();
        assert_eq!(
            line,
            b"32.800,32.800,32.800,1638.400,1638.400,1638.400\r\n".to_vec()
        );
        assert_eq!(Sensitivities::decode(&line).unwrap(), SENS);
        assert!(Sensitivities::decode(b"1,2,3,4,5\r\n").is_err());
        assert!(Sensitivities::decode(b"1,2,3,4,5,0\r\n").is_err());
        assert!(Sensitivities::decode(b"1,2,3,4,5,x\r\n").is_err());
    }

    #[test]
    fn commands_encode_to_spec_bytes() {
        assert_eq!(Command::Read.encode(), b"R");
        assert_eq!(Command::Sensitivities.encode(), b"p");
        assert_eq!(Command::ZeroOffset.encode(), b"O");
        assert_eq!(Command::Version.encode(), b"V");
        assert_eq!(Command::SetFilter(FilterDivider::D4).encode(), b"4F");
        assert_eq!(Command::GetFilter.encode(), b"0F");
        assert_eq!(Command::StartContinuous.encode(), b"S");
        assert_eq!(Command::StopContinuous.encode(), b"E");
        assert!(!Command::StopContinuous.has_reply());
        assert_eq!(decode_filter(b"8\r\n").unwrap(), FilterDivider::D8);
        assert!(decode_filter(b"3\r\n").is_err());
    }
}
