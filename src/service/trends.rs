//! An axis's trends from the store (issue 30): every figure of its finished runs and checks
//! measured under the same compensation as the newest, each charted against control limits
//! learned from its own history and, where `[acceptance]` gives its tolerance, forecast
//! ([`crate::trend`]). Read by `axiscomp trend`, the PLC's check handshake (`service::checks`:
//! the check's verdict) and the console's Trends screen.

use super::results::run_result;
use crate::report::settings::AcceptanceSettings;
use crate::store::{RunId, Store};
use crate::trend::{self, Chart, Forecast, Point, Settings, TrendError};

/// One figure's history: its error, name and unit, and (run, unix µs, value) oldest first.
#[derive(Clone, Debug, PartialEq)]
pub struct FigureHistory {
    pub dof: String,
    pub name: String,
    pub unit: String,
    pub points: Vec<(i64, i64, f64)>,
}

impl FigureHistory {
    /// "dy E …": the error and the figure's name.
    pub fn label(&self) -> String {
        format!("{} {}", self.dof, self.name)
    }

    /// The points as days since `t0_us`.
    pub fn points_since(&self, t0_us: i64) -> Vec<Point> {
        self.points
            .iter()
            .map(|&(_, us, value)| Point {
                days: (us - t0_us) as f64 / 86_400e6,
                value,
            })
            .collect()
    }
}

/// What was trended: the runs used (and when the first and the last were made), and how many
/// were left out for another compensation.
#[derive(Clone, Debug, PartialEq)]
pub struct TrendedRuns {
    pub ids: Vec<i64>,
    pub first_us: i64,
    pub last_us: i64,
    /// The newest run's compensation, in words.
    pub compensation: String,
    pub other: usize,
}

/// The acceptance figure a run's figure is judged against, when it has one.
pub fn tolerance_figure(dof: &str, name: &str) -> Option<&'static str> {
    let first = name.split(' ').next().unwrap_or_default();
    match (dof, first) {
        ("dy", "A") => Some("A"),
        ("dy", "E") => Some("E"),
        ("dy", "R") => Some("R"),
        ("dy", "B") => Some("B"),
        ("dy", "M") => Some("M"),
        ("dx" | "dz", _) if name == "straightness (least squares)" => Some("straightness"),
        ("ex", _) if name == "max − min (mean)" => Some("pitch"),
        ("ey", _) if name == "max − min (mean)" => Some("roll"),
        ("ez", _) if name == "max − min (mean)" => Some("yaw"),
        _ => None,
    }
}

/// What a drift in a figure calls for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Remedy {
    /// A compensation table reaches it: compose one from the run that shows it.
    Table,
    /// Beyond a table's reach: maintenance, for the likely cause.
    Maintenance(&'static str),
    /// The set-up moved, not the machine.
    SetUp(&'static str),
}

impl Remedy {
    /// In words, for a line after the figure.
    pub fn words(self) -> String {
        match self {
            Remedy::Table => "within a table's reach: generate one from the newest run".into(),
            Remedy::Maintenance(cause) => format!("maintenance: {cause}"),
            Remedy::SetUp(what) => format!("the set-up: {what}"),
        }
    }
}

/// What a drift in figure `name` of error `dof` calls for, with its likely cause.
pub fn remedy(dof: &str, name: &str) -> Remedy {
    let first = name.split(' ').next().unwrap_or_default();
    if first == "slope" {
        return Remedy::SetUp(
            "the beam's slope to the axis moved: the head or its mount shifted, align again",
        );
    }
    match (dof, first) {
        ("dy", "R") => Remedy::Maintenance(
            "the repeatability worsens: play, friction or the drive's tuning; no table compensates scatter",
        ),
        ("dy", "B" | "B̄") => Remedy::Maintenance(
            "the reversal grows: wear or lost preload in the ball screw's nut or its bearings, or a coupling working loose; a table holds a steady reversal, not a growing one",
        ),
        ("dy" | "dx" | "dz", _) => Remedy::Table,
        ("ex", _) => Remedy::Maintenance(
            "pitch grows: guideway wear, or the foundation and the machine's levelling; a table takes its effect at the tool for one set-up only",
        ),
        ("ez", _) => Remedy::Maintenance(
            "yaw grows: guideway or gib wear; a table takes its effect at the tool for one set-up only",
        ),
        ("ey", _) => Remedy::Maintenance(
            "roll grows: guideway twist or wear, or the machine's levelling; no compensation of the axis corrects roll",
        ),
        _ => Remedy::Maintenance("a figure of an unknown kind moves: look at the run"),
    }
}

/// The compensation a run measured under: the tables the PLC applied, as recorded when it
/// started.
pub fn compensation(store: &Store, run: RunId) -> String {
    match store.run_tables(run) {
        Ok(Some(t)) if t.known => {
            let tables: Vec<String> = t
                .tables
                .iter()
                .map(|a| {
                    format!(
                        "{} {} sequence {} CRC 0x{:08X}",
                        a.kind, a.axis, a.sequence, a.crc
                    )
                })
                .collect();
            if tables.is_empty() {
                "no tables".into()
            } else {
                tables.join(", ")
            }
        }
        Ok(Some(t)) => format!("unknown ({})", t.source),
        Ok(None) | Err(_) => "not recorded".into(),
    }
}

/// Every figure of `axis`'s finished runs measured under the same compensation as the newest
/// (a table published since an earlier run changed what its figures mean), oldest first.
pub fn histories(store: &Store, axis: &str) -> Result<(Vec<FigureHistory>, TrendedRuns), String> {
    let mut runs: Vec<_> = store
        .list_runs()
        .map_err(|e| e.to_string())?
        .into_iter()
        .filter(|r| r.axis.eq_ignore_ascii_case(axis) && r.state.as_str() == "finished")
        .collect();
    runs.sort_by_key(|r| (r.created_us, r.id.0));
    let keys: Vec<String> = runs.iter().map(|r| compensation(store, r.id)).collect();
    let newest = keys.last().cloned().unwrap_or_default();
    let other = keys.iter().filter(|k| **k != newest).count();
    let mut out: Vec<FigureHistory> = Vec::new();
    let (mut ids, mut first_us, mut last_us) = (Vec::new(), i64::MAX, i64::MIN);
    for (r, _) in runs.iter().zip(&keys).filter(|(_, k)| **k == newest) {
        let result = run_result(store, Some(r.id.0))?;
        if result.incomplete.is_some() {
            continue;
        }
        ids.push(r.id.0);
        first_us = first_us.min(r.created_us);
        last_us = last_us.max(r.created_us);
        for d in &result.dofs {
            for f in &d.figures {
                let at = (r.id.0, r.created_us, f.value);
                match out.iter_mut().find(|h| h.dof == d.name && h.name == f.name) {
                    Some(h) => h.points.push(at),
                    None => out.push(FigureHistory {
                        dof: d.name.clone(),
                        name: f.name.clone(),
                        unit: f.unit.clone(),
                        points: vec![at],
                    }),
                }
            }
        }
    }
    Ok((
        out,
        TrendedRuns {
            ids,
            first_us,
            last_us,
            compensation: newest,
            other,
        },
    ))
}

/// One figure judged: its chart (or why it has none yet), its tolerance and forecast.
#[derive(Clone, Debug)]
pub struct Judged {
    pub history: FigureHistory,
    pub chart: Result<Chart, TrendError>,
    pub tolerance: Option<f64>,
    pub forecast: Option<Forecast>,
}

impl Judged {
    /// `history` charted with `settings` from `t0_us`, against its tolerance in `acceptance`.
    pub fn of(
        history: FigureHistory,
        t0_us: i64,
        acceptance: &AcceptanceSettings,
        settings: &Settings,
    ) -> Judged {
        let pts = history.points_since(t0_us);
        let tolerance = tolerance_figure(&history.dof, &history.name)
            .and_then(|f| acceptance.of(f))
            .map(|t| t.limit);
        Judged {
            chart: trend::chart(&pts, settings),
            forecast: tolerance.and_then(|t| trend::forecast(&pts, t, settings.window)),
            tolerance,
            history,
        }
    }

    /// The index of run `run` among the points.
    fn at(&self, run: i64) -> Option<usize> {
        self.history.points.iter().position(|p| p.0 == run)
    }

    /// Whether run `run`'s value signals on the chart (beyond the control limits).
    pub fn signals_at(&self, run: i64) -> bool {
        match (&self.chart, self.at(run)) {
            (Ok(c), Some(i)) => c.signals.get(i).copied().unwrap_or(false),
            _ => false,
        }
    }

    /// The figure as JSON (`axiscomp trend --json`, the control API's `trend`): its points
    /// with the EWMA and limits, the history's mean and σ, the alarm and what it calls for,
    /// the tolerance and the forecast (dates as unix µs, from `t0_us` the first run's).
    pub fn to_json(&self, t0_us: i64) -> serde_json::Value {
        let h = &self.history;
        let chart = self.chart.as_ref().ok();
        let points: Vec<serde_json::Value> = h
            .points
            .iter()
            .enumerate()
            .map(|(i, p)| {
                serde_json::json!({
                    "run_id": p.0, "unix_us": p.1, "value": p.2,
                    "ewma": chart.map(|c| c.ewma[i]),
                    "limits": chart.map(|c| [c.limits[i].0, c.limits[i].1]),
                })
            })
            .collect();
        let at = |days: f64| t0_us + (days * 86_400e6) as i64;
        serde_json::json!({
            "dof": h.dof, "name": h.name, "unit": h.unit,
            "points": points,
            "mean": chart.map(|c| c.mean),
            "sigma": chart.map(|c| c.sigma),
            "alarm_run": chart.and_then(|c| c.alarm).map(|i| h.points[i].0),
            "remedy": chart.and_then(|c| c.alarm).map(|_| remedy(&h.dof, &h.name).words()),
            "no_limits": self.chart.as_ref().err().map(ToString::to_string),
            "tolerance": self.tolerance,
            "forecast": self.forecast.map(|f| serde_json::json!({
                "slope_per_day": f.slope_per_day,
                "slope_u": f.slope_u,
                "points": f.points,
                "crossing_unix_us": f.crossing.map(|c| at(c.day)),
                "crossing_low_unix_us": f.crossing.map(|c| at(c.low)),
                "crossing_high_unix_us": f.crossing.map(|c| at(c.high)),
            })),
        })
    }

    /// Whether run `run`'s value is beyond the figure's tolerance.
    pub fn beyond_tolerance_at(&self, run: i64) -> bool {
        match (self.tolerance, self.at(run)) {
            (Some(t), Some(i)) => self.history.points[i].2 > t,
            _ => false,
        }
    }
}

/// An axis's trends: the runs and every figure judged.
#[derive(Clone, Debug)]
pub struct AxisTrends {
    pub axis: String,
    pub runs: TrendedRuns,
    pub figures: Vec<Judged>,
}

/// What run `run` says of the axis, among its trends.
#[derive(Clone, Debug, PartialEq)]
pub enum Verdict {
    /// Every figure charted within its limits and tolerance.
    InControl,
    /// Too few runs under these tables for control limits yet.
    Learning,
    /// These figures signal (labels), each with what it calls for.
    Drift(Vec<(String, Remedy)>),
    /// These figures are beyond their tolerance (labels).
    Tolerance(Vec<String>),
    /// The run is not in the trends (not finished, or measured under other tables).
    NotTrended,
}

impl AxisTrends {
    /// The trends of `axis` in `store`.
    pub fn read(
        store: &Store,
        axis: &str,
        acceptance: &AcceptanceSettings,
        settings: &Settings,
    ) -> Result<AxisTrends, String> {
        let (all, runs) = histories(store, axis)?;
        let t0_us = runs.first_us;
        let figures = all
            .into_iter()
            .map(|h| Judged::of(h, t0_us, acceptance, settings))
            .collect();
        Ok(AxisTrends {
            axis: axis.to_string(),
            runs,
            figures,
        })
    }

    /// The whole as JSON: the axis, the runs trended, and every figure ([`Judged::to_json`]).
    pub fn to_json(&self) -> serde_json::Value {
        let t0 = self.runs.first_us;
        serde_json::json!({
            "axis": self.axis, "runs": self.runs.ids,
            "compensation": self.runs.compensation, "runs_under_other_tables": self.runs.other,
            "first_unix_us": (!self.runs.ids.is_empty()).then_some(t0),
            "figures": self.figures.iter().map(|j| j.to_json(t0)).collect::<Vec<_>>(),
        })
    }

    /// The axis of the newest finished run in `store`, when there is one.
    pub fn newest_axis(store: &Store) -> Result<Option<String>, String> {
        Ok(store
            .list_runs()
            .map_err(|e| e.to_string())?
            .into_iter()
            .filter(|r| r.state.as_str() == "finished")
            .max_by_key(|r| (r.created_us, r.id.0))
            .map(|r| r.axis))
    }

    /// What run `run` says: a figure beyond its tolerance first, then a drift.
    pub fn verdict(&self, run: i64) -> Verdict {
        if !self.runs.ids.contains(&run) {
            return Verdict::NotTrended;
        }
        let labels = |f: &dyn Fn(&Judged) -> bool| -> Vec<String> {
            self.figures
                .iter()
                .filter(|j| f(j))
                .map(|j| j.history.label())
                .collect()
        };
        let beyond = labels(&|j| j.beyond_tolerance_at(run));
        if !beyond.is_empty() {
            return Verdict::Tolerance(beyond);
        }
        let drift: Vec<(String, Remedy)> = self
            .figures
            .iter()
            .filter(|j| j.signals_at(run))
            .map(|j| (j.history.label(), remedy(&j.history.dof, &j.history.name)))
            .collect();
        if !drift.is_empty() {
            return Verdict::Drift(drift);
        }
        if self.figures.iter().all(|j| j.chart.is_err()) {
            return Verdict::Learning;
        }
        Verdict::InControl
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_drift_names_what_it_calls_for() {
        // Positioning and straightness: a table reaches them.
        for (dof, name) in [
            ("dy", "E (systematic)"),
            ("dy", "A (accuracy)"),
            ("dx", "straightness (least squares)"),
        ] {
            assert_eq!(remedy(dof, name), Remedy::Table, "{dof} {name}");
        }
        // A growing reversal, scatter and the angles are the machine's: maintenance, with
        // the likely cause named.
        for (dof, name, cause) in [
            ("dy", "B (reversal)", "ball screw"),
            ("dy", "B̄ (mean reversal)", "ball screw"),
            ("dy", "R (repeatability)", "play"),
            ("ey", "max − min (mean)", "roll"),
            ("ex", "max − min (+)", "pitch"),
            ("ez", "max − min (−)", "yaw"),
        ] {
            match remedy(dof, name) {
                Remedy::Maintenance(c) => assert!(c.contains(cause), "{dof} {name}: {c}"),
                r => panic!("{dof} {name}: {r:?}"),
            }
        }
        // The beam's slope is the set-up's.
        assert!(matches!(
            remedy("dx", "slope (beam alignment)"),
            Remedy::SetUp(_)
        ));
        assert!(Remedy::Table.words().contains("table's reach"));
    }
}
