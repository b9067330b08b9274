//! Bota Systems serial sensor simulator: boots printing `App Init` and streams binary
//! frames (as a real sensor does from power-up), answers the configuration commands
//! with `r,0,<cmd>,0`, and serves the wrench of a [`WrenchSource`].
//!
//! Modes: *run* (a frame every `19.53125 µs × sinc_len`, frame k due at start + k
//! periods, caught up when the serve loop is late; the timestamp is the sample time in
//! µs since power-up) and *config* (entered with `C`, the stream stops; `c,…` and
//! `f,…` are answered and applied; `R` runs again). Commands have no terminator (the
//! vendor's example sends none): `C` and `R` act at once; `c,…` / `f,…` act when their
//! four fields are complete and a line end, the next command letter or
//! [`COMMAND_IDLE`] of silence follows. A command that does not parse is ignored.
//!
//! Opt-in: a constant status word on every frame ([`BotaSimConfig::status`], e.g.
//! overrange), the boot text repeated while nobody configures the sensor
//! ([`BotaSimConfig::banner_every`]: a real sensor reboots when its USB port is opened
//! and prints it then, which a pseudo-terminal cannot tell the simulator), and the
//! seeded faults of [`FaultConfig`] per frame (queries) and per answer (commands):
//! late, a byte dropped, garbled (one bit flipped: the CRC fails), garbage before it,
//! a reset (reboot: boot text, run mode, default filter), a disconnect.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use super::codec::{Command, Frame, BOOT_TEXT, SINC_PERIOD_S};
use super::driver::DEFAULT_SINC_LEN;
use crate::device::ft_common::{
    no_faults, FaultConfig, OutQueue, ReplyClass, SimCounters, SimFaults, WrenchSource,
};
use crate::device::pty::{Flow, Simulator};

/// A `c,…` / `f,…` command is complete after this much silence.
pub const COMMAND_IDLE: Duration = Duration::from_millis(5);

/// Simulator configuration.
#[derive(Debug, Clone)]
pub struct BotaSimConfig {
    /// Status word of every frame (0: healthy).
    pub status: u16,
    /// Temperature reported, °C.
    pub temperature_c: f32,
    /// Repeat the boot text this often while in run mode and not yet configured.
    pub banner_every: Option<Duration>,
    /// Faults to inject (none by default).
    pub faults: FaultConfig,
}

impl Default for BotaSimConfig {
    fn default() -> Self {
        BotaSimConfig {
            status: 0,
            temperature_c: 24.5,
            banner_every: None,
            faults: no_faults(),
        }
    }
}

/// The simulated sensor.
pub struct BotaSim {
    config: BotaSimConfig,
    source: Box<dyn WrenchSource>,
    faults: SimFaults,
    out: OutQueue,
    /// Run mode: when the next frame is due.
    next_frame: Option<Duration>,
    sinc_len: u32,
    cmd: Vec<u8>,
    cmd_since: Duration,
    configured: bool,
    next_banner: Option<Duration>,
    boot_pending: bool,
    drop_link: bool,
}

impl BotaSim {
    /// A sensor reading its load from `source`, booting at time 0.
    pub fn new(config: BotaSimConfig, source: impl WrenchSource + 'static) -> Self {
        let faults = SimFaults::new(config.faults.clone());
        let next_banner = config.banner_every;
        BotaSim {
            config,
            source: Box::new(source),
            faults,
            out: OutQueue::default(),
            next_frame: Some(Duration::ZERO),
            sinc_len: DEFAULT_SINC_LEN,
            cmd: Vec::new(),
            cmd_since: Duration::ZERO,
            configured: false,
            next_banner,
            boot_pending: true,
            drop_link: false,
        }
    }

    /// Counters shared with the caller.
    pub fn counters(&self) -> Arc<SimCounters> {
        self.faults.counters()
    }

    fn period(&self) -> Duration {
        Duration::from_secs_f64(SINC_PERIOD_S * self.sinc_len.max(1) as f64)
    }

    fn reboot(&mut self, now: Duration) {
        self.out.clear();
        self.sinc_len = DEFAULT_SINC_LEN;
        self.cmd.clear();
        self.configured = false;
        self.boot_pending = true;
        self.next_frame = Some(now);
    }

    fn emit(&mut self, bytes: Vec<u8>, now: Duration, class: ReplyClass) {
        let plan = self.faults.plan(class);
        if plan.disconnect {
            self.drop_link = true;
            return;
        }
        if plan.reset {
            self.reboot(now);
            return;
        }
        let bytes = self.faults.shape(&plan, bytes, flip_bit);
        let at = if plan.late {
            now + self.faults.late_by()
        } else {
            now
        };
        self.out.push(at, bytes);
    }

    fn answer(&mut self, cmd: Command, now: Duration) {
        self.faults
            .counters()
            .replies
            .fetch_add(1, Ordering::SeqCst);
        let text = format!("{}\r\n", cmd.ack()).into_bytes();
        self.emit(text, now, ReplyClass::Command);
    }

    fn execute(&mut self, cmd: Command, now: Duration) {
        match cmd {
            Command::Config => {
                self.next_frame = None;
                self.configured = true;
                self.answer(cmd, now);
            }
            Command::Run => {
                self.configured = true;
                self.answer(cmd, now);
                if self.next_frame.is_none() {
                    self.next_frame = Some(now + self.period());
                }
            }
            // Settings only apply in config mode, as on the sensor.
            Command::Comm { .. } if self.next_frame.is_none() => self.answer(cmd, now),
            Command::Filter { sinc_len, .. } if self.next_frame.is_none() => {
                if (1..=4096).contains(&sinc_len) {
                    self.sinc_len = sinc_len;
                }
                self.answer(cmd, now);
            }
            Command::Comm { .. } | Command::Filter { .. } => {}
        }
    }

    /// Executes the buffered `c,…` / `f,…` command if it parses.
    fn flush_cmd(&mut self, now: Duration) {
        let text = String::from_utf8_lossy(&self.cmd).into_owned();
        self.cmd.clear();
        if let Some(c) = Command::parse(&text) {
            self.execute(c, now);
        }
    }

    fn receive(&mut self, input: &[u8], now: Duration) {
        for &b in input {
            if self.drop_link {
                return;
            }
            match b {
                b'C' | b'R' | b'c' | b'f' | b'\r' | b'\n' if !self.cmd.is_empty() => {
                    self.flush_cmd(now);
                    if matches!(b, b'\r' | b'\n') {
                        continue;
                    }
                }
                _ => {}
            }
            match b {
                b'C' if self.cmd.is_empty() => self.execute(Command::Config, now),
                b'R' if self.cmd.is_empty() => self.execute(Command::Run, now),
                b'c' | b'f' if self.cmd.is_empty() => {
                    self.cmd.push(b);
                    self.cmd_since = now;
                }
                b'\r' | b'\n' => {}
                _ if !self.cmd.is_empty() => {
                    self.cmd.push(b);
                    self.cmd_since = now;
                    if self.cmd.len() > 64 {
                        self.cmd.clear();
                    }
                }
                _ => {}
            }
        }
    }

    fn frame(&mut self, due: Duration) -> Vec<u8> {
        let w = self.source.wrench_at(due);
        let v = [
            w.force_n[0],
            w.force_n[1],
            w.force_n[2],
            w.torque_nm[0],
            w.torque_nm[1],
            w.torque_nm[2],
        ];
        Frame {
            status: self.config.status,
            values: v.map(|x| x as f32),
            timestamp: due.as_micros() as u32,
            temperature_c: self.config.temperature_c,
        }
        .encode()
        .to_vec()
    }
}

/// Bota garble: flip one bit of the payload or CRC (never the header), so only the
/// CRC can catch it.
fn flip_bit(bytes: &mut [u8], i: usize) {
    if bytes.len() > 1 {
        let j = 1 + i % (bytes.len() - 1);
        bytes[j] ^= 1 << (i / 7 % 8);
    }
}

impl Simulator for BotaSim {
    fn step(&mut self, now: Duration, input: &[u8], output: &mut Vec<u8>) -> Flow {
        if self.boot_pending {
            self.boot_pending = false;
            output.extend_from_slice(format!("\r\n{BOOT_TEXT}\r\n").as_bytes());
        }
        if !self.drop_link {
            self.receive(input, now);
        }
        if !self.cmd.is_empty() && now.saturating_sub(self.cmd_since) >= COMMAND_IDLE {
            self.flush_cmd(now);
        }
        if let Some(t) = self.next_banner.filter(|&t| t <= now) {
            if !self.configured && self.next_frame.is_some() {
                output.extend_from_slice(format!("\r\n{BOOT_TEXT}\r\n").as_bytes());
            }
            self.next_banner = self.config.banner_every.map(|p| t + p);
        }
        while let Some(due) = self.next_frame.filter(|&t| t <= now) {
            if self.drop_link {
                break;
            }
            self.next_frame = Some(due + self.period());
            let f = self.frame(due);
            self.faults.counters().frames.fetch_add(1, Ordering::SeqCst);
            self.emit(f, due, ReplyClass::Query);
        }
        if self.drop_link {
            return Flow::Hangup;
        }
        self.out.drain_due(now, output);
        Flow::Continue
    }

    fn next_wake(&self, now: Duration) -> Option<Duration> {
        let cmd = (!self.cmd.is_empty()).then_some(self.cmd_since + COMMAND_IDLE);
        [self.out.next_due(), self.next_frame, cmd, self.next_banner]
            .into_iter()
            .flatten()
            .min()
            .map(|t| t.saturating_sub(now))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::bota::codec::StreamDecoder;
    use crate::device::ft_common::SharedWrench;
    use crate::device::Wrench;

    fn sim() -> BotaSim {
        let w = SharedWrench::new(Wrench {
            force_n: [1.5, -2.25, 12.34],
            torque_nm: [0.125, -0.05, 0.3],
        });
        BotaSim::new(BotaSimConfig::default(), w)
    }

    fn frames(bytes: &[u8]) -> Vec<Frame> {
        let mut d = StreamDecoder::default();
        let mut out = Vec::new();
        d.push(bytes, &mut out);
        out
    }

    #[test]
    fn boots_streaming_and_configures() {
        let mut s = sim();
        let mut out = Vec::new();
        s.step(Duration::from_millis(95), &[], &mut out);
        assert!(out.starts_with(b"\r\nApp Init\r\n"));
        let f = frames(&out);
        assert_eq!(f.len(), 10, "100 Hz: frames at 0..=90 ms");
        assert_eq!(f[1].timestamp, 10_000);
        assert_eq!(f[0].values[2], 12.34f32);
        out.clear();
        s.step(Duration::from_millis(96), b"C", &mut out);
        assert_eq!(out, b"r,0,C,0\r\n");
        out.clear();
        s.step(Duration::from_millis(97), b"f,256,0,0,1", &mut out);
        assert!(out.is_empty(), "waits for the command to end");
        s.step(Duration::from_millis(103), &[], &mut out);
        assert_eq!(out, b"r,0,f,0\r\n");
        out.clear();
        s.step(Duration::from_millis(200), &[], &mut out);
        assert!(out.is_empty(), "config mode: no stream");
        s.step(Duration::from_millis(200), b"c,0,1,0,4R", &mut out);
        assert_eq!(out, b"r,0,c,0\r\nr,0,R,0\r\n");
        out.clear();
        s.step(Duration::from_millis(250), &[], &mut out);
        assert_eq!(frames(&out).len(), 10, "sinc 256: 5 ms");
    }
}
