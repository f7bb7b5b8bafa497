//! The follower encoder's calibration certificate: the length reference along the axis.
//!
//! Format (CSV, UTF-8, read by `util::csv`: `,` or `;`, quoted fields, a decimal comma in a
//! `;` file): lines starting with `#` are comments, blank lines are skipped; the first other
//! line is the header, these four columns in any order,
//!
//! ```text
//! position_mm,error_um,direction,uncertainty_um
//! ```
//!
//! then one row per calibrated point: the encoder position (mm), the stage's error there
//! (µm, actual − indicated, the sign of a measured deviation), the direction of approach
//! (`+` or `-`) and the point's standard uncertainty (µm, k = 1). Rows of one direction are
//! in increasing position; the two directions may come in either order, one after the other
//! or interleaved. A certificate with one direction only applies to both.
//!
//! Every refused row names the file, the line and (for a field) the column.

use super::Direction;
use crate::util::csv::{CsvError, CsvTable};
use crate::util::range::{POSITION_MM, Range};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// The smallest standard uncertainty a certificate row may state (µm).
pub const MIN_UNCERTAINTY_UM: f64 = 0.001;

/// The header a certificate starts with, as the simulator writes it (any order is read).
pub const HEADER: &str = "position_mm,error_um,direction,uncertainty_um";

/// The columns of a certificate.
const COLUMNS: [&str; 4] = ["position_mm", "error_um", "direction", "uncertainty_um"];

/// Why a certificate was refused.
#[derive(Debug, Error, PartialEq)]
pub enum CertificateError {
    #[error("{file} line {line}: {problem}")]
    Row {
        file: String,
        line: usize,
        problem: String,
    },
    #[error("{file}: {problem}")]
    File { file: String, problem: String },
    #[error(transparent)]
    Csv(#[from] CsvError),
}

/// One calibrated point (internal units: mm).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CertificatePoint {
    pub position_mm: f64,
    pub error_mm: f64,
    pub direction: Direction,
    pub uncertainty_mm: f64,
}

/// A parsed certificate: its points per direction, in increasing position.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Certificate {
    /// Where it came from (the file name).
    pub name: String,
    pub up: Vec<CertificatePoint>,
    pub down: Vec<CertificatePoint>,
}

impl Certificate {
    /// Parse certificate text; `file` names it in errors.
    pub fn parse(text: &str, file: &str) -> Result<Certificate, CertificateError> {
        let row = |line: usize, problem: String| CertificateError::Row {
            file: file.to_string(),
            line,
            problem,
        };
        let table = CsvTable::read(text, file, &COLUMNS, &[])?;
        let at = |name: &str| table.col(name).unwrap_or(0);
        let (cp, ce, cd, cu) = (
            at("position_mm"),
            at("error_um"),
            at("direction"),
            at("uncertainty_um"),
        );
        let (mut up, mut down): (Vec<CertificatePoint>, Vec<CertificatePoint>) = (vec![], vec![]);
        let mut last_line = [0usize; 2];
        for (line, fields) in &table.rows {
            let line = *line;
            let number = |k: usize, name: &str| table.number(line, name, &fields[k]);
            let in_range =
                |name: &str, v: f64, r: Range| r.check(v).map_err(|p| table.error(line, name, p));
            let position_mm = in_range("position_mm", number(cp, "position_mm")?, POSITION_MM)?;
            // A stage's error beyond 10 mm is a wrong unit, not an error to map.
            let error_um = in_range(
                "error_um",
                number(ce, "error_um")?,
                Range::symmetric(10_000.0, "µm"),
            )?;
            let direction = match fields[cd].as_str() {
                "+" => Direction::Up,
                "-" => Direction::Down,
                "" => {
                    return Err(table
                        .error(line, "direction", "empty field: write + or -".into())
                        .into());
                }
                other => {
                    return Err(table
                        .error(line, "direction", format!("\"{other}\" is neither + nor -"))
                        .into());
                }
            };
            let u = number(cu, "uncertainty_um")?;
            // A laser certificate states tenths of a micrometre; below a nanometre the figure is
            // a typo (and would vanish in the conversion to millimetres).
            if u < MIN_UNCERTAINTY_UM {
                return Err(table
                    .error(
                        line,
                        "uncertainty_um",
                        format!(
                            "{} is below {MIN_UNCERTAINTY_UM} µm: write the point's standard uncertainty in micrometres",
                            fields[cu]
                        ),
                    )
                    .into());
            }
            let u = in_range(
                "uncertainty_um",
                u,
                Range::new(MIN_UNCERTAINTY_UM, 1000.0, "µm"),
            )?;
            let (list, k) = match direction {
                Direction::Up => (&mut up, 0),
                Direction::Down => (&mut down, 1),
            };
            if let Some(prev) = list.last()
                && position_mm <= prev.position_mm
            {
                return Err(row(
                    line,
                    format!(
                        "position {position_mm} mm is not above the previous {} row's {} mm (line {}): rows of one direction go in increasing position",
                        direction.sign(),
                        prev.position_mm,
                        last_line[k]
                    ),
                ));
            }
            last_line[k] = line;
            list.push(CertificatePoint {
                position_mm,
                error_mm: error_um * 1e-3,
                direction,
                uncertainty_mm: u * 1e-3,
            });
        }
        let file_err = |problem: String| CertificateError::File {
            file: file.to_string(),
            problem,
        };
        if up.len().max(down.len()) < 2
            || (!up.is_empty() && up.len() < 2)
            || (!down.is_empty() && down.len() < 2)
        {
            return Err(file_err(
                "a certificate needs at least two points in each direction it gives".to_string(),
            ));
        }
        Ok(Certificate {
            name: file.to_string(),
            up,
            down,
        })
    }

    /// The points approached in `dir` (the other direction's when the certificate has one
    /// direction only).
    pub fn points(&self, dir: Direction) -> &[CertificatePoint] {
        match dir {
            Direction::Up if !self.up.is_empty() => &self.up,
            Direction::Down if !self.down.is_empty() => &self.down,
            _ if self.up.is_empty() => &self.down,
            _ => &self.up,
        }
    }

    /// Whether both directions were calibrated.
    pub fn bidirectional(&self) -> bool {
        !self.up.is_empty() && !self.down.is_empty()
    }

    /// The error (mm) and its standard uncertainty at `position_mm` approached in `dir`,
    /// linear between points, held beyond the ends.
    pub fn at(&self, position_mm: f64, dir: Direction) -> (f64, f64) {
        let p = self.points(dir);
        let xs: Vec<f64> = p.iter().map(|c| c.position_mm).collect();
        let e: Vec<f64> = p.iter().map(|c| c.error_mm).collect();
        let u: Vec<f64> = p.iter().map(|c| c.uncertainty_mm).collect();
        (
            crate::util::interpolate(&xs, &e, position_mm),
            crate::util::interpolate(&xs, &u, position_mm),
        )
    }

    /// The range of positions it covers (mm).
    pub fn span(&self) -> (f64, f64) {
        let all = self.up.iter().chain(&self.down).map(|c| c.position_mm);
        all.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| {
            (lo.min(x), hi.max(x))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn err(text: &str) -> String {
        Certificate::parse(text, "cert.csv")
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn a_good_certificate_reads_in_mm() {
        let c = Certificate::parse(
            "# vendor X\nposition_mm,error_um,direction,uncertainty_um\n0,0.5,+,0.2\n10,1.5,+,0.2\n0,1,-,0.3\n10,2,-,0.3\n",
            "cert.csv",
        )
        .unwrap();
        assert!(c.bidirectional());
        let (e, u) = c.at(5.0, Direction::Up);
        assert!((e - 1.0e-3).abs() < 1e-15 && (u - 0.2e-3).abs() < 1e-15);
        assert_eq!(c.at(20.0, Direction::Down).0, 2e-3);
    }

    #[test]
    fn bad_rows_are_refused_with_their_line() {
        let h = "position_mm,error_um,direction,uncertainty_um\n";
        assert_eq!(
            err(&format!("{h}0,0,+,0.2\n10,0,+,0.2\n5,0,+,0.2\n")),
            "cert.csv line 4: position 5 mm is not above the previous + row's 10 mm (line 3): rows of one direction go in increasing position"
        );
        assert_eq!(
            err(&format!("{h}0,0,+,0.2\n10,0,,0.2\n")),
            "cert.csv line 3, column direction: empty field: write + or -"
        );
        assert_eq!(
            err(&format!("{h}0,NaN,+,0.2\n")),
            "cert.csv line 2, column error_um: \"NaN\" is not a finite number"
        );
        assert_eq!(
            err(&format!("{h}0,1,+\n")),
            "cert.csv line 2: 3 fields, the header has 4"
        );
        assert_eq!(
            err("x,y\n"),
            "cert.csv line 1: unknown column \"x\": the columns are position_mm,error_um,direction,uncertainty_um"
        );
        assert!(err(&format!("{h}0,1,+,0.2\n")).contains("at least two points"));
        assert_eq!(
            err(""),
            "cert.csv: no header line: the first line must name the columns (position_mm,error_um,direction,uncertainty_um)"
        );
        // A vanishing uncertainty (found by the fuzzer: 0.201e-320 µm became 0 mm).
        assert_eq!(
            err(&format!("{h}0,1,+,0.201e-320\n")),
            "cert.csv line 2, column uncertainty_um: 0.201e-320 is below 0.001 µm: write the point's standard uncertainty in micrometres"
        );
    }
}
