//! The control API's wire types, on their own floor: the requests, the snapshot and the views
//! of the procedures, as the control socket carries them (newline-delimited JSON) and the
//! console and the command line read them. User units (µm, arcsec) at this edge. Nothing here
//! imports the service: the service, the console and the CLI import these.

pub mod follower;
pub mod hexapod;
pub mod machine;
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
    /// A stored run's flagged captures (each with its values, why, and whether it was
    /// retaken or excluded) and the events that could move its reference.
    RunFlags { run_id: i64 },
    /// Exclude flagged capture `flag` of run `run_id` with `reason` (audited): it stays out of
    /// the run, and no longer holds its tables back.
    RunExclude {
        run_id: i64,
        flag: i64,
        reason: String,
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
    TableGenerate {
        run_id: i64,
        /// Write the run's residual as the table even when the tables the PLC applied while
        /// it ran are not recorded (asked for by name: a residual published alone undoes the
        /// compensation it was measured under).
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        residual_only: bool,
    },
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
    /// The newest stored alignment of `axis` ("X" when not given), the one the pre-run check
    /// judges, or null: what a console shows after a restart until the next advice.
    AlignStored {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        axis: Option<String>,
    },
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
    /// The stored machines, newest first (issue 27).
    Machines,
    /// Stored machine `id` (or the newest): its plan set-up by set-up, the squarenesses so far,
    /// the model's predicted volumetric error when every set-up is measured.
    Machine {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        id: Option<i64>,
    },
    /// Store a machine from its record (the TOML text, `commission::record`), or from the
    /// record's file at `path` on the service's host (the console's way); `origin` names it in
    /// errors (its file, say).
    MachineNew {
        #[serde(default, skip_serializing_if = "String::is_empty")]
        record: String,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        path: Option<String>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        origin: Option<String>,
    },
    /// Attach stored run `run_id` to set-up `setup` (1-based) of machine `id`: in the plan's
    /// order, and only a finished run of the set-up's axis over its travel with no flag open.
    MachineAttach { id: i64, setup: usize, run_id: i64 },
    /// Detach the run of set-up `setup` (1-based) of machine `id`, and of every set-up after it.
    MachineDetach { id: i64, setup: usize },
    /// The trends of an axis's finished runs and checks (`service::trends`; `axiscomp trend`
    /// reads the same): `axis`, or the newest finished run's.
    Trend {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        axis: Option<String>,
    },
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
            | Request::RunFlags { .. }
            | Request::Audit { .. }
            | Request::Calibration
            | Request::HexapodStatus
            | Request::TableList { .. }
            | Request::TableStatus
            | Request::AlignStored { .. }
            | Request::FollowerMap { id: None }
            | Request::FollowerMapStatus
            | Request::FollowerLevelStatus
            | Request::Machines
            | Request::Machine { .. }
            | Request::Trend { .. } => Role::Viewer,
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

    /// Every number of the request within its range, or the first that is not, named with
    /// the range (DESIGN §8: bad input gets a clear error that names the input and what to
    /// do). Checked once, right after the line parses, so nothing downstream sees a NaN, an
    /// infinity or a count no machine has; how the numbers fit together (a span's ends, a
    /// plan's targets for its length) is checked where they are used.
    pub fn check(&self) -> Result<(), String> {
        use crate::util::range::{POSITION_MM, Range, field, int_field};
        // Stored runs, tables and maps are numbered from 1.
        let id = |name: &str, v: Option<i64>| match v {
            Some(v) if v < 1 => Err(format!(
                "\"{name}\": {v} is not an id: give a stored one's, 1 or more"
            )),
            _ => Ok(()),
        };
        const LIMIT: usize = 10_000;
        match self {
            Request::Subscribe { hz } => field("hz", *hz, crate::config::SNAPSHOT_HZ),
            Request::Follower { mm, .. } | Request::Nominal { mm } => field("mm", *mm, POSITION_MM),
            Request::RunStart { plan, .. } => plan.check().map_err(|e| e.to_string()),
            Request::Runs { limit } | Request::TableList { limit } => {
                int_field("limit", *limit, 1, LIMIT)
            }
            Request::Audit { limit } => int_field("limit", *limit, 1, LIMIT as u32),
            Request::RunResult { run_id } => id("run_id", *run_id),
            Request::RunFlags { run_id } => id("run_id", Some(*run_id)),
            Request::RunExclude { run_id, flag, .. } => {
                id("run_id", Some(*run_id)).and_then(|_| id("flag", Some(*flag)))
            }
            Request::TableGenerate { run_id, .. } => id("run_id", Some(*run_id)),
            Request::TablePublish { table_id, .. } => id("table_id", Some(*table_id)),
            Request::FollowerMap { id: map } => id("id", *map),
            Request::Machine { id: m } => id("id", *m),
            Request::MachineAttach {
                id: m,
                setup,
                run_id,
            } => {
                id("id", Some(*m))?;
                id("run_id", Some(*run_id))?;
                int_field("setup", Some(*setup), 1, crate::commission::SETUPS.len())
            }
            Request::MachineDetach { id: m, setup } => {
                id("id", Some(*m))?;
                int_field("setup", Some(*setup), 1, crate::commission::SETUPS.len())
            }
            Request::MachineNew { record, path, .. } if record.is_empty() == path.is_none() => {
                Err(
                    "give the machine record as \"record\" (its TOML text) or \"path\" (its file on the service's host), one of them"
                        .into(),
                )
            }
            Request::MachineNew { record, .. } if record.len() > 64 * 1024 => Err(format!(
                "\"record\": {} bytes: a machine record is a short TOML file (64 KiB at most)",
                record.len()
            )),
            Request::HexapodStart { poses, .. } => {
                use hexapod::{MAX_POSES, MIN_POSES};
                int_field("poses", *poses, MIN_POSES, MAX_POSES)
            }
            Request::AlignRead { at_mm } => field("at_mm", *at_mm, POSITION_MM),
            Request::AlignTarget { psd, x, y } => {
                // What a target in front of a PSD shows: within a hand's width of its centre.
                let target = Range::symmetric(100.0, "mm");
                int_field("psd", Some(*psd), 1, 3)?;
                field("x", Some(*x), target)?;
                field("y", Some(*y), target)
            }
            Request::AlignAdvice { from_mm, to_mm, .. } => {
                field("from_mm", Some(*from_mm), POSITION_MM)?;
                field("to_mm", Some(*to_mm), POSITION_MM)
            }
            Request::FollowerMapStart(m) => m.check(),
            Request::FollowerLevelStart(l) => l.check(),
            Request::FollowerLevelReading { arcsec } if !arcsec.is_null() => {
                follower::typed_reading(arcsec).map(drop)
            }
            // No numbers (a new request with numbers must be added above).
            Request::Trend { axis: Some(a) } if !["X", "Y", "Z"].contains(&a.as_str()) => Err(
                format!("\"axis\": \"{a}\" is not an axis: give X, Y or Z (or none: the newest run's)"),
            ),
            Request::Status
            | Request::Zero
            | Request::ClearZero
            | Request::Strategy { .. }
            | Request::RunStatus
            | Request::RunAbort
            | Request::Trend { .. }
            | Request::Calibration
            | Request::CalibrationFit { .. }
            | Request::CalibrationAccept { .. }
            | Request::CalibrationReject
            | Request::HexapodStatus
            | Request::HexapodStop
            | Request::TableStatus
            | Request::AlignClear
            | Request::AlignStored { .. }
            | Request::FollowerCertificate(_)
            | Request::FollowerMapStatus
            | Request::FollowerMapStop
            | Request::FollowerMapFinish
            | Request::FollowerLevelStatus
            | Request::FollowerLevelReading { .. }
            | Request::FollowerLevelStop
            | Request::FollowerLevelFinish
            | Request::Machines
            | Request::MachineNew { .. } => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_machine_comes_as_its_record_or_its_file_one_of_them() {
        let r: Request =
            serde_json::from_str(r#"{"cmd":"machine_new","path":"/etc/axiscomp/vmc.toml"}"#)
                .unwrap();
        assert_eq!(
            r,
            Request::MachineNew {
                record: String::new(),
                path: Some("/etc/axiscomp/vmc.toml".into()),
                origin: None
            }
        );
        assert_eq!((r.needs(), r.check()), (Role::Operator, Ok(())));
        let r: Request =
            serde_json::from_str(r#"{"cmd":"machine_new","record":"name = \"VMC\""}"#).unwrap();
        assert_eq!(r.check(), Ok(()));
        for neither_or_both in [
            r#"{"cmd":"machine_new"}"#,
            r#"{"cmd":"machine_new","record":"name = 1","path":"/m.toml"}"#,
        ] {
            let r: Request = serde_json::from_str(neither_or_both).unwrap();
            let e = r.check().unwrap_err();
            assert!(e.contains("\"record\"") && e.contains("\"path\""), "{e}");
        }
    }

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

    /// One request of each kind with every numeric field given (nested ones too).
    fn numeric_samples() -> Vec<Request> {
        vec![
            Request::Subscribe { hz: Some(10.0) },
            Request::Follower {
                action: FollowerAction::Jog,
                mm: Some(0.5),
            },
            Request::Nominal { mm: Some(12.0) },
            Request::RunStart {
                plan: crate::run::PlanSpec {
                    reference_mm: Some(0.0),
                    ..Default::default()
                },
                dialect: None,
                notes: None,
            },
            Request::Runs { limit: Some(5) },
            Request::RunResult { run_id: Some(1) },
            Request::RunFlags { run_id: 1 },
            Request::RunExclude {
                run_id: 1,
                flag: 1,
                reason: "the carriage was knocked".into(),
            },
            Request::Audit { limit: Some(5) },
            Request::HexapodStart {
                plan: None,
                poses: Some(200),
                out: None,
            },
            Request::TableList { limit: Some(5) },
            Request::TableGenerate {
                run_id: 1,
                residual_only: false,
            },
            Request::TablePublish {
                table_id: 1,
                confirm: false,
            },
            Request::AlignRead { at_mm: Some(0.0) },
            Request::AlignTarget {
                psd: 2,
                x: 1.0,
                y: -1.0,
            },
            Request::AlignAdvice {
                from_mm: 0.0,
                to_mm: 500.0,
                axis: None,
            },
            Request::FollowerMap { id: Some(1) },
            Request::FollowerMapStart(MappingRequest {
                from_mm: Some(0.0),
                to_mm: Some(400.0),
                step_mm: Some(3.75),
                passes: Some(2),
                frames: Some(1000),
                lead_mm: Some(5.0),
                probe_every: Some(13),
                feed_mm_min: Some(2000.0),
                ..Default::default()
            }),
            Request::FollowerLevelStart(LevelRequest {
                from_mm: Some(0.0),
                to_mm: Some(400.0),
                station_mm: Some(100.0),
                readings: Some(20),
                feed_mm_min: Some(2000.0),
                ..Default::default()
            }),
            Request::FollowerLevelReading {
                arcsec: serde_json::json!(1.5),
            },
            Request::Machine { id: Some(1) },
            Request::MachineAttach {
                id: 1,
                setup: 2,
                run_id: 3,
            },
            Request::MachineDetach { id: 1, setup: 4 },
        ]
    }

    /// The JSON paths (object keys) of every number in `v`.
    fn number_paths(v: &serde_json::Value, path: &mut Vec<String>, out: &mut Vec<Vec<String>>) {
        match v {
            serde_json::Value::Number(_) => out.push(path.clone()),
            serde_json::Value::Object(m) => {
                for (k, x) in m {
                    path.push(k.clone());
                    number_paths(x, path, out);
                    path.pop();
                }
            }
            _ => {}
        }
    }

    /// Every numeric field of every request, set in turn to the extremes JSON can carry
    /// (tiny, huge, negative, zero, negative zero, subnormal, the largest integers): the line
    /// is refused by serde (a fraction or a sign an integer field cannot hold), accepted by
    /// `Request::check`, or refused by it naming the field; never a panic.
    #[test]
    fn a_trend_is_asked_for_an_axis_by_its_name() {
        let r: Request = serde_json::from_str(r#"{"cmd":"trend","axis":"X"}"#).expect("parses");
        assert_eq!(
            r,
            Request::Trend {
                axis: Some("X".into())
            }
        );
        assert_eq!(r.check(), Ok(()));
        assert_eq!(r.needs(), Role::Viewer);
        let newest: Request = serde_json::from_str(r#"{"cmd":"trend"}"#).expect("parses");
        assert_eq!(newest.check(), Ok(()));
        let bad = Request::Trend {
            axis: Some("W".into()),
        };
        let e = bad.check().expect_err("W is no axis");
        assert!(e.contains("\"W\" is not an axis: give X, Y or Z"), "{e}");
    }

    #[test]
    fn every_numeric_field_is_range_checked() {
        const EXTREMES: [&str; 11] = [
            "1e-300",
            "1e300",
            "-1",
            "0",
            "-0.0",
            "5e-324",
            "2.2250738585072014e-308",
            "9223372036854775807",
            "-9223372036854775808",
            "18446744073709551615",
            "1.7976931348623157e308",
        ];
        let (mut fields, mut refused) = (0, 0);
        for sample in numeric_samples() {
            assert_eq!(sample.check(), Ok(()), "{sample:?}");
            let v = serde_json::to_value(&sample).unwrap();
            let mut paths = Vec::new();
            number_paths(&v, &mut Vec::new(), &mut paths);
            assert!(!paths.is_empty(), "{v}");
            for path in paths {
                fields += 1;
                let name = path.last().unwrap().clone();
                for x in EXTREMES {
                    let mut w = v.clone();
                    let leaf = path.iter().fold(&mut w, |w, k| &mut w[k.as_str()]);
                    *leaf = serde_json::json!("@X@");
                    let line = w.to_string().replace("\"@X@\"", x);
                    let Ok(r) = serde_json::from_str::<Request>(&line) else {
                        continue;
                    };
                    if let Err(e) = r.check() {
                        refused += 1;
                        assert!(e.contains(&name), "{line}: {e}");
                        assert!(!e.contains("Some("), "{line}: {e}");
                    }
                }
            }
        }
        assert_eq!(fields, 49, "numeric fields covered");
        assert!(refused > 100, "{refused}");
        let r: Request = serde_json::from_str(r#"{"cmd":"subscribe","hz":1e-300}"#).unwrap();
        assert_eq!(
            r.check().unwrap_err(),
            r#""hz": 1e-300 Hz is out of range: use 0.1 to 100 Hz"#
        );
        let r: Request =
            serde_json::from_str(r#"{"cmd":"follower_map_start","frames":5,"passes":2}"#).unwrap();
        assert_eq!(
            r.check().unwrap_err(),
            r#""frames": 5 is out of range: use 10 to 100000"#
        );
        let r: Request = serde_json::from_str(
            r#"{"cmd":"run_start","plan":{"axis":"X","start_mm":0,"end_mm":100,"targets":11,"runs":5,"overrun_mm":2,"dwell_s":1e300,"feed_mm_min":3000,"lead_mm":0}}"#,
        )
        .unwrap();
        assert_eq!(
            r.check().unwrap_err(),
            "test plan: dwell_s: 1e300 s is out of range: use 0 to 3600 s"
        );
        let r: Request = serde_json::from_str(r#"{"cmd":"table_publish","table_id":0}"#).unwrap();
        assert_eq!(
            r.check().unwrap_err(),
            r#""table_id": 0 is not an id: give a stored one's, 1 or more"#
        );
    }
}
