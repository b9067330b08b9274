//! `tactbench import`: a folder of frames + a CSV of F/T readings -> a run directory
//! (library: [`tactbench::bench::import`]).

use std::path::PathBuf;
use std::process::ExitCode;

use tactbench::bench::import::{self, ImportOptions};
use tactbench::units::ForceUnit;

/// Import a recording made elsewhere: frames + F/T readings per frame -> a run directory.
///
/// Reads every frame named in WRENCH.csv from DIR, tracks it against the unloaded
/// reference with the default tracker, and writes RUN_DIR as `run` would (manifest with
/// `source: "import"`, journal, frames/NNNNN_0.png, displacements/, forces/ when the
/// sensor file is measured, integrity digests), so that `track`, `report` and `fit`
/// read it. Greyscale frames (8- and 16-bit) serve `dark` and `bright` layers.
///
/// WRENCH.csv: a header and one row per frame. Our column names (the keys of --map)
/// and the CSV columns read by default: frame (`frame`: the file name in DIR), fx, fy,
/// fz (`fx_n`, `fy_n`, `fz_n`: force, in --force-unit), mx, my, mz (`mx_nm`, `my_nm`,
/// `mz_nm`: torque, N·m, optional: all three or none), x, y (`x_mm`, `y_mm`: contact
/// position in the sensor frame, mm, optional), depth (`depth_mm`: indentation depth,
/// mm, > 0 presses, optional). Other columns are ignored.
///
/// Reference (unloaded) frame: --reference FILE, else the row with the smallest |F|
/// (the first of equals); the manifest says which and why.
///
/// Exit status: 0 imported; 2 bad input (nothing usable written: a frame name that
/// matches no file, a non-numeric or non-finite value, a missing column, a duplicate
/// frame name, frames of another size than the sensor's [camera], an existing
/// non-empty RUN_DIR), naming the file, line, column and value.
#[derive(clap::Args)]
#[command(allow_negative_numbers = true)]
pub struct Args {
    /// Folder holding the frames (PNG, JPEG or BMP; RGB or 8/16-bit greyscale).
    #[arg(long, value_name = "DIR")]
    frames: PathBuf,
    /// F/T readings, one row per frame, keyed by frame file name.
    #[arg(long, value_name = "WRENCH.csv")]
    wrench: PathBuf,
    /// Column names: OURS=THEIRS pairs, comma-separated, e.g.
    /// `fx=Fx_N,fz=force_z,frame=filename`. OURS is one of frame, fx, fy, fz, mx, my,
    /// mz, x, y, depth (defaults: frame, fx_n, fy_n, fz_n, mx_nm, my_nm, mz_nm, x_mm,
    /// y_mm, depth_mm). A mapped column must exist.
    #[arg(long, value_name = "OURS=THEIRS,...", value_delimiter = ',', value_parser = pair)]
    map: Vec<(String, String)>,
    /// Unit of fx, fy, fz in the CSV: N or gf (torques are always N·m).
    #[arg(long, value_name = "UNIT", default_value = "N")]
    force_unit: ForceUnit,
    /// Sensor description (sensor.toml); a draft (`sensor init`) tracks but does not
    /// reconstruct forces.
    #[arg(long, value_name = "S.toml")]
    sensor: PathBuf,
    /// Reference (unloaded) frame: a file name in DIR. Default: the row with the
    /// smallest |F|.
    #[arg(long, value_name = "FILE")]
    reference: Option<String>,
    /// Contact position X,Y (mm, sensor frame) of every row, when the CSV has no x, y
    /// columns. Without either: the middle of the marker grid (the manifest says so).
    #[arg(long, value_name = "X,Y", value_delimiter = ',', num_args = 2)]
    position: Option<Vec<f64>>,
    /// Indenter for the synthesised plan: point, flat:DIAMETER_MM or
    /// hemisphere:DIAMETER_MM (fit's indentation route needs the shape).
    #[arg(long, value_name = "SHAPE[:D_MM]", default_value = "point", value_parser = indenter)]
    indenter: (String, Option<f64>),
    /// Output run directory (new or empty).
    #[arg(long, value_name = "RUN_DIR")]
    out: PathBuf,
}

fn pair(s: &str) -> Result<(String, String), String> {
    let (a, b) = s
        .split_once('=')
        .ok_or_else(|| format!("{s:?} is not OURS=THEIRS (e.g. fx=Fx_N)"))?;
    let (a, b) = (a.trim(), b.trim());
    if !import::COLUMNS.contains(&a) {
        return Err(format!(
            "`{a}` is not one of our columns: {}",
            import::COLUMNS.join(", ")
        ));
    }
    if b.is_empty() {
        return Err(format!("{s:?}: empty CSV column name"));
    }
    Ok((a.to_string(), b.to_string()))
}

fn indenter(s: &str) -> Result<(String, Option<f64>), String> {
    let (shape, d) = match s.split_once(':') {
        Some((a, b)) => (a, Some(b)),
        None => (s, None),
    };
    let d = d
        .map(|d| {
            d.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite() && *v > 0.0)
                .ok_or_else(|| format!("diameter {d:?} is not a positive number of mm"))
        })
        .transpose()?;
    match (shape, d) {
        ("point", None) => Ok(("point".into(), None)),
        ("flat" | "hemisphere", Some(d)) => Ok((shape.into(), Some(d))),
        ("flat" | "hemisphere", None) => Err(format!("{shape} needs a diameter: {shape}:5.0 (mm)")),
        ("point", Some(_)) => Err("a point indenter has no diameter".into()),
        (other, _) => Err(format!(
            "unknown indenter `{other}`: point, flat:D_MM or hemisphere:D_MM"
        )),
    }
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let o = ImportOptions {
        frames_dir: args.frames,
        wrench_csv: args.wrench,
        map: args.map,
        force_unit: args.force_unit,
        sensor_path: args.sensor,
        reference: args.reference,
        position_mm: args.position.map(|p| [p[0], p[1]]),
        indenter: args.indenter,
        out: args.out,
    };
    let s = import::import(&o)?;
    eprintln!(
        "imported {} frames into {} (reference {})",
        s.rows,
        o.out.display(),
        s.reference
    );
    if s.flagged > 0 {
        eprintln!(
            "note: {} of {} rows tracked below the quality gate (quality = flagged)",
            s.flagged, s.rows
        );
    }
    if let Some(why) = &s.unreconstructed {
        eprintln!("note: forces {why}");
    }
    if s.unused_frames > 0 {
        eprintln!(
            "note: {} file(s) in {} are named by no CSV row and were left out",
            s.unused_frames,
            o.frames_dir.display()
        );
    }
    Ok(ExitCode::SUCCESS)
}
