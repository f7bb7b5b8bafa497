//! What an acceptance report needs from the store, read without the service: the run, its
//! plan, captures and evaluation, the calibration it ran with, the operator who started it,
//! the follower map and the compensation tables active while it ran.

use crate::evaluate::axis::{AxisEvaluation, EvalOptions, ThermalConfig, evaluate_captures};
use crate::evaluate::recorded::Recorded;
use crate::evaluate::uncertainty::Budget;
use crate::run::{Capture, Plan};
use crate::store::{CalibrationRecord, PublicationOutcome, RunId, RunRecord, Store, StoreError};
use thiserror::Error;

/// Why a run's report data could not be read.
#[derive(Debug, Error)]
pub enum SourceError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("run {run}: {problem}")]
    Run { run: i64, problem: String },
}

/// A compensation table active in the PLC during a run.
#[derive(Clone, Debug, PartialEq)]
pub struct ActiveTable {
    /// The stored table, when the store has it (a run recorded by the demo's lab names the
    /// tables its twin PLC applied by sequence and CRC only).
    pub table_id: Option<i64>,
    pub kind: String,
    pub axis: String,
    pub sequence: u32,
    /// When it was published (µs since the Unix epoch).
    pub published_us: i64,
    pub source_run: Option<i64>,
    pub crc: u32,
}

/// Where the list of active tables comes from.
#[derive(Clone, Debug, PartialEq)]
pub enum ActiveTables {
    /// Recorded with the run when it started (read back from the PLC).
    Recorded(Vec<ActiveTable>),
    /// Inferred from the publication log: the last accepted publication of each kind and axis
    /// before the run started. The PLC may have been changed by other means since.
    Inferred(Vec<ActiveTable>),
}

/// The follower map in use, in brief.
#[derive(Clone, Debug, PartialEq)]
pub struct FollowerMapInfo {
    pub id: i64,
    pub name: String,
    pub source: String,
    pub created_us: i64,
}

/// One run as a report shows it.
#[derive(Clone, Debug)]
pub struct RunData {
    pub record: RunRecord,
    /// The validated plan, when the stored one parses.
    pub plan: Option<Plan>,
    pub captures: Vec<Capture>,
    pub eval: AxisEvaluation,
    /// Its uncertainty budget (ISO/TR 230-9), when one was made.
    pub budget: Option<Budget>,
    pub calibration: Option<CalibrationRecord>,
    /// Who started the run (from the audit log), when known.
    pub operator: Option<String>,
    pub tables: ActiveTables,
    /// What the run recorded of its budget's inputs when it started (the follower map it
    /// used among them).
    pub recorded: Recorded,
}

/// Read run `id` and evaluate it; positioning is normalised to 20 °C with
/// `expansion_um_per_m_k` about the plan's reference point when it is given.
pub fn run_data(
    store: &Store,
    id: RunId,
    expansion_um_per_m_k: Option<f64>,
) -> Result<RunData, SourceError> {
    let record = store.run(id)?;
    let captures = store.captures(id)?;
    if captures.is_empty() {
        return Err(SourceError::Run {
            run: id.0,
            problem: "has no captures: nothing to report (was it started?)".into(),
        });
    }
    let plan: Option<Plan> = serde_json::from_value(record.plan.clone()).ok();
    let reference_mm = plan
        .as_ref()
        .map(|p| p.reference_mm)
        .or_else(|| captures.iter().map(|c| c.target_mm).reduce(f64::min))
        .unwrap_or(0.0);
    let opts = EvalOptions {
        thermal: expansion_um_per_m_k.map(|alpha| ThermalConfig {
            alpha_um_per_m_k: alpha,
            reference_mm,
        }),
    };
    let eval = evaluate_captures(&captures, &opts).map_err(|e| SourceError::Run {
        run: id.0,
        problem: format!("cannot be evaluated: {e}"),
    })?;
    let calibration = match record.calibration {
        Some(c) => store.calibrations()?.into_iter().find(|r| r.id == c),
        None => None,
    };
    let operator = operator(store, &record)?;
    let tables = active_tables(store, &record)?;
    let recorded = Recorded::of_config(&record.config);
    Ok(RunData {
        record,
        plan,
        captures,
        eval,
        budget: None,
        calibration,
        operator,
        tables,
        recorded,
    })
}

/// The user whose `run_start` request was logged last before the run was created (within a
/// minute).
fn operator(store: &Store, r: &RunRecord) -> Result<Option<String>, StoreError> {
    Ok(store
        .audit_entries(100_000)?
        .into_iter()
        .map(|a| a.entry)
        .filter(|e| {
            e.action == "run_start"
                && e.unix_us <= r.created_us
                && r.created_us - e.unix_us <= 60_000_000
        })
        .max_by_key(|e| e.unix_us)
        .and_then(|e| e.who.user))
}

/// The tables active during the run: as recorded when it started (read from the PLC), or,
/// for a run made before runs recorded them or when the PLC could not be read, inferred from
/// the publication log.
fn active_tables(store: &Store, r: &RunRecord) -> Result<ActiveTables, StoreError> {
    let tables = store.tables()?;
    if let Some(rt) = store.run_tables(r.id)?
        && rt.known
    {
        let publications = store.publications(None)?;
        let recorded = rt
            .tables
            .iter()
            .map(|a| {
                let id = a.table.map_or(0, |t| t.0);
                let stored = tables.iter().find(|t| t.id.0 == id);
                let published_us = publications
                    .iter()
                    .map(|p| &p.publication)
                    .filter(|p| p.table.0 == id && p.sequence == a.sequence)
                    .map(|p| p.unix_us)
                    .max()
                    .unwrap_or(rt.unix_us);
                ActiveTable {
                    table_id: a.table.map(|t| t.0),
                    kind: a.kind.clone(),
                    axis: a.axis.clone(),
                    sequence: a.sequence,
                    published_us,
                    source_run: stored.and_then(|t| t.entry.source_run.map(|r| r.0)),
                    crc: a.crc,
                }
            })
            .collect();
        return Ok(ActiveTables::Recorded(recorded));
    }
    let mut latest: Vec<ActiveTable> = Vec::new();
    for p in store.publications(None)? {
        let p = p.publication;
        if p.outcome != PublicationOutcome::Accepted || p.unix_us > r.created_us {
            continue;
        }
        let Some(t) = tables.iter().find(|t| t.id == p.table) else {
            continue;
        };
        let a = ActiveTable {
            table_id: Some(t.id.0),
            kind: t.entry.kind.clone(),
            axis: t.entry.axis.clone(),
            sequence: p.sequence,
            published_us: p.unix_us,
            source_run: t.entry.source_run.map(|r| r.0),
            crc: t.entry.crc,
        };
        match latest
            .iter_mut()
            .find(|x| x.kind == a.kind && x.axis == a.axis)
        {
            Some(x) if x.published_us <= a.published_us => *x = a,
            Some(_) => {}
            None => latest.push(a),
        }
    }
    latest.sort_by(|a, b| (&a.axis, &a.kind).cmp(&(&b.axis, &b.kind)));
    Ok(ActiveTables::Inferred(latest))
}

/// The follower map in use now, if any.
pub fn follower_map(store: &Store) -> Result<Option<FollowerMapInfo>, StoreError> {
    Ok(store.follower_map_in_use()?.map(|m| FollowerMapInfo {
        id: m.id,
        name: m.name,
        source: m.source,
        created_us: m.created_us,
    }))
}
