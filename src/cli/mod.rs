//! Command-line interface: argument parsing (clap), progress drawing and exit codes.
//! Each subcommand lives in its own file and calls into the library; no logic here
//! that the library lacks.

use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod camera;
mod ft;
mod model;
mod ports;
mod reconstruct;
mod report;
mod reproduce;
mod run;
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
    Reconstruct(reconstruct::Args),
    Report(report::Args),
    ReproducePaper(reproduce::Args),
    Track(track::Args),
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
    /// Simulation studies: accuracy against time, layer separation (paper Fig. 6).
    #[command(subcommand)]
    Study(study::StudyCommand),
}

/// Parses arguments, runs the command, prints the error chain on failure.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Run(args) => run::run(args),
        Command::Reconstruct(args) => reconstruct::run(args),
        Command::Report(args) => report::run(args),
        Command::ReproducePaper(args) => reproduce::run(args),
        Command::Track(args) => track::run(args),
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
            eprintln!("error: {err}");
            for cause in err.chain().skip(1) {
                eprintln!("  caused by: {cause}");
            }
            ExitCode::from(2)
        }
    }
}
