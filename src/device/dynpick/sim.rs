//! WACOH DynPick simulator: serves the single-byte command protocol from a
//! [`WrenchSource`] (the virtual world, or a test closure).
//!
//! State: record counter (0–9, +1 per record), sensitivities, offset (set by `O` to
//! the current load, so that records read zero there), firmware version string and
//! filter divider n (records average the source over the last n 1-kHz samples:
//! t, t − 1 ms, …, t − (n−1) ms). Unknown bytes are ignored; a digit waits for the
//! `F` that completes `nF` (any other byte cancels it; n ∉ {0, 1, 2, 4, 8} is
//! ignored). Continuous output: `S` starts a record every [`SAMPLE_PERIOD`] (record k
//! due at start + k ms, caught up when the serve loop is late), `E` ends it; commands
//! are still answered in between, their replies interleaved with the records (how a
//! sensor left streaming confuses a host that does not send `E` first). Opt-in
//! behaviours seen with real sensors: [`DynPickSimConfig::streaming_at_start`] and
//! [`DynPickSimConfig::tare_ignored`]. Faults from [`FaultConfig`] apply per reply
//! (not to continuous records). See `protocols/dynpick.md`.

use std::sync::Arc;
use std::time::Duration;

use super::codec::{encode_filter, FilterDivider, Record, Sensitivities};
use crate::device::ft_common::{
    no_faults, FaultConfig, OutQueue, ReplyClass, SimCounters, SimFaults, WrenchSource,
};
use crate::device::pty::{Flow, Simulator};
use crate::device::Wrench;

/// Sensitivities of the simulated sensor (LSB/N, LSB/(N·m)): 32.8 LSB/N gives
/// ±250 N over the 14-bit range, 1638.4 LSB/(N·m) gives ±5 N·m.
pub const DEFAULT_SENSITIVITIES: Sensitivities =
    Sensitivities([32.8, 32.8, 32.8, 1638.4, 1638.4, 1638.4]);
/// Firmware version line of the simulator.
pub const DEFAULT_FIRMWARE: &str = "DynPick simulator 1.0 (tactbench)";
/// Internal sampling period used by the filter average.
pub const SAMPLE_PERIOD: Duration = Duration::from_millis(1);

/// Simulator configuration.
#[derive(Debug, Clone)]
pub struct DynPickSimConfig {
    /// Sensitivities the device reports and uses.
    pub sensitivities: Sensitivities,
    /// `V` reply (without CR LF).
    pub firmware: String,
    /// Faults to inject (none by default).
    pub faults: FaultConfig,
    /// In continuous output from power-on (left so by an earlier program) until `E`.
    pub streaming_at_start: bool,
    /// The first this many `O` commands do nothing (the ROS driver's note: the offset
    /// reset "only works when sent several times").
    pub tare_ignored: u32,
}

impl Default for DynPickSimConfig {
    fn default() -> Self {
        DynPickSimConfig {
            sensitivities: DEFAULT_SENSITIVITIES,
            firmware: DEFAULT_FIRMWARE.to_string(),
            faults: no_faults(),
            streaming_at_start: false,
            tare_ignored: 0,
        }
    }
}

/// The simulated DynPick.
pub struct DynPickSim {
    config: DynPickSimConfig,
    source: Box<dyn WrenchSource>,
    counter: u8,
    filter: FilterDivider,
    offset_lsb: [f64; 6],
    pending_digit: Option<u8>,
    out: OutQueue,
    faults: SimFaults,
    drop_link: bool,
    /// Continuous output: when the next record is due.
    continuous_next: Option<Duration>,
    /// `O` commands still to ignore.
    tare_ignored: u32,
}

impl DynPickSim {
    /// A simulator reading its load from `source`.
    pub fn new(config: DynPickSimConfig, source: impl WrenchSource + 'static) -> Self {
        let faults = SimFaults::new(config.faults.clone());
        let continuous_next = config.streaming_at_start.then_some(Duration::ZERO);
        let tare_ignored = config.tare_ignored;
        DynPickSim {
            continuous_next,
            tare_ignored,
            config,
            source: Box::new(source),
            counter: 0,
            filter: FilterDivider::D1,
            offset_lsb: [0.0; 6],
            pending_digit: None,
            out: OutQueue::default(),
            faults,
            drop_link: false,
        }
    }

    /// Counters shared with the caller (replies, injected faults).
    pub fn counters(&self) -> Arc<SimCounters> {
        self.faults.counters()
    }

    /// Load in LSB per channel at `now`, filter average applied, before offset.
    fn load_lsb(&mut self, t: Duration) -> [f64; 6] {
        let n = self.filter.n();
        let s = self.config.sensitivities.0;
        let mut acc = [0.0; 6];
        for k in 0..n {
            let w: Wrench = self.source.wrench_at(t.saturating_sub(SAMPLE_PERIOD * k));
            let v = [
                w.force_n[0],
                w.force_n[1],
                w.force_n[2],
                w.torque_nm[0],
                w.torque_nm[1],
                w.torque_nm[2],
            ];
            for i in 0..6 {
                acc[i] += v[i] * s[i] / n as f64;
            }
        }
        acc
    }

    fn record(&mut self, now: Duration) -> Vec<u8> {
        let lsb = self.load_lsb(now);
        let s = self.config.sensitivities;
        // Convert the offset-corrected LSB back to a wrench and let the codec round and
        // saturate, so the simulator and the codec share one quantisation rule.
        let w = Wrench {
            force_n: [0, 1, 2].map(|i| (lsb[i] - self.offset_lsb[i]) / s.0[i]),
            torque_nm: [3, 4, 5].map(|i| (lsb[i] - self.offset_lsb[i]) / s.0[i]),
        };
        let r = Record {
            counter: self.counter,
            raw: Record::raw_from_wrench(&w, &s),
        };
        self.counter = (self.counter + 1) % 10;
        r.encode().to_vec()
    }

    fn reset(&mut self) {
        self.counter = 0;
        self.filter = FilterDivider::D1;
        self.offset_lsb = [0.0; 6];
        self.pending_digit = None;
        self.continuous_next = None;
        self.out.clear();
    }

    /// Sends a reply through the fault injector.
    fn reply(&mut self, bytes: Vec<u8>, now: Duration) {
        let counters = self.faults.counters();
        counters
            .replies
            .fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        let plan = self.faults.plan(ReplyClass::Query);
        if plan.disconnect {
            self.drop_link = true;
            return;
        }
        if plan.reset {
            self.reset();
            return;
        }
        let bytes = self.faults.shape(&plan, bytes, garble_ascii);
        let at = if plan.late {
            now + self.faults.late_by()
        } else {
            now
        };
        self.out.push(at, bytes);
    }

    fn command(&mut self, b: u8, now: Duration) {
        if let Some(d) = self.pending_digit.take() {
            if b == b'F' {
                if d == 0 {
                    let line = encode_filter(self.filter);
                    self.reply(line, now);
                } else if let Some(f) = FilterDivider::from_n(d as u32) {
                    self.filter = f;
                }
                return;
            }
        }
        match b {
            b'R' => {
                let r = self.record(now);
                self.reply(r, now);
            }
            b'p' => {
                let l = self.config.sensitivities.encode();
                self.reply(l, now);
            }
            b'O' if self.tare_ignored > 0 => self.tare_ignored -= 1,
            b'O' => self.offset_lsb = self.load_lsb(now),
            b'S' => {
                if self.continuous_next.is_none() {
                    self.continuous_next = Some(now);
                }
            }
            b'E' => self.continuous_next = None,
            b'V' => {
                let l = format!("{}\r\n", self.config.firmware).into_bytes();
                self.reply(l, now);
            }
            b'0'..=b'9' => self.pending_digit = Some(b - b'0'),
            _ => {}
        }
    }
}

/// DynPick garble: a character of the line body becomes `G` (not a hex digit, not a
/// number), so the reply fails to decode.
fn garble_ascii(bytes: &mut [u8], i: usize) {
    if bytes.len() > 2 {
        let n = bytes.len() - 2;
        bytes[i % n] = b'G';
    }
}

impl Simulator for DynPickSim {
    fn step(&mut self, now: Duration, input: &[u8], output: &mut Vec<u8>) -> Flow {
        for &b in input {
            if self.drop_link {
                break;
            }
            self.command(b, now);
        }
        if self.drop_link {
            return Flow::Hangup;
        }
        self.out.drain_due(now, output);
        while let Some(due) = self.continuous_next.filter(|&t| t <= now) {
            self.continuous_next = Some(due + SAMPLE_PERIOD);
            let r = self.record(due);
            output.extend_from_slice(&r);
        }
        Flow::Continue
    }

    fn next_wake(&self, now: Duration) -> Option<Duration> {
        let q = self.out.next_due();
        match (q, self.continuous_next) {
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

    fn run(sim: &mut DynPickSim, input: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        sim.step(Duration::from_millis(5), input, &mut out);
        out
    }

    #[test]
    fn zero_offset_makes_current_load_read_zero() {
        let w = SharedWrench::new(Wrench {
            force_n: [1.0, -2.0, 30.0],
            torque_nm: [0.1, 0.0, -0.2],
        });
        let mut sim = DynPickSim::new(DynPickSimConfig::default(), w.clone());
        let before = Record::decode(&run(&mut sim, b"R")).unwrap();
        assert_eq!(before.raw[2], 8192 + (30.0f64 * 32.8).round() as u16);
        run(&mut sim, b"O");
        let after = Record::decode(&run(&mut sim, b"R")).unwrap();
        assert_eq!(after.raw, [8192; 6]);
        assert_eq!((before.counter, after.counter), (0, 1));
    }

    #[test]
    fn continuous_output_sends_a_record_per_ms_until_e() {
        let cfg = DynPickSimConfig {
            streaming_at_start: true,
            ..DynPickSimConfig::default()
        };
        let mut sim = DynPickSim::new(cfg, SharedWrench::default());
        let mut out = Vec::new();
        // Due at 0, 1, ..., 4 ms.
        sim.step(Duration::from_millis(4), &[], &mut out);
        assert_eq!(out.len(), 5 * 27);
        assert!(Record::decode(&out[27..54]).is_ok());
        out.clear();
        // `V` is answered between records: the reply is interleaved.
        sim.step(Duration::from_millis(5), b"V", &mut out);
        assert!(out.starts_with(b"DynPick simulator"), "{out:?}");
        assert_eq!(out.len(), DEFAULT_FIRMWARE.len() + 2 + 27);
        out.clear();
        sim.step(Duration::from_millis(6), b"E", &mut out);
        sim.step(Duration::from_millis(60), &[], &mut out);
        assert!(out.is_empty());
        // `S` starts it again.
        sim.step(Duration::from_millis(61), b"S", &mut out);
        sim.step(Duration::from_millis(62), &[], &mut out);
        assert_eq!(out.len(), 2 * 27);
    }

    #[test]
    fn tare_ignored_skips_the_first_o_commands() {
        let w = SharedWrench::new(Wrench {
            force_n: [0.0, 0.0, 30.0],
            torque_nm: [0.0; 3],
        });
        let cfg = DynPickSimConfig {
            tare_ignored: 2,
            ..DynPickSimConfig::default()
        };
        let mut sim = DynPickSim::new(cfg, w);
        for _ in 0..2 {
            run(&mut sim, b"O");
            assert_ne!(Record::decode(&run(&mut sim, b"R")).unwrap().raw[2], 8192);
        }
        run(&mut sim, b"O");
        assert_eq!(Record::decode(&run(&mut sim, b"R")).unwrap().raw, [8192; 6]);
    }

    #[test]
    fn filter_divider_is_set_and_read_back() {
        let mut sim = DynPickSim::new(DynPickSimConfig::default(), SharedWrench::default());
        assert_eq!(run(&mut sim, b"0F"), b"1\r\n");
        assert!(run(&mut sim, b"4F").is_empty());
        assert_eq!(run(&mut sim, b"0F"), b"4\r\n");
        // 3 is not a divider: ignored.
        run(&mut sim, b"3F");
        assert_eq!(run(&mut sim, b"0F"), b"4\r\n");
    }

    #[test]
    fn filter_averages_the_last_n_samples() {
        // Fz ramps 1 N per ms: the average over t, t-1, t-2, t-3 ms lags by 1.5 ms.
        let ramp = |t: Duration| Wrench {
            force_n: [0.0, 0.0, t.as_secs_f64() * 1000.0],
            torque_nm: [0.0; 3],
        };
        let mut sim = DynPickSim::new(DynPickSimConfig::default(), ramp);
        run(&mut sim, b"4F");
        let lsb = sim.load_lsb(Duration::from_millis(100));
        assert!((lsb[2] / 32.8 - 98.5).abs() < 1e-9, "{}", lsb[2] / 32.8);
    }
}
