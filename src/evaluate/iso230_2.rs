//! ISO 230-2 positioning figures (DESIGN §7), from the deviations `x_ij = P_ij − P_i` of n runs
//! per direction at every target.
//!
//! Per target i: x̄↑, x̄↓ (means), x̄ = (x̄↑ + x̄↓)/2, B_i = x̄↑ − x̄↓, s↑, s↓ (n − 1 in the
//! denominator), R↑_i = 4s↑, R↓_i = 4s↓, R_i = max(2s↑ + 2s↓ + |B_i|, R↑_i, R↓_i).
//! Axis: B = max|B_i|, B̄ = mean B_i, R↑ = max R↑_i, R↓ = max R↓_i, R = max R_i,
//! E↑ = max x̄↑ − min x̄↑, E↓ likewise, E = max(x̄↑, x̄↓) − min(x̄↑, x̄↓), M = max x̄ − min x̄,
//! A↑ = max(x̄↑ + 2s↑) − min(x̄↑ − 2s↑), A↓ likewise, A = max over both directions of
//! (x̄ + 2s) − min over both of (x̄ − 2s).
//!
//! With one direction only, the bidirectional figures (x̄, B_i, R_i; A, B, B̄, R, E, M) and the
//! other direction's figures are undefined (`None`); `Iso230_2::undefined` names them.

use super::group::{Directions, Grouped, Keyed, group};
use super::{EvalError, mean_sd, range};
use serde::Serialize;

/// One positioning deviation (`value`, mm) with its key.
pub type Sample = Keyed<f64>;

/// The figures of one target (mm).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TargetFigures {
    pub index: u32,
    pub position_mm: f64,
    pub x_up: Option<f64>,
    pub x_down: Option<f64>,
    pub x_mean: Option<f64>,
    pub b: Option<f64>,
    pub s_up: Option<f64>,
    pub s_down: Option<f64>,
    pub r_up: Option<f64>,
    pub r_down: Option<f64>,
    pub r: Option<f64>,
}

/// The figures of the axis (mm).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct AxisFigures {
    pub a: Option<f64>,
    pub a_up: Option<f64>,
    pub a_down: Option<f64>,
    pub b: Option<f64>,
    pub b_mean: Option<f64>,
    pub r: Option<f64>,
    pub r_up: Option<f64>,
    pub r_down: Option<f64>,
    pub e: Option<f64>,
    pub e_up: Option<f64>,
    pub e_down: Option<f64>,
    pub m: Option<f64>,
}

/// An ISO 230-2 evaluation.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Iso230_2 {
    pub directions: Directions,
    pub runs: Vec<u32>,
    pub targets: Vec<TargetFigures>,
    pub axis: AxisFigures,
}

impl Iso230_2 {
    /// Names of the axis figures the data cannot define (one direction only), in report order.
    pub fn undefined(&self) -> Vec<&'static str> {
        let a = &self.axis;
        [
            ("A", a.a),
            ("A_up", a.a_up),
            ("A_down", a.a_down),
            ("B", a.b),
            ("B_mean", a.b_mean),
            ("R", a.r),
            ("R_up", a.r_up),
            ("R_down", a.r_down),
            ("E", a.e),
            ("E_up", a.e_up),
            ("E_down", a.e_down),
            ("M", a.m),
        ]
        .into_iter()
        .filter(|(_, v)| v.is_none())
        .map(|(n, _)| n)
        .collect()
    }
}

/// Validate and evaluate positioning deviations (rows in any order).
pub fn evaluate(samples: &[Sample]) -> Result<Iso230_2, EvalError> {
    let g = group(samples)?;
    for t in &g.targets {
        for (d, vals) in [("+", &t.up), ("-", &t.down)] {
            if let Some((k, v)) = vals.iter().enumerate().find(|(_, v)| !v.is_finite()) {
                return Err(EvalError::NotFinite {
                    target: t.index,
                    run: g.runs[k],
                    direction: d,
                    at: String::new(),
                    what: "the deviation".into(),
                    value: *v,
                });
            }
        }
    }
    Ok(from_grouped(&g))
}

/// Evaluate validated data (see `group::group` for what that guarantees: ≥ 2 runs, ≥ 2 targets).
pub fn from_grouped(g: &Grouped<f64>) -> Iso230_2 {
    let both = g.directions == Directions::Both;
    let targets: Vec<TargetFigures> = g
        .targets
        .iter()
        .map(|t| {
            let up = (!t.up.is_empty()).then(|| mean_sd(&t.up));
            let down = (!t.down.is_empty()).then(|| mean_sd(&t.down));
            let (x_up, s_up) = (up.map(|u| u.0), up.and_then(|u| u.1));
            let (x_down, s_down) = (down.map(|u| u.0), down.and_then(|u| u.1));
            let b = both.then(|| x_up.unwrap_or(0.0) - x_down.unwrap_or(0.0));
            let r_up = s_up.map(|s| 4.0 * s);
            let r_down = s_down.map(|s| 4.0 * s);
            let r = match (s_up, s_down, b) {
                (Some(su), Some(sd), Some(b)) => {
                    Some((2.0 * su + 2.0 * sd + b.abs()).max(4.0 * su).max(4.0 * sd))
                }
                _ => None,
            };
            TargetFigures {
                index: t.index,
                position_mm: t.position_mm,
                x_up,
                x_down,
                x_mean: match (x_up, x_down) {
                    (Some(u), Some(d)) => Some((u + d) / 2.0),
                    _ => None,
                },
                b,
                s_up,
                s_down,
                r_up,
                r_down,
                r,
            }
        })
        .collect();

    let col = |f: fn(&TargetFigures) -> Option<f64>| -> Option<Vec<f64>> {
        targets.iter().map(f).collect::<Option<Vec<f64>>>()
    };
    let max = |v: &[f64]| v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let min = |v: &[f64]| v.iter().copied().fold(f64::INFINITY, f64::min);
    let (xu, xd, xm) = (col(|t| t.x_up), col(|t| t.x_down), col(|t| t.x_mean));
    let (su, sd) = (col(|t| t.s_up), col(|t| t.s_down));
    let bs = col(|t| t.b);
    let band = |x: &[f64], s: &[f64]| -> (Vec<f64>, Vec<f64>) {
        (
            x.iter().zip(s).map(|(x, s)| x + 2.0 * s).collect(),
            x.iter().zip(s).map(|(x, s)| x - 2.0 * s).collect(),
        )
    };
    let a_dir = |x: &Option<Vec<f64>>, s: &Option<Vec<f64>>| match (x, s) {
        (Some(x), Some(s)) => {
            let (hi, lo) = band(x, s);
            Some(max(&hi) - min(&lo))
        }
        _ => None,
    };
    let a = match (&xu, &su, &xd, &sd) {
        (Some(xu), Some(su), Some(xd), Some(sd)) => {
            let (hu, lu) = band(xu, su);
            let (hd, ld) = band(xd, sd);
            Some(max(&hu).max(max(&hd)) - min(&lu).min(min(&ld)))
        }
        _ => None,
    };
    let axis = AxisFigures {
        a,
        a_up: a_dir(&xu, &su),
        a_down: a_dir(&xd, &sd),
        b: bs
            .as_ref()
            .map(|b| b.iter().fold(0.0f64, |m, x| m.max(x.abs()))),
        b_mean: bs.as_ref().map(|b| b.iter().sum::<f64>() / b.len() as f64),
        r: col(|t| t.r).map(|r| max(&r)),
        r_up: col(|t| t.r_up).map(|r| max(&r)),
        r_down: col(|t| t.r_down).map(|r| max(&r)),
        e: match (&xu, &xd) {
            (Some(u), Some(d)) => Some(range(u.iter().chain(d).copied())),
            _ => None,
        },
        e_up: xu.as_ref().map(|u| range(u.iter().copied())),
        e_down: xd.as_ref().map(|d| range(d.iter().copied())),
        m: xm.as_ref().map(|m| range(m.iter().copied())),
    };
    Iso230_2 {
        directions: g.directions,
        runs: g.runs.clone(),
        targets,
        axis,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::run::Direction;

    /// Two targets, three runs, numbers chosen so every figure is easy by hand (mm).
    fn samples(dirs: &[Direction]) -> Vec<Sample> {
        // target 0: up 1, 2, 3 (mean 2, s 1); down 0, 0, 3 (mean 1, s √3)
        // target 1: up 4, 4, 4 (mean 4, s 0); down 5, 6, 7 (mean 6, s 1)
        let data = [
            (0, Direction::Up, [1.0, 2.0, 3.0]),
            (0, Direction::Down, [0.0, 0.0, 3.0]),
            (1, Direction::Up, [4.0, 4.0, 4.0]),
            (1, Direction::Down, [5.0, 6.0, 7.0]),
        ];
        let mut v = Vec::new();
        for (t, d, xs) in data {
            if !dirs.contains(&d) {
                continue;
            }
            for (r, x) in xs.into_iter().enumerate() {
                v.push(Sample {
                    target_index: t,
                    target_mm: 100.0 * t as f64,
                    run: r as u32 + 1,
                    direction: d,
                    line: None,
                    value: x,
                });
            }
        }
        v
    }

    fn close(a: Option<f64>, b: f64) {
        let a = a.expect("defined");
        assert!((a - b).abs() < 1e-12, "{a} vs {b}");
    }

    #[test]
    fn bidirectional_by_hand() {
        let r = evaluate(&samples(&[Direction::Up, Direction::Down])).unwrap();
        let s3 = 3f64.sqrt();
        let t0 = &r.targets[0];
        close(t0.x_up, 2.0);
        close(t0.x_down, 1.0);
        close(t0.x_mean, 1.5);
        close(t0.b, 1.0);
        close(t0.s_down, s3);
        close(t0.r_down, 4.0 * s3);
        close(t0.r, (2.0 + 2.0 * s3 + 1.0f64).max(4.0 * s3));
        let t1 = &r.targets[1];
        close(t1.b, -2.0);
        close(t1.r, 2.0 * 0.0 + 2.0 * 1.0 + 2.0);
        let a = &r.axis;
        close(a.b, 2.0);
        close(a.b_mean, -0.5);
        close(a.r_up, 4.0);
        close(a.r_down, 4.0 * s3);
        close(a.e_up, 2.0);
        close(a.e_down, 5.0);
        close(a.e, 5.0);
        close(a.m, 5.0 - 1.5);
        close(a.a_up, (4.0f64).max(2.0 + 2.0) - (2.0f64 - 2.0).min(4.0));
        close(a.a_down, (6.0 + 2.0) - (1.0 - 2.0 * s3));
        close(a.a, 8.0 - (1.0 - 2.0 * s3));
        assert!(r.undefined().is_empty());
        assert!(a.e.unwrap() >= a.e_up.unwrap().max(a.e_down.unwrap()));
    }

    #[test]
    fn unidirectional_names_what_is_undefined() {
        let r = evaluate(&samples(&[Direction::Up])).unwrap();
        assert_eq!(r.directions, Directions::UpOnly);
        close(r.axis.e_up, 2.0);
        close(r.axis.a_up, 4.0);
        assert_eq!(r.targets[0].x_mean, None);
        assert_eq!(r.targets[0].r, None);
        assert_eq!(
            r.undefined(),
            vec![
                "A", "A_down", "B", "B_mean", "R", "R_down", "E", "E_down", "M"
            ]
        );
    }
}
