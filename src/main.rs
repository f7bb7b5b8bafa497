//! The `axiscomp` binary: parses the command line and hands over to `cli`. Errors print as one
//! line; bad input exits with 2, other failures with 1.

mod cli;

use clap::Parser;
use std::process::ExitCode;

fn main() -> ExitCode {
    let args = cli::Cli::parse();
    match cli::run(args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("axiscomp: {}", cli::one_line(&e));
            ExitCode::from(cli::exit_code(&e))
        }
    }
}
