//! axiscomp: six-DOF geometric error measurement and compensation for machine-tool linear axes.
//!
//! Data flows one way (DESIGN §5), and the modules follow it:
//!
//! `acquire` (PSD registers → `Frame`) → `track` (PSD2's stitched position) → `decouple` (readings → six errors with covariance,
//! using the head's model from `optics` and its calibration from `calibrate`).
//! Field links: `modbus` (the I/O module), `can` + `canopen` (the follower drive).
//! A run's captures go to `evaluate` (ISO 230-2/230-1 figures) and then to `comp` (compensation
//! tables and controller exports).
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
pub mod run;

// In data-flow order after `run` (not alphabetical): captures → ISO figures →
pub mod evaluate;
// → compensation tables and controller exports.
pub mod comp;

pub mod service;
pub mod sim;
pub mod track;
pub mod units;
pub mod util;

pub use units::Errors6;
