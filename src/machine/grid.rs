//! The model evaluated onto a 3-D grid of the axes' positions, as the controls that take
//! correction vectors at a grid's corners interpolate them (FANUC's three-dimensional error
//! compensation: trilinear between the eight corners around the point). The grid is taken
//! at one tool offset: the angular errors' share at another offset is not in it.
//!
//! Its file for the control: `fanuc_grid`.

use super::error::MachineError;
use super::model::{MachineModel, Volumetric};

/// Error vectors (mm, machine X, Y, Z) at the corners of a regular grid over the volume.
#[derive(Clone, Debug, PartialEq)]
pub struct Grid {
    origin_mm: [f64; 3],
    step_mm: [f64; 3],
    counts: [usize; 3],
    tool_mm: [f64; 3],
    /// X fastest, then Y, then Z.
    vectors: Vec<[f64; 3]>,
}

impl Grid {
    /// `model` at every corner of a grid from `from_mm` to `to_mm` (each axis's ends
    /// included) no wider than `step_mm`, with tool offset `tool_mm`.
    pub fn of_model(
        model: &MachineModel,
        from_mm: [f64; 3],
        to_mm: [f64; 3],
        step_mm: [f64; 3],
        tool_mm: [f64; 3],
    ) -> Result<Grid, MachineError> {
        let mut counts = [0usize; 3];
        let mut step = [0.0; 3];
        for k in 0..3 {
            let span = to_mm[k] - from_mm[k];
            if !(span > 0.0 && step_mm[k] > 0.0 && span.is_finite()) {
                return Err(MachineError::Missing(format!(
                    "a grid from {} to {} mm every {} mm along {}: give a positive span and step",
                    from_mm[k],
                    to_mm[k],
                    step_mm[k],
                    ["X", "Y", "Z"][k]
                )));
            }
            let cells = (span / step_mm[k]).ceil().max(1.0) as usize;
            counts[k] = cells + 1;
            step[k] = span / cells as f64;
        }
        let mut vectors = Vec::with_capacity(counts.iter().product());
        for k in 0..counts[2] {
            for j in 0..counts[1] {
                for i in 0..counts[0] {
                    let p = [
                        from_mm[0] + i as f64 * step[0],
                        from_mm[1] + j as f64 * step[1],
                        from_mm[2] + k as f64 * step[2],
                    ];
                    vectors.push(model.error_at(p, tool_mm));
                }
            }
        }
        Ok(Grid {
            origin_mm: from_mm,
            step_mm: step,
            counts,
            tool_mm,
            vectors,
        })
    }

    /// This grid with each corner moved by a sixteenth of its second differences, taken back:
    /// between two corners a linear blend lies off a curve by up to h²f″/8 at the middle and 0
    /// at the corners; moved so, it lies off by h²f″/16 at both, half the largest, for a field
    /// whose curvature changes little over a cell. A corner on a face takes its neighbour's
    /// second difference along that axis. What the controls that blend corners should be given,
    /// rather than the model at them.
    pub fn curvature_balanced(&self) -> Grid {
        let n = self.counts;
        let mut out = self.clone();
        for k in 0..n[2] {
            for j in 0..n[1] {
                for i in 0..n[0] {
                    let mut shift = [0.0; 3];
                    for (axis, &count) in n.iter().enumerate() {
                        if count < 3 {
                            continue;
                        }
                        let at = [i, j, k][axis].clamp(1, count - 2);
                        let mut idx = [i, j, k];
                        let mut v = [[0.0; 3]; 3];
                        for (d, slot) in v.iter_mut().enumerate() {
                            idx[axis] = at + d - 1;
                            *slot = self.corner(idx[0], idx[1], idx[2]);
                        }
                        for m in 0..3 {
                            shift[m] += (v[0][m] - 2.0 * v[1][m] + v[2][m]) / 16.0;
                        }
                    }
                    let c = &mut out.vectors[(k * n[1] + j) * n[0] + i];
                    for m in 0..3 {
                        c[m] -= shift[m];
                    }
                }
            }
        }
        out
    }

    /// A grid of `vectors` (X fastest, then Y, then Z) at the corners from `origin_mm` every
    /// `step_mm`, `counts` corners along each axis (at least two), taken with `tool_mm`: what a
    /// grid's file holds.
    pub fn from_corners(
        origin_mm: [f64; 3],
        step_mm: [f64; 3],
        counts: [usize; 3],
        tool_mm: [f64; 3],
        vectors: Vec<[f64; 3]>,
    ) -> Result<Grid, MachineError> {
        for k in 0..3 {
            let axis = ["X", "Y", "Z"][k];
            if counts[k] < 2 {
                return Err(MachineError::Missing(format!(
                    "a grid of {} corner(s) along {axis}: it needs at least two to interpolate between",
                    counts[k]
                )));
            }
            if !(step_mm[k] > 0.0 && step_mm[k].is_finite() && origin_mm[k].is_finite()) {
                return Err(MachineError::Missing(format!(
                    "a grid from {} mm every {} mm along {axis}: give a finite origin and a positive step",
                    origin_mm[k], step_mm[k]
                )));
            }
        }
        let n: usize = counts.iter().product();
        if vectors.len() != n {
            return Err(MachineError::Missing(format!(
                "a grid of {} × {} × {} corners with {} vectors: give one per corner",
                counts[0],
                counts[1],
                counts[2],
                vectors.len()
            )));
        }
        Ok(Grid {
            origin_mm,
            step_mm,
            counts,
            tool_mm,
            vectors,
        })
    }

    /// The first corner (mm).
    pub fn origin_mm(&self) -> [f64; 3] {
        self.origin_mm
    }

    /// The error vector (mm) at corner `(i, j, k)` (along X, Y, Z).
    pub fn vector(&self, i: usize, j: usize, k: usize) -> [f64; 3] {
        self.corner(i, j, k)
    }

    /// Corners along X, Y, Z.
    pub fn counts(&self) -> [usize; 3] {
        self.counts
    }

    /// The spacing along X, Y, Z (mm).
    pub fn step_mm(&self) -> [f64; 3] {
        self.step_mm
    }

    /// The tool offset the grid was taken with (mm).
    pub fn tool_mm(&self) -> [f64; 3] {
        self.tool_mm
    }

    fn corner(&self, i: usize, j: usize, k: usize) -> [f64; 3] {
        self.vectors[(k * self.counts[1] + j) * self.counts[0] + i]
    }

    /// The error vector at `p` (mm): trilinear between the corners around it, the grid's
    /// faces held beyond it.
    pub fn at(&self, p: [f64; 3]) -> [f64; 3] {
        let mut cell = [0usize; 3];
        let mut w = [0.0; 3];
        for k in 0..3 {
            let cells = self.counts[k] - 1;
            let u = ((p[k] - self.origin_mm[k]) / self.step_mm[k]).clamp(0.0, cells as f64);
            cell[k] = (u.floor() as usize).min(cells - 1);
            w[k] = u - cell[k] as f64;
        }
        let mut out = [0.0; 3];
        for (dk, wk) in [(0, 1.0 - w[2]), (1, w[2])] {
            for (dj, wj) in [(0, 1.0 - w[1]), (1, w[1])] {
                for (di, wi) in [(0, 1.0 - w[0]), (1, w[0])] {
                    let c = self.corner(cell[0] + di, cell[1] + dj, cell[2] + dk);
                    for m in 0..3 {
                        out[m] += wi * wj * wk * c[m];
                    }
                }
            }
        }
        out
    }
}

impl Volumetric for Grid {
    /// The grid's vector at `cmd`; the tool is the grid's own (a control with a grid knows
    /// no other).
    fn error_at(&self, cmd: [f64; 3], _tool: [f64; 3]) -> [f64; 3] {
        self.at(cmd)
    }
}
