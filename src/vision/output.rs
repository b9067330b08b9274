//! The `track` output: the displacement CSV of `formats` (`layer,marker,x_mm,y_mm,
//! ux_mm,uy_mm`) extended with `frame,x_px,y_px,ux_px,uy_px,status`.
//!
//! One row per marker per frame, frames in the given order, markers by layer (sensor
//! order) then id. `x_mm, y_mm` is the reference position in the sensor frame and
//! `x_px, y_px` the reference centroid; `frame` is the frame label (the file name as
//! given). Only `ok` markers carry `ux_mm, uy_mm`: lost, merged and outlier markers
//! leave them empty so `reconstruct` drops them. `ux_px, uy_px` hold what was measured
//! (empty when lost). A grid node with no marker in the reference is written as lost in
//! every frame with its node position and empty pixel columns.

use std::io::Write;
use std::path::Path;

use super::camera::PixelMapping;
use super::{MarkerStatus, MarkerTrack, Reference};
use crate::formats::{FormatError, Num, DISPLACEMENT_COLUMNS};
use crate::sensor::Sensor;

/// The columns `track` writes after [`DISPLACEMENT_COLUMNS`].
pub const TRACK_EXTRA_COLUMNS: [&str; 6] = ["frame", "x_px", "y_px", "ux_px", "uy_px", "status"];

/// Writes the tracks of several frames to a file (see the module docs).
pub fn write_tracks(
    path: &Path,
    sensor: &Sensor,
    reference: &Reference,
    frames: &[(String, Vec<MarkerTrack>)],
) -> Result<(), FormatError> {
    write_tracks_mapped(
        path,
        sensor,
        reference,
        frames,
        &PixelMapping::Linear(sensor.camera),
    )
}

/// As [`write_tracks`], converting pixel displacements to mm with `mapping` (a camera
/// calibration; `PixelMapping::Linear(sensor.camera)` is [`write_tracks`]).
pub fn write_tracks_mapped(
    path: &Path,
    sensor: &Sensor,
    reference: &Reference,
    frames: &[(String, Vec<MarkerTrack>)],
    mapping: &PixelMapping,
) -> Result<(), FormatError> {
    let io = |source| FormatError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut w = std::io::BufWriter::new(std::fs::File::create(path).map_err(io)?);
    write_tracks_mapped_to(&mut w, sensor, reference, frames, mapping).map_err(io)?;
    w.flush().map_err(io)
}

/// As [`write_tracks`], to any writer.
pub fn write_tracks_to(
    w: &mut impl Write,
    sensor: &Sensor,
    reference: &Reference,
    frames: &[(String, Vec<MarkerTrack>)],
) -> std::io::Result<()> {
    write_tracks_mapped_to(
        w,
        sensor,
        reference,
        frames,
        &PixelMapping::Linear(sensor.camera),
    )
}

/// As [`write_tracks_mapped`], to any writer.
pub fn write_tracks_mapped_to(
    w: &mut impl Write,
    sensor: &Sensor,
    reference: &Reference,
    frames: &[(String, Vec<MarkerTrack>)],
    mapping: &PixelMapping,
) -> std::io::Result<()> {
    // Row order: (layer, id) -> Some(marker index) or None (missing).
    let mut rows: Vec<(usize, u64, Option<usize>, [f64; 2])> = reference
        .markers
        .iter()
        .enumerate()
        .map(|(i, m)| (m.layer, m.id, Some(i), m.position_mm))
        .chain(
            reference
                .missing
                .iter()
                .map(|m| (m.layer, m.id, None, m.node_mm)),
        )
        .collect();
    rows.sort_by_key(|r| (r.0, r.1));
    writeln!(
        w,
        "{},{}",
        DISPLACEMENT_COLUMNS.join(","),
        TRACK_EXTRA_COLUMNS.join(",")
    )?;
    for (label, tracks) in frames {
        let label = csv_field(label);
        for &(layer, id, index, pos) in &rows {
            let name = &sensor.layers[layer].name;
            write!(w, "{name},{id},{},{},", Num(pos[0]), Num(pos[1]))?;
            let Some(i) = index else {
                writeln!(w, ",,{label},,,,,lost")?;
                continue;
            };
            let t = &tracks[i];
            let r = &reference.markers[i];
            if t.status == MarkerStatus::Ok {
                let u = mapping.displacement_mm(layer, r.centroid_px, t.displacement_px);
                write!(w, "{},{}", Num(u[0]), Num(u[1]))?;
            } else {
                write!(w, ",")?;
            }
            write!(
                w,
                ",{label},{},{},",
                Num(r.centroid_px[0]),
                Num(r.centroid_px[1])
            )?;
            if t.status == MarkerStatus::Lost {
                write!(w, ",")?;
            } else {
                write!(
                    w,
                    "{},{}",
                    Num(t.displacement_px[0]),
                    Num(t.displacement_px[1])
                )?;
            }
            writeln!(w, ",{}", t.status)?;
        }
    }
    Ok(())
}

/// Quotes a field when it holds a comma, quote or line break (RFC 4180).
fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}
