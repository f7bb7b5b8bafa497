//! Beam alignments per axis (issue 13): every alignment advice the service gives, with its
//! check, so that the pre-run check can find the newest one for the axis and a maintenance
//! engineer can see how the head was aligned. Angles in rad, positions in mm (the store's units).

use super::{Store, StoreError, now_us};
use rusqlite::{OptionalExtension, params};

/// An alignment as the service judged it.
#[derive(Clone, Debug, PartialEq)]
pub struct NewAlignment {
    pub axis: String,
    /// The travel the check covered (mm).
    pub from_mm: f64,
    pub to_mm: f64,
    pub passed: bool,
    /// The beam's residual angle to the travel (yaw, pitch; rad).
    pub yaw_rad: f64,
    pub pitch_rad: f64,
    /// The check in words ("every spot stays … inside" or which PSD leaves where).
    pub check: String,
    /// The advice as the control API answers it (turns, stations).
    pub advice: serde_json::Value,
}

/// A stored alignment.
#[derive(Clone, Debug, PartialEq)]
pub struct AlignmentRecord {
    pub id: i64,
    pub unix_us: i64,
    pub alignment: NewAlignment,
}

impl Store {
    /// Store an alignment; returns its id.
    pub fn insert_alignment(&mut self, a: &NewAlignment) -> Result<i64, StoreError> {
        let finite = [a.from_mm, a.to_mm, a.yaw_rad, a.pitch_rad]
            .iter()
            .all(|v| v.is_finite());
        if !finite || a.from_mm >= a.to_mm || a.axis.is_empty() {
            return Err(StoreError::Invalid {
                what: "alignment",
                problem: format!(
                    "axis \"{}\", {} to {} mm: give an axis and a span from below to above",
                    a.axis, a.from_mm, a.to_mm
                ),
            });
        }
        let advice = serde_json::to_string(&a.advice).map_err(|e| StoreError::Invalid {
            what: "alignment advice",
            problem: e.to_string(),
        })?;
        self.conn
            .execute(
                "INSERT INTO alignments (unix_us, axis, from_mm, to_mm, passed, yaw_rad, \
                 pitch_rad, check_text, advice_json) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)",
                params![
                    now_us(),
                    a.axis,
                    a.from_mm,
                    a.to_mm,
                    i64::from(a.passed),
                    a.yaw_rad,
                    a.pitch_rad,
                    a.check,
                    advice
                ],
            )
            .map_err(|e| self.fail("store an alignment", e))?;
        Ok(self.conn.last_insert_rowid())
    }

    /// The newest alignment of `axis`, passed or not.
    pub fn latest_alignment(&self, axis: &str) -> Result<Option<AlignmentRecord>, StoreError> {
        let what = "read the alignments";
        type Raw = (i64, i64, String, f64, f64, i64, f64, f64, String, String);
        let raw: Option<Raw> = self
            .conn
            .query_row(
                "SELECT id, unix_us, axis, from_mm, to_mm, passed, yaw_rad, pitch_rad, \
                 check_text, advice_json FROM alignments WHERE axis = ?1 ORDER BY id DESC LIMIT 1",
                [axis],
                |r| {
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
                },
            )
            .optional()
            .map_err(|e| self.fail(what, e))?;
        let Some((id, unix_us, axis, from_mm, to_mm, passed, yaw_rad, pitch_rad, check, advice)) =
            raw
        else {
            return Ok(None);
        };
        Ok(Some(AlignmentRecord {
            id,
            unix_us,
            alignment: NewAlignment {
                axis,
                from_mm,
                to_mm,
                passed: passed != 0,
                yaw_rad,
                pitch_rad,
                check,
                advice: serde_json::from_str(&advice).map_err(|e| self.decode(what, e))?,
            },
        }))
    }

    /// The axes that have an alignment.
    pub fn aligned_axes(&self) -> Result<Vec<String>, StoreError> {
        let what = "read the alignments";
        let mut stmt = self
            .conn
            .prepare("SELECT DISTINCT axis FROM alignments ORDER BY axis")
            .map_err(|e| self.fail(what, e))?;
        let rows = stmt
            .query_map([], |r| r.get::<_, String>(0))
            .map_err(|e| self.fail(what, e))?;
        rows.collect::<Result<Vec<_>, _>>()
            .map_err(|e| self.fail(what, e))
    }
}
