//! The twin's follower drive (DESIGN §9): a CiA 402 servo node on a CAN transport, the slave
//! counterpart of `crate::canopen`.
//!
//! Sans-I/O like the master (`handle_frame`, `handle_timeout`, `poll_transmit`,
//! `poll_timeout`), with a thin task ([`spawn_twin_drive`]) and a handle for fault injection.
//! It provides:
//! - NMT slave: boot-up message, start/stop/pre-operational, reset node and reset
//!   communication (communication objects back to their defaults, then boot-up again), and a
//!   heartbeat producer at 0x1017;
//! - an SDO server of its own (expedited and segmented, any length; canopen-rs's server stops
//!   at 32 bytes and its object dictionary cannot veto writes, which the PDO mapping rules
//!   need) over a small object dictionary with the CiA 301/402 objects the master uses,
//!   including the PDO parameters 0x1400/0x1600/0x1800/0x1A00, which it honours: the RPDO
//!   and TPDO carry exactly the mapped objects, and the mapping may only change while the PDO
//!   is disabled (COB-ID bit 31) and its count is 0;
//! - RPDO applied and TPDO sent on SYNC (synchronous transmission types), or at once
//!   (types 254/255);
//! - the CiA 402 state machine, profile position (set-point handshake, change immediately,
//!   relative targets, halt, software limits 0x607D) and homing (moves to the home switch at
//!   the 0x6099 speeds and sets the position there to the home offset; methods 35 and 37 home
//!   on the current position);
//! - cyclic synchronous position (mode 8): each RPDO applied (at SYNC for the synchronous
//!   types) takes 0x607A as the new position demand, clamped to 0x607D, with no handshake.
//!   The internal demand (0x6062) moves linearly from where it was to the new demand over one
//!   cycle (the usual one-cycle delay of a CSP drive; the cycle is the drive's running average
//!   of the intervals between demands, as a drive locks onto the SYNC); a late demand finds it
//!   going on at the same velocity for up to one more cycle, then holding. The
//!   stage servoes onto it with velocity feed-forward within the drive's own limits, not the
//!   profile ones (which the master's demand ramp keeps to, so these must be well above
//!   them: the stage has to catch up with a demand one cycle ahead): 0x607F max profile
//!   velocity (default 1000 mm/s) and 0x60C5 max acceleration (default 20 000 mm/s², also
//!   used for braking). On entering mode 8, on enabling in mode 8 and on releasing halt the demand is
//!   where the stage is. Statusword in mode 8: bit 10 reserved (always 0; the master works
//!   out "target reached" itself), bit 12 = 1 while the drive uses the target position
//!   (operation enabled, no halt) per CiA 402, bit 13 = following error while |internal
//!   demand − actual| exceeds 0x6065. Halt (bit 8) brakes with 0x6084 and ignores the target
//!   position until released;
//! - a trapezoidal motion profile in real time: every update reports the stage position to
//!   `on_position` (the plant's follower encoder). Its encoder is exact: the plant applies the
//!   follower's own errors.
//! - fault injection: a fault with its EMCY (e.g. 0x8611 following error), heartbeat off/on,
//!   refused SDO requests (abort), slow SDO replies.
//!
//! Positions: the stage's physical frame has the home switch at 0; `on_position` receives the
//! physical position, which is what the encoder reads after homing with a zero offset. Before
//! homing the encoder reads 0 at power-on.
//!
//! The node is one [`TwinDrive`] whose parts are `impl TwinDrive` blocks in their own files
//! over the state defined here; this file is its face: the configuration, the status, the
//! state, the machine interface and the unit conversions.
//! - `od`: the object dictionary and its contents (communication and CiA 402 objects);
//! - `sdo`: the SDO server and the rules of writing objects (PDO mapping, modes);
//! - `nmt`: the NMT slave (boot-up, state commands, resets) and the heartbeat period;
//! - `pdo`: RPDO and TPDO, SYNC, EMCY;
//! - `cia402`: the power state machine, controlword and statusword, modes of operation and
//!   the set-point handshake;
//! - `motion`: the stage's motion over time: profile moves, homing, the cyclic synchronous
//!   position demand;
//! - `profile`: the kinematics themselves (trapezoidal mover, CSP interpolation), pure;
//! - `faults`: fault injection;
//! - `task`: the tokio task ([`spawn_twin_drive`]) and its [`TwinDriveHandle`].

mod cia402;
mod faults;
mod motion;
mod nmt;
mod od;
mod pdo;
mod profile;
mod sdo;
mod task;
#[cfg(test)]
mod tests;

pub use od::DEVICE_NAME;
pub use task::{TwinControl, TwinDriveHandle, spawn_twin_drive};

use self::od::{Od, build_od};
use self::profile::{Goal, Interp, Mover};
use crate::can::CanFrame;
use crate::canopen::cia402::{HomingStatus, PowerState};
use crate::canopen::config::Scaling;
use crate::canopen::pdo::MapEntry;
use crate::canopen::sdo::{AbortCode, ObjAddr};
use crate::canopen::{NmtState, NodeId, cob};
use crate::sim::SimError;
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// How the twin drive is built.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TwinDriveConfig {
    pub node_id: u8,
    /// The same scaling as the master's: increments per mm.
    pub scaling: Scaling,
    /// Physical position at power-on (mm; the home switch is at 0).
    pub start_mm: f64,
    /// Producer heartbeat time at power-on and after reset communication (0x1017 default;
    /// 0 = no heartbeat until the master writes one).
    pub default_heartbeat_ms: u16,
    /// Motion update period while moving.
    pub tick: Duration,
    /// Where the final approach to the home switch starts (mm before it).
    pub homing_approach_mm: f64,
}

impl Default for TwinDriveConfig {
    fn default() -> Self {
        TwinDriveConfig {
            node_id: 1,
            scaling: Scaling::default(),
            start_mm: 0.0,
            default_heartbeat_ms: 0,
            tick: Duration::from_millis(2),
            homing_approach_mm: 0.5,
        }
    }
}

/// Refuse SDO requests: to objects of `index` (or every object) with `code`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SdoRefusal {
    pub index: Option<u16>,
    pub code: AbortCode,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Homing {
    Idle,
    /// Fast search toward the switch, then the slow final approach.
    Search,
    Approach,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Transfer {
    Upload {
        obj: ObjAddr,
        pos: usize,
        toggle: bool,
    },
    Download {
        obj: ObjAddr,
        size: Option<usize>,
        toggle: bool,
    },
}

/// What the twin drive reports about itself.
#[derive(Clone, Debug, PartialEq)]
pub struct TwinStatus {
    pub nmt: NmtState,
    pub state: PowerState,
    pub statusword: u16,
    pub mode: i8,
    /// Encoder position (mm) as reported in 0x6064.
    pub position_mm: f64,
    /// Physical position (mm, home switch at 0).
    pub physical_mm: f64,
    pub moving: bool,
    /// Cyclic synchronous position: the latest position demand taken (encoder frame, mm)
    /// while the drive follows demands.
    pub demand_mm: Option<f64>,
    pub homed: bool,
    pub heartbeat_ms: u16,
    pub heartbeat_on: bool,
    pub fault_code: u16,
    pub rpdo1_map: Vec<MapEntry>,
    pub tpdo1_map: Vec<MapEntry>,
    pub rpdo1_valid: bool,
    pub tpdo1_valid: bool,
}

/// The twin's CiA 402 drive node.
pub struct TwinDrive {
    cfg: TwinDriveConfig,
    node: NodeId,
    cpm: f64,
    od: Od,
    nmt: NmtState,
    heartbeat_on: bool,
    next_heartbeat: Option<Instant>,
    transfer: Option<Transfer>,
    /// Bytes of the transfer in progress.
    buf: Vec<u8>,
    refusal: Option<SdoRefusal>,
    sdo_delay: Duration,
    delayed: VecDeque<(Instant, CanFrame)>,
    rpdo_latched: Option<Vec<u8>>,
    tpdo_syncs: u16,
    last_tpdo: Option<Vec<u8>>,
    fsa: PowerState,
    last_cw: u16,
    ack: bool,
    pending: Option<f64>,
    /// The last accepted set-point (encoder increments), base of relative moves.
    last_target: i32,
    halted: bool,
    internal_limit: bool,
    homing: Homing,
    homing_status: HomingStatus,
    homed: bool,
    following_error: bool,
    fault_code: u16,
    mover: Mover,
    /// Cyclic synchronous position: the internal demand while demands are followed (mode 8,
    /// operation enabled, no halt).
    csp: Option<Interp>,
    /// When the last demand came in mode 8.
    demand_at: Option<Instant>,
    /// The cycle: the running average of the intervals between demands (up to 1 s).
    cycle: Option<Duration>,
    /// |internal demand − actual| at the last update (mm).
    csp_error: f64,
    /// Physical position where the encoder reads 0.
    zero: f64,
    last_update: Instant,
    reported: Option<f64>,
    on_position: Box<dyn FnMut(f64) + Send>,
    tx: VecDeque<CanFrame>,
}

impl std::fmt::Debug for TwinDrive {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TwinDrive")
            .field("node", &self.node.raw())
            .field("nmt", &self.nmt)
            .field("fsa", &self.fsa)
            .field("mover", &self.mover)
            .finish_non_exhaustive()
    }
}

fn frame(id: u16, data: &[u8]) -> CanFrame {
    crate::canopen::frame(id, data)
}

impl TwinDrive {
    /// Power on at `now`: the boot-up message is the first frame out.
    pub fn new(
        cfg: TwinDriveConfig,
        on_position: Box<dyn FnMut(f64) + Send>,
        now: Instant,
    ) -> Result<Self, SimError> {
        let node = NodeId::new(cfg.node_id).map_err(|_| {
            SimError::Input(format!(
                "twin drive node id {} is not 1 to 127",
                cfg.node_id
            ))
        })?;
        let cpm = cfg.scaling.counts_per_mm();
        if !(cpm.is_finite() && cpm > 0.0) {
            return Err(SimError::Input(format!(
                "twin drive scaling gives {cpm} increments/mm: use positive feed and resolution"
            )));
        }
        if !cfg.start_mm.is_finite() || cfg.tick.is_zero() {
            return Err(SimError::Input(
                "twin drive start_mm must be finite and tick > 0".into(),
            ));
        }
        let mut d = TwinDrive {
            od: build_od(&cfg, cpm),
            cfg,
            node,
            cpm,
            nmt: NmtState::PreOperational,
            heartbeat_on: true,
            next_heartbeat: None,
            transfer: None,
            buf: Vec::new(),
            refusal: None,
            sdo_delay: Duration::ZERO,
            delayed: VecDeque::new(),
            rpdo_latched: None,
            tpdo_syncs: 0,
            last_tpdo: None,
            fsa: PowerState::SwitchOnDisabled,
            last_cw: 0,
            ack: false,
            pending: None,
            last_target: 0,
            halted: false,
            internal_limit: false,
            homing: Homing::Idle,
            homing_status: HomingStatus::Interrupted,
            homed: false,
            following_error: false,
            fault_code: 0,
            mover: Mover {
                pos: cfg.start_mm,
                vel: 0.0,
                goal: Goal::Idle,
            },
            csp: None,
            demand_at: None,
            cycle: None,
            csp_error: 0.0,
            zero: cfg.start_mm,
            last_update: now,
            reported: None,
            on_position,
            tx: VecDeque::new(),
        };
        d.report_position();
        d.boot(now);
        Ok(d)
    }

    // --- the machine interface ------------------------------------------------------------

    pub fn handle_frame(&mut self, f: &CanFrame, now: Instant) {
        if f.is_extended() || f.is_remote() {
            return;
        }
        let id = f.id() as u16;
        let node = self.id();
        if id == cob::NMT {
            self.on_nmt(f.data(), now);
        } else if id == cob::SYNC {
            self.on_sync(now);
        } else if id == cob::SDO_RX + node {
            self.on_sdo(f.data(), now);
        } else if self.nmt == NmtState::Operational && Some(id as u32) == self.rpdo_cob() {
            self.on_rpdo(f.data(), now);
        } else {
            return;
        }
        self.event_tpdo();
    }

    pub fn handle_timeout(&mut self, now: Instant) {
        self.update(now);
        while self.delayed.front().is_some_and(|(due, _)| *due <= now) {
            if let Some((_, f)) = self.delayed.pop_front() {
                self.tx.push_back(f);
            }
        }
        if let Some(due) = self.next_heartbeat
            && now >= due
        {
            self.tx
                .push_back(frame(cob::HEARTBEAT + self.id(), &[self.nmt as u8]));
            let period = Duration::from_millis(self.od.u16(0x1017, 0) as u64);
            let mut next = due + period;
            if next <= now {
                next = now + period;
            }
            self.next_heartbeat = Some(next);
        }
        self.event_tpdo();
    }

    pub fn poll_timeout(&self) -> Option<Instant> {
        let motion =
            (self.mover.moving() || self.csp_busy()).then(|| self.last_update + self.cfg.tick);
        [
            self.next_heartbeat,
            self.delayed.front().map(|(d, _)| *d),
            motion,
        ]
        .into_iter()
        .flatten()
        .min()
    }

    pub fn poll_transmit(&mut self) -> Option<CanFrame> {
        self.tx.pop_front()
    }

    pub fn status(&self) -> TwinStatus {
        TwinStatus {
            nmt: self.nmt,
            state: self.fsa,
            statusword: self.statusword(),
            mode: self.mode(),
            position_mm: self.to_mm(self.encoder_counts()),
            physical_mm: self.mover.pos,
            moving: self.mover.moving() || self.csp_busy(),
            demand_mm: self.csp.map(|ip| ip.to - self.zero),
            homed: self.homed,
            heartbeat_ms: self.od.u16(0x1017, 0),
            heartbeat_on: self.heartbeat_on,
            fault_code: self.fault_code,
            rpdo1_map: self.od.mapping(0x1600),
            tpdo1_map: self.od.mapping(0x1A00),
            rpdo1_valid: self.rpdo_cob().is_some(),
            tpdo1_valid: self.tpdo_cob().is_some(),
        }
    }

    // --- node id and units --------------------------------------------------------------

    fn id(&self) -> u16 {
        self.node.raw() as u16
    }

    fn to_mm(&self, counts: i32) -> f64 {
        counts as f64 / self.cpm
    }

    fn speed(&self, index: u16, sub: u8) -> f64 {
        self.od.u32(index, sub) as f64 / self.cpm
    }

    fn encoder_counts(&self) -> i32 {
        self.counts(self.mover.pos)
    }

    /// A physical position in encoder increments.
    fn counts(&self, phys: f64) -> i32 {
        let c = ((phys - self.zero) * self.cpm).round();
        c.clamp(i32::MIN as f64, i32::MAX as f64) as i32
    }
}
