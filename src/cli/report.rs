//! `axiscomp report`: a run's acceptance report (HTML, Markdown, PDF) from the store, without
//! the service, optionally against a second run (before/after); `--json` prints the ISO figures
//! and the uncertainty budget; `--format raw` writes the per-error plots and tables as before.

use super::InputError;
use super::run::{StoreArgs, open_store};
use anyhow::{Context, Result};
use axiscomp::evaluate::recorded::Recorded;
use axiscomp::evaluate::uncertainty::{self, Budget, FollowerInput};
use axiscomp::report::budget::{Fallbacks, run_budget};
use axiscomp::report::source::{RunData, follower_map, run_data};
use axiscomp::report::{Format, RunMeta, acceptance, write_acceptance, write_run_report};
use axiscomp::store::{RunId, Store};
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct ReportArgs {
    #[command(flatten)]
    pub store: StoreArgs,
    /// A second run to compare with (before/after: the earlier run is "before").
    #[arg(long, value_name = "RUN")]
    pub compare: Option<i64>,
    /// Directory for the report.
    #[arg(long, required_unless_present = "json")]
    pub out: Option<PathBuf>,
    /// Formats, comma-separated: html, md, pdf (default: all three), or raw (the per-error
    /// plots, SVG and PNG, with report.html and report.md of the figures).
    #[arg(long, value_delimiter = ',', value_name = "html|md|pdf|raw")]
    pub format: Vec<String>,
    /// The operator to name on the report (default: who started the run, from the audit log).
    #[arg(long)]
    pub operator: Option<String>,
    /// Print the ISO figures and the uncertainty budget of every DOF and point as JSON (µm,
    /// arcsec; standard u per term, U expanded with k = 2).
    #[arg(long)]
    pub json: bool,
    /// The follower stage's specification, ±µm along its axis and ±µm vertical straightness
    /// (e.g. 4,2), for the budget's follower term of a run that used no follower map (the map
    /// a run used, recorded when it started, comes first); without either the term is not
    /// stated, and the report says why.
    #[arg(long, value_delimiter = ',', value_name = "ALONG_UM,VERTICAL_UM")]
    pub follower_spec_um: Option<Vec<f64>>,
    /// When the report is made (µs since the epoch; `None`: now). The demo's runs are dated
    /// by the twin's clock, which runs its minutes of machine time ahead of the wall's: its
    /// report is made when its simulated session ends, not before the runs it reports.
    #[arg(skip)]
    pub made_us: Option<i64>,
}

fn follower_input(spec: Option<&[f64]>) -> Result<Option<FollowerInput>> {
    Ok(Some(match spec {
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
        None => return Ok(None),
    }))
}

/// PSD2's sensitivities from the layout, first order at mid-travel: for a run that did not
/// record its own decoupling's.
fn layout_sensitivity(run: &RunData) -> Result<[[f64; 2]; 6]> {
    let layout = super::load_layout(None)?;
    let decoupler = axiscomp::decouple::Decoupler {
        source: axiscomp::decouple::Source::Simulated(layout),
        method: axiscomp::decouple::Method::Linear,
        sigma_mm: [1e-3; 6],
        options: axiscomp::decouple::SolveOptions::default(),
    };
    let p = &run.eval.positions_mm;
    let mid = p.iter().sum::<f64>() / p.len().max(1) as f64;
    uncertainty::psd2_sensitivity(&decoupler, mid)
        .context("the head's sensitivities to PSD2 from the layout")
}

/// The run's uncertainty budget, from what it recorded (see `report::budget`).
fn budget(store: &Store, run: &RunData, follower_spec: Option<&FollowerInput>) -> Result<Budget> {
    let fb = Fallbacks {
        psd2_sensitivity: layout_sensitivity(run)?,
        follower_spec: follower_spec.cloned(),
    };
    Ok(run_budget(store, run, &fb)?)
}

fn formats(given: &[String]) -> Result<(Vec<Format>, bool)> {
    if given.is_empty() {
        return Ok((Format::ALL.to_vec(), false));
    }
    let mut out = Vec::new();
    let mut raw = false;
    for f in given {
        match (f.as_str(), Format::parse(f)) {
            ("raw", _) => raw = true,
            (_, Some(f)) => out.push(f),
            (other, None) => {
                return Err(InputError(format!(
                    "--format {other}: use html, md, pdf or raw (comma-separated)"
                ))
                .into());
            }
        }
    }
    out.sort();
    out.dedup();
    Ok((out, raw))
}

/// `axiscomp report --run N [--compare M] [--format …] (--out DIR | --json)`.
pub fn report(a: ReportArgs) -> Result<()> {
    for f in written(a)? {
        println!("{}", f.display());
    }
    Ok(())
}

/// The report `a` asks for, written (or printed as JSON with `--json`): the files written
/// (none with `--json`, which prints instead).
pub fn written(a: ReportArgs) -> Result<Vec<PathBuf>> {
    let mut written = Vec::new();
    let (formats, raw) = formats(&a.format)?;
    let settings = super::service::settings(a.store.config.as_deref())?;
    let store = open_store(&a.store)?;
    let alpha = settings.machine.expansion_um_per_m_k;
    let follower = follower_input(a.follower_spec_um.as_deref())?;
    let mut run = run_data(&store, RunId(a.store.run), alpha)?;
    run.budget = Some(budget(&store, &run, follower.as_ref())?);
    let compare = match a.compare {
        Some(m) if m == a.store.run => {
            return Err(InputError(format!(
                "--compare {m}: that is the run reported; give another run"
            ))
            .into());
        }
        Some(m) => {
            let mut c = run_data(&store, RunId(m), alpha)?;
            c.budget = Some(budget(&store, &c, follower.as_ref())?);
            if c.record.axis != run.record.axis {
                return Err(InputError(format!(
                    "--compare {m}: run {m} measured axis {}, run {} axis {}: compare runs of one axis",
                    c.record.axis, a.store.run, run.record.axis
                ))
                .into());
            }
            Some(c)
        }
        None => None,
    };
    let generated_us = a.made_us.unwrap_or_else(axiscomp::store::now_us);
    if let Some(out) = &a.out {
        let map = follower_map(&store)?;
        let doc = acceptance::document(&acceptance::Acceptance {
            machine: &settings.machine,
            head_serial: &settings.head.serial,
            tolerances: &settings.acceptance,
            follower_map: map.as_ref(),
            run: &run,
            compare: compare.as_ref(),
            operator: a.operator.as_deref(),
            generated_us,
        });
        let mut files = write_acceptance(out, &doc, &formats, generated_us)?;
        if raw {
            let mut report = axiscomp::report::runs::run_report(
                RunMeta::from_record(&run.record),
                &run.captures,
                &run.eval,
            );
            if let Some(b) = &run.budget {
                axiscomp::report::runs::add_budget(&mut report, b);
            }
            files.extend(write_run_report(out, &report)?);
        }
        if !a.json {
            written = files;
        }
    }
    if a.json {
        let report = axiscomp::report::runs::run_report(
            RunMeta::from_record(&run.record),
            &run.captures,
            &run.eval,
        );
        let json = serde_json::json!({
            "run": run.record.id.0,
            "axis": run.record.axis,
            "figures": report.dofs.iter().map(|d| serde_json::json!({
                "dof": d.dof.name(),
                "figures": d.figures.iter().map(|f| serde_json::json!({
                    "name": f.name, "value": f.value, "unit": f.unit,
                })).collect::<Vec<_>>(),
            })).collect::<Vec<_>>(),
            "budget": run.budget.as_ref().map(Budget::to_user_json),
            "budget_inputs": match &run.recorded {
                Recorded::Yes(r) => r.to_json(),
                other => serde_json::json!({ "not_recorded": other.missing() }),
            },
        });
        println!("{}", serde_json::to_string_pretty(&json)?);
    }
    Ok(written)
}
