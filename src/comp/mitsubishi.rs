//! Mitsubishi CNC machine error compensation (M800 / M80 / E70): pitch error data per division
//! point, absolute or incremental.
//!
//! From Mitsubishi's "Machine error compensation" chapter (C64 / E68 manuals, §9.2 "Setting
//! compensation data"): the axis is divided at a fixed interval from the reference point; each
//! division point has a compensation number; the range of one value is −128..=127 in the unit
//! of output, whose real size is set by the compensation scale factor.
//! - Incremental system: on the positive side of the reference the value at point n is
//!   (division interval − actual movement from n − 1 to n), on the negative side (division
//!   interval + actual movement from n + 1 to n), in output units — i.e. −Δe over the interval
//!   in both cases (the actual movement from n + 1 to n is negative).
//! - Absolute system: the value at a point is the compensation at that point, −e, relative to the
//!   reference point (0 there).
//!
//! Unconfirmed (said in the file header and `--help`): the parameter numbers and names
//! (`#4000 Pinc` 0 absolute / 1 incremental, `#4001 cmpax` base axis, `#4002 drcax` compensated
//! axis, `#4003 rdvno` reference point's division number, `#4004 mdvno` / `#4005 pdvno` most
//! negative / positive division numbers, `#4006 sc` scale factor, `#4007 spcdv` interval, data
//! at `#(4100 + n)`) were not found in a public M800/M80/E70 document; they follow the M700-era
//! layout. The sheet is for entry on the parameter screen, one `#number value` per line.

use super::table::{CompTable, GridLimits, TableValues};
use super::{CompError, Exported, check_identifier, trimmed};
use std::fmt::Write;

/// Absolute or incremental data (`#4000 Pinc`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Mode {
    #[default]
    Absolute,
    Incremental,
}

/// Options.
#[derive(Clone, Debug, PartialEq)]
pub struct MecOptions {
    /// The base / compensated axis name (e.g. "X").
    pub axis_name: String,
    pub mode: Mode,
    /// The unit of output (mm), e.g. 0.001 (1 µm) for input setting unit B… × scale factor.
    pub output_unit_mm: f64,
    /// Compensation scale factor (`#4006 sc`).
    pub scale: u8,
    /// First compensation number used (the division numbers are `first..`), default 4101
    /// counting from 1.
    pub first_number: u16,
    /// Division points available to the axis.
    pub max_points: usize,
    pub step_mm: Option<f64>,
}

impl MecOptions {
    pub fn new(axis_name: &str) -> Self {
        MecOptions {
            axis_name: axis_name.into(),
            mode: Mode::Absolute,
            output_unit_mm: 0.001,
            scale: 1,
            first_number: 1,
            max_points: 1024,
            step_mm: None,
        }
    }
    fn unit_mm(&self) -> f64 {
        self.output_unit_mm * f64::from(self.scale)
    }
}

/// Division numbers and values as written.
#[derive(Clone, Debug, PartialEq)]
pub struct MecData {
    pub reference_number: u16,
    pub most_negative: u16,
    pub most_positive: u16,
    pub values: Vec<(u16, i64)>,
}

const F: &str = "Mitsubishi machine error compensation";

/// The parameter sheet of a unidirectional positioning table.
pub fn mec(table: &CompTable, o: &MecOptions) -> Result<Exported, CompError> {
    Ok(build(table, o)?.0)
}

/// The numbers behind `mec`.
pub fn mec_data(table: &CompTable, o: &MecOptions) -> Result<MecData, CompError> {
    Ok(build(table, o)?.1)
}

fn build(table: &CompTable, o: &MecOptions) -> Result<(Exported, MecData), CompError> {
    check_identifier("axis_name", &o.axis_name)?;
    if !(o.output_unit_mm > 0.0 && o.output_unit_mm.is_finite()) || o.scale == 0 {
        return Err(CompError::Option {
            name: "output_unit_mm",
            problem: format!(
                "{} mm × scale {}: give a positive unit and scale",
                o.output_unit_mm, o.scale
            ),
        });
    }
    super::own_axis(table, F, "export the positioning table")?;
    if matches!(table.values, TableValues::Bidirectional { .. }) {
        return Err(CompError::Unsupported {
            format: F,
            problem: "one table serves both directions: export without --bidirectional (one table; the backlash goes to the backlash parameter)".into(),
        });
    }
    let grid = super::fit_checked(
        F,
        table,
        &GridLimits {
            step_quantum_mm: 0.001,
            ..GridLimits::points(o.max_points, o.step_mm)
        },
        format!("{} division points", o.max_points),
        "comp.mitsubishi.max_points (--max-points)",
    )?;
    let t = table.resample(&grid.positions());
    let unit = o.unit_mm();
    let c: Vec<i64> = t
        .primary()
        .iter()
        .map(|e| (-e / unit).round() as i64)
        .collect();
    let r = grid.reference_index;
    let first = i64::from(o.first_number);
    let values: Vec<i64> = match o.mode {
        Mode::Absolute => c.clone(),
        Mode::Incremental => (0..c.len())
            .map(|i| match i.cmp(&r) {
                std::cmp::Ordering::Equal => 0,
                // Positive side: the interval from i − 1 to i.
                std::cmp::Ordering::Greater => c[i] - c[i - 1],
                // Negative side: the interval from i + 1 to i.
                std::cmp::Ordering::Less => c[i] - c[i + 1],
            })
            .collect(),
    };
    let mut numbered = Vec::new();
    for (i, v) in values.iter().enumerate() {
        let n = first + i as i64;
        if !(-128..=127).contains(v) {
            return Err(CompError::OutOfRange {
                format: F,
                what: format!("division point {n}"),
                value: *v,
                min: -128,
                max: 127,
                position_mm: t.positions_mm[i],
                hint: "raise the compensation scale factor (comp.mitsubishi.scale, #4006 sc) or shorten the interval",
            });
        }
        numbered.push((n as u16, *v));
    }
    let data = MecData {
        reference_number: (first + r as i64) as u16,
        most_negative: first as u16,
        most_positive: (first + values.len() as i64 - 1) as u16,
        values: numbered,
    };
    let mut out = String::new();
    let _ = writeln!(
        out,
        "; axiscomp machine error compensation: {} ({}), value = -e in units of {} mm, {}",
        t.name,
        o.axis_name,
        trimmed(unit, 6),
        match o.mode {
            Mode::Absolute => "absolute (compensation at each division point)",
            Mode::Incremental =>
                "incremental (change over each division interval, away from the reference)",
        }
    );
    out.push_str("; parameter numbers unconfirmed for M800/M80/E70 (M700-era layout): check the control's parameter manual\n");
    let step_units = (grid.step_mm / 0.001).round() as i64;
    for (p, name, v) in [
        (4000, "Pinc", i64::from(o.mode == Mode::Incremental)),
        (4003, "rdvno", i64::from(data.reference_number)),
        (4004, "mdvno", i64::from(data.most_negative)),
        (4005, "pdvno", i64::from(data.most_positive)),
        (4006, "sc", i64::from(o.scale)),
        (4007, "spcdv", step_units),
    ] {
        let _ = writeln!(out, "#{p} {name} {v}");
    }
    let _ = writeln!(out, "#4001 cmpax {}", o.axis_name);
    let _ = writeln!(out, "#4002 drcax {}", o.axis_name);
    for (n, v) in &data.values {
        let _ = writeln!(out, "#{} {v}", 4100 + u32::from(*n));
    }
    Ok((
        Exported {
            text: out,
            table: t,
            grid: Some(grid),
        },
        data,
    ))
}
