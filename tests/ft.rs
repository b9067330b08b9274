//! Force/torque sensors and cameras end to end: transcript replay (driver bytes must
//! match recorded exchanges, every expectation used), each driver against its
//! simulator over a real pseudo-terminal, every injected fault and its outcome, the
//! FT 300 stream without frame loss, and the `tactbench ft` / `camera` CLI.

use std::ffi::OsStr;
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tactbench::device::dynpick::codec::FilterDivider;
use tactbench::device::dynpick::{driver as dp, DynPick, DynPickSim, DynPickSimConfig};
use tactbench::device::ft300::{driver as ft, Ft300, Ft300Sim, Ft300SimConfig};
use tactbench::device::ft_common::{
    no_faults, open_serial, FaultConfig, FaultKind, FaultTarget, SharedWrench, SimCounters,
};
use tactbench::device::pty::PtyServer;
use tactbench::device::replay::{Dir, Replay, Transcript};
use tactbench::device::{ErrorKind, ForceSensor, Wrench};

use crate::util::{
    self, assert_wrench_near, ft_faults, json_wrench, wrench_channels, Served, FT_LOAD,
};

type Port = Box<dyn serialport::SerialPort>;

/// DynPick quantum per channel (1 LSB) with the simulator's sensitivities.
const DP_LSB: [f64; 6] = [
    1.0 / 32.8,
    1.0 / 32.8,
    1.0 / 32.8,
    1.0 / 1638.4,
    1.0 / 1638.4,
    1.0 / 1638.4,
];
/// FT 300 quantum: 0.01 N, 0.001 N·m.
const FT_LSB: [f64; 6] = [0.01, 0.01, 0.01, 0.001, 0.001, 0.001];

fn dynpick_sim(
    faults: FaultConfig,
    load: SharedWrench,
) -> (PtyServer<DynPickSim>, Arc<SimCounters>) {
    let sim = DynPickSim::new(
        DynPickSimConfig {
            faults,
            ..Default::default()
        },
        load,
    );
    let c = sim.counters();
    (PtyServer::spawn(sim, None).expect("pty"), c)
}

fn ft300_sim(faults: FaultConfig, load: SharedWrench) -> (PtyServer<Ft300Sim>, Arc<SimCounters>) {
    let sim = Ft300Sim::new(
        Ft300SimConfig {
            faults,
            ..Default::default()
        },
        load,
    );
    let c = sim.counters();
    (PtyServer::spawn(sim, None).expect("pty"), c)
}

fn open(device: &'static str, path: &Path, baud: u32) -> Port {
    open_serial(device, path.to_str().expect("utf-8 path"), baud).expect("open pty")
}

fn get(c: &std::sync::atomic::AtomicU64) -> u64 {
    c.load(Ordering::SeqCst)
}

// ---------------------------------------------------------------- transcripts

fn escape(bytes: &[u8], all_hex: bool) -> String {
    let mut s = String::new();
    for (i, &b) in bytes.iter().enumerate() {
        match b {
            _ if all_hex => s.push_str(&format!("\\x{b:02X}")),
            // A trailing space would be lost to the parser's trim: escape only that one.
            b' ' if i + 1 < bytes.len() => s.push(' '),
            b'\r' => s.push_str("\\r"),
            b'\n' => s.push_str("\\n"),
            b'\\' => s.push_str("\\\\"),
            0x21..=0x7e => s.push(b as char),
            _ => s.push_str(&format!("\\x{b:02X}")),
        }
    }
    s
}

fn replay_of(name: &str) -> Replay {
    let text = std::fs::read_to_string(transcript_path(name)).expect("transcript");
    Replay::new(Transcript::parse(&text).expect("transcript parses"))
}

/// A recorded session: direction and bytes, consecutive same-direction chunks merged.
type Log = Arc<Mutex<Vec<(Dir, Vec<u8>)>>>;

/// Records a session (for regenerating transcripts from the simulators).
struct Recorder<P> {
    inner: P,
    log: Log,
}

impl<P> Recorder<P> {
    fn push(&self, dir: Dir, bytes: &[u8]) {
        let mut log = self.log.lock().unwrap();
        match log.last_mut() {
            Some((d, b)) if *d == dir => b.extend_from_slice(bytes),
            _ => log.push((dir, bytes.to_vec())),
        }
    }
}

impl<P: Read> Read for Recorder<P> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.push(Dir::Device, &buf[..n]);
        Ok(n)
    }
}

impl<P: Write> Write for Recorder<P> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.push(Dir::Host, &buf[..n]);
        Ok(n)
    }
    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }
}

fn transcript_path(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("protocols/transcripts")
        .join(name)
}

fn write_transcript(name: &str, header: &str, log: &[(Dir, Vec<u8>)], hex: bool) {
    let mut s = String::from(header);
    for (d, b) in log {
        let arrow = if *d == Dir::Host { ">" } else { "<" };
        s.push_str(&format!("{arrow} {}\n", escape(b, hex)));
    }
    std::fs::write(transcript_path(name), s).expect("write transcript");
}

/// The session recorded in `dynpick_session.txt`: connect, version, filter, read, tare,
/// read.
fn dynpick_session<P: Read + Write>(port: P) -> (Vec<Wrench>, String, FilterDivider) {
    let mut d = DynPick::connect(port).expect("connect");
    let fw = d.firmware_version().expect("V");
    d.set_filter(FilterDivider::D2).expect("2F");
    let f = d.filter().expect("0F");
    let a = d.read().expect("R");
    d.tare().expect("O");
    let b = d.read().expect("R");
    (vec![a, b], fw, f)
}

/// The session recorded in `ft300_session.txt`: connect, info, read.
fn ft300_session<P: Read + Write>(port: P) -> (Wrench, ft::Ft300Info) {
    let mut d = Ft300::connect(port).expect("connect");
    let info = d.info().expect("info");
    let w = d.read().expect("read");
    (w, info)
}

/// Regenerates the transcripts from the simulators (run with `--ignored` after a
/// deliberate protocol change, then review the diff).
#[test]
#[ignore]
fn regenerate_transcripts() {
    let (server, _) = dynpick_sim(no_faults(), SharedWrench::new(FT_LOAD));
    let log = Arc::new(Mutex::new(Vec::new()));
    let port = Recorder {
        inner: open("dynpick", server.path(), dp::BAUD),
        log: Arc::clone(&log),
    };
    dynpick_session(port);
    write_transcript(
        "dynpick_session.txt",
        "# DynPick session recorded from the simulator (load Fx 1.5 Fy -2.25 Fz 12.34 N,\n\
         # Mx 0.125 My -0.05 Mz 0.3 N·m): connect (E ends continuous output, no reply; p),\n\
         # V, 2F + 0F (set, read back), 0F, R, O (no reply) + R (the tare took), R. Regenerate: cargo test --test tests ft::regenerate_transcripts\n\
         # -- --ignored. No hardware on the development machines: formats follow\n\
         # protocols/dynpick.md, recorded against the simulator.\n",
        &log.lock().unwrap(),
        false,
    );
    let (server, _) = ft300_sim(no_faults(), SharedWrench::new(FT_LOAD));
    let log = Arc::new(Mutex::new(Vec::new()));
    let port = Recorder {
        inner: open("ft300", server.path(), ft::BAUD),
        log: Arc::clone(&log),
    };
    ft300_session(port);
    write_transcript(
        "ft300_session.txt",
        "# FT 300 session recorded from the simulator (same load), Modbus RTU bytes as\n\
         # \\xHH: connect (50 x FF stop bytes, read 180+6), info (read 500+3, 510+4,\n\
         # 514+1), read 180+6. CRCs checked against codec tests (4B37, C5 CD vectors).\n",
        &log.lock().unwrap(),
        true,
    );
}

#[test]
fn dynpick_transcript_replays_exactly() {
    let mut replay = replay_of("dynpick_session.txt");
    let (ws, fw, f) = dynpick_session(&mut replay);
    replay.finish().expect("every expectation used");
    assert_eq!(fw, "DynPick simulator 1.0 (tactbench)");
    assert_eq!(f, FilterDivider::D2);
    assert_wrench_near(&ws[0], &FT_LOAD, DP_LSB);
    assert_wrench_near(&ws[1], &Wrench::default(), DP_LSB);
}

#[test]
fn ft300_transcript_replays_exactly() {
    let mut replay = replay_of("ft300_session.txt");
    let (w, info) = ft300_session(&mut replay);
    replay.finish().expect("every expectation used");
    assert_eq!(info.serial, "FTS-1234");
    assert_eq!(info.year, 2026);
    assert_eq!(info.firmware, "FTS-3.0.1");
    assert_wrench_near(&w, &FT_LOAD, FT_LSB);
}

#[test]
fn dynpick_replay_fails_when_the_session_stops_early() {
    // Connect only: the rest of the recorded session is left unused.
    let mut replay = replay_of("dynpick_session.txt");
    DynPick::connect(&mut replay).expect("connect");
    assert!(replay.finish().is_err());
}

// ---------------------------------------------------------------- DynPick on a pty

#[test]
fn dynpick_reads_the_simulated_load_over_a_pty() {
    let load = SharedWrench::new(FT_LOAD);
    let (server, counters) = dynpick_sim(no_faults(), load.clone());
    let mut d = DynPick::connect(open("dynpick", server.path(), dp::BAUD)).unwrap();
    assert_eq!(
        d.sensitivities().0,
        [32.8, 32.8, 32.8, 1638.4, 1638.4, 1638.4]
    );
    for _ in 0..20 {
        assert_wrench_near(&d.read().unwrap(), &FT_LOAD, DP_LSB);
    }
    // The counter digit advances once per record (p was reply 1, records follow).
    assert_eq!(d.last_counter(), Some(19 % 10));
    let changed = Wrench {
        force_n: [-100.0, 50.0, 0.0],
        torque_nm: [1.0, -2.0, 0.5],
    };
    load.set(changed);
    assert_wrench_near(&d.read().unwrap(), &changed, DP_LSB);
    assert_eq!(get(&counters.replies), 22);
    assert_eq!(d.stats().retries, 0);
}

#[test]
fn dynpick_tare_zeroes_the_current_load_on_the_device() {
    let (server, _) = dynpick_sim(no_faults(), SharedWrench::new(FT_LOAD));
    let mut d = DynPick::connect(open("dynpick", server.path(), dp::BAUD)).unwrap();
    d.tare().unwrap();
    assert_wrench_near(&d.read().unwrap(), &Wrench::default(), DP_LSB);
    d.set_filter(FilterDivider::D8).unwrap();
    assert_eq!(d.filter().unwrap(), FilterDivider::D8);
    assert_eq!(
        d.firmware_version().unwrap(),
        "DynPick simulator 1.0 (tactbench)"
    );
}

fn dynpick_with(faults: FaultConfig) -> (PtyServer<DynPickSim>, Arc<SimCounters>, DynPick<Port>) {
    // Connect cleanly (the `p` reply is reply 1); faults start with the first record.
    let (server, counters) = dynpick_sim(
        FaultConfig {
            skip: faults.skip.max(1),
            ..faults
        },
        SharedWrench::new(FT_LOAD),
    );
    let d = DynPick::connect(open("dynpick", server.path(), dp::BAUD));
    (server, counters, d.expect("connect"))
}

#[test]
fn dynpick_late_reply_within_timeout_is_simply_slower() {
    let faults = FaultConfig {
        late_by: dp::REPLY_TIMEOUT / 2,
        ..ft_faults(0, &[FaultKind::LateReply], 1.0)
    };
    let (_s, c, mut d) = dynpick_with(faults);
    for _ in 0..5 {
        assert_wrench_near(&d.read().unwrap(), &FT_LOAD, DP_LSB);
    }
    assert_eq!(d.stats().retries, 0);
    assert_eq!(get(&c.late), 5);
}

#[test]
fn dynpick_late_reply_past_timeout_is_discarded_and_retried() {
    // Every 2nd-ish reply late by 1.5 timeouts: the attempt times out, the drain
    // discards the late record, the retry gets a fresh one.
    let faults = FaultConfig {
        late_by: dp::REPLY_TIMEOUT * 3 / 2,
        ..ft_faults(7, &[FaultKind::LateReply], 0.4)
    };
    let (_s, c, mut d) = dynpick_with(faults);
    let mut ok = 0;
    for _ in 0..15 {
        match d.read() {
            Ok(w) => {
                assert_wrench_near(&w, &FT_LOAD, DP_LSB);
                ok += 1;
            }
            // Three late replies in a row: a clear timeout, never a wrong value.
            Err(e) => assert_eq!(e.kind(), ErrorKind::Timeout, "{e}"),
        }
    }
    assert!(ok >= 12, "{ok} of 15 reads succeeded");
    assert!(get(&c.late) > 0);
    assert!(
        d.stats().timeouts > 0 && d.stats().retries > 0,
        "{:?}",
        d.stats()
    );
}

#[test]
fn dynpick_dropped_and_garbled_bytes_are_retried() {
    let faults = ft_faults(3, &[FaultKind::DroppedByte, FaultKind::Garbled], 0.2);
    let (_s, c, mut d) = dynpick_with(faults);
    let mut ok = 0;
    for _ in 0..30 {
        match d.read() {
            Ok(w) => {
                assert_wrench_near(&w, &FT_LOAD, DP_LSB);
                ok += 1;
            }
            // Three bad replies in a row: a clear protocol error, never a wrong value.
            Err(e) => assert_eq!(e.kind(), ErrorKind::Protocol, "{e}"),
        }
    }
    assert!(ok >= 27, "{ok} of 30 reads succeeded");
    assert!(get(&c.dropped) + get(&c.garbled) > 0);
    // Every bad reply cost one attempt: retried, or (third in a row) reported.
    let failed = 30 - ok as u64;
    assert_eq!(
        d.stats().protocol_errors,
        d.stats().retries + failed,
        "{:?}",
        d.stats()
    );
    assert!(d.stats().retries > 0);
}

#[test]
fn dynpick_always_garbled_is_a_protocol_error_with_the_bytes() {
    let faults = ft_faults(0, &[FaultKind::Garbled], 1.0);
    let (server, _) = dynpick_sim(faults, SharedWrench::new(FT_LOAD));
    let e = DynPick::connect(open("dynpick", server.path(), dp::BAUD))
        .err()
        .expect("must fail");
    assert_eq!(e.kind(), ErrorKind::Protocol);
    assert_eq!(e.command, "p");
    assert!(
        e.message.contains('G') && e.message.contains("after 3 attempts"),
        "{e}"
    );
}

#[test]
fn dynpick_unsolicited_bytes_are_skipped_without_retry() {
    let faults = ft_faults(11, &[FaultKind::Unsolicited], 1.0);
    let (_s, c, mut d) = dynpick_with(faults);
    for _ in 0..20 {
        assert_wrench_near(&d.read().unwrap(), &FT_LOAD, DP_LSB);
    }
    assert_eq!(get(&c.unsolicited), 20);
    assert_eq!(d.stats().retries, 0, "{:?}", d.stats());
    assert!(d.stats().resyncs > 0);
}

#[test]
fn dynpick_reset_recovers_by_retry_but_loses_the_device_tare() {
    let faults = ft_faults(5, &[FaultKind::DeviceReset], 0.15);
    let (_s, c, mut d) = dynpick_with(faults);
    d.tare().unwrap();
    let mut saw_untared = false;
    for _ in 0..30 {
        let w = d.read().unwrap();
        let near_zero = wrench_channels(&w)
            .iter()
            .zip(DP_LSB)
            .all(|(v, l)| v.abs() <= 0.5 * l + 1e-9);
        if !near_zero {
            // After a reset the device offset is gone: the full load reads again.
            assert_wrench_near(&w, &FT_LOAD, DP_LSB);
            saw_untared = true;
        }
    }
    assert!(get(&c.resets) > 0);
    assert!(saw_untared, "a reset must make the tare visible as lost");
    assert!(d.stats().timeouts > 0);
}

#[test]
fn dynpick_disconnect_is_reported_without_retry() {
    let faults = FaultConfig::once(FaultKind::Disconnect, FaultTarget::Any, 4);
    let (server, _, mut d) = dynpick_with(faults);
    for _ in 0..3 {
        d.read().unwrap();
    }
    let t = Instant::now();
    let e = d.read().unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
    assert!(server.is_finished() || t.elapsed() < Duration::from_secs(5));
}

#[test]
fn dynpick_connect_ends_continuous_output_left_running() {
    // A sensor left in continuous output (`S`) by an earlier program: without `E` at
    // connect, `V` could be answered by a data record taken for the version.
    for run in 0..3 {
        let sim = DynPickSim::new(
            DynPickSimConfig {
                streaming_at_start: true,
                ..Default::default()
            },
            SharedWrench::new(FT_LOAD),
        );
        let server = PtyServer::spawn(sim, None).expect("pty");
        // Let records pile up in the pty before the host connects.
        std::thread::sleep(Duration::from_millis(20));
        let mut d = DynPick::connect(open("dynpick", server.path(), dp::BAUD)).expect("connect");
        assert_eq!(
            d.firmware_version().unwrap(),
            "DynPick simulator 1.0 (tactbench)",
            "run {run}"
        );
        assert_eq!(d.filter().unwrap(), FilterDivider::D1);
        for _ in 0..5 {
            assert_wrench_near(&d.read().unwrap(), &FT_LOAD, DP_LSB);
        }
        assert_eq!(d.stats().retries, 0, "run {run}: {:?}", d.stats());
    }
}

#[test]
fn dynpick_version_is_never_a_data_record() {
    // A record arriving where the `V` line is expected (a sensor streaming again) is
    // skipped, not returned as the firmware version.
    let text = "> E\n> p\n< 32.800,32.800,32.800,1638.400,1638.400,1638.400\\r\\n\n\
                > V\n< 020311FB6219520CD1FAE21EC\\r\\n\n< WACOH DynPick 2.1\\r\\n\n";
    let mut replay = Replay::new(Transcript::parse(text).expect("transcript"));
    let mut d = DynPick::connect(&mut replay).expect("connect");
    assert_eq!(d.firmware_version().unwrap(), "WACOH DynPick 2.1");
    assert_eq!(d.stats().retries, 0);
    replay.finish().expect("every expectation used");
}

#[test]
fn dynpick_tare_is_verified_and_repeated_until_it_takes() {
    // The first two `O` are ignored, as the ROS driver's note says happens.
    let sim = DynPickSim::new(
        DynPickSimConfig {
            tare_ignored: 2,
            ..Default::default()
        },
        SharedWrench::new(FT_LOAD),
    );
    let server = PtyServer::spawn(sim, None).expect("pty");
    let mut d = DynPick::connect(open("dynpick", server.path(), dp::BAUD)).unwrap();
    assert_eq!(d.tare_verified().unwrap(), 3, "took at the third `O`");
    assert_wrench_near(&d.read().unwrap(), &Wrench::default(), DP_LSB);
    // Through the trait too: already tared, takes at once.
    d.tare().unwrap();
    assert_wrench_near(&d.read().unwrap(), &Wrench::default(), DP_LSB);
}

#[test]
fn dynpick_tare_that_never_takes_is_a_clear_error() {
    let sim = DynPickSim::new(
        DynPickSimConfig {
            tare_ignored: 100,
            ..Default::default()
        },
        SharedWrench::new(FT_LOAD),
    );
    let counters = sim.counters();
    let server = PtyServer::spawn(sim, None).expect("pty");
    let mut d = DynPick::connect(open("dynpick", server.path(), dp::BAUD)).unwrap();
    let e = d.tare().unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Rejected, "{e}");
    let text = e.to_string();
    assert!(
        text.contains(&format!(
            "tare did not take after {} `O` commands",
            dp::TARE_ATTEMPTS
        )) && text.contains("tolerance ±16 LSB")
            && text.contains("+405"),
        "{text}"
    );
    // One read-back per `O` (p was reply 1), bounded.
    assert_eq!(get(&counters.replies), 1 + dp::TARE_ATTEMPTS as u64);
}

// ---------------------------------------------------------------- FT 300 on a pty

fn ft300_with(faults: FaultConfig) -> (PtyServer<Ft300Sim>, Arc<SimCounters>, Ft300<Port>) {
    // Connect cleanly (one read of the wrench); faults start after it.
    let (server, counters) = ft300_sim(
        FaultConfig {
            skip: faults.skip.max(1),
            ..faults
        },
        SharedWrench::new(FT_LOAD),
    );
    let d = Ft300::connect(open("ft300", server.path(), ft::BAUD)).expect("connect");
    (server, counters, d)
}

#[test]
fn ft300_polled_reads_info_and_software_tare() {
    let (_s, _c, mut d) = ft300_with(no_faults());
    for _ in 0..10 {
        assert_wrench_near(&d.read().unwrap(), &FT_LOAD, FT_LSB);
    }
    let info = d.info().unwrap();
    assert_eq!(
        (info.serial.as_str(), info.year, info.firmware.as_str()),
        ("FTS-1234", 2026, "FTS-3.0.1")
    );
    d.tare().unwrap();
    assert_wrench_near(&d.read().unwrap(), &Wrench::default(), FT_LSB);
    assert_wrench_near(&d.read_raw_wrench().unwrap(), &FT_LOAD, FT_LSB);
}

#[test]
fn ft300_exception_is_rejected_and_not_retried() {
    let (_s, c, mut d) = ft300_with(no_faults());
    let before = get(&c.replies);
    let e = d.read_registers(1000, 2).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Rejected);
    assert!(e.message.contains("illegal data address"), "{e}");
    assert_eq!(e.command, "read 1000+2");
    assert_eq!(get(&c.replies), before + 1);
    let e = d.write_registers(410, &[1]).unwrap_err();
    assert!(e.message.contains("illegal data value"), "{e}");
}

#[test]
fn ft300_late_dropped_garbled_and_unsolicited_replies_recover() {
    let faults = FaultConfig {
        late_by: ft::REPLY_TIMEOUT * 3 / 2,
        ..ft_faults(
            21,
            &[
                FaultKind::LateReply,
                FaultKind::DroppedByte,
                FaultKind::Garbled,
                FaultKind::Unsolicited,
            ],
            0.4,
        )
    };
    let (_s, c, mut d) = ft300_with(faults);
    let mut ok = 0;
    for _ in 0..30 {
        match d.read() {
            Ok(w) => {
                assert_wrench_near(&w, &FT_LOAD, FT_LSB);
                ok += 1;
            }
            Err(e) => assert!(
                matches!(e.kind(), ErrorKind::Timeout | ErrorKind::Protocol),
                "{e}"
            ),
        }
    }
    assert!(ok >= 28, "{ok} of 30");
    let s = d.stats();
    assert!(get(&c.late) + get(&c.dropped) + get(&c.garbled) > 0);
    assert!(s.retries > 0 && s.resyncs > 0, "{s:?}");
}

#[test]
fn ft300_and_dynpick_reply_deadlines_are_set_at_connect() {
    // Every reply 150 ms late: past the FT 300's default 100 ms deadline (the test
    // above shows the retries), inside the 500 ms the simulated bench allows.
    let late = FaultConfig {
        late_by: Duration::from_millis(150),
        ..ft_faults(0, &[FaultKind::LateReply], 1.0)
    };
    let (server, c) = ft300_sim(late.clone(), SharedWrench::new(FT_LOAD));
    let slow = Duration::from_millis(500);
    let mut d = Ft300::connect_with(open("ft300", server.path(), ft::BAUD), 9, slow)
        .expect("a 150 ms late reply is within a 500 ms deadline");
    for _ in 0..3 {
        assert_wrench_near(&d.read().unwrap(), &FT_LOAD, FT_LSB);
    }
    assert_eq!(d.stats().timeouts, 0, "{:?}", d.stats());
    assert!(get(&c.late) >= 4);
    // The same late device with the default deadline: every attempt times out.
    let (server, _) = ft300_sim(late, SharedWrench::new(FT_LOAD));
    let e = Ft300::connect(open("ft300", server.path(), ft::BAUD))
        .err()
        .expect("150 ms late is past the default deadline");
    assert_eq!(e.kind(), ErrorKind::Timeout, "{e}");
    assert!(e.message.contains("within 100 ms"), "{e}");

    // DynPick: 75 ms late, past its 50 ms default.
    let late = FaultConfig {
        late_by: dp::REPLY_TIMEOUT * 3 / 2,
        ..ft_faults(0, &[FaultKind::LateReply], 1.0)
    };
    let (server, _) = dynpick_sim(late.clone(), SharedWrench::new(FT_LOAD));
    let mut d = DynPick::connect_with(open("dynpick", server.path(), dp::BAUD), slow)
        .expect("within 500 ms");
    assert_wrench_near(&d.read().unwrap(), &FT_LOAD, DP_LSB);
    assert_eq!(d.stats().timeouts, 0, "{:?}", d.stats());
    let (server, _) = dynpick_sim(late, SharedWrench::new(FT_LOAD));
    let e = DynPick::connect(open("dynpick", server.path(), dp::BAUD))
        .err()
        .expect("past the default deadline");
    assert_eq!(e.kind(), ErrorKind::Timeout, "{e}");
}

#[test]
fn read_once_makes_one_attempt_and_the_next_read_discards_its_late_reply() {
    // DynPick: replies 1 (`p` at connect), 2 and 3 on time, reply 4 late by 1.5
    // deadlines, the rest on time.
    let late = FaultConfig {
        late_by: dp::REPLY_TIMEOUT * 3 / 2,
        ..FaultConfig::once(FaultKind::LateReply, FaultTarget::Any, 3)
    };
    let (server, c) = dynpick_sim(late, SharedWrench::new(FT_LOAD));
    let mut d = DynPick::connect(open("dynpick", server.path(), dp::BAUD)).unwrap();
    for _ in 0..2 {
        assert_wrench_near(&d.read_once().unwrap(), &FT_LOAD, DP_LSB);
    }
    assert_eq!(d.last_counter(), Some(1));
    let e = d.read_once().unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Timeout, "{e}");
    assert!(e.message.contains("after 1 attempt)"), "{e}");
    assert_eq!((d.stats().timeouts, d.stats().retries), (1, 0));
    // The late record (counter 2) arrives after the deadline; the next read drains it
    // and takes a fresh one (counter 3), not the stale reply.
    assert_wrench_near(&d.read().unwrap(), &FT_LOAD, DP_LSB);
    assert_eq!(d.last_counter(), Some(3));
    assert_eq!(get(&c.late), 1);

    // FT 300: reply 1 is the connect's read; reply 2 late.
    let late = FaultConfig {
        late_by: ft::REPLY_TIMEOUT * 3 / 2,
        ..FaultConfig::once(FaultKind::LateReply, FaultTarget::Any, 1)
    };
    let (server, c) = ft300_sim(late, SharedWrench::new(FT_LOAD));
    let mut d = Ft300::connect(open("ft300", server.path(), ft::BAUD)).unwrap();
    let e = d.read_once().unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Timeout, "{e}");
    assert_eq!((d.stats().timeouts, d.stats().retries), (1, 0));
    for _ in 0..3 {
        assert_wrench_near(&d.read().unwrap(), &FT_LOAD, FT_LSB);
    }
    assert_eq!(d.stats().retries, 0, "{:?}", d.stats());
    assert_eq!(get(&c.late), 1);
}

#[test]
fn ft300_always_bad_crc_is_a_protocol_error() {
    let (server, _) = ft300_sim(
        ft_faults(0, &[FaultKind::Garbled], 1.0),
        SharedWrench::new(FT_LOAD),
    );
    let e = Ft300::connect(open("ft300", server.path(), ft::BAUD))
        .err()
        .expect("must fail");
    assert_eq!(e.kind(), ErrorKind::Protocol, "{e}");
    assert!(e.message.contains("bad crc"), "{e}");
}

#[test]
fn ft300_always_dropped_byte_is_a_timeout_on_the_incomplete_reply() {
    let (server, _) = ft300_sim(
        ft_faults(0, &[FaultKind::DroppedByte], 1.0),
        SharedWrench::new(FT_LOAD),
    );
    let e = Ft300::connect(open("ft300", server.path(), ft::BAUD))
        .err()
        .expect("must fail");
    assert!(
        matches!(e.kind(), ErrorKind::Timeout | ErrorKind::Protocol),
        "{e}"
    );
}

#[test]
fn ft300_reset_is_retried_and_keeps_the_software_tare() {
    let faults = ft_faults(9, &[FaultKind::DeviceReset], 0.15);
    let (_s, c, mut d) = ft300_with(faults);
    d.tare().unwrap();
    for _ in 0..30 {
        // The offset lives in the driver: resets do not undo it.
        assert_wrench_near(&d.read().unwrap(), &Wrench::default(), FT_LSB);
    }
    assert!(get(&c.resets) > 0);
    assert!(d.stats().timeouts > 0);
}

#[test]
fn ft300_disconnect_is_reported() {
    let (_s, _c, mut d) = ft300_with(FaultConfig::once(
        FaultKind::Disconnect,
        FaultTarget::Any,
        3,
    ));
    d.read().unwrap();
    d.read().unwrap();
    let e = d.read().unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
}

#[test]
fn ft300_stream_delivers_every_frame_for_1_5_s() {
    let (server, c) = ft300_sim(no_faults(), SharedWrench::new(FT_LOAD));
    let d = Ft300::connect(open("ft300", server.path(), ft::BAUD)).unwrap();
    let mut s = d.start_stream().unwrap();
    assert_eq!(s.sample_rate_hz(), 100.0);
    let start = Instant::now();
    let mut samples = Vec::new();
    let mut reads = 0;
    while start.elapsed() < Duration::from_millis(1500) {
        assert_wrench_near(&s.read().unwrap(), &FT_LOAD, FT_LSB);
        reads += 1;
        samples.extend(s.take_samples());
    }
    let (mut d, summary) = s.stop().unwrap();
    samples.extend(summary.remaining);
    // Lossless: every frame the simulator sent was decoded, in order, none corrupt.
    let sent = get(&c.frames);
    assert!(sent >= 100, "{sent} frames in 1.5 s");
    assert_eq!(samples.len() as u64, sent);
    assert_eq!(summary.stats.frames, sent);
    assert_eq!(
        (
            summary.stats.bad_crc,
            summary.stats.bytes_skipped,
            summary.overflowed
        ),
        (0, 0, 0)
    );
    for (i, x) in samples.iter().enumerate() {
        assert_eq!(x.seq, i as u64 + 1, "stream sequence");
        assert_wrench_near(&x.raw_wrench, &FT_LOAD, FT_LSB);
    }
    assert!(reads > 0);
    // After the stream, polled reads work again.
    assert_wrench_near(&d.read().unwrap(), &FT_LOAD, FT_LSB);
}

#[test]
fn ft300_stream_resyncs_after_dropped_garbled_and_unsolicited_bytes() {
    let faults = FaultConfig {
        late_by: Duration::from_millis(25),
        ..ft_faults(
            4,
            &[
                FaultKind::LateReply,
                FaultKind::DroppedByte,
                FaultKind::Garbled,
                FaultKind::Unsolicited,
            ],
            0.2,
        )
    };
    let (server, c) = ft300_sim(faults, SharedWrench::new(FT_LOAD));
    let d = Ft300::connect(open("ft300", server.path(), ft::BAUD)).unwrap();
    let mut s = d.start_stream().unwrap();
    let start = Instant::now();
    let mut samples = Vec::new();
    while start.elapsed() < Duration::from_millis(1000) {
        // Every sample that gets through is correct (CRC-checked).
        assert_wrench_near(&s.read().unwrap(), &FT_LOAD, FT_LSB);
        samples.extend(s.take_samples());
    }
    let (_d, summary) = s.stop().unwrap();
    samples.extend(summary.remaining);
    let sent = get(&c.frames);
    let damaged = get(&c.dropped) + get(&c.garbled);
    assert!(damaged > 0 && get(&c.unsolicited) > 0);
    // Each damaged frame is lost, and may take its neighbour with it when garbage or
    // a drop splices two frames; nothing else is lost.
    let lost = sent - samples.len() as u64;
    assert!(
        lost >= 1 && lost <= 2 * damaged,
        "lost {lost} of {sent}, damaged {damaged}"
    );
    assert!(
        summary.stats.bad_crc > 0 && summary.stats.bytes_skipped > 0,
        "{:?}",
        summary.stats
    );
}

#[test]
fn ft300_stream_restarts_after_a_device_reset() {
    let faults = ft_faults(2, &[FaultKind::DeviceReset], 0.01);
    let (server, c) = ft300_sim(faults, SharedWrench::new(FT_LOAD));
    let d = Ft300::connect(open("ft300", server.path(), ft::BAUD)).unwrap();
    let mut s = d.start_stream().unwrap();
    let start = Instant::now();
    let mut ok = 0;
    while start.elapsed() < Duration::from_millis(2000) {
        match s.read() {
            Ok(w) => {
                assert_wrench_near(&w, &FT_LOAD, FT_LSB);
                ok += 1;
            }
            // While the stream is down, reads time out clearly.
            Err(e) => assert_eq!(e.kind(), ErrorKind::Timeout, "{e}"),
        }
    }
    let (_d, summary) = s.stop().unwrap();
    assert!(get(&c.resets) > 0);
    assert!(summary.stats.restarts >= 1, "{:?}", summary.stats);
    assert!(ok > 50, "{ok} good reads");
}

#[test]
fn ft300_stream_disconnect_is_reported() {
    let faults = FaultConfig::once(FaultKind::Disconnect, FaultTarget::Any, 30);
    let (server, _) = ft300_sim(faults, SharedWrench::new(FT_LOAD));
    let d = Ft300::connect(open("ft300", server.path(), ft::BAUD)).unwrap();
    let mut s = d.start_stream().unwrap();
    let e = loop {
        match s.read() {
            Ok(_) => continue,
            Err(e) => break e,
        }
    };
    assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
}

fn ft300_sim_with(cfg: Ft300SimConfig) -> (PtyServer<Ft300Sim>, Arc<SimCounters>) {
    let sim = Ft300Sim::new(cfg, SharedWrench::new(FT_LOAD));
    let c = sim.counters();
    (PtyServer::spawn(sim, None).expect("pty"), c)
}

/// Whether the simulator sends no stream frame for 150 ms (15 periods).
fn ft300_sim_is_quiet(c: &SimCounters) -> bool {
    let before = get(&c.frames);
    std::thread::sleep(Duration::from_millis(150));
    get(&c.frames) == before
}

#[test]
fn ft300_serial_number_decodes_as_the_vendor_driver_does() {
    // Registers 510-513: 'F' 'T' | 'S' 0 | low word | high word.
    for (number, text) in [(1234, "FTS-1234"), (70_000, "FTS-70000"), (42, "FTS-0042")] {
        let (server, _) = ft300_sim_with(Ft300SimConfig {
            serial: (*b"FTS", number),
            ..Default::default()
        });
        let mut d = Ft300::connect(open("ft300", server.path(), ft::BAUD)).unwrap();
        assert_eq!(d.info().unwrap().serial, text);
    }
}

#[test]
fn ft300_stream_start_without_echo_is_confirmed_by_the_stream() {
    let (server, c) = ft300_sim_with(Ft300SimConfig {
        drop_stream_echo: true,
        ..Default::default()
    });
    let d = Ft300::connect(open("ft300", server.path(), ft::BAUD)).unwrap();
    let mut s = d
        .start_stream()
        .expect("the arriving stream confirms the start");
    for _ in 0..20 {
        assert_wrench_near(&s.read().unwrap(), &FT_LOAD, FT_LSB);
    }
    let (mut d, summary) = s.stop().unwrap();
    // Confirmed on the first attempt by the first frame: no frame lost, none repeated.
    assert_eq!(d.stats().retries, 0, "{:?}", d.stats());
    assert_eq!(summary.stats.frames, get(&c.frames));
    assert_eq!((summary.stats.bad_crc, summary.stats.bytes_skipped), (0, 0));
    assert!(ft300_sim_is_quiet(&c), "stopped");
    assert_wrench_near(&d.read().unwrap(), &FT_LOAD, FT_LSB);
}

#[test]
fn ft300_failed_stream_start_leaves_the_sensor_stopped() {
    // The device takes the write, but the echo is lost and every frame fails its CRC:
    // nothing confirms the start. The driver must stop the stream it cannot see.
    let (server, c) = ft300_sim_with(Ft300SimConfig {
        drop_stream_echo: true,
        faults: FaultConfig {
            skip: 1, // the connect read
            ..ft_faults(6, &[FaultKind::Garbled], 1.0)
        },
        ..Default::default()
    });
    let d = Ft300::connect(open("ft300", server.path(), ft::BAUD)).unwrap();
    let e = match d.start_stream() {
        Ok(_) => panic!("a stream of bad frames must not confirm the start"),
        Err(e) => e,
    };
    assert_eq!(e.kind(), ErrorKind::Timeout, "{e}");
    let text = e.to_string();
    assert!(
        text.contains("stream start not confirmed")
            && text.contains("failed the CRC")
            && text.contains("after 3 attempts")
            && text.contains("stop bytes sent, the line is quiet"),
        "{text}"
    );
    assert!(get(&c.frames) > 0, "the device did stream");
    assert!(ft300_sim_is_quiet(&c), "left streaming");
}

#[test]
fn ft300_stream_start_exception_is_rejected() {
    // A slave that refuses the write (another slave's register map): not retried.
    let (server, c) = ft300_sim_with(Ft300SimConfig::default());
    let d = Ft300::connect(open("ft300", server.path(), ft::BAUD)).unwrap();
    let mut d = d;
    let e = d.write_registers(410, &[1]).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Rejected, "{e}");
    assert!(ft300_sim_is_quiet(&c));
}

#[test]
fn ft300_connect_stops_a_stream_left_running() {
    let (server, c) = ft300_sim_with(Ft300SimConfig {
        streaming_at_start: true,
        ..Default::default()
    });
    std::thread::sleep(Duration::from_millis(30));
    let mut d = Ft300::connect(open("ft300", server.path(), ft::BAUD)).expect("connect");
    assert!(get(&c.frames) > 0, "was streaming");
    assert!(ft300_sim_is_quiet(&c), "stopped at connect");
    assert_eq!(d.info().unwrap().serial, "FTS-1234");
    assert_wrench_near(&d.read().unwrap(), &FT_LOAD, FT_LSB);
    assert_eq!(d.stats().retries, 0, "{:?}", d.stats());
}

#[test]
fn ft300_dropped_stream_is_stopped_on_the_device() {
    // An error path that drops the stream without `stop()` (e.g. `?` on a read) must
    // not leave the sensor streaming.
    let (server, c) = ft300_sim(no_faults(), SharedWrench::new(FT_LOAD));
    let d = Ft300::connect(open("ft300", server.path(), ft::BAUD)).unwrap();
    let mut s = d.start_stream().unwrap();
    s.read().unwrap();
    drop(s);
    assert!(ft300_sim_is_quiet(&c), "left streaming after drop");
}

// ---------------------------------------------------------------- CLI end to end

/// Starts `tactbench sim-serve-ft` and waits for its "serving" line.
fn serve(protocol: &str, link: &Path) -> Served {
    serve_with(protocol, link, &[])
}

/// As [`serve`], with extra arguments (faults).
fn serve_with(protocol: &str, link: &Path, extra: &[&str]) -> Served {
    let mut args = vec![OsStr::new("--link"), link.as_os_str()];
    args.extend(extra.iter().map(OsStr::new));
    let (served, line) = util::serve_ft(protocol, &args);
    assert!(line.starts_with("serving simulated"), "{line}");
    served
}

fn run_ok(args: &[&str], port: &Path) -> String {
    let out = util::command()
        .args(["ft", "--port"])
        .arg(port)
        .args(args)
        .output()
        .expect("run");
    assert!(
        out.status.success(),
        "tactbench ft {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("utf-8")
}

#[test]
fn cli_ft_dynpick_read_info_tare_against_a_served_simulator() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("dynpick");
    let _sim = serve("dynpick", &link);
    let out = run_ok(
        &["--protocol", "dynpick", "read", "--samples", "3", "--json"],
        &link,
    );
    let v: serde_json::Value = serde_json::from_str(&out).expect("json");
    assert_eq!(v["protocol"], "dynpick");
    let samples = v["samples"].as_array().expect("samples");
    assert_eq!(samples.len(), 3);
    for s in samples {
        assert_wrench_near(&json_wrench(s), &FT_LOAD, DP_LSB);
    }
    assert_wrench_near(&json_wrench(&v["mean"]), &FT_LOAD, DP_LSB);
    let text = run_ok(&["--protocol", "dynpick", "read"], &link);
    assert!(
        text.contains("Fz   +12.317 N") || text.contains("Fz   +12.348 N"),
        "{text}"
    );
    let info = run_ok(&["--protocol", "dynpick", "info", "--json"], &link);
    let v: serde_json::Value = serde_json::from_str(&info).expect("json");
    assert_eq!(v["firmware"], "DynPick simulator 1.0 (tactbench)");
    assert_eq!(v["filter_divider"], "1");
    // Tare is kept by the device across invocations.
    run_ok(&["--protocol", "dynpick", "tare"], &link);
    let out = run_ok(&["--protocol", "dynpick", "read", "--json"], &link);
    let v: serde_json::Value = serde_json::from_str(&out).expect("json");
    assert_wrench_near(&json_wrench(&v["mean"]), &Wrench::default(), DP_LSB);
}

#[test]
fn cli_ft_ft300_polled_stream_and_info_against_a_served_simulator() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ft300");
    let _sim = serve("ft300", &link);
    for extra in [&[][..], &["--stream"][..]] {
        let mut args = vec!["--protocol", "ft300", "read", "--samples", "5", "--json"];
        args.extend_from_slice(extra);
        let v: serde_json::Value = serde_json::from_str(&run_ok(&args, &link)).expect("json");
        assert_eq!(v["samples"].as_array().map(Vec::len), Some(5));
        assert_wrench_near(&json_wrench(&v["mean"]), &FT_LOAD, FT_LSB);
    }
    let v: serde_json::Value = serde_json::from_str(&run_ok(
        &["--protocol", "ft300", "read", "--tare", "--json"],
        &link,
    ))
    .expect("json");
    assert_wrench_near(&json_wrench(&v["mean"]), &Wrench::default(), FT_LSB);
    let info = run_ok(&["--protocol", "ft300", "info"], &link);
    assert!(
        info.contains("serial: FTS-1234") && info.contains("production_year: 2026"),
        "{info}"
    );
    let out = util::command()
        .args(["ft", "--port"])
        .arg(&link)
        .args(["--protocol", "ft300", "tare"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("software offset"));
}

#[test]
fn cli_ft_dynpick_left_streaming_info_and_a_tare_that_needs_three_tries() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("dynpick");
    let _sim = serve_with("dynpick", &link, &["--streaming", "--tare-ignored", "2"]);
    let info = run_ok(&["--protocol", "dynpick", "info", "--json"], &link);
    let v: serde_json::Value = serde_json::from_str(&info).expect("json");
    assert_eq!(v["firmware"], "DynPick simulator 1.0 (tactbench)");
    let out = run_ok(&["--protocol", "dynpick", "tare"], &link);
    assert!(out.starts_with("tared (3 `O` commands sent); now"), "{out}");
    let out = run_ok(&["--protocol", "dynpick", "read", "--json"], &link);
    let v: serde_json::Value = serde_json::from_str(&out).expect("json");
    assert_wrench_near(&json_wrench(&v["mean"]), &Wrench::default(), DP_LSB);
}

#[test]
fn cli_ft_ft300_left_streaming_serial_and_stream_without_echo() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ft300");
    let _sim = serve_with("ft300", &link, &["--streaming", "--drop-stream-echo"]);
    let info = run_ok(&["--protocol", "ft300", "info", "--json"], &link);
    let v: serde_json::Value = serde_json::from_str(&info).expect("json");
    assert_eq!(v["serial"], "FTS-1234");
    let args = [
        "--protocol",
        "ft300",
        "read",
        "--stream",
        "--samples",
        "5",
        "--json",
    ];
    let v: serde_json::Value = serde_json::from_str(&run_ok(&args, &link)).expect("json");
    assert_eq!(v["samples"].as_array().map(Vec::len), Some(5));
    assert_wrench_near(&json_wrench(&v["mean"]), &FT_LOAD, FT_LSB);
    // Stopped after the read: polled reads answer.
    let v: serde_json::Value =
        serde_json::from_str(&run_ok(&["--protocol", "ft300", "read", "--json"], &link))
            .expect("json");
    assert_wrench_near(&json_wrench(&v["mean"]), &FT_LOAD, FT_LSB);
}

#[test]
fn cli_ft_reports_a_simulated_disconnect_with_exit_code_2() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("dynpick");
    // p and two records pass, the third record's reply is a hang-up.
    let _sim = serve_with(
        "dynpick",
        &link,
        &["--fault", "disconnect", "--fault-skip", "3"],
    );
    let out = util::command()
        .args(["ft", "--port"])
        .arg(&link)
        .args(["--protocol", "dynpick", "read", "--samples", "5"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("dynpick: `R` failed (disconnected)"), "{err}");
}

#[test]
fn cli_ft_missing_port_is_a_clear_error() {
    let out = util::command()
        .args([
            "ft",
            "--port",
            "/dev/tactbench-no-such-port",
            "--protocol",
            "dynpick",
            "read",
        ])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("cannot open serial port /dev/tactbench-no-such-port at 921600 baud"),
        "{err}"
    );
}

#[test]
fn cli_camera_grab_from_an_image_directory_and_clear_error_without_a_camera() {
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("frames");
    std::fs::create_dir(&frames).unwrap();
    let img = image::RgbImage::from_fn(8, 6, |x, y| image::Rgb([x as u8 * 30, y as u8 * 40, 99]));
    img.save(frames.join("0001.png")).unwrap();
    let out_png = dir.path().join("grab.png");
    let out = util::command()
        .args(["camera", "grab", "--device"])
        .arg(format!("dir:{}", frames.display()))
        .arg("--out")
        .arg(&out_png)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(image::open(&out_png).unwrap().to_rgb8(), img);

    // No camera on this machine: V4L2 index 0 must fail clearly (skipped where one exists).
    // Only with the `v4l` feature; the default build's refusal is tested in `cli`.
    if cfg!(feature = "v4l") && !Path::new("/dev/video0").exists() {
        let out = util::command()
            .args(["camera", "grab", "--device", "0", "--out"])
            .arg(dir.path().join("x.png"))
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            err.contains("cannot open V4L2 camera 0") && err.contains("0 V4L2 camera(s) found"),
            "{err}"
        );
        let list = util::command().args(["camera", "list"]).output().unwrap();
        assert!(list.status.success());
        assert!(String::from_utf8_lossy(&list.stdout).contains("no V4L2 cameras found"));
    }
}

/// Measures the sustained FT 300 stream for 10 s and the polled rates of both drivers
/// over a pty; prints the figures (not a pass/fail speed check). Run once with
/// `cargo test --test tests ft::measure_sustained_rates -- --ignored --nocapture`.
#[test]
#[ignore]
fn measure_sustained_rates() {
    let (server, c) = ft300_sim(no_faults(), SharedWrench::new(FT_LOAD));
    let d = Ft300::connect(open("ft300", server.path(), ft::BAUD)).unwrap();
    let mut s = d.start_stream().unwrap();
    let start = Instant::now();
    let mut samples = Vec::new();
    let mut reads = 0u64;
    while start.elapsed() < Duration::from_secs(10) {
        s.read().unwrap();
        reads += 1;
        samples.extend(s.take_samples());
    }
    let elapsed = start.elapsed().as_secs_f64();
    let (mut polled, summary) = s.stop().unwrap();
    samples.extend(summary.remaining);
    let sent = get(&c.frames);
    let max_gap = samples
        .windows(2)
        .map(|w| w[1].received.duration_since(w[0].received))
        .max()
        .unwrap_or_default();
    println!(
        "ft300 stream 10 s: sent {sent}, decoded {}, lost {}, bad crc {}, skipped {} B, \
         {:.2} frames/s, {reads} newest-sample reads, max inter-arrival {:.1} ms",
        samples.len(),
        sent - samples.len() as u64,
        summary.stats.bad_crc,
        summary.stats.bytes_skipped,
        samples.len() as f64 / elapsed,
        max_gap.as_secs_f64() * 1e3
    );
    let t = Instant::now();
    let mut n = 0;
    while t.elapsed() < Duration::from_secs(3) {
        polled.read().unwrap();
        n += 1;
    }
    println!(
        "ft300 polled over pty: {:.0} reads/s",
        n as f64 / t.elapsed().as_secs_f64()
    );
    let (server, _) = dynpick_sim(no_faults(), SharedWrench::new(FT_LOAD));
    let mut d = DynPick::connect(open("dynpick", server.path(), dp::BAUD)).unwrap();
    let t = Instant::now();
    let mut n = 0;
    while t.elapsed() < Duration::from_secs(3) {
        d.read().unwrap();
        n += 1;
    }
    println!(
        "dynpick polled over pty: {:.0} reads/s",
        n as f64 / t.elapsed().as_secs_f64()
    );
}

// ------------------------------------- FT 300 against a real Modbus stack (pymodbus)
//
// `tests/pymodbus_ft300/server.py` serves the FT 300 register map with pymodbus (RTU)
// on a pseudo-terminal, plus the stream the firmware adds around it. The ignored tests
// below run it when TACTBENCH_PYTHON names a Python with pymodbus
// (`pip install pymodbus pyserial`):
//
//     TACTBENCH_PYTHON=python3 cargo test --test integration ft::ft300_against_pymodbus -- --ignored
//
// and record what it answers as `protocols/transcripts/ft300_pymodbus_*.txt`, which
// the `ft300_pymodbus_*_replays` tests replay in CI (no Python needed there).

/// Starts the pymodbus FT 300 with `extra` options; waits for its `ready` line.
fn pymodbus_ft300(link: &Path, extra: &[&str]) -> Served {
    use std::io::BufRead;
    let python = std::env::var("TACTBENCH_PYTHON").unwrap_or_else(|_| {
        panic!("set TACTBENCH_PYTHON to a Python with pymodbus (pip install pymodbus pyserial)")
    });
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/pymodbus_ft300/server.py");
    let mut child = std::process::Command::new(python)
        .arg(script)
        .arg("--link")
        .arg(link)
        .args(["--duration-s", "60"])
        .args(extra)
        .stdout(std::process::Stdio::piped())
        .spawn()
        .expect("spawn the pymodbus server");
    let stdout = child.stdout.take().expect("stdout");
    let served = Served(child);
    let mut line = String::new();
    std::io::BufReader::new(stdout)
        .read_line(&mut line)
        .expect("ready line");
    assert!(line.starts_with("ready"), "pymodbus server: {line:?}");
    served
}

/// A recorder on the pymodbus FT 300's pty.
fn recorded(link: &Path) -> (Recorder<Port>, Log) {
    let log: Log = Arc::new(Mutex::new(Vec::new()));
    let port = Recorder {
        inner: open("ft300", link, ft::BAUD),
        log: Arc::clone(&log),
    };
    (port, log)
}

/// Connect, stream start (echo or not), at least 10 frames, stop.
fn ft300_stream_session<P: Read + Write + Send + 'static>(
    port: P,
) -> (
    Vec<ft::StreamSample>,
    tactbench::device::ft_common::LinkStats,
) {
    let d = Ft300::connect(port).expect("connect");
    let mut s = d.start_stream().expect("stream start");
    let mut samples = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(2);
    while samples.len() < 10 && Instant::now() < deadline {
        samples.extend(s.take_samples());
        std::thread::sleep(Duration::from_millis(5));
    }
    let (d, summary) = s.stop().expect("stop");
    samples.extend(summary.remaining);
    (samples, d.stats())
}

const PYMODBUS_HEADER: &str = "# Recorded from a real Modbus RTU stack: pymodbus serving the FT 300 register map\n\
     # (tests/pymodbus_ft300/server.py, serial FTS-1234, firmware FTS-3.0.4, year 2019,\n\
     # load Fx 1.5 Fy -2.25 Fz 12.34 N, Mx 0.125 My -0.05 Mz 0.3 N·m). Regenerate:\n\
     # TACTBENCH_PYTHON=python3 cargo test --test integration ft::ft300_against_pymodbus -- --ignored\n";

#[test]
#[ignore]
fn ft300_against_pymodbus_serial_number_and_session() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ft300");
    let _server = pymodbus_ft300(&link, &[]);
    let (port, log) = recorded(&link);
    let (w, info) = ft300_session(port);
    assert_eq!(info.serial, "FTS-1234");
    assert_eq!(info.firmware, "FTS-3.0.4");
    assert_eq!(info.year, 2019);
    assert_wrench_near(&w, &FT_LOAD, FT_LSB);
    write_transcript(
        "ft300_pymodbus_session.txt",
        &format!("{PYMODBUS_HEADER}# connect (stop bytes, read 180+6), info (500+3, 510+4, 514+1), read 180+6.\n"),
        &log.lock().unwrap(),
        true,
    );
    // The binary against the same server.
    let out = run_ok(&["--protocol", "ft300", "info", "--json"], &link);
    let v: serde_json::Value = serde_json::from_str(&out).expect("json");
    assert_eq!(v["serial"], "FTS-1234");
}

#[test]
#[ignore]
fn ft300_against_pymodbus_stream_start_without_echo() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ft300");
    let _server = pymodbus_ft300(&link, &["--drop-echo"]);
    let (port, log) = recorded(&link);
    let (samples, stats) = ft300_stream_session(port);
    assert!(samples.len() >= 10, "{} samples", samples.len());
    for x in &samples {
        assert_wrench_near(&x.raw_wrench, &FT_LOAD, FT_LSB);
    }
    assert_eq!(stats.retries, 0, "confirmed by the first frames: {stats:?}");
    write_transcript(
        "ft300_pymodbus_stream_no_echo.txt",
        &format!(
            "{PYMODBUS_HEADER}# --drop-echo: connect, write 410 = 0x0200 whose echo is lost, the stream\n\
             # confirms the start; frames; stop bytes; frames in flight.\n"
        ),
        &log.lock().unwrap(),
        true,
    );
    // And the binary.
    let args = [
        "--protocol",
        "ft300",
        "read",
        "--stream",
        "--samples",
        "3",
        "--json",
    ];
    let v: serde_json::Value = serde_json::from_str(&run_ok(&args, &link)).expect("json");
    assert_wrench_near(&json_wrench(&v["mean"]), &FT_LOAD, FT_LSB);
}

#[test]
#[ignore]
fn ft300_against_pymodbus_failed_stream_start_is_stopped_and_left_stream_is_stopped() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ft300");
    {
        // Echo lost and every frame corrupt: no confirmation; the stream must be stopped.
        let _server = pymodbus_ft300(&link, &["--drop-echo", "--garble-stream"]);
        let d = Ft300::connect(open("ft300", &link, ft::BAUD)).expect("connect");
        let e = match d.start_stream() {
            Ok(_) => panic!("corrupt frames must not confirm"),
            Err(e) => e,
        };
        assert!(e.to_string().contains("the line is quiet"), "{e}");
        let mut port = open("ft300", &link, ft::BAUD);
        let mut buf = [0u8; 64];
        let t = Instant::now();
        while t.elapsed() < Duration::from_millis(200) {
            match port.read(&mut buf) {
                Ok(n) => panic!("still streaming: {n} bytes"),
                Err(_) => continue,
            }
        }
    }
    // A sensor left streaming by an earlier program: connect stops it.
    let _server = pymodbus_ft300(&link, &["--streaming"]);
    std::thread::sleep(Duration::from_millis(50));
    let (port, log) = recorded(&link);
    let mut d = Ft300::connect(port).expect("connect");
    assert_eq!(d.info().expect("info").serial, "FTS-1234");
    write_transcript(
        "ft300_pymodbus_left_streaming.txt",
        &format!(
            "{PYMODBUS_HEADER}# --streaming: the sensor streams when the host connects; the stop bytes end\n\
             # it (frames in flight drained), then read 180+6 and info.\n"
        ),
        &log.lock().unwrap(),
        true,
    );
}

#[test]
fn ft300_pymodbus_session_replays() {
    let mut replay = replay_of("ft300_pymodbus_session.txt");
    let (w, info) = ft300_session(&mut replay);
    replay.finish().expect("every expectation used");
    assert_eq!(
        (info.serial.as_str(), info.firmware.as_str(), info.year),
        ("FTS-1234", "FTS-3.0.4", 2019)
    );
    assert_wrench_near(&w, &FT_LOAD, FT_LSB);
}

#[test]
fn ft300_pymodbus_stream_without_echo_replays() {
    let replay = replay_of("ft300_pymodbus_stream_no_echo.txt");
    let shared = SharedReplay(Arc::new(Mutex::new(replay)));
    let (samples, stats) = ft300_stream_session(shared.clone());
    shared
        .0
        .lock()
        .unwrap()
        .finish()
        .expect("every expectation used");
    assert!(samples.len() >= 10);
    for (i, x) in samples.iter().enumerate() {
        assert_eq!(x.seq, i as u64 + 1);
        assert_wrench_near(&x.raw_wrench, &FT_LOAD, FT_LSB);
    }
    assert_eq!(stats.retries, 0);
}

#[test]
fn ft300_pymodbus_left_streaming_replays() {
    let mut replay = replay_of("ft300_pymodbus_left_streaming.txt");
    {
        let mut d = Ft300::connect(&mut replay).expect("connect");
        assert_eq!(d.info().expect("info").serial, "FTS-1234");
    }
    replay.finish().expect("every expectation used");
}

/// A replay shared with the stream's reader thread (the port moves into it).
#[derive(Clone)]
struct SharedReplay(Arc<Mutex<Replay>>);

impl Read for SharedReplay {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        self.0.lock().unwrap().read(buf)
    }
}

impl Write for SharedReplay {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.0.lock().unwrap().write(buf)
    }
    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}
