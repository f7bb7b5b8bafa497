//! The service's measurement logic, sans-I/O: frames, follower status and drive events go in
//! (with the time), outputs come out (follower targets, captures, handovers, run results),
//! and alarms are kept. The live service's core task drives it from its sockets; the
//! virtual-time lab (`sim::lab`) drives the very same logic on a simulated clock.

use super::api::snapshot::Alarm;
use super::measure::{Measure, ReferenceState};
use crate::acquire::Frame;
use crate::align::Knock;
use crate::canopen::{DriveStatus, Event, PowerState};
use crate::decouple::Decoupler;
use crate::run::{Capture, RunAction, RunMachine};
use crate::track::{
    FollowerCommand, FollowerState, HandoverRecord, TrackEvent, TrackSettings, Tracker,
};
use crate::units::Errors6;
use std::collections::VecDeque;
use std::time::{Duration, Instant};

pub use crate::store::now_us;

/// Active and recently cleared alarms, newest first.
#[derive(Debug, Default)]
pub struct Alarms {
    list: Vec<Alarm>,
}

impl Alarms {
    /// Raise (or update) the alarm `code`.
    pub fn raise(&mut self, code: &str, text: String) {
        if let Some(a) = self.list.iter_mut().find(|a| a.code == code && a.active) {
            a.text = text;
            return;
        }
        tracing::warn!(alarm = code, "{text}");
        self.list.insert(
            0,
            Alarm {
                code: code.into(),
                text,
                since_unix_us: now_us(),
                active: true,
            },
        );
        self.list.truncate(50);
    }

    /// Clear the alarm `code` (it stays in the list, inactive).
    pub fn clear(&mut self, code: &str) {
        for a in self.list.iter_mut().filter(|a| a.code == code && a.active) {
            a.active = false;
            tracing::info!(alarm = code, "cleared");
        }
    }

    /// The alarms, newest first.
    pub fn list(&self) -> &[Alarm] {
        &self.list
    }

    /// Whether `code` is raised now.
    pub fn is_active(&self, code: &str) -> bool {
        self.list.iter().any(|a| a.code == code && a.active)
    }
}

/// What the pipeline asks of its driver.
#[derive(Clone, Debug, PartialEq)]
pub enum Output {
    /// Command the follower (a move: the latest wins; a follow target: sent at once).
    Follower(FollowerCommand),
    /// Stop the follower now (its drive is lost).
    QuickStop,
    /// Enable the follower drive again: its heartbeat came back after a loss that stopped it
    /// (a glitch of the bus or of a loaded host must not end an unattended run).
    ReEnable,
    /// Keep this handover record.
    Handover(HandoverRecord),
    /// Store this capture of the active run.
    Captured(Capture),
    /// Handshake: tell the PLC this target code is captured.
    Acknowledge(u32),
    /// A PSD lost its spot during the run: the run is paused (nothing is captured) until
    /// every spot is back; the driver holds the CNC or stops the program at its next stop.
    RunPaused(String),
    /// Every spot is back (PSD2's stitch re-referenced by the encoder): the driver sends the
    /// rest of the cycle from the next missing capture.
    RunResumed,
    /// The active run has every capture.
    RunFinished,
    /// The active run cannot go on.
    RunFailed(String),
    /// The run's judge flagged this capture (`run::judge`): keep it with the reason, out of
    /// the store when `stored`; the run retakes it.
    Flagged {
        capture: Capture,
        reason: String,
        stored: bool,
    },
    /// Something that can move the positioning reference happened during the run, or the
    /// judge found that it did and shifted the zero back: record it with the run.
    RunEvent { kind: String, detail: String },
    /// A stored capture's u stated again (`RunMachine::turns_bounded`): `capture` as it is
    /// now; keep it with the reason.
    Restated { capture: Capture, reason: String },
}

/// The measurement logic.
#[derive(Debug)]
pub struct Pipeline {
    pub tracker: Tracker,
    pub measure: Measure,
    pub alarms: Alarms,
    drive: Option<DriveStatus>,
    referenced_once: bool,
    /// A resumed run waits for the spot: re-reference by the encoder when PSD2 finds it.
    rereference_on_spot: bool,
    run: Option<RunMachine>,
    outputs: VecDeque<Output>,
    pub last_frame: Option<Frame>,
    pub late_frames: u64,
    /// A zero reference asked for: taken once the window has refilled with no follower step.
    zero: Option<PendingZero>,
    /// Since when each PSD has had no spot.
    no_spot_since: [Option<Instant>; 3],
    /// Why the active run is paused.
    paused: Option<String>,
    /// The follower was quick-stopped for a lost heartbeat (re-enabled when it comes back).
    stopped_for_heartbeat: bool,
    /// Where the carriage stands in the follower's encoder coordinates, less the nominal it
    /// stands at (mm), from the last rest on a target: where a follower that lost the spot
    /// finds it.
    carriage_offset_mm: Option<f64>,
}

/// A zero reference on its way (see [`Pipeline::begin_zero`]).
#[derive(Clone, Copy, Debug)]
struct PendingZero {
    due: Instant,
    window: Duration,
    retakes: u8,
}

/// A zero is retaken at most this many times for follower steps in its window.
const ZERO_RETAKES: u8 = 3;

/// A knock's step is placed to within this: the captures it may have reached are counted
/// from this much before it.
const KNOCK_PLACED: Duration = Duration::from_millis(100);

/// A PSD without a spot for this long pauses a run (a beam cut for a moment does not).
pub const PAUSE_AFTER: Duration = Duration::from_millis(500);

impl Pipeline {
    /// A pipeline with these tracking settings, decoupler and live window.
    pub fn new(tracking: TrackSettings, decoupler: Decoupler, live_window: Duration) -> Self {
        Pipeline {
            tracker: Tracker::new(tracking),
            measure: Measure::new(decoupler, live_window),
            alarms: Alarms::default(),
            drive: None,
            referenced_once: false,
            rereference_on_spot: false,
            run: None,
            outputs: VecDeque::new(),
            last_frame: None,
            late_frames: 0,
            zero: None,
            no_spot_since: [None; 3],
            stopped_for_heartbeat: false,
            paused: None,
            carriage_offset_mm: None,
        }
    }

    /// Whether the beam is off the fixed PSDs (PSD1 or PSD3 has no spot): blocked, or the head
    /// knocked. PSD2 alone without a spot is the follower behind the carriage, which the
    /// carriage's next pass brings back.
    pub fn beam_lost(&self) -> bool {
        self.no_spot_since[0].is_some() || self.no_spot_since[2].is_some()
    }

    /// Why the active run is paused, if it is.
    pub fn paused(&self) -> Option<&str> {
        self.paused.as_deref()
    }

    /// Pause or resume the active run by the PSDs' spots at `now`.
    fn judge_spots(&mut self, now: Instant) {
        if self.run.is_none() {
            self.paused = None;
            return;
        }
        let lost: Vec<String> = (0..3)
            .filter(|&k| {
                self.no_spot_since[k]
                    .is_some_and(|t| now.saturating_duration_since(t) >= PAUSE_AFTER)
            })
            .map(|k| format!("PSD{}", k + 1))
            .collect();
        match (&self.paused, lost.is_empty()) {
            (None, false) => {
                // PSD2 alone, with its follower not following: the stage, not the beam.
                let follower_down = self.follower_state().is_none_or(|f| !f.ready);
                let what = if lost == ["PSD2"] && !follower_down {
                    "the follower lost the carriage and goes to it at the next target".to_string()
                } else if lost == ["PSD2"] && follower_down {
                    let state = self
                        .drive
                        .as_ref()
                        .and_then(|d| d.state)
                        .map(|s| s.to_string())
                        .unwrap_or_else(|| "unknown".into());
                    format!(
                        "the follower drive is not following (state {state}): enable and home it on screen 2"
                    )
                } else {
                    "clear the beam or realign the head (axiscomp align)".to_string()
                };
                let msg = format!(
                    "{} {} no spot: the run is paused; {what}, and it resumes at the next missing capture",
                    lost.join(", "),
                    if lost.len() == 1 { "has" } else { "have" }
                );
                // A lost PSD2 is the tracker's SpotLost, which has the encoder bridge the gap
                // when the spot is back.
                self.alarms.raise("run-paused", msg.clone());
                if let Some(run) = &mut self.run {
                    run.interrupt();
                }
                self.drain_run();
                self.paused = Some(msg.clone());
                self.outputs.push_back(Output::RunPaused(msg));
            }
            (Some(_), true)
                if self.no_spot_since.iter().all(Option::is_none)
                    && !self.rereference_on_spot
                    && self.tracker.stitch().valid =>
            {
                self.paused = None;
                self.alarms.clear("run-paused");
                self.measure.restart();
                if let Some(run) = &mut self.run {
                    run.pause_ended();
                }
                self.outputs.push_back(Output::RunResumed);
            }
            _ => {}
        }
    }

    /// The next output.
    pub fn poll_output(&mut self) -> Option<Output> {
        self.outputs.pop_front()
    }

    /// The follower as the tracker needs it: ready only when homed and not homing (before
    /// that its encoder is not the stage's position, and following would fight the homing).
    pub fn follower_state(&self) -> Option<FollowerState> {
        let st = self.drive.as_ref()?;
        Some(FollowerState {
            position_mm: st.position_mm?,
            ready: st.state == Some(PowerState::OperationEnabled)
                && st.heartbeat_ok
                && !st.emcy_active
                && st.homed
                && st.busy != Some("home"),
            target_reached: st.target_reached,
            at: st.position_at,
        })
    }

    /// A frame, judged at its own time `f.at`. A `late` frame (the driver fell behind) is
    /// tracked but not decoupled.
    pub fn handle_frame(&mut self, f: &Frame, late: bool) {
        let now = f.at;
        self.last_frame = Some(*f);
        for (k, since) in self.no_spot_since.iter_mut().enumerate() {
            match f.spots[k] {
                Some(_) => *since = None,
                None => {
                    since.get_or_insert(now);
                }
            }
        }
        match f.spots.iter().position(Option::is_none) {
            Some(k) => self.alarms.raise(
                "beam-blocked",
                format!(
                    "PSD{} has no spot (SUM {:.2} V): beam blocked or off the PSD; frames are not used",
                    k + 1,
                    f.sums[k]
                ),
            ),
            None => self.alarms.clear("beam-blocked"),
        }
        self.tracker.handle_frame(f, now);
        // The stitch starts where the follower is when first seen ready, homed and idle, with
        // the spot on PSD2; after that only a zero reference re-references it.
        if !self.referenced_once
            && !self.tracker.stitch().valid
            && f.spots[1].is_some()
            && self
                .drive
                .as_ref()
                .is_some_and(|d| d.homed && d.busy.is_none())
            && self
                .follower_state()
                .is_some_and(|s| s.ready && s.target_reached)
        {
            // A zero kept across a restart brings the stitch it was taken with: bridged from
            // there by the encoder, not referenced afresh where the follower stands now.
            self.referenced_once = if self.tracker.anchored() {
                let bridged = self.tracker.reference_by_encoder();
                if bridged {
                    tracing::info!(
                        "PSD2's stitch bridged by the follower's encoder from where it stood at the zero"
                    );
                }
                bridged
            } else {
                self.tracker.reference()
            };
        }
        self.drain_tracker();
        self.judge_spots(now);
        self.place_carriage(f, now);
        if late {
            self.late_frames += 1;
            return;
        }
        match self.measure.handle_frame(f, &self.tracker.stitch(), now) {
            Ok(sample) => {
                self.alarms.clear("decoupling");
                if let Some(k) = self.measure.take_knock() {
                    self.knocked(&k);
                }
                if let Some(a) = self.measure.take_bounded()
                    && let Some(run) = self.run.as_mut()
                {
                    let what = a.words();
                    let measure = &self.measure;
                    run.turns_bounded(|travel| measure.turns_var(travel), &what);
                    self.drain_run();
                }
                if let (Some(run), Some(s), None) = (self.run.as_mut(), sample, &self.paused) {
                    run.handle_sample(&s, now);
                    run.handle_timeout(now);
                    self.drain_run();
                }
            }
            Err(e) => self
                .alarms
                .raise("decoupling", format!("a frame could not be decoupled: {e}")),
        }
    }

    fn drain_tracker(&mut self) {
        while let Some(cmd) = self.tracker.poll_command() {
            self.outputs.push_back(Output::Follower(cmd));
        }
        while let Some(e) = self.tracker.poll_event() {
            match e {
                TrackEvent::Handover(r) => {
                    tracing::debug!(?r.kind, delta_mm = r.delta[0], "handover");
                    self.measure.restart();
                    if let Some(run) = &mut self.run {
                        run.restart_average();
                    }
                    self.outputs.push_back(Output::Handover(r));
                }
                TrackEvent::FollowedWhileMoving { from_mm, to_mm } => {
                    tracing::debug!(from_mm, to_mm, "followed by encoder while moving");
                    self.measure.restart();
                    if let Some(run) = &mut self.run {
                        run.restart_average();
                    }
                }
                TrackEvent::SpotLost if self.rereference_on_spot => {
                    tracing::info!("PSD2 has no spot yet: waiting for the carriage");
                }
                TrackEvent::SpotLost if self.run.is_some() => {
                    // The run pauses (judge_spots); the encoder bridges the gap when the spot
                    // is back.
                    self.rereference_on_spot = true;
                    self.alarms.raise(
                        "stitch-broken",
                        "PSD2 lost the spot during the run: positioning is bridged by the follower's encoder when it is back".into(),
                    );
                }
                TrackEvent::SpotLost => {
                    self.alarms.raise(
                        "stitch-broken",
                        "PSD2 lost the spot: positioning has lost its reference; zero again (control: zero)".into(),
                    );
                }
                TrackEvent::SpotFound if self.rereference_on_spot => {
                    if self.tracker.reference_by_encoder() {
                        self.rereference_on_spot = false;
                        self.measure.restart();
                        self.alarms.clear("stitch-broken");
                        tracing::info!("PSD2 found the spot: stitch re-referenced by the encoder");
                        self.reference_event(
                            "stitch-rereferenced",
                            "PSD2's stitch re-referenced by the follower's encoder".into(),
                        );
                    }
                }
                TrackEvent::SpotFound => tracing::info!("PSD2 sees the spot again"),
                TrackEvent::FollowerProblem(p) => self.alarms.raise("follower", p),
                TrackEvent::FollowerRecovered => {
                    tracing::info!("the follower serves the tracker again");
                    self.alarms.clear("follower");
                }
            }
        }
    }

    /// The carriage rests on a target of the run (its nominal set) with PSD2 on the spot:
    /// where it stands in the follower's encoder coordinates, less the nominal.
    fn place_carriage(&mut self, f: &Frame, now: Instant) {
        // Cheapest first: a nominal is set only while the run averages on a target.
        let (Some(nominal), Some(spot), true) =
            (self.measure.nominal(), f.spots[1], self.run.is_some())
        else {
            return;
        };
        if let Some(fs) = self.follower_state().filter(|s| s.ready)
            && self.tracker.at_rest(now)
            && self.tracker.stitch().valid
        {
            self.carriage_offset_mm = Some(fs.position_mm + spot.x - nominal);
        }
    }

    fn drain_run(&mut self) {
        let Some(run) = self.run.as_mut() else {
            return;
        };
        let mut finished = None;
        while let Some(a) = run.poll_action() {
            match a {
                RunAction::SetNominal(n) => self.measure.set_nominal(n),
                RunAction::Captured(c) => self.outputs.push_back(Output::Captured(c)),
                RunAction::Acknowledge { code } => {
                    self.outputs.push_back(Output::Acknowledge(code))
                }
                RunAction::Finished => finished = Some(Output::RunFinished),
                RunAction::Failed(msg) => finished = Some(Output::RunFailed(msg)),
                RunAction::Flagged {
                    capture,
                    reason,
                    stored,
                } => {
                    tracing::warn!("capture flagged: {reason}");
                    self.alarms.raise("capture-flagged", reason.clone());
                    self.outputs.push_back(Output::Flagged {
                        capture,
                        reason,
                        stored,
                    });
                }
                RunAction::Restated { capture, reason } => {
                    tracing::info!("{reason}");
                    self.outputs.push_back(Output::Restated { capture, reason });
                }
                RunAction::ShiftZero { by, reason } => {
                    tracing::warn!("zero shifted back: {reason}");
                    self.measure.shift_zero(by);
                    self.outputs.push_back(Output::RunEvent {
                        kind: "zero-shifted".into(),
                        detail: reason,
                    });
                }
            }
        }
        if let Some(out) = finished {
            self.run = None;
            self.alarms.clear("capture-flagged");
            if self.paused.take().is_some() {
                self.alarms.clear("run-paused");
            }
            self.measure.set_nominal(None);
            self.outputs.push_back(out);
        }
    }

    /// A follower drive status update.
    pub fn handle_drive_status(&mut self, st: &DriveStatus, now: Instant) {
        self.drive = Some(st.clone());
        if let Some(fs) = self.follower_state() {
            if fs.ready {
                for &(at, mm) in st.recent_positions.iter().flatten() {
                    self.tracker.follower_sample(at, mm);
                }
            }
            self.tracker.handle_follower(fs, now);
            self.drain_tracker();
        }
    }

    /// Something that could move the positioning reference happened during the active run:
    /// it is recorded with the run. When the reference itself was taken again (PSD2's stitch
    /// re-referenced by the encoder, a resume after a restart) the run holds its captures
    /// until one checks the reference (`run::judge`); a drive fault, a stop or a lost
    /// heartbeat moves the reference only through such a re-reference (the optical stitch
    /// carries it otherwise), so they are recorded, not held for.
    pub fn reference_event(&mut self, kind: &str, detail: String) {
        let Some(run) = self.run.as_mut() else {
            return;
        };
        let moves = match kind {
            "stitch-rereferenced" => Some(stitch_moves(
                self.measure.decoupler(),
                self.tracker.stitch().follower_mm,
            )),
            "resumed" => Some(crate::run::judge::MOVES_ALL),
            _ => None,
        };
        if let Some(moves) = moves {
            run.reference_event(&detail, moves);
        }
        self.outputs.push_back(Output::RunEvent {
            kind: kind.into(),
            detail,
        });
    }

    /// The live pipeline found a knock that turned the head on its mount and takes its turn
    /// out of every frame from now on; the active run retakes what the frames before that
    /// touched and checks what follows (`RunMachine::knocked`).
    fn knocked(&mut self, k: &Knock) {
        let what = format!("a knock turned the head on its mount ({})", k.describe());
        tracing::warn!("{what}: taken out of every frame from it on");
        let Some(run) = self.run.as_mut() else {
            return;
        };
        run.knocked(k.since.earlier(KNOCK_PLACED), &what);
        self.drain_run();
        self.outputs.push_back(Output::RunEvent {
            kind: "knock".into(),
            detail: what,
        });
    }

    /// A follower drive event; `peer` names the CAN link in alarms.
    pub fn handle_drive_event(&mut self, e: &Event, peer: &str) {
        match e {
            Event::FollowingEnded(Err(err)) => self.reference_event(
                "following-ended",
                format!("the follower's following ended on an error ({err})"),
            ),
            Event::PowerState { to, .. }
                if matches!(
                    to,
                    PowerState::Fault
                        | PowerState::FaultReactionActive
                        | PowerState::QuickStopActive
                ) =>
            {
                self.reference_event("drive-stopped", format!("the follower drive went to {to}"))
            }
            _ => {}
        }
        match e {
            Event::HeartbeatLost => {
                self.reference_event(
                    "heartbeat-lost",
                    format!("the follower drive's heartbeat lost ({peer})"),
                );
                self.alarms.raise(
                    "heartbeat-lost",
                    format!("the follower drive's heartbeat stopped ({peer}): follower stopped"),
                );
                self.outputs.push_back(Output::QuickStop);
                self.stopped_for_heartbeat = true;
            }
            Event::HeartbeatResumed => {
                self.alarms.clear("heartbeat-lost");
                if std::mem::take(&mut self.stopped_for_heartbeat) {
                    self.outputs.push_back(Output::ReEnable);
                }
            }
            Event::Emcy(emcy) => {
                if emcy.is_reset() {
                    self.alarms.clear("drive-fault");
                } else {
                    self.reference_event("drive-fault", format!("a follower drive fault ({emcy})"));
                    self.alarms.raise(
                        "drive-fault",
                        format!("follower drive EMCY: {emcy}; reset it with the follower fault_reset command"),
                    );
                }
            }
            Event::BootUp { expected: false } => {
                self.reference_event("drive-rebooted", "the follower drive rebooted".into());
                self.alarms.raise(
                    "drive-rebooted",
                    "the follower drive rebooted: reconfiguring it".into(),
                );
                self.tracker.forget();
            }
            _ => {}
        }
    }

    /// Break the stitch (the follower was moved outside the tracker's control).
    pub fn invalidate_stitch(&mut self, why: &str) {
        self.tracker.invalidate();
        self.alarms.raise("stitch-broken", why.to_string());
    }

    /// Start a zero reference: re-reference the stitch now and take the live mean as zero
    /// once the averaging window has refilled (`zero_ready`). False when the follower's
    /// position is not known yet.
    ///
    /// A follower step in the window (PSD2 centred on the spot right after the reference) is
    /// placed by an encoder that lags the frames, and moved the zero by up to 40 µm on mounted
    /// heads: the zero waits for the step to end and is taken again over a fresh window (at
    /// most `ZERO_RETAKES` times).
    pub fn begin_zero(&mut self, now: Instant, window: Duration) -> bool {
        if !self.reference_for_zero() {
            return false;
        }
        self.zero = Some(PendingZero {
            due: now + window + Duration::from_millis(50),
            window,
            retakes: 0,
        });
        true
    }

    fn reference_for_zero(&mut self) -> bool {
        if !self.tracker.reference() {
            return false;
        }
        self.referenced_once = true;
        self.rereference_on_spot = false;
        self.alarms.clear("stitch-broken");
        self.measure.restart();
        self.measure.start_zero();
        true
    }

    /// Whether a zero reference is on its way.
    pub fn zero_pending(&self) -> bool {
        self.zero.is_some()
    }

    /// When a zero reference is pending and due at `now`: take it (`Some(Some(offsets))`), or
    /// report that there were no valid frames (`Some(None)`).
    pub fn zero_ready(&mut self, now: Instant) -> Option<Option<Errors6>> {
        let z = self.zero?;
        if now < z.due {
            return None;
        }
        let stepping = self.tracker.handing_over();
        let stepped = stepping || self.tracker.stitch().handovers > 0;
        // A step that does not end (the follower cannot reach the spot) does not hold the
        // zero for ever: after this long it is taken as it is.
        let waited_out = now >= z.due + Duration::from_secs(10);
        if stepped && z.retakes < ZERO_RETAKES && !waited_out {
            // Wait for the step's end, then refill the window from a new reference.
            if stepping || !self.reference_for_zero() {
                return None;
            }
            self.zero = Some(PendingZero {
                due: now + z.window + Duration::from_millis(50),
                retakes: z.retakes + 1,
                ..z
            });
            return None;
        }
        self.zero = None;
        Some(self.measure.set_zero(self.tracker.anchor()))
    }

    /// Take back the zero reference kept across a restart, with the stitch it was taken with
    /// (bridged by the encoder at the first frame that has the spot).
    pub fn restore_reference(&mut self, state: &ReferenceState) -> Result<(), String> {
        self.measure.restore_reference(state)?;
        if let Some(a) = &state.stitch {
            self.tracker.restore(a);
        }
        Ok(())
    }

    /// Start measuring a resumed run: the carriage may be away from PSD2 (it went on while
    /// the service was down), so the spot is awaited, not failed on, and the stitch is
    /// re-referenced by the encoder when it comes (at once when PSD2 sees it already).
    pub fn resume_run(&mut self, machine: RunMachine) {
        self.start_run(machine);
        self.reference_event("resumed", "a resume after a restart".into());
        self.rereference_on_spot = true;
        if !self.tracker.stitch().valid || self.tracker.is_lost() {
            self.tracker.invalidate();
        } else if self.tracker.reference_by_encoder() {
            self.rereference_on_spot = false;
        }
    }

    /// Start measuring a run.
    pub fn start_run(&mut self, machine: RunMachine) {
        self.run = Some(machine);
        self.drain_run();
    }

    /// Stop the active run, if any.
    pub fn abort_run(&mut self) -> bool {
        let had = self.run.take().is_some();
        if self.paused.take().is_some() {
            self.alarms.clear("run-paused");
        }
        if had {
            self.measure.set_nominal(None);
        }
        had
    }

    /// The active run's progress (captures taken, expected).
    pub fn run_progress(&self) -> Option<(usize, usize)> {
        self.run.as_ref().map(RunMachine::progress)
    }

    /// The active run's judge: captures flagged, captures held, and the event they wait on.
    pub fn run_judged(&self) -> Option<(usize, usize, Option<String>)> {
        self.run.as_ref().map(|r| {
            let (f, h, e) = r.judged();
            (f, h, e.map(str::to_string))
        })
    }

    /// The active run's flagged captures.
    pub fn run_flagged(&self) -> Option<std::collections::BTreeSet<crate::run::TargetKey>> {
        self.run.as_ref().map(|r| r.flagged().clone())
    }

    /// The active run's missing captures.
    pub fn run_missing(&self) -> Option<Vec<crate::run::TargetKey>> {
        self.run.as_ref().map(RunMachine::missing)
    }

    /// A handshake report from the PLC: the CNC is at the target with this code.
    pub fn handle_at_target(&mut self, code: u32, now: Instant) {
        let Some(run) = self.run.as_mut() else {
            return;
        };
        run.handle_at_target(code, now);
        self.drain_run();
        if let Some(nominal) = self.measure.nominal() {
            self.seek_carriage(nominal, now);
        }
    }

    /// PSD2 has lost the spot and the carriage went on without the follower (a drive fault,
    /// a following error): send the follower to where the carriage stands or will stop, at
    /// `nominal_mm` on the axis, placed by the last rest on a target. A make-up pass visits
    /// only the missing targets and may never pass the follower where it stood. Whether it was
    /// sent (not when the spot is not lost, no rest has placed the carriage yet, or the
    /// follower is not ready).
    pub fn seek_carriage(&mut self, nominal_mm: f64, now: Instant) -> bool {
        let Some(offset) = self.carriage_offset_mm.filter(|_| self.tracker.is_lost()) else {
            return false;
        };
        let sent = self.tracker.seek(nominal_mm + offset, now);
        if sent {
            self.drain_tracker();
        }
        sent
    }
}

/// The errors a move of PSD2's stitch can move (`run::judge`): those that a micrometre of
/// PSD2 along or vertically moves by at least 0.01 µm or 0.01″ at `travel` (with the
/// reference layout: positioning, the vertical straightness and roll). Every error when the
/// decoupler cannot say.
fn stitch_moves(decoupler: &Decoupler, travel: f64) -> [bool; 6] {
    match crate::evaluate::uncertainty::psd2_sensitivity(decoupler, travel) {
        Ok(s) => std::array::from_fn(|k| {
            let per_um = (s[k][0] + s[k][1]) * 1e-3;
            let floor = if k < 3 {
                1e-5
            } else {
                0.01 * crate::units::RAD_PER_ARCSEC
            };
            per_um >= floor
        }),
        Err(_) => crate::run::judge::MOVES_ALL,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decouple::{Method, SolveOptions, Source};
    use crate::optics::Layout;

    fn pipeline() -> Pipeline {
        let decoupler = Decoupler {
            source: Source::Simulated(Layout::reference()),
            method: Method::Nonlinear,
            sigma_mm: [1e-3; 6],
            options: SolveOptions::default(),
        };
        Pipeline::new(
            TrackSettings::default(),
            decoupler,
            Duration::from_millis(200),
        )
    }

    #[test]
    fn a_stitch_moves_positioning_vertical_straightness_and_roll_only() {
        let p = pipeline();
        for travel in [0.0, 500.0, 1000.0] {
            assert_eq!(
                stitch_moves(p.measure.decoupler(), travel),
                [false, true, true, false, true, false],
                "at {travel} mm"
            );
        }
    }

    fn outputs(p: &mut Pipeline) -> Vec<Output> {
        std::iter::from_fn(|| p.poll_output()).collect()
    }

    /// A lost heartbeat stops the follower; when it comes back the drive is enabled again
    /// (once), so a glitch does not leave an unattended run with a dead follower.
    #[test]
    fn the_follower_is_enabled_again_when_its_heartbeat_comes_back() {
        let mut p = pipeline();
        p.handle_drive_event(&Event::HeartbeatResumed, "can0");
        assert!(outputs(&mut p).is_empty(), "nothing was stopped");
        p.handle_drive_event(&Event::HeartbeatLost, "can0");
        assert!(matches!(outputs(&mut p)[..], [Output::QuickStop]));
        assert!(p.alarms.is_active("heartbeat-lost"));
        p.handle_drive_event(&Event::HeartbeatResumed, "can0");
        assert!(matches!(outputs(&mut p)[..], [Output::ReEnable]));
        assert!(!p.alarms.is_active("heartbeat-lost"));
        p.handle_drive_event(&Event::HeartbeatResumed, "can0");
        assert!(outputs(&mut p).is_empty(), "enabled once");
    }
}
