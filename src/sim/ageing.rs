//! A year of short checks on the twin, in minutes (issue 30).
//!
//! The axis is commissioned as in [`closed_loop::run`] (aligned, its follower mapped, measured,
//! its tables published into the twin's PLC), then ages day by day by a [`Drift`] of its
//! positioning (the twin's screw wear, `p·sin²(πu)` mid-travel, growing linearly from an
//! onset), while its CNC runs a short check ([`YearSpec::check`]: a few targets, one or two
//! bidirectional runs) every `interval_days`. Only the checks take machine time on the lab's
//! clock; the days between them are the wear's.
//!
//! What the service does with them, as it would on a machine: every figure of every check is
//! trended ([`crate::trend`]) against limits learned from the first checks as commissioned;
//! E, the figure wear moves, is forecast to its tolerance at every check. On E's drift alarm a
//! composed table is proposed ([`crate::comp::compose`]: the positioning table in force plus
//! the check's residual, re-composed from each later check); it is published when the forecast
//! gives the tolerance less than `notice_days` (the operator's notice), and the checks after it
//! are charted against the commissioned limits again.
//!
//! Judged by the truth: each check's figures beside the twin's at the same captures, and the
//! day E would have crossed its tolerance had nothing been published (the twin knows its wear:
//! the check's true captures with each later day's wear added), against the forecast.

use super::axis::{Direction as AxisDirection, Wear};
use super::closed_loop::{
    self, Figures, LoopError, LoopSpec, Measured, Pass, Published, Step, publish_all, tables_of,
};
use super::lab::Lab;
use crate::comp::TableSet;
use crate::comp::table::compose;
use crate::evaluate::{AxisEvaluation, EvalOptions, ReferenceLine, evaluate_captures};
use crate::run::{Capture, Direction, Plan, PlanError, PlanSpec};
use crate::trend::{self, Chart, Forecast, Point};
use std::time::Duration;

/// The figures trended, in the order of [`values`]: E, M, A, R, B of positioning (µm), the
/// two straightnesses (µm), pitch, yaw and roll (max − min of the mean profile, ″), and the
/// positioning drift (µm): the RMS change of the mean positional deviations at the check's
/// targets, both directions, from the mean of the first checks' ([`profile`]).
///
/// Why the drift beside E: E is a range (largest − smallest mean deviation), and a change
/// inside that range moves it little or not at all. Wear mid-travel of 0.47 µm moved the
/// twin's true E by 0.14 µm (seed 7) and the largest deviation change read 0.44 µm; the drift sees what
/// changed wherever it is, E only what passed the extremes. Why the RMS and not the largest
/// change: it averages the noise of 12 deviations (over 200 stable checks, σ 0.019 µm for
/// the RMS on seed 47, 0.042 µm for the largest on seed 11), and sees a change of any shape, where a mean of the signed changes is
/// blind to one that tilts the profile. E still carries the tolerance the forecast aims at.
pub const FIGURES: [&str; 11] = [
    "E",
    "M",
    "A",
    "R",
    "B",
    "straightness x",
    "straightness z",
    "pitch",
    "yaw",
    "roll",
    "positioning drift",
];

/// Index of E in [`FIGURES`]: the figure the forecast follows to its tolerance.
pub const E: usize = 0;

/// Index of the positioning drift in [`FIGURES`]: the figure the drift alarm watches.
pub const DRIFT: usize = 10;

/// The figures positioning wear moves (E, M, A, the drift): on a wearing axis their signals
/// are not false.
pub const WEAR_MOVES: [usize; 4] = [0, 1, 2, DRIFT];

/// The units of [`FIGURES`].
pub fn unit(figure: usize) -> &'static str {
    if (7..DRIFT).contains(&figure) {
        "″"
    } else {
        "µm"
    }
}

/// A figure set in user units (µm, ″) in the order of [`FIGURES`]; NaN where undefined (the
/// drift: it needs the first checks' profile).
pub fn values(f: &Figures) -> [f64; 11] {
    let um = |v: f64| v * 1e3;
    let arcsec = |v: f64| v.to_degrees() * 3600.0;
    [
        um(f.e),
        um(f.m),
        f.a.map_or(f64::NAN, um),
        f.r.map_or(f64::NAN, um),
        f.b.map_or(f64::NAN, um),
        um(f.straightness_x),
        um(f.straightness_z),
        arcsec(f.pitch),
        arcsec(f.yaw),
        arcsec(f.roll),
        f64::NAN,
    ]
}

/// The mean positional deviation (µm) at each target, up then down: what the drift compares.
pub fn profile(eval: &AxisEvaluation) -> Vec<f64> {
    let p = &eval.profiles[1];
    [Direction::Up, Direction::Down]
        .into_iter()
        .flat_map(|d| p.direction(d).unwrap_or_default().iter().map(|v| v * 1e3))
        .collect()
}

/// E's standard uncertainty (µm) by `m`'s budget: √2 × the RMS of the bidirectional mean's
/// standard uncertainty over the targets (E is the difference of two of them).
fn e_uncertainty(m: &Measured) -> f64 {
    let u: Vec<f64> = m
        .budget
        .points
        .iter()
        .filter(|p| p.dof == 1 && p.direction.is_none())
        .map(|p| p.combined)
        .collect();
    if u.is_empty() {
        return 0.0;
    }
    let rms = (u.iter().map(|v| v * v).sum::<f64>() / u.len() as f64).sqrt();
    rms * std::f64::consts::SQRT_2 * 1e3
}

/// The RMS change (µm) of `profile` from `reference` (NaN when they do not match).
fn drift_of(profile: &[f64], reference: &[f64]) -> f64 {
    if profile.len() != reference.len() || profile.is_empty() {
        return f64::NAN;
    }
    let ss: f64 = profile
        .iter()
        .zip(reference)
        .map(|(p, r)| (p - r).powi(2))
        .sum();
    (ss / profile.len() as f64).sqrt()
}

/// The mean of `profiles`, leaving out the one at `skip` (if any).
fn mean_profile(profiles: &[&[f64]], skip: Option<usize>) -> Vec<f64> {
    let n = profiles.first().map_or(0, |p| p.len());
    let used: Vec<&[f64]> = profiles
        .iter()
        .enumerate()
        .filter(|(i, p)| Some(*i) != skip && p.len() == n)
        .map(|(_, p)| *p)
        .collect();
    let k = used.len().max(1) as f64;
    (0..n)
        .map(|j| used.iter().map(|p| p[j]).sum::<f64>() / k)
        .collect()
}

/// The short check of a commissioning plan: every other of its targets (where the tables in
/// force were measured, so that a check reads what they left, not the screw's periodic error
/// between their points: the twin's seed 7 read E 6.4 µm at 6 targets of its own placing
/// against 0.4 µm at these), two bidirectional runs.
pub fn check_plan(full: &Plan) -> Result<Plan, PlanError> {
    let targets: Vec<f64> = full.targets.iter().step_by(2).copied().collect();
    let mut plan = Plan::new(PlanSpec {
        targets: targets.len(),
        runs: 2,
        ..full.spec.clone()
    })?;
    plan.targets = targets;
    Ok(plan)
}

/// Positioning wear that grows linearly from a day on.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Drift {
    /// The day (since commissioning) it begins.
    pub onset_day: f64,
    /// Its growth (µm of peak wear per day).
    pub um_per_day: f64,
}

impl Drift {
    /// The peak wear (µm) on `day`.
    pub fn wear_um(&self, day: f64) -> f64 {
        (day - self.onset_day).max(0.0) * self.um_per_day
    }
}

/// The year to simulate.
#[derive(Clone, Debug)]
pub struct YearSpec {
    /// The short check's plan.
    pub check: Plan,
    /// How many weekly (say) checks, and the days between them; a publication adds a check in
    /// the same break, to verify it.
    pub checks: usize,
    pub interval_days: f64,
    /// The positioning wear (`None`: a stable machine).
    pub drift: Option<Drift>,
    /// E's tolerance (µm), which the forecast aims at.
    pub tolerance_e_um: f64,
    /// A proposal is published once the forecast gives the tolerance less than this (days).
    pub notice_days: f64,
    pub trend: trend::Settings,
}

/// One check as the service saw it and as the twin knows it.
#[derive(Clone, Debug, PartialEq)]
pub struct CheckRecord {
    /// Days since commissioning, and the peak wear (µm) that day.
    pub day: f64,
    pub wear_um: f64,
    /// The figures (µm, ″; see [`FIGURES`]) measured, and the twin's at the same captures.
    pub measured: [f64; 11],
    pub truth: [f64; 11],
    /// The positioning profile measured and true ([`profile`]).
    pub profile: [Vec<f64>; 2],
    /// E's standard uncertainty (µm) by the check's budget: the bidirectional mean's at its
    /// targets (RMS) for each of the two points E is the difference of.
    pub e_u: f64,
    /// The sequence of the positioning table in force.
    pub table: u32,
    /// Whether each figure's chart signals at this check.
    pub signals: [bool; 11],
    /// E's forecast from this check (the current table's checks).
    pub forecast: Option<Forecast>,
    /// The day E would reach its tolerance had no table been published from this check on:
    /// the twin's truth (`None`: not within two years).
    pub true_crossing_day: Option<f64>,
    /// Machine time of the check.
    pub machine_time: Duration,
}

/// A composed table, proposed from a check.
#[derive(Clone, Debug)]
pub struct Proposal {
    /// The check it was composed from.
    pub check: usize,
    pub tables: TableSet,
}

/// A proposal published.
#[derive(Clone, Debug)]
pub struct Publication {
    /// The check after which it went to the PLC, and the check it was composed from.
    pub after_check: usize,
    pub from_check: usize,
    pub published: Vec<Published>,
}

/// The year's outcome.
#[derive(Clone, Debug)]
pub struct Year {
    /// The commissioning run's figures, measured and true (µm, ″).
    pub commissioned: [[f64; 11]; 2],
    pub checks: Vec<CheckRecord>,
    /// Where the checks under each table begin (the first at 0: the commissioned table).
    pub segments: Vec<usize>,
    /// The first check at which the positioning drift's or E's chart signalled.
    pub alarm: Option<usize>,
    /// The last proposal made (re-composed from each check after the alarm until published).
    pub proposal: Option<Proposal>,
    pub publication: Option<Publication>,
}

impl Year {
    /// The chart of `figure` up to check `upto`: over the commissioned table's checks, its
    /// limits learned from the first of them and every one in control since; under a later
    /// table, against the commissioned table's history (the table brought the axis back).
    /// `None` while there are too few checks, or the figure has no values (A and R of a
    /// one-run check).
    pub fn chart(&self, figure: usize, upto: usize, s: &trend::Settings) -> Option<Chart> {
        let upto = upto.min(self.checks.len().checked_sub(1)?);
        let start = self
            .segments
            .iter()
            .copied()
            .filter(|&st| st <= upto)
            .max()
            .unwrap_or(0);
        let first_end = self.segments.get(1).copied().unwrap_or(self.checks.len());
        if start == 0 {
            return trend::chart(&points(&self.checks[..=upto], figure), s).ok();
        }
        let commissioned = trend::chart(&points(&self.checks[..first_end], figure), s).ok()?;
        Some(trend::follow(
            &commissioned.history,
            &points(&self.checks[start..=upto], figure),
            s,
        ))
    }
}

/// What the year is doing, for whoever shows progress.
#[derive(Debug)]
pub enum YearStep<'a> {
    /// A step of commissioning.
    Commissioning(Step),
    /// A check is in.
    Checked(usize, &'a CheckRecord),
    /// A drift alarm (the positioning drift's or E's), and a composed table proposed from
    /// check `usize`.
    Proposed(usize),
    /// The proposal went to the PLC.
    Published(&'a Publication),
}

/// Commission the axis of `spec` on a new lab and run the year's checks.
pub fn year(
    spec: &LoopSpec,
    y: &YearSpec,
    mut step: impl FnMut(YearStep),
) -> Result<Year, LoopError> {
    let mut lab = Lab::new(&spec.lab).map_err(|source| LoopError::Lab {
        pass: Pass::Before,
        source,
    })?;
    let mut loop_step = |s| step(YearStep::Commissioning(s));
    closed_loop::prepare(&mut lab, spec, &mut loop_step)?;
    let first = closed_loop::measure(&mut lab, spec, Pass::Before, &mut loop_step)?;
    let truth_of = |m: &Measured| {
        let eval =
            evaluate_captures(&m.truth_captures(), &EvalOptions::default()).map_err(|source| {
                LoopError::Evaluate {
                    pass: Pass::Before,
                    source,
                }
            })?;
        Ok::<_, LoopError>((
            values(&Figures::of(&eval, spec.straightness_line)),
            profile(&eval),
        ))
    };
    let commissioned = [values(&first.figures), truth_of(&first)?.0];
    let mut in_force = tables_of(spec, &first.eval)?;
    let published = publish_all(&lab, spec, &in_force, 1, &mut loop_step)?;
    // The positioning table's sequence (published first), and the last one used.
    let mut sequence = published.first().map_or(1, |p| p.sequence);
    let mut last = published.last().map_or(1, |p| p.sequence);
    let check_spec = LoopSpec {
        plan: y.check.clone(),
        align_rounds: 0,
        follower: None,
        budget: closed_loop::BudgetSpec {
            drift_check: None,
            ..spec.budget.clone()
        },
        ..spec.clone()
    };
    let mut year = Year {
        commissioned,
        checks: Vec::with_capacity(y.checks),
        segments: vec![0],
        alarm: None,
        proposal: None,
        publication: None,
    };
    // Where the current table's checks begin; the first checks' mean profiles (measured, true).
    let mut segment = 0;
    let mut references: [Option<Vec<f64>>; 2] = [None, None];
    // After a publication, a check in the same break verifies it; the weekly ones go on.
    let (mut scheduled, mut verify_on) = (0, None);
    while scheduled < y.checks || verify_on.is_some() {
        let i = year.checks.len();
        let day = verify_on.take().unwrap_or_else(|| {
            scheduled += 1;
            (scheduled - 1) as f64 * y.interval_days
        });
        let wear_um = y.drift.map_or(0.0, |d| d.wear_um(day));
        let axis = &lab.plant.axis;
        axis.set_wear(Wear {
            positioning_um: wear_um,
            ..axis.wear()
        });
        let t = lab.now();
        let m = closed_loop::measure(&mut lab, &check_spec, Pass::Before, &mut |_| {})?;
        let machine_time = lab.now() - t;
        let (truth, true_profile) = truth_of(&m)?;
        year.checks.push(CheckRecord {
            day,
            wear_um,
            measured: values(&m.figures),
            truth,
            profile: [profile(&m.eval), true_profile],
            e_u: e_uncertainty(&m),
            table: sequence,
            signals: [false; 11],
            forecast: None,
            true_crossing_day: None,
            machine_time,
        });
        if i + 1 == y.trend.baseline {
            references = drift_references(&mut year.checks);
        } else if let (Some(rec), [Some(m), Some(t)]) = (year.checks.last_mut(), &references) {
            rec.measured[DRIFT] = drift_of(&rec.profile[0], m);
            rec.truth[DRIFT] = drift_of(&rec.profile[1], t);
        }
        // The newest point of each chart is this check's, when it has a value.
        let signals: [bool; 11] = std::array::from_fn(|k| {
            year.checks[i].measured[k].is_finite()
                && year
                    .chart(k, i, &y.trend)
                    .and_then(|c| c.signals.last().copied())
                    .unwrap_or(false)
        });
        let e_points = points(&year.checks[segment..], E);
        // The forecast's interval states E's own uncertainty beside the line's.
        let forecast = trend::forecast(&e_points, y.tolerance_e_um, y.trend.window)
            .map(|f| f.with_level_u(year.checks[i].e_u));
        let true_crossing_day = true_crossing(&lab, &m, spec.straightness_line, y, day);
        if let Some(rec) = year.checks.last_mut() {
            rec.signals = signals;
            rec.forecast = forecast;
            rec.true_crossing_day = true_crossing_day;
            step(YearStep::Checked(i, rec));
        }
        let alarmed = |c: &CheckRecord| c.signals[DRIFT] || c.signals[E];
        if alarmed(&year.checks[i]) && year.alarm.is_none() {
            year.alarm = Some(i);
        }
        // Positioning drifted under the table in force: propose, re-composed from the newest
        // check.
        let drifting = year.checks[segment..].iter().any(alarmed);
        if !drifting {
            continue;
        }
        let residual = tables_of(&check_spec, &m.eval)?;
        let tables = TableSet {
            positioning: compose(&in_force.positioning, &residual.positioning)?,
            straightness: in_force.straightness.clone(),
            abbe: Vec::new(),
        };
        if year.proposal.as_ref().is_none_or(|p| p.check < segment) {
            step(YearStep::Proposed(i));
        }
        let due = forecast
            .and_then(|f| f.crossing)
            .is_some_and(|c| c.day - day <= y.notice_days);
        let proposal = year.proposal.insert(Proposal { check: i, tables });
        if due {
            let published = publish_all(&lab, spec, &proposal.tables, last + 1, &mut |_| {})?;
            sequence = published.first().map_or(sequence, |p| p.sequence);
            last = published.last().map_or(last, |p| p.sequence);
            in_force = proposal.tables.clone();
            let publication = Publication {
                after_check: i,
                from_check: proposal.check,
                published,
            };
            step(YearStep::Published(&publication));
            year.publication = Some(publication);
            segment = i + 1;
            year.segments.push(segment);
            verify_on = Some(day);
        }
    }
    Ok(year)
}

/// Each figure's (day, value) over `checks`, its undefined values left out.
pub fn points(checks: &[CheckRecord], figure: usize) -> Vec<Point> {
    checks
        .iter()
        .map(|c| Point {
            days: c.day,
            value: c.measured[figure],
        })
        .filter(|p| p.value.is_finite())
        .collect()
}

/// The first checks' mean profiles (measured, true), and each of those checks' drift from
/// the mean of the others (its own left out: as far from it as a later check's noise is).
fn drift_references(checks: &mut [CheckRecord]) -> [Option<Vec<f64>>; 2] {
    std::array::from_fn(|k| {
        let profiles: Vec<Vec<f64>> = checks.iter().map(|c| c.profile[k].clone()).collect();
        let refs: Vec<&[f64]> = profiles.iter().map(Vec::as_slice).collect();
        for (j, c) in checks.iter_mut().enumerate() {
            let d = drift_of(&profiles[j], &mean_profile(&refs, Some(j)));
            match k {
                0 => c.measured[DRIFT] = d,
                _ => c.truth[DRIFT] = d,
            }
        }
        Some(mean_profile(&refs, None))
    })
}

/// The day E of `m`'s captures would reach the tolerance with no new table: the twin's true
/// captures of the check with each later day's wear added (`None` beyond two years).
fn true_crossing(
    lab: &Lab,
    m: &Measured,
    line: ReferenceLine,
    y: &YearSpec,
    day: f64,
) -> Option<f64> {
    let drift = y.drift?;
    let axis = &lab.plant.axis;
    let now = axis.wear();
    let base = m.truth_captures();
    let reference = y.check.reference_mm;
    let e_at = |d: f64| -> Option<f64> {
        let w = Wear {
            positioning_um: drift.wear_um(d),
            ..now
        };
        let moved = |mm: f64, dir: AxisDirection| {
            axis.wear_dy_of(&w, mm, dir) - axis.wear_dy_of(&now, mm, dir)
        };
        let zero = moved(reference, AxisDirection::Up);
        let caps: Vec<Capture> = base
            .iter()
            .map(|c| {
                let dir = match c.direction {
                    Direction::Up => AxisDirection::Up,
                    Direction::Down => AxisDirection::Down,
                };
                let mut errors = c.errors;
                errors.dy += moved(c.target_mm, dir) - zero;
                Capture { errors, ..*c }
            })
            .collect();
        let eval = evaluate_captures(&caps, &EvalOptions::default()).ok()?;
        Some(Figures::of(&eval, line).e * 1e3)
    };
    let tol = y.tolerance_e_um;
    let above = |d: f64| e_at(d).is_some_and(|e| e >= tol);
    if above(day) {
        return Some(day);
    }
    // A week at a time to two years ahead, then halving to a hundredth of a day.
    let mut lo = day;
    let mut hi = None;
    let mut d = day;
    while d < day + 730.0 {
        d += 7.0;
        if above(d) {
            hi = Some(d);
            break;
        }
        lo = d;
    }
    let mut hi = hi?;
    while hi - lo > 0.01 {
        let mid = 0.5 * (lo + hi);
        if above(mid) {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    Some(hi)
}
