//! HEIDENHAIN non-linear axis error compensation tables (`*.COM`), two families.
//!
//! TNC 640 / MANUALplus 620 (`Family::Tnc640`): a table file `BEGIN <name> MM`, a header line
//! of column names, one row per compensation point, `[END]`. Columns: `NR`, `AXISPOS` (the
//! compensation points, "given with respect to the machine datum (MP_refPosition)"), a column
//! named after the compensated axis (its key in CfgAxes/axisList) holding the values, and
//! `BACKLASH` for "the compensation values measured in the negative direction of traverse"
//! (MANUALplus 620 Technical Manual, "Entering compensation values", p. 716). The `.COM` is then
//! assigned in a `.CMA` table, in the column of the axis it depends on (pp. 716–718); `cma`
//! writes that file.
//!
//! TNC 4xx / iTNC 530 (`Family::Tnc4xx`): the compensation points are equally spaced at a power
//! of two (the TNC 407 example: 7 mm asked for, "possible power of two = 2^16 = 6.5536 mm", i.e.
//! 2^k × 0.1 µm), from a datum (distance to the machine datum) where "the error curve must
//! always start with correction value = 0", continued in the positive direction (TNC 407
//! Technical Manual 01.98, §1.6.4, pp. 4-27–4-28; TNC 360 Technical Manual 8/95, §1.6.4), with
//! at most 256 entries per table (TNC 407 module 9095, error 3, p. 622 of the PDF). So the datum
//! is the reference point and the table must start there: data below it is refused.
//!
//! Value = +e (mm), with sign and 4 decimals (0.1 µm). Unconfirmed (said in `--help`; these
//! tables carry no comments): the value sign (+e, the error as measured, as in the ISO 230-1
//! columns of KinematicsComp), whether the control adds `BACKLASH` on reversal or uses it as
//! the negative direction's value (`Backlash::Negative` writes e↓ as the manual's words say;
//! `Backlash::Reversal` writes e↓ − e↑ for a control that adds it), the TNC 4xx text layout
//! (`DATUM`/`SPACING` lines before the rows) and the `.CMA` layout.

use super::table::{CompTable, Grid, GridLimits, TableValues};
use super::{CompError, Exported, fixed, trimmed};
use std::fmt::Write;

/// Decimals written (mm).
pub const DECIMALS: usize = 4;

/// Which control generation reads the table.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Family {
    /// TNC 640 / MANUALplus 620: AXISPOS column, any spacing.
    #[default]
    Tnc640,
    /// TNC 4xx / iTNC 530: power-of-two spacing from a datum.
    Tnc4xx,
}

impl Family {
    pub fn from_name(s: &str) -> Option<Self> {
        match s {
            "tnc640" => Some(Family::Tnc640),
            "tnc4xx" => Some(Family::Tnc4xx),
            _ => None,
        }
    }
}

/// What the BACKLASH column holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Backlash {
    /// The negative direction's values e↓ (the manual's words).
    #[default]
    Negative,
    /// The reversal e↓ − e↑ (for a control that adds BACKLASH to the value on reversal).
    Reversal,
}

/// `.COM` options.
#[derive(Clone, Debug, PartialEq)]
pub struct ComOptions {
    /// File name, e.g. "Y.COM" (letters, digits, `_`, `-`; ends in `.COM`).
    pub file_name: String,
    /// The compensated axis's key; default its letter.
    pub axis_key: Option<String>,
    /// Most rows (256: the TNC 407 limit; unconfirmed for the TNC 640).
    pub max_points: usize,
    pub step_mm: Option<f64>,
    pub family: Family,
    /// The machine datum's position in the table's coordinates (mm): AXISPOS = position − this.
    pub datum_mm: f64,
    pub backlash: Backlash,
}

impl ComOptions {
    pub fn new(file_name: &str) -> Self {
        ComOptions {
            file_name: file_name.into(),
            axis_key: None,
            max_points: 256,
            step_mm: None,
            family: Family::Tnc640,
            datum_mm: 0.0,
            backlash: Backlash::Negative,
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

/// 0.1 µm in mm: the unit of the TNC 4xx spacing.
const TNC4XX_UNIT_MM: f64 = 1e-4;

/// The smallest power-of-two spacing (2^k × 0.1 µm) at least `mm`.
pub fn power_of_two_step(mm: f64) -> (u32, f64) {
    let mut k = 0;
    while TNC4XX_UNIT_MM * f64::from(1u32 << k) < mm * (1.0 - 1e-12) && k < 30 {
        k += 1;
    }
    (k, TNC4XX_UNIT_MM * f64::from(1u32 << k))
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
    if !o.datum_mm.is_finite() {
        return Err(CompError::Option {
            name: "datum_mm",
            problem: format!("{} is not a position", o.datum_mm),
        });
    }
    let key = o
        .axis_key
        .clone()
        .unwrap_or_else(|| table.comp_axis.letter().to_string());
    super::check_identifier("axis_key", &key)?;
    let grid = match o.family {
        Family::Tnc640 => super::fit_checked(
            F,
            table,
            &GridLimits::points(o.max_points, o.step_mm),
            format!("{} rows", o.max_points),
            "comp.heidenhain.max_points (--max-points)",
        )?,
        Family::Tnc4xx => tnc4xx_grid(table, o, F)?,
    };
    let t = table.resample(&grid.positions());
    let reverse = match &t.values {
        TableValues::Single {
            backlash_mm: None, ..
        } => None,
        _ => Some(match o.backlash {
            Backlash::Negative => t.reverse(),
            Backlash::Reversal => t
                .reverse()
                .iter()
                .zip(t.primary())
                .map(|(d, u)| d - u)
                .collect(),
        }),
    };
    let mut out = format!("BEGIN {} MM\n", o.file_name);
    match o.family {
        Family::Tnc640 => {
            let _ = write!(out, "{:<6}{:<14}{:<14}", "NR", "AXISPOS", key);
        }
        Family::Tnc4xx => {
            let (k, _) = power_of_two_step(grid.step_mm);
            let _ = writeln!(out, "DATUM {}", signed(grid.start_mm - o.datum_mm));
            let _ = writeln!(out, "SPACING {k}");
            let _ = write!(out, "{:<6}{:<14}", "NR", key);
        }
    }
    if reverse.is_some() {
        out.push_str("BACKLASH");
    }
    out = out.trim_end().to_string();
    out.push('\n');
    for (n, (p, v)) in t.positions_mm.iter().zip(t.primary()).enumerate() {
        let mut line = match o.family {
            Family::Tnc640 => format!("{n:<6}{:<14}{:<14}", signed(p - o.datum_mm), signed(*v)),
            Family::Tnc4xx => format!("{n:<6}{:<14}", signed(*v)),
        };
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

/// TNC 4xx: from the reference (the datum, value 0) upwards at a power-of-two spacing.
fn tnc4xx_grid(table: &CompTable, o: &ComOptions, f: &'static str) -> Result<Grid, CompError> {
    let (Some(&first), Some(&last)) = (table.positions_mm.first(), table.positions_mm.last())
    else {
        return Err(CompError::Unsupported {
            format: f,
            problem: "the table is empty".into(),
        });
    };
    let r = table.reference_mm;
    if first < r - 1e-9 {
        return Err(CompError::Limit {
            format: f,
            limit: "the TNC 4xx table, which starts at its datum (value 0) and runs in the positive direction (TNC 407 §1.6.4)".into(),
            value: format!(
                "data from {} mm, below the reference {} mm",
                trimmed(first, 3),
                trimmed(r, 3)
            ),
            setting: format!(
                "set --reference-mm (comp reference) to the negative end, {} mm",
                trimmed(first, 3)
            ),
        });
    }
    let span = (last - r).max(0.0);
    let wanted = o.step_mm.unwrap_or_else(|| table.mean_step_mm().max(1e-3));
    let (_, mut step) = power_of_two_step(wanted);
    while (span / step - 1e-9).ceil() as usize + 1 > o.max_points {
        step *= 2.0;
    }
    if o.step_mm.is_some() && step > power_of_two_step(wanted).1 * (1.0 + 1e-9) {
        return Err(CompError::Limit {
            format: f,
            limit: format!("{} entries per table (TNC 407 module 9095)", o.max_points),
            value: format!(
                "{} points at {} mm",
                (span / power_of_two_step(wanted).1).ceil() as usize + 1,
                trimmed(power_of_two_step(wanted).1, 4)
            ),
            setting: "give a larger --step-mm".into(),
        });
    }
    let count = ((span / step - 1e-9).ceil() as usize + 1).max(2);
    Ok(Grid {
        start_mm: r,
        step_mm: step,
        count,
        reference_index: 0,
    })
}

/// The `.CMA` assignment table (TNC 640 family): one row assigning `com_file` to the compensated
/// axis in the column of the axis it depends on. Layout unconfirmed.
pub fn cma(table: &CompTable, com_file: &str, axis_key: Option<&str>) -> String {
    let comp = axis_key.unwrap_or(table.comp_axis.letter());
    let base = table.base_axis.letter();
    let mut out = String::from("BEGIN AXISCOMP.CMA\n");
    let _ = writeln!(out, "{:<6}{:<14}{}", "NR", "AXIS", base);
    let _ = writeln!(out, "{:<6}{:<14}{}", 0, comp, com_file);
    out.push_str("[END]\n");
    out
}
