//! axiscomp: six-DOF geometric error measurement and compensation for machine-tool linear axes.
//!
//! Data flows one way (DESIGN §5), from PSD readings to a published table:
//!
//! 1. `acquire`: the I/O module's registers → a `Frame` of three PSD spots (over `modbus`);
//! 2. `track`: PSD2's stitched position as the follower stage keeps the spot on it (the
//!    follower is driven over `can` + `canopen`);
//! 3. `decouple`: readings → the six errors with their covariance, using the head's model
//!    (`optics`) and its calibration (`calibrate`);
//! 4. `run`: the ISO 230-2 test cycle and the captures at each target;
//! 5. `evaluate`: ISO 230-2 / 230-1 figures from the captures;
//! 6. `comp`: compensation tables and controller exports; `machine`: the three axes together,
//!    their 21 errors and the controls' volumetric compensation; `commission`: a machine's
//!    record, its commissioning plan set-up by set-up, the model from the stored runs;
//! 7. `plc`: tables into the CNC's PLC over Modbus TCP (push with handshake, pull server).
//!
//! Around them: `service` (the live service: tasks, snapshot, control API), `console` (the
//! terminal UI over the control API), `store` (SQLite), `report` (plots and run reports),
//! `config`, `sim` (the digital twin everything is tested against), `units` (the conventions)
//! and `util`.

pub mod acquire;
pub mod align;
pub mod calibrate;
pub mod can;
pub mod canopen;
pub mod commission;
pub mod comp;
pub mod config;
pub mod console;
pub mod decouple;
pub mod evaluate;
pub mod follower;
pub mod hexapod;
pub mod machine;
pub mod modbus;
pub mod optics;
pub mod plc;
pub mod report;
pub mod run;
pub mod service;
pub mod sim;
pub mod store;
pub mod track;
pub mod trend;
pub mod units;
pub mod util;

pub use units::Errors6;
