//! A run measured in the virtual-time lab, stored as the service stores a live one: the run
//! with its plan, its captures, its times by the twin's clock, finished, and the budget's
//! inputs it used with the follower map it applied (`report::budget::record_lab_run`), so
//! that a report, an export or a machine's commissioning reads it back as it would a live run.

use crate::evaluate::uncertainty::BudgetInputs;
use crate::follower::FollowerMap;
use crate::report::budget::record_lab_run;
use crate::report::source::SourceError;
use crate::run::{Capture, Plan};
use crate::store::{NewRun, RunId, RunState, RunTables, Store};

/// What a lab run is stored with.
pub struct LabRunRecord<'a> {
    pub plan: &'a Plan,
    /// The run's configuration snapshot (what the twin was).
    pub config: serde_json::Value,
    pub notes: String,
    pub captures: &'a [Capture],
    /// Its first and last moment by the twin's clock (µs since the Unix epoch).
    pub times_us: [i64; 2],
    /// The budget's inputs and the map the run applied, when it made a budget.
    pub budget: Option<(&'a BudgetInputs, Option<&'a FollowerMap>)>,
    /// What the twin's PLC applied while it ran, when known (`None`: not recorded).
    pub tables: Option<RunTables>,
    /// The calibration in the store the run decoupled with, if any.
    pub calibration: Option<crate::store::CalibrationId>,
}

/// Store `run`; its id.
pub fn store_lab_run(store: &mut Store, run: &LabRunRecord) -> Result<RunId, SourceError> {
    let id = store.create_run(&NewRun {
        axis: run.plan.spec.axis.clone(),
        plan: serde_json::to_value(run.plan).unwrap_or(serde_json::Value::Null),
        config: run.config.clone(),
        calibration: run.calibration,
        notes: run.notes.clone(),
    })?;
    store.set_run_state(id, RunState::Running)?;
    if let Some(t) = &run.tables {
        store.record_run_tables(id, t)?;
    }
    for c in run.captures {
        store.insert_capture(id, c)?;
    }
    store.set_run_state(id, RunState::Finished)?;
    // Dated by the twin's clock, as its captures are: the run's machine time.
    store.set_run_times(id, run.times_us[0], run.times_us[1])?;
    if let Some((inputs, map)) = run.budget {
        record_lab_run(store, id, inputs, map)?;
    }
    Ok(id)
}
