//! `tactbench sensor init`: a sensor-file draft from one unloaded frame (library:
//! [`tactbench::vision::onboard`]).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, Context};
use clap::Subcommand;
use tactbench::sensor::{MarkerColor, Roi, Sensor};
use tactbench::vision::onboard::{parse_roi_arg, sensor_draft, DraftOptions, Scale};
use tactbench::vision::Frame;

/// Sensor files: write a draft for a new sensor.
#[derive(Subcommand)]
pub enum SensorCommand {
    #[command(allow_negative_numbers = true)]
    Init(InitArgs),
}

/// Write a sensor-file draft from one unloaded frame of a new sensor.
///
/// Finds the markers of the given appearance (--color) inside the ROI (no layout
/// assumed), measures their count, spacing (median nearest neighbour, px), diameter,
/// contrast against the local background and the share whose tracking window crosses
/// the ROI border (tracked as lost), and writes a sensor file that loads as it is:
/// the camera size, the ROI, mm_per_px (from --pitch-mm or --mm-per-px), a
/// [layers.markers] grid when the markers form a square-pitched rectangular grid
/// aligned with the image (else none: the layout is the reference frame's), and a
/// force grid over the markers. What a frame cannot tell (elastomer, marker depth,
/// mm_per_px without a scale) is written as a placeholder marked `# TODO: measure`,
/// and the file starts with `draft = true` and `placeholders = [...]` naming those
/// keys: `track` uses a draft as it is, `reconstruct`, `run` and `report` refuse it
/// until the placeholders are measured (or run with --allow-draft).
///
/// --pitch-mm and --mm-per-px are checked against the sensor file's plausible ranges
/// (docs/limits.md), and the draft is loaded back before it is written: what
/// `sensor init` writes, its own loader reads. An existing --out is not replaced
/// without --force.
///
/// --roi syntax: circle:X,Y,R or rect:X0,Y0,X1,Y1 (pixels, pixel centres at integers).
///
/// Exit status: 0 written; 2 on errors: --out exists (without --force), unreadable
/// frame, invalid --roi (outside the image, zero size) or scale, a blank or saturated
/// frame, no marker of that kind.
#[derive(clap::Args)]
pub struct InitArgs {
    /// The unloaded reference frame.
    #[arg(long, value_name = "REF.png")]
    reference: PathBuf,
    /// The markers' appearance: dark (on a lit gel), bright (on a dark skin), or the
    /// colour of coloured markers.
    #[arg(long, value_enum)]
    color: ColorArg,
    /// Where to look: circle:X,Y,R or rect:X0,Y0,X1,Y1 (px).
    #[arg(long, value_name = "SHAPE", value_parser = roi)]
    roi: Option<Roi>,
    /// The markers' known pitch (centre to centre of neighbours), mm: sets mm_per_px.
    #[arg(long, value_name = "P", conflicts_with = "mm_per_px")]
    pitch_mm: Option<f64>,
    /// The camera's scale, mm per pixel.
    #[arg(long, value_name = "S")]
    mm_per_px: Option<f64>,
    /// Output sensor file (the draft). An existing file is not replaced (it may be a
    /// measured sensor file) unless --force.
    #[arg(long, value_name = "sensor.toml")]
    out: PathBuf,
    /// Replace --out when it exists.
    #[arg(long)]
    force: bool,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum ColorArg {
    Dark,
    Bright,
    Blue,
    Red,
    Green,
}

fn roi(s: &str) -> Result<Roi, String> {
    parse_roi_arg(s)
}

pub fn run(cmd: SensorCommand) -> anyhow::Result<ExitCode> {
    match cmd {
        SensorCommand::Init(args) => init(args),
    }
}

fn init(args: InitArgs) -> anyhow::Result<ExitCode> {
    // Before any work: a measured sensor file is not replaced by a draft unasked.
    if args.out.exists() && !args.force {
        bail!(
            "{} exists: sensor init does not replace a file (it may be a measured sensor file); give another --out, or --force to replace it",
            args.out.display()
        );
    }
    let color = match args.color {
        ColorArg::Dark => MarkerColor::Dark,
        ColorArg::Bright => MarkerColor::Bright,
        ColorArg::Blue => MarkerColor::Blue,
        ColorArg::Red => MarkerColor::Red,
        ColorArg::Green => MarkerColor::Green,
    };
    let scale = match (args.pitch_mm, args.mm_per_px) {
        (Some(p), _) => Scale::PitchMm(p),
        (None, Some(s)) => Scale::MmPerPx(s),
        (None, None) => Scale::Unknown,
    };
    let frame = Frame::open(&args.reference)?;
    let options = DraftOptions {
        color,
        roi_px: args.roi,
        scale,
    };
    let draft = sensor_draft(&frame.view(), &options, &args.reference)?;
    eprintln!("{}: {}", args.reference.display(), draft.summary());
    let text = draft.to_toml(&args.reference.display().to_string());
    // What we write, our loader must read (with the same ranges).
    Sensor::from_toml_str(&text, &args.out)
        .context("the draft does not load with the sensor-file checks; nothing written")?;
    write_out(&args.out, &text, args.force)?;
    eprintln!(
        "-> {} (a draft: placeholders {})",
        args.out.display(),
        draft.placeholders().join(", ")
    );
    Ok(ExitCode::SUCCESS)
}

/// Writes the draft; without `force` only as a new file (never over one created
/// meanwhile).
fn write_out(out: &std::path::Path, text: &str, force: bool) -> anyhow::Result<()> {
    use std::io::Write as _;
    let mut options = std::fs::OpenOptions::new();
    options.write(true);
    if force {
        options.create(true).truncate(true);
    } else {
        options.create_new(true);
    }
    let mut f = options.open(out).with_context(|| {
        if out.exists() && !force {
            format!("{} exists (give --force to replace it)", out.display())
        } else {
            format!("writing {}", out.display())
        }
    })?;
    f.write_all(text.as_bytes())
        .with_context(|| format!("writing {}", out.display()))
}
