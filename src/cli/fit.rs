//! `tactbench fit`: identify the sensor model from a characterization run, or predict
//! what a plan can determine (library: [`tactbench::fit`]).

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{bail, Context};
use tactbench::bench::plan::Plan;
use tactbench::fit::fitted_toml::fitted_toml;
use tactbench::fit::identify::{fit_run, FitOptions};
use tactbench::fit::predict::{predict, DeclaredNoise};
use tactbench::fit::{FitDoc, FitError};
use tactbench::report::fit_page::write_fit_page;
use tactbench::sensor::Sensor;
use tactbench::sim::scene::Scene;

/// Default tracking noise of one frame, px (see docs/fit.md for where it comes from).
const DEFAULT_TRACKING_NOISE_PX: f64 = 0.02;
/// Default F/T noise of one sample, N.
const DEFAULT_FT_NOISE_N: f64 = 0.005;

/// Measure the elastomer: identify the sensor model from a characterization run.
///
/// Fits, by nonlinear least squares over every setpoint of RUN_DIR (a run directory of
/// `run` or `import`, live, finished or archived with its displacements), the
/// parameters of the sensor model: young_modulus_kpa (poisson_ratio held unless
/// listed), depth_mm.<layer> for every layer, thickness_mm (bonded-layer model),
/// mm_per_px (or mm_per_px.<layer>), the F/T mounting ft_rotation_deg, the contact
/// offset contact_offset_x_mm / contact_offset_y_mm and the stage z of first contact
/// contact_z_mm.
///
/// Two routes, reported side by side and fitted jointly: the indentation route (stage
/// depth past contact against the F/T normal force through the indenter's contact law:
/// Hertz, flat punch, the bonded layer's own law) and the displacement route (the
/// forward model driven by the measured wrench spread over the contact, against the
/// tracked displacements). Where they disagree beyond their intervals the output says
/// the model does not describe this gel.
///
/// Every fitted value comes with a 95 % interval (from the Jacobian and the residuals,
/// the larger of the classical and the per-setpoint cluster-robust covariance). A
/// parameter the run cannot determine is reported `identifiable: false`, held at its
/// nominal value, with the kind of setpoint that would determine it.
///
/// Writes --out fitted.toml (the sensor file with the fitted values and their
/// intervals as comments; `track`, `run` and `reconstruct` load it unedited), --json
/// fit.json (give RUN_DIR/fit.json for `report --acceptance` to judge fit.<NAME>
/// criteria) and fit.html beside fitted.toml (or --html).
///
/// With --plan PLAN --sensor S.toml --predict: prints, before anything moves, the 95 %
/// interval each parameter can expect from the plan with the declared noise, and the
/// plan's bench time.
///
/// Exit status: 0 fitted (or predicted); 1 the run determines none of the parameters
/// asked (the outputs are written, every parameter held with its reason) or the fit
/// failed numerically; 2 bad input or a run that cannot determine the
/// model (no displacements, no F/T data, one setpoint, unknown parameter, a sensor file
/// that does not match the run), naming the file, key and value.
#[derive(clap::Args)]
#[command(allow_negative_numbers = true)]
pub struct Args {
    /// The run directory to fit.
    #[arg(value_name = "RUN_DIR", required_unless_present = "predict")]
    run_dir: Option<PathBuf>,
    /// The nominal sensor file (default: the sensor embedded in the run's manifest).
    /// Its layers must be the run's.
    #[arg(long, value_name = "S.toml")]
    sensor: Option<PathBuf>,
    /// The parameters to fit, comma-separated (default: every one the run can hold):
    /// young_modulus_kpa, poisson_ratio, thickness_mm, depth_mm.<layer>, mm_per_px,
    /// mm_per_px.<layer>, ft_rotation_deg, contact_offset_x_mm, contact_offset_y_mm,
    /// contact_z_mm.
    #[arg(long, value_name = "LIST")]
    params: Option<String>,
    /// The fitted sensor file to write.
    #[arg(long, value_name = "fitted.toml", required_unless_present = "predict")]
    out: Option<PathBuf>,
    /// Also write fit.json here (RUN_DIR/fit.json lets `report` judge fit.<NAME>).
    #[arg(long, value_name = "fit.json")]
    json: Option<PathBuf>,
    /// Where to write the fit.html page (default: fit.html beside --out).
    #[arg(long, value_name = "fit.html")]
    html: Option<PathBuf>,
    /// Cross-validation folds: one per trial when the run has several, otherwise every
    /// k-th setpoint (0: no cross-validation).
    #[arg(long, default_value_t = 4, value_name = "K")]
    folds: usize,
    /// Predict the intervals a plan can give (needs --plan and --sensor).
    #[arg(long, requires_all = ["plan", "sensor"])]
    predict: bool,
    /// The plan to predict for (with --predict).
    #[arg(long, value_name = "PLAN.toml")]
    plan: Option<PathBuf>,
    /// With --predict: take the F/T noise from this scene's [bench] ft_noise.
    #[arg(long, value_name = "SCENE.toml")]
    scene: Option<PathBuf>,
    /// With --predict: tracking noise of one frame, px.
    #[arg(long, value_name = "PX", default_value_t = DEFAULT_TRACKING_NOISE_PX)]
    tracking_noise_px: f64,
    /// With --predict: F/T noise of one sample, N (default 0.005, or the scene's).
    #[arg(long, value_name = "N")]
    ft_noise_n: Option<f64>,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    if args.predict {
        return run_predict(&args);
    }
    let (Some(run_dir), Some(out)) = (args.run_dir.clone(), args.out.clone()) else {
        bail!("fit needs RUN_DIR and --out fitted.toml (or --predict with --plan and --sensor)");
    };
    let opts = FitOptions {
        run_dir: run_dir.clone(),
        sensor: args.sensor.clone(),
        params: args.params.clone(),
        folds: args.folds,
    };
    let mut progress = |s: &str| eprintln!("fit: {s}");
    let outcome = match fit_run(&opts, &mut progress) {
        Ok(o) => o,
        Err(e @ FitError::Numerical(_)) => {
            eprintln!("error: {e}");
            return Ok(ExitCode::from(1));
        }
        Err(e) => return Err(e.into()),
    };
    let date = tactbench::bench::events::rfc3339_now();
    let toml = fitted_toml(
        &outcome.nominal_text,
        &outcome.doc,
        &outcome.nominal,
        &date[..10.min(date.len())],
    )?;
    write(&out, &toml)?;
    if let Some(j) = &args.json {
        let text = serde_json::to_string_pretty(&outcome.doc)?;
        write(j, &(text + "\n"))?;
    }
    let html = args
        .html
        .clone()
        .unwrap_or_else(|| out.parent().unwrap_or(Path::new(".")).join("fit.html"));
    write_fit_page(&outcome.doc, &html).with_context(|| format!("writing {}", html.display()))?;
    print_summary(&outcome.doc, outcome.seconds);
    let determined = outcome.doc.parameters.values().any(|p| p.fitted);
    eprintln!(
        "wrote {} and {}{}",
        out.display(),
        html.display(),
        args.json
            .as_ref()
            .map(|j| format!(" and {}", j.display()))
            .unwrap_or_default()
    );
    if !determined {
        eprintln!(
            "error: this run determines none of the parameters asked (each is held at its nominal value, with what would determine it, in the table above): {} repeats the nominal values",
            out.display()
        );
        return Ok(ExitCode::from(1));
    }
    Ok(ExitCode::SUCCESS)
}

fn write(path: &Path, text: &str) -> anyhow::Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
}

fn print_summary(doc: &FitDoc, seconds: f64) {
    println!(
        "{:<24} {:>12} {:>27} {:>6} {:>12}  route / note",
        "parameter", "value", "95 % interval", "unit", "nominal"
    );
    for (name, p) in &doc.parameters {
        let ci = p
            .ci95
            .map(|[a, b]| format!("[{}, {}]", sig(a), sig(b)))
            .unwrap_or_else(|| "-".into());
        let note = match (&p.reason, p.fitted) {
            (_, true) => format!("{:?}", p.route).to_lowercase(),
            (Some(r), false) if !p.identifiable => format!("NOT IDENTIFIABLE: {r}"),
            (Some(r), false) => r.clone(),
            (None, false) => "held".into(),
        };
        println!(
            "{name:<24} {:>12} {ci:>27} {:>6} {:>12}  {note}",
            sig(p.value),
            p.unit,
            sig(p.nominal)
        );
    }
    if let Some(d) = doc.routes.get("disagreements").and_then(|v| v.as_array()) {
        for m in d {
            println!("routes disagree: {}", m.as_str().unwrap_or_default());
        }
    }
    if let Some(w) = doc
        .routes
        .pointer("/indentation/reason")
        .and_then(|v| v.as_str())
    {
        println!("indentation route: not available: {w}");
    }
    let layers: Vec<String> = doc
        .residual_rms_px
        .iter()
        .map(|(k, v)| format!("{k} {v:.4}"))
        .collect();
    println!("residual RMS per layer (px): {}", layers.join(", "));
    let cv = &doc.cross_validation;
    match (cv.pointer("/rms_error_n/nominal"), cv.pointer("/rms_error_n/fitted")) {
        (Some(a), Some(b)) => println!(
            "cross-validation ({}, {} held-out setpoints): force-sum RMS error {:.4} N with the nominal file, {:.4} N with the fitted one",
            cv["method"].as_str().unwrap_or_default(),
            cv["held_out_setpoints"],
            a.as_f64().unwrap_or(f64::NAN),
            b.as_f64().unwrap_or(f64::NAN)
        ),
        _ => println!("cross-validation: {}", cv.get("reason").and_then(|v| v.as_str()).unwrap_or("not made")),
    }
    println!("fit took {seconds:.2} s");
}

fn sig(v: f64) -> String {
    if v == 0.0 || (v.abs() >= 1e-3 && v.abs() < 1e5) {
        format!("{v:.5}")
            .trim_end_matches('0')
            .trim_end_matches('.')
            .to_string()
    } else {
        format!("{v:.4e}")
    }
}

fn run_predict(args: &Args) -> anyhow::Result<ExitCode> {
    let (Some(plan_path), Some(sensor_path)) = (&args.plan, &args.sensor) else {
        bail!("--predict needs --plan PLAN.toml and --sensor S.toml");
    };
    let plan = Plan::from_path(plan_path)?;
    let sensor = Sensor::from_path(sensor_path)?;
    let scene_ft = match &args.scene {
        Some(s) => {
            let scene = Scene::from_path(s)?;
            scene.bench.ft_noise.map(|n| n.sigma_n)
        }
        None => None,
    };
    let ft = args.ft_noise_n.or(scene_ft).unwrap_or(DEFAULT_FT_NOISE_N);
    let noise = DeclaredNoise {
        tracking_px: args.tracking_noise_px,
        ft_n: ft,
    };
    let p = predict(&plan, &sensor, noise, args.params.as_deref())?;
    println!(
        "plan {}: {} loaded of {} setpoints, estimated bench time {:.0} s; noise per frame {} px, per F/T sample {} N (of the means: {:.4} px, {:.2e} N)",
        plan_path.display(),
        p.setpoints,
        p.plan_setpoints,
        p.bench_time_s,
        args.tracking_noise_px,
        ft,
        p.noise_of_mean.0,
        p.noise_of_mean.1
    );
    if let Some(w) = &p.no_indentation {
        println!("indentation route: not available: {w}");
    }
    println!(
        "{:<24} {:>12} {:>16} {:>6}  note",
        "parameter", "nominal", "expected 95 % +/-", "unit"
    );
    for e in &p.params {
        let hw = if e.half_width.is_finite() {
            sig(e.half_width)
        } else {
            "unbounded".into()
        };
        let note = match e.needs {
            Some(n) => format!("NOT IDENTIFIABLE from this plan: needs {n}"),
            None => String::new(),
        };
        println!(
            "{:<24} {:>12} {:>16} {:>6}  {note}",
            e.name,
            sig(e.nominal),
            hw,
            e.unit
        );
    }
    if let Some(j) = &args.json {
        write(j, &(serde_json::to_string_pretty(&p.to_json())? + "\n"))?;
    }
    Ok(ExitCode::SUCCESS)
}
