//! The one CSV reader: every CSV file the product reads (capture files, certificates, pose
//! lists and plans, decoupling inputs) goes through [`CsvTable::read`], on the `csv` crate.
//!
//! - A header names the columns, in any order; a reader says which it requires and which it
//!   may take, and any other column is refused (a misspelt optional column is an error, not
//!   ignored).
//! - The delimiter is `,` or `;` (read from the header line, or from a first line `sep=;`
//!   as spreadsheets write it); fields may be quoted (`"1,5"`, a quote doubled inside).
//! - The decimal separator is `.`, or `,` in a `;` file (the European convention); a comment
//!   line `# decimal = ,` or `# decimal = .` above the header says otherwise. A number with
//!   the other separator is refused, not misread: `1,5` is never 15.
//! - Lines starting with `#` are comments (metadata, kept in order), blank lines are skipped.
//! - Every error names the source, the line and the column, and says what was expected; each
//!   reader states its columns' ranges ([`NumericCsv::check_ranges`]).

use super::range::Range;
use std::collections::HashMap;
use thiserror::Error;

/// Why a CSV input was refused.
#[derive(Clone, Debug, Error, PartialEq)]
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
    #[error("{source_name} line {line}: {problem}")]
    Syntax {
        source_name: String,
        line: usize,
        problem: String,
    },
}

/// How a file writes its fields and numbers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Dialect {
    /// `,` or `;`.
    pub delimiter: u8,
    /// Whether numbers write their decimals after a comma (`0,25`).
    pub decimal_comma: bool,
}

/// A CSV file read into text fields: the header's columns, and the rows with their 1-based
/// line numbers, every row as wide as the header.
#[derive(Clone, Debug, PartialEq)]
pub struct CsvTable {
    source_name: String,
    columns: Vec<String>,
    index: HashMap<String, usize>,
    dialect: Dialect,
    /// Rows with their 1-based line numbers.
    pub rows: Vec<(usize, Vec<String>)>,
    /// Comment lines (without the leading `#`), in order.
    pub comments: Vec<String>,
}

/// `# decimal = ,` (or `.`): the separator the comment line `c` (without its `#`) states.
fn decimal_said(c: &str) -> Option<bool> {
    let (key, value) = c.split_once(['=', ':'])?;
    if !key.trim().eq_ignore_ascii_case("decimal") {
        return None;
    }
    match value.trim() {
        "," => Some(true),
        "." => Some(false),
        _ => None,
    }
}

/// The delimiter of a header line: `;` when it has `;` and no `,` outside quotes, else `,`.
fn delimiter_of(header: &str) -> u8 {
    let (mut quoted, mut comma, mut semi) = (false, false, false);
    for ch in header.chars() {
        match ch {
            '"' => quoted = !quoted,
            ',' if !quoted => comma = true,
            ';' if !quoted => semi = true,
            _ => {}
        }
    }
    if semi && !comma { b';' } else { b',' }
}

impl CsvTable {
    /// Read `text`, named `source_name` in errors. Every column in `required` must be present;
    /// columns in `optional` may be; any other column is refused.
    pub fn read(
        text: &str,
        source_name: &str,
        required: &[&str],
        optional: &[&str],
    ) -> Result<CsvTable, CsvError> {
        let expected = required.join(",");
        // Comments, a `sep=` line and blank lines out first (each left as an empty line, so
        // that the csv reader's line numbers stay the file's).
        let mut comments = Vec::new();
        let mut body = String::with_capacity(text.len());
        let (mut sep, mut decimal, mut header_line) = (None, None, None);
        for (i, raw) in text.lines().enumerate() {
            let l = raw.trim();
            if let Some(c) = l.strip_prefix('#') {
                let c = c.trim();
                if header_line.is_none()
                    && let Some(d) = decimal_said(c)
                {
                    decimal = Some(d);
                }
                comments.push(c.to_string());
            } else if header_line.is_none() && sep.is_none() && l.starts_with("sep=") {
                sep = match &l[4..] {
                    ";" => Some(b';'),
                    "," => Some(b','),
                    other => {
                        return Err(CsvError::Syntax {
                            source_name: source_name.into(),
                            line: i + 1,
                            problem: format!(
                                "\"sep={other}\" is not a delimiter this reader takes: use sep=, or sep=;"
                            ),
                        });
                    }
                };
            } else {
                if !l.is_empty() && header_line.is_none() {
                    header_line = Some(l);
                }
                body.push_str(raw);
            }
            body.push('\n');
        }
        let Some(header_text) = header_line else {
            return Err(CsvError::NoHeader {
                source_name: source_name.into(),
                expected,
            });
        };
        let delimiter = sep.unwrap_or_else(|| delimiter_of(header_text));
        let dialect = Dialect {
            delimiter,
            decimal_comma: decimal.unwrap_or(delimiter == b';'),
        };
        // The csv reader neither counts the empty lines it skips nor starts a record's position
        // after them: a record's line is found from its byte offset, past those lines.
        let starts: Vec<usize> = std::iter::once(0)
            .chain(body.match_indices('\n').map(|(i, _)| i + 1))
            .collect();
        let line_at = |p: Option<&csv::Position>| {
            p.map_or(0, |p| {
                let from = p.byte() as usize;
                let skip = body.get(from..).map_or(0, |rest| {
                    rest.len() - rest.trim_start_matches(['\r', '\n']).len()
                });
                starts.partition_point(|&s| s <= from + skip)
            })
        };
        let mut reader = csv::ReaderBuilder::new()
            .has_headers(false)
            .flexible(true)
            .trim(csv::Trim::All)
            .delimiter(delimiter)
            .from_reader(body.as_bytes());
        let mut header: Option<(usize, Vec<String>)> = None;
        let mut rows = Vec::new();
        for record in reader.records() {
            let record = record.map_err(|e| CsvError::Syntax {
                source_name: source_name.into(),
                line: line_at(e.position()),
                problem: format!("not CSV this reader can take ({e})"),
            })?;
            let line = line_at(record.position());
            if record.iter().all(str::is_empty) {
                continue;
            }
            let fields: Vec<String> = record.iter().map(str::to_string).collect();
            if header.is_none() {
                header = Some((line, fields));
            } else {
                rows.push((line, fields));
            }
        }
        let Some((hline, columns)) = header else {
            return Err(CsvError::NoHeader {
                source_name: source_name.into(),
                expected,
            });
        };
        let header_err = |problem: String| CsvError::Header {
            source_name: source_name.into(),
            line: hline,
            problem,
        };
        let mut index = HashMap::new();
        for (i, c) in columns.iter().enumerate() {
            if !required.contains(&c.as_str()) && !optional.contains(&c.as_str()) {
                let mut known: Vec<&str> = required.to_vec();
                known.extend_from_slice(optional);
                return Err(header_err(format!(
                    "unknown column \"{c}\": the columns are {}",
                    known.join(",")
                )));
            }
            if index.insert(c.clone(), i).is_some() {
                return Err(header_err(format!("column \"{c}\" appears twice")));
            }
        }
        for r in required {
            if !index.contains_key(*r) {
                return Err(header_err(format!(
                    "missing column \"{r}\": the header must have {expected}"
                )));
            }
        }
        for (line, fields) in &rows {
            if fields.len() != columns.len() {
                return Err(CsvError::Width {
                    source_name: source_name.into(),
                    line: *line,
                    found: fields.len(),
                    expected: columns.len(),
                });
            }
        }
        Ok(CsvTable {
            source_name: source_name.into(),
            columns,
            index,
            dialect,
            rows,
            comments,
        })
    }

    /// How the file writes its fields and numbers.
    pub fn dialect(&self) -> Dialect {
        self.dialect
    }

    /// Column position, if present.
    pub fn col(&self, column: &str) -> Option<usize> {
        self.index.get(column).copied()
    }

    /// The error at `line`, `column`: `problem`.
    pub fn error(&self, line: usize, column: &str, problem: String) -> CsvError {
        CsvError::Field {
            source_name: self.source_name.clone(),
            line,
            column: column.to_string(),
            problem,
        }
    }

    /// The field `f` of `column` at `line` as a finite number, with this file's decimal
    /// separator.
    pub fn number(&self, line: usize, column: &str, f: &str) -> Result<f64, CsvError> {
        let err = |problem: String| Err(self.error(line, column, problem));
        if f.is_empty() {
            return err("empty field: give a number".into());
        }
        let (ours, other) = if self.dialect.decimal_comma {
            (',', '.')
        } else {
            ('.', ',')
        };
        if f.contains(other) {
            return err(if self.dialect.decimal_comma {
                format!(
                    "\"{f}\" has a decimal point, and this file's decimals follow a comma (a ; file): write {} or put # decimal = . above the header",
                    f.replace('.', ",")
                )
            } else {
                format!(
                    "\"{f}\" has a decimal comma, and this file's decimals follow a point: write {} or put # decimal = , above the header",
                    f.replace(',', ".")
                )
            });
        }
        let v: f64 = match f.replace(ours, ".").parse() {
            Ok(v) => v,
            Err(_) => return err(format!("\"{f}\" is not a number")),
        };
        if !v.is_finite() {
            return err(format!("\"{f}\" is not a finite number"));
        }
        Ok(v)
    }
}

/// A parsed numeric table: every field a finite number.
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

/// How a reader turns the field of a text column into a number (`+` → 1), or says why not.
pub type ReadText<'a> = &'a dyn Fn(&str) -> Result<f64, String>;

/// A text column and its reading.
pub type TextColumn<'a> = (&'a str, ReadText<'a>);

impl NumericCsv {
    /// Parse `text` ([`CsvTable::read`]): every field a number.
    pub fn parse(
        text: &str,
        source_name: &str,
        required: &[&str],
        optional: &[&str],
    ) -> Result<NumericCsv, CsvError> {
        Self::parse_with(text, source_name, required, optional, &[])
    }

    /// Parse `text`, the columns of `text_columns` through their own reading.
    pub fn parse_with(
        text: &str,
        source_name: &str,
        required: &[&str],
        optional: &[&str],
        text_columns: &[TextColumn],
    ) -> Result<NumericCsv, CsvError> {
        let t = CsvTable::read(text, source_name, required, optional)?;
        let readers: Vec<Option<ReadText>> = t
            .columns
            .iter()
            .map(|c| {
                text_columns
                    .iter()
                    .find(|(name, _)| name == c)
                    .map(|(_, f)| *f)
            })
            .collect();
        let mut rows = Vec::with_capacity(t.rows.len());
        for (line, fields) in &t.rows {
            let mut values = Vec::with_capacity(fields.len());
            for ((f, c), read) in fields.iter().zip(&t.columns).zip(&readers) {
                values.push(match read {
                    Some(read) => read(f).map_err(|p| t.error(*line, c, p))?,
                    None => t.number(*line, c, f)?,
                });
            }
            rows.push((*line, values));
        }
        Ok(NumericCsv {
            source_name: t.source_name,
            columns: t.columns,
            index: t.index,
            rows,
            comments: t.comments,
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

    #[test]
    fn semicolons_quotes_and_a_decimal_comma() {
        // A European vendor's export: `;`, decimal commas, quoted fields, columns reordered,
        // blank and comment lines between the rows.
        let t = "# exported 2026-11-30\nb;\"a\"\n\"0,5\";-1,25\n\n# pause\n2;3e-3\n";
        let c = NumericCsv::parse(t, "eu.csv", &["a", "b"], &[]).unwrap();
        assert_eq!(c.columns(), ["b", "a"]);
        assert_eq!(c.rows, vec![(3, vec![0.5, -1.25]), (6, vec![2.0, 0.003])]);
        // A decimal point in a `;` file is refused, not read as a thousand.
        let e = NumericCsv::parse("a;b\n1;2.5\n", "eu.csv", &["a", "b"], &[]).unwrap_err();
        assert_eq!(
            e.to_string(),
            "eu.csv line 2, column b: \"2.5\" has a decimal point, and this file's decimals follow a comma (a ; file): write 2,5 or put # decimal = . above the header"
        );
        // The file says its decimals: `;` with points.
        let c =
            NumericCsv::parse("# decimal = .\na;b\n1;2.5\n", "x.csv", &["a", "b"], &[]).unwrap();
        assert_eq!(c.rows, vec![(3, vec![1.0, 2.5])]);
        // A comma file with decimal commas in quotes, as it says.
        let c =
            NumericCsv::parse("#decimal=,\na,b\n\"1,5\",2\n", "x.csv", &["a", "b"], &[]).unwrap();
        assert_eq!(c.rows, vec![(3, vec![1.5, 2.0])]);
        // Without saying so, a quoted decimal comma in a comma file is refused.
        let e = NumericCsv::parse("a,b\n\"1,5\",2\n", "x.csv", &["a", "b"], &[]).unwrap_err();
        assert!(
            e.to_string()
                .starts_with("x.csv line 2, column a: \"1,5\" has a decimal comma"),
            "{e}"
        );
        // A spreadsheet's `sep=` line.
        let c = NumericCsv::parse("sep=;\na\n1,5\n", "x.csv", &["a"], &[]).unwrap();
        assert_eq!(c.rows, vec![(3, vec![1.5])]);
        let e = NumericCsv::parse("sep=|\na\n1\n", "x.csv", &["a"], &[]).unwrap_err();
        assert!(e.to_string().contains("line 1: \"sep=|\""), "{e}");
    }

    #[test]
    fn text_columns_are_read_by_their_reader() {
        let dir = |f: &str| match f {
            "+" => Ok(1.0),
            "-" => Ok(-1.0),
            _ => Err(format!("\"{f}\" is not a direction: give + or -")),
        };
        let t = "d;x\n+;1\n-;2\n";
        let c = NumericCsv::parse_with(t, "d.csv", &["d", "x"], &[], &[("d", &dir)]).unwrap();
        assert_eq!(c.rows, vec![(2, vec![1.0, 1.0]), (3, vec![-1.0, 2.0])]);
        let e = NumericCsv::parse_with("x,d\n1,up\n", "d.csv", &["d", "x"], &[], &[("d", &dir)])
            .unwrap_err();
        assert_eq!(
            e.to_string(),
            "d.csv line 2, column d: \"up\" is not a direction: give + or -"
        );
    }
}
