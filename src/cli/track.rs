//! `tactbench track`: reference image + frames -> displacement CSV (library:
//! [`tactbench::vision`]).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use tactbench::sensor::Sensor;
use tactbench::vision::{
    detect, load_frame, write_tracks, DetectConfig, StatusCounts, TrackConfig, TrackMode, Tracker,
};

/// Track markers: images -> marker displacements (CSV).
///
/// Finds every layer's markers in the unloaded REFERENCE image, matches them to the
/// layer grids of the sensor file (marker id = row-major grid index), then measures
/// each FRAME against it and writes one row per marker per frame.
///
/// Images: PNG, JPEG or BMP, 8-bit RGB/RGBA or 16-bit RGB/RGBA, of the size given in
/// the sensor's [camera] section. Grayscale images are rejected (layers are told apart
/// by colour: blue, red, green).
///
/// Output columns: layer,marker,x_mm,y_mm,ux_mm,uy_mm,frame,x_px,y_px,ux_px,uy_px,status.
/// x_mm, y_mm: reference position in the sensor frame (mm); ux_mm, uy_mm: displacement
/// (mm), given only for status `ok`; frame: the frame file name as given; x_px, y_px:
/// reference centroid (px, pixel centres at integers); ux_px, uy_px: measured
/// displacement (px), empty when lost; status: ok | lost (not found or too weak) |
/// merged (two markers on one blob) | outlier (disagrees with its neighbours). The file
/// is the input of `tactbench reconstruct`, which drops rows without ux_mm.
///
/// A summary of lost, merged and outlier markers is printed on stderr.
#[derive(clap::Args)]
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
    /// (large motion across a sequence); `per-window` measures every frame on its own
    /// around the reference positions (the paper's method, small motion).
    #[arg(long, value_enum, default_value_t = Mode::FrameToFrame)]
    mode: Mode,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum Mode {
    FrameToFrame,
    PerWindow,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let sensor = Sensor::from_path(&args.sensor)?;
    let reference_image = load_frame(&args.reference, &sensor.camera)?;
    let reference = detect(&reference_image.view(), &sensor, &DetectConfig::default())
        .with_context(|| format!("reference image {}", args.reference.display()))?;
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
    let mut tracker = Tracker::new(reference, config);
    let mut frames = Vec::with_capacity(args.frames.len());
    let mut total = StatusCounts::default();
    for path in &args.frames {
        let image = load_frame(path, &sensor.camera)?;
        let tracks = tracker.track(&image.view())?;
        let c = StatusCounts::of(tracks, missing);
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
    }
    write_tracks(&args.out, &sensor, tracker.reference(), &frames)?;
    eprintln!(
        "{} frames: {} ok, {} lost, {} merged, {} outlier marker measurements -> {}",
        frames.len(),
        total.ok,
        total.lost,
        total.merged,
        total.outlier,
        args.out.display()
    );
    Ok(ExitCode::SUCCESS)
}
