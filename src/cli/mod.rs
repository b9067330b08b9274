//! Command-line interface: argument parsing (clap), progress drawing and exit codes.
//! Each subcommand lives in its own file and calls into the library; no logic here
//! that the library lacks.

use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod archive;
mod calibrate;
mod camera;
mod compare;
mod ft;
mod import;
mod model;
mod ports;
mod reconstruct;
mod report;
mod reproduce;
mod run;
mod sensor;
mod serve;
mod signals;
mod sim;
mod solver_args;
mod stage;
mod study;
mod track;

pub use solver_args::SolverArgs;

/// tactbench: test bench controller for vision-based tactile sensors.
///
/// Units everywhere: millimetres, newtons, N/mm² internally; sensor files give the
/// Young's modulus in kPa. Sensor frame: x, y in the surface plane, z into the
/// elastomer; fz > 0 presses into the sensor.
#[derive(Parser)]
#[command(name = "tactbench", version, about, long_about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    Run(run::Args),
    Serve(serve::Args),
    Reconstruct(reconstruct::Args),
    Report(report::Args),
    Compare(compare::Args),
    Archive(archive::Args),
    Import(import::Args),
    ReproducePaper(reproduce::Args),
    Track(track::Args),
    Calibrate(calibrate::Args),
    #[command(subcommand)]
    Sensor(sensor::SensorCommand),
    #[command(subcommand)]
    Model(model::ModelCommand),
    #[command(subcommand)]
    Sim(sim::SimCommand),
    /// List serial ports.
    Ports(ports::Args),
    Stage(stage::Args),
    /// Serve a stage simulator on a pseudo-terminal (test helper).
    #[command(hide = true)]
    SimServeStage(stage::ServeArgs),
    /// Force/torque sensor: read, tare, info.
    Ft(ft::Args),
    /// Cameras: list, grab a frame.
    #[command(subcommand)]
    Camera(camera::CameraCommand),
    /// Serve a force/torque sensor simulator on a pseudo-terminal (test helper).
    #[command(hide = true)]
    SimServeFt(ft::ServeArgs),
    /// Simulation studies: accuracy against time, layer separation (paper Fig. 6),
    /// model error (half-space against a bonded layer).
    #[command(subcommand)]
    Study(study::StudyCommand),
}

/// Parses arguments, runs the command, prints the error chain on failure.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Run(args) => run::run(args),
        Command::Serve(args) => serve::run(args),
        Command::Reconstruct(args) => reconstruct::run(args),
        Command::Report(args) => report::run(args),
        Command::Compare(args) => compare::run(args),
        Command::Archive(args) => archive::run(args),
        Command::Import(args) => import::run(args),
        Command::ReproducePaper(args) => reproduce::run(args),
        Command::Track(args) => track::run(args),
        Command::Calibrate(args) => calibrate::run(args),
        Command::Sensor(cmd) => sensor::run(cmd),
        Command::Model(cmd) => model::run(cmd),
        Command::Sim(cmd) => sim::run(cmd),
        Command::Ports(args) => ports::run(args),
        Command::Stage(args) => stage::run(args),
        Command::SimServeStage(args) => stage::serve(args),
        Command::Ft(args) => ft::run(args),
        Command::Camera(cmd) => camera::run(cmd),
        Command::SimServeFt(args) => ft::serve(args),
        Command::Study(cmd) => study::run(cmd),
    };
    match result {
        Ok(code) => code,
        Err(err) => {
            eprint!("{}", error_report(&err));
            ExitCode::from(2)
        }
    }
}

/// `error: MESSAGE` and one `  caused by: CAUSE` line per cause in the chain, leaving
/// out causes whose text an earlier line already shows (many errors print their
/// source inside their own message, e.g. `{path}: {source}`; `#[error(transparent)]`
/// repeats it verbatim).
fn error_report(err: &anyhow::Error) -> String {
    let mut shown: Vec<String> = Vec::new();
    let mut out = String::new();
    for (i, cause) in err.chain().enumerate() {
        let text = cause.to_string();
        if i > 0 && shown.iter().any(|s| s.contains(&text)) {
            continue;
        }
        if i == 0 {
            out.push_str(&format!("error: {text}\n"));
        } else {
            out.push_str(&format!("  caused by: {text}\n"));
        }
        shown.push(text);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, thiserror::Error)]
    enum Inner {
        #[error("{path}: {source}")]
        Io {
            path: String,
            source: std::io::Error,
        },
    }

    #[derive(Debug, thiserror::Error)]
    enum Outer {
        #[error(transparent)]
        Inner(#[from] Inner),
    }

    #[test]
    fn caused_by_lines_never_repeat_a_message_already_shown() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "No such file");
        let err = anyhow::Error::new(Outer::from(Inner::Io {
            path: "runs/x/manifest.json".into(),
            source: io,
        }))
        .context("cannot resume runs/x");
        let text = error_report(&err);
        assert_eq!(
            text,
            "error: cannot resume runs/x\n  caused by: runs/x/manifest.json: No such file\n"
        );
        let plain = anyhow::anyhow!("root").context("middle").context("top");
        assert_eq!(
            error_report(&plain),
            "error: top\n  caused by: middle\n  caused by: root\n"
        );
    }
}
