//! ISO 230-1's rigid-body model of a three-axis machine: six component errors per linear axis
//! (tabulated against the axis' position), three squarenesses, and the kinematic chain that
//! says how they add up at the tool.
//!
//! Conventions (stated once, used by the twin, the exports and every figure):
//!
//! - An axis' six errors are those of the *relative* motion of tool and workpiece when that
//!   axis alone moves, as an instrument between the two measures them: `E{X,Y,Z}{axis}`
//!   translations (mm) and `E{A,B,C}{axis}` rotations about X, Y, Z (rad, right-handed). A
//!   table axis (on the workpiece side) is measured so too, so the bed's place in the chain
//!   does not change the sum; it is kept for the controls that ask for it.
//! - The translations are those of the line through the machine's origin (the other axes at
//!   0) at zero tool offset: a table measured along another line (an Abbe offset) is reduced
//!   to it before it enters the model.
//! - Squareness: X is the reference; Y's line is turned about Z by `C0Y` and Z's about Y by
//!   `B0Z` and about X by `A0Z` (right-handed: a positive `C0Y` opens the angle between +X
//!   and +Y beyond 90°, a positive `B0Z` leans +Z towards +X, a positive `A0Z` towards −Y).
//! - The chain runs from the workpiece to the tool: the tool's point in the workpiece frame is
//!   `M₁(q₁)·M₂(q₂)·M₃(q₃)·t`, each `M` turning by its rotations about its own frame's
//!   origin and shifting by `q·d + δ`, `t` the tool offset. The model keeps the first order
//!   in the errors (they are 10⁻⁴ of the travel); `sim::machine` composes the same chain
//!   exactly, and the tests hold the two together.

use super::error::MachineError;
use crate::comp::mapping::MachineAxis;
use serde::{Deserialize, Serialize};
use std::fmt;

/// The ISO 230-1 names of an axis' six component errors, in the order of a
/// [`ComponentTable`]'s columns: `["EXX", "EYX", "EZX", "EAX", "EBX", "ECX"]` for X.
pub fn component_names(axis: MachineAxis) -> [String; 6] {
    let letters = ["X", "Y", "Z", "A", "B", "C"];
    std::array::from_fn(|k| format!("E{}{}", letters[k], axis.letter()))
}

/// One axis' six component errors against its position: translations along X, Y, Z (mm),
/// rotations about X, Y, Z (rad).
#[derive(Clone, Debug, PartialEq)]
pub struct ComponentTable {
    axis: MachineAxis,
    positions_mm: Vec<f64>,
    values: Vec<[f64; 6]>,
}

impl ComponentTable {
    /// A table of at least two rows, positions strictly increasing, every value finite.
    pub fn new(
        axis: MachineAxis,
        positions_mm: Vec<f64>,
        values: Vec<[f64; 6]>,
    ) -> Result<ComponentTable, MachineError> {
        let bad = |problem: String| MachineError::Table { axis, problem };
        if positions_mm.len() != values.len() {
            return Err(bad(format!(
                "{} positions but {} rows of errors",
                positions_mm.len(),
                values.len()
            )));
        }
        if positions_mm.len() < 2 {
            return Err(bad(format!(
                "{} row(s): a table needs at least two positions to interpolate between",
                positions_mm.len()
            )));
        }
        let names = component_names(axis);
        for (i, (p, row)) in positions_mm.iter().zip(&values).enumerate() {
            if !p.is_finite() {
                return Err(bad(format!("row {}: the position is not a number", i + 1)));
            }
            if let Some(k) = row.iter().position(|v| !v.is_finite()) {
                return Err(bad(format!(
                    "row {} at {p} mm: {} is not a number",
                    i + 1,
                    names[k]
                )));
            }
        }
        for (i, w) in positions_mm.windows(2).enumerate() {
            if w[1] <= w[0] {
                return Err(bad(format!(
                    "positions must increase: row {} is {} mm after {} mm",
                    i + 2,
                    w[1],
                    w[0]
                )));
            }
        }
        Ok(ComponentTable {
            axis,
            positions_mm,
            values,
        })
    }

    /// A table of `f` sampled every `step_mm` from `from_mm` to `to_mm` (both ends included).
    pub fn sample(
        axis: MachineAxis,
        from_mm: f64,
        to_mm: f64,
        step_mm: f64,
        f: impl Fn(f64) -> [f64; 6],
    ) -> Result<ComponentTable, MachineError> {
        if !(step_mm > 0.0 && to_mm > from_mm) {
            return Err(MachineError::Table {
                axis,
                problem: format!(
                    "cannot sample {from_mm} to {to_mm} mm every {step_mm} mm: give a positive step over a positive span"
                ),
            });
        }
        let n = ((to_mm - from_mm) / step_mm).ceil() as usize;
        let positions: Vec<f64> = (0..=n)
            .map(|i| (from_mm + i as f64 * step_mm).min(to_mm))
            .collect();
        let values = positions.iter().map(|&q| f(q)).collect();
        ComponentTable::new(axis, positions, values)
    }

    /// This table resampled every `step_mm` over its span from a cubic spline through its rows,
    /// column by column (`util::spline`): a control interpolates its table linearly between
    /// rows, and a machine's errors are smooth between the targets they were measured at (a
    /// target every 20 mm misses an axis's shorter waves by up to a micrometre in straight
    /// lines; the spline follows them).
    pub fn refined(&self, step_mm: f64) -> Result<ComponentTable, MachineError> {
        let p = &self.positions_mm;
        let splines = (0..6)
            .map(|k| {
                let column: Vec<f64> = self.values.iter().map(|v| v[k]).collect();
                crate::util::spline::Spline::new(p, &column)
            })
            .collect::<Option<Vec<_>>>()
            .ok_or_else(|| MachineError::Table {
                axis: self.axis,
                problem: "its rows make no spline (positions not increasing or values not finite)"
                    .into(),
            })?;
        let (from, to) = (p[0], p[p.len() - 1]);
        ComponentTable::sample(self.axis, from, to, step_mm, |q| {
            std::array::from_fn(|k| splines[k].at(q))
        })
    }

    pub fn axis(&self) -> MachineAxis {
        self.axis
    }

    pub fn positions_mm(&self) -> &[f64] {
        &self.positions_mm
    }

    pub fn values(&self) -> &[[f64; 6]] {
        &self.values
    }

    /// The errors at `q` (mm): linear between rows, the end rows' values beyond them (as the
    /// controls hold a table's ends).
    pub fn at(&self, q: f64) -> [f64; 6] {
        let p = &self.positions_mm;
        let last = p.len() - 1;
        if q <= p[0] {
            return self.values[0];
        }
        if q >= p[last] {
            return self.values[last];
        }
        let i = p.partition_point(|&x| x <= q).clamp(1, last);
        let (a, b) = (p[i - 1], p[i]);
        let w = (q - a) / (b - a);
        std::array::from_fn(|k| self.values[i - 1][k] * (1.0 - w) + self.values[i][k] * w)
    }
}

/// The three squarenesses (rad), X the reference (see the module's conventions).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Squareness {
    /// Y's line turned about Z.
    pub c0y: f64,
    /// Z's line turned about Y.
    pub b0z: f64,
    /// Z's line turned about X.
    pub a0z: f64,
}

impl Squareness {
    /// The ISO 230-1 names, in the order of [`Squareness::to_array`].
    pub const NAMES: [&'static str; 3] = ["C0Y", "B0Z", "A0Z"];

    pub fn to_array(self) -> [f64; 3] {
        [self.c0y, self.b0z, self.a0z]
    }

    pub fn from_array(a: [f64; 3]) -> Squareness {
        Squareness {
            c0y: a[0],
            b0z: a[1],
            a0z: a[2],
        }
    }

    /// How far `axis`' unit line leaves its nominal direction, to first order.
    pub fn tilt(self, axis: MachineAxis) -> [f64; 3] {
        match axis {
            MachineAxis::X => [0.0; 3],
            MachineAxis::Y => [-self.c0y, 0.0, 0.0],
            MachineAxis::Z => [self.b0z, -self.a0z, 0.0],
        }
    }
}

/// The kinematic chain: the three axes from the workpiece to the tool, and how many of them
/// carry the workpiece (the bed sits after them).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Chain {
    order: [MachineAxis; 3],
    workpiece_axes: usize,
}

impl Chain {
    /// `order` from the workpiece to the tool, each axis once; the first `workpiece_axes`
    /// move the workpiece.
    pub fn new(order: [MachineAxis; 3], workpiece_axes: usize) -> Result<Chain, MachineError> {
        let chain = Chain {
            order,
            workpiece_axes,
        };
        let wrong: Vec<String> = MachineAxis::ALL
            .iter()
            .filter_map(|&a| match order.iter().filter(|&&b| b == a).count() {
                1 => None,
                0 => Some(format!("{a} is missing")),
                n => Some(format!("{a} appears {n} times")),
            })
            .collect();
        if !wrong.is_empty() {
            return Err(MachineError::Chain {
                chain: chain.to_string(),
                problem: format!("{}: name each of X, Y and Z once", wrong.join(", ")),
            });
        }
        if workpiece_axes > 3 {
            return Err(MachineError::Chain {
                chain: chain.to_string(),
                problem: format!("{workpiece_axes} workpiece axes of 3"),
            });
        }
        Ok(chain)
    }

    /// A vertical machining centre with a cross table: the X table on the Y saddle on the bed,
    /// the Z head on the column (workpiece – X – Y – bed – Z – tool).
    pub fn cross_table() -> Chain {
        use MachineAxis::*;
        Chain {
            order: [X, Y, Z],
            workpiece_axes: 2,
        }
    }

    /// A gantry: the workpiece on the bed, the Y bridge, the X carriage on it, the Z ram
    /// (workpiece – bed – Y – X – Z – tool).
    pub fn gantry() -> Chain {
        use MachineAxis::*;
        Chain {
            order: [Y, X, Z],
            workpiece_axes: 0,
        }
    }

    /// The axes from the workpiece to the tool.
    pub fn order(&self) -> [MachineAxis; 3] {
        self.order
    }

    pub fn workpiece_axes(&self) -> usize {
        self.workpiece_axes
    }
}

impl fmt::Display for Chain {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("workpiece")?;
        for (i, a) in self.order.iter().enumerate() {
            if i == self.workpiece_axes {
                f.write_str(" – bed")?;
            }
            write!(f, " – {a}")?;
        }
        if self.workpiece_axes == 3 {
            f.write_str(" – bed")?;
        }
        f.write_str(" – tool")
    }
}

/// A machine's 21 geometric errors and its chain.
#[derive(Clone, Debug, PartialEq)]
pub struct MachineModel {
    pub chain: Chain,
    /// X, Y, Z.
    tables: [ComponentTable; 3],
    pub squareness: Squareness,
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

impl MachineModel {
    /// The model of `tables` (one per axis, in any order).
    pub fn new(
        chain: Chain,
        tables: Vec<ComponentTable>,
        squareness: Squareness,
    ) -> Result<MachineModel, MachineError> {
        let mut by_axis: [Option<ComponentTable>; 3] = [None, None, None];
        for t in tables {
            let i = t.axis().index();
            if by_axis[i].is_some() {
                return Err(MachineError::Table {
                    axis: t.axis(),
                    problem: "given twice: one table per axis".into(),
                });
            }
            by_axis[i] = Some(t);
        }
        let [Some(x), Some(y), Some(z)] = by_axis else {
            let missing: Vec<&str> = MachineAxis::ALL
                .iter()
                .zip(&by_axis)
                .filter(|(_, t)| t.is_none())
                .map(|(a, _)| a.letter())
                .collect();
            return Err(MachineError::Missing(format!(
                "no component errors for axis {}: the model needs all three",
                missing.join(", ")
            )));
        };
        Ok(MachineModel {
            chain,
            tables: [x, y, z],
            squareness,
        })
    }

    pub fn table(&self, axis: MachineAxis) -> &ComponentTable {
        &self.tables[axis.index()]
    }

    pub fn tables(&self) -> &[ComponentTable; 3] {
        &self.tables
    }

    /// The tool point's error (mm, machine X, Y, Z) at commanded position `cmd` (mm) with
    /// tool offset `tool` (mm, in the spindle's frame at rest): where it is in the workpiece
    /// frame minus `cmd + tool`.
    pub fn error_at(&self, cmd: [f64; 3], tool: [f64; 3]) -> [f64; 3] {
        let order = self.chain.order;
        let mut e = [0.0; 3];
        for (i, &axis) in order.iter().enumerate() {
            let q = cmd[axis.index()];
            let row = self.table(axis).at(q);
            let tilt = self.squareness.tilt(axis);
            // What this axis turns: the nominal displacement of the axes after it and the tool.
            let mut lever = tool;
            for &after in &order[i + 1..] {
                lever[after.index()] += cmd[after.index()];
            }
            let turn = cross([row[3], row[4], row[5]], lever);
            for k in 0..3 {
                e[k] += row[k] + q * tilt[k] + turn[k];
            }
        }
        e
    }
}

/// What a control compensates by: the tool point's error (mm, machine X, Y, Z) it expects at
/// a commanded position (mm) with a tool offset (mm).
pub trait Volumetric {
    fn error_at(&self, cmd: [f64; 3], tool: [f64; 3]) -> [f64; 3];
}

impl Volumetric for MachineModel {
    fn error_at(&self, cmd: [f64; 3], tool: [f64; 3]) -> [f64; 3] {
        MachineModel::error_at(self, cmd, tool)
    }
}
