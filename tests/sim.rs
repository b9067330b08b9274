//! Scene simulation: ideal renderer exactness, effect isolation, contact models against
//! closed forms, scene parsing errors, and the `sim render` outputs.

use image::Rgb32FImage;
use tactbench::sensor::paper_sensor;
use tactbench::sim::render::{reference_markers, to_rgb16, to_rgb8, Marker, PixelFilter, Renderer};

/// Intensity-weighted centroid (px, integer pixel centres) of channel `ch` minus the
/// background level, over a window around `around_px`.
fn centroid(frame: &Rgb32FImage, ch: usize, bg: f32, around_px: [f64; 2], half: i64) -> [f64; 2] {
    let (mut sw, mut sx, mut sy) = (0.0f64, 0.0f64, 0.0f64);
    let (cx, cy) = (around_px[0].round() as i64, around_px[1].round() as i64);
    for j in cy - half..=cy + half {
        for i in cx - half..=cx + half {
            if i < 0 || j < 0 || i >= frame.width() as i64 || j >= frame.height() as i64 {
                continue;
            }
            let w = (frame.get_pixel(i as u32, j as u32).0[ch] - bg) as f64;
            sw += w;
            sx += w * i as f64;
            sy += w * j as f64;
        }
    }
    [sx / sw, sy / sw]
}

#[test]
fn ideal_disc_centroid_equals_true_centre_to_the_area_sampling_limit() {
    let s = paper_sensor();
    let r = Renderer::new(&s);
    let bg = r.palette().background[2];
    let (mut worst, mut sum_abs, mut n) = (0.0f64, 0.0f64, 0usize);
    // Sub-pixel offsets on a 0.1 px lattice (and an irrational-ish one).
    for a in 0..10 {
        for b in 0..10 {
            let c_px = [
                100.0 + 0.1 * a as f64 + 0.0137,
                80.0 + 0.1 * b as f64 + 0.0071,
            ];
            let p_mm = s.camera.px_to_mm(c_px);
            let f = r
                .render(&[Marker {
                    layer: 0,
                    position_mm: p_mm,
                    diameter_mm: 0.6,
                }])
                .unwrap();
            let c = centroid(&f, 2, bg, c_px, 10);
            for e in [(c[0] - c_px[0]).abs(), (c[1] - c_px[1]).abs()] {
                worst = worst.max(e);
                sum_abs += e;
                n += 1;
            }
        }
    }
    let mean = sum_abs / n as f64;
    eprintln!("centroid error: worst {worst:.2e} px, mean {mean:.2e} px");
    // Exact area coverage assigns each covered area to its pixel centre: for a 12 px
    // disc this box-filter sampling error is up to 1.53e-3 px (mean 0.98e-3 px) over
    // sub-pixel positions; the coverage itself is exact (unit tests).
    assert!(
        worst <= 2e-3 && mean <= 1.1e-3,
        "worst centroid error {worst} px, mean {mean} px"
    );
}

#[test]
fn tent_filter_disc_centroid_equals_true_centre_within_1e_5_px() {
    let s = paper_sensor();
    let r = Renderer::new(&s).with_filter(PixelFilter::Tent);
    let bg = r.palette().background[2];
    let mut worst = 0.0f64;
    for a in 0..10 {
        for b in 0..10 {
            let c_px = [
                100.0 + 0.1 * a as f64 + 0.0137,
                80.0 + 0.1 * b as f64 + 0.0071,
            ];
            let m = Marker {
                layer: 0,
                position_mm: s.camera.px_to_mm(c_px),
                diameter_mm: 0.6,
            };
            let c = centroid(&r.render(&[m]).unwrap(), 2, bg, c_px, 10);
            worst = worst
                .max((c[0] - c_px[0]).abs())
                .max((c[1] - c_px[1]).abs());
        }
    }
    // Exact in exact arithmetic; f32 pixel values and sums leave ~1e-6 px.
    assert!(worst <= 1e-5, "worst centroid error {worst} px");
}

#[test]
fn ideal_render_is_deterministic_and_16_bit_keeps_coverage() {
    let s = paper_sensor();
    let r = Renderer::new(&s);
    let m = reference_markers(&s);
    assert_eq!(m.len(), 260);
    let a = r.render(&m).unwrap();
    let b = r.render(&m).unwrap();
    assert_eq!(a.as_raw(), b.as_raw());
    let a16 = to_rgb16(&a);
    let a8 = to_rgb8(&a);
    for (f, (w16, w8)) in a.as_raw().iter().zip(a16.as_raw().iter().zip(a8.as_raw())) {
        assert!((*w16 as f32 / 65535.0 - f).abs() <= 0.5 / 65535.0 + 1e-7);
        assert!((*w8 as f32 / 255.0 - f).abs() <= 0.5 / 255.0 + 1e-7);
    }
}

// ---- effects -------------------------------------------------------------------------

use tactbench::sim::effects::{Effect, Pipeline, Scratch};

/// Paper sensor markers, a renderer and a frame rendered through `effects`.
fn through(effects: Vec<Effect>, frame: u64) -> (Rgb32FImage, Vec<Marker>) {
    let s = paper_sensor();
    let p = Pipeline::new(effects, s.layers.len()).unwrap();
    let r = Renderer::new(&s);
    let mut m = reference_markers(&s);
    p.build_markers(&mut m);
    let mut out = r.blank();
    p.render_frame(&r, &m, frame, &mut out, &mut Scratch::default())
        .unwrap();
    (out, m)
}

fn ideal() -> Rgb32FImage {
    let s = paper_sensor();
    Renderer::new(&s).render(&reference_markers(&s)).unwrap()
}

fn max_abs_diff(a: &Rgb32FImage, b: &Rgb32FImage) -> f32 {
    a.as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn pixel_noise(seed: u64) -> Effect {
    Effect::PixelNoise {
        sigma_8bit: 2.0,
        seed,
    }
}

#[test]
fn empty_effect_list_is_the_ideal_render_bit_for_bit() {
    let ideal = ideal();
    for frame in [0, 1, 7] {
        assert_eq!(through(vec![], frame).0.as_raw(), ideal.as_raw());
    }
}

#[test]
fn random_effects_repeat_with_their_seed_and_change_with_it() {
    let random = |seed| {
        vec![
            vec![pixel_noise(seed)],
            vec![Effect::ShotNoise {
                full_scale_photons: 5000.0,
                seed,
            }],
            vec![Effect::SizeJitter {
                sigma_mm: 0.02,
                seed,
            }],
            vec![Effect::PlacementJitter {
                sigma_mm: 0.02,
                seed,
            }],
            vec![Effect::Drift {
                px_per_frame: [0.0, 0.0],
                random_walk_px: 0.3,
                seed,
            }],
        ]
    };
    for (a, (b, c)) in random(3)
        .into_iter()
        .zip(random(3).into_iter().zip(random(4)))
    {
        let kind = a[0].kind();
        let fa = through(a, 2).0;
        assert_eq!(fa.as_raw(), through(b, 2).0.as_raw(), "{kind}: same seed");
        assert_ne!(fa.as_raw(), through(c, 2).0.as_raw(), "{kind}: other seed");
    }
}

#[test]
fn pixel_noise_is_zero_mean_with_sigma_in_8bit_levels_and_fresh_per_frame() {
    let ideal = ideal();
    let (f1, _) = through(vec![pixel_noise(9)], 1);
    let (f2, _) = through(vec![pixel_noise(9)], 2);
    let res: Vec<f64> = f1
        .as_raw()
        .iter()
        .zip(ideal.as_raw())
        .map(|(a, b)| 255.0 * (a - b) as f64)
        .collect();
    let n = res.len() as f64; // 438,600 samples: SE of σ ≈ σ/√(2n) ≈ 0.1%
    let mean = res.iter().sum::<f64>() / n;
    let sd = (res.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / n).sqrt();
    assert!(mean.abs() < 0.02, "mean {mean} levels");
    assert!((sd - 2.0).abs() < 0.02, "σ {sd} levels");
    assert_ne!(f1.as_raw(), f2.as_raw(), "frames get independent noise");
}

#[test]
fn shot_noise_variance_is_value_over_full_scale_photons() {
    // Background pixels (value 0.04 in R): variance 0.04 / N.
    let n_ph = 2000.0;
    let ideal = ideal();
    let (f, _) = through(
        vec![Effect::ShotNoise {
            full_scale_photons: n_ph,
            seed: 1,
        }],
        1,
    );
    let bg = ideal.as_raw()[0];
    let res: Vec<f64> = f
        .as_raw()
        .iter()
        .zip(ideal.as_raw())
        .step_by(3)
        .filter(|(_, b)| **b == bg)
        .map(|(a, b)| (a - b) as f64)
        .collect();
    let n = res.len() as f64;
    let var = res.iter().map(|r| r * r).sum::<f64>() / n;
    let want = bg as f64 / n_ph;
    // > 60k samples: 5 standard errors of a variance ≈ 5 √(2/n) ≈ 3%.
    assert!(
        (var / want - 1.0).abs() < 0.03,
        "var {var} want {want} (n {n})"
    );
}

#[test]
fn quantize8_rounds_to_code_values_within_half_a_level() {
    let ideal = ideal();
    let (f, _) = through(vec![Effect::Quantize8], 1);
    for (q, v) in f.as_raw().iter().zip(ideal.as_raw()) {
        let code = q * 255.0;
        assert!((code - code.round()).abs() < 1e-4, "{q}");
        assert!((q - v).abs() <= 0.5 / 255.0 + 1e-7);
    }
}

#[test]
fn occlusion_greys_out_its_rectangle_in_its_frames_only() {
    let ideal = ideal();
    let occlusion = Effect::Occlusion {
        rect_px: [10.0, 20.0, 100.5, 60.0],
        level: 0.5,
        first_frame: 2,
        last_frame: Some(3),
    };
    for frame in [0, 1, 4] {
        let (f, _) = through(vec![occlusion.clone()], frame);
        assert_eq!(f.as_raw(), ideal.as_raw(), "frame {frame} untouched");
    }
    for frame in [2, 3] {
        let (f, _) = through(vec![occlusion.clone()], frame);
        for (i, j, p) in f.enumerate_pixels() {
            // Pixel centres 10..=100 x 20..=59 are covered.
            if (10..=100).contains(&i) && (20..60).contains(&j) {
                assert_eq!(p.0, [0.5; 3], "({i},{j}) frame {frame}");
            } else {
                assert_eq!(p.0, ideal.get_pixel(i, j).0, "({i},{j}) frame {frame}");
            }
        }
    }
    // From a scene file: default level 0.5, every loaded frame (1 on), checked keys.
    let ok = Scene::from_toml_str(
        &format!("{BASE}[[effects]]\nkind = \"occlusion\"\nrect_px = [0.0, 0.0, 215.0, 340.0]\n"),
        "s.toml",
        paper_sensor(),
    )
    .unwrap();
    assert_eq!(
        ok.pipeline.effects(),
        &[Effect::Occlusion {
            rect_px: [0.0, 0.0, 215.0, 340.0],
            level: 0.5,
            first_frame: 1,
            last_frame: None,
        }]
    );
    let e = scene_err(&format!(
        "{BASE}[[effects]]\nkind = \"occlusion\"\nrect_px = [0.0, 0.0, 10.0, 10.0]\nframes = [5, 2]\n"
    ));
    assert!(e.contains("effects[0] (occlusion): frames = [5, 2]"), "{e}");
    let e = scene_err(&format!(
        "{BASE}[[effects]]\nkind = \"occlusion\"\nrect_px = [20.0, 0.0, 10.0, 10.0]\n"
    ));
    assert!(e.contains("rect_px") && e.contains("x0 < x1"), "{e}");
}

#[test]
fn illumination_and_vignetting_multiply_by_their_gain_only() {
    let s = paper_sensor();
    let (w, h) = (s.camera.width_px as f64, s.camera.height_px as f64);
    let ideal = ideal();
    let g = [0.4, -0.2];
    let (f, _) = through(vec![Effect::Illumination { gradient: g }], 1);
    for (i, j, p) in f.enumerate_pixels() {
        let gain = 1.0 + g[0] * (i as f64 / (w - 1.0) - 0.5) + g[1] * (j as f64 / (h - 1.0) - 0.5);
        for ch in 0..3 {
            let want = ideal.get_pixel(i, j).0[ch] as f64 * gain;
            assert!((p.0[ch] as f64 - want).abs() < 1e-6, "({i},{j})");
        }
    }
    let c = [200.0, 150.0];
    let (f, _) = through(
        vec![Effect::Vignetting {
            strength: 0.5,
            center_px: Some(c),
        }],
        1,
    );
    assert_eq!(
        f.get_pixel(200, 150),
        ideal.get_pixel(200, 150),
        "no loss at the centre"
    );
    // Farthest corner from (200, 150) in a 430x340 frame is (429, 339): loss 0.5.
    let corner = f.get_pixel(429, 339).0[0] / ideal.get_pixel(429, 339).0[0];
    assert!((corner - 0.5).abs() < 1e-6, "{corner}");
}

#[test]
fn shift_moves_loaded_frames_by_exactly_the_shift_and_leaves_the_reference() {
    let s = paper_sensor();
    let shift = |d: [f64; 2]| vec![Effect::Shift { shift_px: d }];
    assert_eq!(through(shift([3.0, 0.0]), 0).0.as_raw(), ideal().as_raw());
    let bg = Renderer::new(&s).palette().background[2];
    let ideal = ideal();
    for d in [[3.0, 0.0], [-1.25, 2.6]] {
        let (f, m) = through(shift(d), 1);
        // Every blue marker away from the border (window ±10 px around the marker).
        let mut worst = 0.0f64;
        for mk in m.iter().filter(|mk| mk.layer == 0) {
            let c0 = s.camera.mm_to_px(mk.position_mm);
            if c0[0] < 15.0 || c0[1] < 15.0 || c0[0] > 410.0 || c0[1] > 320.0 {
                continue;
            }
            let a = centroid(&ideal, 2, bg, c0, 9);
            let b = centroid(&f, 2, bg, [c0[0] + d[0], c0[1] + d[1]], 9);
            worst = worst
                .max((b[0] - a[0] - d[0]).abs())
                .max((b[1] - a[1] - d[1]).abs());
        }
        // Integer shifts keep the sub-pixel phase (exact to float rounding); fractional
        // ones change the area-sampling error (≤ 1.53e-3 px each, see above) of both
        // centroids, so their difference is within 2 × 1.53e-3 px.
        let tol = if d == [3.0, 0.0] { 1e-4 } else { 3.5e-3 };
        assert!(worst < tol, "shift {d:?}: centroid error {worst} px");
    }
}

#[test]
fn drift_offsets_frame_k_by_k_steps() {
    let p = Pipeline::new(
        vec![Effect::Drift {
            px_per_frame: [0.5, -0.25],
            random_walk_px: 0.0,
            seed: 0,
        }],
        2,
    )
    .unwrap();
    assert_eq!(p.image_offset_px(0), [0.0, 0.0]);
    assert_eq!(p.image_offset_px(4), [2.0, -1.0]);
    let walk = Pipeline::new(
        vec![Effect::Drift {
            px_per_frame: [0.0, 0.0],
            random_walk_px: 0.2,
            seed: 5,
        }],
        2,
    )
    .unwrap();
    // A random walk: frame k+1 continues frame k.
    let (a, b) = (walk.image_offset_px(3), walk.image_offset_px(4));
    assert!((b[0] - a[0]).abs() < 1.5 && a != [0.0, 0.0] && a != b);
    assert_eq!(walk.image_offset_px(3), a);
}

#[test]
fn jitter_effects_change_only_their_own_property() {
    let s = paper_sensor();
    let reference = reference_markers(&s);
    let (_, sized) = through(
        vec![Effect::SizeJitter {
            sigma_mm: 0.03,
            seed: 2,
        }],
        0,
    );
    let (_, placed) = through(
        vec![Effect::PlacementJitter {
            sigma_mm: 0.03,
            seed: 2,
        }],
        0,
    );
    let mut sd = (0.0f64, 0.0f64);
    for ((r, a), b) in reference.iter().zip(&sized).zip(&placed) {
        assert_eq!(a.position_mm, r.position_mm);
        assert_eq!(b.diameter_mm, r.diameter_mm);
        sd.0 += (a.diameter_mm - r.diameter_mm).powi(2);
        sd.1 += (b.position_mm[0] - r.position_mm[0]).powi(2);
    }
    let n = reference.len() as f64;
    let (sd_d, sd_x) = ((sd.0 / n).sqrt(), (sd.1 / n).sqrt());
    // 260 draws: the sample σ is within ±25% of 0.03 mm with overwhelming probability.
    assert!(
        (sd_d - 0.03).abs() < 0.0075 && (sd_x - 0.03).abs() < 0.0075,
        "{sd_d} {sd_x}"
    );
}

#[test]
fn an_added_effect_does_not_change_the_draws_of_another() {
    // The noise field of pixel_noise(seed 5) is the same with and without a shift and a
    // placement jitter in front of it (each effect draws from its own seed).
    let ideal_shifted = through(
        vec![Effect::Shift {
            shift_px: [2.0, 1.0],
        }],
        1,
    )
    .0;
    let noisy_shifted = through(
        vec![
            Effect::Shift {
                shift_px: [2.0, 1.0],
            },
            pixel_noise(5),
        ],
        1,
    )
    .0;
    let noisy = through(vec![pixel_noise(5)], 1).0;
    let ideal = ideal();
    for k in 0..ideal.as_raw().len() {
        let n1 = noisy_shifted.as_raw()[k] - ideal_shifted.as_raw()[k];
        let n2 = noisy.as_raw()[k] - ideal.as_raw()[k];
        assert!((n1 - n2).abs() < 1e-6, "sample {k}");
    }
    let m1 = through(
        vec![Effect::PlacementJitter {
            sigma_mm: 0.02,
            seed: 8,
        }],
        0,
    )
    .1;
    let m2 = through(
        vec![
            Effect::SizeJitter {
                sigma_mm: 0.02,
                seed: 8,
            },
            Effect::PlacementJitter {
                sigma_mm: 0.02,
                seed: 8,
            },
        ],
        0,
    )
    .1;
    for (a, b) in m1.iter().zip(&m2) {
        assert_eq!(a.position_mm, b.position_mm);
    }
}

#[test]
fn blur_preserves_each_marker_intensity_and_centre_and_zero_sigma_is_ideal() {
    let s = paper_sensor();
    let ideal = ideal();
    let (sharp, _) = through(
        vec![Effect::Blur {
            sigma_px: vec![0.0, 0.0],
        }],
        1,
    );
    assert!(max_abs_diff(&sharp, &ideal) < 1e-6);
    let (f, m) = through(
        vec![Effect::Blur {
            sigma_px: vec![1.5, 0.0],
        }],
        1,
    );
    assert!(max_abs_diff(&f, &ideal) > 0.05, "blue is blurred");
    let r = Renderer::new(&s);
    let red = r.palette().red;
    // Red (6 mm, drawn on top, σ = 0) interiors keep their exact colour.
    for mk in m.iter().filter(|mk| mk.layer == 1) {
        let c = s.camera.mm_to_px(mk.position_mm);
        assert_eq!(f.get_pixel(c[0].round() as u32, c[1].round() as u32).0, red);
    }
    // A blue marker's blue-channel centroid (±8 px window; its red neighbours, 21 px
    // away diagonally, are outside) is unchanged by the symmetric blur.
    let bg = r.palette().background[2];
    let mk = m[6 * 13 + 6]; // blue (6, 6)
    let c = s.camera.mm_to_px(mk.position_mm);
    let a = centroid(&ideal, 2, bg, c, 8);
    let b = centroid(&f, 2, bg, c, 8);
    assert!(
        (a[0] - b[0]).abs() < 2e-3 && (a[1] - b[1]).abs() < 2e-3,
        "{a:?} vs {b:?}"
    );
}

#[test]
fn image_effects_listed_before_marker_effects_are_rejected() {
    let e = Pipeline::new(
        vec![
            pixel_noise(1),
            Effect::Shift {
                shift_px: [1.0, 0.0],
            },
        ],
        2,
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("effects[1] (shift)") && e.contains("effects[0] (pixel_noise)"),
        "{e}"
    );
    let e = Pipeline::new(
        vec![Effect::Vignetting {
            strength: 1.5,
            center_px: None,
        }],
        2,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("strength = 1.5") && e.contains("[0, 1]"), "{e}");
}

// ---- scenes ----------------------------------------------------------------------------

use std::path::{Path, PathBuf};
use tactbench::sim::contact::{Indenter, Normal, Tangential};
use tactbench::sim::scene::Scene;
use tactbench::units::gf_to_n;

fn scenes_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("experiments/scenes")
}

const BASE: &str = r#"
sensor = "../paper_sensor.toml"
[indenter]
kind = "flat"
diameter_mm = 5.0
[load]
position_mm = [9.0, 6.75]
normal_force_gf = 910.0
"#;

fn scene_err(text: &str) -> String {
    Scene::from_toml_str(text, "s.toml", paper_sensor())
        .expect_err("should be rejected")
        .to_string()
}

#[test]
fn paper_scenes_parse_with_their_paper_values() {
    let fig4 = Scene::from_path(scenes_dir().join("fig4_flat_910gf.toml")).unwrap();
    assert_eq!(fig4.indenter, Indenter::Flat { diameter_mm: 5.0 });
    assert_eq!(fig4.load.normal, Normal::ForceN(gf_to_n(910.0)));
    assert!(fig4.pipeline.effects().is_empty());
    let fig8 = Scene::from_path(scenes_dir().join("fig8_angle_400gf.toml")).unwrap();
    assert_eq!(
        fig8.load.normal,
        Normal::ForceN(gf_to_n(400.0) * 30f64.to_radians().cos())
    );
    assert!(
        matches!(fig8.load.tangential, Tangential::Angle { angle_deg, .. } if angle_deg == 30.0)
    );
    let fig7 = Scene::from_path(scenes_dir().join("fig7_hemisphere_ramp.toml")).unwrap();
    assert_eq!(fig7.frames, 15);
    assert_eq!(
        fig7.frame_load(1).normal,
        Normal::ForceN(gf_to_n(750.0) / 15.0)
    );
    let t1 = Scene::from_path(scenes_dir().join("table1_shift.toml")).unwrap();
    assert_eq!(t1.pipeline.image_offset_px(1), [3.0, 0.0]);
    assert!(t1.pipeline.quantizes_to_8bit());
    let lm = Scene::from_path(scenes_dir().join("large_motion.toml")).unwrap();
    assert_eq!(lm.frames, 12);
}

#[test]
fn scene_errors_name_file_key_value_and_unit() {
    let e = scene_err(&BASE.replace("normal_force_gf = 910.0", "normal_force_gf = -3.0"));
    assert!(
        e.contains("s.toml") && e.contains("load.normal_force_gf = -3") && e.contains("gf"),
        "{e}"
    );
    let e = scene_err(&BASE.replace(
        "normal_force_gf = 910.0",
        "normal_force_gf = 910.0\ndepth_mm = 1.0",
    ));
    assert!(
        e.contains("normal_force_gf and depth_mm") && e.contains("exactly one"),
        "{e}"
    );
    let e = scene_err(&BASE.replace("normal_force_gf = 910.0", ""));
    assert!(e.contains("exactly one of normal_force_n"), "{e}");
    let e = scene_err(&BASE.replace("normal_force_gf", "normal_force_kg"));
    assert!(e.contains("normal_force_kg") && e.contains("line"), "{e}");
    let e = scene_err(
        &BASE
            .replace("kind = \"flat\"\ndiameter_mm = 5.0", "kind = \"point\"")
            .replace("normal_force_gf = 910.0", "depth_mm = 1.0"),
    );
    assert!(e.contains("point indenter has no indentation depth"), "{e}");
    let e = scene_err(&BASE.replace("diameter_mm = 5.0", "radius_mm = 5.0"));
    assert!(e.contains("radius_mm"), "{e}");
    let e = scene_err(&format!("{BASE}angle_deg = 95.0\n"));
    assert!(
        e.contains("load.angle_deg = 95") && e.contains("[0, 90)"),
        "{e}"
    );
    let e = scene_err(&format!("pixel_filter = \"gauss\"\n{BASE}"));
    assert!(
        e.contains("pixel_filter = \"gauss\"") && e.contains("tent"),
        "{e}"
    );
    let tent = Scene::from_toml_str(
        &format!("pixel_filter = \"tent\"\n{BASE}"),
        "s.toml",
        paper_sensor(),
    );
    assert_eq!(tent.unwrap().pixel_filter, PixelFilter::Tent);
    let e = scene_err(&format!("{BASE}[sequence]\nframes = 0\n"));
    assert!(e.contains("sequence.frames = 0"), "{e}");
}

#[test]
fn effect_errors_name_the_effect_and_reject_unknown_kinds_keys_and_layers() {
    let e = scene_err(&format!("{BASE}[[effects]]\nkind = \"sparkle\"\n"));
    assert!(e.contains("sparkle") && e.contains("line"), "{e}");
    let e = scene_err(&format!(
        "{BASE}[[effects]]\nkind = \"pixel_noise\"\nsigma_8bit = 2.0\nseed = 1\ncolour = 3\n"
    ));
    assert!(e.contains("colour"), "{e}");
    let e = scene_err(&format!(
        "{BASE}[[effects]]\nkind = \"pixel_noise\"\nsigma_8bit = 2.0\n"
    ));
    assert!(e.contains("seed"), "missing seed: {e}");
    let e = scene_err(&format!(
        "{BASE}[[effects]]\nkind = \"blur\"\nsigma_px = {{ green = 1.0 }}\n"
    ));
    assert!(
        e.contains("effects[0].sigma_px.green") && e.contains("blue, red"),
        "{e}"
    );
    let e = scene_err(&format!(
        "{BASE}[[effects]]\nkind = \"pixel_noise\"\nsigma_8bit = -1.0\nseed = 1\n"
    ));
    assert!(
        e.contains("effects[0] (pixel_noise): sigma_8bit = -1"),
        "{e}"
    );
}

#[test]
fn missing_sensor_file_is_reported_with_its_resolved_path() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("scene.toml");
    std::fs::write(&p, BASE.replace("../paper_sensor.toml", "nowhere.toml")).unwrap();
    let e = Scene::from_path(&p).unwrap_err().to_string();
    assert!(
        e.contains("nowhere.toml") && e.contains("scene.toml"),
        "{e}"
    );
}

// ---- simulation and CLI ------------------------------------------------------------------

use tactbench::formats::{read_displacements, read_forces};
use tactbench::sim::simulate::Simulation;

#[test]
fn angled_scene_force_grid_truth_sums_to_the_applied_force() {
    let sc = Scene::from_path(scenes_dir().join("fig8_angle_400gf.toml")).unwrap();
    let mut sim = Simulation::from_scene(&sc);
    let mut f = sim.blank_frame();
    let t = sim.render_load(&sc.frame_load(1), 1, &mut f).unwrap();
    let total = gf_to_n(400.0);
    let a = 30f64.to_radians();
    let want = [total * a.sin(), 0.0, total * a.cos()];
    for (b, w) in want.iter().enumerate() {
        let s: f64 = t.forces_n.iter().skip(b).step_by(3).sum();
        assert!((s - w).abs() < 1e-12, "axis {b}: {s} vs {w}");
    }
}

fn run_cli(scene: &Path, out: &Path) -> std::process::Output {
    crate::util::command()
        .args(["sim", "render", "--scene"])
        .arg(scene)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

#[test]
fn sim_render_writes_16_bit_frames_and_truth_an_ideal_tracker_reproduces() {
    let dir = tempfile::tempdir().unwrap();
    let o = run_cli(&scenes_dir().join("fig4_flat_910gf.toml"), dir.path());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let s = paper_sensor();
    let img = image::open(dir.path().join("frame_000.png")).unwrap();
    assert!(
        matches!(img, image::DynamicImage::ImageRgb16(_)),
        "16-bit PNG"
    );
    let reference = image::open(dir.path().join("reference.png"))
        .unwrap()
        .to_rgb32f();
    let frame = img.to_rgb32f();
    let frames = read_displacements(&dir.path().join("markers.csv"), &s).unwrap();
    assert_eq!(frames.len(), 1);
    assert_eq!(frames[0].records.len(), 260);
    // Forces sum to 910 gf along z.
    let forces = read_forces(&dir.path().join("forces.csv")).unwrap();
    let fz: f64 = forces.iter().map(|f| f.f_n[2]).sum();
    assert!((fz - gf_to_n(910.0)).abs() < 1e-9, "{fz}");
    // Centroid tracking on the written PNGs reproduces the truth of interior blue markers
    // (16-bit rounding adds < 1e-5 px; area sampling ≤ 2 × 1.53e-3 px).
    let bg = Renderer::new(&s).palette().background[2];
    let mut worst = 0.0f64;
    for r in frames[0].records.iter().filter(|r| r.layer == 0) {
        let p0 = s.camera.mm_to_px(r.position_mm);
        if p0[0] < 40.0 || p0[1] < 40.0 || p0[0] > 390.0 || p0[1] > 300.0 {
            continue;
        }
        let u = r.u_mm.unwrap();
        let p1 = s
            .camera
            .mm_to_px([r.position_mm[0] + u[0], r.position_mm[1] + u[1]]);
        let a = centroid(&reference, 2, bg, p0, 9);
        let b = centroid(&frame, 2, bg, p1, 9);
        let du = [
            (b[0] - a[0]) * s.camera.mm_per_px,
            (b[1] - a[1]) * s.camera.mm_per_px,
        ];
        worst = worst.max((du[0] - u[0]).abs()).max((du[1] - u[1]).abs());
    }
    assert!(
        worst / s.camera.mm_per_px < 3.5e-3,
        "tracked vs truth: {} px",
        worst / s.camera.mm_per_px
    );
}

#[test]
fn sim_render_writes_8_bit_frames_when_the_scene_quantizes() {
    let dir = tempfile::tempdir().unwrap();
    let o = run_cli(&scenes_dir().join("table1_shift.toml"), dir.path());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let img = image::open(dir.path().join("frame_000.png")).unwrap();
    assert!(matches!(img, image::DynamicImage::ImageRgb8(_)));
    let s = paper_sensor();
    let frames = read_displacements(&dir.path().join("markers.csv"), &s).unwrap();
    // The truth of a pure shift: every marker moved by exactly 3 px = 0.15 mm along x.
    for r in &frames[0].records {
        let u = r.u_mm.unwrap();
        assert!((u[0] - 0.15).abs() < 1e-12 && u[1].abs() < 1e-12, "{u:?}");
    }
}

#[test]
fn sim_render_reports_a_bad_scene_without_panicking() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("bad.toml");
    std::fs::write(&p, BASE.replace("normal_force_gf", "force")).unwrap();
    let o = run_cli(&p, &dir.path().join("out"));
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("bad.toml") && err.contains("force"), "{err}");
}

#[test]
fn two_blur_entries_compose_like_one_with_added_variances() {
    let one = through(
        vec![Effect::Blur {
            sigma_px: vec![1.0, 0.0],
        }],
        1,
    )
    .0;
    let split = std::f64::consts::FRAC_1_SQRT_2;
    let two = through(
        vec![
            Effect::Blur {
                sigma_px: vec![split, 0.0],
            },
            Effect::Blur {
                sigma_px: vec![split, 0.0],
            },
        ],
        1,
    )
    .0;
    assert!(max_abs_diff(&one, &two) < 1e-5);
}

#[test]
fn large_motion_scene_moves_markers_over_40_px_in_small_steps() {
    let sc = Scene::from_path(scenes_dir().join("large_motion.toml")).unwrap();
    let mut sim = Simulation::from_scene(&sc);
    let mut f = sim.blank_frame();
    let mm_per_px = sc.sensor.camera.mm_per_px;
    let mut prev = vec![0.0; 2 * sim.markers().len()];
    let (mut max_total, mut max_step) = (0.0f64, 0.0f64);
    for k in 1..=sc.frames {
        let t = sim
            .render_load(&sc.frame_load(k), k as u64, &mut f)
            .unwrap();
        for m in 0..sim.markers().len() {
            let u = [t.elastic_u_mm[2 * m], t.elastic_u_mm[2 * m + 1]];
            let d = [u[0] - prev[2 * m], u[1] - prev[2 * m + 1]];
            max_total = max_total.max(u[0].hypot(u[1]) / mm_per_px);
            max_step = max_step.max(d[0].hypot(d[1]) / mm_per_px);
        }
        prev = t.elastic_u_mm;
    }
    assert!(max_total >= 40.0, "largest motion {max_total} px");
    assert!(max_step <= 6.0, "largest frame-to-frame step {max_step} px");
}
