//! Global matching and appearance checks of the tracker (`tactbench::vision::Tracker`)
//! on frames drawn by the `sim` renderer (exact-coverage discs) with pixel noise added
//! here: layouts without a grid in the sensor file (hexagonal, perspective-distorted,
//! several hundred markers) tracked per window from the reference alone, markers that
//! vanish or change appearance, and the paper sensor with a dark patch (issue 24,
//! case 5).

use image::RgbImage;
use tactbench::sensor::{paper_sensor, Sensor};
use tactbench::sim::render::{draw_disc, render_sensor, to_rgb8, PixelFilter, Renderer};
use tactbench::vision::{
    detect, DetectConfig, FrameView, MarkerStatus, MarkerTrack, Reference, StatusCounts,
    TrackConfig, TrackMode, Tracker,
};

/// Small deterministic Gaussian generator (xorshift64* + Box–Muller).
struct Noise(u64);

impl Noise {
    fn new(seed: u64) -> Noise {
        Noise(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }
    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        ((self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn gauss(&mut self) -> f64 {
        let (u, v) = (self.uniform(), self.uniform());
        (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
    }
}

/// Adds Gaussian noise of `sigma` levels to an 8-bit image (rounded, clamped).
fn noisy(img: &RgbImage, sigma: f64, seed: u64) -> RgbImage {
    let mut n = Noise::new(seed);
    let mut out = img.clone();
    for v in out.iter_mut() {
        *v = (*v as f64 + sigma * n.gauss()).round().clamp(0.0, 255.0) as u8;
    }
    out
}

// ---- a layout without a grid ------------------------------------------------------

const W: u32 = 640;
const H: u32 = 480;
const CENTRE: [f64; 2] = [320.0, 240.0];
/// Spacing of the undistorted hexagonal lattice, px.
const S0: f64 = 18.0;
/// Radius of the circular field the markers fill, px.
const FIELD: f64 = 200.0;

/// A one-layer sensor (the paper's blue layer) without `[layers.markers]`, seen by a
/// 640×480 camera: the layout is whatever the reference frame shows.
fn free_sensor() -> Sensor {
    let mut s = paper_sensor();
    s.layers.truncate(1);
    s.layers[0].markers = None;
    s.camera.width_px = W;
    s.camera.height_px = H;
    s
}

/// Local scale of the perspective: the lattice is 12 % finer at the top of the field
/// and 12 % coarser at the bottom (a camera looking at the skin obliquely).
fn scale_at(y: f64) -> f64 {
    1.0 + 0.12 * (y - CENTRE[1]) / FIELD
}

/// Centres (px) of a hexagonal lattice of spacing `S0`, perspective-distorted by
/// `scale_at`, inside the circular field: ~310 markers, local spacing 16–20 px.
fn hex_layout() -> Vec<[f64; 2]> {
    let mut out = Vec::new();
    let rows = (FIELD / (S0 * 0.75)).ceil() as i64 + 2;
    for j in -rows..=rows {
        for i in -rows..=rows {
            let x = (i as f64 + 0.5 * (j.rem_euclid(2)) as f64) * S0;
            let y = j as f64 * S0 * 3f64.sqrt() / 2.0;
            if x.hypot(y) > FIELD * 0.85 {
                continue;
            }
            // Perspective: distances from the centre scale with the local scale.
            let k = scale_at(CENTRE[1] + y);
            out.push([CENTRE[0] + x * k, CENTRE[1] + y * k]);
        }
    }
    out
}

/// Marker radius at `p`: a quarter of the local spacing (the pins shrink with the
/// lattice), about a TacTip's.
fn radius_at(p: [f64; 2]) -> f64 {
    0.25 * S0 * scale_at(p[1])
}

/// Renders markers at `centres` (px) with the `sim` renderer's disc coverage and
/// palette, 8-bit, noise σ = 2.
fn render_free(sensor: &Sensor, centres: &[[f64; 2]], radii: &[f64], seed: u64) -> RgbImage {
    render_alpha(sensor, centres, radii, &vec![1.0; centres.len()], seed)
}

/// As [`render_free`], each marker drawn with opacity `alpha` (1 = the palette's
/// colour, less = a fainter marker).
fn render_alpha(
    sensor: &Sensor,
    centres: &[[f64; 2]],
    radii: &[f64],
    alpha: &[f32],
    seed: u64,
) -> RgbImage {
    let renderer = Renderer::new(sensor);
    let color = renderer.layer_color(0);
    let mut f = renderer.blank();
    for ((&c, &r), &k) in centres.iter().zip(radii).zip(alpha) {
        draw_disc(&mut f, PixelFilter::Area, c, r, |p, a| {
            for ch in 0..3 {
                p[ch] += k * a * (color[ch] - p[ch]);
            }
        });
    }
    noisy(&to_rgb8(&f), 2.0, seed)
}

fn reference_of(img: &RgbImage, sensor: &Sensor) -> Reference {
    detect(&FrameView::rgb8(img), sensor, &DetectConfig::default()).expect("markers detected")
}

/// The true layout index of each reference marker (nearest true centre, < 1 px).
fn truth_index(reference: &Reference, truth: &[[f64; 2]]) -> Vec<usize> {
    reference
        .markers
        .iter()
        .map(|m| {
            let (k, d) = truth
                .iter()
                .enumerate()
                .map(|(k, t)| (k, (t[0] - m.centroid_px[0]).hypot(t[1] - m.centroid_px[1])))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap();
            assert!(
                d < 0.05,
                "reference marker {} at {:?} is {d} px from any true centre",
                m.id,
                m.centroid_px
            );
            k
        })
        .collect()
}

/// Distance to the nearest other marker of `layout`, px.
fn local_spacing(layout: &[[f64; 2]], k: usize) -> f64 {
    layout
        .iter()
        .enumerate()
        .filter(|(j, _)| *j != k)
        .map(|(_, p)| (p[0] - layout[k][0]).hypot(p[1] - layout[k][1]))
        .fold(f64::INFINITY, f64::min)
}

fn per_window() -> TrackConfig {
    TrackConfig {
        mode: TrackMode::PerWindow,
        ..TrackConfig::default()
    }
}

/// A smooth displacement field of `fraction` local spacings everywhere: a rotation of
/// its direction across the field (so no two regions move alike) on top of a shift.
fn field(layout: &[[f64; 2]], fraction: f64, angle0: f64) -> Vec<[f64; 2]> {
    (0..layout.len())
        .map(|k| {
            let p = layout[k];
            let s = local_spacing(layout, k);
            let a = angle0 + 0.8 * (p[0] - CENTRE[0]) / FIELD;
            [fraction * s * a.cos(), fraction * s * a.sin()]
        })
        .collect()
}

#[test]
fn hexagonal_perspective_layout_without_grid_is_found_whole() {
    let s = free_sensor();
    let layout = hex_layout();
    assert!(layout.len() > 300, "{} markers", layout.len());
    let radii: Vec<f64> = layout.iter().map(|&p| radius_at(p)).collect();
    let r = reference_of(&render_free(&s, &layout, &radii, 1), &s);
    assert_eq!(r.markers.len(), layout.len(), "every drawn marker found");
    assert!(r.missing.is_empty() && r.unmatched.is_empty());
    truth_index(&r, &layout);
}

/// Issue 19 part 3: displacements up to about half the local marker spacing (0.4
/// here: every marker ok; at 0.45 a marker in a few hundred may be lost) are
/// tracked from the reference alone (no frame sequence), on a layout that is not a
/// grid and whose spacing varies by 1.27× across the image.
#[test]
fn hexagonal_layout_tracked_per_window_up_to_0_4_local_spacing() {
    let s = free_sensor();
    let layout = hex_layout();
    let radii: Vec<f64> = layout.iter().map(|&p| radius_at(p)).collect();
    let r = reference_of(&render_free(&s, &layout, &radii, 1), &s);
    let index = truth_index(&r, &layout);
    for (case, (fraction, angle0)) in [(0.3, 0.0), (0.4, 0.5), (0.4, 2.0), (0.4, -2.5)]
        .into_iter()
        .enumerate()
    {
        let u = field(&layout, fraction, angle0);
        let moved: Vec<[f64; 2]> = layout
            .iter()
            .zip(&u)
            .map(|(p, d)| [p[0] + d[0], p[1] + d[1]])
            .collect();
        let img = render_free(&s, &moved, &radii, 10 + case as u64);
        let mut t = Tracker::new(r.clone(), per_window());
        let tracks = t.track(&FrameView::rgb8(&img)).unwrap();
        let counts = StatusCounts::of(tracks, 0);
        assert_eq!(counts.ok, layout.len(), "case {case}: {counts:?}");
        let mut worst = 0.0f64;
        for (tr, &k) in tracks.iter().zip(&index) {
            let e = (tr.displacement_px[0] - u[k][0]).hypot(tr.displacement_px[1] - u[k][1]);
            worst = worst.max(e);
        }
        eprintln!("case {case} ({fraction} spacing): worst error {worst:.4} px");
        assert!(worst < 0.1, "case {case}: worst error {worst} px");
    }
}

/// A marker missing from the frame while its neighbours moved 0.4 local spacings
/// towards its place: it is not ok, and no marker is reported at a neighbour's
/// position.
#[test]
fn vanished_marker_is_lost_not_matched_to_its_neighbour() {
    let s = free_sensor();
    let layout = hex_layout();
    let radii: Vec<f64> = layout.iter().map(|&p| radius_at(p)).collect();
    let r = reference_of(&render_free(&s, &layout, &radii, 1), &s);
    let index = truth_index(&r, &layout);
    // Every marker within 100 px of the centre, one at a time, would be slow: take a
    // dozen spread over the field, each in its own frame.
    let victims: Vec<usize> = (0..layout.len()).step_by(layout.len() / 12).collect();
    for (n, &victim) in victims.iter().enumerate() {
        let u = field(&layout, 0.4, 0.7 * n as f64);
        let (mut moved, mut rad) = (Vec::new(), Vec::new());
        for k in 0..layout.len() {
            if k != victim {
                moved.push([layout[k][0] + u[k][0], layout[k][1] + u[k][1]]);
                rad.push(radii[k]);
            }
        }
        let img = render_free(&s, &moved, &rad, 100 + n as u64);
        let mut t = Tracker::new(r.clone(), per_window());
        let tracks = t.track(&FrameView::rgb8(&img)).unwrap();
        for (tr, &k) in tracks.iter().zip(&index) {
            if k == victim {
                assert_ne!(tr.status, MarkerStatus::Ok, "victim {victim}: {tr:?}");
                continue;
            }
            if tr.status == MarkerStatus::Ok {
                let e = (tr.displacement_px[0] - u[k][0]).hypot(tr.displacement_px[1] - u[k][1]);
                assert!(e < 0.1, "victim {victim}: marker {k} off by {e} px");
            }
        }
        // Known limitation (docs/tracking.md): in one of these eight field directions
        // (victim 182's frame) the per-window start chain goes wrong and 106 of 313
        // markers are lost; lost, never reported at another marker's position
        // (checked above). The other frames keep at least 305 of 313 ok.
        let c = StatusCounts::of(tracks, 0);
        eprintln!("victim {victim}: {c:?}");
        assert!(c.ok >= 200, "victim {victim}: {c:?}");
    }
}

// ---- appearance changes (issue 24, case 5) ------------------------------------------

/// The paper sensor's unloaded frame (the `sim` renderer, 8-bit, noise σ = 2), with
/// every pixel whose centre lies in `patch` = `[x0, y0, x1, y1]` set to black.
fn paper_frame(patch: Option<[f64; 4]>, seed: u64) -> RgbImage {
    let s = paper_sensor();
    let mut img = to_rgb8(&render_sensor(&s, None).expect("render"));
    if let Some([x0, y0, x1, y1]) = patch {
        for (x, y, p) in img.enumerate_pixels_mut() {
            let (x, y) = (x as f64, y as f64);
            if x >= x0 && x < x1 && y >= y0 && y < y1 {
                p.0 = [2, 2, 3];
            }
        }
    }
    noisy(&img, 2.0, seed)
}

/// Fraction of the disc of centre `c`, radius `r` inside the rectangle (supersampled).
fn covered_fraction(c: [f64; 2], r: f64, rect: [f64; 4]) -> f64 {
    let n = 64;
    let (mut inside, mut total) = (0usize, 0usize);
    for a in 0..n {
        for b in 0..n {
            let x = c[0] - r + 2.0 * r * (a as f64 + 0.5) / n as f64;
            let y = c[1] - r + 2.0 * r * (b as f64 + 0.5) / n as f64;
            if (x - c[0]).hypot(y - c[1]) > r {
                continue;
            }
            total += 1;
            // Pixels are covered by their centre: the patch acts on [x0 − ½, x1 − ½).
            if x >= rect[0] - 0.5 && x < rect[2] - 0.5 && y >= rect[1] - 0.5 && y < rect[3] - 0.5 {
                inside += 1;
            }
        }
    }
    inside as f64 / total as f64
}

/// Issue 24, case 5: an unloaded frame of the paper sensor with a dark patch (dust,
/// a cable's shadow). Before the fix: `236 ok, 24 lost, 0 merged, 0 outlier`, and 15
/// `ok` markers on the patch's edge carried 0.4–2.3 px of false displacement. Now every
/// marker the patch reaches is lost or flagged `outlier`; every `ok` marker's
/// displacement is noise (the true one is zero).
#[test]
fn half_covered_marker_is_flagged_not_ok() {
    let s = paper_sensor();
    let patch = [101.3, 77.6, 198.4, 171.2];
    let r = reference_of(&paper_frame(None, 1), &s);
    assert_eq!(r.markers.len(), 260);
    let img = paper_frame(Some(patch), 2);
    let radius = 0.5 * s.layers[0].markers.unwrap().diameter_mm / s.camera.mm_per_px;
    for mode in [TrackMode::PerWindow, TrackMode::FrameToFrame] {
        let mut t = Tracker::new(
            r.clone(),
            TrackConfig {
                mode,
                ..TrackConfig::default()
            },
        );
        let tracks: Vec<MarkerTrack> = t.track(&FrameView::rgb8(&img)).unwrap().to_vec();
        let c = StatusCounts::of(&tracks, 0);
        eprintln!("{mode:?}: {c:?}");
        let (mut touched, mut flagged) = (0, 0);
        for (m, tr) in r.markers.iter().zip(&tracks) {
            let f = covered_fraction(m.centroid_px, radius, patch);
            let u = tr.displacement_px[0].hypot(tr.displacement_px[1]);
            if tr.status == MarkerStatus::Ok {
                assert!(
                    u < 0.1,
                    "{mode:?}: ok marker {} (layer {}) {:.1} % covered moved {u:.3} px",
                    m.id,
                    m.layer,
                    100.0 * f
                );
            }
            if f > 0.0 && f < 1.0 {
                touched += 1;
                flagged += (tr.status != MarkerStatus::Ok) as usize;
            }
            if f > 0.02 {
                assert_ne!(
                    tr.status,
                    MarkerStatus::Ok,
                    "{mode:?}: marker {} (layer {}) {:.1} % covered is ok ({u:.3} px)",
                    m.id,
                    m.layer,
                    100.0 * f
                );
            }
        }
        eprintln!("{mode:?}: {flagged} of {touched} partly covered markers not ok");
        assert!(c.outlier > 0, "{mode:?}: {c:?}");
        assert_eq!(c.ok + c.lost + c.merged + c.outlier, 260);
    }
}

/// Appearance changes away from any patch: a marker drawn at 55 % opacity, or 1.2×
/// as large, in an otherwise unchanged frame is an outlier; the others stay ok.
#[test]
fn marker_of_another_size_or_contrast_is_an_outlier() {
    let s = free_sensor();
    let layout = hex_layout();
    let radii: Vec<f64> = layout.iter().map(|&p| radius_at(p)).collect();
    let r = reference_of(&render_free(&s, &layout, &radii, 1), &s);
    let index = truth_index(&r, &layout);
    let (big, faint) = (layout.len() / 3, 2 * layout.len() / 3);
    let mut rad = radii.clone();
    rad[big] *= 1.2;
    let mut alpha = vec![1.0f32; layout.len()];
    alpha[faint] = 0.55;
    let img = render_alpha(&s, &layout, &rad, &alpha, 2);
    let mut t = Tracker::new(r.clone(), per_window());
    let tracks = t.track(&FrameView::rgb8(&img)).unwrap();
    for (tr, &k) in tracks.iter().zip(&index) {
        let want = if k == big || k == faint {
            MarkerStatus::Outlier
        } else {
            MarkerStatus::Ok
        };
        assert_eq!(tr.status, want, "marker {k}: {tr:?}");
    }
}

/// The check can be turned off: the same half-covered frame then tracks the edge
/// markers `ok` again (the behaviour before issue 24).
#[test]
fn appearance_check_off_reports_edge_markers_ok() {
    let s = paper_sensor();
    let patch = [101.3, 77.6, 198.4, 171.2];
    let r = reference_of(&paper_frame(None, 1), &s);
    let img = paper_frame(Some(patch), 2);
    let mut t = Tracker::new(
        r,
        TrackConfig {
            mode: TrackMode::PerWindow,
            appearance_tolerance: f64::INFINITY,
            ..TrackConfig::default()
        },
    );
    let c = StatusCounts::of(t.track(&FrameView::rgb8(&img)).unwrap(), 0);
    eprintln!("check off: {c:?}");
    assert_eq!(c.outlier, 0, "{c:?}");
}

// ---- Table I for the dark and bright appearances ------------------------------------

/// A one-layer sensor of the paper's geometry (13 × 10 markers of 0.6 mm every
/// 1.5 mm, 0.05 mm/px, 430 × 340 px) whose markers have the appearance `color`.
fn table_i_sensor(color: &str) -> Sensor {
    let text = format!(
        "[elastomer]\nyoung_modulus_kpa = 1000.0\npoisson_ratio = 0.5\nthickness_mm = 40.0\n\n\
         [[layers]]\nname = \"markers\"\ncolor = \"{color}\"\ndepth_mm = 3.0\n\
         [layers.markers]\nnx = 13\nny = 10\npitch_mm = 1.5\norigin_mm = [0.0, 0.0]\ndiameter_mm = 0.6\n\n\
         [force_grid]\nnx = 10\nny = 8\npitch_mm = 2.2\norigin_mm = [-0.9, -0.95]\n\n\
         [camera]\nmm_per_px = 0.05\norigin_px = [25.0, 25.0]\nwidth_px = 430\nheight_px = 340\n"
    );
    Sensor::from_toml_str(&text, "table1.toml").unwrap()
}

/// The illumination gradient of the `dark` cases: gain 0.775 … 1.225 across the
/// image (the lit gel from 0.64 to 1.0 of full scale, as on a GelSight).
const GRADIENT: &str = "[[effects]]\nkind = \"illumination\"\ngradient = [0.3, 0.15]\n";
/// A broad glare over the image centre: it saturates the lit gel around four
/// `dark` markers and lifts four `bright` markers and their background by up to 0.3.
const GLARE: &str =
    "[[effects]]\nkind = \"glare\"\ncenter_px = [215.0, 170.0]\nsigma_px = 25.0\namplitude = 0.3\n";

/// Paper Table I with the `sim` renderer: reference and a frame shifted by 3 px
/// along x (the scene's `shift` effect), no load, 8-bit with pixel noise σ = 2 levels
/// drawn independently in both (as `experiments/scenes/table1_shift.toml`), plus the
/// image effects `extra`; tracked per window. Returns the status counts and (mean x,
/// SD x, SD y, largest error, px) over the ok markers.
fn table_i_track(color: &str, extra: &str) -> (StatusCounts, (f64, f64, f64, f64)) {
    use tactbench::sim::{scene::Scene, simulate::Simulation};
    let s = table_i_sensor(color);
    let text = format!(
        "sensor = \"table1.toml\"\n[indenter]\nkind = \"point\"\n[load]\nposition_mm = [9.0, 6.75]\nnormal_force_n = 0.0\n\
         [[effects]]\nkind = \"shift\"\nshift_px = [3.0, 0.0]\n{extra}\
         [[effects]]\nkind = \"pixel_noise\"\nsigma_8bit = 2.0\nseed = 1\n[[effects]]\nkind = \"quantize8\"\n"
    );
    let scene = Scene::from_toml_str(&text, "table1_scene.toml", s.clone()).unwrap();
    let mut sim = Simulation::from_scene(&scene);
    let mut f = sim.blank_frame();
    sim.render_reference(&mut f).unwrap();
    let reference = to_rgb8(&f);
    sim.render_load(&scene.frame_load(1), 1, &mut f).unwrap();
    let shifted = to_rgb8(&f);
    let r = reference_of(&reference, &s);
    assert_eq!((r.markers.len(), r.missing.len()), (130, 0));
    let mut t = Tracker::new(r, per_window());
    let tracks = t.track(&FrameView::rgb8(&shifted)).unwrap();
    let c = StatusCounts::of(tracks, 0);
    let (ux, uy): (Vec<f64>, Vec<f64>) = tracks
        .iter()
        .filter(|t| t.status == MarkerStatus::Ok)
        .map(|t| (t.displacement_px[0], t.displacement_px[1]))
        .unzip();
    let n = ux.len() as f64;
    let mean = |v: &[f64]| v.iter().sum::<f64>() / n;
    let sd =
        |v: &[f64], m: f64| (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    let (mx, my) = (mean(&ux), mean(&uy));
    let worst = ux
        .iter()
        .zip(&uy)
        .map(|(x, y)| (x - 3.0).hypot(*y))
        .fold(0.0, f64::max);
    let figures = (mx, sd(&ux, mx), sd(&uy, my), worst);
    eprintln!(
        "Table I, {color} {}: {c:?}; x {:.4} ± {:.4} px, y SD {:.4} px, largest error {:.3} px",
        extra.replace('\n', " "),
        figures.0,
        figures.1,
        figures.2,
        figures.3
    );
    (c, figures)
}

/// As [`table_i_track`], checking that every marker is found and ok.
fn table_i_figures(color: &str, extra: &str) -> (f64, f64, f64, f64) {
    let (c, figures) = table_i_track(color, extra);
    assert_eq!(c.ok, 130, "{color} {extra}: {c:?}");
    figures
}

/// `dark` markers on a lit gel with an illumination gradient. Measured: x 3.0001 ±
/// 0.0054 px, y SD 0.0056 px, largest error 0.026 px (paper sensor on the same
/// renderer: 2.9991 ± 0.0132 px; the paper: 2.98 ± 0.06 / 3.00 ± 0.09 px).
#[test]
fn table_i_dark_markers_under_an_illumination_gradient() {
    let (mx, sx, sy, worst) = table_i_figures("dark", GRADIENT);
    assert!((mx - 3.0).abs() <= 0.002, "mean {mx}");
    assert!(sx <= 0.007 && sy <= 0.007, "SD {sx} / {sy}");
    assert!(worst <= 0.035, "largest error {worst}");
}

/// The same with a broad glare saturating the gel around the central markers.
/// Measured: x 3.0001 ± 0.0056 px, y SD 0.0058 px, largest error 0.026 px: the glare
/// is static while the markers move, but over a window it is nearly flat or
/// clipped flat, and the ring plane removes its slope.
#[test]
fn table_i_dark_markers_under_a_gradient_and_glare() {
    let (mx, sx, sy, worst) = table_i_figures("dark", &format!("{GRADIENT}{GLARE}"));
    assert!((mx - 3.0).abs() <= 0.002, "mean {mx}");
    assert!(sx <= 0.007 && sy <= 0.007, "SD {sx} / {sy}");
    assert!(worst <= 0.035, "largest error {worst}");
}

/// `bright` markers on the dark background. Measured: x 2.9998 ± 0.0047 px, y SD
/// 0.0049 px, largest error 0.022 px.
#[test]
fn table_i_bright_markers() {
    let (mx, sx, sy, worst) = table_i_figures("bright", "");
    assert!((mx - 3.0).abs() <= 0.002, "mean {mx}");
    assert!(sx <= 0.006 && sy <= 0.006, "SD {sx} / {sy}");
    assert!(worst <= 0.03, "largest error {worst}");
}

/// `bright` markers under the broad glare. Measured: x 3.0000 ± 0.0048 px, y SD
/// 0.0049 px, largest error 0.022 px.
#[test]
fn table_i_bright_markers_under_glare() {
    let (mx, sx, sy, worst) = table_i_figures("bright", GLARE);
    assert!((mx - 3.0).abs() <= 0.002, "mean {mx}");
    assert!(sx <= 0.006 && sy <= 0.006, "SD {sx} / {sy}");
    assert!(worst <= 0.03, "largest error {worst}");
}

/// A small saturating specular highlight (σ 2.5 px, full scale) 2 px right of the
/// centre of the `dark` marker at (205, 175) px, static while the sensor shifts by
/// 3 px: it hides a different part of the marker in each frame. Measured before the
/// highlight check: that marker off by 2.15 px and reported ok (its signal changed
/// little; 2.15 px is below the neighbour check's 3 px), the layer's SD 0.19 px.
/// Now it is an `outlier` (a saturated pixel on its disc) and the other 129 markers
/// keep the figures of the plain case.
#[test]
fn table_i_dark_marker_under_a_specular_highlight_is_an_outlier() {
    let spot = "[[effects]]\nkind = \"glare\"\ncenter_px = [207.0, 175.0]\nsigma_px = 2.5\namplitude = 1.0\n";
    let (c, (mx, sx, sy, worst)) = table_i_track("dark", &format!("{GRADIENT}{spot}"));
    assert_eq!((c.ok, c.outlier, c.lost, c.merged), (129, 1, 0, 0), "{c:?}");
    assert!((mx - 3.0).abs() <= 0.002, "mean {mx}");
    assert!(sx <= 0.007 && sy <= 0.007, "SD {sx} / {sy}");
    assert!(worst <= 0.035, "largest error {worst}");
}

/// The same highlight on a `bright` marker. Before the check for bright markers it
/// was measured 0.42 px off and reported ok (the layer's SD 0.037 px): bright pins may
/// saturate by themselves, so the `dark` rule (any saturated pixel on the dot) does
/// not apply. Now a bright marker whose saturated pixels changed against its own
/// reference's (here 73 → 82 pixels, their mean offset from the centroid moved by
/// 1.3 px: the spot stays with the light) while none of its neighbours shows
/// saturation is an `outlier`, and the other 129 keep the plain case's figures. The
/// broad glare of `table_i_bright_markers_under_glare` changes the saturated pixels
/// of three markers as much (18 → 49 pixels, offsets moved 0.7–1.4 px) without moving
/// their centroids (errors ≤ 0.012 px): it saturates their neighbours too, and they
/// stay ok.
#[test]
fn table_i_bright_marker_under_a_specular_highlight_is_an_outlier() {
    let spot = "[[effects]]\nkind = \"glare\"\ncenter_px = [207.0, 175.0]\nsigma_px = 2.5\namplitude = 1.0\n";
    let (c, (mx, sx, sy, worst)) = table_i_track("bright", spot);
    assert_eq!((c.ok, c.outlier, c.lost, c.merged), (129, 1, 0, 0), "{c:?}");
    assert!((mx - 3.0).abs() <= 0.002, "mean {mx}");
    assert!(sx <= 0.006 && sy <= 0.006, "SD {sx} / {sy}");
    assert!(worst <= 0.03, "largest error {worst}");
}

/// Paper Table I through `tactbench run --sim` and `tactbench report` (the
/// committed plan `experiments/table1_displacement.toml` and scene
/// `experiments/scenes/table1_carried.toml`: 10 trials of a 0.15 mm = 3 px stage
/// shift carrying the sensor, pixel noise σ = 2, 8-bit) with the paper sensor's blue
/// layer drawn `dark` on the lit gel under the illumination gradient and the broad
/// glare (static while the sensor moves), and `bright` under the glare: `run` accepts
/// the new appearances, and an ROI (`roi_px` rectangle 5 px inside the image, for the
/// dark sensor: every marker's window stays inside it, all 130 ok). Measured (`verdict.json`, `displacement.max_sd_px` /
/// `max_abs_bias_px`): dark 0.005496 / 0.000119 px, bright 0.004920 / 0.000046 px
/// (paper sensor 0.014063 / 0.001887 px).
#[test]
fn run_table_i_plan_with_dark_and_bright_sensors_under_glare() {
    let root = |rel: &str| std::fs::read_to_string(crate::util::root(rel)).unwrap();
    let paper = root("experiments/paper_sensor.toml");
    let (red, grid) = (
        paper.find("[[layers]]\nname = \"red\"").unwrap(),
        paper.find("[force_grid]").unwrap(),
    );
    let one_layer = format!("{}{}", &paper[..red], &paper[grid..]);
    let roi = "height_px = 340\nroi_px = { min = [5.0, 5.0], max = [425.0, 335.0] }";
    for (color, effects, roi, max_sd) in [
        ("dark", format!("{GRADIENT}{GLARE}"), roi, 0.0065),
        ("bright", GLARE.to_string(), "height_px = 340", 0.006),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        std::fs::write(
            d.join("sensor.toml"),
            one_layer
                .replace(
                    "name = \"blue\"\ncolor = \"blue\"",
                    &format!("name = \"dots\"\ncolor = \"{color}\""),
                )
                .replace("height_px = 340", roi),
        )
        .unwrap();
        std::fs::write(
            d.join("plan.toml"),
            root("experiments/table1_displacement.toml")
                .replace("sensor = \"paper_sensor.toml\"", "sensor = \"sensor.toml\""),
        )
        .unwrap();
        std::fs::write(
            d.join("scene.toml"),
            root("experiments/scenes/table1_carried.toml")
                .replace(
                    "sensor = \"../paper_sensor.toml\"",
                    "sensor = \"sensor.toml\"",
                )
                .replacen(
                    "[[effects]]\nkind = \"pixel_noise\"",
                    &format!("{effects}\n[[effects]]\nkind = \"pixel_noise\""),
                    1,
                ),
        )
        .unwrap();
        let o = crate::util::run_in(
            d,
            &["run", "plan.toml", "--sim", "scene.toml", "--out", "R"],
        );
        assert!(o.status.success(), "{color}: {}", crate::util::stderr(&o));
        let o = crate::util::run_in(d, &["report", "R"]);
        assert!(o.status.success(), "{color}: {}", crate::util::stderr(&o));
        let verdict: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(d.join("R/verdict.json")).unwrap())
                .unwrap();
        let metric = |name: &str| {
            verdict["metrics"]
                .as_array()
                .unwrap()
                .iter()
                .find(|m| m["name"] == name)
                .and_then(|m| m["value"].as_f64())
                .unwrap_or_else(|| panic!("{color}: no {name} in verdict.json"))
        };
        let (sd, bias) = (
            metric("displacement.max_sd_px"),
            metric("displacement.max_abs_bias_px"),
        );
        let journal = std::fs::read_to_string(d.join("R/journal.csv")).unwrap();
        let mut lines = journal.lines();
        let head: Vec<&str> = lines.next().unwrap().split(',').collect();
        let ok_col = head.iter().position(|h| *h == "markers_ok").unwrap();
        for l in lines {
            assert_eq!(l.split(',').nth(ok_col), Some("130"), "{color}: {l}");
        }
        eprintln!("run Table I, {color}: max SD {sd:.6} px, max |bias| {bias:.6} px");
        assert!(
            sd <= max_sd && bias <= 0.001,
            "{color}: SD {sd}, bias {bias}"
        );
    }
}

// ---- windows cut by the image edge --------------------------------------------------

/// One case of [`windows_cut_by_the_image_edge_measure_dots_inside_like_interior_ones`]:
/// the Table I geometry (0.6 mm markers every 1.5 mm at 0.05 mm/px, 430 × 340 px) with
/// the grid's first column and row `origin` px from the image's left and top pixel
/// centres, a frame shifted by `shift` px, 8-bit, σ = 2, plus `extra` effects; tracked
/// per window. Per marker: (|displacement − shift|, how far its dot of the detected
/// radius clears the left/top image edge in the reference or the frame, whichever is
/// less (true centres), whether its window is cut in either, status).
fn edge_case(
    color: &str,
    extra: &str,
    origin: f64,
    shift: [f64; 2],
) -> Vec<(f64, f64, bool, MarkerStatus)> {
    use tactbench::sim::{scene::Scene, simulate::Simulation};
    let text = format!(
        "[elastomer]\nyoung_modulus_kpa = 1000.0\npoisson_ratio = 0.5\nthickness_mm = 40.0\n\n\
         [[layers]]\nname = \"markers\"\ncolor = \"{color}\"\ndepth_mm = 3.0\n\
         [layers.markers]\nnx = 13\nny = 10\npitch_mm = 1.5\norigin_mm = [0.0, 0.0]\ndiameter_mm = 0.6\n\n\
         [force_grid]\nnx = 10\nny = 8\npitch_mm = 2.2\norigin_mm = [-0.9, -0.95]\n\n\
         [camera]\nmm_per_px = 0.05\norigin_px = [{origin}, {origin}]\nwidth_px = 430\nheight_px = 340\n"
    );
    let s = Sensor::from_toml_str(&text, "edge.toml").unwrap();
    let scene_text = format!(
        "sensor = \"edge.toml\"\n[indenter]\nkind = \"point\"\n[load]\nposition_mm = [9.0, 6.75]\nnormal_force_n = 0.0\n\
         [[effects]]\nkind = \"shift\"\nshift_px = [{}, {}]\n{extra}\
         [[effects]]\nkind = \"pixel_noise\"\nsigma_8bit = 2.0\nseed = 3\n[[effects]]\nkind = \"quantize8\"\n",
        shift[0], shift[1]
    );
    let scene = Scene::from_toml_str(&scene_text, "edge_scene.toml", s.clone()).unwrap();
    let mut sim = Simulation::from_scene(&scene);
    let mut f = sim.blank_frame();
    sim.render_reference(&mut f).unwrap();
    let reference = to_rgb8(&f);
    sim.render_load(&scene.frame_load(1), 1, &mut f).unwrap();
    let shifted = to_rgb8(&f);
    let r = reference_of(&reference, &s);
    let half = (r.layers[0].aperture_radius_px + 3.0).floor();
    let radius = r.layers[0].marker_radius_px;
    let refs: Vec<[f64; 2]> = r.markers.iter().map(|m| m.centroid_px).collect();
    let mut t = Tracker::new(r, per_window());
    let tracks = t.track(&FrameView::rgb8(&shifted)).unwrap();
    refs.iter()
        .zip(tracks)
        .map(|(c, t)| {
            // The true centre: the grid node nearest to the measured reference centroid.
            let node = |v: f64| origin + 30.0 * ((v - origin) / 30.0).round();
            let truth = [node(c[0]), node(c[1])];
            let at = [truth[0] + shift[0], truth[1] + shift[1]];
            let near = truth[0].min(truth[1]).min(at[0]).min(at[1]);
            let cut = [truth, at]
                .iter()
                .any(|p| p[0].round() < half || p[1].round() < half);
            let e = (t.displacement_px[0] - shift[0]).hypot(t.displacement_px[1] - shift[1]);
            (e, near + 0.5 - radius, cut, t.status)
        })
        .collect()
}

/// Issue 19: a marker near the image edge whose window (half-size 11 px here) is cut
/// by the edge but whose dot (detected radius + 1 px) is inside is measured on the
/// window's pixels inside the image (`window::clipped`: the background plane fitted
/// on the ring's part inside). Rendered frames with ground truth: the grid's first
/// column and row placed 6.0–12.0 px from the left and top pixel centres in 0.25 px
/// steps, frames shifted by (0.37, 0.21), (−0.33, −0.42) and (0, 0.5) px, 8-bit with
/// σ = 2 noise; four appearances: `dark` under the illumination gradient, the same
/// with vignetting (strength 0.4: curved illumination, strongest at the edges where
/// the cut windows are), `bright`, `bright` with vignetting. "Clearance": how far the
/// dot (detected radius) stays inside the edge, in the reference or the frame,
/// whichever is less. Measured |displacement error| over ok markers, rms / max, px:
///
/// | case | whole windows (8518) | cut windows, clearance ≥ 1 px (1012) |
/// |---|---|---|
/// | dark, gradient | 0.0080 / 0.0263 | 0.0087 / 0.0239 |
/// | dark, gradient + vignetting | 0.0090 / 0.0296 | 0.0117 / 0.0298 |
/// | bright | 0.0071 / 0.0247 | 0.0068 / 0.0192 |
/// | bright, vignetting | 0.0078 / 0.0266 | 0.0091 / 0.0261 |
///
/// Per 0.25 px bin of clearance from 1 to 5 px the largest error stays flat (dark with
/// vignetting: 0.026–0.030 px in every bin): a cut window measures as well as a whole
/// one (within Table I's 0.035 px bound), so such markers are `ok`. Under vignetting
/// the cut windows' rms is up to 30 % above the whole windows' (they sit where the
/// illumination curves most; their largest error does not grow). Dots within 1 px of
/// the edge (clearance < 1) are `lost`, in the frame or the reference (176 per case).
#[test]
fn windows_cut_by_the_image_edge_measure_dots_inside_like_interior_ones() {
    let vignette = "[[effects]]\nkind = \"vignetting\"\nstrength = 0.4\n";
    for (color, extra) in [
        ("dark", GRADIENT.to_string()),
        ("dark", format!("{GRADIENT}{vignette}")),
        ("bright", String::new()),
        ("bright", vignette.to_string()),
    ] {
        let what = format!("{color} {}", extra.replace('\n', " "));
        // Errors of ok markers: whole windows, cut windows.
        let (mut whole, mut cut_ok, mut lost) = (Vec::new(), Vec::new(), 0);
        for k in 0..25 {
            let origin = 6.0 + 0.25 * k as f64;
            for shift in [[0.37, 0.21], [-0.33, -0.42], [0.0, 0.5]] {
                for (e, clearance, cut, st) in edge_case(color, &extra, origin, shift) {
                    // Statuses are asserted away from the limit (the tracker judges
                    // measured centres, these are true ones).
                    if !cut {
                        assert_eq!(st, MarkerStatus::Ok, "{what}: whole window");
                        whole.push(e);
                    } else if clearance >= 1.05 {
                        assert_eq!(st, MarkerStatus::Ok, "{what}: clearance {clearance:.2}");
                        cut_ok.push(e);
                    } else if clearance < 0.95 {
                        assert_eq!(st, MarkerStatus::Lost, "{what}: clearance {clearance:.2}");
                        lost += 1;
                    }
                }
            }
        }
        let stats = |v: &mut Vec<f64>| {
            v.sort_by(f64::total_cmp);
            let rms = (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
            (v.len(), rms, v[v.len() - 1])
        };
        let (nw, rw, mw) = stats(&mut whole);
        let (nc, rc, mc) = stats(&mut cut_ok);
        eprintln!(
            "cut windows, {what}: whole {nw}: rms {rw:.4} max {mw:.4} px; cut, ok {nc}: rms {rc:.4} max {mc:.4} px; {lost} lost"
        );
        assert!(nc >= 950 && lost >= 150, "{what}: {nc} ok / {lost} lost");
        // Within the interior bound: Table I's 0.035 px, and within 10 % of this
        // run's whole windows' largest error.
        assert!(mc <= 0.035 && mc <= 1.1 * mw && rc <= 1.35 * rw, "{what}");
    }
}

// ---- independent frames against one reference (issue 29 item 5) --------------------

/// Independent frames (no sequence: each a smooth field of 0.3–0.4 local spacings in
/// another direction, the next one often opposite) tracked in order against one
/// reference by the default mode. Frame to frame it used to start every window at
/// the previous, unrelated frame's position plus that frame's "velocity", up to 1.2
/// local spacings off: markers landed on neighbours' blobs. Now every marker is ok
/// and within 0.1 px of the drawn displacement, as per window.
#[test]
fn hexagonal_layout_independent_frames_tracked_by_default_as_per_window() {
    let s = free_sensor();
    let layout = hex_layout();
    let radii: Vec<f64> = layout.iter().map(|&p| radius_at(p)).collect();
    let r = reference_of(&render_free(&s, &layout, &radii, 1), &s);
    let index = truth_index(&r, &layout);
    let mut t = Tracker::new(r, TrackConfig::default());
    let cases = [
        (0.4, 0.5),
        (0.4, 0.5 + std::f64::consts::PI),
        (0.3, 2.0),
        (0.4, -2.5),
        (0.4, 2.0),
        (0.0, 0.0),
        (0.4, 0.5 + std::f64::consts::PI),
    ];
    for (case, (fraction, angle0)) in cases.into_iter().enumerate() {
        let u = field(&layout, fraction, angle0);
        let moved: Vec<[f64; 2]> = layout
            .iter()
            .zip(&u)
            .map(|(p, d)| [p[0] + d[0], p[1] + d[1]])
            .collect();
        let img = render_free(&s, &moved, &radii, 300 + case as u64);
        let tracks = t.track(&FrameView::rgb8(&img)).unwrap();
        let counts = StatusCounts::of(tracks, 0);
        let mut worst = 0.0f64;
        for (tr, &k) in tracks.iter().zip(&index) {
            if tr.status == MarkerStatus::Ok {
                let e = (tr.displacement_px[0] - u[k][0]).hypot(tr.displacement_px[1] - u[k][1]);
                worst = worst.max(e);
            }
        }
        eprintln!("frame {case} ({fraction} spacing at {angle0:.2} rad): {counts:?}, worst ok error {worst:.4} px");
        assert_eq!(counts.ok, layout.len(), "frame {case}: {counts:?}");
        assert!(worst < 0.1, "frame {case}: worst error {worst} px");
    }
}

/// Independent contacts rendered by the simulator (`experiments/scenes/large_motion.toml`'s
/// sensor, indenter and imaging: the paper sensor, a 5 mm hemisphere, blur, noise,
/// 8-bit) at unrelated loads: pressed and dragged along +x, then −x, +y, at another
/// place, unloaded, then −x again; tracked in order against the unloaded reference
/// by the default mode. Every ok marker's displacement is within 0.1 px of the
/// simulator's truth and within 3 of as many are ok as per window.
#[test]
fn independent_contacts_rendered_by_the_simulator_tracked_by_default_as_per_window() {
    use tactbench::sim::contact::{LoadCase, Normal, Tangential};
    use tactbench::sim::{scene::Scene, simulate::Simulation};
    let scene =
        Scene::from_path(crate::util::root("experiments/scenes/large_motion.toml")).unwrap();
    let mm_per_px = scene.sensor.camera.mm_per_px;
    let mut sim = Simulation::from_scene(&scene);
    let mut f = sim.blank_frame();
    let t0 = sim.render_reference(&mut f).unwrap();
    let r = reference_of(&to_rgb8(&f), &scene.sensor);
    assert_eq!(r.markers.len(), sim.markers().len());
    // Simulator marker index of each reference marker (same layer and grid id).
    let ids = sim.marker_ids().to_vec();
    let index: Vec<usize> = r
        .markers
        .iter()
        .map(|m| {
            ids.iter()
                .position(|&(l, id)| l == m.layer && id as u64 == m.id)
                .unwrap()
        })
        .collect();
    let load = |at: [f64; 2], q: [f64; 2]| LoadCase {
        position_mm: at,
        normal: Normal::ForceN(10.0),
        tangential: Tangential::ForceN(q),
        friction: 1.0,
    };
    let contacts = [
        load([9.0, 6.75], [8.0, 0.0]),
        load([9.0, 6.75], [-8.0, 0.0]),
        load([9.0, 6.75], [0.0, 8.0]),
        load([6.0, 4.5], [6.0, -6.0]),
        load([9.0, 6.75], [0.0, 0.0]),
        load([9.0, 6.75], [-8.0, 0.0]),
    ];
    let mut t = Tracker::new(r.clone(), TrackConfig::default());
    let mut largest = 0.0f64;
    let mut seen = Vec::new();
    for (k, c) in contacts.iter().enumerate() {
        let truth = sim.render_load(c, 1 + k as u64, &mut f).unwrap();
        let img = to_rgb8(&f);
        let tracks = t.track(&FrameView::rgb8(&img)).unwrap().to_vec();
        let pw = Tracker::new(r.clone(), per_window())
            .track(&FrameView::rgb8(&img))
            .unwrap()
            .to_vec();
        let (counts, pw_counts) = (StatusCounts::of(&tracks, 0), StatusCounts::of(&pw, 0));
        let mut worst = 0.0f64;
        for (tr, &m) in tracks.iter().zip(&index) {
            let u = truth.apparent_u_px(m, mm_per_px, t0.offset_px);
            largest = largest.max(u[0].hypot(u[1]));
            if tr.status == MarkerStatus::Ok {
                let e = (tr.displacement_px[0] - u[0]).hypot(tr.displacement_px[1] - u[1]);
                worst = worst.max(e);
            }
        }
        let what = format!(
            "contact {k}: default {counts:?}, per window {pw_counts:?}, worst ok error {worst:.4} px"
        );
        eprintln!("{what}");
        seen.push((what, worst, counts.ok, pw_counts.ok));
    }
    eprintln!("largest true displacement {largest:.1} px");
    for (what, worst, ok, pw_ok) in seen {
        assert!(worst < 0.1, "{what}");
        assert!(ok + 3 >= pw_ok, "{what}");
    }
}

/// The sequence of `experiments/scenes/large_motion.toml` (a hemisphere pressed and
/// dragged over 12 frames: markers travel over 40 px, up to 6 px per frame), tracked
/// in order against its reference by the default mode: the re-acquisition from the
/// reference (issue 29 item 5) must not cost the sequence anything. Measured after
/// it: 3120 of 3120 marker-frames ok, largest true displacement 43.0 px, ok error
/// rms 0.0122 px, max 0.0412 px.
#[test]
fn large_motion_scene_sequence_tracked_by_default_against_the_truth() {
    use tactbench::sim::{scene::Scene, simulate::Simulation};
    let scene =
        Scene::from_path(crate::util::root("experiments/scenes/large_motion.toml")).unwrap();
    let mm_per_px = scene.sensor.camera.mm_per_px;
    let mut sim = Simulation::from_scene(&scene);
    let mut f = sim.blank_frame();
    let t0 = sim.render_reference(&mut f).unwrap();
    let r = reference_of(&to_rgb8(&f), &scene.sensor);
    let ids = sim.marker_ids().to_vec();
    let index: Vec<usize> = r
        .markers
        .iter()
        .map(|m| {
            ids.iter()
                .position(|&(l, id)| l == m.layer && id as u64 == m.id)
                .unwrap()
        })
        .collect();
    let mut t = Tracker::new(r, TrackConfig::default());
    let (mut largest, mut worst, mut sq, mut n) = (0.0f64, 0.0f64, 0.0, 0usize);
    for k in 1..=scene.frames {
        let truth = sim
            .render_load(&scene.frame_load(k), k as u64, &mut f)
            .unwrap();
        let tracks = t.track(&FrameView::rgb8(&to_rgb8(&f))).unwrap();
        let counts = StatusCounts::of(tracks, 0);
        let mut frame_worst = 0.0f64;
        for (tr, &m) in tracks.iter().zip(&index) {
            let u = truth.apparent_u_px(m, mm_per_px, t0.offset_px);
            largest = largest.max(u[0].hypot(u[1]));
            if tr.status == MarkerStatus::Ok {
                let e = (tr.displacement_px[0] - u[0]).hypot(tr.displacement_px[1] - u[1]);
                frame_worst = frame_worst.max(e);
                sq += e * e;
                n += 1;
            }
        }
        worst = worst.max(frame_worst);
        eprintln!("frame {k}: {counts:?}, worst ok error {frame_worst:.4} px");
    }
    let rms = (sq / n as f64).sqrt();
    eprintln!(
        "large_motion.toml: {n} ok of {} marker-frames, largest true displacement {largest:.1} px, ok error rms {rms:.4} px, max {worst:.4} px",
        scene.frames * index.len()
    );
    assert!(
        largest > 40.0 && worst < 0.1,
        "largest {largest} px, worst {worst} px"
    );
}
