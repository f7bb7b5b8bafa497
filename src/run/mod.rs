//! Measurement runs (DESIGN §6, §7): the ISO 230-2 test plan, the part program, capture at each
//! target, and the run state machine. A run produces `Capture`s, which `evaluate` turns into ISO
//! figures and `comp` into compensation tables.

pub mod judge;
pub mod machine;
pub mod plan;
pub mod program;
pub mod session;

pub use judge::{Decision, Judge, Repeatability};
pub use machine::{CaptureSettings, FrameSample, RunAction, RunMachine};
pub use plan::{ETA_ACCEL_MM_S2, Plan, PlanError, PlanSpec, Step, TargetKey};
pub use program::{CaptureMode, Dialect, Handshake};

use crate::units::Errors6;
use serde::{Deserialize, Serialize};

/// The direction the target was approached in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub enum Direction {
    /// Approached moving towards increasing position (ISO 230-2 ↑).
    #[serde(rename = "+")]
    Up,
    /// Approached moving towards decreasing position (ISO 230-2 ↓).
    #[serde(rename = "-")]
    Down,
}

impl Direction {
    /// "+" or "-".
    pub fn sign(self) -> &'static str {
        match self {
            Direction::Up => "+",
            Direction::Down => "-",
        }
    }

    /// "upwards" or "downwards".
    pub fn words(self) -> &'static str {
        match self {
            Direction::Up => "upwards",
            Direction::Down => "downwards",
        }
    }
}

/// One capture: the stable mean of the six errors at one target, in one run and direction.
/// Deviations are `measured − nominal` (ISO 230-2: x = P_measured − P_target).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Capture {
    /// Run number, 1-based.
    pub run: u32,
    /// Target number, 0-based, in increasing position.
    pub target_index: u32,
    /// The target's nominal position (mm).
    pub target_mm: f64,
    pub direction: Direction,
    /// Mean of the six errors over the capture window (internal units: mm, rad), relative to
    /// the zero reference when one was set.
    pub errors: Errors6,
    /// Standard deviation of single frames in the window (internal units).
    pub frame_sd: Errors6,
    /// Standard uncertainty of `errors` (internal units): noise of the mean, stitching and
    /// the decoupling's covariance.
    pub u: Errors6,
    /// Frames averaged.
    pub frames: u32,
    /// Material and air temperature (°C), when sensors are configured.
    pub material_c: Option<f64>,
    pub air_c: Option<f64>,
    /// When it was taken (µs since the Unix epoch).
    pub unix_us: i64,
}
