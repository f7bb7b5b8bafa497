//! The digital twin (DESIGN §9): the plant that real hardware would be, built on the same
//! layout file and speaking the same interfaces, recording its truth so every test can compare
//! what was measured with what was injected.
//!
//! So far: the optical head with random installation errors, PSD gain errors and noise
//! (`head`), a hexapod that applies calibration poses (`hexapod`), the plant's shared physical
//! state (`plant`: the measured axis, the follower, the beam), the I/O module that serves the
//! PSDs as raw counts over Modbus TCP following an I/O-module map, with fault injection
//! (`iomodule`), the follower's CiA 402 drive on a CAN transport (`drive`), the follower
//! stage's own errors and its vendor certificate (`follower`), the stop-and-go self-calibration
//! of those errors on the lab (`follower_cal`), and the PLC that takes compensation tables and
//! applies them to the axis (`plc`).

pub mod ageing;
pub mod axis;
pub mod closed_loop;
pub mod cnc;
pub mod config;
pub mod drive;
pub mod follower;
pub mod follower_cal;
pub mod head;
pub mod hexapod;
pub mod hexapod_servers;
pub mod iomodule;
pub mod lab;
pub mod lab_store;
pub mod machine;
pub mod machine_lab;
pub mod machine_time;
pub mod plant;
pub mod plc;
pub mod rng;
pub mod study;
pub mod twin;

pub use drive::{TwinDrive, TwinDriveConfig, TwinDriveHandle, spawn_twin_drive};
pub use head::{InstallSpec, TwinHead};
pub use hexapod::{Hexapod, PoseWindow};
pub use rng::Rng;

use thiserror::Error;

/// Why the twin could not be built.
#[derive(Debug, Error, PartialEq)]
pub enum SimError {
    #[error(
        "no head with installation errors of {offset_mm} mm / {tilt_deg}° could be aligned (every spot within {limit_mm} mm of its PSD centre) in {tries} draws: use smaller errors"
    )]
    CannotAlign {
        offset_mm: f64,
        tilt_deg: f64,
        limit_mm: f64,
        tries: usize,
    },
    #[error("{0}")]
    Input(String),
}
