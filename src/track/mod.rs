//! Follower tracking and stitching (DESIGN §4): keep the laser spot on PSD2 by moving the
//! follower stage, and know where PSD2 really is.
//!
//! Two strategies:
//! - **Overlap** (the paper's method, made exact): hand over only while the carriage is at
//!   rest. Average many frames before and after the follower's step; the difference of the
//!   spot's position is the follower's true displacement, measured by the PSD itself — along its
//!   axis (X2) and vertically (Y2), so neither the follower's positioning error nor its
//!   straightness enters the result. Noise adds up as a random walk; every handover adds its
//!   variance to the accumulated uncertainty. If the carriage runs the spot towards the PSD's
//!   edge without stopping, the follower must follow anyway: that step is taken from the
//!   encoder, with the encoder's uncertainty, and recorded as such.
//! - **Encoder**: the follower follows continuously and PSD2's position is the encoder's.
//!   Fast, but the follower's own positioning and vertical straightness enter 1:1 (1 µm of
//!   follower straightness reads as 1.38″ of roll).
//!
//! With a map of the follower stage's own errors (a [`StageCorrection`], such as
//! `follower::FollowerMap`; `set_map`) every displacement taken from the
//! encoder — the encoder strategy, and the overlap strategy's steps while the carriage runs —
//! is corrected by the map's difference between the two positions, along the axis and
//! vertically (the reversal by the direction the follower last moved in), with the map's
//! uncertainty in place of the encoder's per-mm terms.
//!
//! Every handover is recorded (time, spot before and after, encoder before and after, counts),
//! so a run can be re-stitched offline (`restitch`).
//!
//! The machine is sans-I/O: feed it frames (`handle_frame`) and follower states
//! (`handle_follower`) with the time, take follower commands (`poll_command`) and events
//! (`poll_event`); `stitch()` gives the current PSD2 position estimate for the decoupling.

pub mod carriage;
mod correction;

pub use correction::StageCorrection;

use crate::acquire::Frame;
use crate::run::Direction;
use carriage::CarriageEstimator;
use correction::Applied;
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Below this speed (mm/s) the carriage stands: a follower is not sent after it.
const STANDING_MM_S: f64 = 2.0;

/// How the follower's position is known.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Strategy {
    Overlap,
    Encoder,
}

impl Strategy {
    /// Its name in the configuration and the API: "overlap" or "encoder".
    pub fn name(self) -> &'static str {
        match self {
            Strategy::Overlap => "overlap",
            Strategy::Encoder => "encoder",
        }
    }
}

/// Tracking settings (validated by the config layer).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackSettings {
    pub strategy: Strategy,
    /// Overlap: hand over when the spot is this far from PSD2's centre at rest (mm).
    pub handover_mm: f64,
    /// Overlap: follow during motion when the spot gets this far out (mm), before it is lost.
    pub edge_mm: f64,
    /// Overlap: follow already when the spot will be `edge_mm` out within this long at the
    /// carriage's speed (the follower's time to start following; zero: at the edge only).
    pub anticipate: Duration,
    /// At rest: the spot stays within ± this of its mean (mm) for `rest_time`.
    pub rest_tolerance_mm: f64,
    pub rest_time: Duration,
    /// Frames averaged on each side of a handover.
    pub average_frames: usize,
    /// Wait after the follower reports its target reached.
    pub settle: Duration,
    /// Following: re-centre when the spot is this far out (mm) or the carriage moves, at most
    /// every `follow_interval`, on the carriage's position at the frame's time plus its
    /// estimated motion over `lead` (extra feed-forward: the drive's cyclic synchronous mode
    /// already carries each time-stamped target on to its SYNC).
    pub follow_band_mm: f64,
    pub follow_interval: Duration,
    pub lead: Duration,
    /// The spot is lost when PSD2 has had no valid reading for this long.
    pub lost_after: Duration,
    /// Encoder accuracy: standard deviation `a + b·|travelled|` (mm, and mm per mm).
    pub encoder_sd_mm: f64,
    pub encoder_sd_per_mm: f64,
    /// With a follower map in use that does not know it from its own self-calibration
    /// (`StageCorrection::unmapped_sd`: a certificate alone, a map stored before), what the
    /// stage repeats to beyond its map (mm, standard deviation): `encoder_sd_mm` also covers
    /// the unmapped screw-periodic and reversal errors at short distance, which the map takes
    /// out.
    pub mapped_sd_mm: f64,
    /// Without a map, the follower's vertical straightness as a standard deviation `a +
    /// b·|travelled|` (mm, and mm per mm): what an encoder step leaves unmeasured across the
    /// axis (it reads as roll, 1.38″ per µm).
    pub vertical_sd_mm: f64,
    pub vertical_sd_per_mm: f64,
    /// With a map, what its vertical misses beyond its own stated uncertainty (mm, standard
    /// deviation; its χ² does not see it). The twin's map misses 0.065 µm RMS (roll 0.09″),
    /// as it states, but 0.31 µm at one target of twin seed 6 (a storm, every pass): 0.08 µm
    /// left that outside U, 0.2 µm covers it at a roll U 4.7 times its RMS error.
    pub mapped_vertical_sd_mm: f64,
    /// A follower move that has not finished after this long is abandoned.
    pub move_timeout: Duration,
    /// Every follower move ends with an approach from below over this distance (mm; 0: none):
    /// to `target − approach_mm`, then up to the target. The stage's reversal then always
    /// stands in the "up" state at rest, whatever the drive did between two samples of its
    /// encoder (a servo's overshoot and return between SYNCs is invisible to the master, and
    /// would leave the stage turned while its samples say it did not).
    pub approach_mm: f64,
}

impl TrackSettings {
    /// What the follower takes at each stop before the stitch stands still for a capture:
    /// the carriage's rest it waits for, and its own settling after its final approach.
    pub fn rest_at_stop(&self) -> Duration {
        self.rest_time + self.settle
    }
}

impl Default for TrackSettings {
    fn default() -> Self {
        TrackSettings {
            strategy: Strategy::Overlap,
            handover_mm: 1.5,
            edge_mm: 3.5,
            anticipate: Duration::ZERO,
            rest_tolerance_mm: 0.005,
            rest_time: Duration::from_millis(300),
            average_frames: 200,
            settle: Duration::from_millis(100),
            follow_band_mm: 0.3,
            follow_interval: Duration::from_millis(20),
            lead: Duration::ZERO,
            lost_after: Duration::from_millis(500),
            encoder_sd_mm: 1e-3,
            encoder_sd_per_mm: 5e-6,
            mapped_sd_mm: 0.5e-3,
            vertical_sd_mm: 0.2e-3,
            vertical_sd_per_mm: 3e-6,
            mapped_vertical_sd_mm: 0.2e-3,
            move_timeout: Duration::from_secs(10),
            approach_mm: 0.02,
        }
    }
}

/// What the follower drive reports.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FollowerState {
    /// Encoder position (mm).
    pub position_mm: f64,
    /// Operation enabled, no fault, heartbeat alive.
    pub ready: bool,
    /// The last commanded target is reached.
    pub target_reached: bool,
    /// When the position was sampled, if the drive says (else when it arrived).
    pub at: Option<Instant>,
}

/// A command for the follower.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FollowerCommand {
    /// Move to an absolute encoder position (mm) and stop there (a handover step).
    MoveTo(f64),
    /// Continuous following: the carriage, in encoder coordinates, was at `target_mm` at `at`
    /// moving at `velocity_mm_s` (the drive's cyclic synchronous position mode moves it on to
    /// each SYNC).
    Follow {
        target_mm: f64,
        velocity_mm_s: f64,
        at: Instant,
    },
}

/// How a handover's displacement was measured.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum HandoverKind {
    /// Optically, spot before minus spot after, carriage at rest.
    Overlap,
    /// From the encoder (encoder strategy, or the carriage moved during the handover).
    Encoder,
}

/// One handover, enough to re-stitch offline.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct HandoverRecord {
    pub unix_us: i64,
    pub kind: HandoverKind,
    /// Mean spot on PSD2 before and after (mm), and the frames averaged.
    pub before: [f64; 2],
    pub after: [f64; 2],
    pub n_before: usize,
    pub n_after: usize,
    /// Standard deviation of single frames (mm, X2 and Y2), pooled over both windows.
    pub frame_sd: [f64; 2],
    pub encoder_before: f64,
    pub encoder_after: f64,
    /// Displacement used for the stitch (mm, along and across) and its variance (mm²).
    pub delta: [f64; 2],
    pub variance: [f64; 2],
}

/// Where PSD2 is, for the decoupling.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Stitch {
    /// PSD2's position along the follower axis (mm): the `follower` argument of the model.
    pub follower_mm: f64,
    /// PSD2's vertical displacement since the reference (mm): add it to Y2.
    pub vertical_mm: f64,
    /// Accumulated variance (mm²) of each.
    pub variance: [f64; 2],
    pub handovers: usize,
    pub strategy: Strategy,
    /// False after the spot was lost: the stitch is broken until re-referenced.
    pub valid: bool,
}

/// Where the stitch stood at a zero reference, kept with the zero across a restart: PSD2 was
/// at `follower_mm` (vertical `vertical_mm`, variance `variance_mm2`) with the follower's
/// encoder at `encoder_mm`, where the follower map's correction was `corr_mm`. A service
/// that restarts bridges from here by the encoder (`Tracker::restore`); referencing afresh
/// where the follower stands after the restart dropped the follower's shape between the two,
/// and read roll 0.8″ off after a SIGKILL (issue 24).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StitchAnchor {
    pub encoder_mm: f64,
    pub corr_mm: [f64; 2],
    pub follower_mm: f64,
    pub vertical_mm: f64,
    pub variance_mm2: [f64; 2],
}

impl StitchAnchor {
    /// Refuse an anchor that cannot be one (a damaged row).
    pub fn check(&self) -> Result<(), String> {
        let mut numbers = [self.encoder_mm, self.follower_mm, self.vertical_mm]
            .into_iter()
            .chain(self.corr_mm)
            .chain(self.variance_mm2);
        if numbers.any(|v| !v.is_finite()) {
            return Err("the stitch's anchor holds a value that is not a finite number".into());
        }
        if self.variance_mm2.iter().any(|v| *v < 0.0) {
            return Err("the stitch's anchor has a negative variance".into());
        }
        Ok(())
    }
}

/// Events for the service.
#[derive(Clone, Debug, PartialEq)]
pub enum TrackEvent {
    Handover(HandoverRecord),
    /// The carriage ran the spot towards the edge without stopping: followed by encoder.
    FollowedWhileMoving {
        from_mm: f64,
        to_mm: f64,
    },
    /// PSD2 lost its spot; the stitch is invalid until `reference` is called.
    SpotLost,
    /// PSD2 sees the spot again.
    SpotFound,
    /// A follower move did not finish in time or the follower is not ready.
    FollowerProblem(String),
    /// The follower serves again after a `FollowerProblem`: ready again after it was not,
    /// or a move reached its target after one did not in time.
    FollowerRecovered,
}

/// What the last `FollowerProblem` was, and so what ends it.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Problem {
    NotReady,
    Late,
}

#[derive(Clone, Debug, PartialEq)]
enum Phase {
    /// Watching the spot.
    Watch,
    /// Overlap: averaging frames before the step.
    Before { since: Instant },
    /// An overlap handover's follower step is under way.
    Moving {
        target: f64,
        /// The approach point below the target, while the follower still goes there.
        via: Option<f64>,
        since: Instant,
        reached_at: Option<Instant>,
    },
    /// The carriage runs the spot along: the follower follows continuously; PSD2's
    /// displacement over this segment comes from the encoder.
    Following { encoder_start: f64 },
    /// Overlap: averaging frames after the step.
    After { since: Instant },
    /// The carriage stopped after the follower followed it: the follower's final approach
    /// from below (`via`, then back to `target`) before the step is taken from the encoder
    /// (overlap: from `encoder_start`), or, in the encoder strategy (`encoder_start` none),
    /// before following goes on.
    Approach {
        encoder_start: Option<f64>,
        via: Option<f64>,
        target: f64,
        since: Instant,
    },
    /// PSD2 lost the spot and the carriage stands elsewhere: the follower goes to it (by
    /// `via` below it when an approach is configured, as every final approach does). Frames
    /// are not tracked on the way; the stitch is bridged by the encoder once it stands.
    Seek {
        via: Option<f64>,
        target: f64,
        since: Instant,
    },
}

/// How a move by an approach point went on at one follower status (`Tracker::leg`).
enum Leg {
    Going,
    OnToTarget,
    Arrived,
    Late,
}

/// Running mean and variance (Welford).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Stats2 {
    n: usize,
    mean: [f64; 2],
    m2: [f64; 2],
}

impl Stats2 {
    fn push(&mut self, x: [f64; 2]) {
        self.n += 1;
        for ((xk, mean), m2) in x.iter().zip(&mut self.mean).zip(&mut self.m2) {
            let d = xk - *mean;
            *mean += d / self.n as f64;
            *m2 += d * (xk - *mean);
        }
    }
    fn var(&self) -> [f64; 2] {
        if self.n < 2 {
            return [0.0; 2];
        }
        self.m2.map(|m| m / (self.n - 1) as f64)
    }
}

/// The tracking and stitching machine.
#[derive(Debug)]
pub struct Tracker {
    settings: TrackSettings,
    phase: Phase,
    follower: Option<FollowerState>,
    /// Recent PSD2 spots (time, x, y) for the rest test.
    recent: VecDeque<(Instant, [f64; 2])>,
    /// The carriage in encoder coordinates (frames placed by the follower's samples).
    carriage: CarriageEstimator,
    last_valid: Option<Instant>,
    lost: bool,
    last_follow_cmd: Option<Instant>,
    before: Stats2,
    after: Stats2,
    encoder_before: f64,
    /// Overlap: PSD2's position along the follower axis, stitched from the reference (mm).
    follower_mm: f64,
    /// The encoder position at the reference (mm).
    reference_encoder: f64,
    /// Overlap: the encoder position where PSD2 stood at `follower_mm` (the last handover's
    /// end, or the reference), when the stitch has been referenced.
    stitch_encoder: Option<f64>,
    vertical_mm: f64,
    /// The stitch's variance (mm²: along, vertical) up to the open chain of encoder steps.
    variance: [f64; 2],
    /// Overlap: where the open chain of encoder-bridged steps began (encoder mm), and its
    /// variance so far. Consecutive encoder steps telescope: their errors are the stage's
    /// own error at the chain's end less that at its start, one difference whatever the
    /// number of steps (the follower at rest always stands after an approach from below, so
    /// in the same reversal state). Summing each step's variance made the stated U a random
    /// walk over a run, 1.4 → 12.8 µm through a run whose captures agreed within 0.3 µm
    /// (issue 24). An optical handover (the follower stepped, measured on PSD2) closes it.
    chain_from: Option<f64>,
    chain_var: [f64; 2],
    handovers: usize,
    valid: bool,
    commands: VecDeque<FollowerCommand>,
    events: VecDeque<TrackEvent>,
    last_frame_unix_us: i64,
    /// The follower error map applied to encoder displacements.
    map: Option<Applied>,
    /// The direction the follower last moved in, and the turning point it is judged from.
    motion: Direction,
    motion_anchor: Option<f64>,
    /// The follower has followed the carriage since its last final approach.
    followed: bool,
    /// The follower is held where it stands (a procedure moves the head itself): no
    /// anticipated following (see [`Tracker::hold`]).
    held: bool,
    /// The map's correction at the reference, at `stitch_encoder`, and where the follower
    /// left the stitched position (mm: along, vertical).
    ref_corr: [f64; 2],
    stitch_corr: [f64; 2],
    before_corr: [f64; 2],
    /// The follower problem last reported and not yet recovered from.
    problem: Option<Problem>,
}

/// The follower has turned when it is this far back from its furthest point (mm).
const TURN_MM: f64 = 0.5e-3;

/// An encoder step's recorded start this far from the stitch's (mm) is not where the stitch
/// stood (the follower's final approach is 20 µm).
const STEP_START_MM: f64 = 0.05;

/// An overlap handover's optical step agrees with the encoder's within this floor (mm) plus
/// `STEP_AGREE_SIGMAS` times the encoder step's standard deviation, or the carriage moved.
/// The floor is far above any stage's own error over a step of a few millimetres (the
/// follower's self-calibration measures that error by these very differences: a floor of
/// 5 µm turned its larger steps into encoder steps, and the demo's positioning came out
/// 1.4 µm off with a U of 0.75 µm), and far below a carriage's move between two stops.
const STEP_AGREE_FLOOR_MM: f64 = 0.05;
const STEP_AGREE_SIGMAS: f64 = 5.0;

impl Tracker {
    /// A tracker that has not yet been referenced (its stitch is invalid until `reference`).
    pub fn new(settings: TrackSettings) -> Self {
        Tracker {
            settings,
            phase: Phase::Watch,
            follower: None,
            recent: VecDeque::new(),
            carriage: CarriageEstimator::default(),
            last_valid: None,
            lost: false,
            last_follow_cmd: None,
            before: Stats2::default(),
            after: Stats2::default(),
            encoder_before: 0.0,
            follower_mm: 0.0,
            reference_encoder: 0.0,
            stitch_encoder: None,
            vertical_mm: 0.0,
            variance: [0.0; 2],
            chain_from: None,
            chain_var: [0.0; 2],
            handovers: 0,
            valid: false,
            commands: VecDeque::new(),
            events: VecDeque::new(),
            problem: None,
            last_frame_unix_us: 0,
            map: None,
            motion: Direction::Up,
            motion_anchor: None,
            followed: false,
            held: false,
            ref_corr: [0.0; 2],
            stitch_corr: [0.0; 2],
            before_corr: [0.0; 2],
        }
    }

    /// The follower is held (`true`) or free: a procedure that moves the head itself (a
    /// hexapod calibration) holds it, and its commands go nowhere. A held follower is not
    /// sent after a spot by anticipation (`anticipate`): the head's poses move the spot fast
    /// within PSD2 and stop there, which is not a carriage running out.
    pub fn hold(&mut self, held: bool) {
        self.held = held;
    }

    /// Apply `map` to every displacement taken from the encoder from now on (`None`: the
    /// encoder alone). Take the reference again after changing it.
    pub fn set_map<M: StageCorrection>(&mut self, map: Option<Arc<M>>) {
        self.map = map.map(Applied::new);
    }

    /// The follower map in use, as the `Arc<M>` it was given in (`None` without a map, or
    /// with one of another type).
    pub fn map<M: StageCorrection>(&self) -> Option<&Arc<M>> {
        self.map.as_ref()?.get()
    }

    /// Replace the settings (a calibration procedure's longer averaging, say).
    pub fn set_settings(&mut self, settings: TrackSettings) {
        self.settings = settings;
    }

    /// The direction the follower last moved in.
    pub fn motion(&self) -> Direction {
        self.motion
    }

    /// The map's correction (mm: along, vertical) at encoder `mm` in the current direction.
    fn corr(&self, mm: f64) -> [f64; 2] {
        self.map
            .as_ref()
            .map_or([0.0; 2], |m| m.correction(mm, self.motion))
    }

    /// Follow the follower's direction of motion from its encoder.
    fn track_motion(&mut self, mm: f64) {
        let Some(anchor) = self.motion_anchor else {
            self.motion_anchor = Some(mm);
            return;
        };
        let (further, turned) = match self.motion {
            Direction::Up => (mm > anchor, mm < anchor - TURN_MM),
            Direction::Down => (mm < anchor, mm > anchor + TURN_MM),
        };
        if turned {
            self.motion = match self.motion {
                Direction::Up => Direction::Down,
                Direction::Down => Direction::Up,
            };
        }
        if further || turned {
            self.motion_anchor = Some(mm);
        }
    }

    /// PSD2's displacement (mm: along, vertical) and its variance when the follower went from
    /// encoder `from` (where the map's correction was `from_corr`) to `to` by its encoder
    /// alone.
    fn encoder_step(&self, from: f64, from_corr: [f64; 2], to: f64) -> ([f64; 2], [f64; 2]) {
        (
            self.encoder_delta(from, from_corr, to),
            self.bridge_var(from, to),
        )
    }

    /// PSD2's displacement alone (see `encoder_step`), where its variance is the chain's.
    fn encoder_delta(&self, from: f64, from_corr: [f64; 2], to: f64) -> [f64; 2] {
        let moved = to - from;
        match &self.map {
            None => [moved, 0.0],
            Some(_) => {
                let c = self.corr(to);
                [moved + c[0] - from_corr[0], c[1] - from_corr[1]]
            }
        }
    }

    /// The variance (mm²: along, vertical) of PSD2's displacement bridged by the encoder
    /// from `from` to `to`: the stage's error at one less that at the other, with the map's
    /// correction its residual.
    fn bridge_var(&self, from: f64, to: f64) -> [f64; 2] {
        match &self.map {
            None => self.encoder_var(to - from),
            Some(m) => {
                let s = &self.settings;
                // Which direction the start was in does not change the map's uncertainty.
                let dv = m.difference_variance(from, to, self.motion, self.motion);
                let along = m.unmapped_sd().unwrap_or(s.mapped_sd_mm);
                [
                    along.powi(2) + dv[0],
                    s.mapped_vertical_sd_mm.powi(2) + dv[1],
                ]
            }
        }
    }

    /// Extend the open chain of encoder steps (begun at `from` unless one is open) to `to`.
    fn chain_to(&mut self, from: f64, to: f64) {
        let start = *self.chain_from.get_or_insert(from);
        self.chain_var = self.bridge_var(start, to);
    }

    /// The stitch's variance with its open chain.
    fn total_var(&self) -> [f64; 2] {
        [
            self.variance[0] + self.chain_var[0],
            self.variance[1] + self.chain_var[1],
        ]
    }

    /// The settings in use.
    pub fn settings(&self) -> &TrackSettings {
        &self.settings
    }

    /// Switch strategy (takes effect at the next step; the stitch so far is kept).
    pub fn set_strategy(&mut self, s: Strategy) {
        self.settings.strategy = s;
    }

    /// PSD2 has had no spot for `lost_after`.
    pub fn is_lost(&self) -> bool {
        self.lost
    }

    /// PSD2 has lost the spot while the carriage stands at `carriage_mm` (encoder
    /// coordinates): send the follower there, so that a carriage that went on while the
    /// follower could not follow (a drive fault, a following error) is found again where it
    /// stands rather than waited for at the follower (a make-up pass may never come by).
    /// False, and nothing sent, when the spot is not lost, the follower is not ready, or it is
    /// already on its way there.
    pub fn seek(&mut self, carriage_mm: f64, now: Instant) -> bool {
        let Some(f) = self.follower.filter(|f| f.ready) else {
            return false;
        };
        if !self.lost {
            return false;
        }
        if let Phase::Seek { target, .. } = self.phase
            && (target - carriage_mm).abs() <= self.settings.follow_band_mm
        {
            return false;
        }
        let a = self.settings.approach_mm;
        let via = (a > 0.0).then_some(carriage_mm - a);
        tracing::info!(
            from_mm = f.position_mm,
            to_mm = carriage_mm,
            "PSD2 has no spot: the follower goes to the carriage"
        );
        self.commands
            .push_back(FollowerCommand::MoveTo(via.unwrap_or(carriage_mm)));
        self.phase = Phase::Seek {
            via,
            target: carriage_mm,
            since: now,
        };
        true
    }

    /// Whether the follower is on its way to the carriage (`seek`).
    pub fn seeking(&self) -> bool {
        matches!(self.phase, Phase::Seek { .. })
    }

    /// Re-reference after the stitch was broken in the middle of something (a service restart
    /// in a run, a spot lost and found again): PSD2 is where the encoder says, the encoder
    /// bridging the gap with its uncertainty over the distance. A stitch referenced before
    /// (or restored, `restore`) keeps what it had measured (overlap: the stitched position and
    /// the vertical offset), moved on by the encoder's increment since; the encoder strategy
    /// keeps its reference. Otherwise the encoder is taken from its home.
    pub fn reference_by_encoder(&mut self) -> bool {
        let Some(f) = self.follower else {
            return false;
        };
        if self.seeking() {
            // Not while the follower still moves to the carriage: the seek's end says
            // `SpotFound` again when the spot is there.
            return false;
        }
        if let (Strategy::Encoder, Some(_)) = (self.settings.strategy, self.stitch_encoder) {
            // Every position is the encoder's from the reference: the reference still holds.
            if self.lost {
                return false;
            }
            self.valid = true;
            self.phase = Phase::Watch;
            return true;
        }
        if let (Strategy::Overlap, Some(at)) = (self.settings.strategy, self.stitch_encoder) {
            if self.lost {
                return false;
            }
            let d = self.encoder_delta(at, self.stitch_corr, f.position_mm);
            self.follower_mm += d[0];
            self.vertical_mm += d[1];
            self.stitch_encoder = Some(f.position_mm);
            self.stitch_corr = self.corr(f.position_mm);
            self.chain_to(at, f.position_mm);
            self.valid = true;
            self.phase = Phase::Watch;
            return true;
        }
        if !self.reference() {
            return false;
        }
        self.variance = self.encoder_var(f.position_mm);
        true
    }

    /// Take the current follower position as the reference: PSD2 is where the encoder says,
    /// with no vertical offset and no uncertainty. Called at the zero reference.
    pub fn reference(&mut self) -> bool {
        let Some(f) = self.follower else {
            return false;
        };
        self.follower_mm = f.position_mm;
        self.reference_encoder = f.position_mm;
        self.stitch_encoder = Some(f.position_mm);
        self.ref_corr = self.corr(f.position_mm);
        self.stitch_corr = self.ref_corr;
        self.vertical_mm = 0.0;
        self.variance = [0.0; 2];
        self.chain_from = None;
        self.chain_var = [0.0; 2];
        self.handovers = 0;
        self.valid = !self.lost;
        self.phase = Phase::Watch;
        true
    }

    /// Where the stitch stands now, to be kept with a zero reference (`StitchAnchor`): none
    /// while it is not valid or a handover is under way.
    pub fn anchor(&self) -> Option<StitchAnchor> {
        if !self.valid || self.lost || self.handing_over() {
            return None;
        }
        match self.settings.strategy {
            Strategy::Encoder => self.stitch_encoder.map(|_| StitchAnchor {
                encoder_mm: self.reference_encoder,
                corr_mm: self.ref_corr,
                follower_mm: self.reference_encoder,
                vertical_mm: 0.0,
                variance_mm2: [0.0; 2],
            }),
            Strategy::Overlap => self.stitch_encoder.map(|e| StitchAnchor {
                encoder_mm: e,
                corr_mm: self.stitch_corr,
                follower_mm: self.follower_mm,
                vertical_mm: self.vertical_mm,
                variance_mm2: self.total_var(),
            }),
        }
    }

    /// Take back the stitch kept with a zero reference before a restart: it stays invalid
    /// until `reference_by_encoder` bridges from the anchor to where the follower stands.
    pub fn restore(&mut self, a: &StitchAnchor) {
        self.follower_mm = a.follower_mm;
        self.vertical_mm = a.vertical_mm;
        self.reference_encoder = a.encoder_mm;
        self.ref_corr = a.corr_mm;
        self.stitch_encoder = Some(a.encoder_mm);
        self.stitch_corr = a.corr_mm;
        self.variance = a.variance_mm2;
        self.chain_from = None;
        self.chain_var = [0.0; 2];
        self.handovers = 0;
        self.valid = false;
        self.phase = Phase::Watch;
    }

    /// Whether the stitch has a reference to bridge from (taken, or restored).
    pub fn anchored(&self) -> bool {
        self.stitch_encoder.is_some()
    }

    /// Mark the stitch broken (the follower was moved outside the tracker's control); it stays
    /// invalid until `reference`.
    pub fn invalidate(&mut self) {
        self.valid = false;
        self.phase = Phase::Watch;
    }

    /// Forget the stitch altogether (the follower's encoder may have a new origin: a drive
    /// that rebooted homes again): only a new reference makes it valid.
    pub fn forget(&mut self) {
        self.invalidate();
        self.stitch_encoder = None;
    }

    /// Where PSD2 is now.
    pub fn stitch(&self) -> Stitch {
        let (follower_mm, vertical_mm, variance) = match (self.settings.strategy, self.follower) {
            (Strategy::Encoder, Some(f)) => {
                let (d, e) =
                    self.encoder_step(self.reference_encoder, self.ref_corr, f.position_mm);
                (self.reference_encoder + d[0], d[1], e)
            }
            (Strategy::Overlap, Some(f)) => match self.in_flight_from() {
                // Mid-handover the follower has left the stitched position: until the
                // handover is measured, PSD2 is where its encoder says (a stale stitch would
                // read a moving carriage as standing where the handover began).
                Some(from) => {
                    let (from, from_corr) =
                        self.step_origin(from).unwrap_or((from, self.before_corr));
                    let d = self.encoder_delta(from, from_corr, f.position_mm);
                    let e = self.bridge_var(self.chain_from.unwrap_or(from), f.position_mm);
                    (
                        self.follower_mm + d[0],
                        self.vertical_mm + d[1],
                        [self.variance[0] + e[0], self.variance[1] + e[1]],
                    )
                }
                None => (self.follower_mm, self.vertical_mm, self.total_var()),
            },
            _ => (self.follower_mm, self.vertical_mm, self.total_var()),
        };
        Stitch {
            follower_mm,
            vertical_mm,
            variance,
            handovers: self.handovers,
            strategy: self.settings.strategy,
            valid: self.valid && !self.lost,
        }
    }

    /// Overlap: where a step recorded as begun at encoder `from` really begins, when that is
    /// not `from`: the stitch's own position (and the map's correction there), the follower
    /// having moved in between without a step the tracker saw end. Read in flight too: the
    /// stitch counted from the recorded start placed a carriage 2.5 mm past where it stopped,
    /// and the run filed a capture approached from below under the other direction (issue 24).
    fn step_origin(&self, from: f64) -> Option<(f64, [f64; 2])> {
        match (self.settings.strategy, self.stitch_encoder) {
            (Strategy::Overlap, Some(at)) if (at - from).abs() > STEP_START_MM => {
                Some((at, self.stitch_corr))
            }
            _ => None,
        }
    }

    /// Whether a handover is under way (the follower stepping or settling): a carriage that
    /// starts to move now may leave PSD2 before the follower follows.
    pub fn handing_over(&self) -> bool {
        self.in_flight_from().is_some()
    }

    /// Overlap: the encoder position the follower left the stitched position from, while a
    /// handover is under way (moving, settling, or following a carriage that does not stop).
    fn in_flight_from(&self) -> Option<f64> {
        match self.phase {
            Phase::Moving { .. } | Phase::After { .. } => Some(self.encoder_before),
            Phase::Following { encoder_start }
            | Phase::Approach {
                encoder_start: Some(encoder_start),
                ..
            } => Some(encoder_start),
            _ => None,
        }
    }

    /// Whether the carriage is judged at rest (PSD2's spot steady for the rest time).
    pub fn at_rest(&self, now: Instant) -> bool {
        let window = self.settings.rest_time;
        let Some((first, _)) = self.recent.front() else {
            return false;
        };
        if now.saturating_duration_since(*first) < window.mul_f64(0.9) {
            return false;
        }
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for (_, p) in &self.recent {
            for k in 0..2 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        (0..2).all(|k| hi[k] - lo[k] <= 2.0 * self.settings.rest_tolerance_mm)
    }

    /// Variance (along, vertical) of PSD2's position after the follower travelled `moved`
    /// mm by its encoder alone.
    fn encoder_var(&self, moved: f64) -> [f64; 2] {
        let s = &self.settings;
        let along = s.encoder_sd_mm + s.encoder_sd_per_mm * moved.abs();
        let vertical = s.vertical_sd_mm + s.vertical_sd_per_mm * moved.abs();
        [along * along, vertical * vertical]
    }

    /// A follower position sampled at `at` (mm) that came with a later status: a reader slower
    /// than the SYNC gets several at once, and every one places frames (the follower's path
    /// between samples far apart is not a straight line).
    pub fn follower_sample(&mut self, at: Instant, mm: f64) {
        if self.follower.is_some_and(|f| f.ready) {
            self.carriage.handle_follower(at, mm, false);
        }
    }

    /// A follower status update.
    pub fn handle_follower(&mut self, state: FollowerState, now: Instant) {
        self.track_motion(state.position_mm);
        if !state.ready {
            self.carriage.clear();
        } else {
            let at = state.at.unwrap_or(now);
            self.carriage
                .handle_follower(at, state.position_mm, state.target_reached);
        }
        self.follower = Some(state);
        if state.ready && self.problem == Some(Problem::NotReady) {
            self.recovered();
        }
        match self.phase.clone() {
            Phase::Moving {
                target,
                via,
                since,
                reached_at,
            } => {
                if !state.ready {
                    self.problem = Some(Problem::NotReady);
                    self.events.push_back(TrackEvent::FollowerProblem(
                        "the follower is not ready".into(),
                    ));
                    self.finish_encoder_step(now);
                    return;
                }
                if let Some(v) = via {
                    if self.reached(&state, v) {
                        self.commands.push_back(FollowerCommand::MoveTo(target));
                        self.phase = Phase::Moving {
                            target,
                            via: None,
                            since,
                            reached_at: None,
                        };
                    } else if self.timed_out(since, v, now) {
                        self.finish_encoder_step(now);
                    }
                } else if self.reached(&state, target) {
                    if reached_at.is_none() {
                        if self.problem == Some(Problem::Late) {
                            self.recovered();
                        }
                        tracing::debug!(
                            position_mm = state.position_mm,
                            target_mm = target,
                            "follower at target"
                        );
                        self.approached();
                        self.phase = Phase::Moving {
                            target,
                            via: None,
                            since,
                            reached_at: Some(now),
                        };
                    }
                } else if self.timed_out(since, target, now) {
                    self.finish_encoder_step(now);
                }
            }
            Phase::Approach {
                encoder_start,
                via,
                target,
                since,
            } => {
                let done = |tr: &mut Tracker| match encoder_start {
                    Some(start) => {
                        tr.encoder_before = start;
                        tr.finish_encoder_step(now);
                    }
                    None => tr.phase = Phase::Watch,
                };
                if !state.ready {
                    done(self);
                    return;
                }
                match self.leg(&state, via, target, since, now) {
                    Leg::OnToTarget => {
                        self.phase = Phase::Approach {
                            encoder_start,
                            via: None,
                            target,
                            since,
                        };
                    }
                    Leg::Arrived => {
                        if self.problem == Some(Problem::Late) {
                            self.recovered();
                        }
                        self.approached();
                        done(self);
                    }
                    Leg::Late => done(self),
                    Leg::Going => {}
                }
            }
            Phase::Seek { via, target, since } => {
                if !state.ready {
                    self.phase = Phase::Watch;
                    return;
                }
                match self.leg(&state, via, target, since, now) {
                    Leg::OnToTarget => {
                        self.phase = Phase::Seek {
                            via: None,
                            target,
                            since,
                        };
                    }
                    Leg::Arrived => {
                        self.approached();
                        self.phase = Phase::Watch;
                        self.recent.clear();
                        if !self.lost {
                            // The spot came back on the way: it is found now that the
                            // follower stands.
                            self.events.push_back(TrackEvent::SpotFound);
                        }
                    }
                    Leg::Late => self.phase = Phase::Watch,
                    Leg::Going => {}
                }
            }
            _ => {}
        }
    }

    /// One status of a move to `target` by the approach point `via` below it (none: the
    /// last leg), begun at `since`: at the approach point (the target is commanded now), at
    /// the target, late (said as a follower problem), or still going.
    fn leg(
        &mut self,
        state: &FollowerState,
        via: Option<f64>,
        target: f64,
        since: Instant,
        now: Instant,
    ) -> Leg {
        match via {
            Some(v) if self.reached(state, v) => {
                self.commands.push_back(FollowerCommand::MoveTo(target));
                Leg::OnToTarget
            }
            None if self.reached(state, target) => Leg::Arrived,
            _ if self.timed_out(since, via.unwrap_or(target), now) => Leg::Late,
            _ => Leg::Going,
        }
    }

    /// The follower reports its target reached, at `target` (within 10 µm, or within a
    /// quarter of the approach when that is shorter, so that the approach point and the
    /// target are told apart).
    fn reached(&self, state: &FollowerState, target: f64) -> bool {
        let tol = match self.settings.approach_mm {
            a if a > 0.0 => (a / 4.0).min(0.01),
            _ => 0.01,
        };
        state.target_reached && (state.position_mm - target).abs() < tol
    }

    /// The follower problem reported last is over (said as an event).
    fn recovered(&mut self) {
        self.problem = None;
        self.events.push_back(TrackEvent::FollowerRecovered);
    }

    /// A move begun at `since` towards `target` has not finished in time (said as an event).
    fn timed_out(&mut self, since: Instant, target: f64, now: Instant) -> bool {
        let late = now.saturating_duration_since(since) > self.settings.move_timeout;
        if late {
            self.problem = Some(Problem::Late);
            self.events.push_back(TrackEvent::FollowerProblem(format!(
                "the follower did not reach {target:.3} mm in {:.1} s",
                self.settings.move_timeout.as_secs_f64()
            )));
        }
        late
    }

    /// The follower ended a move by its approach from below: the stage stands in its "up"
    /// state, whatever the samples showed on the way.
    fn approached(&mut self) {
        if self.settings.approach_mm > 0.0 {
            self.motion = Direction::Up;
            self.motion_anchor = self.follower.map(|f| f.position_mm);
        }
    }

    /// Begin the final approach to where the follower stands (`target`, mm): down to the
    /// approach point, then up. Without an approach configured, at once what follows it.
    fn begin_approach(&mut self, encoder_start: Option<f64>, target: f64, now: Instant) {
        let a = self.settings.approach_mm;
        if a <= 0.0 {
            match encoder_start {
                Some(start) => {
                    self.encoder_before = start;
                    self.finish_encoder_step(now);
                }
                None => self.phase = Phase::Watch,
            }
            return;
        }
        self.commands.push_back(FollowerCommand::MoveTo(target - a));
        self.phase = Phase::Approach {
            encoder_start,
            via: Some(target - a),
            target,
            since: now,
        };
    }

    /// A frame from the I/O module.
    pub fn handle_frame(&mut self, frame: &Frame, now: Instant) {
        self.last_frame_unix_us = frame.unix_us;
        let spot = frame.spots[1].map(|s| [s.x, s.y]);
        let Some(p) = spot else {
            if !self.lost
                && self
                    .last_valid
                    .is_none_or(|t| now.saturating_duration_since(t) > self.settings.lost_after)
            {
                self.lost = true;
                self.valid = false;
                self.recent.clear();
                if !self.seeking() {
                    self.phase = Phase::Watch;
                }
                self.events.push_back(TrackEvent::SpotLost);
            }
            return;
        };
        if self.lost {
            self.lost = false;
            self.events.push_back(TrackEvent::SpotFound);
        }
        self.last_valid = Some(now);
        self.recent.push_back((now, p));
        while let Some((t, _)) = self.recent.front() {
            if now.saturating_duration_since(*t) > self.settings.rest_time {
                self.recent.pop_front();
            } else {
                break;
            }
        }
        let Some(f) = self.follower else {
            return;
        };
        if !f.ready {
            // A follower that is not ready may be homing: its coordinates jump. Keep no
            // history across that.
            self.carriage.clear();
            return;
        }
        self.carriage.handle_frame(now, p[0]);
        if self.seeking() {
            return;
        }
        match self.settings.strategy {
            Strategy::Encoder => self.track_encoder(p, f, now),
            Strategy::Overlap => self.track_overlap(p, f, now),
        }
    }

    /// One step of continuous following: aim at the carriage (placed by the follower's own
    /// samples, so the follower's motion does not feed back into its target), moved on by its
    /// velocity over the lead; the drive moves it on to each SYNC by the same velocity.
    fn follow_step(&mut self, p: [f64; 2], f: FollowerState, now: Instant) {
        if !f.ready {
            return;
        }
        // Before the follower has placed a frame (it has just started to report), the
        // carriage is where the latest report and the spot say, standing.
        let (carriage, v) = self
            .carriage
            .estimate(now)
            .map_or((f.position_mm + p[0], 0.0), |c| {
                (c.position_mm, c.velocity_mm_s)
            });
        if p[0].abs() <= self.settings.follow_band_mm && v.abs() < STANDING_MM_S {
            return;
        }
        let due = self
            .last_follow_cmd
            .is_none_or(|t| now.saturating_duration_since(t) >= self.settings.follow_interval);
        if due {
            let target = carriage + v * self.settings.lead.as_secs_f64();
            tracing::trace!(
                reported = f.position_mm,
                x2 = p[0],
                carriage,
                v,
                target,
                "follow"
            );
            self.commands.push_back(FollowerCommand::Follow {
                target_mm: target,
                velocity_mm_s: v,
                at: now,
            });
            self.last_follow_cmd = Some(now);
            self.followed = true;
            if self.settings.strategy == Strategy::Encoder {
                // In this strategy a "handover" is one follow step.
                self.handovers += 1;
            }
        }
    }

    /// The encoder strategy: follow, and once the carriage has come to rest after the
    /// follower followed it, the follower's final approach.
    fn track_encoder(&mut self, p: [f64; 2], f: FollowerState, now: Instant) {
        if let Phase::Approach { .. } = self.phase {
            if p[0].abs() <= self.settings.follow_band_mm {
                return;
            }
            // The carriage moves on: follow again, the approach at its next stop.
            self.phase = Phase::Watch;
        }
        self.follow_step(p, f, now);
        if self.followed
            && self.at_rest(now)
            && p[0].abs() <= self.settings.follow_band_mm
            && f.target_reached
        {
            self.followed = false;
            self.begin_approach(None, f.position_mm, now);
        }
    }

    fn track_overlap(&mut self, p: [f64; 2], f: FollowerState, now: Instant) {
        let s = self.settings;
        match self.phase.clone() {
            Phase::Watch => {
                if !f.ready {
                    return;
                }
                if self.runs_out(p[0], now) {
                    // The carriage runs the spot towards the edge: follow now, by the encoder.
                    self.phase = Phase::Following {
                        encoder_start: f.position_mm,
                    };
                    self.before_corr = self.corr(f.position_mm);
                    self.follow_step(p, f, now);
                } else if p[0].abs() >= s.handover_mm && self.at_rest(now) {
                    self.before = Stats2::default();
                    self.phase = Phase::Before { since: now };
                    self.before.push(p);
                }
            }
            Phase::Before { .. } => {
                if p[0].abs() >= s.edge_mm || !self.within_rest(p) {
                    // The carriage moved: abandon this handover.
                    self.phase = Phase::Watch;
                    return;
                }
                self.before.push(p);
                if self.before.n >= s.average_frames {
                    let target = f.position_mm + self.before.mean[0];
                    tracing::debug!(
                        before_mm = ?self.before.mean,
                        encoder_mm = f.position_mm,
                        target_mm = target,
                        "handover: follower step"
                    );
                    self.start_move(target, now);
                }
            }
            Phase::Moving {
                reached_at: Some(t),
                ..
            } => {
                if now.saturating_duration_since(t) >= s.settle {
                    self.after = Stats2::default();
                    self.after.push(p);
                    self.phase = Phase::After { since: now };
                }
            }
            Phase::Following { encoder_start } => {
                self.follow_step(p, f, now);
                if self.at_rest(now) && p[0].abs() <= s.follow_band_mm && f.target_reached {
                    self.begin_approach(Some(encoder_start), f.position_mm, now);
                }
            }
            Phase::Approach {
                encoder_start: Some(encoder_start),
                ..
            } if p[0].abs() >= s.edge_mm => {
                // The carriage moves on: follow again, the approach at its next stop.
                self.phase = Phase::Following { encoder_start };
                self.follow_step(p, f, now);
            }
            Phase::Moving { .. } | Phase::Approach { .. } | Phase::Seek { .. } => {}
            Phase::After { .. } => {
                self.after.push(p);
                if self.after.n >= s.average_frames {
                    tracing::debug!(after_mm = ?self.after.mean, "handover: after window");
                    if self.after_is_steady() {
                        self.finish_overlap_step(now);
                    } else {
                        self.finish_encoder_step(now);
                    }
                }
            }
        }
    }

    /// The spot at `x2` (mm) is at the edge, or beyond the handover band with the carriage
    /// running it to the edge within the time the follower needs to start following: at 3.5 mm a carriage accelerating at 500 mm/s² is
    /// 16 ms from PSD2's edge, less than the drive takes to enter cyclic synchronous position
    /// and pick it up, and the spot was lost for ~75 ms at most starts (issue 24).
    fn runs_out(&self, x2: f64, now: Instant) -> bool {
        let s = &self.settings;
        if x2.abs() >= s.edge_mm {
            return true;
        }
        // Inside the handover band a carriage may yet stop (a short jog ends in an exact
        // overlap handover at rest); beyond it, a spot moving outwards fast is followed.
        if x2.abs() < s.handover_mm || self.held {
            return false;
        }
        let Some(c) = self.carriage.estimate(now) else {
            return false;
        };
        let v = c.velocity_mm_s;
        v * x2 > 0.0 && (x2 + v * s.anticipate.as_secs_f64()).abs() >= s.edge_mm
    }

    /// The before-window's spread so far stays within the rest tolerance.
    fn within_rest(&self, p: [f64; 2]) -> bool {
        (0..2).all(|k| (p[k] - self.before.mean[k]).abs() <= 4.0 * self.settings.rest_tolerance_mm)
    }

    fn after_is_steady(&self) -> bool {
        let v = self.after.var();
        let tol = self.settings.rest_tolerance_mm;
        v[0].sqrt() <= tol && v[1].sqrt() <= tol
    }

    fn start_move(&mut self, target: f64, now: Instant) {
        if let Some(f) = self.follower {
            self.encoder_before = f.position_mm;
            self.before_corr = self.corr(f.position_mm);
        }
        // By the approach point below the target when one is configured.
        let a = self.settings.approach_mm;
        let via = (a > 0.0).then_some(target - a);
        self.commands
            .push_back(FollowerCommand::MoveTo(via.unwrap_or(target)));
        self.phase = Phase::Moving {
            target,
            via,
            since: now,
            reached_at: None,
        };
    }

    fn finish_overlap_step(&mut self, now: Instant) {
        let enc_after = self
            .follower
            .map(|f| f.position_mm)
            .unwrap_or(self.encoder_before);
        let (b, a) = (self.before, self.after);
        // PSD2 measures the follower's step only if the carriage stood through it: both
        // windows steady is not enough (a carriage that moved between them, as from a
        // program's overrun point to its target, stands in each). The encoder's own step
        // tells: beyond what the stage's error allows, the step is bridged by the encoder. A
        // storm's stitch stood 2.0 mm off its encoder after one such, and no intermediate
        // target was captured again (issue 24).
        let (enc, enc_var) = self.encoder_step(self.encoder_before, self.before_corr, enc_after);
        let optical = b.mean[0] - a.mean[0];
        let limit = STEP_AGREE_FLOOR_MM + STEP_AGREE_SIGMAS * enc_var[0].sqrt();
        if (optical - enc[0]).abs() > limit {
            tracing::warn!(
                optical_mm = optical,
                encoder_mm = enc[0],
                limit_mm = limit,
                "the carriage moved during a handover: the follower's step is bridged by its encoder"
            );
            self.finish_encoder_step(now);
            return;
        }
        let (vb, va) = (b.var(), a.var());
        let pooled = |k: usize| {
            let dof = (b.n + a.n).saturating_sub(2).max(1) as f64;
            (((b.n.max(1) - 1) as f64 * vb[k] + (a.n.max(1) - 1) as f64 * va[k]) / dof).sqrt()
        };
        let frame_sd = [pooled(0), pooled(1)];
        let delta = [b.mean[0] - a.mean[0], b.mean[1] - a.mean[1]];
        let variance = std::array::from_fn(|k| {
            frame_sd[k].powi(2) * (1.0 / b.n.max(1) as f64 + 1.0 / a.n.max(1) as f64)
        });
        self.apply(HandoverRecord {
            unix_us: self.last_frame_unix_us,
            kind: HandoverKind::Overlap,
            before: b.mean,
            after: a.mean,
            n_before: b.n,
            n_after: a.n,
            frame_sd,
            encoder_before: self.encoder_before,
            encoder_after: enc_after,
            delta,
            variance,
        });
    }

    fn finish_encoder_step(&mut self, _now: Instant) {
        let enc_after = self
            .follower
            .map(|f| f.position_mm)
            .unwrap_or(self.encoder_before);
        // The step is bridged from where the stitch stands. A step whose recorded start is
        // elsewhere (the follower moved in between without a step the tracker saw end: a
        // drive's following error mid-step) counted the distance between the two once more:
        // a storm's stitch stood 3.79 mm off its encoder after one, and no stop was on a
        // target again (issue 24).
        if let Some((at, corr)) = self.step_origin(self.encoder_before) {
            tracing::warn!(
                recorded_mm = self.encoder_before,
                stitch_mm = at,
                "an encoder step began away from the stitch: bridged from the stitch"
            );
            self.encoder_before = at;
            self.before_corr = corr;
        }
        let moved = enc_after - self.encoder_before;
        let (delta, variance) = self.encoder_step(self.encoder_before, self.before_corr, enc_after);
        let record = HandoverRecord {
            unix_us: self.last_frame_unix_us,
            kind: HandoverKind::Encoder,
            before: self.before.mean,
            after: self.after.mean,
            n_before: self.before.n,
            n_after: self.after.n,
            frame_sd: [0.0; 2],
            encoder_before: self.encoder_before,
            encoder_after: enc_after,
            delta,
            variance,
        };
        if moved != 0.0 {
            self.events.push_back(TrackEvent::FollowedWhileMoving {
                from_mm: self.encoder_before,
                to_mm: enc_after,
            });
        }
        self.apply(record);
    }

    fn apply(&mut self, r: HandoverRecord) {
        self.follower_mm += r.delta[0];
        if self.stitch_encoder.is_some() {
            self.stitch_encoder = Some(r.encoder_after);
            self.stitch_corr = self.corr(r.encoder_after);
        }
        self.vertical_mm += r.delta[1];
        match r.kind {
            HandoverKind::Encoder => self.chain_to(r.encoder_before, r.encoder_after),
            HandoverKind::Overlap => {
                // The follower stepped with the carriage standing, measured optically: the
                // chain before it is closed, the next one begins where it stands.
                self.variance = self.total_var();
                self.variance[0] += r.variance[0];
                self.variance[1] += r.variance[1];
                self.chain_from = None;
                self.chain_var = [0.0; 2];
            }
        }
        self.handovers += 1;
        self.before = Stats2::default();
        self.after = Stats2::default();
        self.phase = Phase::Watch;
        self.recent.clear();
        self.events.push_back(TrackEvent::Handover(r));
    }

    /// The next follower command.
    pub fn poll_command(&mut self) -> Option<FollowerCommand> {
        self.commands.pop_front()
    }

    /// The next event.
    pub fn poll_event(&mut self) -> Option<TrackEvent> {
        self.events.pop_front()
    }
}

/// Re-stitch recorded handovers offline: PSD2's displacement from the reference and its
/// variance, using each record's optical difference (`optical`) or its encoder difference.
/// Encoder-kind records use their recorded displacement (the encoder's, with the follower
/// map's correction when one was applied).
pub fn restitch(records: &[HandoverRecord], optical: bool, settings: &TrackSettings) -> Stitch {
    let mut out = Stitch {
        follower_mm: 0.0,
        vertical_mm: 0.0,
        variance: [0.0; 2],
        handovers: records.len(),
        strategy: if optical {
            Strategy::Overlap
        } else {
            Strategy::Encoder
        },
        valid: true,
    };
    for r in records {
        if r.kind == HandoverKind::Encoder || optical {
            // Optical steps, and encoder steps as recorded (with the follower map's
            // correction when one was applied).
            out.follower_mm += r.delta[0];
            out.vertical_mm += r.delta[1];
            out.variance[0] += r.variance[0];
            out.variance[1] += r.variance[1];
        } else {
            let moved = r.encoder_after - r.encoder_before;
            let along = settings.encoder_sd_mm + settings.encoder_sd_per_mm * moved.abs();
            let vertical = settings.vertical_sd_mm + settings.vertical_sd_per_mm * moved.abs();
            out.follower_mm += moved;
            out.variance[0] += along * along;
            out.variance[1] += vertical * vertical;
        }
    }
    out
}

#[cfg(test)]
mod tests;
