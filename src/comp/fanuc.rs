//! FANUC pitch error compensation as a parameter tape.
//!
//! Parameters (per axis): 3620 number of the compensation point at the reference position,
//! 3621 / 3622 the most negative / most positive point numbers, 3623 magnification, 3624 the
//! interval (least input increments). Point N (k = N − 3620) stands for the interval
//! ((k − 1)·d, k·d] from the reference position; its value is the *increment* of the
//! compensation over that interval, in detection units × magnification, output when the axis
//! crosses it (Parameter Manual B-63980EN/01, parameters 3620–3624 and the example on p. 100).
//! The compensation is added to the command, so the absolute compensation at the points is
//! C = −e and each value ≈ −Δe. The absolute values are rounded first and then differenced, so
//! rounding never accumulates along the axis.
//!
//! Rules and sources:
//! - 3620 follows the reference position: the table is zeroed at the reference (`--reference-mm`,
//!   the machine position of the reference point) and, unless configured, 3620 is chosen so the
//!   most negative point is number 0 (B-63980EN/01 p. 100: the numbers run on both sides of
//!   the reference, 33…49 around 40 in the example). A 3620 that pushes a point below 0 or
//!   beyond the control's last number is refused, naming 3620.
//! - Minimum interval: max feed rate (mm/min) / 7500 (B-63980EN/01, parameter 3624). An
//!   interval asked for below it is refused; an automatic one is made at least that long.
//! - Value range by generation: −128..=127 (0i: B-63980EN/01, pitch error data), ±7 ×
//!   magnification on older controls (unconfirmed: no public page read gives it), −32768..=32767
//!   on 30i-class controls (unconfirmed).
//! - Bidirectional pitch error compensation (FANUC Technical Report A-77810E, "Bidirectional
//!   pitch error compensation", 16i/18i-MA/TA, Table (a)): 3605#0 = 1; 3621/3622 the most
//!   negative / most positive point for travel in the positive direction; 3626 the most negative
//!   point for travel in the negative direction (its set follows with the same count); 3627 the
//!   compensation (absolute value) at the reference position when the machine moves to it in the
//!   negative direction. 3627's sign is taken as the pitch data's (C = −e); unconfirmed.
//!
//! Tape: a record between `%` lines; axis parameters `N03620A1P40` (N parameter, A controlled
//! axis, P value); pitch data `N1xxxx P<value>` with N = 10000 + point number (B-63330EN/03
//! p. 25, B-63950EN/02 §3.3). One line per block (LF, the ISO end of block). The bit parameter
//! 3605 is written as `N03605A<a>P00000001` (#7…#0); unconfirmed. FANUC tapes carry no comments,
//! so what is unconfirmed is said in `axiscomp export --help`.

use super::table::{CompTable, GridLimits, TableValues};
use super::{CompError, Exported, trimmed};
use std::fmt::Write;

/// The range of one pitch compensation value (depends on the control's generation).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ValueRange {
    /// −128..=127 (0i / 16i-class).
    Int8,
    /// −7..=7 (older controls; × magnification 3623).
    Pm7,
    /// −32768..=32767 (30i-class).
    Int16,
}

impl ValueRange {
    pub fn bounds(self) -> (i64, i64) {
        match self {
            ValueRange::Int8 => (i8::MIN as i64, i8::MAX as i64),
            ValueRange::Pm7 => (-7, 7),
            ValueRange::Int16 => (i16::MIN as i64, i16::MAX as i64),
        }
    }

    /// The `--family` / `comp.fanuc.family` name.
    pub fn family(self) -> &'static str {
        match self {
            ValueRange::Int8 => "0i",
            ValueRange::Pm7 => "legacy",
            ValueRange::Int16 => "30i",
        }
    }

    pub fn from_family(s: &str) -> Option<Self> {
        match s {
            "0i" => Some(ValueRange::Int8),
            "legacy" => Some(ValueRange::Pm7),
            "30i" => Some(ValueRange::Int16),
            _ => None,
        }
    }
}

/// Pitch error compensation options.
#[derive(Clone, Debug, PartialEq)]
pub struct PitchOptions {
    /// Controlled axis number (1-based), the A of the tape.
    pub axis_number: u8,
    /// Parameter 3620: point number of the reference position; `None`: the most negative point
    /// gets number 0.
    pub reference_number: Option<u16>,
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
    /// Smallest interval besides the feed rule (mm).
    pub min_interval_mm: f64,
    /// The axis's maximum feed rate (mm/min): the interval must be at least this / 7500.
    pub max_feed_mm_min: Option<f64>,
    pub step_mm: Option<f64>,
    /// Bidirectional tables: parameter 3626 (`None`: the point after the positive set).
    pub negative_start: Option<u16>,
}

impl PitchOptions {
    /// 0.001 mm units, magnification 1, int8 values, 128 points, 3620 = `reference_number`.
    pub fn new(axis_number: u8, reference_number: u16) -> Self {
        PitchOptions {
            axis_number,
            reference_number: Some(reference_number),
            max_number: 1023,
            max_points: 128,
            input_increment_mm: 0.001,
            detection_unit_mm: 0.001,
            magnification: 1,
            range: ValueRange::Int8,
            min_interval_mm: 0.0,
            max_feed_mm_min: None,
            step_mm: None,
            negative_start: None,
        }
    }

    /// One value unit (mm).
    pub fn unit_mm(&self) -> f64 {
        self.detection_unit_mm * f64::from(self.magnification)
    }

    /// The shortest interval allowed (mm).
    pub fn min_step_mm(&self) -> f64 {
        self.min_interval_mm
            .max(self.max_feed_mm_min.map(|f| f / 7500.0).unwrap_or(0.0))
    }
}

/// Point numbers and values as written (for tests and reports).
#[derive(Clone, Debug, PartialEq)]
pub struct PitchData {
    pub reference_number: u16,
    pub most_negative: u16,
    pub most_positive: u16,
    pub interval_increments: i64,
    /// (point number, incremental value), positive direction (or both).
    pub points: Vec<(u16, i64)>,
    pub backlash_units: Option<i64>,
    /// Bidirectional: the negative direction's set.
    pub negative: Option<NegativeSet>,
}

/// The negative direction's data of a bidirectional tape.
#[derive(Clone, Debug, PartialEq)]
pub struct NegativeSet {
    /// Parameter 3626: its first point number.
    pub start: u16,
    /// Parameter 3627: the absolute compensation at the reference, approached going negative.
    pub at_reference: i64,
    /// (point number, incremental value).
    pub points: Vec<(u16, i64)>,
}

/// Where the grid's points sit relative to the reference and its number.
#[derive(Clone, Copy)]
struct Numbering {
    k_lo: i64,
    r: i64,
    reference_mm: f64,
    step_mm: f64,
}

const F: &str = "Fanuc pitch error";

/// The parameter tape for a positioning table (unidirectional, or bidirectional with 3605#0).
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

fn check_options(o: &PitchOptions) -> Result<(), CompError> {
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
            format!("{}: parameter 3623 takes 1 to 100", o.magnification),
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
    if let Some(f) = o.max_feed_mm_min
        && !(f > 0.0 && f.is_finite())
    {
        return Err(opt(
            "max_feed_mm_min",
            format!("{f} mm/min: give the axis's maximum feed rate"),
        ));
    }
    if let Some(r) = o.reference_number
        && r > o.max_number
    {
        return Err(opt(
            "reference_number",
            format!("{r} is beyond the last point {}", o.max_number),
        ));
    }
    Ok(())
}

/// Incremental values `c(k) − c(k − 1)` for the numbers `n_lo..=n_hi` (k = n − r), checked
/// against the range.
fn increments(
    c: &[i64],
    at: &Numbering,
    (n_lo, n_hi): (i64, i64),
    first_number: i64,
    o: &PitchOptions,
) -> Result<Vec<(u16, i64)>, CompError> {
    let Numbering {
        k_lo,
        r,
        reference_mm,
        step_mm,
    } = *at;
    let (lo, hi) = o.range.bounds();
    let c_at = |k: i64| -> i64 { c[(k - k_lo).clamp(0, c.len() as i64 - 1) as usize] };
    let mut points = Vec::new();
    for n in n_lo..=n_hi {
        let k = n - r;
        let v = c_at(k) - c_at(k - 1);
        if v < lo || v > hi {
            return Err(CompError::OutOfRange {
                format: F,
                what: format!("point {}", first_number + (n - n_lo)),
                value: v,
                min: lo,
                max: hi,
                position_mm: reference_mm + k as f64 * step_mm,
                hint: "raise the magnification (comp.fanuc.magnification, parameter 3623), shorten the interval, or pick the control's generation (--family)",
            });
        }
        points.push(((first_number + (n - n_lo)) as u16, v));
    }
    Ok(points)
}

fn build(
    table: &CompTable,
    o: &PitchOptions,
) -> Result<(String, PitchData, CompTable, super::Grid), CompError> {
    check_options(o)?;
    super::own_axis(
        table,
        F,
        "pitch error compensation acts on the axis's own position (use the control's straightness compensation)",
    )?;
    let min_step = o.min_step_mm();
    if let Some(s) = o.step_mm
        && s < min_step * (1.0 - 1e-9)
    {
        return Err(CompError::Unsupported {
            format: F,
            problem: format!(
                "the interval {} mm is below the minimum interval {} mm (max feed {} mm/min / 7500, parameter 3624): give a --step-mm of at least {} mm, or check comp.fanuc.max_feed_mm_min",
                trimmed(s, 4),
                trimmed(min_step, 4),
                trimmed(o.max_feed_mm_min.unwrap_or(0.0), 1),
                trimmed(min_step, 4)
            ),
        });
    }
    let (backlash, bidirectional) = match &table.values {
        TableValues::Single { backlash_mm, .. } => (*backlash_mm, false),
        TableValues::Bidirectional { .. } => (None, true),
    };
    // The negative set needs as many numbers again.
    let grid = super::fit_checked(
        F,
        table,
        &GridLimits {
            max_points: o.max_points,
            min_step_mm: min_step,
            step_quantum_mm: o.input_increment_mm,
            step_mm: o.step_mm,
        },
        format!("{} points per axis", o.max_points),
        "comp.fanuc.max_points (--max-points)",
    )?;
    let t = table.resample(&grid.positions());
    let unit = o.unit_mm();
    let k_lo = -(grid.reference_index as i64);
    let k_hi = k_lo + grid.count as i64 - 1;
    let to_units =
        |v: &[f64]| -> Vec<i64> { v.iter().map(|e| (-e / unit).round() as i64).collect() };
    let c_up = to_units(t.primary());
    let r = match o.reference_number {
        Some(r) => i64::from(r),
        None => (-(k_lo + 1)).max(0),
    };
    let (n_neg, n_pos) = (r + (k_lo + 1).min(0), r + k_hi.max(0));
    let max_n = i64::from(o.max_number);
    if n_neg < 0 || n_pos > max_n {
        return Err(CompError::Limit {
            format: F,
            limit: format!("point numbers 0 to {max_n} (comp.fanuc.max_number)"),
            value: format!("points {n_neg} to {n_pos} around reference number 3620 = {r}"),
            setting: format!(
                "set comp.fanuc.reference_number (parameter 3620) to {} or leave it out",
                (-(k_lo + 1)).max(0)
            ),
        });
    }
    let at = Numbering {
        k_lo,
        r,
        reference_mm: table.reference_mm,
        step_mm: grid.step_mm,
    };
    let points = increments(&c_up, &at, (n_neg, n_pos), n_neg, o)?;
    let negative = if bidirectional {
        let c_down = to_units(&t.reverse());
        let start = o.negative_start.map(i64::from).unwrap_or(n_pos + 1);
        let end = start + (n_pos - n_neg);
        if start <= n_pos && end >= n_neg || end > max_n {
            return Err(CompError::Limit {
                format: F,
                limit: format!(
                    "point numbers 0 to {max_n}, apart from the positive set {n_neg} to {n_pos}"
                ),
                value: format!("the negative set {start} to {end}"),
                setting: "change comp.fanuc.negative_start (parameter 3626) or leave it out".into(),
            });
        }
        let at_ref = c_down[grid.reference_index];
        let pts = increments(&c_down, &at, (n_neg, n_pos), start, o)?;
        Some(NegativeSet {
            start: start as u16,
            at_reference: at_ref,
            points: pts,
        })
    } else {
        None
    };
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
    if negative.is_some() {
        let _ = writeln!(out, "N03605A{a}P00000001");
    }
    for (p, v) in [
        (3620, r),
        (3621, n_neg),
        (3622, n_pos),
        (3623, i64::from(o.magnification)),
        (3624, interval),
    ] {
        let _ = writeln!(out, "N{p:05}A{a}P{v}");
    }
    if let Some(n) = &negative {
        let _ = writeln!(out, "N03626A{a}P{}", n.start);
        let _ = writeln!(out, "N03627A{a}P{}", n.at_reference);
    }
    if let Some(b) = backlash_units {
        let _ = writeln!(out, "N01851A{a}P{b}");
    }
    for (n, v) in points.iter().chain(negative.iter().flat_map(|n| &n.points)) {
        let _ = writeln!(out, "N{:05}P{v}", 10000 + u32::from(*n));
    }
    out.push_str("%\n");
    Ok((
        out,
        PitchData {
            reference_number: r as u16,
            most_negative: n_neg as u16,
            most_positive: n_pos as u16,
            interval_increments: interval,
            points,
            backlash_units,
            negative,
        },
        t,
        grid,
    ))
}
