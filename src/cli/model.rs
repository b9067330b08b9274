//! `tactbench model inspect`: what the forward model and a solver make of a geometry.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;

use tactbench::formats;
use tactbench::model::{self, ForwardModel, MarkerSite};
use tactbench::sensor::Sensor;
use tactbench::solve::{self, Method, Problem, SolverConfig};
use tactbench::units;

use super::SolverArgs;

/// Inspect the forward model (transfer matrix H of paper Eq. 5).
#[derive(clap::Subcommand)]
pub enum ModelCommand {
    /// Print the diagnostics of a sensor geometry and solver: the shape of H, its
    /// singular values (mm/N), condition number, effective rank, noise gain ||P||_2
    /// (N of force error per mm of displacement error) and the force error that 0.1 px
    /// of displacement noise would cause, the regularisation chosen, and whether the
    /// fourier solver can handle the geometry.
    ///
    /// The markers are the layer grids of the sensor file, or the markers present in
    /// the first frame of `--displacements` (which automatic lambda / rank also use).
    #[command(allow_negative_numbers = true)]
    Inspect(InspectArgs),
    /// Compute marker displacements from surface forces with the forward model
    /// (paper Eq. 1, 2, 5, or the bonded layer the sensor file's `[elastomer] model`
    /// selects): reads a forces CSV (`ix,iy,x_mm,y_mm,fx_n,fy_n,fz_n`, N;
    /// the positions are used, so any point set works) and writes a displacement CSV
    /// (`layer,marker,x_mm,y_mm,ux_mm,uy_mm`, mm) for every marker of the sensor's layer
    /// grids. Handy for synthetic data and for checking a solver on known forces.
    Forward(ForwardArgs),
}

/// Arguments of `model forward`.
#[derive(clap::Args)]
pub struct ForwardArgs {
    /// Sensor description (sensor.toml); its layer grids give the markers.
    #[arg(long, value_name = "S.toml")]
    sensor: PathBuf,
    /// Forces CSV (N) at surface points.
    #[arg(long, value_name = "F.csv")]
    forces: PathBuf,
    /// Where to write the displacement CSV (mm).
    #[arg(long, value_name = "D.csv")]
    out: PathBuf,
}

/// Arguments of `model inspect`.
#[derive(clap::Args)]
pub struct InspectArgs {
    /// Sensor description (sensor.toml).
    #[arg(long, value_name = "S.toml")]
    sensor: PathBuf,
    /// Displacement CSV: its first frame defines the marker set (lost markers dropped);
    /// the first frame with those markers and nonzero displacements feeds automatic
    /// lambda / rank selection.
    #[arg(long, value_name = "D.csv")]
    displacements: Option<PathBuf>,
    /// Print every singular value instead of a summary.
    #[arg(long)]
    all: bool,
    /// Print the diagnostics as one JSON object.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    solver: SolverArgs,
}

pub fn run(cmd: ModelCommand) -> Result<ExitCode> {
    match cmd {
        ModelCommand::Inspect(args) => inspect(args),
        ModelCommand::Forward(args) => forward(args),
    }
}

fn forward(args: ForwardArgs) -> Result<ExitCode> {
    let sensor = Sensor::from_path(&args.sensor)?;
    let forces = formats::read_forces_for(&args.forces, &sensor)?;
    let points: Vec<[f64; 2]> = forces.iter().map(|r| r.position_mm).collect();
    let f: Vec<f64> = forces.iter().flat_map(|r| r.f_n).collect();
    // The sensor file's `[elastomer] model` (half-space or bonded layer).
    let model = ForwardModel::from_elastomer(&sensor.elastomer);
    let mut records = Vec::new();
    for (li, layer) in sensor.layers.iter().enumerate() {
        let Some(m) = &layer.markers else { continue };
        let sites: Vec<MarkerSite> = m
            .grid
            .nodes_mm()
            .into_iter()
            .map(|p| MarkerSite {
                layer: li,
                position_mm: p,
                depth_mm: layer.depth_mm,
            })
            .collect();
        let u = model::forward(&model, &sites, &points, &f)?;
        for (k, s) in sites.iter().enumerate() {
            records.push(formats::DisplacementRecord {
                layer: li,
                marker: k as u64,
                position_mm: s.position_mm,
                u_mm: Some([u[2 * k], u[2 * k + 1]]),
                line: 0,
            });
        }
    }
    if records.is_empty() {
        anyhow::bail!(
            "{}: no layer has a [layers.markers] grid",
            args.sensor.display()
        );
    }
    formats::write_displacements(&args.out, &sensor, &records)?;
    eprintln!(
        "model forward: {} force points -> {} markers written to {}",
        points.len(),
        records.len(),
        args.out.display()
    );
    Ok(ExitCode::SUCCESS)
}

fn inspect(args: InspectArgs) -> Result<ExitCode> {
    let sensor = Sensor::from_path(&args.sensor)?;
    let (sites, frame) = inspect_markers(&args, &sensor)?;
    let config = args.solver.config().map_err(anyhow::Error::msg)?;
    let problem = Problem::new(&sensor, &sites);
    let solver = solve::precompute(&problem, &config, frame.as_deref()).map_err(|e| {
        // The hint on automatic parameters only where it is the cause.
        let hint = if matches!(e, solve::SolveError::NeedsFrame(_)) {
            " (automatic lambda / rank needs --displacements, or give --lambda <value> / --rank <k>)"
        } else {
            ""
        };
        anyhow::Error::new(e).context(format!("cannot set up the {} solver{hint}", config.method))
    })?;
    let d = solver.diagnostics();
    let noise_mm = 0.1 * sensor.camera.mm_per_px;
    let fourier = if config.method == Method::Fourier {
        Ok(())
    } else {
        let fconf = SolverConfig {
            method: Method::Fourier,
            lambda: solve::Lambda::Fixed(0.0),
            ..config
        };
        solve::precompute(&problem, &fconf, None).map(|_| ())
    };
    if args.json {
        let v = serde_json::json!({
            "sensor": args.sensor.display().to_string(),
            "markers": sites.len(),
            "force_points": sensor.force_grid.len(),
            "rows": d.shape.0,
            "columns": d.shape.1,
            "solver": d.method.name(),
            "singular_values_mm_per_n": d.singular_values,
            "condition_number": finite_or_null(d.condition_of_h()),
            "effective_rank": d.effective_rank,
            "noise_gain_n_per_mm": d.noise_gain,
            "force_error_per_0_1px_noise_n": d.noise_gain * noise_mm,
            "lambda_mm_per_n": d.lambda,
            "rank": d.rank,
            "notes": d.notes,
            "warnings": d.warnings().collect::<Vec<_>>(),
            "fourier_compatible": fourier.is_ok(),
            "fourier_reason": fourier.as_ref().err().map(|e| e.to_string()),
        });
        println!("{v}");
        return Ok(ExitCode::SUCCESS);
    }
    print_geometry(&args, &sensor, &sites);
    print_diagnostics(d, noise_mm, args.all);
    match fourier {
        Ok(()) => println!("fourier      compatible with this geometry"),
        Err(e) => println!("fourier      not available: {e}"),
    }
    Ok(ExitCode::SUCCESS)
}

/// The marker set `inspect` builds `H` for, and the frame automatic λ / rank choose
/// with: the first frame of `--displacements` with a usable marker, and the first
/// loaded frame with its markers (an unloaded reference often comes first); else the
/// sensor's layer grids and no frame.
fn inspect_markers(
    args: &InspectArgs,
    sensor: &Sensor,
) -> Result<(Vec<MarkerSite>, Option<Vec<f64>>)> {
    let Some(path) = &args.displacements else {
        let sites = MarkerSite::from_sensor_grids(sensor);
        if sites.is_empty() {
            anyhow::bail!(
                "{}: no layer has a [layers.markers] grid; pass --displacements to give marker positions",
                args.sensor.display()
            );
        }
        return Ok((sites, None));
    };
    let frames = formats::read_displacements(path, sensor)?;
    formats::require_usable_marker(&frames, sensor, path)?;
    // The first frame with a usable marker gives the marker set.
    let first = frames
        .iter()
        .find(|f| f.records.iter().any(|r| r.u_mm.is_some()))
        .unwrap_or(&frames[0]);
    // Automatic lambda / rank needs a loaded frame: the first frame whose
    // displacements are not all zero among those with the first frame's markers
    // (an unloaded reference often comes first).
    let present = |f: &formats::DisplacementFrame| {
        f.records
            .iter()
            .map(|r| (r.layer, r.marker, r.u_mm.is_some()))
            .collect::<Vec<_>>()
    };
    let key = present(first);
    let chooser = frames
        .iter()
        .find(|f| present(f) == key && f.u_mm().iter().any(|&v| v != 0.0))
        .unwrap_or(first);
    Ok((first.sites(sensor), Some(chooser.u_mm())))
}

/// The geometry as text: sensor file, elastomer, layers with their marker counts,
/// force grid.
fn print_geometry(args: &InspectArgs, sensor: &Sensor, sites: &[MarkerSite]) {
    let e = &sensor.elastomer;
    println!("sensor       {}", args.sensor.display());
    println!(
        "elastomer    E = {} kPa ({} N/mm²), Poisson ratio {}, thickness {} mm",
        e.young_modulus_kpa,
        e.young_modulus_n_per_mm2(),
        e.poisson_ratio,
        e.thickness_mm
    );
    for (i, l) in sensor.layers.iter().enumerate() {
        let n = sites.iter().filter(|s| s.layer == i).count();
        let grid = l
            .markers
            .map(|m| {
                format!(
                    ", grid {}x{} every {} mm",
                    m.grid.nx, m.grid.ny, m.grid.pitch_mm
                )
            })
            .unwrap_or_default();
        println!(
            "layer        {} ({}) at {} mm: {n} markers{grid}",
            l.name, l.color, l.depth_mm
        );
    }
    let g = &sensor.force_grid;
    println!(
        "force grid   {}x{} every {} mm from ({}, {}) mm",
        g.nx, g.ny, g.pitch_mm, g.origin_mm[0], g.origin_mm[1]
    );
}

/// The solver's diagnostics as text: shape of `H`, singular values (all with
/// `all`), condition, effective rank, noise gain and what `noise_mm` of displacement
/// noise costs, λ / rank, notes and warnings.
fn print_diagnostics(d: &solve::Diagnostics, noise_mm: f64, all: bool) {
    println!(
        "system H     {} x {} (2 per marker x 3 per force point)",
        d.shape.0, d.shape.1
    );
    println!("solver       {}", d.method);
    let sv = &d.singular_values;
    if !sv.is_empty() {
        if all || sv.len() <= 12 {
            println!("singular values (mm/N): {}", fmt_list(sv));
        } else {
            println!(
                "singular values (mm/N): {} ... {} ({} in all; --all lists them)",
                fmt_list(&sv[..5]),
                fmt_list(&sv[sv.len() - 5..]),
                sv.len()
            );
        }
    }
    // κ describes H, whatever the cut-off (--rcond) or regularisation: those change
    // the solution, reported as the rank used / effective rank below.
    println!(
        "condition    {:.4e} (sigma_max / sigma_min of H)",
        d.condition_of_h()
    );
    println!("eff. rank    {:.1}", d.effective_rank);
    println!(
        "noise gain   {:.4e} N/mm: 0.1 px ({} mm) of displacement noise -> up to {:.4e} N ({:.3} gf) per force component",
        d.noise_gain,
        solve::fmt_num(noise_mm),
        d.noise_gain * noise_mm,
        units::n_to_gf(d.noise_gain * noise_mm)
    );
    if let Some(l) = d.lambda {
        println!("lambda       {l:.4e} mm/N");
    }
    if let Some(k) = d.rank {
        println!(
            "rank used    {k} of {} singular values",
            d.singular_values.len()
        );
    }
    for n in &d.notes {
        match n.strip_prefix(solve::WARNING_PREFIX) {
            Some(w) => println!("warning      {w}"),
            None => println!("note         {n}"),
        }
    }
    for w in d.warnings() {
        eprintln!("model inspect: warning: {w}");
    }
}

fn finite_or_null(v: f64) -> serde_json::Value {
    if v.is_finite() {
        serde_json::json!(v)
    } else {
        serde_json::Value::Null
    }
}

fn fmt_list(v: &[f64]) -> String {
    v.iter()
        .map(|x| format!("{x:.4e}"))
        .collect::<Vec<_>>()
        .join(" ")
}
