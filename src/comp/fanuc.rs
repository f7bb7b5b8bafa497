//! FANUC pitch error compensation as a parameter tape.
//!
//! Parameters (per axis): 3620 number of the compensation point at the reference position,
//! 3621 / 3622 the most negative / most positive point numbers, 3623 magnification, 3624 the
//! interval (least input increments). Point N (k = N − 3620) stands for the interval
//! ((k − 1)·d, k·d] from the reference position; its value is the *increment* of the
//! compensation over that interval, in detection units × magnification, output when the axis
//! crosses it (Parameter Manual B-63980EN/01, parameter 3620–3624 and the example on p. 100).
//! The compensation is added to the command, so the absolute compensation at the points is
//! C = −e and each value ≈ −Δe. The absolute values are rounded first and then differenced, so
//! rounding never accumulates along the axis.
//!
//! Tape: a record between `%` lines; axis parameters `N03620A1P40` (N parameter, A controlled
//! axis, P value); pitch data `N1xxxx P<value>` with N = 10000 + point number. One line per
//! block (LF, the ISO end of block). Uncertain details are listed in the module docs of `comp`.

use super::table::{CompTable, GridLimits, TableKind, TableValues, fit_grid};
use super::{CompError, Exported};
use std::fmt::Write;

/// The range of one pitch compensation value (depends on the series).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ValueRange {
    /// −128..=127 (0i / 16i-class).
    Int8,
    /// −32768..=32767.
    Int16,
}

impl ValueRange {
    pub fn bounds(self) -> (i64, i64) {
        match self {
            ValueRange::Int8 => (i8::MIN as i64, i8::MAX as i64),
            ValueRange::Int16 => (i16::MIN as i64, i16::MAX as i64),
        }
    }
}

/// Pitch error compensation options.
#[derive(Clone, Debug, PartialEq)]
pub struct PitchOptions {
    /// Controlled axis number (1-based), the A of the tape.
    pub axis_number: u8,
    /// Parameter 3620: point number of the reference position.
    pub reference_number: u16,
    /// Highest point number of the control (e.g. 1023).
    pub max_number: u16,
    /// Most points one axis may use.
    pub max_points: usize,
    /// Least input increment (mm): the unit of parameter 3624.
    pub input_increment_mm: f64,
    /// Detection unit (mm).
    pub detection_unit_mm: f64,
    /// Parameter 3623 (1..=100).
    pub magnification: u8,
    pub range: ValueRange,
    /// Smallest interval (the manuals give max feed rate [mm/min] / 7500).
    pub min_interval_mm: f64,
    pub step_mm: Option<f64>,
}

impl PitchOptions {
    /// 0.001 mm units, magnification 1, int8 values, 128 points from number 0.
    pub fn new(axis_number: u8, reference_number: u16) -> Self {
        PitchOptions {
            axis_number,
            reference_number,
            max_number: 1023,
            max_points: 128,
            input_increment_mm: 0.001,
            detection_unit_mm: 0.001,
            magnification: 1,
            range: ValueRange::Int8,
            min_interval_mm: 0.0,
            step_mm: None,
        }
    }

    /// One value unit (mm).
    pub fn unit_mm(&self) -> f64 {
        self.detection_unit_mm * f64::from(self.magnification)
    }
}

/// Point numbers and values as written (for tests and reports).
#[derive(Clone, Debug, PartialEq)]
pub struct PitchData {
    pub most_negative: u16,
    pub most_positive: u16,
    pub interval_increments: i64,
    /// (point number, incremental value).
    pub points: Vec<(u16, i64)>,
    pub backlash_units: Option<i64>,
}

const F: &str = "Fanuc pitch error";

/// The parameter tape for a unidirectional positioning table.
pub fn pitch(table: &CompTable, o: &PitchOptions) -> Result<Exported, CompError> {
    let (text, _, t, grid) = build(table, o)?;
    Ok(Exported {
        text,
        table: t,
        grid: Some(grid),
    })
}

/// The numbers behind `pitch`.
pub fn pitch_data(table: &CompTable, o: &PitchOptions) -> Result<PitchData, CompError> {
    Ok(build(table, o)?.1)
}

fn build(
    table: &CompTable,
    o: &PitchOptions,
) -> Result<(String, PitchData, CompTable, super::Grid), CompError> {
    let opt = |name: &'static str, problem: String| CompError::Option { name, problem };
    if o.axis_number == 0 {
        return Err(opt(
            "axis_number",
            "controlled axes are numbered from 1".into(),
        ));
    }
    if !(1..=100).contains(&o.magnification) {
        return Err(opt(
            "magnification",
            format!("{}: parameter 3623 takes 1..=100", o.magnification),
        ));
    }
    for (name, v) in [
        ("input_increment_mm", o.input_increment_mm),
        ("detection_unit_mm", o.detection_unit_mm),
    ] {
        if !(v > 0.0 && v.is_finite()) {
            return Err(opt(name, format!("{v} mm: give a positive unit")));
        }
    }
    if o.reference_number > o.max_number {
        return Err(opt(
            "reference_number",
            format!(
                "{} is beyond the last point {}",
                o.reference_number, o.max_number
            ),
        ));
    }
    if table.kind != TableKind::Positioning || table.base_axis != table.comp_axis {
        return Err(CompError::Unsupported {
            format: F,
            problem: format!(
                "{} is a cross-axis table: pitch error compensation acts on the axis's own position (use straightness compensation of the control)",
                table.name
            ),
        });
    }
    let backlash = match &table.values {
        TableValues::Single { backlash_mm, .. } => *backlash_mm,
        TableValues::Bidirectional { .. } => {
            return Err(CompError::Unsupported {
                format: F,
                problem: "bidirectional pitch error compensation (3605#0, 3626, 3627) is not exported: build a unidirectional table (backlash goes to parameter 1851)".into(),
            });
        }
    };
    let grid = fit_grid(
        table,
        &GridLimits {
            // The points written are at most the grid's (one fewer unless the reference is
            // the first grid point).
            max_points: o.max_points,
            min_step_mm: o.min_interval_mm,
            step_quantum_mm: o.input_increment_mm,
            step_mm: o.step_mm,
        },
        F,
    )?;
    let t = table.resample(&grid.positions());
    let unit = o.unit_mm();
    let (lo, hi) = o.range.bounds();
    // Absolute compensation in units at every grid point, k = k_lo.. relative to the reference.
    let k_lo = -(grid.reference_index as i64);
    let c: Vec<i64> = t
        .primary()
        .iter()
        .map(|e| (-e / unit).round() as i64)
        .collect();
    let c_at = |k: i64| -> i64 {
        let i = (k - k_lo).clamp(0, c.len() as i64 - 1) as usize;
        c[i]
    };
    let k_hi = k_lo + grid.count as i64 - 1;
    let r = i64::from(o.reference_number);
    let (n_neg, n_pos) = (r + (k_lo + 1).min(0), r + k_hi.max(0));
    if n_neg < 0 || n_pos > i64::from(o.max_number) {
        return Err(CompError::Unsupported {
            format: F,
            problem: format!(
                "points {n_neg}..={n_pos} are needed around reference number {r} but the control has 0..={}: move parameter 3620",
                o.max_number
            ),
        });
    }
    let mut points = Vec::new();
    for n in n_neg..=n_pos {
        let k = n - r;
        let v = c_at(k) - c_at(k - 1);
        if v < lo || v > hi {
            return Err(CompError::OutOfRange {
                format: F,
                what: format!("point {n}"),
                value: v,
                min: lo,
                max: hi,
                position_mm: table.reference_mm + k as f64 * grid.step_mm,
                hint: "raise the magnification (parameter 3623) or shorten the interval",
            });
        }
        points.push((n as u16, v));
    }
    let interval = (grid.step_mm / o.input_increment_mm).round() as i64;
    let backlash_units = match backlash {
        Some(b) => {
            let v = (b / o.detection_unit_mm).round() as i64;
            if !(-9999..=9999).contains(&v) {
                return Err(CompError::OutOfRange {
                    format: F,
                    what: "backlash (parameter 1851)".into(),
                    value: v,
                    min: -9999,
                    max: 9999,
                    position_mm: table.reference_mm,
                    hint: "the backlash is implausibly large: check the data",
                });
            }
            Some(v)
        }
        None => None,
    };
    let a = o.axis_number;
    let mut out = String::from("%\n");
    for (p, v) in [
        (3620, r),
        (3621, n_neg),
        (3622, n_pos),
        (3623, i64::from(o.magnification)),
        (3624, interval),
    ] {
        let _ = writeln!(out, "N{p:05}A{a}P{v}");
    }
    if let Some(b) = backlash_units {
        let _ = writeln!(out, "N01851A{a}P{b}");
    }
    for (n, v) in &points {
        let _ = writeln!(out, "N{:05}P{v}", 10000 + u32::from(*n));
    }
    out.push_str("%\n");
    Ok((
        out,
        PitchData {
            most_negative: n_neg as u16,
            most_positive: n_pos as u16,
            interval_increments: interval,
            points,
            backlash_units,
        },
        t,
        grid,
    ))
}
