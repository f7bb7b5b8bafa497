//! Beckhoff TwinCAT CNC (ISG kernel) leadscrew error compensation list (`kw.ssfk.*`).
//!
//! One ASCII compensation value list per axis (TF5200 Axis compensation parameters, "Leadscrew
//! error compensation (kw.ssfk.*)" and "Example of a compensation value list", Beckhoff
//! Information System):
//! - header `kopf.achs_nr` (logical axis number) and `kopf.log_achs_name`;
//! - `kw.ssfk.interval` 0 (non-equidistant: every point's `kw.ssfk.table[i].setpoint` is given,
//!   as in the manual's example), `kw.ssfk.kw_startpos`, `kw.ssfk.kw_nr_max` (the number of
//!   entries, P-COMP-00020), `kw.ssfk.unit 1` (as in the example), `kw.ssfk.bilateral` (0: one
//!   table for both directions, 1: `pos` and `neg` per point, P-COMP-00021);
//! - `kw.ssfk.table[i].pos` / `.neg` (P-COMP-00023/24). All lengths in 0.1 µm.
//! - Limit: at most 1500 entries (the default of P-COMP-00059 `kw.ssfk.max_points`, and the
//!   fixed maximum before CNC build V3.1.3079.06).
//!
//! Sign: the example computes the compensation value as Δs = s_actual − s_setpoint (measured −
//! programmed): value = +e, in 0.1 µm ("Example – Non-equidistant bilateral SSFK": 19856.5 µm
//! measured at 19866.7 µm programmed gives pos −102). The CNC corrects the setpoint by it and
//! removes it from the displayed actual value.
//!
//! Unconfirmed: the `#` comment lines of the header (the manual has a page on comments in the
//! ASCII file that was not read) and the meaning of `unit` 1 (copied from the example).

use super::table::{CompTable, GridLimits, TableValues};
use super::{CompError, Exported, check_identifier, trimmed};
use std::fmt::Write;

/// 0.1 µm in mm.
pub const UNIT_MM: f64 = 1e-4;
/// Default and former fixed maximum of entries.
pub const MAX_POINTS: usize = 1500;

/// Options.
#[derive(Clone, Debug, PartialEq)]
pub struct SsfkOptions {
    /// Logical axis number (`kopf.achs_nr`).
    pub axis_number: u16,
    /// Logical axis name (`kopf.log_achs_name`).
    pub axis_name: String,
    /// P-COMP-00059 `kw.ssfk.max_points`.
    pub max_points: usize,
    pub step_mm: Option<f64>,
}

impl SsfkOptions {
    pub fn new(axis_number: u16, axis_name: &str) -> Self {
        SsfkOptions {
            axis_number,
            axis_name: axis_name.into(),
            max_points: MAX_POINTS,
            step_mm: None,
        }
    }
}

fn units(mm: f64) -> i64 {
    (mm / UNIT_MM).round() as i64
}

/// The compensation value list for a positioning table: bilateral when the table has two
/// directions (or a backlash, folded into `neg`).
pub fn ssfk(table: &CompTable, o: &SsfkOptions) -> Result<Exported, CompError> {
    const F: &str = "Beckhoff SSFK";
    check_identifier("axis_name", &o.axis_name)?;
    super::own_axis(
        table,
        F,
        "leadscrew compensation acts on the axis's own position (use kw.crosscomp)",
    )?;
    let (t, grid) = super::measured_or_grid(
        F,
        table,
        &GridLimits {
            step_quantum_mm: UNIT_MM,
            ..GridLimits::points(o.max_points, o.step_mm)
        },
        format!("P-COMP-00059 kw.ssfk.max_points = {}", o.max_points),
        "comp.beckhoff.max_points (--max-points) with P-COMP-00059",
    )?;
    let bilateral = !matches!(
        &t.values,
        TableValues::Single {
            backlash_mm: None,
            ..
        }
    );
    let rev = t.reverse();
    let mut out = String::new();
    let _ = writeln!(
        out,
        "# axiscomp leadscrew error compensation: {} ({} of {}), value = e = measured - setpoint, 0.1 um",
        t.name,
        t.kind.name(),
        t.comp_axis
    );
    let _ = writeln!(
        out,
        "# zero at the reference point {} mm; activate with P-AXIS-00175 lr_param.ssfk = 1",
        trimmed(t.reference_mm, 4)
    );
    let _ = writeln!(out, "kopf.achs_nr                 {}", o.axis_number);
    let _ = writeln!(out, "kopf.log_achs_name           {}", o.axis_name);
    let _ = writeln!(out, "kw.ssfk.interval             0");
    let _ = writeln!(
        out,
        "kw.ssfk.kw_startpos          {}",
        units(t.positions_mm[0])
    );
    let _ = writeln!(out, "kw.ssfk.kw_nr_max            {}", t.positions_mm.len());
    let _ = writeln!(out, "kw.ssfk.unit                 1");
    let _ = writeln!(out, "kw.ssfk.bilateral            {}", u8::from(bilateral));
    let _ = writeln!(out, "kw.ssfk.modulo               0");
    for (i, p) in t.positions_mm.iter().enumerate() {
        let _ = writeln!(out, "kw.ssfk.table[{i}].setpoint    {}", units(*p));
    }
    for (i, v) in t.primary().iter().enumerate() {
        let _ = writeln!(out, "kw.ssfk.table[{i}].pos         {}", units(*v));
    }
    if bilateral {
        for (i, v) in rev.iter().enumerate() {
            let _ = writeln!(out, "kw.ssfk.table[{i}].neg         {}", units(*v));
        }
    }
    Ok(Exported {
        text: out,
        table: t,
        grid,
    })
}
