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
mod tests;
