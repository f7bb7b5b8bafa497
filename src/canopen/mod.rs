//! CANopen master for the follower drive (DESIGN §6): NMT, heartbeat consumer, SDO client,
//! PDO mapping, SYNC, EMCY and the CiA 402 drive state machine.
//!
//! Every protocol piece is a sans-I/O machine (quinn-proto shape, DESIGN §11): it takes
//! `now` as an argument, is fed frames with `handle_frame` and deadlines with
//! `handle_timeout`, and hands out what to do with `poll_transmit`, `poll_timeout` and
//! `poll_event`. One thin tokio task (`task`) owns a [`CanTransport`](crate::can::CanTransport)
//! and runs the whole [`Master`]; tests run the same machines on a virtual clock.
//!
//! - `sdo`: SDO client over canopen-rs's codecs, adding what canopen-rs 0.6.1 lacks
//!   (DESIGN §10): per-exchange timeouts, a check of the response multiplexer, abort frames on
//!   a local abort or timeout, and segmented transfers of any length.
//! - `nmt`: NMT commands and the heartbeat consumer (boot-up detection, loss, state).
//! - `emcy`: EMCY decoding with CiA 301/402 error-code texts.
//! - `pdo`: the PDO mapping sequence, RPDO1/TPDO1 codecs and the SYNC producer.
//! - `cia402`: statusword/controlword, power states, homing, profile-position and cyclic
//!   synchronous position bits.
//! - `csp`: the demand ramp for following in cyclic synchronous position.
//! - `config`: validated configuration (node id, timings, scaling, homing, profile, limits).
//! - `master`: the drive master composing all of the above behind high-level commands.
//! - `task`: the driver task with a cloneable [`DriveHandle`] and a watch of [`DriveStatus`].

pub mod cia402;
pub mod config;
pub mod csp;
pub mod emcy;
pub mod master;
pub mod nmt;
pub mod pdo;
pub mod sdo;
pub mod task;

pub use canopen_rs::{NmtCommand, NmtState, NodeId};
pub use cia402::{HomingStatus, PowerState, Statusword};
pub use config::{
    ConfigError, DriveConfig, DriveSettings, HomingConfig, ProfileConfig, Scaling, TravelLimits,
};
pub use emcy::Emcy;
pub use master::{Command, DriveError, DriveStatus, Event, Master, OpId, Reply};
pub use sdo::{AbortCode, ObjAddr, SdoClient, SdoError};
pub use task::{DriveHandle, spawn_drive};

use crate::can::CanFrame;

/// COB-ID bases of the predefined connection set (CiA 301 §7.3.5).
pub mod cob {
    /// NMT node control (master → nodes).
    pub const NMT: u16 = 0x000;
    /// SYNC.
    pub const SYNC: u16 = 0x080;
    /// EMCY, + node id.
    pub const EMCY: u16 = 0x080;
    /// TPDO1 (drive → master), + node id.
    pub const TPDO1: u16 = 0x180;
    /// RPDO1 (master → drive), + node id.
    pub const RPDO1: u16 = 0x200;
    /// SDO server → client, + node id.
    pub const SDO_TX: u16 = 0x580;
    /// SDO client → server, + node id.
    pub const SDO_RX: u16 = 0x600;
    /// NMT error control (heartbeat, boot-up), + node id.
    pub const HEARTBEAT: u16 = 0x700;
}

/// A standard-id frame built from a COB-ID of the predefined connection set.
///
/// Callers pass base + node id (≤ 0x77F) and at most 8 data bytes; the id is masked to 11
/// bits and the data cut to 8 bytes, so `CanFrame::new` always accepts.
pub(crate) fn frame(id: u16, data: &[u8]) -> CanFrame {
    match CanFrame::new(id & 0x7FF, &data[..data.len().min(8)]) {
        Some(f) => f,
        None => unreachable!("an 11-bit id with at most 8 data bytes is a valid frame"),
    }
}
