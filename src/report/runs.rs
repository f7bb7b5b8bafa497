//! A run's report from its captures and their ISO evaluation: per error and direction the
//! mean over the runs at each target with its standard deviation and the captures' standard
//! uncertainty, and the ISO 230-2 / 230-1 figures in user units.

use super::{
    BudgetPoint, BudgetTable, BudgetTerm, DofResult, EnvSample, Figure, RunMeta, RunReport, Series,
};
use crate::evaluate::AxisEvaluation;
use crate::evaluate::iso230_1::ReferenceLine;
use crate::evaluate::uncertainty::{Budget, Component};
use crate::run::{Capture, Direction};
use std::collections::BTreeMap;

/// Per-target series of one DOF in one direction, from the captures.
pub fn series(captures: &[Capture], dof: usize, direction: Direction) -> Option<Series> {
    let mut by_target: BTreeMap<u32, (f64, Vec<f64>, Vec<f64>)> = BTreeMap::new();
    for c in captures.iter().filter(|c| c.direction == direction) {
        let e = by_target
            .entry(c.target_index)
            .or_insert((c.target_mm, Vec::new(), Vec::new()));
        e.1.push(c.errors.to_array()[dof]);
        e.2.push(c.u.to_array()[dof]);
    }
    if by_target.is_empty() {
        return None;
    }
    let mut out = Series {
        direction,
        positions_mm: Vec::new(),
        mean: Vec::new(),
        s: Vec::new(),
        n: Vec::new(),
        u: Some(Vec::new()),
    };
    for (_, (pos, xs, us)) in by_target {
        let n = xs.len() as f64;
        let mean = xs.iter().sum::<f64>() / n;
        let s = if xs.len() > 1 {
            (xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt()
        } else {
            0.0
        };
        out.positions_mm.push(pos);
        out.mean.push(mean);
        out.s.push(s);
        out.n.push(xs.len() as u32);
        if let Some(u) = out.u.as_mut() {
            u.push(us.iter().sum::<f64>() / n);
        }
    }
    Some(out)
}

fn fig(name: &str, value_mm_or_rad: Option<f64>, dof: super::Dof) -> Option<Figure> {
    value_mm_or_rad.map(|v| Figure {
        name: name.to_string(),
        value: dof.to_user(v),
        unit: dof.unit().to_string(),
    })
}

/// The report of a run.
pub fn run_report(meta: RunMeta, captures: &[Capture], eval: &AxisEvaluation) -> RunReport {
    use super::Dof;
    let mut dofs = Vec::new();
    for dof in [Dof::Dx, Dof::Dy, Dof::Dz, Dof::Ex, Dof::Ey, Dof::Ez] {
        let k = dof.index();
        let series: Vec<Series> = [Direction::Up, Direction::Down]
            .into_iter()
            .filter_map(|d| series(captures, k, d))
            .collect();
        let mut figures = Vec::new();
        match dof {
            Dof::Dy => {
                let a = &eval.positioning.axis;
                for (n, v) in [
                    ("A (accuracy)", a.a),
                    ("E (systematic)", a.e),
                    ("M (mean)", a.m),
                    ("R (repeatability)", a.r),
                    ("B (reversal)", a.b),
                    ("B̄ (mean reversal)", a.b_mean),
                ] {
                    figures.extend(fig(n, v, dof));
                }
            }
            Dof::Dx | Dof::Dz => {
                let st = if dof == Dof::Dx {
                    &eval.straightness_x
                } else {
                    &eval.straightness_z
                };
                let ls = st.mean.line(ReferenceLine::LeastSquares);
                let ep = st.mean.line(ReferenceLine::EndPoint);
                figures.extend(fig(
                    "straightness (least squares)",
                    Some(ls.straightness),
                    dof,
                ));
                figures.extend(fig("straightness (end points)", Some(ep.straightness), dof));
                figures.push(Figure {
                    name: "slope (beam alignment)".into(),
                    value: ls.slope_um_per_m(),
                    unit: "µm/m".into(),
                });
            }
            Dof::Ex | Dof::Ey | Dof::Ez => {
                let a = match dof {
                    Dof::Ex => &eval.pitch,
                    Dof::Ey => &eval.roll,
                    _ => &eval.yaw,
                };
                figures.extend(fig("max − min (mean)", Some(a.mean), dof));
                figures.extend(fig("max − min (+)", a.up, dof));
                figures.extend(fig("max − min (−)", a.down, dof));
            }
        }
        dofs.push(DofResult {
            dof,
            series,
            figures,
            budget: None,
        });
    }
    RunReport {
        meta,
        dofs,
        comparisons: Vec::new(),
        environment: captures.iter().map(EnvSample::of_capture).collect(),
    }
}

/// Put each DOF's uncertainty budget into `report` (user units).
pub fn add_budget(report: &mut RunReport, budget: &Budget) {
    let sources = budget.sources();
    for d in &mut report.dofs {
        let k = d.dof.index();
        let (largest, uc, big) = budget.largest(k);
        d.budget = Some(BudgetTable {
            k: budget.k,
            terms: Component::ALL
                .iter()
                .map(|c| BudgetTerm {
                    name: c.name().into(),
                    formula: c.formula().into(),
                    source: sources[c.index()].clone(),
                    largest: d.dof.to_user(largest[c.index()]),
                })
                .collect(),
            largest_combined: d.dof.to_user(uc),
            largest_expanded: d.dof.to_user(big),
            points: budget
                .points
                .iter()
                .filter(|p| p.dof == k)
                .filter_map(|p| {
                    p.direction.map(|direction| BudgetPoint {
                        position_mm: p.position_mm,
                        direction,
                        terms: p.terms.iter().map(|&t| d.dof.to_user(t)).collect(),
                        combined: d.dof.to_user(p.combined),
                        expanded: d.dof.to_user(p.expanded),
                    })
                })
                .collect(),
        });
    }
}
