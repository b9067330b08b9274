//! Host check: round-trip latency of a one-byte echo over a real pseudo-terminal,
//! served by the same [`PtyServer`] loop as the simulated bench.
//!
//! `cargo run --release --example pty_latency -- 30` runs for 30 s and prints the
//! median, p99, p99.9 and worst round trip, and for the worst one how long the byte
//! took to reach the simulator (the rest is the way back). The simulated bench's
//! reply deadlines (500 ms for the F/T sensors) assume the host delivers pty bytes
//! well within that. On a 2-vCPU VM whose CPUs were saturated by other processes,
//! the kernel's pty flush work was measured to wait for seconds (threads blocked in
//! `flush_work`); then the simulated devices time out and runs abort cleanly.
use std::io::{Read, Write};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tactbench::device::ft_common::open_serial;
use tactbench::device::pty::{Flow, PtyServer, Simulator};

/// Echoes every byte; records when it last received one (ns since `origin`).
struct Echo {
    seen_ns: Arc<AtomicU64>,
    origin: Instant,
}

impl Simulator for Echo {
    fn step(&mut self, _now: Duration, input: &[u8], output: &mut Vec<u8>) -> Flow {
        if !input.is_empty() {
            let ns = self.origin.elapsed().as_nanos() as u64;
            self.seen_ns.store(ns, Ordering::SeqCst);
        }
        output.extend_from_slice(input);
        Flow::Continue
    }
}

fn main() {
    let secs: f64 = match std::env::args().nth(1).map(|s| s.parse::<f64>()) {
        None => 10.0,
        Some(Ok(s)) if s > 0.0 && s.is_finite() => s,
        Some(_) => {
            eprintln!("usage: pty_latency [SECONDS > 0] (default 10)");
            std::process::exit(2);
        }
    };
    let origin = Instant::now();
    let seen_ns = Arc::new(AtomicU64::new(0));
    let echo = Echo {
        seen_ns: Arc::clone(&seen_ns),
        origin,
    };
    let server = match PtyServer::spawn(echo, None) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(2);
        }
    };
    let path = server.path().display().to_string();
    let mut port = match open_serial("echo", &path, 921_600) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(2);
        }
    };
    let t0 = Instant::now();
    let mut ms = Vec::new();
    // (round trip, outbound leg) of the worst round trip, ms.
    let mut worst = (0.0f64, 0.0f64);
    while t0.elapsed().as_secs_f64() < secs {
        let sent = Instant::now();
        if let Err(e) = port.write_all(b"R") {
            eprintln!("error: write: {e}");
            std::process::exit(2);
        }
        let mut b = [0u8; 1];
        loop {
            match port.read(&mut b) {
                Ok(1) => break,
                Ok(_) => {}
                Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                Err(e) => {
                    eprintln!("error: read: {e}");
                    std::process::exit(2);
                }
            }
        }
        let total = sent.elapsed().as_secs_f64() * 1e3;
        if total > worst.0 {
            let out_ns = seen_ns.load(Ordering::SeqCst) as f64
                - sent.duration_since(origin).as_nanos() as f64;
            worst = (total, out_ns * 1e-6);
        }
        ms.push(total);
    }
    ms.sort_by(f64::total_cmp);
    let n = ms.len();
    let q = |p: f64| ms[((n as f64 * p) as usize).min(n - 1)];
    println!(
        "{n} round trips in {secs} s: median {:.3} ms, p99 {:.3} ms, p99.9 {:.3} ms, worst {:.1} ms (outbound {:.1} ms); over 100 ms: {}",
        q(0.5),
        q(0.99),
        q(0.999),
        worst.0,
        worst.1,
        ms.iter().filter(|&&m| m > 100.0).count()
    );
}
