//! The ISO 230-2 test plan: targets with non-uniform spacing over the measurement travel, n
//! bidirectional runs in the standard linear cycle, overrun, dwell, feed.
//!
//! Non-uniform spacing (ISO 230-2 asks for it so periodic errors, such as a ball screw's, are
//! not sampled at one phase): target i sits at `i·p + r_i`, where `p` is the mean interval and
//! `r_i` spreads the targets' phases over the screw lead by the golden-ratio sequence
//! (`r_i = lead·(frac(i·φ) − ½)`, kept within a third of the interval). The first and last
//! targets sit exactly at the ends of the travel.
//!
//! The linear cycle: each run approaches every target in the + direction, starting below the
//! first by the overrun, then every target in the − direction from beyond the last, dwelling
//! at each target.

use super::Direction;
use crate::util::range::{self, FEED_MM_MIN, POSITION_MM, Range};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Why a plan was refused.
#[derive(Clone, Debug, Error, PartialEq)]
#[error("test plan: {field}: {problem}")]
pub struct PlanError {
    pub field: &'static str,
    pub problem: String,
}

fn bad(field: &'static str, problem: impl Into<String>) -> PlanError {
    PlanError {
        field,
        problem: problem.into(),
    }
}

/// The acceleration the run's estimates assume (mm/s²): a machine tool's axis at measuring
/// feed is at speed within a millimetre or two, so the dwells and the feed set the time.
pub const ETA_ACCEL_MM_S2: f64 = 500.0;

/// What the user asks for.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlanSpec {
    /// The machine axis under test ("X", "Y" or "Z").
    pub axis: String,
    /// Measurement travel (mm): first and last target.
    pub start_mm: f64,
    pub end_mm: f64,
    /// Number of targets (ISO 230-2: at least five per metre, and at least five).
    pub targets: usize,
    /// Bidirectional runs (ISO 230-2: five).
    pub runs: u32,
    /// Distance beyond the end targets where the axis reverses (mm).
    pub overrun_mm: f64,
    /// Dwell at each target (s).
    pub dwell_s: f64,
    /// Feed between targets (mm/min).
    pub feed_mm_min: f64,
    /// Ball-screw lead (mm), for the non-uniform spacing; 0 gives uniform spacing.
    pub lead_mm: f64,
    /// The reference point (mm): where compensation tables are zero. Defaults to the start.
    #[serde(default)]
    pub reference_mm: Option<f64>,
}

/// The most targets a plan may have: one a millimetre over a metre, beyond any ISO test.
pub const MAX_TARGETS: usize = 1000;
/// The most bidirectional runs (ISO 230-2 asks for five).
pub const MAX_RUNS: u32 = 100;

impl PlanSpec {
    /// Every number within its range (the relations between them are checked by
    /// [`Plan::new`]), or the first that is not, named.
    pub fn check(&self) -> Result<(), PlanError> {
        for (f, v, r) in [
            ("start_mm", self.start_mm, POSITION_MM),
            ("end_mm", self.end_mm, POSITION_MM),
            ("overrun_mm", self.overrun_mm, Range::new(0.0, 1000.0, "mm")),
            ("dwell_s", self.dwell_s, Range::new(0.0, 3600.0, "s")),
            ("feed_mm_min", self.feed_mm_min, FEED_MM_MIN),
            ("lead_mm", self.lead_mm, Range::new(0.0, 1000.0, "mm")),
            (
                "reference_mm",
                self.reference_mm.unwrap_or(0.0),
                POSITION_MM,
            ),
        ] {
            r.check(v).map_err(|p| bad(f, p))?;
        }
        range::int(self.targets, 5, MAX_TARGETS, "").map_err(|p| bad("targets", p))?;
        if self.runs < 2 {
            return Err(bad(
                "runs",
                format!(
                    "{}: at least 2 runs are needed for a standard deviation (ISO 230-2: 5)",
                    self.runs
                ),
            ));
        }
        range::int(self.runs, 2, MAX_RUNS, "").map_err(|p| bad("runs", p))?;
        Ok(())
    }
}

impl Default for PlanSpec {
    fn default() -> Self {
        PlanSpec {
            axis: "X".into(),
            start_mm: 0.0,
            end_mm: 1000.0,
            targets: 11,
            runs: 5,
            overrun_mm: 5.0,
            dwell_s: 2.0,
            feed_mm_min: 2000.0,
            lead_mm: 10.0,
            reference_mm: None,
        }
    }
}

/// One stop of the cycle.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Step {
    /// Where the axis goes (mm).
    pub position_mm: f64,
    /// `Some` when this stop is a target to capture; `None` for the reversal points.
    pub target: Option<TargetKey>,
}

/// A target in a run and direction.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct TargetKey {
    pub run: u32,
    pub target_index: u32,
    pub direction: Direction,
}

impl TargetKey {
    /// The key of a capture.
    pub fn of(c: &super::Capture) -> TargetKey {
        TargetKey {
            run: c.run,
            target_index: c.target_index,
            direction: c.direction,
        }
    }

    /// In words, with the target's position from `plan`: `run 1, target 8 at 700.000 mm,
    /// approached upwards`.
    pub fn describe(&self, plan: &Plan) -> String {
        let at = plan
            .targets
            .get(self.target_index as usize)
            .map(|t| format!(" at {t:.3} mm"))
            .unwrap_or_default();
        format!("{self}{at}, approached {}", self.direction.words())
    }
}

impl std::fmt::Display for TargetKey {
    /// `run 1, target 8` (targets counted from 1, as the plan lists them).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "run {}, target {}", self.run, self.target_index + 1)
    }
}

/// A validated plan.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    pub spec: PlanSpec,
    /// Target positions (mm), increasing.
    pub targets: Vec<f64>,
    pub reference_mm: f64,
}

const PHI: f64 = 0.618_033_988_749_894_9;

impl Plan {
    /// Validate the spec and place the targets.
    pub fn new(spec: PlanSpec) -> Result<Plan, PlanError> {
        if !["X", "Y", "Z"].contains(&spec.axis.as_str()) {
            return Err(bad("axis", format!("\"{}\": use X, Y or Z", spec.axis)));
        }
        spec.check()?;
        let len = spec.end_mm - spec.start_mm;
        if len <= 0.0 {
            return Err(bad(
                "end_mm",
                format!(
                    "{} mm must be beyond start_mm ({} mm)",
                    spec.end_mm, spec.start_mm
                ),
            ));
        }
        let min_targets = ((len / 1000.0) * 5.0).ceil().max(5.0) as usize;
        if spec.targets < min_targets {
            return Err(bad(
                "targets",
                format!(
                    "{} are too few for {len} mm: ISO 230-2 asks for at least {min_targets} (five per metre, at least five)",
                    spec.targets
                ),
            ));
        }
        let m = spec.targets;
        let p = len / (m - 1) as f64;
        let spread = spec.lead_mm.min(p / 3.0);
        let targets: Vec<f64> = (0..m)
            .map(|i| {
                if i == 0 {
                    spec.start_mm
                } else if i == m - 1 {
                    spec.end_mm
                } else {
                    let frac = (i as f64 * PHI).fract();
                    spec.start_mm + i as f64 * p + spread * (frac - 0.5)
                }
            })
            .collect();
        let reference_mm = spec.reference_mm.unwrap_or(spec.start_mm);
        if !(spec.start_mm..=spec.end_mm).contains(&reference_mm) {
            return Err(bad(
                "reference_mm",
                format!(
                    "{reference_mm} mm is outside the travel {} .. {} mm",
                    spec.start_mm, spec.end_mm
                ),
            ));
        }
        Ok(Plan {
            spec,
            targets,
            reference_mm,
        })
    }

    /// Every stop of the cycle in order: for each run, the start below the first target,
    /// the targets upwards, the reversal beyond the last, the targets downwards.
    pub fn steps(&self) -> Vec<Step> {
        let s = &self.spec;
        let below = s.start_mm - s.overrun_mm;
        let beyond = s.end_mm + s.overrun_mm;
        let mut out = Vec::with_capacity((s.runs as usize) * (2 * self.targets.len() + 2));
        for run in 1..=s.runs {
            out.push(Step {
                position_mm: below,
                target: None,
            });
            for (i, &t) in self.targets.iter().enumerate() {
                out.push(Step {
                    position_mm: t,
                    target: Some(TargetKey {
                        run,
                        target_index: i as u32,
                        direction: Direction::Up,
                    }),
                });
            }
            out.push(Step {
                position_mm: beyond,
                target: None,
            });
            for (i, &t) in self.targets.iter().enumerate().rev() {
                out.push(Step {
                    position_mm: t,
                    target: Some(TargetKey {
                        run,
                        target_index: i as u32,
                        direction: Direction::Down,
                    }),
                });
            }
        }
        out
    }

    /// The travel the run covers (mm): the end targets and the overrun beyond them, the span
    /// the beam alignment must hold.
    pub fn travel_mm(&self) -> (f64, f64) {
        let lo = self.targets.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = self
            .targets
            .iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max);
        (lo - self.spec.overrun_mm, hi + self.spec.overrun_mm)
    }

    /// The number of captures a complete run gives.
    pub fn capture_count(&self) -> usize {
        2 * self.targets.len() * self.spec.runs as usize
    }

    /// Where the plan departs from ISO 230-2 without being invalid, as sentences (empty: it
    /// follows the standard). Shown before a run starts and in the run's reply.
    pub fn warnings(&self) -> Vec<String> {
        self.departures()
            .into_iter()
            .map(|(_, full)| full)
            .collect()
    }

    /// [`Plan::warnings`] in a few words each (a console at 80 columns).
    pub fn warnings_brief(&self) -> Vec<String> {
        self.departures().into_iter().map(|(b, _)| b).collect()
    }

    fn departures(&self) -> Vec<(String, String)> {
        let mut w = Vec::new();
        if self.spec.runs < 5 {
            w.push((
                format!("ISO 230-2 asks for 5 runs, not {}", self.spec.runs),
                format!(
                    "{} runs: ISO 230-2 asks for 5 bidirectional runs; the figures (R, E, A) of fewer runs are not comparable with a full test",
                    self.spec.runs
                ),
            ));
        }
        w
    }

    /// Motion time plus dwell time of the whole cycle (s), for a trapezoidal profile with
    /// acceleration `accel` (mm/s²): the floor for the run's wall time.
    pub fn motion_time_s(&self, accel_mm_s2: f64) -> f64 {
        let v = self.spec.feed_mm_min / 60.0;
        let a = accel_mm_s2.max(1e-9);
        let move_time = |d: f64| {
            let d = d.abs();
            let d_acc = v * v / a;
            if d >= d_acc {
                2.0 * v / a + (d - d_acc) / v
            } else {
                2.0 * (d / a).sqrt()
            }
        };
        let steps = self.steps();
        let mut t = 0.0;
        let mut here = steps.first().map(|s| s.position_mm).unwrap_or(0.0);
        for s in &steps {
            t += move_time(s.position_mm - here);
            here = s.position_mm;
            if s.target.is_some() {
                t += self.spec.dwell_s;
            }
        }
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn targets_are_non_uniform_cover_the_lead_and_the_ends() {
        let plan = Plan::new(PlanSpec::default()).unwrap();
        let t = &plan.targets;
        assert_eq!(t.len(), 11);
        assert_eq!(t[0], 0.0);
        assert_eq!(t[10], 1000.0);
        assert!(t.windows(2).all(|w| w[1] > w[0]));
        let gaps: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
        let (lo, hi) = gaps
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), g| (a.min(*g), b.max(*g)));
        assert!(hi - lo > 1.0, "spacing should vary: {gaps:?}");
        // The inner targets' phases on the 10 mm lead are spread, not repeated.
        let mut phases: Vec<f64> = t[1..10].iter().map(|x| x.rem_euclid(10.0)).collect();
        phases.sort_by(f64::total_cmp);
        assert!(phases.windows(2).all(|w| w[1] - w[0] > 0.3), "{phases:?}");
    }

    #[test]
    fn cycle_visits_every_target_both_ways() {
        let plan = Plan::new(PlanSpec {
            runs: 2,
            ..PlanSpec::default()
        })
        .unwrap();
        let steps = plan.steps();
        assert_eq!(steps.len(), 2 * (2 * 11 + 2));
        assert_eq!(steps[0].position_mm, -5.0);
        assert_eq!(steps[12].position_mm, 1005.0);
        let captures: Vec<TargetKey> = steps.iter().filter_map(|s| s.target).collect();
        assert_eq!(captures.len(), plan.capture_count());
        let mut unique = captures.clone();
        unique.sort();
        unique.dedup();
        assert_eq!(unique.len(), captures.len());
        // Down-direction targets come in decreasing order.
        assert_eq!(steps[13].target.unwrap().target_index, 10);
        assert_eq!(steps[13].target.unwrap().direction, Direction::Down);
    }

    #[test]
    fn bad_plans_name_the_field() {
        let e = Plan::new(PlanSpec {
            targets: 6,
            end_mm: 2000.0,
            ..PlanSpec::default()
        })
        .unwrap_err();
        assert_eq!(e.field, "targets");
        assert!(e.to_string().contains("at least 10"), "{e}");
        let e = Plan::new(PlanSpec {
            axis: "W".into(),
            ..PlanSpec::default()
        })
        .unwrap_err();
        assert_eq!(e.field, "axis");
        let e = Plan::new(PlanSpec {
            runs: 1,
            ..PlanSpec::default()
        })
        .unwrap_err();
        assert_eq!(e.field, "runs");
    }

    #[test]
    fn fewer_than_five_runs_warn() {
        let spec = |runs| PlanSpec {
            runs,
            ..PlanSpec::default()
        };
        assert_eq!(Plan::new(spec(5)).unwrap().warnings(), Vec::<String>::new());
        let w = Plan::new(spec(3)).unwrap().warnings();
        assert_eq!(w.len(), 1);
        assert!(
            w[0].starts_with("3 runs: ISO 230-2 asks for 5 bidirectional runs;"),
            "{}",
            w[0]
        );
        assert_eq!(
            Plan::new(spec(3)).unwrap().warnings_brief(),
            ["ISO 230-2 asks for 5 runs, not 3"]
        );
    }

    #[test]
    fn motion_time_adds_moves_and_dwells() {
        let plan = Plan::new(PlanSpec {
            start_mm: 0.0,
            end_mm: 100.0,
            targets: 5,
            runs: 2,
            overrun_mm: 0.0,
            dwell_s: 1.0,
            feed_mm_min: 600.0,
            lead_mm: 0.0,
            ..PlanSpec::default()
        })
        .unwrap();
        // 10 mm/s, accel 1e9: moves of 25 mm take 2.5 s; per run 4 moves up + 4 down (the
        // reversals coincide with the end targets), 10 dwells.
        let t = plan.motion_time_s(1e9);
        assert!((t - 2.0 * (8.0 * 2.5 + 10.0)).abs() < 1e-3, "{t}");
    }
}
