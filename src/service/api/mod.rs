//! The control API's wire types, on their own floor: the requests, the snapshot and the views
//! of the procedures, as the control socket carries them (newline-delimited JSON) and the
//! console and the command line read them. User units (µm, arcsec) at this edge. Nothing here
//! imports the service: the service, the console and the CLI import these.

pub mod follower;
pub mod hexapod;
pub mod snapshot;

use crate::track::Strategy;
use serde::{Deserialize, Serialize};

pub use follower::{
    CertificateImport, FollowerMapView, LevelRequest, LevelView, MappingRequest, MappingView,
    StationView,
};
pub use hexapod::HexapodView;
pub use snapshot::Snapshot;

/// What a peer may do.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    Viewer,
    Operator,
}

/// What the follower should do.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FollowerAction {
    Home,
    Enable,
    Disable,
    /// Relative move by `mm`.
    Jog,
    /// Absolute move to `mm`.
    Move,
    Stop,
    FaultReset,
}

/// A control request.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "cmd", rename_all = "snake_case", deny_unknown_fields)]
pub enum Request {
    /// The current snapshot.
    Status,
    /// A stream of snapshots at `hz` (default: the service's snapshot rate).
    Subscribe {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        hz: Option<f64>,
    },
    /// Command the follower.
    Follower {
        action: FollowerAction,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        mm: Option<f64>,
    },
    /// Take the live errors here as the zero reference (and re-reference the stitching).
    Zero,
    /// Forget the zero reference.
    ClearZero,
    /// Set (or clear, with null) the nominal travel position the carriage is commanded to.
    Nominal { mm: Option<f64> },
    /// Switch the stitching strategy.
    Strategy { strategy: Strategy },
    /// Start an ISO 230-2 run: the plan, optionally another program dialect than configured.
    RunStart {
        plan: crate::run::PlanSpec,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        dialect: Option<String>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        notes: Option<String>,
    },
    /// The active (or last) run's progress.
    RunStatus,
    /// Stop the active run (its captures stay stored).
    RunAbort,
    /// The stored runs, newest first (at most `limit`, default 50).
    Runs {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        limit: Option<usize>,
    },
    /// A stored run's evaluation: the six errors per direction and the ISO figures
    /// (`run_id`, or the newest finished run).
    RunResult {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        run_id: Option<i64>,
    },
    /// The newest entries of the audit log (every operator request, who and when), newest
    /// first (at most `limit`, default 50).
    Audit {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        limit: Option<u32>,
    },
    /// The calibration in use, the one waiting for a decision, whether a fit runs.
    Calibration,
    /// Fit the pose set at `poses` (a CSV on the service's host, `calibrate fit`'s input
    /// format); the result waits for accept or reject.
    CalibrationFit { poses: String },
    /// Store the waiting calibration and decouple with it from now on (the zero is cleared).
    /// A calibration with plausibility concerns (`calibrate::plausible`) is refused unless
    /// `force` is set.
    CalibrationAccept {
        #[serde(default)]
        force: bool,
    },
    /// Drop the waiting calibration.
    CalibrationReject,
    /// Calibrate with the hexapod in the loop (`[hexapod]`): the plan CSV `plan` on the
    /// service's host, or `poses` poses generated over the operating window (200); the run
    /// directory `out` (default: `hexapod-run` in the state directory) resumes when it holds
    /// poses of the same plan. The fit then waits for accept or reject.
    HexapodStart {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        plan: Option<String>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        poses: Option<usize>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        out: Option<String>,
    },
    /// Where the hexapod run is (`api::hexapod::HexapodView`).
    HexapodStatus,
    /// Halt the hexapod and end its run before the next pose (start again to resume).
    HexapodStop,
    /// The stored compensation tables, newest first (at most `limit`, default 50), each with
    /// its latest publication.
    TableList {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        limit: Option<usize>,
    },
    /// Evaluate stored run `run_id`, build its compensation tables for the configured CNC map
    /// and store them: their ids and a summary.
    TableGenerate { run_id: i64 },
    /// Publish stored table `table_id` to the PLC (push, or serve it for pull); refused unless
    /// `confirm` is true. The reply says committed (with the sequence), rejected (with the
    /// PLC's code) or failed (with the reason).
    TablePublish {
        table_id: i64,
        #[serde(default)]
        confirm: bool,
    },
    /// What the PLC holds now, read back and compared with the store.
    TableStatus,
    /// Beam alignment: read the spots as a station with the carriage at rest at `at_mm` (the
    /// measured position when left out).
    AlignRead {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        at_mm: Option<f64>,
    },
    /// What the alignment target in front of PSD `psd` (1..3) shows at the last station (mm),
    /// where the spot is off the PSD.
    AlignTarget { psd: usize, x: f64, y: f64 },
    /// The screw turns, beam angle and check over `from_mm`..`to_mm` from the stations read.
    AlignAdvice {
        from_mm: f64,
        to_mm: f64,
        /// The axis the alignment is stored for ("X" when not given).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        axis: Option<String>,
    },
    /// Forget the stations read (after turning screws, read both ends again).
    AlignClear,
    /// The follower error map in use and the stored ones; with `id`, put stored map `id` in
    /// use first (operators).
    FollowerMap {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        id: Option<i64>,
    },
    /// Import the follower encoder's calibration certificate (`path` on the service's host,
    /// or its `csv` text): stored with its map and, unless `keep_current`, applied at once
    /// (joined with the self-calibration of the map in use when it has one).
    FollowerCertificate(follower::CertificateImport),
    /// Map the follower by the stop-and-go self-calibration (`service::follower_map`): its
    /// part program to the CNC; at the end the map stored and put in use.
    FollowerMapStart(follower::MappingRequest),
    /// Where the follower mapping is (`api::follower::MappingView`).
    FollowerMapStatus,
    /// Stop the follower mapping: nothing is stored.
    FollowerMapStop,
    /// Build the follower map now from the steps so far (with a CNC the service does not
    /// drive, or when enough is enough).
    FollowerMapFinish,
    /// Read a level at stations along the follower's map (`service::follower_level`): at the
    /// end the map refitted with the stations, stored and put in use.
    FollowerLevelStart(follower::LevelRequest),
    /// Where the level stations are (`api::follower::LevelView`).
    FollowerLevelStatus,
    /// The level's reading (arcsec) at the station being read (`[follower] level = "manual"`).
    FollowerLevelReading {
        #[serde(default)]
        arcsec: serde_json::Value,
    },
    /// Stop the level stations: nothing is stored.
    FollowerLevelStop,
    /// Fit the map now with the stations taken (two at least).
    FollowerLevelFinish,
}

impl Request {
    /// The role the request needs.
    pub fn needs(&self) -> Role {
        match self {
            Request::Status
            | Request::Subscribe { .. }
            | Request::RunStatus
            | Request::Runs { .. }
            | Request::RunResult { .. }
            | Request::Audit { .. }
            | Request::Calibration
            | Request::HexapodStatus
            | Request::TableList { .. }
            | Request::TableStatus
            | Request::FollowerMap { id: None }
            | Request::FollowerMapStatus
            | Request::FollowerLevelStatus => Role::Viewer,
            _ => Role::Operator,
        }
    }

    /// Whether the tables task answers it (`service::tables`), not the core.
    pub fn is_table(&self) -> bool {
        matches!(
            self,
            Request::TableList { .. }
                | Request::TableGenerate { .. }
                | Request::TablePublish { .. }
                | Request::TableStatus
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requests_parse_and_name_their_role() {
        let r: Request =
            serde_json::from_str(r#"{"cmd":"follower","action":"jog","mm":0.5}"#).unwrap();
        assert_eq!(
            r,
            Request::Follower {
                action: FollowerAction::Jog,
                mm: Some(0.5)
            }
        );
        assert_eq!(r.needs(), Role::Operator);
        let r: Request = serde_json::from_str(r#"{"cmd":"status"}"#).unwrap();
        assert_eq!(r.needs(), Role::Viewer);
        let r: Request = serde_json::from_str(r#"{"cmd":"run_result","run_id":3}"#).unwrap();
        assert_eq!(r, Request::RunResult { run_id: Some(3) });
        assert_eq!(r.needs(), Role::Viewer);
        let r: Request = serde_json::from_str(r#"{"cmd":"audit","limit":5}"#).unwrap();
        assert_eq!(r, Request::Audit { limit: Some(5) });
        assert_eq!(r.needs(), Role::Viewer);
        let r: Request = serde_json::from_str(r#"{"cmd":"runs"}"#).unwrap();
        assert_eq!(r, Request::Runs { limit: None });
        assert_eq!(r.needs(), Role::Viewer);
        let r: Request =
            serde_json::from_str(r#"{"cmd":"table_publish","table_id":4,"confirm":true}"#).unwrap();
        assert_eq!(
            r,
            Request::TablePublish {
                table_id: 4,
                confirm: true
            }
        );
        assert_eq!((r.needs(), r.is_table()), (Role::Operator, true));
        let r: Request = serde_json::from_str(r#"{"cmd":"table_publish","table_id":4}"#).unwrap();
        assert!(matches!(r, Request::TablePublish { confirm: false, .. }));
        let r: Request = serde_json::from_str(r#"{"cmd":"table_generate","run_id":2}"#).unwrap();
        assert_eq!(r.needs(), Role::Operator);
        for text in [r#"{"cmd":"table_status"}"#, r#"{"cmd":"table_list"}"#] {
            let r: Request = serde_json::from_str(text).unwrap();
            assert_eq!((r.needs(), r.is_table()), (Role::Viewer, true), "{text}");
        }
        assert!(!Request::Zero.is_table());
        let r: Request = serde_json::from_str(r#"{"cmd":"nominal","mm":null}"#).unwrap();
        assert_eq!(r, Request::Nominal { mm: None });
        let r: Request =
            serde_json::from_str(r#"{"cmd":"strategy","strategy":"encoder"}"#).unwrap();
        assert_eq!(
            r,
            Request::Strategy {
                strategy: Strategy::Encoder
            }
        );
        // A misspelt field is refused, not ignored (serde checks fields of struct variants).
        let e = serde_json::from_str::<Request>(r#"{"cmd":"follower","action":"jog","mn":1}"#);
        assert!(e.unwrap_err().to_string().contains("unknown field `mn`"));
        assert!(serde_json::from_str::<Request>(r#"{"cmd":"launch"}"#).is_err());
        let r: Request = serde_json::from_str(
            r#"{"cmd":"follower_map_start","from_mm":0,"to_mm":60,"passes":2}"#,
        )
        .unwrap();
        let Request::FollowerMapStart(mapping) = &r else {
            panic!("{r:?}")
        };
        assert_eq!(
            (
                mapping.from_mm,
                mapping.to_mm,
                mapping.passes,
                mapping.frames
            ),
            (Some(0.0), Some(60.0), Some(2), None)
        );
        assert_eq!(r.needs(), Role::Operator);
        let r: Request = serde_json::from_str(r#"{"cmd":"follower_map_start"}"#).unwrap();
        assert_eq!(r, Request::FollowerMapStart(Default::default()));
        let e = serde_json::from_str::<Request>(r#"{"cmd":"follower_map_start","form_mm":0}"#);
        assert!(
            e.unwrap_err()
                .to_string()
                .contains("unknown field `form_mm`")
        );
        let r: Request = serde_json::from_str(r#"{"cmd":"follower_map_status"}"#).unwrap();
        assert_eq!(r.needs(), Role::Viewer);
        let r: Request =
            serde_json::from_str(r#"{"cmd":"follower_certificate","path":"/tmp/c.csv"}"#).unwrap();
        assert_eq!(
            r,
            Request::FollowerCertificate(crate::service::api::CertificateImport {
                path: Some("/tmp/c.csv".into()),
                ..Default::default()
            })
        );
        // Serialised back flat, as the command line sends it.
        assert_eq!(
            serde_json::to_value(&r).unwrap(),
            serde_json::json!({"cmd": "follower_certificate", "path": "/tmp/c.csv", "keep_current": false})
        );
        assert_eq!(r.needs(), Role::Operator);
    }
}
