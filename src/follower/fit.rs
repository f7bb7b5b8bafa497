//! The self-calibration's two weighted least-squares fits (pure functions).
//!
//! Along the axis, per step: `along − Δencoder = Σ c_k ΔP_k + s·Δsin + c·Δcos + r·ρ`, with
//! `P_k` Legendre polynomials over the visited span (degree 1..K: PSD2's gain and the long
//! shape, discarded), the screw-periodic basis at the lead, and `ρ` = +1 on the first step
//! down after moving up, −1 on the first step up after moving down (the reversal `r`), else 0.
//!
//! Vertically: unknown `v` at the visited positions (clustered within `merge_mm`), linear in
//! between, zero at both ends, and a slope `c`; each step observes `v(to) − v(from) + c·Δ`.
//! The slope takes what a step shows in proportion to its length: PSD2's in-plane tilt and the
//! follower's inclination to PSD2's u axis, which no handover can tell apart (the spot is
//! fixed in space and only the follower moves). So the map is the follower's straightness
//! relative to its end-point line; the line itself is not mapped.
//!
//! With a level's readings at stations along the travel (`LevelStation`: the true vertical at
//! a station up to one common constant, from the head's roll beside a level's), the vertical
//! fit is anchored by them instead: `v` is zero at the first position only, each station
//! observes `v(x) + k` (one unknown constant `k`), and the steps as before. The stations fix
//! the line and pin the steps' random walk between them, so the map is the follower's whole
//! vertical relative to its first position, with its uncertainty from both.
//!
//! Both solve the normal equations by Cholesky; a singular system (a gap in the steps, too
//! few of them) is an error naming what is missing. Standard uncertainties come from the
//! stated step variances, scaled by √χ²_red when the residuals say they were optimistic.

use super::{Direction, Estimate, LevelStation, MapError, MapSettings, Periodic, Step};
use nalgebra::{DMatrix, DVector};

pub(super) struct AlongFit {
    pub periodic: Periodic,
    pub reversal: Option<Estimate>,
    pub reversals: usize,
    pub chi2: f64,
}

pub(super) struct VerticalFit {
    pub positions: Vec<f64>,
    pub values: Vec<f64>,
    pub u: Vec<f64>,
    pub slope: f64,
    pub chi2: f64,
}

/// Legendre polynomials P_1..P_k at t (k ≥ 1).
pub(super) fn legendre(t: f64, k: usize) -> Vec<f64> {
    let mut out = Vec::with_capacity(k);
    let (mut p0, mut p1) = (1.0, t);
    out.push(p1);
    for n in 1..k {
        let n = n as f64;
        let p2 = ((2.0 * n + 1.0) * t * p1 - n * p0) / (n + 1.0);
        out.push(p2);
        p0 = p1;
        p1 = p2;
    }
    out
}

/// Solve a weighted least-squares problem by its normal equations: the solution, its
/// covariance (scaled by χ²_red when above 1) and χ²_red (1 when there are no degrees of
/// freedom left).
fn solve(
    rows: &[(Vec<f64>, f64, f64)],
    what: &'static str,
    hint: &str,
) -> Result<(DVector<f64>, DMatrix<f64>, f64), MapError> {
    let p = rows.first().map_or(0, |r| r.0.len());
    let mut n = DMatrix::<f64>::zeros(p, p);
    let mut b = DVector::<f64>::zeros(p);
    for (a, y, w) in rows {
        for i in 0..p {
            if a[i] == 0.0 {
                continue;
            }
            b[i] += w * a[i] * y;
            for j in 0..p {
                n[(i, j)] += w * a[i] * a[j];
            }
        }
    }
    let singular = || MapError::Singular {
        what,
        hint: hint.to_string(),
    };
    let chol = n.cholesky().ok_or_else(singular)?;
    let x = chol.solve(&b);
    let cov = chol.inverse();
    if !x.iter().all(|v| v.is_finite()) {
        return Err(singular());
    }
    let dof = rows.len().saturating_sub(p);
    let chi2 = if dof == 0 {
        1.0
    } else {
        rows.iter()
            .map(|(a, y, w)| {
                let r = y - a.iter().zip(x.iter()).map(|(ai, xi)| ai * xi).sum::<f64>();
                w * r * r
            })
            .sum::<f64>()
            / dof as f64
    };
    Ok((x, cov * chi2.max(1.0), chi2))
}

fn weight(var: f64) -> f64 {
    // A step whose stated variance is zero (a noiseless twin) gets a 0.01 µm floor.
    1.0 / var.max(1e-10)
}

pub(super) fn along(steps: &[Step], s: &MapSettings) -> Result<AlongFit, MapError> {
    let (lo, hi) = span(steps);
    let k = s.long_degree.max(1);
    let t = |x: f64| 2.0 * (x - lo) / (hi - lo).max(1e-9) - 1.0;
    let lead = s.lead_mm;
    let per = |x: f64| {
        let a = 2.0 * std::f64::consts::PI * x / lead;
        [a.sin(), a.cos()]
    };
    let mut rows = Vec::new();
    let mut reversals = 0;
    for i in 1..steps.len() {
        let (prev, st) = (&steps[i - 1], &steps[i]);
        let gap = st.from_mm - prev.to_mm;
        let before = if gap.abs() > 0.005 {
            if gap > 0.0 {
                Direction::Up
            } else {
                Direction::Down
            }
        } else {
            prev.direction()
        };
        let rho = match (before, st.direction()) {
            (Direction::Up, Direction::Down) => 1.0,
            (Direction::Down, Direction::Up) => -1.0,
            _ => 0.0,
        };
        if rho != 0.0 {
            reversals += 1;
        }
        let (la, lb) = (legendre(t(st.to_mm), k), legendre(t(st.from_mm), k));
        let (pa, pb) = (per(st.to_mm), per(st.from_mm));
        let mut a: Vec<f64> = la.iter().zip(&lb).map(|(x, y)| x - y).collect();
        a.push(pa[0] - pb[0]);
        a.push(pa[1] - pb[1]);
        a.push(rho);
        rows.push((
            a,
            st.along_mm - (st.to_mm - st.from_mm),
            weight(st.variance[0]),
        ));
    }
    let has_reversal = reversals > 0;
    if !has_reversal {
        for r in &mut rows {
            r.0.pop();
        }
    }
    let p = k + 2 + usize::from(has_reversal);
    if rows.len() < p + 5 {
        return Err(MapError::TooFewSteps {
            found: steps.len(),
            needed: p + 6,
        });
    }
    let (x, cov, chi2) = solve(
        &rows,
        "along-axis",
        "the steps must not all be a whole number of screw leads long",
    )?;
    let periodic = Periodic {
        lead_mm: lead,
        sin_mm: x[k],
        cos_mm: x[k + 1],
        cov_mm2: [
            [cov[(k, k)], cov[(k, k + 1)]],
            [cov[(k + 1, k)], cov[(k + 1, k + 1)]],
        ],
    };
    let reversal = has_reversal.then(|| Estimate {
        value_mm: x[k + 2],
        u_mm: cov[(k + 2, k + 2)].max(0.0).sqrt(),
    });
    Ok(AlongFit {
        periodic,
        reversal,
        reversals,
        chi2,
    })
}

fn span(steps: &[Step]) -> (f64, f64) {
    steps
        .iter()
        .flat_map(|s| [s.from_mm, s.to_mm])
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| {
            (lo.min(x), hi.max(x))
        })
}

/// The visited positions, clustered within `merge` (mm): each cluster's mean.
fn nodes(steps: &[Step], merge: f64) -> Vec<f64> {
    let mut xs: Vec<f64> = steps.iter().flat_map(|s| [s.from_mm, s.to_mm]).collect();
    xs.sort_by(f64::total_cmp);
    let mut out: Vec<f64> = Vec::new();
    let mut group: Vec<f64> = Vec::new();
    for x in xs {
        if group.first().is_some_and(|g| x - g > merge) {
            out.push(group.iter().sum::<f64>() / group.len() as f64);
            group.clear();
        }
        group.push(x);
    }
    if !group.is_empty() {
        out.push(group.iter().sum::<f64>() / group.len() as f64);
    }
    out
}

/// Linear-interpolation weights of `x` on `nodes` (not empty): (index, weight) pairs, the
/// end node's value held outside (as `util::interpolate`).
pub(super) fn weights(nodes: &[f64], x: f64) -> [(usize, f64); 2] {
    let n = nodes.len();
    if n == 1 || x <= nodes[0] {
        return [(0, 1.0), (0, 0.0)];
    }
    if x >= nodes[n - 1] {
        return [(n - 1, 1.0), (n - 1, 0.0)];
    }
    let k = nodes.partition_point(|&p| p <= x).clamp(1, n - 1);
    let t = (x - nodes[k - 1]) / (nodes[k] - nodes[k - 1]);
    [(k - 1, 1.0 - t), (k, t)]
}

pub(super) fn vertical(
    steps: &[Step],
    stations: &[LevelStation],
    s: &MapSettings,
) -> Result<VerticalFit, MapError> {
    let nodes = nodes(steps, s.merge_mm.max(1e-6));
    if nodes.len() < 4 {
        return Err(MapError::TooFewSteps {
            found: steps.len(),
            needed: 3,
        });
    }
    // Unknowns: v at the nodes but the first (zero) and, without stations, the last (zero:
    // the end-point line); the slope c (PSD2's jump per mm of follower step that is not
    // straightness); with stations, their common constant k.
    let last = nodes.len() - 1;
    let referenced = stations.len() >= 2;
    let free = if referenced { last } else { last - 1 };
    let p = free + 1 + usize::from(referenced);
    let slope = free;
    let column = |i: usize| (i > 0 && (referenced || i < last)).then(|| i - 1);
    let mut rows: Vec<(Vec<f64>, f64, f64)> = steps
        .iter()
        .map(|st| {
            let mut a = vec![0.0; p];
            for (sign, x) in [(1.0, st.to_mm), (-1.0, st.from_mm)] {
                for (i, w) in weights(&nodes, x) {
                    if let Some(c) = column(i) {
                        a[c] += sign * w;
                    }
                }
            }
            a[slope] = st.to_mm - st.from_mm;
            (a, st.vertical_mm, weight(st.variance[1]))
        })
        .collect();
    let hint = "every visited position must be linked to both ends by steps (passes over the whole travel)";
    let n_steps = rows.len();
    let node_list = &nodes;
    let station_rows = |scale: f64| {
        stations.iter().map(move |st| {
            let mut a = vec![0.0; p];
            for (i, w) in weights(node_list, st.position_mm) {
                if let Some(c) = column(i) {
                    a[c] += w;
                }
            }
            a[p - 1] = 1.0;
            (a, st.value_mm, weight(st.variance_mm2 * scale))
        })
    };
    if referenced {
        rows.extend(station_rows(1.0));
    }
    let (mut x, mut cov, mut chi2) = solve(&rows, "vertical", hint)?;
    if referenced {
        // The stations' own consistency with the steps (their residuals against their stated
        // variances; one degree of freedom goes to k): stations that scatter more than stated
        // (the head's reading beside the level has errors of its own) are weighted by what they
        // show, and the fit taken again.
        let resid: f64 = rows[n_steps..]
            .iter()
            .map(|(a, y, w)| {
                let r = y - a.iter().zip(x.iter()).map(|(ai, xi)| ai * xi).sum::<f64>();
                w * r * r
            })
            .sum();
        let birge = resid / (stations.len() - 1) as f64;
        if birge > 1.0 {
            rows.truncate(n_steps);
            rows.extend(station_rows(birge));
            (x, cov, chi2) = solve(&rows, "vertical", hint)?;
        }
    }
    let mut values = vec![0.0];
    let mut u = vec![0.0];
    for i in 0..free {
        values.push(x[i]);
        u.push(cov[(i, i)].max(0.0).sqrt());
    }
    if !referenced {
        values.push(0.0);
        u.push(0.0);
    }
    Ok(VerticalFit {
        positions: nodes,
        values,
        u,
        slope: x[slope],
        chi2,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn legendre_matches_the_closed_forms() {
        let t: f64 = 0.3;
        let p = legendre(t, 3);
        assert!((p[0] - t).abs() < 1e-15);
        assert!((p[1] - (3.0 * t * t - 1.0) / 2.0).abs() < 1e-15);
        assert!((p[2] - (5.0 * t.powi(3) - 3.0 * t) / 2.0).abs() < 1e-15);
    }

    #[test]
    fn nodes_cluster_nearby_positions() {
        let st = |a: f64, b: f64| Step {
            from_mm: a,
            to_mm: b,
            along_mm: b - a,
            vertical_mm: 0.0,
            variance: [1e-8; 2],
        };
        let n = nodes(
            &[st(0.0, 3.0), st(3.0, 6.0), st(6.0, 3.2), st(3.2, 0.1)],
            0.5,
        );
        assert_eq!(n.len(), 3);
        assert!((n[0] - 0.05).abs() < 1e-12 && (n[1] - 3.1).abs() < 1e-12 && n[2] == 6.0);
    }
}
