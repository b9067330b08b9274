//! Force/torque sensor overheads: codec costs, driver per-command overhead against an
//! in-memory simulator (no OS in the loop), and full round trips over a real
//! pseudo-terminal (driver + pty + simulator thread), whose inverse is the sustained
//! polled rate. Run: `cargo bench --bench ft`.

use std::io::{self, Read, Write};
use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, Criterion};

use tactbench::device::dynpick::codec::Record;
use tactbench::device::dynpick::{driver as dp, DynPick, DynPickSim, DynPickSimConfig};
use tactbench::device::ft300::codec::{crc16, StreamDecoder, StreamFrame};
use tactbench::device::ft300::{driver as ft, Ft300, Ft300Sim, Ft300SimConfig};
use tactbench::device::ft_common::{open_serial, SharedWrench};
use tactbench::device::pty::{PtyServer, Simulator};
use tactbench::device::{ForceSensor, Wrench};

/// A simulator as an in-memory `Read + Write`: writes step it, reads return its
/// output; nothing to read is `TimedOut`, as on a serial port.
struct Loop<S> {
    sim: S,
    start: Instant,
    out: Vec<u8>,
}

impl<S: Simulator> Loop<S> {
    fn new(sim: S) -> Self {
        Loop {
            sim,
            start: Instant::now(),
            out: Vec::new(),
        }
    }
}

impl<S: Simulator> Read for Loop<S> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if self.out.is_empty() {
            let now = self.start.elapsed();
            self.sim.step(now, &[], &mut self.out);
        }
        if self.out.is_empty() {
            return Err(io::Error::new(io::ErrorKind::TimedOut, "nothing"));
        }
        let n = buf.len().min(self.out.len());
        buf[..n].copy_from_slice(&self.out[..n]);
        self.out.drain(..n);
        Ok(n)
    }
}

impl<S: Simulator> Write for Loop<S> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let now = self.start.elapsed();
        self.sim.step(now, buf, &mut self.out);
        Ok(buf.len())
    }
    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

const LOAD: Wrench = Wrench {
    force_n: [1.5, -2.25, 12.34],
    torque_nm: [0.125, -0.05, 0.3],
};

fn codecs(c: &mut Criterion) {
    let rec = Record {
        counter: 3,
        raw: [8192, 8300, 7000, 9000, 8192, 100],
    }
    .encode();
    c.bench_function("codec/dynpick_record_decode", |b| {
        b.iter(|| Record::decode(std::hint::black_box(&rec)))
    });
    let frame = StreamFrame {
        raw: [1, -2, 300, 4, -5, 6],
    }
    .encode();
    c.bench_function("codec/ft300_crc16_14_bytes", |b| {
        b.iter(|| crc16(std::hint::black_box(&frame[..14])))
    });
    let chunk: Vec<u8> = (0..16).flat_map(|_| frame).collect();
    c.bench_function("codec/ft300_stream_decode_16_frames", |b| {
        let mut d = StreamDecoder::default();
        let mut out = Vec::with_capacity(16);
        b.iter(|| {
            out.clear();
            d.push(std::hint::black_box(&chunk), &mut out);
            out.len()
        })
    });
}

fn drivers_in_memory(c: &mut Criterion) {
    let sim = DynPickSim::new(DynPickSimConfig::default(), SharedWrench::new(LOAD));
    let mut d = DynPick::connect(Loop::new(sim)).expect("connect");
    c.bench_function("driver_in_memory/dynpick_read", |b| {
        b.iter(|| d.read().expect("read"))
    });
    let sim = Ft300Sim::new(Ft300SimConfig::default(), SharedWrench::new(LOAD));
    let mut f = Ft300::connect(Loop::new(sim)).expect("connect");
    c.bench_function("driver_in_memory/ft300_read", |b| {
        b.iter(|| f.read().expect("read"))
    });
}

fn drivers_over_pty(c: &mut Criterion) {
    let mut g = c.benchmark_group("pty_round_trip");
    g.measurement_time(Duration::from_secs(5));
    let server = PtyServer::spawn(
        DynPickSim::new(DynPickSimConfig::default(), SharedWrench::new(LOAD)),
        None,
    )
    .expect("pty");
    let port =
        open_serial("dynpick", server.path().to_str().expect("path"), dp::BAUD).expect("open");
    let mut d = DynPick::connect(port).expect("connect");
    g.bench_function("dynpick_read", |b| b.iter(|| d.read().expect("read")));
    let server2 = PtyServer::spawn(
        Ft300Sim::new(Ft300SimConfig::default(), SharedWrench::new(LOAD)),
        None,
    )
    .expect("pty");
    let port =
        open_serial("ft300", server2.path().to_str().expect("path"), ft::BAUD).expect("open");
    let mut f = Ft300::connect(port).expect("connect");
    g.bench_function("ft300_read", |b| b.iter(|| f.read().expect("read")));
    g.finish();
    drop((server, server2));
}

criterion_group!(benches, codecs, drivers_in_memory, drivers_over_pty);
criterion_main!(benches);
