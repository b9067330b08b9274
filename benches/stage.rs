//! Driver overhead per command: GRBL and Zaber drivers against their simulators
//! served on a real pseudo-terminal. A pty has no wire time, so each figure is the
//! round trip through the driver, the kernel pty and the simulator thread; the
//! wire time a real 115200-baud link adds is bytes × 10 bit / 115200 baud (printed
//! for comparison).
//!
//! Run: `cargo bench --bench stage`

use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion};
use tactbench::device::grbl::sim::{GrblSim, GrblSimConfig};
use tactbench::device::grbl::{self, Grbl, GrblConfig};
use tactbench::device::pty::{PtyServer, Simulator};
use tactbench::device::zaber::sim::{ZaberSim, ZaberSimConfig};
use tactbench::device::zaber::{self, Zaber, ZaberConfig};
use tactbench::device::Stage;

/// The simulator in-process, without a pty or thread: writes step it, reads return
/// what it produced. Isolates the driver's (and simulator's) own CPU cost.
struct Loopback<S> {
    sim: S,
    start: std::time::Instant,
    out: Vec<u8>,
}

impl<S: Simulator> Loopback<S> {
    fn new(sim: S) -> Self {
        Loopback {
            sim,
            start: std::time::Instant::now(),
            out: Vec::new(),
        }
    }
}

impl<S: Simulator> std::io::Read for Loopback<S> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        if self.out.is_empty() {
            let mut out = Vec::new();
            self.sim.step(self.start.elapsed(), &[], &mut out);
            self.out = out;
        }
        if self.out.is_empty() {
            return Err(std::io::Error::new(
                std::io::ErrorKind::TimedOut,
                "nothing yet",
            ));
        }
        let n = self.out.len().min(buf.len());
        buf[..n].copy_from_slice(&self.out[..n]);
        self.out.drain(..n);
        Ok(n)
    }
}

impl<S: Simulator> std::io::Write for Loopback<S> {
    fn write(&mut self, data: &[u8]) -> std::io::Result<usize> {
        let mut out = Vec::new();
        self.sim.step(self.start.elapsed(), data, &mut out);
        self.out.extend_from_slice(&out);
        Ok(data.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

fn bench_in_process(c: &mut Criterion) {
    let mut g = Grbl::connect(
        Loopback::new(GrblSim::new(GrblSimConfig::default())),
        GrblConfig::default(),
    )
    .expect("connect");
    c.bench_function("in-process grbl position (driver + sim CPU only)", |b| {
        b.iter(|| g.position().expect("position"))
    });
    c.bench_function("in-process grbl unlock (driver + sim CPU only)", |b| {
        b.iter(|| g.unlock().expect("unlock"))
    });
    let mut z = Zaber::connect(
        Loopback::new(ZaberSim::new(ZaberSimConfig::three_single_axis(1_000_000))),
        ZaberConfig::default(),
    )
    .expect("connect");
    c.bench_function(
        "in-process zaber position, 3 axes (driver + sim CPU only)",
        |b| b.iter(|| z.position().expect("position")),
    );
}

fn wire_ms(bytes: usize) -> f64 {
    bytes as f64 * 10.0 / 115_200.0 * 1e3
}

fn bench_grbl(c: &mut Criterion) {
    let server = PtyServer::spawn(GrblSim::new(GrblSimConfig::default()), None).expect("pty");
    let port = grbl::open_serial(&server.path().to_string_lossy(), 115_200).expect("open");
    let mut g = Grbl::connect(port, GrblConfig::default()).expect("connect");
    // `?` (1 byte) + `<Idle|MPos:0.000,0.000,0.000|FS:0,0>\r\n` (~40 bytes).
    eprintln!(
        "grbl position: wire time at 115200 baud ~ {:.2} ms",
        wire_ms(41)
    );
    c.bench_function("grbl position (? -> status report)", |b| {
        b.iter(|| g.position().expect("position"))
    });
    // `$X\n` + `ok\r\n`: the plainest line round trip.
    eprintln!("grbl unlock: wire time ~ {:.2} ms", wire_ms(7));
    c.bench_function("grbl unlock ($X -> ok)", |b| {
        b.iter(|| g.unlock().expect("unlock"))
    });
    // `G21 G53 G1 X.. Y.. Z.. F..\n` (~45 bytes) + `ok\r\n`; the move is 0 mm long.
    eprintln!("grbl move_to: wire time ~ {:.2} ms", wire_ms(49));
    c.bench_function("grbl move_to (line -> ok), zero-length move", |b| {
        b.iter(|| g.move_to([0.0, 0.0, 0.0], Some(10.0)).expect("move"))
    });
    // move_to + wait_idle: `G4 P0` round trip after a zero-length move.
    c.bench_function("grbl move_to + wait_idle, zero-length move", |b| {
        b.iter(|| {
            g.move_to([0.0, 0.0, 0.0], Some(10.0)).expect("move");
            g.wait_idle(Duration::from_secs(1)).expect("wait")
        })
    });
    drop(server);
}

fn bench_zaber(c: &mut Criterion) {
    let server = PtyServer::spawn(
        ZaberSim::new(ZaberSimConfig::three_single_axis(1_000_000)),
        None,
    )
    .expect("pty");
    let port = zaber::open_serial(&server.path().to_string_lossy(), 115_200).expect("open");
    let mut z = Zaber::connect(port, ZaberConfig::default()).expect("connect");
    // Three `/1 1 12 get pos:CC\n` (~20 bytes) + `@01 1 12 OK IDLE WR 500000:CC\r\n` (~31).
    eprintln!(
        "zaber position: wire time ~ {:.2} ms (3 axes)",
        wire_ms(3 * 51)
    );
    c.bench_function("zaber position (3 x get pos)", |b| {
        b.iter(|| z.position().expect("position"))
    });
    drop(server);
}

criterion_group! {
    name = benches;
    config = Criterion::default()
        .sample_size(50)
        .measurement_time(Duration::from_secs(3))
        .warm_up_time(Duration::from_millis(500));
    targets = bench_in_process, bench_grbl, bench_zaber
}
criterion_main!(benches);
