//! Machine records and the runs attached to their set-ups (issue 27). The store keeps a
//! record as its TOML text (`commission::record` reads it) and each attachment or detachment
//! of a run as a row: the newest row per set-up is in force, the rest is the history.

use super::{RunId, Store, StoreError};
use rusqlite::{OptionalExtension, params};

/// A stored machine.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredMachine {
    pub id: i64,
    pub name: String,
    pub record_toml: String,
    /// µs since the Unix epoch.
    pub created_us: i64,
}

/// A `machines` row: id, name, record_toml, created_us.
fn machine_row(r: &rusqlite::Row<'_>) -> rusqlite::Result<StoredMachine> {
    Ok(StoredMachine {
        id: r.get(0)?,
        name: r.get(1)?,
        record_toml: r.get(2)?,
        created_us: r.get(3)?,
    })
}

impl Store {
    /// Store a machine's record; its id.
    pub fn create_machine(
        &mut self,
        name: &str,
        record_toml: &str,
        unix_us: i64,
    ) -> Result<i64, StoreError> {
        let what = "store a machine record";
        self.conn
            .execute(
                "INSERT INTO machines (name, record_toml, created_us) VALUES (?1, ?2, ?3)",
                params![name, record_toml, unix_us],
            )
            .map_err(|e| self.fail(what, e))?;
        Ok(self.conn.last_insert_rowid())
    }

    /// Every stored machine, newest first.
    pub fn machines(&self) -> Result<Vec<StoredMachine>, StoreError> {
        let what = "list the machines";
        let mut stmt = self
            .conn
            .prepare("SELECT id, name, record_toml, created_us FROM machines ORDER BY id DESC")
            .map_err(|e| self.fail(what, e))?;
        let rows = stmt
            .query_map([], machine_row)
            .and_then(|rows| rows.collect::<Result<Vec<_>, _>>())
            .map_err(|e| self.fail(what, e))?;
        Ok(rows)
    }

    /// Machine `id`.
    pub fn machine(&self, id: i64) -> Result<StoredMachine, StoreError> {
        let what = "read a machine record";
        self.conn
            .query_row(
                "SELECT id, name, record_toml, created_us FROM machines WHERE id = ?1",
                params![id],
                machine_row,
            )
            .optional()
            .map_err(|e| self.fail(what, e))?
            .ok_or(StoreError::NoSuchMachine(id))
    }

    /// Attach run `run` to set-up `setup` of machine `machine` (`None`: detach what is there).
    pub fn set_machine_setup(
        &mut self,
        machine: i64,
        setup: usize,
        run: Option<RunId>,
        unix_us: i64,
    ) -> Result<(), StoreError> {
        let what = "attach a run to a machine's set-up";
        self.machine(machine)?;
        if let Some(r) = run {
            self.run(r)?;
        }
        self.conn
            .execute(
                "INSERT INTO machine_setups (machine_id, setup, run_id, unix_us) \
                 VALUES (?1, ?2, ?3, ?4)",
                params![machine, setup as i64, run.map(|r| r.0), unix_us],
            )
            .map_err(|e| self.fail(what, e))?;
        Ok(())
    }

    /// The run in force on each of machine `machine`'s first `setups` set-ups.
    pub fn machine_setups(
        &self,
        machine: i64,
        setups: usize,
    ) -> Result<Vec<Option<RunId>>, StoreError> {
        let what = "read a machine's set-ups";
        let mut stmt = self
            .conn
            .prepare(
                "SELECT setup, run_id FROM machine_setups WHERE machine_id = ?1 \
                 ORDER BY id",
            )
            .map_err(|e| self.fail(what, e))?;
        let rows = stmt
            .query_map(params![machine], |r| {
                Ok((r.get::<_, i64>(0)?, r.get::<_, Option<i64>>(1)?))
            })
            .and_then(|rows| rows.collect::<Result<Vec<_>, _>>())
            .map_err(|e| self.fail(what, e))?;
        let mut out = vec![None; setups];
        for (setup, run) in rows {
            if let Some(slot) = usize::try_from(setup).ok().and_then(|s| out.get_mut(s)) {
                *slot = run.map(RunId);
            }
        }
        Ok(out)
    }
}
