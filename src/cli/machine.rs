//! `axiscomp machine new|list|show|attach|detach|export|report`: the whole machine (issue 27).
//! The record and the commissioning plan through the running service's control API
//! (`service::machine` does the work); `export` and `report` read the store themselves, as
//! `axiscomp export` does: every control's files with the stored machine's model, each read
//! back, and the machine acceptance report (`commission::report`).
//!
//! Exit codes: 0 done; 1 the service is unreachable or a file could not be written; 2 the
//! request was refused (a bad record, a run that cannot stand for its set-up, a set-up out of
//! order, no such machine, role) or bad arguments.

use super::InputError;
use super::run::open_store_at;
use anyhow::{Context, Result};
use axiscomp::commission::stored;
use axiscomp::machine::exports;
use axiscomp::service::api::Request;
use axiscomp::service::api::machine::{MachineSummary, MachineView};
use clap::Subcommand;
use std::path::PathBuf;

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Store a machine from its record (TOML: name, chain, travels, tool, the squares'
    /// certificates); prints its commissioning plan.
    New(NewArgs),
    /// The stored machines, newest first, with how far each is measured.
    List(super::table::Common),
    /// A machine's plan set-up by set-up, the squarenesses so far, the model's prediction.
    Show(ShowArgs),
    /// Attach a finished run to a set-up (in the plan's order).
    Attach(AttachArgs),
    /// Detach a set-up's run, and those of the set-ups after it.
    Detach(DetachArgs),
    /// Write every control's files from a stored machine's model (read from the store).
    Export(ExportArgs),
    /// Write the machine acceptance report (HTML, Markdown, PDF) from the store, with every
    /// control's files in OUT/controls.
    Report(ExportArgs),
}

#[derive(clap::Args, Debug)]
pub struct NewArgs {
    #[command(flatten)]
    pub at: super::table::Common,
    /// The machine's record (TOML).
    pub record: PathBuf,
}

#[derive(clap::Args, Debug)]
pub struct ShowArgs {
    #[command(flatten)]
    pub at: super::table::Common,
    /// The machine (default: the newest).
    #[arg(long)]
    pub id: Option<i64>,
}

#[derive(clap::Args, Debug)]
pub struct AttachArgs {
    #[command(flatten)]
    pub at: super::table::Common,
    /// The machine.
    #[arg(long)]
    pub id: i64,
    /// The set-up, 1 to 4 in the plan's order.
    #[arg(long)]
    pub setup: usize,
    /// The finished run that measured it.
    #[arg(long)]
    pub run: i64,
}

#[derive(clap::Args, Debug)]
pub struct DetachArgs {
    #[command(flatten)]
    pub at: super::table::Common,
    /// The machine.
    #[arg(long)]
    pub id: i64,
    /// The set-up, 1 to 4; the set-ups after it are detached too.
    #[arg(long)]
    pub setup: usize,
}

#[derive(clap::Args, Debug)]
pub struct ExportArgs {
    /// The machine.
    #[arg(long)]
    pub id: i64,
    /// The directory the files go to (made when missing).
    #[arg(long)]
    pub out: PathBuf,
    /// The store (default: axiscomp.db in the configured state directory).
    #[arg(long)]
    pub db: Option<PathBuf>,
    /// The configuration (its state directory).
    #[arg(long)]
    pub config: Option<PathBuf>,
}

pub fn run(c: Command) -> Result<()> {
    let (at, req) = match c {
        Command::Export(a) => return export(&a),
        Command::Report(a) => return report(&a),
        Command::New(a) => {
            let text = std::fs::read_to_string(&a.record).map_err(|e| {
                InputError(format!(
                    "{}: cannot read the machine record ({e}); give the path of its TOML file",
                    a.record.display()
                ))
            })?;
            (
                a.at,
                Request::MachineNew {
                    record: text,
                    path: None,
                    origin: Some(a.record.display().to_string()),
                },
            )
        }
        Command::List(at) => (at, Request::Machines),
        Command::Show(a) => (a.at, Request::Machine { id: a.id }),
        Command::Attach(a) => (
            a.at,
            Request::MachineAttach {
                id: a.id,
                setup: a.setup,
                run_id: a.run,
            },
        ),
        Command::Detach(a) => (
            a.at,
            Request::MachineDetach {
                id: a.id,
                setup: a.setup,
            },
        ),
    };
    let v = super::control_request(at.socket.as_deref(), at.config.as_deref(), &req)?;
    super::stdout_closes_quietly();
    if at.json {
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    let parse = |e: serde_json::Error| anyhow::anyhow!("unexpected reply from the service: {e}");
    if let Request::Machines = req {
        let list: Vec<MachineSummary> =
            serde_json::from_value(v["machines"].clone()).map_err(parse)?;
        if list.is_empty() {
            println!("no machine stored: store its record with axiscomp machine new FILE");
        }
        for m in &list {
            println!(
                "machine {} ({}), stored {}: {} of {} set-ups measured{}",
                m.id,
                m.name,
                m.created,
                m.measured,
                m.setups,
                m.next
                    .as_ref()
                    .map(|n| format!("; next: {n}"))
                    .unwrap_or_default()
            );
        }
        return Ok(());
    }
    let view: MachineView = serde_json::from_value(v).map_err(parse)?;
    for line in lines(&view) {
        println!("{line}");
    }
    Ok(())
}

/// A machine's view in words: the plan with each set-up's state, the next set-up's steps,
/// the squarenesses and the model's prediction.
pub fn lines(v: &MachineView) -> Vec<String> {
    let mut out = vec![format!(
        "machine {} ({}): {}, X {:.0} × Y {:.0} × Z {:.0} mm, tool ({:.0}, {:.0}, {:.0}) mm",
        v.id,
        v.name,
        v.chain,
        v.travel_mm[0],
        v.travel_mm[1],
        v.travel_mm[2],
        v.tool_mm[0],
        v.tool_mm[1],
        v.tool_mm[2]
    )];
    for s in &v.setups {
        out.push(format!(
            "  set-up {}: {}",
            s.title,
            match s.run_id {
                Some(r) => format!("measured by run {r}"),
                None => s.state.clone(),
            }
        ));
    }
    if let Some(next) = v.setups.iter().find(|s| s.state == "next") {
        out.push(format!("next, set-up {}:", next.title));
        for (i, step) in next.steps.iter().enumerate() {
            out.push(format!("  {}. {step}", i + 1));
        }
        out.push(format!(
            "  then: axiscomp machine attach --id {} --setup {} --run RUN",
            v.id, next.number
        ));
    }
    for q in &v.squareness {
        out.push(format!(
            "  {} ({}) {:+.2}″ ± {:.2}″ (k = 2), through square {}",
            q.name, q.pair, q.value_arcsec, q.expanded_arcsec, q.square
        ));
    }
    match (&v.predicted, &v.no_model) {
        (Some(p), _) => out.push(format!(
            "the 21-error model: the tool point's error uncompensated {:.1} µm largest (at {:.0}, {:.0}, {:.0} mm), {:.1} µm RMS over {} points; export the controls' files with axiscomp machine export --id {} --out DIR",
            p.max_um, p.at_mm[0], p.at_mm[1], p.at_mm[2], p.rms_um, p.points, v.id
        )),
        (None, Some(why)) => out.push(format!("no model yet: {why}")),
        (None, None) => {}
    }
    out
}

/// `machine export`: the stored machine's model into every control's files, each read back.
fn export(a: &ExportArgs) -> Result<()> {
    let store = open_store_at(a.db.as_ref(), a.config.as_ref())?;
    let state = stored::state(&store, a.id)?;
    let model = state.model().map_err(InputError)?;
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("creating {}; choose another --out", a.out.display()))?;
    let title = format!("axiscomp machine {} ({})", a.id, state.record.name);
    let files = exports::write_and_read_back(model, &a.out, &title, state.record.tool_mm)?;
    super::stdout_closes_quietly();
    println!(
        "machine {} ({}): the 21-error model of runs {} written for each control and read back:",
        a.id,
        state.record.name,
        state.runs_words()
    );
    for f in &files {
        println!("  {}: {} ({})", f.control, f.path.display(), f.carries);
    }
    Ok(())
}

/// `machine report`: the stored machine's acceptance report and every control's files.
fn report(a: &ExportArgs) -> Result<()> {
    let store = open_store_at(a.db.as_ref(), a.config.as_ref())?;
    let written = axiscomp::commission::report::write(
        &store,
        a.id,
        &a.out,
        &a.out.join("controls"),
        axiscomp::util::clock::unix_us(),
    )?;
    super::stdout_closes_quietly();
    println!("machine {}: the acceptance report", a.id);
    for p in &written.report {
        println!("  {}", p.display());
    }
    println!("and each control's files, read back:");
    for e in &written.exports {
        println!("  {}: {} ({})", e.control, e.path.display(), e.carries);
    }
    Ok(())
}
