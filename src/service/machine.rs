//! The whole machine's requests (issue 27), answered from the store off the loop: the stored
//! machines, one machine's plan and fit (`commission::stored`) as the API's views, a record
//! stored, a run attached to or detached from a set-up.

use super::api::machine::{MachineSummary, MachineView, PredictedView, SetupView, SquarenessView};
use crate::commission::plan::{self, SETUPS, SetupState};
use crate::commission::stored::{self, MachineState};
use crate::machine::MachineModel;
use crate::store::{Store, iso_utc};
use crate::units::RAD_PER_ARCSEC;

/// Points a side of the grid the model's prediction is taken on.
const GRID_SIDE: usize = 11;

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
    let (mut max, mut sum2, mut at, mut n) = (0.0f64, 0.0, [0.0; 3], 0usize);
    let step = |k: usize, i: usize| travel_mm[k] * i as f64 / (GRID_SIDE - 1) as f64;
    for i in 0..GRID_SIDE {
        for j in 0..GRID_SIDE {
            for l in 0..GRID_SIDE {
                let p = [step(0, i), step(1, j), step(2, l)];
                let e = model.error_at(p, tool_mm);
                let norm = (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]).sqrt();
                sum2 += norm * norm;
                n += 1;
                if norm > max {
                    (max, at) = (norm, p);
                }
            }
        }
    }
    PredictedView {
        points: n,
        tool_mm,
        max_um: max * 1e3,
        rms_um: (sum2 / n.max(1) as f64).sqrt() * 1e3,
        at_mm: at,
    }
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
