//! Robotiq FT 300 simulator: a Modbus RTU slave (address 9 by default) holding the
//! wrench registers 180–185 (sampled from a [`WrenchSource`] when read), identity
//! registers 500–502 / 510–514, and the stream control register 410; in stream mode
//! it sends a 16-byte frame every 10 ms (frame k at start + k × 10 ms, so the average
//! rate is exactly 100 Hz even when the serve loop is late) until it receives a run of
//! [`STOP_RUN`] 0xFF bytes.
//!
//! Requests are framed by length (function code and byte count), as the driver frames
//! replies; a request with a bad CRC or for another address gets no reply (Modbus
//! rule), an unknown function exception 01, a register outside the map exception 02,
//! a bad value for 410 exception 03. Faults from [`FaultConfig`] apply per reply and
//! per frame. See `protocols/ft300.md`.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use super::codec::{
    encode_serial, raw_from_wrench, ExceptionCode, Request, Response, StreamFrame, FN_READ_HOLDING,
    FN_WRITE_MULTIPLE, REG_FIRMWARE, REG_SERIAL, REG_STREAM, REG_WRENCH, REG_YEAR, SLAVE_ADDRESS,
    STREAM_START,
};
use crate::device::ft_common::{
    no_faults, FaultConfig, OutQueue, ReplyClass, SimCounters, SimFaults, WrenchSource,
};
use crate::device::pty::{Flow, Simulator};

/// Stream period (100 Hz).
pub const STREAM_PERIOD: Duration = Duration::from_millis(10);
/// Consecutive 0xFF bytes that stop the stream (the host sends about 50).
pub const STOP_RUN: usize = 16;
/// Incomplete request bytes older than this are discarded (a Modbus RTU frame ends
/// with a 3.5-character silence; the simulator uses a generous stand-in).
pub const REQUEST_STALE: Duration = Duration::from_millis(50);

/// Simulator configuration.
#[derive(Debug, Clone)]
pub struct Ft300SimConfig {
    /// Modbus slave address.
    pub slave: u8,
    /// Serial number: three characters (registers 510, 511 high byte) and a 32-bit
    /// number (513 high word, 512 low word), as a real sensor holds it: `FTS-1234`.
    pub serial: ([u8; 3], u32),
    /// Production year (register 514).
    pub year: u16,
    /// Firmware: 3 letters and major, minor, patch (registers 500–502).
    pub firmware: ([u8; 3], [u8; 3]),
    /// Faults to inject (none by default).
    pub faults: FaultConfig,
    /// The Modbus reply to the stream-start write is lost (the stream still starts), as
    /// on links where Robotiq's driver takes the arriving stream as the confirmation.
    pub drop_stream_echo: bool,
    /// The sensor is streaming from power-on (left so by an earlier session), until the
    /// host's stop bytes.
    pub streaming_at_start: bool,
}

impl Default for Ft300SimConfig {
    fn default() -> Self {
        Ft300SimConfig {
            slave: SLAVE_ADDRESS,
            serial: (*b"FTS", 1234),
            year: 2026,
            firmware: (*b"FTS", [3, 0, 1]),
            faults: no_faults(),
            drop_stream_echo: false,
            streaming_at_start: false,
        }
    }
}

/// The simulated FT 300.
pub struct Ft300Sim {
    config: Ft300SimConfig,
    source: Box<dyn WrenchSource>,
    rx: Vec<u8>,
    rx_since: Option<Duration>,
    ff_run: usize,
    stream_next: Option<(Duration, u64)>,
    out: OutQueue,
    faults: SimFaults,
    drop_link: bool,
}

impl Ft300Sim {
    /// A simulator reading its load from `source`.
    pub fn new(config: Ft300SimConfig, source: impl WrenchSource + 'static) -> Self {
        let faults = SimFaults::new(config.faults.clone());
        let stream_next = config.streaming_at_start.then_some((Duration::ZERO, 0));
        Ft300Sim {
            config,
            source: Box::new(source),
            rx: Vec::new(),
            rx_since: None,
            ff_run: 0,
            stream_next,
            out: OutQueue::default(),
            faults,
            drop_link: false,
        }
    }

    /// Counters shared with the caller (replies, frames, injected faults).
    pub fn counters(&self) -> Arc<SimCounters> {
        self.faults.counters()
    }

    fn raw_now(&mut self, now: Duration) -> [i16; 6] {
        raw_from_wrench(&self.source.wrench_at(now))
    }

    fn register(&mut self, reg: u16, now: Duration) -> Option<u16> {
        let serial = encode_serial(self.config.serial.0, self.config.serial.1);
        let (letters, version) = self.config.firmware;
        let fw = [
            letters[0], letters[1], letters[2], version[0], version[1], version[2],
        ];
        match reg {
            r if (REG_WRENCH..REG_WRENCH + 6).contains(&r) => {
                Some(self.raw_now(now)[(r - REG_WRENCH) as usize] as u16)
            }
            r if (REG_FIRMWARE..REG_FIRMWARE + 3).contains(&r) => {
                let i = 2 * (r - REG_FIRMWARE) as usize;
                Some(u16::from_be_bytes([fw[i], fw[i + 1]]))
            }
            r if (REG_SERIAL..REG_SERIAL + 4).contains(&r) => {
                Some(serial[(r - REG_SERIAL) as usize])
            }
            REG_YEAR => Some(self.config.year),
            REG_STREAM => Some(if self.stream_next.is_some() {
                STREAM_START
            } else {
                0
            }),
            _ => None,
        }
    }

    fn handle(&mut self, req: Request, now: Duration) {
        let slave = self.config.slave;
        let exception = |function, code| Response::Exception {
            slave,
            function,
            code,
        };
        let resp = match req {
            Request::ReadHolding { slave: s, .. } | Request::WriteMultiple { slave: s, .. }
                if s != slave =>
            {
                return;
            }
            Request::ReadHolding { start, count, .. } => {
                if count == 0 || count > 125 {
                    exception(FN_READ_HOLDING, ExceptionCode::IllegalDataValue)
                } else {
                    // The wrench registers are sampled once per request (a coherent set).
                    let raw = self.raw_now(now);
                    let values: Option<Vec<u16>> = (start..start.saturating_add(count))
                        .map(|r| {
                            if (REG_WRENCH..REG_WRENCH + 6).contains(&r) {
                                Some(raw[(r - REG_WRENCH) as usize] as u16)
                            } else {
                                self.register(r, now)
                            }
                        })
                        .collect();
                    match values {
                        Some(values) => Response::ReadHolding { slave, values },
                        None => exception(FN_READ_HOLDING, ExceptionCode::IllegalDataAddress),
                    }
                }
            }
            Request::WriteMultiple { start, values, .. } => {
                if start != REG_STREAM || values.len() != 1 {
                    exception(FN_WRITE_MULTIPLE, ExceptionCode::IllegalDataAddress)
                } else if values[0] != STREAM_START {
                    exception(FN_WRITE_MULTIPLE, ExceptionCode::IllegalDataValue)
                } else {
                    let ack = Response::WriteMultiple {
                        slave,
                        start,
                        count: 1,
                    };
                    let started = if self.config.drop_stream_echo {
                        // The echo is lost on the way; the device took the write.
                        self.faults
                            .counters()
                            .replies
                            .fetch_add(1, Ordering::SeqCst);
                        true
                    } else {
                        self.reply(ack.encode(), now, ReplyClass::Command)
                    };
                    if started && self.stream_next.is_none() {
                        self.stream_next = Some((now + STREAM_PERIOD, 0));
                    }
                    return;
                }
            }
        };
        self.reply(resp.encode(), now, ReplyClass::Query);
    }

    fn reset(&mut self) {
        self.rx.clear();
        self.rx_since = None;
        self.ff_run = 0;
        self.stream_next = None;
        self.out.clear();
    }

    /// Sends bytes through the fault injector; false if the device reset or dropped
    /// the link instead.
    fn emit(&mut self, bytes: Vec<u8>, at: Duration, class: ReplyClass) -> bool {
        let plan = self.faults.plan(class);
        if plan.disconnect {
            self.drop_link = true;
            return false;
        }
        if plan.reset {
            self.reset();
            return false;
        }
        let bytes = self.faults.shape(&plan, bytes, flip_bit);
        let at = if plan.late {
            at + self.faults.late_by()
        } else {
            at
        };
        self.out.push(at, bytes);
        true
    }

    fn reply(&mut self, bytes: Vec<u8>, now: Duration, class: ReplyClass) -> bool {
        self.faults
            .counters()
            .replies
            .fetch_add(1, Ordering::SeqCst);
        self.emit(bytes, now, class)
    }

    fn parse_requests(&mut self, now: Duration) {
        loop {
            if self.rx.is_empty() {
                self.rx_since = None;
                return;
            }
            if self.rx[0] == 0xFF {
                // Stop bytes (or line noise): never the start of a request to us.
                self.rx.remove(0);
                continue;
            }
            match Request::frame_len(&self.rx) {
                None => return,
                Some(Err(function)) => {
                    // Unknown function: answer if addressed to us, then drop the
                    // address byte and look again (its length is unknown).
                    if self.rx[0] == self.config.slave {
                        let e = Response::Exception {
                            slave: self.config.slave,
                            function,
                            code: ExceptionCode::IllegalFunction,
                        };
                        self.reply(e.encode(), now, ReplyClass::Query);
                        self.rx.drain(..2);
                    } else {
                        self.rx.remove(0);
                    }
                }
                Some(Ok(n)) if self.rx.len() >= n => match Request::decode(&self.rx[..n]) {
                    Ok(req) => {
                        self.rx.drain(..n);
                        self.handle(req, now);
                    }
                    // Bad CRC: no reply (Modbus rule); slide by one byte.
                    Err(_) => {
                        self.rx.remove(0);
                    }
                },
                Some(Ok(_)) => return,
            }
        }
    }
}

/// FT 300 garble ("bad CRC"): flip one bit in the last three bytes (last payload byte
/// or the CRC), so the framing (address, function, byte count, header) stays intact
/// and only the CRC check can catch it.
fn flip_bit(bytes: &mut [u8], i: usize) {
    if bytes.len() >= 3 {
        let j = bytes.len() - 3 + i % 3;
        bytes[j] ^= 0x01 << (i / 3 % 8);
    }
}

impl Ft300Sim {
    fn receive(&mut self, bytes: &[u8], now: Duration) {
        if self
            .rx_since
            .is_some_and(|t| now.saturating_sub(t) > REQUEST_STALE)
        {
            self.rx.clear();
        }
        for &b in bytes {
            if b == 0xFF {
                self.ff_run += 1;
                if self.ff_run >= STOP_RUN {
                    self.stream_next = None;
                }
            } else {
                self.ff_run = 0;
            }
        }
        if self.rx.is_empty() {
            self.rx_since = Some(now);
        }
        self.rx.extend_from_slice(bytes);
        self.parse_requests(now);
    }
}

impl Simulator for Ft300Sim {
    fn step(&mut self, now: Duration, input: &[u8], output: &mut Vec<u8>) -> Flow {
        if !self.drop_link && !input.is_empty() {
            self.receive(input, now);
        }
        while let Some((due, k)) = self.stream_next {
            if due > now || self.drop_link {
                break;
            }
            self.stream_next = Some((due + STREAM_PERIOD, k + 1));
            let frame = StreamFrame {
                raw: self.raw_now(due),
            }
            .encode()
            .to_vec();
            self.faults.counters().frames.fetch_add(1, Ordering::SeqCst);
            self.emit(frame, due, ReplyClass::Query);
        }
        if self.drop_link {
            return Flow::Hangup;
        }
        self.out.drain_due(now, output);
        Flow::Continue
    }

    fn next_wake(&self, now: Duration) -> Option<Duration> {
        let q = self.out.next_due();
        let s = self.stream_next.map(|(t, _)| t);
        match (q, s) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
        .map(|t| t.saturating_sub(now))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::ft_common::SharedWrench;
    use crate::device::Wrench;

    fn exchange(sim: &mut Ft300Sim, req: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        sim.step(Duration::from_millis(1), req, &mut out);
        out
    }

    fn sim() -> Ft300Sim {
        let w = SharedWrench::new(Wrench {
            force_n: [1.5, -2.0, 12.34],
            torque_nm: [0.1, 0.0, -0.25],
        });
        Ft300Sim::new(Ft300SimConfig::default(), w)
    }

    #[test]
    fn serves_wrench_registers_big_endian() {
        let mut s = sim();
        let req = Request::ReadHolding {
            slave: 9,
            start: 180,
            count: 6,
        }
        .encode();
        let resp = Response::decode(&exchange(&mut s, &req)).unwrap();
        let expect: Vec<u16> = [150i16, -200, 1234, 100, 0, -250]
            .iter()
            .map(|&v| v as u16)
            .collect();
        assert_eq!(
            resp,
            Response::ReadHolding {
                slave: 9,
                values: expect
            }
        );
    }

    #[test]
    fn unknown_register_and_value_give_exceptions() {
        let mut s = sim();
        let req = Request::ReadHolding {
            slave: 9,
            start: 1000,
            count: 1,
        }
        .encode();
        assert_eq!(
            Response::decode(&exchange(&mut s, &req)).unwrap(),
            Response::Exception {
                slave: 9,
                function: 3,
                code: ExceptionCode::IllegalDataAddress
            }
        );
        let req = Request::WriteMultiple {
            slave: 9,
            start: 410,
            values: vec![1],
        }
        .encode();
        assert_eq!(
            Response::decode(&exchange(&mut s, &req)).unwrap(),
            Response::Exception {
                slave: 9,
                function: 16,
                code: ExceptionCode::IllegalDataValue
            }
        );
    }

    #[test]
    fn other_slaves_and_bad_crc_get_no_reply() {
        let mut s = sim();
        let req = Request::ReadHolding {
            slave: 8,
            start: 180,
            count: 6,
        }
        .encode();
        assert!(exchange(&mut s, &req).is_empty());
        let mut req = Request::ReadHolding {
            slave: 9,
            start: 180,
            count: 6,
        }
        .encode();
        req[7] ^= 0xFF;
        assert!(exchange(&mut s, &req).is_empty());
    }

    #[test]
    fn stream_runs_at_100_hz_and_stops_on_ff_run() {
        let mut s = sim();
        let t0 = Duration::from_millis(1);
        let req = Request::WriteMultiple {
            slave: 9,
            start: 410,
            values: vec![STREAM_START],
        }
        .encode();
        let mut out = Vec::new();
        s.step(t0, &req, &mut out);
        assert_eq!(out.len(), 8, "write acknowledgement only");
        out.clear();
        // 1 s later: exactly 100 frames due.
        s.step(t0 + Duration::from_secs(1), &[], &mut out);
        assert_eq!(out.len(), 100 * 16);
        let f = StreamFrame::decode(&out[..16]).unwrap();
        assert_eq!(f.raw, [150, -200, 1234, 100, 0, -250]);
        out.clear();
        s.step(t0 + Duration::from_secs(1), &[0xFF; 50], &mut out);
        s.step(t0 + Duration::from_secs(2), &[], &mut out);
        assert!(out.is_empty());
    }
}
