//! The compensation tables active in the PLC while a run ran (issue 15): what a run measured
//! is the axis as compensated by these, so a table made from it is the residual on top of
//! them. Recorded once per run, when it starts (`service::tables` reads the PLC back).

use super::{RunId, Store, StoreError, TableId};
use rusqlite::{OptionalExtension, params};
use serde::{Deserialize, Serialize};

/// One table the PLC applied.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ActiveTable {
    /// "positioning", "straightness" or "abbe".
    pub kind: String,
    /// The machine axis its values act on.
    pub axis: String,
    /// The stored table it is, when the store has it.
    pub table: Option<TableId>,
    pub sequence: u32,
    pub crc: u32,
    /// True when the PLC's staging area was read back with this sequence and CRC; false when
    /// it is known from the store's record of what the PLC accepted (the staging area holds
    /// only the last table published).
    pub read_back: bool,
}

/// The tables active during a run, as read when it started.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct RunTables {
    /// When they were read (µs since the Unix epoch).
    pub unix_us: i64,
    /// False when the PLC could not be read: `source` says why, `tables` is empty.
    pub known: bool,
    /// Where they were read ("generic at 127.0.0.1:1502", "no PLC configured"), or why not.
    pub source: String,
    pub tables: Vec<ActiveTable>,
}

impl RunTables {
    /// The active table acting on `axis` of `kind`, if any.
    pub fn find(&self, kind: &str, axis: &str) -> Option<&ActiveTable> {
        self.tables
            .iter()
            .find(|t| t.kind == kind && t.axis == axis)
    }

    /// One line: "none", "unknown (why)" or "table 3 (positioning Y, sequence 4), …".
    pub fn summary(&self) -> String {
        if !self.known {
            return format!("unknown ({})", self.source);
        }
        if self.tables.is_empty() {
            return "none".into();
        }
        self.tables
            .iter()
            .map(|t| {
                let id = t
                    .table
                    .map_or_else(|| "a table".into(), |i| format!("table {i}"));
                format!("{id} ({} {}, sequence {})", t.kind, t.axis, t.sequence)
            })
            .collect::<Vec<_>>()
            .join(", ")
    }
}

impl Store {
    /// Record the tables active during run `run` (once: a second record is refused).
    pub fn record_run_tables(&mut self, run: RunId, t: &RunTables) -> Result<(), StoreError> {
        let what = "record the tables active during a run";
        let path = self.label();
        let fail = |e| super::classify(&path, what, e);
        let tx = self.conn.transaction().map_err(fail)?;
        let n = tx
            .execute(
                "INSERT INTO run_tables_read (run_id, unix_us, known, source) \
                 VALUES (?1, ?2, ?3, ?4) ON CONFLICT (run_id) DO NOTHING",
                params![run.0, t.unix_us, t.known, t.source],
            )
            .map_err(|e| {
                if e.sqlite_error()
                    .is_some_and(|s| s.extended_code == super::records::CONSTRAINT_FOREIGNKEY)
                {
                    StoreError::NoSuchRun(run)
                } else {
                    fail(e)
                }
            })?;
        if n == 0 {
            return Err(StoreError::Invalid {
                what: "tables active during a run",
                problem: format!("run {run} has them recorded already"),
            });
        }
        for a in &t.tables {
            tx.execute(
                "INSERT INTO run_tables (run_id, kind, axis, table_id, sequence, crc, read_back) \
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)",
                params![
                    run.0,
                    a.kind,
                    a.axis,
                    a.table.map(|i| i.0),
                    a.sequence,
                    a.crc,
                    a.read_back
                ],
            )
            .map_err(|e| match e.sqlite_error() {
                Some(s) if s.extended_code == super::records::CONSTRAINT_FOREIGNKEY => {
                    StoreError::NoSuchTable(a.table.unwrap_or(TableId(0)))
                }
                _ => fail(e),
            })?;
        }
        tx.commit().map_err(fail)
    }

    /// The tables active during run `run`; `None` when they were not recorded (a run made
    /// before schema version 4, or one whose start was never seen by the tables task).
    pub fn run_tables(&self, run: RunId) -> Result<Option<RunTables>, StoreError> {
        let what = "read the tables active during a run";
        let head: Option<(i64, bool, String)> = self
            .conn
            .query_row(
                "SELECT unix_us, known, source FROM run_tables_read WHERE run_id = ?1",
                [run.0],
                |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)),
            )
            .optional()
            .map_err(|e| self.fail(what, e))?;
        let Some((unix_us, known, source)) = head else {
            return Ok(None);
        };
        let mut stmt = self
            .conn
            .prepare_cached(
                "SELECT kind, axis, table_id, sequence, crc, read_back FROM run_tables \
                 WHERE run_id = ?1 ORDER BY sequence, kind, axis",
            )
            .map_err(|e| self.fail(what, e))?;
        let tables = stmt
            .query_map([run.0], |r| {
                Ok(ActiveTable {
                    kind: r.get(0)?,
                    axis: r.get(1)?,
                    table: r.get::<_, Option<i64>>(2)?.map(TableId),
                    sequence: r.get(3)?,
                    crc: r.get(4)?,
                    read_back: r.get(5)?,
                })
            })
            .and_then(|rows| rows.collect::<rusqlite::Result<Vec<_>>>())
            .map_err(|e| self.fail(what, e))?;
        Ok(Some(RunTables {
            unix_us,
            known,
            source,
            tables,
        }))
    }

    /// Runs planned or running whose active tables are not recorded, oldest first,
    /// created at or after `since_us` (the tables task records these as it sees them).
    pub fn runs_without_tables(&self, since_us: i64) -> Result<Vec<RunId>, StoreError> {
        let what = "list runs without their active tables";
        let mut stmt = self
            .conn
            .prepare_cached(
                "SELECT id FROM runs WHERE created_us >= ?1 AND state IN ('planned', 'running') \
                 AND id NOT IN (SELECT run_id FROM run_tables_read) ORDER BY id",
            )
            .map_err(|e| self.fail(what, e))?;
        stmt.query_map([since_us], |r| Ok(RunId(r.get(0)?)))
            .and_then(|rows| rows.collect())
            .map_err(|e| self.fail(what, e))
    }
}
