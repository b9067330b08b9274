//! The ground truth `tactbench fit` is tested on: a scene's sensor that differs from
//! the plan's (the truth the camera and the force law see against the nominal one the
//! run reconstructs with) through `run --sim` and `run --bench` with a `[sim]` bench
//! file, and `bench::synthetic_run` against `run --sim` on the same plan.

use std::path::Path;

use tactbench::bench::journal::{read_rows, JournalRow, Manifest};
use tactbench::bench::plan::Plan;
use tactbench::bench::synthetic::{synthetic_run, SyntheticOptions};
use tactbench::formats::read_displacements;
use tactbench::sensor::Sensor;
use tactbench::sim::scene::Scene;

use crate::util::{root, run, stderr};

/// A small plan on the calibration plan's settings: two normal loads at two
/// positions and one shear, hemisphere, two frames, sensor `sensor` (absolute).
fn small_plan(dir: &Path, sensor: &Path) -> std::path::PathBuf {
    let text = std::fs::read_to_string(root("experiments/calibrate_elastomer.toml")).unwrap();
    let head = text.split("\n[[sweep.points]]").next().unwrap();
    let head = head.replace(
        "sensor = \"paper_sensor.toml\"",
        &format!("sensor = {:?}", sensor.display().to_string()),
    );
    // pinv: a linear map, so force sums scale exactly with the displacements (GCV's
    // λ would follow the signal and bias the two gels differently).
    let head = head.replace(
        "solver = \"tikhonov\"\nlambda = \"gcv\"",
        "solver = \"pinv\"",
    );
    assert!(head.contains("solver = \"pinv\""));
    let plan = format!(
        "{head}\n[[sweep.points]]\nposition_mm = [9.0, 6.75]\nnormal = 1.0\n\n[[sweep.points]]\nposition_mm = [7.0, 6.75]\nnormal = 2.5\n\n[[sweep.points]]\nposition_mm = [9.0, 6.75]\nnormal = 2.0\ntangential = [0.6, 0.0]\n"
    );
    let path = dir.join("small_plan.toml");
    std::fs::write(&path, plan).unwrap();
    path
}

/// A copy of the mis-built scene `name` in `dir` without its camera effects (pixel
/// noise, 8-bit quantisation; the F/T noise of `[bench]` stays), its sensor path made
/// absolute. With pinv, the scenes' camera noise (2 levels) puts a tracking noise of
/// about 0.55 N on one setpoint's force sum (measured over 20 seeds; the journal's
/// `fsum_sd_z_n` says 0.33 N, the frames' scatter only), so the force sums of
/// single setpoints are compared without it.
fn without_camera_noise(dir: &Path, name: &str) -> std::path::PathBuf {
    let misbuilt = root("experiments/scenes/misbuilt");
    let text = std::fs::read_to_string(misbuilt.join(name)).unwrap();
    let (mut out, mut in_effect) = (String::new(), false);
    for line in text.lines() {
        let t = line.trim_start();
        if t.starts_with('[') {
            in_effect = t.starts_with("[[effects]]");
        }
        if in_effect {
            continue;
        }
        match t.strip_prefix("sensor = ") {
            Some(rel) => {
                let abs = misbuilt.join(rel.trim().trim_matches('"'));
                out.push_str(&format!("sensor = {:?}\n", abs.display().to_string()));
            }
            None => {
                out.push_str(line);
                out.push('\n');
            }
        }
    }
    assert!(
        !out.contains("pixel_noise") && out.contains("ft_noise"),
        "{out}"
    );
    let path = dir.join(format!("clean_{name}"));
    std::fs::write(&path, out).unwrap();
    path
}

fn run_sim(plan: &Path, scene: &Path, out: &Path) {
    let o = run(&[
        "run",
        plan.to_str().unwrap(),
        "--sim",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "run --sim: {}", stderr(&o));
}

fn synthetic(plan: &Path, scene: &Path, out: &Path) {
    let text = std::fs::read_to_string(plan).unwrap();
    let p = Plan::from_toml_str(&text, plan).unwrap();
    let s = Scene::from_path(scene).unwrap();
    synthetic_run(&p, &text, &s, out, &SyntheticOptions::default()).unwrap();
}

/// Hertz for the 5 mm hemisphere of the scenes on a gel of modulus `e_kpa`, ν = 0.5:
/// `P = 4/3 E* √R δ^{3/2}`, at the GRBL simulated bench's surface z = −30 mm pressing
/// towards −z.
fn hertz_n(e_kpa: f64, stage_z_mm: f64) -> f64 {
    let e_star = e_kpa * 1e-3 / (1.0 - 0.25);
    let depth = -(stage_z_mm + 30.0);
    4.0 / 3.0 * e_star * 2.5f64.sqrt() * depth.max(0.0).powf(1.5)
}

/// How far a journalled F/T mean may be from the force it measures, N: half a count
/// of the simulated DynPick (1/32.8 N: its 5 mN noise is too small to dither the
/// rounding away) plus three σ of the mean of 20 samples of that noise.
const FT_READ_N: f64 = 0.5 / 32.8 + 3.0 * 0.005 / 4.47;

fn ratio_z(r: &JournalRow) -> f64 {
    r.fsum_z_n / r.fz_n
}

/// Was ignored as "synthetic_run's F_sum/F 0.19 against run --sim's ~1.39": both
/// paths track the same displacements; the two ratios were single pinv solves under
/// the scenes' camera noise (see [`without_camera_noise`]), a difference of about
/// 1.4 σ. Compared without the camera noise, the soft gel's ratio is 1/0.7 times the
/// nominal one as the elastic model says.
#[test]
fn a_scene_gel_30_percent_soft_follows_its_own_law_and_scales_the_nominal_force_sum() {
    let tmp = tempfile::tempdir().unwrap();
    let misbuilt = root("experiments/scenes/misbuilt");
    let plan = small_plan(tmp.path(), &misbuilt.join("nominal_half_space.toml"));
    let soft = without_camera_noise(tmp.path(), "e_minus30.toml");
    // Through `run --sim` and through a `[sim]` bench file.
    let via_sim = tmp.path().join("sim");
    run_sim(&plan, &soft, &via_sim);
    let bench = tmp.path().join("bench.toml");
    std::fs::write(
        &bench,
        format!(
            "[sim]\nscene = {:?}\nstage = \"grbl\"\nforce_sensor = \"dynpick\"\n",
            soft.display().to_string()
        ),
    )
    .unwrap();
    let via_bench = tmp.path().join("bench");
    let o = run(&[
        "run",
        plan.to_str().unwrap(),
        "--bench",
        bench.to_str().unwrap(),
        "--out",
        via_bench.to_str().unwrap(),
        "--limit",
        "2",
    ]);
    assert!(o.status.success(), "run --bench: {}", stderr(&o));
    // The control: the nominal scene (as built = as declared), synthetic.
    let control = tmp.path().join("control");
    synthetic(
        &plan,
        &without_camera_noise(tmp.path(), "nominal.toml"),
        &control,
    );
    let control_rows = read_rows(&control).unwrap();

    for dir in [&via_sim, &via_bench] {
        let m = Manifest::read(dir).unwrap();
        assert!(
            m.sensor_toml.contains("young_modulus_kpa = 1000.0"),
            "the plan's sensor is recorded"
        );
        assert_eq!(m.bench["geometry"]["press_direction"], -1.0, "{}", m.bench);
        let rows = read_rows(dir).unwrap();
        for r in rows.iter().filter(|r| r.target_tx_n == 0.0) {
            // The F/T sensor reads the truth's law at the stage z it journalled (to
            // its resolution and noise; GRBL's 1 µm position steps move it < 3 mN).
            let want = hertz_n(700.0, r.stage_z_mm);
            assert!(
                (r.fz_n - want).abs() < FT_READ_N + 0.003,
                "{}: setpoint {} fz {} N, Hertz at E = 700 kPa {want} N (at 1000 kPa {} N)",
                dir.display(),
                r.index,
                r.fz_n,
                hertz_n(1000.0, r.stage_z_mm)
            );
            // The force sum reconstructed with the nominal E is E_nom / E_true = 1/0.7
            // times the force, against the same solver's ratio on the nominal gel, up
            // to what pinv's force-sum bias (0.8 to 1.0 here) changes with the contact's
            // shape: the soft gel's contact is (1/0.7)^(1/3) = 1.13 times wider at the
            // same force (Hertz), and the frames are rendered at other depths (measured
            // k: 1.36 to 1.47 over both routes and setpoints). Within 10 % of 1/0.7 is
            // still far from 1 (E not seen) and from 2 (E half).
            let c = &control_rows[r.index];
            let k = ratio_z(r) / ratio_z(c);
            assert!(
                (k - 1.0 / 0.7).abs() < 0.1 / 0.7,
                "{}: setpoint {}: F_sum/F ratio {} against the nominal gel's {}: {k}, predicted {}",
                dir.display(),
                r.index,
                ratio_z(r),
                ratio_z(c),
                1.0 / 0.7
            );
        }
    }
}

#[test]
fn synthetic_run_agrees_with_run_sim_on_the_same_plan_and_report_accepts_it() {
    let tmp = tempfile::tempdir().unwrap();
    let misbuilt = root("experiments/scenes/misbuilt");
    let plan = small_plan(tmp.path(), &misbuilt.join("nominal_half_space.toml"));
    let scene = misbuilt.join("ft_rotated_7deg.toml");
    let (a, b) = (tmp.path().join("sim"), tmp.path().join("synthetic"));
    run_sim(&plan, &scene, &a);
    synthetic(&plan, &scene, &b);
    let (ra, rb) = (read_rows(&a).unwrap(), read_rows(&b).unwrap());
    assert_eq!(ra.len(), rb.len());
    let sensor = Sensor::from_path(misbuilt.join("nominal_half_space.toml")).unwrap();
    let tol = 0.03; // the plan's control.force_tolerance, N
    for (x, y) in ra.iter().zip(&rb) {
        assert_eq!(
            (x.index, x.trial, x.position),
            (y.index, y.trial, y.position)
        );
        // The runner stops within the tolerance of the targets; the F/T readings of
        // both are in the rotated sensor's axes.
        assert!((x.fz_n - y.fz_n).abs() <= tol + FT_READ_N, "{x:?}\n{y:?}");
        let (qa, qb) = (x.fx_n, y.fx_n);
        assert!((qa - qb).abs() <= tol + FT_READ_N, "fx {qa} vs {qb}");
        // Rotated 7°: a shear along sensor +x reads fy = −sin 7° |Q| in the F/T axes.
        if x.target_tx_n > 0.0 {
            let q = y.fx_n / 7f64.to_radians().cos();
            assert!(
                (y.fy_n + q * 7f64.to_radians().sin()).abs() < FT_READ_N,
                "{y:?}"
            );
            assert!((x.fy_n - y.fy_n).abs() < tol, "fy {} vs {}", x.fy_n, y.fy_n);
        }
        assert!((x.stage_z_mm - y.stage_z_mm).abs() < 0.02, "{x:?}\n{y:?}");
        assert_eq!(x.frames, y.frames);
        // Displacements: the same markers, within tracking noise plus what the force
        // tolerance changes (both small against the field).
        let name = format!("displacements/{:05}.csv", x.index);
        let da = read_displacements(&a.join(&name), &sensor).unwrap();
        let db = read_displacements(&b.join(&name), &sensor).unwrap();
        assert_eq!(da.len(), db.len(), "{name}: frames");
        let (mut ss, mut ss_u, mut n) = (0.0, 0.0, 0);
        for (fa, fb) in da.iter().zip(&db) {
            for (p, q) in fa.records.iter().zip(&fb.records) {
                assert_eq!((p.layer, p.marker), (q.layer, q.marker));
                if let (Some(u), Some(v)) = (p.u_mm, q.u_mm) {
                    ss += (u[0] - v[0]).powi(2) + (u[1] - v[1]).powi(2);
                    ss_u += v[0] * v[0] + v[1] * v[1];
                    n += 1;
                }
            }
        }
        assert!(n > 200, "{name}: {n} markers ok in both");
        let (rms, rms_u) = ((ss / n as f64).sqrt(), (ss_u / n as f64).sqrt());
        assert!(
            rms < 0.002 + 0.03 * rms_u,
            "{name}: rms difference {rms} mm against an rms field of {rms_u} mm"
        );
        assert!(y.fsum_z_n.is_finite() && y.failure.is_none(), "{y:?}");
    }
    let m = Manifest::read(&b).unwrap();
    assert_eq!(m.simulated, Some(true));
    assert_eq!(m.bench["geometry"]["surface_z_mm"], -30.0);
    let o = run(&["report", b.to_str().unwrap()]);
    assert!(o.status.success(), "report: {}", stderr(&o));
    assert!(b.join("report.html").exists());
    assert!(
        !crate::util::stdout(&o).contains("modified") && !stderr(&o).contains("modified"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn synthetic_runs_of_another_seed_differ_and_of_the_same_seed_repeat() {
    let tmp = tempfile::tempdir().unwrap();
    let misbuilt = root("experiments/scenes/misbuilt");
    let plan = small_plan(tmp.path(), &misbuilt.join("nominal_half_space.toml"));
    let text = std::fs::read_to_string(&plan).unwrap();
    let p = Plan::from_toml_str(&text, &plan).unwrap();
    let s = Scene::from_path(misbuilt.join("e_plus50.toml")).unwrap();
    let gen = |name: &str, seed: u64| {
        let d = tmp.path().join(name);
        let o = SyntheticOptions {
            seed: Some(seed),
            skip_frames: true,
            ..SyntheticOptions::default()
        };
        synthetic_run(&p, &text, &s, &d, &o).unwrap();
        read_rows(&d).unwrap()
    };
    let (a, b, c) = (gen("a", 1), gen("b", 1), gen("c", 2));
    let key = |r: &[JournalRow]| r.iter().map(|x| (x.fz_n, x.fsum_z_n)).collect::<Vec<_>>();
    assert_eq!(key(&a), key(&b));
    assert_ne!(key(&a), key(&c));
    // An existing run is not overwritten.
    let o = SyntheticOptions::default();
    let e = synthetic_run(&p, &text, &s, &tmp.path().join("a"), &o).unwrap_err();
    assert!(e.to_string().contains("already holds a run"), "{e}");
}

/// The discrepancy of the ignored ratio test: without camera noise, the two paths'
/// pinv force sums agree setpoint by setpoint, so neither path was wrong.
#[test]
fn the_pinv_force_sum_gap_of_synthetic_and_run_sim_was_camera_noise() {
    let tmp = tempfile::tempdir().unwrap();
    let misbuilt = root("experiments/scenes/misbuilt");
    let plan = small_plan(tmp.path(), &misbuilt.join("nominal_half_space.toml"));
    let scene = without_camera_noise(tmp.path(), "nominal.toml");
    let (a, b) = (tmp.path().join("sim"), tmp.path().join("synthetic"));
    run_sim(&plan, &scene, &a);
    synthetic(&plan, &scene, &b);
    for (x, y) in read_rows(&a).unwrap().iter().zip(read_rows(&b).unwrap()) {
        // The force sums per newton of F/T force: the runner stops within 30 mN of
        // the target, the synthetic run on it; what is left is pinv's response to the
        // frames' 8-bit rendering at slightly different depths (measured: 0.1 % to 3 %).
        let (ra, rb) = (ratio_z(x), ratio_z(&y));
        assert!(
            (ra - rb).abs() < 0.05 * rb,
            "setpoint {}: F_sum/F run --sim {ra}, synthetic {rb}",
            x.index
        );
        // The noise-free ratios are near 1 (0.8 to 1.0), far from the 0.19 a noisy
        // synthetic setpoint gave.
        assert!(rb > 0.7 && rb < 1.1, "setpoint {}: {rb}", y.index);
    }
}

/// Fixed: `synthetic_run` wrote its force files without the per-node σ columns the
/// runner writes since issue 32, recorded an empty bench `file` where `run --sim`
/// records the scene, and gave the F/T readings untared and unquantised where
/// `run --sim`'s simulated DynPick reads counts of 1/32.8 N after a tare.
#[test]
fn synthetic_run_writes_the_force_sigma_bench_file_and_ft_counts_run_sim_writes() {
    let tmp = tempfile::tempdir().unwrap();
    let misbuilt = root("experiments/scenes/misbuilt");
    let plan = small_plan(tmp.path(), &misbuilt.join("nominal_half_space.toml"));
    let scene = misbuilt.join("nominal.toml");
    let (a, b) = (tmp.path().join("sim"), tmp.path().join("synthetic"));
    run_sim(&plan, &scene, &a);
    synthetic(&plan, &scene, &b);
    let header = |d: &Path, i: usize| {
        let t = std::fs::read_to_string(d.join(format!("forces/{i:05}.csv"))).unwrap();
        t.lines().next().unwrap().to_string()
    };
    let (ma, mb) = (Manifest::read(&a).unwrap(), Manifest::read(&b).unwrap());
    assert_eq!(ma.bench["file"], mb.bench["file"]);
    assert_eq!(mb.bench["file"], scene.display().to_string());
    let samples = 20.0; // the plan's acquire.samples
    for (x, y) in read_rows(&a).unwrap().iter().zip(read_rows(&b).unwrap()) {
        let h = header(&b, y.index);
        assert_eq!(header(&a, x.index), h);
        assert!(h.contains("sfz_n"), "{h}");
        for (dir, r) in [("run --sim", x), ("synthetic", &y)] {
            for f in [r.fx_n, r.fy_n, r.fz_n] {
                // A mean of 20 readings of whole counts of 1/32.8 N.
                let counts = f * 32.8 * samples;
                assert!(
                    (counts - counts.round()).abs() < 1e-6,
                    "{dir}: setpoint {} reads {f} N, not a mean of DynPick counts",
                    r.index
                );
            }
        }
    }
}

/// One setpoint's displacements, tracked by both paths from their own frames, differ
/// by the tracking noise of the two (each path's mean of two frames less its
/// reference: σ√1.5 per path, σ from the scatter between its frames) plus the field
/// change of the force difference the runner's control tolerance allows.
#[test]
fn one_setpoint_s_displacements_of_both_paths_agree_within_tracking_noise() {
    let tmp = tempfile::tempdir().unwrap();
    let misbuilt = root("experiments/scenes/misbuilt");
    let sensor_path = misbuilt.join("nominal_half_space.toml");
    let plan = small_plan(tmp.path(), &sensor_path);
    let scene = misbuilt.join("nominal.toml");
    let (a, b) = (tmp.path().join("sim"), tmp.path().join("synthetic"));
    run_sim(&plan, &scene, &a);
    synthetic(&plan, &scene, &b);
    let sensor = Sensor::from_path(&sensor_path).unwrap();
    // Setpoint 1: 2.5 N at (7, 6.75) mm.
    let name = "displacements/00001.csv";
    let (da, db) = (
        read_displacements(&a.join(name), &sensor).unwrap(),
        read_displacements(&b.join(name), &sensor).unwrap(),
    );
    assert_eq!((da.len(), db.len()), (2, 2), "{name}: two frames each");
    let u = |f: &tactbench::formats::DisplacementFrame| {
        f.records.iter().map(|r| r.u_mm).collect::<Vec<_>>()
    };
    let (a0, a1, b0, b1) = (u(&da[0]), u(&da[1]), u(&db[0]), u(&db[1]));
    let (mut scatter, mut diff, mut field, mut n) = (0.0, 0.0, 0.0, 0usize);
    for i in 0..a0.len() {
        let (Some(p0), Some(p1), Some(q0), Some(q1)) = (a0[i], a1[i], b0[i], b1[i]) else {
            continue;
        };
        for ax in 0..2 {
            // var(u0 − u1) = 2σ² per path.
            scatter += ((p0[ax] - p1[ax]).powi(2) + (q0[ax] - q1[ax]).powi(2)) / 4.0;
            let (ma, mb) = ((p0[ax] + p1[ax]) / 2.0, (q0[ax] + q1[ax]) / 2.0);
            diff += (ma - mb).powi(2);
            field += mb * mb;
            n += 1;
        }
    }
    // 260 markers (two layers of 130), two components each.
    assert!(n > 400, "{n} components tracked in all four frames");
    let (sigma, rms, rms_u) = (
        (scatter / n as f64).sqrt(),
        (diff / n as f64).sqrt(),
        (field / n as f64).sqrt(),
    );
    let (x, y) = (&read_rows(&a).unwrap()[1], &read_rows(&b).unwrap()[1]);
    let control = ((x.fz_n - y.fz_n).abs() + 0.03) / y.fz_n * rms_u;
    let bound = (1.2 * 3f64.sqrt() * sigma).hypot(control);
    assert!(
        rms < bound,
        "rms difference {rms} mm, tracking noise σ {sigma} mm, field {rms_u} mm, bound {bound} mm"
    );
    // And the field is far above both: the comparison is not of noise against noise.
    assert!(rms_u > 20.0 * sigma, "field {rms_u} mm, σ {sigma} mm");
}
