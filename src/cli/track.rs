//! `tactbench track`: reference image + frames -> displacement CSV (library:
//! [`tactbench::vision`]).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use tactbench::sensor::Sensor;
use tactbench::vision::onboard::check_frame_levels;
use tactbench::vision::{
    check_layers, decode_ahead, decoder_threads, detect_mapped, load_frame, write_tracks_mapped,
    CameraCalibration, DetectConfig, PixelMapping, ReferenceHealth, StatusCounts, TrackConfig,
    TrackMode, Tracker,
};

/// Track markers: images -> marker displacements (CSV).
///
/// Finds every layer's markers in the unloaded REFERENCE image, matches them to the
/// layer grids of the sensor file (marker id = row-major grid index), then measures
/// each FRAME against it and writes one row per marker per frame.
///
/// Images: PNG (RGB, RGBA or palette), JPEG or BMP, 8-bit or 16-bit, of the size given
/// in the sensor's [camera] section; the reference and the frames may differ in bit
/// depth (8-bit samples count as 257 × their value on a 16-bit scale, so a mixed pair
/// tracks like a matched one). 8- and 16-bit greyscale images serve dark and bright
/// layers; a coloured layer (blue, red, green) on a greyscale image is an error naming
/// the layer. Layers of color dark (dark markers on a lit gel)
/// or bright (light pins or dots on a dark skin) are found by their contrast against
/// the local illumination, so gradients, vignetting and stripes do not hide them. With
/// [camera] roi_px markers are sought only inside the ROI, and a marker whose window
/// crosses its border is reported lost.
///
/// Output columns: layer,marker,x_mm,y_mm,ux_mm,uy_mm,frame,x_px,y_px,ux_px,uy_px,status.
/// x_mm, y_mm: reference position in the sensor frame (mm); ux_mm, uy_mm: displacement
/// (mm), given only for status `ok`; frame: the frame file name as given; x_px, y_px:
/// reference centroid (px, pixel centres at integers); ux_px, uy_px: measured
/// displacement (px), empty when lost; status: ok | lost (not found or too weak) |
/// merged (two markers on one blob) | outlier (disagrees with its neighbours). The file
/// is the input of `tactbench reconstruct`, which drops rows without ux_mm.
///
/// With --camera camera.toml (from `tactbench calibrate`) pixels are converted to the
/// sensor frame per layer with the calibration (scale, origin, lens distortion): x_mm,
/// y_mm and ux_mm, uy_mm then come from it; the pixel columns are unchanged.
///
/// A summary of lost, merged and outlier markers is printed on stderr.
///
/// A frame that cannot be read (missing, undecodable, another size than the sensor's
/// [camera], past the frame-size cap) does not lose the batch: every other frame is
/// tracked and written, the bad one is left out of the CSV and named on stderr with
/// the reason (both sizes for a size mismatch), and the exit status is 1.
///
/// Drafts: a sensor file from `sensor init` (`draft = true`) is used as it is (tracking
/// needs only its geometry); its placeholders are named on stderr, and when
/// `camera.mm_per_px` is one of them the mm columns are in its placeholder unit.
///
/// Exit status: 0 when every frame tracked; 1 when a frame lost more than
/// --max-lost-fraction of the sensor's markers (lost or merged, reference-missing ones
/// included: typically the wrong sensor file, a blank or over-exposed frame, or another
/// scene) or could not be read — the CSV is still written with every other frame and
/// each failing frame is named on stderr; 2 on errors (unreadable or mismatched sensor
/// file or reference, no marker in the reference, no frame readable: nothing written).
#[derive(clap::Args)]
#[command(allow_negative_numbers = true)]
pub struct Args {
    /// Sensor description (sensor.toml: layers, marker grids, camera mapping).
    #[arg(long, value_name = "S.toml")]
    sensor: PathBuf,
    /// Reference image taken with no load on the sensor.
    #[arg(long, value_name = "REF.png")]
    reference: PathBuf,
    /// Frames to track, in sequence order.
    #[arg(required = true, value_name = "FRAME")]
    frames: Vec<PathBuf>,
    /// Output displacement CSV.
    #[arg(long, value_name = "D.csv")]
    out: PathBuf,
    /// Window placement: `frame-to-frame` follows each marker from its last position
    /// (large motion across a sequence) and re-acquires from its reference position
    /// what that does not find near it, keeping per marker the result consistent with
    /// its neighbours (independent frames, such as taps at unrelated poses, track as
    /// per window); `per-window` measures every frame on its own around the reference
    /// positions (the paper's method, small motion).
    #[arg(long, value_enum, default_value_t = Mode::FrameToFrame)]
    mode: Mode,
    /// Largest fraction of the sensor's markers a frame may lose (status lost or
    /// merged, reference-missing markers included) before the command fails with exit
    /// status 1; 1 disables the check.
    #[arg(long, value_name = "F", default_value_t = DEFAULT_MAX_LOST_FRACTION, value_parser = fraction)]
    max_lost_fraction: f64,
    /// Camera calibration (camera.toml, from `tactbench calibrate`): pixels are mapped
    /// to the sensor frame per layer with its scale, origin and lens distortion, for the
    /// reference positions and the displacements (mm). Without it the sensor file's
    /// linear [camera] mapping is used, as before.
    #[arg(long, value_name = "camera.toml")]
    camera: Option<PathBuf>,
    /// Threads that read and decode frames ahead while this one tracks (decoding a PNG
    /// costs about ten times tracking it). Default: one per core; 1 decodes on one
    /// worker while the main thread tracks. The output is the same for any value.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u16).range(1..=64))]
    decode_threads: Option<u16>,
}

/// Default of `--max-lost-fraction`: a quarter of the markers.
pub const DEFAULT_MAX_LOST_FRACTION: f64 = 0.25;

fn fraction(s: &str) -> Result<f64, String> {
    let v: f64 = s
        .parse()
        .map_err(|_| format!("{s:?} is not a number (a fraction between 0 and 1)"))?;
    if (0.0..=1.0).contains(&v) {
        Ok(v)
    } else {
        Err(format!("{v} is outside 0..=1 (a fraction of the markers)"))
    }
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum Mode {
    FrameToFrame,
    PerWindow,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let sensor = Sensor::from_path(&args.sensor)?;
    if !sensor.placeholders().is_empty() {
        let scale = sensor
            .placeholders()
            .iter()
            .any(|k| k == "camera.mm_per_px");
        eprintln!(
            "note: {} is a draft: its placeholders ({}) are not used for tracking{}",
            args.sensor.display(),
            sensor.placeholders().join(", "),
            if scale {
                "; camera.mm_per_px is a placeholder, so the mm columns are in its placeholder unit (px at mm_per_px = 1), not mm"
            } else {
                ""
            }
        );
    }
    let mapping = match &args.camera {
        None => PixelMapping::Linear(sensor.camera),
        Some(path) => PixelMapping::Calibrated(CameraCalibration::from_path(path, &sensor)?),
    };
    let reference_image = load_frame(&args.reference, &sensor.camera)?;
    let layers = || sensor.layers.iter().map(|l| (l.name.as_str(), l.color));
    check_layers(&reference_image.view(), layers())
        .with_context(|| format!("reference image {}", args.reference.display()))?;
    let detected = detect_mapped(
        &reference_image.view(),
        &sensor,
        &DetectConfig::default(),
        &mapping,
    );
    let health = ReferenceHealth::of(detected.as_ref().ok(), &sensor, &reference_image.view());
    if detected.is_err() || 1.0 - health.found_fraction() > args.max_lost_fraction {
        eprintln!(
            "reference {} does not match the sensor file: {health}; {}",
            args.reference.display(),
            health.measurements()
        );
        for d in health.diagnosis() {
            eprintln!("  likely {d}");
        }
    }
    if detected.is_err() {
        // A blank or saturated reference is the likelier cause: say so first.
        check_frame_levels(
            &reference_image.view(),
            sensor.camera.roi_px.as_ref(),
            &args.reference,
        )
        .with_context(|| format!("reference image for sensor {}", args.sensor.display()))?;
    }
    let reference = detected.with_context(|| {
        format!(
            "reference image {} with sensor {}",
            args.reference.display(),
            args.sensor.display()
        )
    })?;
    eprintln!(
        "reference {}: {} markers found, {} grid nodes without a marker, {} blobs without a grid node",
        args.reference.display(),
        reference.markers.len(),
        reference.missing.len(),
        reference.unmatched.len()
    );
    for m in &reference.missing {
        eprintln!(
            "  missing: layer {} marker {} at ({}, {}) mm",
            sensor.layers[m.layer].name, m.id, m.node_mm[0], m.node_mm[1]
        );
    }
    for u in &reference.unmatched {
        eprintln!(
            "  unmatched {} blob at ({:.2}, {:.2}) px",
            sensor.layers[u.layer].name, u.centroid_px[0], u.centroid_px[1]
        );
    }
    let config = TrackConfig {
        mode: match args.mode {
            Mode::FrameToFrame => TrackMode::FrameToFrame,
            Mode::PerWindow => TrackMode::PerWindow,
        },
        ..TrackConfig::default()
    };
    let missing = reference.missing.len();
    let expected = reference.markers.len() + missing;
    let reference_bits = reference.bit_depth;
    let mut tracker = Tracker::new(reference, config);
    let mut frames = Vec::with_capacity(args.frames.len());
    let mut total = StatusCounts::default();
    let mut mixed_noted = false;
    // Frames that lost too many markers: (path, lost or merged).
    let mut failed: Vec<(String, usize)> = Vec::new();
    // Frames that could not be read or tracked: (path, why); left out of the CSV.
    let mut unread: Vec<(String, String)> = Vec::new();
    // Frames are decoded ahead on worker threads while this thread tracks, in the
    // order given (vision::prefetch): the same output as one frame after another.
    let threads = args
        .decode_threads
        .map_or_else(|| decoder_threads(args.frames.len()), usize::from);
    let mut fatal: Option<anyhow::Error> = None;
    decode_ahead(
        &args.frames,
        threads,
        2 * threads,
        |path| load_frame(path, &sensor.camera),
        |k, loaded| {
            let path = &args.frames[k];
            let image = match loaded {
                Ok(i) => i,
                Err(e) => {
                    eprintln!("error: {e}: frame left out, the others are tracked");
                    unread.push((path.display().to_string(), e.to_string()));
                    return true;
                }
            };
            let view = image.view();
            if let Err(e) =
                check_layers(&view, layers()).with_context(|| format!("frame {}", path.display()))
            {
                fatal = Some(e);
                return false;
            }
            if view.bit_depth() != reference_bits && !mixed_noted {
                mixed_noted = true;
                eprintln!(
                    "note: the reference is {reference_bits}-bit and {} is {}-bit: compared on a common scale (8-bit value × 257 = 16-bit value)",
                    path.display(),
                    view.bit_depth()
                );
            }
            let tracks = match tracker.track(&view) {
                Ok(t) => t,
                Err(e) => {
                    eprintln!(
                        "error: {}: {e}: frame left out, the others are tracked",
                        path.display()
                    );
                    unread.push((path.display().to_string(), e.to_string()));
                    return true;
                }
            };
            let c = StatusCounts::of(tracks, missing);
            let gone = c.lost + c.merged;
            if expected > 0 && gone as f64 > args.max_lost_fraction * expected as f64 {
                failed.push((path.display().to_string(), gone));
            }
            if c.lost + c.merged + c.outlier > 0 {
                eprintln!(
                    "{}: {} ok, {} lost, {} merged, {} outlier",
                    path.display(),
                    c.ok,
                    c.lost,
                    c.merged,
                    c.outlier
                );
            }
            total.ok += c.ok;
            total.lost += c.lost;
            total.merged += c.merged;
            total.outlier += c.outlier;
            frames.push((path.to_string_lossy().into_owned(), tracks.to_vec()));
            true
        },
    );
    if let Some(e) = fatal {
        return Err(e);
    }
    if frames.is_empty() {
        anyhow::bail!(
            "none of the {} frame(s) could be read, nothing written: {}",
            unread.len(),
            unread
                .iter()
                .map(|(_, why)| why.as_str())
                .collect::<Vec<_>>()
                .join("; ")
        );
    }
    write_tracks_mapped(&args.out, &sensor, tracker.reference(), &frames, &mapping)?;
    eprintln!(
        "{} frames: {} ok, {} lost, {} merged, {} outlier marker measurements -> {}",
        frames.len(),
        total.ok,
        total.lost,
        total.merged,
        total.outlier,
        args.out.display()
    );
    for (_, why) in &unread {
        eprintln!("error: not in the CSV: {why}");
    }
    if !unread.is_empty() {
        eprintln!(
            "{} of {} frames could not be read and are not in {}; the other {} are",
            unread.len(),
            args.frames.len(),
            args.out.display(),
            frames.len()
        );
    }
    if failed.is_empty() {
        return Ok(if unread.is_empty() {
            ExitCode::SUCCESS
        } else {
            ExitCode::from(1)
        });
    }
    for (path, gone) in &failed {
        eprintln!(
            "error: {path}: {gone} of {expected} markers lost or merged ({:.0} %), more than --max-lost-fraction {} ({:.0} %)",
            100.0 * *gone as f64 / expected as f64,
            args.max_lost_fraction,
            100.0 * args.max_lost_fraction
        );
    }
    eprintln!(
        "tracking failed in {} of {} frames: check that the frames show this sensor (sensor file, [camera] mm_per_px and origin_px), that they are not blank or over-exposed, and that the reference is unloaded",
        failed.len(),
        frames.len()
    );
    Ok(ExitCode::from(1))
}
