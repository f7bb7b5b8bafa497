//! A measurement run's programs, sans-I/O: which part program the CNC gets next. The live
//! service (`service::procedure::run`) and the virtual-time lab (`sim::lab`) both drive
//! this, so a run is made up and resumed the same way in both.
//!
//! - The first program is the whole cycle, or, for a run resumed after a restart, what is
//!   left of it from the first missing capture (its approach points held: the carriage comes
//!   back from wherever the CNC left it).
//! - A pause (a PSD lost its spot) stops the program at its next stop; once the spots are
//!   back and the program has ended, the rest of the cycle follows, from the first capture
//!   still missing.
//! - A program that ended with captures missing is followed by a make-up pass over them:
//!   each target approached from the plan's overrun, dwelling twice as long as the cycle (what
//!   missed a capture the first time was a dwell too short for the follower to settle). A
//!   capture still missing after [`MAKEUP_TRIES`] make-up passes fails the run.
//!
//! Captures that were taken but flagged and reopened for a retake (`run::machine`) are
//! missing again, so the make-up pass retakes them while the run is on the machine.

use super::plan::{Plan, Step, TargetKey};
use super::program::{
    CaptureMode, Dialect, ProgramError, generate_settled, makeup_steps, remaining_steps,
};
use std::collections::{BTreeMap, BTreeSet};

/// A make-up pass is sent for a missing capture at most this many times before the run fails.
pub const MAKEUP_TRIES: u32 = 3;

/// A make-up pass approaches each target from at most this far on its side (mm; the plan's
/// overrun when that is shorter): farther than the run machine's target tolerance (0.5 mm),
/// so the approach's side is told, and within the tracker's handover band (1.5 mm) with the
/// follower centred at the approach point, so that the last millimetre is no overlap
/// handover. Each such handover closes the stitch's encoder chain; from the overrun (2 mm in
/// the storm) a make-up pass of 22 captures made a random walk of them, and its captures'
/// u grew from 0.55 to 1.90 µm (issue 24).
pub const MAKEUP_APPROACH_MM: f64 = 1.0;

/// A program for the CNC: its stops, a note for its title, the dwell at each target and the
/// hold at each approach point (s).
#[derive(Clone, Debug, PartialEq)]
pub struct Program {
    pub steps: Vec<Step>,
    pub note: String,
    pub dwell_s: f64,
    pub hold_s: f64,
}

impl Program {
    /// The part program's text for `plan` in `dialect`: this program's stops, its dwell at
    /// each target and its hold at each approach point.
    pub fn text(
        &self,
        plan: &Plan,
        dialect: Dialect,
        mode: CaptureMode,
    ) -> Result<String, ProgramError> {
        let mut plan = plan.clone();
        plan.spec.dwell_s = self.dwell_s;
        generate_settled(&plan, &self.steps, &self.note, dialect, mode, self.hold_s)
    }
}

/// What comes after a program ended.
#[derive(Clone, Debug, PartialEq)]
pub enum Next {
    /// Send this program.
    Program(Program),
    /// Nothing is missing: the run ends when its last capture is in.
    Nothing,
    /// Captures are still missing after every make-up pass allowed: the run fails.
    Fail(String),
}

/// The run's program bookkeeping.
#[derive(Clone, Debug)]
pub struct Session {
    plan: Plan,
    /// Make-up passes sent so far for each capture.
    makeup_for: BTreeMap<TargetKey, u32>,
    /// The program was stopped by a pause: the rest of the cycle follows, not a make-up.
    stopped_by_pause: bool,
    /// Programs sent so far.
    pub programs: u32,
}

impl Session {
    pub fn new(plan: Plan) -> Session {
        Session {
            plan,
            makeup_for: BTreeMap::new(),
            stopped_by_pause: false,
            programs: 0,
        }
    }

    /// The plan.
    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    /// The first program, with `done` captures already stored: the whole cycle, or what is
    /// left of it. A resumed run (`resumed_at`: where the follower holds the carriage's last
    /// position) first comes back there, and holds its approach points. `None`: nothing is
    /// left to capture.
    pub fn first(
        &mut self,
        done: &BTreeSet<TargetKey>,
        resumed_at: Option<f64>,
    ) -> Option<Program> {
        let mut steps = remaining_steps(&self.plan, done)?;
        let (note, hold_s) = match resumed_at {
            Some(at) => {
                steps.insert(
                    0,
                    Step {
                        position_mm: at,
                        target: None,
                    },
                );
                ("resumed", self.plan.spec.dwell_s)
            }
            None => ("", 0.0),
        };
        Some(self.program(steps, note, self.plan.spec.dwell_s, hold_s))
    }

    /// The run paused and its program was stopped at its next stop.
    pub fn paused(&mut self) {
        self.stopped_by_pause = true;
    }

    /// Whether the program now running was stopped by a pause.
    pub fn stopped_by_pause(&self) -> bool {
        self.stopped_by_pause
    }

    /// The program ended (and the spots are on their PSDs) with `missing` captures missing:
    /// what the CNC gets next.
    pub fn ended(&mut self, missing: &[TargetKey]) -> Next {
        if missing.is_empty() {
            self.stopped_by_pause = false;
            return Next::Nothing;
        }
        if std::mem::take(&mut self.stopped_by_pause) {
            // The rest of the cycle, from the carriage's stop, the approach points held as
            // after a restart.
            let done: BTreeSet<TargetKey> = self
                .plan
                .steps()
                .iter()
                .filter_map(|s| s.target)
                .filter(|k| !missing.contains(k))
                .collect();
            return match remaining_steps(&self.plan, &done) {
                Some(steps) => {
                    let (dwell, hold) = (self.plan.spec.dwell_s, self.plan.spec.dwell_s);
                    Next::Program(self.program(steps, "resumed", dwell, hold))
                }
                None => Next::Nothing,
            };
        }
        let tries = |k: &TargetKey| self.makeup_for.get(k).copied().unwrap_or(0);
        if missing.iter().all(|k| tries(k) >= MAKEUP_TRIES) {
            let first = missing
                .first()
                .map(|k| format!(" (the first: {})", k.describe(&self.plan)))
                .unwrap_or_default();
            let n = missing.len();
            return Next::Fail(format!(
                "{n} capture{} still missing after {MAKEUP_TRIES} make-up passes{first}",
                if n == 1 { "" } else { "s" }
            ));
        }
        let pass = missing.iter().map(tries).min().unwrap_or(0) + 1;
        for k in missing {
            *self.makeup_for.entry(*k).or_insert(0) += 1;
        }
        let approach = self.plan.spec.overrun_mm.min(MAKEUP_APPROACH_MM);
        let steps = makeup_steps(&self.plan, missing, approach);
        let (dwell, hold) = (2.0 * self.plan.spec.dwell_s, self.plan.spec.dwell_s);
        Next::Program(self.program(steps, &format!("make-up {pass}"), dwell, hold))
    }

    fn program(&mut self, steps: Vec<Step>, note: &str, dwell_s: f64, hold_s: f64) -> Program {
        self.programs += 1;
        Program {
            steps,
            note: note.to_string(),
            dwell_s,
            hold_s,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::run::{Direction, PlanSpec};

    fn plan() -> Plan {
        Plan::new(PlanSpec {
            axis: "X".into(),
            start_mm: 0.0,
            end_mm: 100.0,
            targets: 5,
            runs: 2,
            overrun_mm: 2.0,
            dwell_s: 1.5,
            feed_mm_min: 3000.0,
            lead_mm: 0.0,
            reference_mm: None,
        })
        .expect("plan")
    }

    fn key(run: u32, t: u32, d: Direction) -> TargetKey {
        TargetKey {
            run,
            target_index: t,
            direction: d,
        }
    }

    #[test]
    fn the_first_program_is_the_cycle_or_what_is_left() {
        let p = plan();
        let mut s = Session::new(p.clone());
        let first = s.first(&BTreeSet::new(), None).expect("a program");
        assert_eq!(first.steps, p.steps());
        assert_eq!(
            (first.dwell_s, first.hold_s, first.note.as_str()),
            (1.5, 0.0, "")
        );
        // Resumed with run 1 up done: back to where the follower is, then from run 1 down.
        let done: BTreeSet<TargetKey> = (0..5).map(|t| key(1, t, Direction::Up)).collect();
        let mut s = Session::new(p.clone());
        let r = s.first(&done, Some(57.0)).expect("a program");
        assert_eq!(r.steps[0].position_mm, 57.0);
        assert_eq!(r.steps[0].target, None);
        let first_key = r.steps.iter().find_map(|s| s.target).expect("a capture");
        assert_eq!(first_key, key(1, 4, Direction::Down));
        assert_eq!((r.note.as_str(), r.hold_s), ("resumed", 1.5));
        let all: BTreeSet<TargetKey> = p.steps().iter().filter_map(|s| s.target).collect();
        assert_eq!(Session::new(p).first(&all, None), None);
    }

    #[test]
    fn after_a_pause_the_rest_of_the_cycle_then_make_ups_then_failure() {
        let p = plan();
        let mut s = Session::new(p.clone());
        let _ = s.first(&BTreeSet::new(), None);
        s.paused();
        let missing: Vec<TargetKey> = vec![key(2, 0, Direction::Up), key(2, 1, Direction::Up)];
        let Next::Program(rest) = s.ended(&missing) else {
            panic!("the rest of the cycle")
        };
        assert_eq!(rest.note, "resumed");
        assert_eq!(rest.steps.iter().find_map(|s| s.target), Some(missing[0]));
        // The rest ended with one still missing: make-up passes, twice the dwell.
        for pass in 1..=MAKEUP_TRIES {
            let Next::Program(m) = s.ended(&missing[1..]) else {
                panic!("make-up {pass}")
            };
            assert_eq!(m.note, format!("make-up {pass}"));
            assert_eq!((m.dwell_s, m.hold_s), (3.0, 1.5));
            let keys: Vec<TargetKey> = m.steps.iter().filter_map(|s| s.target).collect();
            assert_eq!(keys, &missing[1..]);
            // Approached from below (an upward capture), 1 mm away: within the tracker's
            // handover band, short of the plan's 2 mm overrun.
            assert_eq!(m.steps[0].position_mm, p.targets[1] - MAKEUP_APPROACH_MM);
        }
        match s.ended(&missing[1..]) {
            Next::Fail(why) => assert!(
                why.starts_with(
                    "1 capture still missing after 3 make-up passes (the first: run 2, target 2"
                ),
                "{why}"
            ),
            other => panic!("{other:?}"),
        }
        assert_eq!(s.ended(&[]), Next::Nothing);
        assert_eq!(s.programs, 5);
    }
}
