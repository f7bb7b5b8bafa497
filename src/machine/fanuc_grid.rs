//! The model at the corners of a grid, for FANUC's three-dimensional error compensation: the
//! writer and its one reader.
//!
//! Confirmed (FANUC Series 30i-MODEL A, "Three-dimensional error compensation", A-79351E, page
//! 3 of 13): the control holds a compensation value per axis (X, Y, Z) at every vertex of a
//! grid of rectangular cells over the volume, and at a point between them adds the trilinear
//! blend of the eight vertices around it (`Grid::at` computes the same).
//!
//! Not confirmed: how the values enter the control (its parameter numbers, the data screen or
//! a file of its own). This file is axiscomp's own, self-describing text: the grid's origin,
//! far corner and number of corners per axis, the tool offset it was taken with, and one line
//! per corner with its indices and its compensation vector in mm, the error taken back (the
//! control adds it to the axes' positions). A commissioning engineer enters the values by the
//! procedure of the machine's FANUC documentation.
//!
//! The grid is the model at one tool offset: the angular errors' share at another tool is not
//! in it (a FANUC control with a different tool needs its own grid).

use super::error::{MachineError, read_text};
use super::grid::Grid;
use std::fmt::Write as _;
use std::path::Path;

/// The file for `grid`, headed by `title` (one comment line per line of it).
pub fn write(grid: &Grid, title: &str) -> String {
    let mut out = String::new();
    for line in title.lines() {
        let _ = writeln!(out, "; {line}");
    }
    out.push_str(
        "; FANUC three-dimensional error compensation: the compensation vector at each corner of a grid\n\
         ; Compensation = the model's error taken back, mm (the control adds it to the axes' positions);\n\
         ; trilinear between the eight corners around a point. Corners: X fastest, then Y, then Z.\n",
    );
    let (o, s, n, t) = (
        grid.origin_mm(),
        grid.step_mm(),
        grid.counts(),
        grid.tool_mm(),
    );
    let end: [f64; 3] = std::array::from_fn(|k| o[k] + s[k] * (n[k] - 1) as f64);
    out.push_str("UNIT MM\n");
    let _ = writeln!(out, "ORIGIN {:.6} {:.6} {:.6}", o[0], o[1], o[2]);
    let _ = writeln!(out, "END {:.6} {:.6} {:.6}", end[0], end[1], end[2]);
    let _ = writeln!(out, "POINTS {} {} {}", n[0], n[1], n[2]);
    let _ = writeln!(out, "TOOL {:.6} {:.6} {:.6}", t[0], t[1], t[2]);
    out.push_str("; I J K CX CY CZ\n");
    for k in 0..n[2] {
        for j in 0..n[1] {
            for i in 0..n[0] {
                let v = grid.vector(i, j, k);
                let _ = writeln!(
                    out,
                    "{i} {j} {k} {:+.7} {:+.7} {:+.7}",
                    taken_back(v[0]),
                    taken_back(v[1]),
                    taken_back(v[2])
                );
            }
        }
    }
    out
}

/// The compensation of an error: its negative, a zero written as +0.
fn taken_back(e: f64) -> f64 {
    0.0 - e
}

struct Header {
    origin: Option<[f64; 3]>,
    end: Option<[f64; 3]>,
    points: Option<[usize; 3]>,
    tool: Option<[f64; 3]>,
}

fn err(path: &str, line: usize, problem: String) -> MachineError {
    MachineError::at(path, line, problem)
}

fn three<T: std::str::FromStr>(
    f: &[&str],
    path: &str,
    line: usize,
) -> Result<[T; 3], MachineError> {
    let bad = || {
        err(
            path,
            line,
            format!(
                "{} takes three numbers (X, Y, Z), found {}",
                f[0],
                f[1..].join(" ")
            ),
        )
    };
    if f.len() != 4 {
        return Err(bad());
    }
    let v: Vec<T> = f[1..]
        .iter()
        .map(|s| s.parse::<T>().map_err(|_| bad()))
        .collect::<Result<_, _>>()?;
    let mut it = v.into_iter();
    match (it.next(), it.next(), it.next()) {
        (Some(a), Some(b), Some(c)) => Ok([a, b, c]),
        _ => Err(bad()),
    }
}

/// Read `text` (from `path`, named in every error): the grid of the model's errors it carries.
pub fn parse(text: &str, path: &str) -> Result<Grid, MachineError> {
    let mut h = Header {
        origin: None,
        end: None,
        points: None,
        tool: None,
    };
    let mut rows: Vec<(usize, [usize; 3], [f64; 3])> = Vec::new();
    let mut unit_seen = false;
    for (i, raw) in text.lines().enumerate() {
        let n = i + 1;
        let content = raw.split(';').next().unwrap_or("").trim();
        if content.is_empty() {
            continue;
        }
        let f: Vec<&str> = content.split_whitespace().collect();
        match f[0].to_ascii_uppercase().as_str() {
            "UNIT" => {
                if f.len() != 2 || !f[1].eq_ignore_ascii_case("MM") {
                    return Err(err(
                        path,
                        n,
                        format!(
                            "UNIT {}: axiscomp's grid is in mm (UNIT MM)",
                            f[1..].join(" ")
                        ),
                    ));
                }
                unit_seen = true;
            }
            "ORIGIN" => h.origin = Some(three(&f, path, n)?),
            "END" => h.end = Some(three(&f, path, n)?),
            "POINTS" => h.points = Some(three(&f, path, n)?),
            "TOOL" => h.tool = Some(three(&f, path, n)?),
            _ => {
                if f.len() != 6 {
                    return Err(err(
                        path,
                        n,
                        format!(
                            "a corner takes six fields (I J K CX CY CZ), found {}",
                            f.len()
                        ),
                    ));
                }
                let idx: [usize; 3] = std::array::from_fn(|k| f[k].parse().unwrap_or(usize::MAX));
                if idx.contains(&usize::MAX) {
                    return Err(err(
                        path,
                        n,
                        format!(
                            "{} {} {} are not a corner's indices (whole numbers from 0)",
                            f[0], f[1], f[2]
                        ),
                    ));
                }
                let mut v = [0.0; 3];
                for k in 0..3 {
                    v[k] = f[3 + k]
                        .parse::<f64>()
                        .ok()
                        .filter(|x| x.is_finite())
                        .ok_or_else(|| {
                            err(
                                path,
                                n,
                                format!("{} is not a number (mm, with a decimal point)", f[3 + k]),
                            )
                        })?;
                }
                rows.push((n, idx, v));
            }
        }
    }
    let missing = |what: &str| {
        err(
            path,
            text.lines().count().max(1),
            format!(
                "no {what} line: the grid's file gives UNIT, ORIGIN, END, POINTS and TOOL before its corners"
            ),
        )
    };
    if !unit_seen {
        return Err(missing("UNIT"));
    }
    let origin = h.origin.ok_or_else(|| missing("ORIGIN"))?;
    let end = h.end.ok_or_else(|| missing("END"))?;
    let counts = h.points.ok_or_else(|| missing("POINTS"))?;
    let tool = h.tool.ok_or_else(|| missing("TOOL"))?;
    let step: [f64; 3] =
        std::array::from_fn(|k| (end[k] - origin[k]) / (counts[k].max(2) - 1) as f64);
    let total: usize = counts.iter().product();
    let mut vectors: Vec<Option<[f64; 3]>> = vec![None; total];
    for (n, [i, j, k], v) in rows {
        if i >= counts[0] || j >= counts[1] || k >= counts[2] {
            return Err(err(
                path,
                n,
                format!(
                    "corner {i} {j} {k} is outside the grid of {} × {} × {} corners (from 0)",
                    counts[0], counts[1], counts[2]
                ),
            ));
        }
        let slot = &mut vectors[(k * counts[1] + j) * counts[0] + i];
        if slot.is_some() {
            return Err(err(path, n, format!("corner {i} {j} {k} is given twice")));
        }
        *slot = Some([-v[0], -v[1], -v[2]]);
    }
    if let Some(at) = vectors.iter().position(Option::is_none) {
        let (i, j, k) = (
            at % counts[0],
            (at / counts[0]) % counts[1],
            at / (counts[0] * counts[1]),
        );
        return Err(missing_corner(path, text, [i, j, k], total));
    }
    let vectors = vectors.into_iter().flatten().collect();
    Grid::from_corners(origin, step, counts, tool, vectors).map_err(|e| MachineError::Io {
        path: path.to_string(),
        problem: e.to_string(),
    })
}

fn missing_corner(path: &str, text: &str, c: [usize; 3], total: usize) -> MachineError {
    err(
        path,
        text.lines().count().max(1),
        format!(
            "corner {} {} {} is missing: the grid needs all {total} corners",
            c[0], c[1], c[2]
        ),
    )
}

/// Read the file at `path`.
pub fn read(path: &Path) -> Result<Grid, MachineError> {
    let (text, name) = read_text(path)?;
    parse(&text, &name)
}
