//! `tactbench reconstruct`: displacements CSV -> forces CSV.

use std::collections::HashMap;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, Context, Result};

use tactbench::formats::{self, DisplacementFrame};
use tactbench::model::MarkerSite;
use tactbench::sensor::Sensor;
use tactbench::solve::{self, fmt_num, FrameSolver, Problem, SolverConfig};

use super::SolverArgs;

/// Reconstruct surface force vectors from marker displacements.
///
/// Reads the sensor file and a displacement CSV (`layer,marker,x_mm,y_mm,ux_mm,uy_mm`,
/// extra columns allowed; a `frame` column groups rows into frames), solves `u = H f`
/// for the forces on the sensor's force grid and writes `ix,iy,x_mm,y_mm,fx_n,fy_n,fz_n`
/// (then `sfx_n,sfy_n,sfz_n` with --uncertainty, then `frame` when there are several
/// frames). Displacements in mm, forces in N, fz > 0 pressing into the elastomer. Lost
/// markers (empty or NaN displacement) are dropped from the system and counted on
/// stderr.
///
/// Multi-frame files: a frame whose displacements are all exactly zero (e.g. the
/// unloaded reference) gives zero force; a frame whose markers are all lost gives NaN
/// forces (a flagged row, warned on stderr); the file goes on either way. A file in
/// which no frame has a usable marker is an error (exit 2, no output file) naming the
/// lost markers.
///
/// Drafts: a sensor file with `draft = true` and placeholders left (`sensor init`) is
/// refused (exit 2, the placeholders listed) unless --allow-draft, which names them
/// on stderr before and after the solve.
///
/// Plausibility: no F/T reading here, so each frame's force field is bounded by what
/// the elastomer can carry, E × the force grid's area (`nx·ny·pitch²`): a frame whose
/// total load Σ|f| exceeds it (an automatic λ far too small, a unit slip) is written as
/// NaN rows and named on stderr with the bound and the λ used, and the command exits 1
/// (the other frames are written as usual).
///
/// Exit status: 0 written; 1 written, but a frame's forces were past the elastomer
/// bound (its rows NaN); 2 on errors (nothing written).
#[derive(clap::Args)]
#[command(
    allow_negative_numbers = true,
    after_long_help = "Examples:\n  tactbench reconstruct --sensor experiments/paper_sensor.toml \\\n      --displacements experiments/examples/fig6_displacements.csv --out forces.csv\n  tactbench reconstruct --sensor S.toml --displacements D.csv --solver tikhonov --lambda gcv --out F.csv\n  tactbench reconstruct --sensor S.toml --displacements D.csv --solver tikhonov --uncertainty --noise-px 0.1 --out F.csv"
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
    /// Where automatic lambda (tikhonov / fourier with gcv or lcurve) and the automatic
    /// tsvd rank are chosen: `file` (default) chooses once per set of present markers,
    /// on the first frame of the file with that set whose displacements are not all
    /// zero, and keeps it for every frame of the set (cheap: one decomposition per
    /// set; forces of different frames are comparable); `frame` chooses on every frame
    /// (one decomposition per frame). An error with pinv or a fixed lambda / rank.
    #[arg(long, value_enum, value_name = "file|frame")]
    lambda_per: Option<LambdaPer>,
    /// Also write the standard deviation of every force component (`sfx_n, sfy_n,
    /// sfz_n`, N) for independent displacement noise of --noise-px per value, and
    /// print the standard deviation of F_sum on stderr.
    #[arg(long, requires = "noise_px")]
    uncertainty: bool,
    /// Displacement noise (standard deviation per ux / uy value) in camera pixels,
    /// converted to mm with the sensor's [camera] mm_per_px. Needs --uncertainty.
    #[arg(long, value_name = "PX", requires = "uncertainty")]
    noise_px: Option<f64>,
    /// Compute with a draft sensor file's placeholder values (`sensor init`): its
    /// placeholders are printed on stderr before and after, the forces are not
    /// measurements.
    #[arg(long)]
    allow_draft: bool,
}

/// `--lambda-per`.
#[derive(Clone, Copy, PartialEq, Eq, Debug, clap::ValueEnum)]
enum LambdaPer {
    /// Once per marker set, on its first loaded frame.
    File,
    /// On every frame.
    Frame,
}

/// A solver per set of present markers: `(layer, marker id, present)` per row.
type MarkerKey = Vec<(usize, u64, bool)>;

fn marker_key(frame: &DisplacementFrame) -> MarkerKey {
    frame
        .records
        .iter()
        .map(|r| (r.layer, r.marker, r.u_mm.is_some()))
        .collect()
}

/// Runs `tactbench reconstruct`: the inputs checked ([`check_inputs`]), each frame
/// reconstructed in turn ([`reconstruct_frame`]), the forces written, the frames past
/// the elastomer's bound named (exit 1).
pub fn run(args: Args) -> Result<ExitCode> {
    let sensor = Sensor::from_path(&args.sensor)?;
    let draft = match sensor.draft_warning(&args.sensor) {
        Some(w) if args.allow_draft => {
            eprintln!("reconstruct: warning: {w}");
            Some(w)
        }
        _ => {
            sensor.refuse_draft(&args.sensor)?;
            None
        }
    };
    let frames = formats::read_displacements(&args.displacements, &sensor)?;
    // No usable marker in any frame: an error (exit 2, no output file), not a file of
    // NaN rows.
    formats::require_usable_marker(&frames, &sensor, &args.displacements)?;
    let (config, per, sigma_mm) = check_inputs(&args, &sensor)?;
    let ctx = Ctx {
        sensor: &sensor,
        config: &config,
        frames: &frames,
        per,
        sigma_mm,
        keys: frames.iter().map(marker_key).collect(),
        zero: frames
            .iter()
            .map(|f| f.u_mm().iter().all(|&v| v == 0.0))
            .collect(),
        what: if config.method == solve::Method::Tsvd {
            "rank"
        } else {
            "lambda"
        },
        n_out: 3 * sensor.force_grid.len(),
        // No F/T reading: the elastomer's load bound is the plausibility gate.
        max_load: sensor.max_load_n(),
    };
    // `file`: one precompute per distinct set of present markers, parameters chosen on
    // the set's first loaded frame. `frame`: one precompute per frame.
    let mut cache: HashMap<MarkerKey, Box<dyn FrameSolver>> = HashMap::new();
    let mut out = Outputs {
        forces: Vec::with_capacity(frames.len()),
        sds: Vec::with_capacity(frames.len()),
        implausible: Vec::new(),
        reported: false,
    };
    for i in 0..frames.len() {
        reconstruct_frame(&ctx, i, &mut cache, &mut out)?;
    }
    let outputs = out.forces;
    if sigma_mm.is_some() {
        formats::write_forces_sd(&args.out, &sensor.force_grid, &outputs, &out.sds)?;
    } else {
        formats::write_forces(&args.out, &sensor.force_grid, &outputs)?;
    }
    eprintln!(
        "reconstruct: wrote {} force points x {} frame(s) to {}",
        sensor.force_grid.len(),
        outputs.len(),
        args.out.display()
    );
    if let Some(w) = &draft {
        eprintln!("reconstruct: warning: {w}");
    }
    let implausible = out.implausible;
    if implausible.is_empty() {
        return Ok(ExitCode::SUCCESS);
    }
    eprintln!(
        "reconstruct: {} of {} frame(s) past the elastomer's load bound of {} N, written as NaN: {}",
        implausible.len(),
        outputs.len(),
        fmt_num(ctx.max_load),
        implausible.join(", ")
    );
    Ok(ExitCode::from(1))
}

/// The solver configuration, how automatic parameters are chosen (`--lambda-per`,
/// refused where nothing is chosen from the data) and the displacement noise σ in mm
/// for `--uncertainty` (said on stderr).
fn check_inputs(args: &Args, sensor: &Sensor) -> Result<(SolverConfig, LambdaPer, Option<f64>)> {
    let config = args.solver.config().map_err(anyhow::Error::msg)?;
    if let Some(per) = args.lambda_per {
        if !config.needs_frame() {
            bail!(
                "--lambda-per {} does not apply to the {} solver with {}: only an automatic lambda (gcv, lcurve) or an automatic tsvd rank is chosen from the data",
                if per == LambdaPer::File { "file" } else { "frame" },
                config.method,
                match config.method {
                    solve::Method::Pinv => "its fixed cut-off",
                    solve::Method::Tsvd => "a fixed --rank",
                    _ => "a fixed --lambda",
                }
            );
        }
    }
    let per = args.lambda_per.unwrap_or(LambdaPer::File);
    let sigma_mm = match (args.uncertainty, args.noise_px) {
        (true, Some(px)) => {
            if !(px.is_finite() && px >= 0.0) {
                bail!(
                    "--noise-px {}: the displacement noise must be a finite number >= 0 px",
                    fmt_num(px)
                );
            }
            let mm = solve::noise_px_to_mm(sensor, px);
            eprintln!(
                "reconstruct: displacement noise {} px = {} mm (mm_per_px {}) per ux / uy value",
                fmt_num(px),
                fmt_num(mm),
                fmt_num(sensor.camera.mm_per_px)
            );
            Some(mm)
        }
        _ => None,
    };
    Ok((config, per, sigma_mm))
}

/// What every frame's reconstruction reads.
struct Ctx<'a> {
    sensor: &'a Sensor,
    config: &'a SolverConfig,
    frames: &'a [DisplacementFrame],
    per: LambdaPer,
    /// Displacement noise, mm, with `--uncertainty`.
    sigma_mm: Option<f64>,
    /// Each frame's set of present markers.
    keys: Vec<MarkerKey>,
    /// Whether each frame's displacements are all exactly zero.
    zero: Vec<bool>,
    /// What automatic parameter is chosen: `rank` or `lambda`.
    what: &'static str,
    /// Force values per frame (3 per force point).
    n_out: usize,
    /// The elastomer's load bound, N.
    max_load: f64,
}

/// What the frames give: forces per frame (labelled), their SDs with
/// `--uncertainty`, the frames past the load bound, whether the diagnostics were
/// reported in full yet.
struct Outputs {
    forces: Vec<(String, Vec<f64>)>,
    sds: Vec<Vec<f64>>,
    implausible: Vec<String>,
    reported: bool,
}

/// Reconstructs frame `i` into `out`: NaN when all its markers are lost, zero when
/// it and every frame that could choose its parameters are unloaded, NaN when its
/// force field is past the elastomer's bound; its SDs with `--uncertainty`.
fn reconstruct_frame(
    ctx: &Ctx<'_>,
    i: usize,
    cache: &mut HashMap<MarkerKey, Box<dyn FrameSolver>>,
    out: &mut Outputs,
) -> Result<()> {
    let (frame, n_out) = (&ctx.frames[i], ctx.n_out);
    let label = if frame.frame.is_empty() {
        String::new()
    } else {
        format!(" (frame {})", frame.frame)
    };
    report_lost(frame, ctx.sensor, &label);
    let sites = frame.sites(ctx.sensor);
    if sites.is_empty() {
        eprintln!(
            "reconstruct: warning: all {} markers lost{label}: no force can be reconstructed, its rows are written as NaN",
            frame.records.len()
        );
        out.forces
            .push((frame.frame.clone(), vec![f64::NAN; n_out]));
        out.sds.push(vec![f64::NAN; n_out]);
        return Ok(());
    }
    let Some(c) = chooser(ctx, i) else {
        eprintln!(
            "reconstruct: note: all displacements are zero{label}: the forces are zero (no loaded frame{} to choose the {} from{})",
            if ctx.per == LambdaPer::File { " with these markers" } else { "" },
            ctx.what,
            if ctx.sigma_mm.is_some() { ", so no uncertainty: sd columns are NaN" } else { "" }
        );
        out.forces.push((frame.frame.clone(), vec![0.0; n_out]));
        out.sds.push(vec![f64::NAN; n_out]);
        return Ok(());
    };
    let mut fresh = None;
    let solver = solver_for(
        ctx,
        i,
        c,
        &sites,
        &label,
        cache,
        &mut fresh,
        &mut out.reported,
    )?;
    let u = frame.u_mm();
    let mut f = vec![0.0; solver.n_outputs()];
    solver
        .apply(&u, &mut f)
        .with_context(|| format!("reconstruction failed{label}"))?;
    let sum = axis_sums(&f);
    eprintln!(
        "reconstruct: F_sum{label} = ({}, {}, {}) N",
        fmt_num(sum[0]),
        fmt_num(sum[1]),
        fmt_num(sum[2])
    );
    if !within_load_bound(ctx, &**solver, &f, &label) {
        out.implausible.push(if frame.frame.is_empty() {
            "the frame".to_string()
        } else {
            format!("frame {}", frame.frame)
        });
        out.forces
            .push((frame.frame.clone(), vec![f64::NAN; n_out]));
        if ctx.sigma_mm.is_some() {
            out.sds.push(vec![f64::NAN; n_out]);
        }
        return Ok(());
    }
    if let Some(s) = ctx.sigma_mm {
        out.sds.push(force_sd(&**solver, s, &label)?);
    }
    out.forces.push((frame.frame.clone(), f));
    Ok(())
}

/// The frame that chooses frame `i`'s automatic parameters (any frame of its marker
/// set when none are automatic): its own when loaded (`frame`), else the first
/// loaded frame with its markers (`file`). `None` when there is none.
fn chooser(ctx: &Ctx<'_>, i: usize) -> Option<usize> {
    if !ctx.config.needs_frame() {
        Some(i)
    } else {
        match ctx.per {
            LambdaPer::File => {
                (0..ctx.frames.len()).find(|&j| ctx.keys[j] == ctx.keys[i] && !ctx.zero[j])
            }
            LambdaPer::Frame => (!ctx.zero[i]).then_some(i),
        }
    }
}

/// The solver for frame `i` with parameters chosen on frame `c`: built fresh into
/// `fresh` per frame (`--lambda-per frame` with automatic parameters), else from the
/// cache per marker set, built on first use. Its diagnostics reported as it is built.
#[allow(clippy::too_many_arguments)]
fn solver_for<'a>(
    ctx: &Ctx<'_>,
    i: usize,
    c: usize,
    sites: &[MarkerSite],
    label: &str,
    cache: &'a mut HashMap<MarkerKey, Box<dyn FrameSolver>>,
    fresh: &'a mut Option<Box<dyn FrameSolver>>,
    reported: &mut bool,
) -> Result<&'a mut Box<dyn FrameSolver>> {
    let (config, frames) = (ctx.config, ctx.frames);
    let build = |c: usize| -> Result<Box<dyn FrameSolver>> {
        let problem = Problem::new(ctx.sensor, sites);
        let uc = frames[c].u_mm();
        let chosen_on = if c == i || frames[c].frame.is_empty() {
            String::new()
        } else {
            format!(" ({} chosen on frame {})", ctx.what, frames[c].frame)
        };
        solve::precompute(&problem, config, Some(&uc)).with_context(|| {
            format!(
                "cannot set up the {} solver{label}{chosen_on}",
                config.method
            )
        })
    };
    if ctx.per == LambdaPer::Frame && config.needs_frame() {
        let s = fresh.insert(build(c)?);
        report(s.diagnostics(), config, label, reported);
        return Ok(s);
    }
    Ok(match cache.entry(ctx.keys[i].clone()) {
        std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
        std::collections::hash_map::Entry::Vacant(e) => {
            let s = build(c)?;
            if config.needs_frame() && c != i && !frames[c].frame.is_empty() {
                eprintln!(
                    "reconstruct: {} for this marker set chosen on frame {} (the first with nonzero displacements)",
                    ctx.what, frames[c].frame
                );
            }
            report(s.diagnostics(), config, "", reported);
            e.insert(s)
        }
    })
}

/// Whether the force field `f` stays within the elastomer's load bound; when not,
/// says so on stderr with the bound and the likely cause.
fn within_load_bound(ctx: &Ctx<'_>, solver: &dyn FrameSolver, f: &[f64], label: &str) -> bool {
    let load = total_load(f);
    if !(load.is_nan() || load > ctx.max_load) {
        return true;
    }
    let sum = axis_sums(f);
    let sensor = ctx.sensor;
    eprintln!(
        "reconstruct: error{label}: the force field carries sum |f| = {} N (|F_sum| = {} N), past what the elastomer can carry: E x force-grid area = {} N/mm^2 x {} mm^2 = {} N (docs/limits.md); its rows are written as NaN. Likely {}",
        fmt_num(load),
        fmt_num((sum[0] * sum[0] + sum[1] * sum[1] + sum[2] * sum[2]).sqrt()),
        fmt_num(sensor.elastomer.young_modulus_n_per_mm2()),
        fmt_num(sensor.force_grid_area_mm2()),
        fmt_num(ctx.max_load),
        likely_cause(solver.diagnostics(), ctx.config)
    );
    false
}

/// Per-node force SDs for displacement noise `s` (mm), the SD of the force sums said
/// on stderr.
fn force_sd(solver: &dyn FrameSolver, s: f64, label: &str) -> Result<Vec<f64>> {
    let mut sd = vec![0.0; solver.n_outputs()];
    solver
        .force_sd(s, &mut sd)
        .with_context(|| format!("cannot compute the force uncertainty{label}"))?;
    let ssd = solve::force_sum_sd(solver, s)
        .with_context(|| format!("cannot compute the force uncertainty{label}"))?;
    eprintln!(
        "reconstruct: sd of F_sum{label} = ({}, {}, {}) N",
        fmt_num(ssd[0]),
        fmt_num(ssd[1]),
        fmt_num(ssd[2])
    );
    Ok(sd)
}

/// Σ_nodes |f_node| of an interleaved force vector, N (NaN when any value is).
fn total_load(f: &[f64]) -> f64 {
    f.chunks_exact(3)
        .map(|c| (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt())
        .sum()
}

/// The likely cause of a force field past the elastomer's bound, from how it was
/// solved.
fn likely_cause(d: &solve::Diagnostics, config: &SolverConfig) -> String {
    let edge = d
        .warnings()
        .find(|w| w.contains("boundary") || w.contains("edge"))
        .map(|w| format!(" ({w})"))
        .unwrap_or_default();
    match (d.lambda, config.needs_frame()) {
        (Some(l), true) => format!(
            "the automatically chosen lambda = {l:.3e} mm/N is far too small for this frame{edge}: give a larger --lambda <mm/N>; or the sensor file's units (young_modulus_kpa in kPa, every _mm key in mm) or an unfitted E"
        ),
        (Some(l), false) => format!(
            "lambda = {l:.3e} mm/N is too small for this frame's noise: give a larger --lambda; or the sensor file's units (young_modulus_kpa in kPa, every _mm key in mm) or an unfitted E"
        ),
        (None, _) => format!(
            "the {} solver amplifies this frame's noise (noise gain {:.3e} N/mm): try --solver tikhonov; or the sensor file's units (young_modulus_kpa in kPa, every _mm key in mm) or an unfitted E",
            d.method, d.noise_gain
        ),
    }
}

/// ΣFx, ΣFy, ΣFz of an interleaved force vector.
fn axis_sums(f: &[f64]) -> [f64; 3] {
    let mut s = [0.0; 3];
    for (k, v) in f.iter().enumerate() {
        s[k % 3] += v;
    }
    s
}

/// Counts lost markers per layer on stderr.
fn report_lost(frame: &DisplacementFrame, sensor: &Sensor, label: &str) {
    let lost = frame.lost();
    if lost.is_empty() {
        return;
    }
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

/// The diagnostics of a precompute on stderr: in full the first time, then (per-frame
/// choices) one line with the λ / rank chosen and any warning.
fn report(d: &solve::Diagnostics, config: &SolverConfig, label: &str, reported: &mut bool) {
    if !*reported {
        report_diagnostics(d);
        *reported = true;
        return;
    }
    let mut line = format!("reconstruct: {}{label}:", config.method);
    if let Some(l) = d.lambda {
        line.push_str(&format!(" lambda {l:.3e} mm/N"));
    }
    if let Some(k) = d.rank {
        line.push_str(&format!(" rank {k}"));
    }
    eprintln!("{line}");
    for w in d.warnings() {
        eprintln!("reconstruct: warning{label}: {w}");
    }
}

/// One stderr line on what the precompute found, then its notes (warnings as such).
fn report_diagnostics(d: &solve::Diagnostics) {
    let mut line = format!(
        "reconstruct: {} on a {}x{} system, condition number {:.3e}, effective rank {:.1}, noise gain {:.3e} N/mm",
        d.method,
        d.shape.0,
        d.shape.1,
        d.condition_of_h(),
        d.effective_rank,
        d.noise_gain
    );
    if let Some(l) = d.lambda {
        line.push_str(&format!(", lambda {l:.3e} mm/N"));
    }
    if let Some(k) = d.rank {
        line.push_str(&format!(", rank {k}"));
    }
    eprintln!("{line}");
    for n in &d.notes {
        match n.strip_prefix(solve::WARNING_PREFIX) {
            Some(w) => eprintln!("reconstruct: warning: {w}"),
            None => eprintln!("reconstruct: note: {n}"),
        }
    }
}
