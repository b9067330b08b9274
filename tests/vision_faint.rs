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
use tactbench::vision::{
    detect, DetectConfig, FrameView, MarkerStatus, TrackConfig, TrackMode, Tracker,
};

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

/// A one-layer sensor of appearance `color` (no marker grid: `sensor init`'s draft).
fn sensor_of(color: &str) -> Sensor {
    let text = format!(
        "[elastomer]\nyoung_modulus_kpa = 100.0\npoisson_ratio = 0.5\nthickness_mm = 4.0\n\n\
         [[layers]]\nname = \"pins\"\ncolor = \"{color}\"\ndepth_mm = 1.0\n\n\
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

/// The detected centroids of `color` markers in `img` (none when `detect` finds none).
fn found_in(img: &RgbImage, color: &str) -> Vec<[f64; 2]> {
    match detect(
        &FrameView::rgb8(img),
        &sensor_of(color),
        &DetectConfig::default(),
    ) {
        Ok(r) => r.markers.iter().map(|m| m.centroid_px).collect(),
        Err(_) => Vec::new(),
    }
}

/// Runs the detector on one case: (true, found, false).
pub(crate) fn detect_case(case: &Faint) -> (usize, usize, usize) {
    score(&case.truth(), &found_in(&case.render(), "bright"))
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
    for shrink in [0.5, 0.56, 0.58, 0.6, 0.62, 0.65, 0.7] {
        let (n, hit, fp, bad) = gelslim_found_and_tracked(shrink);
        eprintln!(
            "GelSlim-like dark dots, radius 5 px at the top, {:.2} px at the bottom: {hit}/{n} found, {fp} false, {} tracked not ok against itself (both modes)",
            5.0 * (1.0 - shrink),
            bad.len()
        );
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

/// The low-contrast pin frame at its worst: pins at 12 % of full scale at the
/// field's centre, 2.4 % at its edge (the first pass's threshold, a fifth of the
/// brightest pins' contrast, dropped ~8 % of them).
#[test]
fn faint_pins_under_a_vignette_are_all_found() {
    for radius_px in [2.0, 3.0] {
        let (n, hit, fp) = detect_case(&case(0.12, radius_px, 0.2));
        assert!(
            100 * hit >= 99 * n && fp == 0,
            "r {radius_px} px: {hit}/{n} found, {fp} false"
        );
    }
}

/// A frame of pixel noise alone, and one with a smooth illumination gradient under
/// the noise, hold no marker of either brightness appearance; nor does the noise
/// around a patch of real pins add any (the second pass judges every local maximum
/// of the noise there).
#[test]
fn a_noise_only_frame_finds_no_markers() {
    let flat = Rgb32FImage::from_pixel(W, H, image::Rgb([0.3; 3]));
    let mut ramp = flat.clone();
    for (x, y, p) in ramp.enumerate_pixels_mut() {
        let g = 0.15 + 0.5 * x as f32 / W as f32 + 0.2 * (y as f32 / H as f32).powi(2);
        *p = image::Rgb([g, 0.9 * g, 0.8 * g]);
    }
    for (name, frame) in [("flat", &flat), ("gradient", &ramp)] {
        for seed in [1, 2, 3] {
            let img = noisy(&to_rgb8(frame), 2.0, seed);
            for color in ["bright", "dark"] {
                let found = found_in(&img, color);
                assert!(found.is_empty(), "{name} {color} seed {seed}: {found:?}");
            }
        }
    }
    // Pins only inside a 60 px disc; noise over the rest of the frame.
    let pins = Faint {
        contrast: 0.12,
        radius_px: 3.0,
        spacing_px: 12.0,
        edge_gain: 1.0,
        seed: 9,
    };
    let truth: Vec<[f64; 2]> = pins
        .truth()
        .into_iter()
        .filter(|p| (p[0] - CENTRE[0]).hypot(p[1] - CENTRE[1]) < 60.0)
        .collect();
    let mut f = Rgb32FImage::from_pixel(W, H, image::Rgb([BACKGROUND; 3]));
    for &c in &truth {
        draw_disc(&mut f, PixelFilter::Area, c, 3.0, |p, a| {
            p.iter_mut().take(3).for_each(|v| *v += 0.12 * a)
        });
    }
    let (n, hit, fp) = score(&truth, &found_in(&noisy(&to_rgb8(&f), 2.0, 9), "bright"));
    assert_eq!(
        (hit, fp),
        (n, 0),
        "pins on noise: {hit}/{n} found, {fp} false"
    );
}

/// A GelSlim-like frame: dark dots under green light seen in strong perspective, so
/// the dots and their spacing shrink towards the bottom rows by `shrink` (radius 5 px
/// and pitch 25 px at the top, `5 (1 − shrink)` px and `25 (1 − shrink)` px at the
/// bottom), the light falling off towards the right. True centres and the frame.
fn gelslim_frame_of(shrink: f64) -> (Vec<[f64; 2]>, RgbImage) {
    let (top, bottom) = (24.0, 456.0);
    let scale = |y: f64| 1.0 - shrink * (y - top) / (bottom - top);
    let mut truth = Vec::new();
    let mut y = top;
    let mut row = 0;
    while y <= bottom {
        let s = scale(y);
        let pitch = 25.0 * s;
        let shift = 0.31 * row as f64;
        let n = (290.0 / pitch).floor() as i64;
        for i in -n..=n {
            truth.push([320.0 + i as f64 * pitch + shift, y + 0.17]);
        }
        y += 25.0 * s;
        row += 1;
    }
    let light = |x: f64, y: f64| 1.0 - 0.35 * x / W as f64 - 0.1 * y / H as f64;
    let (gel, dot) = ([0.12f32, 0.78, 0.24], [0.03f32, 0.10, 0.04]);
    let mut f = Rgb32FImage::from_fn(W, H, |x, y| {
        let l = light(x as f64, y as f64) as f32;
        image::Rgb([gel[0] * l, gel[1] * l, gel[2] * l])
    });
    for &c in &truth {
        let r = 5.0 * scale(c[1]);
        let l = light(c[0], c[1]) as f32;
        draw_disc(&mut f, PixelFilter::Area, c, r, |p, a| {
            for (v, (g, d)) in p.iter_mut().zip(gel.iter().zip(dot)) {
                *v -= a * (g - d) * l;
            }
        });
    }
    (truth, noisy(&to_rgb8(&f), 2.0, 11))
}

/// The GelSlim-like frame of `shrink` (`gelslim_frame_of`) detected as a `dark` layer
/// and tracked against itself in both modes: (true dots, found, false detections, the
/// markers not `ok` per mode with their centroid and status).
fn gelslim_found_and_tracked(shrink: f64) -> (usize, usize, usize, Vec<String>) {
    let (truth, img) = gelslim_frame_of(shrink);
    let sensor = sensor_of("dark");
    let view = FrameView::rgb8(&img);
    let reference = detect(&view, &sensor, &DetectConfig::default()).unwrap();
    let found: Vec<[f64; 2]> = reference.markers.iter().map(|m| m.centroid_px).collect();
    let (n, hit, fp) = score(&truth, &found);
    let mut bad = Vec::new();
    for mode in [TrackMode::FrameToFrame, TrackMode::PerWindow] {
        let mut tracker = Tracker::new(
            reference.clone(),
            TrackConfig {
                mode,
                ..Default::default()
            },
        );
        let tracks = tracker.track(&view).unwrap();
        bad.extend(
            tracks
                .iter()
                .zip(&reference.markers)
                .filter(|(t, _)| t.status != MarkerStatus::Ok)
                .map(|(t, m)| format!("{mode:?} {:?} {:?}", m.centroid_px, t.status)),
        );
    }
    (n, hit, fp, bad)
}

/// A GelSlim-like frame in a 2 : 1 perspective (radius 5 px at the top, 2.5 px at
/// the bottom): every dot is found, nothing else (the second pass adds no false dot
/// on a dark layer under coloured light), and every one tracks `ok` against itself in
/// both modes.
#[test]
fn gelslim_like_dots_in_perspective_are_all_found_and_track_ok() {
    let (n, hit, fp, bad) = gelslim_found_and_tracked(0.5);
    assert_eq!((hit, fp), (n, 0), "{hit}/{n} found, {fp} false");
    assert!(bad.is_empty(), "{} not ok: {bad:?}", bad.len());
}

/// Issue 29 item 6: the same frame in a stronger perspective, radius 5 px at the top
/// and 2.1 px at the bottom (0.42 of the top's). Judged against the layer's median
/// radius, the far rows' dots (below 0.63 of it) were dropped: 901 of 956 found. Each
/// blob is now judged against its neighbours' size (`detect::keep_markers`): at least
/// 99 % found, no false detection, and every one tracks `ok` against itself.
#[test]
fn gelslim_like_dots_in_stronger_perspective_are_all_found() {
    let (n, hit, fp, bad) = gelslim_found_and_tracked(0.58);
    assert!(
        100 * hit >= 99 * n && fp == 0,
        "{hit}/{n} found, {fp} false"
    );
    assert!(bad.is_empty(), "{} not ok: {bad:?}", bad.len());
}

/// OpenCV's SimpleBlobDetector (`tests/opencv_ref/blobs.py`) on the same rendered
/// frames as ours, scored alike: `TACTBENCH_PYTHON=/path/to/python-with-opencv cargo
/// test --test integration vision_faint::opencv_blob_detector_on_faint_frames --
/// --ignored --nocapture`. The frames are written to the system's temporary directory.
#[test]
#[ignore = "needs Python with OpenCV (TACTBENCH_PYTHON); prints both detectors' counts"]
fn opencv_blob_detector_on_faint_frames() {
    let Ok(python) = std::env::var("TACTBENCH_PYTHON") else {
        println!("TACTBENCH_PYTHON is not set: skipped (set it to a python with opencv)");
        return;
    };
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/opencv_ref/blobs.py");
    let dir = std::env::temp_dir().join(format!("tactbench_faint_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let opencv = |img: &RgbImage, name: &str, color: &str| -> Vec<[f64; 2]> {
        let path = dir.join(name);
        img.save(&path).unwrap();
        let out = std::process::Command::new(&python)
            .arg(&script)
            .arg(&path)
            .arg(color)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout)
            .lines()
            .filter_map(|l| {
                let (x, y) = l.split_once(',')?;
                Some([x.trim().parse().ok()?, y.trim().parse().ok()?])
            })
            .collect()
    };
    let cases = [
        ("4 % r 3", case(0.04, 3.0, 1.0)),
        ("5 % r 1", case(0.05, 1.0, 1.0)),
        ("12 % -> 2.4 % r 2", case(0.12, 2.0, 0.2)),
        ("12 % -> 2.4 % r 3", case(0.12, 3.0, 0.2)),
        ("6 % -> 3 % r 3", case(0.06, 3.0, 0.5)),
    ];
    for (k, (name, c)) in cases.iter().enumerate() {
        let img = c.render();
        let (n, ours, our_fp) = score(&c.truth(), &found_in(&img, "bright"));
        let (_, cv, cv_fp) = score(
            &c.truth(),
            &opencv(&img, &format!("pins_{k}.png"), "bright"),
        );
        println!("{name}: ours {ours}/{n} ({our_fp} false), OpenCV {cv}/{n} ({cv_fp} false)");
    }
    for shrink in [0.5, 0.58, 0.6, 0.65] {
        let (truth, img) = gelslim_frame_of(shrink);
        let (n, ours, our_fp) = score(&truth, &found_in(&img, "dark"));
        let (_, cv, cv_fp) = score(
            &truth,
            &opencv(&img, &format!("gelslim_{shrink}.png"), "dark"),
        );
        println!("GelSlim-like, shrink {shrink}: ours {ours}/{n} ({our_fp} false), OpenCV {cv}/{n} ({cv_fp} false)");
    }
    std::fs::remove_dir_all(&dir).ok();
}
