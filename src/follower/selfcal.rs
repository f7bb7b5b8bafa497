//! The stop-and-go self-calibration as a procedure (DESIGN §4), sans-I/O: the plan of
//! carriage stops, the dwell each stop needs, and the collection of the follower's steps
//! from the tracker's handover records, up to the map ([`super::build`]). The service
//! (`service::follower_map`, a part program on the CNC) and the virtual-time lab
//! (`sim::follower_cal`, the lab's carriage) drive the same plan and the same collector;
//! time is an argument.
//!
//! **The plan.** The carriage first comes to the span's start through a lead-in point
//! [`LEAD_IN_MM`] above it, then steps `step_mm` at a time over the span and rests at each
//! stop: passes alternate up and down, and every `probe_every` stops of a pass it steps back
//! and forth once, so the follower reverses (the reversal error) all along the travel. Each
//! stop after the start is one follower handover with the spot fixed in space.
//!
//! **The collection.** Before the start the tracker follows as it usually does, with the
//! overlap strategy (the approach may come from anywhere, so a long move must be followed
//! with the usual margin to PSD2's edge); the lead-in's last leg, a move of −[`LEAD_IN_MM`] followed by the encoder, arms the
//! collector, and from then on the tracker runs with the procedure's settings
//! ([`Collector::tracking`]: overlap, the procedure's averaging, an edge beyond one step) and
//! every handover record is one stop: an optical one is kept as a [`Step`], an encoder-kind
//! one (the carriage moved during the handover, the after-window was not steady) counts as
//! skipped. A lead-in record seen again before the first stop (an approach from further up)
//! arms the collector again.
//!
//! **The dwell.** At each stop the carriage must rest through the tracker's rest detection,
//! the averaging before the step, the follower's move and settle, and the averaging after it
//! ([`Timing::dwell_s`]).

use super::{Certificate, FollowerMap, MapError, MapSettings, Step, build};
use crate::track::{HandoverRecord, Strategy, TrackSettings};
use crate::util::range::{self, POSITION_MM};
use serde::{Deserialize, Serialize};
use std::time::{Duration, Instant};
use thiserror::Error;

/// The lead-in: the carriage comes to the start from this far above it (mm). More than the
/// tracker's edge (PSD2's half-width is 4.5 mm), so its last leg is always followed by the
/// encoder and recorded as such: the record that arms the collector.
pub const LEAD_IN_MM: f64 = 12.0;

/// A record's encoder displacement within this of −[`LEAD_IN_MM`] is the lead-in's (mm): the
/// follower re-centres the spot within the tracker's follow band (0.3 mm) after following.
const LEAD_IN_TOLERANCE_MM: f64 = 1.0;

/// The carriage's step between stops (mm): above this, and at most [`MAX_STEP_MM`] (PSD2's
/// half-width less a margin: the spot must stay on it at every stop).
pub const MIN_STEP_MM: f64 = 0.5;
pub const MAX_STEP_MM: f64 = 4.0;

/// How the stop-and-go runs.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Spec {
    /// The carriage's span (mm).
    pub from_mm: f64,
    pub to_mm: f64,
    /// The carriage's step (mm): not a whole number of screw leads.
    pub step_mm: f64,
    /// Passes over the span, alternately up and down.
    pub passes: usize,
    /// A back-and-forth probe every this many stops of a pass (0: none).
    pub probe_every: usize,
}

impl Default for Spec {
    fn default() -> Self {
        Spec {
            from_mm: 0.0,
            to_mm: 1000.0,
            step_mm: 3.75,
            passes: 4,
            probe_every: 13,
        }
    }
}

/// Why a self-calibration cannot be planned or built.
#[derive(Debug, Error)]
pub enum SelfCalError {
    #[error("self-calibration: {0}")]
    Spec(String),
    #[error("self-calibration: {0}")]
    Map(#[from] MapError),
}

/// The carriage's stops.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    spec: Spec,
    stops: Vec<f64>,
}

impl Plan {
    /// The plan for `spec`, or why it cannot be run.
    pub fn new(spec: Spec) -> Result<Plan, SelfCalError> {
        let bad = |why: String| Err(SelfCalError::Spec(why));
        if ![spec.from_mm, spec.to_mm, spec.step_mm]
            .iter()
            .all(|v| v.is_finite())
        {
            return bad(format!(
                "span {} to {} mm, step {} mm: give finite numbers",
                spec.from_mm, spec.to_mm, spec.step_mm
            ));
        }
        // The span along a machine axis, and passes and probes a day's mapping can hold.
        for (name, v) in [("from_mm", spec.from_mm), ("to_mm", spec.to_mm)] {
            POSITION_MM
                .check(v)
                .map_err(|p| SelfCalError::Spec(format!("{name} {p}")))?;
        }
        for (name, v, max) in [
            ("passes", spec.passes, 100),
            ("probe_every", spec.probe_every, 1000),
        ] {
            range::int(v, 0, max, "").map_err(|p| SelfCalError::Spec(format!("{name} {p}")))?;
        }
        if !(spec.step_mm > MIN_STEP_MM && spec.step_mm <= MAX_STEP_MM)
            || spec.to_mm <= spec.from_mm + spec.step_mm
        {
            return bad(format!(
                "a step of {} mm over {} to {} mm: give a step above {MIN_STEP_MM} and up to {MAX_STEP_MM} mm and a span of several steps",
                spec.step_mm, spec.from_mm, spec.to_mm
            ));
        }
        if spec.to_mm - spec.from_mm < LEAD_IN_MM {
            return bad(format!(
                "a span of {:.1} mm ({} to {} mm): give at least {LEAD_IN_MM} mm (the carriage comes to the start from {LEAD_IN_MM} mm above it)",
                spec.to_mm - spec.from_mm,
                spec.from_mm,
                spec.to_mm
            ));
        }
        if spec.passes == 0 {
            return bad("0 passes: give at least one".into());
        }
        let n = ((spec.to_mm - spec.from_mm) / spec.step_mm).floor() as usize;
        let mut stops = Vec::new();
        for p in 0..spec.passes {
            for k in 1..=n {
                let (x, back) = if p % 2 == 0 {
                    let x = spec.from_mm + k as f64 * spec.step_mm;
                    (x, x - spec.step_mm)
                } else {
                    let x = spec.from_mm + (n - k) as f64 * spec.step_mm;
                    (x, x + spec.step_mm)
                };
                stops.push(x);
                if spec.probe_every > 0 && k % spec.probe_every == 0 && k < n {
                    stops.push(back);
                    stops.push(x);
                }
            }
        }
        Ok(Plan { spec, stops })
    }

    pub fn spec(&self) -> &Spec {
        &self.spec
    }

    /// Stops in each pass: a step per `step_mm` of the span and two per probe.
    pub fn stops_per_pass(&self) -> usize {
        self.stops.len() / self.spec.passes.max(1)
    }

    /// The approach: the lead-in point, then the start (mm).
    pub fn approach(&self) -> [f64; 2] {
        [self.spec.from_mm + LEAD_IN_MM, self.spec.from_mm]
    }

    /// The stops after the start, in order (mm): each one a follower step.
    pub fn stops(&self) -> &[f64] {
        &self.stops
    }

    /// Every position the carriage goes to, in order: the approach, then the stops (mm).
    pub fn positions(&self) -> Vec<f64> {
        self.approach()
            .into_iter()
            .chain(self.stops.iter().copied())
            .collect()
    }

    /// Whether the plan has steps enough for the map's fits with `settings`: the along-axis
    /// fit takes the long-wavelength degree, the periodic term and the reversal, with five
    /// steps to spare.
    pub fn check_fit(&self, settings: &MapSettings) -> Result<(), SelfCalError> {
        let needed = settings.long_degree.max(1) + 9;
        if self.stops.len() < needed {
            return Err(SelfCalError::Spec(format!(
                "{} stops ({:.1} to {:.1} mm by {} mm, {} passes) are too few for the fit: it needs at least {needed}; give more passes, a longer span or a smaller step",
                self.stops.len(),
                self.spec.from_mm,
                self.spec.to_mm,
                self.spec.step_mm,
                self.spec.passes
            )));
        }
        Ok(())
    }

    /// The carriage's displacement planned for stop `k` (mm).
    fn planned_move(&self, k: usize) -> Option<f64> {
        let here = *self.stops.get(k)?;
        let before = if k == 0 {
            self.spec.from_mm
        } else {
            self.stops[k - 1]
        };
        Some(here - before)
    }

    /// Machine time of the whole plan (s): every move at `timing`'s feed, a dwell at every
    /// position.
    pub fn machine_time_s(&self, timing: &Timing) -> f64 {
        self.time_from(None, timing)
    }

    /// Machine time left after `done` stops (s), from the start when `done` is `None` (the
    /// approach still to come).
    fn time_from(&self, done: Option<usize>, timing: &Timing) -> f64 {
        let dwell = timing.dwell_s(self.spec.step_mm);
        let positions = self.positions();
        // positions[0..2] is the approach; stop k is positions[k + 2].
        let first = match done {
            None => 0,
            Some(d) => (d + 2).min(positions.len()),
        };
        let mut t = 0.0;
        for i in first..positions.len() {
            let d = if i == 0 {
                LEAD_IN_MM
            } else {
                positions[i] - positions[i - 1]
            };
            t += timing.carriage_move_s(d) + dwell;
        }
        t
    }
}

/// What sets the time a stop takes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Timing {
    /// PSD frames per second.
    pub frame_rate_hz: f64,
    /// Frames averaged on each side of a handover.
    pub average_frames: usize,
    /// The tracker's rest detection (the spot steady this long) and its settle after the
    /// follower's move.
    pub rest: Duration,
    pub settle: Duration,
    /// The follower's profile (mm/s, mm/s²) and its set-point handshake (a SYNC period).
    pub follower_velocity_mm_s: f64,
    pub follower_accel_mm_s2: f64,
    pub sync: Duration,
    /// The carriage's programmed feed (mm/min) and the acceleration assumed (mm/s²).
    pub feed_mm_min: f64,
    pub accel_mm_s2: f64,
}

/// Dwell margin: a frame late or dropped, a rest detection that starts again.
const DWELL_MARGIN: f64 = 1.25;
const DWELL_MARGIN_S: f64 = 0.5;

/// Time of a trapezoidal (or triangular) move of `d` at `v` and `a`.
fn move_s(d: f64, v: f64, a: f64) -> f64 {
    let d = d.abs();
    if !(v > 0.0 && a > 0.0) || d == 0.0 {
        return 0.0;
    }
    if d >= v * v / a {
        d / v + v / a
    } else {
        2.0 * (d / a).sqrt()
    }
}

impl Timing {
    /// Averaging one side of a handover (s).
    fn side_s(&self) -> f64 {
        self.average_frames as f64 / self.frame_rate_hz.max(1.0)
    }

    /// The follower's step of `step_mm`: its profile and two SYNC periods for the set-point
    /// handshake and "target reached" (s).
    fn follower_step_s(&self, step_mm: f64) -> f64 {
        move_s(
            step_mm,
            self.follower_velocity_mm_s,
            self.follower_accel_mm_s2,
        ) + 2.0 * self.sync.as_secs_f64()
    }

    /// The dwell at each stop (s, rounded up to 0.1 s): rest detection, the frames before, the
    /// follower's step and settle, the frames after, with 25 % and 0.5 s of margin.
    pub fn dwell_s(&self, step_mm: f64) -> f64 {
        let need = self.rest.as_secs_f64()
            + 2.0 * self.side_s()
            + self.follower_step_s(step_mm)
            + self.settle.as_secs_f64();
        ((need * DWELL_MARGIN + DWELL_MARGIN_S) * 10.0).ceil() / 10.0
    }

    /// What the dwell is made of, in words.
    pub fn dwell_text(&self, step_mm: f64) -> String {
        format!(
            "dwell {:.1} s at each stop: rest detection {:.2} s + {} frames before at {:.0} Hz ({:.2} s) + the follower's {:.2} mm step {:.2} s + settle {:.2} s + {} frames after ({:.2} s), with 25 % and 0.5 s of margin",
            self.dwell_s(step_mm),
            self.rest.as_secs_f64(),
            self.average_frames,
            self.frame_rate_hz,
            self.side_s(),
            step_mm,
            self.follower_step_s(step_mm),
            self.settle.as_secs_f64(),
            self.average_frames,
            self.side_s()
        )
    }

    /// The carriage's move of `d` mm at the feed (s).
    pub fn carriage_move_s(&self, d: f64) -> f64 {
        move_s(d, self.feed_mm_min / 60.0, self.accel_mm_s2)
    }
}

/// Where the collection stands.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Progress {
    /// The lead-in's record was seen: the stops count from here.
    pub armed: bool,
    /// Stops seen (handover records since the start) and planned.
    pub stops_seen: usize,
    pub stops_planned: usize,
    /// Optical steps kept, and stops whose handover was not optical (left out).
    pub steps_kept: usize,
    pub skipped: usize,
    /// Kept steps whose encoder displacement is not the plan's carriage move (more than a
    /// quarter step off): the CNC runs another program, or a stop was missed.
    pub out_of_plan: usize,
    /// Records before the start (the approach).
    pub approach_records: usize,
}

/// What a handover record was to the collector.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Taken {
    /// Before the start: the approach.
    Approach,
    /// The lead-in's last leg: the stops count from the next record.
    Armed,
    /// A stop's optical step, kept.
    Kept,
    /// A stop whose step was not optical: left out.
    Skipped,
}

/// The steps of a self-calibration, collected from the tracker's handover records.
#[derive(Clone, Debug)]
pub struct Collector {
    plan: Plan,
    started: Instant,
    steps: Vec<Step>,
    progress: Progress,
}

impl Collector {
    /// Collect for `plan`, starting at `now` (the approach to come).
    pub fn new(plan: Plan, now: Instant) -> Collector {
        let progress = Progress {
            stops_planned: plan.stops().len(),
            ..Progress::default()
        };
        Collector {
            plan,
            started: now,
            steps: Vec::new(),
            progress,
        }
    }

    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    /// The carriage is at the start (a driver that moved it there itself): the stops count
    /// from the next record.
    pub fn arm(&mut self) {
        self.progress.armed = true;
        self.progress.stops_seen = 0;
    }

    /// One handover record of the tracker.
    pub fn handle_record(&mut self, r: &HandoverRecord) -> Taken {
        let moved = r.encoder_after - r.encoder_before;
        let lead_in = (moved + LEAD_IN_MM).abs() <= LEAD_IN_TOLERANCE_MM;
        if lead_in && self.progress.stops_seen == 0 {
            self.arm();
            return Taken::Armed;
        }
        if !self.progress.armed {
            self.progress.approach_records += 1;
            return Taken::Approach;
        }
        let k = self.progress.stops_seen;
        self.progress.stops_seen += 1;
        match Step::from_record(r) {
            Some(step) => {
                let tol = (0.25 * self.plan.spec.step_mm).max(0.15);
                if self
                    .plan
                    .planned_move(k)
                    .is_none_or(|want| (moved - want).abs() > tol)
                {
                    self.progress.out_of_plan += 1;
                }
                self.steps.push(step);
                self.progress.steps_kept += 1;
                Taken::Kept
            }
            None => {
                self.progress.skipped += 1;
                Taken::Skipped
            }
        }
    }

    pub fn progress(&self) -> Progress {
        self.progress
    }

    /// Every planned stop has been seen.
    pub fn all_seen(&self) -> bool {
        self.progress.armed && self.progress.stops_seen >= self.progress.stops_planned
    }

    /// The steps kept, in the order taken.
    pub fn steps(&self) -> &[Step] {
        &self.steps
    }

    /// Machine time since the collector started.
    pub fn elapsed(&self, now: Instant) -> Duration {
        now.saturating_duration_since(self.started)
    }

    /// Machine time left by the plan (s): the stops not seen yet (and the approach, before
    /// the start).
    pub fn left_s(&self, timing: &Timing) -> f64 {
        let done = self.progress.armed.then_some(self.progress.stops_seen);
        self.plan.time_from(done, timing)
    }

    /// The tracker's settings now, from the service's own `base`, always with the overlap
    /// strategy (only it records a handover per follower step): during the approach `base`'s
    /// own edge and averaging (a long move is followed with the usual margin); from the start
    /// `average_frames` a side, a handover at half a step and an edge beyond one step (the
    /// spot rests a step off centre at each stop).
    pub fn tracking(&self, base: &TrackSettings, average_frames: usize) -> TrackSettings {
        let mut s = *base;
        s.strategy = Strategy::Overlap;
        if !self.progress.armed {
            return s;
        }
        let step = self.plan.spec.step_mm;
        s.average_frames = average_frames.max(10);
        s.edge_mm = s.edge_mm.max(step + 0.45);
        // Each step stops short of the edge by design: never follow it ahead of time.
        s.anticipate = std::time::Duration::ZERO;
        s.handover_mm = s.handover_mm.min(step * 0.5);
        // No final approach from below: the passes measure the reversal, so each step ends in
        // the direction it moved.
        s.approach_mm = 0.0;
        s
    }

    /// The map from the steps kept and `certificate`, with the machine time up to `now`.
    pub fn build(
        &self,
        certificate: Option<&Certificate>,
        settings: &MapSettings,
        now: Instant,
    ) -> Result<FollowerMap, SelfCalError> {
        let mut map = build(&self.steps, certificate, settings)?;
        if let Some(s) = map.self_calibration.as_mut() {
            s.machine_time_s = Some(self.elapsed(now).as_secs_f64());
        }
        Ok(map)
    }
}

/// The degree of the along-axis fit's long-wavelength nuisance for a span (mm): one per
/// 80 mm, 2 to 12 (12 over a metre, as the defaults; a short span has few steps to fit it).
pub fn long_degree(span_mm: f64) -> usize {
    ((span_mm / 80.0).round() as usize).clamp(2, MapSettings::default().long_degree)
}
