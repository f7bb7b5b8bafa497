//! Runs you can find years later (issue 15): one summary per run with its date, axis, range,
//! plan, notes, operator, calibration, the tables active while it ran and its state, read
//! from the store alone (`axiscomp run list`, the console's run list).

use super::{RunId, RunRecord, Store, StoreError};
use serde::{Deserialize, Serialize};

/// "2026-11-25T17:39:03Z": ISO 8601, UTC, to the second, from µs since the Unix epoch.
pub fn iso_utc(unix_us: i64) -> String {
    crate::util::time::rfc3339(unix_us.div_euclid(1_000_000))
}

/// One run as `run list` shows it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunSummary {
    pub id: i64,
    /// When it was created, ISO 8601 UTC.
    pub date: String,
    pub created_us: i64,
    pub axis: String,
    /// The plan's travel (mm), when the plan says.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub end_mm: Option<f64>,
    /// "11 targets, 5 runs, 2 s dwell, 3000 mm/min".
    pub plan: String,
    /// Bidirectional runs in the plan.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub runs: Option<u64>,
    pub captures: usize,
    pub notes: String,
    /// Who started it (from the audit log), when known.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub operator: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<i64>,
    /// "none", "unknown (why)", "not recorded" or the active tables.
    pub tables_active: String,
    pub state: String,
}

fn plan_summary(plan: &serde_json::Value) -> (Option<f64>, Option<f64>, Option<u64>, String) {
    let spec = plan.get("spec").unwrap_or(plan);
    let f = |k: &str| spec.get(k).and_then(serde_json::Value::as_f64);
    let targets = plan
        .get("targets")
        .and_then(serde_json::Value::as_array)
        .map(Vec::len)
        .or_else(|| {
            spec.get("targets")
                .and_then(serde_json::Value::as_u64)
                .map(|n| n as usize)
        });
    let runs = spec.get("runs").and_then(serde_json::Value::as_u64);
    let mut parts = Vec::new();
    if let Some(t) = targets {
        parts.push(format!("{t} targets"));
    }
    if let Some(r) = runs {
        parts.push(format!("{r} runs"));
    }
    if let Some(d) = f("dwell_s") {
        parts.push(format!("{d} s dwell"));
    }
    if let Some(v) = f("feed_mm_min") {
        parts.push(format!("{v} mm/min"));
    }
    let text = if parts.is_empty() {
        "plan not readable".into()
    } else {
        parts.join(", ")
    };
    (f("start_mm"), f("end_mm"), runs, text)
}

impl Store {
    /// Every run, oldest first, summarised for finding it later.
    pub fn run_summaries(&self) -> Result<Vec<RunSummary>, StoreError> {
        let runs = self.list_runs()?;
        let operators = self.run_operators()?;
        runs.iter()
            .map(|r| self.summary(r, operators.iter().find(|(id, _)| *id == r.id)))
            .collect()
    }

    fn summary(
        &self,
        r: &RunRecord,
        operator: Option<&(RunId, String)>,
    ) -> Result<RunSummary, StoreError> {
        let (start_mm, end_mm, runs, plan) = plan_summary(&r.plan);
        let tables_active = match self.run_tables(r.id)? {
            Some(t) => t.summary(),
            None => "not recorded".into(),
        };
        Ok(RunSummary {
            id: r.id.0,
            date: iso_utc(r.created_us),
            created_us: r.created_us,
            axis: r.axis.clone(),
            start_mm,
            end_mm,
            plan,
            runs,
            captures: self.captures(r.id)?.len(),
            notes: r.notes.clone(),
            operator: operator.map(|(_, u)| u.clone()),
            calibration: r.calibration.map(|c| c.0),
            tables_active,
            state: r.state.as_str().into(),
        })
    }

    /// Who started each run: the audit log's `run_start` entries matched to the runs created
    /// right after them (the entry is written before the request is handled).
    fn run_operators(&self) -> Result<Vec<(RunId, String)>, StoreError> {
        let what = "read who started the runs";
        let mut stmt = self
            .conn
            .prepare_cached(
                "SELECT r.id, (SELECT a.user FROM audit a \
                   WHERE a.unix_us <= r.created_us AND a.user IS NOT NULL \
                   AND a.action = 'run_start' \
                   ORDER BY a.unix_us DESC LIMIT 1) FROM runs r ORDER BY r.id",
            )
            .map_err(|e| self.fail(what, e))?;
        let rows: Vec<(i64, Option<String>)> = stmt
            .query_map([], |r| Ok((r.get(0)?, r.get(1)?)))
            .and_then(|rows| rows.collect())
            .map_err(|e| self.fail(what, e))?;
        Ok(rows
            .into_iter()
            .filter_map(|(id, u)| u.map(|u| (RunId(id), u)))
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn iso_dates_are_utc_civil_dates() {
        assert_eq!(iso_utc(0), "1970-01-01T00:00:00Z");
        // 2026-11-25T17:39:03Z = 1 795 628 343 s (date -u -d @1795628343).
        assert_eq!(iso_utc(1_795_628_343_000_000), "2026-11-25T17:39:03Z");
        // A leap day, and before the epoch.
        assert_eq!(iso_utc(951_782_400_000_000), "2000-02-29T00:00:00Z");
        assert_eq!(iso_utc(-1_000_000), "1969-12-31T23:59:59Z");
    }

    #[test]
    fn a_plan_reads_as_a_line() {
        let p = serde_json::json!({"spec": {"axis": "X", "start_mm": 0.0, "end_mm": 200.0,
            "targets": 6, "runs": 2, "dwell_s": 2.0, "feed_mm_min": 3000.0},
            "targets": [0.0, 40.0, 80.0, 120.0, 160.0, 200.0], "reference_mm": 0.0});
        let (a, b, runs, text) = plan_summary(&p);
        assert_eq!((a, b, runs), (Some(0.0), Some(200.0), Some(2)));
        assert_eq!(text, "6 targets, 2 runs, 2 s dwell, 3000 mm/min");
        assert_eq!(plan_summary(&serde_json::json!({})).3, "plan not readable");
    }
}
