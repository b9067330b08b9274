//! Plans and dry runs (issue 10): caps checked before anything is expanded (also
//! under an address-space limit), required keys, dry runs that check every input
//! and show the stage coordinates, plain run logs when stderr is not a terminal, CSV
//! numbers without binary noise, and the help texts.

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::util;

/// Copies the Fig. 7 plan (with `edit` applied) and the paper sensor into `dir`.
fn fig7_plan(dir: &Path, name: &str, edit: impl Fn(String) -> String) -> PathBuf {
    let text = std::fs::read_to_string(util::root("experiments/fig7_magnitude.toml")).unwrap();
    std::fs::copy(
        util::root("experiments/paper_sensor.toml"),
        dir.join("paper_sensor.toml"),
    )
    .unwrap();
    let p = dir.join(name);
    std::fs::write(&p, edit(text)).unwrap();
    p
}

/// Runs `tactbench ARGS` in the crate root under `ulimit -v` (KiB).
fn run_limited(kib: u64, args: &[&str]) -> std::process::Output {
    let mut cmd = format!("ulimit -v {kib} && exec \"$0\"");
    for i in 0..args.len() {
        cmd += &format!(" \"${}\"", i + 1);
    }
    Command::new("sh")
        .arg("-c")
        .arg(cmd)
        .arg(util::bin())
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .unwrap()
}

#[test]
fn a_plan_with_to_1e9_is_refused_under_a_1_gb_memory_limit_naming_key_value_and_cap() {
    let tmp = tempfile::tempdir().unwrap();
    let typo = fig7_plan(tmp.path(), "typo.toml", |t| {
        t.replace("to = 750.0", "to = 1e9")
    });
    let one = fig7_plan(tmp.path(), "one.toml", |t| {
        t.replace("to = 750.0", "to = 1e9")
            .replace("trials = 10", "trials = 1")
    });
    let out = tmp.path().join("never");
    for (plan, setpoints) in [(&typo, "200000010"), (&one, "20000001")] {
        for extra in [
            vec!["--dry-run"],
            vec![
                "--sim",
                "experiments/scenes/fig7_hemisphere_ramp.toml",
                "--out",
                out.to_str().unwrap(),
            ],
        ] {
            let mut args = vec!["run", plan.to_str().unwrap()];
            args.extend(extra);
            // 1 GiB of address space: refused by validation, not killed by the limit.
            let o = run_limited(1 << 20, &args);
            let e = util::stderr(&o);
            assert_eq!(o.status.code(), Some(2), "{args:?}: {e}");
            assert!(
                e.contains(plan.to_str().unwrap())
                    && e.contains("sweep.to = 1000000000 gf")
                    && e.contains(&format!("{setpoints} setpoints"))
                    && e.contains("cap of 100000 setpoints"),
                "{e}"
            );
            assert!(!out.exists(), "nothing is created for a refused plan");
        }
    }
}

#[test]
fn a_plan_without_trials_is_refused_and_the_dry_run_echoes_the_defaults() {
    let tmp = tempfile::tempdir().unwrap();
    let p = fig7_plan(tmp.path(), "p.toml", |t| t.replace("trials = 10\n", ""));
    let o = util::run(&["run", p.to_str().unwrap(), "--dry-run"]);
    assert_eq!(o.status.code(), Some(2));
    let e = util::stderr(&o);
    assert!(
        e.contains("sweep.trials = (missing)") && e.contains("required by sweep kind"),
        "{e}"
    );
    // Settle, acquire and control left out: each default is printed with its key.
    let p = fig7_plan(tmp.path(), "q.toml", |t| {
        let cut = t.find("[control]").unwrap();
        let keep = t.find("[safety]").unwrap();
        format!("{}{}", &t[..cut], &t[keep..])
    });
    let o = util::run(&["run", p.to_str().unwrap(), "--dry-run"]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    let s = util::stdout(&o);
    for line in [
        "  control.force_tolerance = 5 gf (approach.contact_force)",
        "  control.max_steps = 40",
        "  settle.window_s = 0.5 s",
        "  settle.max_sd = 2.5 gf (control.force_tolerance / 2)",
        "  settle.timeout_s = 10 s",
        "  settle.dwell_s = 0 s",
        "  acquire.samples = 20",
        "  acquire.frames = 1",
        "  reconstruct.solver = \"pinv\"",
    ] {
        assert!(s.contains(line), "{line:?} missing from:\n{s}");
    }
    assert!(
        s.contains("caps: 160 of 100000 setpoints, 160 of 200000 frames"),
        "{s}"
    );
}

#[test]
fn dry_runs_with_a_missing_scene_or_frame_directory_fail_with_exit_2() {
    let tmp = tempfile::tempdir().unwrap();
    let o = util::run(&[
        "run",
        "experiments/fig7_magnitude.toml",
        "--sim",
        "experiments/scenes/missing.toml",
        "--dry-run",
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", util::stdout(&o));
    let e = util::stderr(&o);
    assert!(
        e.contains("cannot read scene file experiments/scenes/missing.toml"),
        "{e}"
    );

    let bench = tmp.path().join("bench.toml");
    std::fs::write(&bench, "[sim]\nscene = \"gone.toml\"\n").unwrap();
    let o = util::run(&[
        "run",
        "experiments/fig7_magnitude.toml",
        "--bench",
        bench.to_str().unwrap(),
        "--dry-run",
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", util::stdout(&o));
    let e = util::stderr(&o);
    assert!(
        e.contains("bench.toml") && e.contains("gone.toml") && e.contains("scene"),
        "{e}"
    );

    // A recorded-frames camera: a missing directory is an error, too few frames a
    // failed check (the run would stop at the end of the recording).
    let hw = std::fs::read_to_string(util::root("experiments/bench_example.toml")).unwrap();
    let frames = tmp.path().join("frames");
    let cam_bench = tmp.path().join("cam.toml");
    std::fs::write(
        &cam_bench,
        hw.replace(
            "device = 0  ",
            &format!("device = \"dir:{}\"  ", frames.display()),
        ),
    )
    .unwrap();
    let args = [
        "run",
        "experiments/fig7_magnitude.toml",
        "--bench",
        cam_bench.to_str().unwrap(),
        "--dry-run",
        "--limit",
        "2",
    ];
    let o = util::run(&args);
    assert_eq!(o.status.code(), Some(2), "{}", util::stdout(&o));
    assert!(util::stderr(&o).contains("frames"), "{}", util::stderr(&o));
    std::fs::create_dir(&frames).unwrap();
    for i in 0..2 {
        image::RgbImage::new(4, 4)
            .save(frames.join(format!("{i}.png")))
            .unwrap();
    }
    let o = util::run(&args);
    assert_eq!(o.status.code(), Some(3), "{}", util::stderr(&o));
    assert!(
        util::stdout(&o).contains("[FAIL] camera dir:")
            && util::stdout(&o).contains("holds 2 frames; the run grabs 3"),
        "{}",
        util::stdout(&o)
    );
}

#[test]
fn dry_runs_with_a_bench_show_stage_coordinates_and_check_its_travel_limits() {
    let tmp = tempfile::tempdir().unwrap();
    let csv = tmp.path().join("setpoints.csv");
    let o = util::run(&[
        "run",
        "experiments/fig7_magnitude.toml",
        "--bench",
        "experiments/bench_sim.toml",
        "--dry-run",
        "--setpoints-csv",
        csv.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    let s = util::stdout(&o);
    assert!(!s.contains("unknown without a bench"), "{s}");
    assert!(
        s.contains("stage travel limits from the simulated GRBL stage")
            && s.contains("and the stage's travel limits x -200..0"),
        "{s}"
    );
    // Sensor centre (9, 6.75) over the origin at (-100, -100); surface z = -30,
    // pressing towards -z: retract at -29, deepest allowed indentation 3 mm at -33.
    assert!(
        s.contains("     0     0     9.0000     6.7500       0.0000       0.0000       0.0000     0.0000   -91.0000   -93.2500    -29.0000      -33.0000"),
        "{s}"
    );
    assert!(s.contains("(120 setpoints not shown"), "{s}");
    let rows = std::fs::read_to_string(&csv).unwrap();
    assert_eq!(rows.lines().count(), 161);
    assert!(rows.starts_with("index,trial,x_mm,y_mm,normal_gf,tx_gf,ty_gf,swept,stage_x_mm,stage_y_mm,stage_z_clr,stage_z_limit\n"));

    // A hardware bench whose stated travel stops short of the deepest point.
    let hw = std::fs::read_to_string(util::root("experiments/bench_example.toml")).unwrap();
    let bench = tmp.path().join("bench.toml");
    std::fs::write(
        &bench,
        hw.replace(
            "baud = 115200",
            "baud = 115200\ntravel_min_mm = [-200.0, -200.0, -32.0]\ntravel_max_mm = [0.0, 0.0, 0.0]",
        ),
    )
    .unwrap();
    let o = util::run(&[
        "run",
        "experiments/fig7_magnitude.toml",
        "--bench",
        bench.to_str().unwrap(),
        "--dry-run",
    ]);
    assert_eq!(o.status.code(), Some(3), "{}", util::stderr(&o));
    let s = util::stdout(&o);
    assert!(
        s.contains("[FAIL] setpoint 0 (deepest point): stage requested z = -33 mm is below travel limit -32 mm")
            && s.contains("... and 150 more like these"),
        "{s}"
    );
}

#[test]
fn limit_zero_is_refused_at_parse_time() {
    let o = util::run(&[
        "run",
        "experiments/fig7_magnitude.toml",
        "--dry-run",
        "--limit",
        "0",
    ]);
    assert_eq!(o.status.code(), Some(2));
    let e = util::stderr(&o);
    assert!(e.contains("--limit") && e.contains('0'), "{e}");
}

#[test]
fn help_texts_cite_existing_files_name_sim_cameras_and_keep_examples_whole() {
    let o = util::run(&["reconstruct", "--help"]);
    let s = util::stdout(&o);
    let cited: Vec<&str> = s
        .split_whitespace()
        .filter(|w| w.starts_with("experiments/") || w.starts_with("tests/"))
        .collect();
    assert!(!cited.is_empty(), "{s}");
    for f in cited {
        assert!(util::root(f).exists(), "reconstruct --help cites {f}");
    }
    let s = util::stdout(&util::run(&["camera", "grab", "--help"]));
    assert!(s.contains("sim:PATH") && s.contains("dir:PATH"), "{s}");
    for width in ["80", "200"] {
        let o = Command::new(util::bin())
            .args(["run", "--help"])
            .env("COLUMNS", width)
            .output()
            .unwrap();
        let s = util::stdout(&o);
        let examples = &s[s.find("Examples:").expect("examples") + 9..];
        let mut commands = 0;
        for line in examples.lines().map(str::trim).filter(|l| !l.is_empty()) {
            assert!(
                line.starts_with('#') || line.starts_with("tactbench ") || line.starts_with("--"),
                "an example wrapped mid-command at COLUMNS={width}: {line:?}\n{s}"
            );
            commands += usize::from(line.starts_with("tactbench "));
        }
        assert_eq!(commands, 5, "{s}");
    }
}

/// Significant digits of a decimal number as written (`0.04903325` has 7).
fn significant_digits(field: &str) -> usize {
    let mantissa = field.split(['e', 'E']).next().unwrap_or("");
    let digits: String = mantissa.chars().filter(char::is_ascii_digit).collect();
    let digits = digits.trim_start_matches('0');
    if mantissa.contains('.') {
        digits.len()
    } else {
        digits.trim_end_matches('0').len()
    }
}

/// Checks every number of a CSV file: at most 12 significant digits, and no value of
/// magnitude below 1e-12 other than 0.
fn assert_no_float_noise(path: &Path) {
    let text = std::fs::read_to_string(path).unwrap();
    let mut numbers = 0;
    for line in text.lines().skip(1) {
        for field in line.split(',') {
            let Ok(v) = field.parse::<f64>() else {
                continue;
            };
            if !v.is_finite() {
                continue;
            }
            numbers += 1;
            assert!(
                significant_digits(field) <= 12,
                "{}: {field:?} carries binary noise",
                path.display()
            );
            assert!(
                v == 0.0 || v.abs() >= 1e-12,
                "{}: {field:?} is arithmetic residue",
                path.display()
            );
        }
    }
    assert!(numbers > 0, "{}", path.display());
}

#[test]
fn a_run_with_stderr_on_a_pipe_logs_plain_lines_and_its_csvs_carry_no_float_noise() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("run");
    // stderr is a pipe here (not a terminal) and --no-progress is not given.
    let o = util::run(&[
        "run",
        "experiments/fig8_angle.toml",
        "--sim",
        "experiments/scenes/fig8_angle_400gf.toml",
        "--limit",
        "2",
        "--out",
        out.to_str().unwrap(),
    ]);
    let e = util::stderr(&o);
    assert!(o.status.success(), "{e}");
    let lines: Vec<&str> = e.lines().collect();
    let at = |prefix: &str| {
        lines
            .iter()
            .position(|l| l.starts_with(prefix))
            .unwrap_or_else(|| panic!("no line starting {prefix:?} in:\n{e}"))
    };
    let started = at(&format!("run {}: 2 setpoints", out.display()));
    let tared = at("force sensor tared (|F| = ");
    let reference = at("reference frame frames/reference.png: ");
    let first = at("setpoint 0 (1/2): target fx/fy/fz 0.000/0.000/400.000 gf, measured ");
    let second = at("setpoint 1 (2/2): target fx/fy/fz ");
    let done = at("run completed: 2 setpoints");
    assert!(started < tared && tared < reference && reference < first);
    assert!(first < second && second < done);
    assert!(lines[first].contains(" gf, F_sum z ") && lines[first].ends_with(" s"));
    assert!(
        !e.contains('\r') && !e.contains('\u{1b}'),
        "no progress-bar redraws in a log: {e:?}"
    );
    assert_no_float_noise(&out.join("journal.csv"));
    assert_no_float_noise(&out.join("displacements/00001.csv"));
    assert_no_float_noise(&out.join("forces/00001.csv"));
}
