//! The zero reference in force, kept across a restart (issue 24): a service killed in a run
//! comes back measuring against the zero it had, with the turns of the head it had found, and
//! checks them at the carriage's first return to the zero. Each change is a row; the newest
//! row is the reference in force. The store keeps the state as the service gives it (JSON)
//! and the name of the decoupling it belongs to.

use super::{Store, StoreError};
use rusqlite::{OptionalExtension, params};

/// The newest zero reference as stored.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredReference {
    /// When it was recorded (µs since the Unix epoch).
    pub unix_us: i64,
    /// The decoupling it is in the terms of.
    pub decoupler: String,
    /// The reference (JSON); `None`: there was none.
    pub state_json: Option<String>,
}

impl Store {
    /// Record the zero reference now in force (`None`: none).
    pub fn record_reference(
        &mut self,
        unix_us: i64,
        decoupler: &str,
        state: Option<&serde_json::Value>,
    ) -> Result<(), StoreError> {
        let what = "record the zero reference";
        let text = state.map(|v| v.to_string());
        self.conn
            .execute(
                "INSERT INTO zero_references (unix_us, decoupler, state_json) VALUES (?1, ?2, ?3)",
                params![unix_us, decoupler, text],
            )
            .map_err(|e| self.fail(what, e))?;
        Ok(())
    }

    /// The zero reference in force when the service last recorded one.
    pub fn latest_reference(&self) -> Result<Option<StoredReference>, StoreError> {
        let what = "read the zero reference";
        self.conn
            .query_row(
                "SELECT unix_us, decoupler, state_json FROM zero_references \
                 ORDER BY id DESC LIMIT 1",
                [],
                |r| {
                    Ok(StoredReference {
                        unix_us: r.get(0)?,
                        decoupler: r.get(1)?,
                        state_json: r.get(2)?,
                    })
                },
            )
            .optional()
            .map_err(|e| self.fail(what, e))
    }
}
