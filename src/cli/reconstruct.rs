//! `tactbench reconstruct`: displacements CSV -> forces CSV.

use std::collections::HashMap;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};

use tactbench::formats;
use tactbench::sensor::Sensor;
use tactbench::solve::{self, Problem};

use super::SolverArgs;

/// Reconstruct surface force vectors from marker displacements.
///
/// Reads the sensor file and a displacement CSV (`layer,marker,x_mm,y_mm,ux_mm,uy_mm`,
/// extra columns allowed; a `frame` column groups rows into frames), solves `u = H f`
/// for the forces on the sensor's force grid and writes `ix,iy,x_mm,y_mm,fx_n,fy_n,fz_n`
/// (plus `frame` when there are several frames). Displacements in mm, forces in N,
/// fz > 0 pressing into the elastomer. Lost markers (empty or NaN displacement) are
/// dropped from the system and counted on stderr.
#[derive(clap::Args)]
#[command(
    after_long_help = "Examples:\n  tactbench reconstruct --sensor experiments/paper_sensor.toml \\\n      --displacements experiments/examples/fig6_displacements.csv --out forces.csv\n  tactbench reconstruct --sensor S.toml --displacements D.csv --solver tikhonov --lambda gcv --out F.csv"
)]
pub struct Args {
    /// Sensor description (sensor.toml).
    #[arg(long, value_name = "S.toml")]
    sensor: PathBuf,
    /// Displacement CSV (mm), e.g. written by `tactbench track`.
    #[arg(long, value_name = "D.csv")]
    displacements: PathBuf,
    /// Where to write the forces CSV (N).
    #[arg(long, value_name = "F.csv")]
    out: PathBuf,
    #[command(flatten)]
    solver: SolverArgs,
}

pub fn run(args: Args) -> Result<ExitCode> {
    let sensor = Sensor::from_path(&args.sensor)?;
    let frames = formats::read_displacements(&args.displacements, &sensor)?;
    let config = args.solver.config();

    // One precompute per distinct set of present markers: frames that lost the same
    // markers share a solver. Automatic λ / rank is chosen on the first frame of a set.
    let mut cache: HashMap<Vec<bool>, Box<dyn solve::FrameSolver>> = HashMap::new();
    let mut outputs = Vec::with_capacity(frames.len());
    for frame in &frames {
        let label = if frame.frame.is_empty() {
            String::new()
        } else {
            format!(" (frame {})", frame.frame)
        };
        let lost = frame.lost();
        if !lost.is_empty() {
            let mut per_layer = vec![0usize; sensor.layers.len()];
            for (layer, _) in &lost {
                per_layer[*layer] += 1;
            }
            let detail: Vec<String> = per_layer
                .iter()
                .zip(&sensor.layers)
                .filter(|(n, _)| **n > 0)
                .map(|(n, l)| format!("{}: {n}", l.name))
                .collect();
            eprintln!(
                "reconstruct: {} of {} markers lost{label} ({}); their rows were dropped",
                lost.len(),
                frame.records.len(),
                detail.join(", ")
            );
        }
        let sites = frame.sites(&sensor);
        let u = frame.u_mm();
        let key: Vec<bool> = frame.records.iter().map(|r| r.u_mm.is_some()).collect();
        let solver = match cache.entry(key) {
            std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::hash_map::Entry::Vacant(e) => {
                let problem = Problem::new(&sensor, &sites);
                let solver = solve::precompute(&problem, &config, Some(&u)).with_context(|| {
                    format!("cannot set up the {} solver{label}", config.method)
                })?;
                report_diagnostics(solver.diagnostics());
                e.insert(solver)
            }
        };
        let mut f = vec![0.0; solver.n_outputs()];
        solver
            .apply(&u, &mut f)
            .with_context(|| format!("reconstruction failed{label}"))?;
        let sum = (0..3)
            .map(|a| f.iter().skip(a).step_by(3).sum::<f64>())
            .collect::<Vec<_>>();
        eprintln!(
            "reconstruct: F_sum{label} = ({:.6}, {:.6}, {:.6}) N",
            sum[0], sum[1], sum[2]
        );
        outputs.push((frame.frame.clone(), f));
    }
    formats::write_forces(&args.out, &sensor.force_grid, &outputs)?;
    eprintln!(
        "reconstruct: wrote {} force points x {} frame(s) to {}",
        sensor.force_grid.len(),
        outputs.len(),
        args.out.display()
    );
    Ok(ExitCode::SUCCESS)
}

/// One stderr line on what the precompute found.
fn report_diagnostics(d: &solve::Diagnostics) {
    let mut line = format!(
        "reconstruct: {} on a {}x{} system, condition number {:.3e}, effective rank {:.1}, noise gain {:.3e} N/mm",
        d.method, d.shape.0, d.shape.1, d.condition_number, d.effective_rank, d.noise_gain
    );
    if let Some(l) = d.lambda {
        line.push_str(&format!(", lambda {l:.3e} mm/N"));
    }
    if let Some(k) = d.rank {
        line.push_str(&format!(", rank {k}"));
    }
    eprintln!("{line}");
    for n in &d.notes {
        eprintln!("reconstruct: note: {n}");
    }
}
