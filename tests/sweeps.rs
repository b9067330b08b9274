//! Up-down magnitude sweeps, trials at several contact positions and hold sweeps
//! (issue 13, the bench side) on the simulated bench: the journal's `direction`,
//! `position` and `hold_t_s`, dry runs, resume across a hold, and the viscoelastic
//! bench effect seen in the journal (zero hysteresis and creep without it, the
//! configured loop and creep with it).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use tactbench::bench::journal::{Direction, JournalRow, Manifest, RunStatus};
use tactbench::bench::plan::Plan;

use crate::util::{self, rows};

/// Runs `tactbench run PLAN --sim SCENE --out OUT` and asserts it completed.
fn run_sim(plan: &Path, scene: &Path, out: &Path) -> Vec<JournalRow> {
    let o = util::run(&[
        "run",
        plan.to_str().unwrap(),
        "--sim",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--no-progress",
    ]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    assert_eq!(Manifest::read(out).unwrap().status, RunStatus::Completed);
    rows(out)
}

/// Writes `text` as `dir/name`, with the paper sensor beside it.
fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    std::fs::copy(
        util::root("experiments/paper_sensor.toml"),
        dir.join("paper_sensor.toml"),
    )
    .unwrap();
    util::write(dir, name, text)
}

/// An example plan with `edit` applied, written into `dir`.
fn example(dir: &Path, example: &str, name: &str, edit: impl Fn(String) -> String) -> PathBuf {
    let text = std::fs::read_to_string(util::root(&format!("experiments/{example}"))).unwrap();
    write(dir, name, &edit(text))
}

/// A hemisphere scene rendered with exact centroids (`tent`), so the reconstruction
/// follows the field's scale closely, with `bench` as its `[bench]` table.
fn tent_scene(dir: &Path, name: &str, bench: &str) -> PathBuf {
    write(
        dir,
        name,
        &format!(
            "sensor = \"paper_sensor.toml\"\npixel_filter = \"tent\"\n[indenter]\nkind = \"hemisphere\"\nradius_mm = 2.5\n[load]\nposition_mm = [9.0, 6.75]\nnormal_force_gf = 300.0\n{bench}"
        ),
    )
}

/// A solver with a fixed rank: no automatic choice that could differ between runs,
/// and little amplification of the tracker's 1e-3 px noise.
fn fixed_rank(text: String) -> String {
    text.replace(
        "[sweep]",
        "[reconstruct]\nsolver = \"tsvd\"\nrank = 120\n\n[sweep]",
    )
}

#[test]
fn dry_runs_show_the_up_down_rows_the_positions_and_the_hold_schedule() {
    let tmp = tempfile::tempdir().unwrap();
    let o = util::run(&[
        "run",
        "experiments/magnitude_updown.toml",
        "--sim",
        "experiments/scenes/fig7_hemisphere_ramp.toml",
        "--dry-run",
        "--setpoints-csv",
        tmp.path().join("sp.csv").to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    let s = util::stdout(&o);
    for needle in [
        "45 setpoints",
        "sweep.direction = \"up-down\": each trial runs from 0 up to 300 gf (top level once) and back down to 0 gf",
        "3 trial(s) at each of 3 positions in turn",
        "1: [7.5, 6.75] mm (trials 3..5)",
        "direction position  hold_t_s",
        "[ok] sweep.positions_mm[2] [10.5, 6.75] mm within the sensor's force grid",
    ] {
        assert!(s.contains(needle), "{needle:?} missing from:\n{s}");
    }
    let csv = std::fs::read_to_string(tmp.path().join("sp.csv")).unwrap();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines.len(), 46);
    assert!(
        lines[0].ends_with(",direction,position,hold_t_s"),
        "{}",
        lines[0]
    );
    // Trial 3 (position 1) unloads from 300 to 150 gf: row 18.
    assert!(lines[19].starts_with("18,3,7.5000,"), "{}", lines[19]);
    assert!(lines[19].ends_with(",down,1,-"), "{}", lines[19]);

    let o = util::run(&[
        "run",
        "experiments/hold_example.toml",
        "--sim",
        "experiments/scenes/viscoelastic_hemisphere.toml",
        "--dry-run",
    ]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    let s = util::stdout(&o);
    assert!(
        s.contains("13 setpoints")
            && s.contains("hold: 300 gf for 4 s, 2 hold(s); samples at 0, 1, 2, 3, 4 s after the force is reached"),
        "{s}"
    );
    let sample: Vec<&str> = s
        .lines()
        .map(|l| l.split_whitespace().collect::<Vec<_>>())
        .find(|w| w.first() == Some(&"4"))
        .unwrap_or_default();
    assert_eq!(
        sample[sample.len() - 3..],
        ["-", "-", "3"],
        "row 4 is the 3 s sample"
    );

    // A position off the sensor (inside a widened travel box) fails the dry run.
    let p = example(tmp.path(), "magnitude_updown.toml", "off.toml", |t| {
        t.replace(
            "travel_max_mm = [18.0, 13.5, 3.0]",
            "travel_max_mm = [30.0, 13.5, 3.0]",
        )
        .replace("[10.5, 6.75]]", "[25.0, 6.75]]")
    });
    let o = util::run(&["run", p.to_str().unwrap(), "--dry-run"]);
    assert_eq!(o.status.code(), Some(3), "{}", util::stderr(&o));
    assert!(
        util::stdout(&o)
            .contains("[FAIL] sweep.positions_mm[2] [25, 6.75] mm OUTSIDE the sensor's force grid"),
        "{}",
        util::stdout(&o)
    );
}

#[test]
fn the_up_down_example_runs_three_trials_at_three_positions_with_direction_and_position() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("run");
    let plan = Plan::from_path(util::root("experiments/magnitude_updown.toml")).unwrap();
    let rows = run_sim(
        &util::root("experiments/magnitude_updown.toml"),
        &util::root("experiments/scenes/fig7_hemisphere_ramp.toml"),
        &out,
    );
    let sps = plan.setpoints();
    assert_eq!(rows.len(), 45);
    let tol = plan.force_tolerance_n + 0.013;
    for (r, sp) in rows.iter().zip(&sps) {
        assert_eq!(r.index, sp.index);
        assert_eq!(
            (r.trial, r.direction, r.position, r.hold_t_s),
            (sp.trial, sp.direction, sp.position, None),
            "row {}",
            r.index
        );
        assert!(
            (r.fz_n - sp.normal_n).abs() <= tol,
            "row {}: fz {}",
            r.index,
            r.fz_n
        );
        // The stage pressed where the row says: position p is x = 9, 7.5, 10.5 mm
        // (GRBL sensor origin at stage x = -100 mm).
        let x = [9.0, 7.5, 10.5][r.position.unwrap()];
        assert!((r.stage_x_mm - (x - 100.0)).abs() < 1e-3, "row {}", r.index);
    }
    for trial in 0..9 {
        let t: Vec<&JournalRow> = rows.iter().filter(|r| r.trial == trial).collect();
        let levels: Vec<(f64, Option<Direction>)> =
            t.iter().map(|r| (r.swept_value, r.direction)).collect();
        let (u, d) = (Some(Direction::Up), Some(Direction::Down));
        assert_eq!(
            levels,
            [(0.0, u), (150.0, u), (300.0, u), (150.0, d), (0.0, d)],
            "trial {trial}"
        );
        assert_eq!(t[0].position, Some(trial / 3));
        // Unloaded at both ends: the contact was released.
        assert!(
            t[0].fz_n.abs() < 0.013 && t[4].fz_n.abs() < 0.013,
            "trial {trial}"
        );
    }
    let text = std::fs::read_to_string(out.join("journal.csv")).unwrap();
    assert!(text.lines().nth(4).unwrap().contains(",down,0,"), "{text}");
}

/// The loop of a one-trial up-down sweep: per loaded `down` row, its force `fz`, its
/// `F_sum z` and the up branch's at the same `fz` (interpolated linearly in the F/T
/// force: the levels differ by the control tolerance), and the full-scale output
/// (`F_sum z` at the top).
fn loop_points(rows: &[JournalRow]) -> Vec<(f64, f64, f64, f64)> {
    let mut up: Vec<(f64, f64)> = rows
        .iter()
        .filter(|r| r.direction == Some(Direction::Up))
        .map(|r| (r.fz_n, r.fsum_z_n))
        .collect();
    up.sort_by(|a, b| a.0.total_cmp(&b.0));
    let top = up.last().unwrap().1;
    let at = |f: f64| {
        let i = up
            .iter()
            .position(|p| p.0 >= f)
            .unwrap_or(up.len() - 1)
            .max(1);
        let (a, b) = (up[i - 1], up[i]);
        a.1 + (b.1 - a.1) * (f - a.0) / (b.0 - a.0)
    };
    rows.iter()
        .filter(|r| r.direction == Some(Direction::Down) && r.target_normal_n > 0.0)
        .map(|r| (r.fz_n, r.fsum_z_n, at(r.fz_n), top))
        .collect()
}

#[test]
fn an_ideal_bench_shows_no_hysteresis_and_a_viscoelastic_one_the_configured_loop() {
    let tmp = tempfile::tempdir().unwrap();
    let plan = example(tmp.path(), "magnitude_updown.toml", "loop.toml", |t| {
        fixed_rank(
            t.replace("to = 300.0", "to = 400.0")
                .replace("step = 150.0", "step = 100.0")
                .replace("trials = 3", "trials = 1")
                .replace(
                    "positions_mm = [[9.0, 6.75], [7.5, 6.75], [10.5, 6.75]]",
                    "",
                ),
        )
    });
    let ideal = tent_scene(tmp.path(), "ideal.toml", "");
    let h = 0.1;
    let hyst = tent_scene(
        tmp.path(),
        "hyst.toml",
        &format!("[bench]\nviscoelastic = {{ hysteresis = {h} }}\n"),
    );
    let rows_ideal = run_sim(&plan, &ideal, &tmp.path().join("ideal"));
    let rows_hyst = run_sim(&plan, &hyst, &tmp.path().join("hyst"));
    assert_eq!(rows_ideal.len(), 9);
    // Ideal: the down rows lie on the up branch (within 1 % of full scale: the
    // DynPick's 1/82 N counts and the tracker's 1e-3 px).
    for (fz, down, up, fs) in loop_points(&rows_ideal) {
        let w = (down - up) / fs;
        assert!(
            w.abs() < 0.01,
            "ideal at {fz} N: down - up = {w} of full scale"
        );
    }
    // Viscoelastic: unloading from the top P, the camera sees the field of
    // F + 4hF(P − F)/P, so down / up = 1 + 4h(P − F)/P (h = 0.1: 1.2 at P/2, 1.3 at
    // P/4), within 3 % (the up branch is interpolated between levels 1 N apart; the
    // levels are approached from one side, so the up rows are pure loading).
    let top = rows_hyst.iter().map(|r| r.fz_n).fold(0.0f64, f64::max);
    let points = loop_points(&rows_hyst);
    assert_eq!(points.len(), 3);
    for (fz, down, up, _) in points {
        let want = 1.0 + 4.0 * h * (top - fz) / top;
        assert!(
            (down / up - want).abs() < 0.03,
            "at {fz} N: down / up = {}, the model's {want}",
            down / up
        );
    }
}

#[test]
fn the_hold_example_samples_on_its_schedule_between_unloaded_readings() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("hold");
    let plan = Plan::from_path(util::root("experiments/hold_example.toml")).unwrap();
    let rows = run_sim(
        &util::root("experiments/hold_example.toml"),
        &util::root("experiments/scenes/viscoelastic_hemisphere.toml"),
        &out,
    );
    assert_eq!(rows.len(), 13);
    let sps = plan.setpoints();
    let mut last: Option<f64> = None;
    for (r, sp) in rows.iter().zip(&sps) {
        assert_eq!((r.trial, r.direction, r.position), (sp.trial, None, None));
        match sp.hold_t_s {
            None => {
                assert_eq!(r.target_normal_n, 0.0);
                assert_eq!(r.hold_t_s, None, "row {}", r.index);
                assert!(r.fz_n.abs() < 0.013, "unloaded: {}", r.fz_n);
                last = None;
            }
            Some(t) => {
                let got = r.hold_t_s.expect("a hold sample has hold_t_s");
                assert!(
                    got >= t,
                    "row {}: sampled at {got} s, scheduled {t} s",
                    r.index
                );
                assert!(last.is_none_or(|l| got > l), "row {}", r.index);
                assert!(r.settled, "an uninterrupted hold");
                last = Some(got);
            }
        }
    }
    // The force was controlled once per hold: the stage stood still through it.
    for hold in [1..6, 7..12] {
        let z: Vec<f64> = rows[hold].iter().map(|r| r.stage_z_mm).collect();
        assert!(z.iter().all(|v| *v == z[0]), "{z:?}");
    }
    let text = std::fs::read_to_string(out.join("journal.csv")).unwrap();
    let row2 = text.lines().nth(3).unwrap();
    assert!(row2.starts_with("2,0,300,"), "{row2}");
    assert!(row2.ends_with(",,,1.0") || row2.contains(",,,1."), "{row2}");
}

#[test]
fn the_viscoelastic_creep_shows_in_f_sum_over_hold_t_s_and_the_ideal_bench_has_none() {
    let tmp = tempfile::tempdir().unwrap();
    let plan = example(tmp.path(), "hold_example.toml", "hold.toml", |t| {
        fixed_rank(
            t.replace("duration_s = 4.0", "duration_s = 3.0")
                .replace("sample_interval_s = 1.0", "sample_interval_s = 0.5")
                .replace("trials = 2 ", "trials = 1 "),
        )
    });
    let (a, tau) = (0.2, 1.0);
    let ideal = tent_scene(tmp.path(), "ideal.toml", "");
    let creep = tent_scene(
        tmp.path(),
        "creep.toml",
        &format!("[bench]\nviscoelastic = {{ creep = {a}, time_constant_s = {tau} }}\n"),
    );
    let samples = |rows: &[JournalRow]| -> Vec<(f64, f64, f64)> {
        rows.iter()
            .filter_map(|r| r.hold_t_s.map(|t| (t, r.fz_n, r.fsum_z_n)))
            .collect()
    };
    let ideal_rows = samples(&run_sim(&plan, &ideal, &tmp.path().join("ideal")));
    assert_eq!(ideal_rows.len(), 7);
    // Ideal: zero creep, exactly (same stage position, same frames).
    let (_, fz0, k) = ideal_rows[0];
    for (t, fz, fsum) in &ideal_rows {
        assert_eq!((*fz, *fsum), (fz0, k), "ideal at {t} s");
    }
    // Viscoelastic: F_sum / K = 1 + a − (a − c₀/F)·e^{−t/τ} (c₀ the creep already
    // there when the force was reached): the least-squares fit of A − B·e^{−t/τ}
    // gives A = 1 + a.
    let creep_rows = samples(&run_sim(&plan, &creep, &tmp.path().join("creep")));
    let (xs, ys): (Vec<f64>, Vec<f64>) = creep_rows
        .iter()
        .map(|(t, _, fsum)| ((-t / tau).exp(), fsum / k))
        .unzip();
    let n = xs.len() as f64;
    let (mx, my) = (xs.iter().sum::<f64>() / n, ys.iter().sum::<f64>() / n);
    let b = xs
        .iter()
        .zip(&ys)
        .map(|(x, y)| (x - mx) * (y - my))
        .sum::<f64>()
        / xs.iter().map(|x| (x - mx).powi(2)).sum::<f64>();
    let big_a = my - b * mx;
    assert!(
        (big_a - (1.0 + a)).abs() <= 0.02,
        "fitted asymptote {big_a} vs 1 + creep = {}; samples {creep_rows:?}",
        1.0 + a
    );
    assert!(b < 0.0, "F_sum grows through the hold");
    // The F/T side holds still (no force relaxation in this scene).
    assert!(creep_rows.iter().all(|(_, fz, _)| *fz == creep_rows[0].1));
}

#[test]
fn a_run_killed_mid_hold_resumes_with_the_force_re_established_and_no_row_repeated() {
    let tmp = tempfile::tempdir().unwrap();
    let plan = example(tmp.path(), "hold_example.toml", "hold.toml", |t| {
        t.replace("duration_s = 4.0", "duration_s = 3.0")
    });
    let scene = util::root("experiments/scenes/fig7_hemisphere_ramp.toml");
    let out = tmp.path().join("run");
    let mut child = Command::new(util::bin())
        .args([
            "run",
            plan.to_str().unwrap(),
            "--sim",
            scene.to_str().unwrap(),
        ])
        .args(["--no-progress", "--out", out.to_str().unwrap()])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // Rows: 0 unloaded, 1..=4 the first hold (0, 1, 2, 3 s), 5 unloaded, ...
    let t = Instant::now();
    loop {
        let done = std::fs::read_to_string(out.join("journal.csv"))
            .map(|s| s.lines().count().saturating_sub(1))
            .unwrap_or(0);
        if done >= 3 {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "no progress");
        assert!(child.try_wait().unwrap().is_none(), "run ended early");
        std::thread::sleep(Duration::from_millis(5));
    }
    child.kill().unwrap(); // mid-hold: the next sample is a second away
    child.wait().unwrap();
    let before = rows(&out).len();
    assert!((3..5).contains(&before), "{before} rows before the kill");

    let o = util::run(&["run", "--resume", out.to_str().unwrap(), "--no-progress"]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    assert!(
        util::stderr(&o).contains("resumed part-way"),
        "the restart is logged: {}",
        util::stderr(&o)
    );
    let rows = rows(&out);
    assert_eq!(
        rows.iter().map(|r| r.index).collect::<Vec<_>>(),
        (0..11).collect::<Vec<_>>(),
        "every setpoint exactly once"
    );
    let sched = [None, Some(0.0), Some(1.0), Some(2.0), Some(3.0), None];
    for r in &rows {
        let s = if r.index < 6 {
            sched[r.index]
        } else {
            sched[r.index - 5]
        };
        match s {
            None => assert!(r.hold_t_s.is_none() && r.settled, "row {}", r.index),
            Some(t) => {
                let got = r.hold_t_s.unwrap();
                assert!(
                    got >= t,
                    "row {}: {got} s before its schedule {t} s",
                    r.index
                );
                // Rows of the interrupted hold measured after the resume are flagged;
                // the ones before it and the next hold are not.
                let restarted = r.index >= before && r.index < 5;
                assert_eq!(r.settled, !restarted, "row {}", r.index);
                // Re-established: the force is back at the target.
                assert!(
                    (r.fz_n - r.target_normal_n).abs() < 0.062,
                    "row {}",
                    r.index
                );
            }
        }
    }
}
