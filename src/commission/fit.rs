//! The 21-error model from the measured set-ups (issue 27): each squareness from the two
//! set-ups that share its square's beam, as soon as both are measured; the model when every
//! set-up is: X, Y and the first Z set-up's tables (each axis's six errors) and the three
//! squarenesses.

use super::plan::{Beam, MODEL_SETUPS, SETUPS};
use super::record::MachineRecord;
use crate::machine::squareness::{self, MeasuredSquareness, SetupSlopes};
use crate::machine::{ComponentTable, MachineError, MachineModel, Squareness};

/// What one set-up measured: its axis's table (refined for the control) and its straightness
/// slopes against its beam.
#[derive(Clone, Debug)]
pub struct MeasuredSetup {
    pub table: ComponentTable,
    pub slopes: SetupSlopes,
}

/// The machine as far as it is measured.
#[derive(Clone, Debug)]
pub struct MachineFit {
    /// Each squareness whose two set-ups are measured, in the plan's order.
    pub squareness: Vec<MeasuredSquareness>,
    /// The 21 errors, when every set-up is measured.
    pub model: Option<MachineModel>,
}

/// Fit what the measured set-ups give (`setups[i]` for `SETUPS[i]`, `None` when not measured).
pub fn fit(
    record: &MachineRecord,
    setups: &[Option<MeasuredSetup>; 4],
) -> Result<MachineFit, MachineError> {
    let mut squareness = Vec::new();
    let mut values = [None; 3];
    for (i, (_, beam)) in SETUPS.iter().enumerate() {
        let Beam::Through(pair, from) = *beam else {
            continue;
        };
        let (Some(first), Some(second)) = (&setups[from], &setups[i]) else {
            continue;
        };
        let sq = squareness::measure(
            pair,
            &first.slopes,
            &second.slopes,
            &record.squares[pair.index()],
            None,
        )?;
        values[pair.index()] = Some(sq.value_rad);
        squareness.push(sq);
    }
    let model = match (values, setups.iter().all(Option::is_some)) {
        ([Some(c0y), Some(b0z), Some(a0z)], true) => {
            let tables = setups
                .iter()
                .take(MODEL_SETUPS)
                .flatten()
                .map(|s| s.table.clone())
                .collect();
            Some(MachineModel::new(
                record.chain,
                tables,
                Squareness::from_array([c0y, b0z, a0z]),
            )?)
        }
        _ => None,
    };
    Ok(MachineFit { squareness, model })
}
