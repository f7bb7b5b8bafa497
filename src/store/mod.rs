//! Persistence (DESIGN §8): one SQLite file (bundled SQLite) holding calibrations, runs, captures,
//! follower handovers, compensation tables, their publications and the audit log.
//!
//! Durability is the point: every capture is committed, and synced to disk, before
//! `insert_capture` returns, so a run interrupted by a crash or a power loss resumes at the next
//! target (`completed_keys`). The store opens with
//! - `journal_mode=WAL`: readers (console, reports) never block the writer, nor it them;
//! - `synchronous=FULL`: in WAL mode this syncs the log on every commit; `NORMAL` would be
//!   crash-safe but could lose the last commits on power loss, which is what we must not lose;
//! - `foreign_keys=ON`: a capture cannot name a run that does not exist;
//! - a 5 s busy timeout, and `BEGIN IMMEDIATE` for read-then-write transactions, so two
//!   processes on one file wait for each other instead of failing.
//!
//! Opening checks the file before using it: another program's database, a damaged file
//! (`PRAGMA quick_check`) or a schema newer than this build is refused with an error naming the
//! file and what to do; an older schema is migrated forward (`schema`). Values are stored in the
//! crate's internal units (mm, rad; see `schema` for the column naming).
//!
//! `Store` wraps one connection: it is `Send` but not `Sync`; share it behind a mutex or own it in
//! one task. Open a second `Store` (e.g. `open_read_only`) for a concurrent reader.

mod alignments;
mod flags;
mod follower;
mod machines;
pub mod queue;
mod records;
mod references;
mod run_list;
mod run_tables;
pub mod schema;

pub use alignments::{AlignmentRecord, NewAlignment};
pub use flags::{CaptureFlag, Restatement, RunEvent};
pub use follower::FollowerMapRecord;
pub use machines::StoredMachine;
pub use queue::{QueueError, StoreQueue};
pub use records::{
    Actor, AuditEntry, AuditOutcome, AuditRecord, CalibrationId, CalibrationRecord,
    CalibrationSummary, NewRun, Publication, PublicationOutcome, PublicationRecord, RunId,
    RunRecord, RunState, StoredHandover, TableEntry, TableId, TableRecord,
};
pub use references::StoredReference;
pub use run_list::{RunSummary, iso_utc};
pub use run_tables::{ActiveTable, RunTables};

use rusqlite::{Connection, ErrorCode, OpenFlags, TransactionBehavior};
use std::path::{Path, PathBuf};
use std::time::Duration;
use thiserror::Error;

/// How long a statement waits for another connection's lock before failing.
pub const BUSY_TIMEOUT: Duration = Duration::from_secs(5);

/// Why a store operation failed. Each message names the file and says what to do.
#[derive(Debug, Error)]
pub enum StoreError {
    #[error(
        "store {path}: cannot open it ({source}); check that the path exists, its directory is \
         writable by the service, and the file is not held by another program"
    )]
    Open {
        path: String,
        source: rusqlite::Error,
    },
    #[error(
        "store {path}: not an SQLite database (or its header is destroyed); move it aside and \
         restore a backup, or let the service start a new store"
    )]
    NotADatabase { path: String },
    #[error(
        "store {path}: the database is damaged ({detail}); stop the service, move the file \
         (with its -wal and -shm files) aside and restore a backup"
    )]
    Corrupt { path: String, detail: String },
    #[error(
        "store {path}: an SQLite database of another application (application_id {found:#x}, \
         schema version {version}); point the store setting at axiscomp's own file"
    )]
    Foreign {
        path: String,
        found: i32,
        version: i64,
    },
    #[error(
        "store {path}: schema version {found} is newer than this build supports ({supported}); \
         run the axiscomp version that wrote it, or restore a backup made by this version"
    )]
    FutureVersion {
        path: String,
        found: i64,
        supported: i64,
    },
    #[error(
        "store {path}: schema version {found} is older than this build's ({supported}) and the \
         store is open read-only; open it read-write once (start the service) to migrate it"
    )]
    NeedsMigration {
        path: String,
        found: i64,
        supported: i64,
    },
    #[error(
        "store {path}: migration to schema version {to} failed ({source}); the file is unchanged \
         at version {from}; report this with the file"
    )]
    Migration {
        path: String,
        from: i64,
        to: i64,
        source: rusqlite::Error,
    },
    #[error("store {path}: cannot set {pragma} ({detail}); the file system must support it")]
    Pragma {
        path: String,
        pragma: &'static str,
        detail: String,
    },
    #[error(
        "store {path}: {what}: the database stayed locked by another connection for {}s; \
         check for a stuck process holding it",
        BUSY_TIMEOUT.as_secs()
    )]
    Busy { path: String, what: &'static str },
    #[error("store {path}: {what}: the disk is full; free space on its file system")]
    DiskFull { path: String, what: &'static str },
    #[error(
        "store {path}: {what}: the store is read-only (opened read-only, or the file or its \
         directory is not writable by this user)"
    )]
    ReadOnly { path: String, what: &'static str },
    #[error("store {path}: {what}: I/O error ({source}); check the disk and the kernel log")]
    Io {
        path: String,
        what: &'static str,
        source: rusqlite::Error,
    },
    #[error(
        "store {path}: {what} failed ({source}); unexpected: report it with the file and this message"
    )]
    Sql {
        path: String,
        what: &'static str,
        source: rusqlite::Error,
    },
    #[error(
        "store {path}: {what}: a stored value is unreadable ({problem}); the row was written by other software or damaged"
    )]
    Decode {
        path: String,
        what: &'static str,
        problem: String,
    },
    #[error("run {0} is not in the store; list the runs to find its id")]
    NoSuchRun(RunId),
    #[error("calibration {0} is not in the store; list the calibrations to find its id")]
    NoSuchCalibration(CalibrationId),
    #[error("compensation table {0} is not in the store; list the tables to find its id")]
    NoSuchTable(TableId),
    #[error("follower map {0} is not in the store; list the maps to find its id")]
    NoSuchFollowerMap(i64),
    #[error("machine {0} is not in the store; list the machines to find its id")]
    NoSuchMachine(i64),
    #[error("invalid {what}: {problem}")]
    Invalid { what: &'static str, problem: String },
    #[error("run {run} is {from}: it cannot become {to}")]
    StateTransition {
        run: RunId,
        from: RunState,
        to: RunState,
    },
}

/// The store: one SQLite connection with the pragmas above.
#[derive(Debug)]
pub struct Store {
    conn: Connection,
    path: PathBuf,
    read_only: bool,
}

impl Store {
    /// Open (creating it when missing) the store at `path` for reading and writing, and migrate
    /// its schema to this build's version.
    pub fn open(path: impl AsRef<Path>) -> Result<Store, StoreError> {
        Self::open_mode(path.as_ref(), false)
    }

    /// Open an existing store for reading only (reports, the console, a second process while
    /// the service writes). It is never migrated: an older schema gives `NeedsMigration`.
    pub fn open_read_only(path: impl AsRef<Path>) -> Result<Store, StoreError> {
        Self::open_mode(path.as_ref(), true)
    }

    fn open_mode(path: &Path, read_only: bool) -> Result<Store, StoreError> {
        let label = path.display().to_string();
        let flags = if read_only {
            OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX
        } else {
            OpenFlags::SQLITE_OPEN_READ_WRITE
                | OpenFlags::SQLITE_OPEN_CREATE
                | OpenFlags::SQLITE_OPEN_NO_MUTEX
        };
        let mut conn =
            Connection::open_with_flags(path, flags).map_err(|source| StoreError::Open {
                path: label.clone(),
                source,
            })?;
        let fail = |what, e| classify(&label, what, e);
        conn.busy_timeout(BUSY_TIMEOUT)
            .map_err(|e| fail("set the busy timeout", e))?;
        conn.set_transaction_behavior(TransactionBehavior::Immediate);

        // Reading the header is where a file that is not a database shows itself.
        let app_id: i32 = conn
            .pragma_query_value(None, "application_id", |r| r.get(0))
            .map_err(|e| fail("read the header", e))?;
        let version: i64 = conn
            .pragma_query_value(None, "user_version", |r| r.get(0))
            .map_err(|e| fail("read the schema version", e))?;
        if app_id != schema::APPLICATION_ID {
            let objects: i64 = conn
                .query_row("SELECT count(*) FROM sqlite_schema", [], |r| r.get(0))
                .map_err(|e| fail("read the schema", e))?;
            if app_id != 0 || version != 0 || objects != 0 {
                return Err(StoreError::Foreign {
                    path: label,
                    found: app_id,
                    version,
                });
            }
        }
        if version > schema::LATEST {
            return Err(StoreError::FutureVersion {
                path: label,
                found: version,
                supported: schema::LATEST,
            });
        }

        if !read_only {
            let mode: String = conn
                .pragma_update_and_check(None, "journal_mode", "wal", |r| r.get(0))
                .map_err(|e| fail("set journal_mode", e))?;
            if !mode.eq_ignore_ascii_case("wal") {
                return Err(StoreError::Pragma {
                    path: label,
                    pragma: "journal_mode=WAL",
                    detail: format!("SQLite kept journal mode {mode}"),
                });
            }
        }
        conn.pragma_update(None, "synchronous", "FULL")
            .map_err(|e| fail("set synchronous", e))?;
        conn.pragma_update(None, "foreign_keys", true)
            .map_err(|e| fail("set foreign_keys", e))?;
        let fk: bool = conn
            .pragma_query_value(None, "foreign_keys", |r| r.get(0))
            .map_err(|e| fail("read foreign_keys", e))?;
        if !fk {
            return Err(StoreError::Pragma {
                path: label,
                pragma: "foreign_keys=ON",
                detail: "SQLite was built without foreign keys".into(),
            });
        }

        let problems = check(&conn, "quick_check").map_err(|e| fail("check the file", e))?;
        if problems != ["ok"] {
            return Err(StoreError::Corrupt {
                path: label,
                detail: problems.join("; "),
            });
        }

        if version < schema::LATEST {
            if read_only {
                return Err(StoreError::NeedsMigration {
                    path: label,
                    found: version,
                    supported: schema::LATEST,
                });
            }
            migrate(&mut conn, schema::MIGRATIONS).map_err(|(from, to, source)| match classify(
                &label,
                "migrate the schema",
                source,
            ) {
                StoreError::Sql { source, .. } => StoreError::Migration {
                    path: label.clone(),
                    from,
                    to,
                    source,
                },
                other => other,
            })?;
        }
        Ok(Store {
            conn,
            path: path.to_path_buf(),
            read_only,
        })
    }

    /// The file this store was opened from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// True when opened with `open_read_only`.
    pub fn is_read_only(&self) -> bool {
        self.read_only
    }

    /// The schema version of the file (`PRAGMA user_version`).
    pub fn schema_version(&self) -> Result<i64, StoreError> {
        self.conn
            .pragma_query_value(None, "user_version", |r| r.get(0))
            .map_err(|e| self.fail("read the schema version", e))
    }

    /// `PRAGMA integrity_check`: `["ok"]` when the file is sound, else SQLite's findings.
    /// It reads every page, so it is for maintenance and tests, not for every open.
    pub fn integrity_check(&self) -> Result<Vec<String>, StoreError> {
        check(&self.conn, "integrity_check").map_err(|e| self.fail("check integrity", e))
    }

    fn label(&self) -> String {
        self.path.display().to_string()
    }

    fn fail(&self, what: &'static str, e: rusqlite::Error) -> StoreError {
        classify(&self.label(), what, e)
    }

    fn decode(&self, what: &'static str, problem: impl std::fmt::Display) -> StoreError {
        StoreError::Decode {
            path: self.label(),
            what,
            problem: problem.to_string(),
        }
    }
}

/// Run `PRAGMA quick_check` or `integrity_check` and collect its rows.
fn check(conn: &Connection, pragma: &str) -> rusqlite::Result<Vec<String>> {
    let mut stmt = conn.prepare(&format!("PRAGMA {pragma}"))?;
    let rows = stmt.query_map([], |r| r.get::<_, String>(0))?;
    rows.collect()
}

/// Apply `steps` from the file's version on; each step with its version bump in one
/// (immediate) transaction. On failure: (from, to, error).
fn migrate(conn: &mut Connection, steps: &[&str]) -> Result<(), (i64, i64, rusqlite::Error)> {
    for (i, sql) in steps.iter().enumerate() {
        let to = i as i64 + 1;
        let step = |conn: &mut Connection| -> rusqlite::Result<()> {
            let tx = conn.transaction()?;
            // Re-read inside the lock: another process may have migrated meanwhile.
            let v: i64 = tx.pragma_query_value(None, "user_version", |r| r.get(0))?;
            if v >= to {
                return Ok(());
            }
            tx.execute_batch(sql)?;
            tx.pragma_update(None, "user_version", to)?;
            tx.commit()
        };
        step(conn).map_err(|e| (to - 1, to, e))?;
    }
    Ok(())
}

/// Map an SQLite error to what the operator can act on.
fn classify(path: &str, what: &'static str, e: rusqlite::Error) -> StoreError {
    let path = path.to_string();
    match e.sqlite_error_code() {
        Some(ErrorCode::NotADatabase) => StoreError::NotADatabase { path },
        Some(ErrorCode::DatabaseCorrupt) => StoreError::Corrupt {
            path,
            detail: e.to_string(),
        },
        Some(ErrorCode::DatabaseBusy | ErrorCode::DatabaseLocked) => {
            StoreError::Busy { path, what }
        }
        Some(ErrorCode::DiskFull) => StoreError::DiskFull { path, what },
        Some(ErrorCode::ReadOnly) => StoreError::ReadOnly { path, what },
        Some(ErrorCode::SystemIoFailure) => StoreError::Io {
            path,
            what,
            source: e,
        },
        _ => StoreError::Sql {
            path,
            what,
            source: e,
        },
    }
}

/// Now, in µs since the Unix epoch (the stamp of bookkeeping columns).
pub fn now_us() -> i64 {
    crate::util::clock::unix_us()
}

#[cfg(test)]
mod tests;
