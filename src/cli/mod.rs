//! Subcommands. Each module turns arguments into library calls and prints the result; the
//! measurement logic lives in the library.

mod align;
mod calibrate;
mod client;
mod config;
mod console;
mod decouple;
mod demo;
mod demo_machine;
mod demo_trend;
mod evaluate;
mod export;
mod follower;
mod follower_level;
mod machine;
mod optics;
mod report;
mod run;
mod run_text;
mod service;
mod table;
mod trend;

use anyhow::Result;
use clap::{Parser, Subcommand};
use std::path::{Path, PathBuf};

/// Input the user must fix (exit code 2).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct InputError(pub String);

/// The user pressed Ctrl-C: what was left as it stands, and how to take it up (exit code 130,
/// as a shell reports a command ended by SIGINT).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct Interrupted(pub String);

#[derive(Parser, Debug)]
#[command(
    name = "axiscomp",
    version,
    about = "Six-DOF geometric error measurement and compensation for machine-tool linear axes"
)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// The end-to-end demo on the built-in digital twin.
    Demo(demo::Args),
    /// The optical model: trace poses, print the sensitivity matrix.
    #[command(subcommand)]
    Optics(optics::Command),
    /// Calibrate the head from known poses.
    #[command(subcommand)]
    Calibrate(calibrate::Command),
    /// Decouple PSD readings (CSV on standard input) into the six errors.
    Decouple(decouple::Args),
    /// ISO 230-2 positioning figures from a deviation table (CSV).
    Evaluate(evaluate::Args),
    /// An axis's figures over its stored runs: control limits from its first runs, the drift
    /// alarm, and when each reaches its tolerance.
    Trend(trend::Args),
    /// Run the measurement service (systemd: Type=notify).
    Serve(service::ServeArgs),
    /// Print the running service's live snapshot.
    Status(service::StatusArgs),
    /// The terminal UI over the running service (commissioning and maintenance).
    Console(console::Args),
    /// Check the configuration and every file it names, offline.
    Check(service::ServeArgs),
    /// The configuration's reference and its documented example.
    #[command(subcommand)]
    Config(config::Command),
    /// Run the digital twin (I/O module, follower drive, axis) for the service to measure.
    Sim(service::SimArgs),
    /// ISO 230-2 measurement runs on the running service.
    #[command(subcommand)]
    Run(run::Command),
    /// Write a run's acceptance report (HTML, Markdown, PDF) from the store, optionally
    /// against a second run (before/after).
    Report(report::ReportArgs),
    /// Export a run's compensation table for a controller.
    Export(export::ExportArgs),
    /// Beam alignment on the running service: read the spots at each end of the travel, enter
    /// what a target shows, get the screw turns and the check.
    #[command(subcommand)]
    Align(align::Command),
    /// Compensation tables for the CNC's PLC on the running service: list, generate,
    /// publish, status.
    #[command(subcommand)]
    Table(table::Command),
    /// The follower stage's error map: import its certificate, map it (stop-and-go
    /// self-calibration), show and export the map in use.
    #[command(subcommand)]
    Follower(follower::Command),
    /// The whole machine: its record, the commissioning plan set-up by set-up, the runs that
    /// measured each set-up, the 21-error model and every control's files.
    #[command(subcommand)]
    Machine(machine::Command),
}

/// Let a closed standard output end the process quietly, as it ends `cat` or `grep`
/// (`axiscomp decouple < readings.csv | head`). Rust ignores SIGPIPE, so a write into a closed
/// pipe fails and `println!` panics with a backtrace instead. Only for commands whose last
/// work is printing: the service, the twin and the console keep it ignored (a write into a
/// socket whose peer left must be an error they handle, not the end of the process), and the
/// control-socket clients call this once their request is answered.
pub fn stdout_closes_quietly() {
    // SAFETY: restoring a signal's default action has no memory effects; the CLI installs no
    // SIGPIPE handler of its own.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// One request to the running service's control socket (`socket`, else the configured one);
/// a request the service refused is input to fix (exit code 2).
pub fn control_request(
    socket: Option<&Path>,
    config: Option<&Path>,
    req: &axiscomp::service::api::Request,
) -> Result<serde_json::Value> {
    let socket = client::socket_path(socket, config)?;
    client::runtime()?
        .block_on(async {
            let mut c = axiscomp::service::control::Client::connect(&socket).await?;
            c.request(req).await
        })
        .map_err(client::refused)
}

/// Run a parsed command line.
pub fn run(cli: Cli) -> Result<()> {
    if matches!(
        cli.command,
        Command::Optics(_)
            | Command::Calibrate(_)
            | Command::Decouple(_)
            | Command::Evaluate(_)
            | Command::Trend(_)
            | Command::Check(_)
            | Command::Config(_)
            | Command::Report(_)
            | Command::Export(_)
    ) {
        stdout_closes_quietly();
    }
    match cli.command {
        // The year of checks builds on the demo's set-up: it takes its turn here, so that the
        // demo does not call back into what it serves.
        Command::Demo(a) if a.trend && !a.machine => demo_trend::run(&a),
        Command::Demo(a) => demo::run(a),
        Command::Optics(c) => optics::run(c),
        Command::Calibrate(c) => calibrate::run(c),
        Command::Decouple(a) => decouple::run(a),
        Command::Evaluate(a) => evaluate::run(a),
        Command::Trend(a) => trend::run(a),
        Command::Serve(a) => service::serve(a),
        Command::Status(a) => service::status(a),
        Command::Console(a) => console::run(a),
        Command::Check(a) => service::check(a),
        Command::Config(c) => config::run(c),
        Command::Sim(a) => service::sim(a),
        Command::Run(c) => run::run(c),
        Command::Report(a) => report::report(a),
        Command::Export(a) => export::run(a),
        Command::Table(c) => table::run(c),
        Command::Align(c) => align::run(c),
        Command::Follower(c) => follower::run(c),
        Command::Machine(c) => machine::run(c),
    }
}

/// The error and its causes on one line, each cause once: an error whose message already
/// quotes its cause (`"{pass} run: {source}"`) is not followed by the cause again.
pub fn one_line(e: &anyhow::Error) -> String {
    let mut out = e.to_string();
    for cause in e.chain().skip(1) {
        let c = cause.to_string();
        if !out.contains(&c) {
            out.push_str(": ");
            out.push_str(&c);
        }
    }
    out
}

/// 2 for input the user must fix, 1 for anything else.
pub fn exit_code(e: &anyhow::Error) -> u8 {
    use axiscomp::calibrate::CalError;
    use axiscomp::hexapod::procedure::ProcedureError;
    for cause in e.chain() {
        if cause.is::<Interrupted>()
            || matches!(
                cause.downcast_ref::<ProcedureError>(),
                Some(ProcedureError::Stopped { .. })
            )
        {
            return 130;
        }
        if cause.is::<InputError>()
            || cause.is::<axiscomp::optics::LayoutError>()
            || cause.is::<axiscomp::util::csv::CsvError>()
            || cause.is::<axiscomp::sim::SimError>()
            || cause.is::<axiscomp::evaluate::EvalError>()
            || cause.is::<axiscomp::comp::CompError>()
            || cause.is::<axiscomp::follower::CertificateError>()
        {
            return 2;
        }
        if let Some(c) = cause.downcast_ref::<axiscomp::commission::CommissionError>() {
            use axiscomp::commission::CommissionError as C;
            use axiscomp::store::StoreError;
            return match c {
                C::NoModel(_) | C::Run { .. } | C::Refused { .. } | C::Record(_) => 2,
                C::Store(StoreError::NoSuchMachine(_)) => 2,
                _ => 1,
            };
        }
        if let Some(c) = cause.downcast_ref::<CalError>() {
            return match c {
                CalError::Csv(_)
                | CalError::Input(_)
                | CalError::File { .. }
                | CalError::TooFewPoses { .. }
                | CalError::LowRank { .. } => 2,
                _ => 1,
            };
        }
    }
    1
}

/// The default layout file, relative to the working directory, if present; otherwise the
/// copy compiled into the binary.
pub const DEFAULT_LAYOUT: &str = "configs/optics/reference.toml";

/// Load `--layout FILE`, or the default.
pub fn load_layout(path: Option<&Path>) -> Result<axiscomp::optics::Layout> {
    Ok(match path {
        Some(p) => axiscomp::optics::Layout::load(p)?,
        None => {
            let p = PathBuf::from(DEFAULT_LAYOUT);
            if p.exists() {
                axiscomp::optics::Layout::load(&p)?
            } else {
                axiscomp::optics::Layout::reference()
            }
        }
    })
}

/// Remove the store at `db` with its -wal and -shm files, for a demo that writes a new one.
pub fn remove_store(db: &Path) -> Result<()> {
    use anyhow::Context;
    for suffix in ["", "-wal", "-shm"] {
        let p = PathBuf::from(format!("{}{suffix}", db.display()));
        if p.exists() {
            std::fs::remove_file(&p)
                .with_context(|| format!("replacing {}; remove it by hand", p.display()))?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    #[derive(Debug, thiserror::Error)]
    #[error("the run failed: {0}")]
    struct Outer(#[source] Inner);

    #[derive(Debug, thiserror::Error)]
    #[error("PSD2 lost the spot")]
    struct Inner;

    #[test]
    fn one_line_says_each_cause_once() {
        let e = anyhow::Error::new(Outer(Inner)).context("before run");
        assert_eq!(
            super::one_line(&e),
            "before run: the run failed: PSD2 lost the spot"
        );
        let plain = anyhow::Error::new(Inner).context("demo");
        assert_eq!(super::one_line(&plain), "demo: PSD2 lost the spot");
    }
}

#[cfg(test)]
mod help_tests {
    use super::Cli;
    use clap::CommandFactory;

    /// Every subcommand says what it does and every flag has its help text (`--help` is
    /// what an engineer at the machine reads).
    #[test]
    fn every_command_and_flag_has_help() {
        fn walk(c: &clap::Command, path: &str, missing: &mut Vec<String>) {
            let here = format!("{path} {}", c.get_name());
            if c.get_about().is_none() && !path.is_empty() {
                missing.push(format!("{here}: the command has no help"));
            }
            for a in c.get_arguments() {
                let id = a.get_id().as_str();
                if id == "help" || id == "version" {
                    continue;
                }
                if a.get_help().is_none() && a.get_long_help().is_none() {
                    missing.push(format!("{here} {id}"));
                }
            }
            for s in c.get_subcommands() {
                walk(s, &here, missing);
            }
        }
        let mut missing = Vec::new();
        walk(&Cli::command(), "", &mut missing);
        assert!(
            missing.is_empty(),
            "{} without help:\n{}",
            missing.len(),
            missing.join("\n")
        );
    }
}
