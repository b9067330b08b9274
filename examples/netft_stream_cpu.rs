//! The CPU cost of holding a Net F/T (or OnRobot HEX) RDT stream open for a run, and
//! the rate the driver reads at.
//!
//! `cargo run --release --example netft_stream_cpu -- [RATE_HZ] [SECONDS] [READ_HZ...]`
//! (defaults: 7000 Hz, 10 s, reads at 500, 100 and 10 Hz). The simulator streams on
//! loopback from its own threads; the driver runs on this thread, reading at each
//! READ_HZ for SECONDS (a run reads the sensor at its own pace: 500 Hz is the most the
//! driver advertises, [`tactbench::device::netft::driver::READ_RATE_CAP_HZ`]). For each,
//! it prints the readings made, the records the driver took and lost, and the CPU
//! time of this thread alone (user + system, `getrusage(RUSAGE_THREAD)`, Linux) over
//! the window as a percentage of one core, so the simulator's own cost is not counted.
//! Records the socket buffer could not hold between two slow readings are lost by
//! the kernel and counted (the RDT sequence skips); a reading averages the newest.
//!
//! With `--host HOST RDT_PORT` as the first arguments it reads a real sensor (or a
//! `tactbench sim-serve-ft` in another process) instead, with the Net F/T's default
//! scale of the simulator (counts per unit 1 000 000: only the CPU figures mean
//! anything then).
use std::time::{Duration, Instant};

use tactbench::device::ft_common::SharedWrench;
use tactbench::device::netft::driver::NetFtOptions;
use tactbench::device::netft::sim::DEFAULT_CALINFO;
use tactbench::device::netft::{NetFt, NetFtCore, NetFtServer, NetFtSimConfig, UdpTransport};
use tactbench::device::{ForceSensor, Wrench};

/// User + system CPU time of the calling thread.
fn thread_cpu() -> Duration {
    // SAFETY: getrusage fills the zeroed struct it is given.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    let r = unsafe { libc::getrusage(libc::RUSAGE_THREAD, &mut u) };
    assert_eq!(r, 0, "getrusage(RUSAGE_THREAD)");
    let tv = |t: libc::timeval| Duration::new(t.tv_sec as u64, t.tv_usec as u32 * 1000);
    tv(u.ru_utime) + tv(u.ru_stime)
}

fn main() {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let external = if args.first().map(String::as_str) == Some("--host") {
        let host = args.get(1).cloned().expect("--host HOST RDT_PORT");
        let port: u16 = args
            .get(2)
            .and_then(|p| p.parse().ok())
            .expect("--host HOST RDT_PORT");
        args.drain(..3);
        Some((host, port))
    } else {
        None
    };
    let num = |i: usize, d: f64| args.get(i).and_then(|v| v.parse().ok()).unwrap_or(d);
    let rate = num(0, 7000.0);
    let seconds = num(1, 10.0);
    let mut read_hz: Vec<f64> = args.iter().skip(2).filter_map(|v| v.parse().ok()).collect();
    if read_hz.is_empty() {
        read_hz = vec![500.0, 100.0, 10.0];
    }
    let load = Wrench {
        force_n: [1.5, -2.25, 12.34],
        torque_nm: [0.125, -0.05, 0.3],
    };
    let server;
    let simulated = external.is_none();
    let (host, port) = match external {
        Some(hp) => hp,
        None => {
            let core = NetFtCore::new(
                NetFtSimConfig {
                    rate_hz: rate,
                    ..NetFtSimConfig::default()
                },
                SharedWrench::new(load),
            );
            server = NetFtServer::spawn(core, 0, 0).expect("serve the simulator");
            ("127.0.0.1".to_string(), server.rdt_addr().port())
        }
    };
    let scale = DEFAULT_CALINFO.scale().expect("scale");
    let link = UdpTransport::connect("netft", &host, port).expect("udp");
    let mut d = NetFt::connect(link, NetFtOptions::netft(scale)).expect("connect");
    println!(
        "stream measured at {:.0} Hz at connect ({} s per case)",
        d.measured_rate_hz(),
        seconds
    );
    println!("read_hz  readings  readings/s  records  lost   records/s  cpu_ms  cpu_%_of_one_core");
    for hz in read_hz {
        let period = Duration::from_secs_f64(1.0 / hz);
        let s0 = d.stats();
        let c0 = thread_cpu();
        let t0 = Instant::now();
        let end = t0 + Duration::from_secs_f64(seconds);
        let mut next = t0;
        let mut n = 0u64;
        while Instant::now() < end {
            let w = d.read().expect("read");
            if simulated {
                assert!((w.force_n[2] - load.force_n[2]).abs() < 1e-5, "{w:?}");
            }
            n += 1;
            next += period;
            let now = Instant::now();
            if next > now {
                std::thread::sleep(next - now);
            }
        }
        let wall = t0.elapsed().as_secs_f64();
        let cpu = thread_cpu() - c0;
        let s = d.stats();
        println!(
            "{hz:>7.0}  {n:>8}  {:>10.1}  {:>7}  {:>5}  {:>9.0}  {:>6.1}  {:>6.2}",
            n as f64 / wall,
            s.records - s0.records,
            s.lost - s0.lost,
            (s.records - s0.records) as f64 / wall,
            cpu.as_secs_f64() * 1e3,
            cpu.as_secs_f64() / wall * 100.0
        );
    }
}
