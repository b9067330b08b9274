//! The `tactbench` command: parse arguments, run, print the error chain, exit code.

use std::process::ExitCode;

mod cli;

fn main() -> ExitCode {
    cli::main()
}
