//! Tracking on real camera frames of real sensors (issue 19, part 5): the TacTip taps
//! with the robot's pose, and the FOTS GelSight pair with that project's own
//! integer-pixel tracks. The frames are read from `../shared/real_frames/` (see its
//! README; CI has `../shared` beside the clone) and never copied into the repository.

use std::path::PathBuf;

use tactbench::sensor::Sensor;
use tactbench::vision::{
    detect, load_frame, DetectConfig, Frame, MarkerStatus, Reference, StatusCounts, TrackConfig,
    TrackMode, Tracker,
};

fn real(rel: &str) -> PathBuf {
    let p = crate::util::real_frames_dir().join(rel);
    assert!(
        p.exists(),
        "{}: the real frames are expected in ../shared/real_frames beside the clone",
        p.display()
    );
    p
}

/// A one-layer sensor without a marker grid: the layout is what the reference shows.
fn sensor(color: &str, width: u32, height: u32, mm_per_px: f64, roi: &str) -> Sensor {
    let text = format!(
        r#"
[elastomer]
young_modulus_kpa = 1000.0
poisson_ratio = 0.5
thickness_mm = 40.0

[[layers]]
name = "pins"
color = "{color}"
depth_mm = 3.0

[force_grid]
nx = 4
ny = 4
pitch_mm = 2.0
origin_mm = [0.0, 0.0]

[camera]
mm_per_px = {mm_per_px}
origin_px = [0.0, 0.0]
width_px = {width}
height_px = {height}
{roi}
"#
    );
    Sensor::from_toml_str(&text, "real.toml").expect("sensor")
}

fn tactip_sensor() -> Sensor {
    sensor(
        "bright",
        640,
        480,
        0.05,
        "roi_px = { center = [300.0, 245.0], radius = 205.0 }",
    )
}

fn frame(s: &Sensor, rel: &str) -> Frame {
    load_frame(&real(rel), &s.camera).expect("frame")
}

fn reference(s: &Sensor, f: &Frame) -> Reference {
    detect(&f.view(), s, &DetectConfig::default()).expect("markers")
}

fn per_window() -> TrackConfig {
    TrackConfig {
        mode: TrackMode::PerWindow,
        ..TrackConfig::default()
    }
}

/// Least-squares line `y = a x + b`; returns R².
fn r2(x: &[f64], y: &[f64]) -> f64 {
    let n = x.len() as f64;
    let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let sxy: f64 = x.iter().zip(y).map(|(a, b)| (a - mx) * (b - my)).sum();
    let sxx: f64 = x.iter().map(|a| (a - mx).powi(2)).sum();
    let syy: f64 = y.iter().map(|b| (b - my).powi(2)).sum();
    sxy * sxy / (sxx * syy)
}

/// `pose_4`, `pose_5` (tilt about x and y, degrees) of `image_1..10.png`.
fn tactip_poses() -> Vec<[f64; 2]> {
    let text = std::fs::read_to_string(real("tactip/targets.csv")).unwrap();
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| head.iter().position(|h| *h == name).unwrap();
    // The obj_pose column is a quoted list with commas: count from the end.
    let (c4, c5, n) = (col("pose_4"), col("pose_5"), head.len());
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            let at = |c: usize| f[f.len() - (n - c)].parse::<f64>().unwrap();
            [at(c4), at(c5)]
        })
        .collect()
}

/// Issue 19: the mean pin displacement between consecutive TacTip taps follows the
/// robot's tilt change (mean dx against Δpose_5, mean dy against Δpose_4, nine pairs).
/// Baselines from the issue: the old tracker R² 0.03 / 0.08; a 30-line OpenCV script
/// 0.62 / 0.61 (ours, `tests/opencv_ref/track_ref.py`: 0.65 / 0.79). Measured here:
/// R² 0.643 / 0.664, median ok share 0.964 (OpenCV baseline 92 %); taps 7→8 and 8→9
/// keep only 193 and 231 of 335 pins ok (lost, never wrong).
#[test]
fn tactip_mean_pin_displacement_follows_the_robot_tilt() {
    let s = tactip_sensor();
    let poses = tactip_poses();
    let frames: Vec<Frame> = (1..=10)
        .map(|k| frame(&s, &format!("tactip/image_{k}.png")))
        .collect();
    let (mut dx, mut dy, mut d4, mut d5, mut share) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for k in 0..9 {
        let r = reference(&s, &frames[k]);
        let n = r.markers.len();
        let mut t = Tracker::new(r, per_window());
        let tracks = t.track(&frames[k + 1].view()).unwrap();
        let ok: Vec<_> = tracks
            .iter()
            .filter(|t| t.status == MarkerStatus::Ok)
            .collect();
        let c = StatusCounts::of(tracks, 0);
        eprintln!("tap {} -> {}: {n} pins, {c:?}", k + 1, k + 2);
        dx.push(ok.iter().map(|t| t.displacement_px[0]).sum::<f64>() / ok.len() as f64);
        dy.push(ok.iter().map(|t| t.displacement_px[1]).sum::<f64>() / ok.len() as f64);
        d4.push(poses[k + 1][0] - poses[k][0]);
        d5.push(poses[k + 1][1] - poses[k][1]);
        share.push(ok.len() as f64 / n as f64);
    }
    let (rx, ry) = (r2(&d5, &dx), r2(&d4, &dy));
    share.sort_by(f64::total_cmp);
    let median_share = share[share.len() / 2];
    eprintln!("R² dx~Δpose_5 {rx:.3}, dy~Δpose_4 {ry:.3}; median ok share {median_share:.3}");
    assert!(rx >= 0.58 && ry >= 0.58, "R² {rx} / {ry}");
    assert!(median_share >= 0.93, "median ok share {median_share}");
}

/// What tracking the TacTip taps `image_2..10.png` in order against `image_1.png`
/// as the one reference (independent contacts, issue 29 item 5) gives with `config`.
struct IndependentTaps {
    /// Pins in the reference.
    pins: usize,
    /// Per frame: ok pins.
    ok: Vec<usize>,
    /// Per frame: the ok pins' displacements (reference order; `None` when not ok).
    u: Vec<Vec<Option<[f64; 2]>>>,
    /// Largest distance of an ok pin's displacement from the median of its ok
    /// neighbours' (those within 1.6 of its nearest-pin distance at rest), in units
    /// of that distance (its local pitch).
    worst_swap: f64,
    /// Per frame: that largest distance.
    swap_per_frame: Vec<f64>,
    /// Largest ok displacement, px.
    largest_px: f64,
    /// R² of the mean ok dx against pose_5 − pose_5(image_1), of the mean dy against
    /// pose_4 − pose_4(image_1).
    r2: [f64; 2],
}

fn tactip_independent_taps(config: TrackConfig) -> IndependentTaps {
    let s = tactip_sensor();
    let poses = tactip_poses();
    let frames: Vec<Frame> = (1..=10)
        .map(|k| frame(&s, &format!("tactip/image_{k}.png")))
        .collect();
    let r = reference(&s, &frames[0]);
    let at: Vec<[f64; 2]> = r.markers.iter().map(|m| m.centroid_px).collect();
    let dist = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).hypot(a[1] - b[1]);
    // Local pitch and neighbours at rest, computed here (not the tracker's lists).
    let pitch: Vec<f64> = (0..at.len())
        .map(|i| {
            (0..at.len())
                .filter(|&j| j != i)
                .map(|j| dist(at[i], at[j]))
                .fold(f64::INFINITY, f64::min)
        })
        .collect();
    let near: Vec<Vec<usize>> = (0..at.len())
        .map(|i| {
            (0..at.len())
                .filter(|&j| j != i && dist(at[i], at[j]) <= 1.6 * pitch[i])
                .collect()
        })
        .collect();
    let mut t = Tracker::new(r, config);
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        let n = v.len();
        0.5 * (v[(n - 1) / 2] + v[n / 2])
    };
    let (mut ok, mut u, mut mx, mut my, mut d4, mut d5) =
        (vec![], vec![], vec![], vec![], vec![], vec![]);
    let (mut worst_swap, mut largest_px) = (0.0f64, 0.0f64);
    let mut swap_per_frame = Vec::new();
    for (k, f) in frames.iter().enumerate().skip(1) {
        let mut frame_swap = 0.0f64;
        let tracks = t.track(&f.view()).unwrap();
        let uk: Vec<Option<[f64; 2]>> = tracks
            .iter()
            .map(|t| (t.status == MarkerStatus::Ok).then_some(t.displacement_px))
            .collect();
        for (i, ui) in uk.iter().enumerate() {
            let Some(ui) = ui else { continue };
            largest_px = largest_px.max(ui[0].hypot(ui[1]));
            let nb: Vec<[f64; 2]> = near[i].iter().filter_map(|&j| uk[j]).collect();
            if nb.is_empty() {
                continue;
            }
            let m = [
                median(nb.iter().map(|v| v[0]).collect()),
                median(nb.iter().map(|v| v[1]).collect()),
            ];
            frame_swap = frame_swap.max(dist(*ui, m) / pitch[i]);
        }
        worst_swap = worst_swap.max(frame_swap);
        swap_per_frame.push(frame_swap);
        let good: Vec<[f64; 2]> = uk.iter().flatten().copied().collect();
        let n = good.len() as f64;
        mx.push(good.iter().map(|v| v[0]).sum::<f64>() / n);
        my.push(good.iter().map(|v| v[1]).sum::<f64>() / n);
        d4.push(poses[k][0] - poses[0][0]);
        d5.push(poses[k][1] - poses[0][1]);
        ok.push(good.len());
        u.push(uk);
    }
    IndependentTaps {
        pins: at.len(),
        ok,
        u,
        worst_swap,
        swap_per_frame,
        largest_px,
        r2: [r2(&d5, &mx), r2(&d4, &my)],
    }
}

/// Issue 29 item 5: the TacTip taps are independent contacts (a robot tap at another
/// pose each), tracked in order against `image_1.png` as the one reference. The
/// default mode (frame to frame) followed each pin from its position in the previous,
/// unrelated tap plus that tap's "velocity": 4–37 pins ok per frame, moved 29–119 px
/// where the pitch is 16 px (on neighbours' blobs). It now re-acquires from the
/// reference what the last positions do not explain. Measured (per window / default):
/// ok 298/298, 298/304, 294/298, 285/304, 314/325, 302/322, 216/227, 330/331,
/// 305/321 of 335 pins for image_2..10; no ok pin farther than 0.499 pitch from its
/// ok neighbours' median displacement (per window 0.498); largest ok displacement
/// 17.6 px (13.0). Against `image_1` (itself a tap at 8.8°, 12.7° tilt) the mean
/// displacement carries no pose signal with either mode on these nine taps (R² of
/// mean dx against Δpose_5, dy against Δpose_4: per window 0.011 / 0.082, default
/// 0.220 / 0.000): tilt changes of up to 27° move pins beyond half a pitch, where
/// no reference-based window reaches; printed, not asserted.
#[test]
fn tactip_independent_taps_against_image_1_tracked_by_default_as_per_window() {
    let pw = tactip_independent_taps(per_window());
    let def = tactip_independent_taps(TrackConfig::default());
    eprintln!(
        "per window: {} pins, ok {:?}, worst swap {:.3} pitch, largest {:.1} px, R² {:.3} / {:.3}",
        pw.pins, pw.ok, pw.worst_swap, pw.largest_px, pw.r2[0], pw.r2[1]
    );
    eprintln!(
        "default:    {} pins, ok {:?}, worst swap {:.3} pitch, largest {:.1} px, R² {:.3} / {:.3}",
        def.pins, def.ok, def.worst_swap, def.largest_px, def.r2[0], def.r2[1]
    );
    // Where both report a pin ok they agree (the same blob, the same window).
    let mut worst_diff = 0.0f64;
    for (k, (a, b)) in def.u.iter().zip(&pw.u).enumerate() {
        let mut differ = 0;
        for (a, b) in a.iter().zip(b) {
            if let (Some(a), Some(b)) = (a, b) {
                let d = (a[0] - b[0]).hypot(a[1] - b[1]);
                worst_diff = worst_diff.max(d);
                differ += usize::from(d > 0.01);
            }
        }
        eprintln!(
            "image_{}: ok {} / {} (default / per window), {differ} ok in both differ, worst swap {:.3} / {:.3} pitch",
            k + 2,
            def.ok[k],
            pw.ok[k],
            def.swap_per_frame[k],
            pw.swap_per_frame[k]
        );
    }
    eprintln!("largest |default − per window| over pins ok in both: {worst_diff:.4} px");
    for (k, (&a, &b)) in def.ok.iter().zip(&pw.ok).enumerate() {
        assert!(a >= b, "image_{}: {a} ok by default, {b} per window", k + 2);
    }
    assert!(
        def.worst_swap <= 0.5,
        "an ok pin {} pitches off its neighbours",
        def.worst_swap
    );
}

/// `(Mx + dx, My + dy)` and `(dx, dy)` per row of a FOTS CSV (whole pixels; the same
/// markers in the same order in `0.csv` and `1.csv`).
fn fots_rows(rel: &str) -> Vec<([f64; 2], [f64; 2])> {
    let text = std::fs::read_to_string(real(rel)).unwrap();
    text.lines()
        .skip(1)
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|x| x.trim().parse().unwrap()).collect();
            ([v[0] + v[2], v[1] + v[3]], [v[2], v[3]])
        })
        .collect()
}

/// Sorted absolute values' quantile (nearest rank).
fn quantile(sorted: &[f64], q: f64) -> f64 {
    let k = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len()) - 1;
    sorted[k]
}

/// Issue 19: the FOTS GelSight pair (`gelsight_fots/0.png` → `1.png`, dark dots on a
/// white gel under coloured LEDs, a dilation with displacements up to 12.2 px, 0.45
/// of the 27 px spacing) tracked with `color = "dark"`, no grid, from `0.png` as the
/// reference, against the FOTS project's own Lucas–Kanade tracks: each marker's
/// displacement should equal `(dx, dy)₁ − (dx, dy)₀` of `1.csv` and `0.csv`. Markers are
/// matched by position (`(Mx + dx₀, My + dy₀)` is the marker's position in frame 0).
/// Both CSVs are rounded to whole pixels: their difference alone scatters by a
/// median |error| of 0.51 px and a 95th percentile of 0.94 px (two uniform roundings
/// per axis), so that is the best agreement possible.
///
/// Measured (both modes give the same): 68 ok, 15 outlier, 16 lost, 0 merged of 99.
/// * ok: |ours − FOTS| median 0.504 px, p95 0.862 px, max 1.087 px (the rounding
///   limit);
/// * ok + outlier (83 found): median 0.504 px, p95 0.862 px; the one beyond 1.1 px
///   is the dot at (141, 174) px with a specular highlight that changes shape between
///   the frames (ours +9.4 px in y, FOTS +6; its neighbours above and below moved
///   11 and 6 px): flagged `outlier`, as are 14 dots stretched or shaded under the
///   indentation (signal 0.83–1.24 × their neighbours'), whose displacements agree
///   with FOTS to 1.1 px: not trusted although right (the appearance check cannot
///   tell a stretched dot from a covered one);
/// * lost: the 16 dots whose dot (radius 6.2 px + 1 px) crosses the image edge in
///   frame 1: the right column (cut by the edge) and the bottom row (moved 2–5 px
///   down towards the edge). Before windows cut by the edge were measured (their
///   part inside the image, `window::clipped`), 19 were lost and 65 ok: the three
///   dots whose window, but not dot, crosses the edge are now measured, and the
///   bounds below hold with them.
#[test]
fn fots_pair_displacements_agree_with_the_fots_tracker_to_about_a_pixel() {
    let s = sensor("dark", 320, 240, 1.0 / 19.58, "");
    let f0 = frame(&s, "gelsight_fots/0.png");
    let f1 = frame(&s, "gelsight_fots/1.png");
    let r = reference(&s, &f0);
    assert_eq!(r.markers.len(), 99);
    let rows0 = fots_rows("gelsight_fots/0.csv");
    let rows1 = fots_rows("gelsight_fots/1.csv");
    assert_eq!((rows0.len(), rows1.len()), (99, 99));
    for mode in [TrackMode::PerWindow, TrackMode::FrameToFrame] {
        let mut t = Tracker::new(
            r.clone(),
            TrackConfig {
                mode,
                ..TrackConfig::default()
            },
        );
        let tracks = t.track(&f1.view()).unwrap().to_vec();
        let c = StatusCounts::of(&tracks, 0);
        // |ours − FOTS| of the ok markers and of every found (ok or outlier) marker.
        let (mut ok, mut found) = (Vec::new(), Vec::new());
        let mut largest: f64 = 0.0;
        let mut matched = vec![false; r.markers.len()];
        for ((p0, d0), (_, d1)) in rows0.iter().zip(&rows1) {
            // Our reference marker nearest to FOTS's frame-0 position.
            let (k, dist) = r
                .markers
                .iter()
                .enumerate()
                .map(|(k, m)| {
                    (
                        k,
                        (m.centroid_px[0] - p0[0]).hypot(m.centroid_px[1] - p0[1]),
                    )
                })
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap();
            assert!(dist < 7.0, "FOTS marker at {p0:?}: ours {dist:.1} px away");
            assert!(!matched[k], "two FOTS markers on our marker {k}");
            matched[k] = true;
            let theirs = [d1[0] - d0[0], d1[1] - d0[1]];
            largest = largest.max(theirs[0].hypot(theirs[1]));
            let tr = &tracks[k];
            let at1 = [p0[0] + theirs[0], p0[1] + theirs[1]];
            match tr.status {
                MarkerStatus::Lost => {
                    // Only where the dot (its radius, 6.2 px here, + 1 px, from the
                    // pixel edge at ±½) crosses the image edge, 1 px slack for rounding.
                    let edge = at1[0].min(319.0 - at1[0]).min(at1[1]).min(239.0 - at1[1]);
                    let reach = r.layers[0].marker_radius_px + 1.0 - 0.5 + 1.0;
                    assert!(
                        edge < reach,
                        "{mode:?}: marker at {p0:?} lost {edge:.1} px from the edge"
                    );
                    continue;
                }
                MarkerStatus::Merged => panic!("{mode:?}: marker at {p0:?} merged"),
                MarkerStatus::Ok | MarkerStatus::Outlier => {}
            }
            let e = (tr.displacement_px[0] - theirs[0]).hypot(tr.displacement_px[1] - theirs[1]);
            if tr.status == MarkerStatus::Ok {
                ok.push(e);
            }
            found.push(e);
        }
        ok.sort_by(f64::total_cmp);
        found.sort_by(f64::total_cmp);
        let stats = |v: &[f64]| (quantile(v, 0.5), quantile(v, 0.95), v[v.len() - 1]);
        let (m_ok, p_ok, w_ok) = stats(&ok);
        let (m_all, p_all, _) = stats(&found);
        let what = format!(
            "FOTS 0 -> 1, {mode:?}: {c:?}; largest FOTS displacement {largest:.1} px; |ours − FOTS| over {} ok: median {m_ok:.3} px, p95 {p_ok:.3} px, max {w_ok:.3} px; over {} found: median {m_all:.3} px, p95 {p_all:.3} px",
            ok.len(),
            found.len()
        );
        eprintln!("{what}");
        assert!(found.len() >= 83 && ok.len() >= 68, "{what}");
        assert!(m_ok <= 0.6 && p_ok <= 1.0 && w_ok <= 1.25, "{what}");
        assert!(m_all <= 0.6 && p_all <= 1.0, "{what}");
        // Every disagreement beyond the rounding is flagged, never reported ok.
        assert!(found.iter().filter(|&&e| e > 1.25).count() <= 1, "{what}");
    }
}

/// Runs the OpenCV reference tracker `tests/opencv_ref/track_ref.py` (interpreter:
/// `TACTBENCH_PYTHON`, default `python3`) from `reference` to `frame`: per reference
/// blob its position and, unless lost, its position in the frame, px.
fn opencv_track(
    appearance: &str,
    roi: Option<[f64; 3]>,
    reference: &str,
    frame: &str,
) -> Vec<([f64; 2], Option<[f64; 2]>)> {
    let python = std::env::var("TACTBENCH_PYTHON").unwrap_or_else(|_| "python3".into());
    let mut cmd = std::process::Command::new(python);
    cmd.arg(crate::util::root("tests/opencv_ref/track_ref.py"))
        .args(["--appearance", appearance]);
    if let Some([x, y, r]) = roi {
        cmd.arg("--roi")
            .args([x.to_string(), y.to_string(), r.to_string()]);
    }
    let out = cmd
        .arg(real(reference))
        .arg(real(frame))
        .output()
        .expect("run python");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.rsplitn(6, ',').collect();
            // Reversed: status, y, x, y_ref, x_ref, frame.
            let v = |k: usize| f[k].parse::<f64>().unwrap();
            let at = (f[0] == "ok").then(|| [v(2), v(1)]);
            ([v(4), v(3)], at)
        })
        .collect()
}

/// The OpenCV reference tracker side by side with ours (issue 19): on the FOTS pair
/// against the FOTS CSVs, and on the nine TacTip tap pairs against the robot's
/// tilt. Printed per case: markers matched, |displacement − FOTS| median / p95 /
/// max, R², ok shares. Run with
/// `pip install numpy opencv-python-headless` and
/// `cargo test --test integration opencv_tracker -- --ignored --nocapture`.
#[test]
#[ignore = "needs python3 with opencv-python-headless and numpy"]
fn opencv_tracker_side_by_side_on_the_fots_pair_and_the_tactip_taps() {
    // FOTS: both trackers against the FOTS CSVs, markers matched by position.
    let s = sensor("dark", 320, 240, 1.0 / 19.58, "");
    let r = reference(&s, &frame(&s, "gelsight_fots/0.png"));
    let mut t = Tracker::new(r.clone(), per_window());
    let ours = t
        .track(&frame(&s, "gelsight_fots/1.png").view())
        .unwrap()
        .to_vec();
    let theirs = opencv_track("dark", None, "gelsight_fots/0.png", "gelsight_fots/1.png");
    let rows0 = fots_rows("gelsight_fots/0.csv");
    let rows1 = fots_rows("gelsight_fots/1.csv");
    let (mut e_ours, mut e_cv, mut e_both) = (Vec::new(), Vec::new(), Vec::new());
    for ((p0, d0), (_, d1)) in rows0.iter().zip(&rows1) {
        let fots = [d1[0] - d0[0], d1[1] - d0[1]];
        let near = |q: [f64; 2]| (q[0] - p0[0]).hypot(q[1] - p0[1]);
        let k = (0..r.markers.len())
            .min_by(|&a, &b| {
                near(r.markers[a].centroid_px).total_cmp(&near(r.markers[b].centroid_px))
            })
            .unwrap();
        let mine = (ours[k].status == MarkerStatus::Ok).then_some(ours[k].displacement_px);
        let cv = theirs
            .iter()
            .filter(|(q, _)| near(*q) < 7.0)
            .min_by(|a, b| near(a.0).total_cmp(&near(b.0)))
            .and_then(|(q, at)| at.map(|a| [a[0] - q[0], a[1] - q[1]]));
        let err = |u: [f64; 2], v: [f64; 2]| (u[0] - v[0]).hypot(u[1] - v[1]);
        if let Some(u) = mine {
            e_ours.push(err(u, fots));
        }
        if let Some(u) = cv {
            e_cv.push(err(u, fots));
        }
        if let (Some(u), Some(v)) = (mine, cv) {
            e_both.push(err(u, v));
        }
    }
    let stats = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        format!(
            "{} markers, median {:.3} px, p95 {:.3} px, max {:.3} px",
            v.len(),
            quantile(v, 0.5),
            quantile(v, 0.95),
            v[v.len() - 1]
        )
    };
    eprintln!("FOTS 0 -> 1, |ours - FOTS|: {}", stats(&mut e_ours));
    eprintln!("FOTS 0 -> 1, |OpenCV - FOTS|: {}", stats(&mut e_cv));
    eprintln!(
        "FOTS 0 -> 1, |ours - OpenCV| (ok in both): {}",
        stats(&mut e_both)
    );
    assert!(quantile(&e_both, 0.5) <= 0.5, "ours and OpenCV disagree");

    // TacTip: mean displacement of each tracker's ok pins against the tilt change.
    let s = tactip_sensor();
    let poses = tactip_poses();
    let (mut ox, mut oy, mut cx, mut cy, mut d4, mut d5) =
        (vec![], vec![], vec![], vec![], vec![], vec![]);
    for k in 1..=9 {
        let (a, b) = (
            format!("tactip/image_{k}.png"),
            format!("tactip/image_{}.png", k + 1),
        );
        let r = reference(&s, &frame(&s, &a));
        let n = r.markers.len();
        let mut t = Tracker::new(r, per_window());
        let tracks = t.track(&frame(&s, &b).view()).unwrap();
        let ok: Vec<[f64; 2]> = tracks
            .iter()
            .filter(|t| t.status == MarkerStatus::Ok)
            .map(|t| t.displacement_px)
            .collect();
        let cv: Vec<[f64; 2]> = opencv_track("bright", Some([300.0, 245.0, 205.0]), &a, &b)
            .iter()
            .filter_map(|(q, at)| at.map(|p| [p[0] - q[0], p[1] - q[1]]))
            .collect();
        let n_cv = opencv_track("bright", Some([300.0, 245.0, 205.0]), &a, &b).len();
        let mean = |v: &[[f64; 2]], c: usize| v.iter().map(|u| u[c]).sum::<f64>() / v.len() as f64;
        eprintln!(
            "tap {k} -> {}: ours {}/{n} ok, mean ({:.2}, {:.2}) px; OpenCV {}/{n_cv} ok, mean ({:.2}, {:.2}) px",
            k + 1,
            ok.len(),
            mean(&ok, 0),
            mean(&ok, 1),
            cv.len(),
            mean(&cv, 0),
            mean(&cv, 1)
        );
        ox.push(mean(&ok, 0));
        oy.push(mean(&ok, 1));
        cx.push(mean(&cv, 0));
        cy.push(mean(&cv, 1));
        d4.push(poses[k][0] - poses[k - 1][0]);
        d5.push(poses[k][1] - poses[k - 1][1]);
    }
    let (rx, ry, cvx, cvy) = (r2(&d5, &ox), r2(&d4, &oy), r2(&d5, &cx), r2(&d4, &cy));
    eprintln!(
        "TacTip R² dx~Δpose_5 / dy~Δpose_4: ours {rx:.3} / {ry:.3}, OpenCV {cvx:.3} / {cvy:.3}"
    );
    assert!(rx >= 0.58 && ry >= 0.58 && cvx > 0.0 && cvy > 0.0);
}
