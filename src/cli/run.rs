//! `axiscomp run start|status|abort` (through the running service), `axiscomp report` and
//! `axiscomp export` (from the store).

use super::InputError;
use anyhow::{Context, Result};
use axiscomp::comp::{self, AxisMapping, MachineAxis, PositioningMode, TableSpec};
use axiscomp::evaluate::iso230_1::ReferenceLine;
use axiscomp::evaluate::{EvalOptions, evaluate_captures};
use axiscomp::report::{RunMeta, write_run_report};
use axiscomp::run::PlanSpec;
use axiscomp::service::control::{Client, Request};
use axiscomp::store::{RunId, Store};
use clap::{Subcommand, ValueEnum};
use std::path::{Path, PathBuf};

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Start an ISO 230-2 run on the running service.
    Start(StartArgs),
    /// The active (or last) run's progress.
    Status(Where),
    /// Stop the active run (its captures stay stored).
    Abort(Where),
}

/// How to reach the service.
#[derive(clap::Args, Debug)]
pub struct Where {
    /// The control socket (default: from the configuration).
    #[arg(long)]
    pub socket: Option<PathBuf>,
    #[arg(long)]
    pub config: Option<PathBuf>,
}

#[derive(clap::Args, Debug)]
pub struct StartArgs {
    #[command(flatten)]
    pub at: Where,
    /// The plan as a TOML file (the fields below); flags override it.
    #[arg(long)]
    pub plan: Option<PathBuf>,
    #[arg(long)]
    pub axis: Option<String>,
    #[arg(long)]
    pub start_mm: Option<f64>,
    #[arg(long)]
    pub end_mm: Option<f64>,
    #[arg(long)]
    pub targets: Option<usize>,
    #[arg(long)]
    pub runs: Option<u32>,
    #[arg(long)]
    pub overrun_mm: Option<f64>,
    #[arg(long)]
    pub dwell_s: Option<f64>,
    #[arg(long)]
    pub feed_mm_min: Option<f64>,
    #[arg(long)]
    pub lead_mm: Option<f64>,
    /// Program dialect: iso, siemens, heidenhain, linuxcnc (default: the configuration's).
    #[arg(long)]
    pub dialect: Option<String>,
}

pub fn run(c: Command) -> Result<()> {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let (at, req) = match c {
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
                    notes: None,
                },
            )
        }
        Command::Status(w) => (w, Request::RunStatus),
        Command::Abort(w) => (w, Request::RunAbort),
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
    println!("{}", serde_json::to_string_pretty(&v)?);
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
    #[arg(long)]
    pub config: Option<PathBuf>,
}

fn open_store(a: &StoreArgs) -> Result<Store> {
    let path = match &a.db {
        Some(p) => p.clone(),
        None => super::service::settings(a.config.as_deref())?
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

#[derive(clap::Args, Debug)]
pub struct ReportArgs {
    #[command(flatten)]
    pub store: StoreArgs,
    /// Directory for the report (HTML, Markdown, SVG and PNG plots).
    #[arg(long)]
    pub out: PathBuf,
}

/// `axiscomp report --run ID --out DIR`.
pub fn report(a: ReportArgs) -> Result<()> {
    let store = open_store(&a.store)?;
    let id = RunId(a.store.run);
    let rec = store.run(id)?;
    let captures = store.captures(id)?;
    let eval = evaluate_captures(&captures, &EvalOptions::default())?;
    let report = axiscomp::report::runs::run_report(RunMeta::from_record(&rec), &captures, &eval);
    let files = write_run_report(&a.out, &report)?;
    for f in files {
        println!("{}", f.display());
    }
    Ok(())
}

#[derive(Clone, Copy, Debug, ValueEnum, PartialEq)]
pub enum Format {
    SiemensLec,
    SiemensCec,
    Fanuc,
    Heidenhain,
    LinuxcncType0,
    LinuxcncType1,
    Csv,
    Json,
}

#[derive(Clone, Copy, Debug, ValueEnum, PartialEq)]
pub enum Table {
    Positioning,
    StraightnessX,
    StraightnessZ,
}

#[derive(clap::Args, Debug)]
pub struct ExportArgs {
    #[command(flatten)]
    pub store: StoreArgs,
    #[arg(long, value_enum)]
    pub format: Format,
    /// Which table (the head's transverse x or vertical z straightness, or positioning).
    #[arg(long, value_enum, default_value_t = Table::Positioning)]
    pub table: Table,
    /// The machine axis the head measured along (default: the run's).
    #[arg(long)]
    pub axis: Option<String>,
    /// One table per direction instead of one with backlash.
    #[arg(long)]
    pub bidirectional: bool,
    #[arg(long)]
    pub out: PathBuf,
}

/// `axiscomp export --run ID --format FORMAT --out FILE`.
pub fn export(a: ExportArgs) -> Result<()> {
    let store = open_store(&a.store)?;
    let id = RunId(a.store.run);
    let rec = store.run(id)?;
    let captures = store.captures(id)?;
    let eval = evaluate_captures(&captures, &EvalOptions::default())?;
    let axis_name = a.axis.clone().unwrap_or(rec.axis.clone());
    let axis = MachineAxis::from_letter(&axis_name)
        .ok_or_else(|| InputError(format!("--axis {axis_name}: use X, Y or Z")))?;
    let plan: Option<axiscomp::run::Plan> = serde_json::from_value(rec.plan.clone()).ok();
    let spec = TableSpec {
        mapping: AxisMapping::standard(axis),
        reference_mm: plan.map(|p| p.reference_mm).unwrap_or(0.0),
        positioning: if a.bidirectional {
            PositioningMode::Bidirectional
        } else {
            PositioningMode::Unidirectional
        },
        straightness_line: ReferenceLine::LeastSquares,
        functional_point_mm: None,
    };
    let set = comp::build_tables(&eval, &spec)?;
    let table = match a.table {
        Table::Positioning => &set.positioning,
        Table::StraightnessX => set
            .straightness
            .first()
            .ok_or_else(|| InputError("no straightness table".into()))?,
        Table::StraightnessZ => set
            .straightness
            .get(1)
            .ok_or_else(|| InputError("no vertical straightness table".into()))?,
    };
    let letter = axis.letter();
    let text = match a.format {
        Format::SiemensLec => {
            comp::siemens::lec(table, &comp::siemens::LecOptions::new(letter))?.text
        }
        Format::SiemensCec => {
            comp::siemens::cec(
                table,
                &comp::siemens::CecOptions {
                    table_index: 0,
                    input_axis: table.base_axis.letter().to_string(),
                    output_axis: table.comp_axis.letter().to_string(),
                    max_points: 200,
                    step_mm: None,
                },
            )?
            .text
        }
        Format::Fanuc => {
            comp::fanuc::pitch(
                table,
                &comp::fanuc::PitchOptions::new(axis.index() as u8 + 1, 0),
            )?
            .text
        }
        Format::Heidenhain => {
            comp::heidenhain::com(
                table,
                &comp::heidenhain::ComOptions::new(&file_name(&a.out)),
            )?
            .text
        }
        Format::LinuxcncType0 => {
            comp::linuxcnc::comp_file(
                table,
                &comp::linuxcnc::CompFileOptions::new(comp::linuxcnc::CompFileType::Type0),
            )?
            .text
        }
        Format::LinuxcncType1 => {
            comp::linuxcnc::comp_file(
                table,
                &comp::linuxcnc::CompFileOptions::new(comp::linuxcnc::CompFileType::Type1),
            )?
            .text
        }
        Format::Csv => comp::neutral::csv(table),
        Format::Json => comp::neutral::json(table)?,
    };
    std::fs::write(&a.out, text).with_context(|| format!("writing {}", a.out.display()))?;
    eprintln!(
        "wrote {} ({} table {})",
        a.out.display(),
        format!("{:?}", a.format).to_lowercase(),
        table.name
    );
    Ok(())
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "AXISCOMP.COM".into())
}
