//! The follower's procedures on the wire: the map in use, a certificate import, the
//! stop-and-go mapping and the level stations (their requests and views).

use crate::follower::Sources;
use serde::{Deserialize, Serialize};

/// The map in use, as the snapshot shows it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FollowerMapView {
    pub id: i64,
    pub name: String,
    /// `certificate`, `self-calibration` or `both`.
    pub source: String,
    /// When it was stored (RFC 3339, UTC).
    pub created: String,
    /// Where each term comes from.
    pub sources: Sources,
}

/// Where a certificate to import comes from: a file on the service's host, or its text.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CertificateImport {
    /// A CSV file on the service's host.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub path: Option<String>,
    /// The CSV text itself (the command line sends the file it read).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub csv: Option<String>,
    /// The name errors and the store give it (default: the path's file name).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// Store it without putting it in use.
    #[serde(default)]
    pub keep_current: bool,
}

/// `follower_map_start`: every field optional.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MappingRequest {
    /// The span (mm); default: the axis' last alignment.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub from_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub to_mm: Option<f64>,
    /// The carriage's step between stops (mm, default 3.75).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_mm: Option<f64>,
    /// Passes over the span, alternately up and down (default 4).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub passes: Option<usize>,
    /// Frames averaged each side of a handover (default 1000).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frames: Option<usize>,
    /// The follower's screw lead (mm, default 5).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lead_mm: Option<f64>,
    /// A back-and-forth probe every this many stops (default 13; 0: none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub probe_every: Option<usize>,
    /// The carriage's feed (mm/min, default 2000).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub feed_mm_min: Option<f64>,
    /// The machine axis (default X): its alignment, the program's axis letter.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis: Option<String>,
    /// The program's dialect (default: the configured one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dialect: Option<String>,
    /// A certificate CSV on the service's host (default: the one kept with the map in use).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub certificate: Option<String>,
}

/// The mapping as `follower_map_status` and the snapshot show it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MappingView {
    /// "approaching" (before the start), "mapping", "finishing", "done", "stopped",
    /// "failed", "interrupted" (by a service restart).
    pub state: String,
    pub axis: String,
    pub from_mm: f64,
    pub to_mm: f64,
    pub step_mm: f64,
    pub passes: usize,
    pub frames: usize,
    pub stops_done: usize,
    pub stops_planned: usize,
    pub steps_kept: usize,
    pub skipped: usize,
    /// Kept steps whose move is not the plan's (another program on the CNC, a stop missed).
    pub out_of_plan: usize,
    /// Machine time since the start, and left by the plan (s).
    pub elapsed_s: f64,
    pub left_s: f64,
    pub dwell_s: f64,
    /// What the dwell is made of, in words.
    pub dwell: String,
    /// The part program's file, and where it went.
    pub program: String,
    pub cnc: String,
    /// The certificate the map is built with, in words.
    pub certificate: String,
    pub started: String,
    pub started_by: String,
    /// Why it stopped, failed or was interrupted.
    pub error: Option<String>,
    /// The map stored, and its summary (`FollowerMap::summary`), once done.
    pub map_id: Option<i64>,
    pub summary: Vec<String>,
}

impl MappingView {
    /// Whether a mapping is under way.
    pub fn active(&self) -> bool {
        matches!(self.state.as_str(), "approaching" | "mapping" | "finishing")
    }
}

/// `follower_level_start`: every field optional.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LevelRequest {
    /// The carriage's span (mm); default: the map in use's span.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub from_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub to_mm: Option<f64>,
    /// Stations at most this far apart, both ends included (mm, default 100).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub station_mm: Option<f64>,
    /// Readings of the head (and of the twin's level) at each station (default 20).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub readings: Option<usize>,
    /// The carriage's feed between stations (mm/min, default 2000).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub feed_mm_min: Option<f64>,
    /// The machine axis: the program's axis letter (default X).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis: Option<String>,
    /// The program's dialect (default: the configured one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dialect: Option<String>,
    /// Check the map in use on this set-up instead of fitting it again: the stations are
    /// fitted as its vertical plus a smooth bend of this set-up (`follower::reuse`); a map
    /// that fits is stored with the bend and put in use, one that does not (the rail
    /// changed) is refused with the span to map again. No self-calibration's steps needed:
    /// the instrument's map from its bench does.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub check_map: bool,
}

/// One station as the view shows it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct StationView {
    /// Where the carriage rests (mm).
    pub at_mm: f64,
    /// "waiting", "reading", "awaiting the level" or "taken".
    pub state: String,
    /// The head's readings taken.
    pub readings: usize,
    /// The follower's encoder there, the head's and the level's mean roll (arcsec), and the
    /// follower's vertical the station gives (µm, up to the common constant) with its u.
    pub encoder_mm: Option<f64>,
    pub head_arcsec: Option<f64>,
    pub level_arcsec: Option<f64>,
    pub value_um: Option<f64>,
    pub u_um: Option<f64>,
}

/// The level stations as `follower_level_status` and the snapshot show them.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LevelView {
    /// "stations" (under way), "done", "stopped", "failed".
    pub state: String,
    /// The stations check the map in use on this set-up (`LevelRequest::check_map`) rather
    /// than fit it again.
    pub check_map: bool,
    /// "manual" or "twin".
    pub level: String,
    /// The instrument in words.
    pub instrument: String,
    pub axis: String,
    pub from_mm: f64,
    pub to_mm: f64,
    pub station_mm: f64,
    pub readings: usize,
    pub stations: Vec<StationView>,
    pub taken: usize,
    /// The station being read, and (manual level) the one whose level reading is awaited.
    pub current: Option<usize>,
    pub awaiting_reading: Option<usize>,
    /// What the operator is to do now.
    pub prompt: String,
    pub dwell_s: f64,
    pub dwell: String,
    pub program: String,
    pub cnc: String,
    /// The map in use the stations are fitted with (its id and name).
    pub map_from: i64,
    pub map_from_name: String,
    pub started: String,
    pub started_by: String,
    pub elapsed_s: f64,
    pub error: Option<String>,
    /// The map stored, its summary, and the vertical's u at mid-span before (the steps alone)
    /// and after (with the stations), µm.
    pub map_id: Option<i64>,
    pub summary: Vec<String>,
    pub u_mid_steps_um: Option<f64>,
    pub u_mid_level_um: Option<f64>,
}

impl LevelView {
    /// Whether the stations are under way (or their map is being stored and the zero taken
    /// again with it).
    pub fn active(&self) -> bool {
        matches!(self.state.as_str(), "stations" | "finishing")
    }
}

impl MappingRequest {
    /// Every number given within its range (`start` and the plan check how they fit
    /// together), or the first that is not, named.
    pub fn check(&self) -> Result<(), String> {
        use crate::follower::selfcal::{MAX_STEP_MM, MIN_STEP_MM};
        use crate::util::range::{Range, field, int_field};
        check_span_and_feed(self.from_mm, self.to_mm, self.feed_mm_min)?;
        let step = Range::new(MIN_STEP_MM, MAX_STEP_MM, "mm");
        field("step_mm", self.step_mm, step)?;
        field("lead_mm", self.lead_mm, Range::new(0.1, 100.0, "mm"))?;
        int_field("passes", self.passes, 1, 100)?;
        int_field("frames", self.frames, 10, 100_000)?;
        int_field("probe_every", self.probe_every, 0, 1000)
    }
}

impl LevelRequest {
    /// Every number given within its range (`start` checks the span against the map's), or
    /// the first that is not, named.
    pub fn check(&self) -> Result<(), String> {
        use crate::util::range::{Range, field, int_field};
        check_span_and_feed(self.from_mm, self.to_mm, self.feed_mm_min)?;
        field(
            "station_mm",
            self.station_mm,
            Range::new(1.0, 10_000.0, "mm"),
        )?;
        int_field("readings", self.readings, 2, 1000)
    }
}

/// A request's span and the carriage's feed, when given (`follower_map_start`,
/// `follower_level_start`).
fn check_span_and_feed(
    from_mm: Option<f64>,
    to_mm: Option<f64>,
    feed_mm_min: Option<f64>,
) -> Result<(), String> {
    use crate::util::range::{FEED_MM_MIN, POSITION_MM, field};
    field("from_mm", from_mm, POSITION_MM)?;
    field("to_mm", to_mm, POSITION_MM)?;
    field("feed_mm_min", feed_mm_min, FEED_MM_MIN)
}

/// A level's reading beyond this is refused (arcsec): a typing error, not a roll.
pub const LEVEL_LIMIT_ARCSEC: f64 = 1000.0;

/// A level's reading typed by the operator (`arcsec`): a finite number within
/// ±[`LEVEL_LIMIT_ARCSEC`]; the error names the field.
pub fn typed_reading(v: &serde_json::Value) -> Result<f64, String> {
    let x = match v {
        serde_json::Value::Null => {
            return Err("follower_level_reading needs \"arcsec\": the level's reading at the station, a number of arcsec".into());
        }
        v => v.as_f64().ok_or_else(|| {
            format!("\"arcsec\" is {v}: give the level's reading as a number of arcsec")
        })?,
    };
    if !x.is_finite() || x.abs() > LEVEL_LIMIT_ARCSEC {
        return Err(format!(
            "\"arcsec\" is {x}: give the level's reading within ±{LEVEL_LIMIT_ARCSEC:.0}″"
        ));
    }
    Ok(x)
}
