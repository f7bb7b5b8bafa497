//! LinuxCNC joint compensation file (`[JOINT_n]COMP_FILE`, `COMP_FILE_TYPE`).
//!
//! One triplet per line, separated by spaces, nominal positions ascending, machine units (mm):
//! - type 0: `nominal forward_actual reverse_actual` — where the joint really is when commanded
//!   to `nominal` moving in the positive / negative direction: `nominal + e`;
//! - type 1: `nominal forward_trim reverse_trim` — the loader uses them as given, and converts
//!   type 0 with `trim = nominal − actual` (src/emc/motion/usrmotintf.cc, `usrmotLoadComp`),
//!   so trim = −e.
//!
//! The loader reads with `sscanf("%lf %lf %lf")` and stops at the first line that does not give
//! three numbers: the file has no header or comments. At most 256 triplets per joint
//! (ini-config.adoc). With a `COMP_FILE`, `BACKLASH` is not used, so a table's backlash is folded
//! into the reverse column (reverse = e + backlash).
//!
//! LinuxCNC interpolates linearly between arbitrary nominals, so the measured targets are
//! written as they are when they fit; otherwise the table is resampled onto a uniform grid.
//!
//! Units and coordinates: the loader reads the file in the joint's machine units (ini-config.adoc,
//! `[JOINT_n]COMP_FILE`: "…in machine units") and applies it to the *joint* position
//! (usrmotintf.cc hands the triplets to motion per joint), so an inch machine needs inches
//! (`Units::Inch`: every number / 25.4) and the nominals are joint positions — the axis
//! positions on a trivkins machine. A gantry's two joints each need the file in their own
//! `[JOINT_n]` section; `axiscomp export` names the sections. The file has no room to say this,
//! so the CLI prints it.

use super::table::{CompTable, GridLimits};
use super::{CompError, Exported, fixed};
use std::fmt::Write;

/// Decimals written (mm): 1 nm.
pub const DECIMALS: usize = 6;

/// Type 0 (actual positions) or type 1 (trims).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CompFileType {
    Type0,
    Type1,
}

/// The machine's length unit (`[TRAJ]LINEAR_UNITS`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Units {
    #[default]
    Mm,
    Inch,
}

impl Units {
    /// mm per unit.
    pub fn mm(self) -> f64 {
        match self {
            Units::Mm => 1.0,
            Units::Inch => 25.4,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            Units::Mm => "mm",
            Units::Inch => "inch",
        }
    }
}

/// Compensation file options.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CompFileOptions {
    pub file_type: CompFileType,
    pub units: Units,
    /// 256 in LinuxCNC.
    pub max_points: usize,
    /// Spacing when resampling is needed.
    pub step_mm: Option<f64>,
}

impl CompFileOptions {
    pub fn new(file_type: CompFileType) -> Self {
        CompFileOptions {
            file_type,
            units: Units::Mm,
            max_points: 256,
            step_mm: None,
        }
    }
}

/// The compensation file of a positioning table.
pub fn comp_file(table: &CompTable, o: &CompFileOptions) -> Result<Exported, CompError> {
    const F: &str = "LinuxCNC comp file";
    super::own_axis(
        table,
        F,
        "a joint comp file acts on the joint's own position",
    )?;
    let (t, grid) = super::measured_or_grid(
        F,
        table,
        &GridLimits::points(o.max_points, o.step_mm),
        format!("{} points", o.max_points),
        "comp.linuxcnc.max_points (--max-points)",
    )?;
    let fwd = t.primary().to_vec();
    let rev = t.reverse();
    let u = o.units.mm();
    // 1 nm in either unit: inches get two more decimals.
    let decimals = match o.units {
        Units::Mm => DECIMALS,
        Units::Inch => DECIMALS + 2,
    };
    let mut out = String::new();
    for ((p, f), r) in t.positions_mm.iter().zip(&fwd).zip(&rev) {
        let (a, b) = match o.file_type {
            CompFileType::Type0 => ((p + f) / u, (p + r) / u),
            CompFileType::Type1 => (-f / u, -r / u),
        };
        let p = p / u;
        let _ = writeln!(
            out,
            "{} {} {}",
            fixed(p, decimals),
            fixed(a, decimals),
            fixed(b, decimals)
        );
    }
    Ok(Exported {
        text: out,
        table: t,
        grid,
    })
}
