//! Our own formats: CSV and JSON, in µm, holding e = measured − nominal exactly as the table
//! has it (no resampling). For archives, reports and the PLC publication path.
//!
//! CSV: `#` metadata lines (`key: value`), then `position_mm,e_um` for a single profile or
//! `position_mm,e_up_um,e_down_um` for a bidirectional one; readable by `util::csv`.

use super::CompError;
use super::table::{CompTable, TableValues};
use crate::units::MM_PER_UM;
use serde::Serialize;
use std::fmt::Write;

/// µm decimals written (1 pm, i.e. the f64 value survives for any practical error).
const DECIMALS: usize = 6;

fn um(x: f64) -> String {
    super::fixed(x / MM_PER_UM, DECIMALS)
}

/// The table as CSV.
pub fn csv(t: &CompTable) -> String {
    let mut out = String::from("# axiscomp compensation table\n");
    let _ = writeln!(out, "# name: {}", t.name);
    let _ = writeln!(out, "# kind: {}", t.kind.name());
    let _ = writeln!(out, "# base_axis: {}", t.base_axis);
    let _ = writeln!(out, "# compensated_axis: {}", t.comp_axis);
    let _ = writeln!(out, "# reference_mm: {}", super::trimmed(t.reference_mm, 6));
    out.push_str("# values: e = measured - nominal (um), zero at the reference point\n");
    match &t.values {
        TableValues::Single {
            values,
            backlash_mm,
        } => {
            if let Some(b) = backlash_mm {
                let _ = writeln!(out, "# backlash_um: {}", um(*b));
            }
            out.push_str("position_mm,e_um\n");
            for (p, v) in t.positions_mm.iter().zip(values) {
                let _ = writeln!(out, "{},{}", super::trimmed(*p, 6), um(*v));
            }
        }
        TableValues::Bidirectional { up, down } => {
            out.push_str("position_mm,e_up_um,e_down_um\n");
            for ((p, u), d) in t.positions_mm.iter().zip(up).zip(down) {
                let _ = writeln!(out, "{},{},{}", super::trimmed(*p, 6), um(*u), um(*d));
            }
        }
    }
    out
}

#[derive(Serialize)]
struct JsonTable<'a> {
    name: &'a str,
    kind: &'a str,
    base_axis: &'a str,
    compensated_axis: &'a str,
    reference_mm: f64,
    sign: &'static str,
    unit: &'static str,
    positions_mm: &'a [f64],
    e_up_um: Vec<f64>,
    e_down_um: Option<Vec<f64>>,
    backlash_um: Option<f64>,
}

/// The table as JSON (`e_up_um` holds the single profile when there is one).
pub fn json(t: &CompTable) -> Result<String, CompError> {
    let to_um = |v: &[f64]| v.iter().map(|x| x / MM_PER_UM).collect::<Vec<f64>>();
    let (up, down, backlash) = match &t.values {
        TableValues::Single {
            values,
            backlash_mm,
        } => (to_um(values), None, backlash_mm.map(|b| b / MM_PER_UM)),
        TableValues::Bidirectional { up, down } => (to_um(up), Some(to_um(down)), None),
    };
    let j = JsonTable {
        name: &t.name,
        kind: t.kind.name(),
        base_axis: t.base_axis.letter(),
        compensated_axis: t.comp_axis.letter(),
        reference_mm: t.reference_mm,
        sign: "e = measured - nominal",
        unit: "um",
        positions_mm: &t.positions_mm,
        e_up_um: up,
        e_down_um: down,
        backlash_um: backlash,
    };
    serde_json::to_string_pretty(&j).map_err(|e| CompError::Unsupported {
        format: "JSON",
        problem: e.to_string(),
    })
}
