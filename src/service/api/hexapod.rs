//! The hexapod calibration run on the wire (`hexapod_status`, the snapshot).

use serde::{Deserialize, Serialize};

/// Fewest poses a generated plan may have.
pub const MIN_POSES: usize = 20;
/// Poses of the default plan.
pub const DEFAULT_POSES: usize = 200;
/// The most poses a generated plan takes (a day at a few seconds a pose).
pub const MAX_POSES: usize = 20_000;

/// Where the run is, as `hexapod_status` answers (DOFs in µm and arcsec).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct HexapodView {
    /// "idle", "running", "stopping", "fitting", "stopped", "failed" or "done".
    pub state: String,
    pub controller: String,
    /// The plan file, or "" for the generated plan of `poses` poses.
    pub plan: String,
    pub poses: usize,
    pub out: String,
    pub done: usize,
    pub total: usize,
    pub resumed_from: usize,
    pub machine_s: f64,
    pub elapsed_s: f64,
    pub eta_s: Option<f64>,
    pub reconnects: u32,
    pub fit_iteration: u32,
    /// Why it stopped or failed (the controller's code and text when it was the controller).
    pub error: Option<String>,
    /// The judgement: held-out poses and frames, RMS of single frames against the reached
    /// poses, the single-frame Cramér–Rao bound, and their ratio, per DOF.
    pub holdout_poses: usize,
    pub holdout_frames: usize,
    /// Held-out frames the calibration could not decouple, left out of the judgement.
    pub untraceable: usize,
    /// Positions along the travel (carriage, follower; mm) the plan visits.
    pub stations: usize,
    pub holdout_rms: Option<[f64; 6]>,
    pub crlb: Option<[f64; 6]>,
    pub ratio: Option<[f64; 6]>,
    pub calibration_file: String,
}

impl HexapodView {
    pub fn idle() -> HexapodView {
        HexapodView {
            state: "idle".into(),
            ..HexapodView::default()
        }
    }

    /// Whether a run (or its fit) is under way.
    pub fn active(&self) -> bool {
        matches!(self.state.as_str(), "running" | "stopping" | "fitting")
    }
}
