//! What the store holds, and the typed operations on each table.

use super::{Store, StoreError, now_us};
use crate::calibrate::file::CalibrationFile;
use crate::run::{Capture, Direction, TargetKey};
use crate::track::{HandoverKind, HandoverRecord};
use crate::units::Errors6;
use rusqlite::types::{FromSql, FromSqlError, FromSqlResult, ToSqlOutput, ValueRef};
use rusqlite::{OptionalExtension, Row, ToSql, params};
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;
use std::fmt;

/// SQLite's extended code for a foreign-key violation.
pub(super) const CONSTRAINT_FOREIGNKEY: i32 = 787;

macro_rules! id_type {
    ($(#[$m:meta])* $name:ident) => {
        $(#[$m])*
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
        #[serde(transparent)]
        pub struct $name(pub i64);

        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                write!(f, "{}", self.0)
            }
        }
    };
}

id_type!(
    /// A run's row id.
    RunId
);
id_type!(
    /// A calibration's row id.
    CalibrationId
);
id_type!(
    /// A compensation table's row id.
    TableId
);

// ---------------------------------------------------------------------------------------------
// Runs

/// Where a run is in its life. `finished` is final; `aborted` and `failed` runs may be resumed
/// (back to `running`); nothing goes back to `planned`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RunState {
    Planned,
    Running,
    Finished,
    Aborted,
    Failed,
}

impl RunState {
    /// All states, in life order.
    pub const ALL: [RunState; 5] = [
        RunState::Planned,
        RunState::Running,
        RunState::Finished,
        RunState::Aborted,
        RunState::Failed,
    ];

    /// The stored text.
    pub fn as_str(self) -> &'static str {
        match self {
            RunState::Planned => "planned",
            RunState::Running => "running",
            RunState::Finished => "finished",
            RunState::Aborted => "aborted",
            RunState::Failed => "failed",
        }
    }

    /// Parse the stored text.
    pub fn parse(s: &str) -> Option<RunState> {
        Self::ALL.into_iter().find(|st| st.as_str() == s)
    }

    /// Whether a run in this state may be set to `to`. Setting the same state again is
    /// allowed (it only touches `updated`), except for leaving `finished`.
    pub fn may_become(self, to: RunState) -> bool {
        use RunState::*;
        match (self, to) {
            (_, Planned) => self == Planned,
            (Finished, _) => to == Finished,
            (Planned, Running | Aborted | Failed) => true,
            (Planned, Finished) => false,
            (Running, _) => true,
            (Aborted | Failed, Running) => true,
            (Aborted | Failed, _) => self == to,
        }
    }
}

impl fmt::Display for RunState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl ToSql for RunState {
    fn to_sql(&self) -> rusqlite::Result<ToSqlOutput<'_>> {
        Ok(ToSqlOutput::from(self.as_str()))
    }
}

impl FromSql for RunState {
    fn column_result(value: ValueRef<'_>) -> FromSqlResult<Self> {
        let s = value.as_str()?;
        RunState::parse(s)
            .ok_or_else(|| FromSqlError::Other(format!("unknown run state {s:?}").into()))
    }
}

/// A run to create. `plan` and `config` are JSON snapshots (the run module's plan and the
/// validated configuration), kept as they were when the run was made.
#[derive(Clone, Debug, PartialEq)]
pub struct NewRun {
    /// The machine axis under test (its name in the axis mapping).
    pub axis: String,
    pub plan: serde_json::Value,
    pub config: serde_json::Value,
    /// The calibration the head used, when it is in the store.
    pub calibration: Option<CalibrationId>,
    pub notes: String,
}

/// A stored run.
#[derive(Clone, Debug, PartialEq)]
pub struct RunRecord {
    pub id: RunId,
    /// Stamped by the store (µs since the Unix epoch).
    pub created_us: i64,
    pub updated_us: i64,
    pub state: RunState,
    pub axis: String,
    pub plan: serde_json::Value,
    pub config: serde_json::Value,
    pub calibration: Option<CalibrationId>,
    pub notes: String,
}

impl RunRecord {
    /// Its machine time (s): from its start to its last change of state (for an ended run,
    /// its end), pauses and any restart of the service included.
    pub fn machine_time_s(&self) -> f64 {
        (self.updated_us - self.created_us).max(0) as f64 * 1e-6
    }
}

const RUN_COLUMNS: &str =
    "id, created_us, updated_us, state, axis, plan_json, config_json, calibration_id, notes";

struct RawRun {
    id: i64,
    created_us: i64,
    updated_us: i64,
    state: RunState,
    axis: String,
    plan: String,
    config: String,
    calibration: Option<i64>,
    notes: String,
}

fn raw_run(r: &Row<'_>) -> rusqlite::Result<RawRun> {
    Ok(RawRun {
        id: r.get(0)?,
        created_us: r.get(1)?,
        updated_us: r.get(2)?,
        state: r.get(3)?,
        axis: r.get(4)?,
        plan: r.get(5)?,
        config: r.get(6)?,
        calibration: r.get(7)?,
        notes: r.get(8)?,
    })
}

// ---------------------------------------------------------------------------------------------
// Captures

/// A `Direction` as its stored sign.
pub(super) struct Sign(pub(super) Direction);

impl ToSql for Sign {
    fn to_sql(&self) -> rusqlite::Result<ToSqlOutput<'_>> {
        Ok(ToSqlOutput::from(self.0.sign()))
    }
}

impl FromSql for Sign {
    fn column_result(value: ValueRef<'_>) -> FromSqlResult<Self> {
        match value.as_str()? {
            "+" => Ok(Sign(Direction::Up)),
            "-" => Ok(Sign(Direction::Down)),
            s => Err(FromSqlError::Other(
                format!("unknown direction {s:?}").into(),
            )),
        }
    }
}

const CAPTURE_COLUMNS: &str = "run, target_index, target_mm, direction, \
    dx_mm, dy_mm, dz_mm, ex_rad, ey_rad, ez_rad, \
    sd_dx_mm, sd_dy_mm, sd_dz_mm, sd_ex_rad, sd_ey_rad, sd_ez_rad, \
    u_dx_mm, u_dy_mm, u_dz_mm, u_ex_rad, u_ey_rad, u_ez_rad, \
    frames, material_c, air_c, unix_us";

fn errors6_at(r: &Row<'_>, first: usize) -> rusqlite::Result<Errors6> {
    let mut a = [0.0; 6];
    for (k, v) in a.iter_mut().enumerate() {
        *v = r.get(first + k)?;
    }
    Ok(Errors6::from_array(a))
}

fn capture_row(r: &Row<'_>) -> rusqlite::Result<Capture> {
    Ok(Capture {
        run: r.get(0)?,
        target_index: r.get(1)?,
        target_mm: r.get(2)?,
        direction: r.get::<_, Sign>(3)?.0,
        errors: errors6_at(r, 4)?,
        frame_sd: errors6_at(r, 10)?,
        u: errors6_at(r, 16)?,
        frames: r.get(22)?,
        material_c: r.get(23)?,
        air_c: r.get(24)?,
        unix_us: r.get(25)?,
    })
}

fn validate_capture(c: &Capture) -> Result<(), StoreError> {
    let bad = |problem: String| StoreError::Invalid {
        what: "capture",
        problem,
    };
    if c.run < 1 {
        return Err(bad("run numbers start at 1".into()));
    }
    if !c.target_mm.is_finite() {
        return Err(bad(format!(
            "target position {} is not finite",
            c.target_mm
        )));
    }
    for (label, e, non_negative) in [
        ("mean", c.errors, false),
        ("frame standard deviation", c.frame_sd, true),
        ("standard uncertainty", c.u, true),
    ] {
        for (name, v) in crate::units::DOF_NAMES.iter().zip(e.to_array()) {
            if !v.is_finite() || (non_negative && v < 0.0) {
                return Err(bad(format!(
                    "{label} of {name} is {v} at target {} ({}) of run {}",
                    c.target_index,
                    c.direction.sign(),
                    c.run
                )));
            }
        }
    }
    for (name, t) in [("material", c.material_c), ("air", c.air_c)] {
        if t.is_some_and(|t| !t.is_finite()) {
            return Err(bad(format!("{name} temperature is not finite")));
        }
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Handovers

/// A stored handover.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StoredHandover {
    pub id: i64,
    /// The run it was taken in; `None` when taken outside a run (e.g. while aligning).
    pub run: Option<RunId>,
    pub record: HandoverRecord,
}

fn kind_str(k: HandoverKind) -> &'static str {
    match k {
        HandoverKind::Overlap => "overlap",
        HandoverKind::Encoder => "encoder",
    }
}

/// A `HandoverKind` as its stored text.
struct Kind(HandoverKind);

impl FromSql for Kind {
    fn column_result(value: ValueRef<'_>) -> FromSqlResult<Self> {
        match value.as_str()? {
            "overlap" => Ok(Kind(HandoverKind::Overlap)),
            "encoder" => Ok(Kind(HandoverKind::Encoder)),
            s => Err(FromSqlError::Other(
                format!("unknown handover kind {s:?}").into(),
            )),
        }
    }
}

const HANDOVER_COLUMNS: &str = "id, run_id, unix_us, kind, before_x2_mm, before_y2_mm, \
    after_x2_mm, after_y2_mm, n_before, n_after, sd_x2_mm, sd_y2_mm, encoder_before_mm, \
    encoder_after_mm, delta_along_mm, delta_across_mm, var_along_mm2, var_across_mm2";

/// A non-negative count stored as INTEGER.
fn count_at(r: &Row<'_>, idx: usize) -> rusqlite::Result<usize> {
    let v: i64 = r.get(idx)?;
    usize::try_from(v).map_err(|e| {
        rusqlite::Error::FromSqlConversionFailure(idx, rusqlite::types::Type::Integer, Box::new(e))
    })
}

fn handover_row(r: &Row<'_>) -> rusqlite::Result<StoredHandover> {
    Ok(StoredHandover {
        id: r.get(0)?,
        run: r.get::<_, Option<i64>>(1)?.map(RunId),
        record: HandoverRecord {
            unix_us: r.get(2)?,
            kind: r.get::<_, Kind>(3)?.0,
            before: [r.get(4)?, r.get(5)?],
            after: [r.get(6)?, r.get(7)?],
            n_before: count_at(r, 8)?,
            n_after: count_at(r, 9)?,
            frame_sd: [r.get(10)?, r.get(11)?],
            encoder_before: r.get(12)?,
            encoder_after: r.get(13)?,
            delta: [r.get(14)?, r.get(15)?],
            variance: [r.get(16)?, r.get(17)?],
        },
    })
}

// ---------------------------------------------------------------------------------------------
// Calibrations

/// Figures copied out of a calibration file when it is stored (the file's user units).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CalibrationSummary {
    /// `[meta] created`.
    pub file_created: String,
    pub layout_hash: String,
    pub poses: u32,
    pub rank: u32,
    pub condition_number: f64,
    /// Residual RMS per reading X1..Y3 (µm).
    pub residual_rms_um: [f64; 6],
    /// Hold-out RMS per DOF (µm, arcsec), when the calibration had a hold-out set.
    pub holdout_rms: Option<[f64; 6]>,
}

impl CalibrationSummary {
    /// The summary of a parsed calibration file.
    pub fn of(file: &CalibrationFile) -> Result<CalibrationSummary, StoreError> {
        let count = |what: &'static str, n: usize| {
            u32::try_from(n).map_err(|_| StoreError::Invalid {
                what: "calibration file",
                problem: format!("{what} = {n} is out of range"),
            })
        };
        Ok(CalibrationSummary {
            file_created: file.meta.created.clone(),
            layout_hash: file.meta.layout_hash.clone(),
            poses: count("poses", file.meta.poses)?,
            rank: count("rank", file.linear.rank)?,
            condition_number: file.linear.condition_number,
            residual_rms_um: file.linear.residual_rms_um,
            holdout_rms: file.linear.holdout_rms,
        })
    }
}

/// A stored calibration: the file as given and its summary.
#[derive(Clone, Debug, PartialEq)]
pub struct CalibrationRecord {
    pub id: CalibrationId,
    /// When it was stored (µs since the Unix epoch).
    pub created_us: i64,
    pub file_text: String,
    pub summary: CalibrationSummary,
}

const CALIBRATION_COLUMNS: &str = "id, created_us, file_text, file_created, layout_hash, poses, \
    rank, condition_number, residual_rms_um, holdout_rms";

struct RawCalibration {
    id: i64,
    created_us: i64,
    file_text: String,
    file_created: String,
    layout_hash: String,
    poses: u32,
    rank: u32,
    condition_number: f64,
    residual: String,
    holdout: Option<String>,
}

fn raw_calibration(r: &Row<'_>) -> rusqlite::Result<RawCalibration> {
    Ok(RawCalibration {
        id: r.get(0)?,
        created_us: r.get(1)?,
        file_text: r.get(2)?,
        file_created: r.get(3)?,
        layout_hash: r.get(4)?,
        poses: r.get(5)?,
        rank: r.get(6)?,
        condition_number: r.get(7)?,
        residual: r.get(8)?,
        holdout: r.get(9)?,
    })
}

// ---------------------------------------------------------------------------------------------
// Tables, publications, audit

/// A compensation table to store (DESIGN §7).
#[derive(Clone, Debug, PartialEq)]
pub struct TableEntry {
    /// What it compensates, as `comp` names it (e.g. "positioning", "straightness").
    pub kind: String,
    /// The machine axis it is for.
    pub axis: String,
    /// The approach direction it applies to; `None` for both.
    pub direction: Option<Direction>,
    /// When it was generated (µs since the Unix epoch).
    pub generated_us: i64,
    /// The run it was computed from.
    pub source_run: Option<RunId>,
    /// The values, as `comp` serialises them.
    pub values: serde_json::Value,
    /// CRC-32/ISO-HDLC of the payload as published.
    pub crc: u32,
}

/// A stored compensation table.
#[derive(Clone, Debug, PartialEq)]
pub struct TableRecord {
    pub id: TableId,
    pub entry: TableEntry,
}

/// What the PLC made of a publication.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase", tag = "result")]
pub enum PublicationOutcome {
    /// The PLC echoed the sequence as accepted.
    Accepted,
    /// The PLC answered and refused it (e.g. CRC mismatch, out of range).
    Rejected { code: Option<i64>, text: String },
    /// No answer or the link failed (timeout, Modbus exception, read-back mismatch).
    Failed { code: Option<i64>, text: String },
}

impl PublicationOutcome {
    fn parts(&self) -> (&'static str, Option<i64>, Option<&str>) {
        match self {
            PublicationOutcome::Accepted => ("accepted", None, None),
            PublicationOutcome::Rejected { code, text } => ("rejected", *code, Some(text)),
            PublicationOutcome::Failed { code, text } => ("failed", *code, Some(text)),
        }
    }
}

/// One attempt to publish a table.
#[derive(Clone, Debug, PartialEq)]
pub struct Publication {
    pub table: TableId,
    /// The PLC (plc-map name) it went to.
    pub target: String,
    /// The sequence number written with the commit word.
    pub sequence: u32,
    pub outcome: PublicationOutcome,
    /// When the outcome was known (µs since the Unix epoch).
    pub unix_us: i64,
}

/// A stored publication.
#[derive(Clone, Debug, PartialEq)]
pub struct PublicationRecord {
    pub id: i64,
    pub publication: Publication,
}

/// Who did something: the control socket's peer credentials, when there was a peer.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Actor {
    pub uid: Option<u32>,
    pub user: Option<String>,
    pub pid: Option<i32>,
}

/// One audit entry.
#[derive(Clone, Debug, PartialEq)]
pub struct AuditEntry {
    pub unix_us: i64,
    pub who: Actor,
    /// The role it acted in ("operator", "viewer", "service", "plc", ...).
    pub role: String,
    /// What was done ("start-run", "publish", ...).
    pub action: String,
    pub details: serde_json::Value,
    /// What became of it.
    pub outcome: AuditOutcome,
}

/// What became of an audited request.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub enum AuditOutcome {
    /// Written before it was handled (entries from before outcomes were kept, and the
    /// service's own records).
    #[default]
    Recorded,
    /// Carried out.
    Done,
    /// Refused, with the reason given.
    Refused(String),
}

impl AuditOutcome {
    /// The stored word.
    pub fn as_str(&self) -> &'static str {
        match self {
            AuditOutcome::Recorded => "recorded",
            AuditOutcome::Done => "done",
            AuditOutcome::Refused(_) => "refused",
        }
    }

    /// The reason of a refusal.
    pub fn reason(&self) -> Option<&str> {
        match self {
            AuditOutcome::Refused(r) => Some(r),
            _ => None,
        }
    }
}

/// A stored audit entry.
#[derive(Clone, Debug, PartialEq)]
pub struct AuditRecord {
    pub id: i64,
    pub entry: AuditEntry,
}

fn json_text(what: &'static str, v: &serde_json::Value) -> Result<String, StoreError> {
    serde_json::to_string(v).map_err(|e| StoreError::Invalid {
        what,
        problem: e.to_string(),
    })
}

fn direction_text(d: Option<Direction>) -> &'static str {
    d.map_or("both", Direction::sign)
}

fn to_i64(what: &'static str, n: usize) -> Result<i64, StoreError> {
    i64::try_from(n).map_err(|_| StoreError::Invalid {
        what,
        problem: format!("{n} is out of range"),
    })
}

// ---------------------------------------------------------------------------------------------

impl Store {
    /// Map a write error, turning a foreign-key violation into `missing`.
    fn write_fail(
        &self,
        what: &'static str,
        e: rusqlite::Error,
        missing: StoreError,
    ) -> StoreError {
        if e.sqlite_error()
            .is_some_and(|s| s.extended_code == CONSTRAINT_FOREIGNKEY)
        {
            missing
        } else {
            self.fail(what, e)
        }
    }

    fn json(&self, what: &'static str, text: &str) -> Result<serde_json::Value, StoreError> {
        serde_json::from_str(text).map_err(|e| self.decode(what, e))
    }

    // ----- runs

    /// Create a run in state `planned`.
    pub fn create_run(&mut self, run: &NewRun) -> Result<RunId, StoreError> {
        let plan = json_text("run plan", &run.plan)?;
        let config = json_text("run configuration", &run.config)?;
        let now = now_us();
        let missing = StoreError::NoSuchCalibration(run.calibration.unwrap_or(CalibrationId(0)));
        self.conn
            .execute(
                "INSERT INTO runs (created_us, updated_us, state, axis, plan_json, config_json, \
                 calibration_id, notes) VALUES (?1, ?1, ?2, ?3, ?4, ?5, ?6, ?7)",
                params![
                    now,
                    RunState::Planned,
                    run.axis,
                    plan,
                    config,
                    run.calibration.map(|c| c.0),
                    run.notes
                ],
            )
            .map_err(|e| self.write_fail("create a run", e, missing))?;
        Ok(RunId(self.conn.last_insert_rowid()))
    }

    fn run_from_raw(&self, raw: RawRun) -> Result<RunRecord, StoreError> {
        Ok(RunRecord {
            id: RunId(raw.id),
            created_us: raw.created_us,
            updated_us: raw.updated_us,
            state: raw.state,
            axis: raw.axis,
            plan: self.json("run plan", &raw.plan)?,
            config: self.json("run configuration", &raw.config)?,
            calibration: raw.calibration.map(CalibrationId),
            notes: raw.notes,
        })
    }

    /// One run.
    pub fn run(&self, id: RunId) -> Result<RunRecord, StoreError> {
        let raw = self
            .conn
            .query_row(
                &format!("SELECT {RUN_COLUMNS} FROM runs WHERE id = ?1"),
                [id.0],
                raw_run,
            )
            .optional()
            .map_err(|e| self.fail("read a run", e))?
            .ok_or(StoreError::NoSuchRun(id))?;
        self.run_from_raw(raw)
    }

    fn query_runs(&self, filter: Option<RunState>) -> Result<Vec<RunRecord>, StoreError> {
        let what = "list runs";
        let mut stmt = self
            .conn
            .prepare_cached(&format!(
                "SELECT {RUN_COLUMNS} FROM runs WHERE ?1 IS NULL OR state = ?1 ORDER BY id"
            ))
            .map_err(|e| self.fail(what, e))?;
        let raws = stmt
            .query_map([filter], raw_run)
            .and_then(|rows| rows.collect::<rusqlite::Result<Vec<_>>>())
            .map_err(|e| self.fail(what, e))?;
        raws.into_iter().map(|r| self.run_from_raw(r)).collect()
    }

    /// All runs, oldest first.
    pub fn list_runs(&self) -> Result<Vec<RunRecord>, StoreError> {
        self.query_runs(None)
    }

    /// The runs in `state`, oldest first (e.g. `running` at start-up: runs to resume).
    pub fn runs_in_state(&self, state: RunState) -> Result<Vec<RunRecord>, StoreError> {
        self.query_runs(Some(state))
    }

    /// Move a run to `to` (see `RunState::may_become`), stamping `updated`.
    /// Date a run measured on another clock (the twin's simulated one) as that clock read its
    /// start and end (µs since the Unix epoch).
    pub fn set_run_times(
        &mut self,
        id: RunId,
        created_us: i64,
        updated_us: i64,
    ) -> Result<(), StoreError> {
        let path = self.label();
        let n = self
            .conn
            .execute(
                "UPDATE runs SET created_us = ?2, updated_us = ?3 WHERE id = ?1",
                params![id.0, created_us, updated_us],
            )
            .map_err(|e| super::classify(&path, "date a run", e))?;
        if n == 0 {
            return Err(StoreError::NoSuchRun(id));
        }
        Ok(())
    }

    pub fn set_run_state(&mut self, id: RunId, to: RunState) -> Result<(), StoreError> {
        let what = "change a run's state";
        let path = self.label();
        let fail = |e| super::classify(&path, what, e);
        let tx = self.conn.transaction().map_err(fail)?;
        let from: RunState = tx
            .query_row("SELECT state FROM runs WHERE id = ?1", [id.0], |r| r.get(0))
            .optional()
            .map_err(fail)?
            .ok_or(StoreError::NoSuchRun(id))?;
        if !from.may_become(to) {
            return Err(StoreError::StateTransition { run: id, from, to });
        }
        tx.execute(
            "UPDATE runs SET state = ?2, updated_us = ?3 WHERE id = ?1",
            params![id.0, to, now_us()],
        )
        .map_err(fail)?;
        tx.commit().map_err(fail)
    }

    /// Replace a run's notes, stamping `updated`.
    pub fn set_run_notes(&mut self, id: RunId, notes: &str) -> Result<(), StoreError> {
        let n = self
            .conn
            .execute(
                "UPDATE runs SET notes = ?2, updated_us = ?3 WHERE id = ?1",
                params![id.0, notes, now_us()],
            )
            .map_err(|e| self.fail("change a run's notes", e))?;
        if n == 0 {
            return Err(StoreError::NoSuchRun(id));
        }
        Ok(())
    }

    /// Set `key` of a run's configuration snapshot (an object) to `value`, keeping the rest;
    /// `updated` is not stamped (the run's dates are its measurement's). For what a run's
    /// record gains after it was created (the lab's budget inputs, known once it has run).
    pub fn set_run_config_key(
        &mut self,
        id: RunId,
        key: &str,
        value: serde_json::Value,
    ) -> Result<(), StoreError> {
        let what = "change a run's configuration";
        let path = self.label();
        let fail = |e| super::classify(&path, what, e);
        let tx = self.conn.transaction().map_err(fail)?;
        let text: String = tx
            .query_row("SELECT config_json FROM runs WHERE id = ?1", [id.0], |r| {
                r.get(0)
            })
            .optional()
            .map_err(fail)?
            .ok_or(StoreError::NoSuchRun(id))?;
        let mut config: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| StoreError::Invalid {
                what: "run configuration",
                problem: e.to_string(),
            })?;
        match config.as_object_mut() {
            Some(o) => {
                o.insert(key.to_string(), value);
            }
            None => {
                return Err(StoreError::Invalid {
                    what: "run configuration",
                    problem: format!("run {} has a configuration that is not an object", id.0),
                });
            }
        }
        tx.execute(
            "UPDATE runs SET config_json = ?2 WHERE id = ?1",
            params![id.0, json_text("run configuration", &config)?],
        )
        .map_err(fail)?;
        tx.commit().map_err(fail)
    }

    // ----- captures

    /// Store a capture of run `run`: `Ok(true)` when stored, `Ok(false)` when a capture with the
    /// same key (`TargetKey`) is already there — that one is kept, so a resumed run may offer
    /// its last capture again. One statement, one transaction: it is committed and synced to
    /// disk before this returns. Non-finite values, and negative standard deviations or
    /// uncertainties, are refused (`Invalid`) before anything is written.
    pub fn insert_capture(&mut self, run: RunId, c: &Capture) -> Result<bool, StoreError> {
        validate_capture(c)?;
        let (e, sd, u) = (c.errors.to_array(), c.frame_sd.to_array(), c.u.to_array());
        let sql = format!(
            "INSERT INTO captures (run_id, {CAPTURE_COLUMNS}) VALUES (?1, ?2, ?3, ?4, ?5, \
             ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16, ?17, ?18, ?19, ?20, ?21, ?22, \
             ?23, ?24, ?25, ?26, ?27) \
             ON CONFLICT (run_id, run, target_index, direction) DO NOTHING"
        );
        let n = self
            .conn
            .prepare_cached(&sql)
            .and_then(|mut stmt| {
                stmt.execute(params![
                    run.0,
                    c.run,
                    c.target_index,
                    c.target_mm,
                    Sign(c.direction),
                    e[0],
                    e[1],
                    e[2],
                    e[3],
                    e[4],
                    e[5],
                    sd[0],
                    sd[1],
                    sd[2],
                    sd[3],
                    sd[4],
                    sd[5],
                    u[0],
                    u[1],
                    u[2],
                    u[3],
                    u[4],
                    u[5],
                    c.frames,
                    c.material_c,
                    c.air_c,
                    c.unix_us
                ])
            })
            .map_err(|err| self.write_fail("store a capture", err, StoreError::NoSuchRun(run)))?;
        Ok(n == 1)
    }

    /// A run's captures, in the order they were stored (the order they were taken), each
    /// with its u in force: the newest restatement's (`Store::restate_capture`), else as taken.
    pub fn captures(&self, run: RunId) -> Result<Vec<Capture>, StoreError> {
        let what = "read captures";
        let columns: Vec<String> = CAPTURE_COLUMNS
            .split(',')
            .map(str::trim)
            .map(|col| {
                if col.starts_with("u_") {
                    format!("COALESCE(r.{col}, c.{col})")
                } else {
                    format!("c.{col}")
                }
            })
            .collect();
        let mut stmt = self
            .conn
            .prepare_cached(&format!(
                "SELECT {} FROM captures c LEFT JOIN capture_restatements r ON r.id = \
                 (SELECT max(x.id) FROM capture_restatements x WHERE x.run_id = c.run_id \
                 AND x.run = c.run AND x.target_index = c.target_index \
                 AND x.direction = c.direction AND x.capture_us = c.unix_us) \
                 WHERE c.run_id = ?1 ORDER BY c.id",
                columns.join(", ")
            ))
            .map_err(|e| self.fail(what, e))?;
        stmt.query_map([run.0], capture_row)
            .and_then(|rows| rows.collect())
            .map_err(|e| self.fail(what, e))
    }

    /// The keys of a run's stored captures: a resumed run skips these and continues at the
    /// first target of its plan that is not in the set.
    pub fn completed_keys(&self, run: RunId) -> Result<BTreeSet<TargetKey>, StoreError> {
        let what = "read completed captures";
        let mut stmt = self
            .conn
            .prepare_cached("SELECT run, target_index, direction FROM captures WHERE run_id = ?1")
            .map_err(|e| self.fail(what, e))?;
        stmt.query_map([run.0], |r| {
            Ok(TargetKey {
                run: r.get(0)?,
                target_index: r.get(1)?,
                direction: r.get::<_, Sign>(2)?.0,
            })
        })
        .and_then(|rows| rows.collect())
        .map_err(|e| self.fail(what, e))
    }

    // ----- handovers

    /// Store a follower handover, during run `run` or outside any run (`None`).
    pub fn insert_handover(
        &mut self,
        run: Option<RunId>,
        h: &HandoverRecord,
    ) -> Result<i64, StoreError> {
        let values = [
            h.before[0],
            h.before[1],
            h.after[0],
            h.after[1],
            h.frame_sd[0],
            h.frame_sd[1],
            h.encoder_before,
            h.encoder_after,
            h.delta[0],
            h.delta[1],
            h.variance[0],
            h.variance[1],
        ];
        if let Some(v) = values.iter().find(|v| !v.is_finite()) {
            return Err(StoreError::Invalid {
                what: "handover",
                problem: format!("value {v} is not finite"),
            });
        }
        let n_before = to_i64("handover frame count", h.n_before)?;
        let n_after = to_i64("handover frame count", h.n_after)?;
        let missing = StoreError::NoSuchRun(run.unwrap_or(RunId(0)));
        self.conn
            .execute(
                &format!(
                    "INSERT INTO handovers ({}) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, \
                     ?11, ?12, ?13, ?14, ?15, ?16, ?17)",
                    &HANDOVER_COLUMNS["id, ".len()..]
                ),
                params![
                    run.map(|r| r.0),
                    h.unix_us,
                    kind_str(h.kind),
                    values[0],
                    values[1],
                    values[2],
                    values[3],
                    n_before,
                    n_after,
                    values[4],
                    values[5],
                    values[6],
                    values[7],
                    values[8],
                    values[9],
                    values[10],
                    values[11]
                ],
            )
            .map_err(|e| self.write_fail("store a handover", e, missing))?;
        Ok(self.conn.last_insert_rowid())
    }

    /// The handovers of run `run` (`Some`), or those taken outside any run (`None`), in time
    /// order.
    pub fn handovers(&self, run: Option<RunId>) -> Result<Vec<StoredHandover>, StoreError> {
        let what = "read handovers";
        let mut stmt = self
            .conn
            .prepare_cached(&format!(
                "SELECT {HANDOVER_COLUMNS} FROM handovers WHERE run_id IS ?1 \
                 ORDER BY unix_us, id"
            ))
            .map_err(|e| self.fail(what, e))?;
        stmt.query_map([run.map(|r| r.0)], handover_row)
            .and_then(|rows| rows.collect())
            .map_err(|e| self.fail(what, e))
    }

    // ----- calibrations

    /// Store a calibration file (its text, verbatim). The text must parse as a calibration
    /// file: the summary is taken from it.
    pub fn insert_calibration(&mut self, file_text: &str) -> Result<CalibrationId, StoreError> {
        let file = CalibrationFile::parse(file_text, "calibration to store").map_err(|e| {
            StoreError::Invalid {
                what: "calibration file",
                problem: e.to_string(),
            }
        })?;
        let s = CalibrationSummary::of(&file)?;
        let residual =
            serde_json::to_string(&s.residual_rms_um).map_err(|e| StoreError::Invalid {
                what: "calibration residuals",
                problem: e.to_string(),
            })?;
        let holdout = s
            .holdout_rms
            .map(|h| serde_json::to_string(&h))
            .transpose()
            .map_err(|e| StoreError::Invalid {
                what: "calibration hold-out RMS",
                problem: e.to_string(),
            })?;
        self.conn
            .execute(
                "INSERT INTO calibrations (created_us, file_text, file_created, layout_hash, \
                 poses, rank, condition_number, residual_rms_um, holdout_rms) \
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)",
                params![
                    now_us(),
                    file_text,
                    s.file_created,
                    s.layout_hash,
                    s.poses,
                    s.rank,
                    s.condition_number,
                    residual,
                    holdout
                ],
            )
            .map_err(|e| self.fail("store a calibration", e))?;
        Ok(CalibrationId(self.conn.last_insert_rowid()))
    }

    fn calibration_from_raw(&self, raw: RawCalibration) -> Result<CalibrationRecord, StoreError> {
        let what = "calibration summary";
        let residual_rms_um: [f64; 6] =
            serde_json::from_str(&raw.residual).map_err(|e| self.decode(what, e))?;
        let holdout_rms = raw
            .holdout
            .map(|h| serde_json::from_str::<[f64; 6]>(&h))
            .transpose()
            .map_err(|e| self.decode(what, e))?;
        Ok(CalibrationRecord {
            id: CalibrationId(raw.id),
            created_us: raw.created_us,
            file_text: raw.file_text,
            summary: CalibrationSummary {
                file_created: raw.file_created,
                layout_hash: raw.layout_hash,
                poses: raw.poses,
                rank: raw.rank,
                condition_number: raw.condition_number,
                residual_rms_um,
                holdout_rms,
            },
        })
    }

    fn query_calibrations(
        &self,
        sql_tail: &str,
        param: Option<&dyn ToSql>,
    ) -> Result<Vec<CalibrationRecord>, StoreError> {
        let what = "read calibrations";
        let mut stmt = self
            .conn
            .prepare_cached(&format!(
                "SELECT {CALIBRATION_COLUMNS} FROM calibrations {sql_tail}"
            ))
            .map_err(|e| self.fail(what, e))?;
        let rows = match param {
            Some(p) => stmt.query_map([p], raw_calibration),
            None => stmt.query_map([], raw_calibration),
        };
        let raws = rows
            .and_then(|rows| rows.collect::<rusqlite::Result<Vec<_>>>())
            .map_err(|e| self.fail(what, e))?;
        raws.into_iter()
            .map(|r| self.calibration_from_raw(r))
            .collect()
    }

    /// All calibrations, oldest first.
    pub fn calibrations(&self) -> Result<Vec<CalibrationRecord>, StoreError> {
        self.query_calibrations("ORDER BY id", None)
    }

    /// One calibration.
    pub fn calibration(&self, id: CalibrationId) -> Result<CalibrationRecord, StoreError> {
        self.query_calibrations("WHERE id = ?1", Some(&id.0))?
            .pop()
            .ok_or(StoreError::NoSuchCalibration(id))
    }

    /// The newest calibration made for the layout with `layout_hash`.
    pub fn latest_calibration(
        &self,
        layout_hash: &str,
    ) -> Result<Option<CalibrationRecord>, StoreError> {
        Ok(self
            .query_calibrations(
                "WHERE layout_hash = ?1 ORDER BY id DESC LIMIT 1",
                Some(&layout_hash),
            )?
            .pop())
    }

    // ----- tables

    /// Store a compensation table.
    pub fn insert_table(&mut self, t: &TableEntry) -> Result<TableId, StoreError> {
        if t.kind.is_empty() {
            return Err(StoreError::Invalid {
                what: "compensation table",
                problem: "its kind is empty".into(),
            });
        }
        let values = json_text("table values", &t.values)?;
        let missing = StoreError::NoSuchRun(t.source_run.unwrap_or(RunId(0)));
        self.conn
            .execute(
                "INSERT INTO tables (kind, axis, direction, generated_us, source_run_id, \
                 values_json, crc) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)",
                params![
                    t.kind,
                    t.axis,
                    direction_text(t.direction),
                    t.generated_us,
                    t.source_run.map(|r| r.0),
                    values,
                    t.crc
                ],
            )
            .map_err(|e| self.write_fail("store a compensation table", e, missing))?;
        Ok(TableId(self.conn.last_insert_rowid()))
    }

    fn query_tables(&self, id: Option<TableId>) -> Result<Vec<TableRecord>, StoreError> {
        let what = "read compensation tables";
        type Raw = (i64, String, String, String, i64, Option<i64>, String, u32);
        let mut stmt = self
            .conn
            .prepare_cached(
                "SELECT id, kind, axis, direction, generated_us, source_run_id, values_json, crc \
                 FROM tables WHERE ?1 IS NULL OR id = ?1 ORDER BY id",
            )
            .map_err(|e| self.fail(what, e))?;
        let raws: Vec<Raw> = stmt
            .query_map([id.map(|t| t.0)], |r| {
                Ok((
                    r.get(0)?,
                    r.get(1)?,
                    r.get(2)?,
                    r.get(3)?,
                    r.get(4)?,
                    r.get(5)?,
                    r.get(6)?,
                    r.get(7)?,
                ))
            })
            .and_then(|rows| rows.collect())
            .map_err(|e| self.fail(what, e))?;
        raws.into_iter()
            .map(|(id, kind, axis, dir, generated_us, run, values, crc)| {
                let direction = match dir.as_str() {
                    "+" => Some(Direction::Up),
                    "-" => Some(Direction::Down),
                    "both" => None,
                    other => return Err(self.decode(what, format!("direction {other:?}"))),
                };
                Ok(TableRecord {
                    id: TableId(id),
                    entry: TableEntry {
                        kind,
                        axis,
                        direction,
                        generated_us,
                        source_run: run.map(RunId),
                        values: self.json("table values", &values)?,
                        crc,
                    },
                })
            })
            .collect()
    }

    /// All compensation tables, oldest first.
    pub fn tables(&self) -> Result<Vec<TableRecord>, StoreError> {
        self.query_tables(None)
    }

    /// One compensation table.
    pub fn table(&self, id: TableId) -> Result<TableRecord, StoreError> {
        self.query_tables(Some(id))?
            .pop()
            .ok_or(StoreError::NoSuchTable(id))
    }

    // ----- publications

    /// Record a publication attempt and its outcome.
    pub fn insert_publication(&mut self, p: &Publication) -> Result<i64, StoreError> {
        let (result, code, text) = p.outcome.parts();
        self.conn
            .execute(
                "INSERT INTO publications (table_id, target, sequence, result, error_code, \
                 error_text, unix_us) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)",
                params![
                    p.table.0, p.target, p.sequence, result, code, text, p.unix_us
                ],
            )
            .map_err(|e| {
                self.write_fail("record a publication", e, StoreError::NoSuchTable(p.table))
            })?;
        Ok(self.conn.last_insert_rowid())
    }

    /// The publications of table `table` (`Some`) or of all tables (`None`), oldest first.
    pub fn publications(
        &self,
        table: Option<TableId>,
    ) -> Result<Vec<PublicationRecord>, StoreError> {
        let what = "read publications";
        type Raw = (
            i64,
            i64,
            String,
            u32,
            String,
            Option<i64>,
            Option<String>,
            i64,
        );
        let mut stmt = self
            .conn
            .prepare_cached(
                "SELECT id, table_id, target, sequence, result, error_code, error_text, unix_us \
                 FROM publications WHERE ?1 IS NULL OR table_id = ?1 ORDER BY id",
            )
            .map_err(|e| self.fail(what, e))?;
        let raws: Vec<Raw> = stmt
            .query_map([table.map(|t| t.0)], |r| {
                Ok((
                    r.get(0)?,
                    r.get(1)?,
                    r.get(2)?,
                    r.get(3)?,
                    r.get(4)?,
                    r.get(5)?,
                    r.get(6)?,
                    r.get(7)?,
                ))
            })
            .and_then(|rows| rows.collect())
            .map_err(|e| self.fail(what, e))?;
        raws.into_iter()
            .map(
                |(id, table, target, sequence, result, code, text, unix_us)| {
                    let text = text.unwrap_or_default();
                    let outcome = match result.as_str() {
                        "accepted" => PublicationOutcome::Accepted,
                        "rejected" => PublicationOutcome::Rejected { code, text },
                        "failed" => PublicationOutcome::Failed { code, text },
                        other => return Err(self.decode(what, format!("result {other:?}"))),
                    };
                    Ok(PublicationRecord {
                        id,
                        publication: Publication {
                            table: TableId(table),
                            target,
                            sequence,
                            outcome,
                            unix_us,
                        },
                    })
                },
            )
            .collect()
    }

    // ----- audit

    /// Append an audit entry.
    pub fn audit(&mut self, a: &AuditEntry) -> Result<i64, StoreError> {
        if a.action.is_empty() {
            return Err(StoreError::Invalid {
                what: "audit entry",
                problem: "its action is empty".into(),
            });
        }
        let details = json_text("audit details", &a.details)?;
        self.conn
            .execute(
                "INSERT INTO audit (unix_us, uid, user, pid, role, action, details_json, \
                 outcome, reason) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)",
                params![
                    a.unix_us,
                    a.who.uid,
                    a.who.user,
                    a.who.pid,
                    a.role,
                    a.action,
                    details,
                    a.outcome.as_str(),
                    a.outcome.reason()
                ],
            )
            .map_err(|e| self.fail("append to the audit log", e))?;
        Ok(self.conn.last_insert_rowid())
    }

    /// The newest `limit` audit entries, oldest first.
    pub fn audit_entries(&self, limit: u32) -> Result<Vec<AuditRecord>, StoreError> {
        let what = "read the audit log";
        type Raw = (
            i64,
            i64,
            Option<u32>,
            Option<String>,
            Option<i32>,
            String,
            String,
            String,
            String,
            Option<String>,
        );
        let mut stmt = self
            .conn
            .prepare_cached(
                "SELECT * FROM (SELECT id, unix_us, uid, user, pid, role, action, details_json, \
                 outcome, reason FROM audit ORDER BY id DESC LIMIT ?1) ORDER BY id",
            )
            .map_err(|e| self.fail(what, e))?;
        let raws: Vec<Raw> = stmt
            .query_map([limit], |r| {
                Ok((
                    r.get(0)?,
                    r.get(1)?,
                    r.get(2)?,
                    r.get(3)?,
                    r.get(4)?,
                    r.get(5)?,
                    r.get(6)?,
                    r.get(7)?,
                    r.get(8)?,
                    r.get(9)?,
                ))
            })
            .and_then(|rows| rows.collect())
            .map_err(|e| self.fail(what, e))?;
        raws.into_iter()
            .map(
                |(id, unix_us, uid, user, pid, role, action, details, outcome, reason)| {
                    let outcome = match outcome.as_str() {
                        "done" => AuditOutcome::Done,
                        "refused" => AuditOutcome::Refused(reason.unwrap_or_default()),
                        _ => AuditOutcome::Recorded,
                    };
                    Ok(AuditRecord {
                        id,
                        entry: AuditEntry {
                            unix_us,
                            who: Actor { uid, user, pid },
                            role,
                            action,
                            details: self.json("audit details", &details)?,
                            outcome,
                        },
                    })
                },
            )
            .collect()
    }
}
