//! SINUMERIK 840D sl interpolatory compensation (Function Manual Extended Functions, K3).
//!
//! - Leadscrew/measuring system error compensation (LEC/MSEC): an NC program
//!   `%_N_AX_EEC_INI` with `CHANDATA(1)`, one `$AA_ENC_COMP[<encoder>,<N>,<axis>]=<mm>` per
//!   interpolation point, then `$AA_ENC_COMP_STEP`, `_MIN`, `_MAX` (mm) and `_IS_MODULO`, ended
//!   by `M17`. Points = (MAX − MIN)/STEP + 1 ≤ MD38000 `$MA_MM_ENC_COMP_MAX_POINTS`. Not
//!   direction-dependent; the backlash goes to MD32450 `$MA_BACKLASH` (written as a comment).
//! - Sag/angularity compensation (CEC): `%_N_NC_CEC_INI`, `$AN_CEC[<t>,<N>]=<mm>` with
//!   `$AN_CEC_INPUT_AXIS[t]=(<base>)`, `$AN_CEC_OUTPUT_AXIS[t]=(<comp>)`, `$AN_CEC_STEP`, `_MIN`,
//!   `_MAX`, `$AN_CEC_DIRECTION[t]` (0 both, 1 positive, −1 negative traverse),
//!   `$AN_CEC_MULT_BY_TABLE[t]=0`, `$AN_CEC_IS_MODULO[t]=0`; points ≤ MD18342
//!   `$MN_MM_CEC_MAX_POINTS[t]`. A bidirectional table becomes two tables (t: DIRECTION 1,
//!   t + 1: DIRECTION −1).
//!
//! Value = +e (mm): "a positive compensation value causes the corresponding machine axis to
//! move in the negative direction". The table is zero at the reference point, as K3 asks, so
//! activating it after referencing makes no jump. Comments are ASCII (`;`).

use super::table::{CompTable, GridLimits, TableKind, TableValues, fit_grid};
use super::{CompError, Exported, check_identifier, trimmed};
use std::fmt::Write;

/// Decimals of mm written (0.1 nm: below any measuring-system resolution, so no rounding bias).
const DECIMALS: usize = 7;

/// LEC options.
#[derive(Clone, Debug, PartialEq)]
pub struct LecOptions {
    /// The machine axis name in the NC (e.g. "X1" or "AX1").
    pub axis: String,
    /// Measuring system: 0 (first) or 1 (second).
    pub encoder: u8,
    /// MD38000 `$MA_MM_ENC_COMP_MAX_POINTS`.
    pub max_points: usize,
    /// Wanted spacing (mm); default the mean target spacing.
    pub step_mm: Option<f64>,
}

impl LecOptions {
    pub fn new(axis: &str) -> Self {
        LecOptions {
            axis: axis.into(),
            encoder: 0,
            max_points: 125,
            step_mm: None,
        }
    }
}

/// CEC options.
#[derive(Clone, Debug, PartialEq)]
pub struct CecOptions {
    /// Table index t (0-based); a bidirectional table also uses t + 1.
    pub table_index: usize,
    /// Base (input) axis name, e.g. "AX2".
    pub input_axis: String,
    /// Compensation (output) axis name, e.g. "AX1".
    pub output_axis: String,
    /// MD18342 `$MN_MM_CEC_MAX_POINTS[t]`.
    pub max_points: usize,
    pub step_mm: Option<f64>,
}

fn grid_limits(max_points: usize, step_mm: Option<f64>) -> GridLimits {
    GridLimits {
        max_points,
        min_step_mm: 0.0,
        step_quantum_mm: 0.0,
        step_mm,
    }
}

fn header(out: &mut String, program: &str, t: &CompTable, what: &str) {
    // Writing to a String cannot fail.
    let _ = writeln!(out, "{program}\nCHANDATA(1)");
    let _ = writeln!(
        out,
        "; axiscomp {what}: {} ({} of {} over {}), value = e = measured - nominal (mm)",
        t.name,
        t.kind.name(),
        t.comp_axis,
        t.base_axis
    );
    let _ = writeln!(
        out,
        "; zero at the reference point {} mm; linear interpolation between points",
        trimmed(t.reference_mm, 4)
    );
}

/// The LEC program for a positioning table (base = compensated axis, not bidirectional).
pub fn lec(table: &CompTable, o: &LecOptions) -> Result<Exported, CompError> {
    const F: &str = "Siemens LEC";
    check_identifier("axis", &o.axis)?;
    if o.encoder > 1 {
        return Err(CompError::Option {
            name: "encoder",
            problem: format!("{}: give 0 or 1 (measuring system 1 or 2)", o.encoder),
        });
    }
    if table.kind != TableKind::Positioning || table.base_axis != table.comp_axis {
        return Err(CompError::Unsupported {
            format: F,
            problem: format!(
                "{} compensates {} over {}: LEC compensates an axis over its own position; use cec",
                table.name, table.comp_axis, table.base_axis
            ),
        });
    }
    let backlash = match &table.values {
        TableValues::Single { backlash_mm, .. } => *backlash_mm,
        TableValues::Bidirectional { .. } => {
            return Err(CompError::Unsupported {
                format: F,
                problem: "LEC is not direction-dependent: build a unidirectional table (backlash to MD32450) or export both directions with cec ($AN_CEC_DIRECTION)".into(),
            });
        }
    };
    let grid = fit_grid(table, &grid_limits(o.max_points, o.step_mm), F)?;
    let t = table.resample(&grid.positions());
    let (e, a) = (o.encoder, &o.axis);
    let mut out = String::new();
    header(&mut out, "%_N_AX_EEC_INI", &t, "LEC");
    if let Some(b) = backlash {
        let _ = writeln!(
            out,
            "; backlash (not in this table): MD32450 $MA_BACKLASH[{e}] = {} mm",
            trimmed(b, 4)
        );
    }
    for (n, v) in t.primary().iter().enumerate() {
        let _ = writeln!(out, "$AA_ENC_COMP[{e},{n},{a}]={}", trimmed(*v, DECIMALS));
    }
    let _ = writeln!(
        out,
        "$AA_ENC_COMP_STEP[{e},{a}]={}",
        trimmed(grid.step_mm, DECIMALS)
    );
    let _ = writeln!(
        out,
        "$AA_ENC_COMP_MIN[{e},{a}]={}",
        trimmed(grid.start_mm, DECIMALS)
    );
    let _ = writeln!(
        out,
        "$AA_ENC_COMP_MAX[{e},{a}]={}",
        trimmed(grid.end_mm(), DECIMALS)
    );
    let _ = writeln!(out, "$AA_ENC_COMP_IS_MODULO[{e},{a}]=0\nM17");
    Ok(Exported {
        text: out,
        table: t,
        grid: Some(grid),
    })
}

/// The CEC program for any table: a cross-axis table (straightness, Abbe) or a positioning
/// table (bidirectional → two direction-dependent tables).
pub fn cec(table: &CompTable, o: &CecOptions) -> Result<Exported, CompError> {
    const F: &str = "Siemens CEC";
    check_identifier("input_axis", &o.input_axis)?;
    check_identifier("output_axis", &o.output_axis)?;
    let grid = fit_grid(table, &grid_limits(o.max_points, o.step_mm), F)?;
    let t = table.resample(&grid.positions());
    let mut out = String::new();
    header(&mut out, "%_N_NC_CEC_INI", &t, "CEC");
    let tables: Vec<(usize, i8, &[f64])> = match &t.values {
        TableValues::Single {
            values,
            backlash_mm,
        } => {
            if let Some(b) = backlash_mm {
                let _ = writeln!(
                    out,
                    "; backlash (not in this table): MD32450 $MA_BACKLASH = {} mm",
                    trimmed(*b, 4)
                );
            }
            vec![(o.table_index, 0, values)]
        }
        TableValues::Bidirectional { up, down } => vec![
            (o.table_index, 1, up.as_slice()),
            (o.table_index + 1, -1, down.as_slice()),
        ],
    };
    for (ti, dir, values) in tables {
        for (n, v) in values.iter().enumerate() {
            let _ = writeln!(out, "$AN_CEC[{ti},{n}]={}", trimmed(*v, DECIMALS));
        }
        let _ = writeln!(out, "$AN_CEC_INPUT_AXIS[{ti}]=({})", o.input_axis);
        let _ = writeln!(out, "$AN_CEC_OUTPUT_AXIS[{ti}]=({})", o.output_axis);
        let _ = writeln!(
            out,
            "$AN_CEC_STEP[{ti}]={}",
            trimmed(grid.step_mm, DECIMALS)
        );
        let _ = writeln!(
            out,
            "$AN_CEC_MIN[{ti}]={}",
            trimmed(grid.start_mm, DECIMALS)
        );
        let _ = writeln!(
            out,
            "$AN_CEC_MAX[{ti}]={}",
            trimmed(grid.end_mm(), DECIMALS)
        );
        let _ = writeln!(out, "$AN_CEC_DIRECTION[{ti}]={dir}");
        let _ = writeln!(out, "$AN_CEC_MULT_BY_TABLE[{ti}]=0");
        let _ = writeln!(out, "$AN_CEC_IS_MODULO[{ti}]=0");
    }
    out.push_str("M17\n");
    Ok(Exported {
        text: out,
        table: t,
        grid: Some(grid),
    })
}
