//! axiscomp: six-DOF geometric error measurement and compensation for machine-tool linear axes.
//!
//! Data flows one way (DESIGN §5), and the modules follow it:
//!
//! `acquire` (PSD registers → `Frame`) → `track` (PSD2's stitched position) → `decouple` (readings → six errors with covariance,
//! using the head's model from `optics` and its calibration from `calibrate`).
//! Field links: `modbus` (the I/O module), `can` + `canopen` (the follower drive).
//! `store` keeps calibrations, runs, captures, tables and the audit log in SQLite; `report` draws
//! plots and writes run reports.
//! `sim` is the digital twin the rest is tested against; `units` holds the conventions;
//! `util` the small shared pieces.

pub mod acquire;
pub mod calibrate;
pub mod can;
pub mod canopen;
pub mod config;
pub mod decouple;
pub mod modbus;
pub mod optics;
pub mod report;
pub mod run;
pub mod service;
pub mod sim;
pub mod store;
pub mod track;
pub mod units;
pub mod util;

pub use units::Errors6;
