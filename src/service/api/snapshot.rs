//! The `Snapshot`: everything the console and `axiscomp status` show, published on a watch
//! channel and sent over the control API as JSON. User units (µm, arcsec) throughout, since it
//! is an edge.

use serde::{Deserialize, Serialize};

/// The service's state at one instant.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Snapshot {
    /// When it was taken (µs since the Unix epoch).
    pub unix_us: i64,
    /// The last frame from the PSDs.
    pub psd: Option<PsdView>,
    /// The live six errors.
    pub live: Option<LiveView>,
    pub follower: FollowerView,
    pub tracking: TrackingView,
    pub links: LinksView,
    /// Active and recently cleared alarms, newest first.
    pub alarms: Vec<Alarm>,
    /// The active run, if any.
    #[serde(default)]
    pub run: Option<RunView>,
    /// The follower's stop-and-go mapping: under way, or how the last one since the service
    /// started ended.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub follower_mapping: Option<super::MappingView>,
    /// The follower's level stations: under way, or how the last one since the service
    /// started ended.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub follower_level: Option<super::LevelView>,
}

/// A measurement run in progress.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RunView {
    pub id: i64,
    pub axis: String,
    pub captures: usize,
    pub expected: usize,
    /// Where the part program went (a file, or "twin").
    pub program: String,
    /// Why the run is paused (a PSD without its spot), while it is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub paused: Option<String>,
}

/// The last PSD frame.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PsdView {
    pub seq: u64,
    /// Spot per PSD (X, Y in µm), `None` when its SUM is below threshold.
    pub spots_um: [Option<[f64; 2]>; 3],
    pub sums_v: [f64; 3],
    /// PSD active-area half-size (µm), for drawing the boxes.
    pub half_size_um: [f64; 3],
    /// Every PSD has its spot and the frame is fresh (not older than the acquisition's
    /// stale age: 100 ms, or 5 frame periods at low rates).
    pub valid: bool,
    /// The frame's age when the snapshot was taken (ms).
    #[serde(default)]
    pub age_ms: f64,
    /// Frames per second over the last second.
    pub rate_hz: f64,
    /// Invalid frames (beam blocked or off a PSD) since start.
    pub invalid_frames: u64,
    /// Frames the core was too late to decouple (tracked, not averaged) since start.
    #[serde(default)]
    pub late_frames: u64,
}

/// The live six errors in user units.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LiveView {
    /// dx, dy, dz (µm), ex, ey, ez (arcsec).
    pub errors: [f64; 6],
    /// Standard deviations, same units.
    pub sd: [f64; 6],
    pub frames: usize,
    pub travel_mm: f64,
    /// The nominal position; without it positioning (dy) is not defined.
    pub nominal_mm: Option<f64>,
    pub position_mm: f64,
    pub zeroed: bool,
}

/// The follower drive.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FollowerView {
    pub node_id: u8,
    /// CiA 402 power state, e.g. "Operation enabled".
    pub state: String,
    pub position_mm: Option<f64>,
    pub target_mm: Option<f64>,
    pub homed: bool,
    pub heartbeat_ok: bool,
    /// The last emergency message, decoded.
    pub last_emcy: Option<String>,
    /// The drive command under way ("home", "move", ...) and for how long (s).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub busy: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub busy_s: Option<f64>,
}

/// The follower tracking and stitching.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TrackingView {
    /// "overlap" or "encoder".
    pub strategy: String,
    pub valid: bool,
    pub at_rest: bool,
    /// PSD2's stitched position along the follower axis (mm) and vertical offset (µm).
    pub follower_mm: f64,
    pub vertical_um: f64,
    /// Accumulated stitching standard deviation (µm), along and vertical.
    pub sd_um: [f64; 2],
    pub handovers: usize,
    /// The follower error map applied to encoder steps, when one is in use.
    #[serde(default)]
    pub follower_map: Option<super::FollowerMapView>,
}

/// One field link.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LinkView {
    /// "up" (good replies), "connecting", "connected" (no reply yet), "refusing" (Modbus
    /// exceptions only), "down", "closed"; the CAN link: "up" or "no heartbeat".
    pub state: String,
    /// Peer address or interface.
    pub peer: String,
    /// The last error, when down.
    pub detail: Option<String>,
    pub rate_hz: f64,
    pub latency_p50_us: f64,
    pub latency_p99_us: f64,
    pub errors: u64,
    /// Of which Modbus exception replies.
    #[serde(default)]
    pub exceptions: u64,
    pub reconnects: u64,
}

/// The field links.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LinksView {
    pub io: LinkView,
    pub can: LinkView,
}

/// An alarm.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Alarm {
    /// Stable code, e.g. "heartbeat-lost", "drive-fault", "drive-absent", "beam-blocked",
    /// "io-link-down", "io-exception".
    pub code: String,
    pub text: String,
    pub since_unix_us: i64,
    pub active: bool,
}
