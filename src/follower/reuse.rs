//! The instrument's map on a new set-up (issue 26): what belongs to the follower stage stays
//! with it, what the set-up adds is measured again in minutes.
//!
//! The stage's own errors — its long-wavelength positioning (the encoder's certificate), the
//! screw-periodic term, the reversal and the rail's vertical shape — travel with the
//! instrument: mapped once (the stop-and-go self-calibration with a level, an hour and more),
//! stored, and reused. Bolted to another machine's bed, the rail bends with the bed: its
//! vertical changes by a smooth shape over the travel (a tilt, a sag, an S), which a level's
//! stations read in a few minutes. The check here takes those stations (`follower::level`,
//! read with the stored map in tracking: each is the rail's true vertical there up to a
//! constant) and fits the difference from the stored vertical with a polynomial of a low
//! degree (Legendre, over the map's span). The map is reused when every station lies on that
//! smooth bend within its uncertainty (all at once, at 99.9 %: `util::simultaneous_k`); the
//! bend is added to the stored vertical and its uncertainty to the vertical's. A station off
//! the bend means the rail itself changed there (a kink, a knock, a foot on a chip): the map
//! is refused with the span between the neighbouring stations, to be mapped again.
//!
//! The along-axis terms are not re-read here: the set-up's bend moves PSD2 along the axis by
//! its slope times PSD2's height over the rail (nanometres for a micrometre's bend).
//!
//! Sans-I/O: the stations in, the map (or the reason) out.

use super::{FollowerMap, VerticalReference};
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// How the check decides.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReuseSettings {
    /// Degree of the set-up's bend (3: a tilt, a sag and an S).
    pub degree: usize,
    /// Every station on the bend at once at this probability.
    pub confidence: f64,
}

impl ReuseSettings {
    /// The stations a check needs: the bend's coefficients and the constant, and two to spare
    /// to judge the fit by.
    pub fn stations_needed(&self) -> usize {
        self.degree + 3
    }
}

impl Default for ReuseSettings {
    fn default() -> Self {
        ReuseSettings {
            degree: 3,
            confidence: 0.999,
        }
    }
}

/// What the check of a stored map on this set-up found (kept with the map in use).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Reuse {
    /// The level's stations read on this set-up, and the bend's degree.
    pub stations: usize,
    pub degree: usize,
    /// The set-up's bend against the stored map: its range over the map's span (mm) and the
    /// largest standard uncertainty it adds to the vertical (mm).
    pub bend_range_mm: f64,
    pub bend_u_max_mm: f64,
    /// The bend's standard uncertainty (mm) at each of the map's vertical positions: its own
    /// term in the budget (empty in a map kept before it was stored; then the budget finds it
    /// only inside the vertical's).
    #[serde(default)]
    pub bend_u_mm: Vec<f64>,
    /// The station furthest off the bend (standard uncertainties) and the limit.
    pub worst_z: f64,
    pub limit_z: f64,
}

impl Reuse {
    /// In words: "the instrument's stored map, re-used on this set-up: a bend of 6.30 µm
    /// range (u ≤ 0.112 µm, degree 3) from 12 level stations, each within 1.9 u of it (limit
    /// 4.0)".
    pub fn describe(&self) -> String {
        format!(
            "the instrument's stored map, re-used on this set-up: a bend of {:.2} µm range (u ≤ {:.3} µm, degree {}) from {} level stations, each within {:.1} u of it (limit {:.1})",
            self.bend_range_mm * 1e3,
            self.bend_u_max_mm * 1e3,
            self.degree,
            self.stations,
            self.worst_z,
            self.limit_z
        )
    }
}

/// Why a stored map cannot be used on this set-up.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum ReuseError {
    #[error(
        "{found} level stations: checking a stored map on a new set-up needs {needed} at least (a bend of degree {degree}, and stations to spare to judge it by); read more stations"
    )]
    TooFewStations {
        found: usize,
        needed: usize,
        degree: usize,
    },
    #[error(
        "the stored map has no vertical map to re-reference: map the follower on this set-up (`axiscomp follower map`)"
    )]
    NoVertical,
    #[error(
        "the stored map covers the follower's encoder from {map_from:.1} to {map_to:.1} mm, and this set-up uses {from:.1} to {to:.1} mm: map the follower over the whole span"
    )]
    Span {
        map_from: f64,
        map_to: f64,
        from: f64,
        to: f64,
    },
    #[error(
        "the level's station at {at_mm:.0} mm is {off_um:+.2} µm off the stored map beyond a smooth bend of this set-up ({z:.1} standard uncertainties; the limit is {limit:.1}): the rail changed since it was mapped, most likely between {from_mm:.0} and {to_mm:.0} mm; map the follower again over that span or its whole travel (`axiscomp follower map`)"
    )]
    Changed {
        at_mm: f64,
        off_um: f64,
        z: f64,
        limit: f64,
        from_mm: f64,
        to_mm: f64,
    },
    #[error("the bend's fit is singular: the level's stations do not spread over the travel")]
    Singular,
}

/// How far a set-up may use the rail beyond the stored map's ends (mm): the follower's
/// encoder stands a few millimetres off the carriage's position, differently on each set-up;
/// there the map's end values hold (the rail's shape over a few mm is nanometres).
pub const END_SLACK_MM: f64 = 5.0;

/// Legendre polynomials P0..=Pdegree at `t` (−1..1): the constant, then `fit`'s P1..Pdegree.
fn legendre(t: f64, degree: usize) -> Vec<f64> {
    let mut p = vec![1.0];
    if degree > 0 {
        p.extend(super::fit::legendre(t, degree));
    }
    p
}

/// A weighted least-squares fit of (position, value, variance) data by a basis, with a
/// change of the rail (`Change`) when asked for.
struct Fit {
    coef: DVector<f64>,
    cov: DMatrix<f64>,
    /// Residuals over their standard deviations, and the fit's leverage at each point.
    resid: DVector<f64>,
    leverage: Vec<f64>,
}

/// A change of the rail at one place, added to the bend to find where it changed: a kink
/// (its vertical turns there) or a step (it shifts there: a foot moved, a chip under it).
#[derive(Clone, Copy, Debug)]
enum Change {
    Kink(f64),
    Step(f64),
}

impl Fit {
    fn new(
        data: &[(f64, f64, f64)],
        basis: impl Fn(f64) -> Vec<f64>,
        change: Option<Change>,
    ) -> Result<Fit, ReuseError> {
        let row = |x: f64| {
            let mut b = basis(x);
            match change {
                Some(Change::Kink(c)) => b.push((x - c).max(0.0)),
                Some(Change::Step(c)) => b.push(if x > c { 1.0 } else { 0.0 }),
                None => {}
            }
            b
        };
        let m = row(data[0].0).len();
        let n = data.len();
        let mut a = DMatrix::<f64>::zeros(n, m);
        let mut y = DVector::<f64>::zeros(n);
        for (i, &(x, v, var)) in data.iter().enumerate() {
            let w = 1.0 / var.max(1e-18).sqrt();
            for (j, p) in row(x).into_iter().enumerate() {
                a[(i, j)] = p * w;
            }
            y[i] = v * w;
        }
        let cov = (a.transpose() * &a)
            .try_inverse()
            .ok_or(ReuseError::Singular)?;
        let coef = &cov * a.transpose() * &y;
        let resid = &y - &a * &coef;
        let hat = &a * &cov * a.transpose();
        let leverage = (0..n).map(|i| hat[(i, i)]).collect();
        Ok(Fit {
            coef,
            cov,
            resid,
            leverage,
        })
    }

    fn chi2(&self) -> f64 {
        self.resid.norm_squared()
    }

    /// The point furthest off the fit, as a residual's standard deviations (the leverage
    /// out), and which it is.
    fn worst(&self) -> (usize, f64) {
        let mut worst = (0usize, 0.0f64);
        for (i, h) in self.leverage.iter().enumerate() {
            let z = self.resid[i] / (1.0 - h).max(1e-9).sqrt();
            if z.abs() > worst.1.abs() {
                worst = (i, z);
            }
        }
        worst
    }
}

/// Check `stored` against the level's stations read on this set-up (`reference`, with the
/// stored map in tracking) and return the map re-referenced by the set-up's bend, with what
/// the check found; or why it cannot be used.
pub fn reuse(
    stored: &FollowerMap,
    reference: &VerticalReference,
    settings: &ReuseSettings,
) -> Result<(FollowerMap, Reuse), ReuseError> {
    let vp = &stored.vertical_positions_mm;
    if vp.len() < 2 {
        return Err(ReuseError::NoVertical);
    }
    let degree = settings.degree;
    let st = &reference.stations;
    let needed = settings.stations_needed();
    if st.len() < needed {
        return Err(ReuseError::TooFewStations {
            found: st.len(),
            needed,
            degree,
        });
    }
    let (lo, hi) = (vp[0].min(vp[vp.len() - 1]), vp[0].max(vp[vp.len() - 1]));
    let (from, to) = st
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), s| {
            (a.min(s.position_mm), b.max(s.position_mm))
        });
    if from < lo - END_SLACK_MM || to > hi + END_SLACK_MM {
        return Err(ReuseError::Span {
            map_from: lo,
            map_to: hi,
            from,
            to,
        });
    }
    let t_of = |x: f64| 2.0 * (x - lo) / (hi - lo) - 1.0;
    let vertical = |x: f64| stored.correction(x, super::Direction::Up)[1];
    // The stored vertical's variance at `x`: its stated u (relative to its first point), and
    // at least the variance of its own nearest station (the first point's is no less
    // uncertain than the others, only the reference of the rest).
    let own_stations = stored.vertical_reference.as_ref().map(|r| &r.stations[..]);
    let stored_var = |x: f64| {
        let u = stored.point(x, super::Direction::Up).vertical_u_um * 1e-3;
        let nearest = own_stations
            .and_then(|s| {
                s.iter().min_by(|a, b| {
                    (a.position_mm - x)
                        .abs()
                        .total_cmp(&(b.position_mm - x).abs())
                })
            })
            .map_or(0.0, |s| s.variance_mm2);
        (u * u).max(nearest)
    };
    // Each station's value less the stored vertical there, and its variance (the station's
    // and the stored map's there).
    let n = st.len();
    let data: Vec<(f64, f64, f64)> = st
        .iter()
        .map(|s| {
            let x = s.position_mm;
            (x, s.value_mm - vertical(x), s.variance_mm2 + stored_var(x))
        })
        .collect();
    let fit = Fit::new(&data, |x| legendre(t_of(x), degree), None)?;
    let limit = crate::util::simultaneous_k(n, settings.confidence);
    let (wi, wz) = fit.worst();

    if wz.abs() > limit {
        // Where the rail changed: the kink or the step between two neighbouring stations
        // that, added to the bend, explains the stations best.
        let changed = |c: Change| Fit::new(&data, |x| legendre(t_of(x), degree), Some(c)).ok();
        let at = (0..n - 1)
            .map(|i| (data[i].0 + data[i + 1].0) / 2.0)
            .flat_map(|c| [(c, Change::Kink(c)), (c, Change::Step(c))])
            .filter_map(|(c, change)| changed(change).map(|f| (c, f.chi2())))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map_or(data[wi].0, |(c, _)| c);
        let below = data.iter().rev().find(|d| d.0 < at).map_or(lo, |d| d.0);
        let above = data.iter().find(|d| d.0 > at).map_or(hi, |d| d.0);
        return Err(ReuseError::Changed {
            at_mm: data[wi].0,
            off_um: fit.resid[wi] * data[wi].2.sqrt() * 1e3,
            z: wz.abs(),
            limit,
            from_mm: below,
            to_mm: above,
        });
    }
    let (coef, cov, m) = (&fit.coef, &fit.cov, degree + 1);
    // The bend relative to the map's first point (only differences are applied), and its
    // variance from the fit's covariance (the constant left out: it is no bend).
    let bend_basis = |x: f64| {
        let p = legendre(t_of(x), degree);
        let p0 = legendre(t_of(vp[0]), degree);
        DVector::from_iterator(m, (0..m).map(|j| if j == 0 { 0.0 } else { p[j] - p0[j] }))
    };
    let mut map = stored.clone();
    if map.vertical_reference.is_none()
        && let Some(l) = map.vertical_line.take()
    {
        // The line becomes part of the whole vertical, as a level's stations make it.
        for (k, x) in vp.iter().enumerate() {
            map.vertical_mm[k] += l.slope * (x - l.origin_mm);
            map.vertical_u_mm[k] = map.vertical_u_mm[k].hypot(l.u_slope * (x - l.origin_mm));
        }
    }
    let (mut bmin, mut bmax, mut umax) = (f64::INFINITY, f64::NEG_INFINITY, 0.0f64);
    let mut bend_u_mm = Vec::with_capacity(vp.len());
    for (k, &x) in vp.iter().enumerate() {
        let b = bend_basis(x);
        let bend = b.dot(coef);
        let u = (b.transpose() * cov * &b)[(0, 0)].max(0.0).sqrt();
        map.vertical_mm[k] += bend;
        map.vertical_u_mm[k] = map.vertical_u_mm[k].hypot(u);
        bmin = bmin.min(bend);
        bmax = bmax.max(bend);
        umax = umax.max(u);
        bend_u_mm.push(u);
    }
    let check = Reuse {
        stations: n,
        degree,
        bend_range_mm: bmax - bmin,
        bend_u_max_mm: umax,
        bend_u_mm,
        worst_z: wz.abs(),
        limit_z: limit,
    };
    map.vertical_reference = Some(VerticalReference {
        stations: st.clone(),
        source: format!("{}, on this set-up", reference.source),
    });
    map.reuse = Some(check.clone());
    Ok((map, check))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::follower::{LevelStation, MapSettings, build_referenced};

    /// A stored map whose vertical is `shape` at 3.75 mm spacing over 0..1001 mm, built from
    /// steps up that read it exactly and a level's stations every 100 mm (as the instrument
    /// is mapped).
    fn stored(shape: impl Fn(f64) -> f64) -> FollowerMap {
        let steps: Vec<crate::follower::Step> = (0..267)
            .map(|k| {
                let (a, b) = (3.75 * k as f64, 3.75 * (k + 1) as f64);
                crate::follower::Step {
                    from_mm: a,
                    to_mm: b,
                    along_mm: b - a,
                    vertical_mm: shape(b) - shape(a),
                    variance: [1e-10, 1e-11],
                }
            })
            .collect();
        let level = VerticalReference {
            stations: crate::follower::level::stations((0.0, 1001.25), 100.0)
                .into_iter()
                .map(|x| LevelStation {
                    position_mm: x,
                    value_mm: shape(x),
                    variance_mm2: 0.03e-3f64.powi(2),
                })
                .collect(),
            source: "a level".into(),
        };
        build_referenced(&steps, None, &MapSettings::default(), Some(&level)).unwrap()
    }

    /// A level's stations every 100 mm reading `f` (up to a constant) with `sd_mm` of noise.
    fn stations(f: impl Fn(f64) -> f64, sd_mm: f64, seed: u64) -> VerticalReference {
        let mut rng = crate::sim::Rng::new(seed);
        VerticalReference {
            stations: crate::follower::level::stations((0.0, 1000.0), 100.0)
                .into_iter()
                .map(|x| LevelStation {
                    position_mm: x,
                    value_mm: f(x) + 0.7e-3 + rng.gauss(sd_mm),
                    variance_mm2: sd_mm * sd_mm,
                })
                .collect(),
            source: "a level".into(),
        }
    }

    #[test]
    fn a_smooth_bend_is_taken_in_and_a_kink_is_refused_where_it_is() {
        let own = |x: f64| 1e-3 * (x / 137.0).sin() + 0.4e-3 * (x / 41.0).cos();
        let map = stored(own);
        for seed in [1, 2, 3] {
            // A sag and an S of a few µm: the map re-referenced reads the new shape.
            let t = |x: f64| x / 500.0 - 1.0;
            let bent = |x: f64| own(x) + 1.5e-3 * t(x) * t(x) - 0.8e-3 * t(x).powi(3);
            let (m, check) = reuse(
                &map,
                &stations(bent, 0.03e-3, seed),
                &ReuseSettings::default(),
            )
            .unwrap();
            assert!(check.worst_z < check.limit_z);
            assert!(check.bend_range_mm > 1e-3, "{}", check.describe());
            for x in [100.0, 333.0, 650.0, 990.0] {
                let got = m.correction(x, super::super::Direction::Up)[1]
                    - m.correction(0.0, super::super::Direction::Up)[1];
                let want = bent(x) - bent(0.0);
                let u = m.point(x, super::super::Direction::Up).vertical_u_um * 1e-3;
                assert!(
                    (got - want).abs() < 4.0 * u && u < 0.1e-3,
                    "seed {seed} at {x}: {got} for {want} (u {u})"
                );
            }
            assert_eq!(m.reuse.as_ref(), Some(&check));
            // The bend's u, kept per position, is what the re-use added to the vertical's,
            // and the budget takes it out into its own term (relative to the zero at 0 mm).
            let up = super::super::Direction::Up;
            let v = |m: &FollowerMap, x: f64| m.point(x, up).vertical_u_um * 1e-3;
            let input = crate::evaluate::uncertainty::FollowerInput::of_map(
                &m,
                0.0,
                0.0,
                2.5,
                "test".into(),
            );
            // (The bend is relative to the map's first point: nothing there.)
            assert_eq!(m.bend_u_mm(m.vertical_positions_mm[0]), 0.0);
            for &x in m.vertical_positions_mm.iter().skip(1).step_by(25) {
                let b = m.bend_u_mm(x);
                assert!(b > 0.0 && b <= check.bend_u_max_mm, "at {x}: {b}");
                let added = (v(&m, x).powi(2) - v(&map, x).powi(2)).sqrt();
                assert!((b - added).abs() < 1e-9, "at {x}: {b} for {added}");
            }
            for x in (1..40).map(|k| 25.0 * k as f64) {
                let b = m.bend_u_mm(x);
                let at = input.at(x);
                let whole = v(&m, x).hypot(v(&m, 0.0));
                assert!((at.bend_mm - b.hypot(m.bend_u_mm(0.0))).abs() < 1e-12);
                assert!((at.vertical_mm.hypot(at.bend_mm) - whole).abs() < 1e-9 * whole.max(1e-6));
            }
            // The rail kinked by 10 µrad (2″) at 430 mm: refused, the span around it named.
            // (5 µrad is about what 11 stations with 0.03 µm of noise tell from a bend.)
            let kinked = |x: f64| bent(x) + 10e-6 * (x - 430.0).max(0.0);
            let e = match reuse(
                &map,
                &stations(kinked, 0.03e-3, seed),
                &ReuseSettings::default(),
            ) {
                Ok((_, c)) => panic!("seed {seed}: the kink passed: {}", c.describe()),
                Err(e) => e,
            };
            let ReuseError::Changed { from_mm, to_mm, .. } = e.clone() else {
                panic!("{e}");
            };
            assert!(from_mm <= 430.0 && to_mm >= 430.0, "{e}");
            assert!(e.to_string().contains("map the follower again"), "{e}");
        }
    }

    #[test]
    fn too_few_stations_or_a_span_beyond_the_map_are_refused_with_the_reason() {
        let map = stored(|_| 0.0);
        let mut few = stations(|_| 0.0, 0.03e-3, 1);
        few.stations.truncate(5);
        assert!(matches!(
            reuse(&map, &few, &ReuseSettings::default()),
            Err(ReuseError::TooFewStations {
                found: 5,
                needed: 6,
                ..
            })
        ));
        let mut far = stations(|_| 0.0, 0.03e-3, 1);
        far.stations[10].position_mm = 1200.0;
        let e = reuse(&map, &far, &ReuseSettings::default()).unwrap_err();
        assert!(e.to_string().contains("1200.0 mm"), "{e}");
    }
}
