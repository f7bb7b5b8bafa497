//! An axis's six component errors from what the head measured on it: the mean of both
//! directions at each target (the reversal is the axis compensation's, not the volumetric
//! model's), put on the machine by the head's mounting, each straightness taken from its
//! least-squares line (the beam's pointing and the axis's reference line cannot be told
//! apart on one axis: the squarenesses carry the lines, measured with an optical square).
//! Positioning and the angles stay relative to the zero, where the head took it.

use super::error::MachineError;
use super::model::ComponentTable;
use crate::comp::mapping::AxisMapping;
use crate::evaluate::iso230_1::fit_line;
use crate::evaluate::{AxisEvaluation, ReferenceLine};

/// `axis`' table from the head's errors (mm, rad; `Errors6` order, relative to the zero) at
/// `positions_mm`, the head mounted as `mapping` says.
pub fn table_from_head(
    mapping: &AxisMapping,
    positions_mm: &[f64],
    head: &[[f64; 6]],
) -> Result<ComponentTable, MachineError> {
    let axis = mapping.axis();
    if positions_mm.len() != head.len() {
        return Err(MachineError::Table {
            axis,
            problem: format!(
                "{} positions but {} rows of the head's errors",
                positions_mm.len(),
                head.len()
            ),
        });
    }
    let mut rows: Vec<[f64; 6]> = head
        .iter()
        .map(|e| {
            let t = mapping.to_machine([e[0], e[1], e[2]]);
            let r = mapping.to_machine([e[3], e[4], e[5]]);
            [t[0], t[1], t[2], r[0], r[1], r[2]]
        })
        .collect();
    for k in (0..3).filter(|&k| k != axis.index()) {
        let values: Vec<f64> = rows.iter().map(|r| r[k]).collect();
        // Positions that do not spread fit no line: the table refuses them below.
        if let Some(line) = fit_line(positions_mm, &values, ReferenceLine::LeastSquares) {
            for (r, v) in rows.iter_mut().zip(line.residuals) {
                r[k] = v;
            }
        }
    }
    ComponentTable::new(axis, positions_mm.to_vec(), rows)
}

/// `table_from_head` of an evaluated run: the mean of both directions at each target.
pub fn table_from_evaluation(
    mapping: &AxisMapping,
    eval: &AxisEvaluation,
) -> Result<ComponentTable, MachineError> {
    if eval.profiles.len() < 6 {
        return Err(MachineError::Missing(format!(
            "the run's evaluation holds {} of the six errors: the table needs all six",
            eval.profiles.len()
        )));
    }
    let head: Vec<[f64; 6]> = (0..eval.positions_mm.len())
        .map(|i| std::array::from_fn(|k| eval.profiles[k].mean[i]))
        .collect();
    table_from_head(mapping, &eval.positions_mm, &head)
}
