//! HEIDENHAIN KinematicsComp: a compensation table (`*.COM`) per linear axis and the excerpt of
//! the kinematics description that links its columns into the transformation chain, with the
//! squarenesses as position errors; the writer and its one reader.
//!
//! Confirmed from the manuals:
//! - iTNC 530 HSCI Technical Manual (07/2013), page 680: HEIDENHAIN's recommended scheme for a
//!   linear axis puts its six ISO 230-1 component errors into columns `C1` … `C6` of its COM
//!   file in the order EXX, EYX, EZX, EAX, EBX, ECX, and defines the errors before the axis
//!   in the transformation chain; page 684: the kinematics description's columns `NR DOC KEY
//!   AXIS COORD COMPTAB`, position errors as `Trans` entries before the axis and taken back
//!   after it (`B0X Trans B`, `MachAxis X`, `-B0X Trans B`), the table ending `[END]`;
//! - MANUALplus 620 Technical Manual, page 716: a `*.COM` table's compensation points stand in
//!   its `AXISPOS` column, against the machine datum.
//!
//! Not confirmed: the units of `C4`–`C6` and of a rotational `Trans` (written here in degrees,
//! as the kinematics description's rotations are), the form of a `COMPTAB` reference (written
//! `X..C2` after page 684's `A..C2`), the `BEGIN` line's form (that of HEIDENHAIN's other
//! tables), and whether the control wants the errors or their negatives (written: the errors,
//! which KinematicsComp puts into the chain as the machine's real transformation). Check them
//! against the machine's own kinematics before use.

use super::error::{MachineError, read_text};
use super::model::{ComponentTable, MachineModel, Squareness, component_names};
use crate::comp::mapping::MachineAxis;
use std::fmt::Write as _;
use std::path::Path;

/// The kinematics description's excerpt.
pub const KINEMATICS_FILE: &str = "KINEMATICS.TAB";
/// What the files are, in words, beside them.
pub const README_FILE: &str = "README.txt";

/// The COM file of `axis`: `X.COM`.
pub fn com_file(axis: MachineAxis) -> String {
    format!("{}.COM", axis.letter())
}

/// What the files carry: a table per axis and the squarenesses.
#[derive(Clone, Debug, PartialEq)]
pub struct KinematicsComp {
    pub tables: Vec<ComponentTable>,
    pub squareness: Squareness,
}

/// The files for `model` (name, text): `X.COM`, `Y.COM`, `Z.COM`, `KINEMATICS.TAB`, and
/// `README.txt` with `title` and what the files hold (the tables take no comments).
pub fn write(model: &MachineModel, title: &str) -> Vec<(String, String)> {
    let mut files = Vec::new();
    for t in model.tables() {
        let name = com_file(t.axis());
        let mut out = String::new();
        let _ = writeln!(out, "BEGIN {name} MM");
        let _ = writeln!(
            out,
            "{:<6} {:>12} {:>14} {:>14} {:>14} {:>16} {:>16} {:>16}",
            "NR", "AXISPOS", "C1", "C2", "C3", "C4", "C5", "C6"
        );
        for (i, (p, row)) in t.positions_mm().iter().zip(t.values()).enumerate() {
            let _ = write!(out, "{i:<6} {p:>+12.4}");
            for v in &row[..3] {
                let _ = write!(out, " {v:>+14.7}");
            }
            for v in &row[3..] {
                let _ = write!(out, " {:>+16.10}", v.to_degrees());
            }
            out.push('\n');
        }
        out.push_str("[END]\n");
        files.push((name, out));
    }
    files.push((KINEMATICS_FILE.to_string(), kinematics(model)));
    // HEIDENHAIN's tables hold no comments: what they are stands beside them.
    let mut readme = String::new();
    for l in title.lines() {
        let _ = writeln!(readme, "{l}");
    }
    readme.push_str(
        "HEIDENHAIN KinematicsComp files written by axiscomp from the machine's ISO 230-1 model.\n\
         X.COM, Y.COM, Z.COM: each axis's six component errors against its position (AXISPOS, mm):\n\
         C1-C3 the translations EX*, EY*, EZ* (mm), C4-C6 the rotations EA*, EB*, EC* (degrees).\n\
         KINEMATICS.TAB: the excerpt of the transformation chain that links those columns before\n\
         each axis (COMPTAB X..C2: column C2 of X.COM) and sets the squarenesses C0Y, B0Z, A0Z\n\
         (degrees, X the reference) before their axis, taken back after it.\n\
         What of this is confirmed from HEIDENHAIN's manuals and what must be checked against the\n\
         machine's own kinematics: axiscomp's user guide, \"Integrating with the controls\".\n",
    );
    files.push((README_FILE.to_string(), readme));
    files
}

/// The transformation chain's excerpt: each axis's six errors before it, referring to its COM
/// file's columns, and the squarenesses as position errors around their axis.
fn kinematics(model: &MachineModel) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "BEGIN {KINEMATICS_FILE}");
    let _ = writeln!(
        out,
        "{:<4} {:<8} {:<9} {:<4} {:>16} {:<8}",
        "NR", "DOC", "KEY", "AXIS", "COORD", "COMPTAB"
    );
    let mut nr = 0;
    let mut line = |out: &mut String, doc: &str, key: &str, axis: &str, coord: &str, comp: &str| {
        let _ = writeln!(
            out,
            "{nr:<4} {doc:<8} {key:<9} {axis:<4} {coord:>16} {comp:<8}"
        );
        nr += 1;
    };
    let s = model.squareness;
    let directions = ["X", "Y", "Z", "A", "B", "C"];
    for &axis in model.chain.order().iter() {
        let names = component_names(axis);
        for (k, name) in names.iter().enumerate() {
            let comp = format!("{}..C{}", axis.letter(), k + 1);
            line(&mut out, name, "Trans", directions[k], "", &comp);
        }
        // The squareness of this axis (X the reference): its line turned before it, taken back
        // after it.
        let turns: Vec<(&str, &str, f64)> = match axis {
            MachineAxis::X => vec![],
            MachineAxis::Y => vec![("C0Y", "C", s.c0y)],
            MachineAxis::Z => vec![("B0Z", "B", s.b0z), ("A0Z", "A", s.a0z)],
        };
        for &(doc, dir, v) in &turns {
            line(
                &mut out,
                doc,
                "Trans",
                dir,
                &format!("{:+.10}", v.to_degrees()),
                "",
            );
        }
        line(&mut out, "", "MachAxis", axis.letter(), "", "");
        for &(doc, dir, v) in turns.iter().rev() {
            line(
                &mut out,
                &format!("-{doc}"),
                "Trans",
                dir,
                &format!("{:+.10}", -v.to_degrees()),
                "",
            );
        }
    }
    out.push_str("[END]\n");
    out
}

fn err(path: &str, line: usize, problem: String) -> MachineError {
    MachineError::at(path, line, problem)
}

/// The lines of a HEIDENHAIN table between its `BEGIN` line and `[END]`, comments (`;`) and
/// blank lines dropped, each with its line number: the header first.
fn table_lines<'a>(text: &'a str, path: &str) -> Result<Vec<(usize, &'a str)>, MachineError> {
    let mut lines = Vec::new();
    let mut begun = false;
    let mut ended = false;
    for (i, raw) in text.lines().enumerate() {
        let content = raw.split(';').next().unwrap_or("").trim();
        if content.is_empty() {
            continue;
        }
        if !begun {
            if !content.to_ascii_uppercase().starts_with("BEGIN") {
                return Err(err(
                    path,
                    i + 1,
                    "a HEIDENHAIN table starts with its BEGIN line".into(),
                ));
            }
            begun = true;
            continue;
        }
        if content.eq_ignore_ascii_case("[END]") {
            ended = true;
            break;
        }
        lines.push((i + 1, content));
    }
    if !ended {
        return Err(err(
            path,
            text.lines().count().max(1),
            "no [END] line: the table is cut short".into(),
        ));
    }
    if lines.is_empty() {
        return Err(err(path, 1, "no header line after BEGIN".into()));
    }
    Ok(lines)
}

/// The header's line and its column names, upper case.
fn header(lines: &[(usize, &str)]) -> (usize, Vec<String>) {
    let (line, text) = lines[0];
    let cols = text
        .split_whitespace()
        .map(|c| c.to_ascii_uppercase())
        .collect();
    (line, cols)
}

/// Read a COM file of `axis` (from `path`, named in every error).
pub fn parse_com(
    text: &str,
    path: &str,
    axis: MachineAxis,
) -> Result<ComponentTable, MachineError> {
    let lines = table_lines(text, path)?;
    let (hline, cols) = header(&lines);
    let find = |name: &str| cols.iter().position(|c| c == name);
    let pos = find("AXISPOS").ok_or_else(|| {
        err(
            path,
            hline,
            "no AXISPOS column: the compensation points' positions stand there".into(),
        )
    })?;
    let c: [Option<usize>; 6] = std::array::from_fn(|k| find(&format!("C{}", k + 1)));
    if c.iter().all(Option::is_none) {
        return Err(err(
            path,
            hline,
            "none of the columns C1-C6 that carry the axis's errors".into(),
        ));
    }
    let mut positions = Vec::new();
    let mut values = Vec::new();
    for &(n, row) in &lines[1..] {
        let f: Vec<&str> = row.split_whitespace().collect();
        if f.len() != cols.len() {
            return Err(err(
                path,
                n,
                format!(
                    "{} fields under a header of {} columns (line {hline})",
                    f.len(),
                    cols.len()
                ),
            ));
        }
        let num = |i: usize| {
            f[i].parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| {
                    err(
                        path,
                        n,
                        format!(
                            "{} under {} is not a number (with a decimal point)",
                            f[i], cols[i]
                        ),
                    )
                })
        };
        positions.push(num(pos)?);
        let mut v = [0.0; 6];
        for k in 0..6 {
            if let Some(i) = c[k] {
                let x = num(i)?;
                v[k] = if k < 3 { x } else { x.to_radians() };
            }
        }
        values.push(v);
    }
    ComponentTable::new(axis, positions, values).map_err(|e| err(path, hline, e.to_string()))
}

/// Read the kinematics excerpt (from `path`): the squarenesses of its position errors `C0Y`,
/// `B0Z`, `A0Z` (an absent one is zero).
pub fn parse_kinematics(text: &str, path: &str) -> Result<Squareness, MachineError> {
    let lines = table_lines(text, path)?;
    let (hline, cols) = header(&lines);
    if !(cols.iter().any(|c| c == "DOC") && cols.iter().any(|c| c == "COORD")) {
        return Err(err(
            path,
            hline,
            "the header names no DOC or no COORD column".into(),
        ));
    }
    let mut s = [None; 3];
    for &(n, row) in &lines[1..] {
        let f: Vec<&str> = row.split_whitespace().collect();
        // NR first, then DOC when the row names one; a squareness's row goes on with KEY
        // (Trans), AXIS and COORD in degrees.
        let d = usize::from(f.first().is_some_and(|x| x.parse::<u32>().is_ok()));
        let Some(k) = f.get(d).and_then(|name| {
            Squareness::NAMES
                .iter()
                .position(|x| x.eq_ignore_ascii_case(name))
        }) else {
            continue;
        };
        let name = Squareness::NAMES[k];
        let value = f
            .get(d + 3)
            .and_then(|v| v.parse::<f64>().ok())
            .filter(|x| x.is_finite())
            .ok_or_else(|| {
                err(
                    path,
                    n,
                    format!("{name} has no number under COORD (degrees) after Trans and its axis"),
                )
            })?;
        if s[k].is_some() {
            return Err(err(path, n, format!("{name} is given twice")));
        }
        s[k] = Some(value.to_radians());
    }
    Ok(Squareness::from_array(std::array::from_fn(|k| {
        s[k].unwrap_or(0.0)
    })))
}

/// Read the files in `dir` that [`write`] writes.
pub fn read(dir: &Path) -> Result<KinematicsComp, MachineError> {
    let text = |name: &str| read_text(&dir.join(name));
    let mut tables = Vec::new();
    for axis in MachineAxis::ALL {
        let (t, p) = text(&com_file(axis))?;
        tables.push(parse_com(&t, &p, axis)?);
    }
    let (t, p) = text(KINEMATICS_FILE)?;
    let squareness = parse_kinematics(&t, &p)?;
    Ok(KinematicsComp { tables, squareness })
}
