//! Numeric CSV: a header of column names, then rows of finite numbers. Lines starting with `#`
//! are comments (metadata), blank lines are skipped. Every error names the source, the line
//! and the column, and says what was expected; each reader states its columns' ranges
//! ([`NumericCsv::check_ranges`]).

use super::range::Range;
use std::collections::HashMap;
use thiserror::Error;

/// Why a CSV input was refused.
#[derive(Debug, Error, PartialEq)]
pub enum CsvError {
    #[error("{source_name}: no header line: the first line must name the columns ({expected})")]
    NoHeader {
        source_name: String,
        expected: String,
    },
    #[error("{source_name} line {line}: {problem}")]
    Header {
        source_name: String,
        line: usize,
        problem: String,
    },
    #[error("{source_name} line {line}, column {column}: {problem}")]
    Field {
        source_name: String,
        line: usize,
        column: String,
        problem: String,
    },
    #[error("{source_name} line {line}: {found} fields, the header has {expected}")]
    Width {
        source_name: String,
        line: usize,
        found: usize,
        expected: usize,
    },
}

/// A parsed numeric table.
#[derive(Clone, Debug, PartialEq)]
pub struct NumericCsv {
    source_name: String,
    columns: Vec<String>,
    index: HashMap<String, usize>,
    /// Rows with their 1-based line numbers.
    pub rows: Vec<(usize, Vec<f64>)>,
    /// Comment lines (without the leading `#`), in order.
    pub comments: Vec<String>,
}

impl NumericCsv {
    /// Parse `text`. Every column in `required` must be present; columns in `optional` may be;
    /// any other column is refused (a misspelt optional column is an error, not ignored).
    pub fn parse(
        text: &str,
        source_name: &str,
        required: &[&str],
        optional: &[&str],
    ) -> Result<NumericCsv, CsvError> {
        let expected = required.join(",");
        let mut lines = text.lines().enumerate().map(|(i, l)| (i + 1, l.trim()));
        let mut comments = Vec::new();
        let (hline, header) = loop {
            match lines.next() {
                None => {
                    return Err(CsvError::NoHeader {
                        source_name: source_name.into(),
                        expected,
                    });
                }
                Some((_, "")) => continue,
                Some((_, l)) if l.starts_with('#') => comments.push(l[1..].trim().to_string()),
                Some(x) => break x,
            }
        };
        let columns: Vec<String> = header.split(',').map(|c| c.trim().to_string()).collect();
        let mut index = HashMap::new();
        for (i, c) in columns.iter().enumerate() {
            if !required.contains(&c.as_str()) && !optional.contains(&c.as_str()) {
                let mut known: Vec<&str> = required.to_vec();
                known.extend_from_slice(optional);
                return Err(CsvError::Header {
                    source_name: source_name.into(),
                    line: hline,
                    problem: format!(
                        "unknown column \"{c}\": the columns are {}",
                        known.join(",")
                    ),
                });
            }
            if index.insert(c.clone(), i).is_some() {
                return Err(CsvError::Header {
                    source_name: source_name.into(),
                    line: hline,
                    problem: format!("column \"{c}\" appears twice"),
                });
            }
        }
        for r in required {
            if !index.contains_key(*r) {
                return Err(CsvError::Header {
                    source_name: source_name.into(),
                    line: hline,
                    problem: format!("missing column \"{r}\": the header must have {expected}"),
                });
            }
        }
        let mut rows = Vec::new();
        for (ln, l) in lines {
            if l.is_empty() {
                continue;
            }
            if let Some(c) = l.strip_prefix('#') {
                comments.push(c.trim().to_string());
                continue;
            }
            let fields: Vec<&str> = l.split(',').collect();
            if fields.len() != columns.len() {
                return Err(CsvError::Width {
                    source_name: source_name.into(),
                    line: ln,
                    found: fields.len(),
                    expected: columns.len(),
                });
            }
            let mut values = Vec::with_capacity(fields.len());
            for (f, c) in fields.iter().zip(&columns) {
                let f = f.trim();
                let v: f64 = f.parse().map_err(|_| CsvError::Field {
                    source_name: source_name.into(),
                    line: ln,
                    column: c.clone(),
                    problem: if f.is_empty() {
                        "empty field: give a number".into()
                    } else {
                        format!("\"{f}\" is not a number")
                    },
                })?;
                if !v.is_finite() {
                    return Err(CsvError::Field {
                        source_name: source_name.into(),
                        line: ln,
                        column: c.clone(),
                        problem: format!("\"{f}\" is not a finite number"),
                    });
                }
                values.push(v);
            }
            rows.push((ln, values));
        }
        Ok(NumericCsv {
            source_name: source_name.into(),
            columns,
            index,
            rows,
            comments,
        })
    }

    /// Every value of each present column of `ranges` within its range, or the first (by
    /// line) that is not, named by its line and column.
    pub fn check_ranges(&self, ranges: &[(&str, Range)]) -> Result<(), CsvError> {
        let cols: Vec<(usize, &str, &Range)> = ranges
            .iter()
            .filter_map(|(c, r)| self.col(c).map(|i| (i, *c, r)))
            .collect();
        for (line, row) in &self.rows {
            for (i, c, r) in &cols {
                r.check(row[*i]).map_err(|problem| CsvError::Field {
                    source_name: self.source_name.clone(),
                    line: *line,
                    column: c.to_string(),
                    problem,
                })?;
            }
        }
        Ok(())
    }

    /// Whether a column is present.
    pub fn has(&self, column: &str) -> bool {
        self.index.contains_key(column)
    }

    /// Column position, if present.
    pub fn col(&self, column: &str) -> Option<usize> {
        self.index.get(column).copied()
    }

    /// The column names in file order.
    pub fn columns(&self) -> &[String] {
        &self.columns
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_with_comments_and_optional_columns() {
        let t = "# seed 3\na,b,c\n1,2,3\n\n# note\n4, 5 ,6e-3\n";
        let c = NumericCsv::parse(t, "x.csv", &["a", "b"], &["c"]).unwrap();
        assert_eq!(c.rows.len(), 2);
        assert_eq!(c.rows[1], (6, vec![4.0, 5.0, 0.006]));
        assert_eq!(c.comments, vec!["seed 3", "note"]);
        assert_eq!(c.col("c"), Some(2));
        let r = Range::new(0.0, 5.0, "mm");
        assert_eq!(c.check_ranges(&[("a", r), ("b", r), ("zz", r)]), Ok(()));
        assert_eq!(
            c.check_ranges(&[("a", Range::new(0.0, 3.0, "mm"))])
                .unwrap_err()
                .to_string(),
            "x.csv line 6, column a: 4 mm is out of range: use 0 to 3 mm"
        );
    }

    #[test]
    fn errors_name_line_and_column() {
        let e = NumericCsv::parse("a,b\n1,2\n3,x\n", "in.csv", &["a", "b"], &[]).unwrap_err();
        assert_eq!(
            e.to_string(),
            "in.csv line 3, column b: \"x\" is not a number"
        );
        let e = NumericCsv::parse("a,b\n1,\n", "in.csv", &["a", "b"], &[]).unwrap_err();
        assert!(e.to_string().contains("line 2, column b: empty field"));
        let e = NumericCsv::parse("a,b\n1,2,3\n", "in.csv", &["a", "b"], &[]).unwrap_err();
        assert_eq!(e.to_string(), "in.csv line 2: 3 fields, the header has 2");
        let e = NumericCsv::parse("a,bb\n", "in.csv", &["a", "b"], &[]).unwrap_err();
        assert!(e.to_string().contains("unknown column \"bb\""), "{e}");
        let e = NumericCsv::parse("a\n", "in.csv", &["a", "b"], &[]).unwrap_err();
        assert!(e.to_string().contains("missing column \"b\""), "{e}");
        let e = NumericCsv::parse("a\nNaN\n", "in.csv", &["a"], &[]).unwrap_err();
        assert!(e.to_string().contains("not a finite number"), "{e}");
        let e = NumericCsv::parse("", "in.csv", &["a"], &[]).unwrap_err();
        assert!(e.to_string().contains("no header line"), "{e}");
    }
}
