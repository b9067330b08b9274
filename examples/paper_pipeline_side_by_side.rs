//! The paper's pipeline (track + solve), tactbench against NumPy/OpenCV, side by side
//! in one run (issue 19, part 6): the accuracy-vs-time study's `pinv` row (per-window
//! tracking, 8 re-centrings, pinv f64 on the sensor's force grid) on
//! `experiments/scenes/study_hemisphere_noisy.toml` (the paper sensor, 8-bit camera,
//! σ = 2 levels of noise), then `tests/numpy_ref/paper_pipeline.py` (the same method
//! in NumPy, pinv precomputed; a `plain` and a `tuned` variant) on the same rendered
//! frames. Prints the time per force frame of each (median thread / process CPU time
//! and wall time), the ratios, and the force sums (they must agree: the same
//! computation).
//!
//! Run (needs `pip install numpy opencv-python-headless`):
//! `TACTBENCH_PYTHON=python3 cargo run --release --example paper_pipeline_side_by_side [REPS]`

use std::process::Command;

use anyhow::{bail, Context};
use serde_json::json;
use tactbench::analysis::accuracy_time::{run_study, Setting, StudyOptions};
use tactbench::sim::render::to_rgb8;
use tactbench::sim::scene::Scene;
use tactbench::sim::simulate::Simulation;
use tactbench::vision::{detect, DetectConfig, Frame};

fn main() -> anyhow::Result<()> {
    let reps: usize = std::env::args().nth(1).map_or(Ok(200), |a| a.parse())?;
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let python = std::env::var("TACTBENCH_PYTHON").unwrap_or_else(|_| "python3".into());
    let scene = Scene::from_path(root.join("experiments/scenes/study_hemisphere_noisy.toml"))?;
    let scratch = std::env::temp_dir().join(format!("tactbench_pipeline_{}", std::process::id()));
    std::fs::create_dir_all(&scratch)?;

    // The frames the study tracks: its reference and its first loaded frame.
    let mut sim = Simulation::from_scene(&scene);
    if !sim.pipeline().quantizes_to_8bit() {
        bail!("the scene must quantise to 8 bits (the study's camera)");
    }
    let mut buf = sim.blank_frame();
    sim.render_reference(&mut buf)?;
    let reference = to_rgb8(&buf);
    sim.render_load(&scene.load, 1, &mut buf)?;
    let loaded = to_rgb8(&buf);
    let frame_path = scratch.join("frame.png");
    loaded.save(&frame_path)?;

    // What the NumPy pipeline needs: reference centroids (detection is precompute for
    // both), marker positions and depths, windows, force nodes, material.
    let s = &scene.sensor;
    let r = detect(&Frame::Rgb8(reference).view(), s, &DetectConfig::default())?;
    let position = |m: &tactbench::vision::ReferenceMarker| {
        s.layers[m.layer].markers.map_or(m.position_mm, |g| {
            let k = m.id as usize;
            g.grid.node_mm(k % g.grid.nx, k / g.grid.nx)
        })
    };
    let g = &s.force_grid;
    let nodes: Vec<[f64; 2]> = (0..g.ny)
        .flat_map(|iy| (0..g.nx).map(move |ix| g.node_mm(ix, iy)))
        .collect();
    let case = json!({
        "frame": frame_path,
        "reference_px": r.markers.iter().map(|m| m.centroid_px).collect::<Vec<_>>(),
        "layer": r.markers.iter().map(|m| m.layer).collect::<Vec<_>>(),
        "position_mm": r.markers.iter().map(position).collect::<Vec<_>>(),
        "depth_mm": r.markers.iter().map(|m| s.layers[m.layer].depth_mm).collect::<Vec<_>>(),
        "layers": r.layers.iter().map(|l| json!({
            "aperture_px": l.aperture_radius_px,
            "weights": l.score_weights,
        })).collect::<Vec<_>>(),
        "force_nodes_mm": nodes,
        "mm_per_px": s.camera.mm_per_px,
        "young_n_per_mm2": s.elastomer.young_modulus_kpa * 1e-3,
        "poisson": s.elastomer.poisson_ratio,
    });
    let case_path = scratch.join("case.json");
    std::fs::write(&case_path, serde_json::to_vec(&case)?)?;

    // tactbench: the study's pinv row, timed as the study times it.
    let study = run_study(
        &scene,
        &StudyOptions {
            settings: vec![Setting::baseline()],
            reps,
            realisations: 1,
        },
        &mut |_| {},
    )?;
    let row = study
        .rows
        .first()
        .context("the pinv row was not measured")?;

    let script = root.join("tests/numpy_ref/paper_pipeline.py");
    let out = Command::new(&python)
        .arg(&script)
        .arg(&case_path)
        .args(["--reps", &reps.min(300).to_string()])
        .output()
        .with_context(|| format!("running {python} {}", script.display()))?;
    if !out.status.success() {
        bail!("{}", String::from_utf8_lossy(&out.stderr));
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let field = |key: &str| -> anyhow::Result<String> {
        text.lines()
            .find_map(|l| l.strip_prefix(key))
            .map(str::to_string)
            .with_context(|| format!("{key} missing in: {text}"))
    };
    let ours_cpu = row.total_cpu_s * 1e6;
    let ours_wall = row.total_s * 1e6;
    println!("paper pipeline (track + solve) per force frame, {reps} repetitions, medians:");
    println!(
        "  tactbench pinv row: {ours_cpu:.1} µs CPU ({ours_wall:.1} µs wall; track {:.1} + solve {:.1}), {} of {} markers, force sum [{:.4}, {:.4}, {:.4}] N",
        row.track_s * 1e6,
        row.solve_s * 1e6,
        row.markers_used.0,
        row.markers_used.1,
        row.fsum_n[0],
        row.fsum_n[1],
        row.fsum_n[2],
    );
    let markers = field("numpy_markers=")?;
    for variant in ["plain", "tuned"] {
        let cpu: f64 = field(&format!("numpy_{variant}_us_per_frame_cpu="))?.parse()?;
        let wall: f64 = field(&format!("numpy_{variant}_us_per_frame_wall="))?.parse()?;
        let track: f64 = field(&format!("numpy_{variant}_track_us_cpu="))?.parse()?;
        println!(
            "  NumPy {variant}: {cpu:.1} µs CPU ({wall:.1} µs wall; track {track:.1}), {markers} markers, force sum [{}] N; tactbench is {:.1}× faster (CPU), {:.1}× (wall)",
            field(&format!("numpy_{variant}_fsum_n="))?,
            cpu / ours_cpu,
            wall / ours_wall
        );
    }
    let _ = std::fs::remove_dir_all(&scratch);
    Ok(())
}
