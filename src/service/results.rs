//! What the store holds, for the control API: the runs and their results (`runs`,
//! `run_result`: the console's Results screen) and the audit log (`audit`: its Events screen). The evaluation is the library's (`evaluate::evaluate_captures` and
//! `report::runs::run_report`, as `axiscomp report` does); this module only turns it into JSON
//! in user units (µm, arcsec) — an edge, like the snapshot.

use crate::evaluate::{EvalOptions, evaluate_captures};
use crate::report::runs::{run_report, series};
use crate::report::{Dof, Figure, RunMeta, Series};
use crate::run::Direction;
use crate::store::{Actor, AuditEntry, RunId, RunRecord, Store};
use serde::{Deserialize, Serialize};

/// One stored run, as the `runs` list shows it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RunSummary {
    pub id: i64,
    pub axis: String,
    /// "planned", "running", "finished", "aborted" or "failed".
    pub state: String,
    /// µs since the Unix epoch.
    pub created_us: i64,
    pub updated_us: i64,
    /// Captures stored so far.
    pub captures: usize,
    pub notes: String,
}

/// One error in one approach direction against position: per target the mean over the runs
/// and its standard deviation s, in the error's user unit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SeriesView {
    pub direction: Direction,
    pub positions_mm: Vec<f64>,
    pub mean: Vec<f64>,
    pub s: Vec<f64>,
    /// Runs averaged at each target.
    pub n: Vec<u32>,
}

/// One figure (ISO 230-2 / 230-1), `value` in `unit`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FigureView {
    pub name: String,
    pub value: f64,
    pub unit: String,
}

/// One of the six errors of a run.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DofView {
    /// "dx" … "ez".
    pub name: String,
    /// "horizontal straightness" … "yaw".
    pub meaning: String,
    /// "µm" or "arcsec".
    pub unit: String,
    /// One per direction measured (+ first).
    pub series: Vec<SeriesView>,
    pub figures: Vec<FigureView>,
}

/// A run's evaluation: the `run_result` reply.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RunResult {
    pub run: RunSummary,
    /// The six errors in `Errors6` order.
    pub dofs: Vec<DofView>,
    /// Why there are no figures (the run cannot be evaluated yet: under way, or aborted with
    /// targets missing); the series are then the captures so far.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub incomplete: Option<String>,
}

fn summary(store: &Store, r: &RunRecord) -> RunSummary {
    RunSummary {
        id: r.id.0,
        axis: r.axis.clone(),
        state: r.state.as_str().to_string(),
        created_us: r.created_us,
        updated_us: r.updated_us,
        captures: store.captures(r.id).map(|c| c.len()).unwrap_or(0),
        notes: r.notes.clone(),
    }
}

/// The stored runs, newest first, at most `limit`.
pub fn runs(store: &Store, limit: usize) -> Result<Vec<RunSummary>, String> {
    let mut all = store.list_runs().map_err(|e| e.to_string())?;
    all.sort_by_key(|r| std::cmp::Reverse(r.id.0));
    Ok(all.iter().take(limit).map(|r| summary(store, r)).collect())
}

/// Run `id`'s evaluation, or (without an id) the newest finished run's. A run that cannot be
/// evaluated (under way, or aborted with targets missing) gives its series so far and says
/// why there are no figures.
pub fn run_result(store: &Store, id: Option<i64>) -> Result<RunResult, String> {
    let rec = match id {
        Some(id) => store.run(RunId(id)).map_err(|e| e.to_string())?,
        None => store
            .list_runs()
            .map_err(|e| e.to_string())?
            .into_iter()
            .filter(|r| r.state.as_str() == "finished")
            .max_by_key(|r| r.id.0)
            .ok_or("no finished run yet: start one (run_start) and let it complete")?,
    };
    let captures = store.captures(rec.id).map_err(|e| e.to_string())?;
    let view = |dof: Dof, series: &[Series], figures: &[Figure]| DofView {
        name: dof.name().to_string(),
        meaning: dof.meaning().to_string(),
        unit: dof.unit().to_string(),
        series: series
            .iter()
            .map(|s| SeriesView {
                direction: s.direction,
                positions_mm: s.positions_mm.clone(),
                mean: s.mean.iter().map(|v| dof.to_user(*v)).collect(),
                s: s.s.iter().map(|v| dof.to_user(*v)).collect(),
                n: s.n.clone(),
            })
            .collect(),
        figures: figures
            .iter()
            .map(|f| FigureView {
                name: f.name.clone(),
                value: f.value,
                unit: f.unit.clone(),
            })
            .collect(),
    };
    let (dofs, incomplete) = match evaluate_captures(&captures, &EvalOptions::default()) {
        Ok(eval) => {
            let report = run_report(RunMeta::from_record(&rec), &captures, &eval);
            let dofs = report
                .dofs
                .iter()
                .map(|d| view(d.dof, &d.series, &d.figures))
                .collect();
            (dofs, None)
        }
        // Not evaluable yet (a run under way, or aborted): the series so far, no figures.
        Err(e) => {
            let dofs = Dof::ALL
                .iter()
                .map(|&dof| {
                    let series: Vec<Series> = [Direction::Up, Direction::Down]
                        .into_iter()
                        .filter_map(|d| series(&captures, dof.index(), d))
                        .collect();
                    view(dof, &series, &[])
                })
                .collect();
            (dofs, Some(format!("no ISO figures: {e}")))
        }
    };
    Ok(RunResult {
        run: summary(store, &rec),
        dofs,
        incomplete,
    })
}

/// One audit-log entry as the `audit` request gives it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct AuditView {
    pub id: i64,
    /// µs since the Unix epoch.
    pub unix_us: i64,
    pub user: Option<String>,
    pub uid: Option<u32>,
    /// The role it acted in.
    pub role: String,
    /// The request (`run_start`, `zero`, …).
    pub action: String,
    /// The request's fields.
    pub details: serde_json::Value,
    /// "done", "refused" or "recorded" (before outcomes were kept).
    #[serde(default)]
    pub outcome: String,
    /// Why it was refused.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

/// The newest `limit` audit entries, newest first.
pub fn audit(store: &Store, limit: u32) -> Result<Vec<AuditView>, String> {
    let mut v: Vec<AuditView> = store
        .audit_entries(limit)
        .map_err(|e| e.to_string())?
        .into_iter()
        .map(|r| AuditView {
            id: r.id,
            unix_us: r.entry.unix_us,
            user: r.entry.who.user,
            uid: r.entry.who.uid,
            role: r.entry.role,
            action: r.entry.action,
            details: r.entry.details,
            outcome: r.entry.outcome.as_str().to_string(),
            reason: r.entry.outcome.reason().map(str::to_string),
        })
        .collect();
    v.reverse();
    Ok(v)
}

/// The audit entry of a request: its `cmd` as the action, its other fields as details.
pub fn audit_entry(
    unix_us: i64,
    who: Actor,
    role: &str,
    request: &serde_json::Value,
) -> AuditEntry {
    let mut details = request.clone();
    let action = details
        .as_object_mut()
        .and_then(|m| m.remove("cmd"))
        .and_then(|c| c.as_str().map(str::to_string))
        .unwrap_or_else(|| "request".into());
    AuditEntry {
        unix_us,
        who,
        role: role.to_string(),
        action,
        details,
        outcome: crate::store::AuditOutcome::Recorded,
    }
}

/// A flagged capture as `run_flags` shows it: the key, the values in user units, why, and
/// what became of it.
pub fn flag_view(f: &crate::store::CaptureFlag) -> serde_json::Value {
    let e = f.capture.errors.to_user();
    serde_json::json!({
        "flag": f.id,
        "run": f.key.run,
        "target": f.key.target_index + 1,
        "target_mm": f.capture.target_mm,
        "direction": f.key.direction.sign(),
        "errors_um_arcsec": e,
        "reason": f.reason,
        "was_stored": f.was_stored,
        "state": if f.retaken {
            "retaken".to_string()
        } else if let Some((by, _, why)) = &f.excluded {
            format!("excluded by {by}: {why}")
        } else {
            "open".to_string()
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn audit_entries_name_the_request_and_come_back_newest_first() {
        let dir = std::env::temp_dir().join(format!("axiscomp-audit-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let mut store = Store::open(dir.join("store.sqlite")).unwrap();
        let who = Actor {
            uid: Some(1000),
            user: Some("ana".into()),
            pid: Some(42),
        };
        for (t, r) in [
            (1, serde_json::json!({"cmd": "zero"})),
            (
                2,
                serde_json::json!({"cmd": "follower", "action": "jog", "mm": 0.1}),
            ),
        ] {
            store
                .audit(&audit_entry(t, who.clone(), "operator", &r))
                .unwrap();
        }
        let v = audit(&store, 10).unwrap();
        assert_eq!(
            v.iter().map(|a| a.action.as_str()).collect::<Vec<_>>(),
            ["follower", "zero"]
        );
        assert_eq!(
            v[0].details,
            serde_json::json!({"action": "jog", "mm": 0.1})
        );
        assert_eq!((v[0].user.as_deref(), v[0].uid), (Some("ana"), Some(1000)));
        assert_eq!(audit(&store, 1).unwrap().len(), 1);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
