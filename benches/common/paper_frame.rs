//! The paper frame the vision bench and `examples/vision_profile.rs` both track, so
//! the criterion medians and the callgrind counts measure the same input. Included
//! with `#[path]` (benches and examples cannot import each other).

use image::RgbImage;
use tactbench::sensor::paper_sensor;
use tactbench::sim::render::{reference_markers, render_sensor, to_rgb8};

/// The paper sensor's markers shifted by `shift_px` in x, rendered at 8 bits with
/// Gaussian noise of σ = 2 levels (deterministic xorshift + Box–Muller).
pub fn frame(shift_px: f64, seed: u64) -> RgbImage {
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
