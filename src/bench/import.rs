//! `tactbench import`: a recording made elsewhere (a folder of frames and a CSV of F/T
//! readings keyed by frame file name) turned into a run directory that `track`,
//! `report` and `fit` read like one the runner wrote (issue 30, item 7).
//!
//! What is written (docs/import.md is the reference):
//! - `frames/NNNNN_0.png`: each CSV row's frame, in CSV order (PNG files copied byte
//!   for byte, so 16-bit greyscale stays 16-bit; other formats decoded and saved as
//!   PNG), `frames/reference.png`: the unloaded reference;
//! - `displacements/NNNNN.csv`: tracked with the default tracker against the reference;
//! - `forces/NNNNN.csv` and `fsum_*`: reconstructed with the plan's default solver when
//!   the sensor file is measured; a draft sensor (`sensor init`) leaves them out and
//!   every row says why in `failure` (fit needs no force sums);
//! - `journal.csv`: one row per CSV row (the wrench as given, SD 0: one reading per
//!   frame; `stage_x_mm`, `stage_y_mm` the contact position, `stage_z_mm` the
//!   indentation depth when given, else 0 and `bench.recorded.depth = false`);
//! - `manifest.json`: `source: "import"`, a synthesised explicit `setpoints` plan (the
//!   measured wrench as its targets), the sensor file's text, `bench` = the import's
//!   description, every device `replayed` ("imported recording"), and the integrity
//!   digests of the journal and every evidence file (`bench::integrity`).

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use thiserror::Error;

use crate::bench::integrity::{file_sha256, RecordDigests};
use crate::bench::journal::{
    self, DeviceProvenance, Journal, JournalError, JournalRow, Manifest, Provenance, RowQuality,
    RunStatus, Session, StepTimes,
};
use crate::bench::plan::{Plan, Setpoint};
use crate::device::Wrench;
use crate::formats::DisplacementFrame;
use crate::sensor::Sensor;
use crate::solve::{self, Problem};
use crate::units::ForceUnit;
use crate::vision::{self, DetectConfig, PixelMapping, StatusCounts, TrackConfig, Tracker};

/// Our column names (the keys of `--map`), in the order `--help` lists them.
pub const COLUMNS: [&str; 10] = [
    "frame", "fx", "fy", "fz", "mx", "my", "mz", "x", "y", "depth",
];

/// The CSV column each of [`COLUMNS`] is read from when `--map` does not say.
pub const DEFAULT_COLUMNS: [&str; 10] = [
    "frame", "fx_n", "fy_n", "fz_n", "mx_nm", "my_nm", "mz_nm", "x_mm", "y_mm", "depth_mm",
];

/// Columns every WRENCH.csv must have.
const REQUIRED: [&str; 4] = ["frame", "fx", "fy", "fz"];

/// Unmatched frame names listed in an error before "and N more".
const LIST_FIRST: usize = 5;

/// Why an import failed. `Input` is bad input (exit 2): it names the file, and the
/// line, column and value where there is one.
#[derive(Debug, Error)]
pub enum ImportError {
    /// Bad input: the file at fault and what is wrong with it.
    #[error("{path}: {message}")]
    Input {
        /// File or directory at fault.
        path: PathBuf,
        /// Line, column, value and what was expected.
        message: String,
    },
    /// Writing the run directory failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// Writing the journal or manifest failed.
    #[error(transparent)]
    Journal(#[from] JournalError),
}

fn bad(path: &Path, message: impl Into<String>) -> ImportError {
    ImportError::Input {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// What to import and how.
#[derive(Debug, Clone)]
pub struct ImportOptions {
    /// Folder of frames.
    pub frames_dir: PathBuf,
    /// The F/T readings, one row per frame.
    pub wrench_csv: PathBuf,
    /// `(our name, CSV column)` pairs from `--map`.
    pub map: Vec<(String, String)>,
    /// Unit of the force columns (torques are N·m).
    pub force_unit: ForceUnit,
    /// Sensor file.
    pub sensor_path: PathBuf,
    /// Reference frame file name in `frames_dir`; `None`: the row with the smallest |F|.
    pub reference: Option<String>,
    /// Contact position for every row when the CSV has no x, y columns, mm.
    pub position_mm: Option<[f64; 2]>,
    /// The indenter for the plan: `flat`, `hemisphere` or `point`, and its diameter.
    pub indenter: (String, Option<f64>),
    /// Output run directory (must not exist or be empty).
    pub out: PathBuf,
}

/// One WRENCH.csv row, in N, N·m and mm.
#[derive(Debug, Clone, PartialEq)]
pub struct WrenchRow {
    /// Frame file name as given.
    pub frame: String,
    /// 1-based CSV line.
    pub line: u64,
    /// fx, fy, fz, N.
    pub force_n: [f64; 3],
    /// mx, my, mz, N·m (0 when the CSV has no torques: `recorded.torques = false`).
    pub torque_nm: [f64; 3],
    /// Contact position, mm, sensor frame, when the CSV has x, y.
    pub position_mm: Option<[f64; 2]>,
    /// Indentation depth, mm (> 0 presses), when the CSV has it.
    pub depth_mm: Option<f64>,
}

/// What an import did, for the command's summary.
#[derive(Debug, Clone, PartialEq)]
pub struct ImportSummary {
    /// Rows (setpoints) written.
    pub rows: usize,
    /// The reference frame and the rule that chose it.
    pub reference: String,
    /// Rows flagged for tracking quality.
    pub flagged: usize,
    /// Rows without reconstructed forces, and why (the first reason).
    pub unreconstructed: Option<String>,
    /// Frames in the folder that no CSV row names (left out).
    pub unused_frames: usize,
}

/// Reads WRENCH.csv with the column map: every row's frame name, wrench, position and
/// depth, or an error naming the line, column and value.
pub fn read_wrench(
    path: &Path,
    map: &[(String, String)],
    unit: ForceUnit,
) -> Result<(Vec<WrenchRow>, BTreeMap<String, bool>), ImportError> {
    let mut names: HashMap<&str, String> = COLUMNS
        .iter()
        .zip(DEFAULT_COLUMNS)
        .map(|(k, v)| (*k, v.to_string()))
        .collect();
    let mut mapped = Vec::new();
    for (ours, theirs) in map {
        let Some(slot) = names.get_mut(ours.as_str()) else {
            return Err(bad(
                path,
                format!(
                    "--map names `{ours}`, which is not one of our columns ({})",
                    COLUMNS.join(", ")
                ),
            ));
        };
        *slot = theirs.clone();
        mapped.push(ours.as_str());
    }
    let mut rdr = csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .from_path(path)
        .map_err(|e| bad(path, e.to_string()))?;
    let headers = rdr.headers().map_err(|e| bad(path, e.to_string()))?.clone();
    let index: HashMap<&str, usize> = COLUMNS
        .iter()
        .filter_map(|k| {
            let col = &names[k];
            headers.iter().position(|h| h == col).map(|i| (*k, i))
        })
        .collect();
    for k in COLUMNS {
        let must = REQUIRED.contains(&k) || mapped.contains(&k);
        if must && !index.contains_key(k) {
            return Err(bad(
                path,
                format!(
                    "line 1: no column `{}` (our `{k}`{}); the header has: {} (map a column with --map {k}=NAME)",
                    names[k],
                    if mapped.contains(&k) { ", from --map" } else { ", by default" },
                    headers.iter().collect::<Vec<_>>().join(", ")
                ),
            ));
        }
    }
    let has = |k: &str| index.contains_key(k);
    if has("x") != has("y") {
        return Err(bad(
            path,
            format!(
                "line 1: a contact position needs both x and y columns (found only `{}`)",
                if has("x") { &names["x"] } else { &names["y"] }
            ),
        ));
    }
    let torques = ["mx", "my", "mz"].iter().filter(|k| has(k)).count();
    if torques != 0 && torques != 3 {
        return Err(bad(
            path,
            "line 1: torques need all three columns mx, my, mz (or none)",
        ));
    }
    let mut rows: Vec<WrenchRow> = Vec::new();
    let mut seen: HashMap<String, u64> = HashMap::new();
    for rec in rdr.records() {
        let rec = rec.map_err(|e| bad(path, e.to_string()))?;
        let line = rec.position().map_or(0, |p| p.line());
        let num = |k: &str| -> Result<Option<f64>, ImportError> {
            let Some(&i) = index.get(k) else {
                return Ok(None);
            };
            let text = rec.get(i).unwrap_or("");
            match text.parse::<f64>() {
                Ok(v) if v.is_finite() => Ok(Some(v)),
                Ok(v) => Err(bad(
                    path,
                    format!(
                        "line {line}, column `{}`: value {v} is not a finite number",
                        names[k]
                    ),
                )),
                Err(_) => Err(bad(
                    path,
                    format!(
                        "line {line}, column `{}`: value {text:?} is not a number",
                        names[k]
                    ),
                )),
            }
        };
        let frame = rec.get(index["frame"]).unwrap_or("").to_string();
        if frame.is_empty() {
            return Err(bad(
                path,
                format!("line {line}, column `{}`: empty frame name", names["frame"]),
            ));
        }
        if let Some(first) = seen.insert(frame.clone(), line) {
            return Err(bad(
                path,
                format!(
                    "line {line}, column `{}`: frame {frame:?} appears twice (first on line {first})",
                    names["frame"]
                ),
            ));
        }
        let f = |k| -> Result<f64, ImportError> { Ok(unit.to_newtons(num(k)?.unwrap_or(0.0))) };
        let t = |k| -> Result<f64, ImportError> { Ok(num(k)?.unwrap_or(0.0)) };
        let position_mm = match (num("x")?, num("y")?) {
            (Some(x), Some(y)) => Some([x, y]),
            _ => None,
        };
        rows.push(WrenchRow {
            frame,
            line,
            force_n: [f("fx")?, f("fy")?, f("fz")?],
            torque_nm: [t("mx")?, t("my")?, t("mz")?],
            position_mm,
            depth_mm: num("depth")?,
        });
    }
    if rows.is_empty() {
        return Err(bad(path, "no data rows (one row per frame is needed)"));
    }
    let recorded = BTreeMap::from([
        ("torques".to_string(), torques == 3),
        ("position".to_string(), has("x")),
        ("depth".to_string(), has("depth")),
    ]);
    Ok((rows, recorded))
}

/// Pairs every CSV row with a file of the frames folder (by file name), refusing
/// names that match no file (listing the first ones).
fn match_frames(dir: &Path, csv: &Path, rows: &[WrenchRow]) -> Result<usize, ImportError> {
    let entries = std::fs::read_dir(dir).map_err(|e| bad(dir, e.to_string()))?;
    let mut files = std::collections::BTreeSet::new();
    for e in entries.flatten() {
        if e.path().is_file() {
            files.insert(e.file_name().to_string_lossy().into_owned());
        }
    }
    let missing: Vec<&WrenchRow> = rows.iter().filter(|r| !files.contains(&r.frame)).collect();
    if !missing.is_empty() {
        let list: Vec<String> = missing
            .iter()
            .take(LIST_FIRST)
            .map(|r| format!("{:?} (line {})", r.frame, r.line))
            .collect();
        let more = missing.len().saturating_sub(LIST_FIRST);
        return Err(bad(
            csv,
            format!(
                "{} of {} frame names match no file in {}: {}{}",
                missing.len(),
                rows.len(),
                dir.display(),
                list.join(", "),
                if more > 0 {
                    format!(" and {more} more")
                } else {
                    String::new()
                }
            ),
        ));
    }
    Ok(files.len() - rows.len())
}

/// The reference frame: the named file, or the row with the smallest |F| (the first
/// of equals). Returns its file name and the rule in words.
fn choose_reference(
    rows: &[WrenchRow],
    given: Option<&str>,
    dir: &Path,
) -> Result<(String, String), ImportError> {
    if let Some(name) = given {
        if !dir.join(name).is_file() {
            return Err(bad(
                dir,
                format!("--reference {name:?}: no such file in the frames folder"),
            ));
        }
        return Ok((name.to_string(), "given (--reference)".to_string()));
    }
    let norm = |r: &WrenchRow| r.force_n.iter().map(|v| v * v).sum::<f64>().sqrt();
    let best = rows
        .iter()
        .min_by(|a, b| norm(a).total_cmp(&norm(b)))
        .ok_or_else(|| bad(dir, "no frames"))?;
    Ok((
        best.frame.clone(),
        format!(
            "the row with the smallest |F| ({:.4} N, line {})",
            norm(best),
            best.line
        ),
    ))
}

/// The synthesised explicit `setpoints` plan: one point per row, its measured wrench as
/// the target, limits that hold every reading.
fn plan_toml(rows: &[WrenchRow], positions: &[[f64; 2]], o: &ImportOptions) -> String {
    let mut max_f = [0.0f64; 3];
    for r in rows {
        for (m, f) in max_f.iter_mut().zip(r.force_n) {
            *m = m.max(f.abs());
        }
    }
    let limit = max_f.map(|v| (v * 2.0).max(1.0));
    let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
    for p in positions {
        for k in 0..2 {
            lo[k] = lo[k].min(p[k] - 1.0);
            hi[k] = hi[k].max(p[k] + 1.0);
        }
    }
    let deepest = rows
        .iter()
        .filter_map(|r| r.depth_mm)
        .fold(1.0f64, |a, d| a.max(d + 1.0));
    let diameter = match o.indenter.1 {
        Some(d) => format!("diameter_mm = {d:?}\n"),
        None => String::new(),
    };
    let mut t = format!(
        "# Synthesised by `tactbench import` from {} and {}: one point per frame, the\n\
         # measured wrench as its target (nothing was moved by tactbench).\n\
         name = \"import\"\nsensor = {:?}\nforce_unit = \"N\"\n\n\
         [indenter]\nshape = {:?}\n{diameter}\n\
         [approach]\nposition_mm = [{:?}, {:?}]\nspeed_mm_s = 1.0\ncontact_force = 0.01\n\n\
         [acquire]\nsamples = 1\nframes = 1\n\n\
         [safety]\nmax_force = [{:?}, {:?}, {:?}]\ntravel_min_mm = [{:?}, {:?}, -5.0]\n\
         travel_max_mm = [{:?}, {:?}, {:?}]\nmax_speed_mm_s = 5.0\n\n[sweep]\nkind = \"setpoints\"\n",
        o.frames_dir.display(),
        o.wrench_csv.display(),
        o.sensor_path.display().to_string(),
        o.indenter.0,
        positions[0][0],
        positions[0][1],
        limit[0],
        limit[1],
        limit[2],
        lo[0],
        lo[1],
        hi[0],
        hi[1],
        deepest
    );
    for (r, p) in rows.iter().zip(positions) {
        t.push_str(&format!(
            "\n[[sweep.points]]  # {}\nposition_mm = [{:?}, {:?}]\nnormal = {:?}\ntangential = [{:?}, {:?}]\n",
            r.frame,
            p[0],
            p[1],
            r.force_n[2].max(0.0),
            r.force_n[0],
            r.force_n[1]
        ));
    }
    t
}

/// Imports a recording into `o.out` (see the module docs).
///
/// Steps: the inputs read and checked (sensor file, frames folder, wrench CSV, the
/// frames it names, the reference, an empty `--out`); the synthesised plan; every
/// frame decoded before anything is written ([`load_frames`]); then per row the frame
/// copied, tracked, reconstructed and journalled ([`Importer::row`]); the record's
/// digests and the manifest last.
pub fn import(o: &ImportOptions) -> Result<ImportSummary, ImportError> {
    let sensor_toml = std::fs::read_to_string(&o.sensor_path).map_err(|e| ImportError::Io {
        path: o.sensor_path.clone(),
        source: e,
    })?;
    let sensor = Sensor::from_toml_str(&sensor_toml, &o.sensor_path)
        .map_err(|e| bad(&o.sensor_path, e.to_string()))?;
    if !o.frames_dir.is_dir() {
        return Err(bad(&o.frames_dir, "not a folder of frames"));
    }
    let (rows, recorded) = read_wrench(&o.wrench_csv, &o.map, o.force_unit)?;
    let unused = match_frames(&o.frames_dir, &o.wrench_csv, &rows)?;
    let (ref_name, ref_rule) = choose_reference(&rows, o.reference.as_deref(), &o.frames_dir)?;
    check_out(&o.out)?;
    let positions: Vec<[f64; 2]> = rows
        .iter()
        .map(|r| {
            r.position_mm
                .or(o.position_mm)
                .unwrap_or_else(|| grid_centre(&sensor))
        })
        .collect();
    let plan_text = plan_toml(&rows, &positions, o);
    let plan = Plan::from_toml_str(&plan_text, "import-plan.toml").map_err(|e| {
        bad(
            &o.wrench_csv,
            format!("the plan synthesised from it is invalid: {e}"),
        )
    })?;
    let setpoints = plan.setpoints();
    let ref_path = o.frames_dir.join(&ref_name);
    let (reference, frames) = load_frames(o, &sensor, &rows, &ref_path, &ref_name)?;
    let mapping = PixelMapping::Linear(sensor.camera);
    let detected = vision::detect_mapped(
        &reference.view(),
        &sensor,
        &DetectConfig::default(),
        &mapping,
    )
    .map_err(|e| bad(&ref_path, format!("reference frame: {e}")))?;

    std::fs::create_dir_all(o.out.join("frames")).map_err(|e| io(&o.out, e))?;
    std::fs::create_dir_all(o.out.join("displacements")).map_err(|e| io(&o.out, e))?;
    let mut evidence = BTreeMap::new();
    copy_frame(&ref_path, &o.out, "frames/reference.png", &mut evidence)?;
    let reconstruct = sensor.placeholders().is_empty();
    if reconstruct {
        std::fs::create_dir_all(o.out.join("forces")).map_err(|e| io(&o.out, e))?;
    }
    let not_reconstructed = (!reconstruct).then(|| {
        format!(
            "not reconstructed: the sensor file {} is a draft (placeholders {}); fit it (`tactbench fit`) and reconstruct with the fitted file",
            o.sensor_path.display(),
            sensor.placeholders().join(", ")
        )
    });
    let mut importer = Importer {
        o,
        sensor: &sensor,
        plan: &plan,
        mapping,
        missing: detected.missing.len(),
        tracker: Tracker::new(detected, TrackConfig::default()),
        solvers: HashMap::new(),
        evidence,
        not_reconstructed,
        now: crate::bench::runner::rfc3339_now(),
    };
    let mut journal = Journal::create(&o.out)?;
    let mut flagged = 0;
    for (i, ((r, f), sp)) in rows.iter().zip(&frames).zip(&setpoints).enumerate() {
        let row = importer.row(i, r, f, sp, positions[i])?;
        if row.quality != Some(RowQuality::Ok) {
            flagged += 1;
        }
        journal.append(&row)?;
    }
    drop(journal);
    let now = importer.now;
    let record = RecordDigests::journal_now(&o.out, importer.evidence, rows.len(), now.clone())
        .map_err(|e| io(&o.out.join(journal::JOURNAL_FILE), e))?;
    write_manifest(
        o,
        &plan_text,
        &sensor_toml,
        &recorded,
        &ref_name,
        &ref_rule,
        rows.len(),
        record,
        &now,
    )?;
    Ok(ImportSummary {
        rows: rows.len(),
        reference: format!("{ref_name}: {ref_rule}"),
        flagged,
        unreconstructed: importer.not_reconstructed,
        unused_frames: unused,
    })
}

/// The reference and every row's frame, decoded before anything is written: each
/// must decode and have the sensor's size, and the reference the sensor's layers.
fn load_frames(
    o: &ImportOptions,
    sensor: &Sensor,
    rows: &[WrenchRow],
    ref_path: &Path,
    ref_name: &str,
) -> Result<(vision::Frame, Vec<vision::Frame>), ImportError> {
    let reference =
        vision::load_frame(ref_path, &sensor.camera).map_err(|e| bad(ref_path, e.to_string()))?;
    let layers = || sensor.layers.iter().map(|l| (l.name.as_str(), l.color));
    vision::check_layers(&reference.view(), layers()).map_err(|e| bad(ref_path, e.to_string()))?;
    let mut frames = Vec::with_capacity(rows.len());
    for r in rows {
        let p = o.frames_dir.join(&r.frame);
        let f = vision::load_frame(&p, &sensor.camera).map_err(|e| {
            bad(
                &p,
                format!(
                    "{e} (line {} of {}; the reference {ref_name} is {}×{} px)",
                    r.line,
                    o.wrench_csv.display(),
                    reference.view().width_px(),
                    reference.view().height_px()
                ),
            )
        })?;
        frames.push(f);
    }
    Ok((reference, frames))
}

/// What importing the rows needs and keeps: the tracker against the reference, the
/// solvers per marker set, the evidence digests written so far.
struct Importer<'a> {
    o: &'a ImportOptions,
    sensor: &'a Sensor,
    plan: &'a Plan,
    mapping: PixelMapping,
    /// Grid nodes the reference has no marker for.
    missing: usize,
    tracker: Tracker,
    solvers: HashMap<Vec<bool>, Box<dyn solve::FrameSolver>>,
    evidence: BTreeMap<String, String>,
    /// Why nothing is reconstructed (a draft sensor file), else `None`.
    not_reconstructed: Option<String>,
    /// The rows' completion time (one import, one time).
    now: String,
}

impl Importer<'_> {
    /// Row `i` (CSV row `r`, frame `f`, setpoint `sp` at `position`): the frame
    /// copied, tracked and its displacements written; flagged below the plan's
    /// `min_ok_fraction`; reconstructed ([`Self::forces`]); the journal row.
    fn row(
        &mut self,
        i: usize,
        r: &WrenchRow,
        f: &vision::Frame,
        sp: &Setpoint,
        position: [f64; 2],
    ) -> Result<JournalRow, ImportError> {
        let o = self.o;
        let name = format!("frames/{i:05}_0.png");
        copy_frame(
            &o.frames_dir.join(&r.frame),
            &o.out,
            &name,
            &mut self.evidence,
        )?;
        let t0 = std::time::Instant::now();
        let tracks = self
            .tracker
            .track(&f.view())
            .map_err(|e| bad(&o.frames_dir.join(&r.frame), e.to_string()))?
            .to_vec();
        let t_track = t0.elapsed().as_secs_f64();
        let counts = StatusCounts::of(&tracks, self.missing);
        let dpath = format!("displacements/{i:05}.csv");
        let tracked = vec![(name.clone(), tracks)];
        vision::write_tracks_mapped(
            &o.out.join(&dpath),
            self.sensor,
            self.tracker.reference(),
            &tracked,
            &self.mapping,
        )
        .map_err(|e| bad(&o.out.join(&dpath), e.to_string()))?;
        digest(&o.out, &dpath, &mut self.evidence)?;
        let total = counts.ok + counts.lost + counts.merged + counts.outlier;
        let ok = total > 0 && counts.ok as f64 >= self.plan.quality.min_ok_fraction * total as f64;
        let t1 = std::time::Instant::now();
        let (fsum, failure) = self.forces(i, &tracked[0].1)?;
        let t_solve = if self.not_reconstructed.is_none() {
            t1.elapsed().as_secs_f64()
        } else {
            0.0
        };
        let quality = if ok {
            RowQuality::Ok
        } else {
            RowQuality::Flagged
        };
        let wrench = Wrench {
            force_n: r.force_n,
            torque_nm: r.torque_nm,
        };
        // No sweep placement and no F/T SDs: the CSV has one wrench a frame.
        Ok(JournalRow {
            completed_at: self.now.clone(),
            ft_status: Some(format!("imported: {} line {}", r.frame, r.line)),
            ..JournalRow::setpoint(i, sp.trial, sp.swept_value, sp.normal_n, sp.tangential_n)
                .with_wrench(&wrench, [0.0; 3])
                .at_stage([position[0], position[1], r.depth_mm.unwrap_or(0.0)], true)
                .with_frames(&[name], &counts, 0)
                .with_force_sum(fsum, None)
                .with_verdict(quality, failure, None)
                .timed(StepTimes {
                    track_s: t_track,
                    solve_s: t_solve,
                    ..StepTimes::default()
                })
        })
    }

    /// Row `i`'s force sums from its tracks, its forces written to
    /// `forces/NNNNN.csv`; NaN and why when the reconstruction failed or the sensor
    /// file is a draft.
    fn forces(
        &mut self,
        i: usize,
        tracks: &[vision::MarkerTrack],
    ) -> Result<([f64; 3], Option<String>), ImportError> {
        if self.not_reconstructed.is_some() {
            return Ok(([f64::NAN; 3], self.not_reconstructed.clone()));
        }
        let records = self
            .tracker
            .displacement_records_mapped(tracks, &self.mapping);
        let frame = DisplacementFrame {
            frame: String::new(),
            records,
        };
        Ok(
            match solve_frame(self.sensor, self.plan, &frame, &mut self.solvers) {
                Ok(forces) => {
                    let out = &self.o.out;
                    let fpath = format!("forces/{i:05}.csv");
                    crate::formats::write_forces(
                        &out.join(&fpath),
                        &self.sensor.force_grid,
                        &[(String::new(), forces.clone())],
                    )
                    .map_err(|e| bad(&out.join(&fpath), e.to_string()))?;
                    digest(out, &fpath, &mut self.evidence)?;
                    let mut s = [0.0; 3];
                    for (j, v) in forces.iter().enumerate() {
                        s[j % 3] += v;
                    }
                    (s, None)
                }
                Err(e) => ([f64::NAN; 3], Some(format!("reconstruction failed: {e}"))),
            },
        )
    }
}

/// The middle of the first layer's marker grid, mm (the contact position when the CSV
/// has none and `--position` is not given; the manifest says so).
fn grid_centre(sensor: &Sensor) -> [f64; 2] {
    sensor
        .layers
        .iter()
        .find_map(|l| l.markers.as_ref())
        .map_or([0.0, 0.0], |m| {
            let g = &m.grid;
            [
                g.origin_mm[0] + 0.5 * g.pitch_mm * (g.nx.saturating_sub(1)) as f64,
                g.origin_mm[1] + 0.5 * g.pitch_mm * (g.ny.saturating_sub(1)) as f64,
            ]
        })
}

fn solve_frame(
    sensor: &Sensor,
    plan: &Plan,
    frame: &DisplacementFrame,
    solvers: &mut HashMap<Vec<bool>, Box<dyn solve::FrameSolver>>,
) -> Result<Vec<f64>, String> {
    let u = frame.u_mm();
    let n_out = 3 * sensor.force_grid.len();
    // An exactly unmoved frame (the reference itself) is zero force for every linear
    // solver, and solving it would pick an automatic λ on a frame without signal.
    if !u.is_empty() && u.iter().all(|v| *v == 0.0) {
        return Ok(vec![0.0; n_out]);
    }
    let key: Vec<bool> = frame.records.iter().map(|r| r.u_mm.is_some()).collect();
    if !solvers.contains_key(&key) {
        let sites = frame.sites(sensor);
        let problem = Problem::new(sensor, &sites);
        let s = solve::precompute(&problem, &plan.solver, Some(&u)).map_err(|e| e.to_string())?;
        solvers.insert(key.clone(), s);
    }
    let s = solvers.get_mut(&key).ok_or("solver cache")?;
    let mut f = vec![f64::NAN; n_out];
    s.apply(&u, &mut f).map_err(|e| e.to_string())?;
    Ok(f)
}

fn io(path: &Path, source: std::io::Error) -> ImportError {
    ImportError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Refuses an output directory that exists and is not empty (never overwrite a run).
fn check_out(out: &Path) -> Result<(), ImportError> {
    if let Ok(mut entries) = std::fs::read_dir(out) {
        if entries.next().is_some() {
            return Err(bad(
                out,
                "--out exists and is not empty: give a new or empty directory (an import never overwrites a run)",
            ));
        }
    } else if out.exists() {
        return Err(bad(out, "--out exists and is not a directory"));
    }
    Ok(())
}

/// Copies a frame into the run directory (PNG byte for byte, other formats decoded
/// and saved as PNG) and records its digest.
fn copy_frame(
    src: &Path,
    out: &Path,
    rel: &str,
    evidence: &mut BTreeMap<String, String>,
) -> Result<(), ImportError> {
    let dst = out.join(rel);
    let png = src
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if png {
        std::fs::copy(src, &dst).map_err(|e| io(&dst, e))?;
    } else {
        let img = image::open(src).map_err(|e| bad(src, e.to_string()))?;
        img.save(&dst).map_err(|e| bad(&dst, e.to_string()))?;
    }
    digest(out, rel, evidence)
}

fn digest(
    out: &Path,
    rel: &str,
    evidence: &mut BTreeMap<String, String>,
) -> Result<(), ImportError> {
    let d =
        file_sha256(&out.join(rel)).ok_or_else(|| bad(&out.join(rel), "cannot be read back"))?;
    evidence.insert(rel.to_string(), d);
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn write_manifest(
    o: &ImportOptions,
    plan_text: &str,
    sensor_toml: &str,
    recorded: &BTreeMap<String, bool>,
    ref_name: &str,
    ref_rule: &str,
    n: usize,
    record: RecordDigests,
    now: &str,
) -> Result<(), ImportError> {
    let why = format!(
        "imported recording (tactbench import): frames from {}, wrench from {}",
        o.frames_dir.display(),
        o.wrench_csv.display()
    );
    let devices = serde_json::json!({
        "stage": "imported: not recorded by tactbench",
        "force_sensor": format!("imported: {}", o.wrench_csv.display()),
        "camera": format!("imported: {}", o.frames_dir.display()),
    });
    let position = if recorded["position"] {
        "the CSV's x, y columns".to_string()
    } else if let Some(p) = o.position_mm {
        format!("--position {}, {} for every row", p[0], p[1])
    } else {
        "assumed: the middle of the first layer's marker grid (no x, y columns, no --position)"
            .into()
    };
    let bench = serde_json::json!({
        "source": "import",
        "frames_dir": o.frames_dir.display().to_string(),
        "wrench_csv": o.wrench_csv.display().to_string(),
        "columns": o.map.iter().map(|(a, b)| (a.clone(), serde_json::Value::String(b.clone()))).collect::<serde_json::Map<_, _>>(),
        "force_unit": o.force_unit.symbol(),
        "recorded": recorded,
        "position": position,
        "reference": {"file": ref_name, "rule": ref_rule},
        // stage_z_mm holds the indentation depth: the surface at 0, +z presses.
        "geometry": {"sensor_origin_in_stage_mm": [0.0, 0.0], "surface_z_mm": 0.0, "press_direction": 1},
    });
    let m = Manifest {
        plan_path: "import (synthesised)".into(),
        plan_name: "import".into(),
        plan_toml: plan_text.to_string(),
        sensor_path: o.sensor_path.display().to_string(),
        sensor_toml: sensor_toml.to_string(),
        bench,
        devices,
        build_id: None,
        software_version: env!("CARGO_PKG_VERSION").into(),
        started_at: now.to_string(),
        resumed_at: vec![],
        setpoints: n,
        planned_setpoints: Some(n),
        limit: None,
        sessions: vec![Session {
            started_at: now.to_string(),
            limit: None,
            setpoints_before: 0,
            setpoints_after: n,
        }],
        measured_setpoints: n,
        status: RunStatus::Completed,
        end_reason: None,
        stop_signal: None,
        incomplete_reason: None,
        ended_at: Some(now.to_string()),
        software_commit: Some(journal::GIT_COMMIT.into()),
        camera_path: None,
        camera_toml: None,
        simulated: Some(false),
        write_failure: None,
        device_provenance: ["stage", "force_sensor", "camera"]
            .iter()
            .map(|d| DeviceProvenance {
                device: d.to_string(),
                identity: "imported".into(),
                provenance: Provenance::Replayed,
                why: Some(why.clone()),
            })
            .collect(),
        record: Some(record),
    };
    // `source: "import"` at the top level: readers deserialising into `Manifest`
    // ignore it; it says where the run came from to whoever reads the JSON.
    let mut v = serde_json::to_value(&m).map_err(|e| bad(&o.out, e.to_string()))?;
    if let Some(obj) = v.as_object_mut() {
        obj.insert("source".into(), serde_json::Value::String("import".into()));
    }
    let path = o.out.join(journal::MANIFEST_FILE);
    let text = serde_json::to_string_pretty(&v).map_err(|e| bad(&path, e.to_string()))?;
    std::fs::write(&path, text + "\n").map_err(|e| io(&path, e))
}
