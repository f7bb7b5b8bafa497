//! The run state machine: from live frame estimates to one capture per target, run and
//! direction, exactly once (sans-I/O; time is an argument).
//!
//! Capture by stability: the carriage is at rest (its measured position stays within a
//! tolerance for the settle time) near a target; the direction is the side it came from; the
//! run is the lowest run whose capture of that target and direction is still missing. Then
//! frames are averaged. Rests elsewhere (reversal points) are ignored, and after a capture the
//! carriage must leave before the next one can start. Identifying targets by where the carriage
//! rests rather than by counting makes a resumed run (service restarted mid-run) pick up
//! wherever the CNC is; targets passed while nobody watched stay missing and `missing()` lists
//! them for a make-up program.
//!
//! Capture by handshake: the PLC reports "at target <code>"; the machine averages the next
//! frames and answers with the code (`RunAction::Acknowledge`).
//!
//! The nominal position the frames are decoupled with is set by the machine (`SetNominal`):
//! the target the carriage rests at. A frame's measured position (`position_mm`, nominal plus
//! dy) is valid whatever nominal it was decoupled with, so rest detection does not depend on it.

use super::judge::{Decision, Judge, Repeatability};
use super::plan::{Plan, TargetKey};
use super::{Capture, Direction};
use crate::units::Errors6;
use crate::util::clock::FrameTime;
use std::collections::{BTreeSet, VecDeque};
use std::time::{Duration, Instant};

/// Positions (one per 20 ms of history) in the median that tells where the carriage came
/// from: a spike of one position does not count, an excursion of two or more does (the
/// reversal of a 1 mm overrun at 500 mm/s² is four beyond a 0.5 mm tolerance, and no more than
/// two of those may be lost).
const APPROACH_MEDIAN: usize = 3;

/// A gap this long in the positions (no frame reached the machine: a link down, PSD2
/// without its spot, a paused run, a service that fell behind) ends the history that tells
/// the approach: the carriage may have gone past the target and back unseen. A reversal of a
/// 1 mm overrun at 500 mm/s² takes about 180 ms; a storm's slow I/O module (25 ms a reply)
/// leaves gaps far shorter. Seen in the storm (issue 24): PSD2 lost its spot while the
/// carriage left the first target upward, the carriage came back to it from below unseen,
/// and the last position seen (31 mm above) filed the rest as the downward capture.
const APPROACH_GAP: Duration = Duration::from_millis(250);

/// How captures are taken.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CaptureSettings {
    /// The carriage is at rest when its position stays within ± this (mm) for `settle`.
    pub rest_tolerance_mm: f64,
    pub settle: Duration,
    /// A rest counts as a target when within this of it (mm); must be below the overrun.
    pub target_tolerance_mm: f64,
    /// Frames averaged per capture.
    pub frames: usize,
    /// With no capture for this long the run fails.
    pub timeout: Duration,
    /// How far a capture may sit from the others of its target and direction (`run::judge`).
    pub repeatability: Repeatability,
    /// Judge every capture before it counts (`run::judge`; `[capture] judge`, off by default
    /// until the fault storm passes with it: issue 24).
    pub judge: bool,
}

impl CaptureSettings {
    /// The settings as a run's configuration snapshot records them (units in the names).
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({
            "rest_tolerance_mm": self.rest_tolerance_mm,
            "settle_s": self.settle.as_secs_f64(),
            "target_tolerance_mm": self.target_tolerance_mm,
            "frames": self.frames,
            "timeout_s": self.timeout.as_secs_f64(),
            "repeatability_um": self.repeatability.linear_mm * 1e3,
            "repeatability_arcsec": self.repeatability.angular_rad.to_degrees() * 3600.0,
            "judge": self.judge,
        })
    }
}

impl Default for CaptureSettings {
    fn default() -> Self {
        CaptureSettings {
            rest_tolerance_mm: 0.005,
            settle: Duration::from_millis(250),
            target_tolerance_mm: 0.5,
            frames: 150,
            timeout: Duration::from_secs(120),
            repeatability: Repeatability::default(),
            judge: false,
        }
    }
}

impl CaptureSettings {
    /// The shortest dwell that leaves a capture time at `rate_hz` frames per second, with a
    /// follower that needs `follower_rest` at each stop (the tracker's rest time and settling:
    /// after following the carriage it makes its final approach, which changes the stitch
    /// and restarts the average): the capture's settling, the follower's rest, the frames,
    /// and half a second for the follower's approach and for frames the link drops. On the
    /// twin (500 Hz, the default settings: 1.45 s) a dwell of 1.4 s captures and one of 1.3 s
    /// ends with no capture after the first stops (PSD2 loses its spot when the carriage
    /// leaves a follower still on its approach).
    pub fn min_dwell(&self, rate_hz: f64, follower_rest: Duration) -> Duration {
        self.settle
            + follower_rest
            + Duration::from_secs_f64(self.frames as f64 / rate_hz.max(1.0) + 0.5)
    }

    /// Refuse a plan whose dwell cannot hold a capture (it would end in make-up passes, or
    /// with no capture at all), with the least dwell that works and what it is made of.
    pub fn check_dwell(
        &self,
        plan: &Plan,
        rate_hz: f64,
        follower_rest: Duration,
    ) -> Result<(), String> {
        let need = self.min_dwell(rate_hz, follower_rest).as_secs_f64();
        if plan.spec.dwell_s < need {
            return Err(format!(
                "a dwell of {} s is too short to capture: use at least {need:.2} s (the capture's settling {} s, the follower's rest and settling at each stop {} s, {} frames at {rate_hz} Hz, and 0.5 s for the follower's final approach and dropped frames), or lower capture.frames",
                plan.spec.dwell_s,
                self.settle.as_secs_f64(),
                follower_rest.as_secs_f64(),
                self.frames
            ));
        }
        Ok(())
    }
}

/// One decoupled frame, as the live pipeline gives it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameSample {
    pub at: Instant,
    pub unix_us: i64,
    /// Measured carriage position: the nominal used plus dy (mm).
    pub position_mm: f64,
    /// The nominal the frame was decoupled with (mm), if any.
    pub nominal: Option<f64>,
    /// The six errors (internal units), relative to the zero reference when one is set.
    pub errors: Errors6,
    /// Per-frame variance of each error from the PSD noise (internal units squared).
    pub var: Errors6,
    /// Variance of each error that averaging does not reduce: the stitching of PSD2's
    /// position, the zero reference, the turns of the head taken out and the calibration in
    /// use (the same for every frame until the next handover).
    pub stitch_var: Errors6,
    /// The turns' part of `stitch_var` while turns of the head found since the last return to
    /// the zero that agreed are known only by their own variance: the next return that agrees
    /// bounds them, and the u of the captures read through them is stated again
    /// (`RunMachine::turns_bounded`). `None` otherwise.
    pub turns_var: Option<Errors6>,
    pub material_c: Option<f64>,
    pub air_c: Option<f64>,
}

/// What the service must do.
#[derive(Clone, Debug, PartialEq)]
pub enum RunAction {
    /// Decouple the following frames with this nominal position.
    SetNominal(Option<f64>),
    /// Store this capture.
    Captured(Capture),
    /// Handshake: tell the PLC this target code is captured.
    Acknowledge { code: u32 },
    /// Every capture of the plan is taken.
    Finished,
    /// The run cannot go on.
    Failed(String),
    /// The judge found this capture wrong or could not check it (`run::judge`): keep it
    /// with the reason (out of the store when `stored`); it is retaken.
    Flagged {
        capture: Capture,
        reason: String,
        stored: bool,
    },
    /// The reference moved by `by` (internal units): shift the zero by it.
    ShiftZero { by: Errors6, reason: String },
    /// A stored capture's u stated again (`RunMachine::turns_bounded`): `capture` as it is
    /// now; keep it with the reason (which gives its u before).
    Restated { capture: Capture, reason: String },
}

#[derive(Clone, Debug, PartialEq)]
enum Phase {
    /// Looking for a rest near a target.
    Watch,
    /// Averaging frames for `key` at `position`.
    Averaging {
        key: TargetKey,
        code: Option<u32>,
        since: Instant,
    },
    /// After a capture at `position`: wait until the carriage leaves it.
    Leaving {
        position: f64,
    },
    Done,
}

#[derive(Clone, Copy, Debug, Default)]
struct Acc {
    n: usize,
    sum: [f64; 6],
    sum_sq: [f64; 6],
    var: [f64; 6],
    stitch_var: [f64; 6],
    turns_var: Option<[f64; 6]>,
    material: (f64, usize),
    air: (f64, usize),
    first_us: i64,
    /// The last frame, in the order frames were read (its wall time can be before the first's).
    last: Option<FrameTime>,
}

/// The standard uncertainties that changed from `was` to `now`, in words
/// ("dx 0.52 → 0.18 µm, ez 0.31 → 0.12″").
fn u_change(was: &Errors6, now: &Errors6) -> String {
    const NAMES: [&str; 6] = ["dx", "dy", "dz", "ex", "ey", "ez"];
    let (was, now) = (was.to_user(), now.to_user());
    let words: Vec<String> = (0..6)
        .filter(|&k| (was[k] - now[k]).abs() > 5e-3 * was[k].abs().max(1e-9))
        .map(|k| {
            let unit = if k < 3 { "µm" } else { "″" };
            format!("{} {:.2} → {:.2} {unit}", NAMES[k], was[k], now[k])
        })
        .collect();
    if words.is_empty() {
        "no change".into()
    } else {
        words.join(", ")
    }
}

/// The run machine.
#[derive(Debug)]
pub struct RunMachine {
    plan: Plan,
    settings: CaptureSettings,
    handshake: bool,
    done: BTreeSet<TargetKey>,
    total: usize,
    phase: Phase,
    rest: VecDeque<(Instant, f64)>,
    /// Positions over the last seconds, to tell the approach direction.
    history: VecDeque<(Instant, f64)>,
    acc: Acc,
    nominal: Option<f64>,
    last_progress: Option<Instant>,
    actions: VecDeque<RunAction>,
    /// The cycle's targets in order, and where the carriage is in it: past the last capture
    /// taken. A rest is the next matching stop from here, so a missed stop does not shift
    /// the run numbers of those after it.
    cycle: Vec<TargetKey>,
    cursor: usize,
    /// Every capture judged before it counts.
    judge: Judge,
    /// The captures flagged so far.
    flagged: BTreeSet<TargetKey>,
    /// The newest captures with their last frame's time: a knock found after them may have
    /// moved their last frames.
    recent: VecDeque<(Capture, FrameTime)>,
    /// The captures taken since the last knock through turns known only by their own
    /// variance, with that variance (the turns' part of their u², internal units²): the next
    /// return to the zero that agrees bounds it (`RunMachine::turns_bounded`).
    turns_pending: Vec<(Capture, [f64; 6])>,
}

/// How many of the newest captures a knock found late may reach back to: half a window
/// late from the watch, or since the last return to the zero (`align::revisit`), a pass or
/// two of a long run.
const RECENT: usize = 512;

impl RunMachine {
    /// A machine for `plan`; `completed` are captures already stored (a resumed run).
    pub fn new(
        plan: Plan,
        settings: CaptureSettings,
        handshake: bool,
        completed: BTreeSet<TargetKey>,
    ) -> Self {
        Self::with_judge(plan, settings, handshake, completed, Vec::new())
    }

    /// A resumed run: `stored` are its captures already stored, which the judge takes as true
    /// (the captures after the restart are checked against them).
    pub fn resumed(
        plan: Plan,
        settings: CaptureSettings,
        handshake: bool,
        stored: Vec<Capture>,
    ) -> Self {
        let done = stored.iter().map(TargetKey::of).collect();
        // A knock found at the first return to the zero after the restart may be dated
        // before it: the stored captures are within its reach (by their first frame's time,
        // as the store keeps it; a capture ends at rest, where a knock is found at once).
        let mut recent: VecDeque<(Capture, FrameTime)> = stored
            .iter()
            .map(|c| (*c, FrameTime::Kept(c.unix_us)))
            .collect();
        recent.make_contiguous().sort_by_key(|(_, t)| *t);
        while recent.len() > RECENT {
            recent.pop_front();
        }
        let mut m = Self::with_judge(plan, settings, handshake, done, stored);
        m.recent = recent;
        m
    }

    fn with_judge(
        plan: Plan,
        settings: CaptureSettings,
        handshake: bool,
        completed: BTreeSet<TargetKey>,
        stored: Vec<Capture>,
    ) -> Self {
        let total = plan.capture_count();
        let judge = Judge::new(settings.repeatability, stored);
        let mut m = RunMachine {
            plan,
            settings,
            handshake,
            judge,
            flagged: BTreeSet::new(),
            done: completed,
            total,
            phase: Phase::Watch,
            rest: VecDeque::new(),
            history: VecDeque::new(),
            acc: Acc::default(),
            nominal: None,
            last_progress: None,
            actions: VecDeque::new(),
            cycle: Vec::new(),
            cursor: 0,
            recent: VecDeque::new(),
            turns_pending: Vec::new(),
        };
        m.cycle = m.plan.steps().iter().filter_map(|s| s.target).collect();
        if m.done.len() >= m.total {
            m.phase = Phase::Done;
            m.actions.push_back(RunAction::Finished);
        }
        m
    }

    /// Captures taken and expected.
    pub fn progress(&self) -> (usize, usize) {
        (self.done.len(), self.total)
    }

    /// Captures flagged so far, and those held for want of a check (with the event).
    pub fn judged(&self) -> (usize, usize, Option<&str>) {
        (
            self.flagged.len(),
            self.judge.held(),
            self.judge.unverified(),
        )
    }

    /// The captures flagged so far (each reopened for a retake).
    pub fn flagged(&self) -> &BTreeSet<TargetKey> {
        &self.flagged
    }

    /// An event that can move the positioning reference happened (`run::judge`): the
    /// captures after it are held until one checks it. `moves`: the errors it can move.
    pub fn reference_event(&mut self, what: &str, moves: [bool; 6]) {
        if self.phase != Phase::Done && self.settings.judge {
            self.judge.event(what, moves);
        }
    }

    /// The head was knocked on its mount (`align::knock`) at `since` (in the order frames were
    /// read: the wall clock can step back between a capture and a knock), found only now: the
    /// frames from then on read through a turn that the live pipeline takes out from now
    /// on. The capture being averaged starts again; a capture whose frames reach past the
    /// knock is flagged (out of the store when it was stored) and retaken; the captures
    /// after it are checked like those after any event that can move the reference.
    pub fn knocked(&mut self, since: FrameTime, what: &str) {
        if self.phase == Phase::Done {
            return;
        }
        self.restart_average();
        let hit: Vec<Capture> = self
            .recent
            .iter()
            .filter(|(c, last)| *last >= since && self.done.contains(&TargetKey::of(c)))
            .map(|(c, _)| *c)
            .collect();
        self.recent.retain(|(_, last)| *last < since);
        // Those before it read through turns this one changed: the next return cannot tell
        // what they read through, and their u stays as stated.
        self.turns_pending.clear();
        let mut decisions = Vec::new();
        for c in hit {
            let key = TargetKey::of(&c);
            // Without the judge every capture was stored as it came.
            let stored = if self.settings.judge {
                self.judge.withdraw(key)
            } else {
                Some(true)
            };
            if let Some(stored) = stored {
                decisions.push(Decision::Flag {
                    reason: format!(
                        "{key} {}: {what}, found after this capture was taken, reached its frames: retaken",
                        c.direction.sign()
                    ),
                    capture: c,
                    stored,
                });
            }
        }
        self.apply(decisions);
        self.reference_event(what, super::judge::MOVES_ALL);
    }

    /// A return to the zero agreed (`service::measure::Measure::take_bounded`): the turns
    /// found since the one before are bounded by what it read, and `var_at(target)` is their
    /// variance now at a target (internal units²). The captures taken since the last knock
    /// read through those very turns (a knock between would have been found, or the return
    /// would not agree): the turns' part of each one's u² is replaced by the bound. A capture
    /// the judge holds is stored with it; one stored is restated (`RunAction::Restated`).
    /// `what` says what the return read.
    pub fn turns_bounded(&mut self, var_at: impl Fn(f64) -> Errors6, what: &str) {
        for (c, was) in std::mem::take(&mut self.turns_pending) {
            let key = TargetKey::of(&c);
            let now = var_at(c.target_mm).to_array();
            let change: [f64; 6] = std::array::from_fn(|k| now[k] - was[k]);
            let restated = if self.settings.judge {
                self.judge.restate(key, c.unix_us, &change)
            } else {
                Some((
                    Capture {
                        u: super::judge::restated_u(&c.u, &change),
                        ..c
                    },
                    c.u,
                    true,
                ))
            };
            let Some((now, was, stored)) = restated else {
                continue;
            };
            if let Some((r, _)) = self
                .recent
                .iter_mut()
                .find(|(r, _)| TargetKey::of(r) == key && r.unix_us == c.unix_us)
            {
                r.u = now.u;
            }
            if stored {
                self.actions.push_back(RunAction::Restated {
                    capture: now,
                    reason: format!(
                        "{key} {}: u stated again by the return to the zero that agreed ({what}): {}",
                        c.direction.sign(),
                        u_change(&was, &now.u)
                    ),
                });
            }
        }
    }

    /// Carry out the judge's decisions: stored captures go out, flagged ones are reopened
    /// for the make-up pass.
    fn apply(&mut self, decisions: Vec<Decision>) {
        for d in decisions {
            match d {
                Decision::Store(c) => self.actions.push_back(RunAction::Captured(c)),
                Decision::Flag {
                    capture,
                    reason,
                    stored,
                } => {
                    self.done.remove(&TargetKey::of(&capture));
                    self.flagged.insert(TargetKey::of(&capture));
                    self.actions.push_back(RunAction::Flagged {
                        capture,
                        reason,
                        stored,
                    });
                }
                Decision::ShiftZero { by, reason } => {
                    self.actions.push_back(RunAction::ShiftZero { by, reason })
                }
            }
        }
    }

    /// The keys still missing, in cycle order.
    pub fn missing(&self) -> Vec<TargetKey> {
        self.plan
            .steps()
            .iter()
            .filter_map(|s| s.target)
            .filter(|k| !self.done.contains(k))
            .collect()
    }

    /// Whether every capture is taken.
    pub fn is_finished(&self) -> bool {
        self.phase == Phase::Done
    }

    /// The next action.
    pub fn poll_action(&mut self) -> Option<RunAction> {
        self.actions.pop_front()
    }

    fn set_nominal(&mut self, n: Option<f64>) {
        if self.nominal != n {
            self.nominal = n;
            self.actions.push_back(RunAction::SetNominal(n));
        }
    }

    /// The target nearest to `p` within the tolerance.
    fn target_at(&self, p: f64) -> Option<(u32, f64)> {
        self.plan
            .targets
            .iter()
            .enumerate()
            .map(|(i, &t)| (i as u32, t))
            .filter(|(_, t)| (p - t).abs() <= self.settings.target_tolerance_mm)
            .min_by(|a, b| (p - a.1).abs().total_cmp(&(p - b.1).abs()))
    }

    /// The side the carriage came from to rest at `p`: the last remembered position farther
    /// than the target tolerance, judged on the median of `APPROACH_MEDIAN` consecutive
    /// positions; with it, that position. A single position is not trusted: while the
    /// follower still hunts after a step, PSD2's stitch (the follower's last reported encoder
    /// position against a frame of another instant) reads the resting carriage up to a
    /// millimetre off for a sample, and one such spike on the far side must not turn an
    /// approach from above into one from below.
    fn approach(&self, p: f64) -> Option<(Direction, f64)> {
        let tol = self.settings.target_tolerance_mm;
        let xs: Vec<f64> = self.history.iter().map(|(_, x)| *x).collect();
        let n = APPROACH_MEDIAN.min(xs.len());
        if n == 0 {
            return None;
        }
        (n..=xs.len())
            .rev()
            .map(|end| {
                let mut w = xs[end - n..end].to_vec();
                w.sort_by(f64::total_cmp);
                w[n / 2]
            })
            .find(|x| (x - p).abs() > tol)
            .map(|x| {
                let dir = if x < p {
                    Direction::Up
                } else {
                    Direction::Down
                };
                (dir, x)
            })
    }

    /// The capture a rest at `target_index` approached in `dir` is: the next such stop of
    /// the cycle not yet taken, or (a make-up pass, a resumed run) the first one missing.
    fn key_for(&self, target_index: u32, dir: Direction) -> Option<TargetKey> {
        let matches = |k: &TargetKey| {
            k.target_index == target_index && k.direction == dir && !self.done.contains(k)
        };
        self.cycle
            .iter()
            .enumerate()
            .skip(self.cursor)
            .find(|(_, k)| matches(k))
            .or_else(|| self.cycle.iter().enumerate().find(|(_, k)| matches(k)))
            .map(|(_, k)| *k)
    }

    /// The median of the last `APPROACH_MEDIAN` remembered positions.
    fn recent_median(&self) -> Option<f64> {
        let n = APPROACH_MEDIAN.min(self.history.len());
        if n < APPROACH_MEDIAN {
            return None;
        }
        let mut w: Vec<f64> = self.history.iter().rev().take(n).map(|(_, x)| *x).collect();
        w.sort_by(f64::total_cmp);
        Some(w[n / 2])
    }

    fn at_rest(&self, now: Instant) -> Option<f64> {
        let (first, _) = self.rest.front()?;
        if now.saturating_duration_since(*first) < self.settings.settle.mul_f64(0.9) {
            return None;
        }
        let (lo, hi) = self
            .rest
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), (_, x)| {
                (a.min(*x), b.max(*x))
            });
        (hi - lo <= 2.0 * self.settings.rest_tolerance_mm).then_some(0.5 * (lo + hi))
    }

    /// A handshake report: the CNC is at the target with this code.
    pub fn handle_at_target(&mut self, code: u32, now: Instant) {
        if self.phase == Phase::Done {
            return;
        }
        let (run, index, dir) = super::program::decode_target_code(code);
        let key = TargetKey {
            run,
            target_index: index,
            direction: dir,
        };
        if (index as usize) >= self.plan.targets.len() || run == 0 || run > self.plan.spec.runs {
            self.actions.push_back(RunAction::Failed(format!(
                "the PLC reported target code {code}, which is not in the plan"
            )));
            return;
        }
        if self.done.contains(&key) {
            // Already stored (a resumed run): acknowledge at once so the CNC goes on.
            self.actions.push_back(RunAction::Acknowledge { code });
            return;
        }
        self.set_nominal(Some(self.plan.targets[index as usize]));
        self.acc = Acc::default();
        self.phase = Phase::Averaging {
            key,
            code: Some(code),
            since: now,
        };
    }

    /// A frame estimate from the live pipeline.
    /// The stitch changed under a capture (a handover was measured): frames from before it
    /// are not averaged with those after.
    /// A pause: a capture in progress is dropped (it is taken again when the run goes on).
    pub fn interrupt(&mut self) {
        if matches!(self.phase, Phase::Averaging { .. }) {
            self.acc = Acc::default();
            self.set_nominal(None);
            self.phase = Phase::Watch;
        }
    }

    pub fn restart_average(&mut self) {
        if matches!(self.phase, Phase::Averaging { .. }) {
            self.acc = Acc::default();
        }
    }

    /// A pause (a PSD without its spot) has ended. The time paused waited for the operator,
    /// not for the machine: the progress timeout counts again from the next frame.
    pub fn pause_ended(&mut self) {
        self.restart_average();
        self.last_progress = None;
    }

    pub fn handle_sample(&mut self, s: &FrameSample, now: Instant) {
        if self.phase == Phase::Done {
            return;
        }
        self.last_progress.get_or_insert(now);
        self.rest.push_back((now, s.position_mm));
        while self
            .rest
            .front()
            .is_some_and(|(t, _)| now.saturating_duration_since(*t) > self.settings.settle)
        {
            self.rest.pop_front();
        }
        if let Some((t, x)) = self.history.back()
            && now.saturating_duration_since(*t) > APPROACH_GAP
        {
            tracing::debug!(
                last_mm = *x,
                unseen_ms = now.saturating_duration_since(*t).as_millis() as u64,
                "positions unseen: the approach is judged from the positions after the gap"
            );
            self.history.clear();
        }
        let keep = Duration::from_secs(30);
        if self
            .history
            .back()
            .is_none_or(|(t, _)| now.saturating_duration_since(*t) >= Duration::from_millis(20))
        {
            self.history.push_back((now, s.position_mm));
        }
        while self
            .history
            .front()
            .is_some_and(|(t, _)| now.saturating_duration_since(*t) > keep)
        {
            self.history.pop_front();
        }
        match self.phase.clone() {
            Phase::Done => {}
            Phase::Leaving { position } => {
                // With the judge, left only when the median of the last positions is off the
                // target: one spike of the stitch (a follower still hunting) is not a move, and
                // taken for one it filed the same stop again under the next run (issue 24).
                let off = |x: f64| (x - position).abs() > self.settings.target_tolerance_mm;
                let left = if self.settings.judge {
                    self.recent_median().is_some_and(off)
                } else {
                    off(s.position_mm)
                };
                if left {
                    tracing::debug!(from_mm = position, at_mm = s.position_mm, "left the target");
                    self.phase = Phase::Watch;
                }
            }
            Phase::Watch => {
                if self.handshake {
                    return;
                }
                let Some(p) = self.at_rest(now) else {
                    return;
                };
                let Some((index, target)) = self.target_at(p) else {
                    return;
                };
                let Some((dir, from)) = self.approach(p) else {
                    return;
                };
                let Some(key) = self.key_for(index, dir) else {
                    // Every run of this target and direction is in: nothing to do here.
                    self.phase = Phase::Leaving { position: p };
                    return;
                };
                // Frames must be decoupled at the target: restart the average from here.
                tracing::debug!(
                    at_mm = p,
                    from_mm = from,
                    ?key,
                    "at rest on a target: averaging"
                );
                self.set_nominal(Some(target));
                self.acc = Acc::default();
                self.phase = Phase::Averaging {
                    key,
                    code: None,
                    since: now,
                };
            }
            Phase::Averaging { key, code, .. } => {
                let target = self.plan.targets[key.target_index as usize];
                if s.nominal != Some(target) {
                    return; // decoupled with another nominal: wait for the switch
                }
                if code.is_none()
                    && (s.position_mm - target).abs() > self.settings.target_tolerance_mm
                {
                    // The carriage moved off before the average was complete: start over.
                    tracing::debug!(
                        ?key,
                        at_mm = s.position_mm,
                        frames = self.acc.n,
                        "moved off the target while averaging"
                    );
                    self.set_nominal(None);
                    self.phase = Phase::Watch;
                    return;
                }
                if code.is_none() && self.at_rest(now).is_none() {
                    tracing::debug!(
                        ?key,
                        frames = self.acc.n,
                        "no longer at rest while averaging"
                    );
                    self.set_nominal(None);
                    self.phase = Phase::Watch;
                    return;
                }
                self.accumulate(s);
                if self.acc.n >= self.settings.frames {
                    self.finish_capture(key, code, target, s.position_mm, now);
                }
            }
        }
    }

    fn accumulate(&mut self, s: &FrameSample) {
        let a = &mut self.acc;
        if a.n == 0 {
            a.first_us = s.unix_us;
        }
        a.last = Some(FrameTime::Read(s.at));
        a.n += 1;
        let (e, v, sv) = (
            s.errors.to_array(),
            s.var.to_array(),
            s.stitch_var.to_array(),
        );
        a.stitch_var = sv;
        a.turns_var = s.turns_var.map(|v| v.to_array());
        for k in 0..6 {
            a.sum[k] += e[k];
            a.sum_sq[k] += e[k] * e[k];
            a.var[k] += v[k];
        }
        if let Some(t) = s.material_c {
            a.material.0 += t;
            a.material.1 += 1;
        }
        if let Some(t) = s.air_c {
            a.air.0 += t;
            a.air.1 += 1;
        }
    }

    fn finish_capture(
        &mut self,
        key: TargetKey,
        code: Option<u32>,
        target: f64,
        position: f64,
        now: Instant,
    ) {
        let a = self.acc;
        let n = a.n as f64;
        let mean: [f64; 6] = std::array::from_fn(|k| a.sum[k] / n);
        let frame_sd: [f64; 6] = std::array::from_fn(|k| {
            if a.n < 2 {
                0.0
            } else {
                ((a.sum_sq[k] - n * mean[k] * mean[k]) / (n - 1.0))
                    .max(0.0)
                    .sqrt()
            }
        });
        // Standard uncertainty of the mean: the noise (model variance or scatter, whichever is
        // larger) over n frames, plus the stitching, which averaging does not reduce.
        let u: [f64; 6] = std::array::from_fn(|k| {
            let noise = (a.var[k] / n).max(frame_sd[k] * frame_sd[k]);
            (noise / n + a.stitch_var[k]).sqrt()
        });
        let avg = |(s, c): (f64, usize)| (c > 0).then(|| s / c as f64);
        let capture = Capture {
            run: key.run,
            target_index: key.target_index,
            target_mm: target,
            direction: key.direction,
            errors: Errors6::from_array(mean),
            frame_sd: Errors6::from_array(frame_sd),
            u: Errors6::from_array(u),
            frames: a.n as u32,
            material_c: avg(a.material),
            air_c: avg(a.air),
            unix_us: a.first_us,
        };
        self.done.insert(key);
        if let Some(v) = a.turns_var {
            self.turns_pending.push((capture, v));
        }
        self.recent
            .push_back((capture, a.last.unwrap_or(FrameTime::Kept(a.first_us))));
        if self.recent.len() > RECENT {
            self.recent.pop_front();
        }
        if let Some(i) = self.cycle.iter().position(|k| *k == key) {
            self.cursor = i + 1;
        }
        if self.settings.judge {
            let decisions = self.judge.offer(capture);
            self.apply(decisions);
        } else {
            self.actions.push_back(RunAction::Captured(capture));
        }
        if let Some(code) = code {
            self.actions.push_back(RunAction::Acknowledge { code });
        }
        self.last_progress = Some(now);
        self.acc = Acc::default();
        self.rest.clear();
        // Off the target, frames are decoupled at their measured travel again: with the
        // target's nominal they would read as positions near it while the carriage moves on.
        self.set_nominal(None);
        if self.done.len() >= self.total && self.settings.judge {
            // Every capture in (stored or held): the judge's review may reopen some.
            let decisions = self.judge.review();
            self.apply(decisions);
        }
        if self.done.len() >= self.total {
            self.phase = Phase::Done;
            self.actions.push_back(RunAction::Finished);
        } else {
            self.phase = if code.is_some() {
                Phase::Watch
            } else {
                Phase::Leaving { position }
            };
        }
    }

    /// Check the progress timeout.
    pub fn handle_timeout(&mut self, now: Instant) {
        if self.phase == Phase::Done {
            return;
        }
        if let Some(t) = self.last_progress
            && now.saturating_duration_since(t) > self.settings.timeout
        {
            let missing = self.missing();
            let next = missing
                .first()
                .map(|k| format!(", the next {}", k.describe(&self.plan)))
                .unwrap_or_default();
            self.actions.push_back(RunAction::Failed(format!(
                "no capture for {:.0} s; {} captures missing{next}",
                self.settings.timeout.as_secs_f64(),
                missing.len(),
            )));
            self.last_progress = Some(now);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::run::plan::PlanSpec;
    use crate::sim::Rng;
    use std::collections::BTreeMap;

    fn plan() -> Plan {
        Plan::new(PlanSpec {
            axis: "X".into(),
            start_mm: 0.0,
            end_mm: 100.0,
            targets: 5,
            runs: 2,
            overrun_mm: 3.0,
            dwell_s: 1.0,
            feed_mm_min: 3000.0,
            lead_mm: 0.0,
            reference_mm: None,
        })
        .unwrap()
    }

    /// Feed the machine a carriage running the plan's cycle at 50 mm/s with 2 ms frames.
    /// The measured position is the truth plus noise; errors are a function of position
    /// (dy = 1 µm per 10 mm) so captures can be checked.
    struct Feed {
        t0: Instant,
        now: Instant,
        nominal: Option<f64>,
        rng: Rng,
        /// The turns' part of each frame's systematic variance, while turns found are pending.
        turns_var: Option<Errors6>,
        /// The captures restated, as they came.
        restated: Vec<Capture>,
        /// How far the wall clock was stepped (µs; back is negative).
        wall_step_us: i64,
    }

    impl Feed {
        /// The wall clock at `t` (µs since the feed began, plus any step).
        fn wall_us(&self, t: Instant) -> i64 {
            (t - self.t0).as_micros() as i64 + self.wall_step_us
        }

        /// The frame read `us` µs after the feed began, in the order frames were read.
        fn order_at(&self, us: i64) -> FrameTime {
            FrameTime::Read(self.t0 + Duration::from_micros(us as u64))
        }

        fn sample(&mut self, pos: f64) -> FrameSample {
            let dy = 1e-4 * pos + self.rng.gauss(1e-3);
            FrameSample {
                at: self.now,
                unix_us: self.wall_us(self.now),
                position_mm: pos + self.rng.gauss(1e-3),
                nominal: self.nominal,
                errors: Errors6 {
                    dy,
                    ..Errors6::ZERO
                },
                var: Errors6::from_array([1e-6; 6]),
                stitch_var: Errors6::from_array(std::array::from_fn(|k| {
                    1e-8 + self.turns_var.map_or(0.0, |v| v.to_array()[k])
                })),
                turns_var: self.turns_var,
                material_c: Some(20.5),
                air_c: None,
            }
        }

        fn run(
            &mut self,
            m: &mut RunMachine,
            moves: &[(f64, f64)],
            skip: Option<(usize, usize)>,
        ) -> Vec<Capture> {
            let mut out = Vec::new();
            let mut pos = moves[0].0;
            for (i, &(to, dwell)) in moves.iter().enumerate() {
                let skipped = skip.is_some_and(|(a, b)| i >= a && i < b);
                // Move at 50 mm/s, then dwell.
                while (to - pos).abs() > 1e-9 {
                    pos += (to - pos).clamp(-0.1, 0.1);
                    self.step(m, pos, skipped, &mut out);
                }
                for _ in 0..(dwell / 0.002) as usize {
                    self.step(m, pos, skipped, &mut out);
                }
            }
            out
        }

        fn step(&mut self, m: &mut RunMachine, pos: f64, skipped: bool, out: &mut Vec<Capture>) {
            self.now += Duration::from_millis(2);
            if !skipped {
                let s = self.sample(pos);
                m.handle_sample(&s, self.now);
            }
            while let Some(a) = m.poll_action() {
                match a {
                    RunAction::SetNominal(n) => self.nominal = n,
                    RunAction::Captured(c) => out.push(c),
                    RunAction::Restated { capture, .. } => self.restated.push(capture),
                    _ => {}
                }
            }
        }
    }

    fn cycle(p: &Plan) -> Vec<(f64, f64)> {
        p.steps()
            .iter()
            .map(|s| {
                (
                    s.position_mm,
                    if s.target.is_some() {
                        p.spec.dwell_s
                    } else {
                        0.2
                    },
                )
            })
            .collect()
    }

    /// A make-up pass over `missing`: each target approached from 2 mm on its side, then a
    /// 1 s dwell on it.
    fn makeup(p: &Plan, missing: &[TargetKey]) -> Vec<(f64, f64)> {
        missing
            .iter()
            .flat_map(|k| {
                let t = p.targets[k.target_index as usize];
                let from = match k.direction {
                    Direction::Up => t - 2.0,
                    Direction::Down => t + 2.0,
                };
                [(from, 0.2), (t, 1.0)]
            })
            .collect()
    }

    /// A machine for `p` with the default capture settings and nothing captured yet.
    fn fresh(p: &Plan) -> RunMachine {
        RunMachine::new(
            p.clone(),
            CaptureSettings::default(),
            false,
            BTreeSet::new(),
        )
    }

    fn feed() -> Feed {
        let t0 = crate::util::clock::now();
        Feed {
            t0,
            now: t0,
            nominal: None,
            rng: Rng::new(8),
            turns_var: None,
            restated: Vec::new(),
            wall_step_us: 0,
        }
    }

    #[test]
    fn stability_capture_takes_every_target_once_in_order() {
        let p = plan();
        let mut m = fresh(&p);
        let caps = feed().run(&mut m, &cycle(&p), None);
        assert!(m.is_finished());
        assert_eq!(caps.len(), p.capture_count());
        let keys: Vec<TargetKey> = caps.iter().map(TargetKey::of).collect();
        let expected: Vec<TargetKey> = p.steps().iter().filter_map(|s| s.target).collect();
        assert_eq!(keys, expected);
        for c in &caps {
            assert_eq!(c.frames, 150);
            // dy = 1e-4·position, measured with 1 µm noise over 150 frames.
            assert!((c.errors.dy - 1e-4 * c.target_mm).abs() < 5.0 * 1e-3 / 150f64.sqrt());
            assert!((c.u.dy - (1e-6 / 150.0 + 1e-8f64).sqrt()).abs() < 2e-5);
            assert_eq!(c.material_c, Some(20.5));
        }
    }

    #[test]
    fn a_missed_stop_does_not_shift_the_run_numbers_after_it() {
        let p = plan();
        let steps = cycle(&p);
        let mut m = fresh(&p);
        // The frames of the first run's second target are lost (the carriage still stops).
        let missed = p
            .steps()
            .iter()
            .enumerate()
            .filter(|(_, s)| s.target.is_some())
            .nth(1)
            .map(|(i, _)| i)
            .expect("a second target");
        let caps = feed().run(&mut m, &steps, Some((missed, missed + 1)));
        let got: Vec<TargetKey> = caps.iter().map(TargetKey::of).collect();
        let expected: Vec<TargetKey> = p.steps().iter().filter_map(|s| s.target).collect();
        let lost = p.steps()[missed].target.expect("a target stop");
        let want: Vec<TargetKey> = expected.into_iter().filter(|k| *k != lost).collect();
        assert_eq!(got, want, "every later capture keeps its own run number");
        assert_eq!(m.missing(), vec![lost]);
    }

    #[test]
    fn a_dwell_too_short_is_refused_with_the_least_that_works() {
        // Issue 26: a demo with a 1 s dwell mapped its follower for minutes and then took no
        // capture. 0.25 s settling + 0.4 s of the follower's rest and settling + 150 frames
        // at 500 Hz (0.3 s) + 0.5 s = 1.45 s.
        let c = CaptureSettings::default();
        let rest = Duration::from_millis(400);
        assert!((c.min_dwell(500.0, rest).as_secs_f64() - 1.45).abs() < 1e-9);
        let mut p = plan();
        p.spec.dwell_s = 1.4;
        let why = c.check_dwell(&p, 500.0, rest).unwrap_err();
        assert!(
            why.starts_with("a dwell of 1.4 s is too short to capture: use at least 1.45 s"),
            "{why}"
        );
        p.spec.dwell_s = 1.45;
        assert_eq!(c.check_dwell(&p, 500.0, rest), Ok(()));
        // Fewer frames a second need a longer dwell.
        assert!((c.min_dwell(200.0, rest).as_secs_f64() - 1.9).abs() < 1e-9);
    }

    #[test]
    fn an_approach_not_seen_is_not_guessed_from_before_the_gap() {
        // The storm's mislabel (issue 24): the carriage leaves the first target upward, PSD2
        // loses its spot at 30 mm, and unseen the carriage goes back to the overrun below
        // and up onto the first target. The rest seen there is no approach from above.
        let p = plan();
        let mut m = fresh(&p);
        let (t0, dwell) = (p.targets[0], p.spec.dwell_s);
        let below = t0 - p.spec.overrun_mm;
        let moves = [
            (below, 0.2),
            (t0, dwell),
            (t0 + 30.0, 0.0),
            (below, 0.2),
            (t0, 0.0),
            (t0, dwell),
        ];
        let caps = feed().run(&mut m, &moves, Some((3, 5)));
        let keys: Vec<TargetKey> = caps.iter().map(TargetKey::of).collect();
        let first = TargetKey {
            run: 1,
            target_index: 0,
            direction: Direction::Up,
        };
        assert_eq!(
            keys,
            vec![first],
            "only the capture whose approach was seen"
        );
        assert!(m.missing().contains(&TargetKey {
            direction: Direction::Down,
            ..first
        }));
        // Seen, the same motion is the next run's upward approach.
        let mut m = fresh(&p);
        let caps = feed().run(&mut m, &moves, None);
        let keys: Vec<TargetKey> = caps.iter().map(TargetKey::of).collect();
        assert_eq!(keys, vec![first, TargetKey { run: 2, ..first }]);
    }

    #[test]
    fn spikes_at_the_target_do_not_turn_the_approach() {
        // The carriage comes down onto a target; while the follower hunts, the stitched
        // position jumps 0.8 mm below the target for one history sample at a time, the last
        // one well after the carriage stopped. The capture is still the downward one.
        let p = plan();
        let mut m = fresh(&p);
        let mut f = feed();
        let (t3, beyond) = (p.targets[3], p.spec.end_mm + p.spec.overrun_mm);
        let mut out = Vec::new();
        let mut pos = beyond;
        for _ in 0..100 {
            f.step(&mut m, pos, false, &mut out);
        }
        while pos > t3 {
            pos = (pos - 0.1).max(t3);
            f.step(&mut m, pos, false, &mut out);
        }
        for k in 0..700 {
            // Three spikes of 10 frames (one history sample each), 100 ms apart, within the
            // first 300 ms of the rest.
            let spike = k < 150 && k % 50 < 10;
            let s = f.sample(if spike { t3 - 0.8 } else { t3 });
            f.now += Duration::from_millis(2);
            m.handle_sample(&s, f.now);
            while let Some(a) = m.poll_action() {
                match a {
                    RunAction::SetNominal(n) => f.nominal = n,
                    RunAction::Captured(c) => out.push(c),
                    _ => {}
                }
            }
        }
        let keys: Vec<TargetKey> = out.iter().map(TargetKey::of).collect();
        assert_eq!(
            keys,
            vec![TargetKey {
                run: 1,
                target_index: 3,
                direction: Direction::Down
            }]
        );
    }

    #[test]
    fn a_knock_found_after_a_restart_reaches_back_to_the_captures_stored_before_it() {
        for judge in [false, true] {
            let p = plan();
            let steps = cycle(&p);
            let settings = CaptureSettings {
                judge,
                ..CaptureSettings::default()
            };
            let mut m = RunMachine::new(p.clone(), settings, false, BTreeSet::new());
            let stored = feed().run(&mut m, &steps[..8], None);
            assert!(stored.len() >= 4, "{} captures", stored.len());
            // The service restarts; at the first return to the zero the head is found
            // turned since it last agreed, which was before the third capture.
            let mut resumed = RunMachine::resumed(p.clone(), settings, false, stored.clone());
            resumed.knocked(
                FrameTime::Kept(stored[2].unix_us - 1),
                "a knock found after the restart",
            );
            let mut flagged = BTreeSet::new();
            while let Some(a) = resumed.poll_action() {
                if let RunAction::Flagged {
                    capture, stored, ..
                } = a
                {
                    assert!(stored, "judge {judge}: it was in the store");
                    flagged.insert(TargetKey::of(&capture));
                }
            }
            let after: BTreeSet<TargetKey> = stored[2..].iter().map(TargetKey::of).collect();
            assert_eq!(flagged, after, "judge {judge}");
            for c in &stored[..2] {
                assert!(!resumed.missing().contains(&TargetKey::of(c)));
            }
            for k in &after {
                assert!(resumed.missing().contains(k), "judge {judge}: {k} retaken");
            }
        }
    }

    #[test]
    fn a_knock_found_after_a_capture_s_last_frames_has_it_retaken() {
        for judge in [false, true] {
            let p = plan();
            let steps = cycle(&p);
            let settings = CaptureSettings {
                judge,
                ..CaptureSettings::default()
            };
            let mut m = RunMachine::new(p.clone(), settings, false, BTreeSet::new());
            let mut f = feed();
            let first = f.run(&mut m, &steps[..6], None);
            assert!(first.len() >= 2, "{} captures", first.len());
            let (before, last) = (first[first.len() - 2], first[first.len() - 1]);
            // The knock lies within the last capture's 150 frames (0.3 s from its first).
            m.knocked(f.order_at(last.unix_us + 200_000), "a knock");
            let mut flagged = Vec::new();
            while let Some(a) = m.poll_action() {
                if let RunAction::Flagged {
                    capture, stored, ..
                } = a
                {
                    flagged.push((TargetKey::of(&capture), stored));
                }
            }
            assert_eq!(
                flagged,
                vec![(TargetKey::of(&last), true)],
                "judge {judge}: the last capture only, out of the store"
            );
            assert!(m.missing().contains(&TargetKey::of(&last)));
            assert!(!m.missing().contains(&TargetKey::of(&before)));
            // A knock found after a capture's last frames touches none.
            let mut m2 = RunMachine::new(p.clone(), settings, false, BTreeSet::new());
            let mut f2 = feed();
            let caps = f2.run(&mut m2, &steps[..6], None);
            let last2 = caps[caps.len() - 1];
            m2.knocked(f2.order_at(last2.unix_us + 400_000), "a knock");
            while let Some(a) = m2.poll_action() {
                assert!(
                    !matches!(a, RunAction::Flagged { .. }),
                    "judge {judge}: {a:?}"
                );
            }
            // The run goes on: the rest of the cycle and a make-up pass over what is
            // missing finish it, every key once.
            let rest = f.run(&mut m, &steps[6..], None);
            let missing = m.missing();
            let retaken = f.run(&mut m, &makeup(&p, &missing), None);
            assert!(m.is_finished(), "judge {judge}: missing {:?}", m.missing());
            let keys: BTreeSet<TargetKey> = first[..first.len() - 1]
                .iter()
                .chain(&rest)
                .chain(&retaken)
                .map(TargetKey::of)
                .collect();
            assert_eq!(keys.len(), p.capture_count(), "judge {judge}");
            assert!(
                retaken
                    .iter()
                    .any(|c| TargetKey::of(c) == TargetKey::of(&last))
            );
        }
    }

    /// The wall clock stepped back an hour between a knock and the captures it reached (an
    /// NTP correction, a clock set by hand): they are still after it in the order frames were
    /// read, and retaken. In a storm (twin 29, faults 34) a knock dated by the wall clock
    /// missed three captures read through a 13 µrad turn, dx up to 9 µm off.
    #[test]
    fn a_knock_reaches_the_captures_after_it_whatever_the_wall_clock_did() {
        for judge in [false, true] {
            let p = plan();
            let steps = cycle(&p);
            let settings = CaptureSettings {
                judge,
                ..CaptureSettings::default()
            };
            let mut m = RunMachine::new(p.clone(), settings, false, BTreeSet::new());
            let mut f = feed();
            let first = f.run(&mut m, &steps[..4], None);
            let knock = FrameTime::Read(f.now);
            let knock_us = f.wall_us(f.now);
            f.wall_step_us = -3_600_000_000;
            let after = f.run(&mut m, &steps[4..8], None);
            assert!(after.len() >= 2, "judge {judge}: {} captures", after.len());
            assert!(
                after.iter().all(|c| c.unix_us < knock_us),
                "the wall clock says they came before the knock"
            );
            m.knocked(knock, "a knock found at the zero");
            let mut flagged = BTreeSet::new();
            while let Some(a) = m.poll_action() {
                if let RunAction::Flagged { capture, .. } = a {
                    flagged.insert(TargetKey::of(&capture));
                }
            }
            let reached: BTreeSet<TargetKey> = after.iter().map(TargetKey::of).collect();
            assert_eq!(flagged, reached, "judge {judge}");
            for c in &first {
                assert!(!m.missing().contains(&TargetKey::of(c)), "judge {judge}");
            }
        }
    }

    /// Captures taken after a knock carry the turns' own variance; the return that agrees
    /// bounds it, and each of them is stated again: its u² less what the turns added, plus the
    /// bound at its target. Stored ones are restated, held ones stored with it; those before
    /// the knock, and those before a later knock, keep their u.
    #[test]
    fn a_return_that_agrees_states_again_the_u_of_the_captures_read_through_the_turns() {
        let pending = Errors6::from_array([4e-8, 0.0, 9e-8, 1e-12, 0.0, 4e-12]);
        // The bound grows along the travel, as a turn's effect does.
        let bound = |t: f64| Errors6::from_array([1e-10 * (1.0 + t), 0.0, 2e-9, 1e-14, 0.0, 2e-14]);
        for judge in [false, true] {
            let p = plan();
            let steps = cycle(&p);
            let settings = CaptureSettings {
                judge,
                ..CaptureSettings::default()
            };
            // The knock after the sixth stop; the return after the twelfth.
            let knocked_run = |later_knock: bool| {
                let mut m = RunMachine::new(p.clone(), settings, false, BTreeSet::new());
                let mut f = feed();
                let mut out = f.run(&mut m, &steps[..6], None);
                let before: Vec<Capture> = out.clone();
                m.knocked(FrameTime::Read(f.now), "a knock at rest");
                f.turns_var = Some(pending);
                out.extend(f.run(&mut m, &steps[6..12], None));
                // The captures as taken since the knock: their u carries the pending variance.
                let taken: BTreeMap<(TargetKey, i64), Errors6> = m
                    .turns_pending
                    .iter()
                    .map(|(c, _)| ((TargetKey::of(c), c.unix_us), c.u))
                    .collect();
                if later_knock {
                    m.knocked(FrameTime::Read(f.now), "another knock");
                    assert!(m.turns_pending.is_empty());
                }
                f.turns_var = None;
                m.turns_bounded(bound, "pitch +0.10 ± 0.05 µrad");
                assert!(m.turns_pending.is_empty());
                out.extend(f.run(&mut m, &steps[11..], None));
                let missing = m.missing();
                if !missing.is_empty() {
                    out.extend(f.run(&mut m, &makeup(&p, &missing), None));
                }
                assert!(m.is_finished(), "judge {judge}: missing {:?}", m.missing());
                (before, taken, out, f.restated)
            };
            let (before, taken, stored, restated) = knocked_run(false);
            assert!(
                taken.len() >= 3,
                "judge {judge}: {} after the knock",
                taken.len()
            );
            // Each capture since the knock ends with its u stated again: restated once when
            // it was stored before the return, stored with it when held until after.
            let mut last: BTreeMap<(TargetKey, i64), Errors6> = BTreeMap::new();
            let mut times: BTreeMap<(TargetKey, i64), usize> = BTreeMap::new();
            for c in stored.iter().chain(&restated) {
                last.insert((TargetKey::of(c), c.unix_us), c.u);
            }
            for c in &restated {
                *times.entry((TargetKey::of(c), c.unix_us)).or_default() += 1;
            }
            assert!(
                times.values().all(|n| *n == 1),
                "judge {judge}: restated twice"
            );
            for (id, was) in &taken {
                let Some(u) = last.get(id) else {
                    // Flagged and retaken since: the retake has its own u.
                    continue;
                };
                let (w, u, b, v) = (
                    was.to_array(),
                    u.to_array(),
                    bound(id.0.target_index as f64 * 25.0).to_array(),
                    pending.to_array(),
                );
                for k in 0..6 {
                    let want = (w[k] * w[k] - v[k] + b[k]).sqrt();
                    assert!(
                        (u[k] - want).abs() <= 1e-9 * want.max(1e-12),
                        "judge {judge}: {} error {k}: u {:e}, want {want:e} (was {:e})",
                        id.0,
                        u[k],
                        w[k]
                    );
                }
                assert!(u[0] < w[0] && u[2] < w[2], "judge {judge}: sharper");
            }
            assert!(
                taken.keys().filter(|id| last.contains_key(id)).count() >= 3,
                "judge {judge}: the captures since the knock are kept"
            );
            if !judge {
                assert_eq!(restated.len(), taken.len(), "all stored as they came");
            }
            // Those before the knock are not touched.
            assert!(restated.iter().all(|c| !before.contains(c)));
            // Through turns a later knock changed, the captures keep their u as taken.
            let (_, taken, stored, restated) = knocked_run(true);
            assert!(
                restated.is_empty(),
                "judge {judge}: restated after a later knock"
            );
            for c in &stored {
                if let Some(was) = taken.get(&(TargetKey::of(c), c.unix_us)) {
                    assert_eq!(c.u, *was, "judge {judge}: {}", TargetKey::of(c));
                }
            }
        }
    }

    #[test]
    fn resumed_run_takes_what_is_missing_and_lists_what_was_passed() {
        let p = plan();
        let steps = cycle(&p);
        // First service: sees the first 8 stops only.
        let mut m = fresh(&p);
        let mut f = feed();
        let first = f.run(&mut m, &steps[..8], None);
        let done: BTreeSet<TargetKey> = first
            .iter()
            .map(|c| TargetKey {
                run: c.run,
                target_index: c.target_index,
                direction: c.direction,
            })
            .collect();
        // The service is down while the CNC does stops 8..10; a new machine resumes after.
        let mut m2 = RunMachine::new(p.clone(), CaptureSettings::default(), false, done.clone());
        let second = f.run(&mut m2, &steps[8..], Some((0, 2)));
        let mut all: Vec<TargetKey> = done.iter().copied().collect();
        all.extend(second.iter().map(|c| TargetKey {
            run: c.run,
            target_index: c.target_index,
            direction: c.direction,
        }));
        let unique: BTreeSet<TargetKey> = all.iter().copied().collect();
        assert_eq!(unique.len(), all.len(), "no capture twice");
        let missing = m2.missing();
        assert_eq!(missing.len() + all.len(), p.capture_count());
        assert!(!missing.is_empty() && missing.len() <= 2, "{missing:?}");
        // A make-up pass over the missing targets completes the run.
        let third = f.run(&mut m2, &makeup(&p, &missing), None);
        assert_eq!(third.len(), missing.len());
        assert!(m2.is_finished());
    }

    #[test]
    fn handshake_capture_and_acknowledge() {
        let p = plan();
        let mut m = RunMachine::new(
            p.clone(),
            CaptureSettings {
                frames: 10,
                ..CaptureSettings::default()
            },
            true,
            BTreeSet::new(),
        );
        let mut f = feed();
        let code = crate::run::program::target_code(1, 2, Direction::Up);
        m.handle_at_target(code, f.now);
        assert_eq!(
            m.poll_action(),
            Some(RunAction::SetNominal(Some(p.targets[2])))
        );
        f.nominal = Some(p.targets[2]);
        let mut acts = Vec::new();
        for _ in 0..10 {
            f.now += Duration::from_millis(2);
            let s = f.sample(p.targets[2]);
            m.handle_sample(&s, f.now);
            while let Some(a) = m.poll_action() {
                acts.push(a);
            }
        }
        assert!(matches!(acts[0], RunAction::Captured(c) if c.target_index == 2 && c.run == 1));
        assert_eq!(acts[1], RunAction::Acknowledge { code });
        // The same code again (a resumed PLC) is acknowledged without a second capture.
        m.handle_at_target(code, f.now);
        assert_eq!(m.poll_action(), Some(RunAction::Acknowledge { code }));
        m.handle_at_target(99_999, f.now);
        assert!(matches!(m.poll_action(), Some(RunAction::Failed(_))));
    }

    /// A machine on `plan()` whose progress timeout is 5 s.
    fn with_a_5_s_timeout() -> RunMachine {
        RunMachine::new(
            plan(),
            CaptureSettings {
                timeout: Duration::from_secs(5),
                ..CaptureSettings::default()
            },
            false,
            BTreeSet::new(),
        )
    }

    /// Whether the actions pending include a failure (drains them).
    fn failed(m: &mut RunMachine) -> bool {
        let mut failed = false;
        while let Some(a) = m.poll_action() {
            failed |= matches!(a, RunAction::Failed(_));
        }
        failed
    }

    #[test]
    fn timeout_fails_the_run() {
        let mut m = with_a_5_s_timeout();
        let mut f = feed();
        let s = f.sample(50.0);
        m.handle_sample(&s, f.now);
        m.handle_timeout(f.now + Duration::from_secs(6));
        assert!(failed(&mut m));
    }

    #[test]
    fn a_pause_longer_than_the_timeout_does_not_fail_the_run() {
        let mut m = with_a_5_s_timeout();
        let mut f = feed();
        let s = f.sample(50.0);
        m.handle_sample(&s, f.now);
        // Paused 60 s (no samples reach the machine), then the spot is back.
        m.interrupt();
        m.pause_ended();
        let later = f.now + Duration::from_secs(60);
        m.handle_sample(&s, later);
        m.handle_timeout(later + Duration::from_secs(4));
        assert!(!failed(&mut m), "failed after a pause");
        // Still stalled 5 s after the pause: that fails.
        m.handle_timeout(later + Duration::from_secs(6));
        assert!(failed(&mut m));
    }
}
