//! Robotiq FT 300 wire codec (pure, no I/O): Modbus RTU requests and responses
//! (functions 03 read holding registers, 16 write multiple registers, exceptions),
//! CRC-16/MODBUS, the register map, and the binary stream frames with a resynchronising
//! decoder.
//!
//! CRC-16/MODBUS: reflected polynomial 0xA001 (0x8005 bit-reversed), initial value
//! 0xFFFF, no final XOR; sent low byte first. Check value over ASCII "123456789" is
//! 0x4B37.
//!
//! Scaling (registers and stream alike): `F = raw / 100` N, `M = raw / 1000` N·m with
//! raw a signed 16-bit integer. Modbus registers are big-endian on the wire; stream
//! values are little-endian. See `protocols/ft300.md`.

use crate::device::ft_common::resync_frames;
use crate::device::Wrench;

/// Default Modbus slave address of the FT 300.
pub const SLAVE_ADDRESS: u8 = 9;
/// First force register (Fx); Fy, Fz, Mx, My, Mz follow.
pub const REG_WRENCH: u16 = 180;
/// First firmware-version register (3 registers: 3 ASCII letters, then major, minor,
/// patch bytes). Taken from an open-source driver, not from the manual.
pub const REG_FIRMWARE: u16 = 500;
/// First serial-number register (4 registers): three ASCII characters (510 high byte,
/// 510 low byte, 511 high byte), then a 32-bit number with register 513 the high word
/// and 512 the low word, as Robotiq's `rq_sensor_com` decodes it. See [`decode_serial`].
pub const REG_SERIAL: u16 = 510;
/// Production year register.
pub const REG_YEAR: u16 = 514;
/// Stream control register; writing [`STREAM_START`] starts the stream.
pub const REG_STREAM: u16 = 410;
/// Value written to [`REG_STREAM`] to start streaming.
pub const STREAM_START: u16 = 0x0200;
/// Stream frame length in bytes.
pub const FRAME_LEN: usize = 16;
/// Stream frame header.
pub const FRAME_HEADER: [u8; 2] = [0x20, 0x4E];
/// Bytes the host sends to stop the stream: the "jam signal" of Robotiq's driver,
/// 50 × 0xFF.
pub const STOP_STREAM: [u8; 50] = [0xFF; 50];
/// Newtons per force LSB.
pub const FORCE_N_PER_LSB: f64 = 0.01;
/// Newton-metres per torque LSB.
pub const TORQUE_NM_PER_LSB: f64 = 0.001;

/// Function codes.
pub const FN_READ_HOLDING: u8 = 0x03;
/// Write multiple registers.
pub const FN_WRITE_MULTIPLE: u8 = 0x10;

/// CRC-16/MODBUS of `data`.
pub fn crc16(data: &[u8]) -> u16 {
    let mut crc: u16 = 0xFFFF;
    for &b in data {
        crc ^= b as u16;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xA001
            } else {
                crc >> 1
            };
        }
    }
    crc
}

/// Appends the CRC, low byte first.
pub fn with_crc(mut frame: Vec<u8>) -> Vec<u8> {
    let c = crc16(&frame);
    frame.extend_from_slice(&c.to_le_bytes());
    frame
}

/// Whether the last two bytes are the CRC of the rest.
pub fn crc_ok(frame: &[u8]) -> bool {
    frame.len() >= 3 && {
        let (body, c) = frame.split_at(frame.len() - 2);
        crc16(body) == u16::from_le_bytes([c[0], c[1]])
    }
}

/// A Modbus exception code.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExceptionCode {
    /// 01: function not supported.
    IllegalFunction,
    /// 02: register address not allowed.
    IllegalDataAddress,
    /// 03: value not allowed.
    IllegalDataValue,
    /// 04: the device failed.
    DeviceFailure,
    /// Any other code.
    Other(u8),
}

impl ExceptionCode {
    /// From the wire byte.
    pub fn from_byte(b: u8) -> Self {
        match b {
            1 => Self::IllegalFunction,
            2 => Self::IllegalDataAddress,
            3 => Self::IllegalDataValue,
            4 => Self::DeviceFailure,
            x => Self::Other(x),
        }
    }
    /// The wire byte.
    pub fn byte(self) -> u8 {
        match self {
            Self::IllegalFunction => 1,
            Self::IllegalDataAddress => 2,
            Self::IllegalDataValue => 3,
            Self::DeviceFailure => 4,
            Self::Other(x) => x,
        }
    }
    /// Meaning, for error messages.
    pub fn describe(self) -> &'static str {
        match self {
            Self::IllegalFunction => "illegal function",
            Self::IllegalDataAddress => "illegal data address",
            Self::IllegalDataValue => "illegal data value",
            Self::DeviceFailure => "slave device failure",
            Self::Other(_) => "unknown exception",
        }
    }
}

/// A request from the host.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Request {
    /// Function 03.
    ReadHolding {
        /// Slave address.
        slave: u8,
        /// First register.
        start: u16,
        /// Register count (1..=125).
        count: u16,
    },
    /// Function 16.
    WriteMultiple {
        /// Slave address.
        slave: u8,
        /// First register.
        start: u16,
        /// Values (1..=123).
        values: Vec<u16>,
    },
}

/// A reply from the device.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Response {
    /// Function 03 reply.
    ReadHolding {
        /// Slave address.
        slave: u8,
        /// Register values.
        values: Vec<u16>,
    },
    /// Function 16 reply (echo of start and count).
    WriteMultiple {
        /// Slave address.
        slave: u8,
        /// First register.
        start: u16,
        /// Register count.
        count: u16,
    },
    /// Exception reply (function | 0x80, code).
    Exception {
        /// Slave address.
        slave: u8,
        /// The function that failed (without the 0x80 bit).
        function: u8,
        /// Why.
        code: ExceptionCode,
    },
}

/// A Modbus frame that does not follow the protocol.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ModbusError {
    /// CRC mismatch.
    #[error("bad crc in `{bytes}`")]
    Crc {
        /// The frame, escaped.
        bytes: String,
    },
    /// Shape does not match the function.
    #[error("malformed frame `{bytes}`: {why}")]
    Malformed {
        /// The frame, escaped.
        bytes: String,
        /// What is wrong.
        why: &'static str,
    },
    /// A function this codec does not know.
    #[error("unsupported function 0x{function:02x} in `{bytes}`")]
    Function {
        /// The function code.
        function: u8,
        /// The frame, escaped.
        bytes: String,
    },
}

impl Request {
    /// The frame on the wire, CRC included.
    pub fn encode(&self) -> Vec<u8> {
        match self {
            Request::ReadHolding {
                slave,
                start,
                count,
            } => {
                let mut f = vec![*slave, FN_READ_HOLDING];
                f.extend_from_slice(&start.to_be_bytes());
                f.extend_from_slice(&count.to_be_bytes());
                with_crc(f)
            }
            Request::WriteMultiple {
                slave,
                start,
                values,
            } => {
                let mut f = vec![*slave, FN_WRITE_MULTIPLE];
                f.extend_from_slice(&start.to_be_bytes());
                f.extend_from_slice(&(values.len() as u16).to_be_bytes());
                f.push((values.len() * 2) as u8);
                for v in values {
                    f.extend_from_slice(&v.to_be_bytes());
                }
                with_crc(f)
            }
        }
    }

    /// The command as text, for error messages (`read 180+6`, `write 410 = [0x0200]`).
    pub fn text(&self) -> String {
        match self {
            Request::ReadHolding { start, count, .. } => format!("read {start}+{count}"),
            Request::WriteMultiple { start, values, .. } => {
                let v: Vec<String> = values.iter().map(|v| format!("0x{v:04x}")).collect();
                format!("write {start} = [{}]", v.join(", "))
            }
        }
    }

    /// Length of the request frame starting with `prefix`, once enough of it is known
    /// (`None` = need more bytes; `Some(Err)` = unknown function).
    pub fn frame_len(prefix: &[u8]) -> Option<Result<usize, u8>> {
        let f = *prefix.get(1)?;
        match f {
            FN_READ_HOLDING => Some(Ok(8)),
            FN_WRITE_MULTIPLE => prefix.get(6).map(|&n| Ok(9 + n as usize)),
            other => Some(Err(other)),
        }
    }

    /// Decodes one complete request frame.
    pub fn decode(frame: &[u8]) -> Result<Request, ModbusError> {
        let shown = || show_bytes_hex(frame);
        if !crc_ok(frame) {
            return Err(ModbusError::Crc { bytes: shown() });
        }
        let be = |i: usize| u16::from_be_bytes([frame[i], frame[i + 1]]);
        match frame.get(1) {
            Some(&FN_READ_HOLDING) if frame.len() == 8 => Ok(Request::ReadHolding {
                slave: frame[0],
                start: be(2),
                count: be(4),
            }),
            Some(&FN_WRITE_MULTIPLE) if frame.len() >= 9 => {
                let count = be(4) as usize;
                let n = frame[6] as usize;
                if n != 2 * count || frame.len() != 9 + n {
                    return Err(ModbusError::Malformed {
                        bytes: shown(),
                        why: "byte count does not match register count",
                    });
                }
                Ok(Request::WriteMultiple {
                    slave: frame[0],
                    start: be(2),
                    values: (0..count).map(|k| be(7 + 2 * k)).collect(),
                })
            }
            Some(&f) if f == FN_READ_HOLDING || f == FN_WRITE_MULTIPLE => {
                Err(ModbusError::Malformed {
                    bytes: shown(),
                    why: "wrong length",
                })
            }
            Some(&f) => Err(ModbusError::Function {
                function: f,
                bytes: shown(),
            }),
            None => Err(ModbusError::Malformed {
                bytes: shown(),
                why: "too short",
            }),
        }
    }
}

impl Response {
    /// The frame on the wire, CRC included.
    pub fn encode(&self) -> Vec<u8> {
        match self {
            Response::ReadHolding { slave, values } => {
                let mut f = vec![*slave, FN_READ_HOLDING, (values.len() * 2) as u8];
                for v in values {
                    f.extend_from_slice(&v.to_be_bytes());
                }
                with_crc(f)
            }
            Response::WriteMultiple {
                slave,
                start,
                count,
            } => {
                let mut f = vec![*slave, FN_WRITE_MULTIPLE];
                f.extend_from_slice(&start.to_be_bytes());
                f.extend_from_slice(&count.to_be_bytes());
                with_crc(f)
            }
            Response::Exception {
                slave,
                function,
                code,
            } => with_crc(vec![*slave, function | 0x80, code.byte()]),
        }
    }

    /// Length of the reply frame starting with `prefix`, once known (`None` = need
    /// more bytes; `Some(Err)` = a function this codec cannot frame).
    pub fn frame_len(prefix: &[u8]) -> Option<Result<usize, u8>> {
        let f = *prefix.get(1)?;
        match f {
            FN_READ_HOLDING => prefix.get(2).map(|&n| Ok(5 + n as usize)),
            FN_WRITE_MULTIPLE => Some(Ok(8)),
            f if f & 0x80 != 0 => Some(Ok(5)),
            other => Some(Err(other)),
        }
    }

    /// Decodes one complete reply frame.
    pub fn decode(frame: &[u8]) -> Result<Response, ModbusError> {
        let shown = || show_bytes_hex(frame);
        if !crc_ok(frame) {
            return Err(ModbusError::Crc { bytes: shown() });
        }
        let be = |i: usize| u16::from_be_bytes([frame[i], frame[i + 1]]);
        let bad = |why| ModbusError::Malformed {
            bytes: shown(),
            why,
        };
        match frame.get(1) {
            Some(&FN_READ_HOLDING) => {
                let n = *frame.get(2).ok_or_else(|| bad("too short"))? as usize;
                if !n.is_multiple_of(2) || frame.len() != 5 + n {
                    return Err(bad("byte count does not match length"));
                }
                Ok(Response::ReadHolding {
                    slave: frame[0],
                    values: (0..n / 2).map(|k| be(3 + 2 * k)).collect(),
                })
            }
            Some(&FN_WRITE_MULTIPLE) if frame.len() == 8 => Ok(Response::WriteMultiple {
                slave: frame[0],
                start: be(2),
                count: be(4),
            }),
            Some(&f) if f & 0x80 != 0 && frame.len() == 5 => Ok(Response::Exception {
                slave: frame[0],
                function: f & 0x7F,
                code: ExceptionCode::from_byte(frame[2]),
            }),
            Some(&f) if f == FN_WRITE_MULTIPLE || f & 0x80 != 0 => Err(bad("wrong length")),
            Some(&f) => Err(ModbusError::Function {
                function: f,
                bytes: shown(),
            }),
            None => Err(bad("too short")),
        }
    }
}

/// The serial number registers 510–513 as text, the way Robotiq's `rq_sensor_com`
/// prints it: the three characters, a dash, then the 32-bit number (register 513 high
/// word, 512 low word) with at least four digits (`FTS-1234`, `FTS-0042`,
/// `FTS-70000`). A number of 0 means the sensor has none: `UNKNOWN`, as the vendor
/// driver says. A byte that is not printable ASCII shows as `?`.
pub fn decode_serial(regs: [u16; 4]) -> String {
    let number = (regs[3] as u32) << 16 | regs[2] as u32;
    if number == 0 {
        return "UNKNOWN".to_string();
    }
    let [a, b] = regs[0].to_be_bytes();
    let [c, _] = regs[1].to_be_bytes();
    let letters: String = [a, b, c]
        .iter()
        .map(|&x| if x.is_ascii_graphic() { x as char } else { '?' })
        .collect();
    format!("{letters}-{number:04}")
}

/// The serial number registers 510–513 for three characters and a number (the
/// inverse of [`decode_serial`]; the low byte of 511 is 0).
pub fn encode_serial(letters: [u8; 3], number: u32) -> [u16; 4] {
    [
        u16::from_be_bytes([letters[0], letters[1]]),
        u16::from_be_bytes([letters[2], 0]),
        (number & 0xFFFF) as u16,
        (number >> 16) as u16,
    ]
}

/// Bytes as hex for error messages (`09 03 00 b4`).
pub fn show_bytes_hex(bytes: &[u8]) -> String {
    let v: Vec<String> = bytes.iter().map(|b| format!("{b:02x}")).collect();
    v.join(" ")
}

/// Raw int16 channel values to a wrench (÷100 N, ÷1000 N·m).
pub fn wrench_from_raw(raw: [i16; 6]) -> Wrench {
    Wrench {
        force_n: [0, 1, 2].map(|i| raw[i] as f64 * FORCE_N_PER_LSB),
        torque_nm: [3, 4, 5].map(|i| raw[i] as f64 * TORQUE_NM_PER_LSB),
    }
}

/// A wrench to raw values (rounded, saturated to the int16 range; NaN → 0).
pub fn raw_from_wrench(w: &Wrench) -> [i16; 6] {
    let q = |v: f64, lsb: f64| {
        let r = (v / lsb).round();
        if r.is_nan() {
            0
        } else {
            r.clamp(i16::MIN as f64, i16::MAX as f64) as i16
        }
    };
    [
        q(w.force_n[0], FORCE_N_PER_LSB),
        q(w.force_n[1], FORCE_N_PER_LSB),
        q(w.force_n[2], FORCE_N_PER_LSB),
        q(w.torque_nm[0], TORQUE_NM_PER_LSB),
        q(w.torque_nm[1], TORQUE_NM_PER_LSB),
        q(w.torque_nm[2], TORQUE_NM_PER_LSB),
    ]
}

/// One stream frame: six raw int16 values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StreamFrame {
    /// Fx Fy Fz (0.01 N) Mx My Mz (0.001 N·m).
    pub raw: [i16; 6],
}

impl StreamFrame {
    /// The 16 bytes on the wire: header, six int16 LE, CRC-16/MODBUS LE of bytes 0..14.
    pub fn encode(&self) -> [u8; FRAME_LEN] {
        let mut f = [0u8; FRAME_LEN];
        f[..2].copy_from_slice(&FRAME_HEADER);
        for (i, v) in self.raw.iter().enumerate() {
            f[2 + 2 * i..4 + 2 * i].copy_from_slice(&v.to_le_bytes());
        }
        let c = crc16(&f[..14]);
        f[14..].copy_from_slice(&c.to_le_bytes());
        f
    }

    /// Decodes 16 bytes; `None` unless header and CRC are right.
    pub fn decode(f: &[u8]) -> Option<StreamFrame> {
        if f.len() != FRAME_LEN || f[..2] != FRAME_HEADER || !crc_ok(f) {
            return None;
        }
        let mut raw = [0i16; 6];
        for (i, r) in raw.iter_mut().enumerate() {
            *r = i16::from_le_bytes([f[2 + 2 * i], f[3 + 2 * i]]);
        }
        Some(StreamFrame { raw })
    }

    /// The wrench.
    pub fn wrench(&self) -> Wrench {
        wrench_from_raw(self.raw)
    }
}

/// Counters of a stream decoder.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct StreamStats {
    /// Valid frames decoded.
    pub frames: u64,
    /// Candidate frames (header found, 16 bytes) whose CRC failed.
    pub bad_crc: u64,
    /// Bytes skipped while looking for a header.
    pub bytes_skipped: u64,
    /// Times the reader restarted a stalled stream (driver only).
    pub restarts: u64,
}

/// Splits a byte stream into frames, resynchronising on the header: after a bad CRC
/// it moves on by one byte (the header may sit inside the rejected 16 bytes, e.g.
/// after a dropped byte), and bytes before a header are skipped and counted.
#[derive(Debug, Default)]
pub struct StreamDecoder {
    buf: Vec<u8>,
    /// Counters.
    pub stats: StreamStats,
}

impl StreamDecoder {
    /// Feeds bytes; decoded frames are appended to `out`.
    pub fn push(&mut self, bytes: &[u8], out: &mut Vec<StreamFrame>) {
        self.buf.extend_from_slice(bytes);
        // A lone trailing header byte may start the next frame: `resync_frames` keeps it.
        let r = resync_frames(
            &mut self.buf,
            &FRAME_HEADER,
            FRAME_LEN,
            StreamFrame::decode,
            out,
        );
        self.stats.frames += r.frames;
        self.stats.bad_crc += r.rejected;
        // Counted here: every byte not in a frame, a rejected frame's first one too.
        self.stats.bytes_skipped += r.skipped + r.rejected;
    }

    /// Bytes held waiting for the rest of a frame.
    pub fn pending(&self) -> usize {
        self.buf.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc_check_value_of_123456789_is_4b37() {
        assert_eq!(crc16(b"123456789"), 0x4B37);
    }

    #[test]
    fn crc_of_classic_read_request_is_c5_cd() {
        // 01 03 00 00 00 0A: the textbook "read 10 holding registers from slave 1".
        let f = with_crc(vec![0x01, 0x03, 0x00, 0x00, 0x00, 0x0A]);
        assert_eq!(&f[6..], &[0xC5, 0xCD]);
    }

    #[test]
    fn read_wrench_request_known_bytes() {
        let r = Request::ReadHolding {
            slave: 9,
            start: 180,
            count: 6,
        };
        let f = r.encode();
        assert_eq!(&f[..6], &[0x09, 0x03, 0x00, 0xB4, 0x00, 0x06]);
        assert!(crc_ok(&f));
        assert_eq!(Request::decode(&f).unwrap(), r);
    }

    #[test]
    fn requests_and_responses_round_trip() {
        let reqs = [
            Request::ReadHolding {
                slave: 9,
                start: 510,
                count: 5,
            },
            Request::WriteMultiple {
                slave: 9,
                start: 410,
                values: vec![0x0200],
            },
        ];
        for r in reqs {
            let f = r.encode();
            assert_eq!(Request::frame_len(&f), Some(Ok(f.len())));
            assert_eq!(Request::decode(&f).unwrap(), r);
        }
        let resps = [
            Response::ReadHolding {
                slave: 9,
                values: vec![1, 0xFFFF, 0x8000, 7, 0, 42],
            },
            Response::WriteMultiple {
                slave: 9,
                start: 410,
                count: 1,
            },
            Response::Exception {
                slave: 9,
                function: 3,
                code: ExceptionCode::IllegalDataAddress,
            },
        ];
        for r in resps {
            let f = r.encode();
            assert_eq!(Response::frame_len(&f), Some(Ok(f.len())));
            assert_eq!(Response::decode(&f).unwrap(), r);
        }
    }

    #[test]
    fn serial_number_is_three_letters_and_a_32_bit_number_high_word_in_513() {
        // FTS-1234: 'F' 'T' | 'S' 0 | 1234 | 0, as a real sensor's registers hold it.
        assert_eq!(decode_serial([0x4654, 0x5300, 1234, 0]), "FTS-1234");
        // The high word is register 513: 70000 = 0x0001_1170.
        assert_eq!(decode_serial([0x4654, 0x5300, 0x1170, 0x0001]), "FTS-70000");
        // At least four digits, as the vendor's `%.4lu`.
        assert_eq!(decode_serial([0x4654, 0x5300, 42, 0]), "FTS-0042");
        assert_eq!(decode_serial([0x4654, 0x5300, 0, 0]), "UNKNOWN");
        assert_eq!(decode_serial([0x4601, 0x5300, 7, 0]), "F?S-0007");
        for n in [1, 1234, 65535, 65536, 70000, u32::MAX] {
            assert_eq!(
                decode_serial(encode_serial(*b"FTS", n)),
                format!("FTS-{n:04}")
            );
        }
        assert_eq!(encode_serial(*b"FTS", 1234), [0x4654, 0x5300, 0x04D2, 0]);
    }

    #[test]
    fn exception_reply_known_bytes() {
        let f = Response::Exception {
            slave: 9,
            function: 3,
            code: ExceptionCode::IllegalDataAddress,
        }
        .encode();
        assert_eq!(&f[..3], &[0x09, 0x83, 0x02]);
    }

    #[test]
    fn corrupted_frames_fail_the_crc() {
        let mut f = Response::ReadHolding {
            slave: 9,
            values: vec![100, 200],
        }
        .encode();
        f[4] ^= 0x01;
        assert!(matches!(Response::decode(&f), Err(ModbusError::Crc { .. })));
    }

    #[test]
    fn scaling_matches_spec() {
        let w = wrench_from_raw([100, -250, 30000, 1000, -1, 0]);
        assert_eq!(w.force_n, [1.0, -2.5, 300.0]);
        assert_eq!(w.torque_nm, [1.0, -0.001, 0.0]);
        assert_eq!(raw_from_wrench(&w), [100, -250, 30000, 1000, -1, 0]);
        let big = Wrench {
            force_n: [1e9, -1e9, f64::NAN],
            torque_nm: [0.0; 3],
        };
        assert_eq!(&raw_from_wrench(&big)[..3], &[i16::MAX, i16::MIN, 0]);
    }

    #[test]
    fn stream_frame_known_layout() {
        let f = StreamFrame {
            raw: [1, -1, 0x1234, 0, 0, 0],
        }
        .encode();
        assert_eq!(&f[..8], &[0x20, 0x4E, 0x01, 0x00, 0xFF, 0xFF, 0x34, 0x12]);
        let c = crc16(&f[..14]);
        assert_eq!(&f[14..], &c.to_le_bytes());
        assert_eq!(
            StreamFrame::decode(&f).unwrap().raw,
            [1, -1, 0x1234, 0, 0, 0]
        );
    }

    #[test]
    fn decoder_resyncs_after_garbage_bad_crc_and_partial_frames() {
        let a = StreamFrame {
            raw: [1, 2, 3, 4, 5, 6],
        }
        .encode();
        let b = StreamFrame {
            raw: [7, 8, 9, 10, 11, 12],
        }
        .encode();
        let mut bad = a;
        bad[5] ^= 0x10;
        let mut stream = vec![0x00, 0x4E, 0x20]; // garbage incl. a half header
        stream.extend_from_slice(&a);
        stream.extend_from_slice(&bad);
        stream.extend_from_slice(&a[..9]); // partial frame (bytes lost)
        stream.extend_from_slice(&b);
        let mut d = StreamDecoder::default();
        let mut out = Vec::new();
        // Feed in awkward chunks.
        for chunk in stream.chunks(5) {
            d.push(chunk, &mut out);
        }
        let raws: Vec<_> = out.iter().map(|f| f.raw).collect();
        assert_eq!(raws, vec![[1, 2, 3, 4, 5, 6], [7, 8, 9, 10, 11, 12]]);
        assert_eq!(d.stats.frames, 2);
        assert!(d.stats.bad_crc >= 2, "{:?}", d.stats);
        assert_eq!(d.pending(), 0);
    }
}
