//! `axiscomp run start|status|abort` (through the running service), `axiscomp run list` (from
//! the store), and where the store is for `axiscomp report` (`report.rs`) and `axiscomp export`
//! (`export.rs`).

use super::InputError;
use super::run_text;
use anyhow::{Context, Result};
use axiscomp::run::PlanSpec;
use axiscomp::service::api::Request;
use axiscomp::service::control::Client;
use axiscomp::store::Store;
use clap::Subcommand;
use std::path::PathBuf;

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Start an ISO 230-2 run on the running service.
    Start(Box<StartArgs>),
    /// The active (or last) run's progress.
    Status(Where),
    /// Stop the active run (its captures stay stored).
    Abort(Where),
    /// Every stored run with its date, axis, range, plan, notes, operator, calibration, the
    /// tables active while it ran and its state (from the store; no service needed).
    List(ListArgs),
    /// A run's flagged captures (values, why, retaken or excluded) and the events that could
    /// move its reference.
    Flags(FlagsArgs),
    /// Exclude a flagged capture with a reason (audited): it stays out of the run, and no
    /// longer holds the run's tables back.
    Exclude(ExcludeArgs),
}

#[derive(clap::Args, Debug)]
pub struct FlagsArgs {
    #[command(flatten)]
    pub at: Where,
    /// The run.
    #[arg(long)]
    pub run: i64,
}

#[derive(clap::Args, Debug)]
pub struct ExcludeArgs {
    #[command(flatten)]
    pub at: Where,
    /// The run.
    #[arg(long)]
    pub run: i64,
    /// The flag (`run flags` lists them).
    #[arg(long)]
    pub flag: i64,
    /// Why it is excluded (kept with the flag and in the audit log).
    #[arg(long)]
    pub reason: String,
}

#[derive(clap::Args, Debug)]
pub struct ListArgs {
    /// The store (default: axiscomp.db in the configured state directory).
    #[arg(long)]
    pub db: Option<PathBuf>,
    /// The configuration naming the state directory.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// One JSON array of runs instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// How to reach the service.
#[derive(clap::Args, Debug)]
pub struct Where {
    /// The control socket (default: from the configuration).
    #[arg(long)]
    pub socket: Option<PathBuf>,
    /// The service's configuration (default: /etc/axiscomp/axiscomp.toml), for the socket.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Print the service's answer as JSON (the control API's) instead of words.
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct StartArgs {
    #[command(flatten)]
    pub at: Where,
    /// The plan as a TOML file (the fields below); flags override it.
    #[arg(long)]
    pub plan: Option<PathBuf>,
    /// The machine axis: X, Y or Z.
    #[arg(long)]
    pub axis: Option<String>,
    /// The first target (mm).
    #[arg(long)]
    pub start_mm: Option<f64>,
    /// The last target (mm).
    #[arg(long)]
    pub end_mm: Option<f64>,
    /// Targets (ISO 230-2: at least five, and five per metre).
    #[arg(long)]
    pub targets: Option<usize>,
    /// Bidirectional runs (ISO 230-2: five).
    #[arg(long)]
    pub runs: Option<u32>,
    /// How far beyond the end targets the axis reverses (mm).
    #[arg(long)]
    pub overrun_mm: Option<f64>,
    /// Dwell at each target (s).
    #[arg(long)]
    pub dwell_s: Option<f64>,
    /// Feed between targets (mm/min).
    #[arg(long)]
    pub feed_mm_min: Option<f64>,
    /// Ball-screw lead (mm) for non-uniform target spacing; 0 spaces them evenly.
    #[arg(long)]
    pub lead_mm: Option<f64>,
    /// Program dialect: iso, siemens, heidenhain, linuxcnc (default: the configuration's).
    #[arg(long)]
    pub dialect: Option<String>,
    /// Notes kept with the run (why it was measured, the machine's state): `run list` shows
    /// them.
    #[arg(long)]
    pub notes: Option<String>,
}

pub fn run(c: Command) -> Result<()> {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    type Words = fn(&serde_json::Value) -> String;
    let (at, req, words): (Where, Request, Words) = match c {
        Command::Start(a) => {
            let mut spec = match &a.plan {
                Some(p) => {
                    let text = std::fs::read_to_string(p)
                        .map_err(|e| InputError(format!("{}: cannot read it: {e}", p.display())))?;
                    toml::from_str::<PlanSpec>(&text).map_err(|e| {
                        InputError(format!(
                            "{}: {}",
                            p.display(),
                            axiscomp::util::toml_error_line(&text, &e)
                        ))
                    })?
                }
                None => PlanSpec::default(),
            };
            macro_rules! set {
                ($($f:ident),*) => { $( if let Some(v) = a.$f.clone() { spec.$f = v; } )* };
            }
            set!(
                axis,
                start_mm,
                end_mm,
                targets,
                runs,
                overrun_mm,
                dwell_s,
                feed_mm_min,
                lead_mm
            );
            axiscomp::run::Plan::new(spec.clone()).map_err(|e| InputError(e.to_string()))?;
            (
                a.at,
                Request::RunStart {
                    plan: spec,
                    dialect: a.dialect,
                    notes: a.notes,
                },
                run_text::started,
            )
        }
        Command::Status(w) => (w, Request::RunStatus, run_text::status),
        Command::Abort(w) => (w, Request::RunAbort, run_text::aborted),
        Command::Flags(a) => (a.at, Request::RunFlags { run_id: a.run }, run_text::flags),
        Command::Exclude(a) => (
            a.at,
            Request::RunExclude {
                run_id: a.run,
                flag: a.flag,
                reason: a.reason,
            },
            run_text::excluded,
        ),
        Command::List(a) => return list(&a),
    };
    let socket = match at.socket {
        Some(s) => s,
        None => {
            super::service::settings(at.config.as_deref())?
                .service
                .socket
        }
    };
    let v = rt.block_on(async {
        let mut c = Client::connect(&socket).await?;
        c.request(&req).await
    })?;
    super::stdout_closes_quietly();
    if at.json {
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("{}", words(&v));
    }
    Ok(())
}

/// Where the store is.
#[derive(clap::Args, Debug)]
pub struct StoreArgs {
    /// The run.
    #[arg(long)]
    pub run: i64,
    /// The store (default: axiscomp.db in the configured state directory).
    #[arg(long)]
    pub db: Option<PathBuf>,
    /// The configuration (state directory; for reports also the machine and tolerances).
    #[arg(long)]
    pub config: Option<PathBuf>,
}

pub(super) fn open_store(a: &StoreArgs) -> Result<Store> {
    open_store_at(a.db.as_ref(), a.config.as_ref())
}

/// The store at `db`, or in the state directory `config` names, read-only.
pub(super) fn open_store_at(db: Option<&PathBuf>, config: Option<&PathBuf>) -> Result<Store> {
    let path = match db {
        Some(p) => p.clone(),
        None => super::service::settings(config.map(PathBuf::as_path))?
            .service
            .state_dir
            .join("axiscomp.db"),
    };
    if !path.exists() {
        return Err(InputError(format!(
            "{}: no store there; give --db or --config",
            path.display()
        ))
        .into());
    }
    Ok(Store::open_read_only(&path)?)
}

/// `axiscomp run list`.
fn list(a: &ListArgs) -> Result<()> {
    let store = open_store_at(a.db.as_ref(), a.config.as_ref())?;
    let runs = store.run_summaries()?;
    super::stdout_closes_quietly();
    if a.json {
        println!("{}", serde_json::to_string_pretty(&runs)?);
        return Ok(());
    }
    if runs.is_empty() {
        println!("no runs stored: start one with axiscomp run start");
        return Ok(());
    }
    for r in &runs {
        let range = match (r.start_mm, r.end_mm) {
            (Some(a), Some(b)) => format!("{a}..{b} mm"),
            _ => "range unknown".into(),
        };
        println!(
            "run {:<4} {}  {} {}  {}  {} captures  {}",
            r.id, r.date, r.axis, range, r.plan, r.captures, r.state
        );
        let mut who = Vec::new();
        if let Some(o) = &r.operator {
            who.push(format!("operator {o}"));
        }
        who.push(match r.calibration {
            Some(c) => format!("calibration {c}"),
            None => "no stored calibration".into(),
        });
        who.push(format!("tables active: {}", r.tables_active));
        println!("         {}", who.join("; "));
        if !r.notes.is_empty() {
            println!("         notes: {}", r.notes);
        }
    }
    Ok(())
}
