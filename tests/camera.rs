//! Camera effects (`perspective`, `refraction`, `lens_distortion`) and `tactbench
//! calibrate` (issue 14, deliverables 3 and 4).

use std::path::Path;

use tactbench::report::sha256::sha256_hex;
use tactbench::sim::{scene::Scene, simulate::Simulation};

use crate::util::root;

/// SHA-256 of every frame a scene renders (reference, then each loaded frame): the
/// exact `f32` bits of the float frames, little-endian, frame after frame.
fn scene_frames_sha256(path: &Path) -> String {
    let scene = Scene::from_path(path).unwrap();
    let mut sim = Simulation::from_scene(&scene);
    let mut frame = sim.blank_frame();
    let mut bytes: Vec<u8> = Vec::new();
    sim.render_reference(&mut frame).unwrap();
    bytes.extend(frame.as_raw().iter().flat_map(|v| v.to_bits().to_le_bytes()));
    for k in 1..=scene.frames {
        sim.render_load(&scene.frame_load(k), k as u64, &mut frame)
            .unwrap();
        bytes.extend(frame.as_raw().iter().flat_map(|v| v.to_bits().to_le_bytes()));
    }
    sha256_hex(&bytes)
}

/// The example scenes of `experiments/scenes/` (sorted by name).
fn example_scenes() -> Vec<std::path::PathBuf> {
    let mut v: Vec<_> = std::fs::read_dir(root("experiments/scenes"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    v.sort();
    v
}

/// Golden hashes recorded from `main` at c6ee1f8 (before the camera effects existed),
/// `tests/fixtures/camera/example_scene_frame_hashes.txt`: `scene-file sha256` per line.
/// With no camera effect listed every frame of every example scene must be
/// bit-identical to what that code rendered.
#[test]
fn example_scenes_render_bit_identically_to_before_the_camera_effects() {
    let golden = std::fs::read_to_string(root(
        "tests/fixtures/camera/example_scene_frame_hashes.txt",
    ))
    .unwrap();
    let mut checked = 0;
    let mut lines = Vec::new();
    for path in example_scenes() {
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        let got = scene_frames_sha256(&path);
        lines.push(format!("{name} {got}"));
        if let Some(want) = golden
            .lines()
            .filter(|l| !l.starts_with('#'))
            .find_map(|l| l.strip_prefix(&format!("{name} ")))
        {
            assert_eq!(got, want.trim(), "{name}: frames differ from main's");
            checked += 1;
        }
    }
    eprintln!("{}", lines.join("\n"));
    assert!(checked >= 10, "only {checked} scenes had a golden hash");
}
