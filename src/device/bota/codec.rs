//! Bota Systems serial sensor wire codec (pure, no I/O): the text configuration
//! commands and their `r,0,<cmd>,0` answers, and the binary stream frame with its
//! CRC-16/X-25 and a resynchronising decoder.
//!
//! ```text
//! frame, 37 bytes: 0xAA | payload, 34 bytes, little-endian:
//!     u16 status | f32 Fx Fy Fz (N) | f32 Mx My Mz (N·m) | u32 timestamp | f32 temperature (°C)
//!   | u16 CRC-16/X-25 of the payload, little-endian
//! ```
//!
//! CRC-16/X-25: reflected polynomial 0x8408 (0x1021 bit-reversed), initial value
//! 0xFFFF, final XOR 0xFFFF; check value over ASCII "123456789" 0x906E. See
//! `protocols/bota.md` for the sources.

use crate::device::ft_common::resync_frames;
use crate::device::Wrench;

/// Frame header byte.
pub const HEADER: u8 = 0xAA;
/// Payload length.
pub const PAYLOAD_LEN: usize = 34;
/// Frame length: header, payload, CRC.
pub const FRAME_LEN: usize = 1 + PAYLOAD_LEN + 2;
/// Status bit 0: the sensor's application took too long (a sample was late).
pub const STATUS_APP_TOO_LONG: u16 = 1 << 0;
/// Status bit 1: a channel is over its range.
pub const STATUS_OVERRANGE: u16 = 1 << 1;
/// Status bit 2: the measurement is invalid.
pub const STATUS_INVALID: u16 = 1 << 2;
/// Status bit 3: raw measurements (no calibration applied).
pub const STATUS_RAW: u16 = 1 << 3;
/// Boot text a sensor prints after power-up or reset.
pub const BOOT_TEXT: &str = "App Init";
/// Sample period per sinc-filter length unit: 19.53125 µs (512 → 10 ms).
pub const SINC_PERIOD_S: f64 = 19.531_25e-6;
/// Baud-rate indices of the `c` command: 0 9600, 1 57600, 2 115200, 3 230400, 4 460800.
pub const BAUD_RATES: [u32; 5] = [9600, 57_600, 115_200, 230_400, 460_800];

/// CRC-16/X-25 of `data`.
pub fn crc16_x25(data: &[u8]) -> u16 {
    let mut crc: u16 = 0xFFFF;
    for &b in data {
        crc ^= b as u16;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0x8408
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// A configuration command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Command {
    /// `C`: enter configuration mode (the stream stops).
    Config,
    /// `c,<temp_comp>,<use_calib>,<format>,<baud index>`: communication setup.
    Comm {
        /// Temperature compensation (0 off, 1 on).
        temp_comp: u8,
        /// Use the calibration matrix (1) or send raw measurements (0).
        use_calib: u8,
        /// Data format: 0 binary, 1 CSV.
        format: u8,
        /// Baud-rate index (see [`BAUD_RATES`]).
        baud_index: u8,
    },
    /// `f,<sinc_len>,<chop>,<fast>,<fir_disable>`: filter setup.
    Filter {
        /// Sinc filter length (sample period = 19.53125 µs × sinc_len).
        sinc_len: u32,
        /// Chop enable.
        chop: u8,
        /// Fast enable.
        fast: u8,
        /// FIR disable.
        fir_disable: u8,
    },
    /// `R`: run (stream frames).
    Run,
}

impl Command {
    /// The bytes sent (no terminator: the vendor's example sends none).
    pub fn encode(&self) -> Vec<u8> {
        match *self {
            Command::Config => b"C".to_vec(),
            Command::Run => b"R".to_vec(),
            Command::Comm {
                temp_comp,
                use_calib,
                format,
                baud_index,
            } => format!("c,{temp_comp},{use_calib},{format},{baud_index}").into_bytes(),
            Command::Filter {
                sinc_len,
                chop,
                fast,
                fir_disable,
            } => format!("f,{sinc_len},{chop},{fast},{fir_disable}").into_bytes(),
        }
    }

    /// The command letter, as echoed in the answer.
    pub fn letter(&self) -> char {
        match self {
            Command::Config => 'C',
            Command::Comm { .. } => 'c',
            Command::Filter { .. } => 'f',
            Command::Run => 'R',
        }
    }

    /// The answer that confirms it: `r,0,<letter>,0`.
    pub fn ack(&self) -> String {
        format!("r,0,{},0", self.letter())
    }

    /// Parses a complete command text (`C`, `R`, `c,…` with four fields, `f,…` with
    /// four fields); `None` when it is not one.
    pub fn parse(text: &str) -> Option<Command> {
        let t = text.trim();
        match t {
            "C" => return Some(Command::Config),
            "R" => return Some(Command::Run),
            _ => {}
        }
        let mut parts = t.split(',');
        let head = parts.next()?;
        let nums: Vec<u32> = parts
            .map(|p| p.trim().parse().ok())
            .collect::<Option<_>>()?;
        if nums.len() != 4 {
            return None;
        }
        let small = |v: u32| u8::try_from(v).ok();
        match head {
            "c" => Some(Command::Comm {
                temp_comp: small(nums[0])?,
                use_calib: small(nums[1])?,
                format: small(nums[2])?,
                baud_index: small(nums[3])?,
            }),
            "f" => Some(Command::Filter {
                sinc_len: nums[0],
                chop: small(nums[1])?,
                fast: small(nums[2])?,
                fir_disable: small(nums[3])?,
            }),
            _ => None,
        }
    }
}

/// One decoded frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Frame {
    /// Status bits ([`STATUS_OVERRANGE`] and the others).
    pub status: u16,
    /// Fx Fy Fz (N), Mx My Mz (N·m) as sent (f32).
    pub values: [f32; 6],
    /// The sensor's timestamp (µs counter, wraps).
    pub timestamp: u32,
    /// The sensor's temperature, °C.
    pub temperature_c: f32,
}

impl Frame {
    /// The 37 bytes on the wire.
    pub fn encode(&self) -> [u8; FRAME_LEN] {
        let mut b = [0u8; FRAME_LEN];
        b[0] = HEADER;
        b[1..3].copy_from_slice(&self.status.to_le_bytes());
        for (i, v) in self.values.iter().enumerate() {
            b[3 + 4 * i..7 + 4 * i].copy_from_slice(&v.to_le_bytes());
        }
        b[27..31].copy_from_slice(&self.timestamp.to_le_bytes());
        b[31..35].copy_from_slice(&self.temperature_c.to_le_bytes());
        let crc = crc16_x25(&b[1..35]);
        b[35..37].copy_from_slice(&crc.to_le_bytes());
        b
    }

    /// Decodes one frame (header and CRC checked); `None` when either is wrong.
    pub fn decode(b: &[u8]) -> Option<Frame> {
        if b.len() != FRAME_LEN || b[0] != HEADER {
            return None;
        }
        if crc16_x25(&b[1..35]) != u16::from_le_bytes([b[35], b[36]]) {
            return None;
        }
        let f = |i: usize| f32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
        Some(Frame {
            status: u16::from_le_bytes([b[1], b[2]]),
            values: [f(3), f(7), f(11), f(15), f(19), f(23)],
            timestamp: u32::from_le_bytes([b[27], b[28], b[29], b[30]]),
            temperature_c: f(31),
        })
    }

    /// The wrench (f32 widened).
    pub fn wrench(&self) -> Wrench {
        let v = self.values.map(f64::from);
        Wrench {
            force_n: [v[0], v[1], v[2]],
            torque_nm: [v[3], v[4], v[5]],
        }
    }

    /// Whether the status marks the sample as not to be averaged (overrange, invalid).
    pub fn is_bad(&self) -> bool {
        self.status & (STATUS_OVERRANGE | STATUS_INVALID) != 0
            || !self.values.iter().all(|v| v.is_finite())
    }
}

/// Names of the status bits set in `status`, e.g. `overrange, invalid`.
pub fn status_names(status: u16) -> String {
    let mut v = Vec::new();
    for (bit, name) in [
        (STATUS_APP_TOO_LONG, "app took too long"),
        (STATUS_OVERRANGE, "overrange"),
        (STATUS_INVALID, "invalid measurement"),
        (STATUS_RAW, "raw measurements"),
    ] {
        if status & bit != 0 {
            v.push(name);
        }
    }
    if status & !0x000F != 0 {
        v.push("unknown bits");
    }
    v.join(", ")
}

/// Counters of the stream decoder.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DecoderStats {
    /// Frames decoded.
    pub frames: u64,
    /// Candidate frames (a header and 36 bytes) that failed the CRC.
    pub bad_crc: u64,
    /// Bytes skipped while looking for a header.
    pub skipped: u64,
}

/// A resynchronising stream decoder: bytes in, frames out. On a bad CRC it slides to
/// the next 0xAA after the failed header.
#[derive(Debug, Default, Clone)]
pub struct StreamDecoder {
    buf: Vec<u8>,
    /// Counters.
    pub stats: DecoderStats,
}

impl StreamDecoder {
    /// Feeds `bytes`, appending the frames completed to `out`.
    pub fn push(&mut self, bytes: &[u8], out: &mut Vec<Frame>) {
        self.buf.extend_from_slice(bytes);
        let r = resync_frames(&mut self.buf, &[HEADER], FRAME_LEN, Frame::decode, out);
        self.stats.frames += r.frames;
        self.stats.bad_crc += r.rejected;
        self.stats.skipped += r.skipped;
    }

    /// Bytes held (an incomplete frame).
    pub fn pending(&self) -> &[u8] {
        &self.buf
    }

    /// Forgets buffered bytes.
    pub fn clear(&mut self) {
        self.buf.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame() -> Frame {
        Frame {
            status: 0,
            values: [1.5, -2.25, 12.34, 0.125, -0.05, 0.3],
            timestamp: 123_456,
            temperature_c: 25.5,
        }
    }

    #[test]
    fn crc_x25_check_value() {
        assert_eq!(crc16_x25(b"123456789"), 0x906E);
    }

    #[test]
    fn frame_round_trips_with_layout_offsets() {
        let f = frame();
        let b = f.encode();
        assert_eq!(b.len(), 37);
        assert_eq!(b[0], 0xAA);
        // Payload offsets as the vendor's example unpacks them (from the payload start).
        assert_eq!(
            f32::from_le_bytes(b[1 + 10..1 + 14].try_into().unwrap()),
            12.34
        );
        assert_eq!(
            u32::from_le_bytes(b[1 + 26..1 + 30].try_into().unwrap()),
            123_456
        );
        assert_eq!(
            f32::from_le_bytes(b[1 + 30..1 + 34].try_into().unwrap()),
            25.5
        );
        assert_eq!(Frame::decode(&b), Some(f));
        let mut bad = b;
        bad[5] ^= 1;
        assert_eq!(Frame::decode(&bad), None);
    }

    #[test]
    fn decoder_resyncs_after_garbage_and_bad_crc() {
        let f = frame().encode();
        let mut bad = f;
        bad[20] ^= 0x10;
        let mut stream = b"App Init\r\nr,0,R,0".to_vec();
        stream.extend_from_slice(&bad);
        stream.extend_from_slice(&f);
        stream.push(0xAA);
        stream.extend_from_slice(&f);
        let mut d = StreamDecoder::default();
        let mut out = Vec::new();
        // Byte by byte: framing must not depend on read boundaries.
        for b in &stream {
            d.push(std::slice::from_ref(b), &mut out);
        }
        assert_eq!(out.len(), 2);
        assert!(d.stats.bad_crc >= 2, "{:?}", d.stats);
        assert!(d.pending().len() < FRAME_LEN);
    }

    #[test]
    fn commands_encode_and_parse() {
        let c = Command::Comm {
            temp_comp: 0,
            use_calib: 1,
            format: 0,
            baud_index: 4,
        };
        assert_eq!(c.encode(), b"c,0,1,0,4");
        assert_eq!(c.ack(), "r,0,c,0");
        let f = Command::Filter {
            sinc_len: 512,
            chop: 0,
            fast: 0,
            fir_disable: 1,
        };
        assert_eq!(f.encode(), b"f,512,0,0,1");
        assert_eq!(Command::parse("f,512,0,0,1"), Some(f));
        assert_eq!(Command::parse("c,0,1,0,4"), Some(c));
        assert_eq!(Command::parse("C"), Some(Command::Config));
        assert_eq!(Command::parse("c,0,1,0"), None);
        assert_eq!(Command::parse("f,x,0,0,1"), None);
    }

    #[test]
    fn status_bits_are_named_and_bad_frames_flagged() {
        assert_eq!(
            status_names(STATUS_OVERRANGE | STATUS_INVALID),
            "overrange, invalid measurement"
        );
        let mut f = frame();
        assert!(!f.is_bad());
        f.status = STATUS_APP_TOO_LONG;
        assert!(!f.is_bad(), "a late sample is still a measurement");
        f.status = STATUS_OVERRANGE;
        assert!(f.is_bad());
        f.status = 0;
        f.values[2] = f32::NAN;
        assert!(f.is_bad());
    }
}
