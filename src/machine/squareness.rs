//! A squareness measured with an optical square (issue 27), as the laser systems take it: the
//! straightness of one axis against the beam as it comes, then the straightness of the other
//! axis against the same beam turned through 90° by a pentaprism (`optics::square`), the laser
//! not touched between the two. Each run's least-squares straightness line gives the axis's
//! direction against its beam (a slope per head axis); the square relates the two beams by its
//! certified turn, 90° + δ; the two lines' cosine is the squareness (X the reference, the names
//! and signs of `machine::model`: C0Y = −cos(X, Y), B0Z = cos(X, Z), A0Z = −cos(Y, Z)).
//!
//! The set-up on the second axis is the head's usual one (mount, follower, alignment of the
//! out-of-plane angle and the offsets); only the beam's direction in the square's plane is
//! fixed by the square, so that screw is not turned.
//!
//! The uncertainty (standard, combined in quadrature, expanded with k = 2):
//!
//! | term | from |
//! |---|---|
//! | slope, first axis | its straightness points: the scatter terms of its budget through the least-squares weights, and its largest instrument term as a tilt across the travel (±2u/L, rectangular) |
//! | slope, second axis | the same, through the square |
//! | optical square | its certificate's standard uncertainty of δ |
//! | laser pointing | the laser's pointing stability between the two runs, when stated |

use super::error::MachineError;
use super::model::Squareness;
use crate::comp::mapping::{AxisMapping, MachineAxis};
use crate::evaluate::AxisEvaluation;
use crate::evaluate::uncertainty::{Budget, Component, K};
use crate::optics::V3;
use crate::optics::square::OpticalSquare;
use crate::units::RAD_PER_ARCSEC;

/// The two axes of a squareness, in the order they are measured.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SquarePair {
    /// X with the beam as it comes, Y through the square: C0Y.
    XY,
    /// X, then Z through the square: B0Z.
    ZX,
    /// Y, then Z through the square: A0Z.
    YZ,
}

impl SquarePair {
    pub const ALL: [SquarePair; 3] = [SquarePair::XY, SquarePair::ZX, SquarePair::YZ];

    /// The axis measured first (the beam as it comes) and the one through the square.
    pub fn axes(self) -> (MachineAxis, MachineAxis) {
        use MachineAxis::*;
        match self {
            SquarePair::XY => (X, Y),
            SquarePair::ZX => (X, Z),
            SquarePair::YZ => (Y, Z),
        }
    }

    /// The ISO 230-1 name of the squareness it gives.
    pub fn name(self) -> &'static str {
        Squareness::NAMES[self.index()]
    }

    /// Its place in [`Squareness::to_array`].
    pub fn index(self) -> usize {
        match self {
            SquarePair::XY => 0,
            SquarePair::ZX => 1,
            SquarePair::YZ => 2,
        }
    }

    /// The square's axis in the machine's frame: it turns the first axis's direction into the
    /// second's by +90° about it (right hand).
    pub fn square_axis(self) -> V3 {
        match self {
            SquarePair::XY => V3::z(),
            SquarePair::ZX => -V3::y(),
            SquarePair::YZ => V3::x(),
        }
    }

    /// The squareness (rad) from the cosine of the two axes' lines.
    fn of_cosine(self, c: f64) -> f64 {
        let a = c.clamp(-1.0, 1.0).asin();
        match self {
            SquarePair::XY | SquarePair::YZ => -a,
            SquarePair::ZX => a,
        }
    }
}

impl std::fmt::Display for SquarePair {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            SquarePair::XY => "XY",
            SquarePair::ZX => "ZX",
            SquarePair::YZ => "YZ",
        })
    }
}

/// What the optical square's certificate states.
#[derive(Clone, Debug, PartialEq)]
pub struct SquareCertificate {
    /// Its serial or certificate number, for the report.
    pub id: String,
    /// The turn is 90° + this (rad), about the square's axis.
    pub deviation_rad: f64,
    /// Standard uncertainty of the deviation (rad).
    pub u_rad: f64,
}

/// One set-up's straightness slopes as the head measured them: the axis's line against the
/// beam, per head axis (x, z; mm per mm of travel), with their standard uncertainties.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SetupSlopes {
    pub mapping: AxisMapping,
    pub slope: [f64; 2],
    pub u: [f64; 2],
}

impl SetupSlopes {
    /// From a run's evaluation and its budget: each straightness's least-squares slope (the
    /// bidirectional mean), its u from the budget's points (see the module's table).
    pub fn from_evaluation(
        mapping: AxisMapping,
        eval: &AxisEvaluation,
        budget: &Budget,
    ) -> Result<SetupSlopes, MachineError> {
        let axis = mapping.axis();
        let p = &eval.positions_mm;
        let n = p.len();
        let mean = p.iter().sum::<f64>() / n.max(1) as f64;
        let sxx: f64 = p.iter().map(|x| (x - mean).powi(2)).sum();
        let len = p.iter().fold(f64::NEG_INFINITY, |a, &b| a.max(b))
            - p.iter().fold(f64::INFINITY, |a, &b| a.min(b));
        if n < 3 || !(sxx > 0.0 && len > 0.0) {
            return Err(MachineError::Table {
                axis,
                problem: format!(
                    "{n} targets: a squareness needs the straightness at three or more spread along the travel"
                ),
            });
        }
        let scatter = [Component::Noise, Component::Repeatability];
        let mut out = [(0.0, 0.0); 2];
        for (j, (k, line)) in [(0usize, &eval.straightness_x), (2, &eval.straightness_z)]
            .into_iter()
            .enumerate()
        {
            let slope = line
                .mean
                .line(crate::evaluate::ReferenceLine::LeastSquares)
                .slope;
            let (mut random, mut systematic) = (0.0f64, 0.0f64);
            for (i, &ti) in eval.target_indices.iter().enumerate() {
                let point = budget.point(k, ti, None).ok_or_else(|| {
                    MachineError::Missing(format!(
                        "the budget of {axis} has no point at target {ti} for its straightness: measure the run with its budget"
                    ))
                })?;
                let w = (p[i] - mean) / sxx;
                let r2: f64 = scatter.iter().map(|c| point.terms[c.index()].powi(2)).sum();
                random += w * w * r2;
                let s2: f64 = Component::ALL
                    .iter()
                    .filter(|c| !scatter.contains(c))
                    .map(|c| point.terms[c.index()].powi(2))
                    .sum();
                systematic = systematic.max(s2.sqrt());
            }
            let tilt = 2.0 * systematic / len / 3f64.sqrt();
            out[j] = (slope, random.sqrt().hypot(tilt));
        }
        let s = SetupSlopes {
            mapping,
            slope: [out[0].0, out[1].0],
            u: [out[0].1, out[1].1],
        };
        if s.slope.iter().chain(&s.u).all(|v| v.is_finite()) {
            Ok(s)
        } else {
            Err(MachineError::Table {
                axis,
                problem: "the straightness slopes or their uncertainties are not finite".into(),
            })
        }
    }
}

/// One term of a squareness's budget.
#[derive(Clone, Debug, PartialEq)]
pub struct SquarenessTerm {
    pub name: String,
    /// Standard uncertainty (rad).
    pub u_rad: f64,
    /// Where it comes from.
    pub source: String,
}

/// A measured squareness with its budget.
#[derive(Clone, Debug, PartialEq)]
pub struct MeasuredSquareness {
    pub pair: SquarePair,
    pub value_rad: f64,
    pub terms: Vec<SquarenessTerm>,
    /// Combined standard uncertainty (rad).
    pub u_rad: f64,
    /// Expanded, k = 2 (rad).
    pub expanded_rad: f64,
}

impl std::fmt::Display for MeasuredSquareness {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} ({}) {:+.2}″ ± {:.2}″ (k = 2)",
            self.pair.name(),
            self.pair,
            self.value_rad / RAD_PER_ARCSEC,
            self.expanded_rad / RAD_PER_ARCSEC
        )
    }
}

/// The machine-frame unit vector of head axis `k` (0 x, 1 y, 2 z) of a set-up.
fn head_axis(m: &AxisMapping, k: usize) -> V3 {
    let mut v = [0.0; 3];
    v[k] = 1.0;
    V3::from(m.to_machine(v))
}

/// The cosine of the two lines: the first set-up's beam along its head's y, the second's that
/// beam turned by the square, each line its beam plus its slopes along its head's x and z.
fn cosine(first: &SetupSlopes, second: &SetupSlopes, square: &OpticalSquare) -> f64 {
    let line = |s: &SetupSlopes, beam: V3| {
        beam + head_axis(&s.mapping, 0) * s.slope[0] + head_axis(&s.mapping, 2) * s.slope[1]
    };
    let beam = head_axis(&first.mapping, 1);
    let (a, b) = (line(first, beam), line(second, square.turn(beam)));
    a.dot(&b) / (a.norm() * b.norm())
}

/// The squareness of `pair` from the two set-ups' slopes, the square's certificate and, when
/// stated, the laser's pointing stability between the two runs (rad, standard).
pub fn measure(
    pair: SquarePair,
    first: &SetupSlopes,
    second: &SetupSlopes,
    square: &SquareCertificate,
    pointing_u_rad: Option<f64>,
) -> Result<MeasuredSquareness, MachineError> {
    let (a, b) = pair.axes();
    for (s, want, which) in [(first, a, "first"), (second, b, "second")] {
        if s.mapping.axis() != want {
            return Err(MachineError::Missing(format!(
                "{} ({pair}): the {which} set-up measured {}, it must be {want}",
                pair.name(),
                s.mapping.axis()
            )));
        }
    }
    let stated = [
        square.deviation_rad,
        square.u_rad,
        pointing_u_rad.unwrap_or(0.0),
    ];
    if !stated.iter().all(|v| v.is_finite()) || square.u_rad < 0.0 {
        return Err(MachineError::Missing(format!(
            "optical square {}: its deviation and uncertainty must be finite numbers, the uncertainty not negative",
            square.id
        )));
    }
    let value = |f: &SetupSlopes, s: &SetupSlopes, d: f64| -> Result<f64, MachineError> {
        let sq = OpticalSquare::new(pair.square_axis(), d).ok_or_else(|| {
            MachineError::Missing(format!("optical square {}: no turn", square.id))
        })?;
        Ok(pair.of_cosine(cosine(f, s, &sq)))
    };
    let v = value(first, second, square.deviation_rad)?;
    // Sensitivities by central differences (the function is smooth and nearly linear).
    let h = 1e-7;
    let slope_u = |which: usize| -> Result<f64, MachineError> {
        let mut sum = 0.0;
        for j in 0..2 {
            let bump = |sign: f64| {
                let (mut f, mut s) = (*first, *second);
                if which == 0 {
                    f.slope[j] += sign * h;
                } else {
                    s.slope[j] += sign * h;
                }
                value(&f, &s, square.deviation_rad)
            };
            let c = (bump(1.0)? - bump(-1.0)?) / (2.0 * h);
            let u = if which == 0 { first.u[j] } else { second.u[j] };
            sum += (c * u).powi(2);
        }
        Ok(sum.sqrt())
    };
    let c_delta = (value(first, second, square.deviation_rad + h)?
        - value(first, second, square.deviation_rad - h)?)
        / (2.0 * h);
    let mut terms = vec![
        SquarenessTerm {
            name: format!("straightness slope of {a}"),
            u_rad: slope_u(0)?,
            source: format!(
                "{a}'s straightness points against the beam (scatter and instrument terms of its budget)"
            ),
        },
        SquarenessTerm {
            name: format!("straightness slope of {b}"),
            u_rad: slope_u(1)?,
            source: format!("{b}'s straightness points against the beam turned by the square"),
        },
        SquarenessTerm {
            name: "optical square".into(),
            u_rad: (c_delta * square.u_rad).abs(),
            source: format!(
                "certificate {}: deviation from 90° {:+.2}″, u {:.2}″",
                square.id,
                square.deviation_rad / RAD_PER_ARCSEC,
                square.u_rad / RAD_PER_ARCSEC
            ),
        },
    ];
    terms.push(match pointing_u_rad {
        Some(u) => SquarenessTerm {
            name: "laser pointing".into(),
            u_rad: u.abs(),
            source: "the laser's pointing stability between the two runs, as stated".into(),
        },
        None => SquarenessTerm {
            name: "laser pointing".into(),
            u_rad: 0.0,
            source: "not stated: the laser's pointing is taken as stable between the two runs"
                .into(),
        },
    });
    let u = terms.iter().map(|t| t.u_rad * t.u_rad).sum::<f64>().sqrt();
    Ok(MeasuredSquareness {
        pair,
        value_rad: v,
        terms,
        u_rad: u,
        expanded_rad: K * u,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn slopes(axis: MachineAxis, s: [f64; 2]) -> SetupSlopes {
        SetupSlopes {
            mapping: AxisMapping::standard(axis),
            slope: s,
            u: [1e-7, 2e-7],
        }
    }

    fn square(deviation_arcsec: f64) -> SquareCertificate {
        SquareCertificate {
            id: "OS-1".into(),
            deviation_rad: deviation_arcsec * RAD_PER_ARCSEC,
            u_rad: 0.25 * RAD_PER_ARCSEC,
        }
    }

    /// By hand, first order: the beam on X points off X's line by the slope the head reads
    /// (X's head x is −Y); the square turns it by 90° + δ; Y's line is that turned beam plus
    /// its own slope along its head x (+X). X·Y = −s₁ − δ + s₂, so C0Y = s₁ + δ − s₂.
    #[test]
    fn the_squareness_of_x_and_y_by_hand() {
        let (s1, s2, d) = (3e-5, -2e-5, 4.0);
        let m = measure(
            SquarePair::XY,
            &slopes(MachineAxis::X, [s1, 7e-5]),
            &slopes(MachineAxis::Y, [s2, -5e-5]),
            &square(d),
            None,
        )
        .expect("squareness");
        let want = s1 + d * RAD_PER_ARCSEC - s2;
        // Second order (the out-of-plane slopes' product, 3.5e-9 here) aside.
        assert!(
            (m.value_rad - want).abs() < 1e-8,
            "{} want {want}",
            m.value_rad
        );
        // The out-of-plane slopes do not enter to first order.
        assert!(
            (m.terms[0].u_rad - 1e-7).abs() < 1e-10,
            "{}",
            m.terms[0].u_rad
        );
        assert!((m.terms[1].u_rad - 1e-7).abs() < 1e-10);
        assert!((m.terms[2].u_rad - 0.25 * RAD_PER_ARCSEC).abs() < 1e-10);
        let u = (2e-14 + (0.25 * RAD_PER_ARCSEC).powi(2)).sqrt();
        assert!((m.expanded_rad - 2.0 * u).abs() < 1e-12);
    }

    /// X then Z, square about −Y: X's line is its beam plus s₁z along +Z (X's head z); the
    /// turned beam leans towards +X by s₁z − δ, and Z's line by s₂x more (Z's head x is +X):
    /// B0Z = X·Z = s₁z + s₂x − δ. Y then Z, square about +X: Y's line leans to +Z by s₁z; the
    /// turned beam leans to −Y by δ and Z's line by s₂z more (Z's head z is −Y):
    /// A0Z = −Y·Z = s₂z + δ − s₁z.
    #[test]
    fn the_squarenesses_with_z_by_hand() {
        let (a, b, d) = (2e-5, -6e-5, -3.0);
        let dr = d * RAD_PER_ARCSEC;
        let zx = measure(
            SquarePair::ZX,
            &slopes(MachineAxis::X, [9e-5, a]),
            &slopes(MachineAxis::Z, [b, 4e-5]),
            &square(d),
            Some(0.1 * RAD_PER_ARCSEC),
        )
        .expect("ZX");
        assert!(
            (zx.value_rad - (a + b - dr)).abs() < 1e-8,
            "{}",
            zx.value_rad
        );
        assert!((zx.terms[3].u_rad - 0.1 * RAD_PER_ARCSEC).abs() < 1e-15);
        let yz = measure(
            SquarePair::YZ,
            &slopes(MachineAxis::Y, [9e-5, a]),
            &slopes(MachineAxis::Z, [4e-5, b]),
            &square(d),
            None,
        )
        .expect("YZ");
        assert!(
            (yz.value_rad - (b + dr - a)).abs() < 1e-8,
            "{}",
            yz.value_rad
        );
    }

    #[test]
    fn a_set_up_of_another_axis_or_a_bad_certificate_is_refused() {
        let e = measure(
            SquarePair::XY,
            &slopes(MachineAxis::X, [0.0; 2]),
            &slopes(MachineAxis::Z, [0.0; 2]),
            &square(0.0),
            None,
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("the second set-up measured Z, it must be Y"),
            "{e}"
        );
        let mut bad = square(0.0);
        bad.u_rad = f64::NAN;
        let e = measure(
            SquarePair::XY,
            &slopes(MachineAxis::X, [0.0; 2]),
            &slopes(MachineAxis::Y, [0.0; 2]),
            &bad,
            None,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("optical square OS-1"), "{e}");
    }
}
