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
//!
//! The machine is one [`Master`] whose parts are `impl Master` blocks in their own files,
//! each over the state and the step vocabulary defined here (quinn-proto's `connection/`
//! shape); this file is its face: the public types, the state, the inputs and outputs.
//! - `plan`: a command as its program of steps, with the time bounds of its waits and the
//!   parameters configure writes;
//! - `steps`: the command engine: running a program step by step, starting and polling
//!   each step, and a command's end;
//! - `cyclic`: the cyclic exchange: the RPDO1 image the master sends, TPDO1 into the
//!   [`DriveStatus`], the SYNC's pace;
//! - `following`: following in cyclic synchronous position (the demand ramp at each SYNC,
//!   entering and leaving it, following's start and end);
//! - `heartbeat`: the heartbeat consumer's events (boot-up, loss, NMT state) and what a
//!   lost or rebooted drive makes the master forget.

mod cyclic;
mod following;
mod heartbeat;
mod plan;
mod steps;
#[cfg(test)]
mod tests;

use super::cia402::{HomingStatus, PowerState};
use super::cob;
use super::config::{ConfigError, DriveConfig, DriveSettings};
use super::csp::{DemandRamp, TargetTrack};
use super::emcy::Emcy;
use super::nmt::HeartbeatConsumer;
use super::pdo::{self, SdoWrite, SyncProducer};
use super::sdo::{ObjAddr, SdoClient, SdoError, SdoOutcome};
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
    #[error("{what}: nothing within {:.1} s", .after.as_secs_f64())]
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
    #[error("the drive reports {0}")]
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
    /// The command in progress, and since when (a homing takes seconds to a minute: a
    /// console says how long it has been going).
    pub busy: Option<&'static str>,
    pub busy_since: Option<Instant>,
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
            busy_since: None,
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

    fn collect_sdo(&mut self) {
        while let Some(f) = self.sdo.poll_transmit() {
            self.tx.push_back(f);
        }
        if let Some(r) = self.sdo.poll_outcome() {
            self.sdo_result = Some(r);
        }
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
}
