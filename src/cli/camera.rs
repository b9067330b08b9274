//! `tactbench camera`: list V4L2 cameras, grab one frame to a PNG from a camera, an
//! image directory (`dir:PATH`) or a simulated bench's camera socket (`sim:PATH`).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;

use tactbench::device::camera::{self, v4l, CameraSpec};

/// Camera commands.
#[derive(clap::Subcommand)]
pub enum CameraCommand {
    /// List V4L2 cameras.
    List,
    /// Grab one frame and save it.
    Grab {
        /// A V4L2 index (0, 1, ...), dir:PATH (a directory of recorded frames) or
        /// sim:PATH (the camera socket of a simulated bench, e.g.
        /// sim:links/camera.sock from `tactbench sim bench --links links`).
        #[arg(long, value_name = "N|dir:PATH|sim:PATH")]
        device: String,
        /// Output image (format from the extension, e.g. .png).
        #[arg(long)]
        out: PathBuf,
    },
}

/// Runs `tactbench camera`.
pub fn run(cmd: CameraCommand) -> anyhow::Result<ExitCode> {
    match cmd {
        CameraCommand::List => {
            let cams = v4l::list()?;
            if cams.is_empty() {
                println!("no V4L2 cameras found (dir:PATH replays recorded frames)");
            }
            for c in cams {
                println!("{}: {} ({})", c.index, c.name, c.description);
            }
        }
        CameraCommand::Grab { device, out } => {
            let spec = CameraSpec::parse(&device)?;
            let mut cam = camera::open(&spec)?;
            let frame = cam.grab()?;
            frame
                .image
                .save(&out)
                .with_context(|| format!("cannot write frame to {}", out.display()))?;
            println!(
                "saved {}x{} frame from {device} to {}",
                frame.image.width(),
                frame.image.height(),
                out.display()
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
