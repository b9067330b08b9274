//! `tactbench study`: simulation studies (library: [`tactbench::analysis`]) —
//! accuracy against time, layer separation (paper Fig. 6), and model error (the
//! half-space against a bonded layer, issue 14).

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use tactbench::analysis::accuracy_time::{
    default_settings, run_study, write_budgets_csv, Metric, StudyEvent, StudyOptions, Sweep,
};
use tactbench::analysis::layer_separation::{
    paper_fig6_load, run_layer_separation, LayerCase, LayerOptions,
};
use tactbench::analysis::model_error::{
    run_model_error, CameraEffects, EffectSet, LoadKind, ModelErrorEvent, ModelErrorOptions,
    RowStatus,
};
use tactbench::report::plot::save_figure;
use tactbench::report::study_plots::{LayerSeparationFigure, ModelErrorFigure, ParetoFigure};
use tactbench::sensor::{paper_sensor, ModelKind, Sensor};
use tactbench::sim::scene::Scene;
use tactbench::solve::{Lambda, Method, SolverConfig};

/// Simulation studies: what accuracy costs in time, and how far apart the marker layers
/// should be.
#[derive(clap::Subcommand)]
pub enum StudyCommand {
    AccuracyVsTime(AccuracyArgs),
    LayerSeparation(LayerArgs),
    ModelError(ModelErrorArgs),
}

/// Measure force error against time per frame for the choices that trade one for the other.
///
/// Renders the scene's full load (its last frame) with the scene's effects, then for
/// each setting tracks the frames, solves for the forces and compares them with the
/// scene's ground truth. Each setting varies one thing around the baseline (the paper's
/// pipeline: pinv, f64, the sensor's force grid, per-window tracking with the measured
/// window and 8 re-centrings, one frame):
///
///   solver:   pinv, tikhonov (gcv, lcurve, lambda = 1e-3/1e-2/1e-1 sigma_max), tsvd
///             (auto, fixed rank), fourier (lcurve, 0/10/30 CGLS refinements; skipped
///             when the grids do not allow it), f32 against f64;
///
///   grid:     force-grid pitch (marker pitch, twice it, 1.5x the sensor's), with pinv,
///             tikhonov gcv and fourier;
///
///   tracking: window aperture 0.6/0.8/1.25x the measured one; 1, 2, 4 re-centrings;
///
///   frames:   N frames (independent seeded noise) tracked and averaged, pinv and tikhonov.
///
/// Errors: `sum` = |sum F - F_applied| / |F_applied| (the total force vector, paper
/// Fig. 7's quantity); `field` = ||f - f*|| / ||f*|| over the force grid (f* = the
/// traction integrated over each node's cell; includes the point-force model error, so
/// it does not reach zero). Time per force frame: tracking N frames + averaging + one
/// solve, wall-clock median over --reps repetitions on this machine; precompute
/// (reference detection + solver set-up, paid once) is reported separately.
///
/// Writes DIR/accuracy_vs_time.csv (one row per setting, both errors, times, pareto
/// flag), DIR/accuracy_vs_time.png and .svg (error against time, log-log, Pareto front
/// in red) and DIR/budgets.csv; prints the fastest setting within each error budget.
/// Settings that cannot run are listed on stderr and left out.
#[derive(clap::Args)]
#[command(
    after_long_help = "Examples:\n  tactbench study accuracy-vs-time --scene experiments/scenes/study_hemisphere_noisy.toml --out study\n  tactbench study accuracy-vs-time --scene experiments/scenes/fig4_flat_910gf.toml --sweeps solver --metric field --budgets 20,30,50"
)]
pub struct AccuracyArgs {
    /// The scene (sensor, indenter, load, effects); its full load is reconstructed.
    #[arg(long, value_name = "S.toml")]
    scene: PathBuf,
    /// Output directory (created if missing; files are overwritten).
    #[arg(long, value_name = "DIR", default_value = "study")]
    out: PathBuf,
    /// Timing repetitions per setting (the median is reported).
    #[arg(long, value_name = "N", default_value_t = 30)]
    reps: usize,
    /// Error used for the Pareto front and the budgets: `sum` or `field` (both are in
    /// the CSV).
    #[arg(long, default_value = "sum", value_parser = parse_metric)]
    metric: Metric,
    /// Error budgets, percent.
    #[arg(
        long,
        value_name = "PCT,...",
        value_delimiter = ',',
        allow_negative_numbers = true,
        default_value = "1,2,5,10,20"
    )]
    budgets: Vec<f64>,
    /// Which sweeps to run: solver, grid, tracking, frames.
    #[arg(long, value_name = "LIST", value_delimiter = ',', default_value = "solver,grid,tracking,frames", value_parser = parse_sweep)]
    sweeps: Vec<Sweep>,
    /// Numbers of frames averaged (frames sweep; 1 is the baseline).
    #[arg(
        long,
        value_name = "N,...",
        value_delimiter = ',',
        default_value = "2,4,8"
    )]
    frames: Vec<usize>,
    /// Independent force frames (noise realisations) each error is averaged over (RMS);
    /// realisation g of an N-frame setting averages loaded frames gN+1..gN+N.
    #[arg(long, value_name = "R", default_value_t = 4)]
    realisations: usize,
}

/// Force error against the distance between the two marker layers (paper Fig. 6).
///
/// For the single first layer, then the second layer at separations d below the first
/// (0 = same depth, i.e. one layer of twice the density), computes the displacements of
/// the paper's Fig. 6 load with the forward model — 100 gf along z and 50 gf along y
/// spread equally over the 4 x 4 force points (4,3)-(7,6) of the 10 x 8 grid, as in
/// experiments/examples/fig6_forces.csv — adds Gaussian noise of each --noise-px level
/// (seeded; --trials draws, averaged; 0 = exact data, one draw) and reconstructs with
/// pinv, tikhonov (gcv, lcurve) and tsvd (auto). The solver and its automatic lambda or
/// rank are set up on the first draw and kept.
///
/// Error: the paper's mean absolute difference between calculated and actual force per
/// axis, averaged over the force points (N per axis in the CSV; the mean over the three
/// axes in gf in the plot), and the relative L2 error.
///
/// Writes DIR/layer_separation.csv and DIR/layer_separation.png and .svg.
#[derive(clap::Args)]
#[command(
    after_long_help = "Examples:\n  tactbench study layer-separation --out study\n  tactbench study layer-separation --sensor experiments/paper_sensor.toml --noise-px 0,0.05,0.1 --trials 50"
)]
pub struct LayerArgs {
    /// Sensor (two layers with marker grids, a force grid of at least 7 x 6 nodes)
    /// [default: the paper's sensor, experiments/paper_sensor.toml].
    #[arg(long, value_name = "S.toml")]
    sensor: Option<PathBuf>,
    /// Output directory (created if missing; files are overwritten).
    #[arg(long, value_name = "DIR", default_value = "study")]
    out: PathBuf,
    /// Layer separations, mm (the single-layer case is always included).
    #[arg(
        long,
        value_name = "MM,...",
        value_delimiter = ',',
        allow_negative_numbers = true,
        default_value = "0,1,2,3,4,5,6,8,13"
    )]
    separations: Vec<f64>,
    /// Displacement noise levels, px (Gaussian sigma per component; the paper: 0.1).
    #[arg(
        long,
        value_name = "PX,...",
        value_delimiter = ',',
        allow_negative_numbers = true,
        default_value = "0,0.1"
    )]
    noise_px: Vec<f64>,
    /// Noise draws per noisy case.
    #[arg(long, value_name = "N", default_value_t = 20)]
    trials: usize,
    /// Seed of the noise.
    #[arg(long, default_value_t = 6)]
    seed: u64,
}

/// What the half-space assumption costs a bonded elastomer layer, per thickness and
/// camera effect, against a solver that models the layer, and what each costs in time.
///
/// For each elastomer thickness h, data is made with each --physics: `bonded-layer`
/// (the layer of thickness h bonded to a rigid plate, what a scene's `[physics] model =
/// "bonded-layer"` renders) and `half-space` (the reference), and the forces are
/// reconstructed by each --solver inverting the half-space (`[elastomer] model =
/// "half-space"`, the paper's) and the bonded layer of the same thickness (`model =
/// "bonded-layer"`). A row is `matched` when the solver's model is the data's.
///
/// Marker depths: the sensor's (the paper's 3 and 6 mm) while the deepest lies within
/// --max-depth-fraction of h, else all scaled so that it does (a 3 mm gel: 0.75 / 1.5 mm).
///
/// Loads: the paper's Fig. 6 load, 100 gf along z and 50 gf along y spread over the 4 x 4
/// force points (4,3)-(7,6): `normal` (its z part), `tangential` (its y part), `mixed`
/// (both, the paper's).
///
/// Camera effects (--effects, one entry per row set): `none` = no camera, the forward
/// model's marker displacements with the load exactly on the force nodes (only model
/// error and regularisation remain); `ideal` = rendered, tracked and solved with no
/// effect; anything else = scene effect kinds joined by `+` (e.g. `pixel_noise+quantize8`,
/// `perspective`, `perspective+refraction`), rendered with those effects, tracked and
/// solved. Each kind's parameters come from the `[[effects]]` tables of --scene (parsed
/// by the scene parser, so every effect a scene accepts works here) or, without
/// --scene, from the built-in Table I camera (pixel_noise sigma 2 levels, quantize8).
/// Rendered rows use the paper's 5 mm flat probe centred on the Fig. 6 patch (100 gf,
/// plus 50 gf along +y for `mixed`; a contact cannot carry a purely tangential load, so
/// those rows are refused), --realisations loaded frames each.
///
/// Errors (relative): field = ||f - f*|| / ||f*|| over nodes and axes (per axis:
/// ||f_a - f*_a|| / ||f*||); F_sum = |sum F - F_applied| / |F_applied| (per axis, signed:
/// (sum F_a - F_applied,a) / |F_applied|); mean |f - f*| in gf (the paper's Fig. 6
/// metric). Times: build = H for the full marker set (cold Hankel tables for the layer) +
/// the solver's precompute; per frame = tracking (rendered rows) + one solve, medians
/// over --reps. A solver that refuses a problem (fourier on grids it cannot represent
/// or, until it learns the layer kernel, on a bonded-layer sensor) gives a row with
/// status `refused` and its reason.
///
/// Writes DIR/model_error.csv (one row per thickness, physics, effects, load, solver
/// model and solver), DIR/model_error.png and .svg (error against thickness on
/// bonded-layer data, half-space solver dashed, matching solver solid, one colour per
/// load) and DIR/README.md (what ran, the headline table, refused rows).
#[derive(clap::Args)]
#[command(
    after_long_help = "Examples:\n  tactbench study model-error --out study/model_error\n  tactbench study model-error --thickness 3,40 --effects none --loads mixed --reps 5 --out /tmp/me\n  # camera effects from a scene file (its [[effects]] tables give the parameters):\n  tactbench study model-error --scene my_camera.toml --effects none,ideal,perspective,perspective+refraction --out study/camera\n  # the Fourier solver next to dense tikhonov (rows it refuses say why):\n  tactbench study model-error --solver tikhonov,fourier --out study/fourier"
)]
pub struct ModelErrorArgs {
    /// Sensor (two marker layers with grids, a force grid of at least 7 x 6 nodes); its
    /// thickness and [elastomer] model are replaced per row [default: the paper's
    /// sensor, experiments/paper_sensor.toml].
    #[arg(long, value_name = "S.toml")]
    sensor: Option<PathBuf>,
    /// Base scene whose [[effects]] tables (and pixel_filter) give the parameters of the
    /// effects named in --effects; its sensor, indenter and load are not used
    /// [default: the Table I camera: pixel_noise (sigma_8bit = 2, seed 7), quantize8].
    #[arg(long, value_name = "SCENE.toml")]
    scene: Option<PathBuf>,
    /// Output directory (created if missing; files are overwritten).
    #[arg(long, value_name = "DIR", default_value = "study")]
    out: PathBuf,
    /// Elastomer thicknesses, mm (distinct, > 0).
    #[arg(
        long,
        alias = "thicknesses",
        value_name = "MM,...",
        value_delimiter = ',',
        allow_negative_numbers = true,
        default_value = "3,5,10,20,40"
    )]
    thickness: Vec<f64>,
    /// Camera-effect sets: `none` (forward model, no camera), `ideal` (rendered, no
    /// effect) or scene effect kinds joined by `+`.
    #[arg(
        long,
        value_name = "SET,...",
        value_delimiter = ',',
        default_value = "none,ideal,pixel_noise+quantize8",
        value_parser = parse_effect_set
    )]
    effects: Vec<EffectSet>,
    /// Loads: normal, tangential, mixed.
    #[arg(long, value_name = "LOAD,...", value_delimiter = ',', default_value = "normal,tangential,mixed", value_parser = parse_load)]
    loads: Vec<LoadKind>,
    /// What the data is made with: bonded-layer, half-space.
    #[arg(long, value_name = "MODEL,...", value_delimiter = ',', default_value = "bonded-layer,half-space", value_parser = parse_model)]
    physics: Vec<ModelKind>,
    /// Solver kinds: pinv, tikhonov, tsvd, fourier (each run with the half-space and
    /// the bonded-layer model).
    #[arg(long, value_name = "SOLVER,...", value_delimiter = ',', default_value = "tikhonov", value_parser = parse_method)]
    solver: Vec<Method>,
    /// Regularisation of tikhonov and fourier: `auto` (gcv for tikhonov, lcurve for
    /// fourier), `gcv`, `lcurve` or a fixed value in mm/N.
    #[arg(long, default_value = "auto")]
    lambda: String,
    /// fourier: CGLS refinement iterations after the two-level solve [default: 0].
    #[arg(long, value_name = "N")]
    refine_iterations: Option<usize>,
    /// The deepest marker lies at most this fraction of the thickness, in (0, 1]
    /// (deeper layers are all scaled by one factor).
    #[arg(long, value_name = "F", default_value_t = 0.5)]
    max_depth_fraction: f64,
    /// Timing repetitions per row (medians reported).
    #[arg(long, value_name = "N", default_value_t = 30)]
    reps: usize,
    /// Loaded frames rendered per rendered data set (errors RMS over them; each draws
    /// its seeded noise from its own stream).
    #[arg(long, value_name = "R", default_value_t = 4)]
    realisations: usize,
    /// Gaussian noise added to the forward (`none`) displacements, px (sigma per
    /// component; 0 = exact data: model error alone).
    #[arg(
        long,
        value_name = "PX",
        default_value_t = 0.0,
        allow_negative_numbers = true
    )]
    noise_px: f64,
    /// Seed of that noise.
    #[arg(long, default_value_t = 14)]
    seed: u64,
}

fn parse_effect_set(s: &str) -> Result<EffectSet, String> {
    s.parse()
}

fn parse_load(s: &str) -> Result<LoadKind, String> {
    s.parse()
}

fn parse_model(s: &str) -> Result<ModelKind, String> {
    ModelKind::from_name(s.trim())
        .ok_or_else(|| format!("unknown model `{s}`: expected bonded-layer or half-space"))
}

fn parse_method(s: &str) -> Result<Method, String> {
    s.parse()
}

fn parse_metric(s: &str) -> Result<Metric, String> {
    s.parse()
}

fn parse_sweep(s: &str) -> Result<Sweep, String> {
    s.parse()
}

pub fn run(cmd: StudyCommand) -> Result<ExitCode> {
    match cmd {
        StudyCommand::AccuracyVsTime(a) => accuracy(a),
        StudyCommand::LayerSeparation(a) => layers(a),
        StudyCommand::ModelError(a) => model_error(a),
    }
}

fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir)
        .with_context(|| format!("cannot create output directory {}", dir.display()))
}

fn accuracy(a: AccuracyArgs) -> Result<ExitCode> {
    if let Some(b) = a.budgets.iter().find(|b| !(b.is_finite() && **b > 0.0)) {
        bail!("--budgets: {b} % is not a positive percentage");
    }
    if let Some(n) = a.frames.iter().find(|n| **n == 0) {
        bail!("--frames: {n} frames averaged: need at least 1");
    }
    let scene = Scene::from_path(&a.scene)?;
    let settings = default_settings(&scene.sensor, &a.sweeps, &a.frames);
    let options = StudyOptions {
        settings,
        reps: a.reps,
        realisations: a.realisations,
    };
    create_dir(&a.out)?;
    let metric = a.metric;
    let result = run_study(&scene, &options, &mut |e| match e {
        StudyEvent::Rendered { frames, seconds } => eprintln!(
            "study: rendered the reference and {frames} loaded frame(s) in {seconds:.2} s"
        ),
        StudyEvent::Prepared {
            index,
            total,
            label,
        } => eprintln!("study: [{:>2}/{total}] {label}: tracked, solved, scored", index + 1),
        StudyEvent::Measured { index, total, row } => eprintln!(
            "study: [{:>2}/{total}] {:<40} sum {:>8.3} %  field {:>8.3} %  {:>9.1} µs/frame (cpu {:.1}; track {:.1}, solve {:.1}), precompute {:.1} ms",
            index + 1,
            row.label,
            row.sum_error * 100.0,
            row.field_error * 100.0,
            row.total_s * 1e6,
            row.total_cpu_s * 1e6,
            row.track_s * 1e6,
            row.solve_s * 1e6,
            row.precompute_s * 1e3
        ),
        StudyEvent::Skipped {
            index,
            total,
            skipped,
        } => eprintln!(
            "study: [{:>2}/{total}] {} skipped: {}",
            index + 1,
            skipped.label,
            // The first clause says why; the rest (alternatives) is in the library error.
            skipped.reason.split("; ").next().unwrap_or_default()
        ),
    })
    .with_context(|| format!("study of {}", a.scene.display()))?;
    if result.rows.is_empty() {
        bail!("no setting could run (see the messages above)");
    }

    let csv = a.out.join("accuracy_vs_time.csv");
    result.write_csv(&csv, metric)?;
    let budgets: Vec<f64> = a.budgets.iter().map(|b| b / 100.0).collect();
    let choices = result.budgets(metric, &budgets);
    let budgets_csv = a.out.join("budgets.csv");
    write_budgets_csv(&budgets_csv, &result, metric, &choices)?;
    let name = scene
        .path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let fig = ParetoFigure::from_result(
        &result,
        metric,
        &budgets,
        &format!("Accuracy against time: {name}"),
    );
    let files = save_figure(&fig, &a.out, "accuracy_vs_time", (1400, 900))?;

    let f = result.applied_n;
    println!(
        "scene {}: applied force ({:.4}, {:.4}, {:.4}) N; {} settings measured, {} skipped; {} timing reps, errors RMS over {} realisations",
        a.scene.display(),
        f[0],
        f[1],
        f[2],
        result.rows.len(),
        result.skipped.len(),
        result.reps,
        result.realisations
    );
    println!("Pareto front ({} error):", metric.name());
    let front = result.pareto(metric);
    let mut on: Vec<usize> = (0..result.rows.len()).filter(|&i| front[i]).collect();
    on.sort_by(|&i, &j| result.rows[i].total_s.total_cmp(&result.rows[j].total_s));
    for i in on {
        let r = &result.rows[i];
        println!(
            "  {:>9.1} µs  {:>8.3} %  {}",
            r.total_s * 1e6,
            r.error(metric) * 100.0,
            r.label
        );
    }
    println!(
        "fastest setting within each {} error budget:",
        metric.name()
    );
    for c in &choices {
        match c.row {
            Some(i) => {
                let r = &result.rows[i];
                println!(
                    "  {:>5} %: {} ({:.3} %, {:.1} µs/frame)",
                    c.budget * 100.0,
                    r.label,
                    r.error(metric) * 100.0,
                    r.total_s * 1e6
                );
            }
            None => println!("  {:>5} %: no setting meets it", c.budget * 100.0),
        }
    }
    println!(
        "wrote {}, {}, {}, {}",
        csv.display(),
        budgets_csv.display(),
        files.png.display(),
        files.svg.display()
    );
    Ok(ExitCode::SUCCESS)
}

fn layers(a: LayerArgs) -> Result<ExitCode> {
    let sensor = match &a.sensor {
        Some(p) => Sensor::from_path(p)?,
        None => paper_sensor(),
    };
    if let Some(d) = a
        .separations
        .iter()
        .find(|d| !(d.is_finite() && **d >= 0.0))
    {
        bail!("--separations: {d} mm must be finite and >= 0");
    }
    let mut cases = vec![LayerCase::SingleLayer];
    cases.extend(a.separations.iter().map(|&d| LayerCase::Separation(d)));
    let options = LayerOptions {
        cases: cases.clone(),
        noise_px: a.noise_px.clone(),
        trials: a.trials,
        seed: a.seed,
        ..LayerOptions::default()
    };
    let load = paper_fig6_load(&sensor.force_grid)?;
    create_dir(&a.out)?;
    let result = run_layer_separation(&sensor, &load, &options, &mut |p| {
        eprintln!("layer separation: {}/{} cases done", p.done, p.total)
    })?;
    for s in &result.skipped {
        eprintln!(
            "layer separation: {} at {}, noise {} px skipped: {}",
            s.solver,
            s.case.label(),
            s.noise_px,
            s.reason
        );
    }
    let csv = a.out.join("layer_separation.csv");
    result
        .write_csv(&csv)
        .with_context(|| format!("cannot write {}", csv.display()))?;
    let note = format!(
        "load: paper Fig. 6, 100 gf z + 50 gf y over force points (4,3)-(7,6); layer 1 at {} mm; {} noise draws per noisy case, seed {}",
        sensor.layers[0].depth_mm, a.trials, a.seed
    );
    let fig = LayerSeparationFigure::from_result(&result, &cases, &note);
    let files = save_figure(&fig, &a.out, "layer_separation", (1400, 650))?;

    println!("mean |f - f*| over force points and axes, gf (paper Fig. 6 metric):");
    let solvers: Vec<String> = {
        let mut v: Vec<String> = Vec::new();
        for r in &result.rows {
            if !v.contains(&r.solver) {
                v.push(r.solver.clone());
            }
        }
        v
    };
    for &noise in &a.noise_px {
        println!("noise {noise} px:");
        print!("  {:<14}", "case");
        for s in &solvers {
            print!(" {s:>16}");
        }
        println!();
        for &c in &cases {
            print!("  {:<14}", c.label());
            for s in &solvers {
                match result.find(c, s, noise) {
                    Some(r) => print!(" {:>16.4e}", r.mean_abs_gf),
                    None => print!(" {:>16}", "-"),
                }
            }
            println!();
        }
    }
    println!(
        "wrote {}, {}, {}",
        csv.display(),
        files.png.display(),
        files.svg.display()
    );
    Ok(ExitCode::SUCCESS)
}

fn model_error(a: ModelErrorArgs) -> Result<ExitCode> {
    let sensor = match &a.sensor {
        Some(p) => Sensor::from_path(p)?,
        None => paper_sensor(),
    };
    let camera = match &a.scene {
        Some(p) => CameraEffects::from_path(p)?,
        None => CameraEffects::default_camera(),
    };
    if let Some(h) = a.thickness.iter().find(|h| !(h.is_finite() && **h > 0.0)) {
        bail!("--thickness: {h} mm must be a finite number > 0");
    }
    if a.noise_px < 0.0 || !a.noise_px.is_finite() {
        bail!("--noise-px: {} px must be a finite number >= 0", a.noise_px);
    }
    let mut solvers = Vec::new();
    for &m in &a.solver {
        let lambda = match (a.lambda.as_str(), m) {
            ("auto", Method::Fourier) => Lambda::LCurve,
            ("auto", _) => Lambda::Gcv,
            (l, _) => l
                .parse()
                .map_err(|e: String| anyhow::anyhow!("--lambda: {e}"))?,
        };
        if a.lambda != "auto" && matches!(m, Method::Pinv | Method::Tsvd) && a.solver.len() == 1 {
            bail!("--lambda does not apply to the {m} solver, which has no regularisation parameter lambda (tikhonov and fourier use it)");
        }
        let mut c = SolverConfig {
            method: m,
            lambda,
            ..SolverConfig::default()
        };
        if let Some(n) = a.refine_iterations {
            if !a.solver.contains(&Method::Fourier) {
                bail!("--refine-iterations applies to the fourier solver only; --solver does not list it");
            }
            c.fourier_refine_iterations = n;
        }
        solvers.push(c);
    }
    let options = ModelErrorOptions {
        thicknesses_mm: a.thickness.clone(),
        physics: a.physics.clone(),
        solvers,
        loads: a.loads.clone(),
        effects: a.effects.clone(),
        max_depth_fraction: a.max_depth_fraction,
        reps: a.reps,
        realisations: a.realisations,
        noise_px: a.noise_px,
        seed: a.seed,
        ..ModelErrorOptions::default()
    };
    create_dir(&a.out)?;
    let result = run_model_error(&sensor, &camera, &options, &mut |e| match e {
        ModelErrorEvent::Operator {
            thickness_mm,
            model,
            seconds,
        } => eprintln!(
            "model error: h = {thickness_mm} mm: H of the {model} model built in {:.1} ms",
            seconds * 1e3
        ),
        ModelErrorEvent::Group { done, total, rows } => {
            let Some(r0) = rows.first() else { return };
            let mut line = format!(
                "model error: [{done:>3}/{total}] h = {} mm, {} data, effects {}, {} load:",
                r0.thickness_mm,
                r0.physics,
                r0.effects,
                r0.load.name()
            );
            for r in rows {
                match &r.status {
                    RowStatus::Ok => line.push_str(&format!(
                        " | {} {}: field {:.3} %, F_sum {:.3} %, build {:.1} ms, {:.1} µs/frame",
                        r.solver_model,
                        r.solver.name(),
                        100.0 * r.errors.field,
                        100.0 * r.errors.sum,
                        r.t_build_s * 1e3,
                        r.t_frame_s * 1e6
                    )),
                    RowStatus::Refused(why) => line.push_str(&format!(
                        " | {} {}: refused ({})",
                        r.solver_model,
                        r.solver.name(),
                        why.split("; ").next().unwrap_or_default()
                    )),
                }
            }
            eprintln!("{line}");
        }
    })?;
    if result.rows.iter().all(|r| !r.is_ok()) {
        bail!("every row was refused (see the messages above): nothing measured");
    }
    let csv = a.out.join("model_error.csv");
    result.write_csv(&csv)?;
    let fig = ModelErrorFigure::from_result(&result);
    let files = save_figure(&fig, &a.out, "model_error", (1500, 700))?;
    let readme = a.out.join("README.md");
    let args: Vec<String> = std::env::args().skip(1).collect();
    let command = format!("tactbench {}", args.join(" "));
    result.write_readme(&readme, &command)?;
    // The headline on stdout: the README's table.
    let text = result.readme(&command);
    for line in text
        .lines()
        .filter(|l| l.starts_with('|') || l.starts_with("## "))
    {
        println!("{line}");
    }
    let refused = result.rows.iter().filter(|r| !r.is_ok()).count();
    println!(
        "{} rows, {} measured, {} refused (reasons in the CSV and README)",
        result.rows.len(),
        result.rows.len() - refused,
        refused
    );
    println!(
        "wrote {}, {}, {}, {}",
        csv.display(),
        files.png.display(),
        files.svg.display(),
        readme.display()
    );
    Ok(ExitCode::SUCCESS)
}
