//! Evaluation of a measured axis (DESIGN §7): ISO 230-2 positioning statistics, ISO 230-1
//! straightness and angular errors, per-point expanded uncertainty and thermal normalisation.
//!
//! Input is either the service's `Capture`s (all six DOFs, `evaluate_captures`) or a plain
//! table of positioning deviations (`input::parse_deviation_csv` + `iso230_2::evaluate`, the
//! `axiscomp evaluate` CLI). Both go through the same validation (`group`): every target needs
//! the same runs in each direction present, at least two runs (for s) and two targets, and
//! positions that increase with the target index; every error names target, run and direction
//! (and the line, for files).
//!
//! Signs: a deviation is `measured − nominal` (ISO 230-2 `x = P − P_target`), in the head's
//! frame (y along the travel; `comp` maps it to machine axes). Values are in mm and rad inside;
//! µm, µm/m and arcsec exist only where results are printed.

pub mod axis;
pub mod group;
pub mod input;
pub mod iso230_1;
pub mod iso230_2;
pub mod recorded;
pub mod uncertainty;

pub use axis::{
    AxisEvaluation, DofProfile, EvalOptions, ThermalConfig, ThermalReport, evaluate_captures,
};
pub use group::{Directions, Grouped, Keyed, Target};
pub use iso230_1::{Angular, DirectionalStraightness, LineFit, ReferenceLine, Straightness};
pub use iso230_2::{AxisFigures, Iso230_2, Sample, TargetFigures};

use thiserror::Error;

/// Why an evaluation input was refused. Every variant is a problem with the input the user must
/// fix (the CLI exits with 2).
#[derive(Debug, Error, PartialEq)]
pub enum EvalError {
    #[error(transparent)]
    Csv(#[from] crate::util::csv::CsvError),
    #[error("{source_name} line {line}, column {column}: {problem}")]
    Field {
        source_name: String,
        line: usize,
        column: String,
        problem: String,
    },
    #[error("no data: give at least one capture per target, run and direction")]
    Empty,
    #[error(
        "target {target}, run {run}, direction {direction}{at}: {what} is {value}, not a finite number"
    )]
    NotFinite {
        target: u32,
        run: u32,
        direction: &'static str,
        at: String,
        what: String,
        value: f64,
    },
    #[error(
        "target {target} is at {found} mm{at} but at {first} mm{first_at}: a target has one nominal position"
    )]
    TargetMoved {
        target: u32,
        found: f64,
        at: String,
        first: f64,
        first_at: String,
    },
    #[error("target {target}, run {run}, direction {direction} appears twice{lines}: keep one")]
    Duplicate {
        target: u32,
        run: u32,
        direction: &'static str,
        lines: String,
    },
    #[error(
        "{count} capture(s) missing: {list}; every target needs the same runs ({runs}) in each direction present"
    )]
    Missing {
        count: usize,
        list: String,
        runs: String,
    },
    #[error(
        "only {found} run(s) ({runs}): at least 2 runs per direction are needed for the standard uncertainty s"
    )]
    TooFewRuns { found: usize, runs: String },
    #[error("only {found} target(s): at least 2 targets are needed")]
    TooFewTargets { found: usize },
    #[error(
        "target {later} ({later_mm} mm) is not beyond target {earlier} ({earlier_mm} mm): positions must increase with the target index"
    )]
    NotIncreasing {
        earlier: u32,
        earlier_mm: f64,
        later: u32,
        later_mm: f64,
    },
    #[error("thermal normalisation: {0}")]
    Thermal(String),
}

/// " (line 12)" for a located input, "" otherwise.
pub(crate) fn at_line(line: Option<usize>) -> String {
    match line {
        Some(l) => format!(" (line {l})"),
        None => String::new(),
    }
}

/// Mean and sample standard deviation (n − 1) of `v`; the deviation is `None` below 2 values.
pub(crate) fn mean_sd(v: &[f64]) -> (f64, Option<f64>) {
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    if v.len() < 2 {
        return (mean, None);
    }
    let ss: f64 = v.iter().map(|x| (x - mean) * (x - mean)).sum();
    (mean, Some((ss / (n - 1.0)).sqrt()))
}

/// Largest minus smallest of `v` (0 for one value).
pub(crate) fn range(v: impl IntoIterator<Item = f64>) -> f64 {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for x in v {
        lo = lo.min(x);
        hi = hi.max(x);
    }
    if lo.is_finite() { hi - lo } else { 0.0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mean_sd_and_range() {
        let (m, s) = mean_sd(&[1.0, 2.0, 3.0, 4.0]);
        assert_eq!(m, 2.5);
        // Σ(x − 2.5)² = 5, / 3.
        assert!((s.unwrap() - (5.0f64 / 3.0).sqrt()).abs() < 1e-15);
        assert_eq!(mean_sd(&[7.0]), (7.0, None));
        assert_eq!(range([3.0, -1.0, 2.0]), 4.0);
        assert_eq!(range([]), 0.0);
    }
}
