//! Vision benchmarks on the paper geometry (430×340 px, 260 markers in two layers):
//! reference detection, and tracking one 8-bit frame per-window and frame-to-frame,
//! and per-window with the two layers slid into one another (every marker partly
//! covered: the overlap path, `Window::locate_masked`, runs for all 260).
//! Frames come from the `sim` ideal renderer with σ = 2 pixel noise added here; and
//! real frames of real sensors (`../shared/real_frames`: TacTip 640×480, GelSight
//! 1280×720 and 320×240), tracked per window.
//! Paper (Table II): 2.9 ms for tracking + reconstruction on a 1.8 GHz Pentium 4.
//!
//! The tracking benches run twice: timed by the wall clock, and by this thread's CPU
//! time (`vision/cpu_*`; the machine is shared, so wall time includes waiting).
//!
//! And files in, displacements out: decode + track per TacTip PNG, one after another
//! and with the frames decoded ahead on worker threads (`vision/decode_track_*`).
//!
//! Run: `cargo bench --bench vision`.

use std::hint::black_box;
use std::path::PathBuf;

use criterion::measurement::{Measurement, ValueFormatter, WallTime};
use criterion::{criterion_group, criterion_main, Criterion};
#[path = "common/paper_frame.rs"]
mod paper_frame;
#[path = "common/real_frames.rs"]
mod real_frames;

use image::RgbImage;
use paper_frame::frame;
use tactbench::sensor::paper_sensor;
use tactbench::vision::{
    decode_ahead, decoder_threads, detect, DetectConfig, Frame, FrameView, TrackConfig, TrackMode,
    Tracker,
};

/// Criterion measurement of this thread's CPU time (`CLOCK_THREAD_CPUTIME_ID`), so
/// figures on the shared, loaded machine are not inflated by time spent waiting for a
/// core. Read once per sample of many iterations.
struct CpuTime;

/// This thread's CPU time, ns.
fn thread_cpu_ns() -> u64 {
    tactbench::clock::thread_cpu_ns().expect("thread CPU clock (Linux)")
}

impl Measurement for CpuTime {
    type Intermediate = u64;
    type Value = u64;
    fn start(&self) -> u64 {
        thread_cpu_ns()
    }
    fn end(&self, start: u64) -> u64 {
        thread_cpu_ns().saturating_sub(start)
    }
    fn add(&self, a: &u64, b: &u64) -> u64 {
        a + b
    }
    fn zero(&self) -> u64 {
        0
    }
    fn to_f64(&self, v: &u64) -> f64 {
        *v as f64
    }
    fn formatter(&self) -> &dyn ValueFormatter {
        WallTime.formatter()
    }
}

fn vision(c: &mut Criterion) {
    detection(c);
    tracking(c, "");
    real(c, "");
    decode_and_track(c);
}

fn vision_cpu(c: &mut Criterion<CpuTime>) {
    tracking(c, "cpu_");
    real(c, "cpu_");
}

/// Per-window tracking of real frames (issue 19, part 6; `benches/common/real_frames.rs`):
/// TacTip 640×480 with ~330 pins (target ≤ 1 ms on one core), the GelSight bright
/// dots at 1280×720, the FOTS dark dots at 320×240. Skipped, with a message, when
/// `../shared/real_frames` is absent. The OpenCV pipeline on the same files runs
/// beside ours in `examples/tracking_side_by_side.rs`.
fn real<M: Measurement + 'static>(c: &mut Criterion<M>, prefix: &str) {
    let scratch = std::env::temp_dir().join(format!("tactbench_bench_{}", std::process::id()));
    let Some(cases) = real_frames::cases(&scratch) else {
        eprintln!(
            "{}: real frames absent, real-frame benches skipped",
            real_frames::dir().display()
        );
        return;
    };
    for case in &cases {
        let (_reference, frame, r) = real_frames::load(case);
        let n = r.markers.len();
        let mut t = Tracker::new(
            r,
            TrackConfig {
                mode: TrackMode::PerWindow,
                ..TrackConfig::default()
            },
        );
        let view = frame.view();
        c.bench_function(
            &format!("vision/{prefix}track_real_{}_{n}_markers", case.name),
            |b| b.iter(|| t.track(black_box(&view)).unwrap().len()),
        );
    }
    let _ = std::fs::remove_dir_all(&scratch);
}

/// Files in, displacements out (issue 32): decode + track per frame of the real
/// TacTip frames (10 PNG files, 640×480), one after another on one thread, and through
/// `vision::decode_ahead` (decoding on worker threads while this one tracks), per
/// frame. The OpenCV pipeline on the same files: `tests/opencv_ref/files_bench.py`.
fn decode_and_track(c: &mut Criterion) {
    let scratch = std::env::temp_dir().join(format!("tactbench_bench_d{}", std::process::id()));
    let Some(cases) = real_frames::cases(&scratch) else {
        return;
    };
    let Some(case) = cases.iter().find(|c| c.name.starts_with("tactip")) else {
        return;
    };
    let (_reference, _frame, r) = real_frames::load(case);
    let files: Vec<PathBuf> = (1..=10)
        .map(|k| real_frames::dir().join(format!("tactip/image_{k}.png")))
        .collect();
    let mut t = Tracker::new(
        r,
        TrackConfig {
            mode: TrackMode::FrameToFrame,
            ..TrackConfig::default()
        },
    );
    let mut g = c.benchmark_group("vision/decode_track_tactip_10_files");
    g.throughput(criterion::Throughput::Elements(files.len() as u64));
    g.bench_function("sequential", |b| {
        b.iter(|| {
            for f in &files {
                let frame = Frame::open(f).unwrap();
                black_box(t.track(&frame.view()).unwrap().len());
            }
        })
    });
    let threads = decoder_threads(files.len());
    g.bench_function(format!("decode_ahead_{threads}_threads"), |b| {
        b.iter(|| {
            decode_ahead(
                &files,
                threads,
                2 * threads,
                |f| Frame::open(f).unwrap(),
                |_, frame| {
                    black_box(t.track(&frame.view()).unwrap().len());
                    true
                },
            )
        })
    });
    g.finish();
    let _ = std::fs::remove_dir_all(&scratch);
}

fn detection(c: &mut Criterion) {
    let s = paper_sensor();
    let reference = frame(0.0, 1);
    let reference_view = FrameView::rgb8(&reference);
    c.bench_function("vision/detect_reference_paper_430x340", |b| {
        b.iter(|| detect(black_box(&reference_view), &s, &DetectConfig::default()).unwrap())
    });
}

/// The tracking benches, timed by `M` (wall clock, or thread CPU time with `prefix`
/// `"cpu_"`).
fn tracking<M: Measurement + 'static>(c: &mut Criterion<M>, prefix: &str) {
    let s = paper_sensor();
    let reference = frame(0.0, 1);
    let shifted = frame(3.0, 2);
    // A steady sequence: 0.25 px per frame along x, 8 frames, cycled.
    let sequence: Vec<RgbImage> = (0..8)
        .map(|k| frame(3.0 + 0.25 * k as f64, 10 + k))
        .collect();
    let reference_view = FrameView::rgb8(&reference);
    let r = detect(&reference_view, &s, &DetectConfig::default()).unwrap();
    assert_eq!(r.markers.len(), 260);

    // Per-window: every frame measured from the reference positions (3 px shift).
    let mut per_window = Tracker::new(
        r.clone(),
        TrackConfig {
            mode: TrackMode::PerWindow,
            ..TrackConfig::default()
        },
    );
    let view = FrameView::rgb8(&shifted);
    c.bench_function(
        &format!("vision/{prefix}track_per_window_paper_260_markers"),
        |b| b.iter(|| per_window.track(black_box(&view)).unwrap().len()),
    );

    // Frame-to-frame on a steady sequence (markers move 0.25 px every frame; each
    // window starts at the last position plus the last velocity). The wrap from the
    // last frame back to the first (−1.75 px) is included once every 8 frames.
    let mut f2f = Tracker::new(r, TrackConfig::default());
    let views: Vec<FrameView<'_>> = sequence.iter().map(FrameView::rgb8).collect();
    for v in &views {
        f2f.track(v).unwrap();
    }
    let mut k = 0;
    c.bench_function(
        &format!("vision/{prefix}track_frame_to_frame_paper_260_markers"),
        |b| {
            b.iter(|| {
                k = (k + 1) % views.len();
                f2f.track(black_box(&views[k])).unwrap().len()
            })
        },
    );
}

/// The blue layer slid diagonally until each blue marker's centre is 10 px from its
/// red neighbour's (as `tests/vision.rs`, overlapping layers): 8-bit, noise-free.
fn overlapping_frame() -> RgbImage {
    use tactbench::sim::render::{reference_markers, render_sensor, to_rgb8};
    let s = paper_sensor();
    let slide = (15.0 * std::f64::consts::SQRT_2 - 10.0) / std::f64::consts::SQRT_2;
    let u_mm: Vec<f64> = reference_markers(&s)
        .iter()
        .flat_map(|m| {
            let u = if m.layer == 0 { slide } else { 0.0 };
            [u * s.camera.mm_per_px, u * s.camera.mm_per_px]
        })
        .collect();
    to_rgb8(&render_sensor(&s, Some(&u_mm)).unwrap())
}

/// Per-window tracking of [`overlapping_frame`]: the overlap path's cost.
fn overlap(c: &mut Criterion) {
    let s = paper_sensor();
    let reference = frame(0.0, 1);
    let r = detect(&FrameView::rgb8(&reference), &s, &DetectConfig::default()).unwrap();
    let mut t = Tracker::new(
        r,
        TrackConfig {
            mode: TrackMode::PerWindow,
            ..TrackConfig::default()
        },
    );
    let f = overlapping_frame();
    let view = FrameView::rgb8(&f);
    c.bench_function("vision/track_overlapping_layers_paper_260_markers", |b| {
        b.iter(|| t.track(black_box(&view)).unwrap().len())
    });
}

criterion_group!(benches, vision, overlap);
criterion_group! {
    name = cpu;
    config = Criterion::default().with_measurement(CpuTime);
    targets = vision_cpu
}
criterion_main!(benches, cpu);
