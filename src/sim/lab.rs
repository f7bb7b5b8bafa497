//! The virtual-time lab: the whole measurement chain on a simulated clock. The plant; the I/O
//! module's registers, encoded and decoded through the I/O map; the follower's CiA 402 drive
//! and the service's CANopen master exchanging real CAN frames; the service's pipeline
//! (tracking, stitching, decoupling, the run machine); the twin's CNC running the part program
//! text the service generates, with the PLC handshake when asked for.
//!
//! Only the transports are left out (they are tested on their own, in real time, over
//! loopback and the kernel's CAN stack): every part here is the production state machine, and
//! time is an argument to all of them. So a five-run ISO 230-2 cycle over a metre, a quarter of
//! an hour on the machine, takes seconds — for the acceptance tests, the demo and the closed
//! loop.

use super::SimError;
use super::cnc::{Cnc, parse};
use super::drive::{TwinDrive, TwinDriveConfig};
use super::plant::{Plant, PlantSpec, Truth};
use crate::acquire::IoMap;
use crate::acquire::decode::{Reading, encode, frame};
use crate::align::{Advice, AlignSettings, Check, Observed, SpotSource, Station};
use crate::canopen::{Command, DriveConfig, DriveError, DriveStatus, Event, Master, OpId};
use crate::config::Settings;
use crate::decouple::Decoupler;
use crate::optics::Layout;
use crate::optics::Spot;
use crate::run::program::{CaptureMode, generate};
use crate::run::session::{Next, Session};
use crate::run::{Capture, CaptureSettings, Dialect, Plan, RunMachine, TargetKey};
use crate::service::pipeline::{Output, Pipeline, now_us};
use crate::track::{FollowerCommand, HandoverRecord, TrackSettings};
use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::{Duration, Instant};
use thiserror::Error;

/// Why the lab stopped.
#[derive(Debug, Error)]
pub enum LabError {
    #[error("lab set-up: {0}")]
    Setup(#[from] SimError),
    #[error("follower drive settings: {0}")]
    Drive(#[from] crate::canopen::ConfigError),
    #[error("the follower's {what} failed: {why}")]
    BringUp { what: &'static str, why: String },
    #[error("{what} did not happen within {:.0} s of simulated time", within.as_secs_f64())]
    Timeout { what: String, within: Duration },
    #[error("part program: {0}")]
    Program(String),
    #[error("the plan: {0}")]
    Plan(String),
    #[error("the run failed: {0}")]
    RunFailed(String),
    #[error("the run is incomplete: {0}")]
    Incomplete(String),
    #[error("the pre-run check refused the run: {check}; align the head first (axiscomp align)")]
    Refused { check: String },
    #[error("the alignment did not pass in {rounds} rounds: {check}")]
    NotAligned { rounds: usize, check: String },
    #[error("alignment: {0}")]
    Align(#[from] crate::align::AlignError),
    #[error("I/O map: {0}")]
    Io(String),
    #[error("the lab's clock stalled at {:.3} s: a state machine keeps asking for the same instant", .0.as_secs_f64())]
    Stalled(Duration),
}

/// What the lab is built from.
#[derive(Clone, Debug)]
pub struct LabSpec {
    /// The head's nominal layout (the plant draws its true one from it).
    pub layout: Layout,
    pub plant: PlantSpec,
    pub twin_drive: TwinDriveConfig,
    pub map: IoMap,
    /// The service side: the master's drive settings, tracking and capture settings.
    pub drive: DriveConfig,
    pub tracking: TrackSettings,
    pub capture: CaptureSettings,
    pub live_window: Duration,
    pub decoupler: Decoupler,
    /// The I/O module's sampling period (the service polls it at this rate).
    pub frame_period: Duration,
}

impl LabSpec {
    /// The lab for a twin (`axiscomp sim` config) and a service (`serve` settings, with the
    /// head's decoupler).
    pub fn new(
        layout: &Layout,
        twin: &super::twin::TwinSpec,
        settings: &Settings,
        decoupler: Decoupler,
    ) -> LabSpec {
        LabSpec::with_parts(
            layout,
            twin.plant.clone(),
            twin.drive,
            twin.io_map.clone(),
            settings,
            decoupler,
        )
    }

    fn with_parts(
        layout: &Layout,
        plant: PlantSpec,
        twin_drive: TwinDriveConfig,
        map: IoMap,
        settings: &Settings,
        decoupler: Decoupler,
    ) -> LabSpec {
        LabSpec {
            layout: layout.clone(),
            plant,
            twin_drive,
            map,
            drive: settings.follower.drive,
            tracking: settings.tracking,
            capture: settings.capture,
            live_window: settings.head.live_window,
            decoupler,
            // At 0 Hz the module is read as fast as it answers: 2 ms here.
            frame_period: if settings.io.acquire.rate_hz > 0.0 {
                Duration::from_secs_f64(1.0 / settings.io.acquire.rate_hz)
            } else {
                Duration::from_millis(2)
            },
        }
    }
}

/// The service's dwell check at the lab's frame period, with its follower's rest at each stop.
fn check_dwell(
    capture: &CaptureSettings,
    frame_period: Duration,
    tracking: &TrackSettings,
    plan: &Plan,
) -> Result<(), LabError> {
    let rate_hz = 1.0 / frame_period.as_secs_f64().max(1e-6);
    capture
        .check_dwell(plan, rate_hz, tracking.rest_at_stop())
        .map_err(LabError::Plan)
}

impl LabSpec {
    /// Refuse a plan these settings cannot capture (a dwell too short: the service's own
    /// check, at the lab's frame rate and with its follower's rest at each stop).
    pub fn check_plan(&self, plan: &Plan) -> Result<(), LabError> {
        check_dwell(&self.capture, self.frame_period, &self.tracking, plan)
    }

    /// The reference head on `plant`, the service's built-in settings and I/O map, the
    /// follower starting 2 mm from its home switch; decoupling with `decoupler`, or with the
    /// nominal layout when `None` (right for a head without installation errors).
    pub fn standard(plant: PlantSpec, decoupler: Option<Decoupler>) -> Result<LabSpec, LabError> {
        let input = |e: String| LabError::Setup(SimError::Input(e));
        let settings = crate::config::load(&crate::config::Layers::default())
            .map_err(|e| input(format!("built-in settings: {e}")))?;
        let layout = Layout::reference();
        let decoupler = decoupler.unwrap_or_else(|| Decoupler {
            source: crate::decouple::Source::Simulated(layout.clone()),
            method: crate::decouple::Method::Nonlinear,
            sigma_mm: [plant.noise_mm.max(1e-6); 6],
            options: crate::decouple::SolveOptions::default(),
        });
        let map = IoMap::generic().map_err(|e| input(format!("generic I/O map: {e}")))?;
        let drive = TwinDriveConfig {
            start_mm: 2.0,
            ..TwinDriveConfig::default()
        };
        let mut spec = LabSpec::with_parts(&layout, plant, drive, map, &settings, decoupler);
        // The follower's stage covers the twin's axis (it follows the carriage all the way).
        let limits = &mut spec.drive.limits;
        limits.max_mm = limits.max_mm.max(spec.plant.axis.length_mm + 100.0);
        Ok(spec)
    }
}

/// One capture with the twin's truth when it was taken.
#[derive(Clone, Debug, PartialEq)]
pub struct TrueCapture {
    pub capture: Capture,
    pub truth: Truth,
}

/// A measured run.
#[derive(Clone, Debug)]
pub struct LabRun {
    pub captures: Vec<TrueCapture>,
    pub handovers: Vec<HandoverRecord>,
    /// The part program the CNC ran.
    pub program: String,
    /// Simulated time from the program's start to the last capture.
    pub duration: Duration,
}

/// Progress of a run, for whoever shows it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Progress {
    pub captures: usize,
    pub expected: usize,
    /// Simulated seconds since the program started.
    pub elapsed_s: f64,
    pub position_mm: f64,
    /// Whether the carriage is moving.
    pub moving: bool,
}

/// One frame as the lab saw it (`Lab::trace`), for finding out why a run went wrong.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TraceRow {
    /// Simulated seconds.
    pub t_s: f64,
    pub truth: Truth,
    /// PSD2's spot as read (mm).
    pub psd2: Option<(f64, f64)>,
    /// The stitch's follower position (mm), when valid.
    pub stitch_mm: Option<f64>,
    /// The measured carriage position of the frame (mm), when it was decoupled.
    pub position_mm: Option<f64>,
}

/// Counters.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LabStats {
    pub frames: u64,
    pub can_frames: u64,
    pub follow_targets: u64,
    pub follow_refused: u64,
}

/// Where the handshake stands between the CNC and the service (the PLC's part).
#[derive(Clone, Copy, Debug, Default)]
struct Plc {
    at_target_seen: bool,
    acknowledged: Option<u32>,
}

/// The lab.
pub struct Lab {
    /// The head's nominal layout (what the service knows of it).
    layout: Layout,
    t0: Instant,
    unix0_us: i64,
    now: Instant,
    pub plant: Arc<Plant>,
    drive: TwinDrive,
    master: Master,
    pub pipeline: Pipeline,
    map: IoMap,
    capture: CaptureSettings,
    frame_period: Duration,
    next_frame: Instant,
    seq: u64,
    cnc: Option<Cnc>,
    plc: Plc,
    status: DriveStatus,
    completed: Vec<(OpId, Result<(), String>)>,
    captures: Vec<TrueCapture>,
    handovers: Vec<HandoverRecord>,
    run_end: Option<Result<(), String>>,
    /// A follower target waiting for the set-point in progress.
    pending_follow: Option<f64>,
    pub stats: LabStats,
    /// Every frame, when set to `Some` (off by default: it grows by a row per frame).
    pub trace: Option<Vec<TraceRow>>,
    /// The spots of every frame while a station is read.
    spot_log: Option<Vec<[Option<Spot>; 3]>>,
    /// The last alignment check that passed.
    alignment: Option<Check>,
    /// How the lab's technician aligns the head.
    pub align: AlignSettings,
    /// The lab's technician realigns a head whose spots left their PSDs during a run (the
    /// targets show the beam off the PSD, not blocked), instead of waiting for them.
    pub realign_when_paused: bool,
    /// What the last run went through: pauses (with why) and resumptions.
    pub pauses: Vec<String>,
    /// The last run's flagged captures (`run::judge`), with the truth when each was taken and
    /// the reason.
    pub flags: Vec<(TrueCapture, String)>,
    /// The last run's events that could move the reference (kind, what).
    pub events: Vec<(String, String)>,
    /// The truth every 100 ms over the last hour (µs since the epoch): a capture held until
    /// the judge checked it is compared with the truth of when it was taken.
    truths: std::collections::VecDeque<(i64, Truth)>,
    /// The last run's programs after the first (resumed and make-up ones).
    pub extra_programs: usize,
}

/// The truth is kept every this often (µs), this many times (an hour).
const TRUTH_EVERY_US: i64 = 100_000;
const TRUTHS_KEPT: usize = 36_000;

/// A station is read over this long with the carriage at rest.
const STATION_WINDOW: Duration = Duration::from_millis(500);

/// One round of alignment: what the spots read and what the technician was told.
#[derive(Clone, Debug, PartialEq)]
pub struct AlignRound {
    pub stations: Vec<Station>,
    pub advice: Advice,
}

impl std::fmt::Debug for Lab {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Lab")
            .field("elapsed", &self.elapsed())
            .field("stats", &self.stats)
            .finish_non_exhaustive()
    }
}

/// How long the lab may sit at one instant before it calls the clock stalled.
const STALL_LIMIT: usize = 10_000;

impl Lab {
    /// Build the lab; its clock starts now (an arbitrary origin: nothing waits on it).
    pub fn new(spec: &LabSpec) -> Result<Lab, LabError> {
        let t0 = crate::util::clock::now();
        let plant = Arc::new(Plant::new(&spec.layout, &spec.plant, t0)?);
        let p = plant.clone();
        let drive = TwinDrive::new(
            spec.twin_drive,
            Box::new(move |mm| p.set_follower_encoder(mm)),
            t0,
        )?;
        let master = Master::new(&spec.drive)?;
        if spec.frame_period.is_zero() {
            return Err(LabError::Setup(SimError::Input(
                "the lab's frame period must be positive".into(),
            )));
        }
        Ok(Lab {
            layout: spec.layout.clone(),
            t0,
            unix0_us: now_us(),
            now: t0,
            plant,
            drive,
            status: master.status().clone(),
            master,
            pipeline: Pipeline::new(spec.tracking, spec.decoupler.clone(), spec.live_window),
            map: spec.map.clone(),
            capture: spec.capture,
            frame_period: spec.frame_period,
            next_frame: t0,
            seq: 0,
            cnc: None,
            plc: Plc::default(),
            completed: Vec::new(),
            captures: Vec::new(),
            handovers: Vec::new(),
            run_end: None,
            pending_follow: None,
            stats: LabStats::default(),
            trace: None,
            spot_log: None,
            alignment: None,
            align: AlignSettings::default(),
            realign_when_paused: true,
            pauses: Vec::new(),
            flags: Vec::new(),
            events: Vec::new(),
            truths: std::collections::VecDeque::new(),
            extra_programs: 0,
        })
    }

    /// Simulated time since the lab was built.
    pub fn elapsed(&self) -> Duration {
        self.now - self.t0
    }

    /// The lab's clock.
    pub fn now(&self) -> Instant {
        self.now
    }

    /// The lab's clock as the frames and captures are dated (µs since the Unix epoch).
    pub fn unix_us(&self) -> i64 {
        self.unix0_us + (self.now - self.t0).as_micros() as i64
    }

    /// The twin's truth now.
    pub fn truth(&self) -> Truth {
        self.plant.truth(self.now)
    }

    /// The follower drive as the master sees it.
    pub fn drive_status(&self) -> &DriveStatus {
        &self.status
    }

    /// Run the clock for `d`.
    pub fn advance(&mut self, d: Duration) -> Result<(), LabError> {
        let until = self.now + d;
        let mut same = 0usize;
        loop {
            self.step();
            let next = [
                Some(self.next_frame),
                self.drive.poll_timeout(),
                self.master.poll_timeout(),
                self.cnc.as_ref().and_then(Cnc::next_wake),
            ]
            .into_iter()
            .flatten()
            .min()
            .unwrap_or(until)
            .min(until);
            if next <= self.now {
                if self.now >= until {
                    return Ok(());
                }
                same += 1;
                if same > STALL_LIMIT {
                    return Err(LabError::Stalled(self.elapsed()));
                }
                continue;
            }
            same = 0;
            self.now = next;
        }
    }

    /// Run the clock until `done` holds (checked after every step), for at most `within`.
    pub fn advance_until(
        &mut self,
        what: &str,
        within: Duration,
        mut done: impl FnMut(&Lab) -> bool,
    ) -> Result<(), LabError> {
        let until = self.now + within;
        let slice = self.frame_period;
        while !done(self) {
            if self.now >= until {
                return Err(LabError::Timeout {
                    what: what.to_string(),
                    within,
                });
            }
            self.advance(slice.min(until - self.now))?;
        }
        Ok(())
    }

    /// Everything due at the current instant.
    fn step(&mut self) {
        let now = self.now;
        if self.drive.poll_timeout().is_some_and(|t| t <= now) {
            self.drive.handle_timeout(now);
        }
        if self.master.poll_timeout().is_some_and(|t| t <= now) {
            self.master.handle_timeout(now);
        }
        self.exchange();
        if let Some(cnc) = self.cnc.as_mut() {
            let captured = self.plc.acknowledged == Some(cnc.handshake.code);
            cnc.step(now, &self.plant, captured);
            let hs = cnc.handshake;
            if hs.at_target && !self.plc.at_target_seen {
                self.pipeline.handle_at_target(hs.code, now);
            }
            self.plc.at_target_seen = hs.at_target;
        }
        if self.next_frame <= now {
            self.sample(now);
            self.next_frame += self.frame_period;
            if self.next_frame <= now {
                self.next_frame = now + self.frame_period;
            }
        }
        self.pump();
        self.exchange();
    }

    /// The I/O module: the plant sampled, digitised per the map, read back as a frame.
    fn sample(&mut self, now: Instant) {
        let s = self.plant.sample(now);
        let reading = Reading {
            spots: s.spots,
            sums: s.sums,
        };
        let unix_us = self.unix0_us + (now - self.t0).as_micros() as i64;
        if self
            .truths
            .back()
            .is_none_or(|(t, _)| unix_us - t >= TRUTH_EVERY_US)
        {
            if self.truths.len() >= TRUTHS_KEPT {
                self.truths.pop_front();
            }
            self.truths.push_back((unix_us, self.plant.truth(now)));
        }
        let f = encode(&self.map, &reading)
            .and_then(|block| frame(&self.map, &block, self.seq, now, unix_us));
        self.seq += 1;
        match f {
            Ok(f) => {
                self.stats.frames += 1;
                if let Some(log) = self.spot_log.as_mut() {
                    log.push(f.spots);
                }
                self.pipeline.handle_frame(&f, false);
                if let Some(rows) = self.trace.as_mut() {
                    let st = self.pipeline.tracker.stitch();
                    rows.push(TraceRow {
                        t_s: (now - self.t0).as_secs_f64(),
                        truth: self.plant.truth(now),
                        psd2: f.spots[1].map(|s| (s.x, s.y)),
                        stitch_mm: st.valid.then_some(st.follower_mm),
                        position_mm: self.pipeline.measure.position_at(now),
                    });
                }
            }
            Err(e) => self
                .pipeline
                .alarms
                .raise("io-decode", format!("a block could not be decoded: {e}")),
        }
    }

    /// CAN frames both ways until the bus is quiet; then the master's news to the pipeline.
    fn exchange(&mut self) {
        let now = self.now;
        loop {
            let mut any = false;
            while let Some(f) = self.master.poll_transmit() {
                self.drive.handle_frame(&f, now);
                self.stats.can_frames += 1;
                any = true;
            }
            while let Some(f) = self.drive.poll_transmit() {
                self.master.handle_frame(&f, now);
                self.stats.can_frames += 1;
                any = true;
            }
            if !any {
                break;
            }
        }
        while let Some(e) = self.master.poll_event() {
            if let Event::Completed { id, result } = &e {
                self.completed
                    .push((*id, result.clone().map(|_| ()).map_err(|e| e.to_string())));
            }
            self.pipeline.handle_drive_event(&e, "lab bus");
        }
        if *self.master.status() != self.status {
            self.status = self.master.status().clone();
            self.pipeline.handle_drive_status(&self.status, now);
        }
        if self.status.busy.is_none()
            && let Some(mm) = self.pending_follow.take()
        {
            self.master
                .submit(Command::SetTarget { target_mm: mm }, now);
        }
    }

    /// Carry out what the pipeline asks.
    fn pump(&mut self) {
        let now = self.now;
        while let Some(out) = self.pipeline.poll_output() {
            match out {
                // A handover step: the latest set-point wins (as the service's follower task).
                Output::Follower(FollowerCommand::MoveTo(mm)) => self.pending_follow = Some(mm),
                Output::Follower(FollowerCommand::Follow {
                    target_mm,
                    velocity_mm_s,
                    at,
                }) => {
                    self.stats.follow_targets += 1;
                    match self
                        .master
                        .follow_moving(target_mm, Some(velocity_mm_s), at, now)
                    {
                        Ok(()) => {}
                        // Following ended (a stop, a fault): a move re-arms it, as in the
                        // service.
                        Err(DriveError::FollowDisarmed) => self.pending_follow = Some(target_mm),
                        Err(e) => tracing::warn!("lab: follow {target_mm:.4} mm: {e}"),
                    }
                }
                Output::QuickStop => {
                    self.master.submit(Command::QuickStop, now);
                }
                Output::ReEnable => {
                    self.master.submit(Command::Enable, now);
                }
                Output::Handover(r) => self.handovers.push(r),
                Output::Captured(c) => {
                    let truth = self.truth_of(&c);
                    self.captures.push(TrueCapture { capture: c, truth });
                }
                Output::Flagged {
                    capture,
                    reason,
                    stored,
                } => {
                    if stored {
                        let key = TargetKey::of(&capture);
                        self.captures.retain(|t| TargetKey::of(&t.capture) != key);
                    }
                    let truth = self.truth_of(&capture);
                    self.flags.push((TrueCapture { capture, truth }, reason));
                }
                Output::RunEvent { kind, detail } => self.events.push((kind, detail)),
                Output::Restated { capture, reason } => {
                    let key = TargetKey::of(&capture);
                    if let Some(t) = self.captures.iter_mut().find(|t| {
                        TargetKey::of(&t.capture) == key && t.capture.unix_us == capture.unix_us
                    }) {
                        t.capture.u = capture.u;
                    }
                    self.events.push(("u-restated".into(), reason));
                }
                Output::Acknowledge(code) => self.plc.acknowledged = Some(code),
                Output::RunPaused(why) => {
                    self.pauses.push(why);
                    if let Some(cnc) = self.cnc.as_mut() {
                        cnc.stop_at_next_stop();
                    }
                }
                Output::RunResumed => {}
                Output::RunFinished => self.run_end = Some(Ok(())),
                Output::RunFailed(why) => self.run_end = Some(Err(why)),
            }
        }
    }

    /// The truth when capture `c` was taken: at the end of its frames (when the run machine
    /// had it), from the history.
    fn truth_of(&self, c: &Capture) -> Truth {
        let end = c.unix_us + (self.frame_period * c.frames).as_micros() as i64;
        self.truths
            .iter()
            .min_by_key(|(t, _)| (t - end).abs())
            .map(|(_, truth)| *truth)
            .unwrap_or_else(|| self.plant.truth(self.now))
    }

    /// Submit a drive command and run the clock until it completes.
    fn command(&mut self, cmd: Command, within: Duration) -> Result<(), LabError> {
        let what = cmd.name();
        let id = self.master.submit(cmd, self.now);
        self.exchange();
        self.advance_until(what, within, |lab| {
            lab.completed.iter().any(|(i, _)| *i == id)
        })?;
        let pos = self.completed.iter().position(|(i, _)| *i == id);
        match pos.map(|p| self.completed.remove(p)) {
            Some((_, Ok(()))) => Ok(()),
            Some((_, Err(why))) => Err(LabError::BringUp { what, why }),
            None => Err(LabError::BringUp {
                what,
                why: "no completion".into(),
            }),
        }
    }

    /// Bring the follower up as the service does: configure, start, enable, home; then wait
    /// until the tracker has taken its reference (the spot on PSD2, the follower at rest) —
    /// on a head not aligned yet, as long as PSD2 can be brought to its spot.
    pub fn bring_up(&mut self) -> Result<(), LabError> {
        let t = Duration::from_secs(30);
        for cmd in [
            Command::Configure,
            Command::Start,
            Command::Enable,
            Command::Home,
        ] {
            self.command(cmd, t)?;
        }
        let referenced = |lab: &Lab| lab.pipeline.tracker.stitch().valid;
        if self
            .advance_until(
                "the stitch's first reference",
                Duration::from_secs(5),
                referenced,
            )
            .is_ok()
        {
            return Ok(());
        }
        // PSD2 shows no spot: a head not aligned yet. The technician brings the follower to
        // the spot when its target shows it; the zero reference takes the stitch's reference
        // after the alignment.
        self.find_psd2_spot()?;
        let _ = self.advance_until("the stitch's first reference", t, referenced);
        Ok(())
    }

    /// Move the carriage to `mm` (as a jog would) and wait until it and the follower are at
    /// rest.
    pub fn move_carriage(&mut self, mm: f64) -> Result<(), LabError> {
        self.plant.move_carriage(mm, self.now);
        let end = self.plant.carriage_move_end();
        let within = (end - self.now) + Duration::from_secs(10);
        self.advance_until("the carriage and follower at rest", within, |lab| {
            lab.now >= end
                && lab.pipeline.tracker.at_rest(lab.now)
                && !lab.pipeline.tracker.handing_over()
        })
    }

    /// Take the zero reference as an operator does with the carriage at rest at `at_mm`: set
    /// the nominal (without it the positioning error reads as travel), re-reference the
    /// stitch, take the live mean as the errors' zero, clear the nominal.
    pub fn zero(
        &mut self,
        at_mm: f64,
        window: Duration,
    ) -> Result<crate::units::Errors6, LabError> {
        self.pipeline.measure.set_nominal(Some(at_mm));
        let r = self.take_zero(window);
        self.pipeline.measure.set_nominal(None);
        r
    }

    fn take_zero(&mut self, window: Duration) -> Result<crate::units::Errors6, LabError> {
        if !self.pipeline.begin_zero(self.now, window) {
            return Err(LabError::BringUp {
                what: "zero",
                why: "the follower's position is not known".into(),
            });
        }
        // The pipeline takes it once the averaging window has refilled, again after a
        // follower step in the window (`Pipeline::begin_zero`).
        let deadline = self.now + (window + Duration::from_secs(10)) * 5;
        self.advance(window + Duration::from_millis(60))?;
        loop {
            match self.pipeline.zero_ready(self.now) {
                Some(Some(z)) => return Ok(z),
                Some(None) => {
                    return Err(LabError::BringUp {
                        what: "zero",
                        why: "no valid frames in the window".into(),
                    });
                }
                None if self.now >= deadline => {
                    return Err(LabError::BringUp {
                        what: "zero",
                        why: "the reference was not due".into(),
                    });
                }
                None => self.advance(Duration::from_millis(20))?,
            }
        }
    }

    /// Measure `plan`: the CNC runs the program the service generates for it (`dialect`,
    /// stability or handshake capture), the pipeline captures. `progress` is called about
    /// once per simulated second.
    ///
    /// The run starts only when the pre-run check passes ([`Lab::pre_run_check`]). A spot lost
    /// on the way pauses it: the program stops at its next stop, the lab's technician clears
    /// the beam's way (waits), brings the follower back to the spot or realigns the head, and
    /// the rest of the cycle runs from the next missing capture. Captures still missing when
    /// a program ends are taken by make-up passes, as the service does.
    pub fn measure(
        &mut self,
        plan: &Plan,
        dialect: Dialect,
        mode: CaptureMode,
        mut progress: impl FnMut(Progress),
    ) -> Result<LabRun, LabError> {
        check_dwell(
            &self.capture,
            self.frame_period,
            self.pipeline.tracker.settings(),
            plan,
        )?;
        self.pre_run_check(plan)?;
        let text = generate(plan, dialect, mode).map_err(|e| LabError::Program(e.to_string()))?;
        let handshake = matches!(mode, CaptureMode::Handshake(_));
        self.captures.clear();
        self.handovers.clear();
        self.pauses.clear();
        self.flags.clear();
        self.events.clear();
        self.extra_programs = 0;
        self.run_end = None;
        let started = self.now;
        self.load(&text, plan, dialect)?;
        self.pipeline.start_run(RunMachine::new(
            plan.clone(),
            self.capture,
            handshake,
            BTreeSet::new(),
        ));
        self.pump();
        // Generous: the whole motion and dwell time three times over, the capture timeout,
        // and ten minutes for pauses.
        let limit = Duration::from_secs_f64(3.0 * plan.motion_time_s(self.plant.spec.accel))
            + self.capture.timeout
            + Duration::from_secs(600);
        let expected = plan.capture_count();
        // The programs after the first: the rest of the cycle after a pause, make-up passes
        // for what is still missing; the same bookkeeping as the service's.
        let mut session = Session::new(plan.clone());
        let mut next_recovery = self.now;
        let result = loop {
            if let Some(end) = self.run_end.take() {
                break end.map_err(LabError::RunFailed);
            }
            if self.now - started > limit {
                break Err(LabError::Timeout {
                    what: format!("the run's {expected} captures"),
                    within: limit,
                });
            }
            let cnc_done = self.cnc.as_ref().is_none_or(Cnc::is_done);
            if self.pipeline.paused().is_some() {
                if !session.stopped_by_pause() {
                    session.paused();
                }
                if cnc_done && self.now >= next_recovery {
                    if let Err(e) = self.recover(plan) {
                        self.pipeline.abort_run();
                        break Err(e);
                    }
                    next_recovery = self.now + Duration::from_secs(2);
                }
            } else if cnc_done
                && self.now
                    > self
                        .cnc
                        .as_ref()
                        .and_then(|c| c.finished)
                        .unwrap_or(self.now)
                        + self.capture.settle * 4
                        + self.live_window_bound()
            {
                let missing = self.pipeline.run_missing().unwrap_or_default();
                match session.ended(&missing) {
                    Next::Program(p) => {
                        let text = p
                            .text(plan, dialect, mode)
                            .map_err(|e| LabError::Program(e.to_string()))?;
                        self.load(&text, plan, dialect)?;
                        self.extra_programs += 1;
                    }
                    Next::Nothing => {}
                    Next::Fail(why) => {
                        self.pipeline.abort_run();
                        break Err(LabError::Incomplete(why));
                    }
                }
            }
            if let Err(e) = self.advance(Duration::from_secs(1)) {
                self.pipeline.abort_run();
                break Err(e);
            }
            let (position_mm, moving) = self.plant.carriage(self.now);
            progress(Progress {
                captures: self.captures.len(),
                expected,
                elapsed_s: (self.now - started).as_secs_f64(),
                position_mm,
                moving,
            });
        };
        self.cnc = None;
        result?;
        let last = self
            .captures
            .iter()
            .map(|c| c.capture.unix_us)
            .max()
            .unwrap_or(0);
        let start_us = self.unix0_us + (started - self.t0).as_micros() as i64;
        Ok(LabRun {
            captures: std::mem::take(&mut self.captures),
            handovers: std::mem::take(&mut self.handovers),
            program: text,
            duration: Duration::from_micros((last - start_us).max(0) as u64),
        })
    }

    /// Load a part program into the CNC (which starts it at once).
    fn load(&mut self, text: &str, plan: &Plan, dialect: Dialect) -> Result<(), LabError> {
        let ops =
            parse(text, dialect, &plan.spec.axis).map_err(|e| LabError::Program(e.to_string()))?;
        self.plc = Plc::default();
        self.cnc = Some(Cnc::new(ops));
        Ok(())
    }

    /// A paused run, its program stopped: what the technician does. A beam that shows on no
    /// target is blocked: wait. PSD2's spot on its target only: bring the follower to it. PSD1's
    /// or PSD3's spot on its target: the head moved on its mount: realign over the plan's
    /// travel and take the zero again at the plan's reference.
    fn recover(&mut self, plan: &Plan) -> Result<(), LabError> {
        let spots = self
            .pipeline
            .last_frame
            .map(|f| f.spots)
            .unwrap_or([None; 3]);
        let targets = self.plant.target_readings(self.now);
        let off = |k: usize| spots[k].is_none() && targets[k].is_some();
        let blocked = (0..3).any(|k| spots[k].is_none() && targets[k].is_none());
        if blocked {
            return Ok(());
        }
        if self.realign_when_paused && (off(0) || off(2)) {
            let span = plan_span(plan);
            self.align(span, 8, |_| {})?;
            self.move_carriage(plan.reference_mm)?;
            self.zero(plan.reference_mm, Duration::from_millis(500))?;
            return Ok(());
        }
        if off(1) {
            self.find_psd2_spot()?;
        }
        Ok(())
    }

    /// PSD2 shows no spot: the technician reads it on PSD2's target and moves the follower by
    /// as much (X2 grows as the follower falls behind the carriage); when the target shows
    /// nothing either, the follower goes to where the carriage is first.
    fn find_psd2_spot(&mut self) -> Result<(), LabError> {
        if self.psd2_sees_spot() {
            return Ok(());
        }
        if self.pipeline.paused().is_none() {
            self.pipeline
                .invalidate_stitch("the follower was moved to find the spot: zero again");
        }
        for _ in 0..2 {
            let Some(at) = self.status.position_mm else {
                return Ok(());
            };
            let target = match self.plant.target_readings(self.now)[1] {
                Some(t) => at + t.x,
                None => self.plant.carriage(self.now).0,
            };
            if (target - at).abs() < 0.05 {
                break;
            }
            self.command(
                Command::SetTarget { target_mm: target },
                Duration::from_secs(120),
            )?;
            if self
                .advance_until("PSD2's spot", Duration::from_secs(1), Lab::psd2_sees_spot)
                .is_ok()
            {
                break;
            }
        }
        Ok(())
    }

    fn psd2_sees_spot(&self) -> bool {
        self.pipeline
            .last_frame
            .is_some_and(|f| f.spots[1].is_some())
    }

    /// Move the carriage to `mm` for a reading and let it settle; bring the follower to the
    /// spot if PSD2 lost it on the way.
    fn goto(&mut self, mm: f64) -> Result<(), LabError> {
        // A jog waits for a handover in progress, as an operator waits for the follower.
        let _ = self.advance_until("the handover's end", Duration::from_secs(10), |lab| {
            !lab.pipeline.tracker.handing_over()
        });
        self.plant.move_carriage(mm, self.now);
        let end = self.plant.carriage_move_end();
        if end > self.now {
            self.advance(end - self.now)?;
        }
        let rest = |lab: &Lab| lab.pipeline.tracker.at_rest(lab.now);
        if self
            .advance_until("rest", Duration::from_secs(5), rest)
            .is_err()
        {
            self.find_psd2_spot()?;
            let _ = self.advance_until("rest", Duration::from_secs(5), rest);
        }
        Ok(())
    }

    /// The spots with the carriage at rest at `mm`: each PSD's mean over a short window, or
    /// where its spot is off the PSD, what its alignment target shows.
    pub fn read_station(&mut self, mm: f64) -> Result<Station, LabError> {
        self.goto(mm)?;
        self.spot_log = Some(Vec::new());
        let r = self.advance(STATION_WINDOW);
        let log = self.spot_log.take().unwrap_or_default();
        r?;
        let mut st = crate::align::mean_station(mm, log.iter());
        let targets = self.plant.target_readings(self.now);
        for (o, t) in st.spots.iter_mut().zip(targets) {
            if o.is_none() {
                *o = t.map(|t| Observed {
                    x: t.x,
                    y: t.y,
                    source: SpotSource::Target,
                });
            }
        }
        Ok(st)
    }

    /// Align the head over `span` (mm) as a technician does: read the spots at both ends,
    /// turn the screws as advised, and again, until the check passes (at most `rounds`
    /// times). `report` hears each round. The check that passed is kept for the pre-run
    /// check.
    pub fn align(
        &mut self,
        span: (f64, f64),
        rounds: usize,
        mut report: impl FnMut(&AlignRound),
    ) -> Result<Vec<AlignRound>, LabError> {
        let mut out: Vec<AlignRound> = Vec::new();
        for i in 0..rounds {
            // Start at the end the carriage is nearer to.
            let pos = self.plant.carriage(self.now).0;
            let order = if i == 0 || (pos - span.0).abs() <= (pos - span.1).abs() {
                [span.0, span.1]
            } else {
                [span.1, span.0]
            };
            let stations = vec![self.read_station(order[0])?, self.read_station(order[1])?];
            let advice = crate::align::advise(&self.layout, &self.align, &stations, span)?;
            let round = AlignRound { stations, advice };
            report(&round);
            let passed = round.advice.now.passed();
            if passed {
                self.alignment = Some(round.advice.now.clone());
            } else {
                for t in &round.advice.turns {
                    self.plant.turn_screw(t.screw, t.turns);
                }
            }
            out.push(round);
            if passed {
                return Ok(out);
            }
        }
        Err(LabError::NotAligned {
            rounds,
            check: out
                .last()
                .map(|r| r.advice.now.to_string())
                .unwrap_or_default(),
        })
    }

    /// Before a run: the spots must stay on their PSDs over the plan's whole travel. From the
    /// last alignment when it covers the travel, else from a quick traverse to both ends (the
    /// carriage is brought back). Refuses with the PSD that leaves, where, and what to turn.
    pub fn pre_run_check(&mut self, plan: &Plan) -> Result<Check, LabError> {
        let span = plan_span(plan);
        if let Some(c) = self.alignment.as_ref().filter(|c| c.covers(span)) {
            return Ok(c.clone());
        }
        let back = self.plant.carriage(self.now).0;
        let stations = [self.read_station(span.0)?, self.read_station(span.1)?];
        self.goto(back)?;
        match crate::align::advise(&self.layout, &self.align, &stations, span) {
            Ok(a) if a.now.passed() => {
                self.alignment = Some(a.now.clone());
                Ok(a.now)
            }
            Ok(a) => {
                let turns: Vec<String> = a.turns.iter().map(ToString::to_string).collect();
                Err(LabError::Refused {
                    check: format!("{} (to correct: {})", a.now, turns.join(", ")),
                })
            }
            Err(e) => Err(LabError::Refused {
                check: e.to_string(),
            }),
        }
    }

    /// How long averaging a capture can take after the carriage stops.
    fn live_window_bound(&self) -> Duration {
        self.frame_period * (self.capture.frames as u32 + 10)
    }
}

/// The travel a plan covers, with the overrun on both sides (mm).
pub fn plan_span(plan: &Plan) -> (f64, f64) {
    plan.travel_mm()
}
