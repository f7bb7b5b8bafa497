//! `axiscomp trend AXIS [FIGURE] [--json]`: every figure of the axis's finished runs over time,
//! each against control limits learned from its first runs and each later one in control,
//! with the drift alarm and, where
//! `[acceptance]` gives its tolerance, the day the figure's trend line reaches it
//! ([`axiscomp::trend`]). Reads the store; the service need not run.

use super::InputError;
use super::run::open_store_at;
use anyhow::Result;
use axiscomp::report::settings::AcceptanceSettings;
use axiscomp::service::trends::{FigureHistory, Judged, histories, remedy};
use axiscomp::store::iso_utc;
use axiscomp::trend::{self, Settings};
use serde_json::json;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The axis (as its runs name it: X, Y, Z).
    pub axis: String,
    /// One figure (its error and name, e.g. "dy E" or "ey max − min (mean)"): each run's value
    /// with the EWMA and its limits. Without it, one line per figure.
    pub figure: Option<String>,
    /// The store (default: axiscomp.db in the configured state directory).
    #[arg(long)]
    pub db: Option<PathBuf>,
    /// The configuration (the state directory and the `[acceptance]` tolerances).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// The first runs, as commissioned, the limits are learned from.
    #[arg(long, default_value_t = Settings::default().baseline)]
    pub baseline: usize,
    /// The newest runs the forecast's line is fitted to.
    #[arg(long, default_value_t = Settings::default().window)]
    pub window: usize,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let store = open_store_at(a.db.as_ref(), a.config.as_ref())?;
    let acceptance = match &a.config {
        Some(c) => super::service::settings(Some(c))?.acceptance,
        None => AcceptanceSettings::default(),
    };
    let (all, runs) = histories(&store, &a.axis).map_err(InputError)?;
    if runs.ids.is_empty() {
        return Err(InputError(format!(
            "axis {}: no finished run in the store to trend; measure it (axiscomp run start) first",
            a.axis
        ))
        .into());
    }
    let t0_us = runs.first_us;
    let settings = Settings {
        baseline: a.baseline,
        window: a.window,
        ..Settings::default()
    };
    let wanted: Vec<&FigureHistory> = match &a.figure {
        None => all.iter().collect(),
        Some(f) => {
            let f = f.trim().to_lowercase();
            // "dy B" is the reversal, not also B̄: a figure by its short name first, then
            // every figure whose name begins with what was given.
            let short = |h: &FigureHistory| {
                format!("{} {}", h.dof, h.name.split(' ').next().unwrap_or_default()).to_lowercase()
            };
            let mut hit: Vec<&FigureHistory> = all.iter().filter(|h| short(h) == f).collect();
            if hit.is_empty() {
                hit = all
                    .iter()
                    .filter(|h| h.label().to_lowercase().starts_with(&f))
                    .collect();
            }
            if hit.is_empty() {
                let names: Vec<String> = all.iter().map(FigureHistory::label).collect();
                return Err(InputError(format!(
                    "no figure \"{f}\" in axis {}'s runs: give one of {}",
                    a.axis,
                    names.join(", ")
                ))
                .into());
            }
            hit
        }
    };
    let judged: Vec<Judged> = wanted
        .into_iter()
        .map(|h| Judged::of(h.clone(), t0_us, &acceptance, &settings))
        .collect();
    if a.json {
        let figures: Vec<serde_json::Value> = judged.iter().map(|j| j.to_json(t0_us)).collect();
        println!(
            "{}",
            serde_json::to_string_pretty(&json!({"axis": a.axis, "runs": runs.ids,
                "compensation": runs.compensation, "runs_under_other_tables": runs.other,
                "figures": figures}))?
        );
        return Ok(());
    }
    println!(
        "axis {}: {} finished run{} under the newest's compensation ({}), {} to {}; limits from the first {} and each later run in control",
        a.axis,
        runs.ids.len(),
        if runs.ids.len() == 1 { "" } else { "s" },
        runs.compensation,
        day(t0_us),
        day(runs.last_us),
        settings.baseline
    );
    match runs.other {
        0 => {}
        1 => println!(
            "  1 earlier run measured under other tables is not in the trend: a table published changes what the figures measure"
        ),
        n => println!(
            "  {n} earlier runs measured under other tables are not in the trend: a table published changes what the figures measure"
        ),
    }
    if a.figure.is_some() && judged.len() == 1 {
        print!("{}", detail(&judged[0], t0_us, settings.baseline));
    } else {
        for j in &judged {
            println!("{}", line(j, t0_us));
        }
    }
    Ok(())
}

fn day(us: i64) -> String {
    iso_utc(us)[..10].to_string()
}

/// The date `days` after `t0_us`.
fn date_after(t0_us: i64, days: f64) -> String {
    day(t0_us + (days * 86_400e6) as i64)
}

fn line(j: &Judged, t0_us: i64) -> String {
    let h = &j.history;
    let last = h.points.last().map_or(f64::NAN, |p| p.2);
    let state = match &j.chart {
        Err(trend::TrendError::TooFew { have, need, .. }) => {
            format!("no limits yet: {have} of the {need} runs they need")
        }
        Err(e) => format!("no limits: {e}"),
        Ok(c) => {
            let (lo, hi) = c.limits.last().copied().unwrap_or((f64::NAN, f64::NAN));
            let alarm = match c.alarm {
                Some(i) => format!(
                    "DRIFT since run {} ({}); {}",
                    h.points[i].0,
                    day(h.points[i].1),
                    remedy(&h.dof, &h.name).words()
                ),
                None => "in control".into(),
            };
            format!(
                "EWMA {:.2} within {:.2} to {:.2}: {alarm}",
                c.ewma.last().copied().unwrap_or(f64::NAN),
                lo,
                hi
            )
        }
    };
    let reach = forecast_text(j, t0_us)
        .map(|t| format!("; {t}"))
        .unwrap_or_default();
    format!(
        "{:<36} {:>9.2} {:<6} {state}{reach}",
        h.label(),
        last,
        h.unit
    )
}

fn forecast_text(j: &Judged, t0_us: i64) -> Option<String> {
    let t = j.tolerance?;
    let unit = &j.history.unit;
    let Some(f) = j.forecast else {
        return Some(format!(
            "no forecast against its tolerance {t} {unit}: it needs 3 runs spanning a day or more"
        ));
    };
    Some(match f.crossing {
        Some(c) => format!(
            "reaches its tolerance {t} {unit} about {} (95 %: {} to {}; {:+.3} {unit}/day over the last {} runs)",
            date_after(t0_us, c.day),
            date_after(t0_us, c.low),
            date_after(t0_us, c.high),
            f.slope_per_day,
            f.points
        ),
        None => format!(
            "not heading for its tolerance {t} {unit} within a century ({:+.3} {unit}/day over the last {} runs)",
            f.slope_per_day, f.points
        ),
    })
}

fn detail(j: &Judged, t0_us: i64, baseline: usize) -> String {
    let h = &j.history;
    let mut out = format!("{}, {}\n", h.label(), h.unit);
    out.push_str("run    date         value      EWMA    limits\n");
    for (i, p) in h.points.iter().enumerate() {
        let (z, lim) = match &j.chart {
            Ok(c) => (
                format!("{:>9.2}", c.ewma[i]),
                format!("{:.2} to {:.2}", c.limits[i].0, c.limits[i].1),
            ),
            Err(_) => ("        —".into(), "—".into()),
        };
        let mark = match &j.chart {
            Ok(c) if c.alarm == Some(i) => "  ← drift alarm",
            _ => "",
        };
        out.push_str(&format!(
            "{:<6} {} {:>9.2} {z}    {lim}{mark}\n",
            p.0,
            day(p.1),
            p.2
        ));
    }
    match &j.chart {
        Ok(c) => out.push_str(&format!(
            "limits learned from {} runs (the first {} and each later one in control): mean {:.2} {}, σ {:.2} {}\n",
            c.history.len(),
            baseline,
            c.mean,
            h.unit,
            c.sigma,
            h.unit
        )),
        Err(e) => out.push_str(&format!("no limits yet: {e}\n")),
    }
    if let Some(t) = forecast_text(j, t0_us) {
        out.push_str(&format!("forecast: {t}\n"));
    }
    out
}
