//! The CSV file formats shared by `track`, `reconstruct` and the runner (a public
//! contract, see DESIGN.md and the README).
//!
//! **Displacements** (input of `reconstruct`, output of `track`):
//! `layer,marker,x_mm,y_mm,ux_mm,uy_mm`, then optional extra columns. `x_mm, y_mm` is
//! the marker's reference position in the sensor frame, `layer` a layer name of
//! sensor.toml, `marker` an integer id unique within the layer. An empty or `NaN`
//! displacement marks a lost marker: it is dropped from the system and counted. When
//! an extra `frame` column is present, rows are grouped into frames by its value (in
//! order of first appearance), as `track` writes them for a sequence.
//!
//! **Forces** (output of `reconstruct`): `ix,iy,x_mm,y_mm,fx_n,fy_n,fz_n`, one row per
//! force-grid node in row-major order; with several frames a trailing `frame` column is
//! added. `reconstruct --uncertainty` inserts `sfx_n,sfy_n,sfz_n` (standard deviation
//! of each component, N) after `fz_n`.
//!
//! **Numbers** in every CSV the project writes (these two, `journal.csv`,
//! `summary.csv`) go through [`Num`]: rounded to [`CSV_SIGNIFICANT_DIGITS`]
//! significant digits and written in the shortest form that reads back as that value
//! (`7.85`, not the `7.8500000000000005` binary arithmetic leaves), and a magnitude
//! below [`CSV_ZERO_BELOW`] is written as `0`. Every column is in N, mm, N·m, s, px or
//! a unit of that order, where 1e-12 is far below any instrument's resolution: such
//! values are the residue of arithmetic (`cos 90° = 6.1e-17`), not measurements.
//! Twelve digits keep every value within a relative 5e-12 of what was computed,
//! several orders below the noise of any measured quantity. NaN stays `NaN`. The
//! displacement and force columns of these two files are linear quantities whose
//! scale is the data's, not the unit's: there the cut is relative to the frame's
//! largest value ([`NumRel`]), so scaling a frame by 1e-12 scales its file.

use std::collections::HashSet;
use std::io::Write;
use std::path::{Path, PathBuf};

use thiserror::Error;

use crate::model::MarkerSite;
use crate::sensor::{Grid, Sensor};

/// Significant digits kept in CSV numbers (see the module docs).
pub const CSV_SIGNIFICANT_DIGITS: usize = 12;

/// Magnitudes below this are written as `0` in CSVs (arithmetic residue; see the
/// module docs).
pub const CSV_ZERO_BELOW: f64 = 1e-12;

/// `v` rounded to [`CSV_SIGNIFICANT_DIGITS`] significant digits, with a magnitude
/// below [`CSV_ZERO_BELOW`] as 0 (non-finite values unchanged).
pub fn csv_round(v: f64) -> f64 {
    if !v.is_finite() {
        return v;
    }
    if v.abs() < CSV_ZERO_BELOW {
        return 0.0;
    }
    // Scientific notation with 11 digits after the point = 12 significant digits;
    // the decimal text reads back as the nearest double.
    format!("{:.*e}", CSV_SIGNIFICANT_DIGITS - 1, v)
        .parse()
        .unwrap_or(v)
}

/// A number as the CSVs write it: [`csv_round`], then the shortest decimal that reads
/// back as that value (exponent notation below 1e-5 and from 1e15 on).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Num(pub f64);

impl std::fmt::Display for Num {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let v = csv_round(self.0);
        if v == 0.0 {
            f.write_str("0")
        } else if v.is_nan() {
            f.write_str("NaN")
        } else if v.is_finite() && (v.abs() < 1e-5 || v.abs() >= 1e15) {
            write!(f, "{v:e}")
        } else {
            write!(f, "{v}")
        }
    }
}

/// A number of a linear quantity as the displacement and forces CSVs write it: as
/// [`Num`], except that the zero cut is relative to `scale` (the largest magnitude of
/// its frame and column family): a value below `CSV_ZERO_BELOW × scale` is written as
/// `0`. Forces are linear in the displacements, so the file of a frame scaled by
/// 1e-12 is the file of the frame, scaled (no absolute threshold zeroes small loads).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NumRel(pub f64, pub f64);

impl std::fmt::Display for NumRel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let NumRel(v, scale) = *self;
        if !v.is_finite() {
            return Num(v).fmt(f);
        }
        let scale = if scale.is_finite() { scale } else { 0.0 };
        if v == 0.0 || v.abs() < CSV_ZERO_BELOW * scale {
            return f.write_str("0");
        }
        let r: f64 = format!("{:.*e}", CSV_SIGNIFICANT_DIGITS - 1, v)
            .parse()
            .unwrap_or(v);
        if r.abs() < 1e-5 || r.abs() >= 1e15 {
            write!(f, "{r:e}")
        } else {
            write!(f, "{r}")
        }
    }
}

/// Largest finite magnitude in `v` (0 for none).
fn max_finite_abs(v: impl IntoIterator<Item = f64>) -> f64 {
    v.into_iter()
        .filter(|x| x.is_finite())
        .fold(0.0, |m, x| m.max(x.abs()))
}

/// Rewrites one CSV field the way [`Num`] writes numbers when it is a decimal number
/// with a fraction or an exponent (what serde writes for an `f64`); integers, text
/// and empty fields are returned unchanged.
pub fn tidy_csv_field(field: &str) -> std::borrow::Cow<'_, str> {
    let numeric = field.contains(['.', 'e', 'E'])
        && field
            .bytes()
            .all(|b| b.is_ascii_digit() || matches!(b, b'.' | b'e' | b'E' | b'-' | b'+'));
    match field.parse::<f64>() {
        Ok(v) if numeric => std::borrow::Cow::Owned(Num(v).to_string()),
        _ => std::borrow::Cow::Borrowed(field),
    }
}

/// Rewrites CSV records (as a serde-driven `csv::Writer` wrote them, no header) with
/// every number field through [`tidy_csv_field`].
pub fn tidy_csv_records(bytes: &[u8]) -> Result<Vec<u8>, csv::Error> {
    let mut rdr = csv::ReaderBuilder::new()
        .has_headers(false)
        .flexible(true)
        .from_reader(bytes);
    let mut w = csv::WriterBuilder::new()
        .has_headers(false)
        .flexible(true)
        .from_writer(Vec::new());
    for rec in rdr.records() {
        let rec = rec?;
        w.write_record(rec.iter().map(|f| tidy_csv_field(f).into_owned()))?;
    }
    w.into_inner().map_err(|e| csv::Error::from(e.into_error()))
}

/// The displacement CSV's required leading columns.
pub const DISPLACEMENT_COLUMNS: [&str; 6] = ["layer", "marker", "x_mm", "y_mm", "ux_mm", "uy_mm"];
/// The forces CSV's columns.
pub const FORCE_COLUMNS: [&str; 7] = ["ix", "iy", "x_mm", "y_mm", "fx_n", "fy_n", "fz_n"];
/// The standard-deviation columns `reconstruct --uncertainty` adds after `fz_n`, N.
pub const FORCE_SD_COLUMNS: [&str; 3] = ["sfx_n", "sfy_n", "sfz_n"];

/// An error reading or writing a CSV file. Data errors name file, line and column.
#[derive(Debug, Error)]
pub enum FormatError {
    /// The file could not be opened, read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The CSV layer failed (malformed quoting, unequal row lengths).
    #[error("{path}: {message}")]
    Csv {
        /// The file.
        path: PathBuf,
        /// What the CSV reader said.
        message: String,
    },
    /// The header is not the expected one.
    #[error("{path}: line 1: header must start with `{expected}`, found `{found}`")]
    Header {
        /// The file.
        path: PathBuf,
        /// The expected leading columns.
        expected: String,
        /// What was found.
        found: String,
    },
    /// A field has a bad value.
    #[error("{path}: line {line}, column `{column}`: {message} (value `{value}`)")]
    Value {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: u64,
        /// Column name.
        column: &'static str,
        /// The raw value.
        value: String,
        /// What is wrong, with units.
        message: String,
    },
    /// The file has a header but no data rows.
    #[error("{path}: no data rows")]
    Empty {
        /// The file.
        path: PathBuf,
    },
    /// No frame of the file has a single usable marker: nothing can be reconstructed.
    #[error(
        "{path}: no usable marker in any of its {frames} frame(s): every marker is lost \
         (empty or NaN displacement): {markers}; nothing can be reconstructed"
    )]
    NoUsableMarker {
        /// The file.
        path: PathBuf,
        /// Frames in the file.
        frames: usize,
        /// The lost markers, per layer (`blue: 0-259`).
        markers: String,
    },
}

/// Largest force component accepted from a file, N (1e6 N, 100 tonnes-force): far
/// beyond what any elastomer sensor survives, far below what `f64` sums can hold.
pub const MAX_FORCE_N: f64 = 1e6;

/// What a value read from a file may plausibly be on this sensor: positions within
/// the sensor's extent (the camera's field, the force grid and the marker grids)
/// widened by its size on every side, displacements no larger than its size. The
/// size is the diagonal of that extent (at least the elastomer's thickness), so the
/// bounds are generous for real data and still refuse 1e9 mm or 1e300 mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plausible {
    /// Sensor extent `[x_min, y_min, x_max, y_max]`, mm.
    pub extent_mm: [f64; 4],
    /// The sensor's size, mm.
    pub size_mm: f64,
}

impl Plausible {
    /// The bounds of `sensor`.
    pub fn of(sensor: &Sensor) -> Self {
        let cam = &sensor.camera;
        let mut pts = vec![
            cam.px_to_mm([0.0, 0.0]),
            cam.px_to_mm([cam.width_px as f64, cam.height_px as f64]),
        ];
        pts.extend(sensor.force_grid.nodes_mm());
        for l in &sensor.layers {
            if let Some(m) = &l.markers {
                let g = &m.grid;
                if !g.is_empty() {
                    pts.push(g.node_mm(0, 0));
                    pts.push(g.node_mm(g.nx - 1, g.ny - 1));
                }
            }
        }
        let mut e = [
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ];
        for p in pts.iter().filter(|p| p[0].is_finite() && p[1].is_finite()) {
            e = [
                e[0].min(p[0]),
                e[1].min(p[1]),
                e[2].max(p[0]),
                e[3].max(p[1]),
            ];
        }
        let size = (e[2] - e[0])
            .hypot(e[3] - e[1])
            .max(sensor.elastomer.thickness_mm);
        Plausible {
            extent_mm: e,
            size_mm: size,
        }
    }

    /// `Err(what is allowed)` when coordinate `axis` (0 = x, 1 = y) of a position is
    /// outside the widened extent.
    pub fn position(&self, axis: usize, v_mm: f64) -> Result<(), String> {
        let lo = self.extent_mm[axis] - self.size_mm;
        let hi = self.extent_mm[axis + 2] + self.size_mm;
        if (lo..=hi).contains(&v_mm) {
            Ok(())
        } else {
            Err(format!(
                "position {} mm is outside the sensor: it must lie within {} ... {} mm (the \
                 sensor's extent {} ... {} mm, widened by its size {} mm)",
                crate::units::fmt_num(v_mm),
                crate::units::fmt_num(lo),
                crate::units::fmt_num(hi),
                crate::units::fmt_num(self.extent_mm[axis]),
                crate::units::fmt_num(self.extent_mm[axis + 2]),
                crate::units::fmt_num(self.size_mm)
            ))
        }
    }

    /// `Err(what is allowed)` when a displacement component is larger than the sensor.
    pub fn displacement(&self, v_mm: f64) -> Result<(), String> {
        if v_mm.abs() <= self.size_mm {
            Ok(())
        } else {
            Err(format!(
                "displacement {v_mm:.3e} mm is larger than the sensor itself ({} mm across): \
                 no marker can move that far (is the unit mm?)",
                crate::units::fmt_num(self.size_mm)
            ))
        }
    }
}

/// `Err(what is allowed)` when a force component is beyond [`MAX_FORCE_N`].
pub fn plausible_force(v_n: f64) -> Result<(), String> {
    if v_n.abs() <= MAX_FORCE_N {
        Ok(())
    } else {
        Err(format!(
            "force {} N is beyond {} N: no elastomer sensor carries that (is the unit N?)",
            crate::units::fmt_num(v_n),
            crate::units::fmt_num(MAX_FORCE_N)
        ))
    }
}

/// Refuses a displacement file in which no frame has a single usable marker (every
/// row lost): the error names the file, the frame count and the lost markers per
/// layer (id ranges, the first ones when there are many).
pub fn require_usable_marker(
    frames: &[DisplacementFrame],
    sensor: &Sensor,
    path: &Path,
) -> Result<(), FormatError> {
    if frames
        .iter()
        .any(|f| f.records.iter().any(|r| r.u_mm.is_some()))
    {
        return Ok(());
    }
    let mut per_layer: Vec<Vec<u64>> = vec![Vec::new(); sensor.layers.len()];
    for f in frames {
        for r in &f.records {
            per_layer[r.layer].push(r.marker);
        }
    }
    let markers: Vec<String> = per_layer
        .iter_mut()
        .zip(&sensor.layers)
        .filter(|(ids, _)| !ids.is_empty())
        .map(|(ids, l)| {
            ids.sort_unstable();
            ids.dedup();
            format!("{} ({} lost: {})", l.name, ids.len(), id_ranges(ids, 8))
        })
        .collect();
    Err(FormatError::NoUsableMarker {
        path: path.to_path_buf(),
        frames: frames.len(),
        markers: markers.join("; "),
    })
}

/// The value of a field for a message: as written, unless that is long (`1` and 306
/// zeros), then in scientific notation.
fn short_value(raw: &str, v: f64) -> String {
    if raw.len() > 24 {
        format!("{v:.3e}")
    } else {
        raw.to_string()
    }
}

/// Sorted ids as ranges (`0-9, 12, 20-25`), at most `max` ranges then `…`.
fn id_ranges(ids: &[u64], max: usize) -> String {
    let mut ranges: Vec<(u64, u64)> = Vec::new();
    for &id in ids {
        match ranges.last_mut() {
            Some((_, hi)) if id == *hi + 1 => *hi = id,
            _ => ranges.push((id, id)),
        }
    }
    let mut out: Vec<String> = ranges
        .iter()
        .take(max)
        .map(|&(a, b)| {
            if a == b {
                a.to_string()
            } else {
                format!("{a}-{b}")
            }
        })
        .collect();
    if ranges.len() > max {
        out.push(format!("... ({} more ranges)", ranges.len() - max));
    }
    out.join(", ")
}

/// One marker's row of a displacement file, after validation.
#[derive(Debug, Clone, PartialEq)]
pub struct DisplacementRecord {
    /// Index of the layer in the sensor.
    pub layer: usize,
    /// Marker id within the layer.
    pub marker: u64,
    /// Reference position, mm.
    pub position_mm: [f64; 2],
    /// Displacement, mm; `None` when the marker was lost.
    pub u_mm: Option<[f64; 2]>,
    /// 1-based line in the file.
    pub line: u64,
}

/// One frame of displacements, ready for a solver.
#[derive(Debug, Clone, PartialEq)]
pub struct DisplacementFrame {
    /// The frame label (`""` when the file has no `frame` column).
    pub frame: String,
    /// Every row of the frame, lost markers included.
    pub records: Vec<DisplacementRecord>,
}

impl DisplacementFrame {
    /// The markers that carry data (lost ones dropped), in file order.
    pub fn sites(&self, sensor: &Sensor) -> Vec<MarkerSite> {
        self.records
            .iter()
            .filter(|r| r.u_mm.is_some())
            .map(|r| MarkerSite {
                layer: r.layer,
                position_mm: r.position_mm,
                depth_mm: sensor.layers[r.layer].depth_mm,
            })
            .collect()
    }

    /// Interleaved `ux, uy` (mm) of the markers that carry data, matching [`Self::sites`].
    pub fn u_mm(&self) -> Vec<f64> {
        self.records
            .iter()
            .filter_map(|r| r.u_mm)
            .flat_map(|u| u.into_iter())
            .collect()
    }

    /// The lost markers: `(layer index, marker id)`.
    pub fn lost(&self) -> Vec<(usize, u64)> {
        self.records
            .iter()
            .filter(|r| r.u_mm.is_none())
            .map(|r| (r.layer, r.marker))
            .collect()
    }
}

fn csv_error(path: &Path, e: csv::Error) -> FormatError {
    FormatError::Csv {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// Reads a displacement file, validated against the sensor's layer names.
///
/// Rejected (with file, line, column and value): a wrong header, unknown layer names,
/// non-integer marker ids, non-finite positions, infinite displacements, a displacement
/// with one component given and the other empty, duplicate `(layer, marker)` pairs
/// within a frame, and files without rows.
pub fn read_displacements(
    path: &Path,
    sensor: &Sensor,
) -> Result<Vec<DisplacementFrame>, FormatError> {
    let file = std::fs::File::open(path).map_err(|source| FormatError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    read_displacements_from(file, path, sensor)
}

/// As [`read_displacements`], from any reader; `path` is used in messages only.
pub fn read_displacements_from(
    reader: impl std::io::Read,
    path: &Path,
    sensor: &Sensor,
) -> Result<Vec<DisplacementFrame>, FormatError> {
    let mut rdr = csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .from_reader(reader);
    let headers = rdr.headers().map_err(|e| csv_error(path, e))?.clone();
    let lead: Vec<&str> = headers.iter().take(6).collect();
    if lead != DISPLACEMENT_COLUMNS {
        return Err(FormatError::Header {
            path: path.to_path_buf(),
            expected: DISPLACEMENT_COLUMNS.join(","),
            found: headers.iter().collect::<Vec<_>>().join(","),
        });
    }
    let frame_col = headers.iter().position(|h| h == "frame");
    let plausible = Plausible::of(sensor);

    let mut frames: Vec<DisplacementFrame> = Vec::new();
    let mut seen: Vec<HashSet<(usize, u64)>> = Vec::new();
    for result in rdr.records() {
        let rec = result.map_err(|e| csv_error(path, e))?;
        let line = rec.position().map(|p| p.line()).unwrap_or(0);
        let bad = |column: &'static str, value: &str, message: String| FormatError::Value {
            path: path.to_path_buf(),
            line,
            column,
            value: value.to_string(),
            message,
        };
        let layer_name = &rec[0];
        let layer = sensor.layer_index(layer_name).ok_or_else(|| {
            let names: Vec<&str> = sensor.layers.iter().map(|l| l.name.as_str()).collect();
            bad(
                "layer",
                layer_name,
                format!("unknown layer: the sensor has {}", names.join(", ")),
            )
        })?;
        let marker: u64 = rec[1].parse().map_err(|_| {
            bad(
                "marker",
                &rec[1],
                "marker id must be a non-negative integer".into(),
            )
        })?;
        let mut pos = [0.0; 2];
        for (i, col) in [(2usize, "x_mm"), (3, "y_mm")] {
            let v: f64 = rec[i]
                .parse()
                .map_err(|_| bad(col, &rec[i], "expected a number in mm".into()))?;
            if !v.is_finite() {
                return Err(bad(
                    col,
                    &rec[i],
                    "reference position must be finite (mm)".into(),
                ));
            }
            let axis = if i == 2 { 0 } else { 1 };
            plausible
                .position(axis, v)
                .map_err(|m| bad(col, &short_value(&rec[i], v), m))?;
            pos[axis] = v;
        }
        let mut comp = [None; 2];
        for (k, (i, col)) in [(4usize, "ux_mm"), (5, "uy_mm")].into_iter().enumerate() {
            let raw = &rec[i];
            if raw.is_empty() {
                continue;
            }
            let v: f64 = raw.parse().map_err(|_| {
                bad(
                    col,
                    raw,
                    "expected a number in mm, or empty / NaN for a lost marker".into(),
                )
            })?;
            if v.is_infinite() {
                return Err(bad(
                    col,
                    raw,
                    "displacement is infinite: use empty or NaN to mark a lost marker".into(),
                ));
            }
            if !v.is_nan() {
                plausible
                    .displacement(v)
                    .map_err(|m| bad(col, &short_value(raw, v), m))?;
                comp[k] = Some(v);
            }
        }
        let u_mm = match comp {
            [Some(x), Some(y)] => Some([x, y]),
            [None, None] => None,
            _ => {
                let (col, raw) = if comp[0].is_none() {
                    ("ux_mm", &rec[4])
                } else {
                    ("uy_mm", &rec[5])
                };
                return Err(bad(
                    col,
                    raw,
                    "one displacement component is missing: give both or neither".into(),
                ));
            }
        };
        let frame_label = frame_col.and_then(|c| rec.get(c)).unwrap_or("").to_string();
        let fi = match frames.iter().position(|f| f.frame == frame_label) {
            Some(i) => i,
            None => {
                frames.push(DisplacementFrame {
                    frame: frame_label,
                    records: Vec::new(),
                });
                seen.push(HashSet::new());
                frames.len() - 1
            }
        };
        if !seen[fi].insert((layer, marker)) {
            return Err(bad(
                "marker",
                &rec[1],
                format!("duplicate marker id in layer `{layer_name}`"),
            ));
        }
        frames[fi].records.push(DisplacementRecord {
            layer,
            marker,
            position_mm: pos,
            u_mm,
            line,
        });
    }
    if frames.is_empty() {
        return Err(FormatError::Empty {
            path: path.to_path_buf(),
        });
    }
    Ok(frames)
}

/// Writes a displacement file (one frame) with the required columns only.
pub fn write_displacements(
    path: &Path,
    sensor: &Sensor,
    records: &[DisplacementRecord],
) -> Result<(), FormatError> {
    let io = |source| FormatError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut w = std::io::BufWriter::new(std::fs::File::create(path).map_err(io)?);
    writeln!(w, "{}", DISPLACEMENT_COLUMNS.join(",")).map_err(io)?;
    let scale = max_finite_abs(records.iter().filter_map(|r| r.u_mm).flatten());
    for r in records {
        let name = &sensor.layers[r.layer].name;
        match r.u_mm {
            Some(u) => writeln!(
                w,
                "{name},{},{},{},{},{}",
                r.marker,
                Num(r.position_mm[0]),
                Num(r.position_mm[1]),
                NumRel(u[0], scale),
                NumRel(u[1], scale)
            ),
            None => writeln!(
                w,
                "{name},{},{},{},,",
                r.marker,
                Num(r.position_mm[0]),
                Num(r.position_mm[1])
            ),
        }
        .map_err(io)?;
    }
    w.flush().map_err(io)
}

/// Writes the forces of one or more frames. `frames` pairs a frame label with its force
/// vector (interleaved `fx, fy, fz` per node, N); the `frame` column is written only
/// when there is more than one frame.
pub fn write_forces(
    path: &Path,
    grid: &Grid,
    frames: &[(String, Vec<f64>)],
) -> Result<(), FormatError> {
    let io = |source| FormatError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut w = std::io::BufWriter::new(std::fs::File::create(path).map_err(io)?);
    write_forces_to(&mut w, grid, frames).map_err(io)?;
    w.flush().map_err(io)
}

/// As [`write_forces`], with the standard deviation of every force component (`sd`,
/// one vector per frame, same layout as the forces, N) in the columns
/// [`FORCE_SD_COLUMNS`] after `fz_n` (before `frame`).
pub fn write_forces_sd(
    path: &Path,
    grid: &Grid,
    frames: &[(String, Vec<f64>)],
    sd: &[Vec<f64>],
) -> Result<(), FormatError> {
    let io = |source| FormatError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut w = std::io::BufWriter::new(std::fs::File::create(path).map_err(io)?);
    write_forces_sd_to(&mut w, grid, frames, Some(sd)).map_err(io)?;
    w.flush().map_err(io)
}

/// As [`write_forces`], to any writer.
pub fn write_forces_to(
    w: &mut impl Write,
    grid: &Grid,
    frames: &[(String, Vec<f64>)],
) -> std::io::Result<()> {
    write_forces_sd_to(w, grid, frames, None)
}

/// As [`write_forces_sd`] (`sd: Some`) or [`write_forces`] (`None`), to any writer.
pub fn write_forces_sd_to(
    w: &mut impl Write,
    grid: &Grid,
    frames: &[(String, Vec<f64>)],
    sd: Option<&[Vec<f64>]>,
) -> std::io::Result<()> {
    let multi = frames.len() > 1;
    write!(w, "{}", FORCE_COLUMNS.join(","))?;
    if sd.is_some() {
        write!(w, ",{}", FORCE_SD_COLUMNS.join(","))?;
    }
    writeln!(w, "{}", if multi { ",frame" } else { "" })?;
    for (fi, (label, f)) in frames.iter().enumerate() {
        // Zero cut relative to the frame's largest force (and SD): see [`NumRel`].
        let scale = max_finite_abs(f.iter().copied());
        let sd_frame = sd.and_then(|s| s.get(fi));
        let sd_scale = sd_frame.map_or(0.0, |s| max_finite_abs(s.iter().copied()));
        for iy in 0..grid.ny {
            for ix in 0..grid.nx {
                let j = iy * grid.nx + ix;
                let p = grid.node_mm(ix, iy);
                write!(
                    w,
                    "{ix},{iy},{},{},{},{},{}",
                    Num(p[0]),
                    Num(p[1]),
                    NumRel(f[3 * j], scale),
                    NumRel(f[3 * j + 1], scale),
                    NumRel(f[3 * j + 2], scale)
                )?;
                if let Some(s) = sd_frame {
                    write!(
                        w,
                        ",{},{},{}",
                        NumRel(s[3 * j], sd_scale),
                        NumRel(s[3 * j + 1], sd_scale),
                        NumRel(s[3 * j + 2], sd_scale)
                    )?;
                }
                if multi {
                    write!(w, ",{label}")?;
                }
                writeln!(w)?;
            }
        }
    }
    Ok(())
}

/// One row of a forces file.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ForceRecord {
    /// Grid column.
    pub ix: usize,
    /// Grid row.
    pub iy: usize,
    /// Node position, mm.
    pub position_mm: [f64; 2],
    /// Force, N.
    pub f_n: [f64; 3],
}

/// Reads a forces file (the first frame's rows when there are several), as written:
/// what a run recorded is evidence, read back whatever it holds (NaN rows, the
/// forces of a flagged setpoint). [`read_forces_for`] checks input files.
pub fn read_forces(path: &Path) -> Result<Vec<ForceRecord>, FormatError> {
    read_forces_checked(path, None)
}

/// As [`read_forces`], for a forces file given as input (`model forward --forces`):
/// positions finite and within the sensor's plausible extent ([`Plausible`]), forces
/// finite (or NaN) and within [`MAX_FORCE_N`].
pub fn read_forces_for(path: &Path, sensor: &Sensor) -> Result<Vec<ForceRecord>, FormatError> {
    read_forces_checked(path, Some(&Plausible::of(sensor)))
}

/// The per-node standard deviations a forces file records in the columns
/// [`FORCE_SD_COLUMNS`] (`sfx_n, sfy_n, sfz_n`, N; first frame, in row order), or `None`
/// when the file has no such columns (written without uncertainty, or by a run from
/// before runs recorded it).
pub fn read_force_sd(path: &Path) -> Result<Option<Vec<[f64; 3]>>, FormatError> {
    let mut rdr = csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .from_path(path)
        .map_err(|e| csv_error(path, e))?;
    let headers = rdr.headers().map_err(|e| csv_error(path, e))?.clone();
    let col: Vec<Option<usize>> = FORCE_SD_COLUMNS
        .iter()
        .map(|c| headers.iter().position(|h| h == *c))
        .collect();
    let (Some(cx), Some(cy), Some(cz)) = (col[0], col[1], col[2]) else {
        return Ok(None);
    };
    let frame_col = headers.iter().position(|h| h == "frame");
    let mut first_frame: Option<String> = None;
    let mut out = Vec::new();
    for result in rdr.records() {
        let rec = result.map_err(|e| csv_error(path, e))?;
        if let Some(fc) = frame_col {
            let label = rec.get(fc).unwrap_or_default();
            match &first_frame {
                None => first_frame = Some(label.to_string()),
                Some(f) if f != label => break,
                Some(_) => {}
            }
        }
        let line = rec.position().map(|p| p.line()).unwrap_or(0);
        let mut sd = [0.0; 3];
        for (k, (c, name)) in [cx, cy, cz].iter().zip(FORCE_SD_COLUMNS).enumerate() {
            let text = rec.get(*c).unwrap_or_default();
            sd[k] = text
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_nan() || (v.is_finite() && *v >= 0.0))
                .ok_or_else(|| FormatError::Value {
                    path: path.to_path_buf(),
                    line,
                    column: name,
                    value: text.to_string(),
                    message: "expected a standard deviation in N (a number ≥ 0, or NaN)".into(),
                })?;
        }
        out.push(sd);
    }
    Ok(Some(out))
}

fn read_forces_checked(
    path: &Path,
    plausible: Option<&Plausible>,
) -> Result<Vec<ForceRecord>, FormatError> {
    let mut rdr = csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .from_path(path)
        .map_err(|e| csv_error(path, e))?;
    let headers = rdr.headers().map_err(|e| csv_error(path, e))?.clone();
    if headers.iter().take(7).collect::<Vec<_>>() != FORCE_COLUMNS {
        return Err(FormatError::Header {
            path: path.to_path_buf(),
            expected: FORCE_COLUMNS.join(","),
            found: headers.iter().collect::<Vec<_>>().join(","),
        });
    }
    let mut out = Vec::new();
    for result in rdr.records() {
        let rec = result.map_err(|e| csv_error(path, e))?;
        let line = rec.position().map(|p| p.line()).unwrap_or(0);
        let bad = |i: usize, message: String| FormatError::Value {
            path: path.to_path_buf(),
            line,
            column: FORCE_COLUMNS[i],
            value: rec[i].to_string(),
            message,
        };
        let num = |i: usize| -> Result<f64, FormatError> {
            let v = rec[i]
                .parse::<f64>()
                .map_err(|_| bad(i, "expected a number".into()))?;
            let Some(p) = plausible else {
                return Ok(v);
            };
            // NaN forces are what `reconstruct` writes for a frame it could not solve.
            if v.is_infinite() || (v.is_nan() && i < 4) {
                return Err(bad(i, "must be a finite number".into()));
            }
            match i {
                2 | 3 => p.position(i - 2, v).map_err(|m| bad(i, m))?,
                4..=6 if !v.is_nan() => plausible_force(v).map_err(|m| bad(i, m))?,
                _ => {}
            }
            Ok(v)
        };
        out.push(ForceRecord {
            ix: num(0)? as usize,
            iy: num(1)? as usize,
            position_mm: [num(2)?, num(3)?],
            f_n: [num(4)?, num(5)?, num(6)?],
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sensor::paper_sensor;

    fn read(text: &str) -> Result<Vec<DisplacementFrame>, FormatError> {
        read_displacements_from(text.as_bytes(), Path::new("d.csv"), &paper_sensor())
    }

    #[test]
    fn reads_rows_and_drops_lost_markers() {
        let f = read("layer,marker,x_mm,y_mm,ux_mm,uy_mm\nblue,0,0,0,0.01,-0.02\nred,3,0.75,0.75,,\nred,4,2.25,0.75,NaN,NaN\n").unwrap();
        assert_eq!(f.len(), 1);
        let s = paper_sensor();
        assert_eq!(f[0].sites(&s).len(), 1);
        assert_eq!(f[0].u_mm(), vec![0.01, -0.02]);
        assert_eq!(f[0].lost(), vec![(1, 3), (1, 4)]);
        assert_eq!(f[0].sites(&s)[0].depth_mm, 3.0);
    }

    #[test]
    fn groups_frames_by_frame_column_and_accepts_extra_columns() {
        let t = "layer,marker,x_mm,y_mm,ux_mm,uy_mm,frame,status\nblue,0,0,0,0.1,0,a.png,ok\nblue,0,0,0,0.2,0,b.png,ok\n";
        let f = read(t).unwrap();
        assert_eq!(f.len(), 2);
        assert_eq!(f[1].frame, "b.png");
    }

    #[test]
    fn rejects_bad_input_naming_line_column_and_value() {
        let h = "layer,marker,x_mm,y_mm,ux_mm,uy_mm\n";
        let e = read(&format!("{h}blue,0,0,0,0,0\ngreen,1,0,0,0,0\n"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("line 3")
                && e.contains("`layer`")
                && e.contains("green")
                && e.contains("blue, red"),
            "{e}"
        );
        let e = read(&format!("{h}blue,0,0,0,inf,0\n"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("line 2") && e.contains("ux_mm") && e.contains("infinite"),
            "{e}"
        );
        let e = read(&format!("{h}blue,0,0,0,abc,0\n"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("abc") && e.contains("mm"), "{e}");
        let e = read(&format!("{h}blue,0,0,0,0.1,\n"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("uy_mm") && e.contains("both or neither"), "{e}");
        let e = read(&format!("{h}blue,0,0,0,0,0\nblue,0,1,0,0,0\n"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("duplicate"), "{e}");
        let e = read("x,y\n1,2\n").unwrap_err().to_string();
        assert!(e.contains("header"), "{e}");
        assert!(matches!(read(h), Err(FormatError::Empty { .. })));
    }

    #[test]
    fn forces_round_trip() {
        let s = paper_sensor();
        let f: Vec<f64> = (0..240).map(|i| i as f64 * 0.125 - 3.0).collect();
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("f.csv");
        write_forces(&p, &s.force_grid, &[(String::new(), f.clone())]).unwrap();
        let back = read_forces(&p).unwrap();
        assert_eq!(back.len(), 80);
        assert_eq!(back[11].ix, 1);
        assert_eq!(back[11].iy, 1);
        assert_eq!(back[11].f_n, [f[33], f[34], f[35]]);
    }

    #[test]
    fn csv_numbers_drop_binary_noise_and_keep_measured_digits() {
        let show = |v: f64| Num(v).to_string();
        assert_eq!(show(7.8500000000000005), "7.85");
        assert_eq!(show(29.999000000000002), "29.999");
        assert_eq!(show(-2.220446049250313e-16), "0");
        assert_eq!(show(0.1 + 0.2), "0.3");
        assert_eq!(show(-0.0), "0");
        assert_eq!(show(f64::NAN), "NaN");
        assert_eq!(show(50.0), "50");
        assert_eq!(show(-100.0), "-100");
        assert_eq!(show(0.049033249999999996), "0.04903325");
        assert_eq!(show(1.5e-9), "1.5e-9");
        assert_eq!(show(123_456.789_012_345), "123456.789012");
        // A value read back is within 5e-12 relative of what was computed.
        for v in [std::f64::consts::PI, 1e-7 / 3.0, -2.0 / 3.0 * 1e6] {
            let back: f64 = show(v).parse().unwrap();
            assert!(((back - v) / v).abs() <= 5e-12, "{v} -> {back}");
        }
        assert_eq!(tidy_csv_field("7.8500000000000005"), "7.85");
        assert_eq!(tidy_csv_field("-2.22e-16"), "0");
        assert_eq!(tidy_csv_field("12"), "12");
        assert_eq!(tidy_csv_field("frames/00001_0.png"), "frames/00001_0.png");
        assert_eq!(
            tidy_csv_field("2026-11-24T00:00:00Z"),
            "2026-11-24T00:00:00Z"
        );
        assert_eq!(tidy_csv_field("NaN"), "NaN");
        assert_eq!(tidy_csv_field("true"), "true");
    }
}
