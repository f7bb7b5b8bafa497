//! A stored machine as the service, the command line and the console show it (issue 27): its
//! record, each set-up's state and run, each set-up's six errors and slopes from its stored
//! run (evaluated and budgeted as a report does, `report::source` and `report::budget`), the
//! squarenesses measured so far and, when every set-up is measured, the 21-error model. A run
//! is attached to a set-up only when it can stand for it: finished, on the set-up's axis, over
//! its travel, no flag open (issue 24: nothing flagged reaches a table), its budget's inputs
//! recorded.

use super::fit::{MachineFit, MeasuredSetup, fit};
use super::plan::{self, SETUPS, SetupState};
use super::record::{MachineRecord, RecordError};
use crate::comp::mapping::AxisMapping;
use crate::evaluate::uncertainty::Budget;
use crate::machine::exports::TABLE_STEP_MM;
use crate::machine::from_head::table_from_evaluation;
use crate::machine::squareness::SetupSlopes;
use crate::machine::{MachineError, MachineModel};
use crate::report::budget::{Fallbacks, run_budget};
use crate::report::source::{RunData, SourceError, run_data};
use crate::store::{RunId, Store, StoreError, StoredMachine};
use thiserror::Error;

/// Why a machine could not be read, stored or fitted, or a run not attached.
#[derive(Debug, Error)]
pub enum CommissionError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    Source(#[from] SourceError),
    #[error(transparent)]
    Record(#[from] RecordError),
    #[error("machine {machine}: {source}")]
    Machine {
        machine: i64,
        #[source]
        source: MachineError,
    },
    #[error("run {run} {problem} (machine {machine}, set-up {title})")]
    Run {
        machine: i64,
        title: String,
        run: i64,
        problem: String,
    },
    #[error("machine {machine}: {problem}")]
    Refused { machine: i64, problem: String },
    #[error(transparent)]
    Report(#[from] crate::report::ReportError),
    /// The machine has no model yet; the message names it and what is missing.
    #[error("{0}")]
    NoModel(String),
}

/// Store a machine from its record's text (checked first); its id.
pub fn create(
    store: &mut Store,
    text: &str,
    origin: &str,
    unix_us: i64,
) -> Result<i64, CommissionError> {
    let record = MachineRecord::from_toml(text, origin)?;
    Ok(store.create_machine(&record.name, &record.to_toml(), unix_us)?)
}

/// Machine `id`'s record, read back and checked.
pub fn record(stored: &StoredMachine) -> Result<MachineRecord, CommissionError> {
    Ok(MachineRecord::from_toml(
        &stored.record_toml,
        &format!("of machine {} in the store", stored.id),
    )?)
}

/// The runs in force on each set-up.
pub fn attached(store: &Store, machine: i64) -> Result<[Option<i64>; 4], CommissionError> {
    let runs = store.machine_setups(machine, SETUPS.len())?;
    Ok(std::array::from_fn(|i| {
        runs.get(i).copied().flatten().map(|r| r.0)
    }))
}

/// A stored run that can stand for a set-up: its data, evaluated, and its budget.
pub struct SetupRun {
    /// The set-up (0-based, [`SETUPS`] order) and the run.
    pub setup: usize,
    pub run: i64,
    pub data: RunData,
    pub budget: Budget,
}

/// Stored run `run` as set-up `setup` of `record` takes it, or why it cannot stand for the
/// set-up.
pub fn setup_run(
    store: &Store,
    machine: i64,
    record: &MachineRecord,
    setup: usize,
    run: i64,
) -> Result<SetupRun, CommissionError> {
    let title = plan::title(setup);
    let refuse = |problem: String| CommissionError::Run {
        machine,
        title: title.clone(),
        run,
        problem,
    };
    let (axis, _) = plan::setup_at(setup);
    let rec = store.run(RunId(run))?;
    if rec.state.as_str() != "finished" {
        return Err(refuse(format!(
            "is {}: attach a finished run",
            rec.state.as_str()
        )));
    }
    if !rec.axis.eq_ignore_ascii_case(&axis.to_string()) {
        return Err(refuse(format!(
            "measured axis {}: this set-up measures {axis}",
            rec.axis
        )));
    }
    // A run started from the plan names its set-up; it stands for no other.
    if let Some(k) = plan::setup_named(&rec.notes)
        && k != setup
    {
        return Err(refuse(format!(
            "was measured for set-up {} (its notes: \"{}\"): attach it there",
            plan::title(k),
            rec.notes
        )));
    }
    if let Some(why) = store.open_flags(RunId(run))? {
        return Err(refuse(format!(
            "has flags open ({why}): retake or exclude them first (run flags)"
        )));
    }
    let data = run_data(store, RunId(run), None)?;
    let travel = record.travel_mm[axis.index()];
    let (lo, hi) = data
        .eval
        .positions_mm
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        });
    // A table that does not span the travel leaves the model to extrapolate.
    let slack = record.target_every_mm;
    if lo > slack || hi < travel - slack {
        return Err(refuse(format!(
            "covers {lo:.1}–{hi:.1} mm: the set-up needs {axis}'s travel, 0–{travel:.0} mm (within one target spacing, {slack:.0} mm, at each end)"
        )));
    }
    let sensitivity = data
        .recorded
        .budget()
        .and_then(|r| r.psd2_sensitivity)
        .ok_or_else(|| {
            refuse(
                "did not record its budget's inputs (PSD2's sensitivities): a squareness needs its budget; measure the set-up again with this version".into(),
            )
        })?;
    let fb = Fallbacks {
        psd2_sensitivity: sensitivity,
        follower_spec: None,
    };
    let budget = run_budget(store, &data, &fb)?;
    Ok(SetupRun {
        setup,
        run,
        data,
        budget,
    })
}

/// What set-up `setup` of `record` takes from stored run `run`: its table and slopes, or why
/// the run cannot stand for the set-up ([`setup_run`]).
pub fn measured_setup(
    store: &Store,
    machine: i64,
    record: &MachineRecord,
    setup: usize,
    run: i64,
) -> Result<MeasuredSetup, CommissionError> {
    measured_of(machine, &setup_run(store, machine, record, setup, run)?)
}

/// What a set-up's run gives the fit: its axis's table and its slopes.
fn measured_of(machine: i64, r: &SetupRun) -> Result<MeasuredSetup, CommissionError> {
    let (axis, _) = plan::setup_at(r.setup);
    let machine_err = |source| CommissionError::Machine { machine, source };
    // The head mounted as the standard mounting says (`AxisMapping::standard`): its y along
    // the axis, x and z as the commissioning plan's steps set it.
    let mapping = AxisMapping::standard(axis);
    let measured = table_from_evaluation(&mapping, &r.data.eval).map_err(machine_err)?;
    let table = measured.refined(TABLE_STEP_MM).map_err(machine_err)?;
    let slopes =
        SetupSlopes::from_evaluation(mapping, &r.data.eval, &r.budget).map_err(machine_err)?;
    Ok(MeasuredSetup { table, slopes })
}

/// A stored machine and where it stands.
#[derive(Clone, Debug)]
pub struct MachineState {
    pub id: i64,
    pub record: MachineRecord,
    pub created_us: i64,
    /// The run in force on each set-up.
    pub attached: [Option<i64>; 4],
    pub states: [SetupState; 4],
    /// The squarenesses and the model so far, or why they could not be fitted.
    pub fit: Result<MachineFit, String>,
}

impl MachineState {
    /// The runs attached, in the plan's order: "1, 2, 3, 4".
    pub fn runs_words(&self) -> String {
        let runs: Vec<String> = self.attached.iter().flatten().map(i64::to_string).collect();
        runs.join(", ")
    }

    /// The model, or why there is none yet.
    pub fn model(&self) -> Result<&MachineModel, String> {
        match &self.fit {
            Err(e) => Err(e.clone()),
            Ok(f) => f.model.as_ref().ok_or_else(|| {
                let missing: Vec<String> = (0..SETUPS.len())
                    .filter(|&i| self.attached[i].is_none())
                    .map(plan::title)
                    .collect();
                format!(
                    "machine {} is not measured yet: {} to go ({})",
                    self.id,
                    missing.len(),
                    missing.join("; ")
                )
            }),
        }
    }
}

/// Machine `id` as stored, fitted from its set-ups' runs.
pub fn state(store: &Store, id: i64) -> Result<MachineState, CommissionError> {
    Ok(state_with_runs(store, id)?.0)
}

/// Machine `id` as [`state`] gives it, with the attached set-ups' runs it was fitted from
/// (those that could stand for their set-up), in the plan's order.
pub fn state_with_runs(
    store: &Store,
    id: i64,
) -> Result<(MachineState, Vec<SetupRun>), CommissionError> {
    let stored = store.machine(id)?;
    let record = record(&stored)?;
    let attached = attached(store, id)?;
    let mut setups: [Option<MeasuredSetup>; 4] = Default::default();
    let mut runs = Vec::new();
    let mut why = None;
    for (i, run) in attached.iter().enumerate() {
        if let Some(run) = *run {
            match setup_run(store, id, &record, i, run).and_then(|r| Ok((measured_of(id, &r)?, r)))
            {
                Ok((m, r)) => {
                    setups[i] = Some(m);
                    runs.push(r);
                }
                Err(e) => {
                    why.get_or_insert(e.to_string());
                }
            }
        }
    }
    let fit = match why {
        Some(w) => Err(w),
        None => fit(&record, &setups).map_err(|e| format!("machine {id}: {e}")),
    };
    let state = MachineState {
        id,
        record,
        created_us: stored.created_us,
        attached,
        states: plan::states(&attached),
        fit,
    };
    Ok((state, runs))
}

/// Attach run `run` to set-up `setup` (0-based) of machine `machine`: in the plan's order, and
/// only a run that can stand for the set-up ([`measured_setup`]).
pub fn attach(
    store: &mut Store,
    machine: i64,
    setup: usize,
    run: i64,
    unix_us: i64,
) -> Result<(), CommissionError> {
    let stored = store.machine(machine)?;
    let record = record(&stored)?;
    let attached = attached(store, machine)?;
    if let Some(problem) = plan::refuse_attach(&attached, setup) {
        return Err(CommissionError::Refused { machine, problem });
    }
    if let Some(i) = attached.iter().position(|r| *r == Some(run)) {
        return Err(CommissionError::Refused {
            machine,
            problem: format!(
                "run {run} already stands for set-up {}: each set-up needs its own run",
                plan::title(i)
            ),
        });
    }
    measured_setup(store, machine, &record, setup, run)?;
    store.set_machine_setup(machine, setup, Some(RunId(run)), unix_us)?;
    Ok(())
}

/// Detach the run from set-up `setup`, and from every set-up after it (they were taken with
/// its beam, or after it in the plan).
pub fn detach(
    store: &mut Store,
    machine: i64,
    setup: usize,
    unix_us: i64,
) -> Result<Vec<usize>, CommissionError> {
    store.machine(machine)?;
    if setup >= SETUPS.len() {
        return Err(CommissionError::Refused {
            machine,
            problem: format!("there is no set-up {}: 1 to {}", setup + 1, SETUPS.len()),
        });
    }
    let attached = attached(store, machine)?;
    let mut gone = Vec::new();
    for (i, run) in attached.iter().enumerate().skip(setup) {
        if run.is_some() {
            store.set_machine_setup(machine, i, None, unix_us)?;
            gone.push(i);
        }
    }
    Ok(gone)
}
