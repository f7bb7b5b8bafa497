//! The calibration hexapod (DESIGN §3): the controllers metrology labs own, driven over their
//! documented TCP protocols, and the calibration procedure that carries the head's moving
//! module through a pose plan.
//!
//! - `gcs`: PI C-887 controllers, GCS 2.0 over TCP port 50000 (`MOV`, `POS?`, `ONT?`, `ERR?`,
//!   `SPI`, `KSD`/`KEN`), sans-I/O;
//! - `xps`: Newport HXP controllers, the XPS API over TCP port 5001 (`HexapodMoveAbsolute(...)`
//!   answered `code,values,EndOfAPI`, `ErrorStringGet` for the controller's text), sans-I/O;
//! - `driver`: [`Hexapod`], one thin TCP driver for either machine: connect, initialise/home,
//!   coordinate systems, move and wait in position, read the reached pose, stop, reconnect;
//! - `plan`: the pose plan (generated over the operating window, or read from a CSV file) and
//!   its workspace check before the first move;
//! - `bench`: what moves the carriage and the follower to the plan's stations;
//! - `procedure`: the calibration run, resumable from its pose file;
//! - `session`: connect, run or resume, fit, judge and write the files (CLI and service);
//! - `config`: `[hexapod]`.
//!
//! Poses on the wire are in the controllers' units, millimetres and degrees, X Y Z U V W; in
//! the code they are [`HexPose`]. The work coordinate system is the head's frame (DESIGN §1)
//! with its origin at the moving module's reference point, so a pose is the six errors
//! `(dx, dy, dz, ex, ey, ez)` the head should read (small angles: U, V, W about x, y, z).

pub mod bench;
pub mod config;
pub mod driver;
mod exchange;
pub mod gcs;
pub mod plan;
pub mod procedure;
pub mod session;
pub mod xps;

pub use driver::Hexapod;

use crate::units::Errors6;
use thiserror::Error;

/// The axis names both controllers use, in order.
pub const AXES: [&str; 6] = ["X", "Y", "Z", "U", "V", "W"];

/// A pose in controller units: X, Y, Z in mm, U, V, W in degrees.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct HexPose(pub [f64; 6]);

impl HexPose {
    /// The pose that makes the moving module err by `e` (internal units: mm, rad).
    pub fn from_errors(e: &Errors6) -> Self {
        let a = e.to_array();
        HexPose([
            a[0],
            a[1],
            a[2],
            a[3].to_degrees(),
            a[4].to_degrees(),
            a[5].to_degrees(),
        ])
    }

    /// The six errors this pose gives the moving module.
    pub fn to_errors(&self) -> Errors6 {
        let p = self.0;
        Errors6::from_array([
            p[0],
            p[1],
            p[2],
            p[3].to_radians(),
            p[4].to_radians(),
            p[5].to_radians(),
        ])
    }
}

/// The controller's workspace, as a box in the work coordinate system (mm, degrees).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Workspace {
    pub min: [f64; 6],
    pub max: [f64; 6],
}

impl Workspace {
    /// Symmetric limits: ± `half` per axis.
    pub fn symmetric(half: [f64; 6]) -> Self {
        Workspace {
            min: half.map(|h| -h),
            max: half,
        }
    }

    /// The first axis of `p` outside the workspace: (axis index, value).
    pub fn outside(&self, p: &HexPose) -> Option<(usize, f64)> {
        (0..6)
            .find(|&k| !(p.0[k] >= self.min[k] && p.0[k] <= self.max[k]))
            .map(|k| (k, p.0[k]))
    }
}

/// Which controller and protocol.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Driver {
    /// PI C-887, GCS 2.0 (TCP port 50000).
    PiGcs,
    /// Newport HXP, XPS API (TCP port 5001).
    NewportXps,
}

impl Driver {
    pub fn name(self) -> &'static str {
        match self {
            Driver::PiGcs => "PI C-887",
            Driver::NewportXps => "Newport HXP",
        }
    }

    /// The port the real controllers listen on.
    pub fn default_port(self) -> u16 {
        match self {
            Driver::PiGcs => 50000,
            Driver::NewportXps => 5001,
        }
    }

    /// A fresh protocol machine for this controller.
    pub fn machine(self, group: &str) -> Box<dyn Protocol> {
        match self {
            Driver::PiGcs => Box::new(gcs::Gcs::new()),
            Driver::NewportXps => Box::new(xps::Xps::new(group)),
        }
    }
}

/// Why a hexapod command failed.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum HexapodError {
    /// The controller refused or failed: its own code and text.
    #[error("{controller} error {code}: {text}")]
    Controller {
        controller: &'static str,
        code: i64,
        text: String,
    },
    #[error(
        "link to the {controller} at {addr}: {reason}; check the address and that the controller is on"
    )]
    Link {
        controller: &'static str,
        addr: String,
        reason: String,
    },
    #[error(
        "the {controller} answered \"{reply}\" to {command}, which is not what its manual says"
    )]
    Protocol {
        controller: &'static str,
        command: String,
        reply: String,
    },
    #[error("the {controller} did not answer {command} within {seconds:.1} s")]
    Timeout {
        controller: &'static str,
        command: String,
        seconds: f64,
    },
    #[error("the {controller} did not reach the pose within {seconds:.1} s")]
    NotInPosition {
        controller: &'static str,
        seconds: f64,
    },
}

impl HexapodError {
    /// Whether the link is gone (reconnect before going on).
    pub fn is_link(&self) -> bool {
        matches!(
            self,
            HexapodError::Link { .. } | HexapodError::Timeout { .. }
        )
    }
}

/// What the driver asks a protocol machine to do.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Command {
    /// The controller's identification.
    Identify,
    /// Servo on / initialise, and start the reference move (homing).
    Initialize,
    /// Whether the hexapod is referenced and ready.
    Referenced,
    /// The pivot point (mm, in the platform's frame).
    SetPivot([f64; 3]),
    /// The work coordinate system, relative to the controller's own (mm, degrees).
    SetWork(HexPose),
    /// Move to an absolute pose in the work coordinate system.
    Move(HexPose),
    /// The reached pose.
    Position,
    /// Whether every axis is on target (in position).
    OnTarget,
    /// Stop all motion now.
    Stop,
    /// The linear speed (mm/s): GCS `VLS`; on the HXP the velocity of the six actuators'
    /// SGamma profiles (`PositionerSGammaParametersSet`, see `xps`).
    SetSpeed(f64),
}

impl Command {
    pub fn name(&self) -> &'static str {
        match self {
            Command::Identify => "identify",
            Command::Initialize => "initialise",
            Command::Referenced => "reference status",
            Command::SetPivot(_) => "set pivot",
            Command::SetWork(_) => "set work coordinate system",
            Command::Move(_) => "move",
            Command::Position => "position",
            Command::OnTarget => "on-target status",
            Command::Stop => "stop",
            Command::SetSpeed(_) => "set speed",
        }
    }
}

/// A command's result.
#[derive(Clone, Debug, PartialEq)]
pub enum Reply {
    Done,
    Text(String),
    Pose(HexPose),
    Flag(bool),
}

/// A controller protocol, sans-I/O (DESIGN §11): a command goes in (`start`), bytes to send
/// come out (`poll_transmit`), received bytes go in (`handle_input`), and the command's
/// outcome comes out (`poll_outcome`) once the controller has answered everything it needs.
/// Timeouts are the driver's: the machines wait for bytes only.
pub trait Protocol: Send {
    fn controller(&self) -> &'static str;
    /// Begin `cmd`; a command still running is dropped (with its partial input).
    fn start(&mut self, cmd: Command);
    fn poll_transmit(&mut self) -> Option<Vec<u8>>;
    fn handle_input(&mut self, data: &[u8]);
    fn poll_outcome(&mut self) -> Option<Result<Reply, HexapodError>>;
    /// The request being answered (for messages).
    fn current(&self) -> String;
}

/// Format a number for the wire: enough digits for 0.1 nm / 1e-7°, no exponent.
pub fn wire_number(v: f64) -> String {
    let s = format!("{v:.7}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" || s.is_empty() {
        "0".into()
    } else {
        s.to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pose_units_are_mm_and_degrees() {
        let e = Errors6::from_user([100.0, -2000.0, 5.0, 3600.0, 0.0, -36.0]);
        let p = HexPose::from_errors(&e);
        assert!((p.0[0] - 0.1).abs() < 1e-12);
        assert!((p.0[1] + 2.0).abs() < 1e-12);
        assert!((p.0[3] - 1.0).abs() < 1e-12, "3600″ = 1°");
        assert!((p.0[5] + 0.01).abs() < 1e-12);
        let back = p.to_errors().to_array();
        let a = e.to_array();
        for k in 0..6 {
            assert!((back[k] - a[k]).abs() < 1e-15);
        }
    }

    #[test]
    fn workspace_names_the_first_axis_outside() {
        let w = Workspace::symmetric([1.0, 2.0, 1.0, 0.1, 0.1, 0.1]);
        assert_eq!(w.outside(&HexPose([0.5, -2.0, 0.0, 0.0, 0.0, 0.0])), None);
        assert_eq!(
            w.outside(&HexPose([0.5, -2.5, 0.0, 0.2, 0.0, 0.0])),
            Some((1, -2.5))
        );
        // NaN is outside every box.
        assert_eq!(w.outside(&HexPose([f64::NAN; 6])).map(|(k, _)| k), Some(0));
    }

    #[test]
    fn wire_numbers() {
        assert_eq!(wire_number(0.0), "0");
        assert_eq!(wire_number(-0.0), "0");
        assert_eq!(wire_number(1.5), "1.5");
        assert_eq!(wire_number(-0.0001234), "-0.0001234");
        assert_eq!(wire_number(2.0), "2");
    }
}
