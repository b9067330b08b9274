//! `tactbench import` (issue 30, item 7): a recording tactbench did not make (greyscale
//! copies of the real TacTip taps in `../shared/real_frames/tactip`, written to a
//! temporary directory, never committed, with a WRENCH.csv written here: made-up but
//! plausible forces keyed by those file names) becomes a run directory that `track`
//! and `report` read; bad input is refused with exit 2 naming file, line, column, value.

use std::path::{Path, PathBuf};

use image::{ImageBuffer, Luma};

use crate::util::{self, arg as p};

type Gray16Image = ImageBuffer<Luma<u16>, Vec<u16>>;

/// Grey copies (`round((R + G + B) / 3)`, `bits` 8 or 16) of TacTip taps 1..=5 as
/// `DIR/rec/tap_K.png`, and a draft sensor file from `sensor init` on tap 1 (bright
/// pins, the ROI and scale `vision_gray` uses). `None` when the real frames are absent.
fn recording(dir: &Path, bits: u32) -> Option<(PathBuf, PathBuf)> {
    let real = util::real_frames_dir().join("tactip");
    if !real.is_dir() {
        eprintln!("skipped: {} is absent", real.display());
        return None;
    }
    let rec = dir.join("rec");
    std::fs::create_dir_all(&rec).unwrap();
    for k in 1..=5 {
        let img = image::open(real.join(format!("image_{k}.png")))
            .unwrap()
            .to_rgb8();
        let g = util::gray8_of(&img);
        let out = rec.join(format!("tap_{k}.png"));
        if bits == 8 {
            g.save(&out).unwrap();
        } else {
            Gray16Image::from_fn(g.width(), g.height(), |x, y| {
                Luma([g.get_pixel(x, y).0[0] as u16 * 257])
            })
            .save(&out)
            .unwrap();
        }
    }
    let sensor = dir.join("draft.toml");
    let tap_1 = rec.join("tap_1.png");
    let mut args = vec![
        "sensor",
        "init",
        "--reference",
        p(&tap_1),
        "--out",
        p(&sensor),
    ];
    args.extend_from_slice(&util::TACTIP_INIT);
    let o = util::run(&args);
    assert!(o.status.success(), "{}", util::stderr(&o));
    Some((rec, sensor))
}

/// The draft with its placeholders taken as measured (the typical values `sensor init`
/// writes), so forces are reconstructed.
fn measured(draft: &Path, out: &Path) -> PathBuf {
    let text = std::fs::read_to_string(draft).unwrap();
    let kept: Vec<&str> = text
        .lines()
        .filter(|l| !l.starts_with("draft =") && !l.starts_with("placeholders ="))
        .collect();
    std::fs::write(out, kept.join("\n")).unwrap();
    out.to_path_buf()
}

/// A WRENCH.csv in a lab's own column names (tap 1 unloaded: the smallest |F|).
const WRENCH: &str = "filename,Fx,Fy,Fz,Tx,Ty,Tz,indent\n\
    tap_1.png,0.002,-0.001,0.004,0,0,0,0\n\
    tap_2.png,0.12,0.03,1.35,0.001,-0.002,0,2.1\n\
    tap_3.png,-0.08,0.10,2.20,0,0.001,0,3.0\n\
    tap_4.png,0.05,-0.11,3.05,0.002,0,0.001,4.2\n\
    tap_5.png,0.02,0.04,4.10,0,0,0,5.0\n";

const MAP: &str = "frame=filename,fx=Fx,fy=Fy,fz=Fz,mx=Tx,my=Ty,mz=Tz,depth=indent";

fn import(rec: &Path, csv: &Path, sensor: &Path, out: &Path) -> std::process::Output {
    util::run(&[
        "import",
        "--frames",
        p(rec),
        "--wrench",
        p(csv),
        "--map",
        MAP,
        "--sensor",
        p(sensor),
        "--indenter",
        "hemisphere:6",
        "--out",
        p(out),
    ])
}

/// 8- and 16-bit greyscale TacTip taps with a lab's CSV: the run directory has the
/// manifest (`source: "import"`, every device replayed, the reference chosen by the
/// smallest |F|, a setpoints plan with the measured wrench), one journal row per frame
/// with the CSV's wrench and depth, the frames copied byte for byte (16-bit stays
/// 16-bit), tracked displacements and reconstructed forces; `track` tracks its frames
/// and `report` reads it without calling it modified.
#[test]
fn tactip_grey_recording_imports_and_track_and_report_read_it() {
    for bits in [8, 16] {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let Some((rec, draft)) = recording(d, bits) else {
            return;
        };
        let sensor = measured(&draft, &d.join("sensor.toml"));
        let csv = d.join("wrench.csv");
        std::fs::write(&csv, WRENCH).unwrap();
        let run = d.join("run");
        let o = import(&rec, &csv, &sensor, &run);
        assert!(o.status.success(), "{bits}-bit: {}", util::stderr(&o));

        let m = util::json(&run.join("manifest.json"));
        assert_eq!(m["source"], "import");
        assert_eq!(m["bench"]["source"], "import");
        assert_eq!(m["bench"]["reference"]["file"], "tap_1.png");
        assert_eq!(m["bench"]["recorded"]["depth"], true);
        assert_eq!(m["bench"]["recorded"]["position"], false);
        assert_eq!(m["status"], "completed");
        for dp in m["device_provenance"].as_array().unwrap() {
            assert_eq!(dp["provenance"], "replayed");
        }
        let plan = m["plan_toml"].as_str().unwrap();
        assert!(plan.contains("kind = \"setpoints\""), "{plan}");
        assert!(plan.contains("shape = \"hemisphere\""), "{plan}");

        let mut rdr = csv::Reader::from_path(run.join("journal.csv")).unwrap();
        let rows: Vec<csv::StringRecord> = rdr.records().map(|r| r.unwrap()).collect();
        let h = rdr.headers().unwrap().clone();
        let col = |r: &csv::StringRecord, name: &str| {
            r.get(h.iter().position(|c| c == name).unwrap())
                .unwrap()
                .to_string()
        };
        assert_eq!(rows.len(), 5);
        assert_eq!(col(&rows[2], "fz_n"), "2.2");
        assert_eq!(col(&rows[2], "fx_n"), "-0.08");
        assert_eq!(col(&rows[3], "mz_nm"), "0.001");
        assert_eq!(col(&rows[4], "stage_z_mm"), "5");
        assert_eq!(col(&rows[1], "frames"), "frames/00001_0.png");
        for r in &rows {
            assert_eq!(col(r, "failure"), "", "{bits}-bit");
            assert!(col(r, "fsum_z_n").parse::<f64>().unwrap().is_finite());
            assert!(col(r, "markers_ok").parse::<usize>().unwrap() > 200);
        }
        // The unloaded reference row tracks as unmoved.
        assert_eq!(col(&rows[0], "fsum_z_n"), "0");
        for k in 0..5 {
            let src = std::fs::read(rec.join(format!("tap_{}.png", k + 1))).unwrap();
            let dst = std::fs::read(run.join(format!("frames/{k:05}_0.png"))).unwrap();
            assert_eq!(src, dst, "{bits}-bit frame {k}");
            assert!(run.join(format!("displacements/{k:05}.csv")).is_file());
            assert!(run.join(format!("forces/{k:05}.csv")).is_file());
        }
        let frame = image::open(run.join("frames/00003_0.png")).unwrap();
        assert_eq!(frame.color().bits_per_pixel(), bits as u16, "{bits}-bit");

        let out = d.join("tracked.csv");
        let o = util::run(&[
            "track",
            "--sensor",
            p(&sensor),
            "--reference",
            p(&run.join("frames/reference.png")),
            p(&run.join("frames/00002_0.png")),
            "--out",
            p(&out),
        ]);
        assert!(o.status.code() != Some(2), "{}", util::stderr(&o));
        let tracked = std::fs::read_to_string(&out).unwrap();
        assert!(tracked.lines().filter(|l| l.ends_with(",ok")).count() > 200);

        let o = util::run(&["report", p(&run), "--out", p(&d.join("report"))]);
        let text = format!("{}{}", util::stdout(&o), util::stderr(&o));
        assert!(o.status.code() != Some(2), "{bits}-bit: {text}");
        assert!(!text.contains("modified"), "{bits}-bit: {text}");
        assert!(d.join("report/report.html").is_file(), "{text}");
    }
}

/// A draft sensor file tracks but does not reconstruct: every row says why.
#[test]
fn import_with_a_draft_sensor_tracks_and_leaves_forces_out() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let Some((rec, draft)) = recording(d, 8) else {
        return;
    };
    let csv = d.join("wrench.csv");
    std::fs::write(&csv, WRENCH).unwrap();
    let run = d.join("run");
    let o = import(&rec, &csv, &draft, &run);
    assert!(o.status.success(), "{}", util::stderr(&o));
    let journal = std::fs::read_to_string(run.join("journal.csv")).unwrap();
    assert_eq!(journal.matches("not reconstructed").count(), 5, "{journal}");
    assert!(run.join("displacements/00004.csv").is_file());
    assert!(!run.join("forces").exists());
}

/// Every kind of bad input exits 2 with the file, line, column and value.
#[test]
fn import_bad_input_names_file_line_column_and_value() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let Some((rec, sensor)) = recording(d, 8) else {
        return;
    };
    let case = |name: &str, text: &str, want: &[&str]| {
        let csv = d.join(format!("{name}.csv"));
        std::fs::write(&csv, text).unwrap();
        let out = d.join(format!("out_{name}"));
        let o = import(&rec, &csv, &sensor, &out);
        let err = util::stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{name}: {err}");
        for w in want {
            assert!(err.contains(w), "{name}: {w:?} not in {err}");
        }
        assert!(!out.join("manifest.json").exists(), "{name}");
    };
    let h = "filename,Fx,Fy,Fz,Tx,Ty,Tz,indent\n";
    case(
        "no_match",
        &format!("{h}a.png,0,0,1,0,0,0,1\nb.png,0,0,1,0,0,0,1\n"),
        &[
            "no_match.csv",
            "2 of 2 frame names match no file",
            "\"a.png\" (line 2)",
        ],
    );
    case(
        "partial",
        &format!("{h}tap_1.png,0,0,0,0,0,0,0\ntap_9.png,0,0,1,0,0,0,1\n"),
        &["1 of 2 frame names", "\"tap_9.png\" (line 3)"],
    );
    case(
        "text",
        &format!("{h}tap_1.png,0,0,abc,0,0,0,0\n"),
        &["text.csv", "line 2, column `Fz`", "\"abc\" is not a number"],
    );
    case(
        "nan",
        &format!("{h}tap_1.png,0,inf,0,0,0,0,0\n"),
        &["line 2, column `Fy`", "inf is not a finite number"],
    );
    case(
        "missing",
        "filename,Fx,Fy,Tx,Ty,Tz,indent\ntap_1.png,0,0,0,0,0,0\n",
        &["line 1: no column `Fz`", "--map fz=NAME"],
    );
    case(
        "duplicate",
        &format!("{h}tap_1.png,0,0,0,0,0,0,0\ntap_1.png,0,0,1,0,0,0,1\n"),
        &["line 3", "\"tap_1.png\" appears twice (first on line 2)"],
    );
    // A frame of another size than the others (and the sensor's [camera]).
    let small = image::open(rec.join("tap_2.png"))
        .unwrap()
        .crop_imm(0, 0, 320, 240);
    small.save(rec.join("small.png")).unwrap();
    case(
        "size",
        &format!("{h}tap_1.png,0,0,0,0,0,0,0\nsmall.png,0,0,1,0,0,0,1\n"),
        &["small.png", "320", "240", "line 3"],
    );
    // An existing, non-empty --out.
    let full = d.join("out_full");
    std::fs::create_dir_all(&full).unwrap();
    std::fs::write(full.join("keep.txt"), "x").unwrap();
    let csv = d.join("ok.csv");
    std::fs::write(&csv, WRENCH).unwrap();
    let o = import(&rec, &csv, &sensor, &full);
    assert_eq!(o.status.code(), Some(2), "{}", util::stderr(&o));
    assert!(
        util::stderr(&o).contains("not empty"),
        "{}",
        util::stderr(&o)
    );
    assert!(full.join("keep.txt").is_file());
}

/// Data not recorded by tactbench: greyscale TacTip taps with a lab's CSV, imported and
/// fitted. The numbers are a lab's own (the taps and the forces were not made for each
/// other), so the test asks what a user must get on any data: the fit finishes, every
/// value is finite, every parameter is fitted with an interval or held with a reason,
/// the exit status says whether anything was determined, and `fitted.toml` loads.
#[test]
fn tactip_grey_recording_imports_and_fits_without_a_made_up_number() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let Some((rec, draft)) = recording(d, 16) else {
        return;
    };
    let sensor = measured(&draft, &d.join("sensor.toml"));
    let csv = d.join("wrench.csv");
    std::fs::write(&csv, WRENCH).unwrap();
    let run = d.join("run");
    let o = import(&rec, &csv, &sensor, &run);
    assert!(o.status.success(), "{}", util::stderr(&o));
    let fitted = d.join("fitted.toml");
    let j = d.join("fit.json");
    let o = util::run(&["fit", p(&run), "--out", p(&fitted), "--json", p(&j)]);
    // Five taps of one pose cannot determine the model: every parameter is held, and
    // the exit status says nothing was determined (1), never a silent success.
    let any_fitted = util::json(&j)["parameters"]
        .as_object()
        .unwrap()
        .values()
        .any(|p| p["fitted"] == true);
    let want = if any_fitted { 0 } else { 1 };
    assert_eq!(o.status.code(), Some(want), "fit: {}", util::stderr(&o));
    eprintln!("{}", util::stdout(&o));
    let doc = util::json(&j);
    for (name, par) in doc["parameters"].as_object().unwrap() {
        assert!(par["value"].as_f64().unwrap().is_finite(), "{name}: {par}");
        if par["fitted"] == true {
            let ci = par["ci95"].as_array().unwrap();
            assert!(
                ci.iter().all(|v| v.as_f64().unwrap().is_finite()),
                "{name}: {par}"
            );
        } else {
            assert!(par["ci95"].is_null(), "{name}: {par}");
            assert!(!par["reason"].as_str().unwrap().is_empty(), "{name}: {par}");
        }
    }
    // The indentation route read the CSV's depth column.
    assert_eq!(doc["routes"]["indentation"]["rows"], 4, "{}", doc["routes"]);
    tactbench::sensor::Sensor::from_path(&fitted).unwrap();
}
