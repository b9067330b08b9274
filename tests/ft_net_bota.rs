//! The ATI Net F/T (network) and Bota (serial) force sensors end to end: each driver
//! against its simulator (loopback UDP/TCP, a pseudo-terminal) with losses, duplicates,
//! reordering and corrupt frames injected; the `tactbench ft` CLI and its errors;
//! transcripts recorded against third-party code (LoomDeBWiles/cof_tester's Net F/T
//! simulator, frames built from Bota's example layout) replayed; the `#[ignore]`d
//! outside checks that record them; simulated Fig. 7 runs with each sensor.

use std::io::{BufRead, BufReader};
use std::net::{SocketAddr, TcpListener, UdpSocket};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use tactbench::bench::journal::{self, Manifest};
use tactbench::device::bota::codec::{Frame, StreamDecoder};
use tactbench::device::bota::{Bota, BotaOptions, BotaSim, BotaSimConfig};
use tactbench::device::ft_common::{
    no_faults, open_serial, FaultConfig, FaultKind, FaultTarget, SharedWrench,
};
use tactbench::device::netft::codec::Scale;
use tactbench::device::netft::driver::{calinfo_exchange, NetFtOptions};
use tactbench::device::netft::sim::DEFAULT_CALINFO;
use tactbench::device::netft::transport::{hex, DatagramReplay};
use tactbench::device::netft::{
    read_calinfo, Datagram, NetFt, NetFtCore, NetFtServer, NetFtSimConfig, UdpTransport,
};
use tactbench::device::pty::PtyServer;
use tactbench::device::replay::{Replay, Transcript};
use tactbench::device::{ErrorKind, ForceSensor, Wrench};

use crate::util::{self, assert_wrench_near, json_wrench, wrench_channels, Served, FT_LOAD};

/// The Bota sends f32: its quantum is the f32 spacing at the value.
fn f32_quantum(w: &Wrench) -> [f64; 6] {
    wrench_channels(w).map(|v| (v.abs() as f32 * f32::EPSILON) as f64 * 2.0 + 1e-12)
}

fn netft_scale() -> Scale {
    DEFAULT_CALINFO.scale().unwrap()
}

/// Seeded faults of `kinds` with probability `p` on every record / reply; a late reply
/// comes 20 ms late.
fn faults(seed: u64, kinds: &[FaultKind], p: f64) -> FaultConfig {
    FaultConfig {
        late_by: Duration::from_millis(20),
        ..util::ft_faults(seed, kinds, p)
    }
}

fn netft_server(faults: FaultConfig, status: u32) -> NetFtServer {
    let core = NetFtCore::new(
        NetFtSimConfig {
            faults,
            status,
            ..NetFtSimConfig::default()
        },
        SharedWrench::new(FT_LOAD),
    );
    NetFtServer::spawn(core, 0, 0).expect("serve netft")
}

// ---- Net F/T: driver against the simulator over loopback -----------------------------

#[test]
fn netft_readings_are_exact_with_loss_duplicates_reordering_and_truncated_datagrams() {
    let server = netft_server(
        faults(
            7,
            &[
                FaultKind::DroppedByte,
                FaultKind::Unsolicited,
                FaultKind::LateReply,
                FaultKind::Garbled,
            ],
            0.2,
        ),
        0,
    );
    let cal = server.cal_addr().unwrap();
    let info = read_calinfo("127.0.0.1", cal.port()).unwrap();
    assert_eq!(info, DEFAULT_CALINFO);
    let link = UdpTransport::connect("netft", "127.0.0.1", server.rdt_addr().port()).unwrap();
    let mut d = NetFt::connect(link, NetFtOptions::netft(info.scale().unwrap())).unwrap();
    let q = netft_scale().resolution();
    for _ in 0..50 {
        assert_wrench_near(&d.read().unwrap(), &FT_LOAD, q);
        std::thread::sleep(Duration::from_millis(2));
    }
    let s = d.stats();
    assert!(
        s.lost > 0 && s.duplicates > 0 && s.stale > 0 && s.malformed > 0,
        "every fault kind was met: {s:?}"
    );
    let note = d.take_status().expect("losses reported");
    assert!(
        note.starts_with("netft:") && note.contains("lost"),
        "{note}"
    );
    d.tare().unwrap();
    assert_wrench_near(&d.read().unwrap(), &Wrench::default(), q);
}

/// The Net F/T's usual (1 kHz) and maximum (7 kHz) RDT rates and a slow one, each with
/// 15 % of the records lost, duplicated or delayed 20 ms (reordered), seeded: the
/// driver over real loopback UDP against the simulator.
#[test]
fn netft_driver_at_100_1000_and_7000_hz_over_loopback_udp_with_loss_duplicates_and_reordering() {
    for rate in [100.0, 1000.0, 7000.0] {
        let core = NetFtCore::new(
            NetFtSimConfig {
                rate_hz: rate,
                faults: faults(
                    29,
                    &[
                        FaultKind::DroppedByte,
                        FaultKind::Unsolicited,
                        FaultKind::LateReply,
                    ],
                    0.15,
                ),
                ..NetFtSimConfig::default()
            },
            SharedWrench::new(FT_LOAD),
        );
        let server = NetFtServer::spawn(core, 0, 0).expect("serve netft");
        let link = UdpTransport::connect("netft", "127.0.0.1", server.rdt_addr().port()).unwrap();
        let mut d = NetFt::connect(link, NetFtOptions::netft(netft_scale())).unwrap();
        let q = netft_scale().resolution();
        let mut reads = 0u32;
        loop {
            assert_wrench_near(&d.read().unwrap(), &FT_LOAD, q);
            reads += 1;
            let s = d.stats();
            // Half a second of the stream at least, through 20 readings at least.
            let span = (rate * 0.5).max(300.0) as u64;
            if s.good + s.lost >= span
                && reads >= 20
                && s.lost > 0
                && s.duplicates > 0
                && s.stale > 0
            {
                break;
            }
        }
        let s = d.stats();
        eprintln!(
            "{rate} Hz: measured {:.0} Hz at connect, {reads} readings, {s:?}",
            d.measured_rate_hz()
        );
        // The simulator really streamed at a high rate (the rate is read from the RDT
        // sequence, so a loaded machine that wakes the simulator late still counts
        // every record it caught up on).
        assert!(
            d.measured_rate_hz() > rate * 0.5,
            "{rate} Hz stream measured at {:.0} Hz",
            d.measured_rate_hz()
        );
        // 15 % faulted, a third of them lost: most records are averaged.
        assert!(s.good * 10 > (s.good + s.lost) * 8, "{rate} Hz: {s:?}");
        assert_eq!(
            s.malformed + s.bad_status + s.restarts,
            0,
            "{rate} Hz: {s:?}"
        );
    }
}

/// `tactbench ft read` runs until it is killed, failing the test, if it takes longer
/// than `limit` (a hang, not a speed check: a read takes milliseconds).
fn ft_within(args: &[&str], limit: Duration) -> Output {
    let mut child = util::command()
        .arg("ft")
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run");
    let t0 = Instant::now();
    while child.try_wait().expect("wait").is_none() {
        if t0.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "`tactbench ft {}` hung: killed after {limit:?}",
                args.join(" ")
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().expect("output")
}

#[test]
fn netft_cli_read_returns_at_1000_and_7000_hz() {
    for rate in ["1000", "7000"] {
        let (_s, line) = util::serve_ft(
            "netft",
            &[
                "--rate-hz",
                rate,
                "--fault",
                "loss",
                "--fault",
                "duplicate",
                "--fault",
                "reorder",
                "--fault-probability",
                "0.05",
            ],
        );
        let (rdt, cal) = netft_ports(&line);
        let o = ft_within(
            &[
                "--protocol",
                "netft",
                "--port",
                "127.0.0.1",
                "--rdt-port",
                &rdt,
                "--cal-port",
                &cal,
                "read",
                "--samples",
                "200",
                "--tare",
                "--json",
            ],
            Duration::from_secs(60),
        );
        assert!(o.status.success(), "{rate} Hz: {}", util::stderr(&o));
        let v: serde_json::Value = serde_json::from_str(util::stdout(&o).trim()).unwrap();
        let samples = v["samples"].as_array().unwrap();
        assert_eq!(samples.len(), 200);
        for s in samples {
            assert_wrench_near(
                &json_wrench(s),
                &Wrench::default(),
                netft_scale().resolution(),
            );
        }
        assert!(
            util::stderr(&o).contains("lost"),
            "{rate} Hz: {}",
            util::stderr(&o)
        );
    }
}

#[test]
fn netft_status_word_is_reported_and_never_averaged() {
    let server = netft_server(no_faults(), 0x0002_0000);
    let link = UdpTransport::connect("netft", "127.0.0.1", server.rdt_addr().port()).unwrap();
    let mut d = NetFt::connect(link, NetFtOptions::netft(netft_scale())).unwrap();
    let e = d.read().unwrap_err();
    assert_eq!(e.kind, ErrorKind::Limit, "{e}");
    assert!(e.to_string().contains("0x00020000"), "{e}");
    assert!(d.take_status().unwrap().contains("status 0x00020000"));
}

#[test]
fn netft_sensor_that_vanishes_is_disconnected_naming_the_host_within_seconds() {
    let server = netft_server(
        FaultConfig {
            skip: 400,
            ..FaultConfig::once(FaultKind::Disconnect, FaultTarget::Any, 400)
        },
        0,
    );
    let port = server.rdt_addr().port();
    let link = UdpTransport::connect("netft", "127.0.0.1", port).unwrap();
    let mut d = NetFt::connect(link, NetFtOptions::netft(netft_scale())).unwrap();
    let t0 = Instant::now();
    let e = loop {
        match d.read() {
            Ok(_) => assert!(t0.elapsed() < Duration::from_secs(10)),
            Err(e) if e.kind == ErrorKind::Disconnected => break e,
            Err(e) => assert!(t0.elapsed() < Duration::from_secs(10), "{e}"),
        }
    };
    assert!(e.to_string().contains(&format!("127.0.0.1:{port}")), "{e}");
    assert!(t0.elapsed() < Duration::from_secs(5), "{:?}", t0.elapsed());
    assert!(server.is_finished());
}

#[test]
fn netft_reset_device_is_restarted_by_the_driver() {
    let server = netft_server(
        FaultConfig::once(FaultKind::DeviceReset, FaultTarget::Any, 300),
        0,
    );
    let link = UdpTransport::connect("netft", "127.0.0.1", server.rdt_addr().port()).unwrap();
    let mut d = NetFt::connect(link, NetFtOptions::netft(netft_scale())).unwrap();
    for _ in 0..40 {
        assert_wrench_near(&d.read().unwrap(), &FT_LOAD, netft_scale().resolution());
        std::thread::sleep(Duration::from_millis(10));
    }
    assert!(d.stats().start_requests >= 2, "{:?}", d.stats());
    assert!(server.is_streaming());
}

// ---- Net F/T: CLI --------------------------------------------------------------------

/// `--rdt-port N --cal-port M` from a netft "serving" line.
fn netft_ports(line: &str) -> (String, String) {
    let w: Vec<&str> = line.split_whitespace().collect();
    let after = |k: &str| {
        w.iter()
            .position(|x| *x == k)
            .map(|i| w[i + 1].to_string())
            .unwrap_or_else(|| panic!("{k} in {line}"))
    };
    (after("--rdt-port"), after("--cal-port"))
}

fn ft(args: &[&str]) -> Output {
    util::command().arg("ft").args(args).output().expect("run")
}

#[test]
fn netft_cli_info_read_tare_work_with_faults_injected() {
    let (_s, line) = util::serve_ft(
        "netft",
        &[
            "--fault",
            "loss",
            "--fault",
            "duplicate",
            "--fault",
            "reorder",
            "--fault",
            "garbled",
            "--fault-probability",
            "0.1",
        ],
    );
    let (rdt, cal) = netft_ports(&line);
    let run = |extra: &[&str]| {
        let o = ft_on_loopback("netft", &rdt, Some(&cal), extra);
        assert!(o.status.success(), "{extra:?}: {}", util::stderr(&o));
        util::stdout(&o)
    };
    let info = run(&["info"]);
    assert!(info.contains("counts_per_n: 1000000"), "{info}");
    assert!(info.contains("READCALINFO"), "{info}");
    let read = run(&["read", "--samples", "5", "--json"]);
    let v: serde_json::Value = serde_json::from_str(read.trim()).unwrap();
    assert_eq!(v["protocol"], "netft");
    for s in v["samples"].as_array().unwrap() {
        assert_wrench_near(&json_wrench(s), &FT_LOAD, netft_scale().resolution());
    }
    let tare = run(&["tare"]);
    assert!(tare.contains("biased"), "{tare}");
    // The simulator keeps the bias: the next command reads zero.
    let v: serde_json::Value = serde_json::from_str(run(&["read", "--json"]).trim()).unwrap();
    assert_wrench_near(
        &json_wrench(&v["mean"]),
        &Wrench::default(),
        netft_scale().resolution(),
    );
}

/// `tactbench ft --protocol PROTOCOL --port 127.0.0.1 --rdt-port RDT [--cal-port CAL]
/// ARGS`.
fn ft_on_loopback(protocol: &str, rdt: &str, cal: Option<&str>, args: &[&str]) -> Output {
    let mut a = vec![
        "--protocol",
        protocol,
        "--port",
        "127.0.0.1",
        "--rdt-port",
        rdt,
    ];
    if let Some(cal) = cal {
        a.extend(["--cal-port", cal]);
    }
    a.extend_from_slice(args);
    ft(&a)
}

/// A port nothing listens on: bound, then released.
fn free_udp_port() -> u16 {
    UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn free_tcp_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

#[test]
fn netft_missing_device_and_unresolvable_host_are_clear_errors_within_seconds() {
    let (rdt, cal) = (free_udp_port().to_string(), free_tcp_port().to_string());
    let t0 = Instant::now();
    let o = ft_on_loopback("netft", &rdt, Some(&cal), &["read"]);
    assert!(!o.status.success());
    let e = util::stderr(&o);
    assert!(e.contains("127.0.0.1") && e.contains(&cal), "{e}");
    assert!(t0.elapsed() < Duration::from_secs(5), "{:?}", t0.elapsed());
    // The HEX has no calibration query: the RDT port itself is found dead.
    let t0 = Instant::now();
    let o = ft_on_loopback("onrobot-hex", &rdt, None, &["read"]);
    assert!(!o.status.success());
    let e = util::stderr(&o);
    assert!(e.contains(&format!("127.0.0.1:{rdt}")), "{e}");
    assert!(t0.elapsed() < Duration::from_secs(5), "{:?}", t0.elapsed());
    let o = ft(&[
        "--protocol",
        "netft",
        "--port",
        "no-such-sensor.invalid",
        "read",
    ]);
    assert!(!o.status.success());
    let e = util::stderr(&o);
    assert!(
        e.contains("does not resolve") && e.contains("no-such-sensor.invalid"),
        "{e}"
    );
}

#[test]
fn netft_simulator_on_a_port_in_use_is_a_clear_error() {
    let busy = UdpSocket::bind("127.0.0.1:0").unwrap();
    let port = busy.local_addr().unwrap().port().to_string();
    let o = util::command()
        .args(["sim-serve-ft", "--protocol", "netft", "--rdt-port", &port])
        .output()
        .unwrap();
    assert!(!o.status.success());
    let e = util::stderr(&o);
    assert!(e.contains("cannot bind") && e.contains(&port), "{e}");
}

#[test]
fn onrobot_hex_reads_the_rdt_records_with_its_fixed_scale() {
    let (_s, line) = util::serve_ft::<&str>("onrobot-hex", &[]);
    let w: Vec<&str> = line.split_whitespace().collect();
    let rdt = w[w.iter().position(|x| *x == "--rdt-port").unwrap() + 1];
    let o = ft_on_loopback("onrobot-hex", rdt, None, &["read", "--json"]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    let v: serde_json::Value = serde_json::from_str(util::stdout(&o).trim()).unwrap();
    assert_wrench_near(
        &json_wrench(&v["mean"]),
        &FT_LOAD,
        Scale::ONROBOT_HEX.resolution(),
    );
}

// ---- Net F/T: transcripts recorded against cof_tester --------------------------------

const COF_UDP: &str = "protocols/transcripts/netft_cof_tester_session.txt";
const COF_TCP: &str = "protocols/transcripts/netft_cof_tester_calinfo.txt";

/// What cof_tester's constant signal puts in every record (see serve.py).
const COF_COUNTS: [i32; 6] = [0, 86_602, 86_602, 0, -86_602, -86_602];

#[test]
fn netft_transcript_from_cof_tester_replays() {
    // TCP: the calibration query, byte for byte.
    let t = Transcript::parse(&std::fs::read_to_string(util::root(COF_TCP)).unwrap()).unwrap();
    let mut r = Replay::new(t);
    let cal = calinfo_exchange(
        &mut r,
        "READCALINFO",
        Instant::now() + Duration::from_secs(1),
    )
    .unwrap();
    r.finish().unwrap();
    assert_eq!(
        (
            cal.force_unit,
            cal.torque_unit,
            cal.counts_per_force,
            cal.counts_per_torque
        ),
        (2, 3, 1_000_000, 1_000_000)
    );
    // UDP: start, the records as they arrived (lost and reordered by cof_tester's own
    // fault injection), stop.
    let replay =
        DatagramReplay::parse(&std::fs::read_to_string(util::root(COF_UDP)).unwrap()).unwrap();
    let opts = NetFtOptions {
        // Replayed records arrive at once: none is stale.
        stale_after: Duration::from_secs(3600),
        ..NetFtOptions::netft(cal.scale().unwrap())
    };
    let mut d = NetFt::connect(replay, opts).unwrap();
    let w = d.read().unwrap();
    let want = cal.scale().unwrap().wrench(&COF_COUNTS);
    assert_wrench_near(&w, &want, cal.scale().unwrap().resolution());
    let s = d.stats();
    assert!(s.records > 100 && s.bad_status == 0, "{s:?}");
    d.stop().unwrap();
}

/// Records every datagram a transport sends and receives.
struct Recorder<T: Datagram> {
    inner: T,
    log: std::sync::Arc<std::sync::Mutex<Vec<String>>>,
}

impl<T: Datagram> Datagram for Recorder<T> {
    fn send(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.log.lock().unwrap().push(format!("> {}", hex(bytes)));
        self.inner.send(bytes)
    }
    fn recv(&mut self, buf: &mut [u8], deadline: Instant) -> std::io::Result<Option<usize>> {
        let r = self.inner.recv(buf, deadline)?;
        if let Some(n) = r {
            self.log
                .lock()
                .unwrap()
                .push(format!("< {}", hex(&buf[..n])));
        }
        Ok(r)
    }
    fn peer(&self) -> String {
        self.inner.peer()
    }
}

/// Outside check (issue 20 part 4): the driver against LoomDeBWiles/cof_tester's Net F/T
/// simulator, with its loss and reorder injection on; records the transcripts replayed
/// above. Needs TACTBENCH_COF_TESTER (cof_tester's `src/`) and numpy; see
/// `docs/force-sensors.md`.
#[test]
#[ignore = "needs python3, numpy and a checkout of LoomDeBWiles/cof_tester (TACTBENCH_COF_TESTER)"]
fn netft_against_cof_tester_records_a_transcript() {
    let python = std::env::var("TACTBENCH_PYTHON").unwrap_or_else(|_| "python3".into());
    let mut child = Command::new(python)
        .arg(util::root("tests/netft_cof_tester/serve.py"))
        .env("COF_LOSS", "0.03")
        .env("COF_REORDER", "0.03")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .expect("python3");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let ports: serde_json::Value = serde_json::from_str(&line).expect("ports line");
    let (udp, tcp) = (
        ports["udp"].as_u64().unwrap() as u16,
        ports["tcp"].as_u64().unwrap() as u16,
    );
    // TCP, recorded byte for byte.
    let addr: SocketAddr = format!("127.0.0.1:{tcp}").parse().unwrap();
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_millis(100)))
        .unwrap();
    let cal = calinfo_exchange(
        &mut s,
        "READCALINFO",
        Instant::now() + Duration::from_secs(2),
    )
    .unwrap();
    let esc = |b: &[u8]| b.iter().map(|x| format!("\\x{x:02x}")).collect::<String>();
    let mut req = vec![1u8];
    req.resize(20, 0);
    std::fs::write(
        util::root(COF_TCP),
        format!(
            "# READCALINFO against LoomDeBWiles/cof_tester's simulator (recorded by\n\
             # ft_net_bota::netft_against_cof_tester_records_a_transcript)\n> {}\n< {}\n",
            esc(&req),
            esc(&cal.encode())
        ),
    )
    .unwrap();
    // UDP through a recorder.
    let log = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let link = Recorder {
        inner: UdpTransport::connect("netft", "127.0.0.1", udp).unwrap(),
        log: std::sync::Arc::clone(&log),
    };
    let scale = cal.scale().unwrap();
    let mut d = NetFt::connect(link, NetFtOptions::netft(scale)).unwrap();
    let want = scale.wrench(&COF_COUNTS);
    for _ in 0..20 {
        assert_wrench_near(&d.read().unwrap(), &want, scale.resolution());
    }
    let st = d.stats();
    assert_eq!(
        st.start_requests, 1,
        "a re-sent start would not replay: {st:?}"
    );
    d.stop().unwrap();
    drop(d);
    drop(child.stdin.take());
    let _ = child.wait();
    let log = log.lock().unwrap();
    // Keep the session up to the first stop (the drop sends another).
    let end = log.iter().position(|l| l == "> 1234000000000000").unwrap() + 1;
    let mut text = String::from(
        "# RDT datagrams between the netft driver and LoomDeBWiles/cof_tester's Net F/T\n\
         # simulator (loss 3 %, reorder 3 %), as received (recorded by\n\
         # ft_net_bota::netft_against_cof_tester_records_a_transcript). `>` host, `<` device, hex.\n",
    );
    for l in &log[..end] {
        text.push_str(l);
        text.push('\n');
    }
    std::fs::write(util::root(COF_UDP), text).unwrap();
    eprintln!("recorded {} datagrams, stats {st:?}", end);
}

// ---- Bota ----------------------------------------------------------------------------

fn bota_sim(config: BotaSimConfig) -> PtyServer<BotaSim> {
    PtyServer::spawn(BotaSim::new(config, SharedWrench::new(FT_LOAD)), None).expect("pty")
}

fn bota_port(s: &PtyServer<BotaSim>) -> Box<dyn serialport::SerialPort> {
    open_serial("bota", &s.path().to_string_lossy(), 460_800).unwrap()
}

#[test]
fn bota_readings_are_exact_with_corrupt_dropped_and_garbage_bytes_injected() {
    let server = bota_sim(BotaSimConfig {
        faults: FaultConfig {
            target: FaultTarget::Queries,
            ..faults(
                3,
                &[
                    FaultKind::Garbled,
                    FaultKind::DroppedByte,
                    FaultKind::Unsolicited,
                    FaultKind::LateReply,
                ],
                0.2,
            )
        },
        ..BotaSimConfig::default()
    });
    // The simulator streams from power-up: the driver meets a stream left running.
    std::thread::sleep(Duration::from_millis(50));
    let mut d = Bota::connect(bota_port(&server), BotaOptions::default()).unwrap();
    let q = f32_quantum(&FT_LOAD);
    for _ in 0..30 {
        assert_wrench_near(&d.read().unwrap(), &FT_LOAD, q);
    }
    let s = d.stats();
    assert!(s.bad_crc > 0 && s.skipped > 0, "{s:?}");
    let note = d.take_status().unwrap();
    assert!(note.contains("24.50 C") && note.contains(" us"), "{note}");
    let f = d.last_frame().unwrap();
    assert!(f.timestamp > 0 && f.temperature_c == 24.5);
    d.tare().unwrap();
    assert_wrench_near(&d.read().unwrap(), &Wrench::default(), q);
}

#[test]
fn bota_overrange_frames_are_never_averaged_and_fail_the_reading() {
    let server = bota_sim(BotaSimConfig {
        status: 0x0002,
        ..BotaSimConfig::default()
    });
    let mut d = Bota::connect(bota_port(&server), BotaOptions::default()).unwrap();
    let e = d.read_once().unwrap_err();
    assert_eq!(e.kind, ErrorKind::Limit, "{e}");
    assert!(e.message.contains("overrange"), "{e}");
    assert!(d.take_status().unwrap().contains("left out (overrange)"));
}

#[test]
fn bota_crc_failing_stream_that_never_recovers_is_a_clear_error() {
    let server = bota_sim(BotaSimConfig {
        faults: FaultConfig {
            target: FaultTarget::Queries,
            ..faults(5, &[FaultKind::Garbled], 1.0)
        },
        ..BotaSimConfig::default()
    });
    let e = Bota::connect(bota_port(&server), BotaOptions::default())
        .err()
        .unwrap();
    assert_eq!(e.kind, ErrorKind::Protocol, "{e}");
    assert!(e.message.contains("CRC"), "{e}");
}

#[test]
fn bota_cli_info_read_tare_against_the_simulator_left_streaming() {
    let tmp = tempfile::tempdir().unwrap();
    let link = tmp.path().join("bota");
    let (_s, line) = util::serve_ft(
        "bota",
        &[
            "--link",
            link.to_str().unwrap(),
            "--fault",
            "garbled",
            "--fault",
            "dropped-byte",
            "--fault-probability",
            "0.05",
        ],
    );
    assert!(line.starts_with("serving simulated bota"), "{line}");
    let port = link.to_str().unwrap();
    let run = |extra: &[&str]| {
        let mut a = vec!["--protocol", "bota", "--port", port];
        a.extend_from_slice(extra);
        let o = ft(&a);
        assert!(o.status.success(), "{extra:?}: {}", util::stderr(&o));
        util::stdout(&o)
    };
    let info = run(&["info"]);
    assert!(
        info.contains("temperature_c: 24.50") && info.contains("sample_period: 10"),
        "{info}"
    );
    let v: serde_json::Value =
        serde_json::from_str(run(&["read", "--samples", "3", "--json"]).trim()).unwrap();
    assert_wrench_near(&json_wrench(&v["mean"]), &FT_LOAD, f32_quantum(&FT_LOAD));
    let tare = run(&["tare"]);
    assert!(tare.contains("software offset"), "{tare}");
}

#[test]
fn bota_vendor_layout_frames_replay_through_the_driver() {
    let t = Transcript::parse(
        &std::fs::read_to_string(util::root("protocols/transcripts/bota_vendor_frames.txt"))
            .unwrap(),
    )
    .unwrap();
    let mut d = Bota::connect(
        Replay::new(t),
        BotaOptions {
            stale_after: Duration::from_secs(3600),
            ..BotaOptions::default()
        },
    )
    .unwrap();
    // Frames 1, 2 and 5 are averaged (status 0, 0, app took too long); 3 (overrange)
    // and 4 (invalid) are left out; the corrupted copy fails the CRC.
    let v = [
        [1.5f32, -2.25, 12.34, 0.125, -0.05, 0.3],
        [0.0; 6],
        [3.0, 4.0, 5.0, 0.3, 0.4, 0.5],
    ];
    let mean: Vec<f64> = (0..6)
        .map(|i| v.iter().map(|r| r[i] as f64).sum::<f64>() / 3.0)
        .collect();
    let want = Wrench {
        force_n: [mean[0], mean[1], mean[2]],
        torque_nm: [mean[3], mean[4], mean[5]],
    };
    assert_wrench_near(&d.read().unwrap(), &want, [1e-9; 6]);
    let s = d.stats();
    assert_eq!((s.frames, s.good, s.bad, s.late), (5, 3, 2, 1), "{s:?}");
    assert!(s.bad_crc >= 1, "{s:?}");
    let note = d.take_status().unwrap();
    assert!(
        note.contains("overrange") && note.contains("invalid measurement"),
        "{note}"
    );
    assert!(note.contains("t 20000 us, 26.00 C"), "{note}");
}

/// Outside check, the other way (issue 20 part 4): the frames of the replay above are
/// what the vendor's layout gives. Needs python3 with `crc` (pip install crc).
#[test]
#[ignore = "needs python3 with the `crc` package"]
fn bota_frames_built_from_the_vendor_layout_decode() {
    let python = std::env::var("TACTBENCH_PYTHON").unwrap_or_else(|_| "python3".into());
    let o = Command::new(python)
        .arg(util::root("tests/bota_vendor/frames.py"))
        .output()
        .expect("python3");
    assert!(o.status.success(), "{}", util::stderr(&o));
    let mut n = 0;
    for line in util::stdout(&o).lines() {
        let (h, j) = line.split_once(' ').unwrap();
        let bytes: Vec<u8> = (0..h.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&h[i..i + 2], 16).unwrap())
            .collect();
        let v: serde_json::Value = serde_json::from_str(j).unwrap();
        let f = Frame::decode(&bytes).expect("CRC and header as the vendor's");
        assert_eq!(f.status as u64, v["status"].as_u64().unwrap());
        assert_eq!(f.timestamp as u64, v["timestamp"].as_u64().unwrap());
        // Python printed the f32 values widened to double; JSON parsing may round the
        // last digit of the double, never the f32 it came from.
        for i in 0..6 {
            assert_eq!(f.values[i], v["values"][i].as_f64().unwrap() as f32);
        }
        assert_eq!(f.temperature_c, v["temperature"].as_f64().unwrap() as f32);
        // And through the stream decoder, split at an odd boundary.
        let mut d = StreamDecoder::default();
        let mut out = Vec::new();
        d.push(&bytes[..11], &mut out);
        d.push(&bytes[11..], &mut out);
        assert_eq!(out, vec![f]);
        n += 1;
    }
    assert_eq!(n, 5);
}

/// Outside check (issue 20 part 4): the vendor's example reader
/// (tud-phi/bota_ft_sensors `python/bota_serial_example.py`, unchanged: it takes the
/// port as its argument) reads our simulator on a pseudo-terminal. Needs
/// TACTBENCH_BOTA_EXAMPLE (the script's path) and python3 with pyserial and crc.
#[test]
#[ignore = "needs the vendor example (TACTBENCH_BOTA_EXAMPLE), pyserial and crc"]
fn bota_vendor_example_reads_the_simulator() {
    let script =
        PathBuf::from(std::env::var("TACTBENCH_BOTA_EXAMPLE").expect("TACTBENCH_BOTA_EXAMPLE"));
    let python = std::env::var("TACTBENCH_PYTHON").unwrap_or_else(|_| "python3".into());
    let server = bota_sim(BotaSimConfig {
        banner_every: Some(Duration::from_millis(300)),
        ..BotaSimConfig::default()
    });
    let child = Command::new(python)
        .arg("-u")
        .arg(&script)
        .arg(server.path())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("python3");
    std::thread::sleep(Duration::from_secs(4));
    // Ctrl-C: the example's loop catches KeyboardInterrupt and prints `stopped`.
    unsafe {
        libc::kill(child.id() as i32, libc::SIGINT);
    }
    let o = child.wait_with_output().unwrap();
    let text = util::stdout(&o);
    assert!(
        text.contains("Frame synced"),
        "{text}\n{}",
        util::stderr(&o)
    );
    let last = |k: &str| -> f64 {
        text.lines()
            .rev()
            .find_map(|l| l.strip_prefix(&format!("{k} ")))
            .unwrap_or_else(|| panic!("{k} in {text}"))
            .trim()
            .parse()
            .unwrap()
    };
    let got = Wrench {
        force_n: [last("Fx"), last("Fy"), last("Fz")],
        torque_nm: [last("Mx"), last("My"), last("Mz")],
    };
    assert_wrench_near(&got, &FT_LOAD, f32_quantum(&FT_LOAD));
    assert_eq!(last("Temperature"), 24.5);
    assert_eq!(last("Status"), 0.0);
    assert!(last("Timestamp") > 0.0);
    eprintln!("{}", &text[text.len().saturating_sub(400)..]);
}

// ---- simulated Fig. 7 runs with each new sensor --------------------------------------

fn sim_run(dir: &Path, ft: &str, limit: &str) -> Vec<journal::JournalRow> {
    let scene = util::root("experiments/scenes/fig7_hemisphere_ramp.toml");
    let bench = dir.join(format!("bench_{ft}.toml"));
    std::fs::write(
        &bench,
        format!(
            "[sim]\nscene = {:?}\nforce_sensor = \"{ft}\"\n",
            scene.display().to_string()
        ),
    )
    .unwrap();
    let out = dir.join(format!("run_{ft}"));
    let o = util::run(&[
        "run",
        "experiments/fig7_magnitude.toml",
        "--bench",
        bench.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--limit",
        limit,
        "--no-progress",
    ]);
    assert!(o.status.success(), "{ft}: {}", util::stderr(&o));
    let m = Manifest::read(&out).unwrap();
    assert_eq!(m.devices["force_sensor"]["protocol"], ft);
    journal::read_rows(&out).unwrap()
}

#[test]
fn simulated_fig7_runs_with_netft_and_bota_match_a_dynpick_run() {
    let tmp = tempfile::tempdir().unwrap();
    let dp = sim_run(tmp.path(), "dynpick", "4");
    let nf = sim_run(tmp.path(), "netft", "4");
    let bo = sim_run(tmp.path(), "bota", "4");
    let plan =
        tactbench::bench::plan::Plan::from_path(util::root("experiments/fig7_magnitude.toml"))
            .unwrap();
    let tol = plan.force_tolerance_n;
    for (name, rows) in [("netft", &nf), ("bota", &bo)] {
        assert_eq!(rows.len(), dp.len(), "{name}");
        for (r, d) in rows.iter().zip(&dp) {
            assert!(
                (r.fz_n - r.target_normal_n).abs() <= tol + 1e-9,
                "{name} #{}: fz {} target {}",
                r.index,
                r.fz_n,
                r.target_normal_n
            );
            // The reconstruction sees the same world: F^sum agrees with the DynPick
            // run's to the force control's tolerance on both sides.
            eprintln!(
                "{name} #{}: fz {:.5} N (DynPick {:.5} N), F^sum z {:.5} N (DynPick {:.5} N), target {:.5} N",
                r.index, r.fz_n, d.fz_n, r.fsum_z_n, d.fsum_z_n, r.target_normal_n
            );
            assert!(
                (r.fsum_z_n - d.fsum_z_n).abs() <= 2.0 * tol,
                "{name} #{}: F^sum z {} vs DynPick {}",
                r.index,
                r.fsum_z_n,
                d.fsum_z_n
            );
        }
    }
    // Bota rows record the sensor's timestamp and temperature.
    for r in &bo {
        let s = r.ft_status.as_deref().unwrap_or_default();
        assert!(
            s.contains("24.50 C") && s.contains(" us"),
            "row {}: {s:?}",
            r.index
        );
    }
}

#[test]
fn dry_run_and_ports_know_the_network_sensors() {
    let tmp = tempfile::tempdir().unwrap();
    let bench = tmp.path().join("bench.toml");
    std::fs::write(
        &bench,
        "[stage]\nprotocol = \"grbl\"\nport = \"/dev/ttyUSB0\"\n[force_sensor]\nprotocol = \"netft\"\nhost = \"127.0.0.1\"\n[camera]\ndevice = 0\n[geometry]\nsensor_origin_in_stage_mm = [-100.0, -100.0]\nsurface_z_mm = -30.0\npress_direction = -1\n",
    )
    .unwrap();
    let o = util::run(&[
        "run",
        "experiments/fig7_magnitude.toml",
        "--bench",
        bench.to_str().unwrap(),
        "--out",
        tmp.path().join("run").to_str().unwrap(),
        "--dry-run",
    ]);
    let all = format!("{}{}", util::stdout(&o), util::stderr(&o));
    assert!(all.contains("force sensor netft at 127.0.0.1"), "{all}");
    // A serial port named for a network sensor is refused with the key and the fix.
    std::fs::write(
        &bench,
        std::fs::read_to_string(&bench)
            .unwrap()
            .replace("host = \"127.0.0.1\"", "port = \"/dev/ttyUSB1\""),
    )
    .unwrap();
    let o = util::run(&[
        "run",
        "experiments/fig7_magnitude.toml",
        "--bench",
        bench.to_str().unwrap(),
        "--out",
        tmp.path().join("run2").to_str().unwrap(),
        "--dry-run",
    ]);
    assert!(!o.status.success());
    let e = util::stderr(&o);
    assert!(
        e.contains("force_sensor.port") && e.contains("network sensor"),
        "{e}"
    );
    let o = util::run(&["ports"]);
    assert!(o.status.success());
    assert!(util::stdout(&o).contains("--protocol netft"));
}

#[test]
fn sim_bench_serves_a_netft_that_the_ft_command_reads() {
    let tmp = tempfile::tempdir().unwrap();
    let links = tmp.path().join("bench");
    let mut child = util::command()
        .args(["sim", "bench", "--scene"])
        .arg(util::root("experiments/scenes/fig7_hemisphere_ramp.toml"))
        .args(["--ft", "netft", "--links"])
        .arg(&links)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut out = BufReader::new(child.stdout.take().unwrap());
    let served = Served(child);
    let mut ft_line = String::new();
    for _ in 0..10 {
        let mut line = String::new();
        out.read_line(&mut line).unwrap();
        if line.starts_with("ft ") {
            ft_line = line;
            break;
        }
    }
    let (rdt, cal) = netft_ports(&ft_line);
    assert!(ft_line.contains("127.0.0.1"), "{ft_line}");
    let o = ft_on_loopback("netft", &rdt, Some(&cal), &["read", "--json"]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    // The stage starts above the surface: no load.
    let v: serde_json::Value = serde_json::from_str(util::stdout(&o).trim()).unwrap();
    assert_wrench_near(
        &json_wrench(&v["mean"]),
        &Wrench::default(),
        netft_scale().resolution(),
    );
    drop(served);
}
