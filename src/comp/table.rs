//! Compensation tables (DESIGN §7) from an axis evaluation, and their resampling onto a
//! controller's grid.
//!
//! Every table holds the error `e = measured − nominal` (mm) of one machine axis (the
//! compensated axis) as a function of the position of the axis under test (the base axis),
//! zeroed at the reference point; each exporter converts e to its controller's sign.
//! - Positioning (base = compensated axis): unidirectional (the + direction's mean profile and
//!   one backlash value, the mean of x̄↓ − x̄↑) or bidirectional (both profiles).
//! - Straightness: cross-axis tables, compensated axis = the transverse machine axis the head's
//!   x or z maps to; the bidirectional mean profile minus the chosen reference line (its slope is
//!   the beam's alignment, not the machine's, so it is removed — which also removes any real
//!   squareness, a separate measurement).
//! - Abbe: the angular errors turned into translations at a functional point r (tool centre
//!   relative to the head's measurement point, machine coordinates): Δ = ε × r (small angles),
//!   one table per machine axis that Δ moves.
//!
//! Resampling onto a controller's grid ([`onto_grid`]) starts from linear interpolation between
//! the measured targets, with the end values held outside the measured range (no extrapolated
//! slope), and then takes the smallest change of the grid's values that makes the controller's
//! own linear interpolation pass through every measured target again. Without it a target
//! between two grid points read the chord of the grid, not its measured value: at a bend of the
//! measured curve (0.45 µm/mm of change of slope on a 5 mm grid) up to 0.5 µm, which the
//! compensated axis kept at that target.

use super::CompError;
use super::mapping::{AxisMapping, MachineAxis};
use crate::evaluate::{AxisEvaluation, Directions, ReferenceLine};
use serde::Serialize;

/// What a table compensates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum TableKind {
    Positioning,
    Straightness,
    Abbe,
}

impl TableKind {
    pub fn name(self) -> &'static str {
        match self {
            TableKind::Positioning => "positioning",
            TableKind::Straightness => "straightness",
            TableKind::Abbe => "abbe",
        }
    }
}

/// The values of a table (mm, e = measured − nominal, one per position).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub enum TableValues {
    /// One profile for both directions; `backlash_mm` (the mean of e↓ − e↑; positive for the
    /// usual lost motion) when the positioning table is unidirectional from bidirectional data.
    Single {
        values: Vec<f64>,
        backlash_mm: Option<f64>,
    },
    /// One profile per approach direction.
    Bidirectional { up: Vec<f64>, down: Vec<f64> },
}

/// A compensation table in machine terms.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CompTable {
    pub kind: TableKind,
    /// ISO 230-1 name ("EYY", "EXY") or, for Abbe tables, "ABBE_<axis>".
    pub name: String,
    /// The axis whose position indexes the table (the axis under test).
    pub base_axis: MachineAxis,
    /// The axis the values act on.
    pub comp_axis: MachineAxis,
    /// The reference point (mm, base-axis position) where the values are zero.
    pub reference_mm: f64,
    /// Base-axis positions, strictly increasing (mm).
    pub positions_mm: Vec<f64>,
    pub values: TableValues,
}

impl CompTable {
    /// The positive-direction (or only) profile.
    pub fn primary(&self) -> &[f64] {
        match &self.values {
            TableValues::Single { values, .. } => values,
            TableValues::Bidirectional { up, .. } => up,
        }
    }

    /// The profile that applies when travelling towards decreasing position: the down profile,
    /// or the single profile plus the backlash.
    pub fn reverse(&self) -> Vec<f64> {
        match &self.values {
            TableValues::Single {
                values,
                backlash_mm,
            } => values
                .iter()
                .map(|v| v + backlash_mm.unwrap_or(0.0))
                .collect(),
            TableValues::Bidirectional { down, .. } => down.clone(),
        }
    }

    /// The table on `positions` (strictly increasing), so that linear interpolation between
    /// them passes through the table's own points ([`onto_grid`]).
    pub fn resample(&self, positions: &[f64]) -> CompTable {
        let at = |v: &[f64]| onto_grid(&self.positions_mm, v, positions);
        let values = match &self.values {
            TableValues::Single {
                values,
                backlash_mm,
            } => TableValues::Single {
                values: at(values),
                backlash_mm: *backlash_mm,
            },
            TableValues::Bidirectional { up, down } => TableValues::Bidirectional {
                up: at(up),
                down: at(down),
            },
        };
        CompTable {
            positions_mm: positions.to_vec(),
            values,
            name: self.name.clone(),
            ..*self
        }
    }

    /// Mean spacing of the table's positions.
    pub fn mean_step_mm(&self) -> f64 {
        let n = self.positions_mm.len();
        if n < 2 {
            return 0.0;
        }
        (self.positions_mm[n - 1] - self.positions_mm[0]) / (n - 1) as f64
    }
}

pub use crate::util::interpolate;

/// How the positioning table is made.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum PositioningMode {
    /// The + direction's profile and one backlash value (or the one direction measured).
    Unidirectional,
    /// One profile per direction (needs both).
    Bidirectional,
}

/// What to build.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct TableSpec {
    pub mapping: AxisMapping,
    /// Reference point (mm, position of the axis under test).
    pub reference_mm: f64,
    pub positioning: PositioningMode,
    pub straightness_line: ReferenceLine,
    /// Functional point relative to the measurement point, machine coordinates (mm);
    /// `None`: no Abbe tables.
    pub functional_point_mm: Option<[f64; 3]>,
}

/// The tables of one axis.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TableSet {
    pub positioning: CompTable,
    /// Head x, then head z.
    pub straightness: Vec<CompTable>,
    /// One per machine axis that the angular errors move at the functional point.
    pub abbe: Vec<CompTable>,
}

/// Below this an Abbe component is taken as absent (mm): 1 pm, far below any controller unit.
const ABBE_NEGLIGIBLE_MM: f64 = 1e-9;

/// Build the tables of an evaluated axis.
pub fn build_tables(eval: &AxisEvaluation, spec: &TableSpec) -> Result<TableSet, CompError> {
    if !spec.reference_mm.is_finite() {
        return Err(CompError::Option {
            name: "reference_mm",
            problem: format!("{} is not a finite position", spec.reference_mm),
        });
    }
    if let Some(r) = spec.functional_point_mm
        && r.iter().any(|x| !x.is_finite())
    {
        return Err(CompError::Option {
            name: "functional_point_mm",
            problem: format!("{} is not a finite vector", crate::util::numbers(&r)),
        });
    }
    let m = &spec.mapping;
    let names = m.iso_names();
    let base = m.axis();
    let pos = &eval.positions_mm;
    let zero = |v: Vec<f64>, basis: &[f64]| -> Vec<f64> {
        let off = interpolate(pos, basis, spec.reference_mm);
        v.into_iter().map(|x| x - off).collect()
    };
    let table = |kind, name: String, comp_axis, values| CompTable {
        kind,
        name,
        base_axis: base,
        comp_axis,
        reference_mm: spec.reference_mm,
        positions_mm: pos.clone(),
        values,
    };

    // Positioning: machine sign of dy.
    let dy = &eval.profiles[1];
    let s = f64::from(names[1].sign);
    let machine = |v: &[f64]| -> Vec<f64> { v.iter().map(|x| s * x).collect() };
    let values = match (spec.positioning, eval.directions) {
        (PositioningMode::Bidirectional, Directions::Both) => {
            let (up, down) = (
                machine(dy.up.as_deref().unwrap_or(&dy.mean)),
                machine(dy.down.as_deref().unwrap_or(&dy.mean)),
            );
            TableValues::Bidirectional {
                up: zero(up.clone(), &up),
                down: zero(down, &up),
            }
        }
        (PositioningMode::Bidirectional, d) => {
            return Err(CompError::Option {
                name: "positioning",
                problem: format!(
                    "a bidirectional table needs both directions; the data has {}: use Unidirectional",
                    d.words()
                ),
            });
        }
        (PositioningMode::Unidirectional, Directions::Both) => {
            let up = machine(dy.up.as_deref().unwrap_or(&dy.mean));
            let down = machine(dy.down.as_deref().unwrap_or(&dy.mean));
            let backlash = down.iter().zip(&up).map(|(d, u)| d - u).sum::<f64>() / up.len() as f64;
            TableValues::Single {
                values: zero(up.clone(), &up),
                backlash_mm: Some(backlash),
            }
        }
        (PositioningMode::Unidirectional, _) => {
            let one = machine(&dy.mean);
            TableValues::Single {
                values: zero(one.clone(), &one),
                backlash_mm: None,
            }
        }
    };
    let positioning = table(TableKind::Positioning, names[1].name.clone(), base, values);

    // Straightness: head x (dx) and head z (dz), residuals from the reference line.
    let mut straightness = Vec::new();
    for (k, st) in [(0usize, &eval.straightness_x), (2, &eval.straightness_z)] {
        let n = &names[k];
        let s = f64::from(n.sign);
        let v: Vec<f64> = st
            .mean
            .line(spec.straightness_line)
            .residuals
            .iter()
            .map(|r| s * r)
            .collect();
        straightness.push(table(
            TableKind::Straightness,
            n.name.clone(),
            n.along,
            TableValues::Single {
                values: zero(v.clone(), &v),
                backlash_mm: None,
            },
        ));
    }

    // Abbe: Δ = ε × r at every target.
    let mut abbe = Vec::new();
    if let Some(r) = spec.functional_point_mm {
        let deltas: Vec<[f64; 3]> = (0..pos.len())
            .map(|i| {
                let e = m.to_machine([
                    eval.profiles[3].mean[i],
                    eval.profiles[4].mean[i],
                    eval.profiles[5].mean[i],
                ]);
                [
                    e[1] * r[2] - e[2] * r[1],
                    e[2] * r[0] - e[0] * r[2],
                    e[0] * r[1] - e[1] * r[0],
                ]
            })
            .collect();
        for a in MachineAxis::ALL {
            let v: Vec<f64> = deltas.iter().map(|d| d[a.index()]).collect();
            let v = zero(v.clone(), &v);
            if v.iter().any(|x| x.abs() > ABBE_NEGLIGIBLE_MM) {
                abbe.push(table(
                    TableKind::Abbe,
                    format!("ABBE_{a}"),
                    a,
                    TableValues::Single {
                        values: v,
                        backlash_mm: None,
                    },
                ));
            }
        }
    }
    Ok(TableSet {
        positioning,
        straightness,
        abbe,
    })
}

/// Values on `grid` (strictly increasing, mm) whose linear interpolation passes through the
/// measured points (`positions`, `values`) that lie within the grid.
///
/// It starts from the measured curve's linear interpolation at the grid's points (end values
/// held) and adds the smallest change (least norm) that makes the grid's interpolation equal
/// each measured value at its position: on a grid at least twice as fine as the targets,
/// where no two measured points share a grid point of the intervals they lie in (each target
/// moves its own two points). On a coarser grid the grid samples the measured curve (its
/// points are the curve's values there) and is left so. A grid point that is itself a
/// measured position keeps its measured value, so the reference point stays zero.
pub fn onto_grid(positions: &[f64], values: &[f64], grid: &[f64]) -> Vec<f64> {
    use nalgebra::{DMatrix, DVector};
    let mut y: Vec<f64> = grid
        .iter()
        .map(|&x| interpolate(positions, values, x))
        .collect();
    let (Some(&lo), Some(&hi)) = (grid.first(), grid.last()) else {
        return y;
    };
    // One row per measured point inside the grid: the grid interval it lies in, where, and
    // its value (a point on a grid point pins that point: f = 0).
    let last = grid.len().saturating_sub(1);
    let rows: Vec<(usize, f64, f64)> = positions
        .iter()
        .zip(values)
        .filter(|(x, _)| **x >= lo && **x <= hi && last >= 1)
        .map(|(&x, &v)| {
            let k = grid.partition_point(|&g| g <= x).clamp(1, last);
            let f = (x - grid[k - 1]) / (grid[k] - grid[k - 1]);
            match f {
                f if f < 1e-9 => (k - 1, 0.0, v),
                f if f > 1.0 - 1e-9 => (k, 0.0, v),
                f => (k - 1, f, v),
            }
        })
        .collect();
    // Each point between grid points is taken by its own two: none shares one with another.
    let inside: Vec<usize> = rows.iter().filter(|r| r.1 > 0.0).map(|r| r.0).collect();
    if inside.is_empty() || inside.windows(2).any(|w| w[1] < w[0] + 2) {
        return y;
    }
    let mut a = DMatrix::<f64>::zeros(rows.len(), grid.len());
    let mut miss = DVector::<f64>::zeros(rows.len());
    for (i, &(k, f, v)) in rows.iter().enumerate() {
        a[(i, k)] = 1.0 - f;
        miss[i] = v - (1.0 - f) * y[k];
        if f > 0.0 {
            a[(i, k + 1)] = f;
            miss[i] -= f * y[k + 1];
        }
    }
    if miss.amax() == 0.0 {
        return y;
    }
    // δ = Aᵀ (A Aᵀ)⁺ miss: the least-norm change that closes the misses.
    let gram = &a * a.transpose();
    let Ok(pinv) = gram.pseudo_inverse(1e-12) else {
        return y;
    };
    let delta = a.transpose() * (pinv * miss);
    for (v, d) in y.iter_mut().zip(delta.iter()) {
        *v += d;
    }
    y
}

/// An equally spaced grid `start + k·step`, k = 0..count.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Grid {
    pub start_mm: f64,
    pub step_mm: f64,
    pub count: usize,
    /// Index of the reference point in the grid (it lies on it by construction).
    pub reference_index: usize,
}

impl Grid {
    pub fn positions(&self) -> Vec<f64> {
        (0..self.count)
            .map(|k| self.start_mm + k as f64 * self.step_mm)
            .collect()
    }
    pub fn end_mm(&self) -> f64 {
        self.start_mm + (self.count.saturating_sub(1)) as f64 * self.step_mm
    }
}

/// A controller's grid limits.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct GridLimits {
    /// Most points the controller holds for one table.
    pub max_points: usize,
    /// Smallest spacing the controller accepts (mm).
    pub min_step_mm: f64,
    /// The spacing must be a multiple of this (mm); 0 for any.
    pub step_quantum_mm: f64,
    /// Wanted spacing (mm); default: the mean spacing of the measured targets. Made coarser when
    /// the points would not fit.
    pub step_mm: Option<f64>,
}

impl GridLimits {
    /// At most `max_points`, any spacing (`step_mm` wanted).
    pub fn points(max_points: usize, step_mm: Option<f64>) -> Self {
        GridLimits {
            max_points,
            min_step_mm: 0.0,
            step_quantum_mm: 0.0,
            step_mm,
        }
    }
}

/// Fit a grid through the reference point that covers the measured range and the reference,
/// within `limits`: the spacing starts at the wanted one (at least the minimum, rounded up to
/// the quantum) and grows until the points fit. A reference point outside the measured range
/// widens the grid (the end values are held out there), so far outside it coarsens the table.
pub fn fit_grid(
    table: &CompTable,
    limits: &GridLimits,
    format: &'static str,
) -> Result<Grid, CompError> {
    let bad = |name: &'static str, problem: String| CompError::Option { name, problem };
    if limits.max_points < 2 {
        return Err(bad(
            "max_points",
            format!("{}: a table needs at least 2 points", limits.max_points),
        ));
    }
    if !(limits.min_step_mm >= 0.0 && limits.min_step_mm.is_finite()) {
        return Err(bad(
            "min_step_mm",
            format!("{} mm is not a spacing", limits.min_step_mm),
        ));
    }
    if !(limits.step_quantum_mm >= 0.0 && limits.step_quantum_mm.is_finite()) {
        return Err(bad(
            "step_quantum_mm",
            format!("{} mm is not a spacing", limits.step_quantum_mm),
        ));
    }
    if let Some(s) = limits.step_mm
        && !(s > 0.0 && s.is_finite())
    {
        return Err(bad("step_mm", format!("{s} mm: give a positive spacing")));
    }
    let p = &table.positions_mm;
    let (Some(&first), Some(&last)) = (p.first(), p.last()) else {
        return Err(CompError::Unsupported {
            format,
            problem: "the table is empty".into(),
        });
    };
    let r = table.reference_mm;
    let (lo, hi) = (first.min(r), last.max(r));
    let quantise = |s: f64| {
        let q = limits.step_quantum_mm;
        if q > 0.0 {
            (s / q - 1e-9).ceil().max(1.0) * q
        } else {
            s
        }
    };
    let mut step = quantise(
        limits
            .step_mm
            .unwrap_or_else(|| table.mean_step_mm())
            .max(limits.min_step_mm)
            .max(f64::MIN_POSITIVE),
    );
    if !step.is_finite() || step <= 0.0 {
        step = quantise((hi - lo).max(1e-3));
    }
    for _ in 0..200 {
        let k_lo = ((lo - r) / step + 1e-9).floor();
        let k_hi = ((hi - r) / step - 1e-9).ceil();
        let count = (k_hi - k_lo) as usize + 1;
        if count <= limits.max_points {
            return Ok(Grid {
                start_mm: r + k_lo * step,
                step_mm: step,
                count,
                reference_index: (-k_lo) as usize,
            });
        }
        let grown = step * (count as f64 / limits.max_points as f64);
        step = quantise(grown.max(step * (1.0 + 1e-6)));
    }
    Err(CompError::Unsupported {
        format,
        problem: format!(
            "no grid of at most {} points covers {lo}..{hi} mm",
            limits.max_points
        ),
    })
}

/// A table measured under compensation, composed with the table that was active (issue 15).
///
/// A run taken while `base` was applied sees only what `base` left: the residual. The table
/// the axis needs is `base + residual`, on `base`'s grid (the grid the controller already
/// holds): the residual is interpolated at `base`'s positions (end values held, as
/// `resample`). Both are zero at their reference points; when those differ the residual's
/// value at `base`'s reference is subtracted, so the sum is zero where `base` is. Single
/// profiles without backlash stay single; otherwise both directions are composed, each with
/// its own profile (`reverse` for a single one with backlash). Refused when the two tables do
/// not compensate the same thing (kind, name, axes).
pub fn compose(base: &CompTable, residual: &CompTable) -> Result<CompTable, CompError> {
    if base.kind != residual.kind
        || base.name != residual.name
        || base.base_axis != residual.base_axis
        || base.comp_axis != residual.comp_axis
    {
        return Err(CompError::Unsupported {
            format: "composition",
            problem: format!(
                "the active table is {} {} (acting on {} along {}) and the measured residual {} {} (acting on {} along {}): they do not compensate the same error",
                base.kind.name(),
                base.name,
                base.comp_axis,
                base.base_axis,
                residual.kind.name(),
                residual.name,
                residual.comp_axis,
                residual.base_axis
            ),
        });
    }
    if base.positions_mm.is_empty() || residual.positions_mm.is_empty() {
        return Err(CompError::Unsupported {
            format: "composition",
            problem: "a table without points cannot be composed".into(),
        });
    }
    // The residual on the base's points, through its measured points ([`onto_grid`]).
    let on_base = |r: &[f64]| onto_grid(&residual.positions_mm, r, &base.positions_mm);
    let r_up = on_base(residual.primary());
    let r_down = on_base(&residual.reverse());
    // Zero the residual where the base is zero.
    let shift = interpolate(&base.positions_mm, &r_up, base.reference_mm);
    let add = |b: &[f64], r: &[f64]| -> Vec<f64> {
        b.iter().zip(r).map(|(&bv, &rv)| bv + rv - shift).collect()
    };
    let single = |t: &CompTable| {
        matches!(
            t.values,
            TableValues::Single {
                backlash_mm: None,
                ..
            }
        )
    };
    let values = if single(base) && single(residual) {
        TableValues::Single {
            values: add(base.primary(), &r_up),
            backlash_mm: None,
        }
    } else {
        TableValues::Bidirectional {
            up: add(base.primary(), &r_up),
            down: add(&base.reverse(), &r_down),
        }
    };
    Ok(CompTable {
        kind: base.kind,
        name: base.name.clone(),
        base_axis: base.base_axis,
        comp_axis: base.comp_axis,
        reference_mm: base.reference_mm,
        positions_mm: base.positions_mm.clone(),
        values,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn table(pos: Vec<f64>, v: Vec<f64>, r: f64) -> CompTable {
        CompTable {
            kind: TableKind::Positioning,
            name: "EYY".into(),
            base_axis: MachineAxis::Y,
            comp_axis: MachineAxis::Y,
            reference_mm: r,
            positions_mm: pos,
            values: TableValues::Single {
                values: v,
                backlash_mm: None,
            },
        }
    }

    #[test]
    fn interpolation_is_linear_with_held_ends() {
        let p = [0.0, 10.0, 30.0];
        let v = [0.0, 1.0, -1.0];
        assert_eq!(interpolate(&p, &v, -5.0), 0.0);
        assert_eq!(interpolate(&p, &v, 5.0), 0.5);
        assert_eq!(interpolate(&p, &v, 10.0), 1.0);
        assert_eq!(interpolate(&p, &v, 20.0), 0.0);
        assert_eq!(interpolate(&p, &v, 99.0), -1.0);
    }

    #[test]
    fn the_grid_passes_through_every_measured_point_it_can() {
        // A bend at 101 mm, between the 5 mm grid's points 100 and 105: the chord of the
        // plain resample misses it by 0.45 µm/mm × 5 mm × 0.2 × 0.8 = 0.36 µm.
        let pos = [0.0, 101.0, 200.0];
        let val = [0.0, 0.025, 0.005];
        let grid: Vec<f64> = (0..=40).map(|k| 5.0 * k as f64).collect();
        let chord = interpolate(
            &grid,
            &grid
                .iter()
                .map(|&x| interpolate(&pos, &val, x))
                .collect::<Vec<_>>(),
            101.0,
        );
        assert!((val[1] - chord - 0.36e-3).abs() < 1e-6, "{chord}");
        let y = onto_grid(&pos, &val, &grid);
        for (x, v) in pos.iter().zip(val) {
            assert!(
                (interpolate(&grid, &y, *x) - v).abs() < 1e-12,
                "at {x} mm: {y:?}"
            );
        }
        // Only the two points around the bend move, by the least that closes the miss.
        let lin: Vec<f64> = grid.iter().map(|&x| interpolate(&pos, &val, x)).collect();
        let moved: Vec<usize> = (0..grid.len())
            .filter(|&k| (y[k] - lin[k]).abs() > 1e-15)
            .collect();
        assert_eq!(moved, vec![20, 21]);
        // Two measured points between the same two points of a coarse grid: the grid samples
        // the curve.
        let y = onto_grid(
            &[0.0, 10.0, 30.0, 40.0],
            &[0.0, 1.0, 1.0, 0.0],
            &[0.0, 40.0],
        );
        assert_eq!(y, vec![0.0, 0.0]);
    }

    #[test]
    fn grid_through_reference_within_limits() {
        let pos: Vec<f64> = (0..41).map(|k| 2.0 + 24.5 * k as f64).collect();
        let t = table(pos, vec![0.0; 41], 0.0);
        let lim = GridLimits {
            max_points: 1000,
            min_step_mm: 0.0,
            step_quantum_mm: 0.001,
            step_mm: Some(10.0),
        };
        let g = fit_grid(&t, &lim, "test").unwrap();
        assert_eq!((g.start_mm, g.step_mm, g.reference_index), (0.0, 10.0, 0));
        // Covers 0 .. 982 mm: 0, 10, …, 990.
        assert_eq!(g.count, 100);
        let g = fit_grid(
            &t,
            &GridLimits {
                max_points: 20,
                ..lim
            },
            "test",
        )
        .unwrap();
        assert!(g.count <= 20 && g.end_mm() >= 982.0, "{g:?}");
        assert!(((g.step_mm / 0.001).round() * 0.001 - g.step_mm).abs() < 1e-9);
        // Reference inside: it is a grid point.
        let t = table(vec![-100.0, 0.0, 250.0], vec![0.0; 3], 40.0);
        let g = fit_grid(
            &t,
            &GridLimits {
                step_mm: Some(30.0),
                ..lim
            },
            "test",
        )
        .unwrap();
        let p = g.positions();
        assert!((p[g.reference_index] - 40.0).abs() < 1e-9);
        assert!(p[0] <= -100.0 && *p.last().unwrap() >= 250.0);
        assert!(
            fit_grid(
                &t,
                &GridLimits {
                    max_points: 1,
                    ..lim
                },
                "test"
            )
            .is_err()
        );
    }

    #[test]
    fn a_residual_composes_onto_the_active_tables_grid() {
        // The active table on a 0, 50, 100 mm grid; the residual measured at 0, 30, 60, 90:
        // two between the same grid points, so the grid samples the residual.
        let base = table(vec![0.0, 50.0, 100.0], vec![0.0, 0.010, 0.004], 0.0);
        let mut residual = table(
            vec![0.0, 30.0, 60.0, 90.0],
            vec![0.0, 0.003, 0.006, -0.003],
            0.0,
        );
        residual.values = TableValues::Single {
            values: vec![0.0, 0.003, 0.006, -0.003],
            backlash_mm: Some(0.002),
        };
        let c = compose(&base, &residual).unwrap();
        assert_eq!(c.positions_mm, vec![0.0, 50.0, 100.0]);
        // At 50 mm the residual is 0.003 + (20/30)·0.003 = 0.005; at 100 mm held at −0.003.
        let TableValues::Bidirectional { up, down } = &c.values else {
            panic!("a residual with backlash makes both directions: {c:?}");
        };
        let want_up = [0.0, 0.015, 0.001];
        for (u, w) in up.iter().zip(want_up) {
            assert!((u - w).abs() < 1e-12, "{up:?}");
        }
        for (d, w) in down.iter().zip(want_up) {
            assert!((d - (w + 0.002)).abs() < 1e-12, "{down:?}");
        }
        // On a grid twice as fine as the residual's points the composed table adds the
        // residual exactly at each of them, where the controller interpolates.
        let fine: Vec<f64> = (0..=10).map(|k| 10.0 * k as f64).collect();
        let fine_base = table(fine.clone(), fine.iter().map(|x| x * 1e-4).collect(), 0.0);
        let off = table(
            vec![0.0, 33.0, 61.0, 94.0],
            vec![0.0, 0.003, 0.006, -0.003],
            0.0,
        );
        let c = compose(&fine_base, &off).unwrap();
        let plain: Vec<f64> = fine
            .iter()
            .map(|&x| interpolate(&off.positions_mm, off.primary(), x))
            .collect();
        let plain_at_33 = interpolate(&fine, &plain, 33.0);
        assert!(
            (plain_at_33 - 0.003).abs() > 1e-5,
            "the chord alone would miss it"
        );
        for (x, r) in off.positions_mm.iter().zip(off.primary()) {
            let added = interpolate(&fine, c.primary(), *x) - x * 1e-4;
            assert!((added - r).abs() < 1e-12, "at {x} mm: {added} against {r}");
        }
        // Single profiles stay single; another error is refused.
        let plain = table(vec![0.0, 100.0], vec![0.0, 0.002], 0.0);
        let c = compose(&base, &plain).unwrap();
        assert_eq!(c.primary(), &[0.0, 0.011, 0.006][..]);
        let mut other = plain.clone();
        other.name = "EXY".into();
        let e = compose(&base, &other).unwrap_err().to_string();
        assert!(e.contains("do not compensate the same error"), "{e}");
    }
}
