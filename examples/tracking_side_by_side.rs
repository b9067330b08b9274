//! Tracking speed on real frames, side by side with an OpenCV pipeline, in one run
//! (issue 19, part 6): for each case of `benches/common/real_frames.rs` (TacTip
//! 640×480 with ~330 pins, GelSight bright dots 1280×720, FOTS dark dots 320×240),
//! times tactbench's per-window tracker on one core (this thread's CPU time and the
//! wall clock, `REPS` repetitions of one frame), then runs
//! `tests/opencv_ref/track_ref.py --bench REPS` (blob centroids + nearest neighbour,
//! NumPy/OpenCV) on the same files, and prints frames per second of both and the ratio.
//! The OpenCV figure is its process CPU time (all of OpenCV's threads) and wall time.
//!
//! Run (needs `pip install numpy opencv-python-headless`):
//! `TACTBENCH_PYTHON=python3 cargo run --release --example tracking_side_by_side [REPS]`

#[path = "../benches/common/real_frames.rs"]
mod real_frames;

use std::process::Command;
use std::time::Instant;

use anyhow::{bail, Context};
use tactbench::vision::{MarkerStatus, TrackConfig, TrackMode, Tracker};

fn main() -> anyhow::Result<()> {
    let reps: usize = std::env::args().nth(1).map_or(Ok(200), |a| a.parse())?;
    let python = std::env::var("TACTBENCH_PYTHON").unwrap_or_else(|_| "python3".into());
    let script =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/opencv_ref/track_ref.py");
    let scratch =
        std::env::temp_dir().join(format!("tactbench_side_by_side_{}", std::process::id()));
    let Some(cases) = real_frames::cases(&scratch) else {
        bail!("{}: real frames absent", real_frames::dir().display());
    };
    println!(
        "| frame | markers (ok) | tactbench µs/frame CPU (wall) | frames/s CPU | OpenCV blobs | OpenCV frames/s CPU (wall) | ratio (CPU) |"
    );
    println!("|---|---|---|---|---|---|---|");
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
        let ok = t
            .track(&view)?
            .iter()
            .filter(|m| m.status == MarkerStatus::Ok)
            .count();
        let (c0, w0) = (
            tactbench::clock::thread_cpu_ns().context("thread CPU clock")?,
            Instant::now(),
        );
        for _ in 0..reps {
            std::hint::black_box(t.track(std::hint::black_box(&view))?.len());
        }
        let cpu_us = (tactbench::clock::thread_cpu_ns().context("thread CPU clock")? - c0) as f64
            / 1e3
            / reps as f64;
        let wall_us = w0.elapsed().as_secs_f64() * 1e6 / reps as f64;

        let mut cmd = Command::new(&python);
        cmd.arg(&script)
            .args(["--appearance", case.appearance])
            .args(["--kernel", &case.kernel.to_string()])
            .args(["--bench", &reps.min(200).to_string()]);
        if let Some([x, y, r]) = case.roi {
            cmd.arg("--roi")
                .args([x.to_string(), y.to_string(), r.to_string()]);
        }
        let out = cmd
            .arg(&case.reference)
            .arg(&case.frame)
            .output()
            .with_context(|| format!("running {python} {}", script.display()))?;
        if !out.status.success() {
            bail!("{}", String::from_utf8_lossy(&out.stderr));
        }
        let text = String::from_utf8_lossy(&out.stdout);
        let field = |key: &str| -> anyhow::Result<f64> {
            text.lines()
                .find_map(|l| l.strip_prefix(key))
                .with_context(|| format!("{key} missing in: {text}"))?
                .parse::<f64>()
                .with_context(|| key.to_string())
        };
        let (blobs, fps_cpu, fps_wall) = (
            field("opencv_blobs=")?,
            field("opencv_frames_per_s_cpu=")?,
            field("opencv_frames_per_s_wall=")?,
        );
        let ours = 1e6 / cpu_us;
        println!(
            "| {} | {n} ({ok}) | {cpu_us:.0} ({wall_us:.0}) | {ours:.0} | {blobs:.0} | {fps_cpu:.1} ({fps_wall:.1}) | {:.0}× |",
            case.name,
            ours / fps_cpu
        );
    }
    let _ = std::fs::remove_dir_all(&scratch);
    Ok(())
}
