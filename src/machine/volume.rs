//! The tool point's error over the volume: a model's prediction on a regular grid, as the
//! service's machine view, the machine report and the CLI state it, and what a control's
//! compensation leaves of it (the model minus the compensation the control applies).
//!
//! The points are the corners of a regular grid over the travels, ends included: the same
//! points every time, so two figures of one machine compare.

use super::model::Volumetric;

/// Points a side of the survey's grid (11³ = 1331 points).
pub const SIDE: usize = 11;

/// The largest and the RMS of the tool point's error over a grid (mm).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Survey {
    pub points: usize,
    pub max_mm: f64,
    pub rms_mm: f64,
    /// Where the largest is (mm, machine X, Y, Z).
    pub at_mm: [f64; 3],
}

/// Position `i` of `side` evenly spaced over `0..=travel`.
fn along(travel: f64, side: usize, i: usize) -> f64 {
    if side < 2 {
        0.0
    } else {
        travel * i as f64 / (side - 1) as f64
    }
}

/// The length of the tool point's error at `p` (mm): `model`'s, less what `applied` takes
/// off when a compensation is given.
fn residual(
    model: &dyn Volumetric,
    applied: Option<&dyn Volumetric>,
    p: [f64; 3],
    tool: [f64; 3],
) -> f64 {
    let e = model.error_at(p, tool);
    let c = applied.map_or([0.0; 3], |a| a.error_at(p, tool));
    let d = [e[0] - c[0], e[1] - c[1], e[2] - c[2]];
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

/// `model`'s tool-point error over `SIDE`³ points of `travel_mm` with `tool_mm`; with `applied`,
/// what that compensation leaves of it.
pub fn survey(
    model: &dyn Volumetric,
    applied: Option<&dyn Volumetric>,
    travel_mm: [f64; 3],
    tool_mm: [f64; 3],
) -> Survey {
    let (mut max, mut sum2, mut at, mut n) = (0.0f64, 0.0, [0.0; 3], 0usize);
    for i in 0..SIDE {
        for j in 0..SIDE {
            for l in 0..SIDE {
                let p = [
                    along(travel_mm[0], SIDE, i),
                    along(travel_mm[1], SIDE, j),
                    along(travel_mm[2], SIDE, l),
                ];
                let r = residual(model, applied, p, tool_mm);
                sum2 += r * r;
                n += 1;
                if r > max {
                    (max, at) = (r, p);
                }
            }
        }
    }
    Survey {
        points: n,
        max_mm: max,
        rms_mm: (sum2 / n.max(1) as f64).sqrt(),
        at_mm: at,
    }
}

/// A map of the tool point's error in one plane of constant Z: `x_side` × `y_side` points over
/// the X and Y travels.
#[derive(Clone, Debug, PartialEq)]
pub struct PlaneMap {
    pub z_mm: f64,
    pub x_mm: Vec<f64>,
    pub y_mm: Vec<f64>,
    /// `error_mm[j][i]`: the length of the error at (`x_mm[i]`, `y_mm[j]`).
    pub error_mm: Vec<Vec<f64>>,
}

/// `model`'s tool-point error (less `applied` when given) in the plane `z_mm`.
pub fn plane_map(
    model: &dyn Volumetric,
    applied: Option<&dyn Volumetric>,
    travel_mm: [f64; 3],
    tool_mm: [f64; 3],
    z_mm: f64,
    x_side: usize,
    y_side: usize,
) -> PlaneMap {
    let x_mm: Vec<f64> = (0..x_side)
        .map(|i| along(travel_mm[0], x_side, i))
        .collect();
    let y_mm: Vec<f64> = (0..y_side)
        .map(|j| along(travel_mm[1], y_side, j))
        .collect();
    let error_mm = y_mm
        .iter()
        .map(|&y| {
            x_mm.iter()
                .map(|&x| residual(model, applied, [x, y, z_mm], tool_mm))
                .collect()
        })
        .collect();
    PlaneMap {
        z_mm,
        x_mm,
        y_mm,
        error_mm,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A machine whose tool point is off by a fixed vector plus `gain` × X along X.
    struct Linear {
        offset: [f64; 3],
        gain: f64,
    }
    impl Volumetric for Linear {
        fn error_at(&self, cmd: [f64; 3], _tool: [f64; 3]) -> [f64; 3] {
            [
                self.offset[0] + self.gain * cmd[0],
                self.offset[1],
                self.offset[2],
            ]
        }
    }

    #[test]
    fn the_survey_finds_the_largest_error_where_it_is_and_its_rms() {
        let m = Linear {
            offset: [0.0, 0.003, 0.004],
            gain: 0.0,
        };
        let s = survey(&m, None, [100.0, 50.0, 20.0], [0.0; 3]);
        assert_eq!(s.points, SIDE * SIDE * SIDE);
        // A constant 3-4-5 error: 5 µm everywhere.
        assert!((s.max_mm - 0.005).abs() < 1e-15 && (s.rms_mm - 0.005).abs() < 1e-15);
        let g = Linear {
            offset: [0.0; 3],
            gain: 1e-5,
        };
        let s = survey(&g, None, [100.0, 50.0, 20.0], [0.0; 3]);
        assert!((s.max_mm - 1e-3).abs() < 1e-15);
        assert_eq!(s.at_mm[0], 100.0);
        // RMS of g·x over x = 0, 10, …, 100: g·√(Σ x²/11) = g·√3500.
        assert!(
            (s.rms_mm - 1e-5 * 3500f64.sqrt()).abs() < 1e-12,
            "{}",
            s.rms_mm
        );
    }

    #[test]
    fn a_compensation_leaves_its_difference_and_the_map_holds_the_plane() {
        let m = Linear {
            offset: [0.001, 0.0, 0.0],
            gain: 2e-5,
        };
        let c = Linear {
            offset: [0.001, 0.0, 0.0],
            gain: 1e-5,
        };
        let s = survey(&m, Some(&c), [200.0, 100.0, 50.0], [0.0; 3]);
        assert!((s.max_mm - 2e-3).abs() < 1e-15, "{}", s.max_mm);
        let map = plane_map(&m, None, [200.0, 100.0, 50.0], [0.0; 3], 25.0, 5, 3);
        assert_eq!(map.x_mm, vec![0.0, 50.0, 100.0, 150.0, 200.0]);
        assert_eq!(map.y_mm, vec![0.0, 50.0, 100.0]);
        assert_eq!(map.error_mm.len(), 3);
        assert!((map.error_mm[2][4] - (0.001 + 2e-5 * 200.0)).abs() < 1e-15);
    }
}
