//! The tracker on real camera frames of real sensors (`../shared/real_frames/`, see
//! its README; never copied into the repository): every marker found in the
//! reference of each kind of sensor, with the marker counts established by eye once
//! (stated per test), and the refusals of `sensor init`.
//!
//! The frames live beside the clone (CI has them); without the directory every test
//! here prints why it did not run and passes.
//!
//! `opencv_reference_agrees_on_real_frames` (ignored) compares the detections with an
//! independent OpenCV detector, `tests/opencv_ref/detect.py`:
//! `pip install opencv-python-headless numpy`, then
//! `cargo test --test tests vision_real -- --ignored` (`TACTBENCH_PYTHON` picks the
//! interpreter, default `python3`).

use std::path::{Path, PathBuf};
use std::process::Command;

use tactbench::sensor::{MarkerColor, Roi, Sensor};
use tactbench::vision::onboard::{sensor_draft, DraftError, DraftOptions, Scale};
use tactbench::vision::{detect, DetectConfig, Frame, Reference};

use crate::util::{self, arg as p};

/// `../shared/real_frames`, or `None` (with a message) when it is absent.
fn real_frames() -> Option<PathBuf> {
    let dir = util::real_frames_dir();
    if dir.is_dir() {
        Some(dir)
    } else {
        eprintln!(
            "skipped: {} is absent (real camera frames; CI has ../shared beside the clone)",
            dir.display()
        );
        None
    }
}

/// A one-layer, layout-free sensor file of the frame's size.
fn sensor_toml(color: &str, width: u32, height: u32, roi: Option<&str>) -> String {
    format!(
        "[elastomer]\nyoung_modulus_kpa = 100.0\npoisson_ratio = 0.5\nthickness_mm = 4.0\n\n\
         [[layers]]\nname = \"markers\"\ncolor = \"{color}\"\ndepth_mm = 1.0\n\n\
         [force_grid]\nnx = 4\nny = 3\npitch_mm = 2.0\norigin_mm = [0.0, 0.0]\n\n\
         [camera]\nmm_per_px = 0.05\norigin_px = [0.0, 0.0]\nwidth_px = {width}\nheight_px = {height}\n{}",
        roi.map(|r| format!("roi_px = {r}\n")).unwrap_or_default()
    )
}

fn reference(path: &Path, color: &str, roi: Option<&str>) -> Reference {
    let frame = Frame::open(path).unwrap();
    let v = frame.view();
    let sensor = Sensor::from_toml_str(
        &sensor_toml(color, v.width_px(), v.height_px(), roi),
        "real.toml",
    )
    .unwrap();
    detect(&v, &sensor, &DetectConfig::default()).unwrap()
}

fn centroids(r: &Reference) -> Vec<[f64; 2]> {
    r.markers.iter().map(|m| m.centroid_px).collect()
}

/// For each expected position, the distance to the nearest detection, px.
fn nearest(expected: &[[f64; 2]], found: &[[f64; 2]]) -> Vec<f64> {
    expected
        .iter()
        .map(|e| {
            found
                .iter()
                .map(|f| (f[0] - e[0]).hypot(f[1] - e[1]))
                .fold(f64::INFINITY, f64::min)
        })
        .collect()
}

/// `Mx + dx, My + dy` of a FOTS CSV: where that project's tracker put each marker in
/// the frame (whole pixels).
fn fots_positions(csv: &Path) -> Vec<[f64; 2]> {
    let text = std::fs::read_to_string(csv).unwrap();
    text.lines()
        .skip(1)
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|x| x.trim().parse().unwrap()).collect();
            [v[0] + v[2], v[1] + v[3]]
        })
        .collect()
}

/// GelSight (FOTS) dark dots on a white gel under coloured LEDs (a strong colour
/// gradient, red-blue-green across the frame): 11 columns × 9 rows = 99 dots whose
/// centres lie in the 320×240 frame, counted by eye in both frames (the right column
/// is cut by the edge; slivers of a 12th column at the left edge, centres outside the
/// frame, are not markers to find). Each of the 99 positions of the FOTS project's own
/// tracker (rounded to whole pixels, and off by up to 6 px on dots with a specular
/// highlight, checked by eye) has one of ours within 7 px (a quarter pitch), the
/// median distance is below 1 px, and nothing else is found.
#[test]
fn gelsight_dark_dots_under_a_colour_gradient_are_all_found() {
    let Some(dir) = real_frames() else { return };
    for k in 0..2 {
        let r = reference(&dir.join(format!("gelsight_fots/{k}.png")), "dark", None);
        let found = centroids(&r);
        assert_eq!(found.len(), 99, "frame {k}: {} dots found", found.len());
        let expected = fots_positions(&dir.join(format!("gelsight_fots/{k}.csv")));
        assert_eq!(expected.len(), 99);
        let mut d = nearest(&expected, &found);
        let worst = d.iter().cloned().fold(0.0, f64::max);
        assert!(
            worst < 7.0,
            "frame {k}: a FOTS marker is {worst:.2} px from ours"
        );
        d.sort_by(f64::total_cmp);
        assert!(d[49] < 1.0, "frame {k}: median distance {:.2} px", d[49]);
    }
}

/// The same gel's lighting without markers: no dark marker, so `sensor init` refuses
/// with the reason, and the detector finds nothing.
#[test]
fn gelsight_background_without_markers_gives_no_marker_and_a_refusal() {
    let Some(dir) = real_frames() else { return };
    let path = dir.join("gelsight_fots/background_no_markers.png");
    let frame = Frame::open(&path).unwrap();
    let options = DraftOptions {
        color: MarkerColor::Dark,
        roi_px: None,
        scale: Scale::Unknown,
    };
    let err = sensor_draft(&frame.view(), &options, &path).unwrap_err();
    assert!(matches!(err, DraftError::NoMarkers { .. }), "{err}");
    let text = err.to_string();
    assert!(
        text.contains("background_no_markers.png") && text.contains("no dark marker"),
        "{text}"
    );
}

/// GelSight bright dots on a striped, colour-graded background (1280×720): an 8 × 8
/// grid, 64 dots counted by eye. Every dot is found (a detection within 14 px of the
/// expected point: the table gives one y per row, and a row's dots spread ±9 px in y), and nothing else: not the stripes, not the
/// scratch near (710, 573) nor the speck at (769, 29).
#[test]
fn gelsight_bright_dots_on_stripes_are_all_found() {
    let Some(dir) = real_frames() else { return };
    let r = reference(
        &dir.join("gelsight_bright/raw_1280x720.png"),
        "bright",
        None,
    );
    let found = centroids(&r);
    // The grid is slightly rotated and distorted: columns drift right by ~5 px over
    // the rows on the left and ~20 px on the right. The dots' centres (whole px) as the
    // OpenCV detector of `tests/opencv_ref` gives them, checked one by one on the
    // image: per row its y and the eight x.
    let rows: [(f64, [f64; 8]); 8] = [
        (
            61.0,
            [321.0, 408.0, 495.0, 581.0, 669.0, 754.0, 842.0, 929.0],
        ),
        (
            148.0,
            [322.0, 409.0, 495.0, 582.0, 669.0, 756.0, 843.0, 931.0],
        ),
        (
            233.0,
            [321.0, 408.0, 495.0, 582.0, 670.0, 758.0, 846.0, 934.0],
        ),
        (
            318.0,
            [322.0, 408.0, 496.0, 582.0, 672.0, 760.0, 849.0, 937.0],
        ),
        (
            403.0,
            [322.0, 408.0, 496.0, 584.0, 674.0, 763.0, 851.0, 939.0],
        ),
        (
            487.0,
            [321.0, 409.0, 497.0, 585.0, 675.0, 764.0, 853.0, 943.0],
        ),
        (
            573.0,
            [322.0, 411.0, 499.0, 588.0, 678.0, 768.0, 857.0, 946.0],
        ),
        (
            660.0,
            [326.0, 414.0, 503.0, 591.0, 682.0, 771.0, 861.0, 949.0],
        ),
    ];
    let expected: Vec<[f64; 2]> = rows
        .iter()
        .flat_map(|(y, xs)| xs.iter().map(move |&x| [x, *y]))
        .collect();
    let d = nearest(&expected, &found);
    let missed: Vec<[f64; 2]> = expected
        .iter()
        .zip(&d)
        .filter(|(_, &d)| d > 14.0)
        .map(|(e, _)| *e)
        .collect();
    assert!(missed.is_empty(), "dots not found: {missed:?}");
    assert_eq!(found.len(), 64, "found {} blobs: {found:?}", found.len());
}

/// TacTip pins (white pins on a black skin, hexagonal packing, LEDs around the
/// circular field): 331 pins inside the field of `image_1.png`, counted by eye on an
/// annotated enlargement (the outermost ring lies ~172 px from the field's centre
/// near (304, 250); the small grey speck at (222, 193), between three pins and off
/// the lattice, is not a pin). With the ROI `circle (304, 250) r 182` the LED ring and
/// its reflections at the skin's rim (186–200 px from the centre) are ignored and
/// every pin is found.
#[test]
fn tactip_pins_inside_the_field_are_all_found_and_the_leds_ignored() {
    let Some(dir) = real_frames() else { return };
    let path = dir.join("tactip/image_1.png");
    let roi = "{ center = [304.0, 250.0], radius = 182.0 }";
    let r = reference(&path, "bright", Some(roi));
    let found = centroids(&r);
    assert_eq!(found.len(), 331, "found {} pins", found.len());
    let centre = [304.0, 250.0];
    let far = found
        .iter()
        .map(|p| (p[0] - centre[0]).hypot(p[1] - centre[1]))
        .fold(0.0, f64::max);
    assert!(
        far < 176.0,
        "a detection {far:.1} px from the centre: not a pin"
    );
    // Without the ROI the LEDs and their reflections come in too.
    let all = reference(&path, "bright", None);
    assert!(all.markers.len() > found.len());
    let roi = Roi::Circle {
        center_px: centre,
        radius_px: 182.0,
    };
    assert!(all.markers.iter().any(|m| !roi.contains(m.centroid_px)));
}

/// The OpenCV detector of `tests/opencv_ref/detect.py` (black-hat / top-hat, Otsu,
/// connected components) against ours on the same frames: every marker we find has an
/// OpenCV blob within 1 px on the FOTS frames and all but one pin (1.59 px) of the
/// TacTip frame (the two centroids differ in
/// definition: a thresholded component against a background-corrected window),
/// printed per frame with the counts (OpenCV also counts the slivers, the scratch, the
/// speck: see the tests above). On the striped bright frame (dots of 23 px) measured
/// with OpenCV 5.0: 52 of 64 within 1 px, median 0.46 px, max 4.72 px (4.36 px before a
/// two-cycle between windows was resolved by the better-centred window: the dot at
/// (578.2, 318.7) px sits on a stripe, where both windows are fixed points): our reference
/// centroid is refined in a window whose ring plane cannot remove the stripes (and
/// counts the dots' colour fringes), OpenCV's on a top-hat; asserted as measured
/// (a known limitation, docs/real-sensors.md).
#[test]
#[ignore = "needs python3 with opencv-python-headless and numpy"]
fn opencv_reference_agrees_on_real_frames() {
    let Some(dir) = real_frames() else { return };
    let python = std::env::var("TACTBENCH_PYTHON").unwrap_or_else(|_| "python3".into());
    let script = util::root("tests/opencv_ref/detect.py");
    // (frame, color, optional (sensor init --roi, sensor file roi_px))
    type Case<'a> = (&'a str, &'a str, Option<(&'a str, &'a str)>);
    let cases: [Case; 4] = [
        ("gelsight_fots/0.png", "dark", None),
        ("gelsight_fots/1.png", "dark", None),
        ("gelsight_bright/raw_1280x720.png", "bright", None),
        (
            "tactip/image_1.png",
            "bright",
            Some((
                "circle:304,250,182",
                "{ center = [304.0, 250.0], radius = 182.0 }",
            )),
        ),
    ];
    for (file, color, roi) in cases {
        let path = dir.join(file);
        let mut cmd = Command::new(&python);
        cmd.arg(&script).arg(&path).arg(color);
        if let Some((arg, _)) = roi {
            cmd.arg(arg);
        }
        let out = cmd.output().expect("run python");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let theirs: Vec<[f64; 2]> = String::from_utf8_lossy(&out.stdout)
            .lines()
            .map(|l| {
                let (x, y) = l.split_once(',').unwrap();
                [x.parse().unwrap(), y.parse().unwrap()]
            })
            .collect();
        let ours = centroids(&reference(&path, color, roi.map(|r| r.1)));
        let d = nearest(&ours, &theirs);
        let close = d.iter().filter(|&&d| d <= 1.0).count();
        let mut sorted = d.clone();
        sorted.sort_by(f64::total_cmp);
        eprintln!(
            "{file}: ours {}, OpenCV {}, matched within 1 px {close}; distance median {:.3} px, max {:.3} px",
            ours.len(),
            theirs.len(),
            sorted[sorted.len() / 2],
            sorted[sorted.len() - 1]
        );
        for (o, d) in ours.iter().zip(&d) {
            if *d > 1.0 {
                eprintln!(
                    "  ({:.1}, {:.1}) px: OpenCV's nearest {d:.2} px away",
                    o[0], o[1]
                );
            }
        }
        let (least, worst) = match file {
            f if f.starts_with("gelsight_bright") => (52, 4.8),
            // One pin at (368.1, 392.9) px: 1.59 px (measured).
            f if f.starts_with("tactip") => (ours.len() - 1, 1.7),
            _ => (ours.len(), 1.0),
        };
        assert!(
            close >= least && sorted[sorted.len() - 1] <= worst,
            "{file}: {close} of {} within 1 px",
            ours.len()
        );
    }
}

/// Runs `tactbench sensor init` on a real frame and returns the draft's path; fails
/// the test with the command's stderr when it does not succeed.
fn sensor_init(dir: &Path, frame: &Path, args: &[&str]) -> PathBuf {
    let out = dir.join("draft.toml");
    let mut all = vec![
        "sensor",
        "init",
        "--reference",
        frame.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    all.extend_from_slice(args);
    let o = util::run(&all);
    assert!(
        o.status.success(),
        "sensor init {args:?}: {}",
        util::stderr(&o)
    );
    out
}

/// Runs `tactbench track --mode per-window` with `sensor` from `reference` to `frame`
/// and returns the status counts of the CSV (ok, not ok) and the exit status.
fn track_counts(dir: &Path, sensor: &Path, reference: &Path, frame: &Path) -> (usize, usize) {
    let csv = dir.join("tracks.csv");
    let o = util::run(&[
        "track",
        "--sensor",
        sensor.to_str().unwrap(),
        "--reference",
        reference.to_str().unwrap(),
        "--mode",
        "per-window",
        "--out",
        csv.to_str().unwrap(),
        frame.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "track: {}", util::stderr(&o));
    let text = std::fs::read_to_string(&csv).unwrap();
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = head.iter().position(|h| *h == "status").unwrap();
    let statuses: Vec<String> = lines
        .map(|l| l.split(',').nth(col).unwrap().to_string())
        .collect();
    let ok = statuses.iter().filter(|s| *s == "ok").count();
    (ok, statuses.len() - ok)
}

/// The draft `sensor init` writes loads with the sensor parser as it is (its
/// placeholders are marked `# TODO: measure` but valid values), carries what was
/// asked (appearance, ROI, scale) and what was measured (frame size, grid), and
/// `track` works with it at once on the next frame of the same sensor. Measured:
/// FOTS 0 → 1 65 ok of 99 (the 19 whose window crosses the image edge lost, 15
/// outliers: see `vision_tracking_real::fots_pair_…`); TacTip 1 → 2 (the next tap,
/// ROI r 182 px) 280 ok of 331; the bright 8 × 8 grid against itself 63 ok of 64, its
/// draft with the grid (`[layers.markers]`, 8 × 8): the dot at (499, 233) px, with a
/// magenta fringe among the stripes, is measured 13.3 px off against its own frame
/// and flagged `outlier` (the window's ring plane cannot remove stripes; detection's
/// top-hat does — a known limitation, docs/real-sensors.md).
#[test]
fn sensor_init_drafts_load_unedited_and_track_the_next_frame() {
    let Some(real) = real_frames() else { return };
    // (reference, next frame, sensor init options, colour, ROI in the draft, the
    // draft's grid: Some((nx, ny)) or None, least ok markers in the next frame)
    type Case<'a> = (
        &'a str,
        &'a str,
        &'a [&'a str],
        &'a str,
        bool,
        Option<(usize, usize)>,
        usize,
    );
    let cases: [Case; 3] = [
        (
            "gelsight_fots/0.png",
            "gelsight_fots/1.png",
            &["--color", "dark", "--mm-per-px", "0.05107"],
            "dark",
            false,
            None,
            65,
        ),
        (
            "tactip/image_1.png",
            "tactip/image_2.png",
            &util::TACTIP_INIT,
            "bright",
            true,
            None,
            275,
        ),
        (
            "gelsight_bright/raw_1280x720.png",
            "gelsight_bright/raw_1280x720.png",
            &["--color", "bright", "--pitch-mm", "2.0"],
            "bright",
            false,
            Some((8, 8)),
            63,
        ),
    ];
    for (reference, next, args, color, roi, grid, least_ok) in cases {
        let dir = tempfile::tempdir().unwrap();
        let (reference, next) = (real.join(reference), real.join(next));
        let draft = sensor_init(dir.path(), &reference, args);
        let text = std::fs::read_to_string(&draft).unwrap();
        assert!(text.contains("# TODO: measure"), "{text}");
        let s = Sensor::from_path(&draft).unwrap_or_else(|e| panic!("{e}\n{text}"));
        let frame = Frame::open(&reference).unwrap();
        let v = frame.view();
        assert_eq!(
            (s.camera.width_px, s.camera.height_px),
            (v.width_px(), v.height_px())
        );
        assert_eq!(s.layers.len(), 1);
        assert_eq!(s.layers[0].color.to_string(), color);
        assert_eq!(s.camera.roi_px.is_some(), roi, "{text}");
        assert_eq!(
            s.layers[0].markers.as_ref().map(|m| (m.grid.nx, m.grid.ny)),
            grid,
            "{text}"
        );
        let (ok, not_ok) = track_counts(dir.path(), &draft, &reference, &next);
        eprintln!(
            "{}: draft loads; track to {}: {ok} ok, {not_ok} not ok",
            reference.display(),
            next.display()
        );
        assert!(ok >= least_ok, "{ok} ok, {not_ok} not");
    }
}

// ---- bad input: every refusal names the file, the key and the value ------------------

/// A 13 × 10 grid sensor of the paper's geometry (430 × 340 px, 0.05 mm/px) with one
/// layer of appearance `color` and the `[camera]` line `roi` (may be empty).
fn grid_sensor_toml(color: &str, roi: &str) -> String {
    format!(
        "[elastomer]\nyoung_modulus_kpa = 1000.0\npoisson_ratio = 0.5\nthickness_mm = 40.0\n\n\
         [[layers]]\nname = \"markers\"\ncolor = \"{color}\"\ndepth_mm = 3.0\n\
         [layers.markers]\nnx = 13\nny = 10\npitch_mm = 1.5\norigin_mm = [0.0, 0.0]\ndiameter_mm = 0.6\n\n\
         [force_grid]\nnx = 10\nny = 8\npitch_mm = 2.2\norigin_mm = [-0.9, -0.95]\n\n\
         [camera]\nmm_per_px = 0.05\norigin_px = [25.0, 25.0]\nwidth_px = 430\nheight_px = 340\n{roi}\n"
    )
}

/// Writes `grid_sensor_toml(color, roi)` and a frame of that sensor rendered with the
/// appearance `drawn` (the `sim` renderer, 8-bit) into `dir`: (sensor, frame).
fn grid_case(dir: &Path, color: &str, roi: &str, drawn: &str) -> (PathBuf, PathBuf) {
    let sensor = dir.join(format!("{color}_sensor.toml"));
    std::fs::write(&sensor, grid_sensor_toml(color, roi)).unwrap();
    let drawn = Sensor::from_toml_str(&grid_sensor_toml(drawn, ""), "drawn.toml").unwrap();
    let frame = dir.join(format!("{}_frame.png", drawn.layers[0].color));
    let img = tactbench::sim::render::render_sensor(&drawn, None).unwrap();
    tactbench::sim::render::to_rgb8(&img).save(&frame).unwrap();
    (sensor, frame)
}

/// `tactbench track` with `sensor` from `reference` to `reference` (per window).
fn track_cli(dir: &Path, sensor: &Path, reference: &Path) -> std::process::Output {
    let out = dir.join("t.csv");
    util::run(&[
        "track",
        "--sensor",
        p(sensor),
        "--reference",
        p(reference),
        "--mode",
        "per-window",
        "--out",
        p(&out),
        p(reference),
    ])
}

fn calibrate_cli(dir: &Path, sensor: &Path, reference: &Path) -> std::process::Output {
    let out = dir.join("camera.toml");
    util::run(&[
        "calibrate",
        "--sensor",
        p(sensor),
        "--reference",
        p(reference),
        "--radial-terms",
        "0",
        "--out",
        p(&out),
    ])
}

/// `tactbench sensor init` on `reference`, the draft written into `dir`.
fn init_cli(dir: &Path, reference: &Path, args: &[&str]) -> std::process::Output {
    let out = dir.join("draft.toml");
    let mut all = vec![
        "sensor",
        "init",
        "--reference",
        p(reference),
        "--out",
        p(&out),
    ];
    all.extend_from_slice(args);
    util::run(&all)
}

/// Exit status 2 and every `needle` in stderr.
fn refused(o: &std::process::Output, needles: &[&str]) {
    let err = util::stderr(o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    for n in needles {
        assert!(err.contains(n), "{n:?} not in: {err}");
    }
}

/// `[camera] roi_px` outside the image (`track`, `calibrate`) and `--roi` outside the
/// frame (`sensor init`): refused, naming the file, the key and the value.
#[test]
fn roi_outside_the_image_is_refused_naming_file_key_and_value() {
    let dir = tempfile::tempdir().unwrap();
    let roi = "roi_px = { center = [1000.0, 1000.0], radius = 10.0 }";
    let (sensor, frame) = grid_case(dir.path(), "dark", roi, "dark");
    let needles = [
        "dark_sensor.toml",
        "camera.roi_px",
        "{ center = [1000.0, 1000.0], radius = 10.0 }",
        "must lie inside the 430×340 px image",
    ];
    refused(&track_cli(dir.path(), &sensor, &frame), &needles);
    refused(&calibrate_cli(dir.path(), &sensor, &frame), &needles);
    let rect = "roi_px = { min = [-5.0, 0.0], max = [100.0, 100.0] }";
    let (sensor, frame) = grid_case(dir.path(), "dark", rect, "dark");
    refused(
        &track_cli(dir.path(), &sensor, &frame),
        &[
            "dark_sensor.toml",
            "camera.roi_px",
            "min = [-5.0, 0.0]",
            "inside",
        ],
    );
    refused(
        &init_cli(
            dir.path(),
            &frame,
            &["--color", "dark", "--roi", "circle:1000,1000,10"],
        ),
        &[
            "dark_frame.png",
            "--roi",
            "center = [1000.0, 1000.0]",
            "must lie inside",
        ],
    );
}

/// An ROI of zero size: radius 0, `min == max` along x or y; in the sensor file and
/// as `--roi`.
#[test]
fn roi_of_zero_size_is_refused_naming_file_key_and_value() {
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        (
            "roi_px = { center = [200.0, 150.0], radius = 0.0 }",
            ["camera.roi_px.radius", "= 0 px", "> 0 px"],
        ),
        (
            "roi_px = { min = [10.0, 10.0], max = [10.0, 200.0] }",
            ["camera.roi_px.max[0]", "= 10 px", "zero or negative size"],
        ),
        (
            "roi_px = { min = [10.0, 10.0], max = [200.0, 10.0] }",
            ["camera.roi_px.max[1]", "= 10 px", "zero or negative size"],
        ),
    ];
    for (roi, [key, value, why]) in cases {
        let (sensor, frame) = grid_case(dir.path(), "dark", roi, "dark");
        let needles = ["dark_sensor.toml", key, value, why];
        refused(&track_cli(dir.path(), &sensor, &frame), &needles);
        refused(&calibrate_cli(dir.path(), &sensor, &frame), &needles);
    }
    let (_, frame) = grid_case(dir.path(), "dark", "", "dark");
    for arg in ["circle:200,150,0", "rect:10,10,10,200", "rect:10,10,200,10"] {
        refused(
            &init_cli(dir.path(), &frame, &["--color", "dark", "--roi", arg]),
            &["dark_frame.png", "--roi", "zero or negative size"],
        );
    }
}

/// `color = "dark"` on a frame with no dark markers (the `sim` renderer's bright
/// markers on a dark skin): `track` and `calibrate` refuse naming the frame, the
/// sensor file and `layers[0].color = "dark"`; `sensor init --color dark` names the
/// frame and `--color dark`. The same on the real TacTip frame (bright pins).
#[test]
fn dark_color_on_a_frame_without_dark_markers_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let (sensor, frame) = grid_case(dir.path(), "dark", "", "bright");
    let needles = [
        "bright_frame.png",
        "dark_sensor.toml",
        r#"layers[0].color = "dark""#,
    ];
    refused(&track_cli(dir.path(), &sensor, &frame), &needles);
    refused(&calibrate_cli(dir.path(), &sensor, &frame), &needles);
    refused(
        &init_cli(dir.path(), &frame, &["--color", "dark"]),
        &["bright_frame.png", "no dark marker found (--color dark)"],
    );
    let Some(real) = real_frames() else { return };
    let tactip = real.join("tactip/image_1.png");
    let s = dir.path().join("tactip_dark.toml");
    std::fs::write(
        &s,
        sensor_toml(
            "dark",
            640,
            480,
            Some("{ center = [304.0, 250.0], radius = 182.0 }"),
        ),
    )
    .unwrap();
    refused(
        &track_cli(dir.path(), &s, &tactip),
        &[
            "image_1.png",
            "tactip_dark.toml",
            r#"layers[0].color = "dark""#,
        ],
    );
    refused(
        &init_cli(
            dir.path(),
            &tactip,
            &["--color", "dark", "--roi", "circle:304,250,182"],
        ),
        &["image_1.png", "no dark marker found (--color dark"],
    );
}

/// A blank (uniform grey) and a saturated (white) reference: `track`, `calibrate` and
/// `sensor init` refuse, naming the frame, what is wrong and the measured value.
#[test]
fn blank_and_saturated_references_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let (sensor, _) = grid_case(dir.path(), "dark", "", "dark");
    for (name, level, what, value) in [
        (
            "blank.png",
            128u8,
            "blank frame",
            "within 0.0 % of full scale",
        ),
        (
            "white.png",
            255u8,
            "saturated frame",
            "100.0 % of the pixels",
        ),
    ] {
        let frame = dir.path().join(name);
        image::RgbImage::from_pixel(430, 340, image::Rgb([level; 3]))
            .save(&frame)
            .unwrap();
        let needles = [name, what, value];
        refused(&track_cli(dir.path(), &sensor, &frame), &needles);
        refused(&calibrate_cli(dir.path(), &sensor, &frame), &needles);
        refused(
            &init_cli(dir.path(), &frame, &["--color", "dark"]),
            &needles,
        );
    }
}

/// `tactbench calibrate` with `dark` and `bright` layers and an ROI around the grid
/// (frames of the `sim` renderer, 20 px/mm): it writes camera.toml with the scale.
#[test]
fn calibrate_accepts_dark_and_bright_layers_and_an_roi() {
    let dir = tempfile::tempdir().unwrap();
    for color in ["dark", "bright"] {
        let roi = "roi_px = { min = [5.0, 5.0], max = [425.0, 335.0] }";
        let (sensor, frame) = grid_case(dir.path(), color, roi, color);
        let o = calibrate_cli(dir.path(), &sensor, &frame);
        let err = util::stderr(&o);
        assert!(o.status.success(), "{color}: {err}");
        assert!(err.contains("130 markers"), "{color}: {err}");
        assert!(
            err.contains("20.0000") || err.contains("19.9999"),
            "{color}: {err}"
        );
        let text = std::fs::read_to_string(dir.path().join("camera.toml")).unwrap();
        assert!(text.contains("px_per_mm"), "{text}");
    }
}
