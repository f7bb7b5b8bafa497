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

use crate::can::{CanError, CanFrame, CanTransport};
use crate::canopen::cia402::{
    self, CW_CHANGE_IMMEDIATELY, CW_HALT, CW_NEW_SETPOINT, CW_RELATIVE, FsaCommand, HomingStatus,
    MODE_CSP, MODE_HOMING, MODE_PROFILE_POSITION, PowerState, SW_CSP_TARGET_USED,
    SW_FOLLOWING_ERROR, SW_INTERNAL_LIMIT, SW_REMOTE, SW_SETPOINT_ACK, SW_TARGET_REACHED,
    SW_VOLTAGE_ENABLED,
};
use crate::canopen::config::Scaling;
use crate::canopen::emcy::Emcy;
use crate::canopen::pdo::{COB_INVALID, MapEntry};
use crate::canopen::sdo::{AbortCode, ObjAddr, encode_abort};
use crate::canopen::{NmtState, NodeId, cob};
use crate::sim::SimError;
use canopen_rs::sdo as codec;
use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;

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

// --- the object dictionary ------------------------------------------------------------------

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Access {
    Ro,
    Rw,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Pdo {
    No,
    /// May be mapped into an RPDO (written by the master).
    Rx,
    /// May be mapped into a TPDO (read by the master).
    Tx,
}

#[derive(Clone, Debug)]
struct Entry {
    data: Vec<u8>,
    access: Access,
    /// `None`: variable length up to `max`.
    size: Option<usize>,
    max: usize,
    pdo: Pdo,
}

#[derive(Clone, Debug, Default)]
struct Od {
    map: BTreeMap<(u16, u8), Entry>,
}

impl Od {
    fn add(&mut self, index: u16, sub: u8, data: Vec<u8>, access: Access, pdo: Pdo) {
        let size = Some(data.len());
        self.map.insert(
            (index, sub),
            Entry {
                max: data.len(),
                data,
                access,
                size,
                pdo,
            },
        );
    }
    fn add_var(&mut self, index: u16, sub: u8, data: Vec<u8>, max: usize, access: Access) {
        self.map.insert(
            (index, sub),
            Entry {
                data,
                access,
                size: None,
                max,
                pdo: Pdo::No,
            },
        );
    }
    fn entry(&self, obj: ObjAddr) -> Result<&Entry, AbortCode> {
        match self.map.get(&(obj.index, obj.sub)) {
            Some(e) => Ok(e),
            None if self.map.keys().any(|(i, _)| *i == obj.index) => Err(AbortCode::NO_SUBINDEX),
            None => Err(AbortCode::NO_OBJECT),
        }
    }
    fn read(&self, obj: ObjAddr) -> Result<Vec<u8>, AbortCode> {
        self.entry(obj).map(|e| e.data.clone())
    }
    /// Existence, access and length of a write of `len` bytes.
    fn check_write(&self, obj: ObjAddr, len: usize) -> Result<(), AbortCode> {
        let e = self.entry(obj)?;
        if e.access != Access::Rw {
            return Err(AbortCode::WRITE_OF_READ_ONLY);
        }
        match e.size {
            Some(n) if len > n => Err(AbortCode::LENGTH_TOO_HIGH),
            Some(n) if len < n => Err(AbortCode::LENGTH_TOO_LOW),
            None if len > e.max => Err(AbortCode::LENGTH_TOO_HIGH),
            _ => Ok(()),
        }
    }
    /// Store without checks (internal values, PDO data already checked).
    fn set(&mut self, index: u16, sub: u8, data: &[u8]) {
        if let Some(e) = self.map.get_mut(&(index, sub)) {
            e.data = data.to_vec();
        }
    }
    fn uint(&self, index: u16, sub: u8) -> u64 {
        self.map.get(&(index, sub)).map_or(0, |e| {
            e.data
                .iter()
                .take(8)
                .rev()
                .fold(0u64, |acc, &b| (acc << 8) | b as u64)
        })
    }
    fn u8(&self, index: u16, sub: u8) -> u8 {
        self.uint(index, sub) as u8
    }
    fn u16(&self, index: u16, sub: u8) -> u16 {
        self.uint(index, sub) as u16
    }
    fn u32(&self, index: u16, sub: u8) -> u32 {
        self.uint(index, sub) as u32
    }
    fn i32(&self, index: u16, sub: u8) -> i32 {
        self.u32(index, sub) as i32
    }
    fn i8(&self, index: u16, sub: u8) -> i8 {
        self.u8(index, sub) as i8
    }
    fn mapping(&self, map_index: u16) -> Vec<MapEntry> {
        let n = self.u8(map_index, 0).min(8);
        (1..=n)
            .map(|k| MapEntry::decode(self.u32(map_index, k)))
            .collect()
    }
}

/// The communication objects (reset by NMT reset communication).
fn communication_objects(od: &mut Od, node: u8, heartbeat_ms: u16) {
    let id = node as u32;
    od.add(
        0x1017,
        0,
        heartbeat_ms.to_le_bytes().to_vec(),
        Access::Rw,
        Pdo::No,
    );
    od.add(0x1400, 0, vec![2], Access::Ro, Pdo::No);
    od.add(
        0x1400,
        1,
        (0x200 + id).to_le_bytes().to_vec(),
        Access::Rw,
        Pdo::No,
    );
    od.add(0x1400, 2, vec![255], Access::Rw, Pdo::No);
    od.add(0x1600, 0, vec![1], Access::Rw, Pdo::No);
    od.add(
        0x1600,
        1,
        0x6040_0010u32.to_le_bytes().to_vec(),
        Access::Rw,
        Pdo::No,
    );
    for k in 2..=8 {
        od.add(0x1600, k, vec![0; 4], Access::Rw, Pdo::No);
    }
    od.add(0x1800, 0, vec![5], Access::Ro, Pdo::No);
    od.add(
        0x1800,
        1,
        (0x180 + id).to_le_bytes().to_vec(),
        Access::Rw,
        Pdo::No,
    );
    od.add(0x1800, 2, vec![255], Access::Rw, Pdo::No);
    od.add(0x1800, 3, vec![0; 2], Access::Rw, Pdo::No);
    od.add(0x1800, 5, vec![0; 2], Access::Rw, Pdo::No);
    od.add(0x1A00, 0, vec![1], Access::Rw, Pdo::No);
    od.add(
        0x1A00,
        1,
        0x6041_0010u32.to_le_bytes().to_vec(),
        Access::Rw,
        Pdo::No,
    );
    for k in 2..=8 {
        od.add(0x1A00, k, vec![0; 4], Access::Rw, Pdo::No);
    }
}

/// The device name (0x1008): longer than 32 bytes, so reading it needs a segmented upload
/// beyond canopen-rs's limit.
pub const DEVICE_NAME: &str = "axiscomp twin follower drive (CiA 402 servo: profile position, homing, cyclic synchronous position)";

fn build_od(cfg: &TwinDriveConfig, cpm: f64) -> Od {
    let mut od = Od::default();
    let c = |mm: f64| ((mm * cpm).round().max(0.0) as u32).to_le_bytes().to_vec();
    od.add(
        0x1000,
        0,
        0x0002_0192u32.to_le_bytes().to_vec(),
        Access::Ro,
        Pdo::No,
    );
    od.add(0x1001, 0, vec![0], Access::Ro, Pdo::Tx);
    od.add(
        0x1008,
        0,
        DEVICE_NAME.as_bytes().to_vec(),
        Access::Ro,
        Pdo::No,
    );
    od.add(0x1018, 0, vec![4], Access::Ro, Pdo::No);
    for (k, v) in [
        (1u8, 0x0000_0A5Cu32),
        (2, 0x0000_402F),
        (3, 0x0001_0000),
        (4, 1),
    ] {
        od.add(0x1018, k, v.to_le_bytes().to_vec(), Access::Ro, Pdo::No);
    }
    communication_objects(&mut od, cfg.node_id, cfg.default_heartbeat_ms);
    od.add_var(0x2000, 0, Vec::new(), 256, Access::Rw);
    od.add(0x603F, 0, vec![0; 2], Access::Ro, Pdo::Tx);
    od.add(0x6040, 0, vec![0; 2], Access::Rw, Pdo::Rx);
    od.add(0x6041, 0, vec![0; 2], Access::Ro, Pdo::Tx);
    od.add(0x605A, 0, 2i16.to_le_bytes().to_vec(), Access::Rw, Pdo::No);
    od.add(0x6060, 0, vec![0], Access::Rw, Pdo::Rx);
    od.add(0x6061, 0, vec![0], Access::Ro, Pdo::Tx);
    od.add(0x6062, 0, vec![0; 4], Access::Ro, Pdo::Tx);
    od.add(0x6064, 0, vec![0; 4], Access::Ro, Pdo::Tx);
    od.add(0x6065, 0, c(0.5), Access::Rw, Pdo::No);
    od.add(0x6067, 0, c(0.001), Access::Rw, Pdo::No);
    od.add(0x606C, 0, vec![0; 4], Access::Ro, Pdo::Tx);
    od.add(0x607A, 0, vec![0; 4], Access::Rw, Pdo::Rx);
    od.add(0x607C, 0, vec![0; 4], Access::Rw, Pdo::No);
    od.add(0x607D, 0, vec![2], Access::Ro, Pdo::No);
    od.add(0x607D, 1, vec![0; 4], Access::Rw, Pdo::No);
    od.add(0x607D, 2, vec![0; 4], Access::Rw, Pdo::No);
    od.add(0x6081, 0, c(10.0), Access::Rw, Pdo::No);
    od.add(0x6083, 0, c(100.0), Access::Rw, Pdo::No);
    od.add(0x6084, 0, c(100.0), Access::Rw, Pdo::No);
    od.add(0x6085, 0, c(500.0), Access::Rw, Pdo::No);
    // CSP limits: max profile velocity, max acceleration.
    od.add(0x607F, 0, c(1000.0), Access::Rw, Pdo::No);
    od.add(0x60C5, 0, c(20_000.0), Access::Rw, Pdo::No);
    let s = cfg.scaling;
    od.add(0x608F, 0, vec![2], Access::Ro, Pdo::No);
    od.add(
        0x608F,
        1,
        s.encoder_increments.to_le_bytes().to_vec(),
        Access::Ro,
        Pdo::No,
    );
    od.add(
        0x608F,
        2,
        s.motor_revolutions.to_le_bytes().to_vec(),
        Access::Ro,
        Pdo::No,
    );
    // 0x6092:01 feed in µm of travel (this twin's unit), :02 shaft revolutions.
    od.add(0x6092, 0, vec![2], Access::Ro, Pdo::No);
    let feed_um = (s.feed_mm * 1000.0).round().clamp(0.0, u32::MAX as f64) as u32;
    od.add(
        0x6092,
        1,
        feed_um.to_le_bytes().to_vec(),
        Access::Ro,
        Pdo::No,
    );
    od.add(
        0x6092,
        2,
        s.shaft_revolutions.to_le_bytes().to_vec(),
        Access::Ro,
        Pdo::No,
    );
    od.add(0x6098, 0, vec![19], Access::Rw, Pdo::No);
    od.add(0x6099, 0, vec![2], Access::Ro, Pdo::No);
    od.add(0x6099, 1, c(5.0), Access::Rw, Pdo::No);
    od.add(0x6099, 2, c(0.5), Access::Rw, Pdo::No);
    od.add(0x609A, 0, c(50.0), Access::Rw, Pdo::No);
    // Supported drive modes: profile position (bit 0), homing (bit 5), cyclic synchronous
    // position (bit 7).
    od.add(
        0x6502,
        0,
        0xA1u32.to_le_bytes().to_vec(),
        Access::Ro,
        Pdo::No,
    );
    od
}

// --- motion -------------------------------------------------------------------------------

#[derive(Clone, Copy, Debug, PartialEq)]
enum Goal {
    Idle,
    /// Go to `target` (mm) with at most `v` (mm/s), accelerating with `a`, braking with `d`.
    To {
        target: f64,
        v: f64,
        a: f64,
        d: f64,
    },
    /// Brake to standstill with `d`.
    Stop {
        d: f64,
    },
}

/// A point mass following a trapezoidal profile: the velocity tracks the largest speed from
/// which it can still stop within the distance to go, capped at `v`, within the acceleration
/// limits; so it accelerates, cruises and brakes to arrive at rest, from any starting
/// velocity (a target changed on the fly). The braking speed is the discrete-time one,
/// `h·(√(¼ + 2s/(h·dt)) − ½)` with `h = d·dt`, so that stepping `x += v·dt` after each
/// velocity change stops on the target rather than overshooting it.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Mover {
    pos: f64,
    vel: f64,
    goal: Goal,
}

impl Mover {
    /// Advance by `dt` seconds; returns true when the goal was reached in this step.
    fn step(&mut self, dt: f64) -> bool {
        match self.goal {
            Goal::Idle => false,
            Goal::Stop { d } => {
                let dv = d * dt;
                if self.vel.abs() <= dv {
                    self.vel = 0.0;
                    self.goal = Goal::Idle;
                    return true;
                }
                self.vel -= dv * self.vel.signum();
                self.pos += self.vel * dt;
                false
            }
            Goal::To { target, v, a, d } => {
                let s = target - self.pos;
                if s.abs() < 1e-12 {
                    self.pos = target;
                    self.vel = 0.0;
                    self.goal = Goal::Idle;
                    return true;
                }
                let h = d * dt;
                let braking = h * ((0.25 + 2.0 * s.abs() / (h * dt)).sqrt() - 0.5);
                let want = s.signum() * v.min(braking);
                let speeding_up = want.abs() > self.vel.abs() && want * self.vel >= 0.0;
                let limit = if speeding_up { a } else { d } * dt;
                self.vel += (want - self.vel).clamp(-limit, limit);
                let next = self.pos + self.vel * dt;
                if (target - next) * s <= 0.0 {
                    // Crossed or reached the target in this step: arrive.
                    self.pos = target;
                    self.vel = 0.0;
                    self.goal = Goal::Idle;
                    return true;
                }
                self.pos = next;
                false
            }
        }
    }

    fn moving(&self) -> bool {
        self.goal != Goal::Idle || self.vel != 0.0
    }

    /// Servo for `dt` seconds onto a set-point that is at `s` (mm) at the end of the step and
    /// moves at `sv` (mm/s), within `v` (mm/s) and `a` (mm/s², speeding up and braking):
    /// velocity feed-forward plus the braking speed that closes the remaining gap. Lands on
    /// the set-point when one step can, within both limits.
    fn track(&mut self, s: f64, sv: f64, v: f64, a: f64, dt: f64) {
        self.goal = Goal::Idle;
        if dt <= 0.0 {
            return;
        }
        let h = a * dt;
        let land = (s - self.pos) / dt;
        if land.abs() <= v && (land - self.vel).abs() <= h && (land - sv).abs() <= h {
            self.pos = s;
            self.vel = if sv == 0.0 && land.abs() < 1e-12 {
                0.0
            } else {
                land
            };
            return;
        }
        let gap = s - self.pos - sv * dt;
        let braking = if h > 0.0 {
            h * ((0.25 + 2.0 * gap.abs() / (h * dt)).sqrt() - 0.5)
        } else {
            0.0
        };
        let want = (sv + gap.signum() * braking).clamp(-v, v);
        self.vel += (want - self.vel).clamp(-h, h);
        self.pos += self.vel * dt;
    }

    /// Brake with `d` (at once idle when already at rest).
    fn brake(&mut self, d: f64) {
        self.goal = if self.vel == 0.0 {
            Goal::Idle
        } else {
            Goal::Stop { d }
        };
    }
}

/// Cyclic synchronous position: the internal position demand (physical mm), moving linearly
/// from `from` to the latest demand `to` over `span` from `start`; then, if the motion is
/// steady (this segment's velocity within a quarter of the previous one's), on at that
/// velocity for up to one more `span` (a late next demand), else holding.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Interp {
    from: f64,
    to: f64,
    start: Instant,
    span: Duration,
    /// Go on past `to` while the next demand is late.
    steady: bool,
}

impl Interp {
    /// At rest at `pos`.
    fn hold(pos: f64, now: Instant) -> Self {
        Interp {
            from: pos,
            to: pos,
            start: now,
            span: Duration::ZERO,
            steady: false,
        }
    }

    /// The velocity of the segment (mm/s).
    fn vel(&self) -> f64 {
        let span = self.span.as_secs_f64();
        if span > 0.0 {
            (self.to - self.from) / span
        } else {
            0.0
        }
    }

    /// The internal demand and its velocity at `t`.
    fn at(&self, t: Instant) -> (f64, f64) {
        let span = self.span.as_secs_f64();
        let since = t.saturating_duration_since(self.start).as_secs_f64();
        if span <= 0.0 {
            return (self.to, 0.0);
        }
        let v = self.vel();
        let go_on = if self.steady { 2.0 } else { 1.0 };
        if since <= go_on * span {
            (self.from + v * since, v)
        } else {
            (self.from + go_on * v * span, 0.0)
        }
    }

    /// When the internal demand comes to rest.
    fn end(&self) -> Instant {
        self.start + self.span * if self.steady { 2 } else { 1 }
    }
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
            SimError::Input(format!("twin drive node id {} is not 1..=127", cfg.node_id))
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

    fn id(&self) -> u16 {
        self.node.raw() as u16
    }

    // --- NMT ------------------------------------------------------------------------------

    fn boot(&mut self, now: Instant) {
        self.nmt = NmtState::PreOperational;
        self.transfer = None;
        self.rpdo_latched = None;
        self.tpdo_syncs = 0;
        self.last_tpdo = None;
        self.tx
            .push_back(frame(cob::HEARTBEAT + self.id(), &[0x00]));
        self.schedule_heartbeat(now);
    }

    fn schedule_heartbeat(&mut self, now: Instant) {
        let ms = self.od.u16(0x1017, 0);
        self.next_heartbeat =
            (ms > 0 && self.heartbeat_on).then(|| now + Duration::from_millis(ms as u64));
    }

    fn reset_communication(&mut self, now: Instant) {
        communication_objects(
            &mut self.od,
            self.cfg.node_id,
            self.cfg.default_heartbeat_ms,
        );
        self.boot(now);
    }

    fn reset_application(&mut self) {
        self.mover.vel = 0.0;
        self.mover.goal = Goal::Idle;
        self.csp = None;
        self.demand_at = None;
        self.cycle = None;
        self.csp_error = 0.0;
        self.fsa = PowerState::SwitchOnDisabled;
        self.last_cw = 0;
        self.ack = false;
        self.pending = None;
        self.halted = false;
        self.homing = Homing::Idle;
        self.homing_status = HomingStatus::Interrupted;
        self.homed = false;
        self.following_error = false;
        self.fault_code = 0;
        self.zero = self.mover.pos;
        self.last_target = 0;
        self.od.set(0x6040, 0, &[0, 0]);
        self.od.set(0x6060, 0, &[0]);
        self.od.set(0x607A, 0, &[0; 4]);
    }

    fn on_nmt(&mut self, data: &[u8], now: Instant) {
        if data.len() != 2 || (data[1] != 0 && data[1] != self.node.raw()) {
            return;
        }
        match data[0] {
            0x01 => self.nmt = NmtState::Operational,
            0x02 => self.nmt = NmtState::Stopped,
            0x80 => self.nmt = NmtState::PreOperational,
            0x81 => {
                self.reset_application();
                self.reset_communication(now);
            }
            0x82 => self.reset_communication(now),
            _ => {}
        }
        if self.nmt != NmtState::Operational {
            self.rpdo_latched = None;
        }
    }

    // --- SDO server -------------------------------------------------------------------------

    fn respond(&mut self, p: [u8; 8], now: Instant) {
        let f = frame(cob::SDO_TX + self.id(), &p);
        if self.sdo_delay.is_zero() {
            self.tx.push_back(f);
        } else {
            self.delayed.push_back((now + self.sdo_delay, f));
        }
    }

    fn abort(&mut self, obj: ObjAddr, code: AbortCode, now: Instant) {
        self.transfer = None;
        self.respond(encode_abort(obj, code), now);
    }

    fn on_sdo(&mut self, data: &[u8], now: Instant) {
        if self.nmt == NmtState::Stopped || data.is_empty() {
            return;
        }
        let mut p = [0u8; 8];
        p[..data.len().min(8)].copy_from_slice(&data[..data.len().min(8)]);
        let mux = ObjAddr::from_frame(&p);
        let cs = p[0] >> 5;
        let current = match self.transfer {
            Some(Transfer::Upload { obj, .. } | Transfer::Download { obj, .. }) => Some(obj),
            None => None,
        };
        if cs == 4 {
            // The client aborts: no answer.
            self.transfer = None;
            return;
        }
        if let Some(r) = self.refusal {
            let obj = if matches!(cs, 1 | 2) {
                mux
            } else {
                current.unwrap_or(mux)
            };
            if r.index.is_none_or(|i| i == obj.index) {
                return self.abort(obj, r.code, now);
            }
        }
        match cs {
            1 => self.sdo_download_initiate(mux, &p, now),
            0 => self.sdo_download_segment(&p, now),
            2 => self.sdo_upload_initiate(mux, now),
            3 => self.sdo_upload_segment(&p, now),
            _ => self.abort(current.unwrap_or(mux), AbortCode::COMMAND_INVALID, now),
        }
    }

    fn sdo_download_initiate(&mut self, obj: ObjAddr, p: &[u8; 8], now: Instant) {
        self.transfer = None;
        let expedited = p[0] & 0x02 != 0;
        let sized = p[0] & 0x01 != 0;
        if expedited {
            let len = if sized {
                4 - ((p[0] >> 2) & 0x03) as usize
            } else {
                // Size not indicated: the object's own size, at most 4.
                self.od.entry(obj).map_or(4, |e| e.size.unwrap_or(4).min(4))
            };
            match self.write_object(obj, &p[4..4 + len], now) {
                Ok(()) => self.respond(codec::encode_download_response(addr(obj)), now),
                Err(code) => self.abort(obj, code, now),
            }
            return;
        }
        let size = sized.then(|| u32::from_le_bytes([p[4], p[5], p[6], p[7]]) as usize);
        // Check what can be checked before the data arrives.
        let check = match size {
            Some(n) => self.od.check_write(obj, n),
            None => self.od.check_write(obj, 0).or_else(|c| {
                if c == AbortCode::LENGTH_TOO_LOW {
                    Ok(())
                } else {
                    Err(c)
                }
            }),
        };
        if let Err(code) = check {
            return self.abort(obj, code, now);
        }
        self.buf.clear();
        self.transfer = Some(Transfer::Download {
            obj,
            size,
            toggle: false,
        });
        self.respond(codec::encode_download_response(addr(obj)), now);
    }

    fn sdo_download_segment(&mut self, p: &[u8; 8], now: Instant) {
        let Some(Transfer::Download { obj, size, toggle }) = self.transfer else {
            return self.abort(ObjAddr::new(0, 0), AbortCode::COMMAND_INVALID, now);
        };
        let Ok(seg) = codec::decode_data_segment(p) else {
            return self.abort(obj, AbortCode::COMMAND_INVALID, now);
        };
        if seg.toggle != toggle {
            return self.abort(obj, AbortCode::TOGGLE_NOT_ALTERNATED, now);
        }
        self.buf.extend_from_slice(seg.data);
        if !seg.last {
            self.transfer = Some(Transfer::Download {
                obj,
                size,
                toggle: !toggle,
            });
            return self.respond(codec::encode_download_segment_response(toggle), now);
        }
        self.transfer = None;
        if size.is_some_and(|n| n != self.buf.len()) {
            return self.abort(obj, AbortCode::LENGTH_MISMATCH, now);
        }
        let data = std::mem::take(&mut self.buf);
        match self.write_object(obj, &data, now) {
            Ok(()) => self.respond(codec::encode_download_segment_response(toggle), now),
            Err(code) => self.abort(obj, code, now),
        }
    }

    fn sdo_upload_initiate(&mut self, obj: ObjAddr, now: Instant) {
        self.transfer = None;
        self.refresh_od();
        let data = match self.od.read(obj) {
            Ok(d) => d,
            Err(code) => return self.abort(obj, code, now),
        };
        if (1..=4).contains(&data.len()) {
            // Expedited: scs 2, n = 4 − len unused bytes, e = 1, s = 1; data in bytes 4–7.
            let mut p = [0u8; 8];
            p[0] = 0x43 | (((4 - data.len()) as u8) << 2);
            p[1..3].copy_from_slice(&obj.index.to_le_bytes());
            p[3] = obj.sub;
            p[4..4 + data.len()].copy_from_slice(&data);
            return self.respond(p, now);
        }
        self.respond(
            codec::encode_upload_initiate_segmented_response(addr(obj), data.len() as u32),
            now,
        );
        self.buf = data;
        self.transfer = Some(Transfer::Upload {
            obj,
            pos: 0,
            toggle: false,
        });
    }

    fn sdo_upload_segment(&mut self, p: &[u8; 8], now: Instant) {
        let Some(Transfer::Upload { obj, pos, toggle }) = self.transfer else {
            return self.abort(ObjAddr::new(0, 0), AbortCode::COMMAND_INVALID, now);
        };
        if (p[0] & 0x10 != 0) != toggle {
            return self.abort(obj, AbortCode::TOGGLE_NOT_ALTERNATED, now);
        }
        let end = (pos + codec::SEGMENT_DATA_MAX).min(self.buf.len());
        let last = end == self.buf.len();
        let Ok(seg) = codec::encode_data_segment(&self.buf[pos..end], toggle, last) else {
            return self.abort(obj, AbortCode::GENERAL, now);
        };
        self.transfer = (!last).then_some(Transfer::Upload {
            obj,
            pos: end,
            toggle: !toggle,
        });
        self.respond(seg, now);
    }

    /// Write an object through the SDO server: access, length and the object's own rules.
    fn write_object(&mut self, obj: ObjAddr, data: &[u8], now: Instant) -> Result<(), AbortCode> {
        self.od.check_write(obj, data.len())?;
        let u32v = || {
            let mut b = [0u8; 4];
            b[..data.len().min(4)].copy_from_slice(&data[..data.len().min(4)]);
            u32::from_le_bytes(b)
        };
        match (obj.index, obj.sub) {
            (0x1400 | 0x1800, 1) => {
                let cur = self.od.u32(obj.index, 1);
                let new = u32v();
                if cur & COB_INVALID == 0 && new & COB_INVALID == 0 && new != cur {
                    return Err(AbortCode::INVALID_VALUE);
                }
            }
            (0x1600 | 0x1A00, sub) => {
                let comm = obj.index - 0x200;
                if self.od.u32(comm, 1) & COB_INVALID == 0 {
                    return Err(AbortCode::DEVICE_STATE);
                }
                if sub == 0 {
                    self.check_mapping(obj.index, data.first().copied().unwrap_or(0))?;
                } else if self.od.u8(obj.index, 0) != 0 {
                    return Err(AbortCode::DEVICE_STATE);
                }
            }
            (0x6060, 0)
                if !matches!(
                    data[0] as i8,
                    0 | MODE_PROFILE_POSITION | MODE_HOMING | MODE_CSP
                ) =>
            {
                return Err(AbortCode::INVALID_VALUE);
            }
            _ => {}
        }
        self.od.set(obj.index, obj.sub, data);
        self.after_write(obj.index, now);
        Ok(())
    }

    /// Enabling `n` entries of mapping `map_index`: each must name a mappable object of the
    /// right direction with its exact length, and all together fit 64 bits.
    fn check_mapping(&self, map_index: u16, n: u8) -> Result<(), AbortCode> {
        if n > 8 {
            return Err(AbortCode::VALUE_TOO_HIGH);
        }
        let want = if map_index == 0x1600 {
            Pdo::Rx
        } else {
            Pdo::Tx
        };
        let mut bits = 0u32;
        for k in 1..=n {
            let e = MapEntry::decode(self.od.u32(map_index, k));
            let entry = self
                .od
                .entry(ObjAddr::new(e.index, e.sub))
                .map_err(|_| AbortCode::NOT_MAPPABLE)?;
            if entry.pdo != want || entry.size.map(|s| s * 8) != Some(e.bits as usize) {
                return Err(AbortCode::NOT_MAPPABLE);
            }
            bits += e.bits as u32;
        }
        if bits > 64 {
            return Err(AbortCode::PDO_TOO_LONG);
        }
        Ok(())
    }

    fn after_write(&mut self, index: u16, now: Instant) {
        match index {
            0x1017 => self.schedule_heartbeat(now),
            0x6040 => {
                let cw = self.od.u16(0x6040, 0);
                self.on_controlword(cw, now);
            }
            0x6060 => self.on_mode(now),
            _ => {}
        }
    }

    // --- PDO and SYNC -----------------------------------------------------------------------

    fn rpdo_cob(&self) -> Option<u32> {
        let c = self.od.u32(0x1400, 1);
        (c & COB_INVALID == 0).then_some(c & 0x7FF)
    }

    fn tpdo_cob(&self) -> Option<u32> {
        let c = self.od.u32(0x1800, 1);
        (c & COB_INVALID == 0).then_some(c & 0x7FF)
    }

    fn on_rpdo(&mut self, data: &[u8], now: Instant) {
        let need: usize = self
            .od
            .mapping(0x1600)
            .iter()
            .map(|e| e.bits as usize / 8)
            .sum();
        if data.len() < need {
            // CiA 301: PDO not processed due to length error.
            self.emcy(0x8210, [0; 5]);
            return;
        }
        if self.od.u8(0x1400, 2) <= 240 {
            self.rpdo_latched = Some(data.to_vec());
        } else {
            self.apply_rpdo(data, now);
        }
    }

    fn apply_rpdo(&mut self, data: &[u8], now: Instant) {
        let mut at = 0;
        let mut touched = Vec::new();
        for e in self.od.mapping(0x1600) {
            let n = e.bits as usize / 8;
            self.od.set(e.index, e.sub, &data[at..at + n]);
            touched.push(e.index);
            at += n;
        }
        // Mode first, then the controlword (which may start a set-point with the new target),
        // then in CSP the target as the new demand.
        if touched.contains(&0x6060) {
            self.on_mode(now);
        }
        if touched.contains(&0x6040) {
            let cw = self.od.u16(0x6040, 0);
            self.on_controlword(cw, now);
        }
        if touched.contains(&0x607A) && self.mode() == MODE_CSP {
            self.take_demand(now);
        }
    }

    /// Cyclic synchronous position: 0x607A is the new demand (when the drive follows), reached
    /// by the internal demand one cycle later.
    fn take_demand(&mut self, now: Instant) {
        self.update(now);
        if let Some(prev) = self.demand_at.replace(now) {
            let iv = now.saturating_duration_since(prev);
            if iv <= Duration::from_secs(1) {
                self.cycle = Some(match self.cycle {
                    Some(c) => (c * 3 + iv) / 4,
                    None => iv,
                });
            }
        }
        let Some(ip) = self.csp else {
            return;
        };
        let mut t = self.od.i32(0x607A, 0);
        let (lo, hi) = (self.od.i32(0x607D, 1), self.od.i32(0x607D, 2));
        self.internal_limit = false;
        if lo < hi && !(lo..=hi).contains(&t) {
            t = t.clamp(lo, hi);
            self.internal_limit = true;
        }
        self.last_target = t;
        let mut next = Interp {
            from: ip.at(now).0,
            to: self.to_mm(t) + self.zero,
            start: now,
            span: self.cycle.unwrap_or(Duration::ZERO),
            steady: false,
        };
        let (v, before) = (next.vel(), ip.vel());
        next.steady = v != 0.0 && (v - before).abs() <= 0.25 * v.abs();
        self.csp = Some(next);
    }

    /// Follow demands from where the stage is, if mode 8, operation enabled and no halt.
    fn csp_hold_here(&mut self) {
        let follows =
            self.mode() == MODE_CSP && self.fsa == PowerState::OperationEnabled && !self.halted;
        self.csp = follows.then(|| Interp::hold(self.mover.pos, self.last_update));
        if follows {
            self.mover.goal = Goal::Idle;
        }
    }

    /// Whether CSP motion is still under way (the internal demand moving or not yet reached).
    fn csp_busy(&self) -> bool {
        self.csp.is_some_and(|ip| {
            (ip.from != ip.to && self.last_update < ip.end())
                || self.mover.pos != ip.at(ip.end()).0
                || self.mover.vel != 0.0
        })
    }

    fn tpdo_data(&mut self) -> Vec<u8> {
        self.refresh_od();
        let mut d = Vec::with_capacity(8);
        for e in self.od.mapping(0x1A00) {
            if let Ok(v) = self.od.read(ObjAddr::new(e.index, e.sub)) {
                d.extend_from_slice(&v);
            }
        }
        d
    }

    fn send_tpdo(&mut self, cob_id: u32) {
        let d = self.tpdo_data();
        self.tx.push_back(frame(cob_id as u16, &d));
        self.last_tpdo = Some(d);
    }

    fn on_sync(&mut self, now: Instant) {
        if self.nmt != NmtState::Operational {
            return;
        }
        if let Some(d) = self.rpdo_latched.take() {
            self.apply_rpdo(&d, now);
        }
        self.update(now);
        if let Some(cob_id) = self.tpdo_cob() {
            let ty = self.od.u8(0x1800, 2);
            if ty == 0 {
                self.send_tpdo(cob_id);
            } else if ty <= 240 {
                self.tpdo_syncs += 1;
                if self.tpdo_syncs >= ty as u16 {
                    self.tpdo_syncs = 0;
                    self.send_tpdo(cob_id);
                }
            }
        }
    }

    /// Event-driven TPDO (types 254/255): sent when its data changes.
    fn event_tpdo(&mut self) {
        if self.nmt != NmtState::Operational {
            return;
        }
        if let Some(cob_id) = self.tpdo_cob()
            && self.od.u8(0x1800, 2) >= 254
        {
            let d = self.tpdo_data();
            if self.last_tpdo.as_ref() != Some(&d) {
                self.send_tpdo(cob_id);
            }
        }
    }

    fn emcy(&mut self, code: u16, manufacturer: [u8; 5]) {
        if self.nmt == NmtState::Stopped {
            return;
        }
        let register = self.od.u8(0x1001, 0);
        let e = Emcy {
            code,
            register,
            manufacturer,
        };
        self.tx.push_back(frame(cob::EMCY + self.id(), &e.encode()));
    }

    // --- CiA 402 ----------------------------------------------------------------------------

    fn mode(&self) -> i8 {
        self.od.i8(0x6060, 0)
    }

    fn on_mode(&mut self, now: Instant) {
        self.update(now);
        if self.homing != Homing::Idle && self.mode() != MODE_HOMING {
            self.interrupt_homing();
        }
        self.ack = false;
        let was_csp = self.csp.is_some();
        if self.mode() == MODE_CSP {
            if !was_csp {
                self.pending = None;
                self.csp_hold_here();
            }
        } else if was_csp {
            // Out of CSP: brake what motion is left; the last demand is the base of relative
            // moves.
            self.csp = None;
            if self.mover.vel != 0.0 {
                let d = self.speed(0x6084, 0).max(1e-6);
                self.mover.brake(d);
            }
        }
    }

    fn to_mm(&self, counts: i32) -> f64 {
        counts as f64 / self.cpm
    }

    fn speed(&self, index: u16, sub: u8) -> f64 {
        self.od.u32(index, sub) as f64 / self.cpm
    }

    fn enter(&mut self, to: PowerState) {
        let from = self.fsa;
        self.fsa = to;
        match to {
            PowerState::QuickStopActive => {
                self.csp = None;
                let d = self.speed(0x6085, 0).max(1e-6);
                self.mover.brake(d);
                self.pending = None;
                if self.homing != Homing::Idle {
                    self.interrupt_homing();
                }
            }
            PowerState::OperationEnabled if from != PowerState::OperationEnabled => {
                self.csp_hold_here();
            }
            PowerState::OperationEnabled => {}
            _ if from == PowerState::OperationEnabled || from == PowerState::QuickStopActive => {
                // Power removed: the stage stops where it is (the brake holds it).
                self.csp = None;
                self.mover.vel = 0.0;
                self.mover.goal = Goal::Idle;
                self.pending = None;
                self.ack = false;
                if self.homing != Homing::Idle {
                    self.interrupt_homing();
                }
            }
            _ => {}
        }
        if from == PowerState::Fault && to == PowerState::SwitchOnDisabled {
            self.fault_code = 0;
            self.following_error = false;
            self.od.set(0x603F, 0, &[0, 0]);
            self.od.set(0x1001, 0, &[0]);
            self.emcy(0, [0; 5]);
        }
    }

    fn on_controlword(&mut self, cw: u16, now: Instant) {
        self.update(now);
        let prev = self.last_cw;
        self.last_cw = cw;
        if let Some(cmd) = FsaCommand::decode(cw, prev)
            && let Some(next) = cia402::transition(self.fsa, cmd)
        {
            self.enter(next);
            if !self.mover.moving() {
                self.standstill();
            }
        }
        if self.fsa != PowerState::OperationEnabled {
            self.refresh_ack(cw);
            return;
        }
        let rising = |bit: u16| cw & bit != 0 && prev & bit == 0;
        let falling = |bit: u16| cw & bit == 0 && prev & bit != 0;
        if cw & CW_HALT != 0 {
            if !self.halted {
                self.halted = true;
                self.csp = None;
                let d = self.speed(0x6084, 0).max(1e-6);
                self.mover.brake(d);
                self.pending = None;
                if self.homing != Homing::Idle {
                    self.interrupt_homing();
                }
            }
        } else if self.halted {
            self.halted = false;
            if self.mode() == MODE_CSP {
                self.csp_hold_here();
            }
        }
        match self.mode() {
            MODE_PROFILE_POSITION if !self.halted && rising(CW_NEW_SETPOINT) && !self.ack => {
                self.accept_setpoint(cw);
            }
            MODE_HOMING if rising(cia402::CW_HOMING_START) && !self.halted => self.start_homing(),
            MODE_HOMING if falling(cia402::CW_HOMING_START) && self.homing != Homing::Idle => {
                self.interrupt_homing();
            }
            _ => {}
        }
        self.refresh_ack(cw);
    }

    /// Set-point acknowledge (bit 12) drops once the master has dropped bit 4 and the
    /// set-point buffer is free.
    fn refresh_ack(&mut self, cw: u16) {
        if cw & CW_NEW_SETPOINT == 0 && self.pending.is_none() {
            self.ack = false;
        }
    }

    fn accept_setpoint(&mut self, cw: u16) {
        let t = self.od.i32(0x607A, 0);
        let mut target = if cw & CW_RELATIVE != 0 {
            self.last_target.saturating_add(t)
        } else {
            t
        };
        let (lo, hi) = (self.od.i32(0x607D, 1), self.od.i32(0x607D, 2));
        self.internal_limit = false;
        if lo < hi && !(lo..=hi).contains(&target) {
            target = target.clamp(lo, hi);
            self.internal_limit = true;
        }
        self.last_target = target;
        self.ack = true;
        let phys = self.to_mm(target) + self.zero;
        if self.mover.moving() && cw & CW_CHANGE_IMMEDIATELY == 0 {
            self.pending = Some(phys);
        } else {
            self.move_to(phys);
        }
    }

    fn move_to(&mut self, phys: f64) {
        let v = self.speed(0x6081, 0);
        let a = self.speed(0x6083, 0).max(1e-6);
        let d = self.speed(0x6084, 0).max(1e-6);
        self.mover.goal = Goal::To {
            target: phys,
            v,
            a,
            d,
        };
    }

    fn start_homing(&mut self) {
        let method = self.od.i8(0x6098, 0);
        let offset = self.to_mm(self.od.i32(0x607C, 0));
        match method {
            35 | 37 => {
                self.zero = self.mover.pos - offset;
                self.finish_homing();
            }
            1..=34 => {
                let (fast, slow) = (self.speed(0x6099, 1), self.speed(0x6099, 2));
                if fast <= 0.0 || slow <= 0.0 {
                    self.homing_status = HomingStatus::ErrorStopped;
                    return;
                }
                self.homing_status = HomingStatus::InProgress;
                let here = self.mover.pos;
                let approach = self.cfg.homing_approach_mm.max(0.0);
                let a = self.speed(0x609A, 0).max(1e-6);
                if here.abs() > approach {
                    self.homing = Homing::Search;
                    self.mover.goal = Goal::To {
                        target: here.signum() * approach,
                        v: fast,
                        a,
                        d: a,
                    };
                } else {
                    self.homing = Homing::Approach;
                    self.mover.goal = Goal::To {
                        target: 0.0,
                        v: slow,
                        a,
                        d: a,
                    };
                }
            }
            _ => self.homing_status = HomingStatus::ErrorStopped,
        }
    }

    fn finish_homing(&mut self) {
        self.homing = Homing::Idle;
        self.homing_status = HomingStatus::Completed;
        self.homed = true;
        self.last_target = self.encoder_counts();
    }

    fn interrupt_homing(&mut self) {
        self.homing = Homing::Idle;
        self.homing_status = HomingStatus::Interrupted;
        if self.mover.goal != Goal::Idle {
            let d = self.speed(0x609A, 0).max(1e-6);
            self.mover.brake(d);
        }
    }

    /// A reached goal: next homing phase, buffered set-point, or the end of a stop.
    fn arrived(&mut self) {
        match self.homing {
            Homing::Search => {
                self.homing = Homing::Approach;
                let a = self.speed(0x609A, 0).max(1e-6);
                self.mover.goal = Goal::To {
                    target: 0.0,
                    v: self.speed(0x6099, 2),
                    a,
                    d: a,
                };
                return;
            }
            Homing::Approach => {
                let offset = self.to_mm(self.od.i32(0x607C, 0));
                // The switch is at physical 0: there the encoder reads the home offset.
                self.zero = -offset;
                self.finish_homing();
                return;
            }
            Homing::Idle => {}
        }
        if let Some(p) = self.pending.take() {
            self.move_to(p);
            let cw = self.last_cw;
            self.refresh_ack(cw);
        }
    }

    fn standstill(&mut self) {
        match self.fsa {
            PowerState::FaultReactionActive => self.fsa = PowerState::Fault,
            // 0x605A quick stop option: 0–4 end in switch on disabled, 5–8 stay.
            PowerState::QuickStopActive if (0..=4).contains(&(self.od.u16(0x605A, 0) as i16)) => {
                self.fsa = PowerState::SwitchOnDisabled;
            }
            _ => {}
        }
    }

    /// Advance the motion to `now` in steps of at most 1 ms.
    fn update(&mut self, now: Instant) {
        let mut t = self.last_update;
        const STEP: Duration = Duration::from_millis(1);
        let (v, a) = (self.speed(0x607F, 0), self.speed(0x60C5, 0));
        while t < now {
            let dt = (now - t).min(STEP);
            t += dt;
            if let Some(ip) = self.csp {
                let (s, sv) = ip.at(t);
                self.mover.track(s, sv, v, a, dt.as_secs_f64());
            } else if self.mover.step(dt.as_secs_f64()) {
                self.arrived();
            }
        }
        self.last_update = self.last_update.max(now);
        self.csp_error = self
            .csp
            .map_or(0.0, |ip| (ip.at(self.last_update).0 - self.mover.pos).abs());
        if !self.mover.moving() {
            self.standstill();
        }
        self.report_position();
    }

    fn report_position(&mut self) {
        let p = self.mover.pos;
        if self.reported != Some(p) {
            self.reported = Some(p);
            (self.on_position)(p);
        }
    }

    fn encoder_counts(&self) -> i32 {
        self.counts(self.mover.pos)
    }

    /// A physical position in encoder increments.
    fn counts(&self, phys: f64) -> i32 {
        let c = ((phys - self.zero) * self.cpm).round();
        c.clamp(i32::MIN as f64, i32::MAX as f64) as i32
    }

    fn statusword(&self) -> u16 {
        let mut sw = self.fsa.statusword_bits() | SW_REMOTE;
        if self.fsa != PowerState::NotReadyToSwitchOn {
            sw |= SW_VOLTAGE_ENABLED;
        }
        let still = !self.mover.moving();
        match self.mode() {
            MODE_PROFILE_POSITION => {
                if still && self.pending.is_none() {
                    sw |= SW_TARGET_REACHED;
                }
                if self.ack {
                    sw |= SW_SETPOINT_ACK;
                }
                if self.following_error {
                    sw |= SW_FOLLOWING_ERROR;
                }
            }
            MODE_CSP => {
                // Bit 10 is reserved in CSP.
                if self.csp.is_some() {
                    sw |= SW_CSP_TARGET_USED;
                }
                if self.following_error || self.csp_error > self.speed(0x6065, 0) {
                    sw |= SW_FOLLOWING_ERROR;
                }
            }
            MODE_HOMING => {
                let mut h = self.homing_status;
                if h == HomingStatus::ErrorStopped && !still {
                    h = HomingStatus::ErrorMoving;
                }
                if h == HomingStatus::Interrupted && !still {
                    h = HomingStatus::InProgress;
                }
                sw |= h.bits();
            }
            _ => {
                if still {
                    sw |= SW_TARGET_REACHED;
                }
            }
        }
        if self.internal_limit {
            sw |= SW_INTERNAL_LIMIT;
        }
        sw
    }

    /// Bring the process values in the dictionary up to date.
    fn refresh_od(&mut self) {
        let sw = self.statusword();
        self.od.set(0x6041, 0, &sw.to_le_bytes());
        let pos = self.encoder_counts();
        self.od.set(0x6064, 0, &pos.to_le_bytes());
        let demand = match self.csp {
            Some(ip) => self.counts(ip.at(self.last_update).0),
            None => pos,
        };
        self.od.set(0x6062, 0, &demand.to_le_bytes());
        let vel = (self.mover.vel * self.cpm).round() as i32;
        self.od.set(0x606C, 0, &vel.to_le_bytes());
        let mode = self.mode();
        self.od.set(0x6061, 0, &[mode as u8]);
        self.od.set(0x603F, 0, &self.fault_code.to_le_bytes());
    }

    // --- fault injection --------------------------------------------------------------------

    /// Raise a drive fault with EMCY `code`: fault reaction (quick-stop ramp), then fault.
    /// Code 0x8611 also sets the following-error bit.
    pub fn inject_fault(&mut self, code: u16, manufacturer: [u8; 5], now: Instant) {
        self.update(now);
        self.fault_code = code;
        self.following_error = code == 0x8611;
        let class = match code >> 8 {
            0x21..=0x23 => 0x02,
            0x30..=0x33 => 0x04,
            0x40..=0x44 => 0x08,
            0x81 => 0x10,
            0x50..=0x8F => 0x20,
            _ => 0x80,
        };
        self.od.set(0x1001, 0, &[0x01 | class]);
        self.od.set(0x603F, 0, &code.to_le_bytes());
        self.pending = None;
        self.ack = false;
        if self.homing != Homing::Idle {
            self.homing = Homing::Idle;
            self.homing_status = HomingStatus::ErrorStopped;
        }
        self.fsa = PowerState::FaultReactionActive;
        self.csp = None;
        let d = self.speed(0x6085, 0).max(1e-6);
        self.mover.brake(d);
        self.emcy(code, manufacturer);
        self.update(now);
    }

    /// Stop or resume the heartbeat producer.
    pub fn set_heartbeat(&mut self, on: bool, now: Instant) {
        self.heartbeat_on = on;
        self.schedule_heartbeat(now);
    }

    /// Refuse SDO requests (`None`: serve them again).
    pub fn refuse_sdo(&mut self, refusal: Option<SdoRefusal>) {
        self.refusal = refusal;
    }

    /// Delay every SDO response by `delay`.
    pub fn set_sdo_delay(&mut self, delay: Duration) {
        self.sdo_delay = delay;
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
}

fn addr(obj: ObjAddr) -> canopen_rs::Address {
    canopen_rs::Address::new(obj.index, obj.sub)
}

// --- the task -------------------------------------------------------------------------------

/// Fault injection and control for a running twin drive.
#[derive(Clone, Debug)]
pub enum TwinControl {
    Fault { code: u16, manufacturer: [u8; 5] },
    Heartbeat(bool),
    RefuseSdo(Option<SdoRefusal>),
    SdoDelay(Duration),
}

/// A handle on a running twin drive.
#[derive(Clone, Debug)]
pub struct TwinDriveHandle {
    control: mpsc::UnboundedSender<TwinControl>,
    status: watch::Receiver<TwinStatus>,
}

impl TwinDriveHandle {
    fn send(&self, c: TwinControl) {
        // A stopped twin ignores injections.
        let _ = self.control.send(c);
    }
    /// Raise a fault with EMCY `code`.
    pub fn inject_fault(&self, code: u16, manufacturer: [u8; 5]) {
        self.send(TwinControl::Fault { code, manufacturer });
    }
    pub fn set_heartbeat(&self, on: bool) {
        self.send(TwinControl::Heartbeat(on));
    }
    pub fn refuse_sdo(&self, refusal: Option<SdoRefusal>) {
        self.send(TwinControl::RefuseSdo(refusal));
    }
    pub fn set_sdo_delay(&self, delay: Duration) {
        self.send(TwinControl::SdoDelay(delay));
    }
    pub fn status(&self) -> TwinStatus {
        self.status.borrow().clone()
    }
    pub fn watch_status(&self) -> watch::Receiver<TwinStatus> {
        self.status.clone()
    }
}

/// Run a twin drive on `transport`, reporting its position to `on_position` (e.g.
/// `move |mm| plant.set_follower_encoder(mm)`). Ends when every handle is dropped or the
/// transport closes.
pub fn spawn_twin_drive<T: CanTransport>(
    transport: T,
    config: TwinDriveConfig,
    on_position: impl FnMut(f64) + Send + 'static,
) -> Result<(TwinDriveHandle, JoinHandle<Result<(), CanError>>), SimError> {
    let d = TwinDrive::new(config, Box::new(on_position), crate::util::clock::now())?;
    let (control, rx) = mpsc::unbounded_channel();
    let (status_tx, status) = watch::channel(d.status());
    let join = tokio::spawn(twin_task(d, transport, rx, status_tx));
    Ok((TwinDriveHandle { control, status }, join))
}

async fn twin_task<T: CanTransport>(
    mut d: TwinDrive,
    bus: T,
    mut control: mpsc::UnboundedReceiver<TwinControl>,
    status: watch::Sender<TwinStatus>,
) -> Result<(), CanError> {
    loop {
        while let Some(f) = d.poll_transmit() {
            match bus.send(&f).await {
                Ok(()) => {}
                Err(CanError::Closed) => return Err(CanError::Closed),
                Err(e) => tracing::warn!("twin drive could not send {f:?}: {e}"),
            }
        }
        let s = d.status();
        status.send_if_modified(|old| {
            let changed = *old != s;
            *old = s;
            changed
        });
        let deadline = d.poll_timeout();
        tokio::select! {
            r = bus.recv() => match r {
                Ok(f) => d.handle_frame(&f, crate::util::clock::now()),
                Err(e @ (CanError::Lagged(_) | CanError::Malformed(_))) => {
                    tracing::warn!("twin drive: {e}")
                }
                Err(e) => return Err(e),
            },
            c = control.recv() => {
                let now = crate::util::clock::now();
                match c {
                    Some(TwinControl::Fault { code, manufacturer }) => d.inject_fault(code, manufacturer, now),
                    Some(TwinControl::Heartbeat(on)) => d.set_heartbeat(on, now),
                    Some(TwinControl::RefuseSdo(r)) => d.refuse_sdo(r),
                    Some(TwinControl::SdoDelay(t)) => d.set_sdo_delay(t),
                    None => return Ok(()),
                }
            }
            _ = async {
                match deadline {
                    Some(t) => tokio::time::sleep_until(tokio::time::Instant::from_std(t)).await,
                    None => std::future::pending().await,
                }
            } => d.handle_timeout(crate::util::clock::now()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::canopen::pdo::TPDO1_MAP;

    fn parse(s: &str) -> CanFrame {
        let (id, data) = s.split_once('#').unwrap();
        let bytes: Vec<u8> = (0..data.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&data[i..i + 2], 16).unwrap())
            .collect();
        CanFrame::new(u16::from_str_radix(id, 16).unwrap(), &bytes).unwrap()
    }

    fn drive(t0: Instant) -> TwinDrive {
        TwinDrive::new(TwinDriveConfig::default(), Box::new(|_| {}), t0).unwrap()
    }

    fn out(d: &mut TwinDrive) -> Vec<String> {
        std::iter::from_fn(|| d.poll_transmit())
            .map(|f| format!("{f:?}"))
            .collect()
    }

    /// Send a request, return the answer.
    fn ask(d: &mut TwinDrive, req: &str, now: Instant) -> String {
        d.handle_frame(&parse(req), now);
        let o = out(d);
        assert_eq!(o.len(), 1, "{req} → {o:?}");
        o[0].clone()
    }

    #[test]
    fn boot_up_then_heartbeat_at_the_written_period() {
        let t0 = crate::util::clock::now();
        let ms = |n: u64| t0 + Duration::from_millis(n);
        let mut d = drive(t0);
        assert_eq!(out(&mut d), vec!["701#00"]);
        assert_eq!(d.poll_timeout(), None);
        // 0x1017 = 50 ms.
        assert_eq!(
            ask(&mut d, "601#2B17100032000000", t0),
            "581#6017100000000000"
        );
        assert_eq!(d.poll_timeout(), Some(ms(50)));
        d.handle_timeout(ms(50));
        assert_eq!(out(&mut d), vec!["701#7F"]);
        d.handle_frame(&parse("000#0101"), ms(60));
        d.handle_timeout(ms(100));
        // The default TPDO1 (statusword, event-driven) goes out on entering operational.
        assert_eq!(out(&mut d), vec!["181#5006", "701#05"]);
        d.set_heartbeat(false, ms(110));
        d.handle_timeout(ms(400));
        assert!(out(&mut d).is_empty());
        d.set_heartbeat(true, ms(400));
        d.handle_timeout(ms(450));
        assert_eq!(out(&mut d), vec!["701#05"]);
        // NMT to another node is ignored; broadcast stop is not.
        d.handle_frame(&parse("000#0202"), ms(460));
        d.handle_frame(&parse("000#0200"), ms(470));
        d.handle_timeout(ms(500));
        assert_eq!(out(&mut d), vec!["701#04"]);
        // Reset communication: boot-up, 0x1017 back to its default (no heartbeat).
        d.handle_frame(&parse("000#8201"), ms(510));
        assert_eq!(out(&mut d), vec!["701#00"]);
        assert_eq!(d.poll_timeout(), None);
    }

    /// The server's answers to python-canopen's requests equal python-canopen's own server.
    #[test]
    fn sdo_server_matches_python_canopen() {
        let t0 = crate::util::clock::now();
        let mut d = drive(t0);
        out(&mut d);
        assert_eq!(
            ask(&mut d, "601#2B4060000F000000", t0),
            "581#6040600000000000"
        );
        let trace = [
            ("601#2100200028000000", "581#6000200000000000"),
            ("601#0030313233343536", "581#2000000000000000"),
            ("601#103738393A3B3C3D", "581#3000000000000000"),
            ("601#003E3F4041424344", "581#2000000000000000"),
            ("601#1045464748494A4B", "581#3000000000000000"),
            ("601#004C4D4E4F505152", "581#2000000000000000"),
            ("601#1553545556570000", "581#3000000000000000"),
        ];
        for (req, resp) in trace {
            assert_eq!(ask(&mut d, req, t0), resp, "{req}");
        }
        // Read the 40 bytes back: segmented upload, 0x41 with the size, then 6 segments.
        assert_eq!(
            ask(&mut d, "601#4000200000000000", t0),
            "581#4100200028000000"
        );
        let segs = [
            ("601#6000000000000000", "581#0030313233343536"),
            ("601#7000000000000000", "581#103738393A3B3C3D"),
            ("601#6000000000000000", "581#003E3F4041424344"),
            ("601#7000000000000000", "581#1045464748494A4B"),
            ("601#6000000000000000", "581#004C4D4E4F505152"),
            ("601#7000000000000000", "581#1553545556570000"),
        ];
        for (req, resp) in segs {
            assert_eq!(ask(&mut d, req, t0), resp, "{req}");
        }
        // Expedited upload of the device type: 0x43, 4 bytes.
        assert_eq!(
            ask(&mut d, "601#4000100000000000", t0),
            "581#4300100092010200"
        );
        // A 1-byte object: 0x4F.
        assert_eq!(
            ask(&mut d, "601#4060600000000000", t0),
            "581#4F60600000000000"
        );
    }

    #[test]
    fn sdo_server_aborts() {
        let t0 = crate::util::clock::now();
        let mut d = drive(t0);
        out(&mut d);
        // No object; no sub-index; read-only; too long; too short; bad toggle.
        assert_eq!(
            ask(&mut d, "601#4000300000000000", t0),
            "581#8000300000000206"
        );
        assert_eq!(
            ask(&mut d, "601#4000100100000000", t0),
            "581#8000100111000906"
        );
        assert_eq!(
            ask(&mut d, "601#2341600000000000", t0),
            "581#8041600002000106"
        );
        assert_eq!(
            ask(&mut d, "601#2340600000000000", t0),
            "581#8040600012000706"
        );
        assert_eq!(
            ask(&mut d, "601#2F7A600001000000", t0),
            "581#807A600013000706"
        );
        ask(&mut d, "601#2100200010000000", t0);
        assert_eq!(
            ask(&mut d, "601#1030313233343536", t0),
            "581#8000200000000305"
        );
        // Modes other than 0, 1, 6, 8 are refused.
        assert_eq!(
            ask(&mut d, "601#2F60600003000000", t0),
            "581#8060600030000906"
        );
        // Refusal injection names the object and code.
        d.refuse_sdo(Some(SdoRefusal {
            index: Some(0x6081),
            code: AbortCode::DEVICE_STATE,
        }));
        assert_eq!(
            ask(&mut d, "601#2381600000100000", t0),
            "581#8081600022000008"
        );
        assert_eq!(
            ask(&mut d, "601#4064600000000000", t0),
            "581#4364600000000000"
        );
        d.refuse_sdo(None);
        // Slow replies.
        d.set_sdo_delay(Duration::from_millis(300));
        d.handle_frame(&parse("601#4064600000000000"), t0);
        assert!(out(&mut d).is_empty());
        assert_eq!(d.poll_timeout(), Some(t0 + Duration::from_millis(300)));
        d.handle_timeout(t0 + Duration::from_millis(300));
        assert_eq!(out(&mut d), vec!["581#4364600000000000"]);
    }

    #[test]
    fn pdo_mapping_rules_and_honoured_mapping() {
        let t0 = crate::util::clock::now();
        let mut d = drive(t0);
        out(&mut d);
        // Mapping while the PDO is valid: refused (device state).
        assert_eq!(
            ask(&mut d, "601#2F001A0000000000", t0),
            "581#80001A0022000008"
        );
        // Disable TPDO1, count 0.
        assert_eq!(
            ask(&mut d, "601#2300180181010080", t0),
            "581#6000180100000000"
        );
        assert_eq!(
            ask(&mut d, "601#2F001A0000000000", t0),
            "581#60001A0000000000"
        );
        // Entry writes with count 0 are fine; a receive-only object cannot go into a TPDO.
        ask(&mut d, "601#23001A0110004060", t0);
        assert_eq!(
            ask(&mut d, "601#2F001A0001000000", t0),
            "581#80001A0041000406"
        );
        // Nor a wrong length.
        ask(&mut d, "601#23001A0120004160", t0);
        assert_eq!(
            ask(&mut d, "601#2F001A0001000000", t0),
            "581#80001A0041000406"
        );
        // More than 64 bits.
        for (k, v) in [(1, "10004160"), (2, "20006460"), (3, "20006C60")] {
            ask(&mut d, &format!("601#23001A0{k}{v}"), t0);
        }
        assert_eq!(
            ask(&mut d, "601#2F001A0003000000", t0),
            "581#80001A0042000406"
        );
        // Entries with a count set: refused.
        ask(&mut d, "601#23001A0308006160", t0);
        assert_eq!(
            ask(&mut d, "601#2F001A0003000000", t0),
            "581#60001A0000000000"
        );
        assert_eq!(
            ask(&mut d, "601#23001A0110004160", t0),
            "581#80001A0122000008"
        );
        // Enable: statusword + position + mode display (7 bytes), synchronous.
        ask(&mut d, "601#2F00180201000000", t0);
        ask(&mut d, "601#2300180181010000", t0);
        // Changing the COB-ID of a valid PDO is refused.
        assert_eq!(
            ask(&mut d, "601#2300180182010000", t0),
            "581#8000180130000906"
        );
        assert_eq!(
            d.status().tpdo1_map,
            vec![TPDO1_MAP[0], TPDO1_MAP[1], MapEntry::new(0x6061, 0, 8)]
        );
        // No PDO before operational.
        d.handle_frame(&parse("080#"), t0);
        assert!(out(&mut d).is_empty());
        d.handle_frame(&parse("000#0100"), t0);
        d.handle_frame(&parse("080#"), t0);
        // 0x0650: switch on disabled 0x40, voltage 0x10, remote 0x200, target reached 0x400;
        // position 0 (4 bytes), mode 0 (1 byte).
        assert_eq!(out(&mut d), vec!["181#50060000000000"]);
    }

    #[test]
    fn controlword_drives_the_fsa_and_statusword() {
        let t0 = crate::util::clock::now();
        let mut d = drive(t0);
        out(&mut d);
        let sw = |d: &mut TwinDrive, cw: u16| {
            let v = cw.to_le_bytes();
            ask(d, &format!("601#2B406000{:02X}{:02X}0000", v[0], v[1]), t0);
            d.status().statusword
        };
        assert_eq!(sw(&mut d, 0x06), 0x0631);
        assert_eq!(sw(&mut d, 0x07), 0x0633);
        assert_eq!(sw(&mut d, 0x0F), 0x0637);
        assert_eq!(d.status().state, PowerState::OperationEnabled);
        assert_eq!(sw(&mut d, 0x07), 0x0633);
        assert_eq!(sw(&mut d, 0x0F), 0x0637);
        // Quick stop at standstill: quick stop active ends at once in switch on disabled
        // (0x605A = 2).
        assert_eq!(sw(&mut d, 0x02), 0x0650);
        assert_eq!(sw(&mut d, 0x06), 0x0631);
        assert_eq!(sw(&mut d, 0x00), 0x0650);
    }

    #[test]
    fn fault_injection_emcy_and_reset() {
        let t0 = crate::util::clock::now();
        let mut d = drive(t0);
        out(&mut d);
        d.inject_fault(0x8611, [0xDE, 0xAD, 0, 0, 1], t0);
        // Code 0x8611 LE, register generic + device profile, manufacturer bytes.
        assert_eq!(out(&mut d), vec!["081#118621DEAD000001"]);
        let s = d.status();
        assert_eq!(s.state, PowerState::Fault);
        assert_eq!(s.fault_code, 0x8611);
        assert_eq!(
            ask(&mut d, "601#403F600000000000", t0),
            "581#4B3F600011860000"
        );
        assert_eq!(
            ask(&mut d, "601#4001100000000000", t0),
            "581#4F01100021000000"
        );
        // Enable does nothing in fault; the rising edge of bit 7 resets, with an EMCY reset.
        ask(&mut d, "601#2B4060000F000000", t0);
        assert_eq!(d.status().state, PowerState::Fault);
        d.handle_frame(&parse("601#2B40600080000000"), t0);
        assert_eq!(
            out(&mut d),
            vec!["081#0000000000000000", "581#6040600000000000"]
        );
        assert_eq!(d.status().state, PowerState::SwitchOnDisabled);
        assert_eq!(d.status().fault_code, 0);
    }

    /// A 10 mm move at 10 mm/s with 100 mm/s² ramps: 0.1 s up, 0.9 s cruise, 0.1 s down.
    #[test]
    fn trapezoidal_profile() {
        let mut m = Mover {
            pos: 0.0,
            vel: 0.0,
            goal: Goal::To {
                target: 10.0,
                v: 10.0,
                a: 100.0,
                d: 100.0,
            },
        };
        let dt = 1e-4;
        let mut t = 0.0;
        let mut at = |m: &mut Mover, until: f64| {
            while t < until - 1e-12 {
                if m.step(dt) {
                    return true;
                }
                t += dt;
            }
            false
        };
        assert!(!at(&mut m, 0.1));
        // End of the ramp: v = 10 mm/s, s = ½·a·t² = 0.5 mm.
        assert!((m.vel - 10.0).abs() < 1e-6, "{m:?}");
        assert!((m.pos - 0.5).abs() < 1e-3, "{m:?}");
        assert!(!at(&mut m, 0.55));
        assert!((m.pos - 5.0).abs() < 1e-3);
        assert!(!at(&mut m, 1.0));
        assert!((m.pos - 9.5).abs() < 2e-3, "{m:?}");
        // Braking, then arrival at 1.1 s.
        assert!(at(&mut m, 1.2));
        assert!((t - 1.1).abs() < 2e-3, "{t}");
        assert_eq!(m.pos, 10.0);
        assert_eq!(m.vel, 0.0);
        assert!(!m.moving());
        // A short move is a triangle: peak √(a·s) for equal ramps.
        let mut m = Mover {
            pos: 0.0,
            vel: 0.0,
            goal: Goal::To {
                target: 0.25,
                v: 10.0,
                a: 100.0,
                d: 100.0,
            },
        };
        let mut peak: f64 = 0.0;
        let mut n = 0;
        while !m.step(dt) {
            peak = peak.max(m.vel);
            n += 1;
        }
        assert!((peak - 5.0).abs() < 0.05, "{peak}");
        assert!((n as f64 * dt - 0.1).abs() < 2e-3);
        // Braking from speed with a stop goal: v²/(2d) = 0.5 mm.
        let mut m = Mover {
            pos: 0.0,
            vel: 10.0,
            goal: Goal::Stop { d: 100.0 },
        };
        while !m.step(dt) {}
        assert!((m.pos - 0.5).abs() < 1e-3, "{m:?}");
    }

    #[test]
    fn position_reaches_the_plant_callback() {
        let t0 = crate::util::clock::now();
        let seen = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let s = seen.clone();
        let mut d = TwinDrive::new(
            TwinDriveConfig {
                start_mm: 1.5,
                ..Default::default()
            },
            Box::new(move |mm| s.lock().unwrap().push(mm)),
            t0,
        )
        .unwrap();
        assert_eq!(*seen.lock().unwrap(), vec![1.5]);
        out(&mut d);
        // Enable, homing mode, start homing: the stage drives to the switch at 0.
        for cw in ["06", "07", "0F"] {
            ask(&mut d, &format!("601#2B406000{cw}000000"), t0);
        }
        ask(&mut d, "601#2F60600006000000", t0);
        ask(&mut d, "601#2B4060001F000000", t0);
        let mut t = t0;
        while d.poll_timeout().is_some() && t < t0 + Duration::from_secs(10) {
            t = d.poll_timeout().unwrap();
            d.handle_timeout(t);
        }
        let v = seen.lock().unwrap().clone();
        assert_eq!(*v.last().unwrap(), 0.0);
        assert!(
            v.len() > 100 && v.windows(2).all(|w| w[1] <= w[0]),
            "monotonic"
        );
        let s = d.status();
        assert!(s.homed && !s.moving);
        assert_eq!(s.position_mm, 0.0);
        // Homing attained + target reached in homing mode: 0x1637.
        assert_eq!(s.statusword, 0x1637);
    }

    /// A drive with RPDO1 = controlword + target position (synchronous), 0x607F = 20 mm/s,
    /// 0x60C5 = 200 mm/s², enabled in mode 8 and operational, its output drained.
    fn csp_drive(t0: Instant) -> TwinDrive {
        let mut d = drive(t0);
        out(&mut d);
        for req in [
            "601#2300140101020080",
            "601#2F00140201000000",
            "601#2F00160000000000",
            "601#2300160110004060",
            "601#2300160220007A60",
            "601#2F00160002000000",
            "601#2300140101020000",
            // 0x607F = 20 mm/s = 524 288 inc/s; 0x60C5 = 200 mm/s² = 5 242 880 inc/s².
            "601#237F600000000800",
            "601#23C5600000005000",
        ] {
            assert!(ask(&mut d, req, t0).starts_with("581#60"), "{req}");
        }
        for cw in ["06", "07", "0F"] {
            ask(&mut d, &format!("601#2B406000{cw}000000"), t0);
        }
        assert_eq!(
            ask(&mut d, "601#2F60600008000000", t0),
            "581#6060600000000000"
        );
        assert_eq!(
            ask(&mut d, "601#4061600000000000", t0),
            "581#4F61600008000000"
        );
        // Operation enabled 0x0237 with bit 12 (target used), not bit 10.
        assert_eq!(d.status().statusword, 0x1237);
        d.handle_frame(&parse("000#0100"), t0);
        out(&mut d);
        d
    }

    /// RPDO1 with controlword 0x000F and `mm` as the target position, then SYNC, at `t`.
    fn csp_demand(d: &mut TwinDrive, mm: f64, t: Instant) {
        let c = (mm * Scaling::default().counts_per_mm()).round() as i32;
        let b = c.to_le_bytes();
        let rpdo = format!("201#0F00{:02X}{:02X}{:02X}{:02X}", b[0], b[1], b[2], b[3]);
        d.handle_frame(&parse(&rpdo), t);
        d.handle_frame(&parse("080#"), t);
        out(d);
    }

    /// A demand 5 ms late while the motion is steady: the internal demand goes on at the same
    /// velocity meanwhile (no stop and go). At the end of a move (the velocity changing by
    /// more than a quarter) a late demand finds it holding: the stage stops on the last demand
    /// without going past it by more than its servo's overshoot.
    #[test]
    fn csp_late_demand_while_steady_and_at_the_end() {
        let t0 = crate::util::clock::now();
        let ms = |n: u64| t0 + Duration::from_millis(n);
        let mut d = csp_drive(t0);
        // Positions as the drive has them, in whole increments.
        let cpm = Scaling::default().counts_per_mm();
        let q = |mm: f64| (mm * cpm).round() / cpm;
        let at = |d: &TwinDrive| d.status().physical_mm;
        // 10 mm/s: 0.1 mm per 10 ms SYNC.
        for k in 0..30u64 {
            csp_demand(&mut d, 0.1 * k as f64, ms(10 * k));
            d.handle_timeout(ms(10 * k + 5));
        }
        // One cycle behind: at 295 ms the stage is at 2.85 mm (demand 2.9 reached at 300).
        assert!((at(&d) - 2.85).abs() < 1e-4, "{:?}", d.status());
        // The next demand comes at 305 instead of 300: at 303 the stage went on to 2.93.
        d.handle_timeout(ms(303));
        assert!((at(&d) - 2.93).abs() < 1e-4, "{:?}", d.status());
        csp_demand(&mut d, 3.0, ms(305));
        // Braking at 100 mm/s² (1 mm/s less each cycle) to rest at 3.45 mm; the demand after
        // the last step comes 15 ms late.
        let mut x = 3.0;
        for k in 1..=9u64 {
            x += 0.01 * (10 - k) as f64;
            csp_demand(&mut d, x, ms(305 + 10 * k));
        }
        d.handle_timeout(ms(410));
        let mut max = at(&d);
        d.handle_timeout(ms(420));
        max = max.max(at(&d));
        assert_eq!(at(&d), q(3.45), "{:?}", d.status());
        for k in 0..20u64 {
            csp_demand(&mut d, 3.45, ms(410 + 10 * k));
            d.handle_timeout(ms(415 + 10 * k));
            max = max.max(at(&d));
        }
        // Past it only by the servo's own overshoot (a few µm), not by going on for the late
        // cycle (1 mm/s × 15 ms = 15 µm).
        assert!(max - q(3.45) < 0.005, "{max}");
        assert!(at(&d) == q(3.45) && !d.status().moving, "{:?}", d.status());
    }

    /// Mode 8 on the wire: RPDO1 mapped to controlword + target position (synchronous), the
    /// drive enabled, 0x6060 = 8. Each RPDO at SYNC is a new demand, no handshake: the stage
    /// follows a 15 mm/s ramp one SYNC behind, within 0x607F (20 mm/s) and 0x60C5
    /// (200 mm/s²), reports a following error (bit 13) while the start of the ramp is beyond
    /// its acceleration, bit 12 while it uses the target, bit 10 never (reserved), and stops
    /// exactly on a held demand; a jump is run at the velocity limit.
    #[test]
    fn csp_follows_demands_within_its_limits() {
        let t0 = crate::util::clock::now();
        let ms = |n: u64| t0 + Duration::from_millis(n);
        let mut d = csp_drive(t0);
        let cpm = Scaling::default().counts_per_mm();
        let mut samples: Vec<(f64, f64, u16)> = vec![];
        // RPDO + SYNC every 10 ms from `from` to `to` ms with the demand at each, sampling the
        // stage at every motion tick.
        let run = |d: &mut TwinDrive,
                   samples: &mut Vec<(f64, f64, u16)>,
                   from: u64,
                   to: u64,
                   demand: &dyn Fn(u64) -> f64| {
            for k in (from..to).step_by(10) {
                let c = (demand(k) * cpm).round() as i32;
                let b = c.to_le_bytes();
                let rpdo = format!("201#0F00{:02X}{:02X}{:02X}{:02X}", b[0], b[1], b[2], b[3]);
                d.handle_frame(&parse(&rpdo), ms(k));
                d.handle_frame(&parse("080#"), ms(k));
                out(d);
                let end = ms(k + 10);
                while let Some(n) = d.poll_timeout().filter(|n| *n < end) {
                    d.handle_timeout(n);
                    let s = d.status();
                    samples.push(((n - t0).as_secs_f64(), s.physical_mm, s.statusword));
                }
                d.handle_timeout(end);
                let s = d.status();
                samples.push(((end - t0).as_secs_f64(), s.physical_mm, s.statusword));
            }
        };
        let ramp = |k: u64| 15.0 * k as f64 / 1000.0;
        run(&mut d, &mut samples, 0, 500, &ramp);
        // Caught up: one SYNC behind the ramp (the demand taken at k is reached at k + 10 ms).
        for &(t, x, sw) in samples.iter().filter(|s| s.0 >= 0.3) {
            assert!((x - 15.0 * (t - 0.01)).abs() < 1e-3, "{t}: {x}");
            assert_eq!(sw, 0x1237, "{t}");
        }
        let lagging = samples.iter().filter(|s| s.2 & 0x2000 != 0).count();
        assert!(lagging > 0, "following error while accelerating");
        assert!(samples.iter().all(|s| s.2 & 0x0400 == 0), "bit 10 reserved");
        // Hold at 7.5 mm (the last demand of the ramp is 7.35), then a 5 mm jump.
        run(&mut d, &mut samples, 500, 900, &|_| 7.5);
        assert_eq!(d.status().physical_mm, 7.5);
        assert_eq!(d.status().statusword, 0x1237);
        assert_eq!(d.status().demand_mm, Some(7.5));
        run(&mut d, &mut samples, 900, 1500, &|_| 12.5);
        assert_eq!(d.status().physical_mm, 12.5);
        assert_eq!(d.status().statusword, 0x1237);
        assert!(!d.status().moving);
        // The limits, from the sampled positions (2 ms apart or less).
        let v: Vec<(f64, f64)> = samples
            .windows(2)
            .filter(|w| w[1].0 > w[0].0)
            .map(|w| (w[1].0, (w[1].1 - w[0].1) / (w[1].0 - w[0].0)))
            .collect();
        let vmax = v.iter().map(|x| x.1.abs()).fold(0.0, f64::max);
        assert!(vmax <= 20.0 + 1e-6 && vmax > 19.9, "{vmax}");
        for w in v.windows(2) {
            let a = (w[1].1 - w[0].1) / (w[1].0 - w[0].0);
            assert!(
                a.abs() <= 200.0 * (1.0 + 1e-6) + 1e-6,
                "{a} mm/s² at {}",
                w[1].0
            );
        }
        // Halt: the target is ignored (bit 12 clear) and the stage stays.
        d.handle_frame(&parse("201#0F01000000FF"), ms(1500));
        d.handle_frame(&parse("080#"), ms(1500));
        d.handle_timeout(ms(1700));
        let s = d.status();
        assert_eq!(s.physical_mm, 12.5);
        assert_eq!(s.statusword & 0x1000, 0);
        assert_eq!(s.demand_mm, None);
    }
}
