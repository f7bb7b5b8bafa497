//! `axiscomp run start|status|abort` (through the running service), `axiscomp run list` and
//! `axiscomp report` (from the store); `axiscomp export` is in `export.rs`.

use super::InputError;
use anyhow::{Context, Result};
use axiscomp::evaluate::{EvalOptions, evaluate_captures};
use axiscomp::report::{RunMeta, write_run_report};
use axiscomp::run::PlanSpec;
use axiscomp::service::control::{Client, Request};
use axiscomp::store::{RunId, Store};
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
                    notes: a.notes,
                },
            )
        }
        Command::Status(w) => (w, Request::RunStatus),
        Command::Abort(w) => (w, Request::RunAbort),
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

pub(super) fn open_store(a: &StoreArgs) -> Result<Store> {
    open_store_at(a.db.as_ref(), a.config.as_ref())
}

/// The store at `db`, or in the state directory `config` names, read-only.
fn open_store_at(db: Option<&PathBuf>, config: Option<&PathBuf>) -> Result<Store> {
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

#[derive(clap::Args, Debug)]
pub struct ReportArgs {
    #[command(flatten)]
    pub store: StoreArgs,
    /// Directory for the report (HTML, Markdown, SVG and PNG plots).
    #[arg(long, required_unless_present = "json")]
    pub out: Option<PathBuf>,
    /// Print the ISO figures and the uncertainty budget of every DOF and point as JSON (µm,
    /// arcsec; standard u per term, U expanded with k = 2).
    #[arg(long)]
    pub json: bool,
    /// The follower stage's specification, ±µm along its axis and ±µm vertical straightness
    /// (e.g. 4,2), for the budget's follower term until a follower map is in use; without it
    /// the term is stated as unknown.
    #[arg(long, value_delimiter = ',', value_name = "ALONG_UM,VERTICAL_UM")]
    pub follower_spec_um: Option<Vec<f64>>,
}

/// `axiscomp report --run ID (--out DIR | --json)`.
pub fn report(a: ReportArgs) -> Result<()> {
    use axiscomp::evaluate::uncertainty::{self, BudgetInputs, FollowerInput};
    let store = open_store(&a.store)?;
    let id = RunId(a.store.run);
    let rec = store.run(id)?;
    let captures = store.captures(id)?;
    let eval = evaluate_captures(&captures, &EvalOptions::default())?;
    let mut report =
        axiscomp::report::runs::run_report(RunMeta::from_record(&rec), &captures, &eval);
    let handovers: Vec<_> = store
        .handovers(Some(id))?
        .into_iter()
        .map(|h| h.record)
        .collect();
    let follower = match a.follower_spec_um.as_deref() {
        Some(&[along, vertical]) if along >= 0.0 && vertical >= 0.0 => {
            FollowerInput::Specification {
                positioning_mm: along * 1e-3,
                straightness_mm: vertical * 1e-3,
            }
        }
        Some(v) => {
            let given: Vec<String> = v.iter().map(ToString::to_string).collect();
            return Err(InputError(format!(
                "--follower-spec-um {}: give two non-negative numbers, µm along and µm vertical (e.g. 4,2)",
                given.join(",")
            ))
            .into());
        }
        None => FollowerInput::Unstated,
    };
    // The head's sensitivities to PSD2 from the layout: first order, as the stored run does
    // not carry its decoupler.
    let layout = super::load_layout(None)?;
    let decoupler = axiscomp::decouple::Decoupler {
        source: axiscomp::decouple::Source::Simulated(layout),
        method: axiscomp::decouple::Method::Linear,
        sigma_mm: [1e-3; 6],
        options: axiscomp::decouple::SolveOptions::default(),
    };
    let mid = eval.positions_mm.iter().sum::<f64>() / eval.positions_mm.len().max(1) as f64;
    let reference_mm = rec
        .plan
        .get("reference_mm")
        .and_then(serde_json::Value::as_f64)
        .or_else(|| eval.positions_mm.first().copied())
        .unwrap_or(0.0);
    let inputs = BudgetInputs {
        reference_mm,
        psd2_sensitivity: uncertainty::psd2_sensitivity(&decoupler, mid)
            .context("the head's sensitivities to PSD2 from the layout")?,
        follower,
        calibration: None,
        thermal: None,
        drift_range: None,
    };
    let budget = uncertainty::budget(
        &eval,
        &uncertainty::stitched(&captures, &handovers),
        &inputs,
    );
    axiscomp::report::runs::add_budget(&mut report, &budget);
    if let Some(out) = &a.out {
        let files = write_run_report(out, &report)?;
        if !a.json {
            for f in files {
                println!("{}", f.display());
            }
        }
    }
    if a.json {
        let json = serde_json::json!({
            "run": id.0,
            "axis": rec.axis,
            "figures": report.dofs.iter().map(|d| serde_json::json!({
                "dof": d.dof.name(),
                "figures": d.figures.iter().map(|f| serde_json::json!({
                    "name": f.name, "value": f.value, "unit": f.unit,
                })).collect::<Vec<_>>(),
            })).collect::<Vec<_>>(),
            "budget": budget.to_user_json(),
        });
        println!("{}", serde_json::to_string_pretty(&json)?);
    }
    Ok(())
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
