//! Repeatable instruction counts for the tracker: renders the paper frames of
//! `benches/vision.rs` (8-bit, σ = 2 noise), detects the reference, then tracks
//! `N` frames in one mode, for `valgrind --tool=callgrind` (criterion medians are noisy
//! on a shared machine; instruction counts are not).
//!
//! Run: `cargo build --release --example vision_profile && valgrind --tool=callgrind
//! --toggle-collect='*Tracker*track*' target/release/examples/vision_profile per-window 20`
//! and divide the reported `Collected` instructions by `N` (valgrind reports no AVX-512,
//! so this measures the AVX2 kernel).

use image::RgbImage;
use tactbench::sensor::paper_sensor;
use tactbench::sim::render::{reference_markers, render_sensor, to_rgb8};
use tactbench::vision::{detect, DetectConfig, FrameView, TrackConfig, TrackMode, Tracker};

/// As `benches/vision.rs`: the paper markers shifted by `shift_px` in x, 8-bit, σ = 2.
fn frame(shift_px: f64, seed: u64) -> RgbImage {
    let s = paper_sensor();
    let n = reference_markers(&s).len();
    let u: Vec<f64> = (0..n)
        .flat_map(|_| [shift_px * s.camera.mm_per_px, 0.0])
        .collect();
    let mut img = to_rgb8(&render_sensor(&s, Some(&u)).expect("paper sensor renders"));
    let mut state = seed | 1;
    let mut uniform = move || {
        state ^= state >> 12;
        state ^= state << 25;
        state ^= state >> 27;
        ((state.wrapping_mul(0x2545F4914F6CDD1D) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    for v in img.iter_mut() {
        let g = (-2.0 * uniform().ln()).sqrt() * (2.0 * std::f64::consts::PI * uniform()).cos();
        *v = (*v as f64 + 2.0 * g).round().clamp(0.0, 255.0) as u8;
    }
    img
}

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
