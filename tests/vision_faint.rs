//! Faint and small markers (issue 29, item 6): the contrast and size floors of the
//! reference detection (`vision::detect`, `sensor init`) measured on synthesised
//! frames with ground truth — `bright` pins on a dark skin in a circular field, drawn
//! with the `sim` renderer's exact disc coverage, dimmed towards the field's edge by a
//! vignette, 8-bit with pixel noise σ = 2 levels per channel.
//!
//! A marker is found when a detection lies within 1 px of its true centre; a false
//! marker is a detection farther than 2 px from every true centre.
//!
//! `faint_marker_floors_table` (ignored) prints the whole table (`cargo test --test
//! integration faint_marker_floors_table -- --ignored --nocapture`);
//! OpenCV's SimpleBlobDetector on the same frames: `tests/opencv_ref/blobs.py` (by hand).

use image::{Rgb32FImage, RgbImage};
use tactbench::sensor::Sensor;
use tactbench::sim::render::{draw_disc, to_rgb8, PixelFilter};
use tactbench::vision::{detect, DetectConfig, FrameView};

const W: u32 = 640;
const H: u32 = 480;
const CENTRE: [f64; 2] = [320.0, 240.0];
/// Radius of the circular field the pins fill, px.
const FIELD: f64 = 200.0;
/// Background level (fraction of full scale), the black skin.
const BACKGROUND: f32 = 0.04;

/// One synthesised frame: pins of radius `radius_px` every `spacing_px` on a
/// hexagonal lattice inside the field, each `contrast` (fraction of full scale) above
/// the background at the field's centre and `contrast × edge_gain` at its edge
/// (vignette: gain `1 − (1 − edge_gain)·(ρ/FIELD)²`).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Faint {
    pub contrast: f64,
    pub radius_px: f64,
    pub spacing_px: f64,
    pub edge_gain: f64,
    pub seed: u64,
}

impl Faint {
    fn gain(&self, p: [f64; 2]) -> f64 {
        let rho = (p[0] - CENTRE[0]).hypot(p[1] - CENTRE[1]) / FIELD;
        1.0 - (1.0 - self.edge_gain) * rho * rho
    }

    /// True centres, px.
    pub(crate) fn truth(&self) -> Vec<[f64; 2]> {
        let s = self.spacing_px;
        let n = (FIELD / (s * 0.8)).ceil() as i64 + 1;
        let mut out = Vec::new();
        for j in -n..=n {
            for i in -n..=n {
                let x = (i as f64 + 0.5 * j.rem_euclid(2) as f64) * s + 0.37;
                let y = j as f64 * s * 3f64.sqrt() / 2.0 + 0.21;
                if x.hypot(y) <= FIELD - self.radius_px - 6.0 {
                    out.push([CENTRE[0] + x, CENTRE[1] + y]);
                }
            }
        }
        out
    }

    pub(crate) fn render(&self) -> RgbImage {
        let mut f = Rgb32FImage::from_pixel(W, H, image::Rgb([BACKGROUND; 3]));
        for c in self.truth() {
            let level = (self.contrast * self.gain(c)) as f32;
            draw_disc(&mut f, PixelFilter::Area, c, self.radius_px, |p, a| {
                for v in p.iter_mut().take(3) {
                    *v += a * level;
                }
            });
        }
        noisy(&to_rgb8(&f), 2.0, self.seed)
    }
}

/// Adds Gaussian noise of `sigma` levels (xorshift64* + Box–Muller), rounded, clamped.
fn noisy(img: &RgbImage, sigma: f64, seed: u64) -> RgbImage {
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut uniform = || {
        s ^= s >> 12;
        s ^= s << 25;
        s ^= s >> 27;
        ((s.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    let mut out = img.clone();
    for v in out.iter_mut() {
        let (u, w) = (uniform(), uniform());
        let g = (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * w).cos();
        *v = (*v as f64 + sigma * g).round().clamp(0.0, 255.0) as u8;
    }
    out
}

fn sensor() -> Sensor {
    let text = format!(
        "[elastomer]\nyoung_modulus_kpa = 100.0\npoisson_ratio = 0.5\nthickness_mm = 4.0\n\n\
         [[layers]]\nname = \"pins\"\ncolor = \"bright\"\ndepth_mm = 1.0\n\n\
         [force_grid]\nnx = 4\nny = 3\npitch_mm = 2.0\norigin_mm = [0.0, 0.0]\n\n\
         [camera]\nmm_per_px = 0.05\norigin_px = [0.0, 0.0]\nwidth_px = {W}\nheight_px = {H}\n"
    );
    Sensor::from_toml_str(&text, "faint.toml").unwrap()
}

/// (true markers, found within 1 px, false detections farther than 2 px from all).
pub(crate) fn score(truth: &[[f64; 2]], found: &[[f64; 2]]) -> (usize, usize, usize) {
    let near = |a: [f64; 2], set: &[[f64; 2]], d: f64| {
        set.iter().any(|b| (a[0] - b[0]).hypot(a[1] - b[1]) <= d)
    };
    let hit = truth.iter().filter(|t| near(**t, found, 1.0)).count();
    let fp = found.iter().filter(|f| !near(**f, truth, 2.0)).count();
    (truth.len(), hit, fp)
}

/// Runs the detector on one case: (true, found, false).
pub(crate) fn detect_case(case: &Faint) -> (usize, usize, usize) {
    let img = case.render();
    let found: Vec<[f64; 2]> =
        match detect(&FrameView::rgb8(&img), &sensor(), &DetectConfig::default()) {
            Ok(r) => r.markers.iter().map(|m| m.centroid_px).collect(),
            Err(_) => Vec::new(),
        };
    score(&case.truth(), &found)
}

fn case(contrast: f64, radius_px: f64, edge_gain: f64) -> Faint {
    Faint {
        contrast,
        radius_px,
        spacing_px: (4.0 * radius_px).max(12.0),
        edge_gain,
        seed: 5,
    }
}

/// Prints the floors table: found / true (false) per contrast at r = 3 px, per radius
/// at 12 % contrast, and under vignettes.
#[test]
#[ignore = "measurement: prints the table of docs/tracking.md (faint and small markers)"]
fn faint_marker_floors_table() {
    for c in [0.01, 0.015, 0.02, 0.025, 0.03, 0.04, 0.05, 0.06, 0.08, 0.12] {
        let (n, hit, fp) = detect_case(&case(c, 3.0, 1.0));
        eprintln!(
            "contrast {:5.1} %, r 3 px, no vignette: {hit}/{n} found, {fp} false",
            100.0 * c
        );
    }
    for r in [1.0, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0, 4.0] {
        for c in [0.05, 0.12] {
            let (n, hit, fp) = detect_case(&case(c, r, 1.0));
            eprintln!(
                "contrast {:5.1} %, r {r} px, no vignette: {hit}/{n} found, {fp} false",
                100.0 * c
            );
        }
    }
    for (c, g) in [(0.12, 0.42), (0.12, 0.3), (0.12, 0.2), (0.06, 0.5)] {
        for r in [2.0, 3.0] {
            let (n, hit, fp) = detect_case(&case(c, r, g));
            eprintln!(
                "contrast {:5.1} % at the centre, {:4.1} % at the edge, r {r} px: {hit}/{n} found, {fp} false",
                100.0 * c,
                100.0 * c * g
            );
        }
    }
}
