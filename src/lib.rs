//! axiscomp: six-DOF geometric error measurement and compensation for machine-tool linear axes.
//!
//! Data flows one way (DESIGN §5), and the modules follow it:
//!
//! `optics` (the head: layout, ray tracing, forward model) → `decouple` (readings → six errors
//! with covariance) ← `calibrate` (β and installation errors from known poses).
//! `sim` is the digital twin the rest is tested against; `units` holds the conventions;
//! `util` the small shared pieces.

pub mod calibrate;
pub mod decouple;
pub mod optics;
pub mod sim;
pub mod units;
pub mod util;

pub use units::Errors6;
