//! Per-frame time of the Rust tracker on one frame, the yardstick of the Python
//! bindings' speed (`experiments/python/bench_tracker.py` runs it beside
//! `tactbench.Tracker.track` on the same files in one run).
//!
//! Run: `cargo run --release --example track_time -- SENSOR.toml REF.png FRAME.png
//! [N] [per-window|frame-to-frame]`; prints `rust_track_us min=… median=…` over N
//! frames (each `Tracker::track` call timed on its own, after 50 warm-up calls).

use std::path::PathBuf;
use std::time::Instant;

use tactbench::sensor::Sensor;
use tactbench::vision::{detect, load_frame, DetectConfig, TrackConfig, TrackMode, Tracker};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 4 {
        anyhow::bail!(
            "usage: track_time SENSOR.toml REF.png FRAME.png [N] [per-window|frame-to-frame]"
        );
    }
    let sensor = Sensor::from_path(PathBuf::from(&args[1]))?;
    let reference = load_frame(&PathBuf::from(&args[2]), &sensor.camera)?;
    let frame = load_frame(&PathBuf::from(&args[3]), &sensor.camera)?;
    let n: usize = args.get(4).map_or(Ok(2000), |a| a.parse())?;
    let mode = match args.get(5).map(String::as_str) {
        None | Some("frame-to-frame") => TrackMode::FrameToFrame,
        Some("per-window") => TrackMode::PerWindow,
        Some(other) => anyhow::bail!("unknown mode {other}"),
    };
    let r = detect(&reference.view(), &sensor, &DetectConfig::default())?;
    let mut t = Tracker::new(
        r,
        TrackConfig {
            mode,
            ..TrackConfig::default()
        },
    );
    let view = frame.view();
    for _ in 0..50 {
        t.track(&view)?;
    }
    let mut times = Vec::with_capacity(n);
    for _ in 0..n {
        let t0 = Instant::now();
        std::hint::black_box(t.track(&view)?);
        times.push(t0.elapsed().as_secs_f64() * 1e6);
    }
    times.sort_by(f64::total_cmp);
    println!(
        "rust_track_us min={:.2} median={:.2} n={n}",
        times[0],
        times[n / 2]
    );
    Ok(())
}
