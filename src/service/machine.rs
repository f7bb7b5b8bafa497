//! The whole machine's requests (issue 27), answered from the store off the loop: the stored
//! machines, one machine's plan and fit (`commission::stored`) as the API's views, a record
//! stored, a run attached to or detached from a set-up.

use super::api::machine::{MachineSummary, MachineView, PredictedView, SetupView, SquarenessView};
use crate::commission::plan::{self, SETUPS, SetupState};
use crate::commission::stored::{self, MachineState};
use crate::machine::{MachineModel, volume};
use crate::store::{Store, iso_utc};
use crate::units::RAD_PER_ARCSEC;

/// The stored machines, newest first.
pub fn list(store: &Store) -> Result<Vec<MachineSummary>, String> {
    let machines = store.machines().map_err(|e| e.to_string())?;
    machines
        .into_iter()
        .map(|m| {
            // What is attached, not fitted: a list does not evaluate every machine's runs.
            let attached = stored::attached(store, m.id).map_err(|e| e.to_string())?;
            Ok(MachineSummary {
                id: m.id,
                name: m.name,
                created: iso_utc(m.created_us),
                measured: attached.iter().flatten().count(),
                setups: SETUPS.len(),
                next: plan::states(&attached)
                    .iter()
                    .position(|st| *st == SetupState::Next)
                    .map(plan::title),
            })
        })
        .collect()
}

/// Machine `id`, or the newest.
pub fn view(store: &Store, id: Option<i64>) -> Result<MachineView, String> {
    let id = match id {
        Some(id) => id,
        None => store
            .machines()
            .map_err(|e| e.to_string())?
            .first()
            .map(|m| m.id)
            .ok_or("no machine is stored yet: store its record first (machine new FILE)")?,
    };
    let s = stored::state(store, id).map_err(|e| e.to_string())?;
    Ok(machine_view(&s))
}

/// A machine's state as the API shows it.
pub fn machine_view(s: &MachineState) -> MachineView {
    let r = &s.record;
    let setups = SETUPS
        .iter()
        .enumerate()
        .map(|(i, (axis, _))| {
            let p = plan::run_plan(r, i);
            SetupView {
                number: i + 1,
                title: plan::title(i),
                axis: axis.to_string(),
                state: match s.states[i] {
                    SetupState::Measured { .. } => "measured",
                    SetupState::Next => "next",
                    SetupState::Waiting => "waiting",
                }
                .into(),
                run_id: s.attached[i],
                steps: plan::steps(r, i),
                plan: p,
                run_notes: plan::run_notes(s.id, i),
            }
        })
        .collect();
    let squareness = match &s.fit {
        Ok(f) => f
            .squareness
            .iter()
            .map(|q| SquarenessView {
                pair: q.pair.to_string(),
                name: q.pair.name().into(),
                value_arcsec: q.value_rad / RAD_PER_ARCSEC,
                expanded_arcsec: q.expanded_rad / RAD_PER_ARCSEC,
                square: r.squares[q.pair.index()].id.clone(),
            })
            .collect(),
        Err(_) => Vec::new(),
    };
    let (predicted, no_model) = match s.model() {
        Ok(m) => (Some(predicted(m, r.travel_mm, r.tool_mm)), None),
        Err(why) => (None, Some(why)),
    };
    MachineView {
        id: s.id,
        name: r.name.clone(),
        chain: r.chain.to_string(),
        travel_mm: r.travel_mm,
        tool_mm: r.tool_mm,
        created: iso_utc(s.created_us),
        setups,
        squareness,
        predicted,
        no_model,
    }
}

/// The model's error of the tool point, uncompensated, on a regular grid over the volume.
pub fn predicted(model: &MachineModel, travel_mm: [f64; 3], tool_mm: [f64; 3]) -> PredictedView {
    let s = volume::survey(model, None, travel_mm, tool_mm);
    PredictedView {
        points: s.points,
        tool_mm,
        max_um: s.max_mm * 1e3,
        rms_um: s.rms_mm * 1e3,
        at_mm: s.at_mm,
    }
}

/// The machine record's text from its file on this host (at most 64 KiB), or why not.
pub fn read_record(path: &str) -> Result<String, String> {
    let too_big = || format!("{path}: a machine record is a short TOML file (64 KiB at most)");
    match std::fs::metadata(path) {
        Ok(m) if m.len() > 64 * 1024 => return Err(too_big()),
        Ok(m) if !m.is_file() => {
            return Err(format!(
                "{path}: not a file; give the path of the machine's record (TOML) on the service's host"
            ));
        }
        _ => {}
    }
    std::fs::read_to_string(path).map_err(|e| {
        format!(
            "{path}: cannot read the machine record ({e}); give the path of its TOML file on the service's host"
        )
    })
}

/// Store a machine from its record's text; its view.
pub fn create(store: &mut Store, text: &str, origin: &str) -> Result<MachineView, String> {
    let id = stored::create(store, text, origin, crate::util::clock::unix_us())
        .map_err(|e| e.to_string())?;
    view(store, Some(id))
}

/// Attach a run to a set-up (1-based); the machine's view after it.
pub fn attach(store: &mut Store, id: i64, setup: usize, run: i64) -> Result<MachineView, String> {
    let index = setup
        .checked_sub(1)
        .ok_or("\"setup\": the set-ups are numbered from 1")?;
    stored::attach(store, id, index, run, crate::util::clock::unix_us())
        .map_err(|e| e.to_string())?;
    view(store, Some(id))
}

/// Detach a set-up's run (1-based) and those after it; the machine's view after it.
pub fn detach(store: &mut Store, id: i64, setup: usize) -> Result<MachineView, String> {
    let index = setup
        .checked_sub(1)
        .ok_or("\"setup\": the set-ups are numbered from 1")?;
    stored::detach(store, id, index, crate::util::clock::unix_us()).map_err(|e| e.to_string())?;
    view(store, Some(id))
}
