//! The whole machine on the wire (issue 27): a stored machine, its commissioning plan set-up by
//! set-up, the squarenesses measured so far and the model's predicted volumetric error, as the
//! `machines` and `machine` requests answer. User units (µm, arcsec).

use serde::{Deserialize, Serialize};

/// A stored machine in a list.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MachineSummary {
    pub id: i64,
    pub name: String,
    /// When it was stored (RFC 3339, UTC).
    pub created: String,
    /// Set-ups measured, of how many.
    pub measured: usize,
    pub setups: usize,
    /// The next set-up's title, or `None` when every one is measured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub next: Option<String>,
}

/// One set-up of the plan.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SetupView {
    /// 1-based, in the plan's order.
    pub number: usize,
    /// "2 of 4: Y through the optical square for XY".
    pub title: String,
    pub axis: String,
    /// "measured", "next" or "waiting".
    pub state: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub run_id: Option<i64>,
    /// What the technician does, step by step.
    pub steps: Vec<String>,
    /// The run's plan, to start it with (`run_start`; the console's Measure screen).
    #[serde(default)]
    pub plan: crate::run::PlanSpec,
    /// The notes its run carries (`run_start`'s), which tie the run to this set-up.
    #[serde(default)]
    pub run_notes: String,
}

/// A squareness as measured.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SquarenessView {
    /// "XY", "ZX", "YZ".
    pub pair: String,
    /// ISO 230-1: "C0Y", "B0Z", "A0Z".
    pub name: String,
    pub value_arcsec: f64,
    /// Expanded, k = 2.
    #[serde(rename = "U_arcsec")]
    pub expanded_arcsec: f64,
    /// The certificate of the square it was measured through.
    pub square: String,
}

/// The model's predicted error of the tool point over the volume, uncompensated.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PredictedView {
    /// Points of a regular grid over the volume.
    pub points: usize,
    pub tool_mm: [f64; 3],
    pub max_um: f64,
    pub rms_um: f64,
    /// Where the largest is (mm, machine coordinates).
    pub at_mm: [f64; 3],
}

/// A stored machine and where its commissioning stands.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MachineView {
    pub id: i64,
    pub name: String,
    pub chain: String,
    pub travel_mm: [f64; 3],
    pub tool_mm: [f64; 3],
    pub created: String,
    pub setups: Vec<SetupView>,
    pub squareness: Vec<SquarenessView>,
    /// The model's prediction when every set-up is measured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub predicted: Option<PredictedView>,
    /// Why there is no model (yet), in words.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub no_model: Option<String>,
}
