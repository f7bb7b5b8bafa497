//! Compensation tables and controller exports (DESIGN §7).
//!
//! `mapping` turns the head's frame into machine axes and ISO 230-1 names; `table` builds the
//! positioning, straightness and Abbe tables from an `AxisEvaluation` (all holding
//! `e = measured − nominal`, zeroed at the reference point) and fits them to a controller's grid;
//! the exporters write each controller's file with its own sign rule:
//!
//! | exporter | file | value written | source |
//! |---|---|---|---|
//! | `siemens::lec` | `%_N_AX_EEC_INI`, `$AA_ENC_COMP[e,N,AX]` (mm) | `+e` | SINUMERIK 840D sl Function Manual Extended Functions, K3 Compensation, §"Measuring system error compensation (MSEC)" and its example (6FC5397-1BP40-3BA1, 03/2013, pp. 238–242) |
//! | `siemens::cec` | `%_N_NC_CEC_INI`, `$AN_CEC[t,N]` (mm) | `+e` | same manual, §"Compensation of sag and angularity errors", table parameters (pp. 248–249); 802D sl K3 example `%_N_NC_CEC_INI` (6FC5397-1CP10-5BA0, p. 222) |
//! | `fanuc::pitch` | parameter tape: 3620–3624 and pitch data `N1xxxx P` (incremental, units of detection unit × magnification) | `≈ −Δe` | FANUC Series 0i-PB Parameter Manual B-63980EN/01 (parameters 3620–3624, example p. 100); Series 16i/18i bidirectional pitch error compensation A-77810E (parameter list); 15i/30i parameter manuals B-63330EN/03 p. 25, B-63950EN/02 §3.3 (tape format) |
//! | `heidenhain::com` | `*.COM` table: `NR AXISPOS <axis> [BACKLASH]` (mm) | `+e` | HEIDENHAIN MANUALplus 620 Technical Manual, "Entering compensation values" / "Assigning the compensation value tables" (pp. 716–718); TNC 407 Technical Manual (non-linear axis error compensation, .COM/.CMA) |
//! | `linuxcnc::comp_file` | `[JOINT_n]COMP_FILE`, type 0: `nominal fwd_actual rev_actual`; type 1: `nominal fwd_trim rev_trim` | type 0: `nominal + e`; type 1: `−e` | LinuxCNC docs/src/config/ini-config.adoc (`COMP_FILE`, `COMP_FILE_TYPE`); src/emc/motion/usrmotintf.cc `usrmotLoadComp` (trim = nominal − actual) |
//! | `beckhoff::ssfk` | TwinCAT CNC (ISG) compensation value list `kw.ssfk.*` (0.1 µm, bilateral, ≤ 1500 points) | `+e` | Beckhoff TF5200 Axis compensation, "Leadscrew error compensation (kw.ssfk.*)", P-COMP-00059, "Example – Non-equidistant bilateral SSFK" (Δs = s_actual − s_setpoint) |
//! | `mitsubishi::mec` | M800/M80/E70 machine error compensation parameter sheet, absolute or incremental | absolute `−e`, incremental `≈ −Δe` | Mitsubishi "Machine error compensation" §9.2 (C64/E68 manuals: incremental values, range −128..127); parameter numbers unconfirmed |
//! | `neutral::csv`, `neutral::json` | our own | `+e` (µm) | — |
//!
//! Sign reasoning, for a +10 µm overshoot (the carriage stops 10 µm beyond nominal, e = +10 µm):
//! Siemens: "a positive compensation value causes the machine axis to move in the negative
//! direction" (MSEC) — so +0.010 mm; CEC is written the same way, which K3 does not state for
//! CEC (unconfirmed, said in the CEC file). Beckhoff's value is measured − setpoint, +e. Fanuc adds the compensation pulses to the
//! command, so the absolute compensation is −e and the data are its increments per interval.
//! LinuxCNC adds `trim = nominal − actual` to the command (usrmotintf.cc).
//!
//! Each exporter's module docs cite the manual, section and page of every sign and layout
//! rule, and list what stays unconfirmed; `axiscomp export --help` repeats that list
//! (`cli/export.rs`), and formats with comments say it in the file's header. Controller
//! settings come from `[comp.<controller>]` (`settings`).

pub mod beckhoff;
pub mod fanuc;
pub mod heidenhain;
pub mod linuxcnc;
pub mod mapping;
pub mod mitsubishi;
pub mod neutral;
pub mod settings;
pub mod siemens;
pub mod table;

pub use mapping::{AxisMapping, IsoName, MachineAxis, SignedAxis};
pub use table::{
    CompTable, Grid, GridLimits, PositioningMode, TableKind, TableSet, TableSpec, TableValues,
    build_tables, fit_grid, interpolate,
};

use thiserror::Error;

/// Why a table could not be built or exported.
#[derive(Debug, Error, PartialEq)]
pub enum CompError {
    #[error("axis mapping: {0}")]
    Mapping(String),
    #[error("option {name}: {problem}")]
    Option { name: &'static str, problem: String },
    #[error("{format}: {problem}")]
    Unsupported {
        format: &'static str,
        problem: String,
    },
    #[error("{format}: {what} = {value} at {position_mm} mm is outside {min} to {max}: {hint}")]
    OutOfRange {
        format: &'static str,
        what: String,
        value: i64,
        min: i64,
        max: i64,
        position_mm: f64,
        hint: &'static str,
    },
    /// The table does not fit a controller limit: one line with the limit, the value and the
    /// setting to change.
    #[error("{format}: {value} exceeds {limit}: {setting}")]
    Limit {
        format: &'static str,
        limit: String,
        value: String,
        setting: String,
    },
}

/// How much coarser than the measured targets' spacing a controller's grid may be without a
/// spacing asked for: a quantised spacing (a power of two for TNC 4xx) rounds up, short of
/// twice.
const MAX_COARSENING: f64 = 2.0;

/// The controller's grid for `table` within `limits`, refused when its reference point lies
/// more than a spacing outside the measured range, when it had to be made coarser than the
/// measured spacing with none asked for (`MAX_COARSENING`), or coarser than the spacing asked for: the controller's point limit (named by `limit`; `setting` is the
/// key that raises it) does not hold the table at that spacing.
pub(crate) fn fit_checked(
    format: &'static str,
    table: &CompTable,
    limits: &GridLimits,
    limit: String,
    setting: &str,
) -> Result<Grid, CompError> {
    // A reference point far outside the measured range would zero the table where nothing
    // was measured and hold the end values over the gap (`--reference-mm 5000` on a 1000 mm
    // axis zeroed the table 4 m past the travel).
    let r = table.reference_mm;
    let measured = table.mean_step_mm();
    if let (Some(&first), Some(&last)) = (table.positions_mm.first(), table.positions_mm.last()) {
        let reach = measured.max(limits.step_mm.unwrap_or(0.0));
        let beyond = (first - r).max(r - last);
        if beyond > reach * (1.0 + 1e-9) {
            return Err(CompError::Unsupported {
                format,
                problem: format!(
                    "the reference point {} mm is {} mm outside the measured range {} to {} mm (more than one spacing, {} mm): the table would be zero where nothing was measured; give the machine position of the reference point on the measured travel (--reference-mm)",
                    trimmed(r, 3),
                    trimmed(beyond, 3),
                    trimmed(first, 3),
                    trimmed(last, 3),
                    trimmed(reach, 3)
                ),
            });
        }
    }
    let grid = fit_grid(table, limits, format)?;
    // Without a spacing asked for, the table is not made coarser than the targets were
    // measured: a 5-point limit resampled a 1000 mm table 264 mm apart, losing what the
    // targets between showed. A coarser table is written when --step-mm asks for it.
    if limits.step_mm.is_none()
        && measured > 0.0
        && grid.step_mm > MAX_COARSENING * measured.max(limits.min_step_mm)
    {
        return Err(CompError::Limit {
            format,
            limit,
            value: format!(
                "{} points at the measured targets' spacing of {} mm (they would be {} mm apart)",
                table.positions_mm.len(),
                trimmed(measured, 3),
                trimmed(grid.step_mm, 3)
            ),
            setting: format!(
                "raise {setting}, or ask for the coarser table with --step-mm {}",
                trimmed(grid.step_mm, 3)
            ),
        });
    }
    if let Some(w) = limits.step_mm
        && grid.step_mm > w * (1.0 + 1e-9)
    {
        let (lo, hi) = match (table.positions_mm.first(), table.positions_mm.last()) {
            (Some(a), Some(b)) => (a.min(r), b.max(r)),
            _ => (r, r),
        };
        let need = (((hi - r) / w - 1e-9).ceil() - ((lo - r) / w + 1e-9).floor()) as usize + 1;
        return Err(CompError::Limit {
            format,
            limit,
            value: format!(
                "{need} points at the {} mm spacing asked for",
                trimmed(w, 4)
            ),
            setting: format!("raise {setting} or give a larger --step-mm"),
        });
    }
    Ok(grid)
}

/// The table as measured when its points fit `limits.max_points` and no spacing is asked for
/// (for controllers that take any positions), else resampled on `fit_checked`'s grid.
pub(crate) fn measured_or_grid(
    format: &'static str,
    table: &CompTable,
    limits: &GridLimits,
    limit: String,
    setting: &str,
) -> Result<(CompTable, Option<Grid>), CompError> {
    if table.positions_mm.len() <= limits.max_points && limits.step_mm.is_none() {
        return Ok((table.clone(), None));
    }
    let g = fit_checked(format, table, limits, limit, setting)?;
    Ok((table.resample(&g.positions()), Some(g)))
}

/// Refuse a cross-axis table for a format that compensates an axis over its own position.
pub(crate) fn own_axis(
    table: &CompTable,
    format: &'static str,
    why: &str,
) -> Result<(), CompError> {
    if table.kind != TableKind::Positioning || table.base_axis != table.comp_axis {
        return Err(CompError::Unsupported {
            format,
            problem: format!(
                "{} compensates {} over {}: {why}",
                table.name, table.comp_axis, table.base_axis
            ),
        });
    }
    Ok(())
}

/// A written file and exactly what it encodes: `table` is the resampled table (before rounding
/// to the file's resolution) on the controller's grid.
#[derive(Clone, Debug, PartialEq)]
pub struct Exported {
    pub text: String,
    pub table: CompTable,
    /// The grid, when the table was resampled onto an equally spaced one.
    pub grid: Option<Grid>,
}

/// `x` with `decimals` decimals, without a negative zero.
pub(crate) fn fixed(x: f64, decimals: usize) -> String {
    let s = format!("{x:.decimals$}");
    if s.trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        s.trim_start_matches('-').to_string()
    } else {
        s
    }
}

/// `x` rounded to `decimals`, trailing zeros removed but one decimal kept: "0.003", "-200.0".
pub(crate) fn trimmed(x: f64, decimals: usize) -> String {
    let s = fixed(x, decimals);
    if !s.contains('.') {
        return format!("{s}.0");
    }
    let t = s.trim_end_matches('0');
    if t.ends_with('.') {
        format!("{t}0")
    } else {
        t.to_string()
    }
}

/// A controller identifier: ASCII letters, digits and `_`, starting with a letter.
pub(crate) fn check_identifier(name: &'static str, v: &str) -> Result<(), CompError> {
    let ok = v.chars().next().is_some_and(|c| c.is_ascii_alphabetic())
        && v.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
    if ok {
        Ok(())
    } else {
        Err(CompError::Option {
            name,
            problem: format!(
                "\"{v}\" is not a controller name: letters, digits and _, starting with a letter"
            ),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn number_formats() {
        assert_eq!(fixed(-0.00001, 4), "0.0000");
        assert_eq!(fixed(-0.00012, 4), "-0.0001");
        assert_eq!(trimmed(0.003, 6), "0.003");
        assert_eq!(trimmed(-200.0, 6), "-200.0");
        assert_eq!(trimmed(-0.0000001, 6), "0.0");
        assert_eq!(trimmed(6.73, 4), "6.73");
        assert!(check_identifier("axis", "AX1").is_ok());
        assert!(check_identifier("axis", "1X").is_err());
        assert!(check_identifier("axis", "X 1").is_err());
    }
}
