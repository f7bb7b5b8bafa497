//! Siemens SINUMERIK: the leadscrew (measuring-system) error compensation (EEC) for each axis's
//! positioning error and the sag/angularity compensation (CEC) carrying each axis's
//! straightnesses and squareness into the other axes, as the part programs that set their
//! system variables; the writer and its one reader.
//!
//! Confirmed from the manuals (SINUMERIK Function Manual Extended Functions, K3
//! Compensations, 6FC5397-1BP40-3BA1 (03/2013), pages 242 and 248-249; 802D sl Function Manual
//! 6FC5397-1CP10-5BA0 (11/2012), page 222): the EEC table of a machine axis as
//! `$AA_ENC_COMP[0,N,X1]` with `$AA_ENC_COMP_STEP`, `_MIN`, `_MAX` and `_IS_MODULO`, in the
//! program `%_N_AX_EEC_INI`; a CEC table `t` as `$AN_CEC[t,N]` with `$AN_CEC_INPUT_AXIS[t]`
//! (the basic axis whose setpoint is the input), `$AN_CEC_OUTPUT_AXIS[t]` (the compensation
//! axis), `$AN_CEC_STEP`, `_MIN`, `_MAX`, `_DIRECTION`, `_MULT_BY_TABLE`, `_IS_MODULO`, in
//! `%_N_NC_CEC_INI` after `CHANDATA(1)`, ending `M17`; equidistant points, values in mm, the
//! first point's value held below `MIN` and the last's above `MAX`.
//!
//! Not confirmed, to be checked on the machine: the axis names (`X1`, `Y1`, `Z1` here, as in
//! the manual's examples; they must be the machine's), and the sign: the values are written as
//! compensations, the model's error taken back (the manual's example adds its values to the
//! compensation axis). The machine data that size the tables (MD38000
//! `MM_ENC_COMP_MAX_POINTS`, MD18342 `MM_CEC_MAX_POINTS`) must hold the points written.
//!
//! What these tables cannot carry: the angular errors (pitch, yaw, roll) reach the tool through
//! the other axes' positions and the tool offset, a function of two axes or more, which one
//! table of one input does not hold; SINUMERIK's volumetric compensation (VCS) takes them, in
//! a format not public here. The read-back model has them zero, and the squarenesses folded
//! into the straightness tables as lines.

use super::error::{MachineError, read_text};
use super::model::{ComponentTable, MachineModel};
use crate::comp::mapping::MachineAxis;
use std::fmt::Write as _;
use std::path::Path;

/// The EEC program's file.
pub const EEC_FILE: &str = "AX_EEC.INI";
/// The CEC program's file.
pub const CEC_FILE: &str = "NC_CEC.INI";

/// The machine axis name written for `axis`.
pub fn axis_name(axis: MachineAxis) -> String {
    format!("{}1", axis.letter())
}

/// `X1`, `Y1`, `Z1`, or the general names `AX1`, `AX2`, `AX3` (the manual's example on page
/// 222 of the 802D sl manual calls AX2 "basic axis Y1" and AX1 "compensation axis X1"), with or
/// without parentheses.
fn axis_of(name: &str) -> Option<MachineAxis> {
    let n = name.trim_matches(|c| c == '(' || c == ')').trim();
    MachineAxis::ALL.into_iter().find(|a| {
        axis_name(*a).eq_ignore_ascii_case(n)
            || format!("AX{}", a.index() + 1).eq_ignore_ascii_case(n)
    })
}

/// The equidistant points over `table`'s span, no further apart than `step_mm`.
fn points(table: &ComponentTable, step_mm: f64) -> Vec<f64> {
    let p = table.positions_mm();
    let (from, to) = (p[0], p[p.len() - 1]);
    let n = ((to - from) / step_mm).ceil().max(1.0) as usize;
    (0..=n)
        .map(|i| from + (to - from) * i as f64 / n as f64)
        .collect()
}

/// The two programs for `model` (name, text), each headed by `title`, the tables every
/// `step_mm` at most: `AX_EEC.INI` and `NC_CEC.INI`.
pub fn write(model: &MachineModel, step_mm: f64, title: &str) -> Vec<(String, String)> {
    let head = |name: &str| {
        let mut out = format!("%_N_{name}_INI\n");
        for l in title.lines() {
            let _ = writeln!(out, "; {l}");
        }
        out
    };
    let mut eec = head("AX_EEC");
    eec.push_str("; positioning errors taken back (mm), each axis against its own position\n");
    eec.push_str("CHANDATA(1)\n");
    let mut cec = head("NC_CEC");
    cec.push_str("; straightness and squareness taken back (mm): OUTPUT axis against INPUT axis\n");
    cec.push_str("CHANDATA(1)\n");
    let mut t = 0;
    for table in model.tables() {
        let a = table.axis();
        let name = axis_name(a);
        let q = points(table, step_mm);
        let (from, to) = (q[0], q[q.len() - 1]);
        let step = (to - from) / (q.len() - 1) as f64;
        let _ = writeln!(eec, "; {a}: {} points", q.len());
        for (n, &x) in q.iter().enumerate() {
            let e = table.at(x)[a.index()];
            let _ = writeln!(eec, "$AA_ENC_COMP[0,{n},{name}]={:.7}", 0.0 - e);
        }
        let _ = writeln!(eec, "$AA_ENC_COMP_STEP[0,{name}]={step:.6}");
        let _ = writeln!(eec, "$AA_ENC_COMP_MIN[0,{name}]={from:.6}");
        let _ = writeln!(eec, "$AA_ENC_COMP_MAX[0,{name}]={to:.6}");
        let _ = writeln!(eec, "$AA_ENC_COMP_IS_MODULO[0,{name}]=0");
        let tilt = model.squareness.tilt(a);
        for out in MachineAxis::ALL.into_iter().filter(|b| *b != a) {
            let k = out.index();
            let _ = writeln!(
                cec,
                "; table {t}: {out} against {a} ({}{a} and the squareness's line)",
                ["EX", "EY", "EZ"][k]
            );
            for (n, &x) in q.iter().enumerate() {
                let e = table.at(x)[k] + x * tilt[k];
                let _ = writeln!(cec, "$AN_CEC[{t},{n}]={:.7}", 0.0 - e);
            }
            let _ = writeln!(cec, "$AN_CEC_INPUT_AXIS[{t}]=({name})");
            let _ = writeln!(cec, "$AN_CEC_OUTPUT_AXIS[{t}]=({})", axis_name(out));
            let _ = writeln!(cec, "$AN_CEC_STEP[{t}]={step:.6}");
            let _ = writeln!(cec, "$AN_CEC_MIN[{t}]={from:.6}");
            let _ = writeln!(cec, "$AN_CEC_MAX[{t}]={to:.6}");
            let _ = writeln!(cec, "$AN_CEC_DIRECTION[{t}]=0");
            let _ = writeln!(cec, "$AN_CEC_MULT_BY_TABLE[{t}]=0");
            let _ = writeln!(cec, "$AN_CEC_IS_MODULO[{t}]=0");
            t += 1;
        }
    }
    eec.push_str("M17\n");
    cec.push_str("M17\n");
    vec![(EEC_FILE.to_string(), eec), (CEC_FILE.to_string(), cec)]
}

/// One table as the program sets it.
#[derive(Default)]
struct Table {
    values: Vec<Option<f64>>,
    input: Option<MachineAxis>,
    output: Option<MachineAxis>,
    step: Option<f64>,
    min: Option<f64>,
    max: Option<f64>,
    line: usize,
}

fn err(path: &str, line: usize, problem: String) -> MachineError {
    MachineError::at(path, line, problem)
}

/// `$NAME[i,j,...]=value` split: the name, its indices, the value's text.
fn assignment(line: &str) -> Option<(String, Vec<String>, String)> {
    let (lhs, rhs) = line.split_once('=')?;
    let lhs = lhs.trim();
    let open = lhs.find('[')?;
    let close = lhs.rfind(']')?;
    let name = lhs[..open].trim().to_ascii_uppercase();
    let idx = lhs[open + 1..close]
        .split(',')
        .map(|s| s.trim().to_string())
        .collect();
    Some((name, idx, rhs.trim().to_string()))
}

/// The tables a program sets: EEC's (`$AA_ENC_COMP`, keyed by axis) or CEC's (`$AN_CEC`,
/// keyed by table number).
fn tables(text: &str, path: &str, eec: bool) -> Result<Vec<(usize, Table)>, MachineError> {
    let mut out: Vec<(usize, Table)> = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let n = i + 1;
        let line = raw.split(';').next().unwrap_or("").trim();
        let upper = line.to_ascii_uppercase();
        if line.is_empty()
            || upper.starts_with("%_N_")
            || upper.starts_with("CHANDATA")
            || upper == "M17"
            || upper == "M30"
        {
            continue;
        }
        let (name, idx, value) = assignment(line).ok_or_else(|| {
            err(
                path,
                n,
                format!("{line}: not a system variable's assignment ($NAME[…]=value)"),
            )
        })?;
        let prefix = if eec { "$AA_ENC_COMP" } else { "$AN_CEC" };
        let Some(field) = name.strip_prefix(prefix).map(str::to_string) else {
            return Err(err(
                path,
                n,
                format!("{name} does not belong in this program: it sets {prefix}… alone"),
            ));
        };
        let num = || {
            value
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| {
                    err(
                        path,
                        n,
                        format!("{name}: {value} is not a number (mm, with a decimal point)"),
                    )
                })
        };
        let index = |s: &str| {
            s.parse::<usize>().map_err(|_| {
                err(
                    path,
                    n,
                    format!("{name}: {s} is not an index (a whole number from 0)"),
                )
            })
        };
        // EEC: [0,N,AXIS] or [0,AXIS] (the table of that axis); CEC: [t,N] or [t].
        let (key, point) = if eec {
            let axis = idx.last().and_then(|s| axis_of(s)).ok_or_else(|| {
                err(
                    path,
                    n,
                    format!(
                        "{name}: the last index names no axis of X1, Y1, Z1 (AX1, AX2, AX3) ({})",
                        idx.join(",")
                    ),
                )
            })?;
            let point = if idx.len() == 3 {
                Some(index(&idx[1])?)
            } else {
                None
            };
            (axis.index(), point)
        } else {
            let t = index(idx.first().map(String::as_str).unwrap_or(""))?;
            let point = if idx.len() == 2 {
                Some(index(&idx[1])?)
            } else {
                None
            };
            (t, point)
        };
        let pos = match out.iter().position(|(k, _)| *k == key) {
            Some(p) => p,
            None => {
                out.push((
                    key,
                    Table {
                        line: n,
                        input: eec.then(|| MachineAxis::ALL[key]),
                        output: eec.then(|| MachineAxis::ALL[key]),
                        ..Table::default()
                    },
                ));
                out.len() - 1
            }
        };
        let t = &mut out[pos].1;
        match (field.as_str(), point) {
            ("", Some(p)) => {
                if t.values.len() <= p {
                    t.values.resize(p + 1, None);
                }
                t.values[p] = Some(num()?);
            }
            ("_STEP", None) => t.step = Some(num()?),
            ("_MIN", None) => t.min = Some(num()?),
            ("_MAX", None) => t.max = Some(num()?),
            ("_INPUT_AXIS" | "_OUTPUT_AXIS", None) if !eec => {
                let axis = axis_of(&value).ok_or_else(|| {
                    err(
                        path,
                        n,
                        format!("{name}: {value} is not X1, Y1 or Z1 (AX1, AX2, AX3)"),
                    )
                })?;
                if field == "_INPUT_AXIS" {
                    t.input = Some(axis);
                } else {
                    t.output = Some(axis);
                }
            }
            ("_IS_MODULO", None) | ("_DIRECTION", None) | ("_MULT_BY_TABLE", None) => {
                if num()? != 0.0 {
                    return Err(err(
                        path,
                        n,
                        format!(
                            "{name}={value}: axiscomp's model takes a table for both directions, unmultiplied, without modulo (0)"
                        ),
                    ));
                }
            }
            _ => {
                return Err(err(
                    path,
                    n,
                    format!("{name}[{}] is not a variable of this table", idx.join(",")),
                ));
            }
        }
    }
    Ok(out)
}

/// One read-back column of an input axis: its points, the direction it corrects (0..3), its
/// values.
type Column = (Vec<f64>, usize, Vec<f64>);

/// A table's points and values, checked whole.
fn resolved(t: &Table, path: &str, what: &str) -> Result<(Vec<f64>, Vec<f64>), MachineError> {
    let bad = |problem: String| err(path, t.line, format!("{what}: {problem}"));
    let (Some(step), Some(min), Some(max)) = (t.step, t.min, t.max) else {
        return Err(bad("STEP, MIN or MAX is not set".into()));
    };
    let values = t
        .values
        .iter()
        .enumerate()
        .map(|(i, v)| v.ok_or_else(|| bad(format!("point {i} has no value"))))
        .collect::<Result<Vec<f64>, _>>()?;
    if values.len() < 2 || step.is_nan() || step <= 0.0 {
        return Err(bad(format!(
            "{} point(s) every {step} mm: a table needs two points or more and a positive step",
            values.len()
        )));
    }
    let span = step * (values.len() - 1) as f64;
    if ((min + span) - max).abs() > 1e-3 * step.max(1.0) {
        return Err(bad(format!(
            "{} points every {step} mm from {min} mm end at {} mm, not at MAX {max} mm",
            values.len(),
            min + span
        )));
    }
    let points = (0..values.len()).map(|i| min + step * i as f64).collect();
    Ok((points, values))
}

/// Read the two programs: each axis's table with its positioning error (from EEC) and its
/// straightnesses with the squareness's line (from CEC), the angles zero. Every axis needs a
/// table of either kind; an absent one is zero.
pub fn parse(
    eec_text: &str,
    eec_path: &str,
    cec_text: &str,
    cec_path: &str,
) -> Result<Vec<ComponentTable>, MachineError> {
    let eec = tables(eec_text, eec_path, true)?;
    let cec = tables(cec_text, cec_path, false)?;
    let mut columns: [Vec<Column>; 3] = Default::default();
    for (_, t) in &eec {
        let axis = t.input.unwrap_or(MachineAxis::X);
        let (p, v) = resolved(
            t,
            eec_path,
            &format!("the EEC table of {}", axis_name(axis)),
        )?;
        columns[axis.index()].push((p, axis.index(), v));
    }
    for (n, t) in &cec {
        let what = format!("CEC table {n}");
        let (Some(input), Some(output)) = (t.input, t.output) else {
            return Err(err(
                cec_path,
                t.line,
                format!("{what}: its INPUT_AXIS or OUTPUT_AXIS is not set"),
            ));
        };
        if input == output {
            return Err(err(
                cec_path,
                t.line,
                format!(
                    "{what}: {} against itself is the EEC's positioning error, not a cross-axis table",
                    axis_name(input)
                ),
            ));
        }
        let (p, v) = resolved(t, cec_path, &what)?;
        columns[input.index()].push((p, output.index(), v));
    }
    MachineAxis::ALL
        .into_iter()
        .map(|axis| {
            let cols = &columns[axis.index()];
            let Some((points, _, _)) = cols.first() else {
                return Err(MachineError::Missing(format!(
                    "{eec_path} and {cec_path} hold no table of {}: the model needs all three axes",
                    axis_name(axis)
                )));
            };
            let mut values = vec![[0.0; 6]; points.len()];
            let mut seen = [false; 3];
            for (p, k, v) in cols {
                if p.len() != points.len()
                    || p.iter().zip(points).any(|(a, b)| (a - b).abs() > 1e-6)
                {
                    return Err(MachineError::Missing(format!(
                        "the tables of {} stand on different points: axiscomp reads back tables on one set of points per input axis",
                        axis_name(axis)
                    )));
                }
                if std::mem::replace(&mut seen[*k], true) {
                    return Err(MachineError::Missing(format!(
                        "two tables carry {} against {}",
                        axis_name(MachineAxis::ALL[*k]),
                        axis_name(axis)
                    )));
                }
                for (row, x) in values.iter_mut().zip(v) {
                    row[*k] = -x;
                }
            }
            ComponentTable::new(axis, points.clone(), values)
        })
        .collect()
}

/// Read the two programs in `dir` that [`write`] writes.
pub fn read(dir: &Path) -> Result<Vec<ComponentTable>, MachineError> {
    let text = |name: &str| read_text(&dir.join(name));
    let (eec, ep) = text(EEC_FILE)?;
    let (cec, cp) = text(CEC_FILE)?;
    parse(&eec, &ep, &cec, &cp)
}
