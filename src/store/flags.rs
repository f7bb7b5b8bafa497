//! Every stored capture true or flagged (issue 24): the events of a run that could move its
//! positioning reference (`run_events`), and the captures its judge flagged (`capture_flags`)
//! with their values and the reason, and the captures whose u a later check stated again
//! (`capture_restatements`). A flagged capture is never in `captures`: it was kept
//! out, or (found by the review at the run's end) moved out in the same transaction as its
//! flag was written, so nothing is lost and every reader of `captures` sees judged captures
//! only. A flag is *open* until its capture is retaken (a capture of the same run, target and
//! direction is stored) or the operator excludes it with a reason.

use super::records::{CONSTRAINT_FOREIGNKEY, Sign};
use super::{RunId, Store, StoreError};
use crate::run::{Capture, TargetKey};
use rusqlite::params;
use serde::Serialize;

/// An event of a run that could move its reference, as stored.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RunEvent {
    pub unix_us: i64,
    /// "following-ended", "drive-fault", "stitch-rereferenced", "resumed", "zero-shifted"…
    pub kind: String,
    pub detail: String,
}

/// A capture's u stated again, as stored: the capture (its key and time), when, and why.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Restatement {
    pub key: TargetKey,
    pub capture_us: i64,
    pub unix_us: i64,
    pub reason: String,
}

/// A flagged capture, as stored.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CaptureFlag {
    pub id: i64,
    pub key: TargetKey,
    /// When it was flagged.
    pub unix_us: i64,
    /// The capture as it was taken.
    pub capture: Capture,
    pub reason: String,
    /// It had been stored, and was moved out when flagged.
    pub was_stored: bool,
    /// A capture of its run, target and direction is stored now.
    pub retaken: bool,
    /// The operator's exclusion: who, when, why.
    pub excluded: Option<(String, i64, String)>,
}

impl CaptureFlag {
    /// Neither retaken nor excluded.
    pub fn open(&self) -> bool {
        !self.retaken && self.excluded.is_none()
    }
}

/// A `capture_flags` row as read: id, flagged at, the capture's JSON, the reason, was
/// stored, retaken, the exclusion.
type FlagRow = (
    i64,
    i64,
    String,
    String,
    bool,
    bool,
    Option<(String, i64, String)>,
);

impl Store {
    /// Record an event of run `run` that could move its reference.
    pub fn record_run_event(
        &mut self,
        run: RunId,
        unix_us: i64,
        kind: &str,
        detail: &str,
    ) -> Result<(), StoreError> {
        let what = "record a run's event";
        self.conn
            .execute(
                "INSERT INTO run_events (run_id, unix_us, kind, detail) VALUES (?1, ?2, ?3, ?4)",
                params![run.0, unix_us, kind, detail],
            )
            .map_err(|e| self.fk_or(run, what, e))?;
        Ok(())
    }

    fn fk_or(&self, run: RunId, what: &'static str, e: rusqlite::Error) -> StoreError {
        if e.sqlite_error()
            .is_some_and(|s| s.extended_code == CONSTRAINT_FOREIGNKEY)
        {
            StoreError::NoSuchRun(run)
        } else {
            self.fail(what, e)
        }
    }

    /// Flag capture `c` of run `run` with `reason` at `unix_us`; `stored`: it is in
    /// `captures` and comes out of it in the same transaction.
    pub fn flag_capture(
        &mut self,
        run: RunId,
        c: &Capture,
        reason: &str,
        stored: bool,
        unix_us: i64,
    ) -> Result<(), StoreError> {
        let what = "flag a capture";
        let json = serde_json::to_string(c).map_err(|e| StoreError::Invalid {
            what: "capture",
            problem: e.to_string(),
        })?;
        let path = self.label();
        let fail = |e| super::classify(&path, what, e);
        let tx = self.conn.transaction().map_err(fail)?;
        tx.execute(
            "INSERT INTO capture_flags (run_id, run, target_index, direction, unix_us, \
             capture_json, reason, was_stored) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8)",
            params![
                run.0,
                c.run,
                c.target_index,
                Sign(c.direction),
                unix_us,
                json,
                reason,
                stored
            ],
        )
        .map_err(|e| match e.sqlite_error() {
            Some(s) if s.extended_code == CONSTRAINT_FOREIGNKEY => StoreError::NoSuchRun(run),
            _ => fail(e),
        })?;
        if stored {
            tx.execute(
                "DELETE FROM captures WHERE run_id = ?1 AND run = ?2 AND target_index = ?3 \
                 AND direction = ?4",
                params![run.0, c.run, c.target_index, Sign(c.direction)],
            )
            .map_err(fail)?;
        }
        tx.commit().map_err(fail)
    }

    /// State the u of a stored capture of run `run` again (`run::RunMachine::turns_bounded`):
    /// `c` is the capture as it is now, matched by its key and its time. The row as taken
    /// stays (captures are immutable); a restatement row keeps the new u with `reason` (what
    /// it was, what bounded it), and [`Store::captures`] reads the newest. `Ok(false)` when
    /// no such capture is stored (flagged since, or not yet stored: the capture offered later
    /// carries the new u), and nothing is written.
    pub fn restate_capture(
        &mut self,
        run: RunId,
        c: &Capture,
        reason: &str,
        unix_us: i64,
    ) -> Result<bool, StoreError> {
        let u = c.u.to_array();
        if u.iter().any(|v| !v.is_finite() || *v < 0.0) || reason.is_empty() {
            return Err(StoreError::Invalid {
                what: "restated capture",
                problem: format!(
                    "{} {}: a u that is not a finite, non-negative number, or no reason",
                    TargetKey::of(c),
                    c.direction.sign()
                ),
            });
        }
        let what = "state a capture's u again";
        let n = self
            .conn
            .execute(
                "INSERT INTO capture_restatements (run_id, run, target_index, direction, \
                 capture_us, u_dx_mm, u_dy_mm, u_dz_mm, u_ex_rad, u_ey_rad, u_ez_rad, unix_us, \
                 reason) SELECT ?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13 \
                 WHERE EXISTS (SELECT 1 FROM captures WHERE run_id = ?1 AND run = ?2 \
                 AND target_index = ?3 AND direction = ?4 AND unix_us = ?5)",
                params![
                    run.0,
                    c.run,
                    c.target_index,
                    Sign(c.direction),
                    c.unix_us,
                    u[0],
                    u[1],
                    u[2],
                    u[3],
                    u[4],
                    u[5],
                    unix_us,
                    reason
                ],
            )
            .map_err(|e| self.fk_or(run, what, e))?;
        Ok(n == 1)
    }

    /// The restatements of run `run`'s captures, in order.
    pub fn restatements(&self, run: RunId) -> Result<Vec<Restatement>, StoreError> {
        let what = "read a run's restated captures";
        let mut stmt = self
            .conn
            .prepare_cached(
                "SELECT run, target_index, direction, capture_us, unix_us, reason \
                 FROM capture_restatements WHERE run_id = ?1 ORDER BY id",
            )
            .map_err(|e| self.fail(what, e))?;
        stmt.query_map([run.0], |r| {
            Ok(Restatement {
                key: TargetKey {
                    run: r.get(0)?,
                    target_index: r.get(1)?,
                    direction: r.get::<_, Sign>(2)?.0,
                },
                capture_us: r.get(3)?,
                unix_us: r.get(4)?,
                reason: r.get(5)?,
            })
        })
        .and_then(|rows| rows.collect())
        .map_err(|e| self.fail(what, e))
    }

    /// The events of run `run`, in order.
    pub fn run_events(&self, run: RunId) -> Result<Vec<RunEvent>, StoreError> {
        let what = "read a run's events";
        let mut stmt = self
            .conn
            .prepare_cached(
                "SELECT unix_us, kind, detail FROM run_events WHERE run_id = ?1 ORDER BY id",
            )
            .map_err(|e| self.fail(what, e))?;
        stmt.query_map([run.0], |r| {
            Ok(RunEvent {
                unix_us: r.get(0)?,
                kind: r.get(1)?,
                detail: r.get(2)?,
            })
        })
        .and_then(|rows| rows.collect())
        .map_err(|e| self.fail(what, e))
    }

    /// The flags of run `run`, in order, each with whether it was retaken.
    pub fn capture_flags(&self, run: RunId) -> Result<Vec<CaptureFlag>, StoreError> {
        let what = "read a run's flagged captures";
        let mut stmt = self
            .conn
            .prepare_cached(
                "SELECT f.id, f.unix_us, f.capture_json, f.reason, f.was_stored, \
                 EXISTS (SELECT 1 FROM captures c WHERE c.run_id = f.run_id AND c.run = f.run \
                         AND c.target_index = f.target_index AND c.direction = f.direction), \
                 f.excluded_by, f.excluded_us, f.excluded_reason \
                 FROM capture_flags f WHERE f.run_id = ?1 ORDER BY f.id",
            )
            .map_err(|e| self.fail(what, e))?;
        let rows: Vec<FlagRow> = stmt
            .query_map([run.0], |r| {
                let by: Option<String> = r.get(6)?;
                let at: Option<i64> = r.get(7)?;
                let why: Option<String> = r.get(8)?;
                Ok((
                    r.get(0)?,
                    r.get(1)?,
                    r.get(2)?,
                    r.get(3)?,
                    r.get(4)?,
                    r.get(5)?,
                    match (by, at, why) {
                        (Some(by), Some(at), Some(why)) => Some((by, at, why)),
                        _ => None,
                    },
                ))
            })
            .and_then(|rows| rows.collect())
            .map_err(|e| self.fail(what, e))?;
        rows.into_iter()
            .map(
                |(id, unix_us, json, reason, was_stored, retaken, excluded)| {
                    let capture: Capture =
                        serde_json::from_str(&json).map_err(|e| StoreError::Invalid {
                            what: "flagged capture",
                            problem: format!("flag {id}: {e}"),
                        })?;
                    Ok(CaptureFlag {
                        id,
                        key: TargetKey::of(&capture),
                        unix_us,
                        capture,
                        reason,
                        was_stored,
                        retaken,
                        excluded,
                    })
                },
            )
            .collect()
    }

    /// Why run `run` cannot give a table, a report's verdict or a publication: its open flags
    /// in words, or None when it has none.
    pub fn open_flags(&self, run: RunId) -> Result<Option<String>, StoreError> {
        let open: Vec<CaptureFlag> = self
            .capture_flags(run)?
            .into_iter()
            .filter(CaptureFlag::open)
            .collect();
        let run_n = run.0;
        Ok(open.first().map(|f| {
            format!(
                "run {run} has {} flagged capture{} neither retaken nor excluded (the first: {}); retake them (run the make-up again) or exclude them with a reason (axiscomp run flags --run {run_n}; axiscomp run exclude --run {run_n} --flag N --reason …)",
                open.len(),
                if open.len() == 1 { "" } else { "s" },
                f.reason
            )
        }))
    }

    /// The operator excludes flag `flag` of run `run`: `who` says why. The capture stays out
    /// of the run; the flag no longer holds the run's tables back.
    pub fn exclude_flag(
        &mut self,
        run: RunId,
        flag: i64,
        who: &str,
        reason: &str,
        unix_us: i64,
    ) -> Result<(), StoreError> {
        if reason.trim().is_empty() {
            return Err(StoreError::Invalid {
                what: "exclusion",
                problem: "give the reason for excluding the capture".into(),
            });
        }
        let what = "exclude a flagged capture";
        let n = self
            .conn
            .execute(
                "UPDATE capture_flags SET excluded_by = ?3, excluded_us = ?4, \
                 excluded_reason = ?5 WHERE run_id = ?1 AND id = ?2 AND excluded_us IS NULL",
                params![run.0, flag, who, unix_us, reason],
            )
            .map_err(|e| self.fail(what, e))?;
        if n == 0 {
            return Err(StoreError::Invalid {
                what: "exclusion",
                problem: format!(
                    "run {run} has no flag {flag} that is not excluded already (axiscomp run flags --run {})",
                    run.0
                ),
            });
        }
        Ok(())
    }
}
