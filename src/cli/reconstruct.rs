//! `tactbench reconstruct`: displacements CSV -> forces CSV.
use std::process::ExitCode;
/// Reconstruct surface forces.
#[derive(clap::Args)]
pub struct Args {}
pub fn run(_a: Args) -> anyhow::Result<ExitCode> {
    Ok(ExitCode::SUCCESS)
}
