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
//! move in the negative direction" (K3, MSEC). The table is zero at the reference point, as K3
//! asks, so activating it after referencing makes no jump. Comments are ASCII (`;`).
//!
//! Rules and where they come from (SINUMERIK 840D sl Function Manual Extended Functions,
//! 6FC5397-1BP40-3BA1, 03/2013, K3 §4.4 "Interpolatory compensation"):
//! - the axis index is the *machine* axis name (`X1`, `AX1`; MD10000
//!   `$MN_AXCONF_MACHAX_NAME_TAB`, default X1, Y1, Z1 …): §4.4.2.2, "<AXi> = Axis name (e.g.
//!   X1, Y1, Z1)", p. 239, and the example for machine axis X1, §4.4.2.3, p. 242. A bare
//!   geometry letter is refused;
//! - 0 ≤ N ≤ MD38000 − 1 (p. 240); CEC tables hold MD18342 `$MN_MM_CEC_MAX_POINTS[t]` points,
//!   and on the 828D eight tables of 200 points are fixed, "This cannot be extended!" (§4.4.4.3,
//!   p. 264). Both limits are settings (`[comp.siemens]`, `--max-points`);
//! - "The first and last compensation values remain active over the entire traversing range;
//!   i.e. these values should be set to 0 if the compensation table does not cover the entire
//!   traversing range" (p. 240): `EndHandling::Hold` writes the measured end values and says so
//!   in the file; `EndHandling::Zero` adds one point beyond each end holding 0, so the
//!   compensation ramps to 0 over one interval;
//! - linear interpolation between equally spaced points from MIN to MAX (p. 237).
//!
//! Unconfirmed: the CEC sign. K3's sentence on the sign is in the MSEC section; the same +e is
//! written for CEC, and the file's header says that this is not confirmed for CEC. The `M17`
//! closing the CEC file is copied from the MSEC example.

use super::table::{CompTable, Grid, GridLimits, TableKind, TableValues};
use super::{CompError, Exported, check_identifier, fit_checked, trimmed};
use std::fmt::Write;

/// Decimals of mm written (0.1 nm: below any measuring-system resolution, so no rounding bias).
const DECIMALS: usize = 7;

/// What the table holds beyond its first and last points (K3: the end values stay active).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum EndHandling {
    /// The measured end values, active over the rest of the travel.
    #[default]
    Hold,
    /// One more point beyond each end, holding 0: the compensation is 0 outside the table.
    Zero,
}

/// The control: its point limits.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum SiemensControl {
    /// 840D sl: MD38000 / MD18342 as configured.
    #[default]
    S840d,
    /// 828D / 808D: CEC tables have 200 points, fixed.
    S828d,
}

/// CEC points on the 828D (K3 §4.4.4.3, p. 264).
pub const CEC_POINTS_828D: usize = 200;

/// LEC options.
#[derive(Clone, Debug, PartialEq)]
pub struct LecOptions {
    /// The machine axis name in the NC (e.g. "X1" or "AX1"), never the geometry letter.
    pub axis: String,
    /// Measuring system: 0 (first) or 1 (second).
    pub encoder: u8,
    /// MD38000 `$MA_MM_ENC_COMP_MAX_POINTS`.
    pub max_points: usize,
    /// Wanted spacing (mm); default the mean target spacing.
    pub step_mm: Option<f64>,
    pub ends: EndHandling,
}

impl LecOptions {
    pub fn new(axis: &str) -> Self {
        LecOptions {
            axis: axis.into(),
            encoder: 0,
            max_points: 125,
            step_mm: None,
            ends: EndHandling::Hold,
        }
    }
}

/// The control's default machine axis name for a geometry axis (MD10000: X1, Y1, Z1).
pub fn default_machine_axis(letter: &str) -> String {
    format!("{letter}1")
}

/// A machine axis name: an identifier that is not a bare geometry letter.
fn check_machine_axis(name: &'static str, v: &str) -> Result<(), CompError> {
    check_identifier(name, v)?;
    if v.len() == 1 {
        return Err(CompError::Option {
            name,
            problem: format!(
                "\"{v}\" is a geometry axis letter; K3 indexes tables by the machine axis name (MD10000, e.g. {}): give --machine-axis or comp.siemens.machine_axis",
                default_machine_axis(v)
            ),
        });
    }
    Ok(())
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
    pub ends: EndHandling,
    pub control: SiemensControl,
}

impl CecOptions {
    /// Table 0, 200 points (MD18342), held ends, 840D sl.
    pub fn new(input_axis: &str, output_axis: &str) -> Self {
        CecOptions {
            table_index: 0,
            input_axis: input_axis.into(),
            output_axis: output_axis.into(),
            max_points: 200,
            step_mm: None,
            ends: EndHandling::Hold,
            control: SiemensControl::S840d,
        }
    }
}

fn grid_limits(max_points: usize, step_mm: Option<f64>, ends: EndHandling) -> GridLimits {
    GridLimits {
        // Zero ends take one point at each end.
        max_points: match ends {
            EndHandling::Hold => max_points,
            EndHandling::Zero => max_points.saturating_sub(2),
        },
        min_step_mm: 0.0,
        step_quantum_mm: 0.0,
        step_mm,
    }
}

/// The table on `grid`, with a zero point added beyond each end for `EndHandling::Zero`.
fn on_grid(table: &CompTable, grid: &Grid, ends: EndHandling) -> (CompTable, Grid) {
    let t = table.resample(&grid.positions());
    match ends {
        EndHandling::Hold => (t, *grid),
        EndHandling::Zero => {
            let g = Grid {
                start_mm: grid.start_mm - grid.step_mm,
                count: grid.count + 2,
                reference_index: grid.reference_index + 1,
                ..*grid
            };
            let pad = |v: &[f64]| -> Vec<f64> {
                std::iter::once(0.0)
                    .chain(v.iter().copied())
                    .chain(std::iter::once(0.0))
                    .collect()
            };
            let values = match &t.values {
                TableValues::Single {
                    values,
                    backlash_mm,
                } => TableValues::Single {
                    values: pad(values),
                    backlash_mm: *backlash_mm,
                },
                TableValues::Bidirectional { up, down } => TableValues::Bidirectional {
                    up: pad(up),
                    down: pad(down),
                },
            };
            (
                CompTable {
                    positions_mm: g.positions(),
                    values,
                    name: t.name.clone(),
                    ..t
                },
                g,
            )
        }
    }
}

fn ends_comment(out: &mut String, ends: EndHandling) {
    let _ = writeln!(
        out,
        "{}",
        match ends {
            EndHandling::Hold =>
                "; ends: held - the first and last values stay active beyond MIN and MAX (K3 p. 240); set ends = zero if the table does not cover the whole travel",
            EndHandling::Zero =>
                "; ends: zero - one point beyond each measured end holds 0, so the compensation is 0 beyond MIN and MAX (K3 p. 240)",
        }
    );
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
    check_machine_axis("machine_axis", &o.axis)?;
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
                problem: "LEC is not direction-dependent: export without --bidirectional (one table, the backlash to MD32450), or both directions with --format siemens-cec ($AN_CEC_DIRECTION)".into(),
            });
        }
    };
    let grid = fit_checked(
        F,
        table,
        &grid_limits(o.max_points, o.step_mm, o.ends),
        format!("MD38000 $MA_MM_ENC_COMP_MAX_POINTS = {}", o.max_points),
        "comp.siemens.enc_comp_max_points (--max-points) with MD38000 on the control",
    )?;
    let (t, grid) = on_grid(table, &grid, o.ends);
    let (e, a) = (o.encoder, &o.axis);
    let mut out = String::new();
    header(&mut out, "%_N_AX_EEC_INI", &t, "LEC");
    let _ = writeln!(
        out,
        "; {} points, MD38000 $MA_MM_ENC_COMP_MAX_POINTS[{e},{a}] >= {} needed",
        grid.count, grid.count
    );
    ends_comment(&mut out, o.ends);
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
    check_machine_axis("input_axis", &o.input_axis)?;
    check_machine_axis("output_axis", &o.output_axis)?;
    if o.control == SiemensControl::S828d && o.max_points > CEC_POINTS_828D {
        return Err(CompError::Limit {
            format: F,
            limit: format!("the 828D's fixed {CEC_POINTS_828D} points per table (K3 p. 264)"),
            value: format!("max_points {}", o.max_points),
            setting: "set comp.siemens.cec_max_points (--max-points) to 200 or less".into(),
        });
    }
    let grid = fit_checked(
        F,
        table,
        &grid_limits(o.max_points, o.step_mm, o.ends),
        format!("MD18342 $MN_MM_CEC_MAX_POINTS = {}", o.max_points),
        "comp.siemens.cec_max_points (--max-points) with MD18342 on the control",
    )?;
    let (t, grid) = on_grid(table, &grid, o.ends);
    let mut out = String::new();
    header(&mut out, "%_N_NC_CEC_INI", &t, "CEC");
    let _ = writeln!(
        out,
        "; {} points per table, MD18342 $MN_MM_CEC_MAX_POINTS >= {} needed",
        grid.count, grid.count
    );
    ends_comment(&mut out, o.ends);
    out.push_str("; CEC sign unconfirmed: +e as for MSEC (K3 states the sign for MSEC only)\n");
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
