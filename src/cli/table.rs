//! `axiscomp table list|generate|publish|status`: compensation tables through the running
//! service's control API (`service::tables` does the work).
//!
//! Exit codes: 0 done (publish: committed); 1 the service is unreachable, or a publish was
//! rejected by the PLC or failed; 2 the request itself was refused (no such run or table,
//! no confirmation, no PLC configured, role) or bad arguments.

use super::InputError;
use anyhow::Result;
use axiscomp::service::api::Request;
use axiscomp::service::tables::{PublishView, StatusView, TableView};
use clap::Subcommand;
use std::path::PathBuf;

#[derive(Subcommand, Debug)]
pub enum Command {
    /// The stored tables, newest first, with their latest publication.
    List(ListArgs),
    /// Evaluate a stored run and store its compensation tables for the configured CNC map.
    Generate(GenerateArgs),
    /// Publish a stored table to the PLC (needs --confirm).
    Publish(PublishArgs),
    /// What the PLC holds now, read back and compared with the store.
    Status(Common),
}

/// How to reach the service, and the output form.
#[derive(clap::Args, Debug)]
pub struct Common {
    /// The control socket (default: from the configuration).
    #[arg(long)]
    pub socket: Option<PathBuf>,
    /// The service's configuration (default: /etc/axiscomp/axiscomp.toml), for the socket.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Print the service's reply as JSON.
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct ListArgs {
    #[command(flatten)]
    pub at: Common,
    /// At most this many tables.
    #[arg(long, default_value_t = 50)]
    pub limit: usize,
}

#[derive(clap::Args, Debug)]
pub struct GenerateArgs {
    #[command(flatten)]
    pub at: Common,
    /// The stored run (finished) to build the tables from.
    #[arg(long)]
    pub run: i64,
    /// Write the run's residual as the table when the tables the PLC applied while it ran
    /// are not recorded (a run not measured by the service). Published alone, a residual
    /// replaces the table it was measured under.
    #[arg(long)]
    pub residual_only: bool,
}

#[derive(clap::Args, Debug)]
pub struct PublishArgs {
    #[command(flatten)]
    pub at: Common,
    /// The stored table.
    #[arg(long)]
    pub table: i64,
    /// Confirm that the PLC should apply this table from now on.
    #[arg(long)]
    pub confirm: bool,
}

pub fn run(c: Command) -> Result<()> {
    let (at, req) = match c {
        Command::List(a) => (
            a.at,
            Request::TableList {
                limit: Some(a.limit),
            },
        ),
        Command::Generate(a) => (
            a.at,
            Request::TableGenerate {
                run_id: a.run,
                residual_only: a.residual_only,
            },
        ),
        Command::Publish(a) => {
            if !a.confirm {
                return Err(InputError(format!(
                    "table publish changes the compensation the machine applies: check table {} (axiscomp table list) and add --confirm",
                    a.table
                ))
                .into());
            }
            (
                a.at,
                Request::TablePublish {
                    table_id: a.table,
                    confirm: true,
                },
            )
        }
        Command::Status(a) => (a, Request::TableStatus),
    };
    let v = super::control_request(at.socket.as_deref(), at.config.as_deref(), &req)?;
    super::stdout_closes_quietly();
    if at.json {
        println!("{}", serde_json::to_string_pretty(&v)?);
    }
    let parse = |e: serde_json::Error| anyhow::anyhow!("unexpected reply from the service: {e}");
    match req {
        Request::TableList { .. } | Request::TableGenerate { .. } => {
            let tables: Vec<TableView> =
                serde_json::from_value(v["tables"].clone()).map_err(parse)?;
            if !at.json {
                if let Request::TableGenerate { run_id, .. } = req {
                    println!(
                        "run {run_id}: {} table(s) for {}",
                        tables.len(),
                        v["map"].as_str().unwrap_or("?")
                    );
                }
                if tables.is_empty() {
                    println!(
                        "no tables stored: generate them with axiscomp table generate --run ID"
                    );
                }
                for t in &tables {
                    print_table(t);
                }
            }
            Ok(())
        }
        Request::TablePublish { .. } => {
            let p: PublishView = serde_json::from_value(v).map_err(parse)?;
            if !at.json {
                println!(
                    "table {} → {}: {} (sequence {}){}",
                    p.table_id,
                    p.target,
                    p.result,
                    p.sequence,
                    p.code.map(|c| format!(", code {c}")).unwrap_or_default()
                );
                println!("{}", p.message);
                if let Some(w) = &p.not_recorded {
                    println!("WARNING: not recorded in the store: {w}");
                }
            }
            match p.result.as_str() {
                "committed" => Ok(()),
                other => Err(anyhow::anyhow!(
                    "publish {other}: {}{}",
                    p.code.map(|c| format!("code {c}: ")).unwrap_or_default(),
                    p.message
                )),
            }
        }
        _ => {
            let s: StatusView = serde_json::from_value(v).map_err(parse)?;
            if !at.json {
                println!("{}", s.message);
                let ready = if s.plc.ready == 1 {
                    "ready"
                } else {
                    "not ready"
                };
                if s.plc.active_sequence == 0 {
                    println!("PLC: {ready}, empty: no table applied yet ({})", s.source);
                } else {
                    println!(
                        "PLC: {ready}, active sequence {}; last commit: {} sequence {}{} ({})",
                        s.plc.active_sequence,
                        s.plc.status,
                        s.plc.status_sequence,
                        if s.plc.error_code != 0 {
                            format!(", error code {}", s.plc.error_code)
                        } else {
                            String::new()
                        },
                        s.source
                    );
                }
                if !s.active_source.is_empty() {
                    println!("active tables ({}):", s.active_source);
                }
                for a in &s.active {
                    println!(
                        "  {} {} {}: sequence {}, CRC {}, published {}, from run {}{}{}",
                        a.table_id.map_or_else(
                            || "a table not in the store".into(),
                            |i| format!("table {i}")
                        ),
                        a.kind,
                        a.axis,
                        a.sequence,
                        a.crc,
                        a.published_us
                            .map_or_else(|| "(not recorded)".into(), axiscomp::store::iso_utc),
                        a.source_run.map_or_else(|| "-".into(), |r| r.to_string()),
                        if a.read_back { ", read back" } else { "" },
                        if a.composition.starts_with("composed") {
                            format!("; {}", a.composition)
                        } else {
                            String::new()
                        }
                    );
                }
                if let Some(st) = s.staged.as_ref().filter(|st| st.sequence != 0) {
                    println!(
                        "staging area: sequence {}, {} points, CRC {}{}",
                        st.sequence,
                        st.points,
                        st.crc,
                        st.invalid
                            .as_ref()
                            .map(|i| format!(", refused: {i}"))
                            .unwrap_or_default()
                    );
                }
            }
            Ok(())
        }
    }
}

fn print_table(t: &TableView) {
    println!(
        "table {:>3}  {:<4} {:<12} {} on {} {:<13} {:>4} points from {:.3} mm every {:.4} mm, e {:+.2}..{:+.2} µm, CRC {}, run {}{}",
        t.id,
        t.name,
        t.kind,
        t.axis,
        t.base_axis,
        t.direction,
        t.points,
        t.start_mm,
        t.interval_mm,
        t.min_um,
        t.max_um,
        t.crc,
        t.source_run.map(|r| r.to_string()).unwrap_or("-".into()),
        t.last_publication
            .as_ref()
            .map(|p| format!(", last published: {} as sequence {}", p.result, p.sequence))
            .unwrap_or_default()
    );
    if t.composition.starts_with("composed") {
        println!("           {}", t.composition);
    }
}
