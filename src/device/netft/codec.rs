//! ATI Net F/T (and OnRobot HEX) wire codec (pure, no I/O): the RDT request and record
//! on UDP, and the READCALINFO request and reply on TCP. Everything is big-endian.
//!
//! ```text
//! RDT request, 8 bytes:  u16 0x1234 | u16 command | u32 sample count (0 = until stopped)
//! RDT record, 36 bytes:  u32 RDT sequence | u32 F/T sequence | u32 status | 6 × i32 counts
//! READCALINFO request, 20 bytes: u8 1 | 19 reserved bytes (0)
//! READCALINFO reply, 24 bytes (`>HBBII6H`): u16 0x1234 | u8 force unit | u8 torque unit |
//!                        u32 counts per force | u32 counts per torque | 6 × u16 scale factors
//! ```
//!
//! Value = counts / counts-per-unit, in the unit the device reports; [`Scale`] converts
//! to N and N·m. See `protocols/netft.md` for the sources.

use crate::device::Wrench;

/// UDP port of the RDT interface.
pub const RDT_PORT: u16 = 49152;
/// TCP port of the command interface (READCALINFO).
pub const CAL_PORT: u16 = 49151;
/// Header of every RDT request and of the READCALINFO reply.
pub const HEADER: u16 = 0x1234;
/// RDT request length.
pub const REQUEST_LEN: usize = 8;
/// RDT record length.
pub const RECORD_LEN: usize = 36;
/// READCALINFO request length.
pub const CAL_REQUEST_LEN: usize = 20;
/// READCALINFO reply length.
pub const CAL_REPLY_LEN: usize = 24;
/// READCALINFO command byte.
pub const CMD_READCALINFO: u8 = 1;

/// An RDT command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Command {
    /// 0x0000: stop streaming.
    Stop,
    /// 0x0002: start real-time streaming (one record per sample).
    StartRealtime,
    /// 0x0003: start buffered streaming (records batched by the device).
    StartBuffered,
    /// 0x0042: set the software bias (zero at the current load).
    SetBias,
    /// 0x0081: OnRobot HEX filter (the count field carries the filter index).
    OnRobotFilter,
    /// 0x0082: OnRobot HEX rate (the count field carries the period in ms).
    OnRobotRate,
    /// Any other command word.
    Other(u16),
}

impl Command {
    /// The command word.
    pub fn word(self) -> u16 {
        match self {
            Command::Stop => 0x0000,
            Command::StartRealtime => 0x0002,
            Command::StartBuffered => 0x0003,
            Command::SetBias => 0x0042,
            Command::OnRobotFilter => 0x0081,
            Command::OnRobotRate => 0x0082,
            Command::Other(w) => w,
        }
    }

    /// From the command word.
    pub fn from_word(w: u16) -> Command {
        match w {
            0x0000 => Command::Stop,
            0x0002 => Command::StartRealtime,
            0x0003 => Command::StartBuffered,
            0x0042 => Command::SetBias,
            0x0081 => Command::OnRobotFilter,
            0x0082 => Command::OnRobotRate,
            w => Command::Other(w),
        }
    }
}

/// An RDT request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Request {
    /// The command.
    pub command: Command,
    /// Sample count (0 = until stopped), or the OnRobot command's argument.
    pub count: u32,
}

/// Bytes that do not follow the protocol.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CodecError {
    /// A datagram or reply of the wrong length.
    #[error("{what} has {len} bytes, expected {expected}")]
    Length {
        /// What was decoded.
        what: &'static str,
        /// Bytes received.
        len: usize,
        /// Bytes expected.
        expected: usize,
    },
    /// A header that is not 0x1234.
    #[error("{what} header is 0x{found:04x}, expected 0x1234")]
    Header {
        /// What was decoded.
        what: &'static str,
        /// The header found.
        found: u16,
    },
    /// A calibration the driver cannot use.
    #[error("calibration {field} = {value} is not usable: {why}")]
    Calibration {
        /// The field.
        field: &'static str,
        /// Its value.
        value: String,
        /// Why.
        why: &'static str,
    },
}

impl Request {
    /// A request with a sample count of 0.
    pub fn new(command: Command) -> Request {
        Request { command, count: 0 }
    }

    /// The 8 bytes on the wire.
    pub fn encode(&self) -> [u8; REQUEST_LEN] {
        let mut b = [0u8; REQUEST_LEN];
        b[0..2].copy_from_slice(&HEADER.to_be_bytes());
        b[2..4].copy_from_slice(&self.command.word().to_be_bytes());
        b[4..8].copy_from_slice(&self.count.to_be_bytes());
        b
    }

    /// Decodes one request datagram.
    pub fn decode(b: &[u8]) -> Result<Request, CodecError> {
        if b.len() != REQUEST_LEN {
            return Err(CodecError::Length {
                what: "RDT request",
                len: b.len(),
                expected: REQUEST_LEN,
            });
        }
        let h = u16::from_be_bytes([b[0], b[1]]);
        if h != HEADER {
            return Err(CodecError::Header {
                what: "RDT request",
                found: h,
            });
        }
        Ok(Request {
            command: Command::from_word(u16::from_be_bytes([b[2], b[3]])),
            count: u32::from_be_bytes([b[4], b[5], b[6], b[7]]),
        })
    }

    /// The request as text, for error messages.
    pub fn text(&self) -> String {
        format!("RDT 0x{:04x} count {}", self.command.word(), self.count)
    }
}

/// One RDT record.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Record {
    /// RDT sequence: +1 per record sent since the stream started.
    pub rdt_seq: u32,
    /// F/T sequence: +1 per internal sample of the device.
    pub ft_seq: u32,
    /// Status word; non-zero is a fault the device reports.
    pub status: u32,
    /// Counts Fx Fy Fz Tx Ty Tz.
    pub counts: [i32; 6],
}

impl Record {
    /// The 36 bytes on the wire.
    pub fn encode(&self) -> [u8; RECORD_LEN] {
        let mut b = [0u8; RECORD_LEN];
        b[0..4].copy_from_slice(&self.rdt_seq.to_be_bytes());
        b[4..8].copy_from_slice(&self.ft_seq.to_be_bytes());
        b[8..12].copy_from_slice(&self.status.to_be_bytes());
        for (i, c) in self.counts.iter().enumerate() {
            b[12 + 4 * i..16 + 4 * i].copy_from_slice(&c.to_be_bytes());
        }
        b
    }

    /// Decodes one record datagram (exactly 36 bytes: UDP delivers whole datagrams, so
    /// any other length is a datagram that is not a record).
    pub fn decode(b: &[u8]) -> Result<Record, CodecError> {
        if b.len() != RECORD_LEN {
            return Err(CodecError::Length {
                what: "RDT record",
                len: b.len(),
                expected: RECORD_LEN,
            });
        }
        let u = |i: usize| u32::from_be_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
        let mut counts = [0i32; 6];
        for (k, c) in counts.iter_mut().enumerate() {
            *c = u(12 + 4 * k) as i32;
        }
        Ok(Record {
            rdt_seq: u(0),
            ft_seq: u(4),
            status: u(8),
            counts,
        })
    }
}

/// The READCALINFO request: command 1 and 19 reserved zero bytes.
pub fn calinfo_request() -> [u8; CAL_REQUEST_LEN] {
    let mut b = [0u8; CAL_REQUEST_LEN];
    b[0] = CMD_READCALINFO;
    b
}

/// The READCALINFO reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CalInfo {
    /// Force unit code (2 = N; see [`force_unit_n`]).
    pub force_unit: u8,
    /// Torque unit code (3 = N·m; see [`torque_unit_nm`]).
    pub torque_unit: u8,
    /// Counts per force unit.
    pub counts_per_force: u32,
    /// Counts per torque unit.
    pub counts_per_torque: u32,
    /// Scale factors of the six channels (informational).
    pub scale_factors: [u16; 6],
}

impl CalInfo {
    /// The 24 bytes on the wire.
    pub fn encode(&self) -> [u8; CAL_REPLY_LEN] {
        let mut b = [0u8; CAL_REPLY_LEN];
        b[0..2].copy_from_slice(&HEADER.to_be_bytes());
        b[2] = self.force_unit;
        b[3] = self.torque_unit;
        b[4..8].copy_from_slice(&self.counts_per_force.to_be_bytes());
        b[8..12].copy_from_slice(&self.counts_per_torque.to_be_bytes());
        for (i, s) in self.scale_factors.iter().enumerate() {
            b[12 + 2 * i..14 + 2 * i].copy_from_slice(&s.to_be_bytes());
        }
        b
    }

    /// Decodes a READCALINFO reply.
    pub fn decode(b: &[u8]) -> Result<CalInfo, CodecError> {
        if b.len() != CAL_REPLY_LEN {
            return Err(CodecError::Length {
                what: "READCALINFO reply",
                len: b.len(),
                expected: CAL_REPLY_LEN,
            });
        }
        let h = u16::from_be_bytes([b[0], b[1]]);
        if h != HEADER {
            return Err(CodecError::Header {
                what: "READCALINFO reply",
                found: h,
            });
        }
        let u = |i: usize| u32::from_be_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
        let mut scale_factors = [0u16; 6];
        for (i, s) in scale_factors.iter_mut().enumerate() {
            *s = u16::from_be_bytes([b[12 + 2 * i], b[13 + 2 * i]]);
        }
        Ok(CalInfo {
            force_unit: b[2],
            torque_unit: b[3],
            counts_per_force: u(4),
            counts_per_torque: u(8),
            scale_factors,
        })
    }

    /// The scale in N and N·m: counts per N and per N·m.
    pub fn scale(&self) -> Result<Scale, CodecError> {
        let fu = force_unit_n(self.force_unit).ok_or_else(|| CodecError::Calibration {
            field: "force unit",
            value: self.force_unit.to_string(),
            why: "not a Net F/T force unit code (1 lbf, 2 N, 3 klbf, 4 kN, 5 kgf, 6 gf)",
        })?;
        let tu = torque_unit_nm(self.torque_unit).ok_or_else(|| CodecError::Calibration {
            field: "torque unit",
            value: self.torque_unit.to_string(),
            why: "not a Net F/T torque unit code (1 lbf·in, 2 lbf·ft, 3 N·m, 4 N·mm, 5 kgf·cm, 6 kN·m)",
        })?;
        if self.counts_per_force == 0 {
            return Err(CodecError::Calibration {
                field: "counts per force",
                value: "0".into(),
                why: "must be positive (it divides the counts)",
            });
        }
        if self.counts_per_torque == 0 {
            return Err(CodecError::Calibration {
                field: "counts per torque",
                value: "0".into(),
                why: "must be positive (it divides the counts)",
            });
        }
        // counts per unit / (N per unit) = counts per N.
        Ok(Scale {
            counts_per_n: self.counts_per_force as f64 / fu,
            counts_per_nm: self.counts_per_torque as f64 / tu,
        })
    }
}

/// Newtons per Net F/T force unit code: 1 lbf, 2 N, 3 klbf, 4 kN, 5 kgf, 6 gf.
pub fn force_unit_n(code: u8) -> Option<f64> {
    const LBF: f64 = 4.448_221_615_260_5;
    const G: f64 = 9.806_65;
    match code {
        1 => Some(LBF),
        2 => Some(1.0),
        3 => Some(1000.0 * LBF),
        4 => Some(1000.0),
        5 => Some(G),
        6 => Some(G / 1000.0),
        _ => None,
    }
}

/// Newton-metres per Net F/T torque unit code: 1 lbf·in, 2 lbf·ft, 3 N·m, 4 N·mm,
/// 5 kgf·cm, 6 kN·m.
pub fn torque_unit_nm(code: u8) -> Option<f64> {
    const LBF: f64 = 4.448_221_615_260_5;
    const G: f64 = 9.806_65;
    match code {
        1 => Some(LBF * 0.0254),
        2 => Some(LBF * 0.3048),
        3 => Some(1.0),
        4 => Some(0.001),
        5 => Some(G * 0.01),
        6 => Some(1000.0),
        _ => None,
    }
}

/// Counts per N and per N·m.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scale {
    /// Counts per newton.
    pub counts_per_n: f64,
    /// Counts per newton-metre.
    pub counts_per_nm: f64,
}

impl Scale {
    /// OnRobot HEX: fixed by the product (OnRobot's `highspeed_udp.c`: forces divided by
    /// 10000, torques by 100000), not queried.
    pub const ONROBOT_HEX: Scale = Scale {
        counts_per_n: 10_000.0,
        counts_per_nm: 100_000.0,
    };

    /// The wrench of a record's counts.
    pub fn wrench(&self, counts: &[i32; 6]) -> Wrench {
        Wrench {
            force_n: [0, 1, 2].map(|i| counts[i] as f64 / self.counts_per_n),
            torque_nm: [3, 4, 5].map(|i| counts[i] as f64 / self.counts_per_nm),
        }
    }

    /// Counts for a wrench (rounded, saturated to i32): the inverse of
    /// [`Scale::wrench`] up to one count.
    pub fn counts(&self, w: &Wrench) -> [i32; 6] {
        let v = [
            w.force_n[0] * self.counts_per_n,
            w.force_n[1] * self.counts_per_n,
            w.force_n[2] * self.counts_per_n,
            w.torque_nm[0] * self.counts_per_nm,
            w.torque_nm[1] * self.counts_per_nm,
            w.torque_nm[2] * self.counts_per_nm,
        ];
        v.map(|x| {
            if x.is_nan() {
                0
            } else {
                x.round().clamp(i32::MIN as f64, i32::MAX as f64) as i32
            }
        })
    }

    /// One count in N (forces) and N·m (torques): the codec's resolution.
    pub fn resolution(&self) -> [f64; 6] {
        let f = 1.0 / self.counts_per_n;
        let t = 1.0 / self.counts_per_nm;
        [f, f, f, t, t, t]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn request_known_bytes() {
        let r = Request {
            command: Command::StartRealtime,
            count: 0,
        };
        assert_eq!(r.encode(), [0x12, 0x34, 0x00, 0x02, 0, 0, 0, 0]);
        let b = Request {
            command: Command::SetBias,
            count: 0,
        }
        .encode();
        assert_eq!(b, [0x12, 0x34, 0x00, 0x42, 0, 0, 0, 0]);
        assert_eq!(Request::decode(&b).unwrap().command, Command::SetBias);
        assert!(matches!(
            Request::decode(&[0x43, 0x21, 0, 2, 0, 0, 0, 0]),
            Err(CodecError::Header { found: 0x4321, .. })
        ));
        assert!(Request::decode(&b[..7]).is_err());
    }

    #[test]
    fn record_known_bytes_and_round_trip() {
        // rdt 1, ft 7, status 0, Fx = 1000000 (1 N at 1e6 counts/N), Fy = -1, rest 0.
        let mut b = [0u8; RECORD_LEN];
        b[3] = 1;
        b[7] = 7;
        b[12..16].copy_from_slice(&[0x00, 0x0F, 0x42, 0x40]);
        b[16..20].copy_from_slice(&[0xFF; 4]);
        let r = Record::decode(&b).unwrap();
        assert_eq!((r.rdt_seq, r.ft_seq, r.status), (1, 7, 0));
        assert_eq!(r.counts, [1_000_000, -1, 0, 0, 0, 0]);
        assert_eq!(r.encode(), b);
        let s = Scale {
            counts_per_n: 1e6,
            counts_per_nm: 1e6,
        };
        let w = s.wrench(&r.counts);
        assert_eq!(w.force_n, [1.0, -1e-6, 0.0]);
        assert!(Record::decode(&b[..35]).is_err());
    }

    #[test]
    fn calinfo_round_trips_and_converts_units() {
        let c = CalInfo {
            force_unit: 1,
            torque_unit: 1,
            counts_per_force: 1_000_000,
            counts_per_torque: 1_000_000,
            scale_factors: [1; 6],
        };
        let b = c.encode();
        assert_eq!(&b[..4], &[0x12, 0x34, 1, 1]);
        assert_eq!(CalInfo::decode(&b).unwrap(), c);
        let s = c.scale().unwrap();
        // 1e6 counts per lbf = 1e6 / 4.448 counts per N.
        assert!((s.counts_per_n - 1e6 / 4.448_221_615_260_5).abs() < 1e-6);
        assert!((s.counts_per_nm - 1e6 / (4.448_221_615_260_5 * 0.0254)).abs() < 1e-3);
        let bad = CalInfo { force_unit: 9, ..c };
        assert!(bad.scale().unwrap_err().to_string().contains("force unit"));
        let zero = CalInfo {
            counts_per_torque: 0,
            ..c
        };
        assert!(zero.scale().is_err());
        assert_eq!(calinfo_request()[0], 1);
        assert_eq!(calinfo_request().len(), 20);
    }

    #[test]
    fn counts_invert_wrench_within_one_count() {
        let s = Scale {
            counts_per_n: 1e6,
            counts_per_nm: 1e6,
        };
        let w = Wrench {
            force_n: [1.234_567_4, -45.6, 100.0],
            torque_nm: [0.5, -1.25, f64::NAN],
        };
        let back = s.wrench(&s.counts(&w));
        assert!((back.force_n[0] - 1.234_567).abs() < 1e-12);
        assert_eq!(back.torque_nm[2], 0.0);
        let huge = Wrench {
            force_n: [1e9, -1e9, 0.0],
            torque_nm: [0.0; 3],
        };
        assert_eq!(s.counts(&huge)[..2], [i32::MAX, i32::MIN]);
    }
}
