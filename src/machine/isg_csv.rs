//! Beckhoff TwinCAT CNC volumetric compensation (TF5280), the `ISG_CSV` parameter file: the
//! writer and its one reader.
//!
//! Confirmed from the manual (infosys.beckhoff.com, TF5280, "ISG CSV format" and "Units of
//! measure"; the same pages on isg-stuttgart.de): a header line names the columns (arguments
//! and parameters), the records follow, one per line; `//` starts a row comment; a line `#`
//! is a "file break" after which a new header and its records follow; component errors are
//! named as ISO 230-1 does (`X EXX EYX EZX EAX EBX ECX`), values in mm and rad, the argument in
//! mm; position errors stand in a header of their own with one data row. The example
//! separates columns by blanks.
//!
//! Not confirmed: the names of the linear axes' squarenesses. The manual's example of
//! position errors shows only a rotary axis' (`Y0A Z0A X0B`); this file writes `C0Y B0Z A0Z`
//! after ISO 230-1's location errors `EC0Y`, `EB0Z`, `EA0Z` without the `E`, as the manual's
//! example drops it. Check them against the control before use. The chain (`Chain` of the
//! compensation list, `workpiece_axes`) is not in this file: the control's start-up list
//! holds it.
//!
//! The reader takes what the writer writes and the manual's examples: blanks, `;` or `,`
//! between columns, a decimal point, component columns in any order and any subset (an
//! absent one is zero). A block that depends on two arguments (the manual's `Z X EXX …`) is
//! refused: the model here is ISO 230-1's rigid body, one argument per table.

use super::error::MachineError;
use super::model::{ComponentTable, Squareness, component_names};
use crate::comp::mapping::MachineAxis;
use std::fmt::Write as _;
use std::path::Path;

/// What an `ISG_CSV` file holds: component errors per axis and the squarenesses.
#[derive(Clone, Debug, PartialEq)]
pub struct IsgCsv {
    pub tables: Vec<ComponentTable>,
    pub squareness: Option<Squareness>,
}

/// The file for `tables` and `squareness`, headed by `title` (one comment line per line of
/// it).
pub fn write(tables: &[ComponentTable], squareness: Squareness, title: &str) -> String {
    let mut out = String::new();
    for line in title.lines() {
        let _ = writeln!(out, "// {line}");
    }
    out.push_str("// ISO 230-1 component errors: translations in mm, rotations in rad, against the axis position in mm\n");
    for (i, t) in tables.iter().enumerate() {
        if i > 0 {
            out.push_str("#\n");
        }
        let axis = t.axis();
        let _ = writeln!(out, "// Component errors of the {axis} axis");
        let _ = writeln!(out, "{} {}", axis.letter(), component_names(axis).join(" "));
        for (p, row) in t.positions_mm().iter().zip(t.values()) {
            let _ = write!(out, "{p:.3}");
            for v in &row[..3] {
                let _ = write!(out, " {v:.7}");
            }
            for v in &row[3..] {
                let _ = write!(out, " {v:.10}");
            }
            out.push('\n');
        }
    }
    if !tables.is_empty() {
        out.push_str("#\n");
    }
    out.push_str("// Squarenesses of the linear axes (rad), X the reference\n");
    let _ = writeln!(out, "{}", Squareness::NAMES.join(" "));
    let s = squareness.to_array();
    let _ = writeln!(out, "{:.10} {:.10} {:.10}", s[0], s[1], s[2]);
    out
}

/// What a header column names.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Column {
    Argument(MachineAxis),
    /// Component error `k` (0..6) of an axis.
    Component(MachineAxis, usize),
    Square(usize),
}

fn column(name: &str) -> Option<Column> {
    if let Some(a) = MachineAxis::from_letter(name) {
        return Some(Column::Argument(a));
    }
    if let Some(k) = Squareness::NAMES
        .iter()
        .position(|n| n.eq_ignore_ascii_case(name))
    {
        return Some(Column::Square(k));
    }
    MachineAxis::ALL.into_iter().find_map(|a| {
        component_names(a)
            .iter()
            .position(|n| n.eq_ignore_ascii_case(name))
            .map(|k| Column::Component(a, k))
    })
}

fn fields(line: &str) -> Vec<&str> {
    line.split(|c: char| c.is_whitespace() || c == ';' || c == ',')
        .filter(|s| !s.is_empty())
        .collect()
}

/// A block: its header's columns and its rows of values, with the lines they stand on.
struct Block {
    line: usize,
    columns: Vec<Column>,
    rows: Vec<Vec<f64>>,
}

/// Where an error lies: the file and the line.
struct At<'a>(&'a str);

impl At<'_> {
    fn err(&self, line: usize, problem: String) -> MachineError {
        MachineError::File {
            path: self.0.to_string(),
            line,
            problem,
        }
    }
}

/// The file's blocks (a header and its rows each), comments and blank lines dropped.
fn blocks(text: &str, at: &At) -> Result<Vec<Block>, MachineError> {
    let mut blocks: Vec<Block> = Vec::new();
    let mut open: Option<Block> = None;
    for (i, raw) in text.lines().enumerate() {
        let n = i + 1;
        let content = raw.split("//").next().unwrap_or("").trim();
        if content.is_empty() {
            continue;
        }
        if content.starts_with('#') {
            blocks.extend(open.take());
            continue;
        }
        let f = fields(content);
        let Some(b) = open.as_mut() else {
            let columns = f
                .iter()
                .map(|name| {
                    column(name).ok_or_else(|| {
                        at.err(
                            n,
                            format!(
                                "column {name} is not an argument (X, Y, Z), a component error of a linear axis (EXX … ECZ) or a squareness ({})",
                                Squareness::NAMES.join(", ")
                            ),
                        )
                    })
                })
                .collect::<Result<Vec<_>, _>>()?;
            open = Some(Block {
                line: n,
                columns,
                rows: Vec::new(),
            });
            continue;
        };
        if f.len() != b.columns.len() {
            return Err(at.err(
                n,
                format!(
                    "{} values under a header of {} columns (line {})",
                    f.len(),
                    b.columns.len(),
                    b.line
                ),
            ));
        }
        let values = f
            .iter()
            .map(|s| {
                s.parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite())
                    .ok_or_else(|| {
                        at.err(
                            n,
                            format!("{s} is not a number (mm or rad, with a decimal point)"),
                        )
                    })
            })
            .collect::<Result<Vec<_>, _>>()?;
        b.rows.push(values);
    }
    blocks.extend(open);
    Ok(blocks)
}

/// A block of position errors alone: the squarenesses, one row.
fn squareness_of(b: &Block, at: &At) -> Result<Squareness, MachineError> {
    if b.columns.iter().any(|c| !matches!(c, Column::Square(_))) {
        return Err(at.err(
            b.line,
            "component errors without their argument: name the axis (X, Y or Z) as the first column".into(),
        ));
    }
    let [row] = b.rows.as_slice() else {
        return Err(at.err(
            b.line,
            format!("position errors take one data row, found {}", b.rows.len()),
        ));
    };
    let mut s = [0.0; 3];
    for (c, v) in b.columns.iter().zip(row) {
        if let Column::Square(k) = c {
            s[*k] = *v;
        }
    }
    Ok(Squareness::from_array(s))
}

/// A block against one axis (its argument in column `arg`): that axis's table.
fn table_of(
    b: &Block,
    axis: MachineAxis,
    arg: usize,
    at: &At,
) -> Result<ComponentTable, MachineError> {
    for c in &b.columns {
        match *c {
            Column::Component(a, k) if a != axis => {
                return Err(at.err(
                    b.line,
                    format!(
                        "{} is a component error of {a}, in a block against {axis}: give each axis a block of its own",
                        component_names(a)[k]
                    ),
                ));
            }
            Column::Square(k) => {
                return Err(at.err(
                    b.line,
                    format!(
                        "the squareness {} in a block against {axis}: give it a block of its own",
                        Squareness::NAMES[k]
                    ),
                ));
            }
            _ => {}
        }
    }
    let positions = b.rows.iter().map(|row| row[arg]).collect();
    let values = b
        .rows
        .iter()
        .map(|row| {
            let mut v = [0.0; 6];
            for (c, x) in b.columns.iter().zip(row) {
                if let Column::Component(_, k) = c {
                    v[*k] = *x;
                }
            }
            v
        })
        .collect();
    ComponentTable::new(axis, positions, values).map_err(|e| at.err(b.line, e.to_string()))
}

/// Read `text` (from `path`, named in every error).
pub fn parse(text: &str, path: &str) -> Result<IsgCsv, MachineError> {
    let at = At(path);
    let mut tables: Vec<ComponentTable> = Vec::new();
    let mut squareness: Option<Squareness> = None;
    for b in blocks(text, &at)? {
        let arguments: Vec<(usize, MachineAxis)> = b
            .columns
            .iter()
            .enumerate()
            .filter_map(|(i, c)| match c {
                Column::Argument(a) => Some((i, *a)),
                _ => None,
            })
            .collect();
        match arguments.as_slice() {
            [] => {
                if squareness.is_some() {
                    return Err(at.err(b.line, "the squarenesses are given twice".into()));
                }
                squareness = Some(squareness_of(&b, &at)?);
            }
            [(arg, axis)] => {
                if tables.iter().any(|t| t.axis() == *axis) {
                    return Err(at.err(
                        b.line,
                        format!("the component errors of {axis} are given twice"),
                    ));
                }
                tables.push(table_of(&b, *axis, *arg, &at)?);
            }
            more => {
                let names: Vec<&str> = more.iter().map(|(_, a)| a.letter()).collect();
                return Err(at.err(
                    b.line,
                    format!(
                        "a block against {} arguments ({}): axiscomp's model takes each table against its own axis alone",
                        more.len(),
                        names.join(", ")
                    ),
                ));
            }
        }
    }
    Ok(IsgCsv { tables, squareness })
}

/// Read the file at `path`.
pub fn read(path: &Path) -> Result<IsgCsv, MachineError> {
    let text = std::fs::read_to_string(path).map_err(|e| MachineError::Io {
        path: path.display().to_string(),
        problem: e.to_string(),
    })?;
    parse(&text, &path.display().to_string())
}
