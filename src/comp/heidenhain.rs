//! HEIDENHAIN non-linear axis error compensation table (`*.COM`).
//!
//! A table file: `BEGIN <name> MM`, a header line of column names, one row per compensation
//! point, `[END]`. Columns: `NR` (row number), `AXISPOS` (position of the base axis relative to
//! the machine datum, mm), a column named after the compensated axis (its key in
//! CfgAxes/axisList) holding the compensation values (mm), and `BACKLASH` for the values of the
//! negative direction of traverse when the table is direction-dependent (MANUALplus 620
//! Technical Manual, "Entering compensation values"). The `.COM` is then entered in a `.CMA`
//! table under the base axis's column: `[comp axis] = F(base axis)`.
//!
//! Value = +e (mm), written with sign and 4 decimals (0.1 µm). The sign and the exact meaning of
//! `BACKLASH` are not confirmed by the sources read (see `comp`'s module docs).

use super::table::{CompTable, GridLimits, TableValues, fit_grid};
use super::{CompError, Exported, fixed};
use std::fmt::Write;

/// Decimals written (mm).
pub const DECIMALS: usize = 4;

/// `.COM` options.
#[derive(Clone, Debug, PartialEq)]
pub struct ComOptions {
    /// File name, e.g. "Y.COM" (letters, digits, `_`, `-`; ends in `.COM`).
    pub file_name: String,
    /// The compensated axis's key; default its letter.
    pub axis_key: Option<String>,
    /// Most rows (the TNC 407 manual's limit is 256 per table).
    pub max_points: usize,
    pub step_mm: Option<f64>,
}

impl ComOptions {
    pub fn new(file_name: &str) -> Self {
        ComOptions {
            file_name: file_name.into(),
            axis_key: None,
            max_points: 256,
            step_mm: None,
        }
    }
}

fn signed(x: f64) -> String {
    let s = fixed(x, DECIMALS);
    if s.starts_with('-') {
        s
    } else {
        format!("+{s}")
    }
}

/// The `.COM` table.
pub fn com(table: &CompTable, o: &ComOptions) -> Result<Exported, CompError> {
    const F: &str = "Heidenhain .COM";
    let stem_ok = o
        .file_name
        .strip_suffix(".COM")
        .or_else(|| o.file_name.strip_suffix(".com"))
        .is_some_and(|s| {
            !s.is_empty()
                && s.chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        });
    if !stem_ok {
        return Err(CompError::Option {
            name: "file_name",
            problem: format!(
                "\"{}\": give a name like Y.COM (letters, digits, _ and -)",
                o.file_name
            ),
        });
    }
    let key = o
        .axis_key
        .clone()
        .unwrap_or_else(|| table.comp_axis.letter().to_string());
    super::check_identifier("axis_key", &key)?;
    let grid = fit_grid(
        table,
        &GridLimits {
            max_points: o.max_points,
            min_step_mm: 0.0,
            step_quantum_mm: 0.0,
            step_mm: o.step_mm,
        },
        F,
    )?;
    let t = table.resample(&grid.positions());
    let reverse = match &t.values {
        TableValues::Single {
            backlash_mm: None, ..
        } => None,
        _ => Some(t.reverse()),
    };
    let mut out = format!("BEGIN {} MM\n", o.file_name);
    let _ = write!(out, "{:<6}{:<14}{:<14}", "NR", "AXISPOS", key);
    if reverse.is_some() {
        out.push_str("BACKLASH");
    }
    out = out.trim_end().to_string();
    out.push('\n');
    for (n, (p, v)) in t.positions_mm.iter().zip(t.primary()).enumerate() {
        let mut line = format!("{n:<6}{:<14}{:<14}", signed(*p), signed(*v));
        if let Some(r) = &reverse {
            line.push_str(&signed(r[n]));
        }
        out.push_str(line.trim_end());
        out.push('\n');
    }
    out.push_str("[END]\n");
    Ok(Exported {
        text: out,
        table: t,
        grid: Some(grid),
    })
}
