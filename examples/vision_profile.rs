//! Repeatable instruction counts for the tracker: renders the paper frames of
//! `benches/vision.rs` (8-bit, σ = 2 noise), detects the reference, then tracks
//! `N` frames in one mode, for `valgrind --tool=callgrind` (criterion medians are noisy
//! on a shared machine; instruction counts are not).
//!
//! Run: `cargo build --release --example vision_profile && valgrind --tool=callgrind
//! --toggle-collect='*Tracker*track*' target/release/examples/vision_profile per-window 20`
//! and divide the reported `Collected` instructions by `N` (valgrind reports no AVX-512,
//! so this measures the AVX2 kernel).

#[path = "../benches/common/paper_frame.rs"]
mod paper_frame;

use image::RgbImage;
use paper_frame::frame;
use tactbench::sensor::paper_sensor;
use tactbench::vision::{detect, DetectConfig, FrameView, TrackConfig, TrackMode, Tracker};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let mode = match args.get(1).map(String::as_str) {
        Some("per-window") => TrackMode::PerWindow,
        Some("frame-to-frame") => TrackMode::FrameToFrame,
        other => {
            anyhow::bail!("usage: vision_profile per-window|frame-to-frame [N] (got {other:?})")
        }
    };
    let n: usize = args.get(2).map_or(Ok(20), |a| a.parse())?;
    let s = paper_sensor();
    let reference = frame(0.0, 1);
    let r = detect(&FrameView::rgb8(&reference), &s, &DetectConfig::default())?;
    let frames: Vec<RgbImage> = match mode {
        TrackMode::PerWindow => vec![frame(3.0, 2)],
        TrackMode::FrameToFrame => (0..8)
            .map(|k| frame(3.0 + 0.25 * k as f64, 10 + k))
            .collect(),
    };
    let views: Vec<FrameView<'_>> = frames.iter().map(FrameView::rgb8).collect();
    let mut t = Tracker::new(
        r,
        TrackConfig {
            mode,
            ..TrackConfig::default()
        },
    );
    if mode == TrackMode::FrameToFrame {
        // Warm the velocities as the bench does.
        for v in &views {
            t.track(v)?;
        }
    }
    let mut ok = 0;
    for k in 0..n {
        let tracks = t.track(&views[k % views.len()])?;
        ok += tracks
            .iter()
            .filter(|t| t.status == tactbench::vision::MarkerStatus::Ok)
            .count();
    }
    println!("{mode:?}: {n} frames, {ok} ok tracks");
    Ok(())
}
