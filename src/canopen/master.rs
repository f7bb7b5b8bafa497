//! The drive master: one sans-I/O machine composing NMT, heartbeat consumer, SDO client, PDO
//! and SYNC, EMCY and the CiA 402 handshakes behind high-level commands.
//!
//! Commands ([`Command`]) are queued and run one at a time as small programs of steps (SDO
//! writes, NMT commands, controlword changes, waits on the statusword). Each completes with an
//! [`Event::Completed`] carrying its [`OpId`]. Stop, quick stop and disable pre-empt: they
//! interrupt the running command and drop the queued ones, since after them the queued moves
//! no longer make sense.
//!
//! Cyclic exchange: once the drive is configured and operational, every SYNC period the
//! master sends RPDO1 (controlword + target position) and then SYNC; the drive answers with
//! TPDO1 (statusword + position actual). A controlword change goes out with the next SYNC, so
//! every wait on the statusword only looks at TPDOs answering a SYNC sent after the change.
//! After [`QUIET_AFTER`] with nothing under way and nothing changed, the SYNC slows to the
//! configured quiet period; a command, a follow target, an EMCY or a TPDO showing a new state
//! or movement brings the full rate back at once (the first SYNC one period after the last).
//!
//! Power and motion commands need the PDOs running (configure, then start); configuration and
//! raw SDO access work in pre-operational.
//!
//! Following (cyclic synchronous position, mode 8): [`Master::follow`] records the latest
//! target without waiting. When not following yet, it queues a [`Command::Follow`] that waits
//! for a profile move to end, holds the actual position as the demand, writes 0x6060 = 8 and
//! reads 0x6061 until it shows 8. From then on every RPDO1 at SYNC carries the demand in
//! 0x607A (no handshake), moved toward the latest target by a [`DemandRamp`] within the
//! profile velocity and acceleration, leading a moving target by `csp_lead_periods` SYNC
//! periods to make up for the drive's interpolation delay. [`Command::StopFollowing`] brings
//! the demand to rest on the last target and returns to profile position; move, jog,
//! set-target and home first bring the demand to rest where it can stop, then switch to their
//! modes. In CSP the drive's bit 10 is reserved and bit 12 means "target position used", so
//! the master works out "target reached" itself: |actual − demand| below the position window
//! with the demand unchanged for a SYNC. A following error (bit 13), a fault or leaving
//! operation enabled ends following ([`Event::FollowingEnded`] with the reason); after that,
//! or after stop, quick stop or disable, follow targets are refused until the next other
//! command.

use super::cia402::{
    self, CW_CHANGE_IMMEDIATELY, CW_COMMAND_MASK, CW_FAULT_RESET, CW_HALT, CW_NEW_SETPOINT,
    CW_RELATIVE, FsaCommand, HomingStatus, MODE_CSP, MODE_HOMING, MODE_PROFILE_POSITION, NextStep,
    PowerState, Statusword,
};
use super::cob;
use super::config::{ConfigError, DriveConfig, DriveSettings};
use super::csp::{DemandRamp, TargetTrack};
use super::emcy::Emcy;
use super::nmt::{HeartbeatConsumer, HeartbeatEvent, command_frame};
use super::pdo::{self, SdoWrite, SyncProducer};
use super::sdo::{AbortCode, ObjAddr, SdoClient, SdoError, SdoOutcome, value};
use crate::can::CanFrame;
use canopen_rs::{NmtCommand, NmtState};
use std::collections::VecDeque;
use std::time::{Duration, Instant};
use thiserror::Error;

/// Identifies a submitted command in its completion event.
pub type OpId = u64;

/// The name of [`Command::Follow`].
const FOLLOW: &str = "follow";

/// What the master can be asked to do.
#[derive(Clone, Debug, PartialEq)]
pub enum Command {
    /// Reset communication (optional), pre-operational, check the device type, write the
    /// heartbeat time, the PDO mapping and the profile/homing/limit parameters, read the
    /// statusword, position and mode back.
    Configure,
    /// NMT start, wait for the heartbeat to say operational, start SYNC.
    Start,
    /// A raw NMT command (stop, pre-operational, resets) with its confirmation.
    Nmt(NmtCommand),
    /// Walk the power states to operation enabled.
    Enable,
    /// Disable voltage (switch on disabled). Pre-empts.
    Disable,
    /// Homing (mode 6) with the configured method.
    Home,
    /// Profile-position move to an absolute position; done at "target reached".
    MoveTo { target_mm: f64 },
    /// Relative profile-position move (controlword bit 6); done at "target reached".
    Jog { delta_mm: f64 },
    /// New absolute set-point with "change set immediately"; done at the acknowledge, for a
    /// tracker that updates the target at SYNC rate.
    SetTarget { target_mm: f64 },
    /// Start following (cyclic synchronous position) toward `target_mm`; done when the demand
    /// streams. [`Master::follow`] queues it by itself; later targets come by `follow`.
    Follow { target_mm: f64 },
    /// Bring the following demand to rest on the last target, then return to profile
    /// position; done when the drive is there (at once when not following).
    StopFollowing,
    /// Halt (controlword bit 8) and wait for standstill. Pre-empts.
    Stop,
    /// Quick stop command; done when the drive has stopped. Pre-empts.
    QuickStop,
    /// Rising edge of controlword bit 7; done when the drive has left fault.
    FaultReset,
    /// Read an object.
    SdoRead(ObjAddr),
    /// Write an object.
    SdoWrite(ObjAddr, Vec<u8>),
}

impl Command {
    pub fn name(&self) -> &'static str {
        match self {
            Command::Configure => "configure",
            Command::Start => "start",
            Command::Nmt(_) => "NMT command",
            Command::Enable => "enable",
            Command::Disable => "disable",
            Command::Home => "home",
            Command::MoveTo { .. } => "move",
            Command::Jog { .. } => "jog",
            Command::SetTarget { .. } => "set target",
            Command::Follow { .. } => FOLLOW,
            Command::StopFollowing => "stop following",
            Command::Stop => "stop",
            Command::QuickStop => "quick stop",
            Command::FaultReset => "fault reset",
            Command::SdoRead(_) => "SDO read",
            Command::SdoWrite(..) => "SDO write",
        }
    }

    fn preempts(&self) -> bool {
        matches!(self, Command::Stop | Command::QuickStop | Command::Disable)
    }
}

/// A successful command's result.
#[derive(Clone, Debug, PartialEq)]
pub enum Reply {
    Done,
    /// The bytes of an `SdoRead`.
    Data(Vec<u8>),
}

/// Why a command failed.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum DriveError {
    #[error(transparent)]
    Sdo(#[from] SdoError),
    #[error("{what}: nothing within {after:?}")]
    Timeout { what: &'static str, after: Duration },
    #[error("the drive is in fault: {}", match .emcy { Some(e) => e.to_string(), None => "no EMCY received".into() })]
    Fault { emcy: Option<Emcy> },
    #[error("the drive's heartbeat was lost")]
    HeartbeatLost,
    #[error("the drive rebooted (boot-up message): configure it again")]
    Rebooted,
    #[error("{what} needs the drive configured: run configure first")]
    NotConfigured { what: &'static str },
    #[error(
        "{what} needs the drive operational with PDOs and SYNC running: configure and start it first"
    )]
    NotOperational { what: &'static str },
    #[error("{what} needs operation enabled; the drive is in {state}")]
    NotEnabled { what: &'static str, state: String },
    #[error("the drive has not been homed since it was configured: home it first")]
    NotHomed,
    #[error("target {target_mm} mm is outside the travel limits {min_mm}..{max_mm} mm")]
    OutOfLimits {
        target_mm: f64,
        min_mm: f64,
        max_mm: f64,
    },
    #[error("the drive reports a following error (statusword bit 13)")]
    FollowingError,
    #[error("homing failed: {0:?}")]
    Homing(HomingStatus),
    #[error("interrupted by {by}")]
    Interrupted { by: &'static str },
    #[error("object 0x1000 reports device type 0x{0:08X}: not a CiA 402 drive (profile 0x0192)")]
    NotADrive(u32),
    #[error("{obj} returned {len} bytes, expected {want}")]
    BadLength {
        obj: ObjAddr,
        len: usize,
        want: usize,
    },
    #[error("no controlword leads from {from} to {to}")]
    NoPath { from: PowerState, to: PowerState },
    #[error(
        "follow targets are refused since following ended or the drive was stopped: send another command first (e.g. enable, stop following, a move)"
    )]
    FollowDisarmed,
    #[error("the drive link is closed")]
    Closed,
}

/// What happened, for the service and the console.
#[derive(Clone, Debug, PartialEq)]
pub enum Event {
    /// A boot-up message; `expected` after a reset this master commanded.
    BootUp {
        expected: bool,
    },
    /// The heartbeat reports a new NMT state.
    Nmt(NmtState),
    /// No heartbeat for the consumer time: the service stops the follower and raises an alarm.
    HeartbeatLost,
    HeartbeatResumed,
    /// An EMCY from the drive (code 0x0000: error reset).
    Emcy(Emcy),
    /// The statusword shows a new power state.
    PowerState {
        from: Option<PowerState>,
        to: PowerState,
    },
    /// Following started: the demand streams at every SYNC.
    FollowingStarted,
    /// Following ended (or could not start): `Ok` after stop following or a command that took
    /// over, `Err` with the reason otherwise.
    FollowingEnded(Result<(), DriveError>),
    /// A command finished.
    Completed {
        id: OpId,
        result: Result<Reply, DriveError>,
    },
}

/// TPDO positions kept in [`DriveStatus::recent_positions`].
pub const RECENT_POSITIONS: usize = 8;

/// How long the follower must be quiet (nothing under way, nothing changed) before SYNC
/// slows to `DriveConfig::quiet_sync_period`. At rest in profile position the status only
/// confirms itself; a slower SYNC saves the service a wake-up per period.
pub const QUIET_AFTER: Duration = Duration::from_secs(1);

/// The drive as the master sees it.
#[derive(Clone, Debug, PartialEq)]
pub struct DriveStatus {
    pub nmt: Option<NmtState>,
    pub heartbeat_ok: bool,
    pub configured: bool,
    pub sync_running: bool,
    /// SYNC at the quiet period (see `DriveConfig::quiet_sync_period`).
    pub sync_quiet: bool,
    pub statusword: Option<u16>,
    pub state: Option<PowerState>,
    /// Modes of operation display (0x6061), as last read or set.
    pub mode: Option<i8>,
    pub position_counts: Option<i32>,
    pub position_mm: Option<f64>,
    /// When the position was sampled: the SYNC before the TPDO that brought it (a drive
    /// samples its synchronous TPDO at the SYNC), not when it arrived. Set at every TPDO (a
    /// position unchanged since the last says the drive still stands there); `None` for a
    /// position read otherwise.
    pub position_at: Option<Instant>,
    /// The positions (mm) of the last TPDOs with their sample times, oldest first: a reader
    /// slower than the SYNC (a watch keeps only the latest status) still gets every sample
    /// of the last few periods.
    pub recent_positions: [Option<(Instant, f64)>; RECENT_POSITIONS],
    /// The last accepted set-point (mm); while following, the demand sent at the last SYNC.
    pub commanded_mm: Option<f64>,
    /// Statusword bit 10; in cyclic synchronous position worked out by the master:
    /// |actual − demand| below the position window with the demand unchanged for a SYNC.
    pub target_reached: bool,
    pub setpoint_ack: bool,
    pub following_error: bool,
    /// The master streams follow demands (cyclic synchronous position).
    pub following: bool,
    pub homed: bool,
    /// The last EMCY with an error code other than 0x0000.
    pub last_emcy: Option<Emcy>,
    /// Whether an error EMCY is pending (not yet followed by an error-reset EMCY).
    pub emcy_active: bool,
    /// The command in progress.
    pub busy: Option<&'static str>,
    /// The controlword the master sends.
    pub controlword: u16,
    /// TPDOs received.
    pub tpdo_count: u64,
}

impl Default for DriveStatus {
    /// Nothing heard from the drive yet.
    fn default() -> Self {
        Self::new()
    }
}

impl DriveStatus {
    fn new() -> Self {
        DriveStatus {
            nmt: None,
            heartbeat_ok: false,
            configured: false,
            sync_running: false,
            sync_quiet: false,
            statusword: None,
            state: None,
            mode: None,
            position_counts: None,
            position_mm: None,
            position_at: None,
            recent_positions: [None; RECENT_POSITIONS],
            commanded_mm: None,
            target_reached: false,
            setpoint_ack: false,
            following_error: false,
            following: false,
            homed: false,
            last_emcy: None,
            emcy_active: false,
            busy: None,
            controlword: 0,
            tpdo_count: 0,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum ReadUse {
    DeviceType,
    Statusword,
    Position,
    Mode,
    Reply,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Cond {
    /// A TPDO reflecting the current controlword has arrived.
    Applied,
    AckSet,
    AckClear,
    TargetReached,
    HomingDone,
    NotFault,
    Stopped,
    QuickStopped,
    /// CSP: the demand at rest and reached.
    CspSettled,
}

impl Cond {
    fn what(self) -> &'static str {
        match self {
            Cond::Applied => "TPDO after the controlword change",
            Cond::AckSet => "set-point acknowledge (statusword bit 12)",
            Cond::AckClear => "set-point acknowledge cleared (statusword bit 12)",
            Cond::TargetReached => "target reached (statusword bit 10)",
            Cond::HomingDone => "homing attained (statusword bits 12 and 10)",
            Cond::NotFault => "leaving fault after fault reset",
            Cond::Stopped => "standstill after halt (statusword bit 10)",
            Cond::QuickStopped => "standstill after quick stop",
            Cond::CspSettled => {
                "following demand at rest and reached (within the position window, still)"
            }
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Motion {
    Absolute(f64),
    Relative(f64),
    Track(f64),
}

#[derive(Clone, Debug, PartialEq)]
enum Step {
    SetConfigured(bool),
    RequireConfigured,
    RequirePdo,
    RequireEnabled,
    RequireHomed,
    Nmt(NmtCommand),
    AwaitBootUp,
    /// Let time pass (stale responses drain, further boot-ups count as expected).
    Settle(Duration),
    AwaitNmt(NmtState),
    Write(SdoWrite),
    Read(ObjAddr, ReadUse),
    EnsureMode(i8),
    AwaitMode(i8),
    SyncOn,
    SyncOff,
    AwaitTpdo,
    Power(PowerState),
    Cw {
        set: u16,
        clear: u16,
    },
    Target(i32),
    Commanded(i32),
    Plan(Motion),
    AwaitStatus(Cond, Duration),
    MarkHomed,
    /// Start following toward this target (or go on following).
    CspEnter(f64),
    /// The actual position as the target (demand).
    HoldActual,
    /// Mode 8 confirmed: the ramp starts from the held demand.
    CspStart,
    /// End following: the demand comes to rest on the last target (`stop_following`) or
    /// where it can stop, and the mode goes back to profile position (`stop_following`).
    CspLeave {
        stop_following: bool,
    },
    /// The demand is at rest: stop the ramp.
    CspEnd,
}

#[derive(Debug)]
struct Op {
    id: OpId,
    name: &'static str,
    steps: VecDeque<Step>,
    started: bool,
    deadline: Option<Instant>,
    /// For `AwaitTpdo`: the TPDO must answer this SYNC or a later one.
    after_sync: u64,
    /// For `AwaitBootUp`: boot-ups counted before the reset.
    boot_mark: u64,
    /// For homing: "in progress" has been seen.
    seen_progress: bool,
    /// Times a configure started over after an unexpected boot-up.
    restarts: u32,
    reply: Option<Vec<u8>>,
}

enum Progress {
    Next,
    /// This step is done and these steps run next.
    Replace(Vec<Step>),
    Wait,
    Fail(DriveError),
}

/// The drive master machine.
#[derive(Debug)]
pub struct Master {
    s: DriveSettings,
    sdo: SdoClient,
    sdo_result: Option<Result<SdoOutcome, SdoError>>,
    hb: HeartbeatConsumer,
    sync: SyncProducer,
    queue: VecDeque<(OpId, Command)>,
    op: Option<Op>,
    next_id: OpId,
    /// RPDO1 image.
    cw: u16,
    target: i32,
    /// The first SYNC whose TPDO reflects the current RPDO image.
    cw_applied_at: u64,
    /// The SYNC the last TPDO answered.
    tpdo_sync: u64,
    boot_count: u64,
    commanded: Option<i32>,
    /// CSP: the demand generator, while the master streams demands.
    ramp: Option<DemandRamp>,
    /// The ramp has not stepped yet: its first step is one nominal period, however long ago
    /// the previous SYNC went out (a quiet SYNC, or none yet in this mode).
    ramp_new: bool,
    /// Follow targets feed the ramp's goal.
    following: bool,
    /// The follow targets (time-stamped), the latest one first of all.
    follow_track: TargetTrack,
    /// The `Follow` command `follow` queued, while it runs.
    follow_entry: Option<OpId>,
    /// Follow targets are taken (cleared by stop, quick stop, disable or following ending
    /// abnormally; set by any other command).
    follow_armed: bool,
    /// When the previous SYNC went out.
    last_sync_at: Option<Instant>,
    /// The SYNC that first carried the current target position.
    demand_since: u64,
    /// The position changed by at most the position window between the last two TPDOs.
    standstill: bool,
    /// The last time something was under way or changed (see [`QUIET_AFTER`]).
    active_at: Option<Instant>,
    status: DriveStatus,
    tx: VecDeque<CanFrame>,
    events: VecDeque<Event>,
}

impl Master {
    /// A master for the drive described by `config` (validated here).
    pub fn new(config: &DriveConfig) -> Result<Self, ConfigError> {
        let s = config.validate()?;
        Ok(Master {
            sdo: SdoClient::new(s.node(), config.sdo_timeout),
            sdo_result: None,
            hb: HeartbeatConsumer::new(s.node(), config.heartbeat_timeout),
            sync: SyncProducer::with_quiet_period(config.sync_period, config.quiet_sync_period),
            queue: VecDeque::new(),
            op: None,
            next_id: 1,
            cw: 0,
            target: 0,
            cw_applied_at: 0,
            tpdo_sync: 0,
            boot_count: 0,
            commanded: None,
            ramp: None,
            ramp_new: false,
            following: false,
            follow_track: TargetTrack::default(),
            follow_entry: None,
            follow_armed: true,
            last_sync_at: None,
            demand_since: 0,
            standstill: false,
            active_at: None,
            status: DriveStatus::new(),
            tx: VecDeque::new(),
            events: VecDeque::new(),
            s,
        })
    }

    /// Produce SYNC on the grid `origin + n·sync_period` (see
    /// [`SyncProducer::align_to`]): the driver task aligns it to the acquisition's pacer.
    pub fn align_sync(&mut self, origin: Instant) {
        self.sync.align_to(origin);
    }

    pub fn settings(&self) -> &DriveSettings {
        &self.s
    }

    pub fn status(&self) -> &DriveStatus {
        &self.status
    }

    /// Queue a command; its completion comes as `Event::Completed` with the returned id.
    pub fn submit(&mut self, cmd: Command, now: Instant) -> OpId {
        let id = self.next_id;
        self.next_id += 1;
        if cmd.preempts() {
            let by = cmd.name();
            self.abort_following(DriveError::Interrupted { by });
            self.follow_armed = false;
            if let Some(op) = self.op.take() {
                self.cancel_sdo_of(&op);
                self.finish(op, Err(DriveError::Interrupted { by }));
            }
            for (qid, qcmd) in std::mem::take(&mut self.queue) {
                self.complete(qid, qcmd.name(), Err(DriveError::Interrupted { by }));
            }
        } else {
            self.follow_armed = true;
        }
        self.queue.push_back((id, cmd));
        self.run(now);
        id
    }

    /// The latest follow target (mm), where the follower should be at `at` (when the
    /// tracker worked it out; `now` is the current time), taken without waiting. While
    /// following, at each SYNC the ramp's goal is the latest target moved on to the SYNC's
    /// time by the target's velocity while that is plausible (see [`TargetTrack`]). Otherwise a
    /// [`Command::Follow`] is queued (one at a time) whose failure comes as
    /// [`Event::FollowingEnded`]. Refused outside the travel limits, and after following
    /// ended abnormally or a stop until the next other command.
    pub fn follow(&mut self, target_mm: f64, at: Instant, now: Instant) -> Result<(), DriveError> {
        self.follow_moving(target_mm, None, at, now)
    }

    /// As [`follow`](Self::follow), with the target's velocity (mm/s) when the caller knows
    /// it: each SYNC then moves the target on by it to the SYNC's time, however late (see
    /// [`TargetTrack`]).
    pub fn follow_moving(
        &mut self,
        target_mm: f64,
        velocity_mm_s: Option<f64>,
        at: Instant,
        now: Instant,
    ) -> Result<(), DriveError> {
        self.check_limits(target_mm)?;
        if !self.follow_armed {
            return Err(DriveError::FollowDisarmed);
        }
        match velocity_mm_s {
            Some(v) => self.follow_track.push_moving(target_mm, v, at),
            None => self.follow_track.push(target_mm, at),
        }
        self.active_at = Some(now);
        if self.following {
            // Taken at the next SYNC.
        } else if self.follow_entry.is_none() {
            let id = self.next_id;
            self.next_id += 1;
            self.follow_entry = Some(id);
            self.queue.push_back((id, Command::Follow { target_mm }));
            self.run(now);
        }
        Ok(())
    }

    fn check_limits(&self, target_mm: f64) -> Result<(), DriveError> {
        let l = self.s.config().limits;
        if target_mm >= l.min_mm
            && target_mm <= l.max_mm
            && self.s.mm_to_counts(target_mm).is_some()
        {
            Ok(())
        } else {
            Err(DriveError::OutOfLimits {
                target_mm,
                min_mm: l.min_mm,
                max_mm: l.max_mm,
            })
        }
    }

    /// Report a command's end; a failed `Follow` ends following before it started.
    fn complete(&mut self, id: OpId, name: &'static str, result: Result<Reply, DriveError>) {
        if name == FOLLOW
            && let Err(e) = &result
        {
            self.follow_track = TargetTrack::default();
            if self.follow_entry == Some(id) {
                tracing::warn!("the follower could not start following: {e}");
                self.follow_armed = false;
                self.events.push_back(Event::FollowingEnded(Err(e.clone())));
            }
        }
        if self.follow_entry == Some(id) {
            self.follow_entry = None;
        }
        self.events.push_back(Event::Completed { id, result });
    }

    /// Follow targets go on feeding the ramp (which must exist).
    fn start_following(&mut self) {
        if let (Some(r), Some(g)) = (self.ramp.as_mut(), self.follow_track.latest()) {
            r.set_goal(g);
        }
        if !self.following {
            self.following = true;
            self.status.following = true;
            tracing::info!("follower following (cyclic synchronous position)");
            self.events.push_back(Event::FollowingStarted);
        }
    }

    /// Following ends; the ramp, if any, is left as it is. An error refuses further follow
    /// targets until the next command.
    fn end_following(&mut self, result: Result<(), DriveError>) {
        self.follow_track = TargetTrack::default();
        if !self.following {
            return;
        }
        self.following = false;
        self.status.following = false;
        match &result {
            Ok(()) => tracing::info!("follower following ended"),
            Err(e) => {
                tracing::warn!("follower following ended: {e}");
                self.follow_armed = false;
            }
        }
        self.events.push_back(Event::FollowingEnded(result));
    }

    /// End following with the demand braking to where it can stop.
    fn brake_following(&mut self, result: Result<(), DriveError>) {
        let period = self.s.config().sync_period.as_secs_f64();
        if let Some(r) = self.ramp.as_mut() {
            let stop = r.stopping_point(period);
            r.hold_at(stop);
        }
        self.end_following(result);
    }

    /// End following at once: no more ramp, the demand is the actual position.
    fn abort_following(&mut self, e: DriveError) {
        if self.ramp.take().is_some()
            && let Some(p) = self.status.position_counts
        {
            self.set_demand(p, self.sync.count() + 1);
        }
        self.end_following(Err(e));
    }

    fn cancel_sdo_of(&mut self, op: &Op) {
        let in_sdo = op.started
            && matches!(
                op.steps.front(),
                Some(Step::Write(_) | Step::Read(..) | Step::AwaitMode(_))
            );
        if in_sdo && self.sdo.cancel(AbortCode::GENERAL) {
            // The cancelled transfer's own outcome is of no interest any more.
            while self.sdo.poll_outcome().is_some() {}
            while let Some(f) = self.sdo.poll_transmit() {
                self.tx.push_back(f);
            }
        }
        self.sdo_result = None;
    }

    // --- inputs ------------------------------------------------------------------------

    /// Feed a frame from the bus.
    pub fn handle_frame(&mut self, f: &CanFrame, now: Instant) {
        let node = self.s.node().raw() as u16;
        if self.sdo.handle_frame(f, now) {
            self.collect_sdo();
        } else if self.hb.handle_frame(f, now) {
            self.collect_heartbeat();
        } else if !f.is_extended() && !f.is_remote() && f.id() == (cob::EMCY + node) as u32 {
            match Emcy::decode(f.data()) {
                Ok(e) => {
                    self.active_at = Some(now);
                    if e.is_reset() {
                        self.status.emcy_active = false;
                    } else {
                        self.status.last_emcy = Some(e);
                        self.status.emcy_active = true;
                    }
                    tracing::warn!(node, "{e}");
                    self.events.push_back(Event::Emcy(e));
                }
                Err(e) => tracing::warn!(node, "{e}"),
            }
        } else if !f.is_extended() && !f.is_remote() && f.id() == (cob::TPDO1 + node) as u32 {
            if let Some((sw, pos)) = pdo::decode_tpdo1(f.data()) {
                self.on_tpdo(sw, pos, now);
            }
        } else {
            return;
        }
        self.run(now);
    }

    /// Feed the clock (call at `poll_timeout`, or any time).
    pub fn handle_timeout(&mut self, now: Instant) {
        self.sdo.handle_timeout(now);
        self.collect_sdo();
        self.hb.handle_timeout(now);
        self.collect_heartbeat();
        if self.sync.handle_timeout(now) {
            let dt = self.last_sync_at.map(|t| now.saturating_duration_since(t));
            self.last_sync_at = Some(now);
            if self.pdo_active() {
                self.csp_tick(dt, now);
                self.tx
                    .push_back(pdo::rpdo1_frame(self.s.node(), self.cw, self.target));
            }
            self.tx.push_back(pdo::sync_frame());
        }
        self.run(now);
    }

    /// One SYNC of following: the ramp's next demand goes into this SYNC's RPDO. `dt` is the
    /// time since the previous SYNC (the nominal period if unknown; bounded to ¼..4 periods).
    fn csp_tick(&mut self, dt: Option<Duration>, now: Instant) {
        if self.ramp.is_none() {
            return;
        }
        let goal = if self.following {
            self.follow_goal(now)
        } else {
            None
        };
        let Some(r) = self.ramp.as_mut() else {
            return;
        };
        if let Some((g, v)) = goal {
            r.set_goal_moving(g, v);
        }
        let period = self.s.config().sync_period.as_secs_f64();
        let dt = match dt {
            Some(d) if !std::mem::take(&mut self.ramp_new) => d.as_secs_f64(),
            _ => period,
        };
        let mm = r.step(dt.clamp(period / 4.0, period * 4.0));
        if let Some(c) = self.s.mm_to_counts(mm) {
            self.set_demand(c, self.sync.count());
            self.commanded = Some(c);
            self.status.commanded_mm = Some(self.s.counts_to_mm(c));
        }
    }

    /// The follow target at `now` and its velocity (see [`TargetTrack`]), within the limits.
    fn follow_goal(&mut self, now: Instant) -> Option<(f64, f64)> {
        let c = self.s.config();
        let p = c.profile;
        let (g, v) = self
            .follow_track
            .goal(now, c.sync_period, p.velocity_mm_s, p.accel_mm_s2)?;
        Some((g.clamp(c.limits.min_mm, c.limits.max_mm), v))
    }

    /// The target position as a cyclic demand, first carried by SYNC number `sync` (no wait
    /// on the drive depends on it, unlike `set_target`).
    fn set_demand(&mut self, t: i32, sync: u64) {
        if t != self.target {
            self.target = t;
            self.demand_since = sync;
            self.csp_demand_moved();
        }
    }

    /// A new demand: "target reached" in CSP waits for a TPDO answering a later SYNC.
    fn csp_demand_moved(&mut self) {
        if self.status.mode == Some(MODE_CSP) {
            self.status.target_reached = false;
        }
    }

    fn window_mm(&self) -> f64 {
        self.s.config().profile.position_window_mm
    }

    fn collect_sdo(&mut self) {
        while let Some(f) = self.sdo.poll_transmit() {
            self.tx.push_back(f);
        }
        if let Some(r) = self.sdo.poll_outcome() {
            self.sdo_result = Some(r);
        }
    }

    fn collect_heartbeat(&mut self) {
        while let Some(ev) = self.hb.poll_event() {
            match ev {
                HeartbeatEvent::BootUp => {
                    self.boot_count += 1;
                    let expected = matches!(
                        self.op.as_ref().and_then(|o| o.steps.front()),
                        Some(Step::AwaitBootUp | Step::Settle(_))
                    );
                    self.events.push_back(Event::BootUp { expected });
                    if !expected {
                        tracing::warn!("follower drive rebooted unexpectedly");
                        self.abort_following(DriveError::Rebooted);
                        self.forget_configuration();
                        if let Some(mut op) = self.op.take() {
                            self.cancel_sdo_of(&op);
                            if op.name == Command::Configure.name() && op.restarts < 2 {
                                // A boot-up during configure (a late power-on boot-up taken
                                // for the reset's, or a drive that restarted): what was
                                // written is gone, so start over on the fresh drive.
                                op.restarts += 1;
                                op.steps = self.plan_configure(false);
                                op.steps
                                    .push_front(Step::Settle(self.s.config().boot_settle));
                                op.started = false;
                                op.deadline = None;
                                self.op = Some(op);
                            } else {
                                self.finish(op, Err(DriveError::Rebooted));
                            }
                        }
                    }
                }
                HeartbeatEvent::State(st) => {
                    self.status.nmt = Some(st);
                    self.events.push_back(Event::Nmt(st));
                }
                HeartbeatEvent::Lost => {
                    tracing::error!("follower drive heartbeat lost");
                    self.events.push_back(Event::HeartbeatLost);
                    self.brake_following(Err(DriveError::HeartbeatLost));
                    let resetting = matches!(
                        self.op.as_ref().and_then(|o| o.steps.front()),
                        Some(Step::AwaitBootUp | Step::Settle(_))
                    );
                    if !resetting && let Some(op) = self.op.take() {
                        self.cancel_sdo_of(&op);
                        self.finish(op, Err(DriveError::HeartbeatLost));
                    }
                }
                HeartbeatEvent::Resumed => self.events.push_back(Event::HeartbeatResumed),
            }
        }
        self.status.heartbeat_ok = self.hb.is_alive();
    }

    fn forget_configuration(&mut self) {
        self.abort_following(DriveError::NotConfigured { what: "follow" });
        // Disable voltage until told otherwise: the safe controlword for a drive we lost.
        self.set_cw(0);
        self.status.configured = false;
        self.status.homed = false;
        self.sync.stop();
        self.status.sync_running = false;
    }

    fn on_tpdo(&mut self, sw: u16, pos: i32, now: Instant) {
        self.tpdo_sync = self.sync.count();
        self.status.tpdo_count += 1;
        let window = self.window_mm();
        self.standstill = self
            .status
            .position_counts
            .is_some_and(|p| (self.s.counts_to_mm(pos) - self.s.counts_to_mm(p)).abs() < window);
        if !self.standstill || self.status.statusword != Some(sw) {
            // Moving, or a new state: the full SYNC rate until it settles.
            self.active_at = Some(now);
        }
        self.set_statusword(sw);
        self.status.position_at = self.last_sync_at;
        self.set_position(pos);
        if let Some(at) = self.last_sync_at {
            let h = &mut self.status.recent_positions;
            h.rotate_left(1);
            h[RECENT_POSITIONS - 1] = Some((at, self.s.counts_to_mm(pos)));
        }
        if self.status.mode == Some(MODE_CSP) {
            self.csp_status(Statusword(sw), pos);
        }
    }

    /// Cyclic synchronous position: what a TPDO means for following, and "target reached".
    fn csp_status(&mut self, w: Statusword, pos: i32) {
        let st = w.state();
        let enabled = st == Some(PowerState::OperationEnabled);
        if !enabled {
            if self.ramp.is_some() {
                let e = match st {
                    Some(s) if s.is_fault() => self.fault(),
                    _ => DriveError::NotEnabled {
                        what: "follow",
                        state: st.map_or("an unknown state".into(), |s| s.to_string()),
                    },
                };
                self.abort_following(e);
            }
            // Enabling in CSP takes the target position at once: keep it where the stage is.
            self.set_demand(pos, self.sync.count() + 1);
        } else if w.following_error() && self.following {
            self.brake_following(Err(DriveError::FollowingError));
        }
        let err = (self.s.counts_to_mm(pos) - self.s.counts_to_mm(self.target)).abs();
        self.status.target_reached =
            enabled && err < self.window_mm() && self.tpdo_sync > self.demand_since;
    }

    fn set_statusword(&mut self, sw: u16) {
        let w = Statusword(sw);
        let st = w.state();
        if let Some(to) = st
            && self.status.state != Some(to)
        {
            tracing::info!(from = ?self.status.state, to = %to, "follower drive power state");
            self.events.push_back(Event::PowerState {
                from: self.status.state,
                to,
            });
        }
        self.status.statusword = Some(sw);
        self.status.state = st;
        self.status.target_reached = w.target_reached();
        let pp = self.status.mode == Some(MODE_PROFILE_POSITION);
        let csp = self.status.mode == Some(MODE_CSP);
        self.status.setpoint_ack = pp && w.setpoint_ack();
        self.status.following_error = (pp || csp) && w.following_error();
    }

    fn set_position(&mut self, pos: i32) {
        self.status.position_counts = Some(pos);
        self.status.position_mm = Some(self.s.counts_to_mm(pos));
    }

    fn pdo_active(&self) -> bool {
        self.status.configured && self.hb.state() == Some(NmtState::Operational)
    }

    // --- outputs -----------------------------------------------------------------------

    pub fn poll_transmit(&mut self) -> Option<CanFrame> {
        self.tx.pop_front()
    }

    pub fn poll_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    pub fn poll_timeout(&self) -> Option<Instant> {
        [
            self.sdo.poll_timeout(),
            self.hb.poll_timeout(),
            self.sync.poll_timeout(),
            self.op.as_ref().and_then(|o| o.deadline),
        ]
        .into_iter()
        .flatten()
        .min()
    }

    // --- the command engine --------------------------------------------------------------

    fn finish(&mut self, op: Op, result: Result<(), DriveError>) {
        let result = match result {
            Ok(()) => Ok(op.reply.map_or(Reply::Done, Reply::Data)),
            Err(e) => {
                tracing::warn!(op = op.name, "{e}");
                // Never leave a set-point, homing start or fault reset request standing.
                self.set_cw(self.cw & !(CW_NEW_SETPOINT | CW_FAULT_RESET));
                Err(e)
            }
        };
        self.status.busy = None;
        self.complete(op.id, op.name, result);
    }

    fn set_cw(&mut self, cw: u16) {
        if cw != self.cw {
            self.cw = cw;
            self.cw_applied_at = self.sync.count() + 1;
        }
        self.status.controlword = self.cw;
    }

    fn set_target(&mut self, t: i32) {
        if t != self.target {
            self.target = t;
            self.cw_applied_at = self.sync.count() + 1;
            self.demand_since = self.sync.count() + 1;
            self.csp_demand_moved();
        }
    }

    fn run(&mut self, now: Instant) {
        // A command under way (or one that ends in this call) counts as activity.
        if self.op.is_some() || !self.queue.is_empty() {
            self.active_at = Some(now);
        }
        loop {
            if self.op.is_none() {
                let Some((id, cmd)) = self.queue.pop_front() else {
                    break;
                };
                self.status.busy = Some(cmd.name());
                let steps = self.plan(&cmd);
                self.op = Some(Op {
                    id,
                    name: cmd.name(),
                    steps,
                    started: false,
                    deadline: None,
                    after_sync: 0,
                    boot_mark: 0,
                    seen_progress: false,
                    restarts: 0,
                    reply: None,
                });
            }
            let Some(mut op) = self.op.take() else {
                break;
            };
            let Some(step) = op.steps.front().cloned() else {
                self.finish(op, Ok(()));
                continue;
            };
            let progress = if op.started {
                self.poll_step(&mut op, &step, now)
            } else {
                op.started = true;
                self.start_step(&mut op, &step, now)
            };
            match progress {
                Progress::Next | Progress::Replace(_) => {
                    op.steps.pop_front();
                    if let Progress::Replace(steps) = progress {
                        for s in steps.into_iter().rev() {
                            op.steps.push_front(s);
                        }
                    }
                    op.started = false;
                    op.deadline = None;
                    self.op = Some(op);
                }
                Progress::Wait => {
                    if op.deadline.is_some_and(|d| now >= d) {
                        let err = self.timeout_error(&step);
                        self.cancel_sdo_of(&op);
                        self.finish(op, Err(err));
                        continue;
                    }
                    self.op = Some(op);
                    break;
                }
                Progress::Fail(e) => self.finish(op, Err(e)),
            }
        }
        self.pace_sync(now);
        self.status.sync_running = self.sync.is_running();
    }

    /// SYNC at the quiet period once nothing has been under way or changed for
    /// [`QUIET_AFTER`]: in profile position (or not enabled), no command running or queued,
    /// not following. Anything else, and the first change the drive reports, brings back the
    /// full rate at once.
    fn pace_sync(&mut self, now: Instant) {
        // Commands were counted when `run` began (with this same `now`).
        if self.following || self.ramp.is_some() || self.status.mode == Some(MODE_CSP) {
            self.active_at = Some(now);
        }
        let quiet = self
            .active_at
            .is_none_or(|t| now.saturating_duration_since(t) >= QUIET_AFTER);
        self.sync.set_quiet(quiet, now);
        self.status.sync_quiet = self.sync.is_quiet();
    }

    fn timeout_error(&self, step: &Step) -> DriveError {
        let c = self.s.config();
        match step {
            Step::AwaitBootUp => DriveError::Timeout {
                what: "boot-up after reset",
                after: c.boot_timeout,
            },
            Step::AwaitNmt(_) => DriveError::Timeout {
                what: "heartbeat with the requested NMT state",
                after: self.nmt_timeout(),
            },
            Step::AwaitMode(_) => DriveError::Timeout {
                what: "modes of operation display (0x6061)",
                after: c.state_timeout,
            },
            Step::AwaitTpdo => DriveError::Timeout {
                what: "TPDO1 after SYNC",
                after: c.state_timeout,
            },
            Step::Power(_) => DriveError::Timeout {
                what: "power state transition",
                after: c.state_timeout,
            },
            Step::AwaitStatus(cond, after) => DriveError::Timeout {
                what: cond.what(),
                after: *after,
            },
            _ => DriveError::Timeout {
                what: "drive response",
                after: c.state_timeout,
            },
        }
    }

    fn nmt_timeout(&self) -> Duration {
        let c = self.s.config();
        c.state_timeout.max(c.heartbeat_timeout * 2)
    }

    /// A command as steps.
    fn plan(&self, cmd: &Command) -> VecDeque<Step> {
        let c = self.s.config();
        let mut v = Vec::new();
        match cmd {
            Command::Configure => return self.plan_configure(c.reset_communication),
            Command::Start => {
                v.push(Step::RequireConfigured);
                v.push(Step::Nmt(NmtCommand::StartRemoteNode));
                v.push(Step::AwaitNmt(NmtState::Operational));
                v.push(Step::SyncOn);
                v.push(Step::AwaitTpdo);
            }
            Command::Nmt(n) => {
                v.push(Step::Nmt(*n));
                match n {
                    NmtCommand::StartRemoteNode => {
                        v.push(Step::AwaitNmt(NmtState::Operational));
                        if self.status.configured {
                            v.push(Step::SyncOn);
                        }
                    }
                    NmtCommand::StopRemoteNode => v.push(Step::AwaitNmt(NmtState::Stopped)),
                    NmtCommand::EnterPreOperational => {
                        v.push(Step::AwaitNmt(NmtState::PreOperational))
                    }
                    NmtCommand::ResetNode | NmtCommand::ResetCommunication => {
                        v.push(Step::AwaitBootUp);
                        v.push(Step::Settle(c.boot_settle));
                    }
                }
            }
            Command::Enable => {
                v.push(Step::RequirePdo);
                v.push(Step::Power(PowerState::OperationEnabled));
            }
            Command::Disable => {
                v.push(Step::RequirePdo);
                v.push(Step::Power(PowerState::SwitchOnDisabled));
            }
            Command::Home => {
                let h = c.homing;
                v.push(Step::RequirePdo);
                v.push(Step::RequireEnabled);
                v.push(Step::CspLeave {
                    stop_following: false,
                });
                v.push(Step::EnsureMode(MODE_HOMING));
                // Bit 4 low first so that setting it is a rising edge.
                v.push(Step::Cw {
                    set: 0,
                    clear: CW_NEW_SETPOINT | CW_HALT,
                });
                v.push(Step::AwaitStatus(Cond::Applied, c.state_timeout));
                v.push(Step::Cw {
                    set: cia402::CW_HOMING_START,
                    clear: 0,
                });
                v.push(Step::AwaitStatus(Cond::HomingDone, h.timeout));
                v.push(Step::Cw {
                    set: 0,
                    clear: cia402::CW_HOMING_START,
                });
                v.push(Step::AwaitStatus(Cond::Applied, c.state_timeout));
                v.push(Step::MarkHomed);
            }
            Command::MoveTo { target_mm } => self.plan_move(&mut v, Motion::Absolute(*target_mm)),
            Command::Jog { delta_mm } => self.plan_move(&mut v, Motion::Relative(*delta_mm)),
            Command::SetTarget { target_mm } => self.plan_move(&mut v, Motion::Track(*target_mm)),
            Command::Follow { target_mm } => {
                v.push(Step::RequirePdo);
                v.push(Step::RequireEnabled);
                v.push(Step::RequireHomed);
                v.push(Step::CspEnter(*target_mm));
            }
            Command::StopFollowing => v.push(Step::CspLeave {
                stop_following: true,
            }),
            Command::Stop => {
                v.push(Step::RequirePdo);
                v.push(Step::Cw {
                    set: CW_HALT,
                    clear: CW_NEW_SETPOINT,
                });
                v.push(Step::AwaitStatus(
                    Cond::Stopped,
                    c.state_timeout + self.stop_time(c.profile.decel_mm_s2),
                ));
            }
            Command::QuickStop => {
                v.push(Step::RequirePdo);
                v.push(Step::Cw {
                    set: FsaCommand::QuickStop.bits(),
                    clear: CW_COMMAND_MASK | CW_NEW_SETPOINT,
                });
                v.push(Step::AwaitStatus(
                    Cond::QuickStopped,
                    c.state_timeout + self.stop_time(c.profile.quick_stop_decel_mm_s2),
                ));
            }
            Command::FaultReset => {
                v.push(Step::RequirePdo);
                v.push(Step::Cw {
                    set: FsaCommand::DisableVoltage.bits(),
                    clear: CW_COMMAND_MASK | CW_NEW_SETPOINT,
                });
                v.push(Step::AwaitStatus(Cond::Applied, c.state_timeout));
                v.push(Step::Cw {
                    set: CW_FAULT_RESET,
                    clear: 0,
                });
                v.push(Step::AwaitStatus(Cond::NotFault, c.state_timeout));
                v.push(Step::Cw {
                    set: 0,
                    clear: CW_FAULT_RESET,
                });
                v.push(Step::AwaitStatus(Cond::Applied, c.state_timeout));
            }
            Command::SdoRead(obj) => v.push(Step::Read(*obj, ReadUse::Reply)),
            Command::SdoWrite(obj, data) => v.push(Step::Write(SdoWrite::bytes(
                obj.index,
                obj.sub,
                data.clone(),
            ))),
        }
        v.into()
    }

    fn plan_configure(&self, reset: bool) -> VecDeque<Step> {
        let mut v = vec![Step::SyncOff, Step::SetConfigured(false)];
        if reset {
            v.push(Step::Nmt(NmtCommand::ResetCommunication));
            v.push(Step::AwaitBootUp);
            // A power-on boot-up still in flight may have been taken for the reset's.
            v.push(Step::Settle(self.s.config().boot_settle));
        }
        v.push(Step::Nmt(NmtCommand::EnterPreOperational));
        v.push(Step::Read(ObjAddr::new(0x1000, 0), ReadUse::DeviceType));
        v.push(Step::Write(SdoWrite::u16(0x1017, 0, self.s.heartbeat_ms())));
        for w in pdo::follower_pdo_sequence(self.s.node()) {
            v.push(Step::Write(w));
        }
        for w in self.parameter_writes() {
            v.push(Step::Write(w));
        }
        v.push(Step::Read(ObjAddr::new(0x6041, 0), ReadUse::Statusword));
        v.push(Step::Read(ObjAddr::new(0x6064, 0), ReadUse::Position));
        v.push(Step::Read(ObjAddr::new(0x6061, 0), ReadUse::Mode));
        v.push(Step::AwaitNmt(NmtState::PreOperational));
        v.push(Step::SetConfigured(true));
        v.into()
    }

    fn plan_move(&self, v: &mut Vec<Step>, m: Motion) {
        v.push(Step::RequirePdo);
        v.push(Step::RequireEnabled);
        v.push(Step::RequireHomed);
        v.push(Step::CspLeave {
            stop_following: false,
        });
        v.push(Step::EnsureMode(MODE_PROFILE_POSITION));
        v.push(Step::Plan(m));
    }

    /// Time to stop from profile velocity at `decel`.
    fn stop_time(&self, decel: f64) -> Duration {
        Duration::from_secs_f64(self.s.config().profile.velocity_mm_s / decel)
    }

    /// How long a profile move over `dist_mm` takes (trapezoid or triangle).
    fn move_time(&self, dist_mm: f64) -> Duration {
        let p = self.s.config().profile;
        let (v, a, d) = (p.velocity_mm_s, p.accel_mm_s2, p.decel_mm_s2);
        let dist = dist_mm.abs();
        let ramps = v * v / (2.0 * a) + v * v / (2.0 * d);
        let t = if dist >= ramps {
            dist / v + v / (2.0 * a) + v / (2.0 * d)
        } else {
            let vp = (2.0 * dist * a * d / (a + d)).sqrt();
            vp / a + vp / d
        };
        Duration::from_secs_f64(t.min(1e6))
    }

    /// A generous bound on the ramp coming to rest over `dist_mm` from `vel` (mm/s).
    fn ramp_time(&self, dist_mm: f64, vel: f64) -> Duration {
        let p = self.s.config().profile;
        let (v, a) = (p.velocity_mm_s, p.accel_mm_s2);
        let t = dist_mm.abs() / v + 2.0 * v / a + vel.abs() / a;
        Duration::from_secs_f64((2.0 * t).min(1e6))
    }

    fn parameter_writes(&self) -> Vec<SdoWrite> {
        let c = self.s.config();
        let s = &self.s;
        let u = |v: f64| s.unsigned_counts(v).unwrap_or(u32::MAX);
        let i = |v: f64| s.mm_to_counts(v).unwrap_or(0);
        let mut w = vec![
            SdoWrite::u32(0x6081, 0, u(c.profile.velocity_mm_s)),
            SdoWrite::u32(0x6083, 0, u(c.profile.accel_mm_s2)),
            SdoWrite::u32(0x6084, 0, u(c.profile.decel_mm_s2)),
            SdoWrite::u32(0x6085, 0, u(c.profile.quick_stop_decel_mm_s2)).optional(),
            SdoWrite::u32(0x6067, 0, u(c.profile.position_window_mm)).optional(),
            SdoWrite::u32(0x6065, 0, u(c.profile.following_error_window_mm)).optional(),
            SdoWrite::i8(0x6098, 0, c.homing.method),
            SdoWrite::u32(0x6099, 1, u(c.homing.switch_speed_mm_s)),
            SdoWrite::u32(0x6099, 2, u(c.homing.zero_speed_mm_s)),
            SdoWrite::u32(0x609A, 0, u(c.homing.accel_mm_s2)).optional(),
            SdoWrite::i32(0x607C, 0, i(c.homing.offset_mm)).optional(),
        ];
        if c.limits.write_to_drive {
            w.push(SdoWrite::i32(0x607D, 1, i(c.limits.min_mm)).optional());
            w.push(SdoWrite::i32(0x607D, 2, i(c.limits.max_mm)).optional());
        }
        w
    }

    fn start_sdo(&mut self, r: Result<(), SdoError>) -> Progress {
        self.collect_sdo();
        match r {
            Ok(()) => Progress::Wait,
            Err(e) => Progress::Fail(e.into()),
        }
    }

    fn start_step(&mut self, op: &mut Op, step: &Step, now: Instant) -> Progress {
        let c = *self.s.config();
        match step {
            Step::SetConfigured(b) => {
                if !b {
                    self.forget_configuration();
                }
                self.status.configured = *b;
                Progress::Next
            }
            Step::RequireConfigured => {
                if self.status.configured {
                    Progress::Next
                } else {
                    Progress::Fail(DriveError::NotConfigured { what: op.name })
                }
            }
            Step::RequirePdo => {
                if self.pdo_active() && self.sync.is_running() {
                    Progress::Next
                } else {
                    Progress::Fail(DriveError::NotOperational { what: op.name })
                }
            }
            Step::RequireEnabled => match self.status.state {
                Some(PowerState::OperationEnabled) => Progress::Next,
                Some(st) if st.is_fault() => Progress::Fail(self.fault()),
                st => Progress::Fail(DriveError::NotEnabled {
                    what: op.name,
                    state: st.map_or("an unknown state".into(), |s| s.to_string()),
                }),
            },
            Step::RequireHomed => {
                if c.require_homing && !self.status.homed {
                    Progress::Fail(DriveError::NotHomed)
                } else {
                    Progress::Next
                }
            }
            Step::Nmt(n) => {
                if !matches!(n, NmtCommand::StartRemoteNode) {
                    self.abort_following(DriveError::Interrupted { by: "NMT command" });
                }
                op.boot_mark = self.boot_count;
                if matches!(n, NmtCommand::ResetNode | NmtCommand::ResetCommunication) {
                    self.forget_configuration();
                }
                if !matches!(n, NmtCommand::StartRemoteNode) {
                    self.sync.stop();
                }
                self.tx.push_back(command_frame(*n, self.s.node()));
                Progress::Next
            }
            Step::AwaitBootUp => {
                op.deadline = Some(now + c.boot_timeout);
                self.poll_step(op, step, now)
            }
            Step::AwaitNmt(_) => {
                op.deadline = Some(now + self.nmt_timeout());
                self.poll_step(op, step, now)
            }
            Step::Settle(d) => {
                op.deadline = Some(now + *d);
                self.poll_step(op, step, now)
            }
            Step::Write(w) => {
                let r = self.sdo.download(w.obj, w.data.clone(), now);
                self.start_sdo(r)
            }
            Step::Read(obj, _) => {
                let r = self.sdo.upload(*obj, now);
                self.start_sdo(r)
            }
            Step::EnsureMode(m) => {
                if self.status.mode == Some(*m) {
                    return Progress::Next;
                }
                self.status.mode = None;
                Progress::Replace(vec![
                    Step::Write(SdoWrite::i8(0x6060, 0, *m)),
                    Step::AwaitMode(*m),
                ])
            }
            Step::AwaitMode(_) => {
                op.deadline = Some(now + c.state_timeout);
                let r = self.sdo.upload(ObjAddr::new(0x6061, 0), now);
                self.start_sdo(r)
            }
            Step::SyncOn => {
                self.sync.start(now);
                Progress::Next
            }
            Step::SyncOff => {
                self.sync.stop();
                Progress::Next
            }
            Step::AwaitTpdo => {
                op.after_sync = self.sync.count() + 1;
                op.deadline = Some(now + c.state_timeout);
                Progress::Wait
            }
            Step::Power(_) => {
                op.deadline = Some(now + c.state_timeout);
                self.poll_step(op, step, now)
            }
            Step::Cw { set, clear } => {
                self.set_cw((self.cw & !clear) | set);
                Progress::Next
            }
            Step::Target(t) => {
                self.set_target(*t);
                Progress::Next
            }
            Step::Commanded(t) => {
                self.commanded = Some(*t);
                self.status.commanded_mm = Some(self.s.counts_to_mm(*t));
                Progress::Next
            }
            Step::Plan(m) => self.expand_move(*m),
            Step::AwaitStatus(_, after) => {
                op.deadline = Some(now + *after);
                self.poll_step(op, step, now)
            }
            Step::MarkHomed => {
                self.status.homed = true;
                if let Some(p) = self.status.position_counts {
                    self.commanded = Some(p);
                    self.status.commanded_mm = Some(self.s.counts_to_mm(p));
                    self.set_target(p);
                }
                Progress::Next
            }
            Step::CspEnter(t) => self.csp_enter(*t, now),
            Step::HoldActual => {
                if let Some(p) = self.status.position_counts {
                    self.set_target(p);
                }
                Progress::Next
            }
            Step::CspStart => {
                let (p, l) = (c.profile, c.limits);
                let start = self.s.counts_to_mm(self.target);
                let lead = c.csp_lead_periods * c.sync_period.as_secs_f64();
                let mut r =
                    DemandRamp::new(start, p.velocity_mm_s, p.accel_mm_s2, l.min_mm, l.max_mm)
                        .with_lead(lead);
                if let Some(g) = self.follow_track.latest() {
                    r.hold_at(g);
                }
                self.ramp = Some(r);
                self.ramp_new = true;
                self.commanded = Some(self.target);
                self.status.commanded_mm = Some(start);
                self.start_following();
                Progress::Next
            }
            Step::CspLeave { stop_following } => self.csp_leave(*stop_following),
            Step::CspEnd => {
                self.ramp = None;
                self.commanded = Some(self.target);
                self.status.commanded_mm = Some(self.s.counts_to_mm(self.target));
                Progress::Next
            }
        }
    }

    /// The steps into following: let a profile move end, hold the actual position as the
    /// demand (so the switch asks for no motion), mode 8 confirmed in 0x6061, then stream.
    fn csp_enter(&mut self, target_mm: f64, now: Instant) -> Progress {
        if let Err(e) = self.check_limits(target_mm) {
            return Progress::Fail(e);
        }
        if self.follow_track.latest().is_none() {
            self.follow_track.push(target_mm, now);
        }
        if self.ramp.is_some() {
            self.start_following();
            return Progress::Next;
        }
        let c = *self.s.config();
        let mut v = Vec::new();
        if self.status.mode == Some(MODE_PROFILE_POSITION) && !self.status.target_reached {
            let here = self.status.position_counts.unwrap_or(0);
            let dist =
                self.s.counts_to_mm(self.commanded.unwrap_or(here)) - self.s.counts_to_mm(here);
            let t = c.state_timeout + self.move_time(dist) * 2 + c.profile.move_timeout_margin;
            v.push(Step::AwaitStatus(Cond::TargetReached, t));
        }
        v.push(Step::Cw {
            set: 0,
            clear: CW_NEW_SETPOINT | CW_CHANGE_IMMEDIATELY | CW_RELATIVE | CW_HALT,
        });
        v.push(Step::HoldActual);
        v.push(Step::AwaitStatus(Cond::Applied, c.state_timeout));
        v.push(Step::EnsureMode(MODE_CSP));
        v.push(Step::CspStart);
        Progress::Replace(v)
    }

    /// The steps out of following: the demand to rest (on the last target for stop following,
    /// else where it can stop), reached, then profile position for stop following.
    fn csp_leave(&mut self, stop_following: bool) -> Progress {
        let c = *self.s.config();
        let period = c.sync_period.as_secs_f64();
        let mut v = Vec::new();
        let to_last = if stop_following && self.following {
            self.follow_track.latest()
        } else {
            None
        };
        if let Some(r) = self.ramp.as_mut() {
            let goal = to_last.unwrap_or_else(|| r.stopping_point(period));
            r.hold_at(goal);
            let (dist, vel) = (goal - r.pos(), r.vel());
            v.push(Step::AwaitStatus(
                Cond::CspSettled,
                c.state_timeout + self.ramp_time(dist, vel),
            ));
            v.push(Step::CspEnd);
        }
        self.end_following(Ok(()));
        if stop_following && (self.status.mode == Some(MODE_CSP) || self.ramp.is_some()) {
            v.push(Step::EnsureMode(MODE_PROFILE_POSITION));
        }
        Progress::Replace(v)
    }

    /// Turn a move into its concrete steps, now that the current state is known.
    fn expand_move(&mut self, m: Motion) -> Progress {
        let c = *self.s.config();
        let base = self.commanded.or(self.status.position_counts).unwrap_or(0);
        let here = self.status.position_counts.unwrap_or(base);
        let (target_mm, relative, immediate) = match m {
            Motion::Absolute(t) => (t, false, c.profile.change_immediately),
            Motion::Track(t) => (t, false, true),
            Motion::Relative(d) => (self.s.counts_to_mm(base) + d, true, false),
        };
        let l = c.limits;
        if !(target_mm >= l.min_mm && target_mm <= l.max_mm) {
            return Progress::Fail(DriveError::OutOfLimits {
                target_mm,
                min_mm: l.min_mm,
                max_mm: l.max_mm,
            });
        }
        let Some(abs) = self.s.mm_to_counts(target_mm) else {
            return Progress::Fail(DriveError::OutOfLimits {
                target_mm,
                min_mm: l.min_mm,
                max_mm: l.max_mm,
            });
        };
        let value = if relative { abs - base } else { abs };
        let mut set = CW_NEW_SETPOINT;
        let mut clear = CW_HALT | CW_RELATIVE | CW_CHANGE_IMMEDIATELY;
        if relative {
            set |= CW_RELATIVE;
            clear &= !CW_RELATIVE;
        }
        if immediate {
            set |= CW_CHANGE_IMMEDIATELY;
            clear &= !CW_CHANGE_IMMEDIATELY;
        }
        let dist = self.s.counts_to_mm(abs) - self.s.counts_to_mm(here);
        let mut steps = vec![
            Step::AwaitStatus(Cond::AckClear, c.state_timeout),
            Step::Target(value),
            Step::Cw { set, clear },
            Step::AwaitStatus(Cond::AckSet, c.state_timeout),
            Step::Cw {
                set: 0,
                clear: CW_NEW_SETPOINT,
            },
            Step::Commanded(abs),
        ];
        if !matches!(m, Motion::Track(_)) {
            let t = self.move_time(dist) * 2 + c.profile.move_timeout_margin;
            steps.push(Step::AwaitStatus(Cond::TargetReached, t));
        }
        Progress::Replace(steps)
    }

    fn fault(&self) -> DriveError {
        DriveError::Fault {
            emcy: self.status.last_emcy,
        }
    }

    fn poll_step(&mut self, op: &mut Op, step: &Step, now: Instant) -> Progress {
        match step {
            Step::AwaitBootUp => {
                if self.boot_count > op.boot_mark {
                    Progress::Next
                } else {
                    Progress::Wait
                }
            }
            Step::Settle(_) => {
                if op.deadline.is_none_or(|d| now >= d) {
                    Progress::Next
                } else {
                    Progress::Wait
                }
            }
            Step::AwaitNmt(want) => {
                if self.hb.state() == Some(*want) && self.hb.is_alive() {
                    Progress::Next
                } else {
                    Progress::Wait
                }
            }
            Step::Write(w) => match self.sdo_result.take() {
                None => Progress::Wait,
                Some(Ok(_)) => Progress::Next,
                Some(Err(e)) if w.optional && e.is_missing_object() => {
                    tracing::debug!("optional object {} absent on the drive", w.obj);
                    Progress::Next
                }
                Some(Err(e)) => Progress::Fail(e.into()),
            },
            Step::Read(obj, use_) => match self.sdo_result.take() {
                None => Progress::Wait,
                Some(Err(e)) => Progress::Fail(e.into()),
                Some(Ok(o)) => self.use_read(op, *obj, *use_, uploaded(o)),
            },
            Step::AwaitMode(m) => match self.sdo_result.take() {
                None => Progress::Wait,
                Some(Err(e)) => Progress::Fail(e.into()),
                Some(Ok(o)) => match value::i8(&uploaded(o)) {
                    Some(got) if got == *m => {
                        self.status.mode = Some(got);
                        Progress::Next
                    }
                    Some(_) => {
                        let r = self.sdo.upload(ObjAddr::new(0x6061, 0), now);
                        self.start_sdo(r)
                    }
                    None => Progress::Fail(DriveError::BadLength {
                        obj: ObjAddr::new(0x6061, 0),
                        len: 0,
                        want: 1,
                    }),
                },
            },
            Step::AwaitTpdo => {
                if self.status.tpdo_count > 0 && self.tpdo_sync >= op.after_sync {
                    Progress::Next
                } else {
                    Progress::Wait
                }
            }
            Step::Power(to) => self.poll_power(op, *to, now),
            Step::AwaitStatus(cond, _) => self.poll_status(op, *cond),
            _ => Progress::Next,
        }
    }

    fn use_read(&mut self, op: &mut Op, obj: ObjAddr, use_: ReadUse, data: Vec<u8>) -> Progress {
        let bad = |want: usize| {
            Progress::Fail(DriveError::BadLength {
                obj,
                len: data.len(),
                want,
            })
        };
        match use_ {
            ReadUse::DeviceType => match value::u32(&data) {
                Some(t) if t & 0xFFFF == 0x0192 => Progress::Next,
                Some(t) => Progress::Fail(DriveError::NotADrive(t)),
                None => bad(4),
            },
            ReadUse::Statusword => match value::u16(&data) {
                Some(sw) => {
                    self.set_statusword(sw);
                    Progress::Next
                }
                None => bad(2),
            },
            ReadUse::Position => match value::i32(&data) {
                Some(p) => {
                    self.set_position(p);
                    self.status.position_at = None;
                    self.set_target(p);
                    self.commanded = None;
                    self.status.commanded_mm = None;
                    Progress::Next
                }
                None => bad(4),
            },
            ReadUse::Mode => match value::i8(&data) {
                Some(m) => {
                    self.status.mode = Some(m);
                    Progress::Next
                }
                None => bad(1),
            },
            ReadUse::Reply => {
                op.reply = Some(data);
                Progress::Next
            }
        }
    }

    /// Whether the last TPDO reflects the current RPDO image.
    fn fresh(&self) -> bool {
        self.status.tpdo_count > 0 && self.tpdo_sync >= self.cw_applied_at
    }

    fn poll_power(&mut self, op: &mut Op, to: PowerState, now: Instant) -> Progress {
        if !self.fresh() {
            return Progress::Wait;
        }
        let Some(from) = self.status.state else {
            return Progress::Wait;
        };
        match cia402::next_step(from, to) {
            NextStep::Done => Progress::Next,
            NextStep::Wait => Progress::Wait,
            NextStep::Send(cmd) => {
                let cw = cmd.apply_to(self.cw) & !(CW_NEW_SETPOINT | CW_FAULT_RESET);
                if cw != self.cw {
                    self.set_cw(cw);
                    op.deadline = Some(now + self.s.config().state_timeout);
                }
                Progress::Wait
            }
            NextStep::Blocked if from.is_fault() => Progress::Fail(self.fault()),
            NextStep::Blocked => Progress::Fail(DriveError::NoPath { from, to }),
        }
    }

    fn poll_status(&mut self, op: &mut Op, cond: Cond) -> Progress {
        if !self.fresh() {
            return Progress::Wait;
        }
        let Some(sw) = self.status.statusword.map(Statusword) else {
            return Progress::Wait;
        };
        let st = sw.state();
        match cond {
            Cond::Applied => return Progress::Next,
            Cond::NotFault => {
                return match st {
                    Some(s) if !s.is_fault() => Progress::Next,
                    _ => Progress::Wait,
                };
            }
            _ => {}
        }
        if st.is_some_and(PowerState::is_fault) {
            return Progress::Fail(self.fault());
        }
        let enabled = st == Some(PowerState::OperationEnabled);
        let not_enabled = || DriveError::NotEnabled {
            what: op.name,
            state: st.map_or("an unknown state".into(), |s| s.to_string()),
        };
        match cond {
            Cond::Applied | Cond::NotFault => Progress::Next,
            Cond::AckSet | Cond::AckClear | Cond::TargetReached | Cond::CspSettled if !enabled => {
                Progress::Fail(not_enabled())
            }
            Cond::CspSettled if sw.following_error() => Progress::Fail(DriveError::FollowingError),
            // Reached and still (not passing through the window), before a mode switch.
            Cond::CspSettled => yes(self.ramp.is_none_or(|r| r.at_rest())
                && self.status.target_reached
                && self.standstill
                && self.tpdo_sync > self.demand_since),
            Cond::AckSet if sw.following_error() => Progress::Fail(DriveError::FollowingError),
            Cond::AckSet => yes(sw.setpoint_ack()),
            Cond::AckClear => yes(!sw.setpoint_ack()),
            Cond::TargetReached if sw.following_error() => {
                Progress::Fail(DriveError::FollowingError)
            }
            Cond::TargetReached => yes(sw.target_reached()),
            Cond::HomingDone => {
                if !enabled {
                    return Progress::Fail(not_enabled());
                }
                match sw.homing() {
                    HomingStatus::Completed => Progress::Next,
                    HomingStatus::InProgress | HomingStatus::AttainedNotReached => {
                        op.seen_progress = true;
                        Progress::Wait
                    }
                    HomingStatus::Interrupted if !op.seen_progress => Progress::Wait,
                    h => Progress::Fail(DriveError::Homing(h)),
                }
            }
            Cond::Stopped => yes(self.still(sw) || !enabled),
            Cond::QuickStopped => yes(st == Some(PowerState::SwitchOnDisabled)
                || (st == Some(PowerState::QuickStopActive) && self.still(sw))
                || !matches!(
                    st,
                    Some(PowerState::QuickStopActive | PowerState::OperationEnabled)
                )),
        }
    }

    /// At standstill: bit 10 (target reached, profile position and homing), or in cyclic
    /// synchronous position (where bit 10 is reserved) a position that stayed within the
    /// position window between the last two TPDOs.
    fn still(&self, sw: Statusword) -> bool {
        if self.status.mode == Some(MODE_CSP) {
            self.standstill
        } else {
            sw.target_reached()
        }
    }
}

/// The bytes of an upload (none for a download, which a read step never starts).
fn uploaded(o: SdoOutcome) -> Vec<u8> {
    match o {
        SdoOutcome::Uploaded { data, .. } => data,
        SdoOutcome::Downloaded { .. } => Vec::new(),
    }
}

fn yes(b: bool) -> Progress {
    if b { Progress::Next } else { Progress::Wait }
}

#[cfg(test)]
mod tests {
    //! The master against the twin drive's machine, both on one virtual clock: frames are
    //! delivered at once, time jumps from deadline to deadline.
    use super::*;
    use crate::canopen::pdo::{RPDO1_MAP, TPDO1_MAP};
    use crate::sim::drive::{SdoRefusal, TwinDrive, TwinDriveConfig};
    use std::sync::{Arc, Mutex};

    struct Rig {
        t: Instant,
        t0: Instant,
        m: Master,
        d: TwinDrive,
        events: Vec<(Duration, Event)>,
        log: Vec<String>,
        plant: Arc<Mutex<f64>>,
    }

    impl Rig {
        fn new(cfg: DriveConfig, twin: TwinDriveConfig) -> Rig {
            let t0 = crate::util::clock::now();
            let plant = Arc::new(Mutex::new(f64::NAN));
            let p = plant.clone();
            let d = TwinDrive::new(twin, Box::new(move |mm| *p.lock().unwrap() = mm), t0).unwrap();
            let mut r = Rig {
                t: t0,
                t0,
                m: Master::new(&cfg).unwrap(),
                d,
                events: vec![],
                log: vec![],
                plant,
            };
            r.pump();
            r
        }

        fn default() -> Rig {
            Rig::new(
                DriveConfig::default(),
                TwinDriveConfig {
                    start_mm: 2.0,
                    ..Default::default()
                },
            )
        }

        fn pump(&mut self) {
            for _ in 0..10_000 {
                let mut any = false;
                while let Some(f) = self.m.poll_transmit() {
                    self.log.push(format!("{f:?}"));
                    self.d.handle_frame(&f, self.t);
                    any = true;
                }
                while let Some(f) = self.d.poll_transmit() {
                    self.log.push(format!("{f:?}"));
                    self.m.handle_frame(&f, self.t);
                    any = true;
                }
                while let Some(e) = self.m.poll_event() {
                    self.events.push((self.t - self.t0, e));
                }
                if !any {
                    return;
                }
            }
            panic!("the machines keep talking");
        }

        /// Let `dur` of virtual time pass.
        fn advance(&mut self, dur: Duration) {
            let end = self.t + dur;
            for _ in 0..10_000_000 {
                self.pump();
                let next = [self.m.poll_timeout(), self.d.poll_timeout()]
                    .into_iter()
                    .flatten()
                    .min();
                match next {
                    Some(n) if n <= end => {
                        self.t = self.t.max(n);
                        self.m.handle_timeout(self.t);
                        self.d.handle_timeout(self.t);
                    }
                    _ => {
                        self.t = end;
                        self.pump();
                        return;
                    }
                }
            }
            panic!("time does not advance");
        }

        fn completion(&self, id: OpId) -> Option<Result<Reply, DriveError>> {
            self.events.iter().find_map(|(_, e)| match e {
                Event::Completed { id: i, result } if *i == id => Some(result.clone()),
                _ => None,
            })
        }

        /// Submit and run until done (at most `limit` of virtual time).
        fn run(&mut self, cmd: Command, limit: Duration) -> Result<Reply, DriveError> {
            let id = self.m.submit(cmd, self.t);
            let end = self.t + limit;
            while self.t < end {
                self.advance(Duration::from_millis(5));
                if let Some(r) = self.completion(id) {
                    return r;
                }
            }
            panic!("command {id} not done within {limit:?}");
        }

        fn ok(&mut self, cmd: Command) {
            let name = cmd.name();
            if let Err(e) = self.run(cmd, Duration::from_secs(60)) {
                panic!("{name}: {e}");
            }
        }

        fn ready(&mut self) {
            self.ok(Command::Configure);
            self.ok(Command::Start);
            self.ok(Command::Enable);
            self.ok(Command::Home);
        }

        fn frames_since(&self, start: usize, prefix: &str) -> Vec<String> {
            self.log[start..]
                .iter()
                .filter(|l| l.starts_with(prefix))
                .cloned()
                .collect()
        }

        /// The distinct successive controlwords of the RPDO1 frames since `start`.
        fn controlwords(&self, start: usize) -> Vec<u16> {
            let mut v: Vec<u16> = vec![];
            for l in self.frames_since(start, "201#") {
                let cw = u16::from_str_radix(&l[6..8], 16).unwrap() << 8
                    | u16::from_str_radix(&l[4..6], 16).unwrap();
                if v.last() != Some(&cw) {
                    v.push(cw);
                }
            }
            v
        }
    }

    #[test]
    fn configure_writes_the_pdo_mapping_and_the_drive_honours_it() {
        let mut r = Rig::default();
        let start = r.log.len();
        r.ok(Command::Configure);
        let sdo = r.frames_since(start, "601#");
        // Reset communication, boot-up, pre-operational, then SDO: first the device type.
        assert_eq!(r.log[start], "000#8201");
        assert_eq!(r.log[start + 1], "701#00");
        assert_eq!(r.log[start + 2], "000#8001");
        assert_eq!(sdo[0], "601#4000100000000000");
        // Heartbeat time 100 ms = 0x0064 as UNSIGNED16 (0x2B: 2 bytes).
        assert_eq!(sdo[1], "601#2B17100064000000");
        // RPDO1: disable (bit 31), type 1, count 0, 0x60400010, 0x607A0020, count 2, enable.
        // Bytes: command (0x23: 4 bytes, 0x2F: 1 byte), index LE, sub-index, value LE.
        assert_eq!(
            &sdo[2..9],
            &[
                "601#2300140101020080",
                "601#2F00140201000000",
                "601#2F00160000000000",
                "601#2300160110004060",
                "601#2300160220007A60",
                "601#2F00160002000000",
                "601#2300140101020000",
            ]
        );
        // TPDO1 likewise.
        assert_eq!(
            &sdo[9..16],
            &[
                "601#2300180181010080",
                "601#2F00180201000000",
                "601#2F001A0000000000",
                "601#23001A0110004160",
                "601#23001A0220006460",
                "601#2F001A0002000000",
                "601#2300180181010000",
            ]
        );
        // The twin has no PDOs 2–4: its "object does not exist" aborts are tolerated.
        assert_eq!(r.frames_since(start, "581#80011401").len(), 1);
        let s = r.d.status();
        assert_eq!(s.rpdo1_map, RPDO1_MAP.to_vec());
        assert_eq!(s.tpdo1_map, TPDO1_MAP.to_vec());
        assert!(s.rpdo1_valid && s.tpdo1_valid);
        assert_eq!(s.heartbeat_ms, 100);
        let st = r.m.status();
        assert!(st.configured && st.heartbeat_ok);
        assert_eq!(st.nmt, Some(NmtState::PreOperational));
        assert_eq!(st.state, Some(PowerState::SwitchOnDisabled));
        assert_eq!(st.position_mm, Some(0.0));
        assert!(
            r.events
                .iter()
                .any(|(_, e)| *e == Event::BootUp { expected: true })
        );
    }

    #[test]
    fn enable_walks_shutdown_switch_on_enable_operation() {
        let mut r = Rig::default();
        r.ok(Command::Configure);
        r.ok(Command::Start);
        assert!(r.m.status().sync_running);
        assert_eq!(r.m.status().nmt, Some(NmtState::Operational));
        let start = r.log.len();
        r.ok(Command::Enable);
        // The first TPDO after the request already leads to shutdown: 0x06, 0x07, 0x0F.
        assert_eq!(r.controlwords(start), vec![0x0006, 0x0007, 0x000F]);
        assert_eq!(r.m.status().state, Some(PowerState::OperationEnabled));
        let states: Vec<PowerState> = r
            .events
            .iter()
            .filter_map(|(_, e)| match e {
                Event::PowerState { to, .. } => Some(*to),
                _ => None,
            })
            .collect();
        assert_eq!(
            states,
            vec![
                PowerState::SwitchOnDisabled,
                PowerState::ReadyToSwitchOn,
                PowerState::SwitchedOn,
                PowerState::OperationEnabled
            ]
        );
        // Each RPDO goes out right before its SYNC.
        let i = r.log.iter().rposition(|l| l.starts_with("201#")).unwrap();
        assert_eq!(r.log[i + 1], "080#");
        let start = r.log.len();
        r.ok(Command::Disable);
        assert_eq!(r.controlwords(start), vec![0x0000]);
        assert_eq!(r.m.status().state, Some(PowerState::SwitchOnDisabled));
    }

    #[test]
    fn homing_handshake() {
        let mut r = Rig::default();
        r.ok(Command::Configure);
        r.ok(Command::Start);
        r.ok(Command::Enable);
        // Moves are refused before homing.
        assert_eq!(
            r.run(Command::MoveTo { target_mm: 1.0 }, Duration::from_secs(1)),
            Err(DriveError::NotHomed)
        );
        let start = r.log.len();
        r.ok(Command::Home);
        // 0x6060 = 6 (homing) by SDO, confirmed in 0x6061; bit 4 up, then down.
        assert!(
            r.frames_since(start, "601#")
                .contains(&"601#2F60600006000000".to_string())
        );
        assert!(
            r.frames_since(start, "601#")
                .contains(&"601#4061600000000000".to_string())
        );
        assert_eq!(r.controlwords(start), vec![0x001F, 0x000F]);
        let st = r.m.status();
        assert!(st.homed);
        assert_eq!(st.mode, Some(6));
        assert_eq!(st.position_counts, Some(0));
        // The stage went from 2 mm to the switch at 0, which the plant saw.
        assert_eq!(*r.plant.lock().unwrap(), 0.0);
        assert!(r.d.status().homed);
    }

    #[test]
    fn homing_error_is_reported() {
        let cfg = DriveConfig {
            homing: crate::canopen::HomingConfig {
                method: 0,
                ..Default::default()
            },
            ..Default::default()
        };
        let mut r = Rig::new(cfg, TwinDriveConfig::default());
        r.ok(Command::Configure);
        r.ok(Command::Start);
        r.ok(Command::Enable);
        assert_eq!(
            r.run(Command::Home, Duration::from_secs(5)),
            Err(DriveError::Homing(HomingStatus::ErrorStopped))
        );
        // Bit 4 is not left standing.
        assert_eq!(r.m.status().controlword & CW_NEW_SETPOINT, 0);
    }

    #[test]
    fn profile_position_handshake_and_positions() {
        let mut r = Rig::default();
        r.ready();
        let cpm = r.m.settings().counts_per_mm();
        for target in [3.0, -1.25, 7.5, 7.5, 0.0] {
            let start = r.log.len();
            let t0 = r.t;
            r.ok(Command::MoveTo { target_mm: target });
            // New set-point (bit 4) with the target, then bit 4 down after the acknowledge.
            let cws = r.controlwords(start);
            assert!(cws.ends_with(&[0x001F, 0x000F]), "{target}: {cws:?}");
            assert!(cws.iter().all(|c| [0x000F, 0x001F].contains(c)), "{cws:?}");
            let want = (target * cpm).round() as i32;
            let rpdo = format!("201#1F00{}", hex_le(want));
            assert!(r.frames_since(start, "201#1F00").contains(&rpdo), "{rpdo}");
            let st = r.m.status();
            assert!(st.target_reached);
            assert!(
                (st.position_mm.unwrap() - target).abs() <= 1.0 / cpm,
                "{st:?}"
            );
            assert_eq!(st.commanded_mm, Some(want as f64 / cpm));
            // The plant sees the stage at the commanded increment.
            assert!((*r.plant.lock().unwrap() - want as f64 / cpm).abs() < 1e-9);
            // A 10 mm/s, 100 mm/s² profile: a move over x mm takes x/10 + 0.1 s (or less).
            let took = (r.t - t0).as_secs_f64();
            assert!(took < 1.5 + 0.1 * 10.0, "{took}");
        }
    }

    fn hex_le(v: i32) -> String {
        v.to_le_bytes().iter().map(|b| format!("{b:02X}")).collect()
    }

    #[test]
    fn relative_jog_and_limits() {
        let mut r = Rig::default();
        r.ready();
        r.ok(Command::MoveTo { target_mm: 3.0 });
        let start = r.log.len();
        r.ok(Command::Jog { delta_mm: -1.0 });
        // Bit 6 (relative) with bit 4: 0x5F; the target is the increment.
        let cpm = r.m.settings().counts_per_mm();
        let delta = ((2.0 * cpm).round() - (3.0 * cpm).round()) as i32;
        assert!(
            r.frames_since(start, "201#5F00")
                .contains(&format!("201#5F00{}", hex_le(delta)))
        );
        assert!((r.m.status().position_mm.unwrap() - 2.0).abs() < 1e-4);
        let e = r
            .run(Command::MoveTo { target_mm: 30.0 }, Duration::from_secs(1))
            .unwrap_err();
        assert!(matches!(e, DriveError::OutOfLimits { .. }));
        assert_eq!(
            e.to_string(),
            "target 30 mm is outside the travel limits -25..25 mm"
        );
        let e = r
            .run(Command::Jog { delta_mm: -30.0 }, Duration::from_secs(1))
            .unwrap_err();
        assert!(
            matches!(e, DriveError::OutOfLimits { target_mm, .. } if (target_mm + 28.0).abs() < 1e-4)
        );
    }

    /// A tracker's set-point with "change set immediately" replaces a running move.
    #[test]
    fn change_set_immediately() {
        let mut r = Rig::default();
        r.ready();
        let id = r.m.submit(Command::MoveTo { target_mm: 10.0 }, r.t);
        r.advance(Duration::from_millis(300));
        assert!(r.completion(id).is_none());
        let start = r.log.len();
        r.ok(Command::SetTarget { target_mm: 1.0 });
        assert!(r.controlwords(start).contains(&0x003F));
        // The waiting move completes when the drive reaches the new target.
        r.advance(Duration::from_secs(3));
        assert!(r.completion(id).unwrap().is_ok());
        assert!((r.m.status().position_mm.unwrap() - 1.0).abs() < 1e-4);
    }

    #[test]
    fn halt_and_quick_stop_preempt() {
        let mut r = Rig::default();
        r.ready();
        let id = r.m.submit(Command::MoveTo { target_mm: 20.0 }, r.t);
        r.advance(Duration::from_millis(500));
        r.ok(Command::Stop);
        assert_eq!(
            r.completion(id),
            Some(Err(DriveError::Interrupted { by: "stop" }))
        );
        let p = r.m.status().position_mm.unwrap();
        assert!(p > 2.0 && p < 10.0, "{p}");
        assert!(r.m.status().controlword & CW_HALT != 0);
        // The next move clears halt.
        r.ok(Command::MoveTo { target_mm: 1.0 });
        assert_eq!(r.m.status().controlword & CW_HALT, 0);
        let id = r.m.submit(Command::MoveTo { target_mm: 20.0 }, r.t);
        let queued = r.m.submit(Command::MoveTo { target_mm: 0.0 }, r.t);
        r.advance(Duration::from_millis(500));
        let start = r.log.len();
        r.ok(Command::QuickStop);
        assert!(r.controlwords(start).contains(&0x0002));
        assert_eq!(
            r.completion(id),
            Some(Err(DriveError::Interrupted { by: "quick stop" }))
        );
        assert_eq!(
            r.completion(queued),
            Some(Err(DriveError::Interrupted { by: "quick stop" }))
        );
        assert_eq!(r.m.status().state, Some(PowerState::SwitchOnDisabled));
        r.ok(Command::Enable);
        assert_eq!(r.m.status().state, Some(PowerState::OperationEnabled));
    }

    #[test]
    fn drive_fault_by_emcy_then_fault_reset() {
        let mut r = Rig::default();
        r.ready();
        let id = r.m.submit(Command::MoveTo { target_mm: 15.0 }, r.t);
        r.advance(Duration::from_millis(300));
        r.d.inject_fault(0x8611, [0xDE, 0xAD, 0, 0, 1], r.t);
        r.advance(Duration::from_millis(500));
        let emcy = r
            .events
            .iter()
            .find_map(|(_, e)| match e {
                Event::Emcy(e) => Some(*e),
                _ => None,
            })
            .unwrap();
        assert_eq!(emcy.code, 0x8611);
        assert_eq!(emcy.text(), "following error");
        assert_eq!(emcy.register, 0x21);
        assert_eq!(emcy.manufacturer, [0xDE, 0xAD, 0, 0, 1]);
        let err = r.completion(id).unwrap().unwrap_err();
        assert_eq!(err, DriveError::Fault { emcy: Some(emcy) });
        assert!(err.to_string().contains("following error"), "{err}");
        let st = r.m.status();
        assert_eq!(st.state, Some(PowerState::Fault));
        assert!(st.emcy_active);
        // Fault reaction active came first.
        assert!(r.events.iter().any(|(_, e)| matches!(
            e,
            Event::PowerState {
                to: PowerState::FaultReactionActive,
                ..
            }
        )));
        // Enabling is refused while in fault.
        assert!(matches!(
            r.run(Command::Enable, Duration::from_secs(2)),
            Err(DriveError::Fault { .. })
        ));
        let start = r.log.len();
        r.ok(Command::FaultReset);
        // Bit 7 rises from 0 (a disable-voltage controlword), then drops again.
        assert_eq!(r.controlwords(start), vec![0x0000, 0x0080, 0x0000]);
        assert_eq!(r.m.status().state, Some(PowerState::SwitchOnDisabled));
        assert!(!r.m.status().emcy_active);
        assert!(
            r.events
                .iter()
                .any(|(_, e)| matches!(e, Event::Emcy(e) if e.is_reset()))
        );
        r.ok(Command::Enable);
        r.ok(Command::MoveTo { target_mm: 4.0 });
        assert!((r.m.status().position_mm.unwrap() - 4.0).abs() < 1e-4);
    }

    #[test]
    fn heartbeat_loss_is_detected_within_the_consumer_time() {
        let mut r = Rig::default();
        r.ok(Command::Configure);
        r.ok(Command::Start);
        r.advance(Duration::from_millis(250));
        let last_hb = |r: &Rig| r.m.hb.last_heard().unwrap();
        r.d.set_heartbeat(false, r.t);
        let stopped = r.t;
        let heard = last_hb(&r);
        r.advance(Duration::from_secs(1));
        let (at, _) = r
            .events
            .iter()
            .find(|(_, e)| *e == Event::HeartbeatLost)
            .unwrap();
        // Declared lost exactly one consumer time after the last heartbeat.
        assert_eq!(r.t0 + *at, heard + Duration::from_millis(350));
        assert!(r.t0 + *at <= stopped + Duration::from_millis(350));
        assert!(!r.m.status().heartbeat_ok);
        r.d.set_heartbeat(true, r.t);
        r.advance(Duration::from_millis(200));
        assert!(r.events.iter().any(|(_, e)| *e == Event::HeartbeatResumed));
        assert!(r.m.status().heartbeat_ok);
    }

    #[test]
    fn drive_abort_is_a_typed_error_naming_object_and_text() {
        let mut r = Rig::default();
        r.d.refuse_sdo(Some(SdoRefusal {
            index: Some(0x6081),
            code: AbortCode::VALUE_TOO_HIGH,
        }));
        let e = r
            .run(Command::Configure, Duration::from_secs(10))
            .unwrap_err();
        assert_eq!(
            e,
            DriveError::Sdo(SdoError::Aborted {
                dir: super::super::sdo::Direction::Download,
                obj: ObjAddr::new(0x6081, 0),
                code: AbortCode::VALUE_TOO_HIGH,
            })
        );
        assert_eq!(
            e.to_string(),
            "SDO write of 0x6081:00: the drive aborted with 0x06090031 (value of parameter written too high (download only))"
        );
        assert!(!r.m.status().configured);
    }

    #[test]
    fn slow_drive_times_out_and_gets_an_abort() {
        let mut r = Rig::default();
        r.d.set_sdo_delay(Duration::from_secs(2));
        let start = r.log.len();
        let e = r
            .run(
                Command::SdoRead(ObjAddr::new(0x6041, 0)),
                Duration::from_secs(5),
            )
            .unwrap_err();
        assert!(
            matches!(e, DriveError::Sdo(SdoError::Timeout { .. })),
            "{e}"
        );
        assert_eq!(
            r.frames_since(start, "601#"),
            vec!["601#4041600000000000", "601#8041600000000405"]
        );
        // The late answer arrives and is dropped; the next transfer works.
        r.d.set_sdo_delay(Duration::ZERO);
        r.advance(Duration::from_secs(3));
        let Ok(Reply::Data(d)) = r.run(
            Command::SdoRead(ObjAddr::new(0x1000, 0)),
            Duration::from_secs(1),
        ) else {
            panic!()
        };
        assert_eq!(d, 0x0002_0192u32.to_le_bytes());
    }

    #[test]
    fn long_objects_over_sdo() {
        let mut r = Rig::default();
        let Ok(Reply::Data(name)) = r.run(
            Command::SdoRead(ObjAddr::new(0x1008, 0)),
            Duration::from_secs(1),
        ) else {
            panic!()
        };
        assert_eq!(name, crate::sim::drive::DEVICE_NAME.as_bytes());
        assert!(name.len() > 32);
        let data: Vec<u8> = (0..200u32).map(|i| (i * 7 % 251) as u8).collect();
        r.ok(Command::SdoWrite(ObjAddr::new(0x2000, 0), data.clone()));
        let Ok(Reply::Data(back)) = r.run(
            Command::SdoRead(ObjAddr::new(0x2000, 0)),
            Duration::from_secs(1),
        ) else {
            panic!()
        };
        assert_eq!(back, data);
    }

    #[test]
    fn commands_need_the_right_state() {
        let mut r = Rig::default();
        assert_eq!(
            r.run(Command::Enable, Duration::from_secs(1)),
            Err(DriveError::NotOperational { what: "enable" })
        );
        assert_eq!(
            r.run(Command::Start, Duration::from_secs(1)),
            Err(DriveError::NotConfigured { what: "start" })
        );
        r.ok(Command::Configure);
        r.ok(Command::Start);
        assert!(matches!(
            r.run(Command::Home, Duration::from_secs(1)),
            Err(DriveError::NotEnabled { what: "home", .. })
        ));
    }

    #[test]
    fn unexpected_reboot_forgets_the_configuration() {
        let mut r = Rig::default();
        r.ready();
        // Someone else resets the node.
        r.d.handle_frame(&CanFrame::new(0, &[0x81, 0x01]).unwrap(), r.t);
        r.advance(Duration::from_millis(50));
        assert!(
            r.events
                .iter()
                .any(|(_, e)| *e == Event::BootUp { expected: false })
        );
        let st = r.m.status();
        assert!(!st.configured && !st.homed && !st.sync_running);
        assert_eq!(st.controlword, 0);
        assert!(matches!(
            r.run(Command::MoveTo { target_mm: 1.0 }, Duration::from_secs(1)),
            Err(DriveError::NotOperational { .. })
        ));
        // Configure again and carry on.
        r.ready();
        r.ok(Command::MoveTo { target_mm: 1.0 });
    }

    /// A boot-up in the middle of configure (here a drive that restarts while its PDOs are
    /// being written): the master settles, then configures the fresh drive from the start.
    #[test]
    fn configure_starts_over_after_a_boot_up() {
        let mut r = Rig::default();
        let start = r.log.len();
        let id = r.m.submit(Command::Configure, r.t);
        // Run until the RPDO mapping is being written, then reboot the drive.
        while !r.log[start..]
            .iter()
            .any(|l| l.starts_with("601#2300160110004060"))
        {
            r.advance(Duration::from_millis(1));
        }
        r.d.handle_frame(&CanFrame::new(0, &[0x82, 0x01]).unwrap(), r.t);
        r.advance(Duration::from_secs(2));
        assert!(
            matches!(r.completion(id), Some(Ok(_))),
            "{:?}",
            r.completion(id)
        );
        assert!(
            r.events
                .iter()
                .any(|(_, e)| *e == Event::BootUp { expected: false })
        );
        // The device type was read twice: configure ran again from the top.
        assert_eq!(r.frames_since(start, "601#4000100000000000").len(), 2);
        let s = r.d.status();
        assert_eq!(s.rpdo1_map, RPDO1_MAP.to_vec());
        assert!(s.rpdo1_valid && s.tpdo1_valid && r.m.status().configured);
    }

    #[test]
    fn nmt_commands_are_confirmed_by_heartbeat() {
        let mut r = Rig::default();
        r.ok(Command::Configure);
        r.ok(Command::Start);
        r.ok(Command::Nmt(NmtCommand::StopRemoteNode));
        assert_eq!(r.m.status().nmt, Some(NmtState::Stopped));
        assert!(!r.m.status().sync_running);
        r.ok(Command::Nmt(NmtCommand::EnterPreOperational));
        assert_eq!(r.m.status().nmt, Some(NmtState::PreOperational));
        r.ok(Command::Nmt(NmtCommand::ResetNode));
        assert!(!r.m.status().configured);
    }

    // --- cyclic synchronous position --------------------------------------------------------

    /// A config for following: 60 mm/s, 600 mm/s² (6 mm/s and 0.06 mm per SYNC² at 10 ms).
    fn csp_config() -> DriveConfig {
        DriveConfig {
            profile: crate::canopen::ProfileConfig {
                velocity_mm_s: 60.0,
                accel_mm_s2: 600.0,
                decel_mm_s2: 600.0,
                ..Default::default()
            },
            ..Default::default()
        }
    }

    /// At rest in profile position SYNC slows to the quiet period after `QUIET_AFTER`; a
    /// command brings the full rate back before its first step needs it, and so does a
    /// change the drive reports (here a fault).
    #[test]
    fn sync_slows_at_rest_and_any_command_or_drive_change_speeds_it_up() {
        let mut r = Rig::default();
        r.ready();
        let syncs_in = |r: &mut Rig, d: Duration| {
            let c0 = r.m.sync.count();
            r.advance(d);
            r.m.sync.count() - c0
        };
        // Homing just ended: the full rate for QUIET_AFTER, then 100 ms.
        assert!(!r.m.status().sync_quiet);
        assert_eq!(syncs_in(&mut r, Duration::from_millis(500)), 50);
        r.advance(QUIET_AFTER);
        assert!(r.m.status().sync_quiet);
        assert_eq!(syncs_in(&mut r, Duration::from_secs(1)), 10);
        let tpdos = r.m.status().tpdo_count;
        r.advance(Duration::from_millis(300));
        assert_eq!(r.m.status().tpdo_count - tpdos, 3, "the status still comes");
        // A jog: its first SYNC within one full period; 100 SYNC/s while it runs.
        let t = r.t;
        let id = r.m.submit(Command::Jog { delta_mm: 2.0 }, r.t);
        assert!(!r.m.status().sync_quiet);
        assert!(r.m.sync.poll_timeout().unwrap() <= t + Duration::from_millis(10));
        let c0 = r.m.sync.count();
        while r.completion(id).is_none() {
            r.advance(Duration::from_millis(5));
        }
        assert!(matches!(r.completion(id), Some(Ok(_))));
        let rate = (r.m.sync.count() - c0) as f64 / (r.t - t).as_secs_f64();
        assert!((rate - 100.0).abs() < 10.0, "{rate} SYNC/s during the jog");
        r.advance(QUIET_AFTER + Duration::from_millis(200));
        assert!(r.m.status().sync_quiet);
        // A fault: the EMCY ends the quiet, and its statusword comes at the full rate.
        r.d.inject_fault(0x7500, [0; 5], r.t);
        r.advance(Duration::from_millis(2));
        assert!(!r.m.status().sync_quiet);
        r.advance(Duration::from_millis(20));
        assert!(r.m.status().state.is_some_and(|s| s.is_fault()));
    }

    /// Following that starts after a quiet spell runs as it does from the full rate: the
    /// ramp's first step is one SYNC period, not the 100 ms since the last quiet SYNC (which
    /// the twin, like a drive, answered with a following error).
    #[test]
    fn following_after_a_quiet_spell_has_no_following_error() {
        let mut r = Rig::new(
            DriveConfig {
                quiet_sync_period: Duration::from_millis(100),
                ..csp_config()
            },
            TwinDriveConfig {
                start_mm: 2.0,
                ..Default::default()
            },
        );
        r.ready();
        r.advance(QUIET_AFTER * 2);
        assert!(r.m.status().sync_quiet);
        let t0 = r.t;
        while r.t - t0 < Duration::from_millis(800) {
            let target = 2.0 + 20.0 * (r.t - t0).as_secs_f64();
            r.m.follow_moving(target, Some(20.0), r.t, r.t)
                .unwrap_or_else(|e| panic!("{e}: {:?}", following_events(&r)));
            r.advance(Duration::from_millis(2));
        }
        assert_eq!(following_events(&r), vec![Event::FollowingStarted]);
    }

    fn csp_rig() -> Rig {
        let mut r = Rig::new(
            csp_config(),
            TwinDriveConfig {
                start_mm: 2.0,
                ..Default::default()
            },
        );
        r.ready();
        r
    }

    /// The target positions (0x607A) of the RPDO1 frames since `start`, with their
    /// controlwords.
    fn rpdos(r: &Rig, start: usize) -> Vec<(u16, i32)> {
        r.frames_since(start, "201#")
            .iter()
            .map(|l| {
                let b: Vec<u8> = (4..l.len())
                    .step_by(2)
                    .map(|i| u8::from_str_radix(&l[i..i + 2], 16).unwrap())
                    .collect();
                (
                    u16::from_le_bytes([b[0], b[1]]),
                    i32::from_le_bytes([b[2], b[3], b[4], b[5]]),
                )
            })
            .collect()
    }

    fn following_events(r: &Rig) -> Vec<Event> {
        r.events
            .iter()
            .filter(|(_, e)| matches!(e, Event::FollowingStarted | Event::FollowingEnded(_)))
            .map(|(_, e)| e.clone())
            .collect()
    }

    /// The whole CSP sequence on the wire: the demand held at the actual position, 0x6060 = 8
    /// by SDO, 0x6061 read back until it shows 8, then at every SYNC an RPDO1 with
    /// controlword 0x000F and the ramped demand (closed form a·T²·k(k+1)/2 while
    /// accelerating), no handshake; at rest the master's "target reached"; a move switches
    /// back to profile position (0x6060 = 1) and runs its set-point handshake.
    #[test]
    fn csp_sequence_on_the_wire() {
        let mut r = csp_rig();
        let cpm = r.m.settings().counts_per_mm();
        assert_eq!(r.m.status().position_counts, Some(0));
        let start = r.log.len();
        r.m.follow(5.0, r.t, r.t).unwrap();
        // Mode switch: write 0x6060 = 8 (0x2F: expedited, 1 byte), read 0x6061, the drive
        // answers 8 (0x4F: expedited upload of 1 byte).
        let write = "601#2F60600008000000";
        let read = "601#4061600000000000";
        let shows8 = "581#4F61600008000000";
        while !r.log[start..].iter().any(|l| l == shows8) {
            r.advance(Duration::from_millis(1));
        }
        let at = |l: &str| r.log[start..].iter().position(|x| x == l).unwrap() + start;
        assert!(at(write) < at(read) && at(read) < at(shows8));
        // Up to the confirmation every RPDO holds the actual position (0) with no set-point
        // bits: 0x000F.
        let held = rpdos(&r, start);
        assert!(
            held.iter().all(|&(cw, t)| cw == 0x000F && t == 0),
            "{held:?}"
        );
        let from = at(shows8);
        r.advance(Duration::from_millis(60));
        let demands = rpdos(&r, from);
        assert!(demands.len() >= 5);
        let step = 600.0 * 0.01 * 0.01;
        for (k, &(cw, t)) in demands.iter().take(5).enumerate() {
            let k = (k + 1) as f64;
            let mm = step * k * (k + 1.0) / 2.0;
            assert_eq!(cw, 0x000F);
            assert_eq!(t, (mm * cpm).round() as i32, "SYNC {k}");
        }
        // The RPDO bytes themselves: COB-ID 0x201, controlword 0F 00, 0x607A LE.
        let first = r.frames_since(from, "201#")[0].clone();
        assert_eq!(
            first,
            format!("201#0F00{}", hex_le((step * cpm).round() as i32))
        );
        // Each RPDO still goes out right before its SYNC.
        let i = r.log.iter().rposition(|l| l.starts_with("201#")).unwrap();
        assert_eq!(r.log[i + 1], "080#");
        assert!(r.m.status().following && !r.m.status().target_reached);
        r.advance(Duration::from_secs(1));
        let st = r.m.status();
        assert_eq!(st.mode, Some(MODE_CSP));
        assert!(
            st.following && st.target_reached && !st.following_error,
            "{st:?}"
        );
        assert!((st.position_mm.unwrap() - 5.0).abs() < 1.0 / cpm, "{st:?}");
        // The drive's TPDO: operation enabled 0x0237 + bit 12 "target position used", bit 10
        // reserved (0) in CSP.
        let tpdo = r.log.iter().rev().find(|l| l.starts_with("181#")).unwrap();
        assert!(tpdo.starts_with("181#3712"), "{tpdo}");
        assert_eq!(r.d.status().mode, MODE_CSP);
        // A move leaves CSP: 0x6060 = 1, confirmed, then the set-point handshake.
        let start = r.log.len();
        r.ok(Command::MoveTo { target_mm: 2.0 });
        let sdo = r.frames_since(start, "601#");
        assert!(sdo.contains(&"601#2F60600001000000".to_string()), "{sdo:?}");
        assert!(r.log[start..].contains(&"581#4F61600001000000".to_string()));
        assert!(r.controlwords(start).ends_with(&[0x001F, 0x000F]));
        let st = r.m.status();
        assert_eq!(st.mode, Some(MODE_PROFILE_POSITION));
        assert!(!st.following && st.target_reached);
        assert!((st.position_mm.unwrap() - 2.0).abs() < 1.0 / cpm);
        assert_eq!(
            following_events(&r),
            vec![Event::FollowingStarted, Event::FollowingEnded(Ok(()))]
        );
    }

    /// Demands stay within the profile velocity and acceleration whatever the target does;
    /// a moving target is followed closely; `StopFollowing` rests on the last target and
    /// returns to profile position.
    #[test]
    fn csp_ramp_limits_and_tracking() {
        let mut r = csp_rig();
        let cpm = r.m.settings().counts_per_mm();
        let start = r.log.len();
        // A target at 40 mm/s for 0.5 s, updated every 2 ms, then a jump back to -20 mm.
        let t0 = r.t;
        let mut worst: f64 = 0.0;
        while r.t - t0 < Duration::from_millis(500) {
            let target = 40.0 * (r.t - t0).as_secs_f64();
            r.m.follow(target, r.t, r.t)
                .unwrap_or_else(|e| panic!("{e}: {:?}", following_events(&r)));
            r.advance(Duration::from_millis(2));
            if r.t - t0 > Duration::from_millis(250) {
                // Caught up: the stage within half a millimetre of the moving target.
                worst = worst.max((*r.plant.lock().unwrap() - target).abs());
            }
        }
        assert!(worst < 0.5, "{worst} mm behind");
        r.m.follow(-20.0, r.t, r.t).unwrap();
        r.advance(Duration::from_secs(2));
        let d: Vec<f64> = rpdos(&r, start)
            .iter()
            .map(|&(_, t)| t as f64 / cpm)
            .collect();
        let v: Vec<f64> = d.windows(2).map(|w| (w[1] - w[0]) / 0.01).collect();
        let q = 1.0 / cpm / 0.01; // one increment per SYNC, in mm/s
        assert!(v.iter().all(|x| x.abs() <= 60.0 + 2.0 * q), "{v:?}");
        assert!(
            v.windows(2)
                .all(|w| ((w[1] - w[0]) / 0.01).abs() <= 600.0 + 4.0 * q / 0.01),
            "acceleration"
        );
        assert!(v.iter().any(|x| x.abs() > 59.0), "cruised at the limit");
        let st = r.m.status();
        assert!(st.following && st.target_reached && !st.following_error);
        assert_eq!(st.position_counts, Some((-20.0 * cpm).round() as i32));
        // Stop following: back to profile position, at rest on the last target.
        r.ok(Command::StopFollowing);
        let st = r.m.status();
        assert!(
            !st.following && st.mode == Some(MODE_PROFILE_POSITION),
            "{st:?}"
        );
        assert_eq!(st.commanded_mm, Some((-20.0 * cpm).round() / cpm));
        assert_eq!(r.d.status().mode, MODE_PROFILE_POSITION);
        // A second stop is a no-op; a relative jog works from the last demand.
        r.ok(Command::StopFollowing);
        r.ok(Command::Jog { delta_mm: 1.0 });
        assert!((r.m.status().position_mm.unwrap() + 19.0).abs() < 1e-4);
    }

    /// Stop following while the target still moves: the demand is brought to rest on the
    /// last target (overshooting within the limits), then profile position.
    #[test]
    fn stop_following_while_moving() {
        let mut r = csp_rig();
        let t0 = r.t;
        let mut last = 0.0;
        while r.t - t0 < Duration::from_millis(300) {
            last = 30.0 * (r.t - t0).as_secs_f64();
            r.m.follow(last, r.t, r.t).unwrap();
            r.advance(Duration::from_millis(2));
        }
        r.ok(Command::StopFollowing);
        let cpm = r.m.settings().counts_per_mm();
        let st = r.m.status();
        assert_eq!(st.position_counts, Some((last * cpm).round() as i32));
        assert_eq!(st.mode, Some(MODE_PROFILE_POSITION));
    }

    /// The drive cannot keep up (its own maximum acceleration 0x60C5 lowered below the
    /// profile's): it reports bit 13, the master surfaces it, ends following and refuses follow
    /// targets until the next command.
    #[test]
    fn csp_following_error_ends_following() {
        let mut r = csp_rig();
        // 0x60C5 = 20 mm/s² on the drive (524 288 increments/s²).
        r.ok(Command::SdoWrite(
            ObjAddr::new(0x60C5, 0),
            524_288u32.to_le_bytes().to_vec(),
        ));
        r.m.follow(10.0, r.t, r.t).unwrap();
        let t0 = r.t;
        while !r.m.status().following && r.t - t0 < Duration::from_secs(1) {
            r.advance(Duration::from_millis(1));
        }
        while r.m.status().following && r.t - t0 < Duration::from_secs(2) {
            r.advance(Duration::from_millis(1));
        }
        // Surfaced in the status with the TPDO that ended following.
        let st = r.m.status();
        assert!(st.following_error && !st.following, "{st:?}");
        assert_eq!(st.statusword.map(|w| w & 0x3400), Some(0x3000));
        assert!(
            r.log.iter().any(|l| l.starts_with("181#37")
                && u16::from_str_radix(&l[6..8], 16).unwrap() & 0x20 != 0),
            "a TPDO with bit 13"
        );
        assert_eq!(
            following_events(&r),
            vec![
                Event::FollowingStarted,
                Event::FollowingEnded(Err(DriveError::FollowingError))
            ]
        );
        assert_eq!(r.m.follow(3.0, r.t, r.t), Err(DriveError::FollowDisarmed));
        // Limit back to 20 000 mm/s²; after another command following works again.
        r.ok(Command::SdoWrite(
            ObjAddr::new(0x60C5, 0),
            524_288_000u32.to_le_bytes().to_vec(),
        ));
        r.advance(Duration::from_secs(2));
        r.m.follow(3.0, r.t, r.t).unwrap();
        r.advance(Duration::from_secs(1));
        let st = r.m.status();
        assert!(
            st.following && st.target_reached && !st.following_error,
            "{st:?}"
        );
        assert!((st.position_mm.unwrap() - 3.0).abs() < 1e-4);
    }

    /// Quick stop while following ends it (interrupted) and refuses follow targets until the
    /// next command; re-enabled in mode 8 the drive holds where it stopped (the master keeps
    /// the demand on the actual position while the drive is not enabled), and following
    /// resumes. A drive fault ends following with the fault.
    #[test]
    fn csp_quick_stop_and_fault_end_following() {
        let mut r = csp_rig();
        r.m.follow(20.0, r.t, r.t).unwrap();
        r.advance(Duration::from_millis(200));
        assert!(r.m.status().following);
        r.ok(Command::QuickStop);
        assert_eq!(r.m.status().state, Some(PowerState::SwitchOnDisabled));
        assert_eq!(
            following_events(&r).last(),
            Some(&Event::FollowingEnded(Err(DriveError::Interrupted {
                by: "quick stop"
            })))
        );
        assert_eq!(r.m.follow(1.0, r.t, r.t), Err(DriveError::FollowDisarmed));
        let stopped = r.m.status().position_counts.unwrap();
        let start = r.log.len();
        r.ok(Command::Enable);
        r.advance(Duration::from_millis(100));
        // Every RPDO since carried the stopped position: enabling asked for no motion.
        assert!(rpdos(&r, start).iter().all(|&(_, t)| t == stopped));
        assert_eq!(r.m.status().position_counts, Some(stopped));
        assert_eq!(r.m.status().mode, Some(MODE_CSP));
        // Following again: no mode switch needed (already 8).
        let start = r.log.len();
        r.m.follow(1.0, r.t, r.t).unwrap();
        r.advance(Duration::from_secs(2));
        assert!(
            !r.frames_since(start, "601#")
                .iter()
                .any(|l| l.starts_with("601#2F6060"))
        );
        let st = r.m.status();
        assert!(st.following && st.target_reached);
        assert!((st.position_mm.unwrap() - 1.0).abs() < 1e-4);
        // A fault while following.
        r.m.follow(15.0, r.t, r.t).unwrap();
        r.advance(Duration::from_millis(100));
        r.d.inject_fault(0x7500, [0; 5], r.t);
        r.advance(Duration::from_millis(200));
        assert!(matches!(
            following_events(&r).last(),
            Some(Event::FollowingEnded(Err(DriveError::Fault { emcy: Some(e) }))) if e.code == 0x7500
        ));
        assert!(!r.m.status().following);
        r.ok(Command::FaultReset);
        r.ok(Command::Enable);
        // Home from CSP: the mode goes to 6 and back to 1 for the move.
        r.ok(Command::Home);
        assert_eq!(r.m.status().mode, Some(MODE_HOMING));
        r.ok(Command::MoveTo { target_mm: 0.5 });
        assert!((r.m.status().position_mm.unwrap() - 0.5).abs() < 1e-4);
    }

    /// A drive that refuses mode 8 (as the python-canopen interop drive does): following ends
    /// before it starts with the drive's abort, follow targets are refused until the next
    /// command, and profile position goes on working.
    #[test]
    fn drive_refusing_csp() {
        let mut r = csp_rig();
        r.d.refuse_sdo(Some(SdoRefusal {
            index: Some(0x6060),
            code: AbortCode::INVALID_VALUE,
        }));
        r.m.follow(3.0, r.t, r.t).unwrap();
        r.advance(Duration::from_millis(200));
        let want = DriveError::Sdo(SdoError::Aborted {
            dir: super::super::sdo::Direction::Download,
            obj: ObjAddr::new(0x6060, 0),
            code: AbortCode::INVALID_VALUE,
        });
        assert_eq!(following_events(&r), vec![Event::FollowingEnded(Err(want))]);
        assert!(!r.m.status().following);
        assert_eq!(r.m.follow(3.0, r.t, r.t), Err(DriveError::FollowDisarmed));
        r.d.refuse_sdo(None);
        r.ok(Command::MoveTo { target_mm: 3.0 });
        assert_eq!(r.m.status().mode, Some(MODE_PROFILE_POSITION));
        assert!((r.m.status().position_mm.unwrap() - 3.0).abs() < 1e-4);
        // Out of the travel limits: refused at once.
        assert!(matches!(
            r.m.follow(30.0, r.t, r.t),
            Err(DriveError::OutOfLimits { .. })
        ));
    }
}
