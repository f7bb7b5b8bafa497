//! The positioning-deviation CSV of `axiscomp evaluate`:
//! `target_index,target_mm,run,direction,deviation_um`, rows in any order, `direction` `+` or
//! `-`, `#` comment lines allowed, read by `util::csv` (`,` or `;`, quoted fields, the same
//! errors everywhere); the direction column, the one text column, is read as `+` or `-`, and
//! the integer columns are checked after, each error naming the line and the column.

use super::EvalError;
use super::iso230_2::Sample;
use crate::run::Direction;
use crate::units::MM_PER_UM;
use crate::util::csv::NumericCsv;
use crate::util::range::{POSITION_MM, Range};

/// The header, in the documented order (any column order is accepted).
pub const COLUMNS: [&str; 5] = [
    "target_index",
    "target_mm",
    "run",
    "direction",
    "deviation_um",
];

/// Parse the deviation CSV into samples (deviations in mm).
pub fn parse_deviation_csv(text: &str, source_name: &str) -> Result<Vec<Sample>, EvalError> {
    let direction = |f: &str| match f {
        "+" => Ok(1.0),
        "-" => Ok(-1.0),
        "" => Err("empty field: give + or -".to_string()),
        _ => Err(format!("\"{f}\" is not a direction: give + or -")),
    };
    let csv = NumericCsv::parse_with(
        text,
        source_name,
        &COLUMNS,
        &[],
        &[("direction", &direction)],
    )?;
    // A deviation beyond 10 mm is a wrong unit or a crash, not a positioning error.
    csv.check_ranges(&[
        ("target_mm", POSITION_MM),
        ("deviation_um", Range::symmetric(10_000.0, "µm")),
    ])?;
    let col = |name: &str| csv.col(name).unwrap_or(0);
    let (ct, cp, cr, cd, cv) = (
        col("target_index"),
        col("target_mm"),
        col("run"),
        col("direction"),
        col("deviation_um"),
    );
    let field = |line: usize, column: &str, problem: String| EvalError::Field {
        source_name: source_name.into(),
        line,
        column: column.into(),
        problem,
    };
    let whole = |line: usize, column: &str, v: f64, min: f64| -> Result<u32, EvalError> {
        if v.fract() != 0.0 || v < min || v > u32::MAX as f64 {
            return Err(field(
                line,
                column,
                format!("{v} is not a whole number ≥ {min}"),
            ));
        }
        Ok(v as u32)
    };
    csv.rows
        .iter()
        .map(|(line, row)| {
            Ok(Sample {
                target_index: whole(*line, "target_index", row[ct], 0.0)?,
                target_mm: row[cp],
                run: whole(*line, "run", row[cr], 1.0)?,
                direction: if row[cd] > 0.0 {
                    Direction::Up
                } else {
                    Direction::Down
                },
                line: Some(*line),
                value: row[cv] * MM_PER_UM,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_any_order_and_maps_units() {
        let t = "# from the PSI report\ndirection,run,target_index,target_mm,deviation_um\n-,2,1,10.5,-0.25\n+,1,0,0,1.5\n";
        let s = parse_deviation_csv(t, "c.csv").unwrap();
        assert_eq!(s.len(), 2);
        assert_eq!(s[0].direction, Direction::Down);
        assert_eq!((s[0].target_index, s[0].run, s[0].line), (1, 2, Some(3)));
        assert!((s[0].value + 0.25e-3).abs() < 1e-18);
        assert_eq!(s[1].direction, Direction::Up);
    }

    #[test]
    fn errors_name_line_and_column() {
        let h = "target_index,target_mm,run,direction,deviation_um\n";
        let e = |body: &str| {
            parse_deviation_csv(&format!("{h}{body}"), "in.csv")
                .unwrap_err()
                .to_string()
        };
        assert_eq!(
            e("0,0,1,up,1\n"),
            "in.csv line 2, column direction: \"up\" is not a direction: give + or -"
        );
        assert_eq!(
            e("0,0,1,,1\n"),
            "in.csv line 2, column direction: empty field: give + or -"
        );
        assert_eq!(
            e("0,0,1,+,x\n"),
            "in.csv line 2, column deviation_um: \"x\" is not a number"
        );
        assert_eq!(
            e("0,0,1.5,+,1\n"),
            "in.csv line 2, column run: 1.5 is not a whole number ≥ 1"
        );
        assert_eq!(
            e("-1,0,1,+,1\n"),
            "in.csv line 2, column target_index: -1 is not a whole number ≥ 0"
        );
        assert_eq!(e("0,0,1,+\n"), "in.csv line 2: 4 fields, the header has 5");
        let e = parse_deviation_csv("target_index,target_mm,run,deviation_um\n", "in.csv")
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing column \"direction\""), "{e}");
    }
}
