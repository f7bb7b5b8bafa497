//! `axiscomp align read|target|advice|clear`: beam alignment through the running service's
//! control API (`service::align` keeps the stations, `align` does the geometry).
//!
//! The procedure: jog the carriage to the near end of the travel, `align read`; where a PSD
//! shows no spot, read its alignment target and `align target --psd N --x X --y Y`; the same
//! at the far end; `align advice --from-mm A --to-mm B` says which screws to turn by how much
//! and whether every spot stays on its PSD over A..B; turn them, `align clear`, and again until
//! the check passes. Exit codes: 0 done (advice: check passed), 1 the service is unreachable or
//! the check did not pass yet, 2 the request was refused or bad arguments.

use super::table::Common;
use anyhow::Result;
use axiscomp::service::api::Request;
use clap::Subcommand;

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Read the spots as a station, the carriage at rest at --at-mm (default: the measured
    /// position).
    Read(ReadArgs),
    /// What the alignment target in front of a PSD shows at the last station (mm).
    Target(TargetArgs),
    /// The screw turns, the beam's angle to the travel and the check over a span of travel.
    Advice(AdviceArgs),
    /// Forget the stations read (after turning screws).
    Clear(Common),
}

#[derive(clap::Args, Debug)]
pub struct ReadArgs {
    #[command(flatten)]
    pub at: Common,
    /// Where the carriage stands (mm).
    #[arg(long)]
    pub at_mm: Option<f64>,
}

#[derive(clap::Args, Debug)]
pub struct TargetArgs {
    #[command(flatten)]
    pub at: Common,
    /// The PSD (1, 2 or 3).
    #[arg(long)]
    pub psd: usize,
    /// The spot on the target, across (X) and up (Y), mm.
    #[arg(long, allow_negative_numbers = true)]
    pub x: f64,
    /// The spot's height on the target (Y, mm).
    #[arg(long, allow_negative_numbers = true)]
    pub y: f64,
}

#[derive(clap::Args, Debug)]
pub struct AdviceArgs {
    #[command(flatten)]
    pub at: Common,
    /// The travel the spots must stay on their PSDs over (mm).
    #[arg(long, allow_negative_numbers = true)]
    pub from_mm: f64,
    /// The far end of that travel (mm).
    #[arg(long, allow_negative_numbers = true)]
    pub to_mm: f64,
    /// The machine axis the alignment is stored for (the pre-run check of its runs reads it).
    #[arg(long, default_value = "X")]
    pub axis: String,
}

pub fn run(c: Command) -> Result<()> {
    let (at, req) = match c {
        Command::Read(a) => (a.at, Request::AlignRead { at_mm: a.at_mm }),
        Command::Target(a) => (
            a.at,
            Request::AlignTarget {
                psd: a.psd,
                x: a.x,
                y: a.y,
            },
        ),
        Command::Advice(a) => (
            a.at,
            Request::AlignAdvice {
                from_mm: a.from_mm,
                to_mm: a.to_mm,
                axis: Some(a.axis),
            },
        ),
        Command::Clear(a) => (a, Request::AlignClear),
    };
    let v = super::control_request(at.socket.as_deref(), at.config.as_deref(), &req)?;
    super::stdout_closes_quietly();
    if at.json {
        println!("{}", serde_json::to_string_pretty(&v)?);
    }
    match req {
        Request::AlignAdvice { .. } => {
            if !at.json {
                print!("{}", v["text"].as_str().unwrap_or_default());
            }
            if v["passed"].as_bool() == Some(true) {
                Ok(())
            } else {
                Err(anyhow::anyhow!(
                    "the alignment check did not pass: turn the screws as advised, then align clear and read both ends again"
                ))
            }
        }
        Request::AlignClear => {
            if !at.json {
                println!("stations cleared: read both ends again");
            }
            Ok(())
        }
        _ => {
            if !at.json {
                print_station(&v);
            }
            Ok(())
        }
    }
}

fn print_station(v: &serde_json::Value) {
    let at = v["at_mm"].as_f64().unwrap_or(f64::NAN);
    let spots: Vec<String> = (0..3)
        .map(|k| {
            let s = &v["spots"][k];
            match (s["x"].as_f64(), s["y"].as_f64()) {
                (Some(x), Some(y)) => format!(
                    "PSD{} X {x:+.3} mm, Y {y:+.3} mm{}",
                    k + 1,
                    if s["from"] == "target" {
                        " (target)"
                    } else {
                        ""
                    }
                ),
                _ => format!(
                    "PSD{} no spot: read its target and enter it (axiscomp align target --psd {} --x X --y Y)",
                    k + 1,
                    k + 1
                ),
            }
        })
        .collect();
    println!("station at {at:.1} mm: {}", spots.join("; "));
}
