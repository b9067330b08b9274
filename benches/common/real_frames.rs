//! The real camera frames the speed benchmarks and `examples/tracking_side_by_side.rs`
//! track (issue 19, part 6), so the criterion medians and the side-by-side run measure
//! the same input. Frames are read from `../shared/real_frames/` (never copied into the
//! repository). Included with `#[path]` (benches and examples cannot import each other).

#![allow(dead_code)]

use std::path::{Path, PathBuf};

use image::RgbImage;
use tactbench::sensor::Sensor;
use tactbench::vision::{detect, DetectConfig, Frame, FrameView, Reference};

/// `../shared/real_frames` beside the clone (`TACTBENCH_REAL_FRAMES` overrides it).
pub fn dir() -> PathBuf {
    std::env::var_os("TACTBENCH_REAL_FRAMES").map_or_else(
        || Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/real_frames"),
        PathBuf::from,
    )
}

/// One speed case: a reference and a loaded frame of a real sensor, with the sensor
/// file that describes it (one layout-free layer) and what the OpenCV script needs.
pub struct Case {
    /// Short name (bench ids, table rows).
    pub name: &'static str,
    /// Reference frame file (unloaded).
    pub reference: PathBuf,
    /// Frame file tracked against it.
    pub frame: PathBuf,
    /// `bright` or `dark`.
    pub appearance: &'static str,
    /// Region of interest as a circle (cx, cy, r), px.
    pub roi: Option<[f64; 3]>,
    /// The OpenCV script's top-hat kernel, px.
    pub kernel: u32,
}

/// An 8-bit RGB image shifted by whole pixels (`dx`, `dy`), edges replicated: a
/// loaded frame for a sensor of which only one real frame exists.
pub fn shifted(img: &RgbImage, dx: i64, dy: i64) -> RgbImage {
    let (w, h) = (img.width() as i64, img.height() as i64);
    RgbImage::from_fn(img.width(), img.height(), |x, y| {
        let sx = (x as i64 - dx).clamp(0, w - 1) as u32;
        let sy = (y as i64 - dy).clamp(0, h - 1) as u32;
        *img.get_pixel(sx, sy)
    })
}

/// The cases: TacTip (640×480, ~330 bright pins, tap 1 → tap 2), the GelSight bright
/// dots (1280×720, the one frame against itself shifted by (3, 2) px, written to
/// `scratch`), and the FOTS dark dots (320×240, frame 0 → 1, displacements up to half
/// the pitch). `None` when the real frames are absent.
pub fn cases(scratch: &Path) -> Option<Vec<Case>> {
    let d = dir();
    if !d.join("tactip/image_1.png").exists() {
        return None;
    }
    let bright = d.join("gelsight_bright/raw_1280x720.png");
    let raw = image::open(&bright).ok()?.to_rgb8();
    std::fs::create_dir_all(scratch).ok()?;
    let moved = scratch.join("raw_1280x720_shift_3_2.png");
    shifted(&raw, 3, 2).save(&moved).ok()?;
    Some(vec![
        Case {
            name: "tactip_640x480",
            reference: d.join("tactip/image_1.png"),
            frame: d.join("tactip/image_2.png"),
            appearance: "bright",
            roi: Some([300.0, 245.0, 205.0]),
            kernel: 15,
        },
        Case {
            name: "gelsight_bright_1280x720",
            reference: bright,
            frame: moved,
            appearance: "bright",
            roi: None,
            kernel: 41,
        },
        Case {
            name: "fots_dark_320x240",
            reference: d.join("gelsight_fots/0.png"),
            frame: d.join("gelsight_fots/1.png"),
            appearance: "dark",
            roi: None,
            kernel: 15,
        },
    ])
}

/// A one-layer, layout-free sensor file for `frame` (the tracker needs no elastic
/// parameters; these are placeholders of the right kind, never solved with).
pub fn sensor(case: &Case, frame: &FrameView<'_>) -> Sensor {
    let roi = case.roi.map_or(String::new(), |[x, y, r]| {
        format!("roi_px = {{ center = [{x}, {y}], radius = {r} }}\n")
    });
    let text = format!(
        "[elastomer]\nyoung_modulus_kpa = 100.0\npoisson_ratio = 0.5\nthickness_mm = 4.0\n\n\
         [[layers]]\nname = \"markers\"\ncolor = \"{}\"\ndepth_mm = 1.0\n\n\
         [force_grid]\nnx = 4\nny = 3\npitch_mm = 2.0\norigin_mm = [0.0, 0.0]\n\n\
         [camera]\nmm_per_px = 0.05\norigin_px = [0.0, 0.0]\nwidth_px = {}\nheight_px = {}\n{roi}",
        case.appearance,
        frame.width_px(),
        frame.height_px()
    );
    Sensor::from_toml_str(&text, case.name).expect("real-frame sensor")
}

/// The case's frames, loaded, and the reference detected.
pub fn load(case: &Case) -> (Frame, Frame, Reference) {
    let reference = Frame::open(&case.reference).expect("reference frame");
    let frame = Frame::open(&case.frame).expect("frame");
    let s = sensor(case, &reference.view());
    let r = detect(&reference.view(), &s, &DetectConfig::default()).expect("markers");
    (reference, frame, r)
}
