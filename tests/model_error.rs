//! The model-error study (issue 14, deliverable 5): library (`run_model_error`) and
//! `tactbench study model-error`.

use std::collections::HashMap;
use std::path::Path;

use tactbench::analysis::model_error::{
    run_model_error, CameraEffects, DataPath, EffectSet, LoadKind, ModelErrorOptions,
    ModelErrorResult, RowStatus, MODEL_ERROR_COLUMNS,
};
use tactbench::sensor::{paper_sensor, ModelKind};
use tactbench::solve::{Method, SolverConfig};

use crate::util;

/// Forward-path options (no camera), one timing repetition.
fn forward_only(thicknesses: &[f64]) -> ModelErrorOptions {
    ModelErrorOptions {
        thicknesses_mm: thicknesses.to_vec(),
        effects: vec![EffectSet::Forward],
        reps: 1,
        ..ModelErrorOptions::default()
    }
}

fn field(
    r: &ModelErrorResult,
    h: f64,
    physics: ModelKind,
    solver: ModelKind,
    l: LoadKind,
) -> (f64, f64) {
    let row = r
        .find(h, physics, solver, Method::Tikhonov, l, "none")
        .unwrap_or_else(|| panic!("no row h={h} {physics} {solver} {l:?}"));
    (row.errors.field, row.errors.sum)
}

#[test]
fn mismatched_solvers_converge_to_the_matched_one_as_the_layer_thickens() {
    // Marker depths stay the paper's 3 / 6 mm at these thicknesses, so only the rigid
    // plate's distance changes: the layer tends to the half-space (its difference falls
    // like 1/h), and so must the error of a solver that assumes the other model, in
    // both directions, for every load, in the field and in F_sum.
    let hs = [20.0, 80.0, 320.0];
    let r = run_model_error(
        &paper_sensor(),
        &CameraEffects::default_camera(),
        &forward_only(&hs),
        &mut |_| {},
    )
    .unwrap();
    assert_eq!(r.rows.len(), 3 * 2 * 3 * 2);
    assert!(r
        .rows
        .iter()
        .all(|r| r.is_ok() && r.data == DataPath::Forward));
    for load in LoadKind::ALL {
        for (physics, solver) in [
            (ModelKind::BondedLayer, ModelKind::HalfSpace),
            (ModelKind::HalfSpace, ModelKind::BondedLayer),
        ] {
            let e: Vec<(f64, f64)> = hs
                .iter()
                .map(|&h| field(&r, h, physics, solver, load))
                .collect();
            for w in e.windows(2) {
                assert!(
                    w[1].0 < w[0].0 && w[1].1 < w[0].1,
                    "{load:?} {physics} data, {solver} solver: {e:?}"
                );
            }
            // At 320 mm the F_sum error is a small fraction of the one at 20 mm.
            assert!(e[2].1 < 0.25 * e[0].1, "{load:?}: {e:?}");
        }
        // The matched solvers recover exact data at every thickness.
        for &h in &hs {
            for m in [ModelKind::BondedLayer, ModelKind::HalfSpace] {
                let (f, s) = field(&r, h, m, m, load);
                assert!(f < 1e-3 && s < 1e-3, "h={h} {m} {load:?}: {f} {s}");
            }
        }
    }
}

#[test]
fn solver_refusals_are_rows_with_the_solvers_reason() {
    let options = ModelErrorOptions {
        solvers: vec![
            SolverConfig {
                method: Method::Tikhonov,
                ..SolverConfig::default()
            },
            SolverConfig {
                method: Method::Fourier,
                ..SolverConfig::default()
            },
        ],
        loads: vec![LoadKind::Normal],
        ..forward_only(&[40.0])
    };
    let r = run_model_error(
        &paper_sensor(),
        &CameraEffects::default_camera(),
        &options,
        &mut |_| {},
    )
    .unwrap();
    // 2 physics × 2 solver models × 2 solver kinds.
    assert_eq!(r.rows.len(), 8);
    for row in &r.rows {
        match (row.solver, &row.status) {
            (Method::Tikhonov, RowStatus::Ok) => {}
            // The paper's 2.2 mm force grid and 1.5 mm markers have no common lattice
            // (and a bonded-layer sensor is refused until fourier learns the kernel).
            (Method::Fourier, RowStatus::Refused(why)) => {
                assert!(why.contains("fourier"), "{why}")
            }
            (m, s) => panic!("{m} {:?}: {s:?}", row.solver_model),
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("m.csv");
    r.write_csv(&csv).unwrap();
    let text = std::fs::read_to_string(&csv).unwrap();
    let refused: Vec<&str> = text.lines().filter(|l| l.contains(",refused,")).collect();
    assert_eq!(refused.len(), 4, "{text}");
    assert!(refused.iter().all(|l| l.contains("fourier")));
}

/// One pipeline row set on a scene file's effects: (thickness 40, half-space data,
/// normal load, one realisation).
fn pipeline_rows(base: &str, sets: &[&str]) -> ModelErrorResult {
    let camera = CameraEffects::from_scene_text(base, Path::new("base.toml")).unwrap();
    let options = ModelErrorOptions {
        thicknesses_mm: vec![40.0],
        physics: vec![ModelKind::HalfSpace],
        solver_models: vec![ModelKind::HalfSpace],
        loads: vec![LoadKind::Normal],
        effects: sets.iter().map(|s| s.parse().unwrap()).collect(),
        reps: 1,
        realisations: 1,
        ..ModelErrorOptions::default()
    };
    run_model_error(&paper_sensor(), &camera, &options, &mut |_| {}).unwrap()
}

#[test]
fn effects_come_from_the_scene_file_and_an_unlisted_effect_has_no_influence() {
    let quiet = "[[effects]]\nkind = \"quantize8\"\n";
    let noisy = "pixel_filter = \"area\"\n[[effects]]\nkind = \"pixel_noise\"\nsigma_8bit = 6.0\nseed = 3\n\n[[effects]]\nkind = \"quantize8\"\n";
    let a = pipeline_rows(quiet, &["quantize8"]);
    let b = pipeline_rows(noisy, &["quantize8", "pixel_noise+quantize8"]);
    let row = |r: &ModelErrorResult, e: &str| {
        r.rows
            .iter()
            .find(|x| x.effects == e)
            .unwrap_or_else(|| panic!("no row {e}"))
            .clone()
    };
    let (qa, qb, nb) = (
        row(&a, "quantize8"),
        row(&b, "quantize8"),
        row(&b, "pixel_noise+quantize8"),
    );
    for r in [&qa, &qb, &nb] {
        assert!(r.is_ok(), "{:?}", r.status);
        assert_eq!(r.data, DataPath::Pipeline);
        assert!(r.t_track_s.is_some_and(|t| t > 0.0));
        assert!((r.t_frame_s - r.t_solve_s - r.t_track_s.unwrap()).abs() < 1e-12);
    }
    // pixel_noise is in the second file but not in the set: bit-identical results.
    assert_eq!(qa.errors, qb.errors);
    // Listed, it changes the data.
    assert_ne!(qb.errors, nb.errors);
}

/// Column index by name.
fn columns(header: &str) -> HashMap<String, usize> {
    header
        .split(',')
        .enumerate()
        .map(|(i, c)| (c.to_string(), i))
        .collect()
}

#[test]
fn cli_model_error_on_two_thicknesses_writes_csv_plot_and_readme_with_the_known_behaviour() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("me");
    let o = util::run(&[
        "study",
        "model-error",
        "--thickness",
        "3,40",
        "--effects",
        "none,pixel_noise+quantize8",
        "--loads",
        "normal,tangential",
        "--reps",
        "2",
        "--realisations",
        "1",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", util::stderr(&o));
    let err = util::stderr(&o);
    assert!(
        err.contains("[  8/16]") && err.contains("H of the bonded-layer model built"),
        "{err}"
    );
    let csv = std::fs::read_to_string(out.join("model_error.csv")).unwrap();
    let mut lines = csv.lines();
    let header = lines.next().unwrap();
    assert_eq!(header, MODEL_ERROR_COLUMNS.join(","));
    let c = columns(header);
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    // 2 thicknesses × 2 physics × 2 effect sets × 2 loads × 2 solver models.
    assert_eq!(rows.len(), 32);
    let get = |r: &Vec<&str>, name: &str| r[c[name]].to_string();
    let num = |r: &Vec<&str>, name: &str| -> f64 {
        get(r, name)
            .parse()
            .unwrap_or_else(|_| panic!("{name} = {:?} in {r:?}", get(r, name)))
    };
    let always = [
        "thickness_mm",
        "applied_fx_n",
        "applied_fy_n",
        "applied_fz_n",
        "fsum_x_n",
        "fsum_y_n",
        "fsum_z_n",
        "field_error",
        "field_error_x",
        "field_error_y",
        "field_error_z",
        "sum_error",
        "sum_error_x",
        "sum_error_y",
        "sum_error_z",
        "mean_abs_gf",
        "markers_used",
        "markers_total",
        "realisations",
        "t_h_ms",
        "t_precompute_ms",
        "t_build_ms",
        "t_solve_us",
        "t_frame_us",
        "lambda_mm_per_n",
        "condition_number",
    ];
    for r in &rows {
        assert_eq!(get(r, "solver"), "tikhonov");
        assert_eq!(
            get(r, "matched"),
            (get(r, "physics") == get(r, "solver_model")).to_string()
        );
        let pipeline = get(r, "effects") != "none";
        assert_eq!(
            get(r, "data"),
            if pipeline { "pipeline" } else { "forward" }
        );
        if pipeline && get(r, "load") == "tangential" {
            assert_eq!(get(r, "status"), "refused");
            assert!(get(r, "reason").contains("tangential"), "{r:?}");
            assert_eq!(get(r, "field_error"), "");
            continue;
        }
        assert_eq!(get(r, "status"), "ok", "{r:?}");
        for name in always {
            assert!(num(r, name).is_finite(), "{name} in {r:?}");
        }
        assert!(num(r, "t_build_ms") >= num(r, "t_h_ms"));
        if pipeline {
            let t = num(r, "t_track_us");
            assert!(t > 0.0);
            assert!((num(r, "t_frame_us") - t - num(r, "t_solve_us")).abs() < 0.01);
        } else {
            assert_eq!(get(r, "t_track_us"), "");
            assert_eq!(num(r, "t_frame_us"), num(r, "t_solve_us"));
        }
        let depths = get(r, "depths_mm");
        let want = if num(r, "thickness_mm") == 3.0 {
            "0.75;1.5"
        } else {
            "3;6"
        };
        assert_eq!(depths, want);
    }
    // Bonded-layer data, forward path: the matching solver is far better than the
    // half-space one at 3 mm, and the half-space solver's F_sum error falls as the layer
    // thickens towards a half-space.
    let find = |h: &str, model: &str, load: &str| {
        rows.iter()
            .find(|r| {
                get(r, "thickness_mm") == h
                    && get(r, "physics") == "bonded-layer"
                    && get(r, "solver_model") == model
                    && get(r, "effects") == "none"
                    && get(r, "load") == load
            })
            .unwrap()
    };
    for load in ["normal", "tangential"] {
        let (hs3, bl3) = (
            find("3", "half-space", load),
            find("3", "bonded-layer", load),
        );
        for e in ["field_error", "sum_error"] {
            assert!(
                num(bl3, e) < 0.01 * num(hs3, e),
                "{load} {e}: matching {} vs half-space {}",
                num(bl3, e),
                num(hs3, e)
            );
        }
        let hs40 = find("40", "half-space", load);
        assert!(num(hs40, "sum_error") < num(hs3, "sum_error"), "{load}");
    }
    let img = image::open(out.join("model_error.png")).unwrap();
    assert_eq!((img.width(), img.height()), (1500, 700));
    let svg = std::fs::read_to_string(out.join("model_error.svg")).unwrap();
    assert!(svg.contains("half-space solver") && svg.contains("bonded-layer solver"));
    let readme = std::fs::read_to_string(out.join("README.md")).unwrap();
    assert!(
        readme.contains("study model-error --thickness 3,40"),
        "{readme}"
    );
    assert!(readme.contains("| 3 | 0.75 / 1.5 | normal |"), "{readme}");
    assert!(readme.contains("Refused rows (8)"), "{readme}");
    assert!(util::stdout(&o).contains("32 rows, 24 measured, 8 refused"));
}

#[test]
fn cli_model_error_rejects_bad_flags_with_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("me");
    let out = out.to_str().unwrap();
    let missing = dir.path().join("nope.toml");
    let bad_scene = dir.path().join("bad.toml");
    std::fs::write(
        &bad_scene,
        "[[effects]]\nkind = \"pixel_noise\"\nsigma_8bit = -1.0\nseed = 1\n",
    )
    .unwrap();
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (vec!["--thickness", "0"], "--thickness: 0 mm"),
        (vec!["--thickness", "3,3"], "thickness 3 mm is listed twice"),
        (vec!["--thickness", "x"], "invalid value 'x' for '--thickness"),
        (
            vec!["--effects", "none,perspective"],
            "effect `perspective` is not among the scene's [[effects]] (it has: pixel_noise, quantize8)",
        ),
        (vec!["--effects", "none+ideal"], "cannot be combined"),
        (vec!["--loads", "sideways"], "unknown load `sideways`"),
        (vec!["--physics", "plastic"], "unknown model `plastic`"),
        (vec!["--solver", "magic"], "unknown solver `magic`"),
        (vec!["--max-depth-fraction", "2"], "must be in (0, 1]"),
        (vec!["--reps", "0"], "reps = 0"),
        (vec!["--realisations", "0"], "realisations = 0"),
        (vec!["--noise-px", "-1"], "--noise-px: -1 px"),
        (vec!["--lambda", "soft"], "invalid lambda `soft`"),
        (vec!["--refine-iterations", "5"], "applies to the fourier solver only"),
        (vec!["--scene", missing.to_str().unwrap()], "nope.toml: cannot read"),
        (
            vec!["--scene", bad_scene.to_str().unwrap(), "--effects", "pixel_noise"],
            "bad.toml",
        ),
    ];
    for (extra, expected) in cases {
        let mut args = vec!["study", "model-error", "--out", out];
        args.extend_from_slice(&extra);
        let o = util::run(&args);
        assert_eq!(o.status.code(), Some(2), "{extra:?} accepted");
        assert!(
            util::stderr(&o).contains(expected),
            "{extra:?}: {}",
            util::stderr(&o)
        );
    }
    let o = util::run(&["study", "model-error", "--help"]);
    let help = util::stdout(&o);
    for word in [
        "--thickness",
        "--effects",
        "--scene",
        "bonded-layer",
        "refused",
        "build",
        "model_error.csv",
    ] {
        assert!(help.contains(word), "--help lacks {word}: {help}");
    }
}
