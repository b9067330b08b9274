//! `tactbench model`: inspect the forward model.
use std::process::ExitCode;
#[derive(clap::Subcommand)]
pub enum ModelCommand {
    Inspect,
}
pub fn run(_a: ModelCommand) -> anyhow::Result<ExitCode> {
    Ok(ExitCode::SUCCESS)
}
